//! Trains the fast coder's built-in tables (`codec/src/format/fast/builtin.bin`, see
//! `wavesplat_codec::format::fast::builtin`): compresses the project's phantoms (Shepp–Logan,
//! with and without noise, the spheres, the RGB head, the beating heart) at several sizes,
//! families and rates with the fast coder, and sums each header table's symbol counts over the
//! files. The CT phantom is left out, as for the sigmap coder's priors: the test set holds a
//! volume like it, and the tables must be measured on volumes they were not trained on.
//!
//! `cargo run --release -p wavesplat-compressor --example train_fast_tables -- OUT.bin [MIN_FILES]`
//! (MIN_FILES: the least weight, in files of 4 096 symbols, a table needs to be built in;
//! default 4)

use wavesplat_codec::format::fast::builtin::Training;
use wavesplat_codec::format::CoderKind;
use wavesplat_compressor::encode::CompressOptions;

#[path = "training_set/mod.rs"]
mod training_set;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let out = args
        .next()
        .ok_or("usage: train_fast_tables OUT.bin [MIN_FILES]")?;
    let min_files: u64 = args.next().map_or(Ok(4), |s| s.parse())?;
    let volumes = training_set::volumes(&[[48, 40, 36], [96, 96, 96], [160, 128, 112]])?;
    let training = Training::start();
    training_set::compress_all(
        &volumes,
        &CompressOptions {
            coder: CoderKind::Fast,
            refine: None,
            ..CompressOptions::default()
        },
    )?;
    let levels = training.finish(min_files);
    std::fs::write(&out, levels.to_bytes())?;
    eprintln!(
        "{} of {} tables built in, written to {out}",
        levels.count(),
        levels.0.len()
    );
    Ok(())
}
