//! `bench refine`'s view path and records: the walk (rest, a 90° turn, rest, a zoom into a
//! corner, rest), one run per frame budget and link speed with its frames and their quality,
//! the per-frame CSV and the charts of Q_I against time and bytes. `wavesplat bench refine`
//! drives it and prints the summary.

use crate::report::{Chart, Series};
use crate::scoring::{q_i_at, FrameQuality};
use anyhow::Result;
use std::io::Write;
use std::path::Path;
use wavesplat_codec::layout::Geometry;
use wavesplat_codec::view::{View, ViewSpec};
use wavesplat_viewer::walk::{turn, zoom_to, FrameSample, PathStep};

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
