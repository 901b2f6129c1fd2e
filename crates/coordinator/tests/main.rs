//! The coordinator's integration tests, one module per subject, built as one test binary.

mod scheduler;
mod wire_fuzz;
