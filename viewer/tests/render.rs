//! Renderer features of issue 3: multiview, depth cueing, progressive refinement, regions of
//! interest and thread-count independence.
mod common;

use wavesplat_codec::family::Family;
use wavesplat_codec::layout::Geometry;
use wavesplat_codec::metrics::{q_i_paper_db, snr_db};
use wavesplat_codec::view::multiview_cameras;
use wavesplat_viewer::{render_reference, PaddedVolume, RenderOptions, Renderer, View};
use wavesplat_viewer::{Cue, CueDirection};

/// Each of the three permuted multiviews equals the same view rendered directly with its own
/// footprints (max difference ≤ 1e-6 of the image peak; measured ~1e-7, f32 rounding).
#[test]
fn multiview_permutations_equal_direct_views() {
    for family in Family::ALL {
        let (g, coeffs, _) = common::coefficients(24, family, 2);
        let view = View::new(0.66, 0.91, 96, 96);
        let mut r = Renderer::new(RenderOptions::default());
        let (views, _) = r.render_multiview_views(&coeffs, &g, &view).unwrap();
        let cams = multiview_cameras(&view, &g).unwrap();
        for k in 0..3 {
            let mut direct = Renderer::new(RenderOptions::default());
            let (img, _) = direct.render_camera(&coeffs, &g, &cams[k]).unwrap();
            let e = common::max_rel(&views[k].data, &img.data);
            eprintln!("{family} multiview {}: max rel diff {e:.2e}", k + 1);
            assert!(e <= 1e-6, "{family} view {}: {e}", k + 1);
        }
        let (both, _) = r.render_multiview(&coeffs, &g, &view).unwrap();
        assert_eq!(both.width, 288);
    }
}

/// Depth cueing with L along the view equals the emission–absorption reference for every family
/// and k ∈ {0.01, 0.1, 0.5} per voxel: SNR ≥ 30 dB (measured: Haar 40.5 / 40.7 / 38.5, linear
/// 45.0 / 45.2 / 38.4, cubic 39.5 / 40.3 / 32.4 dB). The cue is cut at the data's light-facing
/// faces, so what the spline supports sum to in front of the data is not amplified (before, the
/// splines gave 2.6 dB and −50.8 dB at k = 0.5).
#[test]
fn depth_cue_matches_emission_absorption_reference() {
    for family in [Family::Haar, Family::Linear, Family::Cubic] {
        // The compressor's default margin (half the coarsest support), what files have.
        let margin = Geometry::separating_margin(family, 2);
        let (g, coeffs) = common::coefficients_with_margin(32, family, 2, margin);
        let vol = PaddedVolume::from_coefficients(&coeffs, &g, 1).unwrap();
        let mut r = Renderer::new(RenderOptions::default());
        for &k in &[0.01, 0.1, 0.5] {
            let view = View::new(0.66, 0.91, 128, 128).with_cue(Cue {
                k,
                direction: CueDirection::View,
            });
            let img = r.render(&coeffs, &g, &view).unwrap();
            let reference =
                render_reference(&vol, &view, &common::reference_options(family)).unwrap();
            let snr = snr_db(&reference.data, &img.data);
            eprintln!("{family} cue k={k}: SNR {snr:.1} dB");
            assert!(snr >= 30.0, "{family} k={k}: {snr}");
        }
    }
}

/// Stiff and extreme extinctions with M up to 5 give finite pixels only.
#[test]
fn stiff_depth_cue_stays_finite() {
    for family in Family::ALL {
        for levels in [3usize, 5] {
            let n = 32;
            let vol = common::phantom(n, 3);
            let g = Geometry::new([n, n, n], family, levels, 0).unwrap();
            let c = wavesplat_codec::dwt::decompose_channel(&vol, &g);
            let coeffs = common::to_coefficients(&g, &c);
            let mut r = Renderer::new(RenderOptions {
                max_fft: Some(512),
                ..RenderOptions::default()
            });
            for &k in &[1e-12, 5.0, 50.0, 1e3] {
                for dir in [
                    CueDirection::View,
                    CueDirection::Angles {
                        alpha: 2.0,
                        beta: -0.4,
                    },
                ] {
                    let view = View::new(0.3, -0.7, 48, 48).with_cue(Cue { k, direction: dir });
                    let img = r.render(&coeffs, &g, &view).unwrap();
                    assert!(
                        img.data.iter().all(|v| v.is_finite()),
                        "{family} M={levels} k={k}"
                    );
                }
            }
        }
    }
}

/// Rendering the n most significant coefficients (|value|²·‖basis‖²) for increasing n gives a
/// rising Q_I against the full image (strictly monotone here: no quantization), until n holds
/// every nonzero coefficient (Haar's phantom has exact zeros): from there the image is the full
/// one.
#[test]
fn progressive_quality_rises() {
    for family in [Family::Haar, Family::Linear] {
        let (g, mut coeffs, _) = common::coefficients(32, family, 3);
        coeffs.sort_by(|a, b| {
            let ea = (a.value as f64).powi(2) * g.basis_norm2(a.band);
            let eb = (b.value as f64).powi(2) * g.basis_norm2(b.band);
            eb.total_cmp(&ea)
        });
        let view = View::new(0.66, 0.91, 128, 128);
        let mut r = Renderer::new(RenderOptions::default());
        let full = r.render(&coeffs, &g, &view).unwrap();
        let mut last = f64::NEG_INFINITY;
        let mut line = String::new();
        let nonzero = coeffs.iter().filter(|c| c.value != 0.0).count();
        assert!(nonzero > 1000, "{family}: {nonzero} nonzero coefficients");
        for n in [100, 300, 1000, 3000, 10000, 30000] {
            let img = r.render(&coeffs[..n], &g, &view).unwrap();
            let q = q_i_paper_db(&full.data, &img.data);
            line += &format!(" n={n}: {q:.1} dB;");
            if n >= nonzero {
                assert!(
                    q > 200.0,
                    "{family}: Q_I {q} with every nonzero coefficient"
                );
            } else {
                assert!(q > last, "{family}: Q_I {q} after {last} at n={n}");
            }
            last = q;
        }
        eprintln!("{family} progressive Q_I (paper dB):{line}");
    }
}

/// Zoomed on a corner: splats missing the screen are skipped and the image equals the crop of
/// the full image rendered at the same zoom (1e-4 of the peak).
#[test]
fn region_of_interest_equals_crop() {
    for family in [Family::Haar, Family::Cubic] {
        let (g, coeffs, _) = common::coefficients(32, family, 2);
        let zoom = 6.0;
        let full_view = View::new(0.66, 0.91, 384, 384).with_zoom(zoom);
        let mut r = Renderer::new(RenderOptions::default());
        let (full, fs) = r.render_with_stats(&coeffs, &g, &full_view).unwrap();
        // A 96×96 window whose top-left pixel is (32, 64) of the full image: pan so that its
        // centre (80, 112) maps to the centre of the small image; whole-pixel shift so the
        // subpixel phases are identical.
        let (cx, cy) = (32.0 + 48.0, 64.0 + 48.0);
        let pan = [(cx - 192.0) / zoom, -(cy - 192.0) / zoom];
        let roi = full_view.with_pan(pan);
        let roi = View {
            width: 96,
            height: 96,
            ..roi
        };
        let (img, stats) = r.render_with_stats(&coeffs, &g, &roi).unwrap();
        let crop = full.crop(32, 64, 96, 96);
        let e = common::max_rel(&img.data, &crop.data);
        eprintln!(
            "{family} ROI: skipped {} of {} (full view skipped {}), max rel diff {e:.2e}",
            stats.skipped, stats.coefficients, fs.skipped
        );
        assert!(stats.skipped > 0);
        assert_eq!(stats.skipped + stats.splatted, coeffs.len());
        assert!(e <= 1e-4, "{family}: {e}");
    }
}

/// One thread and the default pool give bit-identical images.
#[test]
fn thread_count_does_not_change_the_image() {
    let (g, coeffs, _) = common::coefficients(32, Family::Linear, 2);
    let view = View::new(2.5, 0.1, 160, 130);
    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    let a = one.install(|| {
        Renderer::new(RenderOptions::default())
            .render(&coeffs, &g, &view)
            .unwrap()
    });
    let many = rayon::ThreadPoolBuilder::new()
        .num_threads(4)
        .build()
        .unwrap();
    let b = many.install(|| {
        Renderer::new(RenderOptions::default())
            .render(&coeffs, &g, &view)
            .unwrap()
    });
    assert!(a.data == b.data);
}

/// Bad input gives typed errors, never panics.
#[test]
fn bad_input_is_rejected() {
    let (g, mut coeffs, _) = common::coefficients(16, Family::Haar, 2);
    let mut r = Renderer::new(RenderOptions::default());
    assert!(r
        .render(&coeffs, &g, &View::new(f64::NAN, 0.0, 8, 8))
        .is_err());
    assert!(r.render(&coeffs, &g, &View::new(0.0, 0.0, 0, 8)).is_err());
    assert!(r
        .render(&coeffs, &g, &View::new(0.0, 0.0, 8, 8).with_zoom(-1.0))
        .is_err());
    coeffs[5].channel = 3;
    assert!(r.render(&coeffs, &g, &View::new(0.0, 0.0, 8, 8)).is_err());
    coeffs[5].channel = 0;
    coeffs[5].pos = [99, 0, 0];
    assert!(r.render(&coeffs, &g, &View::new(0.0, 0.0, 8, 8)).is_err());
}

/// PNG (auto window) and raw f32 output.
#[test]
fn png_and_raw_output() {
    let (g, coeffs, _) = common::coefficients(16, Family::Haar, 2);
    let img = Renderer::new(RenderOptions::default())
        .render(&coeffs, &g, &View::new(0.3, 0.2, 40, 30))
        .unwrap();
    let dir = std::env::temp_dir().join(format!("wavesplat-viewer-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    img.write_png(&dir.join("a.png"), None).unwrap();
    img.write_raw(&dir.join("a.f32")).unwrap();
    let raw = std::fs::read(dir.join("a.f32")).unwrap();
    assert_eq!(raw.len(), 40 * 30 * 4);
    assert_eq!(
        f32::from_le_bytes(raw[4 * 45..4 * 46].try_into().unwrap()),
        img.data[45]
    );
    assert!(img.write_png(&dir.join("b.png"), Some((1.0, 1.0))).is_err());
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A depth-cued view splits coefficients into pieces and places the pieces in chunks on the
/// pool; a coefficient counts as splatted once when any of its pieces reaches the screen, also
/// when its pieces straddle two chunks. The count over all coefficients equals the sum of the
/// counts over groups of them rendered alone (groups of 37, so the chunk boundaries of the whole
/// fall inside groups), zoomed in so that some coefficients miss the screen.
#[test]
fn cued_pieces_count_each_coefficient_once() {
    let (g, coeffs, _) = common::coefficients(24, Family::Linear, 2);
    let mut view = View::new(0.66, 0.91, 64, 64).with_cue(Cue {
        k: 0.05,
        direction: CueDirection::View,
    });
    view.zoom = Some(6.0);
    view.pan = [20.0, -10.0];
    let mut r = Renderer::new(RenderOptions::default());
    let (_, whole) = r.render_with_stats(&coeffs, &g, &view).unwrap();
    let mut splatted = 0;
    let mut skipped = 0;
    for group in coeffs.chunks(37) {
        let (_, part) = r.render_with_stats(group, &g, &view).unwrap();
        splatted += part.splatted;
        skipped += part.skipped;
    }
    assert!(
        whole.splatted > 0 && whole.skipped > 0,
        "the view shows some coefficients and misses others: {whole:?}"
    );
    assert!(coeffs.len() > 4 * 1024, "pieces span several chunks");
    assert_eq!((whole.splatted, whole.skipped), (splatted, skipped));
}
