//! The README's examples run as shown: every `salient` command of its `sh` blocks is run (with
//! its output folder moved to a temporary one), and the quick start's printed table is what the
//! main command prints, timings aside. Commands that need a running coordinator or take hours
//! are named here and checked otherwise (the distributed tests run those commands; a spec that
//! takes hours is parsed, not run).

use salient_tests::docs::{read, root, sh_lines, shell_words};
use salient_tests::{salient, salient_path};

fn readme() -> String {
    read("README.md")
}

/// Commands run against a coordinator: covered by tests/tests/distributed_cli.rs.
const NEED_A_COORDINATOR: &[&str] = &["coordinator", "worker", "submit", "watch", "results"];

/// Specs of examples too long for a test (Table 2 for hours, the grid comparison's references
/// and the 200×200 MEGNO map for minutes): parsed instead.
const TOO_LONG: &[&str] = &[
    "examples/table2.toml",
    "examples/grid-precision.toml",
    "examples/megno-200.toml",
];

#[test]
fn every_salient_example_in_the_readme_runs() {
    let root = root();
    let dir = tempfile::tempdir().unwrap();
    let mut ran = 0;
    for line in sh_lines(&readme()) {
        let words = shell_words(&line);
        let words: Vec<&str> = words.iter().map(String::as_str).collect();
        // `salient ARGS…`, or `cargo run … -- ARGS…`.
        let rest = match words.as_slice() {
            ["salient", rest @ ..] => rest,
            ["cargo", "run", ..] => match words.iter().position(|w| *w == "--") {
                Some(k) => &words[k + 1..],
                None => continue,
            },
            _ => continue,
        };
        let args: Vec<String> = rest.iter().map(|s| s.to_string()).collect();
        if NEED_A_COORDINATOR.contains(&args[0].as_str()) {
            continue;
        }
        let mut args = args;
        // Outputs go to the temporary folder, specs are read from the repository.
        if let Some(k) = args.iter().position(|a| a == "--out") {
            args[k + 1] = dir.path().join(format!("out{ran}")).display().to_string();
        } else if args[0] == "run" {
            args.extend([
                "--out".into(),
                dir.path().join(format!("out{ran}")).display().to_string(),
            ]);
        }
        for a in args.iter_mut().filter(|a| a.ends_with(".toml")) {
            if TOO_LONG.contains(&a.as_str()) {
                // Parsed and refused by a cell cap far below its grid: proves the spec is valid
                // up to its size without running it.
                let out = salient(&[
                    "run",
                    &root.join(&*a).display().to_string(),
                    "--max-cells",
                    "1",
                ]);
                let text = String::from_utf8_lossy(&out.stderr);
                assert_eq!(out.status.code(), Some(2), "{line}: {text}");
                assert!(text.contains("cells"), "{line}: {text}");
                args.clear();
                break;
            }
            *a = root.join(&*a).display().to_string();
        }
        if args.is_empty() {
            continue;
        }
        let out = std::process::Command::new(salient_path())
            .args(&args)
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "`{line}` failed: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        ran += 1;
    }
    assert!(ran >= 3, "only {ran} README examples ran");
}

/// The table rows of the README's quick-start output block up to the orbits column: the
/// dropped work and the times after it depend on the threads and the host.
fn table_without_timings(text: &str) -> Vec<String> {
    text.lines()
        .filter(|l| l.starts_with('|') && !l.starts_with("|--"))
        .map(|l| {
            let cells: Vec<&str> = l.split('|').map(str::trim).collect();
            // A leading empty cell, then tau … orbits.
            cells[1..10].join("|")
        })
        .collect()
}

#[test]
fn the_quick_start_prints_the_table_the_readme_shows() {
    let text = readme();
    let start = text.find("## Quick start").expect("a quick start section");
    let block = text[start..]
        .split("```")
        .nth(1)
        .expect("the quick start's output block");
    let shown = table_without_timings(block);
    assert_eq!(shown.len(), 2, "{block}");
    let root = root();
    let dir = tempfile::tempdir().unwrap();
    let out = salient(&[
        "run",
        &root.join("examples/quick.toml").display().to_string(),
        "--out",
        &dir.path().join("quick").display().to_string(),
    ]);
    assert!(out.status.success());
    let printed = table_without_timings(&String::from_utf8_lossy(&out.stdout));
    assert_eq!(
        printed, shown,
        "README's quick-start table differs from what the command prints"
    );
}
