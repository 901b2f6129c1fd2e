//! The maps `salient run` draws: every cell of the class map in its class's colour, the SALI
//! map's bands, and SVG beside every PNG.

use salient_report::{CellMap, CellPixels, CELL_MAP_SIZE};
use salient_tests::{run_dirs, run_embedded, write_spec};

const SPEC: &str = r#"
name = "maps"
[system]
kind = "henon-heiles"
energy = 0.125
[grid]
cells = [40, 40]
tile = [10, 10]
[sweep]
method = ["tm-sbab2c"]
tau = [0.5]
t_final = [1e3]
"#;

/// The class map's colours as docs/outputs.md gives them.
fn class_colour(class: &str) -> [u8; 3] {
    match class {
        "regular" => [0, 114, 178],
        "sticky" => [240, 228, 66],
        "chaotic" => [213, 94, 0],
        "forbidden" => [225, 225, 225],
        other => panic!("no colour for {other}"),
    }
}

/// The RGB pixels of a PNG and its width.
fn decode(path: &std::path::Path) -> (Vec<u8>, u32) {
    let decoder = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(path).unwrap()));
    let mut reader = decoder.read_info().unwrap();
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).unwrap();
    assert_eq!(info.color_type, png::ColorType::Rgb);
    assert_eq!((info.width, info.height), CELL_MAP_SIZE);
    buf.truncate(info.buffer_size());
    (buf, info.width)
}

/// Where the cells of the 40 × 40 maps lie in the default-size images.
fn cell_pixels() -> CellPixels {
    let codes = vec![0u8; 40 * 40];
    let layout = CellMap {
        codes: &codes,
        categories: &[salient_report::Category {
            label: "",
            colour: [0; 3],
        }],
        nx: 40,
        ny: 40,
        x_range: (0.0, 1.0),
        y_range: (0.0, 1.0),
        title: "layout",
        x_label: "q₂",
        y_label: "p₂",
        scale: None,
    };
    layout.cell_pixels().unwrap()
}

#[test]
fn each_cell_of_the_class_map_is_drawn_in_its_class_colour() {
    let dir = tempfile::tempdir().unwrap();
    let spec = write_spec(dir.path(), "maps.toml", SPEC);
    let out = dir.path().join("out");
    run_embedded(&spec, &out);
    let run = run_dirs(&out).remove(0);
    for f in ["class_map.png", "class_map.svg", "map.png", "map.svg"] {
        assert!(run.join(f).exists(), "{f}");
    }
    // Every cell's class from cells.csv (forbidden where it has no row).
    let mut class = vec!["forbidden".to_string(); 40 * 40];
    let csv = std::fs::read_to_string(run.join("cells.csv")).unwrap();
    for line in csv.lines().skip(1) {
        let f: Vec<&str> = line.split(',').collect();
        let (i, j): (usize, usize) = (f[0].parse().unwrap(), f[1].parse().unwrap());
        class[i * 40 + j] = f[5].to_string();
    }
    // Known cells: the forbidden corner, the big island right of the centre, the chaotic sea
    // above it.
    let cell = |q2: f64, p2: f64| {
        let run_json: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(run.join("run.json")).unwrap()).unwrap();
        let b = &run_json["bounds"];
        let at = |v: f64, r: &serde_json::Value| {
            let (lo, hi) = (r[0].as_f64().unwrap(), r[1].as_f64().unwrap());
            ((v - lo) / (hi - lo) * 40.0) as usize
        };
        (at(q2, &b["q2"]), at(p2, &b["p2"]))
    };
    let island = cell(0.35, 0.0);
    let sea = cell(0.2, 0.25);
    assert_eq!(class[0], "forbidden");
    assert_eq!(class[island.0 * 40 + island.1], "regular");
    assert_eq!(class[sea.0 * 40 + sea.1], "chaotic");

    let (rgb, width) = decode(&run.join("class_map.png"));
    let pixels = cell_pixels();
    let pixel = |i: usize, j: usize| {
        let (x, y) = pixels.centre(i, j);
        let k = 3 * (y as usize * width as usize + x as usize);
        [rgb[k], rgb[k + 1], rgb[k + 2]]
    };
    for (i, j) in [(0, 0), island, sea] {
        assert_eq!(
            pixel(i, j),
            class_colour(&class[i * 40 + j]),
            "cell ({i}, {j})"
        );
    }
    for i in 0..40 {
        for j in 0..40 {
            assert_eq!(
                pixel(i, j),
                class_colour(&class[i * 40 + j]),
                "cell ({i}, {j})"
            );
        }
    }
    // The SVG names the same classes in its legend, with their percentages.
    let svg = std::fs::read_to_string(run.join("class_map.svg")).unwrap();
    for name in ["regular ", "sticky ", "chaotic ", "forbidden"] {
        assert!(svg.contains(name), "{name}");
    }
    let map_svg = std::fs::read_to_string(run.join("map.svg")).unwrap();
    assert!(map_svg.contains("log₁₀ SALI"));
}

/// `--dpi 300`: the map's PNG three times as large each way, with its resolution recorded, and
/// every cell in its colour where the default map has it; a resolution out of range is refused.
#[test]
fn maps_at_another_resolution_keep_their_layout() {
    let dir = tempfile::tempdir().unwrap();
    let spec = write_spec(dir.path(), "maps.toml", SPEC);
    let (out, fine) = (dir.path().join("out"), dir.path().join("fine"));
    run_embedded(&spec, &out);
    let done = salient_tests::salient(&[
        "run",
        &spec,
        "--dpi",
        "300",
        "--out",
        fine.to_str().unwrap(),
    ]);
    assert!(done.status.success());
    let (rgb, width) = decode(&run_dirs(&out).remove(0).join("class_map.png"));
    let file = std::fs::File::open(run_dirs(&fine).remove(0).join("class_map.png")).unwrap();
    let mut reader = png::Decoder::new(std::io::BufReader::new(file))
        .read_info()
        .unwrap();
    let info = reader.info();
    assert_eq!(
        (info.width, info.height),
        (3 * CELL_MAP_SIZE.0, 3 * CELL_MAP_SIZE.1)
    );
    let dims = info.pixel_dims.expect("the resolution is recorded");
    assert_eq!((dims.xppu, dims.unit), (11_811, png::Unit::Meter));
    let mut big = vec![0; reader.output_buffer_size()];
    reader.next_frame(&mut big).unwrap();
    let pixels = cell_pixels();
    for i in 0..40 {
        for j in 0..40 {
            let (x, y) = pixels.centre(i, j);
            let k = 3 * (y as usize * width as usize + x as usize);
            let (bx, by) = (3 * x as usize + 1, 3 * y as usize + 1);
            let kb = 3 * (by * 3 * width as usize + bx);
            assert_eq!(big[kb..kb + 3], rgb[k..k + 3], "cell ({i}, {j})");
        }
    }
    let refused =
        salient_tests::salient(&["run", &spec, "--dpi", "20", "--out", fine.to_str().unwrap()]);
    assert_eq!(refused.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&refused.stderr).contains("--dpi must be in 50..=600"));
}
