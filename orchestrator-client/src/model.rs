//! Domain types of the orchestrator: what a job asks for ([`JobSpec`]), where it stands
//! ([`JobState`]) and how an attempt ended ([`Outcome`]). Plain Rust, serialisable for the
//! store; the wire types live in `wavesplat_proto::pb` and are converted in [`crate::convert`].

use crate::error::ClientError;
use serde::{Deserialize, Deserializer, Serialize, Serializer};
use std::path::PathBuf;
use wavesplat_codec::family::Family;
use wavesplat_codec::format::CoderKind;

/// A job's id (assigned in submission order, starting at 1).
pub type JobId = u64;

/// Longest volume name (bytes), as in the cache.
pub const MAX_NAME_BYTES: usize = 255;

/// Where a job's volume comes from.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub enum Source {
    /// A file on storage every worker can read.
    Path(PathBuf),
    /// Bytes uploaded with the submission and kept by the orchestrator (keyed by their hash).
    Upload {
        /// Size in bytes.
        size: u64,
    },
}

/// Sample type of a headerless raw file (the worker's reader maps it to its own type).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum SampleType {
    /// Unsigned 8-bit.
    U8,
    /// Signed 8-bit.
    I8,
    /// Unsigned 16-bit.
    U16,
    /// Signed 16-bit.
    I16,
    /// Unsigned 32-bit.
    U32,
    /// Signed 32-bit.
    I32,
    /// Unsigned 64-bit.
    U64,
    /// Signed 64-bit.
    I64,
    /// IEEE-754 32-bit float.
    F32,
    /// IEEE-754 64-bit float.
    F64,
}

impl SampleType {
    /// Parses `u8`, `i8`, `u16`, `i16`, `u32`, `i32`, `u64`, `i64`, `f32` or `f64`
    /// (case-insensitive; `uint8`, `int8`, …, `int64`, `float32`, `float`, `float64` and
    /// `double` too: the names the raw reader takes).
    pub fn from_name(name: &str) -> Option<SampleType> {
        match name.trim().to_ascii_lowercase().as_str() {
            "u8" | "uint8" => Some(SampleType::U8),
            "i8" | "int8" => Some(SampleType::I8),
            "u16" | "uint16" => Some(SampleType::U16),
            "i16" | "int16" => Some(SampleType::I16),
            "u32" | "uint32" => Some(SampleType::U32),
            "i32" | "int32" => Some(SampleType::I32),
            "u64" | "uint64" => Some(SampleType::U64),
            "i64" | "int64" => Some(SampleType::I64),
            "f32" | "float32" | "float" => Some(SampleType::F32),
            "f64" | "float64" | "double" => Some(SampleType::F64),
            _ => None,
        }
    }

    /// The canonical names.
    pub fn names() -> &'static [&'static str] {
        &[
            "u8", "i8", "u16", "i16", "u32", "i32", "u64", "i64", "f32", "f64",
        ]
    }

    /// The canonical name.
    pub fn name(self) -> &'static str {
        match self {
            SampleType::U8 => "u8",
            SampleType::I8 => "i8",
            SampleType::U16 => "u16",
            SampleType::I16 => "i16",
            SampleType::U32 => "u32",
            SampleType::I32 => "i32",
            SampleType::U64 => "u64",
            SampleType::I64 => "i64",
            SampleType::F32 => "f32",
            SampleType::F64 => "f64",
        }
    }

    /// Bytes per sample.
    pub fn size(self) -> usize {
        match self {
            SampleType::U8 | SampleType::I8 => 1,
            SampleType::U16 | SampleType::I16 => 2,
            SampleType::U32 | SampleType::I32 | SampleType::F32 => 4,
            SampleType::U64 | SampleType::I64 | SampleType::F64 => 8,
        }
    }
}

/// Layout of a headerless raw file (see `wavesplat_worker::archive` for the naming convention).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct RawLayout {
    /// Dimensions (x fastest).
    pub dims: [usize; 3],
    /// Sample type.
    pub dtype: SampleType,
    /// Big-endian samples.
    pub big_endian: bool,
    /// 1 or 3.
    pub channels: usize,
}

impl RawLayout {
    /// Checks the layout (channels 1 or 3, no zero dimension).
    pub fn validate(&self) -> Result<(), ClientError> {
        if self.channels != 1 && self.channels != 3 {
            return Err(ClientError::InvalidRequest(format!(
                "raw channels {}; allowed 1 or 3",
                self.channels
            )));
        }
        if self.dims.contains(&0) {
            return Err(ClientError::InvalidRequest(format!(
                "raw dims {:?}; each must be at least 1",
                self.dims
            )));
        }
        Ok(())
    }
}

/// How much to keep (mirrors the compressor's target, serialisable).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub enum TargetSpec {
    /// Fraction (0, 1] of all coefficients.
    Fraction(f64),
    /// Whole-file bytes.
    Bytes(u64),
    /// Number of coefficients.
    Coefficients(u64),
    /// Energy percentage Q_V.
    QvPercent(f64),
    /// Every non-zero coefficient.
    All,
}

/// The colour space a job compresses RGB volumes in.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum ColorSpace {
    /// RGB as is.
    Rgb,
    /// NTSC YIQ.
    Yiq,
    /// Principal components of the volume's colours.
    Pca,
}

impl ColorSpace {
    /// Parses `rgb`, `yiq` or `pca` (case-insensitive; `klt` and `eigen` mean PCA).
    pub fn from_name(name: &str) -> Option<ColorSpace> {
        match name.trim().to_ascii_lowercase().as_str() {
            "rgb" => Some(ColorSpace::Rgb),
            "yiq" => Some(ColorSpace::Yiq),
            "pca" | "klt" | "eigen" => Some(ColorSpace::Pca),
            _ => None,
        }
    }

    /// The canonical name.
    pub fn name(self) -> &'static str {
        match self {
            ColorSpace::Rgb => "rgb",
            ColorSpace::Yiq => "yiq",
            ColorSpace::Pca => "pca",
        }
    }
}

/// Parses a family name (`haar`, `linear`, `cubic`, case-insensitive).
pub fn parse_family(name: &str) -> Result<Family, ClientError> {
    Family::from_name(&name.trim().to_ascii_lowercase())
        .ok_or_else(|| invalid(format!("family {name:?}; allowed haar, linear, cubic")))
}

/// Parses a colour space name.
pub fn parse_colorspace(name: &str) -> Result<ColorSpace, ClientError> {
    ColorSpace::from_name(name)
        .ok_or_else(|| invalid(format!("colour space {name:?}; allowed rgb, yiq, pca")))
}

/// Parses a coder name (`sigmap`, `fast`, `range`, `huffman`, case-insensitive).
pub fn parse_coder(name: &str) -> Result<CoderKind, ClientError> {
    CoderKind::from_name(&name.trim().to_ascii_lowercase()).ok_or_else(|| {
        invalid(format!(
            "coder {name:?}; allowed sigmap, fast, range, huffman"
        ))
    })
}

/// Serialises the named option enums by their canonical names (the stored form of a job, and
/// part of its identity: [`JobSpec::dedup_key`]).
mod by_name {
    use super::*;

    pub trait Named: Copy {
        fn canonical(self) -> &'static str;
        fn parse(s: &str) -> Result<Self, ClientError>;
    }
    impl Named for Family {
        fn canonical(self) -> &'static str {
            self.name()
        }
        fn parse(s: &str) -> Result<Self, ClientError> {
            parse_family(s)
        }
    }
    impl Named for CoderKind {
        fn canonical(self) -> &'static str {
            self.name()
        }
        fn parse(s: &str) -> Result<Self, ClientError> {
            parse_coder(s)
        }
    }
    impl Named for ColorSpace {
        fn canonical(self) -> &'static str {
            self.name()
        }
        fn parse(s: &str) -> Result<Self, ClientError> {
            parse_colorspace(s)
        }
    }

    pub fn serialize<T: Named, S: Serializer>(v: &T, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(v.canonical())
    }

    pub fn deserialize<'de, T: Named, D: Deserializer<'de>>(d: D) -> Result<T, D::Error> {
        let s = String::deserialize(d)?;
        T::parse(&s).map_err(serde::de::Error::custom)
    }
}

/// Compressor options of a job, in the orchestrator's own terms (the worker maps them to the
/// compressor's options). Names are parsed on the way in; [`JobOptions::validate`] checks the
/// numbers once, at submission.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct JobOptions {
    /// Wavelet family.
    #[serde(with = "by_name")]
    pub family: Family,
    /// Decomposition depth (`None`: automatic).
    pub levels: Option<usize>,
    /// Colour space of RGB volumes.
    #[serde(with = "by_name")]
    pub colorspace: ColorSpace,
    /// Quantization bits 1..=16.
    pub bits: u8,
    /// Sigmap quantizer step (> 0).
    pub step: f64,
    /// Entropy coder.
    #[serde(with = "by_name")]
    pub coder: CoderKind,
    /// What to keep.
    pub target: TargetSpec,
    /// Tile edge (`None`: automatic).
    pub tile: Option<usize>,
    /// Quality layers (`None`: automatic).
    pub layers: Option<usize>,
    /// Rounds of least-squares refinement (`None`: the compressor's default).
    #[serde(default)]
    pub refine_rounds: Option<usize>,
    /// No least-squares refinement (the oracle's coefficients, as in the paper).
    #[serde(default)]
    pub no_refine: bool,
    /// Layer growth (`None`: the compressor's default).
    #[serde(default)]
    pub layer_growth: Option<f64>,
    /// Compress as a bricked volume in bricks of at most this side (`None`: one volume).
    #[serde(default)]
    pub brick: Option<usize>,
    /// Of a time series: the temporal group its time points are compressed together in
    /// (`None`: 8).
    #[serde(default)]
    pub time_group: Option<usize>,
    /// Compression effort (the options above given too override it). Left out of the stored
    /// form when it is the default, so that a job's identity is what it was before efforts.
    #[serde(default, skip_serializing_if = "Effort::is_default")]
    pub effort: Effort,
    /// Each worker's memory for this job in bytes (`None`: no limit): a volume compressed
    /// whole that would need more is refused, and a bricked job's workers keep tops only in
    /// what one brick per thread leaves. Left out of the stored form when unset, so that a job's
    /// identity is what it was before limits.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub memory_limit: Option<u64>,
}

/// Compression effort of a job, by name (the compressor's `Effort`: fast, default, best).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Effort {
    /// The depth predicted, one cheap refinement (bricks unrefined).
    Fast,
    /// Depths compared, three refinement rounds.
    #[default]
    Default,
    /// More refinement.
    Best,
}

impl Effort {
    /// Its name.
    pub fn name(self) -> &'static str {
        match self {
            Effort::Fast => "fast",
            Effort::Default => "default",
            Effort::Best => "best",
        }
    }

    fn is_default(&self) -> bool {
        *self == Effort::Default
    }
}

/// Parses an effort name.
pub fn parse_effort(name: &str) -> Result<Effort, ClientError> {
    match name.trim().to_ascii_lowercase().as_str() {
        "fast" => Ok(Effort::Fast),
        "default" => Ok(Effort::Default),
        "best" => Ok(Effort::Best),
        _ => Err(invalid(format!(
            "effort {name:?}; allowed fast, default, best"
        ))),
    }
}

pub use wavesplat_codec::format::bricked::MIN_BRICK;
/// Largest brick side a job may ask for (a brick is one transform: 1024³ is already 23 GB).
pub const MAX_BRICK: usize = 1024;

impl Default for JobOptions {
    /// The compressor's defaults (the worker's tests check that they agree).
    fn default() -> Self {
        JobOptions {
            family: Family::Linear,
            levels: None,
            colorspace: ColorSpace::Pca,
            bits: 8,
            step: 1.0,
            coder: CoderKind::Sigmap,
            target: TargetSpec::Fraction(0.05),
            tile: None,
            layers: None,
            refine_rounds: None,
            no_refine: false,
            layer_growth: None,
            brick: None,
            time_group: None,
            effort: Effort::Default,
            memory_limit: None,
        }
    }
}

fn invalid(msg: String) -> ClientError {
    ClientError::InvalidRequest(msg)
}

impl JobOptions {
    /// Checks every value.
    pub fn validate(self) -> Result<JobOptions, ClientError> {
        if !(1..=16).contains(&self.bits) {
            return Err(invalid(format!("bits {}; allowed 1..=16", self.bits)));
        }
        if !(self.step.is_finite() && self.step > 0.0) {
            return Err(invalid(format!(
                "step {}; must be finite and > 0",
                self.step
            )));
        }
        if let Some(l) = self.levels {
            if !(1..=16).contains(&l) {
                return Err(invalid(format!("levels {l}; allowed 1..=16")));
            }
        }
        if let Some(l) = self.layers {
            if l == 0 {
                return Err(invalid("layers 0; must be at least 1".into()));
            }
        }
        if self.refine_rounds.is_some_and(|r| r > 64) {
            return Err(invalid(format!(
                "refine rounds {:?}; allowed 0..=64",
                self.refine_rounds
            )));
        }
        if let Some(g) = self.layer_growth {
            if !(g.is_finite() && g > 1.0) {
                return Err(invalid(format!("layer growth {g}; must be finite and > 1")));
            }
        }
        if self.tile == Some(0) {
            return Err(invalid("tile 0; must be at least 1".into()));
        }
        if self.memory_limit == Some(0) {
            return Err(invalid("memory limit 0; must be at least 1 byte".into()));
        }
        if let Some(g) = self.time_group {
            if !g.is_power_of_two() || g > 1 << 15 {
                return Err(invalid(format!(
                    "time group {g}; a power of two up to 32768"
                )));
            }
        }
        if let Some(b) = self.brick {
            if !(MIN_BRICK..=MAX_BRICK).contains(&b) {
                return Err(invalid(format!(
                    "brick {b}; allowed {MIN_BRICK}..={MAX_BRICK} voxels a side"
                )));
            }
            if self.family == Family::Cubic {
                return Err(invalid(
                    "bricked volumes do not support the cubic family yet; use linear or haar"
                        .into(),
                ));
            }
        }
        match self.target {
            TargetSpec::Fraction(f) if !(f > 0.0 && f <= 1.0) => {
                return Err(invalid(format!("target fraction {f}; allowed (0, 1]")))
            }
            TargetSpec::QvPercent(q) if !(q > 0.0 && q <= 100.0) => {
                return Err(invalid(format!("target Q_V {q} %; allowed (0, 100]")))
            }
            TargetSpec::Bytes(0) | TargetSpec::Coefficients(0) => {
                return Err(invalid(
                    "target of 0 bytes/coefficients; must be > 0".into(),
                ))
            }
            _ => {}
        }
        Ok(self)
    }
}

/// Everything a worker needs to run a job.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct JobSpec {
    /// Name of the result in the cache.
    pub name: String,
    /// Where the volume comes from.
    pub source: Source,
    /// SHA-256 of the source: the file, or the bundle of a multi-file volume (see
    /// `wavesplat_worker::archive::source_bytes`).
    pub sha256: [u8; 32],
    /// Raw layout (`None`: a format with a header — DICOM, NRRD, MetaImage, NIfTI).
    pub raw: Option<RawLayout>,
    /// The one channel read of a source of several (a Zarr array's channel axis; of RGB, one
    /// of its three), as a volume of one channel; `None`: every channel, and a Zarr array of
    /// several is refused. Left out of the stored form when unset, so that a job's identity
    /// is what it was before channels were chosen. A worker that predates it refuses a Zarr
    /// array of several channels (the only jobs `archive submit` gives a channel), but would
    /// read every channel of an RGB source given one through the API.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub channel: Option<u32>,
    /// Compressor options.
    pub options: JobOptions,
    /// Set for one brick's share of a bricked volume's job (its parent): what the worker
    /// running the parent decided for all bricks, and which brick and step this is.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub part: Option<PartSpec>,
}

/// One step of one brick of a bricked job, run as a job of its own so that any worker can take
/// it: the parent's worker plans the volume (depth, offset, colour transform), spreads the
/// bricks' scoring and then their coding over the queue, and commits the volume to the cache
/// once, from the parts' results.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PartSpec {
    /// The bricked job this belongs to.
    pub parent: JobId,
    /// The brick, in the grid's order (x fastest).
    pub index: u32,
    /// Bricks in the grid.
    pub of: u32,
    /// Scoring or coding.
    pub step: PartStep,
    /// Decomposition depth of every brick.
    pub levels: u32,
    /// The whole's offset (scalar volumes).
    pub offset: Option<f64>,
    /// The whole's colour transform (RGB volumes).
    pub color: Option<PartColor>,
    /// The source file's length when the job was planned (`None`: not checked): a part whose
    /// file has another length refuses to run rather than mix two files' bricks.
    #[serde(default)]
    pub source_bytes: Option<u64>,
    /// Set for a part of a time series: the series' time points. The part is then unit
    /// `index` of `of` (every temporal component's bricks, component after component), and
    /// `offset` a time point's.
    #[serde(default)]
    pub time_points: Option<u32>,
    /// The worker that last scored or coded this brick, which may hold its kept top: a lease
    /// from it takes this part before older ones, any worker's otherwise. Not part of the
    /// part's identity ([`JobSpec::dedup_key`]): it steers the work, it does not change it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub prefer_worker: Option<String>,
}

/// What a part does.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub enum PartStep {
    /// Score the brick's coefficients: the result is its score summary (with energies when
    /// `energies`).
    Score {
        /// Whether the summary carries each bin's energy (a Q_V target needs them).
        energies: bool,
    },
    /// Code the brick keeping its top `count` coefficients (`None`: all): the result is the
    /// brick's `.wsp` file. `trial` numbers the rate search's rounds.
    Encode {
        /// Coefficients to keep.
        count: Option<u64>,
        /// The round of the byte target's search.
        trial: u32,
    },
}

/// A colour transform as plain numbers (the compressor's `ColorTransform` without its kind,
/// which is the job's colour space).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PartColor {
    /// Rows: the projections onto C1..C3.
    pub basis: [[f64; 3]; 3],
    /// The colour subtracted first.
    pub mean: [f64; 3],
    /// Each channel's importance.
    pub importance: [f64; 3],
}

/// Whether `name` can be a part's preferred worker: 1..=[`MAX_NAME_BYTES`] bytes without
/// control characters.
pub fn is_worker_name(name: &str) -> bool {
    !name.is_empty() && name.len() <= MAX_NAME_BYTES && !name.chars().any(char::is_control)
}

/// Largest result a part may report: a brick's file (a 1024³ brick's is far below this).
pub const MAX_PART_RESULT_BYTES: usize = 512 << 20;

impl PartSpec {
    /// Checks the numbers.
    pub fn validate(&self) -> Result<(), ClientError> {
        if self.of == 0 || self.index >= self.of {
            return Err(invalid(format!(
                "part {} of {}: the index must be below the count",
                self.index, self.of
            )));
        }
        if !(1..=16).contains(&self.levels) {
            return Err(invalid(format!(
                "part depth {}; allowed 1..=16",
                self.levels
            )));
        }
        if self.time_points == Some(0) {
            return Err(invalid("a part of a series of no time points".to_string()));
        }
        if let Some(w) = &self.prefer_worker {
            if !is_worker_name(w) {
                return Err(invalid(format!(
                    "a part's preferred worker must be 1..={MAX_NAME_BYTES} bytes without \
                     control characters ({} bytes)",
                    w.len()
                )));
            }
        }
        let finite = |v: &[f64]| v.iter().all(|x| x.is_finite());
        if self.offset.is_some_and(|o| !o.is_finite())
            || self.color.is_some_and(|c| {
                !finite(&c.mean) || !finite(&c.importance) || !c.basis.iter().all(|r| finite(r))
            })
        {
            return Err(invalid(
                "part offset or colour transform not finite".to_string(),
            ));
        }
        Ok(())
    }

    /// A short label: "brick 3/8 scoring", "series unit 3/8 coding (trial 1)".
    pub fn label(&self) -> String {
        let what = if self.time_points.is_some() {
            "series unit"
        } else {
            "brick"
        };
        let (i, of) = (self.index + 1, self.of);
        match self.step {
            PartStep::Score { .. } => format!("{what} {i}/{of} scoring"),
            PartStep::Encode { trial, .. } => format!("{what} {i}/{of} coding (trial {trial})"),
        }
    }
}

impl JobSpec {
    /// Validates the spec (name, layout, options).
    pub fn validate(mut self) -> Result<JobSpec, ClientError> {
        if self.name.is_empty()
            || self.name.len() > MAX_NAME_BYTES
            || self.name.chars().any(char::is_control)
        {
            return Err(invalid(format!(
                "name {:?}; must be 1..={MAX_NAME_BYTES} bytes without control characters",
                self.name
            )));
        }
        if let Some(r) = &self.raw {
            r.validate()?;
        }
        if let Source::Path(p) = &self.source {
            if p.as_os_str().is_empty() {
                return Err(invalid("empty source path".into()));
            }
        }
        self.options = self.options.validate()?;
        if let Some(p) = &self.part {
            p.validate()?;
            if self.options.brick.is_none() && p.time_points.is_none() {
                return Err(invalid(
                    "a part of a job that is neither bricked nor a time series".into(),
                ));
            }
        }
        Ok(self)
    }

    /// Whether `part` is a part of this job: the same delivery, source and options.
    pub fn is_parent_of(&self, part: &JobSpec) -> bool {
        self.part.is_none()
            && self.name == part.name
            && self.source == part.source
            && self.sha256 == part.sha256
            && self.raw == part.raw
            && self.channel == part.channel
            && self.options == part.options
    }

    /// The identity of the work: content hash, layout, options and the name it is delivered
    /// under (not the source location: the same file uploaded or read from another path is the
    /// same job). Two submissions with the same key are the same job; the same content under a
    /// new name (`archive submit --name-suffix`) is a new delivery.
    pub fn dedup_key(&self) -> String {
        let opts = serde_json::to_string(&(&self.raw, &self.options)).unwrap_or_default();
        let part = match &self.part {
            None => String::new(),
            Some(p) => {
                let work = PartSpec {
                    prefer_worker: None,
                    ..p.clone()
                };
                format!("|part:{}", serde_json::to_string(&work).unwrap_or_default())
            }
        };
        // Only a chosen channel is said: the keys of jobs without one stay what they were.
        let channel = self
            .channel
            .map_or(String::new(), |c| format!("|channel:{c}"));
        format!(
            "{}|{opts}|{}{part}{channel}",
            wavesplat_net::digest::hex(&self.sha256),
            self.name
        )
    }
}

/// Why an attempt failed; decides whether the job is retried.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum FailureKind {
    /// Not a valid volume (size, dims, NaN, header, hash mismatch).
    InvalidInput,
    /// The compressor rejected the volume with these options.
    Compress,
    /// The source could not be read.
    SourceUnavailable,
    /// The cache could not be reached.
    CacheUnavailable,
    /// The cache refused the result.
    CacheRejected,
    /// The worker stopped heartbeating.
    LeaseExpired,
    /// Anything else.
    Worker,
}

impl FailureKind {
    /// Whether running the job again cannot help.
    pub fn is_permanent(self) -> bool {
        matches!(
            self,
            FailureKind::InvalidInput | FailureKind::Compress | FailureKind::CacheRejected
        )
    }

    /// Short name.
    pub fn name(self) -> &'static str {
        match self {
            FailureKind::InvalidInput => "invalid-input",
            FailureKind::Compress => "compress",
            FailureKind::SourceUnavailable => "source-unavailable",
            FailureKind::CacheUnavailable => "cache-unavailable",
            FailureKind::CacheRejected => "cache-rejected",
            FailureKind::LeaseExpired => "lease-expired",
            FailureKind::Worker => "worker",
        }
    }
}

/// A failed attempt.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Failure {
    /// What kind.
    pub kind: FailureKind,
    /// The reason, for people.
    pub message: String,
}

/// A successful delivery to the cache.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Delivery {
    /// The volume's id in the cache.
    pub cache_volume_id: u64,
    /// Size of the compressed file.
    pub output_bytes: u64,
    /// Voxels of the source volume.
    pub voxels: u64,
    /// The cache already held identical content.
    pub existed: bool,
    /// SHA-256 of the delivered file, lower-case hex (empty in jobs stored before it was
    /// recorded).
    #[serde(default)]
    pub sha256: String,
}

/// How an attempt ended.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Outcome {
    /// Delivered.
    Delivered(Delivery),
    /// Failed.
    Failed(Failure),
}

/// Bytes of a lease's token ([`LeaseToken`]).
pub const LEASE_TOKEN_BYTES: usize = 16;

/// Bytes of the form a lease's token is stored in: its SHA-256.
pub const LEASE_TOKEN_DIGEST_BYTES: usize = 32;

/// The secret of one lease: random bytes the orchestrator draws when it grants the lease and
/// hands only to the worker it leases to (`Lease.lease_token`), which every RPC acting on the
/// lease must present. The store keeps only the secret's SHA-256 (with the running attempt;
/// never in a job's wire form), so that whoever reads the store (a backup, an operator's
/// query) learns nothing that acts on a lease; a presented token is hashed and compared with
/// it. The secret itself is held only by the token the orchestrator has just drawn, to hand it
/// out. Its `Debug` shows no bytes; its stored form is the digest in lower-case hex. Two
/// tokens are equal when their digests are.
#[derive(Clone, Copy)]
pub struct LeaseToken {
    digest: [u8; LEASE_TOKEN_DIGEST_BYTES],
    secret: Option<[u8; LEASE_TOKEN_BYTES]>,
}

impl LeaseToken {
    /// The token of a freshly drawn secret.
    pub fn from_secret(secret: [u8; LEASE_TOKEN_BYTES]) -> LeaseToken {
        LeaseToken {
            digest: wavesplat_net::digest::sha256(&secret),
            secret: Some(secret),
        }
    }

    /// The token of its stored form: a digest ([`LEASE_TOKEN_DIGEST_BYTES`]), or the secret
    /// itself as stores before digests kept it ([`LEASE_TOKEN_BYTES`]: it still matches, and
    /// is stored as its digest when its job is next written); `None` for any other length.
    pub fn from_stored(bytes: &[u8]) -> Option<LeaseToken> {
        match bytes.len() {
            LEASE_TOKEN_DIGEST_BYTES => Some(LeaseToken {
                digest: bytes.try_into().ok()?,
                secret: None,
            }),
            LEASE_TOKEN_BYTES => Some(LeaseToken::from_secret(bytes.try_into().ok()?)),
            _ => None,
        }
    }

    /// What the store keeps: the secret's SHA-256.
    pub fn stored(&self) -> &[u8; LEASE_TOKEN_DIGEST_BYTES] {
        &self.digest
    }

    /// The secret, to hand to the worker the lease is granted to: known in a token drawn by
    /// this process, and in one an older build stored as itself; `None` in one read back as a
    /// digest.
    pub fn secret(&self) -> Option<&[u8; LEASE_TOKEN_BYTES]> {
        self.secret.as_ref()
    }

    /// Whether `presented` is this token's secret: its SHA-256 compared with the digest in
    /// constant time (a presented string of another length is refused at once: the length is
    /// no secret).
    pub fn matches(&self, presented: &[u8]) -> bool {
        if presented.len() != LEASE_TOKEN_BYTES {
            return false;
        }
        let digest = wavesplat_net::digest::sha256(presented);
        let diff = self
            .digest
            .iter()
            .zip(&digest)
            .fold(0u8, |d, (a, b)| d | (a ^ b));
        std::hint::black_box(diff) == 0
    }
}

impl PartialEq for LeaseToken {
    fn eq(&self, other: &LeaseToken) -> bool {
        self.digest == other.digest
    }
}

impl Eq for LeaseToken {}

impl std::fmt::Debug for LeaseToken {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("LeaseToken(..)")
    }
}

impl Serialize for LeaseToken {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(&wavesplat_net::digest::hex(&self.digest))
    }
}

impl<'de> Deserialize<'de> for LeaseToken {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<LeaseToken, D::Error> {
        let s = String::deserialize(d)?;
        wavesplat_net::digest::unhex(&s)
            .and_then(|b| LeaseToken::from_stored(&b))
            .ok_or_else(|| {
                serde::de::Error::custom(format!(
                    "a stored lease token is {LEASE_TOKEN_DIGEST_BYTES} bytes (its SHA-256) \
                     or {LEASE_TOKEN_BYTES} in hex"
                ))
            })
    }
}

/// Where a job stands.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum JobState {
    /// Waiting for a worker, not before `not_before_ms` (retry backoff).
    Queued {
        /// Unix ms.
        not_before_ms: u64,
    },
    /// Leased by a worker.
    Running {
        /// Worker identity.
        worker: String,
        /// Attempt number of the lease.
        attempt: u32,
        /// Lease expiry, unix ms.
        lease_expires_ms: u64,
        /// When the attempt started, unix ms.
        started_ms: u64,
        /// Progress 0..=1.
        progress: f32,
        /// Current stage.
        stage: String,
        /// The lease's secret, which the holder presents on every RPC acting on it (`None` in
        /// a lease stored before tokens: no worker can present it, so it runs out and the job
        /// runs again).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        lease_token: Option<LeaseToken>,
    },
    /// Delivered.
    Done {
        /// Where it went.
        delivery: Delivery,
        /// Wall time of the successful attempt.
        run_ms: u64,
        /// The worker that held the successful attempt (empty in jobs stored before it was
        /// recorded).
        #[serde(default)]
        worker: String,
    },
    /// Gave up.
    Failed(Failure),
    /// Cancelled by a user.
    Cancelled,
}

impl JobState {
    /// Short name: queued, running, done, failed, cancelled.
    pub fn name(&self) -> &'static str {
        match self {
            JobState::Queued { .. } => "queued",
            JobState::Running { .. } => "running",
            JobState::Done { .. } => "done",
            JobState::Failed(_) => "failed",
            JobState::Cancelled => "cancelled",
        }
    }

    /// The token of a running lease (`None` when not running, or for a lease stored before
    /// tokens).
    pub fn lease_token(&self) -> Option<&LeaseToken> {
        match self {
            JobState::Running { lease_token, .. } => lease_token.as_ref(),
            _ => None,
        }
    }

    /// Done, failed or cancelled.
    pub fn is_terminal(&self) -> bool {
        matches!(
            self,
            JobState::Done { .. } | JobState::Failed(_) | JobState::Cancelled
        )
    }
}

/// A job and its history.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Job {
    /// Id.
    pub id: JobId,
    /// What to do.
    pub spec: JobSpec,
    /// Where it stands.
    pub state: JobState,
    /// Attempts started (leases granted) since submission; the current lease's attempt
    /// number. Never reset, so a lease's (job, attempt) names one lease however often the job
    /// is retried.
    pub attempts: u32,
    /// `attempts` when the job was last retried: the retry budget counts only the attempts
    /// after it.
    #[serde(default)]
    pub retried_at: u32,
    /// For a part of a bricked job: the attempt of its parent that last asked for it (added
    /// it, or polled it). A part that ended before the parent's running attempt asked for it
    /// runs again when that attempt asks, if its work is needed; one that ends after stays as
    /// it ended. Attempt numbers, not times: orchestrators sharing a database need not agree
    /// on the clock. 0 for other jobs, and in parts stored before it was recorded.
    #[serde(default)]
    pub asked_by_attempt: u32,
    /// The last failure of an attempt (kept while the job is retried).
    pub last_failure: Option<Failure>,
    /// Unix ms.
    pub created_ms: u64,
    /// Unix ms.
    pub updated_ms: u64,
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A token matches only its own secret, is stored as the secret's SHA-256 in hex and back
    /// (the secret itself never stored), and is never shown.
    #[test]
    fn a_lease_token_matches_only_itself_and_is_stored_as_its_digest() {
        let secret = [0x5a; LEASE_TOKEN_BYTES];
        let t = LeaseToken::from_secret(secret);
        assert_eq!(t.secret(), Some(&secret));
        assert!(t.matches(&secret));
        let mut other = secret;
        other[0] ^= 0x80;
        assert!(!t.matches(&other));
        assert!(!t.matches(&[]));
        assert!(!t.matches(&[0x5a; LEASE_TOKEN_BYTES + 1]));
        // Presenting the stored digest is no use.
        assert!(!t.matches(t.stored()));
        let json = serde_json::to_string(&t).unwrap();
        let digest = wavesplat_net::digest::hex(&wavesplat_net::digest::sha256(&secret));
        assert_eq!(json, format!("\"{digest}\""));
        assert!(!json.contains(&"5a".repeat(4)), "{json}");
        let back = serde_json::from_str::<LeaseToken>(&json).unwrap();
        assert_eq!(back, t);
        assert_eq!(back.secret(), None, "read back, the secret is not known");
        assert!(back.matches(&secret) && !back.matches(&other));
        // A store written before digests kept the secret: it still matches, and is written
        // back as its digest.
        let legacy: LeaseToken =
            serde_json::from_str(&format!("\"{}\"", "5a".repeat(LEASE_TOKEN_BYTES))).unwrap();
        assert!(legacy.matches(&secret) && !legacy.matches(&other));
        assert_eq!(serde_json::to_string(&legacy).unwrap(), json);
        assert!(serde_json::from_str::<LeaseToken>("\"5a5a\"").is_err());
        assert_eq!(LeaseToken::from_stored(&[0; 20]), None);
        assert_eq!(format!("{t:?}"), "LeaseToken(..)");
        // A running lease stored before tokens has none.
        let old = r#"{"Running":{"worker":"w","attempt":1,"lease_expires_ms":5,"started_ms":1,"progress":0.0,"stage":"s"}}"#;
        let state: JobState = serde_json::from_str(old).unwrap();
        assert_eq!(state.lease_token(), None);
    }
}
