//! `salient run --resume`: a run stopped by SIGKILL at a random moment, or by SIGTERM, goes on
//! from its checkpoint and ends with the files of an uninterrupted run, byte for byte; a
//! checkpoint of another spec, or one left without `--resume`, is refused.

use salient_tests::{run_dirs, run_embedded, salient, salient_path, write_spec};
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

/// Two runs, the second (DOP853) a few seconds long.
const SPEC: &str = r#"
name = "resume"
[system]
kind = "henon-heiles"
energy = 0.125
[grid]
cells = [80, 80]
[sweep]
method = ["tm-sbab2c", "dop853"]
tau = [0.05]
t_final = [1e4]
delta = [1e-9]
"#;

/// Starts `salient run SPEC --out OUT` with a checkpoint after every commit, stops it with
/// `signal` after `delay`, and returns its exit status.
fn interrupted(spec: &str, out: &Path, delay: Duration, signal: &str) -> Option<i32> {
    let mut child = Command::new(salient_path())
        .args([
            "run",
            spec,
            "--threads",
            "2",
            "--checkpoint-every",
            "0",
            "--out",
        ])
        .arg(out)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    std::thread::sleep(delay);
    let pid = child.id().to_string();
    let killed = Command::new("kill").args([signal, &pid]).status().unwrap();
    assert!(killed.success());
    child.wait().unwrap().code()
}

fn assert_same_cells(a: &Path, b: &Path) {
    let (da, db) = (run_dirs(a), run_dirs(b));
    assert_eq!(da.len(), db.len());
    for (x, y) in da.iter().zip(&db) {
        let (cx, cy) = (
            std::fs::read(x.join("cells.csv")).unwrap(),
            std::fs::read(y.join("cells.csv")).unwrap(),
        );
        assert!(cx == cy, "cells.csv differs in {}", y.display());
    }
}

#[test]
fn runs_stopped_by_sigkill_or_sigterm_resume_to_the_same_bytes() {
    let dir = tempfile::tempdir().unwrap();
    let spec = write_spec(dir.path(), "resume.toml", SPEC);
    let whole = dir.path().join("whole");
    run_embedded(&spec, &whole);
    // A moment drawn from the clock: anywhere in the first run, the second, or between.
    let nanos = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .unwrap()
        .subsec_nanos();
    let random = Duration::from_millis(50 + u64::from(nanos) % 2500);
    for (signal, delay) in [("-KILL", random), ("-TERM", Duration::from_millis(1500))] {
        let out = dir.path().join(format!("stopped{signal}"));
        let status = interrupted(&spec, &out, delay, signal);
        let label = format!("{signal} after {delay:?}");
        if signal == "-TERM" {
            // 128 + 15, with the finished first run's folder in place.
            assert_eq!(status, Some(143), "{label}");
            assert!(
                run_dirs(&out).len() == 1,
                "{label}: the finished run is published"
            );
        }
        let again = salient(&["run", &spec, "--out", out.to_str().unwrap()]);
        if out.join(".salient-checkpoint").exists() {
            assert_eq!(again.status.code(), Some(2), "{label}");
            assert!(String::from_utf8_lossy(&again.stderr).contains("add --resume"));
        }
        let resumed = salient(&["run", &spec, "--resume", "--out", out.to_str().unwrap()]);
        assert!(
            resumed.status.success(),
            "{label}: {}",
            String::from_utf8_lossy(&resumed.stderr)
        );
        assert_same_cells(&whole, &out);
        assert!(!out.join(".salient-checkpoint").exists(), "{label}");
    }
}

#[test]
fn a_checkpoint_of_another_spec_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let spec = write_spec(dir.path(), "resume.toml", SPEC);
    let out = dir.path().join("out");
    interrupted(&spec, &out, Duration::from_millis(1200), "-KILL");
    assert!(out.join(".salient-checkpoint/spec.json").exists());
    let other = write_spec(
        dir.path(),
        "other.toml",
        &SPEC.replace("t_final = [1e4]", "t_final = [2e4]"),
    );
    let refused = salient(&["run", &other, "--resume", "--out", out.to_str().unwrap()]);
    assert_eq!(refused.status.code(), Some(2));
    let err = String::from_utf8_lossy(&refused.stderr);
    assert!(err.contains("another spec"), "{err}");
    // The checkpoint is untouched: its own spec still resumes.
    let resumed = salient(&["run", &spec, "--resume", "--out", out.to_str().unwrap()]);
    assert!(resumed.status.success());
}
