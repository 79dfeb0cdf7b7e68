//! `wavesplat bench stability`: runs the stiff and extreme numerical cases of
//! `wavesplat_harness::stability` (each judged against the reference ray caster with a
//! scale-free measure and its own pass criterion), prints them as a table and writes
//! `stability.csv`. The process exits non-zero when any case fails, after the table and the CSV
//! are written.

use anyhow::{bail, Context, Result};
use clap::Args;
use std::io::Write;
use std::path::PathBuf;
use wavesplat_harness::stability::{cases, csv_field, csv_number, excluded_row, run_case, Row};

/// Arguments of `wavesplat bench stability`.
#[derive(Args, Debug)]
pub struct StabilityArgs {
    /// Directory for `stability.csv`.
    #[arg(long, default_value = "wavesplat-stability")]
    pub out: PathBuf,
    /// The subset for the test suite: small volumes and images, fewer parameter values.
    #[arg(long)]
    pub quick: bool,
}

/// Runs the subcommand.
pub fn run(a: StabilityArgs) -> Result<()> {
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let cases = cases(a.quick);
    outln!(
        "{} stability cases ({}); max_rel = max|image - reference| / max|reference|, SNR = 10 log10(Σref² / Σerr²)",
        cases.len(),
        if a.quick { "quick" } else { "full" }
    );
    // Panics are reported in the table; keep their default messages off the terminal.
    let hook = std::panic::take_hook();
    std::panic::set_hook(Box::new(|_| {}));
    let mut rows = Vec::with_capacity(cases.len());
    outln!(
        "{:<18} {:<44} {:>10} {:>9} {:>4} {:<8} outcome",
        "category",
        "case",
        "max_rel",
        "SNR dB",
        "nonf",
        "pass"
    );
    for c in &cases {
        let row = if a.quick && c.known.is_some() {
            excluded_row(c)
        } else {
            run_case(c)
        };
        outln!(
            "{:<18} {:<44} {:>10.2e} {:>9.2} {:>4} {:<8} {}",
            row.category,
            row.name,
            row.max_rel,
            row.snr_db,
            row.non_finite,
            row.verdict(),
            row.outcome
        );
        rows.push(row);
    }
    std::panic::set_hook(hook);
    let path = a.out.join("stability.csv");
    let mut csv =
        std::fs::File::create(&path).with_context(|| format!("creating {}", path.display()))?;
    writeln!(
        csv,
        "category,case,parameters,outcome,max_rel,snr_db,non_finite,pass,criterion,seconds"
    )?;
    for r in &rows {
        writeln!(
            csv,
            "{},{},{},{},{},{},{},{},{},{:.3}",
            r.category,
            csv_field(&r.name),
            csv_field(&r.params),
            csv_field(&r.outcome),
            csv_number(r.max_rel, true),
            csv_number(r.snr_db, false),
            r.non_finite,
            if r.excluded {
                "excluded"
            } else if r.pass {
                "true"
            } else {
                "false"
            },
            csv_field(&r.criterion),
            r.seconds
        )?;
    }
    let failed: Vec<&Row> = rows.iter().filter(|r| !r.pass && !r.excluded).collect();
    let excluded = rows.iter().filter(|r| r.excluded).count();
    outln!(
        "{} of {} cases passed, {} failed, {excluded} known failures excluded; wrote {}",
        rows.len() - failed.len() - excluded,
        rows.len(),
        failed.len(),
        path.display()
    );
    if !failed.is_empty() {
        for r in &failed {
            outln!(
                "FAIL {} / {}: {} ({})",
                r.category,
                r.name,
                r.outcome,
                r.criterion
            );
        }
        bail!("{} of {} stability cases failed", failed.len(), rows.len());
    }
    Ok(())
}
