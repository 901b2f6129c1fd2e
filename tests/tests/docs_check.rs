//! The tree describes the product as it is: no tracked Markdown or Rust file tells the history of
//! its development (dates, numbered stages of the work, commit hashes in prose) or points
//! outside the repository. Dates may appear only on the "measured on" lines of
//! docs/performance.md. The phrases are spelt in pieces here, so that this file, and checks
//! like it that read the whole tree, do not find them in it.

use salient_tests::docs::root;
use std::path::{Path, PathBuf};

/// Tracked `*.md` and `*.rs` files: git's list where git and the repository are there, else
/// every such file outside build output and hidden folders.
fn files() -> Vec<PathBuf> {
    let root = root();
    let listed = std::process::Command::new("git")
        .args(["ls-files", "-z", "--", "*.md", "*.rs"])
        .current_dir(&root)
        .output()
        .ok()
        .filter(|o| o.status.success() && !o.stdout.is_empty());
    if let Some(out) = listed {
        return out
            .stdout
            .split(|&b| b == 0)
            .filter(|p| !p.is_empty())
            .map(|p| root.join(String::from_utf8_lossy(p).as_ref()))
            .filter(|p| p.exists())
            .collect();
    }
    let mut found = Vec::new();
    let mut stack = vec![root];
    while let Some(dir) = stack.pop() {
        for entry in std::fs::read_dir(&dir).unwrap().flatten() {
            let path = entry.path();
            let name = entry.file_name().to_string_lossy().into_owned();
            if name.starts_with('.') || name == "target" {
                continue;
            }
            if path.is_dir() {
                stack.push(path);
            } else if name.ends_with(".md") || name.ends_with(".rs") {
                found.push(path);
            }
        }
    }
    found
}

/// The words of a line, split at anything that cannot be part of a hash or a date.
fn tokens(line: &str) -> impl Iterator<Item = &str> {
    line.split(|c: char| !(c.is_ascii_alphanumeric() || c == '-'))
        .filter(|t| !t.is_empty())
}

/// `YYYY-MM-DD` with a plausible month and day.
fn is_iso_date(t: &str) -> bool {
    let b = t.as_bytes();
    b.len() == 10
        && b[4] == b'-'
        && b[7] == b'-'
        && [0, 1, 2, 3, 5, 6, 8, 9]
            .iter()
            .all(|&k| b[k].is_ascii_digit())
        && t.starts_with("20")
        && (1..=12).contains(&t[5..7].parse::<u32>().unwrap())
        && (1..=31).contains(&t[8..10].parse::<u32>().unwrap())
}

/// 7 to 40 lowercase hex digits with at least two letters and two digits: what an abbreviated
/// or full commit hash looks like, and what ordinary words and numbers do not.
fn is_hash_like(t: &str) -> bool {
    (7..=40).contains(&t.len())
        && t.bytes()
            .all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b))
        && t.bytes().filter(u8::is_ascii_digit).count() >= 2
        && t.bytes().filter(u8::is_ascii_lowercase).count() >= 2
}

/// Phrases that tell how the work went or point outside the repository.
const HISTORY: &[&str] = &[
    concat!("sess", "ion"),
    concat!("research", " note"),
    concat!("design", " contract"),
    concat!("design", ".md"),
    concat!("../", "shared"),
    concat!("../", ".library"),
    concat!("the issue", "'s"),
];

/// Numbered stages of the work ("stage 3").
const STAGES: &[&str] = &["stage 1", "stage 2", "stage 3", "stage 4", "stage 5"];

fn problems_of(rel: &str, text: &str) -> Vec<String> {
    let dated_ok =
        |line: &str| rel == "docs/performance.md" && line.to_lowercase().contains("measured on");
    let mut found = Vec::new();
    for (n, line) in text.lines().enumerate() {
        let at = format!("{rel}:{}", n + 1);
        let lower = line.to_lowercase();
        if let Some(p) = HISTORY.iter().chain(STAGES).find(|p| lower.contains(*p)) {
            found.push(format!("{at}: \"{p}\": {line}"));
        }
        for t in tokens(line) {
            if is_iso_date(t) && !dated_ok(line) {
                found.push(format!("{at}: a date ({t}): {line}"));
            }
            if is_hash_like(t) {
                found.push(format!("{at}: a commit-hash-like word ({t}): {line}"));
            }
        }
    }
    found
}

#[test]
fn no_tracked_doc_or_source_tells_history_or_points_outside_the_repository() {
    let root = root();
    let this = Path::new(file!())
        .file_name()
        .expect("this file's name")
        .to_owned();
    let mut problems = Vec::new();
    let mut read = 0;
    for path in files() {
        // This file names the phrases it looks for.
        if path.file_name() == Some(this.as_os_str()) {
            continue;
        }
        let Ok(text) = std::fs::read_to_string(&path) else {
            continue;
        };
        read += 1;
        let rel = path
            .strip_prefix(&root)
            .unwrap()
            .to_string_lossy()
            .replace('\\', "/");
        problems.extend(problems_of(&rel, &text));
    }
    assert!(
        read > 50,
        "only {read} files read: is the repository there?"
    );
    assert!(
        problems.is_empty(),
        "{} lines tell history or point outside the repository:\n{}",
        problems.len(),
        problems.join("\n")
    );
}

#[test]
fn the_checks_catch_what_they_are_for() {
    assert!(is_iso_date("2026-11-26"));
    assert!(!is_iso_date("2026-13-26") && !is_iso_date("1e-5"));
    assert!(is_hash_like("5eacb58") && is_hash_like("d893cc2"));
    assert!(!is_hash_like("1234567") && !is_hash_like("defaced") && !is_hash_like("0x1f"));
    let bad = format!(
        "measured in the ninth {} (2026-11-26, `920f0c1`), see {}/DESIGN.md",
        HISTORY[0], HISTORY[4]
    );
    assert_eq!(problems_of("README.md", &bad).len(), 3);
    assert!(problems_of("docs/performance.md", "measured on 2026-11-26").is_empty());
    assert!(problems_of("README.md", "measured on 2026-11-26").len() == 1);
    assert!(problems_of("src/a.rs", "let seed = 0xcbf2_9ce4_8422_2325; // FNV").is_empty());
}
