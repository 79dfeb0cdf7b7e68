//! How close the splats of a real volume with every coefficient kept come to exact line
//! integrals, on and off the axes:
//! `cargo run --release -p wavesplat-viewer --example axis_accuracy -- VOLUME [FAMILY] [LEVELS] [SIZE...]`.
//!
//! The volume (any format `compress` reads, first channel) is decomposed without quantization
//! and every coefficient splatted. Axis views are held to the closed-form pixel-area average of
//! the spline's line integrals ([`wavesplat_viewer::spline_axis_exact`]); oblique ones to the
//! ray reference at 4×4 rays per pixel (slow on a large volume). Prints the SNR per view and
//! size, also with the family's fixed default subpixel phases (what minified views had before
//! `minified_subpixel`) and, on the axes, what moving the image by a fraction of a voxel costs
//! against itself (how much a convention elsewhere would read as error). The figures are in
//! BENCHMARKS.md ("Axis views against exact line integrals").
use std::path::Path;
use std::time::Instant;
use wavesplat_codec::dwt::decompose_channel;
use wavesplat_codec::family::Family;
use wavesplat_codec::format::packet::Coefficient;
use wavesplat_codec::layout::Geometry;
use wavesplat_codec::metrics::snr_db;
use wavesplat_viewer::{
    render_reference, PaddedVolume, ReferenceOptions, RenderOptions, Renderer, View,
};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let Some(path) = args.get(1) else {
        return Err("usage: axis_accuracy VOLUME [linear|cubic] [LEVELS] [SIZE...]".into());
    };
    let family = match args.get(2).map(String::as_str) {
        None | Some("linear") => Family::Linear,
        Some("cubic") => Family::Cubic,
        Some(other) => return Err(format!("family {other}: linear or cubic").into()),
    };
    let levels: usize = args.get(3).map_or(Ok(2), |s| s.parse())?;
    let sizes: Vec<usize> = if args.len() > 4 {
        args[4..]
            .iter()
            .map(|s| s.parse())
            .collect::<Result<_, _>>()?
    } else {
        vec![256]
    };
    let volume = wavesplat_compressor::reader::read_volume(Path::new(path), None)?;
    let margin = wavesplat_compressor::encode::default_margin(&volume, family, levels);
    let g = Geometry::new(volume.dims(), family, levels, margin)?.with_spacing(volume.spacing())?;
    let coeffs = Coefficient::all_of(&g, 0, &decompose_channel(volume.channel(0), &g));
    let padded = PaddedVolume::from_coefficients(&coeffs, &g, 1)?;
    println!(
        "{path}: {:?}, {family} M = {levels}, margin {margin}, {} coefficients",
        volume.dims(),
        coeffs.len()
    );
    let mut renderer = Renderer::new(RenderOptions::default());
    let half_pi = std::f64::consts::FRAC_PI_2;
    for size in sizes {
        for (name, a, b, fitted) in [
            ("x axis", 0.0, 0.0, false),
            ("y axis", half_pi, 0.0, false),
            ("z axis", 0.0, half_pi, false),
            ("x axis, fitted as `render` does", 0.0, 0.0, true),
            ("z axis, fitted as `render` does", 0.0, half_pi, true),
            ("oblique", 0.66, 0.91, false),
        ] {
            let mut view = View::new(a, b, size, size);
            if fitted {
                view = view.with_zoom(wavesplat_viewer::Camera::new(&view, &g)?.fitting_zoom(&g));
            }
            let t = Instant::now();
            let image = renderer.render(&coeffs, &g, &view)?;
            let splat_ms = t.elapsed().as_secs_f64() * 1e3;
            let t = Instant::now();
            let options = ReferenceOptions {
                supersample: 4,
                step: 0.125,
            };
            let reference = render_reference(&padded, &view, &options)?;
            let reference_s = t.elapsed().as_secs_f64();
            println!(
                "{size}² {name}: SNR {:.2} dB (splats {splat_ms:.0} ms, reference {reference_s:.1} s)",
                snr_db(&reference.data, &image.data)
            );
            // The same view with the family's fixed default S (no finer phases for minified
            // views), against the same reference.
            let mut fixed = Renderer::new(RenderOptions {
                subpixel: Some(wavesplat_viewer::PlanOptions::default_subpixel(family)),
                ..RenderOptions::default()
            });
            let fixed_image = fixed.render(&coeffs, &g, &view)?;
            println!(
                "    at the default S = {}: {:.2} dB",
                wavesplat_viewer::PlanOptions::default_subpixel(family),
                snr_db(&reference.data, &fixed_image.data)
            );
            if !name.starts_with('o') && !fitted {
                // What a convention that puts the voxels elsewhere by a fraction of a voxel
                // (a sample grid read from the box's corner instead of the voxel centres, say)
                // costs against the same exact image.
                for shift in [0.5, 0.1, 0.02] {
                    let moved = view.with_pan([shift, 0.0]);
                    let other = render_reference(&padded, &moved, &options)?;
                    println!(
                        "    the exact image against itself moved by {shift} of a spacing unit: {:.2} dB",
                        snr_db(&reference.data, &other.data)
                    );
                }
            }
        }
    }
    Ok(())
}
