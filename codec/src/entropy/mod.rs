//! Entropy coding toolkit of the wavesplat bitstream (paper §4.3, Table 3).
//!
//! It owns every layer between symbols and bytes: the MSB-first bit writer and reader with an
//! emitting sink and a counting sink that share one interface, so that a rate estimate is the
//! size actually written ([`bits`]); length-limited canonical Huffman codes with a compact
//! serialization of their code lengths and a table-driven decoder using the paper's 10-bit
//! look-up tables ([`huffman`]); JPEG-style magnitude categories that map unbounded integers to a
//! small Huffman alphabet plus raw extra bits ([`category`]); and an adaptive binary range coder
//! with integer binarizations, the arithmetic-coding option named as future work in the paper
//! ([`range`]); and static-model rANS with tables described by small
//! integer levels, fractional code lengths at a table look-up per symbol ([`rans`]). Every
//! decoder here reads untrusted bytes: malformed or truncated input yields an
//! [`EntropyError`], never a panic or an endless loop.
//!
//! ```
//! use wavesplat_codec::entropy::bits::{BitCounter, BitReader, BitSink, BitWriter};
//! use wavesplat_codec::entropy::huffman::{HuffmanCode, HuffmanDecoder};
//!
//! let code = HuffmanCode::from_frequencies(&[10, 3, 0, 1], 16);
//! let (mut writer, mut counter) = (BitWriter::new(), BitCounter::new());
//! for sym in [0, 1, 0, 3] {
//!     code.encode(sym, &mut writer);
//!     code.encode(sym, &mut counter);
//! }
//! assert_eq!(writer.bits(), counter.bits());
//! let bytes = writer.finish();
//! let decoder = HuffmanDecoder::new(&code);
//! let mut reader = BitReader::new(&bytes);
//! let decoded: Vec<usize> = (0..4).map(|_| decoder.decode(&mut reader).unwrap()).collect();
//! assert_eq!(decoded, [0, 1, 0, 3]);
//! ```

pub mod bits;
pub mod category;
pub mod huffman;
pub mod range;
pub mod rans;

/// Errors of the entropy decoders and table validation.
#[derive(Debug, thiserror::Error, PartialEq, Eq, Clone)]
#[non_exhaustive]
pub enum EntropyError {
    /// The input ended before a complete value could be read.
    #[error("unexpected end of input: needed {needed} more bits, only {remaining} remain")]
    UnexpectedEnd {
        /// Bits the value required.
        needed: u64,
        /// Bits that were left in the input.
        remaining: u64,
    },
    /// The bits at `position` are not a codeword of the Huffman code in use.
    #[error("invalid Huffman codeword at bit position {position}")]
    InvalidCode {
        /// Bit offset (from the start of the reader's input) where decoding failed.
        position: u64,
    },
    /// A code-length table is malformed (description says what is wrong).
    #[error("invalid Huffman table: {0}")]
    InvalidTable(String),
    /// A header names a built-in table that this build does not hold.
    #[error("table {0} is named built-in, and this build holds no such table")]
    NoBuiltinTable(usize),
    /// A decoded or requested value lies outside its allowed range.
    #[error("{what} is {value}, allowed range is {min}..={max}")]
    ValueOutOfRange {
        /// What the value is (e.g. "magnitude category").
        what: &'static str,
        /// The offending value (saturated to `i128`).
        value: i128,
        /// Smallest allowed value.
        min: i128,
        /// Largest allowed value.
        max: i128,
    },
}

impl EntropyError {
    /// Shorthand for [`EntropyError::ValueOutOfRange`].
    pub(crate) fn out_of_range(
        what: &'static str,
        value: impl Into<i128>,
        min: impl Into<i128>,
        max: impl Into<i128>,
    ) -> Self {
        EntropyError::ValueOutOfRange {
            what,
            value: value.into(),
            min: min.into(),
            max: max.into(),
        }
    }
}
