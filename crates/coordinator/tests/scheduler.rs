//! The scheduler driven without a network: simulated workers integrate real orbits with the
//! grid's tile executor and report in awkward orders; the labels must equal the embedded
//! run's, and every wire rule (versions, stale attempts, repeats, malformed reports, restart)
//! must hold.

use salient_coordinator::scheduler::{Config, Scheduler};
use salient_grid::spec::{self, JobSpec};
use salient_grid::{integrate_cells, run_embedded, Label, Ledger, OutcomeNews};
use salient_proto::v1;
use salient_proto::{outcome_from_wire, Expected, PROTOCOL_VERSION};
use salient_store::Store;
use std::collections::HashSet;
use std::time::Duration;
use tonic::Code;

fn spec_json(mode: &str, methods: &str) -> String {
    format!(
        r#"{{"name": "t", "system": {{"kind": "henon-heiles", "energy": 0.125}},
            "grid": {{"cells": [14, 12], "tile": [4, 5], "mode": "{mode}"}},
            "sweep": {{"method": [{methods}], "tau": [0.5], "t_final": [200.0], "delta": [1e-6]}}}}"#
    )
}

fn config() -> Config {
    Config {
        lease: Duration::from_secs(60),
        poll: Duration::from_millis(10),
        ..Config::default()
    }
}

fn register(s: &mut Scheduler) -> String {
    s.register(&v1::RegisterRequest {
        protocol_version: PROTOCOL_VERSION,
        name: "test".into(),
        threads: 1,
    })
    .unwrap()
    .worker_id
}

/// Labels of every cell of every run, rebuilt from the results stream as `salient results`
/// does.
fn labels(s: &Scheduler, job: u64) -> Vec<Vec<Option<Label>>> {
    use v1::results_chunk::Part;
    let mut spec: Option<JobSpec> = None;
    let mut ledgers: Vec<Ledger> = Vec::new();
    for c in s.results(job, 7).unwrap() {
        match c.part.unwrap() {
            Part::Header(h) => spec = Some(spec::parse(&h.spec_json, true).unwrap()),
            Part::Run(h) => {
                let sp = spec.as_ref().unwrap();
                ledgers.push(Ledger::new(
                    &sp.grid(h.run as usize),
                    sp.mode(h.run as usize),
                ));
            }
            Part::Outcomes(b) => {
                let sp = spec.as_ref().unwrap();
                let k = Expected::of_run(&sp.cell_run(b.run as usize));
                for o in &b.outcomes {
                    ledgers[b.run as usize]
                        .offer(outcome_from_wire(o, &sp.grid(b.run as usize), k).unwrap());
                }
            }
        }
    }
    let grid = spec.unwrap().grid(0);
    ledgers
        .iter()
        .map(|l| {
            assert!(l.done());
            (0..grid.cells() as u32).map(|c| l.label(c)).collect()
        })
        .collect()
}

fn embedded(json: &str) -> Vec<Vec<Option<Label>>> {
    let spec = spec::parse(json, true).unwrap();
    let grid = spec.grid(0);
    (0..spec.runs.len())
        .map(|i| {
            let l = run_embedded(&grid, &spec.cell_run(i), spec.mode(i), 8, |_| {});
            (0..grid.cells() as u32).map(|c| l.label(c)).collect()
        })
        .collect()
}

/// Integrates a lease's cells, minus those the coordinator said to skip.
fn work(lease: &v1::Lease, skip: &HashSet<u32>) -> v1::TileReport {
    let spec = spec::parse(&lease.spec_json, true).unwrap();
    let tile = lease.lease.unwrap();
    let cells: Vec<u32> = lease
        .cells
        .iter()
        .copied()
        .filter(|c| !skip.contains(c))
        .collect();
    let outcomes = integrate_cells(
        &spec.grid(0),
        &spec.cell_run(tile.run as usize),
        spec.mode(tile.run as usize),
        &cells,
    );
    v1::TileReport {
        lease: Some(tile),
        outcomes: outcomes.iter().map(v1::Outcome::from).collect(),
        finished: true,
        cpu_ns: 1,
        ..Default::default()
    }
}

/// Simulated workers: each poll returns a lease, which is worked on and reported in a later
/// poll, so leases overlap and reports arrive out of canonical order.
fn drive(s: &mut Scheduler, job: u64, workers: usize, mut stop_after: Option<usize>) -> usize {
    let ids: Vec<String> = (0..workers).map(|_| register(s)).collect();
    let mut pending: Vec<Option<v1::Lease>> = vec![None; workers];
    let mut skips: Vec<HashSet<u32>> = vec![HashSet::new(); workers];
    let mut reports = 0;
    for round in 0.. {
        assert!(round < 100_000, "no progress");
        if s.is_finished(job).unwrap() {
            break;
        }
        if stop_after == Some(reports) {
            break;
        }
        // Workers take turns in a shuffled order.
        let w = (round * 7 + round / 3) % workers;
        let report = pending[w].take().map(|l| work(&l, &skips[w]));
        reports += report.is_some() as usize;
        let held: Vec<v1::TileRef> = Vec::new();
        let reply = s
            .poll(&v1::PollRequest {
                worker_id: ids[w].clone(),
                free_slots: 1,
                held,
                reports: report.into_iter().collect(),
                draining: false,
                ..Default::default()
            })
            .unwrap();
        for sk in reply.skips {
            skips[w].extend(sk.cells);
        }
        pending[w] = reply.leases.into_iter().next();
        if stop_after.is_some_and(|n| reports >= n) {
            stop_after = Some(reports);
        }
    }
    reports
}

#[test]
fn simulated_workers_give_the_embedded_labels_in_both_modes() {
    for (mode, methods) in [
        ("fast-pss", r#""tm-sbab2c", "dop853""#),
        ("full", r#""tm-sbab2c""#),
    ] {
        let json = spec_json(mode, methods);
        let mut s = Scheduler::new(Store::open_in_memory().unwrap(), config()).unwrap();
        let (job, _) = s.submit(&json).unwrap();
        drive(&mut s, job, 3, None);
        let st = s.status(Some(job)).unwrap().jobs.remove(0);
        assert_eq!(st.state, "done");
        assert_eq!(st.runs_done, st.runs_total);
        assert_eq!(labels(&s, job), embedded(&json), "{mode}");
    }
}

/// Orbits dropped per run, from the results stream.
fn dropped(s: &Scheduler, job: u64) -> Vec<u64> {
    use v1::results_chunk::Part;
    s.results(job, 7)
        .unwrap()
        .into_iter()
        .filter_map(|c| match c.part.unwrap() {
            Part::Run(r) => Some(r.orbits_dropped),
            _ => None,
        })
        .collect()
}

/// With the labellers of the finished run as its forecast, the scheduler leases only the
/// cells that need their own orbit (none is dropped), from anywhere in the grid, and the labels
/// stay the embedded run's; a forecast of another grid is refused.
#[test]
fn a_forecast_leases_only_the_cells_that_need_their_own_orbit() {
    let json = spec_json("fast-pss", r#""tm-sbab2c""#);
    let spec = spec::parse(&json, true).unwrap();
    let grid = spec.grid(0);
    let finished = run_embedded(&grid, &spec.cell_run(0), spec.mode(0), 8, |_| {});
    let mut s = Scheduler::new(Store::open_in_memory().unwrap(), config()).unwrap();
    let (job, _) = s.submit(&json).unwrap();
    s.set_forecast(job, 0, finished.forecast()).unwrap();
    let other = spec::parse(&json.replace("[14, 12]", "[10, 10]"), true).unwrap();
    let small = Ledger::new(&other.grid(0), other.mode(0)).forecast();
    assert_eq!(
        s.set_forecast(job, 0, small).unwrap_err().code(),
        Code::InvalidArgument
    );
    assert_eq!(
        s.set_forecast(job, 1, finished.forecast())
            .unwrap_err()
            .code(),
        Code::NotFound
    );
    drive(&mut s, job, 3, None);
    assert_eq!(labels(&s, job), embedded(&json));
    assert_eq!(dropped(&s, job), vec![0]);

    // Without the forecast the same workers drop speculative orbits.
    let mut s = Scheduler::new(Store::open_in_memory().unwrap(), config()).unwrap();
    let (job, _) = s.submit(&json).unwrap();
    drive(&mut s, job, 3, None);
    assert!(dropped(&s, job)[0] > 0);
}

/// A finished run forecasts the unfinished runs it resembles: the longer run of its method
/// and τ (the same orbits, longer), not a method whose threads run one orbit at a time; the
/// labels stay the embedded run's.
#[test]
fn a_finished_run_forecasts_the_longer_run_of_its_method() {
    let json =
        spec_json("fast-pss", r#""tm-sbab2c", "dop853""#).replace("[200.0]", "[50.0, 200.0]");
    let spec = spec::parse(&json, true).unwrap();
    let index = |method: &str, t: f64| {
        (0..spec.runs.len())
            .find(|&r| spec.runs[r].method.name() == method && spec.runs[r].t_final == t)
            .unwrap()
    };
    let (short, long) = (index("tm-sbab2c", 50.0), index("tm-sbab2c", 200.0));
    let mut s = Scheduler::new(Store::open_in_memory().unwrap(), config()).unwrap();
    let (job, _) = s.submit(&json).unwrap();
    assert_eq!(s.forecast_from(job, long), None);
    drive(&mut s, job, 3, None);
    assert_eq!(s.forecast_from(job, long), Some(short));
    assert_eq!(s.forecast_from(job, short), None);
    assert_eq!(s.forecast_from(job, index("dop853", 200.0)), None);
    assert_eq!(labels(&s, job), embedded(&json));
}

#[test]
fn a_restarted_scheduler_resumes_without_integrating_committed_cells_again() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("c.db");
    let json = spec_json("fast-pss", r#""tm-sbab2c""#);
    let (job, committed) = {
        let mut s = Scheduler::new(Store::open(&db).unwrap(), config()).unwrap();
        let (job, _) = s.submit(&json).unwrap();
        let n = drive(&mut s, job, 2, Some(3));
        assert_eq!(n, 3);
        assert!(!s.is_finished(job).unwrap());
        let stored = Store::open(&db).unwrap().outcomes(job, 0).unwrap();
        assert!(!stored.is_empty());
        (job, stored.iter().map(|o| o.cell).collect::<HashSet<u32>>())
    };
    // A new scheduler on the same file: no lease it hands out holds a committed cell.
    let mut s = Scheduler::new(Store::open(&db).unwrap(), config()).unwrap();
    let w = register(&mut s);
    let mut leased = Vec::new();
    while !s.is_finished(job).unwrap() {
        let reply = s
            .poll(&v1::PollRequest {
                worker_id: w.clone(),
                free_slots: 1,
                ..Default::default()
            })
            .unwrap();
        for l in reply.leases {
            leased.extend(l.cells.iter().copied());
            let report = work(&l, &HashSet::new());
            s.report(&v1::ReportRequest {
                worker_id: w.clone(),
                reports: vec![report],
            })
            .unwrap();
        }
    }
    assert!(leased.iter().all(|c| !committed.contains(c)));
    assert_eq!(labels(&s, job), embedded(&json));
}

/// The job's status without the clock-dependent fields.
fn snapshot(s: &Scheduler, job: u64) -> String {
    let mut st = s.status(Some(job)).unwrap();
    for j in &mut st.jobs {
        for r in &mut j.runs {
            r.wall_s = 0.0;
            r.orbits_per_s = 0.0;
            r.eta_s = None;
        }
    }
    format!("{st:?}")
}

/// The leases one poll of a free slot brings.
fn poll_leases(s: &mut Scheduler, w: &str) -> Vec<v1::Lease> {
    s.poll(&v1::PollRequest {
        worker_id: w.into(),
        free_slots: 1,
        ..Default::default()
    })
    .unwrap()
    .leases
}

fn lease_one(s: &mut Scheduler, w: &str) -> v1::Lease {
    poll_leases(s, w).remove(0)
}

/// Fast PSS: leases cut the canonical order into units of `FAST_PSS_LEASE_CELLS`, whatever the
/// spec's tile, and a poll's slot takes the units within a worker's batch of the order; the
/// next worker gets the units right after, not the next spec tile hundreds of cells on. Full
/// mode leases the spec's tiles whole.
#[test]
fn fast_pss_leases_small_units_of_the_order_and_fill_a_batch_from_several() {
    use salient_coordinator::scheduler::FAST_PSS_LEASE_CELLS as UNIT;
    let json = |mode: &str| {
        format!(
            r#"{{"name": "t", "system": {{"kind": "henon-heiles", "energy": 0.125}},
                "grid": {{"cells": [40, 40], "tile": [20, 20], "mode": "{mode}"}},
                "sweep": {{"method": ["tm-sbab2c"], "tau": [0.5], "t_final": [200.0]}}}}"#
        )
    };
    let batch = 2 * UNIT + UNIT / 2;
    let cfg = Config {
        lease_cells_per_thread: batch,
        ..config()
    };
    let mut s = Scheduler::new(Store::open_in_memory().unwrap(), cfg).unwrap();
    let (job, _) = s.submit(&json("fast-pss")).unwrap();
    let order = spec::parse(&json("fast-pss"), true)
        .unwrap()
        .grid(0)
        .canonical()
        .to_vec();
    assert!(
        order.len() > 20 * 20 + batch,
        "the grid must hold more than a spec tile"
    );
    let (a, b) = (register(&mut s), register(&mut s));
    let poll = poll_leases;
    let first = poll(&mut s, &a);
    assert_eq!(first.len(), 3, "a batch of 2.5 units takes three leases");
    let cells: Vec<u32> = first.iter().flat_map(|l| l.cells.clone()).collect();
    assert_eq!(cells, order[..batch]);
    for (i, l) in first.iter().enumerate() {
        assert_eq!(l.lease.unwrap().tile as usize, i);
    }
    let second = poll(&mut s, &b);
    assert_eq!(
        second[0].cells[0],
        order[3 * UNIT],
        "the next unit after the leased ones"
    );
    assert!(second.iter().all(|l| l.lease.unwrap().job == job));

    let mut s = Scheduler::new(Store::open_in_memory().unwrap(), config()).unwrap();
    s.submit(&json("full")).unwrap();
    let w = register(&mut s);
    let full = poll(&mut s, &w);
    assert_eq!(full.len(), 1);
    assert_eq!(full[0].cells, order[..20 * 20]);
}

/// Fast PSS: what a running orbit crossed claims those cells as its outcome will: another
/// worker holding one is told to skip it, and the claim goes when the orbit stops. Crossings
/// of earlier cells, of a lease the worker does not hold, or of a cell outside the lease
/// change nothing.
#[test]
fn a_running_orbits_crossings_keep_other_workers_off_its_cells_until_it_stops() {
    let json = spec_json("fast-pss", r#""tm-sbab2c""#);
    let mut s = Scheduler::new(Store::open_in_memory().unwrap(), config()).unwrap();
    let (job, _) = s.submit(&json).unwrap();
    let (a, b) = (register(&mut s), register(&mut s));
    let (lease_a, lease_b) = (lease_one(&mut s, &a), lease_one(&mut s, &b));
    let (tile_a, tile_b) = (lease_a.lease.unwrap(), lease_b.lease.unwrap());
    assert!(tile_a.tile < tile_b.tile);
    let (running, target) = (lease_a.cells[0], lease_b.cells[0]);
    let poll = |s: &mut Scheduler, w: &str, held: v1::TileRef, crossings| {
        s.poll(&v1::PollRequest {
            worker_id: w.into(),
            held: vec![held],
            crossings,
            ..Default::default()
        })
        .unwrap()
    };
    let crossing = |lease: v1::TileRef, cell: u32, crossed: Vec<u32>, stopped| v1::Crossings {
        lease: Some(lease),
        cell,
        crossed,
        stopped,
    };
    let skipped = |reply: &v1::PollReply| -> Vec<u32> {
        reply.skips.iter().flat_map(|k| k.cells.clone()).collect()
    };
    let wanted = |s: &Scheduler| s.progress(job).unwrap().wanted_cells;
    let before = wanted(&s);
    // Ignored: b's orbit crossing an earlier cell; a naming b's lease; a cell not in the lease.
    let ignored = vec![
        crossing(tile_b, target, vec![running], false),
        crossing(tile_b, running, vec![target], false),
        crossing(tile_a, target, vec![lease_b.cells[1]], false),
    ];
    poll(&mut s, &a, tile_a, ignored.clone());
    assert!(skipped(&poll(&mut s, &b, tile_b, ignored[..1].to_vec())).is_empty());
    assert_eq!(wanted(&s), before);
    poll(
        &mut s,
        &a,
        tile_a,
        vec![crossing(tile_a, running, vec![target], false)],
    );
    assert_eq!(wanted(&s), before - 1);
    assert_eq!(skipped(&poll(&mut s, &b, tile_b, Vec::new())), vec![target]);
    poll(
        &mut s,
        &a,
        tile_a,
        vec![crossing(tile_a, running, Vec::new(), true)],
    );
    assert_eq!(wanted(&s), before);
}

/// Fast PSS: a worker gets the outcomes other workers reported in the run it holds leases
/// of that count (they commit or turn live; dropped ones never go), its own only when its mark
/// asks for them (a ledger made afresh), continuing from the mark it sends, so a reply it lost
/// comes again.
#[test]
fn outcomes_are_relayed_to_the_other_workers_from_their_marks() {
    let json = spec_json("fast-pss", r#""tm-sbab2c""#);
    let mut s = Scheduler::new(Store::open_in_memory().unwrap(), config()).unwrap();
    let (job, _) = s.submit(&json).unwrap();
    let (a, b) = (register(&mut s), register(&mut s));
    let lease_a = lease_one(&mut s, &a);
    let lease_b = lease_one(&mut s, &b);
    // The cells whose outcomes come to count, in the order they do, as a ledger of the run
    // tells them.
    let sp = spec::parse(&json, true).unwrap();
    let mut mirror = Ledger::new(&sp.grid(0), sp.mode(0));
    mirror.watch_outcomes();
    let mut counting = |outcomes: &[v1::Outcome]| -> Vec<u32> {
        let k = Expected::of_run(&sp.cell_run(0));
        for o in outcomes {
            mirror.offer(outcome_from_wire(o, &sp.grid(0), k).unwrap());
        }
        let mut cells: Vec<u32> = Vec::new();
        for news in mirror.take_outcome_news() {
            if let OutcomeNews::Counts(c) = news {
                if !cells.contains(&c) {
                    cells.push(c);
                }
            }
        }
        cells
    };
    let poll_marked =
        |s: &mut Scheduler, w: &str, held: &v1::Lease, reports, next: Option<u64>, own| {
            s.poll(&v1::PollRequest {
                worker_id: w.into(),
                held: vec![held.lease.unwrap()],
                reports,
                relayed: next
                    .map(|next| v1::RelayMark {
                        job,
                        run: 0,
                        next,
                        own,
                    })
                    .into_iter()
                    .collect(),
                ..Default::default()
            })
            .unwrap()
        };
    let poll = |s: &mut Scheduler, w: &str, held: &v1::Lease, reports, next: Option<u64>| {
        poll_marked(s, w, held, reports, next, false)
    };
    let relayed = |r: &v1::PollReply| -> Vec<(Vec<u32>, u64)> {
        r.relays
            .iter()
            .map(|x| {
                assert_eq!((x.job, x.run), (job, 0));
                let cell = |b: &prost::bytes::Bytes| {
                    <v1::Outcome as prost::Message>::decode(&b[..])
                        .unwrap()
                        .cell
                };
                (x.outcomes.iter().map(cell).collect(), x.next)
            })
            .collect()
    };
    // A's finished lease is relayed to B (which holds a lease of the run), not back to A.
    let mut report_a = work(&lease_a, &HashSet::new());
    report_a.finished = false;
    let cells_a = counting(&report_a.outcomes);
    assert!(!cells_a.is_empty());
    let n = cells_a.len() as u64;
    // A gets none of its own, only the mark past them.
    let r = poll(&mut s, &a, &lease_a, vec![report_a.clone()], None);
    assert_eq!(relayed(&r), vec![(vec![], n)]);
    let r = poll(&mut s, &b, &lease_b, vec![], None);
    assert_eq!(relayed(&r), vec![(cells_a.clone(), n)]);
    // Nothing new after the mark; everything again from an older one (a lost reply).
    assert!(relayed(&poll(&mut s, &b, &lease_b, vec![], Some(n))).is_empty());
    assert_eq!(
        relayed(&poll(&mut s, &b, &lease_b, vec![], Some(0))),
        vec![(cells_a.clone(), n)]
    );
    // A mark past the end cannot be this coordinator's: everything again.
    assert_eq!(
        relayed(&poll(&mut s, &b, &lease_b, vec![], Some(u64::MAX))),
        vec![(cells_a.clone(), n)]
    );
    // B's outcomes go to A, past A's own, which it skips but counts in the mark.
    let mut report_b = work(&lease_b, &HashSet::new());
    report_b.finished = false;
    let cells_b = counting(&report_b.outcomes);
    let reported = report_a.outcomes.len() + report_b.outcomes.len();
    assert!(
        cells_a.len() + cells_b.len() < reported,
        "some outcomes were dropped, and not relayed"
    );
    poll(&mut s, &b, &lease_b, vec![report_b], Some(n));
    let total = n + cells_b.len() as u64;
    assert_eq!(
        relayed(&poll(&mut s, &a, &lease_a, vec![], Some(0))),
        vec![(cells_b.clone(), total)]
    );
    // A ledger made afresh asks for its own as well.
    let all: Vec<u32> = cells_a.iter().chain(&cells_b).copied().collect();
    assert_eq!(
        relayed(&poll_marked(&mut s, &a, &lease_a, vec![], Some(0), true)),
        vec![(all, total)]
    );
}

#[test]
fn another_protocol_version_is_refused() {
    let mut s = Scheduler::new(Store::open_in_memory().unwrap(), config()).unwrap();
    let e = s
        .register(&v1::RegisterRequest {
            protocol_version: PROTOCOL_VERSION + 1,
            name: "old".into(),
            threads: 4,
        })
        .unwrap_err();
    assert_eq!(e.code(), Code::FailedPrecondition);
    assert!(e.message().contains("protocol version"), "{}", e.message());
    let e = s
        .poll(&v1::PollRequest {
            worker_id: "w1".into(),
            ..Default::default()
        })
        .unwrap_err();
    assert_eq!(e.code(), Code::NotFound);
}

#[test]
fn a_lapsed_lease_goes_to_another_worker_and_the_old_report_is_stale() {
    let mut s = Scheduler::new(
        Store::open_in_memory().unwrap(),
        Config {
            lease: Duration::from_millis(1),
            poll: Duration::from_millis(1),
            ..Config::default()
        },
    )
    .unwrap();
    let (job, _) = s.submit(&spec_json("full", r#""tm-sbab2c""#)).unwrap();
    let a = register(&mut s);
    let first = lease_one(&mut s, &a);
    std::thread::sleep(Duration::from_millis(5));
    s.tick();
    // (Worker a is forgotten too: silent for three lease periods. Its report still counts as
    // stale below, since reports are judged by attempt.)
    let b = register(&mut s);
    let second = lease_one(&mut s, &b);
    let (r1, r2) = (first.lease.unwrap(), second.lease.unwrap());
    assert_eq!(r1.key(), r2.key(), "the lapsed tile is leased again first");
    assert_eq!(r2.attempt, r1.attempt + 1);
    let before = s.status(Some(job)).unwrap();
    let a = register(&mut s);
    let reply = s
        .report(&v1::ReportRequest {
            worker_id: a.clone(),
            reports: vec![work(&first, &HashSet::new())],
        })
        .unwrap();
    assert_eq!(reply.stale, vec![r1]);
    assert!(reply.acknowledged.is_empty());
    let after = s.status(Some(job)).unwrap();
    assert_eq!(after.jobs[0].stale_reports, 1);
    assert_eq!(
        after.jobs[0].runs[0].resolved,
        before.jobs[0].runs[0].resolved
    );
    // The current attempt's report counts, and a repeat of it changes nothing (the orbits it
    // abandoned are counted as dropped once).
    let mut report = work(&second, &HashSet::new());
    report.abandoned_orbits = 2;
    report.abandoned_steps = 100;
    for _ in 0..2 {
        let reply = s
            .report(&v1::ReportRequest {
                worker_id: b.clone(),
                reports: vec![report.clone()],
            })
            .unwrap();
        assert_eq!(reply.acknowledged, vec![r2]);
    }
    let st = s.status(Some(job)).unwrap().jobs.remove(0);
    assert_eq!(st.runs[0].resolved, second.cells.len() as u64);
    assert_eq!(
        st.runs[0].dropped,
        first.cells.len() as u64 + 2,
        "stale + abandoned"
    );
}

#[test]
fn malformed_reports_are_refused_and_change_nothing() {
    let mut s = Scheduler::new(Store::open_in_memory().unwrap(), config()).unwrap();
    let (job, _) = s.submit(&spec_json("full", r#""tm-sbab2c""#)).unwrap();
    let w = register(&mut s);
    let lease = lease_one(&mut s, &w);
    let good = work(&lease, &HashSet::new());
    let tile = lease.lease.unwrap();
    let spec = spec::parse(&lease.spec_json, true).unwrap();
    let grid = salient_coordinator::scheduler::lease_grid(&spec, 0);
    let other_tile_cell = grid
        .canonical()
        .iter()
        .copied()
        .find(|&c| grid.tile_of(c) != Some(tile.tile as usize))
        .unwrap();
    let with = |f: &dyn Fn(&mut v1::TileReport)| {
        let mut r = good.clone();
        f(&mut r);
        r
    };
    let cases: Vec<(v1::TileReport, Code, &str)> = vec![
        (
            with(&|r| r.lease.as_mut().unwrap().job = 99),
            Code::InvalidArgument,
            "job",
        ),
        (
            with(&|r| r.lease.as_mut().unwrap().run = 5),
            Code::InvalidArgument,
            "run",
        ),
        (
            with(&|r| r.lease.as_mut().unwrap().tile = 10_000),
            Code::InvalidArgument,
            "tile",
        ),
        (
            with(&|r| r.lease.as_mut().unwrap().attempt = 9),
            Code::InvalidArgument,
            "attempt",
        ),
        (with(&|r| r.lease = None), Code::InvalidArgument, "lease"),
        (
            with(&|r| r.outcomes[0].cell = 1_000_000),
            Code::InvalidArgument,
            "outcome.cell",
        ),
        (
            with(&|r| r.outcomes[0].cell = other_tile_cell),
            Code::InvalidArgument,
            "tile",
        ),
        (
            with(&|r| r.outcomes[0].visited = vec![u32::MAX]),
            Code::InvalidArgument,
            "visited",
        ),
        (
            with(&|r| r.outcomes[0].status = 77),
            Code::InvalidArgument,
            "status",
        ),
        (
            with(&|r| r.outcomes[0].checkpoints.clear()),
            Code::InvalidArgument,
            "checkpoints",
        ),
    ];
    let before = snapshot(&s, job);
    for (report, code, field) in cases {
        // A bad report spoils the whole request, even next to a good one.
        let e = s
            .report(&v1::ReportRequest {
                worker_id: w.clone(),
                reports: vec![good.clone(), report],
            })
            .unwrap_err();
        assert_eq!(e.code(), code, "{field}: {}", e.message());
        assert!(
            e.message().contains(field),
            "'{}' does not name {field}",
            e.message()
        );
        assert_eq!(snapshot(&s, job), before, "{field}");
    }
}

#[test]
fn cancelling_revokes_leases_and_stops_leasing() {
    let mut s = Scheduler::new(Store::open_in_memory().unwrap(), config()).unwrap();
    let (job, _) = s.submit(&spec_json("full", r#""tm-sbab2c""#)).unwrap();
    let w = register(&mut s);
    let lease = lease_one(&mut s, &w);
    assert_eq!(s.cancel(job).unwrap(), "cancelled");
    let reply = s
        .poll(&v1::PollRequest {
            worker_id: w.clone(),
            free_slots: 2,
            held: vec![lease.lease.unwrap()],
            ..Default::default()
        })
        .unwrap();
    assert_eq!(reply.revoked, vec![lease.lease.unwrap()]);
    assert!(reply.leases.is_empty());
    assert!(s.is_finished(job).unwrap());
    assert_eq!(s.cancel(job).unwrap(), "cancelled", "cancel is idempotent");
    assert_eq!(s.cancel(12345).unwrap_err().code(), Code::NotFound);
}

#[test]
fn bad_specs_from_the_wire_are_refused_with_the_field_named() {
    let mut s = Scheduler::new(Store::open_in_memory().unwrap(), config()).unwrap();
    for (json, field) in [
        (spec_json("fast-pss", r#""tm-nope""#), "sweep.method"),
        (spec_json("sideways", r#""tm-sbab2c""#), "grid.mode"),
        ("{".to_string(), "JSON"),
        (
            spec_json("full", r#""tm-sbab2c""#).replace(r#""t""#, r#""..""#),
            "name",
        ),
        (
            spec_json("full", r#""tm-sbab2c""#).replace(
                r#""name": "t""#,
                &format!(r#""name": "{}""#, "y".repeat(65_536)),
            ),
            "name",
        ),
    ] {
        let e = s.submit(&json).unwrap_err();
        assert_eq!(e.code(), Code::InvalidArgument);
        assert!(e.message().contains(field), "{}", e.message());
        assert!(
            e.message().len() < 1000,
            "the message quotes a long input in part"
        );
    }
    assert!(s.status(None).unwrap().jobs.is_empty());
}

/// Cells × runs are capped per job: every run keeps its ledger in the coordinator's memory.
#[test]
fn a_job_over_the_cells_times_runs_cap_is_refused() {
    let mut s = Scheduler::new(
        Store::open_in_memory().unwrap(),
        Config {
            max_cell_runs: 14 * 12,
            ..config()
        },
    )
    .unwrap();
    let one = spec_json("full", r#""tm-sbab2c""#);
    s.submit(&one).unwrap();
    let two = spec_json("full", r#""tm-sbab2c", "tm-sbab2""#);
    let e = s.submit(&two).unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument);
    assert!(e.message().contains("--max-cell-runs"), "{}", e.message());
    assert_eq!(s.status(None).unwrap().jobs.len(), 1);
}

/// A poll's reply goes out before its group is committed, so the answers to the reports it
/// carried come with a later reply, once the group is durable, and only once.
#[test]
fn answers_to_a_grouped_poll_wait_until_its_group_is_durable() {
    let json = spec_json("full", r#""tm-sbab2c""#);
    let mut s = Scheduler::new(Store::open_in_memory().unwrap(), config()).unwrap();
    s.submit(&json).unwrap();
    let w = register(&mut s);
    let lease = lease_one(&mut s, &w);
    let poll = |s: &mut Scheduler, reports: Vec<v1::TileReport>| {
        s.poll(&v1::PollRequest {
            worker_id: w.clone(),
            reports,
            ..Default::default()
        })
        .unwrap()
    };
    s.begin_group();
    let reply = poll(&mut s, vec![work(&lease, &HashSet::new())]);
    assert!(reply.acknowledged.is_empty() && reply.stale.is_empty());
    s.commit_group(Vec::new());
    s.sync_store();
    let reply = poll(&mut s, Vec::new());
    assert_eq!(reply.acknowledged, vec![lease.lease.unwrap()]);
    assert!(poll(&mut s, Vec::new()).acknowledged.is_empty());
}

/// Leases are answered before their attempt is committed, so after a restart the number
/// after the stored one may be held by a worker: it is never issued again, and a worker
/// naming either gets its lease back.
#[test]
fn a_restarted_scheduler_never_issues_an_attempt_number_twice() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("c.db");
    let json = spec_json("full", r#""tm-sbab2c""#);
    let first = {
        let mut s = Scheduler::new(Store::open(&db).unwrap(), config()).unwrap();
        s.submit(&json).unwrap();
        let w = register(&mut s);
        lease_one(&mut s, &w).lease.unwrap()
    };
    assert_eq!(first.attempt, 1);
    for named in [1, 2] {
        let mut s = Scheduler::new(Store::open(&db).unwrap(), config()).unwrap();
        let w = register(&mut s);
        let reply = s
            .poll(&v1::PollRequest {
                worker_id: w.clone(),
                held: vec![v1::TileRef {
                    attempt: named,
                    ..first
                }],
                ..Default::default()
            })
            .unwrap();
        assert!(reply.revoked.is_empty(), "attempt {named} taken back");
    }
    let mut s = Scheduler::new(Store::open(&db).unwrap(), config()).unwrap();
    let w = register(&mut s);
    let again = lease_one(&mut s, &w).lease.unwrap();
    assert_eq!((again.tile, again.attempt), (first.tile, 3));
    let other = register(&mut s);
    let stale = s
        .poll(&v1::PollRequest {
            worker_id: other,
            held: vec![v1::TileRef {
                attempt: 2,
                ..first
            }],
            ..Default::default()
        })
        .unwrap();
    assert_eq!(stale.revoked.len(), 1);
}

/// The progress guarantee: a worker that returns the same fast-PSS tile without an outcome
/// lease after lease (a worker that cannot settle it) stalls the run; then the tile goes to
/// another worker, and back to the first only when it is the one left.
#[test]
fn a_tile_returned_empty_again_and_again_goes_to_another_worker() {
    let json = spec_json("fast-pss", r#""tm-sbab2c""#);
    let mut s = Scheduler::new(Store::open_in_memory().unwrap(), config()).unwrap();
    let (job, _) = s.submit(&json).unwrap();
    let (a, b) = (register(&mut s), register(&mut s));
    let empty = |lease: &v1::Lease| v1::ReportRequest {
        worker_id: a.clone(),
        reports: vec![v1::TileReport {
            lease: lease.lease,
            finished: true,
            ..Default::default()
        }],
    };
    let first = lease_one(&mut s, &a);
    let stuck = first.lease.unwrap().key();
    let mut lease = first;
    // Under the threshold the worker keeps getting the tile back (it is the frontier's).
    for _ in 0..31 {
        s.report(&empty(&lease)).unwrap();
        lease = lease_one(&mut s, &a);
        assert_eq!(lease.lease.unwrap().key(), stuck);
    }
    s.report(&empty(&lease)).unwrap();
    let other = lease_one(&mut s, &a);
    assert_ne!(
        other.lease.unwrap().key(),
        stuck,
        "the stalled tile is left to others"
    );
    let taken = lease_one(&mut s, &b);
    assert_eq!(taken.lease.unwrap().key(), stuck, "another worker gets it");
    // Its outcome moves the run on: the stall ends.
    s.report(&v1::ReportRequest {
        worker_id: b.clone(),
        reports: vec![work(&taken, &HashSet::new())],
    })
    .unwrap();
    let st = s.status(Some(job)).unwrap().jobs.remove(0);
    assert!(st.runs[0].resolved > 0);
}

/// With one worker left the stalled tile still goes to it: leaving it unleased would stop the
/// run for good.
#[test]
fn a_stalled_tile_goes_back_to_the_only_worker() {
    let json = spec_json("fast-pss", r#""tm-sbab2c""#);
    let mut s = Scheduler::new(Store::open_in_memory().unwrap(), config()).unwrap();
    s.submit(&json).unwrap();
    let a = register(&mut s);
    let mut lease = lease_one(&mut s, &a);
    let stuck = lease.lease.unwrap().key();
    for _ in 0..40 {
        s.report(&v1::ReportRequest {
            worker_id: a.clone(),
            reports: vec![v1::TileReport {
                lease: lease.lease,
                finished: true,
                ..Default::default()
            }],
        })
        .unwrap();
        lease = lease_one(&mut s, &a);
        assert_eq!(lease.lease.unwrap().key(), stuck);
    }
}
