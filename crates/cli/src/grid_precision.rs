//! `salient precision --grid SPEC`: speed against error for whole section grids. Runs the
//! sweep as `salient run` does and compares every run's class per cell with a reference run
//! of the same grid: by default full mode with a tight f64 Taylor run per t_final, computed
//! once and kept in a cache folder keyed by everything that sets its classes.

use crate::output::{print_result, write_tables, Staged};
use crate::run::{mode_name, run_sweep, thread_count, RunResult, CLASS_CODE_NAMES};
use crate::spec::{self, JobSpec, Mode};
use crate::usage::{runtime, CliError, CliResult};
use salient_report::{read_npy_u8, render_loglog, HLine, Line, LogLogPlot, Table, CELL_MAP_DPI};
use serde_json::{json, Value};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// δ of the default reference: tight for f64 Taylor series, a few hundred times its floor.
pub const REFERENCE_DELTA: f64 = 1e-13;

/// What `salient precision --grid` was asked.
pub struct GridRequest {
    pub spec: PathBuf,
    pub reference: Option<PathBuf>,
    pub cache: Option<PathBuf>,
    pub fast_vs_full: bool,
    pub threads: Option<usize>,
    pub out: Option<PathBuf>,
    pub json: bool,
}

/// One run's classes against another's, cell by cell.
#[derive(Clone, Debug, PartialEq)]
pub struct Comparison {
    pub compatible: u64,
    /// `pairs[a][b]`: cells whose code (class.npy's) is `a` in the run and `b` in the other.
    pub pairs: [[u64; 6]; 6],
}

impl Comparison {
    /// Tallies two runs' class.npy codes over the same grid; the grids must agree on which
    /// cells are compatible.
    pub fn of(run: &[u8], other: &[u8]) -> Result<Comparison, String> {
        if run.len() != other.len() {
            return Err(format!(
                "the grids differ: {} cells against {}",
                run.len(),
                other.len()
            ));
        }
        let mut pairs = [[0u64; 6]; 6];
        for (cell, (&a, &b)) in run.iter().zip(other).enumerate() {
            if (a == 0) != (b == 0) || a > 5 || b > 5 {
                return Err(format!(
                    "the grids differ: cell {cell} is {} in one and {} in the other",
                    code_name(a),
                    code_name(b)
                ));
            }
            pairs[a as usize][b as usize] += 1;
        }
        let compatible = pairs.iter().flatten().sum::<u64>() - pairs[0][0];
        Ok(Comparison { compatible, pairs })
    }

    /// Cells whose code differs.
    pub fn differing(&self) -> u64 {
        (1..6)
            .flat_map(|a| (1..6).map(move |b| (a, b)))
            .filter(|(a, b)| a != b)
            .map(|(a, b)| self.pairs[a][b])
            .sum()
    }

    /// [`Comparison::differing`] in percent of the compatible cells.
    pub fn differing_percent(&self) -> f64 {
        percent(self.differing(), self.compatible)
    }

    /// The run's percentage of regular, sticky and chaotic cells minus the other's.
    pub fn percent_errors(&self) -> [f64; 3] {
        [1, 2, 3].map(|code| {
            let mine: u64 = self.pairs[code].iter().sum();
            let theirs: u64 = self.pairs.iter().map(|row| row[code]).sum();
            percent(mine, self.compatible) - percent(theirs, self.compatible)
        })
    }

    /// The differing cells by (class in the run, class in the other), most first.
    pub fn pair_counts(&self) -> Vec<(&'static str, &'static str, u64)> {
        let mut v: Vec<_> = (1..6)
            .flat_map(|a| (1..6).map(move |b| (a, b)))
            .filter(|&(a, b)| a != b && self.pairs[a][b] > 0)
            .map(|(a, b)| (CLASS_CODE_NAMES[a], CLASS_CODE_NAMES[b], self.pairs[a][b]))
            .collect();
        v.sort_by(|x, y| y.2.cmp(&x.2).then((x.0, x.1).cmp(&(y.0, y.1))));
        v
    }
}

fn code_name(code: u8) -> &'static str {
    CLASS_CODE_NAMES
        .get(code as usize)
        .copied()
        .unwrap_or("an unknown code")
}

fn percent(n: u64, of: u64) -> f64 {
    if of == 0 {
        0.0
    } else {
        100.0 * n as f64 / of as f64
    }
}

/// class.npy's codes of a run that serves as reference, and what it cost.
struct Reference {
    codes: Vec<u8>,
    /// Where it came from: "given", "cached" or "computed", and its folder.
    origin: &'static str,
    dir: PathBuf,
    cpu_s: f64,
    wall_s: f64,
}

/// The default reference of a sweep's runs at `energy` to `t_final`: the same system, grid and
/// checks in full mode, f64 Taylor at δ = [`REFERENCE_DELTA`] with the free protocol, sampled
/// every `tau` (the sweep's smallest τ).
fn reference_spec(job: &JobSpec, energy: f64, t_final: f64, tau: f64) -> CliResult<JobSpec> {
    let mut v = job.source.clone();
    v["name"] = json!(format!("{}-reference", job.name));
    v["system"]["energy"] = json!(energy);
    v["grid"]["mode"] = json!("full");
    v["sweep"] = json!({
        "method": ["taylor"], "tau": [tau], "t_final": [t_final], "delta": [REFERENCE_DELTA],
    });
    v["integration"]["protocol"] = json!("free");
    reparse(&v)
}

/// Run `index` of the sweep alone in full mode (what fast PSS is compared with).
fn full_mode_spec(job: &JobSpec, index: usize) -> CliResult<JobSpec> {
    let r = &job.runs[index];
    let mut v = job.source.clone();
    v["name"] = json!(format!("{}-full", job.name));
    v["system"]["energy"] = json!(r.energy);
    v["grid"]["mode"] = json!("full");
    v["sweep"] = json!({
        "method": [r.method.name()], "tau": [r.tau], "t_final": [r.t_final],
        "delta": r.delta.map(|d| vec![d]),
    });
    reparse(&v)
}

fn reparse(v: &Value) -> CliResult<JobSpec> {
    spec::parse(&v.to_string(), true)
        .map_err(|e| CliError::Runtime(format!("building a comparison run: {}", e.0)))
}

/// The cache folder: `--cache`, else `$SALIENT_CACHE`, `$XDG_CACHE_HOME/salient` or
/// `~/.cache/salient`, each with `references/` below it.
fn cache_root(flag: Option<&Path>) -> CliResult<PathBuf> {
    let var = |k: &str| {
        std::env::var_os(k)
            .filter(|v| !v.is_empty())
            .map(PathBuf::from)
    };
    let root = flag
        .map(Path::to_path_buf)
        .or_else(|| var("SALIENT_CACHE"))
        .or_else(|| var("XDG_CACHE_HOME").map(|d| d.join("salient")))
        .or_else(|| var("HOME").map(|d| d.join(".cache").join("salient")))
        .ok_or_else(|| {
            CliError::Usage(
                "--cache: no cache folder given and neither $HOME nor $XDG_CACHE_HOME is set"
                    .into(),
            )
        })?;
    Ok(root.join("references"))
}

/// FNV-1a of the spec as parsed (sorted keys, the name left out) and Salient's version: the
/// same key means the same classes.
fn cache_key(job: &JobSpec) -> String {
    let mut v = job.source.clone();
    v["name"] = Value::Null;
    let text = format!("{}|{}", v, env!("CARGO_PKG_VERSION"));
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for b in text.bytes() {
        h ^= u64::from(b);
        h = h.wrapping_mul(0x0100_0000_01b3);
    }
    format!("{h:016x}")
}

/// The one-run `job`'s classes from the cache, or computed on `threads` threads and kept there.
fn cached_run(job: &JobSpec, cache: &Path, threads: usize) -> CliResult<Reference> {
    let dir = cache.join(cache_key(job));
    let meta_path = dir.join("reference.json");
    if let Ok(text) = std::fs::read_to_string(&meta_path) {
        let meta: Value = serde_json::from_str(&text)
            .map_err(|e| runtime(&format!("reading {}", meta_path.display()), e))?;
        let run_dir = dir.join(meta["run"].as_str().unwrap_or_default());
        let (_, codes) = read_npy_u8(&run_dir.join("class.npy"))
            .map_err(|e| runtime("reading a cached reference", e))?;
        return Ok(Reference {
            codes,
            origin: "cached",
            dir: run_dir,
            cpu_s: meta["cpu_s"].as_f64().unwrap_or(f64::NAN),
            wall_s: meta["wall_s"].as_f64().unwrap_or(f64::NAN),
        });
    }
    let r = &job.runs[0];
    eprintln!(
        "salient precision: computing {} {} τ = {} t = {} in full mode (kept in {})",
        r.method.name(),
        r.delta.map_or(String::new(), |d| format!("δ = {d:e}")),
        r.tau,
        r.t_final,
        dir.display()
    );
    let staged = Staged::begin(&dir, "--cache")?;
    let results = run_sweep(
        job,
        threads,
        &dir,
        Some((staged.path(), CELL_MAP_DPI)),
        None,
    )?;
    let run = &results[0];
    let (cpu_s, wall_s) = run.cost();
    let meta = json!({
        "run": run.dir_name(), "cpu_s": cpu_s, "wall_s": wall_s,
        "spec": job.source, "salient": env!("CARGO_PKG_VERSION"),
    });
    crate::run::write_file(
        &staged.path().join("reference.json"),
        &(serde_json::to_string_pretty(&meta).expect("JSON") + "\n"),
    )?;
    staged.publish()?;
    Ok(Reference {
        codes: run.class_codes(),
        origin: "computed",
        dir: dir.join(run.dir_name()),
        cpu_s,
        wall_s,
    })
}

/// `--reference DIR`: a run folder of the same grid holding class.npy.
fn given_reference(dir: &Path, shape: [usize; 2]) -> CliResult<Reference> {
    let (got, codes) = read_npy_u8(&dir.join("class.npy")).map_err(|e| {
        CliError::Usage(format!(
            "--reference {}: not a run folder with class.npy ({e})",
            dir.display()
        ))
    })?;
    if got != shape {
        return Err(CliError::Usage(format!(
            "--reference {}: its grid is {got:?} cells, the spec's {shape:?}",
            dir.display()
        )));
    }
    Ok(Reference {
        codes,
        origin: "given",
        dir: dir.to_path_buf(),
        cpu_s: f64::NAN,
        wall_s: f64::NAN,
    })
}

/// One run of the sweep against its reference (and, with `--fast-vs-full`, against the same
/// run in full mode).
struct Row {
    index: usize,
    against_reference: Comparison,
    reference: usize,
    fast_vs_full: Option<Comparison>,
}

pub fn run(req: GridRequest) -> CliResult<()> {
    let job = spec::load(&req.spec, spec::MAX_CELLS)?;
    if job.sweeps_mode() {
        return Err(CliError::Usage(
            "--grid: sweep.mode lists both modes; compare one mode at a time (--fast-vs-full \
             sets fast PSS beside full mode)"
                .into(),
        ));
    }
    let threads = thread_count(req.threads)?;
    let shape = [job.grid.n_q2, job.grid.n_p2];
    let given = req
        .reference
        .as_deref()
        .map(|d| given_reference(d, shape))
        .transpose()?;
    let cache = cache_root(req.cache.as_deref())?;
    let staged = req
        .out
        .as_deref()
        .map(|d| Staged::begin(d, "--out"))
        .transpose()?;
    let out = req.out.clone().unwrap_or_default();
    let results = run_sweep(
        &job,
        threads,
        &out,
        staged.as_ref().map(|s| (s.path(), CELL_MAP_DPI)),
        None,
    )?;
    let (references, rows) = compare_all(&job, &results, given, &cache, threads, req.fast_vs_full)?;
    let table = comparison_table(&job, &results, &references, &rows);
    let summary = summary_json(&job, &results, &references, &rows);
    if let Some(staged) = staged {
        write_tables(staged.path(), "grid_precision", &table, &summary)?;
        plot_misclassified(
            &job,
            &results,
            &rows,
            &staged.path().join("misclassified_vs_cpu.png"),
        )?;
        staged.publish()?;
    }
    print_result(
        req.json,
        &summary,
        &table,
        req.out.as_deref(),
        "grid_precision.md, grid_precision.csv, grid_precision.json, misclassified_vs_cpu.png and the runs' folders",
    );
    Ok(())
}

/// Every run against its reference (the given one, or the default per t_final from the cache).
fn compare_all(
    job: &JobSpec,
    results: &[RunResult],
    given: Option<Reference>,
    cache: &Path,
    threads: usize,
    fast_vs_full: bool,
) -> CliResult<(Vec<Reference>, Vec<Row>)> {
    let tau = job.runs.iter().map(|r| r.tau).fold(f64::INFINITY, f64::min);
    let one_given = given.is_some();
    let mut references: Vec<Reference> = given.into_iter().collect();
    // Per (energy, t_final): its reference.
    let mut by_run: BTreeMap<(u64, u64), usize> = BTreeMap::new();
    let mut rows = Vec::new();
    for (index, result) in results.iter().enumerate() {
        let (energy, t_final) = (result.spec().energy, result.spec().t_final);
        let key = (energy.to_bits(), t_final.to_bits());
        let reference = if one_given {
            0
        } else if let Some(&k) = by_run.get(&key) {
            k
        } else {
            let spec = reference_spec(job, energy, t_final, tau)?;
            references.push(cached_run(&spec, cache, threads)?);
            by_run.insert(key, references.len() - 1);
            references.len() - 1
        };
        let codes = result.class_codes();
        let against_reference =
            Comparison::of(&codes, &references[reference].codes).map_err(|e| {
                CliError::Usage(format!(
                    "--reference {}: {e}",
                    references[reference].dir.display()
                ))
            })?;
        let fast_vs_full = if fast_vs_full && job.mode(index) == Mode::FastPss {
            let full = cached_run(&full_mode_spec(job, index)?, cache, threads)?;
            Some(Comparison::of(&codes, &full.codes).map_err(CliError::Runtime)?)
        } else {
            None
        };
        rows.push(Row {
            index,
            against_reference,
            reference,
            fast_vs_full,
        });
    }
    Ok((references, rows))
}

fn run_label(r: &RunResult) -> String {
    let s = r.spec();
    match s.delta {
        Some(d) => format!("δ={d:e}"),
        None => format!("τ={}", s.tau),
    }
}

fn comparison_table(
    job: &JobSpec,
    results: &[RunResult],
    references: &[Reference],
    rows: &[Row],
) -> Table {
    let swept = job.sweeps_energy();
    let mut headers = if swept { vec!["H"] } else { Vec::new() };
    headers.extend([
        "method",
        "tau",
        "delta",
        "t_final",
        "CPU s",
        "wall s",
        "% cells differing",
        "cells differing",
        "by class (run / reference)",
        "Δ % regular",
        "Δ % sticky",
        "Δ % chaotic",
        "% fast vs full",
        "reference",
    ]);
    let mut table = Table::new(&headers);
    for row in rows {
        let r = &results[row.index];
        let s = r.spec();
        let c = &row.against_reference;
        let (cpu, wall) = r.cost();
        let pairs: Vec<String> = c
            .pair_counts()
            .iter()
            .take(3)
            .map(|(a, b, n)| format!("{a}/{b} {n}"))
            .collect();
        let [dr, ds, dc] = c.percent_errors();
        let mut cells = if swept {
            vec![s.energy.to_string()]
        } else {
            Vec::new()
        };
        cells.extend([
            s.method.name(),
            s.tau.to_string(),
            s.delta.map_or("—".into(), |d| format!("{d:e}")),
            s.t_final.to_string(),
            format!("{cpu:.3}"),
            format!("{wall:.3}"),
            format!("{:.2}", c.differing_percent()),
            c.differing().to_string(),
            if pairs.is_empty() {
                "—".into()
            } else {
                pairs.join(", ")
            },
            format!("{dr:+.2}"),
            format!("{ds:+.2}"),
            format!("{dc:+.2}"),
            row.fast_vs_full
                .as_ref()
                .map_or("—".into(), |f| format!("{:.2}", f.differing_percent())),
            references[row.reference].origin.to_string(),
        ]);
        table.push(cells);
    }
    table
}

fn comparison_json(c: &Comparison) -> Value {
    let [dr, ds, dc] = c.percent_errors();
    json!({
        "compatible": c.compatible,
        "differing": c.differing(),
        "differing_percent": c.differing_percent(),
        "percent_errors": { "regular": dr, "sticky": ds, "chaotic": dc },
        "pairs": c.pair_counts().iter().map(|(a, b, n)| json!({"run": a, "reference": b, "cells": n})).collect::<Vec<_>>(),
    })
}

fn summary_json(
    job: &JobSpec,
    results: &[RunResult],
    references: &[Reference],
    rows: &[Row],
) -> Value {
    json!({
        "spec": job.name,
        "mode": mode_name(job.mode(0)),
        "references": references.iter().map(|r| json!({
            "origin": r.origin, "folder": r.dir.display().to_string(),
            "cpu_s": finite_or_null(r.cpu_s), "wall_s": finite_or_null(r.wall_s),
        })).collect::<Vec<_>>(),
        "rows": rows.iter().map(|row| {
            let r = &results[row.index];
            let s = r.spec();
            let (cpu, wall) = r.cost();
            json!({
                "energy": s.energy, "method": s.method.name(), "tau": s.tau, "delta": s.delta,
                "t_final": s.t_final,
                "cpu_s": cpu, "wall_s": wall, "reference": row.reference,
                "against_reference": comparison_json(&row.against_reference),
                "fast_vs_full": row.fast_vs_full.as_ref().map(comparison_json),
            })
        }).collect::<Vec<_>>(),
    })
}

fn finite_or_null(x: f64) -> Value {
    if x.is_finite() {
        json!(x)
    } else {
        Value::Null
    }
}

/// Cells misclassified (%) against CPU s, one line per method (and protocol, and t_final when
/// the sweep has several); runs with no differing cell drawn on a labelled floor.
fn plot_misclassified(
    job: &JobSpec,
    results: &[RunResult],
    rows: &[Row],
    path: &Path,
) -> CliResult<()> {
    let compatible = rows
        .first()
        .map_or(1, |r| r.against_reference.compatible.max(1));
    // Half a cell: below every nonzero count, so the floor reads as "none".
    let floor = 50.0 / compatible as f64;
    let varies = |f: fn(&RunResult) -> f64| results.windows(2).any(|w| f(&w[0]) != f(&w[1]));
    let several_t = varies(|r| r.spec().t_final);
    let several_tau = varies(|r| r.spec().tau);
    let several_h = job.sweeps_energy();
    let mut groups: BTreeMap<String, (Vec<f64>, Vec<f64>)> = BTreeMap::new();
    let mut labels = Vec::new();
    for row in rows {
        let r = &results[row.index];
        let s = r.spec();
        // A curve runs over τ for a tangent-map method and over δ for an adaptive one, so an
        // adaptive method's curves are per τ too.
        let mut key = s.method.name();
        if s.method.is_adaptive() {
            key = format!("{key} ({})", job.protocol.as_str());
            if several_tau {
                key = format!("{key} τ={}", s.tau);
            }
        }
        if several_t {
            key = format!("{key}, t={}", s.t_final);
        }
        if several_h {
            key = format!("{key}, H={}", s.energy);
        }
        let y = row.against_reference.differing_percent().max(floor);
        let x = r.cost().0.max(1e-3);
        let g = groups.entry(key).or_default();
        g.0.push(x);
        g.1.push(y);
        labels.push((x, y, run_label(r)));
    }
    let lines: Vec<Line> = groups
        .iter()
        .map(|(k, (xs, ys))| Line { label: k, xs, ys })
        .collect();
    let floor_label = "no cell differs (drawn at half a cell)";
    let title = format!(
        "cells misclassified, {} ({})",
        job.name,
        mode_name(job.mode(0))
    );
    let plot = LogLogPlot {
        title: &title,
        x_label: "CPU time (s)",
        y_label: "cells whose class differs from the reference (%)",
        lines,
        hlines: vec![HLine {
            label: floor_label,
            y: floor,
        }],
        point_labels: labels,
        markers: true,
    };
    render_loglog(&plot, path, 1400, 1000)
        .map_err(|e| runtime("plotting misclassified_vs_cpu.png", e))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_run_against_itself_differs_nowhere() {
        let codes = [0, 1, 2, 3, 3, 4, 5, 1, 0];
        let c = Comparison::of(&codes, &codes).unwrap();
        assert_eq!(c.compatible, 7);
        assert_eq!(c.differing(), 0);
        assert_eq!(c.percent_errors(), [0.0; 3]);
        assert!(c.pair_counts().is_empty());
    }

    #[test]
    fn differing_cells_are_counted_by_pair_and_add_up() {
        let run = [0, 1, 3, 3, 2, 1, 4];
        let reference = [0, 1, 1, 1, 3, 3, 5];
        let c = Comparison::of(&run, &reference).unwrap();
        assert_eq!(c.compatible, 6);
        assert_eq!(c.differing(), 5);
        let pairs = c.pair_counts();
        assert_eq!(pairs[0], ("chaotic", "regular", 2));
        assert_eq!(pairs.iter().map(|p| p.2).sum::<u64>(), c.differing());
        // Regular: 2 of 6 in the run, 3 of 6 in the reference.
        let [dr, ds, dc] = c.percent_errors();
        assert!((dr - (200.0 / 6.0 - 300.0 / 6.0)).abs() < 1e-12);
        assert!((ds - 100.0 / 6.0).abs() < 1e-12);
        assert!((dc - (200.0 / 6.0 - 200.0 / 6.0)).abs() < 1e-12);
    }

    #[test]
    fn grids_that_disagree_on_compatible_cells_are_refused() {
        assert!(Comparison::of(&[0, 1], &[1, 1])
            .unwrap_err()
            .contains("cell 0"));
        assert!(Comparison::of(&[1, 1], &[1])
            .unwrap_err()
            .contains("2 cells against 1"));
    }

    #[test]
    fn the_cache_key_ignores_the_name_and_follows_what_sets_the_classes() {
        let spec = |name: &str, t: f64| {
            salient_grid::spec::parse(
                &format!(
                    r#"{{"name": "{name}", "system": {{"kind": "henon-heiles", "energy": 0.125}},
                        "grid": {{"cells": [10, 10], "mode": "full"}},
                        "sweep": {{"method": ["taylor"], "tau": [0.5], "t_final": [{t}], "delta": [1e-8]}}}}"#
                ),
                true,
            )
            .unwrap()
        };
        assert_eq!(cache_key(&spec("a", 100.0)), cache_key(&spec("b", 100.0)));
        assert_ne!(cache_key(&spec("a", 100.0)), cache_key(&spec("a", 200.0)));
        let reference = reference_spec(&spec("a", 100.0), 0.125, 100.0, 0.5).unwrap();
        assert_eq!(reference.mode(0), Mode::Full);
        assert_eq!(reference.runs.len(), 1);
        assert_eq!(reference.runs[0].delta, Some(REFERENCE_DELTA));
    }
}
