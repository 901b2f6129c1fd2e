//! `salient run` end to end: determinism across threads, the output contract, full mode's
//! checkpoints, and bad specs.

use salient_tests::{json_stdout, run_dirs, salient, write_spec};

const SMALL: &str = r#"
name = "small"
[system]
kind = "henon-heiles"
energy = 0.125
[grid]
cells = [40, 40]
tile = [10, 10]
mode = "fast-pss"
[sweep]
method = ["tm-sbab2c"]
tau = [0.5]
t_final = [2e3]
"#;

/// `salient run SPEC --threads THREADS --out OUT --json`, its JSON (the run must succeed).
fn run_json(spec: &str, threads: &str, out: &std::path::Path) -> serde_json::Value {
    json_stdout(&salient(&[
        "run",
        spec,
        "--threads",
        threads,
        "--out",
        out.to_str().unwrap(),
        "--json",
    ]))
}

#[test]
fn cells_csv_is_byte_identical_for_one_and_two_threads() {
    let dir = tempfile::tempdir().unwrap();
    let spec = write_spec(dir.path(), "s.toml", SMALL);
    let mut csv = Vec::new();
    for threads in ["1", "2"] {
        let out = dir.path().join(format!("out{threads}"));
        run_json(&spec, threads, &out);
        csv.push(std::fs::read(run_dirs(&out).remove(0).join("cells.csv")).unwrap());
    }
    assert!(csv[0].len() > 1000);
    assert_eq!(csv[0], csv[1]);
}

/// The tile is a unit of work only: cutting the grid into other tiles changes no byte of
/// cells.csv, while another scan order (the grid's canonical order) changes the labels.
#[test]
fn the_tile_size_changes_no_byte_of_cells_csv_and_the_order_does() {
    let dir = tempfile::tempdir().unwrap();
    let cells_csv = |name: &str, grid_extra: &str| {
        let text = SMALL.replace("tile = [10, 10]", grid_extra);
        let spec = write_spec(dir.path(), &format!("{name}.toml"), &text);
        let out = dir.path().join(name);
        let run = run_json(&spec, "2", &out)["runs"][0].clone();
        let csv = std::fs::read(run_dirs(&out).remove(0).join("cells.csv")).unwrap();
        (csv, run)
    };
    let (reference, run) = cells_csv("t10", "tile = [10, 10]");
    assert!(reference.len() > 1000);
    assert_eq!(run["order"], "q2-outer");
    for tile in [
        "tile = [7, 13]",
        "tile = [40, 40]",
        "tile = [1, 1]",
        "tile = [3, 40]",
    ] {
        let name = tile.replace(|c: char| !c.is_ascii_digit(), "_");
        assert!(
            cells_csv(&name, tile).0 == reference,
            "{tile} changed cells.csv"
        );
    }
    let (shuffled, run) = cells_csv(
        "shuffle",
        "tile = [10, 10]\norder = \"shuffle\"\norder_seed = 5",
    );
    assert_eq!(
        (run["order"].as_str(), run["order_seed"].as_u64()),
        (Some("shuffle"), Some(5))
    );
    assert!(
        shuffled != reference,
        "a shuffled order labels the cells otherwise"
    );
    let (reversed, _) = cells_csv("reversed", "tile = [10, 10]\norder = \"p2-outer-reversed\"");
    assert!(reversed != reference && reversed != shuffled);
}

/// In a sweep, a run with the τ and t_final of an earlier one takes that run's labellers as a
/// forecast for scheduling (run.json names it), and its cells.csv is byte for byte that of the
/// same run alone.
#[test]
fn a_sweep_forecast_leaves_cells_csv_unchanged() {
    let dir = tempfile::tempdir().unwrap();
    let sweep = SMALL
        .replace(
            r#"method = ["tm-sbab2c"]"#,
            r#"method = ["tm-sbab2c", "dop853"]"#,
        )
        .replace("tau = [0.5]", "tau = [0.05]\ndelta = [1e-8]")
        .replace("t_final = [2e3]", "t_final = [500]");
    let alone = sweep.replace(r#"["tm-sbab2c", "dop853"]"#, r#"["dop853"]"#);
    let mut csv = Vec::new();
    for (name, text) in [("sweep", &sweep), ("alone", &alone)] {
        let spec = write_spec(dir.path(), &format!("{name}.toml"), text);
        let out = dir.path().join(name);
        run_json(&spec, "2", &out);
        let run = run_dirs(&out).pop().unwrap();
        let meta: serde_json::Value =
            serde_json::from_slice(&std::fs::read(run.join("run.json")).unwrap()).unwrap();
        let from = meta["forecast_from"].as_str().map(str::to_owned);
        if name == "sweep" {
            assert_eq!(from.as_deref(), Some("01-tm-sbab2c-tau0.05-t500"));
        } else {
            assert_eq!(from, None);
        }
        csv.push(std::fs::read(run.join("cells.csv")).unwrap());
    }
    assert!(csv[0].len() > 1000);
    assert_eq!(csv[0], csv[1]);
}

#[test]
fn run_writes_the_contract_and_never_lists_incompatible_cells() {
    let dir = tempfile::tempdir().unwrap();
    let spec = write_spec(dir.path(), "s.toml", SMALL);
    let out = dir.path().join("out");
    let v = json_stdout(&salient(&[
        "run",
        &spec,
        "--out",
        out.to_str().unwrap(),
        "--json",
    ]));
    let r = &v["runs"][0];
    for key in [
        "method",
        "tau",
        "delta",
        "t_final",
        "mode",
        "cells",
        "compatible",
        "percent",
        "counts",
        "orbits_integrated",
        "orbits_dropped",
        "steps_total",
        "cpu_s",
        "wall_s",
        "out_dir",
    ] {
        assert!(r.get(key).is_some(), "{key} missing: {r}");
    }
    assert_eq!(r["mode"], "fast-pss");
    assert_eq!(r["cells"], serde_json::json!([40, 40]));
    let p = &r["percent"];
    let total = p["regular"].as_f64().unwrap()
        + p["sticky"].as_f64().unwrap()
        + p["chaotic"].as_f64().unwrap();
    assert!((total - 100.0).abs() < 1e-9);
    let run = run_dirs(&out).remove(0);
    for f in [
        "cells.csv",
        "class.npy",
        "sali.npy",
        "map.png",
        "class_map.png",
        "run.json",
    ] {
        assert!(run.join(f).exists(), "{f}");
    }
    for f in ["table.md", "table.csv", "table.json"] {
        assert!(out.join(f).exists(), "{f}");
    }
    // A tangent-map run has no δ: an empty CSV field, a dash in Markdown.
    let table = std::fs::read_to_string(out.join("table.csv")).unwrap();
    assert!(!table.contains('—'), "{table}");
    assert!(std::fs::read_to_string(out.join("table.md"))
        .unwrap()
        .contains('—'));
    let csv = std::fs::read_to_string(run.join("cells.csv")).unwrap();
    let mut lines = csv.lines();
    assert_eq!(
        lines.next().unwrap(),
        "i,j,q2,p2,sali,class,status,label_source,t_end"
    );
    let mut rows = 0;
    // q2 by i, p2 by j, and each labelling orbit's (sali, class, status, t_end) by its cell.
    let mut q2_of_i = std::collections::HashMap::new();
    let mut p2_of_j = std::collections::HashMap::new();
    let mut orbit_of_row = std::collections::HashMap::new();
    let mut sources = Vec::new();
    for l in lines {
        let f: Vec<&str> = l.split(',').collect();
        let (q2, p2): (f64, f64) = (f[2].parse().unwrap(), f[3].parse().unwrap());
        let radicand = 0.25 - p2 * p2 - q2 * q2 + 2.0 * q2 * q2 * q2 / 3.0;
        assert!(radicand > 0.0, "incompatible cell listed: {l}");
        assert!(["regular", "sticky", "chaotic"].contains(&f[5]), "{l}");
        assert_eq!(*q2_of_i.entry(f[0]).or_insert(f[2]), f[2], "{l}");
        assert_eq!(*p2_of_j.entry(f[1]).or_insert(f[3]), f[3], "{l}");
        let (i, j): (u32, u32) = (f[0].parse().unwrap(), f[1].parse().unwrap());
        let orbit = [f[4], f[5], f[6], f[8]].join(",");
        orbit_of_row.insert(i * 40 + j, orbit.clone());
        sources.push((f[7].parse::<u32>().unwrap(), orbit));
        rows += 1;
    }
    assert_eq!(rows as u64, r["compatible"].as_u64().unwrap());
    // Every cell carries what its labelling orbit's own cell carries.
    for (source, orbit) in &sources {
        assert_eq!(orbit_of_row.get(source), Some(orbit), "source {source}");
    }
    // q2 grows with i and p2 with j.
    let ascending = |m: &std::collections::HashMap<&str, &str>| {
        let mut v: Vec<(u32, f64)> = m
            .iter()
            .map(|(k, x)| (k.parse().unwrap(), x.parse().unwrap()))
            .collect();
        v.sort_by_key(|e| e.0);
        v.windows(2).all(|w| w[0].1 < w[1].1)
    };
    assert!(ascending(&q2_of_i) && ascending(&p2_of_j));
    let npy = std::fs::read(run.join("sali.npy")).unwrap();
    assert!(npy.starts_with(b"\x93NUMPY"));
    assert_eq!(npy.len() % 16, (128 + 40 * 40 * 8) % 16);
}

#[test]
fn full_mode_reports_checkpoints_and_plots_percent_against_t() {
    let dir = tempfile::tempdir().unwrap();
    let spec = write_spec(
        dir.path(),
        "f.toml",
        &SMALL
            .replace("fast-pss", "full")
            .replace("[40, 40]", "[16, 16]")
            .replace("[10, 10]", "[8, 8]"),
    );
    let out = dir.path().join("out");
    let v = json_stdout(&salient(&[
        "run",
        &spec,
        "--out",
        out.to_str().unwrap(),
        "--json",
    ]));
    assert_eq!(v["runs"][0]["orbits_dropped"], 0);
    assert_eq!(
        v["runs"][0]["orbits_integrated"],
        v["runs"][0]["compatible"]
    );
    let run: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(run_dirs(&out).remove(0).join("run.json")).unwrap(),
    )
    .unwrap();
    let cps = run["checkpoints"].as_array().unwrap();
    assert!(cps.len() >= 8);
    // Classes only move towards chaos as t grows: the chaotic share never falls.
    let chaotic: Vec<f64> = cps.iter().map(|c| c["chaotic"].as_f64().unwrap()).collect();
    assert!(
        chaotic.windows(2).all(|w| w[1] >= w[0] - 1e-9),
        "{chaotic:?}"
    );
    let last = cps.last().unwrap();
    assert_eq!(last["t"], 2e3);
    assert!(
        (last["chaotic"].as_f64().unwrap() - v["runs"][0]["percent"]["chaotic"].as_f64().unwrap())
            .abs()
            < 1e-9
    );
    assert!(out.join("percent_vs_t.png").exists());
}

#[test]
fn bad_specs_exit_2_naming_the_field_and_write_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let cases: &[(&str, &str, &str)] = &[
        ("tau = [0.5]", "tau = [-0.5]", "sweep.tau"),
        ("tau = [0.5]", "tau = [nan]", "sweep.tau"),
        ("tau = [0.5]", "tau = []", "sweep.tau"),
        ("t_final = [2e3]", "t_final = [0.1]", "sweep.t_final"),
        (
            "method = [\"tm-sbab2c\"]",
            "method = [\"rk4\"]",
            "sweep.method",
        ),
        (
            "method = [\"tm-sbab2c\"]",
            "method = [\"dop853\"]\ndelta = [-1e-5]",
            "sweep.delta",
        ),
        ("energy = 0.125", "energy = 1.5", "system.energy"),
        (
            "kind = \"henon-heiles\"",
            "kind = \"lorenz\"",
            "system.kind",
        ),
        ("cells = [40, 40]", "cells = [0, 40]", "grid.cells"),
        ("tile = [10, 10]", "tile = [50, 10]", "grid.tile"),
        (
            "mode = \"fast-pss\"",
            "mode = \"fast-pss\"\nq2 = [-0.9, 0.5]",
            "grid.q2",
        ),
        ("mode = \"fast-pss\"", "mode = \"fastest\"", "mode"),
        ("[grid]", "[grid]\ncolour = 3", "colour"),
        // Wrong types, non-finite literals, unknown keys anywhere.
        ("tau = [0.5]", "tau = [\"0.5\"]", "sweep.tau"),
        ("tau = [0.5]", "tau = 0.5", "sweep.tau"),
        ("t_final = [2e3]", "t_final = [inf]", "sweep.t_final"),
        ("t_final = [2e3]", "t_final = [-inf]", "sweep.t_final"),
        ("cells = [40, 40]", "cells = [40.5, 40]", "grid.cells"),
        ("cells = [40, 40]", "cells = [40, 40, 40]", "grid.cells"),
        ("cells = [40, 40]", "cells = [-40, 40]", "grid.cells"),
        ("energy = 0.125", "energy = \"low\"", "system.energy"),
        ("energy = 0.125", "energy = inf", "system.energy"),
        ("[sweep]", "[sweep]\nspeed = 1", "speed"),
        ("name = \"small\"", "name = \"small\"\nowner = 1", "owner"),
        ("name = \"small\"", "name = 7", "name"),
        (
            "[sweep]",
            "[classify]\nregular = nan\n[sweep]",
            "classify.regular",
        ),
        (
            "[sweep]",
            "[classify]\nenergy_drift = -1\n[sweep]",
            "classify.energy_drift",
        ),
        (
            "[sweep]",
            "[integration]\nprotocol = \"fast\"\n[sweep]",
            "integration.protocol",
        ),
        (
            "[sweep]",
            "[integration]\nseed = \"x\"\n[sweep]",
            "integration.seed",
        ),
        // Beyond the default cap of 16 000 000 cells.
        ("cells = [40, 40]", "cells = [4000, 4001]", "grid.cells"),
        ("cells = [40, 40]", "cells = [5000, 10]", "grid.cells"),
        // Not TOML at all.
        ("[grid]", "[grid", "line"),
    ];
    for (i, (from, to, field)) in cases.iter().enumerate() {
        assert!(SMALL.contains(from), "{from}");
        let spec = write_spec(
            dir.path(),
            &format!("bad{i}.toml"),
            &SMALL.replacen(from, to, 1),
        );
        let out = dir.path().join(format!("never{i}"));
        let o = salient(&["run", &spec, "--out", out.to_str().unwrap()]);
        let stderr = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{to}: {stderr}");
        assert_eq!(stderr.trim().lines().count(), 1, "{to}: {stderr}");
        assert!(
            stderr.contains(field),
            "{to}: message does not name {field}: {stderr}"
        );
        assert!(!out.exists(), "{to}: wrote output");
    }
    let spec = write_spec(dir.path(), "ok.toml", SMALL);
    let o = salient(&["run", &spec, "--threads", "0"]);
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("--threads"));
    // The cell cap is configurable: 1600 cells are refused under a cap of 1000.
    let out = dir.path().join("capped");
    let o = salient(&[
        "run",
        &spec,
        "--max-cells",
        "1000",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_eq!(o.status.code(), Some(2));
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(
        stderr.contains("grid.cells") && stderr.contains("1000"),
        "{stderr}"
    );
    assert!(!out.exists());
    // Bad flags are refused by the flag parser with exit 2 too.
    for args in [
        vec!["run", &spec, "--threads", "many"],
        vec!["run", &spec, "--max-cells", "-1"],
        vec!["run", &spec, "--bogus"],
        vec!["run"],
    ] {
        let o = salient(&args);
        assert_eq!(o.status.code(), Some(2), "{args:?}");
    }
    let o = salient(&["run", dir.path().join("missing.toml").to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("missing.toml"));
}

/// `sweep.energy`: one run per energy on the grid of each, each the same files as that energy
/// run alone, a column H in the table and percent_vs_energy.png.
#[test]
fn an_energy_sweep_runs_each_energy_as_it_runs_alone() {
    let dir = tempfile::tempdir().unwrap();
    let swept = SMALL
        .replace("energy = 0.125\n", "")
        .replace("[sweep]", "[sweep]\nenergy = [0.1, 0.125, 0.18]");
    let spec = write_spec(dir.path(), "swept.toml", &swept);
    let out = dir.path().join("swept");
    let v = run_json(&spec, "2", &out);
    let runs = v["runs"].as_array().unwrap();
    assert_eq!(runs.len(), 3);
    // Higher energy, fewer regular cells.
    let regular = |k: usize| runs[k]["percent"]["regular"].as_f64().unwrap();
    assert!(regular(0) > regular(1) && regular(1) > regular(2), "{v}");
    assert_eq!(runs[0]["energy"], 0.1);
    let table = std::fs::read_to_string(out.join("table.md")).unwrap();
    assert!(table.starts_with("| H "), "{table}");
    assert!(out.join("percent_vs_energy.png").is_file());
    assert!(out.join("percent_vs_energy.svg").is_file());
    let dirs = run_dirs(&out);
    assert!(
        dirs[1].ends_with("02-H0.125-tm-sbab2c-tau0.5-t2000"),
        "{dirs:?}"
    );

    let alone = dir.path().join("alone");
    run_json(&write_spec(dir.path(), "alone.toml", SMALL), "1", &alone);
    for file in ["cells.csv", "class.npy", "sali.npy"] {
        assert_eq!(
            std::fs::read(dirs[1].join(file)).unwrap(),
            std::fs::read(run_dirs(&alone)[0].join(file)).unwrap(),
            "{file}"
        );
    }
}

/// `sweep.mode` runs full mode and fast PSS from one spec (the paper's Fig. 7 in one
/// command): each mode's run is the run of that mode alone, byte for byte, the folders and
/// the table name the mode, and percent_vs_t draws both.
#[test]
fn a_mode_sweep_runs_each_mode_as_it_runs_alone() {
    let dir = tempfile::tempdir().unwrap();
    let swept = SMALL
        .replace("mode = \"fast-pss\"\n", "")
        .replace("[sweep]", "[sweep]\nmode = [\"full\", \"fast-pss\"]");
    let out = dir.path().join("swept");
    let v = run_json(&write_spec(dir.path(), "swept.toml", &swept), "2", &out);
    let runs = v["runs"].as_array().unwrap();
    let modes: Vec<&str> = runs.iter().map(|r| r["mode"].as_str().unwrap()).collect();
    assert_eq!(modes, ["full", "fast-pss"]);
    let table = std::fs::read_to_string(out.join("table.md")).unwrap();
    assert!(table.starts_with("| mode "), "{table}");
    assert!(out.join("percent_vs_t.png").is_file());
    let dirs = run_dirs(&out);
    assert!(
        dirs[0].ends_with("01-full-tm-sbab2c-tau0.5-t2000"),
        "{dirs:?}"
    );
    assert!(
        dirs[1].ends_with("02-fast-pss-tm-sbab2c-tau0.5-t2000"),
        "{dirs:?}"
    );
    for (k, mode) in ["full", "fast-pss"].iter().enumerate() {
        let alone = dir.path().join(mode);
        let text = SMALL.replace("mode = \"fast-pss\"", &format!("mode = \"{mode}\""));
        run_json(
            &write_spec(dir.path(), &format!("{mode}.toml"), &text),
            "1",
            &alone,
        );
        for file in ["cells.csv", "class.npy", "sali.npy"] {
            assert_eq!(
                std::fs::read(dirs[k].join(file)).unwrap(),
                std::fs::read(run_dirs(&alone)[0].join(file)).unwrap(),
                "{mode}: {file}"
            );
        }
    }
}
