//! `results.nc`: one run's per-cell results as a NetCDF-3 classic file that
//! `xarray.open_dataset` reads with coordinates (the cell centres in q₂ and p₂) and attributes
//! saying what was run.

use std::path::Path;

use salient_core::orbit::Status;
use salient_grid::SystemSpec;
use salient_report::{write_netcdf, AttrValue, Axis, GridFile, GridVar, Values};

use crate::run::{RunResult, CLASS_CODE_NAMES, INDICATORS};
use crate::spec::JobSpec;
use crate::usage::{runtime, CliResult};

/// The `status` codes of results.nc, 0 for a cell without an orbit (off the energy surface).
const STATUS_CODES: [(i32, &str); 7] = [
    (0, "incompatible"),
    (1, "ok"),
    (2, "chaotic-early-stop"),
    (3, "escaped"),
    (4, "non-finite"),
    (5, "step-limit"),
    (6, "energy-drift"),
];

fn status_code(s: Status) -> i32 {
    let name = s.as_str();
    STATUS_CODES
        .iter()
        .find(|(_, n)| *n == name)
        .map(|&(c, _)| c)
        .expect("every status has a code")
}

/// CF's flag_values and flag_meanings of a code list (names with `_` for `-` and spaces).
fn flags<'a>(codes: impl Iterator<Item = (i32, &'a str)>) -> Vec<(&'static str, AttrValue)> {
    let (values, names): (Vec<i32>, Vec<String>) =
        codes.map(|(c, n)| (c, n.replace(['-', ' '], "_"))).unzip();
    vec![
        ("flag_values", AttrValue::I32s(values)),
        ("flag_meanings", AttrValue::Text(names.join(" "))),
    ]
}

/// Writes `results.nc` of run `r` of `job` in `dir`, with `indicators` (the run's
/// [`RunResult::indicator_values`]) when it has them.
pub fn write_results_nc(
    job: &JobSpec,
    r: &RunResult,
    indicators: Option<&[Vec<f64>]>,
    dir: &Path,
) -> CliResult<()> {
    let g = r.grid();
    let q2: Vec<f64> = (0..g.n_q2).map(|i| g.centre(g.index(i, 0)).0).collect();
    let p2: Vec<f64> = (0..g.n_p2).map(|j| g.centre(g.index(0, j)).1).collect();
    let class: Vec<i32> = r.class_codes().iter().map(|&c| i32::from(c)).collect();
    let mut status = vec![0i32; g.cells()];
    let mut sali = vec![f64::NAN; g.cells()];
    let mut source_cell = vec![-1i32; g.cells()];
    let mut t_end = vec![f64::NAN; g.cells()];
    for cell in (0..g.cells() as u32).filter(|&c| g.is_compatible(c)) {
        let l = r
            .ledger()
            .label(cell)
            .expect("every compatible cell is labelled");
        let k = cell as usize;
        status[k] = status_code(l.status);
        sali[k] = l.sali;
        source_cell[k] = l.source as i32;
        t_end[k] = l.t_end;
    }
    let text = |s: &str| AttrValue::Text(s.to_string());
    let mut vars = vec![
        GridVar {
            name: "class",
            long_name: "class of the cell (fast PSS: of the orbit that labelled it)",
            values: Values::I32(&class),
            attrs: flags(
                CLASS_CODE_NAMES
                    .iter()
                    .enumerate()
                    .map(|(c, n)| (c as i32, *n)),
            ),
        },
        GridVar {
            name: "status",
            long_name: "how the labelling orbit ended",
            values: Values::I32(&status),
            attrs: flags(STATUS_CODES.iter().copied()),
        },
        GridVar {
            name: "sali",
            long_name: "SALI of the labelling orbit at its end (NaN: none)",
            values: Values::F64(&sali),
            attrs: vec![("units", text("1"))],
        },
        GridVar {
            name: "label_source",
            long_name: "cell whose orbit labelled this one, as i * n_p2 + j",
            values: Values::I32(&source_cell),
            attrs: vec![("_FillValue", AttrValue::I32s(vec![-1]))],
        },
        GridVar {
            name: "t_end",
            long_name: "time the labelling orbit reached (its escape time if it escaped)",
            values: Values::F64(&t_end),
            attrs: vec![],
        },
    ];
    for ((name, long_name), v) in INDICATORS.iter().zip(indicators.unwrap_or_default()) {
        vars.push(GridVar {
            name,
            long_name,
            values: Values::F64(v),
            attrs: vec![],
        });
    }
    let s = r.spec();
    let th = job.thresholds;
    let mut attrs = vec![
        ("title", text(&crate::maps::figure_title(job, r))),
        ("system", text(job.surface.system().kind())),
        ("energy", AttrValue::F64(s.energy)),
        ("method", text(&s.method.name())),
        ("tau", AttrValue::F64(s.tau)),
        ("t_final", AttrValue::F64(s.t_final)),
        ("mode", text(crate::run::mode_name(s.mode))),
        ("order", text(g.order.name())),
        ("regular_threshold", AttrValue::F64(th.regular)),
        ("chaotic_threshold", AttrValue::F64(th.chaotic)),
        ("salient_version", text(env!("CARGO_PKG_VERSION"))),
        ("spec", text(&job.source.to_string())),
    ];
    if let SystemSpec::Polynomial { dof, potential } = job.surface.system() {
        attrs.push(("dof", AttrValue::I32s(vec![*dof as i32])));
        attrs.push(("potential", text(potential)));
    }
    if th.energy_drift.is_finite() {
        attrs.push(("energy_drift_limit", AttrValue::F64(th.energy_drift)));
    }
    if let Some(d) = s.delta {
        attrs.push(("delta", AttrValue::F64(d)));
        attrs.push(("protocol", text(job.protocol.as_str())));
    }
    let [x_name, y_name] = job.surface.axis_names();
    let [x_label, y_label] = job.surface.axis_labels();
    let (x_long, y_long) = (
        format!("{x_label} at the cell centres"),
        format!("{y_label} at the cell centres"),
    );
    let file = GridFile {
        x: Axis {
            name: x_name,
            long_name: &x_long,
            values: &q2,
        },
        y: Axis {
            name: y_name,
            long_name: &y_long,
            values: &p2,
        },
        vars,
        attrs,
    };
    write_netcdf(&file, &dir.join("results.nc")).map_err(|e| runtime("writing results.nc", e))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_status_has_its_own_code() {
        let codes: Vec<i32> = Status::ALL.iter().map(|&s| status_code(s)).collect();
        assert_eq!(codes, vec![1, 2, 3, 4, 5, 6]);
    }
}
