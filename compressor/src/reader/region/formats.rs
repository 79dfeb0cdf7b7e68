//! Opening each format for region reads: where its samples lie (file, offset, compression, sample
//! type, byte order, rescale) is parsed here from the header alone; what the header means
//! (validation, channels, spacing, placement) is taken from the format's own decoder run on a
//! *stand-in*: the same header with every size set to one voxel (or two, where a size of 1 or 3
//! decides which axis holds the channels), the data attached, raw, and zero-filled. So
//! [`super::RegionReader`] reports exactly what [`crate::reader::read_volume`] would, without a
//! second copy of the geometry code, and the stand-in is a few bytes whatever the volume's size.
//! The sizes, the data location and encoding, which the stand-in replaces, are validated here
//! with the decoders' rules and messages.

use std::fs::File;
use std::io::{self, BufRead, BufReader, Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use super::{read_whole, Opened, Source, Stored};
use crate::reader::text::{self, header_lines, MAX_TEXT_HEADER};
use crate::reader::{
    metaimage, nifti, nrrd, Endian, Format, RawDtype, RawSpec, ReadError, SampleType, SourceFiles,
};
use wavesplat_codec::volume::{Volume, VolumeError};

/// Opens `path` by format, as [`crate::reader::read_volume`] dispatches.
pub(super) fn open(path: &Path, raw: Option<&RawSpec>) -> Result<Opened, ReadError> {
    let meta = std::fs::metadata(path).map_err(|e| ReadError::io(path, e))?;
    if meta.is_dir() {
        return read_whole(path); // a DICOM series
    }
    let by_name = Format::from_name(path);
    if let (None, Some(spec)) = (by_name, raw) {
        return open_raw(path, spec);
    }
    let format = match by_name {
        Some(f) => Some(f),
        None => Format::sniff(&read_prefix(path, 512)?),
    };
    match format {
        Some(Format::Dicom) => read_whole(path),
        Some(Format::Nrrd) => open_nrrd(path),
        Some(Format::MetaImage) => open_metaimage(path),
        Some(Format::Nifti) => open_nifti(path),
        None => Err(ReadError::MissingRawSpec {
            path: path.to_path_buf(),
        }),
    }
}

/// Up to `limit` bytes from the start of a file.
fn read_prefix(path: &Path, limit: u64) -> Result<Vec<u8>, ReadError> {
    let f = File::open(path).map_err(|e| ReadError::io(path, e))?;
    let mut out = Vec::new();
    f.take(limit)
        .read_to_end(&mut out)
        .map_err(|e| ReadError::io(path, e))?;
    Ok(out)
}

/// Bytes of `dims` × `channels` samples of `sample`, checked (u128, then u64).
fn stored_bytes(
    path: &Path,
    dims: [usize; 3],
    channels: usize,
    size: usize,
) -> Result<u64, ReadError> {
    if dims.contains(&0) {
        return Err(ReadError::volume(path, VolumeError::ZeroDimension(dims)));
    }
    dims.iter()
        .chain([&channels, &size])
        .try_fold(1u128, |acc, d| acc.checked_mul(*d as u128))
        .and_then(|b| u64::try_from(b).ok())
        .filter(|b| *b <= i64::MAX as u64)
        .ok_or(ReadError::TooLarge {
            dims,
            channels,
            bytes_per_sample: size,
        })
}

/// Samples stored uncompressed in `data_path` from `offset` on; the file must hold all
/// `expected` bytes.
fn stored_at(
    data_path: &Path,
    offset: u64,
    expected: u64,
    sample: SampleType,
    endian: Endian,
) -> Result<Stored, ReadError> {
    let file = File::open(data_path).map_err(|e| ReadError::io(data_path, e))?;
    let len = file
        .metadata()
        .map_err(|e| ReadError::io(data_path, e))?
        .len();
    let actual = len.saturating_sub(offset);
    if actual < expected {
        return Err(ReadError::Truncated {
            path: data_path.to_path_buf(),
            offset,
            expected,
            actual,
        });
    }
    Ok(Stored {
        file,
        path: data_path.to_path_buf(),
        offset,
        sample,
        endian,
        slope: 1.0,
        inter: 0.0,
    })
}

/// Inflates exactly `expected` bytes of `stream` (the samples of `data_path`, compressed with
/// `what`) into an anonymous temporary file, in 1 MiB steps.
fn spool(
    stream: &mut dyn Read,
    expected: u64,
    data_path: &Path,
    format: &'static str,
    what: &str,
    sample: SampleType,
    endian: Endian,
) -> Result<Stored, ReadError> {
    let temp_err = |e: io::Error| {
        ReadError::io(
            &std::env::temp_dir(),
            io::Error::new(
                e.kind(),
                format!(
                    "writing the inflated samples of {} to a temporary file: {e}",
                    data_path.display()
                ),
            ),
        )
    };
    let mut file = tempfile::tempfile().map_err(temp_err)?;
    let mut buf = vec![0u8; 1 << 20];
    let mut done = 0u64;
    while done < expected {
        let want = (expected - done).min(buf.len() as u64) as usize;
        let n = match stream.read(&mut buf[..want]) {
            Ok(0) => break,
            Ok(n) => n,
            Err(e) if e.kind() == io::ErrorKind::Interrupted => continue,
            Err(e)
                if matches!(
                    e.kind(),
                    io::ErrorKind::InvalidInput | io::ErrorKind::InvalidData
                ) =>
            {
                return Err(ReadError::bad_header(
                    data_path,
                    format,
                    format!("the {what} data is corrupt: {e}"),
                ))
            }
            Err(e) => return Err(ReadError::io(data_path, e)),
        };
        file.write_all(&buf[..n]).map_err(temp_err)?;
        done += n as u64;
    }
    if done != expected {
        return Err(ReadError::Truncated {
            path: data_path.to_path_buf(),
            offset: 0,
            expected,
            actual: done,
        });
    }
    file.flush().map_err(temp_err)?;
    Ok(Stored {
        file,
        path: data_path.to_path_buf(),
        offset: 0,
        sample,
        endian,
        slope: 1.0,
        inter: 0.0,
    })
}

/// A file positioned at `offset`, buffered.
fn reader_at(path: &Path, offset: u64) -> Result<BufReader<File>, ReadError> {
    let mut f = File::open(path).map_err(|e| ReadError::io(path, e))?;
    f.seek(SeekFrom::Start(offset))
        .map_err(|e| ReadError::io(path, e))?;
    Ok(BufReader::new(f))
}

/// Runs a format's decoder on a stand-in file `name` (in `dir`) holding `bytes`.
fn stand_in(dir: &Path, name: String, format: Format, bytes: Vec<u8>) -> Result<Volume, ReadError> {
    let src = SourceFiles {
        origin: dir.join(&name),
        base: dir.to_path_buf(),
        format: Some(format),
        files: vec![(name, bytes)],
    };
    match format {
        Format::Nrrd => nrrd::decode(&src),
        Format::MetaImage => metaimage::decode(&src),
        _ => unreachable!("stand-ins are built for text headers only"),
    }
}

fn file_name(path: &Path) -> String {
    path.file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default()
}

fn parent(path: &Path) -> PathBuf {
    path.parent().map(Path::to_path_buf).unwrap_or_default()
}

// ---------------------------------------------------------------------------------------------
// Raw.

fn open_raw(path: &Path, spec: &RawSpec) -> Result<Opened, ReadError> {
    if spec.channels != 1 && spec.channels != 3 {
        return Err(ReadError::ChannelCount(spec.channels));
    }
    if spec.spacing.iter().any(|s| !(s.is_finite() && *s > 0.0)) {
        return Err(ReadError::Volume(VolumeError::Spacing(spec.spacing)));
    }
    if spec.dims.contains(&0) {
        return Err(ReadError::Volume(VolumeError::ZeroDimension(spec.dims)));
    }
    let size = spec.dtype.size();
    let expected = stored_bytes(path, spec.dims, spec.channels, size)?;
    let sample = match spec.dtype {
        RawDtype::U8 => SampleType::U8,
        RawDtype::U16 => SampleType::U16,
        RawDtype::I16 => SampleType::I16,
        RawDtype::F32 => SampleType::F32,
    };
    // A raw file must be exactly as large as its description (as `read_raw` requires).
    let len = std::fs::metadata(path)
        .map_err(|e| ReadError::io(path, e))?
        .len();
    if len != expected {
        return Err(ReadError::SizeMismatch {
            path: Some(path.to_path_buf()),
            expected,
            actual: len,
            dims: spec.dims,
            channels: spec.channels,
            dtype: spec.dtype,
            bytes_per_sample: size,
        });
    }
    Ok(Opened {
        dims: spec.dims,
        channels: spec.channels,
        spacing: spec.spacing,
        placement: None,
        source: Source::Stored(stored_at(path, 0, expected, sample, spec.endian)?),
    })
}

// ---------------------------------------------------------------------------------------------
// NIfTI-1.

/// Size of a NIfTI-1 header in bytes.
const NIFTI1_HEADER_BYTES: u64 = 348;
/// Largest `vox_offset` accepted (as the NIfTI reader).
const MAX_VOX_OFFSET: u64 = 1 << 30;

fn open_nifti(path: &Path) -> Result<Opened, ReadError> {
    let gz = read_prefix(path, 2)?.starts_with(&[0x1f, 0x8b]);
    let file = reader_at(path, 0)?;
    let mut stream: Box<dyn Read> = if gz {
        Box::new(flate2::bufread::MultiGzDecoder::new(file))
    } else {
        Box::new(file)
    };
    let bad = |reason: String| ReadError::bad_header(path, "NIfTI", reason);
    let mut head = Vec::with_capacity(NIFTI1_HEADER_BYTES as usize);
    (&mut stream)
        .take(NIFTI1_HEADER_BYTES)
        .read_to_end(&mut head)
        .map_err(|e| ReadError::io(path, e))?;
    if head.len() as u64 != NIFTI1_HEADER_BYTES {
        return Err(bad(format!(
            "file holds {} bytes, a NIfTI-1 header needs {NIFTI1_HEADER_BYTES}",
            head.len()
        )));
    }
    // The stand-in: this header with dim[1..=7] = 1, the data right after it (one voxel of
    // zeros; at most 8 bytes, 32 given).
    let big = head[..4] == 348i32.to_be_bytes();
    let mut probe = head.clone();
    for i in 1..8 {
        let one = if big {
            1u16.to_be_bytes()
        } else {
            1u16.to_le_bytes()
        };
        probe[40 + 2 * i..42 + 2 * i].copy_from_slice(&one);
    }
    let at352 = if big {
        352f32.to_be_bytes()
    } else {
        352f32.to_le_bytes()
    };
    probe[108..112].copy_from_slice(&at352);
    probe.extend_from_slice(&[0u8; 4 + 32]);
    let meta = nifti::decode_nifti(path, &probe)?;

    let header =
        ::nifti::NiftiHeader::from_reader(&head[..]).map_err(|source| ReadError::Nifti {
            path: path.to_path_buf(),
            source,
        })?;
    // The stand-in had every size 1: check the real ones as the decoder does.
    let ndim = usize::from(header.dim[0]);
    let mut dims = [1usize; 3];
    for i in 1..=ndim {
        let d = usize::from(header.dim[i]);
        if d == 0 {
            return Err(bad(format!("dim[{i}] is 0, expected at least 1")));
        }
        if i <= 3 {
            dims[i - 1] = d;
        } else if d != 1 {
            return Err(ReadError::unsupported(
                path,
                format!(
                    "dim[{i}] is {d}: only 3D volumes are supported (dim[0] = {ndim}, extra dimensions must be 1); dim = {:?}",
                    &header.dim[1..=ndim]
                ),
            ));
        }
    }
    let sample = match header.datatype {
        2 | 128 => SampleType::U8,
        4 => SampleType::I16,
        8 => SampleType::I32,
        16 => SampleType::F32,
        64 => SampleType::F64,
        256 => SampleType::I8,
        512 => SampleType::U16,
        768 => SampleType::U32,
        1024 => SampleType::I64,
        1280 => SampleType::U64,
        t => {
            return Err(bad(format!(
                "datatype {t} passed the decoder but is unknown here"
            )))
        }
    };
    let channels = meta.channel_count();
    let expected = stored_bytes(path, dims, channels, sample.size())?;
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
    let endian = match header.endianness {
        ::nifti::Endianness::Little => Endian::Little,
        ::nifti::Endianness::Big => Endian::Big,
    };
    let mut stored = if gz {
        let skip = vox_offset - NIFTI1_HEADER_BYTES;
        let skipped = io::copy(&mut (&mut stream).take(skip), &mut io::sink())
            .map_err(|e| ReadError::io(path, e))?;
        if skipped != skip {
            return Err(ReadError::Truncated {
                path: path.to_path_buf(),
                offset: vox_offset,
                expected,
                actual: 0,
            });
        }
        spool(&mut stream, expected, path, "NIfTI", "gzip", sample, endian)?
    } else {
        stored_at(path, vox_offset, expected, sample, endian)?
    };
    if channels == 1
        && header.scl_slope.is_finite()
        && header.scl_slope != 0.0
        && header.scl_inter.is_finite()
    {
        stored.slope = f64::from(header.scl_slope);
        stored.inter = f64::from(header.scl_inter);
    }
    Ok(Opened {
        dims,
        channels,
        spacing: meta.spacing(),
        placement: meta.placement().copied(),
        source: Source::Stored(stored),
    })
}

// ---------------------------------------------------------------------------------------------
// NRRD.

/// The text header of `path`: the bytes up to where a header that the decoders accept can
/// end (each line within [`MAX_TEXT_HEADER`], starting within it), and the file's length.
fn text_header(path: &Path) -> Result<(Vec<u8>, u64), ReadError> {
    let len = std::fs::metadata(path)
        .map_err(|e| ReadError::io(path, e))?
        .len();
    Ok((read_prefix(path, 2 * MAX_TEXT_HEADER as u64 + 2)?, len))
}

/// A NRRD stand-in size: 1 and 3 kept (they decide which axis of a 4D volume holds the
/// channels), 0 kept (refused), any other size 2.
fn nrrd_stand_in_size(s: u64) -> u64 {
    match s {
        0 | 1 | 3 => s,
        _ => 2,
    }
}

fn open_nrrd(path: &Path) -> Result<Opened, ReadError> {
    const FORMAT: &str = "NRRD";
    let bad = |reason: String| ReadError::bad_header(path, FORMAT, reason);
    let (prefix, len) = text_header(path)?;
    if !prefix.starts_with(b"NRRD000") {
        return Err(bad("the file does not start with the magic NRRD000N".into()));
    }
    let (lines, end, found) = header_lines(&prefix, |l| l.is_empty(), false)
        .ok_or_else(|| bad("the header is not UTF-8 text or is longer than 1 MiB".into()))?;

    // The fields that say where the samples are; every other line goes to the stand-in.
    let mut probe = format!("{}\n", lines[0]);
    let mut sizes: Option<Vec<u64>> = None;
    let mut encoding: Option<String> = None;
    let mut sample = None;
    let mut endian = None;
    let mut first_direction_none = None;
    let (mut byte_skip, mut line_skip) = (0i64, 0u64);
    let mut data_file: Option<String> = None;
    for line in lines.iter().skip(1) {
        let keep = match line.split_once(": ") {
            Some(_) if line.starts_with('#') || line.contains(":=") => true,
            None => true, // the decoder names the malformed line
            Some((field, value)) => {
                let value = value.trim();
                match field.trim().to_ascii_lowercase().as_str() {
                    "sizes" => match text::sizes(value) {
                        Some(s) => {
                            sizes = Some(s);
                            false
                        }
                        None => true,
                    },
                    "encoding" => {
                        encoding = Some(value.to_ascii_lowercase());
                        false
                    }
                    "type" => {
                        sample = text::nrrd_type(value);
                        true
                    }
                    "endian" => {
                        endian = match value {
                            "little" => Some(Endian::Little),
                            "big" => Some(Endian::Big),
                            _ => None,
                        };
                        true
                    }
                    "space directions" => {
                        first_direction_none = text::vector_items(value)
                            .map(|d| d.first().is_some_and(Option::is_none));
                        true
                    }
                    "byte skip" => match value.parse() {
                        Ok(v) => {
                            byte_skip = v;
                            false
                        }
                        Err(_) => true,
                    },
                    "line skip" => match value.parse() {
                        Ok(v) => {
                            line_skip = v;
                            false
                        }
                        Err(_) => true,
                    },
                    "data file" | "datafile" => {
                        data_file = Some(value.to_string());
                        if value == "LIST" {
                            break;
                        }
                        false
                    }
                    _ => true,
                }
            }
        };
        if keep {
            probe += line;
            probe.push('\n');
        }
    }
    if let Some(e) = &encoding {
        if matches!(e.as_str(), "ascii" | "text" | "txt") {
            return read_whole(path); // decimal text: no fixed place per voxel
        }
    }
    if let Some(s) = &sizes {
        let s: Vec<String> = s
            .iter()
            .map(|s| nrrd_stand_in_size(*s).to_string())
            .collect();
        probe += &format!("sizes: {}\n", s.join(" "));
    }
    probe += "encoding: raw\n\n";
    let mut probe = probe.into_bytes();
    probe.resize(probe.len() + 3 * 3 * 3 * 3 * 8, 0);
    let meta = stand_in(&parent(path), file_name(path), Format::Nrrd, probe)?;

    // The stand-in's decoder checked dimension (1..=4), one size per axis, the type, the
    // endian for multi-byte samples, and the 4D channel layout.
    let (Some(sizes), Some(sample)) = (sizes, sample) else {
        return Err(bad(
            "the stand-in header was accepted without sizes or type".into(),
        ));
    };
    let channels = meta.channel_count();
    let mut spatial: Vec<usize> = (0..sizes.len()).collect();
    if sizes.len() == 4 {
        if matches!(sizes[0], 1 | 3) && first_direction_none != Some(false) {
            spatial.remove(0);
        } else {
            spatial.pop();
        }
    }
    let mut dims = [1usize; 3];
    for (d, a) in dims.iter_mut().zip(&spatial) {
        *d = usize::try_from(sizes[*a]).unwrap_or(usize::MAX);
    }
    let stand_in_dims = dims.map(|d| nrrd_stand_in_size(d as u64) as usize);
    if meta.dims() != stand_in_dims {
        return Err(bad(format!(
            "sizes {sizes:?}: the decoder laid out the axes as {:?}, this reader as {stand_in_dims:?}",
            meta.dims()
        )));
    }
    let expected = stored_bytes(path, dims, channels, sample.size())?;
    let endian = endian.unwrap_or(Endian::Little);

    // Where the data starts: the data file, or just past the blank line.
    let (data_path, mut offset) = match &data_file {
        Some(f) => {
            if f == "LIST" || f.contains('%') || f.split_whitespace().count() > 1 {
                return Err(ReadError::unsupported(
                    path,
                    format!("data file {f:?}: only a single data file is supported (not LIST or a file name pattern)"),
                ));
            }
            (parent(path).join(f), 0u64)
        }
        None if found => (path.to_path_buf(), end as u64),
        None => {
            return Err(bad(
                "no blank line ends the header and no `data file` is named".into(),
            ))
        }
    };
    let data_len = if data_file.is_some() {
        std::fs::metadata(&data_path)
            .map_err(|e| ReadError::io(&data_path, e))?
            .len()
    } else {
        len
    };
    if line_skip > 0 {
        offset = skip_lines(&data_path, offset, line_skip).map_err(|e| match e {
            Some(e) => ReadError::io(&data_path, e),
            None => bad(format!("line skip {line_skip} passes the end of the data")),
        })?;
    }
    let stored = match encoding.as_deref().unwrap_or("") {
        "raw" => {
            let start = match byte_skip {
                -1 => data_len
                    .checked_sub(expected)
                    .filter(|s| *s >= offset)
                    .ok_or(ReadError::Truncated {
                        path: data_path.clone(),
                        offset,
                        expected,
                        actual: data_len.saturating_sub(offset),
                    })?,
                s if s >= 0 => offset.saturating_add(s as u64),
                s => return Err(bad(format!("byte skip {s}; -1 or ≥ 0 allowed"))),
            };
            stored_at(&data_path, start, expected, sample, endian)?
        }
        "gzip" | "gz" => {
            if byte_skip != 0 {
                return Err(ReadError::unsupported(path, "byte skip with gzip encoding"));
            }
            let mut z = flate2::bufread::MultiGzDecoder::new(reader_at(&data_path, offset)?);
            spool(&mut z, expected, &data_path, FORMAT, "gzip", sample, endian)?
        }
        "" => return Err(bad("no `encoding` field".into())),
        e => {
            return Err(ReadError::unsupported(
                path,
                format!("encoding {e:?}; supported are raw, gzip and ascii"),
            ))
        }
    };
    Ok(Opened {
        dims,
        channels,
        spacing: meta.spacing(),
        placement: meta.placement().copied(),
        source: Source::Stored(stored),
    })
}

/// The offset just past `lines` newlines from `offset` in `path`; `Err(None)` when the file
/// ends first. Scans without holding a line.
fn skip_lines(path: &Path, offset: u64, lines: u64) -> Result<u64, Option<io::Error>> {
    let mut f = File::open(path).map_err(Some)?;
    f.seek(SeekFrom::Start(offset)).map_err(Some)?;
    let mut r = BufReader::new(f);
    let (mut pos, mut left) = (offset, lines);
    while left > 0 {
        let buf = r.fill_buf().map_err(Some)?;
        if buf.is_empty() {
            return Err(None);
        }
        let mut used = buf.len();
        for (i, b) in buf.iter().enumerate() {
            if *b == b'\n' {
                left -= 1;
                if left == 0 {
                    used = i + 1;
                    break;
                }
            }
        }
        r.consume(used);
        pos += used as u64;
    }
    Ok(pos)
}

// ---------------------------------------------------------------------------------------------
// MetaImage.

fn open_metaimage(path: &Path) -> Result<Opened, ReadError> {
    const FORMAT: &str = "MetaImage";
    let bad = |reason: String| ReadError::bad_header(path, FORMAT, reason);
    let (prefix, len) = text_header(path)?;
    let (lines, end, found) = header_lines(
        &prefix,
        |l| {
            l.split_once('=')
                .is_some_and(|(k, _)| k.trim().eq_ignore_ascii_case("ElementDataFile"))
        },
        true,
    )
    .ok_or_else(|| bad("the header is not UTF-8 text or is longer than 1 MiB".into()))?;
    if !found {
        return Err(bad("no ElementDataFile line ends the header".into()));
    }
    let mut fields: Vec<(String, String)> = Vec::new();
    let mut probe = String::new();
    const REPLACED: &[&str] = &[
        "DimSize",
        "CompressedData",
        "CompressedDataSize",
        "HeaderSize",
        "ElementDataFile",
    ];
    for line in &lines {
        if let Some((k, v)) = line.split_once('=') {
            let k = k.trim();
            fields.push((k.to_string(), v.trim().to_string()));
            if REPLACED.iter().any(|r| r.eq_ignore_ascii_case(k)) {
                continue;
            }
        }
        probe += line;
        probe.push('\n');
    }
    let get = |keys: &[&str]| -> Option<(String, String)> {
        keys.iter().find_map(|k| {
            fields
                .iter()
                .find(|(f, _)| f.eq_ignore_ascii_case(k))
                .cloned()
        })
    };
    let ndims = get(&["NDims"])
        .and_then(|(_, v)| v.parse::<usize>().ok())
        .filter(|n| (1..=3).contains(n));
    let sizes = match (get(&["DimSize"]), ndims) {
        (Some((_, v)), Some(n)) => match text::sizes(&v).filter(|s| s.len() == n) {
            Some(s) => {
                probe += &format!("DimSize = {}\n", vec!["1"; n].join(" "));
                Some(s)
            }
            None => {
                probe += &format!("DimSize = {v}\n"); // refused by the decoder
                None
            }
        },
        (Some((_, v)), None) => {
            probe += &format!("DimSize = {v}\n");
            None
        }
        (None, _) => None,
    };
    probe += "ElementDataFile = LOCAL\n";
    let mut probe = probe.into_bytes();
    probe.resize(probe.len() + 3 * 8, 0);
    let meta = stand_in(&parent(path), file_name(path), Format::MetaImage, probe)?;

    // The stand-in's decoder checked NDims, the DimSize count, the element type and channels,
    // BinaryData and the byte order.
    let Some(sizes) = sizes else {
        return Err(bad(
            "the stand-in header was accepted without DimSize".into()
        ));
    };
    let mut dims = [1usize; 3];
    for (d, s) in dims.iter_mut().zip(&sizes) {
        *d = usize::try_from(*s).unwrap_or(usize::MAX);
    }
    let channels = meta.channel_count();
    let ty = get(&["ElementType"]).map(|(_, t)| t.to_ascii_uppercase());
    let sample = match ty.as_deref() {
        Some("MET_CHAR") => SampleType::I8,
        Some("MET_UCHAR") => SampleType::U8,
        Some("MET_SHORT") => SampleType::I16,
        Some("MET_USHORT") => SampleType::U16,
        Some("MET_INT" | "MET_LONG") => SampleType::I32,
        Some("MET_UINT" | "MET_ULONG") => SampleType::U32,
        Some("MET_LONG_LONG") => SampleType::I64,
        Some("MET_ULONG_LONG") => SampleType::U64,
        Some("MET_FLOAT") => SampleType::F32,
        Some("MET_DOUBLE") => SampleType::F64,
        t => {
            return Err(bad(format!(
                "ElementType {t:?} passed the decoder but is unknown here"
            )))
        }
    };
    let bool_field = |keys: &[&str]| -> Result<Option<bool>, ReadError> {
        match get(keys) {
            None => Ok(None),
            Some((k, v)) => match v.to_ascii_lowercase().as_str() {
                "true" | "1" => Ok(Some(true)),
                "false" | "0" => Ok(Some(false)),
                _ => Err(bad(format!("{k} = {v:?} is not True or False"))),
            },
        }
    };
    let endian = match bool_field(&["BinaryDataByteOrderMSB", "ElementByteOrderMSB"])? {
        Some(true) => Endian::Big,
        _ => Endian::Little,
    };
    let compressed = bool_field(&["CompressedData"])?.unwrap_or(false);
    let header_size = match get(&["HeaderSize"]) {
        None => 0i64,
        Some((_, v)) => v
            .parse::<i64>()
            .ok()
            .filter(|s| *s >= -1)
            .ok_or_else(|| bad(format!("HeaderSize = {v:?}; -1 or ≥ 0 expected")))?,
    };
    let expected = stored_bytes(path, dims, channels, sample.size())?;
    let (data_path, base, data_len) = match get(&["ElementDataFile"]) {
        Some((_, v)) if v.eq_ignore_ascii_case("LOCAL") => (path.to_path_buf(), end as u64, len),
        Some((_, v)) => {
            if v.eq_ignore_ascii_case("LIST") || v.contains('%') || v.split_whitespace().count() > 1
            {
                return Err(ReadError::unsupported(
                    path,
                    format!("ElementDataFile = {v}: only LOCAL or a single data file is supported (not LIST or a file name pattern)"),
                ));
            }
            let p = parent(path).join(&v);
            let l = std::fs::metadata(&p)
                .map_err(|e| ReadError::io(&p, e))?
                .len();
            (p, 0, l)
        }
        None => return Err(bad("no ElementDataFile".into())),
    };
    let stored = if compressed {
        if header_size != 0 {
            return Err(ReadError::unsupported(
                path,
                "HeaderSize with CompressedData",
            ));
        }
        let mut z = flate2::bufread::ZlibDecoder::new(reader_at(&data_path, base)?);
        spool(&mut z, expected, &data_path, FORMAT, "zlib", sample, endian)?
    } else {
        let start = if header_size == -1 {
            data_len
                .checked_sub(expected)
                .filter(|s| *s >= base)
                .ok_or(ReadError::Truncated {
                    path: data_path.clone(),
                    offset: 0,
                    expected,
                    actual: data_len.saturating_sub(base),
                })?
        } else {
            base.saturating_add(header_size as u64)
        };
        stored_at(&data_path, start, expected, sample, endian)?
    };
    Ok(Opened {
        dims,
        channels,
        spacing: meta.spacing(),
        placement: meta.placement().copied(),
        source: Source::Stored(stored),
    })
}
