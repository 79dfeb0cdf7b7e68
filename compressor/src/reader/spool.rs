//! Decoded chunks kept for the regions that share them. A region (a brick) decodes the chunks
//! of a file it covers: a TIFF page's strips or tiles, a Zarr array's chunks. A chunk that
//! reaches outside the region (a page stored as one Deflate strip, a Zarr chunk of one whole
//! plane) is needed again by the regions beside it, and decoding it for each would decode a
//! 2048-pixel-wide plane 64 times in 256³ bricks. [`ChunkSpool`] spools a chunk the second
//! time a region needs it: decodes it once more, writes its samples to an anonymous temporary
//! file (in the system's temporary directory, gone when the reader is dropped), and every
//! region after reads back only the bytes it needs. Not the first time: a reader that reads one
//! region (a worker's brick job opens its own) would write whole chunks it never reads again.
//! Once the regions have read every sample of a chunk, its bytes are released (a hole punched
//! in the file), so the disk holds the shared chunks of the bricks being read, a layer of
//! bricks, not the volume's; a later pass over the volume spools a released chunk again the
//! first time it needs it. Where its share of the disk is spent (regions that read a chunk
//! twice, or not at all, throw its count off; a worker reads only some of the bricks), the
//! oldest chunks are released to make room. Memory stays one chunk per reading thread. Where
//! the temporary file cannot be made or written, a chunk is decoded for each region as before.
//! (Written here: the caches on crates.io keep their values in memory, and these values add up
//! to the volume; the file is a [`ScratchFile`].)

use std::borrow::Borrow;
use std::collections::hash_map::{Entry, HashMap};
use std::collections::VecDeque;
use std::hash::Hash;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
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
    /// Each chunk a region has needed, and where it stands, and the spooled ones in the order
    /// they were written.
    chunks: Mutex<Chunks<K, M>>,
    /// Chunks decoded so far, by any region (what the spool saves is seen here).
    decoded: AtomicUsize,
    /// Bytes of spooled chunks not yet released: what the budget bounds.
    held: AtomicU64,
    /// The most bytes held at once.
    peak: AtomicU64,
    /// The size of the last chunk spooled: the next is not decoded where no room can be made
    /// for one of this size (the chunks of a file are mostly of one size).
    last_len: AtomicU64,
    /// Set when the file could not be made or written: no chunk is decoded for the spool
    /// after that, only by the regions themselves.
    refused: AtomicBool,
    /// Set when a hole could not be punched: spooled chunks stay to the end.
    keep_all: AtomicBool,
}

/// The chunks a spool knows of.
#[derive(Debug)]
struct Chunks<K, M> {
    /// Each chunk a region has needed, and where it stands.
    slots: HashMap<K, Slot<M>>,
    /// The chunks written, oldest first, by their key and offset (an entry whose chunk was
    /// released since is passed over): where the budget is spent, the oldest are released
    /// to make room, as the regions are read in order and have mostly done with them.
    written: VecDeque<(K, u64)>,
}

/// Where a chunk stands in the spool.
#[derive(Debug)]
enum Slot<M> {
    /// Needed and not spooled, with the samples of it the regions that decoded it themselves
    /// have read: the next region needing it spools it.
    Seen(u64),
    /// Spooled (or being spooled, or not spooled: `None` in the cell), with the samples of it
    /// that regions have read back so far.
    Spool(SpoolCell<M>, u64),
    /// Read back whole by the regions and released: a region needing it again (another pass
    /// over the volume) spools it again.
    Released,
}

impl<K, M> Default for ChunkSpool<K, M> {
    fn default() -> Self {
        ChunkSpool {
            file: OnceLock::new(),
            budget: None,
            chunks: Mutex::new(Chunks {
                slots: HashMap::new(),
                written: VecDeque::new(),
            }),
            decoded: AtomicUsize::new(0),
            held: AtomicU64::new(0),
            peak: AtomicU64::new(0),
            last_len: AtomicU64::new(0),
            refused: AtomicBool::new(false),
            keep_all: AtomicBool::new(false),
        }
    }
}

impl<K, M> Drop for ChunkSpool<K, M> {
    fn drop(&mut self) {
        if let Some(Some((file, _))) = self.file.get() {
            tracing::debug!(
                chunks_decoded = self.decoded.load(Ordering::Relaxed),
                bytes_written = file.len(),
                peak_bytes_held = self.peak.load(Ordering::Relaxed),
                bytes_held = self.held.load(Ordering::Relaxed),
                "spool of decoded chunks closed"
            );
        }
    }
}

/// The share of the temporary directory's free space (when the spool's file is made) that
/// the spool may fill, as the kept tops may theirs ([`crate::encode::TOP_DISK_SHARE`]):
/// beyond it, chunks are decoded for each region that needs them until others are released.
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

/// Why a chunk was not spooled.
enum NotSpooled {
    /// It could not be decoded: its regions decode it themselves (and report the failure).
    Failed,
    /// The budget was spent: a later region may spool it once others are released.
    Full,
}

impl<K: Hash + Eq + Clone, M: Copy> ChunkSpool<K, M> {
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

    /// Bytes spooled and not yet released, and the most there were at once.
    #[cfg(test)]
    pub(crate) fn held(&self) -> (u64, u64) {
        (
            self.held.load(Ordering::Relaxed),
            self.peak.load(Ordering::Relaxed),
        )
    }

    /// A spool whose file may hold `bytes`.
    #[cfg(test)]
    pub(crate) fn with_budget(bytes: u64) -> Self {
        let mut spool = ChunkSpool::default();
        spool.budget = Some(bytes);
        spool
    }

    /// The chunk `key`, spooled: by `decode` (what to note of it and its bytes, or `None`
    /// where it fails) if no region has spooled it yet, while other regions wanting it wait.
    /// `None` the first time the chunk is asked for, where it could not be decoded or
    /// spooled, and once the file could not be made or written: the caller decodes it itself
    /// (and reports a failure). `samples`: what the caller reads of the chunk (in the unit of
    /// [`ChunkSpool::read`]'s total), counted here where it decodes the chunk itself.
    pub(crate) fn get_or_spool(
        &self,
        key: K,
        samples: u64,
        decode: impl FnOnce() -> Option<(M, Vec<u8>)>,
    ) -> Option<Spooled<M>> {
        let cell = 'cell: {
            let mut chunks = self.chunks.lock().unwrap_or_else(PoisonError::into_inner);
            match chunks.slots.entry(key.clone()) {
                Entry::Vacant(v) => {
                    v.insert(Slot::Seen(samples));
                    return None;
                }
                Entry::Occupied(mut o) => {
                    let slot = o.get_mut();
                    let read = match slot {
                        Slot::Spool(cell, _) => break 'cell Arc::clone(cell),
                        Slot::Seen(read) => *read,
                        Slot::Released => 0,
                    };
                    let cell = SpoolCell::default();
                    *slot = Slot::Spool(Arc::clone(&cell), read);
                    cell
                }
            }
        };
        let mut full = false;
        let got = *cell.get_or_init(|| match self.spool(&key, decode) {
            Ok(s) => Some(s),
            Err(NotSpooled::Full) => {
                full = true;
                None
            }
            Err(NotSpooled::Failed) => None,
        });
        if got.is_none() {
            // The caller decodes the chunk itself: its samples count. Where the budget was
            // spent, the chunk is spooled when asked for again if there is room by then.
            let mut chunks = self.chunks.lock().unwrap_or_else(PoisonError::into_inner);
            if let Some(slot) = chunks.slots.get_mut(&key) {
                match slot {
                    Slot::Spool(c, read) if Arc::ptr_eq(c, &cell) => {
                        *read = read.saturating_add(samples);
                        if full {
                            *slot = Slot::Seen(*read);
                        }
                    }
                    Slot::Seen(read) => *read = read.saturating_add(samples),
                    _ => {}
                }
            }
        }
        got
    }

    /// Decodes chunk `key` by `decode` and writes it to the file, within the budget (the
    /// oldest chunks released to make room).
    fn spool(
        &self,
        key: &K,
        decode: impl FnOnce() -> Option<(M, Vec<u8>)>,
    ) -> Result<Spooled<M>, NotSpooled> {
        if self.refused.load(Ordering::Relaxed) {
            return Err(NotSpooled::Failed);
        }
        let Some((file, budget)) = self.file() else {
            self.refused.store(true, Ordering::Relaxed);
            return Err(NotSpooled::Failed);
        };
        // Not decoded where a chunk like the last spooled would not fit the whole budget, or
        // no room can be made for it.
        let like_last = self.last_len.load(Ordering::Relaxed).max(1);
        if self.held.load(Ordering::Relaxed).saturating_add(like_last) > budget
            && !self.make_room(file, like_last, budget)
        {
            return Err(NotSpooled::Full);
        }
        let (meta, bytes) = decode().ok_or(NotSpooled::Failed)?;
        let len = bytes.len() as u64;
        // The bytes are reserved before they are written: threads at once stay within it.
        let held = loop {
            let reserved = self
                .held
                .fetch_update(Ordering::AcqRel, Ordering::Acquire, |held| {
                    held.checked_add(len).filter(|h| *h <= budget)
                });
            match reserved {
                Ok(before) => {
                    self.last_len.store(len, Ordering::Relaxed);
                    break before + len;
                }
                Err(_) if self.make_room(file, len, budget) => {}
                Err(_) => {
                    tracing::debug!(budget, "the spool of decoded chunks is full");
                    return Err(NotSpooled::Full);
                }
            }
        };
        match file.append(&bytes) {
            Ok(offset) => {
                self.peak.fetch_max(held, Ordering::Relaxed);
                let mut chunks = self.chunks.lock().unwrap_or_else(PoisonError::into_inner);
                chunks.written.push_back((key.clone(), offset));
                Ok(Spooled { offset, len, meta })
            }
            Err(e) => {
                tracing::debug!(error = %e, "a decoded chunk not spooled");
                self.held.fetch_sub(len, Ordering::AcqRel);
                self.refused.store(true, Ordering::Relaxed);
                Err(NotSpooled::Failed)
            }
        }
    }

    /// Releases the oldest chunks still spooled until `len` more bytes fit the budget; whether
    /// they do (not where every chunk is released already, or no hole can be punched).
    fn make_room(&self, file: &ScratchFile, len: u64, budget: u64) -> bool {
        if len > budget {
            return false;
        }
        let mut chunks = self.chunks.lock().unwrap_or_else(PoisonError::into_inner);
        let Chunks { slots, written } = &mut *chunks;
        while self.held.load(Ordering::Acquire).saturating_add(len) > budget {
            if self.keep_all.load(Ordering::Relaxed) {
                return false;
            }
            let Some((key, offset)) = written.pop_front() else {
                return false;
            };
            let Some(slot) = slots.get_mut(&key) else {
                continue;
            };
            let spooled = match &*slot {
                Slot::Spool(cell, _) => *cell.get().unwrap_or(&None),
                _ => None,
            };
            if let Some(s) = spooled.filter(|s| s.offset == offset) {
                self.release(file, &s, slot);
            }
        }
        true
    }

    /// Releases the spooled chunk `s` in `slot` (a hole punched in `file`), or keeps every
    /// chunk from now on where no hole can be punched.
    fn release(&self, file: &ScratchFile, s: &Spooled<M>, slot: &mut Slot<M>) {
        match file.release(s.offset, s.len) {
            Ok(()) => {
                self.held.fetch_sub(s.len, Ordering::AcqRel);
                *slot = Slot::Released;
            }
            Err(e) => {
                tracing::debug!(error = %e, "spooled chunks kept to the end");
                self.keep_all.store(true, Ordering::Relaxed);
            }
        }
    }

    /// The file and its budget, made the first time (`None`: it could not be).
    fn file(&self) -> Option<(&ScratchFile, u64)> {
        let made = self.file.get_or_init(|| {
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
        });
        made.as_ref().map(|(f, b)| (f, *b))
    }

    /// Bytes `at..at + len` of the spooled chunk `key` (`s`, as [`ChunkSpool::get_or_spool`]
    /// gave it), for a region that reads `samples` of the chunk's `total` (in any unit, the
    /// same for every region). Once the regions have read `total`, the chunk is released: its
    /// disk space given back, and a region needing it again spools it again. `None`: past its
    /// end, released, or the file could not be read; the caller decodes the chunk.
    pub(crate) fn read<Q>(
        &self,
        key: &Q,
        s: &Spooled<M>,
        (at, len): (u64, usize),
        (samples, total): (u64, u64),
    ) -> Option<Vec<u8>>
    where
        K: Borrow<Q>,
        Q: Hash + Eq + ?Sized,
    {
        let (file, _) = self.file.get()?.as_ref()?;
        if at.checked_add(len as u64)? > s.len {
            return None;
        }
        // Under the lock of the chunks, so that no region releases the chunk in between.
        let mut chunks = self.chunks.lock().unwrap_or_else(PoisonError::into_inner);
        let slot = chunks.slots.get_mut(key)?;
        let Slot::Spool(cell, read) = slot else {
            return None;
        };
        if !matches!(cell.get(), Some(Some(c)) if c.offset == s.offset) {
            return None;
        }
        let bytes = file.read(s.offset + at, len).ok()?;
        *read = read.saturating_add(samples);
        if *read >= total && !self.keep_all.load(Ordering::Relaxed) {
            self.release(file, s, slot);
        }
        Some(bytes)
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
        let first = spool.get_or_spool(7, 0, || panic!("decoded the first time"));
        assert!(first.is_none(), "not spooled the first time");
        assert!(!spool.has_file());
        let samples = [f32::NAN, -0.0, 1e-38, f32::INFINITY, 3.5, -2.25];
        let s = spool
            .get_or_spool(7, 0, || Some((3, f32::to_bytes(&samples))))
            .expect("spooled the second time");
        assert_eq!(s.meta, 3);
        let back = spool
            .read(&7, &s, (16, 8), (2, 6))
            .expect("the last two samples");
        assert_eq!(f32::from_bytes(&back), [3.5, -2.25]);
        assert!(
            spool.read(&7, &s, (17, 8), (2, 6)).is_none(),
            "past the end"
        );
        assert!(
            spool.read(&6, &s, (0, 8), (2, 6)).is_none(),
            "another chunk"
        );
        // Spooled once: later requests do not decode it again.
        let again = spool.get_or_spool(7, 0, || panic!("decoded a third time"));
        assert_eq!(again.map(|s| s.meta), Some(3));
        // A chunk that fails to decode is not spooled, and its later requests decode it.
        assert!(spool.get_or_spool(8, 0, || None).is_none());
        assert!(spool.get_or_spool(8, 0, || None).is_none());
        let mut asked = false;
        assert!(spool
            .get_or_spool(8, 0, || {
                asked = true;
                None
            })
            .is_none());
        assert!(!asked, "the failure is kept: its caller decodes it itself");
    }

    /// Where its share of the disk is spent, the spool releases its oldest chunks to make
    /// room for a new one (a region then reading one released decodes it itself); a chunk
    /// larger than the whole share is not spooled; chunks read whole by their regions are
    /// released without waiting for that.
    #[test]
    fn a_full_spool_releases_its_oldest_chunks_to_make_room() {
        let spool: ChunkSpool<u32, ()> = ChunkSpool::with_budget(40);
        let chunk = |b: u8| move || Some(((), vec![b; 24]));
        for key in [1, 2, 3, 4] {
            assert!(spool
                .get_or_spool(key, 0, || panic!("decoded the first time"))
                .is_none());
        }
        let one = spool.get_or_spool(1, 0, chunk(1)).expect("24 of 40 bytes");
        assert!(spool.get_or_spool(1, 0, || panic!("spooled")).is_some());
        let two = spool.get_or_spool(2, 0, chunk(2)).expect("room made");
        assert_eq!(spool.held(), (24, 24), "the first released");
        assert!(spool.read(&1, &one, (0, 4), (4, 24)).is_none(), "released");
        assert_eq!(spool.read(&2, &two, (0, 2), (2, 24)), Some(vec![2, 2]));
        // Asked for again, the first is spooled again (the second released for it).
        let again = spool.get_or_spool(1, 0, chunk(1)).expect("spooled again");
        assert!(again.offset >= 48, "appended after both");
        assert!(spool.read(&2, &two, (0, 2), (2, 24)).is_none(), "released");
        // Chunk 1 read whole by two regions (12 samples of 24 each): released at once.
        assert!(spool.read(&1, &again, (0, 12), (12, 24)).is_some());
        assert_eq!(spool.held().0, 24);
        assert!(spool.read(&1, &again, (12, 12), (12, 24)).is_some());
        assert_eq!(spool.held(), (0, 24), "released");
        // Larger than the whole share: not spooled.
        let big = || Some(((), vec![3u8; 48]));
        assert!(spool.get_or_spool(3, 0, big).is_none());
        assert_eq!(spool.held().0, 0);
        let four = spool.get_or_spool(4, 0, chunk(4)).expect("room");
        assert_eq!(
            spool.read(&4, &four, (0, 24), (24, 24)),
            Some(vec![4u8; 24])
        );
        assert_eq!(spool.held().0, 0);
    }

    /// A chunk released after a pass over the volume is spooled again by the next pass the
    /// first time it is needed, and every read back gives its samples, from threads at once.
    #[test]
    fn a_released_chunk_is_spooled_again_by_the_next_pass() {
        let spool: ChunkSpool<u32, ()> = ChunkSpool::default();
        let samples: Vec<u16> = (0..64).map(|i| i * 3 + 1).collect();
        let decoded = AtomicUsize::new(0);
        let chunk = || {
            decoded.fetch_add(1, Ordering::Relaxed);
            Some(((), u16::to_bytes(&samples)))
        };
        assert!(
            spool.get_or_spool(9, 0, chunk).is_none(),
            "the first sighting"
        );
        for pass in 1..=3 {
            // Four regions of 16 samples, two threads.
            std::thread::scope(|scope| {
                for t in 0..2u64 {
                    let (spool, samples, chunk) = (&spool, &samples, &chunk);
                    scope.spawn(move || {
                        for quarter in [t, t + 2] {
                            let s = spool.get_or_spool(9, 0, chunk).expect("spooled");
                            let at = (quarter * 32, 32);
                            // Released only once all four are read: never before a read.
                            let got = spool.read(&9, &s, at, (16, 64)).expect("read back");
                            let q = quarter as usize * 16;
                            assert_eq!(u16::from_bytes(&got), samples[q..q + 16]);
                        }
                    });
                }
            });
            assert_eq!(spool.held().0, 0, "pass {pass}: released");
            assert_eq!(decoded.load(Ordering::Relaxed), pass, "once a pass");
        }
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
