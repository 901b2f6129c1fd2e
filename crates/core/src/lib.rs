//! The numerical kernel of Salient: Hamiltonians H = ½|p|² + V(q) ([`Hamiltonian`],
//! [`HenonHeiles`]), symplectic splitting schemes as data ([`Scheme`]), the tangent-map method
//! that advances an orbit and its deviation vectors together ([`TangentMap`], and
//! [`batch::integrate_feed`] for several orbits in SIMD lanes), chaos indicators (SALI, GALI_k, the
//! maximal Lyapunov exponent), section crossings, the one-orbit drivers ([`orbit`],
//! [`adaptive`]) and adaptive orbits in SIMD lanes ([`lanes`]).
//!
//! No I/O, no threads, no async runtime: callers own all of that. The adaptive driver is an
//! `async fn` only as a coroutine — a lane of a SIMD batch suspends it at each step until the
//! batch has stepped ([`lanes`]); it is polled by hand, never by an executor, and waits on
//! nothing else.

// Index loops over phase-space components mirror the formulas they implement.
#![allow(clippy::needless_range_loop)]
// The one crate with `unsafe` (the workspace denies it elsewhere): the SIMD drivers call the
// copies compiled for AVX-512 once the host is known to have it (`batch::Isa`), the lane
// types' loads and stores (`real`), and the thread CPU clock (`engine::thread_cpu_ns`).
#![allow(unsafe_code)]

pub mod adaptive;
pub mod batch;
pub mod dd;
pub mod dop853;
pub mod engine;
pub mod hamiltonian;
pub mod indicators;
pub mod lanes;
pub mod method;
pub mod orbit;
pub mod polynomial;
pub mod real;
pub mod run;
pub mod scheme;
pub mod section;
pub mod stepping;
pub mod tangent;
pub mod taylor;

pub use hamiltonian::{Hamiltonian, HenonHeiles};
pub use method::Method;
pub use orbit::{Class, Deviation, OrbitConfig, OrbitResult, Requests, Status, Thresholds};
pub use scheme::Scheme;
pub use section::Crossing;
pub use tangent::{Phase, TangentMap};
