//! NIfTI-1 (`.nii`, `.nii.gz`: header and samples in one file; `.hdr` + `.img`, either
//! gzip-compressed too: a header with magic `ni1` and its samples in the `.img` beside it, as
//! SPM and FSL's `NIFTI_PAIR` write them) and Analyze 7.5 (`.hdr` + `.img` with no NIfTI magic;
//! its orientation fields are not NIfTI's, so it has no placement): the header parsed with the
//! `nifti` crate, the samples decoded here, and the grid's placement from the `sform` (else the
//! `qform`) affine, converted from NIfTI's RAS to LPS.

use std::io::{self, Read};
use std::path::{Path, PathBuf};

use super::{deinterleave, read_exact_or_truncated, voxel_count, Endian, ReadError, SampleType};
use wavesplat_codec::volume::{Placement, Volume};

/// Whether `path` names a NIfTI single file (`.nii` or `.nii.gz`, case-insensitive).
pub fn is_nifti_path(path: &Path) -> bool {
    let name = lower_name(path);
    name.ends_with(".nii") || name.ends_with(".nii.gz")
}

/// Whether `path` names the header of a `.hdr` + `.img` pair (NIfTI-1 or Analyze 7.5): `.hdr`
/// or `.hdr.gz`, case-insensitive.
pub fn is_pair_header_path(path: &Path) -> bool {
    let name = lower_name(path);
    name.ends_with(".hdr") || name.ends_with(".hdr.gz")
}

fn lower_name(path: &Path) -> String {
    path.file_name()
        .map(|n| n.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default()
}

/// The name of `path` split at its `ext` suffix (case-insensitive; `ext` lower case, with its
/// dot): (stem, the suffix as written).
fn split_suffix(path: &Path, ext: &str) -> Option<(String, String)> {
    let name = path.file_name()?.to_string_lossy().into_owned();
    let cut = name.len().checked_sub(ext.len())?;
    (name.is_char_boundary(cut) && name[cut..].eq_ignore_ascii_case(ext))
        .then(|| (name[..cut].to_string(), name[cut..].to_string()))
}

/// The files the samples of the `.hdr` header at `path` may be in, in the order they are
/// looked for: the `.img` beside it with the same stem, compressed as the header is first
/// (`x.hdr`: `x.img`, then `x.img.gz`; `x.hdr.gz`: `x.img.gz`, then `x.img`), in the header's
/// letter case first. Empty when `path` is not named `.hdr` / `.hdr.gz`.
pub fn pair_data_candidates(path: &Path) -> Vec<PathBuf> {
    let (stem, suffix, gz) = if let Some((s, x)) = split_suffix(path, ".hdr.gz") {
        (s, x, true)
    } else if let Some((s, x)) = split_suffix(path, ".hdr") {
        (s, x, false)
    } else {
        return Vec::new();
    };
    let upper = suffix[1..4].chars().all(|c| c.is_ascii_uppercase());
    let (img, dotgz) = if upper {
        (".IMG", ".GZ")
    } else {
        (".img", ".gz")
    };
    let same = [format!("{img}{dotgz}"), img.to_string()];
    let lower = [".img.gz".to_string(), ".img".to_string()];
    let order = |pair: &[String; 2]| {
        if gz {
            [pair[0].clone(), pair[1].clone()]
        } else {
            [pair[1].clone(), pair[0].clone()]
        }
    };
    let dir = path.parent().unwrap_or(Path::new(""));
    let mut out: Vec<PathBuf> = Vec::new();
    for ext in order(&same).into_iter().chain(order(&lower)) {
        let p = dir.join(format!("{stem}{ext}"));
        if !out.contains(&p) {
            out.push(p);
        }
    }
    out
}

/// The data file of the `.hdr` header at `path`: the first of [`pair_data_candidates`] that
/// exists; none is [`ReadError::MissingPairData`], naming the files looked for.
pub fn pair_data_file(path: &Path) -> Result<PathBuf, ReadError> {
    let candidates = pair_data_candidates(path);
    if let Some(found) = candidates.iter().find(|p| p.is_file()) {
        return Ok(found.clone());
    }
    Err(ReadError::MissingPairData {
        header: path.to_path_buf(),
        looked_for: candidates.into_iter().take(2).collect(),
    })
}

/// Whether the file at `path` is the header of a NIfTI-1 or Analyze 7.5 pair: named `.hdr` or
/// `.hdr.gz`, and its first bytes (inflated when gzip-compressed) have `sizeof_hdr` 348 in
/// either byte order. Other files of that name (ENVI's text headers, Radiance HDR images) are
/// not.
pub fn is_pair_header(path: &Path) -> bool {
    if !is_pair_header_path(path) {
        return false;
    }
    let Ok(bytes) = std::fs::File::open(path).and_then(|f| {
        let mut head = Vec::new();
        f.take(4096).read_to_end(&mut head)?;
        Ok(head)
    }) else {
        return false;
    };
    let mut head = Vec::new();
    let read = inflated(&bytes).take(4).read_to_end(&mut head);
    read.is_ok() && has_header_size(&head)
}

/// The `.hdr` header beside the `.img` (or `.img.gz`) at `path`, when there is one: what to
/// read instead of the samples alone.
pub(crate) fn pair_header_of(path: &Path) -> Option<PathBuf> {
    let stem = split_suffix(path, ".img.gz")
        .or_else(|| split_suffix(path, ".img"))?
        .0;
    let dir = path.parent().unwrap_or(Path::new(""));
    [".hdr", ".hdr.gz", ".HDR", ".HDR.GZ"]
        .iter()
        .map(|e| dir.join(format!("{stem}{e}")))
        .find(|p| p.is_file())
}

/// The error for the samples of a pair read without their header (see [`pair_header_of`]).
pub(crate) fn pair_data_read_alone(path: &Path, header: &Path) -> ReadError {
    ReadError::unsupported(
        path,
        format!(
            "this is the data file of the NIfTI-1 / Analyze 7.5 pair whose header is {}: read \
             the header, which describes these samples",
            header.display()
        ),
    )
}

/// Whether `head` starts like an uncompressed NIfTI-1 header (`sizeof_hdr` = 348 in either
/// byte order and magic `n+1` (a single file) or `ni1` (a `.hdr` of a pair) at offset 344).
pub(crate) fn looks_like_header(head: &[u8]) -> bool {
    head.len() >= 348 && has_header_size(head) && matches!(&head[344..347], b"n+1" | b"ni1")
}

/// Whether `sizeof_hdr` is 348, in either byte order.
fn has_header_size(head: &[u8]) -> bool {
    head.len() >= 4 && (head[..4] == 348i32.to_le_bytes() || head[..4] == 348i32.to_be_bytes())
}

/// What a header's magic says of where its samples are.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Flavour {
    /// `n+1`: a single file (`.nii`), the samples after the header from `vox_offset` (≥ 352).
    Single,
    /// `ni1`: a `.hdr` whose samples are in the `.img` beside it, from `vox_offset` (usually 0).
    Pair,
    /// No NIfTI magic and `sizeof_hdr` 348: an Analyze 7.5 `.hdr`, its samples in the `.img`
    /// from `vox_offset`; no placement (its orientation fields are not NIfTI's) and no time
    /// unit.
    Analyze,
}

/// The flavour of the header `head` (its first 348 bytes); `None` for none (neither NIfTI magic
/// nor an Analyze header's size).
pub(crate) fn flavour(head: &[u8]) -> Option<Flavour> {
    match head.get(344..348)? {
        b"n+1\0" => Some(Flavour::Single),
        b"ni1\0" => Some(Flavour::Pair),
        _ if has_header_size(head) => Some(Flavour::Analyze),
        _ => None,
    }
}

/// Reads a NIfTI-1 single file (see [`decode_nifti`]).
pub fn read_nifti(path: &Path) -> Result<Volume, ReadError> {
    let bytes = super::read_file(path)?;
    decode_nifti(path, &bytes)
}

/// Size of a NIfTI-1 header in bytes.
pub(super) const NIFTI1_HEADER_BYTES: u64 = 348;
/// Largest `vox_offset` accepted (extensions beyond this are implausible).
const MAX_VOX_OFFSET: u64 = 1 << 30;

/// The first [`NIFTI1_HEADER_BYTES`] bytes of `stream`: the header; an error when the file
/// holds fewer.
pub(super) fn read_header_bytes(stream: &mut impl Read, path: &Path) -> Result<Vec<u8>, ReadError> {
    let mut head = Vec::with_capacity(NIFTI1_HEADER_BYTES as usize);
    stream
        .take(NIFTI1_HEADER_BYTES)
        .read_to_end(&mut head)
        .map_err(|e| ReadError::io(path, e))?;
    if head.len() as u64 != NIFTI1_HEADER_BYTES {
        return Err(ReadError::bad_header(
            path,
            "NIfTI",
            format!(
                "file holds {} bytes, a NIfTI-1 header needs {NIFTI1_HEADER_BYTES}",
                head.len()
            ),
        ));
    }
    Ok(head)
}

/// The header in `head` (from [`read_header_bytes`]) as the `nifti` crate parses it. An
/// Analyze 7.5 header (no NIfTI magic, `sizeof_hdr` 348) is parsed as a pair's (its fields up
/// to `vox_offset` and the scale factor `funused1` lie where NIfTI's do); [`flavour`] tells
/// them apart.
pub(super) fn parse_header(path: &Path, head: &[u8]) -> Result<nifti::NiftiHeader, ReadError> {
    let mut patched;
    let head = if flavour(head) == Some(Flavour::Analyze) && head.len() >= 348 {
        patched = head.to_vec();
        patched[344..348].copy_from_slice(b"ni1\0");
        &patched[..]
    } else {
        head
    };
    nifti::NiftiHeader::from_reader(head).map_err(|source| ReadError::Nifti {
        path: path.to_path_buf(),
        source,
    })
}

/// The header in `head` parsed and checked (`sizeof_hdr`), with its flavour.
fn checked_header(path: &Path, head: &[u8]) -> Result<(nifti::NiftiHeader, Flavour), ReadError> {
    let header = parse_header(path, head)?;
    if header.sizeof_hdr != NIFTI1_HEADER_BYTES as i32 {
        return Err(ReadError::bad_header(
            path,
            "NIfTI",
            format!(
                "sizeof_hdr is {}, expected 348 (NIfTI-2 files are not supported)",
                header.sizeof_hdr
            ),
        ));
    }
    // The crate accepted the (possibly patched) magic: there is a flavour.
    let flavour = flavour(head).unwrap_or(Flavour::Pair);
    Ok((header, flavour))
}

/// The grid's dimensions from `dim[0..=7]`: `dim[0]` in 1..=7, every size at least 1, and any
/// beyond the third 1 (3D volumes only: a fourth of more than 1 is a time series, refused
/// here as [`ReadError::TimeSeries`]; [`series_dims`] reads it).
pub(super) fn grid_dims(path: &Path, header: &nifti::NiftiHeader) -> Result<[usize; 3], ReadError> {
    match series_dims(path, header)? {
        (dims, 1) => Ok(dims),
        (_, points) => Err(ReadError::TimeSeries {
            path: path.to_path_buf(),
            points,
        }),
    }
}

/// The grid's dimensions and time points: as [`grid_dims`], but `dim[4]` is the number of time
/// points (any beyond it must be 1).
pub(super) fn series_dims(
    path: &Path,
    header: &nifti::NiftiHeader,
) -> Result<([usize; 3], usize), ReadError> {
    let dims = space_dims(path, header)?;
    let points = if header.dim[0] >= 4 {
        usize::from(header.dim[4])
    } else {
        1
    };
    Ok((dims, points))
}

/// The spatial dimensions, with every dimension beyond the fourth 1.
fn space_dims(path: &Path, header: &nifti::NiftiHeader) -> Result<[usize; 3], ReadError> {
    let ndim = usize::from(header.dim[0]);
    if !(1..=7).contains(&ndim) {
        return Err(ReadError::bad_header(
            path,
            "NIfTI",
            format!("dim[0] is {ndim}, expected 1..=7"),
        ));
    }
    let mut dims = [1usize; 3];
    for i in 1..=ndim {
        let d = usize::from(header.dim[i]);
        if d == 0 {
            return Err(ReadError::bad_header(
                path,
                "NIfTI",
                format!("dim[{i}] is 0, expected at least 1"),
            ));
        }
        if i <= 3 {
            dims[i - 1] = d;
        } else if i > 4 && d != 1 {
            return Err(ReadError::unsupported(
                path,
                format!(
                    "dim[{i}] is {d}: only 3D volumes and time series are supported (dim[0] = {ndim}, dimensions beyond the fourth must be 1); dim = {:?}",
                    &header.dim[1..=ndim]
                ),
            ));
        }
    }
    Ok(dims)
}

/// Where the samples start: `vox_offset` as a whole number of bytes up to [`MAX_VOX_OFFSET`],
/// from the header's end in a single file, from 0 in a pair's data file.
pub(super) fn data_offset(
    path: &Path,
    header: &nifti::NiftiHeader,
    flavour: Flavour,
) -> Result<u64, ReadError> {
    let vox_offset = header.vox_offset;
    let (min, what) = match flavour {
        Flavour::Single => (NIFTI1_HEADER_BYTES, " (at least 352 for a single file)"),
        Flavour::Pair | Flavour::Analyze => (0, " (into the .img)"),
    };
    if !vox_offset.is_finite()
        || vox_offset < min as f32
        || vox_offset.fract() != 0.0
        || vox_offset > MAX_VOX_OFFSET as f32
    {
        return Err(ReadError::bad_header(
            path,
            "NIfTI",
            format!(
                "vox_offset is {vox_offset}, expected a whole number of bytes in {min}..={MAX_VOX_OFFSET}{what}"
            ),
        ));
    }
    Ok(vox_offset as u64)
}

/// Reads past what lies between byte `at` of a file (where `stream` is: the header's end in a
/// single file, 0 in a pair's data file) and `vox_offset`; a file that ends first is
/// truncated (`expected`: the sample bytes it should hold).
pub(super) fn skip_to_data(
    stream: &mut impl Read,
    path: &Path,
    at: u64,
    vox_offset: u64,
    expected: u64,
) -> Result<(), ReadError> {
    let skip = vox_offset.saturating_sub(at);
    let skipped =
        io::copy(&mut stream.take(skip), &mut io::sink()).map_err(|e| ReadError::io(path, e))?;
    if skipped != skip {
        return Err(ReadError::Truncated {
            path: path.to_path_buf(),
            offset: vox_offset,
            expected,
            actual: 0,
        });
    }
    Ok(())
}

/// The samples' byte order.
pub(super) fn endian(header: &nifti::NiftiHeader) -> Endian {
    match header.endianness {
        nifti::Endianness::Little => Endian::Little,
        nifti::Endianness::Big => Endian::Big,
    }
}

/// The header's (slope, intercept) when it applies: one channel, a finite non-zero slope and a
/// finite intercept. (An Analyze 7.5 header's `funused1` and `funused2`, where SPM keeps its
/// scale factor and intercept, lie where NIfTI's `scl_slope` and `scl_inter` do.)
pub(super) fn scaling(header: &nifti::NiftiHeader, channels: usize) -> Option<(f64, f64)> {
    (channels == 1
        && header.scl_slope.is_finite()
        && header.scl_slope != 0.0
        && header.scl_inter.is_finite())
    .then(|| (f64::from(header.scl_slope), f64::from(header.scl_inter)))
}

/// The sample type and channels of `datatype`, checked against `bitpix`.
fn sample_type(path: &Path, header: &nifti::NiftiHeader) -> Result<(SampleType, usize), ReadError> {
    let bad = |reason: String| ReadError::bad_header(path, "NIfTI", reason);
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
            return Err(ReadError::unsupported(
                path,
                format!(
                "datatype {t} ({}); supported are uint8/int8/(u)int16/(u)int32/(u)int64/float32/float64 and RGB24",
                match t {
                    32 => "complex64",
                    1536 => "float128",
                    1792 => "complex128",
                    2048 => "complex256",
                    _ => "RGBA32",
                }
            ),
            ))
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
    Ok((sample, channels))
}

/// `bytes`, inflated when they are gzip-compressed (detected by content, not by name).
fn inflated(bytes: &[u8]) -> Box<dyn Read + '_> {
    if bytes.starts_with(&[0x1f, 0x8b]) {
        Box::new(flate2::bufread::MultiGzDecoder::new(bytes))
    } else {
        Box::new(bytes)
    }
}

/// Decodes a NIfTI-1 single file (`.nii`, or gzip-compressed: detected by content, not by
/// name); `path` names it in messages. The header of a `.hdr` + `.img` pair (magic `ni1`) or
/// an Analyze 7.5 header is refused here: [`decode_nifti_pair`] reads it with its samples.
///
/// Scalar volumes with `dim[0]` ≤ 3, or more dimensions that are all 1 (e.g. 4D with one time
/// point), give 1 channel; `scl_slope`/`scl_inter` are applied when the slope is finite and
/// non-zero. RGB24 gives 3 channels with values 0..255 (scaling does not apply to RGB, as the
/// standard says). Integer and float types up to 64 bits are supported; complex, RGBA and
/// 128-bit types are not. Spacing comes from `pixdim[1..=3]`; non-positive or non-finite entries
/// (and axes beyond `dim[0]`) fall back to 1.0. The placement comes from the `sform` when
/// `sform_code` > 0 and it is orthonormal (an sform may carry shear from registration), else
/// from the `qform` when `qform_code` > 0, else there is none.
pub fn decode_nifti(path: &Path, bytes: &[u8]) -> Result<Volume, ReadError> {
    let mut stream = inflated(bytes);
    let head = read_header_bytes(&mut stream, path)?;
    let (header, flavour) = checked_header(path, &head)?;
    match flavour {
        Flavour::Single => {}
        Flavour::Pair => {
            return Err(ReadError::unsupported(
                path,
                "this is the header of a .hdr/.img pair (magic `ni1`), its samples in another \
                 file: read it named .hdr (or .hdr.gz), with its .img beside it",
            ))
        }
        Flavour::Analyze => {
            return Err(ReadError::bad_header(
                path,
                "NIfTI",
                format!(
                    "magic is {:?}, expected \"n+1\\0\" (an Analyze 7.5 header is read named \
                     .hdr, with its .img beside it)",
                    String::from_utf8_lossy(&head[344..348])
                ),
            ))
        }
    }
    decode_samples(
        path,
        &header,
        flavour,
        &mut stream,
        path,
        bytes.len(),
        NIFTI1_HEADER_BYTES,
    )
}

/// Decodes a `.hdr` + `.img` pair: the header (`header_bytes`, from `header_path`, gzip or not)
/// of a NIfTI-1 pair (magic `ni1`) or of Analyze 7.5 (`sizeof_hdr` 348 and no NIfTI magic),
/// and its samples from byte `vox_offset` of `data_bytes` (the `.img` at `data_path`, gzip or
/// not). A NIfTI pair is read as [`decode_nifti`] reads a single file (scaling, datatypes,
/// byte order, spacing, placement); Analyze the same but with no placement (its orientation
/// fields are not NIfTI's `qform`/`sform`, so where the grid lies is unknown: a warning says
/// so), `funused1` as a scale factor when it is non-zero, as SPM writes it.
pub fn decode_nifti_pair(
    header_path: &Path,
    header_bytes: &[u8],
    data_path: &Path,
    data_bytes: &[u8],
) -> Result<Volume, ReadError> {
    let mut stream = inflated(header_bytes);
    let head = read_header_bytes(&mut stream, header_path)?;
    let (header, flavour) = checked_header(header_path, &head)?;
    if flavour == Flavour::Single {
        return Err(ReadError::bad_header(
            header_path,
            "NIfTI",
            "magic is \"n+1\\0\", a single file's (its samples follow the header in it): name \
             it .nii, or give the pair's header magic \"ni1\\0\"",
        ));
    }
    let mut data = inflated(data_bytes);
    decode_samples(
        header_path,
        &header,
        flavour,
        &mut data,
        data_path,
        data_bytes.len(),
        0,
    )
}

/// Decodes the samples `header` describes from `stream`, which is at byte `at` of the file
/// holding them (`data_path`, of `available` bytes as stored); `path` (the header's file)
/// names the header's faults.
fn decode_samples(
    path: &Path,
    header: &nifti::NiftiHeader,
    flavour: Flavour,
    stream: &mut dyn Read,
    data_path: &Path,
    available: usize,
    at: u64,
) -> Result<Volume, ReadError> {
    let dims = grid_dims(path, header)?;
    let (sample, channels) = sample_type(path, header)?;
    let voxels = voxel_count(dims).map_err(|e| ReadError::volume(path, e))?;
    let expected = voxels
        .checked_mul(sample.size() * channels)
        .ok_or(ReadError::TooLarge {
            dims,
            channels,
            bytes_per_sample: sample.size(),
        })?;

    let vox_offset = data_offset(path, header, flavour)?;
    let mut stream = stream;
    skip_to_data(&mut stream, data_path, at, vox_offset, expected as u64)?;

    // Voxel data: grow as data arrives, so a lying header on a short file allocates little.
    let data = read_exact_or_truncated(&mut stream, expected, available, data_path, vox_offset)?;

    let endian = endian(header);
    let (slope, inter) = scaling(header, channels).unwrap_or((1.0, 0.0));
    let ndim = usize::from(header.dim[0]);
    let mut spacing = [1.0f32; 3];
    for (i, s) in spacing.iter_mut().enumerate().take(ndim.min(3)) {
        let p = header.pixdim[i + 1];
        if p.is_finite() && p > 0.0 {
            *s = p;
        }
    }
    let planar = deinterleave(&data, sample, endian, channels, slope, inter);
    drop(data);
    let volume = Volume::new(dims, spacing, planar).map_err(|e| ReadError::volume(data_path, e))?;
    Ok(match placement(path, header, flavour) {
        Some(p) => volume
            .with_placement(p)
            .map_err(|e| ReadError::volume(path, e))?,
        None => volume,
    })
}

/// The time between time points in seconds from `pixdim[4]` and the time unit of
/// `xyzt_units` (seconds, milliseconds or microseconds), when both say (never for Analyze 7.5,
/// which has no time unit).
pub(super) fn time_step(header: &nifti::NiftiHeader, flavour: Flavour) -> Option<f64> {
    if flavour == Flavour::Analyze {
        return None;
    }
    let step = f64::from(header.pixdim[4]);
    let unit = match header.xyzt_units & 0x38 {
        8 => 1.0,
        16 => 1e-3,
        24 => 1e-6,
        _ => return None,
    };
    (step.is_finite() && step > 0.0).then_some(step * unit)
}

/// The grid's placement in LPS from the sform (preferred) or the qform; none for Analyze 7.5
/// (whose bytes there are other fields). NIfTI's world frame is RAS: LPS negates x and y.
fn placement(path: &Path, h: &::nifti::NiftiHeader, flavour: Flavour) -> Option<Placement> {
    if flavour == Flavour::Analyze {
        tracing::warn!(
            path = %path.display(),
            "an Analyze 7.5 header (no NIfTI magic): its orientation is unknown, so the volume \
             has no placement in patient space (its spacing is kept)"
        );
        return None;
    }
    let to_lps = |v: [f64; 3]| [-v[0], -v[1], v[2]];
    if h.sform_code > 0 {
        let rows = [h.srow_x, h.srow_y, h.srow_z].map(|r| r.map(f64::from));
        let mut p = Placement {
            origin: to_lps([rows[0][3], rows[1][3], rows[2][3]]),
            directions: [[0.0; 3]; 3],
        };
        let mut ok = true;
        for (a, d) in p.directions.iter_mut().enumerate() {
            let col = [rows[0][a], rows[1][a], rows[2][a]];
            let norm = (col[0] * col[0] + col[1] * col[1] + col[2] * col[2]).sqrt();
            ok &= norm.is_finite() && norm > 0.0;
            *d = to_lps(col.map(|c| c / norm));
        }
        if ok && p.validate().is_ok() {
            return Some(p);
        }
        tracing::warn!(
            "NIfTI sform is not a rigid placement (shear or bad values); trying the qform"
        );
    }
    if h.qform_code > 0 {
        let (b, c, d) = (
            f64::from(h.quatern_b),
            f64::from(h.quatern_c),
            f64::from(h.quatern_d),
        );
        let a = (1.0 - (b * b + c * c + d * d)).max(0.0).sqrt();
        let qfac = if h.pixdim[0] < 0.0 { -1.0 } else { 1.0 };
        // Rotation matrix of the unit quaternion (a, b, c, d), NIfTI-1 standard; columns are
        // the axis directions, the third scaled by qfac.
        let r = [
            [
                a * a + b * b - c * c - d * d,
                2.0 * (b * c - a * d),
                2.0 * (b * d + a * c),
            ],
            [
                2.0 * (b * c + a * d),
                a * a + c * c - b * b - d * d,
                2.0 * (c * d - a * b),
            ],
            [
                2.0 * (b * d - a * c),
                2.0 * (c * d + a * b),
                a * a + d * d - c * c - b * b,
            ],
        ];
        let col = |j: usize, s: f64| to_lps([r[0][j] * s, r[1][j] * s, r[2][j] * s]);
        let p = Placement {
            origin: to_lps([h.quatern_x, h.quatern_y, h.quatern_z].map(f64::from)),
            directions: [col(0, 1.0), col(1, 1.0), col(2, qfac)],
        };
        if p.validate().is_ok() {
            return Some(p);
        }
        tracing::warn!("NIfTI qform is invalid; the volume has no placement");
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::reader::read_volume;
    use std::fs::File;
    use std::io::Write;
    use wavesplat_codec::volume::VolumeError;

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
        // Real 4D: a time series, which one volume's reader refuses by name.
        let e = read_volume(&path, None).unwrap_err();
        assert!(matches!(e, ReadError::TimeSeries { points: 3, .. }), "{e}");
        assert!(e.to_string().contains("--time-point"), "{e}");
        // Beyond the fourth dimension: refused.
        let mut b = good([5, 2, 2, 2, 1, 2, 1, 1], 2, 8);
        b.extend(vec![0u8; 16]);
        write_file(&path, &b, false);
        let e = read_volume(&path, None).unwrap_err();
        assert!(matches!(e, ReadError::Unsupported { .. }), "{e}");
        assert!(e.to_string().contains("dim[5] is 2"), "{e}");

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
            Err(ReadError::InvalidVolume {
                problem: VolumeError::TooLarge { .. },
                ..
            })
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
            Err(ReadError::InvalidVolume {
                problem: VolumeError::NonFinite { .. },
                ..
            })
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

    /// A `.hdr`'s data file is looked for beside it, compressed as the header is first, in
    /// its letter case first; a `.img` names its header.
    #[test]
    fn a_pairs_data_file_is_looked_for_beside_its_header() {
        let p = |s: &str| Path::new("/d").join(s);
        assert_eq!(
            pair_data_candidates(&p("a.b.hdr")),
            [p("a.b.img"), p("a.b.img.gz")]
        );
        assert_eq!(
            pair_data_candidates(&p("x.hdr.gz")),
            [p("x.img.gz"), p("x.img")]
        );
        assert_eq!(
            pair_data_candidates(&p("X.HDR")),
            [p("X.IMG"), p("X.IMG.GZ"), p("X.img"), p("X.img.gz")]
        );
        assert!(pair_data_candidates(&p("x.nii")).is_empty());
        assert!(is_pair_header_path(&p("x.Hdr")) && !is_pair_header_path(&p("x.img")));

        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        // Only the compressed data file: found second.
        std::fs::write(d.join("v.img.gz"), b"").unwrap();
        assert_eq!(
            pair_data_file(&d.join("v.hdr")).unwrap(),
            d.join("v.img.gz")
        );
        let e = pair_data_file(&d.join("w.hdr")).unwrap_err();
        assert!(e.to_string().contains("w.img nor"), "{e}");
        assert_eq!(pair_header_of(&d.join("v.img.gz")), None);
        std::fs::write(d.join("v.hdr"), b"").unwrap();
        assert_eq!(pair_header_of(&d.join("v.img.gz")), Some(d.join("v.hdr")));
        assert_eq!(pair_header_of(&d.join("v.nii")), None);
        // Only a header of NIfTI's size is a pair's header (not ENVI's text).
        assert!(!is_pair_header(&d.join("v.hdr")));
        std::fs::write(d.join("e.hdr"), b"ENVI\nsamples = 4\n").unwrap();
        assert!(!is_pair_header(&d.join("e.hdr")));
        let h = nifti_header([3, 1, 1, 1, 1, 1, 1, 1], 2, 8, [1.0; 8], 1.0, 0.0, true);
        write_file(&d.join("n.hdr.gz"), &h[..348], true);
        assert!(is_pair_header(&d.join("n.hdr.gz")));
        assert_eq!(flavour(&h), Some(Flavour::Single));
        let mut a = h.clone();
        a[344..348].copy_from_slice(b"ni1\0");
        assert!(looks_like_header(&a));
        assert_eq!(flavour(&a), Some(Flavour::Pair));
        a[344..348].copy_from_slice(&[1, 2, 3, 4]);
        assert!(!looks_like_header(&a));
        assert_eq!(flavour(&a), Some(Flavour::Analyze));
        a[..4].copy_from_slice(&[0; 4]);
        assert_eq!(flavour(&a), None);
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
