//! Preparation: the colour transform, padding and spline prefilter, the 3D transform per
//! channel, the oracle's scores and their histogram, the targets and axis views refinement and
//! the depth choice need (`Prepared`); the default margin and the automatic tiling and layering.

use super::options::{default_levels, CompressError, CompressOptions, Stage, TileChoice};
use crate::colorspace::{face_activity, face_median, ColorSpaceKind, ColorTransform};
use crate::refine::{pad_f32, KeptValue, Scratch};
use crate::select::{band_map, histogram, Histogram, Scores, CHUNK};
use crate::visible::Visible;
use rayon::prelude::*;
use wavesplat_codec::dwt::bridge::bridge_padding;
use wavesplat_codec::dwt::{forward_3d, pad_channel, samples_to_coefficients, Dwt1d};
use wavesplat_codec::family::Family;
use wavesplat_codec::format::{ColorInfo, ColorKind};
use wavesplat_codec::layout::{Band, Geometry};
use wavesplat_codec::volume::{Placement, Volume};

/// One scored coefficient.
#[derive(Debug, Clone, Copy)]
pub(super) struct Scored {
    pub(super) score: f64,
    pub(super) channel: u8,
    pub(super) index: u32,
    pub(super) value: f32,
}

/// The transformed volume: dense coefficients per channel and what scores them.
pub(super) struct Prepared {
    pub(super) geometry: Geometry,
    pub(super) margin: usize,
    pub(super) color: ColorInfo,
    pub(super) channels: usize,
    pub(super) value_range: [f32; 2],
    pub(super) placement: Option<Placement>,
    /// Band index of every coefficient (one channel's grid).
    pub(super) band_of: Vec<u8>,
    /// ‖b‖² per band index.
    pub(super) norms: Vec<f64>,
    /// The wavelet coefficients of each channel (Mallat layout).
    pub(super) coefficients: Vec<Vec<f32>>,
    /// Score histogram of the oracle (S = E·I).
    pub(super) histogram: Histogram,
    pub(super) total_energy: f64,
    /// Energy of the coefficients the oracle may keep (score ≥ 0): the total less a bridge's
    /// coefficients wholly outside the box, which are never kept. What a Q_V target and the
    /// reported Q_V are counted against (summed in fixed chunks: thread-count independent).
    pub(super) selectable_energy: f64,
    pub(super) total_coefficients: u64,
    /// The channels' voxel samples after the colour transform on the padded grid (for
    /// refinement; empty without).
    pub(super) targets: Vec<Vec<f32>>,
    /// The three axis X-ray views of each coded channel on the volume's box (for
    /// [`Prepared::view_error`]; empty when no depths are compared).
    pub(super) views: Vec<[Vec<f64>; 3]>,
    /// Non-zero coefficients of the transform.
    pub(super) nonzero: u64,
    /// Grid-sized arrays the refinements and view comparisons on this grid pass on to each
    /// other (fresh ones would fault in their pages every time).
    pub(super) scratch: Scratch,
    /// The seen share of each coefficient's energy, where smooth padding fills a clipped
    /// grid (the oracle then ranks by what is drawn; see [`crate::visible`]).
    pub(super) visible: Option<Visible>,
}

/// Coefficients by decreasing score: a prefix of the oracle's order, or a refined set followed
/// by its extension and the part of the oracle's order that scores below both.
pub(super) struct Ranked {
    pub(super) sorted: Vec<Scored>,
    /// The oracle's order this came from holds every non-zero coefficient (nothing beyond it
    /// could be added).
    pub(super) complete: bool,
    /// The first `refined` entries are least-squares refined values.
    pub(super) refined: usize,
    /// Band and position of the first entries of `sorted`, found as far as an encoding has
    /// asked ([`Ranked::located`]).
    located: std::sync::Mutex<Vec<Located>>,
}

/// A coefficient's band and its position in the band.
pub(super) type Located = (Band, [u32; 3]);

impl Ranked {
    /// `sorted` as a ranking (none of it located yet).
    pub(super) fn new(sorted: Vec<Scored>, complete: bool, refined: usize) -> Ranked {
        Ranked {
            sorted,
            complete,
            refined,
            located: std::sync::Mutex::new(Vec::new()),
        }
    }

    /// Keeps the first `len` entries; what lay beyond could have been added (not complete).
    pub(super) fn truncate(&mut self, len: usize) {
        self.sorted.truncate(len);
        self.complete = false;
        let located = self.located.get_mut().unwrap_or_else(|p| p.into_inner());
        located.truncate(len);
    }

    /// Band and position of at least the first `k` entries of `sorted` on grid `g`. A rate
    /// search codes prefixes of one ranking many times; finding a million coefficients' bands
    /// from their indices took a tenth of each trial, so each is found once.
    pub(super) fn located(
        &self,
        g: &Geometry,
        k: usize,
    ) -> std::sync::MutexGuard<'_, Vec<Located>> {
        let mut done = self.located.lock().unwrap_or_else(|p| p.into_inner());
        let from = done.len();
        if k > from {
            done.par_extend(self.sorted[from..k].par_iter().map(|s| {
                let (band, pos) = g.locate(s.index as usize);
                (band, pos.map(|p| p as u32))
            }));
        }
        done
    }

    /// The first `k` entries as refinement input.
    pub(super) fn top_values(&self, k: usize) -> Vec<KeptValue> {
        self.sorted[..k]
            .iter()
            .map(|s| KeptValue {
                channel: s.channel,
                index: s.index,
                value: s.value,
            })
            .collect()
    }
}

/// Face activity ([`face_activity`]) above which a volume's faces count as cut through its
/// content: between the two groups the test set (`scripts/testset.py`) shows, faces constant
/// up to noise (the MNI variants, the RGB phantoms: 0.00–0.03) and faces cutting through the
/// content (a cropped head 0.19, slabs and CT through the body 0.68–0.93).
pub const STRUCTURED_FACES: f64 = 0.1;

/// The margin when none is given. Where any channel's faces carry structure
/// ([`STRUCTURED_FACES`]), none: zeros around data that does not fall to zero at its faces cost
/// coefficients (2.6–13.7 dB Q_I on the test set's slabs and CT, BENCHMARKS.md), and the
/// renderer clips the basis functions that cross the faces. Where the faces are flat, the
/// separating margin ([`Geometry::separating_margin`]): it costs at most ~0.7 dB there, and
/// every coefficient stays one splat (clipped pieces cost the viewer 2.6–4.4× the render time
/// of a CT volume).
pub fn default_margin(volume: &Volume, family: Family, levels: usize) -> usize {
    margin_for_faces(faces_structured(volume), family, levels)
}

/// Whether any channel's faces carry structure ([`STRUCTURED_FACES`]).
fn faces_structured(volume: &Volume) -> bool {
    (0..volume.channel_count())
        .any(|c| face_activity(volume.channel(c), volume.dims()) > STRUCTURED_FACES)
}

/// [`default_margin`] once the faces are known.
pub(super) fn margin_for_faces(structured: bool, family: Family, levels: usize) -> usize {
    if structured {
        0
    } else {
        Geometry::separating_margin(family, levels)
    }
}

fn color_info(t: &ColorTransform) -> ColorInfo {
    ColorInfo {
        kind: match t.kind {
            ColorSpaceKind::Rgb => ColorKind::Rgb,
            ColorSpaceKind::Yiq => ColorKind::Yiq,
            ColorSpaceKind::Pca => ColorKind::Pca,
        },
        basis: t.basis,
        mean: t.mean,
        importance: t.importance,
    }
}

/// Sample arrays, one per channel.
type Channels = Vec<Vec<f32>>;

/// The channels the transform codes: an RGB volume in its colour space, an intensity volume
/// less its faces' median (`None`: the volume's own channels), with the header's colour info.
pub(super) fn coded_channels(
    volume: &Volume,
    opts: &CompressOptions,
) -> Result<(Option<Channels>, ColorInfo), CompressError> {
    if volume.channel_count() == 3 {
        let t = match &opts.color_transform {
            Some(t) => t.clone(),
            None => ColorTransform::fit(opts.colorspace, volume)?,
        };
        let v = t.forward(volume)?;
        return Ok((Some(v.into_channels()), color_info(&t)));
    }
    // The faces' median is subtracted (see `crate::colorspace`): the padded grid is zero, so a
    // face of air at −1000 would otherwise be a step along the whole face. Samples near
    // ±f32::MAX on both sides of the offset could overflow when shifted; such a volume is
    // coded without one.
    let dims = volume.dims();
    let offset = opts
        .offset
        .unwrap_or_else(|| face_median(volume.channel(0), dims));
    let shifted = (offset != 0.0)
        .then(|| {
            volume
                .channel(0)
                .par_iter()
                .map(|v| (f64::from(*v) - offset) as f32)
                .collect::<Vec<f32>>()
        })
        .filter(|s| s.par_iter().all(|v| v.is_finite()));
    let mut color = ColorInfo::intensity();
    if shifted.is_some() {
        color.mean[0] = offset;
    }
    Ok((shifted.map(|s| vec![s]), color))
}

/// The three axis X-ray views of a channel on its box (sums along x, along y, along z; f64).
///
/// One pass reads each sample once: slices are taken in fixed groups of eight, each group
/// summing its slices' rows (along x) and columns (along y) and its part of the z view; the
/// groups' z views are then added in order, so every sum adds the same terms in the same order
/// whatever the thread count.
pub(crate) fn axis_views(
    dims: [usize; 3],
    at: &(impl Fn(usize, usize, usize) -> f64 + Sync),
) -> [Vec<f64>; 3] {
    let [nx, ny, nz] = dims;
    // Per group of slices: each slice's rows (along x) and columns (along y), and the group's
    // part of the z view.
    type Group = (Vec<(Vec<f64>, Vec<f64>)>, Vec<f64>);
    let zs: Vec<usize> = (0..nz).collect();
    let groups: Vec<Group> = zs
        .par_chunks(8)
        .map(|zs| {
            let mut img = vec![0.0; nx * ny];
            let slices = zs
                .iter()
                .map(|&z| {
                    let mut rows = vec![0.0; ny];
                    let mut cols = vec![0.0; nx];
                    // (`max(1)`: a volume without columns has no lines, not chunks of zero.)
                    for (y, line) in img.chunks_mut(nx.max(1)).enumerate() {
                        let mut a = 0.0;
                        for x in 0..nx {
                            let d = at(x, y, z);
                            a += d;
                            cols[x] += d;
                            line[x] += d;
                        }
                        rows[y] = a;
                    }
                    (rows, cols)
                })
                .collect();
            (slices, img)
        })
        .collect();
    let mut along_x = Vec::with_capacity(ny * nz);
    let mut along_y = Vec::with_capacity(nx * nz);
    let mut images = Vec::with_capacity(groups.len());
    for (slices, img) in groups {
        for (rows, cols) in slices {
            along_x.extend(rows);
            along_y.extend(cols);
        }
        images.push(img);
    }
    [along_x, along_y, sum_in_order(images, nx * ny)]
}

/// The sum of the groups' z views, added in order (the first as it is, each later one added to
/// it term by term), so that every sum adds the same terms in the same order; `len` zeros when
/// there is no group.
fn sum_in_order(images: impl IntoIterator<Item = Vec<f64>>, len: usize) -> Vec<f64> {
    let mut sum: Option<Vec<f64>> = None;
    for img in images {
        match sum.as_mut() {
            None => sum = Some(img),
            Some(a) => a.iter_mut().zip(&img).for_each(|(a, b)| *a += b),
        }
    }
    sum.unwrap_or_else(|| vec![0.0; len])
}

/// What every decomposition depth of one volume shares: the coded channels (`None`: the
/// volume's own), the header's colour info, whether its faces carry structure and, for a depth
/// comparison, the channels' axis views ([`Prepared::views`]). Computed once per compression,
/// not once per depth compared.
pub(super) struct Coded {
    pub(super) transformed: Option<Channels>,
    pub(super) color: ColorInfo,
    pub(super) views: Vec<[Vec<f64>; 3]>,
    /// Whether the volume's faces carry structure (the default margin, [`default_margin`]).
    pub(super) structured_faces: bool,
}

impl Coded {
    /// The channels the transform codes.
    pub(super) fn channels<'a>(&'a self, volume: &'a Volume) -> &'a [Vec<f32>] {
        self.transformed.as_deref().unwrap_or(volume.channels())
    }
}

/// [`coded_channels`], with the axis views when `with_views`.
pub(super) fn code(
    volume: &Volume,
    opts: &CompressOptions,
    with_views: bool,
    progress: &(dyn Fn(Stage, f64) + Sync),
) -> Result<Coded, CompressError> {
    progress(Stage::Color, 0.0);
    let (transformed, color) = coded_channels(volume, opts)?;
    let mut coded = Coded {
        transformed,
        color,
        views: Vec::new(),
        structured_faces: opts.margin.is_none() && faces_structured(volume),
    };
    if with_views {
        let dims = volume.dims();
        coded.views = coded
            .channels(volume)
            .iter()
            .map(|ch| {
                let at =
                    |x: usize, y: usize, z: usize| f64::from(ch[x + dims[0] * (y + dims[1] * z)]);
                axis_views(dims, &at)
            })
            .collect();
    }
    Ok(coded)
}

/// ‖b‖² of each band of `geometry`, by band index (what a score multiplies a coefficient's
/// square by).
pub(crate) fn band_norms(geometry: &Geometry) -> Vec<f64> {
    geometry
        .bands()
        .iter()
        .map(|b| geometry.basis_norm2(*b))
        .collect()
}

/// One depth's decomposition of the `coded` channels of `volume` (with the padded targets of
/// the refinement when `with_targets`), scored for the oracle.
pub(super) fn prepare(
    volume: &Volume,
    opts: &CompressOptions,
    coded: &Coded,
    with_targets: bool,
    progress: &(dyn Fn(Stage, f64) + Sync),
) -> Result<Prepared, CompressError> {
    if !(opts.step.is_finite() && opts.step > 0.0 && opts.step <= 64.0) {
        return Err(CompressError::InvalidOption(format!(
            "quantizer step {}; allowed (0, 64]",
            opts.step
        )));
    }
    let versions = [
        wavesplat_codec::format::LAST_UNPRIMED_VERSION,
        wavesplat_codec::format::PRIORS_VERSION,
        wavesplat_codec::format::COMPACT_HEADER_VERSION,
        wavesplat_codec::format::RANS_VERSION,
        wavesplat_codec::format::VERSION,
    ];
    if !versions.contains(&opts.format_version) {
        return Err(CompressError::InvalidOption(format!(
            "format version {}; {}, {}, {}, {} or {} allowed",
            opts.format_version, versions[0], versions[1], versions[2], versions[3], versions[4]
        )));
    }
    if !(1..=16).contains(&opts.bits) {
        return Err(CompressError::InvalidOption(format!(
            "quantization bits P = {}; allowed 1..=16",
            opts.bits
        )));
    }
    let dims = volume.dims();
    let levels = opts.levels.unwrap_or(default_levels(dims, opts.family));
    let margin = opts
        .margin
        .unwrap_or_else(|| margin_for_faces(coded.structured_faces, opts.family, levels));
    let geometry =
        Geometry::new(dims, opts.family, levels, margin)?.with_spacing(volume.spacing())?;
    let channels = coded.channels(volume);
    let color = coded.color;
    let (lo, hi) = volume.value_range();
    let mut planner = Dwt1d::new(opts.family);
    let norms = band_norms(&geometry);
    let band_of = band_map(&geometry);
    let mut coefficients = Vec::with_capacity(channels.len());
    let bridged = opts.smooth_padding && geometry.clips_to_box();
    let with_targets = opts.refine.is_some() && with_targets;
    let mut targets = Vec::new();
    for (c, ch) in channels.iter().enumerate() {
        opts.stop.check()?;
        progress(Stage::Transform(c), c as f64 / channels.len() as f64);
        let mut data = pad_channel(ch, &geometry);
        if bridged {
            bridge_padding(&mut data, &geometry);
            if with_targets {
                targets.push(data.par_iter().map(|v| *v as f32).collect());
            }
        } else if with_targets {
            targets.push(pad_f32(ch, &geometry));
        }
        samples_to_coefficients(&mut data, &geometry);
        forward_3d(&mut data, &geometry, &mut planner);
        let coded: Vec<f32> = data.into_par_iter().map(|v| v as f32).collect();
        // Samples near ±f32::MAX grow past it in the transform: refused here, not written
        // as a file whose header no reader takes.
        if !coded.par_iter().all(|v| v.is_finite()) {
            return Err(CompressError::CoefficientOverflow {
                largest: f64::from(lo.abs().max(hi.abs())),
            });
        }
        coefficients.push(coded);
    }
    opts.stop.check()?;
    progress(Stage::Sort, 0.0);
    let n = geometry.coefficient_count();
    // Σ w²·‖b‖² in fixed chunks (thread-count independent).
    let per_channel = n.div_ceil(CHUNK);
    let parts: Vec<f64> = (0..coefficients.len() * per_channel)
        .into_par_iter()
        .map(|job| {
            let (c, j) = (job / per_channel, job % per_channel);
            (j * CHUNK..((j + 1) * CHUNK).min(n))
                .map(|i| (coefficients[c][i] as f64).powi(2) * norms[band_of[i] as usize])
                .sum::<f64>()
        })
        .collect();
    let total_energy = parts.iter().sum();
    let mut prepared = Prepared {
        geometry,
        margin,
        color,
        channels: channels.len(),
        value_range: [lo, hi],
        placement: volume.placement().copied(),
        band_of,
        norms,
        coefficients,
        histogram: Histogram::empty(),
        total_energy,
        selectable_energy: 0.0,
        total_coefficients: (n * channels.len()) as u64,
        views: coded.views.clone(),
        targets,
        nonzero: 0,
        scratch: Scratch::default(),
        visible: if bridged {
            Visible::new(&geometry)
        } else {
            None
        },
    };
    let histogram = {
        let p = &prepared;
        histogram(
            p.channels,
            n,
            &PreparedScores(p),
            Some(&|c: usize, i: usize| p.energy(c, i)),
        )
    };
    prepared.nonzero = histogram.positive;
    // Summed over the same chunks in the same order as the total: without a bridge (every
    // non-zero coefficient selectable) the two are the same number.
    prepared.selectable_energy = histogram.selected_energy;
    prepared.histogram = histogram;
    Ok(prepared)
}

/// Expected file size from which [`TileChoice::Auto`] splits the coefficients into two quality
/// layers (one below it). A layer buys a coarse preview of the whole volume before the rest of
/// the file arrives, and costs rate: each layer's packets code their own significance maps
/// (the partition between layers is paid in positions) and learn their models afresh, which
/// the tighter magnitude bounds per layer do not pay back. At equal bytes, one layer against
/// three (growth 16) gained Q_I on every volume of the test set at every size from 0.07 % to
/// 5.85 %: +0.3 to +2.6 dB below 10 KB, +0.02 to +0.7 dB at 10–220 KB, +0.05 to +0.5 dB at
/// 0.35–1 MB; two layers gained less (BENCHMARKS.md, "Quality layers cost rate"). Below this
/// size the whole file crosses a 100 Mbit/s link in about 40 ms, a few frames, so a preview
/// layer is not worth that much; the view-dependent order of a tiled file's packets still
/// gives a spatial progression.
pub(super) const AUTO_TWO_LAYERS_BYTES: u64 = 512 << 10;

/// Shallowest decomposition that gets a coarse layer ([`CompressOptions::coarse_layer`]). At
/// M = 1 the scaling band is an eighth of the voxels and most of a file: not a coarse picture,
/// and its one quantizer range over every score cost the test set's 5.85 % points 3 % of their
/// coefficients (−1.3 dB Q_I) where the score layers' tighter ranges did not (BENCHMARKS.md).
pub const COARSE_LAYER_MIN_LEVELS: usize = 2;

/// Expected file size from which [`TileChoice::Auto`] uses three quality layers.
pub(super) const AUTO_THREE_LAYERS_BYTES: u64 = 4 << 20;

/// Bytes a tile should hold on average under [`TileChoice::Auto`]: a packet pays for the top
/// of its octrees and for its adaptive models learning from scratch, ~2 % of the file at this
/// size (tile 64 against 128 at the 5.85 % point above) and ~8 % at a quarter of it (tile 32).
const AUTO_TILE_BYTES: u64 = 4096;

/// Picks tile size and layer count for an expected file size.
pub(super) fn choose_tiling(
    geometry: &Geometry,
    choice: TileChoice,
    layers: Option<usize>,
    expected_bytes: u64,
) -> (usize, usize) {
    let block = 1usize << geometry.levels;
    let max_dim = *geometry.padded.iter().max().expect("3 dims");
    let single = max_dim.div_ceil(block) * block;
    let count = |t: usize| -> usize { geometry.padded.iter().map(|p| p.div_ceil(t)).product() };
    match choice {
        TileChoice::Single => (single, layers.unwrap_or(1)),
        TileChoice::Size(t) => {
            let t = t.max(1).div_ceil(block) * block;
            (t.min(single), layers.unwrap_or(3))
        }
        TileChoice::Auto => {
            let nl = layers.unwrap_or(match expected_bytes {
                0..AUTO_TWO_LAYERS_BYTES => 1,
                AUTO_TWO_LAYERS_BYTES..AUTO_THREE_LAYERS_BYTES => 2,
                _ => 3,
            });
            let tiles_budget = (expected_bytes / AUTO_TILE_BYTES).max(1) as usize;
            let mut t = block.max(32).next_power_of_two();
            while t < single && count(t) > tiles_budget {
                t *= 2;
            }
            (t.min(single), nl)
        }
    }
}

/// [`Prepared::score`] as a selection's [`Scores`]: a run of coefficients of a clipped grid
/// walks their seen fractions ([`Visible::walk`]) instead of finding each one's position from
/// its index. The same scores, to the bit.
pub(super) struct PreparedScores<'a>(pub(super) &'a Prepared);

impl Scores for PreparedScores<'_> {
    #[inline]
    fn score(&self, c: usize, i: usize) -> f64 {
        self.0.score(c, i)
    }

    #[inline]
    fn for_each(&self, c: usize, range: std::ops::Range<usize>, mut f: impl FnMut(usize, f64)) {
        let p = self.0;
        let Some(visible) = p.visible.as_ref() else {
            for i in range {
                f(i, p.score(c, i));
            }
            return;
        };
        let values = &p.coefficients[c][range.clone()];
        let bands = &p.band_of[range.clone()];
        let mut walk = visible.walk(range.start);
        for ((i, &w), &band) in range.zip(values).zip(bands) {
            let s = if w == 0.0 {
                -1.0
            } else {
                p.score_seen(c, w, band, walk.fraction(band))
            };
            f(i, s);
            walk.advance();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::{axis_views, sum_in_order, Ranked, Scored};
    use rand::{Rng, SeedableRng};
    use wavesplat_codec::family::Family;
    use wavesplat_codec::layout::Geometry;

    /// A ranking's located prefix, grown by several encodings' asks and cut back, is each
    /// entry's band and position as the grid locates it, however far it was asked.
    #[test]
    fn a_rankings_located_prefix_agrees_with_the_grid() {
        let g = Geometry::new([13, 9, 7], Family::Linear, 2, 3).unwrap();
        let n = g.coefficient_count();
        let mut rng = rand::rngs::StdRng::seed_from_u64(5);
        let sorted: Vec<Scored> = (0..500)
            .map(|i| Scored {
                score: 1000.0 - i as f64,
                channel: 0,
                index: rng.gen_range(0..n) as u32,
                value: 1.0,
            })
            .collect();
        let mut ranked = Ranked::new(sorted, false, 0);
        let check = |ranked: &Ranked, k: usize| {
            let located = ranked.located(&g, k);
            assert!(located.len() >= k);
            for (s, &(band, pos)) in ranked.sorted.iter().zip(located.iter()) {
                let (b, p) = g.locate(s.index as usize);
                assert_eq!((band, pos), (b, p.map(|c| c as u32)), "index {}", s.index);
            }
        };
        for k in [0, 17, 17, 3, 240, 500] {
            check(&ranked, k);
        }
        ranked.truncate(100);
        assert!(!ranked.complete);
        assert_eq!(ranked.located(&g, 0).len(), 100);
        check(&ranked, 100);
    }

    /// The three views by plain loops, in the order the one pass must keep: each row along x
    /// and each column along y from zero in sample order, the z view by groups of eight slices
    /// added in order.
    fn plain_views(dims: [usize; 3], at: &dyn Fn(usize, usize, usize) -> f64) -> [Vec<f64>; 3] {
        let [nx, ny, nz] = dims;
        let mut along_x = vec![0.0; ny * nz];
        let mut along_y = vec![0.0; nx * nz];
        for z in 0..nz {
            for y in 0..ny {
                for x in 0..nx {
                    along_x[y + ny * z] += at(x, y, z);
                    along_y[x + nx * z] += at(x, y, z);
                }
            }
        }
        let zs: Vec<usize> = (0..nz).collect();
        let images = zs.chunks(8).map(|group| {
            let mut img = vec![0.0; nx * ny];
            for &z in group {
                for y in 0..ny {
                    for x in 0..nx {
                        img[x + nx * y] += at(x, y, z);
                    }
                }
            }
            img
        });
        [along_x, along_y, sum_in_order(images, nx * ny)]
    }

    #[test]
    fn one_pass_views_equal_plain_sums_bit_for_bit() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(41);
        let shapes = [
            [1, 1, 1],
            [1, 1, 9],
            [7, 1, 3],
            [5, 6, 17],
            [13, 11, 8],
            [4, 9, 24],
            [31, 2, 1],
            [3, 3, 0],
            [0, 4, 2],
        ];
        for dims in shapes {
            let [nx, ny, nz] = dims;
            // Magnitudes over many octaves, so that any change in the order of additions
            // changes some sum's last bits.
            let samples: Vec<f64> = (0..nx * ny * nz)
                .map(|_| rng.gen_range(-1.0..1.0) * 10f64.powi(rng.gen_range(-6..7)))
                .collect();
            let at = |x: usize, y: usize, z: usize| samples[x + nx * (y + ny * z)];
            let fast = axis_views(dims, &at);
            let plain = plain_views(dims, &at);
            for (v, (f, p)) in fast.iter().zip(&plain).enumerate() {
                assert_eq!(f.len(), p.len(), "{dims:?} view {v}");
                for (i, (a, b)) in f.iter().zip(p).enumerate() {
                    assert_eq!(a.to_bits(), b.to_bits(), "{dims:?} view {v} sample {i}");
                }
            }
        }
    }
}
