//! `wavesplat demo`: the main job on a fresh machine, in one process and without a GPU. It
//! compresses a volume (a built-in phantom by default), then renders it straight from the
//! coefficient stream as it would arrive over the network: after growing byte budgets, each
//! image scored against the ground truth — the reference ray caster's X-ray of the original,
//! uncompressed volume (Q_I of eq. 18 in the paper's units and the conventional SNR) — plus a
//! multiview and a depth-cued image. Writes PNGs and a CSV of quality against bytes and time.

use super::render::load_coefficients;
use anyhow::{Context, Result};
use clap::Args;
use std::io::Write;
use std::path::PathBuf;
use wavesplat_codec::format::parse_file;
use wavesplat_codec::metrics::{q_i_paper_db, snr_db};
use wavesplat_compressor::encode::{compress, CompressOptions, Target};
use wavesplat_compressor::phantom::Phantom;
use wavesplat_viewer::{
    render_reference, Cue, CueDirection, PaddedVolume, ReferenceOptions, RenderOptions, Renderer,
    View,
};

/// Arguments of `wavesplat demo`.
#[derive(Args, Debug)]
pub struct DemoArgs {
    /// Output directory for the .wsp, PNGs and CSV.
    #[arg(long, default_value = "wavesplat-demo")]
    pub out: PathBuf,
    /// Phantom to use (shepp-logan, spheres, rgb-head, …).
    #[arg(long, default_value = "shepp-logan")]
    pub phantom: String,
    /// Phantom size (cube edge in voxels).
    #[arg(long, default_value_t = 96)]
    pub size: usize,
    /// Image size (square, pixels).
    #[arg(long, default_value_t = 256)]
    pub image: usize,
}

/// Runs the subcommand.
pub fn run(a: DemoArgs) -> Result<()> {
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let phantom = Phantom::from_name(&a.phantom).with_context(|| {
        format!(
            "unknown phantom {:?}; choose one of {:?}",
            a.phantom,
            Phantom::names()
        )
    })?;
    let volume = phantom.generate([a.size; 3]);
    outln!(
        "1/3 compressing the {} phantom ({}³, {} channel(s)) …",
        a.phantom,
        a.size,
        volume.channel_count()
    );
    let t = std::time::Instant::now();
    let opts = CompressOptions {
        target: Target::Fraction(0.03),
        ..Default::default()
    };
    let c = compress(&volume, &opts, &|_, _| {})?;
    let wsp = a.out.join("volume.wsp");
    std::fs::write(&wsp, &c.bytes)?;
    outln!(
        "    {} bytes ({:.3} % of 8-bit), {} coefficients, Q_V {:.3} %, {} packets, {:.2} s",
        c.bytes.len(),
        100.0 * c.bytes.len() as f64 / (volume.voxel_count() * volume.channel_count()) as f64,
        c.stats.kept,
        c.stats.q_v,
        c.stats.packets,
        t.elapsed().as_secs_f64()
    );

    outln!("2/3 rendering progressively from the coefficient stream …");
    let header = parse_file(&c.bytes)?.header;
    let mut renderer = Renderer::new(RenderOptions {
        channels: header.channels,
        ..RenderOptions::default()
    });
    let view = View::new(0.66, 0.91, a.image, a.image);
    let (_, all) = load_coefficients(&c.bytes, None, None)?;
    // Ground truth: exact line integrals of the original volume (same geometry and padding).
    let t = std::time::Instant::now();
    let original = PaddedVolume::from_volume(volume.channels(), &header.geometry);
    let reference = render_reference(&original, &view, &ReferenceOptions::default())?;
    reference.write_png(&a.out.join("reference.png"), None)?;
    outln!(
        "    reference ray caster on the original volume: {:.0} ms (reference.png)",
        t.elapsed().as_secs_f64() * 1e3
    );
    let mut csv = std::fs::File::create(a.out.join("progressive.csv"))?;
    writeln!(csv, "bytes,coefficients,render_ms,q_i_paper_db,snr_db")?;
    let total = c.bytes.len();
    let mut budget = 1024usize.min(total);
    loop {
        let (_, coeffs) = load_coefficients(&c.bytes, None, Some(budget))?;
        let t = std::time::Instant::now();
        let img = renderer.render(&coeffs, &header.geometry, &view)?;
        let ms = t.elapsed().as_secs_f64() * 1e3;
        let q = q_i_paper_db(&reference.data, &img.data);
        let s = snr_db(&reference.data, &img.data);
        writeln!(csv, "{budget},{},{ms:.2},{q:.3},{s:.3}", coeffs.len())?;
        outln!(
            "    {budget:>8} bytes  {:>7} coefficients  {ms:7.1} ms  Q_I {q:6.2} dB (paper units)  SNR {s:6.2} dB",
            coeffs.len()
        );
        img.write_png(&a.out.join(format!("progressive-{budget:08}.png")), None)?;
        if budget >= total {
            break;
        }
        budget = (budget * 4).min(total);
    }

    outln!("3/3 multiview and depth cueing …");
    let (mv, _) = renderer.render_multiview(&all, &header.geometry, &view)?;
    mv.write_png(&a.out.join("multiview.png"), None)?;
    let cued = renderer.render(
        &all,
        &header.geometry,
        &view.with_cue(Cue {
            k: 0.02,
            direction: CueDirection::View,
        }),
    )?;
    cued.write_png(&a.out.join("depth-cued.png"), None)?;
    outln!("wrote {}/{{volume.wsp, reference.png, progressive-*.png, multiview.png, depth-cued.png, progressive.csv}}", a.out.display());
    Ok(())
}
