//! What of each basis function a clipped file shows: where the grid leaves less room than the
//! separating margin ([`Geometry::clips_to_box`]; the renderer clips every spline file to the
//! volume's box) and the decoder crops to it, a coefficient whose basis
//! function lies mostly in the padding (or wraps round to the far face) is mostly never seen.
//! Its energy w²·‖b‖² overstates what keeping it buys; w²·‖b‖²·v, with v the fraction of
//! ‖b‖² inside the box, does not. With smooth padding ([`crate::encode::CompressOptions`]'s
//! `smooth_padding`) the padding holds a bridge between faces that the transform must
//! represent but nobody draws, and ranking by the seen energy keeps the budget inside.
//!
//! The fraction is separable: a basis function is a product of one periodic line per axis,
//! so v = v_x·v_y·v_z, each the share of the line's squared level-0 expansion that falls on
//! the box's voxels. Per axis, level and kind the line of position 0 is synthesized once and
//! every position's share read from circular prefix sums (positions at level l are shifts
//! by 2^l).

use strength_reduce::StrengthReducedUsize;
use wavesplat_codec::dwt::unit_basis_line;
use wavesplat_codec::layout::Geometry;

/// Per axis, per level (0..=M): the seen fraction of each position's basis line, indexed by
/// the coefficient's coordinate in the Mallat layout (φ positions first, then ψ from half the
/// level's block).
#[derive(Debug, Clone)]
pub struct Visible {
    /// The grid's row and column lengths as divisors: every score takes a coefficient's
    /// position from its index, and a hardware division per axis was a tenth of a bricked
    /// compression's time.
    row: StrengthReducedUsize,
    column: StrengthReducedUsize,
    levels: Vec<u8>,
    tables: [Vec<Vec<f32>>; 3],
}

impl Visible {
    /// The fractions for `geometry`, or `None` when it is not clipped (everything is drawn).
    pub fn new(geometry: &Geometry) -> Option<Visible> {
        if !geometry.clips_to_box() {
            return None;
        }
        let tables = std::array::from_fn(|a| {
            let p = geometry.padded[a];
            let (lo, n) = (geometry.origin[a], geometry.dims[a]);
            (0..=geometry.levels)
                .map(|l| {
                    let shares = |wavelet| {
                        let line = unit_basis_line(geometry.family, p, l, wavelet, false);
                        seen_shares(&line, lo, n, 1 << l)
                    };
                    // Level l's φ positions then its ψ positions, as the layout stores them
                    // along the axis (level 0 has only φ).
                    let mut table = shares(false);
                    if l > 0 {
                        table.extend(shares(true));
                    }
                    table
                })
                .collect()
        });
        Some(Visible {
            row: StrengthReducedUsize::new(geometry.padded[0]),
            column: StrengthReducedUsize::new(geometry.padded[1]),
            levels: geometry.bands().iter().map(|b| b.level).collect(),
            tables,
        })
    }

    /// The seen fraction of coefficient `index` of band index `band` where `visible` applies,
    /// 1 (everything drawn) where it does not: the factor every score takes.
    #[inline]
    pub fn share(visible: Option<&Visible>, index: usize, band: u8) -> f64 {
        visible.map_or(1.0, |v| v.fraction(index, band))
    }

    /// Bytes its tables hold on the heap.
    pub fn heap_bytes(&self) -> usize {
        let tables: usize = self
            .tables
            .iter()
            .flatten()
            .map(|t| t.capacity() * std::mem::size_of::<f32>())
            .sum();
        tables + self.levels.capacity()
    }

    /// The seen fraction of coefficient `index` (Mallat layout) of band index `band`.
    #[inline]
    pub fn fraction(&self, index: usize, band: u8) -> f64 {
        self.fraction_at(self.position(index), band)
    }

    /// The grid position (x, y, z) of coefficient `index`.
    #[inline]
    fn position(&self, index: usize) -> [usize; 3] {
        let (plane_and_row, x) = StrengthReducedUsize::div_rem(index, self.row);
        let (z, y) = StrengthReducedUsize::div_rem(plane_and_row, self.column);
        [x, y, z]
    }

    /// The seen fraction of the coefficient at grid position `at` of band index `band`: the
    /// one product every path takes, x first, so that a walk and a lookup agree to the bit.
    #[inline]
    fn fraction_at(&self, at: [usize; 3], band: u8) -> f64 {
        let l = self.levels[band as usize] as usize;
        let mut v = 1.0f64;
        for (table, c) in self.tables.iter().zip(at) {
            v *= f64::from(table[l][c]);
        }
        v
    }

    /// A walk over consecutive coefficients from `index` on: their fractions without a
    /// position taken from each index (two divisions each, a tenth of a bricked compression's
    /// scoring time).
    pub fn walk(&self, index: usize) -> VisibleWalk<'_> {
        VisibleWalk {
            visible: self,
            at: self.position(index),
        }
    }
}

/// [`Visible::walk`]: the fractions of consecutive coefficients, x fastest.
pub struct VisibleWalk<'a> {
    visible: &'a Visible,
    at: [usize; 3],
}

impl VisibleWalk<'_> {
    /// The seen fraction of the current coefficient, of band index `band`: what
    /// [`Visible::fraction`] gives for its index.
    #[inline]
    pub fn fraction(&self, band: u8) -> f64 {
        self.visible.fraction_at(self.at, band)
    }

    /// Moves on to the next coefficient.
    #[inline]
    pub fn advance(&mut self) {
        let v = self.visible;
        self.at[0] += 1;
        if self.at[0] == v.row.get() {
            self.at[0] = 0;
            self.at[1] += 1;
            if self.at[1] == v.column.get() {
                self.at[1] = 0;
                self.at[2] += 1;
            }
        }
    }
}

/// For a periodic line whose position k is `line` shifted by k·`step`, the share of its
/// squared values on samples `lo..lo + n`, for every position.
fn seen_shares(line: &[f64], lo: usize, n: usize, step: usize) -> Vec<f32> {
    let p = line.len();
    let sq: Vec<f64> = line.iter().map(|v| v * v).collect();
    let total: f64 = sq.iter().sum();
    // Prefix sums over two periods, so any window of up to p samples is one difference.
    let mut prefix = Vec::with_capacity(2 * p + 1);
    prefix.push(0.0);
    for i in 0..2 * p {
        let last = prefix[i];
        prefix.push(last + sq[i % p]);
    }
    (0..p / step)
        .map(|k| {
            if total == 0.0 {
                return 0.0;
            }
            // Box samples lo..lo+n of the shifted line are samples lo − k·step.. of `line`.
            let start = (lo + p - (k * step) % p) % p;
            ((prefix[start + n] - prefix[start]) / total) as f32
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use wavesplat_codec::family::Family;
    use wavesplat_codec::layout::Band;

    /// Against a direct computation: the basis function of a coefficient synthesized on the
    /// whole grid, its squared expansion summed inside the box over the total.
    #[test]
    fn fractions_match_the_synthesized_basis_functions() {
        let g = Geometry::new([10, 7, 5], Family::Linear, 2, 1).unwrap();
        assert!(g.clips_to_box());
        let v = Visible::new(&g).unwrap();
        let bands = g.bands();
        let n = g.coefficient_count();
        let band_of = crate::select::band_map(&g);
        let mut planner = wavesplat_codec::dwt::Dwt1d::new(g.family);
        for index in (0..n).step_by(7) {
            let mut data = vec![0.0f64; n];
            data[index] = 1.0;
            wavesplat_codec::dwt::inverse_3d(&mut data, &g, &mut planner);
            let total: f64 = data.iter().map(|x| x * x).sum();
            let mut inside = 0.0;
            for z in 0..g.dims[2] {
                for y in 0..g.dims[1] {
                    for x in 0..g.dims[0] {
                        let i = (g.origin[0] + x)
                            + g.padded[0] * ((g.origin[1] + y) + g.padded[1] * (g.origin[2] + z));
                        inside += data[i] * data[i];
                    }
                }
            }
            let want = inside / total;
            let got = v.fraction(index, band_of[index]);
            let band: Band = bands[band_of[index] as usize];
            assert!(
                (got - want).abs() < 1e-5,
                "index {index} ({band:?}): {got} against {want}"
            );
        }
        // Unclipped geometries need no fractions.
        assert!(Visible::new(&Geometry::new([10, 7, 5], Family::Linear, 2, 6).unwrap()).is_none());
    }

    /// A walk from any coefficient on gives each following coefficient the fraction
    /// [`Visible::fraction`] gives its index, to the bit, across rows and planes, for every
    /// family and a depth whose grid is padded unevenly.
    #[test]
    fn a_walk_agrees_with_the_fractions_by_index() {
        for (family, dims, levels) in [
            (Family::Linear, [10, 7, 5], 2),
            (Family::Cubic, [9, 6, 11], 1),
            (Family::Linear, [13, 4, 3], 1),
        ] {
            let g = Geometry::new(dims, family, levels, 1).unwrap();
            let v = Visible::new(&g).expect("a clipped grid");
            let band_of = crate::select::band_map(&g);
            let n = g.coefficient_count();
            let mut partial = 0;
            for start in [0, 1, g.padded[0] - 1, g.padded[0] * g.padded[1] - 1, n / 2] {
                let mut walk = v.walk(start);
                for (i, &band) in band_of.iter().enumerate().skip(start) {
                    let want = v.fraction(i, band);
                    assert_eq!(
                        walk.fraction(band).to_bits(),
                        want.to_bits(),
                        "{family:?} {dims:?}: index {i} from {start}"
                    );
                    partial += usize::from(want < 1.0);
                    walk.advance();
                }
            }
            assert!(partial > 0, "{family:?} {dims:?}: nothing clipped");
        }
    }
}
