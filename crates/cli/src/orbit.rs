//! `salient orbit`: one orbit, its indicators, and (with `--out`) a time series and plots.

use crate::human::{csv_number, human};
use crate::output::Staged;
use crate::system::{OrbitReport, PointArgs, System, SystemArgs};
use crate::usage::{finite, positive, runtime, CliError, CliResult};
use clap::{Args, ValueEnum};
use salient_core::adaptive::driver::Protocol as AdaptiveProtocol;
use salient_core::orbit::{OrbitConfig, OrbitResult, Requests, Thresholds};
use salient_core::run::{MethodRun, Vectors};
use salient_core::{Deviation, Method};
use salient_report::{
    render_lines, render_loglog, render_panels, HLine, Line, LinePlot, LogLogPlot, Panels,
    ReportError,
};
use serde_json::{json, Map, Value};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Refuse runs beyond this many steps: a typo in --t-final should not start a year-long job.
const MAX_STEPS: f64 = 1e12;

/// Tolerance of the adaptive methods when --delta is not given.
const DEFAULT_DELTA: f64 = 1e-10;

/// Energy of an orbit started on the section when --energy is not given.
const DEFAULT_ENERGY: f64 = 0.125;

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum Protocol {
    Restart,
    Free,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum DeviationKind {
    Axes,
    Random,
}

#[derive(Args, Debug)]
#[command(allow_negative_numbers = true)]
pub struct OrbitArgs {
    /// q2 of the initial condition on the section q1 = 0 (p1 > 0 follows from the energy);
    /// systems of 2 degrees of freedom.
    #[arg(long, required_unless_present = "q", requires = "p2", conflicts_with_all = ["q", "p"])]
    q2: Option<f64>,
    /// p2 of the initial condition on the section.
    #[arg(long, requires = "q2")]
    p2: Option<f64>,
    #[command(flatten)]
    point: PointArgs,
    /// Energy H of the orbit started on the section [default: 0.125].
    #[arg(long, conflicts_with = "q")]
    energy: Option<f64>,
    #[command(flatten)]
    system: SystemArgs,
    /// Integration method, e.g. tm-sbab2c, tm-srkn14a.
    #[arg(long)]
    method: String,
    /// Renormalisation interval τ: deviation vectors are renormalised and SALI checked every τ;
    /// for tm-* methods it is also the integration step.
    #[arg(long, default_value_t = 0.05)]
    tau: f64,
    /// Tolerance δ of the adaptive methods, rtol = atol = δ (default 1e-10; ignored by tm-*).
    #[arg(long)]
    delta: Option<f64>,
    /// Protocol of the adaptive methods (ignored by tm-* methods).
    #[arg(long, value_enum)]
    protocol: Option<Protocol>,
    /// Final time.
    #[arg(long = "t-final")]
    t_final: f64,
    /// Write series.csv, crossings.csv, orbit.json and the plots here.
    #[arg(long)]
    out: Option<PathBuf>,
    /// Print exactly one JSON object on stdout.
    #[arg(long)]
    json: bool,
    /// Follow 2N deviation vectors for GALI_2..GALI_2N (default: 2 vectors, SALI and GALI_2).
    #[arg(long)]
    gali_all: bool,
    /// SALI at or above which an orbit is regular.
    #[arg(long, default_value_t = 1e-4)]
    regular: f64,
    /// SALI below which an orbit is chaotic.
    #[arg(long, default_value_t = 1e-8)]
    chaotic: f64,
    /// Integrate to t_final even after SALI falls below the chaotic threshold.
    #[arg(long)]
    no_early_stop: bool,
    /// Stop with status energy-drift once |ΔH/H| exceeds this.
    #[arg(long, default_value_t = salient_core::orbit::ENERGY_DRIFT_DEFAULT)]
    energy_drift: f64,
    /// Initial deviation vectors: the phase-space axes, or seeded random unit vectors.
    #[arg(long, value_enum, default_value = "axes")]
    deviation: DeviationKind,
    /// Seed of the random deviation vectors.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Samples per decade of t in series.csv.
    #[arg(long, default_value_t = 20)]
    samples_per_decade: u32,
}

/// A validated orbit request.
struct OrbitJob {
    system: System,
    method: Method,
    energy: f64,
    /// The tolerance in force (adaptive methods only).
    delta: Option<f64>,
    protocol: AdaptiveProtocol,
    q: Vec<f64>,
    p: Vec<f64>,
    config: OrbitConfig,
    requests: Requests,
    gali_all: bool,
    warnings: Vec<String>,
}

impl OrbitJob {
    fn run(&self) -> MethodRun {
        MethodRun {
            method: self.method.clone(),
            delta: self.delta,
            protocol: self.protocol,
        }
    }
}

fn validate(a: &OrbitArgs) -> CliResult<OrbitJob> {
    let method = Method::parse(&a.method).map_err(|e| CliError::Usage(format!("--method: {e}")))?;
    let system = a.system.system()?;
    let (q, p, energy) = start_of(a, &system)?;
    let tau = positive("--tau", a.tau)?;
    if !(a.t_final.is_finite() && a.t_final >= tau) {
        return Err(CliError::Usage(format!(
            "--t-final must be a finite number ≥ --tau = {tau} (got {})",
            a.t_final
        )));
    }
    if a.t_final / tau > MAX_STEPS {
        return Err(CliError::Usage(format!(
            "--t-final / --tau = {:.3e} steps; at most {MAX_STEPS:e} steps are allowed",
            a.t_final / tau
        )));
    }
    let mut warnings = Vec::new();
    if let Some(d) = a.delta {
        positive("--delta", d)?;
    }
    let mut delta = None;
    if method.is_adaptive() {
        let (d, warning) = method.honoured_delta(a.delta.unwrap_or(DEFAULT_DELTA));
        delta = Some(d);
        warnings.extend(warning);
    } else {
        if a.delta.is_some() {
            warnings.push(format!(
                "--delta is ignored by {}: its accuracy is set by --tau",
                method.name()
            ));
        }
        if a.protocol.is_some() {
            warnings.push(format!(
                "--protocol is ignored by {}: it steps exactly to every τ",
                method.name()
            ));
        }
    }
    let protocol = match a.protocol.unwrap_or(Protocol::Restart) {
        Protocol::Restart => AdaptiveProtocol::Restart,
        Protocol::Free => AdaptiveProtocol::Free,
    };
    let regular = positive("--regular", a.regular)?;
    let chaotic = positive("--chaotic", a.chaotic)?;
    let energy_drift = positive("--energy-drift", a.energy_drift)?;
    if !(chaotic <= regular && regular <= 2f64.sqrt()) {
        return Err(CliError::Usage(format!(
            "--chaotic and --regular must satisfy 0 < chaotic ≤ regular ≤ √2 (got {chaotic}, {regular})"
        )));
    }
    if a.samples_per_decade > 1000 {
        return Err(CliError::Usage(format!(
            "--samples-per-decade must be in 0..=1000 (got {})",
            a.samples_per_decade
        )));
    }
    let deviation = match a.deviation {
        DeviationKind::Axes => Deviation::Axes,
        DeviationKind::Random => Deviation::Random { seed: a.seed },
    };
    let config = OrbitConfig {
        tau,
        t_final: a.t_final,
        thresholds: Thresholds {
            regular,
            chaotic,
            early_stop: !a.no_early_stop,
            energy_drift,
        },
        deviation,
        escape_radius: None,
    };
    let requests = Requests {
        crossings: true,
        gali: true,
        energy: true,
        growth: true,
        samples_per_decade: if a.out.is_some() {
            a.samples_per_decade
        } else {
            0
        },
    };
    Ok(OrbitJob {
        system,
        method,
        energy,
        delta,
        protocol,
        q,
        p,
        config,
        requests,
        gali_all: a.gali_all,
        warnings,
    })
}

/// The initial point (q, p) and its energy: from --q and --p, or on the section q1 = 0 from
/// --q2, --p2 and --energy.
fn start_of(a: &OrbitArgs, system: &System) -> CliResult<(Vec<f64>, Vec<f64>, f64)> {
    if let Some(point) = a.point.of(system)? {
        return Ok(point);
    }
    let dof = system.dof();
    if dof != 2 {
        return Err(CliError::Usage(format!(
            "--q2/--p2 start on the section of a 2-degree-of-freedom system; with --dof {dof} \
             give the whole point with --q and --p"
        )));
    }
    let q2 = finite("--q2", a.q2.expect("clap requires --q2 without --q"))?;
    let p2 = finite("--p2", a.p2.expect("clap requires --p2 with --q2"))?;
    let energy = finite("--energy", a.energy.unwrap_or(DEFAULT_ENERGY))?;
    let (q, p) = system.on_section(energy, q2, p2).ok_or_else(|| {
        let e_min = system.potential_at(&[0.0, q2]) + 0.5 * p2 * p2;
        CliError::Usage(format!(
            "--energy {energy}: (q2, p2) = ({q2}, {p2}) is not on the section q1 = 0, p1 > 0; \
             allowed: --energy > {e_min} for this point"
        ))
    })?;
    Ok((q, p, energy))
}

pub fn run(args: OrbitArgs) -> CliResult<()> {
    let job = validate(&args)?;
    let staged = args
        .out
        .as_deref()
        .map(|dir| Staged::begin(dir, "--out"))
        .transpose()?;
    let start = Instant::now();
    let vectors = if job.gali_all {
        Vectors::All
    } else {
        Vectors::Two
    };
    let mut report = Finish {
        args: &args,
        job: &job,
        staged,
        start,
    };
    job.system.run_orbit(
        &job.run(),
        job.energy,
        (&job.q, &job.p),
        &job.config,
        &job.requests,
        vectors,
        &mut report,
    )
}

/// [`finish`] as the report of [`System::run_orbit`].
struct Finish<'a> {
    args: &'a OrbitArgs,
    job: &'a OrbitJob,
    staged: Option<Staged>,
    start: Instant,
}

impl OrbitReport<CliResult<()>> for Finish<'_> {
    fn report<const N: usize>(&mut self, result: &OrbitResult<N>) -> CliResult<()> {
        finish(self.args, self.job, self.staged.take(), result, self.start)
    }
}

/// Reports the orbit: the summary on stdout and, with --out, the files and plots.
fn finish<const N: usize>(
    args: &OrbitArgs,
    job: &OrbitJob,
    staged: Option<Staged>,
    result: &OrbitResult<N>,
    start: Instant,
) -> CliResult<()> {
    let wall = start.elapsed().as_secs_f64();
    let mut summary = summary_json(job, result, wall);
    if let (Some(staged), Some(dir)) = (staged, &args.out) {
        let mut warnings = write_outputs(staged.path(), job, result)?;
        if let Some(Value::Array(w)) = summary.get_mut("warnings") {
            w.extend(warnings.drain(..).map(Value::String));
        }
        summary["out_dir"] = json!(dir.display().to_string());
        write_file(
            &staged.path().join("orbit.json"),
            &(serde_json::to_string_pretty(&summary).unwrap() + "\n"),
        )?;
        staged.publish()?;
    }
    // Warnings go to stderr; with --json they are also a field of the one object on stdout.
    for w in summary["warnings"].as_array().into_iter().flatten() {
        tracing::warn!("{}", w.as_str().unwrap_or(""));
    }
    if args.json {
        println!("{summary}");
    } else {
        print!("{}", summary_text(&summary));
    }
    Ok(())
}

fn summary_json<const N: usize>(job: &OrbitJob, r: &OrbitResult<N>, wall: f64) -> Value {
    let mut gali = Map::new();
    for (i, g) in r.gali.iter().enumerate() {
        gali.insert((i + 2).to_string(), json!(g));
    }
    let mut initial = Map::new();
    for (name, x) in [("q", &job.q), ("p", &job.p)] {
        for (i, v) in x.iter().enumerate() {
            initial.insert(format!("{name}{}", i + 1), json!(v));
        }
    }
    json!({
        "system": job.system.name(),
        "potential": job.system.text(),
        "dof": N,
        "energy": job.energy,
        "method": job.method.name(),
        "tau": job.config.tau,
        "delta": job.delta,
        "protocol": job.method.is_adaptive().then(|| job.protocol.as_str()),
        "order": job.run().order(),
        "t_final": job.config.t_final,
        "t_reached": r.t_reached,
        "status": r.status.as_str(),
        "class": r.class.map(|c| c.as_str()),
        "sali": r.sali,
        "gali": gali,
        "mle": r.mle,
        "megno": r.growth.map(|g| g.megno),
        "megno_mean": r.growth.map(|g| g.megno_mean),
        "fli": r.growth.map(|g| g.fli),
        "energy_error_max": r.energy_error_max,
        "steps": r.steps,
        "crossings": r.crossings.len(),
        "wall_s": wall,
        "ns_per_step": if r.steps > 0 { wall * 1e9 / r.steps as f64 } else { 0.0 },
        "initial": initial,
        "warnings": job.warnings,
    })
}

fn summary_text(s: &Value) -> String {
    let num = |k: &str| {
        s[k].as_f64()
            .map_or("—".to_string(), |v| format!("{v:.4e}"))
    };
    let mut t = String::new();
    let plain = |k: &str| s[k].as_f64().map_or("—".to_string(), human);
    let _ = writeln!(
        t,
        "{}  τ = {}  t_final = {}",
        s["method"].as_str().unwrap_or(""),
        plain("tau"),
        plain("t_final")
    );
    let _ = writeln!(
        t,
        "status {}  class {}  t_reached {}",
        s["status"].as_str().unwrap_or(""),
        s["class"].as_str().unwrap_or("—"),
        plain("t_reached")
    );
    let mut gali = String::new();
    if let Some(g) = s["gali"].as_object() {
        for (k, v) in g {
            let _ = write!(
                gali,
                "  GALI_{k} {}",
                v.as_f64().map_or("—".into(), |v| format!("{v:.4e}"))
            );
        }
    }
    let _ = writeln!(
        t,
        "SALI {}{gali}  mLE {}  max|ΔH/H| {}",
        num("sali"),
        num("mle"),
        num("energy_error_max")
    );
    let _ = writeln!(
        t,
        "MEGNO Y {}  ⟨Y⟩ {}  FLI {}",
        num("megno"),
        num("megno_mean"),
        num("fli")
    );
    let _ = writeln!(
        t,
        "steps {}  crossings {}  wall {:.3} s  {:.1} ns/step",
        s["steps"],
        s["crossings"],
        s["wall_s"].as_f64().unwrap_or(0.0),
        s["ns_per_step"].as_f64().unwrap_or(0.0)
    );
    if let Some(d) = s["out_dir"].as_str() {
        let _ = writeln!(
            t,
            "wrote {d}/series.csv, crossings.csv, indicators.png, energy.png, section.png, orbit.json"
        );
    }
    t
}

fn write_file(path: &Path, text: &str) -> CliResult<()> {
    std::fs::write(path, text).map_err(|e| runtime(&format!("writing {}", path.display()), e))
}

/// Writes series.csv, crossings.csv and the two plots; returns warnings for plots that had
/// nothing to draw.
fn write_outputs<const N: usize>(
    dir: &Path,
    job: &OrbitJob,
    r: &OrbitResult<N>,
) -> CliResult<Vec<String>> {
    let k_max = r.series.first().map_or(0, |s| s.gali.len()) + 1;
    let mut csv = String::from("t,sali");
    for k in 2..=k_max {
        let _ = write!(csv, ",gali_{k}");
    }
    csv.push_str(",mle,megno,megno_mean,fli,energy_error\n");
    for s in &r.series {
        let _ = write!(csv, "{},{}", csv_number(s.t), csv_number(s.sali));
        for &g in &s.gali {
            let _ = write!(csv, ",{}", csv_number(g));
        }
        let _ = write!(csv, ",{}", csv_number(s.mle));
        let growth = s
            .growth
            .map_or([f64::NAN; 3], |g| [g.megno, g.megno_mean, g.fli]);
        for v in growth {
            let _ = write!(csv, ",{}", csv_number(v));
        }
        let _ = writeln!(csv, ",{}", csv_number(s.energy_error));
    }
    write_file(&dir.join("series.csv"), &csv)?;

    // t, then q2…qN and p2…pN (the section's coordinates), then p1.
    let mut cross = String::from("t");
    for name in ["q", "p"] {
        for i in 2..=N {
            let _ = write!(cross, ",{name}{i}");
        }
    }
    cross.push_str(",p1\n");
    for c in &r.crossings {
        let _ = write!(cross, "{}", c.t);
        for x in c.q[1..].iter().chain(&c.p[1..]) {
            let _ = write!(cross, ",{x}");
        }
        let _ = writeln!(cross, ",{}", c.p[0]);
    }
    write_file(&dir.join("crossings.csv"), &cross)?;

    plot_orbit(job, r, k_max, dir)
}

/// indicators.png (SALI with its thresholds, GALI_k, the mLE, MEGNO's ⟨Y⟩ and the FLI: five
/// panels), energy.png and
/// section.png (the crossings of q1 = 0 upward) of one orbit; warnings for plots without data.
fn plot_orbit<const N: usize>(
    job: &OrbitJob,
    r: &OrbitResult<N>,
    k_max: usize,
    dir: &Path,
) -> CliResult<Vec<String>> {
    let t: Vec<f64> = r.series.iter().map(|s| s.t).collect();
    let column = |f: &dyn Fn(&salient_core::orbit::Sample) -> f64| -> Vec<f64> {
        r.series.iter().map(f).collect()
    };
    let sali = column(&|s| s.sali);
    let gali: Vec<Vec<f64>> = (0..k_max.saturating_sub(1))
        .map(|k| column(&|s| s.gali[k]))
        .collect();
    let mle = column(&|s| s.mle);
    let megno_mean = column(&|s| s.growth.map_or(f64::NAN, |g| g.megno_mean));
    let fli = column(&|s| s.growth.map_or(f64::NAN, |g| g.fli));
    let energy = column(&|s| s.energy_error);
    let labels: Vec<String> = (2..=k_max).map(|k| format!("GALI_{k}")).collect();
    let start = if N == 2 && job.q[0] == 0.0 {
        format!("(q₂, p₂) = ({}, {})", job.q[1], job.p[1])
    } else {
        let list = |x: &[f64]| {
            x.iter()
                .map(|v| v.to_string())
                .collect::<Vec<_>>()
                .join(", ")
        };
        format!("q = ({}), p = ({})", list(&job.q), list(&job.p))
    };
    let title = format!("{} τ = {}  {start}", job.method.name(), job.config.tau);
    let th = job.config.thresholds;
    let (regular_label, chaotic_label) = (
        format!("regular ≥ {:e}", th.regular),
        format!("chaotic < {:e}", th.chaotic),
    );
    let panel = |title, y_label, lines, hlines| LogLogPlot {
        title,
        x_label: "t",
        y_label,
        lines,
        hlines,
        point_labels: Vec::new(),
        markers: false,
    };
    let sali_panel = panel(
        &title,
        "SALI",
        vec![Line {
            label: "SALI",
            xs: &t,
            ys: &sali,
        }],
        vec![
            HLine {
                label: &regular_label,
                y: th.regular,
            },
            HLine {
                label: &chaotic_label,
                y: th.chaotic,
            },
        ],
    );
    let gali_lines = gali
        .iter()
        .zip(&labels)
        .map(|(g, l)| Line {
            label: l,
            xs: &t,
            ys: g,
        })
        .collect();
    let mle_line = vec![Line {
        label: "mLE (finite-time)",
        xs: &t,
        ys: &mle,
    }];
    let megno_line = vec![Line {
        label: "MEGNO ⟨Y⟩",
        xs: &t,
        ys: &megno_mean,
    }];
    let quasi_periodic = vec![HLine {
        label: "quasi-periodic: 2",
        y: 2.0,
    }];
    let fli_line = vec![Line {
        label: "FLI",
        xs: &t,
        ys: &fli,
    }];
    let indicators = Panels {
        panels: vec![
            sali_panel,
            panel("", "GALI_k", gali_lines, Vec::new()),
            panel("", "mLE", mle_line, Vec::new()),
            panel("", "⟨Y⟩", megno_line, quasi_periodic),
            panel("", "FLI", fli_line, Vec::new()),
        ],
    };
    let mut warnings = Vec::new();
    let path = dir.join("indicators.png");
    warn_if_empty(
        render_panels(&indicators, &path, 1000, 1900),
        &path,
        &mut warnings,
    )?;
    let energy_plot = panel(
        &title,
        "|ΔH/H|",
        vec![Line {
            label: "|ΔH/H|",
            xs: &t,
            ys: &energy,
        }],
        Vec::new(),
    );
    let path = dir.join("energy.png");
    warn_if_empty(
        render_loglog(&energy_plot, &path, 1000, 700),
        &path,
        &mut warnings,
    )?;
    plot_section(r, &title, dir, &mut warnings)?;
    Ok(warnings)
}

/// section.png: where the orbit crosses q1 = 0 upward, in the (q₂, p₂) plane (with more than
/// two degrees of freedom, the section's projection on that plane).
fn plot_section<const N: usize>(
    r: &OrbitResult<N>,
    title: &str,
    dir: &Path,
    warnings: &mut Vec<String>,
) -> CliResult<()> {
    let q2: Vec<f64> = r.crossings.iter().map(|c| c.q[1]).collect();
    let p2: Vec<f64> = r.crossings.iter().map(|c| c.p[1]).collect();
    let plot = LinePlot {
        title,
        x_label: "q₂",
        y_label: "p₂",
        lines: vec![Line {
            label: "",
            xs: &q2,
            ys: &p2,
        }],
        y_range: None,
        dots: true,
    };
    let path = dir.join("section.png");
    warn_if_empty(render_lines(&plot, &path, 900, 800), &path, warnings)
}

/// Ok for a drawn plot, a warning for a plot with nothing to draw, an error otherwise.
fn warn_if_empty(
    drawn: Result<(), ReportError>,
    path: &Path,
    warnings: &mut Vec<String>,
) -> CliResult<()> {
    match drawn {
        Ok(()) => Ok(()),
        Err(ReportError::EmptyData(what)) => {
            // The file's name only: `path` lies in the staging folder, gone once published.
            let name = path
                .file_name()
                .map_or_else(String::new, |n| n.to_string_lossy().into());
            warnings.push(format!("{name} not drawn: {what}"));
            Ok(())
        }
        Err(e) => Err(runtime(&format!("plotting {}", path.display()), e)),
    }
}
