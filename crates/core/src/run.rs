//! One entry point for every method: a [`MethodRun`] says which integrator, with which τ, δ and
//! protocol, and [`run_orbit`] dispatches to the tangent-map, DOP853 or Taylor driver.

use crate::adaptive::dop853::{Dop853, Dop853Config};
use crate::adaptive::driver::{
    integrate_adaptive_watched, Abandoned, Dop853Orbit, Protocol, TaylorOrbit, Unwatched, Watch,
};
use crate::adaptive::lanes::{
    integrate_feed_dop853_on, integrate_feed_scalar, integrate_feed_taylor_on, LaneSetup, SimdOf,
    FEWER_LANES_ABOVE_T_FINAL, LANES, LONG_RUN_LANES,
};
use crate::adaptive::taylor::Taylor;
use crate::arith::dd::DoubleDouble;
use crate::method::{LanePolicy, Method, F64_TAYLOR_LANES_BELOW_TAU};
use crate::orbit::{initial_vectors, integrate, OrbitConfig, OrbitResult, Requests};
use crate::phase::Phase;
use crate::systems::polynomial::PolynomialSystem;
use crate::systems::series::TaylorSeries;
use crate::tangent_map::batch::{integrate_feed_on, BatchFeed, IcsFeed, Isa};
use crate::tangent_map::map::TangentMap;
use crate::{Hamiltonian, HenonHeiles};

/// A method with its settings.
#[derive(Clone, Debug, PartialEq)]
pub struct MethodRun {
    /// The method.
    pub method: Method,
    /// The tolerance in force (adaptive methods; `None` for tangent-map methods).
    pub delta: Option<f64>,
    /// Protocol of the adaptive methods.
    pub protocol: Protocol,
}

impl MethodRun {
    /// The Taylor order, DOP853's 8 or the splitting scheme's order ([`Method::order`]).
    pub fn order(&self) -> u32 {
        self.method.order(self.delta)
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
    if let Ok(result) = run_orbit_on_derivatives::<H, N, K>(ham, run, (q, p), config, requests) {
        return result;
    }
    // Through a `dyn Watch`: the watched orbits of the grid's feeds share this copy.
    let mut unwatched: &mut dyn Watch<N> = &mut Unwatched;
    run_adaptive::<H, N, K>(ham, run, energy, q, p, config, requests, &mut unwatched)
        .expect("an unwatched orbit is never abandoned")
}

/// [`run_orbit`] on a system known only by its derivatives (a [`Hamiltonian`] without a Taylor
/// recursion): the tangent-map methods and DOP853 need nothing more; the Taylor methods are
/// refused with the reason.
pub fn run_orbit_on_derivatives<H: Hamiltonian<N>, const N: usize, const K: usize>(
    ham: &H,
    run: &MethodRun,
    (q, p): ([f64; N], [f64; N]),
    config: &OrbitConfig,
    requests: &Requests,
) -> Result<OrbitResult<N>, String> {
    match &run.method {
        Method::TangentMap(scheme) => {
            let map = TangentMap::new(ham, scheme, config.tau);
            Ok(integrate::<H, N, K>(&map, q, p, config, requests))
        }
        Method::Dop853 => {
            let mut unwatched: &mut dyn Watch<N> = &mut Unwatched;
            let result = run_dop853::<H, N, K>(ham, run, (q, p), config, requests, &mut unwatched);
            Ok(result.expect("an unwatched orbit is never abandoned"))
        }
        Method::Taylor | Method::TaylorDd => Err(format!(
            "{} needs the system's Taylor recursion (TaylorSeries); {} has none",
            run.method.name(),
            ham.name()
        )),
    }
}

/// The deviation vectors a single orbit carries.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Vectors {
    /// Two: SALI and GALI_2.
    Two,
    /// 2N, one per phase-space dimension: GALI_3 … GALI_2N as well.
    All,
}

/// [`run_orbit`] on Hénon–Heiles. The single-orbit commands (`salient orbit`, `salient
/// precision`) and the tests call this rather than instantiating the integrators themselves:
/// compiled here once, with the grid's drivers.
pub fn run_henon_heiles(
    run: &MethodRun,
    energy: f64,
    (q, p): ([f64; 2], [f64; 2]),
    config: &OrbitConfig,
    requests: &Requests,
    vectors: Vectors,
) -> OrbitResult<2> {
    let ham = &HenonHeiles;
    match vectors {
        Vectors::Two => run_orbit::<_, 2, 2>(ham, run, energy, q, p, config, requests),
        Vectors::All => run_orbit::<_, 2, 4>(ham, run, energy, q, p, config, requests),
    }
}

/// The degrees of freedom polynomial systems are compiled for: the plane and space systems,
/// and a chain of 8 for single orbits (each size adds about 20 s to the build of this crate).
pub const POLYNOMIAL_DOFS: [usize; 3] = [2, 3, 8];

/// [`run_orbit`] on a polynomial system, compiled here once for each of [`POLYNOMIAL_DOFS`]
/// (see [`run_henon_heiles`]).
pub trait PolynomialRun<const N: usize> {
    /// Integrates the orbit from (q, p) with `vectors` deviation vectors.
    fn run(
        &self,
        run: &MethodRun,
        energy: f64,
        start: ([f64; N], [f64; N]),
        config: &OrbitConfig,
        requests: &Requests,
        vectors: Vectors,
    ) -> OrbitResult<N>;
}

/// The implementation of [`PolynomialRun`] for N degrees of freedom, with all 2N vectors as
/// `all` (a constant: the driver's vector count is a type parameter).
macro_rules! polynomial_run {
    ($($n:literal => $all:literal),*) => {$(
        impl PolynomialRun<$n> for PolynomialSystem<$n> {
            fn run(
                &self,
                run: &MethodRun,
                energy: f64,
                (q, p): ([f64; $n], [f64; $n]),
                config: &OrbitConfig,
                requests: &Requests,
                vectors: Vectors,
            ) -> OrbitResult<$n> {
                match vectors {
                    Vectors::Two => {
                        run_orbit::<_, $n, 2>(self, run, energy, q, p, config, requests)
                    }
                    Vectors::All => {
                        run_orbit::<_, $n, $all>(self, run, energy, q, p, config, requests)
                    }
                }
            }
        }
    )*};
}

polynomial_run!(2 => 4, 3 => 6, 8 => 16);

/// [`run_adaptive`] on Hénon–Heiles, compiled here once (see [`run_henon_heiles`]).
#[allow(clippy::too_many_arguments)]
pub fn run_adaptive_henon_heiles(
    run: &MethodRun,
    energy: f64,
    (q, p): ([f64; 2], [f64; 2]),
    config: &OrbitConfig,
    requests: &Requests,
    vectors: Vectors,
    mut watch: &mut dyn Watch<2>,
) -> Result<OrbitResult<2>, Abandoned> {
    let ham = &HenonHeiles;
    let watch = &mut watch;
    match vectors {
        Vectors::Two => run_adaptive::<_, 2, 2>(ham, run, energy, q, p, config, requests, watch),
        Vectors::All => run_adaptive::<_, 2, 4>(ham, run, energy, q, p, config, requests, watch),
    }
}

/// The batched tangent-map driver ([`integrate_feed_on`]) on Hénon–Heiles in `lanes` (4 or 8)
/// SIMD lanes on `isa`, with two deviation vectors. The grid's executor and the tests call
/// this copy, compiled here once, rather than instantiating the driver themselves: each copy
/// of the driver is a large share of a crate's build.
pub fn integrate_feed_henon_heiles(
    isa: Isa,
    lanes: usize,
    map: &TangentMap<'_, HenonHeiles>,
    config: &OrbitConfig,
    requests: &Requests,
    mut feed: &mut dyn BatchFeed<2>,
) {
    match lanes {
        4 => integrate_feed_on::<_, 2, 2, 4>(isa, map, config, requests, &mut feed),
        8 => integrate_feed_on::<_, 2, 2, 8>(isa, map, config, requests, &mut feed),
        _ => panic!("the batched driver runs 4 or 8 lanes, not {lanes}"),
    }
}

/// [`integrate_feed_henon_heiles`] on the orbits from `ics`, each result handed to `sink` with
/// its index in `ics`.
#[allow(clippy::too_many_arguments)]
pub fn integrate_batch_henon_heiles(
    isa: Isa,
    lanes: usize,
    map: &TangentMap<'_, HenonHeiles>,
    ics: &[([f64; 2], [f64; 2])],
    config: &OrbitConfig,
    requests: &Requests,
    sink: &mut dyn FnMut(usize, OrbitResult<2>),
) {
    let mut feed = IcsFeed::new(ics, sink);
    integrate_feed_henon_heiles(isa, lanes, map, config, requests, &mut feed)
}

/// [`integrate_feed_adaptive`] on Hénon–Heiles with two deviation vectors, compiled here once
/// (see [`integrate_feed_henon_heiles`]).
pub fn integrate_feed_adaptive_henon_heiles(
    run: &MethodRun,
    energy: f64,
    config: &OrbitConfig,
    requests: &Requests,
    guided: bool,
    mut feed: &mut dyn BatchFeed<2>,
) {
    integrate_feed_adaptive::<_, 2, 2>(
        &HenonHeiles,
        run,
        energy,
        config,
        requests,
        guided,
        &mut feed,
    )
}

/// The grid's two drivers on one system with two deviation vectors — the batched tangent-map
/// driver and the adaptive methods' — compiled here once per system: Hénon–Heiles, and the
/// polynomial systems of 2 and 3 degrees of freedom (grids run in those; chains only as
/// single orbits). The grid's executor is generic over this trait and matches once over the
/// systems it knows.
pub trait FeedDrivers<const N: usize>: TaylorSeries<N> + Sized {
    /// [`integrate_feed_on`] in `lanes` (4 or 8) SIMD lanes on `isa`.
    fn integrate_feed(
        isa: Isa,
        lanes: usize,
        map: &TangentMap<'_, Self>,
        config: &OrbitConfig,
        requests: &Requests,
        feed: &mut dyn BatchFeed<N>,
    );
    /// [`integrate_feed_adaptive`] on this system.
    fn integrate_feed_adaptive(
        &self,
        run: &MethodRun,
        energy: f64,
        config: &OrbitConfig,
        requests: &Requests,
        guided: bool,
        feed: &mut dyn BatchFeed<N>,
    );

    /// The grid's driver for `run` on this system: the batched tangent map in `lanes` (4 or 8)
    /// lanes, or [`Self::integrate_feed_adaptive`] for an adaptive method.
    #[allow(clippy::too_many_arguments)]
    fn integrate_feed_run(
        &self,
        run: &MethodRun,
        energy: f64,
        config: &OrbitConfig,
        requests: &Requests,
        (lanes, guided): (usize, bool),
        feed: &mut dyn BatchFeed<N>,
    ) {
        match &run.method {
            Method::TangentMap(scheme) => {
                let map = TangentMap::new(self, scheme, config.tau);
                Self::integrate_feed(Isa::detect(), lanes, &map, config, requests, feed)
            }
            _ => self.integrate_feed_adaptive(run, energy, config, requests, guided, feed),
        }
    }
}

impl FeedDrivers<2> for HenonHeiles {
    fn integrate_feed(
        isa: Isa,
        lanes: usize,
        map: &TangentMap<'_, Self>,
        config: &OrbitConfig,
        requests: &Requests,
        feed: &mut dyn BatchFeed<2>,
    ) {
        integrate_feed_henon_heiles(isa, lanes, map, config, requests, feed)
    }
    fn integrate_feed_adaptive(
        &self,
        run: &MethodRun,
        energy: f64,
        config: &OrbitConfig,
        requests: &Requests,
        guided: bool,
        feed: &mut dyn BatchFeed<2>,
    ) {
        integrate_feed_adaptive_henon_heiles(run, energy, config, requests, guided, feed)
    }
}

/// [`FeedDrivers`] for the polynomial systems of the listed sizes.
macro_rules! polynomial_feed_drivers {
    ($($n:literal),*) => {$(
        impl FeedDrivers<$n> for PolynomialSystem<$n> {
            fn integrate_feed(
                isa: Isa,
                lanes: usize,
                map: &TangentMap<'_, Self>,
                config: &OrbitConfig,
                requests: &Requests,
                mut feed: &mut dyn BatchFeed<$n>,
            ) {
                match lanes {
                    4 => integrate_feed_on::<_, $n, 2, 4>(isa, map, config, requests, &mut feed),
                    8 => integrate_feed_on::<_, $n, 2, 8>(isa, map, config, requests, &mut feed),
                    _ => panic!("the batched driver runs 4 or 8 lanes, not {lanes}"),
                }
            }
            fn integrate_feed_adaptive(
                &self,
                run: &MethodRun,
                energy: f64,
                config: &OrbitConfig,
                requests: &Requests,
                guided: bool,
                mut feed: &mut dyn BatchFeed<$n>,
            ) {
                integrate_feed_adaptive::<_, $n, 2>(
                    self, run, energy, config, requests, guided, &mut feed,
                )
            }
        }
    )*};
}

/// The sizes grids run in ([`FeedDrivers`]).
pub const GRID_DOFS: [usize; 2] = [2, 3];

polynomial_feed_drivers!(2, 3);

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
        Method::Dop853 => run_dop853::<H, N, K>(ham, run, (q, p), config, requests, watch),
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

/// The DOP853 branch of [`run_adaptive`], which needs only the Hamiltonian's derivatives.
fn run_dop853<H: Hamiltonian<N>, const N: usize, const K: usize>(
    ham: &H,
    run: &MethodRun,
    (q, p): ([f64; N], [f64; N]),
    config: &OrbitConfig,
    requests: &Requests,
    watch: &mut impl Watch<N>,
) -> Result<OrbitResult<N>, Abandoned> {
    let (dq, dp) = initial_vectors::<N, K>(config.deviation);
    let delta = run.delta.expect("adaptive methods carry a tolerance");
    let y = Phase { q, p, dq, dp };
    let mut integ = Dop853Orbit::new(
        ham,
        Dop853::new(ham, Dop853Config::with_delta(delta), 0.0, y),
    );
    integrate_adaptive_watched(ham, &mut integ, run.protocol, config, requests, watch)
}

/// How many orbits one thread of [`integrate_feed_adaptive`] integrates at once with the
/// adaptive `method` at renormalisation interval `tau` up to `t_final` (schedulers size their
/// work by it).
pub fn adaptive_orbits_per_thread(method: &Method, tau: f64, t_final: f64) -> usize {
    let in_lanes = match method.info().lanes {
        LanePolicy::Adaptive {
            lanes_below_tau, ..
        } => tau < lanes_below_tau,
        LanePolicy::Batched => false,
    };
    // Long runs at large τ (natural steps, where a lane's step saves least) take fewer lanes.
    let long = tau >= F64_TAYLOR_LANES_BELOW_TAU && t_final > FEWER_LANES_ABOVE_T_FINAL;
    match (in_lanes, long) {
        (false, _) => 1,
        (true, false) => LANES,
        (true, true) => LONG_RUN_LANES,
    }
}

/// DOP853's lanes per batch where a forecast guides the feed (`guided` in
/// [`integrate_feed_adaptive`]) and the host has AVX-512: one register per number. Its steps
/// cost less per orbit in 8 lanes than in 4, but without a forecast the fast-PSS rule drops
/// far more of the steps of 8 lanes in flight than of 4: with a forecast (say TM-SBAB2C's
/// labellers, earlier in a sweep) 8 lanes are faster, alone 4 are (figures:
/// docs/performance.md). f64 Taylor and taylor-dd step no cheaper per orbit in 8 lanes.
pub const GUIDED_DOP853_LANES: usize = 8;

/// The orbits one thread of [`integrate_feed_adaptive`] integrates at once: as
/// [`adaptive_orbits_per_thread`], but a method registered `wider_when_guided` (DOP853,
/// [`LanePolicy`]) takes [`GUIDED_DOP853_LANES`] when `guided` and
/// the host runs that many lanes in one register ([`Isa::lanes`]).
pub fn feed_orbits_per_thread(method: &Method, tau: f64, t_final: f64, guided: bool) -> usize {
    match adaptive_orbits_per_thread(method, tau, t_final) {
        LANES
            if guided
                && matches!(
                    method.info().lanes,
                    LanePolicy::Adaptive {
                        wider_when_guided: true,
                        ..
                    }
                )
                && Isa::detect().lanes() == GUIDED_DOP853_LANES =>
        {
            GUIDED_DOP853_LANES
        }
        n => n,
    }
}

/// Integrates the orbits `feed` supplies with an adaptive method, each as [`run_adaptive`]
/// would under a watch that passes its crossings to the feed and lets the feed abandon it, and
/// hands each result to the feed as its orbit ends: [`feed_orbits_per_thread`] orbits at a
/// time in SIMD lanes ([`crate::adaptive::lanes`], the same bits) where that is more than one, else
/// one at a time. `guided`: the feed orders its cells by a forecast, which keeps the orbits in
/// flight from being overtaken, so DOP853 may take wider batches.
pub fn integrate_feed_adaptive<H: TaylorSeries<N>, const N: usize, const K: usize>(
    ham: &H,
    run: &MethodRun,
    energy: f64,
    config: &OrbitConfig,
    requests: &Requests,
    guided: bool,
    feed: &mut impl BatchFeed<N>,
) {
    let setup = LaneSetup {
        ham,
        delta: run.delta.expect("adaptive methods carry a tolerance"),
        protocol: run.protocol,
        config,
        requests,
    };
    match feed_orbits_per_thread(&run.method, config.tau, config.t_final, guided) {
        // Only DOP853 takes this width: the Taylor methods are not compiled for it.
        GUIDED_DOP853_LANES => {
            let (dq, dp) = initial_vectors::<N, K>(config.deviation);
            let start = |q, p| Phase { q, p, dq, dp };
            integrate_feed_dop853_on::<H, N, K, GUIDED_DOP853_LANES>(
                Isa::detect(),
                &setup,
                start,
                feed,
            )
        }
        LANES => in_lanes::<H, N, K, LANES>(&setup, run, energy, feed),
        LONG_RUN_LANES => in_lanes::<H, N, K, LONG_RUN_LANES>(&setup, run, energy, feed),
        // One orbit at a time: at large τ a step is cheap enough beside the work of a crossing
        // that the orbits lanes put in flight cost more than the lanes save.
        // The watch goes as a `dyn Watch`, so that this shares `run_orbit`'s copy.
        _ => integrate_feed_scalar(feed, |q, p, watch| {
            let mut watch: &mut dyn Watch<N> = watch;
            run_adaptive::<H, N, K>(ham, run, energy, q, p, config, requests, &mut watch)
        }),
    }
}

/// [`integrate_feed_adaptive`] in `L` lanes.
fn in_lanes<H: TaylorSeries<N>, const N: usize, const K: usize, const L: usize>(
    setup: &LaneSetup<'_, H>,
    run: &MethodRun,
    energy: f64,
    feed: &mut impl BatchFeed<N>,
) where
    f64: SimdOf<L>,
    DoubleDouble: SimdOf<L>,
{
    let isa = Isa::detect();
    let (dq, dp) = initial_vectors::<N, K>(setup.config.deviation);
    let start = |q, p| Phase { q, p, dq, dp };
    match &run.method {
        // f64 Taylor's four lanes fill one AVX2 register per number; compiled for AVX-512 the
        // compiler packs two numbers into one register and shuffles them apart, which is
        // slower than the pinned copy (figures: docs/performance.md). DOP853's stages and
        // taylor-dd's double-double sums gain from AVX-512's 32 registers.
        Method::Taylor => {
            integrate_feed_taylor_on::<H, f64, N, K, L>(Isa::Pinned, setup, start, feed)
        }
        Method::Dop853 => integrate_feed_dop853_on::<H, N, K, L>(isa, setup, start, feed),
        Method::TaylorDd => integrate_feed_taylor_on::<H, DoubleDouble, N, K, L>(
            isa,
            setup,
            |q, p| dd_start(setup.ham, energy, q, p, (dq, dp)),
            feed,
        ),
        Method::TangentMap(_) => panic!("integrate_feed_adaptive is for adaptive methods"),
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
