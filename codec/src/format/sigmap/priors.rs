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
use super::contexts::Models;
use crate::entropy::range::{AdaptiveUintModel, BitModel};
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

/// The table's file: magic, then version (u16), model count (u32), the bits a prior counts as
/// seen (u8), entry count (u32), entries (index u32, p0 u16, little-endian, by increasing
/// index), CRC-32 of everything before it.
const TABLE: &[u8] = include_bytes!("priors.bin");
const TABLE_MAGIC: &[u8; 4] = b"WSPP";
const TABLE_VERSION: u16 = 1;

/// Why a priors table does not read.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
#[error("priors table: {0}")]
pub struct TableError(String);

/// A priors table: per canonical model, its starting probability of a 0 in units of 2^−12
/// (0: no prior, start at ½), and how many bits a prior counts as seen.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Table {
    /// Per canonical model, p0 or 0.
    pub p0: Vec<u16>,
    /// The bits a model starting from its prior counts as seen (see [`BitModel::primed`]).
    pub seen: u8,
}

impl Table {
    /// Reads a table written by [`Table::to_bytes`].
    pub fn from_bytes(bytes: &[u8]) -> Result<Table, TableError> {
        let bad = |s: &str| TableError(s.to_string());
        if bytes.len() < 19 || &bytes[..4] != TABLE_MAGIC {
            return Err(bad("not a priors table"));
        }
        let (body, crc) = bytes.split_at(bytes.len() - 4);
        if crc32fast::hash(body) != u32::from_le_bytes(crc.try_into().expect("4 bytes")) {
            return Err(bad("checksum mismatch"));
        }
        let u16_at = |i: usize| u16::from_le_bytes([body[i], body[i + 1]]);
        let u32_at = |i: usize| u32::from_le_bytes(body[i..i + 4].try_into().expect("4 bytes"));
        if u16_at(4) != TABLE_VERSION {
            return Err(bad("unknown version"));
        }
        if u32_at(6) as usize != CANONICAL_MODELS {
            return Err(bad("model count differs from this codec's"));
        }
        let seen = body[10];
        let count = u32_at(11) as usize;
        if body.len() != 15 + 6 * count {
            return Err(bad("length does not match the entry count"));
        }
        let mut p0 = vec![0u16; CANONICAL_MODELS];
        let mut last = None;
        for e in body[15..].chunks_exact(6) {
            let index = u32::from_le_bytes(e[..4].try_into().expect("4 bytes")) as usize;
            let p = u16::from_le_bytes([e[4], e[5]]);
            if index >= CANONICAL_MODELS || last.is_some_and(|l| index <= l) {
                return Err(bad("entry index out of order or range"));
            }
            if !(1..4096).contains(&p) {
                return Err(bad("probability out of range"));
            }
            p0[index] = p;
            last = Some(index);
        }
        Ok(Table { p0, seen })
    }

    /// Writes the table in the form [`Table::from_bytes`] reads.
    pub fn to_bytes(&self) -> Vec<u8> {
        let entries: Vec<(usize, u16)> = self
            .p0
            .iter()
            .enumerate()
            .filter(|(_, p)| **p != 0)
            .map(|(i, p)| (i, *p))
            .collect();
        let mut out = Vec::with_capacity(19 + 6 * entries.len());
        out.extend_from_slice(TABLE_MAGIC);
        out.extend_from_slice(&TABLE_VERSION.to_le_bytes());
        out.extend_from_slice(&(CANONICAL_MODELS as u32).to_le_bytes());
        out.push(self.seen);
        out.extend_from_slice(&(entries.len() as u32).to_le_bytes());
        for (i, p) in entries {
            out.extend_from_slice(&(i as u32).to_le_bytes());
            out.extend_from_slice(&p.to_le_bytes());
        }
        let crc = crc32fast::hash(&out);
        out.extend_from_slice(&crc.to_le_bytes());
        out
    }

    /// The model a prior `p` (0: none) starts.
    fn model(&self, p: u16) -> BitModel {
        if p == 0 {
            BitModel::new()
        } else {
            BitModel::primed(p, self.seen)
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

/// Calls `f(canonical index, model)` for every model of `m`, whose band index `bi` is band
/// `bands[bi]`. The arrays' layouts are those of [`Models`] (see its context functions).
fn for_each_model<'m>(
    m: &'m mut Models,
    bands: &[Band],
    mut f: impl FnMut(usize, &'m mut BitModel),
) {
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
pub(super) fn prime(m: &mut Models, bands: &[Band], table: &Table) {
    for_each_model(m, bands, |i, model| *model = table.model(table.p0[i]));
}

/// Whether a [`Training`] is recording.
static RECORDING: AtomicBool = AtomicBool::new(false);
/// Per canonical model: Σ w·p0 and Σ w over the packets recorded.
static RECORDED: Mutex<Vec<(f64, f64)>> = Mutex::new(Vec::new());

/// Records, while a [`Training`] runs, where each model of a coded packet ended: its p0,
/// weighted by the bits it saw (up to 64). Coding is the same whether or not it records.
pub(super) fn record(m: &mut Models, bands: &[Band]) {
    if !RECORDING.load(Ordering::Relaxed) {
        return;
    }
    let mut seen = Vec::new();
    for_each_model(m, bands, |i, model| {
        let (p0, n) = model.state();
        if n > 0 {
            seen.push((i, p0, n));
        }
    });
    let mut recorded = RECORDED.lock().unwrap_or_else(|e| e.into_inner());
    if recorded.len() != CANONICAL_MODELS {
        *recorded = vec![(0.0, 0.0); CANONICAL_MODELS];
    }
    for (i, p0, n) in seen {
        let w = f64::from(n.min(64));
        recorded[i].0 += w * f64::from(p0);
        recorded[i].1 += w;
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
        *RECORDED.lock().unwrap_or_else(|e| e.into_inner()) = vec![(0.0, 0.0); CANONICAL_MODELS];
        RECORDING.store(true, Ordering::SeqCst);
        Training(())
    }

    /// Stops recording and returns the table: each model's mean end state, for the models
    /// with at least `min_weight` recorded bits (weighted as in [`record`]); `seen` as given.
    pub fn finish(self, min_weight: f64, seen: u8) -> Table {
        RECORDING.store(false, Ordering::SeqCst);
        let recorded = std::mem::take(&mut *RECORDED.lock().unwrap_or_else(|e| e.into_inner()));
        let p0 = recorded
            .iter()
            .map(|(sum, w)| {
                if *w >= min_weight && *w > 0.0 {
                    (sum / w).round().clamp(1.0, 4095.0) as u16
                } else {
                    0
                }
            })
            .collect();
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
        assert!(t.seen > 0);
    }

    #[test]
    fn a_table_survives_its_bytes_and_damage_is_refused() {
        let mut p0 = vec![0u16; CANONICAL_MODELS];
        p0[3] = 100;
        p0[CANONICAL_MODELS - 1] = 4000;
        let t = Table { p0, seen: 9 };
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
