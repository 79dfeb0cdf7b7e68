//! The compression pipeline (paper Fig. 10): colour transform → 3D wavelet transform per channel
//! → oracle (score S = E·I, eq. 14; keep the most significant coefficients to meet a target) →
//! quality layers and tiles → significance order with spatial clustering → quantization and
//! entropy coding into packets (`wavesplat_codec::format`).
//!
//! A byte target is met by bisection on the number of kept coefficients, measuring the size the
//! real encoder writes (the estimate is the written size). The encoder returns its own
//! reconstruction (the decoder's view of every kept coefficient), so callers can check a decode
//! bit for bit and compute Q_E without decoding.

use crate::colorspace::{ColorError, ColorSpaceKind, ColorTransform};
use crate::order::{cluster_order, Clustering, Item};
use crate::refine::{refine, KeptValue, RefineOptions};
use rayon::prelude::*;
use thiserror::Error;
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
    /// Smallest set whose energy is at least this percentage of the total (Q_V, eq. 19).
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
    /// Decomposition depth M (`None`: min(6, maximum) for Haar, min(3, maximum) for linear,
    /// min(2, maximum) for cubic, whose coarse supports grow as (2j − 1)·2^M).
    pub levels: Option<usize>,
    /// Zero margin in voxels around the volume (`None`: [`Geometry::default_margin`], what the
    /// renderer needs to be exact).
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
    /// Quality layers (`None`: automatic).
    pub layers: Option<usize>,
    /// Each layer holds this many times the coefficients of all layers before it (> 1;
    /// [`LAYER_GROWTH`] by default). Smaller values give a finer coarse-to-fine progression in
    /// file order and bigger files.
    pub layer_growth: f64,
    /// Spatial clustering (`None`: pure significance order; Huffman and range coders only).
    pub clustering: Option<Clustering>,
    /// Quantizer step of the sigmap coder, relative to each substream's smallest kept
    /// magnitude (1 = coefficients at the threshold are known to ±½ threshold).
    pub step: f64,
    /// Least-squares refinement of the kept set before quantization (`None`: send the
    /// oracle's coefficients unchanged, as the paper does). See [`crate::refine`].
    pub refine: Option<RefineOptions>,
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
            clustering: Some(Clustering {
                radius: 4,
                threshold: 0.5,
            }),
            step: 1.0,
            refine: Some(RefineOptions::default()),
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
    /// Layers used.
    pub layers: usize,
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
    value: f64,
}

/// The transformed, scored volume, ready to be cut at any K.
struct Prepared {
    geometry: Geometry,
    margin: usize,
    color: ColorInfo,
    channels: usize,
    value_range: [f32; 2],
    placement: Option<Placement>,
    /// Non-zero coefficients by decreasing score.
    sorted: Vec<Scored>,
    total_energy: f64,
    total_coefficients: u64,
    /// The channels' voxel samples after the colour transform (for refinement).
    samples: Vec<Vec<f32>>,
    /// Non-zero coefficients of the transform.
    nonzero: u64,
    /// `sorted` holds a refined set.
    refined: bool,
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

fn prepare(
    volume: &Volume,
    opts: &CompressOptions,
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
    let max_levels = Geometry::max_levels(dims);
    // Deeper spline decompositions wrap more of their dual tails around the period and
    // render less exactly (see Geometry::default_margin); these depths keep ≥ 30 dB.
    let levels = opts.levels.unwrap_or(match opts.family {
        Family::Haar => max_levels.min(6),
        Family::Linear => max_levels.min(3),
        Family::Cubic => max_levels.min(2),
    });
    let margin = opts
        .margin
        .unwrap_or_else(|| Geometry::default_margin(opts.family, levels));
    let geometry =
        Geometry::new(dims, opts.family, levels, margin)?.with_spacing(volume.spacing())?;
    progress(Stage::Color, 0.0);
    let (channels, color) = if volume.channel_count() == 3 {
        let t = ColorTransform::fit(opts.colorspace, volume)?;
        let v = t.forward(volume)?;
        (v.into_channels(), color_info(&t))
    } else {
        (volume.channels().to_vec(), ColorInfo::intensity())
    };
    let (lo, hi) = volume.value_range();
    let mut planner = Dwt1d::new(opts.family);
    let bands = geometry.bands();
    let norms: Vec<f64> = bands.iter().map(|b| geometry.basis_norm2(*b)).collect();
    let mut sorted = Vec::new();
    let mut total_energy = 0.0;
    for (c, ch) in channels.iter().enumerate() {
        progress(Stage::Transform(c), c as f64 / channels.len() as f64);
        let mut data = pad_channel(ch, &geometry);
        samples_to_coefficients(&mut data, &geometry);
        forward_3d(&mut data, &geometry, &mut planner);
        let importance = color.importance[c];
        let scored: Vec<(Scored, f64)> = data
            .par_iter()
            .enumerate()
            .filter(|(_, w)| **w != 0.0)
            .map(|(i, w)| {
                let (band, _) = geometry.locate(i);
                let bi = geometry.band_index(band).expect("band of a located index");
                let e = w * w * norms[bi];
                (
                    Scored {
                        score: e * importance,
                        channel: c as u8,
                        index: i as u32,
                        value: *w,
                    },
                    e,
                )
            })
            .collect();
        total_energy += scored.iter().map(|(_, e)| e).sum::<f64>();
        sorted.extend(scored.into_iter().map(|(s, _)| s));
    }
    progress(Stage::Sort, 0.0);
    // Deterministic total order: score, then channel, then index.
    sorted.par_sort_unstable_by(|a, b| {
        b.score
            .total_cmp(&a.score)
            .then(a.channel.cmp(&b.channel))
            .then(a.index.cmp(&b.index))
    });
    let sorted_len = sorted.len() as u64;
    Ok(Prepared {
        geometry,
        margin,
        color,
        channels: channels.len(),
        value_range: [lo, hi],
        placement: volume.placement().copied(),
        sorted,
        total_energy,
        total_coefficients: (geometry.coefficient_count() * channels.len()) as u64,
        samples: channels,
        nonzero: sorted_len,
        refined: false,
    })
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
            // One layer for tiny files, a preview layer from 2 KB, three layers from 8 KB.
            let nl = layers.unwrap_or(match expected_bytes {
                0..2048 => 1,
                2048..8192 => 2,
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
    /// The same volume with its top `k` replaced by their least-squares refinement (at most `k`
    /// coefficients; the rest of the order is dropped).
    fn refined(&self, k: usize, opts: &RefineOptions) -> Prepared {
        let kept: Vec<KeptValue> = self.sorted[..k]
            .iter()
            .map(|s| KeptValue {
                channel: s.channel,
                index: s.index,
                value: s.value,
            })
            .collect();
        let importance = &self.color.importance[..self.channels];
        let refined = refine(&self.geometry, &self.samples, importance, &kept, opts);
        let g = &self.geometry;
        let sorted = refined
            .iter()
            .map(|r| {
                let (band, _) = g.locate(r.index as usize);
                Scored {
                    score: r.value * r.value * g.basis_norm2(band) * importance[r.channel as usize],
                    channel: r.channel,
                    index: r.index,
                    value: r.value,
                }
            })
            .collect();
        Prepared {
            geometry: self.geometry,
            margin: self.margin,
            color: self.color,
            channels: self.channels,
            value_range: self.value_range,
            placement: self.placement,
            sorted,
            total_energy: self.total_energy,
            total_coefficients: self.total_coefficients,
            samples: Vec::new(),
            nonzero: self.nonzero,
            refined: true,
        }
    }

    /// Encodes the top `k` coefficients.
    fn encode(&self, k: usize, opts: &CompressOptions, expected_bytes: u64) -> Compressed {
        let g = &self.geometry;
        let kept = &self.sorted[..k];
        let (tile, nl) = choose_tiling(g, opts.tile, opts.layers, expected_bytes);
        let nl = nl.clamp(1, MAX_LAYERS);
        // Layer l ends at rank k·G^(l−(L−1)) with G the layer growth: layer 0 holds the top
        // k/G^(L−1).
        let mut ends = Vec::with_capacity(nl);
        for l in 0..nl {
            let frac = opts.layer_growth.powi(l as i32 - (nl as i32 - 1));
            ends.push(((k as f64 * frac).ceil() as usize).clamp(1.min(k), k));
        }
        let mut layer_bounds = Vec::with_capacity(nl);
        let mut start = 0usize;
        for (l, end) in ends.iter().enumerate() {
            let bound = if l == 0 || start >= k {
                f64::INFINITY
            } else {
                kept[start].score
            };
            layer_bounds.push(bound.min(layer_bounds.last().copied().unwrap_or(f64::INFINITY)));
            start = (*end).max(start);
        }
        let nb = g.band_count();
        let nsub = self.channels * nb;
        // Substream parameters: w0 = largest magnitude, Δ from the sorted magnitudes (eq. 15).
        let mut mags: Vec<Vec<f64>> = vec![Vec::new(); nsub];
        let locate = |s: &Scored| g.locate(s.index as usize);
        for s in kept {
            let (band, _) = locate(s);
            let sub = s.channel as usize * nb + g.band_index(band).expect("band");
            mags[sub].push(s.value.abs());
        }
        // Smallest kept score: every kept coefficient's magnitude is at least the threshold.
        let score_threshold = kept.last().map_or(0.0, |s| s.score);
        let substreams: Vec<Option<SubstreamParams>> = mags
            .iter()
            .enumerate()
            .map(|(sub, m)| {
                (!m.is_empty()).then(|| {
                    let delta = if opts.coder == CoderKind::Sigmap {
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
            score_threshold,
            substreams,
            tables: None,
            total_energy: self.total_energy,
            kept: k as u64,
        };
        // Group by (layer, tile), keeping significance order inside each group.
        let mut groups: std::collections::BTreeMap<(usize, usize), Vec<(Scored, Coefficient)>> =
            Default::default();
        let mut layer = 0usize;
        for (rank, s) in kept.iter().enumerate() {
            while rank >= ends[layer] {
                layer += 1;
            }
            let (band, pos) = locate(s);
            let t = header.tile_of(band, pos);
            let c = Coefficient {
                channel: s.channel,
                band,
                pos: [pos[0] as u32, pos[1] as u32, pos[2] as u32],
                value: s.value as f32,
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
                // The sigmap coder codes positions as octree maps, so the order inside a
                // packet carries no cost and clustering is skipped.
                let clustering = opts.clustering.filter(|_| opts.coder != CoderKind::Sigmap);
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
        let mut exact: Vec<&Coefficient> = inputs.iter().flat_map(|i| &i.coefficients).collect();
        let mut decoded: Vec<&Coefficient> = encoded.reconstruction.iter().flatten().collect();
        exact.sort_by_key(|c| key(c));
        decoded.sort_by_key(|c| key(c));
        let q_e = q_e_percent(
            exact
                .iter()
                .zip(&decoded)
                .map(|(a, b)| (a.value as f64, b.value as f64, g.basis_norm2(a.band))),
        );
        let kept_energy: f64 = kept
            .iter()
            .map(|s| {
                let (band, _) = locate(s);
                s.value * s.value * g.basis_norm2(band)
            })
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
            layers: nl,
            refined: self.refined,
        };
        Compressed {
            bytes,
            header,
            stats,
            reconstruction: encoded.reconstruction,
        }
    }
}

/// Compresses a volume. `progress(stage, fraction)` is called as work proceeds.
pub fn compress(
    volume: &Volume,
    opts: &CompressOptions,
    progress: &(dyn Fn(Stage, f64) + Sync),
) -> Result<Compressed, CompressError> {
    if !(opts.layer_growth.is_finite() && opts.layer_growth > 1.0) {
        return Err(CompressError::InvalidOption(format!(
            "layer growth {}; allowed: a finite number above 1",
            opts.layer_growth
        )));
    }
    let prepared = prepare(volume, opts, progress)?;
    let n = prepared.sorted.len();
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
            let g = &prepared.geometry;
            let mut acc = 0.0;
            let mut k = n;
            for (i, s) in prepared.sorted.iter().enumerate() {
                let (band, _) = g.locate(s.index as usize);
                acc += s.value * s.value * g.basis_norm2(band);
                if acc >= goal * (1.0 - 1e-12) {
                    k = i + 1;
                    break;
                }
            }
            k
        }
        Target::Bytes(b) => {
            return match &opts.refine {
                Some(r) => compress_to_bytes_refined(&prepared, opts, r, b, progress),
                None => compress_to_bytes(&prepared, opts, b, progress),
            };
        }
    };
    let prepared = match &opts.refine {
        Some(r) if k > 0 && k < n => {
            progress(Stage::Refine, 0.0);
            prepared.refined(k, r)
        }
        _ => prepared,
    };
    let k = k.min(prepared.sorted.len());
    progress(Stage::Encode(0), 0.0);
    // File size guess for the automatic tiling: measured bytes per kept coefficient are
    // ~0.7–0.9 for the sigmap coder and 2–3 for the paper's syntaxes.
    let per_coefficient = if opts.coder == CoderKind::Sigmap {
        1
    } else {
        3
    };
    let expected = (k as u64).saturating_mul(per_coefficient).max(64);
    Ok(prepared.encode(k, opts, expected))
}

/// Byte target with refinement: find K for the oracle's order, refine at K, and cut the refined
/// order to the target; while the refined set comes out more than 2 % under the target, refine
/// again at a proportionally larger K (at most four refinements).
fn compress_to_bytes_refined(
    prepared: &Prepared,
    opts: &CompressOptions,
    refine_opts: &RefineOptions,
    target: u64,
    progress: &(dyn Fn(Stage, f64) + Sync),
) -> Result<Compressed, CompressError> {
    let plain = compress_to_bytes(prepared, opts, target, progress)?;
    let n = prepared.sorted.len();
    let k0 = plain.stats.kept as usize;
    if k0 == 0 || k0 >= n {
        return Ok(plain);
    }
    let mut best: Option<Compressed> = None;
    let mut k = k0;
    for _attempt in 0..4 {
        progress(Stage::Refine, 0.0);
        let refined = prepared.refined(k, refine_opts);
        let all = refined.sorted.len();
        if all == 0 {
            break;
        }
        let whole = refined.encode(all, opts, target);
        let candidate = if whole.stats.bytes <= target {
            whole
        } else {
            compress_to_bytes(&refined, opts, target, progress)?
        };
        let fill = candidate.stats.bytes as f64 / target as f64;
        let better = best
            .as_ref()
            .is_none_or(|b| candidate.stats.bytes > b.stats.bytes);
        if better {
            best = Some(candidate);
        }
        if fill >= 0.98 {
            break;
        }
        // Under-filled: the refined set codes more cheaply than the oracle's; grow K.
        k = ((k as f64 / fill.max(0.25)).ceil() as usize).clamp(k + 1, n);
    }
    // The rate search promises the target within 2 %: when refined sets never fill it (sizes
    // are not monotone in K for the paper's coders), fall back to the oracle's coefficients.
    Ok(best
        .filter(|b| b.stats.bytes as f64 >= 0.98 * target as f64)
        .unwrap_or(plain))
}

/// Bisection on the number of kept coefficients for the largest file ≤ `target` bytes.
fn compress_to_bytes(
    prepared: &Prepared,
    opts: &CompressOptions,
    target: u64,
    progress: &(dyn Fn(Stage, f64) + Sync),
) -> Result<Compressed, CompressError> {
    let n = prepared.sorted.len();
    let mut trial = 0usize;
    let mut run = |k: usize| {
        trial += 1;
        progress(Stage::Encode(trial), 0.0);
        prepared.encode(k, opts, target)
    };
    let smallest = run(n.min(1));
    if smallest.stats.bytes > target {
        return Err(CompressError::TargetTooSmall {
            target,
            minimum: smallest.stats.bytes,
        });
    }
    let mut best = smallest;
    // Exponential search for a k whose file exceeds the target (never encodes more than about
    // twice the coefficients that fit), then bisection. Invariant: size(lo) ≤ target < size(hi).
    // Sizes are nearly monotone in k (the tables adapt), so keep the best feasible trial seen.
    let mut lo = n.min(1);
    let mut hi = n + 1;
    let mut k = lo.max(1);
    while k < n {
        k = (k * 2).min(n);
        let c = run(k);
        if c.stats.bytes <= target {
            lo = k;
            best = c;
        } else {
            hi = k;
            break;
        }
    }
    if hi == n + 1 {
        return Ok(best);
    }
    while hi - lo > 1 {
        let mid = lo + (hi - lo) / 2;
        let c = run(mid);
        if c.stats.bytes <= target {
            lo = mid;
            if c.stats.kept > best.stats.kept {
                best = c;
            }
        } else {
            hi = mid;
        }
    }
    Ok(best)
}
