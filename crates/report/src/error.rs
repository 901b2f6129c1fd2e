//! The error type shared by every writer in this crate.

use std::fmt;

/// Why a report artefact could not be produced.
#[derive(Debug)]
pub enum ReportError {
    /// Creating or writing the output file failed.
    Io(std::io::Error),
    /// The plotting library failed, or the request was malformed (mismatched lengths, empty or
    /// inverted ranges, an unsupported output extension, an image too small to lay out, ...).
    Plot(String),
    /// There was nothing drawable; the text says what was missing.
    EmptyData(&'static str),
}

impl fmt::Display for ReportError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            ReportError::Io(e) => write!(f, "I/O error: {e}"),
            ReportError::Plot(msg) => write!(f, "plotting failed: {msg}"),
            ReportError::EmptyData(what) => write!(f, "nothing to plot: {what}"),
        }
    }
}

impl std::error::Error for ReportError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            ReportError::Io(e) => Some(e),
            ReportError::Plot(_) | ReportError::EmptyData(_) => None,
        }
    }
}

impl From<std::io::Error> for ReportError {
    fn from(e: std::io::Error) -> Self {
        ReportError::Io(e)
    }
}

/// Converts any plotters error into [`ReportError::Plot`].
pub(crate) fn plot_err<E: fmt::Display>(e: E) -> ReportError {
    ReportError::Plot(e.to_string())
}
