//! Headerless raw volumes: 8-, 16-, 32- and 64-bit integer samples (`u8`, `i8`, `u16`, `i16`,
//! `u32`, `i32`, `u64`, `i64`), `f32` and `f64` in either byte order (values become f32, as
//! every reader's do), 1 or 3
//! interleaved channels, x fastest, described by a [`RawSpec`] (from the command line or the
//! archive's file-name convention), optionally after a fixed-size header the spec skips
//! ([`RawSpec::header_bytes`]). The size is checked against the description before anything
//! is read.

use std::fmt;
use std::fs::File;
use std::io::{self, Read, Seek, SeekFrom};
use std::path::Path;

use super::{deinterleave, voxel_count, ReadError, SampleType};
use wavesplat_codec::volume::Volume;

/// Sample type of a raw volume file.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum RawDtype {
    /// Unsigned 8-bit integer.
    U8,
    /// Signed 8-bit integer (two's complement).
    I8,
    /// Unsigned 16-bit integer.
    U16,
    /// Signed 16-bit integer (two's complement).
    I16,
    /// Unsigned 32-bit integer (values above 2^24 are rounded to f32).
    U32,
    /// Signed 32-bit integer (two's complement; magnitudes above 2^24 are rounded to f32).
    I32,
    /// Unsigned 64-bit integer (rounded to f32).
    U64,
    /// Signed 64-bit integer (two's complement; rounded to f32).
    I64,
    /// IEEE-754 32-bit float. NaN and Inf are rejected when the volume is built.
    F32,
    /// IEEE-754 64-bit float, rounded to f32. NaN, Inf and values beyond f32's range are
    /// rejected when the volume is built.
    F64,
}

impl RawDtype {
    /// Every sample type, in the order of [`RawDtype::names`].
    pub const ALL: [RawDtype; 10] = [
        RawDtype::U8,
        RawDtype::I8,
        RawDtype::U16,
        RawDtype::I16,
        RawDtype::U32,
        RawDtype::I32,
        RawDtype::U64,
        RawDtype::I64,
        RawDtype::F32,
        RawDtype::F64,
    ];

    /// Parses `u8`, `i8`, `u16`, `i16`, `u32`, `i32`, `u64`, `i64`, `f32` or `f64`
    /// (case-insensitive; `uint8`, `int8`, …, `int64`, `float32`, `float`, `float64` and
    /// `double` are accepted too).
    pub fn from_name(name: &str) -> Result<RawDtype, ReadError> {
        match name.trim().to_ascii_lowercase().as_str() {
            "u8" | "uint8" => Ok(RawDtype::U8),
            "i8" | "int8" => Ok(RawDtype::I8),
            "u16" | "uint16" => Ok(RawDtype::U16),
            "i16" | "int16" => Ok(RawDtype::I16),
            "u32" | "uint32" => Ok(RawDtype::U32),
            "i32" | "int32" => Ok(RawDtype::I32),
            "u64" | "uint64" => Ok(RawDtype::U64),
            "i64" | "int64" => Ok(RawDtype::I64),
            "f32" | "float32" | "float" => Ok(RawDtype::F32),
            "f64" | "float64" | "double" => Ok(RawDtype::F64),
            _ => Err(ReadError::UnknownDtype(name.to_string())),
        }
    }

    /// The canonical names accepted by [`RawDtype::from_name`].
    pub fn names() -> &'static [&'static str] {
        &[
            "u8", "i8", "u16", "i16", "u32", "i32", "u64", "i64", "f32", "f64",
        ]
    }

    /// The canonical name (`u8`, `i8`, `u16`, `i16`, `u32`, `i32`, `u64`, `i64`, `f32`, `f64`).
    pub fn name(self) -> &'static str {
        match self {
            RawDtype::U8 => "u8",
            RawDtype::I8 => "i8",
            RawDtype::U16 => "u16",
            RawDtype::I16 => "i16",
            RawDtype::U32 => "u32",
            RawDtype::I32 => "i32",
            RawDtype::U64 => "u64",
            RawDtype::I64 => "i64",
            RawDtype::F32 => "f32",
            RawDtype::F64 => "f64",
        }
    }

    /// Bytes per sample.
    pub fn size(self) -> usize {
        self.sample().size()
    }

    /// The sample type the readers decode.
    pub(crate) fn sample(self) -> SampleType {
        match self {
            RawDtype::U8 => SampleType::U8,
            RawDtype::I8 => SampleType::I8,
            RawDtype::U16 => SampleType::U16,
            RawDtype::I16 => SampleType::I16,
            RawDtype::U32 => SampleType::U32,
            RawDtype::I32 => SampleType::I32,
            RawDtype::U64 => SampleType::U64,
            RawDtype::I64 => SampleType::I64,
            RawDtype::F32 => SampleType::F32,
            RawDtype::F64 => SampleType::F64,
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
    /// Bytes before the samples (a fixed-size header of some other program's, skipped
    /// unread); 0 for a headerless file. The file must hold exactly these and the samples.
    pub header_bytes: u64,
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
            header_bytes: 0,
        }
    }

    /// Exact byte size of one volume's samples with this layout (a file holds
    /// [`RawSpec::header_bytes`] more: [`RawSpec::file_len`]), validating dims and channel
    /// count.
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

    /// Exact byte size a file of one volume with this layout must have: the header's bytes
    /// and the samples'.
    pub fn file_len(&self) -> Result<u64, ReadError> {
        let samples = self.byte_len()?;
        (samples as u64)
            .checked_add(self.header_bytes)
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

    /// The size error of a file (or buffer) of `actual` bytes where `expected` (the header's
    /// and the samples') are needed.
    fn mismatch(&self, path: Option<&Path>, expected: u64, actual: u64) -> ReadError {
        ReadError::SizeMismatch {
            path: path.map(Path::to_path_buf),
            expected,
            actual,
            header_bytes: self.header_bytes,
            dims: self.dims,
            channels: self.channels,
            dtype: self.dtype,
            bytes_per_sample: self.dtype.size() as u8,
            time_points: self.time_points,
        }
    }
}

/// Reads a raw volume. The file must be exactly as large as `spec` requires (its
/// [`RawSpec::header_bytes`] and the samples); its size is checked before anything is read,
/// and the header's bytes are skipped unread.
pub fn read_raw(path: &Path, spec: &RawSpec) -> Result<Volume, ReadError> {
    spec.one_time_point(Some(path))?;
    let expected = spec.byte_len()?;
    let total = spec.file_len()?;
    let io_err = |source| ReadError::Io {
        path: path.to_path_buf(),
        source,
    };
    let mut file = File::open(path).map_err(io_err)?;
    let len = file.metadata().map_err(io_err)?.len();
    if len != total {
        return Err(spec.mismatch(Some(path), total, len));
    }
    if spec.header_bytes > 0 {
        file.seek(SeekFrom::Start(spec.header_bytes))
            .map_err(io_err)?;
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
        return Err(spec.mismatch(Some(path), total, spec.header_bytes + got as u64));
    }
    decode_samples(&bytes, spec)
}

/// Decodes a raw volume from memory: `bytes` are the file's whole contents, exactly as long as
/// `spec` requires ([`RawSpec::file_len`]: its [`RawSpec::header_bytes`], skipped, then the
/// samples).
pub fn decode_raw(bytes: &[u8], spec: &RawSpec) -> Result<Volume, ReadError> {
    spec.one_time_point(None)?;
    let total = spec.file_len()?;
    if bytes.len() as u64 != total {
        return Err(spec.mismatch(None, total, bytes.len() as u64));
    }
    decode_samples(&bytes[spec.header_bytes as usize..], spec)
}

/// Decodes the samples of one volume (`bytes`: exactly [`RawSpec::byte_len`] of them).
fn decode_samples(bytes: &[u8], spec: &RawSpec) -> Result<Volume, ReadError> {
    let channels = deinterleave(
        bytes,
        spec.dtype.sample(),
        spec.endian,
        spec.channels,
        1.0,
        0.0,
    );
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
            header_bytes: 0,
        }
    }

    #[test]
    fn dtype_and_endian_names() {
        for n in RawDtype::names() {
            assert_eq!(RawDtype::from_name(n).unwrap().name(), *n);
        }
        assert_eq!(RawDtype::from_name("UINT16").unwrap(), RawDtype::U16);
        assert_eq!(RawDtype::names().len(), RawDtype::ALL.len());
        for (d, n) in RawDtype::ALL.iter().zip(RawDtype::names()) {
            assert_eq!(d.name(), *n);
        }
        for (n, d, size) in [
            ("f64", RawDtype::F64, 8),
            ("double", RawDtype::F64, 8),
            ("i32", RawDtype::I32, 4),
            ("INT32", RawDtype::I32, 4),
            ("u32", RawDtype::U32, 4),
            ("i8", RawDtype::I8, 1),
            ("uint64", RawDtype::U64, 8),
            ("i64", RawDtype::I64, 8),
        ] {
            assert_eq!(RawDtype::from_name(n).unwrap(), d, "{n}");
            assert_eq!(d.size(), size, "{n}");
        }
        let e = RawDtype::from_name("u12").unwrap_err();
        assert!(e.to_string().contains("u12"), "{e}");
        assert!(
            e.to_string().contains("i32") && e.to_string().contains("f64"),
            "{e}"
        );
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

    /// Bytes of `vals` in `endian`, each through `to` (its `to_le_bytes` / `to_be_bytes`).
    fn bytes_of<T: Copy, const N: usize>(
        vals: &[T],
        endian: Endian,
        le: fn(T) -> [u8; N],
        be: fn(T) -> [u8; N],
    ) -> Vec<u8> {
        vals.iter()
            .flat_map(|v| match endian {
                Endian::Little => le(*v),
                Endian::Big => be(*v),
            })
            .collect()
    }

    /// Raw f64 and i32 files (and i8, u32, u64, i64 data) read back to their values, in either
    /// byte order; a file of the wrong size says the size its description needs.
    #[test]
    fn wide_integers_and_doubles_read_back() {
        let dir = tempfile::tempdir().unwrap();
        let dims = [3, 2, 1];
        for endian in [Endian::Little, Endian::Big] {
            let f64s = [-1.5f64, 0.0, 1e-3, 3.25, 1e30, -7.0];
            let path = dir.path().join(format!("v_{endian:?}.f64"));
            std::fs::write(
                &path,
                bytes_of(&f64s, endian, f64::to_le_bytes, f64::to_be_bytes),
            )
            .unwrap();
            let s = spec(dims, RawDtype::from_name("f64").unwrap(), endian, 1);
            let v = read_volume(&path, Some(&s)).unwrap();
            let want: Vec<f32> = f64s.iter().map(|x| *x as f32).collect();
            assert_eq!(v.channel(0), &want[..]);
            assert_eq!(v.spacing(), [1.0, 2.0, 0.5]);

            let i32s = [-2_000_000i32, -1, 0, 1, 16_777_216, i32::MIN];
            let path = dir.path().join(format!("v_{endian:?}.i32"));
            std::fs::write(
                &path,
                bytes_of(&i32s, endian, i32::to_le_bytes, i32::to_be_bytes),
            )
            .unwrap();
            let s = spec(dims, RawDtype::from_name("i32").unwrap(), endian, 1);
            let v = read_volume(&path, Some(&s)).unwrap();
            let want: Vec<f32> = i32s.iter().map(|x| *x as f32).collect();
            assert_eq!(v.channel(0), &want[..]);

            let i8s = [-128i8, -1, 0, 1, 127, 5];
            let b = bytes_of(&i8s, endian, i8::to_le_bytes, i8::to_be_bytes);
            let v = decode_raw(&b, &spec(dims, RawDtype::I8, endian, 1)).unwrap();
            assert_eq!(v.channel(0), &[-128.0, -1.0, 0.0, 1.0, 127.0, 5.0]);
            let u32s = [0u32, 1, 70_000, 4_000_000, 16_777_216, 9];
            let b = bytes_of(&u32s, endian, u32::to_le_bytes, u32::to_be_bytes);
            let v = decode_raw(&b, &spec(dims, RawDtype::U32, endian, 1)).unwrap();
            let want: Vec<f32> = u32s.iter().map(|x| *x as f32).collect();
            assert_eq!(v.channel(0), &want[..]);
            let u64s = [0u64, 1, 1 << 40, 300, 7, 65_536];
            let b = bytes_of(&u64s, endian, u64::to_le_bytes, u64::to_be_bytes);
            let v = decode_raw(&b, &spec(dims, RawDtype::U64, endian, 1)).unwrap();
            let want: Vec<f32> = u64s.iter().map(|x| *x as f32).collect();
            assert_eq!(v.channel(0), &want[..]);
            let i64s = [-(1i64 << 40), -1, 0, 1, 123_456, -9];
            let b = bytes_of(&i64s, endian, i64::to_le_bytes, i64::to_be_bytes);
            let v = decode_raw(&b, &spec(dims, RawDtype::I64, endian, 1)).unwrap();
            let want: Vec<f32> = i64s.iter().map(|x| *x as f32).collect();
            assert_eq!(v.channel(0), &want[..]);
        }
        // 6 f64 samples need 48 bytes: a file of 40 is refused, saying so.
        let path = dir.path().join("short.f64");
        std::fs::write(&path, [0u8; 40]).unwrap();
        let e =
            read_volume(&path, Some(&spec(dims, RawDtype::F64, Endian::Little, 1))).unwrap_err();
        assert!(
            matches!(
                e,
                ReadError::SizeMismatch {
                    expected: 48,
                    actual: 40,
                    dtype: RawDtype::F64,
                    bytes_per_sample: 8,
                    ..
                }
            ),
            "{e}"
        );
        let msg = e.to_string();
        assert!(
            msg.contains("exactly 48 bytes") && msg.contains("(f64)"),
            "{msg}"
        );
        // A double beyond f32's range is refused as non-finite, not read as infinity.
        let b = bytes_of(
            &[1e300f64],
            Endian::Little,
            f64::to_le_bytes,
            f64::to_be_bytes,
        );
        assert!(matches!(
            decode_raw(&b, &spec([1, 1, 1], RawDtype::F64, Endian::Little, 1)),
            Err(ReadError::Volume(VolumeError::NonFinite { .. }))
        ));
    }

    /// A raw file with a 512-byte header of another program's before its samples reads back
    /// exactly with `header_bytes` 512, from the file and from memory; a wrong header size is
    /// the size error naming the total the description needs.
    #[test]
    fn a_header_before_the_samples_is_skipped() {
        let dir = tempfile::tempdir().unwrap();
        let u16s: Vec<u16> = (0..24u16).map(|i| i * 2700 + 1).collect();
        let samples = bytes_of(&u16s, Endian::Big, u16::to_le_bytes, u16::to_be_bytes);
        let header: Vec<u8> = (0..512).map(|i| (i * 31 % 256) as u8).collect();
        let path = dir.path().join("scanner.dat");
        std::fs::write(&path, [header.clone(), samples.clone()].concat()).unwrap();
        let mut s = spec([2, 3, 4], RawDtype::U16, Endian::Big, 1);
        s.header_bytes = 512;
        assert_eq!(s.file_len().unwrap(), 512 + 48);
        let want: Vec<f32> = u16s.iter().map(|v| f32::from(*v)).collect();
        let v = read_raw(&path, &s).unwrap();
        assert_eq!(v.channel(0), &want[..]);
        assert_eq!(v.spacing(), [1.0, 2.0, 0.5]);
        assert_eq!(read_volume(&path, Some(&s)).unwrap(), v);
        let whole = std::fs::read(&path).unwrap();
        assert_eq!(decode_raw(&whole, &s).unwrap(), v);
        // Without the header's size the file is 512 bytes too long; with a wrong one, off.
        for (n, expected) in [(0u64, 48u64), (500, 548), (600, 648)] {
            s.header_bytes = n;
            for e in [
                read_raw(&path, &s).unwrap_err(),
                read_volume(&path, Some(&s)).unwrap_err(),
                decode_raw(&whole, &s).unwrap_err(),
            ] {
                assert!(
                    matches!(
                        e,
                        ReadError::SizeMismatch { expected: x, actual: 560, header_bytes: h, .. }
                            if x == expected && h == n
                    ),
                    "{e}"
                );
                let msg = e.to_string();
                assert!(msg.contains(&format!("exactly {expected} bytes")), "{msg}");
                assert_eq!(msg.contains(&format!("a {n}-byte header")), n > 0, "{msg}");
            }
        }
        // A header larger than the file, or than memory addressing, is a size error too.
        s.header_bytes = u64::MAX;
        assert!(read_raw(&path, &s).is_err());
        assert!(decode_raw(&whole, &s).is_err());
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
