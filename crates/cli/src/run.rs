//! `salient run SPEC.toml`: every member of the sweep on this machine's cores, with the same
//! ledger and tile executor the distributed mode uses.

use crate::checkpoint::{files_lock, Checkpoint, RunSaver};
use crate::human::rounded;
use crate::output::Staged;
use crate::spec::{self, JobSpec, RunSpec};
use crate::usage::{runtime, CliError, CliResult};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use rayon::prelude::*;
use salient_core::orbit::{Class, Status};
use salient_grid::{
    process_cpu_seconds, run_embedded_resumed, takes_forecast, CellIndicators, CellRun, Counts,
    Forecast, Grid, Ledger, Mode, Outcome, ScanOrder,
};
use salient_report::{
    render_lines, write_npy_f64, write_npy_u8, Line, LinePlot, Table, CELL_MAP_DPI,
    CELL_MAP_DPI_RANGE,
};
use serde_json::{json, Value};
use std::fmt::Write as _;
use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

#[derive(Args, Debug)]
pub struct RunArgs {
    /// Job spec (TOML, or JSON with the same schema).
    spec: PathBuf,
    /// Worker threads (default: every core).
    #[arg(long)]
    threads: Option<usize>,
    /// Output folder (default: out/<spec name>).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Print exactly one JSON object on stdout.
    #[arg(long)]
    json: bool,
    /// Go on from the checkpoint an interrupted `salient run` of the same spec left in the
    /// output folder (runs it had finished are not integrated again).
    #[arg(long)]
    resume: bool,
    /// Resolution of the maps' PNG files (50..=600; the SVG files scale without loss).
    #[arg(long, default_value_t = CELL_MAP_DPI)]
    dpi: u32,
    /// Seconds between checkpoints of the committed outcomes (0: after every commit).
    #[arg(long, default_value_t = 10.0)]
    checkpoint_every: f64,
    /// Refuse specs whose grid holds more cells than this.
    #[arg(long, default_value_t = spec::MAX_CELLS)]
    max_cells: usize,
}

/// What one finished member of the sweep produced.
pub struct RunResult {
    spec: RunSpec,
    grid: Grid,
    ledger: Ledger,
    counts: Counts,
    cpu_s: f64,
    wall_s: f64,
    dir: PathBuf,
    /// (t, regular %, sticky %, chaotic %) at the checkpoints (full mode).
    checkpoints: Vec<(f64, f64, f64, f64)>,
    /// The folder of the earlier run whose labellers guided this one's scheduling.
    forecast_from: Option<String>,
    /// Whether the sweep covers several energies (the folder's name then says which).
    energy_swept: bool,
    /// Whether the sweep runs both modes (the folder's name then says which).
    mode_swept: bool,
    /// Whether every orbit with a class carries [`CellIndicators`].
    indicators: bool,
}

/// `01-tm-sbab2c-tau0.5-t10000`, with `-delta1e-8` for adaptive methods, and after the number
/// `H0.125-` when the sweep covers several energies and `full-`/`fast-pss-` when it runs both
/// modes.
fn run_dir_name(index: usize, r: &RunSpec, (with_energy, with_mode): (bool, bool)) -> String {
    let mut prefix = if with_energy {
        format!("H{}-", r.energy)
    } else {
        String::new()
    };
    if with_mode {
        let _ = write!(prefix, "{}-", mode_name(r.mode));
    }
    let mut s = format!(
        "{:02}-{prefix}{}-tau{}-t{}",
        index + 1,
        r.method.name(),
        r.tau,
        r.t_final
    );
    if let Some(d) = r.delta {
        let _ = write!(s, "-delta{d:e}");
    }
    s
}

/// `--dpi`: the maps' PNG resolution, in [`CELL_MAP_DPI_RANGE`].
pub fn map_dpi(dpi: u32) -> CliResult<u32> {
    if CELL_MAP_DPI_RANGE.contains(&dpi) {
        Ok(dpi)
    } else {
        Err(CliError::Usage(format!(
            "--dpi must be in {}..={} (got {dpi})",
            CELL_MAP_DPI_RANGE.start(),
            CELL_MAP_DPI_RANGE.end()
        )))
    }
}

/// `--threads`: 1..=1024, every core when absent.
pub fn thread_count(threads: Option<usize>) -> CliResult<usize> {
    match threads {
        Some(0) | Some(1025..) => Err(CliError::Usage(format!(
            "--threads must be in 1..=1024 (got {})",
            threads.unwrap_or(0)
        ))),
        Some(n) => Ok(n),
        None => Ok(std::thread::available_parallelism().map_or(1, |n| n.get())),
    }
}

pub fn run(args: RunArgs) -> CliResult<()> {
    let job = spec::load(&args.spec, args.max_cells)?;
    let threads = thread_count(args.threads)?;
    let out = args
        .out
        .clone()
        .unwrap_or_else(|| Path::new("out").join(&job.name));
    if !(args.checkpoint_every >= 0.0 && args.checkpoint_every <= 1e6) {
        return Err(CliError::Usage(format!(
            "--checkpoint-every must be in 0..=1e6 seconds (got {})",
            args.checkpoint_every
        )));
    }
    let dpi = map_dpi(args.dpi)?;
    let staged = Staged::begin(&out, "--out")?;
    let (checkpoint, committed) = Checkpoint::open(&out, &job, args.resume)?;
    crate::checkpoint::stop_on_signals(staged.path(), &out)?;
    let resume = Resume {
        checkpoint: &checkpoint,
        committed,
        every: Duration::from_secs_f64(args.checkpoint_every),
    };
    let stage = Some((staged.path(), dpi));
    let done = run_sweep(&job, threads, &out, stage, Some(resume)).and_then(|results| {
        // From here a signal lets the sweep's files be published.
        let _files = files_lock();
        crate::checkpoint::finishing();
        write_sweep(&results, Some((&out, staged)), None, args.json)
    });
    if done.is_err() {
        tracing::warn!(
            "the committed outcomes are kept in {}: `salient run SPEC --resume --out {}` goes on from them",
            out.join(crate::checkpoint::FOLDER).display(),
            out.display()
        );
    }
    done?;
    checkpoint.remove()
}

/// A sweep's checkpoint: where its runs' committed outcomes are saved, those an interrupted
/// process saved (per run), and how often to save.
pub struct Resume<'a> {
    pub checkpoint: &'a Checkpoint,
    pub committed: Vec<Vec<Outcome>>,
    pub every: Duration,
}

/// Runs every member of the sweep on `threads` threads, in order, each folder written into
/// `stage` (the staging folder of `out`) as soon as its run is done, when there is one.
pub fn run_sweep(
    job: &JobSpec,
    threads: usize,
    out: &Path,
    stage: Option<(&Path, u32)>,
    mut resume: Option<Resume<'_>>,
) -> CliResult<Vec<RunResult>> {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .map_err(|e| runtime("starting the thread pool", e))?;
    for w in &job.warnings {
        tracing::warn!("{w}");
    }
    let mut results: Vec<RunResult> = Vec::new();
    for (index, r) in job.runs.iter().enumerate() {
        // The last finished run of the sweep with the same τ, t_final, energy and mode
        // (another method, or another δ) forecasts who labels which cell: a scheduling hint
        // that leaves the labels unchanged.
        let similar = takes_forecast(&job.cell_run(index), r.mode)
            .then(|| {
                results.iter().rev().find(|p| {
                    p.spec.tau == r.tau
                        && p.spec.t_final == r.t_final
                        && p.spec.energy == r.energy
                        && p.spec.mode == r.mode
                })
            })
            .flatten();
        let forecast = similar.map(|p| (p.ledger.forecast(), p.dir_name()));
        let saving = resume.as_mut().map(|s| {
            let done = std::mem::take(&mut s.committed[index]);
            (RunSaver::new(s.checkpoint, index, s.every), done)
        });
        let result = pool.install(|| run_one(job, index, r, threads, out, forecast, saving))?;
        if let Some((stage, dpi)) = stage {
            // A stop waits for the folder to be whole, and never publishes one that failed.
            let _files = files_lock();
            if let Err(e) = pool.install(|| write_run(job, &result, stage, dpi)) {
                let _ = std::fs::remove_dir_all(stage.join(result.dir_name()));
                return Err(e);
            }
        }
        results.push(result);
    }
    Ok(results)
}

/// Where a sweep's files go: the output folder and its staging folder.
pub type Destination<'a> = (&'a Path, Staged);

/// The sweep's table.md/.csv/.json and percent_vs_t.png (when a run has checkpoints), written
/// beside the runs' folders in the staging folder, which is then published into the output
/// folder (none: nothing is written); then the table, or the JSON summary (with the job's id
/// when it came from a coordinator; table.json leaves it out), on stdout.
pub fn write_sweep(
    results: &[RunResult],
    to: Option<Destination<'_>>,
    job: Option<u64>,
    json: bool,
) -> CliResult<()> {
    let table = sweep_table(results);
    let mut summary = json!({ "runs": results.iter().map(run_json).collect::<Vec<_>>() });
    let out = match to {
        Some((out, staged)) => {
            let stage = staged.path();
            write_file(&stage.join("table.md"), &table.to_markdown())?;
            write_file(&stage.join("table.csv"), &table.to_csv())?;
            write_file(
                &stage.join("table.json"),
                &(serde_json::to_string_pretty(&summary).expect("JSON") + "\n"),
            )?;
            for ext in ["png", "svg"] {
                if results.iter().any(|r| !r.checkpoints.is_empty()) {
                    plot_percent_vs_t(results, &stage.join(format!("percent_vs_t.{ext}")))?;
                }
                if results.iter().any(|r| r.energy_swept) {
                    let path = stage.join(format!("percent_vs_energy.{ext}"));
                    plot_percent_vs_energy(results, &path)?;
                }
            }
            staged.publish()?;
            Some(out)
        }
        None => None,
    };
    // On stdout only: table.json stays the same file `salient run` writes.
    if let Some(id) = job {
        summary["job"] = json!(id);
    }
    if json {
        println!("{summary}");
    } else {
        print!("{}", table.to_markdown());
        if let Some(out) = out {
            println!("wrote {}", out.display());
        }
    }
    Ok(())
}

fn run_one(
    job: &JobSpec,
    index: usize,
    r: &RunSpec,
    threads: usize,
    out: &Path,
    forecast: Option<(Forecast, String)>,
    saving: Option<(RunSaver<'_>, Vec<Outcome>)>,
) -> CliResult<RunResult> {
    let grid = job.grid(index);
    let mode = job.mode(index);
    let cell_run = job.cell_run(index);
    // Fast PSS speculates at most one batch per thread ahead of the ledger; full mode never
    // drops work, so it takes large windows.
    let window = match mode {
        Mode::FastPss => threads * salient_grid::executor::LANES,
        Mode::Full => threads * 64,
    };
    let label = format!(
        "[{}/{}] {}",
        index + 1,
        job.runs.len(),
        run_dir_name(index, r, (job.sweeps_energy(), job.sweeps_mode()))
    );
    let compatible = grid.compatible_count() as u64;
    let bar = std::io::stderr().is_terminal().then(|| {
        let b = ProgressBar::new(compatible);
        b.set_style(
            ProgressStyle::with_template(
                "{prefix} {bar:30} {pos}/{len} cells  {msg}  {elapsed_precise} ETA {eta}",
            )
            .expect("template"),
        );
        b.set_prefix(label.clone());
        b
    });
    let cpu0 = process_cpu_seconds();
    let start = Instant::now();
    let mut last_log = Instant::now();
    let mut last_bar: Option<Instant> = None;
    let hint = forecast.as_ref().map(|(f, _)| f);
    let (mut saver, done) = saving.map_or((None, Vec::new()), |(s, d)| (Some(s), d));
    if !done.is_empty() {
        tracing::info!(run = %label, orbits = done.len(), "resumed from the checkpoint");
    }
    let mut save_error = None;
    let ledger = run_embedded_resumed(&grid, &cell_run, mode, window, hint, done, |l| {
        if let (Some(s), None) = (saver.as_mut(), &save_error) {
            save_error = s.tick(l).err();
        }
        let resolved = l.resolved() as u64;
        let orbits = l.committed.len();
        let elapsed = start.elapsed().as_secs_f64();
        let rate = orbits as f64 / elapsed.max(1e-9);
        if let Some(b) = &bar {
            b.set_position(resolved);
            // The running percentages read every labelled cell: once a second at most.
            if last_bar.is_none_or(|t| t.elapsed() >= Duration::from_secs(1)) {
                last_bar = Some(Instant::now());
                let (reg, st, ch) = running_percent(&grid, l);
                b.set_message(format!(
                    "{orbits} orbits, {rate:.0}/s, {} dropped; so far {reg:.1} / {st:.1} / {ch:.1} % r/s/c",
                    l.dropped
                ));
            }
        } else if last_log.elapsed() >= Duration::from_secs(5) {
            last_log = Instant::now();
            // Cells still to resolve at the rate so far: optimistic in fast PSS, where the
            // chaotic sea resolves early and the last cells wait on long regular orbits.
            let eta_s = elapsed * (compatible - resolved) as f64 / resolved.max(1) as f64;
            let (reg, st, ch) = running_percent(&grid, l);
            tracing::info!(
                run = %label, resolved, compatible, orbits, orbits_per_s = rounded(rate, 0),
                dropped = l.dropped, eta_s = rounded(eta_s, 0), regular = rounded(reg, 2),
                sticky = rounded(st, 2), chaotic = rounded(ch, 2), "progress"
            );
        }
    });
    if let Some(b) = bar {
        b.finish_and_clear();
    }
    if let Some(e) = save_error {
        return Err(e);
    }
    // The whole run in the checkpoint: a stop in a later run does not integrate it again.
    if let Some(s) = saver.as_mut() {
        s.finish(&ledger)?;
    }
    let wall_s = start.elapsed().as_secs_f64();
    let cpu_s = process_cpu_seconds() - cpu0;
    tracing::info!(run = %label, wall_s = rounded(wall_s, 3), orbits = ledger.committed.len(), "done");
    let mut result = RunResult::new(job, index, grid, ledger, cpu_s, wall_s, out);
    result.forecast_from = forecast.map(|(_, name)| name);
    Ok(result)
}

/// Percentages of regular, sticky and chaotic cells among the cells labelled so far.
fn running_percent(grid: &Grid, ledger: &Ledger) -> (f64, f64, f64) {
    let mut so_far = Counts::default();
    for cell in (0..grid.cells() as u32).filter(|&c| grid.is_compatible(c)) {
        if let Some(l) = ledger.label(cell) {
            so_far.add(l.class, l.status);
        }
    }
    so_far.percent()
}

/// The codes of class.npy: what each [`RunResult::class_codes`] value means.
pub const CLASS_CODE_NAMES: [&str; 6] = [
    "incompatible",
    "regular",
    "sticky",
    "chaotic",
    "escaped",
    "no class",
];

/// The per-cell indicators of `integration.indicators`: name (of the cells.csv column, the
/// .npy file and the results.nc variable) and description.
pub const INDICATORS: [(&str, &str); 4] = [
    (
        "mle",
        "finite-time maximal Lyapunov exponent (1/t) ln|w1| at t_end",
    ),
    ("megno", "MEGNO Y at t_end"),
    ("megno_mean", "running mean <Y> of MEGNO at t_end"),
    (
        "fli",
        "fast Lyapunov indicator, the largest ln|w1| up to t_end",
    ),
];

/// Edges of the ⟨Y⟩ ranges of run.json's `megno_vs_sali`: below 1.5 (near-periodic), around 2
/// (quasi-periodic), then growing (chaotic: ⟨Y⟩ ≈ λt/2).
const MEGNO_RANGES: [f64; 4] = [1.5, 2.5, 4.0, 10.0];

/// run.json's `megno_vs_sali` of a run with indicators: per SALI class, its cells counted by
/// the range of MEGNO's ⟨Y⟩ they fall in ([`MEGNO_RANGES`]), for reading how often the two
/// indicators agree.
fn megno_vs_sali(r: &RunResult) -> Option<Value> {
    if !r.indicators {
        return None;
    }
    let g = &r.grid;
    let mut counts = [[0u64; MEGNO_RANGES.len() + 1]; 3];
    for cell in (0..g.cells() as u32).filter(|&c| g.is_compatible(c)) {
        let l = r
            .ledger
            .label(cell)
            .expect("every compatible cell is labelled");
        if let (Some(class), Some(v)) = (l.class, l.indicators) {
            let row = Class::ALL
                .iter()
                .position(|&c| c == class)
                .expect("a class");
            counts[row][MEGNO_RANGES.partition_point(|&e| e <= v.megno_mean)] += 1;
        }
    }
    Some(json!({
        "megno_mean_edges": MEGNO_RANGES,
        "regular": counts[0],
        "sticky": counts[1],
        "chaotic": counts[2],
    }))
}

/// `v` in the order of [`INDICATORS`].
pub fn indicator_list(v: &CellIndicators) -> [f64; 4] {
    [v.mle, v.megno, v.megno_mean, v.fli]
}

impl RunResult {
    /// Per cell (index order), class.npy's code: 0 incompatible, 1 regular, 2 sticky,
    /// 3 chaotic, 4 escaped, 5 no class for another reason (energy drift, a failed orbit).
    pub fn class_codes(&self) -> Vec<u8> {
        let g = &self.grid;
        let mut codes = vec![0u8; g.cells()];
        for cell in (0..g.cells() as u32).filter(|&c| g.is_compatible(c)) {
            let l = self
                .ledger
                .label(cell)
                .expect("every compatible cell is labelled");
            codes[cell as usize] = match l.class {
                Some(Class::Regular) => 1,
                Some(Class::Sticky) => 2,
                Some(Class::Chaotic) => 3,
                None if l.status == Status::Escaped => 4,
                None => 5,
            };
        }
        codes
    }

    /// The grid the run covered.
    pub fn grid(&self) -> &Grid {
        &self.grid
    }

    /// Every compatible cell's label.
    pub fn ledger(&self) -> &Ledger {
        &self.ledger
    }

    /// The member of the sweep this run is.
    pub fn spec(&self) -> &RunSpec {
        &self.spec
    }

    /// CPU and wall seconds of the run.
    pub fn cost(&self) -> (f64, f64) {
        (self.cpu_s, self.wall_s)
    }

    /// Per indicator of [`INDICATORS`], every cell's value in index order (NaN where the cell
    /// has none), for a run with indicators.
    pub fn indicator_values(&self) -> Option<Vec<Vec<f64>>> {
        if !self.indicators {
            return None;
        }
        let g = &self.grid;
        let mut values = vec![vec![f64::NAN; g.cells()]; INDICATORS.len()];
        for cell in (0..g.cells() as u32).filter(|&c| g.is_compatible(c)) {
            let l = self
                .ledger
                .label(cell)
                .expect("every compatible cell is labelled");
            if let Some(v) = l.indicators {
                for (k, x) in indicator_list(&v).into_iter().enumerate() {
                    values[k][cell as usize] = x;
                }
            }
        }
        Some(values)
    }

    /// The name of the run's folder.
    pub fn dir_name(&self) -> String {
        self.dir
            .file_name()
            .map_or_else(String::new, |n| n.to_string_lossy().into_owned())
    }

    /// A finished run of `job` (embedded, or rebuilt from a coordinator's results), written
    /// under `out`.
    pub fn new(
        job: &JobSpec,
        index: usize,
        grid: Grid,
        ledger: Ledger,
        cpu_s: f64,
        wall_s: f64,
        out: &Path,
    ) -> RunResult {
        let spec = &job.runs[index];
        RunResult {
            counts: Counts::of(&grid, &ledger),
            checkpoints: checkpoint_percentages(&grid, &ledger, &job.cell_run(index)),
            dir: out.join(run_dir_name(
                index,
                spec,
                (job.sweeps_energy(), job.sweeps_mode()),
            )),
            forecast_from: None,
            energy_swept: job.sweeps_energy(),
            mode_swept: job.sweeps_mode(),
            indicators: job.cell_run(index).indicators,
            spec: spec.clone(),
            grid,
            ledger,
            cpu_s,
            wall_s,
        }
    }
}

/// Percentages at each checkpoint of a full-mode run (every cell holds its own orbit).
fn checkpoint_percentages(
    grid: &Grid,
    ledger: &Ledger,
    cell_run: &CellRun,
) -> Vec<(f64, f64, f64, f64)> {
    if ledger.mode() != Mode::Full || cell_run.checkpoints_per_decade == 0 {
        return Vec::new();
    }
    let steps = cell_run.checkpoint_steps();
    let n = grid.compatible_count() as f64;
    steps
        .iter()
        .enumerate()
        .map(|(k, &s)| {
            let (mut r, mut st, mut c) = (0u64, 0u64, 0u64);
            for o in &ledger.committed {
                match o.checkpoints.get(k).copied().flatten() {
                    Some(Class::Regular) => r += 1,
                    Some(Class::Sticky) => st += 1,
                    Some(Class::Chaotic) => c += 1,
                    None => {}
                }
            }
            let pct = |x: u64| 100.0 * x as f64 / n;
            (s as f64 * cell_run.config.tau, pct(r), pct(st), pct(c))
        })
        .collect()
}

fn class_str(class: Option<Class>) -> &'static str {
    class.map_or("none", |c| c.as_str())
}

pub fn write_file(path: &Path, text: &str) -> CliResult<()> {
    std::fs::write(path, text).map_err(|e| runtime(&format!("writing {}", path.display()), e))
}

/// Compatible cells per piece of cells.csv formatted at once: the pieces go to the pool's
/// threads (formatting 121 548 rows of shortest-form floats was most of the time spent writing a
/// 400×400 run's files).
const CSV_ROWS_PER_PIECE: usize = 8192;

/// The text of each row index and centre coordinate of the grid, "i,q2" by i and "j,p2" by
/// j: a cell's centre is (q2 of its row, p2 of its column), so each is formatted once
/// instead of once per cell (two thirds of cells.csv's floats).
struct CentreText {
    i: Vec<String>,
    q2: Vec<String>,
    j: Vec<String>,
    p2: Vec<String>,
}

impl CentreText {
    fn of(g: &Grid) -> CentreText {
        CentreText {
            i: (0..g.n_q2).map(|i| i.to_string()).collect(),
            q2: (0..g.n_q2)
                .map(|i| g.centre(g.index(i, 0)).0.to_string())
                .collect(),
            j: (0..g.n_p2).map(|j| j.to_string()).collect(),
            p2: (0..g.n_p2)
                .map(|j| g.centre(g.index(0, j)).1.to_string())
                .collect(),
        }
    }
}

/// The end of the cells.csv row of every cell an orbit labelled (",sali,class,status,source,
/// t_end" and the newline), by the orbit's cell: a 400×400 fast-PSS run has 121 548 rows
/// and about 5 000 orbits, so each ending is formatted once.
fn row_endings(r: &RunResult) -> Vec<Option<String>> {
    let endings: Vec<(u32, String)> = r
        .ledger
        .committed
        .par_iter()
        .map(|o| {
            let mut text = format!(
                ",{},{},{},{},{}",
                o.sali,
                class_str(o.class),
                o.status.as_str(),
                o.cell,
                o.t_end
            );
            if r.indicators {
                // Empty fields for an orbit without a class.
                let values = o.indicators.as_ref().map(indicator_list);
                for k in 0..INDICATORS.len() {
                    text.push(',');
                    if let Some(v) = values {
                        let _ = write!(text, "{}", v[k]);
                    }
                }
            }
            text.push('\n');
            (o.cell, text)
        })
        .collect();
    let mut by_cell = vec![None; r.grid.cells()];
    for (cell, text) in endings {
        by_cell[cell as usize] = Some(text);
    }
    by_cell
}

/// cells.csv's rows for `cells`, in order.
fn csv_rows(r: &RunResult, text: &CentreText, endings: &[Option<String>], cells: &[u32]) -> String {
    let g = &r.grid;
    let mut csv = String::with_capacity(cells.len() * 100);
    for &cell in cells {
        let l = r
            .ledger
            .label(cell)
            .expect("every compatible cell is labelled");
        let (i, j) = g.ij(cell);
        let ending = endings[l.source as usize]
            .as_deref()
            .expect("the labelling orbit is committed");
        for part in [
            &text.i[i],
            ",",
            &text.j[j],
            ",",
            &text.q2[i],
            ",",
            &text.p2[j],
            ending,
        ] {
            csv.push_str(part);
        }
    }
    csv
}

/// cells.csv: one row per compatible cell in index order, formatted in pieces on the pool.
fn write_cells_csv(r: &RunResult, path: &Path) -> CliResult<()> {
    let g = &r.grid;
    let text = CentreText::of(g);
    let endings = row_endings(r);
    let cells: Vec<u32> = (0..g.cells() as u32)
        .filter(|&c| g.is_compatible(c))
        .collect();
    let pieces: Vec<String> = cells
        .par_chunks(CSV_ROWS_PER_PIECE)
        .map(|chunk| csv_rows(r, &text, &endings, chunk))
        .collect();
    let mut csv = String::with_capacity(pieces.iter().map(String::len).sum::<usize>() + 64);
    // The centres' columns are named after the section's axes (q2, p2 for Hénon–Heiles).
    let [x, y] = g.surface.axis_names();
    csv.push_str(&format!("i,j,{x},{y},sali,class,status,label_source,t_end"));
    if r.indicators {
        for (name, _) in INDICATORS {
            csv.push(',');
            csv.push_str(name);
        }
    }
    csv.push('\n');
    for piece in &pieces {
        csv.push_str(piece);
    }
    write_file(path, &csv)
}

/// cells.csv, class.npy, sali.npy, the maps and run.json of one run, in its folder under
/// `stage` (the staging folder of the output folder); cells.csv is written beside the rest on
/// the current rayon pool.
pub fn write_run(job: &JobSpec, r: &RunResult, stage: &Path, dpi: u32) -> CliResult<()> {
    let dir = &stage.join(r.dir_name());
    std::fs::create_dir_all(dir).map_err(|e| runtime(&format!("creating {}", dir.display()), e))?;
    let (csv, rest) = rayon::join(
        || write_cells_csv(r, &dir.join("cells.csv")),
        || write_arrays_and_map(job, r, dir, dpi),
    );
    csv.and(rest)
}

/// class.npy, sali.npy, the maps ([`crate::maps::write_maps`]), results.nc and run.json of one
/// run, in `dir`.
fn write_arrays_and_map(job: &JobSpec, r: &RunResult, dir: &Path, dpi: u32) -> CliResult<()> {
    let g = &r.grid;
    let class_codes = r.class_codes();
    let mut sali = vec![f64::NAN; g.cells()];
    for cell in (0..g.cells() as u32).filter(|&c| g.is_compatible(c)) {
        let l = r
            .ledger
            .label(cell)
            .expect("every compatible cell is labelled");
        sali[cell as usize] = l.sali;
    }
    let shape = [g.n_q2, g.n_p2];
    write_npy_u8(&dir.join("class.npy"), &shape, &class_codes)
        .map_err(|e| runtime("writing class.npy", e))?;
    write_npy_f64(&dir.join("sali.npy"), &shape, &sali)
        .map_err(|e| runtime("writing sali.npy", e))?;
    let indicators = r.indicator_values();
    if let Some(values) = &indicators {
        for ((name, _), v) in INDICATORS.iter().zip(values) {
            let file = format!("{name}.npy");
            write_npy_f64(&dir.join(&file), &shape, v)
                .map_err(|e| runtime(&format!("writing {file}"), e))?;
        }
    }
    crate::maps::write_maps(job, r, &sali, indicators.as_deref(), (dir, dpi))?;
    crate::dataset::write_results_nc(job, r, indicators.as_deref(), dir)?;
    let mut run = run_json(r);
    run["spec"] = job.source.clone();
    run["versions"] = json!({ "salient": env!("CARGO_PKG_VERSION") });
    run["forecast_from"] = json!(r.forecast_from);
    run["checkpoints"] = json!(r
        .checkpoints
        .iter()
        .map(|&(t, a, b, c)| json!({"t": t, "regular": a, "sticky": b, "chaotic": c}))
        .collect::<Vec<_>>());
    write_file(
        &dir.join("run.json"),
        &(serde_json::to_string_pretty(&run).expect("JSON") + "\n"),
    )
}

/// The spec's name of a mode.
pub fn mode_name(mode: Mode) -> &'static str {
    match mode {
        Mode::FastPss => "fast-pss",
        Mode::Full => "full",
    }
}

/// The grid's bounds keyed by the section's axes: {"q2": [lo, hi], "p2": [lo, hi]}.
fn bounds_json(grid: &Grid) -> Value {
    let [x, y] = grid.surface.axis_names();
    let mut bounds = serde_json::Map::new();
    bounds.insert(x.into(), json!([grid.q2.0, grid.q2.1]));
    bounds.insert(y.into(), json!([grid.p2.0, grid.p2.1]));
    Value::Object(bounds)
}

fn run_json(r: &RunResult) -> Value {
    let c = &r.counts;
    let (reg, st, ch) = c.percent();
    let mut run = json!({
        "energy": r.spec.energy,
        "method": r.spec.method.name(),
        "tau": r.spec.tau,
        "delta": r.spec.delta,
        "t_final": r.spec.t_final,
        "mode": mode_name(r.ledger.mode()),
        "indicators": r.indicators,
        "cells": [r.grid.n_q2, r.grid.n_p2],
        "bounds": bounds_json(&r.grid),
        "order": r.grid.order.name(),
        "order_seed": match r.grid.order { ScanOrder::Shuffle(seed) => Some(seed), _ => None },
        "compatible": c.compatible,
        "percent": { "regular": reg, "sticky": st, "chaotic": ch, "escaped": c.percent_escaped(), "unclassified": c.percent_unclassified() },
        "counts": { "regular": c.regular, "sticky": c.sticky, "chaotic": c.chaotic, "escaped": c.escaped, "unclassified": c.unclassified },
        "status_counts": c.status,
        "orbits_integrated": r.ledger.committed.len(),
        "orbits_dropped": r.ledger.dropped,
        "steps_total": r.ledger.committed_steps + r.ledger.dropped_steps,
        "steps_dropped": r.ledger.dropped_steps,
        "cpu_s": r.cpu_s,
        "wall_s": r.wall_s,
        "out_dir": r.dir.display().to_string(),
    });
    if let Some(table) = megno_vs_sali(r) {
        run["megno_vs_sali"] = table;
    }
    run
}

/// Statuses without a class besides `escaped`: a column each in the table when any run has
/// cells labelled by them.
const FAILURES: [Status; 3] = [Status::EnergyDrift, Status::NonFinite, Status::StepLimit];

fn sweep_table(results: &[RunResult]) -> Table {
    let failures: Vec<Status> = FAILURES
        .into_iter()
        .filter(|&s| results.iter().any(|r| r.counts.with_status(s) > 0))
        .collect();
    let failure_headers: Vec<String> = failures
        .iter()
        .map(|s| format!("% {}", s.as_str()))
        .collect();
    let energy_swept = results.iter().any(|r| r.energy_swept);
    let mode_swept = results.iter().any(|r| r.mode_swept);
    let mut headers = if energy_swept { vec!["H"] } else { Vec::new() };
    if mode_swept {
        headers.push("mode");
    }
    headers.extend([
        "tau",
        "t_final",
        "method",
        "delta",
        "% regular",
        "% sticky",
        "% chaotic",
        "% escaped",
    ]);
    headers.extend(failure_headers.iter().map(|s| s.as_str()));
    headers.extend(["orbits", "dropped", "% steps dropped", "CPU s", "wall s"]);
    let mut t = Table::new(&headers);
    for r in results {
        let (a, b, c) = r.counts.percent();
        let mut row = if energy_swept {
            vec![format!("{}", r.spec.energy)]
        } else {
            Vec::new()
        };
        if mode_swept {
            row.push(mode_name(r.spec.mode).to_string());
        }
        row.extend([
            format!("{}", r.spec.tau),
            format!("{:e}", r.spec.t_final),
            r.spec.method.name(),
            r.spec.delta.map_or("—".into(), |d| format!("{d:e}")),
            format!("{a:.2}"),
            format!("{b:.2}"),
            format!("{c:.2}"),
            format!("{:.2}", r.counts.percent_escaped()),
        ]);
        for &s in &failures {
            row.push(format!(
                "{:.2}",
                100.0 * r.counts.with_status(s) as f64 / r.counts.compatible.max(1) as f64
            ));
        }
        row.extend([
            r.ledger.committed.len().to_string(),
            r.ledger.dropped.to_string(),
            {
                let total = r.ledger.committed_steps + r.ledger.dropped_steps;
                format!(
                    "{:.1}",
                    100.0 * r.ledger.dropped_steps as f64 / total.max(1) as f64
                )
            },
            format!("{:.2}", r.cpu_s),
            format!("{:.2}", r.wall_s),
        ]);
        t.push(row);
    }
    t
}

/// Named series (label, xs, ys) as plot lines.
fn lines_of(series: &[(String, Vec<f64>, Vec<f64>)]) -> Vec<Line<'_>> {
    series
        .iter()
        .map(|(label, xs, ys)| Line { label, xs, ys })
        .collect()
}

/// Percentages of regular, sticky, chaotic and escaped cells against the energy H, one set of
/// lines per member of the sweep at the other axes' values (method, τ, δ, t_final).
fn plot_percent_vs_energy(results: &[RunResult], path: &Path) -> CliResult<()> {
    let mut families: Vec<(String, Vec<&RunResult>)> = Vec::new();
    for r in results {
        let s = &r.spec;
        let mut key = format!("{} τ={} t={}", s.method.name(), s.tau, s.t_final);
        if let Some(d) = s.delta {
            let _ = write!(key, " δ={d:e}");
        }
        match families.iter_mut().find(|(k, _)| *k == key) {
            Some((_, members)) => members.push(r),
            None => families.push((key, vec![r])),
        }
    }
    let one = families.len() == 1;
    let mut series: Vec<(String, Vec<f64>, Vec<f64>)> = Vec::new();
    for (key, members) in &families {
        let h: Vec<f64> = members.iter().map(|r| r.spec.energy).collect();
        type Share = fn(&Counts) -> f64;
        let classes: [(&str, Share); 4] = [
            ("regular", |c| c.percent().0),
            ("sticky", |c| c.percent().1),
            ("chaotic", |c| c.percent().2),
            ("escaped", |c| c.percent_escaped()),
        ];
        for (class, value) in classes {
            let label = if one {
                class.to_string()
            } else {
                format!("{class}, {key}")
            };
            series.push((
                label,
                h.clone(),
                members.iter().map(|r| value(&r.counts)).collect(),
            ));
        }
    }
    let plot = LinePlot {
        title: "percent of compatible cells against the energy",
        x_label: "H",
        y_label: "% of cells",
        lines: lines_of(&series),
        y_range: Some((0.0, 100.0)),
        dots: false,
    };
    render_lines(&plot, path, 1200, 800).map_err(|e| runtime("plotting percent_vs_energy.png", e))
}

/// Fig. 7: full-mode percentages at checkpoints against t, and fast-PSS runs at their t_final.
fn plot_percent_vs_t(results: &[RunResult], path: &Path) -> CliResult<()> {
    let mut series: Vec<(String, Vec<f64>, Vec<f64>)> = Vec::new();
    for r in results.iter().filter(|r| !r.checkpoints.is_empty()) {
        let t: Vec<f64> = r.checkpoints.iter().map(|c| c.0).collect();
        let name = format!(
            "{} τ={} t={:e}",
            r.spec.method.name(),
            r.spec.tau,
            r.spec.t_final
        );
        series.push((
            format!("full {name}: regular"),
            t.clone(),
            r.checkpoints.iter().map(|c| c.1).collect(),
        ));
        series.push((
            format!("full {name}: chaotic"),
            t.clone(),
            r.checkpoints.iter().map(|c| c.3).collect(),
        ));
        series.push((
            format!("full {name}: sticky"),
            t,
            r.checkpoints.iter().map(|c| c.2).collect(),
        ));
    }
    let fast: Vec<&RunResult> = results
        .iter()
        .filter(|r| r.ledger.mode() == Mode::FastPss)
        .collect();
    if !fast.is_empty() {
        let t: Vec<f64> = fast.iter().map(|r| r.spec.t_final).collect();
        series.push((
            "fast PSS: regular".into(),
            t.clone(),
            fast.iter().map(|r| r.counts.percent().0).collect(),
        ));
        series.push((
            "fast PSS: chaotic".into(),
            t.clone(),
            fast.iter().map(|r| r.counts.percent().2).collect(),
        ));
        series.push((
            "fast PSS: sticky".into(),
            t,
            fast.iter().map(|r| r.counts.percent().1).collect(),
        ));
    }
    // log₁₀ t on a linear axis (the checkpoints are log-spaced, as in the paper's figures),
    // percentages on a linear one from 0 to 100 so that a class at 0 % is drawn.
    for (_, t, _) in &mut series {
        t.iter_mut().for_each(|t| *t = t.log10());
    }
    let plot = LinePlot {
        title: "percent of compatible cells against t",
        x_label: "log₁₀ t",
        y_label: "% of compatible cells",
        lines: lines_of(&series),
        y_range: Some((0.0, 100.0)),
        dots: false,
    };
    render_lines(&plot, path, 1200, 800)
        .map_err(|e| runtime(&format!("plotting {}", path.display()), e))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every cell's coordinates as the per-row and per-column texts give them are the text of
    /// `Grid::centre` for that cell, on a square grid and on a lopsided one with odd bounds.
    #[test]
    fn centre_text_is_each_cells_centre() {
        for g in [
            Grid::new(0.125, 400, 400, (-0.4397, 0.6737), (-0.5, 0.5), (20, 20)),
            Grid::new(0.1, 37, 211, (-0.31, 0.52), (-0.447, 0.4471), (5, 7)),
        ] {
            let text = CentreText::of(&g);
            for cell in 0..g.cells() as u32 {
                let (i, j) = g.ij(cell);
                let (q2, p2) = g.centre(cell);
                assert_eq!(text.i[i], i.to_string());
                assert_eq!(text.j[j], j.to_string());
                assert_eq!(text.q2[i], q2.to_string(), "cell {cell}");
                assert_eq!(text.p2[j], p2.to_string(), "cell {cell}");
            }
        }
    }
}
