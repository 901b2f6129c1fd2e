//! Fuzzing the spec parser with proptest: arbitrary text in either syntax, and random edits of
//! a good spec, never panic, and every refusal is one line. `scripts/fuzz.sh` runs these with
//! many more cases (`PROPTEST_CASES`).

use proptest::prelude::*;
use salient_grid::spec::{parse, parse_capped};

const GOOD: &str = r#"
name = "fuzz"
[system]
kind = "henon-heiles"
energy = 0.125
[grid]
cells = [40, 30]
tile = [10, 10]
mode = "full"
q2 = [-0.4, 0.6]
[sweep]
method = ["tm-sbab2c", "dop853"]
tau = [0.5, 0.05]
t_final = [1e3]
delta = [1e-5, 1e-8]
[integration]
protocol = "free"
deviation = "random"
seed = 7
[classify]
regular = 1e-3
chaotic = 1e-9
early_stop = false
energy_drift = 0.5
"#;

fn check(text: &str) {
    for json in [false, true] {
        if let Err(e) = parse_capped(text, json, 1_000_000) {
            assert!(!e.0.contains('\n') && !e.0.is_empty(), "{:?}", e.0);
        }
    }
}

/// Tokens a TOML or JSON spec is made of, to reach deeper than random bytes do.
fn token() -> impl Strategy<Value = String> {
    prop_oneof![
        Just("nan".to_string()),
        Just("inf".to_string()),
        Just("-inf".to_string()),
        Just("[]".to_string()),
        Just("{}".to_string()),
        Just("\"\"".to_string()),
        Just("1e308".to_string()),
        Just("1e-320".to_string()),
        Just("-0.0".to_string()),
        Just("18446744073709551616".to_string()),
        Just("true".to_string()),
        Just("[[grid]]".to_string()),
        Just("\n".to_string()),
        any::<i64>().prop_map(|i| i.to_string()),
        any::<f64>().prop_map(|f| format!("{f:e}")),
        "[a-z_]{1,8}",
    ]
}

/// `PROPTEST_CASES` when set (scripts/fuzz.sh), else a count that keeps the suite quick.
fn cases(default: u32) -> u32 {
    std::env::var("PROPTEST_CASES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

proptest! {
    #![proptest_config(ProptestConfig { cases: cases(256), ..ProptestConfig::default() })]

    #[test]
    fn arbitrary_text_never_panics(bytes in proptest::collection::vec(any::<u8>(), 0..400)) {
        check(&String::from_utf8_lossy(&bytes));
    }

    #[test]
    fn edits_of_a_good_spec_never_panic(
        edits in proptest::collection::vec((any::<prop::sample::Index>(), 0usize..12, token()), 1..6)
    ) {
        let mut text = GOOD.to_string();
        for (at, cut, tok) in edits {
            let mut i = at.index(text.len() + 1);
            while !text.is_char_boundary(i) {
                i -= 1;
            }
            let mut j = (i + cut).min(text.len());
            while !text.is_char_boundary(j) {
                j -= 1;
            }
            text.replace_range(i..j, &tok);
        }
        check(&text);
    }
}

#[test]
fn the_fuzzed_spec_is_itself_valid() {
    parse(GOOD, false).unwrap();
}
