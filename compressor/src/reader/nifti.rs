//! NIfTI-1 single files (`.nii`, `.nii.gz`): the header parsed with the `nifti` crate, the
//! samples decoded here, and the grid's placement from the `sform` (else the `qform`) affine,
//! converted from NIfTI's RAS to LPS.

use std::io::{self, Read};
use std::path::Path;

use super::{deinterleave, read_exact_or_truncated, voxel_count, Endian, ReadError, SampleType};
use wavesplat_codec::volume::{Placement, Volume};

/// Whether `path` names a NIfTI single file (`.nii` or `.nii.gz`, case-insensitive).
pub fn is_nifti_path(path: &Path) -> bool {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default();
    name.ends_with(".nii") || name.ends_with(".nii.gz")
}

/// Whether `head` starts like an uncompressed NIfTI-1 single file (`sizeof_hdr` = 348 in either
/// byte order and magic `n+1` at offset 344).
pub(crate) fn looks_like_header(head: &[u8]) -> bool {
    head.len() >= 348
        && (head[..4] == 348i32.to_le_bytes() || head[..4] == 348i32.to_be_bytes())
        && &head[344..347] == b"n+1"
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

/// The header in `head` (from [`read_header_bytes`]) as the `nifti` crate parses it.
pub(super) fn parse_header(path: &Path, head: &[u8]) -> Result<nifti::NiftiHeader, ReadError> {
    nifti::NiftiHeader::from_reader(head).map_err(|source| ReadError::Nifti {
        path: path.to_path_buf(),
        source,
    })
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

/// The time between time points in seconds from `pixdim[4]` and the time unit of
/// `xyzt_units` (seconds, milliseconds or microseconds), when both say.
pub(super) fn time_step(header: &nifti::NiftiHeader) -> Option<f64> {
    let step = f64::from(header.pixdim[4]);
    let unit = match header.xyzt_units & 0x38 {
        8 => 1.0,
        16 => 1e-3,
        24 => 1e-6,
        _ => return None,
    };
    (step.is_finite() && step > 0.0).then_some(step * unit)
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

/// Where the samples start: `vox_offset` as a whole number of bytes from the header's end to
/// [`MAX_VOX_OFFSET`].
pub(super) fn data_offset(path: &Path, header: &nifti::NiftiHeader) -> Result<u64, ReadError> {
    let vox_offset = header.vox_offset;
    if !vox_offset.is_finite()
        || vox_offset < NIFTI1_HEADER_BYTES as f32
        || vox_offset.fract() != 0.0
        || vox_offset > MAX_VOX_OFFSET as f32
    {
        return Err(ReadError::bad_header(
            path,
            "NIfTI",
            format!(
                "vox_offset is {vox_offset}, expected a whole number of bytes in 348..={MAX_VOX_OFFSET} (at least 352 for a single file)"
            ),
        ));
    }
    Ok(vox_offset as u64)
}

/// Reads past the extender and extensions, from the header's end to `vox_offset`; a file that
/// ends first is truncated (`expected`: the sample bytes it should hold).
pub(super) fn skip_to_data(
    stream: &mut impl Read,
    path: &Path,
    vox_offset: u64,
    expected: u64,
) -> Result<(), ReadError> {
    let skip = vox_offset - NIFTI1_HEADER_BYTES;
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
/// finite intercept.
pub(super) fn scaling(header: &nifti::NiftiHeader, channels: usize) -> Option<(f64, f64)> {
    (channels == 1
        && header.scl_slope.is_finite()
        && header.scl_slope != 0.0
        && header.scl_inter.is_finite())
    .then(|| (f64::from(header.scl_slope), f64::from(header.scl_inter)))
}

/// Decodes a NIfTI-1 single file (`.nii`, or gzip-compressed: detected by content, not by
/// name); `path` names it in messages.
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
    let bad = |reason: String| ReadError::bad_header(path, "NIfTI", reason);
    let unsupported = |reason: String| ReadError::Unsupported {
        path: path.to_path_buf(),
        reason,
    };

    // Detect gzip by its magic bytes rather than by name.
    let mut stream: Box<dyn Read + '_> = if bytes.starts_with(&[0x1f, 0x8b]) {
        Box::new(flate2::bufread::MultiGzDecoder::new(bytes))
    } else {
        Box::new(bytes)
    };

    let header_bytes = read_header_bytes(&mut stream, path)?;
    let header = parse_header(path, &header_bytes)?;
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

    let dims = grid_dims(path, &header)?;

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
    let voxels = voxel_count(dims).map_err(|e| ReadError::volume(path, e))?;
    let expected = voxels
        .checked_mul(sample.size() * channels)
        .ok_or(ReadError::TooLarge {
            dims,
            channels,
            bytes_per_sample: sample.size(),
        })?;

    let vox_offset = data_offset(path, &header)?;
    skip_to_data(&mut stream, path, vox_offset, expected as u64)?;

    // Voxel data: grow as data arrives, so a lying header on a short file allocates little.
    let data = read_exact_or_truncated(&mut stream, expected, bytes.len(), path, vox_offset)?;

    let endian = endian(&header);
    let (slope, inter) = scaling(&header, channels).unwrap_or((1.0, 0.0));
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
    let volume = Volume::new(dims, spacing, planar).map_err(|e| ReadError::volume(path, e))?;
    Ok(match placement(&header) {
        Some(p) => volume
            .with_placement(p)
            .map_err(|e| ReadError::volume(path, e))?,
        None => volume,
    })
}

/// The grid's placement in LPS from the sform (preferred) or the qform. NIfTI's world frame is
/// RAS: LPS negates x and y.
fn placement(h: &::nifti::NiftiHeader) -> Option<Placement> {
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
