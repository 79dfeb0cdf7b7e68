//! Splat image of all coefficients against the independent reference renderer: every family,
//! on the axes, a hair off them, and oblique, must reach 50 dB SNR (the codec's own quality at
//! the rates people use is below that, so the splats must not be what limits an image).
mod common;

use std::f64::consts::FRAC_PI_2;
use wavesplat_codec::family::Family;
use wavesplat_codec::format::packet::Coefficient;
use wavesplat_codec::layout::Geometry;
use wavesplat_codec::metrics::snr_db;
use wavesplat_viewer::{
    render_reference, Cue, CueDirection, PaddedVolume, ReferenceOptions, RenderOptions, Renderer,
    View,
};

/// On each axis, 1e-7 and 1e-4 rad off one, and two oblique views.
const VIEWS: [(f64, f64); 7] = [
    (0.0, 0.0),
    (FRAC_PI_2, 0.0),
    (0.0, FRAC_PI_2),
    (1e-7, 1e-7),
    (1e-4, -1e-4),
    (0.66, 0.91),
    (2.5, 0.1),
];

const REQUIRED_DB: f64 = 50.0;

fn check(family: Family, levels: usize, n: usize, size: usize) {
    let (g, coeffs, _) = common::coefficients(n, family, levels);
    check_with(family, levels, size, g, coeffs);
}

fn check_with(family: Family, levels: usize, size: usize, g: Geometry, coeffs: Vec<Coefficient>) {
    let vol = PaddedVolume::from_coefficients(&coeffs, &g, 1).unwrap();
    let mut r = Renderer::new(RenderOptions::default());
    for (a, b) in VIEWS {
        let view = View::new(a, b, size, size);
        let mut options = common::reference_options(family);
        // Box edges a hair off the pixel grid: the supersampled reference needs many rays per
        // pixel to resolve them (8 → 42 dB, 32 → 51 dB measured); on the axis it is exact.
        if family == Family::Haar && (a.abs().max(b.abs()) - 1e-4).abs() < 1e-9 {
            options = ReferenceOptions {
                supersample: 32,
                ..options
            };
        }
        let what = format!("{family} M={levels} ({a},{b}) {size}²");
        assert_splats_match(&mut r, (&g, &coeffs, &vol), &view, &options, &what);
    }
}

#[test]
fn haar_splats_match_reference() {
    check(Family::Haar, 3, 32, 96);
}

#[test]
fn linear_splats_match_reference() {
    check(Family::Linear, 2, 32, 96);
}

#[test]
fn cubic_splats_match_reference() {
    check(Family::Cubic, 2, 32, 96);
}

#[test]
fn deep_decompositions_match_reference() {
    // Coarse levels have footprints much larger than the image: M = 5 on 32³.
    check(Family::Haar, 5, 32, 96);
    // The reference reconstructs on the unwrapped grid the splats draw, so any margin works,
    // including none; non-cubic sizes too.
    for (family, levels, margin) in [(Family::Linear, 3, 0), (Family::Cubic, 2, 0)] {
        let (g, coeffs) = common::coefficients_with_margin(32, family, levels, margin);
        check_with(family, levels, 96, g, coeffs);
    }
}

/// A noise volume of side `n`: uniform in [0.5, 1.5) inside, zero within 3 voxels of the
/// faces.
fn noise_volume(n: usize) -> Vec<f32> {
    noise_box([n, n, n], 3)
}

/// A noise volume of `dims`: uniform in [0.5, 1.5) inside, zero within `rim` voxels of the
/// faces.
fn noise_box(dims: [usize; 3], rim: usize) -> Vec<f32> {
    let mut state = 0x9e37_79b9_7f4a_7c15u64;
    (0..dims.iter().product::<usize>())
        .map(|i| {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            let c = [i % dims[0], i / dims[0] % dims[1], i / (dims[0] * dims[1])];
            let inside = c
                .iter()
                .zip(dims)
                .all(|(&c, n)| (rim..n - rim).contains(&c));
            if inside {
                0.5 + (state >> 40) as f32 / (1u64 << 24) as f32
            } else {
                0.0
            }
        })
        .collect()
}

/// Geometry (M = 2, margin 8), every coefficient and the reconstructed volume of the noise
/// volume of side `n`.
fn noise_coefficients(n: usize, family: Family) -> (Geometry, Vec<Coefficient>, PaddedVolume) {
    let g = Geometry::new([n, n, n], family, 2, 8).unwrap();
    let vol = noise_volume(n);
    let coeffs = Coefficient::all_of(&g, 0, &wavesplat_codec::dwt::decompose_channel(&vol, &g));
    let pv = PaddedVolume::from_coefficients(&coeffs, &g, 1).unwrap();
    (g, coeffs, pv)
}

/// Renders `view` and asserts ≥ [`REQUIRED_DB`] against the reference renderer with `options`
/// (exact on the axes); `what` names the case.
fn assert_splats_match(
    r: &mut Renderer,
    (g, coeffs, pv): (&Geometry, &[Coefficient], &PaddedVolume),
    view: &View,
    options: &ReferenceOptions,
    what: &str,
) {
    let img = r.render(coeffs, g, view).unwrap();
    let reference = render_reference(pv, view, options).unwrap();
    let snr = snr_db(&reference.data, &img.data);
    eprintln!("{what}: SNR {snr:.1} dB");
    assert!(snr >= REQUIRED_DB, "{what}: SNR {snr:.2} dB");
}

/// 16×16 rays per pixel: what resolves voxel-scale noise off the axes.
const NOISE_RAYS: ReferenceOptions = ReferenceOptions {
    supersample: 16,
    step: 0.125,
};

/// Voxel-scale white noise (what an MRI's texture is at the finest level, where the linear and
/// cubic footprints have their sharpest kinks) on the three axes and obliquely, at sizes where
/// a pixel is about a voxel and where it is not: ≥ 50 dB against exact line integrals on the
/// axes (`spline_axis_exact`) and a reference of 16×16 rays per pixel obliquely.
#[test]
fn voxel_scale_noise_matches_reference() {
    for family in [Family::Linear, Family::Cubic] {
        let (g, coeffs, pv) = noise_coefficients(32, family);
        let mut r = Renderer::new(RenderOptions::default());
        for (a, b, size) in [
            (0.0, 0.0, 32),
            (0.0, 0.0, 45),
            (FRAC_PI_2, 0.0, 45),
            (0.0, FRAC_PI_2, 45),
            (0.66, 0.91, 45),
        ] {
            let view = View::new(a, b, size, size);
            let what = format!("noise {family} ({a},{b}) {size}²");
            assert_splats_match(&mut r, (&g, &coeffs, &pv), &view, &NOISE_RAYS, &what);
        }
    }
}

/// On a view along an axis the wavelets with ψ along that axis project to zero (∫ψ = 0): the
/// renderer leaves them out (counted as vanished, no records), and the image loses nothing and
/// still matches the exact one. Unclipped (Haar), every one of them vanishes, and the
/// closed-form line integrals of those coefficients alone are zero to rounding. Clipped to the
/// box (linear and cubic, at any margin), the coefficients cut by a face are drawn by their
/// pieces, whose ψ is cut and does not integrate to zero: fewer vanish, but some do.
/// Off the axes nothing is left out: obliquely, and for Haar 1e-7 rad off an axis, where its
/// ψ still projects to ~3e-8 of the largest footprint.
#[test]
fn axis_views_leave_out_the_wavelets_that_project_to_zero() {
    let n = 16;
    let peak = |d: &[f32]| d.iter().fold(0f64, |m, v| m.max(v.abs() as f64));
    for family in [Family::Haar, Family::Linear, Family::Cubic] {
        let vol = noise_volume(n);
        let decompose = |margin: usize| {
            let g = Geometry::new([n, n, n], family, 2, margin).unwrap();
            let c = Coefficient::all_of(&g, 0, &wavesplat_codec::dwt::decompose_channel(&vol, &g));
            let pv = PaddedVolume::from_coefficients(&c, &g, 1).unwrap();
            (g, c, pv)
        };
        let (g, coeffs, pv) = decompose(Geometry::separating_margin(family, 2));
        assert!(!g.clips_to_box());
        let (g0, coeffs0, pv0) = decompose(0);
        let mut r = Renderer::new(RenderOptions::default());
        for (axis, a, b) in [(0, 0.0, 0.0), (1, FRAC_PI_2, 0.0), (2, 0.0, FRAC_PI_2)] {
            let view = View::new(a, b, 40, 40);
            let what = format!("{family} along axis {axis}");
            let (_, stats) = r.render_with_stats(&coeffs, &g, &view).unwrap();
            let along: Vec<Coefficient> = coeffs
                .iter()
                .filter(|c| c.band.is_wavelet_along(axis))
                .copied()
                .collect();
            assert!(!along.is_empty());
            if g.splats_clip_to_box() {
                assert!(
                    stats.vanished > 0 && stats.vanished < along.len(),
                    "{what}, clipped: {stats:?} of {}",
                    along.len()
                );
            } else {
                assert_eq!(stats.vanished, along.len(), "{what}: {stats:?}");
                assert_eq!(
                    stats.splatted + stats.skipped,
                    coeffs.len() - along.len(),
                    "{what}"
                );
                let camera = wavesplat_viewer::Camera::new(&view, &g).unwrap();
                let alone = PaddedVolume::from_coefficients(&along, &g, 1).unwrap();
                let zero = wavesplat_viewer::spline_axis_exact(&alone, &camera).unwrap();
                let whole = wavesplat_viewer::spline_axis_exact(&pv, &camera).unwrap();
                assert!(
                    peak(&zero.data) <= 1e-9 * peak(&whole.data),
                    "{what}: the left-out coefficients draw {:e} of the peak",
                    peak(&zero.data) / peak(&whole.data)
                );
            }
            assert_splats_match(&mut r, (&g, &coeffs, &pv), &view, &NOISE_RAYS, &what);

            let (_, clipped) = r.render_with_stats(&coeffs0, &g0, &view).unwrap();
            let along0 = coeffs0
                .iter()
                .filter(|c| c.band.is_wavelet_along(axis))
                .count();
            if g0.splats_clip_to_box() {
                assert!(
                    clipped.vanished > 0 && clipped.vanished < along0,
                    "{what}, clipped: {clipped:?} of {along0}"
                );
            } else {
                // Haar's boxes never reach the volume from a periodic image: nothing is cut.
                assert_eq!(clipped.vanished, along0, "{what}, no margin");
            }
            let what = format!("{what}, no margin");
            assert_splats_match(&mut r, (&g0, &coeffs0, &pv0), &view, &NOISE_RAYS, &what);
        }
        let mut off = vec![(0.66, 0.91)];
        if family == Family::Haar {
            off.push((1e-7, 0.0));
        }
        for (a, b) in off {
            let (_, stats) = r
                .render_with_stats(&coeffs, &g, &View::new(a, b, 40, 40))
                .unwrap();
            assert_eq!(stats.vanished, 0, "{family} ({a},{b}): {stats:?}");
            assert_eq!(
                stats.splatted + stats.skipped,
                coeffs.len(),
                "{family} ({a},{b})"
            );
        }
    }
}

/// Views along each axis, at zooms from about eight voxels per pixel to almost four pixels per
/// voxel (a pixel near one voxel, where the footprints' kinks line up with the pixel grid,
/// included), unpanned and panned by a fraction of a voxel, against the closed-form
/// pixel-area average of the spline's line integrals: every image ≥ 50 dB, for the linear and
/// cubic families. The minified views need the finer phases `minified_subpixel` gives them
/// (at the default S = 8 the linear family fell to 36 dB at 0.13 pixels per voxel). On the real
/// MRI with every coefficient kept the axis views come to 58–74 dB against the same reference
/// (`examples/axis_accuracy.rs`).
#[test]
fn axis_views_match_exact_line_integrals_at_every_scale() {
    let n = 24;
    let half_pi = FRAC_PI_2;
    for family in [Family::Linear, Family::Cubic] {
        let (g, coeffs, pv) = noise_coefficients(n, family);
        let mut r = Renderer::new(RenderOptions::default());
        let mut worst = f64::INFINITY;
        for (a, b) in [(0.0, 0.0), (half_pi, 0.0), (0.0, half_pi), (0.0, -half_pi)] {
            for zoom in [0.13, 0.2, 0.3, 0.45, 0.93, 1.0, 1.07, 2.2, 3.7] {
                for pan in [[0.0, 0.0], [0.37, -0.21]] {
                    let size = ((n as f64 + 6.0) * zoom).ceil() as usize;
                    let view = View::new(a, b, size, size + 3)
                        .with_zoom(zoom)
                        .with_pan(pan);
                    let camera = wavesplat_viewer::Camera::new(&view, &g).unwrap();
                    let exact = wavesplat_viewer::spline_axis_exact(&pv, &camera)
                        .expect("a view along an axis");
                    let img = r.render(&coeffs, &g, &view).unwrap();
                    let snr = snr_db(&exact.data, &img.data);
                    worst = worst.min(snr);
                    assert!(
                        snr >= REQUIRED_DB,
                        "{family} ({a},{b}) zoom {zoom} pan {pan:?}: {snr:.2} dB"
                    );
                }
            }
        }
        eprintln!("{family}: worst axis view {worst:.1} dB");
    }
}

/// Minified views off the axes (a hair off one, a few degrees, oblique) at 0.13–0.3 pixels per
/// voxel, against the ray reference at 16×16 rays per pixel: ≥ 50 dB for the linear and cubic
/// families. At the fixed default S = 8 these read 40–58 dB (the near-axis ones worst; 24×24
/// rays), with the phases `minified_subpixel` gives 55–77 dB.
#[test]
fn minified_views_off_the_axes_match_reference() {
    let n = 24;
    for family in [Family::Linear, Family::Cubic] {
        let (g, coeffs, pv) = noise_coefficients(n, family);
        let mut r = Renderer::new(RenderOptions::default());
        for (a, b, zoom) in [
            (1e-4, -1e-4, 0.2),
            (0.05, 0.0, 0.13),
            (0.2, 0.1, 0.3),
            (0.66, 0.91, 0.13),
        ] {
            let size = ((n as f64 + 6.0) * zoom * 1.8).ceil() as usize;
            let view = View::new(a, b, size, size).with_zoom(zoom);
            let what = format!("minified {family} ({a},{b}) zoom {zoom}");
            assert_splats_match(&mut r, (&g, &coeffs, &pv), &view, &NOISE_RAYS, &what);
        }
    }
}

/// Magnified views of a small volume (10×10×15, M = 3, as a small scan's default), 8–16 pixels
/// per voxel, where the coarse levels' footprints are hundreds of pixels wide and their tables
/// are built with fewer phases (`level_subpixel`: one phase for the two coarsest here): the
/// linear and cubic families ≥ 50 dB against the reference, exact on the axis, rays off it
/// (62–80 dB measured; 72–107 dB with every level at S = 8, for 2.5 times the planning time of
/// a 256² view). Haar keeps its phases (a box edge stays a pixel sharp).
#[test]
fn magnified_views_match_reference() {
    let dims = [10, 10, 15];
    for family in [Family::Linear, Family::Cubic] {
        let g = Geometry::new(dims, family, 3, 4).unwrap();
        let vol = noise_box(dims, 1);
        let coeffs = Coefficient::all_of(&g, 0, &wavesplat_codec::dwt::decompose_channel(&vol, &g));
        let pv = PaddedVolume::from_coefficients(&coeffs, &g, 1).unwrap();
        let mut r = Renderer::new(RenderOptions::default());
        for (a, b, zoom) in [(0.0, 0.0, 16.0), (1e-4, -1e-4, 12.0), (0.66, 0.91, 8.0)] {
            let size = (21.0 * zoom) as usize;
            let view = View::new(a, b, size, size).with_zoom(zoom);
            let what = format!("magnified {family} ({a},{b}) zoom {zoom}");
            let options = common::reference_options(family);
            assert_splats_match(&mut r, (&g, &coeffs, &pv), &view, &options, &what);
        }
        // The depth-cued path builds its tables level by level with the same rule: with a
        // vanishing extinction it draws the uncued image, and with k = 0.1 per voxel it meets
        // the emission-absorption reference as unmagnified views do (`tests/render.rs`).
        let view = View::new(0.66, 0.91, 168, 168).with_zoom(8.0);
        let plain = r.render(&coeffs, &g, &view).unwrap();
        for (k, required, against_plain) in [(1e-9, 55.0, true), (0.1, 30.0, false)] {
            let cued = view.with_cue(Cue {
                k,
                direction: CueDirection::View,
            });
            let img = r.render(&coeffs, &g, &cued).unwrap();
            let expected = if against_plain {
                plain.clone()
            } else {
                render_reference(&pv, &cued, &common::reference_options(family)).unwrap()
            };
            let snr = snr_db(&expected.data, &img.data);
            eprintln!("magnified {family} cued k={k}: SNR {snr:.1} dB");
            assert!(
                snr >= required,
                "magnified {family} cued k={k}: {snr:.2} dB"
            );
        }
    }
}

/// A ball of value 1 and radius `r` voxels at the centre of an `n`³ volume (zero at the faces,
/// so the compressor's default margin is the separating one).
fn ball(n: usize, r: f64) -> Vec<f32> {
    let c = 0.5 * (n as f64 - 1.0);
    (0..n * n * n)
        .map(|i| {
            let p = [i % n, i / n % n, i / (n * n)].map(|v| v as f64 - c);
            f32::from(p.iter().map(|v| v * v).sum::<f64>() <= r * r)
        })
        .collect()
}

/// Whatever the margin, every coefficient splatted draws the line integrals of the volume's
/// own spline: the reference here is built from the voxels (`from_volume`), not from the
/// coefficients. Basis functions across the box's faces were drawn whole when the margin was
/// at least the separating one: what the transform put in the margin, and past the padded
/// grid tails whose wrapped parts would have cancelled them. That drew a ball at 38–43 dB
/// (linear) and 45–55 dB (cubic) at the compressor's default margin, and the reference built
/// from the coefficients, which drew the same, at 53–71 dB at twice that margin.
#[test]
fn every_margin_draws_the_volume_s_own_line_integrals() {
    let n = 24;
    let vol = ball(n, 7.5);
    let rays = ReferenceOptions {
        supersample: 2,
        step: 0.125,
    };
    let mut r = Renderer::new(RenderOptions::default());
    for (family, levels) in [(Family::Linear, 3), (Family::Cubic, 2)] {
        let separating = Geometry::separating_margin(family, levels);
        for margin in [0, separating, 2 * separating] {
            let g = Geometry::new([n; 3], family, levels, margin).unwrap();
            let coeffs =
                Coefficient::all_of(&g, 0, &wavesplat_codec::dwt::decompose_channel(&vol, &g));
            let of_voxels = PaddedVolume::from_volume(std::slice::from_ref(&vol), &g);
            let of_coefficients = PaddedVolume::from_coefficients(&coeffs, &g, 1).unwrap();
            for (a, b) in [(0.0, 0.0), (0.3, 0.2), (0.66, 0.91)] {
                let view = View::new(a, b, 48, 48);
                let what = format!("{family} M = {levels}, margin {margin}, view ({a}, {b})");
                let exact = render_reference(&of_voxels, &view, &rays).unwrap();
                let reference = render_reference(&of_coefficients, &view, &rays).unwrap();
                let snr = snr_db(&exact.data, &reference.data);
                assert!(
                    snr >= 100.0,
                    "{what}: the coefficients' reference {snr:.2} dB"
                );
                let img = r.render(&coeffs, &g, &view).unwrap();
                let snr = snr_db(&exact.data, &img.data);
                assert!(snr >= 48.0, "{what}: the splats {snr:.2} dB");
            }
        }
    }
}
