//! Shared test helpers: a deterministic phantom and its coefficients.
#![allow(dead_code)]

use wavesplat_codec::dwt::decompose_channel;
use wavesplat_codec::family::Family;
use wavesplat_codec::format::packet::Coefficient;
use wavesplat_codec::layout::Geometry;

/// A smooth phantom of a few ellipsoids with a zero margin of `margin` voxels.
pub fn phantom(n: usize, margin: usize) -> Vec<f32> {
    let c = 0.5 * (n as f64 - 1.0);
    let r = 0.5 * (n as f64 - 2.0 * margin as f64) - 0.5;
    // (centre offset / r, semi-axes / r, amplitude)
    let blobs: [([f64; 3], [f64; 3], f64); 4] = [
        ([0.0, 0.0, 0.0], [0.95, 0.8, 0.7], 1.0),
        ([0.3, -0.2, 0.1], [0.35, 0.3, 0.25], 1.5),
        ([-0.35, 0.3, -0.2], [0.25, 0.2, 0.3], -0.6),
        ([0.1, 0.35, 0.3], [0.15, 0.2, 0.15], 2.0),
    ];
    let mut out = vec![0.0f32; n * n * n];
    for z in 0..n {
        for y in 0..n {
            for x in 0..n {
                let p = [(x as f64 - c) / r, (y as f64 - c) / r, (z as f64 - c) / r];
                let mut v = 0.0;
                for (ctr, ax, amp) in &blobs {
                    let d: f64 = (0..3).map(|a| ((p[a] - ctr[a]) / ax[a]).powi(2)).sum();
                    if d < 1.0 {
                        v += amp * (1.0 - d).powf(1.5);
                    }
                }
                let in_margin = [x, y, z].iter().any(|&i| i < margin || i + margin >= n);
                out[x + n * (y + n * z)] = if in_margin { 0.0 } else { v as f32 };
            }
        }
    }
    out
}

/// Geometry and all coefficients (channel 0) of the phantom.
///
/// The splines use a geometry margin of 8 voxels: with the codec's default (2^(M−1)) the dual
/// tails that wrap around the period cost cubic M=2 on 32³ about 7 dB (32 dB instead of 39 dB).
pub fn coefficients(
    n: usize,
    family: Family,
    levels: usize,
) -> (Geometry, Vec<Coefficient>, Vec<f32>) {
    let margin = if family == Family::Haar { 0 } else { 8 };
    let (g, list) = coefficients_with_margin(n, family, levels, margin);
    (g, list, phantom(n, 3))
}

/// Geometry and all coefficients of the phantom with an explicit geometry margin.
pub fn coefficients_with_margin(
    n: usize,
    family: Family,
    levels: usize,
    margin: usize,
) -> (Geometry, Vec<Coefficient>) {
    let vol = phantom(n, 3);
    let g = Geometry::new([n, n, n], family, levels, margin).unwrap();
    let list = Coefficient::all_of(&g, 0, &decompose_channel(&vol, &g));
    (g, list)
}

/// Largest |a − b| / max |b|.
pub fn max_rel(a: &[f32], b: &[f32]) -> f64 {
    wavesplat_viewer::image::max_relative_difference(a, b)
}

/// Reference options: 8×8 rays per pixel for Haar (axis-aligned box edges), 3×3 for splines.
pub fn reference_options(family: Family) -> wavesplat_viewer::ReferenceOptions {
    wavesplat_viewer::ReferenceOptions {
        supersample: if family == Family::Haar { 8 } else { 3 },
        step: 0.125,
    }
}

/// Coefficient list of a Mallat-layout array (channel 0).
pub fn to_coefficients(g: &Geometry, c: &[f64]) -> Vec<Coefficient> {
    Coefficient::all_of(g, 0, c)
}

/// A view along z zoomed into the corner at the origin, a few voxels wide (32², 4 pixels a
/// voxel): on a 40×36×32 volume cut into 20-voxel bricks it sees the bricks at x, y < 20, 18.
pub fn origin_corner_view() -> wavesplat_viewer::View {
    wavesplat_viewer::View::new(
        -std::f64::consts::FRAC_PI_2,
        -std::f64::consts::FRAC_PI_2,
        32,
        32,
    )
    .with_zoom(4.0)
    .with_pan([-10.0, 9.0])
}

/// The reference ray caster's image of `volume` (geometry `g`) for `spec`: each view's camera
/// (multiview's three panels side by side), a cue "along the view" taken along the first
/// panel's direction, as the multiview renderer resolves it.
pub fn reference_image(
    volume: &wavesplat_codec::volume::Volume,
    g: &Geometry,
    spec: &wavesplat_codec::view::ViewSpec,
) -> wavesplat_viewer::Image {
    use wavesplat_codec::view::CueDirection;
    use wavesplat_viewer::reference::{render_reference_camera, PaddedVolume};
    let truth = PaddedVolume::from_volume(volume.channels(), g);
    let cameras = spec.cameras(g).unwrap();
    let n0 = cameras[0].n;
    let panels: Vec<wavesplat_viewer::Image> = cameras
        .iter()
        .map(|c| {
            let cue = spec.view.cue.map(|mut cue| {
                if cue.direction == CueDirection::View {
                    cue.direction = CueDirection::Vector(n0);
                }
                wavesplat_codec::view::resolve_cue(&cue, c, g).unwrap()
            });
            render_reference_camera(&truth, c, cue, &reference_options(g.family))
        })
        .collect();
    if panels.len() == 1 {
        return panels.into_iter().next().unwrap();
    }
    let (w, h) = (panels[0].width, panels[0].height);
    let mut out = wavesplat_viewer::Image::new(3 * w, h, 1);
    for (p, img) in panels.iter().enumerate() {
        for y in 0..h {
            out.data[y * 3 * w + p * w..y * 3 * w + (p + 1) * w]
                .copy_from_slice(&img.data[y * w..(y + 1) * w]);
        }
    }
    out
}
