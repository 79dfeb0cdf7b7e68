//! Which cells of earlier bands hold a coefficient: a significance grid per band region (dense,
//! or sparse beyond a size) and the pyramid of its coarser levels, so a box asks in one lookup
//! whether any cell under it is significant.

/// Most cells a [`SignificanceGrid`] holds (~5 MB): larger bounding boxes are coarsened.
pub(super) const MAX_GRID_CELLS: usize = 1 << 20;

/// Which cells of one band's tile-local region hold a coefficient of this packet, as a 3D
/// prefix sum so that any box is counted in O(1). Its memory is bounded whatever a (possibly
/// hostile) packet holds: when the cells' bounding box exceeds [`MAX_GRID_CELLS`], the grid
/// records 2^shift-cell blocks instead, and a box query answers for the blocks it touches
/// (encoder and decoder build the same grid, so the contexts still agree).
pub(super) struct SignificanceGrid {
    /// Grid size in (possibly coarsened) cells.
    pub(super) dims: [usize; 3],
    /// Bounding box of the cells, in band coordinates.
    pub(super) origin: [u32; 3],
    pub(super) extent: [u64; 3],
    /// Coarsening: a grid cell covers 2^shift band cells per axis.
    pub(super) shift: u32,
    /// The cells themselves (x fastest), for the frequent one-cell queries.
    pub(super) cells: Vec<bool>,
    pub(super) sums: Vec<u32>,
}

impl SignificanceGrid {
    /// The grid of `cells` (coordinates relative to `origin`); it spans only their bounding
    /// box, since every query outside it is empty anyway.
    pub(super) fn new(origin: [u32; 3], cells: &[[u32; 3]]) -> Self {
        let mut lo = [u32::MAX; 3];
        let mut hi = [0u32; 3];
        for p in cells {
            for a in 0..3 {
                lo[a] = lo[a].min(p[a]);
                hi[a] = hi[a].max(p[a] + 1);
            }
        }
        if cells.is_empty() {
            lo = [0; 3];
        }
        let extent = [0, 1, 2].map(|a| (hi[a] - lo[a]) as u64);
        let mut shift = 0u32;
        let coarse = |shift: u32| extent.map(|e| e.div_ceil(1 << shift) as usize);
        while coarse(shift).iter().map(|d| d + 1).product::<usize>() > MAX_GRID_CELLS {
            shift += 1;
        }
        let dims = coarse(shift);
        let origin = [0, 1, 2].map(|a| origin[a] + lo[a]);
        let [nx, ny, nz] = dims.map(|d| d + 1);
        let mut sums = vec![0u32; nx * ny * nz];
        let mut set = vec![false; dims[0] * dims[1] * dims[2]];
        let at = |x: usize, y: usize, z: usize| x + nx * (y + ny * z);
        for p in cells {
            let [x, y, z] = [0, 1, 2].map(|a| ((p[a] - lo[a]) >> shift) as usize);
            set[x + dims[0] * (y + dims[1] * z)] = true;
            sums[at(x + 1, y + 1, z + 1)] = 1;
        }
        // Separable running sums along x, then y, then z (3 adds per cell).
        for z in 1..nz {
            for y in 1..ny {
                let row = at(0, y, z);
                for x in 1..nx {
                    sums[row + x] += sums[row + x - 1];
                }
            }
        }
        for z in 1..nz {
            for y in 1..ny {
                let (row, prev) = (at(0, y, z), at(0, y - 1, z));
                for x in 1..nx {
                    sums[row + x] += sums[prev + x];
                }
            }
        }
        let slice = nx * ny;
        for i in slice..sums.len() {
            sums[i] += sums[i - slice];
        }
        SignificanceGrid {
            dims,
            origin,
            extent,
            shift,
            cells: set,
            sums,
        }
    }

    /// Whether any cell of the band-coordinate box [lo, hi) (clipped to the region) is set.
    pub(super) fn any(&self, lo: [u64; 3], hi: [u64; 3]) -> bool {
        let mut l = [0usize; 3];
        let mut h = [0usize; 3];
        for a in 0..3 {
            let o = self.origin[a] as u64;
            let lc = lo[a].saturating_sub(o).min(self.extent[a]);
            let hc = hi[a].saturating_sub(o).min(self.extent[a]);
            if hc <= lc {
                return false;
            }
            l[a] = (lc >> self.shift) as usize;
            h[a] = (((hc - 1) >> self.shift) + 1) as usize;
        }
        if (0..3).all(|a| h[a] == l[a] + 1) {
            return self.cells[l[0] + self.dims[0] * (l[1] + self.dims[1] * l[2])];
        }
        let [nx, ny, _] = self.dims.map(|d| d + 1);
        let s = |x: usize, y: usize, z: usize| self.sums[x + nx * (y + ny * z)];
        let count = s(h[0], h[1], h[2])
            .wrapping_sub(s(l[0], h[1], h[2]))
            .wrapping_sub(s(h[0], l[1], h[2]))
            .wrapping_sub(s(h[0], h[1], l[2]))
            .wrapping_add(s(l[0], l[1], h[2]))
            .wrapping_add(s(l[0], h[1], l[2]))
            .wrapping_add(s(h[0], l[1], l[2]))
            .wrapping_sub(s(l[0], l[1], l[2]));
        count > 0
    }
}

/// Whether a [`SignificanceGrid`] over cells with bounding box [lo, hi) would be coarsened.
pub(super) fn coarsened(lo: [u32; 3], hi: [u32; 3]) -> bool {
    (0..3)
        .map(|a| (hi[a] - lo[a]) as u128 + 1)
        .product::<u128>()
        > MAX_GRID_CELLS as u128
}

/// The exact occupancy of a set of cells of one tile-local band region, for the only queries
/// the octree makes of it: does any cell of the dyadic cube of edge 2^k at `lo` hold a
/// coefficient? Level k holds one byte per such cube (level 0 the cells), so a query is one
/// lookup and an insertion marks at most one byte per level; a set grows cell by cell, unlike
/// a [`SignificanceGrid`], which is rebuilt over its whole bounding box. It answers what an
/// uncoarsened [`SignificanceGrid`] answers for an octree box: a box is its dyadic cube
/// clipped to the region, and no cell lies outside the region.
pub(super) struct Pyramid {
    /// Per level: its size in cubes, and where it starts in `bytes`.
    pub(super) levels: Vec<([usize; 3], usize)>,
    pub(super) bytes: Vec<u8>,
}

thread_local! {
    /// Byte buffers of this thread's dropped pyramids, the largest that fit in
    /// [`SPARE_PYRAMIDS`] buffers and [`SPARE_PYRAMID_BYTES`]. Every packet builds its own
    /// region-sized pyramids; a buffer fresh from the allocator cost a page fault per 4 KiB on
    /// top of its clearing (most of a decoding thread's page faults), and a reused one costs
    /// only the clearing.
    static SPARE_BYTES: std::cell::RefCell<Vec<Vec<u8>>> = const {
        std::cell::RefCell::new(Vec::new())
    };
}

/// Most spare pyramid buffers a thread keeps (a packet holds a few at a time: the parent
/// level's bands and a level's cousin union).
const SPARE_PYRAMIDS: usize = 16;

/// Most bytes a thread keeps in spare pyramid buffers. A pyramid of the largest dense region
/// is ~4.8 MB; a 128-voxel tile's finest region's ~0.3 MB. Beyond this, what a large or
/// hostile packet allocated is freed as before, not held by the thread.
const SPARE_PYRAMID_BYTES: usize = 16 << 20;

/// `n` zero bytes, in a spare buffer that holds them when this thread has one.
fn zeroed(n: usize) -> Vec<u8> {
    let spare = SPARE_BYTES
        .try_with(|s| {
            let mut s = s.borrow_mut();
            let i = s.iter().position(|b| b.capacity() >= n)?;
            Some(s.swap_remove(i))
        })
        .ok()
        .flatten();
    match spare {
        Some(mut b) => {
            b.clear();
            b.resize(n, 0);
            b
        }
        None => vec![0; n],
    }
}

impl Drop for Pyramid {
    fn drop(&mut self) {
        let bytes = std::mem::take(&mut self.bytes);
        if bytes.capacity() == 0 {
            return;
        }
        // During the thread's exit the spares are gone: the buffer is simply freed.
        let _ = SPARE_BYTES.try_with(|s| {
            let mut s = s.borrow_mut();
            s.push(bytes);
            // The smallest go first, so that small buffers do not crowd out the large ones
            // the next packet's regions need.
            while s.len() > SPARE_PYRAMIDS
                || s.iter().map(Vec::capacity).sum::<usize>() > SPARE_PYRAMID_BYTES
            {
                let smallest = (0..s.len()).min_by_key(|&i| s[i].capacity()).unwrap_or(0);
                s.swap_remove(smallest);
            }
        });
    }
}

impl Pyramid {
    pub(super) fn new(extent: [u32; 3]) -> Pyramid {
        let mut levels = Vec::new();
        let mut total = 0usize;
        for k in 0..u32::BITS {
            let d = extent.map(|e| (e as usize).div_ceil(1 << k).max(1));
            levels.push((d, total));
            total += d[0] * d[1] * d[2];
            if d == [1, 1, 1] {
                break;
            }
        }
        Pyramid {
            levels,
            bytes: zeroed(total),
        }
    }

    pub(super) fn insert(&mut self, p: [u32; 3]) {
        for (k, &(d, offset)) in self.levels.iter().enumerate() {
            let q = [
                (p[0] >> k) as usize,
                (p[1] >> k) as usize,
                (p[2] >> k) as usize,
            ];
            let i = offset + q[0] + d[0] * (q[1] + d[1] * q[2]);
            if self.bytes[i] != 0 {
                // Every coarser cube holding this one is already marked.
                break;
            }
            self.bytes[i] = 1;
        }
    }

    /// Whether any cell of the cube of edge 2^k at `lo` (a multiple of 2^k) is in the set.
    #[inline]
    pub(super) fn cube(&self, k: u32, lo: [u32; 3]) -> bool {
        let top = self.levels.len() - 1;
        let shr = |v: u32| v.checked_shr(k).unwrap_or(0) as usize;
        let q = [shr(lo[0]), shr(lo[1]), shr(lo[2])];
        let (d, offset) = self.levels[(k as usize).min(top)];
        if (0..3).any(|a| q[a] >= d[a]) {
            return false;
        }
        self.bytes[offset + q[0] + d[0] * (q[1] + d[1] * q[2])] != 0
    }
}
