//! The numerical kernel of Salient, in modules by role. Each uses only those listed before it,
//! save the tangent-map methods' batched driver ([`tangent_map::batch`]), which also uses
//! [`section`] and [`orbit`]:
//!
//! - [`arith`]: the number types — f64, SIMD lanes of it, double-double; [`engine`]: choices
//!   that change speed, never results;
//! - [`phase`]: the state every method advances (a point and its deviation vectors);
//! - [`systems`]: H = ½|p|² + V(q) ([`Hamiltonian`]), Hénon–Heiles, polynomial potentials, and
//!   the Taylor recursions of a system;
//! - [`indicators`]: SALI, GALI_k, the maximal Lyapunov exponent, MEGNO, FLI;
//! - [`tangent_map`]: symplectic splitting schemes as data and the tangent-map method for one
//!   orbit ([`TangentMap`]) and for many in SIMD lanes;
//! - [`section`] and [`orbit`]: crossings of the section and the one-orbit driver;
//! - [`adaptive`]: DOP853, Taylor series, their one-orbit driver and their SIMD lanes;
//! - [`method`] and [`run`]: the methods by name and one entry point that runs any of them.
//!
//! No I/O, no threads, no async runtime: callers own all of that. The adaptive driver is an
//! `async fn` only as a coroutine — a lane of a SIMD batch suspends it at each step until the
//! batch has stepped ([`adaptive::lanes`]); it is polled by hand, never by an executor, and
//! waits on nothing else.

// Index loops over phase-space components mirror the formulas they implement.
#![allow(clippy::needless_range_loop)]
// The one crate with `unsafe` (the workspace denies it elsewhere): the SIMD drivers call the
// copies compiled for AVX-512 once the host is known to have it (`tangent_map::batch::Isa`),
// the lane types' loads and stores (`arith::real`), and the thread CPU clock
// (`engine::thread_cpu_ns`).
#![allow(unsafe_code)]

pub mod adaptive;
pub mod arith;
pub mod engine;
pub mod indicators;
pub mod method;
pub mod orbit;
pub mod phase;
pub mod run;
pub mod section;
pub mod systems;
pub mod tangent_map;

pub use method::Method;
pub use orbit::{Class, Deviation, OrbitConfig, OrbitResult, Requests, Status, Thresholds};
pub use phase::Phase;
pub use section::Crossing;
pub use systems::hamiltonian::{Hamiltonian, HenonHeiles};
pub use tangent_map::map::TangentMap;
pub use tangent_map::scheme::Scheme;
