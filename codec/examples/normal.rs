//! Times the f32 synthesis R, its transpose, and the refinement's normal operator Rᵀ(h(R x))
//! (h a pointwise step, `normal_with`) on the MNI volume's padded grid for M = 2, and a copy of
//! the grid on the pool for comparison; min and median of `REPEAT` runs:
//! `cargo run --release -p wavesplat-codec --features rayon --example normal -- [REPEAT]`.
use std::time::Instant;
use wavesplat_codec::dwt::fast::FastTransform;
use wavesplat_codec::family::Family;
use wavesplat_codec::layout::Geometry;

fn stats(mut t: Vec<f64>) -> String {
    t.sort_by(f64::total_cmp);
    format!("min {:6.2} ms  median {:6.2} ms", t[0], t[t.len() / 2])
}

fn main() {
    let repeat: usize = std::env::args()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(15);
    for (family, levels) in [(Family::Linear, 2), (Family::Cubic, 2)] {
        let g = Geometry::new([197, 233, 189], family, levels, 12).expect("geometry");
        let n = g.coefficient_count();
        let fast = FastTransform::new(&g);
        let target: Vec<f32> = (0..n).map(|i| ((i % 1013) as f32) * 0.1).collect();
        let mut data: Vec<f32> = (0..n).map(|i| ((i % 977) as f32) * 0.01).collect();
        let time = |f: &mut dyn FnMut()| -> Vec<f64> {
            (0..repeat)
                .map(|_| {
                    let t = Instant::now();
                    f();
                    t.elapsed().as_secs_f64() * 1e3
                })
                .collect()
        };
        let name = format!("{family:?} M={levels} {:?}", g.padded);
        println!(
            "{name} synthesize          {}",
            stats(time(&mut || fast.synthesize(&mut data)))
        );
        println!(
            "{name} synthesize_adjoint  {}",
            stats(time(&mut || fast.synthesize_adjoint(&mut data)))
        );
        let plane = g.padded[0] * g.padded[1];
        let fused = time(&mut || {
            fast.normal_with(&mut data, &|z, r| {
                let f = &target[z * plane..(z + 1) * plane];
                r.iter_mut().zip(f).for_each(|(r, f)| *r = f - *r);
            })
        });
        println!("{name} normal_with         {}", stats(fused));
        // What memory alone allows: one read and one write of the grid.
        use rayon::prelude::*;
        let pcopy = time(&mut || {
            data.par_chunks_mut(1 << 16)
                .zip(target.par_chunks(1 << 16))
                .for_each(|(d, t)| d.copy_from_slice(t))
        });
        println!("{name} copy (pool)         {}", stats(pcopy));
    }
}
