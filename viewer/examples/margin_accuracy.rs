//! How the margin bears on accuracy: every coefficient of a 32³ ball (value 1, radius 10)
//! splatted at 64², on an axis and two oblique views, against the line integrals of the
//! voxels' own spline (`PaddedVolume::from_volume`, no coefficient involved), and the reference
//! built from the coefficients against the same: `cargo run --release -p wavesplat-viewer
//! --example margin_accuracy`. The figures are in BENCHMARKS.md ("Splatting and accuracy").
use wavesplat_codec::dwt::decompose_channel;
use wavesplat_codec::family::Family;
use wavesplat_codec::format::packet::Coefficient;
use wavesplat_codec::layout::Geometry;
use wavesplat_codec::metrics::snr_db;
use wavesplat_viewer::{
    render_reference, PaddedVolume, ReferenceOptions, RenderOptions, Renderer, View,
};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let n = 32usize;
    let mut v = vec![0f32; n * n * n];
    for z in 0..n {
        for y in 0..n {
            for x in 0..n {
                let d = ((x as f64 - 15.5).powi(2)
                    + (y as f64 - 15.5).powi(2)
                    + (z as f64 - 15.5).powi(2))
                .sqrt();
                if d <= 10.0 {
                    v[x + n * (y + n * z)] = 1.0;
                }
            }
        }
    }
    for (family, levels) in [(Family::Linear, 3usize), (Family::Cubic, 2)] {
        for margin in [
            0usize,
            4,
            Geometry::separating_margin(family, levels),
            2 * Geometry::separating_margin(family, levels),
            64,
        ] {
            let g = Geometry::new([n; 3], family, levels, margin)?;
            let coeffs = Coefficient::all_of(&g, 0, &decompose_channel(&v, &g));
            let truth = PaddedVolume::from_volume(std::slice::from_ref(&v), &g);
            let padded = PaddedVolume::from_coefficients(&coeffs, &g, 1)?;
            let mut renderer = Renderer::new(RenderOptions::default());
            for (a, b) in [(0.0, 0.0), (0.3, 0.2), (0.66, 0.91)] {
                let view = View::new(a, b, 64, 64);
                let image = renderer.render(&coeffs, &g, &view)?;
                let o = ReferenceOptions {
                    supersample: 2,
                    step: 0.125,
                };
                let t = render_reference(&truth, &view, &o)?;
                let r = render_reference(&padded, &view, &o)?;
                println!("{family:?} M={levels} margin {margin:2} clips {} view ({a},{b}): splats vs data {:.2} dB, splats vs coef-reference {:.2} dB, coef-ref vs data {:.2} dB",
                    g.clips_to_box(), snr_db(&t.data, &image.data), snr_db(&r.data, &image.data), snr_db(&t.data, &r.data));
            }
        }
    }
    Ok(())
}
