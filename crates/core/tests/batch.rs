//! The batched stepper gives, lane by lane, exactly the bits of the one-orbit driver.

#![allow(clippy::needless_range_loop, clippy::excessive_precision)]

//!
//! The drivers are called through the copies salient-core compiles for Hénon–Heiles (the
//! `*_henon_heiles` entry points the grid runs): the tests check what ships, and this binary
//! does not compile the drivers again.

use salient_core::indicators::GrowthIndicators;
use salient_core::orbit::{OrbitConfig, OrbitResult, Requests, Status};
use salient_core::run::{integrate_batch_henon_heiles, run_henon_heiles, MethodRun, Vectors};
use salient_core::section::on_section;
use salient_core::tangent_map::batch::Isa;
use salient_core::{HenonHeiles, Method, Scheme, TangentMap};

fn growth_bits(g: Option<GrowthIndicators>) -> Option<[u64; 3]> {
    g.map(|g| [g.megno, g.megno_mean, g.fli].map(f64::to_bits))
}

fn same_bits(a: &OrbitResult<2>, b: &OrbitResult<2>) -> bool {
    let f = |x: f64| x.to_bits();
    a.status == b.status
        && a.class == b.class
        && a.steps == b.steps
        && f(a.t_reached) == f(b.t_reached)
        && a.q_end.iter().chain(&a.p_end).map(|&x| f(x)).eq(b
            .q_end
            .iter()
            .chain(&b.p_end)
            .map(|&x| f(x)))
        && f(a.sali) == f(b.sali)
        && f(a.mle) == f(b.mle)
        && growth_bits(a.growth) == growth_bits(b.growth)
        && a.gali
            .iter()
            .map(|&x| f(x))
            .eq(b.gali.iter().map(|&x| f(x)))
        && a.energy_error_max.map(f) == b.energy_error_max.map(f)
        && a.series.len() == b.series.len()
        && a.series.iter().zip(&b.series).all(|(x, y)| {
            [x.t, x.sali, x.mle, x.energy_error].map(f)
                == [y.t, y.sali, y.mle, y.energy_error].map(f)
                && growth_bits(x.growth) == growth_bits(y.growth)
                && x.gali
                    .iter()
                    .map(|&g| f(g))
                    .eq(y.gali.iter().map(|&g| f(g)))
        })
        && a.crossings.len() == b.crossings.len()
        && a.crossings.iter().zip(&b.crossings).all(|(c, d)| {
            f(c.t) == f(d.t)
                && c.q
                    .iter()
                    .chain(&c.p)
                    .zip(d.q.iter().chain(&d.p))
                    .all(|(x, y)| f(*x) == f(*y))
        })
}

/// A spread of section points: regular, chaotic, and (at a second energy) escaping orbits.
fn ics() -> Vec<([f64; 2], [f64; 2])> {
    let mut v = Vec::new();
    for i in 0..9 {
        for j in 0..5 {
            let (q2, p2) = (-0.42 + 0.13 * i as f64, -0.45 + 0.22 * j as f64);
            if let Ok(x) = on_section(&HenonHeiles, 0.125, &[q2], &[p2]) {
                v.push(x);
            }
            if let Ok(x) = on_section(&HenonHeiles, 0.2, &[q2], &[p2]) {
                v.push(x);
            }
        }
    }
    v
}

fn check<const L: usize>(
    scheme: &str,
    tau: f64,
    t_final: f64,
    requests: Requests,
) -> std::collections::HashSet<Status> {
    check_config::<L>(scheme, &OrbitConfig::new(tau, t_final), requests)
}

fn check_config<const L: usize>(
    scheme: &str,
    cfg: &OrbitConfig,
    requests: Requests,
) -> std::collections::HashSet<Status> {
    check_on::<L>(scheme, cfg, requests, &ics())
}

/// [`check_config`] on the section points `ics`.
fn check_on<const L: usize>(
    scheme: &str,
    cfg: &OrbitConfig,
    requests: Requests,
    ics: &[([f64; 2], [f64; 2])],
) -> std::collections::HashSet<Status> {
    let ham = HenonHeiles;
    let scheme = Scheme::by_name(scheme).unwrap();
    let map = TangentMap::new(&ham, &scheme, cfg.tau);
    let cfg = *cfg;
    let mut got: Vec<Option<OrbitResult<2>>> = vec![None; ics.len()];
    let isa = Isa::detect();
    integrate_batch_henon_heiles(isa, L, &map, ics, &cfg, &requests, &mut |i, r| {
        assert!(got[i].is_none(), "orbit {i} reported twice");
        got[i] = Some(r);
    });
    let mut statuses = std::collections::HashSet::new();
    for (i, &(q, p)) in ics.iter().enumerate() {
        let want = scalar(&scheme, (q, p), &cfg, &requests);
        let have = got[i].as_ref().expect("every orbit reported");
        assert!(
            same_bits(have, &want),
            "{} L={L} orbit {i}:\n batch  {have:?}\n scalar {want:?}",
            scheme.name
        );
        statuses.insert(want.status);
    }
    statuses
}

/// The one-orbit tangent-map driver's result.
fn scalar(
    scheme: &Scheme,
    start: ([f64; 2], [f64; 2]),
    cfg: &OrbitConfig,
    requests: &Requests,
) -> OrbitResult<2> {
    let run = MethodRun {
        method: Method::TangentMap(scheme.clone()),
        delta: None,
        protocol: Default::default(),
    };
    // The energy only matters to taylor-dd.
    run_henon_heiles(&run, f64::NAN, start, cfg, requests, Vectors::Two)
}

/// [`check`], asserting that the sample covers the interesting paths: full runs, early stops
/// and escapes.
fn check_varied<const L: usize>(scheme: &str, tau: f64, t_final: f64, requests: Requests) {
    let statuses = check::<L>(scheme, tau, t_final, requests);
    if t_final > 0.0 {
        assert!(statuses.len() >= 2, "{statuses:?}");
    }
    if t_final >= 1000.0 {
        assert!(statuses.len() >= 3, "{statuses:?}");
    }
}

#[test]
fn batched_lanes_equal_scalar_orbits_bit_for_bit() {
    check_varied::<4>("sbab2c", 0.5, 0.0, Requests::default());
    let crossings = Requests {
        crossings: true,
        ..Requests::default()
    };
    check_varied::<4>("sbab2c", 0.05, 1500.0, crossings);
    check_varied::<8>("sbab2c", 0.5, 3000.0, crossings);
    check_varied::<4>("saba2c", 0.1, 1000.0, Requests::default());
    check_varied::<8>(
        "srkn14a",
        0.25,
        1000.0,
        Requests {
            energy: true,
            gali: true,
            ..crossings
        },
    );
    // More lanes than orbits, and orbits that end before their first step.
    let few = &ics()[..5];
    check_on::<8>("sbab2c", &OrbitConfig::new(0.5, 200.0), crossings, few);
    check_on::<8>("sbab2c", &OrbitConfig::new(0.5, 0.0), crossings, few);
    // Time series (full-mode checkpoints): the same samples at the same steps.
    let series = Requests {
        samples_per_decade: 10,
        gali: true,
        ..Requests::default()
    };
    check_varied::<4>("sbab2c", 0.5, 1500.0, series);
    check_varied::<8>("saba2c", 0.1, 1000.0, series);
    // MEGNO and the FLI: the tracker at every step, in every lane.
    let growth = Requests {
        growth: true,
        samples_per_decade: 5,
        ..crossings
    };
    check_varied::<4>("sbab2c", 0.05, 1500.0, growth);
    check_varied::<8>("sbab2c", 0.5, 1500.0, growth);
}

/// The 4-lane driver's quiet windows (SBAB2C at small τ: 14 steps at τ = 0.01, 2 at 0.05)
/// change no bit: the same results as the scalar driver with early stops, escapes (energy
/// 0.2: orbits leave the windows' radius first) and new orbits coming into lanes mid-window,
/// and with the early stop off, where chaotic orbits' vectors grow through the rescaling
/// band. (The margins themselves are far from what real orbits reach in a window; the bound
/// they rest on is tested along orbits in `tangent_map/map.rs`.)
#[test]
fn quiet_windows_keep_the_scalar_bits() {
    let crossings = Requests {
        crossings: true,
        ..Requests::default()
    };
    for (tau, t_final) in [(0.01, 600.0), (0.05, 3000.0)] {
        let early = check_config::<4>("sbab2c", &OrbitConfig::new(tau, t_final), crossings);
        assert!(early.contains(&Status::ChaoticEarlyStop), "{early:?}");
        assert!(early.contains(&Status::Escaped), "{early:?}");
        let mut cfg = OrbitConfig::new(tau, 5.0 * t_final);
        cfg.thresholds.early_stop = false;
        let late = check_config::<4>("sbab2c", &cfg, crossings);
        assert!(!late.contains(&Status::ChaoticEarlyStop), "{late:?}");
    }
}

/// The copy of the driver compiled for AVX-512 gives the pinned copy's bits (on hosts that
/// have AVX-512; elsewhere there is nothing to compare and the test says so).
#[test]
fn the_avx512_driver_equals_the_pinned_one_bit_for_bit() {
    if !Isa::Avx512.available() {
        // Straight to stderr: the test harness shows it even when the test passes.
        let _ = std::io::Write::write_all(
            &mut std::io::stderr(),
            b"skipped: the_avx512_driver_equals_the_pinned_one_bit_for_bit: this host has no AVX-512\n",
        );
        return;
    }
    let ham = HenonHeiles;
    let ics = ics();
    let requests = Requests {
        crossings: true,
        samples_per_decade: 5,
        gali: true,
        ..Requests::default()
    };
    for (scheme, tau) in [("sbab2c", 0.05), ("saba2c", 0.5), ("srkn14a", 0.25)] {
        let map = TangentMap::new(&ham, &Scheme::by_name(scheme).unwrap(), tau);
        let cfg = OrbitConfig::new(tau, 2000.0);
        let run = |isa, lanes| {
            let mut got = vec![None; ics.len()];
            let sink = &mut |i, r| got[i] = Some(r);
            integrate_batch_henon_heiles(isa, lanes, &map, &ics, &cfg, &requests, sink);
            got
        };
        // 8 lanes (one 512-bit vector each) and 4 (the 256-bit form with 32 registers).
        let pairs = [
            (run(Isa::Avx512, 8), run(Isa::Pinned, 8)),
            (run(Isa::Avx512, 4), run(Isa::Pinned, 4)),
        ];
        for (wide, pinned) in &pairs {
            for (i, (a, b)) in wide.iter().zip(pinned).enumerate() {
                let (a, b) = (a.as_ref().unwrap(), b.as_ref().unwrap());
                assert!(
                    same_bits(a, b),
                    "{scheme} orbit {i}:\n avx512 {a:?}\n pinned {b:?}"
                );
            }
        }
    }
}

/// Steps beyond the splitting's stability limit: the energy checks every
/// `ENERGY_CHECK_EVERY` steps stop the same orbits at the same step in both drivers.
#[test]
fn batched_lanes_stop_on_energy_drift_at_the_scalar_step() {
    let crossings = Requests {
        crossings: true,
        ..Requests::default()
    };
    for tau in [0.9, 1.0, 2.0] {
        let statuses = check::<4>("sbab2c", tau, 400.0, crossings);
        assert!(
            statuses.contains(&Status::EnergyDrift),
            "τ = {tau}: {statuses:?}"
        );
    }
}

/// The steps of the orbits from `ics` (the first `orbits` of them) that cross the section
/// upwards within `steps` steps of `map`.
fn crossing_steps(
    map: &TangentMap<'_, HenonHeiles>,
    orbits: usize,
    steps: u64,
) -> Vec<salient_core::section::CrossingStep<2>> {
    ics()
        .iter()
        .take(orbits)
        .flat_map(|&(q, p)| salient_core::section::upward_crossing_steps(map, q, p, steps))
        .collect()
}

fn crossing_bits(c: &salient_core::section::Crossing<2>) -> [u64; 5] {
    [c.t, c.q[0], c.q[1], c.p[0], c.p[1]].map(f64::to_bits)
}

/// Crossings located together in lanes equal those located one by one, bit for bit, also with
/// fewer crossings than lanes and with a lane whose scaled coefficients underflow (it takes the
/// scalar path).
#[test]
fn crossings_located_in_lanes_equal_scalar_ones() {
    use salient_core::section::{locate_upward, locate_upward_lanes, CrossingStep};
    let ham = HenonHeiles;
    for scheme in ["sbab2c", "saba2c", "sbab1", "srkn14a", "aba864"] {
        let tau = 0.3;
        let map = TangentMap::new(&ham, &Scheme::by_name(scheme).unwrap(), tau);
        let mut starts = crossing_steps(&map, 12, 400);
        // q1 a denormal below zero: h ≈ 1e-310, whose cube underflows to 0.
        let (q, p) = on_section(&ham, 0.125, &[0.1], &[0.05]).unwrap();
        let q1_end = tau * p[0];
        let q = [-1e-310, q[1]];
        starts.insert(
            1,
            CrossingStep {
                q,
                p,
                t: 0.0,
                q1_end,
            },
        );
        assert!(starts.len() > 40, "{scheme}: {}", starts.len());
        for chunk in starts.chunks(4) {
            let lanes = locate_upward_lanes::<_, 2, 4>(&map, chunk);
            for (k, step) in chunk.iter().enumerate() {
                let want = locate_upward(&map, step);
                let have = lanes[k];
                assert_eq!(
                    crossing_bits(&have),
                    crossing_bits(&want),
                    "{scheme}: {have:?} vs {want:?}"
                );
            }
        }
    }
}

/// The search that ends once a crossing's region is certain
/// (`locate_upward_lanes_settling`): for every crossing it settles, the crossing the full
/// search finds lies within the bound it handed over, in q2 and in p2, whatever the scheme's
/// order and the step; most crossings settle at the first partial step (so the bound is not
/// vacuous); and a lane the caller never accepts comes out as the full search's, bit for bit.
#[test]
fn settled_crossings_lie_within_their_bound() {
    use salient_core::section::{locate_upward, locate_upward_lanes_settling, Crossing};
    use std::cell::RefCell;
    let ham = HenonHeiles;
    // (scheme, τ, the share of crossings that must settle at once, a little below the
    // measured share)
    let cases = [
        ("sbab2c", 0.5, 0.99),
        ("sbab2c", 1.0, 0.9),
        ("sbab2c", 0.01, 0.99),
        ("saba1", 1.0, 0.6),
        ("sbab1", 0.5, 0.75),
        ("saba2c", 0.7, 0.99),
        ("srkn14a", 0.5, 0.99),
        ("aba864", 1.0, 0.99),
    ];
    for (scheme, tau, settled_share) in cases {
        let map = TangentMap::new(&ham, &Scheme::by_name(scheme).unwrap(), tau);
        let starts = crossing_steps(&map, 12, (800.0 / tau) as u64);
        assert!(starts.len() > 300, "{scheme} τ = {tau}: {}", starts.len());
        let (mut settled, mut worst) = (0, 0.0f64);
        for chunk in starts.chunks(8) {
            let asked = RefCell::new(Vec::<(Crossing<2>, f64)>::new());
            let lanes = locate_upward_lanes_settling::<_, 2, 8>(&map, chunk, &|c, r| {
                asked.borrow_mut().push((*c, r));
                true
            });
            let refused = locate_upward_lanes_settling::<_, 2, 8>(&map, chunk, &|_, _| false);
            for (k, step) in chunk.iter().enumerate() {
                let want = locate_upward(&map, step);
                assert_eq!(crossing_bits(&refused[k]), crossing_bits(&want));
                let have = lanes[k];
                let bound = asked
                    .borrow()
                    .iter()
                    .find(|(c, _)| crossing_bits(c) == crossing_bits(&have))
                    .map(|&(_, r)| r);
                let Some(r) = bound else {
                    assert_eq!(crossing_bits(&have), crossing_bits(&want));
                    continue;
                };
                settled += 1;
                let off = (have.q[1] - want.q[1])
                    .abs()
                    .max((have.p[1] - want.p[1]).abs());
                assert!(
                    off <= r,
                    "{scheme} τ = {tau}: {have:?} is {off:e} from {want:?}, bound {r:e}"
                );
                worst = worst.max(off / r);
            }
        }
        let share = settled as f64 / starts.len() as f64;
        eprintln!("{scheme} τ = {tau}: {share:.4} settled, largest offset {worst:.3} of the bound");
        assert!(share >= settled_share, "{scheme} τ = {tau}: {share}");
    }
}

/// The adaptive methods as a grid runs them (`integrate_feed_adaptive_henon_heiles`: Taylor,
/// taylor-dd and DOP853 in SIMD lanes or one orbit at a time, by τ and t_final) give, orbit by
/// orbit, the bits of the one-orbit driver (`run_adaptive_henon_heiles`): both protocols, with
/// crossings, energy checks and time series, escaping orbits among them, and orbits the feed
/// abandons (at the same step as a watch abandons the one orbit).
#[test]
fn adaptive_lanes_equal_scalar_orbits_bit_for_bit() {
    use salient_core::adaptive::driver::{Abandoned, Protocol, Watch};
    use salient_core::adaptive::lanes::{LANES, LONG_RUN_LANES};
    use salient_core::run::{
        adaptive_orbits_per_thread, feed_orbits_per_thread, integrate_feed_adaptive_henon_heiles,
        run_adaptive_henon_heiles, GUIDED_DOP853_LANES,
    };
    use salient_core::section::Crossing;
    use salient_core::tangent_map::batch::{BatchFeed, Feed};

    type Outcome = Result<OrbitResult<2>, Abandoned>;
    /// Orbit `id` is abandoned at its third poll when id % 7 == 3, at its fiftieth when
    /// id % 7 == 5 (long after the quiet steps the lanes' loop takes for the driver began: a
    /// poll skipped or made twice moves the abandonment).
    fn abandons(id: usize, polls: &mut usize) -> bool {
        *polls += 1;
        (id % 7 == 3 && *polls == 3) || (id % 7 == 5 && *polls == 50)
    }
    struct Slice<'a> {
        ics: &'a [([f64; 2], [f64; 2])],
        next: usize,
        asked: usize,
        got: Vec<Option<Outcome>>,
        polls: Vec<usize>,
        seen: Vec<Vec<Crossing<2>>>,
    }
    impl BatchFeed<2> for Slice<'_> {
        fn next(&mut self, all_idle: bool) -> Feed<2> {
            // Now and then nothing for the moment, as the fast-PSS feed answers while the
            // outcomes it waits for are on their way.
            self.asked += 1;
            if !all_idle && self.asked.is_multiple_of(5) {
                return Feed::Wait;
            }
            let Some(&(q, p)) = self.ics.get(self.next) else {
                return Feed::Done;
            };
            self.next += 1;
            Feed::Orbit(self.next - 1, q, p)
        }
        fn finished(&mut self, id: usize, r: OrbitResult<2>) {
            assert!(self.got[id].is_none(), "orbit {id} reported twice");
            self.got[id] = Some(Ok(r));
        }
        fn on_crossing(&mut self, id: usize, c: &Crossing<2>) {
            self.seen[id].push(*c);
        }
        fn cancelled(&mut self, id: usize) -> bool {
            abandons(id, &mut self.polls[id])
        }
        fn abandoned(&mut self, id: usize, steps: u64) {
            assert!(self.got[id].is_none(), "orbit {id} reported twice");
            self.got[id] = Some(Err(Abandoned { steps }));
        }
    }
    struct Polls(usize, usize);
    impl Watch<2> for Polls {
        fn cancelled(&mut self) -> bool {
            abandons(self.0, &mut self.1)
        }
    }

    let crossings = Requests {
        crossings: true,
        ..Requests::default()
    };
    let everything = Requests {
        crossings: true,
        energy: true,
        gali: true,
        samples_per_decade: 5,
        growth: true,
    };
    // MEGNO and the FLI without the energy request: lanes take quiet restart steps for the
    // driver, which must note the same growth.
    let growing = Requests {
        crossings: true,
        growth: true,
        ..Requests::default()
    };
    let points = |energy| -> Vec<_> {
        (0..24)
            .filter_map(|k| {
                let (q2, p2) = (-0.4 + 0.045 * k as f64, 0.3 - 0.025 * k as f64);
                on_section(&HenonHeiles, energy, &[q2], &[p2]).ok()
            })
            .collect()
    };
    let (bound, escaping) = (points(0.125), points(0.2));
    // (method, protocol, τ, t_final, δ, energy drift threshold, requests, energy, points)
    #[rustfmt::skip]
    let cases = [
        (Method::Taylor, Protocol::Restart, 0.1, 600.0, 1e-9, None, crossings, 0.125, &bound),
        (Method::Taylor, Protocol::Free, 0.1, 600.0, 1e-9, None, everything, 0.2, &escaping),
        (Method::Taylor, Protocol::Restart, 0.5, 400.0, 1e-7, None, crossings, 0.125, &bound),
        (Method::Taylor, Protocol::Restart, 0.05, 400.0, 1e-9, None, growing, 0.125, &bound),
        (Method::TaylorDd, Protocol::Restart, 0.5, 600.0, 1e-9, None, everything, 0.2, &escaping),
        (Method::TaylorDd, Protocol::Free, 0.1, 600.0, 1e-9, None, crossings, 0.125, &bound),
        (Method::TaylorDd, Protocol::Restart, 0.05, 400.0, 1e-7, None, crossings, 0.125, &bound),
        (Method::Dop853, Protocol::Restart, 0.05, 400.0, 1e-7, None, crossings, 0.125, &bound),
        (Method::Dop853, Protocol::Restart, 0.05, 400.0, 1e-7, None, growing, 0.125, &bound),
        (Method::TaylorDd, Protocol::Restart, 0.05, 400.0, 1e-7, None, growing, 0.125, &bound),
        (Method::Dop853, Protocol::Free, 0.05, 600.0, 1e-9, None, everything, 0.2, &escaping),
        (Method::Dop853, Protocol::Restart, 0.5, 400.0, 1e-7, None, crossings, 0.125, &bound),
        // Long runs take fewer lanes.
        (Method::TaylorDd, Protocol::Restart, 0.5, 4e4, 1e-7, None, crossings, 0.125, &bound),
        // taylor-dd's lanes screen the energy error in f64 at every step: the drift stops
        // the same orbits at the same step as the exact error of the one-orbit driver.
        (Method::TaylorDd, Protocol::Restart, 0.5, 2e3, 1e-4, Some(3e-5), crossings, 0.125, &bound),
    ];
    // The cases take every path: lanes of both widths and one orbit at a time.
    assert_eq!(
        adaptive_orbits_per_thread(&Method::Taylor, 0.1, 600.0),
        LANES
    );
    assert_eq!(adaptive_orbits_per_thread(&Method::Taylor, 0.5, 400.0), 1);
    assert_eq!(
        adaptive_orbits_per_thread(&Method::Dop853, 0.05, 400.0),
        LANES
    );
    assert_eq!(adaptive_orbits_per_thread(&Method::Dop853, 0.5, 400.0), 1);
    assert_eq!(
        adaptive_orbits_per_thread(&Method::TaylorDd, 0.5, 600.0),
        LANES
    );
    assert_eq!(
        adaptive_orbits_per_thread(&Method::TaylorDd, 0.5, 4e4),
        LONG_RUN_LANES
    );
    let wide = Isa::detect().lanes() == GUIDED_DOP853_LANES;
    assert_eq!(
        feed_orbits_per_thread(&Method::Dop853, 0.05, 400.0, true),
        if wide { GUIDED_DOP853_LANES } else { LANES }
    );
    assert_eq!(
        feed_orbits_per_thread(&Method::Taylor, 0.05, 400.0, true),
        LANES
    );
    // DOP853 also in the wider batch a forecast allows, where the host has it.
    let runs = cases
        .iter()
        .flat_map(|c| [(c, false), (c, true)])
        .filter(|(c, guided)| !guided || matches!(c.0, Method::Dop853));
    let (mut abandoned, mut statuses) = (0, std::collections::BTreeSet::new());
    for (case, guided) in runs {
        let (method, protocol, tau, t_final, delta, drift, requests, energy, ics) = case.clone();
        let run = MethodRun {
            method,
            delta: Some(delta),
            protocol,
        };
        let mut config = OrbitConfig::new(tau, t_final);
        if let Some(drift) = drift {
            config.thresholds.energy_drift = drift;
        }
        let mut feed = Slice {
            ics,
            next: 0,
            asked: 0,
            got: vec![None; ics.len()],
            polls: vec![0; ics.len()],
            seen: vec![Vec::new(); ics.len()],
        };
        integrate_feed_adaptive_henon_heiles(&run, energy, &config, &requests, guided, &mut feed);
        let mut case_statuses = std::collections::BTreeSet::new();
        for (i, &start) in ics.iter().enumerate() {
            let want = run_adaptive_henon_heiles(
                &run,
                energy,
                start,
                &config,
                &requests,
                Vectors::Two,
                &mut Polls(i, 0),
            );
            let have = feed.got[i].as_ref().expect("every orbit reported");
            let label = format!("{run:?} τ = {tau} guided {guided}, orbit {i}");
            match (have, &want) {
                (Ok(a), Ok(b)) => {
                    assert!(same_bits(a, b), "{label}:\n lanes  {a:?}\n scalar {b:?}");
                    // The crossings as the feed saw them while the orbit ran.
                    let seen = OrbitResult {
                        crossings: feed.seen[i].clone(),
                        ..b.clone()
                    };
                    assert!(same_bits(&seen, b), "{label}: crossings seen");
                    case_statuses.insert(format!("{:?}", a.status));
                }
                (Err(a), Err(b)) => {
                    assert_eq!(a, b, "{label}");
                    abandoned += 1;
                }
                _ => panic!("{label}:\n lanes  {have:?}\n scalar {want:?}"),
            }
        }
        if drift.is_some() {
            assert!(
                case_statuses.contains("EnergyDrift") && case_statuses.len() > 1,
                "{delta} {case_statuses:?}"
            );
        }
        statuses.extend(case_statuses);
    }
    assert!(abandoned > 0, "no orbit was abandoned");
    assert!(statuses.contains("Escaped"), "{statuses:?}");
    assert!(statuses.len() >= 4, "{statuses:?}");
}

/// DOP853's lanes against the one-orbit integrator step by step, on the paths the grid's
/// restart protocol does not take at every step: lanes left out of a step, steps without a
/// renormalisation, rejected attempts (a bold controller) and the dense output of a step.
#[test]
fn dop853_lanes_equal_the_one_orbit_integrator_step_by_step() {
    use salient_core::adaptive::dop853::{Dense, Dop853, Dop853Config, Dop853Lanes};
    use salient_core::adaptive::stepping::unit_vectors;
    use salient_core::phase::Phase;
    const L: usize = 4;
    let ham = HenonHeiles;
    // A bold controller (steps may grow twentyfold), so that some attempts are rejected.
    let config = Dop853Config {
        safe: 0.99,
        fac_max: 20.0,
        ..Dop853Config::with_delta(1e-12)
    };
    let starts: Vec<Phase<f64, 2, 2>> = [(0.558, 0.0), (-0.25, 0.0), (0.1, 0.2), (0.0, -0.3)]
        .iter()
        .map(|&(q2, p2)| {
            let (q, p) = on_section(&ham, 0.125, &[q2], &[p2]).expect("on the section");
            Phase {
                q,
                p,
                dq: [[1.0, 0.0], [0.0, 1.0]],
                dp: [[0.0; 2]; 2],
            }
        })
        .collect();
    let mut lanes = Dop853Lanes::<_, 2, 2, L>::new(&ham, config);
    let mut alone: Vec<_> = starts
        .iter()
        .enumerate()
        .map(|(l, y)| {
            lanes.start(l, 0.0, y);
            Dop853::new(&ham, config, 0.0, *y)
        })
        .collect();
    let bits = |y: &Phase<f64, 2, 2>| {
        let mut v: Vec<u64> = y.q.iter().chain(&y.p).map(|x| x.to_bits()).collect();
        for k in 0..2 {
            v.extend(y.dq[k].iter().chain(&y.dp[k]).map(|x| x.to_bits()));
        }
        v
    };
    for round in 0..400u32 {
        // Lane l sits out every (l + 2)-th round; some lanes are renormalised, others not.
        let asked: [Option<f64>; L] =
            core::array::from_fn(|l| (!round.is_multiple_of(l as u32 + 2)).then_some(1e4));
        let renormalise: [bool; L] = core::array::from_fn(|l| (round + l as u32).is_multiple_of(3));
        let (outcomes, factors) = lanes.renormalise_and_step(&renormalise, &asked);
        for l in 0..L {
            if renormalise[l] {
                let factor = unit_vectors(&mut alone[l].y);
                alone[l].state_changed();
                assert_eq!(
                    factor.to_bits(),
                    factors[l].to_bits(),
                    "lane {l}, round {round}"
                );
            }
            let Some(end) = asked[l] else {
                assert!(outcomes[l].is_none());
                continue;
            };
            let want = alone[l].step(end, None);
            assert_eq!(outcomes[l], Some(want), "lane {l}, round {round}");
            assert_eq!(lanes.t(l).to_bits(), alone[l].t.to_bits(), "lane {l}");
            assert_eq!(
                bits(&lanes.state(l)),
                bits(&alone[l].y),
                "lane {l}, round {round}"
            );
        }
        if round % 50 == 49 {
            // Valid until the next step: only for the lanes that stepped just now.
            for l in (0..L).filter(|&l| asked[l].is_some()) {
                let (mut a, mut b) = (Dense::empty(), Dense::empty());
                lanes.dense_output(l, &mut a);
                alone[l].dense_output(&mut b);
                let mid = 0.5 * (lanes.t_prev(l) + lanes.t(l));
                assert_eq!(
                    bits(&a.at(mid)),
                    bits(&b.at(mid)),
                    "lane {l}, round {round}"
                );
            }
        }
    }
    let rejected: u64 = alone.iter().map(|a| a.ctl.rejected).sum();
    assert!(
        rejected > 0,
        "no attempt was rejected: the test misses the retry passes"
    );
}
