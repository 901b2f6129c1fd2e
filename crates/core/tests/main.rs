//! The core's integration tests, one module per subject, built as one test binary (each
//! binary links and optimises the integrators anew, so one binary keeps the suite's build
//! short).

mod adaptive;
mod batch;
mod common;
mod dop853;
mod integrators;
mod orbits;
mod polynomial;
mod taylor;
