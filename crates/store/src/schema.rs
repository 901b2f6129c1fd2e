//! The schema, its version (`PRAGMA user_version`) and the migrations that bring an older
//! database up to date.

use rusqlite::{Connection, TransactionBehavior};

use crate::{Result, StoreError};

/// The schema version this build writes and understands. A database with a larger
/// `user_version` was written by a newer build and is refused rather than misread.
pub const SCHEMA_VERSION: i32 = 3;

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
    // 2 -> 3: a checksum per outcome (see `checksum`), verified whenever outcomes are loaded,
    // so a damaged byte is refused rather than served. Rows stored before have theirs
    // computed by `fill_checksums` in the same transaction.
    r#"
    ALTER TABLE outcomes ADD COLUMN checksum INTEGER;
    "#,
];

/// The checksum of an outcome as stored: 64-bit FNV-1a over the job, run and cell it belongs
/// to and its bytes. Every step of FNV-1a is a bijection of its state for a fixed input byte,
/// so any one changed byte, and any outcome moved to another cell, changes the sum.
pub(crate) fn checksum(job: i64, run: u32, cell: u32, data: &[u8]) -> i64 {
    const OFFSET: u64 = 0xcbf2_9ce4_8422_2325;
    const PRIME: u64 = 0x0000_0100_0000_01b3;
    let key = job
        .to_le_bytes()
        .into_iter()
        .chain(run.to_le_bytes())
        .chain(cell.to_le_bytes());
    let sum = key
        .chain(data.iter().copied())
        .fold(OFFSET, |h, b| (h ^ u64::from(b)).wrapping_mul(PRIME));
    sum as i64
}

/// Computes the checksum of every outcome that has none (those stored by schema version 2).
fn fill_checksums(tx: &Connection) -> rusqlite::Result<()> {
    let rows: Vec<(i64, i64, u32, u32, Vec<u8>)> = tx
        .prepare("SELECT seq, job, run, cell, data FROM outcomes WHERE checksum IS NULL")?
        .query_map([], |r| {
            Ok((r.get(0)?, r.get(1)?, r.get(2)?, r.get(3)?, r.get(4)?))
        })?
        .collect::<rusqlite::Result<_>>()?;
    let mut update = tx.prepare("UPDATE outcomes SET checksum = ?2 WHERE seq = ?1")?;
    for (seq, job, run, cell, data) in rows {
        update.execute(rusqlite::params![seq, checksum(job, run, cell, &data)])?;
    }
    Ok(())
}

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
        if step + 1 == 3 {
            fill_checksums(&tx)?;
        }
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
