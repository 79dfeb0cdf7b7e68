//! The fast coder's built-in tables (from format version
//! [`crate::format::FAST_CONTEXTS_VERSION`]): one rANS distribution per table of a file's
//! header (the masks, the occupancy tables, the value tables, in header order), compiled into
//! the codec, which a header names with one bit instead of describing the table's levels.
//! A file's own tables cost ~0.4–1.1 kB of header, most of a small file's gap to the default
//! coder (a 1.3 kB slab at 0.2 %: 401 bytes of header, the payload smaller than the default
//! coder's); the encoder takes a built-in table wherever it codes that table's symbols in
//! fewer bits than the file's own table and its description ([`super::FastTables`]).
//!
//! The tables (`builtin.bin`, compiled in) are trained on the project's phantoms by
//! `cargo run --release -p wavesplat-compressor --example train_fast_tables`, which
//! compresses them with the fast coder and sums each table's symbol counts over the files
//! ([`Training`]), each file's counts weighed as at most 4 096 symbols, so that large files do
//! not outvote small ones. The volumes the codec is measured on are not among them. Written
//! here because no crate holds tables for a custom context model.

use super::{
    HALF_OCTAVE_VALUE_ALPHABET, MASK_ALPHABET, MASK_TABLES, OCCUPANCY_TABLES, RANS_VALUE_TABLES,
};
use crate::entropy::rans::{levels_of_counts, RansTable};
use crate::format::bytes::{ByteReader, ByteWriter};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Mutex;

/// Tables in a header, in header order: masks, occupancy, values.
pub const TABLES: usize = MASK_TABLES + OCCUPANCY_TABLES + RANS_VALUE_TABLES;

/// The alphabet of the header's table `t` (header order).
pub fn alphabet(t: usize) -> usize {
    if t < MASK_TABLES {
        MASK_ALPHABET
    } else if t < MASK_TABLES + OCCUPANCY_TABLES {
        2
    } else {
        HALF_OCTAVE_VALUE_ALPHABET
    }
}

/// The file: magic, version (u16), table count (u16), then per table its level count (u16)
/// and levels (quarter-octave grid, 0: the symbol is absent; no levels: no built-in table),
/// little-endian, and the CRC-32 of everything before it.
const TABLE_FILE: &[u8] = include_bytes!("builtin.bin");
const MAGIC: &[u8; 4] = b"WSFT";
const FILE_VERSION: u16 = 1;

/// Why a built-in tables file does not read.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
#[error("built-in fast-coder tables: {0}")]
pub struct BuiltinError(String);

/// Each header table's built-in levels (empty: none).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Levels(pub Vec<Vec<u8>>);

impl Levels {
    /// Reads a file written by [`Levels::to_bytes`], checking its tables.
    pub fn from_bytes(bytes: &[u8]) -> Result<Levels, BuiltinError> {
        let bad = |s: String| BuiltinError(s);
        if bytes.len() < 12 || &bytes[..4] != MAGIC {
            return Err(bad("not a tables file".into()));
        }
        let (body, crc) = bytes.split_at(bytes.len() - 4);
        if crc32fast::hash(body).to_le_bytes() != crc {
            return Err(bad("checksum mismatch".into()));
        }
        let mut r = ByteReader::new(&body[4..], "built-in tables");
        let err = |e: crate::format::FormatError| bad(e.to_string());
        let version = r.u16().map_err(err)?;
        if version != FILE_VERSION {
            return Err(bad(format!(
                "version {version}, this build reads {FILE_VERSION}"
            )));
        }
        let count = r.u16().map_err(err)? as usize;
        if count != TABLES {
            return Err(bad(format!("{count} tables, a header has {TABLES}")));
        }
        let mut levels = Vec::with_capacity(TABLES);
        for t in 0..TABLES {
            let n = r.u16().map_err(err)? as usize;
            if n > alphabet(t) {
                return Err(bad(format!(
                    "table {t}: {n} levels over an alphabet of {}",
                    alphabet(t)
                )));
            }
            let l = r.take(n).map_err(err)?.to_vec();
            if !l.is_empty() {
                RansTable::from_levels(&l, 1).map_err(|e| bad(format!("table {t}: {e}")))?;
            }
            levels.push(l);
        }
        if r.remaining() != 0 {
            return Err(bad("bytes after the tables".into()));
        }
        Ok(Levels(levels))
    }

    /// The file of these levels.
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut w = ByteWriter::new();
        w.bytes(MAGIC);
        w.u16(FILE_VERSION);
        w.u16(self.0.len() as u16);
        for l in &self.0 {
            w.u16(l.len() as u16);
            w.bytes(l);
        }
        let mut bytes = w.into_bytes();
        let crc = crc32fast::hash(&bytes);
        bytes.extend_from_slice(&crc.to_le_bytes());
        bytes
    }

    /// How many tables have a built-in distribution.
    pub fn count(&self) -> usize {
        self.0.iter().filter(|l| !l.is_empty()).count()
    }
}

/// The compiled-in tables, as distributions (`None`: table `t` has none).
pub(super) fn shipped() -> &'static [Option<RansTable>] {
    static SHIPPED: std::sync::OnceLock<Vec<Option<RansTable>>> = std::sync::OnceLock::new();
    SHIPPED.get_or_init(|| {
        // A unit test checks that the compiled-in file reads; were it not to, no table would
        // be built in, and files naming one would be refused, not misread.
        let levels = Levels::from_bytes(TABLE_FILE).unwrap_or(Levels(vec![Vec::new(); TABLES]));
        levels
            .0
            .iter()
            .map(|l| {
                (!l.is_empty())
                    .then(|| RansTable::from_levels(l, 1).ok())
                    .flatten()
            })
            .collect()
    })
}

/// Whether a [`Training`] is recording.
static RECORDING: AtomicBool = AtomicBool::new(false);
/// Per header table, per symbol: the weighed counts recorded (integers, so that the sums do
/// not depend on the order the files come in).
static RECORDED: Mutex<Vec<Vec<u64>>> = Mutex::new(Vec::new());
/// A file's counts of one table weigh as at most this many symbols.
const FILE_WEIGHT: u64 = 4096;

/// Records, while a [`Training`] runs, one file's symbol counts per header table (header
/// order). Coding is the same whether or not it records.
pub(super) fn record(counts: &[&[u64]]) {
    if !RECORDING.load(Ordering::Relaxed) {
        return;
    }
    let mut recorded = RECORDED.lock().unwrap_or_else(|e| e.into_inner());
    if recorded.len() != TABLES {
        *recorded = (0..TABLES).map(|t| vec![0; alphabet(t)]).collect();
    }
    for (t, c) in counts.iter().enumerate().take(TABLES) {
        let total: u64 = c.iter().sum();
        if total == 0 {
            continue;
        }
        // Each count scaled to a file of at most FILE_WEIGHT symbols, in units of 2^-10.
        let scale = (total.min(FILE_WEIGHT) << 10) as u128;
        for (s, &n) in c.iter().enumerate().take(recorded[t].len()) {
            recorded[t][s] += (n as u128 * scale / total as u128) as u64;
        }
    }
}

/// Records the fast coder's symbol counts of every file the process encodes (format version
/// [`crate::format::FAST_CONTEXTS_VERSION`]) from [`Training::start`] to [`Training::finish`],
/// to train the built-in tables. One at a time per process.
pub struct Training(());

impl Training {
    /// Starts recording (clearing anything recorded before).
    pub fn start() -> Training {
        *RECORDED.lock().unwrap_or_else(|e| e.into_inner()) =
            (0..TABLES).map(|t| vec![0; alphabet(t)]).collect();
        RECORDING.store(true, Ordering::SeqCst);
        Training(())
    }

    /// Stops recording and returns the levels: for each table whose recorded weight is at
    /// least `min_files` files' worth, its distribution on the quarter-octave grid (symbols
    /// never recorded absent).
    pub fn finish(self, min_files: u64) -> Levels {
        RECORDING.store(false, Ordering::SeqCst);
        let recorded = std::mem::take(&mut *RECORDED.lock().unwrap_or_else(|e| e.into_inner()));
        Levels(
            recorded
                .iter()
                .map(|c| {
                    let total: u64 = c.iter().sum();
                    if total < (min_files.max(1) * FILE_WEIGHT) << 10 {
                        return Vec::new();
                    }
                    let mut l = levels_of_counts(c, 1);
                    while l.last() == Some(&0) {
                        l.pop();
                    }
                    l
                })
                .collect(),
        )
    }
}

impl Drop for Training {
    fn drop(&mut self) {
        RECORDING.store(false, Ordering::SeqCst);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_shipped_tables_read_and_build_some_tables() {
        let levels = Levels::from_bytes(TABLE_FILE).expect("reads");
        assert_eq!(levels.0.len(), TABLES);
        assert!(levels.count() > 0, "no table is built in");
        assert_eq!(
            shipped().iter().filter(|t| t.is_some()).count(),
            levels.count()
        );
        // The masks' tables never hold the empty mask (a node is coded because it is
        // occupied); the occupancy tables are binary.
        for (t, table) in shipped().iter().enumerate() {
            let Some(table) = table else { continue };
            if t < MASK_TABLES {
                assert_eq!(table.frequency(0), 0, "table {t}");
            }
            assert!(table.levels().len() <= alphabet(t), "table {t}");
        }
    }

    #[test]
    fn a_damaged_tables_file_is_refused() {
        let good = Levels::from_bytes(TABLE_FILE).unwrap().to_bytes();
        assert_eq!(good, TABLE_FILE, "the file is written as it reads");
        let mut flipped = good.clone();
        flipped[20] ^= 1;
        assert!(Levels::from_bytes(&flipped).is_err());
        assert!(Levels::from_bytes(&good[..good.len() - 1]).is_err());
        let mut wrong_count = Levels(vec![Vec::new(); TABLES - 1]).to_bytes();
        assert!(Levels::from_bytes(&wrong_count).is_err());
        wrong_count.clear();
        assert!(Levels::from_bytes(&wrong_count).is_err());
        // Levels beyond a table's alphabet.
        let mut long = vec![Vec::new(); TABLES];
        long[MASK_TABLES] = vec![1, 1, 1];
        assert!(Levels::from_bytes(&Levels(long).to_bytes()).is_err());
    }
}
