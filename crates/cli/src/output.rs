//! Output folders that change all at once: files are written into a hidden staging folder
//! inside the output folder and moved into place (renamed) only when every one of them is
//! complete. A run that fails, or is stopped, leaves the output folder as it was: no partial
//! file beside an older run's table that would read as a success.

use std::path::{Path, PathBuf};

use crate::usage::{runtime, CliError, CliResult};
use salient_report::Table;

/// The prefix of staging folders; a folder left by a killed process is recognisable by it.
const STAGING_PREFIX: &str = ".salient-partial-";

/// An output folder being filled. Write under [`Staged::path`], then [`Staged::publish`];
/// dropped unpublished, the staging folder and everything in it are removed.
pub struct Staged {
    out: PathBuf,
    stage: PathBuf,
    published: bool,
}

impl Staged {
    /// Creates `out` if needed and its staging folder. Creating the staging folder proves the
    /// output folder writable before any computing starts; `flag` names the option in the
    /// message when it is not (exit 2).
    pub fn begin(out: &Path, flag: &str) -> CliResult<Staged> {
        let refuse = |e: std::io::Error| {
            CliError::Usage(format!(
                "{flag} {}: cannot write there ({e}); nothing was computed",
                out.display()
            ))
        };
        std::fs::create_dir_all(out).map_err(refuse)?;
        remove_abandoned_stages(out);
        let stage = out.join(format!("{STAGING_PREFIX}{}", std::process::id()));
        // A folder of the same name is a leftover of an earlier process with this pid.
        if stage.exists() {
            std::fs::remove_dir_all(&stage).map_err(refuse)?;
        }
        std::fs::create_dir(&stage).map_err(refuse)?;
        // Creating a folder needs write permission on `out`; writing a file needs the file
        // system to accept data, which a read-only mount refuses only here.
        std::fs::write(stage.join(".probe"), b"")
            .and_then(|()| std::fs::remove_file(stage.join(".probe")))
            .map_err(refuse)?;
        Ok(Staged {
            out: out.to_path_buf(),
            stage,
            published: false,
        })
    }

    /// Where the files go until they are published.
    pub fn path(&self) -> &Path {
        &self.stage
    }

    /// Moves every staged file to the same place under the output folder, replacing older
    /// files of the same names, and removes the staging folder. Files in subfolders go first
    /// and files at the top (the tables that say a sweep finished) last, after the older
    /// top-level files they replace were removed: a process killed in between leaves no
    /// finished-looking table beside a mix of runs.
    pub fn publish(mut self) -> CliResult<()> {
        let top = list(&self.stage)?;
        for (name, is_dir) in &top {
            if !is_dir {
                remove_if_present(&self.out.join(name))?;
            }
        }
        for (name, is_dir) in &top {
            if *is_dir {
                move_tree(&self.stage.join(name), &self.out.join(name))?;
            }
        }
        for (name, is_dir) in &top {
            if !is_dir {
                move_file(&self.stage.join(name), &self.out.join(name))?;
            }
        }
        std::fs::remove_dir_all(&self.stage)
            .map_err(|e| runtime(&format!("removing {}", self.stage.display()), e))?;
        self.published = true;
        Ok(())
    }
}

/// Moves the folders staged in `stage` (finished runs) into `out` and removes `stage` with
/// whatever else it holds: for a process stopped by a signal, which keeps what it finished
/// but writes no tables (they would say the sweep finished).
pub fn publish_folders(stage: &Path, out: &Path) -> CliResult<()> {
    for (name, is_dir) in list(stage)? {
        if is_dir {
            move_tree(&stage.join(&name), &out.join(&name))?;
        }
    }
    std::fs::remove_dir_all(stage).map_err(|e| runtime(&format!("removing {}", stage.display()), e))
}

impl Drop for Staged {
    fn drop(&mut self) {
        if !self.published {
            let _ = std::fs::remove_dir_all(&self.stage);
        }
    }
}

/// Removes the staging folders that processes killed before they could clean up left in
/// `out` (Ctrl-C, SIGKILL): those whose process is gone. Where the system does not tell which
/// processes run (no `/proc`), they stay; they are hidden and never read.
fn remove_abandoned_stages(out: &Path) {
    if !Path::new("/proc/self").exists() {
        return;
    }
    let Ok(entries) = std::fs::read_dir(out) else {
        return;
    };
    for entry in entries.flatten() {
        let name = entry.file_name().to_string_lossy().into_owned();
        let Some(pid) = name.strip_prefix(STAGING_PREFIX) else {
            continue;
        };
        let alive = pid
            .parse::<u32>()
            .map_or(true, |pid| Path::new(&format!("/proc/{pid}")).exists());
        if !alive {
            let _ = std::fs::remove_dir_all(entry.path());
        }
    }
}

/// The entries of a folder as (name, is a folder), sorted by name so publishing is
/// deterministic.
fn list(dir: &Path) -> CliResult<Vec<(std::ffi::OsString, bool)>> {
    let read = |e| runtime(&format!("reading {}", dir.display()), e);
    let mut entries = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(read)? {
        let entry = entry.map_err(read)?;
        let is_dir = entry.file_type().map_err(read)?.is_dir();
        entries.push((entry.file_name(), is_dir));
    }
    entries.sort();
    Ok(entries)
}

fn move_tree(from: &Path, to: &Path) -> CliResult<()> {
    std::fs::create_dir_all(to).map_err(|e| runtime(&format!("creating {}", to.display()), e))?;
    for (name, is_dir) in list(from)? {
        if is_dir {
            move_tree(&from.join(&name), &to.join(&name))?;
        } else {
            move_file(&from.join(&name), &to.join(&name))?;
        }
    }
    Ok(())
}

fn move_file(from: &Path, to: &Path) -> CliResult<()> {
    std::fs::rename(from, to).map_err(|e| runtime(&format!("moving {}", to.display()), e))
}

fn remove_if_present(path: &Path) -> CliResult<()> {
    match std::fs::remove_file(path) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
            Err(runtime(&format!("removing {}", path.display()), e))
        }
        _ => Ok(()),
    }
}

/// Writes `STEM.md` and `STEM.csv` (the table) and `STEM.json` (the summary) into `dir`: the
/// three files every table-making command leaves.
pub fn write_tables(
    dir: &Path,
    stem: &str,
    table: &Table,
    summary: &serde_json::Value,
) -> CliResult<()> {
    let write = |ext: &str, text: String| {
        let path = dir.join(format!("{stem}.{ext}"));
        std::fs::write(&path, text).map_err(|e| runtime(&format!("writing {}", path.display()), e))
    };
    write("md", table.to_markdown())?;
    write("csv", table.to_csv())?;
    write(
        "json",
        serde_json::to_string_pretty(summary).expect("JSON") + "\n",
    )
}

/// Prints a table-making command's result: its summary as one JSON object (`--json`), or the
/// table and, when it wrote them, where its `files` went.
pub fn print_result(
    json: bool,
    summary: &serde_json::Value,
    table: &Table,
    out: Option<&Path>,
    files: &str,
) {
    if json {
        println!("{summary}");
    } else {
        print!("{}", table.to_markdown());
        if let Some(dir) = out {
            println!("wrote {}/{files}", dir.display());
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scratch(name: &str) -> PathBuf {
        let dir =
            std::env::temp_dir().join(format!("salient-output-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        dir
    }

    #[test]
    fn published_files_replace_older_ones_and_the_stage_is_gone() {
        let out = scratch("publish");
        std::fs::create_dir_all(out.join("run-a")).unwrap();
        std::fs::write(out.join("table.md"), "old").unwrap();
        std::fs::write(out.join("run-a/cells.csv"), "old").unwrap();
        let staged = Staged::begin(&out, "--out").unwrap();
        std::fs::create_dir_all(staged.path().join("run-a")).unwrap();
        std::fs::write(staged.path().join("table.md"), "new").unwrap();
        std::fs::write(staged.path().join("run-a/cells.csv"), "new").unwrap();
        staged.publish().unwrap();
        assert_eq!(
            std::fs::read_to_string(out.join("table.md")).unwrap(),
            "new"
        );
        assert_eq!(
            std::fs::read_to_string(out.join("run-a/cells.csv")).unwrap(),
            "new"
        );
        let names: Vec<_> = list(&out).unwrap().into_iter().map(|(n, _)| n).collect();
        assert_eq!(names, ["run-a", "table.md"]);
        std::fs::remove_dir_all(&out).unwrap();
    }

    #[test]
    fn an_unpublished_stage_leaves_the_folder_as_it_was() {
        let out = scratch("drop");
        std::fs::create_dir_all(&out).unwrap();
        std::fs::write(out.join("table.md"), "old").unwrap();
        {
            let staged = Staged::begin(&out, "--out").unwrap();
            std::fs::write(staged.path().join("table.md"), "half").unwrap();
        }
        let names: Vec<_> = list(&out).unwrap().into_iter().map(|(n, _)| n).collect();
        assert_eq!(names, ["table.md"]);
        assert_eq!(
            std::fs::read_to_string(out.join("table.md")).unwrap(),
            "old"
        );
        std::fs::remove_dir_all(&out).unwrap();
    }

    #[test]
    fn a_stage_left_by_a_process_that_is_gone_is_removed() {
        let out = scratch("abandoned");
        // Pid numbers stop well below this one.
        let gone = out.join(format!("{STAGING_PREFIX}4294967294"));
        std::fs::create_dir_all(gone.join("run-a")).unwrap();
        let staged = Staged::begin(&out, "--out").unwrap();
        if Path::new("/proc/self").exists() {
            assert!(!gone.exists());
        }
        staged.publish().unwrap();
        std::fs::remove_dir_all(&out).unwrap();
    }

    #[test]
    fn an_output_path_under_a_file_is_refused_as_bad_input() {
        let dir = scratch("under-file");
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join("file"), "").unwrap();
        let err = Staged::begin(&dir.join("file/out"), "--out").err().unwrap();
        assert_eq!(err.exit_code(), 2);
        assert!(err.to_string().contains("--out"), "{err}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
