//! `wavesplat view`: the workstation window (`wavesplat_viewer::window`) on a volume from a
//! `.wsp` file, a published URL or a cache. This module parses the arguments, opens the volume
//! the way `render` does, hands both to the window and prints what it did when it closes.

use super::render::ViewArgs;
use anyhow::{bail, Context, Result};
use clap::Args;
use std::path::PathBuf;
use wavesplat_codec::format::series::{is_series, parse_series};
use wavesplat_codec::view::{Cue, MAX_IMAGE_SIDE};
use wavesplat_viewer::open::{open, Opened, VolumeLocation};
use wavesplat_viewer::remote::{RangeSource, RangeSourceOptions};
use wavesplat_viewer::source::{CacheSource, CacheSourceOptions, FileSource, PacketSource};

/// Where the time points of a series played from elsewhere than a local file come from: a
/// cache (its URLs, CA and token, and the volume's name) or a published URL (and its CA).
enum RemoteSeries {
    Cache((String, wavesplat_client::ConnectOptions, String)),
    Published((String, Option<PathBuf>)),
}
use wavesplat_viewer::window::{self, Script, ViewState, WindowOptions};

/// Arguments of `wavesplat view`.
#[derive(Args, Debug)]
pub struct ViewWindowArgs {
    #[command(flatten)]
    pub view: ViewArgs,
    /// Time budget of one frame in milliseconds (+/- change it in the window).
    #[arg(long, default_value_t = 16.6)]
    pub frame_ms: f64,
    /// Largest image side in pixels (per view); the image follows the window up to this.
    #[arg(long, default_value_t = 1024)]
    pub max_image: usize,
    /// Largest image side in pixels while a drag turns or pans the view on the CPU backend,
    /// shown stretched to the window until the view rests (every frame of a drag is a new
    /// view, and a full-size one costs more than a frame to plan and draw on the host).
    #[arg(long, default_value_t = window::DEFAULT_INTERACTIVE_MAX_IMAGE)]
    pub drag_max_image: usize,
    /// Accumulate on the GPU (the window's adapter).
    #[arg(long, conflicts_with = "cpu")]
    pub gpu: bool,
    /// Accumulate on the CPU. Default: the GPU on a hardware adapter, else the CPU.
    #[arg(long)]
    pub cpu: bool,
    /// Directory for screenshots taken with S.
    #[arg(long, default_value = ".")]
    pub shot_dir: PathBuf,
    /// Write the image shown last to this PNG when the window closes.
    #[arg(long)]
    pub screenshot: Option<PathBuf>,
    /// Close after this many drawn frames (scripts and tests).
    #[arg(long)]
    pub exit_after_frames: Option<u64>,
    /// Synthetic input, run through the same handlers as real events: commands separated by
    /// `;` or new lines, or `@FILE`. Commands: `frames N`, `converge`, `drag X0,Y0 X1,Y1
    /// [shift] [over N]` (the moves in one frame, or spread over N frames), `wheel LINES`,
    /// `key K` (a letter, `+`, `-`, `[`, `]`, `esc`, `f1`, `left`, `right`, `space`),
    /// `played N` (wait until a playing time series moved on N times), `resize WxH`,
    /// `screenshot PATH`,
    /// `signal PATH` (create the file), `await PATH` (wait until it exists), `lose-device`
    /// (destroy the graphics device, as a driver reset would lose it: the window recreates
    /// it), `quit`.
    #[arg(long)]
    pub script: Option<String>,
}

/// Runs the subcommand.
pub fn run(a: ViewWindowArgs) -> Result<()> {
    let request = a.view.request()?;
    request.spec()?;
    // Checked now, not when the window closes with the session's image to write.
    if let Some(shot) = &a.screenshot {
        super::check_output(shot)?;
    }
    if !a.shot_dir.is_dir() {
        bail!(
            "--shot-dir {}: no such directory (screenshots taken with S go there)",
            a.shot_dir.display()
        );
    }
    if !(a.frame_ms.is_finite() && a.frame_ms > 0.0 && a.frame_ms <= 10_000.0) {
        bail!(
            "--frame-ms must be a positive number of milliseconds (at most 10000), got {}",
            a.frame_ms
        );
    }
    if a.max_image == 0 || a.max_image > MAX_IMAGE_SIDE {
        bail!(
            "--max-image must be in 1..={MAX_IMAGE_SIDE}, got {}",
            a.max_image
        );
    }
    if a.drag_max_image == 0 || a.drag_max_image > MAX_IMAGE_SIDE {
        bail!(
            "--drag-max-image must be in 1..={MAX_IMAGE_SIDE}, got {}",
            a.drag_max_image
        );
    }
    let script = match &a.script {
        Some(s) => Script::parse(&match s.strip_prefix('@') {
            Some(path) => {
                std::fs::read_to_string(path).with_context(|| format!("reading script {path}"))?
            }
            None => s.clone(),
        })?,
        None => Script::default(),
    };
    let location = a.view.location()?;
    if !(a.view.fps.is_finite() && a.view.fps > 0.0 && a.view.fps <= 1000.0) {
        bail!(
            "--fps {}: a rate in (0, 1000] time points per second",
            a.view.fps
        );
    }
    // A time series plays: its time points are opened from its bytes as the window asks.
    let series = match &location {
        VolumeLocation::File { path, bytes } if is_series(bytes) => {
            let m = parse_series(bytes)
                .with_context(|| format!("reading {}", path.display()))?
                .manifest;
            let points = m.points.len();
            if let Some(t) = a.view.time_point.filter(|t| *t >= points) {
                bail!(
                    "--time-point {t}: the series has {points} time points (0..={})",
                    points - 1
                );
            }
            let times = m
                .times_known
                .then(|| m.points.iter().map(|p| p.time).collect::<Vec<f64>>());
            Some((bytes.clone(), points, times))
        }
        VolumeLocation::Cache { .. } | VolumeLocation::Published { .. } => None,
        _ => {
            if a.view.time_point.is_some() {
                bail!("--time-point applies to a time series (a local file or in a cache)");
            }
            None
        }
    };
    let cache = match &location {
        VolumeLocation::Cache {
            urls,
            connect,
            name,
        } => Some((urls.clone(), connect.clone(), name.clone())),
        _ => None,
    };
    let published = match &location {
        VolumeLocation::Published { url, ca } => Some((url.clone(), ca.clone())),
        _ => None,
    };
    let title = location.describe();
    let (header, opened, spec) = open(location, &request, None)?;
    // A time series in a cache or published plays too: each time point is a stream (a
    // source) of its own.
    let times_of = |m: &wavesplat_codec::format::series::SeriesManifest| {
        let times = m
            .times_known
            .then(|| m.points.iter().map(|p| p.time).collect::<Vec<f64>>());
        (m.points.len(), times)
    };
    let cached_series = match (&opened, cache, published) {
        (Opened::Cache { source, .. }, Some(cache), _) => source
            .series()
            .map(|m| (RemoteSeries::Cache(cache), times_of(m))),
        (Opened::Remote { source, .. }, _, Some(published)) => source
            .series()
            .map(|m| (RemoteSeries::Published(published), times_of(m))),
        _ => None,
    };
    if cached_series.is_none()
        && matches!(opened, Opened::Cache { .. } | Opened::Remote { .. })
        && a.view.time_point.is_some()
    {
        bail!("--time-point applies to a time series; {title} is one volume");
    }
    // The window turns a view by its angles: a named patient view must be one.
    let state = ViewState::new(
        &spec,
        request.zoom,
        a.frame_ms,
        Cue::default_extinction(&header.geometry),
    );
    let state = match &a.view.view {
        Some(side) => state.with_context(|| format!("--view {side}"))?,
        None => state?,
    }
    .with_max_pixels_per_voxel(request.max_pixels_per_voxel);
    let bricked = opened.bricked_volume();
    let (state, playback) = match series {
        Some((bytes, points, times)) => {
            let state = state.with_time(a.view.time_point.unwrap_or(0), points, times, a.view.fps);
            let open = move |t: usize, spec: &wavesplat_codec::view::ViewSpec| {
                let source = FileSource::open_series_point(bytes.clone(), t, spec)?;
                let volume = source
                    .bricked_volume()
                    .ok_or("a time point is drawn as bricks")?;
                Ok((volume, Box::new(source) as Box<dyn PacketSource>))
            };
            (
                state,
                Some(window::SeriesPlayback {
                    open: Box::new(open),
                }),
            )
        }
        None => match cached_series {
            Some((remote, (points, times))) => {
                let state =
                    state.with_time(a.view.time_point.unwrap_or(0), points, times, a.view.fps);
                let open = move |t: usize, spec: &wavesplat_codec::view::ViewSpec| {
                    let (volume, source): (_, Box<dyn PacketSource>) = match &remote {
                        RemoteSeries::Cache((urls, connect, name)) => {
                            let options = CacheSourceOptions {
                                time_point: u32::try_from(t)?,
                                ..CacheSourceOptions::default()
                            };
                            let key = wavesplat_client::VolumeKey::Name(name.clone());
                            let (source, _) =
                                CacheSource::open_with(urls, connect, key, *spec, options)?;
                            (source.bricked_volume(), Box::new(source))
                        }
                        RemoteSeries::Published((url, ca)) => {
                            let options = RangeSourceOptions {
                                time_point: t,
                                ..RangeSourceOptions::default()
                            };
                            let (source, _) =
                                RangeSource::open(url, ca.as_deref(), *spec, options)?;
                            (source.bricked_volume(), Box::new(source))
                        }
                    };
                    let volume = volume.ok_or("a time point is drawn as bricks")?;
                    Ok((volume, source))
                };
                (
                    state,
                    Some(window::SeriesPlayback {
                        open: Box::new(open),
                    }),
                )
            }
            None => (state, None),
        },
    };
    let options = WindowOptions {
        max_image: a.max_image,
        interactive_max_image: a.drag_max_image,
        backend: super::backend_choice(a.gpu, a.cpu),
        window_size: (
            request.width.min(u32::MAX as usize) as u32,
            request.height.min(u32::MAX as usize) as u32,
        ),
        session: a.view.session_options(),
        shot_dir: a.shot_dir,
        screenshot: a.screenshot,
        exit_after_frames: a.exit_after_frames,
        script,
        title,
        bricked,
        series: playback,
    };
    let outcome = window::run(header, opened.into_source(), state, options)?;
    outln!(
        "view: {} frames drawn, {} coefficients held, {} splatted, {} bytes received, {}",
        outcome.drawn,
        outcome.coefficients_held,
        outcome.splatted_in_view,
        outcome.bytes,
        if outcome.converged {
            "converged"
        } else {
            "refining"
        }
    );
    if let Some(d) = &outcome.dragging {
        outln!(
            "view: {} frames while dragging, images up to {}x{}, frame time median {:.1} ms, 90th percentile {:.1} ms",
            d.frames(),
            d.largest_image.0,
            d.largest_image.1,
            d.frame_ms_quantile(0.5),
            d.frame_ms_quantile(0.9)
        );
    }
    if let Some(p) = outcome.playback {
        outln!(
            "view: played {} time points in {:.2} s ({:.1} per second), {} of those it left shown converged",
            p.advanced,
            p.playing.as_secs_f64(),
            p.advanced as f64 / p.playing.as_secs_f64().max(1e-9),
            p.left_converged
        );
        if p.kept > 1 {
            // Time points already drawn in this view (after the first loop): their kept images.
            outln!(
                "view: {} of them drawn before in this view, shown again at {:.1} per second",
                p.kept,
                (p.kept - 1) as f64 / p.kept_playing.as_secs_f64().max(1e-9)
            );
        }
        if p.opened_ahead > 0 {
            outln!(
                "view: {} of them opened ahead while the one before rested",
                p.opened_ahead
            );
        }
    }
    if let Some(c) = outcome.last_convergence {
        // What a user (and the window's test) reads to see that refinement had the time.
        outln!(
            "view: the last view converged {:.2} s after it changed, {:.0} % of that refining, {} images shown",
            c.elapsed.as_secs_f64(),
            100.0 * c.refining.as_secs_f64() / c.elapsed.as_secs_f64().max(1e-9),
            c.shown
        );
    }
    Ok(())
}
