//! Image description: what the reader needs of one file's header ([`Image`]), read and checked
//! before any pixel is decoded: size and frame count (held to the file's size), sample format,
//! photometric interpretation and palette, pixel spacing, orientation, per-frame positions
//! (from the functional groups, the slice step or an RT Dose grid's offsets), rescale and
//! Dose Grid Scaling, and the refusal of multi-frame files that are time series.

use std::path::Path;

use dicom_core::Tag;
use dicom_dictionary_std::tags;
use dicom_object::{DefaultDicomObject, InMemDicomObject};
use wavesplat_codec::volume::MAX_VOXELS;

use super::attributes::{element, floats_for_frame, get_floats, get_str, get_uint, require_uint};
use super::colour::read_palette;
use super::geometry::{grid_frame_offsets, normal};
use super::Image;
use super::{dicom_err, EXPANSION_SLACK, MAX_FILE_EXPANSION};
use crate::reader::ReadError;

/// SOP Class UID of a DICOMDIR (Media Storage Directory Storage): skipped in series directories.
const DICOMDIR_SOP_CLASS: &str = "1.2.840.10008.1.3.10";

/// Reads what the reader needs of an image's header; `file_len` (the file's size) bounds the
/// frames and sample bytes it may declare, so that a small file cannot make the per-frame
/// loops or the voxel buffer large.
pub(super) fn read_image(
    name: &str,
    path: &Path,
    obj: &DefaultDicomObject,
    file_len: usize,
) -> Result<Option<Image>, ReadError> {
    read_image_as(name, path, obj, file_len, false)
}

/// [`read_image`]; `cine`: a multi-frame file whose frames are instants of one slice over time
/// is read as such (its frames keep the first frame's position), not refused.
pub(super) fn read_image_as(
    name: &str,
    path: &Path,
    obj: &DefaultDicomObject,
    file_len: usize,
    cine: bool,
) -> Result<Option<Image>, ReadError> {
    let meta = obj.meta();
    if meta.media_storage_sop_class_uid().trim_end_matches('\0') == DICOMDIR_SOP_CLASS {
        return Ok(None);
    }
    let o: &InMemDicomObject = obj;
    let (Some(rows), Some(cols)) = (
        get_uint(path, o, tags::ROWS)?,
        get_uint(path, o, tags::COLUMNS)?,
    ) else {
        tracing::debug!(file = %path.display(), "no Rows/Columns: not an image, skipped");
        return Ok(None);
    };
    if rows == 0 || cols == 0 {
        return Err(dicom_err(
            path,
            Some(if rows == 0 { tags::ROWS } else { tags::COLUMNS }),
            "is 0",
        ));
    }
    // Empty when missing: a single file is its own series; files of a directory are grouped
    // by it, and there a missing one is refused (`read_series`).
    let series = get_str(o, tags::SERIES_INSTANCE_UID).unwrap_or_default();
    let frames = get_uint(path, o, tags::NUMBER_OF_FRAMES)?
        .unwrap_or(1)
        .max(1) as usize;
    let samples = get_uint(path, o, tags::SAMPLES_PER_PIXEL)?.unwrap_or(1) as usize;
    if samples != 1 && samples != 3 {
        return Err(dicom_err(
            path,
            Some(tags::SAMPLES_PER_PIXEL),
            format!("{samples}; 1 or 3 supported"),
        ));
    }
    let plane = (rows as usize) * (cols as usize);
    let total = plane
        .checked_mul(frames)
        .filter(|n| *n <= MAX_VOXELS)
        .ok_or_else(|| {
            dicom_err(
                path,
                Some(tags::NUMBER_OF_FRAMES),
                format!("{rows} rows × {cols} columns × {frames} frames exceed the {MAX_VOXELS}-voxel limit"),
            )
        })?;
    let bits_allocated = require_uint(path, o, tags::BITS_ALLOCATED)?;
    if !matches!(bits_allocated, 1 | 8 | 16 | 32) || bits_allocated == 1 && samples != 1 {
        return Err(dicom_err(
            path,
            Some(tags::BITS_ALLOCATED),
            format!(
                "{bits_allocated} with {samples} sample(s) per pixel; 8, 16 or 32 supported, \
                 and 1 (a bit mask) with one sample"
            ),
        ));
    }
    // Every frame needs at least one byte of the file (a native sample, or an encapsulated
    // fragment), and no transfer syntax expands the file beyond MAX_FILE_EXPANSION.
    let declared = total
        .saturating_mul(samples)
        .saturating_mul(bits_allocated as usize)
        .div_ceil(8);
    let most = file_len
        .saturating_mul(MAX_FILE_EXPANSION)
        .saturating_add(EXPANSION_SLACK);
    if frames > file_len || declared > most {
        return Err(dicom_err(
            path,
            Some(tags::PIXEL_DATA),
            format!(
                "{rows}×{cols} × {frames} frame(s) × {samples} sample(s) × {} byte(s) = {declared} bytes cannot come from a file of {file_len} bytes (at most {MAX_FILE_EXPANSION}× its size + {EXPANSION_SLACK} bytes)",
                bits_allocated / 8
            ),
        ));
    }
    let bits_stored = get_uint(path, o, tags::BITS_STORED)?.unwrap_or(bits_allocated);
    if bits_stored == 0 || bits_stored > bits_allocated {
        return Err(dicom_err(
            path,
            Some(tags::BITS_STORED),
            format!("{bits_stored} with {bits_allocated} bits allocated"),
        ));
    }
    let high_bit = get_uint(path, o, tags::HIGH_BIT)?.unwrap_or(bits_stored - 1);
    if high_bit != bits_stored - 1 {
        return Err(dicom_err(
            path,
            Some(tags::HIGH_BIT),
            format!("{high_bit} with {bits_stored} bits stored; only High Bit = Bits Stored − 1 is supported"),
        ));
    }
    let signed = match get_uint(path, o, tags::PIXEL_REPRESENTATION)?.unwrap_or(0) {
        0 => false,
        1 => true,
        r => {
            return Err(dicom_err(
                path,
                Some(tags::PIXEL_REPRESENTATION),
                format!("{r}; 0 or 1"),
            ))
        }
    };
    let photometric =
        get_str(o, tags::PHOTOMETRIC_INTERPRETATION).unwrap_or_else(|| "MONOCHROME2".into());
    let ok_photometric = match samples {
        1 => matches!(
            photometric.as_str(),
            "MONOCHROME1" | "MONOCHROME2" | "PALETTE COLOR"
        ),
        _ => matches!(
            photometric.as_str(),
            "RGB" | "YBR_FULL" | "YBR_FULL_422" | "YBR_ICT" | "YBR_RCT"
        ),
    };
    if !ok_photometric {
        return Err(dicom_err(
            path,
            Some(tags::PHOTOMETRIC_INTERPRETATION),
            format!("{photometric} with {samples} sample(s) per pixel; supported are MONOCHROME1/2 and PALETTE COLOR (one sample), RGB, YBR_FULL, YBR_FULL_422 and (JPEG 2000) YBR_ICT/YBR_RCT (three)"),
        ));
    }
    let palette = if photometric == "PALETTE COLOR" {
        Some(std::sync::Arc::new(read_palette(path, o, signed)?))
    } else {
        None
    };
    let pixel_spacing = match floats_for_frame(
        path,
        o,
        0,
        tags::PIXEL_MEASURES_SEQUENCE,
        tags::PIXEL_SPACING,
    )?
    .or(get_floats(path, o, tags::IMAGER_PIXEL_SPACING)?)
    {
        None => None,
        Some(v) if v.len() >= 2 && v[0] > 0.0 && v[1] > 0.0 => Some([v[0], v[1]]),
        Some(v) => {
            return Err(dicom_err(
                path,
                Some(tags::PIXEL_SPACING),
                format!("{v:?}: two positive numbers expected"),
            ))
        }
    };
    let orientation = match floats_for_frame(
        path,
        o,
        0,
        tags::PLANE_ORIENTATION_SEQUENCE,
        tags::IMAGE_ORIENTATION_PATIENT,
    )? {
        None => None,
        Some(v) if v.len() == 6 => Some([v[0], v[1], v[2], v[3], v[4], v[5]]),
        Some(v) => {
            return Err(dicom_err(
                path,
                Some(tags::IMAGE_ORIENTATION_PATIENT),
                format!("{v:?}: six numbers expected"),
            ))
        }
    };
    let slice_step = {
        let mut s = None;
        for tag in [tags::SPACING_BETWEEN_SLICES, tags::SLICE_THICKNESS] {
            if let Some(v) = floats_for_frame(path, o, 0, tags::PIXEL_MEASURES_SEQUENCE, tag)? {
                if let Some(x) = v.first().copied().filter(|x| *x > 0.0) {
                    s = Some(x);
                    break;
                }
            }
        }
        s
    };
    // Per-frame positions: the functional groups, or the top level for frame 0 (classic
    // multi-frame files then step along the normal by the slice step).
    let mut positions = Vec::with_capacity(frames.min(1 << 16));
    for f in 0..frames {
        let p = match floats_for_frame(
            path,
            o,
            f,
            tags::PLANE_POSITION_SEQUENCE,
            tags::IMAGE_POSITION_PATIENT,
        )? {
            None => None,
            Some(v) if v.len() == 3 => Some([v[0], v[1], v[2]]),
            Some(v) => {
                return Err(dicom_err(
                    path,
                    Some(tags::IMAGE_POSITION_PATIENT),
                    format!("{v:?}: three numbers expected"),
                ))
            }
        };
        positions.push(p);
    }
    let has_per_frame = element(o, tags::PER_FRAME_FUNCTIONAL_GROUPS_SEQUENCE).is_some();
    let grid_offsets = get_floats(path, o, tags::GRID_FRAME_OFFSET_VECTOR)?;
    let over_time = frames > 1 && !has_per_frame && grid_offsets.is_none() && {
        let temporal = temporal_attribute(o);
        if let (Some(t), false) = (temporal, cine) {
            return Err(refusal(path, t, frames));
        }
        temporal.is_some()
    };
    if frames > 1 && !has_per_frame && !over_time {
        if let (Some(p0), Some(iop)) = (positions[0], orientation) {
            let n = normal(&iop);
            let offsets = match &grid_offsets {
                Some(g) => grid_frame_offsets(path, g, frames, p0, n)?,
                None => {
                    let step = slice_step.ok_or_else(|| {
                        dicom_err(
                            path,
                            Some(tags::SPACING_BETWEEN_SLICES),
                            "missing: a multi-frame file without per-frame positions needs the \
                             slice step (or, for RT Dose, Grid Frame Offset Vector (3004,000C))",
                        )
                    })?;
                    (0..frames).map(|f| f as f64 * step).collect()
                }
            };
            for (p, k) in positions.iter_mut().zip(offsets) {
                *p = Some([p0[0] + k * n[0], p0[1] + k * n[1], p0[2] + k * n[2]]);
            }
        }
    }
    // RT Dose: stored values × Dose Grid Scaling are the dose (in Dose Units, Gy or relative).
    let dose_scaling = match get_floats(path, o, tags::DOSE_GRID_SCALING)? {
        None => 1.0,
        Some(v) => match v.first().copied() {
            Some(x) if x > 0.0 => x,
            _ => {
                return Err(dicom_err(
                    path,
                    Some(tags::DOSE_GRID_SCALING),
                    format!("{v:?}: one positive number expected"),
                ))
            }
        },
    };
    let mut rescale = Vec::with_capacity(frames.min(1 << 16));
    for f in 0..frames {
        let slope = floats_for_frame(
            path,
            o,
            f,
            tags::PIXEL_VALUE_TRANSFORMATION_SEQUENCE,
            tags::RESCALE_SLOPE,
        )?
        .and_then(|v| v.first().copied())
        .unwrap_or(1.0);
        let intercept = floats_for_frame(
            path,
            o,
            f,
            tags::PIXEL_VALUE_TRANSFORMATION_SEQUENCE,
            tags::RESCALE_INTERCEPT,
        )?
        .and_then(|v| v.first().copied())
        .unwrap_or(0.0);
        if slope == 0.0 {
            return Err(dicom_err(path, Some(tags::RESCALE_SLOPE), "is 0"));
        }
        rescale.push(if samples == 3 {
            (1.0, 0.0)
        } else {
            (slope * dose_scaling, intercept * dose_scaling)
        });
    }
    // An enhanced multi-frame file's temporal dimension: each frame's Temporal Position Index
    // and Nominal Cardiac Trigger Delay Time, when every frame has one of its own.
    let per_frame = |seq: Tag, tag: Tag| -> Result<Option<Vec<f64>>, ReadError> {
        if !has_per_frame {
            return Ok(None);
        }
        let mut values = Vec::with_capacity(frames.min(1 << 16));
        for f in 0..frames {
            match floats_for_frame(path, o, f, seq, tag)?.and_then(|v| v.first().copied()) {
                Some(v) => values.push(v),
                None => return Ok(None),
            }
        }
        Ok(Some(values))
    };
    let temporal_index = per_frame(tags::FRAME_CONTENT_SEQUENCE, tags::TEMPORAL_POSITION_INDEX)?
        .map(|v| {
            v.into_iter()
                .map(|x| x.max(0.0) as u32)
                .collect::<Vec<u32>>()
        })
        .filter(|v| v.iter().any(|x| *x != v[0]));
    let trigger_delay_ms = per_frame(
        tags::CARDIAC_SYNCHRONIZATION_SEQUENCE,
        tags::NOMINAL_CARDIAC_TRIGGER_DELAY_TIME,
    )?;
    if let (Some(index), false) = (&temporal_index, cine) {
        let points = index
            .iter()
            .collect::<std::collections::BTreeSet<_>>()
            .len();
        return Err(dicom_err(
            path,
            Some(tags::TEMPORAL_POSITION_INDEX),
            format!(
                "a time series, not a volume: {frames} frames at {points} time points (each \
                 frame's Frame Content (0020,9111) gives its Temporal Position Index). \
                 `wavesplat compress` reads it as a time series of {points} time points"
            ),
        ));
    }
    let instance = get_str(o, tags::INSTANCE_NUMBER)
        .and_then(|s| s.parse::<i64>().ok())
        .unwrap_or(0);
    let (time, time_attribute) = [
        (
            tags::TEMPORAL_POSITION_IDENTIFIER,
            "Temporal Position Identifier (0020,0100)",
        ),
        (tags::TRIGGER_TIME, "Trigger Time (0018,1060)"),
        (tags::ACQUISITION_TIME, ACQUISITION_TIME),
    ]
    .into_iter()
    .find_map(|(t, name)| get_str(o, t).map(|v| (Some(v), name)))
    .unwrap_or((None, ""));
    Ok(Some(Image {
        name: name.to_string(),
        path: path.to_path_buf(),
        series,
        rows: rows as usize,
        cols: cols as usize,
        frames,
        samples,
        bits_allocated,
        bits_stored,
        signed,
        pixel_spacing,
        orientation,
        positions,
        rescale,
        slice_step,
        instance,
        time,
        time_attribute,
        photometric,
        palette,
        temporal_index,
        trigger_delay_ms,
        selected: None,
    }))
}

/// The name of Acquisition Time in messages (and how a time series says it is grouped by it).
pub(super) const ACQUISITION_TIME: &str = "Acquisition Time (0008,0032)";

/// Attributes that make a multi-frame image's frames instants of one acquisition over time
/// (cine, gated) rather than slices of a volume.
const TEMPORAL_ATTRIBUTES: [(Tag, &str); 5] = [
    (tags::FRAME_TIME, "Frame Time"),
    (tags::FRAME_TIME_VECTOR, "Frame Time Vector"),
    (tags::TRIGGER_TIME, "Trigger Time"),
    (tags::ACTUAL_FRAME_DURATION, "Actual Frame Duration"),
    (tags::TIME_SLOT_VECTOR, "Time Slot Vector"),
];

/// How a multi-frame file without per-frame positions says its frames step through time: the
/// temporal attribute (its tag, its name) and how (its Frame Increment Pointer names it, or it
/// has it and its pointer names nothing spatial); `None` when nothing does (a volume's frames).
type Temporal = (Tag, &'static str, &'static str);

fn temporal_attribute(o: &InMemDicomObject) -> Option<Temporal> {
    let pointers: Vec<Tag> =
        match element(o, tags::FRAME_INCREMENT_POINTER).and_then(|e| e.value().primitive()) {
            Some(dicom_core::PrimitiveValue::Tags(t)) => t.to_vec(),
            _ => Vec::new(),
        };
    let by_pointer = TEMPORAL_ATTRIBUTES
        .iter()
        .find(|(t, _)| pointers.contains(t));
    let present = TEMPORAL_ATTRIBUTES
        .iter()
        .find(|(t, _)| element(o, *t).is_some());
    let spatial_pointer = pointers
        .iter()
        .any(|t| !TEMPORAL_ATTRIBUTES.iter().any(|(x, _)| x == t));
    match (by_pointer, present) {
        (Some((t, n)), _) => Some((*t, *n, "its Frame Increment Pointer (0028,0009) names")),
        (None, Some((t, n))) if !spatial_pointer => Some((*t, *n, "it has")),
        _ => None,
    }
}

/// One volume's readers refuse a multi-frame cine (stacking time as depth would draw a cine
/// loop as a volume), saying what it is and what reads it.
fn refusal(path: &Path, (tag, name, how): Temporal, frames: usize) -> ReadError {
    dicom_err(
        path,
        Some(tags::FRAME_INCREMENT_POINTER),
        format!(
            "a time series, not a volume: {frames} frames of one slice over time ({how} {name} \
             ({:04X},{:04X}) and no frame has a position of its own). `wavesplat compress` \
             reads it as a time series of {frames} time points",
            tag.group(),
            tag.element()
        ),
    )
}

/// Of a multi-frame file whose frames are instants of one slice over time (a cine, an
/// ultrasound loop): the frames' times in seconds when Frame Time or Frame Time Vector gives
/// them (`Some(None)` when only another temporal attribute says it is a cine); `None` when the
/// file is not such a cine.
pub(super) fn cine_times(
    path: &Path,
    obj: &DefaultDicomObject,
) -> Result<Option<Option<Vec<f64>>>, ReadError> {
    let o: &InMemDicomObject = obj;
    let frames = get_uint(path, o, tags::NUMBER_OF_FRAMES)?.unwrap_or(1) as usize;
    if frames <= 1
        || element(o, tags::PER_FRAME_FUNCTIONAL_GROUPS_SEQUENCE).is_some()
        || get_floats(path, o, tags::GRID_FRAME_OFFSET_VECTOR)?.is_some()
        || temporal_attribute(o).is_none()
    {
        return Ok(None);
    }
    let bad = |what: String| dicom_err(path, Some(tags::FRAME_TIME_VECTOR), what);
    if let Some(v) = get_floats(path, o, tags::FRAME_TIME_VECTOR)? {
        // Per frame: the time since the previous frame (the first's is 0), in ms.
        if v.len() != frames {
            return Err(bad(format!("{} values for {frames} frames", v.len())));
        }
        let mut at = 0.0;
        let mut times = Vec::with_capacity(frames);
        for (f, dt) in v.iter().enumerate() {
            if !(dt.is_finite() && (*dt > 0.0 || f == 0) && *dt >= 0.0) {
                return Err(bad(format!("frame {f}: an increment of {dt} ms")));
            }
            at += dt;
            times.push(at / 1000.0);
        }
        return Ok(Some(Some(times)));
    }
    if let Some(ft) = get_floats(path, o, tags::FRAME_TIME)?.and_then(|v| v.first().copied()) {
        if !(ft.is_finite() && ft > 0.0) {
            return Err(dicom_err(
                path,
                Some(tags::FRAME_TIME),
                format!("{ft} ms between frames"),
            ));
        }
        return Ok(Some(Some(
            (0..frames).map(|f| f as f64 * ft / 1000.0).collect(),
        )));
    }
    Ok(Some(None))
}
