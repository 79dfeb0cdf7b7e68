//! The sigmap coder's adaptive models (`Models`: presence, occupancy, sign and magnitude models
//! of a packet, fresh in every packet: at the trained priors from format version 12, at ½
//! before) and the context index of each decision: occupancy by band, box size, the parent's
//! and cousins' significance and the face state; signs and magnitudes by the coded cells'
//! lower neighbours.

use super::super::Header;
use super::cells::{
    face_state_of_count, CodedCells, FACE_STATES, NEIGHBOUR_STATES, SIGN_CONTEXTS, VALUE_CONTEXTS,
};
use super::octree::Box3;
use super::priors;
use crate::entropy::range::{AdaptiveUintModel, BitModel};
use std::sync::{Arc, Mutex};

/// Most size contexts per band (log2 of a box's cell count, clamped); a packet uses as many as
/// its tile's largest region needs ([`Models::new`]), so small tiles set up fewer models.
const MAX_SIZE_CONTEXTS: usize = 48;

/// The models of a single cell ([`Models::cell_contexts`]).
#[derive(Clone, Copy, Debug)]
pub(super) struct CellContexts {
    /// Its occupancy's face state.
    pub(super) face: usize,
    /// Its sign model.
    pub(super) sign: usize,
    /// Its value model.
    pub(super) value: usize,
}

/// The adaptive models of a packet, and the cells coded so far in the current substream.
pub(super) struct Models {
    pub(super) present: Vec<BitModel>,
    pub(super) occupied: Vec<BitModel>,
    pub(super) sign: Vec<BitModel>,
    pub(super) value: Vec<AdaptiveUintModel>,
    pub(super) coded: CodedCells,
    /// Size contexts per band: enough for the largest box of a tile region.
    pub(super) size_contexts: usize,
    /// Value contexts per band: [`VALUE_CONTEXTS`], or 1 in files before
    /// [`super::MAGNITUDE_CONTEXTS_VERSION`].
    pub(super) value_contexts: usize,
}

impl Models {
    pub(super) fn new(header: &Header) -> Models {
        let nb = header.geometry.band_count();
        let tile_cells = (header.tile as u128).pow(3);
        let size_contexts =
            ((u128::BITS - tile_cells.leading_zeros()) as usize + 1).clamp(2, MAX_SIZE_CONTEXTS);
        let occupied = nb * size_contexts * NEIGHBOUR_STATES * NEIGHBOUR_STATES * FACE_STATES;
        let value_contexts = if header.version >= super::super::MAGNITUDE_CONTEXTS_VERSION {
            VALUE_CONTEXTS
        } else {
            1
        };
        let coded = SPARE_CELLS
            .try_with(|c| c.take())
            .ok()
            .flatten()
            .unwrap_or_default();
        if header.version >= super::super::PRIORS_VERSION {
            let key = (header.geometry.levels, size_contexts, value_contexts);
            let p = primed(key, || {
                let mut m = Models::fresh(nb, size_contexts, value_contexts, occupied);
                priors::prime(m.arrays(), &header.geometry.bands(), priors::shipped());
                Primed {
                    key,
                    present: std::mem::take(&mut m.present),
                    occupied: std::mem::take(&mut m.occupied),
                    sign: std::mem::take(&mut m.sign),
                    value: std::mem::take(&mut m.value),
                }
            });
            return Models {
                size_contexts,
                value_contexts,
                present: p.present.clone(),
                occupied: p.occupied.clone(),
                sign: p.sign.clone(),
                value: p.value.clone(),
                coded,
            };
        }
        let mut m = Models::fresh(nb, size_contexts, value_contexts, occupied);
        m.coded = coded;
        m
    }

    /// Its model arrays, as the priors see them.
    pub(super) fn arrays(&mut self) -> priors::Arrays<'_> {
        priors::Arrays {
            present: &mut self.present,
            occupied: &mut self.occupied,
            sign: &mut self.sign,
            value: &mut self.value,
            size_contexts: self.size_contexts,
            value_contexts: self.value_contexts,
        }
    }

    /// Models at probability ½ (the format before [`super::super::PRIORS_VERSION`]).
    fn fresh(nb: usize, size_contexts: usize, value_contexts: usize, occupied: usize) -> Models {
        Models {
            size_contexts,
            value_contexts,
            present: vec![BitModel::new(); nb],
            occupied: vec![BitModel::new(); occupied],
            sign: vec![BitModel::new(); nb * SIGN_CONTEXTS],
            value: vec![AdaptiveUintModel::new(); nb * value_contexts],
            coded: CodedCells::default(),
        }
    }
}

/// A packet's primed models for one (depth, size contexts, value contexts), copied for each
/// packet of that shape.
struct Primed {
    key: (usize, usize, usize),
    present: Vec<BitModel>,
    occupied: Vec<BitModel>,
    sign: Vec<BitModel>,
    value: Vec<AdaptiveUintModel>,
}

/// Shapes of primed models kept at most (a file has one or two; each is up to ~0.3 MB).
const PRIMED_SHAPES: usize = 8;

/// The primed models of shape `key`, built by `build` the first time (and again after
/// [`PRIMED_SHAPES`] other shapes). Kept for the process, not per thread, so that no thread's
/// exit frees them (and decoding threads share one copy).
fn primed(key: (usize, usize, usize), build: impl FnOnce() -> Primed) -> Arc<Primed> {
    static PRIMED: Mutex<Vec<Arc<Primed>>> = Mutex::new(Vec::new());
    let mut kept = PRIMED.lock().unwrap_or_else(|e| e.into_inner());
    if let Some(i) = kept.iter().position(|p| p.key == key) {
        let p = kept.remove(i);
        kept.push(p.clone());
        return p;
    }
    let p = Arc::new(build());
    if kept.len() == PRIMED_SHAPES {
        kept.remove(0);
    }
    kept.push(p.clone());
    p
}

thread_local! {
    /// The coded cells of this thread's last packet, handed to the next: their dense arrays
    /// are region-sized, and every packet's fresh ones cost a page fault per 4 KiB (the
    /// `CodedCells::reset` before each use clears what the last packet set).
    static SPARE_CELLS: std::cell::Cell<Option<CodedCells>> = const { std::cell::Cell::new(None) };
}

impl Drop for Models {
    fn drop(&mut self) {
        let coded = std::mem::take(&mut self.coded);
        // During the thread's exit the spare is gone: the cells are simply freed.
        let _ = SPARE_CELLS.try_with(|c| c.set(Some(coded)));
    }
}

impl Models {
    /// The contexts of a single cell at `cell` of band index `band`, from one look at its lower
    /// neighbours: its occupancy's face state ([`Models::face_state`]) and, when it holds a
    /// coefficient, its sign and value models ([`CodedCells::leaf_contexts`]; files before
    /// [`super::MAGNITUDE_CONTEXTS_VERSION`] have one value model per band). Nothing is coded
    /// between a cell's occupancy and its leaf, so one look serves both.
    #[inline(always)]
    pub(super) fn cell_contexts(&self, band: usize, cell: [u32; 3]) -> CellContexts {
        let n = self.coded.neighbours(cell);
        let weighed = if self.value_contexts == 1 {
            n.coded
        } else {
            n.magnitudes
        };
        CellContexts {
            face: face_state_of_count(weighed),
            sign: band * SIGN_CONTEXTS + n.signs,
            value: if self.value_contexts == 1 {
                band
            } else {
                band * VALUE_CONTEXTS + n.magnitudes
            },
        }
    }

    /// The face state of a box of `cells` cells ([`CodedCells::face_state`]). From
    /// [`super::MAGNITUDE_CONTEXTS_VERSION`] a single cell's state weighs its coded lower
    /// neighbours by their magnitude classes instead of counting them (the sum of
    /// [`CodedCells::leaf_contexts`]: 0, 1, 2–3, 4 and above), since a cell beside large
    /// coefficients is likelier to hold one ([`Models::cell_contexts`]).
    #[inline(always)]
    pub(super) fn face_state(&self, b: &Box3, cells: usize) -> usize {
        if cells == 1 {
            self.cell_contexts(0, b.lo).face
        } else {
            self.coded.face_state(b, cells)
        }
    }

    /// The occupancy context of a box: its band, the log2 of its cell count, the states of its
    /// parent region (same type one level coarser) and of its cousins (earlier types of the
    /// same level at the same cells), both as coded earlier in this packet, and its face state
    /// (coded cells of the same band touching its lower faces, [`CodedCells::face_state`]).
    pub(super) fn occupancy_context(
        &self,
        band: usize,
        cells: usize,
        neighbours: (usize, usize),
        face: usize,
    ) -> usize {
        let lg = (usize::BITS - cells.leading_zeros()) as usize;
        let size = lg.min(self.size_contexts - 1);
        (((band * self.size_contexts + size) * NEIGHBOUR_STATES + neighbours.0) * NEIGHBOUR_STATES
            + neighbours.1)
            * FACE_STATES
            + face
    }
}
