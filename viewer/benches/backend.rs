//! Accumulation backends on the same records (issue 12): splats per second of the CPU backend
//! and of the wgpu backend (whatever adapter wgpu finds; lavapipe on a machine without a GPU)
//! for 10⁵ and 10⁶ records at 256² and 512², per family. A measurement is `begin` +
//! `accumulate` + `read` (the image back on the host), planning excluded.
//!
//! The GPU backend's display pass is timed too (`display/SIZE`, 256² to 1024²): the accumulated
//! sums to the `Rgba8Unorm` texture a window draws, with the automatic window (its samples read
//! back to the host), waited for on the device; nothing else leaves it.
//!
//! `cargo bench -p wavesplat-viewer --bench backend` (a filter such as `gpu/linear` or
//! `display` narrows it).
use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use wavesplat_codec::dwt::decompose_channel;
use wavesplat_codec::family::Family;
use wavesplat_codec::format::packet::Coefficient;
use wavesplat_codec::layout::Geometry;
use wavesplat_viewer::backend::gpu::DisplayOptions;
use wavesplat_viewer::backend::{AccumulationBackend, CpuBackend, GpuBackend, GpuContext};
use wavesplat_viewer::{PlanOptions, Planner, RenderStats, View, ViewSpec};

/// A ball with a ramp: smooth, so significance order puts coarse levels first.
fn volume(n: usize) -> Vec<f32> {
    let c = 0.5 * (n as f64 - 1.0);
    (0..n * n * n)
        .map(|i| {
            let (x, y, z) = (i % n, (i / n) % n, i / (n * n));
            let r2 = ((x as f64 - c).powi(2) + (y as f64 - c).powi(2) + (z as f64 - c).powi(2))
                / (0.4 * n as f64).powi(2);
            if r2 < 1.0 {
                ((1.0 - r2) * (1.0 + x as f64 / n as f64)) as f32
            } else {
                0.0
            }
        })
        .collect()
}

fn bench(c: &mut Criterion) {
    let gpu = match GpuContext::new() {
        Ok(ctx) => {
            eprintln!("GPU adapter: {:?}", ctx.info());
            Some(ctx)
        }
        Err(e) => {
            eprintln!("no GPU backend: {e}");
            None
        }
    };
    // 100³ gives 10⁶ coefficients: the 10⁵ case takes the most significant tenth.
    let n = 100;
    let vol = volume(n);
    for family in Family::ALL {
        let g = Geometry::new([n, n, n], family, 3, 0).unwrap();
        let mut coeffs = Coefficient::all_of(&g, 0, &decompose_channel(&vol, &g));
        coeffs.sort_by(|a, b| b.value.abs().total_cmp(&a.value.abs()));
        for count in [100_000usize, 1_000_000] {
            for size in [256usize, 512] {
                let spec = ViewSpec::single(View::new(0.66, 0.91, size, size));
                let mut planner = Planner::new(PlanOptions::default());
                let mut plan = planner.plan(&g, &spec, 1).unwrap();
                let mut records = Vec::new();
                plan.splats(&coeffs[..count], &mut records, &mut RenderStats::default())
                    .unwrap();
                let mut probe = CpuBackend::new();
                probe.begin(plan.layout()).unwrap();
                let updates = probe.accumulate(&plan.atlas(), &records).unwrap();
                eprintln!(
                    "{family} {count} coefficients at {size}²: {} records, {updates} pixel updates",
                    records.len()
                );
                let mut backends: Vec<Box<dyn AccumulationBackend>> =
                    vec![Box::new(CpuBackend::new())];
                if let Some(ctx) = &gpu {
                    backends.push(Box::new(GpuBackend::new(ctx.clone()).unwrap()));
                }
                for mut backend in backends {
                    let name = backend.name();
                    let short = name.split(' ').next().unwrap_or("backend").to_string();
                    let mut group = c.benchmark_group(format!("{short}/{family}/{count}/{size}"));
                    group.throughput(Throughput::Elements(records.len() as u64));
                    group.sample_size(10);
                    group.bench_function("accumulate", |b| {
                        b.iter(|| {
                            backend.begin(plan.layout()).unwrap();
                            backend.accumulate(&plan.atlas(), &records).unwrap();
                            backend.read().unwrap()
                        })
                    });
                    group.finish();
                }
            }
        }
    }
    if let Some(ctx) = &gpu {
        bench_display(c, ctx, &vol, n);
    }
}

/// The display pass alone at window sizes, on an image holding the linear family's most
/// significant 10⁵ coefficients (what is drawn does not change the pass's work).
fn bench_display(c: &mut Criterion, ctx: &std::sync::Arc<GpuContext>, vol: &[f32], n: usize) {
    let g = Geometry::new([n, n, n], Family::Linear, 3, 0).unwrap();
    let mut coeffs = Coefficient::all_of(&g, 0, &decompose_channel(vol, &g));
    coeffs.sort_by(|a, b| b.value.abs().total_cmp(&a.value.abs()));
    for size in [256usize, 512, 1024] {
        let spec = ViewSpec::single(View::new(0.66, 0.91, size, size));
        let mut planner = Planner::new(PlanOptions::default());
        let mut plan = planner.plan(&g, &spec, 1).unwrap();
        let mut records = Vec::new();
        plan.splats(
            &coeffs[..100_000],
            &mut records,
            &mut RenderStats::default(),
        )
        .unwrap();
        let mut backend = GpuBackend::new(ctx.clone()).unwrap();
        backend.begin(plan.layout()).unwrap();
        backend.accumulate(&plan.atlas(), &records).unwrap();
        backend.wait().unwrap();
        let mut group = c.benchmark_group(format!("display/{size}"));
        group.throughput(Throughput::Elements((size * size) as u64));
        group.sample_size(20);
        group.bench_function("auto window", |b| {
            b.iter(|| {
                backend.display(&DisplayOptions::default()).unwrap();
                backend.wait().unwrap()
            })
        });
        group.bench_function("fixed window", |b| {
            let options = DisplayOptions {
                window: Some((0.0, 1.0)),
                ..DisplayOptions::default()
            };
            b.iter(|| {
                backend.display(&options).unwrap();
                backend.wait().unwrap()
            })
        });
        group.finish();
    }
}

criterion_group!(benches, bench);
criterion_main!(benches);
