//! NRRD ("nearly raw raster data", teem / 3D Slicer / ITK): attached headers (`.nrrd`, data
//! after the blank line that ends the header) and detached ones (`.nhdr`, data in the file
//! named by `data file`, spaces allowed, or in many: `LIST` and the names on the header's
//! lines after it, or a pattern `slice%03d.raw MIN MAX STEP [DIM]`, each file holding its piece
//! of the samples after its own skipped lines and bytes, or its own gzip stream, as teem reads
//! them), `raw`, `gzip` and `ascii` encodings, either byte
//! order, 3D scalar volumes and 4D ones whose first axis holds 1 or 3 channels (RGB), or whose
//! first or last axis is time (`kinds` `time` or `list`: a Slicer sequence; read as a time
//! series). Spacing and placement come
//! from `space directions` and `space origin` (converted to LPS from `RAS`, `LAS` or `LPS`
//! spaces; other spaces give spacing only), else from `spacings`.
//!
//! The header is parsed by hand: the format is a short list of `field: value` lines, and the
//! Rust NRRD crates available read a subset (no detached headers or no `space directions`)
//! with less validation than a server reading untrusted archives needs.

use std::path::{Path, PathBuf};

use super::text::{self, grid_from_vectors, header_lines, nrrd_type, origin3};
use super::{
    deinterleave, in_piece, join_pieces, read_exact_or_truncated, voxel_count, Endian, ReadError,
    SampleType, SourceFiles,
};
use wavesplat_codec::volume::{Placement, Volume};

const FORMAT: &str = "NRRD";

/// The parsed header fields this reader uses.
#[derive(Debug, Default)]
struct Header {
    dimension: Option<usize>,
    sample: Option<SampleType>,
    sizes: Option<Vec<u64>>,
    encoding: Option<String>,
    endian: Option<Endian>,
    spacings: Option<Vec<f64>>,
    space: Option<String>,
    space_dimension: Option<usize>,
    space_directions: Option<Vec<Option<Vec<f64>>>>,
    space_origin: Option<Vec<f64>>,
    /// Per axis: its kind (`domain`, `space`, `time`, `list`, …), lower case.
    kinds: Option<Vec<String>>,
    /// Per axis: its unit (`mm`, `ms`, …), as written.
    units: Option<Vec<String>>,
    byte_skip: i64,
    line_skip: u64,
    data_file: Option<String>,
    /// The header's lines after `data file: LIST` (the data files' names).
    listed: Vec<String>,
    /// Offset of the attached data (just past the blank line), if the header ended with one.
    data_offset: Option<usize>,
}

fn bad(path: &Path, reason: impl Into<String>) -> ReadError {
    ReadError::bad_header(path, FORMAT, reason)
}

fn parse_header(path: &Path, bytes: &[u8]) -> Result<Header, ReadError> {
    if !bytes.starts_with(b"NRRD000") {
        return Err(bad(path, "the file does not start with the magic NRRD000N"));
    }
    let (lines, end, found) = header_lines(bytes, |l| l.is_empty(), false)
        .ok_or_else(|| bad(path, "the header is not UTF-8 text or is longer than 1 MiB"))?;
    let mut h = Header {
        data_offset: found.then_some(end),
        ..Header::default()
    };
    for (n, line) in lines.iter().enumerate().skip(1) {
        if line.starts_with('#') {
            continue;
        }
        if line.contains(":=") {
            continue; // key/value pairs carry no geometry
        }
        let Some((field, value)) = line.split_once(": ") else {
            return Err(bad(
                path,
                format!("line {}: {line:?} is not `field: value`", n + 1),
            ));
        };
        let value = value.trim();
        let field = field.trim().to_ascii_lowercase();
        let fail = |what: &str| bad(path, format!("{field}: {value:?} is not {what}"));
        match field.as_str() {
            "dimension" => {
                h.dimension = Some(value.parse().map_err(|_| fail("a number"))?);
            }
            "type" => {
                h.sample = Some(nrrd_type(value).ok_or_else(|| {
                    ReadError::unsupported(
                        path,
                        format!("NRRD type {value:?}; supported are the 8-, 16-, 32- and 64-bit integer types, float and double"),
                    )
                })?);
            }
            "sizes" => h.sizes = Some(text::sizes(value).ok_or_else(|| fail("sizes"))?),
            "encoding" => h.encoding = Some(value.to_ascii_lowercase()),
            "endian" => {
                h.endian = Some(match value {
                    "little" => Endian::Little,
                    "big" => Endian::Big,
                    _ => return Err(fail("`little` or `big`")),
                })
            }
            "spacings" => h.spacings = Some(text::numbers(value).ok_or_else(|| fail("numbers"))?),
            "space" => h.space = Some(value.to_ascii_lowercase()),
            "space dimension" => {
                h.space_dimension = Some(value.parse().map_err(|_| fail("a number"))?)
            }
            "space directions" => {
                h.space_directions =
                    Some(text::vector_items(value).ok_or_else(|| fail("a list of vectors"))?)
            }
            "space origin" => {
                h.space_origin = Some(text::vector(value).ok_or_else(|| fail("a vector"))?)
            }
            "kinds" => {
                h.kinds = Some(
                    value
                        .split_whitespace()
                        .map(str::to_ascii_lowercase)
                        .collect(),
                )
            }
            "units" => {
                h.units = Some(
                    value
                        .split_whitespace()
                        .map(|u| u.trim_matches('"').to_string())
                        .collect(),
                )
            }
            "byte skip" => h.byte_skip = value.parse().map_err(|_| fail("a number"))?,
            "line skip" => h.line_skip = value.parse().map_err(|_| fail("a number"))?,
            "data file" | "datafile" => {
                h.data_file = Some(value.to_string());
                if text::is_file_list(value) {
                    h.listed = lines[n + 1..].to_vec(); // the remaining lines name the data files
                    break;
                }
            }
            _ => {} // centers, labels, content, measurement frame, …
        }
    }
    Ok(h)
}

/// Kinds of a leading axis that make it a 4D volume's colour channels (a header without kinds
/// keeps its leading axis of 1 or 3 with no space direction as channels too).
const CHANNEL_KINDS: &[&str] = &[
    "rgb-color",
    "3-color",
    "rgba-color",
    "4-color",
    "vector",
    "3-vector",
];

/// Whether an axis kind makes it a time axis: `time`, or `list` (3D Slicer writes a sequence
/// as `kinds: domain domain domain list`, older versions as `list domain domain domain`).
fn is_time_kind(kind: &str) -> bool {
    kind == "time" || kind == "list"
}

/// The time axis of a 4D header: its last or its first axis, whichever (only one) has a time
/// kind ([`is_time_kind`]).
fn time_axis(h: &Header) -> Option<usize> {
    let k = h.kinds.as_ref().filter(|k| k.len() == 4)?;
    if h.dimension != Some(4) {
        return None;
    }
    match (is_time_kind(&k[0]), is_time_kind(&k[3])) {
        (false, true) => Some(3),
        (true, false) => Some(0),
        _ => None,
    }
}

/// What the axes of a header hold.
#[derive(Debug)]
struct Axes {
    dimension: usize,
    sizes: Vec<u64>,
    /// The spatial axes (x, y, z), in order.
    spatial: Vec<usize>,
    /// Channels (the leading axis of a 4D colour volume; else 1).
    channels: usize,
    /// The time axis of a 4D file and its time points (1: the axis is dropped).
    time: Option<(usize, usize)>,
}

fn axes(path: &Path, h: &Header) -> Result<Axes, ReadError> {
    let dimension = h
        .dimension
        .ok_or_else(|| bad(path, "no `dimension` field"))?;
    let sizes = h
        .sizes
        .clone()
        .ok_or_else(|| bad(path, "no `sizes` field"))?;
    if !(1..=4).contains(&dimension) || sizes.len() != dimension {
        return Err(bad(
            path,
            format!(
                "dimension {dimension} with {} sizes; 1..=4 and one size per axis required",
                sizes.len()
            ),
        ));
    }
    if let Some(z) = sizes.iter().position(|s| *s == 0) {
        return Err(bad(path, format!("size of axis {z} is 0")));
    }
    // A 4D volume: a time axis first or last (by its kind), a leading channel axis (1 or 3,
    // no space direction, a colour kind or no kinds), or a trailing axis of 1.
    let mut spatial: Vec<usize> = (0..dimension).collect();
    let mut channels = 1;
    let mut time = None;
    if let Some(t) = time_axis(h) {
        spatial.remove(t);
        time = Some((t, usize::try_from(sizes[t]).unwrap_or(usize::MAX)));
    } else if dimension == 4 {
        let first_none = h
            .space_directions
            .as_ref()
            .is_some_and(|d| d.first().is_some_and(Option::is_none));
        let colour_kind = match h.kinds.as_ref().and_then(|k| k.first()) {
            None => true,
            // `???` and `none` say nothing: as if no kind were given.
            Some(k) => CHANNEL_KINDS.contains(&k.as_str()) || k == "???" || k == "none",
        };
        if (sizes[0] == 3 || sizes[0] == 1)
            && (first_none || h.space_directions.is_none())
            && colour_kind
        {
            channels = sizes[0] as usize;
            spatial.remove(0);
        } else if sizes[3] == 1 {
            spatial.pop();
        } else {
            return Err(ReadError::unsupported(
                path,
                format!(
                    "4D data of sizes {sizes:?}{}: only 3D volumes, a leading axis of 1 or 3 \
                     channels (kind RGB-color, 3-color, vector or 3-vector, or no kinds), a \
                     trailing axis of size 1, or a time axis first or last (`kinds: … time` or \
                     `list`, as 3D Slicer writes a sequence) are supported",
                    h.kinds
                        .as_ref()
                        .map(|k| format!(" and kinds {k:?}"))
                        .unwrap_or_default()
                ),
            ));
        }
    }
    Ok(Axes {
        dimension,
        sizes,
        spatial,
        channels,
        time,
    })
}

/// The time axis of a 4D NRRD file of more than one time point.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct SeriesAxis {
    /// The axis: 3 (the last: each time point's volume follows the previous one) or 0 (the
    /// first: a voxel's time points follow each other).
    pub axis: usize,
    /// Time points.
    pub points: usize,
    /// Seconds between time points, when the header gives the axis a spacing and a unit of
    /// time (s, ms, us).
    pub step: Option<f64>,
}

/// Of an NRRD file whose first or last axis is time (`kinds` `time` or `list`) with more than
/// one sample: that axis, its time points and their step. `None` for any other NRRD file (and
/// for one whose axes the decoder refuses: it says why).
pub(crate) fn series_info(path: &Path, bytes: &[u8]) -> Result<Option<SeriesAxis>, ReadError> {
    let h = parse_header(path, bytes)?;
    let Some((axis, points)) = axes(path, &h).ok().and_then(|a| a.time) else {
        return Ok(None);
    };
    if points <= 1 {
        return Ok(None);
    }
    let unit = h.units.as_ref().and_then(|u| u.get(axis)).and_then(|u| {
        match u.to_ascii_lowercase().as_str() {
            "s" | "sec" | "second" | "seconds" => Some(1.0),
            "ms" | "msec" => Some(1e-3),
            "us" | "µs" | "usec" => Some(1e-6),
            _ => None,
        }
    });
    let step = h
        .spacings
        .as_ref()
        .and_then(|s| s.get(axis))
        .copied()
        .filter(|s| s.is_finite() && *s > 0.0)
        .zip(unit)
        .map(|(s, u)| s * u);
    Ok(Some(SeriesAxis { axis, points, step }))
}

/// The spatial axes (x, y, z) of the NRRD file whose header is `bytes`, as the decoder takes
/// them.
pub(crate) fn spatial_axes(path: &Path, bytes: &[u8]) -> Result<Vec<usize>, ReadError> {
    Ok(axes(path, &parse_header(path, bytes)?)?.spatial)
}

/// The names of the data files a detached header refers to (relative to its directory).
pub(crate) fn data_files(path: &Path, bytes: &[u8]) -> Result<Vec<String>, ReadError> {
    let h = parse_header(path, bytes)?;
    Ok(data_file_names(path, &h)?.map_or_else(Vec::new, |d| d.names))
}

/// The data files the header `bytes` of `path` names (`None`: the data follows the header),
/// and the length of each one's piece of the `total` bytes of samples.
pub(crate) fn data_pieces(
    path: &Path,
    bytes: &[u8],
    total: u64,
) -> Result<Option<(Vec<String>, u64)>, ReadError> {
    pieces_of(path, &parse_header(path, bytes)?, total)
}

/// [`data_pieces`] of a parsed header.
fn pieces_of(path: &Path, h: &Header, total: u64) -> Result<Option<(Vec<String>, u64)>, ReadError> {
    let Some(d) = data_file_names(path, h)? else {
        return Ok(None);
    };
    let sizes = h.sizes.as_deref().unwrap_or(&[]);
    let piece = text::piece_bytes(sizes, &d, total, true)
        .map_err(|e| bad(path, format!("data file: {e}")))?;
    Ok(Some((d.names, piece)))
}

/// The files the header's `data file` names (a name, a `LIST` or a pattern), as teem reads it.
fn data_file_names(path: &Path, h: &Header) -> Result<Option<text::DataFileNames>, ReadError> {
    h.data_file
        .as_deref()
        .map(|v| {
            text::data_file_names(v, &h.listed)
                .map_err(|e| bad(path, format!("data file {v:?}: {e}")))
        })
        .transpose()
}

/// The volume layout a header describes.
#[derive(Debug, Clone, Copy)]
struct Layout {
    dims: [usize; 3],
    channels: usize,
    spacing: [f32; 3],
    placement: Option<Placement>,
}

fn layout(path: &Path, h: &Header) -> Result<Layout, ReadError> {
    let Axes {
        dimension,
        sizes,
        spatial,
        channels,
        time,
    } = axes(path, h)?;
    if let Some((_, points)) = time.filter(|(_, points)| *points > 1) {
        return Err(ReadError::TimeSeries {
            path: path.to_path_buf(),
            points,
        });
    }
    let mut dims = [1usize; 3];
    for (i, a) in spatial.iter().enumerate() {
        dims[i] = usize::try_from(sizes[*a]).unwrap_or(usize::MAX);
    }
    voxel_count(dims).map_err(|e| ReadError::volume(path, e))?;

    let space = h.space.as_deref();
    let to_lps = match space {
        Some("left-posterior-superior" | "lps" | "left-posterior-superior-time" | "lpst") => {
            Some([1.0, 1.0, 1.0])
        }
        Some("right-anterior-superior" | "ras" | "right-anterior-superior-time" | "rast") => {
            Some([-1.0, -1.0, 1.0])
        }
        Some("left-anterior-superior" | "las" | "left-anterior-superior-time" | "last") => {
            Some([1.0, -1.0, 1.0])
        }
        _ => None,
    };
    let space_dim = match (space, h.space_dimension) {
        (Some(s), _) if s.starts_with("3d-") || s.starts_with("scanner-") || to_lps.is_some() => 3,
        (Some(s), _) => {
            return Err(ReadError::unsupported(path, format!("space {s:?}")));
        }
        (None, d) => d.unwrap_or(0),
    };
    if let Some(dirs) = &h.space_directions {
        if space_dim != 3 {
            return Err(bad(
                path,
                format!("space directions need a 3D space (`space` or `space dimension: 3`), got dimension {space_dim}"),
            ));
        }
        if dirs.len() != dimension {
            return Err(bad(
                path,
                format!(
                    "space directions has {} entries for {dimension} axes",
                    dirs.len()
                ),
            ));
        }
        let mut vectors = [[0.0; 3]; 3];
        for (i, a) in spatial.iter().enumerate() {
            match &dirs[*a] {
                Some(v) if v.len() == 3 => vectors[i] = [v[0], v[1], v[2]],
                Some(v) => {
                    return Err(bad(
                        path,
                        format!(
                            "space directions: axis {a} has {} components, 3 expected",
                            v.len()
                        ),
                    ))
                }
                None if dims[i] == 1 && dimension < 3 => vectors[i] = unit(i),
                None => {
                    return Err(bad(
                        path,
                        format!("space directions: spatial axis {a} is `none`"),
                    ))
                }
            }
        }
        // Axes the file does not have (dimension < 3) get unit steps orthogonal to the others.
        for (i, v) in vectors.iter_mut().enumerate().skip(spatial.len()) {
            *v = unit(i);
        }
        let origin = match &h.space_origin {
            Some(o) => Some(origin3(path, FORMAT, "space origin", o)?),
            None => None,
        };
        let (spacing, placement) =
            grid_from_vectors(path, FORMAT, "space directions", vectors, origin, to_lps)?;
        return Ok(Layout {
            dims,
            channels,
            spacing,
            placement,
        });
    }
    let mut spacing = [1.0f32; 3];
    if let Some(s) = &h.spacings {
        if s.len() != dimension {
            return Err(bad(
                path,
                format!("spacings has {} entries for {dimension} axes", s.len()),
            ));
        }
        for (i, a) in spatial.iter().enumerate() {
            let v = s[*a];
            if v.is_nan() {
                continue; // NRRD writes `nan` for "no spacing"
            }
            let f = v as f32;
            if !(f.is_finite() && f > 0.0) {
                return Err(bad(
                    path,
                    format!("spacings: axis {a} has spacing {v}; it must be finite and positive"),
                ));
            }
            spacing[i] = f;
        }
    }
    Ok(Layout {
        dims,
        channels,
        spacing,
        placement: None,
    })
}

fn unit(i: usize) -> [f64; 3] {
    let mut v = [0.0; 3];
    v[i] = 1.0;
    v
}

/// Decodes an NRRD volume from its gathered files.
pub(crate) fn decode(src: &SourceFiles) -> Result<Volume, ReadError> {
    let (name, header_bytes) = &src.files[0];
    let path = src.path_of(name);
    let h = parse_header(&path, header_bytes)?;
    let layout = layout(&path, &h)?;
    let sample = h.sample.ok_or_else(|| bad(&path, "no `type` field"))?;
    let voxels = voxel_count(layout.dims).map_err(|e| ReadError::volume(&path, e))?;
    let expected =
        voxels
            .checked_mul(layout.channels * sample.size())
            .ok_or(ReadError::TooLarge {
                dims: layout.dims,
                channels: layout.channels,
                bytes_per_sample: sample.size(),
            })?;
    let encoding = h.encoding.as_deref().unwrap_or("");
    let endian = match h.endian {
        Some(e) => e,
        None if sample.size() == 1 || matches!(encoding, "ascii" | "text" | "txt") => {
            Endian::Little
        }
        None => return Err(bad(&path, "no `endian` field for multi-byte samples")),
    };
    // The data: after the header, or in the data files, each holding its piece of the samples
    // after its own skipped lines and bytes (as teem reads them).
    let (pieces, piece): (Vec<(PathBuf, &[u8])>, usize) =
        match pieces_of(&path, &h, expected as u64)? {
            Some((names, piece)) => (src.data_files(&names, FORMAT)?, piece as usize),
            None => {
                let off = h.data_offset.ok_or_else(|| {
                    bad(
                        &path,
                        "no blank line ends the header and no `data file` is named",
                    )
                })?;
                (vec![(path.clone(), &header_bytes[off..])], expected)
            }
        };
    let data_path = pieces[0].0.clone();
    if matches!(encoding, "ascii" | "text" | "txt") {
        if pieces.len() > 1 {
            return Err(ReadError::unsupported(
                &path,
                "ASCII data in several data files",
            ));
        }
        let data = skip_lines(&path, pieces[0].1, h.line_skip)?.1;
        return ascii_volume(&path, &data_path, data, &layout, voxels, sample);
    }
    let raw = join_pieces(&pieces, |p, data| {
        piece_of(&path, &h, encoding, p, data, piece)
    })?;
    let raw: &[u8] = &raw;
    let planar = deinterleave(raw, sample, endian, layout.channels, 1.0, 0.0);
    let wide = [layout.dims[0], layout.dims[1]];
    finish(&data_path, layout, planar)
        .map_err(|e| in_piece(e, &pieces, piece, wide, layout.channels, sample.size()))
}

/// The data after `lines` lines of `data` and the offset it starts at.
fn skip_lines<'a>(path: &Path, data: &'a [u8], lines: u64) -> Result<(u64, &'a [u8]), ReadError> {
    let (mut data, mut offset) = (data, 0u64);
    for _ in 0..lines {
        match data.iter().position(|b| *b == b'\n') {
            Some(i) => {
                data = &data[i + 1..];
                offset += i as u64 + 1;
            }
            None => {
                return Err(bad(
                    path,
                    format!("line skip {lines} passes the end of the data"),
                ))
            }
        }
    }
    Ok((offset, data))
}

/// The `piece` bytes of samples a data file `data` (read from `data_path`) holds, after the
/// header's line skip, then byte skip (applied to the file as stored; -1: the last `piece`
/// bytes of raw data), raw or inflated.
fn piece_of<'a>(
    path: &Path,
    h: &Header,
    encoding: &str,
    data_path: &Path,
    data: &'a [u8],
    piece: usize,
) -> Result<std::borrow::Cow<'a, [u8]>, ReadError> {
    let (offset, data) = skip_lines(data_path, data, h.line_skip)?;
    match encoding {
        "raw" => {
            let skip = match h.byte_skip {
                -1 => data.len().checked_sub(piece).ok_or(ReadError::Truncated {
                    path: data_path.to_path_buf(),
                    offset,
                    expected: piece as u64,
                    actual: data.len() as u64,
                })?,
                s if s >= 0 => usize::try_from(s).unwrap_or(usize::MAX),
                s => return Err(bad(path, format!("byte skip {s}; -1 or ≥ 0 allowed"))),
            };
            let body = data.get(skip..).unwrap_or(&[]);
            if body.len() < piece {
                return Err(ReadError::Truncated {
                    path: data_path.to_path_buf(),
                    offset: offset + skip as u64,
                    expected: piece as u64,
                    actual: body.len() as u64,
                });
            }
            Ok(std::borrow::Cow::Borrowed(&body[..piece]))
        }
        "gzip" | "gz" => {
            if h.byte_skip != 0 {
                return Err(ReadError::unsupported(path, "byte skip with gzip encoding"));
            }
            let mut stream = flate2::bufread::MultiGzDecoder::new(data);
            let bytes = read_exact_or_truncated(&mut stream, piece, data.len(), data_path, 0)
                .map_err(|e| gzip_error(e, data_path))?;
            Ok(std::borrow::Cow::Owned(bytes))
        }
        "" => Err(bad(path, "no `encoding` field")),
        e => Err(ReadError::unsupported(
            path,
            format!("encoding {e:?}; supported are raw, gzip and ascii"),
        )),
    }
}

fn gzip_error(e: ReadError, path: &Path) -> ReadError {
    match e {
        ReadError::Io { source, .. }
            if source.kind() == std::io::ErrorKind::InvalidInput
                || source.kind() == std::io::ErrorKind::InvalidData =>
        {
            ReadError::bad_header(path, FORMAT, format!("the gzip data is corrupt: {source}"))
        }
        e => e,
    }
}

fn ascii_volume(
    path: &Path,
    data_path: &Path,
    data: &[u8],
    layout: &Layout,
    voxels: usize,
    sample: SampleType,
) -> Result<Volume, ReadError> {
    let text = std::str::from_utf8(data).map_err(|_| bad(path, "ascii data is not text"))?;
    let n = voxels * layout.channels;
    let mut planar: Vec<Vec<f32>> = (0..layout.channels)
        .map(|_| Vec::with_capacity(voxels.min(data.len())))
        .collect();
    let mut count = 0usize;
    for tok in text
        .split(|c: char| c.is_whitespace() || c == ',')
        .filter(|t| !t.is_empty())
    {
        if count == n {
            break;
        }
        let v: f64 = tok
            .parse()
            .map_err(|_| bad(path, format!("ascii data: {tok:?} is not a number")))?;
        let v = if matches!(sample, SampleType::F32 | SampleType::F64) {
            v
        } else {
            v.trunc()
        };
        planar[count % layout.channels].push(v as f32);
        count += 1;
    }
    if count != n {
        return Err(ReadError::Truncated {
            path: data_path.to_path_buf(),
            offset: 0,
            expected: n as u64,
            actual: count as u64,
        });
    }
    finish(data_path, *layout, planar)
}

fn finish(path: &Path, layout: Layout, planar: Vec<Vec<f32>>) -> Result<Volume, ReadError> {
    let v =
        Volume::new(layout.dims, layout.spacing, planar).map_err(|e| ReadError::volume(path, e))?;
    match layout.placement {
        Some(p) => v.with_placement(p).map_err(|e| ReadError::volume(path, e)),
        None => Ok(v),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::reader::{read_volume, Format};
    use wavesplat_codec::volume::VolumeError;
    use wavesplat_fixtures::{self as fixtures, Layout as FixtureLayout, NrrdEncoding};

    fn sample_volume(dims: [usize; 3], spacing: [f32; 3]) -> Volume {
        let n = dims.iter().product::<usize>();
        let data: Vec<f32> = (0..n).map(|i| ((i * 37) % 251) as f32 - 100.0).collect();
        let p = Placement {
            origin: [-12.5, 30.0, 7.25],
            directions: [[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]],
        };
        Volume::new(dims, spacing, vec![data])
            .unwrap()
            .with_placement(p)
            .unwrap()
    }

    #[test]
    fn round_trips_every_encoding_and_header_style() {
        let dir = tempfile::tempdir().unwrap();
        let v = sample_volume([5, 4, 3], [0.7, 0.7, 2.5]);
        for encoding in [NrrdEncoding::Raw, NrrdEncoding::Gzip, NrrdEncoding::Ascii] {
            for detached in [false, true] {
                for space in ["left-posterior-superior", "right-anterior-superior", "LAS"] {
                    let name = format!("v_{encoding:?}_{detached}_{space}");
                    let path = fixtures::write_nrrd(
                        dir.path(),
                        &name,
                        &v,
                        FixtureLayout::I16,
                        encoding,
                        detached,
                        space,
                    );
                    let back = read_volume(&path, None).unwrap();
                    assert_eq!(back.dims(), v.dims(), "{name}");
                    assert_eq!(back.channel(0), v.channel(0), "{name}");
                    assert_eq!(back.spacing(), v.spacing(), "{name}");
                    let (a, b) = (back.placement().unwrap(), v.placement().unwrap());
                    for i in 0..3 {
                        assert!((a.origin[i] - b.origin[i]).abs() < 1e-9, "{name}");
                        for j in 0..3 {
                            assert!((a.directions[i][j] - b.directions[i][j]).abs() < 1e-9);
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn rgb_and_spacings_only() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("rgb.nrrd");
        let mut b = b"NRRD0004\ntype: uint8\ndimension: 4\nsizes: 3 2 1 1\nencoding: raw\nspacings: nan 0.5 2 3\n\n".to_vec();
        b.extend_from_slice(&[1, 2, 3, 4, 5, 6]);
        std::fs::write(&p, &b).unwrap();
        let v = read_volume(&p, None).unwrap();
        assert_eq!(v.channel_count(), 3);
        assert_eq!(v.dims(), [2, 1, 1]);
        assert_eq!(v.channel(0), &[1.0, 4.0]);
        assert_eq!(v.channel(2), &[3.0, 6.0]);
        assert_eq!(v.spacing(), [0.5, 2.0, 3.0]);
        assert!(v.placement().is_none());
        // Big-endian floats, 2D, with a byte skip of -1 (data at the end).
        let p = dir.path().join("be.nrrd");
        let mut b = b"NRRD0005\n# comment\ntype: float\ndimension: 2\nsizes: 2 1\nendian: big\nencoding: raw\nbyte skip: -1\nkey:=value\n\nJUNK".to_vec();
        b.extend_from_slice(&1.5f32.to_be_bytes());
        b.extend_from_slice(&(-2.0f32).to_be_bytes());
        std::fs::write(&p, &b).unwrap();
        let v = read_volume(&p, None).unwrap();
        assert_eq!((v.dims(), v.channel(0)), ([2, 1, 1], &[1.5f32, -2.0][..]));
    }

    fn header(fields: &str, data: &[u8]) -> Vec<u8> {
        let mut b = format!("NRRD0004\n{fields}\n").into_bytes();
        b.extend_from_slice(data);
        b
    }

    #[test]
    fn bad_and_hostile_headers_are_errors() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("bad.nrrd");
        let base = "type: uint8\ndimension: 3\nencoding: raw\n";
        let cases: Vec<(String, Vec<u8>)> = vec![
            // Huge dimensions on a tiny file: refused before allocating.
            (format!("{base}sizes: 100000 100000 100000\n"), vec![0; 8]),
            (format!("{base}sizes: 4096 4096 100\n"), vec![0; 8]),
            (format!("{base}sizes: 18446744073709551615 2 2\n"), vec![0; 8]),
            // Zero size, zero / NaN / negative spacing, NaN directions, shear.
            (format!("{base}sizes: 2 0 2\n"), vec![0; 8]),
            (format!("{base}sizes: 2 2 2\nspace: RAS\nspace directions: (1,0,0) (0,0,0) (0,0,1)\n"), vec![0; 8]),
            (format!("{base}sizes: 2 2 2\nspace: RAS\nspace directions: (1,0,0) (0,nan,0) (0,0,1)\n"), vec![0; 8]),
            (format!("{base}sizes: 2 2 2\nspace: RAS\nspace directions: (1,0,0) (0.5,1,0) (0,0,1)\n"), vec![0; 8]),
            (format!("{base}sizes: 2 2 2\nspace: RAS\nspace directions: (1,0,0) (0,1,0) (0,0,1)\nspace origin: (nan,0,0)\n"), vec![0; 8]),
            (format!("{base}sizes: 2 2 2\nspacings: 1 0 1\n"), vec![0; 8]),
            (format!("{base}sizes: 2 2 2\nspacings: 1 -2 1\n"), vec![0; 8]),
            (format!("{base}sizes: 2 2 2\nspacings: 1 inf 1\n"), vec![0; 8]),
            // Inconsistent: wrong counts, missing fields, truncated data.
            (format!("{base}sizes: 2 2\n"), vec![0; 8]),
            (format!("{base}sizes: 2 2 2\nspace: RAS\nspace directions: (1,0,0) (0,1,0)\n"), vec![0; 8]),
            (format!("{base}sizes: 2 2 2\n"), vec![0; 7]),
            ("type: uint8\nsizes: 2 2 2\nencoding: raw\n".into(), vec![0; 8]),
            ("dimension: 3\nsizes: 2 2 2\nencoding: raw\n".into(), vec![0; 8]),
            ("type: short\ndimension: 3\nsizes: 2 2 2\nencoding: raw\n".into(), vec![0; 16]),
            (format!("{base}sizes: 2 2 2\nbyte skip: 100\n"), vec![0; 8]),
            (format!("{base}sizes: 2 2 2\nbyte skip: -7\n"), vec![0; 8]),
            // Unsupported.
            ("type: block\ndimension: 3\nsizes: 2 2 2\nencoding: raw\n".into(), vec![0; 8]),
            ("type: uint8\ndimension: 3\nsizes: 2 2 2\nencoding: bzip2\n".into(), vec![0; 8]),
            ("type: uint8\ndimension: 4\nsizes: 2 2 2 2\nencoding: raw\n".into(), vec![0; 16]),
            // Garbage.
            ("this is not a field\n".into(), vec![]),
            ("type: uint8\ndimension: three\n".into(), vec![]),
        ];
        for (fields, data) in cases {
            std::fs::write(&p, header(&fields, &data)).unwrap();
            let r = read_volume(&p, None);
            assert!(r.is_err(), "accepted: {fields}");
            let e = r.unwrap_err().to_string();
            assert!(e.contains("bad.nrrd"), "{e}");
        }
        // Float NaN samples are rejected by the volume.
        std::fs::write(
            &p,
            header(
                "type: float\ndimension: 1\nsizes: 1\nencoding: raw\nendian: little\n",
                &f32::NAN.to_le_bytes(),
            ),
        )
        .unwrap();
        assert!(matches!(
            read_volume(&p, None),
            Err(ReadError::InvalidVolume {
                problem: VolumeError::NonFinite { .. },
                ..
            })
        ));
        // Corrupt gzip, and a gzip stream shorter than announced.
        std::fs::write(
            &p,
            header(
                &format!("{base}sizes: 2 2 2\n").replace("raw", "gzip"),
                &[0x1f, 0x8b, 9, 9, 9],
            ),
        )
        .unwrap();
        assert!(read_volume(&p, None).is_err());
        let mut gz = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
        std::io::Write::write_all(&mut gz, &[1, 2, 3]).unwrap();
        let gz = gz.finish().unwrap();
        std::fs::write(
            &p,
            header(&format!("{base}sizes: 2 2 2\n").replace("raw", "gzip"), &gz),
        )
        .unwrap();
        assert!(matches!(
            read_volume(&p, None),
            Err(ReadError::Truncated {
                expected: 8,
                actual: 3,
                ..
            })
        ));
        // A detached header whose data file is missing, or a LIST.
        let h = dir.path().join("d.nhdr");
        std::fs::write(
            &h,
            format!("NRRD0004\n{base}sizes: 2 2 2\ndata file: missing.raw\n"),
        )
        .unwrap();
        assert!(matches!(read_volume(&h, None), Err(ReadError::Io { .. })));
        std::fs::write(
            &h,
            format!("NRRD0004\n{base}sizes: 2 2 2\ndata file: LIST\na.raw\n"),
        )
        .unwrap();
        let e = read_volume(&h, None).unwrap_err();
        assert!(matches!(e, ReadError::Io { .. }), "{e}");
        assert!(e.to_string().contains("a.raw"), "{e}");
        // Random bytes after the magic never panic.
        let mut seed = 12345u64;
        for len in 0..200 {
            let mut b = b"NRRD0004\n".to_vec();
            for _ in 0..len {
                seed = seed
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                b.push((seed >> 56) as u8);
            }
            std::fs::write(&p, &b).unwrap();
            let _ = read_volume(&p, None);
        }
        assert_eq!(Format::from_name(&p), Some(Format::Nrrd));
    }

    /// A detached header whose data file's name holds spaces (`data file: Patient 1.raw`, as
    /// teem reads any value but LIST or a pattern as one name) reads, raw and gzip, through
    /// every path: the listing that hashes it, gathering, decoding and region reads.
    #[test]
    fn a_data_file_name_may_hold_spaces() {
        use crate::reader::region::RegionReader;
        use crate::reader::{decode_source, SourceFiles, SourceListing};
        let dir = tempfile::tempdir().unwrap();
        let data: Vec<u8> = (0..24u8).collect();
        let gz = {
            let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
            std::io::Write::write_all(&mut e, &data).unwrap();
            e.finish().unwrap()
        };
        std::fs::write(dir.path().join("Patient 1.raw"), &data).unwrap();
        std::fs::write(dir.path().join("Patient 1.raw.gz"), &gz).unwrap();
        for (encoding, file) in [("raw", "Patient 1.raw"), ("gzip", "Patient 1.raw.gz")] {
            let h = dir.path().join(format!("scan {encoding}.nhdr"));
            std::fs::write(
                &h,
                format!("NRRD0004\ntype: uint8\ndimension: 3\nsizes: 2 3 4\nencoding: {encoding}\ndata file: {file}\n"),
            )
            .unwrap();
            let v = read_volume(&h, None).unwrap_or_else(|e| panic!("{file}: {e}"));
            assert_eq!(v.dims(), [2, 3, 4]);
            let want: Vec<f32> = data.iter().map(|b| f32::from(*b)).collect();
            assert_eq!(v.channel(0), &want[..], "{file}");
            let listing = SourceListing::list(&h, None).unwrap();
            let names: Vec<&str> = listing.files.iter().map(|(n, _, _)| n.as_str()).collect();
            assert_eq!(names[1..], [file], "{file}");
            let src = SourceFiles::gather(&h, None).unwrap();
            assert_eq!(
                src.get(file),
                Some(&std::fs::read(dir.path().join(file)).unwrap()[..])
            );
            assert_eq!(decode_source(&src, None).unwrap(), v);
            let back = SourceFiles::from_bytes(src.to_bytes(), &h).unwrap();
            assert_eq!(decode_source(&back, None).unwrap(), v);
            let r = RegionReader::open(&h, None).unwrap();
            assert_eq!(r.read_region([0; 3], [2, 3, 4]).unwrap(), v);
        }
        // A list whose files are too few for the sizes is refused, saying so
        // (`tests/data_files.rs` reads lists and patterns).
        for list in ["LIST", "LIST 2"] {
            let h = dir.path().join("list.nhdr");
            std::fs::write(
                &h,
                format!("NRRD0004\ntype: uint8\ndimension: 3\nsizes: 2 3 4\nencoding: raw\ndata file: {list}\nPatient 1.raw\n"),
            )
            .unwrap();
            for e in [
                read_volume(&h, None).unwrap_err(),
                RegionReader::open(&h, None).unwrap_err(),
            ] {
                assert!(matches!(e, ReadError::BadHeader { .. }), "{list}: {e}");
                assert!(e.to_string().contains("1 files named"), "{e}");
            }
        }
    }

    fn nrrd_4d(dir: &Path, name: &str, fields: &str, data: &[u8]) -> PathBuf {
        let p = dir.join(name);
        let mut b =
            format!("NRRD0004\ntype: uint8\ndimension: 4\nencoding: raw\nspace: RAS\n{fields}\n")
                .into_bytes();
        b.extend_from_slice(data);
        std::fs::write(&p, b).unwrap();
        p
    }

    /// A 3D Slicer sequence: its `list` axis, first (older Slicer) or last, is time, as a
    /// `time` axis is; a leading axis of 3 with no space direction is colour only when its kind
    /// says so (or no kinds are given), never when it is a `list`.
    #[test]
    fn slicer_list_axes_are_time_and_only_colour_kinds_are_channels() {
        use crate::reader::region::RegionReader;
        let dir = tempfile::tempdir().unwrap();
        let dirs = "space directions: none (1,0,0) (0,1,0) (0,0,1)\n";
        let data: Vec<u8> = (0..24u8).collect();
        // `list domain domain domain`, 3 × 2×2×2: three time points, a voxel's after each
        // other.
        let lead = nrrd_4d(
            dir.path(),
            "lead.nrrd",
            &format!("sizes: 3 2 2 2\nkinds: list domain domain domain\n{dirs}"),
            &data,
        );
        let e = read_volume(&lead, None).unwrap_err();
        assert!(matches!(e, ReadError::TimeSeries { points: 3, .. }), "{e}");
        assert_eq!(crate::reader::time_points(&lead, None).unwrap(), 3);
        let e = RegionReader::open(&lead, None).unwrap_err();
        assert!(matches!(e, ReadError::TimeSeries { points: 3, .. }), "{e}");
        let r = RegionReader::open_series(&lead, None).unwrap();
        assert_eq!((r.time_points(), r.dims(), r.channels()), (3, [2, 2, 2], 1));
        for t in 0..3 {
            let want: Vec<f32> = (0..8).map(|i| (i * 3 + t) as f32).collect();
            let v = r.read_region_at(t, [0; 3], [2, 2, 2]).unwrap();
            assert_eq!(v.channel(0), &want[..], "time point {t}");
            let v = r.read_region_at(t, [1, 0, 1], [1, 2, 1]).unwrap();
            assert_eq!(v.channel(0), &[want[5], want[7]], "time point {t}");
        }
        // `domain domain domain list`, 2×2×2 × 3: each time point's volume after the other.
        let trail = nrrd_4d(
            dir.path(),
            "trail.nrrd",
            "sizes: 2 2 2 3\nkinds: domain domain domain list\nspace directions: (1,0,0) (0,1,0) (0,0,1) none\n",
            &data,
        );
        let e = read_volume(&trail, None).unwrap_err();
        assert!(matches!(e, ReadError::TimeSeries { points: 3, .. }), "{e}");
        let r = RegionReader::open_series(&trail, None).unwrap();
        assert_eq!((r.time_points(), r.dims()), (3, [2, 2, 2]));
        for t in 0..3 {
            let want: Vec<f32> = (0..8).map(|i| (t * 8 + i) as f32).collect();
            assert_eq!(
                r.read_region_at(t, [0; 3], [2, 2, 2]).unwrap().channel(0),
                &want[..]
            );
        }
        // A list of one is a volume, first or last.
        for (name, fields) in [
            (
                "one_lead.nrrd",
                format!("sizes: 1 2 2 2\nkinds: list domain domain domain\n{dirs}"),
            ),
            (
                "one_trail.nrrd",
                "sizes: 2 2 2 1\nkinds: domain domain domain list\n".to_string(),
            ),
        ] {
            let p = nrrd_4d(dir.path(), name, &fields, &data[..8]);
            let v = read_volume(&p, None).unwrap();
            assert_eq!((v.dims(), v.channel_count()), ([2, 2, 2], 1), "{name}");
            assert_eq!(
                v.channel(0),
                &(0..8).map(|i| i as f32).collect::<Vec<_>>()[..]
            );
        }
        // Colour: by a colour kind, or with no kinds at all; not by a `domain` axis.
        for kinds in [
            "kinds: RGB-color domain domain domain\n",
            "kinds: 3-color domain domain domain\n",
            "kinds: vector domain domain domain\n",
            "",
        ] {
            let p = nrrd_4d(
                dir.path(),
                "rgb.nrrd",
                &format!("sizes: 3 2 2 2\n{kinds}{dirs}"),
                &data,
            );
            let v = read_volume(&p, None).unwrap_or_else(|e| panic!("{kinds}: {e}"));
            assert_eq!((v.dims(), v.channel_count()), ([2, 2, 2], 3), "{kinds}");
            assert_eq!(v.channel(1)[1], 4.0, "{kinds}");
            assert_eq!(
                RegionReader::open(&p, None).unwrap().channels(),
                3,
                "{kinds}"
            );
        }
        let p = nrrd_4d(
            dir.path(),
            "domain.nrrd",
            &format!("sizes: 3 2 2 2\nkinds: domain domain domain domain\n{dirs}"),
            &data,
        );
        let e = read_volume(&p, None).unwrap_err();
        assert!(matches!(e, ReadError::Unsupported { .. }), "{e}");
        // A list at both ends says neither which is time nor which is space.
        let p = nrrd_4d(
            dir.path(),
            "both.nrrd",
            &format!("sizes: 3 2 2 2\nkinds: list domain domain list\n{dirs}"),
            &data,
        );
        assert!(read_volume(&p, None).is_err());
        // Three dimensions whose first is a list of 3: never colour.
        let p = dir.path().join("list3d.nrrd");
        let mut b = b"NRRD0004\ntype: uint8\ndimension: 3\nsizes: 3 2 4\nencoding: raw\nkinds: list domain domain\n\n".to_vec();
        b.extend_from_slice(&data);
        std::fs::write(&p, b).unwrap();
        let v = read_volume(&p, None).unwrap();
        assert_eq!((v.dims(), v.channel_count()), ([3, 2, 4], 1));
    }
}
