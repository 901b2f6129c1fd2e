//! Classification counts and percentages over the compatible cells.

use crate::geometry::Grid;
use crate::ledger::Ledger;
use salient_core::orbit::{Class, Status};
use std::collections::BTreeMap;

/// Cells per class (and per status for orbits without a class) over the compatible cells.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Counts {
    /// Cells labelled regular.
    pub regular: u64,
    /// Cells labelled sticky.
    pub sticky: u64,
    /// Cells labelled chaotic.
    pub chaotic: u64,
    /// Cells labelled by orbits that escaped or failed (no class).
    pub unclassified: u64,
    /// Of those, cells labelled by orbits that escaped (above the escape energy).
    pub escaped: u64,
    /// Compatible cells counted.
    pub compatible: u64,
    /// Labelled cells per orbit status.
    pub status: BTreeMap<&'static str, u64>,
}

impl Counts {
    /// Counts one compatible cell labelled with `class` and `status`.
    pub fn add(&mut self, class: Option<Class>, status: Status) {
        self.compatible += 1;
        match class {
            Some(Class::Regular) => self.regular += 1,
            Some(Class::Sticky) => self.sticky += 1,
            Some(Class::Chaotic) => self.chaotic += 1,
            None => self.unclassified += 1,
        }
        if status == Status::Escaped {
            self.escaped += 1;
        }
        *self.status.entry(status.as_str()).or_default() += 1;
    }

    /// Counts of a finished ledger.
    pub fn of(grid: &Grid, ledger: &Ledger) -> Counts {
        let mut c = Counts::default();
        for &cell in grid.canonical() {
            let l = ledger
                .label(cell)
                .expect("a finished ledger labels every compatible cell");
            c.add(l.class, l.status);
        }
        c
    }

    fn pct(&self, n: u64) -> f64 {
        if self.compatible == 0 {
            0.0
        } else {
            100.0 * n as f64 / self.compatible as f64
        }
    }

    /// (regular, sticky, chaotic) in percent of the compatible cells.
    pub fn percent(&self) -> (f64, f64, f64) {
        (
            self.pct(self.regular),
            self.pct(self.sticky),
            self.pct(self.chaotic),
        )
    }

    /// Unclassified cells in percent of the compatible cells.
    pub fn percent_unclassified(&self) -> f64 {
        self.pct(self.unclassified)
    }

    /// Escaped cells in percent of the compatible cells.
    pub fn percent_escaped(&self) -> f64 {
        self.pct(self.escaped)
    }

    /// Cells labelled by orbits with this status.
    pub fn with_status(&self, status: Status) -> u64 {
        self.status.get(status.as_str()).copied().unwrap_or(0)
    }
}
