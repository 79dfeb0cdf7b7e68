//! Trains the sigmap coder's priors table (`codec/src/format/sigmap/priors.bin`, see
//! `wavesplat_codec::format::sigmap::priors`): compresses the project's phantoms (Shepp–Logan,
//! with and without noise, the spheres, the RGB head, the beating heart) at several sizes,
//! families and rates in the format before the priors (version 8, models starting at ½), and
//! records where each model ended each packet. The CT phantom is left out: the test set holds
//! a volume like it, and the priors must be measured on volumes they were not trained on.
//!
//! `cargo run --release -p wavesplat-compressor --example train_priors -- OUT.bin [MAX_SEEN]`
//! (MAX_SEEN: the most bits any prior counts as seen, default 30: fully learnt)

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use wavesplat_codec::family::Family;
use wavesplat_codec::format::sigmap::priors::Training;
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

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let out = args
        .next()
        .ok_or("usage: train_priors OUT.bin [MAX_SEEN]")?;
    let max_seen: u8 = args.next().map_or(Ok(30), |s| s.parse())?;
    let mut volumes: Vec<(String, Volume)> = Vec::new();
    for dims in [[96, 96, 96], [160, 128, 112]] {
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
    let training = Training::start();
    for (name, v) in &volumes {
        for family in [Family::Linear, Family::Cubic, Family::Haar] {
            for fraction in [0.0007, 0.003, 0.0125, 0.05] {
                let opts = CompressOptions {
                    family,
                    target: Target::Fraction(fraction),
                    format_version: wavesplat_codec::format::LAST_UNPRIMED_VERSION,
                    ..CompressOptions::default()
                };
                let c = compress(v, &opts, &|_, _| {})?;
                eprintln!("{name} {family:?} {fraction}: {} bytes", c.bytes.len());
            }
        }
    }
    let table = training.finish(16, max_seen);
    let primed = table.p0.iter().filter(|p| **p != 0).count();
    std::fs::write(&out, table.to_bytes())?;
    eprintln!("{primed} models primed, written to {out}");
    Ok(())
}
