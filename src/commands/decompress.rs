//! `wavesplat decompress`: full decode to raw f32, for checks against the original.

use anyhow::{Context, Result};
use clap::Args;
use std::path::PathBuf;

/// Arguments of `wavesplat decompress`.
#[derive(Args, Debug)]
pub struct DecompressArgs {
    /// The .wsp file.
    pub input: PathBuf,
    /// Output: raw little-endian f32, x fastest, channels interleaved.
    #[arg(short, long)]
    pub output: PathBuf,
}

/// Runs the subcommand.
pub fn run(a: DecompressArgs) -> Result<()> {
    super::check_output(&a.output)?;
    let bytes = super::read_wsp(&a.input)?;
    let progress = wavesplat_harness::console::Progress::new("decompress");
    progress.stage("decoding packets and inverse transform");
    let v = wavesplat_compressor::decode::decompress(&bytes)
        .with_context(|| format!("decoding {}", a.input.display()))?;
    progress.finish();
    let out: Vec<u8> = v
        .to_interleaved()
        .iter()
        .flat_map(|x| x.to_le_bytes())
        .collect();
    std::fs::write(&a.output, out).with_context(|| format!("writing {}", a.output.display()))?;
    let d = v.dims();
    outln!(
        "wrote {} ({}x{}x{}, {} channel(s), f32 LE)",
        a.output.display(),
        d[0],
        d[1],
        d[2],
        v.channel_count()
    );
    Ok(())
}
