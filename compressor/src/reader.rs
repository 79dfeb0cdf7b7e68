//! Volume readers: headerless raw files (`u8`, `u16`, `i16`, `f32`, either byte order, 1 or 3
//! interleaved channels, described by a [`RawSpec`]) and NIfTI-1 single files (`.nii`,
//! `.nii.gz`, header parsed with the `nifti` crate, samples decoded here). Everything read is
//! treated as untrusted: sizes use checked arithmetic and are validated against
//! [`MAX_VOXELS`] before anything large is allocated, the
//! input is never trusted to be as long as its header claims, and every failure is a typed
//! [`ReadError`] whose message states the bad value and what was expected. [`read_volume`] is the
//! front door: it dispatches on the file extension.

use std::fmt;
use std::fs::File;
use std::io::{self, BufReader, Read};
use std::path::{Path, PathBuf};

use thiserror::Error;
use wavesplat_codec::volume::{checked_voxels, Volume, VolumeError, MAX_VOXELS};

/// Errors from reading a volume.
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum ReadError {
    /// The file could not be opened or read.
    #[error("cannot read {}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        #[source]
        source: io::Error,
    },
    /// The decoded samples do not form a valid volume (e.g. NaN or Inf in float data, or bad
    /// spacing).
    #[error(transparent)]
    Volume(#[from] VolumeError),
    /// A raw file (or buffer) does not have exactly the size its description requires.
    #[error(
        "{}raw data is {actual} bytes, but dims {dims:?} × {channels} channel(s) × {bytes_per_sample} byte(s) ({dtype}) need exactly {expected} bytes",
        display_origin(path.as_deref())
    )]
    SizeMismatch {
        /// The file, if the data came from one.
        path: Option<PathBuf>,
        /// Bytes required by the description.
        expected: u64,
        /// Bytes present.
        actual: u64,
        /// The described dimensions.
        dims: [usize; 3],
        /// The described channel count.
        channels: usize,
        /// The described sample type.
        dtype: RawDtype,
        /// Bytes per sample of `dtype`.
        bytes_per_sample: usize,
    },
    /// The byte count of the described volume does not fit in memory addressing.
    #[error("a volume of {dims:?} voxels × {channels} channel(s) × {bytes_per_sample} byte(s) is too large to address")]
    TooLarge {
        /// The described dimensions.
        dims: [usize; 3],
        /// The described channel count.
        channels: usize,
        /// Bytes per sample.
        bytes_per_sample: usize,
    },
    /// Raw volumes have 1 (intensity) or 3 (interleaved RGB) channels.
    #[error("a raw volume has 1 (intensity) or 3 (interleaved RGB) channels, got {0}")]
    ChannelCount(usize),
    /// An unknown raw sample type name.
    #[error("unknown raw sample type `{0}`, expected one of u8, u16, i16, f32")]
    UnknownDtype(String),
    /// An unknown byte order name.
    #[error("unknown byte order `{0}`, expected `little` (or `le`) or `big` (or `be`)")]
    UnknownEndian(String),
    /// The file is not NIfTI and no raw description was given.
    #[error("{} is not a NIfTI file (.nii or .nii.gz); to read it as a headerless raw volume give its layout with --dims and --dtype", path.display())]
    MissingRawSpec {
        /// The file.
        path: PathBuf,
    },
    /// The NIfTI header could not be parsed.
    #[error("{} is not a readable NIfTI-1 file: {source}", path.display())]
    Nifti {
        /// The file.
        path: PathBuf,
        /// What the `nifti` crate reported.
        #[source]
        source: nifti::NiftiError,
    },
    /// A NIfTI header field has an invalid value.
    #[error("{}: invalid NIfTI header: {reason}", path.display())]
    BadHeader {
        /// The file.
        path: PathBuf,
        /// Which field, its value and what was expected.
        reason: String,
    },
    /// The file is valid but uses a feature this reader does not support.
    #[error("{}: unsupported: {reason}", path.display())]
    Unsupported {
        /// The file.
        path: PathBuf,
        /// What is unsupported and what is.
        reason: String,
    },
    /// The NIfTI file ends before all voxel data its header announces.
    #[error("{}: NIfTI data is truncated: the header announces {expected} bytes of voxel data after offset {offset}, but only {actual} are present", path.display())]
    Truncated {
        /// The file.
        path: PathBuf,
        /// Byte offset of the voxel data (`vox_offset`).
        offset: u64,
        /// Bytes of voxel data required.
        expected: u64,
        /// Bytes of voxel data present.
        actual: u64,
    },
}

/// Voxel count of `dims` validated by [`checked_voxels`], guarding against products too large
/// even for its u128 arithmetic.
fn voxel_count(dims: [usize; 3]) -> Result<usize, VolumeError> {
    let fits = dims
        .iter()
        .try_fold(1usize, |acc, d| acc.checked_mul(*d))
        .is_some();
    if fits || dims.contains(&0) {
        checked_voxels(dims)
    } else {
        Err(VolumeError::TooLarge {
            dims,
            voxels: u128::MAX,
            max: MAX_VOXELS,
        })
    }
}

fn display_origin(path: Option<&Path>) -> String {
    match path {
        Some(p) => format!("{}: ", p.display()),
        None => String::new(),
    }
}

/// Sample type of a raw volume file.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum RawDtype {
    /// Unsigned 8-bit integer.
    U8,
    /// Unsigned 16-bit integer.
    U16,
    /// Signed 16-bit integer (two's complement).
    I16,
    /// IEEE-754 32-bit float. NaN and Inf are rejected when the volume is built.
    F32,
}

impl RawDtype {
    /// Parses `u8`, `u16`, `i16` or `f32` (case-insensitive; `uint8`, `uint16`, `int16`,
    /// `float32` and `float` are accepted too).
    pub fn from_name(name: &str) -> Result<RawDtype, ReadError> {
        match name.trim().to_ascii_lowercase().as_str() {
            "u8" | "uint8" => Ok(RawDtype::U8),
            "u16" | "uint16" => Ok(RawDtype::U16),
            "i16" | "int16" => Ok(RawDtype::I16),
            "f32" | "float32" | "float" => Ok(RawDtype::F32),
            _ => Err(ReadError::UnknownDtype(name.to_string())),
        }
    }

    /// The canonical names accepted by [`RawDtype::from_name`].
    pub fn names() -> &'static [&'static str] {
        &["u8", "u16", "i16", "f32"]
    }

    /// The canonical name (`u8`, `u16`, `i16`, `f32`).
    pub fn name(self) -> &'static str {
        match self {
            RawDtype::U8 => "u8",
            RawDtype::U16 => "u16",
            RawDtype::I16 => "i16",
            RawDtype::F32 => "f32",
        }
    }

    /// Bytes per sample.
    pub fn size(self) -> usize {
        match self {
            RawDtype::U8 => 1,
            RawDtype::U16 | RawDtype::I16 => 2,
            RawDtype::F32 => 4,
        }
    }
}

impl fmt::Display for RawDtype {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// Byte order of multi-byte raw samples.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum Endian {
    /// Least significant byte first (x86, ARM; the usual case).
    #[default]
    Little,
    /// Most significant byte first.
    Big,
}

impl Endian {
    /// Parses `little`/`le` or `big`/`be` (case-insensitive).
    pub fn from_name(name: &str) -> Result<Endian, ReadError> {
        match name.trim().to_ascii_lowercase().as_str() {
            "little" | "le" | "l" => Ok(Endian::Little),
            "big" | "be" | "b" => Ok(Endian::Big),
            _ => Err(ReadError::UnknownEndian(name.to_string())),
        }
    }
}

/// Layout of a headerless raw volume: x fastest, then y, then z; with 3 channels the samples of
/// one voxel are interleaved (R, G, B).
#[derive(Debug, Clone, PartialEq)]
pub struct RawSpec {
    /// Dimensions (x, y, z).
    pub dims: [usize; 3],
    /// Sample type.
    pub dtype: RawDtype,
    /// Byte order of multi-byte samples (ignored for `u8`).
    pub endian: Endian,
    /// 1 (intensity) or 3 (RGB, interleaved per voxel).
    pub channels: usize,
    /// Voxel spacing (x, y, z); must be positive and finite.
    pub spacing: [f32; 3],
}

impl RawSpec {
    /// A single-channel, little-endian spec with unit spacing.
    pub fn new(dims: [usize; 3], dtype: RawDtype) -> RawSpec {
        RawSpec {
            dims,
            dtype,
            endian: Endian::Little,
            channels: 1,
            spacing: [1.0; 3],
        }
    }

    /// Exact byte size a file with this layout must have, validating dims and channel count.
    pub fn byte_len(&self) -> Result<usize, ReadError> {
        if self.channels != 1 && self.channels != 3 {
            return Err(ReadError::ChannelCount(self.channels));
        }
        let voxels = voxel_count(self.dims)?;
        voxels
            .checked_mul(self.channels)
            .and_then(|s| s.checked_mul(self.dtype.size()))
            .ok_or(ReadError::TooLarge {
                dims: self.dims,
                channels: self.channels,
                bytes_per_sample: self.dtype.size(),
            })
    }

    fn mismatch(&self, path: Option<&Path>, expected: usize, actual: u64) -> ReadError {
        ReadError::SizeMismatch {
            path: path.map(Path::to_path_buf),
            expected: expected as u64,
            actual,
            dims: self.dims,
            channels: self.channels,
            dtype: self.dtype,
            bytes_per_sample: self.dtype.size(),
        }
    }
}

/// Reads a headerless raw volume. The file must be exactly as large as `spec` requires; its size
/// is checked before anything is read.
pub fn read_raw(path: &Path, spec: &RawSpec) -> Result<Volume, ReadError> {
    let expected = spec.byte_len()?;
    let io_err = |source| ReadError::Io {
        path: path.to_path_buf(),
        source,
    };
    let file = File::open(path).map_err(io_err)?;
    let len = file.metadata().map_err(io_err)?.len();
    if len != expected as u64 {
        return Err(spec.mismatch(Some(path), expected, len));
    }
    let mut bytes = Vec::new();
    bytes.try_reserve_exact(expected).map_err(|_| {
        io_err(io::Error::new(
            io::ErrorKind::OutOfMemory,
            format!("cannot allocate {expected} bytes"),
        ))
    })?;
    // Read at most one byte more than expected so that a file growing under us is detected.
    let got = file
        .take(expected as u64 + 1)
        .read_to_end(&mut bytes)
        .map_err(io_err)?;
    if got != expected {
        return Err(spec.mismatch(Some(path), expected, got as u64));
    }
    decode_raw(&bytes, spec)
}

/// Decodes a headerless raw volume from memory. `bytes` must be exactly as long as `spec`
/// requires.
pub fn decode_raw(bytes: &[u8], spec: &RawSpec) -> Result<Volume, ReadError> {
    let expected = spec.byte_len()?;
    if bytes.len() != expected {
        return Err(spec.mismatch(None, expected, bytes.len() as u64));
    }
    let sample = SampleType::from(spec.dtype);
    let channels = deinterleave(bytes, sample, spec.endian, spec.channels, 1.0, 0.0);
    Ok(Volume::new(spec.dims, spec.spacing, channels)?)
}

/// Every sample type this module can decode (raw and NIfTI).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum SampleType {
    U8,
    I8,
    U16,
    I16,
    U32,
    I32,
    U64,
    I64,
    F32,
    F64,
}

impl From<RawDtype> for SampleType {
    fn from(d: RawDtype) -> Self {
        match d {
            RawDtype::U8 => SampleType::U8,
            RawDtype::U16 => SampleType::U16,
            RawDtype::I16 => SampleType::I16,
            RawDtype::F32 => SampleType::F32,
        }
    }
}

impl SampleType {
    fn size(self) -> usize {
        match self {
            SampleType::U8 | SampleType::I8 => 1,
            SampleType::U16 | SampleType::I16 => 2,
            SampleType::U32 | SampleType::I32 | SampleType::F32 => 4,
            SampleType::U64 | SampleType::I64 | SampleType::F64 => 8,
        }
    }

    /// Decodes one sample; `b` has exactly `self.size()` bytes.
    fn decode(self, b: &[u8], endian: Endian) -> f64 {
        macro_rules! num {
            ($t:ty, $n:expr) => {{
                let mut a = [0u8; $n];
                a.copy_from_slice(b);
                match endian {
                    Endian::Little => <$t>::from_le_bytes(a),
                    Endian::Big => <$t>::from_be_bytes(a),
                }
            }};
        }
        match self {
            SampleType::U8 => f64::from(b[0]),
            SampleType::I8 => f64::from(b[0] as i8),
            SampleType::U16 => f64::from(num!(u16, 2)),
            SampleType::I16 => f64::from(num!(i16, 2)),
            SampleType::U32 => f64::from(num!(u32, 4)),
            SampleType::I32 => f64::from(num!(i32, 4)),
            SampleType::U64 => num!(u64, 8) as f64,
            SampleType::I64 => num!(i64, 8) as f64,
            SampleType::F32 => f64::from(num!(f32, 4)),
            SampleType::F64 => num!(f64, 8),
        }
    }
}

/// Splits interleaved samples into planar channels, applying `slope * v + inter`. The caller has
/// checked that `bytes.len()` is a whole number of voxels.
fn deinterleave(
    bytes: &[u8],
    sample: SampleType,
    endian: Endian,
    channels: usize,
    slope: f64,
    inter: f64,
) -> Vec<Vec<f32>> {
    let size = sample.size();
    let voxel_bytes = size * channels;
    let n = bytes.len() / voxel_bytes;
    let mut out: Vec<Vec<f32>> = (0..channels).map(|_| Vec::with_capacity(n)).collect();
    let identity = slope == 1.0 && inter == 0.0;
    for voxel in bytes.chunks_exact(voxel_bytes) {
        for (c, s) in voxel.chunks_exact(size).enumerate() {
            let v = sample.decode(s, endian);
            let v = if identity { v } else { slope * v + inter };
            out[c].push(v as f32);
        }
    }
    out
}

/// Whether `path` names a NIfTI single file (`.nii` or `.nii.gz`, case-insensitive).
pub fn is_nifti_path(path: &Path) -> bool {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default();
    name.ends_with(".nii") || name.ends_with(".nii.gz")
}

/// Reads a volume, dispatching on the extension: `.nii` / `.nii.gz` are read as NIfTI-1 (a given
/// `raw` spec is then ignored, the header describes the data); anything else is read as a raw
/// volume, which requires `raw`.
pub fn read_volume(path: &Path, raw: Option<&RawSpec>) -> Result<Volume, ReadError> {
    // Say "not found" for a missing file rather than guessing at its format.
    std::fs::metadata(path).map_err(|source| ReadError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    if is_nifti_path(path) {
        read_nifti(path)
    } else {
        match raw {
            Some(spec) => read_raw(path, spec),
            None => Err(ReadError::MissingRawSpec {
                path: path.to_path_buf(),
            }),
        }
    }
}

/// Size of a NIfTI-1 header in bytes.
const NIFTI1_HEADER_BYTES: u64 = 348;
/// Largest `vox_offset` accepted (extensions beyond this are implausible).
const MAX_VOX_OFFSET: u64 = 1 << 30;

/// Reads a NIfTI-1 single file (`.nii`, or gzip-compressed: detected by content, not by name).
///
/// Scalar volumes with `dim[0]` ≤ 3, or more dimensions that are all 1 (e.g. 4D with one time
/// point), give 1 channel; `scl_slope`/`scl_inter` are applied when the slope is finite and
/// non-zero. RGB24 gives 3 channels with values 0..255 (scaling does not apply to RGB, as the
/// standard says). Integer and float types up to 64 bits are supported; complex, RGBA and
/// 128-bit types are not. Spacing comes from `pixdim[1..=3]`; non-positive or non-finite entries
/// (and axes beyond `dim[0]`) fall back to 1.0.
pub fn read_nifti(path: &Path) -> Result<Volume, ReadError> {
    let io_err = |source| ReadError::Io {
        path: path.to_path_buf(),
        source,
    };
    let bad = |reason: String| ReadError::BadHeader {
        path: path.to_path_buf(),
        reason,
    };
    let unsupported = |reason: String| ReadError::Unsupported {
        path: path.to_path_buf(),
        reason,
    };

    let mut file = BufReader::new(File::open(path).map_err(io_err)?);
    // Detect gzip by its magic bytes rather than by name.
    let mut magic = [0u8; 2];
    let gz = {
        let buf = io::BufRead::fill_buf(&mut file).map_err(io_err)?;
        if buf.len() >= 2 {
            magic.copy_from_slice(&buf[..2]);
        }
        magic == [0x1f, 0x8b]
    };
    let mut stream: Box<dyn Read> = if gz {
        Box::new(flate2::bufread::MultiGzDecoder::new(file))
    } else {
        Box::new(file)
    };

    let mut header_bytes = Vec::with_capacity(NIFTI1_HEADER_BYTES as usize);
    let _ = (&mut stream)
        .take(NIFTI1_HEADER_BYTES)
        .read_to_end(&mut header_bytes)
        .map_err(io_err)?;
    if header_bytes.len() as u64 != NIFTI1_HEADER_BYTES {
        return Err(bad(format!(
            "file holds {} bytes, a NIfTI-1 header needs {NIFTI1_HEADER_BYTES}",
            header_bytes.len()
        )));
    }
    let header =
        nifti::NiftiHeader::from_reader(&header_bytes[..]).map_err(|source| ReadError::Nifti {
            path: path.to_path_buf(),
            source,
        })?;
    if header.sizeof_hdr != NIFTI1_HEADER_BYTES as i32 {
        return Err(bad(format!(
            "sizeof_hdr is {}, expected 348 (NIfTI-2 files are not supported)",
            header.sizeof_hdr
        )));
    }
    match &header.magic {
        b"n+1\0" => {}
        b"ni1\0" => {
            return Err(unsupported(
                "this is the header of a .hdr/.img pair (magic `ni1`); only single-file .nii / .nii.gz volumes are supported".into(),
            ))
        }
        m => {
            return Err(bad(format!(
                "magic is {:?}, expected \"n+1\\0\"",
                String::from_utf8_lossy(m)
            )))
        }
    }

    // Dimensions.
    let ndim = usize::from(header.dim[0]);
    if !(1..=7).contains(&ndim) {
        return Err(bad(format!("dim[0] is {ndim}, expected 1..=7")));
    }
    let mut dims = [1usize; 3];
    for i in 1..=ndim {
        let d = usize::from(header.dim[i]);
        if d == 0 {
            return Err(bad(format!("dim[{i}] is 0, expected at least 1")));
        }
        if i <= 3 {
            dims[i - 1] = d;
        } else if d != 1 {
            return Err(unsupported(format!(
                "dim[{i}] is {d}: only 3D volumes are supported (dim[0] = {ndim}, extra dimensions must be 1); dim = {:?}",
                &header.dim[1..=ndim]
            )));
        }
    }

    // Sample type.
    let (sample, channels) = match header.datatype {
        2 => (SampleType::U8, 1),
        4 => (SampleType::I16, 1),
        8 => (SampleType::I32, 1),
        16 => (SampleType::F32, 1),
        64 => (SampleType::F64, 1),
        128 => (SampleType::U8, 3),
        256 => (SampleType::I8, 1),
        512 => (SampleType::U16, 1),
        768 => (SampleType::U32, 1),
        1024 => (SampleType::I64, 1),
        1280 => (SampleType::U64, 1),
        t @ (32 | 1536 | 1792 | 2048 | 2304) => {
            return Err(unsupported(format!(
                "datatype {t} ({}); supported are uint8/int8/(u)int16/(u)int32/(u)int64/float32/float64 and RGB24",
                match t {
                    32 => "complex64",
                    1536 => "float128",
                    1792 => "complex128",
                    2048 => "complex256",
                    _ => "RGBA32",
                }
            )))
        }
        t => {
            return Err(bad(format!(
                "datatype is {t}, not a NIfTI-1 datatype code"
            )))
        }
    };
    let bits = sample.size() * channels * 8;
    if i64::from(header.bitpix) != bits as i64 {
        return Err(bad(format!(
            "bitpix is {}, but datatype {} has {bits} bits per voxel",
            header.bitpix, header.datatype
        )));
    }
    let voxels = voxel_count(dims)?;
    let expected = voxels
        .checked_mul(sample.size() * channels)
        .ok_or(ReadError::TooLarge {
            dims,
            channels,
            bytes_per_sample: sample.size(),
        })?;

    // Voxel data offset.
    let vox_offset = header.vox_offset;
    if !vox_offset.is_finite()
        || vox_offset < NIFTI1_HEADER_BYTES as f32
        || vox_offset.fract() != 0.0
        || vox_offset > MAX_VOX_OFFSET as f32
    {
        return Err(bad(format!(
            "vox_offset is {vox_offset}, expected a whole number of bytes in 348..={MAX_VOX_OFFSET} (at least 352 for a single file)"
        )));
    }
    let vox_offset = vox_offset as u64;
    // Skip the extender and extensions.
    let skip = vox_offset - NIFTI1_HEADER_BYTES;
    let skipped = io::copy(&mut (&mut stream).take(skip), &mut io::sink()).map_err(io_err)?;
    if skipped != skip {
        return Err(ReadError::Truncated {
            path: path.to_path_buf(),
            offset: vox_offset,
            expected: expected as u64,
            actual: 0,
        });
    }

    // Voxel data: grow as data arrives, so a lying header on a short file allocates little.
    let mut data = Vec::new();
    data.try_reserve(expected.min(1 << 26)).map_err(|_| {
        io_err(io::Error::new(
            io::ErrorKind::OutOfMemory,
            "cannot allocate the voxel buffer",
        ))
    })?;
    let got = (&mut stream)
        .take(expected as u64)
        .read_to_end(&mut data)
        .map_err(io_err)?;
    if got != expected {
        return Err(ReadError::Truncated {
            path: path.to_path_buf(),
            offset: vox_offset,
            expected: expected as u64,
            actual: got as u64,
        });
    }

    let endian = match header.endianness {
        nifti::Endianness::Little => Endian::Little,
        nifti::Endianness::Big => Endian::Big,
    };
    let (slope, inter) = if channels == 1
        && header.scl_slope.is_finite()
        && header.scl_slope != 0.0
        && header.scl_inter.is_finite()
    {
        (f64::from(header.scl_slope), f64::from(header.scl_inter))
    } else {
        (1.0, 0.0)
    };
    let mut spacing = [1.0f32; 3];
    for (i, s) in spacing.iter_mut().enumerate().take(ndim.min(3)) {
        let p = header.pixdim[i + 1];
        if p.is_finite() && p > 0.0 {
            *s = p;
        }
    }
    let planar = deinterleave(&data, sample, endian, channels, slope, inter);
    drop(data);
    Ok(Volume::new(dims, spacing, planar)?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write;

    fn spec(dims: [usize; 3], dtype: RawDtype, endian: Endian, channels: usize) -> RawSpec {
        RawSpec {
            dims,
            dtype,
            endian,
            channels,
            spacing: [1.0, 2.0, 0.5],
        }
    }

    #[test]
    fn dtype_and_endian_names() {
        for n in RawDtype::names() {
            assert_eq!(RawDtype::from_name(n).unwrap().name(), *n);
        }
        assert_eq!(RawDtype::from_name("UINT16").unwrap(), RawDtype::U16);
        let e = RawDtype::from_name("u12").unwrap_err();
        assert!(e.to_string().contains("u12"), "{e}");
        assert_eq!(Endian::from_name("BE").unwrap(), Endian::Big);
        assert!(Endian::from_name("middle").is_err());
    }

    #[test]
    fn decode_every_dtype_and_endian() {
        let dims = [3, 2, 1];
        let vals: Vec<f64> = vec![0.0, 1.0, 2.0, 200.0, 255.0, 7.0];
        for endian in [Endian::Little, Endian::Big] {
            let bytes: Vec<u8> = vals.iter().map(|v| *v as u8).collect();
            let v = decode_raw(&bytes, &spec(dims, RawDtype::U8, endian, 1)).unwrap();
            assert_eq!(v.channel(0), &[0.0, 1.0, 2.0, 200.0, 255.0, 7.0]);

            let u16s: Vec<u16> = vec![0, 1, 65535, 300, 4096, 9];
            let bytes: Vec<u8> = u16s
                .iter()
                .flat_map(|v| match endian {
                    Endian::Little => v.to_le_bytes(),
                    Endian::Big => v.to_be_bytes(),
                })
                .collect();
            let v = decode_raw(&bytes, &spec(dims, RawDtype::U16, endian, 1)).unwrap();
            let want: Vec<f32> = u16s.iter().map(|v| *v as f32).collect();
            assert_eq!(v.channel(0), &want[..]);

            let i16s: Vec<i16> = vec![-32768, -1, 0, 1, 32767, -1000];
            let bytes: Vec<u8> = i16s
                .iter()
                .flat_map(|v| match endian {
                    Endian::Little => v.to_le_bytes(),
                    Endian::Big => v.to_be_bytes(),
                })
                .collect();
            let v = decode_raw(&bytes, &spec(dims, RawDtype::I16, endian, 1)).unwrap();
            let want: Vec<f32> = i16s.iter().map(|v| *v as f32).collect();
            assert_eq!(v.channel(0), &want[..]);

            let f32s: Vec<f32> = vec![-1.5, 0.0, 1e-3, 3.25, 1e30, -7.0];
            let bytes: Vec<u8> = f32s
                .iter()
                .flat_map(|v| match endian {
                    Endian::Little => v.to_le_bytes(),
                    Endian::Big => v.to_be_bytes(),
                })
                .collect();
            let v = decode_raw(&bytes, &spec(dims, RawDtype::F32, endian, 1)).unwrap();
            assert_eq!(v.channel(0), &f32s[..]);
            assert_eq!(v.spacing(), [1.0, 2.0, 0.5]);
        }
    }

    #[test]
    fn decode_interleaved_rgb_x_fastest() {
        // 2×1×2 RGB volume: voxel i has (i, 10+i, 20+i).
        let bytes: Vec<u8> = (0..4u8).flat_map(|i| [i, 10 + i, 20 + i]).collect();
        let v = decode_raw(&bytes, &spec([2, 1, 2], RawDtype::U8, Endian::Little, 3)).unwrap();
        assert_eq!(v.channel_count(), 3);
        assert_eq!(v.channel(0), &[0.0, 1.0, 2.0, 3.0]);
        assert_eq!(v.channel(1), &[10.0, 11.0, 12.0, 13.0]);
        assert_eq!(v.channel(2)[v.index(1, 0, 1)], 23.0);
    }

    #[test]
    fn size_errors_are_clear() {
        let s = spec([4, 4, 4], RawDtype::U16, Endian::Little, 1);
        let e = decode_raw(&[0u8; 100], &s).unwrap_err();
        let msg = e.to_string();
        assert!(msg.contains("128") && msg.contains("100"), "{msg}");
        assert!(matches!(
            e,
            ReadError::SizeMismatch {
                expected: 128,
                actual: 100,
                ..
            }
        ));

        // Huge dimensions must error, not overflow or allocate.
        let huge = spec(
            [usize::MAX, usize::MAX, 2],
            RawDtype::F32,
            Endian::Little,
            3,
        );
        assert!(matches!(
            decode_raw(&[], &huge),
            Err(ReadError::Volume(VolumeError::TooLarge { .. }))
        ));
        let zero = spec([0, 4, 4], RawDtype::U8, Endian::Little, 1);
        assert!(matches!(
            decode_raw(&[], &zero),
            Err(ReadError::Volume(VolumeError::ZeroDimension(_)))
        ));
        let two = spec([1, 1, 1], RawDtype::U8, Endian::Little, 2);
        assert!(matches!(
            decode_raw(&[0, 0], &two),
            Err(ReadError::ChannelCount(2))
        ));
        // NaN in float data is rejected with its position.
        let nan: Vec<u8> = [0.0f32, f32::NAN]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        let e = decode_raw(&nan, &spec([2, 1, 1], RawDtype::F32, Endian::Little, 1)).unwrap_err();
        assert!(matches!(
            e,
            ReadError::Volume(VolumeError::NonFinite { x: 1, .. })
        ));
        // Bad spacing.
        let mut s = spec([1, 1, 1], RawDtype::U8, Endian::Little, 1);
        s.spacing = [1.0, -1.0, 1.0];
        assert!(matches!(
            decode_raw(&[0], &s),
            Err(ReadError::Volume(VolumeError::Spacing(_)))
        ));
    }

    #[test]
    fn read_raw_file_and_dispatch() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("vol.raw");
        let bytes: Vec<u8> = (0..24u8).collect();
        std::fs::write(&path, &bytes).unwrap();
        let s = spec([2, 3, 4], RawDtype::U8, Endian::Little, 1);
        let v = read_raw(&path, &s).unwrap();
        assert_eq!(v.dims(), [2, 3, 4]);
        assert_eq!(v.channel(0)[v.index(1, 2, 3)], 23.0);
        assert_eq!(read_volume(&path, Some(&s)).unwrap(), v);

        let e = read_volume(&path, None).unwrap_err();
        assert!(matches!(e, ReadError::MissingRawSpec { .. }));
        assert!(e.to_string().contains("--dims"), "{e}");

        let short = spec([5, 5, 5], RawDtype::U8, Endian::Little, 1);
        let e = read_raw(&path, &short).unwrap_err();
        assert!(matches!(
            e,
            ReadError::SizeMismatch {
                expected: 125,
                actual: 24,
                ..
            }
        ));
        assert!(e.to_string().contains("vol.raw"), "{e}");

        let e = read_raw(&dir.path().join("missing.raw"), &s).unwrap_err();
        assert!(matches!(e, ReadError::Io { .. }));
        assert!(e.to_string().contains("missing.raw"), "{e}");
    }

    /// A NIfTI-1 single-file header, written by hand (little-endian unless `big`).
    fn nifti_header(
        dim: [u16; 8],
        datatype: i16,
        bitpix: i16,
        pixdim: [f32; 8],
        slope: f32,
        inter: f32,
        big: bool,
    ) -> Vec<u8> {
        let mut h = vec![0u8; 348];
        let put = |h: &mut Vec<u8>, off: usize, b: &[u8]| {
            h[off..off + b.len()].copy_from_slice(b);
        };
        macro_rules! w {
            ($h:expr, $off:expr, $v:expr) => {
                if big {
                    put($h, $off, &$v.to_be_bytes())
                } else {
                    put($h, $off, &$v.to_le_bytes())
                }
            };
        }
        w!(&mut h, 0, 348i32);
        for (i, d) in dim.iter().enumerate() {
            w!(&mut h, 40 + 2 * i, *d);
        }
        w!(&mut h, 70, datatype);
        w!(&mut h, 72, bitpix);
        for (i, p) in pixdim.iter().enumerate() {
            w!(&mut h, 76 + 4 * i, *p);
        }
        w!(&mut h, 108, 352.0f32);
        w!(&mut h, 112, slope);
        w!(&mut h, 116, inter);
        put(&mut h, 344, b"n+1\0");
        h.extend_from_slice(&[0, 0, 0, 0]); // extender: no extensions
        h
    }

    fn write_file(path: &Path, bytes: &[u8], gz: bool) {
        let f = File::create(path).unwrap();
        if gz {
            let mut enc = flate2::write::GzEncoder::new(f, flate2::Compression::fast());
            enc.write_all(bytes).unwrap();
            enc.finish().unwrap();
        } else {
            let mut f = f;
            f.write_all(bytes).unwrap();
        }
    }

    #[test]
    fn nifti_scalar_plain_and_gz() {
        let dir = tempfile::tempdir().unwrap();
        let dims = [3u16, 4, 2];
        let n = 24;
        for (gz, big) in [(false, false), (true, false), (false, true), (true, true)] {
            let mut bytes = nifti_header(
                [3, dims[0], dims[1], dims[2], 1, 1, 1, 1],
                4,
                16,
                [1.0, 0.5, 2.0, -3.0, 1.0, 0.0, 0.0, 0.0],
                2.0,
                -1.0,
                big,
            );
            for i in 0..n as i16 {
                let v = i * 10 - 50;
                bytes.extend_from_slice(&if big {
                    v.to_be_bytes()
                } else {
                    v.to_le_bytes()
                });
            }
            let name = if gz { "a.nii.gz" } else { "a.nii" };
            let path = dir.path().join(name);
            write_file(&path, &bytes, gz);
            let v = read_volume(&path, None).unwrap();
            assert_eq!(v.dims(), [3, 4, 2]);
            assert_eq!(v.channel_count(), 1);
            // Negative pixdim falls back to 1.0.
            assert_eq!(v.spacing(), [0.5, 2.0, 1.0]);
            for i in 0..n {
                let raw = (i as f32) * 10.0 - 50.0;
                assert_eq!(v.channel(0)[i], 2.0 * raw - 1.0, "voxel {i}, gz {gz}");
            }
        }
    }

    #[test]
    fn nifti_4d_single_frame_rgb_and_float() {
        let dir = tempfile::tempdir().unwrap();
        // 4D with one time point, float32, slope 0 means "no scaling".
        let mut bytes = nifti_header([4, 2, 2, 1, 1, 1, 1, 1], 16, 32, [1.0; 8], 0.0, 5.0, false);
        for v in [0.5f32, -1.0, 2.0, 3.5] {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
        let path = dir.path().join("f.nii");
        write_file(&path, &bytes, false);
        let v = read_volume(&path, None).unwrap();
        assert_eq!(v.dims(), [2, 2, 1]);
        assert_eq!(v.channel(0), &[0.5, -1.0, 2.0, 3.5]);

        // RGB24 gives three channels.
        let mut bytes = nifti_header([3, 2, 1, 1, 1, 1, 1, 1], 128, 24, [1.0; 8], 1.0, 0.0, false);
        bytes.extend_from_slice(&[255, 0, 10, 1, 2, 3]);
        let path = dir.path().join("rgb.nii.gz");
        write_file(&path, &bytes, true);
        let v = read_volume(&path, None).unwrap();
        assert_eq!(v.channel_count(), 3);
        assert_eq!(v.channel(0), &[255.0, 1.0]);
        assert_eq!(v.channel(1), &[0.0, 2.0]);
        assert_eq!(v.channel(2), &[10.0, 3.0]);
    }

    #[test]
    fn nifti_bad_input_errors_without_panicking() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("bad.nii");
        let good =
            |dim: [u16; 8], dt: i16, bp: i16| nifti_header(dim, dt, bp, [1.0; 8], 1.0, 0.0, false);

        // Real 4D.
        let mut b = good([4, 2, 2, 2, 3, 1, 1, 1], 2, 8);
        b.extend(vec![0u8; 24]);
        write_file(&path, &b, false);
        let e = read_volume(&path, None).unwrap_err();
        assert!(matches!(e, ReadError::Unsupported { .. }), "{e}");
        assert!(e.to_string().contains("dim[4] is 3"), "{e}");

        // Complex data.
        let mut b = good([3, 1, 1, 1, 1, 1, 1, 1], 32, 64);
        b.extend(vec![0u8; 8]);
        write_file(&path, &b, false);
        let e = read_volume(&path, None).unwrap_err();
        assert!(e.to_string().contains("complex64"), "{e}");

        // Truncated data.
        let mut b = good([3, 4, 4, 4, 1, 1, 1, 1], 2, 8);
        b.extend(vec![0u8; 10]);
        write_file(&path, &b, false);
        let e = read_volume(&path, None).unwrap_err();
        assert!(
            matches!(
                e,
                ReadError::Truncated {
                    expected: 64,
                    actual: 10,
                    ..
                }
            ),
            "{e}"
        );

        // A header claiming a huge volume on a tiny file.
        let mut b = good([3, 65535, 65535, 65535, 1, 1, 1, 1], 64, 64);
        b.extend(vec![0u8; 10]);
        write_file(&path, &b, false);
        assert!(matches!(
            read_volume(&path, None),
            Err(ReadError::Volume(VolumeError::TooLarge { .. }))
        ));
        let mut b = good([3, 1024, 1024, 1024, 1, 1, 1, 1], 64, 64);
        b.extend(vec![0u8; 10]);
        write_file(&path, &b, false);
        assert!(matches!(
            read_volume(&path, None),
            Err(ReadError::Truncated { actual: 10, .. })
        ));

        // bitpix inconsistent with datatype.
        let mut b = good([3, 1, 1, 1, 1, 1, 1, 1], 4, 8);
        b.extend(vec![0u8; 2]);
        write_file(&path, &b, false);
        assert!(matches!(
            read_volume(&path, None),
            Err(ReadError::BadHeader { .. })
        ));

        // Zero dimension, unknown datatype, bad vox_offset.
        let mut b = good([3, 1, 0, 1, 1, 1, 1, 1], 2, 8);
        b.extend(vec![0u8; 2]);
        write_file(&path, &b, false);
        assert!(matches!(
            read_volume(&path, None),
            Err(ReadError::BadHeader { .. })
        ));
        let mut b = good([3, 1, 1, 1, 1, 1, 1, 1], 3, 8);
        b.push(0);
        write_file(&path, &b, false);
        assert!(matches!(
            read_volume(&path, None),
            Err(ReadError::BadHeader { .. })
        ));
        let mut b = good([3, 1, 1, 1, 1, 1, 1, 1], 2, 8);
        b[108..112].copy_from_slice(&f32::NAN.to_le_bytes());
        b.push(0);
        write_file(&path, &b, false);
        assert!(matches!(
            read_volume(&path, None),
            Err(ReadError::BadHeader { .. })
        ));

        // Float NaN data.
        let mut b = good([3, 1, 1, 1, 1, 1, 1, 1], 16, 32);
        b.extend_from_slice(&f32::NAN.to_le_bytes());
        write_file(&path, &b, false);
        assert!(matches!(
            read_volume(&path, None),
            Err(ReadError::Volume(VolumeError::NonFinite { .. }))
        ));

        // Garbage, empty and short files; corrupt gzip.
        for junk in [
            &b""[..],
            &b"hello"[..],
            &[0xffu8; 400][..],
            &[0x1f, 0x8b, 1, 2, 3][..],
        ] {
            write_file(&path, junk, false);
            assert!(read_volume(&path, None).is_err());
        }
        let gz_path = dir.path().join("bad.nii.gz");
        write_file(&gz_path, &[7u8; 100], true);
        assert!(read_volume(&gz_path, None).is_err());

        // Missing file.
        assert!(matches!(
            read_volume(&dir.path().join("nope.nii"), None),
            Err(ReadError::Io { .. })
        ));
    }

    #[test]
    fn mni152_if_present() {
        let path = Path::new("/work/shared/data/mni152_t1_1mm.nii.gz");
        if !path.exists() {
            return;
        }
        let v = read_volume(path, None).unwrap();
        assert_eq!(v.dims(), [197, 233, 189]);
        assert_eq!(v.channel_count(), 1);
        let (lo, hi) = v.value_range();
        assert!(lo >= 0.0 && hi <= 255.0 && hi > lo);
    }
}
