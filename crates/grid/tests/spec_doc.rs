//! docs/spec.md against the parser: every key the parser accepts ([`SCHEMA`]) is documented and
//! every documented key is accepted, every method name is listed, and every example spec on the
//! page parses. The page's conventions (its last section) say what is read here:
//!
//! - a heading `### Top level` or `### [TABLE]` opens a table of the schema; the rows up to the
//!   next heading whose first cell is `` `KEY` `` are its documented keys;
//! - the rows of the same form under `## Methods` are the documented method names;
//! - every fenced block marked `toml` or `json` is a complete spec.

use salient_core::Method;
use salient_grid::spec::{parse, JobSpec, SCHEMA};
use std::collections::BTreeMap;

fn doc() -> String {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../../docs/spec.md");
    std::fs::read_to_string(path).unwrap_or_else(|e| panic!("reading {path}: {e}"))
}

/// The key of a table row whose first cell is one backticked word: `| `tau` | ... |`.
fn row_key(line: &str) -> Option<&str> {
    let rest = line.trim().strip_prefix('|')?;
    let cell = rest.split('|').next()?.trim();
    let key = cell.strip_prefix('`')?.strip_suffix('`')?;
    (!key.is_empty() && !key.contains('`')).then_some(key)
}

/// What a heading opens: a table of the schema ("" for the top level), the method list, or
/// nothing this test reads.
#[derive(Clone, Debug, PartialEq)]
enum Part {
    Table(String),
    Methods,
    Other,
}

/// The documented keys of each table and the documented method names, in page order. Fails on
/// a table or key documented twice.
fn documented(doc: &str) -> (BTreeMap<String, Vec<String>>, Vec<String>) {
    let mut tables: BTreeMap<String, Vec<String>> = BTreeMap::new();
    let mut methods = Vec::new();
    let mut part = Part::Other;
    let mut in_fence = false;
    for line in doc.lines() {
        if line.trim_start().starts_with("```") {
            in_fence = !in_fence;
            continue;
        }
        if in_fence {
            continue;
        }
        if line.starts_with('#') {
            let level = line.chars().take_while(|&c| c == '#').count();
            let title = line[level..].trim();
            part = match (level, title) {
                (3, "Top level") => Part::Table(String::new()),
                (3, t) if t.starts_with('[') && t.ends_with(']') => {
                    Part::Table(t[1..t.len() - 1].to_string())
                }
                (2, "Methods") => Part::Methods,
                _ => Part::Other,
            };
            if let Part::Table(t) = &part {
                assert!(
                    tables.insert(t.clone(), Vec::new()).is_none(),
                    "docs/spec.md has two headings for [{t}]"
                );
            }
            continue;
        }
        let Some(key) = row_key(line) else { continue };
        match &part {
            Part::Table(t) => {
                let keys = tables.get_mut(t).unwrap();
                assert!(
                    !keys.iter().any(|k| k == key),
                    "docs/spec.md documents key '{key}' of [{t}] twice"
                );
                keys.push(key.to_string());
            }
            Part::Methods => methods.push(key.to_string()),
            Part::Other => {}
        }
    }
    (tables, methods)
}

fn table_name(t: &str) -> String {
    if t.is_empty() {
        "the top level".into()
    } else {
        format!("[{t}]")
    }
}

/// Every difference between the documented tables and keys and the parser's SCHEMA.
fn schema_mismatches(documented: &BTreeMap<String, Vec<String>>) -> Vec<String> {
    let mut problems = Vec::new();
    for (table, keys) in SCHEMA {
        let name = table_name(table);
        let Some(doc_keys) = documented.get(*table) else {
            problems.push(format!(
                "the parser's SCHEMA has {name} but docs/spec.md has no heading for it"
            ));
            continue;
        };
        for key in *keys {
            if !doc_keys.iter().any(|k| k == key) {
                problems.push(format!(
                    "key '{key}' in {name} is accepted by the parser but not documented in docs/spec.md"
                ));
            }
        }
        for key in doc_keys {
            if !keys.contains(&key.as_str()) {
                problems.push(format!(
                    "key '{key}' in {name} is documented in docs/spec.md but the parser's SCHEMA does not accept it"
                ));
            }
        }
    }
    for table in documented.keys() {
        if !SCHEMA.iter().any(|(t, _)| t == table) {
            problems.push(format!(
                "docs/spec.md documents {} but the parser's SCHEMA has no such table",
                table_name(table)
            ));
        }
    }
    problems
}

/// The fenced blocks marked `lang`, with the line each starts on.
fn fenced(doc: &str, lang: &str) -> Vec<(usize, String)> {
    let mut blocks = Vec::new();
    let mut current: Option<(usize, String)> = None;
    for (n, line) in doc.lines().enumerate() {
        let fence = line.trim_start().strip_prefix("```");
        match (&mut current, fence) {
            (None, Some(info)) if info.trim() == lang => current = Some((n + 1, String::new())),
            (Some(_), Some(_)) => blocks.push(current.take().unwrap()),
            (Some((_, text)), None) => {
                text.push_str(line);
                text.push('\n');
            }
            _ => {}
        }
    }
    assert!(current.is_none(), "docs/spec.md: unclosed ```{lang} block");
    blocks
}

#[test]
fn every_schema_key_is_documented_and_every_documented_key_is_accepted() {
    let (tables, _) = documented(&doc());
    let problems = schema_mismatches(&tables);
    assert!(problems.is_empty(), "\n{}", problems.join("\n"));
}

#[test]
fn the_check_catches_a_missing_and_an_extra_key() {
    // The comparison itself, on edits of the page: a row taken out, a row added, a table gone.
    let doc = doc();
    let row = doc
        .lines()
        .find(|l| row_key(l) == Some("energy_drift"))
        .expect("a row for energy_drift");
    let without = doc.replacen(&format!("{row}\n"), "", 1);
    let extra = doc.replacen(
        &format!("{row}\n"),
        &format!("{row}\n| `no_such_key` | number | no | — | — | — |\n"),
        1,
    );
    let renamed = doc.replacen("### [integration]", "### Integration", 1);
    for (edited, want) in [
        (
            without,
            "key 'energy_drift' in [classify] is accepted by the parser but not documented in docs/spec.md",
        ),
        (
            extra,
            "key 'no_such_key' in [classify] is documented in docs/spec.md but the parser's SCHEMA does not accept it",
        ),
        (
            renamed,
            "the parser's SCHEMA has [integration] but docs/spec.md has no heading for it",
        ),
    ] {
        let problems = schema_mismatches(&documented(&edited).0);
        assert!(problems.iter().any(|p| p == want), "{want}: got {problems:?}");
    }
}

#[test]
fn every_method_name_is_documented() {
    let (_, mut documented) = documented(&doc());
    let mut names = Method::names();
    documented.sort();
    names.sort();
    assert_eq!(
        documented, names,
        "the method names under ## Methods in docs/spec.md (left) differ from the parser's (right)"
    );
}

#[test]
fn the_example_specs_parse() {
    let doc = doc();
    let check = |line: usize, text: &str, json: bool| -> JobSpec {
        let job = parse(text, json)
            .unwrap_or_else(|e| panic!("docs/spec.md line {line}: the example is refused: {e}"));
        assert!(
            job.warnings.is_empty(),
            "docs/spec.md line {line}: the example warns: {:?}",
            job.warnings
        );
        job
    };
    let toml: Vec<JobSpec> = fenced(&doc, "toml")
        .iter()
        .map(|(line, text)| check(*line, text, false))
        .collect();
    let json = fenced(&doc, "json");
    assert!(!toml.is_empty(), "docs/spec.md has no ```toml example");
    assert!(!json.is_empty(), "docs/spec.md has no ```json example");
    for (line, text) in &json {
        let job = check(*line, text, true);
        assert!(
            toml.contains(&job),
            "docs/spec.md line {line}: the JSON example is not the same job as any TOML example"
        );
    }
    // The first example is the complete one: it sets every key of every table, but for
    // `sweep.energy` and `sweep.mode`, which replace `system.energy` and `grid.mode` (a spec
    // gives one of each two), and the keys of polynomial systems, which the example of
    // [section] sets.
    let complete = &toml[0].source;
    assert!(!complete["system"]["energy"].is_null());
    assert!(!complete["grid"]["mode"].is_null());
    let polynomial = toml
        .iter()
        .find(|j| j.source["system"]["kind"] == "polynomial")
        .expect("an example of a polynomial system");
    for key in ["dof", "potential"] {
        assert!(!polynomial.source["system"][key].is_null(), "system.{key}");
    }
    for key in ["plane", "axes", "fixed"] {
        assert!(
            !polynomial.source["section"][key].is_null(),
            "section.{key}"
        );
    }
    for (table, keys) in SCHEMA {
        if table.starts_with("section") {
            continue;
        }
        let t = if table.is_empty() {
            complete
        } else {
            &complete[*table]
        };
        let replaced = [
            ("sweep", "energy"),
            ("sweep", "mode"),
            ("", "section"),
            ("system", "dof"),
            ("system", "potential"),
            ("system", "beta"),
            ("grid", "q1"),
            ("grid", "q3"),
            ("grid", "p1"),
            ("grid", "p3"),
        ];
        for key in keys.iter().filter(|&&k| !replaced.contains(&(*table, k))) {
            assert!(
                !t[*key].is_null(),
                "the first example in docs/spec.md does not set {}{key}",
                if table.is_empty() {
                    String::new()
                } else {
                    format!("{table}.")
                }
            );
        }
    }
    // Its runs are the ones the page lists, in that order.
    let runs: Vec<_> = toml[0]
        .runs
        .iter()
        .map(|r| (r.method.name(), r.tau, r.t_final, r.delta))
        .collect();
    let tm = "tm-sbab2c".to_string();
    let dop = "dop853".to_string();
    assert_eq!(
        runs,
        [
            (tm.clone(), 0.5, 1e4, None),
            (dop.clone(), 0.5, 1e4, Some(1e-10)),
            (tm, 0.05, 1e4, None),
            (dop, 0.05, 1e4, Some(1e-10)),
        ]
    );
}
