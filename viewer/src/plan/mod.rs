//! Splat planning: from a view and coefficients to [`SplatRecord`]s in a [`FootprintAtlas`].
//!
//! The [`Planner`] resolves a [`ViewSpec`] into a [`ViewPlan`]: the cameras (one, or the three
//! multiview cameras of §3.1, which share one footprint set by type permutation when the voxel
//! spacing is the same along the axes the permutation swaps, and have a set each otherwise:
//! swapping two axes of differently spaced voxels is not a symmetry of the data), the resolved
//! depth cue, and the footprint tables of the view, flattened into an atlas. Footprint sets are
//! cached per view like RustFFT's planner caches plans. A [`ViewPlan`] turns coefficients into
//! records: each coefficient is projected to its basis centre on the screen, the (level, type)
//! footprint is placed at the nearest subpixel phase (see [`crate::footprint`]) and records whose
//! box misses the screen are counted and dropped. When the geometry's periodic images reach the
//! volume, coefficients are first clipped to its box ([`crate::pieces::BoxClip`]): those wholly
//! inside stay one splat, the others become pieces. With depth cueing the coefficients are split
//! into cued pieces ([`crate::pieces::expand`], or the clip's pieces with their cue weights). The
//! tables of the factor triples that occur are built on first use and appended to the atlas: at
//! once by default, or, for a frame loop that must not stall
//! ([`ViewPlan::build_tables_in_background`]), on a thread of the plan's own while the coefficients
//! that need them wait ([`ViewPlan::take_deferred`]).
//!
//! [`SplatRecord`]: crate::backend::SplatRecord

mod batch;
mod planner;
mod splat;
mod tables;

pub use batch::{SplatBuffers, SPLAT_BATCH};
pub use planner::{Planner, ResolvedView};

use crate::backend::{FootprintAtlas, TableRef};
use crate::footprint::{AxisFactor, FootprintSet};
use crate::pieces::{BoxClip, Expansions};
use rustc_hash::{FxHashMap as HashMap, FxHashSet as HashSet};
use std::sync::{Arc, RwLock, RwLockReadGuard, RwLockWriteGuard};
pub use tables::SharedFactorTables;
use tables::TableBuilder;
use wavesplat_codec::family::Family;
use wavesplat_codec::layout::{Band, Geometry};
use wavesplat_codec::view::{Camera, ResolvedCue, ViewSpec};

/// How a footprint is placed at a splat's exact screen position.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Placement {
    /// The nearest of the S × S subpixel phases (one record per splat; position error up to
    /// 1/(2S) pixel, which adds up coherently where many centres share a phase, e.g. along the
    /// rays of an axis-aligned view).
    Nearest,
    /// The nearest phase plus the first-order correction of the residual: two more records
    /// reading the footprint's gradient tables, weighted by the residual (error second order
    /// in 1/S; three records per splat and three times the table memory).
    Gradient,
}

/// Planning settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlanOptions {
    /// How footprints are placed.
    pub placement: Placement,
    /// Subpixel phases per axis (even; position error ≤ 1/(2S) pixel); `None` takes the
    /// family's default, [`PlanOptions::default_subpixel`].
    pub subpixel: Option<usize>,
    /// Largest FFT side for a footprint (S is halved until the footprint fits); `None` takes
    /// the family's default, [`PlanOptions::default_max_fft`].
    pub max_fft: Option<usize>,
    /// Footprint sets kept in the planner's cache.
    pub cache_size: usize,
    /// Clip coefficients to the volume's box (exact, [`Geometry::splats_clip_to_box`]; see
    /// [`crate::pieces`]). Off, each coefficient is one splat at its image nearest the volume
    /// centre: what a preview draws (no factor tables to wait for).
    pub clip: bool,
}

impl PlanOptions {
    /// Subpixel phases that bring every view to ≥ 50 dB against the exact line integral with
    /// gradient placement: 16 for Haar, whose box edges leave a kink the gradient cannot
    /// correct (S = 8 measured 46.7 dB on a 96² axis view, S = 16 56.8–65.8 dB), 8 for the
    /// smooth splines (66–72 dB). Haar tables are small, so the doubling costs little.
    pub fn default_subpixel(family: Family) -> usize {
        match family {
            Family::Haar => 16,
            _ => 8,
        }
    }

    /// Largest FFT side: 1024 for Haar, 768 for the splines. A Haar footprint wider than
    /// 1024/16 = 64 px (a coarse level on a large image) would otherwise drop to S = 8 and its
    /// box edges cost accuracy (Haar M = 5 on 32³ in a 96² image: 47.7 dB at 768, 66.6 dB at
    /// 1024, for about three times the planning time of that view).
    pub fn default_max_fft(family: Family) -> usize {
        match family {
            Family::Haar => 1024,
            _ => 768,
        }
    }

    /// The largest FFT side used for `family`.
    pub fn max_fft_for(&self, family: Family) -> usize {
        self.max_fft
            .unwrap_or_else(|| Self::default_max_fft(family))
    }

    /// The subpixel phases used for `family` in a view with screen axes `ex`, `ey` per voxel
    /// step (`Camera::index_axes`) at `zoom` pixels per unit of spacing: the requested ones,
    /// else the family's default raised for minified views ([`minified_subpixel`]).
    pub fn subpixel_for_view(
        &self,
        family: Family,
        zoom: f64,
        ex: [f64; 3],
        ey: [f64; 3],
    ) -> usize {
        self.subpixel.unwrap_or_else(|| {
            Self::default_subpixel(family).max(minified_subpixel(family, zoom, ex, ey))
        })
    }
}

/// Table samples per standard deviation of the narrowest footprint a view draws (a level-0
/// φ along every axis, √(j/12) voxels for B-splines of order j, projected), the least a default
/// view's tables take. Where voxels are smaller than pixels the pixel-averaged footprints'
/// sides are as steep as the footprints are narrow, and the phase tables' residual (second
/// order in the sample spacing after the gradient correction) grows as 1/(S·width)². Measured
/// on the axis views of voxel-scale noise against exact line integrals
/// (`axis_views_match_exact_line_integrals_at_every_scale`) at S = 8: linear 55 dB at 0.45
/// pixels per voxel, 42 dB at 0.2, 36 dB at 0.13; cubic 48.6 dB at 0.3. Linear at 0.13 with
/// S = 16 / 32: 55.8 / 63.8 dB. Two samples per deviation keep the default S = 8 from 0.62
/// (linear) and 0.44 (cubic) pixels per voxel up on the axes, less obliquely.
const SAMPLES_PER_DEVIATION: f64 = 2.0;

/// Most phases per axis [`minified_subpixel`] asks for: S = 32 holds the linear family's axis
/// views at 64 dB at 0.13 pixels per voxel; S = 64 would plan a 256³ volume's 48² thumbnail in
/// about four times as long again (S² phases per table).
const MAX_MINIFIED_SUBPIXEL: usize = 32;

/// The S that puts at least `SAMPLES_PER_DEVIATION` (2) samples in a standard deviation of the
/// narrowest footprint of `family` in a view with screen axes `ex`, `ey` per voxel step at
/// `zoom`: a power of two (placing a record then takes a mask and a shift instead of two
/// divisions, `Footprint::place_with_residual`), at most `MAX_MINIFIED_SUBPIXEL` (32); 2 when
/// that width is not a positive number.
pub fn minified_subpixel(family: Family, zoom: f64, ex: [f64; 3], ey: [f64; 3]) -> usize {
    let deviation = (family.order() as f64 / 12.0).sqrt();
    let width = |e: [f64; 3]| zoom * deviation * e.iter().map(|v| v.abs()).sum::<f64>();
    let narrowest = width(ex).min(width(ey));
    if !(narrowest.is_finite() && narrowest > 0.0) {
        return 2;
    }
    let s = (SAMPLES_PER_DEVIATION / narrowest)
        .ceil()
        .min(MAX_MINIFIED_SUBPIXEL as f64) as usize;
    s.next_power_of_two().clamp(2, MAX_MINIFIED_SUBPIXEL)
}

impl Default for PlanOptions {
    fn default() -> Self {
        PlanOptions {
            placement: Placement::Gradient,
            subpixel: None,
            max_fft: None,
            cache_size: 8,
            clip: true,
        }
    }
}

/// Counters of planning (and accumulation, filled in by the caller).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct RenderStats {
    /// Coefficients given.
    pub coefficients: usize,
    /// Splats accumulated (at least partly on screen), summed over views.
    pub splatted: usize,
    /// Splats skipped because their footprint misses the screen.
    pub skipped: usize,
    /// Splats left out because their footprint vanishes in this view (a ψ along the direction
    /// of a view along an axis: [`crate::footprint::VANISHING`]), summed over views.
    pub vanished: usize,
    /// Pixel updates performed.
    pub pixel_updates: u64,
}

/// One view resolved for planning: cameras, cue, footprints (as an atlas).
#[derive(Debug)]
pub struct ViewPlan {
    /// The volume's geometry.
    pub geometry: Geometry,
    /// The view.
    pub spec: ViewSpec,
    /// One camera, or the three multiview cameras.
    pub cameras: Vec<Camera>,
    /// The resolved depth cue.
    pub cue: Option<ResolvedCue>,
    /// Channels of the image.
    pub channels: usize,
    /// Every footprint of the view (grows with cued factor triples); shared by the plans
    /// one planner made with the same footprint sets (a bricked volume's bricks), so each
    /// table is stored, and uploaded to a device, once. Read it with [`ViewPlan::atlas`].
    atlas: SharedAtlas,
    expansions: Option<Expansions>,
    /// Clipping to the box, when the geometry's periodic images reach the volume.
    clip: Option<BoxClip>,
    /// Footprint sets: one shared by every camera, or one per camera.
    sets: Vec<Arc<FootprintSet>>,
    /// Per set, the uncued tables by `level · 8 + kind`.
    tables: Vec<Vec<Option<TableRef>>>,
    /// Per set, the tables of cued pieces by factor triple.
    factor_tables: Vec<HashMap<[AxisFactor; 3], TableRef>>,
    /// The background builder of cued tables, when enabled.
    builder: Option<TableBuilder>,
    /// Factor tables shared with the other plans of the view (a bricked volume's bricks).
    shared_tables: Option<Arc<SharedFactorTables>>,
    /// Indices (into the last `splats` call's coefficients) left out for want of a table.
    deferred: Vec<usize>,
    /// Cued tables built on the calling thread so far.
    built_inline: usize,
    /// Coefficients (band, position, channel) drawn with a stand-in while their cued tables
    /// are built.
    stood_in: HashSet<(Band, [u32; 3], u8)>,
    /// Stand-ins drawn so far.
    stand_ins_drawn: usize,
    /// Uncued tables of the view for stand-ins, by `level · 8 + kind` (empty: no stand-ins).
    stand_in_tables: Vec<Option<TableRef>>,
    /// Basis centres by band and position.
    centres: Centres,
}

/// [`Geometry::basis_center`] tabulated per axis, level and φ/ψ by position, so that planning a
/// coefficient looks its centre up instead of computing it (a division and a `round` per axis,
/// the largest share of the per-coefficient work); the values are the same f64s.
#[derive(Debug, Clone)]
struct Centres {
    /// By `(level · 2 + wavelet) · 3 + axis`: the centre of each position of that band axis.
    along: Vec<Vec<f64>>,
}

impl Centres {
    fn new(geometry: &Geometry) -> Centres {
        let levels = geometry.levels;
        let mut along = Vec::with_capacity((levels + 1) * 6);
        for level in 0..=levels {
            for wavelet in [false, true] {
                for a in 0..3 {
                    let n = geometry.padded[a] >> level;
                    along.push(
                        (0..n)
                            .map(|k| geometry.basis_center_along(a, level, k, wavelet))
                            .collect(),
                    );
                }
            }
        }
        Centres { along }
    }

    /// The centre of a coefficient already checked against the geometry (`check_coefficient`).
    #[inline]
    fn of(&self, band: Band, pos: [u32; 3]) -> [f64; 3] {
        std::array::from_fn(|a| {
            let wavelet = band.is_wavelet_along(a) as usize;
            self.along[(band.level as usize * 2 + wavelet) * 3 + a][pos[a] as usize]
        })
    }
}

/// A cued table request or result: footprint set index and factor triple.
type TableKey = (usize, [AxisFactor; 3]);

/// An atlas shared by plans (see [`ViewPlan::atlas`]). Plans are planned on one thread and
/// drawn on another, so the lock is a `RwLock`; it is taken once per batch, never per splat.
type SharedAtlas = Arc<RwLock<FootprintAtlas>>;

impl ViewPlan {
    /// Every footprint of the view, as the backends read it. The atlas may be shared with
    /// other plans of the view (they only append to it); hold the guard only while drawing.
    pub fn atlas(&self) -> RwLockReadGuard<'_, FootprintAtlas> {
        // Appends leave the atlas whole even if a panic interrupted one between its vectors'
        // pushes (lengths are only read through phases that were completed).
        self.atlas.read().unwrap_or_else(|e| e.into_inner())
    }

    fn atlas_mut(&self) -> RwLockWriteGuard<'_, FootprintAtlas> {
        self.atlas.write().unwrap_or_else(|e| e.into_inner())
    }

    /// Whether this plan and `other` store their tables in one atlas.
    pub fn shares_atlas_with(&self, other: &ViewPlan) -> bool {
        Arc::ptr_eq(&self.atlas, &other.atlas)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The minified rule: the family's default at a pixel per voxel and up, more phases as the
    /// view is minified (powers of two, never fewer for a smaller zoom), capped, and 2 for
    /// widths that are not positive numbers; an explicit request always wins.
    #[test]
    fn minified_views_get_finer_phases() {
        let axis = ([1.0, 0.0, 0.0], [0.0, -1.0, 0.0]);
        let oblique = ([0.6, 0.8, 0.0], [0.48, -0.36, -0.8]);
        let options = PlanOptions::default();
        for family in [Family::Haar, Family::Linear, Family::Cubic] {
            let default = PlanOptions::default_subpixel(family);
            for (ex, ey) in [axis, oblique] {
                assert_eq!(options.subpixel_for_view(family, 1.0, ex, ey), default);
                assert_eq!(options.subpixel_for_view(family, 40.0, ex, ey), default);
                let mut last = 0;
                for zoom in [2.0, 1.0, 0.5, 0.3, 0.2, 0.13, 0.05, 1e-3, 1e-9] {
                    let s = minified_subpixel(family, zoom, ex, ey);
                    assert!(s.is_power_of_two() && s >= last && s <= MAX_MINIFIED_SUBPIXEL);
                    last = s;
                }
                assert_eq!(last, MAX_MINIFIED_SUBPIXEL);
            }
            // The axis view's footprints are the narrower, so it never gets fewer phases.
            assert!(
                minified_subpixel(family, 0.2, axis.0, axis.1)
                    >= minified_subpixel(family, 0.2, oblique.0, oblique.1)
            );
            for zoom in [0.0, -1.0, f64::NAN, f64::INFINITY] {
                assert_eq!(minified_subpixel(family, zoom, axis.0, axis.1), 2, "{zoom}");
            }
            let asked = PlanOptions {
                subpixel: Some(2),
                ..PlanOptions::default()
            };
            assert_eq!(asked.subpixel_for_view(family, 0.01, axis.0, axis.1), 2);
        }
        // Linear axis views: 16 at 0.45 pixels per voxel (55 dB at 8), 32 at 0.13 (36 dB at 8).
        assert_eq!(minified_subpixel(Family::Linear, 0.45, axis.0, axis.1), 16);
        assert_eq!(minified_subpixel(Family::Linear, 0.13, axis.0, axis.1), 32);
    }

    /// The tabulated centres are `Geometry::basis_center`'s values, bit for bit, for every
    /// position of every band: odd, thin and margined grids, each family.
    #[test]
    fn centre_tables_equal_basis_centres() {
        for (dims, family, levels, margin) in [
            ([13, 8, 5], Family::Linear, 2, 3),
            ([1, 1, 1], Family::Haar, 0, 0),
            ([30, 23, 17], Family::Cubic, 2, 8),
            ([64, 4, 9], Family::Haar, 2, 0),
        ] {
            let g = Geometry::new(dims, family, levels, margin).unwrap();
            let centres = Centres::new(&g);
            for band in g.bands() {
                let bd = g.band_dims(band);
                for z in 0..bd[2] {
                    for y in 0..bd[1] {
                        for x in 0..bd[0] {
                            let pos = [x as u32, y as u32, z as u32];
                            let want = g.basis_center(band, [x, y, z]);
                            let got = centres.of(band, pos);
                            assert_eq!(got.map(f64::to_bits), want.map(f64::to_bits));
                        }
                    }
                }
            }
        }
    }
}
