//! The system of the single-orbit commands (`salient orbit`, `salient precision`): Hénon–Heiles
//! by default, or a polynomial potential given as text or by name, and one orbit of it run
//! with any method in the size it was compiled for.

use crate::usage::{finite, CliError, CliResult};
use clap::{Args, ValueEnum};
use salient_core::orbit::{OrbitConfig, OrbitResult, Requests};
use salient_core::run::{run_henon_heiles, MethodRun, PolynomialRun, Vectors, POLYNOMIAL_DOFS};
use salient_core::systems::polynomial::named::fpu_beta;
use salient_core::systems::polynomial::{Polynomial, PolynomialSystem};
use salient_core::{Hamiltonian, HenonHeiles};

/// The classic systems `--system` names.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum NamedSystem {
    /// The FPU-β chain with fixed ends: --dof particles, quartic coupling --beta.
    FpuBeta,
}

/// The flags that choose the system.
#[derive(Args, Debug)]
#[command(group(clap::ArgGroup::new("polynomial_system").args(["potential", "system"])))]
pub struct SystemArgs {
    /// The potential V of H = ½|p|² + V(q): a polynomial in q1…qN (numbers, + - * /, integer
    /// powers with ^ or **, parentheses), e.g. "(q1^2 + q2^2)/2 + q1^2*q2 - q2^3/3"
    /// [default: Hénon–Heiles].
    #[arg(long)]
    pub potential: Option<String>,
    /// A classic system by name, expanded to its potential (see docs/methods.md).
    #[arg(long, value_enum)]
    pub system: Option<NamedSystem>,
    /// The quartic coupling β of --system fpu-beta.
    #[arg(long, requires = "system")]
    pub beta: Option<f64>,
    /// Degrees of freedom N of --potential or --system: 2, 3 or 8.
    #[arg(long, default_value_t = 2, requires = "polynomial_system")]
    pub dof: usize,
}

/// The whole initial point, for any number of degrees of freedom.
#[derive(Args, Debug)]
pub struct PointArgs {
    /// The whole initial point: q1,…,qN (with --p; the energy follows from them).
    #[arg(
        long,
        value_delimiter = ',',
        allow_hyphen_values = true,
        requires = "p"
    )]
    pub q: Option<Vec<f64>>,
    /// p1,…,pN of the initial point given by --q.
    #[arg(
        long,
        value_delimiter = ',',
        allow_hyphen_values = true,
        requires = "q"
    )]
    pub p: Option<Vec<f64>>,
}

/// A phase-space point (q, p) and its energy.
pub type Point = (Vec<f64>, Vec<f64>, f64);

impl PointArgs {
    /// (q, p) and its energy in `system`, checked, when --q and --p are given.
    pub fn of(&self, system: &System) -> CliResult<Option<Point>> {
        let (Some(q), Some(p)) = (&self.q, &self.p) else {
            return Ok(None);
        };
        let energy = system.whole_point(q, p)?;
        Ok(Some((q.clone(), p.clone(), energy)))
    }
}

/// A validated system: the built-in Hénon–Heiles, or a polynomial potential with its text.
#[derive(Clone, Debug)]
pub enum System {
    /// The built-in Hénon–Heiles, with its hand-fused path.
    HenonHeiles,
    /// A potential given as text (or expanded from a name).
    Polynomial {
        /// The text, as the run records it.
        text: String,
        /// The parsed potential.
        potential: Polynomial,
        /// The system compiled once for its size (boxed: it holds the compiled programs).
        compiled: Box<Compiled>,
    },
}

/// A polynomial system compiled for one of [`POLYNOMIAL_DOFS`].
#[derive(Clone, Debug)]
pub enum Compiled {
    /// 2 degrees of freedom.
    Two(PolynomialSystem<2>),
    /// 3 degrees of freedom.
    Three(PolynomialSystem<3>),
    /// A chain of 8.
    Eight(PolynomialSystem<8>),
}

impl SystemArgs {
    /// The system of --potential or --system in --dof coordinates (Hénon–Heiles without
    /// either).
    pub fn system(&self) -> CliResult<System> {
        let named = match self.system {
            Some(NamedSystem::FpuBeta) => {
                let beta = self.beta.ok_or_else(|| {
                    CliError::Usage(
                        "--system fpu-beta needs --beta, the quartic coupling (e.g. 1.5)".into(),
                    )
                })?;
                Some(fpu_beta(self.dof, finite("--beta", beta)?))
            }
            None => None,
        };
        let Some(text) = named.as_ref().or(self.potential.as_ref()) else {
            return Ok(System::HenonHeiles);
        };
        if !POLYNOMIAL_DOFS.contains(&self.dof) {
            return Err(CliError::Usage(format!(
                "--dof must be one of {POLYNOMIAL_DOFS:?} (got {})",
                self.dof
            )));
        }
        let potential = Polynomial::parse(text, self.dof)
            .map_err(|e| CliError::Usage(format!("--potential {text:?}: {e}")))?;
        let compiled = match self.dof {
            2 => Compiled::Two(PolynomialSystem::new(potential.clone())),
            3 => Compiled::Three(PolynomialSystem::new(potential.clone())),
            8 => Compiled::Eight(PolynomialSystem::new(potential.clone())),
            n => unreachable!("--dof {n} is not in POLYNOMIAL_DOFS"),
        };
        Ok(System::Polynomial {
            text: text.clone(),
            potential,
            compiled: Box::new(compiled),
        })
    }
}

impl System {
    /// Degrees of freedom.
    pub fn dof(&self) -> usize {
        match self {
            System::HenonHeiles => 2,
            System::Polynomial { potential, .. } => potential.dof(),
        }
    }

    /// V(q).
    pub fn potential_at(&self, q: &[f64]) -> f64 {
        match self {
            System::HenonHeiles => HenonHeiles.potential(&[q[0], q[1]]),
            System::Polynomial { potential, .. } => potential.eval(q),
        }
    }

    /// The potential's text (`None` for the built-in Hénon–Heiles).
    pub fn text(&self) -> Option<&str> {
        match self {
            System::HenonHeiles => None,
            System::Polynomial { text, .. } => Some(text),
        }
    }

    /// The name the outputs record: `henon-heiles` or `polynomial`.
    pub fn name(&self) -> &'static str {
        match self {
            System::HenonHeiles => HenonHeiles.name(),
            System::Polynomial { .. } => "polynomial",
        }
    }

    /// The point (q, p) at the energy `energy` on the section q1 = 0, p1 > 0 of a 2-dof system
    /// with q2, p2 given, or `None` where p1² ≤ 0 there. The smallest energy for which the
    /// point is on the section is V(0, q2) + p2²/2.
    pub fn on_section(&self, energy: f64, q2: f64, p2: f64) -> Option<(Vec<f64>, Vec<f64>)> {
        let radicand = 2.0 * (energy - self.potential_at(&[0.0, q2])) - p2 * p2;
        (radicand > 0.0).then(|| (vec![0.0, q2], vec![radicand.sqrt(), p2]))
    }

    /// The energy of the point (q, p) of --q and --p, checked: one finite number per degree of
    /// freedom each, and a finite energy.
    fn whole_point(&self, q: &[f64], p: &[f64]) -> CliResult<f64> {
        let dof = self.dof();
        for (flag, x) in [("--q", q), ("--p", p)] {
            if x.len() != dof {
                return Err(CliError::Usage(format!(
                    "{flag} needs {dof} comma-separated numbers, one per degree of freedom (got {})",
                    x.len()
                )));
            }
            for &c in x {
                finite(flag, c)?;
            }
        }
        let energy = 0.5 * p.iter().map(|x| x * x).sum::<f64>() + self.potential_at(q);
        if !energy.is_finite() {
            return Err(CliError::Usage(format!(
                "--q, --p: the energy at this point is not finite ({energy})"
            )));
        }
        Ok(energy)
    }

    /// One orbit from (q, p) with `run`, in the size this system is compiled for; `report`
    /// receives the result. The one place the single-orbit commands turn their system into a
    /// compiled run: Hénon–Heiles's own copy, or a polynomial system of one of
    /// [`POLYNOMIAL_DOFS`].
    #[allow(clippy::too_many_arguments)]
    pub fn run_orbit<R>(
        &self,
        run: &MethodRun,
        energy: f64,
        (q, p): (&[f64], &[f64]),
        config: &OrbitConfig,
        requests: &Requests,
        vectors: Vectors,
        report: &mut impl OrbitReport<R>,
    ) -> R {
        match self {
            System::HenonHeiles => report.report(&run_henon_heiles(
                run,
                energy,
                point(q, p),
                config,
                requests,
                vectors,
            )),
            System::Polynomial { compiled, .. } => {
                let args = (run, energy, config, requests, vectors);
                match &**compiled {
                    Compiled::Two(s) => report.report(&polynomial(s, args, point(q, p))),
                    Compiled::Three(s) => report.report(&polynomial(s, args, point(q, p))),
                    Compiled::Eight(s) => report.report(&polynomial(s, args, point(q, p))),
                }
            }
        }
    }
}

/// What a command does with an orbit's result, whatever its dimension.
pub trait OrbitReport<R> {
    /// Reports the result of an orbit of N degrees of freedom.
    fn report<const N: usize>(&mut self, result: &OrbitResult<N>) -> R;
}

/// The point as arrays of its dimension (the caller checked the lengths).
fn point<const N: usize>(q: &[f64], p: &[f64]) -> ([f64; N], [f64; N]) {
    let array = |x: &[f64]| x.try_into().expect("the point has one number per dof");
    (array(q), array(p))
}

/// An orbit in the polynomial system of N degrees of freedom.
fn polynomial<const N: usize>(
    system: &PolynomialSystem<N>,
    (run, energy, config, requests, vectors): (&MethodRun, f64, &OrbitConfig, &Requests, Vectors),
    start: ([f64; N], [f64; N]),
) -> OrbitResult<N>
where
    PolynomialSystem<N>: PolynomialRun<N>,
{
    system.run(run, energy, start, config, requests, vectors)
}
