//! A view's footprint set: its tables by (level, type), built at the coarsest level and
//! mipmapped down, and the factor tables of cued and cut pieces kept with it.

use super::factor::{compute_factor_tables_with, AxisFactor, FactorGrids};
use super::mipmap;
use super::slice::{compute_fine, compute_fine_at, level_subpixel};
use super::FineTable;
use super::Footprint;
use super::FootprintParams;

/// A band's table whose peak is at most this fraction of the largest peak of the view's tables
/// is left out, and its coefficients with it. On a view along an axis the four wavelet types
/// with ψ along that axis project to zero (∫ψ = 0: their computed tables are rounding noise,
/// ~1e-17 of the peak), so an axis view splats 3 of the 7 wavelet types. A coefficient left out
/// changes a pixel by at most this fraction of what a coefficient of the same magnitude adds
/// through the largest table: ~100 dB below the f32 image's rounding. Off an axis, a ψ along
/// the view direction projects to a small odd function that the exact image needs, and its
/// table stays while it is larger than that: at 1e-7 rad from an axis a Haar table still peaks
/// at ~3e-8 of the largest and is kept; the smoother families' fall with the square of the
/// angle or faster and are left out there.
pub const VANISHING: f64 = 1e-12;

/// All footprints of one view: index `level · 8 + kind` (levels 0..=M; level 0 unused unless
/// M = 0). With depth cueing the tables are per axis-factor triple instead, built on first use
/// (which triples occur depends on where the coefficients lie relative to the light-facing
/// faces) and kept here for the next rendering of the same view.
#[derive(Debug)]
pub struct FootprintSet {
    /// The parameters they were built for.
    pub params: FootprintParams,
    /// Tables (`None` for (level, kind) pairs that do not occur or whose projection vanishes in
    /// this view, see [`VANISHING`]; all `None` when cued).
    pub tables: Vec<Option<Footprint>>,
    /// Cued tables by factor triple.
    pub factor_tables:
        std::sync::Mutex<std::collections::HashMap<[AxisFactor; 3], std::sync::Arc<Footprint>>>,
    /// The 1D factor transforms on the frequency grids of the factor tables, kept for the next
    /// triples of the same view (evaluating them is most of a table's cost).
    factor_grids: FactorGrids,
}

/// The tables of one level that do not vanish in the view, with their types: a table whose peak
/// is at most [`VANISHING`] of the level's largest is a ψ along the view direction, which
/// integrates to zero along every ray (its splats would add nothing, nor would those of the
/// finer levels, whose tables are its box sums).
fn kept<'t>(tables: &'t [FineTable], kinds: &[u8]) -> Vec<(&'t FineTable, u8)> {
    let peaks: Vec<f64> = tables.iter().map(FineTable::peak).collect();
    let floor = VANISHING * peaks.iter().copied().fold(0.0, f64::max);
    tables
        .iter()
        .zip(kinds)
        .zip(&peaks)
        .filter(|(_, &peak)| peak > floor)
        .map(|((t, &kind), _)| (t, kind))
        .collect()
}

impl FootprintSet {
    /// Builds every table: level M by FFT and finer levels by mipmap (nothing up front when
    /// cued: see [`FootprintSet::factor_tables`]).
    pub fn build(p: &FootprintParams) -> FootprintSet {
        let m = p.levels;
        let mut tables: Vec<Option<Footprint>> = vec![None; (m + 1) * 8];
        let all: Vec<u8> = (0..8).collect();
        let wavelets: Vec<u8> = (1..8).collect();
        if p.cue.is_some() {
            // Built on demand per factor triple.
        } else if m == 0 {
            for level in (if m == 0 { 0 } else { 1 })..=m {
                let kinds = if level == m { &all } else { &wavelets };
                for (t, kind) in compute_fine(p, level, kinds).iter().zip(kinds) {
                    tables[level * 8 + *kind as usize] = Some(Footprint::build(t, p.gradient));
                }
            }
        } else {
            // Levels wide enough for one phase (`level_subpixel`) by their own FFT each; the
            // finer ones from the coarsest of them, at the phases the finest needs, by mipmap
            // (whose box sums reach half a pixel either side: an even S).
            let single = (1..=m)
                .find(|&level| level_subpixel(p, level) == 1)
                .unwrap_or(m + 1);
            for level in single..=m {
                let kinds = if level == m { &all } else { &wavelets };
                let built = compute_fine_at(p, level, kinds, 1);
                for (t, kind) in kept(&built, kinds) {
                    tables[level * 8 + kind as usize] = Some(Footprint::build(t, p.gradient));
                }
            }
            if single > 1 {
                let top = single - 1;
                let kinds = if top == m { &all } else { &wavelets };
                let built = compute_fine_at(p, top, kinds, level_subpixel(p, 1).max(2));
                for (t, kind) in kept(&built, kinds) {
                    tables[top * 8 + kind as usize] = Some(Footprint::build(t, p.gradient));
                    if kind != 0 {
                        // Each level from the one above it (r = 2): the same box sums as from
                        // the top at once, in a quarter of the reads per level, since each
                        // table is a quarter of the one above
                        // (`cascaded_mipmap_equals_the_direct_one`).
                        let mut above = None;
                        for level in (1..top).rev() {
                            let f = mipmap(p, above.as_ref().unwrap_or(t), level + 1, level, kind);
                            tables[level * 8 + kind as usize] =
                                Some(Footprint::build(&f, p.gradient));
                            above = Some(f);
                        }
                    }
                }
            }
        }
        FootprintSet {
            params: *p,
            tables,
            factor_tables: Default::default(),
            factor_grids: FactorGrids::default(),
        }
    }

    /// The cued tables for `keys`, computing (in parallel) and caching the missing ones.
    pub fn factor_footprints(&self, keys: &[[AxisFactor; 3]]) -> Vec<std::sync::Arc<Footprint>> {
        let missing: Vec<[AxisFactor; 3]> = {
            let map = self.factor_tables.lock().unwrap_or_else(|e| e.into_inner());
            keys.iter()
                .filter(|k| !map.contains_key(*k))
                .copied()
                .collect()
        };
        let built: Vec<([AxisFactor; 3], Footprint)> = missing
            .iter()
            .zip(compute_factor_tables_with(
                &self.params,
                &missing,
                &self.factor_grids,
            ))
            .map(|(k, t)| (*k, Footprint::build(&t, self.params.gradient)))
            .collect();
        let mut map = self.factor_tables.lock().unwrap_or_else(|e| e.into_inner());
        for (k, f) in built {
            map.insert(k, std::sync::Arc::new(f));
        }
        keys.iter().map(|k| map[k].clone()).collect()
    }

    /// The table of a band, if any.
    pub fn get(&self, level: usize, kind: u8) -> Option<&Footprint> {
        self.tables
            .get(level * 8 + kind as usize)
            .and_then(|t| t.as_ref())
    }
}
