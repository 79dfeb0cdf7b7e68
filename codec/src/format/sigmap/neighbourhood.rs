//! A box's relatives: the same cells in the parent band (one level coarser) and the cousin bands
//! (earlier types of the same level), looked up in their grids, as occupancy contexts.

use super::super::Header;
use super::cells::DENSE_MAX_CELLS;
use super::grid::{coarsened, Pyramid, SignificanceGrid};
use super::octree::{region, Box3};
use crate::layout::Band;

/// The cells of one band (or of a level's cousin bands) coded so far: a [`Pyramid`] when its
/// answers are those of the [`SignificanceGrid`] the format defines the contexts by (the grid
/// is not coarsened, the region is small enough to hold densely and, for a parent, its region
/// halves the finer level's), the grid itself otherwise.
pub(super) enum CellSet {
    Exact(Pyramid),
    Grid(SignificanceGrid),
}

/// The parent and cousin sets of one band, as coded so far: `None` where the band has none
/// (state 0), `Some(None)` where that set is still empty.
pub(super) struct Relatives<'a> {
    pub(super) parent: Option<Option<&'a CellSet>>,
    pub(super) cousin: Option<Option<&'a CellSet>>,
}

impl Relatives<'_> {
    /// Parent and cousin states of the box `b` (tile-local) of a band whose region starts at
    /// `origin`: 0 no such band, 1 nothing there, 2 a coefficient there.
    #[inline(always)]
    pub(super) fn states(&self, origin: [u32; 3], b: &Box3) -> (usize, usize) {
        let k = b.scale.trailing_zeros();
        let glo = || [0, 1, 2].map(|a| (origin[a] + b.lo[a]) as u64);
        let ghi = || [0, 1, 2].map(|a| (origin[a] + b.hi[a]) as u64);
        let parent = match self.parent {
            None => 0,
            Some(None) => 1,
            // The box's parent cells are the cube of half its edge at half its corner.
            Some(Some(CellSet::Exact(p))) => {
                1 + p.cube(
                    k.saturating_sub(1),
                    [b.lo[0] >> 1, b.lo[1] >> 1, b.lo[2] >> 1],
                ) as usize
            }
            Some(Some(CellSet::Grid(g))) => {
                1 + g.any(glo().map(|v| v / 2), ghi().map(|v| v.div_ceil(2))) as usize
            }
        };
        let cousin = match self.cousin {
            None => 0,
            Some(None) => 1,
            Some(Some(CellSet::Exact(p))) => 1 + p.cube(k, b.lo) as usize,
            Some(Some(CellSet::Grid(g))) => 1 + g.any(glo(), ghi()) as usize,
        };
        (parent, cousin)
    }
}

/// A level's band region in the tile: origin (band coordinates) and extent in cells.
#[derive(Clone, Copy)]
pub(super) struct Region {
    origin: [u32; 3],
    extent: [u32; 3],
}

/// The significance of the bands of the current channel coded so far in this packet, indexed
/// by band; what the occupancy contexts look at.
pub(super) struct Neighbourhood<'h> {
    pub(super) header: &'h Header,
    /// Per level: the tile's band region.
    pub(super) regions: Vec<Region>,
    /// Per band index: its cells, kept for the next finer level's parent queries.
    pub(super) grids: Vec<Option<CellSet>>,
    /// Per level: the union of the wavelet bands coded so far at that level.
    pub(super) cousins: Vec<Option<CellSet>>,
    pub(super) level_cells: Vec<Vec<[u32; 3]>>,
    /// Per level: the bounding box [lo, hi) of `level_cells`.
    pub(super) level_bounds: Vec<([u32; 3], [u32; 3])>,
}

impl<'h> Neighbourhood<'h> {
    pub(super) fn new(header: &'h Header, tile: usize) -> Self {
        let g = &header.geometry;
        let nb = g.band_count();
        let nl = g.levels + 1;
        let regions = (0..nl)
            .map(|l| {
                let band = Band {
                    level: l as u8,
                    kind: 1,
                };
                let (origin, root) = region(header, tile, l as u8, g.band_dims(band));
                Region {
                    origin,
                    extent: root.hi,
                }
            })
            .collect();
        Neighbourhood {
            header,
            regions,
            grids: (0..nb).map(|_| None).collect(),
            cousins: (0..nl).map(|_| None).collect(),
            level_cells: vec![Vec::new(); nl],
            level_bounds: vec![([u32::MAX; 3], [0; 3]); nl],
        }
    }

    pub(super) fn reset(&mut self) {
        self.grids.iter_mut().for_each(|g| *g = None);
        self.cousins.iter_mut().for_each(|g| *g = None);
        self.level_cells.iter_mut().for_each(Vec::clear);
        self.level_bounds
            .iter_mut()
            .for_each(|b| *b = ([u32::MAX; 3], [0; 3]));
    }

    /// The sets the occupancy contexts of band index `bi` look at.
    pub(super) fn relatives(&self, bi: usize, band: Band) -> Relatives<'_> {
        if band.kind == 0 {
            return Relatives {
                parent: None,
                cousin: None,
            };
        }
        Relatives {
            // The parent band (same type, one level coarser) comes 7 band indices earlier.
            parent: ((band.level as usize) < self.header.geometry.levels)
                .then(|| self.grids[bi - 7].as_ref()),
            cousin: (band.kind > 1).then(|| self.cousins[band.level as usize].as_ref()),
        }
    }

    /// Whether a set of `count` cells of level `l` with bounding box [lo, hi) is held as a
    /// [`Pyramid`]: its grid would not be coarsened, its region is small enough, the set is
    /// dense enough to pay for a region-sized pyramid (at least one cell per 8×8×8 block of the
    /// region, so at most ~512 bytes per cell: a sparse set's grid is sized by its bounding
    /// box, so a small packet does not allocate and clear its whole region), and (for a parent set) the finer level's region
    /// maps onto it by halving, so that the halved box is the parent cube. Both forms answer
    /// the same queries identically.
    fn exact(&self, l: usize, lo: [u32; 3], hi: [u32; 3], count: usize, parent: bool) -> bool {
        let r = self.regions[l];
        let cells: u128 = r.extent.iter().map(|&e| e as u128).product();
        if coarsened(lo, hi) || cells > DENSE_MAX_CELLS as u128 || (count as u128) * 512 < cells {
            return false;
        }
        if parent {
            let Some(child) = l.checked_sub(1).map(|c| self.regions[c]) else {
                return false;
            };
            return (0..3).all(|a| {
                child.origin[a] == 2 * r.origin[a] && child.extent[a].div_ceil(2) >= r.extent[a]
            });
        }
        true
    }

    /// Records the cells of `band` just coded; grids nobody will query are not built.
    pub(super) fn record(&mut self, band: Band, origin: [u32; 3], cells: &[[u32; 3]]) {
        if band.kind == 0 || cells.is_empty() {
            return;
        }
        let l = band.level as usize;
        // Only the next coarser level's bands are parents of what follows; drop the rest.
        let geometry = &self.header.geometry;
        for (i, b) in geometry.bands().iter().enumerate() {
            if b.level as usize > l + 1 {
                self.grids[i] = None;
            }
        }
        for level in l + 1..self.cousins.len() {
            self.cousins[level] = None;
        }
        let (mut lo, mut hi) = ([u32::MAX; 3], [0u32; 3]);
        for p in cells {
            for a in 0..3 {
                lo[a] = lo[a].min(p[a]);
                hi[a] = hi[a].max(p[a] + 1);
            }
        }
        if l > 1 {
            if let Some(i) = geometry.band_index(band) {
                let set = if self.exact(l, lo, hi, cells.len(), true) {
                    let mut p = Pyramid::new(self.regions[l].extent);
                    cells.iter().for_each(|c| p.insert(*c));
                    CellSet::Exact(p)
                } else {
                    CellSet::Grid(SignificanceGrid::new(origin, cells))
                };
                self.grids[i] = Some(set);
            }
        }
        if band.kind < 7 {
            self.level_cells[l].extend_from_slice(cells);
            let bounds = &mut self.level_bounds[l];
            for a in 0..3 {
                bounds.0[a] = bounds.0[a].min(lo[a]);
                bounds.1[a] = bounds.1[a].max(hi[a]);
            }
            let (lo, hi) = *bounds;
            let set = if self.exact(l, lo, hi, self.level_cells[l].len(), false) {
                match self.cousins[l].take() {
                    // The union only grows: add the new cells.
                    Some(CellSet::Exact(mut p)) => {
                        cells.iter().for_each(|c| p.insert(*c));
                        CellSet::Exact(p)
                    }
                    _ => {
                        let mut p = Pyramid::new(self.regions[l].extent);
                        self.level_cells[l].iter().for_each(|c| p.insert(*c));
                        CellSet::Exact(p)
                    }
                }
            } else {
                CellSet::Grid(SignificanceGrid::new(origin, &self.level_cells[l]))
            };
            self.cousins[l] = Some(set);
        }
    }
}
