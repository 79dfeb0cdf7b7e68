//! The demo's archive and report: the phantoms and the user's volumes written or found as an
//! archive the worker reads, and per volume the report section of its browsing runs (frame
//! PNGs, a CSV per run, charts of Q_I against time, bytes and frames, and a table of figures).
//! `wavesplat demo` drives it: it starts the local cluster, submits, browses and scores.

use crate::report::{Chart, Section, Series, Table};
use crate::scoring::{q_i_at, FrameQuality};
use anyhow::{bail, Context, Result};
use std::collections::HashSet;
use std::io::Write;
use std::path::{Path, PathBuf};
use wavesplat_codec::volume::Volume;
use wavesplat_viewer::walk::{percentile, FrameSample, PathStep};
use wavesplat_worker::archive;

/// One browsing run: a volume, a scene, its samples and their quality.
pub struct Run {
    /// The volume's name in the cache.
    pub volume: String,
    /// The scene: single, multiview or depth-cued.
    pub scene: &'static str,
    /// The volume's header.
    pub header: wavesplat_codec::format::Header,
    /// The accumulation backend's name.
    pub backend: String,
    /// The walk.
    pub path: Vec<PathStep>,
    /// Its frames.
    pub samples: Vec<FrameSample>,
    /// Their quality (after scoring).
    pub quality: Vec<Option<FrameQuality>>,
    /// The file's size in the cache.
    pub file_bytes: u64,
}

/// A volume of the demo archive: its name in the cache and its original samples.
pub struct ArchiveVolume {
    /// Its name in the cache.
    pub name: String,
    /// Its samples.
    pub original: Volume,
}

/// Writes `v` as raw little-endian f32 (channels interleaved) named by the raw convention.
pub fn write_raw(dir: &Path, name: &str, v: &Volume) -> Result<PathBuf> {
    let d = v.dims();
    let rgb = if v.channel_count() == 3 { "_rgb" } else { "" };
    let path = dir.join(format!("{name}_{}x{}x{}_f32{rgb}.raw", d[0], d[1], d[2]));
    let bytes: Vec<u8> = v
        .to_interleaved()
        .iter()
        .flat_map(|x| x.to_le_bytes())
        .collect();
    std::fs::write(&path, bytes).with_context(|| format!("writing {}", path.display()))?;
    Ok(path)
}

/// The found volumes of a `--volume` argument: the file itself, or what a directory holds.
pub fn found_for(path: &Path) -> Result<Vec<archive::Found>> {
    let meta = std::fs::metadata(path).with_context(|| format!("reading {}", path.display()))?;
    let scan_root = if meta.is_dir() {
        path.to_path_buf()
    } else {
        path.parent()
            .filter(|p| !p.as_os_str().is_empty())
            .unwrap_or(Path::new("."))
            .to_path_buf()
    };
    let scan = archive::scan(&scan_root).with_context(|| format!("scanning {}", path.display()))?;
    if meta.is_dir() {
        if scan.found.is_empty() {
            bail!("no supported volume under {}", path.display());
        }
        return Ok(scan.found);
    }
    let want = std::fs::canonicalize(path)?;
    let hit: Vec<archive::Found> = scan
        .found
        .into_iter()
        .filter(|f| std::fs::canonicalize(&f.path).is_ok_and(|p| p == want))
        .collect();
    if hit.is_empty() {
        bail!(
            "{} is not a supported volume (NIfTI, NRRD, MetaImage, DICOM, or raw named NAME_XxYxZ_DTYPE[_rgb].raw)",
            path.display()
        );
    }
    Ok(hit)
}

/// The original samples of a found volume, read as the worker reads them.
pub fn read_original(f: &archive::Found) -> Result<Volume> {
    let raw = f.raw.as_ref().map(wavesplat_worker::options::raw_spec);
    wavesplat_compressor::reader::read_volume(&f.path, raw.as_ref())
        .with_context(|| format!("reading {}", f.path.display()))
}

fn q_at(r: &Run, step: usize, n: u64) -> Option<f64> {
    q_i_at(&r.samples, &r.quality, step, n)
}

fn fmt(x: Option<f64>, digits: usize) -> String {
    x.filter(|v| v.is_finite())
        .map_or("–".into(), |v| format!("{v:.digits$}"))
}

/// Writes the runs' CSVs, frame PNGs and charts of volume `v`; returns its report section.
pub fn volume_section(
    out: &Path,
    v: &ArchiveVolume,
    runs: &[Run],
    frame_ms: f64,
) -> Result<Section> {
    let mine: Vec<&Run> = runs.iter().filter(|r| r.volume == v.name).collect();
    let slug = v.name.replace(['/', ' '], "_");
    let mut table = Table {
        head: [
            "scene",
            "frames",
            "first image ms",
            "converged ms",
            "Q_I 1 frame",
            "Q_I 10",
            "Q_I 60",
            "Q_I at rest",
            "Q_I after turn",
            "SNR final",
            "bytes",
            "of file",
            "frame p50 ms",
            "p95 ms",
            "past budget",
        ]
        .map(String::from)
        .to_vec(),
        rows: Vec::new(),
    };
    let mut images = Vec::new();
    let mut by_time = Vec::new();
    let mut by_bytes = Vec::new();
    let mut by_frame = Vec::new();
    for r in &mine {
        let csv_path = out.join("runs").join(format!("{slug}-{}.csv", r.scene));
        write_csv(&csv_path, r)?;
        let turn_end = r.path.len() - 1;
        let first_image = r
            .samples
            .iter()
            .find(|s| s.splatted > 0)
            .map(|s| s.t.as_secs_f64() * 1e3);
        let converged = r
            .samples
            .iter()
            .find(|s| s.step == 0 && s.converged)
            .map(|s| s.t.as_secs_f64() * 1e3);
        let times: Vec<f64> = r
            .samples
            .iter()
            .map(|s| s.frame_time.as_secs_f64() * 1e3)
            .collect();
        let over = times.iter().filter(|t| **t > frame_ms).count();
        let last_q = r.quality.iter().rev().flatten().next();
        table.rows.push(vec![
            r.scene.to_string(),
            r.samples.len().to_string(),
            fmt(first_image, 0),
            fmt(converged, 0),
            fmt(q_at(r, 0, 1), 1),
            fmt(q_at(r, 0, 10), 1),
            fmt(q_at(r, 0, 60), 1),
            fmt(q_at(r, 0, u64::MAX), 1),
            fmt(q_at(r, turn_end, u64::MAX), 1),
            fmt(last_q.map(|q| q.snr), 1),
            r.samples.last().map_or(0, |s| s.bytes).to_string(),
            r.file_bytes.to_string(),
            fmt(percentile(&times, 50.0), 1),
            fmt(percentile(&times, 95.0), 1),
            over.to_string(),
        ]);
        let pts = |x: &dyn Fn(&FrameSample) -> f64| -> Vec<(f64, f64)> {
            r.samples
                .iter()
                .zip(&r.quality)
                .filter_map(|(s, q)| q.map(|q| (x(s), q.q_i)))
                .collect()
        };
        by_time.push(Series::new(r.scene, pts(&|s| s.t.as_secs_f64() * 1e3)));
        by_bytes.push(Series::new(
            r.scene,
            pts(&|s| s.bytes as f64)
                .into_iter()
                .filter(|p| p.0 > 0.0)
                .collect(),
        ));
        by_frame.push(Series::new(r.scene, pts(&|s| s.frame as f64)));
        // Frames worth looking at: the first, the 10th, the converged rest, the turn's end and
        // the converged end.
        let step0: Vec<&FrameSample> = r.samples.iter().filter(|s| s.step == 0).collect();
        let picks = [
            ("first frame", r.samples.first()),
            ("frame 10", step0.get(9).copied()),
            ("at rest", step0.last().copied()),
            (
                "first frame after the turn",
                r.samples.iter().find(|s| s.step == turn_end),
            ),
            ("converged after the turn", r.samples.last()),
        ];
        for (caption, s) in picks {
            let Some(s) = s else { continue };
            let Some(img) = &s.image else { continue };
            let file = format!("frames/{slug}-{}-{:04}.png", r.scene, s.frame);
            img.write_png(&out.join(&file), None)?;
            let q = r.quality[(s.frame - 1) as usize];
            images.push((
                file,
                format!(
                    "{} {caption} (frame {}, {:.0} ms, Q_I {})",
                    r.scene,
                    s.frame,
                    s.t.as_secs_f64() * 1e3,
                    fmt(q.map(|q| q.q_i), 1)
                ),
            ));
        }
    }
    let chart_time = format!("charts/{slug}-qi-time.png");
    Chart {
        title: format!("{}: Q_I against time", v.name),
        x_label: "time since opening (ms)".into(),
        y_label: "Q_I (dB, paper units)".into(),
        log_x: true,
        series: by_time,
    }
    .write_png(&out.join(&chart_time), 560, 360)?;
    let chart_bytes = format!("charts/{slug}-qi-bytes.png");
    // Over a fast link every byte can arrive with the first frames: Q_I against bytes is then
    // a vertical line, and Q_I against frames says what the bytes cannot.
    let distinct_bytes: HashSet<u64> = by_bytes
        .iter()
        .flat_map(|s| s.points.iter().map(|p| p.0.to_bits()))
        .collect();
    let (title, x_label, series) = if distinct_bytes.len() >= 4 {
        ("Q_I against bytes received", "bytes received", by_bytes)
    } else {
        (
            "Q_I against frames (every byte arrived within the first frames)",
            "frame",
            by_frame,
        )
    };
    Chart {
        title: format!("{}: {title}", v.name),
        x_label: x_label.into(),
        y_label: "Q_I (dB, paper units)".into(),
        log_x: true,
        series,
    }
    .write_png(&out.join(&chart_bytes), 560, 360)?;
    let d = v.original.dims();
    Ok(Section {
        title: format!(
            "{} ({}×{}×{}, {} channel{})",
            v.name,
            d[0],
            d[1],
            d[2],
            v.original.channel_count(),
            if v.original.channel_count() == 1 {
                ""
            } else {
                "s"
            }
        ),
        text: format!(
            "Compressed file: {} bytes. Each line is one scene; the dips are the 90° turn \
             (a new view restarts accumulation from the most important coefficients held).",
            mine.first().map_or(0, |r| r.file_bytes)
        ),
        charts: vec![chart_time, chart_bytes],
        table,
        images,
    })
}

/// One CSV row per frame.
fn write_csv(path: &Path, r: &Run) -> Result<()> {
    let mut f = std::io::BufWriter::new(
        std::fs::File::create(path).with_context(|| format!("creating {}", path.display()))?,
    );
    writeln!(f, "{},q_i_paper_db,snr_db", FrameSample::CSV_COLUMNS)?;
    for (s, q) in r.samples.iter().zip(&r.quality) {
        writeln!(
            f,
            "{},{},{}",
            s.csv_row(),
            fmt(q.map(|q| q.q_i), 3),
            fmt(q.map(|q| q.snr), 3),
        )?;
    }
    f.flush()?;
    Ok(())
}
