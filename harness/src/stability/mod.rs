//! The stiff and extreme numerical cases of the pipeline (`wavesplat bench stability` prints
//! them as a table and writes `stability.csv`; `tests/stability.rs` runs the quick subset), each
//! judged against the reference ray caster with a scale-free measure and its own pass
//! criterion. This module owns the case table, running one case and its row.
//!
//! Two kinds of case. *Renderer* cases splat every coefficient of an exact decomposition and
//! compare with the reference ray caster on the volume those coefficients reconstruct
//! (`PaddedVolume::from_coefficients`), so only the splatting is judged (depth cue, family ×
//! depth, near-axis views, magnitudes). *Pipeline* cases compress, decode the file and splat it,
//! and compare with the reference on the original volume (`PaddedVolume::from_volume`), so the
//! encoder, quantizer and colour transform are judged too (quantizer bits, magnitudes, constant
//! and degenerate colour). Invalid input (NaN / Inf voxels or coefficients, out-of-range
//! options) must be refused with a typed error. Each case runs under `catch_unwind`, so a panic
//! is reported as that case's failure and the rest still run.
//!
//! Measures, all relative so a 1e30 volume is judged like a 1e-30 one: `max_rel` = max |image −
//! reference| / max |reference| over all pixels and channels, and the conventional SNR
//! `10·log10(Σ ref² / Σ err²)`. A zero reference passes only an exactly zero image. Non-finite
//! pixels fail every case. The process exits non-zero when any case fails, after the table and
//! the CSV are written.

mod cases;
mod inputs;
mod report;
mod run;

use anyhow::Result;
use wavesplat_viewer::Image;

pub use cases::cases;
pub use report::{csv_field, csv_number, Row};
pub use run::{excluded_row, run_case};

/// SNR the accuracy tests (`viewer/tests/accuracy.rs`) require of splats against the reference
/// on clean data: lossless cases must reach it whatever the scale or angle.
const LOSSLESS_DB: f64 = 50.0;
/// SNR the depth-cue test (`viewer/tests/render.rs`) requires at k ≤ 0.5 per voxel.
const CUE_DB: f64 = 30.0;
/// Largest error of a depth-cued image relative to the peak of the same view un-cued, as
/// [`MATCH`] allows un-cued images: the splats sum f32 terms of the un-cued scale, so that is
/// the scale of their error whatever the cue leaves.
const CUE_FLOOR: f64 = 1e-2;

const MATCH: Criterion = Criterion::Match {
    snr_db: LOSSLESS_DB,
    max_rel: 1e-2,
};

/// How a case passes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Criterion {
    /// Finite, SNR ≥ `snr_db` and max_rel ≤ `max_rel`.
    Match { snr_db: f64, max_rel: f64 },
    /// Finite and no worse than a black image: Σ err² ≤ Σ ref² (SNR ≥ 0 dB).
    NoWorseThanZero,
    /// The input is invalid: a typed error is the right answer.
    Refused,
}

impl Criterion {
    /// The criterion in words.
    pub fn describe(&self) -> String {
        match self {
            Criterion::Match { snr_db, max_rel } if *snr_db == f64::NEG_INFINITY => {
                format!("finite, max_rel <= {max_rel:e}")
            }
            Criterion::Match { snr_db, max_rel } => {
                format!("finite, SNR >= {snr_db} dB, max_rel <= {max_rel:e}")
            }
            Criterion::NoWorseThanZero => "finite, SNR >= 0 dB (no worse than zero)".into(),
            Criterion::Refused => "refused with a typed error".into(),
        }
    }
}

/// What a case produced.
pub enum Outcome {
    /// An image and its reference; `scale` (when given) replaces the reference's peak as the
    /// denominator of max_rel.
    Images {
        image: Image,
        reference: Image,
        scale: Option<f64>,
    },
    /// The system refused the input with this (typed) error.
    Rejected(String),
}

type Runner = Box<dyn Fn() -> Result<Outcome>>;

/// One case: what it is, how it passes and how to run it.
pub struct Case {
    /// Its group in the table.
    pub category: &'static str,
    /// Its name.
    pub name: String,
    /// Its parameters in words.
    pub params: String,
    /// How it passes.
    pub criterion: Criterion,
    run: Runner,
    /// A known failure left out of `--quick`, and why.
    pub known: Option<&'static str>,
}

fn case(
    category: &'static str,
    name: impl Into<String>,
    params: impl Into<String>,
    criterion: Criterion,
    run: impl Fn() -> Result<Outcome> + 'static,
) -> Case {
    Case {
        category,
        name: name.into(),
        params: params.into(),
        criterion,
        run: Box::new(run),
        known: None,
    }
}

impl Case {
    fn known_failure(mut self, why: &'static str) -> Case {
        self.known = Some(why);
        self
    }
}
