//! Checks, before SQLite touches a database file, that it and its folder can be written, and
//! creation of a new file readable by its owner only.
//!
//! SQLite opens a file it may not write read-only without a word, and a folder where it may not
//! create the WAL fails only at the first write; a coordinator would then take jobs and fail
//! to keep them. These checks make both fail at start instead.

use std::fs::OpenOptions;
use std::path::Path;

use crate::{Result, StoreError};

/// Refuses a database whose folder does not accept new files or whose existing files (the
/// database, its WAL and its shared-memory file) cannot be opened for writing; creates the
/// database file, owner-only, when it does not exist yet.
pub(crate) fn check_writable(path: &Path, label: &str) -> Result<()> {
    let folder = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    let file_name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .ok_or_else(|| StoreError::Access(format!("database {label}: not a file name")))?;
    let probe = folder.join(format!(".{file_name}.probe-{}", std::process::id()));
    OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(&probe)
        .and_then(|_| std::fs::remove_file(&probe))
        .map_err(|e| {
            StoreError::Access(format!(
                "database {label}: its folder {} does not accept new files ({e}); SQLite \
                 creates {file_name}-wal and {file_name}-shm there. Choose a writable folder",
                folder.display()
            ))
        })?;
    for suffix in ["", "-wal", "-shm"] {
        let file = folder.join(format!("{file_name}{suffix}"));
        match OpenOptions::new().read(true).write(true).open(&file) {
            Ok(_) => {}
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                if suffix.is_empty() {
                    create_owner_only(path, label)?;
                }
            }
            Err(e) => {
                return Err(StoreError::Access(format!(
                    "database {label}: {} cannot be opened for writing ({e}); make it \
                     writable by this user or choose another database",
                    file.display()
                )))
            }
        }
    }
    Ok(())
}

/// Creates an empty database file that only its owner may read or write: it holds every job's
/// spec and results. Another process creating it first is fine.
fn create_owner_only(path: &Path, label: &str) -> Result<()> {
    let mut options = OpenOptions::new();
    options.write(true).create_new(true);
    #[cfg(unix)]
    std::os::unix::fs::OpenOptionsExt::mode(&mut options, 0o600);
    match options.open(path) {
        Ok(_) => Ok(()),
        Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => Ok(()),
        Err(e) => Err(StoreError::Access(format!(
            "database {label}: cannot create it ({e})"
        ))),
    }
}
