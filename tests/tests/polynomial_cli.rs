//! `salient orbit` on potentials given as text: Hénon–Heiles as text against the built-in,
//! a 3-degree-of-freedom orbit with all six GALIs and its section file, and bad potentials
//! and starting points refused.

use salient_tests::{json_stdout, salient};

const HENON_HEILES: &str = "(q1^2 + q2^2)/2 + q1^2*q2 - q2^3/3";

fn orbit_json(extra: &[&str]) -> serde_json::Value {
    let mut args = vec!["orbit", "--t-final", "1e3", "--json"];
    args.extend_from_slice(extra);
    json_stdout(&salient(&args))
}

/// R1 and C1 with every method family: the same class and status through the polynomial path
/// as through the built-in, R1's SALI within 1e-10.
#[test]
fn henon_heiles_as_text_gives_the_built_in_orbits() {
    for method in ["tm-sbab2c", "dop853", "taylor", "taylor-dd"] {
        for (name, q2) in [("R1", "0.558"), ("C1", "-0.25")] {
            let start = ["--q2", q2, "--p2", "0", "--method", method];
            let built_in = orbit_json(&start);
            let mut text = start.to_vec();
            text.extend_from_slice(&["--potential", HENON_HEILES]);
            let text = orbit_json(&text);
            assert_eq!(built_in["system"], "henon-heiles");
            assert_eq!(text["system"], "polynomial");
            assert_eq!(text["potential"], HENON_HEILES);
            for key in ["class", "status", "dof"] {
                assert_eq!(built_in[key], text[key], "{method} {name} {key}");
            }
            if built_in["class"] == "regular" {
                let (a, b) = (built_in["sali"].as_f64(), text["sali"].as_f64());
                assert!((a.unwrap() - b.unwrap()).abs() < 1e-10, "{method} {name}");
            }
        }
    }
}

/// The FPU-β chain by name: an 8-particle orbit with the first normal mode excited keeps its
/// energy, and orbit.json records the potential it expanded to.
#[test]
fn a_named_fpu_beta_chain_runs_by_name() {
    // q_i = A sin(iπ/9), the first normal mode of 8 particles with fixed ends.
    let q: Vec<String> = (1..=8)
        .map(|i| format!("{:.6}", 0.3 * (i as f64 * std::f64::consts::PI / 9.0).sin()))
        .collect();
    let v = orbit_json(&[
        "--system",
        "fpu-beta",
        "--beta",
        "1.5",
        "--dof",
        "8",
        "--q",
        &q.join(","),
        "--p",
        "0,0,0,0,0,0,0,0",
        "--method",
        "tm-sbab2c",
        "--tau",
        "0.05",
    ]);
    assert_eq!(v["dof"], 8);
    let potential = v["potential"].as_str().unwrap();
    assert!(
        potential.starts_with("(q1 - 0)^2/2 + (1.5)*(q1 - 0)^4/4 + (q2 - q1)^2/2"),
        "{potential}"
    );
    assert!(
        v["energy_error_max"].as_f64().unwrap() < 1e-5,
        "{}",
        v["energy_error_max"]
    );
    let run = salient(&[
        "orbit",
        "--system",
        "fpu-beta",
        "--dof",
        "8",
        "--q",
        &q.join(","),
        "--p",
        "0,0,0,0,0,0,0,0",
        "--method",
        "tm-sbab2c",
        "--t-final",
        "10",
    ]);
    assert_eq!(run.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&run.stderr).contains("--system fpu-beta needs --beta"));
}

/// Three coupled oscillators from a whole initial point: six GALIs, the energy from the point,
/// and crossings.csv with the section's four coordinates and p1.
#[test]
fn a_three_dof_orbit_reports_every_gali_and_its_section() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("o3");
    let v = orbit_json(&[
        "--potential",
        "q1^2/2 + q2^2 + 1.5*q3^2 + q1^2*q2 + q1^2*q3",
        "--dof",
        "3",
        "--q",
        "0.1,0.05,-0.05",
        "--p",
        "0.15,0.1,0.05",
        "--method",
        "tm-sbab2c",
        "--gali-all",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_eq!(v["dof"], 3);
    assert_eq!(v["class"], "regular");
    let gali = v["gali"].as_object().unwrap();
    assert_eq!(gali.len(), 5, "GALI_2 … GALI_6: {gali:?}");
    // H = ½|p|² + V at the point, by hand: ½(0.0225 + 0.01 + 0.0025) + 0.005 + 0.0025
    // + 0.00375 + 0.0005 − 0.0005.
    let energy = 0.0175 + 0.005 + 0.0025 + 0.00375;
    assert!(
        (v["energy"].as_f64().unwrap() - energy).abs() < 1e-15,
        "{}",
        v["energy"]
    );
    assert_eq!(v["initial"]["q3"], -0.05);
    assert!(v["energy_error_max"].as_f64().unwrap() < 1e-6);
    let crossings = std::fs::read_to_string(out.join("crossings.csv")).unwrap();
    let mut lines = crossings.lines();
    assert_eq!(lines.next(), Some("t,q2,q3,p2,p3,p1"));
    let rows: Vec<&str> = lines.collect();
    assert_eq!(rows.len() as u64, v["crossings"].as_u64().unwrap());
    assert!(rows.len() > 50 && rows.iter().all(|r| r.split(',').count() == 6));
}

/// Each bad potential, size or starting point: exit 2, one line naming the flag and what is
/// wrong, nothing on stdout, nothing written.
#[test]
fn bad_potentials_and_points_are_refused_and_nothing_is_written() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("never");
    let o = out.to_str().unwrap();
    let cases: &[(&[&str], &str)] = &[
        (
            &["--potential", "q1^2 + q3", "--q2", "0.1", "--p2", "0"],
            "q3 is not a coordinate",
        ),
        (
            &["--potential", "q1 / q2", "--q2", "0.1", "--p2", "0"],
            "division by an expression",
        ),
        (
            &["--potential", "q1^2 +", "--q2", "0.1", "--p2", "0"],
            "at character 7: expected a number",
        ),
        (
            &[
                "--potential",
                "q1^2",
                "--dof",
                "5",
                "--q",
                "0,0",
                "--p",
                "1,1",
            ],
            "--dof must be one of",
        ),
        (
            &[
                "--potential",
                "q1^2+q2^2+q3^2",
                "--dof",
                "3",
                "--q2",
                "0.1",
                "--p2",
                "0",
            ],
            "--q and --p",
        ),
        (
            &[
                "--potential",
                "q1^2+q2^2+q3^2",
                "--dof",
                "3",
                "--q",
                "0,0",
                "--p",
                "1,1,1",
            ],
            "--q needs 3",
        ),
        (&["--q", "0,0.1", "--p", "0.3,nan"], "--p"),
        (
            &["--potential", "q1^2 + q2^2", "--q2", "2", "--p2", "0"],
            "--energy",
        ),
    ];
    for (extra, says) in cases {
        let mut args = vec![
            "orbit",
            "--method",
            "tm-sbab2c",
            "--t-final",
            "10",
            "--out",
            o,
        ];
        args.extend_from_slice(extra);
        let run = salient(&args);
        let stderr = String::from_utf8_lossy(&run.stderr);
        assert_eq!(run.status.code(), Some(2), "{extra:?}: {stderr}");
        assert_eq!(stderr.trim().lines().count(), 1, "{extra:?}: {stderr}");
        assert!(stderr.contains(says), "{extra:?}: {stderr}");
        assert!(run.stdout.is_empty() && !out.exists(), "{extra:?}");
    }
}
