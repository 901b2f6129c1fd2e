//! The batched stepper: `L` orbits advanced in lockstep, one per SIMD lane.
//!
//! A single orbit is a chain of dependent operations and leaves most of a core idle; `L`
//! independent orbits in structure-of-arrays form fill the vector units. The step is the same
//! generic code as the scalar one (on [`Lanes<L>`]), and the per-step checks run vectorised on
//! the fast path; only lanes where something happens (a crossing, a rescaling, a possible early
//! stop, the end) drop to the scalar [`Tracker`](crate::orbit) that the one-orbit driver uses.
//! Every lane therefore produces bit for bit the result of [`integrate`](crate::orbit::integrate)
//! for its orbit. A lane whose orbit ends is refilled with the next initial condition at once.

use crate::hamiltonian::Hamiltonian;
use crate::indicators::{alignment_factor, in_band};
use crate::orbit::{
    escape_radius2, initial_vectors, integrate, steps_to, OrbitConfig, OrbitResult, Requests,
    Tracker,
};
use crate::real::{dot, Lanes};
use crate::tangent::{EdgeIncrement, Phase, TangentMap};

fn get_lane<const N: usize, const K: usize, const L: usize>(
    x: &Phase<Lanes<L>, N, K>,
    inc: &EdgeIncrement<Lanes<L>, N, K>,
    l: usize,
) -> (Phase<f64, N, K>, EdgeIncrement<f64, N, K>) {
    let v = |a: &[Lanes<L>; N]| -> [f64; N] { core::array::from_fn(|i| a[i].0[l]) };
    (
        Phase {
            q: v(&x.q),
            p: v(&x.p),
            dq: core::array::from_fn(|k| v(&x.dq[k])),
            dp: core::array::from_fn(|k| v(&x.dp[k])),
        },
        EdgeIncrement {
            orbit: v(&inc.orbit),
            dev: core::array::from_fn(|k| v(&inc.dev[k])),
        },
    )
}

fn set_lane<const N: usize, const K: usize, const L: usize>(
    x: &mut Phase<Lanes<L>, N, K>,
    inc: &mut EdgeIncrement<Lanes<L>, N, K>,
    l: usize,
    sx: &Phase<f64, N, K>,
    sinc: &EdgeIncrement<f64, N, K>,
) {
    for i in 0..N {
        x.q[i].0[l] = sx.q[i];
        x.p[i].0[l] = sx.p[i];
        inc.orbit[i].0[l] = sinc.orbit[i];
        for k in 0..K {
            x.dq[k][i].0[l] = sx.dq[k][i];
            x.dp[k][i].0[l] = sx.dp[k][i];
            inc.dev[k][i].0[l] = sinc.dev[k][i];
        }
    }
}

struct Job<'h, H, const N: usize, const K: usize> {
    index: usize,
    tracker: Tracker<'h, H, K>,
    result: OrbitResult<N>,
}

/// Integrates every initial condition of `ics` as [`integrate`](crate::orbit::integrate) would,
/// `L` at a time in SIMD lanes, and hands each result to `sink` with its index as soon as it
/// is done (so in completion order, not input order). Time series are not supported here
/// (`requests.samples_per_decade` must be 0): use the one-orbit driver for them.
pub fn integrate_batch<H: Hamiltonian<N>, const N: usize, const K: usize, const L: usize>(
    map: &TangentMap<'_, H>,
    ics: &[([f64; N], [f64; N])],
    config: &OrbitConfig,
    requests: &Requests,
    sink: impl FnMut(usize, OrbitResult<N>),
) {
    integrate_batch_with::<H, N, K, L>(map, ics, config, requests, &NoHooks, sink)
}

/// Lets a caller watch crossings as they are found and abandon orbits whose results it no
/// longer needs (the fast-PSS engine abandons orbits whose cell is certain to be labelled by
/// another). Hooks never change the results of the orbits that complete.
pub trait BatchHooks<const N: usize>: Sync {
    /// Called for every upward crossing of orbit `ic` when it is located.
    fn on_crossing(&self, _ic: usize, _crossing: &crate::section::Crossing<N>) {}
    /// Polled every [`CANCEL_POLL`] steps: true abandons orbit `ic` (no result is reported).
    fn cancelled(&self, _ic: usize) -> bool {
        false
    }
    /// Called when orbit `ic` is abandoned after `steps` steps.
    fn abandoned(&self, _ic: usize, _steps: u64) {}
}

/// No hooks.
pub struct NoHooks;
impl<const N: usize> BatchHooks<N> for NoHooks {}

/// Steps between polls of [`BatchHooks::cancelled`].
pub const CANCEL_POLL: u64 = 64;

/// [`integrate_batch`] with hooks; abandoned orbits are not handed to `sink`.
pub fn integrate_batch_with<H: Hamiltonian<N>, const N: usize, const K: usize, const L: usize>(
    map: &TangentMap<'_, H>,
    ics: &[([f64; N], [f64; N])],
    config: &OrbitConfig,
    requests: &Requests,
    hooks: &dyn BatchHooks<N>,
    mut sink: impl FnMut(usize, OrbitResult<N>),
) {
    assert_eq!(
        requests.samples_per_decade, 0,
        "the batched driver records no time series"
    );
    if steps_to(config.t_final, map.tau()) == 0 {
        for (i, &(q, p)) in ics.iter().enumerate() {
            sink(i, integrate::<H, N, K>(map, q, p, config, requests));
        }
        return;
    }
    let (dq0, dp0) = initial_vectors::<N, K>(config.deviation);
    let mut x: Phase<Lanes<L>, N, K> = Phase::zero();
    let mut inc = map.edge_increment(&x);
    let mut jobs: [Option<Job<'_, H, N, K>>; L] = core::array::from_fn(|_| None);
    let mut next = 0usize;
    let every_step = requests.energy;

    let load = |l: usize,
                next: &mut usize,
                x: &mut Phase<Lanes<L>, N, K>,
                inc: &mut EdgeIncrement<Lanes<L>, N, K>|
     -> Option<Job<'_, H, N, K>> {
        let (sx, job) = if *next < ics.len() {
            let (q, p) = ics[*next];
            let sx = Phase {
                q,
                p,
                dq: dq0,
                dp: dp0,
            };
            let mut result = OrbitResult::empty();
            let mut tracker = Tracker::new(map, &sx, config, requests);
            tracker.begin(&mut result);
            let job = Job {
                index: *next,
                tracker,
                result,
            };
            *next += 1;
            (sx, Some(job))
        } else {
            (Phase::zero(), None)
        };
        set_lane(x, inc, l, &sx, &map.edge_increment(&sx));
        job
    };

    for (l, job) in jobs.iter_mut().enumerate() {
        *job = load(l, &mut next, &mut x, &mut inc);
    }
    let r2_max = escape_radius2(map.hamiltonian(), config);
    let factor = alignment_factor(config.thresholds.chaotic);
    let n_final = steps_to(config.t_final, map.tau());
    let (crossings, early) = (requests.crossings, config.thresholds.early_stop);
    // Steps done per lane; an idle lane (no orbit left to load) holds zeros and is never flagged.
    let mut n = [0u64; L];
    let mut active: [bool; L] = core::array::from_fn(|l| jobs[l].is_some());

    while active.iter().any(|&a| a) {
        let (q_prev, p_prev) = (x.q, x.p);
        map.advance(&mut x, &mut inc);

        // Vectorised screening: which lanes need the scalar bookkeeping this step? Every
        // condition under which `Tracker::after_step` acts must raise the flag.
        let r2 = dot(&x.q, &x.q);
        let n2: [Lanes<L>; K] =
            core::array::from_fn(|k| dot(&x.dq[k], &x.dq[k]) + dot(&x.dp[k], &x.dp[k]));
        let c = dot(&x.dq[0], &x.dq[1]) + dot(&x.dp[0], &x.dp[1]);
        let mut flagged = [false; L];
        // `!(a <= b)` is true for NaN too, which is the point.
        #[allow(clippy::neg_cmp_op_on_partial_ord)]
        for l in 0..L {
            n[l] += 1;
            let mut f = every_step | (n[l] >= n_final) | !(r2.0[l] <= r2_max);
            for n2k in &n2 {
                f |= !in_band(n2k.0[l]);
            }
            f |= crossings & (q_prev[0].0[l] < 0.0) & (x.q[0].0[l] >= 0.0);
            f |= early & (c.0[l] * c.0[l] >= n2[0].0[l] * n2[1].0[l] * factor);
            flagged[l] = f & active[l];
        }
        if n[0] % CANCEL_POLL == 0 {
            for l in 0..L {
                if let Some(j) = jobs[l].as_ref().filter(|j| hooks.cancelled(j.index)) {
                    hooks.abandoned(j.index, n[l]);
                    jobs[l] = load(l, &mut next, &mut x, &mut inc);
                    active[l] = jobs[l].is_some();
                    flagged[l] = false;
                    n[l] = 0;
                }
            }
        }
        for l in (0..L).filter(|&l| flagged[l]) {
            let job = jobs[l].as_mut().expect("flagged lanes are active");
            let crossings_before = job.result.crossings.len();
            let (mut sx, mut sinc) = get_lane(&x, &inc, l);
            let qp: [f64; N] = core::array::from_fn(|i| q_prev[i].0[l]);
            let pp: [f64; N] = core::array::from_fn(|i| p_prev[i].0[l]);
            let stop =
                job.tracker
                    .after_step(map, n[l], &qp, &pp, &mut sx, &mut sinc, &mut job.result);
            for c in &job.result.crossings[crossings_before..] {
                hooks.on_crossing(job.index, c);
            }
            if stop || n[l] == n_final {
                let mut j = jobs[l].take().expect("active");
                j.tracker.finish(n[l], &sx, &mut j.result);
                sink(j.index, j.result);
                jobs[l] = load(l, &mut next, &mut x, &mut inc);
                active[l] = jobs[l].is_some();
                n[l] = 0;
            } else {
                set_lane(&mut x, &mut inc, l, &sx, &sinc);
            }
        }
    }
}
