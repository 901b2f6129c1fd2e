//! Tests that look behind the API: pragmas, raw row counts, rollback.

use super::*;

fn count(store: &Store, table: &str) -> i64 {
    store
        .conn
        .query_row(&format!("SELECT COUNT(*) FROM {table}"), [], |row| {
            row.get(0)
        })
        .unwrap()
}

fn new_file_store() -> (tempfile::TempDir, std::path::PathBuf, Store) {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("state.db");
    let store = Store::open(&path).unwrap();
    (dir, path, store)
}

#[test]
fn file_database_runs_wal_full_sync_with_foreign_keys() {
    let (_dir, path, store) = new_file_store();
    let mode: String = store
        .conn
        .query_row("PRAGMA journal_mode", [], |row| row.get(0))
        .unwrap();
    assert_eq!(mode.to_ascii_lowercase(), "wal");
    let sync: i64 = store
        .conn
        .query_row("PRAGMA synchronous", [], |row| row.get(0))
        .unwrap();
    assert_eq!(sync, 2, "synchronous should be FULL (2)");
    let fk: i64 = store
        .conn
        .query_row("PRAGMA foreign_keys", [], |row| row.get(0))
        .unwrap();
    assert_eq!(fk, 1);
    let timeout: i64 = store
        .conn
        .query_row("PRAGMA busy_timeout", [], |row| row.get(0))
        .unwrap();
    assert!(timeout > 0);
    let version: i32 = store
        .conn
        .query_row("PRAGMA user_version", [], |row| row.get(0))
        .unwrap();
    assert_eq!(version, SCHEMA_VERSION);
    drop(store);

    // WAL is a property of the file: a plain connection sees it too.
    let raw = Connection::open(&path).unwrap();
    let mode: String = raw
        .query_row("PRAGMA journal_mode", [], |row| row.get(0))
        .unwrap();
    assert_eq!(mode.to_ascii_lowercase(), "wal");
}

#[test]
fn in_memory_database_enforces_foreign_keys() {
    let store = Store::open_in_memory().unwrap();
    let fk: i64 = store
        .conn
        .query_row("PRAGMA foreign_keys", [], |row| row.get(0))
        .unwrap();
    assert_eq!(fk, 1);
}

#[test]
fn job_ids_are_not_reused_after_the_highest_is_deleted() {
    let mut store = Store::open_in_memory().unwrap();
    let a = store.insert_job("a", "", 1).unwrap();
    let b = store.insert_job("b", "", 2).unwrap();
    assert!(b > a);
    // No API deletes jobs, but an operator might; plain rowids would then hand `b` out again.
    store
        .conn
        .execute("DELETE FROM jobs WHERE id = ?1", [b as i64])
        .unwrap();
    let c = store.insert_job("c", "", 3).unwrap();
    assert!(c > b, "id {c} reused after deleting {b}");
}

#[test]
fn unknown_job_report_stores_nothing() {
    let mut store = Store::open_in_memory().unwrap();
    let job = store.insert_job("j", "", 0).unwrap();
    let outcomes: [(u32, &[u8]); 2] = [(1, b"x"), (2, b"y")];
    let report = Report {
        job: job + 1,
        run: 0,
        tile: 0,
        attempt: 1,
        worker: "w",
        cpu_ns: 5,
        outcomes: &outcomes,
    };
    let err = store.commit_report(&report).unwrap_err();
    assert!(matches!(err, StoreError::Sqlite(_)), "{err}");
    assert_eq!(count(&store, "reports"), 0);
    assert_eq!(count(&store, "outcomes"), 0);
}

#[test]
fn a_report_failing_midway_is_rolled_back_whole() {
    let mut store = Store::open_in_memory().unwrap();
    let job = store.insert_job("j", "", 0).unwrap();
    // Make the third outcome's insert fail after the report row and two outcomes went in.
    store
        .conn
        .execute_batch(
            "CREATE TEMP TRIGGER boom BEFORE INSERT ON outcomes WHEN NEW.cell = 3
             BEGIN SELECT RAISE(ABORT, 'boom'); END;",
        )
        .unwrap();
    let outcomes: [(u32, &[u8]); 3] = [(1, b"a"), (2, b"b"), (3, b"c")];
    let report = Report {
        job,
        run: 0,
        tile: 0,
        attempt: 1,
        worker: "w",
        cpu_ns: 5,
        outcomes: &outcomes,
    };
    let err = store.commit_report(&report).unwrap_err();
    assert!(err.to_string().contains("boom"), "{err}");
    assert_eq!(count(&store, "reports"), 0);
    assert_eq!(count(&store, "outcomes"), 0);

    // The connection is usable afterwards and the same report goes in once the cause is gone.
    store.conn.execute_batch("DROP TRIGGER boom").unwrap();
    assert_eq!(store.commit_report(&report).unwrap(), 3);
    assert_eq!(count(&store, "reports"), 1);
}

#[test]
fn report_row_records_new_outcome_count() {
    let mut store = Store::open_in_memory().unwrap();
    let job = store.insert_job("j", "", 0).unwrap();
    let first: [(u32, &[u8]); 2] = [(1, b"a"), (2, b"b")];
    let second: [(u32, &[u8]); 2] = [(2, b"B"), (3, b"C")];
    for (attempt, outcomes) in [(1, &first[..]), (2, &second[..])] {
        store
            .commit_report(&Report {
                job,
                run: 0,
                tile: 7,
                attempt,
                worker: "w",
                cpu_ns: 10,
                outcomes,
            })
            .unwrap();
    }
    let rows: Vec<(u32, i64)> = store
        .conn
        .prepare("SELECT attempt, new_outcomes FROM reports ORDER BY id")
        .unwrap()
        .query_map([], |row| Ok((row.get(0)?, row.get(1)?)))
        .unwrap()
        .collect::<rusqlite::Result<_>>()
        .unwrap();
    assert_eq!(rows, vec![(1, 2), (2, 1)]);
}

#[test]
fn existing_current_database_is_not_migrated_again() {
    let (_dir, path, mut store) = new_file_store();
    let job = store.insert_job("j", "spec", 1).unwrap();
    drop(store);
    let store = Store::open(&path).unwrap();
    assert_eq!(store.job(job).unwrap().unwrap().spec, "spec");
    let version: i32 = store
        .conn
        .query_row("PRAGMA user_version", [], |row| row.get(0))
        .unwrap();
    assert_eq!(version, SCHEMA_VERSION);
}
