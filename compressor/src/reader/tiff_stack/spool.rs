//! Decoded strips and tiles kept for the regions that share them. A region (a brick) decodes
//! the chunks of a page it covers; a chunk that reaches outside the region (a page stored as one
//! Deflate strip, or strips of full rows under bricks side by side) is needed again by the
//! regions beside it, and decoding it for each of them would inflate a 2048-pixel-wide page 64
//! times in 256³ bricks. [`ChunkSpool`] spools a chunk the second time a region needs it:
//! decodes it once more, writes its samples as the decoder gave them to an anonymous temporary
//! file (in the system's temporary directory, gone when the reader is dropped), and every
//! region after reads back only the rows it needs. Not the first time: a reader that reads one
//! region (a worker's brick job opens its own) would write whole pages it never reads again.
//! Memory stays one chunk per reading thread; the disk holds the decoded samples of the shared
//! chunks, as the gzip readers' spool holds a whole volume's. Where the temporary file cannot
//! be made or written, a chunk is decoded for each region as before. (Written here: the caches on
//! crates.io keep their values in memory, and this one's values are the size of the volume.)

use std::collections::hash_map::{Entry, HashMap};
use std::fs::File;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, OnceLock, PoisonError};

use ::tiff::decoder::DecodingResult;

use crate::reader::region::{read_at, write_at};

/// Chunks decoded once for the regions that share them, in a temporary file.
#[derive(Debug, Default)]
pub(super) struct ChunkSpool {
    /// The temporary file, made at the first chunk spooled (`None` inside: it could not be).
    file: OnceLock<Option<File>>,
    /// The end of what is written (or reserved for a write under way) in the file.
    end: Mutex<u64>,
    /// Each chunk a region has needed, by its slice and its index in the page: `None` once
    /// needed, then set once, by the second region that needs it, while the others needing it
    /// wait (`None` inside: it could not be spooled).
    chunks: Mutex<HashMap<(usize, u32), Option<Arc<OnceLock<Option<Spooled>>>>>>,
    /// Chunks decoded so far, by any region (what the spool saves is seen here).
    decoded: AtomicUsize,
}

/// Where a spooled chunk's samples lie and how to read them back.
#[derive(Debug, Clone, Copy)]
pub(super) struct Spooled {
    offset: u64,
    kind: Kind,
    /// Samples in a row of the chunk (its width times the channels).
    row: usize,
    rows: usize,
}

impl ChunkSpool {
    /// Counts one decoding of a chunk.
    pub(super) fn count_decoded(&self) {
        self.decoded.fetch_add(1, Ordering::Relaxed);
    }

    /// Chunks decoded so far.
    #[cfg(test)]
    pub(super) fn decoded(&self) -> usize {
        self.decoded.load(Ordering::Relaxed)
    }

    /// Whether a chunk was written to the file (it was made).
    #[cfg(test)]
    pub(super) fn has_file(&self) -> bool {
        self.file.get().is_some_and(Option::is_some)
    }

    /// Chunk `chunk` of slice `slice`, spooled: by `decode` (the chunk's samples, of `row` ×
    /// `rows` at least, or `None` where it fails) if no region has spooled it yet, while other
    /// regions wanting it wait. `None` the first time the chunk is asked for, and where it
    /// could not be decoded or spooled: the caller decodes it itself (and reports a failure).
    pub(super) fn get_or_spool(
        &self,
        slice: usize,
        chunk: u32,
        (row, rows): (usize, usize),
        decode: impl FnOnce() -> Option<DecodingResult>,
    ) -> Option<Spooled> {
        let cell = {
            let mut chunks = self.chunks.lock().unwrap_or_else(PoisonError::into_inner);
            match chunks.entry((slice, chunk)) {
                Entry::Vacant(v) => {
                    v.insert(None);
                    return None;
                }
                Entry::Occupied(mut o) => Arc::clone(o.get_mut().get_or_insert_default()),
            }
        };
        *cell.get_or_init(|| self.store(&decode()?, row, rows))
    }

    /// Writes the first `row` × `rows` samples of `data` to the file.
    fn store(&self, data: &DecodingResult, row: usize, rows: usize) -> Option<Spooled> {
        let file = self
            .file
            .get_or_init(|| match tempfile::tempfile() {
                Ok(f) => Some(f),
                Err(e) => {
                    tracing::warn!(error = %e, "no temporary file for decoded TIFF strips: \
                                   each brick decodes the strips it shares with others");
                    None
                }
            })
            .as_ref()?;
        let (kind, bytes) = to_bytes(data, row.checked_mul(rows)?)?;
        let offset = {
            let mut end = self.end.lock().unwrap_or_else(PoisonError::into_inner);
            let offset = *end;
            *end = offset.checked_add(bytes.len() as u64)?;
            offset
        };
        match write_at(file, &bytes, offset) {
            Ok(()) => Some(Spooled {
                offset,
                kind,
                row,
                rows,
            }),
            Err(e) => {
                tracing::debug!(error = %e, "a decoded TIFF strip not spooled");
                None
            }
        }
    }

    /// Rows `first..end` of a spooled chunk, as the decoder gave them (`None`: the file could
    /// not be read; the caller decodes the chunk).
    pub(super) fn rows(&self, s: &Spooled, first: usize, end: usize) -> Option<DecodingResult> {
        let file = self.file.get()?.as_ref()?;
        if first >= end || end > s.rows {
            return None;
        }
        let size = s.kind.size();
        let mut bytes = vec![0u8; (end - first) * s.row * size];
        let at = s.offset + (first * s.row * size) as u64;
        read_at(file, &mut bytes, at).ok()?;
        Some(from_bytes(s.kind, &bytes))
    }
}

/// The sample types of a spooled chunk, each stored in the machine's byte order (half floats
/// as `f32`, which they convert to exactly), with the conversions both ways.
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
                    $(Kind::$kind => std::mem::size_of::<$t>()),*
                }
            }
        }

        /// The first `n` samples of `data` as bytes (`None`: it holds fewer).
        fn to_bytes(data: &DecodingResult, n: usize) -> Option<(Kind, Vec<u8>)> {
            Some(match data {
                $(DecodingResult::$kind(v) => (
                    Kind::$kind,
                    v.get(..n)?.iter().flat_map(|s| s.to_ne_bytes()).collect(),
                ),)*
                DecodingResult::F16(v) => (
                    Kind::F32,
                    v.get(..n)?.iter().flat_map(|s| s.to_f32().to_ne_bytes()).collect(),
                ),
            })
        }

        /// Samples of `kind` from their bytes.
        fn from_bytes(kind: Kind, bytes: &[u8]) -> DecodingResult {
            match kind {
                $(Kind::$kind => DecodingResult::$kind(
                    bytes
                        .chunks_exact(std::mem::size_of::<$t>())
                        .map(|b| <$t>::from_ne_bytes(b.try_into().expect("chunks of its size")))
                        .collect(),
                ),)*
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

    #[test]
    fn samples_of_every_kind_come_back_as_they_went() {
        let spool = ChunkSpool::default();
        let chunks: [fn() -> DecodingResult; 6] = [
            || DecodingResult::U8(vec![0, 1, 2, 255, 7, 9]),
            || DecodingResult::U16(vec![0, 1, 65535, 300, 7, 9]),
            || DecodingResult::I16(vec![-32768, 1, 32767, -3, 7, 9]),
            || DecodingResult::U64(vec![u64::MAX, 1, 2, 3, 4, 5]),
            || DecodingResult::F32(vec![f32::NAN, -0.0, 1e-38, f32::INFINITY, 3.5, -2.25]),
            || DecodingResult::F64(vec![1e300, -1e-300, 0.5, 2.0, 3.0, 4.0]),
        ];
        for (i, make) in chunks.iter().enumerate() {
            let data = make();
            // Three samples a row, two rows; spooled the second time it is asked for.
            let first = spool.get_or_spool(i, 0, (3, 2), || panic!("decoded the first time"));
            assert!(first.is_none(), "{i}: not spooled the first time");
            let s = spool
                .get_or_spool(i, 0, (3, 2), || Some(make()))
                .expect("spooled");
            let back = spool.rows(&s, 0, 2).expect("read back");
            assert_eq!(format!("{back:?}"), format!("{data:?}"), "{i}");
            // The second row alone: the last three samples of the six, of the same type.
            let second = spool.rows(&s, 1, 2).expect("the second row");
            let listed = |d: &DecodingResult| {
                let text = format!("{d:?}");
                let (kind, rest) = text.split_once('(').expect("a variant");
                let samples: Vec<String> = rest
                    .trim_matches(|c| "[]()".contains(c))
                    .split(", ")
                    .map(str::to_owned)
                    .collect();
                (kind.to_owned(), samples)
            };
            let ((kind, all), (second_kind, row)) = (listed(&data), listed(&second));
            assert_eq!((second_kind, row), (kind, all[3..].to_vec()), "{i}");
            assert!(spool.rows(&s, 2, 3).is_none(), "past the chunk's rows");
        }
        // A second request for a spooled chunk does not decode it again.
        let again = spool.get_or_spool(0, 0, (3, 2), || panic!("decoded twice"));
        assert!(again.is_some());
        // A chunk that holds fewer samples than its size says is not spooled.
        assert!(spool.get_or_spool(9, 0, (3, 3), || None).is_none());
        let short = spool.get_or_spool(9, 0, (3, 3), || Some(DecodingResult::U8(vec![1; 8])));
        assert!(short.is_none());
    }

    #[test]
    fn half_floats_are_spooled_as_the_floats_they_convert_to() {
        let spool = ChunkSpool::default();
        let halves: Vec<_> = [0.5f32, -2.0, 65504.0, 6.1e-5]
            .into_iter()
            .map(::half::f16::from_f32)
            .collect();
        let want: Vec<f32> = halves.iter().map(|h| h.to_f32()).collect();
        assert!(spool.get_or_spool(0, 0, (2, 2), || None).is_none());
        let s = spool
            .get_or_spool(0, 0, (2, 2), || Some(DecodingResult::F16(halves)))
            .expect("spooled");
        match spool.rows(&s, 0, 2) {
            Some(DecodingResult::F32(v)) => assert_eq!(v, want),
            other => panic!("{other:?}"),
        }
    }
}
