//! Job specs (TOML, or JSON with the same schema): parsed strictly, validated up front, every
//! problem reported as one line naming the field by its table path and the allowed range.
//!
//! Both syntaxes are first read into a `serde_json::Value` (TOML's `nan`/`inf` kept as a marker
//! so they are reported as non-finite, not as a type error), then walked field by field with the
//! path in hand. A derived `Deserialize` would only say "invalid type: string, expected f64"
//! without saying where in a JSON document; walking by hand names `grid.cells[1]`.

use crate::executor::CellRun;
use crate::geometry::{Grid, ScanOrder};
use crate::surface::{Coordinate, SectionSpec, Surface, SystemSpec};
use salient_core::adaptive::driver::Protocol;
use salient_core::orbit::{Deviation, OrbitConfig, Thresholds};
use salient_core::run::{MethodRun, GRID_DOFS};
use salient_core::systems::polynomial::named::fpu_beta;
use salient_core::Method;
use serde::Serialize;
use serde_json::{Map, Value};
use std::fmt;
use std::sync::Arc;

/// Largest grid a spec may ask for unless the caller sets another cap.
pub const MAX_CELLS: usize = 16_000_000;
/// Largest number of steps τ in one run.
const MAX_STEPS: f64 = 1e12;
/// Cells per axis.
const MAX_AXIS: usize = 4000;
/// Characters of a job name: it names the output folder and shows in every status table.
pub const MAX_NAME_CHARS: usize = 128;
/// Runs (members of the sweep) in one job.
pub const MAX_RUNS: usize = 1024;
/// Cells per tile along each axis when the spec gives none (clipped to the cells).
const DEFAULT_TILE: usize = 20;

/// The spec's schema: each table ("" for the top level) with the keys it may hold, in the order
/// error messages list them. The parser takes its allowed keys from here and refuses any other,
/// so this is the one list of what a spec can say; `docs/spec.md` documents every key in it (a
/// test holds the two equal).
pub const SCHEMA: &[(&str, &[&str])] = &[
    (
        "",
        &[
            "name",
            "system",
            "section",
            "grid",
            "sweep",
            "integration",
            "classify",
        ],
    ),
    ("system", &["kind", "energy", "dof", "potential", "beta"]),
    ("section", &["plane", "axes", "fixed"]),
    ("section.fixed", &COORDINATES),
    (
        "grid",
        &[
            "cells",
            "tile",
            "mode",
            "q1",
            "q2",
            "q3",
            "p1",
            "p2",
            "p3",
            "order",
            "order_seed",
        ],
    ),
    (
        "sweep",
        &["method", "tau", "t_final", "delta", "energy", "mode"],
    ),
    (
        "integration",
        &["protocol", "deviation", "seed", "indicators"],
    ),
    (
        "classify",
        &["regular", "chaotic", "early_stop", "energy_drift"],
    ),
];

/// The coordinates a grid's section can name (grids run in up to 3 degrees of freedom).
const COORDINATES: [&str; 6] = ["q1", "q2", "q3", "p1", "p2", "p3"];

/// The keys [`SCHEMA`] allows in the table at `path` (none for a table it does not name).
fn allowed_keys(path: &str) -> &'static [&'static str] {
    SCHEMA
        .iter()
        .find(|(table, _)| *table == path)
        .map_or(&[], |(_, keys)| keys)
}

pub use crate::ledger::Mode;

/// The section grid of a job, before a run's energy decides its default bounds. q2 and p2
/// name the section's first and second axis (Hénon–Heiles' q2 and p2).
#[derive(Clone, Debug, PartialEq)]
pub struct GridSpec {
    /// Cells along the first axis.
    pub n_q2: usize,
    /// Cells along the second axis.
    pub n_p2: usize,
    /// Cells per tile along the first axis.
    pub tile_q2: usize,
    /// Cells per tile along the second axis.
    pub tile_p2: usize,
    /// The bounds the spec gives, or `None`: Hénon–Heiles' allowed region at each run's energy
    /// ([`default_bounds`]; a polynomial system's bounds are required).
    pub q2_range: Option<(f64, f64)>,
    /// Like `q2_range`, for the second axis.
    pub p2_range: Option<(f64, f64)>,
    /// The canonical order fast PSS walks the cells in.
    pub order: ScanOrder,
}

/// One member of the sweep (the Cartesian product method × tau × t_final × delta; delta only
/// varies for adaptive methods: `tm-*` methods get `None` and appear once per (tau, t_final)).
#[derive(Clone, Debug, PartialEq)]
pub struct RunSpec {
    /// The energy H of the run's section (`system.energy`, or one of `sweep.energy`).
    pub energy: f64,
    /// Fast PSS or every cell integrated (`grid.mode`, or one of `sweep.mode`).
    pub mode: Mode,
    /// The integration method (`sweep.method`).
    pub method: Method,
    /// Renormalisation interval τ (`sweep.tau`).
    pub tau: f64,
    /// Time to integrate to (`sweep.t_final`).
    pub t_final: f64,
    /// The tolerance of an adaptive method, as honoured (None for tangent-map methods).
    pub delta: Option<f64>,
}

/// A parsed and checked job spec.
#[derive(Clone, Debug, PartialEq)]
pub struct JobSpec {
    /// The job's name (`name`, default `salient`): it names the output folder.
    pub name: String,
    /// The system and its surface of section (`[system]`, `[section]`).
    pub surface: Arc<Surface>,
    /// The section grid.
    pub grid: GridSpec,
    /// The sweep's members, one run each.
    pub runs: Vec<RunSpec>,
    /// How adaptive methods meet the renormalisation times.
    pub protocol: Protocol,
    /// How the initial deviation vectors are chosen.
    pub deviation: Deviation,
    /// Classification thresholds and the early stop.
    pub thresholds: Thresholds,
    /// The finite-time mLE, MEGNO and FLI of every cell of the full-mode runs
    /// (`integration.indicators`); their orbits run to t_final (no early stop).
    pub indicators: bool,
    /// Things the user should know but that do not stop the job (a clamped delta, an ignored
    /// field), one line each.
    pub warnings: Vec<String>,
    /// The spec as parsed (absent optional fields as null), for run.json.
    pub source: serde_json::Value,
}

/// Checkpoints per decade of t at which full-mode orbits are also classified (Fig. 7).
pub const CHECKPOINTS_PER_DECADE: u32 = 4;

impl JobSpec {
    /// The section grid run `index` covers: the spec's cells at the run's energy, within the
    /// spec's bounds or the allowed region at that energy.
    pub fn grid(&self, index: usize) -> Grid {
        let g = &self.grid;
        let energy = self.runs[index].energy;
        let (dq, dp) = default_bounds(energy);
        Grid::on_surface(
            Arc::clone(&self.surface),
            energy,
            [g.n_q2, g.n_p2],
            [g.q2_range.unwrap_or(dq), g.p2_range.unwrap_or(dp)],
            (g.tile_q2, g.tile_p2),
            g.order,
        )
    }

    /// Whether the sweep covers several energies (run folders and tables then name the energy).
    pub fn sweeps_energy(&self) -> bool {
        self.runs.windows(2).any(|w| w[0].energy != w[1].energy)
    }

    /// Run `index`'s mode.
    pub fn mode(&self, index: usize) -> Mode {
        self.runs[index].mode
    }

    /// Whether the sweep runs both modes (run folders and tables then name the mode).
    pub fn sweeps_mode(&self) -> bool {
        self.runs.windows(2).any(|w| w[0].mode != w[1].mode)
    }

    /// How every cell's orbit of run `index` is integrated.
    pub fn cell_run(&self, index: usize) -> CellRun {
        let r = &self.runs[index];
        let indicators = self.indicators && r.mode == Mode::Full;
        CellRun {
            run: MethodRun {
                method: r.method.clone(),
                delta: r.delta,
                protocol: self.protocol,
            },
            config: OrbitConfig {
                tau: r.tau,
                t_final: r.t_final,
                thresholds: Thresholds {
                    // Indicators are read at t_final.
                    early_stop: self.thresholds.early_stop && !indicators,
                    ..self.thresholds
                },
                deviation: self.deviation,
                escape_radius: None,
            },
            checkpoints_per_decade: match r.mode {
                Mode::Full => CHECKPOINTS_PER_DECADE,
                Mode::FastPss => 0,
            },
            indicators,
        }
    }
}

/// The spec as read, before validation; every number in it is finite.
#[derive(Serialize)]
struct RawSpec {
    name: Option<String>,
    system: RawSystem,
    section: Option<RawSection>,
    grid: RawGrid,
    sweep: RawSweep,
    integration: Option<RawIntegration>,
    classify: Option<RawClassify>,
}

#[derive(Serialize)]
struct RawSystem {
    kind: String,
    energy: Option<f64>,
    dof: Option<i128>,
    potential: Option<String>,
    beta: Option<f64>,
}

#[derive(Serialize)]
struct RawSection {
    plane: Option<String>,
    axes: Option<Vec<String>>,
    /// The fixed coordinates in the order given.
    fixed: Option<Map<String, Value>>,
}

#[derive(Serialize)]
struct RawGrid {
    cells: Vec<i128>,
    tile: Option<Vec<i128>>,
    mode: Option<String>,
    q1: Option<Vec<f64>>,
    q2: Option<Vec<f64>>,
    q3: Option<Vec<f64>>,
    p1: Option<Vec<f64>>,
    p2: Option<Vec<f64>>,
    p3: Option<Vec<f64>>,
    order: Option<String>,
    order_seed: Option<u64>,
}

#[derive(Serialize)]
struct RawSweep {
    method: Vec<String>,
    tau: Vec<f64>,
    t_final: Vec<f64>,
    delta: Option<Vec<f64>>,
    energy: Option<Vec<f64>>,
    mode: Option<Vec<String>>,
}

#[derive(Serialize)]
struct RawIntegration {
    protocol: Option<String>,
    deviation: Option<String>,
    seed: Option<u64>,
    indicators: Option<bool>,
}

#[derive(Serialize)]
struct RawClassify {
    regular: Option<f64>,
    chaotic: Option<f64>,
    early_stop: Option<bool>,
    energy_drift: Option<f64>,
}

/// A spec that cannot run: one line naming the field and the allowed range.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SpecError(pub String);

impl fmt::Display for SpecError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for SpecError {}

/// The result of parsing or checking a spec.
pub type SpecResult<T> = Result<T, SpecError>;

/// A usage error, forced onto one line whatever the user's strings held.
fn usage(msg: impl Into<String>) -> SpecError {
    let msg: String = msg.into();
    SpecError(msg.replace('\r', "\\r").replace('\n', "\\n"))
}

fn first_line(s: &str) -> &str {
    s.lines().next().unwrap_or("")
}

/// Whether a spec's text is JSON: its file name ends in `.json` or it starts with `{` (after
/// whitespace); TOML otherwise.
pub fn is_json(file_name: &str, text: &str) -> bool {
    file_name.ends_with(".json") || text.trim_start().starts_with('{')
}

/// Parses and validates a spec's text (`json`: the JSON form, else TOML).
pub fn parse(text: &str, json: bool) -> SpecResult<JobSpec> {
    parse_capped(text, json, MAX_CELLS)
}

/// [`parse`] with a cap on the grid's cells in all (`--max-cells`).
pub fn parse_capped(text: &str, json: bool, max_cells: usize) -> SpecResult<JobSpec> {
    let value = if json {
        serde_json::from_str::<Value>(text).map_err(|e| {
            usage(format!(
                "spec is not valid JSON: {}",
                first_line(&e.to_string())
            ))
        })?
    } else {
        let table = text.parse::<toml::Table>().map_err(|e| {
            let msg = first_line(e.message());
            match e.span() {
                Some(span) => {
                    let (line, content) = line_at(text, span.start);
                    usage(format!("spec line {line} (`{content}`): {msg}"))
                }
                None => usage(format!("spec is not valid TOML: {msg}")),
            }
        })?;
        toml_to_json(toml::Value::Table(table))
    };
    validate(read_raw(&value)?, max_cells)
}

/// The number and trimmed text of the line holding byte offset `at`.
fn line_at(text: &str, at: usize) -> (usize, &str) {
    let mut at = at.min(text.len());
    while !text.is_char_boundary(at) {
        at -= 1;
    }
    let start = text[..at].rfind('\n').map_or(0, |i| i + 1);
    let end = text[start..].find('\n').map_or(text.len(), |i| start + i);
    (
        text[..start].matches('\n').count() + 1,
        text[start..end].trim(),
    )
}

/// Prefix of the string that stands in for a non-finite TOML float (`nan`, `inf`) in the JSON
/// value, so the reader can say "must be a finite number (got NaN)" at the right path.
const NON_FINITE: &str = "\u{0}non-finite\u{0}";

fn toml_to_json(v: toml::Value) -> Value {
    match v {
        toml::Value::String(s) => Value::String(s),
        toml::Value::Integer(i) => Value::from(i),
        toml::Value::Float(f) => serde_json::Number::from_f64(f)
            .map(Value::Number)
            .unwrap_or_else(|| Value::String(format!("{NON_FINITE}{f}"))),
        toml::Value::Boolean(b) => Value::Bool(b),
        toml::Value::Datetime(d) => Value::String(d.to_string()),
        toml::Value::Array(a) => Value::Array(a.into_iter().map(toml_to_json).collect()),
        toml::Value::Table(t) => {
            Value::Object(t.into_iter().map(|(k, v)| (k, toml_to_json(v))).collect())
        }
    }
}

/// "1 value", "3 values".
fn count(n: usize) -> String {
    if n == 1 {
        "1 value".into()
    } else {
        format!("{n} values")
    }
}

/// A value as the user wrote it, for "(got ...)".
fn describe(v: &Value) -> String {
    match v {
        Value::Null => "null".into(),
        Value::Bool(b) => b.to_string(),
        Value::Number(n) => n.to_string(),
        Value::String(s) => match s.strip_prefix(NON_FINITE) {
            Some(f) => f.to_string(),
            None => format!("{s:?}"),
        },
        Value::Array(a) => format!("a list of {}", count(a.len())),
        Value::Object(_) => "a table".into(),
    }
}

type Read<T> = fn(&Value, &str) -> SpecResult<T>;

fn number(v: &Value, path: &str) -> SpecResult<f64> {
    match v {
        Value::Number(n) => match n.as_f64() {
            Some(x) if x.is_finite() => Ok(x),
            _ => Err(usage(format!("{path} must be a finite number (got {n})"))),
        },
        Value::String(s) if s.starts_with(NON_FINITE) => Err(usage(format!(
            "{path} must be a finite number (got {})",
            describe(v)
        ))),
        _ => Err(usage(format!(
            "{path} must be a number (got {})",
            describe(v)
        ))),
    }
}

fn integer(v: &Value, path: &str) -> SpecResult<i128> {
    let n = match v {
        Value::Number(n) => n.as_i64().map(i128::from).or(n.as_u64().map(i128::from)),
        _ => None,
    };
    n.ok_or_else(|| usage(format!("{path} must be an integer (got {})", describe(v))))
}

fn seed(v: &Value, path: &str) -> SpecResult<u64> {
    v.as_u64().ok_or_else(|| {
        usage(format!(
            "{path} must be an integer in 0..={} (got {})",
            u64::MAX,
            describe(v)
        ))
    })
}

fn string(v: &Value, path: &str) -> SpecResult<String> {
    match v {
        Value::String(s) if !s.starts_with(NON_FINITE) => Ok(s.clone()),
        _ => Err(usage(format!(
            "{path} must be a string (got {})",
            describe(v)
        ))),
    }
}

fn boolean(v: &Value, path: &str) -> SpecResult<bool> {
    v.as_bool().ok_or_else(|| {
        usage(format!(
            "{path} must be true or false (got {})",
            describe(v)
        ))
    })
}

fn list<T>(v: &Value, path: &str, read: Read<T>) -> SpecResult<Vec<T>> {
    let Value::Array(items) = v else {
        return Err(usage(format!(
            "{path} must be a list (got {})",
            describe(v)
        )));
    };
    items
        .iter()
        .enumerate()
        .map(|(k, x)| read(x, &format!("{path}[{k}]")))
        .collect()
}

/// One table of the spec, with its path ("" for the top level).
struct Table<'a> {
    path: String,
    obj: &'a Map<String, Value>,
}

impl<'a> Table<'a> {
    /// `v` as the table at `path`, refusing any key [`SCHEMA`] does not allow there.
    fn new(v: &'a Value, path: &str) -> SpecResult<Table<'a>> {
        let allowed = allowed_keys(path);
        let Value::Object(obj) = v else {
            return Err(usage(if path.is_empty() {
                format!("the spec must be a table of sections (got {})", describe(v))
            } else {
                format!("[{path}] must be a table (got {})", describe(v))
            }));
        };
        if let Some(k) = obj.keys().find(|k| !allowed.contains(&k.as_str())) {
            let place = if path.is_empty() {
                "at the top level".to_string()
            } else {
                format!("in [{path}]")
            };
            return Err(usage(format!(
                "unknown field '{k}' {place} (allowed: {})",
                allowed.join(", ")
            )));
        }
        Ok(Table {
            path: path.to_string(),
            obj,
        })
    }

    fn path(&self, key: &str) -> String {
        if self.path.is_empty() {
            key.to_string()
        } else {
            format!("{}.{key}", self.path)
        }
    }

    /// The value at `key`; absent and null are the same.
    fn get(&self, key: &str) -> Option<&'a Value> {
        self.obj.get(key).filter(|v| !v.is_null())
    }

    fn opt<T>(&self, key: &str, read: Read<T>) -> SpecResult<Option<T>> {
        self.get(key).map(|v| read(v, &self.path(key))).transpose()
    }

    fn req<T>(&self, key: &str, read: Read<T>) -> SpecResult<T> {
        let path = self.path(key);
        let v = self
            .get(key)
            .ok_or_else(|| usage(format!("{path} is required")))?;
        read(v, &path)
    }

    fn opt_list<T>(&self, key: &str, read: Read<T>) -> SpecResult<Option<Vec<T>>> {
        self.get(key)
            .map(|v| list(v, &self.path(key), read))
            .transpose()
    }

    fn req_list<T>(&self, key: &str, read: Read<T>) -> SpecResult<Vec<T>> {
        let path = self.path(key);
        let v = self
            .get(key)
            .ok_or_else(|| usage(format!("{path} is required")))?;
        list(v, &path, read)
    }

    fn opt_table(&self, key: &str) -> SpecResult<Option<Table<'a>>> {
        self.get(key)
            .map(|v| Table::new(v, &self.path(key)))
            .transpose()
    }

    fn req_table(&self, key: &str) -> SpecResult<Table<'a>> {
        self.opt_table(key)?
            .ok_or_else(|| usage(format!("the [{}] table is required", self.path(key))))
    }
}

/// Reads the spec's fields with their types; no ranges yet.
fn read_raw(v: &Value) -> SpecResult<RawSpec> {
    let top = Table::new(v, "")?;
    let system = top.req_table("system")?;
    let section = top.opt_table("section")?;
    let grid = top.req_table("grid")?;
    let sweep = top.req_table("sweep")?;
    let integration = top.opt_table("integration")?;
    let classify = top.opt_table("classify")?;
    Ok(RawSpec {
        name: top.opt("name", string)?,
        system: RawSystem {
            kind: system.req("kind", string)?,
            energy: system.opt("energy", number)?,
            dof: system.opt("dof", integer)?,
            potential: system.opt("potential", string)?,
            beta: system.opt("beta", number)?,
        },
        section: match section {
            Some(t) => Some(RawSection {
                plane: t.opt("plane", string)?,
                axes: t.opt_list("axes", string)?,
                fixed: match t.opt_table("fixed")? {
                    Some(f) => {
                        for (k, v) in f.obj {
                            number(v, &f.path(k))?;
                        }
                        Some(f.obj.clone())
                    }
                    None => None,
                },
            }),
            None => None,
        },
        grid: RawGrid {
            cells: grid.req_list("cells", integer)?,
            tile: grid.opt_list("tile", integer)?,
            mode: grid.opt("mode", string)?,
            q1: grid.opt_list("q1", number)?,
            q2: grid.opt_list("q2", number)?,
            q3: grid.opt_list("q3", number)?,
            p1: grid.opt_list("p1", number)?,
            p2: grid.opt_list("p2", number)?,
            p3: grid.opt_list("p3", number)?,
            order: grid.opt("order", string)?,
            order_seed: grid.opt("order_seed", seed)?,
        },
        sweep: RawSweep {
            method: sweep.req_list("method", string)?,
            tau: sweep.req_list("tau", number)?,
            t_final: sweep.req_list("t_final", number)?,
            delta: sweep.opt_list("delta", number)?,
            energy: sweep.opt_list("energy", number)?,
            mode: sweep.opt_list("mode", string)?,
        },
        integration: match integration {
            Some(t) => Some(RawIntegration {
                protocol: t.opt("protocol", string)?,
                deviation: t.opt("deviation", string)?,
                seed: t.opt("seed", seed)?,
                indicators: t.opt("indicators", boolean)?,
            }),
            None => None,
        },
        classify: match classify {
            Some(t) => Some(RawClassify {
                regular: t.opt("regular", number)?,
                chaotic: t.opt("chaotic", number)?,
                early_stop: t.opt("early_stop", boolean)?,
                energy_drift: t.opt("energy_drift", number)?,
            }),
            None => None,
        },
    })
}

fn finite_positive(field: &str, v: f64) -> SpecResult<f64> {
    if v.is_finite() && v > 0.0 {
        Ok(v)
    } else {
        Err(usage(format!(
            "{field} must be a finite number > 0 (got {v})"
        )))
    }
}

/// Two integers, the k-th in 1..=max[k].
fn pair_usize(field: &str, v: &[i128], max: [usize; 2]) -> SpecResult<[usize; 2]> {
    if v.len() != 2 {
        return Err(usage(format!(
            "{field} must be a list of two integers (got {})",
            count(v.len())
        )));
    }
    let mut out = [0usize; 2];
    for k in 0..2 {
        if v[k] < 1 || v[k] > max[k] as i128 {
            return Err(usage(format!(
                "{field}[{k}] must be in 1..={} (got {})",
                max[k], v[k]
            )));
        }
        out[k] = v[k] as usize;
    }
    Ok(out)
}

/// A `[lo, hi]` override of the section bounds, which must lie within the allowed region.
fn range(
    field: &str,
    v: &Option<Vec<f64>>,
    allowed: (f64, f64),
    energy: f64,
) -> SpecResult<(f64, f64)> {
    let Some(v) = v else { return Ok(allowed) };
    if v.len() != 2 {
        return Err(usage(format!(
            "{field} must be a list of two numbers [lo, hi] (got {})",
            count(v.len())
        )));
    }
    let (lo, hi) = (v[0], v[1]);
    if lo >= hi {
        return Err(usage(format!(
            "{field} must have lo < hi (got [{lo}, {hi}])"
        )));
    }
    // The bounds are roots computed in floating point; allow a few ulps for a user who types
    // them from the design notes.
    let tol = 1e-12;
    if lo < allowed.0 - tol || hi > allowed.1 + tol {
        return Err(usage(format!(
            "{field} must lie within [{}, {}] at energy {energy} (got [{lo}, {hi}])",
            allowed.0, allowed.1
        )));
    }
    Ok((lo, hi))
}

/// Largest Hénon–Heiles energy a spec may ask for: six times the escape energy, where most orbits
/// leave within a few crossings.
const MAX_ENERGY: f64 = 1.0;

/// Default section bounds of Hénon–Heiles at energy H: q2 between the two real roots of
/// q2² − (2/3) q2³ = 2H that bracket 0, p2 in [−√(2H), √(2H)]. Above the escape energy 1/6
/// the region opens through the saddle at q2 = 1 and has no right root; the bounded part
/// below the saddle, q2 ≤ 1, is used (where |p2| ≤ √(2H) still holds).
pub fn default_bounds(energy: f64) -> ((f64, f64), (f64, f64)) {
    let f = |q: f64| q * q - 2.0 * q * q * q / 3.0 - 2.0 * energy;
    // f(0) = −2H < 0; f(1) = 1/3 − 2H > 0 and f(−2) = 4 + 16/3 − 2H > 0, so bisection between 0
    // and each of them converges to the roots that bracket 0.
    let bisect = |mut neg: f64, mut pos: f64| {
        for _ in 0..200 {
            let mid = 0.5 * (neg + pos);
            if mid == neg || mid == pos {
                break;
            }
            if f(mid) < 0.0 {
                neg = mid;
            } else {
                pos = mid;
            }
        }
        0.5 * (neg + pos)
    };
    let p = (2.0 * energy).sqrt();
    let upper = if f(1.0) > 0.0 { bisect(0.0, 1.0) } else { 1.0 };
    ((bisect(0.0, -2.0), upper), (-p, p))
}

/// A job name names a folder of its own: 1 to [`MAX_NAME_CHARS`] characters, ASCII letters,
/// digits, `-`, `_`, `.` and `+`, not starting with `.` (so never `.` or `..`, nor hidden) or
/// `-` (never read as an option).
fn check_name(name: &str) -> SpecResult<()> {
    let allowed = |c: char| c.is_ascii_alphanumeric() || "-_.+".contains(c);
    let ok = (1..=MAX_NAME_CHARS).contains(&name.chars().count())
        && name.chars().all(allowed)
        && !name.starts_with(['.', '-']);
    if ok {
        return Ok(());
    }
    // The name as given, cut short: it may be megabytes.
    let shown: String = name.chars().take(40).collect();
    let more = if name.chars().count() > 40 { "…" } else { "" };
    Err(usage(format!(
        "name must be 1 to {MAX_NAME_CHARS} characters from A-Z a-z 0-9 - _ . + (a folder is \
         named after it), not starting with . or - (got {shown:?}{more}, {} characters)",
        name.chars().count()
    )))
}

/// The modes of the sweep: `grid.mode`, or the list `sweep.mode` (one or the other; fast PSS
/// when neither is given).
fn modes_of(raw: &RawSpec) -> SpecResult<Vec<Mode>> {
    let parse = |field: String, name: &str| match name {
        "fast-pss" => Ok(Mode::FastPss),
        "full" => Ok(Mode::Full),
        other => Err(usage(format!(
            "{field} must be \"fast-pss\" or \"full\" (got {other:?})"
        ))),
    };
    match (&raw.grid.mode, &raw.sweep.mode) {
        (Some(m), None) => Ok(vec![parse("grid.mode".into(), m)?]),
        (None, None) => Ok(vec![Mode::FastPss]),
        (None, Some(list)) if list.is_empty() => {
            Err(usage("sweep.mode must list at least one value"))
        }
        (None, Some(list)) => {
            let modes = list
                .iter()
                .enumerate()
                .map(|(k, m)| parse(format!("sweep.mode[{k}]"), m))
                .collect::<SpecResult<Vec<_>>>()?;
            if (1..modes.len()).any(|k| modes[..k].contains(&modes[k])) {
                return Err(usage("sweep.mode must not list a mode twice"));
            }
            Ok(modes)
        }
        (Some(_), Some(_)) => Err(usage(
            "grid.mode and sweep.mode both give the mode: keep one (sweep.mode to sweep it)",
        )),
    }
}

/// The energies of the sweep: `system.energy`, or the list `sweep.energy` (one or the other).
/// Hénon–Heiles' energies lie in (0, [`MAX_ENERGY`]]; a polynomial system's may be any finite
/// number (its grid must still meet the section, see [`every_grid_meets_the_section`]).
fn energies(raw: &RawSpec, system: &SystemSpec) -> SpecResult<Vec<f64>> {
    let bounded = *system == SystemSpec::HenonHeiles;
    let check = |field: String, energy: f64| {
        if !bounded || (energy > 0.0 && energy <= MAX_ENERGY) {
            Ok(energy)
        } else {
            Err(usage(format!(
                "{field} must be in (0, {MAX_ENERGY}] (got {energy}; above the escape energy 1/6 orbits may escape)"
            )))
        }
    };
    match (raw.system.energy, &raw.sweep.energy) {
        (Some(e), None) => Ok(vec![check("system.energy".into(), e)?]),
        (None, Some(list)) if list.is_empty() => {
            Err(usage("sweep.energy must list at least one value"))
        }
        (None, Some(list)) => list
            .iter()
            .enumerate()
            .map(|(k, &e)| check(format!("sweep.energy[{k}]"), e))
            .collect(),
        (Some(_), Some(_)) => Err(usage(
            "system.energy and sweep.energy both give the energy: keep one (sweep.energy to sweep it)",
        )),
        (None, None) => Err(usage(
            "system.energy is required (or sweep.energy, a list of energies to sweep)",
        )),
    }
}

/// The system and section of the spec (`[system]`, `[section]`), compiled.
fn surface_of(raw: &RawSpec) -> SpecResult<Arc<Surface>> {
    let sys = &raw.system;
    // Which of dof, potential and beta each kind takes.
    let takes: &[&str] = match sys.kind.as_str() {
        "henon-heiles" => &[],
        "polynomial" => &["dof", "potential"],
        "fpu-beta" => &["dof", "beta"],
        other => {
            return Err(usage(format!(
            "system.kind must be \"henon-heiles\", \"polynomial\" or \"fpu-beta\" (got {other:?})"
        )))
        }
    };
    for (field, given) in [
        ("dof", sys.dof.is_some()),
        ("potential", sys.potential.is_some()),
        ("beta", sys.beta.is_some()),
    ] {
        if given && !takes.contains(&field) {
            return Err(usage(format!(
                "system.{field} is not a key of kind = {:?} (it takes {})",
                sys.kind,
                if takes.is_empty() {
                    "only energy".to_string()
                } else {
                    takes.join(" and ")
                }
            )));
        }
    }
    let dof = || {
        match sys.dof {
        Some(d) if GRID_DOFS.iter().any(|&n| n as i128 == d) => Ok(d as usize),
        Some(d) => Err(usage(format!(
            "system.dof must be 2 or 3 for a grid (got {d}; longer chains run as single orbits: salient orbit --potential … --dof N)"
        ))),
        None => Err(usage(format!(
            "system.dof is required with kind = {:?} (2 or 3)",
            sys.kind
        ))),
    }
    };
    let system = match sys.kind.as_str() {
        "polynomial" => {
            let dof = dof()?;
            let potential = sys.potential.clone().ok_or_else(|| {
                usage("system.potential is required with kind = \"polynomial\" (a polynomial in q1…qN, e.g. \"(q1^2 + q2^2)/2 + q1^2*q2 - q2^3/3\")")
            })?;
            SystemSpec::Polynomial { dof, potential }
        }
        "fpu-beta" => {
            let dof = dof()?;
            let beta = sys.beta.ok_or_else(|| {
                usage("system.beta is required with kind = \"fpu-beta\" (the quartic coupling, e.g. 1.5)")
            })?;
            SystemSpec::Polynomial {
                dof,
                potential: fpu_beta(dof, beta),
            }
        }
        _ => SystemSpec::HenonHeiles,
    };
    let section = section_of(raw.section.as_ref(), system.dof())?;
    if system == SystemSpec::HenonHeiles && section != SectionSpec::henon_heiles() {
        return Err(usage(
            "section: the henon-heiles system runs on q1 = 0 with axes q2, p2 (write it as kind = \"polynomial\" for another section)",
        ));
    }
    Surface::new(system, section).map_err(|e| match e.at {
        Some(at) => {
            let text = raw.system.potential.as_deref().unwrap_or_default();
            let shown: String = text.chars().take(80).collect();
            usage(format!(
                "system.potential is not a polynomial: {} at character {} of {shown:?}",
                e.message,
                at + 1
            ))
        }
        None => usage(format!("system: {}", e.message)),
    })
}

/// The section of `[section]` in `dof` degrees of freedom: the plane (default q1), the axes
/// (default the first other position and its momentum) and the fixed coordinates (every one
/// left, each given once).
fn section_of(raw: Option<&RawSection>, dof: usize) -> SpecResult<SectionSpec> {
    let names: Vec<String> = (1..=dof)
        .flat_map(|k| [format!("q{k}"), format!("p{k}")])
        .collect();
    let coordinate = |field: &str, name: &str| {
        Coordinate::parse(name, dof).ok_or_else(|| {
            usage(format!(
                "{field} must be one of {} (got {name:?})",
                names.join(", ")
            ))
        })
    };
    let plane = match raw.and_then(|r| r.plane.as_deref()) {
        None => 0,
        Some(name) => match coordinate("section.plane", name)? {
            Coordinate::Q(k) => k,
            Coordinate::P(_) => {
                return Err(usage(format!(
                    "section.plane must be a position q1…q{dof} (the section is q_k = 0 with p_k > 0; got {name:?})"
                )))
            }
        },
    };
    let in_plane = |c: Coordinate| c.index() == plane;
    let first_other = if plane == 0 { 1 } else { 0 };
    let axes = match raw.and_then(|r| r.axes.as_ref()) {
        None => [Coordinate::Q(first_other), Coordinate::P(first_other)],
        Some(list) if list.len() != 2 => {
            return Err(usage(format!(
                "section.axes must be a list of two coordinates (got {})",
                count(list.len())
            )))
        }
        Some(list) => {
            let a = coordinate("section.axes[0]", &list[0])?;
            let b = coordinate("section.axes[1]", &list[1])?;
            if in_plane(a) || in_plane(b) || a == b {
                return Err(usage(format!(
                    "section.axes must be two different coordinates other than q{0} and p{0} (the plane's; got {list:?})",
                    plane + 1
                )));
            }
            [a, b]
        }
    };
    if dof == 2 && axes != [Coordinate::Q(first_other), Coordinate::P(first_other)] {
        return Err(usage(format!(
            "section.axes must be [\"q{0}\", \"p{0}\"] in 2 degrees of freedom",
            first_other + 1
        )));
    }
    let left: Vec<Coordinate> = (0..dof)
        .filter(|&k| k != plane)
        .flat_map(|k| [Coordinate::Q(k), Coordinate::P(k)])
        .filter(|c| !axes.contains(c))
        .collect();
    let mut fixed = Vec::new();
    if let Some(given) = raw.and_then(|r| r.fixed.as_ref()) {
        for (name, v) in given {
            let c = coordinate("section.fixed", name)?;
            if !left.contains(&c) {
                return Err(usage(format!(
                    "section.fixed.{name} is not free to fix: the plane's pair and the axes are not fixed (fix {})",
                    list_names(&left)
                )));
            }
            fixed.push((c, v.as_f64().expect("read as a finite number")));
        }
    }
    let missing: Vec<Coordinate> = left
        .iter()
        .copied()
        .filter(|c| !fixed.iter().any(|(f, _)| f == c))
        .collect();
    if !missing.is_empty() {
        return Err(usage(format!(
            "section.fixed must give {} (every coordinate that is neither the plane's nor an axis)",
            list_names(&missing)
        )));
    }
    Ok(SectionSpec { plane, axes, fixed })
}

/// "q3, p3".
fn list_names(coords: &[Coordinate]) -> String {
    let names: Vec<String> = coords.iter().map(|c| c.name()).collect();
    names.join(", ")
}

/// The grid's bounds along the section's axes. Hénon–Heiles: `grid.q2`/`grid.p2`, each
/// optional and within the allowed region at every energy. A polynomial system: one key per
/// axis, named after it, required. A key for a coordinate that is no axis is refused.
#[allow(clippy::type_complexity)]
fn bounds_of(
    g: &RawGrid,
    surface: &Surface,
    energies: &[f64],
) -> SpecResult<(Option<(f64, f64)>, Option<(f64, f64)>)> {
    let given = [
        ("q1", &g.q1),
        ("q2", &g.q2),
        ("q3", &g.q3),
        ("p1", &g.p1),
        ("p2", &g.p2),
        ("p3", &g.p3),
    ];
    let axes = surface.section().axis_names();
    if let Some((name, _)) = given
        .iter()
        .find(|(name, v)| v.is_some() && !axes.iter().any(|a| a == name))
    {
        return Err(usage(format!(
            "grid.{name} bounds no axis (the section's axes are {}, {})",
            axes[0], axes[1]
        )));
    }
    let bound = |axis: &str| given.iter().find(|(n, _)| *n == axis).map(|(_, v)| *v);
    let [a, b] = [bound(&axes[0]), bound(&axes[1])].map(|v| v.expect("an axis has a key"));
    if *surface.system() != SystemSpec::HenonHeiles {
        let any = (f64::NEG_INFINITY, f64::INFINITY);
        let read = |axis: &str, v: &Option<Vec<f64>>| {
            match v {
            Some(_) => range(&format!("grid.{axis}"), v, any, 0.0).map(Some),
            None => Err(usage(format!(
                "grid.{axis} is required for a polynomial system: [lo, hi] along the section's axis {axis} (cells whose centre lies outside the allowed region are skipped)"
            ))),
        }
        };
        return Ok((read(&axes[0], a)?, read(&axes[1], b)?));
    }
    // Bounds the spec gives must lie in the allowed region at every energy of the sweep.
    let (mut q2_range, mut p2_range) = (None, None);
    for &energy in energies {
        let (dq, dp) = default_bounds(energy);
        if a.is_some() {
            q2_range = Some(range("grid.q2", a, dq, energy)?);
        }
        if b.is_some() {
            p2_range = Some(range("grid.p2", b, dp, energy)?);
        }
    }
    Ok((q2_range, p2_range))
}

/// A polynomial system's grid must hold a cell on the section at every energy of the sweep.
fn every_grid_meets_the_section(job: &JobSpec) -> SpecResult<()> {
    let mut seen = Vec::new();
    for (index, run) in job.runs.iter().enumerate() {
        if seen.contains(&run.energy.to_bits()) {
            continue;
        }
        seen.push(run.energy.to_bits());
        if job.grid(index).compatible_count() == 0 {
            let axes = job.surface.section().axis_names();
            return Err(usage(format!(
                "grid: no cell's centre lies on the section at energy {} (the plane's momentum² ≤ 0 at every centre): widen grid.{} / grid.{}, or check system.energy and section.fixed",
                run.energy, axes[0], axes[1]
            )));
        }
    }
    Ok(())
}

fn validate(raw: RawSpec, max_cells: usize) -> SpecResult<JobSpec> {
    let source = serde_json::to_value(&raw).expect("a read spec holds only finite numbers");
    let mut warnings = Vec::new();

    let name = raw.name.clone().unwrap_or_else(|| "salient".into());
    check_name(&name)?;
    let surface = surface_of(&raw)?;
    let energies = energies(&raw, surface.system())?;

    let g = &raw.grid;
    let [n_q2, n_p2] = pair_usize("grid.cells", &g.cells, [MAX_AXIS, MAX_AXIS])?;
    if n_q2 * n_p2 > max_cells {
        return Err(usage(format!(
            "grid.cells must hold at most {max_cells} cells in all (got {n_q2} × {n_p2} = {}; the cap is --max-cells)",
            n_q2 * n_p2
        )));
    }
    let tile = match &g.tile {
        Some(t) => pair_usize("grid.tile", t, [n_q2, n_p2])?,
        None => [DEFAULT_TILE.min(n_q2), DEFAULT_TILE.min(n_p2)],
    };
    let modes = modes_of(&raw)?;
    let order_name = g.order.as_deref().unwrap_or(ScanOrder::default().name());
    let order = ScanOrder::from_name(order_name, g.order_seed.unwrap_or(1)).ok_or_else(|| {
        usage(format!(
            "grid.order must be one of {} (got {order_name:?})",
            ScanOrder::NAMES
                .iter()
                .map(|n| format!("{n:?}"))
                .collect::<Vec<_>>()
                .join(", ")
        ))
    })?;
    if g.order_seed.is_some() && !matches!(order, ScanOrder::Shuffle(_)) {
        warnings.push(format!(
            "grid.order_seed is ignored with grid.order = {:?}",
            order.name()
        ));
    }
    let (q2_range, p2_range) = bounds_of(g, &surface, &energies)?;
    if modes.contains(&Mode::FastPss) && surface.system().dof() > 2 {
        return Err(usage(format!(
            "fast PSS runs in 2 degrees of freedom only (system.dof = {}: an orbit's crossings \
             lie in a {}-dimensional section, not on the grid's plane): set grid.mode = \"full\"",
            surface.system().dof(),
            2 * surface.system().dof() - 2
        )));
    }

    let s = &raw.sweep;
    for (field, len) in [
        ("sweep.method", s.method.len()),
        ("sweep.tau", s.tau.len()),
        ("sweep.t_final", s.t_final.len()),
    ] {
        if len == 0 {
            return Err(usage(format!("{field} must list at least one value")));
        }
    }
    let methods = s
        .method
        .iter()
        .enumerate()
        .map(|(k, m)| Method::parse(m).map_err(|e| usage(format!("sweep.method[{k}]: {e}"))))
        .collect::<SpecResult<Vec<_>>>()?;
    for (k, &t) in s.tau.iter().enumerate() {
        finite_positive(&format!("sweep.tau[{k}]"), t)?;
    }
    let tau_max = s.tau.iter().copied().fold(0.0, f64::max);
    let (k_min, tau_min) =
        s.tau
            .iter()
            .copied()
            .enumerate()
            .fold(
                (0, f64::INFINITY),
                |a, (k, t)| if t < a.1 { (k, t) } else { a },
            );
    for (k, &t) in s.t_final.iter().enumerate() {
        if !(t.is_finite() && t >= tau_max) {
            return Err(usage(format!(
                "sweep.t_final[{k}] must be a finite number ≥ every sweep.tau (≥ {tau_max}) (got {t})"
            )));
        }
        if t / tau_min > MAX_STEPS {
            return Err(usage(format!(
                "sweep.t_final[{k}] / sweep.tau[{k_min}] = {:.3e} steps of tau; at most {MAX_STEPS:e} are allowed",
                t / tau_min
            )));
        }
    }
    let adaptive = methods.iter().any(Method::is_adaptive);
    let deltas = match &s.delta {
        Some(d) => {
            for (k, &x) in d.iter().enumerate() {
                finite_positive(&format!("sweep.delta[{k}]"), x)?;
            }
            if adaptive && d.is_empty() {
                return Err(usage(
                    "sweep.delta must list at least one value for the adaptive methods (dop853, taylor, taylor-dd)",
                ));
            }
            if !adaptive && !d.is_empty() {
                warnings.push(
                    "sweep.delta is ignored: no method in sweep.method is adaptive".to_string(),
                );
            }
            d.clone()
        }
        None if adaptive => {
            return Err(usage(
                "sweep.delta is required with an adaptive method (dop853, taylor, taylor-dd)",
            ))
        }
        None => Vec::new(),
    };

    let integ = raw.integration.as_ref();
    let protocol = match integ
        .and_then(|i| i.protocol.as_deref())
        .unwrap_or("restart")
    {
        "restart" => Protocol::Restart,
        "free" => Protocol::Free,
        other => {
            return Err(usage(format!(
                "integration.protocol must be \"restart\" or \"free\" (got {other:?})"
            )))
        }
    };
    let seed = integ.and_then(|i| i.seed);
    let deviation = match integ.and_then(|i| i.deviation.as_deref()).unwrap_or("axes") {
        "axes" => {
            if seed.is_some() {
                warnings.push(
                    "integration.seed is ignored with integration.deviation = \"axes\"".into(),
                );
            }
            Deviation::Axes
        }
        "random" => Deviation::Random {
            seed: seed.unwrap_or(1),
        },
        other => {
            return Err(usage(format!(
                "integration.deviation must be \"axes\" or \"random\" (got {other:?})"
            )))
        }
    };

    let c = raw.classify.as_ref();
    let defaults = Thresholds::default();
    let regular = c.and_then(|c| c.regular).unwrap_or(defaults.regular);
    let chaotic = c.and_then(|c| c.chaotic).unwrap_or(defaults.chaotic);
    finite_positive("classify.chaotic", chaotic)?;
    if !(regular.is_finite() && regular <= 2f64.sqrt()) {
        return Err(usage(format!(
            "classify.regular must be ≤ √2, the largest SALI (got {regular})"
        )));
    }
    if chaotic > regular {
        return Err(usage(format!(
            "classify.chaotic must be ≤ classify.regular (got chaotic = {chaotic}, regular = {regular})"
        )));
    }
    let energy_drift = c
        .and_then(|c| c.energy_drift)
        .unwrap_or(defaults.energy_drift);
    if !(energy_drift > 0.0 && energy_drift <= 1e300) {
        return Err(usage(format!(
            "classify.energy_drift must be in (0, 1e300] (got {energy_drift})"
        )));
    }
    let indicators = integ.and_then(|i| i.indicators).unwrap_or(false);
    if indicators && !modes.contains(&Mode::Full) {
        return Err(usage(
            "integration.indicators = true needs a full-mode run (grid.mode = \"full\", or \"full\" in sweep.mode): fast PSS labels cells by other cells' orbits",
        ));
    }
    let early_stop = c.and_then(|c| c.early_stop);
    if indicators && early_stop == Some(true) {
        return Err(usage(
            "classify.early_stop must be false with integration.indicators = true (the indicators are read at t_final)",
        ));
    }
    let thresholds = Thresholds {
        regular,
        chaotic,
        early_stop: early_stop.unwrap_or(defaults.early_stop),
        energy_drift,
    };

    // Counted before the sweep is built: lists of a few thousand values each would make
    // billions of runs.
    let per_pair = methods
        .iter()
        .map(|m| if m.is_adaptive() { deltas.len() } else { 1 })
        .fold(0usize, usize::saturating_add);
    let n_runs = s
        .tau
        .len()
        .saturating_mul(s.t_final.len())
        .saturating_mul(per_pair)
        .saturating_mul(energies.len())
        .saturating_mul(modes.len());
    if n_runs > MAX_RUNS {
        return Err(usage(format!(
            "sweep must make at most {MAX_RUNS} runs (energy × mode × method × tau × t_final × delta; got {n_runs})"
        )));
    }
    let mut runs = Vec::new();
    for (&energy, &mode) in energies
        .iter()
        .flat_map(|e| modes.iter().map(move |m| (e, m)))
    {
        for &tau in &s.tau {
            for &t_final in &s.t_final {
                for m in &methods {
                    if !m.is_adaptive() {
                        runs.push(RunSpec {
                            energy,
                            mode,
                            method: m.clone(),
                            tau,
                            t_final,
                            delta: None,
                        });
                        continue;
                    }
                    for &d in &deltas {
                        let (delta, warning) = m.honoured_delta(d);
                        if let Some(w) = warning {
                            if !warnings.contains(&w) {
                                warnings.push(w);
                            }
                        }
                        runs.push(RunSpec {
                            energy,
                            mode,
                            method: m.clone(),
                            tau,
                            t_final,
                            delta: Some(delta),
                        });
                    }
                }
            }
        }
    }
    let job = JobSpec {
        name,
        surface,
        grid: GridSpec {
            n_q2,
            n_p2,
            tile_q2: tile[0],
            tile_p2: tile[1],
            q2_range,
            p2_range,
            order,
        },
        runs,
        protocol,
        deviation,
        thresholds,
        indicators,
        warnings,
        source,
    };
    if matches!(job.surface.system(), SystemSpec::Polynomial { .. }) {
        every_grid_meets_the_section(&job)?;
    }
    Ok(job)
}

#[cfg(test)]
mod tests {
    use super::*;

    const GOOD: &str = r#"
name = "t"
[system]
kind = "henon-heiles"
energy = 0.125
[grid]
cells = [40, 30]
tile = [10, 10]
mode = "full"
[sweep]
method = ["tm-sbab2c", "dop853"]
tau = [0.5, 0.05]
t_final = [1e3]
delta = [1e-5, 1e-8]
[integration]
protocol = "free"
deviation = "random"
seed = 7
[classify]
regular = 1e-3
chaotic = 1e-9
early_stop = false
energy_drift = 0.5
"#;

    const GOOD_JSON: &str = r#"{
  "name": "t",
  "system": {"kind": "henon-heiles", "energy": 0.125},
  "grid": {"cells": [40, 30], "tile": [10, 10], "mode": "full"},
  "sweep": {"method": ["tm-sbab2c", "dop853"], "tau": [0.5, 0.05], "t_final": [1000],
            "delta": [1e-5, 1e-8]},
  "integration": {"protocol": "free", "deviation": "random", "seed": 7},
  "classify": {"regular": 1e-3, "chaotic": 1e-9, "early_stop": false, "energy_drift": 0.5}
}"#;

    const GOOD_POLYNOMIAL: &str = r#"
name = "p"
[system]
kind = "polynomial"
dof = 3
potential = "(q1^2 + q2^2 + q3^2)/2 + q1^2*q2 + q1^2*q3"
energy = 0.1
[section]
plane = "q1"
axes = ["q2", "p2"]
fixed = { q3 = 0.0, p3 = 0.05 }
[grid]
cells = [20, 20]
mode = "full"
q2 = [-0.4, 0.4]
p2 = [-0.4, 0.4]
[sweep]
method = ["tm-sbab2c"]
tau = [0.5]
t_final = [100]
"#;

    const GOOD_FPU: &str = r#"
name = "fpu"
[system]
kind = "fpu-beta"
dof = 2
beta = 1.5
energy = 0.1
[grid]
cells = [20, 20]
mode = "full"
q2 = [-0.3, 0.3]
p2 = [-0.4, 0.4]
[sweep]
method = ["tm-sbab2c"]
tau = [0.5]
t_final = [100]
"#;

    const MINIMAL: &str = r#"
[system]
kind = "henon-heiles"
energy = 0.125
[grid]
cells = [10, 300]
[sweep]
method = ["tm-sbab2c"]
tau = [0.05]
t_final = [1e3]
"#;

    /// `integration.indicators`: the full-mode runs compute them and run to t_final, the
    /// fast-PSS runs of a mode sweep keep the early stop; a spec without a full-mode run, or
    /// with the early stop asked for, is refused.
    #[test]
    fn indicators_turn_the_early_stop_off_for_full_mode_runs_only() {
        let swept = MINIMAL.replace("[sweep]", "[sweep]\nmode = [\"full\", \"fast-pss\"]")
            + "[integration]\nindicators = true\n";
        let j = parse(&swept, false).unwrap();
        assert!(j.indicators);
        let (full, fast) = (j.cell_run(0), j.cell_run(1));
        assert!(full.indicators && !full.config.thresholds.early_stop);
        assert!(!fast.indicators && fast.config.thresholds.early_stop);
        let fast_only = MINIMAL.to_string() + "[integration]\nindicators = true\n";
        let e = parse(&fast_only, false).unwrap_err();
        assert!(e.0.contains("needs a full-mode run"), "{e}");
        let early = swept.clone() + "[classify]\nearly_stop = true\n";
        let e = parse(&early, false).unwrap_err();
        assert!(e.0.contains("classify.early_stop must be false"), "{e}");
        let off = swept + "[classify]\nearly_stop = false\n";
        assert!(
            !parse(&off, false)
                .unwrap()
                .cell_run(1)
                .config
                .thresholds
                .early_stop
        );
        assert!(!parse(MINIMAL, false).unwrap().cell_run(0).indicators);
    }

    /// `sweep.mode` makes one run per mode, inside the energy axis and outside the others.
    #[test]
    fn mode_as_a_sweep_axis() {
        let swept = MINIMAL
            .replace("[sweep]", "[sweep]\nmode = [\"full\", \"fast-pss\"]")
            .replace("tau = [0.05]", "tau = [0.05, 0.1]");
        let j = parse(&swept, false).unwrap();
        let modes: Vec<Mode> = j.runs.iter().map(|r| r.mode).collect();
        use Mode::{FastPss, Full};
        assert_eq!(modes, [Full, Full, FastPss, FastPss]);
        assert!(j.sweeps_mode());
        assert_eq!(j.cell_run(0).checkpoints_per_decade, CHECKPOINTS_PER_DECADE);
        assert_eq!(j.cell_run(2).checkpoints_per_decade, 0);
        let both = swept
            .replace("energy = 0.125\n", "")
            .replace("[sweep]", "[sweep]\nenergy = [0.1, 0.125]");
        let j = parse(&both, false).unwrap();
        let axes: Vec<(f64, Mode)> = j.runs.iter().map(|r| (r.energy, r.mode)).collect();
        assert_eq!(
            axes[..4],
            [(0.1, Full), (0.1, Full), (0.1, FastPss), (0.1, FastPss)]
        );
        for (text, says) in [
            (
                swept.replace("[grid]", "[grid]\nmode = \"full\""),
                "grid.mode and sweep.mode both give the mode",
            ),
            (
                swept.replace("[\"full\", \"fast-pss\"]", "[]"),
                "sweep.mode must list at least one value",
            ),
            (
                swept.replace("\"fast-pss\"]", "\"fast\"]"),
                "sweep.mode[1] must be \"fast-pss\" or \"full\"",
            ),
            (
                swept.replace("\"fast-pss\"]", "\"full\"]"),
                "must not list a mode twice",
            ),
        ] {
            let msg = usage_message(parse(&text, false));
            assert!(msg.contains(says), "{msg}");
        }
    }

    /// `sweep.energy` makes one run per energy (the outermost axis) on the grid of each.
    #[test]
    fn energy_as_a_sweep_axis() {
        let swept = MINIMAL
            .replace("energy = 0.125\n", "")
            .replace("[sweep]", "[sweep]\nenergy = [0.1, 0.125]")
            .replace("tau = [0.05]", "tau = [0.05, 0.1]");
        let j = parse(&swept, false).unwrap();
        let energies: Vec<f64> = j.runs.iter().map(|r| r.energy).collect();
        assert_eq!(energies, [0.1, 0.1, 0.125, 0.125]);
        assert!(j.sweeps_energy());
        assert_eq!(j.grid(0).q2, default_bounds(0.1).0);
        assert_eq!(j.grid(3).p2, default_bounds(0.125).1);
        for (text, says) in [
            (
                MINIMAL.replace("[sweep]", "[sweep]\nenergy = [0.1]"),
                "both give the energy",
            ),
            (
                swept.replace("[0.1, 0.125]", "[]"),
                "sweep.energy must list at least one value",
            ),
            (
                swept.replace("[0.1, 0.125]", "[0.1, 2.0]"),
                "sweep.energy[1] must be in (0, 1]",
            ),
            (
                MINIMAL.replace("energy = 0.125\n", ""),
                "system.energy is required",
            ),
            // Bounds given must fit the allowed region at every energy: p2 ≤ √(2 · 0.1).
            (
                swept.replace("[grid]", "[grid]\np2 = [-0.5, 0.5]"),
                "grid.p2 must lie within",
            ),
        ] {
            let msg = usage_message(parse(&text, false));
            assert!(msg.contains(says), "{msg}");
        }
        let bounded = parse(&swept.replace("[grid]", "[grid]\np2 = [-0.4, 0.4]"), false).unwrap();
        assert_eq!(bounded.grid(0).p2, (-0.4, 0.4));
        assert_eq!(bounded.grid(3).p2, (-0.4, 0.4));
    }

    /// The compatible cells of a 4 × 4 grid over the allowed region, by hand: a cell is
    /// compatible when p2² + q2² − (2/3) q2³ < 2H at its centre. The centres lie at ±1/4 and
    /// ±3/4 of each half-axis; at H = 1/24 the potential is nearly harmonic and the four corner
    /// cells lie outside ((3/4)² + (3/4)² > 1): 12. At H = 1/8 the two corners at negative q2
    /// (q2 = −0.3005, p2 = ±0.375: 0.2490 < 0.25) come in and the two at q2 = 0.5345 do not
    /// (0.325): 14.
    #[test]
    fn each_energy_has_its_own_compatible_cells() {
        let text = MINIMAL
            .replace("energy = 0.125\n", "")
            .replace("cells = [10, 300]", "cells = [4, 4]")
            .replace("[sweep]", "[sweep]\nenergy = [0.041666666666666664, 0.125]");
        let j = parse(&text, false).unwrap();
        assert_eq!(j.grid(0).compatible_count(), 12);
        assert_eq!(j.grid(1).compatible_count(), 14);
    }

    fn usage_message<T: std::fmt::Debug>(r: SpecResult<T>) -> String {
        match r {
            Err(SpecError(msg)) => msg,
            other => panic!("expected a usage error, got {other:?}"),
        }
    }

    #[test]
    fn a_full_spec_parses_into_the_sweeps_cartesian_product() {
        let j = parse(GOOD, false).unwrap();
        // 2 τ × 1 t_final × (tm once + dop853 × 2 δ)
        assert_eq!(j.runs.len(), 6);
        assert_eq!(j.runs.iter().filter(|r| r.delta.is_none()).count(), 2);
        assert!(j
            .runs
            .iter()
            .all(|r| r.method.is_adaptive() == r.delta.is_some()));
        let dop: Vec<_> = j
            .runs
            .iter()
            .filter(|r| r.method == Method::Dop853)
            .map(|r| (r.tau, r.delta.unwrap()))
            .collect();
        assert_eq!(dop, [(0.5, 1e-5), (0.5, 1e-8), (0.05, 1e-5), (0.05, 1e-8)]);
        assert!(j.runs.iter().all(|r| r.t_final == 1e3));
        assert_eq!(j.name, "t");
        assert!(j.runs.iter().all(|r| r.energy == 0.125));
        assert!(!j.sweeps_energy());
        assert!(j.runs.iter().all(|r| r.mode == Mode::Full));
        assert!(!j.sweeps_mode());
        assert_eq!(
            (j.grid.n_q2, j.grid.n_p2, j.grid.tile_q2, j.grid.tile_p2),
            (40, 30, 10, 10)
        );
        let (q2, p2) = default_bounds(0.125);
        assert_eq!((j.grid.q2_range, j.grid.p2_range), (None, None));
        assert_eq!((j.grid(0).q2, j.grid(0).p2), (q2, p2));
        assert_eq!(j.protocol, Protocol::Free);
        assert_eq!(j.deviation, Deviation::Random { seed: 7 });
        assert_eq!(
            j.thresholds,
            Thresholds {
                regular: 1e-3,
                chaotic: 1e-9,
                early_stop: false,
                energy_drift: 0.5,
            }
        );
        assert!(j.warnings.is_empty(), "{:?}", j.warnings);
        // The recorded source reads back to the same job.
        let json = serde_json::to_string(&j.source).unwrap();
        assert_eq!(parse(&json, true).unwrap(), j);
    }

    #[test]
    fn the_schema_is_every_key_the_parser_reads() {
        // `source` holds every field the parser reads (absent ones as null); between them GOOD
        // and GOOD_POLYNOMIAL have every table.
        let sources = [GOOD, GOOD_POLYNOMIAL].map(|t| parse(t, false).unwrap().source);
        let keys = |v: &Value| -> Vec<String> {
            let mut k: Vec<String> = v.as_object().unwrap().keys().cloned().collect();
            k.sort();
            k
        };
        let mut tables: Vec<&str> = SCHEMA.iter().map(|(t, _)| *t).collect();
        tables.sort();
        tables.dedup();
        assert_eq!(tables.len(), SCHEMA.len(), "a table listed twice");
        for (table, allowed) in SCHEMA {
            let at = |source: &Value| {
                let mut v = source.clone();
                for key in table.split('.').filter(|k| !k.is_empty()) {
                    v = v[key].clone();
                }
                v
            };
            let v = sources
                .iter()
                .map(at)
                .find(Value::is_object)
                .unwrap_or_else(|| panic!("[{table}] in no test spec"));
            let mut want: Vec<String> = allowed.iter().map(|k| k.to_string()).collect();
            want.sort();
            if *table == "section.fixed" {
                // The coordinates a section leaves free: some of them in any one spec.
                assert!(keys(&v).iter().all(|k| want.contains(k)), "[{table}]");
            } else {
                assert_eq!(keys(&v), want, "[{table}]");
            }
        }
        // Every table the top level allows has its keys in SCHEMA.
        for key in allowed_keys("") {
            if sources.iter().any(|s| s[*key].is_object()) {
                assert!(!allowed_keys(key).is_empty(), "[{key}]");
            }
        }
    }

    /// A polynomial system's spec: its surface, its bounds along the named axes, and fast PSS
    /// allowed in 2 dof; Hénon–Heiles written as a polynomial has the built-in's grid.
    #[test]
    fn polynomial_systems_take_their_section_from_the_spec() {
        let j = parse(GOOD_POLYNOMIAL, false).unwrap();
        let section = j.surface.section();
        assert_eq!(section.axis_names(), ["q2", "p2"]);
        assert_eq!(
            section.fixed,
            vec![(Coordinate::P(2), 0.05), (Coordinate::Q(2), 0.0)]
        );
        let grid = j.grid(0);
        assert_eq!((grid.q2, grid.p2), ((-0.4, 0.4), (-0.4, 0.4)));
        assert!(grid.compatible_count() > 0 && grid.compatible_count() < grid.cells());

        let hh = GOOD
            .replace(
                "kind = \"henon-heiles\"",
                "kind = \"polynomial\"\ndof = 2\npotential = \"(q1^2 + q2^2)/2 + q1^2*q2 - q2^3/3\"",
            )
            .replace("mode = \"full\"", "mode = \"full\"\nq2 = [-0.43, 0.67]\np2 = [-0.5, 0.5]");
        let built_in = GOOD.replace(
            "mode = \"full\"",
            "mode = \"full\"\nq2 = [-0.43, 0.67]\np2 = [-0.5, 0.5]",
        );
        let (a, b) = (parse(&hh, false).unwrap(), parse(&built_in, false).unwrap());
        assert_eq!(a.grid(0).canonical(), b.grid(0).canonical());
        assert_ne!(a, b, "the systems differ");

        // Another plane in 2 dof: q2 = 0, axes (q1, p1), fast PSS allowed.
        let plane = GOOD_POLYNOMIAL
            .replace("dof = 3", "dof = 2")
            .replace("+ q3^2", "")
            .replace(" + q1^2*q3", "")
            .replace("plane = \"q1\"", "plane = \"q2\"")
            .replace(
                "axes = [\"q2\", \"p2\"]\nfixed = { q3 = 0.0, p3 = 0.05 }",
                "",
            )
            .replace("mode = \"full\"", "mode = \"fast-pss\"")
            .replace("q2 = [-0.4, 0.4]\np2", "q1 = [-0.4, 0.4]\np1");
        let j = parse(&plane, false).unwrap();
        assert_eq!(j.surface.section().axis_names(), ["q1", "p1"]);
        assert_eq!(j.mode(0), Mode::FastPss);
    }

    /// The FPU-β chain by name is the polynomial system of its expanded potential.
    #[test]
    fn a_named_system_is_its_potential() {
        let named = parse(GOOD_FPU, false).unwrap();
        let text = fpu_beta(2, 1.5);
        let written = GOOD_FPU
            .replace("kind = \"fpu-beta\"", "kind = \"polynomial\"")
            .replace("beta = 1.5", &format!("potential = \"{text}\""));
        let written = parse(&written, false).unwrap();
        assert_eq!(named.surface, written.surface);
        assert_eq!(named.grid(0).canonical(), written.grid(0).canonical());
        assert!(named.grid(0).compatible_count() > 100);
    }

    #[test]
    fn bad_systems_and_sections_name_their_field() {
        let p = GOOD_POLYNOMIAL;
        let cases = [
            (p.replace("\"polynomial\"", "\"quartic\""), "system.kind must be \"henon-heiles\", \"polynomial\" or \"fpu-beta\" (got \"quartic\")"),
            (p.replace("dof = 3", "dof = 8"), "system.dof must be 2 or 3 for a grid (got 8;"),
            (p.replace("dof = 3\n", ""), "system.dof is required with kind = \"polynomial\""),
            (p.replace("potential = \"(q1^2 + q2^2 + q3^2)/2 + q1^2*q2 + q1^2*q3\"\n", ""), "system.potential is required with kind = \"polynomial\""),
            (p.replace("+ q1^2*q2", "+ *q2"), "system.potential is not a polynomial: "),
            (p.replace("q1^2*q2", "q1/q2"), "system.potential is not a polynomial: "),
            (p.replace("q1^2*q3", "q1^2*q4"), "system.potential is not a polynomial: "),
            (p.replace("plane = \"q1\"", "plane = \"p1\""), "section.plane must be a position q1…q3"),
            (p.replace("plane = \"q1\"", "plane = \"q4\""), "section.plane must be one of q1, p1, q2, p2, q3, p3 (got \"q4\")"),
            (p.replace("axes = [\"q2\", \"p2\"]", "axes = [\"q1\", \"p2\"]"), "section.axes must be two different coordinates other than q1 and p1"),
            (p.replace("axes = [\"q2\", \"p2\"]", "axes = [\"q2\"]"), "section.axes must be a list of two coordinates (got 1 value)"),
            (p.replace("q3 = 0.0, p3 = 0.05", "q3 = 0.0"), "section.fixed must give p3 (every coordinate"),
            (p.replace("q3 = 0.0, p3 = 0.05", "q3 = 0.0, p3 = 0.0, q2 = 0.1"), "section.fixed.q2 is not free to fix"),
            (p.replace("q3 = 0.0, p3 = 0.05", "q3 = 0.0, p3 = nan"), "section.fixed.p3 must be a finite number"),
            (p.replace("q3 = 0.0, p3 = 0.05", "q3 = 0.0, p3 = 0.0, x = 1"), "unknown field 'x' in [section.fixed]"),
            (p.replace("p2 = [-0.4, 0.4]", "p2 = [-0.4, 0.4]\nq3 = [0, 1]"), "grid.q3 bounds no axis (the section's axes are q2, p2)"),
            (p.replace("q2 = [-0.4, 0.4]\n", ""), "grid.q2 is required for a polynomial system"),
            (p.replace("q2 = [-0.4, 0.4]", "q2 = [0.4, -0.4]"), "grid.q2 must have lo < hi"),
            (p.replace("mode = \"full\"", "mode = \"fast-pss\""), "fast PSS runs in 2 degrees of freedom only (system.dof = 3: an orbit's crossings lie in a 4-dimensional section"),
            (p.replace("energy = 0.1", "energy = -1"), "grid: no cell's centre lies on the section at energy -1"),
            (GOOD.replace("energy = 0.125", "energy = 0.125\ndof = 2"), "system.dof is not a key of kind = \"henon-heiles\" (it takes only energy)"),
            (p.replace("dof = 3", "dof = 3\nbeta = 1"), "system.beta is not a key of kind = \"polynomial\" (it takes dof and potential)"),
            (GOOD_FPU.replace("beta = 1.5\n", ""), "system.beta is required with kind = \"fpu-beta\""),
            (GOOD_FPU.replace("beta = 1.5", "beta = 1.5\npotential = \"q1\""), "system.potential is not a key of kind = \"fpu-beta\" (it takes dof and beta)"),
            (GOOD.replace("[grid]", "[section]\nplane = \"q2\"\n[grid]"), "section: the henon-heiles system runs on q1 = 0 with axes q2, p2"),
            (GOOD.replace("mode = \"full\"", "mode = \"full\"\nq1 = [0, 1]"), "grid.q1 bounds no axis (the section's axes are q2, p2)"),
        ];
        for (text, want) in cases {
            let msg = usage_message(parse(&text, false));
            assert!(msg.starts_with(want), "{msg}\nwanted: {want}");
            assert!(!msg.contains('\n'), "{msg}");
        }
    }

    #[test]
    fn the_json_form_is_the_same_job() {
        assert_eq!(parse(GOOD_JSON, true).unwrap(), parse(GOOD, false).unwrap());
    }

    #[test]
    fn a_minimal_spec_gets_the_defaults() {
        let j = parse(MINIMAL, false).unwrap();
        assert_eq!(j.name, "salient");
        assert_eq!(j.mode(0), Mode::FastPss);
        // The default 20 × 20 tile, clipped to the 10 cells along q2.
        assert_eq!((j.grid.tile_q2, j.grid.tile_p2), (10, 20));
        assert_eq!(j.protocol, Protocol::Restart);
        assert_eq!(j.deviation, Deviation::Axes);
        assert_eq!(j.thresholds, Thresholds::default());
        assert_eq!(
            j.runs,
            [RunSpec {
                energy: 0.125,
                mode: Mode::FastPss,
                method: Method::parse("tm-sbab2c").unwrap(),
                tau: 0.05,
                t_final: 1e3,
                delta: None
            }]
        );
        assert!(j.warnings.is_empty());
        // The largest grid (each axis at most 4000, 16e6 cells in all) is accepted.
        let big = parse(&MINIMAL.replace("[10, 300]", "[4000, 4000]"), false).unwrap();
        assert_eq!((big.grid.n_q2, big.grid.n_p2), (4000, 4000));
        // Random deviation vectors without a seed use seed 1.
        let j = parse(
            &format!("{MINIMAL}[integration]\ndeviation = \"random\"\n"),
            false,
        )
        .unwrap();
        assert_eq!(j.deviation, Deviation::Random { seed: 1 });
        // The default order is the raster scan; a shuffle without a seed uses seed 1.
        assert_eq!(j.grid.order, ScanOrder::Q2Outer);
        let j = parse(
            &MINIMAL.replace("[grid]", "[grid]\norder = \"shuffle\""),
            false,
        )
        .unwrap();
        assert_eq!(j.grid.order, ScanOrder::Shuffle(1));
        assert_eq!(j.grid(0).order, ScanOrder::Shuffle(1));
        let text = MINIMAL.replace("[grid]", "[grid]\norder = \"p2-outer\"\norder_seed = 4");
        let j = parse(&text, false).unwrap();
        assert_eq!(j.grid.order, ScanOrder::P2Outer);
        assert_eq!(
            j.warnings,
            ["grid.order_seed is ignored with grid.order = \"p2-outer\""]
        );
    }

    #[test]
    fn warnings_for_clamped_and_ignored_values() {
        let text = GOOD.replace("delta = [1e-5, 1e-8]", "delta = [1e-20]");
        let j = parse(&text, false).unwrap();
        // Clamped to what DOP853 honours, warned once although two runs use it.
        assert!(j
            .runs
            .iter()
            .filter(|r| r.method == Method::Dop853)
            .all(|r| r.delta == Some(salient_core::method::DOP853_MIN_DELTA)));
        assert_eq!(j.warnings.len(), 1, "{:?}", j.warnings);

        let text = format!("{MINIMAL}[integration]\nseed = 3\n")
            .replace("t_final = [1e3]", "t_final = [1e3]\ndelta = [1e-9]");
        let j = parse(&text, false).unwrap();
        assert_eq!(j.runs.len(), 1);
        assert_eq!(j.warnings.len(), 2, "{:?}", j.warnings);
        assert!(j.warnings[0].contains("sweep.delta"));
        assert!(j.warnings[1].contains("integration.seed"));
    }

    #[test]
    fn default_bounds_are_the_allowed_region() {
        let ((a, b), (c, d)) = default_bounds(0.125);
        // The design notes' values, to 17 digits.
        #[allow(clippy::excessive_precision)]
        let (lo, hi) = (-0.43969262078590838, 0.67364817766693035);
        assert!((a - lo).abs() < 1e-14, "{a}");
        assert!((b - hi).abs() < 1e-14, "{b}");
        assert!((a - (0.5 + 160f64.to_radians().cos())).abs() < 1e-14);
        assert!((b - (0.5 + 80f64.to_radians().cos())).abs() < 1e-14);
        assert_eq!((c, d), (-0.5, 0.5));
        // Other energies: roots of q² − ⅔q³ = 2H on both sides of 0.
        for h in [1e-6, 0.01, 0.1, 0.16] {
            let ((lo, hi), (plo, phi)) = default_bounds(h);
            assert!(lo < 0.0 && 0.0 < hi && hi < 1.0);
            for q in [lo, hi] {
                assert!(
                    (q * q - 2.0 * q * q * q / 3.0 - 2.0 * h).abs() < 1e-15,
                    "{h} {q}"
                );
            }
            assert_eq!((plo, phi), (-(2.0 * h).sqrt(), (2.0 * h).sqrt()));
        }
        // Above the escape energy the region opens at the saddle q2 = 1: bounded below it.
        for h in [1.0 / 6.0 + 1e-9, 0.2, 1.0] {
            let ((lo, hi), _) = default_bounds(h);
            assert_eq!(hi, 1.0, "{h}");
            assert!((lo * lo - 2.0 * lo * lo * lo / 3.0 - 2.0 * h).abs() < 1e-14);
        }
    }

    #[test]
    fn messages_read_as_documented() {
        let cases = [
            (
                GOOD.replace("energy = 0.125", "energy = 1.5"),
                "system.energy must be in (0, 1] (got 1.5; above the escape energy 1/6 orbits may escape)",
            ),
            (
                GOOD.replace("tau = [0.5, 0.05]", "tau = [0.5, -0.5]"),
                "sweep.tau[1] must be a finite number > 0 (got -0.5)",
            ),
            (
                GOOD.replace("cells = [40, 30]", "cells = [100, 30]")
                    .replace("tile = [10, 10]", "tile = [200, 10]"),
                "grid.tile[0] must be in 1..=100 (got 200)",
            ),
            (
                GOOD.replace("mode = \"full\"", "mode = \"full\"\nfoo = 1"),
                "unknown field 'foo' in [grid] (allowed: cells, tile, mode, q1, q2, q3, p1, p2, p3, order, order_seed)",
            ),
            (
                GOOD.replace("energy = 0.125", "energy = nan"),
                "system.energy must be a finite number (got NaN)",
            ),
        ];
        for (text, want) in cases {
            assert_eq!(usage_message(parse(&text, false)), want);
        }
        let msg = usage_message(parse(
            &GOOD.replace("mode = \"full\"", "mode = \"full\"\nq2 = [-0.5, 0.6]"),
            false,
        ));
        assert!(
            msg.starts_with("grid.q2 must lie within [-0.43969262078590")
                && msg.ends_with("at energy 0.125 (got [-0.5, 0.6])"),
            "{msg}"
        );
        let msg = usage_message(parse(&GOOD.replace("dop853", "rk4"), false));
        assert!(
            msg.starts_with("sweep.method[1]: unknown method 'rk4' (allowed: tm-saba1"),
            "{msg}"
        );
    }

    #[test]
    fn bad_specs_name_their_field_on_one_line() {
        // (text in GOOD, replacement, what the message must contain)
        let cases: &[(&str, &str, &str)] = &[
            ("energy = 0.125", "energy = -1", "system.energy"),
            ("energy = 0.125", "energy = 1.0000001", "system.energy"),
            ("energy = 0.125", "energy = nan", "system.energy"),
            ("energy = 0.125", "energy = -inf", "system.energy"),
            (
                "energy = 0.125",
                "energy = \"x\"",
                "system.energy must be a number",
            ),
            ("energy = 0.125", "", "system.energy is required"),
            ("kind = \"henon-heiles\"", "kind = \"x\"", "system.kind"),
            ("kind = \"henon-heiles\"", "kind = \"a\\nb\"", "system.kind"),
            (
                "kind = \"henon-heiles\"",
                "kind = 3",
                "system.kind must be a string",
            ),
            (
                "[system]",
                "[systems]",
                "unknown field 'systems' at the top level",
            ),
            ("cells = [40, 30]", "cells = [40]", "grid.cells"),
            (
                "cells = [40, 30]",
                "cells = 40",
                "grid.cells must be a list",
            ),
            ("cells = [40, 30]", "cells = [40, -3]", "grid.cells[1]"),
            (
                "cells = [40, 30]",
                "cells = [40, 30.5]",
                "grid.cells[1] must be an integer",
            ),
            (
                "cells = [40, 30]",
                "cells = [4001, 30]",
                "grid.cells[0] must be in 1..=4000",
            ),
            ("cells = [40, 30]", "cells = [4000, 4001]", "grid.cells[1]"),
            (
                "cells = [40, 30]",
                "cells = [40, 99999999999999999999]",
                "cells",
            ),
            (
                "tile = [10, 10]",
                "tile = [10, 31]",
                "grid.tile[1] must be in 1..=30",
            ),
            ("tile = [10, 10]", "tile = [0, 10]", "grid.tile[0]"),
            ("mode = \"full\"", "mode = \"half\"", "grid.mode"),
            (
                "mode = \"full\"",
                "mode = \"full\"\norder = \"spiral\"",
                "grid.order must be one of \"q2-outer\", \"p2-outer\"",
            ),
            (
                "mode = \"full\"",
                "mode = \"full\"\norder_seed = -1",
                "grid.order_seed",
            ),
            (
                "mode = \"full\"",
                "mode = \"full\"\nq2 = [0.5, 0.1]",
                "grid.q2 must have lo < hi",
            ),
            ("mode = \"full\"", "mode = \"full\"\nq2 = [0.5]", "grid.q2"),
            (
                "mode = \"full\"",
                "mode = \"full\"\nq2 = [0.1, inf]",
                "grid.q2[1]",
            ),
            (
                "mode = \"full\"",
                "mode = \"full\"\np2 = [-0.6, 0.1]",
                "grid.p2 must lie within",
            ),
            (
                "mode = \"full\"",
                "mode = \"full\"\n[grid.extra]",
                "unknown field 'extra' in [grid]",
            ),
            (
                "[grid]\ncells = [40, 30]\ntile = [10, 10]\nmode = \"full\"\n",
                "",
                "[grid]",
            ),
            (
                "method = [\"tm-sbab2c\", \"dop853\"]",
                "method = []",
                "sweep.method",
            ),
            (
                "method = [\"tm-sbab2c\", \"dop853\"]",
                "method = [\"tm-sbab2c\", \"rk45\"]",
                "sweep.method[1]",
            ),
            (
                "method = [\"tm-sbab2c\", \"dop853\"]",
                "method = \"dop853\"",
                "sweep.method must be a list",
            ),
            (
                "method = [\"tm-sbab2c\", \"dop853\"]",
                "",
                "sweep.method is required",
            ),
            ("tau = [0.5, 0.05]", "tau = [0.5, 0]", "sweep.tau[1]"),
            ("tau = [0.5, 0.05]", "tau = [inf]", "sweep.tau[0]"),
            (
                "tau = [0.5, 0.05]",
                "tau = [0.5, true]",
                "sweep.tau[1] must be a number",
            ),
            ("t_final = [1e3]", "t_final = [0.1]", "sweep.t_final[0]"),
            (
                "t_final = [1e3]",
                "t_final = [1e3, 1e30]",
                "sweep.t_final[1] / sweep.tau[1]",
            ),
            ("t_final = [1e3]", "t_final = []", "sweep.t_final"),
            (
                "delta = [1e-5, 1e-8]",
                "delta = [1e-5, -1]",
                "sweep.delta[1]",
            ),
            (
                "delta = [1e-5, 1e-8]",
                "delta = [1e-5, nan]",
                "sweep.delta[1]",
            ),
            ("delta = [1e-5, 1e-8]", "", "sweep.delta"),
            ("delta = [1e-5, 1e-8]", "delta = []", "sweep.delta"),
            (
                "protocol = \"free\"",
                "protocol = \"lazy\"",
                "integration.protocol",
            ),
            (
                "deviation = \"random\"",
                "deviation = \"sideways\"",
                "integration.deviation",
            ),
            ("seed = 7", "seed = -1", "integration.seed"),
            ("seed = 7", "seed = 1.5", "integration.seed"),
            (
                "chaotic = 1e-9",
                "chaotic = 1e-2",
                "classify.chaotic must be ≤ classify.regular",
            ),
            ("chaotic = 1e-9", "chaotic = 0", "classify.chaotic"),
            ("regular = 1e-3", "regular = 2", "classify.regular"),
            (
                "early_stop = false",
                "early_stop = 1",
                "classify.early_stop",
            ),
            (
                "energy_drift = 0.5",
                "energy_drift = 0",
                "classify.energy_drift",
            ),
            (
                "energy_drift = 0.5",
                "energy_drift = nan",
                "classify.energy_drift",
            ),
            (
                "energy_drift = 0.5",
                "energy_drift = \"big\"",
                "classify.energy_drift",
            ),
            (
                "[classify]",
                "[classify]\nsali = 1",
                "unknown field 'sali' in [classify]",
            ),
            (
                "name = \"t\"",
                "name = \"t\"\nversion = 2",
                "unknown field 'version' at the top level",
            ),
            ("name = \"t\"", "name = \"\"", "name"),
            ("name = \"t\"", "name = \"a/b\"", "name"),
            ("name = \"t\"", "name = \"..\"", "name"),
            ("name = \"t\"", "name = \".\"", "name"),
            ("name = \"t\"", "name = \".hidden\"", "name"),
            ("name = \"t\"", "name = \"-rf\"", "name"),
            ("name = \"t\"", "name = \"a b\"", "name"),
            ("name = \"t\"", "name = \"a\\u0000b\"", "name"),
            // Syntax errors name the line.
            ("energy = 0.125", "energy = 0.125\nenergy = 0.1", "energy"),
            ("energy = 0.125", "energy = ", "energy"),
        ];
        for (from, to, field) in cases {
            assert!(GOOD.contains(from), "{from}");
            let msg = usage_message(parse(&GOOD.replacen(from, to, 1), false));
            assert!(msg.contains(field), "{to}: '{msg}' does not name {field}");
            assert!(!msg.contains('\n'), "{to}: multi-line message '{msg}'");
        }
    }

    #[test]
    fn bad_json_specs_name_their_field_on_one_line() {
        let cases: &[(&str, &str, &str)] = &[
            (
                "\"cells\": [40, 30]",
                "\"cells\": [40, \"x\"]",
                "grid.cells[1] must be an integer",
            ),
            (
                "\"mode\": \"full\"",
                "\"mode\": \"full\", \"foo\": 2",
                "unknown field 'foo' in [grid]",
            ),
            ("\"name\": \"t\"", "\"name\": 3", "name must be a string"),
            (
                "\"name\": \"t\"",
                "\"name\": \"t\", \"bar\": 1",
                "unknown field 'bar' at the top level",
            ),
            (
                "\"energy\": 0.125",
                "\"energy\": \"high\"",
                "system.energy must be a number",
            ),
            (
                "\"energy\": 0.125",
                "\"energy\": null",
                "system.energy is required",
            ),
            ("\"seed\": 7", "\"seed\": -7", "integration.seed"),
            (
                "\"early_stop\": false",
                "\"early_stop\": \"no\"",
                "classify.early_stop",
            ),
            (
                "\"tau\": [0.5, 0.05]",
                "\"tau\": [0.5, 1e999]",
                "spec is not valid JSON",
            ),
            (
                "\"t_final\": [1000],",
                "\"t_final\": [1000]",
                "spec is not valid JSON",
            ),
            (
                "\"integration\": {",
                "\"integration\": [], \"x\": {",
                "unknown field 'x'",
            ),
            (
                "\"integration\": {",
                "\"integration\": 1, \"x\": {",
                "unknown field 'x'",
            ),
        ];
        for (from, to, field) in cases {
            assert!(GOOD_JSON.contains(from), "{from}");
            let msg = usage_message(parse(&GOOD_JSON.replacen(from, to, 1), true));
            assert!(msg.contains(field), "{to}: '{msg}' does not name {field}");
            assert!(!msg.contains('\n'), "{to}: multi-line message '{msg}'");
        }
        let msg = usage_message(parse(
            &GOOD_JSON.replacen("\"integration\": {", "\"integration\": 1, \"y\": {", 1),
            true,
        ));
        assert!(msg.contains("'y'"), "{msg}");
        let msg = usage_message(parse("[1, 2]", true));
        assert!(msg.contains("the spec must be a table"), "{msg}");
        let msg = usage_message(parse(
            &GOOD_JSON.replacen("\"classify\": {", "\"classify\": [1], \"z\": {", 1),
            true,
        ));
        assert!(msg.contains("'z'"), "{msg}");
    }

    #[test]
    fn names_are_short_file_names_and_sweeps_are_capped() {
        let named = |name: &str| GOOD.replacen("name = \"t\"", &format!("name = \"{name}\""), 1);
        for ok in ["t", "j200b", "run-1.v2_a+b", &"n".repeat(MAX_NAME_CHARS)] {
            assert_eq!(parse(&named(ok), false).unwrap().name, ok);
        }
        // A long name is refused, and the message quotes only its start.
        let msg = usage_message(parse(&named(&"y".repeat(65_536)), false));
        assert!(msg.contains("65536 characters") && msg.len() < 400, "{msg}");
        assert!(!usage_message(parse(&named(&"n".repeat(MAX_NAME_CHARS + 1)), false)).is_empty());
        // Runs are counted before they are made: 2000 × 2000 values would be 4e6 runs.
        let list = |n: usize, scale: f64| {
            let v: Vec<String> = (1..=n).map(|k| format!("{:?}", k as f64 * scale)).collect();
            format!("[{}]", v.join(", "))
        };
        let big = GOOD
            .replacen(
                "tau = [0.5, 0.05]",
                &format!("tau = {}", list(2000, 1e-4)),
                1,
            )
            .replacen(
                "t_final = [1e3]",
                &format!("t_final = {}", list(2000, 1e3)),
                1,
            );
        let msg = usage_message(parse(&big, false));
        assert!(msg.contains("at most 1024 runs"), "{msg}");
    }
}
