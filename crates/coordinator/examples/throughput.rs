//! Coordinator throughput with synthetic workers: outcomes committed per second through the
//! scheduler (validation, SQLite commit with synchronous=FULL, ledger) and CPU per outcome,
//! without networking or integration.
//!
//! cargo run --release -p salient-coordinator --example throughput -- [full|fast-pss] [visited] [group] [jobs] [workers]
//!
//! `group` polls share one store transaction, as the event loop groups the events that queued
//! up while it worked (1: a transaction per poll). `jobs` (default 10) runs the same job that
//! many times in a row, so the figure covers seconds rather than one job's tens of
//! milliseconds. `workers` (default 8) synthetic workers take turns; in fast PSS each
//! outcome is relayed to every other worker of the run, so the relay grows with them.

use salient_coordinator::scheduler::{Config, Scheduler};
use salient_grid::spec;
use salient_proto::v1;
use salient_proto::PROTOCOL_VERSION;
use salient_store::Store;
use std::time::Instant;

fn cpu_seconds() -> f64 {
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    let rest = stat.rsplit_once(')').map_or("", |(_, r)| r);
    // After the command's closing parenthesis come the state (field 3), ..., utime (14) and
    // stime (15): indices 11 and 12 of what follows. The state is not a number, so the
    // fields are indexed before they are parsed (filtering out what does not parse shifted
    // them by one and read stime and cutime, the system time alone).
    let f: Vec<&str> = rest.split_whitespace().collect();
    let field = |i: usize| f.get(i).and_then(|x| x.parse::<f64>().ok());
    field(11)
        .zip(field(12))
        .map_or(f64::NAN, |(u, s)| (u + s) / 100.0)
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let mode = args.get(1).map_or("full", |s| s.as_str()).to_string();
    let visited: usize = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(0);
    let group: usize = args.get(3).and_then(|s| s.parse().ok()).unwrap_or(8).max(1);
    let jobs: usize = args
        .get(4)
        .and_then(|s| s.parse().ok())
        .unwrap_or(10)
        .max(1);
    let n_workers: usize = args.get(5).and_then(|s| s.parse().ok()).unwrap_or(8).max(1);
    let json = format!(
        r#"{{"name": "bench", "system": {{"kind": "henon-heiles", "energy": 0.125}},
            "grid": {{"cells": [400, 400], "tile": [20, 20], "mode": "{mode}"}},
            "sweep": {{"method": ["tm-sbab2c"], "tau": [0.5], "t_final": [1e4]}}}}"#
    );
    let job_spec = spec::parse(&json, true).unwrap();
    let grid = job_spec.grid(0);
    let checkpoints = job_spec.cell_run(0).checkpoint_steps().len();
    let dir = tempfile::tempdir().unwrap();
    let store = Store::open(&dir.path().join("bench.db")).unwrap();
    let mut s = Scheduler::new(store, Config::default()).unwrap();
    let workers: Vec<String> = (0..n_workers)
        .map(|_| {
            s.register(&v1::RegisterRequest {
                protocol_version: PROTOCOL_VERSION,
                name: "synthetic".into(),
                threads: 16,
            })
            .unwrap()
            .worker_id
        })
        .collect();
    let compatible: Vec<u32> = grid.canonical().to_vec();
    let fake = |cell: u32| {
        // Visited cells spread over the grid, sorted: like a chaotic orbit's crossings.
        let pos = grid.position(cell).unwrap();
        let mut v: Vec<u32> = (1..=visited)
            .map(|k| compatible[(pos * 7919 + k * 104_729) % compatible.len()])
            .collect();
        v.sort_unstable();
        v.dedup();
        v1::Outcome {
            cell,
            class: 1,
            status: 1,
            sali: 0.5,
            visited: v,
            steps: 20_000,
            checkpoints: vec![1; checkpoints],
            t_end: 1e4,
            indicators: None,
        }
    };
    // Fabricated before the clock starts: sorting a visited list is a worker's work, and was a
    // tenth of this process's CPU when it was done per report.
    let mut fakes: Vec<Option<v1::Outcome>> = vec![None; grid.cells()];
    for &c in &compatible {
        fakes[c as usize] = Some(fake(c));
    }
    let mut held: Vec<Vec<v1::Lease>> = vec![Vec::new(); workers.len()];
    // Each worker's relay marks, sent back with every poll as a real worker does: without
    // them every poll would be answered with the run's relay log from its start.
    let mut marks: Vec<Vec<v1::RelayMark>> = vec![Vec::new(); workers.len()];
    let mut relayed = 0u64;
    let (t0, c0) = (Instant::now(), cpu_seconds());
    let (mut outcomes, mut reports_sent) = (0u64, 0u64);
    let mut k = 0;
    for _ in 0..jobs {
        let (job, _) = s.submit(&json).unwrap();
        while !s.is_finished(job).unwrap() {
            if k % group == 0 {
                s.begin_group();
            }
            let w = k % workers.len();
            k += 1;
            // Every lease the last reply brought, reported finished: a fast-PSS poll may
            // bring a batch of several lease units.
            let reports: Vec<v1::TileReport> = std::mem::take(&mut held[w])
                .into_iter()
                .map(|l| {
                    outcomes += l.cells.len() as u64;
                    v1::TileReport {
                        lease: l.lease,
                        outcomes: l
                            .cells
                            .iter()
                            .map(|&c| {
                                fakes[c as usize]
                                    .clone()
                                    .expect("leased cells are compatible")
                            })
                            .collect(),
                        finished: true,
                        ..Default::default()
                    }
                })
                .collect();
            reports_sent += reports.len() as u64;
            let reply = s
                .poll(&v1::PollRequest {
                    worker_id: workers[w].clone(),
                    free_slots: 1,
                    reports,
                    relayed: marks[w].clone(),
                    ..Default::default()
                })
                .unwrap();
            held[w] = reply.leases;
            for r in reply.relays {
                relayed += r.outcomes.len() as u64;
                match marks[w]
                    .iter_mut()
                    .find(|m| (m.job, m.run) == (r.job, r.run))
                {
                    Some(m) => m.next = r.next,
                    None => marks[w].push(v1::RelayMark {
                        job: r.job,
                        run: r.run,
                        next: r.next,
                        own: false,
                    }),
                }
            }
            if k % group == 0 {
                s.commit_group(Vec::new());
            }
        }
    }
    if k % group != 0 {
        s.commit_group(Vec::new());
    }
    // Every group committed: the store thread commits behind the loop.
    s.sync_store();
    let (wall, cpu) = (t0.elapsed().as_secs_f64(), cpu_seconds() - c0);
    println!(
        "mode {mode}, {visited} visited per outcome, {group} polls per transaction, {jobs} jobs, \
         {n_workers} workers: \
         {outcomes} outcomes in {reports_sent} reports ({relayed} relayed to other workers), \
         {wall:.2} s wall, {:.0} outcomes/s, {:.1} µs CPU per outcome, {:.2} ms per report",
        outcomes as f64 / wall,
        1e6 * cpu / outcomes as f64,
        1e3 * wall / reports_sent as f64
    );
}
