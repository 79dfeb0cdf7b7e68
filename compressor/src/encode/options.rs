//! What a caller asks of the encoder and what it gets back: the target (bytes, fraction, count,
//! Q_V, all), tiling, the options with their defaults, the typed errors, progress stages,
//! statistics and the compressed file with the decoder's view of its coefficients.

use crate::colorspace::{ColorError, ColorSpaceKind, ColorTransform};
use crate::order::Clustering;
use crate::refine::RefineOptions;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use thiserror::Error;
use wavesplat_codec::family::Family;
use wavesplat_codec::format::packet::{Coefficient, SizeBreakdown};
use wavesplat_codec::format::{CoderKind, Header};
use wavesplat_codec::layout::{Geometry, LayoutError};

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
    /// How a byte target without a depth chooses one.
    pub depth_search: DepthSearch,
    /// Zero margin in voxels around the volume (`None`: [`default_margin`]). Every margin renders
    /// exactly: the renderer clips basis functions to the volume's box
    /// ([`Geometry::splats_clip_to_box`]).
    pub margin: Option<usize>,
    /// Fill the padding of a grid that is clipped to the box with a smooth periodic bridge
    /// instead of zeros ([`wavesplat_codec::dwt::bridge`]): faces that cut the content then
    /// cost no more than the interior. Bricks of a bricked volume use it.
    pub smooth_padding: bool,
    /// The value subtracted from an intensity volume before the transform (`None`: the
    /// median of its faces, see [`crate::colorspace::face_median`]). The bricks of one volume
    /// share the whole's, so that no step appears where two bricks meet.
    pub offset: Option<f64>,
    /// Colour space for 3-channel volumes.
    pub colorspace: ColorSpaceKind,
    /// The colour transform of a 3-channel volume when it is fitted elsewhere (`None`: fitted
    /// to the volume, [`ColorTransform::fit`]). The bricks of one volume share the whole's, so
    /// that they show their values alike and draw into one image.
    pub color_transform: Option<ColorTransform>,
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
    /// Quantizer step of the sigmap and fast coders, relative to each substream's smallest
    /// kept magnitude (1 = coefficients at the threshold are known to ±½ threshold); with
    /// [`Target::All`] also at most 2^−`bits` of the substream's largest.
    pub step: f64,
    /// Least-squares refinement of the kept set before quantization (`None`: send the
    /// oracle's coefficients unchanged, as the paper does). See [`crate::refine`].
    pub refine: Option<RefineOptions>,
    /// Refuse to start when [`memory_estimate`] exceeds this many bytes (`None`: no limit).
    pub memory_limit: Option<u64>,
    /// The plain format version written: [`wavesplat_codec::format::VERSION`] (the fast
    /// coder's occupancy contexts), [`wavesplat_codec::format::RANS_VERSION`] for readers from
    /// before that (the same file for every coder but the fast one: 1–3 % more bytes),
    /// [`wavesplat_codec::format::COMPACT_HEADER_VERSION`] for readers from before rANS (the
    /// same file, for every coder but the fast one, whose symbols it codes with prefix codes:
    /// a few per cent more bytes),
    /// [`wavesplat_codec::format::PRIORS_VERSION`] for readers from before the
    /// compact header (the same packet syntax, a header larger by 100–250 bytes), or
    /// [`wavesplat_codec::format::LAST_UNPRIMED_VERSION`] for readers from before the sigmap
    /// coder's trained priors (its packets then start their models at ½, 2–5 % more bytes).
    pub format_version: u16,
    /// Raised from another thread to end the compression at its next stage with
    /// [`CompressError::Stopped`] (a worker whose lease was lost or whose job was cancelled).
    pub stop: StopFlag,
}

/// A request to stop a compression early, raised from another thread: the compression checks
/// it between its stages (each channel's transform, each trial encoding, each refinement,
/// each brick) and ends with [`CompressError::Stopped`]. Clones share one request; the default
/// is a flag nobody can raise ([`StopFlag::new`] makes one that can be).
#[derive(Debug, Clone, Default)]
pub struct StopFlag(Option<Arc<AtomicBool>>);

impl StopFlag {
    /// A flag not raised yet, which [`StopFlag::stop`] raises for every clone.
    pub fn new() -> StopFlag {
        StopFlag(Some(Arc::new(AtomicBool::new(false))))
    }

    /// Asks the compressions holding this flag (or a clone) to stop.
    pub fn stop(&self) {
        if let Some(f) = &self.0 {
            f.store(true, Ordering::Release);
        }
    }

    /// Whether [`StopFlag::stop`] was called.
    pub fn is_stopped(&self) -> bool {
        self.0.as_ref().is_some_and(|f| f.load(Ordering::Acquire))
    }

    /// [`CompressError::Stopped`] once the flag is raised.
    pub fn check(&self) -> Result<(), CompressError> {
        if self.is_stopped() {
            Err(CompressError::Stopped)
        } else {
            Ok(())
        }
    }
}

/// Any two flags are equal: a stop request is no option of the file, and options that differ
/// only in their flags compress alike (a brick's kept top, scored under one worker lease's
/// flag, is reused by the part coding it under another's).
impl PartialEq for StopFlag {
    fn eq(&self, _: &StopFlag) -> bool {
        true
    }
}

impl Default for CompressOptions {
    fn default() -> Self {
        CompressOptions {
            family: Family::Linear,
            levels: None,
            depth_search: DepthSearch::Compare,
            margin: None,
            smooth_padding: false,
            offset: None,
            colorspace: ColorSpaceKind::Pca,
            color_transform: None,
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
            format_version: wavesplat_codec::format::VERSION,
            stop: StopFlag::default(),
        }
    }
}

/// How a byte target without a given depth chooses the decomposition depth.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DepthSearch {
    /// Compress at [`default_levels`] and one level less (and shallower while the shallowest
    /// wins and its file affords the next coarse band), keeping the depth whose X-ray views
    /// come closer: one more transform and oracle pass per depth.
    Compare,
    /// Take [`default_levels`], going shallower while the file there affords the next coarse
    /// band ([`crate::encode::worth_going_shallower`], taken for every level at once), which
    /// the comparison's measurements say is when the shallower depth wins: no views computed,
    /// at most two depths compressed.
    Predict,
}

/// How much work compression spends for quality: a preset of the options that cost time
/// (the depth search, the least-squares refinement), which flags given on top override.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Effort {
    /// The depth predicted, one cheap refinement ([`RefineOptions::ONE_SET`]); the bricks of
    /// a bricked volume are not refined (the oracle's coefficients as the paper sends them).
    Fast,
    /// Depths compared, three rounds of refinement.
    #[default]
    Default,
    /// Depths compared, more refinement rounds and conjugate-gradient iterations.
    Best,
}

impl Effort {
    /// Every effort's name, fastest first.
    pub const NAMES: [&'static str; 3] = ["fast", "default", "best"];

    /// The effort named `name` (`fast`, `default`, `best`).
    pub fn from_name(name: &str) -> Option<Effort> {
        match name {
            "fast" => Some(Effort::Fast),
            "default" => Some(Effort::Default),
            "best" => Some(Effort::Best),
            _ => None,
        }
    }

    /// Its name.
    pub fn name(self) -> &'static str {
        match self {
            Effort::Fast => "fast",
            Effort::Default => "default",
            Effort::Best => "best",
        }
    }

    /// The depth search of this effort.
    pub fn depth_search(self) -> DepthSearch {
        match self {
            Effort::Fast => DepthSearch::Predict,
            Effort::Default | Effort::Best => DepthSearch::Compare,
        }
    }

    /// The refinement of this effort (`None`: none).
    pub fn refine(self) -> Option<RefineOptions> {
        match self {
            Effort::Fast => Some(RefineOptions::ONE_SET),
            Effort::Default => Some(RefineOptions::default()),
            Effort::Best => Some(RefineOptions {
                rounds: 6,
                cg_iterations: 4,
                ..RefineOptions::default()
            }),
        }
    }

    /// The refinement of this effort with the flags of `compress` or a job on top: `no_refine`
    /// none; a round or iteration count given, one with it (from the effort's refinement, or
    /// the full default one where the effort has none or refines only its one set).
    pub fn refine_with(
        self,
        no_refine: bool,
        rounds: Option<usize>,
        iterations: Option<usize>,
    ) -> Option<RefineOptions> {
        if no_refine {
            return None;
        }
        let asked = rounds.is_some() || iterations.is_some();
        let base = match self.refine() {
            Some(r) if r.one_set && asked => RefineOptions::default(),
            Some(r) => r,
            None if asked => RefineOptions::default(),
            None => return None,
        };
        Some(RefineOptions {
            rounds: rounds.unwrap_or(base.rounds),
            cg_iterations: iterations.unwrap_or(base.cg_iterations),
            ..base
        })
    }

    /// The default options with this effort's choices.
    pub fn options(self) -> CompressOptions {
        CompressOptions {
            depth_search: self.depth_search(),
            refine: self.refine(),
            ..CompressOptions::default()
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
    /// The transform's coefficients do not fit the format's f32 values: samples near
    /// ±f32::MAX grow past it in the coarse bands (a scaling coefficient of depth M is about
    /// 2^(1.5·M) times its samples).
    #[error(
        "the volume's wavelet coefficients exceed the largest value the format stores \
         (f32, about 3.4e38): its samples reach {largest:e} in magnitude; scale them down \
         (by 1e-6, say) and compress again"
    )]
    CoefficientOverflow {
        /// The largest sample magnitude.
        largest: f64,
    },
    /// A kept top's coefficients could not be read back from the temporary file they were
    /// moved to.
    #[error("reading a kept top back from its temporary file")]
    KeptTopRead(#[source] std::io::Error),
    /// The caller raised the options' [`StopFlag`]: nothing was written.
    #[error("compression stopped before it finished: it was asked to stop")]
    Stopped,
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

/// The decomposition depth M when none is given: min(6, maximum) for Haar, min(3, maximum)
/// for linear, min(2, maximum) for cubic (whose coarse supports grow as (2j − 1)·2^M). A byte
/// target also tries one level less, and deeper ones up to [`deepest_compared`] while the
/// deepest tried wins ([`depth_candidates`]).
pub fn default_levels(dims: [usize; 3], family: Family) -> usize {
    let max_levels = Geometry::max_levels(dims);
    match family {
        Family::Haar => max_levels.min(6),
        Family::Linear => max_levels.min(3),
        Family::Cubic => max_levels.min(2),
    }
}

/// The deepest depth a byte target's comparison tries: two levels past the default for linear
/// (5), one for cubic (3), Haar's default (6), within what the grid allows. On the volumes of
/// the test set (≤ 233 voxels a side) a depth past the default never won; on the MNI volume
/// resampled to 512³ (smooth at the finest scales, as an oversampled acquisition is) linear at
/// M = 5 drew +5.6 dB Q_I over M = 3 at equal bytes (BENCHMARKS.md, "Scale and robustness").
pub fn deepest_compared(dims: [usize; 3], family: Family) -> usize {
    let max_levels = Geometry::max_levels(dims);
    match family {
        Family::Haar => max_levels.min(6),
        Family::Linear => max_levels.min(5),
        Family::Cubic => max_levels.min(3),
    }
}
