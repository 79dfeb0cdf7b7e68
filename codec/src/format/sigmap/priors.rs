//! The sigmap coder's trained priors (from format version [`super::super::PRIORS_VERSION`]):
//! the probability each adaptive model starts a packet at, instead of ½. Every packet learns
//! its models from nothing, so that it decodes on its own; a small packet (a brick's, a tile's
//! at a low rate) spends a good part of its bits on that learning. Starting each model where
//! such models usually end (as H.264's CABAC starts its contexts from tables) saves that part
//! and keeps packets self-contained: the priors are the codec's, not the file's.
//!
//! A model is found in the table by what its context means rather than by its place in a
//! packet's model arrays (which depend on the depth and the tile size): the band as scaling
//! or (level 1, 2, 3 and coarser; type), the box size (log2 of its cells, capped), the
//! neighbour and face states, the sign and magnitude contexts. The table
//! (`priors.bin`, compiled in) is trained on the project's phantoms by
//! `cargo run --release -p wavesplat-compressor --example train_priors`, which compresses
//! them in the format before the priors and records where each model ended each packet
//! ([`Training`]); the volumes the codec is measured on are not among them.
//!
//! Written here because no crate holds context priors for a custom context model.

use super::cells::{FACE_STATES, NEIGHBOUR_STATES, SIGN_CONTEXTS, VALUE_CONTEXTS};
use crate::entropy::range::{AdaptiveUintModel, BitModel};
use crate::format::bytes::{ByteReader, ByteWriter};
use crate::format::FormatError;
use crate::layout::Band;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Mutex;

/// Level keys of a wavelet band: levels 1, 2, and 3 or coarser.
const LEVEL_KEYS: usize = 3;
/// Band keys: the scaling band, then (level key, type 1..=7).
const BAND_KEYS: usize = 1 + 7 * LEVEL_KEYS;
/// Size keys of an occupancy context (log2 of the box's cells, larger ones share the last).
const SIZE_KEYS: usize = 26;

const PRESENT_AT: usize = 0;
const OCCUPIED_AT: usize = PRESENT_AT + BAND_KEYS;
const OCCUPIED_PER_BAND: usize = SIZE_KEYS * NEIGHBOUR_STATES * NEIGHBOUR_STATES * FACE_STATES;
const SIGN_AT: usize = OCCUPIED_AT + BAND_KEYS * OCCUPIED_PER_BAND;
const VALUE_AT: usize = SIGN_AT + BAND_KEYS * SIGN_CONTEXTS;
const VALUE_PER_BAND: usize = VALUE_CONTEXTS * AdaptiveUintModel::MODELS;
/// Models in the canonical table.
pub const CANONICAL_MODELS: usize = VALUE_AT + BAND_KEYS * VALUE_PER_BAND;

/// The table's file: magic, then version (u16), model count (u32), entry count (u32), entries
/// (index u32, p0 u16, seen u8; little-endian, by increasing index), CRC-32 of everything
/// before it.
const TABLE: &[u8] = include_bytes!("priors.bin");
const TABLE_MAGIC: &[u8; 4] = b"WSPP";
const TABLE_VERSION: u16 = 1;

/// Why a priors table does not read.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
#[error("priors table: {0}")]
pub struct TableError(String);

/// A priors table: per canonical model, its starting probability of a 0 in units of 2^−12
/// (0: no prior, start at ½), and how many bits that prior counts as seen: how far it is
/// trusted ([`BitModel::primed`]).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Table {
    /// Per canonical model, p0 or 0.
    pub p0: Vec<u16>,
    /// Per canonical model, the bits its prior counts as seen (0 where p0 is 0).
    pub seen: Vec<u8>,
}

impl Table {
    /// Reads a table written by [`Table::to_bytes`].
    pub fn from_bytes(bytes: &[u8]) -> Result<Table, TableError> {
        let bad = |s: &str| TableError(s.to_string());
        if bytes.len() < 18 || &bytes[..4] != TABLE_MAGIC {
            return Err(bad("not a priors table"));
        }
        let (body, crc) = bytes.split_at(bytes.len() - 4);
        if crc32fast::hash(body) != u32::from_le_bytes(crc.try_into().expect("4 bytes")) {
            return Err(bad("checksum mismatch"));
        }
        let read = |e: FormatError| TableError(e.to_string());
        let mut r = ByteReader::new(&body[4..], "priors table");
        if r.u16().map_err(read)? != TABLE_VERSION {
            return Err(bad("unknown version"));
        }
        if r.u32().map_err(read)? as usize != CANONICAL_MODELS {
            return Err(bad("model count differs from this codec's"));
        }
        let count = r.u32().map_err(read)? as usize;
        if r.remaining() != 7 * count {
            return Err(bad("length does not match the entry count"));
        }
        let mut p0 = vec![0u16; CANONICAL_MODELS];
        let mut seen = vec![0u8; CANONICAL_MODELS];
        let mut last = None;
        for _ in 0..count {
            let index = r.u32().map_err(read)? as usize;
            let (p, trust) = (r.u16().map_err(read)?, r.u8().map_err(read)?);
            if index >= CANONICAL_MODELS || last.is_some_and(|l| index <= l) {
                return Err(bad("entry index out of order or range"));
            }
            if !(1..4096).contains(&p) || trust == 0 {
                return Err(bad("probability or trust out of range"));
            }
            p0[index] = p;
            seen[index] = trust;
            last = Some(index);
        }
        Ok(Table { p0, seen })
    }

    /// Writes the table in the form [`Table::from_bytes`] reads.
    pub fn to_bytes(&self) -> Vec<u8> {
        let entries: Vec<(usize, u16, u8)> = self
            .p0
            .iter()
            .enumerate()
            .filter(|(_, p)| **p != 0)
            .map(|(i, p)| (i, *p, self.seen[i].max(1)))
            .collect();
        let mut w = ByteWriter::new();
        w.bytes(TABLE_MAGIC);
        w.u16(TABLE_VERSION);
        w.u32(CANONICAL_MODELS as u32);
        w.u32(entries.len() as u32);
        for (i, p, seen) in entries {
            w.u32(i as u32);
            w.u16(p);
            w.u8(seen);
        }
        let mut out = w.into_bytes();
        let crc = crc32fast::hash(&out);
        out.extend_from_slice(&crc.to_le_bytes());
        out
    }

    /// The model canonical model `i` starts as.
    fn model(&self, i: usize) -> BitModel {
        if self.p0[i] == 0 {
            BitModel::new()
        } else {
            BitModel::primed(self.p0[i], self.seen[i])
        }
    }
}

/// The compiled-in table.
pub fn shipped() -> &'static Table {
    static SHIPPED: std::sync::OnceLock<Table> = std::sync::OnceLock::new();
    SHIPPED.get_or_init(|| {
        Table::from_bytes(TABLE).expect("the compiled-in priors table reads (a unit test checks)")
    })
}

fn band_key(band: Band) -> usize {
    if band.kind == 0 {
        0
    } else {
        1 + (band.level.clamp(1, LEVEL_KEYS as u8) as usize - 1) * 7 + (band.kind as usize - 1)
    }
}

/// A packet's model arrays, laid out as the sigmap coder's context functions index them
/// (`contexts::Models`).
pub(super) struct Arrays<'a> {
    pub(super) present: &'a mut [BitModel],
    pub(super) occupied: &'a mut [BitModel],
    pub(super) sign: &'a mut [BitModel],
    pub(super) value: &'a mut [AdaptiveUintModel],
    pub(super) size_contexts: usize,
    pub(super) value_contexts: usize,
}

/// Calls `f(canonical index, model)` for every model of `m`, whose band index `bi` is band
/// `bands[bi]`.
fn for_each_model<'m>(m: Arrays<'m>, bands: &[Band], mut f: impl FnMut(usize, &'m mut BitModel)) {
    let keys: Vec<usize> = bands.iter().map(|b| band_key(*b)).collect();
    for (bi, model) in m.present.iter_mut().enumerate() {
        f(PRESENT_AT + keys[bi], model);
    }
    let per_band = m.size_contexts * NEIGHBOUR_STATES * NEIGHBOUR_STATES * FACE_STATES;
    let states = NEIGHBOUR_STATES * NEIGHBOUR_STATES * FACE_STATES;
    for (i, model) in m.occupied.iter_mut().enumerate() {
        let (bi, rest) = (i / per_band, i % per_band);
        let (size, state) = (rest / states, rest % states);
        let size = size.min(SIZE_KEYS - 1);
        f(
            OCCUPIED_AT + keys[bi] * OCCUPIED_PER_BAND + size * states + state,
            model,
        );
    }
    for (i, model) in m.sign.iter_mut().enumerate() {
        let (bi, s) = (i / SIGN_CONTEXTS, i % SIGN_CONTEXTS);
        f(SIGN_AT + keys[bi] * SIGN_CONTEXTS + s, model);
    }
    let contexts = m.value_contexts;
    for (i, uint) in m.value.iter_mut().enumerate() {
        let (bi, v) = (i / contexts, i % contexts);
        let base = VALUE_AT + keys[bi] * VALUE_PER_BAND + v * AdaptiveUintModel::MODELS;
        for (j, model) in uint.models_mut().enumerate() {
            f(base + j, model);
        }
    }
}

/// Sets every model of fresh `m` (band index → band: `bands`) to its prior in `table`.
pub(super) fn prime(m: Arrays<'_>, bands: &[Band], table: &Table) {
    for_each_model(m, bands, |i, model| *model = table.model(i));
}

/// Whether a [`Training`] is recording.
static RECORDING: AtomicBool = AtomicBool::new(false);
/// Per canonical model, over the packets recorded: Σ w, Σ w·p0, Σ w·p0², Σ w·⌊2^20 / (n + 2)⌋
/// (n the bits seen, at most 61), w = min(n, 64). Integers, so that the sums do not depend on
/// the order the packets come in.
static RECORDED: Mutex<Vec<[u64; 4]>> = Mutex::new(Vec::new());

/// Records, while a [`Training`] runs, where each model of a coded packet ended: its p0,
/// weighted by the bits it saw (up to 64). Coding is the same whether or not it records.
pub(super) fn record(m: Arrays<'_>, bands: &[Band]) {
    if !RECORDING.load(Ordering::Relaxed) {
        return;
    }
    let mut ended = Vec::new();
    for_each_model(m, bands, |i, model| {
        let (p0, n) = model.state();
        if n > 0 {
            ended.push((i, p0, n));
        }
    });
    let mut recorded = RECORDED.lock().unwrap_or_else(|e| e.into_inner());
    if recorded.len() != CANONICAL_MODELS {
        *recorded = vec![[0; 4]; CANONICAL_MODELS];
    }
    for (i, p0, n) in ended {
        let (w, p) = (u64::from(n.min(64)), u64::from(p0));
        let r = &mut recorded[i];
        r[0] += w;
        r[1] += w * p;
        r[2] += w * p * p;
        r[3] += w * ((1 << 20) / (u64::from(n.min(61)) + 2));
    }
}

/// Records what the sigmap coder's models learn in every packet the process encodes from
/// [`Training::start`] to [`Training::finish`], to train a priors table. One at a time per
/// process; encodes in the format before the priors (version 8) start their models at ½, so
/// they record what a packet learns from nothing.
pub struct Training(());

impl Training {
    /// Starts recording (clearing anything recorded before).
    pub fn start() -> Training {
        *RECORDED.lock().unwrap_or_else(|e| e.into_inner()) = vec![[0; 4]; CANONICAL_MODELS];
        RECORDING.store(true, Ordering::SeqCst);
        Training(())
    }

    /// Stops recording and returns the table: for each model with at least `min_weight`
    /// recorded bits, its mean end state, trusted as much as the spread of the end states
    /// across packets says (a Beta prior's equivalent count, p̄(1 − p̄)/σ² − 2 with σ² the
    /// spread less the end states' own estimation noise), at most `max_seen` bits.
    pub fn finish(self, min_weight: u64, max_seen: u8) -> Table {
        RECORDING.store(false, Ordering::SeqCst);
        let recorded = std::mem::take(&mut *RECORDED.lock().unwrap_or_else(|e| e.into_inner()));
        let mut p0 = vec![0u16; CANONICAL_MODELS];
        let mut seen = vec![0u8; CANONICAL_MODELS];
        for (i, r) in recorded.iter().enumerate() {
            if r[0] < min_weight.max(1) {
                continue;
            }
            let w = r[0] as f64;
            let mean = r[1] as f64 / w;
            let spread = (r[2] as f64 / w - mean * mean).max(0.0);
            let p = mean / 4096.0;
            let noise = p * (1.0 - p) * (r[3] as f64 / w) / f64::from(1u32 << 20);
            let var = spread / (4096.0 * 4096.0) - noise;
            let count = if var > 0.0 {
                p * (1.0 - p) / var - 2.0
            } else {
                f64::INFINITY
            };
            p0[i] = mean.round().clamp(1.0, 4095.0) as u16;
            seen[i] = count.clamp(1.0, f64::from(max_seen.max(1))).round() as u8;
        }
        Table { p0, seen }
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
    fn the_shipped_table_reads_and_primes_some_models() {
        let t = Table::from_bytes(TABLE).expect("reads");
        assert_eq!(t.p0.len(), CANONICAL_MODELS);
        let primed = t.p0.iter().filter(|p| **p != 0).count();
        assert!(primed > 100, "only {primed} primed models");
        assert!((0..CANONICAL_MODELS).all(|i| (t.p0[i] == 0) == (t.seen[i] == 0)));
        assert_eq!(
            t.to_bytes(),
            TABLE,
            "the table writes back to the same bytes"
        );
    }

    #[test]
    fn a_table_survives_its_bytes_and_damage_is_refused() {
        let mut p0 = vec![0u16; CANONICAL_MODELS];
        p0[3] = 100;
        p0[CANONICAL_MODELS - 1] = 4000;
        let mut seen = vec![0u8; CANONICAL_MODELS];
        seen[3] = 9;
        seen[CANONICAL_MODELS - 1] = 1;
        let t = Table { p0, seen };
        let bytes = t.to_bytes();
        assert_eq!(Table::from_bytes(&bytes), Ok(t));
        for at in [0, 5, 12, bytes.len() - 3, bytes.len() - 1] {
            let mut bad = bytes.clone();
            bad[at] ^= 0x10;
            assert!(Table::from_bytes(&bad).is_err(), "byte {at} flipped");
        }
        assert!(Table::from_bytes(&bytes[..bytes.len() - 1]).is_err());
        assert!(Table::from_bytes(&[]).is_err());
    }

    /// Every band of every depth has a key of its own kind, and keys stay in range.
    #[test]
    fn band_keys_cover_every_depth() {
        for levels in 0..=8usize {
            let g = crate::layout::Geometry::new(
                [256, 256, 256],
                crate::family::Family::Haar,
                levels,
                0,
            )
            .unwrap();
            for b in g.bands() {
                let k = band_key(b);
                assert!(k < BAND_KEYS);
                assert_eq!(k == 0, b.kind == 0);
            }
        }
    }
}
