//! Series discovery and assembly: which files of a directory are DICOM (the `DICM` preamble),
//! and [`decode`], which reads every file's header, checks that the images form one series
//! with one in-plane geometry and sample format, has [`super::geometry`] order and place the
//! frames, holds the volume to what the files' bytes can hold, and decodes each file's frames
//! into their slots; [`SeriesRegions`], which does the same checks and reads boxes of the
//! volume by slice ranges, decoding only the files that hold them.

use dicom_object::DefaultDicomObject;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use dicom_core::Tag;
use dicom_dictionary_std::tags;
use wavesplat_codec::volume::{Placement, Volume};

use super::geometry::{order_frames, FrameRef, Ordered};
use super::image::read_image;
use super::image::ACQUISITION_TIME;
use super::pixels::{check_pixel_data, decode_frame};
use super::walk::{has_preamble, parse};
use super::{dicom_err, tag_name, Image, EXPANSION_SLACK, MAX_FILE_EXPANSION};
use crate::reader::{ReadError, SourceFiles, MAX_SOURCE_FILES};

/// A multi-valued decimal attribute as DICOM writes it (`1\0\0\0\1\0`), or "absent".
fn dicom_values<const N: usize>(v: &Option<[f64; N]>) -> String {
    match v {
        Some(values) => values
            .iter()
            .map(|x| x.to_string())
            .collect::<Vec<_>>()
            .join("\\"),
        None => "absent".to_string(),
    }
}

/// The DICOM files directly inside `dir` (regular, non-hidden files starting with the DICOM
/// preamble), sorted by name: (name, path). Reads 132 bytes of each.
pub(crate) fn series_files(dir: &Path) -> Result<Vec<(String, PathBuf)>, ReadError> {
    let mut entries: Vec<_> = std::fs::read_dir(dir)
        .map_err(|e| ReadError::io(dir, e))?
        .collect::<Result<_, _>>()
        .map_err(|e| ReadError::io(dir, e))?;
    entries.sort_by_key(|e| e.file_name());
    let mut files = Vec::new();
    // The first file that is not DICOM, and how many, for the error of a directory without.
    let mut others: (Option<String>, usize, usize) = (None, 0, 0);
    for e in entries {
        let name = e.file_name().to_string_lossy().into_owned();
        let path = e.path();
        if name.starts_with('.')
            || !e
                .file_type()
                .map_err(|x| ReadError::io(&path, x))?
                .is_file()
        {
            continue;
        }
        if !is_dicom_file(&path).map_err(|x| ReadError::io(&path, x))? {
            others.1 += 1;
            others.2 += usize::from(name.to_ascii_lowercase().ends_with(".raw"));
            others.0.get_or_insert(name);
            continue;
        }
        if files.len() == MAX_SOURCE_FILES {
            return Err(ReadError::Series {
                path: dir.to_path_buf(),
                reason: format!("more than {MAX_SOURCE_FILES} DICOM files"),
            });
        }
        files.push((name, path));
    }
    if files.is_empty() {
        return Err(ReadError::Series {
            path: dir.to_path_buf(),
            reason: without_dicom(others),
        });
    }
    Ok(files)
}

/// Why a directory with no DICOM file is refused, and what it could be read as instead:
/// `others` is the first other file's name, the count of other files and of `.raw` ones.
fn without_dicom((first, count, raws): (Option<String>, usize, usize)) -> String {
    let base = "no DICOM files (files with the DICM preamble) in this directory";
    match first {
        None => format!("{base}: it holds no file"),
        Some(_) if raws > 0 => format!(
            "{base}; its {raws} .raw file(s) are read as a time series of raw steps with \
             --dims X,Y,Z and --dtype"
        ),
        Some(name) => format!(
            "{base}; its {count} other file(s) (`{name}`…) are not volume files of a time \
             series either (.nii, .nii.gz, .nrrd, .nhdr, .mha, .mhd, or .raw with --dims and \
             --dtype); name one file to compress it alone"
        ),
    }
}

/// Whether the file at `path` starts with the DICOM preamble (reads 132 bytes).
pub fn is_dicom_file(path: &Path) -> std::io::Result<bool> {
    use std::io::Read;
    let mut head = [0u8; 132];
    let mut f = std::fs::File::open(path)?;
    let mut got = 0;
    while got < head.len() {
        match f.read(&mut head[got..])? {
            0 => break,
            n => got += n,
        }
    }
    Ok(has_preamble(&head[..got]))
}

/// A series described from its files' headers alone: its images, which image and frame each
/// slice z is, and the volume's geometry. [`decode`] fills the whole volume from it;
/// [`SeriesRegions`] reads boxes of it, decoding only the frames a box crosses.
#[derive(Debug)]
struct Described {
    images: Vec<Image>,
    /// The image and frame of each slice, in volume order.
    frames: Vec<FrameRef>,
    dims: [usize; 3],
    spacing: [f32; 3],
    placement: Option<Placement>,
    channels: usize,
}

/// Reads the image headers of `files` (name, path, bytes; pixel data not decoded).
fn read_headers<'a>(
    files: impl Iterator<Item = Result<(&'a str, PathBuf, std::borrow::Cow<'a, [u8]>), ReadError>>,
) -> Result<Vec<Image>, ReadError> {
    let mut images = Vec::new();
    for file in files {
        let (name, path, bytes) = file?;
        let obj = parse(&path, &bytes, false)?;
        if let Some(img) = read_image(name, &path, &obj, bytes.len())? {
            images.push(img);
        }
    }
    Ok(images)
}

/// Checks that `images` (from files of `file_bytes` bytes in all, in `dir`) form one series with
/// one in-plane geometry and sample format that its files' bytes can hold, and orders and
/// places their frames.
fn describe(dir: &Path, images: Vec<Image>, file_bytes: usize) -> Result<Described, ReadError> {
    let dir = &dir.to_path_buf();
    if images.is_empty() {
        return Err(ReadError::Series {
            path: dir.clone(),
            reason: "no image (no file with Rows and Columns)".into(),
        });
    }
    if images.len() > 1 {
        if let Some(i) = images.iter().find(|i| i.series.is_empty()) {
            return Err(dicom_err(
                &i.path,
                Some(tags::SERIES_INSTANCE_UID),
                "missing (the files of a directory are grouped into one series by it)",
            ));
        }
    }
    let mut by_series: BTreeMap<&str, usize> = BTreeMap::new();
    for i in &images {
        *by_series.entry(i.series.as_str()).or_default() += 1;
    }
    if by_series.len() > 1 {
        let list: Vec<String> = by_series
            .iter()
            .map(|(s, n)| format!("{s} ({n} files)"))
            .collect();
        return Err(ReadError::Series {
            path: dir.clone(),
            reason: format!(
                "holds {} series, one volume needs one: {}; give each series its own directory",
                by_series.len(),
                list.join(", ")
            ),
        });
    }
    let first = images[0].clone();
    // Consistency of the in-plane geometry and sample format.
    for i in &images[1..] {
        let mismatch = |tag: Tag, what: String| {
            Err(ReadError::Series {
                path: dir.clone(),
                reason: format!(
                    "{} differs between {} and {}: {what}",
                    tag_name(tag),
                    first.name,
                    i.name
                ),
            })
        };
        if (i.rows, i.cols) != (first.rows, first.cols) {
            return mismatch(
                tags::ROWS,
                format!(
                    "{}×{} against {}×{}",
                    first.rows, first.cols, i.rows, i.cols
                ),
            );
        }
        if (i.samples, i.bits_allocated, i.bits_stored, i.signed)
            != (
                first.samples,
                first.bits_allocated,
                first.bits_stored,
                first.signed,
            )
        {
            return mismatch(tags::BITS_ALLOCATED, "sample format".into());
        }
        let close =
            |a: &[f64], b: &[f64], tol: f64| a.iter().zip(b).all(|(x, y)| (x - y).abs() <= tol);
        match (&first.pixel_spacing, &i.pixel_spacing) {
            (Some(a), Some(b)) if close(a, b, 1e-4 * a[0].max(a[1])) => {}
            (None, None) => {}
            (a, b) => {
                return mismatch(
                    tags::PIXEL_SPACING,
                    format!("{} against {}", dicom_values(a), dicom_values(b)),
                )
            }
        }
        match (&first.orientation, &i.orientation) {
            (Some(a), Some(b)) if close(a, b, 1e-4) => {}
            (None, None) => {}
            (a, b) => {
                return mismatch(
                    tags::IMAGE_ORIENTATION_PATIENT,
                    format!("{} against {}", dicom_values(a), dicom_values(b)),
                )
            }
        }
    }

    let Ordered {
        frames,
        dims,
        spacing,
        placement,
    } = order_frames(dir, &images)?;

    // The whole volume, too, must come from the files' bytes (one slack per volume, not per
    // file, so that many small files cannot add up to a large buffer).
    let declared: usize = images
        .iter()
        .map(|i| {
            i.rows * i.cols * i.frame_list().len() * i.samples * (i.bits_allocated as usize / 8)
        })
        .fold(0usize, usize::saturating_add);
    let most = file_bytes
        .saturating_mul(MAX_FILE_EXPANSION)
        .saturating_add(EXPANSION_SLACK);
    if declared > most {
        return Err(ReadError::Series {
            path: dir.clone(),
            reason: format!(
                "the images declare {declared} bytes of samples, more than {file_bytes} bytes of files can hold (at most {MAX_FILE_EXPANSION}× + {EXPANSION_SLACK} bytes)"
            ),
        });
    }
    Ok(Described {
        channels: first.channels(),
        frames: frames.into_iter().map(|(f, _)| f).collect(),
        images,
        dims,
        spacing,
        placement,
    })
}

/// Decodes a DICOM volume (a series directory's files, or one multi-frame file).
pub(crate) fn decode(src: &SourceFiles) -> Result<Volume, ReadError> {
    let images = read_headers(src.files.iter().map(|(name, bytes)| {
        Ok((
            name.as_str(),
            src.path_of(name),
            std::borrow::Cow::Borrowed(bytes.as_slice()),
        ))
    }))?;
    let file_bytes: usize = src.files.iter().map(|(_, b)| b.len()).sum();
    let dir = &src.origin;
    let d = describe(dir, images, file_bytes)?;
    let by_name: BTreeMap<&str, &[u8]> = src
        .files
        .iter()
        .map(|(n, b)| (n.as_str(), b.as_slice()))
        .collect();
    decode_described(dir, &d, |img| {
        let obj = parse(&img.path, by_name[img.name.as_str()], true)?;
        check_pixel_data(img, &obj)?;
        Ok(std::borrow::Cow::Owned(obj))
    })
}

/// The volume of described images: each image's frames decoded into their slots, its data
/// set (with pixel data, checked) from `object`.
fn decode_described<'a>(
    dir: &Path,
    d: &Described,
    mut object: impl FnMut(&Image) -> Result<std::borrow::Cow<'a, DefaultDicomObject>, ReadError>,
) -> Result<Volume, ReadError> {
    let [nx, ny, nz] = d.dims;
    let plane = nx * ny;
    let mut slot_of: Vec<Vec<usize>> = d.images.iter().map(|i| vec![0; i.frames]).collect();
    for (z, f) in d.frames.iter().enumerate() {
        slot_of[f.image][f.frame] = z;
    }
    let n = plane * nz;
    let mut out = allocate(dir, d.channels, n)?;
    for (ii, img) in d.images.iter().enumerate() {
        let obj = object(img)?;
        for f in img.frame_list() {
            let z = slot_of[ii][f];
            decode_frame(img, &obj, f, z * plane, &mut out)?;
        }
    }
    let v = Volume::new(d.dims, d.spacing, out).map_err(|e| ReadError::volume(dir, e))?;
    match d.placement {
        Some(p) => v.with_placement(p).map_err(|e| ReadError::volume(dir, e)),
        None => Ok(v),
    }
}

/// The time points of a series (in time order) and their times in seconds, when known.
pub type TimeSeries = (Vec<Volume>, Option<Vec<f64>>);

/// A DICOM series directory whose images repeat the same slices at several time points (a
/// cine MR stack, a 4D CT): each time point's images (grouped by Temporal Position Identifier,
/// else Trigger Time, else Acquisition Time where slices repeat positions) decoded as a volume
/// of its own, with every check a volume gets, in time order; and their times in seconds when
/// Trigger Time or Acquisition Time gives them. `Ok(None)` when the images
/// are not a time series (no time, or one). Every time point must be of the first's
/// dimensions and spacing, and every image must say its time: a missing, mixed or unreadable
/// time is an error naming the file, as is a time point whose slices do not form a volume.
/// The series is held in memory (cine and 4D series are small); a larger one is refused by
/// the volume's own memory checks.
/// A directory holding one multi-frame cine file is that file's series ([`read_cine_file`]).
pub fn read_time_series(dir: &Path) -> Result<Option<TimeSeries>, ReadError> {
    let bad = |reason: String| ReadError::Series {
        path: dir.to_path_buf(),
        reason,
    };
    // Only a series whose (first) image says a time is read whole here: a volume's series
    // (a CT without a trigger) costs one header.
    let listed = series_files(dir)?;
    if let [(_, path)] = listed.as_slice() {
        // One file: a multi-frame cine, or one volume.
        return read_cine_file(path);
    }
    let Some((name, path)) = listed.into_iter().next() else {
        return Ok(None);
    };
    let first = crate::reader::read_file(&path)?;
    let Some(said) = read_headers(std::iter::once(Ok((
        name.as_str(),
        path.clone(),
        std::borrow::Cow::Borrowed(first.as_slice()),
    ))))?
    .first()
    .filter(|i| i.time.is_some())
    .map(|i| i.time_attribute) else {
        return Ok(None);
    };
    drop(first);
    if said == ACQUISITION_TIME {
        // Most volumes' slices say when each was acquired: grouped by it only when slices
        // repeat positions. Headers read one file at a time, no bytes kept (a large volume's
        // series is read by region afterwards).
        let listed = series_files(dir)?;
        let images = read_headers(listed.iter().map(|(name, path)| {
            let bytes = crate::reader::read_file(path)?;
            Ok((name.as_str(), path.clone(), std::borrow::Cow::Owned(bytes)))
        }))?;
        if !positions_repeat(&images) {
            return Ok(None);
        }
    }
    let files = SourceFiles::gather(dir, None)?;
    let images = read_headers(files.files.iter().map(|(name, bytes)| {
        Ok((
            name.as_str(),
            files.path_of(name),
            std::borrow::Cow::Borrowed(bytes.as_slice()),
        ))
    }))?;
    let times: std::collections::BTreeSet<&str> =
        images.iter().filter_map(|i| i.time.as_deref()).collect();
    if times.len() < 2 {
        return Ok(None);
    }
    if let Some(i) = images.iter().find(|i| i.time.is_none()) {
        return Err(bad(format!(
            "a time series whose image {} says no time (Temporal Position Identifier, \
             Trigger Time or Acquisition Time) where the others do",
            i.name
        )));
    }
    let attribute = images[0].time_attribute;
    if let Some(i) = images.iter().find(|i| i.time_attribute != attribute) {
        return Err(bad(format!(
            "a time series whose images say their time by different attributes: {} by {}, {} \
             by {attribute}",
            i.name, i.time_attribute, images[0].name
        )));
    }
    // Time points by their time's text, in order of its value.
    let mut by_text: BTreeMap<&str, Vec<String>> = BTreeMap::new();
    for i in &images {
        by_text
            .entry(i.time.as_deref().unwrap_or_default())
            .or_default()
            .push(i.name.clone());
    }
    let mut groups: Vec<(f64, Vec<String>)> = Vec::with_capacity(by_text.len());
    for (text, names) in by_text {
        let value = if attribute == ACQUISITION_TIME {
            seconds_of_day(text)
        } else {
            text.trim().parse::<f64>().ok()
        };
        let value = value.filter(|v| v.is_finite()).ok_or_else(|| {
            bad(format!(
                "image {} has {attribute} {text:?}, not a number",
                names[0]
            ))
        })?;
        groups.push((value, names));
    }
    groups.sort_by(|a, b| a.0.total_cmp(&b.0));
    if let Some(w) = groups.windows(2).find(|w| w[0].0 == w[1].0) {
        return Err(bad(format!(
            "two time points at {attribute} {}: images {} and {}",
            w[0].0, w[0].1[0], w[1].1[0]
        )));
    }
    let mut volumes: Vec<Volume> = Vec::with_capacity(groups.len());
    let mut values = Vec::with_capacity(groups.len());
    for (t, (value, names)) in groups.into_iter().enumerate() {
        let src = SourceFiles {
            origin: dir.to_path_buf(),
            base: dir.to_path_buf(),
            format: Some(crate::reader::Format::Dicom),
            files: files
                .files
                .iter()
                .filter(|(n, _)| names.contains(n))
                .cloned()
                .collect(),
        };
        let what = format!("time point {t} ({attribute} {value})");
        let v = decode(&src).map_err(|e| bad(format!("{what}: {e}")))?;
        same_space_as_first(&volumes, &v, &what).map_err(bad)?;
        volumes.push(v);
        values.push(value);
    }
    let times = if attribute.starts_with("Trigger Time") {
        Some(values.iter().map(|ms| ms / 1000.0).collect())
    } else if attribute == ACQUISITION_TIME {
        Some(values.iter().map(|s| s - values[0]).collect())
    } else {
        None
    };
    Ok(Some((volumes, times)))
}

/// Refuses time point `v` (named `what`) when it is not of the first of `volumes`' dimensions
/// and spacing, saying both.
fn same_space_as_first(volumes: &[Volume], v: &Volume, what: &str) -> Result<(), String> {
    match volumes.first() {
        Some(first) if v.dims() != first.dims() || v.spacing() != first.spacing() => Err(format!(
            "{what} is {:?} at spacing {:?}; time point 0 is {:?} at {:?}",
            v.dims(),
            v.spacing(),
            first.dims(),
            first.spacing()
        )),
        _ => Ok(()),
    }
}

/// A DICOM time of day (TM: `HHMMSS.FFFFFF`, fields from the right optional, or the older
/// `HH:MM:SS`) in seconds since midnight; `None` when it is not one.
fn seconds_of_day(text: &str) -> Option<f64> {
    let t: String = text.trim().chars().filter(|c| *c != ':').collect();
    let (whole, fraction) = t.split_once('.').unwrap_or((&t, ""));
    if whole.len() < 2 || whole.len() % 2 != 0 || whole.len() > 6 {
        return None;
    }
    if !whole.bytes().all(|b| b.is_ascii_digit()) || !fraction.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    let field = |i: usize| {
        whole
            .get(2 * i..2 * i + 2)
            .map_or(Some(0.0), |f| f.parse::<f64>().ok())
    };
    let (h, m, s) = (field(0)?, field(1)?, field(2)?);
    if h > 23.0 || m > 59.0 || s > 60.0 {
        return None;
    }
    let frac = if fraction.is_empty() {
        0.0
    } else {
        format!("0.{fraction}").parse::<f64>().ok()?
    };
    Some(h * 3600.0 + m * 60.0 + s + frac)
}

/// Whether two frames of `images` lie at one position (to a micrometre): slices repeated at
/// several times, not one volume.
fn positions_repeat(images: &[Image]) -> bool {
    let mut seen = std::collections::HashSet::new();
    images
        .iter()
        .flat_map(|i| i.frame_list().into_iter().filter_map(|f| i.positions[f]))
        .any(|p| !seen.insert(p.map(|x| (x * 1000.0).round() as i64)))
}

/// A multi-frame DICOM file whose frames are instants of one slice over time (a cine MR slice,
/// an ultrasound loop: Frame Increment Pointer → Frame Time or Frame Time Vector, no per-frame
/// positions): each frame a time point, a volume of one slice (columns × rows × 1, the pixel
/// spacing and the slice thickness), every value as the volume reader decodes it (rescale,
/// palette, colour); the times in seconds from Frame Time or Frame Time Vector. An enhanced
/// multi-frame file with a temporal dimension is read by [`read_enhanced_series`]. `Ok(None)`
/// for any other file (a volume's frames, one frame, a file whose header does not parse: the
/// volume reader says what is wrong with it).
pub fn read_cine_file(path: &Path) -> Result<Option<TimeSeries>, ReadError> {
    let bytes = crate::reader::read_file(path)?;
    let Ok(header) = parse(path, &bytes, false) else {
        return Ok(None);
    };
    let Some(times) = super::image::cine_times(path, &header)? else {
        return read_enhanced_series(path, &bytes, &header);
    };
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let img = super::image::read_image_as(&name, path, &header, bytes.len(), true)?
        .ok_or_else(|| dicom_err(path, Some(tags::ROWS), "missing: not an image"))?;
    drop(header);
    let obj = parse(path, &bytes, true)?;
    check_pixel_data(&img, &obj)?;
    let plane = img.rows * img.cols;
    let spacing = match img.pixel_spacing {
        // (row spacing, column spacing): x steps along a row by the column spacing.
        Some([row, col]) => [col as f32, row as f32, img.slice_step.unwrap_or(1.0) as f32],
        None => [1.0, 1.0, img.slice_step.unwrap_or(1.0) as f32],
    };
    let mut volumes = Vec::with_capacity(img.frames);
    for f in 0..img.frames {
        let mut out = allocate(path, img.channels(), plane)?;
        decode_frame(&img, &obj, f, 0, &mut out)?;
        volumes.push(
            Volume::new([img.cols, img.rows, 1], spacing, out)
                .map_err(|e| ReadError::volume(path, e))?,
        );
    }
    Ok(Some((volumes, times)))
}

/// An enhanced multi-frame file whose frames carry a temporal dimension (each frame's Frame
/// Content gives its Temporal Position Index, as an enhanced MR cine or a 4D CT stores it):
/// the frames of each index, in index order, a volume read as one volume's frames are (their
/// per-frame positions ordered and checked); the times in seconds from the frames' Nominal
/// Cardiac Trigger Delay Time when every frame has one and they increase. `Ok(None)` when the
/// file has no temporal dimension.
fn read_enhanced_series(
    path: &Path,
    bytes: &[u8],
    header: &DefaultDicomObject,
) -> Result<Option<TimeSeries>, ReadError> {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let Some(img) = super::image::read_image_as(&name, path, header, bytes.len(), true)? else {
        return Ok(None);
    };
    let Some(index) = img.temporal_index.clone() else {
        return Ok(None);
    };
    let bad = |reason: String| ReadError::Series {
        path: path.to_path_buf(),
        reason,
    };
    let mut by_index: BTreeMap<u32, Vec<usize>> = BTreeMap::new();
    for (f, k) in index.iter().enumerate() {
        by_index.entry(*k).or_default().push(f);
    }
    let obj = parse(path, bytes, true)?;
    check_pixel_data(&img, &obj)?;
    let mut volumes: Vec<Volume> = Vec::with_capacity(by_index.len());
    let mut delays = Vec::with_capacity(by_index.len());
    for (t, (k, frames)) in by_index.into_iter().enumerate() {
        let what = format!("time point {t} (Temporal Position Index {k})");
        if let Some(d) = &img.trigger_delay_ms {
            delays.push(d[frames[0]]);
        }
        let view = Image {
            selected: Some(frames),
            ..img.clone()
        };
        let d = describe(path, vec![view], bytes.len()).map_err(|e| bad(format!("{what}: {e}")))?;
        let v = decode_described(path, &d, |_| Ok(std::borrow::Cow::Borrowed(&obj)))
            .map_err(|e| bad(format!("{what}: {e}")))?;
        same_space_as_first(&volumes, &v, &what).map_err(bad)?;
        volumes.push(v);
    }
    let times = (delays.len() == volumes.len() && delays.windows(2).all(|w| w[1] > w[0]))
        .then(|| delays.iter().map(|ms| ms / 1000.0).collect());
    Ok(Some((volumes, times)))
}

/// `channels` zeroed buffers of `n` samples, or an error naming `dir` when memory is short.
fn allocate(dir: &Path, channels: usize, n: usize) -> Result<Vec<Vec<f32>>, ReadError> {
    let mut out: Vec<Vec<f32>> = Vec::with_capacity(channels);
    for _ in 0..channels {
        let mut c = Vec::new();
        c.try_reserve_exact(n).map_err(|_| ReadError::Series {
            path: dir.to_path_buf(),
            reason: format!("cannot allocate {n} voxels"),
        })?;
        c.resize(n, 0.0);
        out.push(c);
    }
    Ok(out)
}

/// A DICOM series (a directory, or one multi-frame file) opened to read boxes of it by slice
/// ranges: opening reads each file once for its header and keeps none of the bytes; a box
/// reads and decodes only the files holding its slices, one frame at a time, so memory is that
/// of the box plus one frame, whatever the series' size. Validation and ordering are
/// [`decode`]'s own (one [`describe`]), so a box holds exactly what the whole decode gives
/// those voxels.
#[derive(Debug)]
pub(crate) struct SeriesRegions {
    origin: PathBuf,
    described: Described,
}

impl SeriesRegions {
    /// Opens the series at `path`: a directory of DICOM files or one DICOM file.
    pub(crate) fn open(path: &Path) -> Result<SeriesRegions, ReadError> {
        let meta = std::fs::metadata(path).map_err(|e| ReadError::io(path, e))?;
        let files: Vec<(String, PathBuf)> = if meta.is_dir() {
            series_files(path)?
        } else {
            let name = path
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default();
            vec![(name, path.to_path_buf())]
        };
        let mut file_bytes = 0usize;
        let images = read_headers(files.iter().map(|(name, path)| {
            let bytes = crate::reader::read_file(path)?;
            file_bytes = file_bytes.saturating_add(bytes.len());
            Ok((name.as_str(), path.clone(), std::borrow::Cow::Owned(bytes)))
        }))?;
        let described = describe(path, images, file_bytes)?;
        Ok(SeriesRegions {
            origin: path.to_path_buf(),
            described,
        })
    }

    /// Dimensions (x, y, z) of the whole volume.
    pub(crate) fn dims(&self) -> [usize; 3] {
        self.described.dims
    }

    /// Channels (1, or 3 for colour).
    pub(crate) fn channels(&self) -> usize {
        self.described.channels
    }

    /// Voxel spacing, as [`decode`] gives it.
    pub(crate) fn spacing(&self) -> [f32; 3] {
        self.described.spacing
    }

    /// Placement of voxel (0, 0, 0), as [`decode`] gives it.
    pub(crate) fn placement(&self) -> Option<&Placement> {
        self.described.placement.as_ref()
    }

    /// The planar channels of the box of `size` at `origin` (within the volume, checked by the
    /// caller), with the modality rescale, as [`decode`] gives those voxels.
    pub(crate) fn read(
        &self,
        origin: [usize; 3],
        size: [usize; 3],
    ) -> Result<Vec<Vec<f32>>, ReadError> {
        let d = &self.described;
        let [nx, ny, _] = d.dims;
        let plane = nx * ny;
        let mut out = allocate(&self.origin, d.channels, size.iter().product())?;
        let mut frame = allocate(&self.origin, d.channels, plane)?;
        // The box's slices by file, so each file is read and parsed once per box.
        let mut by_image: BTreeMap<usize, Vec<(usize, usize)>> = BTreeMap::new();
        for z in origin[2]..origin[2] + size[2] {
            let f = d.frames[z];
            by_image
                .entry(f.image)
                .or_default()
                .push((z - origin[2], f.frame));
        }
        for (ii, slices) in by_image {
            let img = &d.images[ii];
            let bytes = crate::reader::read_file(&img.path)?;
            let obj = parse(&img.path, &bytes, true)?;
            check_pixel_data(img, &obj)?;
            for (bz, f) in slices {
                decode_frame(img, &obj, f, 0, &mut frame)?;
                for (c, channel) in out.iter_mut().enumerate() {
                    for by in 0..size[1] {
                        let from = (origin[1] + by) * nx + origin[0];
                        let to = (bz * size[1] + by) * size[0];
                        channel[to..to + size[0]].copy_from_slice(&frame[c][from..from + size[0]]);
                    }
                }
            }
        }
        Ok(out)
    }
}
