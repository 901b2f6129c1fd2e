//! `salient precision`: speed against error for every method on one orbit (`--grid`: for
//! whole grids, in grid_precision.rs).

use crate::ladder::{default_ladder, reference, run_ladder, Row, ADAPTIVE_TAU, REFERENCE_DELTA};
use crate::output::{print_result, write_tables, Staged};
use crate::system::{PointArgs, System, SystemArgs};
use crate::usage::{finite, runtime, CliError, CliResult};
use clap::Args;
use salient_report::{render_loglog, HLine, Line, LogLogPlot, Table};
use serde_json::{json, Value};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// Energy of an orbit started on the section when --energy is not given.
const DEFAULT_ENERGY: f64 = 0.125;

#[derive(Args, Debug)]
#[command(allow_negative_numbers = true)]
pub struct PrecisionArgs {
    /// R1, C1, C2 (the seed paper's Hénon–Heiles orbits) or Q2,P2 on the section q1 = 0 of a
    /// system of 2 degrees of freedom [default: R1 for Hénon–Heiles].
    #[arg(long, conflicts_with = "q")]
    orbit: Option<String>,
    #[command(flatten)]
    point: PointArgs,
    /// Final time of every run.
    #[arg(long = "t-final", default_value_t = 1e3)]
    t_final: f64,
    /// Energy of an orbit started on the section with --orbit [default: 0.125].
    #[arg(long, conflicts_with = "q")]
    energy: Option<f64>,
    #[command(flatten)]
    system: SystemArgs,
    /// Compare whole grids instead of one orbit: run this job spec's sweep and compare every
    /// run's class per cell with a reference run of the same grid.
    #[arg(
        long,
        value_name = "SPEC",
        conflicts_with_all = ["orbit", "t_final", "energy", "q", "polynomial_system"]
    )]
    grid: Option<PathBuf>,
    /// With --grid: a run folder of the same grid (holding class.npy) to compare every run
    /// with, instead of the default reference (full mode, f64 Taylor at δ = 1e-13, one per
    /// t_final, computed once and cached).
    #[arg(long, value_name = "DIR", requires = "grid")]
    reference: Option<PathBuf>,
    /// With --grid: where computed references are kept (default: $SALIENT_CACHE, else
    /// $XDG_CACHE_HOME/salient, else ~/.cache/salient).
    #[arg(long, value_name = "DIR", requires = "grid")]
    cache: Option<PathBuf>,
    /// With --grid and a fast-PSS spec: also run each member in full mode (cached like the
    /// references) and report how many cells fast PSS itself changes.
    #[arg(long, requires = "grid")]
    fast_vs_full: bool,
    /// With --grid: worker threads (default: every core).
    #[arg(long, requires = "grid")]
    threads: Option<usize>,
    /// Write the tables and plot here: precision.* and work_precision.png for an orbit;
    /// grid_precision.*, misclassified_vs_cpu.png and the runs' folders with --grid.
    #[arg(long)]
    out: Option<PathBuf>,
    /// Print exactly one JSON object on stdout.
    #[arg(long)]
    json: bool,
}

/// (q2, p2) of a named orbit (Hénon–Heiles only) or of "Q2,P2".
fn parse_orbit(s: &str, system: &System) -> CliResult<(String, f64, f64)> {
    let named = match s.to_ascii_uppercase().as_str() {
        "R1" => Some((0.558, 0.0)),
        "C1" => Some((-0.25, 0.0)),
        "C2" => Some((0.335036, -0.385631)),
        _ => None,
    };
    if let Some((q2, p2)) = named {
        if !matches!(system, System::HenonHeiles) {
            return Err(CliError::Usage(format!(
                "--orbit {s}: R1, C1 and C2 are Hénon–Heiles orbits; with --potential or --system \
                 give Q2,P2 on the section or the whole point with --q and --p"
            )));
        }
        return Ok((s.to_ascii_uppercase(), q2, p2));
    }
    let bad = || {
        CliError::Usage(format!(
            "--orbit must be R1, C1, C2 or Q2,P2 with two finite numbers (got '{s}')"
        ))
    };
    let (a, b) = s.split_once(',').ok_or_else(bad)?;
    let q2: f64 = a.trim().parse().map_err(|_| bad())?;
    let p2: f64 = b.trim().parse().map_err(|_| bad())?;
    if !(q2.is_finite() && p2.is_finite()) {
        return Err(bad());
    }
    Ok((format!("{q2},{p2}"), q2, p2))
}

/// The initial point of the ladder: its name, (q, p) and energy, from --q/--p or from --orbit
/// and --energy on the section q1 = 0.
fn start_of(args: &PrecisionArgs, system: &System) -> CliResult<(String, Vec<f64>, Vec<f64>, f64)> {
    if let Some((q, p, energy)) = args.point.of(system)? {
        return Ok(("point".into(), q, p, energy));
    }
    let orbit = match (&args.orbit, system) {
        (Some(o), _) => o.clone(),
        (None, System::HenonHeiles) => "R1".into(),
        (None, _) => {
            return Err(CliError::Usage(
                "--potential/--system: give the orbit, as --orbit Q2,P2 on the section q1 = 0 \
                 (2 degrees of freedom) or as the whole point with --q and --p"
                    .into(),
            ))
        }
    };
    if system.dof() != 2 {
        return Err(CliError::Usage(format!(
            "--orbit starts on the section of a 2-degree-of-freedom system; with --dof {} give \
             the whole point with --q and --p",
            system.dof()
        )));
    }
    let (name, q2, p2) = parse_orbit(&orbit, system)?;
    let energy = finite("--energy", args.energy.unwrap_or(DEFAULT_ENERGY))?;
    let (q, p) = system.on_section(energy, q2, p2).ok_or_else(|| {
        let e_min = system.potential_at(&[0.0, q2]) + 0.5 * p2 * p2;
        CliError::Usage(format!(
            "--energy {energy}: orbit {name} is not on the section q1 = 0, p1 > 0; allowed: \
             --energy > {e_min}"
        ))
    })?;
    Ok((name, q, p, energy))
}

fn fmt_num(x: f64) -> String {
    if x.is_nan() {
        "—".into()
    } else {
        format!("{x:.3e}")
    }
}

fn label(row: &Row) -> String {
    match row.setting.run.delta {
        Some(d) => format!("δ={d:e}"),
        None => format!("τ={}", row.setting.tau),
    }
}

fn row_json(r: &Row) -> Value {
    let run = &r.setting.run;
    json!({
        "method": run.method.name(),
        "tau": r.setting.tau,
        "delta": run.delta,
        "protocol": run.method.is_adaptive().then(|| run.protocol.as_str()),
        "order": r.order,
        "status": r.status.as_str(),
        "steps": r.steps,
        "wall_s": r.wall_s,
        "ns_per_step": r.ns_per_step,
        "energy_error_max": r.energy_error_max,
        "state_error": r.state_error,
        "sali": r.sali,
        "class": r.class.map(|c| c.as_str()),
    })
}

pub fn run(args: PrecisionArgs) -> CliResult<()> {
    if let Some(spec) = args.grid {
        return crate::grid_precision::run(crate::grid_precision::GridRequest {
            spec,
            reference: args.reference,
            cache: args.cache,
            fast_vs_full: args.fast_vs_full,
            threads: args.threads,
            out: args.out,
            json: args.json,
        });
    }
    if !(args.t_final.is_finite() && args.t_final >= 0.5 && args.t_final <= 1e7) {
        return Err(CliError::Usage(format!(
            "--t-final must be a finite number in [0.5, 1e7] (got {})",
            args.t_final
        )));
    }
    let system = args.system.system()?;
    let (name, q, p, energy) = start_of(&args, &system)?;
    let staged = args
        .out
        .as_deref()
        .map(|dir| Staged::begin(dir, "--out"))
        .transpose()?;
    let ladder = default_ladder();
    let n = ladder.len();
    eprintln!(
        "salient precision: orbit {name}, t = {}, reference taylor-dd δ = {REFERENCE_DELTA:e}",
        args.t_final
    );
    let reference = reference(&system, energy, (&q, &p), args.t_final);
    let rows = run_ladder(
        &system,
        (energy, (&q, &p)),
        args.t_final,
        &ladder,
        &reference,
        &mut |i, r| {
            let run = &r.setting.run;
            eprintln!(
                "[{:>2}/{n}] {:<12} {:<12} {:<7} {:>9.3} s  error {}",
                i + 1,
                run.method.name(),
                label(r),
                if run.method.is_adaptive() {
                    run.protocol.as_str()
                } else {
                    ""
                },
                r.wall_s,
                fmt_num(r.state_error)
            );
        },
    );

    let mut table = Table::new(&[
        "method",
        "tau",
        "delta",
        "protocol",
        "order",
        "steps",
        "wall_s",
        "ns/step",
        "max |dH/H|",
        "state error",
        "SALI",
        "class",
    ]);
    for r in &rows {
        let run = &r.setting.run;
        table.push(vec![
            run.method.name(),
            format!("{}", r.setting.tau),
            run.delta.map_or("—".into(), |d| format!("{d:e}")),
            if run.method.is_adaptive() {
                run.protocol.as_str().into()
            } else {
                "—".into()
            },
            r.order.to_string(),
            r.steps.to_string(),
            format!("{:.4}", r.wall_s),
            format!("{:.0}", r.ns_per_step),
            fmt_num(r.energy_error_max),
            fmt_num(r.state_error),
            format!("{:.6}", r.sali),
            r.class
                .map_or(r.status.as_str().to_string(), |c| c.as_str().to_string()),
        ]);
    }
    let summary = json!({
        "system": system.name(),
        "potential": system.text(),
        "dof": system.dof(),
        "orbit": { "name": name, "q": q, "p": p, "energy": energy },
        "t_final": args.t_final,
        "adaptive_tau": ADAPTIVE_TAU,
        "reference": {
            "method": "taylor-dd", "delta": REFERENCE_DELTA, "protocol": "free",
            "steps": reference.steps, "sali": reference.sali,
            "q_end": reference.q_end, "p_end": reference.p_end,
        },
        "rows": rows.iter().map(row_json).collect::<Vec<_>>(),
    });
    if let Some(staged) = staged {
        write_outputs(staged.path(), &name, args.t_final, &table, &summary, &rows)?;
        staged.publish()?;
    }
    print_result(
        args.json,
        &summary,
        &table,
        args.out.as_deref(),
        "precision.md, precision.csv, precision.json, work_precision.png",
    );
    Ok(())
}

fn write_outputs(
    dir: &Path,
    name: &str,
    t_final: f64,
    table: &Table,
    summary: &Value,
    rows: &[Row],
) -> CliResult<()> {
    write_tables(dir, "precision", table, summary)?;

    // One line per method and protocol: end-point error against wall time. An error of 0 (the
    // end point equals the reference's in every digit) is drawn on a floor a decade below the
    // smallest nonzero one, 1e-17 at most, that a dashed line labels.
    let smallest = rows
        .iter()
        .map(|r| r.state_error)
        .filter(|&e| e > 0.0)
        .fold(f64::INFINITY, f64::min);
    let floor = 10f64.powf((smallest.min(1e-16).log10() - 1.0).floor());
    let any_zero = rows.iter().any(|r| r.state_error == 0.0);
    let mut groups: BTreeMap<String, (Vec<f64>, Vec<f64>)> = BTreeMap::new();
    let mut labels = Vec::new();
    for r in rows {
        let error = if r.state_error == 0.0 {
            floor
        } else {
            r.state_error
        };
        let run = &r.setting.run;
        let key = if run.method.is_adaptive() {
            format!("{} ({})", run.method.name(), run.protocol.as_str())
        } else {
            run.method.name()
        };
        let g = groups.entry(key).or_default();
        g.0.push(r.wall_s);
        g.1.push(error);
        labels.push((r.wall_s, error, label(r)));
    }
    let lines: Vec<Line> = groups
        .iter()
        .map(|(k, (xs, ys))| Line { label: k, xs, ys })
        .collect();
    let title = format!("work-precision, orbit {name}, t = {t_final}");
    let floor_label = format!("error 0 (drawn at {floor:e})");
    let plot = LogLogPlot {
        title: &title,
        x_label: "wall time (s)",
        y_label: "end-point error vs taylor-dd",
        lines,
        hlines: if any_zero {
            vec![HLine {
                label: &floor_label,
                y: floor,
            }]
        } else {
            Vec::new()
        },
        point_labels: labels,
        markers: true,
    };
    render_loglog(&plot, &dir.join("work_precision.png"), 1400, 1000)
        .map_err(|e| runtime("plotting work_precision.png", e))?;
    Ok(())
}
