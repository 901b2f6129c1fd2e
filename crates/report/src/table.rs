//! Plain tables rendered as GitHub Markdown or CSV (RFC 4180 quoting).

/// A table of already formatted cells.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Table {
    /// Column headers.
    pub headers: Vec<String>,
    /// Rows, each with one cell per header.
    pub rows: Vec<Vec<String>>,
}

impl Table {
    /// An empty table with these column headers.
    pub fn new(headers: &[&str]) -> Self {
        Table {
            headers: headers.iter().map(|h| h.to_string()).collect(),
            rows: Vec::new(),
        }
    }

    /// Appends a row; it must have one cell per header.
    pub fn push(&mut self, row: Vec<String>) {
        assert_eq!(
            row.len(),
            self.headers.len(),
            "row width must match the headers"
        );
        self.rows.push(row);
    }

    /// A Markdown table with columns padded to equal width; `|` in cells is escaped.
    pub fn to_markdown(&self) -> String {
        let esc = |s: &str| s.replace('|', "\\|");
        let width: Vec<usize> = (0..self.headers.len())
            .map(|c| {
                self.rows
                    .iter()
                    .map(|r| esc(&r[c]).chars().count())
                    .chain([esc(&self.headers[c]).chars().count(), 3])
                    .max()
                    .unwrap_or(3)
            })
            .collect();
        let line = |cells: &[String]| {
            let padded: Vec<String> = cells
                .iter()
                .zip(&width)
                .map(|(c, &w)| format!("{:<w$}", esc(c)))
                .collect();
            format!("| {} |\n", padded.join(" | "))
        };
        let mut out = line(&self.headers);
        let rule: Vec<String> = width.iter().map(|&w| "-".repeat(w)).collect();
        out.push_str(&format!("|-{}-|\n", rule.join("-|-")));
        for r in &self.rows {
            out.push_str(&line(r));
        }
        out
    }

    /// CSV with a header line; cells holding a comma, quote or newline are quoted.
    pub fn to_csv(&self) -> String {
        let cell = |s: &String| {
            // "—" (nothing to show) reads well in Markdown; a CSV reader wants an empty field,
            // which numeric columns parse as missing.
            if s == NOTHING {
                String::new()
            } else if s.contains([',', '"', '\n']) {
                format!("\"{}\"", s.replace('"', "\"\""))
            } else {
                s.clone()
            }
        };
        let mut out = String::new();
        for r in std::iter::once(&self.headers).chain(&self.rows) {
            out.push_str(&r.iter().map(cell).collect::<Vec<_>>().join(","));
            out.push('\n');
        }
        out
    }
}

/// What a table cell holds where there is nothing to show (a δ for a fixed-step method).
pub const NOTHING: &str = "—";

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nothing_is_an_empty_csv_field_and_a_dash_in_markdown() {
        let mut t = Table::new(&["method", "delta"]);
        t.push(vec!["tm-sbab2c".into(), NOTHING.into()]);
        assert_eq!(t.to_csv(), "method,delta\ntm-sbab2c,\n");
        assert!(t.to_markdown().contains("| —"));
    }

    #[test]
    fn markdown_and_csv_render_and_escape() {
        let mut t = Table::new(&["method", "error"]);
        t.push(vec!["tm-sbab2c".into(), "1.2e-7".into()]);
        t.push(vec!["a|b".into(), "x,\"y\"".into()]);
        let md = t.to_markdown();
        let lines: Vec<&str> = md.lines().collect();
        assert_eq!(lines.len(), 4);
        assert!(lines[0].starts_with("| method    | error"));
        assert!(lines[1].starts_with("|-----------|-"));
        assert!(lines[3].contains("a\\|b"));
        assert!(lines
            .iter()
            .all(|l| l.chars().count() == lines[0].chars().count()));
        assert_eq!(
            t.to_csv(),
            "method,error\ntm-sbab2c,1.2e-7\na|b,\"x,\"\"y\"\"\"\n"
        );
    }

    #[test]
    #[should_panic(expected = "row width")]
    fn rows_of_the_wrong_width_are_refused() {
        Table::new(&["a", "b"]).push(vec!["1".into()]);
    }
}
