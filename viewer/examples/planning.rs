//! Footprint planning time for a new view (a planner cache miss, as on every step of an orbit),
//! per family, decomposition depth and image size, as CSV on stdout; with the share of a
//! 16.6 ms frame. `cargo run --release -p wavesplat-viewer --example planning > planning.csv`
//!
//! Each row is the median of five distinct oblique views, each planned by a fresh planner; the
//! variants are the default plan (gradient placement, the family's subpixel phases), the same
//! with nearest placement (no gradient tables), and a preview plan (nearest placement, S = 2)
//! that a viewer can show while the exact tables are built. `atlas_mb` is the footprint
//! memory of the view. A second table (after a blank line) gives the splat time of all
//! coefficients of a 64³ phantom with gradient and with nearest placement (tables cached).
use std::time::Instant;
use wavesplat_codec::family::Family;
use wavesplat_codec::format::packet::Coefficient;
use wavesplat_codec::layout::Geometry;
use wavesplat_codec::view::{View, ViewSpec};
use wavesplat_viewer::{Placement, PlanOptions, Planner, RenderOptions, Renderer};

fn main() {
    println!("family,levels,image,variant,subpixel,plan_ms,frame_share,atlas_mb");
    for family in [Family::Haar, Family::Linear, Family::Cubic] {
        for levels in [2usize, 3, 4, 5] {
            let g = match Geometry::new([256, 256, 256], family, levels, 0) {
                Ok(g) => g,
                Err(e) => {
                    eprintln!("{family} M={levels}: {e}");
                    continue;
                }
            };
            for size in [256usize, 512] {
                let variants = [
                    ("default", PlanOptions::default()),
                    (
                        "nearest",
                        PlanOptions {
                            placement: Placement::Nearest,
                            ..PlanOptions::default()
                        },
                    ),
                    (
                        "preview",
                        PlanOptions {
                            placement: Placement::Nearest,
                            subpixel: Some(2),
                            ..PlanOptions::default()
                        },
                    ),
                ];
                for (name, options) in variants {
                    let (mut atlas_mb, mut subpixel) = (0.0, 0);
                    let mut times: Vec<f64> = (0..5)
                        .map(|i| {
                            let spec = ViewSpec {
                                view: View::new(
                                    0.3 + 0.17 * i as f64,
                                    0.8 - 0.11 * i as f64,
                                    size,
                                    size,
                                ),
                                multiview: false,
                            };
                            let mut planner = Planner::new(options);
                            let t = Instant::now();
                            let plan = planner.plan(&g, &spec, 1).expect("plan");
                            let ms = t.elapsed().as_secs_f64() * 1e3;
                            atlas_mb = plan.atlas().data.len() as f64 * 4.0 / 1e6;
                            let camera = &plan.cameras[0];
                            let (ex, ey) = camera.index_axes();
                            subpixel = options.subpixel_for_view(family, camera.zoom, ex, ey);
                            ms
                        })
                        .collect();
                    times.sort_by(f64::total_cmp);
                    let ms = times[2];
                    println!(
                        "{family},{levels},{size},{name},{subpixel},{ms:.2},{:.2},{atlas_mb:.1}",
                        ms / 16.6
                    );
                }
            }
        }
    }
    println!();
    println!("family,levels,image,placement,coefficients,splat_ms");
    let n = 64;
    let vol = wavesplat_compressor::phantom::Phantom::SheppLogan.generate([n; 3]);
    for family in [Family::Haar, Family::Linear, Family::Cubic] {
        let g = Geometry::new([n; 3], family, 3, 0).expect("geometry");
        let c = wavesplat_codec::dwt::decompose_channel(&vol.channels()[0], &g);
        let coeffs: Vec<Coefficient> = Coefficient::all_of(&g, 0, &c)
            .into_iter()
            .filter(|c| c.value.abs() > 1e-6)
            .collect();
        for placement in [Placement::Gradient, Placement::Nearest] {
            let mut r = Renderer::new(RenderOptions {
                placement,
                ..RenderOptions::default()
            });
            let view = View::new(0.66, 0.91, 256, 256);
            r.render(&coeffs, &g, &view).expect("render");
            let mut times: Vec<f64> = (0..5)
                .map(|_| {
                    let t = Instant::now();
                    std::hint::black_box(r.render(&coeffs, &g, &view).expect("render"));
                    t.elapsed().as_secs_f64() * 1e3
                })
                .collect();
            times.sort_by(f64::total_cmp);
            println!(
                "{family},3,256,{placement:?},{},{:.1}",
                coeffs.len(),
                times[2]
            );
        }
    }
}
