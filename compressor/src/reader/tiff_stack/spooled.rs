//! A TIFF strip or tile in the spool of decoded chunks ([`crate::reader::spool`]): its bytes
//! as the `tiff` crate decoded them, its sample type and size noted beside them, and its rows
//! read back as the decoder gave them.

use ::tiff::decoder::DecodingResult;

use crate::reader::spool::{ChunkSpool, NativeBytes, Spooled};

/// Decoded chunks by their slice and their index in the page.
pub(super) type TiffSpool = ChunkSpool<(usize, u32), TiffChunk>;

/// What a spooled chunk holds.
#[derive(Debug, Clone, Copy)]
pub(super) struct TiffChunk {
    kind: Kind,
    /// Samples in a row of the chunk (its width times the channels).
    row: usize,
    rows: usize,
}

/// The first `row` × `rows` samples of `data`, to spool (`None`: it holds fewer).
pub(super) fn to_spool(
    data: &DecodingResult,
    row: usize,
    rows: usize,
) -> Option<(TiffChunk, Vec<u8>)> {
    let (kind, bytes) = to_bytes(data, row.checked_mul(rows)?)?;
    Some((TiffChunk { kind, row, rows }, bytes))
}

/// Rows `first..end` of the spooled chunk `key` (`s`), as the decoder gave them, for a region
/// that reads `pixels` of its `total` (`None`: past its rows, released, or the file could not
/// be read; the caller decodes the chunk).
pub(super) fn rows(
    spool: &TiffSpool,
    (key, s): (&(usize, u32), &Spooled<TiffChunk>),
    (first, end): (usize, usize),
    (pixels, total): (usize, usize),
) -> Option<DecodingResult> {
    let c = s.meta;
    if first >= end || end > c.rows {
        return None;
    }
    let size = c.kind.size();
    let at = ((first * c.row * size) as u64, (end - first) * c.row * size);
    let bytes = spool.read(key, s, at, (pixels as u64, total as u64))?;
    Some(from_bytes(c.kind, &bytes))
}

/// The sample types of a spooled chunk (half floats as `f32`, which they convert to exactly),
/// with the conversions both ways.
macro_rules! spooled_kinds {
    ($($kind:ident: $t:ty),*) => {
        /// A spooled chunk's sample type.
        #[derive(Debug, Clone, Copy, PartialEq, Eq)]
        enum Kind {
            $($kind),*
        }

        impl Kind {
            /// Bytes per sample.
            fn size(self) -> usize {
                match self {
                    $(Kind::$kind => <$t as NativeBytes>::SIZE),*
                }
            }
        }

        /// The first `n` samples of `data` as bytes (`None`: it holds fewer).
        fn to_bytes(data: &DecodingResult, n: usize) -> Option<(Kind, Vec<u8>)> {
            Some(match data {
                $(DecodingResult::$kind(v) => (Kind::$kind, <$t>::to_bytes(v.get(..n)?)),)*
                DecodingResult::F16(v) => {
                    let floats: Vec<f32> = v.get(..n)?.iter().map(|h| h.to_f32()).collect();
                    (Kind::F32, f32::to_bytes(&floats))
                }
            })
        }

        /// Samples of `kind` from their bytes.
        fn from_bytes(kind: Kind, bytes: &[u8]) -> DecodingResult {
            match kind {
                $(Kind::$kind => DecodingResult::$kind(<$t>::from_bytes(bytes)),)*
            }
        }
    };
}

spooled_kinds!(
    U8: u8, U16: u16, U32: u32, U64: u64, F32: f32, F64: f64, I8: i8, I16: i16, I32: i32, I64: i64
);

#[cfg(test)]
mod tests {
    use super::*;

    /// A variant's name and its samples, as `Debug` writes them (`DecodingResult` has no
    /// `PartialEq`).
    fn listed(d: &DecodingResult) -> (String, Vec<String>) {
        let text = format!("{d:?}");
        let (kind, rest) = text.split_once('(').expect("a variant");
        let samples = rest
            .trim_matches(|c| "[]()".contains(c))
            .split(", ")
            .map(str::to_owned)
            .collect();
        (kind.to_owned(), samples)
    }

    #[test]
    fn chunks_of_every_kind_come_back_as_they_went_row_by_row() {
        let spool = TiffSpool::default();
        let chunks: [fn() -> DecodingResult; 6] = [
            || DecodingResult::U8(vec![0, 1, 2, 255, 7, 9]),
            || DecodingResult::U16(vec![0, 1, 65535, 300, 7, 9]),
            || DecodingResult::I16(vec![-32768, 1, 32767, -3, 7, 9]),
            || DecodingResult::U64(vec![u64::MAX, 1, 2, 3, 4, 5]),
            || DecodingResult::F32(vec![f32::NAN, -0.0, 1e-38, f32::INFINITY, 3.5, -2.25]),
            || DecodingResult::F64(vec![1e300, -1e-300, 0.5, 2.0, 3.0, 4.0]),
        ];
        for (i, make) in chunks.iter().enumerate() {
            // Three samples a row, two rows; spooled the second time it is asked for.
            assert!(spool.get_or_spool((i, 0), 0, || None).is_none());
            let s = spool
                .get_or_spool((i, 0), 0, || to_spool(&make(), 3, 2))
                .expect("spooled");
            let back = rows(&spool, (&(i, 0), &s), (0, 2), (0, 6)).expect("read back");
            assert_eq!(listed(&back), listed(&make()), "{i}");
            // The second row alone: the last three samples of the six, of the same type.
            let (kind, all) = listed(&make());
            let second = rows(&spool, (&(i, 0), &s), (1, 2), (0, 6)).expect("the second row");
            assert_eq!(listed(&second), (kind, all[3..].to_vec()), "{i}");
            assert!(
                rows(&spool, (&(i, 0), &s), (2, 3), (0, 6)).is_none(),
                "past the chunk's rows"
            );
        }
        // A chunk that holds fewer samples than its size says is not spooled.
        assert!(to_spool(&DecodingResult::U8(vec![1; 8]), 3, 3).is_none());
    }

    #[test]
    fn half_floats_are_spooled_as_the_floats_they_convert_to() {
        let spool = TiffSpool::default();
        let halves: Vec<_> = [0.5f32, -2.0, 65504.0, 6.1e-5]
            .into_iter()
            .map(::half::f16::from_f32)
            .collect();
        let want: Vec<f32> = halves.iter().map(|h| h.to_f32()).collect();
        assert!(spool.get_or_spool((0, 0), 0, || None).is_none());
        let s = spool
            .get_or_spool((0, 0), 0, || to_spool(&DecodingResult::F16(halves), 2, 2))
            .expect("spooled");
        match rows(&spool, (&(0, 0), &s), (0, 2), (4, 4)) {
            Some(DecodingResult::F32(v)) => assert_eq!(v, want),
            other => panic!("{other:?}"),
        }
    }
}
