//! The schema, its version (`PRAGMA user_version`) and the migrations that bring an older
//! database up to date.

use rusqlite::{Connection, TransactionBehavior};

use crate::{Result, StoreError};

/// The schema version this build writes and understands. A database with a larger
/// `user_version` was written by a newer build and is refused rather than misread.
pub const SCHEMA_VERSION: i32 = 2;

/// `MIGRATIONS[v]` takes a database from version `v` to `v + 1`; version 0 is an empty (new)
/// database. Append to this list; never edit a step that has shipped.
///
/// Integers: SQLite has only signed 64-bit integers. `u32` columns (run, tile, attempt, cell)
/// fit losslessly. `u64` quantities (job ids, `cpu_ns`, counters) are stored as `i64`: ids come
/// from AUTOINCREMENT and are always in `1..=i64::MAX`; durations and counts saturate at
/// `i64::MAX` (292 years of CPU time), so SQL `SUM` over them stays exact.
const MIGRATIONS: &[&str] = &[
    // 0 -> 1: the initial schema.
    r#"
    -- One row per submitted job. AUTOINCREMENT so an id is never handed out twice, even after
    -- the highest job is gone: clients hold job ids across coordinator restarts.
    CREATE TABLE IF NOT EXISTS jobs (
        id           INTEGER PRIMARY KEY AUTOINCREMENT,
        name         TEXT    NOT NULL,
        spec         TEXT    NOT NULL,
        state        TEXT    NOT NULL
                     CHECK (state IN ('queued', 'running', 'done', 'cancelled', 'failed')),
        submitted_ms INTEGER NOT NULL,
        started_ms   INTEGER,
        finished_ms  INTEGER,
        error        TEXT
    );

    -- One row per accepted worker report (one tile attempt), duplicates included: the audit
    -- trail of who computed what and at which CPU cost.
    CREATE TABLE IF NOT EXISTS reports (
        id           INTEGER PRIMARY KEY AUTOINCREMENT,
        job          INTEGER NOT NULL REFERENCES jobs (id),
        run          INTEGER NOT NULL,
        tile         INTEGER NOT NULL,
        attempt      INTEGER NOT NULL,
        worker       TEXT    NOT NULL,
        cpu_ns       INTEGER NOT NULL,
        new_outcomes INTEGER NOT NULL
    );
    CREATE INDEX IF NOT EXISTS reports_by_run ON reports (job, run);

    -- The first outcome stored for each cell of a run; later ones for the same cell are
    -- ignored. `seq` (AUTOINCREMENT, so strictly increasing) records the order of arrival.
    CREATE TABLE IF NOT EXISTS outcomes (
        seq    INTEGER PRIMARY KEY AUTOINCREMENT,
        job    INTEGER NOT NULL REFERENCES jobs (id),
        run    INTEGER NOT NULL,
        cell   INTEGER NOT NULL,
        report INTEGER NOT NULL REFERENCES reports (id),
        data   BLOB    NOT NULL,
        UNIQUE (job, run, cell)
    );

    -- The latest attempt number leased for each tile, so a restarted coordinator keeps
    -- numbering upwards and recognises reports of attempts leased before the restart.
    CREATE TABLE IF NOT EXISTS attempts (
        job     INTEGER NOT NULL REFERENCES jobs (id),
        run     INTEGER NOT NULL,
        tile    INTEGER NOT NULL,
        attempt INTEGER NOT NULL,
        worker  TEXT    NOT NULL,
        PRIMARY KEY (job, run, tile)
    ) WITHOUT ROWID;

    -- Named per-job counters (stale reports, duplicate reports, ...).
    CREATE TABLE IF NOT EXISTS counters (
        job   INTEGER NOT NULL REFERENCES jobs (id),
        name  TEXT    NOT NULL,
        value INTEGER NOT NULL,
        PRIMARY KEY (job, name)
    ) WITHOUT ROWID;
    "#,
    // 1 -> 2: a random identity for the database, so workers can tell a coordinator restarted
    // on the same store (resend, re-adopt) from one started on another (forget everything).
    r#"
    CREATE TABLE IF NOT EXISTS meta (
        key   TEXT PRIMARY KEY,
        value TEXT NOT NULL
    ) WITHOUT ROWID;
    INSERT OR IGNORE INTO meta (key, value) VALUES ('instance', lower(hex(randomblob(16))));
    "#,
];

/// Brings the database behind `conn` to [`SCHEMA_VERSION`], or refuses it when it is newer.
/// `label` names the database (its path) in errors.
///
/// Runs under `BEGIN IMMEDIATE` so two processes opening the same new file cannot both
/// create the schema, and every step is all-or-nothing together with its version bump.
pub(crate) fn migrate(conn: &mut Connection, label: &str) -> Result<()> {
    let tx = conn.transaction_with_behavior(TransactionBehavior::Immediate)?;
    let found: i32 = tx.query_row("PRAGMA user_version", [], |row| row.get(0))?;
    if found > SCHEMA_VERSION {
        return Err(StoreError::Schema(format!(
            "database {label} has schema version {found}, newer than version {SCHEMA_VERSION} \
             that this build understands; refusing to open it (use a newer salient)"
        )));
    }
    if found < 0 {
        return Err(StoreError::Schema(format!(
            "database {label} has invalid schema version {found}"
        )));
    }
    // `found` is in 0..=SCHEMA_VERSION here, so the casts below are lossless.
    for (step, sql) in MIGRATIONS.iter().enumerate().skip(found as usize) {
        tx.execute_batch(sql)?;
        tx.pragma_update(None, "user_version", step as i32 + 1)?;
    }
    tx.commit()?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_migration_per_version() {
        assert_eq!(MIGRATIONS.len(), SCHEMA_VERSION as usize);
    }
}
