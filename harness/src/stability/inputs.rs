//! The cases' inputs: the smooth test volume and its variants, the lossless compression
//! options and the reference ray caster's accuracy settings.

use anyhow::Result;
use wavesplat_codec::family::Family;
use wavesplat_codec::volume::Volume;
use wavesplat_compressor::encode::{CompressOptions, Target};
use wavesplat_viewer::ReferenceOptions;

/// A smooth volume of a few overlapping ellipsoids (positive and negative) on any shape, zero
/// on a 1-voxel border: what the accuracy tests use, scaled by `scale`.
pub(super) fn blobs(dims: [usize; 3], scale: f64) -> Vec<f32> {
    let blobs: [([f64; 3], [f64; 3], f64); 4] = [
        ([0.0, 0.0, 0.0], [0.95, 0.8, 0.7], 1.0),
        ([0.3, -0.2, 0.1], [0.35, 0.3, 0.25], 1.5),
        ([-0.35, 0.3, -0.2], [0.25, 0.2, 0.3], -0.6),
        ([0.1, 0.35, 0.3], [0.15, 0.2, 0.15], 2.0),
    ];
    let c = dims.map(|d| 0.5 * (d as f64 - 1.0));
    let r = dims.map(|d| (0.5 * d as f64 - 1.0).max(0.5));
    let mut out = vec![0.0f32; dims.iter().product()];
    for z in 0..dims[2] {
        for y in 0..dims[1] {
            for x in 0..dims[0] {
                let p = [
                    (x as f64 - c[0]) / r[0],
                    (y as f64 - c[1]) / r[1],
                    (z as f64 - c[2]) / r[2],
                ];
                let mut v = 0.0;
                for (ctr, ax, amp) in &blobs {
                    let d: f64 = (0..3).map(|a| ((p[a] - ctr[a]) / ax[a]).powi(2)).sum();
                    if d < 1.0 {
                        v += amp * (1.0 - d).powf(1.5);
                    }
                }
                out[x + dims[0] * (y + dims[1] * z)] = (v * scale) as f32;
            }
        }
    }
    out
}

/// Reference accuracy: 8×8 rays per pixel for Haar (box edges), 3×3 for the splines, and a
/// sampling step that resolves e^(−k·t) (1/(8k)) under a depth cue.
pub(super) fn reference_options(family: Family, cue_k: f64) -> ReferenceOptions {
    let step = if cue_k > 0.0 {
        (0.125f64).min(1.0 / (8.0 * cue_k))
    } else {
        0.125
    };
    ReferenceOptions {
        supersample: if family == Family::Haar { 8 } else { 3 },
        step,
    }
}

/// The blobs on a pedestal of 0.5: every face non-zero, so a stiff cue whose light plane is a
/// face leaves the front layer to compare.
pub(super) fn faced(dims: [usize; 3]) -> Vec<f32> {
    blobs(dims, 1.0).into_iter().map(|v| v + 0.5).collect()
}

pub(super) fn volume(dims: [usize; 3], channels: Vec<Vec<f32>>) -> Result<Volume> {
    Ok(Volume::new(dims, [1.0; 3], channels)?)
}

/// Lossless selection (every non-zero coefficient) with the sigmap coder, no refinement, and
/// its step at 1e-3 of the threshold: what is judged is the selection, the transform and the
/// handling of scale, not the coder's default step of one threshold (coefficients at the
/// threshold known to ±½ of it, a rate–distortion choice for lossy rates). The constant cases
/// use the default step.
pub(super) fn lossless(family: Family) -> CompressOptions {
    CompressOptions {
        family,
        target: Target::All,
        refine: None,
        step: 1e-3,
        ..Default::default()
    }
}
