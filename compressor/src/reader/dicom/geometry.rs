//! Frame geometry: the slice normal, the frames' order along it (or by Instance Number where
//! there is no geometry), the checks on the steps between them (duplicates, gaps, irregular
//! spacing, shear, time points), the voxel spacing and the volume's placement; and the offsets
//! of an RT Dose grid's frames from its Grid Frame Offset Vector.

use std::path::Path;

use dicom_dictionary_std::tags;
use wavesplat_codec::volume::Placement;

use super::dicom_err;
use super::Image;
use crate::reader::{voxel_count, ReadError};

/// The offsets along the slice normal of an RT Dose grid's frames from Grid Frame Offset
/// Vector (PS3.3 C.8.8.3.2): relative to Image Position (Patient) when its first value is 0,
/// otherwise the frames' z coordinates, which only an axial grid may use.
pub(super) fn grid_frame_offsets(
    path: &Path,
    g: &[f64],
    frames: usize,
    p0: [f64; 3],
    n: [f64; 3],
) -> Result<Vec<f64>, ReadError> {
    let err = |reason: String| dicom_err(path, Some(tags::GRID_FRAME_OFFSET_VECTOR), reason);
    if g.len() != frames {
        return Err(err(format!("{} values for {frames} frames", g.len())));
    }
    if g[0] == 0.0 {
        return Ok(g.to_vec());
    }
    let axial = n[0].abs() < 1e-6 && n[1].abs() < 1e-6 && (n[2].abs() - 1.0).abs() < 1e-6;
    if !axial {
        return Err(err(format!(
            "absolute offsets (first value {}) need an axial grid; this one's normal is {n:?}",
            g[0]
        )));
    }
    if (g[0] - p0[2]).abs() > 1e-3 * g[0].abs().max(1.0) {
        return Err(err(format!(
            "absolute offsets start at z = {}, but Image Position (Patient) is at z = {}",
            g[0], p0[2]
        )));
    }
    Ok(g.iter().map(|z| (z - p0[2]) * n[2]).collect())
}

pub(super) fn normal(iop: &[f64; 6]) -> [f64; 3] {
    let (r, c) = ([iop[0], iop[1], iop[2]], [iop[3], iop[4], iop[5]]);
    [
        r[1] * c[2] - r[2] * c[1],
        r[2] * c[0] - r[0] * c[2],
        r[0] * c[1] - r[1] * c[0],
    ]
}

pub(super) fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// One frame of the volume, in its final order.
#[derive(Debug, Clone, Copy)]
pub(super) struct FrameRef {
    pub(super) image: usize,
    pub(super) frame: usize,
}

/// Checks the sorted positions: distinct, evenly spaced along the normal (reporting gaps), and
/// stacked along it (no shear). Returns the slice step.
pub(super) fn check_steps(
    dir: &Path,
    images: &[Image],
    frames: &[(FrameRef, Option<[f64; 3]>)],
    pos: &[[f64; 3]],
    n: [f64; 3],
) -> Result<f64, ReadError> {
    let label = |k: usize| {
        let f = frames[k].0;
        let img = &images[f.image];
        if img.frames > 1 {
            format!("{} frame {} at {:?}", img.name, f.frame + 1, pos[k])
        } else {
            format!("{} at {:?}", img.name, pos[k])
        }
    };
    let nz = pos.len();
    let d: Vec<f64> = (1..nz)
        .map(|k| dot(pos[k], n) - dot(pos[k - 1], n))
        .collect();
    let total = dot(pos[nz - 1], n) - dot(pos[0], n);
    for (k, dk) in d.iter().enumerate() {
        if *dk <= 1e-4 {
            let (a, b) = (&images[frames[k].0.image], &images[frames[k + 1].0.image]);
            let times: std::collections::BTreeSet<&str> =
                images.iter().filter_map(|i| i.time.as_deref()).collect();
            let reason = match (&a.time, &b.time) {
                (Some(ta), Some(tb)) if ta != tb => format!(
                    "a time series (4D), not a volume: the same slices at {} time points ({} \
                     {ta} and {tb} at one position: {} and {}). `wavesplat compress` reads \
                     it as a time series (every time point in one file), `--time-point N` \
                     takes one volume out",
                    times.len(),
                    a.time_attribute,
                    label(k),
                    label(k + 1)
                ),
                _ => format!(
                    "two slices at the same position along the normal: {} and {} (several \
                     acquisitions in one series?)",
                    label(k),
                    label(k + 1)
                ),
            };
            return Err(ReadError::Series {
                path: dir.to_path_buf(),
                reason,
            });
        }
    }
    let mut sorted = d.clone();
    sorted.sort_by(f64::total_cmp);
    let typical = sorted[sorted.len() / 2];
    let tol = (0.01 * typical).max(1e-3);
    for (k, dk) in d.iter().enumerate() {
        if (dk - typical).abs() > tol {
            let ratio = dk / typical;
            let reason = if ratio > 1.5 && (ratio - ratio.round()).abs() * typical <= tol {
                format!(
                    "a gap: {} slice(s) missing between {} and {} ({dk:.4} mm apart, slices are {typical:.4} mm apart elsewhere)",
                    ratio.round() as i64 - 1,
                    label(k),
                    label(k + 1)
                )
            } else {
                format!(
                    "irregular slice spacing: {} and {} are {dk:.4} mm apart, slices are {typical:.4} mm apart elsewhere",
                    label(k),
                    label(k + 1)
                )
            };
            return Err(ReadError::Series {
                path: dir.to_path_buf(),
                reason,
            });
        }
    }
    let step = total / (nz - 1) as f64;
    // Stacked along the normal: the mean step between neighbours has no in-plane part.
    let delta = [0, 1, 2].map(|c| (pos[nz - 1][c] - pos[0][c]) / (nz - 1) as f64);
    let along = dot(delta, n);
    let lateral = [0, 1, 2].map(|c| delta[c] - along * n[c]);
    let shear = dot(lateral, lateral).sqrt();
    if shear > (0.01 * step).max(1e-3) {
        return Err(ReadError::Series {
            path: dir.to_path_buf(),
            reason: format!(
                "the slices are not stacked along their normal (each is shifted {shear:.4} mm sideways per {step:.4} mm step, a tilt of {:.2}°: gantry tilt or a sheared acquisition is not supported)",
                shear.atan2(step).to_degrees()
            ),
        });
    }
    Ok(step)
}

/// The frames of a series in volume order, with the volume's size, voxel spacing and
/// placement ([`order_frames`]).
pub(super) struct Ordered {
    /// Each frame and its position, in volume order.
    pub(super) frames: Vec<(FrameRef, Option<[f64; 3]>)>,
    pub(super) dims: [usize; 3],
    pub(super) spacing: [f32; 3],
    pub(super) placement: Option<Placement>,
}

/// Orders the frames of `images` (one series, in-plane geometry already checked to agree)
/// along the slice normal by position, checking the steps between them, or by Instance
/// Number where they have no geometry; `dir` names the series in errors.
pub(super) fn order_frames(dir: &Path, images: &[Image]) -> Result<Ordered, ReadError> {
    let first = &images[0];
    let mut frames: Vec<(FrameRef, Option<[f64; 3]>)> = Vec::new();
    for (ii, img) in images.iter().enumerate() {
        for f in img.frame_list() {
            frames.push((
                FrameRef {
                    image: ii,
                    frame: f,
                },
                img.positions[f],
            ));
        }
    }
    let nz = frames.len();
    let dims = [first.cols, first.rows, nz];
    voxel_count(dims).map_err(|e| ReadError::Series {
        path: dir.to_path_buf(),
        reason: e.to_string(),
    })?;
    let with_pos = frames.iter().filter(|(_, p)| p.is_some()).count();
    if with_pos != 0 && with_pos != nz {
        let (missing, _) = frames
            .iter()
            .find(|(_, p)| p.is_none())
            .expect("some lack a position");
        let img = &images[missing.image];
        return Err(dicom_err(
            &img.path,
            Some(tags::IMAGE_POSITION_PATIENT),
            format!(
                "missing for frame {} while other frames have it",
                missing.frame
            ),
        ));
    }
    let [ps_row, ps_col] = first.pixel_spacing.unwrap_or_else(|| {
        tracing::warn!(series = %dir.display(), "no Pixel Spacing: assuming 1 mm");
        [1.0, 1.0]
    });
    let (z_step, placement) = match (first.orientation, with_pos == nz) {
        (Some(iop), true) => {
            let r = [iop[0], iop[1], iop[2]];
            let c = [iop[3], iop[4], iop[5]];
            let n = normal(&iop);
            let nn = dot(n, n).sqrt();
            if nn.is_nan() || nn <= 0.5 {
                return Err(dicom_err(
                    &first.path,
                    Some(tags::IMAGE_ORIENTATION_PATIENT),
                    format!("{iop:?}: row and column directions are not orthogonal unit vectors"),
                ));
            }
            let n = n.map(|x| x / nn);
            frames.sort_by(|a, b| {
                let (pa, pb) = (
                    a.1.expect("all have positions"),
                    b.1.expect("all have positions"),
                );
                dot(pa, n)
                    .total_cmp(&dot(pb, n))
                    .then(images[a.0.image].instance.cmp(&images[b.0.image].instance))
            });
            let pos: Vec<[f64; 3]> = frames
                .iter()
                .map(|(_, p)| p.expect("all have positions"))
                .collect();
            let step = if nz >= 2 {
                check_steps(dir, images, &frames, &pos, n)?
            } else {
                first.slice_step.unwrap_or(1.0)
            };
            let p = Placement {
                origin: pos[0],
                directions: [r, c, n],
            };
            p.validate().map_err(|e| {
                dicom_err(
                    &first.path,
                    Some(tags::IMAGE_ORIENTATION_PATIENT),
                    e.to_string(),
                )
            })?;
            (step, Some(p))
        }
        _ => {
            // No geometry: order by Instance Number, then frame; no placement.
            frames.sort_by_key(|(f, _)| (images[f.image].instance, f.image, f.frame));
            (first.slice_step.unwrap_or(1.0), None)
        }
    };
    let spacing = [ps_col as f32, ps_row as f32, z_step as f32];
    if spacing.iter().any(|s| !(s.is_finite() && *s > 0.0)) {
        return Err(ReadError::Series {
            path: dir.to_path_buf(),
            reason: format!("voxel spacing {spacing:?} is not finite and positive"),
        });
    }
    Ok(Ordered {
        frames,
        dims,
        spacing,
        placement,
    })
}
