//! The maps of one run, each as PNG and SVG: `class_map` (every cell's class, or why it has
//! none), `map` (log₁₀ SALI in bands whose hue changes at the classification thresholds) and,
//! with `integration.indicators`, `megno_map`, `fli_map` and `mle_map`.

use std::path::Path;

use salient_core::orbit::{Class, Status};
use salient_grid::Mode;
use salient_report::{render_cell_map_at, Category, CellMap, Scale};

use crate::run::{RunResult, INDICATORS};
use crate::spec::JobSpec;
use crate::usage::{runtime, CliResult};

/// The categories of the class map, in legend order, with their colours (Okabe and Ito's
/// colour-blind-safe palette; forbidden cells light grey).
const MAP_CLASSES: [(&str, [u8; 3]); 7] = [
    ("regular", [0, 114, 178]),
    ("sticky", [240, 228, 66]),
    ("chaotic", [213, 94, 0]),
    ("escaped", [0, 158, 115]),
    ("energy drift", [204, 121, 167]),
    ("failed", [0, 0, 0]),
    ("forbidden (no orbit at this H)", [225, 225, 225]),
];
const FORBIDDEN: u8 = 6;

/// The map category of a labelled cell.
fn category(class: Option<Class>, status: Status) -> u8 {
    match (class, status) {
        (Some(Class::Regular), _) => 0,
        (Some(Class::Sticky), _) => 1,
        (Some(Class::Chaotic), _) => 2,
        (None, Status::Escaped) => 3,
        (None, Status::EnergyDrift) => 4,
        (None, _) => 5,
    }
}

/// The figures' title: system, energy, method with its τ or δ, t_final and mode.
pub fn figure_title(job: &JobSpec, r: &RunResult) -> String {
    let s = r.spec();
    let method = match s.delta {
        Some(d) => format!(
            "{} δ = {d:e} ({}), τ = {}",
            s.method.name(),
            job.protocol.as_str(),
            s.tau
        ),
        None => format!("{}, τ = {}", s.method.name(), s.tau),
    };
    let mode = match r.spec().mode {
        Mode::FastPss => "fast PSS",
        Mode::Full => "every cell integrated",
    };
    format!(
        "Hénon–Heiles, H = {}: {method}, t = {:e}, {mode}",
        short(s.energy),
        s.t_final
    )
}

/// A number in at most six significant digits (1/24 reads 0.0416667, 0.125 stays 0.125).
fn short(v: f64) -> String {
    let s = format!("{v}");
    if s.len() <= 8 {
        return s;
    }
    let t = format!("{v:.5e}");
    let parsed: f64 = t.parse().unwrap_or(v);
    format!("{parsed}")
}

/// Every cell's class-map category (forbidden outside the energy surface) and the cells in
/// each category.
fn categories_of(r: &RunResult) -> (Vec<u8>, [u64; MAP_CLASSES.len()]) {
    let g = r.grid();
    let mut codes = vec![FORBIDDEN; g.cells()];
    let mut counts = [0u64; MAP_CLASSES.len()];
    counts[usize::from(FORBIDDEN)] = g.cells() as u64;
    for cell in (0..g.cells() as u32).filter(|&c| g.is_compatible(c)) {
        let l = r
            .ledger()
            .label(cell)
            .expect("every compatible cell is labelled");
        let code = category(l.class, l.status);
        codes[cell as usize] = code;
        counts[usize::from(code)] += 1;
        counts[usize::from(FORBIDDEN)] -= 1;
    }
    (codes, counts)
}

/// class_map.png/.svg and map.png/.svg of one run, and with `indicators` (the run's
/// [`RunResult::indicator_values`]) megno_map, fli_map and mle_map, in `dir`, the PNG files at
/// `dpi`; `sali` per cell (NaN where a cell has none).
pub fn write_maps(
    job: &JobSpec,
    r: &RunResult,
    sali: &[f64],
    indicators: Option<&[Vec<f64>]>,
    (dir, dpi): (&Path, u32),
) -> CliResult<()> {
    let title = figure_title(job, r);
    let (codes, counts) = categories_of(r);
    let compatible: u64 = counts.iter().sum::<u64>() - counts[usize::from(FORBIDDEN)];
    // The three classes always, the others where some cell has them; percentages of the
    // compatible cells.
    let shown: Vec<usize> = (0..MAP_CLASSES.len())
        .filter(|&k| k < 3 || counts[k] > 0)
        .collect();
    let labels: Vec<String> = shown
        .iter()
        .map(|&k| match k as u8 {
            FORBIDDEN => MAP_CLASSES[k].0.to_string(),
            _ => format!(
                "{} {:.2} %",
                MAP_CLASSES[k].0,
                100.0 * counts[k] as f64 / compatible.max(1) as f64
            ),
        })
        .collect();
    let categories: Vec<Category> = shown
        .iter()
        .zip(&labels)
        .map(|(&k, label)| Category {
            label,
            colour: MAP_CLASSES[k].1,
        })
        .collect();
    let mut index = [0u8; MAP_CLASSES.len()];
    for (n, &k) in shown.iter().enumerate() {
        index[k] = n as u8;
    }
    let shown_codes: Vec<u8> = codes.iter().map(|&c| index[usize::from(c)]).collect();
    let map = cell_map(r, &shown_codes, &categories, &title, None);
    let file = |name| MapFile { dir, name, dpi };
    draw(&map, &file("class_map"))?;
    let classes = (&codes[..], &counts);
    write_sali_map(job, r, sali, classes, &title, file("map"))?;
    if let Some(values) = indicators {
        write_indicator_maps(r, values, classes, &title, (dir, dpi))?;
    }
    Ok(())
}

/// Where a map goes: `name`.png (at `dpi`) and `name`.svg in `dir`.
struct MapFile<'a> {
    dir: &'a Path,
    name: &'a str,
    dpi: u32,
}

/// A map of `r`'s grid.
fn cell_map<'a>(
    r: &'a RunResult,
    codes: &'a [u8],
    categories: &'a [Category<'a>],
    title: &'a str,
    scale: Option<Scale<'a>>,
) -> CellMap<'a> {
    let g = r.grid();
    CellMap {
        codes,
        categories,
        nx: g.n_q2,
        ny: g.n_p2,
        x_range: g.q2,
        y_range: g.p2,
        title,
        x_label: g.surface.axis_labels()[0],
        y_label: g.surface.axis_labels()[1],
        scale,
    }
}

/// `map` as its PNG and SVG files.
fn draw(map: &CellMap, to: &MapFile) -> CliResult<()> {
    for ext in ["png", "svg"] {
        let file = format!("{}.{ext}", to.name);
        render_cell_map_at(map, &to.dir.join(&file), to.dpi)
            .map_err(|e| runtime(&format!("drawing {file}"), e))?;
    }
    Ok(())
}

/// Decades of SALI in the map, from 1e-16 (below: the lowest band) to 1.
const SALI_DECADES: usize = 16;

/// The colour of the band of SALI from 10^lo to 10^(lo + 1): a hue per class the band falls in
/// by the job's thresholds (vermilion chaotic, yellow sticky, blue regular), darker toward
/// small SALI in the chaotic hue and toward large SALI in the regular one.
fn band_colour(lo: f64, job: &JobSpec) -> [u8; 3] {
    let mid = lo + 0.5;
    let (chaotic, regular) = (
        job.thresholds.chaotic.log10(),
        job.thresholds.regular.log10(),
    );
    let mix = |a: [f64; 3], b: [f64; 3], t: f64| {
        let t = t.clamp(0.0, 1.0);
        [0, 1, 2].map(|k| (a[k] + (b[k] - a[k]) * t).round() as u8)
    };
    let low = -(SALI_DECADES as f64);
    if mid < chaotic {
        mix(
            [70.0, 25.0, 0.0],
            [235.0, 130.0, 60.0],
            (mid - low) / (chaotic - low),
        )
    } else if mid < regular {
        mix(
            [200.0, 170.0, 20.0],
            [250.0, 240.0, 130.0],
            (mid - chaotic) / (regular - chaotic),
        )
    } else {
        mix(
            [150.0, 200.0, 240.0],
            [0.0, 90.0, 160.0],
            (mid - regular) / -regular,
        )
    }
}

/// map.png/.svg: every classified cell's log₁₀ SALI in one-decade bands, the other cells in
/// their class-map colours (`class_map` is [`categories_of`]'s).
fn write_sali_map(
    job: &JobSpec,
    r: &RunResult,
    sali: &[f64],
    classes: (&[u8], &[u64; MAP_CLASSES.len()]),
    title: &str,
    to: MapFile,
) -> CliResult<()> {
    let edges: Vec<f64> = (0..=SALI_DECADES)
        .map(|k| k as f64 - SALI_DECADES as f64)
        .collect();
    let colours: Vec<[u8; 3]> = edges[..SALI_DECADES]
        .iter()
        .map(|&lo| band_colour(lo, job))
        .collect();
    let log_sali: Vec<f64> = sali.iter().map(|v| v.log10()).collect();
    let bands = Bands {
        label: "log₁₀ SALI",
        edges: &edges,
        colours: &colours,
    };
    write_banded_map(r, &log_sali, &bands, classes, title, to)
}

/// A quantity in bands: `colours[k]` for the values from `edges[k]` to `edges[k + 1]`, values
/// below or above the edges in the end bands.
struct Bands<'a> {
    label: &'a str,
    edges: &'a [f64],
    colours: &'a [[u8; 3]],
}

/// The map of every classified cell's value of `values` in `bands`, the other cells in
/// their class-map colours (`classes` is [`categories_of`]'s).
fn write_banded_map(
    r: &RunResult,
    values: &[f64],
    bands: &Bands,
    (class_codes, counts): (&[u8], &[u64; MAP_CLASSES.len()]),
    title: &str,
    to: MapFile,
) -> CliResult<()> {
    let n = bands.colours.len();
    let mut categories: Vec<Category> = bands
        .colours
        .iter()
        .map(|&colour| Category { label: "", colour })
        .collect();
    // The cells without a class keep their class-map category, after the bands.
    let others: Vec<usize> = (3..MAP_CLASSES.len()).filter(|&k| counts[k] > 0).collect();
    for &k in &others {
        categories.push(Category {
            label: MAP_CLASSES[k].0,
            colour: MAP_CLASSES[k].1,
        });
    }
    let codes: Vec<u8> = class_codes
        .iter()
        .zip(values)
        .map(|(&c, &v)| match usize::from(c) {
            // A classified cell always has a value (NaN would fall in the lowest band).
            0..=2 => (bands.edges.partition_point(|&e| e <= v).max(1) - 1).min(n - 1) as u8,
            k => (n + others.iter().position(|&o| o == k).unwrap_or(0)) as u8,
        })
        .collect();
    let scale = Scale {
        label: bands.label,
        edges: bands.edges,
    };
    let map = cell_map(r, &codes, &categories, title, Some(scale));
    draw(&map, &to)
}

/// Colours of `n` bands along a perceptually ordered sequential scale from dark violet to
/// yellow (anchors of the viridis colour map, van der Walt & Smith), for quantities without
/// class thresholds.
fn sequential_colours(n: usize) -> Vec<[u8; 3]> {
    const ANCHORS: [[f64; 3]; 5] = [
        [68.0, 1.0, 84.0],
        [59.0, 82.0, 139.0],
        [33.0, 145.0, 140.0],
        [94.0, 201.0, 98.0],
        [253.0, 231.0, 37.0],
    ];
    (0..n)
        .map(|k| {
            let x = (k as f64 + 0.5) / n as f64 * (ANCHORS.len() - 1) as f64;
            let i = (x.floor() as usize).min(ANCHORS.len() - 2);
            let t = x - i as f64;
            [0, 1, 2]
                .map(|c| (ANCHORS[i][c] + (ANCHORS[i + 1][c] - ANCHORS[i][c]) * t).round() as u8)
        })
        .collect()
}

/// Band edges of MEGNO's ⟨Y⟩: fine around 2 (quasi-periodic orbits), below it toward 0
/// (stable periodic ones) and in growing steps above it (chaotic ones, ⟨Y⟩ ≈ λt/2).
const MEGNO_EDGES: [f64; 20] = [
    0.0, 0.5, 1.0, 1.5, 1.8, 1.9, 2.0, 2.1, 2.2, 2.5, 3.0, 4.0, 6.0, 10.0, 20.0, 50.0, 100.0,
    200.0, 500.0, 1000.0,
];

/// Band edges of the FLI: steps of about a unit where regular orbits lie (≈ ln t), growing
/// above (chaotic ones, ≈ λt).
const FLI_EDGES: [f64; 19] = [
    0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 10.0, 12.0, 15.0, 20.0, 30.0, 50.0, 100.0, 200.0,
    500.0, 1000.0,
];

/// megno_map, fli_map and mle_map of a run with indicators; `values` per indicator of
/// [`INDICATORS`], `classes` as [`categories_of`] gives them.
fn write_indicator_maps(
    r: &RunResult,
    values: &[Vec<f64>],
    classes: (&[u8], &[u64; MAP_CLASSES.len()]),
    title: &str,
    (dir, dpi): (&Path, u32),
) -> CliResult<()> {
    let column = |name: &str| {
        let k = INDICATORS
            .iter()
            .position(|(n, _)| *n == name)
            .expect("a listed indicator");
        &values[k]
    };
    // The mLE in quarter decades from 1e-5 (regular orbits' ln t / t lies below 1e-3 at
    // t = 1e4, the chaotic sea's λ near 0.05).
    let mle_edges: Vec<f64> = (0..=18).map(|k| -5.0 + 0.25 * f64::from(k)).collect();
    let log_mle: Vec<f64> = column("mle").iter().map(|v| v.log10()).collect();
    let maps: [(&str, &str, &[f64], &[f64]); 3] = [
        (
            "megno_map",
            "MEGNO <Y> (running mean)",
            &MEGNO_EDGES,
            column("megno_mean"),
        ),
        ("fli_map", "FLI = max ln‖w₁‖", &FLI_EDGES, column("fli")),
        ("mle_map", "log₁₀ mLE (finite-time)", &mle_edges, &log_mle),
    ];
    for (name, label, edges, v) in maps {
        let colours = sequential_colours(edges.len() - 1);
        let bands = Bands {
            label,
            edges,
            colours: &colours,
        };
        let to = MapFile { dir, name, dpi };
        write_banded_map(r, v, &bands, classes, title, to)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn short_numbers_keep_six_digits_at_most() {
        assert_eq!(short(0.125), "0.125");
        assert_eq!(short(1.0 / 24.0), "0.0416667");
        assert_eq!(short(1.0 / 6.0), "0.166667");
        assert_eq!(short(0.2), "0.2");
    }

    #[test]
    fn every_status_without_a_class_has_its_own_category() {
        assert_eq!(category(Some(Class::Sticky), Status::Ok), 1);
        assert_eq!(category(None, Status::Escaped), 3);
        assert_eq!(category(None, Status::EnergyDrift), 4);
        assert_eq!(category(None, Status::NonFinite), 5);
        assert_eq!(category(None, Status::StepLimit), 5);
        assert_eq!(
            MAP_CLASSES[FORBIDDEN as usize].0.split(' ').next(),
            Some("forbidden")
        );
    }
}
