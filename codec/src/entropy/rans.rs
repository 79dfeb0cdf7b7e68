//! Static-model rANS (range asymmetric numeral systems): fractional code lengths at a table
//! look-up per symbol, the fast coder's entropy coder from format version 14
//! ([`crate::format::RANS_VERSION`]).
//!
//! A [`RansTable`] is a distribution over at most 256 symbols in units of 2^−[`PRECISION`],
//! described by one small integer per symbol, its *level* (0: the symbol never occurs; level l
//! weighs 2^((l − 1)/4), so the levels cover 12 octaves in quarter octaves), which
//! [`RansTable::write_levels`] serializes as compactly as Huffman code lengths. A table of few
//! counts is described on a coarser grid (half or whole octaves: fewer bits per level), chosen
//! by what the header and the coded symbols cost together ([`RansTable::from_counts`]). The weights
//! become frequencies by integer arithmetic only ([`frequencies_of_levels`]), so every platform
//! decodes the same table. Against a prefix code, a symbol of probability 0.9 costs 0.15 bits
//! instead of 1.
//!
//! [`RansEncoder`] takes a packet's symbols in order and writes them backwards (rANS is a
//! stack) with one 32-bit state; the stream is 16-bit words, little-endian, the final state
//! first. (Two states alternating symbol by symbol decoded no faster here, where each
//! symbol's table depends on the symbols before it, and cost a second final state per
//! packet.) [`RansDecoder`] reads untrusted bytes: it never panics, and
//! [`RansDecoder::is_complete`] holds only when the stream ended exactly where its encoder
//! started (the state back at its initial value, every word read), which a corrupted or
//! truncated stream almost never does.
//!
//! Written here rather than taken from a crate: `constriction`'s ANS coder (the well-kept Rust
//! one) decodes from a `Vec` of words it owns, and this format reads in place from a packet's
//! bytes, with the tables described by levels in the file's header.

use super::bits::{BitCounter, BitReader, BitSink};
use super::huffman::{read_small_values, write_small_values};
use super::EntropyError;

/// Bits of probability resolution: frequencies sum to 2^12.
pub const PRECISION: u32 = 12;
/// The frequencies' total.
pub const TOTAL: u32 = 1 << PRECISION;
/// Largest level ([`RansTable`]): weight 2^12 times the weight of level 1.
pub const MAX_LEVEL: u8 = 49;
/// Largest alphabet: symbols are packed in 8 bits of the decoding table.
pub const MAX_SYMBOLS: usize = 256;
/// The states' lower bound; they live in [2^16, 2^32) and move by 16-bit words.
const LOWER: u32 = 1 << 16;
/// 2^(k/4) for k = 0..4, in units of 2^−12: the levels' weights within an octave.
const QUARTER_OCTAVES: [u64; 4] = [4096, 4871, 5793, 6889];

/// The weight of a level ≥ 1 (integer, so that every platform agrees).
fn weight(level: u8) -> u64 {
    let l = (level - 1) as u64;
    QUARTER_OCTAVES[(l % 4) as usize] << (l / 4)
}

/// Frequencies summing to [`TOTAL`] for symbols' levels (0: absent, frequency 0; others at
/// least 1), by integer arithmetic only: each used symbol gets its share of the total,
/// rounded down and at least 1; what is left over goes to the heaviest symbol, and an excess
/// (from the symbols raised to 1) is taken from the largest frequencies. All zero when no
/// symbol is used. At most [`MAX_SYMBOLS`] levels ([`RansTable::from_levels`] checks).
fn frequencies_of_levels(levels: &[u8]) -> Vec<u32> {
    debug_assert!(levels.len() <= MAX_SYMBOLS);
    let total_weight: u64 = levels.iter().filter(|&&l| l > 0).map(|&l| weight(l)).sum();
    let mut freqs = vec![0u32; levels.len()];
    if total_weight == 0 {
        return freqs;
    }
    let mut sum = 0u32;
    for (f, &l) in freqs.iter_mut().zip(levels) {
        if l > 0 {
            *f = ((weight(l) * TOTAL as u64 / total_weight) as u32).max(1);
            sum += *f;
        }
    }
    let heaviest = (0..levels.len())
        .max_by_key(|&i| (levels[i], std::cmp::Reverse(i)))
        .expect("a used symbol");
    if sum < TOTAL {
        freqs[heaviest] += TOTAL - sum;
    }
    while sum > TOTAL {
        // At most MAX_SYMBOLS symbols were raised to 1, and TOTAL > 2 · MAX_SYMBOLS, so the
        // largest frequency always has room to give.
        let largest = (0..freqs.len())
            .max_by_key(|&i| (freqs[i], std::cmp::Reverse(i)))
            .expect("a used symbol");
        let give = (sum - TOTAL).min(freqs[largest] - 1);
        freqs[largest] -= give;
        sum -= give;
    }
    freqs
}

/// Grid steps of the levels a table may be described on, in quarter octaves: a table of few
/// counts is described as well by whole octaves, in fewer header bits ([`RansTable::from_counts`]
/// picks the step that costs least in all).
pub const LEVEL_STEPS: [u8; 3] = [1, 2, 4];

/// The levels that describe symbol counts on a grid of `step` quarter octaves: each symbol's
/// count relative to the largest, at least 1 for a symbol that occurs (the encoder's side;
/// floating point is fine here, the levels are what is sent).
pub fn levels_of_counts(counts: &[u64], step: u8) -> Vec<u8> {
    let max = counts.iter().copied().max().unwrap_or(0);
    let step = step as f64;
    counts
        .iter()
        .map(|&c| {
            if c == 0 {
                return 0;
            }
            let below = step * (4.0 * (max as f64 / c as f64).log2() / step).round();
            // 48 is a multiple of every step, so level 1 lies on every grid.
            (MAX_LEVEL as f64 - below).max(1.0) as u8
        })
        .collect()
}

/// One static distribution: its levels, frequencies, cumulative starts, and the decoder's
/// table of 2^12 slots, a byte each (the slot's symbol, whose frequency and start the decoder
/// then reads from a table as long as the alphabet: 4 KiB a table rather than 16 with all
/// three in each slot, which kept a file's tables from staying in cache: decoding 11 % faster
/// on MNI at 1.25 %). Empty when no symbol is used.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RansTable {
    /// The levels' grid step, in quarter octaves (one of [`LEVEL_STEPS`]).
    step: u8,
    levels: Vec<u8>,
    freq: Vec<u16>,
    start: Vec<u16>,
    /// Each symbol's cost in 1/256 bits, for size breakdowns.
    cost: Vec<u16>,
    /// The symbol of each of the 2^12 slots (empty for an empty table).
    slots: Box<[u8]>,
    /// Each symbol's frequency (bits 0–15) and start (bits 16–31), for the decoder.
    spans: Box<[u32]>,
}

impl RansTable {
    /// The table described by `levels` (at most [`MAX_SYMBOLS`], each at most [`MAX_LEVEL`]) on
    /// the grid of `step` quarter octaves (one of [`LEVEL_STEPS`]; each used level one more
    /// than a multiple of it).
    pub fn from_levels(levels: &[u8], step: u8) -> Result<RansTable, EntropyError> {
        if !LEVEL_STEPS.contains(&step) {
            return Err(EntropyError::out_of_range("rANS level step", step, 1, 4));
        }
        if levels.len() > MAX_SYMBOLS {
            return Err(EntropyError::out_of_range(
                "rANS alphabet size",
                levels.len() as u64,
                0,
                MAX_SYMBOLS as u64,
            ));
        }
        if let Some(&l) = levels.iter().find(|&&l| l > MAX_LEVEL) {
            return Err(EntropyError::out_of_range("rANS level", l, 0, MAX_LEVEL));
        }
        if levels.iter().any(|&l| l > 0 && (l - 1) % step != 0) {
            return Err(EntropyError::InvalidTable(format!(
                "rANS levels off their grid of {step} quarter octaves"
            )));
        }
        let end = levels.iter().rposition(|&l| l > 0).map_or(0, |i| i + 1);
        let levels = levels[..end].to_vec();
        let freqs = frequencies_of_levels(&levels);
        let mut start = Vec::with_capacity(freqs.len());
        let mut at = 0u32;
        for &f in &freqs {
            start.push(at as u16);
            at += f;
        }
        let mut slots = Vec::new();
        if at == TOTAL {
            slots.reserve_exact(TOTAL as usize);
            for (sym, &f) in freqs.iter().enumerate() {
                slots.extend(std::iter::repeat_n(sym as u8, f as usize));
            }
        }
        let spans = freqs
            .iter()
            .zip(&start)
            .map(|(&f, &s)| f | (s as u32) << 16)
            .collect();
        Ok(RansTable {
            step,
            levels,
            // A frequency is at most TOTAL = 2^12: it fits 16 bits.
            freq: freqs.iter().map(|&f| f as u16).collect(),
            start,
            cost: freqs
                .iter()
                .map(|&f| {
                    if f == 0 {
                        0
                    } else {
                        (256.0 * (TOTAL as f64 / f as f64).log2()).round() as u16
                    }
                })
                .collect(),
            slots: slots.into_boxed_slice(),
            spans,
        })
    }

    /// The table for symbol counts ([`levels_of_counts`]) on the grid step that costs least:
    /// the header bits of its levels plus the counts' coded bits.
    ///
    /// # Panics
    /// If there are more than [`MAX_SYMBOLS`] counts (an encoder-side programming error).
    pub fn from_counts(counts: &[u64]) -> RansTable {
        assert!(
            counts.len() <= MAX_SYMBOLS,
            "rANS alphabet of {} symbols exceeds {MAX_SYMBOLS}",
            counts.len()
        );
        // Every counted symbol has a level on every grid, so each table codes them all.
        let cost = |t: &RansTable| -> f64 {
            t.description_bits() as f64 + t.coded_bits(counts).unwrap_or(f64::INFINITY)
        };
        LEVEL_STEPS
            .iter()
            .map(|&step| {
                RansTable::from_levels(&levels_of_counts(counts, step), step)
                    .expect("levels of at most 256 counts, on their grid")
            })
            .min_by(|a, b| cost(a).total_cmp(&cost(b)))
            .expect("a grid step")
    }

    /// The bits `counts` (per symbol) take coded with this table, at its ideal code lengths;
    /// `None` if a counted symbol cannot be coded with it.
    pub fn coded_bits(&self, counts: &[u64]) -> Option<f64> {
        let mut bits = 0.0;
        for (sym, &c) in counts.iter().enumerate().filter(|&(_, &c)| c > 0) {
            if self.frequency(sym) == 0 {
                return None;
            }
            bits += c as f64 * self.cost_bits(sym);
        }
        Some(bits)
    }

    /// The bits of this table's description ([`RansTable::write_levels`]).
    pub fn description_bits(&self) -> u64 {
        let mut counter = BitCounter::new();
        self.write_levels(&mut counter);
        counter.bits()
    }

    /// Whether no symbol can be coded with this table.
    pub fn is_empty(&self) -> bool {
        self.slots.is_empty()
    }

    /// The symbols' levels (trailing zeros trimmed).
    pub fn levels(&self) -> &[u8] {
        &self.levels
    }

    /// The frequency of a symbol (out of [`TOTAL`]); 0 if it cannot be coded.
    pub fn frequency(&self, sym: usize) -> u32 {
        self.freq.get(sym).map_or(0, |&f| f as u32)
    }

    /// A symbol's cost in bits: −log2 of its probability (+∞ if it cannot be coded).
    pub fn cost_bits(&self, sym: usize) -> f64 {
        (TOTAL as f64 / self.frequency(sym) as f64).log2()
    }

    /// A symbol's cost in 1/256 bits (0 if it cannot be coded), by table look-up.
    #[inline(always)]
    pub fn cost_q8(&self, sym: usize) -> u32 {
        self.cost.get(sym).map_or(0, |&c| c as u32)
    }

    /// Writes the grid step (2 bits: 0, 1, 2 for 1, 2, 4 quarter octaves) and the levels on
    /// it: level l as (l − 1) / step + 1, 0 for an absent symbol ([`write_small_values`]).
    pub fn write_levels(&self, sink: &mut impl BitSink) {
        let code = LEVEL_STEPS
            .iter()
            .position(|&s| s == self.step)
            .unwrap_or(0);
        sink.put_bits(code as u64, 2);
        let units: Vec<u8> = self
            .levels
            .iter()
            .map(|&l| if l == 0 { 0 } else { (l - 1) / self.step + 1 })
            .collect();
        write_small_values(sink, &units);
    }

    /// Reads levels written by [`RansTable::write_levels`] for an alphabet of at most
    /// `max_symbols` (≤ [`MAX_SYMBOLS`]).
    pub fn read_levels(
        reader: &mut BitReader,
        max_symbols: usize,
    ) -> Result<RansTable, EntropyError> {
        let code = reader.get_bits(2)? as usize;
        let step = *LEVEL_STEPS
            .get(code)
            .ok_or_else(|| EntropyError::out_of_range("rANS level step code", code as u64, 0, 2))?;
        let units = read_small_values(
            reader,
            max_symbols.min(MAX_SYMBOLS),
            6,
            ("level", "bits per level"),
        )?;
        // Units are below 64 and steps at most 4: levels stay below 256 before validation.
        let levels: Vec<u8> = units
            .iter()
            .map(|&u| if u == 0 { 0 } else { 1 + (u - 1) * step })
            .collect();
        RansTable::from_levels(&levels, step)
    }
}

/// Collects a stream's symbols in order, then writes them ([`RansEncoder::finish`]).
#[derive(Debug, Default)]
pub struct RansEncoder {
    /// (start, frequency) of each symbol, in decoding order.
    symbols: Vec<(u16, u16)>,
}

impl RansEncoder {
    /// An empty stream.
    pub fn new() -> RansEncoder {
        RansEncoder::default()
    }

    /// An empty stream with room for `n` symbols.
    pub fn with_capacity(n: usize) -> RansEncoder {
        RansEncoder {
            symbols: Vec::with_capacity(n),
        }
    }

    /// Appends `sym` coded with `table`.
    ///
    /// # Panics
    /// If the table cannot code `sym` (its count was 0 when the table was fitted: an
    /// encoder-side programming error).
    pub fn put(&mut self, table: &RansTable, sym: usize) {
        let f = table.frequency(sym);
        assert!(f > 0, "symbol {sym} has no frequency in its rANS table");
        // f ≤ TOTAL = 2^12, and the start of a used symbol is below TOTAL: both fit 16 bits
        // (a frequency of 2^12 is stored as 4096, which fits u16).
        self.symbols.push((table.start[sym], f as u16));
    }

    /// Symbols appended so far.
    pub fn len(&self) -> usize {
        self.symbols.len()
    }

    /// Whether no symbol was appended.
    pub fn is_empty(&self) -> bool {
        self.symbols.is_empty()
    }

    /// The stream's bytes: empty where the state ends where it began with no word written
    /// (no symbols, or only symbols of one-symbol tables, which cost nothing), else the final
    /// state (its high then its low 16-bit word) and the renormalization words, every word
    /// little-endian.
    pub fn finish(self) -> Vec<u8> {
        let mut x = LOWER;
        let mut words: Vec<u16> = Vec::with_capacity(self.symbols.len() / 2 + 2);
        for &(start, freq) in self.symbols.iter().rev() {
            let (start, freq) = (start as u32, freq as u32);
            // Keep x below 2^32 after coding: renormalize (one word suffices) when x ≥
            // 2^(16 + 16 − 12) · freq.
            if x as u64 >= (((LOWER >> PRECISION) as u64) << 16) * freq as u64 {
                words.push(x as u16);
                x >>= 16;
            }
            x = ((x / freq) << PRECISION) + (x % freq) + start;
        }
        if words.is_empty() && x == LOWER {
            // The decoder starts an empty stream at this state: nothing to send.
            return Vec::new();
        }
        words.push(x as u16);
        words.push((x >> 16) as u16);
        words.iter().rev().flat_map(|w| w.to_le_bytes()).collect()
    }
}

/// Reads a stream written by [`RansEncoder::finish`] from untrusted bytes.
#[derive(Debug)]
pub struct RansDecoder<'a> {
    /// The stream's 16-bit words (little-endian).
    words: &'a [[u8; 2]],
    /// The next word to read: past the end (an overrun) once a symbol needed a word the
    /// stream does not have.
    pos: usize,
    state: u32,
}

impl<'a> RansDecoder<'a> {
    /// A decoder of `bytes`: empty (a stream whose symbols cost nothing), or at least the
    /// state, a whole number of words, the state at least 2^16.
    pub fn new(bytes: &'a [u8]) -> Result<RansDecoder<'a>, EntropyError> {
        let (words, odd) = bytes.as_chunks::<2>();
        let mut d = RansDecoder {
            words,
            pos: 0,
            state: LOWER,
        };
        if bytes.is_empty() {
            return Ok(d);
        }
        if bytes.len() < 4 || !odd.is_empty() {
            return Err(EntropyError::InvalidTable(format!(
                "rANS stream of {} bytes: not a whole number of 16-bit words, or shorter than \
                 its state",
                bytes.len()
            )));
        }
        let x = (d.word() as u32) << 16 | d.word() as u32;
        if x < LOWER {
            return Err(EntropyError::InvalidTable(format!(
                "rANS state {x:#x} below its lower bound {LOWER:#x}"
            )));
        }
        d.state = x;
        Ok(d)
    }

    /// `x` with the next word shifted in if it fell below [`LOWER`] (one word always
    /// suffices), without a branch on that: whether a symbol needs a word is as unpredictable
    /// as its cost. The word is read either way (0 past the end, where taking it is an
    /// overrun: the position moves past the end).
    #[inline(always)]
    fn renormalized(&mut self, x: u32) -> u32 {
        let need = x < LOWER;
        let word = self.peek_word() as u32;
        self.pos += usize::from(need);
        if need {
            x << 16 | word
        } else {
            x
        }
    }

    /// The word at the position, 0 past the end.
    #[inline(always)]
    fn peek_word(&self) -> u16 {
        u16::from_le_bytes(self.words.get(self.pos).copied().unwrap_or([0; 2]))
    }

    #[inline(always)]
    fn word(&mut self) -> u16 {
        let word = self.peek_word();
        self.pos += 1;
        word
    }

    /// Decodes one symbol with `table`; `None` if the table is empty (no symbol can come from
    /// it: the stream is not one the encoder wrote).
    #[inline(always)]
    pub fn decode(&mut self, table: &RansTable) -> Option<usize> {
        let x = self.state;
        let slot = x & (TOTAL - 1);
        let symbol = *table.slots.get(slot as usize)? as usize;
        let span = table.spans[symbol];
        self.state = self.renormalized((span & 0xFFFF) * (x >> PRECISION) + slot - (span >> 16));
        Some(symbol)
    }

    /// Decodes a symbol of a binary table (at most two symbols, 0 and 1) from `f0`, the
    /// table's frequency of 0 ([`RansTable::frequency`]; 0 to [`TOTAL`]): the same result as
    /// [`RansDecoder::decode`] on that table, without its 4 KiB slot array, for tables kept
    /// in a few registers. The caller checks that the table is not empty.
    #[inline(always)]
    pub fn decode_binary(&mut self, f0: u32) -> bool {
        debug_assert!(f0 <= TOTAL);
        let x = self.state;
        let slot = x & (TOTAL - 1);
        let bit = slot >= f0;
        let (start, freq) = if bit { (f0, TOTAL - f0) } else { (0, f0) };
        self.state = self.renormalized(freq * (x >> PRECISION) + slot - start);
        bit
    }

    /// Whether a read went past the end of the stream.
    pub fn overrun(&self) -> bool {
        self.pos > self.words.len()
    }

    /// Whether the stream ended exactly where its encoder began: every word read, nothing
    /// read past the end, the state at its initial value.
    pub fn is_complete(&self) -> bool {
        self.pos == self.words.len() && self.state == LOWER
    }
}

#[cfg(test)]
mod tests {
    use super::super::bits::BitWriter;
    use super::*;

    /// A small deterministic generator (xorshift), so the tests need no crate for randomness.
    struct Rng(u64);
    impl Rng {
        fn next(&mut self) -> u64 {
            self.0 ^= self.0 << 13;
            self.0 ^= self.0 >> 7;
            self.0 ^= self.0 << 17;
            self.0
        }
        /// A symbol drawn from `counts` (as a distribution).
        fn draw(&mut self, counts: &[u64]) -> usize {
            let total: u64 = counts.iter().sum();
            let mut r = self.next() % total;
            for (i, &c) in counts.iter().enumerate() {
                if r < c {
                    return i;
                }
                r -= c;
            }
            unreachable!()
        }
    }

    fn tables() -> Vec<(Vec<u64>, RansTable)> {
        let skewed = vec![900, 60, 25, 10, 4, 1];
        let flat = vec![1; 256];
        let sparse: Vec<u64> = (0..256)
            .map(|i| if i % 17 == 3 { i as u64 } else { 0 })
            .collect();
        let lone = vec![0, 0, 5];
        [skewed, flat, sparse, lone]
            .into_iter()
            .map(|c| {
                let t = RansTable::from_counts(&c);
                (c, t)
            })
            .collect()
    }

    #[test]
    fn frequencies_sum_to_the_total_and_keep_every_used_symbol() {
        let mut rng = Rng(7);
        let mut cases: Vec<Vec<u8>> = vec![
            vec![],
            vec![0, 0],
            vec![1],
            vec![MAX_LEVEL],
            vec![1; 256],
            vec![MAX_LEVEL; 256],
        ];
        // One heavy symbol and 255 at the lowest level: the raise to 1 must be paid for.
        let mut heavy = vec![1u8; 256];
        heavy[100] = MAX_LEVEL;
        cases.push(heavy);
        for _ in 0..200 {
            let n = 1 + rng.next() as usize % 256;
            cases.push((0..n).map(|_| (rng.next() % 50) as u8).collect());
        }
        for levels in cases {
            let f = frequencies_of_levels(&levels);
            let used = levels.iter().filter(|&&l| l > 0).count();
            let sum: u32 = f.iter().sum();
            assert_eq!(sum, if used > 0 { TOTAL } else { 0 }, "{levels:?}");
            for (l, f) in levels.iter().zip(&f) {
                assert_eq!(*l > 0, *f > 0, "{levels:?}");
            }
        }
    }

    #[test]
    fn frequencies_follow_the_levels_within_rounding() {
        // Two used symbols eight quarter-octaves apart weigh 1 : 4.
        let f = frequencies_of_levels(&[41, 0, 49]);
        assert_eq!(f[0] + f[2], TOTAL);
        assert!((f[2] as i64 - 4 * f[0] as i64).abs() <= 4, "{f:?}");
        // Symbols at the same level share equally.
        let f = frequencies_of_levels(&[10, 10, 10, 10]);
        assert_eq!(f, vec![1024; 4]);
    }

    #[test]
    fn binary_symbols_decode_as_the_slot_table_decodes_them() {
        // Binary tables from every split, both one-symbol tables included, mixed in one stream
        // with a 256-symbol table; decode_binary must follow decode symbol by symbol.
        let mut rng = Rng(11);
        let binary: Vec<(Vec<u64>, RansTable)> = [
            [1, 0],
            [0, 1],
            [1, 1],
            [999, 1],
            [1, 999],
            [70, 30],
            [3, 5000],
        ]
        .into_iter()
        .map(|c| (c.to_vec(), RansTable::from_counts(&c)))
        .collect();
        let wide = RansTable::from_counts(&[5; 256]);
        let mut enc = RansEncoder::new();
        let mut expected = Vec::new();
        for _ in 0..5000 {
            let t = rng.next() as usize % (binary.len() + 1);
            if t == binary.len() {
                let sym = rng.next() as usize % 256;
                enc.put(&wide, sym);
                expected.push((t, sym));
            } else {
                let sym = rng.draw(&binary[t].0);
                enc.put(&binary[t].1, sym);
                expected.push((t, sym));
            }
        }
        let bytes = enc.finish();
        let mut slow = RansDecoder::new(&bytes).unwrap();
        let mut fast = RansDecoder::new(&bytes).unwrap();
        for &(t, sym) in &expected {
            if t == binary.len() {
                assert_eq!(slow.decode(&wide), Some(sym));
                assert_eq!(fast.decode(&wide), Some(sym));
            } else {
                let table = &binary[t].1;
                assert_eq!(slow.decode(table), Some(sym));
                assert_eq!(fast.decode_binary(table.frequency(0)), sym == 1, "{t}");
            }
        }
        assert!(slow.is_complete() && fast.is_complete());
    }

    #[test]
    fn streams_round_trip_at_any_length() {
        let tables = tables();
        let mut rng = Rng(42);
        for n in [0usize, 1, 2, 3, 10, 1001, 20_000] {
            let mut enc = RansEncoder::with_capacity(n);
            let mut expected = Vec::with_capacity(n);
            for _ in 0..n {
                let t = rng.next() as usize % tables.len();
                let sym = rng.draw(&tables[t].0);
                enc.put(&tables[t].1, sym);
                expected.push((t, sym));
            }
            assert_eq!(enc.len(), n);
            let bytes = enc.finish();
            assert_eq!(
                bytes.is_empty(),
                n == 0 || expected.iter().all(|&(t, _)| t == 3)
            );
            let mut dec = RansDecoder::new(&bytes).unwrap();
            for (i, &(t, sym)) in expected.iter().enumerate() {
                assert_eq!(dec.decode(&tables[t].1), Some(sym), "symbol {i} of {n}");
            }
            assert!(dec.is_complete(), "{n} symbols");
        }
    }

    #[test]
    fn a_stream_costs_its_ideal_length_within_the_final_state() {
        // The independent reference: −log2 of each coded symbol's probability, summed in f64.
        let tables = tables();
        let mut rng = Rng(3);
        for (counts, table) in &tables {
            let mut enc = RansEncoder::new();
            let mut ideal = 0.0;
            for _ in 0..50_000 {
                let sym = rng.draw(counts);
                ideal += table.cost_bits(sym);
                enc.put(table, sym);
            }
            let bits = 8.0 * enc.finish().len() as f64;
            // The 32-bit state is flushed; 12-bit precision costs a little more than ideal.
            assert!(bits >= ideal - 1.0, "{bits} < {ideal}");
            assert!(bits <= ideal * 1.001 + 32.0 + 16.0, "{bits} vs {ideal}");
        }
        // A symbol of probability 0.9 costs about 0.15 bits, where a prefix code spends 1.
        let t = RansTable::from_counts(&[9, 1]);
        assert!(t.cost_bits(0) < 0.2, "{}", t.cost_bits(0));
        // A table of one symbol costs nothing: the stream is empty.
        let lone = RansTable::from_counts(&[0, 0, 5]);
        let mut enc = RansEncoder::new();
        for _ in 0..1000 {
            enc.put(&lone, 2);
        }
        let bytes = enc.finish();
        assert!(bytes.is_empty(), "{} bytes", bytes.len());
        let mut dec = RansDecoder::new(&bytes).unwrap();
        assert!((0..1000).all(|_| dec.decode(&lone) == Some(2)));
        assert!(dec.is_complete());
        // An empty stream holds nothing for a table of two symbols.
        let mut dec = RansDecoder::new(&[]).unwrap();
        let _ = dec.decode(&tables[0].1);
        assert!(!dec.is_complete());
    }

    #[test]
    fn the_grid_step_is_chosen_by_what_header_and_symbols_cost_together() {
        let cost = |t: &RansTable, counts: &[u64]| -> f64 {
            let mut w = BitWriter::new();
            t.write_levels(&mut w);
            let coded: f64 = (0..counts.len())
                .filter(|&i| counts[i] > 0)
                .map(|i| counts[i] as f64 * t.cost_bits(i))
                .sum();
            8.0 * w.finish().len() as f64 + coded
        };
        let mut rng = Rng(5);
        let mut steps = std::collections::BTreeSet::new();
        for scale in [1u64, 3, 30, 3000, 300_000] {
            for _ in 0..10 {
                let counts: Vec<u64> = (0..256)
                    .map(|i| {
                        let r = rng.next();
                        // A geometric-like spread over the alphabet, a few symbols absent.
                        if r.is_multiple_of(7) {
                            0
                        } else {
                            1 + (r >> 8) % (scale * 256 / (i + 1))
                        }
                    })
                    .collect();
                let chosen = RansTable::from_counts(&counts);
                steps.insert(chosen.step);
                for &step in &LEVEL_STEPS {
                    let other =
                        RansTable::from_levels(&levels_of_counts(&counts, step), step).unwrap();
                    // Whole bytes here, bits in the choice: allow the byte rounding.
                    assert!(cost(&chosen, &counts) <= cost(&other, &counts) + 8.0);
                }
            }
        }
        assert!(
            steps.len() >= 2,
            "one step chosen for every spread: {steps:?}"
        );
    }

    #[test]
    fn levels_round_trip_through_the_header_form() {
        for &step in &LEVEL_STEPS {
            let counts = [500, 0, 20, 3, 1, 0, 0];
            let t = RansTable::from_levels(&levels_of_counts(&counts, step), step).unwrap();
            let mut w = BitWriter::new();
            t.write_levels(&mut w);
            let back = RansTable::read_levels(&mut BitReader::new(&w.finish()), 7).unwrap();
            assert_eq!(back, t, "step {step}");
        }
        for (counts, table) in tables() {
            let mut w = BitWriter::new();
            table.write_levels(&mut w);
            let bytes = w.finish();
            let back = RansTable::read_levels(&mut BitReader::new(&bytes), counts.len()).unwrap();
            assert_eq!(back, table);
        }
        let empty = RansTable::from_counts(&[0, 0, 0]);
        assert!(empty.is_empty());
        assert!(
            RansDecoder::new(&[0; 4]).is_err(),
            "a state below the bound"
        );
        assert!(RansDecoder::new(&[1, 0, 0]).is_err(), "an odd length");
        // A level above the largest, or an alphabet above the bound, is refused.
        assert!(RansTable::from_levels(&[MAX_LEVEL + 1], 1).is_err());
        assert!(RansTable::from_levels(&[1; MAX_SYMBOLS + 1], 1).is_err());
        assert!(RansTable::from_levels(&[1, 3], 4).is_err(), "off the grid");
        assert!(RansTable::from_levels(&[1, 5], 3).is_err(), "no such step");
        let mut w = BitWriter::new();
        RansTable::from_counts(&[1; 64]).write_levels(&mut w);
        assert!(RansTable::read_levels(&mut BitReader::new(&w.finish()), 63).is_err());
    }

    #[test]
    fn hostile_streams_never_panic_and_are_not_complete() {
        let tables = tables();
        let mut rng = Rng(99);
        // A valid stream, truncated or with a flipped bit, does not end where it began.
        let mut enc = RansEncoder::new();
        let mut syms = Vec::new();
        for _ in 0..500 {
            let sym = rng.draw(&tables[0].0);
            enc.put(&tables[0].1, sym);
            syms.push(sym);
        }
        let bytes = enc.finish();
        let run = |b: &[u8]| -> bool {
            let Ok(mut d) = RansDecoder::new(b) else {
                return false;
            };
            let same = syms.iter().all(|&s| d.decode(&tables[0].1) == Some(s));
            same && d.is_complete()
        };
        assert!(run(&bytes));
        for cut in [2, 8, bytes.len() / 2, bytes.len() - 2] {
            let short = &bytes[..bytes.len() - cut];
            assert!(!run(short), "cut {cut}");
            // The words cut off are words the symbols need: reading them is an overrun (or
            // what is left is shorter than the state, refused at once).
            if let Ok(mut d) = RansDecoder::new(short) {
                for _ in &syms {
                    d.decode(&tables[0].1);
                }
                assert!(d.overrun(), "cut {cut}");
            }
        }
        let mut flipped = 0;
        for i in 0..bytes.len() {
            let mut b = bytes.clone();
            b[i] ^= 1 << (rng.next() % 8);
            flipped += !run(&b) as usize;
        }
        assert!(
            flipped * 100 >= bytes.len() * 95,
            "{flipped} of {}",
            bytes.len()
        );
        // Random bytes through random tables: no panic, and an empty table yields nothing.
        for _ in 0..500 {
            let n = 2 * (rng.next() as usize % 40);
            let b: Vec<u8> = (0..n).map(|_| rng.next() as u8).collect();
            if let Ok(mut d) = RansDecoder::new(&b) {
                for _ in 0..100 {
                    let t = rng.next() as usize % tables.len();
                    assert!(d.decode(&tables[t].1).is_some_and(|s| s < 256));
                }
                assert_eq!(d.decode(&RansTable::from_counts(&[])), None);
            }
        }
    }
}
