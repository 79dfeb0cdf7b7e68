//! What bricking costs at equal bytes: a volume compressed whole and in bricks to the same byte
//! target, both drawn at 256² and held to the reference ray caster of the original:
//! `cargo run --release -p wavesplat-viewer --example bricked_quality -- VOLUME BYTES BRICK...`.
//!
//! The volume is any file `compress` reads (read whole here: this measures quality, not
//! memory). Prints, per brick edge, the file sizes, the compression times and the image SNR in
//! three views (oblique, along an axis, oblique from the other side), whole against bricked,
//! and the depth each took; `WAVESPLAT_BRICK_LEVELS=M` gives the bricks depth M instead of the
//! one their byte target chooses. The figures are in BENCHMARKS.md ("Scale and robustness").
use std::path::Path;
use std::time::Instant;
use wavesplat_codec::layout::Geometry;
use wavesplat_codec::metrics::snr_db;
use wavesplat_codec::view::{View, ViewSpec};
use wavesplat_compressor::bricked::compress_bricked;
use wavesplat_compressor::encode::{compress, CompressOptions, Target};
use wavesplat_compressor::reader::read_volume;
use wavesplat_viewer::bricked::draw_bricked_file;
use wavesplat_viewer::open::draw_whole_file;
use wavesplat_viewer::reference::{render_reference, PaddedVolume};
use wavesplat_viewer::{CpuBackend, ReferenceOptions};

type Error = Box<dyn std::error::Error>;

/// Draws one view's image (its samples) from a file.
type Draw<'a> = &'a dyn Fn(&ViewSpec) -> Result<Vec<f32>, Error>;

fn main() -> Result<(), Error> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.len() < 3 {
        return Err("usage: bricked_quality VOLUME BYTES BRICK...".into());
    }
    let volume = read_volume(Path::new(&args[0]), None)?;
    let bytes: u64 = args[1].parse()?;
    let bricks: Vec<usize> = args[2..]
        .iter()
        .map(|a| a.parse())
        .collect::<Result<_, _>>()?;
    let opts = CompressOptions {
        target: Target::Bytes(bytes),
        ..CompressOptions::default()
    };
    let started = Instant::now();
    let whole = compress(&volume, &opts, &|_, _| {})?;
    let whole_s = started.elapsed().as_secs_f64();
    let g = Geometry::new(volume.dims(), opts.family, 0, 0)?.with_spacing(volume.spacing())?;
    let truth = PaddedVolume::from_volume(volume.channels(), &g);
    let reference = ReferenceOptions {
        supersample: 3,
        step: 0.125,
    };
    let views = [(0.66, 0.91), (0.0, 0.0), (1.2, -0.3)];
    let mut references = Vec::new();
    for (a, e) in views {
        let view = View::new(a, e, 256, 256);
        references.push((view, render_reference(&truth, &view, &reference)?));
    }
    let snr = |draw: Draw| {
        references
            .iter()
            .map(|(view, r)| Ok(snr_db(&r.data, &draw(&ViewSpec::single(*view))?)))
            .collect::<Result<Vec<f64>, Error>>()
    };
    let sw = snr(&|spec| {
        Ok(draw_whole_file(&whole.bytes, spec, &mut CpuBackend::new())?
            .image
            .data)
    })?;
    println!(
        "whole: {} B, {whole_s:.1} s, SNR {:.2} / {:.2} / {:.2} dB",
        whole.bytes.len(),
        sw[0],
        sw[1],
        sw[2]
    );
    // WAVESPLAT_BRICK_LEVELS=M compresses the bricks at depth M instead of the depth their
    // byte target chooses (the whole's depth is printed to compare).
    let brick_opts = CompressOptions {
        levels: match std::env::var("WAVESPLAT_BRICK_LEVELS") {
            Ok(m) => Some(m.parse()?),
            Err(_) => None,
        },
        ..opts.clone()
    };
    println!("whole: depth M = {}", whole.header.geometry.levels);
    for brick in bricks {
        let started = Instant::now();
        let b = compress_bricked(&volume, &brick_opts, brick, &|_| {})?;
        println!("{brick}³ bricks: depth M = {}", b.levels);
        let secs = started.elapsed().as_secs_f64();
        let sb = snr(&|spec| {
            Ok(draw_bricked_file(&b.bytes, spec, &mut CpuBackend::new())?
                .image
                .data)
        })?;
        println!(
            "{brick}³ bricks ({} of them): {} B, {secs:.1} s, SNR {:.2} / {:.2} / {:.2} dB \
             ({:+.2} / {:+.2} / {:+.2} against whole)",
            b.manifest.bricks.len(),
            b.bytes.len(),
            sb[0],
            sb[1],
            sb[2],
            sb[0] - sw[0],
            sb[1] - sw[1],
            sb[2] - sw[2]
        );
    }
    Ok(())
}
