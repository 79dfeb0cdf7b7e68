//! `bench refine`: framerate-constrained refinement against a cache on loopback. For each frame
//! budget and simulated link speed it walks one view path (rest, a 90° turn, rest, a zoom into
//! a corner, rest) through the frame loop and records per frame the time, the coefficients held
//! and splatted, the bytes received and Q_I / SNR against the reference ray caster's image of
//! the original volume for the same view. Writes `refine.csv` (every frame), `summary.csv` (per
//! run: frame-time percentiles against the budget, Q_I after 1, 10 and 60 frames from rest and
//! after the turn), `left_out.csv` (per scene opened straight at its view: the packets, bytes
//! and coefficients it did not need), charts, and the paper's Table 4 (`table4.csv`:
//! coefficients, Q_V and render time for RGB, YIQ and PCA at 4.6, 9.4, 79 and 368 KB on a 128³
//! RGB phantom) beside the paper's figures.

use crate::browse::{open_frame_loop, probe_backend, reference_options};
use crate::report::{Chart, Series};
use crate::scoring::{q_i_at, score_with, FrameQuality, GroundTruth};
use crate::throughput::median;
use crate::LocalStack;
use anyhow::{Context, Result};
use std::collections::HashMap;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};
use wavesplat_codec::format::parse_file;
use wavesplat_codec::layout::Geometry;
use wavesplat_codec::view::{View, ViewSpec};
use wavesplat_codec::volume::Volume;
use wavesplat_compressor::colorspace::ColorSpaceKind;
use wavesplat_compressor::encode::{compress, CompressOptions, Target, TileChoice};
use wavesplat_compressor::phantom::Phantom;
use wavesplat_viewer::backend::BackendChoice;
use wavesplat_viewer::open::load_coefficients;
use wavesplat_viewer::source::CacheSourceOptions;
use wavesplat_viewer::walk::{percentile, turn, walk, zoom_to, FrameSample, PathStep, WalkOptions};
use wavesplat_viewer::{RenderOptions, Renderer};

/// A link speed in words (0: unlimited).
pub fn link_name(mbit: f64) -> String {
    if mbit == 0.0 {
        "unlimited".into()
    } else {
        format!("{mbit} Mbit/s")
    }
}

/// One run: a budget, a link, its samples and their quality.
pub struct Run {
    /// The frame budget.
    pub budget_ms: f64,
    /// The simulated link speed (0: unlimited).
    pub link_mbit: f64,
    /// The frames.
    pub samples: Vec<FrameSample>,
    /// Their quality.
    pub quality: Vec<Option<FrameQuality>>,
}

/// The volume's largest physical extent (units of spacing).
pub fn widest_extent(geometry: &Geometry) -> f64 {
    (0..3)
        .map(|a| geometry.dims[a] as f64 * f64::from(geometry.spacing[a]))
        .fold(1.0, f64::max)
}

/// The benchmark's view path and the indices of its rests.
pub fn view_path(
    geometry: &Geometry,
    image: usize,
    rest: usize,
) -> Result<(Vec<PathStep>, [usize; 3])> {
    let start = ViewSpec::single(View::new(0.66, 0.91, image, image));
    let mut path = vec![PathStep::rest(start, rest)];
    path.extend(turn(
        start,
        [0.66, 0.91],
        [std::f64::consts::FRAC_PI_2, 0.0],
        6,
        3,
    ));
    let after_turn = path.len();
    let turned = path.last().expect("turn steps").spec;
    path.push(PathStep::rest(turned, rest));
    // Zoom ×4 into the corner a third of the volume off centre, up and right.
    let fit = wavesplat_codec::view::Camera::new(&turned.view, geometry)?.zoom;
    let off = widest_extent(geometry) / 3.0;
    path.extend(zoom_to(turned, geometry, 4.0 * fit, [off, off], 4, 3)?);
    let zoomed = path.last().expect("zoom steps").spec;
    path.push(PathStep::rest(zoomed, rest));
    let corner = path.len() - 1;
    Ok((path, [0, after_turn, corner]))
}

/// Q_I of a frame, NaN when not scored.
pub fn q_of(q: &Option<FrameQuality>) -> f64 {
    q.map_or(f64::NAN, |q| q.q_i)
}

/// Writes every run's frames as one CSV.
pub fn write_frames_csv(path: &Path, runs: &[Run]) -> Result<()> {
    let mut f = std::io::BufWriter::new(std::fs::File::create(path)?);
    writeln!(
        f,
        "budget_ms,link_mbit,{},q_i_paper_db,snr_db",
        FrameSample::CSV_COLUMNS
    )?;
    for r in runs {
        for (s, q) in r.samples.iter().zip(&r.quality) {
            writeln!(
                f,
                "{},{},{},{:.3},{:.3}",
                r.budget_ms,
                r.link_mbit,
                s.csv_row(),
                q_of(q),
                q.map_or(f64::NAN, |q| q.snr)
            )?;
        }
    }
    f.flush()?;
    Ok(())
}

/// Q_I `n` frames into path step `step` of a run.
pub fn q_at(r: &Run, step: usize, n: u64) -> f64 {
    q_i_at(&r.samples, &r.quality, step, n).unwrap_or(f64::NAN)
}

/// Writes the charts: Q_I against time and against bytes per frame budget and link speed.
pub fn write_charts(out: &Path, runs: &[Run], budgets: &[f64], links: &[f64]) -> Result<()> {
    // Q_I against time and bytes per link, at the budget nearest 16.6 ms.
    let mid = budgets
        .iter()
        .copied()
        .min_by(|a, b| (a - 16.6).abs().total_cmp(&(b - 16.6).abs()))
        .unwrap_or(16.6);
    let series = |x: &dyn Fn(&FrameSample) -> f64| -> Vec<Series> {
        runs.iter()
            .filter(|r| r.budget_ms == mid)
            .map(|r| {
                Series::new(
                    link_name(r.link_mbit),
                    r.samples
                        .iter()
                        .zip(&r.quality)
                        .map(|(s, q)| (x(s), q_of(q)))
                        .collect(),
                )
            })
            .collect()
    };
    Chart {
        title: format!("Q_I against time (budget {mid} ms; rest, turn, rest, zoom, rest)"),
        x_label: "time (ms)".into(),
        y_label: "Q_I (dB, paper units)".into(),
        log_x: false,
        series: series(&|s| s.t.as_secs_f64() * 1e3),
    }
    .write_png(&out.join("qi-time.png"), 720, 420)?;
    Chart {
        title: format!("Q_I against bytes received (budget {mid} ms)"),
        x_label: "bytes received".into(),
        y_label: "Q_I (dB, paper units)".into(),
        log_x: true,
        series: series(&|s| s.bytes as f64),
    }
    .write_png(&out.join("qi-bytes.png"), 720, 420)?;
    // Frame-time distribution per budget (fastest link): the CDF, with the budgets marked.
    let fastest = links.iter().copied().fold(f64::NAN, |m, l| {
        if m.is_nan() || l == 0.0 || (m != 0.0 && l > m) {
            l
        } else {
            m
        }
    });
    let mut cdf = Vec::new();
    for r in runs.iter().filter(|r| r.link_mbit == fastest) {
        let mut t: Vec<f64> = r
            .samples
            .iter()
            .map(|s| s.frame_time.as_secs_f64() * 1e3)
            .collect();
        t.sort_by(f64::total_cmp);
        let n = t.len().max(1) as f64;
        cdf.push(Series::new(
            format!("budget {} ms", r.budget_ms),
            t.iter()
                .enumerate()
                .map(|(i, v)| (v.max(0.01), (i + 1) as f64 / n))
                .collect(),
        ));
        cdf.push(Series::marker(
            format!("{} ms", r.budget_ms),
            vec![(r.budget_ms, 0.0), (r.budget_ms, 1.0)],
        ));
    }
    Chart {
        title: "Frame time distribution against the budget".into(),
        x_label: "frame time (ms)".into(),
        y_label: "fraction of frames".into(),
        log_x: true,
        series: cdf,
    }
    .write_png(&out.join("frame-times.png"), 720, 420)?;
    Ok(())
}

/// What `bench refine` measures: the volume, the frame budgets and link speeds (Mbit/s, 0: no
/// limit) of its runs, the image side, the most frames to rest at a view, whether the paper's
/// Table 4 is made too, and the output directory.
pub struct RefineBench {
    /// The volume compressed and browsed.
    pub volume: Volume,
    /// Frame budgets (ms).
    pub budgets: Vec<f64>,
    /// Link speeds (Mbit/s; 0: unlimited).
    pub links: Vec<f64>,
    /// Image side in pixels.
    pub image: usize,
    /// Most frames to rest at a view.
    pub rest_frames: usize,
    /// Whether to make the paper's Table 4 (twelve compressions of a 128³ RGB phantom).
    pub table4: bool,
    /// Output directory (created).
    pub out: PathBuf,
    /// Accumulation backend; `Auto` takes the GPU only on a hardware adapter.
    pub backend: BackendChoice,
}

/// Runs `bench refine` (see the module doc), writing its files under `bench.out` and its
/// progress and tables to `say`.
pub fn run(bench: &RefineBench, say: &mut dyn Write) -> Result<()> {
    std::fs::create_dir_all(&bench.out)
        .with_context(|| format!("creating {}", bench.out.display()))?;
    let volume = &bench.volume;
    let d = volume.dims();
    writeln!(
        say,
        "compressing a {}×{}×{} volume (5 % of the coefficients, tiles of 32, 4 layers) …",
        d[0], d[1], d[2]
    )?;
    let c = compress(
        volume,
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
    let (path, rests) = view_path(&header.geometry, bench.image, bench.rest_frames)?;
    let (backend, reason) = probe_backend(bench.backend)?;
    writeln!(say, "    backend: {reason}")?;
    let truth = GroundTruth::new(volume, &header.geometry, reference_options());
    let mut references = HashMap::new();
    let mut runs = Vec::new();
    for &budget_ms in &bench.budgets {
        for &link_mbit in &bench.links {
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
            writeln!(
                say,
                "budget {budget_ms:>5} ms, link {:>12}: {:4} frames in {:.1} s",
                link_name(link_mbit),
                samples.len(),
                t.elapsed().as_secs_f64()
            )?;
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
        say,
        &bench.out,
        &stack.cache_url,
        &header,
        backend,
        (file_bytes, total_packets, c.stats.kept),
        bench.image,
        bench.rest_frames,
    )?;
    stack.shutdown()?;
    write_frames_csv(&bench.out.join("refine.csv"), &runs)?;
    write_summary(say, &bench.out, &runs, &rests, file_bytes)?;
    write_charts(&bench.out, &runs, &bench.budgets, &bench.links)?;
    if bench.table4 {
        table4(say, &bench.out)?;
    }
    writeln!(
        say,
        "wrote {}/{{refine.csv, summary.csv, *.png{}}}",
        bench.out.display(),
        if !bench.table4 { "" } else { ", table4.csv" }
    )?;
    Ok(())
}

/// What each scene leaves out: a fresh session opened straight at each view, resting until
/// converged (16.6 ms frames, no link limit), asking the cache only for what the view sees.
/// Reports packets and bytes received against the whole file and the coefficients held,
/// splatted and not splatted (invisible in the view).
fn left_out(
    say: &mut dyn Write,
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
    writeln!(
        say,
        "what each scene leaves out (opened straight at the view, resting until converged):"
    )?;
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
        writeln!(say,
            "  {name:34} {:>4}/{total_packets} packets, {:>7}/{file_bytes} bytes ({:4.1} % left out), {:>7} coefficients splatted, {:>6} held but invisible, converged {}, {:.0} ms",
            last.packets,
            last.bytes,
            100.0 * (1.0 - last.bytes as f64 / file_bytes as f64),
            last.splatted,
            last.invisible,
            last.converged,
            last.t.as_secs_f64() * 1e3
        )?;
    }
    Ok(())
}

/// Writes `summary.csv` and prints it: frame-time percentiles against the budget and Q_I after
/// 1, 10 and 60 frames from rest, after the turn and in the corner, per run.
fn write_summary(
    say: &mut dyn Write,
    out: &Path,
    runs: &[Run],
    rests: &[usize; 3],
    file_bytes: u64,
) -> Result<()> {
    let mut f = std::fs::File::create(out.join("summary.csv"))?;
    writeln!(
        f,
        "budget_ms,link_mbit,frames,frame_p50_ms,frame_p95_ms,frame_p99_ms,frames_over_budget,max_batches_past_deadline,q_i_1,q_i_10,q_i_60,q_i_rest,q_i_first_after_turn,q_i_10_after_turn,q_i_after_turn_rest,q_i_corner_rest,bytes_for_rest_view,invisible_corner,held_corner,file_bytes"
    )?;
    writeln!(
        say,
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
    )?;
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
        // The CSV keeps every figure to 0.01; the printed table a selection to 0.1.
        let csv = |xs: &[f64]| {
            let cells: Vec<String> = xs.iter().map(|x| format!("{x:.2}")).collect();
            cells.join(",")
        };
        let (held, invisible) = corner_last.map_or((0, 0), |s| (s.coefficients_held, s.invisible));
        writeln!(
            f,
            "{},{},{},{},{over},{past},{},{bytes_needed},{invisible},{held},{file_bytes}",
            r.budget_ms,
            r.link_mbit,
            r.samples.len(),
            csv(&row[..3]),
            csv(&row[3..]),
        )?;
        let cols = |xs: &[f64], w: usize| {
            let cells: Vec<String> = xs.iter().map(|x| format!("{x:>w$.1}")).collect();
            cells.join(" ")
        };
        writeln!(
            say,
            "{:>7} {:>12} {} {over:>6} {:>5.1} {} {:>7.1} {:>7.1} {bytes_needed:>9}",
            r.budget_ms,
            link_name(r.link_mbit),
            cols(&row[..3], 6),
            row[3],
            cols(&row[4..8], 6),
            row[8],
            row[10],
        )?;
    }
    Ok(())
}

/// The paper's Table 4 on a 128³ RGB phantom: kept coefficients, Q_V and the one-shot render
/// time (256², median of 3) per colour space and file size, beside the paper's figures.
fn table4(say: &mut dyn Write, out: &Path) -> Result<()> {
    // (KB, [(coefficients, Q_V %)] for RGB, YIQ, PCA) from the paper.
    const PAPER: [(f64, [(u64, f64); 3]); 4] = [
        (4.6, [(2155, 65.38), (2175, 81.61), (2184, 85.61)]),
        (9.4, [(4480, 82.73), (4221, 86.91), (3820, 88.27)]),
        (79.0, [(31714, 92.14), (35655, 94.6), (30554, 94.74)]),
        (368.0, [(170761, 96.82), (178065, 98.22), (172240, 98.47)]),
    ];
    writeln!(
        say,
        "Table 4 on a 128³ RGB phantom (the paper's in brackets) …"
    )?;
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
        writeln!(say, "{line}")?;
    }
    Ok(())
}
