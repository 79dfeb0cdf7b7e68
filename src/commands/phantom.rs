//! `wavesplat phantom`: writes a built-in phantom as raw samples, slab by slab, so that a
//! phantom of any size (more voxels than one volume holds: 2048³ and beyond) is written in the
//! memory of one slab.

use anyhow::{bail, Context, Result};
use clap::Args;
use std::io::Write;
use std::path::PathBuf;
use wavesplat_compressor::phantom::Phantom;
use wavesplat_harness::console::Progress;

/// Arguments of `wavesplat phantom`.
#[derive(Args, Debug)]
pub struct PhantomArgs {
    /// Phantom: shepp-logan, spheres, rgb-head, constant, zero, ct, blobs, noise.
    #[arg(default_value = "shepp-logan")]
    pub name: String,
    /// Dimensions X,Y,Z. Any size: the file is generated and written a slab of z at a time.
    #[arg(long, default_value = "64,64,64", value_parser = super::parse_dims)]
    pub dims: [usize; 3],
    /// Sample type of the output: f32 or u8 (values clamped to 0..=255).
    #[arg(long, default_value = "f32")]
    pub dtype: String,
    /// Output file (x fastest, channels interleaved). Written under a temporary name beside
    /// it and renamed when complete, so an interrupted run leaves no partial file behind
    /// (as every command's output).
    #[arg(short, long)]
    pub output: PathBuf,
}

/// Sample types `phantom` writes.
#[derive(Debug, Clone, Copy, PartialEq)]
enum SampleType {
    F32,
    U8,
}

impl SampleType {
    fn parse(s: &str) -> Result<SampleType> {
        match s {
            "f32" => Ok(SampleType::F32),
            "u8" => Ok(SampleType::U8),
            other => bail!("--dtype {other:?}: choose f32 or u8"),
        }
    }

    fn append(self, samples: &[f32], out: &mut Vec<u8>) {
        match self {
            SampleType::F32 => out.extend(samples.iter().flat_map(|x| x.to_le_bytes())),
            SampleType::U8 => out.extend(samples.iter().map(|x| x.round().clamp(0.0, 255.0) as u8)),
        }
    }
}

/// Voxels generated at a time: 16 M (64 MB of f32 samples a channel), at least one slice.
const SLAB_VOXELS: u64 = 1 << 24;

/// Writes `phantom` at `dims` to `out` a slab of whole slices at a time (each slab at most
/// `slab_voxels` voxels, or one slice), calling `done(slices written)` after each; returns
/// the channel count. The bytes are those of the whole generated at once.
fn write_phantom(
    phantom: Phantom,
    dims: [usize; 3],
    dtype: SampleType,
    slab_voxels: u64,
    out: &mut dyn Write,
    mut done: impl FnMut(usize),
) -> Result<usize> {
    if dims.contains(&0) {
        bail!("--dims {dims:?}: every dimension must be at least 1");
    }
    let whole = dims.map(|d| d as u64);
    let slice = whole[0] * whole[1];
    let slab = (slab_voxels / slice).clamp(1, whole[2]) as usize;
    let mut bytes = Vec::new();
    let mut channels = phantom.channel_count();
    for z0 in (0..dims[2]).step_by(slab) {
        let nz = slab.min(dims[2] - z0);
        let v = phantom
            .try_generate_region(whole, [0, 0, z0 as u64], [dims[0], dims[1], nz])
            .with_context(|| format!("generating slices {z0}..{} of {:?}", z0 + nz, dims))?;
        channels = v.channel_count();
        bytes.clear();
        dtype.append(&v.to_interleaved(), &mut bytes);
        out.write_all(&bytes)?;
        done(z0 + nz);
    }
    Ok(channels)
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
    let dtype = SampleType::parse(&a.dtype)?;
    let progress = Progress::new("phantom");
    let channels = super::write_output(&a.output, |_, out| {
        write_phantom(p, a.dims, dtype, SLAB_VOXELS, out, |z| {
            progress.stage(&format!("slice {z} of {}", a.dims[2]))
        })
        .with_context(|| format!("writing {}", a.output.display()))
    })?;
    progress.finish();
    outln!(
        "wrote {} ({}x{}x{}, {} channel(s), {})",
        a.output.display(),
        a.dims[0],
        a.dims[1],
        a.dims[2],
        channels,
        a.dtype
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Slab by slab, every phantom writes the bytes of the whole generated at once, with
    /// slabs of one slice, several slices, a remainder and the whole.
    #[test]
    fn slabs_write_the_whole_phantoms_bytes() {
        let dims = [7, 5, 9];
        for name in Phantom::names() {
            let p = Phantom::from_name(name).expect("listed name");
            for dtype in [SampleType::F32, SampleType::U8] {
                let mut whole = Vec::new();
                dtype.append(&p.generate(dims).to_interleaved(), &mut whole);
                for slab_voxels in [1, 35, 70, 4 * 35, 10_000] {
                    let mut out = Vec::new();
                    let mut slices = Vec::new();
                    let channels =
                        write_phantom(p, dims, dtype, slab_voxels, &mut out, |z| slices.push(z))
                            .expect("writes");
                    assert_eq!(channels, p.channel_count());
                    assert_eq!(out, whole, "{name} {dtype:?} slabs of {slab_voxels} voxels");
                    assert_eq!(slices.last(), Some(&dims[2]));
                    assert!(slices.windows(2).all(|w| w[0] < w[1]));
                }
            }
        }
    }

    #[test]
    fn a_zero_dimension_is_an_error() {
        let mut out = Vec::new();
        let e = write_phantom(Phantom::Ct, [4, 0, 4], SampleType::F32, 1, &mut out, |_| {})
            .expect_err("refused");
        assert!(e.to_string().contains("at least 1"), "{e}");
        assert!(out.is_empty());
    }
}
