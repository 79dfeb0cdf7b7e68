//! The report: a case's row in the table and the CSV, its verdict, and the CSV's number and
//! field formatting.

/// One line of the table.
pub struct Row {
    /// The case's group.
    pub category: &'static str,
    /// The case's name.
    pub name: String,
    /// Its parameters in words.
    pub params: String,
    /// What happened, in words.
    pub outcome: String,
    /// max |image − reference| / max |reference|.
    pub max_rel: f64,
    /// 10·log10(Σ ref² / Σ err²).
    pub snr_db: f64,
    /// Non-finite pixels.
    pub non_finite: usize,
    /// Whether the case passed.
    pub pass: bool,
    /// Left out of `--quick` as a known failure.
    pub excluded: bool,
    /// The criterion in words.
    pub criterion: String,
    /// Run time.
    pub seconds: f64,
}

impl Row {
    /// `pass`, `FAIL` or `excluded`.
    pub fn verdict(&self) -> &'static str {
        if self.excluded {
            "excluded"
        } else if self.pass {
            "pass"
        } else {
            "FAIL"
        }
    }
}

/// A number for the CSV (scientific with `exp`): empty when not measured (NaN).
pub fn csv_number(x: f64, exp: bool) -> String {
    match (x.is_nan(), exp) {
        (true, _) => String::new(),
        (false, true) => format!("{x:e}"),
        (false, false) => format!("{x}"),
    }
}

/// A CSV field, quoted when it needs to be.
pub fn csv_field(s: &str) -> String {
    if s.contains([',', '"', '\n']) {
        format!("\"{}\"", s.replace('"', "\"\""))
    } else {
        s.to_string()
    }
}
