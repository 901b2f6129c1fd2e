//! The one error type of the store.

use std::fmt;

/// What can go wrong behind the store's API.
#[derive(Debug)]
pub enum StoreError {
    /// SQLite refused a statement: I/O, a busy database past the timeout, a violated constraint
    /// (a report or counter for an unknown job fails its foreign key), …
    Sqlite(rusqlite::Error),
    /// The database is not one this build can use: its schema version is newer than the code's,
    /// it holds a job state this build does not know, or it cannot be put in WAL mode.
    Schema(String),
}

/// The store's result type.
pub type Result<T> = std::result::Result<T, StoreError>;

impl fmt::Display for StoreError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            StoreError::Sqlite(e) => write!(f, "store: SQLite error: {e}"),
            StoreError::Schema(msg) => write!(f, "store: {msg}"),
        }
    }
}

impl std::error::Error for StoreError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            StoreError::Sqlite(e) => Some(e),
            StoreError::Schema(_) => None,
        }
    }
}

impl From<rusqlite::Error> for StoreError {
    fn from(e: rusqlite::Error) -> Self {
        StoreError::Sqlite(e)
    }
}
