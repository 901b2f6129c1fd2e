//! `salient orbit` end to end: the JSON contract, the output files, and bad flags.

use salient_tests::{json_stdout, salient};

#[test]
fn r1_json_follows_the_contract() {
    let out = salient(&[
        "orbit",
        "--q2",
        "0.558",
        "--p2",
        "0",
        "--method",
        "tm-sbab2c",
        "--tau",
        "0.05",
        "--t-final",
        "1e4",
        "--json",
    ]);
    let v = json_stdout(&out);
    for key in [
        "method",
        "tau",
        "delta",
        "t_final",
        "t_reached",
        "status",
        "class",
        "sali",
        "gali",
        "mle",
        "energy_error_max",
        "steps",
        "crossings",
        "wall_s",
        "ns_per_step",
    ] {
        assert!(v.get(key).is_some(), "missing key {key} in {v}");
    }
    assert_eq!(v["method"], "tm-sbab2c");
    assert_eq!(v["status"], "ok");
    assert_eq!(v["class"], "regular");
    assert_eq!(v["steps"], 200_000);
    assert_eq!(v["t_reached"], 1e4);
    assert!(v["sali"].as_f64().unwrap() > 1e-2);
    assert!(v["gali"]["2"].as_f64().unwrap() > 1e-2);
    assert!(v["energy_error_max"].as_f64().unwrap() < 5e-7);
    assert!(v["crossings"].as_u64().unwrap() > 100);
    assert!(v["ns_per_step"].as_f64().unwrap() > 0.0);
}

#[test]
fn c1_stops_early_as_chaotic() {
    let out = salient(&[
        "orbit",
        "--q2",
        "-0.25",
        "--p2",
        "0",
        "--method",
        "tm-sbab2c",
        "--t-final",
        "1e4",
        "--json",
    ]);
    let v = json_stdout(&out);
    assert_eq!(v["status"], "chaotic-early-stop");
    assert_eq!(v["class"], "chaotic");
    assert!(v["t_reached"].as_f64().unwrap() < 1000.0);
}

#[test]
fn out_dir_gets_series_crossings_plots_and_summary() {
    let dir = tempfile::tempdir().unwrap();
    let out_dir = dir.path().join("r1");
    let out = salient(&[
        "orbit",
        "--q2",
        "0.558",
        "--p2",
        "0",
        "--method",
        "tm-srkn14a",
        "--tau",
        "0.1",
        "--t-final",
        "1e3",
        "--gali-all",
        "--out",
        out_dir.to_str().unwrap(),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let series = std::fs::read_to_string(out_dir.join("series.csv")).unwrap();
    let mut lines = series.lines();
    assert_eq!(
        lines.next().unwrap(),
        "t,sali,gali_2,gali_3,gali_4,mle,megno,megno_mean,fli,energy_error"
    );
    let rows: Vec<Vec<f64>> = lines
        .map(|l| l.split(',').map(|x| x.parse().unwrap()).collect())
        .collect();
    assert!(rows.len() >= 60, "{} rows", rows.len());
    assert_eq!(rows.last().unwrap()[0], 1e3);
    assert!(rows.windows(2).all(|w| w[1][0] > w[0][0]), "times increase");
    let crossings = std::fs::read_to_string(out_dir.join("crossings.csv")).unwrap();
    assert!(crossings.starts_with("t,q2,p2,p1\n") && crossings.lines().count() > 10);
    for png in ["indicators.png", "energy.png", "section.png"] {
        let bytes = std::fs::read(out_dir.join(png)).unwrap();
        assert!(
            bytes.starts_with(b"\x89PNG\r\n\x1a\n") && bytes.len() > 5000,
            "{png}"
        );
    }
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out_dir.join("orbit.json")).unwrap())
            .unwrap();
    assert_eq!(summary["class"], "regular");
    assert!(summary["gali"]["4"].as_f64().unwrap() > 0.0);
}

#[test]
fn bad_flags_exit_2_with_one_line_naming_the_flag_and_write_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let out_dir = dir.path().join("never");
    let o = out_dir.to_str().unwrap();
    let base = [
        "orbit",
        "--q2",
        "0.558",
        "--p2",
        "0",
        "--method",
        "tm-sbab2c",
        "--out",
        o,
    ];
    let cases: &[(&[&str], &str)] = &[
        (&["--tau", "-0.1", "--t-final", "10"], "--tau"),
        (&["--tau", "0", "--t-final", "10"], "--tau"),
        (&["--tau", "NaN", "--t-final", "10"], "--tau"),
        (&["--tau", "0.5", "--t-final", "0.1"], "--t-final"),
        (&["--t-final", "inf"], "--t-final"),
        (&["--t-final", "1e30"], "--t-final"),
        (&["--t-final", "10", "--energy", "0.01"], "--energy"),
        (&["--t-final", "10", "--energy", "nan"], "--energy"),
        (&["--t-final", "10", "--delta", "-1"], "--delta"),
        (
            &["--t-final", "10", "--chaotic", "1e-3", "--regular", "1e-4"],
            "--chaotic",
        ),
        (
            &["--t-final", "10", "--samples-per-decade", "5000"],
            "--samples-per-decade",
        ),
    ];
    for (extra, flag) in cases {
        let mut args: Vec<&str> = base.to_vec();
        args.extend_from_slice(extra);
        let out = salient(&args);
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{extra:?}: {stderr}");
        assert_eq!(stderr.trim().lines().count(), 1, "{extra:?}: {stderr}");
        assert!(
            stderr.contains(flag),
            "{extra:?}: message does not name {flag}: {stderr}"
        );
        assert!(out.stdout.is_empty(), "{extra:?}");
        assert!(!out_dir.exists(), "{extra:?} wrote {o}");
    }
    // Unknown method: the message lists the allowed ones.
    let out = salient(&[
        "orbit",
        "--q2",
        "0.558",
        "--p2",
        "0",
        "--method",
        "rk4",
        "--t-final",
        "10",
    ]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2));
    assert!(
        stderr.contains("--method") && stderr.contains("tm-sbab2c"),
        "{stderr}"
    );
    // A point outside the section names the energy it would need.
    let out = salient(&[
        "orbit",
        "--q2",
        "0.6",
        "--p2",
        "0.45",
        "--method",
        "tm-sbab2c",
        "--t-final",
        "10",
    ]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2));
    assert!(
        stderr.contains("--energy") && stderr.contains("allowed"),
        "{stderr}"
    );
}

#[test]
fn dop853_runs_in_both_protocols_and_clamps_delta_with_a_warning() {
    let base = [
        "orbit",
        "--q2",
        "0.558",
        "--p2",
        "0",
        "--method",
        "dop853",
        "--t-final",
        "1e3",
        "--json",
    ];
    let mut sali = Vec::new();
    for protocol in ["restart", "free"] {
        let mut args = base.to_vec();
        args.extend_from_slice(&["--delta", "1e-12", "--protocol", protocol]);
        let v = json_stdout(&salient(&args));
        assert_eq!(v["method"], "dop853");
        assert_eq!(v["protocol"], protocol);
        assert_eq!(v["delta"], 1e-12);
        assert_eq!(v["class"], "regular");
        assert_eq!(v["warnings"].as_array().unwrap().len(), 0);
        sali.push(v["sali"].as_f64().unwrap());
    }
    // heyoka (tol 1e-15) gives SALI(1e3) = 1.2535960837 for R1 with the same deviation vectors.
    for s in &sali {
        assert!((s - 1.253_596_083_7).abs() < 1e-8, "SALI(1e3) = {s}");
    }
    let mut args = base.to_vec();
    args.extend_from_slice(&["--delta", "1e-16"]);
    let v = json_stdout(&salient(&args));
    assert_eq!(v["delta"], 1e-14);
    assert!(v["warnings"][0].as_str().unwrap().contains("1e-16"));
    // A tangent-map method says that it ignores --delta.
    let v = json_stdout(&salient(&[
        "orbit",
        "--q2",
        "0.558",
        "--p2",
        "0",
        "--method",
        "tm-sbab2c",
        "--t-final",
        "10",
        "--delta",
        "1e-8",
        "--json",
    ]));
    assert_eq!(v["delta"], serde_json::Value::Null);
    assert!(v["warnings"][0]
        .as_str()
        .unwrap()
        .contains("--delta is ignored"));
}

#[test]
fn taylor_and_taylor_dd_run_and_dd_reaches_extended_precision() {
    let v = json_stdout(&salient(&[
        "orbit",
        "--q2",
        "0.558",
        "--p2",
        "0",
        "--method",
        "taylor",
        "--delta",
        "1e-15",
        "--t-final",
        "1e3",
        "--json",
    ]));
    assert_eq!(v["class"], "regular");
    assert_eq!(v["order"], 18, "Jorba–Zou order at δ = 1e-15");
    assert!((v["sali"].as_f64().unwrap() - 1.253_596_083_7).abs() < 1e-8);
    let v = json_stdout(&salient(&[
        "orbit",
        "--q2",
        "0.558",
        "--p2",
        "0",
        "--method",
        "taylor-dd",
        "--delta",
        "1e-28",
        "--t-final",
        "100",
        "--protocol",
        "free",
        "--json",
    ]));
    assert_eq!(v["status"], "ok");
    let e = v["energy_error_max"].as_f64().unwrap();
    assert!(e < 1e-20 && e > 0.0, "taylor-dd |ΔH/H| = {e:e}");
}

#[test]
fn people_read_rounded_numbers_and_warnings_on_stderr() {
    // C1 stops early at a time that is a sum of τ's: 370.20000000000005 in full.
    let out = salient(&[
        "orbit",
        "--q2",
        "-0.25",
        "--p2",
        "0",
        "--method",
        "tm-sbab2c",
        "--t-final",
        "1e4",
        "--delta",
        "1e-8",
    ]);
    assert!(out.status.success());
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    let reached = stdout
        .split("t_reached ")
        .nth(1)
        .and_then(|r| r.split_whitespace().next())
        .unwrap_or_else(|| panic!("no t_reached in {stdout}"));
    assert!(
        reached.len() <= 8,
        "t_reached {reached} is not rounded for people"
    );
    assert!(stdout.contains("t_final = 10000"), "{stdout}");
    assert!(
        !stdout.contains("warning") && !stdout.contains("ignored"),
        "{stdout}"
    );
    assert!(stderr.contains("--delta is ignored"), "{stderr}");
}

#[test]
fn series_csv_writes_tiny_numbers_in_scientific_notation() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("c1");
    json_stdout(&salient(&[
        "orbit",
        "--q2",
        "-0.25",
        "--p2",
        "0",
        "--method",
        "tm-sbab2c",
        "--t-final",
        "1e4",
        "--json",
        "--out",
        out.to_str().unwrap(),
    ]));
    let csv = std::fs::read_to_string(out.join("series.csv")).unwrap();
    let widest = csv
        .lines()
        .skip(1)
        .flat_map(|l| l.split(','))
        .map(str::len)
        .max()
        .unwrap();
    assert!(widest <= 24, "a field of {widest} characters in series.csv");
    assert!(csv.contains("e-"), "SALI falls below 1e-8: {csv}");
}
