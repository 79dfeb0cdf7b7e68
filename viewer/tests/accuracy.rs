//! Splat image of all coefficients vs the reference renderer (issue 3).
mod common;

use wavesplat_codec::family::Family;
use wavesplat_codec::metrics::snr_db;
use wavesplat_viewer::{render_reference, PaddedVolume, RenderOptions, Renderer, View};

const VIEWS: [(f64, f64); 4] = [(0.0, 0.0), (0.66, 0.91), (2.5, 0.1), (1e-7, 1e-7)];

fn check(family: Family, levels: usize, n: usize, size: usize) {
    let (g, coeffs, _) = common::coefficients(n, family, levels);
    check_with(family, levels, n, size, g, coeffs);
}

fn check_with(
    family: Family,
    levels: usize,
    n: usize,
    size: usize,
    g: wavesplat_codec::layout::Geometry,
    coeffs: Vec<wavesplat_codec::format::packet::Coefficient>,
) {
    let vol = PaddedVolume::from_coefficients(&coeffs, &g, 1).unwrap();
    let mut r = Renderer::new(RenderOptions::default());
    for (a, b) in VIEWS {
        let view = View::new(a, b, size, size);
        let t = std::time::Instant::now();
        let img = r.render(&coeffs, &g, &view).unwrap();
        let ts = t.elapsed();
        let t = std::time::Instant::now();
        let reference = render_reference(&vol, &view, &common::reference_options(family)).unwrap();
        let tr = t.elapsed();
        let snr = snr_db(&reference.data, &img.data);
        eprintln!("{family} M={levels} n={n} ({a},{b}) {size}²: SNR {snr:.1} dB (splat {ts:?}, ref {tr:?})");
        assert!(snr >= 30.0, "{family} ({a},{b}): SNR {snr:.2} dB");
    }
}

#[test]
fn haar_splats_match_reference() {
    check(Family::Haar, 3, 32, 128);
}

#[test]
fn linear_splats_match_reference() {
    check(Family::Linear, 2, 32, 128);
}

#[test]
fn cubic_splats_match_reference() {
    check(Family::Cubic, 2, 32, 128);
}

#[test]
fn deep_decompositions_match_reference() {
    // Coarse levels have footprints much larger than the image: M = 5 on 32³.
    check(Family::Haar, 5, 32, 128);
    // The splines need the default margin (period ≥ volume + coarsest ψ support).
    for (family, levels) in [(Family::Linear, 3), (Family::Cubic, 2)] {
        let margin = wavesplat_codec::layout::Geometry::default_margin(family, levels);
        let (g, coeffs) = common::coefficients_with_margin(32, family, levels, margin);
        check_with(family, levels, 32, 128, g, coeffs);
    }
}
