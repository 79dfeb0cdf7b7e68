//! Volume readers for what hospitals and labs store: DICOM (a series directory, one file per
//! slice, or multi-frame files; [`dicom`]), NRRD (attached `.nrrd` and detached `.nhdr`
//! headers; [`nrrd`]), MetaImage (`.mha`, `.mhd` + data file; [`metaimage`]), NIfTI-1 (`.nii`,
//! `.nii.gz`, and `.hdr` + `.img` pairs, which read Analyze 7.5 too; [`nifti`]) and raw files
//! described by a [`RawSpec`] ([`raw`]; headerless, or after a header of a known size), TIFF
//! stacks and Zarr arrays (v2, v3 and OME-Zarr images; [`zarr`]). Every
//! reader keeps the voxel spacing and, where the format says, the grid's placement in patient
//! space (origin and axis directions, converted to DICOM's LPS frame) on the [`Volume`];
//! values keep their units (rescaled DICOM CT is in HU).
//!
//! A volume's files are first gathered into [`SourceFiles`] (the bytes of every file the
//! volume is made of, by name), then decoded from memory; the same bytes can be hashed,
//! uploaded as one [`SourceFiles::to_bytes`] blob and decoded elsewhere
//! ([`SourceFiles::from_bytes`], [`decode_source`]), so a worker decodes exactly what it
//! verified. Everything read is untrusted: sizes use checked arithmetic and are validated
//! against [`MAX_VOXELS`] and the bytes present before anything large is allocated, and every
//! failure is a typed [`ReadError`] naming the file and the reason. [`read_volume`] is the front
//! door for a path.

pub mod dicom;
pub mod metaimage;
pub mod nifti;
pub mod nrrd;
pub mod raw;
pub mod region;
mod spool;
pub mod steps;
mod text;
pub(crate) mod tiff_stack;
pub mod unpack;
pub mod zarr;

use std::io::{self, Read};
use std::path::{Path, PathBuf};

use thiserror::Error;
use wavesplat_codec::volume::{checked_voxels, Volume, VolumeError, MAX_VOXELS};

pub use nifti::{is_nifti_path, read_nifti};
pub use raw::{decode_raw, read_raw, Endian, RawDtype, RawSpec};
pub use unpack::{unpack_bundle, UnpackedBundle};

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
    /// spacing or placement).
    #[error(transparent)]
    Volume(#[from] VolumeError),
    /// The decoded samples of a file do not form a valid volume.
    // Not a `source`: the message says it, and an error chain would say it twice.
    #[error("{}: {problem}", path.display())]
    InvalidVolume {
        /// The file.
        path: PathBuf,
        /// What was wrong.
        problem: VolumeError,
    },
    /// A raw file (or buffer) does not have exactly the size its description requires.
    #[error(
        "{}raw data is {actual} bytes, but {}dims {dims:?}{} × {channels} channel(s) × {bytes_per_sample} byte(s) ({dtype}) need exactly {expected} bytes",
        display_origin(path.as_deref()),
        display_header_bytes(*header_bytes),
        display_time_points(*time_points)
    )]
    SizeMismatch {
        /// The file, if the data came from one.
        path: Option<PathBuf>,
        /// Bytes required by the description (the header's, when it has one, and the
        /// samples').
        expected: u64,
        /// Bytes present.
        actual: u64,
        /// Bytes of the header before the samples (`--header-bytes`; 0: none).
        header_bytes: u64,
        /// The described dimensions.
        dims: [usize; 3],
        /// The described channel count.
        channels: usize,
        /// The described sample type.
        dtype: RawDtype,
        /// Bytes per sample of `dtype`.
        bytes_per_sample: u8,
        /// The described time points (1: one volume).
        time_points: usize,
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
    #[error("unknown raw sample type `{0}`, expected one of u8, i8, u16, i16, u32, i32, u64, i64, f32, f64")]
    UnknownDtype(String),
    /// An unknown byte order name.
    #[error("unknown byte order `{0}`, expected `little` (or `le`) or `big` (or `be`)")]
    UnknownEndian(String),
    /// The file is of no known format and no raw description was given.
    #[error("{} is not a DICOM, NRRD, MetaImage or NIfTI file (by name or content); to read it as a headerless raw volume give its layout with --dims and --dtype", path.display())]
    MissingRawSpec {
        /// The file.
        path: PathBuf,
    },
    /// The data file of a `.hdr` header (a NIfTI-1 pair or Analyze 7.5) is not beside it.
    #[error(
        "{}: the samples of this .hdr header are in a .img file beside it, but there is no {}",
        header.display(),
        looked_for.iter().map(|p| p.display().to_string()).collect::<Vec<_>>().join(" nor ")
    )]
    MissingPairData {
        /// The header.
        header: PathBuf,
        /// The data files looked for, in order.
        looked_for: Vec<PathBuf>,
    },
    /// The NIfTI header could not be parsed.
    #[error("{} is not a readable NIfTI-1 file: {source}", path.display())]
    Nifti {
        /// The file.
        path: PathBuf,
        /// What the `nifti` crate reported.
        #[source]
        source: ::nifti::NiftiError,
    },
    /// A header field has an invalid value.
    #[error("{}: invalid {format} header: {reason}", path.display())]
    BadHeader {
        /// The file.
        path: PathBuf,
        /// The format (`NIfTI`, `NRRD`, `MetaImage`).
        format: &'static str,
        /// Which field, its value and what was expected.
        reason: String,
    },
    /// Samples that cannot be decoded (a corrupt or truncated chunk of a Zarr array).
    #[error("{}: {format} samples cannot be decoded: {reason}", path.display())]
    Data {
        /// The file (or store).
        path: PathBuf,
        /// The format.
        format: &'static str,
        /// What failed.
        reason: String,
    },
    /// An array of several channels opened without choosing one (a Zarr array, a TIFF storing
    /// channels as planes of their own: every other source is one channel, or three of RGB
    /// read together), or a channel chosen that the source does not hold.
    #[error(
        "{}: {channels} {}, {why}: choose one from 0 to {} (`compress --channel C`)",
        path.display(),
        if *channels == 1 { "channel" } else { "channels" },
        channels.saturating_sub(1)
    )]
    Channels {
        /// The store.
        path: PathBuf,
        /// Channels it holds (1: a source without a channel axis).
        channels: u64,
        /// Where they are, or what was chosen.
        why: String,
    },
    /// The file is valid but uses a feature this reader does not support.
    #[error("{}: unsupported: {reason}", path.display())]
    Unsupported {
        /// The file.
        path: PathBuf,
        /// What is unsupported and what is.
        reason: String,
    },
    /// The file ends before all voxel data its header announces.
    #[error("{}: voxel data is truncated: the header announces {expected} bytes of voxel data after offset {offset}, but only {actual} are present", path.display())]
    Truncated {
        /// The file.
        path: PathBuf,
        /// Byte offset of the voxel data in the (decompressed) file.
        offset: u64,
        /// Bytes of voxel data required.
        expected: u64,
        /// Bytes of voxel data present.
        actual: u64,
    },
    /// A DICOM file lacks an attribute, or has one this reader cannot use.
    #[error("{}: {}{reason}", path.display(), tag.as_ref().map(|t| format!("{t}: ")).unwrap_or_default())]
    Dicom {
        /// The file.
        path: PathBuf,
        /// The attribute, as `(gggg,eeee) Name`, when one is at fault.
        tag: Option<String>,
        /// What is wrong.
        reason: String,
    },
    /// The files of a DICOM series do not form one regular volume (several series, mismatched
    /// slices, irregular spacing or gaps, a sheared grid).
    #[error("{}: {reason}", path.display())]
    Series {
        /// The series directory (or file).
        path: PathBuf,
        /// What is inconsistent, with the files and values involved.
        reason: String,
    },
    /// A region asked of a [`region::RegionReader`] is empty or reaches outside the volume.
    #[error("{}: {reason}", path.display())]
    Region {
        /// The volume's file.
        path: PathBuf,
        /// The region and the volume's dimensions.
        reason: String,
    },
    /// A time series where one volume was asked for.
    #[error(
        "{}: a time series of {points} time points, not one volume: `compress` reads it as a \
         series (every time point in one file), `--time-point N` takes one volume out",
        path.display()
    )]
    TimeSeries {
        /// The file.
        path: PathBuf,
        /// Its time points.
        points: usize,
    },
    /// A bundle of source files (see [`SourceFiles::to_bytes`]) is malformed.
    #[error("malformed source bundle: {0}")]
    Bundle(String),
}

impl ReadError {
    /// A channel chosen (`channel`) that the source at `path`, of `channels`, does not hold.
    pub(crate) fn channel_not_held(path: &Path, channels: u64, channel: usize) -> ReadError {
        ReadError::Channels {
            path: path.to_path_buf(),
            channels,
            why: format!("channel {channel} was chosen"),
        }
    }

    pub(crate) fn bad_header(path: &Path, format: &'static str, reason: impl Into<String>) -> Self {
        ReadError::BadHeader {
            path: path.to_path_buf(),
            format,
            reason: reason.into(),
        }
    }

    pub(crate) fn unsupported(path: &Path, reason: impl Into<String>) -> Self {
        ReadError::Unsupported {
            path: path.to_path_buf(),
            reason: reason.into(),
        }
    }

    pub(crate) fn io(path: &Path, source: io::Error) -> Self {
        ReadError::Io {
            path: path.to_path_buf(),
            source,
        }
    }

    pub(crate) fn volume(path: &Path, source: VolumeError) -> Self {
        ReadError::InvalidVolume {
            path: path.to_path_buf(),
            problem: source,
        }
    }
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

/// " × T time points" of a series' raw size, nothing for one volume.
fn display_time_points(t: usize) -> String {
    if t > 1 {
        format!(" × {t} time points")
    } else {
        String::new()
    }
}

/// "a N-byte header + " of a raw size with a header, nothing without.
fn display_header_bytes(n: u64) -> String {
    if n > 0 {
        format!("a {n}-byte header + ")
    } else {
        String::new()
    }
}

fn display_origin(path: Option<&Path>) -> String {
    match path {
        Some(p) => format!("{}: ", p.display()),
        None => String::new(),
    }
}

/// Every sample type the readers decode.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum SampleType {
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

impl SampleType {
    pub(crate) fn size(self) -> usize {
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
pub(crate) fn deinterleave(
    bytes: &[u8],
    sample: SampleType,
    endian: Endian,
    channels: usize,
    slope: f64,
    inter: f64,
) -> Vec<Vec<f32>> {
    use rayon::prelude::*;
    let size = sample.size();
    let voxel_bytes = size * channels;
    let identity = slope == 1.0 && inter == 0.0;
    (0..channels)
        .map(|c| {
            bytes
                .par_chunks_exact(voxel_bytes)
                .map(|voxel| {
                    let v = sample.decode(&voxel[c * size..(c + 1) * size], endian);
                    let v = if identity { v } else { slope * v + inter };
                    v as f32
                })
                .collect()
        })
        .collect()
}

/// Most bytes a deflate (gzip, zlib) stream can expand one input byte to.
pub(crate) const DEFLATE_MAX_RATIO: usize = 1032;

/// Reads up to `expected` bytes of a (possibly gzip-compressed) stream made of `available`
/// input bytes. The buffer reserved up front is what those bytes can legitimately decode to
/// (at most [`DEFLATE_MAX_RATIO`]× them), so a header lying about the size on a short file
/// allocates little, and a truthful one reads into an exact buffer.
pub(crate) fn read_exact_or_truncated(
    stream: &mut dyn Read,
    expected: usize,
    available: usize,
    path: &Path,
    offset: u64,
) -> Result<Vec<u8>, ReadError> {
    let mut data = Vec::new();
    let reserve = expected.min(
        available
            .saturating_mul(DEFLATE_MAX_RATIO)
            .saturating_add(64),
    );
    data.try_reserve_exact(reserve).map_err(|_| {
        ReadError::io(
            path,
            io::Error::new(
                io::ErrorKind::OutOfMemory,
                "cannot allocate the voxel buffer",
            ),
        )
    })?;
    let got = stream
        .take(expected as u64)
        .read_to_end(&mut data)
        .map_err(|e| ReadError::io(path, e))?;
    if got != expected {
        return Err(ReadError::Truncated {
            path: path.to_path_buf(),
            offset,
            expected: expected as u64,
            actual: got as u64,
        });
    }
    Ok(data)
}

/// The file formats [`read_volume`] and [`decode_source`] understand.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Format {
    /// A DICOM series (a directory of slices) or multi-frame file.
    Dicom,
    /// NRRD, attached (`.nrrd`) or detached (`.nhdr`) header.
    Nrrd,
    /// MetaImage, attached (`.mha`) or detached (`.mhd`) header.
    MetaImage,
    /// NIfTI-1 single file (`.nii`, `.nii.gz`), or a `.hdr` + `.img` pair (NIfTI-1 or Analyze
    /// 7.5; `.hdr.gz`, `.img.gz` too).
    Nifti,
    /// A TIFF stack: a multi-page TIFF (`.tif`, `.tiff`, BigTIFF), or a directory of TIFF files
    /// in the natural order of their names.
    Tiff,
    /// A Zarr store (a directory): an array (v2 or v3) or an OME-Zarr image group.
    Zarr,
}

impl Format {
    /// Lower-case name.
    pub fn name(self) -> &'static str {
        match self {
            Format::Dicom => "dicom",
            Format::Nrrd => "nrrd",
            Format::MetaImage => "metaimage",
            Format::Nifti => "nifti",
            Format::Tiff => "tiff",
            Format::Zarr => "zarr",
        }
    }

    /// The format a file name says (`.dcm`, `.nrrd`/`.nhdr`, `.mha`/`.mhd`, `.nii`/`.nii.gz`,
    /// `.hdr`/`.hdr.gz` (a NIfTI-1 or Analyze 7.5 pair's header), case-insensitive), if any.
    pub fn from_name(path: &Path) -> Option<Format> {
        let name = path.file_name()?.to_string_lossy().to_ascii_lowercase();
        let ext = |e: &str| name.ends_with(e);
        if ext(".nii") || ext(".nii.gz") || ext(".hdr") || ext(".hdr.gz") {
            Some(Format::Nifti)
        } else if ext(".nrrd") || ext(".nhdr") {
            Some(Format::Nrrd)
        } else if ext(".mha") || ext(".mhd") {
            Some(Format::MetaImage)
        } else if ext(".dcm") || ext(".dicom") {
            Some(Format::Dicom)
        } else if tiff_stack::is_tiff_name(&name) || tiff_stack::is_companion_name(&name) {
            Some(Format::Tiff)
        } else if ext(".zarr") || ext(".ome.zarr") {
            Some(Format::Zarr)
        } else {
            None
        }
    }

    /// The format the first bytes of a file say: the DICOM preamble (`DICM` at offset 128),
    /// the NRRD magic (`NRRD000`), a MetaImage header line (`ObjectType =`, `NDims =`), or a
    /// NIfTI-1 header (`sizeof_hdr` 348 and magic `n+1`, or a pair's `ni1`; a gzip stream is
    /// taken as NIfTI).
    pub fn sniff(head: &[u8]) -> Option<Format> {
        if dicom::has_preamble(head) {
            Some(Format::Dicom)
        } else if head.starts_with(b"NRRD000") {
            Some(Format::Nrrd)
        } else if metaimage::looks_like_header(head) {
            Some(Format::MetaImage)
        } else if head.starts_with(&[0x1f, 0x8b]) || nifti::looks_like_header(head) {
            Some(Format::Nifti)
        } else if tiff_stack::looks_like_tiff(head) {
            Some(Format::Tiff)
        } else {
            None
        }
    }
}

/// Largest number of files in one volume's sources (slices of a DICOM series).
pub const MAX_SOURCE_FILES: usize = 1 << 16;

/// The bytes of every file one volume is made of, by name: one file (NIfTI, `.nrrd`, `.mha`, a
/// multi-frame DICOM file), a header and the data files it names (`.nhdr`, `.mhd`; named as the
/// header names them; a `.hdr` and the `.img` beside it), or the files of a DICOM series
/// directory (by file name). The first file is the primary one (the header, or the first
/// slice).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SourceFiles {
    /// Where the files came from (for messages): the primary file, or the series directory.
    pub origin: PathBuf,
    /// The directory the file names are relative to (for messages).
    pub base: PathBuf,
    /// The format, when known.
    pub format: Option<Format>,
    /// (name, bytes); names are unique.
    pub files: Vec<(String, Vec<u8>)>,
}

/// Magic of a multi-file bundle ([`SourceFiles::to_bytes`]).
pub const BUNDLE_MAGIC: &[u8; 8] = b"WSPSRC1\n";

impl SourceFiles {
    /// Gathers the files of the volume at `path`: a directory is a DICOM series (every
    /// non-hidden regular file directly inside that starts with the DICOM preamble); a
    /// detached NRRD or MetaImage header brings the data file(s) it names (relative to the
    /// header's directory), a NIfTI / Analyze `.hdr` the `.img` beside it
    /// ([`nifti::pair_data_file`]), a TIFF holding a multi-file OME-TIFF's XML the dataset's
    /// other files; anything else is one file. `format` overrides detection.
    pub fn gather(path: &Path, format: Option<Format>) -> Result<SourceFiles, ReadError> {
        // The files are found as a listing finds them ([`SourceListing::list`]), so that the
        // bytes hashed by streaming a listing are the bytes gathered here.
        let listing = SourceListing::list(path, format)?;
        let files = listing
            .files
            .into_iter()
            .map(|(name, p, _)| Ok((name, read_file(&p)?)))
            .collect::<Result<_, ReadError>>()?;
        let base = if path.is_dir() {
            path.to_path_buf()
        } else {
            path.parent().unwrap_or(Path::new(".")).to_path_buf()
        };
        Ok(SourceFiles {
            origin: path.to_path_buf(),
            base,
            format: listing.format,
            files,
        })
    }

    /// A file by the name a header gives it.
    pub fn get(&self, name: &str) -> Option<&[u8]> {
        self.files
            .iter()
            .find(|(n, _)| n == name)
            .map(|(_, b)| b.as_slice())
    }

    /// The path of a named file, for messages.
    pub fn path_of(&self, name: &str) -> PathBuf {
        self.base.join(name)
    }

    /// The data files `names` (as a header of `format` names them) with their paths; one not
    /// gathered is an I/O error naming it.
    pub(crate) fn data_files(
        &self,
        names: &[String],
        format: &str,
    ) -> Result<Vec<(PathBuf, &[u8])>, ReadError> {
        names
            .iter()
            .map(|name| {
                let path = self.path_of(name);
                let bytes = self.get(name).ok_or_else(|| {
                    let why = format!("a data file named by the {format} header is missing");
                    ReadError::io(
                        &path,
                        std::io::Error::new(std::io::ErrorKind::NotFound, why),
                    )
                })?;
                Ok((path, bytes))
            })
            .collect()
    }

    /// Serialises the files for hashing and upload: a single file is its own bytes (so its
    /// hash is the file's), but for a Zarr store (a directory, whose one file may be its
    /// metadata alone when every chunk is the fill value); several files are a bundle: [`BUNDLE_MAGIC`], the format name
    /// (u8 length + bytes), the file count (u32 LE), then per file its name (u16 LE length +
    /// UTF-8) and bytes (u64 LE length + bytes), in order.
    pub fn to_bytes(&self) -> Vec<u8> {
        if is_bare(self.format, self.files.len()) {
            return self.files[0].1.clone();
        }
        let total: usize = self.files.iter().map(|(n, b)| n.len() + b.len() + 10).sum();
        let mut out = Vec::with_capacity(total + 64);
        out.extend_from_slice(BUNDLE_MAGIC);
        let f = self.format.map_or("", Format::name);
        out.push(f.len() as u8);
        out.extend_from_slice(f.as_bytes());
        out.extend_from_slice(&(self.files.len() as u32).to_le_bytes());
        for (name, bytes) in &self.files {
            out.extend_from_slice(&(name.len() as u16).to_le_bytes());
            out.extend_from_slice(name.as_bytes());
            out.extend_from_slice(&(bytes.len() as u64).to_le_bytes());
            out.extend_from_slice(bytes);
        }
        out
    }

    /// Parses [`SourceFiles::to_bytes`]: a bundle, or else one file whose format is given by
    /// `origin`'s name or else sniffed from its content. `origin` names the source in messages.
    pub fn from_bytes(bytes: Vec<u8>, origin: &Path) -> Result<SourceFiles, ReadError> {
        if !bytes.starts_with(BUNDLE_MAGIC) {
            let format = Format::from_name(origin).or_else(|| Format::sniff(&bytes));
            let name = origin
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default();
            return Ok(SourceFiles {
                origin: origin.to_path_buf(),
                base: parent_of(origin),
                format,
                files: vec![(name, bytes)],
            });
        }
        let bad = |m: &str| ReadError::Bundle(m.to_string());
        let mut r = &bytes[BUNDLE_MAGIC.len()..];
        fn take<'a>(r: &mut &'a [u8], n: usize) -> Option<&'a [u8]> {
            if r.len() < n {
                return None;
            }
            let (a, b) = r.split_at(n);
            *r = b;
            Some(a)
        }
        let flen = take(&mut r, 1).ok_or_else(|| bad("truncated format name"))?[0] as usize;
        let fname = take(&mut r, flen).ok_or_else(|| bad("truncated format name"))?;
        let format = bundle_format(fname)?;
        let count = take(&mut r, 4).ok_or_else(|| bad("truncated file count"))?;
        let count = u32::from_le_bytes(count.try_into().expect("4 bytes")) as usize;
        // Each entry takes at least 10 bytes: bound the count by the input.
        if count == 0 || count > MAX_SOURCE_FILES || count > r.len() / 10 {
            return Err(ReadError::Bundle(format!(
                "file count {count} is not within 1..={MAX_SOURCE_FILES} or exceeds what {} bytes can hold",
                r.len()
            )));
        }
        let mut files: Vec<(String, Vec<u8>)> = Vec::with_capacity(count);
        for i in 0..count {
            let nl = take(&mut r, 2).ok_or_else(|| bad("truncated name length"))?;
            let nl = u16::from_le_bytes(nl.try_into().expect("2 bytes")) as usize;
            let name = take(&mut r, nl).ok_or_else(|| bad("truncated name"))?;
            let name = std::str::from_utf8(name)
                .map_err(|_| ReadError::Bundle(format!("file {i}: name is not UTF-8")))?
                .to_string();
            let bl = take(&mut r, 8).ok_or_else(|| bad("truncated file length"))?;
            let bl = u64::from_le_bytes(bl.try_into().expect("8 bytes"));
            if bl > r.len() as u64 {
                return Err(ReadError::Bundle(format!(
                    "file {name:?} claims {bl} bytes, {} remain",
                    r.len()
                )));
            }
            let data = take(&mut r, bl as usize).expect("checked").to_vec();
            if files.iter().any(|(n, _)| *n == name) {
                return Err(ReadError::Bundle(format!("file {name:?} appears twice")));
            }
            files.push((name, data));
        }
        if !r.is_empty() {
            return Err(ReadError::Bundle(format!(
                "{} trailing bytes after the last file",
                r.len()
            )));
        }
        // A directory's files (a series, a stack of slices) are named within it.
        let base = if matches!(format, Some(Format::Dicom | Format::Tiff | Format::Zarr)) {
            origin.to_path_buf()
        } else {
            parent_of(origin)
        };
        Ok(SourceFiles {
            origin: origin.to_path_buf(),
            base,
            format,
            files,
        })
    }
}

/// A volume's source files named and measured, not read: the files [`SourceFiles::gather`]
/// reads (it finds them through this listing), whose [`SourceListing::write_to`] streams
/// exactly the bytes of [`SourceFiles::to_bytes`] one file at a time. A source larger than memory (a DICOM series of
/// thousands of slices, a detached header's data) is hashed this way without being held.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SourceListing {
    /// The format, when known (named in a bundle).
    pub format: Option<Format>,
    /// (name, path, length in bytes), the primary file first; names are unique.
    pub files: Vec<(String, PathBuf, u64)>,
}

/// How much of a primary file [`SourceListing::list`] reads to find the data files it names:
/// as much as the region reader reads of a text header ([`text::TEXT_HEADER_WINDOW`]), so that
/// both find the same names (a header's lines start within [`text::MAX_TEXT_HEADER`] and are
/// at most that long; a list of file names after a MetaImage header ends within it).
const LISTING_HEAD: u64 = text::TEXT_HEADER_WINDOW;

impl SourceListing {
    /// Lists the files of the volume at `path` as [`SourceFiles::gather`] would gather them
    /// (the same detection, the same order), reading only a DICOM file's preamble and at most
    /// the first MiB of a primary file (of a TIFF, its page directories and first description,
    /// and an OME companion file whole, up to 64 MiB: a multi-file OME-TIFF's XML names its
    /// other files).
    pub fn list(path: &Path, format: Option<Format>) -> Result<SourceListing, ReadError> {
        let meta = std::fs::metadata(path).map_err(|e| ReadError::io(path, e))?;
        let len_of = |p: &Path| {
            std::fs::metadata(p)
                .map(|m| m.len())
                .map_err(|e| ReadError::io(p, e))
        };
        if meta.is_dir() {
            // A Zarr store, a DICOM series, else a stack of TIFF files.
            let (format, found) = if zarr::is_store(path) || format == Some(Format::Zarr) {
                (Format::Zarr, zarr::store_files(path)?)
            } else {
                match dicom::series_files(path) {
                    Ok(files) => (Format::Dicom, files),
                    Err(no_dicom) => match tiff_stack::stack_files(path)? {
                        tiffs if tiffs.is_empty() => return Err(no_dicom),
                        tiffs => (Format::Tiff, tiffs),
                    },
                }
            };
            let files = found
                .into_iter()
                .map(|(name, p)| {
                    let len = len_of(&p)?;
                    Ok((name, p, len))
                })
                .collect::<Result<_, ReadError>>()?;
            return Ok(SourceListing {
                format: Some(format),
                files,
            });
        }
        let mut head = Vec::new();
        std::fs::File::open(path)
            .and_then(|f| f.take(LISTING_HEAD).read_to_end(&mut head))
            .map_err(|e| ReadError::io(path, e))?;
        let format = format
            .or_else(|| Format::from_name(path))
            .or_else(|| Format::sniff(&head));
        let name = path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        let mut files = vec![(name, path.to_path_buf(), meta.len())];
        let companions = match format {
            Some(Format::Nrrd) => nrrd::data_files(path, &head)?,
            Some(Format::MetaImage) => metaimage::data_files(path, &head)?,
            Some(Format::Nifti) if nifti::is_pair_header_path(path) => {
                let data = nifti::pair_data_file(path)?;
                vec![data
                    .file_name()
                    .map(|n| n.to_string_lossy().into_owned())
                    .unwrap_or_default()]
            }
            // The other files of a multi-file OME-TIFF whose XML this file holds (a file whose
            // description is not read lists alone: the reader says why).
            Some(Format::Tiff) => match tiff_stack::dataset(path) {
                Ok(TiffDataset::Holds(parts)) => parts
                    .iter()
                    .filter_map(|p| p.file_name())
                    .map(|n| n.to_string_lossy().into_owned())
                    .collect(),
                _ => Vec::new(),
            },
            _ => Vec::new(),
        };
        let dir = path.parent().unwrap_or(Path::new("."));
        for c in companions {
            if files.iter().any(|(n, _, _)| *n == c) {
                continue;
            }
            let p = dir.join(&c);
            let len = len_of(&p)?;
            files.push((c, p, len));
        }
        Ok(SourceListing { format, files })
    }

    /// The length of [`SourceListing::write_to`]'s bytes.
    pub fn byte_len(&self) -> u64 {
        match self.files.as_slice() {
            [(_, _, len)] if is_bare(self.format, 1) => *len,
            files => {
                let f = self.format.map_or(0, |f| f.name().len() as u64);
                BUNDLE_MAGIC.len() as u64
                    + 1
                    + f
                    + 4
                    + files
                        .iter()
                        .map(|(n, _, len)| 2 + n.len() as u64 + 8 + len)
                        .sum::<u64>()
            }
        }
    }

    /// Writes the bytes [`SourceFiles::to_bytes`] makes of these files, reading one file at a
    /// time in pieces. A file whose length is no longer the listed one is refused: the bytes
    /// written so far would describe another source.
    pub fn write_to(&self, out: &mut dyn io::Write) -> Result<(), ReadError> {
        let copy = |out: &mut dyn io::Write, p: &Path, len: u64| -> Result<(), ReadError> {
            let f = std::fs::File::open(p).map_err(|e| ReadError::io(p, e))?;
            let copied = io::copy(&mut f.take(len + 1), out).map_err(|e| ReadError::io(p, e))?;
            if copied != len {
                return Err(ReadError::io(
                    p,
                    io::Error::other(format!(
                        "changed while being read: {copied} bytes or more, listed {len}"
                    )),
                ));
            }
            Ok(())
        };
        let written = |e: io::Error| ReadError::io(Path::new("(output)"), e);
        if let ([(_, p, len)], true) = (self.files.as_slice(), is_bare(self.format, 1)) {
            return copy(out, p, *len);
        }
        let f = self.format.map_or("", Format::name);
        let mut head = Vec::with_capacity(BUNDLE_MAGIC.len() + 5 + f.len());
        head.extend_from_slice(BUNDLE_MAGIC);
        head.push(f.len() as u8);
        head.extend_from_slice(f.as_bytes());
        head.extend_from_slice(&(self.files.len() as u32).to_le_bytes());
        out.write_all(&head).map_err(written)?;
        for (name, p, len) in &self.files {
            let mut entry = Vec::with_capacity(name.len() + 10);
            entry.extend_from_slice(&(name.len() as u16).to_le_bytes());
            entry.extend_from_slice(name.as_bytes());
            entry.extend_from_slice(&len.to_le_bytes());
            out.write_all(&entry).map_err(written)?;
            copy(out, p, *len)?;
        }
        Ok(())
    }
}

/// Whether a source of `files` files in `format` travels as its one file's own bytes rather
/// than as a bundle ([`SourceFiles::to_bytes`], [`SourceListing::write_to`]): one file, but for
/// a Zarr store (a directory, whose one file may be its metadata alone).
fn is_bare(format: Option<Format>, files: usize) -> bool {
    files == 1 && format != Some(Format::Zarr)
}

/// The format a bundle names ([`Format::name`]; empty: none).
pub(crate) fn bundle_format(name: &[u8]) -> Result<Option<Format>, ReadError> {
    Ok(match name {
        b"" => None,
        b"dicom" => Some(Format::Dicom),
        b"nrrd" => Some(Format::Nrrd),
        b"metaimage" => Some(Format::MetaImage),
        b"nifti" => Some(Format::Nifti),
        b"tiff" => Some(Format::Tiff),
        b"zarr" => Some(Format::Zarr),
        _ => {
            return Err(ReadError::Bundle(format!(
                "unknown format name {:?}",
                String::from_utf8_lossy(name)
            )))
        }
    })
}

fn parent_of(p: &Path) -> PathBuf {
    p.parent().map(Path::to_path_buf).unwrap_or_default()
}

/// Reads a whole file, reserving its length first (so a file too large for memory is an
/// error, not an abort).
pub(crate) fn read_file(path: &Path) -> Result<Vec<u8>, ReadError> {
    let mut f = std::fs::File::open(path).map_err(|e| ReadError::io(path, e))?;
    let len = f.metadata().map_err(|e| ReadError::io(path, e))?.len();
    let mut bytes = Vec::new();
    bytes
        .try_reserve_exact(usize::try_from(len).unwrap_or(usize::MAX))
        .map_err(|_| {
            ReadError::io(
                path,
                io::Error::new(
                    io::ErrorKind::OutOfMemory,
                    format!("cannot allocate {len} bytes"),
                ),
            )
        })?;
    f.read_to_end(&mut bytes)
        .map_err(|e| ReadError::io(path, e))?;
    Ok(bytes)
}

/// The samples of a stream cut into pieces, one per data file: each file's piece as `piece_of`
/// takes it from the file's bytes, joined in order (one piece: as `piece_of` gives it).
pub(crate) fn join_pieces<'a>(
    pieces: &[(PathBuf, &'a [u8])],
    mut piece_of: impl FnMut(&Path, &'a [u8]) -> Result<std::borrow::Cow<'a, [u8]>, ReadError>,
) -> Result<std::borrow::Cow<'a, [u8]>, ReadError> {
    if let [(path, data)] = pieces {
        return piece_of(path, data);
    }
    let mut joined = Vec::new();
    for (path, data) in pieces {
        joined.extend_from_slice(&piece_of(path, data)?);
    }
    Ok(std::borrow::Cow::Owned(joined))
}

/// The byte of the sample of `channel` at voxel `at` in a stream of samples x fastest,
/// `channels` interleaved, `size` bytes each, of a volume `nx` × `ny` wide.
pub(crate) fn sample_byte(
    at: [usize; 3],
    channel: usize,
    [nx, ny]: [usize; 2],
    channels: usize,
    size: usize,
) -> u128 {
    let voxel = (at[2] as u128 * ny as u128 + at[1] as u128) * nx as u128 + at[0] as u128;
    (voxel * channels as u128 + channel as u128) * size as u128
}

/// `e` naming, for a non-finite sample, the data file that holds it, where the samples (x
/// fastest, `channels` interleaved, `size` bytes each, of a volume `nx` × `ny` wide) are cut
/// into `pieces` of `piece` bytes each; any other error as it is.
pub(crate) fn in_piece(
    e: ReadError,
    pieces: &[(PathBuf, &[u8])],
    piece: usize,
    [nx, ny]: [usize; 2],
    channels: usize,
    size: usize,
) -> ReadError {
    match e {
        ReadError::InvalidVolume {
            problem:
                problem @ VolumeError::NonFinite {
                    channel, x, y, z, ..
                },
            path,
        } => {
            let byte = sample_byte([x, y, z], channel, [nx, ny], channels, size);
            let file = usize::try_from(byte / piece.max(1) as u128).unwrap_or(usize::MAX);
            ReadError::InvalidVolume {
                path: pieces.get(file).map_or(path, |(p, _)| p.clone()),
                problem,
            }
        }
        e => e,
    }
}

/// Decodes a volume from its gathered files, by their format (or, for an unknown format, as
/// raw samples described by `raw`).
pub fn decode_source(src: &SourceFiles, raw: Option<&RawSpec>) -> Result<Volume, ReadError> {
    match src.format {
        Some(Format::Dicom) => dicom::decode(src),
        Some(Format::Nrrd) => nrrd::decode(src),
        Some(Format::MetaImage) => metaimage::decode(src),
        Some(Format::Tiff) => tiff_stack::decode(src),
        Some(Format::Zarr) => zarr::decode(src, None),
        Some(Format::Nifti) => match src.files.as_slice() {
            [(_, bytes)] => nifti::decode_nifti(&src.origin, bytes),
            // A `.hdr` and its `.img`.
            [(_, header), (data, bytes)] => {
                nifti::decode_nifti_pair(&src.origin, header, &src.path_of(data), bytes)
            }
            files => Err(ReadError::Bundle(format!(
                "a NIfTI source is one file or a .hdr and its .img, not {} files",
                files.len()
            ))),
        },
        None => match (raw, src.files.as_slice()) {
            (Some(spec), [(_, bytes)]) => decode_raw(bytes, spec).map_err(|mut e| {
                // Name the file in a size mismatch that names none.
                if let ReadError::SizeMismatch { path, .. } = &mut e {
                    path.get_or_insert_with(|| src.origin.clone());
                }
                e
            }),
            _ => Err(ReadError::MissingRawSpec {
                path: src.origin.clone(),
            }),
        },
    }
}

/// [`decode_source`] with a channel chosen: of a Zarr array with a channel axis, or of a TIFF
/// storing channels as planes of their own, the one read; of any other source, one of its
/// channels (of RGB, 0 to 2) kept as a volume of one channel.
/// `None` reads the source as [`decode_source`] does.
pub fn decode_source_channel(
    src: &SourceFiles,
    raw: Option<&RawSpec>,
    channel: Option<usize>,
) -> Result<Volume, ReadError> {
    match src.format {
        Some(Format::Zarr) => zarr::decode(src, channel),
        Some(Format::Tiff) => match tiff_stack::decode_channel(src, channel)? {
            (v, true) => Ok(v),
            (v, false) => keep_channel(v, channel, &src.origin),
        },
        _ => keep_channel(decode_source(src, raw)?, channel, &src.origin),
    }
}

/// Which of the `channels` a source reads together a choice of `channel` keeps: `None` where
/// all are (none chosen, or the source has one), refused where it lacks the one chosen.
pub(crate) fn channel_to_keep(
    path: &Path,
    channels: usize,
    channel: Option<usize>,
) -> Result<Option<usize>, ReadError> {
    match channel {
        Some(c) if c >= channels => Err(ReadError::channel_not_held(path, channels as u64, c)),
        Some(c) if channels > 1 => Ok(Some(c)),
        _ => Ok(None),
    }
}

/// Volume `v` (read from `path`) with only channel `channel` kept, when one is chosen.
pub fn keep_channel(v: Volume, channel: Option<usize>, path: &Path) -> Result<Volume, ReadError> {
    let Some(c) = channel_to_keep(path, v.channel_count(), channel)? else {
        return Ok(v);
    };
    let (dims, spacing, placement) = (v.dims(), v.spacing(), v.placement().copied());
    let kept = v.into_channels().swap_remove(c);
    let one = Volume::new(dims, spacing, vec![kept]).map_err(|e| ReadError::volume(path, e))?;
    match placement {
        Some(p) => one
            .with_placement(p)
            .map_err(|e| ReadError::volume(path, e)),
        None => Ok(one),
    }
}

/// Reads a volume from a path: a DICOM series directory, a DICOM, NRRD, MetaImage or NIfTI
/// file (by extension, else by content; a `.hdr` reads the `.img` beside it), or else a raw
/// file described by `raw`. A `raw` spec given for a file of a known format is ignored (the
/// header describes the data). The `.img` of a pair, given alone and without `raw`, is
/// refused naming its header.
pub fn read_volume(path: &Path, raw: Option<&RawSpec>) -> Result<Volume, ReadError> {
    read_volume_channel(path, raw, None)
}

/// [`read_volume`] with a channel chosen, as [`decode_source_channel`] chooses it.
pub fn read_volume_channel(
    path: &Path,
    raw: Option<&RawSpec>,
    channel: Option<usize>,
) -> Result<Volume, ReadError> {
    let meta = std::fs::metadata(path).map_err(|e| ReadError::io(path, e))?;
    if meta.is_file() && Format::from_name(path).is_none() {
        if let Some(spec) = raw {
            // Raw data is never sniffed: its first bytes could look like anything.
            return keep_channel(read_raw(path, spec)?, channel, path);
        }
        if let Some(header) = nifti::pair_header_of(path) {
            return Err(nifti::pair_data_read_alone(path, &header));
        }
    }
    let src = SourceFiles::gather(path, None)?;
    decode_source_channel(&src, raw, channel)
}

/// Whether the directory `path` is a TIFF stack: it holds TIFF files and no DICOM file (a
/// DICOM series beside a stray `.tif` preview stays a series).
pub(crate) fn is_tiff_directory(path: &Path) -> Result<bool, ReadError> {
    Ok(dicom::series_files(path).is_err() && !tiff_stack::stack_files(path)?.is_empty())
}

/// The full-resolution pages of the TIFF file at `path` (an archive scan takes a directory of
/// single-page TIFFs as one stack, and a multi-page TIFF as a volume of its own) and the
/// channels it stores as planes of their own (1: none; an ImageJ hyperstack's, an OME-TIFF's
/// `SizeC` over grey pages), each a volume a channel chosen reads; of a multi-file OME-TIFF
/// whose XML the file holds, the planes of all its files. A file whose channel planes do not
/// add up is refused, as the reader refuses it.
pub fn tiff_pages_and_channels(path: &Path) -> Result<(usize, usize), ReadError> {
    tiff_stack::pages_and_channels(path)
}

/// A TIFF file's place in a multi-file OME-TIFF (one acquisition over several files, read
/// from the file holding its XML and first plane).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum TiffDataset {
    /// A file of its own.
    Alone,
    /// It holds a dataset's XML and first plane; the dataset's other files, beside it.
    Holds(Vec<PathBuf>),
    /// A part (its planes placed by the XML of another file, or its own XML in another:
    /// `BinaryOnly`); the file the dataset is read from.
    PartOf(PathBuf),
}

/// The place of the TIFF file at `path` in a multi-file OME-TIFF (its first page's description
/// read).
pub fn tiff_dataset(path: &Path) -> Result<TiffDataset, ReadError> {
    tiff_stack::dataset(path)
}

/// Why a part of a multi-file OME-TIFF whose dataset is read from `holder` (its file name) is
/// no volume of its own, and what to read instead.
pub fn tiff_part_of_dataset(holder: &str) -> String {
    tiff_stack::part_of_dataset(holder)
}

/// How many time points the volume file at `path` holds, from its header alone (a NIfTI's
/// `dim[4]`, an NRRD's time axis (`kinds` `time` or `list`, first or last), a 4D MetaImage's
/// last size, an ImageJ hyperstack's frames, a Zarr array's time axis, a raw spec's time points);
/// 1 for every other file and for other directories (a
/// directory of time steps is [`steps::StepSeries`]'s). Errors only when the file cannot be
/// opened; a header that does not parse says 1 here and is reported by the reader.
pub fn time_points(path: &Path, raw: Option<&RawSpec>) -> Result<usize, ReadError> {
    let meta = std::fs::metadata(path).map_err(|e| ReadError::io(path, e))?;
    if meta.is_dir() && zarr::is_store(path) {
        // A Zarr array's time axis (a store that does not open says 1 here).
        return Ok(zarr::time_points(path).unwrap_or(1));
    }
    if !meta.is_file() {
        return Ok(1);
    }
    let by_name = Format::from_name(path);
    if let (None, Some(spec)) = (by_name, raw) {
        return Ok(spec.time_points.max(1));
    }
    let head = {
        let mut f = std::fs::File::open(path).map_err(|e| ReadError::io(path, e))?;
        let mut head = Vec::new();
        (&mut f)
            .take(512)
            .read_to_end(&mut head)
            .map_err(|e| ReadError::io(path, e))?;
        head
    };
    let format = by_name.or_else(|| Format::sniff(&head));
    if format == Some(Format::Tiff) {
        // An ImageJ hyperstack's frames (a file that does not parse says 1 here).
        return Ok(tiff_stack::time_points(path).unwrap_or(1));
    }
    if matches!(format, Some(Format::Nrrd | Format::MetaImage)) {
        // Its text header (up to 1 MiB): an NRRD time axis, or a 4D MetaImage's last size,
        // says the time points.
        let mut prefix = Vec::new();
        std::fs::File::open(path)
            .and_then(|f| f.take(1 << 20).read_to_end(&mut prefix))
            .map_err(|e| ReadError::io(path, e))?;
        let points = if format == Some(Format::Nrrd) {
            nrrd::series_info(path, &prefix)
                .ok()
                .flatten()
                .map(|s| s.points)
        } else {
            metaimage::series_points(path, &prefix).ok().flatten()
        };
        return Ok(points.unwrap_or(1));
    }
    if format != Some(Format::Nifti) {
        return Ok(1);
    }
    let f = std::fs::File::open(path).map_err(|e| ReadError::io(path, e))?;
    let mut stream: Box<dyn Read> = if head.starts_with(&[0x1f, 0x8b]) {
        Box::new(flate2::read::MultiGzDecoder::new(f))
    } else {
        Box::new(f)
    };
    let parsed = nifti::read_header_bytes(&mut stream, path)
        .and_then(|h| nifti::parse_header(path, &h))
        .and_then(|h| nifti::series_dims(path, &h));
    Ok(parsed.map_or(1, |(_, points)| points))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A listing streams exactly the bytes gathering makes (and says their length) for every
    /// kind of source: a DICOM series directory, detached and attached NRRD and MetaImage, a
    /// NIfTI and a raw file; a file that changes length after listing is refused by name.
    #[test]
    fn a_listing_streams_the_gathered_bytes() {
        use std::io::Write;
        use wavesplat_fixtures::{
            write_dicom_series, write_metaimage, write_nifti, write_nrrd, DicomOptions, Layout,
            NrrdEncoding,
        };
        let dir = tempfile::tempdir().unwrap();
        let head = crate::phantom::Phantom::SheppLogan.generate([20, 18, 12]);
        let whole: Vec<f32> = head.channel(0).iter().map(|x| x.round()).collect();
        let v = Volume::new(head.dims(), head.spacing(), vec![whole]).unwrap();
        let series = dir.path().join("series");
        std::fs::create_dir(&series).unwrap();
        write_dicom_series(&series, &v, &DicomOptions::default());
        // Not DICOM: left out of the series by both.
        std::fs::write(series.join("notes.txt"), b"not a slice").unwrap();
        let nifti = dir.path().join("v.nii");
        write_nifti(&nifti, v.dims(), v.channel(0));
        let raw = dir.path().join("v.f32");
        let le: Vec<u8> = v.channel(0).iter().flat_map(|x| x.to_le_bytes()).collect();
        std::fs::write(&raw, &le).unwrap();
        let mut sources = vec![series, nifti, raw];
        for detached in [true, false] {
            sources.push(write_nrrd(
                dir.path(),
                &format!("n{detached}"),
                &v,
                Layout::F32,
                NrrdEncoding::Raw,
                detached,
                "LPS",
            ));
            sources.push(write_metaimage(
                dir.path(),
                &format!("m{detached}"),
                &v,
                Layout::F32,
                false,
                detached,
            ));
        }
        // Attached headers whose files are larger than what listing reads of them (2 MiB).
        let big = crate::phantom::Phantom::SheppLogan.generate([96, 96, 64]);
        let big_nrrd = write_nrrd(
            dir.path(),
            "big",
            &big,
            Layout::F32,
            NrrdEncoding::Raw,
            false,
            "LPS",
        );
        let big_mha = write_metaimage(dir.path(), "big", &big, Layout::F32, false, false);
        for p in [&big_nrrd, &big_mha] {
            assert!(
                std::fs::metadata(p).unwrap().len() > LISTING_HEAD,
                "{}",
                p.display()
            );
        }
        sources.extend([big_nrrd, big_mha]);
        for path in &sources {
            let gathered = SourceFiles::gather(path, None).unwrap().to_bytes();
            let listing = SourceListing::list(path, None).unwrap();
            let mut streamed = Vec::new();
            listing.write_to(&mut streamed).unwrap();
            assert!(streamed == gathered, "{}", path.display());
            assert_eq!(
                listing.byte_len(),
                gathered.len() as u64,
                "{}",
                path.display()
            );
        }
        let listing = SourceListing::list(&sources[0], None).unwrap();
        assert_eq!(
            listing.files.len(),
            12,
            "one file a slice, the notes left out"
        );
        let (_, slice, _) = &listing.files[3];
        std::fs::OpenOptions::new()
            .append(true)
            .open(slice)
            .unwrap()
            .write_all(b"more")
            .unwrap();
        let e = listing.write_to(&mut Vec::new()).unwrap_err();
        let why = std::error::Error::source(&e).map(|s| s.to_string());
        assert!(e.to_string().contains(&slice.display().to_string()), "{e}");
        assert!(
            why.as_deref()
                .is_some_and(|w| w.contains("changed while being read")),
            "{why:?}"
        );
    }

    #[test]
    fn formats_by_name_and_content() {
        for (n, f) in [
            ("a.nii", Format::Nifti),
            ("a.NII.GZ", Format::Nifti),
            ("a.nrrd", Format::Nrrd),
            ("a.nhdr", Format::Nrrd),
            ("b.mha", Format::MetaImage),
            ("b.MHD", Format::MetaImage),
            ("c.dcm", Format::Dicom),
            ("p.hdr", Format::Nifti),
            ("p.HDR.gz", Format::Nifti),
        ] {
            assert_eq!(Format::from_name(Path::new(n)), Some(f), "{n}");
        }
        assert_eq!(Format::from_name(Path::new("x.raw")), None);
        // A pair's data file is not a volume by name: its header is.
        assert_eq!(Format::from_name(Path::new("p.img")), None);
        let mut pair = vec![0u8; 348];
        pair[..4].copy_from_slice(&348i32.to_le_bytes());
        pair[344..348].copy_from_slice(b"ni1\0");
        assert_eq!(Format::sniff(&pair), Some(Format::Nifti));
        // Analyze 7.5 has no magic to sniff.
        pair[344..348].copy_from_slice(&[0; 4]);
        assert_eq!(Format::sniff(&pair), None);
        let mut dicm = vec![0u8; 128];
        dicm.extend_from_slice(b"DICM\x02\x00");
        assert_eq!(Format::sniff(&dicm), Some(Format::Dicom));
        assert_eq!(
            Format::sniff(b"NRRD0004\ntype: uint8\n"),
            Some(Format::Nrrd)
        );
        assert_eq!(
            Format::sniff(b"ObjectType = Image\nNDims = 3\n"),
            Some(Format::MetaImage)
        );
        assert_eq!(
            Format::sniff(b"NDims = 3\r\nDimSize = 1 1 1\r\n"),
            Some(Format::MetaImage)
        );
        assert_eq!(Format::sniff(&[0x1f, 0x8b, 8, 0]), Some(Format::Nifti));
        assert_eq!(Format::sniff(b"hello world"), None);
        assert_eq!(Format::sniff(&[]), None);
    }

    #[test]
    fn bundles_round_trip_and_reject_garbage() {
        let src = SourceFiles {
            origin: PathBuf::from("vol.nhdr"),
            base: PathBuf::new(),
            format: Some(Format::Nrrd),
            files: vec![
                ("vol.nhdr".into(), b"NRRD0004\n".to_vec()),
                ("data/vol.raw".into(), vec![1, 2, 3]),
            ],
        };
        let bytes = src.to_bytes();
        assert!(bytes.starts_with(BUNDLE_MAGIC));
        let back = SourceFiles::from_bytes(bytes.clone(), Path::new("vol.nhdr")).unwrap();
        assert_eq!(back, src);
        // A single file is its own bytes, sniffed on the way back.
        let one = SourceFiles {
            origin: PathBuf::from("a.nrrd"),
            base: PathBuf::new(),
            format: Some(Format::Nrrd),
            files: vec![("a.nrrd".into(), b"NRRD0004\n".to_vec())],
        };
        assert_eq!(one.to_bytes(), b"NRRD0004\n");
        assert_eq!(
            SourceFiles::from_bytes(one.to_bytes(), Path::new("a.nrrd")).unwrap(),
            one
        );
        // Every truncation, and hostile counts and lengths, are errors.
        for cut in BUNDLE_MAGIC.len()..bytes.len() {
            assert!(
                SourceFiles::from_bytes(bytes[..cut].to_vec(), Path::new("x")).is_err(),
                "cut {cut}"
            );
        }
        let mut huge = BUNDLE_MAGIC.to_vec();
        huge.extend_from_slice(&[0, 0xff, 0xff, 0xff, 0xff]);
        huge.extend_from_slice(&[0u8; 64]);
        assert!(matches!(
            SourceFiles::from_bytes(huge, Path::new("x")),
            Err(ReadError::Bundle(_))
        ));
        let mut long = BUNDLE_MAGIC.to_vec();
        long.extend_from_slice(&[0, 1, 0, 0, 0, 1, 0, b'a']);
        long.extend_from_slice(&u64::MAX.to_le_bytes());
        long.extend_from_slice(&[0u8; 16]);
        assert!(SourceFiles::from_bytes(long, Path::new("x")).is_err());
        let mut trailing = bytes.clone();
        trailing.push(0);
        assert!(SourceFiles::from_bytes(trailing, Path::new("x")).is_err());
    }

    #[test]
    fn unknown_files_need_a_raw_spec() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("mystery.bin");
        std::fs::write(&p, b"0123456789").unwrap();
        let e = read_volume(&p, None).unwrap_err();
        assert!(matches!(e, ReadError::MissingRawSpec { .. }), "{e}");
        assert!(e.to_string().contains("--dims"), "{e}");
        let e = read_volume(&dir.path().join("nope"), None).unwrap_err();
        assert!(matches!(e, ReadError::Io { .. }), "{e}");
    }
}
