//! The one-orbit driver: integrate an orbit with its deviation vectors to t_final (or an early
//! stop), computing SALI every τ and only what the caller asked for besides.

use crate::arith::real::dot;
use crate::indicators::{
    gali, may_be_aligned, norm2, pow2_rescale, sali, GrowthHistory, GrowthIndicators, LogGrowth,
};
use crate::phase::Phase;
use crate::section::{locate_upward, Crossing, CrossingStep};
use crate::systems::hamiltonian::Hamiltonian;
use crate::tangent_map::map::{EdgeIncrement, Stepping, TangentMap};
use rand_chacha::rand_core::{RngCore, SeedableRng};
use serde::{Deserialize, Serialize};

/// How an orbit ended.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Status {
    /// Reached t_final.
    Ok,
    /// SALI fell below the chaotic threshold before t_final.
    ChaoticEarlyStop,
    /// Left the escape radius (possible above the escape energy).
    Escaped,
    /// A NaN or infinity appeared in the orbit or a deviation vector.
    NonFinite,
    /// An adaptive method could not keep its step above the smallest allowed.
    StepLimit,
    /// |ΔH/H| exceeded the configured limit: the integration is not to be trusted (a
    /// splitting step beyond its stability limit, a tolerance far too loose).
    EnergyDrift,
}

impl Status {
    /// Every status, in the order of their declaration.
    pub const ALL: [Status; 6] = [
        Status::Ok,
        Status::ChaoticEarlyStop,
        Status::Escaped,
        Status::NonFinite,
        Status::StepLimit,
        Status::EnergyDrift,
    ];

    /// The status's kebab-case name, as serialised.
    pub fn as_str(self) -> &'static str {
        match self {
            Status::Ok => "ok",
            Status::ChaoticEarlyStop => "chaotic-early-stop",
            Status::Escaped => "escaped",
            Status::NonFinite => "non-finite",
            Status::StepLimit => "step-limit",
            Status::EnergyDrift => "energy-drift",
        }
    }
}

/// The class an orbit's final SALI puts it in.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Class {
    /// SALI at or above the regular threshold.
    Regular,
    /// SALI between the chaotic and the regular thresholds.
    Sticky,
    /// SALI below the chaotic threshold.
    Chaotic,
}

impl Class {
    /// Every class, from regular to chaotic.
    pub const ALL: [Class; 3] = [Class::Regular, Class::Sticky, Class::Chaotic];

    /// The class's kebab-case name, as serialised.
    pub fn as_str(self) -> &'static str {
        match self {
            Class::Regular => "regular",
            Class::Sticky => "sticky",
            Class::Chaotic => "chaotic",
        }
    }
}

/// SALI thresholds (the seed paper's: regular ≥ 1e-4, chaotic < 1e-8) and the early stop.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Thresholds {
    /// SALI at or above this is regular.
    pub regular: f64,
    /// SALI below this is chaotic; between the two, sticky.
    pub chaotic: f64,
    /// Stop as soon as SALI < `chaotic` (the paper's convention).
    pub early_stop: bool,
    /// An orbit whose |ΔH/H| exceeds this stops with status `energy-drift` and no class
    /// (infinity: never).
    #[serde(default = "default_energy_drift")]
    pub energy_drift: f64,
}

fn default_energy_drift() -> f64 {
    ENERGY_DRIFT_DEFAULT
}

/// Default limit on |ΔH/H| before an orbit is declared `energy-drift`.
pub const ENERGY_DRIFT_DEFAULT: f64 = 1e-2;

/// The tangent-map driver checks the energy every this many steps (and at the last): a
/// splitting step beyond its stability limit blows the energy up within a few steps, and a
/// check every step would be a visible share of the step's cost (figures: docs/performance.md).
pub const ENERGY_CHECK_EVERY: u64 = 16;

impl Default for Thresholds {
    fn default() -> Self {
        Thresholds {
            regular: 1e-4,
            chaotic: 1e-8,
            early_stop: true,
            energy_drift: ENERGY_DRIFT_DEFAULT,
        }
    }
}

impl Thresholds {
    /// The class of an orbit whose final SALI is `sali`.
    pub fn classify(&self, sali: f64) -> Class {
        if sali >= self.regular {
            Class::Regular
        } else if sali >= self.chaotic {
            Class::Sticky
        } else {
            Class::Chaotic
        }
    }
}

/// Initial deviation vectors.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Deviation {
    /// The k-th vector is the k-th axis of (δq1..δqN, δp1..δpN).
    Axes,
    /// Unit vectors with components drawn uniformly from [−1, 1) by ChaCha8 from `seed`.
    Random {
        /// Seed of the ChaCha8 generator.
        seed: u64,
    },
}

/// What to integrate.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OrbitConfig {
    /// Renormalisation (and SALI sampling) interval τ.
    pub tau: f64,
    /// Time to integrate to.
    pub t_final: f64,
    /// Classification thresholds and the early stop.
    pub thresholds: Thresholds,
    /// How the initial deviation vectors are chosen.
    pub deviation: Deviation,
    /// Overrides the Hamiltonian's escape radius.
    pub escape_radius: Option<f64>,
}

impl OrbitConfig {
    /// A configuration with default thresholds, axis deviation vectors and the Hamiltonian's escape
    /// radius.
    pub fn new(tau: f64, t_final: f64) -> Self {
        OrbitConfig {
            tau,
            t_final,
            thresholds: Thresholds::default(),
            deviation: Deviation::Axes,
            escape_radius: None,
        }
    }
}

/// What to compute besides the final SALI and mLE; nothing else is computed.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Requests {
    /// Record the upward crossings of q1 = 0.
    pub crossings: bool,
    /// GALI_2..GALI_K at the end (and at samples).
    pub gali: bool,
    /// Track max |ΔH/H| every step.
    pub energy: bool,
    /// Record indicators at this many log-spaced times per decade of t (0: none).
    pub samples_per_decade: u32,
    /// MEGNO and the FLI ([`GrowthIndicators`]) from ln‖w₁‖ at every step (tangent maps) or
    /// step end (adaptive methods).
    pub growth: bool,
}

impl Requests {
    /// Whether the bookkeeping runs after every step (the batched driver's screens and quiet
    /// windows skip steps where nothing of the orbit's outcome can change).
    pub fn every_step(&self) -> bool {
        self.energy || self.growth
    }
}

/// Indicators at one time.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Sample {
    /// Time of the sample.
    pub t: f64,
    /// SALI of the first two deviation vectors.
    pub sali: f64,
    /// GALI_2..GALI_K (empty unless requested).
    pub gali: Vec<f64>,
    /// Finite-time maximal Lyapunov exponent (1/t) ln‖w1(t)‖.
    pub mle: f64,
    /// |ΔH/H| at `t`.
    pub energy_error: f64,
    /// MEGNO and the FLI (when requested; with the free protocol, at the end of the step that
    /// holds `t`).
    pub growth: Option<GrowthIndicators>,
}

/// What an orbit integration produced.
#[derive(Clone, Debug, PartialEq)]
pub struct OrbitResult<const N: usize> {
    /// How the orbit ended.
    pub status: Status,
    /// None for escaped and non-finite orbits.
    pub class: Option<Class>,
    /// The time reached: t_final, or when the orbit stopped.
    pub t_reached: f64,
    /// Integration steps taken.
    pub steps: u64,
    /// SALI at t_reached (NaN for orbits without a class).
    pub sali: f64,
    /// GALI_2..GALI_K at t_reached (empty unless requested).
    pub gali: Vec<f64>,
    /// Finite-time maximal Lyapunov exponent (1/t) ln‖w1(t)‖.
    pub mle: f64,
    /// MEGNO and the FLI at t_reached (when requested; `None` for orbits without a class).
    pub growth: Option<GrowthIndicators>,
    /// max |ΔH/H| over the steps (when requested).
    pub energy_error_max: Option<f64>,
    /// Upward crossings of q1 = 0 (when requested).
    pub crossings: Vec<Crossing<N>>,
    /// Indicators at log-spaced times (when requested).
    pub series: Vec<Sample>,
    /// The orbit's phase-space point at `t_reached`.
    pub q_end: [f64; N],
    /// The orbit's momenta at `t_reached`.
    pub p_end: [f64; N],
}

impl<const N: usize> OrbitResult<N> {
    /// A result with nothing computed: NaN indicators and end point, no steps.
    pub fn empty() -> Self {
        OrbitResult {
            q_end: [f64::NAN; N],
            p_end: [f64::NAN; N],
            status: Status::Ok,
            class: None,
            t_reached: 0.0,
            steps: 0,
            sali: f64::NAN,
            gali: Vec::new(),
            mle: f64::NAN,
            growth: None,
            energy_error_max: None,
            crossings: Vec::new(),
            series: Vec::new(),
        }
    }
}

/// Number of steps τ that reach t_final (t_final itself when it is a multiple of τ).
pub fn steps_to(t_final: f64, tau: f64) -> u64 {
    let r = t_final / tau;
    let nearest = r.round();
    if (r - nearest).abs() <= 1e-9 * nearest.max(1.0) {
        nearest as u64
    } else {
        r.ceil() as u64
    }
}

/// The initial deviation vectors, unit length.
pub fn initial_vectors<const N: usize, const K: usize>(
    deviation: Deviation,
) -> ([[f64; N]; K], [[f64; N]; K]) {
    assert!(K <= 2 * N, "at most 2N = {} deviation vectors", 2 * N);
    let mut dq = [[0.0; N]; K];
    let mut dp = [[0.0; N]; K];
    match deviation {
        Deviation::Axes => {
            for k in 0..K {
                if k < N {
                    dq[k][k] = 1.0;
                } else {
                    dp[k][k - N] = 1.0;
                }
            }
        }
        Deviation::Random { seed } => {
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
            let mut uniform = || (rng.next_u64() >> 11) as f64 * (2.0 / (1u64 << 53) as f64) - 1.0;
            for k in 0..K {
                for i in 0..N {
                    dq[k][i] = uniform();
                    dp[k][i] = uniform();
                }
                let s = 1.0 / norm2(&dq[k], &dp[k]).sqrt();
                for i in 0..N {
                    dq[k][i] *= s;
                    dp[k][i] *= s;
                }
            }
        }
    }
    (dq, dp)
}

/// Steps at which samples are recorded: ~`per_decade` log-spaced per decade, and the last.
pub fn sample_steps(per_decade: u32, n_final: u64) -> Vec<u64> {
    let mut v = Vec::new();
    if per_decade == 0 {
        return v;
    }
    let mut j = 0u32;
    loop {
        let n = 10f64.powf(j as f64 / per_decade as f64).round() as u64;
        if n >= n_final {
            break;
        }
        if v.last() != Some(&n) {
            v.push(n);
        }
        j += 1;
    }
    v.push(n_final);
    v
}

/// Integrates the orbit starting at (`q0`, `p0`) with `K` deviation vectors (2 ≤ K ≤ 2N; SALI
/// uses the first two) by the tangent-map method `map`.
pub fn integrate<H: Hamiltonian<N>, const N: usize, const K: usize>(
    map: &TangentMap<'_, H>,
    q0: [f64; N],
    p0: [f64; N],
    config: &OrbitConfig,
    requests: &Requests,
) -> OrbitResult<N> {
    let mut out = OrbitResult::empty();
    integrate_into::<H, N, K>(map, q0, p0, config, requests, &mut out);
    out
}

/// [`integrate`] into a caller-owned result, reusing its buffers.
pub fn integrate_into<H: Hamiltonian<N>, const N: usize, const K: usize>(
    map: &TangentMap<'_, H>,
    q0: [f64; N],
    p0: [f64; N],
    config: &OrbitConfig,
    requests: &Requests,
    out: &mut OrbitResult<N>,
) {
    let (dq, dp) = initial_vectors::<N, K>(config.deviation);
    let mut stepping = Stepping::new(
        map,
        Phase {
            q: q0,
            p: p0,
            dq,
            dp,
        },
    );
    let mut tracker = Tracker::new(map, &stepping.x, config, requests);
    tracker.begin(out);
    let mut n = 0u64;
    while n < tracker.n_final {
        let (q_prev, p_prev) = (stepping.x.q, stepping.x.p);
        stepping.advance();
        n += 1;
        let (x, inc) = stepping.parts_mut();
        if tracker.after_step(map, n, &q_prev, &p_prev, x, inc, out, None) {
            break;
        }
    }
    tracker.finish(n, &stepping.x, out);
}

/// The squared escape radius in force for `config`.
pub(crate) fn escape_radius2<H: Hamiltonian<N>, const N: usize>(
    ham: &H,
    config: &OrbitConfig,
) -> f64 {
    let radius = config.escape_radius.unwrap_or_else(|| ham.escape_radius());
    radius * radius
}

/// Per-orbit bookkeeping after every step: escape and finiteness checks, power-of-two
/// rescaling, crossings, energy, the early stop and samples. Shared by the scalar driver and
/// the batched one, so both make the same decisions on the same bits.
pub(crate) struct Tracker<'h, H, const K: usize> {
    ham: &'h H,
    tau: f64,
    pub(crate) n_final: u64,
    pub(crate) r2_max: f64,
    /// [`Hamiltonian::way_out_r2`]: beyond it the energy is checked at every step and a drift
    /// past the limit does not stop the orbit.
    pub(crate) well_r2: f64,
    pub(crate) thresholds: Thresholds,
    pub(crate) requests: Requests,
    h0: f64,
    h_scale: f64,
    samples: Vec<u64>,
    next_sample: usize,
    growth: [LogGrowth; K],
    history: GrowthHistory,
    energy_max: f64,
    status: Status,
}

impl<'h, H, const K: usize> Tracker<'h, H, K> {
    pub(crate) fn new<const N: usize>(
        map: &TangentMap<'h, H>,
        x0: &Phase<f64, N, K>,
        config: &OrbitConfig,
        requests: &Requests,
    ) -> Self
    where
        H: Hamiltonian<N>,
    {
        assert!(K >= 2, "SALI needs two deviation vectors");
        let ham = map.hamiltonian();
        let tau = map.tau();
        let n_final = steps_to(config.t_final, tau);
        let h0 = ham.energy(&x0.q, &x0.p);
        Tracker {
            ham,
            tau,
            n_final,
            r2_max: escape_radius2(ham, config),
            well_r2: ham.way_out_r2(h0, escape_radius2(ham, config).sqrt()),
            thresholds: config.thresholds,
            requests: *requests,
            h0,
            h_scale: if h0.abs() > 1e-300 { h0.abs() } else { 1.0 },
            samples: sample_steps(requests.samples_per_decade, n_final),
            next_sample: 0,
            growth: [LogGrowth::default(); K],
            history: GrowthHistory::NEW,
            energy_max: 0.0,
            status: Status::Ok,
        }
    }

    pub(crate) fn begin<const N: usize>(&mut self, out: &mut OrbitResult<N>) {
        out.crossings.clear();
        out.series.clear();
    }

    /// Bookkeeping on the synchronised state `x` after step `n`, which started at
    /// (`q_prev`, `p_prev`). Rescales deviation vectors (and the pending increment `inc`) in
    /// place. Returns true when the orbit stops here. With `defer_crossing`, a crossing in this
    /// step is not located but flagged there, for the caller to locate with
    /// [`locate_upward`] (or its lane-wise twin) and append to `out.crossings`.
    #[allow(clippy::too_many_arguments)]
    #[inline]
    pub(crate) fn after_step<const N: usize>(
        &mut self,
        map: &TangentMap<'_, H>,
        n: u64,
        q_prev: &[f64; N],
        p_prev: &[f64; N],
        x: &mut Phase<f64, N, K>,
        inc: &mut EdgeIncrement<f64, N, K>,
        out: &mut OrbitResult<N>,
        defer_crossing: Option<&mut bool>,
    ) -> bool
    where
        H: Hamiltonian<N>,
    {
        // A non-finite p shows up in q one drift later; `!(a <= b)` also catches NaN.
        let r2 = dot(&x.q, &x.q);
        #[allow(clippy::neg_cmp_op_on_partial_ord)]
        if !(r2 <= self.r2_max) {
            let e = self.energy_error(x);
            self.energy_max = self.energy_max.max(e);
            // Above the escape energy a drift past the limit inside the well stopped the orbit
            // there, and one beyond it is the orbit's way out (its error is in `energy_max`);
            // below it, an orbit that gained that much energy blew up, nothing escaped.
            self.status = if !r2.is_finite() {
                Status::NonFinite
            } else if self.well_r2.is_infinite() && !(e <= self.thresholds.energy_drift) {
                Status::EnergyDrift
            } else {
                Status::Escaped
            };
            return true;
        }
        let mut n2 = [0.0; K];
        for k in 0..K {
            n2[k] = norm2(&x.dq[k], &x.dp[k]);
            if let Some((s, e)) = pow2_rescale(n2[k]) {
                if !(n2[k].is_finite() && n2[k] > 0.0) {
                    self.status = Status::NonFinite;
                    return true;
                }
                for i in 0..N {
                    x.dq[k][i] *= s;
                    x.dp[k][i] *= s;
                    inc.dev[k][i] *= s;
                }
                self.growth[k].binary_orders += e;
                n2[k] *= s * s;
            }
        }
        if self.requests.growth {
            let t = n as f64 * self.tau;
            self.history.note(t, self.growth[0].ln_norm(n2[0]));
        }
        if self.requests.crossings && q_prev[0] < 0.0 && x.q[0] >= 0.0 {
            match defer_crossing {
                // The batched driver locates several lanes' crossings together.
                Some(deferred) => *deferred = true,
                None => {
                    let step = CrossingStep {
                        q: *q_prev,
                        p: *p_prev,
                        t: (n - 1) as f64 * self.tau,
                        q1_end: x.q[0],
                    };
                    out.crossings.push(locate_upward(map, &step));
                }
            }
        }
        let th = self.thresholds;
        let in_well = r2 <= self.well_r2;
        if self.requests.energy
            || n.is_multiple_of(ENERGY_CHECK_EVERY)
            || n == self.n_final
            || !in_well
        {
            let e = self.energy_error(x);
            self.energy_max = self.energy_max.max(e);
            #[allow(clippy::neg_cmp_op_on_partial_ord)]
            if e.is_nan() || (!(e <= th.energy_drift) && in_well) {
                self.status = if e.is_nan() {
                    Status::NonFinite
                } else {
                    Status::EnergyDrift
                };
                return true;
            }
        }
        if th.early_stop {
            let c = dot(&x.dq[0], &x.dq[1]) + dot(&x.dp[0], &x.dp[1]);
            if may_be_aligned(n2[0], n2[1], c, th.chaotic)
                && sali((&x.dq[0], &x.dp[0]), (&x.dq[1], &x.dp[1])) < th.chaotic
            {
                self.status = Status::ChaoticEarlyStop;
            }
        }
        if self.next_sample < self.samples.len() && self.samples[self.next_sample] == n {
            self.next_sample += 1;
            out.series.push(self.sample(x, n as f64 * self.tau));
        }
        self.status != Status::Ok
    }

    /// The step at which the next time-series sample is due (`u64::MAX`: none).
    pub(crate) fn next_sample_step(&self) -> u64 {
        self.samples
            .get(self.next_sample)
            .copied()
            .unwrap_or(u64::MAX)
    }

    /// Fills `out` from the final state after `n` steps.
    pub(crate) fn finish<const N: usize>(
        &mut self,
        n: u64,
        x: &Phase<f64, N, K>,
        out: &mut OrbitResult<N>,
    ) where
        H: Hamiltonian<N>,
    {
        let t = n as f64 * self.tau;
        out.status = self.status;
        out.t_reached = t;
        out.q_end = x.q;
        out.p_end = x.p;
        out.steps = n;
        out.energy_error_max = self.requests.energy.then_some(self.energy_max);
        if matches!(self.status, Status::Ok | Status::ChaoticEarlyStop) {
            out.sali = sali((&x.dq[0], &x.dp[0]), (&x.dq[1], &x.dp[1]));
            out.mle = mle(&self.growth[0], x, t);
            out.growth = self.requests.growth.then(|| self.history.values());
            out.gali = if self.requests.gali {
                gali(&x.dq, &x.dp)
            } else {
                Vec::new()
            };
            out.class = Some(if self.status == Status::ChaoticEarlyStop {
                Class::Chaotic
            } else {
                self.thresholds.classify(out.sali)
            });
            if self.next_sample < self.samples.len() && n > 0 {
                out.series.push(self.sample(x, t));
            }
        } else {
            out.sali = f64::NAN;
            out.mle = f64::NAN;
            out.growth = None;
            out.gali.clear();
            out.class = None;
        }
    }

    fn energy_error<const N: usize>(&self, x: &Phase<f64, N, K>) -> f64
    where
        H: Hamiltonian<N>,
    {
        (self.ham.energy(&x.q, &x.p) - self.h0).abs() / self.h_scale
    }

    fn sample<const N: usize>(&self, x: &Phase<f64, N, K>, t: f64) -> Sample
    where
        H: Hamiltonian<N>,
    {
        Sample {
            t,
            sali: sali((&x.dq[0], &x.dp[0]), (&x.dq[1], &x.dp[1])),
            gali: if self.requests.gali {
                gali(&x.dq, &x.dp)
            } else {
                Vec::new()
            },
            mle: mle(&self.growth[0], x, t),
            energy_error: self.energy_error(x),
            growth: self.requests.growth.then(|| self.history.values()),
        }
    }
}

fn mle<const N: usize, const K: usize>(g: &LogGrowth, x: &Phase<f64, N, K>, t: f64) -> f64 {
    if t > 0.0 {
        g.ln_norm(norm2(&x.dq[0], &x.dp[0])) / t
    } else {
        0.0
    }
}
