//! The store through its public API: job life cycle, reports, attempts, counters, reopening.

use std::collections::BTreeMap;

use salient_store::{
    JobRow, JobState, Report, RunTotals, Store, StoreError, StoredOutcome, SCHEMA_VERSION,
};

fn report<'a>(
    job: u64,
    run: u32,
    tile: u32,
    attempt: u32,
    outcomes: &'a [(u32, &'a [u8])],
) -> Report<'a> {
    Report {
        job,
        run,
        tile,
        attempt,
        worker: "worker-1",
        cpu_ns: 1_000,
        outcomes,
    }
}

fn cells(outcomes: &[StoredOutcome]) -> Vec<u32> {
    outcomes.iter().map(|o| o.cell).collect()
}

#[test]
fn job_state_text_round_trips() {
    let all = [
        JobState::Queued,
        JobState::Running,
        JobState::Done,
        JobState::Cancelled,
        JobState::Failed,
    ];
    let texts: Vec<&str> = all.iter().map(|s| s.as_str()).collect();
    assert_eq!(texts, ["queued", "running", "done", "cancelled", "failed"]);
    for s in all {
        assert_eq!(JobState::parse(s.as_str()), Some(s));
    }
    assert_eq!(JobState::parse("Done"), None);
    assert_eq!(JobState::parse(""), None);
    let terminal: Vec<bool> = all.iter().map(|s| s.is_terminal()).collect();
    assert_eq!(terminal, [false, false, true, true, true]);
}

#[test]
fn new_job_is_queued_with_increasing_ids() {
    let mut store = Store::open_in_memory().unwrap();
    let a = store.insert_job("first", "spec-a", 100).unwrap();
    let b = store.insert_job("second", "spec-b", 200).unwrap();
    assert!(b > a);
    assert_eq!(
        store.job(a).unwrap(),
        Some(JobRow {
            id: a,
            name: "first".into(),
            spec: "spec-a".into(),
            state: JobState::Queued,
            submitted_ms: 100,
            started_ms: None,
            finished_ms: None,
            error: None,
        })
    );
    assert_eq!(store.job(b + 1).unwrap(), None);
    assert_eq!(store.job(u64::MAX).unwrap(), None);
    let ids: Vec<u64> = store.jobs().unwrap().iter().map(|j| j.id).collect();
    assert_eq!(ids, [a, b]);
}

#[test]
fn started_and_finished_are_set_exactly_once() {
    let mut store = Store::open_in_memory().unwrap();
    let job = store.insert_job("j", "", 100).unwrap();

    assert!(store
        .set_job_state(job, JobState::Running, 200, None)
        .unwrap());
    let row = store.job(job).unwrap().unwrap();
    assert_eq!(
        (row.state, row.started_ms, row.finished_ms),
        (JobState::Running, Some(200), None)
    );

    // Back to the queue (e.g. a coordinator restart) and running again: still the first start.
    assert!(store
        .set_job_state(job, JobState::Queued, 250, None)
        .unwrap());
    assert!(store
        .set_job_state(job, JobState::Running, 300, None)
        .unwrap());
    let row = store.job(job).unwrap().unwrap();
    assert_eq!(
        (row.state, row.started_ms, row.finished_ms),
        (JobState::Running, Some(200), None)
    );

    assert!(store.set_job_state(job, JobState::Done, 400, None).unwrap());
    let row = store.job(job).unwrap().unwrap();
    assert_eq!(
        (row.state, row.started_ms, row.finished_ms),
        (JobState::Done, Some(200), Some(400))
    );
    assert_eq!(row.error, None);

    // A second terminal move keeps the first finish time; its error text is stored.
    assert!(store
        .set_job_state(job, JobState::Failed, 500, Some("disk full"))
        .unwrap());
    let row = store.job(job).unwrap().unwrap();
    assert_eq!(
        (row.state, row.started_ms, row.finished_ms),
        (JobState::Failed, Some(200), Some(400))
    );
    assert_eq!(row.error.as_deref(), Some("disk full"));

    // `None` keeps the error already stored.
    assert!(store
        .set_job_state(job, JobState::Failed, 600, None)
        .unwrap());
    assert_eq!(
        store.job(job).unwrap().unwrap().error.as_deref(),
        Some("disk full")
    );
    assert_eq!(store.job(job).unwrap().unwrap().submitted_ms, 100);
}

#[test]
fn cancelling_a_queued_job_finishes_it_without_a_start() {
    let mut store = Store::open_in_memory().unwrap();
    let job = store.insert_job("j", "", 10).unwrap();
    assert!(store
        .set_job_state(job, JobState::Cancelled, 20, None)
        .unwrap());
    let row = store.job(job).unwrap().unwrap();
    assert_eq!(
        (row.state, row.started_ms, row.finished_ms),
        (JobState::Cancelled, None, Some(20))
    );
}

#[test]
fn setting_the_state_of_an_unknown_job_reports_false() {
    let mut store = Store::open_in_memory().unwrap();
    let job = store.insert_job("j", "", 10).unwrap();
    assert!(!store
        .set_job_state(job + 1, JobState::Running, 20, None)
        .unwrap());
    assert!(!store
        .set_job_state(u64::MAX, JobState::Done, 20, None)
        .unwrap());
    assert_eq!(store.job(job).unwrap().unwrap().state, JobState::Queued);
}

#[test]
fn unfinished_jobs_are_the_queued_and_running_ones() {
    let mut store = Store::open_in_memory().unwrap();
    let ids: Vec<u64> = (0..6)
        .map(|i| store.insert_job(&format!("j{i}"), "", i).unwrap())
        .collect();
    store
        .set_job_state(ids[0], JobState::Done, 10, None)
        .unwrap();
    store
        .set_job_state(ids[1], JobState::Running, 10, None)
        .unwrap();
    store
        .set_job_state(ids[2], JobState::Cancelled, 10, None)
        .unwrap();
    store
        .set_job_state(ids[3], JobState::Failed, 10, Some("boom"))
        .unwrap();
    // ids[4] stays queued.
    store
        .set_job_state(ids[5], JobState::Running, 10, None)
        .unwrap();

    let unfinished = store.unfinished_jobs().unwrap();
    let got: Vec<(u64, JobState)> = unfinished.iter().map(|j| (j.id, j.state)).collect();
    assert_eq!(
        got,
        [
            (ids[1], JobState::Running),
            (ids[4], JobState::Queued),
            (ids[5], JobState::Running)
        ]
    );
    assert_eq!(store.jobs().unwrap().len(), 6);
}

#[test]
fn a_cell_keeps_its_first_outcome() {
    let mut store = Store::open_in_memory().unwrap();
    let job = store.insert_job("j", "", 0).unwrap();

    let first: [(u32, &[u8]); 3] = [(1, b"one"), (2, b"two"), (3, b"three")];
    assert_eq!(
        store.commit_report(&report(job, 0, 0, 1, &first)).unwrap(),
        3
    );

    // A retry of the same report adds nothing.
    assert_eq!(
        store.commit_report(&report(job, 0, 0, 1, &first)).unwrap(),
        0
    );

    // A later attempt overlapping cell 3 with a different blob: only cell 4 is new.
    let second: [(u32, &[u8]); 2] = [(3, b"THREE"), (4, b"four")];
    assert_eq!(
        store.commit_report(&report(job, 0, 0, 2, &second)).unwrap(),
        1
    );

    let stored = store.outcomes(job, 0).unwrap();
    let pairs: Vec<(u32, &[u8])> = stored.iter().map(|o| (o.cell, o.data.as_slice())).collect();
    assert_eq!(
        pairs,
        [(1, &b"one"[..]), (2, b"two"), (3, b"three"), (4, b"four")]
    );

    assert_eq!(
        store.run_totals(job, 0).unwrap(),
        RunTotals {
            cpu_ns: 3_000,
            reports: 3,
            outcomes: 4
        }
    );
}

#[test]
fn duplicate_cells_within_one_report_count_once() {
    let mut store = Store::open_in_memory().unwrap();
    let job = store.insert_job("j", "", 0).unwrap();
    let outcomes: [(u32, &[u8]); 3] = [(5, b"a"), (5, b"b"), (6, b"")];
    assert_eq!(
        store
            .commit_report(&report(job, 0, 0, 1, &outcomes))
            .unwrap(),
        2
    );
    assert_eq!(
        store.outcomes(job, 0).unwrap(),
        [
            StoredOutcome {
                cell: 5,
                data: b"a".to_vec()
            },
            StoredOutcome {
                cell: 6,
                data: Vec::new()
            },
        ]
    );
}

#[test]
fn outcomes_come_back_in_insertion_order() {
    let mut store = Store::open_in_memory().unwrap();
    let job = store.insert_job("j", "", 0).unwrap();
    let a: [(u32, &[u8]); 3] = [(90, b"x"), (20, b"y"), (70, b"z")];
    let b: [(u32, &[u8]); 3] = [(10, b"p"), (20, b"q"), (50, b"r")];
    let c: [(u32, &[u8]); 1] = [(0, b"s")];
    store.commit_report(&report(job, 0, 3, 1, &a)).unwrap();
    store.commit_report(&report(job, 0, 1, 1, &b)).unwrap();
    store.commit_report(&report(job, 0, 0, 1, &c)).unwrap();
    assert_eq!(
        cells(&store.outcomes(job, 0).unwrap()),
        [90, 20, 70, 10, 50, 0]
    );
}

#[test]
fn runs_and_jobs_are_kept_apart() {
    let mut store = Store::open_in_memory().unwrap();
    let j1 = store.insert_job("j1", "", 0).unwrap();
    let j2 = store.insert_job("j2", "", 0).unwrap();
    let outcomes: [(u32, &[u8]); 2] = [(1, b"a"), (2, b"b")];
    assert_eq!(
        store
            .commit_report(&report(j1, 0, 0, 1, &outcomes))
            .unwrap(),
        2
    );
    // The same cells in another run and in another job are new there.
    assert_eq!(
        store
            .commit_report(&report(j1, 1, 0, 1, &outcomes))
            .unwrap(),
        2
    );
    assert_eq!(
        store
            .commit_report(&report(j2, 0, 0, 1, &outcomes))
            .unwrap(),
        2
    );
    assert_eq!(cells(&store.outcomes(j1, 0).unwrap()), [1, 2]);
    assert_eq!(cells(&store.outcomes(j1, 1).unwrap()), [1, 2]);
    assert_eq!(cells(&store.outcomes(j2, 0).unwrap()), [1, 2]);
    assert!(store.outcomes(j2, 1).unwrap().is_empty());
    assert_eq!(store.run_totals(j2, 1).unwrap(), RunTotals::default());
    assert_eq!(
        store.run_totals(j1, 1).unwrap(),
        RunTotals {
            cpu_ns: 1_000,
            reports: 1,
            outcomes: 2
        }
    );
}

#[test]
fn run_totals_count_reports_without_new_outcomes() {
    let mut store = Store::open_in_memory().unwrap();
    let job = store.insert_job("j", "", 0).unwrap();
    let outcomes: [(u32, &[u8]); 1] = [(1, b"a")];
    let mut r = report(job, 0, 0, 1, &outcomes);
    r.cpu_ns = 7;
    store.commit_report(&r).unwrap();
    r.attempt = 2;
    r.cpu_ns = 11;
    store.commit_report(&r).unwrap();
    let empty: [(u32, &[u8]); 0] = [];
    let mut e = report(job, 0, 1, 1, &empty);
    e.cpu_ns = 3;
    assert_eq!(store.commit_report(&e).unwrap(), 0);
    assert_eq!(
        store.run_totals(job, 0).unwrap(),
        RunTotals {
            cpu_ns: 21,
            reports: 3,
            outcomes: 1
        }
    );
}

#[test]
fn a_report_for_an_unknown_job_fails_and_stores_nothing() {
    let mut store = Store::open_in_memory().unwrap();
    let job = store.insert_job("j", "", 0).unwrap();
    let outcomes: [(u32, &[u8]); 2] = [(1, b"a"), (2, b"b")];
    let err = store
        .commit_report(&report(job + 1, 0, 0, 1, &outcomes))
        .unwrap_err();
    assert!(matches!(err, StoreError::Sqlite(_)), "{err:?}");
    assert!(
        err.to_string().to_lowercase().contains("foreign key"),
        "{err}"
    );
    assert!(store.outcomes(job + 1, 0).unwrap().is_empty());
    assert_eq!(store.run_totals(job + 1, 0).unwrap(), RunTotals::default());

    // The known job is untouched and still accepts the same cells.
    assert_eq!(
        store
            .commit_report(&report(job, 0, 0, 1, &outcomes))
            .unwrap(),
        2
    );
}

#[test]
fn attempts_keep_the_latest_number_per_tile() {
    let mut store = Store::open_in_memory().unwrap();
    let job = store.insert_job("j", "", 0).unwrap();
    let other = store.insert_job("other", "", 0).unwrap();
    store.record_attempt(job, 1, 5, 1, "w1").unwrap();
    store.record_attempt(job, 0, 9, 1, "w1").unwrap();
    store.record_attempt(job, 0, 2, 1, "w2").unwrap();
    store.record_attempt(job, 0, 9, 2, "w2").unwrap();
    store.record_attempt(job, 0, 9, 3, "w3").unwrap();
    // A late write of an older attempt does not roll the number back.
    store.record_attempt(job, 0, 9, 2, "w2").unwrap();
    store.record_attempt(other, 0, 0, 7, "w1").unwrap();

    assert_eq!(
        store.attempts(job).unwrap(),
        [(0, 2, 1), (0, 9, 3), (1, 5, 1)]
    );
    assert_eq!(store.attempts(other).unwrap(), [(0, 0, 7)]);
    assert!(store.attempts(other + 1).unwrap().is_empty());
    assert!(store.record_attempt(other + 1, 0, 0, 1, "w1").is_err());
}

#[test]
fn counters_start_at_zero_and_add_up() {
    let mut store = Store::open_in_memory().unwrap();
    let job = store.insert_job("j", "", 0).unwrap();
    let other = store.insert_job("other", "", 0).unwrap();
    assert!(store.counters(job).unwrap().is_empty());
    store.add_counter(job, "stale_reports", 1).unwrap();
    store.add_counter(job, "stale_reports", 2).unwrap();
    store.add_counter(job, "duplicate_reports", 0).unwrap();
    store.add_counter(other, "stale_reports", 5).unwrap();
    let expected: BTreeMap<String, u64> = [
        ("duplicate_reports".to_string(), 0),
        ("stale_reports".to_string(), 3),
    ]
    .into();
    assert_eq!(store.counters(job).unwrap(), expected);
    assert_eq!(store.counters(other).unwrap()["stale_reports"], 5);

    // Saturates instead of overflowing.
    store.add_counter(job, "big", u64::MAX).unwrap();
    store.add_counter(job, "big", u64::MAX).unwrap();
    assert_eq!(store.counters(job).unwrap()["big"], i64::MAX as u64);

    assert!(store.add_counter(other + 1, "stale_reports", 1).is_err());
}

#[test]
fn state_survives_close_and_reopen() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("coordinator.db");

    let (done, running, outcomes_before, jobs_before);
    {
        let mut store = Store::open(&path).unwrap();
        done = store.insert_job("done", "[grid]\nn = 4", 1).unwrap();
        running = store.insert_job("running", "[grid]\nn = 8", 2).unwrap();
        store
            .set_job_state(done, JobState::Running, 3, None)
            .unwrap();
        store.set_job_state(done, JobState::Done, 4, None).unwrap();
        store
            .set_job_state(running, JobState::Running, 5, None)
            .unwrap();

        let a: [(u32, &[u8]); 2] = [(8, &[0, 1, 2]), (3, &[255])];
        let b: [(u32, &[u8]); 2] = [(3, &[7]), (1, &[])];
        store.commit_report(&report(running, 0, 1, 1, &a)).unwrap();
        store.commit_report(&report(running, 0, 0, 2, &b)).unwrap();
        store.record_attempt(running, 0, 0, 2, "w1").unwrap();
        store.record_attempt(running, 0, 1, 1, "w2").unwrap();
        store.add_counter(running, "stale_reports", 4).unwrap();
        outcomes_before = store.outcomes(running, 0).unwrap();
        jobs_before = store.jobs().unwrap();
    }

    let mut store = Store::open(&path).unwrap();
    assert_eq!(store.jobs().unwrap(), jobs_before);
    assert_eq!(store.job(done).unwrap().unwrap().finished_ms, Some(4));
    let unfinished: Vec<u64> = store
        .unfinished_jobs()
        .unwrap()
        .iter()
        .map(|j| j.id)
        .collect();
    assert_eq!(unfinished, [running]);
    assert_eq!(outcomes_before.len(), 3);
    assert_eq!(store.outcomes(running, 0).unwrap(), outcomes_before);
    assert_eq!(
        store.outcomes(running, 0).unwrap(),
        [
            StoredOutcome {
                cell: 8,
                data: vec![0, 1, 2]
            },
            StoredOutcome {
                cell: 3,
                data: vec![255]
            },
            StoredOutcome {
                cell: 1,
                data: vec![]
            },
        ]
    );
    assert_eq!(
        store.run_totals(running, 0).unwrap(),
        RunTotals {
            cpu_ns: 2_000,
            reports: 2,
            outcomes: 3
        }
    );
    assert_eq!(store.attempts(running).unwrap(), [(0, 0, 2), (0, 1, 1)]);
    assert_eq!(store.counters(running).unwrap()["stale_reports"], 4);

    // Numbering and first-wins continue across the restart.
    let next = store.insert_job("next", "", 6).unwrap();
    assert!(next > running);
    let again: [(u32, &[u8]); 2] = [(8, &[9]), (2, &[2])];
    assert_eq!(
        store
            .commit_report(&report(running, 0, 1, 3, &again))
            .unwrap(),
        1
    );
    store.record_attempt(running, 0, 1, 3, "w3").unwrap();
    assert_eq!(store.attempts(running).unwrap(), [(0, 0, 2), (0, 1, 3)]);
}

#[test]
fn a_database_from_a_newer_build_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("future.db");
    let newer = SCHEMA_VERSION + 1;
    {
        let conn = rusqlite::Connection::open(&path).unwrap();
        conn.pragma_update(None, "user_version", newer).unwrap();
    }
    let err = match Store::open(&path) {
        Ok(_) => panic!("a version {newer} database was opened"),
        Err(err) => err,
    };
    assert!(matches!(err, StoreError::Schema(_)), "{err:?}");
    let msg = err.to_string();
    assert!(msg.contains(&format!("version {newer}")), "{msg}");
    assert!(msg.contains(&format!("version {SCHEMA_VERSION}")), "{msg}");
    assert!(msg.contains("future.db"), "{msg}");

    // Refusing did not touch the file's version.
    let conn = rusqlite::Connection::open(&path).unwrap();
    let version: i32 = conn
        .query_row("PRAGMA user_version", [], |row| row.get(0))
        .unwrap();
    assert_eq!(version, newer);
}

#[test]
fn errors_display_and_chain() {
    let schema = StoreError::Schema("something odd".into());
    assert!(schema.to_string().contains("something odd"));
    assert!(std::error::Error::source(&schema).is_none());
    let sqlite: StoreError = rusqlite::Error::QueryReturnedNoRows.into();
    assert!(matches!(sqlite, StoreError::Sqlite(_)));
    assert!(std::error::Error::source(&sqlite).is_some());
}

#[test]
fn a_group_commits_everything_at_once_or_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("group.db");
    let job = {
        let mut s = Store::open(&path).unwrap();
        let job = s.insert_job("g", "{}", 1).unwrap();
        // A committed group: both reports, the attempt and the counter are there after reopen.
        s.begin_group().unwrap();
        assert_eq!(
            s.commit_report(&report(job, 0, 0, 1, &[(1, b"a"), (2, b"b")]))
                .unwrap(),
            2
        );
        // Nested report transactions still dedupe within the group.
        assert_eq!(
            s.commit_report(&report(job, 0, 0, 1, &[(2, b"x"), (3, b"c")]))
                .unwrap(),
            1
        );
        s.record_attempt(job, 0, 0, 1, "w1").unwrap();
        s.add_counter(job, "stale_reports", 2).unwrap();
        s.commit_group().unwrap();
        // An open group when the process dies: nothing of it survives.
        s.begin_group().unwrap();
        s.commit_report(&report(job, 0, 1, 1, &[(9, b"z")]))
            .unwrap();
        s.add_counter(job, "stale_reports", 5).unwrap();
        job
    };
    let s = Store::open(&path).unwrap();
    assert_eq!(cells(&s.outcomes(job, 0).unwrap()), vec![1, 2, 3]);
    assert_eq!(s.attempts(job).unwrap(), vec![(0, 0, 1)]);
    assert_eq!(s.counters(job).unwrap()["stale_reports"], 2);
}

#[test]
fn a_database_keeps_its_identity_and_another_has_another() {
    let dir = tempfile::tempdir().unwrap();
    let a = dir.path().join("a.db");
    let id = Store::open(&a).unwrap().instance_id().unwrap();
    assert_eq!(id.len(), 32);
    assert_eq!(Store::open(&a).unwrap().instance_id().unwrap(), id);
    let other = Store::open(&dir.path().join("b.db"))
        .unwrap()
        .instance_id()
        .unwrap();
    assert_ne!(other, id);
}
