//! Job specs (TOML, or JSON with the same schema): parsed strictly, validated up front, every
//! problem reported as one line naming the field and its allowed range.

use crate::usage::{CliError, CliResult};
use salient_core::adaptive::Protocol;
use salient_core::orbit::{Deviation, Thresholds};
use salient_core::Method;
use serde::Deserialize;
use std::path::Path;

/// Largest grid a spec may ask for.
const MAX_CELLS: usize = 16_000_000;
/// Largest number of steps τ in one run.
const MAX_STEPS: f64 = 1e12;
/// Cells per axis.
const MAX_AXIS: usize = 4000;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Mode {
    FastPss,
    Full,
}

#[derive(Clone, Debug, PartialEq)]
pub struct GridSpec {
    pub n_q2: usize,
    pub n_p2: usize,
    pub tile_q2: usize,
    pub tile_p2: usize,
    pub mode: Mode,
    pub q2_range: (f64, f64),
    pub p2_range: (f64, f64),
}

/// One member of the sweep.
#[derive(Clone, Debug, PartialEq)]
pub struct RunSpec {
    pub method: Method,
    pub tau: f64,
    pub t_final: f64,
    /// The tolerance of an adaptive method (None for tangent-map methods).
    pub delta: Option<f64>,
}

#[derive(Clone, Debug, PartialEq)]
pub struct JobSpec {
    pub name: String,
    pub energy: f64,
    pub grid: GridSpec,
    pub runs: Vec<RunSpec>,
    pub protocol: Protocol,
    pub deviation: Deviation,
    pub thresholds: Thresholds,
    pub warnings: Vec<String>,
    /// The spec as parsed, for run.json.
    pub source: serde_json::Value,
}

#[derive(Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
struct RawSpec {
    name: Option<String>,
    system: RawSystem,
    grid: RawGrid,
    sweep: RawSweep,
    integration: Option<RawIntegration>,
    classify: Option<RawClassify>,
}

#[derive(Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
struct RawSystem {
    kind: String,
    energy: f64,
}

#[derive(Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
struct RawGrid {
    cells: Vec<i64>,
    tile: Option<Vec<i64>>,
    mode: Option<String>,
    q2: Option<Vec<f64>>,
    p2: Option<Vec<f64>>,
}

#[derive(Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
struct RawSweep {
    method: Vec<String>,
    tau: Vec<f64>,
    t_final: Vec<f64>,
    delta: Option<Vec<f64>>,
}

#[derive(Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
struct RawIntegration {
    protocol: Option<String>,
    deviation: Option<String>,
    seed: Option<u64>,
}

#[derive(Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
struct RawClassify {
    regular: Option<f64>,
    chaotic: Option<f64>,
    early_stop: Option<bool>,
}

fn usage(msg: String) -> CliError {
    CliError::Usage(msg)
}

/// Reads and validates a spec file: JSON when it ends in `.json` or starts with `{`, else TOML.
pub fn load(path: &Path) -> CliResult<JobSpec> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| usage(format!("spec: cannot read {}: {e}", path.display())))?;
    let json = path.extension().is_some_and(|e| e == "json") || text.trim_start().starts_with('{');
    parse(&text, json)
}

/// The text of the line holding byte offset `at`, to name the field a parser error is about.
fn line_at(text: &str, at: usize) -> (usize, &str) {
    let start = text[..at.min(text.len())].rfind('\n').map_or(0, |i| i + 1);
    let end = text[start..].find('\n').map_or(text.len(), |i| start + i);
    (
        text[..start].matches('\n').count() + 1,
        text[start..end].trim(),
    )
}

/// The JSON key whose value ends at (line, column), to name the field a parser error is about.
fn json_key_before(text: &str, line: usize, column: usize) -> Option<String> {
    let l = text.lines().nth(line.checked_sub(1)?)?;
    let before = l.get(..column.min(l.len()))?;
    let colon = before.rfind(':')?;
    let key_end = before[..colon].rfind('"')?;
    let key_start = before[..key_end].rfind('"')?;
    Some(before[key_start + 1..key_end].to_string())
}

/// Parses and validates a spec's text.
pub fn parse(text: &str, json: bool) -> CliResult<JobSpec> {
    let raw: RawSpec = if json {
        serde_json::from_str(text).map_err(|e| {
            let first = e.to_string().lines().next().unwrap_or("").to_string();
            match json_key_before(text, e.line(), e.column()) {
                Some(key) => usage(format!("spec field \"{key}\": {first}")),
                None => usage(format!("spec: {first}")),
            }
        })?
    } else {
        toml::from_str(text).map_err(|e| {
            let msg = e.message().lines().next().unwrap_or("").to_string();
            match e.span() {
                Some(span) => {
                    let (line, content) = line_at(text, span.start);
                    usage(format!("spec line {line} (`{content}`): {msg}"))
                }
                None => usage(format!("spec: {msg}")),
            }
        })?
    };
    validate(raw)
}

fn finite_positive(field: &str, v: f64) -> CliResult<f64> {
    if v.is_finite() && v > 0.0 {
        Ok(v)
    } else {
        Err(usage(format!(
            "{field} must be a finite number > 0 (got {v})"
        )))
    }
}

fn pair_usize(field: &str, v: &[i64], max: &[usize; 2]) -> CliResult<[usize; 2]> {
    if v.len() != 2 {
        return Err(usage(format!(
            "{field} must be a list of two integers (got {} values)",
            v.len()
        )));
    }
    let mut out = [0usize; 2];
    for k in 0..2 {
        if v[k] < 1 || v[k] as u64 > max[k] as u64 {
            return Err(usage(format!(
                "{field}[{k}] must be in 1..={} (got {})",
                max[k], v[k]
            )));
        }
        out[k] = v[k] as usize;
    }
    Ok(out)
}

fn range(
    field: &str,
    v: &Option<Vec<f64>>,
    default: (f64, f64),
    energy: f64,
) -> CliResult<(f64, f64)> {
    let Some(v) = v else { return Ok(default) };
    let ok = v.len() == 2 && v.iter().all(|x| x.is_finite()) && v[0] < v[1];
    let tol = 1e-12;
    if !ok || v[0] < default.0 - tol || v[1] > default.1 + tol {
        return Err(usage(format!(
            "{field} must be [lo, hi] with lo < hi within [{}, {}] at energy {energy} (got {v:?})",
            default.0, default.1
        )));
    }
    Ok((v[0], v[1]))
}

/// Default section bounds of Hénon–Heiles at energy H (0 < H < 1/6): q2 between the real roots
/// of q2² − (2/3) q2³ = 2H that bracket 0, p2 in [−√(2H), √(2H)].
pub fn default_bounds(energy: f64) -> ((f64, f64), (f64, f64)) {
    let f = |q: f64| q * q - 2.0 * q * q * q / 3.0 - 2.0 * energy;
    // f(0) < 0; f rises to 1/3 − 2H > 0 at q = 1 and is positive far on the negative side.
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
    ((bisect(0.0, -2.0), bisect(0.0, 1.0)), (-p, p))
}

fn validate(raw: RawSpec) -> CliResult<JobSpec> {
    let source = serde_json::to_value(&raw).expect("a parsed spec serialises");
    let name = raw.name.unwrap_or_else(|| "salient".into());
    if name.trim().is_empty() || name.contains(['/', '\\']) {
        return Err(usage(format!(
            "name must be non-empty without path separators (got '{name}')"
        )));
    }
    if raw.system.kind != "henon-heiles" {
        return Err(usage(format!(
            "system.kind must be \"henon-heiles\" (got \"{}\")",
            raw.system.kind
        )));
    }
    let energy = raw.system.energy;
    if !(energy.is_finite() && energy > 0.0 && energy < 1.0 / 6.0) {
        return Err(usage(format!(
            "system.energy must be in (0, 1/6) (got {energy})"
        )));
    }

    let g = &raw.grid;
    let [n_q2, n_p2] = pair_usize("grid.cells", &g.cells, &[MAX_AXIS, MAX_AXIS])?;
    if n_q2 * n_p2 > MAX_CELLS {
        return Err(usage(format!(
            "grid.cells must hold at most {MAX_CELLS} cells (got {})",
            n_q2 * n_p2
        )));
    }
    let tile = match &g.tile {
        Some(t) => pair_usize("grid.tile", t, &[n_q2, n_p2])?,
        None => [20.min(n_q2), 20.min(n_p2)],
    };
    let mode = match g.mode.as_deref().unwrap_or("fast-pss") {
        "fast-pss" => Mode::FastPss,
        "full" => Mode::Full,
        other => {
            return Err(usage(format!(
                "grid.mode must be \"fast-pss\" or \"full\" (got \"{other}\")"
            )))
        }
    };
    let (dq, dp) = default_bounds(energy);
    let q2_range = range("grid.q2", &g.q2, dq, energy)?;
    let p2_range = range("grid.p2", &g.p2, dp, energy)?;

    let s = &raw.sweep;
    for (field, list) in [
        ("sweep.method", s.method.len()),
        ("sweep.tau", s.tau.len()),
        ("sweep.t_final", s.t_final.len()),
    ] {
        if list == 0 {
            return Err(usage(format!("{field} must list at least one value")));
        }
    }
    let mut methods = Vec::new();
    for (k, m) in s.method.iter().enumerate() {
        methods.push(Method::parse(m).map_err(|e| usage(format!("sweep.method[{k}]: {e}")))?);
    }
    for (k, &t) in s.tau.iter().enumerate() {
        finite_positive(&format!("sweep.tau[{k}]"), t)?;
    }
    let tau_max = s.tau.iter().cloned().fold(0.0, f64::max);
    let tau_min = s.tau.iter().cloned().fold(f64::INFINITY, f64::min);
    for (k, &t) in s.t_final.iter().enumerate() {
        if !(t.is_finite() && t >= tau_max) {
            return Err(usage(format!(
                "sweep.t_final[{k}] must be a finite number ≥ every tau (≥ {tau_max}) (got {t})"
            )));
        }
        if t / tau_min > MAX_STEPS {
            return Err(usage(format!(
                "sweep.t_final[{k}] / tau = {:.3e} steps; at most {MAX_STEPS:e} are allowed",
                t / tau_min
            )));
        }
    }
    let adaptive = methods.iter().any(Method::is_adaptive);
    let deltas = match (&s.delta, adaptive) {
        (Some(d), _) if d.is_empty() && adaptive => {
            return Err(usage(
                "sweep.delta must list at least one value for the adaptive methods".into(),
            ))
        }
        (Some(d), _) => {
            for (k, &x) in d.iter().enumerate() {
                finite_positive(&format!("sweep.delta[{k}]"), x)?;
            }
            d.clone()
        }
        (None, true) => {
            return Err(usage(
                "sweep.delta is required with an adaptive method (dop853, taylor, taylor-dd)"
                    .into(),
            ))
        }
        (None, false) => Vec::new(),
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
                "integration.protocol must be \"restart\" or \"free\" (got \"{other}\")"
            )))
        }
    };
    let seed = integ.and_then(|i| i.seed).unwrap_or(1);
    let deviation = match integ.and_then(|i| i.deviation.as_deref()).unwrap_or("axes") {
        "axes" => Deviation::Axes,
        "random" => Deviation::Random { seed },
        other => {
            return Err(usage(format!(
                "integration.deviation must be \"axes\" or \"random\" (got \"{other}\")"
            )))
        }
    };
    let c = raw.classify.as_ref();
    let regular = c.and_then(|c| c.regular).unwrap_or(1e-4);
    let chaotic = c.and_then(|c| c.chaotic).unwrap_or(1e-8);
    if !(chaotic.is_finite()
        && regular.is_finite()
        && chaotic > 0.0
        && chaotic <= regular
        && regular <= 2f64.sqrt())
    {
        return Err(usage(format!(
            "classify.chaotic and classify.regular must satisfy 0 < chaotic ≤ regular ≤ √2 (got {chaotic}, {regular})"
        )));
    }
    let thresholds = Thresholds {
        regular,
        chaotic,
        early_stop: c.and_then(|c| c.early_stop).unwrap_or(true),
    };

    let mut runs = Vec::new();
    let mut warnings = Vec::new();
    for &tau in &s.tau {
        for &t_final in &s.t_final {
            for m in &methods {
                if m.is_adaptive() {
                    for &d in &deltas {
                        let (delta, warning) = m.honoured_delta(d);
                        warnings.extend(warning);
                        runs.push(RunSpec {
                            method: m.clone(),
                            tau,
                            t_final,
                            delta: Some(delta),
                        });
                    }
                } else {
                    runs.push(RunSpec {
                        method: m.clone(),
                        tau,
                        t_final,
                        delta: None,
                    });
                }
            }
        }
    }
    Ok(JobSpec {
        name,
        energy,
        grid: GridSpec {
            n_q2,
            n_p2,
            tile_q2: tile[0],
            tile_p2: tile[1],
            mode,
            q2_range,
            p2_range,
        },
        runs,
        protocol,
        deviation,
        thresholds,
        warnings,
        source,
    })
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
"#;

    #[test]
    fn a_full_spec_parses_into_the_sweeps_cartesian_product() {
        let j = parse(GOOD, false).unwrap();
        // 2 τ × 1 t_final × (tm once + dop853 × 2 δ)
        assert_eq!(j.runs.len(), 6);
        assert_eq!(j.runs.iter().filter(|r| r.delta.is_none()).count(), 2);
        assert_eq!(j.grid.mode, Mode::Full);
        assert_eq!((j.grid.n_q2, j.grid.n_p2, j.grid.tile_q2), (40, 30, 10));
        assert_eq!(j.protocol, Protocol::Free);
        assert_eq!(j.deviation, Deviation::Random { seed: 7 });
        assert!(!j.thresholds.early_stop);
        let json = serde_json::to_string(&j.source).unwrap();
        assert_eq!(parse(&json, true).unwrap(), j);
    }

    #[test]
    fn default_bounds_are_the_allowed_region() {
        let ((a, b), (c, d)) = default_bounds(0.125);
        assert!((a - (0.5 + 160f64.to_radians().cos())).abs() < 1e-14);
        assert!((b - (0.5 + 80f64.to_radians().cos())).abs() < 1e-14);
        assert_eq!((c, d), (-0.5, 0.5));
    }

    #[test]
    fn bad_specs_name_their_field_on_one_line() {
        let cases: &[(&str, &str, &str)] = &[
            ("energy = 0.125", "energy = -1", "system.energy"),
            ("energy = 0.125", "energy = nan", "system.energy"),
            ("energy = 0.125", "energy = \"x\"", "energy"),
            ("kind = \"henon-heiles\"", "kind = \"x\"", "system.kind"),
            ("cells = [40, 30]", "cells = [40]", "grid.cells"),
            ("cells = [40, 30]", "cells = [40, -3]", "grid.cells[1]"),
            ("cells = [40, 30]", "cells = [4000, 4001]", "grid.cells"),
            ("tile = [10, 10]", "tile = [10, 31]", "grid.tile[1]"),
            ("mode = \"full\"", "mode = \"half\"", "grid.mode"),
            (
                "mode = \"full\"",
                "mode = \"full\"\nq2 = [0.5, 0.1]",
                "grid.q2",
            ),
            (
                "mode = \"full\"",
                "mode = \"full\"\np2 = [-0.6, 0.1]",
                "grid.p2",
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
            ("tau = [0.5, 0.05]", "tau = [0.5, 0]", "sweep.tau[1]"),
            ("tau = [0.5, 0.05]", "tau = [inf]", "sweep.tau[0]"),
            ("t_final = [1e3]", "t_final = [0.1]", "sweep.t_final[0]"),
            ("t_final = [1e3]", "t_final = [1e30]", "sweep.t_final[0]"),
            (
                "delta = [1e-5, 1e-8]",
                "delta = [1e-5, -1]",
                "sweep.delta[1]",
            ),
            ("delta = [1e-5, 1e-8]", "", "sweep.delta"),
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
            ("chaotic = 1e-9", "chaotic = 1e-2", "classify"),
            ("[classify]", "[classify]\nsali = 1", "sali"),
            ("name = \"t\"", "name = \"t\"\nversion = 2", "version"),
            ("name = \"t\"", "name = \"\"", "name"),
        ];
        // JSON type errors name the key too.
        match parse(
            r#"{"name": 3, "system": {"kind": "henon-heiles", "energy": 0.125}}"#,
            true,
        ) {
            Err(CliError::Usage(msg)) => assert!(msg.contains("\"name\""), "{msg}"),
            other => panic!("{other:?}"),
        }
        match parse(
            "{\"system\": {\"kind\": \"henon-heiles\",\n \"energy\": \"high\"}}",
            true,
        ) {
            Err(CliError::Usage(msg)) => assert!(msg.contains("\"energy\""), "{msg}"),
            other => panic!("{other:?}"),
        }
        for (from, to, field) in cases {
            assert!(GOOD.contains(from), "{from}");
            let text = GOOD.replacen(from, to, 1);
            match parse(&text, false) {
                Err(CliError::Usage(msg)) => {
                    assert!(msg.contains(field), "{to}: '{msg}' does not name {field}");
                    assert!(!msg.contains('\n'), "{to}: multi-line message '{msg}'");
                }
                other => panic!("{to}: expected a usage error, got {other:?}"),
            }
        }
    }
}
