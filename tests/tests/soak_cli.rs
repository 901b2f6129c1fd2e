//! The soak test of the distributed mode (`scripts/soak.sh`) in short: a few random jobs under
//! worker and coordinator kills and stops, with a fixed seed so that a failure replays. The
//! script exits non-zero when a job does not finish within its deadline or when its results
//! differ from `salient run`'s; this test fails with the script's output then.

use salient_tests::salient_path;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// The seed of the short soak: the specs and the order of the chaos actions follow from it.
const SEED: &str = "424242";
/// The script's own deadlines bound it well within this; past it the script is stopped.
const TIMEOUT: Duration = Duration::from_secs(600);

#[test]
fn a_short_soak_with_kills_and_stops_finishes_every_job_with_salient_runs_outputs() {
    let repo = Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("the repository root");
    let dir = tempfile::tempdir().unwrap();
    let log_path = dir.path().join("soak.log");
    let log = std::fs::File::create(&log_path).unwrap();
    let bin = salient_path();
    let mut child = Command::new("bash")
        .arg(repo.join("scripts/soak.sh"))
        .args([
            "--seed",
            SEED,
            "--jobs",
            "10",
            "--chaos-events",
            "20",
            "--lease-seconds",
            "1",
            "--max-workers",
            "4",
            "--deadline",
            "120",
            "--bin",
        ])
        .arg(&bin)
        .current_dir(repo)
        // The script's work folder goes to this test's temporary folder.
        .env("TMPDIR", dir.path())
        .env_remove("SALIENT_COORDINATOR")
        .env_remove("SALIENT_TOKEN")
        .stdin(Stdio::null())
        .stdout(log.try_clone().unwrap())
        .stderr(log)
        .spawn()
        .expect("run bash scripts/soak.sh");
    let start = Instant::now();
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break Some(s);
        }
        if start.elapsed() > TIMEOUT {
            // SIGTERM lets the script's trap stop the processes it started.
            let _ = Command::new("kill")
                .args(["-TERM", &child.id().to_string()])
                .status();
            let stop = Instant::now();
            while child.try_wait().unwrap().is_none() && stop.elapsed() < Duration::from_secs(30) {
                std::thread::sleep(Duration::from_millis(100));
            }
            let _ = child.kill();
            let _ = child.wait();
            break None;
        }
        std::thread::sleep(Duration::from_millis(200));
    };
    let output = std::fs::read_to_string(&log_path).unwrap_or_default();
    let failure = match status {
        Some(s) if !s.success() => Some(format!("failed ({s})")),
        Some(_) if !output.contains("soak: PASS") => Some("exited 0 without its PASS line".into()),
        Some(_) => None,
        None => Some(format!("ran past {} s", TIMEOUT.as_secs())),
    };
    if let Some(why) = failure {
        // The script keeps its work folder (logs, store, outputs) on failure: keep it too.
        let kept = dir.keep();
        panic!(
            "scripts/soak.sh --seed {SEED} {why}; its work folder is under {}:\n{output}",
            kept.display()
        );
    }
    // Shown with --nocapture: the summary line (jobs, kills, stops, jobs/s, worst finish).
    println!("{output}");
}
