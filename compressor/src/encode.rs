//! The compression pipeline (paper Fig. 10): colour transform → 3D wavelet transform per channel
//! → oracle (score S = E·I, eq. 14; keep the most significant coefficients to meet a target) →
//! quality layers and tiles → significance order with spatial clustering → quantization and
//! entropy coding into packets (`wavesplat_codec::format`).
//!
//! Coefficients are never sorted wholesale: the oracle's order is materialised only for its top
//! candidates ([`crate::select`]). A byte target is met by a rate search on the number of kept
//! coefficients that measures the size the real encoder writes (the estimate is the written
//! size), interpolating log size against log count (typically 3–7 trial encodings); with
//! refinement, one refit of the oracle's set predicts the size of the set to refine, and the
//! refined set is topped up or cut to the target (a second or third refinement only when it
//! lands more than 3 % off, [`refine_to_bytes`]). The encoder returns its own
//! reconstruction (the decoder's view of every kept coefficient), so callers can check a decode
//! bit for bit and compute Q_E without decoding.

use crate::colorspace::{face_activity, face_median, ColorError, ColorSpaceKind, ColorTransform};
use crate::order::{cluster_order, Clustering, Item};
use crate::refine::{pad_f32, refine_with, KeptValue, Output, RefineOptions, Refined};
use crate::select::{band_map, histogram, top_k, Histogram, CHUNK};
use rayon::prelude::*;
use thiserror::Error;
use wavesplat_codec::dwt::fast::FastTransform;
use wavesplat_codec::dwt::{forward_3d, pad_channel, samples_to_coefficients, Dwt1d};
use wavesplat_codec::family::Family;
use wavesplat_codec::format::packet::{encode_packets, Coefficient, PacketInput, SizeBreakdown};
use wavesplat_codec::format::quant::delta_factor;
use wavesplat_codec::format::{
    write_file, CoderKind, ColorInfo, ColorKind, Header, SubstreamParams, MAX_LAYERS,
};
use wavesplat_codec::layout::{Geometry, LayoutError};
use wavesplat_codec::metrics::{q_e_percent, q_v_percent};
use wavesplat_codec::volume::{Placement, Volume};

/// How much to keep.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Target {
    /// Every non-zero coefficient.
    All,
    /// Total file size in bytes (met from below, within 2 % where the granularity allows).
    Bytes(u64),
    /// Fraction (0..=1] of all coefficients.
    Fraction(f64),
    /// Number of coefficients.
    Coefficients(u64),
    /// Smallest set whose energy is at least this percentage of the total (Q_V, eq. 19), the
    /// energy of the coded channels (after the colour transform or intensity offset).
    QvPercent(f64),
}

/// Tile size choice.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum TileChoice {
    /// Chosen from the expected file size so packets are not dominated by framing.
    Auto,
    /// One tile covering the volume and one layer: the paper's single global sequence.
    Single,
    /// Edge length in voxels (rounded up to a multiple of 2^M).
    Size(usize),
}

/// Options of [`compress`]. `Default` gives the recommended settings.
#[derive(Debug, Clone, PartialEq)]
pub struct CompressOptions {
    /// Wavelet family.
    pub family: Family,
    /// Decomposition depth M (`None`: [`default_levels`]; a byte target compares it with one
    /// level less, and shallower ones at high rates, see [`depth_candidates`]).
    pub levels: Option<usize>,
    /// Zero margin in voxels around the volume (`None`: [`default_margin`]). Every margin renders
    /// exactly: below [`Geometry::separating_margin`] the renderer clips basis functions to the
    /// volume's box.
    pub margin: Option<usize>,
    /// Colour space for 3-channel volumes.
    pub colorspace: ColorSpaceKind,
    /// Quantization bits P (1..=16).
    pub bits: u8,
    /// Entropy coder.
    pub coder: CoderKind,
    /// What to keep.
    pub target: Target,
    /// Tiling.
    pub tile: TileChoice,
    /// Score layers, after the coarse layer (`None`: automatic).
    pub layers: Option<usize>,
    /// Each layer holds this many times the coefficients of all layers before it (> 1;
    /// [`LAYER_GROWTH`] by default). Smaller values give a finer coarse-to-fine progression in
    /// file order and bigger files.
    pub layer_growth: f64,
    /// Put each tile's scaling band (the coarsest) in a layer of its own, ahead of the score
    /// layers ([`Header::coarse_layer`]), so that a stream's first packets draw a coarse
    /// picture of the whole volume. Only where that picture is coarse and there is a whole to
    /// draw before the rest: at depths of [`COARSE_LAYER_MIN_LEVELS`] or more and with two
    /// tiles or more (not with [`TileChoice::Single`], the paper's single sequence).
    pub coarse_layer: bool,
    /// Spatial clustering (`None`: pure significance order; Huffman and range coders only).
    pub clustering: Option<Clustering>,
    /// Quantizer step of the sigmap coder, relative to each substream's smallest kept
    /// magnitude (1 = coefficients at the threshold are known to ±½ threshold).
    pub step: f64,
    /// Least-squares refinement of the kept set before quantization (`None`: send the
    /// oracle's coefficients unchanged, as the paper does). See [`crate::refine`].
    pub refine: Option<RefineOptions>,
    /// Refuse to start when [`memory_estimate`] exceeds this many bytes (`None`: no limit).
    pub memory_limit: Option<u64>,
}

impl Default for CompressOptions {
    fn default() -> Self {
        CompressOptions {
            family: Family::Linear,
            levels: None,
            margin: None,
            colorspace: ColorSpaceKind::Pca,
            bits: 8,
            coder: CoderKind::Sigmap,
            target: Target::Fraction(0.05),
            tile: TileChoice::Auto,
            layers: None,
            layer_growth: LAYER_GROWTH,
            coarse_layer: true,
            clustering: Some(Clustering {
                radius: 4,
                threshold: 0.5,
            }),
            step: 1.0,
            refine: Some(RefineOptions::default()),
            memory_limit: None,
        }
    }
}

/// Errors of the compressor.
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum CompressError {
    /// Bad option value.
    #[error("invalid option: {0}")]
    InvalidOption(String),
    /// Geometry problem (levels, size).
    #[error(transparent)]
    Layout(#[from] LayoutError),
    /// Colour transform failed.
    #[error(transparent)]
    Color(#[from] ColorError),
    /// The target cannot be met.
    #[error("target of {target} bytes cannot be met: the smallest file ({minimum} bytes, header and one coefficient) is larger")]
    TargetTooSmall {
        /// Requested bytes.
        target: u64,
        /// Smallest achievable.
        minimum: u64,
    },
    /// The volume needs more working memory than the configured limit.
    #[error(
        "compressing needs about {needed} bytes of memory ({detail}); the limit is {limit} bytes"
    )]
    MemoryLimit {
        /// Estimated peak ([`memory_estimate`]).
        needed: u64,
        /// The configured limit.
        limit: u64,
        /// What dominates the estimate.
        detail: String,
    },
}

/// Stages reported to a progress callback.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stage {
    /// Colour transform.
    Color,
    /// Wavelet transform (channel index).
    Transform(usize),
    /// Scoring and sorting coefficients.
    Sort,
    /// Least-squares refinement of the kept set.
    Refine,
    /// Entropy coding (trial number of the rate search).
    Encode(usize),
    /// A byte target tries this decomposition depth ([`depth_candidates`]); the stages above
    /// then run again for it.
    Depth(usize),
}

/// What the compressor measured.
#[derive(Debug, Clone, PartialEq)]
pub struct CompressStats {
    /// Coefficients in the transform (all channels).
    pub total_coefficients: u64,
    /// Non-zero coefficients.
    pub nonzero_coefficients: u64,
    /// Kept coefficients.
    pub kept: u64,
    /// Q_V (eq. 19), percent.
    pub q_v: f64,
    /// Q_E (eq. 20), percent.
    pub q_e: f64,
    /// File size.
    pub bytes: u64,
    /// Where the bits went.
    pub breakdown: SizeBreakdown,
    /// Header section bytes.
    pub header_bytes: u64,
    /// Number of packets.
    pub packets: u64,
    /// Tile size used.
    pub tile: usize,
    /// Layers used, the coarse layer included.
    pub layers: usize,
    /// Whether layer 0 is the coarse layer ([`Header::coarse_layer`]).
    pub coarse_layer: bool,
    /// The kept values are a least-squares refinement (then Q_V and Q_E are over them, not over
    /// the transform's own coefficients as eq. 19–20 define).
    pub refined: bool,
}

/// A compressed volume.
#[derive(Debug, Clone)]
pub struct Compressed {
    /// The `.wsp` bytes.
    pub bytes: Vec<u8>,
    /// Its header.
    pub header: Header,
    /// Measurements.
    pub stats: CompressStats,
    /// The decoder's view of the kept coefficients, per packet in file order.
    pub reconstruction: Vec<Vec<Coefficient>>,
}

/// One scored coefficient.
#[derive(Debug, Clone, Copy)]
struct Scored {
    score: f64,
    channel: u8,
    index: u32,
    value: f32,
}

/// The transformed volume: dense coefficients per channel and what scores them.
struct Prepared {
    geometry: Geometry,
    margin: usize,
    color: ColorInfo,
    channels: usize,
    value_range: [f32; 2],
    placement: Option<Placement>,
    /// Band index of every coefficient (one channel's grid).
    band_of: Vec<u8>,
    /// ‖b‖² per band index.
    norms: Vec<f64>,
    /// The wavelet coefficients of each channel (Mallat layout).
    coefficients: Vec<Vec<f32>>,
    /// Score histogram of the oracle (S = E·I).
    histogram: Histogram,
    total_energy: f64,
    total_coefficients: u64,
    /// The channels' voxel samples after the colour transform on the padded grid (for
    /// refinement; empty without).
    targets: Vec<Vec<f32>>,
    /// The three axis X-ray views of each coded channel on the volume's box (for
    /// [`Prepared::view_error`]; empty when no depths are compared).
    views: Vec<[Vec<f64>; 3]>,
    /// Non-zero coefficients of the transform.
    nonzero: u64,
}

/// Coefficients by decreasing score: a prefix of the oracle's order, or a refined set followed
/// by its extension and the part of the oracle's order that scores below both.
struct Ranked {
    sorted: Vec<Scored>,
    /// The oracle's order this came from holds every non-zero coefficient (nothing beyond it
    /// could be added).
    complete: bool,
    /// The first `refined` entries are least-squares refined values.
    refined: usize,
}

impl Ranked {
    /// The first `k` entries as refinement input.
    fn top_values(&self, k: usize) -> Vec<KeptValue> {
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
    let structured = (0..volume.channel_count())
        .any(|c| face_activity(volume.channel(c), volume.dims()) > STRUCTURED_FACES);
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
fn coded_channels(
    volume: &Volume,
    opts: &CompressOptions,
) -> Result<(Option<Channels>, ColorInfo), CompressError> {
    if volume.channel_count() == 3 {
        let t = ColorTransform::fit(opts.colorspace, volume)?;
        let v = t.forward(volume)?;
        return Ok((Some(v.into_channels()), color_info(&t)));
    }
    // The faces' median is subtracted (see `crate::colorspace`): the padded grid is zero, so a
    // face of air at −1000 would otherwise be a step along the whole face. Samples near
    // ±f32::MAX on both sides of the offset could overflow when shifted; such a volume is
    // coded without one.
    let dims = volume.dims();
    let offset = face_median(volume.channel(0), dims);
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
fn axis_views(dims: [usize; 3], at: &(dyn Fn(usize, usize, usize) -> f64 + Sync)) -> [Vec<f64>; 3] {
    let [nx, ny, nz] = dims;
    // Along x and along y: each slice z owns its row of both images.
    let (along_x, along_y): (Vec<Vec<f64>>, Vec<Vec<f64>>) = (0..nz)
        .into_par_iter()
        .map(|z| {
            let mut rows = vec![0.0; ny];
            let mut cols = vec![0.0; nx];
            for (y, row) in rows.iter_mut().enumerate() {
                for (x, col) in cols.iter_mut().enumerate() {
                    let d = at(x, y, z);
                    *row += d;
                    *col += d;
                }
            }
            (rows, cols)
        })
        .unzip();
    // Along z: slices summed in fixed groups, then in order (thread-count independent).
    let along_z = (0..nz)
        .collect::<Vec<_>>()
        .par_chunks(8)
        .map(|zs| {
            let mut img = vec![0.0; nx * ny];
            for &z in zs {
                for y in 0..ny {
                    for x in 0..nx {
                        img[x + nx * y] += at(x, y, z);
                    }
                }
            }
            img
        })
        .collect::<Vec<_>>()
        .into_iter()
        .reduce(|mut a, b| {
            a.iter_mut().zip(&b).for_each(|(a, b)| *a += b);
            a
        })
        .unwrap_or_else(|| vec![0.0; nx * ny]);
    [along_x.concat(), along_y.concat(), along_z]
}

fn prepare(
    volume: &Volume,
    opts: &CompressOptions,
    with_views: bool,
    with_targets: bool,
    progress: &(dyn Fn(Stage, f64) + Sync),
) -> Result<Prepared, CompressError> {
    if !(opts.step.is_finite() && opts.step > 0.0 && opts.step <= 64.0) {
        return Err(CompressError::InvalidOption(format!(
            "quantizer step {}; allowed (0, 64]",
            opts.step
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
        .unwrap_or_else(|| default_margin(volume, opts.family, levels));
    let geometry =
        Geometry::new(dims, opts.family, levels, margin)?.with_spacing(volume.spacing())?;
    progress(Stage::Color, 0.0);
    let (transformed, color) = coded_channels(volume, opts)?;
    let channels: &[Vec<f32>] = transformed.as_deref().unwrap_or(volume.channels());
    let (lo, hi) = volume.value_range();
    let mut planner = Dwt1d::new(opts.family);
    let norms: Vec<f64> = geometry
        .bands()
        .iter()
        .map(|b| geometry.basis_norm2(*b))
        .collect();
    let band_of = band_map(&geometry);
    let mut coefficients = Vec::with_capacity(channels.len());
    for (c, ch) in channels.iter().enumerate() {
        progress(Stage::Transform(c), c as f64 / channels.len() as f64);
        let mut data = pad_channel(ch, &geometry);
        samples_to_coefficients(&mut data, &geometry);
        forward_3d(&mut data, &geometry, &mut planner);
        coefficients.push(data.into_par_iter().map(|v| v as f32).collect::<Vec<f32>>());
    }
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
        total_coefficients: (n * channels.len()) as u64,
        views: if with_views {
            channels
                .iter()
                .map(|ch| {
                    let at = |x: usize, y: usize, z: usize| {
                        f64::from(ch[x + dims[0] * (y + dims[1] * z)])
                    };
                    axis_views(dims, &at)
                })
                .collect()
        } else {
            Vec::new()
        },
        targets: if opts.refine.is_some() && with_targets {
            channels.iter().map(|c| pad_f32(c, &geometry)).collect()
        } else {
            Vec::new()
        },
        nonzero: 0,
    };
    let histogram = {
        let p = &prepared;
        histogram(p.channels, n, &|c, i| p.score(c, i), &|c, i| p.energy(c, i))
    };
    prepared.nonzero = histogram.positive;
    prepared.histogram = histogram;
    Ok(prepared)
}

/// Each quality layer holds this many times the coefficients of all layers before it.
///
/// Packets decode on their own, so a layer's significance map cannot lean on the positions of
/// the layers before it: splitting a tile's coefficients into layers costs roughly the entropy
/// of the partition. At the 5.85 % point of the 128³ MNI volume (146 507 coefficients, one
/// tile of 128) two layers cost +4.6 % bytes with growth 4, +2.7 % with 8, +1.8 % with 16,
/// and three layers with growth 16 +1.9 %; growth 16 keeps a coarse-to-fine progression
/// (the first layer is a 1/256 preview at three layers) for a third of the cost of 4.
///
/// The price is a coarser progression for a reader that takes the file in order: the last layer
/// holds 15/16 of each tile, so mid-stream a tile has either all its detail or none of it. On
/// `wavesplat demo` the 16 KB prefix of the 33 KB file scores 41.8 dB Q_I with growth 16, 46.9
/// with 8 (file +3 %) and 50.8 with 4 (4 layers, file +11 %). The cache's view-dependent order
/// softens this; `--layer-growth 4` restores the fine progression where it matters more.
pub const LAYER_GROWTH: f64 = 16.0;

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
const AUTO_TWO_LAYERS_BYTES: u64 = 512 << 10;

/// Shallowest decomposition that gets a coarse layer ([`CompressOptions::coarse_layer`]). At
/// M = 1 the scaling band is an eighth of the voxels and most of a file: not a coarse picture,
/// and its one quantizer range over every score cost the test set's 5.85 % points 3 % of their
/// coefficients (−1.3 dB Q_I) where the score layers' tighter ranges did not (BENCHMARKS.md).
pub const COARSE_LAYER_MIN_LEVELS: usize = 2;

/// Expected file size from which [`TileChoice::Auto`] uses three quality layers.
const AUTO_THREE_LAYERS_BYTES: u64 = 4 << 20;

/// Bytes a tile should hold on average under [`TileChoice::Auto`]: a packet pays for the top
/// of its octrees and for its adaptive models learning from scratch, ~2 % of the file at this
/// size (tile 64 against 128 at the 5.85 % point above) and ~8 % at a quarter of it (tile 32).
const AUTO_TILE_BYTES: u64 = 4096;

/// Picks tile size and layer count for an expected file size.
fn choose_tiling(
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

impl Prepared {
    /// The oracle's score S = E·I of coefficient `i` of channel `c` (−1 for a zero coefficient,
    /// which is never kept).
    fn score(&self, c: usize, i: usize) -> f64 {
        let w = self.coefficients[c][i];
        if w == 0.0 {
            return -1.0;
        }
        (w as f64).powi(2) * self.norms[self.band_of[i] as usize] * self.color.importance[c]
    }

    /// The energy E = w²·‖b‖² (eq. 14, without importance).
    fn energy(&self, c: usize, i: usize) -> f64 {
        (self.coefficients[c][i] as f64).powi(2) * self.norms[self.band_of[i] as usize]
    }

    /// How far a file's three axis X-ray views lie from the volume's: the mean over the views
    /// of ln Σ_c I_c·‖P_v f_c − P_v R ĉ_c‖², with f_c the channel's samples (after the colour
    /// transform or offset; their views are [`Prepared::views`]), ĉ_c the file's decoded
    /// coefficients, R the synthesis to samples, P_v the sum along axis v over the volume's box
    /// and I_c the channel's importance. The log-mean follows Q_I, which averages the views in
    /// dB.
    fn view_error(&self, file: &Compressed) -> f64 {
        let g = &self.geometry;
        let fast = FastTransform::new(g);
        let [px, py, _] = g.padded;
        let [ox, oy, oz] = g.origin;
        let mut energy = [0.0f64; 3];
        for (c, target) in self.views.iter().enumerate() {
            let mut r = vec![0.0f32; g.coefficient_count()];
            for k in file.reconstruction.iter().flatten() {
                if k.channel as usize == c {
                    let pos = [k.pos[0] as usize, k.pos[1] as usize, k.pos[2] as usize];
                    r[g.linear_index(k.band, pos)] = k.value;
                }
            }
            fast.synthesize(&mut r);
            let at = |x: usize, y: usize, z: usize| {
                f64::from(r[(ox + x) + px * ((oy + y) + py * (oz + z))])
            };
            let decoded = axis_views(g.dims, &at);
            let w = self.color.importance[c];
            for ((e, t), d) in energy.iter_mut().zip(target).zip(&decoded) {
                *e += w * t.iter().zip(d).map(|(t, d)| (t - d).powi(2)).sum::<f64>();
            }
        }
        energy
            .iter()
            .map(|e| (e + f64::MIN_POSITIVE).ln())
            .sum::<f64>()
            / 3.0
    }

    /// The oracle's top `cap` coefficients (all non-zero ones when `cap` reaches them).
    fn ranked(&self, cap: usize) -> Ranked {
        let n = self.geometry.coefficient_count();
        let picks = top_k(&self.histogram, self.channels, n, cap, &|c, i| {
            self.score(c, i)
        });
        let sorted: Vec<Scored> = picks
            .into_par_iter()
            .map(|(score, channel, index)| Scored {
                score,
                channel,
                index,
                value: self.coefficients[channel as usize][index as usize],
            })
            .collect();
        Ranked {
            complete: sorted.len() as u64 >= self.nonzero,
            sorted,
            refined: 0,
        }
    }

    /// `ranked` with its top `k` replaced by their least-squares refinement (at most `k`
    /// coefficients, all scoring at least the k-th), followed by up to `extension`
    /// coefficients that would join the refined set next (their values one gradient step from
    /// its fit, see [`Refined::extension`]), then by the rest of `ranked` that scores below
    /// them.
    fn refined(&self, ranked: &Ranked, k: usize, opts: &RefineOptions, extension: usize) -> Ranked {
        let importance = &self.color.importance[..self.channels];
        let Refined {
            kept, extension, ..
        } = self.refine_top(ranked, k, opts, Output::Set { extension });
        let count = kept.len();
        let scored = |r: &KeptValue| {
            let band = self.band_of[r.index as usize] as usize;
            Scored {
                score: (r.value as f64).powi(2) * self.norms[band] * importance[r.channel as usize],
                channel: r.channel,
                index: r.index,
                value: r.value,
            }
        };
        let mut sorted: Vec<Scored> = kept.iter().chain(&extension).map(scored).collect();
        // The rest of the oracle's order, without what the refinement picked up (iterative
        // hard thresholding moves coefficients from beyond rank k into the set) and below the
        // last score so far (the order must stay decreasing).
        let mut picked: Vec<(u8, u32)> = sorted.iter().map(|r| (r.channel, r.index)).collect();
        picked.par_sort_unstable();
        let floor = sorted.last().map_or(f64::INFINITY, |s| s.score);
        sorted.extend(
            ranked.sorted[k..].iter().filter(|s| {
                s.score <= floor && picked.binary_search(&(s.channel, s.index)).is_err()
            }),
        );
        Ranked {
            sorted,
            complete: ranked.complete,
            refined: count,
        }
    }

    /// How many of the top `k` of `ranked` reach the k-th score after one refit
    /// ([`Output::Pilot`]).
    fn pilot(&self, ranked: &Ranked, k: usize, opts: &RefineOptions) -> usize {
        self.refine_top(ranked, k, opts, Output::Pilot)
            .first_survivors
    }

    /// [`refine_with`] on the top `k` of `ranked`, against this volume's padded targets.
    fn refine_top(
        &self,
        ranked: &Ranked,
        k: usize,
        opts: &RefineOptions,
        output: Output,
    ) -> Refined {
        refine_with(
            &self.geometry,
            &self.band_of,
            &self.targets,
            &self.color.importance[..self.channels],
            &ranked.top_values(k),
            opts,
            output,
        )
    }

    /// Encodes the top `k` coefficients of `ranked`. Q_E is left at NaN unless `q_e` is set
    /// (it pairs every kept value with its decoded one, which a rate-search trial skips).
    fn encode(
        &self,
        ranked: &Ranked,
        k: usize,
        opts: &CompressOptions,
        expected_bytes: u64,
        q_e: bool,
    ) -> Compressed {
        let g = &self.geometry;
        let kept = &ranked.sorted[..k];
        let (tile, nl) = choose_tiling(g, opts.tile, opts.layers, expected_bytes);
        let tiles: usize = g.padded.iter().map(|p| p.div_ceil(tile)).product();
        let coarse_layer = opts.coarse_layer
            && g.levels >= COARSE_LAYER_MIN_LEVELS
            && tiles >= 2
            && !matches!(opts.tile, TileChoice::Single);
        // The score layers (after the coarse layer, when there is one).
        let nl = nl.clamp(1, MAX_LAYERS - usize::from(coarse_layer));
        let first_score_layer = usize::from(coarse_layer);
        let locate = |s: &Scored| g.locate(s.index as usize);
        let in_coarse_layer = |s: &Scored| coarse_layer && locate(s).0.kind == 0;
        // What the score layers split: the kept coefficients outside the coarse layer, in
        // significance order.
        let ranked_rest: Vec<&Scored> = kept.iter().filter(|s| !in_coarse_layer(s)).collect();
        let kr = ranked_rest.len();
        // Score layer l ends at rank k·G^(l−(L−1)) with G the layer growth: layer 0 holds the
        // top k/G^(L−1).
        let mut ends = Vec::with_capacity(nl);
        for l in 0..nl {
            let frac = opts.layer_growth.powi(l as i32 - (nl as i32 - 1));
            ends.push(((kr as f64 * frac).ceil() as usize).clamp(1.min(kr), kr));
        }
        let mut layer_bounds = vec![f64::INFINITY; first_score_layer];
        let mut start = 0usize;
        for (l, end) in ends.iter().enumerate() {
            let bound = if l == 0 || start >= kr {
                f64::INFINITY
            } else {
                ranked_rest[start].score
            };
            layer_bounds.push(bound.min(layer_bounds.last().copied().unwrap_or(f64::INFINITY)));
            start = (*end).max(start);
        }
        let nb = g.band_count();
        let nsub = self.channels * nb;
        // Substream parameters: w0 = largest magnitude, Δ from the sorted magnitudes (eq. 15).
        let mut mags: Vec<Vec<f64>> = vec![Vec::new(); nsub];
        for s in kept {
            let (band, _) = locate(s);
            let sub = s.channel as usize * nb + g.band_index(band).expect("band");
            mags[sub].push((s.value as f64).abs());
        }
        // Smallest kept score: every kept coefficient's magnitude is at least the threshold.
        let score_threshold = kept.last().map_or(0.0, |s| s.score);
        let substreams: Vec<Option<SubstreamParams>> = mags
            .iter()
            .enumerate()
            .map(|(sub, m)| {
                (!m.is_empty()).then(|| {
                    let delta = if opts.coder.quantizes_by_threshold() {
                        let band = g.bands()[sub % nb];
                        let weight = g.basis_norm2(band) * self.color.importance[sub / nb];
                        let t = if weight > 0.0 {
                            (score_threshold / weight).sqrt()
                        } else {
                            0.0
                        };
                        // Floor the step at 2^-30 of the largest magnitude so q stays small
                        // even when near-zero coefficients are kept (Target::All).
                        (opts.step * t).max(m[0] * 2f64.powi(-30))
                    } else {
                        delta_factor(m, opts.bits)
                    };
                    SubstreamParams {
                        w0: m[0] as f32,
                        delta: delta as f32,
                    }
                })
            })
            .collect();
        let mut header = Header {
            geometry: *g,
            margin: self.margin,
            placement: self.placement,
            channels: self.channels,
            color: self.color,
            value_range: self.value_range,
            coder: opts.coder,
            bits: opts.bits,
            tile,
            layer_bounds,
            coarse_layer,
            score_threshold,
            substreams,
            tables: None,
            fast_tables: None,
            total_energy: self.total_energy,
            kept: k as u64,
            version: wavesplat_codec::format::VERSION,
        };
        // Group by (layer, tile), keeping significance order inside each group.
        let mut groups: std::collections::BTreeMap<(usize, usize), Vec<(Scored, Coefficient)>> =
            Default::default();
        let mut score_layer = 0usize;
        let mut rank = 0usize;
        for s in kept {
            let layer = if in_coarse_layer(s) {
                0
            } else {
                while rank >= ends[score_layer] {
                    score_layer += 1;
                }
                rank += 1;
                first_score_layer + score_layer
            };
            let (band, pos) = locate(s);
            let t = header.tile_of(band, pos);
            let c = Coefficient {
                channel: s.channel,
                band,
                pos: [pos[0] as u32, pos[1] as u32, pos[2] as u32],
                value: s.value,
            };
            groups.entry((layer, t)).or_default().push((*s, c));
        }
        let inputs: Vec<PacketInput> = groups
            .into_par_iter()
            .map(|((layer, tile), list)| {
                let items: Vec<Item> = list
                    .iter()
                    .map(|(s, c)| {
                        let l = c.band.level as u32;
                        Item {
                            score: s.score,
                            voxel: [c.pos[0] << l, c.pos[1] << l, c.pos[2] << l],
                        }
                    })
                    .collect();
                // The sigmap and fast coders code positions as octree maps, so the order
                // inside a packet carries no cost and clustering is skipped.
                let clustering = opts
                    .clustering
                    .filter(|_| !opts.coder.quantizes_by_threshold());
                let order = cluster_order(&items, clustering);
                PacketInput {
                    tile,
                    layer,
                    coefficients: order.into_iter().map(|i| list[i].1).collect(),
                }
            })
            .collect();
        let encoded = encode_packets(&mut header, &inputs);
        let bytes = write_file(&header, &encoded.packets);
        let header_bytes = wavesplat_codec::format::write_header_section(&header).len() as u64;
        // Q_E over the kept coefficients (importance-free energies, eq. 20–21). The sigmap coder
        // reorders coefficients within a packet, so pair exact and decoded values by address.
        let key = |c: &Coefficient| {
            let p = [c.pos[0] as usize, c.pos[1] as usize, c.pos[2] as usize];
            (c.channel, g.linear_index(c.band, p))
        };
        let q_e = if q_e {
            let mut exact: Vec<&Coefficient> =
                inputs.iter().flat_map(|i| &i.coefficients).collect();
            let mut decoded: Vec<&Coefficient> = encoded.reconstruction.iter().flatten().collect();
            exact.par_sort_unstable_by_key(|c| key(c));
            decoded.par_sort_unstable_by_key(|c| key(c));
            q_e_percent(
                exact
                    .iter()
                    .zip(&decoded)
                    .map(|(a, b)| (a.value as f64, b.value as f64, g.basis_norm2(a.band))),
            )
        } else {
            f64::NAN
        };
        let kept_energy: f64 = kept
            .iter()
            .map(|s| (s.value as f64).powi(2) * self.norms[self.band_of[s.index as usize] as usize])
            .sum();
        let stats = CompressStats {
            total_coefficients: self.total_coefficients,
            nonzero_coefficients: self.nonzero,
            kept: k as u64,
            q_v: q_v_percent(kept_energy, self.total_energy),
            q_e,
            bytes: bytes.len() as u64,
            breakdown: encoded.breakdown,
            header_bytes,
            packets: inputs.len() as u64,
            tile,
            layers: nl + first_score_layer,
            coarse_layer,
            refined: ranked.refined > 0 && k > 0,
        };
        Compressed {
            bytes,
            header,
            stats,
            reconstruction: encoded.reconstruction,
        }
    }
}

/// The peak memory [`compress`] needs for a volume of `dims` × `channels` with `opts`, in bytes,
/// counting the input volume (f32 samples) and, per coefficient of the padded grid: the f64
/// transform of one channel (8 B), the f32 coefficients (4 B per channel), the band map (1 B)
/// and, with refinement, the padded targets, values, gradients and mask (13 B per channel)
/// plus two work arrays (8 B); then the candidate list and the encoder's per-coefficient
/// copies (~200 B per candidate). A byte target that compares two depths holds two
/// transforms at once. Measured peaks stay below it (BENCHMARKS.md, issue 14).
pub fn memory_estimate(
    dims: [usize; 3],
    channels: usize,
    opts: &CompressOptions,
) -> Result<(u64, String), CompressError> {
    let levels = opts.levels.unwrap_or(default_levels(dims, opts.family));
    // The larger grid of the two defaults (see `default_margin`): an upper bound.
    let margin = opts
        .margin
        .unwrap_or_else(|| Geometry::separating_margin(opts.family, levels));
    let g = Geometry::new(dims, opts.family, levels, margin)?;
    let n = g.coefficient_count() as u64;
    let v = dims.iter().map(|d| *d as u64).product::<u64>();
    let c = channels as u64;
    let input = 4 * v * c;
    // The colour transform's output, or an intensity volume's shifted copy (its offset).
    let colour = 4 * v * c;
    let refining = opts.refine.is_some() && opts.family != Family::Haar;
    // Held from the transform to the end: coefficients, band map, padded targets.
    let persistent = 4 * n * c + n + if refining { 4 * n * c } else { 0 };
    // A byte target without a given depth compares two ([`depth_candidates`]): both
    // transforms are held while the second one is scored (without padded targets; the
    // shallower grid is never the larger one), and the scoring synthesizes one channel.
    let comparing =
        matches!(opts.target, Target::Bytes(_)) && depth_candidates(dims, opts).len() > 1;
    let held = if comparing {
        persistent.max(2 * (4 * n * c + n) + 4 * n)
    } else {
        persistent
    };
    let all = n * c;
    let candidates = match opts.target {
        Target::Bytes(b) => b.saturating_mul(4).min(all),
        Target::Fraction(f) => ((2.0 * f * all as f64) as u64).min(all),
        Target::Coefficients(k) => k.saturating_mul(2).min(all),
        Target::All | Target::QvPercent(_) => all,
    };
    // Candidate lists of 24 B an entry held at once by a byte target's search: the oracle's
    // order, its grown copy, the refined order being tried and the best one so far (4 × 24 B),
    // plus the refined set's sorted (channel, index) pairs (8 B). Counting two lists instead
    // put the estimate 11 % under the measured peak of a 512³ volume (5.25 GB against 5.92).
    let lists = candidates.saturating_mul(104);
    let prepare = colour + 8 * n + (32 << 20);
    let refine = if refining { 9 * n * c + 8 * n } else { 0 };
    // Packet inputs, clustering items, reconstruction and Q_E pairs per kept coefficient; the
    // fast coder also holds every packet's symbols (8 B, about 1.3 per coefficient) while it
    // fits its tables.
    let per_kept = if opts.coder == CoderKind::Fast {
        161
    } else {
        150
    };
    let encode = (candidates / 2).saturating_mul(per_kept);
    // The binary, the thread pool and small tables: ~30 MB measured on a 128³ volume.
    let base = 64 << 20;
    let total = base + input + held + prepare.max(lists + refine.max(encode));
    let detail = format!(
        "{} coefficients per channel on the padded {}x{}x{} grid, {} channel(s){}",
        n,
        g.padded[0],
        g.padded[1],
        g.padded[2],
        channels,
        if refining { ", refined" } else { "" }
    );
    Ok((total, detail))
}

/// Compresses a volume. `progress(stage, fraction)` is called as work proceeds.
pub fn compress(
    volume: &Volume,
    opts: &CompressOptions,
    progress: &(dyn Fn(Stage, f64) + Sync),
) -> Result<Compressed, CompressError> {
    let (needed, detail) = memory_estimate(volume.dims(), volume.channel_count(), opts)?;
    tracing::debug!(bytes = needed, detail, "memory estimate");
    if let Some(limit) = opts.memory_limit {
        if needed > limit {
            return Err(CompressError::MemoryLimit {
                needed,
                limit,
                detail,
            });
        }
    }
    if !(opts.layer_growth.is_finite() && opts.layer_growth > 1.0) {
        return Err(CompressError::InvalidOption(format!(
            "layer growth {}; allowed: a finite number above 1",
            opts.layer_growth
        )));
    }
    if let Target::Bytes(b) = opts.target {
        return compress_to_bytes(volume, opts, b, progress);
    }
    let prepared = prepare(volume, opts, false, true, progress)?;
    let n = prepared.nonzero as usize;
    let k = match opts.target {
        Target::All => n,
        Target::Coefficients(c) => (c as usize).min(n),
        Target::Fraction(f) => {
            if !(f > 0.0 && f <= 1.0) {
                return Err(CompressError::InvalidOption(format!(
                    "target fraction {f}; allowed (0, 1]"
                )));
            }
            ((f * prepared.total_coefficients as f64).round() as usize).min(n)
        }
        Target::QvPercent(q) => {
            if !(q > 0.0 && q <= 100.0) {
                return Err(CompressError::InvalidOption(format!(
                    "target Q_V {q} %; allowed (0, 100]"
                )));
            }
            // Energies (without importance) accumulated in score order.
            let goal = q / 100.0 * prepared.total_energy;
            let cap = prepared.histogram.count_for_energy(goal) as usize;
            let ranked = prepared.ranked(cap);
            let mut acc = 0.0;
            let mut k = ranked.sorted.len();
            for (i, s) in ranked.sorted.iter().enumerate() {
                acc += (s.value as f64).powi(2)
                    * prepared.norms[prepared.band_of[s.index as usize] as usize];
                if acc >= goal * (1.0 - 1e-12) {
                    k = i + 1;
                    break;
                }
            }
            k
        }
        Target::Bytes(b) => return compress_to_bytes(volume, opts, b, progress),
    };
    let ranked = prepared.ranked(k);
    let ranked = match &opts.refine {
        Some(r) if k > 0 && k < n => {
            progress(Stage::Refine, 0.0);
            // The refined set is the file: nothing tops it up.
            prepared.refined(&ranked, k, r, 0)
        }
        _ => ranked,
    };
    let k = k.min(ranked.sorted.len());
    progress(Stage::Encode(0), 0.0);
    let expected = (k as u64)
        .saturating_mul(bytes_per_coefficient_guess(opts.coder))
        .max(64);
    Ok(prepared.encode(&ranked, k, opts, expected, true))
}

/// File size guess per kept coefficient for the automatic tiling: measured bytes per kept
/// coefficient are ~0.7–0.9 for the sigmap coder (~0.1 more for the fast coder) and 2–3 for
/// the paper's syntaxes.
fn bytes_per_coefficient_guess(coder: CoderKind) -> u64 {
    if coder.quantizes_by_threshold() {
        1
    } else {
        3
    }
}

/// The decomposition depth M when none is given: min(6, maximum) for Haar, min(3, maximum)
/// for linear, min(2, maximum) for cubic (whose coarse supports grow as (2j − 1)·2^M). A byte
/// target also tries one level less ([`depth_candidates`]).
pub fn default_levels(dims: [usize; 3], family: Family) -> usize {
    let max_levels = Geometry::max_levels(dims);
    match family {
        Family::Haar => max_levels.min(6),
        Family::Linear => max_levels.min(3),
        Family::Cubic => max_levels.min(2),
    }
}

/// The depths a byte target compares first when none is given: the family's default
/// ([`default_levels`]) and, when it is at least 2, one level less (then shallower ones while
/// the shallowest wins and its file affords the next coarse band, [`worth_going_shallower`]). Which one codes a volume
/// better depends on the rate and on the data: on the test set (BENCHMARKS.md, issue 14) the
/// shallower depth gains 0.5–1.3 dB Q_I at 1.25–5.85 % on most volumes and loses up to 38 dB
/// at 0.07 % (a coarse band too large to afford), while a CT volume keeps preferring the
/// deeper one at every rate; a deeper one than the default never won.
fn depth_candidates(dims: [usize; 3], opts: &CompressOptions) -> Vec<usize> {
    match opts.levels {
        Some(m) => vec![m],
        None => {
            let d = default_levels(dims, opts.family);
            if d >= 2 {
                vec![d, d - 1]
            } else {
                vec![d]
            }
        }
    }
}

/// A byte target whose file at depth M keeps at least this share of the coefficients the
/// coarse band of depth M − 1 would hold (per channel) tries M − 1 too: a band 8× larger
/// than M's only pays once the budget nearly affords it. On the test set at M = 2 against
/// M = 1 (refined files, Q_I): the MNI volume plus an offset and its 16-bit variant at 5.85 %
/// (ratio 1.0) gain 2.0–2.1 dB at M = 1; the slabs and aniso at 5.85 % (0.65) lose 0.5–2.3 dB,
/// the RGB phantom at 5.85 % (0.57) 0.4 dB (and its oracle files' views ranked M = 1 first),
/// the first two at 1.25 % (0.24) 1.3 dB, the MNI volume at 1.25 % (0.12) 6 dB.
const SHALLOWER_KEPT: f64 = 0.8;

/// Whether a file of `kept` coefficients over `channels` at `geometry`'s depth M makes depth
/// M − 1 worth a try ([`SHALLOWER_KEPT`]; never below M = 1).
pub fn worth_going_shallower(kept: u64, channels: usize, geometry: &Geometry) -> bool {
    let m = geometry.levels;
    if m < 2 || channels == 0 {
        return false;
    }
    // The coarse band of M − 1 on this grid (the shallower grid is at most this large).
    let coarse = geometry.coefficient_count() as f64 / 8f64.powi(m as i32 - 1);
    kept as f64 / channels as f64 >= SHALLOWER_KEPT * coarse
}

/// Byte target. Per candidate depth ([`depth_candidates`]) the oracle's order is searched for
/// the largest prefix that fits ([`oracle_to_bytes`]) and that file's three axis X-ray views
/// are compared with the volume's ([`Prepared::view_error`]); the depth whose views come closer
/// is kept (the default on a tie); while the shallowest depth compared wins and its file
/// affords the next coarse band ([`worth_going_shallower`]), one level less is compared too.
/// The oracle's ranking of depths predicted the refined files' ranking at all but one point
/// measured (BENCHMARKS.md), at the cost of one more oracle pass per depth. With refinement,
/// [`refine_to_bytes`] then starts from the chosen prefix's size.
fn compress_to_bytes(
    volume: &Volume,
    opts: &CompressOptions,
    target: u64,
    progress: &(dyn Fn(Stage, f64) + Sync),
) -> Result<Compressed, CompressError> {
    let depths = depth_candidates(volume.dims(), opts);
    let comparing = depths.len() > 1;
    let mut trials = 0usize;
    let mut best: Option<(f64, Prepared, Ranked, Compressed)> = None;
    let mut too_small: Option<CompressError> = None;
    let mut depths = depths;
    let mut next = 0;
    while next < depths.len() {
        let m = depths[next];
        next += 1;
        let o = CompressOptions {
            levels: Some(m),
            ..opts.clone()
        };
        // Compared depths hold no padded targets (the scoring needs only the views): two
        // transforms are held at once, and the winner's targets are built afterwards.
        if comparing {
            progress(Stage::Depth(m), 0.0);
        }
        let prepared = prepare(volume, &o, comparing, !comparing, progress)?;
        // A target too small for one depth may fit the other (their headers and coarse bands
        // differ); it is an error only when it fits neither.
        let (ranked, plain) = match oracle_to_bytes(&prepared, &o, target, &mut trials, progress) {
            Ok(found) => found,
            Err(e @ CompressError::TargetTooSmall { .. }) if comparing => {
                tracing::debug!(levels = m, error = %e, "depth candidate does not fit");
                // The error names the smallest file of any depth.
                let smaller = |a: &CompressError, b: &CompressError| match (a, b) {
                    (
                        CompressError::TargetTooSmall { minimum: x, .. },
                        CompressError::TargetTooSmall { minimum: y, .. },
                    ) => x < y,
                    _ => false,
                };
                if too_small.as_ref().is_none_or(|t| smaller(&e, t)) {
                    too_small = Some(e);
                }
                continue;
            }
            Err(e) => return Err(e),
        };
        if !comparing {
            best = Some((0.0, prepared, ranked, plain));
            break;
        }
        let error = prepared.view_error(&plain);
        tracing::debug!(
            levels = m,
            bytes = plain.stats.bytes,
            kept = plain.stats.kept,
            view_error = error,
            "depth candidate"
        );
        if best.as_ref().is_none_or(|b| error < b.0) {
            best = Some((error, prepared, ranked, plain));
        }
        // The shallowest depth so far won: one level less may be better still, when its
        // coarse band is affordable.
        if next == depths.len() {
            if let Some((_, p, _, c)) = &best {
                if p.geometry.levels == m
                    && worth_going_shallower(c.stats.kept, p.channels, &p.geometry)
                {
                    depths.push(m - 1);
                }
            }
        }
    }
    let Some((_, mut prepared, ranked, plain)) = best else {
        return Err(too_small.unwrap_or_else(|| {
            CompressError::InvalidOption("no decomposition depth to try".to_string())
        }));
    };
    prepared.views = Vec::new();
    if comparing && opts.refine.is_some() {
        let (transformed, _) = coded_channels(volume, opts)?;
        let channels: &[Vec<f32>] = transformed.as_deref().unwrap_or(volume.channels());
        prepared.targets = channels
            .iter()
            .map(|c| pad_f32(c, &prepared.geometry))
            .collect();
    }
    let k0 = plain.stats.kept as usize;
    let Some(r) = &opts.refine else {
        return Ok(finish(&prepared, &ranked, plain));
    };
    if k0 == 0 || (ranked.complete && k0 >= ranked.sorted.len()) {
        return Ok(finish(&prepared, &ranked, plain));
    }
    refine_to_bytes(
        &prepared,
        ranked,
        plain,
        r,
        opts,
        target,
        &mut trials,
        progress,
    )
}

/// The oracle's order searched for the largest prefix that fits `target` bytes, on a candidate
/// list grown 4× whenever the search runs off its end.
fn oracle_to_bytes(
    prepared: &Prepared,
    opts: &CompressOptions,
    target: u64,
    trials: &mut usize,
    progress: &(dyn Fn(Stage, f64) + Sync),
) -> Result<(Ranked, Compressed), CompressError> {
    let n = prepared.nonzero as usize;
    // Candidates: 4 per target byte for the sigmap and fast coders (they code ~1.1–1.5
    // coefficients per byte on real data), 1 per byte for the paper's syntaxes.
    let per_byte = if opts.coder.quantizes_by_threshold() {
        4
    } else {
        1
    };
    let mut cap = (target.saturating_mul(per_byte) as usize)
        .max(1024)
        .min(n.max(1));
    let guess = (target / bytes_per_coefficient_guess(opts.coder)) as usize;
    loop {
        let ranked = prepared.ranked(cap);
        let search = RateSearch {
            target,
            guess,
            known: None,
        };
        let plain = fit_bytes(prepared, &ranked, opts, search, trials, progress)?;
        let len = ranked.sorted.len();
        if ranked.complete || (plain.stats.kept as usize) < len || cap >= n {
            return Ok((ranked, plain));
        }
        cap = cap.saturating_mul(4).min(n);
    }
}

/// Refinements a byte target may run (each is ~36 applications of the synthesis and its
/// transpose; the rate searches between them only run the entropy coder).
const MAX_REFINEMENTS: usize = 3;

/// A whole refined set this close to the target ends the search: one below it is topped up
/// with the coefficients that would join it next ([`Refined::extension`]), one above it cut to
/// the target. Measured on the MNI volume at 1.25 % against a set refined to fill the target
/// (Q_I 91.80): topping up 1.8 % or 5 % of the bytes gave 91.84 and 91.74, cutting 4 % 91.78
/// (8 %: 91.70, 13 %: 91.57); on mni-offset at 5.85 % a 4.4 % cut lost 0.17 dB. Another
/// refinement costs as much as the first.
const CLOSE_BELOW: f64 = 0.97;
const CLOSE_ABOVE: f64 = 1.03;

/// The byte target's refinement: a refined set codes at a different size from the oracle's
/// prefix it came from (usually smaller: refitted values are smaller and about a fifth of them
/// are pruned), and neither cutting it to the target nor topping it up by much is as good as
/// refining a set of the right size. So the size K of the first set comes from one refit of
/// the oracle's set ([`predicted_set_size`]), the refined set of K is encoded whole, and
/// while it misses the target by more than [`CLOSE_BELOW`]–[`CLOSE_ABOVE`], K is moved by a
/// secant step on log size against log K ([`next_set_size`]), for at most
/// [`MAX_REFINEMENTS`] refinements. A set within that window is topped up or cut to the target
/// (unless it already fills 98.5–100 %). Otherwise the fullest candidate is kept (a whole set,
/// an overflowing set cut to the target, or on the last attempt the set topped up), unless it
/// fills less than 98 % of the target and less than the unrefined file, which is then kept
/// instead.
#[allow(clippy::too_many_arguments)]
fn refine_to_bytes(
    prepared: &Prepared,
    ranked: Ranked,
    plain: Compressed,
    r: &RefineOptions,
    opts: &CompressOptions,
    target: u64,
    trials: &mut usize,
    progress: &(dyn Fn(Stage, f64) + Sync),
) -> Result<Compressed, CompressError> {
    let n = prepared.nonzero as usize;
    let goal = 0.99 * target as f64;
    // (K, bytes of the whole refined set of K), by K.
    let mut sizes: Vec<(usize, u64)> = Vec::new();
    let mut best: Option<(Compressed, Ranked)> = None;
    let fuller = |best: &Option<(Compressed, Ranked)>, c: &Compressed| {
        best.as_ref()
            .is_none_or(|(b, _)| c.stats.bytes > b.stats.bytes)
    };
    let k0 = plain.stats.kept as usize;
    progress(Stage::Refine, 0.0);
    let mut k = predicted_set_size(
        k0,
        plain.stats.bytes,
        prepared.pilot(&ranked, k0, r),
        target,
        n,
    );

    // The oracle's order, grown when K needs more candidates (`ranked` stays `plain`'s).
    let mut candidates: Option<Ranked> = None;
    for attempt in 0..MAX_REFINEMENTS {
        // The refinement reads the top K; the oracle's order beyond its extension follows.
        let wanted = (k + k / 4).min(n);
        let source = candidates.as_ref().unwrap_or(&ranked);
        if source.sorted.len() < wanted && !source.complete {
            candidates = Some(prepared.ranked(wanted));
        }
        let source = candidates.as_ref().unwrap_or(&ranked);
        progress(Stage::Refine, attempt as f64 / MAX_REFINEMENTS as f64);
        let k_set = k.min(source.sorted.len());
        let refined = prepared.refined(source, k_set, r, k_set.div_ceil(4));
        let count = refined.refined;
        if count == 0 {
            break;
        }
        *trials += 1;
        progress(Stage::Encode(*trials), 0.0);
        let whole = prepared.encode(&refined, count, opts, target, false);
        let bytes = whole.stats.bytes;
        tracing::debug!(k, count, bytes, target, "refined set encoded whole");
        sizes.push((k, bytes));
        let last = attempt + 1 == MAX_REFINEMENTS;
        let close = close_to_target(bytes, target);
        // Close to the target, or out of refinements: top the set up with the coefficients
        // that would join it next, or cut it to the target.
        let fit = |whole: Compressed, trials: &mut usize| {
            let search = RateSearch {
                target,
                guess: count,
                known: Some(whole),
            };
            fit_bytes(prepared, &refined, opts, search, trials, progress)
        };
        let candidate = if bytes <= target {
            if (bytes as f64) < 0.985 * target as f64 && (last || close) {
                fit(whole, trials)
            } else {
                Ok(whole)
            }
        } else {
            fit(whole, trials)
        };
        // A refined set that cannot be cut to the target leaves the oracle's file standing.
        let Ok(candidate) = candidate else {
            break;
        };
        if fuller(&best, &candidate) {
            best = Some((candidate, refined));
        }
        if close {
            break;
        }
        let next = next_set_size(&sizes, goal, n);
        if sizes.iter().any(|&(sk, _)| sk == next) {
            break;
        }
        k = next;
    }
    match best {
        Some((b, refined))
            if b.stats.bytes as f64 >= 0.98 * target as f64
                || b.stats.bytes >= plain.stats.bytes =>
        {
            Ok(finish(prepared, &refined, b))
        }
        _ => Ok(finish(prepared, &ranked, plain)),
    }
}

/// The final refined set's size over the survivors of its first refit ([`Prepared::pilot`]),
/// at the larger K the prediction moves to: 0.95–1.05 around it over the test set's volumes
/// and sizes, a little above 1 on average, so the first set tends to overshoot (cutting costs
/// less than topping up; BENCHMARKS.md, "One refinement per byte target").
const PILOT_KEEP: f64 = 1.0;

/// Log–log slope of a file's size against its number of coefficients, as fitted to the
/// refined sets of the test set (the oracle's prefixes grow a little faster, ~0.9).
const REFINED_SIZE_SLOPE: f64 = 0.85;

/// The first refined-set size a byte target tries: the oracle's prefix of `k0` coefficients
/// fills `bytes0`; a refinement of K keeps about PILOT_KEEP·`survivors`/`k0`·K of them, whose
/// file is about `bytes0`·(kept/`k0`)^REFINED_SIZE_SLOPE. Solved for `target` (BENCHMARKS.md,
/// "One refinement per byte target", for where it lands).
fn predicted_set_size(k0: usize, bytes0: u64, survivors: usize, target: u64, n: usize) -> usize {
    if k0 == 0 || survivors == 0 || bytes0 == 0 {
        return k0.clamp(1, n.max(1));
    }
    // A pilot keeping less than half (never seen: 0.80–0.99 on the test set) is not trusted
    // further: the candidate lists stay within what `memory_estimate` counts.
    let keep = (PILOT_KEEP * survivors as f64 / k0 as f64).max(0.5);
    let grow = (target as f64 / bytes0 as f64).powf(1.0 / REFINED_SIZE_SLOPE);
    ((k0 as f64 * grow / keep).round() as usize).clamp(1, n.max(1))
}

/// Whether a whole refined set of `bytes` ends the search for a `target` (see [`CLOSE_BELOW`]).
fn close_to_target(bytes: u64, target: u64) -> bool {
    let (b, t) = (bytes as f64, target as f64);
    b >= CLOSE_BELOW * t && b <= CLOSE_ABOVE * t
}

/// Growth of a whole refined set's file size with K (log–log slope): about 1, since a refined
/// set keeps a steady ~4/5 of K (measured on the MNI volume between K = 157 k and 192 k: 1.04).
const REFINED_SLOPE: f64 = 1.0;

/// The next refined-set size for a byte goal from the sizes of whole refined sets tried so far:
/// a secant step on log bytes against log K between the tightest sets below and above the
/// goal, or from the nearest one with [`REFINED_SLOPE`].
fn next_set_size(sizes: &[(usize, u64)], goal: f64, n: usize) -> usize {
    let below = sizes
        .iter()
        .filter(|&&(_, b)| (b as f64) <= goal)
        .max_by_key(|&&(k, _)| k)
        .copied();
    let above = sizes
        .iter()
        .filter(|&&(_, b)| (b as f64) > goal)
        .min_by_key(|&&(k, _)| k)
        .copied();
    let step = |(k, b): (usize, u64), slope: f64| -> f64 {
        ((k.max(1) as f64).ln() + (goal.ln() - (b.max(1) as f64).ln()) / slope).exp()
    };
    let k = match (below, above) {
        (Some((lk, lb)), Some((hk, hb))) if hk > lk + 1 && hb > lb => {
            let slope = ((hb as f64).ln() - (lb.max(1) as f64).ln())
                / ((hk as f64).ln() - (lk.max(1) as f64).ln());
            (step((lk, lb), slope.clamp(0.3, 3.0)).round() as usize).clamp(lk + 1, hk - 1)
        }
        (Some(p), Some(_)) => p.0,
        (Some(p), None) => (step(p, REFINED_SLOPE).ceil() as usize).max(p.0 + 1),
        (None, Some(p)) => {
            (step(p, REFINED_SLOPE).floor() as usize).clamp(1, p.0.saturating_sub(1).max(1))
        }
        (None, None) => 1,
    };
    k.clamp(1, n.max(1))
}

/// Fills in Q_E of the chosen file (the rate search skips it).
fn finish(prepared: &Prepared, ranked: &Ranked, mut c: Compressed) -> Compressed {
    let k = c.stats.kept as usize;
    let g = &prepared.geometry;
    let key = |channel: u8, band: wavesplat_codec::layout::Band, pos: [u32; 3]| {
        let p = [pos[0] as usize, pos[1] as usize, pos[2] as usize];
        (channel, g.linear_index(band, p) as u32)
    };
    let mut exact: Vec<(u8, u32, f32)> = ranked.sorted[..k]
        .iter()
        .map(|s| (s.channel, s.index, s.value))
        .collect();
    let mut decoded: Vec<((u8, u32), f32)> = c
        .reconstruction
        .iter()
        .flatten()
        .map(|d| (key(d.channel, d.band, d.pos), d.value))
        .collect();
    exact.par_sort_unstable_by_key(|e| (e.0, e.1));
    decoded.par_sort_unstable_by_key(|d| d.0);
    c.stats.q_e = q_e_percent(exact.iter().zip(&decoded).map(|(a, b)| {
        let norm = prepared.norms[prepared.band_of[a.1 as usize] as usize];
        (a.2 as f64, b.1 as f64, norm)
    }));
    c
}

/// Largest trial files of a rate search before it settles for the best one found.
const MAX_TRIALS: usize = 24;

/// How full a file the rate search settles for: the target to 0.2 % where the granularity
/// allows.
const FILE_FILL: f64 = 0.998;

/// What a rate search ([`fit_bytes`]) looks for and where it starts.
struct RateSearch {
    /// Bytes the file may take.
    target: u64,
    /// Prefix length of the first trial.
    guess: usize,
    /// A file of this ranking already encoded (its prefix length is its kept count): it
    /// counts as the first trial.
    known: Option<Compressed>,
}

/// The rate search: the largest prefix of `ranked` whose file fits `target` bytes, stopping
/// at the first that fills [`FILE_FILL`] of it. Sizes grow smoothly (about as K^0.9) with the
/// number K of kept coefficients, so each trial interpolates log size against log K between
/// the tightest fitting and overflowing trials (extrapolating from the one known side first),
/// and every third step bisects to guarantee progress. Typically 3–7 trials.
fn fit_bytes(
    prepared: &Prepared,
    ranked: &Ranked,
    opts: &CompressOptions,
    search: RateSearch,
    trials: &mut usize,
    progress: &(dyn Fn(Stage, f64) + Sync),
) -> Result<Compressed, CompressError> {
    let RateSearch {
        target,
        guess,
        mut known,
    } = search;
    let len = ranked.sorted.len();
    let mut run = |k: usize| {
        *trials += 1;
        progress(Stage::Encode(*trials), 0.0);
        prepared.encode(ranked, k, opts, target, false)
    };
    let goal = FILE_FILL * target as f64;
    // Steps aim at the middle of the accepted sizes: aiming at its lower edge, the secant
    // creeps up on it a few coefficients at a time.
    let aim = (1.0 + FILE_FILL) / 2.0 * target as f64;
    // Fitting (k, bytes) and overflowing (k, bytes) bounds.
    let mut lo: Option<(usize, u64)> = None;
    let mut hi: Option<(usize, u64)> = None;
    let mut best: Option<Compressed> = None;
    let mut k = guess.clamp(len.min(1), len);
    for step in 0..MAX_TRIALS {
        let c = match known.take() {
            Some(c) if (c.stats.kept as usize) <= len => {
                k = c.stats.kept as usize;
                c
            }
            _ => run(k),
        };
        let bytes = c.stats.bytes;
        tracing::trace!(k, bytes, target, "rate search trial");
        if bytes <= target {
            if lo.is_none_or(|(lk, _)| k > lk) {
                lo = Some((k, bytes));
            }
            if best.as_ref().is_none_or(|b| bytes > b.stats.bytes) {
                best = Some(c);
            }
        } else if hi.is_none_or(|(hk, _)| k < hk) {
            hi = Some((k, bytes));
        }
        if best.as_ref().is_some_and(|b| b.stats.bytes as f64 >= goal) {
            break;
        }
        let log_k = |bytes_at: u64, k_at: usize, slope: f64| -> f64 {
            (k_at.max(1) as f64).ln() + (aim.ln() - (bytes_at.max(1) as f64).ln()) / slope
        };
        let next = match (lo, hi) {
            (Some((lk, _)), _) if lk >= len => break,
            (_, Some((0 | 1, _))) => break,
            (Some((lk, _)), Some((hk, _))) if hk <= lk + 1 => break,
            (Some((lk, lb)), Some((hk, hb))) => {
                let mid = lk + (hk - lk) / 2;
                if step % 3 == 2 || hb <= lb {
                    mid
                } else {
                    let slope = ((hb as f64).ln() - (lb.max(1) as f64).ln())
                        / ((hk as f64).ln() - (lk.max(1) as f64).ln());
                    let x = log_k(lb, lk, slope.clamp(0.3, 3.0)).exp().round() as usize;
                    x.clamp(lk + 1, hk - 1)
                }
            }
            (Some((lk, lb)), None) => {
                let x = log_k(lb, lk, 0.9).exp().ceil() as usize;
                x.clamp(lk + 1, len)
            }
            (None, Some((hk, hb))) => {
                let x = log_k(hb, hk, 0.9).exp().floor() as usize;
                x.clamp(1, hk - 1)
            }
            (None, None) => break,
        };
        k = next;
    }
    match best {
        Some(b) => Ok(b),
        None => {
            let smallest = run(len.min(1));
            if smallest.stats.bytes <= target {
                Ok(smallest)
            } else {
                Err(CompressError::TargetTooSmall {
                    target,
                    minimum: smallest.stats.bytes,
                })
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::phantom::Phantom;

    /// Automatic tiling keeps files below [`AUTO_TWO_LAYERS_BYTES`] to one quality layer, then
    /// two, then three; an explicit layer count always wins, and explicit tiles keep three.
    #[test]
    fn automatic_layers_follow_the_expected_size() {
        let g = Geometry::new([200, 230, 190], Family::Linear, 3, 0).unwrap();
        let layers = |choice, layers, bytes| choose_tiling(&g, choice, layers, bytes).1;
        for bytes in [0, 900, 9_000, 100_000, AUTO_TWO_LAYERS_BYTES - 1] {
            assert_eq!(layers(TileChoice::Auto, None, bytes), 1, "{bytes}");
        }
        assert_eq!(layers(TileChoice::Auto, None, AUTO_TWO_LAYERS_BYTES), 2);
        assert_eq!(
            layers(TileChoice::Auto, None, AUTO_THREE_LAYERS_BYTES - 1),
            2
        );
        assert_eq!(layers(TileChoice::Auto, None, AUTO_THREE_LAYERS_BYTES), 3);
        assert_eq!(layers(TileChoice::Auto, None, u64::MAX), 3);
        assert_eq!(layers(TileChoice::Auto, Some(4), 900), 4);
        assert_eq!(layers(TileChoice::Size(64), None, 900), 3);
        assert_eq!(layers(TileChoice::Single, None, 1 << 30), 1);
    }

    /// Volumes whose faces are flat (zero, a constant, an offset head, the RGB phantom's black
    /// background) get the separating margin; slabs cut through a head or a body get none; an
    /// explicit margin always wins.
    #[test]
    fn the_default_margin_follows_what_the_faces_carry() {
        let sep = Geometry::separating_margin(Family::Linear, 3);
        let flat = [
            Phantom::SheppLogan.generate([40, 36, 30]),
            Phantom::Zero.generate([16, 16, 16]),
            Phantom::Constant(-1000.0).generate([16, 8, 4]),
            Phantom::RgbHead.generate([24, 24, 24]),
        ];
        for v in &flat {
            assert_eq!(default_margin(v, Family::Linear, 3), sep, "{:?}", v.dims());
        }
        // Every 8th slice of a Shepp–Logan head, then 8 slices through its middle: faces cut
        // through the head.
        let head = Phantom::SheppLogan.generate([48, 48, 48]);
        let slab: Vec<f32> = head.channel(0)[48 * 48 * 20..48 * 48 * 28].to_vec();
        let slab = Volume::new([48, 48, 8], [1.0; 3], vec![slab]).unwrap();
        assert!(face_activity(slab.channel(0), slab.dims()) > STRUCTURED_FACES);
        assert_eq!(default_margin(&slab, Family::Linear, 3), 0);
        assert_eq!(
            default_margin(&Phantom::Ct.generate([40, 32, 24]), Family::Cubic, 2),
            0
        );
        let explicit = CompressOptions {
            margin: Some(5),
            target: Target::Fraction(0.2),
            ..Default::default()
        };
        let c = compress(&slab, &explicit, &|_, _| {}).unwrap();
        assert_eq!(c.header.margin, 5);
        let c = compress(&slab, &CompressOptions::default(), &|_, _| {}).unwrap();
        assert_eq!(c.header.margin, 0);
    }

    #[test]
    fn a_refined_set_close_to_the_target_ends_the_search() {
        let t = 100_000;
        assert!(close_to_target(t, t));
        assert!(close_to_target(97_000, t) && close_to_target(103_000, t));
        assert!(!close_to_target(96_999, t) && !close_to_target(103_001, t));
        assert!(!close_to_target(0, t));
    }

    #[test]
    fn a_byte_target_compares_the_default_depth_with_one_less_unless_given() {
        let bytes = |levels| CompressOptions {
            target: Target::Bytes(1000),
            levels,
            ..Default::default()
        };
        assert_eq!(depth_candidates([64, 64, 64], &bytes(None)), vec![3, 2]);
        assert_eq!(depth_candidates([64, 64, 64], &bytes(Some(4))), vec![4]);
        // Two slices allow one level: nothing shallower to try.
        assert_eq!(depth_candidates([64, 64, 2], &bytes(None)), vec![1]);
        assert_eq!(depth_candidates([1, 1, 40], &bytes(None)), vec![0]);
        let cubic = CompressOptions {
            family: Family::Cubic,
            ..bytes(None)
        };
        assert_eq!(depth_candidates([64, 64, 64], &cubic), vec![2, 1]);
        // Comparing holds two transforms: the estimate covers them.
        let (one, _) = memory_estimate([64, 64, 64], 1, &bytes(Some(3))).unwrap();
        let (two, _) = memory_estimate([64, 64, 64], 1, &bytes(None)).unwrap();
        assert!(two > one, "{two} <= {one}");
    }

    /// The first refined-set size falls back to the oracle's when the pilot tells nothing,
    /// grows as fewer of the oracle's set survive its refit (at most 2×) and as the target
    /// grows against the oracle's file, inverts its own size model, and stays within the
    /// non-zero count.
    #[test]
    fn the_first_refined_set_size_follows_the_pilots_survivors() {
        let n = 1_000_000;
        assert_eq!(predicted_set_size(1000, 0, 900, 1000, n), 1000);
        assert_eq!(predicted_set_size(1000, 1000, 0, 1000, n), 1000);
        assert_eq!(predicted_set_size(0, 1000, 0, 1000, n), 1);
        let all_survive = predicted_set_size(1000, 1000, 1000, 1000, n);
        assert_eq!(all_survive, (1000.0 / PILOT_KEEP).round() as usize);
        let fewer = predicted_set_size(1000, 1000, 800, 1000, n);
        assert!(fewer > all_survive, "{fewer} <= {all_survive}");
        let larger_target = predicted_set_size(1000, 1000, 800, 1100, n);
        assert!(larger_target > fewer, "{larger_target} <= {fewer}");
        let kept = PILOT_KEEP * 0.8 * larger_target as f64;
        let bytes = 1000.0 * (kept / 1000.0).powf(REFINED_SIZE_SLOPE);
        assert!((bytes / 1100.0 - 1.0).abs() < 0.005, "{bytes}");
        // A pilot keeping almost nothing is trusted only down to half.
        assert_eq!(predicted_set_size(1000, 1000, 10, 1000, n), 2000);
        assert_eq!(predicted_set_size(1000, 1000, 800, 1000, 1100), 1100);
    }

    #[test]
    fn the_set_size_search_steps_towards_the_goal_and_never_repeats_a_size() {
        let n = 1_000_000;
        // One set below the goal: grow K by the byte ratio (slope 1), at least by one.
        assert!((1250..=1251).contains(&next_set_size(&[(1000, 800)], 1000.0, n)));
        assert_eq!(next_set_size(&[(1000, 999)], 1000.0, n), 1002);
        // One above: shrink, never to the same K or below 1.
        assert!((499..=500).contains(&next_set_size(&[(1000, 2000)], 1000.0, n)));
        assert_eq!(next_set_size(&[(1, 5000)], 1000.0, n), 1);
        // A bracket: the secant on log–log lands strictly inside it.
        let k = next_set_size(&[(1000, 800), (2000, 1600)], 1000.0, n);
        assert!((1249..=1251).contains(&k), "{k}");
        let k = next_set_size(&[(1000, 900), (1010, 1100)], 1000.0, n);
        assert!(k > 1000 && k < 1010, "{k}");
        // Adjacent sizes leave nothing between them: the lower one is returned (already tried,
        // which ends the search).
        assert_eq!(next_set_size(&[(1000, 900), (1001, 1100)], 1000.0, n), 1000);
        // Never beyond the candidates.
        assert_eq!(next_set_size(&[(900_000, 100)], 1000.0, n), n);
    }
}
