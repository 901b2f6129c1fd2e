//! Reading a job spec file; parsing and validation live in `salient_grid::spec`, shared with
//! the coordinator, which validates specs that arrive over the wire.

use crate::usage::{CliError, CliResult};
pub use salient_grid::spec::*;
use std::path::Path;

/// Reads and validates a spec file: JSON when it ends in `.json` or starts with `{` (after
/// whitespace), else TOML. Every problem is a usage error (exit 2).
/// Grids of more than `max_cells` cells are refused.
pub fn load(path: &Path, max_cells: usize) -> CliResult<JobSpec> {
    let text = std::fs::read_to_string(path).map_err(|e| {
        CliError::Usage(format!("spec: cannot read {}: {e}", path.display()).replace('\n', " "))
    })?;
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy())
        .unwrap_or_default();
    parse_capped(&text, is_json(&name, &text), max_cells).map_err(|e| CliError::Usage(e.0))
}

#[cfg(test)]
mod tests {
    use super::*;

    const GOOD: &str = include_str!("../../../examples/quick.toml");

    fn usage_message<T: std::fmt::Debug>(r: CliResult<T>) -> String {
        match r {
            Err(CliError::Usage(msg)) => msg,
            other => panic!("expected a usage error, got {other:?}"),
        }
    }

    #[test]
    fn load_picks_the_syntax_by_extension_or_first_brace() {
        let dir = std::env::temp_dir().join(format!("salient-spec-test-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let good_json = serde_json::to_string(&GOOD.parse::<toml::Table>().unwrap()).unwrap();
        let want = parse(GOOD, false).unwrap();
        for (file, text) in [
            ("a.toml", GOOD),
            ("b.json", good_json.as_str()),
            ("c.toml", good_json.as_str()), // JSON text under another name: it starts with '{'
            ("d", GOOD),
        ] {
            let path = dir.join(file);
            std::fs::write(&path, text).unwrap();
            assert_eq!(load(&path, MAX_CELLS).unwrap(), want, "{file}");
        }
        let msg = usage_message(load(&dir.join("missing.toml"), MAX_CELLS));
        assert!(msg.contains("missing.toml") && !msg.contains('\n'), "{msg}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
