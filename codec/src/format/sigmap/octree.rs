//! The octree's boxes: a box of a tile's band region, its dyadic children in coding order (lower
//! neighbours first, which the contexts rely on), and the region a tile covers in a band.

use super::super::coefficient::region_extent;
use super::super::Header;

/// A box of the tile-local band grid: [lo, hi) per axis, inside the dyadic cube
/// [lo, lo + scale)³ of the virtual power-of-two octree over the region.
#[derive(Clone, Copy)]
pub(super) struct Box3 {
    pub(super) lo: [u32; 3],
    pub(super) hi: [u32; 3],
    /// Edge of the dyadic cube holding the box (a power of two).
    pub(super) scale: u32,
}

impl Box3 {
    /// The root box of a region of `extent` cells: the dyadic cube is the next power of two of
    /// the longest axis, so every box below it is aligned to the region's origin and cells
    /// beyond the region are never coded.
    pub(super) fn root(extent: [u32; 3]) -> Box3 {
        let longest = extent.iter().copied().max().unwrap_or(0).max(1);
        Box3 {
            lo: [0; 3],
            hi: extent,
            scale: longest.next_power_of_two(),
        }
    }
    #[inline]
    pub(super) fn cells(&self) -> usize {
        (self.hi[0] - self.lo[0]) as usize
            * (self.hi[1] - self.lo[1]) as usize
            * (self.hi[2] - self.lo[2]) as usize
    }
    /// The up to 8 children of the dyadic cube (halved on each axis that reaches past its
    /// middle; children wholly outside the region do not exist), in x-fastest order, without
    /// allocating. Halves the scale until some axis splits, so a box of several cells always
    /// has at least two children. Children come in Morton order: a cell's lower neighbours
    /// (−1 along any axis) are always visited before it.
    #[inline(always)]
    pub(super) fn children(&self) -> ([Box3; 8], usize) {
        let mut splits = [[(0u32, 0u32); 2]; 3];
        let mut counts = [1usize; 3];
        let mut half = self.scale / 2;
        while half > 0 && (0..3).all(|a| self.hi[a] - self.lo[a] <= half) {
            half /= 2;
        }
        for a in 0..3 {
            let (lo, hi) = (self.lo[a], self.hi[a]);
            if half > 0 && hi - lo > half {
                let mid = lo + half;
                splits[a] = [(lo, mid), (mid, hi)];
                counts[a] = 2;
            } else {
                splits[a][0] = (lo, hi);
            }
        }
        let mut out = [*self; 8];
        let mut n = 0;
        for z in &splits[2][..counts[2]] {
            for y in &splits[1][..counts[1]] {
                for x in &splits[0][..counts[0]] {
                    out[n] = Box3 {
                        lo: [x.0, y.0, z.0],
                        hi: [x.1, y.1, z.1],
                        scale: half.max(1),
                    };
                    n += 1;
                }
            }
        }
        (out, n)
    }
    pub(super) fn contains(&self, p: [u32; 3]) -> bool {
        (0..3).all(|a| p[a] >= self.lo[a] && p[a] < self.hi[a])
    }
}

pub(super) fn region(
    header: &Header,
    tile: usize,
    level: u8,
    band_dims: [usize; 3],
) -> ([u32; 3], Box3) {
    let (origin, extent) = region_extent(header, tile, level, band_dims);
    (origin, Box3::root(extent))
}
