//! Errors the CLI reports: bad input (exit 2, one line naming the field and the allowed range)
//! and failures while running (exit 1).

use std::fmt;

#[derive(Debug)]
pub enum CliError {
    /// The user's input is out of range; nothing was run or written.
    Usage(String),
    /// Something failed while running (I/O, plotting).
    Runtime(String),
}

impl CliError {
    pub fn exit_code(&self) -> u8 {
        match self {
            CliError::Usage(_) => 2,
            CliError::Runtime(_) => 1,
        }
    }
}

impl fmt::Display for CliError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            CliError::Usage(m) | CliError::Runtime(m) => f.write_str(m),
        }
    }
}

impl std::error::Error for CliError {}

pub type CliResult<T> = Result<T, CliError>;

/// Checks that `flag`'s value is finite and strictly positive.
pub fn positive(flag: &str, v: f64) -> CliResult<f64> {
    if v.is_finite() && v > 0.0 {
        Ok(v)
    } else {
        Err(CliError::Usage(format!(
            "{flag} must be a finite number > 0 (got {v})"
        )))
    }
}

/// Checks that `flag`'s value is finite.
pub fn finite(flag: &str, v: f64) -> CliResult<f64> {
    if v.is_finite() {
        Ok(v)
    } else {
        Err(CliError::Usage(format!(
            "{flag} must be a finite number (got {v})"
        )))
    }
}

pub fn runtime(context: &str, e: impl fmt::Display) -> CliError {
    CliError::Runtime(format!("{context}: {e}"))
}
