//! Series discovery and assembly: which files of a directory are DICOM (the `DICM` preamble),
//! and [`decode`], which reads every file's header, checks that the images form one series
//! with one in-plane geometry and sample format, has [`super::geometry`] order and place the
//! frames, holds the volume to what the files' bytes can hold, and decodes each file's frames
//! into their slots.

use std::collections::BTreeMap;
use std::path::Path;

use dicom_core::Tag;
use dicom_dictionary_std::tags;
use wavesplat_codec::volume::Volume;

use super::geometry::{order_frames, Ordered};
use super::image::read_image;
use super::pixels::{check_pixel_data, decode_frame};
use super::walk::{has_preamble, parse};
use super::{dicom_err, tag_name, EXPANSION_SLACK, MAX_FILE_EXPANSION};
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

/// Gathers the DICOM files directly inside `dir` (regular, non-hidden files starting with the
/// DICOM preamble), sorted by name.
pub(crate) fn gather_series(dir: &Path) -> Result<SourceFiles, ReadError> {
    let mut entries: Vec<_> = std::fs::read_dir(dir)
        .map_err(|e| ReadError::io(dir, e))?
        .collect::<Result<_, _>>()
        .map_err(|e| ReadError::io(dir, e))?;
    entries.sort_by_key(|e| e.file_name());
    let mut files = Vec::new();
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
            continue;
        }
        if files.len() == MAX_SOURCE_FILES {
            return Err(ReadError::Series {
                path: dir.to_path_buf(),
                reason: format!("more than {MAX_SOURCE_FILES} DICOM files"),
            });
        }
        files.push((name, crate::reader::read_file(&path)?));
    }
    if files.is_empty() {
        return Err(ReadError::Series {
            path: dir.to_path_buf(),
            reason: "no DICOM files (files with the DICM preamble) in this directory".into(),
        });
    }
    Ok(SourceFiles {
        origin: dir.to_path_buf(),
        base: dir.to_path_buf(),
        format: Some(crate::reader::Format::Dicom),
        files,
    })
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

/// Decodes a DICOM volume (a series directory's files, or one multi-frame file).
pub(crate) fn decode(src: &SourceFiles) -> Result<Volume, ReadError> {
    // Pass 1: headers only.
    let mut images = Vec::new();
    for (name, bytes) in &src.files {
        let path = src.path_of(name);
        let obj = parse(&path, bytes, false)?;
        if let Some(img) = read_image(name, &path, &obj, bytes.len())? {
            images.push(img);
        }
    }
    let dir = &src.origin;
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
    let [nx, ny, nz] = dims;
    let plane = nx * ny;

    // The whole volume, too, must come from the files' bytes (one slack per volume, not per
    // file, so that many small files cannot add up to a large buffer).
    let file_bytes: usize = src.files.iter().map(|(_, b)| b.len()).sum();
    let declared: usize = images
        .iter()
        .map(|i| i.rows * i.cols * i.frames * i.samples * (i.bits_allocated as usize / 8))
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

    // Pass 2: decode each file's frames into their slots.
    let mut slot_of: Vec<Vec<usize>> = images.iter().map(|i| vec![0; i.frames]).collect();
    for (z, (f, _)) in frames.iter().enumerate() {
        slot_of[f.image][f.frame] = z;
    }
    let channels = first.channels();
    let n = plane * nz;
    let mut out: Vec<Vec<f32>> = Vec::with_capacity(channels);
    for _ in 0..channels {
        let mut c = Vec::new();
        c.try_reserve_exact(n).map_err(|_| ReadError::Series {
            path: dir.clone(),
            reason: format!("cannot allocate {n} voxels"),
        })?;
        c.resize(n, 0.0);
        out.push(c);
    }
    let by_name: BTreeMap<&str, &[u8]> = src
        .files
        .iter()
        .map(|(n, b)| (n.as_str(), b.as_slice()))
        .collect();
    for (ii, img) in images.iter().enumerate() {
        let obj = parse(&img.path, by_name[img.name.as_str()], true)?;
        check_pixel_data(img, &obj)?;
        for f in 0..img.frames {
            let z = slot_of[ii][f];
            decode_frame(img, &obj, f, z * plane, &mut out)?;
        }
    }
    let v = Volume::new(dims, spacing, out).map_err(|e| ReadError::volume(dir, e))?;
    match placement {
        Some(p) => v.with_placement(p).map_err(|e| ReadError::volume(dir, e)),
        None => Ok(v),
    }
}
