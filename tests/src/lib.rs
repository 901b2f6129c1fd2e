//! Helpers for the end-to-end tests in `tests/tests/`: they run the real `salient` binary,
//! which `scripts/test.sh` builds before `cargo test` (cargo does not build another package's
//! binary for a test).

pub mod cluster;
pub mod docs;

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// Path of the `salient` binary next to this test executable's profile directory.
pub fn salient_path() -> PathBuf {
    if let Ok(p) = std::env::var("SALIENT_BIN") {
        return PathBuf::from(p);
    }
    let exe = std::env::current_exe().expect("test executable path");
    // target/<profile>/deps/<test> → target/<profile>/salient
    let profile_dir = exe
        .parent()
        .and_then(|d| d.parent())
        .expect("target/<profile>");
    let bin = profile_dir.join(format!("salient{}", std::env::consts::EXE_SUFFIX));
    assert!(
        bin.exists(),
        "{} is missing: build it first with `cargo build --release -p salient-cli` (scripts/test.sh does)",
        bin.display()
    );
    bin
}

/// Runs `salient` with `args` and returns its output.
pub fn salient(args: &[&str]) -> Output {
    Command::new(salient_path())
        .args(args)
        .output()
        .expect("run salient")
}

/// The single JSON object a `--json` run printed.
pub fn json_stdout(out: &Output) -> serde_json::Value {
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "salient failed ({:?}): {}",
        out.status.code(),
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_str(text.trim())
        .unwrap_or_else(|e| panic!("stdout is not one JSON object ({e}): {text}"))
}

/// Writes a spec file `name` with `text` into `dir` and returns its path as a string.
pub fn write_spec(dir: &Path, name: &str, text: &str) -> String {
    let p = dir.join(name);
    std::fs::write(&p, text).expect("write the spec");
    p.to_str().expect("a UTF-8 path").to_string()
}

/// The run folders of an output folder, sorted (`01-…`, `02-…`); hidden folders (a staging
/// folder, a checkpoint) are not runs.
pub fn run_dirs(out: &Path) -> Vec<PathBuf> {
    let mut dirs: Vec<PathBuf> = std::fs::read_dir(out)
        .expect("the output folder")
        .flatten()
        .filter(|e| !e.file_name().to_string_lossy().starts_with('.'))
        .map(|e| e.path())
        .filter(|p| p.is_dir())
        .collect();
    dirs.sort();
    dirs
}

/// `salient run SPEC --json --out OUT` (every thread of this machine), which must succeed;
/// its JSON summary.
pub fn run_embedded(spec: &str, out: &Path) -> serde_json::Value {
    json_stdout(&salient(&[
        "run",
        spec,
        "--json",
        "--out",
        out.to_str().expect("a UTF-8 path"),
    ]))
}
