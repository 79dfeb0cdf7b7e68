//! `wavesplat phantom`: writes a built-in phantom as raw samples.

use anyhow::{bail, Context, Result};
use clap::Args;
use std::path::PathBuf;
use wavesplat_compressor::phantom::Phantom;

/// Arguments of `wavesplat phantom`.
#[derive(Args, Debug)]
pub struct PhantomArgs {
    /// Phantom: shepp-logan, spheres, rgb-head, constant, zero, ct, noise.
    #[arg(default_value = "shepp-logan")]
    pub name: String,
    /// Dimensions X,Y,Z.
    #[arg(long, default_value = "64,64,64", value_parser = super::parse_dims)]
    pub dims: [usize; 3],
    /// Sample type of the output: f32 or u8 (values clamped to 0..=255).
    #[arg(long, default_value = "f32")]
    pub dtype: String,
    /// Output file (x fastest, channels interleaved).
    #[arg(short, long)]
    pub output: PathBuf,
}

/// Runs the subcommand.
pub fn run(a: PhantomArgs) -> Result<()> {
    let p = Phantom::from_name(&a.name).with_context(|| {
        format!(
            "unknown phantom {:?}; choose one of {:?}",
            a.name,
            Phantom::names()
        )
    })?;
    let v = p.generate(a.dims);
    let data = v.to_interleaved();
    let bytes: Vec<u8> = match a.dtype.as_str() {
        "f32" => data.iter().flat_map(|x| x.to_le_bytes()).collect(),
        "u8" => data
            .iter()
            .map(|x| x.round().clamp(0.0, 255.0) as u8)
            .collect(),
        other => bail!("--dtype {other:?}: choose f32 or u8"),
    };
    std::fs::write(&a.output, bytes).with_context(|| format!("writing {}", a.output.display()))?;
    outln!(
        "wrote {} ({}x{}x{}, {} channel(s), {})",
        a.output.display(),
        a.dims[0],
        a.dims[1],
        a.dims[2],
        v.channel_count(),
        a.dtype
    );
    Ok(())
}
