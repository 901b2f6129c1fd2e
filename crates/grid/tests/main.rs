//! The grid's integration tests, one module per subject, built as one test binary.

mod fast_pss;
mod spec_doc;
mod spec_fuzz;
