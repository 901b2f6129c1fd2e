//! results.nc, the self-describing file of a run: read back with a NetCDF reader, its
//! coordinates are the cell centres and its variables the run's per-cell files.

use netcdf3::FileReader;
use salient_report::read_npy_u8;
use salient_tests::{run_dirs, run_embedded, write_spec};

const SPEC: &str = r#"
name = "nc"
[system]
kind = "henon-heiles"
energy = 0.125
[grid]
cells = [30, 24]
tile = [10, 8]
[sweep]
method = ["dop853"]
tau = [0.5]
t_final = [1e3]
delta = [1e-8]
"#;

#[test]
fn results_nc_round_trips_coordinates_classes_and_attributes() {
    let dir = tempfile::tempdir().unwrap();
    let spec = write_spec(dir.path(), "nc.toml", SPEC);
    let out = dir.path().join("out");
    run_embedded(&spec, &out);
    let run = run_dirs(&out).remove(0);
    let mut reader = FileReader::open(run.join("results.nc")).unwrap();
    let vars = reader.read_all_vars().unwrap();
    let ds = reader.data_set();
    assert_eq!(ds.dim_size("q2"), Some(30));
    assert_eq!(ds.dim_size("p2"), Some(24));
    let attr = |name: &str| ds.get_global_attr_as_string(name).unwrap();
    assert_eq!(attr("method"), "dop853");
    assert_eq!(attr("protocol"), "restart");
    assert_eq!(attr("mode"), "fast-pss");
    assert_eq!(attr("salient_version"), env!("CARGO_PKG_VERSION"));
    assert!(attr("spec").contains("\"nc\""), "the spec as JSON");
    assert_eq!(ds.get_global_attr_f64("energy"), Some(&[0.125][..]));
    assert_eq!(ds.get_global_attr_f64("delta"), Some(&[1e-8][..]));
    assert_eq!(ds.get_global_attr_f64("t_final"), Some(&[1e3][..]));
    assert_eq!(
        ds.get_var_attr_as_string("class", "flag_meanings").unwrap(),
        "incompatible regular sticky chaotic escaped no_class"
    );
    let (q2, p2) = (vars["q2"].get_f64().unwrap(), vars["p2"].get_f64().unwrap());
    let class = vars["class"].get_i32().unwrap();
    let sali = vars["sali"].get_f64().unwrap();
    let source = vars["label_source"].get_i32().unwrap();

    // Each cell's row of cells.csv: its centre, SALI and labelling cell.
    let csv = std::fs::read_to_string(run.join("cells.csv")).unwrap();
    let mut rows = 0;
    for line in csv.lines().skip(1) {
        let f: Vec<&str> = line.split(',').collect();
        let (i, j): (usize, usize) = (f[0].parse().unwrap(), f[1].parse().unwrap());
        let k = i * 24 + j;
        assert_eq!(q2[i].to_string(), f[2], "q2 of cell ({i}, {j})");
        assert_eq!(p2[j].to_string(), f[3], "p2 of cell ({i}, {j})");
        assert_eq!(sali[k].to_string(), f[4]);
        assert_eq!(source[k].to_string(), f[7]);
        rows += 1;
    }
    assert!(rows > 300, "{rows} compatible cells");
    // The class variable is class.npy, cell for cell; cells without a row have no orbit.
    let (shape, npy) = read_npy_u8(&run.join("class.npy")).unwrap();
    assert_eq!(shape, vec![30, 24]);
    let as_u8: Vec<u8> = class.iter().map(|&c| c as u8).collect();
    assert_eq!(
        ds.get_var_attr_i32("status", "flag_values"),
        Some(&[0, 1, 2, 3, 4, 5, 6][..])
    );
    assert_eq!(as_u8, npy);
    assert_eq!(source.iter().filter(|&&s| s == -1).count(), 30 * 24 - rows);
}
