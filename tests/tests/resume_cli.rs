//! `salient run --resume`: a run stopped by SIGKILL at a random moment, or by SIGTERM, goes on
//! from its checkpoint and ends with the files of an uninterrupted run, byte for byte; a
//! checkpoint of another spec, or one left without `--resume`, is refused.

use salient_tests::{run_dirs, run_embedded, salient, salient_path, write_spec};
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

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
/// `signal` once `ready` says so (given the output folder), and returns its exit status (that
/// of a normal end if it finished first).
fn interrupted(spec: &str, out: &Path, signal: &str, ready: impl Fn(&Path) -> bool) -> Option<i32> {
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
    let limit = Instant::now() + Duration::from_secs(120);
    while !ready(out) && Instant::now() < limit && child.try_wait().unwrap().is_none() {
        std::thread::sleep(Duration::from_millis(5));
    }
    let pid = child.id().to_string();
    // It may have ended on its own just now.
    let _ = Command::new("kill")
        .args([signal, &pid])
        .stderr(Stdio::null())
        .status();
    child.wait().unwrap().code()
}

/// Whether the first run's folder is written (in the staging folder): the second is running.
fn first_run_written(out: &Path) -> bool {
    std::fs::read_dir(out).is_ok_and(|entries| {
        entries.flatten().any(|e| {
            e.file_name()
                .to_string_lossy()
                .starts_with(".salient-partial-")
                && std::fs::read_dir(e.path())
                    .is_ok_and(|mut runs| runs.any(|r| r.is_ok_and(|r| r.path().is_dir())))
        })
    })
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
    let started = Instant::now();
    run_embedded(&spec, &whole);
    let wall = started.elapsed();
    // SIGKILL at a moment drawn from the clock within the uninterrupted run's time (the first
    // run, the second, or between); SIGTERM while the second runs.
    let nanos = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .unwrap()
        .subsec_nanos();
    let random = wall.mul_f64(0.05 + 0.85 * f64::from(nanos) / 1e9);
    for signal in ["-KILL", "-TERM"] {
        let out = dir.path().join(format!("stopped{signal}"));
        let label = format!("{signal} (random moment {random:?} of {wall:?})");
        let status = if signal == "-KILL" {
            let deadline = Instant::now() + random;
            interrupted(&spec, &out, signal, |_| Instant::now() >= deadline)
        } else {
            interrupted(&spec, &out, signal, first_run_written)
        };
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
    interrupted(&spec, &out, "-KILL", first_run_written);
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
