//! Checkpoints of `salient run`: the outcomes each run has committed, appended at intervals to
//! `OUT/.salient-checkpoint/run-NN.bin` (framed records, [`salient_grid::record`]), beside the
//! spec and version they belong to. `salient run SPEC --resume` offers them to each run's
//! ledger before any orbit runs, so the runs go on where they stopped and end with the labels
//! of an uninterrupted run. SIGINT, SIGTERM and SIGHUP save what is committed, publish the finished
//! runs' folders and exit; after SIGKILL the last periodic checkpoint is what remains.

use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicI32, Ordering};
use std::sync::{Mutex, MutexGuard, OnceLock};
use std::time::{Duration, Instant};

use salient_grid::record::{decode_records, encode_record};
use salient_grid::{Ledger, Outcome};
use serde_json::{json, Value};

use crate::spec::JobSpec;
use crate::usage::{runtime, CliError, CliResult};

/// The checkpoint's folder inside the output folder.
pub const FOLDER: &str = ".salient-checkpoint";

/// The checkpoint of one output folder.
pub struct Checkpoint {
    dir: PathBuf,
}

/// What a checkpoint is of: the spec as parsed and the version that computed it (another
/// version may round differently, and its outcomes would not be this one's).
fn identity(job: &JobSpec) -> Value {
    json!({ "salient": env!("CARGO_PKG_VERSION"), "spec": job.source })
}

fn run_file(dir: &Path, index: usize) -> PathBuf {
    dir.join(format!("run-{:02}.bin", index + 1))
}

impl Checkpoint {
    /// The checkpoint of `out` for `job`, and the outcomes it holds per run (empty when it
    /// starts anew). With `resume` an existing checkpoint must be `job`'s; without, an existing
    /// one is refused (it would be overwritten), and so is one of another spec or version.
    pub fn open(
        out: &Path,
        job: &JobSpec,
        resume: bool,
    ) -> CliResult<(Checkpoint, Vec<Vec<Outcome>>)> {
        let dir = out.join(FOLDER);
        let spec_file = dir.join("spec.json");
        let mine = identity(job);
        let saved: Option<Value> = std::fs::read_to_string(&spec_file)
            .ok()
            .and_then(|t| serde_json::from_str(&t).ok());
        let usage = |msg: String| Err(CliError::Usage(msg));
        match (&saved, resume) {
            (Some(_), false) => {
                return usage(format!(
                    "--out {} holds the checkpoint of an interrupted run: add --resume to go on with it, or remove {} to start over",
                    out.display(),
                    dir.display()
                ))
            }
            (Some(s), true) if *s != mine => {
                let what = if s["salient"] != mine["salient"] {
                    format!("Salient {} (this is {})", s["salient"], mine["salient"])
                } else {
                    format!("another spec (name {})", s["spec"]["name"])
                };
                return usage(format!(
                    "--resume: the checkpoint in {} was made by {what}; resume it with its own spec, or use another --out",
                    dir.display()
                ));
            }
            (None, true) => tracing::warn!(
                "--resume: {} holds no checkpoint; starting from the beginning",
                out.display()
            ),
            _ => {}
        }
        let fail = |e| runtime(&format!("writing the checkpoint in {}", dir.display()), e);
        std::fs::create_dir_all(&dir).map_err(fail)?;
        let mut committed = Vec::new();
        if saved.is_some() {
            for index in 0..job.runs.len() {
                committed.push(load_run(&run_file(&dir, index), job, index)?);
            }
        } else {
            for index in 0..job.runs.len() {
                let _ = std::fs::remove_file(run_file(&dir, index));
            }
            let text = serde_json::to_string_pretty(&mine).expect("JSON") + "\n";
            let tmp = dir.join("spec.json.tmp");
            std::fs::write(&tmp, text)
                .and_then(|()| std::fs::rename(&tmp, &spec_file))
                .map_err(fail)?;
            committed.resize(job.runs.len(), Vec::new());
        }
        Ok((Checkpoint { dir }, committed))
    }

    /// Appends `outcomes` to run `index`'s file as one record.
    pub fn append(&self, index: usize, outcomes: &[Outcome]) -> CliResult<()> {
        let path = run_file(&self.dir, index);
        std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&path)
            .and_then(|mut f| f.write_all(&encode_record(outcomes)))
            .map_err(|e| runtime(&format!("writing {}", path.display()), e))
    }

    /// Removes the checkpoint once the sweep's files are published.
    pub fn remove(self) -> CliResult<()> {
        std::fs::remove_dir_all(&self.dir)
            .map_err(|e| runtime(&format!("removing {}", self.dir.display()), e))
    }
}

/// The outcomes saved for run `index`, checked against its grid; the file is cut back to its
/// whole records (a record cut short by a kill is dropped, and appends go on after the rest).
fn load_run(path: &Path, job: &JobSpec, index: usize) -> CliResult<Vec<Outcome>> {
    let Ok(bytes) = std::fs::read(path) else {
        return Ok(Vec::new());
    };
    let (outcomes, whole) = decode_records(&bytes);
    if whole < bytes.len() {
        std::fs::OpenOptions::new()
            .write(true)
            .open(path)
            .and_then(|f| f.set_len(whole as u64))
            .map_err(|e| runtime(&format!("repairing {}", path.display()), e))?;
    }
    let grid = job.grid(index);
    let fits = |c: u32| (c as usize) < grid.cells() && grid.is_compatible(c);
    if let Some(o) = outcomes
        .iter()
        .find(|o| !fits(o.cell) || !o.visited.iter().all(|&v| fits(v)))
    {
        return Err(CliError::Usage(format!(
            "--resume: {} names cell {}, not a compatible cell of run {}'s grid: the checkpoint is damaged; remove it to start over",
            path.display(),
            o.cell,
            index + 1
        )));
    }
    Ok(outcomes)
}

/// Saves a run's newly committed outcomes at intervals, and all of them when the process is
/// asked to stop.
pub struct RunSaver<'a> {
    checkpoint: &'a Checkpoint,
    index: usize,
    /// Outcomes of `ledger.committed` already in the file.
    saved: usize,
    every: Duration,
    last: Instant,
}

impl<'a> RunSaver<'a> {
    /// For run `index`, whose first `saved` committed outcomes are in the file already.
    pub fn new(checkpoint: &'a Checkpoint, index: usize, saved: usize, every: Duration) -> Self {
        RunSaver {
            checkpoint,
            index,
            saved,
            every,
            last: Instant::now(),
        }
    }

    /// Appends what `ledger` committed since the last save, if the interval has passed; when a
    /// signal asked the process to stop, saves it all and ends the process ([`stop_now`]).
    pub fn tick(&mut self, ledger: &Ledger) -> CliResult<()> {
        if STOP.load(Ordering::Relaxed) {
            let _files = files_lock();
            self.save(ledger)?;
            stop_now();
        }
        if self.last.elapsed() >= self.every {
            let _files = files_lock();
            self.save(ledger)?;
            self.last = Instant::now();
        }
        Ok(())
    }

    /// Appends everything not saved yet: the run has finished.
    pub fn finish(&mut self, ledger: &Ledger) -> CliResult<()> {
        let _files = files_lock();
        self.save(ledger)
    }

    fn save(&mut self, ledger: &Ledger) -> CliResult<()> {
        if ledger.committed.len() > self.saved {
            self.checkpoint
                .append(self.index, &ledger.committed[self.saved..])?;
            self.saved = ledger.committed.len();
        }
        Ok(())
    }
}

/// A signal asked the process to stop.
static STOP: AtomicBool = AtomicBool::new(false);
/// The number of the signal that asked the process to stop: its exit status is 128 + it.
static STOP_SIGNAL: AtomicI32 = AtomicI32::new(0);
/// Held while files are written (checkpoint records, a finished run's folder), so that a stop
/// never publishes or cuts one half written.
static FILES: Mutex<()> = Mutex::new(());
/// The staging and output folders of the sweep in progress.
static FOLDERS: OnceLock<(PathBuf, PathBuf)> = OnceLock::new();

/// Holds off a stop while files are written.
pub fn files_lock() -> MutexGuard<'static, ()> {
    FILES.lock().unwrap_or_else(|e| e.into_inner())
}

/// How long a stop waits for the run in progress to save its last outcomes before the
/// signal's thread ends the process itself (with the last periodic checkpoint).
const STOP_GRACE: Duration = Duration::from_secs(2);

/// On SIGINT, SIGTERM or SIGHUP: the run in progress saves what it committed at its next commit (or
/// after [`STOP_GRACE`] the periodic checkpoint stands), the finished runs' folders move from
/// `stage` into `out`, and the process exits with 128 + the signal's number.
pub fn stop_on_signals(stage: &Path, out: &Path) -> CliResult<()> {
    use signal_hook::consts::{SIGHUP, SIGINT, SIGTERM};
    let _ = FOLDERS.set((stage.to_path_buf(), out.to_path_buf()));
    let mut signals = signal_hook::iterator::Signals::new([SIGINT, SIGTERM, SIGHUP])
        .map_err(|e| runtime("installing the signal handlers", e))?;
    std::thread::spawn(move || {
        if let Some(signal) = signals.forever().next() {
            STOP_SIGNAL.store(signal, Ordering::Relaxed);
            tracing::warn!("stopping: saving the checkpoint and the finished runs");
            STOP.store(true, Ordering::Relaxed);
            std::thread::sleep(STOP_GRACE);
            let _files = files_lock();
            stop_now();
        }
    });
    Ok(())
}

/// Publishes the finished runs' folders and ends the process (call with [`files_lock`] held).
fn stop_now() -> ! {
    let status = 128 + STOP_SIGNAL.load(Ordering::Relaxed);
    if let Some((stage, out)) = FOLDERS.get() {
        if let Err(e) = crate::output::publish_folders(stage, out) {
            eprintln!("error: {e}");
        }
        eprintln!(
            "stopped: the finished runs are in {}; `salient run SPEC --resume --out {}` goes on from the checkpoint",
            out.display(),
            out.display()
        );
    }
    std::process::exit(status)
}
