//! The system a grid runs on and its surface of section: Hénon–Heiles on q1 = 0 with axes
//! (q2, p2), or a polynomial potential in 2 or 3 degrees of freedom on any plane q_k = 0 with
//! two axes chosen among the other coordinates and the rest held fixed.
//!
//! The core's drivers detect crossings of q1 = 0 upwards and take p1 > 0 from the energy, so a
//! section on q_k = 0 runs on the system with q1 and q_k exchanged ([`Polynomial::swapped`]):
//! the integrators, the crossing detection and taylor-dd's energy-exact momentum need no other
//! plane.

use salient_core::section::{on_section, p1_squared};
use salient_core::systems::polynomial::{Polynomial, PolynomialSystem};
use salient_core::HenonHeiles;
use std::fmt;
use std::sync::Arc;

/// A coordinate of phase space: q_{k+1} or p_{k+1} (`k` counts from 0).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Coordinate {
    /// A position.
    Q(usize),
    /// A momentum.
    P(usize),
}

impl Coordinate {
    /// Reads "q1" … "p3" in `dof` degrees of freedom.
    pub fn parse(name: &str, dof: usize) -> Option<Coordinate> {
        let (kind, k) = name.split_at_checked(1)?;
        let k: usize = k.parse().ok().filter(|&k| (1..=dof).contains(&k))?;
        if k.to_string() != name[1..] {
            return None;
        }
        match kind {
            "q" => Some(Coordinate::Q(k - 1)),
            "p" => Some(Coordinate::P(k - 1)),
            _ => None,
        }
    }

    /// Its name, "q1" … "pN".
    pub fn name(self) -> String {
        match self {
            Coordinate::Q(k) => format!("q{}", k + 1),
            Coordinate::P(k) => format!("p{}", k + 1),
        }
    }

    /// Its name for a figure, "q₂".
    pub fn label(self) -> String {
        let (letter, k) = match self {
            Coordinate::Q(k) => ('q', k + 1),
            Coordinate::P(k) => ('p', k + 1),
        };
        let subscript = |d: char| char::from_u32(0x2080 + d.to_digit(10).unwrap_or(0)).unwrap_or(d);
        std::iter::once(letter)
            .chain(k.to_string().chars().map(subscript))
            .collect()
    }

    /// The degree of freedom it belongs to (from 0).
    pub fn index(self) -> usize {
        match self {
            Coordinate::Q(k) | Coordinate::P(k) => k,
        }
    }

    /// The same coordinate after q1 and q_{plane+1} (and their momenta) are exchanged.
    fn exchanged(self, plane: usize) -> Coordinate {
        let swap = |k: usize| match k {
            k if k == plane => 0,
            0 => plane,
            k => k,
        };
        match self {
            Coordinate::Q(k) => Coordinate::Q(swap(k)),
            Coordinate::P(k) => Coordinate::P(swap(k)),
        }
    }
}

/// The system of a job, as its spec gives it.
#[derive(Clone, Debug, PartialEq)]
pub enum SystemSpec {
    /// The built-in Hénon–Heiles system (its hand-fused kernels).
    HenonHeiles,
    /// H = ½|p|² + V(q) with V the polynomial `potential` in q1…q`dof`.
    Polynomial {
        /// Degrees of freedom (2 or 3 on a grid).
        dof: usize,
        /// The potential as written.
        potential: String,
    },
}

impl SystemSpec {
    /// Degrees of freedom.
    pub fn dof(&self) -> usize {
        match self {
            SystemSpec::HenonHeiles => 2,
            SystemSpec::Polynomial { dof, .. } => *dof,
        }
    }

    /// The spec's name of the kind: "henon-heiles" or "polynomial".
    pub fn kind(&self) -> &'static str {
        match self {
            SystemSpec::HenonHeiles => "henon-heiles",
            SystemSpec::Polynomial { .. } => "polynomial",
        }
    }
}

/// The surface of section: the plane q_{plane+1} = 0 crossed with p_{plane+1} > 0, the two
/// coordinates the grid spans and the values of the others.
#[derive(Clone, Debug, PartialEq)]
pub struct SectionSpec {
    /// The degree of freedom whose position is 0 on the section (from 0).
    pub plane: usize,
    /// The grid's axes: cell (i, j) has i along `axes[0]`, j along `axes[1]`.
    pub axes: [Coordinate; 2],
    /// Every other coordinate but the plane's pair, with its value.
    pub fixed: Vec<(Coordinate, f64)>,
}

impl SectionSpec {
    /// Hénon–Heiles' section: q1 = 0, axes (q2, p2).
    pub fn henon_heiles() -> SectionSpec {
        SectionSpec {
            plane: 0,
            axes: [Coordinate::Q(1), Coordinate::P(1)],
            fixed: Vec::new(),
        }
    }

    /// The names of the axes ("q2", "p2").
    pub fn axis_names(&self) -> [String; 2] {
        self.axes.map(Coordinate::name)
    }
}

/// A system compiled for the integrators, in the section's exchanged coordinates.
#[derive(Debug)]
pub enum Compiled {
    /// The built-in Hénon–Heiles system.
    HenonHeiles(HenonHeiles),
    /// A polynomial system in 2 degrees of freedom.
    Plane(PolynomialSystem<2>),
    /// A polynomial system in 3 degrees of freedom.
    Space(PolynomialSystem<3>),
}

/// Why a system and section cannot make a surface (the message names what is wrong; the spec
/// adds the field).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SurfaceError {
    /// Character position in the potential, for a potential that does not parse.
    pub at: Option<usize>,
    /// What is wrong.
    pub message: String,
}

impl fmt::Display for SurfaceError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.message)
    }
}

/// A system with its section: what a grid's cells start from.
pub struct Surface {
    system: SystemSpec,
    section: SectionSpec,
    compiled: Compiled,
    /// The axes' names and figure labels.
    names: [String; 2],
    labels: [String; 2],
}

impl PartialEq for Surface {
    fn eq(&self, other: &Surface) -> bool {
        self.system == other.system && self.section == other.section
    }
}

impl fmt::Debug for Surface {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Surface")
            .field("system", &self.system)
            .field("section", &self.section)
            .finish()
    }
}

impl Surface {
    /// Hénon–Heiles on q1 = 0 with axes (q2, p2).
    pub fn henon_heiles() -> Arc<Surface> {
        Surface::assemble(
            SystemSpec::HenonHeiles,
            SectionSpec::henon_heiles(),
            Compiled::HenonHeiles(HenonHeiles),
        )
    }

    /// The surface of `system` on `section`: the potential parsed and compiled with the
    /// plane's coordinate first.
    pub fn new(system: SystemSpec, section: SectionSpec) -> Result<Arc<Surface>, SurfaceError> {
        let compiled = match &system {
            SystemSpec::HenonHeiles => {
                if section != SectionSpec::henon_heiles() {
                    return Err(SurfaceError {
                        at: None,
                        message:
                            "the henon-heiles system takes the section q1 = 0 with axes q2, p2"
                                .into(),
                    });
                }
                Compiled::HenonHeiles(HenonHeiles)
            }
            SystemSpec::Polynomial { dof, potential } => {
                let v = Polynomial::parse(potential, *dof).map_err(|e| SurfaceError {
                    at: Some(e.at),
                    message: e.message,
                })?;
                let v = v.swapped(0, section.plane);
                match dof {
                    2 => Compiled::Plane(PolynomialSystem::new(v)),
                    3 => Compiled::Space(PolynomialSystem::new(v)),
                    _ => {
                        return Err(SurfaceError {
                            at: None,
                            message: format!("grids run in 2 or 3 degrees of freedom, not {dof}"),
                        })
                    }
                }
            }
        };
        Ok(Surface::assemble(system, section, compiled))
    }

    fn assemble(system: SystemSpec, section: SectionSpec, compiled: Compiled) -> Arc<Surface> {
        Arc::new(Surface {
            names: section.axis_names(),
            labels: section.axes.map(Coordinate::label),
            system,
            section,
            compiled,
        })
    }

    /// The axes' names, "q2" and "p2" for Hénon–Heiles.
    pub fn axis_names(&self) -> [&str; 2] {
        [&self.names[0], &self.names[1]]
    }

    /// The axes' labels for figures, "q₂" and "p₂" for Hénon–Heiles.
    pub fn axis_labels(&self) -> [&str; 2] {
        [&self.labels[0], &self.labels[1]]
    }

    /// The system as the spec gives it.
    pub fn system(&self) -> &SystemSpec {
        &self.system
    }

    /// The section.
    pub fn section(&self) -> &SectionSpec {
        &self.section
    }

    /// The compiled system the integrators run on.
    pub fn compiled(&self) -> &Compiled {
        &self.compiled
    }

    /// The other coordinates of the point at (x, y) on the axes, in the exchanged system:
    /// q2…qN and p2…pN (up to 2 each; unused entries 0).
    fn rest(&self, x: f64, y: f64) -> ([f64; 2], [f64; 2]) {
        let (mut q, mut p) = ([0.0; 2], [0.0; 2]);
        let values = self.section.axes.iter().zip([x, y]);
        let fixed = self.section.fixed.iter().map(|(c, v)| (c, *v));
        for (c, v) in values.chain(fixed) {
            match c.exchanged(self.section.plane) {
                Coordinate::Q(k) => q[k - 1] = v,
                Coordinate::P(k) => p[k - 1] = v,
            }
        }
        (q, p)
    }

    /// p² of the plane's momentum at (x, y) on the axes: 2(E − V) less the other momenta
    /// squared. The point lies on the section where it is > 0.
    pub fn momentum_squared(&self, energy: f64, x: f64, y: f64) -> f64 {
        let (q, p) = self.rest(x, y);
        match &self.compiled {
            Compiled::HenonHeiles(h) => p1_squared(h, energy, &[0.0, q[0]], &[0.0, p[0]]),
            Compiled::Plane(s) => p1_squared(s, energy, &[0.0, q[0]], &[0.0, p[0]]),
            Compiled::Space(s) => p1_squared(s, energy, &[0.0, q[0], q[1]], &[0.0, p[0], p[1]]),
        }
    }

    /// The phase-space point at (x, y) on the axes, in the exchanged system (q1 = 0, p1 > 0
    /// from the energy), for a system of `N` degrees of freedom; `None` off the section.
    pub fn start<const N: usize>(
        &self,
        energy: f64,
        x: f64,
        y: f64,
    ) -> Option<([f64; N], [f64; N])> {
        let (q, p) = self.rest(x, y);
        let point = match &self.compiled {
            Compiled::HenonHeiles(h) => on_section::<_, 2>(h, energy, &q[..1], &p[..1]).map(widen),
            Compiled::Plane(s) => on_section::<_, 2>(s, energy, &q[..1], &p[..1]).map(widen),
            Compiled::Space(s) => on_section::<_, 3>(s, energy, &q, &p).map(widen),
        };
        point
            .ok()
            .map(|w| w.expect("a start asked in the system's own degrees of freedom"))
    }
}

/// A point of M degrees of freedom as one of N, where they are equal.
fn widen<const M: usize, const N: usize>(
    (q, p): ([f64; M], [f64; M]),
) -> Option<([f64; N], [f64; N])> {
    Some((q.as_slice().try_into().ok()?, p.as_slice().try_into().ok()?))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn polynomial(dof: usize, potential: &str, section: SectionSpec) -> Arc<Surface> {
        let system = SystemSpec::Polynomial {
            dof,
            potential: potential.into(),
        };
        Surface::new(system, section).unwrap()
    }

    const HH: &str = "(q1^2 + q2^2)/2 + q1^2*q2 - q2^3/3";

    /// Hénon–Heiles as text on q1 = 0 starts every cell where the built-in does, to the bit.
    #[test]
    fn henon_heiles_as_text_starts_where_the_built_in_does() {
        let text = polynomial(2, HH, SectionSpec::henon_heiles());
        let built_in = Surface::henon_heiles();
        for (x, y) in [(0.1, 0.2), (-0.3, 0.05), (0.5, -0.1), (0.9, 0.4)] {
            let a = built_in.momentum_squared(0.125, x, y);
            assert_eq!(a, text.momentum_squared(0.125, x, y));
            assert_eq!(
                built_in.start::<2>(0.125, x, y),
                text.start::<2>(0.125, x, y)
            );
            assert_eq!(built_in.start::<2>(0.125, x, y).is_some(), a > 0.0);
        }
    }

    /// A section on q2 = 0 is the section on q1 = 0 of the exchanged system: its axes (q1, p1)
    /// land on the exchanged q2, p2, and the plane's momentum comes from the energy.
    #[test]
    fn another_plane_runs_as_q1_of_the_exchanged_system() {
        let section = SectionSpec {
            plane: 1,
            axes: [Coordinate::Q(0), Coordinate::P(0)],
            fixed: Vec::new(),
        };
        let s = polynomial(2, "q1^2/2 + 2*q2^2 + q1*q2^2", section);
        let (q, p) = s.start::<2>(1.0, 0.3, -0.4).unwrap();
        assert_eq!((q[0], q[1], p[1]), (0.0, 0.3, -0.4));
        // V(q1 = 0.3, q2 = 0) = 0.045; p2² = 2(1 − 0.045) − 0.16.
        assert!((p[0] * p[0] - (2.0 * (1.0 - 0.045) - 0.16)).abs() < 1e-14);
    }

    /// In 3 dof the fixed coordinates take their values, the axes theirs.
    #[test]
    fn fixed_coordinates_hold_their_values() {
        let section = SectionSpec {
            plane: 0,
            axes: [Coordinate::Q(2), Coordinate::P(1)],
            fixed: vec![(Coordinate::Q(1), 0.1), (Coordinate::P(2), -0.2)],
        };
        let s = polynomial(3, "(q1^2 + q2^2 + q3^2)/2", section);
        let (q, p) = s.start::<3>(1.0, 0.3, 0.4).unwrap();
        assert_eq!((q[0], q[1], q[2]), (0.0, 0.1, 0.3));
        assert_eq!((p[1], p[2]), (0.4, -0.2));
        let p1_sq = 2.0 - (0.01 + 0.09) - 0.16 - 0.04;
        assert!((p[0] * p[0] - p1_sq).abs() < 1e-14);
        assert!(s.start::<3>(1.0, 2.0, 0.0).is_none());
    }

    #[test]
    fn coordinates_read_by_name() {
        assert_eq!(Coordinate::parse("q3", 3), Some(Coordinate::Q(2)));
        assert_eq!(Coordinate::parse("p1", 2), Some(Coordinate::P(0)));
        for bad in ["q3", "q0", "x1", "q01", "q", "", "p+1"] {
            assert_eq!(Coordinate::parse(bad, 2), None, "{bad}");
        }
        assert_eq!(Coordinate::Q(2).name(), "q3");
        assert_eq!(Coordinate::P(11).label(), "p₁₂");
    }
}
