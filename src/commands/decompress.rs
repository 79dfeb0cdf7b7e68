//! `wavesplat decompress`: full decode to raw f32, for checks against the original. A bricked
//! file is decoded brick by brick, each brick's rows written in place in the output file, so
//! the whole volume is never in memory.

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
    /// Of a time series, decode time point N (counting from 0; default 0).
    #[arg(long, value_name = "N")]
    pub time_point: Option<usize>,
}

/// Runs the subcommand.
pub fn run(a: DecompressArgs) -> Result<()> {
    super::check_output(&a.output)?;
    super::check_not_input(&a.output, &a.input)?;
    let bytes = super::read_wsp(&a.input)?;
    let series = wavesplat_codec::format::series::is_series(&bytes);
    if a.time_point.is_some() && !series {
        anyhow::bail!(
            "--time-point applies to a time series file; {} is one volume",
            a.input.display()
        );
    }
    if wavesplat_codec::format::bricked::is_bricked(&bytes) {
        return decompress_bricked(&a, &bytes);
    }
    let progress = wavesplat_harness::console::Progress::new("decompress");
    progress.stage("decoding packets and inverse transform");
    let v = if series {
        let t = a.time_point.unwrap_or(0);
        wavesplat_compressor::series::decode_time_point(&bytes, t)
            .with_context(|| format!("decoding time point {t} of {}", a.input.display()))?
    } else {
        wavesplat_compressor::decode::decompress(&bytes)
            .with_context(|| format!("decoding {}", a.input.display()))?
    };
    progress.finish();
    let out: Vec<u8> = v
        .to_interleaved()
        .iter()
        .flat_map(|x| x.to_le_bytes())
        .collect();
    super::write_output(&a.output, |_, w| {
        w.write_all(&out)
            .with_context(|| format!("writing {}", a.output.display()))
    })?;
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

/// Decodes a bricked file into the raw output brick by brick (rows written at their offsets).
fn decompress_bricked(a: &DecompressArgs, bytes: &[u8]) -> Result<()> {
    let manifest = wavesplat_codec::format::bricked::parse_bricked(bytes)
        .with_context(|| format!("reading {}", a.input.display()))?
        .manifest;
    let [nx, ny, nz] = manifest.dims;
    let c = manifest.channels as u64;
    let total = nx
        .checked_mul(ny)
        .and_then(|v| v.checked_mul(nz))
        .and_then(|v| v.checked_mul(4 * c))
        .context("the volume's size overflows")?;
    // A device (`-o /dev/null`) is written in place: a file renamed over it would replace it.
    if std::fs::metadata(&a.output).is_ok_and(|m| !m.is_file()) {
        let file = std::fs::File::options()
            .write(true)
            .open(&a.output)
            .with_context(|| format!("opening {}", a.output.display()))?;
        wavesplat_compressor::bricked::decode_bricks(bytes, &Default::default(), &|e, v| {
            write_brick_rows(&file, &manifest, e, v)
        })
        .with_context(|| format!("decoding {} into {}", a.input.display(), a.output.display()))?;
        outln!(
            "wrote {} ({nx}x{ny}x{nz}, {c} channel(s), f32 LE), decoded brick by brick",
            a.output.display()
        );
        return Ok(());
    }
    // Written beside the output (through a link, beside its target) and renamed over it once
    // complete, so a failure leaves neither a half-written file nor a lost earlier one. Not
    // sized up front: the bricks tile the whole, so the rows they write fill it, and a hostile
    // manifest claiming a huge volume fails at its first brick before anything large exists on
    // disk.
    let target = super::output_target(&a.output)
        .with_context(|| format!("reading the link {}", a.output.display()))?;
    let mut partial = target.clone().into_os_string();
    partial.push(".partial");
    let partial = std::path::PathBuf::from(partial);
    let file = super::interrupt::Unfinished::register(&partial, || std::fs::File::create(&partial))
        .with_context(|| format!("creating {}", partial.display()))?;
    let _unfinished = super::interrupt::Unfinished::guard(&partial);
    let progress = wavesplat_harness::console::Progress::new("decompress");
    progress.stage(&format!("decoding {} bricks", manifest.bricks.len()));
    let done = std::sync::atomic::AtomicUsize::new(0);
    let of = manifest.bricks.len();
    let decoded =
        wavesplat_compressor::bricked::decode_bricks(bytes, &Default::default(), &|e, v| {
            write_brick_rows(&file, &manifest, e, v)?;
            let n = done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
            progress.stage(&format!("decoded {n} of {of} bricks"));
            Ok(())
        })
        .with_context(|| format!("decoding {}", a.input.display()));
    progress.finish();
    let finished = decoded.and_then(|_| {
        let written = file
            .metadata()
            .with_context(|| format!("reading the size of {}", partial.display()))?
            .len();
        anyhow::ensure!(
            written == total,
            "{} holds {written} bytes after every brick, {total} expected",
            partial.display()
        );
        std::fs::rename(&partial, &target)
            .with_context(|| format!("renaming {} to {}", partial.display(), target.display()))
    });
    if let Err(e) = finished {
        let _ = std::fs::remove_file(&partial);
        return Err(e);
    }
    outln!(
        "wrote {} ({nx}x{ny}x{nz}, {c} channel(s), f32 LE), decoded brick by brick ({of} bricks)",
        a.output.display()
    );
    Ok(())
}

/// Writes one decoded brick's rows at their offsets in the whole's raw output.
fn write_brick_rows(
    file: &std::fs::File,
    manifest: &wavesplat_codec::format::bricked::Manifest,
    e: &wavesplat_codec::format::bricked::BrickEntry,
    v: wavesplat_codec::volume::Volume,
) -> std::io::Result<()> {
    use std::os::unix::fs::FileExt;
    let [nx, ny, _] = manifest.dims;
    let c = manifest.channels as u64;
    let samples = v.to_interleaved();
    let row = e.dims[0] * manifest.channels;
    let mut bytes: Vec<u8> = Vec::with_capacity(4 * row);
    for z in 0..e.dims[2] {
        for y in 0..e.dims[1] {
            let at = &samples[(z * e.dims[1] + y) * row..][..row];
            bytes.clear();
            bytes.extend(at.iter().flat_map(|x| x.to_le_bytes()));
            let (gy, gz) = (e.origin[1] + y as u64, e.origin[2] + z as u64);
            let offset = ((gz * ny + gy) * nx + e.origin[0]) * 4 * c;
            file.write_all_at(&bytes, offset)?;
        }
    }
    Ok(())
}
