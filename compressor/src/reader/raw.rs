//! Headerless raw volumes: `u8`, `u16`, `i16`, `f32` samples in either byte order, 1 or 3
//! interleaved channels, x fastest, described by a [`RawSpec`] (from the command line or the
//! archive's file-name convention). The size is checked against the description before
//! anything is read.

use std::fmt;
use std::fs::File;
use std::io::{self, Read};
use std::path::Path;

use super::{deinterleave, voxel_count, ReadError, SampleType};
use wavesplat_codec::volume::Volume;

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
    /// Time points stored one after another (a 4D raw file: x, y, z, t); 1 for a volume.
    pub time_points: usize,
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
            time_points: 1,
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

    /// Refuses a spec of several time points where one volume is read.
    fn one_time_point(&self, path: Option<&Path>) -> Result<(), ReadError> {
        if self.time_points == 1 {
            return Ok(());
        }
        Err(ReadError::TimeSeries {
            path: path.map_or_else(|| "(raw data)".into(), Path::to_path_buf),
            points: self.time_points,
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
            time_points: self.time_points,
        }
    }
}

/// Reads a headerless raw volume. The file must be exactly as large as `spec` requires; its size
/// is checked before anything is read.
pub fn read_raw(path: &Path, spec: &RawSpec) -> Result<Volume, ReadError> {
    spec.one_time_point(Some(path))?;
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
    spec.one_time_point(None)?;
    let expected = spec.byte_len()?;
    if bytes.len() != expected {
        return Err(spec.mismatch(None, expected, bytes.len() as u64));
    }
    let sample = match spec.dtype {
        RawDtype::U8 => SampleType::U8,
        RawDtype::U16 => SampleType::U16,
        RawDtype::I16 => SampleType::I16,
        RawDtype::F32 => SampleType::F32,
    };
    let channels = deinterleave(bytes, sample, spec.endian, spec.channels, 1.0, 0.0);
    Ok(Volume::new(spec.dims, spec.spacing, channels)?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::reader::read_volume;
    use wavesplat_codec::volume::VolumeError;

    fn spec(dims: [usize; 3], dtype: RawDtype, endian: Endian, channels: usize) -> RawSpec {
        RawSpec {
            dims,
            dtype,
            endian,
            channels,
            spacing: [1.0, 2.0, 0.5],
            time_points: 1,
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
}
