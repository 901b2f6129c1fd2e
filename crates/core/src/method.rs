//! Integration methods by their CLI names.

use crate::scheme::Scheme;

/// The smallest tolerance DOP853 can honour in f64: below it the error estimate is round-off.
pub const DOP853_MIN_DELTA: f64 = 1e-14;
/// The smallest tolerance the f64 Taylor method can honour: the unit round-off.
pub const TAYLOR_MIN_DELTA: f64 = f64::EPSILON;
/// The smallest tolerance the double-double Taylor method can honour (~2⁻¹⁰⁴).
pub const TAYLOR_DD_MIN_DELTA: f64 = 1e-31;

/// A method for the orbit and its variational equations.
#[derive(Clone, Debug, PartialEq)]
pub enum Method {
    /// `tm-<scheme>`: the tangent-map method with a symplectic splitting scheme.
    TangentMap(Scheme),
    /// `dop853`: Dormand–Prince 8(5,3) with rtol = atol = δ.
    Dop853,
    /// `taylor`: Taylor series in f64, order and step from δ (Jorba–Zou).
    Taylor,
    /// `taylor-dd`: the same in double-double arithmetic, for δ down to 1e-31.
    TaylorDd,
}

impl Method {
    /// Parses a CLI name such as `tm-sbab2c` or `dop853`.
    pub fn parse(name: &str) -> Result<Method, String> {
        match name {
            "dop853" => return Ok(Method::Dop853),
            "taylor" => return Ok(Method::Taylor),
            "taylor-dd" => return Ok(Method::TaylorDd),
            _ => {}
        }
        if let Some(s) = name.strip_prefix("tm-").and_then(Scheme::by_name) {
            return Ok(Method::TangentMap(s));
        }
        Err(format!(
            "unknown method '{name}' (allowed: {})",
            Method::names().join(", ")
        ))
    }

    /// Every method name the CLI accepts.
    pub fn names() -> Vec<String> {
        let mut v: Vec<String> = Scheme::all()
            .iter()
            .map(|s| format!("tm-{}", s.name))
            .collect();
        v.extend(["dop853", "taylor", "taylor-dd"].map(String::from));
        v
    }

    /// The method's name as the CLI accepts it (`tm-<scheme>`, `dop853`, `taylor`, `taylor-dd`).
    pub fn name(&self) -> String {
        match self {
            Method::TangentMap(s) => format!("tm-{}", s.name),
            Method::Dop853 => "dop853".into(),
            Method::Taylor => "taylor".into(),
            Method::TaylorDd => "taylor-dd".into(),
        }
    }

    /// Whether the method's accuracy is set by a tolerance δ (rather than by the step τ).
    pub fn is_adaptive(&self) -> bool {
        !matches!(self, Method::TangentMap(_))
    }

    /// δ clamped to what the method can honour, with a warning when it was changed.
    pub fn honoured_delta(&self, delta: f64) -> (f64, Option<String>) {
        let floor = match self {
            Method::TangentMap(_) => 0.0,
            Method::Dop853 => DOP853_MIN_DELTA,
            Method::Taylor => TAYLOR_MIN_DELTA,
            Method::TaylorDd => TAYLOR_DD_MIN_DELTA,
        };
        if delta < floor {
            let why = if *self == Method::TaylorDd {
                "double-double"
            } else {
                "double precision"
            };
            let warning = format!(
                "delta {delta:e} is below what {} can honour in {why}; using {floor:e}",
                self.name()
            );
            (floor, Some(warning))
        } else {
            (delta, None)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_round_trip_and_unknown_names_are_refused() {
        for n in Method::names() {
            assert_eq!(Method::parse(&n).unwrap().name(), n);
        }
        assert!(Method::names().contains(&"tm-sbab2c".to_string()));
        assert!(Method::names().contains(&"tm-srkn14a".to_string()));
        assert!(Method::names().contains(&"dop853".to_string()));
        let e = Method::parse("tm-sbab9").unwrap_err();
        assert!(e.contains("tm-sbab2c"), "{e}");
        assert!(Method::parse("sbab2c").is_err());
    }

    #[test]
    fn tolerances_below_double_precision_are_clamped_with_a_warning() {
        let (d, w) = Method::Dop853.honoured_delta(1e-16);
        assert_eq!(d, DOP853_MIN_DELTA);
        assert!(w.unwrap().contains("1e-16"));
        assert_eq!(Method::Dop853.honoured_delta(1e-10), (1e-10, None));
        assert_eq!(Method::Taylor.honoured_delta(1e-20).0, f64::EPSILON);
        assert_eq!(Method::TaylorDd.honoured_delta(1e-28), (1e-28, None));
    }
}
