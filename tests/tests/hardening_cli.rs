//! What an operator can get wrong, or what can go wrong under them, met with a clear refusal or
//! a bounded wait, never with a wrong or partial result: unwritable and full outputs, damaged
//! and read-only stores, exposed listeners, failed authentication, dead workers, a coordinator
//! that restarts under a waiting client, a worker stopped after its coordinator died.

use salient_tests::cluster::{
    assert_same_outputs, client, coordinator, coordinator_with, output_within, spawn, wait_for,
    wait_results, worker, Proc,
};
use salient_tests::{json_stdout, run_embedded, salient, salient_path, write_spec};
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::time::{Duration, Instant};

/// A full-mode job of `cells`² cells in tiles of `tile`², one run of `t_final`.
fn full_spec(dir: &Path, name: &str, cells: u32, tile: u32, t_final: f64) -> String {
    write_spec(
        dir,
        &format!("{name}.toml"),
        &format!(
            "name = \"{name}\"\n[system]\nkind = \"henon-heiles\"\nenergy = 0.125\n[grid]\n\
             cells = [{cells}, {cells}]\ntile = [{tile}, {tile}]\nmode = \"full\"\n[sweep]\n\
             method = [\"tm-sbab2c\"]\ntau = [0.5]\nt_final = [{t_final:e}]\n"
        ),
    )
}

/// Every file under `dir` with its bytes, by path relative to `dir`.
fn snapshot(dir: &Path) -> Vec<(PathBuf, Vec<u8>)> {
    let mut files = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap().flatten() {
            let p = e.path();
            if p.is_dir() {
                stack.push(p);
            } else {
                files.push((
                    p.strip_prefix(dir).unwrap().to_path_buf(),
                    std::fs::read(&p).unwrap(),
                ));
            }
        }
    }
    files.sort();
    files
}

/// A refusal comes before anything starts; a coordinator that started instead would run on.
const REFUSAL_WITHIN: Duration = Duration::from_secs(20);

fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

#[test]
fn a_run_that_fails_writing_leaves_the_older_outputs_as_they_were() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let out = d.join("out");
    let first = full_spec(d, "outputs", 20, 10, 200.0);
    json_stdout(&salient(&[
        "run",
        &first,
        "--json",
        "--out",
        out.to_str().unwrap(),
    ]));
    let before = snapshot(&out);
    assert!(before.iter().any(|(p, _)| p.ends_with("table.md")));
    // Another τ writes another run folder. The file size limit makes the first large write
    // fail as on a full disk (EFBIG instead of ENOSPC); SIGXFSZ ignored, so the write returns
    // the error instead of the signal killing the process.
    let second = write_spec(
        d,
        "second.toml",
        &std::fs::read_to_string(&first)
            .unwrap()
            .replace("tau = [0.5]", "tau = [0.25]"),
    );
    let script = format!(
        "trap '' XFSZ; ulimit -f 8; exec '{}' run '{second}' --out '{}'",
        salient_path().display(),
        out.display()
    );
    let failed = Command::new("bash").args(["-c", &script]).output().unwrap();
    assert_eq!(failed.status.code(), Some(1), "{}", stderr(&failed));
    assert!(
        stderr(&failed).contains("File too large"),
        "{}",
        stderr(&failed)
    );
    // The outputs are as they were; only the checkpoint of the committed outcomes is new, and
    // --resume finishes the run from it once files can be written.
    let checkpoint = Path::new(".salient-checkpoint");
    let after: Vec<_> = snapshot(&out)
        .into_iter()
        .filter(|(p, _)| !p.starts_with(checkpoint))
        .collect();
    assert_eq!(
        after, before,
        "a failed run changed the output folder or left partial files"
    );
    assert!(stderr(&failed).contains("--resume"), "{}", stderr(&failed));
    let resumed = salient(&["run", &second, "--resume", "--out", out.to_str().unwrap()]);
    assert!(resumed.status.success(), "{}", stderr(&resumed));
    assert!(!out.join(checkpoint).exists());
}

/// Runs `salient` as an unprivileged user: directly when this process is one, through
/// `setpriv` as nobody when it is root (root writes read-only files regardless), with a copy
/// of the binary in `dir` (the checkout may lie where nobody cannot reach it). `None` when
/// neither is possible: no `setpriv`, or `dir` itself out of nobody's reach.
#[cfg(unix)]
fn salient_unprivileged(dir: &Path, args: &[&str]) -> Option<Output> {
    let probe = tempfile::NamedTempFile::new().unwrap();
    let mut perms = std::fs::metadata(probe.path()).unwrap().permissions();
    perms.set_readonly(true);
    std::fs::set_permissions(probe.path(), perms).unwrap();
    let privileged = std::fs::OpenOptions::new()
        .write(true)
        .open(probe.path())
        .is_ok();
    let mut cmd = if privileged {
        if Command::new("setpriv").arg("--version").output().is_err() || !others_reach(dir) {
            return None;
        }
        let bin = dir.join("salient-copy");
        if !bin.exists() {
            std::fs::copy(salient_path(), &bin).unwrap();
            chmod(&bin, 0o755);
        }
        let mut c = Command::new("setpriv");
        c.args(["--reuid=65534", "--regid=65534", "--clear-groups"])
            .arg(bin);
        c
    } else {
        Command::new(salient_path())
    };
    Some(output_within(
        cmd.args(args).env_remove("SALIENT_TOKEN"),
        REFUSAL_WITHIN,
    ))
}

/// Whether a user with no rights of owner or group can reach `dir` (every folder above it
/// lets others through).
#[cfg(unix)]
fn others_reach(dir: &Path) -> bool {
    use std::os::unix::fs::PermissionsExt;
    dir.ancestors()
        .all(|a| std::fs::metadata(a).is_ok_and(|m| m.permissions().mode() & 0o001 != 0))
}

#[cfg(unix)]
fn chmod(p: &Path, mode: u32) {
    use std::os::unix::fs::PermissionsExt;
    std::fs::set_permissions(p, std::fs::Permissions::from_mode(mode)).unwrap();
}

#[cfg(unix)]
#[test]
fn read_only_outputs_and_stores_are_refused_before_any_work() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    chmod(d, 0o755);
    let spec = full_spec(d, "ro", 20, 10, 200.0);
    chmod(Path::new(&spec), 0o644);
    let out = d.join("out");
    std::fs::create_dir(&out).unwrap();
    chmod(&out, 0o555);
    let Some(refused) = salient_unprivileged(d, &["run", &spec, "--out", out.to_str().unwrap()])
    else {
        // Straight to stderr: the test harness shows it even when the test passes.
        let _ = std::io::Write::write_all(
            &mut std::io::stderr(),
            b"skipped: read-only refusals: running as root without setpriv, or the temporary folder is out of nobody's reach\n",
        );
        return;
    };
    let text = stderr(&refused);
    assert_eq!(refused.status.code(), Some(2), "{text}");
    assert!(
        text.contains("--out") && text.contains("nothing was computed"),
        "{text}"
    );
    assert!(
        !text.contains("done"),
        "it computed before refusing: {text}"
    );

    // A store file this user may not write, in a folder it may: refused at start.
    let stores = d.join("stores");
    std::fs::create_dir(&stores).unwrap();
    chmod(&stores, 0o777);
    let refusal = |db: &Path| {
        let db = db.to_str().unwrap();
        let args = ["coordinator", "--listen", "127.0.0.1:0", "--db", db];
        let refused = salient_unprivileged(d, &args).unwrap();
        let text = stderr(&refused);
        assert!(!refused.status.success(), "{text}");
        text
    };
    let db = stores.join("ro.db");
    std::fs::write(&db, b"").unwrap();
    chmod(&db, 0o444);
    let text = refusal(&db);
    assert!(
        text.contains("cannot be opened for writing") && text.contains("ro.db"),
        "{text}"
    );
    // A folder that accepts no new files (SQLite's WAL goes there): refused at start.
    let locked = d.join("locked");
    std::fs::create_dir(&locked).unwrap();
    chmod(&locked, 0o555);
    let text = refusal(&locked.join("s.db"));
    assert!(text.contains("does not accept new files"), "{text}");
}

/// Runs a small job to the end on a coordinator with its store at `d/coordinator.db`, then
/// stops the coordinator cleanly (its WAL is folded into the file). Returns the job id.
fn finished_job_in_store(d: &Path) -> u64 {
    let spec = full_spec(d, "stored", 12, 6, 100.0);
    let (mut c, url) = coordinator(d, "127.0.0.1:0", "coordinator-1.log");
    let _w = worker(d, &url, 1);
    let job = json_stdout(&client(&["submit", &spec, "--json"], &url))["job"]
        .as_u64()
        .unwrap();
    let first = d.join("first");
    wait_results(&url, job, &first);
    terminate(&mut c, Duration::from_secs(30));
    job
}

/// SIGTERM, then waits for the exit; panics past `limit`. Returns the exit status.
fn terminate(p: &mut Proc, limit: Duration) -> std::process::ExitStatus {
    let ok = Command::new("kill")
        .args(["-TERM", &p.0.id().to_string()])
        .status()
        .unwrap();
    assert!(ok.success());
    exit_within(p, limit)
}

fn exit_within(p: &mut Proc, limit: Duration) -> std::process::ExitStatus {
    let start = Instant::now();
    loop {
        if let Some(s) = p.0.try_wait().unwrap() {
            return s;
        }
        assert!(start.elapsed() < limit, "still running after {limit:?}");
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// Flips one bit in the middle of every copy of `pattern` in the file (SQLite may leave stale
/// copies of a row in free space; the live one is among them).
fn flip_byte_of(path: &Path, pattern: &[u8]) {
    let mut bytes = std::fs::read(path).unwrap();
    let at: Vec<usize> = bytes
        .windows(pattern.len())
        .enumerate()
        .filter(|(_, w)| *w == pattern)
        .map(|(k, _)| k)
        .collect();
    assert!(!at.is_empty(), "the outcome is in the database file");
    for k in at {
        bytes[k + pattern.len() / 2] ^= 0x10;
    }
    std::fs::write(path, bytes).unwrap();
}

#[test]
fn a_damaged_store_is_refused_with_a_message_and_never_served() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let job = finished_job_in_store(d);
    let db = d.join("coordinator.db");
    assert!(
        !d.join("coordinator.db-wal").exists(),
        "the WAL was folded in at stop"
    );
    let stored: Vec<u8> = {
        let conn = rusqlite::Connection::open(&db).unwrap();
        conn.query_row(
            "SELECT data FROM outcomes WHERE job = ?1 ORDER BY seq LIMIT 1 OFFSET 20",
            [job as i64],
            |r| r.get(0),
        )
        .unwrap()
    };
    let intact = std::fs::read(&db).unwrap();
    flip_byte_of(&db, &stored);

    // One flipped byte in an outcome: the coordinator starts (the job is finished, nothing to
    // resume), but its results are refused, naming the store and the cell.
    let (_c, url) = coordinator(d, "127.0.0.1:0", "coordinator-2.log");
    let out = d.join("served");
    let refused = client(
        &["results", &job.to_string(), "--out", out.to_str().unwrap()],
        &url,
    );
    let text = stderr(&refused);
    assert!(
        !refused.status.success(),
        "damaged results were served: {text}"
    );
    assert!(
        text.contains("damaged")
            && text.contains("fails its checksum")
            && text.contains("coordinator.db"),
        "{text}"
    );
    assert!(!out.join("table.md").exists());
    drop(_c);

    // Half the file gone: refused at start with what to do.
    std::fs::write(&db, &intact[..intact.len() / 2]).unwrap();
    let _ = std::fs::remove_file(d.join("coordinator.db-wal"));
    let start = output_within(
        Command::new(salient_path()).args([
            "coordinator",
            "--listen",
            "127.0.0.1:0",
            "--db",
            db.to_str().unwrap(),
        ]),
        REFUSAL_WITHIN,
    );
    let text = stderr(&start);
    assert!(!start.status.success(), "{text}");
    assert!(text.contains("coordinator.db is damaged"), "{text}");
    assert!(text.contains("restore it from a backup"), "{text}");
}

/// The poll interval is bounded, and a worker is never taken for dead within 5 polls.
#[test]
fn coordinator_timing_flags_are_checked_before_it_starts() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("c.db");
    for (flags, says) in [
        (
            &["--poll-ms", "5"][..],
            "--poll-ms must be in 10..=5000 (got 5)",
        ),
        (
            &["--poll-ms", "2000"][..],
            "--worker-timeout-seconds must be at least 5 polls of --poll-ms (10 s; got 5)",
        ),
    ] {
        let out = output_within(
            Command::new(salient_path())
                .args(["coordinator", "--listen", "127.0.0.1:0", "--db"])
                .arg(&db)
                .args(flags),
            REFUSAL_WITHIN,
        );
        let text = stderr(&out);
        assert_eq!(out.status.code(), Some(2), "{text}");
        assert!(text.contains(says), "{text}");
        assert!(!db.exists(), "no store is made for a refused start");
    }
}

#[test]
fn exposed_listeners_need_a_token_and_failed_logins_are_logged() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let refused = output_within(
        Command::new(salient_path())
            .args(["coordinator", "--listen", "0.0.0.0:0", "--db"])
            .arg(d.join("open.db"))
            .env_remove("SALIENT_TOKEN"),
        REFUSAL_WITHIN,
    );
    let text = stderr(&refused);
    assert_eq!(refused.status.code(), Some(2), "{text}");
    assert!(
        text.contains("--insecure") && text.contains("--token-file"),
        "{text}"
    );
    assert!(
        !d.join("open.db").exists(),
        "refused before opening the store"
    );

    // A token from a file, on an exposed address; a client with the wrong one is refused and
    // the coordinator logs who tried what, not the token.
    let token_file = d.join("token");
    std::fs::write(&token_file, "file-token-123\n").unwrap();
    let (_c, url) = coordinator_with(
        d,
        "0.0.0.0:0",
        "coordinator.log",
        &["--token-file", token_file.to_str().unwrap()],
    );
    let url = url.replace("0.0.0.0", "127.0.0.1");
    let wrong = Command::new(salient_path())
        .args(["status", "--coordinator", &url, "--token", "not-the-token"])
        .output()
        .unwrap();
    assert!(!wrong.status.success());
    assert!(
        stderr(&wrong).contains("bearer token"),
        "{}",
        stderr(&wrong)
    );
    let right = Command::new(salient_path())
        .args([
            "status",
            "--coordinator",
            &url,
            "--token-file",
            token_file.to_str().unwrap(),
        ])
        .env_remove("SALIENT_TOKEN")
        .output()
        .unwrap();
    assert!(right.status.success(), "{}", stderr(&right));
    let log = std::fs::read_to_string(d.join("coordinator.log")).unwrap();
    let line = log
        .lines()
        .find(|l| l.contains("authentication failed"))
        .unwrap_or_else(|| panic!("no failed authentication logged: {log}"));
    assert!(line.contains("127.0.0.1:"), "{line}");
    assert!(line.contains("/salient.v1.ClientService/Status"), "{line}");
    assert!(
        !log.contains("not-the-token") && !log.contains("file-token-123"),
        "{log}"
    );

    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        for f in ["coordinator.db", "coordinator.db-wal"] {
            let mode = std::fs::metadata(d.join(f)).unwrap().permissions().mode() & 0o777;
            assert_eq!(mode, 0o600, "{f}");
        }
    }
}

#[test]
fn a_dead_workers_leases_go_to_another_within_seconds() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    // Four tiles of 10×10 cells at t = 1e5: a second or so each on one thread.
    let spec = full_spec(d, "dead", 20, 10, 1e5);
    // The default 30 s lease: recovery must come from the missed polls, not from the lease.
    let (_c, url) = coordinator_with(d, "127.0.0.1:0", "coordinator.log", &[]);
    let mut w1 = worker(d, &url, 1);
    let job = json_stdout(&client(&["submit", &spec, "--json"], &url))["job"]
        .as_u64()
        .unwrap();
    wait_for("worker 1 to hold a lease", Duration::from_secs(30), || {
        std::fs::read_to_string(d.join("coordinator.log"))
            .unwrap()
            .contains(" leased ")
    });
    w1.0.kill().unwrap();
    w1.0.wait().unwrap();
    let killed = Instant::now();
    let _w2 = worker(d, &url, 2);
    let dist = d.join("dist");
    wait_results(&url, job, &dist);
    let took = killed.elapsed();
    let log = std::fs::read_to_string(d.join("coordinator.log")).unwrap();
    assert!(log.contains("worker silent"), "{log}");
    assert!(
        !log.contains("lease lapsed"),
        "recovered by the lease, not by missed polls: {log}"
    );
    // The whole job takes a few seconds on one thread; waiting out a lease would take 30.
    assert!(
        took < Duration::from_secs(25),
        "finished {took:?} after the kill"
    );
    let emb = d.join("emb");
    run_embedded(&spec, &emb);
    assert_same_outputs(&emb, &dist);
}

#[test]
fn a_waiting_client_rides_out_a_coordinator_restart() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let spec = full_spec(d, "restart", 12, 6, 100.0);
    let (mut c, url) = coordinator(d, "127.0.0.1:0", "coordinator-1.log");
    let job = json_stdout(&client(&["submit", &spec, "--json"], &url))["job"]
        .as_u64()
        .unwrap();
    // No worker yet: the job waits, and so do the clients.
    let dist = d.join("dist");
    let mut results = spawn(
        &[
            "results",
            &job.to_string(),
            "--wait",
            "--json",
            "--coordinator",
            &url,
            "--out",
        ]
        .into_iter()
        .chain([dist.to_str().unwrap()])
        .collect::<Vec<_>>(),
        &d.join("results.log"),
    );
    let mut watch = spawn(
        &["watch", &job.to_string(), "--coordinator", &url],
        &d.join("watch.log"),
    );
    std::thread::sleep(Duration::from_millis(800));
    c.0.kill().unwrap();
    c.0.wait().unwrap();
    std::thread::sleep(Duration::from_secs(2));
    let listen = url.trim_start_matches("http://").to_string();
    let (_c2, url2) = coordinator(d, &listen, "coordinator-2.log");
    assert_eq!(url, url2);
    let _w = worker(d, &url, 1);
    let status = exit_within(&mut results, Duration::from_secs(60));
    let log = std::fs::read_to_string(d.join("results.log")).unwrap();
    assert!(status.success(), "results --wait: {status:?}: {log}");
    assert!(log.contains("out of reach"), "{log}");
    assert!(dist.join("table.md").exists());
    let status = exit_within(&mut watch, Duration::from_secs(30));
    let log = std::fs::read_to_string(d.join("watch.log")).unwrap();
    assert!(status.success(), "watch: {status:?}: {log}");
}

#[test]
fn a_worker_stopped_while_its_coordinator_is_unresponsive_exits_within_its_drain_time() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let spec = full_spec(d, "orphan", 30, 15, 1e6);
    let (c, url) = coordinator(d, "127.0.0.1:0", "coordinator.log");
    let mut w = spawn(
        &[
            "worker",
            "--coordinator",
            &url,
            "--threads",
            "1",
            "--drain-seconds",
            "2",
        ],
        &d.join("worker.log"),
    );
    json_stdout(&client(&["submit", &spec, "--json"], &url));
    wait_for(
        "the worker to hold a lease",
        Duration::from_secs(30),
        || {
            std::fs::read_to_string(d.join("coordinator.log"))
                .unwrap()
                .contains(" leased ")
        },
    );
    // A stopped coordinator is the hard case of one that is gone: connections stay open and
    // nothing answers, so every call of the worker's waits (a killed one refuses at once).
    let ok = Command::new("kill")
        .args(["-STOP", &c.0.id().to_string()])
        .status()
        .unwrap();
    assert!(ok.success());
    std::thread::sleep(Duration::from_millis(500));
    // 2 s of drain, 2 s at most to say goodbye to nobody, and slack for a loaded machine.
    let status = terminate(&mut w, Duration::from_secs(10));
    let log = std::fs::read_to_string(d.join("worker.log")).unwrap();
    assert!(status.success(), "{status:?}: {log}");
    assert!(log.contains("worker stopped"), "{log}");
}

#[test]
fn submit_wait_prints_the_job_with_its_results_and_writes_only_where_told() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let spec = full_spec(d, "waited", 12, 6, 100.0);
    let (_c, url) = coordinator(d, "127.0.0.1:0", "coordinator.log");
    let _w = worker(d, &url, 1);
    let cwd = d.join("cwd");
    std::fs::create_dir(&cwd).unwrap();
    let submit = |extra: &[&str]| {
        let mut cmd = Command::new(salient_path());
        cmd.args(["submit", &spec, "--wait", "--json", "--coordinator", &url])
            .args(extra)
            .env("SALIENT_TOKEN", salient_tests::cluster::TOKEN)
            .current_dir(&cwd);
        json_stdout(&output_within(&mut cmd, Duration::from_secs(120)))
    };
    let v = submit(&[]);
    assert!(v["job"].as_u64().is_some(), "{v}");
    assert_eq!(v["runs"].as_array().unwrap().len(), 1, "{v}");
    assert_eq!(
        std::fs::read_dir(&cwd).unwrap().count(),
        0,
        "submit --wait without --out wrote files"
    );
    let out = d.join("written");
    let v = submit(&["--out", out.to_str().unwrap()]);
    assert!(v["job"].as_u64().is_some(), "{v}");
    assert!(out.join("table.md").exists());
    let job = v["job"].as_u64().unwrap().to_string();
    let again = json_stdout(&client(
        &["results", &job, "--json", "--out", out.to_str().unwrap()],
        &url,
    ));
    assert_eq!(again["job"], v["job"]);

    let missing = client(&["results", "99"], &url);
    assert_eq!(missing.status.code(), Some(2));
    assert_eq!(stderr(&missing).trim(), "error: no job 99");
}
