//! Clipping to the volume's box: with a small or zero margin the periodic images of the basis
//! functions reach the volume, and the splats must still draw the volume and nothing outside
//! it. Checked against the reference renderer on the spline of the original voxels (an
//! independent path: no coefficients are involved), on thin, non-cubic volumes whose faces are
//! not zero, on and off the axes, with and without a stiff depth cue, and in multiview.
mod common;

use std::f64::consts::FRAC_PI_2;
use wavesplat_codec::dwt::decompose_channel;
use wavesplat_codec::family::Family;
use wavesplat_codec::format::packet::Coefficient;
use wavesplat_codec::layout::Geometry;
use wavesplat_codec::metrics::snr_db;
use wavesplat_codec::view::{Cue, CueDirection, ViewSpec};
use wavesplat_viewer::{
    render_reference, render_reference_camera, PaddedVolume, RenderOptions, Renderer, View,
};

const VIEWS: [(f64, f64); 6] = [
    (0.0, 0.0),
    (FRAC_PI_2, 0.0),
    (0.0, FRAC_PI_2),
    (1e-4, -1e-4),
    (0.66, 0.91),
    (2.5, 0.1),
];

/// A smooth field plus a constant, so every face of the box is far from zero, with structure
/// crossing the faces (a slab cut out of a larger body).
fn body(dims: [usize; 3], offset: f32) -> Vec<f32> {
    let mut out = Vec::with_capacity(dims.iter().product());
    for z in 0..dims[2] {
        for y in 0..dims[1] {
            for x in 0..dims[0] {
                let (fx, fy, fz) = (x as f64, y as f64, z as f64);
                let v = (0.31 * fx).sin() * (0.23 * fy + 0.4).cos()
                    + 0.5 * (0.57 * fz + 0.11 * fx).sin()
                    + 0.02 * fy;
                out.push(v as f32 + offset);
            }
        }
    }
    out
}

fn tight(dims: [usize; 3], family: Family, levels: usize) -> (Geometry, Vec<f32>) {
    let g = Geometry::new(dims, family, levels, 0).unwrap();
    assert!(
        g.clips_to_box(),
        "{dims:?} {family} M={levels} needs clipping"
    );
    (g, body(dims, 3.0))
}

fn all_coefficients(g: &Geometry, data: &[f32]) -> Vec<Coefficient> {
    Coefficient::all_of(g, 0, &decompose_channel(data, g))
}

#[test]
fn clipped_splats_draw_the_volume_of_thin_non_cubic_boxes_with_non_zero_faces() {
    for (dims, family, levels) in [
        ([24, 20, 8], Family::Cubic, 2),
        ([24, 20, 8], Family::Linear, 3),
        ([16, 40, 6], Family::Cubic, 1),
        ([13, 11, 17], Family::Cubic, 3),
    ] {
        let (g, data) = tight(dims, family, levels);
        let coeffs = all_coefficients(&g, &data);
        let truth = PaddedVolume::from_volume(&[data], &g);
        let mut r = Renderer::new(RenderOptions::default());
        for (a, b) in VIEWS {
            let view = View::new(a, b, 64, 56);
            let img = r.render(&coeffs, &g, &view).unwrap();
            let reference =
                render_reference(&truth, &view, &common::reference_options(family)).unwrap();
            let snr = snr_db(&reference.data, &img.data);
            assert!(
                snr >= 50.0,
                "{dims:?} {family} M={levels} ({a},{b}): {snr:.1} dB"
            );
        }
    }
}

/// Seen along an axis with the whole box well inside the image, every pixel whose footprint
/// lies beyond the box's projection (plus a B-spline's reach) is zero: the wrapped parts of the
/// basis functions and their tails beyond the faces are not drawn.
#[test]
fn nothing_is_drawn_outside_the_box() {
    let dims = [20, 12, 6];
    let (g, data) = tight(dims, Family::Cubic, 2);
    let coeffs = all_coefficients(&g, &data);
    let view = View {
        zoom: Some(2.0),
        ..View::new(0.0, 0.0, 80, 64)
    };
    let mut r = Renderer::new(RenderOptions::default());
    let img = r.render(&coeffs, &g, &view).unwrap();
    let camera = wavesplat_codec::view::Camera::new(&view, &g).unwrap();
    let max = img.data.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    assert!(max > 1.0, "the volume is drawn ({max})");
    // The screen box of the volume's box widened by a level-0 B-spline's half support.
    let reach = 0.5 * Family::Cubic.phi_support();
    let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for corner in 0..8 {
        let p = [0, 1, 2].map(|a| {
            if corner & (1 << a) == 0 {
                -reach
            } else {
                dims[a] as f64 - 1.0 + reach
            }
        });
        let s = camera.to_screen(p);
        (x0, x1, y0, y1) = (x0.min(s[0]), x1.max(s[0]), y0.min(s[1]), y1.max(s[1]));
    }
    let mut outside = 0;
    for y in 0..img.height {
        for x in 0..img.width {
            let (px, py) = (x as f64 + 0.5, y as f64 + 0.5);
            if px < x0 - 1.0 || px > x1 + 1.0 || py < y0 - 1.0 || py > y1 + 1.0 {
                outside += 1;
                let v = img.data[y * img.width + x];
                assert!(v.abs() <= 1e-5 * max, "pixel ({x}, {y}) outside: {v}");
            }
        }
    }
    assert!(
        outside > 1000,
        "the test sees the outside ({outside} pixels)"
    );
}

/// A depth cue from very soft to very stiff on a zero-margin volume: finite, and equal to the
/// reference's emission–absorption integral of the box.
#[test]
fn clipped_pieces_carry_the_depth_cue() {
    for (family, levels) in [(Family::Cubic, 2), (Family::Linear, 3)] {
        let (g, data) = tight([20, 16, 8], family, levels);
        let coeffs = all_coefficients(&g, &data);
        let truth = PaddedVolume::from_volume(&[data], &g);
        let mut r = Renderer::new(RenderOptions::default());
        for k in [0.02, 0.5, 5.0] {
            for direction in [CueDirection::View, CueDirection::Vector([0.4, -0.3, 0.85])] {
                let view = View::new(0.66, 0.91, 48, 48).with_cue(Cue { k, direction });
                let img = r.render(&coeffs, &g, &view).unwrap();
                assert!(img.data.iter().all(|v| v.is_finite()));
                let reference =
                    render_reference(&truth, &view, &common::reference_options(family)).unwrap();
                let snr = snr_db(&reference.data, &img.data);
                eprintln!("{family} k={k} {direction:?}: {snr:.1} dB");
                assert!(snr >= 35.0, "{family} k={k} {direction:?}: {snr:.1} dB");
            }
        }
    }
}

/// The three multiview cameras of a clipped volume, each against its own reference image: a
/// non-cubic box, and a cubic one padded to the next multiple of 2^M (the box off the padded
/// grid's origin).
#[test]
fn clipped_multiview_matches_each_camera() {
    for (dims, family, levels) in [
        ([20, 16, 12], Family::Cubic, 2),
        ([30, 30, 30], Family::Linear, 3),
    ] {
        let (g, data) = tight(dims, family, levels);
        let coeffs = all_coefficients(&g, &data);
        let truth = PaddedVolume::from_volume(&[data], &g);
        let spec = ViewSpec {
            view: View::new(0.4, 0.3, 48, 48),
            multiview: true,
        };
        let mut r = Renderer::new(RenderOptions::default());
        let (img, _) = r.render_spec(&coeffs, &g, &spec).unwrap();
        let cameras = spec.cameras(&g).unwrap();
        for (k, camera) in cameras.iter().enumerate() {
            let reference =
                render_reference_camera(&truth, camera, None, &common::reference_options(family));
            let got: Vec<f32> = (0..48)
                .flat_map(|y| (0..48).map(move |x| (x, y)))
                .map(|(x, y)| img.get(k * 48 + x, y, 0))
                .collect();
            let snr = snr_db(&reference.data, &got);
            assert!(snr >= 50.0, "{dims:?} {family}: camera {k}: {snr:.1} dB");
        }
    }
}

/// The reference of a set of coefficients is the same box whether built from them or from the
/// voxels they code, and a sparse subset renders against it as exactly as the whole set.
#[test]
fn a_subset_of_coefficients_renders_against_its_clipped_reconstruction() {
    let (g, data) = tight([24, 20, 8], Family::Cubic, 2);
    let mut coeffs = all_coefficients(&g, &data);
    coeffs.sort_by(|a, b| {
        let ea = (a.value as f64).powi(2) * g.basis_norm2(a.band);
        let eb = (b.value as f64).powi(2) * g.basis_norm2(b.band);
        eb.total_cmp(&ea)
    });
    coeffs.truncate(coeffs.len() / 20);
    let vol = PaddedVolume::from_coefficients(&coeffs, &g, 1).unwrap();
    let mut r = Renderer::new(RenderOptions::default());
    for (a, b) in [(0.0, 0.0), (0.66, 0.91)] {
        let view = View::new(a, b, 64, 56);
        let img = r.render(&coeffs, &g, &view).unwrap();
        let reference =
            render_reference(&vol, &view, &common::reference_options(Family::Cubic)).unwrap();
        let snr = snr_db(&reference.data, &img.data);
        assert!(snr >= 50.0, "({a},{b}): {snr:.1} dB");
    }
}
