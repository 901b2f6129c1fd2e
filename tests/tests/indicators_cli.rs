//! The per-cell indicators of `integration.indicators`: cells.csv columns, .npy files,
//! results.nc variables and maps, each cell's values those of `salient orbit` on its centre,
//! and the spec's rules.

use netcdf3::FileReader;
use salient_report::npy_bytes_f64;
use salient_tests::{json_stdout, run_dirs, run_embedded, salient, write_spec};

const SPEC: &str = r#"
name = "indicators"
[system]
kind = "henon-heiles"
energy = 0.125
[grid]
cells = [14, 12]
tile = [5, 5]
mode = "full"
[sweep]
method = ["tm-sbab2c", "dop853"]
tau = [0.1]
t_final = [500]
delta = [1e-9]
[integration]
indicators = true
"#;

#[test]
fn every_cell_carries_the_indicators_of_its_own_orbit() {
    let dir = tempfile::tempdir().unwrap();
    let spec = write_spec(dir.path(), "indicators.toml", SPEC);
    let out = dir.path().join("out");
    let summary = run_embedded(&spec, &out);
    let runs = run_dirs(&out);
    assert_eq!(runs.len(), 2);
    for (run, (method, delta)) in runs
        .iter()
        .zip([("tm-sbab2c", None), ("dop853", Some("1e-9"))])
    {
        for f in [
            "mle.npy",
            "megno.npy",
            "megno_mean.npy",
            "fli.npy",
            "megno_map.png",
            "megno_map.svg",
            "fli_map.png",
            "mle_map.svg",
        ] {
            assert!(run.join(f).exists(), "{f} in {}", run.display());
        }
        let csv = std::fs::read_to_string(run.join("cells.csv")).unwrap();
        let mut lines = csv.lines();
        assert_eq!(
            lines.next().unwrap(),
            "i,j,q2,p2,sali,class,status,label_source,t_end,mle,megno,megno_mean,fli"
        );
        let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
        // The indicators are read at t_final: no orbit stops early.
        assert!(rows.iter().all(|r| r[6] != "chaotic-early-stop"));
        // results.nc holds each indicator as a variable, and the .npy file the same array.
        let mut reader = FileReader::open(run.join("results.nc")).unwrap();
        let vars = reader.read_all_vars().unwrap();
        for name in ["mle", "megno", "megno_mean", "fli"] {
            let v = vars[name].get_f64().unwrap();
            let npy = std::fs::read(run.join(format!("{name}.npy"))).unwrap();
            assert_eq!(npy, npy_bytes_f64(&[14, 12], v), "{name}");
        }
        let megno_mean = vars["megno_mean"].get_f64().unwrap();
        let chaotic = rows
            .iter()
            .find(|r| r[5] == "chaotic")
            .expect("a chaotic cell");
        let regular = rows
            .iter()
            .find(|r| r[5] == "regular")
            .expect("a regular cell");
        for row in [chaotic, regular] {
            let (i, j): (usize, usize) = (row[0].parse().unwrap(), row[1].parse().unwrap());
            assert_eq!(megno_mean[i * 12 + j].to_string(), row[11]);
            // The orbit from the cell's centre, alone: the same values to the last bit.
            let mut args = vec![
                "orbit",
                "--q2",
                row[2],
                "--p2",
                row[3],
                "--method",
                method,
                "--tau",
                "0.1",
                "--t-final",
                "500",
                "--no-early-stop",
                "--json",
            ];
            if let Some(d) = delta {
                args.extend(["--delta", d]);
            }
            let orbit = json_stdout(&salient(&args));
            for (k, name) in [(9, "mle"), (10, "megno"), (11, "megno_mean"), (12, "fli")] {
                assert_eq!(
                    orbit[name].as_f64().unwrap().to_string(),
                    row[k],
                    "{name} {row:?}"
                );
            }
        }
        // Chaotic cells' ⟨Y⟩ is far above the regular cells' 2.
        let y = |r: &Vec<&str>| r[11].parse::<f64>().unwrap();
        assert!(
            y(chaotic) > 4.0 && (y(regular) - 2.0).abs() < 1.0,
            "{chaotic:?} {regular:?}"
        );
    }
    // run.json counts each class's cells by ⟨Y⟩ range: all of them.
    for r in summary["runs"].as_array().unwrap() {
        let table = &r["megno_vs_sali"];
        for class in ["regular", "sticky", "chaotic"] {
            let n: u64 = table[class]
                .as_array()
                .unwrap()
                .iter()
                .map(|v| v.as_u64().unwrap())
                .sum();
            assert_eq!(n, r["counts"][class].as_u64().unwrap(), "{class}");
        }
    }
}

#[test]
fn indicators_need_full_mode_and_no_early_stop() {
    let dir = tempfile::tempdir().unwrap();
    for (text, says) in [
        (
            SPEC.replace("mode = \"full\"", "mode = \"fast-pss\""),
            "integration.indicators = true needs a full-mode run",
        ),
        (
            SPEC.to_string() + "[classify]\nearly_stop = true\n",
            "classify.early_stop must be false with integration.indicators",
        ),
    ] {
        let spec = write_spec(dir.path(), "bad.toml", &text);
        let out = salient(&[
            "run",
            &spec,
            "--out",
            dir.path().join("o").to_str().unwrap(),
        ]);
        assert_eq!(out.status.code(), Some(2));
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(says), "{err}");
    }
}
