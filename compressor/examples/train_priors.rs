//! Trains the sigmap coder's priors table (`codec/src/format/sigmap/priors.bin`, see
//! `wavesplat_codec::format::sigmap::priors`): compresses the project's phantoms (Shepp–Logan,
//! with and without noise, the spheres, the RGB head, the beating heart) at several sizes,
//! families and rates in the format before the priors (version 8, models starting at ½), and
//! records where each model ended each packet. The CT phantom is left out: the test set holds
//! a volume like it, and the priors must be measured on volumes they were not trained on.
//!
//! `cargo run --release -p wavesplat-compressor --example train_priors -- OUT.bin [MAX_SEEN]`
//! (MAX_SEEN: the most bits any prior counts as seen, default 30: fully learnt)

use wavesplat_codec::format::sigmap::priors::Training;
use wavesplat_compressor::encode::CompressOptions;

#[path = "training_set/mod.rs"]
mod training_set;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let out = args
        .next()
        .ok_or("usage: train_priors OUT.bin [MAX_SEEN]")?;
    let max_seen: u8 = args.next().map_or(Ok(30), |s| s.parse())?;
    let volumes = training_set::volumes(&[[96, 96, 96], [160, 128, 112]])?;
    let training = Training::start();
    training_set::compress_all(
        &volumes,
        &CompressOptions {
            format_version: wavesplat_codec::format::LAST_UNPRIMED_VERSION,
            ..CompressOptions::default()
        },
    )?;
    let table = training.finish(16, max_seen);
    let primed = table.p0.iter().filter(|p| **p != 0).count();
    std::fs::write(&out, table.to_bytes())?;
    eprintln!("{primed} models primed, written to {out}");
    Ok(())
}
