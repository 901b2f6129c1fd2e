//! Grids of initial conditions on the surface of section: geometry, tiles and canonical order
//! ([`geometry`]) on the system and section of [`surface`], the fast-PSS [`ledger`] that commits
//! orbit outcomes in canonical order, the tile [`executor`] that integrates cells on a rayon
//! pool, the classification counts ([`summary`]), job [`spec`]s parsed from text and validated,
//! and the process's CPU clock ([`cpu`]). No files, no networking.

pub mod cpu;
pub mod executor;
pub mod geometry;
pub mod ledger;
mod pages;
pub mod record;
pub mod spec;
pub mod summary;
pub mod surface;

pub use cpu::process_cpu_seconds;
pub use executor::{
    integrate_cells, run_embedded, run_embedded_forecast, run_embedded_resumed, takes_forecast,
    CellRun,
};
pub use geometry::{Grid, ScanOrder};
pub use ledger::{CellIndicators, Forecast, Label, Ledger, Mode, Outcome, OutcomeNews};
pub use summary::Counts;
pub use surface::{Coordinate, SectionSpec, Surface, SystemSpec};
