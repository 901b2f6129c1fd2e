//! Grids of polynomial systems end to end: Hénon–Heiles written as a polynomial spec against
//! the built-in, a 3-dof full-mode map and a 2-dof section on another plane run by a
//! coordinator and workers as by `salient run`, and bad systems and sections refused.

use salient_tests::cluster::{coordinator, submit_and_run, worker, Proc};
use salient_tests::{run_dirs, run_embedded, salient, write_spec};
use std::path::Path;

const HENON_HEILES: &str = "(q1^2 + q2^2)/2 + q1^2*q2 - q2^3/3";

/// A spec of Hénon–Heiles at H = 1/8 on 40 × 40 cells in `mode`, built in or as `potential`.
fn henon_heiles_spec(mode: &str, potential: Option<&str>) -> String {
    let system = match potential {
        Some(v) => format!("kind = \"polynomial\"\ndof = 2\npotential = \"{v}\""),
        None => "kind = \"henon-heiles\"".into(),
    };
    format!(
        r#"
name = "hh"
[system]
{system}
energy = 0.125
[grid]
cells = [40, 40]
mode = "{mode}"
q2 = [-0.4396926207859084, 0.6736481776669303]
p2 = [-0.5, 0.5]
[sweep]
method = ["tm-sbab2c"]
tau = [0.5]
t_final = [1e3]
"#
    )
}

/// Each cell's class column of the run's cells.csv.
fn classes(out: &Path) -> Vec<String> {
    let dirs = run_dirs(out);
    let text = std::fs::read_to_string(dirs[0].join("cells.csv")).unwrap();
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let at = header.iter().position(|&h| h == "class").unwrap();
    lines
        .map(|l| l.split(',').nth(at).unwrap().to_string())
        .collect()
}

/// Hénon–Heiles as a polynomial spec gives the built-in's classes: all of them in full mode
/// (the orbits differ by rounding only), all but a few in fast PSS (where a rounding-level
/// difference can change which orbit labels a cell first).
#[test]
fn henon_heiles_as_a_polynomial_spec_gives_the_built_in_classes() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    for mode in ["full", "fast-pss"] {
        let text = write_spec(d, "t.toml", &henon_heiles_spec(mode, Some(HENON_HEILES)));
        let built = write_spec(d, "b.toml", &henon_heiles_spec(mode, None));
        let (out_t, out_b) = (d.join(format!("t-{mode}")), d.join(format!("b-{mode}")));
        let summary = run_embedded(&text, &out_t);
        run_embedded(&built, &out_b);
        let (a, b) = (classes(&out_t), classes(&out_b));
        assert_eq!(a.len(), b.len());
        let differ = a.iter().zip(&b).filter(|(x, y)| x != y).count();
        match mode {
            "full" => assert_eq!(differ, 0, "{mode}"),
            _ => assert!(differ * 200 <= a.len(), "{differ} of {} cells", a.len()),
        }
        let run = std::fs::read_to_string(run_dirs(&out_t)[0].join("run.json")).unwrap();
        assert!(run.contains("\"polynomial\""), "{run}");
        assert!(summary.to_string().contains("tm-sbab2c"), "{summary}");
    }
}

/// A 3-dof map in full mode (tangent map and DOP853) and a 2-dof fast-PSS map on the plane
/// q2 = 0: a coordinator with two workers writes what `salient run` writes, byte for byte.
#[test]
fn polynomial_grids_run_distributed_as_embedded() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let space = write_spec(
        d,
        "space.toml",
        r#"
name = "space"
[system]
kind = "polynomial"
dof = 3
potential = "(q1^2 + 2*q2^2 + 3*q3^2)/2 + q1^2*q2 + q1^2*q3"
energy = 0.09
[section]
plane = "q1"
axes = ["q2", "p2"]
fixed = { q3 = 0.0, p3 = 0.0 }
[grid]
cells = [12, 10]
tile = [4, 5]
mode = "full"
q2 = [-0.3, 0.3]
p2 = [-0.42, 0.42]
[sweep]
method = ["tm-sbab2c", "dop853"]
tau = [0.5]
t_final = [200]
delta = [1e-10]
"#,
    );
    let plane = write_spec(
        d,
        "plane.toml",
        &format!(
            r#"
name = "plane"
[system]
kind = "polynomial"
dof = 2
potential = "{HENON_HEILES}"
energy = 0.125
[section]
plane = "q2"
[grid]
cells = [14, 14]
mode = "fast-pss"
q1 = [-0.6, 0.6]
p1 = [-0.5, 0.5]
[sweep]
method = ["tm-sbab2c"]
tau = [0.5]
t_final = [300]
"#
        ),
    );
    let (_c, url) = coordinator(d, "127.0.0.1:0", "coordinator.log");
    let _w: Vec<Proc> = (1..=2).map(|n| worker(d, &url, n)).collect();
    for (name, spec) in [("space", &space), ("plane", &plane)] {
        let into = d.join(name);
        std::fs::create_dir(&into).unwrap();
        submit_and_run(&into, spec, &url);
    }
    // The run's files name the section's axes.
    let run = std::fs::read_to_string(run_dirs(&d.join("plane").join("emb"))[0].join("run.json"))
        .unwrap();
    let run: serde_json::Value = serde_json::from_str(&run).unwrap();
    assert_eq!(run["bounds"]["q1"], serde_json::json!([-0.6, 0.6]), "{run}");
    let csv = std::fs::read_to_string(run_dirs(&d.join("plane").join("emb"))[0].join("cells.csv"))
        .unwrap();
    assert!(csv.starts_with("i,j,q1,p1,sali,"), "{}", &csv[..40]);
    let svg =
        std::fs::read_to_string(run_dirs(&d.join("plane").join("emb"))[0].join("map.svg")).unwrap();
    assert!(
        svg.contains("q₁") && svg.contains("p₁"),
        "the map's axes are q₁ and p₁"
    );
    let cells =
        std::fs::read_to_string(run_dirs(&d.join("space").join("emb"))[0].join("cells.csv"))
            .unwrap();
    let chaotic_or_regular = cells
        .lines()
        .filter(|l| l.contains(",regular,") || l.contains(",chaotic,"))
        .count();
    assert!(chaotic_or_regular > 20, "{cells}");
}

/// Bad systems and sections: exit 2, one line naming the field and what is wrong, nothing
/// written.
#[test]
fn bad_systems_and_sections_are_refused_and_nothing_is_written() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let good = henon_heiles_spec("full", Some(HENON_HEILES));
    let cases = [
        (
            good.replace("q1^2*q2", "q1^2*)"),
            "system.potential is not a polynomial: ",
        ),
        (
            good.replace("q1^2*q2", "q1/q2"),
            "system.potential is not a polynomial: ",
        ),
        (
            good.replace("dof = 2", "dof = 5"),
            "system.dof must be 2 or 3 for a grid",
        ),
        (
            good.replace("[grid]", "[section]\nplane = \"p1\"\n[grid]"),
            "section.plane must be a position",
        ),
        (
            good.replace("mode = \"full\"", "mode = \"full\"\nq3 = [0, 1]"),
            "grid.q3 bounds no axis",
        ),
        (
            good.replace("p2 = [-0.5, 0.5]\n", ""),
            "grid.p2 is required for a polynomial system",
        ),
        (
            good.replace("dof = 2", "dof = 3")
                .replace("mode = \"full\"", "mode = \"fast-pss\"")
                .replace(
                    "[grid]",
                    "[section]\nfixed = { q3 = 0.0, p3 = 0.0 }\n[grid]",
                ),
            "fast PSS runs in 2 degrees of freedom only",
        ),
    ];
    for (k, (text, want)) in cases.iter().enumerate() {
        let spec = write_spec(d, &format!("bad{k}.toml"), text);
        let out = d.join(format!("out{k}"));
        let run = salient(&["run", &spec, "--out", out.to_str().unwrap()]);
        let stderr = String::from_utf8_lossy(&run.stderr);
        assert_eq!(run.status.code(), Some(2), "{want}: {stderr}");
        assert!(stderr.contains(want), "{want}: {stderr}");
        assert_eq!(stderr.trim().lines().count(), 1, "{stderr}");
        assert!(!out.exists(), "{want}: something was written");
    }
}
