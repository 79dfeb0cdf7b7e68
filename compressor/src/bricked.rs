//! Bricked compression: a volume too large for one transform is split into bricks
//! ([`wavesplat_codec::format::bricked::brick_grid`]), each compressed on its own as a complete
//! `.wsp` (its own transform, no voxel of its neighbours), and written as one bricked
//! container. Rate is allocated as for the whole: a first pass scores every brick's
//! coefficients into absolute score histograms ([`crate::encode::score_summary`]), their sum
//! gives the one score threshold the oracle would take for the whole volume, and the second
//! pass keeps in each brick the coefficients above it (not equal bytes per brick). Only one
//! brick is in memory per worker thread at a time; the bricks come from a [`BrickSource`] (a
//! volume in memory, or a file read by region).
//!
//! Where a face cuts the content, a brick alone would see a step: its transform is periodic.
//! So each brick is padded by 2^M voxels filled with a smooth bridge from face to opposite
//! face ([`wavesplat_codec::dwt::bridge`]), its coefficients are ranked by the energy they
//! show inside its box ([`crate::visible`]), and every brick subtracts the whole's offset
//! (the median of the whole's faces), so that neighbours' images meet without a seam; the
//! bricks of an RGB volume share the whole's colour transform (its faces' median colour and,
//! for PCA, the basis of the whole's colour moments), so that they draw into one image. The
//! renderer clips each brick to its box.
//!
//! A byte target for the whole is met by a search on the global threshold's coefficient count
//! (log bytes against log count, as the single-volume search does), each trial compressing
//! every brick: a few times the work of one pass.

use crate::colorspace::{ColorSpaceKind, ColorTransform};
use rayon::prelude::*;
use thiserror::Error;
use wavesplat_codec::format::bricked::{
    brick_grid, manifest_section, write_bricked, BrickEntry, Manifest,
};
use wavesplat_codec::format::FormatError;
use wavesplat_codec::layout::Geometry;
use wavesplat_codec::volume::{Placement, Volume, VolumeError};

use crate::encode::{
    axis_views, deepest_compared, default_levels, memory_estimate, score_keeping_top,
    score_summary, CompressError, CompressOptions, DepthSearch, KeptTop, ScoreSummary,
    SummedScores, Target, PROCESS_MEMORY, SHALLOWER_KEPT,
};
use crate::reader::ReadError;
use crate::scratch::ScratchFile;

/// The margin a brick is padded with for its smooth bridge (see
/// [`wavesplat_codec::dwt::bridge`]): the coarsest level's spacing 2^M on each side, below the
/// separating margin (1.5·2^M for linear), so the brick is still clipped to its box. Measured
/// on the MRI in 64³ bricks at 87 kB against 2^M/4, 2^M/2 and 1.25·2^M: the narrower bridges
/// are steeper and cost more where a face cuts the head, the wider one pads more voxels. None
/// for Haar, whose boxes never reach past a face.
pub fn bridge_margin(family: wavesplat_codec::family::Family, levels: usize) -> usize {
    if family == wavesplat_codec::family::Family::Haar {
        return 0;
    }
    1 << levels
}

/// The median of the whole volume's faces per channel (as a single volume's offset or colour
/// origin is chosen), read from `source`: every brick subtracts this one offset. Bricks with
/// offsets of their own would each draw their offset as a constant over their box, whose edge
/// is a half-voxel step where the whole's spline ramps, and two neighbours' steps would not
/// cancel. A source that [`BrickSource::reads_rows_whole`] is read in one pass of slabs;
/// others face by face. Either way the samples are the same (edges counted in each face they
/// lie on), so the median is too.
fn whole_face_medians(source: &dyn BrickSource) -> Result<Vec<f64>, BrickError> {
    let mut samples = if source.reads_rows_whole() {
        face_samples_by_slabs(source, FACE_SLAB_BYTES)?
    } else {
        face_samples_by_faces(source)?
    };
    Ok(samples
        .iter_mut()
        .map(|s| crate::colorspace::median_or_zero(s))
        .collect())
}

/// The bytes of samples (as f32, all channels) one read of [`face_samples_by_slabs`] holds.
const FACE_SLAB_BYTES: usize = 64 << 20;

/// The six faces' samples per channel, each face read as one box.
fn face_samples_by_faces(source: &dyn BrickSource) -> Result<Vec<Vec<f32>>, BrickError> {
    let d = source.dims();
    let mut faces: Vec<([u64; 3], [usize; 3])> = Vec::new();
    for a in 0..3 {
        let mut dims = d.map(|v| v as usize);
        dims[a] = 1;
        faces.push(([0; 3], dims));
        if d[a] > 1 {
            let mut origin = [0u64; 3];
            origin[a] = d[a] - 1;
            faces.push((origin, dims));
        }
    }
    let mut samples: Vec<Vec<f32>> = vec![Vec::new(); source.channels()];
    for (origin, dims) in faces {
        let v = source
            .read(origin, dims)
            .map_err(|source| BrickError::Read { origin, source })?;
        for (c, s) in samples.iter_mut().enumerate() {
            s.extend_from_slice(v.channel(c));
        }
    }
    Ok(samples)
}

/// The six faces' samples per channel (the same multiset as [`face_samples_by_faces`]), from
/// one pass over the volume in boxes of whole rows of at most `budget` bytes: several planes
/// at a time, or bands of rows of one plane where a plane is larger. A face across the rows
/// (x = 0 or its last column) read as a box of its own is one positioned read of a single
/// sample per row: on a file every page of it is touched anyway, a page at a time (a 2048³
/// f32 file took hours where not cached), and a DICOM series decodes every slice for it.
fn face_samples_by_slabs(
    source: &dyn BrickSource,
    budget: usize,
) -> Result<Vec<Vec<f32>>, BrickError> {
    let [nx, ny, nz] = source.dims().map(|v| v as usize);
    let channels = source.channels();
    let row_bytes = nx.saturating_mul(channels).saturating_mul(4).max(1);
    let rows_per_read = (budget / row_bytes).max(1);
    // Whole planes per read where a plane fits, else bands of rows of one plane.
    let (band, planes) = if rows_per_read >= ny {
        (ny, (rows_per_read / ny.max(1)).max(1))
    } else {
        (rows_per_read, 1)
    };
    let mut samples: Vec<Vec<f32>> = vec![Vec::new(); channels];
    let mut z0 = 0;
    while z0 < nz {
        let dz = planes.min(nz - z0);
        let mut y0 = 0;
        while y0 < ny {
            let dy = band.min(ny - y0);
            let origin = [0, y0 as u64, z0 as u64];
            let v = source
                .read(origin, [nx, dy, dz])
                .map_err(|source| BrickError::Read { origin, source })?;
            for (c, s) in samples.iter_mut().enumerate() {
                let ch = v.channel(c);
                for z in 0..dz {
                    let whole_plane = z0 + z == 0 || (nz > 1 && z0 + z == nz - 1);
                    for y in 0..dy {
                        let row = &ch[(z * dy + y) * nx..(z * dy + y + 1) * nx];
                        // The z faces, then the y faces, then the x faces: each edge sample
                        // once per face it lies on.
                        if whole_plane {
                            s.extend_from_slice(row);
                        }
                        let yy = y0 + y;
                        if yy == 0 {
                            s.extend_from_slice(row);
                        }
                        if ny > 1 && yy == ny - 1 {
                            s.extend_from_slice(row);
                        }
                        s.push(row[0]);
                        if nx > 1 {
                            s.push(row[nx - 1]);
                        }
                    }
                }
            }
            y0 += dy;
        }
        z0 += dz;
    }
    Ok(samples)
}

/// The colour transform of `kind` every brick of an RGB volume shares: about the whole's faces'
/// median colour `mean`, PCA's basis from the whole's colour second moments, gathered brick by
/// brick from `source` (one brick in memory at a time). Bricks that fitted their own would each
/// code their values in another basis, and could not be drawn into one image progressively.
fn whole_color_transform(
    source: &dyn BrickSource,
    grid: &[([u64; 3], [usize; 3])],
    kind: ColorSpaceKind,
    mean: [f64; 3],
) -> Result<ColorTransform, BrickError> {
    let mut moments = [[0.0f64; 3]; 3];
    if kind == ColorSpaceKind::Pca {
        let total: f64 = grid
            .iter()
            .map(|(_, d)| d.iter().product::<usize>() as f64)
            .sum();
        for &(origin, dims) in grid {
            let v = source
                .read(origin, dims)
                .map_err(|source| BrickError::Read { origin, source })?;
            let share = v.voxel_count() as f64 / total;
            let m = crate::colorspace::second_moments(&v, mean);
            for (row, r) in moments.iter_mut().zip(m) {
                for (a, b) in row.iter_mut().zip(r) {
                    *a += b * share;
                }
            }
        }
    }
    Ok(ColorTransform::with_origin(kind, mean, &moments))
}

/// Where bricks come from: something that can hand out any box of the whole as a volume.
pub trait BrickSource: Sync {
    /// The whole volume's dimensions.
    fn dims(&self) -> [u64; 3];
    /// Its channels.
    fn channels(&self) -> usize;
    /// Its voxel spacing.
    fn spacing(&self) -> [f32; 3];
    /// Its placement in patient space (of voxel (0, 0, 0) of the whole).
    fn placement(&self) -> Option<Placement>;
    /// The box at `origin` of `dims` as a volume (spacing as the whole's, no placement needed).
    fn read(&self, origin: [u64; 3], dims: [usize; 3]) -> Result<Volume, ReadError>;
    /// Whether a box of whole rows costs about what the same rows cut short do, so that what
    /// needs only the faces reads the volume in one pass of slabs instead of face by face: a
    /// file (a column of single samples touches every page of it, one positioned read per
    /// row) or a DICOM series (a face across the slices decodes every slice). False where a
    /// box costs by its voxels (a phantom generates only what is asked).
    fn reads_rows_whole(&self) -> bool {
        false
    }
}

impl BrickSource for Volume {
    fn dims(&self) -> [u64; 3] {
        Volume::dims(self).map(|d| d as u64)
    }

    fn channels(&self) -> usize {
        self.channel_count()
    }

    fn spacing(&self) -> [f32; 3] {
        Volume::spacing(self)
    }

    fn placement(&self) -> Option<Placement> {
        Volume::placement(self).copied()
    }

    fn read(&self, origin: [u64; 3], dims: [usize; 3]) -> Result<Volume, ReadError> {
        Ok(crop(self, origin, dims)?)
    }
}

impl BrickSource for crate::reader::region::RegionReader {
    fn dims(&self) -> [u64; 3] {
        crate::reader::region::RegionReader::dims(self).map(|d| d as u64)
    }

    fn channels(&self) -> usize {
        crate::reader::region::RegionReader::channels(self)
    }

    fn spacing(&self) -> [f32; 3] {
        crate::reader::region::RegionReader::spacing(self)
    }

    fn placement(&self) -> Option<Placement> {
        crate::reader::region::RegionReader::placement(self).copied()
    }

    fn read(&self, origin: [u64; 3], dims: [usize; 3]) -> Result<Volume, ReadError> {
        self.read_region(origin.map(|v| v as usize), dims)
    }

    fn reads_rows_whole(&self) -> bool {
        true
    }
}

impl BrickSource for crate::phantom::PhantomVolume {
    fn dims(&self) -> [u64; 3] {
        self.dims
    }

    fn channels(&self) -> usize {
        self.phantom.channel_count()
    }

    fn spacing(&self) -> [f32; 3] {
        [1.0; 3]
    }

    fn placement(&self) -> Option<Placement> {
        None
    }

    fn read(&self, origin: [u64; 3], dims: [usize; 3]) -> Result<Volume, ReadError> {
        Ok(self.phantom.try_generate_region(self.dims, origin, dims)?)
    }
}

/// The box of `volume` at `origin` of `dims` (within it).
pub fn crop(volume: &Volume, origin: [u64; 3], dims: [usize; 3]) -> Result<Volume, VolumeError> {
    let d = volume.dims();
    VolumeError::check_within(origin, dims, d.map(|n| n as u64))?;
    let o = origin.map(|v| v as usize);
    let channels = volume
        .channels()
        .iter()
        .map(|c| {
            let mut out = Vec::with_capacity(dims.iter().product());
            for z in o[2]..o[2] + dims[2] {
                for y in o[1]..o[1] + dims[1] {
                    let row = (z * d[1] + y) * d[0];
                    out.extend_from_slice(&c[row + o[0]..row + o[0] + dims[0]]);
                }
            }
            out
        })
        .collect();
    Volume::new(dims, volume.spacing(), channels)
}

/// Errors of bricked compression.
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum BrickError {
    /// A brick, or a slab or face of the whole read before the bricks, could not be read.
    #[error("reading the voxels from {origin:?} on")]
    Read {
        /// Where the region read starts in the whole.
        origin: [u64; 3],
        /// Why.
        #[source]
        source: ReadError,
    },
    /// A brick could not be compressed.
    #[error("compressing the brick at {origin:?}")]
    Compress {
        /// Its origin in the whole.
        origin: [u64; 3],
        /// Why (boxed: the compressor's error is large, and this one travels through every
        /// brick's result).
        #[source]
        source: Box<CompressError>,
    },
    /// The options do not suit a bricked volume.
    #[error("invalid option for a bricked volume: {0}")]
    InvalidOption(String),
    /// The container could not be written (or its manifest read).
    #[error(transparent)]
    Format(#[from] FormatError),
    /// A brick could not be decoded.
    #[error("decoding the brick at {origin:?}")]
    Decode {
        /// Its origin in the whole.
        origin: [u64; 3],
        /// Why.
        #[source]
        source: crate::decode::DecodeError,
    },
    /// The coded bricks could not be kept in their temporary file.
    #[error("keeping the coded bricks in a temporary file")]
    Spill(#[source] std::io::Error),
    /// The container could not be written out.
    #[error("writing the bricked file")]
    Output(#[source] std::io::Error),
    /// A decoded brick could not be written out.
    #[error("writing the brick at {origin:?}")]
    Write {
        /// Its origin in the whole.
        origin: [u64; 3],
        /// Why.
        #[source]
        source: std::io::Error,
    },
}

impl BrickError {
    /// Whether a brick was refused for needing more memory than the limit.
    pub fn is_memory_refusal(&self) -> bool {
        matches!(self, BrickError::Compress { source, .. }
            if matches!(**source, CompressError::MemoryLimit { .. }))
    }

    /// Whether this refuses the options (an edge, a target, a depth that cannot be) or the
    /// input's samples (NaN, Inf): running the same command again cannot succeed.
    pub fn is_refusal(&self) -> bool {
        matches!(
            self,
            BrickError::InvalidOption(_)
                | BrickError::Read {
                    source: ReadError::InvalidVolume { .. } | ReadError::Volume(_),
                    ..
                }
        )
    }
}

/// Decodes every brick of a bricked container to a volume and hands it, with its manifest
/// entry, to `sink`: bricks are decoded in parallel, one per worker thread at a time, and come
/// in no particular order, so nothing ever holds the whole volume (each brick within
/// `budget`). A brick whose header disagrees with its manifest entry (dimensions, channels) is
/// refused. Returns the manifest.
pub fn decode_bricks(
    bytes: &[u8],
    budget: &wavesplat_codec::format::packet::DecodeBudget,
    sink: &(dyn Fn(&BrickEntry, Volume) -> std::io::Result<()> + Sync),
) -> Result<Manifest, BrickError> {
    let file = wavesplat_codec::format::bricked::parse_bricked(bytes)?;
    let m = &file.manifest;
    (0..m.bricks.len()).into_par_iter().try_for_each(|i| {
        let e = &m.bricks[i];
        let decode_error = |source| BrickError::Decode {
            origin: e.origin,
            source,
        };
        let data = file
            .brick_bytes(i)
            .map_err(|f| decode_error(crate::decode::DecodeError::Format(f)))?;
        let v = crate::decode::decompress_within(data, budget).map_err(decode_error)?;
        if v.dims() != e.dims || v.channel_count() != m.channels {
            return Err(decode_error(crate::decode::DecodeError::Format(
                FormatError::Invalid {
                    what: "bricked manifest",
                    detail: format!(
                        "brick {i} at {:?} decodes to {:?} with {} channel(s); the manifest says \
                         {:?} with {}",
                        e.origin,
                        v.dims(),
                        v.channel_count(),
                        e.dims,
                        m.channels
                    ),
                },
            )));
        }
        sink(e, v).map_err(|source| BrickError::Write {
            origin: e.origin,
            source,
        })
    })?;
    Ok(file.manifest)
}

/// What a bricked compression made.
#[derive(Debug)]
pub struct BrickedCompressed {
    /// The container's bytes.
    pub bytes: Vec<u8>,
    /// Its manifest (offsets filled in).
    pub manifest: Manifest,
    /// Coefficients of the padded grids of all bricks, all channels.
    pub total_coefficients: u64,
    /// Non-zero coefficients over all bricks.
    pub nonzero: u64,
    /// The depth every brick was transformed with.
    pub levels: usize,
}

/// Progress of a bricked compression.
#[derive(Debug, Clone, Copy)]
pub enum BrickStage {
    /// Brick `done` of `of` scored (first pass).
    Scored {
        /// Bricks scored so far.
        done: usize,
        /// Bricks in all.
        of: usize,
    },
    /// Brick `done` of `of` compressed in trial `trial` (second pass; byte targets run
    /// several trials).
    Compressed {
        /// Bricks compressed so far in this trial.
        done: usize,
        /// Bricks in all.
        of: usize,
        /// The trial (0 for targets other than bytes).
        trial: usize,
    },
}

impl std::fmt::Display for BrickStage {
    /// What a progress line says: "scoring brick 3 of 8", "compressing brick 3 of 8 (trial 1)".
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            BrickStage::Scored { done, of } => write!(f, "scoring brick {done} of {of}"),
            BrickStage::Compressed { done, of, trial } => {
                write!(f, "compressing brick {done} of {of} (trial {trial})")
            }
        }
    }
}

pub use wavesplat_codec::format::bricked::MIN_BRICK;

/// Brick sides a volume too large to compress whole is split into, largest first.
pub const AUTO_BRICK_SIDES: [usize; 4] = [256, 128, 64, 32];

/// Why a volume is compressed as bricks without being asked to ([`auto_brick`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BrickReason {
    /// More voxels than one transform takes ([`wavesplat_codec::volume::MAX_VOXELS`]).
    TooManyVoxels(u128),
    /// Compressing it whole needs about `needed` bytes, more than the `limit`.
    OverMemory {
        /// The estimate for the whole ([`crate::encode::memory_estimate`]).
        needed: u64,
        /// The memory it must fit.
        limit: u64,
    },
}

/// A brick side chosen for a volume that cannot be compressed whole, and why.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct AutoBrick {
    /// The brick edge.
    pub side: usize,
    /// Why the whole does not do.
    pub reason: BrickReason,
}

/// Whether a volume of `dims` voxels and `channels` channels compressed with `opts` should be
/// bricked, and at which side: when it has more voxels than one transform takes, or compressing
/// it whole would need more than `limit` bytes ([`crate::encode::memory_estimate`]). The side is
/// the largest of [`AUTO_BRICK_SIDES`] below the volume's whose bricks, `threads` at a time (one
/// per thread of a process, or one on a worker running a part), fit the limit beside the
/// process's own share; none fitting: `None` for a volume that has few enough voxels (compressed
/// whole, which reports the limit), the smallest side otherwise. What `compress` and `archive
/// submit` do with a volume given without `--brick`.
pub fn auto_brick(
    dims: [usize; 3],
    channels: usize,
    opts: &CompressOptions,
    limit: Option<u64>,
    threads: u64,
) -> Result<Option<AutoBrick>, CompressError> {
    let voxels = dims.iter().map(|v| *v as u128).product::<u128>();
    let reason = if voxels > wavesplat_codec::volume::MAX_VOXELS as u128 {
        BrickReason::TooManyVoxels(voxels)
    } else {
        let (needed, _) = memory_estimate(dims, channels, opts)?;
        match limit {
            Some(limit) if needed > limit => BrickReason::OverMemory { needed, limit },
            _ => return Ok(None),
        }
    };
    let fits = |side: usize| {
        bricks_memory(dims, channels, opts, side, threads)
            .is_some_and(|n| limit.is_none_or(|l| n <= l))
    };
    let side = AUTO_BRICK_SIDES
        .into_iter()
        .filter(|&side| dims.iter().any(|&n| n > side))
        .find(|&side| fits(side));
    Ok(match (side, reason) {
        (Some(side), reason) => Some(AutoBrick { side, reason }),
        (None, BrickReason::TooManyVoxels(_)) => Some(AutoBrick {
            side: AUTO_BRICK_SIDES[AUTO_BRICK_SIDES.len() - 1],
            reason,
        }),
        // No brick fits either: compressing whole reports the limit.
        (None, BrickReason::OverMemory { .. }) => None,
    })
}

/// The memory compressing `dims` in bricks of `side` needs, `threads` bricks at a time: the
/// process's share once ([`PROCESS_MEMORY`]) and the rest of one brick's
/// [`memory_estimate`] per thread. A brick is transformed with its bridge margin at a depth up
/// to its default (what [`BrickPlan::new`] checks against the limit). `None` where a brick's
/// options are refused.
pub fn bricks_memory(
    dims: [usize; 3],
    channels: usize,
    opts: &CompressOptions,
    side: usize,
    threads: u64,
) -> Option<u64> {
    let b = dims.map(|n| n.min(side));
    let levels = opts
        .levels
        .unwrap_or_else(|| default_levels(b, opts.family));
    let brick_opts = CompressOptions {
        levels: Some(levels),
        margin: Some(bridge_margin(opts.family, levels)),
        // As `BrickPlan::build`: bricks drop the fast effort's one refined set.
        refine: opts.refine.filter(|r| !r.one_set),
        ..opts.clone()
    };
    let (n, _) = memory_estimate(b, channels, &brick_opts).ok()?;
    let per_brick = n.saturating_sub(PROCESS_MEMORY);
    Some(PROCESS_MEMORY.saturating_add(per_brick.saturating_mul(threads.max(1))))
}

/// What every brick of one bricked volume shares, decided once on the whole: the depth, the
/// offset a scalar volume's bricks subtract, and the colour transform an RGB volume's bricks
/// share. Plain values, so that a distributed job can hand them to the workers that compress
/// single bricks ([`BrickPlan::with_choices`]).
#[derive(Debug, Clone, PartialEq)]
pub struct SharedChoices {
    /// Decomposition depth M of every brick.
    pub levels: usize,
    /// The whole's offset (scalar volumes).
    pub offset: Option<f64>,
    /// The whole's colour transform (RGB volumes).
    pub color: Option<ColorTransform>,
}

/// The whole volume as bricks: its grid, the choices the bricks share and the options each
/// brick is compressed with. A plan scores and encodes single bricks
/// ([`BrickPlan::score`], [`BrickPlan::encode`]), in this process or on any machine that can
/// read the source; [`allocate`] drives the rate allocation over all of them.
#[derive(Debug, Clone)]
pub struct BrickPlan {
    /// Each brick's origin and dimensions, x fastest.
    pub grid: Vec<([u64; 3], [usize; 3])>,
    /// The brick edge asked for.
    pub brick: usize,
    /// What the bricks share.
    pub choices: SharedChoices,
    /// The whole's target (the bricks' own targets come from the allocation).
    pub target: Target,
    /// Coefficients kept per byte of the bricks' files, where a depth comparison measured it
    /// on a sample of the bricks (scaled by `REFINED_PER_ORACLE` when refining): a byte
    /// target's rate search starts from it ([`allocate_units`]). `None`: from one byte per
    /// coefficient.
    pub coefficients_per_byte: Option<f64>,
    base: CompressOptions,
    dims: [u64; 3],
    channels: usize,
    spacing: [f32; 3],
    placement: Option<Placement>,
}

impl BrickPlan {
    /// Plans `source` as bricks of edge `brick` under `opts` (whose target is the whole's):
    /// checks the options, reads the whole's faces for its offset or colour origin (and, for
    /// PCA, its colour moments brick by brick) and picks the depth.
    pub fn new(
        source: &dyn BrickSource,
        opts: &CompressOptions,
        brick: usize,
    ) -> Result<BrickPlan, BrickError> {
        check_options(opts, brick)?;
        wavesplat_codec::format::bricked::check_bricking(source.dims(), brick)
            .map_err(BrickError::InvalidOption)?;
        let grid = brick_grid(source.dims(), brick);
        // A depth asked for is checked before the whole's faces (and, for PCA, all of it) are
        // read.
        if let Some(m) = opts.levels {
            check_depth(&grid, m)?;
        }
        let offset = match opts.offset {
            Some(o) => Some(o),
            None if source.channels() == 1 => Some(whole_face_medians(source)?[0]),
            None => None,
        };
        let color = match &opts.color_transform {
            Some(t) => Some(t.clone()),
            None if source.channels() == 3 => {
                let m = whole_face_medians(source)?;
                let mean = [m[0], m[1], m[2]];
                Some(whole_color_transform(source, &grid, opts.colorspace, mean)?)
            }
            None => None,
        };
        let mut choices = SharedChoices {
            levels: 0,
            offset,
            color,
        };
        let (levels, coefficients_per_byte) = choose_levels(source, opts, brick, &grid, &choices)?;
        choices.levels = levels;
        check_depth(&grid, choices.levels)?;
        let mut plan = BrickPlan::build(source, opts, brick, grid, choices)?;
        // The sample's files are oracle files; refined ones hold more coefficients per byte.
        plan.coefficients_per_byte = coefficients_per_byte.map(|r| match plan.base.refine {
            Some(_) => r * REFINED_PER_ORACLE,
            None => r,
        });
        Ok(plan)
    }

    /// The plan of `source` with choices already made (by [`BrickPlan::new`] elsewhere):
    /// nothing is read.
    pub fn with_choices(
        source: &dyn BrickSource,
        opts: &CompressOptions,
        brick: usize,
        choices: SharedChoices,
    ) -> Result<BrickPlan, BrickError> {
        check_options(opts, brick)?;
        wavesplat_codec::format::bricked::check_bricking(source.dims(), brick)
            .map_err(BrickError::InvalidOption)?;
        let grid = brick_grid(source.dims(), brick);
        check_depth(&grid, choices.levels)?;
        BrickPlan::build(source, opts, brick, grid, choices)
    }

    /// The plan of checked options, grid and depth.
    fn build(
        source: &dyn BrickSource,
        opts: &CompressOptions,
        brick: usize,
        grid: Vec<([u64; 3], [usize; 3])>,
        choices: SharedChoices,
    ) -> Result<BrickPlan, BrickError> {
        let levels = choices.levels;
        if source.channels() == 3 && choices.color.is_none() {
            return Err(BrickError::InvalidOption(
                "the bricks of an RGB volume need the whole's colour transform".into(),
            ));
        }
        let base = CompressOptions {
            levels: Some(levels),
            margin: Some(bridge_margin(opts.family, levels)),
            smooth_padding: true,
            offset: choices.offset,
            color_transform: choices.color.clone(),
            // The fast effort's one refined set is not worth a brick's second transform: its
            // bricks are coded from the tops their scoring pass kept.
            refine: opts.refine.filter(|r| !r.one_set),
            ..opts.clone()
        };
        // A brick that cannot be compressed within the memory limit is refused before any is
        // scored, not when its turn comes.
        if let Some(limit) = base.memory_limit {
            let (origin, largest) = largest_brick(&grid);
            let (needed, detail) =
                memory_estimate(largest, source.channels(), &base).map_err(|e| {
                    BrickError::Compress {
                        origin,
                        source: Box::new(e),
                    }
                })?;
            if needed > limit {
                return Err(BrickError::Compress {
                    origin,
                    source: Box::new(CompressError::MemoryLimit {
                        needed,
                        limit,
                        detail,
                    }),
                });
            }
        }
        Ok(BrickPlan {
            grid,
            brick,
            choices,
            target: opts.target,
            coefficients_per_byte: None,
            base,
            dims: source.dims(),
            channels: source.channels(),
            spacing: source.spacing(),
            placement: source.placement(),
        })
    }

    /// Reads brick `i` (without placement: the manifest places the whole, and 97 bytes per
    /// brick's header add up at low rates).
    fn read(&self, source: &dyn BrickSource, i: usize) -> Result<Volume, BrickError> {
        let (origin, dims) = *self.grid.get(i).ok_or_else(|| {
            BrickError::InvalidOption(format!("brick {i} of {}", self.grid.len()))
        })?;
        let v = source
            .read(origin, dims)
            .map_err(|source| BrickError::Read { origin, source })?;
        if v.placement().is_none() {
            return Ok(v);
        }
        let (d, s) = (v.dims(), v.spacing());
        Volume::new(d, s, v.into_channels()).map_err(|e| BrickError::Read {
            origin,
            source: e.into(),
        })
    }

    /// A compression error of brick `i`, placed at its origin.
    fn compress_error(&self, i: usize) -> impl FnOnce(CompressError) -> BrickError + '_ {
        move |source| BrickError::Compress {
            origin: self.grid[i].0,
            source: Box::new(source),
        }
    }

    /// The first pass for brick `i`: its coefficients' score histogram.
    pub fn score(&self, source: &dyn BrickSource, i: usize) -> Result<ScoreSummary, BrickError> {
        let v = self.read(source, i)?;
        score_summary(&v, &self.base, &|_, _| {}).map_err(self.compress_error(i))
    }

    /// The first pass for brick `i` ([`BrickPlan::score`]) with its top `cap` coefficients
    /// kept for the second ([`BrickPlan::encode_kept`]) where the bricks do not refine.
    pub fn score_keeping_top(
        &self,
        source: &dyn BrickSource,
        i: usize,
        cap: u64,
    ) -> Result<(ScoreSummary, Option<KeptTop>), BrickError> {
        let v = self.read(source, i)?;
        score_keeping_top(&v, &self.base, cap, &|_, _| {}).map_err(self.compress_error(i))
    }

    /// How many of brick `i`'s top coefficients its first pass should keep for the second
    /// ([`BrickPlan::score_keeping_top`]): [`TOP_SPARE`] times its share of the count the
    /// whole's target is expected to keep (of a fraction, that fraction of its padded grid; of
    /// a count or bytes, its voxels' share), and [`TOP_FLOOR`] more. `None` where nothing
    /// is worth keeping: the bricks refine (the second pass needs the whole transform), or
    /// the target's count is not known before the scores are (a Q_V target, or everything).
    pub fn top_cap(&self, i: usize) -> Option<u64> {
        self.top_cap_within(i, 1)
    }

    /// [`BrickPlan::top_cap`] where the whole's target is shared by `parts` volumes of this
    /// plan's size (the components of a time series), so that a count or byte target is
    /// spread over all of them.
    pub(crate) fn top_cap_within(&self, i: usize, parts: usize) -> Option<u64> {
        if self.base.refine.is_some() {
            return None;
        }
        let (_, d) = *self.grid.get(i)?;
        let voxels = d.iter().map(|v| *v as f64).product::<f64>();
        let whole = self.dims.iter().map(|v| *v as f64).product::<f64>();
        // A count or byte target spreads over the voxels; a fraction is of the padded grids'
        // coefficients, which small bricks have many more of than voxels.
        let share = voxels / (whole * parts.max(1) as f64);
        let expected = match self.target {
            Target::Fraction(f) => {
                let levels = self.choices.levels;
                let margin = bridge_margin(self.base.family, levels);
                let padded = Geometry::new(d, self.base.family, levels, margin)
                    .map_or(voxels, |g| g.coefficient_count() as f64);
                f.clamp(0.0, 1.0) * padded * self.channels as f64
            }
            Target::Coefficients(c) => c as f64 * share,
            Target::Bytes(b) => self.coefficients_per_byte.unwrap_or(1.0) * b as f64 * share,
            Target::QvPercent(_) | Target::All => return None,
        };
        let cap = (TOP_SPARE * expected).ceil();
        cap.is_finite().then(|| cap as u64 + TOP_FLOOR)
    }

    /// Brick `i` compressed from its kept `top` keeping `count` coefficients: the file
    /// [`BrickPlan::encode`] writes for it, without reading or transforming it again. `None`
    /// where the top was not kept under this plan's options or does not cover the count.
    pub fn encode_kept(
        &self,
        i: usize,
        top: &KeptTop,
        count: u64,
    ) -> Option<Result<(Vec<u8>, u64), BrickError>> {
        if !top.scored_with(&self.base) || !top.covers(count) {
            return None;
        }
        Some(
            top.compress(count)
                .map(|c| (c.bytes, c.header.kept))
                .map_err(self.compress_error(i)),
        )
    }

    /// The first pass for brick `i` of volume `volume` (0; a series' component), keeping its
    /// top `cap` coefficients in `tops` where a cap is given and the bricks do not refine.
    pub fn score_into(
        &self,
        source: &dyn BrickSource,
        i: usize,
        tops: &KeptTops,
        volume: usize,
        cap: Option<u64>,
    ) -> Result<ScoreSummary, BrickError> {
        self.base.stop.check().map_err(self.compress_error(i))?;
        let Some(cap) = cap else {
            return self.score(source, i);
        };
        let (summary, top) = self.score_keeping_top(source, i, cap)?;
        if let Some(top) = top {
            tops.keep((volume, self.grid[i]), top);
        }
        Ok(summary)
    }

    /// Brick `i` of volume `volume` compressed as [`BrickPlan::encode`] does: from its top
    /// kept in `tops` where that covers `count`, else read and transformed again (each counted
    /// in `tops`). A brick with no top kept, transformed again for a count within a top of
    /// `cap` coefficients (`Some`: [`BrickPlan::top_cap`]), keeps that top in `tops` on the
    /// way (within their budget), so that the rate search's next trial codes it without
    /// transforming it again (a run resumed from a checkpoint without its tops, a worker's
    /// part of a brick another worker scored).
    pub fn encode_from(
        &self,
        source: &dyn BrickSource,
        i: usize,
        count: Option<u64>,
        tops: &KeptTops,
        volume: usize,
        cap: Option<u64>,
    ) -> Result<(Vec<u8>, u64), BrickError> {
        use std::sync::atomic::Ordering::Relaxed;
        self.base.stop.check().map_err(self.compress_error(i))?;
        let key = (volume, self.grid[i]);
        let held = tops.get(&key);
        let kept = match (count, &held) {
            (Some(count), Some(top)) => self.encode_kept(i, top, count),
            _ => None,
        };
        if let Some(coded) = kept {
            tops.reused.fetch_add(1, Relaxed);
            return coded;
        }
        tops.transformed.fetch_add(1, Relaxed);
        // (A count beyond the cap needs the whole transform; a top already held that does not
        // cover this count is not replaced.)
        if let (Some(count), Some(cap), None) = (count, cap, &held) {
            if count <= cap {
                if let (_, Some(top)) = self.score_keeping_top(source, i, cap)? {
                    if let Some(coded) = self.encode_kept(i, &top, count) {
                        tops.keep(key, top);
                        return coded;
                    }
                }
            }
        }
        self.encode(source, i, count)
    }

    /// Brick `i` compressed as a `.wsp` of its own, keeping its top `count` coefficients
    /// (`None`: all), and the count it kept.
    pub fn encode(
        &self,
        source: &dyn BrickSource,
        i: usize,
        count: Option<u64>,
    ) -> Result<(Vec<u8>, u64), BrickError> {
        let v = self.read(source, i)?;
        let o = CompressOptions {
            target: count.map_or(Target::All, Target::Coefficients),
            ..self.base.clone()
        };
        // A byte target's search counts on the refit's prune (`REFINED_PER_ORACLE`); a count
        // the user gave (a count, a fraction, a Q_V) is kept whole, so the bricks' counts sum
        // to it.
        let fill = match self.target {
            Target::Bytes(_) => crate::encode::CountFill::Pruned,
            _ => crate::encode::CountFill::Exact,
        };
        let c = crate::encode::compress_counting(&v, &o, &|_, _| {}, fill)
            .map_err(self.compress_error(i))?;
        Ok((c.bytes, c.header.kept))
    }

    /// The container of the bricks' files (in grid order) and the counts they kept, and its
    /// manifest (offsets filled in).
    pub fn assemble(&self, bricks: &[(Vec<u8>, u64)]) -> Result<(Vec<u8>, Manifest), BrickError> {
        let kept: Vec<u64> = bricks.iter().map(|(_, k)| *k).collect();
        let mut manifest = self.manifest(&kept);
        let files: Vec<&[u8]> = bricks.iter().map(|(b, _)| b.as_slice()).collect();
        let bytes = write_bricked(&mut manifest, &files)?;
        Ok((bytes, manifest))
    }

    /// The container's manifest section for bricks of (length, CRC-32, coefficients kept) in
    /// grid order, whose bytes follow it in that order, and its manifest (offsets filled in):
    /// for a container written as its bricks stream from elsewhere.
    pub fn manifest_section_for(
        &self,
        bricks: &[(u64, u32, u64)],
    ) -> Result<(Vec<u8>, Manifest), BrickError> {
        let kept: Vec<u64> = bricks.iter().map(|b| b.2).collect();
        let mut manifest = self.manifest(&kept);
        let placed: Vec<(u64, u32)> = bricks.iter().map(|b| (b.0, b.1)).collect();
        let section = wavesplat_codec::format::bricked::place_bricks(&mut manifest, &placed)?;
        Ok((section, manifest))
    }

    /// Writes the container of the coded bricks (in grid order, waiting in a [`Spill`]) to
    /// `out`: the manifest section, then each brick copied from the spill, in one pass.
    pub fn write_container(
        &self,
        bricks: &[CodedBrick<SpilledBrick>],
        out: &mut dyn std::io::Write,
    ) -> Result<ContainerWritten, BrickError> {
        let placed: Vec<(u64, u32, u64)> =
            bricks.iter().map(|c| (c.len, c.file.crc, c.kept)).collect();
        let (section, manifest) = self.manifest_section_for(&placed)?;
        out.write_all(&section).map_err(BrickError::Output)?;
        let mut bytes = section.len() as u64;
        for c in bricks {
            c.file.copy_to(c.len, out).map_err(BrickError::Output)?;
            bytes += c.len;
        }
        out.flush().map_err(BrickError::Output)?;
        let headers: u64 = bricks.iter().map(|c| c.file.header).sum();
        Ok(ContainerWritten {
            manifest,
            bytes,
            overhead: section.len() as u64 + headers,
        })
    }

    /// The bytes of the container's manifest section for this plan's grid: its fields have fixed
    /// widths, so this is exact before any brick is coded (what a byte target sets aside).
    pub fn manifest_len(&self) -> u64 {
        manifest_section(&self.manifest(&vec![0; self.grid.len()])).len() as u64
    }

    /// The manifest of bricks that kept `kept` coefficients each, in grid order (offsets,
    /// lengths and CRCs to be placed).
    fn manifest(&self, kept: &[u64]) -> Manifest {
        Manifest {
            dims: self.dims,
            channels: self.channels,
            spacing: self.spacing,
            placement: self.placement,
            brick: self.brick,
            bricks: self
                .grid
                .iter()
                .zip(kept)
                .map(|((origin, dims), kept)| BrickEntry {
                    origin: *origin,
                    dims: *dims,
                    offset: 0,
                    length: 0,
                    crc: 0,
                    kept: *kept,
                })
                .collect(),
            version: wavesplat_codec::format::bricked::BRICKED_VERSION,
        }
    }
}

/// The origin and dimensions of the brick with the most voxels in `grid` (the first such).
fn largest_brick(grid: &[([u64; 3], [usize; 3])]) -> ([u64; 3], [usize; 3]) {
    grid.iter()
        .copied()
        .rev()
        .max_by_key(|(_, d)| d.iter().product::<usize>())
        .unwrap_or(([0; 3], [1; 3]))
}

fn check_options(opts: &CompressOptions, brick: usize) -> Result<(), BrickError> {
    if brick < MIN_BRICK {
        return Err(BrickError::InvalidOption(format!(
            "brick edge {brick}; at least {MIN_BRICK}"
        )));
    }
    if opts.family == wavesplat_codec::family::Family::Cubic {
        // Measured: every coefficient of cubic bricks draws the whole at 36 dB against the
        // reference ray caster (21 dB before the bridge) where the unbricked file draws 53 dB.
        // A cubic spline's coefficients near a face come from the interpolation prefilter,
        // which reaches a few voxels into the neighbour (its pole decays by 0.27 a voxel), so
        // a brick would need its neighbours' voxels to match the whole; refused until then.
        return Err(BrickError::InvalidOption(
            "the cubic family is not supported for bricked volumes yet (its bricks do not \
             draw the whole accurately); use linear (the default) or haar"
                .into(),
        ));
    }
    match opts.target {
        Target::Fraction(f) if !(f > 0.0 && f <= 1.0) => Err(BrickError::InvalidOption(format!(
            "target fraction {f}; allowed (0, 1]"
        ))),
        Target::QvPercent(q) if !(q > 0.0 && q <= 100.0) => Err(BrickError::InvalidOption(
            format!("target Q_V {q} %; allowed (0, 100]"),
        )),
        _ => Ok(()),
    }
}

/// Refuses a depth that does not fit every brick of `grid`.
fn check_depth(grid: &[([u64; 3], [usize; 3])], levels: usize) -> Result<(), BrickError> {
    match grid.iter().find(|(_, d)| Geometry::max_levels(*d) < levels) {
        Some((_, d)) => Err(BrickError::InvalidOption(format!(
            "depth M = {levels} does not fit a {}x{}x{} brick",
            d[0], d[1], d[2]
        ))),
        None => Ok(()),
    }
}

/// One depth for every brick: the one asked for, or the smallest brick's default; a byte
/// target compares depths as the single-volume search does, on a sample of the bricks
/// ([`compare_depths`]), which also gives the coefficients per byte the sample kept at the
/// depth chosen.
fn choose_levels(
    source: &dyn BrickSource,
    opts: &CompressOptions,
    brick: usize,
    grid: &[([u64; 3], [usize; 3])],
    shared: &SharedChoices,
) -> Result<(usize, Option<f64>), BrickError> {
    let deepest = grid
        .iter()
        .map(|(_, d)| default_levels(*d, opts.family))
        .min()
        .unwrap_or(0);
    match (opts.levels, opts.target) {
        (Some(m), _) => Ok((m, None)),
        (None, Target::Bytes(total)) if grid.len() > 1 && deepest >= 2 => match opts.depth_search {
            DepthSearch::Compare => {
                compare_depths(source, opts, brick, grid, shared, deepest, total)
            }
            DepthSearch::Predict => {
                predict_depth(source, opts, brick, grid, shared, deepest, total).map(|m| (m, None))
            }
        },
        (None, _) => Ok((deepest, None)),
    }
}

/// Coefficients per byte of refined bricks over those of oracle bricks at the same count:
/// least-squares refinement prunes and shrinks values, so a byte target's search started from
/// the depth sample's oracle ratio landed its first trial 7–9 % under (the MRI in 128³ bricks
/// at 1 MB: 1.406 against 1.312, ×1.072; resampled to 512³ in 256³ bricks: 1.594 against
/// 1.481, ×1.077), one trial more than needed.
const REFINED_PER_ORACLE: f64 = 1.07;

/// A brick of a grid: its first voxel in the whole and its dimensions.
pub(crate) type GridBrick = ([u64; 3], [usize; 3]);

/// The sample of `grid` a depth choice compresses ([`depth_sample`]) and its share of the
/// bytes `total` (its share of the voxels, each side's manifest allowed for).
fn sample_and_bytes(grid: &[GridBrick], total: u64) -> (Vec<GridBrick>, u64) {
    let sample: Vec<GridBrick> = depth_sample(grid.len()).iter().map(|&i| grid[i]).collect();
    let voxels = |g: &[GridBrick]| -> f64 {
        g.iter()
            .map(|(_, d)| d.iter().map(|v| *v as f64).product::<f64>())
            .sum()
    };
    let share = voxels(&sample) / voxels(grid).max(1.0);
    let bytes = (total.saturating_sub(manifest_allowance(grid.len())) as f64 * share) as u64
        + manifest_allowance(sample.len());
    (sample, bytes)
}

/// The plan of the bricks `sample` as a bricked volume of their own at depth `m`, allocated
/// `bytes` as oracle files (no refinement: the whole's depth search scores its depths on
/// oracle files too, whose ranking of depths predicts the refined files', BENCHMARKS.md).
fn sample_plan(
    source: &dyn BrickSource,
    opts: &CompressOptions,
    brick: usize,
    (sample, bytes): (&[GridBrick], u64),
    shared: &SharedChoices,
    m: usize,
) -> Result<BrickPlan, BrickError> {
    let oracle = CompressOptions {
        target: Target::Bytes(bytes),
        refine: None,
        ..opts.clone()
    };
    let choices = SharedChoices {
        levels: m,
        ..shared.clone()
    };
    BrickPlan::build(source, &oracle, brick, sample.to_vec(), choices)
}

/// A sample's `plan` allocated on this process's pool, quietly; `None` when its target does
/// not fit the sample at the plan's depth (the options were checked: an invalid option left is
/// a target below the sample's minimum).
fn allocate_sample(
    source: &dyn BrickSource,
    plan: &BrickPlan,
) -> Result<Option<Allocated<Vec<u8>>>, BrickError> {
    let quiet = |_| {};
    match allocate(
        plan,
        &LocalBricks {
            source,
            progress: &quiet,
            checkpoint: None,
            tops: KeptTops::for_plan(plan),
        },
    ) {
        Ok(a) => Ok(Some(a)),
        Err(BrickError::InvalidOption(_)) => Ok(None),
        Err(e) => Err(e),
    }
}

/// The coefficients of the coarse band of depth `m` over the bricks `sample` (their own
/// voxels, not their padded grids), per channel.
fn coarse_band_cells(sample: &[GridBrick], m: usize) -> u64 {
    sample
        .iter()
        .map(|(_, d)| d.iter().map(|v| v.div_ceil(1 << m) as u64).product::<u64>())
        .sum()
}

/// The depth of a bricked byte target under a predicted depth search (`--effort fast`), by the
/// whole's predicting rule (`encode::rate`, [`crate::encode::worth_going_shallower`]) on the bricks: the sample
/// ([`depth_sample`]) allocated once at the deepest default depth, as oracle files, and one
/// level shallower at a time while the coefficients it kept (per channel) afford
/// `SHALLOWER_KEPT` of the next coarse band. The band is counted over the bricks' own voxels:
/// their padded grids, a margin on every side, count up to twice as many and would keep small
/// bricks too deep. One compression of the sample, no decoding: a fraction of
/// [`compare_depths`]' time.
fn predict_depth(
    source: &dyn BrickSource,
    opts: &CompressOptions,
    brick: usize,
    grid: &[GridBrick],
    shared: &SharedChoices,
    deepest: usize,
    total: u64,
) -> Result<usize, BrickError> {
    let (sample, bytes) = sample_and_bytes(grid, total);
    let plan = sample_plan(source, opts, brick, (&sample, bytes), shared, deepest)?;
    let kept: u64 = match allocate_sample(source, &plan)? {
        Some(a) => a.bricks.iter().map(|b| b.kept).sum(),
        // Too small for the deepest depth's coarse band: a shallower one's is larger still.
        None => return Ok(deepest),
    };
    let per_channel = kept as f64 / plan.channels.max(1) as f64;
    let mut m = deepest;
    while m >= 2 && per_channel >= SHALLOWER_KEPT * coarse_band_cells(&sample, m - 1) as f64 {
        m -= 1;
    }
    tracing::debug!(levels = m, bytes, kept, "bricked depth predicted");
    Ok(m)
}

/// Bricks a depth comparison compresses (at most): spread over the grid, a few percent of a
/// large volume's.
const DEPTH_SAMPLE: usize = 8;

/// The bricks of a grid of `n` a depth comparison compresses: a quarter of them (at least 2,
/// at most [`DEPTH_SAMPLE`]; all of a grid of 2), evenly spaced in grid order (x fastest),
/// each in the middle of its stretch. Each depth compared costs the sample's compression, so
/// a small grid's comparison stays below its own allocation.
fn depth_sample(n: usize) -> Vec<usize> {
    let k = (n / 4).clamp(2, DEPTH_SAMPLE).min(n);
    (0..k).map(|j| ((2 * j + 1) * n) / (2 * k)).collect()
}

/// The depth of a bricked byte target, compared as the whole's search compares depths
/// (`encode::rate`) but from both sides of the bricks' default `deepest` ([`search_depth`]:
/// the default and both neighbours, then on in the closest one's direction, deeper up to
/// [`deepest_compared`] of the smallest brick). (The whole's search tries a third shallower
/// depth only when its file affords the next coarse band; the bricks' padded grids, a margin
/// on every side, count up to twice their voxels, so that gate kept 32³ bricks of a CT
/// phantom at M = 2 where M = 1 draws 1 dB closer.) A depth is scored on a sample of the
/// bricks ([`depth_sample`]) allocated together at their share of the bytes (one global
/// threshold over them, as for the whole), decoded, and held to the originals by their three
/// axis X-ray views ([`sample_view_error`]); the closer depth wins, the default on a tie.
///
/// Why not each brick's own search: a brick alone at its share of the bytes goes deeper than
/// the whole does (measured on the MRI at 87 kB and 1 MB, BENCHMARKS.md "Bricked volumes"),
/// which costs both quality and drawing time (coarse levels splat large footprints).
fn compare_depths(
    source: &dyn BrickSource,
    opts: &CompressOptions,
    brick: usize,
    grid: &[GridBrick],
    shared: &SharedChoices,
    deepest: usize,
    total: u64,
) -> Result<(usize, Option<f64>), BrickError> {
    let (sample, bytes) = sample_and_bytes(grid, total);
    // The originals' views, read once for every depth compared.
    let originals = sample
        .par_iter()
        .map(|&(origin, dims)| {
            let v = source
                .read(origin, dims)
                .map_err(|source| BrickError::Read { origin, source })?;
            Ok(channel_views(&v))
        })
        .collect::<Result<Vec<_>, BrickError>>()?;
    // Coefficients per byte each depth's sample kept, in the order scored: the next depth's
    // rate search starts from the last one's, the whole's from the chosen depth's (they
    // differ by ~1 % between depths, and a byte per coefficient is 30 % off on the MRI).
    let mut per_byte: Vec<(usize, f64)> = Vec::new();
    // A depth's axis-view error on the sample (`None`: too small for its coarse band).
    let score = |m: usize| -> Result<Option<f64>, BrickError> {
        // A depth whose bricks would not fit the memory limit is not a candidate (a deeper
        // one's bricks are larger still).
        let mut plan = match sample_plan(source, opts, brick, (&sample, bytes), shared, m) {
            Err(e) if e.is_memory_refusal() => return Ok(None),
            plan => plan?,
        };
        plan.coefficients_per_byte = per_byte.last().map(|&(_, r)| r);
        let scored = sample_view_error(source, &plan, &originals)?;
        tracing::debug!(levels = m, bytes, ?scored, "bricked depth candidate");
        Ok(scored.map(|(error, ratio)| {
            per_byte.push((m, ratio));
            error
        }))
    };
    let cap = grid
        .iter()
        .map(|(_, d)| deepest_compared(*d, opts.family))
        .min()
        .unwrap_or(deepest);
    let chosen = search_depth(deepest, cap, score)?;
    let ratio = per_byte
        .iter()
        .find(|&&(m, _)| m == chosen)
        .map(|&(_, r)| r);
    Ok((chosen, ratio))
}

/// The depth a comparison settles on, given each depth's error (`score`; `None`: the
/// target does not fit that depth): `default` and its two neighbours (one level deeper, up
/// to `cap`; one shallower, down to 1) are scored, and from the closest of the three the
/// search goes on in its direction, one level at a time while the next depth comes closer. A
/// depth that does not fit ends its direction (a shallower depth's coarse band is larger
/// still; a deeper one is past what fits); the default on a tie, and when it does not fit.
///
/// Both neighbours, because the error against the depth need not have one minimum, on
/// either side: the sample of the MRI resampled to 512³ in 256³ bricks scored M = 2 below
/// the default 3, and 4 and 5 below both, so a search that went shallower first stopped at
/// 2, 7 dB Q_I from M = 5; the MRI in 128³ bricks at 1 MB scored 4 and 5 below 3, where M = 2
/// draws 0.6 dB closer than 5 (BENCHMARKS.md, "Scale and robustness").
fn search_depth<E>(
    default: usize,
    cap: usize,
    mut score: impl FnMut(usize) -> Result<Option<f64>, E>,
) -> Result<usize, E> {
    let Some(error) = score(default)? else {
        return Ok(default);
    };
    let mut best = (error, default);
    let deeper = if default < cap {
        score(default + 1)?
    } else {
        None
    };
    let shallower = if default > 1 {
        score(default - 1)?
    } else {
        None
    };
    let closer = |e: Option<f64>, than: f64| e.filter(|e| *e < than);
    match (closer(deeper, error), closer(shallower, error)) {
        // Deeper, unless the shallower neighbour came closer still.
        (Some(d), s) if s.is_none_or(|s| d <= s) => {
            best = (d, default + 1);
            for m in default + 2..=cap {
                match score(m)? {
                    Some(error) if error < best.0 => best = (error, m),
                    _ => break,
                }
            }
        }
        (_, Some(s)) => {
            best = (s, default - 1);
            for m in (1..default - 1).rev() {
                match score(m)? {
                    Some(error) if error < best.0 => best = (error, m),
                    _ => break,
                }
            }
        }
        _ => {}
    }
    Ok(best.1)
}

/// The three axis X-ray views of each channel of `v` ([`axis_views`]).
fn channel_views(v: &Volume) -> Vec<[Vec<f64>; 3]> {
    let dims = v.dims();
    v.channels()
        .iter()
        .map(|f| {
            axis_views(dims, &|x, y, z| {
                f64::from(f[x + dims[0] * (y + dims[1] * z)])
            })
        })
        .collect()
}

/// The sample's bricks as `plan` holds them (at one depth, its target their share of the bytes)
/// allocated as a bricked volume of their own, decoded and held to their originals (whose
/// views are `originals`, per brick and channel): the mean over the three axes of
/// ln Σ ‖P_v f − P_v f̂‖² over bricks and channels (P_v the sum along axis v over a brick's
/// box), as the whole's depth comparison scores a depth, and the coefficients the files kept
/// per byte of them. `None` when the target does not fit the sample at this depth.
fn sample_view_error(
    source: &dyn BrickSource,
    plan: &BrickPlan,
    originals: &[Vec<[Vec<f64>; 3]>],
) -> Result<Option<(f64, f64)>, BrickError> {
    let Some(allocated) = allocate_sample(source, plan)? else {
        return Ok(None);
    };
    let energies = allocated
        .bricks
        .par_iter()
        .zip(originals)
        .zip(&plan.grid)
        .map(|((coded, original), (origin, _))| {
            let decoded =
                crate::decode::decompress(&coded.file).map_err(|source| BrickError::Decode {
                    origin: *origin,
                    source,
                })?;
            let mut energy = [0.0f64; 3];
            for (f, g) in original.iter().zip(channel_views(&decoded)) {
                for ((e, f), g) in energy.iter_mut().zip(f).zip(&g) {
                    *e += f.iter().zip(g).map(|(a, b)| (a - b).powi(2)).sum::<f64>();
                }
            }
            Ok(energy)
        })
        .collect::<Result<Vec<[f64; 3]>, BrickError>>()?;
    let mut energy = [0.0f64; 3];
    for e in &energies {
        energy.iter_mut().zip(e).for_each(|(a, b)| *a += b);
    }
    let error = energy
        .iter()
        .map(|e| (e + f64::MIN_POSITIVE).ln())
        .sum::<f64>()
        / 3.0;
    let kept: u64 = allocated.bricks.iter().map(|b| b.kept).sum();
    let len: u64 = allocated.bricks.iter().map(|b| b.len).sum();
    Ok(Some((error, kept as f64 / len.max(1) as f64)))
}

/// One brick compressed by a [`BrickWork`]: its file (bytes, or wherever the work keeps
/// them), its length and the coefficients it kept.
#[derive(Debug, Clone)]
pub struct CodedBrick<F> {
    /// The file, or a handle to it.
    pub file: F,
    /// Its length in bytes.
    pub len: u64,
    /// Coefficients it kept.
    pub kept: u64,
}

/// Whatever runs the two passes over all bricks of a plan: the rayon pool of this process
/// ([`LocalBricks`]), or jobs spread over workers. [`allocate`] asks for the scores once and
/// for the bricks compressed once per trial of the rate search.
pub trait BrickWork {
    /// Where a compressed brick's file is kept.
    type File;
    /// Every brick's score histogram, in grid order.
    fn score_all(&self, plan: &BrickPlan) -> Result<Vec<ScoreSummary>, BrickError>;
    /// Every brick compressed keeping `counts[i]` coefficients (`None`: all), in grid order;
    /// `trial` counts the rate search's trials.
    fn encode_all(
        &self,
        plan: &BrickPlan,
        counts: Option<&[u64]>,
        trial: usize,
    ) -> Result<Vec<CodedBrick<Self::File>>, BrickError>;
}

/// The bricks a rate allocation chose, and what it summed over them.
#[derive(Debug)]
pub struct Allocated<F> {
    /// The chosen trial's bricks, in grid order.
    pub bricks: Vec<CodedBrick<F>>,
    /// Coefficients of the padded grids of all bricks, all channels.
    pub total_coefficients: u64,
    /// Non-zero coefficients over all bricks.
    pub nonzero: u64,
}

/// Allocates the whole's target across the plan's bricks as for the whole volume: the bricks'
/// score histograms summed give one global threshold; a byte target searches on its count
/// (log bytes against log count, from one byte per coefficient), each trial compressing every
/// brick. The container's size is the bricks' plus its manifest's, known exactly beforehand
/// ([`BrickPlan::manifest_len`]: an estimate, [`manifest_allowance`], left small files up to 4 %
/// under their target).
pub fn allocate<W: BrickWork>(
    plan: &BrickPlan,
    work: &W,
) -> Result<Allocated<W::File>, BrickError> {
    allocate_units(
        plan.target,
        plan.grid.len(),
        plan.manifest_len(),
        plan.coefficients_per_byte,
        || work.score_all(plan),
        |counts, trial| work.encode_all(plan, counts, trial),
    )
}

/// The allocation of [`allocate`] over any `of` units compressed apart (a plan's bricks, or
/// a series' components and their bricks): `score_all` gives every unit's score histogram,
/// `encode_all` every unit compressed keeping the counts given (`None`: all) in a trial of the
/// rate search; `overhead` is what the container adds to the units' bytes, counted against a
/// byte target, whose search starts from `coefficients_per_byte` of the units' bytes where it
/// is known (`None`: one per byte).
pub fn allocate_units<F>(
    target: Target,
    of: usize,
    overhead: u64,
    coefficients_per_byte: Option<f64>,
    score_all: impl FnOnce() -> Result<Vec<ScoreSummary>, BrickError>,
    mut encode_all: impl FnMut(Option<&[u64]>, usize) -> Result<Vec<CodedBrick<F>>, BrickError>,
) -> Result<Allocated<F>, BrickError> {
    let summaries: Vec<ScoreSummary> = match target {
        Target::All => Vec::new(),
        _ => score_all()?,
    };
    let mut whole = SummedScores::new();
    summaries.iter().for_each(|s| whole.add(s));
    if matches!(target, Target::QvPercent(_)) && !summaries.iter().all(|s| s.has_energies()) {
        return Err(BrickError::InvalidOption(
            "a Q_V target needs the parts' energies, and a score summary came without them".into(),
        ));
    }
    let (total_coefficients, nonzero) = (whole.total_coefficients, whole.nonzero);
    let global_k = |k: u64| per_brick_counts(&summaries, &whole, k);
    let done = |bricks| Allocated {
        bricks,
        total_coefficients,
        nonzero,
    };
    let bricks = match target {
        Target::All => encode_all(None, 0)?,
        Target::Coefficients(c) => encode_all(Some(&global_k(c)), 0)?,
        Target::Fraction(f) => {
            let k = (f * total_coefficients as f64).round() as u64;
            encode_all(Some(&global_k(k)), 0)?
        }
        Target::QvPercent(q) => {
            // Of the energy the bricks can keep (each summary's total is its selectable
            // energy: a bridge's coefficients wholly outside the box are never kept, and
            // counting them once made every Q_V target keep everything).
            let k = count_for_energy(&whole, q / 100.0 * whole.total_energy);
            encode_all(Some(&global_k(k)), 0)?
        }
        Target::Bytes(target) => {
            let manifest_guess = overhead;
            let units_bytes = target.saturating_sub(manifest_guess);
            // Aimed 1 % under the target, as the steps below aim.
            let first = match coefficients_per_byte {
                Some(r) if r.is_finite() && r > 0.0 => (0.99 * r * units_bytes as f64) as u64,
                _ => units_bytes,
            };
            let mut k = first.max(1).min(nonzero.max(1));
            let mut best: Option<(u64, Vec<CodedBrick<F>>)> = None;
            let mut last: Option<(f64, f64)> = None;
            // The largest count known to fit and the smallest known to overflow.
            let (mut fits_k, mut over_k) = (0u64, u64::MAX);
            // The smallest file tried: its bytes and its count (for the refusal below).
            let mut smallest = (u64::MAX, 0u64);
            // The bytes at `fits_k` and at `over_k`, and whether the smallest count was tried
            // because nothing fitted (see below).
            let mut bracket_bytes = (0u64, u64::MAX);
            let mut probed = false;
            for trial in 0..BYTE_TRIALS {
                let b = encode_all(Some(&global_k(k)), trial)?;
                let bytes: u64 = b.iter().map(|c| c.len).sum::<u64>() + manifest_guess;
                tracing::debug!(trial, kept = k, bytes, target, "bricked rate search trial");
                smallest = smallest.min((bytes, k));
                let fits = bytes <= target;
                if fits {
                    if k > fits_k {
                        (fits_k, bracket_bytes.0) = (k, bytes);
                    }
                } else if k < over_k {
                    (over_k, bracket_bytes.1) = (k, bytes);
                }
                if fits && best.as_ref().is_none_or(|(bb, _)| bytes > *bb) {
                    best = Some((bytes, b));
                }
                if fits && (bytes as f64 >= 0.98 * target as f64 || k >= nonzero) {
                    break;
                }
                let (lk, lb) = ((k as f64).ln(), (bytes as f64).ln());
                let measured = match last {
                    Some((pk, pb)) if (lk - pk).abs() > 1e-9 => Some((lb - pb) / (lk - pk)),
                    _ => None,
                };
                let slope = measured.map_or(1.0, |s| s.clamp(0.3, 3.0));
                last = Some((lk, lb));
                // Aim 1 % under the target; outside the bracket found so far, bisect it
                // (geometrically) instead.
                let guess = (lk + ((0.99 * target as f64).ln() - lb) / slope).exp();
                let mut next = (guess.round() as u64).clamp(1, nonzero.max(1));
                // Nothing fits after half the trials and the file hardly shrinks with the
                // count: the parts' headers are most of it, and the steps above creep down a
                // tenth at a time. The smallest count tells at once whether any file fits;
                // if it does, the file is about linear in the count between it and the
                // smallest count that overflows, and the rest of the search interpolates so.
                if fits_k == 0
                    && !fits
                    && k > 1
                    && trial + 1 >= BYTE_TRIALS / 2
                    && measured.is_some_and(|s| s < 0.3)
                {
                    next = 1;
                    probed = true;
                } else if probed && fits_k > 0 && over_k != u64::MAX {
                    let (lo, hi) = (bracket_bytes.0 as f64, bracket_bytes.1 as f64);
                    let at = (0.99 * target as f64 - lo) / (hi - lo).max(1.0);
                    next = (fits_k as f64 + at * (over_k - fits_k) as f64).round() as u64;
                    next = next.clamp(fits_k + 1, over_k.saturating_sub(1).max(fits_k + 1));
                }
                if next <= fits_k || next >= over_k {
                    next = match over_k {
                        u64::MAX => (fits_k.max(1) * 2).min(nonzero.max(1)),
                        o => ((fits_k.max(1) as f64 * o as f64).sqrt().round() as u64).max(1),
                    };
                }
                if next == k || next <= fits_k || next >= over_k {
                    break;
                }
                k = next;
            }
            match best {
                Some((_, b)) => b,
                None => {
                    let (bytes, kept) = smallest;
                    return Err(BrickError::InvalidOption(format!(
                        "a target of {target} bytes is too small for {of} parts: the smallest \
                         file tried, keeping {kept} coefficient(s) in all, takes {bytes} bytes \
                         (every part's header and the container's manifest count)"
                    )));
                }
            }
        }
    };
    Ok(done(bricks))
}

/// The bytes a byte target's search sets aside for the container's manifest of `bricks`
/// bricks (an upper estimate).
pub fn manifest_allowance(bricks: usize) -> u64 {
    64 + 72 * bricks as u64
}

/// How many times its expected share of the kept coefficients a brick's first pass keeps
/// ([`BrickPlan::top_cap`]). A brick's share of one global threshold follows its content, not
/// its size: in its voxels' share, the densest brick of the MRI at 1.25 % in 64³ bricks keeps
/// 7.4 times, at 0.5 % in 32³ bricks 18 times, and of the CT phantom at 1 % in 64³ bricks 4.2
/// times. Sized by 8 times the padded grid's share of a fraction, none of the MRI's 48 bricks
/// of 64³ nor its 336 of 32³ is transformed again; 4 times the voxels' share left 12 of the 48
/// to transform again, and 12 times kept and sorted more than it saved (BENCHMARKS.md).
pub const TOP_SPARE: f64 = 8.0;

/// Coefficients a brick's first pass keeps beyond [`TOP_SPARE`] times its share, so that
/// small bricks and low rates are covered too.
pub const TOP_FLOOR: u64 = 1024;

/// The most bytes the kept tops of one allocation hold in memory ([`KeptTops`]); under a
/// memory limit, at most what the bricks being compressed leave free. Tops kept after the
/// budget is spent go to a temporary file where one is allowed ([`KeptTops::spilling_in`]),
/// else they are dropped and their bricks transformed again.
pub const TOP_BUDGET: u64 = 512 << 20;

pub use crate::encode::TOP_DISK_SHARE;

/// Which brick a kept top is of: the volume (0; a time series' component) and the brick.
pub(crate) type TopKey = (usize, GridBrick);

/// The tops the bricks' first passes kept ([`KeptTop`]), by brick, within a budget of bytes in
/// memory and, beyond it, in a temporary file within a share of the free disk; and how many
/// bricks were coded from them and how many transformed again.
#[derive(Default)]
pub struct KeptTops {
    tops: std::sync::Mutex<std::collections::HashMap<TopKey, std::sync::Arc<KeptTop>>>,
    /// The most bytes the tops may hold in memory.
    budget: u64,
    bytes: std::sync::atomic::AtomicU64,
    /// Memory these tops share with others' (a worker's tops of several jobs), counted
    /// beside their own budget; what they hold is given back when they are dropped.
    shared: Option<std::sync::Arc<TopMemory>>,
    /// The directory of the temporary file tops beyond the budget go to (`None`: none).
    spill_dir: Option<Option<std::path::PathBuf>>,
    /// That file and the most bytes it may take, made when the first top goes there (`None`
    /// inside: it could not be made).
    spill: std::sync::OnceLock<Option<(std::sync::Arc<ScratchFile>, u64)>>,
    spilled_bytes: std::sync::atomic::AtomicU64,
    /// Of `bytes`, the metadata of tops moved to the temporary file (counted, never refused).
    metadata_bytes: std::sync::atomic::AtomicU64,
    /// A write to the temporary file failed: nothing more goes there.
    spill_failed: std::sync::atomic::AtomicBool,
    /// Tops moved to the temporary file ([`KeptTops::spilled`]).
    spilled: std::sync::atomic::AtomicUsize,
    /// Bricks coded from a kept top.
    pub reused: std::sync::atomic::AtomicUsize,
    /// Bricks coded by reading and transforming them again.
    pub transformed: std::sync::atomic::AtomicUsize,
}

impl KeptTops {
    /// None yet, to hold at most `budget` bytes (0: keep nothing).
    pub fn new(budget: u64) -> KeptTops {
        let mut tops = KeptTops::default();
        tops.budget = budget;
        tops
    }

    /// None yet, within the budget for compressing `plan` on this process's pool:
    /// [`TOP_BUDGET`], and under a memory limit at most what the limit leaves beside the
    /// process's own share and one brick per thread ([`memory_estimate`] of the largest).
    pub fn for_plan(plan: &BrickPlan) -> KeptTops {
        KeptTops::for_plan_bricks_at_once(plan, rayon::current_num_threads().max(1) as u64)
    }

    /// The same, with `bricks` compressed at once instead of one per thread (a worker running
    /// one part at a time: one).
    pub fn for_plan_bricks_at_once(plan: &BrickPlan, bricks: u64) -> KeptTops {
        let Some(limit) = plan.base.memory_limit else {
            return KeptTops::new(TOP_BUDGET);
        };
        let (_, largest) = largest_brick(&plan.grid);
        let free = memory_estimate(largest, plan.channels, &plan.base).map_or(0, |(n, _)| {
            let per_brick = n.saturating_sub(PROCESS_MEMORY);
            limit.saturating_sub(PROCESS_MEMORY + per_brick.saturating_mul(bricks.max(1)))
        });
        KeptTops::new(free.min(TOP_BUDGET))
    }

    /// The same, with the tops beyond the memory budget moved to an unnamed temporary file in
    /// `dir` (`None`: the temporary directory) while they take at most [`TOP_DISK_SHARE`] of
    /// the free space there; beyond that they are dropped.
    pub fn spilling_in(mut self, dir: Option<&std::path::Path>) -> KeptTops {
        self.spill_dir = Some(dir.map(std::path::Path::to_path_buf));
        self
    }

    /// The same, with the memory the tops hold counted in `shared` too: a top is kept in
    /// memory only where both this budget and the shared one allow.
    pub fn sharing(mut self, shared: std::sync::Arc<TopMemory>) -> KeptTops {
        self.shared = Some(shared);
        self
    }

    /// The most bytes the tops may hold in memory.
    pub fn budget(&self) -> u64 {
        self.budget
    }

    /// Bytes the tops hold in memory.
    pub fn memory_bytes(&self) -> u64 {
        self.bytes.load(std::sync::atomic::Ordering::Relaxed)
    }

    /// Of [`KeptTops::memory_bytes`], what the budgets govern: the tops kept in memory, not
    /// the metadata of those moved to the temporary file.
    pub fn budgeted_bytes(&self) -> u64 {
        use std::sync::atomic::Ordering::Relaxed;
        self.bytes
            .load(Relaxed)
            .saturating_sub(self.metadata_bytes.load(Relaxed))
    }

    /// The temporary file and its budget, made on the first call (`None`: no spill, or it
    /// could not be made, which is said once).
    fn spill_file(&self) -> Option<&(std::sync::Arc<ScratchFile>, u64)> {
        let dir = self.spill_dir.as_ref()?;
        self.spill
            .get_or_init(|| {
                let made = ScratchFile::new(dir.as_deref()).and_then(|file| {
                    let at = dir.clone().unwrap_or_else(tempfile::env::temp_dir);
                    let free = fs2::available_space(&at)?;
                    Ok((
                        std::sync::Arc::new(file),
                        (free as f64 * TOP_DISK_SHARE) as u64,
                    ))
                });
                match made {
                    Ok(spill) => Some(spill),
                    Err(e) => {
                        tracing::warn!(
                            error = %e,
                            "the kept tops beyond their memory budget have no temporary file; \
                             their bricks are transformed again"
                        );
                        None
                    }
                }
            })
            .as_ref()
    }

    /// Keeps `top` for `brick`: in memory if the budget allows, else in the temporary file if
    /// there is one with room, else not at all.
    pub(crate) fn keep(&self, brick: TopKey, mut top: KeptTop) {
        use std::sync::atomic::Ordering::Relaxed;
        let size = top.heap_bytes() as u64;
        let own = self.bytes.fetch_add(size, Relaxed) + size <= self.budget;
        let shared = own && self.shared.as_ref().is_none_or(|m| m.take(size));
        if !shared {
            self.bytes.fetch_sub(size, Relaxed);
            if !self.spill_to_disk(&mut top) {
                return;
            }
            // What stays in memory (the metadata) is counted but not refused: a few kB.
            let metadata = top.heap_bytes() as u64;
            self.bytes.fetch_add(metadata, Relaxed);
            self.metadata_bytes.fetch_add(metadata, Relaxed);
            if let Some(m) = &self.shared {
                m.count(metadata);
            }
        }
        let mut tops = self.tops.lock().unwrap_or_else(|p| p.into_inner());
        tops.insert(brick, std::sync::Arc::new(top));
    }

    /// Moves `top`'s coefficients to the temporary file; whether it did.
    fn spill_to_disk(&self, top: &mut KeptTop) -> bool {
        use std::sync::atomic::Ordering::Relaxed;
        let Some((file, budget)) = self.spill_file() else {
            return false;
        };
        if self.spill_failed.load(Relaxed) {
            return false;
        }
        let size = top.spilled_size();
        if self.spilled_bytes.fetch_add(size, Relaxed) + size > *budget {
            self.spilled_bytes.fetch_sub(size, Relaxed);
            return false;
        }
        if let Some(m) = &self.shared {
            if !m.take_disk(size, *budget) {
                self.spilled_bytes.fetch_sub(size, Relaxed);
                return false;
            }
        }
        match top.spill(file) {
            Ok(()) => {
                self.spilled.fetch_add(1, Relaxed);
                true
            }
            Err(e) => {
                self.spilled_bytes.fetch_sub(size, Relaxed);
                if let Some(m) = &self.shared {
                    m.give_back_disk(size);
                }
                if !self.spill_failed.swap(true, Relaxed) {
                    tracing::warn!(
                        error = %e,
                        "writing a kept top to its temporary file failed; the bricks scored \
                         from now on are transformed again"
                    );
                }
                false
            }
        }
    }

    /// Bricks coded from a kept top, and bricks read and transformed again, so far.
    pub fn counts(&self) -> (usize, usize) {
        use std::sync::atomic::Ordering::Relaxed;
        (self.reused.load(Relaxed), self.transformed.load(Relaxed))
    }

    /// Tops moved to the temporary file so far.
    pub fn spilled(&self) -> usize {
        self.spilled.load(std::sync::atomic::Ordering::Relaxed)
    }

    /// The top kept for `brick`, if any.
    pub(crate) fn get(&self, brick: &TopKey) -> Option<std::sync::Arc<KeptTop>> {
        let tops = self.tops.lock().unwrap_or_else(|p| p.into_inner());
        tops.get(brick).cloned()
    }
}

impl Drop for KeptTops {
    /// Gives the memory and the disk the tops held back to the shared budgets (the temporary
    /// file goes with the last holder of it).
    fn drop(&mut self) {
        if let Some(m) = &self.shared {
            m.give_back(self.memory_bytes());
            m.give_back_disk(
                self.spilled_bytes
                    .load(std::sync::atomic::Ordering::Relaxed),
            );
        }
    }
}

/// A budget of bytes in memory that the [`KeptTops`] of several allocations draw on together
/// ([`KeptTops::sharing`]): a worker running the parts of several bricked jobs at once keeps
/// each job's tops, and all of them within one budget. The tops they move to their temporary
/// files share one disk budget too: the first to spill sets it ([`TOP_DISK_SHARE`] of the free
/// space then), so that many allocations do not each take a share of what the others left.
#[derive(Debug, Default)]
pub struct TopMemory {
    budget: std::sync::atomic::AtomicU64,
    used: std::sync::atomic::AtomicU64,
    disk_budget: std::sync::OnceLock<u64>,
    disk_used: std::sync::atomic::AtomicU64,
}

impl TopMemory {
    /// None used yet, at most `budget` bytes.
    pub fn new(budget: u64) -> TopMemory {
        TopMemory {
            budget: std::sync::atomic::AtomicU64::new(budget),
            ..TopMemory::default()
        }
    }

    /// The same, with at most `bytes` in the temporary files of all allocations together.
    pub fn with_disk_budget(self, bytes: u64) -> TopMemory {
        let _ = self.disk_budget.set(bytes);
        self
    }

    /// Bytes the tops drawing on it hold in their temporary files now.
    pub fn disk_used(&self) -> u64 {
        self.disk_used.load(std::sync::atomic::Ordering::Relaxed)
    }

    /// Takes `size` bytes of the disk budget (set to `first` by the first call where none was
    /// given) if it has them; whether it did.
    fn take_disk(&self, size: u64, first: u64) -> bool {
        use std::sync::atomic::Ordering::Relaxed;
        let budget = *self.disk_budget.get_or_init(|| first);
        if self.disk_used.fetch_add(size, Relaxed) + size > budget {
            self.disk_used.fetch_sub(size, Relaxed);
            return false;
        }
        true
    }

    /// Gives back `size` bytes of the disk budget.
    fn give_back_disk(&self, size: u64) {
        use std::sync::atomic::Ordering::Relaxed;
        let _ = self
            .disk_used
            .fetch_update(Relaxed, Relaxed, |used| Some(used.saturating_sub(size)));
    }

    /// Bytes the tops drawing on it hold now.
    pub fn used(&self) -> u64 {
        self.used.load(std::sync::atomic::Ordering::Relaxed)
    }

    /// The most bytes the tops drawing on it may hold.
    pub fn budget(&self) -> u64 {
        self.budget.load(std::sync::atomic::Ordering::Relaxed)
    }

    /// Sets the most bytes the tops drawing on it may hold (e.g. the smallest budget of the
    /// allocations drawing on it, each within its process's memory limit). Tops already held
    /// beyond it stay; the next ones are refused until there is room.
    pub fn set_budget(&self, budget: u64) {
        self.budget
            .store(budget, std::sync::atomic::Ordering::Relaxed);
    }

    /// Counts `size` bytes held whether or not the budget has them (a spilled top's metadata).
    fn count(&self, size: u64) {
        self.used
            .fetch_add(size, std::sync::atomic::Ordering::Relaxed);
    }

    /// Gives back `size` bytes that tops held.
    fn give_back(&self, size: u64) {
        use std::sync::atomic::Ordering::Relaxed;
        // Never below nothing, should a count and a give-back race.
        let _ = self
            .used
            .fetch_update(Relaxed, Relaxed, |used| Some(used.saturating_sub(size)));
    }

    /// Takes `size` bytes if the budget has them; whether it did.
    fn take(&self, size: u64) -> bool {
        use std::sync::atomic::Ordering::Relaxed;
        if self.used.fetch_add(size, Relaxed) + size > self.budget() {
            self.used.fetch_sub(size, Relaxed);
            return false;
        }
        true
    }
}

/// The bricks of a plan compressed on this process's rayon pool, each read from `source`
/// when its turn comes (one brick per thread in memory), with progress. Where the bricks do
/// not refine, the first pass keeps each brick's top coefficients ([`KeptTops`]) and the
/// second codes from them.
pub struct LocalBricks<'a> {
    /// Where the bricks come from.
    pub source: &'a dyn BrickSource,
    /// Called as bricks finish.
    pub progress: &'a (dyn Fn(BrickStage) + Sync),
    /// Where finished passes are kept and found again (`None`: nowhere).
    pub checkpoint: Option<&'a crate::checkpoint::Checkpoint>,
    /// The first pass's kept tops.
    pub tops: KeptTops,
}

impl BrickWork for LocalBricks<'_> {
    type File = Vec<u8>;

    fn score_all(&self, plan: &BrickPlan) -> Result<Vec<ScoreSummary>, BrickError> {
        let (of, counter) = (plan.grid.len(), std::sync::atomic::AtomicUsize::new(0));
        in_grid_order(of, |i| {
            let energies = matches!(plan.target, Target::QvPercent(_));
            let s = match self.checkpoint.and_then(|c| c.summary(i)) {
                Some(s) => s,
                None => {
                    let mut s = plan.score_into(self.source, i, &self.tops, 0, plan.top_cap(i))?;
                    if !energies {
                        s = s.without_energies();
                    }
                    if let Some(c) = self.checkpoint {
                        c.keep_summary(i, &s, energies);
                        if let Some(top) = self.tops.get(&(0, plan.grid[i])) {
                            c.keep_top(i, &top);
                        }
                    }
                    s
                }
            };
            let done = counter.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
            (self.progress)(BrickStage::Scored { done, of });
            Ok(s)
        })
    }

    fn encode_all(
        &self,
        plan: &BrickPlan,
        counts: Option<&[u64]>,
        trial: usize,
    ) -> Result<Vec<CodedBrick<Vec<u8>>>, BrickError> {
        self.encode_each(plan, counts, trial, &Ok)
    }
}

impl LocalBricks<'_> {
    /// Every brick compressed as [`BrickWork::encode_all`] asks, each file handed to `keep`
    /// as it is made (which decides where it is kept).
    fn encode_each<F: Send>(
        &self,
        plan: &BrickPlan,
        counts: Option<&[u64]>,
        trial: usize,
        keep: &(dyn Fn(Vec<u8>) -> Result<F, BrickError> + Sync),
    ) -> Result<Vec<CodedBrick<F>>, BrickError> {
        let (of, counter) = (plan.grid.len(), std::sync::atomic::AtomicUsize::new(0));
        in_grid_order(of, |i| {
            let count = counts.map(|k| k[i]);
            let (file, kept) = match self.checkpoint.and_then(|c| c.coded(i, count)) {
                Some(coded) => coded,
                None => {
                    // A run again after a kill: the top this brick's first pass kept, from
                    // the checkpoint, where it is not in memory (then the brick is coded
                    // without being read and transformed again).
                    let key = (0, plan.grid[i]);
                    let cap = plan.top_cap(i);
                    let mut had_top = self.tops.get(&key).is_some();
                    if let (Some(c), Some(_)) = (self.checkpoint, count) {
                        if !had_top && cap.is_some() {
                            if let Some(top) = c.top(i, plan.grid[i].1, &plan.base) {
                                self.tops.keep(key, top);
                                had_top = true;
                            }
                        }
                    }
                    let coded = plan.encode_from(self.source, i, count, &self.tops, 0, cap)?;
                    if let Some(c) = self.checkpoint {
                        c.keep_coded(i, count, &coded.0);
                        // A top kept on the way (the checkpoint had none): kept there too,
                        // for a run after another kill.
                        if !had_top {
                            if let Some(top) = self.tops.get(&key) {
                                c.keep_top(i, &top);
                            }
                        }
                    }
                    coded
                }
            };
            let len = file.len() as u64;
            let file = keep(file)?;
            let done = counter.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
            (self.progress)(BrickStage::Compressed { done, of, trial });
            Ok(CodedBrick { len, file, kept })
        })
    }
}

/// `work` for every brick `0..of` on the rayon pool, the bricks started in their grid order
/// (x fastest, then y, then z) by whichever thread is free, and the results in that order;
/// the first error stops new bricks from starting and is returned. Not rayon's split of the
/// range into a part per thread: its threads would each read a different layer of bricks at
/// once, and a reader's chunks shared by a layer (a TIFF page in one strip, a Zarr chunk of a
/// plane, [`crate::reader::spool`]) are released only once the layer has read them, so the
/// disk they take would grow with the threads. In order, the threads share one layer. A time
/// series' units (each component's bricks, [`crate::series`]) start in their order the same way.
pub(crate) fn in_grid_order<T: Send, E: Send>(
    of: usize,
    work: impl Fn(usize) -> Result<T, E> + Sync,
) -> Result<Vec<T>, E> {
    use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
    let (next, failed) = (AtomicUsize::new(0), AtomicBool::new(false));
    let done: Vec<std::sync::Mutex<Option<T>>> =
        (0..of).map(|_| std::sync::Mutex::new(None)).collect();
    let first_error = std::sync::Mutex::new(None);
    let threads = rayon::current_num_threads().clamp(1, of.max(1));
    (0..threads).into_par_iter().for_each(|_| loop {
        let i = next.fetch_add(1, Ordering::Relaxed);
        if i >= of || failed.load(Ordering::Relaxed) {
            return;
        }
        match work(i) {
            Ok(t) => *done[i].lock().unwrap_or_else(|p| p.into_inner()) = Some(t),
            Err(e) => {
                failed.store(true, Ordering::Relaxed);
                let mut first = first_error.lock().unwrap_or_else(|p| p.into_inner());
                first.get_or_insert(e);
                return;
            }
        }
    });
    if let Some(e) = first_error.into_inner().unwrap_or_else(|p| p.into_inner()) {
        return Err(e);
    }
    Ok(done
        .into_iter()
        .map(|m| {
            m.into_inner()
                .unwrap_or_else(|p| p.into_inner())
                .expect("every brick done without an error")
        })
        .collect())
}

/// A trial's coded bricks kept on disk instead of in memory ([`SpillingBricks`]): an unnamed
/// temporary file the bricks are appended to as they are made, gone when the last
/// [`SpilledBrick`] of the trial is dropped. A bricked volume's file can be larger than memory
/// allows to hold twice (a byte target's search keeps its best trial while it tries the next),
/// so no coded brick stays in memory longer than it takes to append it.
#[derive(Debug)]
pub struct Spill {
    file: crate::scratch::ScratchFile,
}

impl Spill {
    /// An empty spill: an unnamed temporary file in `dir` (`None`: the temporary directory).
    pub fn new(dir: Option<&std::path::Path>) -> Result<Spill, BrickError> {
        let file = crate::scratch::ScratchFile::new(dir).map_err(BrickError::Spill)?;
        Ok(Spill { file })
    }

    /// Appends a brick's file (its header section is checked); what finds it again.
    pub fn push(self: &std::sync::Arc<Spill>, bytes: &[u8]) -> Result<SpilledBrick, BrickError> {
        let (_, header) = wavesplat_codec::format::read_header_section(bytes)?;
        let crc = crc32fast::hash(bytes);
        let offset = self.file.append(bytes).map_err(BrickError::Spill)?;
        Ok(SpilledBrick {
            spill: self.clone(),
            offset,
            crc,
            header: header as u64,
        })
    }
}

/// Where a [`Spill`] keeps one coded brick.
#[derive(Debug, Clone)]
pub struct SpilledBrick {
    spill: std::sync::Arc<Spill>,
    offset: u64,
    /// The CRC-32 of its bytes.
    pub(crate) crc: u32,
    /// Its header section's length (what [`BrickedWritten::overhead`] sums).
    header: u64,
}

impl SpilledBrick {
    /// Copies the brick's `len` bytes to `out`.
    pub(crate) fn copy_to(&self, len: u64, out: &mut dyn std::io::Write) -> std::io::Result<()> {
        self.spill.file.copy_to(self.offset, len, out)
    }
}

/// The bricks compressed on this process's pool as [`LocalBricks`] does, each trial's files
/// kept in a [`Spill`] in `dir` (`None`: the temporary directory) rather than in memory.
pub struct SpillingBricks<'a> {
    /// What compresses the bricks.
    pub local: LocalBricks<'a>,
    /// Where the trials' temporary files go.
    pub dir: Option<&'a std::path::Path>,
}

impl BrickWork for SpillingBricks<'_> {
    type File = SpilledBrick;

    fn score_all(&self, plan: &BrickPlan) -> Result<Vec<ScoreSummary>, BrickError> {
        self.local.score_all(plan)
    }

    fn encode_all(
        &self,
        plan: &BrickPlan,
        counts: Option<&[u64]>,
        trial: usize,
    ) -> Result<Vec<CodedBrick<SpilledBrick>>, BrickError> {
        let spill = std::sync::Arc::new(Spill::new(self.dir)?);
        self.local
            .encode_each(plan, counts, trial, &|bytes| spill.push(&bytes))
    }
}

/// What [`BrickPlan::write_container`] wrote.
#[derive(Debug)]
pub struct ContainerWritten {
    /// The container's manifest (offsets filled in).
    pub manifest: Manifest,
    /// Bytes written.
    pub bytes: u64,
    /// Bytes of them outside the bricks' packets: the manifest section and every brick's header
    /// section.
    pub overhead: u64,
}

/// What [`compress_bricked_to`] wrote.
#[derive(Debug)]
pub struct BrickedWritten {
    /// The container's manifest (offsets filled in).
    pub manifest: Manifest,
    /// Bytes written.
    pub bytes: u64,
    /// Bytes of them outside the bricks' packets: the manifest section and every brick's header
    /// section.
    pub overhead: u64,
    /// Coefficients of the padded grids of all bricks, all channels.
    pub total_coefficients: u64,
    /// Non-zero coefficients over all bricks.
    pub nonzero: u64,
    /// The depth every brick was transformed with.
    pub levels: usize,
}

/// Compresses the volume `source` holds as bricks of edge `brick` with `opts` (whose target is
/// the whole's). Bricks are compressed on the rayon pool, each read when its turn comes; the
/// coded bricks wait in a temporary file ([`compress_bricked_to`]) until the container is
/// assembled in memory.
pub fn compress_bricked(
    source: &dyn BrickSource,
    opts: &CompressOptions,
    brick: usize,
    progress: &(dyn Fn(BrickStage) + Sync),
) -> Result<BrickedCompressed, BrickError> {
    let mut bytes = Vec::new();
    let w = compress_bricked_to(source, opts, brick, progress, None, None, &mut bytes)?;
    Ok(BrickedCompressed {
        bytes,
        manifest: w.manifest,
        total_coefficients: w.total_coefficients,
        nonzero: w.nonzero,
        levels: w.levels,
    })
}

/// Compresses as [`compress_bricked`] does, writing the container to `out` as it is assembled:
/// the coded bricks wait in a temporary file in `spill_dir` (`None`: the temporary directory,
/// which must have room for about the file, twice during a byte target's search), not in
/// memory, so that memory stays about one brick per thread however large the file.
/// `out` gets the manifest section and then the bricks, in one pass. With a `checkpoint`,
/// every brick's passes are kept there as they finish and taken from there where it holds them
/// ([`crate::checkpoint`]): an interrupted compression run again does only what is missing.
pub fn compress_bricked_to(
    source: &dyn BrickSource,
    opts: &CompressOptions,
    brick: usize,
    progress: &(dyn Fn(BrickStage) + Sync),
    spill_dir: Option<&std::path::Path>,
    checkpoint: Option<&crate::checkpoint::Checkpoint>,
    out: &mut dyn std::io::Write,
) -> Result<BrickedWritten, BrickError> {
    let kept_plan = checkpoint
        .and_then(|c| c.plan())
        .and_then(|bytes| PlanChoices::from_bytes(&bytes));
    let plan = match kept_plan {
        Some(kept) => {
            let mut plan = BrickPlan::with_choices(source, opts, brick, kept.choices)?;
            plan.coefficients_per_byte = kept.coefficients_per_byte;
            plan
        }
        None => {
            let plan = BrickPlan::new(source, opts, brick)?;
            if let Some(c) = checkpoint {
                c.keep_plan(&PlanChoices::of(&plan).to_bytes());
            }
            plan
        }
    };
    let work = SpillingBricks {
        local: LocalBricks {
            source,
            progress,
            checkpoint,
            tops: KeptTops::for_plan(&plan).spilling_in(spill_dir),
        },
        dir: spill_dir,
    };
    let a = allocate(&plan, &work)?;
    let (from_kept_top, transformed_again) = work.local.tops.counts();
    let spilled = work.local.tops.spilled();
    tracing::debug!(from_kept_top, transformed_again, spilled, "bricks coded");
    let c = plan.write_container(&a.bricks, out)?;
    Ok(BrickedWritten {
        manifest: c.manifest,
        bytes: c.bytes,
        overhead: c.overhead,
        total_coefficients: a.total_coefficients,
        nonzero: a.nonzero,
        levels: plan.choices.levels,
    })
}

/// What [`BrickPlan::new`] chose that a checkpoint keeps, so that a compression run again
/// plans without reading the whole's faces or comparing depths on a sample again: the shared
/// choices and the rate search's start.
#[derive(Debug, Clone, PartialEq)]
struct PlanChoices {
    choices: SharedChoices,
    coefficients_per_byte: Option<f64>,
}

impl PlanChoices {
    fn of(plan: &BrickPlan) -> PlanChoices {
        PlanChoices {
            choices: plan.choices.clone(),
            coefficients_per_byte: plan.coefficients_per_byte,
        }
    }

    /// The choices as bytes: the depth (u64), then the offset, the rate search's start and the
    /// colour transform, each a presence byte and its values (f64 bits, little-endian; the
    /// transform's kind by name, length first).
    fn to_bytes(&self) -> Vec<u8> {
        let mut out = (self.choices.levels as u64).to_le_bytes().to_vec();
        for v in [self.choices.offset, self.coefficients_per_byte] {
            out.push(u8::from(v.is_some()));
            out.extend_from_slice(&v.unwrap_or(0.0).to_le_bytes());
        }
        match &self.choices.color {
            None => out.push(0),
            Some(t) => {
                out.push(1);
                let name = t.kind.name().as_bytes();
                out.push(name.len() as u8);
                out.extend_from_slice(name);
                let values = t.basis.iter().flatten().chain(&t.mean).chain(&t.importance);
                for v in values {
                    out.extend_from_slice(&v.to_le_bytes());
                }
            }
        }
        out
    }

    /// Reads what [`PlanChoices::to_bytes`] wrote; `None` for anything else (the plan is then
    /// made again).
    fn from_bytes(bytes: &[u8]) -> Option<PlanChoices> {
        let mut r = bytes;
        let mut take = |n: usize| -> Option<&[u8]> {
            let (head, rest) = r.split_at_checked(n)?;
            r = rest;
            Some(head)
        };
        let levels = u64::from_le_bytes(take(8)?.try_into().ok()?) as usize;
        let mut optional = || -> Option<Option<f64>> {
            let present = take(1)?[0];
            let v = f64::from_le_bytes(take(8)?.try_into().ok()?);
            match present {
                0 => Some(None),
                1 => Some(Some(v)),
                _ => None,
            }
        };
        let (offset, coefficients_per_byte) = (optional()?, optional()?);
        let color = match take(1)?[0] {
            0 => None,
            1 => {
                let len = take(1)?[0] as usize;
                let kind = ColorSpaceKind::from_name(std::str::from_utf8(take(len)?).ok()?)?;
                let mut values = [0f64; 15];
                for v in &mut values {
                    *v = f64::from_le_bytes(take(8)?.try_into().ok()?);
                }
                let row = |i: usize| [values[i], values[i + 1], values[i + 2]];
                Some(ColorTransform {
                    kind,
                    basis: [row(0), row(3), row(6)],
                    mean: row(9),
                    importance: row(12),
                })
            }
            _ => return None,
        };
        if !r.is_empty() {
            return None;
        }
        Some(PlanChoices {
            choices: SharedChoices {
                levels,
                offset,
                color,
            },
            coefficients_per_byte,
        })
    }
}

/// Trials of the byte target's search on the global count.
const BYTE_TRIALS: usize = 10;

/// The number of coefficients (from the top score down) whose energy reaches `goal`, by the
/// bins of the bricks' summed histogram (down to the bin where it is reached).
fn count_for_energy(whole: &SummedScores, goal: f64) -> u64 {
    let (mut acc, mut count) = (0.0, 0u64);
    for (c, e) in whole.counts().iter().zip(whole.energies()).rev() {
        acc += e;
        count += c;
        if acc >= goal * (1.0 - 1e-9) {
            break;
        }
    }
    count
}

/// Each brick's share of the top `k` coefficients of the whole (`whole`, the bricks' summed
/// summary): every coefficient in a bin above the global threshold bin, and of the threshold
/// bin a share proportional to the brick's count there (so that the shares sum to `k`).
fn per_brick_counts(summaries: &[ScoreSummary], whole: &SummedScores, k: u64) -> Vec<u64> {
    if k >= whole.nonzero {
        // Every selectable coefficient.
        return summaries.iter().map(|s| s.nonzero).collect();
    }
    let cut = whole.cut_for_count(k);
    let above: u64 = whole.counts()[cut + 1..].iter().sum();
    let in_bin = whole.counts()[cut];
    let need = k - above;
    let (mut shares, at): (Vec<u64>, Vec<u64>) =
        summaries.iter().map(|s| s.count_above_and_at(cut)).unzip();
    // Largest-remainder split of `need` over the bricks' counts in the cut bin.
    let exact: Vec<f64> = at
        .iter()
        .map(|a| need as f64 * *a as f64 / in_bin.max(1) as f64)
        .collect();
    let mut given = 0u64;
    for (s, e) in shares.iter_mut().zip(&exact) {
        *s += e.floor() as u64;
        given += e.floor() as u64;
    }
    let mut order: Vec<usize> = (0..summaries.len()).collect();
    order.sort_by(|&a, &b| (exact[b] - exact[b].floor()).total_cmp(&(exact[a] - exact[a].floor())));
    for &i in order.iter().take((need - given) as usize) {
        shares[i] += 1;
    }
    shares
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::encode::{compress, Effort};
    use crate::phantom::Phantom;

    /// Bricks run in grid order give their results in that order, each brick once, from a
    /// pool of several threads; an error stops the bricks not yet started and is returned;
    /// no brick at all is no work.
    #[test]
    fn bricks_in_grid_order_come_back_in_order_and_stop_at_an_error() {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(3)
            .build()
            .unwrap();
        pool.install(|| {
            let calls = std::sync::atomic::AtomicUsize::new(0);
            let got = in_grid_order(100, |i| {
                calls.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                Ok::<_, String>(i * i)
            })
            .unwrap();
            assert_eq!(got, (0..100).map(|i| i * i).collect::<Vec<_>>());
            assert_eq!(calls.into_inner(), 100);
            let started = std::sync::Mutex::new(Vec::new());
            let e = in_grid_order(100, |i| {
                started.lock().unwrap().push(i);
                if i == 10 {
                    return Err(format!("brick {i}"));
                }
                std::thread::sleep(std::time::Duration::from_millis(20));
                Ok(i)
            })
            .unwrap_err();
            assert_eq!(e, "brick 10");
            let started = started.into_inner().unwrap();
            // Started in order, and none after the failure but what was under way: 20 ms a
            // brick, the 89 after brick 10 would take the other two threads 0.9 s.
            assert!((0..=10).all(|i| started.contains(&i)), "{started:?}");
            assert!(started.len() < 30, "{started:?}");
            assert_eq!(in_grid_order(0, |_| Ok::<u8, ()>(1)), Ok(vec![]));
        });
    }

    /// A file's faces are read in one pass of slabs of whole rows, for files of any shape and
    /// any slab size (several planes, a band of rows, a row), and give the same samples as
    /// reading each face as a box: so the offset every brick subtracts is unchanged.
    #[test]
    fn a_file_s_faces_read_by_slabs_are_the_faces_read_one_by_one() {
        use crate::reader::region::RegionReader;
        use crate::reader::{RawDtype, RawSpec};
        let dir = tempfile::tempdir().unwrap();
        for (dims, channels) in [
            ([7, 5, 3], 1),
            ([1, 4, 3], 1),
            ([6, 1, 2], 3),
            ([5, 4, 1], 1),
            ([1, 1, 1], 1),
            ([9, 8, 7], 3),
        ] {
            let n: usize = dims.iter().product::<usize>() * channels;
            // Distinct values, so a sample counted once too often or too rarely shows.
            let bytes: Vec<u8> = (0..n)
                .flat_map(|i| ((i as f32) * 1.5 - 7.0).to_le_bytes())
                .collect();
            let path = dir.path().join(format!(
                "v{}x{}x{}x{channels}.raw",
                dims[0], dims[1], dims[2]
            ));
            std::fs::write(&path, &bytes).unwrap();
            let spec = RawSpec {
                channels,
                ..RawSpec::new(dims, RawDtype::F32)
            };
            let reader = RegionReader::open(&path, Some(&spec)).unwrap();
            assert!(reader.reads_rows_whole());
            let mut by_faces = face_samples_by_faces(&reader).unwrap();
            by_faces.iter_mut().for_each(|s| s.sort_by(f32::total_cmp));
            let row = dims[0] * channels * 4;
            for budget in [1, row, row * dims[1] + 1, row * dims[1] * 2, 1 << 20] {
                let mut by_slabs = face_samples_by_slabs(&reader, budget).unwrap();
                by_slabs.iter_mut().for_each(|s| s.sort_by(f32::total_cmp));
                assert_eq!(by_slabs, by_faces, "{dims:?} x{channels}, budget {budget}");
            }
            let medians = whole_face_medians(&reader).unwrap();
            let expected: Vec<f64> = by_faces
                .iter_mut()
                .map(|s| crate::colorspace::median_or_zero(s))
                .collect();
            assert_eq!(medians, expected, "{dims:?} x{channels}");
        }
    }

    /// The bricks keep the whole's count, split by one global threshold: a brick of empty
    /// space keeps (almost) nothing, unlike an equal split.
    #[test]
    fn one_threshold_allocates_the_whole_target_across_bricks() {
        let v = Phantom::SheppLogan.generate([48, 48, 40]);
        // Without least-squares refinement, which drops those whose refit is zero.
        let opts = CompressOptions {
            target: Target::Fraction(0.03),
            refine: None,
            ..CompressOptions::default()
        };
        let c = compress_bricked(&v, &opts, 24, &|_| {}).unwrap();
        let m = &c.manifest;
        assert_eq!(m.bricks.len(), 8);
        let want = (0.03 * c.total_coefficients as f64).round() as u64;
        assert_eq!(m.kept(), want);
        let counts: Vec<u64> = m.bricks.iter().map(|b| b.kept).collect();
        let (lo, hi) = (counts.iter().min().unwrap(), counts.iter().max().unwrap());
        assert!(hi > lo, "{counts:?}");
        // Every brick reads back as a volume of its own with its own dims.
        let f = wavesplat_codec::format::bricked::parse_bricked(&c.bytes).unwrap();
        for (i, e) in f.manifest.bricks.iter().enumerate() {
            let file = wavesplat_codec::format::parse_file(f.brick_bytes(i).unwrap()).unwrap();
            assert_eq!(file.header.geometry.dims, e.dims);
            assert_eq!(file.header.margin, bridge_margin(opts.family, c.levels));
            assert!(file.header.geometry.clips_to_box());
        }
    }

    /// The container `plan` allocates with `tops`, and the tops after it (what they counted).
    fn allocated_with(v: &Volume, plan: &BrickPlan, tops: KeptTops) -> (Vec<u8>, KeptTops) {
        let quiet = |_| {};
        let work = LocalBricks {
            source: v,
            progress: &quiet,
            checkpoint: None,
            tops,
        };
        let a = allocate(plan, &work).unwrap();
        let files: Vec<(Vec<u8>, u64)> = a.bricks.into_iter().map(|b| (b.file, b.kept)).collect();
        let (bytes, _) = plan.assemble(&files).unwrap();
        (bytes, work.tops)
    }

    /// Bricks coded from the tops their first pass kept are the files a second transform
    /// writes, byte for byte: for fraction, count and byte targets (whose search codes every
    /// brick several times), scalar and colour volumes, with every brick's top kept, with
    /// none (a budget of nothing) and with some (a budget of half); and with the tops beyond
    /// the budget in a temporary file, or a temporary file that cannot be made.
    #[test]
    fn bricks_coded_from_kept_tops_are_the_files_a_second_transform_writes() {
        let ct = Phantom::Ct.generate([72, 60, 40]);
        let rgb = Phantom::RgbHead.generate([40, 36, 30]);
        let cases = [
            (&ct, Target::Fraction(0.02)),
            (&ct, Target::Coefficients(3_000)),
            (&ct, Target::Bytes(12_000)),
            (&rgb, Target::Fraction(0.03)),
            (&rgb, Target::Bytes(9_000)),
        ];
        let dir = tempfile::tempdir().unwrap();
        for (v, target) in cases {
            let opts = CompressOptions {
                target,
                ..Effort::Fast.options()
            };
            let plan = BrickPlan::new(v, &opts, 24).unwrap();
            let bricks = plan.grid.len();
            let (again, none) = allocated_with(v, &plan, KeptTops::new(0));
            let (reused, transformed) = none.counts();
            assert_eq!(reused, 0, "{target:?}");
            assert!(transformed >= bricks, "{target:?}");
            let (kept, all) = allocated_with(v, &plan, KeptTops::for_plan(&plan));
            assert_eq!(kept, again, "{target:?}: every top kept");
            let (reused, transformed) = all.counts();
            assert_eq!(all.spilled(), 0);
            // A brick whose share is beyond its kept top is transformed again; most are not.
            assert!(
                4 * reused >= 3 * (reused + transformed),
                "{target:?}: {reused} {transformed}"
            );
            // A budget for about half the bricks' tops.
            let one = plan.top_cap(0).unwrap() * std::mem::size_of::<(u32, f32)>() as u64;
            let half = KeptTops::new(one * bricks as u64 / 2);
            let (some, half) = allocated_with(v, &plan, half);
            assert_eq!(some, again, "{target:?}: some tops kept");
            let (reused_half, transformed_half) = half.counts();
            assert!(
                reused_half > 0 && transformed_half > 0,
                "{target:?}: {reused_half} {transformed_half}"
            );
            // Nothing in memory, every top in a temporary file: coded from it as from memory.
            let spilling = KeptTops::new(0).spilling_in(Some(dir.path()));
            let (from_disk, spilled) = allocated_with(v, &plan, spilling);
            assert_eq!(from_disk, again, "{target:?}: tops in a temporary file");
            assert_eq!(spilled.counts(), (reused, transformed), "{target:?}");
            assert_eq!(spilled.spilled(), bricks, "{target:?}");
            // Half in memory, the rest on disk.
            let mixed = KeptTops::new(one * bricks as u64 / 2).spilling_in(None);
            let (mixed_bytes, mixed) = allocated_with(v, &plan, mixed);
            assert_eq!(mixed_bytes, again, "{target:?}: half on disk");
            assert_eq!(mixed.counts(), (reused, transformed), "{target:?}");
            let on_disk = mixed.spilled();
            assert!(on_disk > 0 && on_disk < bricks, "{target:?}: {on_disk}");
            // A temporary file that cannot be made: the tops are dropped, the bricks
            // transformed again, the file the same.
            let nowhere = dir.path().join("no such directory");
            let dropped = KeptTops::new(0).spilling_in(Some(&nowhere));
            let (without, dropped) = allocated_with(v, &plan, dropped);
            assert_eq!(without, again, "{target:?}: no temporary file");
            assert_eq!(dropped.counts().0, 0);
            assert_eq!(dropped.spilled(), 0);
        }
        // A refining compression keeps none and codes every brick by transforming it again.
        let opts = CompressOptions {
            target: Target::Fraction(0.02),
            ..Effort::Default.options()
        };
        let plan = BrickPlan::new(&ct, &opts, 24).unwrap();
        assert_eq!(plan.top_cap(0), None);
        let tops = KeptTops::for_plan(&plan).spilling_in(Some(dir.path()));
        let (_, tops) = allocated_with(&ct, &plan, tops);
        assert_eq!(tops.counts().0, 0);
        assert_eq!(tops.spilled(), 0);
    }

    /// A CT phantom in 24-voxel bricks at 2 % without refinement: its plan, brick count, the
    /// file written with no tops kept, a temporary directory for spilled tops, and the bytes
    /// one brick's kept top takes at most.
    struct SharedTopsCase {
        v: Volume,
        plan: BrickPlan,
        bricks: usize,
        again: Vec<u8>,
        dir: tempfile::TempDir,
        one: u64,
    }

    fn shared_tops_case() -> SharedTopsCase {
        let v = Phantom::Ct.generate([72, 60, 40]);
        let opts = CompressOptions {
            target: Target::Fraction(0.02),
            ..Effort::Fast.options()
        };
        let plan = BrickPlan::new(&v, &opts, 24).unwrap();
        let (again, _) = allocated_with(&v, &plan, KeptTops::new(0));
        let one = plan.top_cap(0).unwrap() * std::mem::size_of::<(u32, f32)>() as u64;
        SharedTopsCase {
            bricks: plan.grid.len(),
            v,
            plan,
            again,
            dir: tempfile::tempdir().unwrap(),
            one,
        }
    }

    /// The tops of several allocations drawing on one [`TopMemory`] (a worker's tops of
    /// several jobs): together they hold no more than it allows, those that find it spent go to
    /// the temporary file, the files are the same, and a dropped allocation's memory is free
    /// for the next.
    #[test]
    fn tops_of_several_allocations_share_one_memory_budget() {
        let SharedTopsCase {
            v,
            plan,
            bricks,
            again,
            dir,
            one,
        } = shared_tops_case();
        let budget = one * bricks as u64 / 2;
        let shared = std::sync::Arc::new(TopMemory::new(budget));
        let sharing = || {
            KeptTops::for_plan(&plan)
                .sharing(shared.clone())
                .spilling_in(Some(dir.path()))
        };
        let (first_bytes, first) = allocated_with(&v, &plan, sharing());
        assert_eq!(first_bytes, again);
        assert_eq!(shared.used(), first.memory_bytes());
        assert!(
            first.spilled() > 0 && first.spilled() < bricks,
            "{}",
            first.spilled()
        );
        // The second finds the memory the first holds spent: more of its tops on disk.
        let (second_bytes, second) = allocated_with(&v, &plan, sharing());
        assert_eq!(second_bytes, again);
        assert_eq!(second.counts(), first.counts());
        assert!(second.spilled() > first.spilled(), "{}", second.spilled());
        assert_eq!(shared.used(), first.memory_bytes() + second.memory_bytes());
        // Only the spilled tops' metadata (counted, never refused) goes beyond the budget.
        let metadata = shared.used().saturating_sub(budget);
        assert!(
            metadata < one * bricks as u64 / 8,
            "{} of {budget}",
            shared.used()
        );
        // Dropped, the first's memory is free again: a third keeps as many in memory.
        let first_counts = first.counts();
        drop(first);
        assert_eq!(shared.used(), second.memory_bytes());
        let (third_bytes, third) = allocated_with(&v, &plan, sharing());
        assert_eq!(third_bytes, again);
        assert!(third.spilled() < second.spilled(), "{}", third.spilled());
        drop((second, third));
        assert_eq!(shared.used(), 0);
        // A budget lowered to nothing (a job under a tight memory limit joined): every top of
        // the next goes to disk, the same file.
        shared.set_budget(0);
        let (fourth_bytes, fourth) = allocated_with(&v, &plan, sharing());
        assert_eq!(fourth_bytes, again);
        assert_eq!(fourth.spilled(), bricks);
        assert_eq!(fourth.counts(), first_counts);
        assert_eq!(shared.used(), fourth.memory_bytes());
    }

    /// A byte target's depth comparison under a memory limit that the default depth's bricks
    /// fit and a deeper depth's do not: the deeper depth is no candidate (not a refusal of
    /// the whole plan), and the depth chosen fits.
    #[test]
    fn a_depth_whose_bricks_do_not_fit_the_memory_limit_is_not_compared() {
        let v = Phantom::Ct.generate([96, 80, 64]);
        let (dims, brick) = ([48, 40, 32], 48);
        let default = default_levels(dims, wavesplat_codec::family::Family::Linear);
        assert!(
            deepest_compared(dims, wavesplat_codec::family::Family::Linear) > default,
            "a deeper candidate"
        );
        let opts = CompressOptions {
            target: Target::Bytes(6_000),
            ..CompressOptions::default()
        };
        let need = |levels: usize| {
            let at = CompressOptions {
                levels: Some(levels),
                memory_limit: Some(1),
                ..opts.clone()
            };
            match BrickPlan::new(&v, &at, brick) {
                Err(BrickError::Compress { source, .. }) => match *source {
                    CompressError::MemoryLimit { needed, .. } => needed,
                    e => panic!("{e}"),
                },
                other => panic!("not refused: {:?}", other.map(|p| p.choices.levels)),
            }
        };
        let (fits, deeper) = (need(default), need(default + 1));
        assert!(deeper > fits, "{deeper} {fits}");
        let limited = CompressOptions {
            memory_limit: Some(fits),
            ..opts.clone()
        };
        let plan = BrickPlan::new(&v, &limited, brick).expect("the default depth fits");
        assert!(plan.choices.levels <= default, "{}", plan.choices.levels);
        // Below what the default depth needs, the plan is refused saying so.
        let tight = CompressOptions {
            memory_limit: Some(fits - 1),
            ..opts
        };
        let refused = BrickPlan::new(&v, &tight, brick).err();
        assert!(
            refused.as_ref().is_some_and(BrickError::is_memory_refusal),
            "{refused:?}"
        );
    }

    /// The tops several allocations move to their temporary files share one disk budget: a
    /// second allocation finds what the first spilled counted against it and spills less (the
    /// rest of its bricks transformed again, the same file); the first's dropped, its disk is
    /// free again.
    #[test]
    fn tops_of_several_allocations_share_one_disk_budget() {
        let SharedTopsCase {
            v,
            plan,
            bricks,
            again,
            dir,
            one,
        } = shared_tops_case();
        // No memory for tops; disk for about two thirds of one allocation's.
        let disk = one * bricks as u64 * 2 / 3;
        let shared = std::sync::Arc::new(TopMemory::new(0).with_disk_budget(disk));
        let sharing = || {
            KeptTops::for_plan(&plan)
                .sharing(shared.clone())
                .spilling_in(Some(dir.path()))
        };
        let (first_bytes, first) = allocated_with(&v, &plan, sharing());
        assert_eq!(first_bytes, again);
        assert!(first.spilled() > 0, "{}", first.spilled());
        assert!(shared.disk_used() > 0 && shared.disk_used() <= disk);
        let after_first = shared.disk_used();
        let (second_bytes, second) = allocated_with(&v, &plan, sharing());
        assert_eq!(second_bytes, again);
        assert!(
            second.spilled() < first.spilled(),
            "{} {}",
            second.spilled(),
            first.spilled()
        );
        assert!(
            shared.disk_used() <= disk,
            "{} of {disk}",
            shared.disk_used()
        );
        assert!(
            second.counts().1 > first.counts().1,
            "more transformed again"
        );
        let both = shared.disk_used();
        drop(first);
        assert_eq!(shared.disk_used(), both - after_first);
        drop(second);
        assert_eq!(shared.disk_used(), 0);
    }

    #[test]
    fn a_byte_target_for_the_whole_lands_within_two_percent() {
        let v = Phantom::SheppLogan.generate([40, 40, 40]);
        for target in [6_000u64, 20_000] {
            let opts = CompressOptions {
                target: Target::Bytes(target),
                ..CompressOptions::default()
            };
            let c = compress_bricked(&v, &opts, 20, &|_| {}).unwrap();
            let got = c.bytes.len() as f64;
            assert!(
                got <= target as f64 && got >= 0.98 * target as f64,
                "{got} bytes for {target}"
            );
        }
    }

    /// The whole decoded from a bricked container, and how far its three axis X-ray views lie
    /// from `v`'s (the mean over the axes of ln Σ ‖P f − P f̂‖², as the depth comparison
    /// scores a depth, but over the whole volume and every brick).
    fn whole_view_error(v: &Volume, bytes: &[u8]) -> f64 {
        let d = v.dims();
        let decoded = std::sync::Mutex::new(vec![0f32; d[0] * d[1] * d[2]]);
        let budget = wavesplat_codec::format::packet::DecodeBudget::default();
        decode_bricks(bytes, &budget, &|e, b| {
            let mut out = decoded.lock().unwrap();
            let [bx, by, bz] = e.dims;
            let o = e.origin.map(|o| o as usize);
            for z in 0..bz {
                for y in 0..by {
                    for x in 0..bx {
                        let at = (o[0] + x) + d[0] * ((o[1] + y) + d[1] * (o[2] + z));
                        out[at] = b.channel(0)[x + bx * (y + by * z)];
                    }
                }
            }
            Ok(())
        })
        .unwrap();
        let decoded = decoded.into_inner().unwrap();
        let f = v.channel(0);
        let at = |x: usize, y: usize, z: usize| {
            let i = x + d[0] * (y + d[1] * z);
            f64::from(f[i]) - f64::from(decoded[i])
        };
        axis_views(d, &at)
            .iter()
            .map(|view| view.iter().map(|e| e * e).sum::<f64>().ln())
            .sum::<f64>()
            / 3.0
    }

    /// The axis-view error of `v` in 32³ bricks with `opts` at each depth 1 to 3, and the
    /// smallest.
    fn depth_errors(v: &Volume, opts: &CompressOptions) -> (Vec<(usize, f64)>, f64) {
        let errors: Vec<(usize, f64)> = (1..=3)
            .map(|m| {
                let o = CompressOptions {
                    levels: Some(m),
                    ..opts.clone()
                };
                let c = compress_bricked(v, &o, 32, &|_| {}).unwrap();
                (m, whole_view_error(v, &c.bytes))
            })
            .collect();
        let best = errors.iter().map(|e| e.1).fold(f64::INFINITY, f64::min);
        (errors, best)
    }

    /// A bricked byte target takes its depth as the whole's search does, on the bricks: of the
    /// depths the bricks could take (1 to their default 3), one whose decoded whole comes
    /// closest to the original in its axis X-ray views (within 0.02 of the best's ln error,
    /// 0.1 dB), shallower than the default at a high rate and not the shallowest at low ones
    /// (measured: M = 1 there is 1.4 nats, 6 dB, worse than M = 2).
    #[test]
    fn a_bricked_byte_target_takes_the_depth_that_draws_closest() {
        let v = Phantom::Ct.generate([64, 60, 52]);
        let voxels = 64 * 60 * 52;
        for (bytes, range) in [
            (voxels / 8, 1..=2),
            (voxels / 30, 2..=3),
            (voxels / 60, 2..=3),
        ] {
            let opts = CompressOptions {
                target: Target::Bytes(bytes as u64),
                ..CompressOptions::default()
            };
            let chosen = compress_bricked(&v, &opts, 32, &|_| {}).unwrap();
            let (errors, best) = depth_errors(&v, &opts);
            let got = errors[chosen.levels - 1].1;
            assert!(
                got <= best + 0.02 && range.contains(&chosen.levels),
                "{bytes} B: chose M = {}; errors {errors:?}",
                chosen.levels
            );
        }
    }

    /// A bricked byte target's rate search starts from the coefficients per byte its depth
    /// comparison's sample kept at the depth chosen: it lands within 2 % of the target, and in
    /// fewer trials than the same plan started from one coefficient per byte.
    #[test]
    fn the_rate_search_starts_from_the_sample_s_coefficients_per_byte() {
        /// Counts the rate search's trials.
        struct Counted<'a>(LocalBricks<'a>, std::sync::atomic::AtomicUsize);
        impl BrickWork for Counted<'_> {
            type File = Vec<u8>;
            fn score_all(&self, plan: &BrickPlan) -> Result<Vec<ScoreSummary>, BrickError> {
                self.0.score_all(plan)
            }
            fn encode_all(
                &self,
                plan: &BrickPlan,
                counts: Option<&[u64]>,
                trial: usize,
            ) -> Result<Vec<CodedBrick<Vec<u8>>>, BrickError> {
                self.1.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                self.0.encode_all(plan, counts, trial)
            }
        }
        let v = Phantom::SheppLogan.generate([64, 64, 48]);
        let quiet = |_| {};
        let mut fewer = 0;
        for target in [4_000u64, 12_000, 40_000] {
            let opts = CompressOptions {
                target: Target::Bytes(target),
                ..CompressOptions::default()
            };
            let mut plan = BrickPlan::new(&v, &opts, 32).unwrap();
            let ratio = plan.coefficients_per_byte;
            assert!(ratio.is_some_and(|r| r > 0.5 && r < 10.0), "{ratio:?}");
            let mut trials = [0usize; 2];
            for (i, start) in [ratio, None].into_iter().enumerate() {
                plan.coefficients_per_byte = start;
                let work = Counted(
                    LocalBricks {
                        source: &v,
                        progress: &quiet,
                        checkpoint: None,
                        tops: KeptTops::for_plan(&plan),
                    },
                    Default::default(),
                );
                let a = allocate(&plan, &work).unwrap();
                let bytes = a.bricks.iter().map(|b| b.len).sum::<u64>() + plan.manifest_len();
                assert!(
                    bytes <= target && bytes as f64 >= 0.98 * target as f64,
                    "{bytes} bytes for {target} (start {start:?})"
                );
                trials[i] = work.1.into_inner();
            }
            assert!(trials[0] <= trials[1], "{trials:?} at {target}");
            fewer += usize::from(trials[0] < trials[1]);
        }
        assert!(fewer > 0, "the sample's ratio saved no trial");
    }

    /// Runs [`search_depth`] over `errors[m - 1]` (the error of depth m; `None`: does not
    /// fit) and returns its choice and the depths it scored, in order.
    fn searched(default: usize, cap: usize, errors: &[Option<f64>]) -> (usize, Vec<usize>) {
        let mut scored = Vec::new();
        let chosen = search_depth::<()>(default, cap, |m| {
            scored.push(m);
            Ok(errors[m - 1])
        })
        .unwrap();
        (chosen, scored)
    }

    /// The depth search on error curves measured (BENCHMARKS.md): the default and both
    /// neighbours are scored, and the search goes on from the closest. A curve with two minima
    /// (the resampled MRI's 256³ bricks: M = 2 below 3, and 4 and 5 below both) goes deeper;
    /// one whose deeper neighbour comes closer but whose shallower one comes closer still goes
    /// shallower (the MRI in 128³ bricks at 1 MB); the default stays on a tie, when it does
    /// not fit, and a depth that does not fit ends its direction.
    #[test]
    fn the_depth_search_scores_both_neighbours_and_follows_the_closer() {
        let two_minima = [32.54, 30.42, 30.52, 30.00, 29.89].map(Some);
        assert_eq!(searched(3, 5, &two_minima), (5, vec![3, 4, 2, 5]));
        // Capped below the deeper minimum.
        assert_eq!(searched(3, 4, &two_minima), (4, vec![3, 4, 2]));
        // Deeper comes closer than the default, shallower closer still.
        let both = [13.50, 13.00, 13.27, 13.13, 13.11].map(Some);
        assert_eq!(searched(3, 5, &both), (2, vec![3, 4, 2, 1]));
        // The MRI at 1.25 % (the whole's axis views): the minimum is M = 2.
        let shallower = [20.20, 19.92, 20.01, 20.07, 20.06].map(Some);
        assert_eq!(searched(3, 5, &shallower), (2, vec![3, 4, 2, 1]));
        // A deeper depth past the minimum stops the deeper direction.
        let deeper = [20.06, 19.92, 19.72, 19.70, 19.71].map(Some);
        assert_eq!(searched(3, 5, &deeper), (4, vec![3, 4, 2, 5]));
        // Ties keep the default.
        let flat = [1.0; 5].map(Some);
        assert_eq!(searched(3, 5, &flat), (3, vec![3, 4, 2]));
        // The default does not fit: nothing else is tried.
        let unfit = [Some(1.0), Some(1.0), None, Some(0.5), Some(0.1)];
        assert_eq!(searched(3, 5, &unfit), (3, vec![3]));
        // Neighbours that do not fit end both directions.
        let gaps = [Some(0.1), None, Some(5.0), None, Some(0.2)];
        assert_eq!(searched(3, 5, &gaps), (3, vec![3, 4, 2]));
        // The cap at the default: shallower only, down to 1; the default at 1: deeper only.
        let down = [3.0, 4.0, 5.0, 1.0, 1.0].map(Some);
        assert_eq!(searched(3, 3, &down), (1, vec![3, 2, 1]));
        let up = [3.0, 2.0, 1.0, 1.0, 1.0].map(Some);
        assert_eq!(searched(1, 5, &up), (3, vec![1, 2, 3, 4]));
    }

    /// Where the default depth wins over a shallower one and a deeper one wins over the
    /// default ([`Phantom::Blobs`] at 96³ in 48³ bricks, 3 000 bytes), a bricked
    /// byte target's comparison goes past the default, up to the depth whose decoded whole
    /// draws closest in its axis X-ray views: closer than the default and the next deeper
    /// depth.
    #[test]
    fn a_bricked_byte_target_goes_deeper_on_a_smooth_volume() {
        let v = Phantom::Blobs.generate([96; 3]);
        let opts = CompressOptions {
            target: Target::Bytes(3000),
            refine: None,
            ..CompressOptions::default()
        };
        let default = default_levels([48; 3], opts.family);
        let chosen = compress_bricked(&v, &opts, 48, &|_| {}).unwrap();
        assert!(chosen.levels > default, "M = {}", chosen.levels);
        let error = |m: usize| {
            let o = CompressOptions {
                levels: Some(m),
                ..opts.clone()
            };
            whole_view_error(&v, &compress_bricked(&v, &o, 48, &|_| {}).unwrap().bytes)
        };
        let got = whole_view_error(&v, &chosen.bytes);
        for m in [default, chosen.levels + 1] {
            assert!(
                got < error(m),
                "M = {} ({got}), M = {m} ({})",
                chosen.levels,
                error(m)
            );
        }
    }

    /// Under `--effort fast` (a predicted depth search) a bricked byte target predicts its depth
    /// from one oracle allocation of the sample, as the whole predicts its own: shallower than
    /// the default where the bytes afford the next coarse band, and a depth whose decoded whole
    /// draws within 0.15 nats (0.65 dB) of the best depth's axis views; the file lands within
    /// 2 % of the target. (At 3.3 kB, half of it the 8 bricks' headers, the rule keeps M = 3
    /// where M = 2 draws 0.35 nats closer: the headers leave too few coefficients to afford
    /// the coarse band by count. The comparison of the default effort finds M = 2 there.)
    #[test]
    fn a_fast_bricked_byte_target_predicts_its_depth() {
        let v = Phantom::Ct.generate([64, 60, 52]);
        let voxels = 64 * 60 * 52;
        for (bytes, range) in [(voxels / 8, 1..=1), (voxels / 30, 2..=2)] {
            let opts = CompressOptions {
                target: Target::Bytes(bytes as u64),
                ..Effort::Fast.options()
            };
            let chosen = compress_bricked(&v, &opts, 32, &|_| {}).unwrap();
            let off = (chosen.bytes.len() as f64 / bytes as f64 - 1.0).abs();
            assert!(off <= 0.02, "{bytes} B: {} B", chosen.bytes.len());
            let (errors, best) = depth_errors(&v, &opts);
            let got = errors[chosen.levels - 1].1;
            assert!(
                got <= best + 0.15 && range.contains(&chosen.levels),
                "{bytes} B: predicted M = {}; errors {errors:?}",
                chosen.levels
            );
        }
    }

    /// The manifest's size a byte target sets aside is the container's own: the first brick
    /// starts right after it, with and without a placement.
    #[test]
    fn the_manifest_set_aside_is_the_container_s() {
        let mut v = Phantom::Ct.generate([40, 36, 20]);
        for placed in [false, true] {
            if placed {
                v = v
                    .with_placement(Placement {
                        origin: [1.0, -2.0, 3.0],
                        directions: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
                    })
                    .unwrap();
            }
            let opts = CompressOptions {
                target: Target::Bytes(4000),
                ..CompressOptions::default()
            };
            let plan = BrickPlan::new(&v, &opts, 20).unwrap();
            let c = compress_bricked(&v, &opts, 20, &|_| {}).unwrap();
            assert_eq!(c.manifest.bricks.len(), 4);
            assert_eq!(
                c.manifest.bricks[0].offset,
                plan.manifest_len(),
                "placed {placed}"
            );
        }
    }

    /// The depth sample: a quarter of the grid between 2 and 8 bricks, distinct, in order,
    /// spread from the first stretch to the last.
    #[test]
    fn the_depth_sample_spreads_over_the_grid() {
        assert_eq!(depth_sample(2), vec![0, 1]);
        assert_eq!(depth_sample(8), vec![2, 6]);
        assert_eq!(depth_sample(27).len(), 6);
        for n in 2..600 {
            let s = depth_sample(n);
            assert_eq!(s.len(), (n / 4).clamp(2, 8).min(n), "{n}");
            assert!(
                s.windows(2).all(|w| w[0] < w[1]) && *s.last().unwrap() < n,
                "{n}"
            );
            assert!(
                s[0] < n.div_ceil(s.len()) && *s.last().unwrap() >= n - n / s.len(),
                "{n}"
            );
        }
    }

    /// A work that runs each brick as a separate machine would: a plan rebuilt from the shared
    /// choices alone, scores passed as bytes.
    struct Apart<'a> {
        source: &'a dyn BrickSource,
        opts: CompressOptions,
    }

    impl Apart<'_> {
        fn plan(&self, plan: &BrickPlan) -> BrickPlan {
            BrickPlan::with_choices(self.source, &self.opts, plan.brick, plan.choices.clone())
                .unwrap()
        }
    }

    impl BrickWork for Apart<'_> {
        type File = Vec<u8>;
        fn score_all(&self, plan: &BrickPlan) -> Result<Vec<ScoreSummary>, BrickError> {
            (0..plan.grid.len())
                .map(|i| {
                    let bytes = self.plan(plan).score(self.source, i)?.to_bytes(true);
                    Ok(ScoreSummary::from_bytes(&bytes).unwrap())
                })
                .collect()
        }
        fn encode_all(
            &self,
            plan: &BrickPlan,
            counts: Option<&[u64]>,
            _trial: usize,
        ) -> Result<Vec<CodedBrick<Vec<u8>>>, BrickError> {
            (0..plan.grid.len())
                .map(|i| {
                    let (file, kept) =
                        self.plan(plan)
                            .encode(self.source, i, counts.map(|k| k[i]))?;
                    Ok(CodedBrick {
                        len: file.len() as u64,
                        file,
                        kept,
                    })
                })
                .collect()
        }
    }

    /// Bricks compressed apart, from the shared choices and the scores' bytes, make the same
    /// file as in one process: scalar and PCA colour, a fraction and a byte target.
    #[test]
    fn bricks_compressed_apart_make_the_same_file() {
        let grey = Phantom::SheppLogan.generate([40, 36, 30]);
        let rgb = Phantom::RgbHead.generate([36, 30, 28]);
        for (v, target) in [
            (&grey, Target::Fraction(0.05)),
            (&grey, Target::Bytes(9_000)),
            (&rgb, Target::Fraction(0.04)),
        ] {
            let opts = CompressOptions {
                target,
                ..CompressOptions::default()
            };
            let here = compress_bricked(v, &opts, 20, &|_| {}).unwrap();
            let plan = BrickPlan::new(v, &opts, 20).unwrap();
            let work = Apart {
                source: v,
                opts: opts.clone(),
            };
            let a = allocate(&plan, &work).unwrap();
            let bricks: Vec<(Vec<u8>, u64)> =
                a.bricks.into_iter().map(|c| (c.file, c.kept)).collect();
            assert_eq!(plan.assemble(&bricks).unwrap().0, here.bytes, "{target:?}");
        }
    }

    /// The container streamed from the bricks kept on disk is the one built in memory
    /// (checked by `bricks_compressed_apart_make_the_same_file` too, for several trials of a
    /// byte target); the overhead reported is the file's, and a writer that fails is an
    /// error, not a panic or a short file called done.
    #[test]
    fn a_bricked_file_is_written_from_its_spill() {
        let v = Phantom::SheppLogan.generate([40, 36, 30]);
        let opts = CompressOptions {
            target: Target::Bytes(9_000),
            ..CompressOptions::default()
        };
        let spill = tempfile::tempdir().unwrap();
        let mut out = Vec::new();
        let w = compress_bricked_to(&v, &opts, 20, &|_| {}, Some(spill.path()), None, &mut out)
            .unwrap();
        assert_eq!(out, compress_bricked(&v, &opts, 20, &|_| {}).unwrap().bytes);
        assert_eq!(w.bytes, out.len() as u64);
        let f = wavesplat_codec::format::bricked::parse_bricked(&out).unwrap();
        assert_eq!(w.overhead, f.overhead_bytes(&f.brick_headers().unwrap()));
        assert_eq!(w.manifest, f.manifest);

        struct Full(usize);
        impl std::io::Write for Full {
            fn write(&mut self, b: &[u8]) -> std::io::Result<usize> {
                if self.0 == 0 {
                    return Err(std::io::Error::other("disk full"));
                }
                let n = b.len().min(self.0);
                self.0 -= n;
                Ok(n)
            }
            fn flush(&mut self) -> std::io::Result<()> {
                Ok(())
            }
        }
        for room in [0, 100, out.len() - 1] {
            let e = compress_bricked_to(&v, &opts, 20, &|_| {}, None, None, &mut Full(room))
                .unwrap_err();
            assert!(matches!(e, BrickError::Output(_)), "{room}: {e:?}");
        }
    }

    /// A source that counts its reads and fails the `fail_at`-th one (counting from 1; 0: none),
    /// as a kill, a lost disk or a full one would stop a compression midway.
    struct Flaky<'a> {
        volume: &'a Volume,
        reads: std::sync::atomic::AtomicUsize,
        fail_at: usize,
    }

    impl BrickSource for Flaky<'_> {
        fn dims(&self) -> [u64; 3] {
            BrickSource::dims(self.volume)
        }
        fn channels(&self) -> usize {
            BrickSource::channels(self.volume)
        }
        fn spacing(&self) -> [f32; 3] {
            BrickSource::spacing(self.volume)
        }
        fn placement(&self) -> Option<Placement> {
            BrickSource::placement(self.volume)
        }
        fn read(&self, origin: [u64; 3], dims: [usize; 3]) -> Result<Volume, ReadError> {
            let n = self.reads.fetch_add(1, std::sync::atomic::Ordering::SeqCst) + 1;
            if n == self.fail_at {
                return Err(ReadError::Io {
                    path: "volume.raw".into(),
                    source: std::io::Error::other("the disk went away"),
                });
            }
            BrickSource::read(self.volume, origin, dims)
        }
    }

    /// A compression stopped midway and run again with its checkpoint does only what is
    /// missing and writes the file an uninterrupted run writes, byte for byte. A fraction
    /// target stopped while coding its third brick from the end plans, scores and reads
    /// nothing again but those three bricks; run a third time it reads nothing. A byte target
    /// (a depth compared on a sample, several trials, each brick's count its own entry)
    /// stopped in its last trial ends in the same file, reading less, and nothing the third
    /// time. A checkpoint of other options is emptied, not used.
    #[test]
    fn a_compression_run_again_with_its_checkpoint_goes_on_where_it_stopped() {
        let v = Phantom::SheppLogan.generate([40, 36, 30]);
        // One thread: bricks are read in grid order, so where a run stops is known.
        let one_thread = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap();
        for target in [Target::Fraction(0.05), Target::Bytes(9_000)] {
            let opts = CompressOptions {
                target,
                ..CompressOptions::default()
            };
            let bricks = BrickPlan::new(&v, &opts, 20).unwrap().grid.len();
            let dir = tempfile::tempdir().unwrap();
            let key = format!("{opts:?}");
            let run = |fail_at: usize, checkpoint: bool| {
                let source = Flaky {
                    volume: &v,
                    reads: Default::default(),
                    fail_at,
                };
                let (cp, resumed) = if checkpoint {
                    let (cp, r) = crate::checkpoint::Checkpoint::open(dir.path(), &key).unwrap();
                    (Some(cp), r)
                } else {
                    (None, Default::default())
                };
                let mut out = Vec::new();
                let r = one_thread.install(|| {
                    compress_bricked_to(&source, &opts, 20, &|_| {}, None, cp.as_ref(), &mut out)
                });
                (r.map(|_| out), resumed, source.reads.into_inner())
            };
            // Without a checkpoint: the file, and how many reads it takes.
            let (whole, _, all_reads) = run(0, false);
            let whole = whole.unwrap();
            let (stopped, fresh, _) = run(all_reads - 2, true);
            assert!(
                matches!(stopped, Err(BrickError::Read { .. })),
                "{target:?}: {stopped:?}"
            );
            assert_eq!(fresh, crate::checkpoint::Resumed::default());
            let (again, resumed, reads) = run(0, true);
            assert_eq!(again.unwrap(), whole, "{target:?}");
            assert_eq!(resumed.scored, bricks, "{target:?}: every brick was scored");
            assert!(resumed.planned, "{target:?}");
            assert!(reads < all_reads, "{target:?}: {reads} of {all_reads}");
            // Everything kept, the plan included (the whole's faces, a byte target's depth
            // compared on a sample): nothing is read.
            let (third, _, third_reads) = run(0, true);
            assert_eq!(third.unwrap(), whole, "{target:?}");
            assert_eq!(third_reads, 0, "{target:?}");
            if matches!(target, Target::Fraction(_)) {
                // The plan was kept before the stop: only the 3 bricks left are read.
                assert_eq!(resumed.coded, bricks - 3, "{resumed:?}");
                assert_eq!(reads, 3);
            }
            // Other options: the entries are removed, and nothing of them is used.
            let other = CompressOptions {
                target: Target::Fraction(0.02),
                ..CompressOptions::default()
            };
            let (_, replaced) =
                crate::checkpoint::Checkpoint::open(dir.path(), &format!("{other:?}")).unwrap();
            assert!(replaced.replaced && !replaced.planned);
            assert_eq!(replaced.scored + replaced.coded, 0);
        }
    }

    /// A brick with no top kept, coded for a count within its cap, keeps its top on the way:
    /// the next count is coded from it, reading nothing. Beyond its cap, or without a cap, it
    /// is read once per count and keeps none. Every file is the one a fresh transform writes.
    #[test]
    fn a_brick_transformed_again_keeps_its_top_only_within_its_cap() {
        use std::sync::atomic::Ordering::Relaxed;
        let v = Phantom::Ct.generate([48, 48, 48]);
        let opts = CompressOptions {
            target: Target::Coefficients(600),
            ..crate::encode::Effort::Fast.options()
        };
        let plan = BrickPlan::new(&v, &opts, 24).unwrap();
        let cap = plan.top_cap(0).unwrap();
        let source = Flaky {
            volume: &v,
            reads: Default::default(),
            fail_at: 0,
        };
        let fresh = |count: u64| plan.encode(&v, 0, Some(count)).unwrap().0;
        let key = (0, plan.grid[0]);
        let tops = KeptTops::for_plan(&plan);
        let code = |count: u64, cap: Option<u64>| {
            plan.encode_from(&source, 0, Some(count), &tops, 0, cap)
                .unwrap()
                .0
        };
        assert_eq!(code(cap + 1, Some(cap)), fresh(cap + 1));
        assert_eq!(code(cap / 2, None), fresh(cap / 2));
        assert!(tops.get(&key).is_none());
        assert_eq!(source.reads.load(Relaxed), 2);
        assert_eq!(code(cap / 2, Some(cap)), fresh(cap / 2));
        assert!(tops.get(&key).is_some());
        assert_eq!(source.reads.load(Relaxed), 3);
        assert_eq!(code(cap / 3, Some(cap)), fresh(cap / 3));
        assert_eq!(
            source.reads.load(Relaxed),
            3,
            "coded from the top kept on the way"
        );
        assert_eq!(tops.counts(), (1, 3));
    }

    /// Where the bricks do not refine, the checkpoint keeps each brick's top as well: a run
    /// again after the scores were kept but before a brick was coded codes it from its kept
    /// top, reading nothing, into the same file; without the tops it reads those bricks
    /// again, once each (a byte target too, over its trials), and keeps their tops again. A
    /// count target and a byte target (several trials, each brick's count its own entry), on
    /// one thread and on two.
    #[test]
    fn a_run_again_codes_the_bricks_not_yet_coded_from_their_kept_tops() {
        let v = Phantom::SheppLogan.generate([40, 36, 30]);
        for threads in [1, 2] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            for target in [Target::Coefficients(3_000), Target::Bytes(6_000)] {
                let opts = CompressOptions {
                    target,
                    ..crate::encode::Effort::Fast.options()
                };
                let plan = BrickPlan::new(&v, &opts, 20).unwrap();
                let bricks = plan.grid.len();
                assert!(plan.top_cap(0).is_some(), "the bricks keep tops");
                let dir = tempfile::tempdir().unwrap();
                let key = format!("{opts:?}");
                let run = |checkpoint: bool| {
                    let source = Flaky {
                        volume: &v,
                        reads: Default::default(),
                        fail_at: 0,
                    };
                    let (cp, resumed) = if checkpoint {
                        let (cp, r) =
                            crate::checkpoint::Checkpoint::open(dir.path(), &key).unwrap();
                        (Some(cp), r)
                    } else {
                        (None, Default::default())
                    };
                    let mut out = Vec::new();
                    pool.install(|| {
                        compress_bricked_to(
                            &source,
                            &opts,
                            20,
                            &|_| {},
                            None,
                            cp.as_ref(),
                            &mut out,
                        )
                    })
                    .unwrap();
                    (out, resumed, source.reads.into_inner())
                };
                let (whole, _, _) = run(false);
                let (first, _, _) = run(true);
                assert_eq!(first, whole);
                // A kill after the scores and tops were kept, before any brick was coded.
                let remove = |prefix: &str| {
                    for e in std::fs::read_dir(dir.path()).unwrap() {
                        let path = e.unwrap().path();
                        let name = path.file_name().unwrap().to_string_lossy().to_string();
                        if name.starts_with(prefix) {
                            std::fs::remove_file(path).unwrap();
                        }
                    }
                };
                remove("brick-");
                let (again, resumed, reads) = run(true);
                assert_eq!(again, whole, "{target:?} {threads}");
                assert_eq!(
                    (resumed.scored, resumed.tops),
                    (bricks, bricks),
                    "{resumed:?}"
                );
                assert_eq!(resumed.coded, 0);
                assert_eq!(reads, 0, "{target:?} {threads}: coded from the kept tops");
                // Without the tops the bricks not coded are read and transformed again, once
                // each: a brick transformed again keeps its top for the rate search's next
                // trial, and in the checkpoint.
                remove("brick-");
                remove("top-");
                let (again, resumed, reads) = run(true);
                assert_eq!(again, whole, "{target:?} {threads}");
                assert_eq!(resumed.tops, 0);
                assert_eq!(reads, bricks, "{target:?} {threads}");
                // Killed again before any brick was coded: the tops kept on the way serve.
                remove("brick-");
                let (again, resumed, reads) = run(true);
                assert_eq!(again, whole, "{target:?} {threads}");
                assert_eq!(resumed.tops, bricks, "{target:?} {threads}");
                assert_eq!(reads, 0, "{target:?} {threads}");
            }
        }
    }

    /// The plan's choices a checkpoint keeps read back as they were (a colour transform, a
    /// rate search's start, none of either); anything cut short, longer or with an unknown
    /// tag is refused (the plan is then made again).
    #[test]
    fn the_plan_s_choices_read_back_from_their_bytes() {
        let rgb = Phantom::RgbHead.generate([36, 30, 28]);
        let grey = Phantom::SheppLogan.generate([40, 36, 30]);
        for (v, target) in [
            (&rgb, Target::Fraction(0.04)),
            (&grey, Target::Bytes(9_000)),
            (&grey, Target::Fraction(0.05)),
        ] {
            let opts = CompressOptions {
                target,
                ..CompressOptions::default()
            };
            let kept = PlanChoices::of(&BrickPlan::new(v, &opts, 20).unwrap());
            let bytes = kept.to_bytes();
            assert_eq!(PlanChoices::from_bytes(&bytes), Some(kept.clone()));
            assert!(PlanChoices::from_bytes(&bytes[..bytes.len() - 1]).is_none());
            let mut longer = bytes.clone();
            longer.push(0);
            assert!(PlanChoices::from_bytes(&longer).is_none());
            let mut tag = bytes.clone();
            tag[8] = 7;
            assert!(PlanChoices::from_bytes(&tag).is_none());
        }
        let with_colour =
            PlanChoices::of(&BrickPlan::new(&rgb, &CompressOptions::default(), 20).unwrap());
        assert!(with_colour.choices.color.is_some());
        let scalar = PlanChoices::of(
            &BrickPlan::new(
                &grey,
                &CompressOptions {
                    target: Target::Bytes(9_000),
                    ..CompressOptions::default()
                },
                20,
            )
            .unwrap(),
        );
        assert!(scalar.coefficients_per_byte.is_some() && scalar.choices.offset.is_some());
    }

    /// A summary survives its bytes; damaged bytes are refused, never read as another summary.
    /// In memory it holds its filled bins only, a few bytes each (the planner holds one per
    /// brick), and reads the same counts as the dense sum built from it.
    #[test]
    fn a_score_summary_reads_back_from_its_bytes_and_refuses_damage() {
        let v = Phantom::Spheres.generate([24, 24, 24]);
        let s = score_summary(&v, &CompressOptions::default(), &|_, _| {}).unwrap();
        let mut dense = SummedScores::new();
        dense.add(&s);
        let filled = dense.counts().iter().filter(|c| **c > 0).count();
        assert!(filled > 100, "{filled} bins");
        assert_eq!(dense.counts().iter().sum::<u64>(), s.nonzero);
        let lean = ScoreSummary::from_bytes(&s.to_bytes(false)).unwrap();
        assert!(!lean.has_energies() && s.has_energies());
        assert_eq!(lean, s.clone().without_energies());
        assert!(s.to_bytes(false).len() < 64 + 6 * filled, "{filled} bins");
        assert!(lean.heap_bytes() <= 6 * filled, "{} B", lean.heap_bytes());
        for cut in [0, 1000, 30_000, 32_000, 34_000, 65_535] {
            let above = dense.counts()[cut + 1..].iter().sum::<u64>();
            assert_eq!(lean.count_above_and_at(cut), (above, dense.counts()[cut]));
        }
        let bytes = s.to_bytes(true);
        let back = ScoreSummary::from_bytes(&bytes).unwrap();
        assert_eq!(back, s);
        let mut again = SummedScores::new();
        again.add(&back);
        assert_eq!(again.energies(), dense.energies());
        for cut in [0, 7, 8, 40, bytes.len() - 1] {
            assert!(
                ScoreSummary::from_bytes(&bytes[..cut]).is_err(),
                "cut at {cut}"
            );
        }
        let mut longer = bytes.clone();
        longer.push(0);
        assert!(ScoreSummary::from_bytes(&longer).is_err());
        let mut tag = bytes.clone();
        tag[7] ^= 1;
        assert!(ScoreSummary::from_bytes(&tag).is_err());
        // Totals that disagree with the bins, a bin's energy that is not a finite
        // non-negative number, and a varint past 64 bits are refused.
        let mut nonzero = bytes.clone();
        nonzero[24] ^= 1;
        assert!(ScoreSummary::from_bytes(&nonzero).is_err());
        let first_energy = bytes.len() - 8 * s.bins().count();
        for bad in [f64::NAN, f64::INFINITY, -1.0] {
            let mut e = bytes.clone();
            // The last bin's energy is the last 8 bytes.
            let n = e.len();
            e[n - 8..].copy_from_slice(&bad.to_le_bytes());
            assert!(ScoreSummary::from_bytes(&e).is_err(), "{bad}");
        }
        assert!(first_energy > 41);
        let mut long = bytes[..41].to_vec();
        long.extend_from_slice(&[0xff; 9]);
        long.push(0x02);
        assert!(ScoreSummary::from_bytes(&long).is_err());
        // Summaries without energies cannot meet a Q_V target: refused, not kept whole.
        let refused = allocate_units(
            Target::QvPercent(90.0),
            1,
            0,
            None,
            || Ok(vec![lean.clone()]),
            |_, _| -> Result<Vec<CodedBrick<()>>, BrickError> { unreachable!() },
        );
        assert!(matches!(refused, Err(BrickError::InvalidOption(_))));
    }

    /// A byte target below what the bricks' headers alone take is refused, saying how small
    /// a file they made (an all-zero volume keeps nothing, so "one coefficient each" was wrong).
    #[test]
    fn a_byte_target_below_the_headers_is_refused_with_the_smallest_size() {
        let v = Phantom::Zero.generate([40, 40, 40]);
        let opts = CompressOptions {
            target: Target::Bytes(1_000),
            ..CompressOptions::default()
        };
        match compress_bricked(&v, &opts, 16, &|_| {}) {
            Err(BrickError::InvalidOption(m)) => {
                let bytes: u64 = m
                    .split("takes ")
                    .nth(1)
                    .and_then(|t| t.split(' ').next())
                    .and_then(|n| n.parse().ok())
                    .unwrap_or_else(|| panic!("{m}"));
                assert!(bytes > 1_000 && m.contains("27 parts"), "{m}");
                // The file that size names is one the target could have been.
                let fits = CompressOptions {
                    target: Target::Bytes(bytes),
                    ..CompressOptions::default()
                };
                let made = compress_bricked(&v, &fits, 16, &|_| {}).unwrap();
                assert!(made.bytes.len() as u64 <= bytes, "{m}");
            }
            other => panic!("{:?}", other.map(|c| c.bytes.len())),
        }
    }

    /// A summary's total is the energy its coefficients could keep: the file's total energy
    /// for a volume without a bridge (the same number, summed alike), less for a brick, whose
    /// bridge's coefficients wholly outside its box are never kept.
    #[test]
    fn the_selectable_energy_is_the_total_without_a_bridge_and_less_with_one() {
        let v = Phantom::Ct.generate([40, 36, 30]);
        let opts = CompressOptions::default();
        let summary = score_summary(&v, &opts, &|_, _| {}).unwrap();
        let whole = compress(&v, &opts, &|_, _| {}).unwrap();
        assert_eq!(summary.total_energy, whole.header.total_energy);
        let plan = BrickPlan::new(&v, &opts, 16).unwrap();
        for i in [0, plan.grid.len() - 1] {
            let (file, _) = plan.encode(&v, i, None).unwrap();
            let total = wavesplat_codec::format::parse_file(&file)
                .unwrap()
                .header
                .total_energy;
            let selectable = plan.score(&v, i).unwrap().total_energy;
            assert!(
                selectable > 0.0 && selectable < total,
                "{selectable} {total}"
            );
        }
    }

    /// A Q_V target keeps about what it keeps of the whole volume, not everything (the
    /// bridges' energy outside the bricks' boxes is never kept, and once was counted).
    #[test]
    fn a_bricked_qv_target_keeps_about_the_whole_s_count() {
        let v = Phantom::Ct.generate([48, 40, 36]);
        for q in [80.0, 99.0] {
            let opts = CompressOptions {
                target: Target::QvPercent(q),
                ..CompressOptions::default()
            };
            let whole = compress(&v, &opts, &|_, _| {}).unwrap().stats.kept;
            let bricked = compress_bricked(&v, &opts, 16, &|_| {}).unwrap();
            let kept: u64 = bricked.manifest.bricks.iter().map(|b| b.kept).sum();
            // 16³ bricks of this small volume keep 4.4 times the whole's count at 80 %: each
            // brick's own coarse bands.
            assert!(
                kept < bricked.nonzero / 2 && kept <= 5 * whole.max(25),
                "Q_V {q} %: bricks keep {kept} of {}, the whole {whole}",
                bricked.nonzero
            );
        }
    }

    #[test]
    fn shares_sum_to_the_whole() {
        let v = Phantom::Spheres.generate([32, 32, 32]);
        let opts = CompressOptions::default();
        let s: Vec<ScoreSummary> = brick_grid([32, 32, 32], 16)
            .into_iter()
            .map(|(o, d)| score_summary(&crop(&v, o, d).unwrap(), &opts, &|_, _| {}).unwrap())
            .collect();
        let mut whole = SummedScores::new();
        s.iter().for_each(|b| whole.add(b));
        let nonzero: u64 = s.iter().map(|s| s.nonzero).sum();
        assert_eq!(whole.nonzero, nonzero);
        for k in [0, 1, 17, 1000, nonzero - 1, nonzero, nonzero + 5] {
            let shares = per_brick_counts(&s, &whole, k);
            assert_eq!(shares.iter().sum::<u64>(), k.min(nonzero), "k {k}");
        }
    }
}
