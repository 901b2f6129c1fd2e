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
        // Compared as text: both are this serialisation of a parsed spec (reading floats back
        // through JSON may not give the same bits).
        let text = serde_json::to_string_pretty(&mine).expect("JSON") + "\n";
        let saved = match std::fs::read_to_string(&spec_file) {
            Ok(t) => Some(t),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => None,
            Err(e) => {
                return Err(CliError::Usage(format!(
                    "{} cannot be read ({e}): remove {} to start over",
                    spec_file.display(),
                    dir.display()
                )))
            }
        };
        let usage = |msg: String| Err(CliError::Usage(msg));
        match (&saved, resume) {
            (Some(_), false) => {
                return usage(format!(
                    "--out {} holds the checkpoint of an interrupted run: add --resume to go on with it, or remove {} to start over",
                    out.display(),
                    dir.display()
                ))
            }
            (Some(s), true) if *s != text => {
                let theirs: Value = serde_json::from_str(s).unwrap_or(Value::Null);
                let what = if theirs.is_null() {
                    "a spec.json that does not parse".to_string()
                } else if theirs["salient"] != mine["salient"] {
                    format!("Salient {} (this is {})", theirs["salient"], mine["salient"])
                } else {
                    format!("another spec (name {})", theirs["spec"]["name"])
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
    /// Outcomes of `ledger.committed` already in the file: at the first tick, which comes right
    /// after the saved outcomes were offered and before any orbit ran, all of them.
    saved: Option<usize>,
    every: Duration,
    last: Instant,
}

impl<'a> RunSaver<'a> {
    /// For run `index`, resumed from its file (if any) by [`salient_grid::run_embedded_resumed`].
    pub fn new(checkpoint: &'a Checkpoint, index: usize, every: Duration) -> Self {
        RunSaver {
            checkpoint,
            index,
            saved: None,
            every,
            last: Instant::now(),
        }
    }

    /// Appends what `ledger` committed since the last save, if the interval has passed; when a
    /// signal asked the process to stop, saves it all and ends the process ([`stop_now`]).
    pub fn tick(&mut self, ledger: &Ledger) -> CliResult<()> {
        if self.saved.is_none() {
            self.saved = Some(ledger.committed.len());
        }
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
        let saved = *self.saved.get_or_insert(0);
        if ledger.committed.len() > saved {
            self.checkpoint
                .append(self.index, &ledger.committed[saved..])?;
            self.saved = Some(ledger.committed.len());
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
/// Every run has finished and the sweep's files are being published: a stop lets it finish.
static FINISHING: AtomicBool = AtomicBool::new(false);

/// Marks the sweep as finishing (call with [`files_lock`] held, and hold it while the files
/// are published): a signal from then on does not touch the folders.
pub fn finishing() {
    FINISHING.store(true, Ordering::Relaxed);
}

/// Holds off a stop while files are written.
pub fn files_lock() -> MutexGuard<'static, ()> {
    FILES.lock().unwrap_or_else(|e| e.into_inner())
}

/// How long a stop waits for the run in progress to save its last outcomes before the
/// signal's thread ends the process itself (with the last periodic checkpoint).
const STOP_GRACE: Duration = Duration::from_secs(2);

/// On SIGINT, SIGTERM or SIGHUP: the run in progress saves what it committed at its next
/// commit (or after [`STOP_GRACE`] the periodic checkpoint stands), the finished runs' folders
/// move from `stage` into `out`, and the process exits with 128 + the signal's number. A
/// second signal ends the process at once.
pub fn stop_on_signals(stage: &Path, out: &Path) -> CliResult<()> {
    use signal_hook::consts::{SIGHUP, SIGINT, SIGTERM};
    let _ = FOLDERS.set((stage.to_path_buf(), out.to_path_buf()));
    let mut signals = signal_hook::iterator::Signals::new([SIGINT, SIGTERM, SIGHUP])
        .map_err(|e| runtime("installing the signal handlers", e))?;
    std::thread::spawn(move || {
        for (k, signal) in signals.forever().enumerate() {
            if k > 0 {
                // A second signal: the user will not wait for the first one's saving.
                std::process::exit(128 + signal);
            }
            STOP_SIGNAL.store(signal, Ordering::Relaxed);
            tracing::warn!("stopping: saving the checkpoint and the finished runs");
            STOP.store(true, Ordering::Relaxed);
            std::thread::spawn(|| {
                std::thread::sleep(STOP_GRACE);
                let _files = files_lock();
                if !FINISHING.load(Ordering::Relaxed) {
                    stop_now();
                }
            });
        }
    });
    Ok(())
}

/// Publishes the finished runs' folders and ends the process (call with [`files_lock`] held).
fn stop_now() -> ! {
    let status = 128 + STOP_SIGNAL.load(Ordering::Relaxed);
    if let Some((stage, out)) = FOLDERS.get() {
        // Never a panic on a closed stderr (a hung-up terminal): the process must exit.
        let mut err = std::io::stderr();
        if let Err(e) = crate::output::publish_folders(stage, out) {
            let _ = writeln!(err, "error: {e}");
        }
        let _ = writeln!(
            err,
            "stopped: the finished runs are in {}; `salient run SPEC --resume --out {}` goes on from the checkpoint",
            out.display(),
            out.display()
        );
    }
    std::process::exit(status)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn job(chaotic: &str) -> JobSpec {
        let text = format!(
            "name = \"c\"\n[system]\nkind = \"henon-heiles\"\nenergy = 0.125\n[grid]\ncells = [4, 4]\n[sweep]\nmethod = [\"tm-sbab2c\"]\ntau = [0.5]\nt_final = [10]\n[classify]\nchaotic = {chaotic}\n"
        );
        crate::spec::parse(&text, false).unwrap()
    }

    /// A spec resumes its own checkpoint whatever its numbers (1e-30 does not survive a
    /// parse-and-compare through JSON, its text does), and no other spec's.
    #[test]
    fn a_checkpoint_is_known_by_its_spec_text() {
        let dir = std::env::temp_dir().join(format!("salient-ckpt-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let (mine, other) = (job("1e-30"), job("1e-29"));
        let (checkpoint, saved) = Checkpoint::open(&dir, &mine, false).unwrap();
        assert_eq!(saved, vec![Vec::new()]);
        checkpoint.append(0, &[]).unwrap();
        assert!(matches!(
            Checkpoint::open(&dir, &mine, false),
            Err(CliError::Usage(_))
        ));
        let Err(CliError::Usage(e)) = Checkpoint::open(&dir, &other, true) else {
            panic!("another spec's checkpoint was accepted");
        };
        assert!(e.contains("another spec"), "{e}");
        let (_, saved) = Checkpoint::open(&dir, &mine, true).unwrap();
        assert_eq!(saved, vec![Vec::new()]);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
