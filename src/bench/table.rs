//! Markdown tables of benchmark results.

/// A Markdown table built row by row.
#[derive(Clone, Debug, Default)]
pub struct Markdown {
    header: Vec<String>,
    rows: Vec<Vec<String>>,
}

impl Markdown {
    /// A table with these column headings.
    pub fn new(header: &[&str]) -> Self {
        Markdown {
            header: header.iter().map(|h| h.to_string()).collect(),
            rows: Vec::new(),
        }
    }

    /// Adds a row (missing cells are left empty, extra ones dropped).
    pub fn row(&mut self, mut cells: Vec<String>) {
        cells.resize(self.header.len(), String::new());
        self.rows.push(cells);
    }

    /// The table's text.
    pub fn render(&self) -> String {
        let line = |cells: &[String]| format!("| {} |\n", cells.join(" | "));
        let mut s = line(&self.header);
        s += &format!("|{}\n", "---|".repeat(self.header.len()));
        for r in &self.rows {
            s += &line(r);
        }
        s
    }
}

impl Markdown {
    /// The same table as HTML (cells escaped).
    pub fn html(&self) -> String {
        let row = |tag: &str, cells: &[String]| {
            let cells: String = cells
                .iter()
                .map(|c| format!("<{tag}>{}</{tag}>", escape_html(c)))
                .collect();
            format!("<tr>{cells}</tr>\n")
        };
        let mut s = String::from("<table>\n");
        s += &row("th", &self.header);
        for r in &self.rows {
            s += &row("td", r);
        }
        s + "</table>\n"
    }
}

/// `text` with HTML's special characters escaped.
pub fn escape_html(text: &str) -> String {
    text.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

/// `v` with thousands as `k` (`9.8k`), below as an integer.
pub fn count(v: f64) -> String {
    if v >= 1e3 {
        format!("{:.1}k", v / 1e3)
    } else {
        format!("{v:.0}")
    }
}

/// A count as a short tag: `2.5k`, `10k`, `160k`, `1.5M`.
pub fn short(v: f64) -> String {
    let (x, unit) = if v >= 1e6 {
        (v / 1e6, "M")
    } else if v >= 1e3 {
        (v / 1e3, "k")
    } else {
        (v, "")
    };
    let s = format!("{x:.1}");
    format!("{}{unit}", s.trim_end_matches(".0"))
}

/// Bytes as kB or MB.
pub fn bytes(v: f64) -> String {
    if v >= 1e6 {
        format!("{:.1} MB", v / 1e6)
    } else {
        format!("{:.0} kB", v / 1e3)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn renders_a_header_a_rule_and_padded_rows() {
        let mut t = Markdown::new(&["a", "b"]);
        t.row(vec!["1".into()]);
        assert_eq!(t.render(), "| a | b |\n|---|---|\n| 1 |  |\n");
        assert_eq!(count(9_800.0), "9.8k");
        assert_eq!(short(2_500.0), "2.5k");
        assert_eq!(short(160_000.0), "160k");
        assert_eq!(short(40.0), "40");
        assert_eq!(bytes(67_000.0), "67 kB");
        assert_eq!(bytes(6_100_000.0), "6.1 MB");
    }
}
