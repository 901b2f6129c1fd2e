//! The store on a thread of its own, so that the scheduler's loop never waits for an fsync.
//!
//! With `synchronous=FULL` every commit waits for the disk. While the loop thread waited inside
//! its group commit, the polls that arrived queued behind it, and the workers' lanes ran dry
//! waiting for leases (on a 2-core VM, 2 workers × 1 thread took 5.2–5.6 s with the store on
//! disk and 4.3–4.9 s on tmpfs). Now the loop hands a group's writes and held answers to this
//! thread and goes on with the next events; the thread commits the group and only then lets
//! the answers go, so nothing is acknowledged before it is durable. That alone bought nothing
//! measurable, because each poll's reply still waited for its fsync. Polls are therefore
//! answered at once, with their acknowledgements owed until their group is durable (see
//! [`StoreThread::durable_group`] and `Scheduler::poll`).
//!
//! Outside a group (tests, tools) every write is committed before the call returns, as a
//! plain [`Store`] would. Reads and job inserts wait for the writes queued before them, so
//! they see the scheduler's own writes.

use salient_store::{JobRow, JobState, Report, RunTotals, Store, StoreError, StoredOutcome};
use std::cell::{Cell, RefCell};
use std::collections::BTreeMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{mpsc, Arc};
use std::thread::JoinHandle;

/// An answer held until its group is committed.
pub type Deferred = Box<dyn FnOnce() + Send>;

/// One store write, owned so that it can cross to the store thread.
pub enum Write {
    JobState {
        job: u64,
        state: JobState,
        now_ms: i64,
        error: Option<String>,
    },
    Report {
        job: u64,
        run: u32,
        tile: u32,
        attempt: u32,
        worker: String,
        cpu_ns: u64,
        /// `(cell, encoded outcome)` pairs.
        outcomes: Vec<(u32, prost::bytes::Bytes)>,
    },
    Attempt {
        job: u64,
        run: u32,
        tile: u32,
        attempt: u32,
        worker: String,
    },
    Counter {
        job: u64,
        name: String,
        delta: u64,
    },
}

impl Write {
    fn apply(&self, store: &mut Store) -> Result<(), StoreError> {
        match self {
            Write::JobState {
                job,
                state,
                now_ms,
                error,
            } => store
                .set_job_state(*job, *state, *now_ms, error.as_deref())
                .map(drop),
            Write::Report {
                job,
                run,
                tile,
                attempt,
                worker,
                cpu_ns,
                outcomes,
            } => {
                let blobs: Vec<(u32, &[u8])> = outcomes.iter().map(|(c, b)| (*c, &b[..])).collect();
                store
                    .commit_report(&Report {
                        job: *job,
                        run: *run,
                        tile: *tile,
                        attempt: *attempt,
                        worker,
                        cpu_ns: *cpu_ns,
                        outcomes: &blobs,
                    })
                    .map(drop)
            }
            Write::Attempt {
                job,
                run,
                tile,
                attempt,
                worker,
            } => store.record_attempt(*job, *run, *tile, *attempt, worker),
            Write::Counter { job, name, delta } => store.add_counter(*job, name, *delta),
        }
    }
}

enum Command {
    /// Writes committed in one transaction, then the answers they hold back. Groups are
    /// numbered 1, 2, … in the order sent.
    Group {
        seq: u64,
        writes: Vec<Write>,
        then: Vec<Deferred>,
    },
    Call(Box<dyn FnOnce(&mut Store) + Send>),
}

/// The handle the scheduler holds; the thread ends when it is dropped, after committing
/// everything handed to it.
pub struct StoreThread {
    commands: Option<mpsc::Sender<Command>>,
    thread: Option<JoinHandle<()>>,
    /// Writes of the open group, not yet handed over.
    pending: RefCell<Vec<Write>>,
    grouping: bool,
    /// Groups sent so far.
    sent: Cell<u64>,
    /// The last group committed (groups commit in order).
    durable: Arc<AtomicU64>,
}

impl StoreThread {
    pub fn new(mut store: Store) -> std::io::Result<StoreThread> {
        let (tx, rx) = mpsc::channel::<Command>();
        let durable = Arc::new(AtomicU64::new(0));
        let committed = durable.clone();
        let thread = std::thread::Builder::new()
            .name("salient-store".into())
            .spawn(move || {
                for command in rx {
                    match command {
                        Command::Group { seq, writes, then } => {
                            if !writes.is_empty() {
                                if let Err(e) = commit(&mut store, &writes) {
                                    // The scheduler's memory is ahead of the store: stop
                                    // without acknowledging; a restart resumes from what was
                                    // committed.
                                    tracing::error!(error = %e, "the store cannot commit; stopping");
                                    std::process::exit(1);
                                }
                            }
                            committed.store(seq, Ordering::Release);
                            then.into_iter().for_each(|answer| answer());
                        }
                        Command::Call(f) => f(&mut store),
                    }
                }
            })?;
        Ok(StoreThread {
            commands: Some(tx),
            thread: Some(thread),
            pending: RefCell::new(Vec::new()),
            grouping: false,
            sent: Cell::new(0),
            durable,
        })
    }

    fn send(&self, command: Command) {
        self.commands
            .as_ref()
            .expect("store thread running")
            .send(command)
            .unwrap_or_else(|_| panic!("the store thread stopped"));
    }

    /// Hands the open group's writes over (their commit still to come).
    fn flush(&self) {
        let writes = std::mem::take(&mut *self.pending.borrow_mut());
        if !writes.is_empty() {
            self.send_group(writes, Vec::new());
        }
    }

    fn send_group(&self, writes: Vec<Write>, then: Vec<Deferred>) {
        let seq = self.sent.get() + 1;
        self.sent.set(seq);
        self.send(Command::Group { seq, writes, then });
    }

    /// The group whose commit makes the writes made so far durable (0: they are already,
    /// outside a group).
    pub fn pending_group(&self) -> u64 {
        if self.grouping {
            self.sent.get() + 1
        } else {
            0
        }
    }

    /// The last group committed: a write of group `g` is durable once this is `g` or more.
    pub fn durable_group(&self) -> u64 {
        self.durable.load(Ordering::Acquire)
    }

    /// Runs `f` on the store after every write handed over before, and returns its result.
    pub fn call<T: Send + 'static>(&self, f: impl FnOnce(&mut Store) -> T + Send + 'static) -> T {
        self.flush();
        let (tx, rx) = mpsc::sync_channel(1);
        self.send(Command::Call(Box::new(move |store| {
            let _ = tx.send(f(store));
        })));
        rx.recv()
            .unwrap_or_else(|_| panic!("the store thread stopped"))
    }

    /// Inside a group: queued for the group's commit. Outside: committed before it returns.
    pub fn write(&self, w: Write) -> Result<(), StoreError> {
        if self.grouping {
            self.pending.borrow_mut().push(w);
            Ok(())
        } else {
            self.call(move |store| commit(store, std::slice::from_ref(&w)))
        }
    }

    /// Starts a group: writes wait for [`StoreThread::commit_group`].
    pub fn begin_group(&mut self) {
        self.grouping = true;
    }

    /// Ends the group: its writes are committed in one transaction on the store thread, and
    /// then the answers in `then` go out. Returns at once.
    pub fn commit_group(&mut self, then: Vec<Deferred>) {
        self.grouping = false;
        let writes = std::mem::take(&mut *self.pending.borrow_mut());
        self.send_group(writes, then);
    }

    /// Waits until everything handed over is committed.
    pub fn sync(&self) {
        self.call(|_| ());
    }

    pub fn add_counter(&self, job: u64, name: &str, delta: u64) -> Result<(), StoreError> {
        self.write(Write::Counter {
            job,
            name: name.to_string(),
            delta,
        })
    }

    pub fn set_job_state(
        &self,
        job: u64,
        state: JobState,
        now_ms: i64,
        error: Option<&str>,
    ) -> Result<(), StoreError> {
        self.write(Write::JobState {
            job,
            state,
            now_ms,
            error: error.map(str::to_string),
        })
    }

    pub fn record_attempt(
        &self,
        job: u64,
        run: u32,
        tile: u32,
        attempt: u32,
        worker: &str,
    ) -> Result<(), StoreError> {
        self.write(Write::Attempt {
            job,
            run,
            tile,
            attempt,
            worker: worker.to_string(),
        })
    }

    /// A new job, committed before it returns (its id comes from the store).
    pub fn insert_job(&self, name: &str, spec: &str, now_ms: i64) -> Result<u64, StoreError> {
        let (name, spec) = (name.to_string(), spec.to_string());
        self.call(move |s| s.insert_job(&name, &spec, now_ms))
    }

    pub fn job(&self, job: u64) -> Result<Option<JobRow>, StoreError> {
        self.call(move |s| s.job(job))
    }

    pub fn jobs(&self) -> Result<Vec<JobRow>, StoreError> {
        self.call(|s| s.jobs())
    }

    pub fn unfinished_jobs(&self) -> Result<Vec<JobRow>, StoreError> {
        self.call(|s| s.unfinished_jobs())
    }

    pub fn outcomes(&self, job: u64, run: u32) -> Result<Vec<StoredOutcome>, StoreError> {
        self.call(move |s| s.outcomes(job, run))
    }

    pub fn run_totals(&self, job: u64, run: u32) -> Result<RunTotals, StoreError> {
        self.call(move |s| s.run_totals(job, run))
    }

    pub fn attempts(&self, job: u64) -> Result<Vec<(u32, u32, u32)>, StoreError> {
        self.call(move |s| s.attempts(job))
    }

    pub fn counters(&self, job: u64) -> Result<BTreeMap<String, u64>, StoreError> {
        self.call(move |s| s.counters(job))
    }
}

fn commit(store: &mut Store, writes: &[Write]) -> Result<(), StoreError> {
    store.begin_group()?;
    for w in writes {
        if let Err(e) = w.apply(store) {
            let _ = store.rollback_group();
            return Err(e);
        }
    }
    store.commit_group()
}

impl Drop for StoreThread {
    fn drop(&mut self) {
        self.flush();
        drop(self.commands.take());
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}
