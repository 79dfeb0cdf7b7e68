//! Morton (Z-) order of a region's cells, which both octree coders' encoders sort a
//! substream's points into: in it every dyadic box's points are one run, and a box's children's
//! runs follow in the order the decoders visit them (x fastest). Written here rather than taken
//! from a crate: the order must match the coders' own child order bit for bit, and cells can
//! be wider than a 64-bit key holds (a region of one tile over a long axis).

use std::cmp::Ordering;

/// Bits of each coordinate a `u64` key holds.
pub(crate) const KEY_BITS: u32 = 21;

/// Interleaves the low `log` (≤ [`KEY_BITS`]) bits of a cell's coordinates, x lowest.
pub(crate) fn key(cell: [u32; 3], log: u32) -> u64 {
    debug_assert!(log <= KEY_BITS);
    let low = |c: u32| spread(u64::from(c) & ((1u64 << log) - 1));
    low(cell[0]) | low(cell[1]) << 1 | low(cell[2]) << 2
}

/// The low 21 bits of `x` moved to every third bit (bit i to bit 3i).
fn spread(x: u64) -> u64 {
    let mut x = x & 0x1F_FFFF;
    x = (x | x << 32) & 0x001F_0000_0000_FFFF;
    x = (x | x << 16) & 0x001F_0000_FF00_00FF;
    x = (x | x << 8) & 0x100F_00F0_0F00_F00F;
    x = (x | x << 4) & 0x10C3_0C30_C30C_30C3;
    (x | x << 2) & 0x1249_2492_4924_9249
}

/// Morton order of two cells of any size: the axis whose coordinates differ in the highest
/// bit decides (z before y before x where two differ in the same bit).
pub(crate) fn cmp(a: [u32; 3], b: [u32; 3]) -> Ordering {
    let mut axis = 2;
    let mut top = a[2] ^ b[2];
    for k in [1, 0] {
        let d = a[k] ^ b[k];
        if top < d && top < (top ^ d) {
            axis = k;
            top = d;
        }
    }
    a[axis].cmp(&b[axis])
}

/// Sorts items whose cells lie below 2^`log` on each axis into Morton order: by a `u64` key
/// (computed once per item) where it holds `log` bits per axis (every region a tile or a
/// brick makes), by [`cmp`] beyond that.
pub(crate) fn sort_by_cell<T>(items: &mut [T], log: u32, cell: impl Fn(&T) -> [u32; 3]) {
    if log <= KEY_BITS {
        items.sort_by_cached_key(|t| key(cell(t), log));
    } else {
        items.sort_unstable_by(|a, b| cmp(cell(a), cell(b)));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// The key's order and the comparison's agree wherever the key holds the cells, and the
    /// comparison orders cells beyond it as the key of the same cells shifted down would
    /// (where the shift keeps them apart).
    /// The key against interleaving bit by bit.
    #[test]
    fn key_interleaves_the_bits_x_lowest() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        for log in [0, 1, 4, 9, KEY_BITS] {
            for _ in 0..500 {
                let c = [0; 3].map(|_| rng.gen_range(0..=u32::MAX));
                let mut k = 0u64;
                for bit in (0..log).rev() {
                    for a in (0..3).rev() {
                        k = k << 1 | ((c[a] >> bit) & 1) as u64;
                    }
                }
                assert_eq!(key(c, log), k, "{c:?} log {log}");
            }
        }
    }

    #[test]
    fn key_and_comparison_agree() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        for log in [1, 2, 5, 13, KEY_BITS] {
            for _ in 0..2000 {
                let a = [0; 3].map(|_| rng.gen_range(0..1u32 << log));
                let b = [0; 3].map(|_| rng.gen_range(0..1u32 << log));
                assert_eq!(
                    key(a, log).cmp(&key(b, log)),
                    cmp(a, b),
                    "{a:?} {b:?} log {log}"
                );
            }
        }
        for _ in 0..2000 {
            let a = [0; 3].map(|_| rng.gen_range(0..u32::MAX) & !0x7FF);
            let b = [0; 3].map(|_| rng.gen_range(0..u32::MAX) & !0x7FF);
            let down = |c: [u32; 3]| c.map(|x| x >> 11);
            assert_eq!(
                key(down(a), KEY_BITS).cmp(&key(down(b), KEY_BITS)),
                cmp(a, b)
            );
        }
    }
}
