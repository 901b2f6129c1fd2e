//! `scripts/reproduce-table2.sh` resumes: a second start runs only the sweeps the first did not
//! finish, and the assembled table holds every finished row.

use salient_tests::cluster::output_within;
use salient_tests::docs::root;
use salient_tests::salient_path;
use std::path::Path;
use std::process::{Command, Output};
use std::time::Duration;

/// The script on a 12×12 grid, tangent-map rows at t = 1e4, into `out`.
fn reproduce(out: &Path, extra: &[&str]) -> Output {
    let mut cmd = Command::new(root().join("scripts/reproduce-table2.sh"));
    cmd.args(["--cells", "12", "--out"])
        .arg(out)
        .args(["--bin"])
        .arg(salient_path())
        .args(extra)
        .args(["tm-sbab2c", "1e4"]);
    let done = output_within(&mut cmd, Duration::from_secs(120));
    assert!(
        done.status.success(),
        "{}",
        String::from_utf8_lossy(&done.stderr)
    );
    done
}

/// The lines of the assembled table (every sweep's table under its heading) that start with
/// `prefix`: its rows ("| 0.") or its headings ("### ").
fn lines_of(out: &Path, prefix: &str) -> Vec<String> {
    std::fs::read_to_string(out.join("table2.md"))
        .unwrap()
        .lines()
        .filter(|l| l.starts_with(prefix))
        .map(str::to_string)
        .collect()
}

fn rows(out: &Path) -> Vec<String> {
    lines_of(out, "| 0.")
}

#[test]
fn the_table2_script_resumes_with_the_sweeps_it_did_not_finish() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("t2");
    let first = reproduce(&out, &["--energy-check", "both"]);
    let said = String::from_utf8_lossy(&first.stderr);
    assert_eq!(said.matches("running: ").count(), 4, "{said}");
    let all = rows(&out);
    assert_eq!(all.len(), 4, "{all:?}");
    let order = lines_of(&out, "### ");
    assert_eq!(order.len(), 4, "{order:?}");
    assert!(order[0].contains("τ = 0.5") && order[0].ends_with("energy check 1e-2"));
    assert!(order[3].contains("τ = 0.01") && order[3].contains("energy check off"));

    // As if stopped during the paper-conditions sweep at τ = 0.01: its folder holds no table.
    let finished = out.join("salient/tau0.5-t1e4-tm-sbab2c/table.json");
    let before = (
        std::fs::read(&finished).unwrap(),
        std::fs::metadata(&finished).unwrap().modified().unwrap(),
    );
    std::fs::remove_file(out.join("paper/tau0.01-t1e4-tm-sbab2c/table.json")).unwrap();
    assert_eq!(rows(&out).len(), 4);
    let again = reproduce(&out, &["--energy-check", "both"]);
    let said = String::from_utf8_lossy(&again.stderr);
    assert_eq!(said.matches("finished already: ").count(), 3, "{said}");
    assert_eq!(said.matches("running: ").count(), 1, "{said}");
    assert!(said.contains("running: ") && said.contains("paper/tau0.01-t1e4-tm-sbab2c"));
    let after = (
        std::fs::read(&finished).unwrap(),
        std::fs::metadata(&finished).unwrap().modified().unwrap(),
    );
    assert_eq!(before, after, "a finished sweep is not run again");
    // The same percentages as the first time (the timing columns aside).
    let percentages = |r: &[String]| -> Vec<String> {
        r.iter()
            .map(|l| l.split('|').take(8).collect::<Vec<_>>().join("|"))
            .collect()
    };
    assert_eq!(percentages(&rows(&out)), percentages(&all));

    // A bad option is refused before anything runs.
    let mut bad = Command::new(root().join("scripts/reproduce-table2.sh"));
    bad.args(["--energy-check", "sometimes"]);
    let refused = output_within(&mut bad, Duration::from_secs(30));
    assert_eq!(refused.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&refused.stderr).contains("--energy-check must be"));
}
