//! Wavelet transform throughput on the compressor's largest everyday grid (criterion, wall
//! time, the rayon pool): the f32 synthesis R and its transpose Rᵀ that the least-squares
//! refinement applies ~40 times per compression (`dwt::fast`), and the exact f64 analysis
//! that every compression runs once per depth it tries (`dwt::decompose_channel`, by recursive
//! filters), beside the FFT analysis it is tested against (`dwt::forward_3d_fft`).
//!
//! The grid is the MNI volume's (197×233×189) padded as the compressor pads it for the linear
//! family at M = 3 (224×264×216, 12.8 M coefficients), and for the cubic family at M = 2.
//! Throughput is in coefficients per second of one whole 3D transform.
use criterion::{black_box, criterion_group, criterion_main, Criterion, Throughput};
use std::time::Duration;
use wavesplat_codec::dwt::fast::FastTransform;
use wavesplat_codec::dwt::{
    decompose_channel, forward_3d_fft, pad_channel, samples_to_coefficients_fft, Dwt1d,
};
use wavesplat_codec::family::Family;
use wavesplat_codec::layout::Geometry;

const DIMS: [usize; 3] = [197, 233, 189];

/// Smooth values with structure at several scales (the transforms' cost does not depend on
/// them; they only keep the numbers ordinary).
fn values(n: usize) -> Vec<f32> {
    (0..n)
        .map(|i| {
            let t = i as f32 * 1e-3;
            100.0 + 50.0 * t.sin() + 20.0 * (t * 7.3).cos()
        })
        .collect()
}

fn bench(c: &mut Criterion) {
    let mut group = c.benchmark_group("transform");
    group
        .sample_size(10)
        .measurement_time(Duration::from_secs(6));
    for (family, levels) in [(Family::Linear, 3), (Family::Cubic, 2)] {
        let g = Geometry::new(
            DIMS,
            family,
            levels,
            Geometry::separating_margin(family, levels),
        )
        .expect("geometry");
        let n = g.coefficient_count();
        group.throughput(Throughput::Elements(n as u64));
        let fast = FastTransform::new(&g);
        let mut data = values(n);
        let name = format!("{family:?} M={levels} {:?}", g.padded);
        group.bench_function(format!("synthesize {name}"), |b| {
            b.iter(|| fast.synthesize(black_box(&mut data)))
        });
        group.bench_function(format!("synthesize_adjoint {name}"), |b| {
            b.iter(|| fast.synthesize_adjoint(black_box(&mut data)))
        });
        let volume = values(DIMS.iter().product());
        group.bench_function(format!("exact analysis {name}"), |b| {
            b.iter(|| black_box(decompose_channel(black_box(&volume), &g)))
        });
        group.bench_function(format!("fft analysis {name}"), |b| {
            let mut planner = Dwt1d::new(family);
            b.iter(|| {
                let mut data = pad_channel(black_box(&volume), &g);
                samples_to_coefficients_fft(&mut data, &g);
                forward_3d_fft(&mut data, &g, &mut planner);
                black_box(data)
            })
        });
    }
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
