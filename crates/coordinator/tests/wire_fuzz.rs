//! Fuzzing the coordinator's request handlers with proptest: arbitrary bytes decoded as each
//! request message, and structured reports with random fields, never panic; a refused request
//! leaves the state exactly as it was. `scripts/fuzz.sh` runs these with many more cases.

use proptest::prelude::*;
use prost::Message;
use salient_coordinator::scheduler::{Config, Scheduler};
use salient_proto::v1;
use salient_proto::PROTOCOL_VERSION;
use salient_store::Store;

const SPEC: &str = r#"{"name": "f", "system": {"kind": "henon-heiles", "energy": 0.125},
    "grid": {"cells": [12, 10], "tile": [4, 5], "mode": "fast-pss"},
    "sweep": {"method": ["tm-sbab2c"], "tau": [0.5], "t_final": [50.0]}}"#;

/// A scheduler with one job, one worker and one live lease.
fn setup() -> (Scheduler, String, v1::Lease) {
    let mut s = Scheduler::new(Store::open_in_memory().unwrap(), Config::default()).unwrap();
    s.submit(SPEC).unwrap();
    let w = s
        .register(&v1::RegisterRequest {
            protocol_version: PROTOCOL_VERSION,
            name: "fuzz".into(),
            threads: 1,
        })
        .unwrap()
        .worker_id;
    let lease = s
        .poll(&v1::PollRequest {
            worker_id: w.clone(),
            free_slots: 1,
            ..Default::default()
        })
        .unwrap()
        .leases
        .remove(0);
    (s, w, lease)
}

/// Everything observable about the state, without clocks.
fn snapshot(s: &Scheduler) -> String {
    let mut st = s.status(None).unwrap();
    for j in &mut st.jobs {
        for r in &mut j.runs {
            r.wall_s = 0.0;
            r.orbits_per_s = 0.0;
            r.eta_s = None;
        }
        j.orbits_per_s = 0.0;
    }
    format!("{st:?}")
}

fn outcome() -> impl Strategy<Value = v1::Outcome> {
    (
        0u32..130,
        -1i32..5,
        -1i32..8,
        prop_oneof![Just(f64::NAN), Just(f64::INFINITY), Just(-1.0), 0.0..1.5f64],
        proptest::collection::vec(0u32..140, 0..6),
        any::<u64>(),
        proptest::collection::vec(-1i32..5, 0..3),
        prop_oneof![Just(f64::NAN), Just(-1.0), 0.0..100.0f64],
        proptest::option::of(any::<f64>()),
    )
        .prop_map(
            |(cell, class, status, sali, visited, steps, checkpoints, t_end, indicator)| {
                v1::Outcome {
                    cell,
                    class,
                    status,
                    sali,
                    visited,
                    steps,
                    checkpoints,
                    t_end,
                    indicators: indicator.map(|x| v1::CellIndicators {
                        mle: x,
                        megno: x,
                        megno_mean: x,
                        fli: x,
                    }),
                }
            },
        )
}

fn report(lease: v1::TileRef) -> impl Strategy<Value = v1::TileReport> {
    (
        prop_oneof![Just(lease.job), 0u64..4],
        prop_oneof![Just(lease.run), 0u32..3],
        prop_oneof![Just(lease.tile), 0u32..8],
        prop_oneof![Just(lease.attempt), 0u32..4],
        proptest::collection::vec(outcome(), 0..4),
        any::<bool>(),
        any::<bool>(),
    )
        .prop_map(
            |(job, run, tile, attempt, outcomes, finished, has_lease)| v1::TileReport {
                lease: has_lease.then_some(v1::TileRef {
                    job,
                    run,
                    tile,
                    attempt,
                }),
                outcomes,
                finished,
                cpu_ns: 1,
                abandoned_orbits: 0,
                abandoned_steps: 0,
            },
        )
}

/// `PROPTEST_CASES` when set (scripts/fuzz.sh), else a count that keeps the suite quick.
fn cases(default: u32) -> u32 {
    std::env::var("PROPTEST_CASES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

proptest! {
    #![proptest_config(ProptestConfig { cases: cases(128), ..ProptestConfig::default() })]

    #[test]
    fn arbitrary_bytes_as_requests_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..300)) {
        let (mut s, w, _) = setup();
        let before = snapshot(&s);
        let refused = |r: Result<(), tonic::Status>, s: &Scheduler| {
            if r.is_err() {
                assert_eq!(snapshot(s), before);
            }
        };
        if let Ok(mut r) = v1::PollRequest::decode(bytes.as_slice()) {
            r.worker_id = w.clone();
            let out = s.poll(&r).map(|_| ());
            refused(out, &s);
        }
        if let Ok(mut r) = v1::ReportRequest::decode(bytes.as_slice()) {
            r.worker_id = w.clone();
            let out = s.report(&r).map(|_| ());
            refused(out, &s);
        }
        if let Ok(r) = v1::RegisterRequest::decode(bytes.as_slice()) {
            let _ = s.register(&r);
        }
        if let Some(text) = v1::SubmitRequest::decode(bytes.as_slice())
            .ok()
            .and_then(|r| String::from_utf8(r.spec_json).ok())
        {
            let out = s.submit(&text).map(|_| ());
            refused(out, &s);
        }
        if let Ok(r) = v1::StatusRequest::decode(bytes.as_slice()) {
            let _ = s.status(r.job);
        }
        if let Ok(r) = v1::CancelRequest::decode(bytes.as_slice()) {
            let _ = s.cancel(r.job);
        }
        if let Ok(r) = v1::ResultsRequest::decode(bytes.as_slice()) {
            let _ = s.results(r.job, 16);
        }
    }

    #[test]
    fn random_reports_are_applied_whole_or_refused_without_a_trace(
        reports in proptest::collection::vec(report(v1::TileRef { job: 1, run: 0, tile: 0, attempt: 1 }), 1..4)
    ) {
        let (mut s, w, lease) = setup();
        // Aim half the reports at the real lease.
        let reports: Vec<v1::TileReport> = reports
            .into_iter()
            .enumerate()
            .map(|(k, mut r)| {
                if k % 2 == 0 {
                    r.lease = lease.lease;
                }
                r
            })
            .collect();
        let before = snapshot(&s);
        match s.report(&v1::ReportRequest { worker_id: w.clone(), reports }) {
            Ok(reply) => prop_assert!(!reply.acknowledged.is_empty() || !reply.stale.is_empty()),
            Err(e) => {
                prop_assert_eq!(e.code(), tonic::Code::InvalidArgument);
                prop_assert_eq!(snapshot(&s), before);
            }
        }
    }
}
