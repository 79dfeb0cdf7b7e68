//! The phantoms the codec's trained tables learn from (`train_priors`, `train_fast_tables`),
//! and the compressions they learn from them: Shepp–Logan with and without noise, the noisy spheres and the RGB head at each of the
//! given sizes, and the beating heart. The CT phantom is left out: the test set holds a volume
//! like it, and what is trained must be measured on volumes it was not trained on.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use wavesplat_codec::family::Family;
use wavesplat_codec::volume::Volume;
use wavesplat_compressor::encode::{compress, CompressOptions, Target};
use wavesplat_compressor::phantom::{beating, Phantom};

/// A phantom with seeded Gaussian-like noise of standard deviation `sigma` added (the sum of
/// four uniforms, scaled).
fn noisy(v: &Volume, sigma: f32, seed: u64) -> Volume {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let ch: Vec<f32> = v
        .channel(0)
        .iter()
        .map(|x| {
            let u: f32 = (0..4).map(|_| rng.gen::<f32>() - 0.5).sum();
            x + u * sigma * 1.732
        })
        .collect();
    Volume::new(v.dims(), v.spacing(), vec![ch]).expect("same shape")
}

/// The training volumes, named, at each of `sizes`.
pub fn volumes(sizes: &[[usize; 3]]) -> Result<Vec<(String, Volume)>, Box<dyn std::error::Error>> {
    let mut volumes: Vec<(String, Volume)> = Vec::new();
    for &dims in sizes {
        let sl = Phantom::SheppLogan.generate(dims);
        volumes.push((format!("shepp-logan {dims:?} noisy"), noisy(&sl, 6.0, 7)));
        volumes.push((format!("shepp-logan {dims:?}"), sl));
        volumes.push((
            format!("spheres {dims:?} noisy"),
            noisy(&Phantom::Spheres.generate(dims), 10.0, 11),
        ));
        volumes.push((
            format!("rgb-head {dims:?}"),
            Phantom::RgbHead.generate(dims),
        ));
    }
    volumes.push(("beating".into(), beating([128, 128, 24], 3, 16)?));
    Ok(volumes)
}

/// Compresses each volume with each family at each training rate (`base`'s other options),
/// in one fixed order, reporting each file's size; a training records what the coders see.
pub fn compress_all(
    volumes: &[(String, Volume)],
    base: &CompressOptions,
) -> Result<(), Box<dyn std::error::Error>> {
    for (name, v) in volumes {
        for family in [Family::Linear, Family::Cubic, Family::Haar] {
            for fraction in [0.0007, 0.003, 0.0125, 0.05] {
                let opts = CompressOptions {
                    family,
                    target: Target::Fraction(fraction),
                    ..base.clone()
                };
                let c = compress(v, &opts, &|_, _| {})?;
                eprintln!("{name} {family:?} {fraction}: {} bytes", c.bytes.len());
            }
        }
    }
    Ok(())
}
