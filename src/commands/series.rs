//! Time series at the command line: what `compress` and `info` read as one (the beating
//! phantom, a 4D file, a DICOM cine, a directory of time steps); `compress` of one into one
//! series file, with a summary of its time points, groups and bytes; `info` of a source; and
//! `render` of a series file's time points (one, or a range as PNGs through one display window
//! and an animated PNG).

use anyhow::{bail, Context, Result};
use wavesplat_compressor::bricked::BrickStage;
use wavesplat_compressor::encode::CompressOptions;
use wavesplat_compressor::series::{compress_series_to, SeriesSource};
use wavesplat_harness::console::Progress;

pub use wavesplat_compressor::series::SeriesInput;

/// The time series at `path`, when it is one ([`wavesplat_compressor::series::open_series_path`];
/// of its channels, `channel` when one is chosen),
/// its read errors reported with the path.
pub fn open_path(
    path: &std::path::Path,
    raw: Option<&wavesplat_compressor::reader::RawSpec>,
    channel: Option<usize>,
) -> Result<Option<SeriesInput>> {
    use wavesplat_compressor::series::open_series_path_channel;
    open_series_path_channel(path, raw, channel).map_err(|e| match e {
        wavesplat_compressor::series::SeriesError::Read(r) => super::read_error(path, *r),
        e => anyhow::Error::new(e).context(format!("reading {}", path.display())),
    })
}

/// What `info` says of a time series source: its time points, their size and their times.
pub fn describe_source(path: &std::path::Path, series: &dyn SeriesSource) -> String {
    let d = series.dims();
    let s = series.spacing();
    let n = series.time_points();
    let times = match series.times() {
        Some(t) if n > 1 => format!(
            ", {:.4} s apart (from {:.4} s to {:.4} s)",
            (t[n - 1] - t[0]) / (n - 1) as f64,
            t[0],
            t[n - 1]
        ),
        _ => ", no times in the source (numbered in order)".into(),
    };
    format!(
        "source      {}: a time series of {n} time points of {}x{}x{} x{} (spacing {} x {} x {}){times}\n\
         compress    wavesplat compress {} -o series.wsp (--time-point N takes one volume)",
        path.display(),
        d[0],
        d[1],
        d[2],
        series.channels(),
        s[0],
        s[1],
        s[2],
        path.display()
    )
}

/// Brick edge of a series' components when `--brick` is not given: a time point up to 256 a
/// side is one plain file per component.
const SERIES_BRICK: usize = 256;

/// `compress` of a time series: every time point into one series file.
pub fn compress(
    output: &std::path::Path,
    time_group: usize,
    brick: Option<usize>,
    opts: &CompressOptions,
    source: &dyn SeriesSource,
) -> Result<()> {
    let points = source.time_points();
    if !time_group.is_power_of_two() {
        bail!("--time-group {time_group}: a power of two (1 compresses each time point alone)");
    }
    let group = time_group.min(points.next_power_of_two());
    let brick = brick.unwrap_or(SERIES_BRICK);
    let d = source.dims();
    let progress = Progress::new("compress");
    progress.stage(&format!(
        "time series: {points} time points of {}x{}x{} in groups of {group}",
        d[0], d[1], d[2]
    ));
    let report = |stage: BrickStage| {
        progress.stage(&match stage {
            BrickStage::Scored { done, of } => format!("scoring part {done} of {of}"),
            BrickStage::Compressed { done, of, trial } => {
                format!("compressing part {done} of {of} (trial {trial})")
            }
        })
    };
    let c = super::write_output(output, |spill, out| {
        compress_series_to(source, opts, group, brick, &report, spill, out).context("compressing")
    })?;
    progress.finish();
    let m = &c.manifest;
    let samples =
        d.iter().map(|v| *v as f64).product::<f64>() * source.channels() as f64 * points as f64;
    outln!(
        "{}: {} bytes ({:.4} % of {} samples at one byte each), a time series of {points} time \
         points in groups of {group}: {} components",
        output.display(),
        c.bytes,
        100.0 * c.bytes as f64 / samples,
        samples,
        m.components.len()
    );
    let per_point: Vec<u64> = (0..points).map(|t| m.point_bytes(t)).collect();
    outln!(
        "volume {}x{}x{} x{} | {} M={} | kept {} | a time point reads {}..{} bytes{}",
        d[0],
        d[1],
        d[2],
        source.channels(),
        opts.family.name(),
        c.levels,
        super::kept_of(m.kept(), c.total_coefficients, None),
        per_point.iter().min().unwrap_or(&0),
        per_point.iter().max().unwrap_or(&0),
        match (m.times_known, m.points.get(1)) {
            (true, Some(p)) => format!(" | time step {:.4} s", p.time - m.points[0].time),
            _ => String::new(),
        }
    );
    Ok(())
}

/// The time points `--time-points` names in a series of `points`: `A..B` (both included) or
/// `all`.
pub fn parse_time_range(s: &str, points: usize) -> Result<std::ops::RangeInclusive<usize>> {
    let last = points - 1;
    if s.trim() == "all" {
        return Ok(0..=last);
    }
    let Some((a, b)) = s.split_once("..") else {
        bail!("--time-points {s:?}: give A..B (both included) or all");
    };
    let num = |v: &str| -> Result<usize> {
        v.trim()
            .parse()
            .with_context(|| format!("--time-points {s:?}: {v:?} is not a time point"))
    };
    let (a, b) = (num(a)?, num(b.trim_start_matches('='))?);
    if a > b || b > last {
        bail!("--time-points {s:?}: the series has time points 0..={last}, and A must not pass B");
    }
    Ok(a..=b)
}
