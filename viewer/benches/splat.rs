//! Splats per second at 256² and 512² per family (criterion; footprints cached, so this is the
//! accumulation path: projection, binning and tiled accumulation).
use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use wavesplat_codec::dwt::decompose_channel;
use wavesplat_codec::family::Family;
use wavesplat_codec::format::packet::Coefficient;
use wavesplat_codec::layout::Geometry;
use wavesplat_viewer::{RenderOptions, Renderer, View};

fn volume(n: usize) -> Vec<f32> {
    let c = 0.5 * (n as f64 - 1.0);
    (0..n * n * n)
        .map(|i| {
            let (x, y, z) = (i % n, (i / n) % n, i / (n * n));
            let r2 = ((x as f64 - c).powi(2) + (y as f64 - c).powi(2) + (z as f64 - c).powi(2))
                / (0.4 * n as f64).powi(2);
            if r2 < 1.0 {
                (1.0 - r2) as f32
            } else {
                0.0
            }
        })
        .collect()
}

fn bench(c: &mut Criterion) {
    let n = 64;
    let vol = volume(n);
    for family in Family::ALL {
        let g = Geometry::new([n, n, n], family, 3, 0).unwrap();
        let coeffs = Coefficient::all_of(&g, 0, &decompose_channel(&vol, &g));
        for size in [256usize, 512] {
            let view = View::new(0.66, 0.91, size, size);
            let mut r = Renderer::new(RenderOptions::default());
            r.render(&coeffs, &g, &view).unwrap();
            let mut group = c.benchmark_group(format!("splat_{family}_{size}"));
            group.throughput(Throughput::Elements(coeffs.len() as u64));
            group.sample_size(10);
            group.bench_function("render", |b| {
                b.iter(|| r.render(&coeffs, &g, &view).unwrap())
            });
            group.finish();
        }
    }
}

criterion_group!(benches, bench);
criterion_main!(benches);
