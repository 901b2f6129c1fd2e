//! Integration methods by their CLI names.

use crate::scheme::Scheme;

/// The smallest tolerance DOP853 can honour in f64: below it the error estimate is round-off.
pub const DOP853_MIN_DELTA: f64 = 1e-14;

/// A method for the orbit and its variational equations.
#[derive(Clone, Debug, PartialEq)]
pub enum Method {
    /// `tm-<scheme>`: the tangent-map method with a symplectic splitting scheme.
    TangentMap(Scheme),
    /// `dop853`: Dormand–Prince 8(5,3) with rtol = atol = δ.
    Dop853,
}

impl Method {
    /// Parses a CLI name such as `tm-sbab2c` or `dop853`.
    pub fn parse(name: &str) -> Result<Method, String> {
        if name == "dop853" {
            return Ok(Method::Dop853);
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
        v.push("dop853".into());
        v
    }

    pub fn name(&self) -> String {
        match self {
            Method::TangentMap(s) => format!("tm-{}", s.name),
            Method::Dop853 => "dop853".into(),
        }
    }

    /// Whether the method's accuracy is set by a tolerance δ (rather than by the step τ).
    pub fn is_adaptive(&self) -> bool {
        matches!(self, Method::Dop853)
    }

    /// δ clamped to what the method can honour, with a warning when it was changed.
    pub fn honoured_delta(&self, delta: f64) -> (f64, Option<String>) {
        match self {
            Method::Dop853 if delta < DOP853_MIN_DELTA => (
                DOP853_MIN_DELTA,
                Some(format!(
                    "delta {delta:e} is below what dop853 can honour in double precision; using {DOP853_MIN_DELTA:e}"
                )),
            ),
            _ => (delta, None),
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
    }
}
