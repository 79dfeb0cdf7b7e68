//! Adaptive binary range coder (the arithmetic-coding option of the paper's future work, §6),
//! offered beside Huffman coding.
//!
//! The coder is the LZMA-style carry-less-output range coder: a 32-bit range, a 33-bit `low`
//! with deferred carry propagation, 12-bit probabilities in [`BitModel`] adapted by a shift (faster
//! for a model's first few dozen bits, so fresh per-packet models learn quickly), and
//! bypass bits at probability ½. Two refinements keep tiny streams tiny: LZMA's always-zero first
//! byte is not written, and [`RangeEncoder::finish`] picks the final value with the most
//! trailing zero bits and drops trailing zero bytes, which [`RangeDecoder`] reads back as zeros
//! past the end of its input. [`RangeEncoder::size_bytes`] is the exact length `finish` would
//! return, for rate control.
//!
//! On top of the binary coder, [`AdaptiveUintModel`] codes `u64` values with an adaptive
//! exp-Golomb binarization and [`AdaptiveSintModel`] codes `i64` values as zero flag, sign and
//! magnitude. Decoding garbage never panics and never loops: it yields arbitrary values or
//! [`EntropyError::ValueOutOfRange`].

use super::EntropyError;

/// Precision of [`BitModel`] probabilities in bits.
pub const PROB_BITS: u32 = 12;
const PROB_ONE: u32 = 1 << PROB_BITS;
/// The range is renormalized (one byte shifted out) whenever it drops below this.
const TOP: u32 = 1 << 24;

/// Adaptive probability of a binary event.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BitModel {
    /// Probability that the bit is 0, in units of 2^−12; always in `1..4096`.
    p0: u16,
    /// Adaptation rate: each coded bit moves `p0` by 1/2^shift of the distance to the target.
    shift: u8,
    /// Bits coded so far (saturating); while few, the model adapts faster than `shift`.
    seen: u8,
}

impl Default for BitModel {
    fn default() -> Self {
        Self::new()
    }
}

impl BitModel {
    /// Adaptation shift used by [`BitModel::new`]: fast enough for small streams, fine enough
    /// for skewed ones.
    pub const DEFAULT_SHIFT: u8 = 5;

    /// A model at probability ½ with [`BitModel::DEFAULT_SHIFT`].
    pub const fn new() -> Self {
        Self::with_shift(Self::DEFAULT_SHIFT)
    }

    /// A model at probability ½ adapting with the given shift, clamped to `1..=10` (4 adapts
    /// faster, 7 is more stable).
    pub const fn with_shift(shift: u8) -> Self {
        let shift = if shift < 1 {
            1
        } else if shift > 10 {
            10
        } else {
            shift
        };
        BitModel {
            p0: (PROB_ONE / 2) as u16,
            shift,
            seen: 0,
        }
    }

    /// A model starting at probability `p0` (that the bit is 0, in units of 2^−12, clamped to
    /// `1..4096`) as if it had already seen `seen` bits: its warm-up goes on from there, so a
    /// prior trained elsewhere is trusted about as much as that many bits of this stream.
    pub const fn primed(p0: u16, seen: u8) -> Self {
        let p0 = if p0 < 1 {
            1
        } else if p0 >= PROB_ONE as u16 {
            PROB_ONE as u16 - 1
        } else {
            p0
        };
        BitModel {
            p0,
            shift: Self::DEFAULT_SHIFT,
            seen,
        }
    }

    /// The probability that the next bit is 0 in units of 2^−12, and the bits seen so far
    /// (saturating at 255).
    pub fn state(&self) -> (u16, u8) {
        (self.p0, self.seen)
    }

    /// Current probability that the next bit is 0.
    pub fn p0(&self) -> f64 {
        self.p0 as f64 / PROB_ONE as f64
    }

    /// Estimated cost in bits of coding `bit` with the current probability.
    pub fn cost_bits(&self, bit: bool) -> f64 {
        let p = if bit {
            PROB_ONE - self.p0 as u32
        } else {
            self.p0 as u32
        };
        PROB_BITS as f64 - (p as f64).log2()
    }

    #[inline]
    fn update(&mut self, bit: bool) {
        // Warm-up: after n bits the step is 1/2^⌊log2(n+2)⌋ (capped at the model's shift), close
        // to a counting estimate, so that a fresh model (every packet starts fresh) learns its
        // probability in a few bits instead of ~2^shift.
        let warm = WARM_SHIFT[self.seen as usize];
        self.seen = self.seen.saturating_add(1);
        let shift = warm.min(self.shift);
        // Both moves computed, one kept: the decoded bit is as unpredictable as the data, so a
        // select is cheaper than a branch.
        let p0 = self.p0 as u32;
        let down = p0 - (p0 >> shift);
        let up = p0 + ((PROB_ONE - p0) >> shift);
        self.p0 = if bit { down } else { up } as u16;
    }
}

/// ⌊log2(n + 2)⌋ for every count n a [`BitModel`] holds: its warm-up shift after n bits.
static WARM_SHIFT: [u8; 256] = {
    let mut t = [0u8; 256];
    let mut n = 0;
    while n < 256 {
        t[n] = (31 - (n as u32 + 2).leading_zeros()) as u8;
        n += 1;
    }
    t
};

/// log2(1 + i/256) for i in 0..=256, for [`log2_of_range`]. Computed at compile time by the
/// series ln(x) = 2·atanh((x − 1)/(x + 1)), whose argument stays below 1/3 here (30 terms are
/// exact to f64).
static LOG2_MANTISSA: [f32; 257] = {
    let mut t = [0f32; 257];
    let mut i = 0;
    while i <= 256 {
        let x = 1.0 + i as f64 / 256.0;
        let s = (x - 1.0) / (x + 1.0);
        let (mut term, mut sum, mut k) = (s, 0.0, 1.0);
        while k < 60.0 {
            sum += term / k;
            term *= s * s;
            k += 2.0;
        }
        t[i] = (2.0 * sum / std::f64::consts::LN_2) as f32;
        i += 1;
    }
    t
};

/// log2 of a range (≥ 1), within 5·10⁻⁶ bits (interpolation and f32 rounding): the exponent from the leading zeros, the
/// mantissa's logarithm interpolated in [`LOG2_MANTISSA`]. [`RangeEncoder::bits_spent`] is
/// read around every symbol of a size breakdown, and libm's `log2f` took 5 % of a rate
/// search's time there.
#[inline]
fn log2_of_range(range: u32) -> f32 {
    let range = range.max(1);
    let e = 31 - range.leading_zeros();
    let n = range << (31 - e);
    let i = (n >> 23 & 0xFF) as usize;
    let frac = (n & 0x7F_FFFF) as f32 * (1.0 / (1u32 << 23) as f32);
    let (a, b) = (LOG2_MANTISSA[i], LOG2_MANTISSA[i + 1]);
    e as f32 + a + (b - a) * frac
}

/// Destination of the encoder's bytes: a buffer, or a counter for size queries.
trait ByteOut {
    fn push(&mut self, byte: u8);
}

/// Output buffer that knows how many of its last bytes are zero.
#[derive(Debug, Clone, Default)]
struct Bytes {
    bytes: Vec<u8>,
    trailing_zeros: usize,
}

impl ByteOut for Bytes {
    #[inline]
    fn push(&mut self, byte: u8) {
        self.bytes.push(byte);
        self.trailing_zeros = if byte == 0 {
            self.trailing_zeros + 1
        } else {
            0
        };
    }
}

/// Counts bytes (and trailing zero bytes) without storing them.
struct Count {
    len: usize,
    trailing_zeros: usize,
}

impl ByteOut for Count {
    fn push(&mut self, byte: u8) {
        self.len += 1;
        self.trailing_zeros = if byte == 0 {
            self.trailing_zeros + 1
        } else {
            0
        };
    }
}

/// The arithmetic state of the encoder (everything except the bytes already written).
#[derive(Debug, Clone)]
struct EncState {
    low: u64,
    range: u32,
    /// Byte waiting for a possible carry.
    cache: u8,
    /// 1 + number of 0xFF bytes pending behind `cache`.
    cache_size: u64,
    /// LZMA's first output byte is always 0 and is not written.
    skip_first: bool,
}

impl EncState {
    #[inline]
    fn shift_low(&mut self, out: &mut impl ByteOut) {
        if (self.low as u32) < 0xFF00_0000 || (self.low >> 32) != 0 {
            let carry = (self.low >> 32) as u8;
            let mut byte = self.cache;
            loop {
                if self.skip_first {
                    debug_assert_eq!(byte.wrapping_add(carry), 0);
                    self.skip_first = false;
                } else {
                    out.push(byte.wrapping_add(carry));
                }
                byte = 0xFF;
                self.cache_size -= 1;
                if self.cache_size == 0 {
                    break;
                }
            }
            self.cache = (self.low >> 24) as u8;
        }
        self.cache_size += 1;
        self.low = (self.low & 0x00FF_FFFF) << 8;
    }

    #[inline]
    fn normalize(&mut self, out: &mut impl ByteOut) {
        while self.range < TOP {
            self.range <<= 8;
            self.shift_low(out);
        }
    }

    /// Settles on the value in `[low, low + range)` with the most trailing zero bits and writes
    /// out everything.
    fn flush(&mut self, out: &mut impl ByteOut) {
        let last = self.low + self.range as u64 - 1;
        for k in (0..=32).rev() {
            let mask = (1u64 << k) - 1;
            let v = (self.low + mask) & !mask;
            if v <= last {
                self.low = v;
                break;
            }
        }
        for _ in 0..5 {
            self.shift_low(out);
        }
    }
}

/// Adaptive binary range encoder writing into a `Vec<u8>`.
#[derive(Debug, Clone)]
pub struct RangeEncoder {
    state: EncState,
    out: Bytes,
}

impl Default for RangeEncoder {
    fn default() -> Self {
        Self::new()
    }
}

impl RangeEncoder {
    /// An encoder with nothing coded yet.
    pub fn new() -> Self {
        RangeEncoder {
            state: EncState {
                low: 0,
                range: u32::MAX,
                cache: 0,
                cache_size: 1,
                skip_first: true,
            },
            out: Bytes::default(),
        }
    }

    /// Codes `bit` with the adaptive probability `model`, then updates the model.
    #[inline]
    pub fn encode_bit(&mut self, model: &mut BitModel, bit: bool) {
        let st = &mut self.state;
        let bound = (st.range >> PROB_BITS) * model.p0 as u32;
        if bit {
            st.low += bound as u64;
            st.range -= bound;
        } else {
            st.range = bound;
        }
        model.update(bit);
        st.normalize(&mut self.out);
    }

    /// Codes the low `n` bits of `value` (`n` ≤ 64, most significant first) at probability ½.
    pub fn encode_bypass(&mut self, value: u64, n: u32) {
        debug_assert!(n <= 64, "encode_bypass: n = {n} > 64");
        let st = &mut self.state;
        for i in (0..n.min(64)).rev() {
            st.range >>= 1;
            if (value >> i) & 1 != 0 {
                st.low += st.range as u64;
            }
            st.normalize(&mut self.out);
        }
    }

    /// Information spent so far in bits, fractional: 8 per byte out or waiting for a carry,
    /// minus log2 of the range left (up to a constant). Differences measure what the symbols
    /// between two calls cost, cheaply enough to call per symbol (size breakdowns); use
    /// [`RangeEncoder::size_bytes`] for the exact length. The encoder's first byte (always 0,
    /// never written) is not counted, so that the symbol whose normalization drops it is not
    /// charged 8 bits less than it costs (a tiny stream's breakdown showed −1 byte of values).
    #[inline]
    pub fn bits_spent(&self) -> f64 {
        let st = &self.state;
        let bytes = self.out.bytes.len() as u64 + st.cache_size - u64::from(st.skip_first);
        8.0 * bytes as f64 - log2_of_range(st.range) as f64
    }

    /// Exact number of bytes [`RangeEncoder::finish`] would return if called now.
    pub fn size_bytes(&self) -> usize {
        let mut count = Count {
            len: self.out.bytes.len(),
            trailing_zeros: self.out.trailing_zeros,
        };
        self.state.clone().flush(&mut count);
        count.len - count.trailing_zeros.min(MAX_TRIMMED_ZEROS)
    }

    /// Terminates the stream and returns its bytes.
    pub fn finish(mut self) -> Vec<u8> {
        self.state.flush(&mut self.out);
        let mut bytes = self.out.bytes;
        bytes.truncate(bytes.len() - self.out.trailing_zeros.min(MAX_TRIMMED_ZEROS));
        bytes
    }
}

/// Most trailing zero bytes [`RangeEncoder::finish`] drops (the decoder reads them back as the
/// zeros past the end). Bounded so that a decoder knows how far past the end a valid stream
/// can read: [`RangeDecoder::overrun`].
pub const MAX_TRIMMED_ZEROS: usize = 64;

/// Adaptive binary range decoder over a byte slice. Bytes past the end read as zero, so it
/// never fails; corrupt input just decodes to arbitrary bits.
#[derive(Debug, Clone)]
pub struct RangeDecoder<'a> {
    data: &'a [u8],
    pos: usize,
    range: u32,
    code: u32,
}

impl<'a> RangeDecoder<'a> {
    /// A decoder positioned at the start of a stream written by [`RangeEncoder`].
    pub fn new(data: &'a [u8]) -> Self {
        let mut dec = RangeDecoder {
            data,
            pos: 0,
            range: u32::MAX,
            code: 0,
        };
        for _ in 0..4 {
            dec.code = (dec.code << 8) | dec.next_byte() as u32;
        }
        dec
    }

    #[inline]
    fn next_byte(&mut self) -> u8 {
        let byte = self.data.get(self.pos).copied().unwrap_or(0);
        self.pos = self.pos.saturating_add(1);
        byte
    }

    #[inline]
    fn normalize(&mut self) {
        while self.range < TOP {
            self.range <<= 8;
            self.code = (self.code << 8) | self.next_byte() as u32;
        }
    }

    /// Number of input bytes read so far, including up to 4 bytes of look-ahead; may exceed
    /// the input length, since the encoder drops trailing zero bytes.
    pub fn bytes_read(&self) -> usize {
        self.pos
    }

    /// Whether the decoder has read further past the end than any stream [`RangeEncoder`]
    /// wrote can need (its 4 bytes of look-ahead and the trailing zeros it drops): what it
    /// decodes from here on is not in the data. Decoders check this to stop a hostile payload
    /// from driving them on for free.
    pub fn overrun(&self) -> bool {
        self.pos > self.data.len() + 4 + MAX_TRIMMED_ZEROS
    }

    /// Decodes a bit coded with [`RangeEncoder::encode_bit`] and the same model state.
    #[inline]
    pub fn decode_bit(&mut self, model: &mut BitModel) -> bool {
        let bound = (self.range >> PROB_BITS) * model.p0 as u32;
        // Branch-free: the bit is as unpredictable as the data.
        let bit = self.code >= bound;
        // By masks rather than selects, which the compiler turned into a branch here.
        let mask = 0u32.wrapping_sub(bit as u32);
        self.code -= bound & mask;
        self.range = (bound & !mask) | ((self.range - bound) & mask);
        model.update(bit);
        self.normalize();
        bit
    }

    /// Decodes `n` bypass bits (`n` is clamped to 64) coded with [`RangeEncoder::encode_bypass`].
    pub fn decode_bypass(&mut self, n: u32) -> u64 {
        let mut value = 0u64;
        for _ in 0..n.min(64) {
            self.range >>= 1;
            let bit = self.code >= self.range;
            if bit {
                self.code -= self.range;
            }
            value = (value << 1) | bit as u64;
            self.normalize();
        }
        value
    }
}

/// Suffix bits (below the leading one) of the exp-Golomb code that are context modeled; the
/// rest are bypass coded.
const MODELED_SUFFIX_BITS: u32 = 2;

/// Adaptive exp-Golomb coder for `u64`: `v + 1` is sent as its bit length `k + 1` in unary
/// (one adaptive model per prefix position, no terminator after 64 ones), then its `k` bits
/// below the leading one: the first two through a per-`k` binary context tree, the rest as
/// bypass bits.
#[derive(Debug, Clone)]
pub struct AdaptiveUintModel {
    prefix: [BitModel; 64],
    suffix: [[BitModel; 3]; 65],
}

impl Default for AdaptiveUintModel {
    fn default() -> Self {
        Self::new()
    }
}

impl AdaptiveUintModel {
    /// Fresh models with [`BitModel::DEFAULT_SHIFT`].
    pub fn new() -> Self {
        Self::with_shift(BitModel::DEFAULT_SHIFT)
    }

    /// Fresh models with the given adaptation shift (see [`BitModel::with_shift`]).
    pub fn with_shift(shift: u8) -> Self {
        let m = BitModel::with_shift(shift);
        AdaptiveUintModel {
            prefix: [m; 64],
            suffix: [[m; 3]; 65],
        }
    }

    /// Its binary models, [`AdaptiveUintModel::MODELS`] of them, in a fixed order: the
    /// prefix's, then each bit length's suffix tree.
    pub fn models_mut(&mut self) -> impl Iterator<Item = &mut BitModel> {
        self.prefix
            .iter_mut()
            .chain(self.suffix.iter_mut().flatten())
    }

    /// How many binary models an [`AdaptiveUintModel`] holds.
    pub const MODELS: usize = 64 + 65 * 3;

    /// Codes `v`.
    pub fn encode(&mut self, enc: &mut RangeEncoder, v: u64) {
        let x = v as u128 + 1;
        let k = 127 - x.leading_zeros();
        for i in 0..k as usize {
            enc.encode_bit(&mut self.prefix[i], true);
        }
        if k < 64 {
            enc.encode_bit(&mut self.prefix[k as usize], false);
        }
        let modeled = k.min(MODELED_SUFFIX_BITS);
        let mut ctx = 1usize;
        for j in 0..modeled {
            let bit = (x >> (k - 1 - j)) & 1 != 0;
            enc.encode_bit(&mut self.suffix[k as usize][ctx - 1], bit);
            ctx = 2 * ctx + bit as usize;
        }
        let rest = k - modeled;
        enc.encode_bypass(x as u64, rest);
    }

    /// Decodes a value coded by [`AdaptiveUintModel::encode`] with the same model state.
    /// Garbage input can only fail as [`EntropyError::ValueOutOfRange`] (a 64-bit prefix with
    /// a nonzero suffix, i.e. a value above `u64::MAX`).
    pub fn decode(&mut self, dec: &mut RangeDecoder) -> Result<u64, EntropyError> {
        let mut k = 0u32;
        while k < 64 && dec.decode_bit(&mut self.prefix[k as usize]) {
            k += 1;
        }
        let modeled = k.min(MODELED_SUFFIX_BITS);
        let mut ctx = 1usize;
        for _ in 0..modeled {
            let bit = dec.decode_bit(&mut self.suffix[k as usize][ctx - 1]);
            ctx = 2 * ctx + bit as usize;
        }
        let rest = k - modeled;
        if k < 64 {
            // x < 2^(k+1) fits a u64 (and is at least 1).
            return Ok((((ctx as u64) << rest) | dec.decode_bypass(rest)) - 1);
        }
        let x = ((ctx as u128) << rest) | dec.decode_bypass(rest) as u128;
        u64::try_from(x - 1).map_err(|_| {
            EntropyError::out_of_range("decoded integer", (x - 1) as i128, 0, u64::MAX)
        })
    }
}

/// Adaptive coder for `i64`: an adaptive zero flag, an adaptive sign bit, and `|v| − 1` through
/// an [`AdaptiveUintModel`].
#[derive(Debug, Clone, Default)]
pub struct AdaptiveSintModel {
    nonzero: BitModel,
    negative: BitModel,
    magnitude: AdaptiveUintModel,
}

impl AdaptiveSintModel {
    /// Fresh models with [`BitModel::DEFAULT_SHIFT`].
    pub fn new() -> Self {
        Self::default()
    }

    /// Fresh models with the given adaptation shift (see [`BitModel::with_shift`]).
    pub fn with_shift(shift: u8) -> Self {
        AdaptiveSintModel {
            nonzero: BitModel::with_shift(shift),
            negative: BitModel::with_shift(shift),
            magnitude: AdaptiveUintModel::with_shift(shift),
        }
    }

    /// Codes `v`.
    pub fn encode(&mut self, enc: &mut RangeEncoder, v: i64) {
        enc.encode_bit(&mut self.nonzero, v != 0);
        if v != 0 {
            enc.encode_bit(&mut self.negative, v < 0);
            self.magnitude.encode(enc, v.unsigned_abs() - 1);
        }
    }

    /// Decodes a value coded by [`AdaptiveSintModel::encode`] with the same model state;
    /// magnitudes outside `i64` give [`EntropyError::ValueOutOfRange`].
    pub fn decode(&mut self, dec: &mut RangeDecoder) -> Result<i64, EntropyError> {
        if !dec.decode_bit(&mut self.nonzero) {
            return Ok(0);
        }
        let negative = dec.decode_bit(&mut self.negative);
        let magnitude = self.magnitude.decode(dec)? as i128 + 1;
        let value = if negative { -magnitude } else { magnitude };
        i64::try_from(value)
            .map_err(|_| EntropyError::out_of_range("decoded integer", value, i64::MIN, i64::MAX))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn fresh_models_learn_a_skewed_bit_within_a_few_dozen_bits() {
        // A plain 1/32 step would leave p0 at 1 − ½·(31/32)^20 ≈ 0.73 after 20 zeros.
        let mut m = BitModel::new();
        for _ in 0..20 {
            m.update(false);
        }
        assert!(m.p0() > 0.9, "p0 = {}", m.p0());
        // Later the step settles at the model's shift, so the estimate stays stable.
        let mut m = BitModel::new();
        for _ in 0..1000 {
            m.update(false);
        }
        let before = m.p0();
        m.update(true);
        assert!(before - m.p0() <= before / 32.0 + 1e-9);
        // Probabilities stay strictly inside (0, 1) under any sequence.
        for bit in [false, true] {
            let mut m = BitModel::with_shift(1);
            for _ in 0..100 {
                m.update(bit);
                assert!(m.p0() > 0.0 && m.p0() < 1.0);
            }
        }
    }

    fn entropy_bits(p1: f64, n: usize) -> f64 {
        let h = -(p1 * p1.log2() + (1.0 - p1) * (1.0 - p1).log2());
        h * n as f64
    }

    fn bits_round_trip(p1: f64, n: usize, seed: u64) -> usize {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let bits: Vec<bool> = (0..n).map(|_| rng.gen_bool(p1)).collect();
        let mut enc = RangeEncoder::new();
        let mut model = BitModel::new();
        for (i, &b) in bits.iter().enumerate() {
            if i % 97 == 0 {
                let size = enc.size_bytes();
                assert_eq!(size, enc.clone().finish().len());
            }
            enc.encode_bit(&mut model, b);
        }
        let size = enc.size_bytes();
        let bytes = enc.finish();
        assert_eq!(size, bytes.len());
        let mut dec = RangeDecoder::new(&bytes);
        let mut model = BitModel::new();
        for &b in &bits {
            assert_eq!(dec.decode_bit(&mut model), b);
        }
        bytes.len()
    }

    #[test]
    fn skewed_and_uniform_bits_round_trip_near_entropy() {
        for (p1, slack) in [
            (0.5, 1.03),
            (0.1, 1.08),
            (0.02, 1.25),
            (0.0, 1.0),
            (1.0, 1.0),
        ] {
            let n = 20_000;
            let len = bits_round_trip(p1, n, 1);
            let bound = entropy_bits(p1, n).max(0.0) * slack / 8.0 + 40.0;
            assert!(len as f64 <= bound, "p1 = {p1}: {len} bytes > {bound}");
        }
        for n in 0..20 {
            bits_round_trip(0.3, n, n as u64);
        }
    }

    #[test]
    fn empty_and_tiny_streams() {
        assert!(RangeEncoder::new().finish().is_empty());
        assert_eq!(RangeEncoder::new().size_bytes(), 0);
        let mut enc = RangeEncoder::new();
        let mut m = BitModel::new();
        enc.encode_bit(&mut m, false);
        assert!(enc.finish().len() <= 1);
        let mut enc = RangeEncoder::new();
        AdaptiveUintModel::new().encode(&mut enc, 0);
        AdaptiveSintModel::new().encode(&mut enc, 0);
        assert!(enc.finish().len() <= 1);
    }

    #[test]
    fn bypass_and_mixed_round_trip() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let ops: Vec<(u64, u32, bool)> = (0..2000)
            .map(|_| (rng.gen(), rng.gen_range(0..=64), rng.gen_bool(0.2)))
            .collect();
        let mut enc = RangeEncoder::new();
        let mut models = [BitModel::new(), BitModel::with_shift(4)];
        for &(v, n, b) in &ops {
            enc.encode_bypass(v, n);
            enc.encode_bit(&mut models[n as usize % 2], b);
        }
        let bytes = enc.finish();
        let mut dec = RangeDecoder::new(&bytes);
        let mut models = [BitModel::new(), BitModel::with_shift(4)];
        for &(v, n, b) in &ops {
            let mask = if n == 64 { u64::MAX } else { (1 << n) - 1 };
            assert_eq!(dec.decode_bypass(n), v & mask);
            assert_eq!(dec.decode_bit(&mut models[n as usize % 2]), b);
        }
    }

    #[test]
    fn integers_round_trip_including_extremes() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let mut uints: Vec<u64> = vec![0, 1, 2, 3, u64::MAX, u64::MAX - 1, 1 << 63, (1 << 63) - 1];
        let mut sints: Vec<i64> = vec![0, 1, -1, i64::MIN, i64::MAX, i64::MIN + 1, -2, 2];
        for _ in 0..3000 {
            let shift = rng.gen_range(0..64);
            uints.push(rng.gen::<u64>() >> shift);
            sints.push(rng.gen::<i64>() >> shift);
        }
        let mut enc = RangeEncoder::new();
        let (mut um, mut sm) = (AdaptiveUintModel::new(), AdaptiveSintModel::with_shift(4));
        for (&u, &s) in uints.iter().zip(&sints) {
            um.encode(&mut enc, u);
            sm.encode(&mut enc, s);
        }
        let size = enc.size_bytes();
        let bytes = enc.finish();
        assert_eq!(size, bytes.len());
        let mut dec = RangeDecoder::new(&bytes);
        let (mut um, mut sm) = (AdaptiveUintModel::new(), AdaptiveSintModel::with_shift(4));
        for (&u, &s) in uints.iter().zip(&sints) {
            assert_eq!(um.decode(&mut dec), Ok(u));
            assert_eq!(sm.decode(&mut dec), Ok(s));
        }
    }

    #[test]
    fn small_integers_compress() {
        // Geometric-ish small values: well under the 8 bits a byte per value would cost.
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let values: Vec<u64> = (0..10_000)
            .map(|_| rng.gen_range(0..4u64).pow(2) / 3)
            .collect();
        let mut enc = RangeEncoder::new();
        let mut m = AdaptiveUintModel::new();
        values.iter().for_each(|&v| m.encode(&mut enc, v));
        let bytes = enc.finish();
        assert!(bytes.len() < 10_000 * 2 / 8, "{} bytes", bytes.len());
        let mut dec = RangeDecoder::new(&bytes);
        let mut m = AdaptiveUintModel::new();
        assert!(values.iter().all(|&v| m.decode(&mut dec) == Ok(v)));
    }

    /// The table's logarithm against f64's: every power of two, its neighbours, and a sweep
    /// of ranges from 1 to u32::MAX.
    #[test]
    fn range_logarithm_matches_f64_within_its_bound() {
        let mut worst = 0f64;
        let mut check = |r: u32| {
            let exact = (r as f64).log2();
            let err = (log2_of_range(r) as f64 - exact).abs();
            worst = worst.max(err);
            assert!(
                err < 5e-6,
                "log2({r}) = {} against {exact}",
                log2_of_range(r)
            );
        };
        for e in 0..32 {
            let p = 1u32 << e;
            check(p);
            check(p.saturating_add(1));
            check(p.saturating_sub(1).max(1));
        }
        let mut r = 1u64;
        while r <= u32::MAX as u64 {
            check(r as u32);
            r = r * 1_000_003 / 1_000_000 + 1;
        }
        check(u32::MAX);
        assert!(worst > 0.0);
    }

    #[test]
    fn cost_estimate_is_sane() {
        let mut m = BitModel::new();
        assert!((m.cost_bits(true) - 1.0).abs() < 1e-9);
        let mut enc = RangeEncoder::new();
        for _ in 0..100 {
            enc.encode_bit(&mut m, false);
        }
        assert!(m.p0() > 0.9);
        assert!(m.cost_bits(false) < 0.2 && m.cost_bits(true) > 3.0);
    }

    /// Every symbol's share of `bits_spent` is its cost: never negative (up to the f32
    /// logarithm's rounding), the first byte's normalization included, and the shares add up
    /// to the stream's length within the final flush's bytes (its last byte is partly spent).
    #[test]
    fn bits_spent_charges_every_symbol_what_it_costs() {
        let mut rng = 0x9e37_79b9_7f4a_7c15u64;
        for stream in 0..40 {
            let mut enc = RangeEncoder::new();
            let mut model = BitModel::new();
            let mut uint = AdaptiveUintModel::new();
            let start = enc.bits_spent();
            let mut least = f64::INFINITY;
            for i in 0..(stream * 7 + 3) {
                rng ^= rng << 13;
                rng ^= rng >> 7;
                rng ^= rng << 17;
                let before = enc.bits_spent();
                match i % 3 {
                    0 => enc.encode_bit(&mut model, rng.is_multiple_of(5)),
                    1 => enc.encode_bypass(rng >> 40, (rng % 9) as u32),
                    _ => uint.encode(&mut enc, (rng >> 50) % 300),
                }
                least = least.min(enc.bits_spent() - before);
            }
            assert!(least > -1e-3, "stream {stream}: a symbol cost {least} bits");
            let spent = (enc.bits_spent() - start) / 8.0;
            let size = enc.size_bytes() as f64;
            assert!(
                spent <= size + 1.0,
                "stream {stream}: {spent} bytes spent, {size} out"
            );
            assert!(
                spent >= size - 5.0,
                "stream {stream}: {spent} bytes spent, {size} out"
            );
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]

        #[test]
        fn uint_streams_round_trip(values in proptest::collection::vec(any::<u64>(), 0..50),
                                   shifts in proptest::collection::vec(0u32..64, 50)) {
            let values: Vec<u64> = values.iter().zip(&shifts).map(|(&v, &s)| v >> s).collect();
            let mut enc = RangeEncoder::new();
            let mut m = AdaptiveUintModel::new();
            for &v in &values {
                m.encode(&mut enc, v);
            }
            let size = enc.size_bytes();
            let bytes = enc.finish();
            prop_assert_eq!(size, bytes.len());
            let mut dec = RangeDecoder::new(&bytes);
            let mut m = AdaptiveUintModel::new();
            for &v in &values {
                prop_assert_eq!(m.decode(&mut dec), Ok(v));
            }
        }

        #[test]
        fn garbage_never_panics(bytes in proptest::collection::vec(any::<u8>(), 0..64)) {
            let mut dec = RangeDecoder::new(&bytes);
            let (mut um, mut sm, mut bm) =
                (AdaptiveUintModel::new(), AdaptiveSintModel::new(), BitModel::new());
            for _ in 0..50 {
                let _ = um.decode(&mut dec);
                let _ = sm.decode(&mut dec);
                dec.decode_bit(&mut bm);
                dec.decode_bypass(64);
            }
        }

        #[test]
        fn truncated_streams_never_panic(values in proptest::collection::vec(any::<i64>(), 1..30),
                                         cut in 1usize..16) {
            let mut enc = RangeEncoder::new();
            let mut m = AdaptiveSintModel::new();
            values.iter().for_each(|&v| m.encode(&mut enc, v));
            let bytes = enc.finish();
            let mut dec = RangeDecoder::new(&bytes[..bytes.len().saturating_sub(cut)]);
            let mut m = AdaptiveSintModel::new();
            for _ in 0..values.len() {
                let _ = m.decode(&mut dec);
            }
        }
    }
}
