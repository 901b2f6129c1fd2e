//! The distributed mode end to end with real processes on loopback: a coordinator, workers,
//! and the client commands. The acceptance test of the mode: `salient results` writes files
//! byte-identical to `salient run`'s, also across a coordinator killed and restarted mid-job.

use salient_tests::cluster::{
    assert_same_outputs, client, coordinator, coordinator_with, field, spawn, submit_and_run,
    wait_for, wait_results, worker, Proc, TOKEN,
};
use salient_tests::{json_stdout, run_embedded, salient, salient_path, write_spec};
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// Orbits of a million steps and more tell the coordinator what they cross while they run
/// (the coordinator counts those cells in its "run done" line); the results stay those of
/// `salient run`.
#[test]
fn long_orbits_tell_their_crossings_and_change_no_result() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let spec = write_spec(
        d,
        "spec.toml",
        r#"
name = "crossings"
[system]
kind = "henon-heiles"
energy = 0.125
[grid]
cells = [12, 12]
tile = [4, 4]
mode = "fast-pss"
[sweep]
method = ["tm-sbab2c"]
tau = [0.001]
t_final = [1e3]
"#,
    );
    let (_c, url) = coordinator(d, "127.0.0.1:0", "coordinator.log");
    let _w: Vec<Proc> = (1..=2).map(|n| worker(d, &url, n)).collect();
    submit_and_run(d, &spec, &url);
    let log = std::fs::read_to_string(d.join("coordinator.log")).unwrap();
    let done = log
        .lines()
        .find(|l| l.contains("run done"))
        .expect("a run done line");
    let said: u64 = done
        .split_whitespace()
        .find_map(|f| f.strip_prefix("crossings="))
        .expect("crossings in the run done line")
        .parse()
        .unwrap();
    assert!(said > 0, "{done}");
}

#[test]
fn distributed_results_equal_salient_run_byte_for_byte() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let spec = write_spec(
        d,
        "spec.toml",
        r#"
name = "dist"
[system]
kind = "henon-heiles"
energy = 0.125
[grid]
cells = [40, 36]
tile = [10, 9]
[sweep]
method = ["tm-sbab2c", "dop853"]
tau = [0.5]
t_final = [1e3]
delta = [1e-6]
"#,
    );
    let (_c, url) = coordinator(d, "127.0.0.1:0", "coordinator.log");
    let _w: Vec<Proc> = (1..=2).map(|n| worker(d, &url, n)).collect();

    // Without the token the coordinator refuses clients.
    let out = Command::new(salient_path())
        .args(["status", "--coordinator", &url])
        .env_remove("SALIENT_TOKEN")
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("token"));

    let (summary, embedded) = submit_and_run(d, &spec, &url);
    assert_eq!(summary["runs"].as_array().unwrap().len(), 2);
    let emb = d.join("emb");
    for (a, b) in summary["runs"]
        .as_array()
        .unwrap()
        .iter()
        .zip(embedded["runs"].as_array().unwrap())
    {
        assert_eq!(a["percent"], b["percent"]);
        assert_eq!(a["counts"], b["counts"]);
        assert_eq!(a["orbits_integrated"], b["orbits_integrated"]);
    }

    // status knows the job; results can be fetched again; an unknown job is bad input.
    let st = json_stdout(&client(&["status", "--json"], &url));
    assert_eq!(st["jobs"][0]["state"], "done");
    assert_eq!(st["workers"], 2);
    let again = d.join("again");
    let out = client(
        &["results", "1", "--json", "--out", again.to_str().unwrap()],
        &url,
    );
    json_stdout(&out);
    assert_same_outputs(&emb, &again);
    let out = client(&["results", "7"], &url);
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("no job 7"));
    // watch on a finished job prints its final state.
    let out = client(&["watch", "1"], &url);
    assert!(out.status.success());
    assert_eq!(String::from_utf8_lossy(&out.stdout).trim(), "job 1 done");
    // A long job is cancelled: its leases are revoked and it has no results.
    let long = write_spec(
        d,
        "long.toml",
        &std::fs::read_to_string(&spec)
            .unwrap()
            .replace("t_final = [1e3]", "t_final = [1e8]"),
    );
    let job = json_stdout(&client(&["submit", &long, "--json"], &url))["job"]
        .as_u64()
        .unwrap();
    assert_eq!(job, 2);
    let out = client(&["cancel", "2"], &url);
    assert!(out.status.success());
    assert_eq!(
        String::from_utf8_lossy(&out.stdout).trim(),
        "job 2 cancelled"
    );
    let out = client(&["results", "2"], &url);
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("job 2 is cancelled"));
    let out = client(&["watch", "2"], &url);
    assert_eq!(out.status.code(), Some(1));
    // A bad spec never reaches the coordinator.
    let bad = write_spec(d, "bad.toml", "[system]\nkind = \"henon-heiles\"\nenergy = 0.125\n[grid]\ncells = [0, 4]\n[sweep]\nmethod = [\"tm-sbab2c\"]\ntau = [0.5]\nt_final = [10.0]\n");
    let out = client(&["submit", &bad], &url);
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("grid.cells"));
    // An energy sweep: a grid per energy, and the same files as `salient run`.
    let e = d.join("energy");
    std::fs::create_dir_all(&e).unwrap();
    let text = std::fs::read_to_string(&spec).unwrap();
    let swept = text
        .replace("energy = 0.125\n", "")
        .replace("[sweep]", "[sweep]\nenergy = [0.1, 0.15]");
    let (summary, _) = submit_and_run(&e, &write_spec(&e, "energy.toml", &swept), &url);
    let energies: Vec<f64> = summary["runs"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| r["energy"].as_f64().unwrap())
        .collect();
    assert_eq!(energies, [0.1, 0.1, 0.15, 0.15]);
    // A mode sweep: full mode and fast PSS of one spec, each leased by its own rule, the same
    // files as `salient run`; the full-mode runs with the per-cell indicators.
    let m = d.join("mode");
    std::fs::create_dir_all(&m).unwrap();
    let swept = text.replace("[sweep]", "[sweep]\nmode = [\"full\", \"fast-pss\"]")
        + "[integration]\nindicators = true\n";
    let (summary, _) = submit_and_run(&m, &write_spec(&m, "mode.toml", &swept), &url);
    let modes: Vec<&str> = summary["runs"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| r["mode"].as_str().unwrap())
        .collect();
    assert_eq!(modes, ["full", "full", "fast-pss", "fast-pss"]);
    let indicators: Vec<bool> = summary["runs"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| r["indicators"].as_bool().unwrap())
        .collect();
    assert_eq!(indicators, [true, true, false, false]);
}

#[test]
fn a_coordinator_killed_mid_job_resumes_and_workers_drain_on_sigterm() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let spec = write_spec(
        d,
        "spec.toml",
        r#"
name = "restart"
[system]
kind = "henon-heiles"
energy = 0.125
[grid]
cells = [40, 40]
tile = [5, 5]
mode = "full"
[sweep]
method = ["tm-sbab2c"]
tau = [0.5]
t_final = [2e5]
"#,
    );
    // Long enough (~1 s on two idle cores) that the coordinator dies mid-job: at t = 2e4 the
    // whole job took 0.1 s and the first status already saw most of it done.
    let (mut c, url) = coordinator(d, "127.0.0.1:0", "coordinator-1.log");
    let mut workers: Vec<Proc> = (1..=2).map(|n| worker(d, &url, n)).collect();
    let out = client(&["submit", &spec, "--json"], &url);
    let job = json_stdout(&out)["job"].as_u64().unwrap();
    // Let some outcomes be committed, then kill the coordinator without warning.
    let mut progress = (0, 0);
    wait_for("some committed outcomes", Duration::from_secs(60), || {
        let st = json_stdout(&client(&["status", &job.to_string(), "--json"], &url));
        let run = &st["jobs"][0]["runs"][0];
        progress = (
            run["resolved"].as_u64().unwrap(),
            run["compatible"].as_u64().unwrap(),
        );
        progress.0 > 50
    });
    assert!(
        progress.0 < progress.1 / 2,
        "the job must be far from done: {progress:?}"
    );
    c.0.kill().unwrap();
    c.0.wait().unwrap();
    std::thread::sleep(Duration::from_millis(500));
    // Same address, same store: the workers reconnect, re-register and resend.
    let listen = url.trim_start_matches("http://").to_string();
    let (_c2, url2) = coordinator(d, &listen, "coordinator-2.log");
    assert_eq!(url, url2);
    let dist = d.join("dist");
    let out = client(
        &[
            "results",
            &job.to_string(),
            "--wait",
            "--json",
            "--out",
            dist.to_str().unwrap(),
        ],
        &url,
    );
    json_stdout(&out);
    let log = std::fs::read_to_string(d.join("coordinator-2.log")).unwrap();
    assert!(log.contains("resumed"), "{log}");
    // Committed work is not redone: the restarted coordinator leases at most the cells that
    // had no committed outcome (full mode: every compatible cell once).
    let resumed = field(
        log.lines().find(|l| l.contains("resumed")).unwrap(),
        "resolved=",
    );
    let leased_after: u64 = log
        .lines()
        .filter(|l| l.contains(" leased "))
        .map(|l| field(l, "cells="))
        .sum();
    assert!(resumed > 0);
    assert!(
        leased_after + resumed <= progress.1,
        "leased {leased_after} after resuming {resumed} of {}",
        progress.1
    );

    let emb = d.join("emb");
    json_stdout(&salient(&[
        "run",
        &spec,
        "--threads",
        "2",
        "--json",
        "--out",
        emb.to_str().unwrap(),
    ]));
    assert_same_outputs(&emb, &dist);

    // SIGTERM: the workers drain and exit 0.
    for w in &workers {
        let ok = Command::new("kill")
            .args(["-TERM", &w.0.id().to_string()])
            .status()
            .unwrap();
        assert!(ok.success());
    }
    for w in &mut workers {
        let start = Instant::now();
        let status = loop {
            if let Some(s) = w.0.try_wait().unwrap() {
                break s;
            }
            assert!(
                start.elapsed() < Duration::from_secs(30),
                "worker did not drain"
            );
            std::thread::sleep(Duration::from_millis(50));
        };
        assert!(status.success(), "worker exit {status:?}");
    }
    let wlog = std::fs::read_to_string(d.join("worker-1.log")).unwrap();
    assert!(
        wlog.contains("draining") && wlog.contains("worker stopped"),
        "{wlog}"
    );
}

fn fixture(name: &str) -> String {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("fixtures/tls")
        .join(name)
        .to_str()
        .unwrap()
        .to_string()
}

#[test]
fn tls_with_a_private_ca_and_the_health_service() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let spec = write_spec(d, "spec.toml",
        "name = \"tls\"\n[system]\nkind = \"henon-heiles\"\nenergy = 0.125\n[grid]\ncells = [16, 16]\ntile = [8, 8]\n[sweep]\nmethod = [\"tm-sbab2c\"]\ntau = [0.5]\nt_final = [500.0]\n",
    );
    let (cert, key, ca) = (
        fixture("server.pem"),
        fixture("server.key"),
        fixture("ca.pem"),
    );
    let (_c, url) = coordinator_with(
        d,
        "127.0.0.1:0",
        "coordinator.log",
        &["--tls-cert", &cert, "--tls-key", &key],
    );
    let url = url.replace("http://", "https://");
    let _w = spawn(
        &[
            "worker",
            "--coordinator",
            &url,
            "--threads",
            "1",
            "--tls-ca",
            &ca,
        ],
        &d.join("worker.log"),
    );
    let out = d.join("out");
    let summary = json_stdout(&client(
        &[
            "submit",
            &spec,
            "--wait",
            "--json",
            "--tls-ca",
            &ca,
            "--out",
            out.to_str().unwrap(),
        ],
        &url,
    ));
    assert!(summary["runs"][0]["orbits_integrated"].as_u64().unwrap() > 0);
    let emb = d.join("emb");
    run_embedded(&spec, &emb);
    assert_same_outputs(&emb, &out);
    // Without the CA the client refuses the coordinator's certificate, and says what to give.
    let refused = client(&["status"], &url);
    assert_eq!(refused.status.code(), Some(1));
    let text = String::from_utf8_lossy(&refused.stderr);
    assert!(text.contains("--tls-ca"), "{text}");
    // Plain HTTP to a TLS port: the hint names https.
    let plain = client(&["status"], &url.replace("https://", "http://"));
    assert_eq!(plain.status.code(), Some(1));
    let text = String::from_utf8_lossy(&plain.stderr);
    assert!(text.contains("use an https:// URL"), "{text}");
    // Certificate and key swapped: refused at start, naming the mistake.
    let swapped = salient(&[
        "coordinator",
        "--tls-cert",
        &key,
        "--tls-key",
        &cert,
        "--db",
        d.join("swapped.db").to_str().unwrap(),
    ]);
    assert_eq!(swapped.status.code(), Some(2));
    let text = String::from_utf8_lossy(&swapped.stderr);
    assert!(text.contains("swapped"), "{text}");

    // grpc.health.v1 answers SERVING over TLS, without the token (for probes).
    let rt = tokio::runtime::Runtime::new().unwrap();
    let status = rt.block_on(async {
        let tls = tonic::transport::ClientTlsConfig::new().ca_certificate(
            tonic::transport::Certificate::from_pem(std::fs::read(&ca).unwrap()),
        );
        let channel = tonic::transport::Endpoint::from_shared(url.clone())
            .unwrap()
            .tls_config(tls)
            .unwrap()
            .connect()
            .await
            .unwrap();
        let mut health = tonic_health::pb::health_client::HealthClient::new(channel);
        health
            .check(tonic_health::pb::HealthCheckRequest {
                service: "salient.v1.WorkerService".into(),
            })
            .await
            .unwrap()
            .into_inner()
            .status
    });
    assert_eq!(
        status,
        tonic_health::pb::health_check_response::ServingStatus::Serving as i32
    );
}

#[test]
fn a_worker_killed_mid_run_has_its_tile_leased_again() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let spec = write_spec(d, "spec.toml",
        "name = \"kill\"\n[system]\nkind = \"henon-heiles\"\nenergy = 0.125\n[grid]\ncells = [30, 30]\ntile = [15, 15]\nmode = \"full\"\n[sweep]\nmethod = [\"tm-sbab2c\"]\ntau = [0.5]\nt_final = [1e5]\n",
    );
    let (_c, url) = coordinator_with(
        d,
        "127.0.0.1:0",
        "coordinator.log",
        &["--lease-seconds", "1"],
    );
    // Worker 1 registers first, so the coordinator calls it w1.
    let mut w1 = worker(d, &url, 1);
    wait_for("worker 1 to register", Duration::from_secs(30), || {
        std::fs::read_to_string(d.join("coordinator.log"))
            .unwrap()
            .contains("worker registered")
    });
    let _w2 = worker(d, &url, 2);
    let job = json_stdout(&client(&["submit", &spec, "--json"], &url))["job"]
        .as_u64()
        .unwrap();
    wait_for("worker 1 to hold a lease", Duration::from_secs(30), || {
        std::fs::read_to_string(d.join("coordinator.log"))
            .unwrap()
            .contains("worker=\"w1-")
    });
    w1.0.kill().unwrap();
    w1.0.wait().unwrap();
    let dist = d.join("dist");
    wait_results(&url, job, &dist);
    let log = std::fs::read_to_string(d.join("coordinator.log")).unwrap();
    let lapsed = log
        .lines()
        .find(|l| l.contains("lease lapsed"))
        .expect("a lease lapsed");
    let (tile, attempt) = (field(lapsed, "tile="), field(lapsed, "attempt="));
    let again = format!("tile={tile} attempt={}", attempt + 1);
    assert!(
        log.lines()
            .any(|l| l.contains(" leased ") && l.contains(&again) && l.contains("worker=\"w2-")),
        "tile {tile} was not leased again to w2"
    );
    let emb = d.join("emb");
    run_embedded(&spec, &emb);
    assert_same_outputs(&emb, &dist);
}

#[test]
fn oversize_messages_are_refused_and_change_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let (_c, url) = coordinator(dir.path(), "127.0.0.1:0", "coordinator.log");
    let rt = tokio::runtime::Runtime::new().unwrap();
    let (code, jobs) = rt.block_on(async {
        use salient_proto::v1;
        let channel = tonic::transport::Endpoint::from_shared(url.clone())
            .unwrap()
            .connect()
            .await
            .unwrap();
        let token: tonic::metadata::MetadataValue<_> = format!("Bearer {TOKEN}").parse().unwrap();
        let mut client = v1::client_service_client::ClientServiceClient::with_interceptor(
            channel,
            move |mut r: tonic::Request<()>| {
                r.metadata_mut().insert("authorization", token.clone());
                Ok(r)
            },
        )
        .max_encoding_message_size(64 << 20);
        let mut codes = Vec::new();
        for size in [1, 3].map(|k| k * salient_proto::MAX_MESSAGE_BYTES + 1) {
            let huge = vec![b'x'; size];
            let e = client
                .submit(v1::SubmitRequest { spec_json: huge })
                .await
                .unwrap_err();
            codes.push(e.code());
        }
        // Text that is not UTF-8 is bad input, not a server failure.
        let e = client
            .submit(v1::SubmitRequest {
                spec_json: b"{\"name\": \"\xff\xfe\"}".to_vec(),
            })
            .await
            .unwrap_err();
        assert_eq!(e.code(), tonic::Code::InvalidArgument, "{e}");
        assert!(e.message().contains("UTF-8"), "{e}");
        let jobs = client
            .status(v1::StatusRequest { job: None })
            .await
            .unwrap()
            .into_inner()
            .jobs
            .len();
        (codes, jobs)
    });
    assert_eq!(code, [tonic::Code::OutOfRange; 2]);
    assert_eq!(jobs, 0);
}

#[test]
fn a_worker_whose_coordinator_comes_back_on_another_store_forgets_the_old_jobs() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let spec_text = |t_final: &str| {
        format!(
            "name = \"other\"\n[system]\nkind = \"henon-heiles\"\nenergy = 0.125\n[grid]\ncells = [30, 30]\ntile = [10, 10]\nmode = \"full\"\n[sweep]\nmethod = [\"tm-sbab2c\"]\ntau = [0.5]\nt_final = [{t_final}]\n"
        )
    };
    let first = write_spec(d, "first.toml", &spec_text("1e5"));
    let second = write_spec(d, "second.toml", &spec_text("3e3"));
    let db1 = d.join("one.db");
    let (mut c, url) = coordinator_with(
        d,
        "127.0.0.1:0",
        "coordinator-1.log",
        &["--db", db1.to_str().unwrap()],
    );
    let _w = worker(d, &url, 1);
    let job = json_stdout(&client(&["submit", &first, "--json"], &url))["job"]
        .as_u64()
        .unwrap();
    wait_for(
        "the worker to hold a lease",
        Duration::from_secs(30),
        || {
            std::fs::read_to_string(d.join("coordinator-1.log"))
                .unwrap()
                .contains(" leased ")
        },
    );
    c.0.kill().unwrap();
    c.0.wait().unwrap();
    // Same address, a new store: job ids start again at 1, with another spec.
    let listen = url.trim_start_matches("http://").to_string();
    let db2 = d.join("two.db");
    let (_c2, _) = coordinator_with(
        d,
        &listen,
        "coordinator-2.log",
        &["--db", db2.to_str().unwrap()],
    );
    let job2 = json_stdout(&client(&["submit", &second, "--json"], &url))["job"]
        .as_u64()
        .unwrap();
    assert_eq!(job, job2);
    let dist = d.join("dist");
    json_stdout(&client(
        &[
            "results",
            &job2.to_string(),
            "--wait",
            "--json",
            "--out",
            dist.to_str().unwrap(),
        ],
        &url,
    ));
    let emb = d.join("emb");
    json_stdout(&salient(&[
        "run",
        &second,
        "--json",
        "--out",
        emb.to_str().unwrap(),
    ]));
    assert_same_outputs(&emb, &dist);
    let wlog = std::fs::read_to_string(d.join("worker-1.log")).unwrap();
    assert!(wlog.contains("another store"), "{wlog}");
}

/// A six-run sweep of a 200×200 grid: on 2 or 3 workers each worker moves through more runs
/// than it keeps ledgers of, so it makes some run's ledger again, which must then get the
/// worker's own earlier outcomes; without them it abandons, lease after lease, a cell only
/// those outcomes settle, and the job never finishes.
const SIX_RUN_SWEEP: &str = r#"
name = "j200b"
[system]
kind = "henon-heiles"
energy = 0.125
[grid]
cells = [200, 200]
tile = [10, 10]
mode = "fast-pss"
[sweep]
method = ["tm-sbab2c"]
tau = [0.01, 0.015, 0.02]
t_final = [1e4, 2e4]
"#;

/// A small multi-run fast-PSS spec, varied by `k`: tiles, steps and lengths.
fn small_sweep(k: usize) -> String {
    let tiles = [[10, 10], [8, 5], [40, 40], [7, 9]][k % 4];
    let taus = [["0.05", "0.1"], ["0.02", "0.5"], ["0.1", "0.2"]][k % 3];
    format!(
        r#"
name = "burst-{k}"
[system]
kind = "henon-heiles"
energy = 0.125
[grid]
cells = [40, 40]
tile = [{}, {}]
mode = "fast-pss"
[sweep]
method = ["tm-sbab2c"]
tau = [{}, {}]
t_final = [{}e3, 3e3]
"#,
        tiles[0],
        tiles[1],
        taus[0],
        taus[1],
        1 + k % 2
    )
}

/// Fetches job `id`'s results into `out` with `results --wait`, failing the test with the
/// job's status if they have not come within `limit`.
fn results_within(url: &str, id: u64, out: &Path, limit: Duration) {
    let mut child = Command::new(salient_path())
        .args(["results", &id.to_string(), "--wait", "--out"])
        .arg(out)
        .args(["--coordinator", url])
        .env("SALIENT_TOKEN", TOKEN)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let start = Instant::now();
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            assert!(status.success(), "results of job {id}: {status}");
            return;
        }
        if start.elapsed() > limit {
            let _ = child.kill();
            let st = client(&["status", &id.to_string(), "--json"], url);
            panic!(
                "job {id} has not finished in {limit:?}: {}",
                String::from_utf8_lossy(&st.stdout)
            );
        }
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// Every multi-run fast-PSS job finishes on 2 and on 3 single-thread workers, the six-run
/// sweep and a burst of small jobs submitted at once alike, within ten times the embedded
/// single-thread time of them all (plus start-up), and equals `salient run` byte for byte.
#[test]
fn multi_run_fast_pss_jobs_finish_on_two_and_three_workers() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let mut specs = vec![write_spec(d, "sweep.toml", SIX_RUN_SWEEP)];
    specs.extend((0..12).map(|k| write_spec(d, &format!("burst-{k}.toml"), &small_sweep(k))));
    let start = Instant::now();
    for (k, spec) in specs.iter().enumerate() {
        let out = d.join(format!("emb-{k}"));
        json_stdout(&salient(&[
            "run",
            spec,
            "--threads",
            "1",
            "--json",
            "--out",
            out.to_str().unwrap(),
        ]));
    }
    let limit = 10 * start.elapsed() + Duration::from_secs(30);
    for workers in [2, 3] {
        let sub = d.join(format!("w{workers}"));
        std::fs::create_dir(&sub).unwrap();
        let (_c, url) = coordinator(&sub, "127.0.0.1:0", "coordinator.log");
        let _w: Vec<Proc> = (1..=workers).map(|n| worker(&sub, &url, n)).collect();
        let ids: Vec<u64> = specs
            .iter()
            .map(|spec| {
                json_stdout(&client(&["submit", spec, "--json"], &url))["job"]
                    .as_u64()
                    .unwrap()
            })
            .collect();
        let start = Instant::now();
        for (k, &id) in ids.iter().enumerate() {
            let out = sub.join(format!("dist-{k}"));
            results_within(&url, id, &out, limit.saturating_sub(start.elapsed()));
            assert_same_outputs(&d.join(format!("emb-{k}")), &out);
        }
    }
}
