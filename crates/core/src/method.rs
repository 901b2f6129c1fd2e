//! Integration methods by their CLI names, and the one registry of what the rest of Salient
//! needs to know about each: its order, the smallest tolerance it honours, and how the grid's
//! drivers run its orbits ([`MethodInfo`]). Adding a method is an entry here and its driver in
//! [`crate::run`].

use crate::adaptive::taylor::order_for;
use crate::tangent_map::scheme::Scheme;

/// The smallest tolerance DOP853 can honour in f64: below it the error estimate is round-off.
pub const DOP853_MIN_DELTA: f64 = 1e-14;
/// The smallest tolerance the f64 Taylor method can honour: the unit round-off.
pub const TAYLOR_MIN_DELTA: f64 = f64::EPSILON;
/// The smallest tolerance the double-double Taylor method can honour (~2⁻¹⁰⁴).
pub const TAYLOR_DD_MIN_DELTA: f64 = 1e-31;

/// f64 Taylor runs in SIMD lanes below this τ, one orbit per thread above it. Lanes make a step
/// cheaper per orbit but keep four orbits per thread in flight, and the fast-PSS rule drops
/// far more of their steps than one at a time; the more steps a crossing takes, the more the
/// cheaper step pays, so lanes win at τ = 0.1 and below and lose at τ = 0.5 (figures:
/// docs/performance.md). The same results either way (each lane computes what the scalar
/// driver does).
pub const F64_TAYLOR_LANES_BELOW_TAU: f64 = 0.25;

/// DOP853 runs in SIMD lanes below this τ, one orbit per thread above it: as for f64 Taylor,
/// the lanes' cheaper steps against the share of their steps that speculation drops. Lanes
/// win below τ = 0.1, break even at it and lose above; the lead shrinks at longer t_final, as
/// more of the orbits in flight are overtaken (figures: docs/performance.md).
pub const DOP853_LANES_BELOW_TAU: f64 = 0.1;

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

/// How a method's order is set.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Order {
    /// A fixed order (a splitting scheme's, DOP853's 8).
    Fixed(u32),
    /// The order Jorba & Zou's rule picks for the tolerance δ (Taylor's; [`order_for`]).
    JorbaZou,
}

/// How the grid's drivers run a method's orbits. The results are the same bits either way; the
/// choice is one of speed.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum LanePolicy {
    /// The batched tangent-map driver: as many lanes as the host's vectors and the run's mode
    /// take ([`crate::tangent_map::batch`]).
    Batched,
    /// An adaptive method: in SIMD lanes where τ is below `lanes_below_tau` (infinite: always),
    /// one orbit per thread above it; `wider_when_guided`: eight lanes on AVX-512 hosts where a
    /// forecast orders the feed ([`crate::run::feed_orbits_per_thread`]).
    Adaptive {
        /// The τ below which the method runs in lanes.
        lanes_below_tau: f64,
        /// Whether a forecast lets the method take a full AVX-512 register of lanes.
        wider_when_guided: bool,
    },
}

/// What Salient knows about a method, in one place.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MethodInfo {
    /// How its order is set.
    pub order: Order,
    /// The smallest tolerance it can honour and the arithmetic that sets that floor (`None`:
    /// its accuracy is set by the step τ, not by a tolerance).
    pub delta_floor: Option<(f64, &'static str)>,
    /// How the grid's drivers run its orbits.
    pub lanes: LanePolicy,
}

/// An adaptive method's entry in the registry.
struct Adaptive {
    method: Method,
    name: &'static str,
    info: MethodInfo,
}

/// The adaptive methods, in the order the CLI lists them.
static ADAPTIVE: [Adaptive; 3] = [
    Adaptive {
        method: Method::Dop853,
        name: "dop853",
        info: MethodInfo {
            order: Order::Fixed(8),
            delta_floor: Some((DOP853_MIN_DELTA, "double precision")),
            lanes: LanePolicy::Adaptive {
                lanes_below_tau: DOP853_LANES_BELOW_TAU,
                wider_when_guided: true,
            },
        },
    },
    // f64 Taylor and taylor-dd step no cheaper per orbit in 8 lanes than in 4.
    Adaptive {
        method: Method::Taylor,
        name: "taylor",
        info: MethodInfo {
            order: Order::JorbaZou,
            delta_floor: Some((TAYLOR_MIN_DELTA, "double precision")),
            lanes: LanePolicy::Adaptive {
                lanes_below_tau: F64_TAYLOR_LANES_BELOW_TAU,
                wider_when_guided: false,
            },
        },
    },
    // A double-double step costs enough that lanes win at every τ (figures:
    // docs/performance.md).
    Adaptive {
        method: Method::TaylorDd,
        name: "taylor-dd",
        info: MethodInfo {
            order: Order::JorbaZou,
            delta_floor: Some((TAYLOR_DD_MIN_DELTA, "double-double")),
            lanes: LanePolicy::Adaptive {
                lanes_below_tau: f64::INFINITY,
                wider_when_guided: false,
            },
        },
    },
];

impl Method {
    /// The registry's entry of an adaptive method.
    fn adaptive_entry(&self) -> Option<&'static Adaptive> {
        ADAPTIVE.iter().find(|a| a.method == *self)
    }

    /// What Salient knows about this method.
    pub fn info(&self) -> MethodInfo {
        match self {
            Method::TangentMap(s) => MethodInfo {
                order: Order::Fixed(s.order),
                delta_floor: None,
                lanes: LanePolicy::Batched,
            },
            adaptive => {
                adaptive
                    .adaptive_entry()
                    .expect("every adaptive method is registered")
                    .info
            }
        }
    }

    /// Parses a CLI name such as `tm-sbab2c` or `dop853`.
    pub fn parse(name: &str) -> Result<Method, String> {
        if let Some(a) = ADAPTIVE.iter().find(|a| a.name == name) {
            return Ok(a.method.clone());
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
        v.extend(ADAPTIVE.iter().map(|a| a.name.to_string()));
        v
    }

    /// The method's name as the CLI accepts it (`tm-<scheme>`, `dop853`, `taylor`, `taylor-dd`).
    pub fn name(&self) -> String {
        match self.adaptive_entry() {
            Some(a) => a.name.to_string(),
            None => match self {
                Method::TangentMap(s) => format!("tm-{}", s.name),
                _ => unreachable!("every adaptive method is registered"),
            },
        }
    }

    /// Whether the method's accuracy is set by a tolerance δ (rather than by the step τ).
    pub fn is_adaptive(&self) -> bool {
        self.info().delta_floor.is_some()
    }

    /// The method's order at tolerance `delta` (which only the [`Order::JorbaZou`] methods
    /// read).
    pub fn order(&self, delta: Option<f64>) -> u32 {
        match self.info().order {
            Order::Fixed(o) => o,
            Order::JorbaZou => {
                order_for(delta.expect("methods whose order follows δ carry a tolerance")) as u32
            }
        }
    }

    /// δ clamped to what the method can honour, with a warning when it was changed.
    pub fn honoured_delta(&self, delta: f64) -> (f64, Option<String>) {
        match self.info().delta_floor {
            Some((floor, arithmetic)) if delta < floor => {
                let warning = format!(
                    "delta {delta:e} is below what {} can honour in {arithmetic}; using {floor:e}",
                    self.name()
                );
                (floor, Some(warning))
            }
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
        assert_eq!(Method::Taylor.honoured_delta(1e-20).0, f64::EPSILON);
        assert_eq!(Method::TaylorDd.honoured_delta(1e-28), (1e-28, None));
        let (d, w) = Method::TaylorDd.honoured_delta(1e-33);
        assert_eq!(d, TAYLOR_DD_MIN_DELTA);
        assert!(w.unwrap().contains("double-double"));
        let sbab2c = Method::parse("tm-sbab2c").unwrap();
        assert_eq!(sbab2c.honoured_delta(1e-40), (1e-40, None));
    }

    #[test]
    fn the_registry_gives_each_method_its_order_and_lane_policy() {
        let order = |name: &str, delta| Method::parse(name).unwrap().order(delta);
        assert_eq!(order("tm-sbab2c", None), 4);
        assert_eq!(order("tm-srkn14a", None), 6);
        assert_eq!(order("dop853", Some(1e-9)), 8);
        assert_eq!(order("taylor", Some(1e-5)), 7);
        assert_eq!(order("taylor-dd", Some(1e-28)), 33);
        for n in Method::names() {
            let m = Method::parse(&n).unwrap();
            let batched = m.info().lanes == LanePolicy::Batched;
            assert_eq!(m.is_adaptive(), !batched, "{n}");
            assert_eq!(m.is_adaptive(), !n.starts_with("tm-"), "{n}");
        }
        let lanes_below = |m: Method| match m.info().lanes {
            LanePolicy::Adaptive {
                lanes_below_tau, ..
            } => lanes_below_tau,
            LanePolicy::Batched => panic!("adaptive"),
        };
        assert_eq!(lanes_below(Method::Taylor), F64_TAYLOR_LANES_BELOW_TAU);
        assert_eq!(lanes_below(Method::TaylorDd), f64::INFINITY);
    }
}
