//! A coordinator, workers and client commands as real processes on loopback, for the
//! distributed-mode tests.

use crate::{json_stdout, run_dirs, salient, salient_path};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// The bearer token every process of a test cluster is given.
pub const TOKEN: &str = "s3cret-token";

/// A child process killed when the test ends, whatever happens.
pub struct Proc(pub Child);

impl Drop for Proc {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Starts `salient` with `args`, its stderr written to `log`.
pub fn spawn(args: &[&str], log: &Path) -> Proc {
    let log = std::fs::File::create(log).unwrap();
    Proc(
        Command::new(salient_path())
            .args(args)
            .env("SALIENT_TOKEN", TOKEN)
            .env("RUST_LOG", "info,salient_coordinator=debug")
            .stdout(Stdio::null())
            .stderr(log)
            .spawn()
            .expect("start salient"),
    )
}

/// Waits until `ok` holds, polling every 50 ms; panics after `timeout`, naming `what`.
pub fn wait_for(what: &str, timeout: Duration, mut ok: impl FnMut() -> bool) {
    let start = Instant::now();
    while !ok() {
        assert!(start.elapsed() < timeout, "timed out waiting for {what}");
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// Starts a coordinator on `listen` and returns it with its URL.
pub fn coordinator(dir: &Path, listen: &str, log: &str) -> (Proc, String) {
    coordinator_with(dir, listen, log, &["--lease-seconds", "5"])
}

/// Starts a coordinator on `listen` with arguments `extra` and returns it with its URL.
pub fn coordinator_with(dir: &Path, listen: &str, log: &str, extra: &[&str]) -> (Proc, String) {
    let addr_file = dir.join(format!("{log}.addr"));
    let _ = std::fs::remove_file(&addr_file);
    let db = dir.join("coordinator.db");
    let mut args = vec![
        "coordinator",
        "--listen",
        listen,
        "--address-file",
        addr_file.to_str().unwrap(),
    ];
    // The default store unless `extra` names one.
    if !extra.contains(&"--db") {
        args.extend(["--db", db.to_str().unwrap()]);
    }
    args.extend_from_slice(extra);
    let p = spawn(&args, &dir.join(log));
    wait_for("the coordinator to listen", Duration::from_secs(30), || {
        std::fs::read_to_string(&addr_file).is_ok_and(|a| a.ends_with('\n'))
    });
    let addr = std::fs::read_to_string(&addr_file).unwrap();
    (p, format!("http://{}", addr.trim()))
}

/// Starts worker `n` (one thread, named `w<n>`) against the coordinator at `url`.
pub fn worker(dir: &Path, url: &str, n: usize) -> Proc {
    spawn(
        &[
            "worker",
            "--coordinator",
            url,
            "--threads",
            "1",
            "--name",
            &format!("w{n}"),
        ],
        &dir.join(format!("worker-{n}.log")),
    )
}

/// Runs a client command against the coordinator at `url` and returns its output.
pub fn client(args: &[&str], url: &str) -> std::process::Output {
    Command::new(salient_path())
        .args(args)
        .args(["--coordinator", url])
        .env("SALIENT_TOKEN", TOKEN)
        .output()
        .expect("run salient")
}

/// Every per-cell file of every run is byte-identical.
pub fn assert_same_outputs(a: &Path, b: &Path) {
    let (da, db) = (run_dirs(a), run_dirs(b));
    assert_eq!(da.len(), db.len());
    assert!(!da.is_empty());
    for (x, y) in da.iter().zip(&db) {
        assert_eq!(x.file_name(), y.file_name());
        for f in [
            "cells.csv",
            "class.npy",
            "sali.npy",
            "class_map.svg",
            "map.svg",
        ] {
            let (bx, by) = (
                std::fs::read(x.join(f)).unwrap(),
                std::fs::read(y.join(f)).unwrap(),
            );
            assert!(
                bx == by,
                "{} differs between {} and {}",
                f,
                x.display(),
                y.display()
            );
        }
        // The per-cell indicators' files, in runs that have them.
        for f in [
            "mle.npy",
            "megno.npy",
            "megno_mean.npy",
            "fli.npy",
            "megno_map.svg",
        ] {
            let (bx, by) = (std::fs::read(x.join(f)).ok(), std::fs::read(y.join(f)).ok());
            assert!(
                bx == by,
                "{} differs between {} and {} (or is in one only)",
                f,
                x.display(),
                y.display()
            );
        }
    }
}

/// The number after `key` in a log line.
pub fn field(line: &str, key: &str) -> u64 {
    let at = line
        .find(key)
        .unwrap_or_else(|| panic!("no {key} in {line}"))
        + key.len();
    line[at..]
        .split(|c: char| !c.is_ascii_digit())
        .next()
        .unwrap()
        .parse()
        .unwrap()
}

/// Runs `cmd` to its end and returns its output, killing it and failing the test when it is
/// still running after `limit` (a command expected to refuse at once must not hang a test).
pub fn output_within(cmd: &mut Command, limit: Duration) -> std::process::Output {
    let mut child = cmd
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start the command");
    let start = Instant::now();
    while child.try_wait().expect("wait").is_none() {
        if start.elapsed() > limit {
            let _ = child.kill();
            let out = child.wait_with_output().expect("collect the output");
            panic!(
                "still running after {limit:?}: {}",
                String::from_utf8_lossy(&out.stderr)
            );
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    child.wait_with_output().expect("collect the output")
}

/// `salient results JOB --wait --json --out OUT`, which must succeed; its JSON summary.
pub fn wait_results(url: &str, job: u64, out: &Path) -> serde_json::Value {
    crate::json_stdout(&client(
        &[
            "results",
            &job.to_string(),
            "--wait",
            "--json",
            "--out",
            out.to_str().expect("a UTF-8 path"),
        ],
        url,
    ))
}

/// Submits `spec` with `--wait` (results into `d/dist`), runs it embedded (into `d/emb`), checks
/// that the two wrote the same files, and gives both `--json` summaries.
pub fn submit_and_run(d: &Path, spec: &str, url: &str) -> (serde_json::Value, serde_json::Value) {
    let (dist, emb) = (d.join("dist"), d.join("emb"));
    let submitted = [
        "submit",
        spec,
        "--wait",
        "--json",
        "--out",
        dist.to_str().unwrap(),
    ];
    let summary = json_stdout(&client(&submitted, url));
    let run = [
        "run",
        spec,
        "--threads",
        "2",
        "--json",
        "--out",
        emb.to_str().unwrap(),
    ];
    let embedded = json_stdout(&salient(&run));
    assert_same_outputs(&emb, &dist);
    (summary, embedded)
}
