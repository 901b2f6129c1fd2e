//! `salient precision` end to end: rows for every setting, files, and bad input.

use salient_tests::{json_stdout, salient};

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

#[test]
fn precision_refuses_bad_orbits_and_times() {
    for (args, flag) in [
        (vec!["precision", "--orbit", "R9"], "--orbit"),
        (vec!["precision", "--orbit", "0.1,nan"], "--orbit"),
        (vec!["precision", "--orbit", "0.6,0.45"], "--energy"),
        (vec!["precision", "--t-final", "0.1"], "--t-final"),
    ] {
        let out = salient(&args);
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{args:?}: {stderr}");
        assert!(
            stderr.contains(flag) && stderr.trim().lines().count() == 1,
            "{args:?}: {stderr}"
        );
    }
}
