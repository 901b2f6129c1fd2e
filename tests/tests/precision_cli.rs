//! `salient precision` end to end: rows for every setting, files, and bad input; `--grid`:
//! whole grids against a cached or given reference.

use salient_tests::{json_stdout, run_dirs, salient, write_spec};

#[test]
fn precision_runs_every_setting_against_the_reference() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("p");
    let v = json_stdout(&salient(&[
        "precision",
        "--t-final",
        "10",
        "--json",
        "--out",
        out.to_str().unwrap(),
    ]));
    let rows = v["rows"].as_array().unwrap();
    // 6 schemes × 6 τ, dop853 and taylor 5 δ × 2 protocols, taylor-dd 3 δ × 2 protocols.
    assert_eq!(rows.len(), 62);
    for r in rows {
        for key in [
            "method",
            "tau",
            "delta",
            "protocol",
            "order",
            "steps",
            "wall_s",
            "ns_per_step",
            "energy_error_max",
            "state_error",
            "sali",
            "class",
        ] {
            assert!(r.get(key).is_some(), "{key} missing in {r}");
        }
        assert_eq!(r["class"], "regular", "{r}");
    }
    let find = |m: &str, tau: f64| {
        rows.iter()
            .find(|r| r["method"] == m && r["tau"] == tau)
            .unwrap()
    };
    // Errors fall with the step as the order says: SRKN14a at τ = 0.2 beats SBAB2 at τ = 0.01.
    let e_srkn = find("tm-srkn14a", 0.2)["state_error"].as_f64().unwrap();
    let e_sbab2 = find("tm-sbab2", 0.01)["state_error"].as_f64().unwrap();
    assert!(e_srkn < e_sbab2, "{e_srkn:e} vs {e_sbab2:e}");
    // Taylor orders follow Jorba–Zou.
    let t5 = rows
        .iter()
        .find(|r| r["method"] == "taylor" && r["delta"] == 1e-5)
        .unwrap();
    assert_eq!(t5["order"], 7);
    for f in [
        "precision.md",
        "precision.csv",
        "precision.json",
        "work_precision.png",
    ] {
        assert!(out.join(f).exists(), "{f}");
    }
    let csv = std::fs::read_to_string(out.join("precision.csv")).unwrap();
    assert_eq!(csv.lines().count(), 63);
}

/// `args` exit with status 2 and one line on stderr that names `needle`.
fn assert_refused_in_one_line(args: &[&str], needle: &str) {
    let out = salient(args);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{args:?}: {stderr}");
    assert!(
        stderr.contains(needle) && stderr.trim().lines().count() == 1,
        "{args:?}: {stderr}"
    );
}

#[test]
fn precision_refuses_bad_orbits_and_times() {
    for (args, flag) in [
        (vec!["precision", "--orbit", "R9"], "--orbit"),
        (vec!["precision", "--orbit", "0.1,nan"], "--orbit"),
        (vec!["precision", "--orbit", "0.6,0.45"], "--energy"),
        (vec!["precision", "--t-final", "0.1"], "--t-final"),
    ] {
        assert_refused_in_one_line(&args, flag);
    }
}

/// Hénon–Heiles' potential as text.
const HH_TEXT: &str = "(q1^2 + q2^2)/2 + q1^2*q2 - q2^3/3";

/// The ladder runs on a potential given as text: Hénon–Heiles written out gives, setting by
/// setting, the built-in's classes and end points to within the methods' own errors, and a
/// 3-dof system runs from a whole point given by --q and --p.
#[test]
fn precision_runs_the_ladder_on_polynomial_systems() {
    let built_in = json_stdout(&salient(&["precision", "--t-final", "5", "--json"]));
    let as_text = json_stdout(&salient(&[
        "precision",
        "--potential",
        HH_TEXT,
        "--orbit",
        "0.558,0",
        "--t-final",
        "5",
        "--json",
    ]));
    assert_eq!(as_text["system"], "polynomial");
    assert_eq!(as_text["potential"], HH_TEXT);
    assert_eq!(as_text["orbit"]["q"], built_in["orbit"]["q"]);
    assert_eq!(as_text["orbit"]["p"], built_in["orbit"]["p"]);
    let (a, b) = (
        built_in["rows"].as_array().unwrap(),
        as_text["rows"].as_array().unwrap(),
    );
    assert_eq!(a.len(), b.len());
    for (x, y) in a.iter().zip(b) {
        for key in [
            "method", "tau", "delta", "protocol", "order", "class", "status",
        ] {
            assert_eq!(x[key], y[key], "{key}: {x} vs {y}");
        }
        // The two differ by rounding only; against the reference each keeps its error, down to
        // the round-off the end point carries after 5 time units.
        let (ex, ey) = (
            x["state_error"].as_f64().unwrap(),
            y["state_error"].as_f64().unwrap(),
        );
        assert!((ex - ey).abs() <= 1e-3 * ex.max(ey) + 1e-13, "{x} vs {y}");
    }

    let space = json_stdout(&salient(&[
        "precision",
        "--potential",
        "(q1^2 + 2*q2^2 + 3*q3^2)/2 + q1^2*q2 + q1^2*q3",
        "--dof",
        "3",
        "--q",
        "0,0.1,-0.05",
        "--p",
        "0.3,0.1,0.2",
        "--t-final",
        "5",
        "--json",
    ]));
    assert_eq!(space["dof"], 3);
    let rows = space["rows"].as_array().unwrap();
    assert_eq!(rows.len(), 62);
    let energy = space["orbit"]["energy"].as_f64().unwrap();
    let expected = 0.5 * (0.09 + 0.01 + 0.04) + 0.5 * (2.0 * 0.01 + 3.0 * 0.0025);
    assert!((energy - expected).abs() < 1e-15, "{energy} vs {expected}");
    assert_eq!(space["reference"]["q_end"].as_array().unwrap().len(), 3);
    // A sixth-order scheme at τ = 0.01 is far closer to the reference than a second-order one
    // at τ = 0.5.
    let error = |m: &str, tau: f64| {
        rows.iter()
            .find(|r| r["method"] == m && r["tau"] == tau)
            .unwrap()["state_error"]
            .as_f64()
            .unwrap()
    };
    assert!(error("tm-srkn14a", 0.01) < 1e-3 * error("tm-sbab2", 0.5));
}

#[test]
fn precision_refuses_orbits_its_system_does_not_have() {
    for (args, needle) in [
        (
            vec!["precision", "--potential", HH_TEXT, "--orbit", "R1"],
            "Hénon–Heiles orbits",
        ),
        (vec!["precision", "--potential", HH_TEXT], "--orbit Q2,P2"),
        (
            vec![
                "precision",
                "--potential",
                "q1^2+q2^2+q3^2",
                "--dof",
                "3",
                "--orbit",
                "0.1,0",
            ],
            "--q and --p",
        ),
        (
            vec!["precision", "--q", "0,0.1", "--p", "0.3"],
            "--p needs 2",
        ),
        (
            vec!["precision", "--potential", "q1^2 + q3", "--orbit", "0.1,0"],
            "--potential",
        ),
    ] {
        assert_refused_in_one_line(&args, needle);
    }
}

/// A 20×20 grid at t = 1e3 with a deliberately loose method beside a finer one.
const SMALL_GRID: &str = r#"
name = "small"
[system]
kind = "henon-heiles"
energy = 0.125
[grid]
cells = [20, 20]
tile = [10, 10]
mode = "MODE"
[sweep]
method = ["tm-sbab2", "tm-sbab2c"]
tau = [0.5, 0.05]
t_final = [1e3]
"#;

fn grid_precision(spec: &str, extra: &[&str]) -> serde_json::Value {
    let mut args = vec!["precision", "--grid", spec, "--json"];
    args.extend_from_slice(extra);
    json_stdout(&salient(&args))
}

fn differing(row: &serde_json::Value, against: &str) -> u64 {
    row[against]["differing"].as_u64().unwrap()
}

#[test]
fn grid_precision_counts_cells_against_a_cached_reference() {
    let dir = tempfile::tempdir().unwrap();
    let spec = write_spec(
        dir.path(),
        "small.toml",
        &SMALL_GRID.replace("MODE", "fast-pss"),
    );
    let cache = dir.path().join("cache");
    let out = dir.path().join("out");
    let (cache_s, out_s) = (cache.to_str().unwrap(), out.to_str().unwrap());
    let first = grid_precision(
        &spec,
        &[
            "--cache",
            cache_s,
            "--out",
            out_s,
            "--fast-vs-full",
            "--threads",
            "2",
        ],
    );
    let rows = first["rows"].as_array().unwrap();
    assert_eq!(rows.len(), 4);
    assert_eq!(first["references"][0]["origin"], "computed");
    for row in rows {
        let c = &row["against_reference"];
        let pairs: u64 = c["pairs"]
            .as_array()
            .unwrap()
            .iter()
            .map(|p| p["cells"].as_u64().unwrap())
            .sum();
        assert_eq!(pairs, differing(row, "against_reference"), "{row}");
        assert!(c["compatible"].as_u64().unwrap() > 250, "{row}");
        assert!(
            row["fast_vs_full"]["compatible"] == c["compatible"],
            "{row}"
        );
    }
    // SBAB2 at τ = 0.5 is far from the tight reference.
    let loose = rows
        .iter()
        .find(|r| r["method"] == "tm-sbab2" && r["tau"] == 0.5)
        .unwrap();
    assert!(differing(loose, "against_reference") > 0, "{loose}");
    for f in [
        "grid_precision.md",
        "grid_precision.csv",
        "grid_precision.json",
        "misclassified_vs_cpu.png",
    ] {
        assert!(out.join(f).is_file(), "{f}");
    }
    assert_eq!(run_dirs(&out).len(), 4);

    // Again: the reference comes from the cache, and every count is the same.
    let again = grid_precision(&spec, &["--cache", cache_s, "--fast-vs-full"]);
    assert_eq!(again["references"][0]["origin"], "cached");
    for (a, b) in rows.iter().zip(again["rows"].as_array().unwrap()) {
        assert_eq!(a["against_reference"], b["against_reference"]);
        assert_eq!(a["fast_vs_full"], b["fast_vs_full"]);
    }
}

#[test]
fn a_run_given_as_its_own_reference_differs_nowhere() {
    let dir = tempfile::tempdir().unwrap();
    let spec = write_spec(
        dir.path(),
        "full.toml",
        &SMALL_GRID
            .replace("MODE", "full")
            .replace(r#"tau = [0.5, 0.05]"#, "tau = [0.5]"),
    );
    let out = dir.path().join("run");
    let run = salient(&["run", &spec, "--out", out.to_str().unwrap()]);
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let sbab2 = &run_dirs(&out)[0];
    let v = grid_precision(&spec, &["--reference", sbab2.to_str().unwrap()]);
    let rows = v["rows"].as_array().unwrap();
    assert_eq!(v["references"][0]["origin"], "given");
    assert_eq!(differing(&rows[0], "against_reference"), 0, "{}", rows[0]);
    assert_eq!(
        rows[0]["against_reference"]["percent_errors"]["regular"],
        0.0
    );
    // SBAB2C is another method: some cells differ from SBAB2's map.
    assert!(differing(&rows[1], "against_reference") > 0, "{}", rows[1]);
}

#[test]
fn grid_precision_refuses_a_reference_of_another_grid_or_without_classes() {
    let dir = tempfile::tempdir().unwrap();
    let spec = write_spec(
        dir.path(),
        "small.toml",
        &SMALL_GRID.replace("MODE", "fast-pss"),
    );
    let other = write_spec(
        dir.path(),
        "other.toml",
        &SMALL_GRID
            .replace("MODE", "full")
            .replace("cells = [20, 20]", "cells = [10, 20]"),
    );
    let out = dir.path().join("other");
    assert!(salient(&["run", &other, "--out", out.to_str().unwrap()])
        .status
        .success());
    let other_run = run_dirs(&out)[0].to_str().unwrap().to_string();
    let empty = dir.path().to_str().unwrap().to_string();
    for (args, says) in [
        (
            vec!["precision", "--grid", &spec, "--reference", &other_run],
            "[10, 20]",
        ),
        (
            vec!["precision", "--grid", &spec, "--reference", &empty],
            "class.npy",
        ),
        (vec!["precision", "--reference", &other_run], "--grid"),
        (
            vec!["precision", "--grid", &spec, "--orbit", "R1"],
            "--orbit",
        ),
    ] {
        let o = salient(&args);
        let stderr = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{args:?}: {stderr}");
        assert!(stderr.contains(says), "{args:?}: {stderr}");
    }
}
