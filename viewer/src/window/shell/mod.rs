//! The winit 0.30 front-end of the window: the application handler, a wgpu surface on the
//! adapter it chose (the GPU accumulation backend shares that device when it is chosen, and its
//! display pass then makes the texture drawn, so no image crosses the bus; a host image — the
//! CPU backend's, a preview's — is uploaded), blitted with `wgpu::util::TextureBlitter`; surface
//! upkeep (resize, minimise, lost or outdated surfaces); a lost device (a driver reset; the
//! script's `lose-device` destroys it) recreated on the same window, with the backend when it
//! was on that device, the session drawing what it holds again; the title showing the
//! session's state. What the user controls and the script live in `controls` and `script`.

/// Returns a [`WindowError::Stopped`] with a formatted message.
macro_rules! fail {
    ($($arg:tt)*) => {
        return Err(WindowError::Stopped(format!($($arg)*)))
    };
}

mod events;
mod frame;
mod lifecycle;
mod surface;

use super::controls::{Controls, ViewState, WindowSize};
use super::script::Script;
use super::soft::SoftDisplay;
use super::{Context, Result, WindowError};
use crate::backend::{AccumulationBackend, BackendChoice, GpuContext};
use crate::session::SessionOptions;
use crate::source::PacketSource;
use crate::FrameLoop;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};
use wavesplat_codec::format::Header;
use winit::dpi::PhysicalSize;
use winit::event_loop::EventLoop;
use winit::window::Window;

/// What opens a time series' time points for the window: `open(t, spec)` gives time point
/// `t` as a bricked session's volume and a source of its packets ranked for `spec`.
pub struct SeriesPlayback {
    /// Opens time point `t` for the view `spec`.
    #[allow(clippy::type_complexity)]
    pub open: Box<
        dyn FnMut(
            usize,
            &wavesplat_codec::view::ViewSpec,
        ) -> std::result::Result<
            (crate::session::BrickedVolume, Box<dyn PacketSource>),
            Box<dyn std::error::Error + Send + Sync>,
        >,
    >,
}

impl std::fmt::Debug for SeriesPlayback {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("SeriesPlayback")
    }
}

/// How a series played in the window.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct PlaybackFacts {
    /// Time points the playback moved to.
    pub advanced: u64,
    /// Of the time points it moved away from, those it showed converged.
    pub left_converged: u64,
    /// Time spent playing.
    pub playing: Duration,
    /// Of the moves, those to a time point drawn converged in this view before, shown from its
    /// kept image (after the first loop, every one).
    pub kept: u64,
    /// Time spent on those time points.
    pub kept_playing: Duration,
    /// Of the moves, those to a time point opened ahead while the previous one rested.
    pub opened_ahead: u64,
}

/// Images of a series' converged time points in one view, shown again when playback comes
/// back to them while the view stays: after the first loop a time point costs its display only.
#[derive(Default)]
pub(super) struct TimeImages {
    /// The view they were drawn in.
    pub(super) spec: Option<wavesplat_codec::view::ViewSpec>,
    pub(super) images: std::collections::HashMap<usize, crate::Image>,
    pub(super) bytes: usize,
}

/// Most bytes of time point images kept.
pub(super) const TIME_IMAGES_BYTES: usize = 512 << 20;

impl TimeImages {
    /// The image of time point `t` in view `spec`, if kept.
    pub(super) fn get(
        &self,
        t: usize,
        spec: &wavesplat_codec::view::ViewSpec,
    ) -> Option<&crate::Image> {
        (self.spec.as_ref() == Some(spec))
            .then(|| self.images.get(&t))
            .flatten()
    }

    /// Keeps `image` as time point `t`'s in view `spec` (forgetting those of another view),
    /// within [`TIME_IMAGES_BYTES`].
    pub(super) fn keep(
        &mut self,
        t: usize,
        spec: wavesplat_codec::view::ViewSpec,
        image: crate::Image,
    ) {
        if self.spec != Some(spec) {
            self.images.clear();
            self.bytes = 0;
            self.spec = Some(spec);
        }
        let size = image.data.len() * 4;
        if self.images.contains_key(&t) || self.bytes + size > TIME_IMAGES_BYTES {
            return;
        }
        self.bytes += size;
        self.images.insert(t, image);
    }
}

/// How long a playing series waits at most for a time point to converge before it moves on
/// anyway, beyond its interval.
pub(super) const PLAYBACK_PATIENCE: Duration = Duration::from_secs(2);

/// How the window runs.
#[derive(Debug)]
pub struct WindowOptions {
    /// The largest image side (per view); the image follows the window up to this.
    pub max_image: usize,
    /// The largest image side while a drag turns or pans the view with the image made on the
    /// host ([`DEFAULT_INTERACTIVE_MAX_IMAGE`]); shown stretched to the window.
    pub interactive_max_image: usize,
    /// The accumulation backend: `Auto` takes the window's device unless it is a software one.
    pub backend: BackendChoice,
    /// The window's inner size at start, per view.
    pub window_size: (u32, u32),
    /// The render session's settings.
    pub session: SessionOptions,
    /// Where S saves screenshots.
    pub shot_dir: PathBuf,
    /// Write the image shown last here when the window closes.
    pub screenshot: Option<PathBuf>,
    /// Close after this many drawn frames.
    pub exit_after_frames: Option<u64>,
    /// Synthetic input.
    pub script: Script,
    /// The volume in words, for the title.
    pub title: String,
    /// A bricked volume's bricks (`None`: one volume), drawn as one by the session
    /// ([`crate::session::RenderSession::new_bricked`]); such a window offers single views only.
    pub bricked: Option<crate::session::BrickedVolume>,
    /// A time series: how its time points are opened (its time state is the view state's).
    pub series: Option<SeriesPlayback>,
}

/// What the window did, when it closed.
#[derive(Debug, Clone, PartialEq)]
pub struct WindowOutcome {
    /// Frames drawn.
    pub drawn: u64,
    /// Coefficients the session held at the end.
    pub coefficients_held: usize,
    /// Coefficients splatted in the last view.
    pub splatted_in_view: u64,
    /// Bytes received from the source.
    pub bytes: u64,
    /// Whether the last view had converged.
    pub converged: bool,
    /// How the last view that converged got there.
    pub last_convergence: Option<Convergence>,
    /// The frames drawn while a drag turned or panned the view, if any.
    pub dragging: Option<DragFrames>,
    /// How a time series played, if it did.
    pub playback: Option<PlaybackFacts>,
}

/// The frames drawn while a drag held the view (turning or panning it).
#[derive(Debug, Clone, PartialEq)]
pub struct DragFrames {
    /// The largest image shown meanwhile (width, height).
    pub largest_image: (usize, usize),
    /// Each frame's time (ms), in order.
    pub frame_ms: Vec<f64>,
}

impl DragFrames {
    /// Frames drawn.
    pub fn frames(&self) -> usize {
        self.frame_ms.len()
    }

    /// The `q`-quantile (0..=1) of the frame times, nearest rank.
    pub fn frame_ms_quantile(&self, q: f64) -> f64 {
        let mut t = self.frame_ms.clone();
        t.sort_by(f64::total_cmp);
        match t.len() {
            0 => 0.0,
            n => t[((q.clamp(0.0, 1.0) * (n - 1) as f64).round() as usize).min(n - 1)],
        }
    }
}

/// How a view converged: from the change that made it (a new view, a resize) to the frame that
/// drew everything held with the exact tables and the source done.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Convergence {
    /// Time from the view change to convergence.
    pub elapsed: Duration,
    /// Of that, the time the frame loop had (packet intake and splatting); the rest went to
    /// showing images and to the window's event loop.
    pub refining: Duration,
    /// Images shown meanwhile.
    pub shown: u64,
}

/// The largest image side while a drag turns or pans a view drawn on the host
/// ([`WindowOptions::interactive_max_image`]'s default).
pub const DEFAULT_INTERACTIVE_MAX_IMAGE: usize = 512;

/// Opens a window on the volume of `header`, fed by `source`, starting at `state` (its view and
/// frame budget: [`ViewState::new`]), and runs it until it is closed (or the script or
/// `exit_after_frames` ends it).
pub fn run(
    header: Header,
    source: Box<dyn PacketSource>,
    state: ViewState,
    mut options: WindowOptions,
) -> Result<WindowOutcome> {
    let script = std::mem::take(&mut options.script);
    let event_loop = EventLoop::new().context(
        "opening the display (no X11 display? set DISPLAY, or use `wavesplat render` headless)",
    )?;
    let state_point = state.time.as_ref().map_or(0, |t| t.point);
    let mut app = App {
        controls: Controls::new(state),
        view_size: PhysicalSize::new(0, 0),
        view_max_image: 0,
        script,
        options,
        pending: Some((header, source)),
        gfx: None,
        display: None,
        gpu_backend: false,
        recoveries: 0,
        frames: None,
        error: None,
        drawn: 0,
        shots: 0,
        last_title: Instant::now() - Duration::from_secs(1),
        frame_ms_avg: 0.0,
        display_ms_avg: 0.0,
        converged: false,
        last_report_idle: false,
        last_draw: Instant::now(),
        last_image: None,
        last_view_change: Instant::now(),
        view_refining: Duration::ZERO,
        view_shown: 0,
        last_convergence: None,
        rest_display_ms: None,
        dragging: None,
        last_time_switch: Instant::now(),
        playback: None,
        time_images: TimeImages::default(),
        session_point: state_point,
        cached_point: None,
        prefetched: None,
    };
    event_loop
        .run_app(&mut app)
        .context("running the window's event loop")?;
    if let Some(e) = app.error.take() {
        return Err(e);
    }
    if let (Some(path), true) = (app.options.screenshot.clone(), app.frames.is_some()) {
        app.screenshot(&path)?;
    }
    let mut outcome = WindowOutcome {
        drawn: app.drawn,
        coefficients_held: 0,
        splatted_in_view: 0,
        bytes: 0,
        converged: app.converged,
        last_convergence: app.last_convergence,
        dragging: app.dragging.take(),
        playback: app.playback,
    };
    if let Some(frames) = &app.frames {
        let stats = frames.session.stats();
        outcome.coefficients_held = stats.coefficients_held;
        outcome.splatted_in_view = stats.splatted_in_view;
        outcome.bytes = frames.source_status().bytes;
    }
    Ok(outcome)
}

/// The window, its surface and what draws to it.
struct Gfx {
    // Field order is drop order: the surfaces go before the window they draw to.
    /// Where the image is shown instead of the wgpu surface, on a software device when the
    /// image is made on the host ([`SoftDisplay`]).
    soft: Option<SoftDisplay>,
    surface: wgpu::Surface<'static>,
    config: wgpu::SurfaceConfiguration,
    blitter: wgpu::util::TextureBlitter,
    /// The texture drawn: the display pass's, or `uploaded`.
    texture: Option<(wgpu::Texture, wgpu::TextureView)>,
    /// The texture host images are uploaded to (kept while the size stays).
    uploaded: Option<wgpu::Texture>,
    ctx: Arc<GpuContext>,
    window: Arc<Window>,
}

type Frames = FrameLoop<Box<dyn AccumulationBackend>, Box<dyn PacketSource>>;

struct App {
    options: WindowOptions,
    /// The view state, what input changed since the last frame, and the state last applied.
    controls: Controls,
    /// The window size that view was made for.
    view_size: PhysicalSize<u32>,
    /// The largest image side that view was made with.
    view_max_image: usize,
    pending: Option<(Header, Box<dyn PacketSource>)>,
    gfx: Option<Gfx>,
    /// The display connection a new graphics context is made on after a lost device.
    display: Option<winit::event_loop::OwnedDisplayHandle>,
    /// Whether the session accumulates on the window's device (recreated with it).
    gpu_backend: bool,
    /// Lost devices recovered from.
    recoveries: u32,
    frames: Option<Frames>,
    script: Script,
    error: Option<WindowError>,
    drawn: u64,
    shots: u64,
    last_title: Instant,
    frame_ms_avg: f64,
    display_ms_avg: f64,
    converged: bool,
    last_report_idle: bool,
    last_draw: Instant,
    last_image: Option<(usize, usize)>,
    /// When the view last changed (a new view, a resize).
    last_view_change: Instant,
    /// Time the frame loop had since then, and images shown since then.
    view_refining: Duration,
    view_shown: u64,
    /// How the last view that converged got there.
    last_convergence: Option<Convergence>,
    /// While the view rests and refines: about how often an image is shown.
    rest_display_ms: Option<f64>,
    /// The frames drawn while a drag held the view.
    dragging: Option<DragFrames>,
    /// When the time point last changed.
    last_time_switch: Instant,
    /// How a series played.
    playback: Option<PlaybackFacts>,
    /// Converged time points' images in the current view.
    time_images: TimeImages,
    /// The time point the session draws.
    session_point: usize,
    /// The time point shown from `time_images` instead of the session's image, if one is.
    cached_point: Option<usize>,
    /// The next time point of a playing series, opened while the one shown rests converged
    /// (its source already fetching), for the session to move to without waiting.
    prefetched: Option<Prefetched>,
}

/// A time point opened ahead of being shown: for the view `spec`, its volume and source.
struct Prefetched {
    point: usize,
    spec: wavesplat_codec::view::ViewSpec,
    volume: crate::session::BrickedVolume,
    source: Box<dyn PacketSource>,
}

/// The size winit reports, as the controls take it.
fn window_size(s: PhysicalSize<u32>) -> WindowSize {
    WindowSize::new(s.width, s.height)
}

/// An error with its causes, one after the other.
fn report(e: &dyn std::error::Error) -> String {
    let mut text = e.to_string();
    let mut cause = e.source();
    while let Some(c) = cause {
        text.push_str(": ");
        text.push_str(&c.to_string());
        cause = c.source();
    }
    text
}
