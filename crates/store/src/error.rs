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
    /// The database's contents are damaged: SQLite's checks fail, or a stored outcome does
    /// not match its checksum. Nothing read from it is used.
    Damaged(String),
    /// The database or its folder cannot be written.
    Access(String),
}

impl StoreError {
    /// A damaged database: what is wrong and what the operator can do.
    pub(crate) fn damaged(label: &str, what: &str) -> StoreError {
        StoreError::Damaged(format!(
            "database {label} is damaged ({what}); nothing from it is served. Keep the file \
             for inspection and restore it from a backup, or move it aside and start on a new \
             database (jobs in it must then be submitted again)"
        ))
    }
}

/// The store's result type.
pub type Result<T> = std::result::Result<T, StoreError>;

impl fmt::Display for StoreError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            StoreError::Sqlite(e) => write!(f, "store: SQLite error: {e}"),
            StoreError::Schema(msg) | StoreError::Damaged(msg) | StoreError::Access(msg) => {
                write!(f, "store: {msg}")
            }
        }
    }
}

impl std::error::Error for StoreError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            StoreError::Sqlite(e) => Some(e),
            StoreError::Schema(_) | StoreError::Damaged(_) | StoreError::Access(_) => None,
        }
    }
}

impl From<rusqlite::Error> for StoreError {
    fn from(e: rusqlite::Error) -> Self {
        StoreError::Sqlite(e)
    }
}
