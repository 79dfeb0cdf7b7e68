//! Length-limited canonical Huffman codes (paper §4.3: the positional, tag and delta tables).
//!
//! [`HuffmanCode`] is built from symbol frequencies by package-merge (optimal under a maximum
//! code length) or from transmitted code lengths, and serializes its lengths compactly with
//! [`HuffmanCode::write_lengths`]. Codes are canonical (DEFLATE order: shorter codes first, ties
//! by symbol index), so the lengths alone define the code. [`HuffmanDecoder`] decodes through a
//! 10-bit look-up table as the paper proposes, and resolves longer codes (and invalid prefixes)
//! by comparing against the first canonical code of each longer length. The bit-serial
//! [`HuffmanDecoder::decode_canonical`] is kept as the naive reference both are tested against.

use super::bits::{BitReader, BitSink};
use super::EntropyError;

/// Longest code length supported.
pub const MAX_CODE_LEN: u8 = 16;
/// Largest alphabet supported.
pub const MAX_ALPHABET: usize = 1 << 16;
/// Number of bits the decoder's look-up table resolves at once.
pub const LOOKUP_BITS: u32 = 10;

/// A canonical prefix code: one code length per symbol (0 = symbol has no code).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct HuffmanCode {
    lengths: Vec<u8>,
    codes: Vec<u16>,
}

impl HuffmanCode {
    /// An optimal prefix code for `freqs` with no code longer than `max_len`, by package-merge.
    ///
    /// Symbols with frequency 0 get no code (length 0). With a single used symbol it gets a 1-bit
    /// code; with none the code is empty. `max_len` is clamped to `1..=16` and raised, if needed,
    /// to the smallest length that can give every used symbol a code.
    ///
    /// # Panics
    /// If `freqs.len()` exceeds [`MAX_ALPHABET`] (an encoder-side programming error).
    pub fn from_frequencies(freqs: &[u64], max_len: u8) -> HuffmanCode {
        assert!(
            freqs.len() <= MAX_ALPHABET,
            "Huffman alphabet of {} symbols exceeds {MAX_ALPHABET}",
            freqs.len()
        );
        let mut lengths = vec![0u8; freqs.len()];
        let mut leaves: Vec<(u64, usize)> = freqs
            .iter()
            .enumerate()
            .filter(|&(_, &f)| f > 0)
            .map(|(s, &f)| (f, s))
            .collect();
        match leaves.len() {
            0 => {}
            1 | 2 => leaves.iter().for_each(|&(_, s)| lengths[s] = 1),
            n => {
                leaves.sort_unstable();
                let needed = usize::BITS - (n - 1).leading_zeros();
                let max_len = (max_len.clamp(1, MAX_CODE_LEN) as u32).max(needed);
                package_merge(&leaves, max_len, &mut lengths);
            }
        }
        Self::from_lengths(&lengths).expect("package-merge produced an invalid code")
    }

    /// The canonical code with the given lengths, after validating them: every length ≤ 16, at
    /// most [`MAX_ALPHABET`] symbols, and the Kraft sum Σ 2^−len ≤ 1. Incomplete codes (Kraft sum
    /// < 1, e.g. a single used symbol) are valid; their unused bit patterns fail to decode.
    pub fn from_lengths(lengths: &[u8]) -> Result<HuffmanCode, EntropyError> {
        if lengths.len() > MAX_ALPHABET {
            return Err(EntropyError::InvalidTable(format!(
                "alphabet of {} symbols exceeds the maximum of {MAX_ALPHABET}",
                lengths.len()
            )));
        }
        let mut count = [0u32; MAX_CODE_LEN as usize + 1];
        for (sym, &len) in lengths.iter().enumerate() {
            if len > MAX_CODE_LEN {
                return Err(EntropyError::InvalidTable(format!(
                    "symbol {sym} has code length {len}, maximum is {MAX_CODE_LEN}"
                )));
            }
            count[len as usize] += 1;
        }
        let kraft: u64 = (1..=MAX_CODE_LEN as usize)
            .map(|l| (count[l] as u64) << (MAX_CODE_LEN as usize - l))
            .sum();
        if kraft > 1 << MAX_CODE_LEN {
            return Err(EntropyError::InvalidTable(format!(
                "code lengths oversubscribe the code space (Kraft sum {kraft}/65536 > 1)"
            )));
        }
        // Canonical assignment: first code of each length, then consecutive codes by symbol.
        let mut next = [0u32; MAX_CODE_LEN as usize + 2];
        let mut code = 0u32;
        for len in 1..=MAX_CODE_LEN as usize {
            code = (code + count[len - 1] * (len > 1) as u32) << 1;
            next[len] = code;
        }
        let codes = lengths
            .iter()
            .map(|&len| {
                if len == 0 {
                    return 0;
                }
                let c = next[len as usize];
                next[len as usize] += 1;
                c as u16
            })
            .collect();
        Ok(HuffmanCode {
            lengths: lengths.to_vec(),
            codes,
        })
    }

    /// Writes the codeword of `sym`. Encoding a symbol without a code is a programming error:
    /// it asserts in debug builds and writes nothing in release builds.
    #[inline]
    pub fn encode(&self, sym: usize, sink: &mut impl BitSink) {
        match self.lengths.get(sym) {
            Some(&len) if len > 0 => sink.put_bits(self.codes[sym] as u64, len as u32),
            _ => debug_assert!(false, "Huffman symbol {sym} has no code"),
        }
    }

    /// Length in bits of the codeword of `sym` (0 if it has none).
    #[inline]
    pub fn cost_bits(&self, sym: usize) -> u32 {
        self.lengths.get(sym).map_or(0, |&l| l as u32)
    }

    /// The codeword of `sym` as `(code, length)`, right-aligned, or `None` if it has none.
    pub fn codeword(&self, sym: usize) -> Option<(u16, u8)> {
        match self.lengths.get(sym) {
            Some(&len) if len > 0 => Some((self.codes[sym], len)),
            _ => None,
        }
    }

    /// Total bits needed to code a histogram `freqs` (symbols beyond the alphabet or without a
    /// code contribute nothing).
    pub fn cost_of(&self, freqs: &[u64]) -> u64 {
        freqs
            .iter()
            .enumerate()
            .map(|(s, &f)| f * self.cost_bits(s) as u64)
            .sum()
    }

    /// Code length of every symbol (0 = no code).
    pub fn lengths(&self) -> &[u8] {
        &self.lengths
    }

    /// Size of the alphabet (including symbols without a code).
    pub fn num_symbols(&self) -> usize {
        self.lengths.len()
    }

    /// Number of symbols that have a code.
    pub fn num_used(&self) -> usize {
        self.lengths.iter().filter(|&&l| l > 0).count()
    }

    /// Longest code length (0 for an empty code).
    pub fn max_length(&self) -> u8 {
        self.lengths.iter().copied().max().unwrap_or(0)
    }

    /// Writes the code lengths compactly (see [`HuffmanCode::read_lengths`] for the format).
    /// Use a [`super::bits::BitCounter`] to learn the header cost.
    pub fn write_lengths(&self, sink: &mut impl BitSink) {
        write_small_values(sink, &self.lengths);
    }

    /// Reads code lengths written by [`HuffmanCode::write_lengths`] and validates them as in
    /// [`HuffmanCode::from_lengths`]; an alphabet larger than `max_symbols` is an error.
    ///
    /// Format ([`write_small_values`]): 5 bits `w`, then the alphabet size `n` in `w` bits; 3
    /// bits `b` (bits per length, 0 meaning all lengths are 0); then tokens until `n` lengths
    /// are known: `0` + `b` bits is one literal length, `10` + Elias-gamma `r` is a run of `r`
    /// zeros, `11` + Elias-gamma `r` repeats the previous length (initially 0) `r` times.
    pub fn read_lengths(
        reader: &mut BitReader,
        max_symbols: usize,
    ) -> Result<HuffmanCode, EntropyError> {
        let lengths = read_small_values(
            reader,
            max_symbols.min(MAX_ALPHABET),
            5,
            ("code length", "bits per code length"),
        )?;
        HuffmanCode::from_lengths(&lengths)
    }
}

/// Writes a table of small values (one per symbol, most of them 0 or repeating): Huffman code
/// lengths, and the rANS tables' levels ([`super::rans`]). Format: see
/// [`HuffmanCode::read_lengths`]; `values.len()` must fit 17 bits and the values 7.
pub(crate) fn write_small_values(sink: &mut impl BitSink, values: &[u8]) {
    let n = values.len() as u64;
    let width = u64::BITS - n.leading_zeros();
    sink.put_bits(width as u64, 5);
    sink.put_bits(n, width);
    let max = values.iter().copied().max().unwrap_or(0);
    let lbits = u8::BITS - max.leading_zeros();
    sink.put_bits(lbits as u64, 3);
    if lbits == 0 {
        return;
    }
    let literal_cost = 1 + lbits as u64;
    let mut prev = 0u8;
    let mut i = 0;
    while i < values.len() {
        let len = values[i];
        let run = values[i..].iter().take_while(|&&l| l == len).count();
        let mut rest = run;
        if len == 0 && 2 + gamma_bits(run as u64) < literal_cost * run as u64 {
            sink.put_bits(0b10, 2);
            put_gamma(sink, run as u64);
            rest = 0;
        } else if len != prev {
            sink.put_bit(false);
            sink.put_bits(len as u64, lbits);
            rest -= 1;
        }
        if rest > 0 {
            if 2 + gamma_bits(rest as u64) < literal_cost * rest as u64 {
                sink.put_bits(0b11, 2);
                put_gamma(sink, rest as u64);
            } else {
                for _ in 0..rest {
                    sink.put_bit(false);
                    sink.put_bits(len as u64, lbits);
                }
            }
        }
        prev = len;
        i += run;
    }
}

/// Reads a table written by [`write_small_values`]: at most `max_symbols` values of at most
/// `max_value_bits` bits. `names` name a value and the bits per value in errors.
pub(crate) fn read_small_values(
    reader: &mut BitReader,
    max_symbols: usize,
    max_value_bits: u32,
    names: (&'static str, &'static str),
) -> Result<Vec<u8>, EntropyError> {
    let (what, width_what) = names;
    let width = reader.get_bits(5)? as u32;
    if width > 17 {
        return Err(EntropyError::out_of_range(
            "alphabet size width",
            width,
            0,
            17,
        ));
    }
    let n = reader.get_bits(width)?;
    if n > max_symbols as u64 {
        return Err(EntropyError::out_of_range(
            "alphabet size",
            n,
            0,
            max_symbols as u64,
        ));
    }
    let n = n as usize;
    let lbits = reader.get_bits(3)? as u32;
    if lbits > max_value_bits {
        return Err(EntropyError::out_of_range(
            width_what,
            lbits,
            0,
            max_value_bits,
        ));
    }
    let mut values = Vec::with_capacity(n);
    if lbits > 0 {
        let mut prev = 0u8;
        while values.len() < n {
            if !reader.get_bit()? {
                prev = reader.get_bits(lbits)? as u8;
                values.push(prev);
                continue;
            }
            let repeat = reader.get_bit()?;
            let run = get_gamma(reader, 17)?;
            let left = (n - values.len()) as u64;
            if run > left {
                return Err(EntropyError::InvalidTable(format!(
                    "run of {run} {what}s exceeds the {left} symbols left"
                )));
            }
            let value = if repeat { prev } else { 0 };
            values.extend(std::iter::repeat_n(value, run as usize));
            prev = value;
        }
    } else {
        values.resize(n, 0);
    }
    Ok(values)
}

/// Bits of the Elias-gamma code of `v` ≥ 1.
fn gamma_bits(v: u64) -> u64 {
    let nbits = u64::BITS - v.leading_zeros();
    2 * nbits as u64 - 1
}

/// Elias-gamma code of `v` ≥ 1: `nbits − 1` zeros, then `v` in `nbits` bits.
fn put_gamma(sink: &mut impl BitSink, v: u64) {
    debug_assert!(v >= 1);
    let nbits = u64::BITS - v.leading_zeros();
    sink.put_bits(0, nbits - 1);
    sink.put_bits(v, nbits);
}

/// Reads an Elias-gamma value of at most `max_bits` significant bits.
fn get_gamma(reader: &mut BitReader, max_bits: u32) -> Result<u64, EntropyError> {
    let mut zeros = 0;
    while !reader.get_bit()? {
        zeros += 1;
        if zeros >= max_bits {
            return Err(EntropyError::InvalidTable(format!(
                "run length prefix longer than {} bits",
                max_bits - 1
            )));
        }
    }
    Ok((1 << zeros) | reader.get_bits(zeros)?)
}

/// Package-merge (Larmore–Hirschberg): optimal code lengths ≤ `max_len` for `leaves` (weight,
/// symbol), sorted by ascending weight, with `2^max_len ≥ leaves.len() ≥ 2`.
fn package_merge(leaves: &[(u64, usize)], max_len: u32, lengths: &mut [u8]) {
    const PACKAGE: u32 = u32::MAX;
    let n = leaves.len();
    // Item kinds of every list, from the deepest level (leaves only) up to level 1. Each list is
    // the merge, by weight, of the leaves with the pairwise packages of the list below.
    let mut kinds: Vec<Vec<u32>> = Vec::with_capacity(max_len as usize);
    let mut weights: Vec<u128> = leaves.iter().map(|&(w, _)| w as u128).collect();
    kinds.push((0..n as u32).collect());
    for _ in 1..max_len {
        let packages: Vec<u128> = weights.chunks_exact(2).map(|p| p[0] + p[1]).collect();
        let mut next_w = Vec::with_capacity(n + packages.len());
        let mut next_k = Vec::with_capacity(n + packages.len());
        let (mut i, mut j) = (0, 0);
        while i < n || j < packages.len() {
            if j == packages.len() || (i < n && leaves[i].0 as u128 <= packages[j]) {
                next_w.push(leaves[i].0 as u128);
                next_k.push(i as u32);
                i += 1;
            } else {
                next_w.push(packages[j]);
                next_k.push(PACKAGE);
                j += 1;
            }
        }
        weights = next_w;
        kinds.push(next_k);
    }
    // The first 2n − 2 items of the top list are selected; the packages among a selected prefix
    // are the first packages of the list below, i.e. they select a prefix there too.
    let mut take = 2 * n - 2;
    for list in kinds.iter().rev() {
        debug_assert!(take <= list.len());
        let mut packages = 0;
        for &k in &list[..take.min(list.len())] {
            if k == PACKAGE {
                packages += 1;
            } else {
                lengths[leaves[k as usize].1] += 1;
            }
        }
        take = 2 * packages;
    }
}

/// Look-up-table entry: `symbol << 5 | length`; length 0 sends decoding to the slow path.
type Entry = u32;

/// Table-driven decoder for a [`HuffmanCode`].
#[derive(Debug, Clone)]
pub struct HuffmanDecoder {
    /// Indexed by the next `table_bits` bits of input.
    table: Vec<Entry>,
    table_bits: u32,
    max_len: u32,
    /// Number of codes of each length.
    count: [u32; MAX_CODE_LEN as usize + 1],
    /// First canonical code of each length.
    first: [u32; MAX_CODE_LEN as usize + 1],
    /// Index in `sorted` of the first symbol of each length.
    base: [u32; MAX_CODE_LEN as usize + 1],
    /// Symbols in canonical order (by length, then symbol index).
    sorted: Vec<u32>,
}

impl HuffmanDecoder {
    /// Builds the decoding tables (a look-up table of at most 2^10 entries).
    pub fn new(code: &HuffmanCode) -> HuffmanDecoder {
        let max_len = code.max_length() as u32;
        let table_bits = max_len.clamp(1, LOOKUP_BITS);
        let mut table = vec![0 as Entry; 1 << table_bits];
        let mut count = [0u32; MAX_CODE_LEN as usize + 1];
        let mut sorted: Vec<(u8, u32)> = Vec::new();
        for (sym, &len) in code.lengths.iter().enumerate() {
            if len == 0 {
                continue;
            }
            count[len as usize] += 1;
            sorted.push((len, sym as u32));
            let len = len as u32;
            if len <= table_bits {
                let start = (code.codes[sym] as usize) << (table_bits - len);
                let entry = (sym as u32) << 5 | len;
                table[start..start + (1 << (table_bits - len))].fill(entry);
            }
        }
        sorted.sort_unstable();
        let mut first = [0u32; MAX_CODE_LEN as usize + 1];
        let mut base = [0u32; MAX_CODE_LEN as usize + 1];
        let (mut next_code, mut next_index) = (0u32, 0u32);
        for len in 1..=MAX_CODE_LEN as usize {
            first[len] = next_code;
            base[len] = next_index;
            next_code = (next_code + count[len]) << 1;
            next_index += count[len];
        }
        HuffmanDecoder {
            table,
            table_bits,
            max_len,
            count,
            first,
            base,
            sorted: sorted.into_iter().map(|(_, s)| s).collect(),
        }
    }

    /// Decodes one symbol. Invalid codewords give [`EntropyError::InvalidCode`] and truncated
    /// input [`EntropyError::UnexpectedEnd`]; on error the reader is not advanced.
    #[inline]
    pub fn decode(&self, reader: &mut BitReader) -> Result<usize, EntropyError> {
        let entry = self.table[reader.peek_bits(self.table_bits) as usize];
        let len = entry & 31;
        if len == 0 {
            return self.decode_long(reader);
        }
        reader.consume(len)?;
        Ok((entry >> 5) as usize)
    }

    /// Decodes the symbol at the top of `window` (the next input bits, first bit most
    /// significant, at least as many of them valid as the code's longest codeword, at most
    /// [`MAX_CODE_LEN`]): its symbol and code length, or `None` if the bits start no codeword.
    /// For readers that keep their own bit buffer.
    #[inline]
    pub fn decode_window(&self, window: u64) -> Option<(usize, u32)> {
        let entry = self.table[(window >> (64 - self.table_bits)) as usize];
        let len = entry & 31;
        if len != 0 {
            return Some(((entry >> 5) as usize, len));
        }
        self.decode_window_long(window)
    }

    /// Slow path of [`HuffmanDecoder::decode_window`] and [`HuffmanDecoder::decode`]: codes
    /// longer than the table, compared with the first canonical code of each length.
    fn decode_window_long(&self, window: u64) -> Option<(usize, u32)> {
        for len in self.table_bits + 1..=self.max_len {
            let code = (window >> (64 - len)) as u32;
            let offset = code.wrapping_sub(self.first[len as usize]);
            if offset < self.count[len as usize] {
                let symbol = self.sorted[(self.base[len as usize] + offset) as usize];
                return Some((symbol as usize, len));
            }
        }
        None
    }

    /// Slow path of [`HuffmanDecoder::decode`]: codes longer than the table, or invalid input.
    fn decode_long(&self, reader: &mut BitReader) -> Result<usize, EntropyError> {
        match self.decode_window_long(reader.peek_bits(64)) {
            Some((symbol, len)) => {
                reader.consume(len)?;
                Ok(symbol)
            }
            None => self.invalid(reader),
        }
    }

    fn invalid(&self, reader: &BitReader) -> Result<usize, EntropyError> {
        let remaining = reader.bits_remaining();
        if remaining < self.max_len as u64 {
            // The zero-filled bits past the end may be what made the pattern invalid.
            return Err(EntropyError::UnexpectedEnd {
                needed: self.max_len as u64,
                remaining,
            });
        }
        Err(EntropyError::InvalidCode {
            position: reader.position(),
        })
    }

    /// Decodes one symbol bit-serially from the code-length counts alone, without any table: the
    /// naive reference that [`HuffmanDecoder::decode`] is tested against.
    pub fn decode_canonical(&self, reader: &mut BitReader) -> Result<usize, EntropyError> {
        let window = reader.peek_bits(self.max_len);
        let (mut code, mut first, mut index) = (0u64, 0u64, 0u64);
        for len in 1..=self.max_len {
            code |= (window >> (self.max_len - len)) & 1;
            let count = self.count[len as usize] as u64;
            if code < first + count {
                reader.consume(len)?;
                return Ok(self.sorted[(index + code - first) as usize] as usize);
            }
            index += count;
            first = (first + count) << 1;
            code <<= 1;
        }
        self.invalid(reader)
    }
}

#[cfg(test)]
mod tests {
    use super::super::bits::{BitCounter, BitWriter};
    use super::*;
    use proptest::prelude::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn kraft(lengths: &[u8]) -> u64 {
        lengths
            .iter()
            .filter(|&&l| l > 0)
            .map(|&l| 1u64 << (16 - l))
            .sum()
    }

    /// Cost and depth of an optimal unrestricted Huffman code, by the classic two-smallest merge.
    fn huffman_cost(freqs: &[u64]) -> (u64, u32) {
        use std::cmp::Reverse;
        let mut heap: std::collections::BinaryHeap<Reverse<(u64, u32)>> = freqs
            .iter()
            .filter(|&&f| f > 0)
            .map(|&f| Reverse((f, 0)))
            .collect();
        let mut cost = 0;
        while heap.len() > 1 {
            let (a, da) = heap.pop().unwrap().0;
            let (b, db) = heap.pop().unwrap().0;
            cost += a + b;
            heap.push(Reverse((a + b, da.max(db) + 1)));
        }
        (cost, heap.pop().map_or(0, |r| r.0 .1))
    }

    fn round_trip(code: &HuffmanCode, symbols: &[usize]) {
        let mut w = BitWriter::new();
        let mut c = BitCounter::new();
        code.write_lengths(&mut w);
        code.write_lengths(&mut c);
        for &s in symbols {
            code.encode(s, &mut w);
            code.encode(s, &mut c);
        }
        assert_eq!(w.bits(), c.bits());
        let expected: u64 = symbols.iter().map(|&s| code.cost_bits(s) as u64).sum();
        let bytes = w.finish();
        assert_eq!(bytes.len() as u64, c.bytes());
        let mut r = BitReader::new(&bytes);
        let read = HuffmanCode::read_lengths(&mut r, MAX_ALPHABET).unwrap();
        assert_eq!(&read, code);
        let header = r.position();
        let dec = HuffmanDecoder::new(&read);
        let mut r2 = r.clone();
        let mut r3 = r.clone();
        for &s in symbols {
            assert_eq!(dec.decode(&mut r).unwrap(), s);
            assert_eq!(dec.decode_canonical(&mut r2).unwrap(), s);
            let window = r3.peek_bits(64);
            let (symbol, len) = dec.decode_window(window).unwrap();
            assert_eq!((symbol, len), (s, code.cost_bits(s)));
            r3.consume(len).unwrap();
        }
        assert_eq!(r.position() - header, expected);
        assert_eq!(r2.position(), r.position());
    }

    #[test]
    fn small_cases() {
        let empty = HuffmanCode::from_frequencies(&[0, 0, 0], 16);
        assert_eq!(empty.lengths(), &[0, 0, 0]);
        round_trip(&empty, &[]);
        let dec = HuffmanDecoder::new(&empty);
        assert!(dec.decode(&mut BitReader::new(&[0xFF, 0])).is_err());

        let one = HuffmanCode::from_frequencies(&[0, 7, 0], 16);
        assert_eq!(one.lengths(), &[0, 1, 0]);
        round_trip(&one, &[1, 1, 1]);
        // The unused pattern `1` is invalid.
        let dec = HuffmanDecoder::new(&one);
        let mut r = BitReader::new(&[0x80]);
        assert_eq!(
            dec.decode(&mut r),
            Err(EntropyError::InvalidCode { position: 0 })
        );

        let two = HuffmanCode::from_frequencies(&[1000, 1], 16);
        assert_eq!(two.lengths(), &[1, 1]);
        round_trip(&two, &[0, 1, 1, 0]);

        assert_eq!(HuffmanCode::from_frequencies(&[], 16).num_symbols(), 0);
    }

    #[test]
    fn canonical_codes_match_deflate_example() {
        // RFC 1951 §3.2.2: lengths (3, 3, 3, 3, 3, 2, 4, 4).
        let code = HuffmanCode::from_lengths(&[3, 3, 3, 3, 3, 2, 4, 4]).unwrap();
        let codes: Vec<_> = (0..8).map(|s| code.codeword(s).unwrap().0).collect();
        assert_eq!(
            codes,
            [0b010, 0b011, 0b100, 0b101, 0b110, 0b00, 0b1110, 0b1111]
        );
    }

    #[test]
    fn length_limit_is_respected_and_optimal_when_loose() {
        // Fibonacci frequencies make the unrestricted Huffman tree maximally deep.
        let mut fib = vec![1u64, 1];
        while fib.len() < 30 {
            fib.push(fib[fib.len() - 1] + fib[fib.len() - 2]);
        }
        // 16 Fibonacci weights: the optimal tree has depth 15, within the limit.
        let loose = HuffmanCode::from_frequencies(&fib[..16], 16);
        assert_eq!(huffman_cost(&fib[..16]).1, 15);
        assert_eq!(loose.cost_of(&fib[..16]), huffman_cost(&fib[..16]).0);
        let tight = HuffmanCode::from_frequencies(&fib[..20], 16);
        assert_eq!(tight.max_length(), 16);
        assert!(tight.cost_of(&fib[..20]) > huffman_cost(&fib[..20]).0);
        for max_len in [5u8, 7, 10, 12, 16] {
            let code = HuffmanCode::from_frequencies(&fib, max_len);
            assert!(
                code.max_length() <= max_len,
                "{max_len}: {:?}",
                code.lengths()
            );
            assert_eq!(kraft(code.lengths()), 1 << 16);
            round_trip(&code, &(0..30).chain((0..30).rev()).collect::<Vec<_>>());
        }
        // 30 symbols cannot fit in 4 bits: the limit is raised to 5.
        let code = HuffmanCode::from_frequencies(&fib, 2);
        assert!(code.lengths().iter().all(|&l| l == 4 || l == 5));
    }

    #[test]
    fn long_codes_take_the_slow_path() {
        // Lengths 1, 2, ..., 15, 16, 16: most codes are longer than the 10-bit table.
        let mut lengths: Vec<u8> = (1..=16).collect();
        lengths.push(16);
        let code = HuffmanCode::from_lengths(&lengths).unwrap();
        assert_eq!(kraft(code.lengths()), 1 << 16);
        let symbols: Vec<usize> = (0..17).chain([16, 12, 0, 11, 10, 9]).collect();
        round_trip(&code, &symbols);
        let dec = HuffmanDecoder::new(&code);
        assert!(dec.table.iter().any(|&e| e & 31 == 0));
    }

    #[test]
    fn from_lengths_validation() {
        assert!(HuffmanCode::from_lengths(&[1, 1, 1]).is_err());
        assert!(HuffmanCode::from_lengths(&[17]).is_err());
        assert!(HuffmanCode::from_lengths(&vec![0; MAX_ALPHABET + 1]).is_err());
        assert!(HuffmanCode::from_lengths(&[0, 5, 0]).is_ok());
        assert!(HuffmanCode::from_lengths(&vec![16; 65536]).is_ok());
        let msg = HuffmanCode::from_lengths(&[1, 1, 1])
            .unwrap_err()
            .to_string();
        assert!(msg.contains("Kraft"), "{msg}");
    }

    #[test]
    fn sparse_header_is_small() {
        let mut freqs = vec![0u64; 256];
        freqs[3] = 50;
        freqs[100] = 20;
        freqs[255] = 1;
        let code = HuffmanCode::from_frequencies(&freqs, 16);
        let mut c = BitCounter::new();
        code.write_lengths(&mut c);
        assert!(c.bytes() <= 8, "{} bits", c.bits());
        round_trip(&code, &[3, 100, 255, 3]);

        let dense = HuffmanCode::from_frequencies(&[5, 3, 2, 2, 1, 1, 1, 1], 16);
        let mut c = BitCounter::new();
        dense.write_lengths(&mut c);
        assert!(c.bytes() <= 6, "{} bits", c.bits());

        let big = HuffmanCode::from_frequencies(&vec![1; MAX_ALPHABET], 16);
        let mut c = BitCounter::new();
        big.write_lengths(&mut c);
        assert!(c.bytes() <= 10, "{} bits", c.bits());
        round_trip(&big, &[0, 65535, 1234]);
    }

    #[test]
    fn read_lengths_rejects_oversized_alphabet() {
        let code = HuffmanCode::from_frequencies(&[1; 40], 16);
        let mut w = BitWriter::new();
        code.write_lengths(&mut w);
        let bytes = w.finish();
        assert!(matches!(
            HuffmanCode::read_lengths(&mut BitReader::new(&bytes), 39),
            Err(EntropyError::ValueOutOfRange { .. })
        ));
        assert!(HuffmanCode::read_lengths(&mut BitReader::new(&bytes), 40).is_ok());
    }

    #[test]
    fn decoders_survive_garbage() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        for _ in 0..300 {
            let len = rng.gen_range(0..40);
            let bytes: Vec<u8> = (0..len).map(|_| rng.gen()).collect();
            let mut r = BitReader::new(&bytes);
            if let Ok(code) = HuffmanCode::read_lengths(&mut r, MAX_ALPHABET) {
                let dec = HuffmanDecoder::new(&code);
                while dec.decode(&mut r).is_ok() {}
            }
        }
    }

    /// Frequencies with a random alphabet size (1..=300), random sparsity and random skew.
    fn freqs_strategy() -> impl Strategy<Value = Vec<u64>> {
        (1usize..300, 0u32..4, any::<u64>()).prop_map(|(n, sparsity, seed)| {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            (0..n)
                .map(|_| {
                    if rng.gen_range(0..4) < sparsity {
                        0
                    } else {
                        let e = rng.gen_range(0..24);
                        rng.gen_range(1..=(1u64 << e))
                    }
                })
                .collect()
        })
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]

        #[test]
        fn random_codes_round_trip(
            freqs in freqs_strategy(), max_len in 1u8..=16, seed in any::<u64>()
        ) {
            let code = HuffmanCode::from_frequencies(&freqs, max_len);
            let used: Vec<usize> = (0..freqs.len()).filter(|&s| freqs[s] > 0).collect();
            prop_assert!(kraft(code.lengths()) <= 1 << 16);
            for s in 0..freqs.len() {
                prop_assert_eq!(code.cost_bits(s) == 0, freqs[s] == 0);
            }
            let limit = max_len.max((usize::BITS - used.len().saturating_sub(1).leading_zeros()) as u8);
            prop_assert!(code.max_length() <= limit.max(1));
            let (optimal, depth) = huffman_cost(&freqs);
            if used.len() > 1 {
                prop_assert!(code.cost_of(&freqs) >= optimal);
                if depth <= max_len as u32 {
                    prop_assert_eq!(code.cost_of(&freqs), optimal);
                }
            }
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let symbols: Vec<usize> = if used.is_empty() {
                vec![]
            } else {
                (0..200).map(|_| used[rng.gen_range(0..used.len())]).collect()
            };
            round_trip(&code, &symbols);
        }

        #[test]
        fn truncated_streams_error_without_panicking(
            freqs in freqs_strategy(), seed in any::<u64>(), cut in 0usize..64
        ) {
            let code = HuffmanCode::from_frequencies(&freqs, 12);
            let used: Vec<usize> = (0..freqs.len()).filter(|&s| freqs[s] > 0).collect();
            prop_assume!(!used.is_empty());
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let symbols: Vec<usize> = (0..50).map(|_| used[rng.gen_range(0..used.len())]).collect();
            let mut w = BitWriter::new();
            code.write_lengths(&mut w);
            let header_bits = w.bits();
            for &s in &symbols {
                code.encode(s, &mut w);
            }
            let total_bits = w.bits();
            let bytes = w.finish();
            let cut_bytes = &bytes[..bytes.len().saturating_sub(cut)];
            let mut r = BitReader::new(cut_bytes);
            match HuffmanCode::read_lengths(&mut r, MAX_ALPHABET) {
                Ok(read) => {
                    prop_assert_eq!(&read, &code);
                    let dec = HuffmanDecoder::new(&read);
                    let mut decoded = 0;
                    while let Ok(s) = dec.decode(&mut r) {
                        if decoded < symbols.len() {
                            prop_assert_eq!(s, symbols[decoded]);
                        }
                        decoded += 1;
                    }
                    if (cut_bytes.len() as u64) * 8 < total_bits {
                        prop_assert!(decoded < symbols.len());
                    }
                }
                Err(_) => prop_assert!((cut_bytes.len() as u64) * 8 < header_bits),
            }
        }

        #[test]
        fn random_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..64)) {
            let mut r = BitReader::new(&bytes);
            if let Ok(code) = HuffmanCode::read_lengths(&mut r, 1000) {
                let dec = HuffmanDecoder::new(&code);
                let mut r2 = r.clone();
                loop {
                    let a = dec.decode(&mut r);
                    let b = dec.decode_canonical(&mut r2);
                    prop_assert_eq!(&a, &b);
                    if a.is_err() { break; }
                }
            }
        }
    }
}
