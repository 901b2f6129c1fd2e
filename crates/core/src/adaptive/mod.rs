//! The adaptive methods: the one-orbit driver that steps an integrator to the renormalisation
//! times and locates crossings on its dense output ([`driver`]); DOP853 ([`dop853`]) and Taylor
//! series ([`taylor`]) in any number type ([`stepping`]); and many orbits at once in SIMD lanes
//! ([`lanes`]).

pub mod dop853;
pub mod driver;
pub mod lanes;
pub mod stepping;
pub mod taylor;
