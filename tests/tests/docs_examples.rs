//! The command lines of the user's documents (README.md, docs/*.md, deploy/README.md) hold:
//! every `salient` command names a real subcommand and real flags, every script, cargo target,
//! test filter and environment variable it names exists, the distributed walkthrough and
//! `scripts/local-cluster.sh` run as shown and give `salient run`'s files, and the Python
//! snippet of docs/outputs.md draws the quick example's map. Commands that take minutes to
//! hours (benchmarks, Table 2) are checked for what they name, not run; readme_cli.rs runs the
//! README's quick ones.

use salient_tests::cluster::{
    assert_same_outputs, client, coordinator_with, output_within, spawn, TOKEN,
};
use salient_tests::docs::{
    command_lines, fenced_blocks, inline_code, read, root, sh_lines, user_docs,
};
use salient_tests::{run_embedded, salient, salient_path};
use std::collections::{BTreeSet, HashMap};
use std::path::Path;
use std::process::Command;
use std::time::Duration;

/// The `--long` flags a text mentions.
fn long_flags(text: &str) -> BTreeSet<String> {
    text.split(|c: char| !(c.is_ascii_alphanumeric() || c == '-'))
        .filter(|w| w.len() > 2 && w.starts_with("--") && w.as_bytes()[2].is_ascii_alphabetic())
        .map(str::to_string)
        .collect()
}

/// Every command line of the user's documents, with the document it is in: the lines of `sh`
/// blocks and the inline code that starts like a command.
fn documented_commands() -> Vec<(String, String)> {
    let mut commands = Vec::new();
    for doc in user_docs() {
        let text = read(&doc);
        let lines = sh_lines(&text).into_iter().chain(inline_code(&text));
        for line in lines {
            // A redirection or a pipe ends the command.
            let line = line
                .split(['>', '|'])
                .next()
                .unwrap_or("")
                .trim()
                .to_string();
            let words: Vec<&str> = line.split_whitespace().collect();
            let first = words
                .iter()
                .find(|w| !is_assignment(w))
                .copied()
                .unwrap_or("");
            if ["salient", "target/release/salient", "cargo"].contains(&first)
                || first.starts_with("scripts/")
            {
                commands.push((doc.clone(), line));
            }
        }
    }
    commands
}

/// `NAME=value` before a command.
fn is_assignment(word: &str) -> bool {
    word.split_once('=').is_some_and(|(name, _)| {
        !name.is_empty() && name.bytes().all(|b| b.is_ascii_uppercase() || b == b'_')
    })
}

/// What `salient [SUB] --help` lists, asked once per subcommand.
struct Help(HashMap<String, Result<BTreeSet<String>, String>>);

impl Help {
    fn flags(&mut self, sub: &str) -> &Result<BTreeSet<String>, String> {
        self.0.entry(sub.to_string()).or_insert_with(|| {
            let args: Vec<&str> = sub.split_whitespace().chain(["--help"]).collect();
            let out = salient(&args);
            if out.status.success() {
                Ok(long_flags(&String::from_utf8_lossy(&out.stdout)))
            } else {
                Err(String::from_utf8_lossy(&out.stderr).into_owned())
            }
        })
    }
}

/// The source and scripts, where an environment variable the documents name must be read.
fn sources_text() -> String {
    let mut text = String::new();
    let mut stack = vec![root().join("crates"), root().join("scripts")];
    while let Some(dir) = stack.pop() {
        for entry in std::fs::read_dir(&dir).unwrap().flatten() {
            let path = entry.path();
            if path.is_dir() {
                stack.push(path);
            } else if path.extension().is_some_and(|e| e == "rs" || e == "sh") {
                text.push_str(&std::fs::read_to_string(&path).unwrap_or_default());
            }
        }
    }
    text
}

/// The folder of a workspace package, from its name.
fn package_dir(name: &str) -> Option<std::path::PathBuf> {
    let root = root();
    let mut dirs: Vec<_> = std::fs::read_dir(root.join("crates"))
        .unwrap()
        .flatten()
        .map(|e| e.path())
        .collect();
    dirs.push(root.join("tests"));
    dirs.into_iter().find(|d| {
        std::fs::read_to_string(d.join("Cargo.toml"))
            .is_ok_and(|t| t.contains(&format!("name = \"{name}\"")))
    })
}

/// The value after `flag` in `words`.
fn after<'a>(words: &[&'a str], flag: &str) -> Option<&'a str> {
    let k = words.iter().position(|w| *w == flag)?;
    words.get(k + 1).copied()
}

/// What is wrong with a `cargo …` line: a package, bench, example or test target that does
/// not exist, or a test filter that matches no test.
fn cargo_problem(words: &[&str], help: &mut Help) -> Option<String> {
    let own: Vec<&str> = words.split(|w| *w == "--").next().unwrap_or(&[]).to_vec();
    let Some(package) = after(&own, "-p") else {
        // `cargo build --release`, `cargo install --path DIR`.
        return after(&own, "--path")
            .filter(|p| !root().join(p).is_dir())
            .map(|p| format!("no folder {p}"));
    };
    let Some(dir) = package_dir(package) else {
        return Some(format!("no package {package}"));
    };
    let manifest = std::fs::read_to_string(dir.join("Cargo.toml")).unwrap();
    if let Some(bench) = after(&own, "--bench") {
        if !manifest.contains(&format!("name = \"{bench}\"")) {
            return Some(format!("no bench {bench} in {package}"));
        }
    }
    if let Some(example) = after(&own, "--example") {
        if !dir.join(format!("examples/{example}.rs")).is_file() {
            return Some(format!("no example {example} in {package}"));
        }
    }
    if let Some(test) = after(&own, "--test") {
        if !manifest.contains(&format!("name = \"{test}\"")) {
            return Some(format!("no test target {test} in {package}"));
        }
        // The filter after the target: a test's name or a module (`file::`).
        let k = own.iter().position(|w| *w == "--test").unwrap() + 2;
        if let Some(filter) = own.get(k).filter(|f| !f.starts_with('-')) {
            let module = filter.trim_end_matches("::");
            let tests_dir = dir.join("tests");
            let found = tests_dir.join(format!("{module}.rs")).is_file()
                || std::fs::read_dir(&tests_dir).unwrap().flatten().any(|e| {
                    std::fs::read_to_string(e.path())
                        .is_ok_and(|t| t.contains(&format!("fn {filter}")))
                });
            if !found {
                return Some(format!("no test matches {filter} in {package}"));
            }
        }
    }
    if package == "salient-cli" && words.contains(&"--") {
        let k = words.iter().position(|w| *w == "--").unwrap();
        return salient_problem(&words[k + 1..], help);
    }
    None
}

/// What is wrong with the arguments of a `salient` line: an unknown subcommand or flag.
fn salient_problem(args: &[&str], help: &mut Help) -> Option<String> {
    let sub = args
        .first()
        .filter(|a| !a.starts_with('-'))
        .copied()
        .unwrap_or("");
    match help.flags(sub) {
        Err(e) => Some(format!("`salient {sub} --help` fails: {e}")),
        Ok(known) => {
            let unknown: Vec<String> = long_flags(&args.join(" "))
                .into_iter()
                .filter(|f| !known.contains(f))
                .collect();
            (!unknown.is_empty()).then(|| format!("unknown flags {unknown:?}"))
        }
    }
}

/// What is wrong with a `scripts/…` line: a missing or non-executable script, or a flag the
/// script does not read.
fn script_problem(words: &[&str]) -> Option<String> {
    let path = root().join(words[0]);
    if !path.exists() {
        return Some(format!("no file {}", words[0]));
    }
    if path.extension().is_none_or(|e| e != "sh") {
        return None;
    }
    use std::os::unix::fs::PermissionsExt;
    let mode = path.metadata().unwrap().permissions().mode();
    if mode & 0o111 == 0 {
        return Some(format!("{} is not executable", words[0]));
    }
    let text = std::fs::read_to_string(&path).unwrap();
    let unknown: Vec<String> = long_flags(&words[1..].join(" "))
        .into_iter()
        .filter(|f| !text.contains(f.as_str()))
        .collect();
    (!unknown.is_empty()).then(|| format!("{} does not read {unknown:?}", words[0]))
}

#[test]
fn every_documented_command_names_what_exists() {
    let sources = sources_text();
    let mut help = Help(HashMap::new());
    let mut problems = Vec::new();
    let commands = documented_commands();
    for (doc, line) in &commands {
        let words: Vec<&str> = line
            .split_whitespace()
            .filter(|w| *w != "..." && *w != "…")
            .collect();
        let (env, words): (Vec<&str>, Vec<&str>) = {
            let k = words.iter().position(|w| !is_assignment(w)).unwrap_or(0);
            (words[..k].to_vec(), words[k..].to_vec())
        };
        let mut problem = env
            .iter()
            .map(|a| a.split('=').next().unwrap())
            .find(|name| !sources.contains(name))
            .map(|name| format!("no code reads {name}"));
        if problem.is_none() {
            problem = match words[0] {
                "salient" | "target/release/salient" => salient_problem(&words[1..], &mut help),
                "cargo" => cargo_problem(&words, &mut help),
                _ => script_problem(&words),
            };
        }
        if let Some(p) = problem {
            problems.push(format!("{doc}: `{line}`: {p}"));
        }
    }
    // Enough lines were read that the check means something (the pages hold about 150).
    assert!(
        commands.len() > 100,
        "only {} command lines found",
        commands.len()
    );
    assert!(problems.is_empty(), "{}", problems.join("\n"));
}

#[test]
fn the_checks_find_what_is_wrong() {
    let mut help = Help(HashMap::new());
    assert!(salient_problem(&["run", "SPEC", "--threads", "2"], &mut help).is_none());
    assert!(salient_problem(&["run", "SPEC", "--thread", "2"], &mut help).is_some());
    assert!(salient_problem(&["forecast"], &mut help).is_some());
    assert!(script_problem(&["scripts/soak.sh", "--seed", "1"]).is_none());
    assert!(script_problem(&["scripts/soak.sh", "--sed", "1"]).is_some());
    assert!(script_problem(&["scripts/nothing.sh"]).is_some());
    let cargo = |line: &str, help: &mut Help| {
        let words: Vec<&str> = line.split_whitespace().collect();
        cargo_problem(&words, help)
    };
    assert!(cargo("cargo bench -p salient-bench --bench stepper", &mut help).is_none());
    assert!(cargo("cargo bench -p salient-bench --bench steppers", &mut help).is_some());
    assert!(cargo("cargo run -p salient-core --example nothing", &mut help).is_some());
    assert!(cargo(
        "cargo test -p salient-tests --test integration nothing_",
        &mut help
    )
    .is_some());
    assert!(cargo(
        "cargo run --release -p salient-cli -- run X --bad",
        &mut help
    )
    .is_some());
    assert!(is_assignment("SALIENT_THREADS=1") && !is_assignment("--threads=1"));
}

/// The walkthrough "by hand" of docs/distributed.md, run line by line: the coordinator on a
/// free port with its store in a temporary folder, the client lines against it. The job is
/// the first of a new store, so its id is the 1 the page shows, and the results equal
/// `salient run`'s.
#[test]
fn the_distributed_walkthrough_runs_as_shown() {
    let text = read("docs/distributed.md");
    let block = fenced_blocks(&text)
        .into_iter()
        .find(|(info, body)| info == "sh" && body.contains("salient coordinator"))
        .expect("the walkthrough's block")
        .1;
    let dir = tempfile::tempdir().unwrap();
    let in_dir = |p: &str| dir.path().join(p).display().to_string();
    let mut url = String::new();
    let mut procs = Vec::new();
    let mut ran = Vec::new();
    for line in command_lines(&block) {
        let mut args: Vec<String> = line.split_whitespace().skip(1).map(String::from).collect();
        for k in 1..args.len() {
            if ["--db", "--out"].contains(&args[k - 1].as_str()) {
                args[k] = in_dir(&args[k]);
            } else if args[k].ends_with(".toml") {
                args[k] = root().join(&args[k]).display().to_string();
            }
        }
        let words: Vec<&str> = args.iter().map(String::as_str).collect();
        match words[0] {
            "coordinator" => {
                let (p, u) = coordinator_with(dir.path(), "127.0.0.1:0", "c.log", &words[1..]);
                procs.push(p);
                url = u;
            }
            "worker" => {
                let mut w = words.clone();
                w.extend(["--coordinator", &url]);
                procs.push(spawn(&w, &dir.path().join("w.log")));
            }
            _ => {
                let mut cmd = Command::new(salient_path());
                cmd.args(&words)
                    .args(["--coordinator", &url])
                    .env("SALIENT_TOKEN", TOKEN);
                let out = output_within(&mut cmd, Duration::from_secs(120));
                assert!(
                    out.status.success(),
                    "`{line}`: {}",
                    String::from_utf8_lossy(&out.stderr)
                );
                if words[0] == "submit" {
                    assert_eq!(String::from_utf8_lossy(&out.stdout).trim(), "1", "{line}");
                }
            }
        }
        ran.push(words[0].to_string());
    }
    assert!(ran.contains(&"results".to_string()), "{ran:?}");
    let embedded = dir.path().join("embedded");
    run_embedded(
        &root().join("examples/quick.toml").display().to_string(),
        &embedded,
    );
    assert_same_outputs(&dir.path().join("out/quick"), &embedded);
    // The job is done, so the page's last line, `cancel`, leaves it done.
    let status = client(&["status", "1", "--json"], &url);
    assert!(String::from_utf8_lossy(&status.stdout).contains("done"));
}

/// `scripts/local-cluster.sh 2 --submit examples/quick.toml` (README, docs/distributed.md)
/// starts a coordinator and two workers, waits for the job and writes `salient run`'s files.
#[test]
fn the_local_cluster_script_runs_the_quick_example() {
    let dir = tempfile::tempdir().unwrap();
    let mut cmd = Command::new(root().join("scripts/local-cluster.sh"));
    cmd.args(["2", "--submit", "examples/quick.toml"])
        .current_dir(root())
        .env("SALIENT_BIN", salient_path())
        .env("SALIENT_CLUSTER_DIR", dir.path())
        .env("SALIENT_THREADS", "1")
        .env_remove("SALIENT_TOKEN");
    let out = output_within(&mut cmd, Duration::from_secs(180));
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let embedded = dir.path().join("embedded");
    run_embedded(
        &root().join("examples/quick.toml").display().to_string(),
        &embedded,
    );
    assert_same_outputs(&dir.path().join("results/1"), &embedded);
}

/// The Python modules the pages' snippets import.
const PYTHON_MODULES: [&str; 4] = ["numpy", "matplotlib", "xarray", "scipy"];

/// A Python with [`PYTHON_MODULES`]: this machine's, or a virtual environment made once in the
/// target folder from PyPI. `None` (and the test says it was skipped) without Python or without
/// access to PyPI.
fn python_with_modules() -> Option<std::path::PathBuf> {
    // Once per test binary: two tests making the environment at once would clear each other's.
    static PYTHON: std::sync::OnceLock<Option<std::path::PathBuf>> = std::sync::OnceLock::new();
    PYTHON.get_or_init(find_or_make_python).clone()
}

fn find_or_make_python() -> Option<std::path::PathBuf> {
    let import = format!("import {}", PYTHON_MODULES.join(", "));
    let has = |python: &Path| {
        Command::new(python)
            .args(["-c", &import])
            .output()
            .is_ok_and(|o| o.status.success())
    };
    let system = Path::new("python3");
    if has(system) {
        return Some(system.to_path_buf());
    }
    let venv = root().join("target/docs-python");
    let python = venv.join("bin/python");
    if !has(&python) {
        let made = Command::new("python3")
            .args(["-m", "venv", "--clear"])
            .arg(&venv)
            .status()
            .is_ok_and(|s| s.success())
            && Command::new(&python)
                .args(["-m", "pip", "install", "--quiet"])
                .args(PYTHON_MODULES)
                .status()
                .is_ok_and(|s| s.success());
        if !made {
            return None;
        }
    }
    Some(python)
}

/// Runs the outputs page's Python snippet that writes `image` on the README's quick run (in
/// out/quick/ of a fresh folder, where the README's first command writes) and checks the
/// image. Skipped, and says so, without a Python that has the modules.
fn run_outputs_snippet(image: &str) {
    let Some(python) = python_with_modules() else {
        eprintln!(
            "skipped: no python3 with {}, and none could be installed",
            PYTHON_MODULES.join(", ")
        );
        return;
    };
    let (_, snippet) = fenced_blocks(&read("docs/outputs.md"))
        .into_iter()
        .find(|(info, text)| info == "python" && text.contains(image))
        .unwrap_or_else(|| panic!("a Python snippet of docs/outputs.md writing {image}"));
    let dir = tempfile::tempdir().unwrap();
    run_embedded(
        &root().join("examples/quick.toml").display().to_string(),
        &dir.path().join("out/quick"),
    );
    std::fs::write(dir.path().join("snippet.py"), &snippet).unwrap();
    let out = Command::new(python)
        .arg("snippet.py")
        .current_dir(dir.path())
        .env("MPLBACKEND", "Agg")
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "the snippet fails: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let png = std::fs::read(dir.path().join(image)).expect("the snippet's map");
    assert!(png.starts_with(b"\x89PNG") && png.len() > 10_000);
}

#[test]
fn the_numpy_snippet_of_the_outputs_page_draws_the_map() {
    run_outputs_snippet("map_numpy.png");
}

#[test]
fn the_xarray_snippet_of_the_outputs_page_reads_results_nc() {
    run_outputs_snippet("map_xarray.png");
}
