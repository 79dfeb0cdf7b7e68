//! `wavesplat bench refine`: framerate-constrained refinement against a cache on loopback. For
//! each frame budget and simulated link speed it walks one view path (rest, a 90° turn, rest,
//! a zoom into a corner, rest) through the frame loop and records per frame the time, the
//! coefficients held and splatted, the bytes received and Q_I / SNR against the reference ray
//! caster's image of the original volume for the same view. Writes `refine.csv` (every
//! frame), `summary.csv` (per run: frame-time percentiles against the budget, Q_I after 1,
//! 10 and 60 frames from rest and after the turn), `left_out.csv` (per scene opened straight
//! at its view: the packets, bytes and coefficients it did not need), charts, and the
//! paper's Table 4 (`table4.csv`: coefficients, Q_V and render time for RGB, YIQ and PCA at
//! 4.6, 9.4, 79 and 368 KB on a 128³ RGB phantom) beside the paper's figures.

use super::throughput::median;
use anyhow::{bail, Context, Result};
use clap::Args;
use std::collections::HashMap;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};
use wavesplat_codec::format::parse_file;
use wavesplat_codec::view::{View, ViewSpec};
use wavesplat_codec::volume::Volume;
use wavesplat_compressor::colorspace::ColorSpaceKind;
use wavesplat_compressor::encode::{compress, CompressOptions, Target, TileChoice};
use wavesplat_compressor::phantom::Phantom;
use wavesplat_harness::browse::{open_frame_loop, probe_backend, reference_options};
use wavesplat_harness::refine::{
    link_name, q_at, q_of, view_path, widest_extent, write_charts, write_frames_csv, Run,
};
use wavesplat_harness::scoring::{score_with, GroundTruth};
use wavesplat_harness::LocalStack;
use wavesplat_viewer::backend::BackendChoice;
use wavesplat_viewer::open::load_coefficients;
use wavesplat_viewer::source::CacheSourceOptions;
use wavesplat_viewer::walk::{percentile, walk, PathStep, WalkOptions};
use wavesplat_viewer::{RenderOptions, Renderer};

/// Arguments of `wavesplat bench refine`.
#[derive(Args, Debug)]
pub struct RefineArgs {
    /// Volume file (NIfTI, NRRD, MetaImage, DICOM directory); default: a Shepp–Logan phantom.
    #[arg(long)]
    pub volume: Option<PathBuf>,
    /// Phantom edge when no volume is given (X×X×3X/4).
    #[arg(long, default_value_t = 96)]
    pub size: usize,
    /// Image side in pixels.
    #[arg(long, default_value_t = 256)]
    pub image: usize,
    /// Frame budgets in milliseconds, comma-separated.
    #[arg(long, default_value = "8,16.6,33,100")]
    pub budgets: String,
    /// Link speeds in Mbit/s, comma-separated (`unlimited` or 0 for no limit).
    #[arg(long, default_value = "unlimited,100,10,1")]
    pub links: String,
    /// Most frames to rest at a view waiting for convergence.
    #[arg(long, default_value_t = 300)]
    pub rest_frames: usize,
    /// Skip the paper's Table 4 (twelve compressions of a 128³ RGB phantom).
    #[arg(long)]
    pub no_table4: bool,
    /// Output directory.
    #[arg(long, default_value = "bench-refine")]
    pub out: PathBuf,
}

fn parse_list(s: &str, what: &str) -> Result<Vec<f64>> {
    s.split(',')
        .map(|t| {
            let t = t.trim();
            if t.eq_ignore_ascii_case("unlimited") || t.eq_ignore_ascii_case("inf") {
                return Ok(0.0);
            }
            let v: f64 = t
                .parse()
                .with_context(|| format!("{what}: {t:?} is not a number"))?;
            if !(v.is_finite() && v >= 0.0) {
                bail!("{what}: {t:?} must be a non-negative number");
            }
            Ok(v)
        })
        .collect()
}

/// Runs the subcommand.
pub fn run(a: RefineArgs) -> Result<()> {
    let budgets = parse_list(&a.budgets, "--budgets")?;
    if budgets.iter().any(|b| *b <= 0.0) {
        bail!("--budgets must be positive milliseconds");
    }
    let links = parse_list(&a.links, "--links")?;
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let volume: Volume = match &a.volume {
        Some(p) => wavesplat_compressor::reader::read_volume(p, None)
            .with_context(|| format!("reading {}", p.display()))?,
        None => Phantom::SheppLogan.generate([a.size, a.size, (3 * a.size / 4).max(1)]),
    };
    let d = volume.dims();
    outln!(
        "compressing a {}×{}×{} volume (5 % of the coefficients, tiles of 32, 4 layers) …",
        d[0],
        d[1],
        d[2]
    );
    let c = compress(
        &volume,
        &CompressOptions {
            target: Target::Fraction(0.05),
            tile: TileChoice::Size(32),
            layers: Some(4),
            ..Default::default()
        },
        &|_, _| {},
    )?;
    let header = parse_file(&c.bytes)?.header;
    let file_bytes = c.bytes.len() as u64;
    let db = tempfile::tempdir()?;
    let stack = LocalStack::start(db.path(), false, 0)?;
    stack
        .block_on(async {
            let mut client = wavesplat_client::CacheClient::connect(&stack.cache_url).await?;
            client.ingest("bench", &c.bytes).await
        })
        .context("ingesting into the local cache")?;
    let (path, rests) = view_path(&header.geometry, a.image, a.rest_frames)?;
    let (backend, reason) = probe_backend()?;
    outln!("    backend: {reason}");
    let truth = GroundTruth::new(&volume, &header.geometry, reference_options());
    let mut references = HashMap::new();
    let mut runs = Vec::new();
    for &budget_ms in &budgets {
        for &link_mbit in &links {
            let t = Instant::now();
            let options = CacheSourceOptions {
                link_bytes_per_second: (link_mbit > 0.0)
                    .then(|| (link_mbit * 1e6 / 8.0).round().max(1.0) as u64),
                ..CacheSourceOptions::default()
            };
            let (_, mut frames) =
                open_frame_loop(&stack.cache_url, "bench", path[0].spec, options, backend)?;
            let mut wo = WalkOptions::new(Duration::from_secs_f64(budget_ms / 1e3));
            wo.stall_limit = Duration::from_secs(120);
            let samples = walk(&mut frames, &path, &wo)?;
            drop(frames);
            let quality = score_with(&truth, &path, &samples, &mut references)?;
            outln!(
                "budget {budget_ms:>5} ms, link {:>12}: {:4} frames in {:.1} s",
                link_name(link_mbit),
                samples.len(),
                t.elapsed().as_secs_f64()
            );
            runs.push(Run {
                budget_ms,
                link_mbit,
                // Images are scored; drop them to keep memory flat across runs.
                samples: samples
                    .into_iter()
                    .map(|mut s| {
                        s.image = None;
                        s
                    })
                    .collect(),
                quality,
            });
        }
    }
    let total_packets = parse_file(&c.bytes)?.packets.len();
    left_out(
        &a.out,
        &stack.cache_url,
        &header,
        backend,
        (file_bytes, total_packets, c.stats.kept),
        a.image,
        a.rest_frames,
    )?;
    stack.shutdown()?;
    write_frames_csv(&a.out.join("refine.csv"), &runs)?;
    write_summary(&a.out, &runs, &rests, file_bytes)?;
    write_charts(&a.out, &runs, &budgets, &links)?;
    if !a.no_table4 {
        table4(&a.out)?;
    }
    outln!(
        "wrote {}/{{refine.csv, summary.csv, *.png{}}}",
        a.out.display(),
        if a.no_table4 { "" } else { ", table4.csv" }
    );
    Ok(())
}

/// What each scene leaves out: a fresh session opened straight at each view, resting until
/// converged (16.6 ms frames, no link limit), asking the cache only for what the view sees.
/// Reports packets and bytes received against the whole file and the coefficients held,
/// splatted and not splatted (invisible in the view).
fn left_out(
    out: &Path,
    url: &str,
    header: &wavesplat_codec::format::Header,
    backend: BackendChoice,
    (file_bytes, total_packets, total_coefficients): (u64, usize, u64),
    image: usize,
    rest: usize,
) -> Result<()> {
    let oblique = View::new(0.66, 0.91, image, image);
    let fit = wavesplat_codec::view::Camera::new(&oblique, &header.geometry)?.zoom;
    let off = widest_extent(&header.geometry) / 3.0;
    let scenes = [
        ("oblique, whole volume", ViewSpec::single(oblique)),
        (
            "on the x axis",
            ViewSpec::single(View::new(0.0, 0.0, image, image)),
        ),
        (
            "zoomed ×4 into a corner",
            ViewSpec::single(oblique.with_zoom(4.0 * fit).with_pan([off, off])),
        ),
        (
            "zoomed ×8 into a corner",
            ViewSpec::single(oblique.with_zoom(8.0 * fit).with_pan([off, off])),
        ),
        (
            "multiview",
            ViewSpec {
                view: oblique,
                multiview: true,
            },
        ),
    ];
    let mut f = std::fs::File::create(out.join("left_out.csv"))?;
    writeln!(
        f,
        "scene,packets,total_packets,bytes,file_bytes,coefficients_held,splatted,invisible,total_coefficients,converged_ms"
    )?;
    outln!("what each scene leaves out (opened straight at the view, resting until converged):");
    for (name, spec) in scenes {
        let (_, mut frames) =
            open_frame_loop(url, "bench", spec, CacheSourceOptions::default(), backend)?;
        let mut wo = WalkOptions::new(Duration::from_secs_f64(16.6e-3));
        wo.capture = false;
        let samples = walk(&mut frames, &[PathStep::rest(spec, rest)], &wo)?;
        let last = samples.last().context("no frame")?;
        writeln!(
            f,
            "{name},{},{total_packets},{},{file_bytes},{},{},{},{total_coefficients},{:.1}",
            last.packets,
            last.bytes,
            last.coefficients_held,
            last.splatted,
            last.invisible,
            last.t.as_secs_f64() * 1e3
        )?;
        outln!(
            "  {name:34} {:>4}/{total_packets} packets, {:>7}/{file_bytes} bytes ({:4.1} % left out), {:>7} coefficients splatted, {:>6} held but invisible, converged {}, {:.0} ms",
            last.packets,
            last.bytes,
            100.0 * (1.0 - last.bytes as f64 / file_bytes as f64),
            last.splatted,
            last.invisible,
            last.converged,
            last.t.as_secs_f64() * 1e3
        );
    }
    Ok(())
}

/// Writes `summary.csv` and prints it: frame-time percentiles against the budget and Q_I after
/// 1, 10 and 60 frames from rest, after the turn and in the corner, per run.
fn write_summary(out: &Path, runs: &[Run], rests: &[usize; 3], file_bytes: u64) -> Result<()> {
    let mut f = std::fs::File::create(out.join("summary.csv"))?;
    writeln!(
        f,
        "budget_ms,link_mbit,frames,frame_p50_ms,frame_p95_ms,frame_p99_ms,frames_over_budget,max_batches_past_deadline,q_i_1,q_i_10,q_i_60,q_i_rest,q_i_first_after_turn,q_i_10_after_turn,q_i_after_turn_rest,q_i_corner_rest,bytes_for_rest_view,invisible_corner,held_corner,file_bytes"
    )?;
    outln!(
        "{:>7} {:>12} {:>6} {:>6} {:>6} {:>6} {:>5} {:>6} {:>6} {:>6} {:>6} {:>7} {:>7} {:>9}",
        "budget",
        "link",
        "p50",
        "p95",
        "p99",
        "over",
        "Q1",
        "Q10",
        "Q60",
        "Qrest",
        "Qturn",
        "Qturn10",
        "Qcorner",
        "bytes@99%"
    );
    for r in runs {
        let times: Vec<f64> = r
            .samples
            .iter()
            .map(|s| s.frame_time.as_secs_f64() * 1e3)
            .collect();
        let over = times.iter().filter(|t| **t > r.budget_ms).count();
        let past = r
            .samples
            .iter()
            .map(|s| s.batches_past_deadline)
            .max()
            .unwrap_or(0);
        let [rest0, turned, corner] = *rests;
        let q_rest = q_at(r, rest0, u64::MAX);
        // Bytes the first view needed: received when its Q_I first came within 1 % (0.04 dB
        // in power terms ≈ 0.1 dB) of its final value.
        let bytes_needed = r
            .samples
            .iter()
            .zip(&r.quality)
            .filter(|(s, _)| s.step == rest0)
            .find(|(_, q)| q_of(q) >= q_rest - 0.1)
            .map_or(0, |(s, _)| s.bytes);
        let corner_last = r.samples.iter().rfind(|s| s.step == corner);
        let p = |x: f64| percentile(&times, x).unwrap_or(f64::NAN);
        let row = [
            p(50.0),
            p(95.0),
            p(99.0),
            q_at(r, rest0, 1),
            q_at(r, rest0, 10),
            q_at(r, rest0, 60),
            q_rest,
            q_at(r, turned, 1),
            q_at(r, turned, 10),
            q_at(r, turned, u64::MAX),
            q_at(r, corner, u64::MAX),
        ];
        writeln!(
            f,
            "{},{},{},{:.2},{:.2},{:.2},{over},{past},{:.2},{:.2},{:.2},{:.2},{:.2},{:.2},{:.2},{:.2},{bytes_needed},{},{},{file_bytes}",
            r.budget_ms,
            r.link_mbit,
            r.samples.len(),
            row[0],
            row[1],
            row[2],
            row[3],
            row[4],
            row[5],
            row[6],
            row[7],
            row[8],
            row[9],
            row[10],
            corner_last.map_or(0, |s| s.invisible),
            corner_last.map_or(0, |s| s.coefficients_held),
        )?;
        outln!(
            "{:>7} {:>12} {:>6.1} {:>6.1} {:>6.1} {:>6} {:>5.1} {:>6.1} {:>6.1} {:>6.1} {:>6.1} {:>7.1} {:>7.1} {:>9}",
            r.budget_ms,
            link_name(r.link_mbit),
            row[0],
            row[1],
            row[2],
            over,
            row[3],
            row[4],
            row[5],
            row[6],
            row[7],
            row[8],
            row[10],
            bytes_needed
        );
    }
    Ok(())
}

/// The paper's Table 4 on a 128³ RGB phantom: kept coefficients, Q_V and the one-shot render
/// time (256², median of 3) per colour space and file size, beside the paper's figures.
fn table4(out: &Path) -> Result<()> {
    // (KB, [(coefficients, Q_V %)] for RGB, YIQ, PCA) from the paper.
    const PAPER: [(f64, [(u64, f64); 3]); 4] = [
        (4.6, [(2155, 65.38), (2175, 81.61), (2184, 85.61)]),
        (9.4, [(4480, 82.73), (4221, 86.91), (3820, 88.27)]),
        (79.0, [(31714, 92.14), (35655, 94.6), (30554, 94.74)]),
        (368.0, [(170761, 96.82), (178065, 98.22), (172240, 98.47)]),
    ];
    outln!("Table 4 on a 128³ RGB phantom (the paper's in brackets) …");
    let volume = Phantom::RgbHead.generate([128; 3]);
    let mut f = std::fs::File::create(out.join("table4.csv"))?;
    writeln!(
        f,
        "kbytes,colorspace,bytes,coefficients,q_v_percent,render_ms,paper_coefficients,paper_q_v_percent"
    )?;
    let spaces = [
        ("RGB", ColorSpaceKind::Rgb),
        ("YIQ", ColorSpaceKind::Yiq),
        ("PCA", ColorSpaceKind::Pca),
    ];
    for (kb, paper) in PAPER {
        let mut line = format!("{kb:>6} KB");
        for ((name, space), (pc, pq)) in spaces.iter().zip(paper) {
            let c = compress(
                &volume,
                &CompressOptions {
                    family: wavesplat_codec::family::Family::Haar,
                    levels: Some(3),
                    colorspace: *space,
                    target: Target::Bytes((kb * 1024.0) as u64),
                    refine: None,
                    ..Default::default()
                },
                &|_, _| {},
            )?;
            let (header, coeffs) = load_coefficients(&c.bytes, None, None)?;
            let mut r = Renderer::new(RenderOptions {
                channels: header.channels,
                ..RenderOptions::default()
            });
            let view = View::new(0.66, 0.91, 256, 256);
            r.render(&coeffs, &header.geometry, &view)?;
            let mut times = Vec::new();
            for _ in 0..3 {
                let t = Instant::now();
                r.render(&coeffs, &header.geometry, &view)?;
                times.push(t.elapsed().as_secs_f64() * 1e3);
            }
            let ms = median(times);
            writeln!(
                f,
                "{kb},{name},{},{},{:.2},{ms:.2},{pc},{pq}",
                c.bytes.len(),
                c.stats.kept,
                c.stats.q_v,
            )?;
            line.push_str(&format!(
                " | {name} {:>6} ({pc:>6}) {:5.2} % ({pq:5.2}) {ms:6.1} ms",
                c.stats.kept, c.stats.q_v
            ));
        }
        outln!("{line}");
    }
    Ok(())
}
