//! The format's error type, [`FormatError`], and the shorthand for its most common case, a
//! field out of range or inconsistent.

use super::OLDEST_READABLE_VERSION;
use super::{bricked, series};
use crate::entropy::EntropyError;
use crate::layout::LayoutError;
use thiserror::Error;

/// Errors reading or writing the format.
#[derive(Debug, Error, PartialEq)]
#[non_exhaustive]
pub enum FormatError {
    /// Not a wavesplat file.
    #[error("not a wavesplat file: magic bytes are {0:02x?}, expected \"WSPL\"")]
    BadMagic(Vec<u8>),
    /// A version this build cannot read (files older than [`OLDEST_READABLE_VERSION`] must be
    /// compressed again from their source).
    #[error("unsupported format version {found}; this build reads versions {OLDEST_READABLE_VERSION} to {supported}{}", if *found < *supported { " (the file was written by an older wavesplat: compress the source volume again)" } else { " (the file was written by a newer wavesplat)" })]
    UnsupportedVersion {
        /// Version in the file.
        found: u16,
        /// Version supported.
        supported: u16,
    },
    /// A bricked container ([`bricked`]) where a plain file was expected: its bricks are
    /// plain files, read through [`bricked::parse_bricked`].
    #[error("a bricked volume (format version {} or {}): each brick is a volume of its own, read through the bricked container", bricked::EXPLICIT_BRICKED_VERSION, bricked::BRICKED_VERSION)]
    Bricked,
    /// A series container ([`series`]) where a plain file was expected: its components are
    /// volume files, read through [`series::parse_series`].
    #[error("a time series (format version {}): each time point is a sum of volumes of its own, read through the series container", series::SERIES_VERSION)]
    Series,
    /// Input ended early.
    #[error("truncated {what}: needed {needed} bytes, {available} available")]
    Truncated {
        /// Structure being read.
        what: &'static str,
        /// Bytes needed.
        needed: u64,
        /// Bytes available.
        available: u64,
    },
    /// A checksum did not match.
    #[error("{what} checksum mismatch: stored {stored:#010x}, computed {computed:#010x}")]
    Checksum {
        /// Structure being checked.
        what: &'static str,
        /// Stored CRC.
        stored: u32,
        /// Computed CRC.
        computed: u32,
    },
    /// A field is out of range or inconsistent.
    #[error("invalid {what}: {detail}")]
    Invalid {
        /// Structure being read.
        what: &'static str,
        /// What was wrong.
        detail: String,
    },
    /// A size limit was exceeded.
    #[error("{what} of {size} bytes exceeds the limit of {limit}")]
    TooLarge {
        /// Structure.
        what: &'static str,
        /// Its size.
        size: u64,
        /// The limit.
        limit: u64,
    },
    /// Decoding would cost more than the caller's budget allows.
    #[error("decoding needs {need} {what}, over the budget of {budget}")]
    OverBudget {
        /// What is counted.
        what: &'static str,
        /// What the input declares it needs.
        need: u64,
        /// The budget.
        budget: u64,
    },
    /// Entropy-coded data was malformed.
    #[error("entropy-coded data: {0}")]
    Entropy(#[from] EntropyError),
    /// Geometry was invalid.
    #[error(transparent)]
    Layout(#[from] LayoutError),
}

pub(crate) fn invalid(what: &'static str, detail: impl Into<String>) -> FormatError {
    FormatError::Invalid {
        what,
        detail: detail.into(),
    }
}
