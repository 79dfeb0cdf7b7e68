//! Decoded chunks kept for the regions that share them. A region (a brick) decodes the chunks
//! of a file it covers: a TIFF page's strips or tiles, a Zarr array's chunks. A chunk that
//! reaches outside the region (a page stored as one Deflate strip, a Zarr chunk of one whole
//! plane) is needed again by the regions beside it, and decoding it for each would decode a
//! 2048-pixel-wide plane 64 times in 256³ bricks. [`ChunkSpool`] spools a chunk the second
//! time a region needs it: decodes it once more, writes its samples to an anonymous temporary
//! file (in the system's temporary directory, gone when the reader is dropped), and every
//! region after reads back only the bytes it needs. Not the first time: a reader that reads one
//! region (a worker's brick job opens its own) would write whole chunks it never reads again.
//! Memory stays one chunk per reading thread; the disk holds the decoded samples of the shared
//! chunks, as the gzip readers' spool holds a whole volume's. Where the temporary file cannot
//! be made or written, a chunk is decoded for each region as before. (Written here: the caches
//! on crates.io keep their values in memory, and these values add up to the volume; the file
//! is a [`ScratchFile`].)

use std::collections::hash_map::{Entry, HashMap};
use std::hash::Hash;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, OnceLock, PoisonError};

use crate::scratch::ScratchFile;

/// Chunks decoded once for the regions that share them, in a temporary file; each found by
/// its key `K` (its place in the file), with what its reader needs to know of it, `M`.
#[derive(Debug)]
pub(crate) struct ChunkSpool<K, M> {
    /// The temporary file and the bytes it may hold, made at the first chunk spooled (`None`
    /// inside: it could not be).
    file: OnceLock<Option<(ScratchFile, u64)>>,
    /// The bytes the file may hold, where not [`SPOOL_DISK_SHARE`] of the free space (tests).
    budget: Option<u64>,
    /// Each chunk a region has needed: `None` once needed, then set once, by the second region
    /// that needs it, while the others needing it wait (`None` inside: it was not spooled).
    chunks: Mutex<HashMap<K, Option<SpoolCell<M>>>>,
    /// Chunks decoded so far, by any region (what the spool saves is seen here).
    decoded: AtomicUsize,
    /// Set when a chunk could not be spooled (its budget spent, no file, a failed write):
    /// no chunk is decoded for the spool after that, only by the regions themselves.
    refused: AtomicBool,
}

impl<K, M> Default for ChunkSpool<K, M> {
    fn default() -> Self {
        ChunkSpool {
            file: OnceLock::new(),
            budget: None,
            chunks: Mutex::new(HashMap::new()),
            decoded: AtomicUsize::new(0),
            refused: AtomicBool::new(false),
        }
    }
}

/// The share of the temporary directory's free space (when the spool's file is made) that
/// the spool may fill, as the kept tops may theirs ([`crate::encode::TOP_DISK_SHARE`]):
/// beyond it, chunks are decoded for each region that needs them.
pub(crate) const SPOOL_DISK_SHARE: f64 = 0.25;

/// A chunk's place in the spool, set once (`None` inside: it was not spooled).
type SpoolCell<M> = Arc<OnceLock<Option<Spooled<M>>>>;

/// Where a spooled chunk's bytes lie, and what its reader noted of it.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Spooled<M> {
    offset: u64,
    len: u64,
    pub(crate) meta: M,
}

impl<K: Hash + Eq, M: Copy> ChunkSpool<K, M> {
    /// Counts one decoding of a chunk.
    pub(crate) fn count_decoded(&self) {
        self.decoded.fetch_add(1, Ordering::Relaxed);
    }

    /// Chunks decoded so far.
    #[cfg(test)]
    pub(crate) fn decoded(&self) -> usize {
        self.decoded.load(Ordering::Relaxed)
    }

    /// Whether a chunk was written to the file (it was made).
    #[cfg(test)]
    pub(crate) fn has_file(&self) -> bool {
        self.file.get().is_some_and(Option::is_some)
    }

    /// A spool whose file may hold `bytes`.
    #[cfg(test)]
    pub(crate) fn with_budget(bytes: u64) -> Self {
        ChunkSpool {
            budget: Some(bytes),
            ..ChunkSpool::default()
        }
    }

    /// The chunk `key`, spooled: by `decode` (what to note of it and its bytes, or `None`
    /// where it fails) if no region has spooled it yet, while other regions wanting it wait.
    /// `None` the first time the chunk is asked for, where it could not be decoded or
    /// spooled, and once any chunk could not be stored: the caller decodes it itself (and
    /// reports a failure).
    pub(crate) fn get_or_spool(
        &self,
        key: K,
        decode: impl FnOnce() -> Option<(M, Vec<u8>)>,
    ) -> Option<Spooled<M>> {
        let cell = {
            let mut chunks = self.chunks.lock().unwrap_or_else(PoisonError::into_inner);
            match chunks.entry(key) {
                Entry::Vacant(v) => {
                    v.insert(None);
                    return None;
                }
                Entry::Occupied(mut o) => Arc::clone(o.get_mut().get_or_insert_default()),
            }
        };
        *cell.get_or_init(|| {
            if self.refused.load(Ordering::Relaxed) {
                return None;
            }
            let (meta, bytes) = decode()?;
            let stored = self.store(&bytes, meta);
            if stored.is_none() {
                self.refused.store(true, Ordering::Relaxed);
            }
            stored
        })
    }

    /// Writes `bytes` to the file.
    fn store(&self, bytes: &[u8], meta: M) -> Option<Spooled<M>> {
        let (file, budget) = self
            .file
            .get_or_init(|| {
                let made = ScratchFile::new(None).and_then(|f| {
                    let budget = match self.budget {
                        Some(b) => b,
                        None => {
                            let free = fs2::available_space(tempfile::env::temp_dir())?;
                            (free as f64 * SPOOL_DISK_SHARE) as u64
                        }
                    };
                    Ok((f, budget))
                });
                match made {
                    Ok(spool) => Some(spool),
                    Err(e) => {
                        tracing::warn!(error = %e, "no temporary file for decoded chunks: \
                                       each region decodes the chunks it shares with others");
                        None
                    }
                }
            })
            .as_ref()?;
        let len = bytes.len() as u64;
        if file.len().saturating_add(len) > *budget {
            tracing::debug!(budget, "the spool of decoded chunks is full");
            return None;
        }
        match file.append(bytes) {
            Ok(offset) => Some(Spooled { offset, len, meta }),
            Err(e) => {
                tracing::debug!(error = %e, "a decoded chunk not spooled");
                None
            }
        }
    }

    /// Bytes `at..at + len` of a spooled chunk (`None`: past its end, or the file could not
    /// be read; the caller decodes the chunk).
    pub(crate) fn read(&self, s: &Spooled<M>, at: u64, len: usize) -> Option<Vec<u8>> {
        let (file, _) = self.file.get()?.as_ref()?;
        if at.checked_add(len as u64)? > s.len {
            return None;
        }
        file.read(s.offset + at, len).ok()
    }
}

/// Samples as bytes in the machine's order, and back: what a spool holds.
pub(crate) trait NativeBytes: Copy + Sized {
    /// Bytes of one sample.
    const SIZE: usize;
    /// `samples` as bytes.
    fn to_bytes(samples: &[Self]) -> Vec<u8>;
    /// The samples `bytes` hold (whole samples; a trailing part is left out).
    fn from_bytes(bytes: &[u8]) -> Vec<Self>;
}

macro_rules! native_bytes {
    ($($t:ty),*) => {$(
        impl NativeBytes for $t {
            const SIZE: usize = std::mem::size_of::<$t>();
            fn to_bytes(samples: &[Self]) -> Vec<u8> {
                samples.iter().flat_map(|s| s.to_ne_bytes()).collect()
            }
            fn from_bytes(bytes: &[u8]) -> Vec<Self> {
                bytes
                    .chunks_exact(Self::SIZE)
                    .map(|b| <$t>::from_ne_bytes(b.try_into().expect("chunks of its size")))
                    .collect()
            }
        }
    )*};
}

native_bytes!(u8, u16, u32, u64, i8, i16, i32, i64, f32, f64);

/// For the readers' tests: the boxes of `brick` voxels over a volume of `dims` (cut at its far
/// faces), each passed to `read` (which reads and checks it), by two threads at once.
#[cfg(test)]
pub(crate) fn read_bricks_from_two_threads(
    dims: [usize; 3],
    brick: [usize; 3],
    read: impl Fn([usize; 3], [usize; 3]) + Sync,
) {
    let mut boxes = Vec::new();
    for z in (0..dims[2]).step_by(brick[2]) {
        for y in (0..dims[1]).step_by(brick[1]) {
            for x in (0..dims[0]).step_by(brick[0]) {
                let size = [
                    (dims[0] - x).min(brick[0]),
                    (dims[1] - y).min(brick[1]),
                    (dims[2] - z).min(brick[2]),
                ];
                boxes.push(([x, y, z], size));
            }
        }
    }
    std::thread::scope(|scope| {
        for first in 0..2 {
            let (boxes, read) = (&boxes, &read);
            scope.spawn(move || {
                for &(origin, size) in boxes.iter().skip(first).step_by(2) {
                    read(origin, size);
                }
            });
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_chunk_is_spooled_the_second_time_and_read_back_as_written() {
        let spool: ChunkSpool<u32, u8> = ChunkSpool::default();
        let first = spool.get_or_spool(7, || panic!("decoded the first time"));
        assert!(first.is_none(), "not spooled the first time");
        assert!(!spool.has_file());
        let samples = [f32::NAN, -0.0, 1e-38, f32::INFINITY, 3.5, -2.25];
        let s = spool
            .get_or_spool(7, || Some((3, f32::to_bytes(&samples))))
            .expect("spooled the second time");
        assert_eq!(s.meta, 3);
        let back = spool.read(&s, 16, 8).expect("the last two samples");
        assert_eq!(f32::from_bytes(&back), [3.5, -2.25]);
        assert!(spool.read(&s, 17, 8).is_none(), "past the end");
        // Spooled once: later requests do not decode it again.
        let again = spool.get_or_spool(7, || panic!("decoded a third time"));
        assert_eq!(again.map(|s| s.meta), Some(3));
        // A chunk that fails to decode is not spooled, and its later requests decode it.
        assert!(spool.get_or_spool(8, || None).is_none());
        assert!(spool.get_or_spool(8, || None).is_none());
        let mut asked = false;
        assert!(spool
            .get_or_spool(8, || {
                asked = true;
                None
            })
            .is_none());
        assert!(!asked, "the failure is kept: its caller decodes it itself");
    }

    /// Beyond its share of the disk the spool takes no more chunks: their regions decode them.
    #[test]
    fn a_full_spool_takes_no_more_chunks() {
        let spool: ChunkSpool<u32, ()> = ChunkSpool::with_budget(40);
        let chunk = || Some(((), vec![7u8; 24]));
        for key in [1, 2] {
            assert!(spool
                .get_or_spool(key, || panic!("decoded the first time"))
                .is_none());
        }
        assert!(spool.get_or_spool(1, chunk).is_some(), "24 of 40 bytes");
        assert!(spool.get_or_spool(2, chunk).is_none(), "48 of 40 bytes");
        assert!(spool.get_or_spool(1, || panic!("spooled")).is_some());
        // Once full, a chunk is no longer decoded for the spool (only by its regions).
        assert!(spool.get_or_spool(3, || panic!("the first time")).is_none());
        assert!(spool
            .get_or_spool(3, || panic!("decoded for a full spool"))
            .is_none());
    }

    #[test]
    fn samples_of_every_type_come_back_as_they_went() {
        fn round<T: NativeBytes + PartialEq + std::fmt::Debug>(v: &[T]) {
            assert_eq!(T::from_bytes(&T::to_bytes(v)), v);
        }
        round(&[0u8, 1, 255]);
        round(&[0u16, 1, 65535, 300]);
        round(&[-32768i16, 1, 32767]);
        round(&[u64::MAX, 1]);
        round(&[i64::MIN, -1]);
        round(&[1e300f64, -1e-300, 0.5]);
        round(&[i8::MIN, 7]);
    }
}
