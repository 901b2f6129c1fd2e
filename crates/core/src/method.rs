//! Integration methods by their CLI names.

use crate::scheme::Scheme;

/// A method for the orbit and its variational equations.
#[derive(Clone, Debug, PartialEq)]
pub enum Method {
    /// `tm-<scheme>`: the tangent-map method with a symplectic splitting scheme.
    TangentMap(Scheme),
}

impl Method {
    /// Parses a CLI name such as `tm-sbab2c`.
    pub fn parse(name: &str) -> Result<Method, String> {
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
        Scheme::all()
            .iter()
            .map(|s| format!("tm-{}", s.name))
            .collect()
    }

    pub fn name(&self) -> String {
        match self {
            Method::TangentMap(s) => format!("tm-{}", s.name),
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
        let e = Method::parse("tm-sbab9").unwrap_err();
        assert!(e.contains("tm-sbab2c"), "{e}");
        assert!(Method::parse("sbab2c").is_err());
    }
}
