//! JPEG-style magnitude categories: an integer is sent as a small category symbol (Huffman coded,
//! alphabet of [`NUM_CATEGORIES`]) followed by raw extra bits, so that unbounded values such as
//! positional deltas and coefficient deltas (paper §4.3, Table 3) need only a 65-symbol table.
//!
//! Unsigned: category 0 is the value 0; category `k` ≥ 1 holds `2^(k−1) ..= 2^k − 1` with the
//! `k − 1` bits below the leading one as extra bits. Signed: category `k` holds the magnitudes
//! `2^(k−1) ..= 2^k − 1` with `k` extra bits: `v` itself for `v > 0`, the ones' complement
//! `v + 2^k − 1` for `v < 0` (so the first extra bit is the sign), exactly as in JPEG.

use super::bits::{low_mask, BitReader, BitSink};
use super::huffman::{HuffmanCode, HuffmanDecoder};
use super::EntropyError;

/// Size of the category alphabet (categories `0..=64`), for both signed and unsigned values.
pub const NUM_CATEGORIES: usize = 65;

/// Category of `v` (0..=64), its extra bits and their count (`category − 1`, or 0 for `v = 0`).
#[inline]
pub fn unsigned_category(v: u64) -> (u32, u64, u32) {
    let cat = u64::BITS - v.leading_zeros();
    let nbits = cat.saturating_sub(1);
    (cat, v & low_mask(nbits), nbits)
}

/// Number of extra bits that follow an unsigned category symbol.
#[inline]
pub fn unsigned_extra_bits(cat: u32) -> u32 {
    cat.saturating_sub(1)
}

/// Inverse of [`unsigned_category`]; rejects categories above 64 and extra bits that do not fit.
pub fn unsigned_from_category(cat: u32, extra: u64) -> Result<u64, EntropyError> {
    if cat > 64 {
        return Err(EntropyError::out_of_range("magnitude category", cat, 0, 64));
    }
    let nbits = unsigned_extra_bits(cat);
    if extra > low_mask(nbits) {
        return Err(EntropyError::out_of_range(
            "category extra bits",
            extra,
            0,
            low_mask(nbits),
        ));
    }
    Ok(if cat == 0 { 0 } else { (1u64 << nbits) | extra })
}

/// Category of `v` (0..=64, the bit length of `|v|`), its extra bits and their count
/// (= category).
#[inline]
pub fn signed_category(v: i64) -> (u32, u64, u32) {
    let mag = v.unsigned_abs();
    let cat = u64::BITS - mag.leading_zeros();
    let extra = if v < 0 { !mag & low_mask(cat) } else { mag };
    (cat, extra, cat)
}

/// Number of extra bits that follow a signed category symbol.
#[inline]
pub fn signed_extra_bits(cat: u32) -> u32 {
    cat
}

/// Inverse of [`signed_category`]; rejects categories above 64, extra bits that do not fit, and
/// values outside `i64` (only possible in category 64).
pub fn signed_from_category(cat: u32, extra: u64) -> Result<i64, EntropyError> {
    if cat > 64 {
        return Err(EntropyError::out_of_range("magnitude category", cat, 0, 64));
    }
    if cat == 0 {
        return match extra {
            0 => Ok(0),
            _ => Err(EntropyError::out_of_range(
                "category extra bits",
                extra,
                0,
                0,
            )),
        };
    }
    let mask = low_mask(cat);
    if extra > mask {
        return Err(EntropyError::out_of_range(
            "category extra bits",
            extra,
            0,
            mask,
        ));
    }
    let negative = (extra >> (cat - 1)) & 1 == 0;
    let value = if negative {
        -((mask - extra) as i128)
    } else {
        extra as i128
    };
    i64::try_from(value)
        .map_err(|_| EntropyError::out_of_range("decoded value", value, i64::MIN, i64::MAX))
}

/// Writes `v` as its signed category (Huffman coded with `code`, alphabet ≥ the categories used)
/// followed by the extra bits.
#[inline]
pub fn encode_signed(code: &HuffmanCode, v: i64, sink: &mut impl BitSink) {
    let (cat, extra, n) = signed_category(v);
    code.encode(cat as usize, sink);
    sink.put_bits(extra, n);
}

/// Reads a value written by [`encode_signed`].
#[inline]
pub fn decode_signed(
    decoder: &HuffmanDecoder,
    reader: &mut BitReader,
) -> Result<i64, EntropyError> {
    let cat = category_symbol(decoder.decode(reader)?)?;
    let extra = reader.get_bits(signed_extra_bits(cat))?;
    signed_from_category(cat, extra)
}

/// Writes `v` as its unsigned category (Huffman coded with `code`) followed by the extra bits.
#[inline]
pub fn encode_unsigned(code: &HuffmanCode, v: u64, sink: &mut impl BitSink) {
    let (cat, extra, n) = unsigned_category(v);
    code.encode(cat as usize, sink);
    sink.put_bits(extra, n);
}

/// Reads a value written by [`encode_unsigned`].
#[inline]
pub fn decode_unsigned(
    decoder: &HuffmanDecoder,
    reader: &mut BitReader,
) -> Result<u64, EntropyError> {
    let cat = category_symbol(decoder.decode(reader)?)?;
    let extra = reader.get_bits(unsigned_extra_bits(cat))?;
    unsigned_from_category(cat, extra)
}

/// Bits [`encode_signed`] writes for `v` (category code plus extra bits).
#[inline]
pub fn signed_cost_bits(code: &HuffmanCode, v: i64) -> u32 {
    let (cat, _, n) = signed_category(v);
    code.cost_bits(cat as usize) + n
}

/// Bits [`encode_unsigned`] writes for `v` (category code plus extra bits).
#[inline]
pub fn unsigned_cost_bits(code: &HuffmanCode, v: u64) -> u32 {
    let (cat, _, n) = unsigned_category(v);
    code.cost_bits(cat as usize) + n
}

fn category_symbol(sym: usize) -> Result<u32, EntropyError> {
    if sym >= NUM_CATEGORIES {
        return Err(EntropyError::out_of_range(
            "magnitude category",
            sym as u64,
            0,
            64,
        ));
    }
    Ok(sym as u32)
}

#[cfg(test)]
mod tests {
    use super::super::bits::{BitCounter, BitWriter};
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn jpeg_examples() {
        assert_eq!(signed_category(0), (0, 0, 0));
        assert_eq!(signed_category(1), (1, 1, 1));
        assert_eq!(signed_category(-1), (1, 0, 1));
        assert_eq!(signed_category(-3), (2, 0b00, 2));
        assert_eq!(signed_category(-2), (2, 0b01, 2));
        assert_eq!(signed_category(5), (3, 0b101, 3));
        assert_eq!(signed_category(i64::MIN), (64, (1 << 63) - 1, 64));
        assert_eq!(signed_category(i64::MAX), (63, i64::MAX as u64, 63));
        assert_eq!(unsigned_category(0), (0, 0, 0));
        assert_eq!(unsigned_category(1), (1, 0, 0));
        assert_eq!(unsigned_category(6), (3, 0b10, 2));
        assert_eq!(unsigned_category(u64::MAX), (64, u64::MAX >> 1, 63));
    }

    #[test]
    fn rejects_bad_input() {
        assert!(signed_from_category(65, 0).is_err());
        assert!(signed_from_category(0, 1).is_err());
        assert!(signed_from_category(3, 8).is_err());
        // Category 64, positive: exceeds i64::MAX.
        assert!(signed_from_category(64, 1 << 63).is_err());
        // Category 64, negative beyond i64::MIN.
        assert!(signed_from_category(64, 0).is_err());
        assert_eq!(signed_from_category(64, (1 << 63) - 1), Ok(i64::MIN));
        assert!(unsigned_from_category(65, 0).is_err());
        assert!(unsigned_from_category(0, 1).is_err());
        assert!(unsigned_from_category(3, 4).is_err());
        assert_eq!(unsigned_from_category(64, u64::MAX >> 1), Ok(u64::MAX));
        let msg = signed_from_category(70, 0).unwrap_err().to_string();
        assert_eq!(msg, "magnitude category is 70, allowed range is 0..=64");
    }

    #[test]
    fn huffman_coded_values_round_trip() {
        let values: Vec<i64> = vec![0, 1, -1, 7, -8, 1000, -123_456, i64::MIN, i64::MAX, 3, 3];
        let mut freqs = vec![0u64; NUM_CATEGORIES];
        for &v in &values {
            freqs[signed_category(v).0 as usize] += 1;
            freqs[unsigned_category(v.unsigned_abs()).0 as usize] += 1;
        }
        let code = HuffmanCode::from_frequencies(&freqs, 12);
        let (mut w, mut c) = (BitWriter::new(), BitCounter::new());
        let mut predicted = 0u64;
        for &v in &values {
            encode_signed(&code, v, &mut w);
            encode_unsigned(&code, v.unsigned_abs(), &mut w);
            encode_signed(&code, v, &mut c);
            encode_unsigned(&code, v.unsigned_abs(), &mut c);
            predicted +=
                (signed_cost_bits(&code, v) + unsigned_cost_bits(&code, v.unsigned_abs())) as u64;
        }
        assert_eq!(w.bits(), c.bits());
        assert_eq!(w.bits(), predicted);
        let bytes = w.finish();
        let dec = HuffmanDecoder::new(&code);
        let mut r = BitReader::new(&bytes);
        for &v in &values {
            assert_eq!(decode_signed(&dec, &mut r), Ok(v));
            assert_eq!(decode_unsigned(&dec, &mut r), Ok(v.unsigned_abs()));
        }
    }

    proptest! {
        #[test]
        fn signed_round_trip(v in any::<i64>(), shift in 0u32..64) {
            for v in [v, v >> shift] {
                let (cat, extra, n) = signed_category(v);
                prop_assert!(cat <= 64);
                prop_assert_eq!(n, signed_extra_bits(cat));
                prop_assert!(n == 64 || extra >> n == 0);
                prop_assert_eq!(signed_from_category(cat, extra), Ok(v));
            }
        }

        #[test]
        fn unsigned_round_trip(v in any::<u64>(), shift in 0u32..64) {
            for v in [v, v >> shift] {
                let (cat, extra, n) = unsigned_category(v);
                prop_assert!(cat <= 64);
                prop_assert_eq!(n, unsigned_extra_bits(cat));
                prop_assert!(extra >> n == 0);
                prop_assert_eq!(unsigned_from_category(cat, extra), Ok(v));
            }
        }

        #[test]
        fn arbitrary_pairs_never_panic(cat in 0u32..80, extra in any::<u64>(), n in 0u32..64) {
            let extra = extra >> n;
            if let Ok(v) = signed_from_category(cat, extra) {
                prop_assert_eq!(signed_category(v), (cat, extra, cat));
            }
            if let Ok(v) = unsigned_from_category(cat, extra) {
                prop_assert_eq!(unsigned_category(v), (cat, extra, cat.saturating_sub(1)));
            }
        }
    }
}
