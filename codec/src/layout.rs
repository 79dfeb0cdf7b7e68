//! Coefficient addressing: where every coefficient of the 3D non-standard decomposition lives,
//! which basis function it weights and where that function sits in the volume.
//!
//! The transform runs on a *padded* grid: each axis of the volume is zero-padded to a multiple
//! of 2^M (plus an optional margin, centred) so that every level halves every axis. The boundary
//! treatment is **periodic on the zero-padded grid**: every basis function is an exact translate
//! of the dilated mother function (so 8 footprints per level suffice), and the decomposition is
//! the exact orthogonal projection onto V and W of the periodic spline space. The volume is the
//! spline of the reconstruction's level-0 coefficients inside the box; a renderer places each
//! coefficient at the translate nearest the volume centre when the margin separates the periodic
//! images ([`Geometry::separating_margin`]), and clips the translates that reach the box
//! otherwise.
//!
//! Bands are `(level, type)` pairs: types 1..=7 at levels 1..=M are wavelets, type 0 at level M
//! is the scaling function. A type's bits say which axes carry ψ: bit 2 (value 4) = x,
//! bit 1 (value 2) = y, bit 0 (value 1) = z, as in Table 1 of the paper (type 4 = ψφφ).
//! Coefficients are stored in the in-place (Mallat) layout of a padded-size array, x fastest.

use crate::family::Family;
use thiserror::Error;

/// Largest decomposition depth supported.
pub const MAX_LEVELS: usize = 16;

/// Errors in the geometry of a decomposition.
#[derive(Debug, Error, PartialEq)]
#[non_exhaustive]
pub enum LayoutError {
    /// Too many levels for the volume.
    #[error("{levels} decomposition levels requested; dims {dims:?} allow at most {max} (ceil(log2(smallest dimension)), capped at {cap})", cap = MAX_LEVELS)]
    TooManyLevels {
        /// Requested levels.
        levels: usize,
        /// Volume dimensions.
        dims: [usize; 3],
        /// Allowed maximum.
        max: usize,
    },
    /// The padded grid would be too large.
    #[error("padding {dims:?} to a multiple of 2^{levels} with margin {margin} gives {padded:?}, too many voxels")]
    TooLarge {
        /// Volume dimensions.
        dims: [usize; 3],
        /// Levels.
        levels: usize,
        /// Margin.
        margin: usize,
        /// Padded dimensions.
        padded: [usize; 3],
    },
    /// Zero-sized volume.
    #[error("volume dimensions must be at least 1, got {0:?}")]
    Empty([usize; 3]),
    /// A voxel spacing that is not a finite positive number.
    #[error("voxel spacing {0:?} must be three finite positive numbers")]
    BadSpacing([f32; 3]),
}

/// A band of coefficients: one wavelet type at one level, or the scaling type at level M.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct Band {
    /// Decomposition level (1..=M for wavelets, M for the scaling band; 0 when M = 0).
    pub level: u8,
    /// Type 0..=7 (0 = scaling φφφ).
    pub kind: u8,
}

impl Band {
    /// True if axis `axis` (0 = x, 1 = y, 2 = z) carries ψ in this band.
    pub fn is_wavelet_along(self, axis: usize) -> bool {
        self.kind & (4 >> axis) != 0
    }
}

/// The geometry of one decomposed volume: original and padded sizes, depth and family, and the
/// voxel spacing that places the voxel grid in physical space (cameras, footprints, depth cues
/// and visibility all work in its units, mm for medical data).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Geometry {
    /// Original volume dimensions.
    pub dims: [usize; 3],
    /// Padded grid dimensions (each a multiple of 2^levels).
    pub padded: [usize; 3],
    /// Position of the volume's voxel (0, 0, 0) in the padded grid.
    pub origin: [usize; 3],
    /// Decomposition depth M.
    pub levels: usize,
    /// Wavelet family.
    pub family: Family,
    /// Distance between voxel centres along x, y, z (finite and positive; 1 when unknown).
    pub spacing: [f32; 3],
}

// Every field compares reflexively: the spacing is validated finite (`with_spacing`).
impl Eq for Geometry {}

impl Geometry {
    /// Maximum depth for `dims`: ceil(log2(smallest dimension)), capped at [`MAX_LEVELS`].
    pub fn max_levels(dims: [usize; 3]) -> usize {
        let min = *dims.iter().min().unwrap_or(&1);
        let mut m = 0;
        while (1usize << m) < min {
            m += 1;
        }
        m.min(MAX_LEVELS)
    }

    /// The separating margin (voxels of zeros on each side before rounding up): none for Haar,
    /// whose supports tile the grid and never cross a period; for the splines half the support
    /// of the coarsest wavelet, ⌈(2j − 1)·2^M / 2⌉, so that the period is at least the volume
    /// plus that support and no two periodic images of one basis function reach the volume.
    /// With less, the transform bridges the padding ([`Geometry::clips_to_box`]); the
    /// compressor's default is no margin (the zeros cost coefficients where structure crosses
    /// the faces).
    pub fn separating_margin(family: Family, levels: usize) -> usize {
        match family {
            Family::Haar => 0,
            _ => ((2 * family.order() - 1) << levels).div_ceil(2),
        }
    }

    /// Whether some axis leaves less room around the volume than
    /// [`Geometry::separating_margin`] on each side, so that periodic images of one basis
    /// function can reach the volume (never for Haar). The encoder then bridges the padding
    /// and counts only what lies in the box as seen; the renderer clips to the box in any case
    /// ([`Geometry::splats_clip_to_box`]).
    pub fn clips_to_box(&self) -> bool {
        let room = 2 * Geometry::separating_margin(self.family, self.levels);
        self.family != Family::Haar
            && (0..3).any(|a| self.padded[a] < self.dims[a].saturating_add(room))
    }

    /// Whether the renderer clips this geometry's basis functions to the volume's box: for
    /// every family but Haar, whatever the margin. The volume is the box: a spline basis
    /// function across a face draws, outside it, what the periodic transform put in the margin
    /// and, past the padded grid, tails whose wrapped parts would have cancelled them. Drawn
    /// whole, they put errors of 40 dB into oblique views, and into axis views around the box.
    /// Haar's blocks never leave the padded grid, and what they put in the margin is what
    /// the margin held.
    pub fn splats_clip_to_box(&self) -> bool {
        self.family != Family::Haar
    }

    /// Builds the geometry, padding each axis to `roundup(dim + 2·margin, 2^levels)` with the
    /// volume centred (the extra voxel of an odd split goes after the volume).
    pub fn new(
        dims: [usize; 3],
        family: Family,
        levels: usize,
        margin: usize,
    ) -> Result<Geometry, LayoutError> {
        if dims.contains(&0) {
            return Err(LayoutError::Empty(dims));
        }
        let max = Geometry::max_levels(dims);
        if levels > max {
            return Err(LayoutError::TooManyLevels { levels, dims, max });
        }
        let block = 1usize << levels;
        let mut padded = [0usize; 3];
        let mut origin = [0usize; 3];
        for a in 0..3 {
            let want = dims[a].saturating_add(margin.saturating_mul(2));
            padded[a] = want.div_ceil(block).saturating_mul(block);
            origin[a] = (padded[a] - dims[a]) / 2;
        }
        let voxels = padded
            .iter()
            .try_fold(1u128, |acc, d| acc.checked_mul(*d as u128))
            .unwrap_or(u128::MAX);
        if voxels > crate::volume::MAX_VOXELS as u128 {
            return Err(LayoutError::TooLarge {
                dims,
                levels,
                margin,
                padded,
            });
        }
        Ok(Geometry {
            dims,
            padded,
            origin,
            levels,
            family,
            spacing: [1.0; 3],
        })
    }

    /// The same geometry with voxel spacing `spacing` (each finite and positive).
    pub fn with_spacing(self, spacing: [f32; 3]) -> Result<Geometry, LayoutError> {
        if spacing.iter().any(|s| !(s.is_finite() && *s > 0.0)) {
            return Err(LayoutError::BadSpacing(spacing));
        }
        Ok(Geometry { spacing, ..self })
    }

    /// The spacing in f64.
    pub fn spacing_f64(&self) -> [f64; 3] {
        self.spacing.map(f64::from)
    }

    /// Coefficients per channel (= padded voxel count).
    pub fn coefficient_count(&self) -> usize {
        self.padded.iter().product()
    }

    /// Number of bands: 7 per level plus the scaling band.
    pub fn band_count(&self) -> usize {
        7 * self.levels + 1
    }

    /// All bands, coarse to fine: the scaling band, then levels M..=1 with types 1..=7.
    pub fn bands(&self) -> Vec<Band> {
        let mut out = vec![Band {
            level: self.levels as u8,
            kind: 0,
        }];
        for level in (1..=self.levels).rev() {
            for kind in 1..8u8 {
                out.push(Band {
                    level: level as u8,
                    kind,
                });
            }
        }
        out
    }

    /// Index of `band` in [`Geometry::bands`], or `None` if it does not exist here.
    pub fn band_index(&self, band: Band) -> Option<usize> {
        let (l, k) = (band.level as usize, band.kind as usize);
        if k == 0 {
            return (l == self.levels).then_some(0);
        }
        if k > 7 || l == 0 || l > self.levels {
            return None;
        }
        Some(1 + (self.levels - l) * 7 + (k - 1))
    }

    /// Size of a band's coefficient grid (padded >> level).
    pub fn band_dims(&self, band: Band) -> [usize; 3] {
        let l = band.level as usize;
        [
            self.padded[0] >> l,
            self.padded[1] >> l,
            self.padded[2] >> l,
        ]
    }

    /// Whether coefficient `pos` of `band` sits in the padding: the first voxel of its cell
    /// (`pos · 2^level` on the padded grid) lies outside the volume's box along some axis. Such
    /// coefficients serve only the faces (their basis functions reach into the box from outside),
    /// which is what a brick's bridge padding costs.
    pub fn cell_outside_box(&self, band: Band, pos: [u32; 3]) -> bool {
        (0..3).any(|a| {
            let first = (pos[a] as usize) << band.level;
            first < self.origin[a] || first >= self.origin[a] + self.dims[a]
        })
    }

    /// Linear index (Mallat layout, x fastest) of coefficient `pos` of `band`.
    pub fn linear_index(&self, band: Band, pos: [usize; 3]) -> usize {
        let bd = self.band_dims(band);
        let mut c = [0usize; 3];
        for a in 0..3 {
            c[a] = pos[a] + if band.is_wavelet_along(a) { bd[a] } else { 0 };
        }
        c[0] + self.padded[0] * (c[1] + self.padded[1] * c[2])
    }

    /// Inverse of [`Geometry::linear_index`].
    pub fn locate(&self, index: usize) -> (Band, [usize; 3]) {
        let c = [
            index % self.padded[0],
            (index / self.padded[0]) % self.padded[1],
            index / (self.padded[0] * self.padded[1]),
        ];
        // The level is the finest l such that some coordinate lies in the upper half of the
        // level-(l-1) block; coordinates all in the level-M block mean the scaling band.
        for l in 1..=self.levels {
            let half = [
                self.padded[0] >> l,
                self.padded[1] >> l,
                self.padded[2] >> l,
            ];
            let mut kind = 0u8;
            for a in 0..3 {
                if c[a] >= half[a] {
                    kind |= 4 >> a;
                }
            }
            if kind != 0 {
                let pos = [
                    c[0] - if kind & 4 != 0 { half[0] } else { 0 },
                    c[1] - if kind & 2 != 0 { half[1] } else { 0 },
                    c[2] - if kind & 1 != 0 { half[2] } else { 0 },
                ];
                return (
                    Band {
                        level: l as u8,
                        kind,
                    },
                    pos,
                );
            }
        }
        (
            Band {
                level: self.levels as u8,
                kind: 0,
            },
            c,
        )
    }

    /// Squared L2 norm of the 3D basis function of `band` (the energy weight of eq. 14):
    /// Π over axes of 2^level · ‖φ or ψ‖².
    pub fn basis_norm2(&self, band: Band) -> f64 {
        let s = (1u64 << band.level) as f64;
        (0..3)
            .map(|a| {
                s * if band.is_wavelet_along(a) {
                    self.family.psi_norm2()
                } else {
                    self.family.phi_norm2()
                }
            })
            .product()
    }

    /// Centre (along one axis, padded-grid voxel units) of the level-`level` basis function with
    /// index `k`, before periodic wrapping: 2^m k + (j/2)(2^m − 1) for φ and
    /// 2^m k + (j/2)(2^(m−1) − 1) + (3j − 2) 2^(m−2) for ψ.
    pub fn raw_center_1d(&self, level: usize, k: usize, wavelet: bool) -> f64 {
        let j = self.family.order() as f64;
        let s = (1u64 << level) as f64;
        if wavelet {
            s * k as f64 + 0.5 * j * (0.5 * s - 1.0) + (3.0 * j - 2.0) * 0.25 * s
        } else {
            s * k as f64 + 0.5 * j * (s - 1.0)
        }
    }

    /// Centre of a basis function in the coordinates of the original volume (voxel (i, j, k) at
    /// (i, j, k)), choosing among its periodic images the one nearest the volume centre.
    pub fn basis_center(&self, band: Band, pos: [usize; 3]) -> [f64; 3] {
        std::array::from_fn(|a| {
            self.basis_center_along(a, band.level as usize, pos[a], band.is_wavelet_along(a))
        })
    }

    /// One coordinate of [`Geometry::basis_center`]: along axis `a`, of the level-`level` φ
    /// (or ψ when `wavelet`) at position `k`.
    pub fn basis_center_along(&self, a: usize, level: usize, k: usize, wavelet: bool) -> f64 {
        let raw = self.raw_center_1d(level, k, wavelet);
        let period = self.padded[a] as f64;
        let centre = self.origin[a] as f64 + 0.5 * (self.dims[a] as f64 - 1.0);
        let wrapped = raw - period * ((raw - centre) / period).round();
        wrapped - self.origin[a] as f64
    }

    /// Support half-width (voxels) along one axis of a level-`level` φ or ψ.
    pub fn half_support_1d(&self, level: usize, wavelet: bool) -> f64 {
        let s = (1u64 << level) as f64;
        0.5 * s
            * if wavelet {
                self.family.psi_support()
            } else {
                self.family.phi_support()
            }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn index_round_trip_covers_every_coefficient_once() {
        for levels in 0..=3 {
            let g = Geometry::new([5, 8, 3], Family::Cubic, levels.min(2), 1).unwrap();
            let n = g.coefficient_count();
            let mut seen = vec![false; n];
            for band in g.bands() {
                let bd = g.band_dims(band);
                for z in 0..bd[2] {
                    for y in 0..bd[1] {
                        for x in 0..bd[0] {
                            let i = g.linear_index(band, [x, y, z]);
                            assert!(!seen[i]);
                            seen[i] = true;
                            assert_eq!(g.locate(i), (band, [x, y, z]));
                        }
                    }
                }
            }
            assert!(seen.iter().all(|s| *s));
        }
    }

    #[test]
    fn padding_and_levels() {
        let g = Geometry::new([5, 7, 9], Family::Haar, 3, 0).unwrap();
        assert_eq!(g.padded, [8, 8, 16]);
        assert_eq!(g.origin, [1, 0, 3]);
        assert_eq!(Geometry::max_levels([1, 100, 100]), 0);
        assert_eq!(Geometry::max_levels([5, 100, 100]), 3);
        assert!(matches!(
            Geometry::new([1, 1, 9], Family::Haar, 1, 0),
            Err(LayoutError::TooManyLevels { .. })
        ));
        assert_eq!(
            Geometry::new([1, 1, 9], Family::Haar, 0, 0).unwrap().padded,
            [1, 1, 9]
        );
        assert_eq!(
            g.band_index(Band { level: 1, kind: 7 }),
            Some(g.band_count() - 1)
        );
        assert_eq!(g.band_index(Band { level: 2, kind: 0 }), None);
    }

    /// A cell is in the padding when its first voxel is: a 10-voxel axis with margin 4 at
    /// level 2 pads to 20 with the box at 5..15, and of the cells starting at 0, 4, 8, 12 and
    /// 16 only 8 and 12 start inside; at level 0 exactly the box's voxels are inside.
    #[test]
    fn cells_in_the_padding_are_those_whose_first_voxel_is_outside_the_box() {
        let g = Geometry::new([10, 10, 10], Family::Linear, 2, 4).unwrap();
        assert_eq!((g.padded, g.origin), ([20; 3], [5; 3]));
        let scaling = Band { level: 2, kind: 0 };
        let outside: Vec<u32> = (0..5)
            .filter(|&i| g.cell_outside_box(scaling, [i, 2, 2]))
            .collect();
        assert_eq!(outside, vec![0, 1, 4]);
        // Any axis outside puts the cell outside.
        assert!(g.cell_outside_box(scaling, [2, 2, 4]));
        let voxels = Band { level: 0, kind: 0 };
        let inside = (0..20)
            .filter(|&i| !g.cell_outside_box(voxels, [i, 7, 7]))
            .count();
        assert_eq!(inside, 10);
    }

    #[test]
    fn haar_centres_sit_between_the_voxels_they_cover() {
        let g = Geometry::new([8, 8, 8], Family::Haar, 3, 0).unwrap();
        // Level-1 function 2 covers voxels 4, 5.
        assert_eq!(g.raw_center_1d(1, 2, true), 4.5);
        assert_eq!(g.raw_center_1d(1, 2, false), 4.5);
        // Level-3 scaling function 0 covers voxels 0..8.
        assert_eq!(g.raw_center_1d(3, 0, false), 3.5);
    }
}
