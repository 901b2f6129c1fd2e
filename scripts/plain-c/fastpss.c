/* A plain single-threaded C implementation of the fast-PSS rule (docs/methods.md) for
 * Hénon–Heiles with the TM-SBAB2C tangent map: the yardstick the speed targets of
 * docs/performance.md are stated against. It exists to
 * calibrate a host: `salient run` is compared with it side by side on the same machine
 * (scripts/bench-plain-c.sh), so a figure measured on one host can be read on another.
 *
 * Deliberately plain: one orbit at a time, one step at a time, no SIMD, no speculation, no
 * merging of a step's last kick with the next step's first. It is also an independent second
 * implementation of the rule, so its percentages must agree with salient's to well within the
 * noise of floating-point differences.
 *
 * Usage: fastpss TAU T_FINAL [N]     (N×N cells, default 400, visited in a raster scan: the
 *        grid's default canonical order, i along q2 outer, j along p2 inner)
 * Prints one line of JSON: percentages, orbits integrated, orbit-steps, seconds.
 */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#define ENERGY 0.125
#define Q2_LO (-0.43969262078590838)
#define Q2_HI 0.67364817766693035
#define P2_LO (-0.5)
#define P2_HI 0.5
#define SALI_REGULAR 1e-4
#define SALI_CHAOTIC 1e-8
/* SBAB2 (Laskar & Robutel 2001): B(τ/6) A(τ/2) B(2τ/3) A(τ/2) B(τ/6); corrector g = 1/72 at
 * both ends, p += (g/2)τ³ ∇K with K = |∇V|² (symplectic-sali.md). */
#define G_SBAB2 (1.0 / 72.0)

typedef struct {
    double q[2], p[2];
    double dq[2][2], dp[2][2]; /* two deviation vectors */
} State;

static double potential(double x, double y) {
    return 0.5 * (x * x + y * y) + x * x * y - y * y * y / 3.0;
}

/* p ← p − b ∇V + c ∇K, and the same linearised on the deviation vectors. */
static void kick(State *s, double b, double c, int tangent) {
    double x = s->q[0], y = s->q[1];
    double v1 = x + 2.0 * x * y, v2 = y + x * x - y * y;
    double h11 = 1.0 + 2.0 * y, h12 = 2.0 * x, h22 = 1.0 - 2.0 * y;
    /* ∇K = 2 H ∇V; Hess K = 2 (H² + V1 Hess V1 + V2 Hess V2) */
    double k1 = 2.0 * (h11 * v1 + h12 * v2), k2 = 2.0 * (h12 * v1 + h22 * v2);
    s->p[0] += -b * v1 + c * k1;
    s->p[1] += -b * v2 + c * k2;
    if (!tangent)
        return;
    double m11 = 2.0 * (h11 * h11 + h12 * h12 + 2.0 * v2);
    double m12 = 2.0 * (h11 * h12 + h12 * h22 + 2.0 * v1);
    double m22 = 2.0 * (h12 * h12 + h22 * h22 - 2.0 * v2);
    double a11 = -b * h11 + c * m11, a12 = -b * h12 + c * m12, a22 = -b * h22 + c * m22;
    for (int k = 0; k < 2; k++) {
        double d0 = s->dq[k][0], d1 = s->dq[k][1];
        s->dp[k][0] += a11 * d0 + a12 * d1;
        s->dp[k][1] += a12 * d0 + a22 * d1;
    }
}

static void drift(State *s, double a, int tangent) {
    s->q[0] += a * s->p[0];
    s->q[1] += a * s->p[1];
    if (!tangent)
        return;
    for (int k = 0; k < 2; k++) {
        s->dq[k][0] += a * s->dp[k][0];
        s->dq[k][1] += a * s->dp[k][1];
    }
}

static void sbab2c(State *s, double h, int tangent) {
    double c = 0.5 * G_SBAB2 * h * h * h;
    kick(s, h / 6.0, c, tangent);
    drift(s, 0.5 * h, tangent);
    kick(s, 2.0 * h / 3.0, 0.0, tangent);
    drift(s, 0.5 * h, tangent);
    kick(s, h / 6.0, c, tangent);
}

/* Normalises both deviation vectors and returns SALI = min(|v1 + v2|, |v1 − v2|). */
static double renormalise_sali(State *s) {
    for (int k = 0; k < 2; k++) {
        double n = sqrt(s->dq[k][0] * s->dq[k][0] + s->dq[k][1] * s->dq[k][1] +
                        s->dp[k][0] * s->dp[k][0] + s->dp[k][1] * s->dp[k][1]);
        s->dq[k][0] /= n, s->dq[k][1] /= n, s->dp[k][0] /= n, s->dp[k][1] /= n;
    }
    double plus = 0.0, minus = 0.0;
    for (int i = 0; i < 2; i++) {
        double a = s->dq[0][i] + s->dq[1][i], b = s->dq[0][i] - s->dq[1][i];
        double c = s->dp[0][i] + s->dp[1][i], d = s->dp[0][i] - s->dp[1][i];
        plus += a * a + c * c;
        minus += b * b + d * d;
    }
    return sqrt(plus < minus ? plus : minus);
}

/* The crossing inside a step that starts at `s0` with q1 < 0 and ends with q1 ≥ 0: Newton on
 * the step size h of a partial step of the same scheme (dq1/dh ≈ p1), kept in a bisection
 * bracket. Writes (q2, p2) at the crossing. */
static void locate(const State *s0, double tau, double *q2, double *p2) {
    double lo = 0.0, hi = tau, h = -s0->q[0] / s0->p[0];
    if (!(h > lo && h < hi))
        h = 0.5 * tau;
    State s;
    for (int it = 0; it < 100; it++) {
        s = *s0;
        sbab2c(&s, h, 0);
        double g = s.q[0];
        if (fabs(g) <= 4.0 * 2.220446049250313e-16)
            break;
        if (g < 0.0)
            lo = h;
        else
            hi = h;
        double next = h - g / s.p[0];
        if (!(s.p[0] > 0.0 && next > lo && next < hi))
            next = 0.5 * (lo + hi);
        double done = fabs(next - h) <= 4.0 * 2.220446049250313e-16 * tau;
        h = next;
        if (done || hi - lo <= 4.0 * 2.220446049250313e-16 * hi) {
            s = *s0;
            sbab2c(&s, h, 0);
            break;
        }
    }
    *q2 = s.q[1];
    *p2 = s.p[1];
}

static double radicand(double q2, double p2) {
    return 2.0 * (ENERGY - potential(0.0, q2)) - p2 * p2;
}

int main(int argc, char **argv) {
    if (argc < 3) {
        fprintf(stderr, "usage: %s TAU T_FINAL [N]\n", argv[0]);
        return 2;
    }
    double tau = atof(argv[1]), t_final = atof(argv[2]);
    int n = argc > 3 ? atoi(argv[3]) : 400;
    if (!(tau > 0.0) || !(t_final >= tau) || n <= 0) {
        fprintf(stderr, "bad arguments\n");
        return 2;
    }
    long steps_per_orbit = lround(t_final / tau);
    double dq = (Q2_HI - Q2_LO) / n, dp = (P2_HI - P2_LO) / n;
    /* label: 0 unlabelled, 1 regular, 2 sticky, 3 chaotic; -1 incompatible */
    signed char *label = malloc((size_t)n * n);
    int *crossed = malloc(sizeof(int) * (size_t)(steps_per_orbit + 1));
    long compatible = 0;
    for (int i = 0; i < n; i++)
        for (int j = 0; j < n; j++) {
            int ok = radicand(Q2_LO + (i + 0.5) * dq, P2_LO + (j + 0.5) * dp) > 0.0;
            label[i * n + j] = ok ? 0 : -1;
            compatible += ok;
        }

    struct timespec t0, t1;
    clock_gettime(CLOCK_MONOTONIC, &t0);
    long orbits = 0, orbit_steps = 0, counts[4] = {0, 0, 0, 0};
    for (int i = 0; i < n; i++)
        for (int j = 0; j < n; j++) {
            int cell = i * n + j;
            if (label[cell] != 0)
                continue;
            double q2 = Q2_LO + (i + 0.5) * dq, p2 = P2_LO + (j + 0.5) * dp;
            State s = {{0.0, q2}, {sqrt(radicand(q2, p2)), p2},
                       {{1.0, 0.0}, {0.0, 1.0}}, {{0.0, 0.0}, {0.0, 0.0}}};
            double sali = sqrt(2.0);
            int n_crossed = 0;
            long k;
            for (k = 0; k < steps_per_orbit; k++) {
                State before = s;
                sbab2c(&s, tau, 1);
                if (before.q[0] < 0.0 && s.q[0] >= 0.0) {
                    double cq2, cp2;
                    locate(&before, tau, &cq2, &cp2);
                    double fi = floor((cq2 - Q2_LO) / dq), fj = floor((cp2 - P2_LO) / dp);
                    if (fi >= 0.0 && fj >= 0.0 && fi < n && fj < n)
                        crossed[n_crossed++] = (int)fi * n + (int)fj;
                }
                sali = renormalise_sali(&s);
                if (sali < SALI_CHAOTIC) {
                    k++;
                    break;
                }
            }
            orbits++;
            orbit_steps += k;
            int cls = sali >= SALI_REGULAR ? 1 : sali >= SALI_CHAOTIC ? 2 : 3;
            label[cell] = cls;
            counts[cls]++;
            for (int c = 0; c < n_crossed; c++)
                if (label[crossed[c]] == 0) {
                    label[crossed[c]] = cls;
                    counts[cls]++;
                }
        }
    clock_gettime(CLOCK_MONOTONIC, &t1);
    double secs = (t1.tv_sec - t0.tv_sec) + 1e-9 * (t1.tv_nsec - t0.tv_nsec);
    printf("{\"tau\":%g,\"t_final\":%g,\"cells\":%d,\"compatible\":%ld,"
           "\"percent\":{\"regular\":%.2f,\"sticky\":%.2f,\"chaotic\":%.2f},"
           "\"orbits_integrated\":%ld,\"orbit_steps\":%ld,\"wall_s\":%.3f}\n",
           tau, t_final, n, compatible, 100.0 * counts[1] / compatible,
           100.0 * counts[2] / compatible, 100.0 * counts[3] / compatible, orbits, orbit_steps,
           secs);
    free(label);
    free(crossed);
    return 0;
}
