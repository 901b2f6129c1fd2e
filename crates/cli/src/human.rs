//! Numbers as people read them: on the terminal and in log lines, not in data files (those keep
//! every digit).

/// `v` rounded to 10 significant digits and printed in its shortest form: `370.2`, not
/// `370.20000000000005`; integers without a fraction.
pub fn human(v: f64) -> String {
    if !v.is_finite() || v == 0.0 {
        return format!("{v}");
    }
    let rounded: f64 = format!("{v:.9e}").parse().unwrap_or(v);
    if rounded.abs() >= 1e-4 && rounded.abs() < 1e15 {
        format!("{rounded}")
    } else {
        format!("{rounded:e}")
    }
}

/// `v` with `decimals` digits after the point, for log fields (seconds, percentages).
pub fn rounded(v: f64, decimals: i32) -> f64 {
    let scale = 10f64.powi(decimals);
    (v * scale).round() / scale
}

/// A CSV number: the shortest form that reads back to the same `f64`, in scientific notation
/// where fixed point would spell out long runs of zeros (below 1e-4 or from 1e16).
pub fn csv_number(v: f64) -> String {
    if v != 0.0 && v.is_finite() && !(1e-4..1e16).contains(&v.abs()) {
        format!("{v:e}")
    } else {
        format!("{v}")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn people_see_short_numbers_and_files_keep_every_digit() {
        assert_eq!(human(370.20000000000005), "370.2");
        assert_eq!(human(1e4), "10000");
        assert_eq!(human(0.1 + 0.2), "0.3");
        assert_eq!(human(1.5e-9), "1.5e-9");
        assert_eq!(human(f64::NAN), "NaN");
        assert_eq!(rounded(3.46, 1), 3.5);
        assert_eq!(csv_number(1e-20), "1e-20");
        assert_eq!(csv_number(0.125), "0.125");
        assert_eq!(csv_number(0.0), "0");
        let v = 1.234_567_890_123_456_7e-12;
        assert_eq!(csv_number(v).parse::<f64>().unwrap(), v);
    }
}
