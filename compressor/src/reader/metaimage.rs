//! MetaImage (ITK's `.mha` with the data after the header, `.mhd` with the data in the file
//! named by `ElementDataFile`): `MET_(U)CHAR`/`SHORT`/`INT`/`LONG_LONG`, `MET_FLOAT`,
//! `MET_DOUBLE`, 1 or 3 channels, raw or zlib-compressed (`CompressedData = True`), either
//! byte order, `HeaderSize` (incl. -1: data at the end of the file), 1 to 4 dimensions (ITK
//! writes `NDims = 4` with a last size of 1 for one volume; a last size of more is a time
//! series, each time point's volume after the previous one). The data file's name may hold
//! spaces, as MetaIO reads it; the samples may be cut into many files (`LIST [DIM]` and the
//! names on the lines after it, or a pattern `slice%03d.raw MIN MAX STEP`), each file with its
//! own `HeaderSize` or its own zlib stream, as MetaIO reads them. Spacing from
//! `ElementSpacing` (else `ElementSize`), placement from `Offset` (or `Origin`, `Position`) and
//! `TransformMatrix` (or `Rotation`, `Orientation`), whose rows are the axis directions in ITK's
//! LPS frame, as ITK reads them (`AnatomicalOrientation` is informative only, and ignored as
//! ITK ignores it).
//!
//! The header is parsed by hand: it is a short list of `Key = Value` lines, and there is no
//! maintained Rust MetaImage crate.

use std::path::{Path, PathBuf};

use super::text::{self, grid_from_vectors, header_lines, origin3};
use super::{
    deinterleave, in_piece, join_pieces, read_exact_or_truncated, voxel_count, Endian, ReadError,
    SampleType, SourceFiles,
};
use wavesplat_codec::volume::Volume;

const FORMAT: &str = "MetaImage";

/// Keys that may open a MetaImage header (for content sniffing).
const FIRST_KEYS: &[&str] = &[
    "objecttype",
    "ndims",
    "comment",
    "objectsubtype",
    "formtypename",
];

/// Whether `head` starts with a MetaImage header line (`ObjectType = …`, `NDims = …`).
pub(crate) fn looks_like_header(head: &[u8]) -> bool {
    let line_end = head.iter().take(256).position(|b| *b == b'\n');
    let Some(end) = line_end else { return false };
    let Ok(line) = std::str::from_utf8(&head[..end]) else {
        return false;
    };
    match line.split_once('=') {
        Some((k, _)) => FIRST_KEYS.contains(&k.trim().to_ascii_lowercase().as_str()),
        None => false,
    }
}

#[derive(Debug, Default)]
struct Header {
    fields: Vec<(String, String)>,
    /// Offset of the data after the `ElementDataFile = LOCAL` line.
    data_offset: usize,
}

impl Header {
    fn get(&self, keys: &[&str]) -> Option<(&str, &str)> {
        keys.iter().find_map(|k| {
            self.fields
                .iter()
                .find(|(f, _)| f.eq_ignore_ascii_case(k))
                .map(|(f, v)| (f.as_str(), v.as_str()))
        })
    }
}

fn bad(path: &Path, reason: impl Into<String>) -> ReadError {
    ReadError::bad_header(path, FORMAT, reason)
}

fn parse_header(path: &Path, bytes: &[u8]) -> Result<Header, ReadError> {
    let (lines, end, found) = header_lines(
        bytes,
        |l| {
            l.split_once('=')
                .is_some_and(|(k, _)| k.trim().eq_ignore_ascii_case("ElementDataFile"))
        },
        true,
    )
    .ok_or_else(|| bad(path, "the header is not UTF-8 text or is longer than 1 MiB"))?;
    if !found {
        return Err(bad(path, "no ElementDataFile line ends the header"));
    }
    let mut h = Header {
        data_offset: end,
        ..Header::default()
    };
    for (n, line) in lines.iter().enumerate() {
        if line.trim().is_empty() {
            continue;
        }
        let Some((k, v)) = line.split_once('=') else {
            return Err(bad(
                path,
                format!("line {}: {line:?} is not `Key = Value`", n + 1),
            ));
        };
        h.fields.push((k.trim().to_string(), v.trim().to_string()));
    }
    Ok(h)
}

/// The files `ElementDataFile` names (`None`: `LOCAL`, the data follows the header): one
/// name, `LIST` and the names on the lines after it (`bytes` is the header file), or a
/// pattern, as MetaIO reads them.
fn data_file_names(
    path: &Path,
    h: &Header,
    bytes: &[u8],
) -> Result<Option<text::DataFileNames>, ReadError> {
    let (_, v) = h
        .get(&["ElementDataFile"])
        .ok_or_else(|| bad(path, "no ElementDataFile"))?;
    if v.eq_ignore_ascii_case("LOCAL") {
        return Ok(None);
    }
    let listed = if text::is_file_list(v) {
        // The names run to the end of the file: all of it must lie within what every reader
        // of the header reads of it.
        if bytes.len() > text::MAX_TEXT_HEADER {
            return Err(bad(
                path,
                format!(
                    "ElementDataFile = {v}: the header and its file names are longer than {} bytes",
                    text::MAX_TEXT_HEADER
                ),
            ));
        }
        let rest = bytes.get(h.data_offset..).unwrap_or(&[]);
        header_lines(rest, |_| false, false)
            .ok_or_else(|| {
                bad(
                    path,
                    "the file names after ElementDataFile = LIST are not UTF-8 text or are longer than 1 MiB",
                )
            })?
            .0
    } else {
        Vec::new()
    };
    text::data_file_names(v, &listed)
        .map(Some)
        .map_err(|e| bad(path, format!("ElementDataFile = {v}: {e}")))
}

/// The data files the header `bytes` of `path` names (`None`: `LOCAL`), and the length of each
/// one's piece of the `total` bytes of samples (for a list or a pattern: each file one slice
/// of the slowest axis, or of the dimension `LIST` gives).
pub(crate) fn data_pieces(
    path: &Path,
    bytes: &[u8],
    total: u64,
) -> Result<Option<(Vec<String>, u64)>, ReadError> {
    pieces_of(path, &parse_header(path, bytes)?, bytes, total)
}

/// [`data_pieces`] of a parsed header (`bytes`: the file's, holding a `LIST`'s names).
fn pieces_of(
    path: &Path,
    h: &Header,
    bytes: &[u8],
    total: u64,
) -> Result<Option<(Vec<String>, u64)>, ReadError> {
    let Some(d) = data_file_names(path, h, bytes)? else {
        return Ok(None);
    };
    let sizes = h
        .get(&["DimSize"])
        .and_then(|(_, v)| text::sizes(v))
        .unwrap_or_default();
    let piece = text::piece_bytes(&sizes, &d, total, false)
        .map_err(|e| bad(path, format!("ElementDataFile: {e}")))?;
    Ok(Some((d.names, piece)))
}

/// The names of the data files a detached header refers to (relative to its directory).
pub(crate) fn data_files(path: &Path, bytes: &[u8]) -> Result<Vec<String>, ReadError> {
    let h = parse_header(path, bytes)?;
    Ok(data_file_names(path, &h, bytes)?.map_or_else(Vec::new, |d| d.names))
}

/// The time points of a MetaImage file of `NDims = 4` whose last size is more than 1 (ITK
/// writes a 4D series so, the time points one after another); `None` for any other file. The
/// format gives the time axis no unit, so no time step is read.
pub(crate) fn series_points(path: &Path, bytes: &[u8]) -> Result<Option<usize>, ReadError> {
    let h = parse_header(path, bytes)?;
    let sizes = match (h.get(&["NDims"]), h.get(&["DimSize"])) {
        (Some((_, "4")), Some((_, d))) => text::sizes(d).filter(|s| s.len() == 4),
        _ => None,
    };
    Ok(sizes
        .map(|s| usize::try_from(s[3]).unwrap_or(usize::MAX))
        .filter(|t| *t > 1))
}

fn bool_field(path: &Path, h: &Header, keys: &[&str]) -> Result<Option<bool>, ReadError> {
    match h.get(keys) {
        None => Ok(None),
        Some((k, v)) => match v.to_ascii_lowercase().as_str() {
            "true" | "1" => Ok(Some(true)),
            "false" | "0" => Ok(Some(false)),
            _ => Err(bad(path, format!("{k} = {v:?} is not True or False"))),
        },
    }
}

fn numbers_field(
    path: &Path,
    h: &Header,
    keys: &[&str],
    n: usize,
) -> Result<Option<Vec<f64>>, ReadError> {
    match h.get(keys) {
        None => Ok(None),
        Some((k, v)) => match text::numbers(v) {
            Some(x) if x.len() >= n => Ok(Some(x)),
            _ => Err(bad(path, format!("{k} = {v:?}: {n} numbers expected"))),
        },
    }
}

/// Decodes a MetaImage volume from its gathered files.
pub(crate) fn decode(src: &SourceFiles) -> Result<Volume, ReadError> {
    let (name, header_bytes) = &src.files[0];
    let path = src.path_of(name);
    let h = parse_header(&path, header_bytes)?;
    if let Some((_, t)) = h.get(&["ObjectType"]) {
        if !t.eq_ignore_ascii_case("Image") {
            return Err(ReadError::unsupported(
                &path,
                format!("ObjectType = {t}; only Image"),
            ));
        }
    }
    let ndims = match h.get(&["NDims"]) {
        Some((_, v)) => v
            .parse::<usize>()
            .ok()
            .filter(|n| (1..=4).contains(n))
            .ok_or_else(|| bad(&path, format!("NDims = {v:?}; 1, 2, 3 or 4 supported")))?,
        None => return Err(bad(&path, "no NDims")),
    };
    // The spatial axes; a fourth is time.
    let sdims = ndims.min(3);
    let (_, dim_str) = h
        .get(&["DimSize"])
        .ok_or_else(|| bad(&path, "no DimSize"))?;
    let sizes = text::sizes(dim_str)
        .filter(|s| s.len() == ndims)
        .ok_or_else(|| {
            bad(
                &path,
                format!("DimSize = {dim_str:?}: {ndims} sizes expected"),
            )
        })?;
    let mut dims = [1usize; 3];
    for (d, s) in dims.iter_mut().zip(&sizes) {
        *d = usize::try_from(*s).unwrap_or(usize::MAX);
    }
    match sizes.get(3) {
        Some(0) => return Err(bad(&path, format!("DimSize = {dim_str:?}: a size of 0"))),
        Some(t) if *t > 1 => {
            return Err(ReadError::TimeSeries {
                path: path.clone(),
                points: usize::try_from(*t).unwrap_or(usize::MAX),
            })
        }
        _ => {}
    }
    let voxels = voxel_count(dims).map_err(|e| ReadError::volume(&path, e))?;
    let channels = match h.get(&["ElementNumberOfChannels"]) {
        None => 1,
        Some((_, "1")) => 1,
        Some((_, "3")) => 3,
        Some((_, v)) => {
            return Err(ReadError::unsupported(
                &path,
                format!("ElementNumberOfChannels = {v}; 1 or 3 supported"),
            ))
        }
    };
    let (_, ty) = h
        .get(&["ElementType"])
        .ok_or_else(|| bad(&path, "no ElementType"))?;
    let sample = match ty.to_ascii_uppercase().as_str() {
        "MET_CHAR" => SampleType::I8,
        "MET_UCHAR" => SampleType::U8,
        "MET_SHORT" => SampleType::I16,
        "MET_USHORT" => SampleType::U16,
        "MET_INT" | "MET_LONG" => SampleType::I32,
        "MET_UINT" | "MET_ULONG" => SampleType::U32,
        "MET_LONG_LONG" => SampleType::I64,
        "MET_ULONG_LONG" => SampleType::U64,
        "MET_FLOAT" => SampleType::F32,
        "MET_DOUBLE" => SampleType::F64,
        t => {
            return Err(ReadError::unsupported(
                &path,
                format!("ElementType = {t}; supported are MET_(U)CHAR, MET_(U)SHORT, MET_(U)INT, MET_(U)LONG, MET_(U)LONG_LONG, MET_FLOAT, MET_DOUBLE"),
            ))
        }
    };
    if bool_field(&path, &h, &["BinaryData"])? == Some(false) {
        return Err(ReadError::unsupported(
            &path,
            "BinaryData = False (ASCII data)",
        ));
    }
    let msb = bool_field(
        &path,
        &h,
        &["BinaryDataByteOrderMSB", "ElementByteOrderMSB"],
    )?;
    let endian = if msb == Some(true) {
        Endian::Big
    } else {
        Endian::Little
    };
    let compressed = bool_field(&path, &h, &["CompressedData"])?.unwrap_or(false);

    // Geometry.
    let spacing = numbers_field(&path, &h, &["ElementSpacing", "ElementSize"], ndims)?;
    let matrix = numbers_field(
        &path,
        &h,
        &["TransformMatrix", "Rotation", "Orientation"],
        ndims * ndims,
    )?;
    let origin = numbers_field(&path, &h, &["Offset", "Origin", "Position"], ndims)?;
    let mut vectors = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    if let Some(m) = &matrix {
        if m.len() != ndims * ndims {
            return Err(bad(
                &path,
                format!(
                    "TransformMatrix has {} numbers, {} expected",
                    m.len(),
                    ndims * ndims
                ),
            ));
        }
        // Of a 4D matrix, the spatial 3×3 block; time must not mix with space.
        let mixed =
            (0..ndims).any(|a| (0..ndims).any(|c| (a < 3) != (c < 3) && m[a * ndims + c] != 0.0));
        if mixed {
            return Err(ReadError::unsupported(
                &path,
                format!("TransformMatrix = {m:?} mixes the time axis with space"),
            ));
        }
        for a in 0..sdims {
            for c in 0..3 {
                vectors[a][c] = if c < sdims { m[a * ndims + c] } else { 0.0 };
            }
        }
    }
    let mut steps = [1.0f64; 3];
    if let Some(s) = &spacing {
        if s.len() != ndims {
            return Err(bad(
                &path,
                format!("ElementSpacing has {} numbers, {ndims} expected", s.len()),
            ));
        }
        for a in 0..sdims {
            if !(s[a].is_finite() && s[a] > 0.0) {
                return Err(bad(
                    &path,
                    format!("ElementSpacing {s:?}: axis {a} must be finite and positive"),
                ));
            }
            steps[a] = s[a];
        }
    }
    for a in 0..3 {
        for c in 0..3 {
            vectors[a][c] *= steps[a];
        }
    }
    let origin = match &origin {
        Some(o) => {
            let mut o3 = [0.0; 3];
            o3[..sdims].copy_from_slice(&o[..sdims]);
            Some(origin3(&path, FORMAT, "Offset", &o3)?)
        }
        None => None,
    };
    let geometry_given = matrix.is_some() || origin.is_some();
    let (spacing, placement) = grid_from_vectors(
        &path,
        FORMAT,
        "ElementSpacing and TransformMatrix",
        vectors,
        origin,
        geometry_given.then_some([1.0, 1.0, 1.0]),
    )?;

    // Data.
    let expected = voxels
        .checked_mul(channels * sample.size())
        .ok_or(ReadError::TooLarge {
            dims,
            channels,
            bytes_per_sample: sample.size(),
        })?;
    let header_size = match h.get(&["HeaderSize"]) {
        None => 0i64,
        Some((_, v)) => v
            .parse::<i64>()
            .ok()
            .filter(|s| *s >= -1)
            .ok_or_else(|| bad(&path, format!("HeaderSize = {v:?}; -1 or ≥ 0 expected")))?,
    };
    if compressed && header_size != 0 {
        return Err(ReadError::unsupported(
            &path,
            "HeaderSize with CompressedData",
        ));
    }
    // The data: after the header, or in the data files, each holding its piece of the samples
    // (after its own HeaderSize; each compressed on its own), as MetaIO reads them.
    let (pieces, piece): (Vec<(PathBuf, &[u8])>, usize) =
        match pieces_of(&path, &h, header_bytes, expected as u64)? {
            None => (
                vec![(path.clone(), &header_bytes[h.data_offset..])],
                expected,
            ),
            Some((names, piece)) => (src.data_files(&names, FORMAT)?, piece as usize),
        };
    let data_path = pieces[0].0.clone();
    let raw = join_pieces(&pieces, |p, data| {
        piece_of(p, data, piece, compressed, header_size)
    })?;
    let raw: &[u8] = &raw;
    let planar = deinterleave(raw, sample, endian, channels, 1.0, 0.0);
    let v = Volume::new(dims, spacing, planar).map_err(|e| {
        let e = ReadError::volume(&data_path, e);
        in_piece(
            e,
            &pieces,
            piece,
            [dims[0], dims[1]],
            channels,
            sample.size(),
        )
    })?;
    match placement {
        Some(p) => v.with_placement(p).map_err(|e| ReadError::volume(&path, e)),
        None => Ok(v),
    }
}

/// The `piece` bytes of samples a data file `data` (read from `data_path`) holds: inflated
/// from its zlib stream, or after `header_size` bytes (-1: the last `piece` bytes).
fn piece_of<'a>(
    data_path: &Path,
    data: &'a [u8],
    piece: usize,
    compressed: bool,
    header_size: i64,
) -> Result<std::borrow::Cow<'a, [u8]>, ReadError> {
    if compressed {
        let mut z = flate2::bufread::ZlibDecoder::new(data);
        let bytes = read_exact_or_truncated(&mut z, piece, data.len(), data_path, 0).map_err(
            |e| match e {
                ReadError::Io { source, .. } => {
                    bad(data_path, format!("the zlib data is corrupt: {source}"))
                }
                e => e,
            },
        )?;
        return Ok(std::borrow::Cow::Owned(bytes));
    }
    let skip = if header_size == -1 {
        data.len().checked_sub(piece).ok_or(ReadError::Truncated {
            path: data_path.to_path_buf(),
            offset: 0,
            expected: piece as u64,
            actual: data.len() as u64,
        })?
    } else {
        usize::try_from(header_size).unwrap_or(usize::MAX)
    };
    let body = data.get(skip..).unwrap_or(&[]);
    if body.len() < piece {
        return Err(ReadError::Truncated {
            path: data_path.to_path_buf(),
            offset: skip as u64,
            expected: piece as u64,
            actual: body.len() as u64,
        });
    }
    Ok(std::borrow::Cow::Borrowed(&body[..piece]))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::reader::read_volume;
    use wavesplat_codec::volume::{Placement, VolumeError};
    use wavesplat_fixtures::{self as fixtures, Layout};

    #[test]
    fn round_trips_attached_detached_raw_and_compressed() {
        let dir = tempfile::tempdir().unwrap();
        let dims = [6, 5, 4];
        let n = 120;
        let p = Placement {
            origin: [100.0, -50.5, 0.25],
            directions: [[0.6, 0.8, 0.0], [-0.8, 0.6, 0.0], [0.0, 0.0, 1.0]],
        };
        for (layout, scale) in [(Layout::U8, 1.0), (Layout::I16, -7.0), (Layout::F32, 0.125)] {
            let data: Vec<f32> = (0..n).map(|i| ((i * 13) % 97) as f32 * scale).collect();
            let v = Volume::new(dims, [0.5, 0.75, 3.0], vec![data])
                .unwrap()
                .with_placement(p)
                .unwrap();
            for compressed in [false, true] {
                for detached in [false, true] {
                    let name = format!("m_{layout:?}_{compressed}_{detached}");
                    let path = fixtures::write_metaimage(
                        dir.path(),
                        &name,
                        &v,
                        layout,
                        compressed,
                        detached,
                    );
                    let back = read_volume(&path, None).unwrap();
                    assert_eq!(back.channel(0), v.channel(0), "{name}");
                    assert_eq!(back.spacing(), v.spacing(), "{name}");
                    let b = back.placement().unwrap();
                    for i in 0..3 {
                        assert!((b.origin[i] - p.origin[i]).abs() < 1e-9);
                        for j in 0..3 {
                            assert!((b.directions[i][j] - p.directions[i][j]).abs() < 1e-9);
                        }
                    }
                }
            }
        }
        // RGB.
        let rgb: Vec<Vec<f32>> = (0..3)
            .map(|c| (0..n).map(|i| ((i + 40 * c) % 256) as f32).collect())
            .collect();
        let v = Volume::new(dims, [1.0; 3], rgb).unwrap();
        let path = fixtures::write_metaimage(dir.path(), "rgb", &v, Layout::U8, false, false);
        let back = read_volume(&path, None).unwrap();
        assert_eq!(back.channels(), v.channels());
    }

    #[test]
    fn bad_and_hostile_headers_are_errors() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("bad.mha");
        let base = "ObjectType = Image\nNDims = 3\nElementType = MET_UCHAR\n";
        let cases: Vec<(String, Vec<u8>)> = vec![
            (
                format!("{base}DimSize = 100000 100000 100000\n"),
                vec![0; 8],
            ),
            (format!("{base}DimSize = 4096 4096 100\n"), vec![0; 8]),
            (format!("{base}DimSize = 2 0 2\n"), vec![0; 8]),
            (format!("{base}DimSize = 2 2\n"), vec![0; 8]),
            (
                format!("{base}DimSize = 2 2 2\nElementSpacing = 1 0 1\n"),
                vec![0; 8],
            ),
            (
                format!("{base}DimSize = 2 2 2\nElementSpacing = 1 nan 1\n"),
                vec![0; 8],
            ),
            (
                format!("{base}DimSize = 2 2 2\nElementSpacing = 1 -1 1\n"),
                vec![0; 8],
            ),
            (
                format!("{base}DimSize = 2 2 2\nElementSpacing = 1e39 1 1\n"),
                vec![0; 8],
            ),
            (
                format!("{base}DimSize = 2 2 2\nOffset = 0 nan 0\n"),
                vec![0; 8],
            ),
            (
                format!("{base}DimSize = 2 2 2\nTransformMatrix = 1 0 0 0 1 0 0 0 0\n"),
                vec![0; 8],
            ),
            (
                format!("{base}DimSize = 2 2 2\nTransformMatrix = 1 0 0 0.5 1 0 0 0 1\n"),
                vec![0; 8],
            ),
            (
                format!("{base}DimSize = 2 2 2\nTransformMatrix = 1 0 0\n"),
                vec![0; 8],
            ),
            (format!("{base}DimSize = 2 2 2\n"), vec![0; 7]),
            (
                format!("{base}DimSize = 2 2 2\nHeaderSize = 5\n"),
                vec![0; 8],
            ),
            (
                format!("{base}DimSize = 2 2 2\nHeaderSize = -3\n"),
                vec![0; 8],
            ),
            (
                format!("{base}DimSize = 2 2 2\nCompressedData = True\n"),
                vec![1, 2, 3],
            ),
            (
                format!("{base}DimSize = 2 2 2\nCompressedData = maybe\n"),
                vec![0; 8],
            ),
            (
                format!("{base}DimSize = 2 2 2\nElementNumberOfChannels = 4\n"),
                vec![0; 32],
            ),
            (
                "ObjectType = Image\nNDims = 3\nDimSize = 2 2 2\nElementType = MET_FLOAT_ARRAY\n"
                    .into(),
                vec![0; 32],
            ),
            (
                "ObjectType = Image\nNDims = 4\nDimSize = 2 2 2 2\nElementType = MET_UCHAR\n"
                    .into(),
                vec![0; 16],
            ),
            (
                "ObjectType = Image\nDimSize = 2 2 2\nElementType = MET_UCHAR\n".into(),
                vec![0; 8],
            ),
            (
                "ObjectType = Image\nNDims = 3\nElementType = MET_UCHAR\n".into(),
                vec![0; 8],
            ),
            (
                format!("{base}DimSize = 2 2 2\nthis line has no equals sign\n"),
                vec![0; 8],
            ),
        ];
        for (fields, data) in cases {
            let mut b = format!("{fields}ElementDataFile = LOCAL\n").into_bytes();
            b.extend_from_slice(&data);
            std::fs::write(&p, &b).unwrap();
            let r = read_volume(&p, None);
            assert!(r.is_err(), "accepted: {fields}");
            assert!(r.unwrap_err().to_string().contains("bad.mha"), "{fields}");
        }
        // No ElementDataFile at all; a missing detached file; a file list.
        std::fs::write(&p, format!("{base}DimSize = 1 1 1\n")).unwrap();
        assert!(matches!(
            read_volume(&p, None),
            Err(ReadError::BadHeader { .. })
        ));
        let h = dir.path().join("d.mhd");
        std::fs::write(
            &h,
            format!("{base}DimSize = 1 1 1\nElementDataFile = gone.raw\n"),
        )
        .unwrap();
        assert!(matches!(read_volume(&h, None), Err(ReadError::Io { .. })));
        std::fs::write(
            &h,
            format!("{base}DimSize = 1 1 1\nElementDataFile = LIST\n"),
        )
        .unwrap();
        let e = read_volume(&h, None).unwrap_err();
        assert!(matches!(e, ReadError::BadHeader { .. }), "{e}");
        assert!(e.to_string().contains("LIST names no file"), "{e}");
        // NaN samples.
        let mut b =
            b"NDims = 1\nDimSize = 1\nElementType = MET_FLOAT\nElementDataFile = LOCAL\n".to_vec();
        b.extend_from_slice(&f32::NAN.to_le_bytes());
        std::fs::write(&p, &b).unwrap();
        assert!(matches!(
            read_volume(&p, None),
            Err(ReadError::InvalidVolume {
                problem: VolumeError::NonFinite { .. },
                ..
            })
        ));
        // HeaderSize -1 takes the data from the end; big-endian shorts.
        let mut b = b"NDims = 1\nDimSize = 2\nElementType = MET_SHORT\nBinaryDataByteOrderMSB = True\nHeaderSize = -1\nElementDataFile = LOCAL\nxyz".to_vec();
        b.extend_from_slice(&(-2i16).to_be_bytes());
        b.extend_from_slice(&300i16.to_be_bytes());
        std::fs::write(&p, &b).unwrap();
        let v = read_volume(&p, None).unwrap();
        assert_eq!(v.channel(0), &[-2.0, 300.0]);
        assert!(v.placement().is_none());
    }

    /// `ElementDataFile = CT scan.raw`: MetaIO reads any value but LOCAL, LIST or a pattern as
    /// one file name, spaces included; it reads through the listing that hashes it, gathering,
    /// decoding and region reads.
    #[test]
    fn a_data_file_name_may_hold_spaces() {
        use crate::reader::region::RegionReader;
        use crate::reader::{decode_source, SourceFiles, SourceListing};
        let dir = tempfile::tempdir().unwrap();
        let data: Vec<u8> = (0..24u8).collect();
        std::fs::write(dir.path().join("CT scan.raw"), &data).unwrap();
        let h = dir.path().join("CT scan.mhd");
        let base = "ObjectType = Image\nNDims = 3\nDimSize = 2 3 4\nElementType = MET_UCHAR\n";
        std::fs::write(&h, format!("{base}ElementDataFile = CT scan.raw\n")).unwrap();
        let v = read_volume(&h, None).unwrap();
        let want: Vec<f32> = data.iter().map(|b| f32::from(*b)).collect();
        assert_eq!(v.channel(0), &want[..]);
        let listing = SourceListing::list(&h, None).unwrap();
        assert_eq!(listing.files[1].0, "CT scan.raw");
        let src = SourceFiles::gather(&h, None).unwrap();
        assert_eq!(src.get("CT scan.raw"), Some(&data[..]));
        let back = SourceFiles::from_bytes(src.to_bytes(), &h).unwrap();
        assert_eq!(decode_source(&back, None).unwrap(), v);
        let r = RegionReader::open(&h, None).unwrap();
        assert_eq!(r.read_region([0; 3], [2, 3, 4]).unwrap(), v);
        // A list or a pattern whose files are too few for the sizes is refused, saying so
        // (`tests/data_files.rs` reads lists and patterns).
        for list in [
            "LIST\nCT scan.raw",
            "LIST 2D\nCT scan.raw",
            "CT scan.ra%c 1 1 1",
        ] {
            std::fs::write(&h, format!("{base}ElementDataFile = {list}\n")).unwrap();
            for e in [
                read_volume(&h, None).unwrap_err(),
                RegionReader::open(&h, None).unwrap_err(),
            ] {
                assert!(matches!(e, ReadError::BadHeader { .. }), "{list}: {e}");
            }
        }
        std::fs::write(&h, format!("{base}ElementDataFile = LIST\nCT scan.raw\n")).unwrap();
        let e = read_volume(&h, None).unwrap_err().to_string();
        assert!(e.contains("1 files named"), "{e}");
    }

    /// ITK writes one volume as `NDims = 4` with a last size of 1 (and 4 spacings, a 4×4
    /// matrix, 4 offsets): it reads as the 3D volume. A last size of more is a time series,
    /// named as such; a matrix mixing time with space is refused.
    #[test]
    fn ndims_4_with_a_last_size_of_1_is_a_volume() {
        use crate::reader::region::RegionReader;
        let dir = tempfile::tempdir().unwrap();
        let data: Vec<u8> = (0..24u8).collect();
        let write = |name: &str, header: &str| {
            let p = dir.path().join(name);
            let mut b = format!(
                "ObjectType = Image\nElementType = MET_UCHAR\n{header}ElementDataFile = LOCAL\n"
            )
            .into_bytes();
            b.extend_from_slice(&data);
            std::fs::write(&p, b).unwrap();
            p
        };
        let three = write(
            "three.mha",
            "NDims = 3\nDimSize = 2 3 4\nElementSpacing = 0.5 0.75 2\nOffset = 10 -20 30\nTransformMatrix = 0 1 0 -1 0 0 0 0 1\n",
        );
        let four = write(
            "four.mha",
            "NDims = 4\nDimSize = 2 3 4 1\nElementSpacing = 0.5 0.75 2 1\nOffset = 10 -20 30 0\nTransformMatrix = 0 1 0 0 -1 0 0 0 0 0 1 0 0 0 0 1\n",
        );
        let want = read_volume(&three, None).unwrap();
        assert!(want.placement().is_some());
        assert_eq!(read_volume(&four, None).unwrap(), want);
        assert_eq!(crate::reader::time_points(&four, None).unwrap(), 1);
        let r = RegionReader::open(&four, None).unwrap();
        assert_eq!(r.read_region([0; 3], [2, 3, 4]).unwrap(), want);

        let series = write("series.mha", "NDims = 4\nDimSize = 2 3 2 2\n");
        let e = read_volume(&series, None).unwrap_err();
        assert!(matches!(e, ReadError::TimeSeries { points: 2, .. }), "{e}");
        assert_eq!(crate::reader::time_points(&series, None).unwrap(), 2);
        let mixed = write(
            "mixed.mha",
            "NDims = 4\nDimSize = 2 3 4 1\nTransformMatrix = 1 0 0 0.5 0 1 0 0 0 0 1 0 0 0 0 1\n",
        );
        let e = read_volume(&mixed, None).unwrap_err();
        assert!(e.to_string().contains("mixes the time axis"), "{e}");
        let zero = write("zero.mha", "NDims = 4\nDimSize = 2 3 4 0\n");
        assert!(read_volume(&zero, None).is_err());
        assert!(RegionReader::open_series(&zero, None).is_err());
        let five = write("five.mha", "NDims = 5\nDimSize = 2 3 4 1 1\n");
        assert!(read_volume(&five, None)
            .unwrap_err()
            .to_string()
            .contains("NDims"));
    }
}
