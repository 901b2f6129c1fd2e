//! The coordinator's durable state, in one SQLite database behind a narrow API.
//!
//! This crate owns:
//! - **jobs**: name, spec text, state ([`JobState`]) and its timestamps; ids are never reused;
//! - **reports**: one row per accepted worker report of a tile attempt (worker, CPU time, how
//!   many of its outcomes were new);
//! - **outcomes**: the first outcome stored for each cell of a run, as an opaque byte blob, in
//!   order of arrival;
//! - **attempts**: the latest attempt number leased for each tile, so numbering keeps growing
//!   across coordinator restarts;
//! - **counters**: named per-job counters.
//!
//! It knows nothing of gRPC, of scheduling rules or of what an outcome means numerically: the
//! coordinator decides, the store remembers.
//!
//! Durability: the database runs in WAL mode with `synchronous=FULL`, and every mutating call is
//! one transaction that is committed before the call returns. A caller may therefore
//! acknowledge an RPC as soon as the call returns `Ok`: the change survives a crash or power
//! loss from then on. Inside a group ([`Store::begin_group`] … [`Store::commit_group`]) the
//! calls share one transaction and nothing is durable before `commit_group` returns.
//!
//! Integers: SQLite stores signed 64-bit integers only. `u64` values (job ids, `cpu_ns`,
//! counters) are stored as `i64`. Job ids come from AUTOINCREMENT and always lie in
//! `1..=i64::MAX`, so they round-trip exactly; a `u64` id beyond that range simply names no job.
//! CPU times and counters saturate at `i64::MAX` (292 years of CPU time), which keeps SQL sums
//! over them exact.

mod access;
mod error;
mod schema;

use std::collections::BTreeMap;
use std::path::Path;
use std::time::Duration;

use rusqlite::{params, Connection, OptionalExtension, Row};

pub use error::{Result, StoreError};
pub use schema::SCHEMA_VERSION;

/// How long a statement waits for a lock held by another connection (a second process opening
/// the same file, an external `sqlite3` shell) before failing with `SQLITE_BUSY`.
const BUSY_TIMEOUT: Duration = Duration::from_secs(5);

/// The life cycle of a job. The store records states; which transitions are legal is the
/// coordinator's business.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum JobState {
    /// Submitted, not yet started.
    Queued,
    /// Started (a lease of it went out), not yet finished.
    Running,
    /// Finished with every run complete.
    Done,
    /// Cancelled by a client.
    Cancelled,
    /// Given up with an error.
    Failed,
}

impl JobState {
    /// The text stored in the database (and shown to users).
    pub fn as_str(self) -> &'static str {
        match self {
            JobState::Queued => "queued",
            JobState::Running => "running",
            JobState::Done => "done",
            JobState::Cancelled => "cancelled",
            JobState::Failed => "failed",
        }
    }

    /// The inverse of [`JobState::as_str`]; `None` for any other text.
    pub fn parse(s: &str) -> Option<Self> {
        match s {
            "queued" => Some(JobState::Queued),
            "running" => Some(JobState::Running),
            "done" => Some(JobState::Done),
            "cancelled" => Some(JobState::Cancelled),
            "failed" => Some(JobState::Failed),
            _ => None,
        }
    }

    /// Whether the job has ended (done, cancelled or failed): a restarted coordinator does not
    /// resume it.
    pub fn is_terminal(self) -> bool {
        matches!(
            self,
            JobState::Done | JobState::Cancelled | JobState::Failed
        )
    }
}

/// One job as stored.
#[derive(Clone, Debug, PartialEq)]
pub struct JobRow {
    /// The job's id.
    pub id: u64,
    /// The job's name.
    pub name: String,
    /// The job's spec, as text the store does not interpret.
    pub spec: String,
    /// Where the job is in its life cycle.
    pub state: JobState,
    /// Times in milliseconds since the Unix epoch, as given by the caller.
    pub submitted_ms: i64,
    /// Set by the first move to [`JobState::Running`].
    pub started_ms: Option<i64>,
    /// Set by the first move to a terminal state.
    pub finished_ms: Option<i64>,
    /// Why the job failed ([`JobState::Failed`]).
    pub error: Option<String>,
}

/// The stored outcome of one cell: an opaque blob the coordinator encoded.
#[derive(Clone, Debug, PartialEq)]
pub struct StoredOutcome {
    /// The cell whose orbit produced the outcome.
    pub cell: u32,
    /// The encoded outcome.
    pub data: Vec<u8>,
}

/// One accepted report of a worker: outcomes of cells of one tile attempt.
pub struct Report<'a> {
    /// The job reported on.
    pub job: u64,
    /// Index of the run within the job.
    pub run: u32,
    /// Index of the tile within the run.
    pub tile: u32,
    /// Attempt of the tile's lease.
    pub attempt: u32,
    /// Id of the worker that reported.
    pub worker: &'a str,
    /// CPU time the worker spent on this attempt, in nanoseconds.
    pub cpu_ns: u64,
    /// `(cell, encoded outcome)` pairs.
    pub outcomes: &'a [(u32, &'a [u8])],
}

/// Sums over the reports of one run.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RunTotals {
    /// CPU time of every report, duplicates included (the work was done either way).
    pub cpu_ns: u64,
    /// Reports committed.
    pub reports: u64,
    /// Cells with a stored outcome (the new outcomes of all reports).
    pub outcomes: u64,
}

/// The coordinator's database. One `Store` per process; it is `Send`, not shared: the
/// coordinator's single event loop owns it.
pub struct Store {
    conn: Connection,
    /// The database's path (or ":memory:"), named in errors about its contents.
    label: String,
}

/// SQLite's own findings of damage (`SQLITE_CORRUPT`, `SQLITE_NOTADB`) as
/// [`StoreError::Damaged`], which says what to do; any other error as it is.
fn damaged_if_corrupt(e: StoreError, label: &str) -> StoreError {
    match &e {
        StoreError::Sqlite(rusqlite::Error::SqliteFailure(f, _))
            if matches!(
                f.code,
                rusqlite::ErrorCode::DatabaseCorrupt | rusqlite::ErrorCode::NotADatabase
            ) =>
        {
            StoreError::damaged(label, &e.to_string())
        }
        _ => e,
    }
}

/// A `u64` job id as SQLite sees it. Ids beyond `i64::MAX` cannot exist (AUTOINCREMENT), so
/// they map to -1, which names no row.
fn id_to_sql(id: u64) -> i64 {
    i64::try_from(id).unwrap_or(-1)
}

/// A `u64` amount (nanoseconds, a count) as stored: saturated at `i64::MAX`.
fn amount_to_sql(v: u64) -> i64 {
    i64::try_from(v).unwrap_or(i64::MAX)
}

/// A stored amount back as `u64`. The store never writes negative amounts; a negative value
/// from a foreign writer reads as 0.
fn amount_from_sql(v: i64) -> u64 {
    u64::try_from(v).unwrap_or(0)
}

/// The columns of `jobs` in the order [`job_from_row`] reads them.
const JOB_COLUMNS: &str = "id, name, spec, state, submitted_ms, started_ms, finished_ms, error";

/// A job row with its state still as text: row closures cannot return [`StoreError`], so the
/// state is parsed afterwards by [`RawJob::into_row`].
struct RawJob {
    id: i64,
    name: String,
    spec: String,
    state: String,
    submitted_ms: i64,
    started_ms: Option<i64>,
    finished_ms: Option<i64>,
    error: Option<String>,
}

fn job_from_row(row: &Row<'_>) -> rusqlite::Result<RawJob> {
    Ok(RawJob {
        id: row.get(0)?,
        name: row.get(1)?,
        spec: row.get(2)?,
        state: row.get(3)?,
        submitted_ms: row.get(4)?,
        started_ms: row.get(5)?,
        finished_ms: row.get(6)?,
        error: row.get(7)?,
    })
}

impl RawJob {
    fn into_row(self) -> Result<JobRow> {
        let state = JobState::parse(&self.state).ok_or_else(|| {
            StoreError::Schema(format!(
                "job {} has unknown state {:?}",
                self.id, self.state
            ))
        })?;
        let id = u64::try_from(self.id)
            .map_err(|_| StoreError::Schema(format!("job id {} is negative", self.id)))?;
        Ok(JobRow {
            id,
            name: self.name,
            spec: self.spec,
            state,
            submitted_ms: self.submitted_ms,
            started_ms: self.started_ms,
            finished_ms: self.finished_ms,
            error: self.error,
        })
    }
}

impl Store {
    /// Opens (creating if absent) the database file at `path`, switches it to WAL with
    /// `synchronous=FULL`, enables foreign keys and brings the schema up to date.
    ///
    /// Fails with [`StoreError::Schema`] when the file's schema version is newer than
    /// [`SCHEMA_VERSION`] (written by a newer build; reading it could lose data) or when WAL
    /// cannot be enabled (e.g. a file system without shared memory support).
    ///
    /// Refused at once, with [`StoreError::Access`], when the file or its folder cannot be
    /// written (SQLite would open a read-only file read-only and fail at the first write), and
    /// with [`StoreError::Damaged`] when the file is not a database or SQLite's quick check
    /// finds it damaged. A new file is created readable and writable by its owner only; SQLite
    /// gives its WAL and shared-memory files the same permissions.
    pub fn open(path: &Path) -> Result<Store> {
        let label = path.display().to_string();
        access::check_writable(path, &label)?;
        let conn = Connection::open(path)?;
        let store = Self::setup(conn, &label, true).map_err(|e| damaged_if_corrupt(e, &label))?;
        store.quick_check()?;
        Ok(store)
    }

    /// A private in-memory database with the same schema (for tests and throwaway runs). Its
    /// journal mode is `memory`, as SQLite allows nothing else there.
    pub fn open_in_memory() -> Result<Store> {
        let conn = Connection::open_in_memory()?;
        Self::setup(conn, ":memory:", false)
    }

    fn setup(mut conn: Connection, label: &str, wal: bool) -> Result<Store> {
        // Set before anything else may wait on a lock, including the journal mode switch.
        conn.busy_timeout(BUSY_TIMEOUT)?;
        if wal {
            // WAL: readers never block the writer, and a commit is one append + fsync.
            let mode: String =
                conn.pragma_update_and_check(None, "journal_mode", "WAL", |row| row.get(0))?;
            if !mode.eq_ignore_ascii_case("wal") {
                return Err(StoreError::Schema(format!(
                    "database {label}: cannot enable WAL (journal_mode is {mode})"
                )));
            }
        }
        // FULL: fsync the WAL at every commit, so a returned call is durable even through a
        // power loss (NORMAL would only survive a process crash).
        conn.pragma_update(None, "synchronous", "FULL")?;
        // Per connection and off by default in SQLite; must be set outside a transaction.
        conn.pragma_update(None, "foreign_keys", "ON")?;
        schema::migrate(&mut conn, label)?;
        Ok(Store {
            conn,
            label: label.to_string(),
        })
    }

    /// SQLite's quick check (every page and index entry well formed, no free-list damage;
    /// linear in the file's size): the store is refused when it reports anything.
    fn quick_check(&self) -> Result<()> {
        let mut stmt = self.conn.prepare("PRAGMA quick_check")?;
        let problems: Vec<String> = stmt
            .query_map([], |row| row.get::<_, String>(0))?
            .collect::<rusqlite::Result<_>>()
            .map_err(|e| damaged_if_corrupt(e.into(), &self.label))?;
        if problems.len() == 1 && problems[0] == "ok" {
            return Ok(());
        }
        let shown: Vec<&str> = problems.iter().take(3).map(String::as_str).collect();
        Err(StoreError::damaged(
            &self.label,
            &format!("SQLite's quick check: {}", shown.join("; ")),
        ))
    }

    /// New job in state Queued; ids increase and are never reused (AUTOINCREMENT).
    pub fn insert_job(&mut self, name: &str, spec: &str, now_ms: i64) -> Result<u64> {
        self.conn.execute(
            "INSERT INTO jobs (name, spec, state, submitted_ms) VALUES (?1, ?2, ?3, ?4)",
            params![name, spec, JobState::Queued.as_str(), now_ms],
        )?;
        let id = self.conn.last_insert_rowid();
        u64::try_from(id).map_err(|_| StoreError::Schema(format!("new job id {id} is negative")))
    }

    /// Sets the state; the first move to Running sets started_ms, a terminal state sets
    /// finished_ms; error text stored when Some. Unknown job -> Ok(false), else Ok(true).
    ///
    /// Both timestamps are written once only: a later move to Running or to another terminal
    /// state keeps the first time, so they always describe when the job really started and
    /// ended. `error: None` keeps any error already stored.
    pub fn set_job_state(
        &mut self,
        job: u64,
        state: JobState,
        now_ms: i64,
        error: Option<&str>,
    ) -> Result<bool> {
        let changed = self.conn.execute(
            "UPDATE jobs SET
                 state = ?2,
                 started_ms = CASE WHEN started_ms IS NULL AND ?2 = 'running'
                                   THEN ?3 ELSE started_ms END,
                 finished_ms = CASE WHEN finished_ms IS NULL AND ?4
                                    THEN ?3 ELSE finished_ms END,
                 error = COALESCE(?5, error)
             WHERE id = ?1",
            params![
                id_to_sql(job),
                state.as_str(),
                now_ms,
                state.is_terminal(),
                error
            ],
        )?;
        Ok(changed > 0)
    }

    /// The job with this id, if any.
    pub fn job(&self, job: u64) -> Result<Option<JobRow>> {
        let mut stmt = self
            .conn
            .prepare_cached(&format!("SELECT {JOB_COLUMNS} FROM jobs WHERE id = ?1"))?;
        let raw = stmt
            .query_row(params![id_to_sql(job)], job_from_row)
            .optional()?;
        raw.map(RawJob::into_row).transpose()
    }

    /// All jobs by increasing id.
    pub fn jobs(&self) -> Result<Vec<JobRow>> {
        self.select_jobs(&format!("SELECT {JOB_COLUMNS} FROM jobs ORDER BY id"))
    }

    /// Queued and Running jobs by increasing id (what a restarted coordinator resumes).
    pub fn unfinished_jobs(&self) -> Result<Vec<JobRow>> {
        self.select_jobs(&format!(
            "SELECT {JOB_COLUMNS} FROM jobs WHERE state IN ('queued', 'running') ORDER BY id"
        ))
    }

    fn select_jobs(&self, sql: &str) -> Result<Vec<JobRow>> {
        let mut stmt = self.conn.prepare_cached(sql)?;
        let raws = stmt
            .query_map([], job_from_row)?
            .collect::<rusqlite::Result<Vec<_>>>()?;
        raws.into_iter().map(RawJob::into_row).collect()
    }

    /// The database's random identity, fixed when it was created.
    pub fn instance_id(&self) -> Result<String> {
        Ok(self
            .conn
            .query_row("SELECT value FROM meta WHERE key = 'instance'", [], |row| {
                row.get(0)
            })?)
    }

    /// Starts a group: every call until [`Store::commit_group`] joins one transaction, so a
    /// burst of reports and leases costs one fsync. The caller must not acknowledge anything
    /// done in the group before `commit_group` returns.
    pub fn begin_group(&mut self) -> Result<()> {
        self.conn.execute_batch("BEGIN IMMEDIATE")?;
        Ok(())
    }

    /// Commits the group started by [`Store::begin_group`].
    pub fn commit_group(&mut self) -> Result<()> {
        self.conn.execute_batch("COMMIT")?;
        Ok(())
    }

    /// Abandons the group started by [`Store::begin_group`]: none of its writes stay.
    pub fn rollback_group(&mut self) -> Result<()> {
        self.conn.execute_batch("ROLLBACK")?;
        Ok(())
    }

    /// In ONE transaction: a row for the report (job, run, tile, attempt, worker, cpu_ns, number
    /// of new outcomes) and each outcome with INSERT OR IGNORE on (job, run, cell) so a cell
    /// keeps its first outcome. Returns how many outcomes were new.
    ///
    /// First-wins makes a repeated or overlapping report harmless: retries after a lost
    /// acknowledgement, or a tile re-leased after a timeout whose first worker still reported,
    /// change nothing already stored. A report for an unknown job fails its foreign key and
    /// stores nothing at all.
    pub fn commit_report(&mut self, report: &Report<'_>) -> Result<usize> {
        // A savepoint, so that inside a group (`begin_group`) it nests, and alone it is its own
        // transaction.
        let tx = self.conn.savepoint()?;
        let new = {
            let job = id_to_sql(report.job);
            tx.prepare_cached(
                "INSERT INTO reports (job, run, tile, attempt, worker, cpu_ns, new_outcomes)
                 VALUES (?1, ?2, ?3, ?4, ?5, ?6, 0)",
            )?
            .execute(params![
                job,
                report.run,
                report.tile,
                report.attempt,
                report.worker,
                amount_to_sql(report.cpu_ns),
            ])?;
            let report_id = tx.last_insert_rowid();
            let mut insert = tx.prepare_cached(
                "INSERT OR IGNORE INTO outcomes (job, run, cell, report, data, checksum)
                 VALUES (?1, ?2, ?3, ?4, ?5, ?6)",
            )?;
            let mut new = 0usize;
            for &(cell, data) in report.outcomes {
                let sum = schema::checksum(job, report.run, cell, data);
                new += insert.execute(params![job, report.run, cell, report_id, data, sum])?;
            }
            tx.prepare_cached("UPDATE reports SET new_outcomes = ?2 WHERE id = ?1")?
                .execute(params![report_id, amount_to_sql(new as u64)])?;
            new
        };
        tx.commit()?;
        Ok(new)
    }

    /// The outcomes of a run in the order they were first stored, each verified against its
    /// checksum: one that fails it makes the call fail with [`StoreError::Damaged`], naming the
    /// cell, so a damaged outcome is never served.
    pub fn outcomes(&self, job: u64, run: u32) -> Result<Vec<StoredOutcome>> {
        let mut stmt = self.conn.prepare_cached(
            "SELECT cell, data, checksum FROM outcomes WHERE job = ?1 AND run = ?2 ORDER BY seq",
        )?;
        let job_sql = id_to_sql(job);
        let rows = stmt
            .query_map(params![job_sql, run], |row| {
                Ok((
                    row.get::<_, u32>(0)?,
                    row.get::<_, Vec<u8>>(1)?,
                    row.get(2)?,
                ))
            })
            .and_then(|rows| rows.collect::<rusqlite::Result<Vec<(u32, Vec<u8>, Option<i64>)>>>())
            .map_err(|e| damaged_if_corrupt(e.into(), &self.label))?;
        let mut out = Vec::with_capacity(rows.len());
        for (cell, data, sum) in rows {
            if sum != Some(schema::checksum(job_sql, run, cell, &data)) {
                return Err(StoreError::damaged(
                    &self.label,
                    &format!("the outcome of job {job} run {run} cell {cell} fails its checksum"),
                ));
            }
            out.push(StoredOutcome { cell, data });
        }
        Ok(out)
    }

    /// CPU time, number of reports and number of stored outcomes of a run; zeros for a run
    /// (or job) without reports.
    pub fn run_totals(&self, job: u64, run: u32) -> Result<RunTotals> {
        let mut stmt = self.conn.prepare_cached(
            "SELECT COALESCE(SUM(cpu_ns), 0), COUNT(*), COALESCE(SUM(new_outcomes), 0)
             FROM reports WHERE job = ?1 AND run = ?2",
        )?;
        let (cpu_ns, reports, outcomes) = stmt.query_row(params![id_to_sql(job), run], |row| {
            Ok((
                row.get::<_, i64>(0)?,
                row.get::<_, i64>(1)?,
                row.get::<_, i64>(2)?,
            ))
        })?;
        Ok(RunTotals {
            cpu_ns: amount_from_sql(cpu_ns),
            reports: amount_from_sql(reports),
            outcomes: amount_from_sql(outcomes),
        })
    }

    /// Upsert of the latest attempt number leased for a tile (and to which worker), so attempt
    /// numbers keep growing across restarts.
    ///
    /// The stored number never decreases: recording an attempt lower than or equal to the one
    /// stored changes nothing, so a late or repeated write cannot roll numbering back.
    pub fn record_attempt(
        &mut self,
        job: u64,
        run: u32,
        tile: u32,
        attempt: u32,
        worker: &str,
    ) -> Result<()> {
        self.conn
            .prepare_cached(
                "INSERT INTO attempts (job, run, tile, attempt, worker)
                 VALUES (?1, ?2, ?3, ?4, ?5)
                 ON CONFLICT (job, run, tile) DO UPDATE
                     SET attempt = excluded.attempt, worker = excluded.worker
                     WHERE excluded.attempt > attempts.attempt",
            )?
            .execute(params![id_to_sql(job), run, tile, attempt, worker])?;
        Ok(())
    }

    /// (run, tile, latest attempt) for every tile of the job ever leased, sorted.
    pub fn attempts(&self, job: u64) -> Result<Vec<(u32, u32, u32)>> {
        let mut stmt = self.conn.prepare_cached(
            "SELECT run, tile, attempt FROM attempts WHERE job = ?1 ORDER BY run, tile",
        )?;
        let rows = stmt.query_map(params![id_to_sql(job)], |row| {
            Ok((row.get(0)?, row.get(1)?, row.get(2)?))
        })?;
        Ok(rows.collect::<rusqlite::Result<Vec<_>>>()?)
    }

    /// Named per-job counters (e.g. "stale_reports", "duplicate_reports"): add delta (creating
    /// at 0). The sum saturates at `i64::MAX`. An unknown job fails its foreign key.
    pub fn add_counter(&mut self, job: u64, name: &str, delta: u64) -> Result<()> {
        // Read-modify-write in Rust rather than `value + ?` in SQL: SQLite turns an overflowing
        // integer sum into a REAL, whereas this saturates exactly.
        let tx = self.conn.savepoint()?;
        let job = id_to_sql(job);
        let current: i64 = tx
            .prepare_cached("SELECT value FROM counters WHERE job = ?1 AND name = ?2")?
            .query_row(params![job, name], |row| row.get(0))
            .optional()?
            .unwrap_or(0);
        let value = amount_from_sql(current).saturating_add(delta);
        tx.prepare_cached(
            "INSERT INTO counters (job, name, value) VALUES (?1, ?2, ?3)
             ON CONFLICT (job, name) DO UPDATE SET value = excluded.value",
        )?
        .execute(params![job, name, amount_to_sql(value)])?;
        tx.commit()?;
        Ok(())
    }

    /// All counters of a job by name; empty for a job without counters.
    pub fn counters(&self, job: u64) -> Result<BTreeMap<String, u64>> {
        let mut stmt = self
            .conn
            .prepare_cached("SELECT name, value FROM counters WHERE job = ?1")?;
        let rows = stmt.query_map(params![id_to_sql(job)], |row| {
            Ok((row.get::<_, String>(0)?, row.get::<_, i64>(1)?))
        })?;
        let mut out = BTreeMap::new();
        for row in rows {
            let (name, value) = row?;
            out.insert(name, amount_from_sql(value));
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests;
