//! `salient simulate`: how a job scales over many workers, predicted by the scaling simulator
//! (the real scheduler against simulated workers in virtual time).

use crate::client::spec_json;
use crate::output::{print_result, write_tables, Staged};
use crate::usage::{runtime, CliError, CliResult};
use clap::Args;
use salient_coordinator::scheduler::Config;
use salient_report::{render_loglog, Line, LogLogPlot, Table};
use salient_sim::{ForecastSource, Params, Point, Simulation};
use serde_json::json;
use std::path::{Path, PathBuf};
use std::time::Duration;

#[derive(Args, Debug)]
#[command(allow_negative_numbers = true)]
pub struct SimulateArgs {
    /// The job spec (TOML or JSON), as `salient submit` takes it.
    spec: PathBuf,
    /// Worker counts to simulate, comma-separated (one worker is simulated too: the yardstick).
    #[arg(long, default_value = "1,4,16,64,256", value_delimiter = ',')]
    workers: Vec<usize>,
    /// Threads of each worker.
    #[arg(long, default_value_t = 1)]
    threads: usize,
    /// Orbits a worker thread runs at once (default: what the product runs for the method).
    #[arg(long)]
    lanes: Option<usize>,
    /// Round trip between a worker and the coordinator, in milliseconds.
    #[arg(long = "rtt-ms", default_value_t = 0.5)]
    rtt_ms: f64,
    /// Network bandwidth each way, in Gbit/s.
    #[arg(long = "bandwidth-gbit", default_value_t = 10.0)]
    bandwidth_gbit: f64,
    /// Each one-way latency varies by up to this fraction (seeded, reproducible).
    #[arg(long, default_value_t = 0.1)]
    jitter: f64,
    /// Seed of the latency jitter.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// The interval at which busy workers poll, in milliseconds (what `salient coordinator`
    /// tells its workers: 200).
    #[arg(long = "poll-ms", default_value_t = 200)]
    poll_ms: u64,
    /// Fast PSS: cells per worker thread in one lease, as `salient coordinator
    /// --lease-cells-per-thread`.
    #[arg(long = "lease-cells-per-thread", default_value_t = Config::default().lease_cells_per_thread)]
    lease_cells: usize,
    /// CPU nanoseconds per orbit-step in a thread's full lanes (default: measured here first).
    #[arg(long = "step-ns")]
    step_ns: Option<f64>,
    /// A fixed coordinator cost per poll, in microseconds (default: the scheduler's CPU time
    /// on each poll, measured as it runs).
    #[arg(long = "coordinator-us")]
    coordinator_us: Option<f64>,
    /// CPU microseconds the coordinator's gRPC stack and store spend on a poll besides the
    /// scheduler (default: measured on loopback, see docs/distributed.md).
    #[arg(long = "coordinator-stack-us", default_value_t = salient_sim::COORDINATOR_STACK_NS as f64 / 1e3)]
    coordinator_stack_us: f64,
    /// CPU microseconds a worker's network side spends on a poll round.
    #[arg(long = "worker-stack-us", default_value_t = salient_sim::WORKER_STACK_NS as f64 / 1e3)]
    worker_stack_us: f64,
    /// Put the coordinator and every worker on one host of this many cores (as on loopback);
    /// default: each busy thread has a core of its own.
    #[arg(long = "host-cores")]
    host_cores: Option<f64>,
    /// The coordinator's forecast of who labels each cell: none, perfect (the job's own
    /// labellers: the best a forecast can do) or pilot:T (a pilot run to t_final = T).
    #[arg(long, default_value = "none")]
    forecast: String,
    /// Write simulate.md, simulate.csv, simulate.json, speedup.png and timeline.csv here.
    #[arg(long)]
    out: Option<PathBuf>,
    /// Print exactly one JSON object on stdout.
    #[arg(long)]
    json: bool,
}

fn params(args: &SimulateArgs) -> CliResult<Params> {
    let usage = |m: String| Err(CliError::Usage(m));
    if args.workers.is_empty() || args.workers.iter().any(|&w| !(1..=100_000).contains(&w)) {
        return usage(format!(
            "--workers must list counts in 1..=100000 (got {:?})",
            args.workers
        ));
    }
    if !(1..=4096).contains(&args.threads) {
        return usage(format!(
            "--threads must be in 1..=4096 (got {})",
            args.threads
        ));
    }
    if args.lanes.is_some_and(|l| !(1..=64).contains(&l)) {
        return usage(format!("--lanes must be in 1..=64 (got {:?})", args.lanes));
    }
    if !(args.rtt_ms.is_finite() && (0.0..=60_000.0).contains(&args.rtt_ms)) {
        return usage(format!(
            "--rtt-ms must be in 0..=60000 (got {})",
            args.rtt_ms
        ));
    }
    if !(args.bandwidth_gbit.is_finite() && args.bandwidth_gbit > 0.0) {
        return usage(format!(
            "--bandwidth-gbit must be positive (got {})",
            args.bandwidth_gbit
        ));
    }
    if !(args.jitter.is_finite() && (0.0..1.0).contains(&args.jitter)) {
        return usage(format!("--jitter must be in [0, 1) (got {})", args.jitter));
    }
    if !(10..=5000).contains(&args.poll_ms) {
        return usage(format!(
            "--poll-ms must be in 10..=5000 (got {})",
            args.poll_ms
        ));
    }
    if !(1..=65_536).contains(&args.lease_cells) {
        return usage(format!(
            "--lease-cells-per-thread must be in 1..=65536 (got {})",
            args.lease_cells
        ));
    }
    if args.step_ns.is_some_and(|s| !(s.is_finite() && s > 0.0)) {
        return usage(format!(
            "--step-ns must be positive (got {:?})",
            args.step_ns
        ));
    }
    if args
        .coordinator_us
        .is_some_and(|c| !(c.is_finite() && c >= 0.0))
    {
        return usage(format!(
            "--coordinator-us must be at least 0 (got {:?})",
            args.coordinator_us
        ));
    }
    for (flag, v) in [
        ("--coordinator-stack-us", args.coordinator_stack_us),
        ("--worker-stack-us", args.worker_stack_us),
    ] {
        if !(v.is_finite() && (0.0..=1e6).contains(&v)) {
            return usage(format!("{flag} must be in 0..=1000000 (got {v})"));
        }
    }
    if args
        .host_cores
        .is_some_and(|c| !(c.is_finite() && (1.0..=4096.0).contains(&c)))
    {
        return usage(format!(
            "--host-cores must be in 1..=4096 (got {:?})",
            args.host_cores
        ));
    }
    let forecast = match args.forecast.as_str() {
        "none" => ForecastSource::None,
        "perfect" => ForecastSource::Perfect,
        f => match f.strip_prefix("pilot:").map(str::parse::<f64>) {
            Some(Ok(t)) if t.is_finite() && t > 0.0 => ForecastSource::Pilot(t),
            _ => {
                return usage(format!(
                    "--forecast must be none, perfect or pilot:T with T > 0 (got {f:?})"
                ))
            }
        },
    };
    let config = Config {
        poll: Duration::from_millis(args.poll_ms),
        lease_cells_per_thread: args.lease_cells,
        ..Config::default()
    };
    Ok(Params {
        threads: args.threads,
        lanes: args.lanes,
        rtt_ns: (args.rtt_ms * 1e6) as u64,
        bandwidth: args.bandwidth_gbit * 1.25e8,
        jitter: args.jitter,
        seed: args.seed,
        config,
        step_ns: args.step_ns,
        coordinator_ns: args.coordinator_us.map(|us| (us * 1e3) as u64),
        coordinator_stack_ns: (args.coordinator_stack_us * 1e3) as u64,
        worker_stack_ns: (args.worker_stack_us * 1e3) as u64,
        host_cores: args.host_cores,
        forecast,
        ..Params::default()
    })
}

pub fn simulate(args: SimulateArgs) -> CliResult<()> {
    let params = params(&args)?;
    let (job, json_text) = spec_json(&args.spec, salient_grid::spec::MAX_CELLS)?;
    let staged = args
        .out
        .as_deref()
        .map(|o| Staged::begin(o, "--out"))
        .transpose()?;
    let mut sim = Simulation::new(&json_text, params).map_err(CliError::Usage)?;
    if !args.json {
        eprintln!(
            "simulating {} ({} run(s)): {} lane(s) per thread, {:.2} ns per orbit-step{}",
            job.name,
            job.runs.len(),
            sim.lanes(),
            sim.step_ns(),
            if args.step_ns.is_some() {
                ""
            } else {
                " (measured here)"
            }
        );
    }
    let quiet = args.json;
    let points = sim
        .sweep(&args.workers, |p| {
            if !quiet {
                eprintln!(
                    "  W = {:>6}: {:.3} s simulated, speedup {:.2} (bound {:.2})",
                    p.stats.workers, p.stats.wall_s, p.speedup, p.bound
                );
            }
        })
        .map_err(|e| CliError::Runtime(format!("simulation: {e}")))?;
    let table = table(&points);
    let summary = json!({
        "spec": job.name,
        "threads": args.threads,
        "lanes": sim.lanes(),
        "step_ns": sim.step_ns(),
        "rtt_ms": args.rtt_ms,
        "bandwidth_gbit": args.bandwidth_gbit,
        "poll_ms": args.poll_ms,
        "lease_cells_per_thread": args.lease_cells,
        "coordinator_us": args.coordinator_us,
        "coordinator_stack_us": args.coordinator_stack_us,
        "worker_stack_us": args.worker_stack_us,
        "host_cores": args.host_cores,
        "forecast": args.forecast,
        "traced_orbits": sim.traced(),
        "sequential": sim.sequential(),
        "points": points,
    });
    if let Some(staged) = staged {
        write_outputs(staged.path(), &job.name, &table, &summary, &points)?;
        staged.publish()?;
    }
    print_result(
        args.json,
        &summary,
        &table,
        args.out.as_deref(),
        "simulate.md, simulate.csv, simulate.json, speedup.png, timeline.csv",
    );
    Ok(())
}

fn table(points: &[Point]) -> Table {
    let mut table = Table::new(&[
        "workers",
        "wall_s",
        "speedup",
        "bound",
        "speedup/bound",
        "steps",
        "steps vs 1",
        "extra steps %",
        "open share",
        "abandoned",
        "polls",
        "coord busy %",
        "coord µs/outcome",
        "relay MB",
        "frontier waits s",
    ]);
    for p in points {
        let s = &p.stats;
        table.push(vec![
            s.workers.to_string(),
            format!("{:.3}", s.wall_s),
            format!("{:.2}", p.speedup),
            format!("{:.2}", p.bound),
            format!("{:.2}", p.speedup / p.bound),
            format!("{:.4e}", s.steps as f64),
            format!("{:.3}", p.steps_vs_one),
            format!("{:.1}", p.extra_steps_pct),
            format!("{:.2}", p.open_share),
            s.orbits_abandoned.to_string(),
            s.polls.to_string(),
            format!("{:.1}", p.coordinator_busy_pct),
            format!("{:.1}", p.coordinator_us_per_outcome),
            format!("{:.1}", s.relay_bytes as f64 / 1e6),
            format!(
                "{:.2} / {:.2} / {:.2} / {:.2} / {:.2}",
                s.frontier.unleased_s,
                s.frontier.queued_s,
                s.frontier.running_s,
                s.frontier.reporting_s,
                s.frontier.stranded_s
            ),
        ]);
    }
    table
}

fn write_outputs(
    dir: &Path,
    name: &str,
    table: &Table,
    summary: &serde_json::Value,
    points: &[Point],
) -> CliResult<()> {
    write_tables(dir, "simulate", table, summary)?;
    let ws: Vec<f64> = points.iter().map(|p| p.stats.workers as f64).collect();
    let speedups: Vec<f64> = points.iter().map(|p| p.speedup).collect();
    let bounds: Vec<f64> = points.iter().map(|p| p.bound).collect();
    let title = format!("simulated speedup over one worker, {name}");
    let plot = LogLogPlot {
        title: &title,
        x_label: "workers W",
        y_label: "speedup over one worker",
        lines: vec![
            Line {
                label: "simulated",
                xs: &ws,
                ys: &speedups,
            },
            Line {
                label: "bound min(W, T1 / longest orbit)",
                xs: &ws,
                ys: &bounds,
            },
        ],
        hlines: Vec::new(),
        point_labels: Vec::new(),
        markers: true,
    };
    render_loglog(&plot, &dir.join("speedup.png"), 1200, 900)
        .map_err(|e| runtime("drawing speedup.png", e))?;
    write_timeline(&dir.join("timeline.csv"), points)
}

/// Every worker count's samples of the job's progress over virtual time, one row each.
fn write_timeline(path: &Path, points: &[Point]) -> CliResult<()> {
    let mut csv = String::from(
        "workers,t_s,running_orbits,busy_threads,committed_orbits,resolved_cells,\
         wanted_cells,leased_cells\n",
    );
    for p in points {
        for s in &p.stats.timeline {
            let g = &s.progress;
            csv += &format!(
                "{},{:.4},{},{},{},{},{},{}\n",
                p.stats.workers,
                s.t_s,
                s.running_orbits,
                s.busy_threads,
                g.committed_orbits,
                g.resolved_cells,
                g.wanted_cells,
                g.leased_cells
            );
        }
    }
    std::fs::write(path, csv).map_err(|e| runtime(&format!("writing {}", path.display()), e))
}
