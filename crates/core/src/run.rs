//! One entry point for every method: a [`MethodRun`] says which integrator, with which τ, δ and
//! protocol, and [`run_orbit`] dispatches to the tangent-map, DOP853 or Taylor driver.

use crate::adaptive::{
    integrate_adaptive_watched, Abandoned, Dop853Orbit, Protocol, TaylorOrbit, Unwatched, Watch,
};
use crate::batch::BatchFeed;
use crate::dd::DoubleDouble;
use crate::dop853::{Dop853, Dop853Config};
use crate::lanes::{integrate_feed_scalar, integrate_feed_taylor, TaylorSetup, TAYLOR_LANES};
use crate::method::Method;
use crate::orbit::{initial_vectors, integrate, OrbitConfig, OrbitResult, Requests};
use crate::tangent::{Phase, TangentMap};
use crate::taylor::{Taylor, TaylorSeries};

/// A method with its settings.
#[derive(Clone, Debug, PartialEq)]
pub struct MethodRun {
    pub method: Method,
    /// The tolerance in force (adaptive methods; `None` for tangent-map methods).
    pub delta: Option<f64>,
    /// Protocol of the adaptive methods.
    pub protocol: Protocol,
}

impl MethodRun {
    /// The Taylor order, DOP853's 8 or the splitting scheme's order.
    pub fn order(&self) -> u32 {
        match &self.method {
            Method::TangentMap(s) => s.order,
            Method::Dop853 => 8,
            Method::Taylor | Method::TaylorDd => {
                crate::taylor::order_for(self.delta.expect("adaptive methods carry a tolerance"))
                    as u32
            }
        }
    }
}

/// Integrates the orbit from (q, p) — a point of the energy surface `energy` — with `K`
/// deviation vectors. `taylor-dd` recomputes p[0] from the energy in double-double so that it
/// starts on the energy surface to its own precision.
pub fn run_orbit<H: TaylorSeries<N>, const N: usize, const K: usize>(
    ham: &H,
    run: &MethodRun,
    energy: f64,
    q: [f64; N],
    p: [f64; N],
    config: &OrbitConfig,
    requests: &Requests,
) -> OrbitResult<N> {
    if let Method::TangentMap(scheme) = &run.method {
        let map = TangentMap::new(ham, scheme, config.tau);
        return integrate::<H, N, K>(&map, q, p, config, requests);
    }
    run_adaptive::<H, N, K>(ham, run, energy, q, p, config, requests, &mut Unwatched)
        .expect("an unwatched orbit is never abandoned")
}

/// [`run_orbit`] for the adaptive methods, under a [`Watch`] that sees the crossings as they
/// are found and may abandon the orbit. Tangent-map orbits go through
/// [`integrate`](crate::orbit::integrate) or the batched driver instead.
#[allow(clippy::too_many_arguments)]
pub fn run_adaptive<H: TaylorSeries<N>, const N: usize, const K: usize>(
    ham: &H,
    run: &MethodRun,
    energy: f64,
    q: [f64; N],
    p: [f64; N],
    config: &OrbitConfig,
    requests: &Requests,
    watch: &mut impl Watch<N>,
) -> Result<OrbitResult<N>, Abandoned> {
    let (dq, dp) = initial_vectors::<N, K>(config.deviation);
    let delta = || run.delta.expect("adaptive methods carry a tolerance");
    match &run.method {
        Method::TangentMap(_) => panic!("run_adaptive is for adaptive methods"),
        Method::Dop853 => {
            let y = Phase { q, p, dq, dp };
            let mut integ = Dop853Orbit::new(
                ham,
                Dop853::new(ham, Dop853Config::with_delta(delta()), 0.0, y),
            );
            integrate_adaptive_watched(ham, &mut integ, run.protocol, config, requests, watch)
        }
        Method::Taylor => {
            let y = Phase { q, p, dq, dp };
            let mut integ = TaylorOrbit::new(ham, Taylor::new(ham, delta(), 0.0, y));
            integrate_adaptive_watched(ham, &mut integ, run.protocol, config, requests, watch)
        }
        Method::TaylorDd => {
            let y = dd_start(ham, energy, q, p, (dq, dp));
            let mut integ = TaylorOrbit::new(ham, Taylor::new(ham, delta(), 0.0, y));
            integrate_adaptive_watched(ham, &mut integ, run.protocol, config, requests, watch)
        }
    }
}

/// How many orbits one thread of [`integrate_feed_adaptive`] integrates at once with the
/// adaptive `method` (schedulers size their work by it).
pub fn adaptive_orbits_per_thread(method: &Method) -> usize {
    match method {
        Method::TaylorDd => TAYLOR_LANES,
        _ => 1,
    }
}

/// Integrates the orbits `feed` supplies with an adaptive method, each as [`run_adaptive`]
/// would under a watch that passes its crossings to the feed and lets the feed abandon it, and
/// hands each result to the feed as its orbit ends: `taylor-dd` [`adaptive_orbits_per_thread`]
/// orbits at a time in SIMD lanes ([`crate::lanes`], the same bits), DOP853 and f64 Taylor one
/// at a time.
pub fn integrate_feed_adaptive<H: TaylorSeries<N>, const N: usize, const K: usize>(
    ham: &H,
    run: &MethodRun,
    energy: f64,
    config: &OrbitConfig,
    requests: &Requests,
    feed: &mut impl BatchFeed<N>,
) {
    match &run.method {
        Method::TangentMap(_) => panic!("integrate_feed_adaptive is for adaptive methods"),
        // One orbit at a time: DOP853 rejects steps lane by lane, and an f64 Taylor step is
        // cheap enough that the orbits lanes put in flight cost more than the lanes save
        // (400×400, τ = 0.5, t = 1e4, 2 threads: 3.7 s one at a time, 4.4 s in 4 lanes).
        Method::Dop853 | Method::Taylor => integrate_feed_scalar(feed, |q, p, watch| {
            run_adaptive::<H, N, K>(ham, run, energy, q, p, config, requests, watch)
        }),
        Method::TaylorDd => {
            let setup = TaylorSetup {
                ham,
                delta: run.delta.expect("adaptive methods carry a tolerance"),
                protocol: run.protocol,
                config,
                requests,
            };
            let vectors = initial_vectors::<N, K>(config.deviation);
            integrate_feed_taylor::<H, DoubleDouble, N, K>(
                &setup,
                |q, p| dd_start(ham, energy, q, p, vectors),
                feed,
            )
        }
    }
}

/// The initial state of a `taylor-dd` orbit: the deviation vectors and q as given, p with
/// [`dd_momenta`].
fn dd_start<H: TaylorSeries<N>, const N: usize, const K: usize>(
    ham: &H,
    energy: f64,
    q: [f64; N],
    p: [f64; N],
    (dq, dp): ([[f64; N]; K], [[f64; N]; K]),
) -> Phase<DoubleDouble, N, K> {
    Phase {
        q: q.map(DoubleDouble::from_f64),
        p: dd_momenta(ham, energy, q, p),
        dq: dq.map(|v| v.map(DoubleDouble::from_f64)),
        dp: dp.map(|v| v.map(DoubleDouble::from_f64)),
    }
}

/// The momenta with p[0] = √(2(E − V(q)) − Σ_{i≥1} p_i²) evaluated in double-double.
fn dd_momenta<H: TaylorSeries<N>, const N: usize>(
    ham: &H,
    energy: f64,
    q: [f64; N],
    p: [f64; N],
) -> [DoubleDouble; N] {
    let qd = q.map(DoubleDouble::from_f64);
    let mut pd = p.map(DoubleDouble::from_f64);
    let two = DoubleDouble::from_f64(2.0);
    let mut radicand = (DoubleDouble::from_f64(energy) - ham.potential(&qd)) * two;
    for x in &pd[1..] {
        radicand -= *x * *x;
    }
    pd[0] = radicand.sqrt();
    pd
}
