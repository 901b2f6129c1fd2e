//! Speed against error: every method over a ladder of settings on one orbit, each run compared
//! with a double-double Taylor reference from the same initial condition (the seed paper's
//! Table 1 and Fig. 6, as data), on Hénon–Heiles or any polynomial system.

use crate::system::{OrbitReport, System};
use salient_core::adaptive::driver::Protocol;
use salient_core::method::Method;
use salient_core::orbit::{Class, OrbitConfig, OrbitResult, Requests, Status};
use salient_core::run::{MethodRun, Vectors};
use salient_core::tangent_map::scheme::Scheme;
use std::time::Instant;

/// The renormalisation interval of the adaptive methods' runs (the paper's τ).
pub const ADAPTIVE_TAU: f64 = 0.05;
/// The reference: taylor-dd at this tolerance.
pub const REFERENCE_DELTA: f64 = 1e-28;

/// One setting of the ladder.
#[derive(Clone, Debug, PartialEq)]
pub struct Setting {
    pub run: MethodRun,
    pub tau: f64,
}

/// One measured row.
#[derive(Clone, Debug, PartialEq)]
pub struct Row {
    pub setting: Setting,
    pub status: Status,
    pub order: u32,
    pub steps: u64,
    pub wall_s: f64,
    pub ns_per_step: f64,
    pub energy_error_max: f64,
    /// Max-norm distance of the end point (q, p) from the reference's.
    pub state_error: f64,
    pub sali: f64,
    pub class: Option<Class>,
}

/// The default ladder: τ ladders for a set of tangent-map schemes, δ ladders for the adaptive
/// methods in both protocols.
pub fn default_ladder() -> Vec<Setting> {
    let mut v = Vec::new();
    for name in ["sbab2", "sbab2c", "saba2c", "saba3c", "aba864", "srkn14a"] {
        let scheme = Scheme::by_name(name).expect("known scheme");
        for tau in [0.5, 0.2, 0.1, 0.05, 0.02, 0.01] {
            let run = MethodRun {
                method: Method::TangentMap(scheme.clone()),
                delta: None,
                protocol: Protocol::Restart,
            };
            v.push(Setting { run, tau });
        }
    }
    let adaptive: [(Method, &[f64]); 3] = [
        (Method::Dop853, &[1e-5, 1e-7, 1e-9, 1e-11, 1e-13]),
        (Method::Taylor, &[1e-5, 1e-8, 1e-11, 1e-14, 1e-15]),
        (Method::TaylorDd, &[1e-16, 1e-20, 1e-24]),
    ];
    for (method, deltas) in adaptive {
        for protocol in [Protocol::Restart, Protocol::Free] {
            for &delta in deltas {
                let run = MethodRun {
                    method: method.clone(),
                    delta: Some(delta),
                    protocol,
                };
                v.push(Setting {
                    run,
                    tau: ADAPTIVE_TAU,
                });
            }
        }
    }
    v
}

fn config(tau: f64, t_final: f64) -> OrbitConfig {
    let mut c = OrbitConfig::new(tau, t_final);
    // Every run goes to t_final so that end points compare at the same time.
    c.thresholds.early_stop = false;
    c
}

/// What the ladder keeps of a run: its end point, whatever the system's dimension.
#[derive(Clone, Debug, PartialEq)]
pub struct OrbitEnd {
    pub status: Status,
    pub steps: u64,
    pub q_end: Vec<f64>,
    pub p_end: Vec<f64>,
    pub energy_error_max: Option<f64>,
    pub sali: f64,
    pub class: Option<Class>,
}

/// [`OrbitEnd`] as the report of [`System::run_orbit`].
struct EndOf;

impl OrbitReport<OrbitEnd> for EndOf {
    fn report<const N: usize>(&mut self, r: &OrbitResult<N>) -> OrbitEnd {
        OrbitEnd {
            status: r.status,
            steps: r.steps,
            q_end: r.q_end.to_vec(),
            p_end: r.p_end.to_vec(),
            energy_error_max: r.energy_error_max,
            sali: r.sali,
            class: r.class,
        }
    }
}

/// One orbit of `system` from `start` with `run` at renormalisation interval `tau`.
fn orbit_end(
    system: &System,
    run: &MethodRun,
    (energy, start): (f64, (&[f64], &[f64])),
    (tau, t_final): (f64, f64),
    requests: &Requests,
) -> OrbitEnd {
    let config = config(tau, t_final);
    system.run_orbit(
        run,
        energy,
        start,
        &config,
        requests,
        Vectors::Two,
        &mut EndOf,
    )
}

/// The reference run: taylor-dd at δ = 1e-28, free protocol.
pub fn reference(system: &System, energy: f64, start: (&[f64], &[f64]), t_final: f64) -> OrbitEnd {
    let run = MethodRun {
        method: Method::TaylorDd,
        delta: Some(REFERENCE_DELTA),
        protocol: Protocol::Free,
    };
    let requests = Requests::default();
    orbit_end(
        system,
        &run,
        (energy, start),
        (ADAPTIVE_TAU, t_final),
        &requests,
    )
}

/// Runs every setting on `system` from `start` and measures it against `reference`;
/// `progress` sees each row as it is done.
pub fn run_ladder(
    system: &System,
    (energy, start): (f64, (&[f64], &[f64])),
    t_final: f64,
    ladder: &[Setting],
    reference: &OrbitEnd,
    progress: &mut dyn FnMut(usize, &Row),
) -> Vec<Row> {
    let requests = Requests {
        energy: true,
        ..Requests::default()
    };
    let mut rows = Vec::with_capacity(ladder.len());
    for (i, s) in ladder.iter().enumerate() {
        let start_time = Instant::now();
        let r = orbit_end(system, &s.run, (energy, start), (s.tau, t_final), &requests);
        let wall_s = start_time.elapsed().as_secs_f64();
        let state_error = (0..r.q_end.len())
            .map(|i| {
                (r.q_end[i] - reference.q_end[i])
                    .abs()
                    .max((r.p_end[i] - reference.p_end[i]).abs())
            })
            .fold(0.0, f64::max);
        let row = Row {
            setting: s.clone(),
            status: r.status,
            order: s.run.order(),
            steps: r.steps,
            wall_s,
            ns_per_step: if r.steps > 0 {
                wall_s * 1e9 / r.steps as f64
            } else {
                0.0
            },
            energy_error_max: r.energy_error_max.unwrap_or(f64::NAN),
            state_error,
            sali: r.sali,
            class: r.class,
        };
        progress(i, &row);
        rows.push(row);
    }
    rows
}
