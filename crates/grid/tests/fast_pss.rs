//! The fast-PSS engine on real orbits: the paper's Table 2 TM row, fast vs full, and
//! independence from the number of threads.

use salient_core::adaptive::driver::Protocol;
use salient_core::method::Method;
use salient_core::orbit::OrbitConfig;
use salient_core::run::{adaptive_orbits_per_thread, MethodRun};
use salient_core::Scheme;
use salient_grid::{
    integrate_cells, run_embedded, run_embedded_forecast, CellRun, Counts, Grid, Ledger, Mode,
};

fn paper_grid(n: usize) -> Grid {
    let q2 = (
        0.5 + 160f64.to_radians().cos(),
        0.5 + 80f64.to_radians().cos(),
    );
    Grid::new(0.125, n, n, q2, (-0.5, 0.5), (20, 20))
}

fn tm(scheme: &str, tau: f64, t_final: f64) -> CellRun {
    CellRun {
        run: MethodRun {
            method: Method::TangentMap(Scheme::by_name(scheme).unwrap()),
            delta: None,
            protocol: Protocol::Restart,
        },
        config: OrbitConfig::new(tau, t_final),
        checkpoints_per_decade: 0,
        indicators: false,
    }
}

/// An adaptive method at δ = 1e-8 in the restart protocol.
fn adaptive(method: Method, tau: f64, t_final: f64) -> CellRun {
    CellRun {
        run: MethodRun {
            method,
            delta: Some(1e-8),
            protocol: Protocol::Restart,
        },
        config: OrbitConfig::new(tau, t_final),
        checkpoints_per_decade: 0,
        indicators: false,
    }
}

fn pool(threads: usize) -> rayon::ThreadPool {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap()
}

#[test]
fn table2_tm_row_400x400_tau_0_5_t_1e4() {
    let grid = paper_grid(400);
    let start = std::time::Instant::now();
    let ledger =
        pool(2).install(|| run_embedded(&grid, &tm("sbab2c", 0.5, 1e4), Mode::FastPss, 8, |_| {}));
    let wall = start.elapsed().as_secs_f64();
    let c = Counts::of(&grid, &ledger);
    let (r, s, ch) = c.percent();
    eprintln!(
        "400x400 TM τ=0.5 t=1e4: {r:.2} / {s:.2} / {ch:.2} %, {} orbits, {} dropped, {:.2} s, steps {} + dropped {}",
        ledger.committed.len(),
        ledger.dropped,
        wall,
        ledger.committed_steps,
        ledger.dropped_steps
    );
    assert_eq!(c.compatible, 121_548);
    // The paper's TM row: 40.89 / 0.38 / 58.73.
    assert!(
        (r - 40.89).abs() < 0.5 && (s - 0.38).abs() < 0.5 && (ch - 58.73).abs() < 0.5,
        "{r} {s} {ch}"
    );
    assert!((4000..6000).contains(&ledger.committed.len()));
}

#[test]
fn fast_pss_and_full_agree_within_3_points_on_60x60() {
    // At t = 1e4 the classes have settled (at 1e3 many chaotic orbits still look sticky, and
    // fast PSS spreads that label over every cell they visit).
    let grid = paper_grid(60);
    let run = tm("sbab2c", 0.5, 1e4);
    let fast = pool(2).install(|| run_embedded(&grid, &run, Mode::FastPss, 16, |_| {}));
    let full = pool(2).install(|| run_embedded(&grid, &run, Mode::Full, 256, |_| {}));
    let (a, b) = (
        Counts::of(&grid, &fast).percent(),
        Counts::of(&grid, &full).percent(),
    );
    assert_eq!(full.committed.len(), grid.compatible_count());
    assert!(fast.committed.len() < full.committed.len() / 2);
    for (x, y) in [(a.0, b.0), (a.1, b.1), (a.2, b.2)] {
        assert!((x - y).abs() < 3.0, "fast {a:?} vs full {b:?}");
    }
}

#[test]
fn labels_do_not_depend_on_threads_or_window() {
    let grid = paper_grid(50);
    let run = tm("sbab2c", 0.5, 2e3);
    let a = pool(1).install(|| run_embedded(&grid, &run, Mode::FastPss, 1, |_| {}));
    let cells = |l: &salient_grid::Ledger| l.committed.iter().map(|o| o.cell).collect::<Vec<_>>();
    // At τ = 0.5 two threads run as a stepping/locating pair, three as a pair and a plain
    // driver, four as two pairs; one thread is a plain driver.
    for threads in [2, 3, 4] {
        let b = pool(threads).install(|| run_embedded(&grid, &run, Mode::FastPss, 64, |_| {}));
        for c in 0..grid.cells() as u32 {
            let (x, y) = (a.label(c), b.label(c));
            assert_eq!(
                x.map(|l| (l.class, l.source, l.sali.to_bits())),
                y.map(|l| (l.class, l.source, l.sali.to_bits())),
                "{threads} threads"
            );
        }
        assert_eq!(cells(&a), cells(&b), "{threads} threads");
    }
    // Adaptive methods stream one orbit per thread or a few in SIMD lanes (taylor-dd always,
    // f64 Taylor and DOP853 at small τ), claiming crossed cells and abandoning orbits as they go:
    // the labels are those of the sequential rule (rounds of one cell, the worker's path), with one
    // thread or two.
    let dop = adaptive(Method::Dop853, 0.5, 500.0);
    let mut taylor = dop.clone();
    taylor.run.method = Method::Taylor;
    let mut taylor_dd = dop.clone();
    taylor_dd.run.method = Method::TaylorDd;
    let mut taylor_lanes = taylor.clone();
    taylor_lanes.config = OrbitConfig::new(0.1, 500.0);
    assert!(adaptive_orbits_per_thread(&Method::Taylor, 0.1, 500.0) > 1);
    let mut dop_lanes = dop.clone();
    dop_lanes.config = OrbitConfig::new(0.05, 200.0);
    assert!(adaptive_orbits_per_thread(&Method::Dop853, 0.05, 200.0) > 1);
    for adaptive in [&dop, &taylor, &taylor_dd, &taylor_lanes, &dop_lanes] {
        let mut sequential = Ledger::new(&grid, Mode::FastPss);
        while !sequential.done() {
            let next = sequential.needed(1, &|_| false);
            for o in integrate_cells(&grid, adaptive, Mode::FastPss, &next) {
                sequential.offer(o);
            }
        }
        for threads in [1, 2] {
            let x =
                pool(threads).install(|| run_embedded(&grid, adaptive, Mode::FastPss, 8, |_| {}));
            for c in 0..grid.cells() as u32 {
                let (l, m) = (sequential.label(c), x.label(c));
                assert_eq!(
                    l.map(|l| (l.class, l.source, l.sali.to_bits())),
                    m.map(|l| (l.class, l.source, l.sali.to_bits())),
                    "{:?}, {threads} threads",
                    adaptive.run.method
                );
            }
            assert_eq!(cells(&sequential), cells(&x));
        }
    }
    let f1 = pool(2).install(|| run_embedded(&grid, &dop, Mode::Full, 64, |_| {}));
    let f2 = pool(1).install(|| run_embedded(&grid, &dop, Mode::Full, 1, |_| {}));
    assert_eq!(f1.dropped + f2.dropped, 0, "full mode never drops");
    assert_eq!(cells(&f1), cells(&f2));
}

/// A forecast (the labellers of a similar run) decides which cells the lanes take first, so it
/// changes the work done, never the labels: with its own labellers a run drops nearly nothing,
/// and a poor forecast or another method's gives the same labels as none.
#[test]
fn a_forecast_changes_the_work_and_never_the_labels() {
    let grid = paper_grid(60);
    let labels = |l: &Ledger| {
        (0..grid.cells() as u32)
            .map(|c| l.label(c).map(|l| (l.class, l.source, l.sali.to_bits())))
            .collect::<Vec<_>>()
    };
    let embedded = |run: &CellRun, threads: usize, forecast: Option<&salient_grid::Forecast>| {
        pool(threads)
            .install(|| run_embedded_forecast(&grid, run, Mode::FastPss, 8, forecast, |_| {}))
    };
    // τ = 0.05: four lanes per thread run ahead of the frontier.
    let run = tm("sbab2c", 0.05, 2e3);
    let plain = embedded(&run, 1, None);
    let own = plain.forecast();
    // τ = 0.5's orbits part from τ = 0.05's, and so do their labellers: a poor forecast.
    let poor = embedded(&tm("sbab2c", 0.5, 2e3), 2, None).forecast();
    let other = embedded(&tm("sbab4", 0.05, 2e3), 2, None).forecast();
    for (name, forecast) in [("own", &own), ("poor", &poor), ("other", &other)] {
        for threads in [1, 2] {
            let x = embedded(&run, threads, Some(forecast));
            assert!(labels(&plain) == labels(&x), "{name}, {threads} threads");
        }
    }
    // One thread is deterministic: its own labellers leave the lanes only cells whose orbits
    // commit (the last few cells aside).
    let guided = embedded(&run, 1, Some(&own));
    eprintln!(
        "dropped steps: {} without a forecast, {} with its own",
        plain.dropped_steps, guided.dropped_steps
    );
    assert!(guided.dropped_steps * 10 < plain.dropped_steps);
    // The Table 2 use: an adaptive method forecast by another on the same τ and t_final.
    let dop = adaptive(Method::Dop853, 0.05, 200.0);
    let taylor = adaptive(Method::Taylor, 0.05, 200.0);
    let by_taylor = embedded(&taylor, 2, None).forecast();
    let want = labels(&embedded(&dop, 1, None));
    for threads in [1, 2] {
        assert!(want == labels(&embedded(&dop, threads, Some(&by_taylor))));
    }
}

/// A stream of leased cells, as a worker feeds the executor: each cell given once, in order,
/// and what became of it.
struct ListSource {
    queue: std::sync::Mutex<std::collections::VecDeque<u64>>,
    ended: std::sync::Mutex<Vec<(u32, Option<salient_grid::Outcome>)>>,
    /// Hands out a deferred cell as [`Take::Insist`] (a worker's source does), or as a plain
    /// [`Take::Cell`].
    insist: bool,
}

impl ListSource {
    fn new(entries: impl IntoIterator<Item = u64>, insist: bool) -> Self {
        ListSource {
            queue: std::sync::Mutex::new(entries.into_iter().collect()),
            ended: std::sync::Mutex::new(Vec::new()),
            insist,
        }
    }
}

impl salient_grid::executor::CellSource for ListSource {
    fn take(
        &self,
        all_idle: bool,
        judge: &dyn Fn(u32) -> salient_grid::executor::Verdict,
    ) -> salient_grid::executor::Take {
        use salient_grid::executor::{Take, Verdict};
        let mut queue = self.queue.lock().unwrap();
        if queue.is_empty() {
            return Take::Done;
        }
        let mut i = 0;
        while i < queue.len() {
            match judge(queue[i] as u32) {
                Verdict::Go => return Take::Cell(queue.remove(i).unwrap()),
                Verdict::Later => i += 1,
                Verdict::Drop => {
                    let e = queue.remove(i).unwrap();
                    self.ended.lock().unwrap().push((e as u32, None));
                }
            }
        }
        // With every lane idle nothing here can settle the deferred cells: the first goes.
        match queue.pop_front() {
            Some(e) if all_idle && self.insist => Take::Insist(e),
            Some(e) if all_idle => Take::Cell(e),
            Some(e) => {
                queue.push_front(e);
                Take::Wait
            }
            None => Take::Done,
        }
    }
    fn ended(&self, entry: u64, outcome: Option<salient_grid::Outcome>, _steps: u64) {
        self.ended.lock().unwrap().push((entry as u32, outcome));
    }
}

/// A worker's stream with its own ledger: every outcome it returns is bit for bit the plain
/// one, cells claimed beforehand get none, every cell ends exactly once, and cells that its
/// own earlier orbits crossed wait and end without an orbit once those label them (the cells
/// cover a regular region, whose orbits cross their neighbours).
#[test]
fn worker_streams_skip_claimed_and_crossed_cells_without_changing_outcomes() {
    use salient_grid::executor::{integrate_stream, LocalLedger};
    let grid = paper_grid(100);
    let mut dop = tm("sbab2c", 0.5, 2e3);
    dop.run = MethodRun {
        method: Method::Dop853,
        delta: Some(1e-8),
        protocol: Protocol::Restart,
    };
    // Tangent-map cells run in lane batches, adaptive ones one orbit per thread: both
    // through the same feed.
    for run in [tm("sbab2c", 0.5, 2e3), dop] {
        let cells: Vec<u32> = grid.canonical()[..64].to_vec();
        let plain = pool(2).install(|| integrate_cells(&grid, &run, Mode::FastPss, &cells));
        assert_eq!(plain.len(), cells.len());
        let claimed = [cells[5], cells[40]];
        for threads in [1, 2] {
            let local = LocalLedger::new(&grid, Mode::FastPss);
            for &c in &claimed {
                local.claims().claim(c);
            }
            // Entries carry a serial above the cell, as a worker's do.
            let source = ListSource::new(
                cells
                    .iter()
                    .enumerate()
                    .map(|(i, &c)| ((i as u64 + 1) << 32) | c as u64),
                true,
            );
            pool(threads).install(|| integrate_stream(&grid, &run, Mode::FastPss, &local, &source));
            let ended = source.ended.into_inner().unwrap();
            let mut seen: Vec<u32> = ended.iter().map(|(c, _)| *c).collect();
            seen.sort_unstable();
            let mut want_seen = cells.clone();
            want_seen.sort_unstable();
            assert_eq!(seen, want_seen, "every cell ends exactly once");
            let got: Vec<&salient_grid::Outcome> =
                ended.iter().filter_map(|(_, o)| o.as_ref()).collect();
            for o in &got {
                assert!(
                    !claimed.contains(&o.cell),
                    "{:?}: claimed cell {} integrated",
                    run.run.method,
                    o.cell
                );
                let want = plain.iter().find(|p| p.cell == o.cell).unwrap();
                assert_eq!(o.visited, want.visited);
                assert_eq!(
                    (o.class, o.status, o.steps),
                    (want.class, want.status, want.steps)
                );
                assert_eq!(o.sali.to_bits(), want.sali.to_bits());
            }
            // One thread is deterministic: some cells were crossed by an earlier orbit of the
            // stream and left out.
            if threads == 1 {
                assert!(
                    got.len() < cells.len() - claimed.len(),
                    "{} of {}",
                    got.len(),
                    cells.len()
                );
            }
        }
    }
}

/// A cell that a pending outcome of the stream's own ledger crossed is only probably labelled:
/// that outcome may be dropped by an earlier one the ledger has not seen (a worker's ledger
/// can lack outcomes its coordinator has). Handed out insistently — nothing else runs or waits
/// — its orbit runs to the end and gives the plain outcome; handed out as a plain cell it is
/// abandoned on the same guess, at every lease of it.
#[test]
fn a_cell_insisted_on_is_not_abandoned_on_a_probable_label() {
    use salient_grid::executor::{integrate_stream, LocalLedger};
    let grid = paper_grid(100);
    let run = tm("sbab2c", 0.5, 2e3);
    let cells: Vec<u32> = grid.canonical()[..64].to_vec();
    let plain = pool(1).install(|| integrate_cells(&grid, &run, Mode::FastPss, &cells));
    let pos = |c: u32| grid.position(c).unwrap();
    // An outcome after the first cell (left unsettled, so it stays pending) that crossed a
    // later cell.
    let (claimer, crossed) = plain
        .iter()
        .filter(|o| pos(o.cell) > 0)
        .find_map(|o| {
            o.visited
                .iter()
                .find(|&&v| grid.position(v).is_some_and(|p| p > pos(o.cell)))
                .map(|&v| (o.clone(), v))
        })
        .expect("a regular orbit crosses a later cell");
    let want = integrate_cells(&grid, &run, Mode::FastPss, &[crossed]).remove(0);
    for insist in [true, false] {
        let local = LocalLedger::new(&grid, Mode::FastPss);
        local.offer(claimer.clone());
        let source = ListSource::new([(1u64 << 32) | crossed as u64], insist);
        pool(1).install(|| integrate_stream(&grid, &run, Mode::FastPss, &local, &source));
        let ended = source.ended.into_inner().unwrap();
        assert_eq!(ended.len(), 1);
        match (insist, &ended[0].1) {
            (true, Some(o)) => {
                assert_eq!(
                    (o.cell, o.steps, o.class),
                    (want.cell, want.steps, want.class)
                );
                assert_eq!(o.sali.to_bits(), want.sali.to_bits());
            }
            (false, None) => {} // abandoned on the guess
            (insist, got) => panic!("insist {insist}: {got:?}"),
        }
    }
}
