//! The winit 0.30 front-end of the window: the application handler, a wgpu surface on the
//! adapter it chose (the GPU accumulation backend shares that device when it is chosen, and its
//! display pass then makes the texture drawn, so no image crosses the bus; a host image — the
//! CPU backend's, a preview's — is uploaded), blitted with `wgpu::util::TextureBlitter`; surface
//! upkeep (resize, minimise, lost or outdated surfaces); a lost device (a driver reset; the
//! script's `lose-device` destroys it) recreated on the same window, with the backend when it
//! was on that device, the session drawing what it holds again; the title showing the
//! session's state. What the user controls and the script live in `controls` and `script`.

use super::controls::{
    arrange, grid, Controls, Input, KeyPress, Reaction, TitleFacts, ViewState, WindowSize, HELP,
};
use super::script::{Command, Script};
use super::soft::SoftDisplay;
use super::{Context, Result, WindowError};
use crate::backend::{select, AccumulationBackend, BackendChoice, GpuBackend, GpuContext};
use crate::session::{RenderSession, SessionOptions};
use crate::source::PacketSource;
use crate::{CpuBackend, FrameLoop};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};
use wavesplat_codec::format::Header;
use winit::application::ApplicationHandler;
use winit::dpi::PhysicalSize;
use winit::event::{ElementState, MouseButton, MouseScrollDelta, WindowEvent};
use winit::event_loop::{ActiveEventLoop, ControlFlow, EventLoop};
use winit::keyboard::{Key, NamedKey};
use winit::window::{Window, WindowId};

/// Returns a [`WindowError::Stopped`] with a formatted message.
macro_rules! fail {
    ($($arg:tt)*) => {
        return Err(WindowError::Stopped(format!($($arg)*)))
    };
}

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

/// How long after its last change a view counts as resting (and no button is held): from
/// then on refinement gets the frame, and the image is shown less often.
const REST_AFTER: Duration = Duration::from_millis(150);
/// While the view rests, refinement runs this many times as long as showing an image takes
/// between two images shown, within [`REST_SLICE_MS`]: showing costs at most a fifth of the
/// time however large the window (on a software device a 1920×1080 image costs tens of ms),
/// and input waits at most the upper bound.
const REST_SLICE_PER_DISPLAY: f64 = 4.0;
const REST_SLICE_MS: (f64, f64) = (100.0, 250.0);

/// The refinement time between two images shown while the view rests, for a display that
/// costs `display_ms` and a frame budget of `budget_ms`.
fn rest_slice(display_ms: f64, budget_ms: f64) -> Duration {
    let ms = (REST_SLICE_PER_DISPLAY * display_ms)
        .clamp(REST_SLICE_MS.0, REST_SLICE_MS.1)
        .max(budget_ms);
    Duration::from_secs_f64(ms / 1e3)
}

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
}

/// Lost graphics devices a window recreates before it gives up.
const MAX_RECOVERIES: u32 = 8;

impl App {
    fn fail(&mut self, event_loop: &ActiveEventLoop, e: WindowError) {
        if self.error.is_none() {
            self.error = Some(e);
        }
        event_loop.exit();
    }

    /// Creates the window, its surface and device, and the render session.
    fn init(&mut self, event_loop: &ActiveEventLoop) -> Result<()> {
        let (w, h) = self.initial_window_size();
        let window = Arc::new(
            event_loop
                .create_window(
                    Window::default_attributes()
                        .with_title("wavesplat")
                        .with_inner_size(PhysicalSize::new(w, h)),
                )
                .context("creating the window")?,
        );
        let display = event_loop.owned_display_handle();
        let mut g = open_display(&display, window.clone())?;
        let ctx = g.ctx.clone();
        self.display = Some(display.clone());
        let size = window.inner_size();
        let (header, source) = self
            .pending
            .take()
            .ok_or_else(|| WindowError::Invalid("the window was created twice".into()))?;
        let choice = self.options.backend;
        // The window's device accumulates unless `--cpu` says otherwise or, by default, the
        // adapter is a software one (slower than the CPU backend).
        self.gpu_backend = match choice {
            BackendChoice::Gpu => true,
            BackendChoice::Auto => !ctx.is_software(),
            _ => false,
        };
        let (backend, reason): (Box<dyn AccumulationBackend>, String) =
            match (choice, self.gpu_backend) {
                (BackendChoice::Gpu, _) => (
                    Box::new(GpuBackend::new(ctx.clone()).context("opening the GPU backend")?),
                    "gpu backend (asked for) on the window's adapter".into(),
                ),
                (_, true) => (
                    Box::new(GpuBackend::new(ctx.clone()).context("opening the GPU backend")?),
                    format!("gpu backend: {} is a hardware adapter", ctx.info().name),
                ),
                (BackendChoice::Auto, false) => (
                    Box::new(CpuBackend::new()),
                    format!(
                        "cpu backend: the adapter ({}) is a software device, slower than the CPU backend",
                        ctx.info().name
                    ),
                ),
                _ => {
                    let s = select(choice).context("choosing the accumulation backend")?;
                    (s.backend, s.reason)
                }
            };
        attach_soft_display(&mut g, &display, self.gpu_backend);
        eprintln!(
            "backend: {reason}; {}",
            if g.soft.is_some() {
                format!(
                    "display written from the host to the window's buffer ({} is a software device; WAVESPLAT_DISPLAY=device draws through it)",
                    ctx.info().name
                )
            } else {
                format!(
                    "display on {} ({:?}), {}",
                    ctx.info().name,
                    ctx.info().backend,
                    if shown_on_device(self.gpu_backend, &g) {
                        "the image made there by the display pass"
                    } else {
                        "the image uploaded from the host"
                    }
                )
            }
        );
        let spec = self.controls.state.spec(
            window_size(size).at_least_one(),
            self.options.max_image,
            &header.geometry,
        )?;
        let session = RenderSession::new(header, spec, backend, self.options.session)
            .context("starting the render session")?;
        let mut frames = FrameLoop::new(session, source);
        frames.set_view(spec).context("setting the view")?;
        self.frames = Some(frames);
        self.gfx = Some(g);
        self.view_size = size;
        self.view_max_image = self.options.max_image;
        self.controls.view_changed = false;
        self.last_view_change = Instant::now();
        Ok(())
    }

    fn initial_window_size(&self) -> (u32, u32) {
        let (w, h) = self.options.window_size;
        let w = if self.controls.state.multiview {
            w.saturating_mul(3)
        } else {
            w
        };
        (w.clamp(1, 8192), h.clamp(1, 8192))
    }

    /// Applies one input event (real or scripted) and does what it asks of the window.
    fn input(&mut self, event_loop: &ActiveEventLoop, input: Input) {
        let zoom = self.current_zoom();
        let reaction = self.controls.apply(input, zoom);
        if matches!(input, Input::Key(_)) {
            self.last_title = Instant::now() - Duration::from_secs(1);
        }
        match reaction {
            Reaction::None => {}
            Reaction::Quit => event_loop.exit(),
            Reaction::Help => eprintln!("{HELP}"),
            Reaction::Note(note) => eprintln!("{note}"),
            Reaction::Screenshot => {
                self.shots += 1;
                let secs = std::time::SystemTime::now()
                    .duration_since(std::time::UNIX_EPOCH)
                    .map_or(0, |d| d.as_secs());
                let path = self
                    .options
                    .shot_dir
                    .join(format!("wavesplat-{secs}-{}.png", self.shots));
                match self.screenshot(&path) {
                    Ok(()) => eprintln!("screenshot: {}", path.display()),
                    Err(e) => eprintln!("screenshot failed: {}", report(&e)),
                }
            }
        }
    }

    fn screenshot(&mut self, path: &Path) -> Result<()> {
        let frames = self
            .frames
            .as_mut()
            .ok_or_else(|| WindowError::Invalid("nothing is shown yet".into()))?;
        let image = frames.session.image().context("reading the image")?;
        let window = Some(self.controls.state.display_window(&image));
        arrange(
            image,
            grid(window_size(self.view_size), self.controls.state.multiview),
        )
        .write_png(path, window)
        .with_context(|| format!("writing {}", path.display()))
    }

    /// Pixels per voxel of the current view (for panning by the cursor).
    fn current_zoom(&self) -> f64 {
        self.frames
            .as_ref()
            .and_then(|f| f.session.plan().cameras.first().map(|c| c.zoom))
            .filter(|z| z.is_finite() && *z > 0.0)
            .unwrap_or(1.0)
    }

    /// Runs script commands until one has to wait for frames or a file.
    fn run_script(&mut self, event_loop: &ActiveEventLoop) -> Result<()> {
        while let Some(c) = self.script.commands.front().cloned() {
            match c {
                Command::Frames(n) => {
                    let since = *self.script.waiting_since.get_or_insert(self.drawn);
                    if self.drawn < since + n {
                        return Ok(());
                    }
                    self.script.waiting_since = None;
                }
                Command::Converge => {
                    if !self.converged || self.controls.view_changed {
                        return Ok(());
                    }
                }
                Command::Inputs(v) => {
                    for i in v {
                        self.input(event_loop, i);
                    }
                }
                Command::Resize(w, h) => {
                    // Asks once, then waits until the window has the size (a window manager may
                    // refuse: then go on after 100 frames).
                    let since = match self.script.waiting_since {
                        Some(s) => s,
                        None => {
                            if let Some(g) = &self.gfx {
                                let _ = g.window.request_inner_size(PhysicalSize::new(w, h));
                            }
                            self.script.waiting_since = Some(self.drawn);
                            self.drawn
                        }
                    };
                    if self.view_size != PhysicalSize::new(w, h) && self.drawn < since + 100 {
                        return Ok(());
                    }
                    self.script.waiting_since = None;
                }
                Command::Screenshot(p) => self.screenshot(&p)?,
                Command::Signal(p) => {
                    std::fs::write(&p, b"").with_context(|| format!("writing {}", p.display()))?
                }
                Command::Await(p) => {
                    if !p.exists() {
                        return Ok(());
                    }
                }
                Command::Quit => event_loop.exit(),
                Command::LoseDevice => {
                    if let Some(g) = &self.gfx {
                        g.ctx.lose_device();
                    }
                }
            }
            self.script.commands.pop_front();
        }
        Ok(())
    }

    /// One displayed frame; a lost graphics device (found before the frame or by its failure)
    /// is recreated and the frame skipped.
    fn redraw(&mut self) -> Result<()> {
        let lost = |app: &App| app.gfx.as_ref().is_some_and(|g| g.ctx.is_lost());
        if lost(self) {
            return self.recover();
        }
        match self.redraw_once() {
            Err(e) if lost(self) => {
                tracing::warn!("a frame failed on a lost graphics device: {}", report(&e));
                self.recover()
            }
            other => other,
        }
    }

    /// Recreates the graphics context on the same window after the device was lost, and the
    /// accumulation backend with it when it was on that device (on the CPU backend if the GPU
    /// one cannot be had again); the session keeps what it holds and draws it again.
    fn recover(&mut self) -> Result<()> {
        let (Some(old), Some(display)) = (self.gfx.take(), self.display.clone()) else {
            return Ok(());
        };
        self.recoveries += 1;
        if self.recoveries > MAX_RECOVERIES {
            fail!(
                "the graphics device ({}) was lost {} times; giving up",
                old.ctx.info().name,
                self.recoveries
            );
        }
        eprintln!(
            "graphics device lost ({}); recreating it",
            old.ctx.info().name
        );
        let window = old.window.clone();
        drop(old);
        let mut g = open_display(&display, window).context("recreating the graphics device")?;
        if let (true, Some(frames)) = (self.gpu_backend, self.frames.as_mut()) {
            let backend: Box<dyn AccumulationBackend> = match GpuBackend::new(g.ctx.clone()) {
                Ok(b) => Box::new(b),
                Err(e) => {
                    eprintln!("the GPU backend cannot be reopened ({e}); drawing on the CPU");
                    self.gpu_backend = false;
                    Box::new(CpuBackend::new())
                }
            };
            frames
                .session
                .replace_backend(backend)
                .context("drawing again on the new backend")?;
        }
        attach_soft_display(&mut g, &display, self.gpu_backend);
        eprintln!("recovered: display on {}", g.ctx.info().name);
        self.gfx = Some(g);
        self.controls.image_changed = true;
        self.converged = false;
        Ok(())
    }

    /// One displayed frame: apply a view change, run the frame loop within what the budget
    /// leaves after the display's own cost, upload the image when it changed, present it.
    fn redraw_once(&mut self) -> Result<()> {
        let (Some(g), Some(frames)) = (self.gfx.as_mut(), self.frames.as_mut()) else {
            return Ok(());
        };
        let size = g.window.inner_size();
        if size.width == 0 || size.height == 0 {
            return Ok(()); // minimised
        }
        let start = Instant::now();
        // While a drag turns or pans the view on the host, the image is made smaller and shown
        // stretched: a workstation window's image costs more than a frame to plan, splat and
        // show on two cores, every frame of a drag being a new view.
        let max_image = if self.controls.interacting() && !self.gpu_backend {
            self.options
                .max_image
                .min(self.options.interactive_max_image)
        } else {
            self.options.max_image
        };
        if size != self.view_size || max_image != self.view_max_image {
            self.controls.view_changed = true;
        }
        if self.controls.view_changed {
            let geometry = frames.session.header().geometry;
            let spec = match self
                .controls
                .state
                .spec(window_size(size), max_image, &geometry)
            {
                Ok(spec) => {
                    self.controls.applied = self.controls.state.clone();
                    spec
                }
                Err(e) => {
                    // A view the input asked for that the renderer refuses: keep the last one.
                    eprintln!("view not changed: {}", report(&e));
                    self.controls.state = self.controls.applied.clone();
                    self.controls
                        .state
                        .spec(window_size(size), max_image, &geometry)?
                }
            };
            if self.controls.interacting() {
                frames.set_view_turning(spec)
            } else {
                frames.set_view(spec)
            }
            .context("changing the view")?;
            self.view_size = size;
            self.view_max_image = max_image;
            self.controls.view_changed = false;
            self.controls.image_changed = true;
            self.converged = false;
            self.last_view_change = Instant::now();
            self.view_refining = Duration::ZERO;
            self.view_shown = 0;
        } else if !self.controls.interacting() {
            // A drag ended on the view it last asked for: its exact tables from now on.
            frames.settle();
        }
        // While the user interacts, a frame's splatting gets what the budget leaves after
        // showing the image and planning a changed view, so frames keep to the budget.
        let budget_ms = self.controls.state.budget_ms;
        let refine_start = Instant::now();
        let spent_ms = start.elapsed().as_secs_f64() * 1e3;
        let mut report = frames
            .frame(Duration::from_secs_f64(
                (budget_ms - self.display_ms_avg - spent_ms).max(1.0) / 1e3,
            ))
            .context("rendering a frame")?;
        // When the view rests, refinement gets the frame: frames of the full budget run back
        // to back for a slice several times the display's cost before the image is shown
        // again (a lower display rate while converging; the title says so), instead of a
        // frame's leftover after showing a large image on a software device.
        let resting = !self.controls.interacting() && self.last_view_change.elapsed() >= REST_AFTER;
        self.rest_display_ms = None;
        if resting && !report.idle() && report.changed_image() {
            let slice = rest_slice(self.display_ms_avg, budget_ms);
            let full = Duration::from_secs_f64(budget_ms / 1e3);
            while refine_start.elapsed() < slice {
                let r = frames.frame(full).context("rendering a frame")?;
                report = report.followed_by(&r);
                if report.idle() || !r.changed_image() {
                    // Nothing to draw until the planner or the source delivers: show what
                    // there is rather than spin.
                    break;
                }
            }
            self.rest_display_ms =
                Some(refine_start.elapsed().as_secs_f64() * 1e3 + self.display_ms_avg);
        }
        // Only the background planner at work: wait for it, up to a frame, instead of showing
        // the same preview again.
        frames
            .wait_if_only_planning(&report, Duration::from_secs_f64(budget_ms / 1e3))
            .context("waiting for the view's tables")?;
        self.view_refining += refine_start.elapsed();
        let status = frames.source_status();
        let idle = report.idle();
        let was_converged = self.converged;
        self.converged = idle && status.done;
        if self.converged && !was_converged {
            self.last_convergence = Some(Convergence {
                elapsed: self.last_view_change.elapsed(),
                refining: self.view_refining,
                shown: self.view_shown + 1,
            });
        }
        if report.changed_image() {
            self.controls.image_changed = true;
        }
        let display_start = Instant::now();
        if self.controls.image_changed {
            let panels = grid(window_size(self.view_size), self.controls.state.multiview);
            let state = &self.controls.state;
            // A host image (the CPU backend's, a preview's) is uploaded.
            let on_device = match shown_on_device(self.gpu_backend, g) {
                true => frames
                    .session
                    .device_display(|auto| state.shown_window(auto), panels)
                    .context("showing the image")?
                    .cloned(),
                false => None,
            };
            let (w, h) = match on_device {
                Some(t) => {
                    let v = t.create_view(&wgpu::TextureViewDescriptor::default());
                    let size = (t.width(), t.height());
                    g.texture = Some((t, v));
                    size
                }
                None => upload(g, frames, state, panels)?,
            };
            self.last_image = Some((w as usize, h as usize));
            self.controls.image_changed = false;
        }
        let present_start = Instant::now();
        present(g, size)?;
        let display_ms = display_start.elapsed().as_secs_f64() * 1e3;
        tracing::trace!(
            interacting = self.controls.interacting(),
            frame_ms = start.elapsed().as_secs_f64() * 1e3,
            refine_ms = display_start.duration_since(start).as_secs_f64() * 1e3,
            display_ms,
            present_ms = present_start.elapsed().as_secs_f64() * 1e3,
            coefficients = report.coefficients,
            pending = report.pending,
            "image shown"
        );
        let frame_ms = start.elapsed().as_secs_f64() * 1e3;
        self.display_ms_avg = 0.8 * self.display_ms_avg + 0.2 * display_ms.min(1e3);
        self.frame_ms_avg = if self.drawn == 0 {
            frame_ms
        } else {
            0.9 * self.frame_ms_avg + 0.1 * frame_ms
        };
        if self.controls.interacting() {
            let image = self.last_image.unwrap_or((0, 0));
            let d = self.dragging.get_or_insert(DragFrames {
                largest_image: (0, 0),
                frame_ms: Vec::new(),
            });
            if image.0 * image.1 > d.largest_image.0 * d.largest_image.1 {
                d.largest_image = image;
            }
            d.frame_ms.push(frame_ms);
        }
        self.drawn += 1;
        self.view_shown += 1;
        self.last_draw = Instant::now();
        if idle != self.last_report_idle || self.last_title.elapsed() > Duration::from_millis(250) {
            self.last_report_idle = idle;
            self.last_title = Instant::now();
            let stats = frames.session.stats();
            let (title, state) = self.controls.state.title(&TitleFacts {
                volume: &self.options.title,
                held: stats.coefficients_held,
                splatted: stats.splatted_in_view,
                bytes: status.bytes,
                frame_ms: self.frame_ms_avg,
                connected: status.connected,
                problem: status.problem.as_deref(),
                converged: self.converged,
                idle,
                memory_full: frames.session.memory_full(),
                recoveries: self.recoveries,
                image: self.last_image.unwrap_or((0, 0)),
                rest_display_ms: self.rest_display_ms,
            });
            g.window.set_title(&title);
            tracing::debug!(
                "frame {}: {:.1} ms, {} coefficients, {}",
                self.drawn,
                frame_ms,
                report.coefficients,
                state
            );
        }
        Ok(())
    }
}

/// Whether the window draws the display pass's texture: the GPU backend's image, shown where
/// it was accumulated. Not on an sRGB-only surface: the pass writes linear `Rgba8Unorm`, which
/// such a surface would brighten (host images are uploaded as sRGB there).
fn shown_on_device(gpu_backend: bool, g: &Gfx) -> bool {
    gpu_backend && !g.config.format.is_srgb()
}

/// Uploads the session's host image, arranged in `panels` and mapped through the state's
/// window, to the texture the window draws; returns its size.
fn upload(
    g: &mut Gfx,
    frames: &mut Frames,
    state: &ViewState,
    panels: (usize, usize),
) -> Result<(u32, u32)> {
    let image = frames.session.image().context("reading the image")?;
    let window = Some(state.display_window(&image));
    let image = arrange(image, panels);
    let (w, h) = (image.width as u32, image.height as u32);
    if let Some(soft) = g.soft.as_mut() {
        let words = image.to_rgb_words(window).context("converting the image")?;
        soft.set_image(words, image.width, image.height);
        return Ok((w, h));
    }
    let rgba = image.to_rgba8(window).context("converting the image")?;
    if g.uploaded.as_ref().map(|t| (t.width(), t.height())) != Some((w, h)) {
        g.uploaded = Some(g.ctx.device().create_texture(&wgpu::TextureDescriptor {
            label: Some("wavesplat view image"),
            size: wgpu::Extent3d {
                width: w,
                height: h,
                depth_or_array_layers: 1,
            },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: if g.config.format.is_srgb() {
                wgpu::TextureFormat::Rgba8UnormSrgb
            } else {
                wgpu::TextureFormat::Rgba8Unorm
            },
            usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
            view_formats: &[],
        }));
    }
    let t = g.uploaded.clone().expect("made above");
    g.ctx.queue().write_texture(
        t.as_image_copy(),
        &rgba,
        wgpu::TexelCopyBufferLayout {
            offset: 0,
            bytes_per_row: Some(4 * w),
            rows_per_image: Some(h),
        },
        t.size(),
    );
    let v = t.create_view(&wgpu::TextureViewDescriptor::default());
    g.texture = Some((t, v));
    Ok((w, h))
}

/// Opens a graphics context that can draw to `window` and configures the window's surface on
/// it (at start, and again after the device was lost).
fn open_display(
    display: &winit::event_loop::OwnedDisplayHandle,
    window: Arc<Window>,
) -> Result<Gfx> {
    let instance = wgpu::Instance::new(wgpu::InstanceDescriptor::new_with_display_handle_from_env(
        Box::new(display.clone()),
    ));
    let surface = instance
        .create_surface(window.clone())
        .context("creating a wgpu surface for the window")?;
    let adapter = pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions {
        power_preference: wgpu::PowerPreference::from_env().unwrap_or_default(),
        compatible_surface: Some(&surface),
        ..Default::default()
    }))
    .context("no graphics adapter can draw to this window (WGPU_BACKEND chooses the API)")?;
    let ctx = GpuContext::from_adapter(instance, adapter).context("opening the graphics device")?;
    let size = window.inner_size();
    let caps = surface.get_capabilities(ctx.adapter());
    let format = caps
        .formats
        .iter()
        .copied()
        .find(|f| !f.is_srgb())
        .or_else(|| caps.formats.first().copied())
        .ok_or_else(|| WindowError::Invalid("the surface offers no texture format".into()))?;
    let config = wgpu::SurfaceConfiguration {
        usage: wgpu::TextureUsages::RENDER_ATTACHMENT,
        format,
        width: size.width.max(1),
        height: size.height.max(1),
        present_mode: wgpu::PresentMode::AutoVsync,
        desired_maximum_frame_latency: 2,
        alpha_mode: caps
            .alpha_modes
            .first()
            .copied()
            .unwrap_or(wgpu::CompositeAlphaMode::Auto),
        view_formats: vec![],
        ..surface
            .get_default_config(ctx.adapter(), size.width.max(1), size.height.max(1))
            .ok_or_else(|| {
                WindowError::Invalid("the surface is not supported by the adapter".into())
            })?
    };
    if size.width > 0 && size.height > 0 {
        surface.configure(ctx.device(), &config);
    }
    let blitter = wgpu::util::TextureBlitter::new(ctx.device(), format);
    Ok(Gfx {
        soft: None,
        surface,
        config,
        blitter,
        texture: None,
        uploaded: None,
        ctx,
        window,
    })
}

/// Shows the image through a [`SoftDisplay`] when the image is made on the host and the
/// window's device is a software one (unless `WAVESPLAT_DISPLAY=device`): drawing a texture on
/// it costs more than a frame at a workstation's window size.
fn attach_soft_display(
    g: &mut Gfx,
    display: &winit::event_loop::OwnedDisplayHandle,
    gpu_backend: bool,
) {
    let forced_device = std::env::var("WAVESPLAT_DISPLAY").is_ok_and(|v| v == "device");
    if gpu_backend || forced_device || !g.ctx.is_software() {
        return;
    }
    match SoftDisplay::new(display, g.window.clone()) {
        Ok(soft) => g.soft = Some(soft),
        // The wgpu surface still shows the image, only more slowly.
        Err(e) => tracing::warn!(
            "drawing through {} instead of from the host: {}",
            g.ctx.info().name,
            report(&e)
        ),
    }
}

/// Draws the image texture over the whole surface and presents it, reconfiguring the surface
/// when it is outdated and recreating it when it is lost.
fn present(g: &mut Gfx, size: PhysicalSize<u32>) -> Result<()> {
    if let Some(soft) = g.soft.as_mut() {
        return soft.present(size);
    }
    if (g.config.width, g.config.height) != (size.width, size.height) {
        g.config.width = size.width;
        g.config.height = size.height;
        g.surface.configure(g.ctx.device(), &g.config);
    }
    let frame = match g.surface.get_current_texture() {
        wgpu::CurrentSurfaceTexture::Success(t) => t,
        wgpu::CurrentSurfaceTexture::Suboptimal(t) => {
            // Draw this one, then reconfigure for the next.
            draw(g, &t);
            g.ctx.queue().present(t);
            g.surface.configure(g.ctx.device(), &g.config);
            return Ok(());
        }
        wgpu::CurrentSurfaceTexture::Timeout | wgpu::CurrentSurfaceTexture::Occluded => {
            return Ok(());
        }
        wgpu::CurrentSurfaceTexture::Outdated => {
            g.surface.configure(g.ctx.device(), &g.config);
            return Ok(());
        }
        wgpu::CurrentSurfaceTexture::Lost => {
            tracing::warn!("window surface lost; recreating it");
            g.surface = g
                .ctx
                .instance()
                .create_surface(g.window.clone())
                .context("recreating the window's surface")?;
            g.surface.configure(g.ctx.device(), &g.config);
            return Ok(());
        }
        other => fail!("the window's surface failed: {other:?}"),
    };
    draw(g, &frame);
    g.ctx.queue().present(frame);
    Ok(())
}

fn draw(g: &Gfx, frame: &wgpu::SurfaceTexture) {
    let target = frame
        .texture
        .create_view(&wgpu::TextureViewDescriptor::default());
    let mut encoder = g
        .ctx
        .device()
        .create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("wavesplat view"),
        });
    match &g.texture {
        Some((_, source)) => g
            .blitter
            .copy(g.ctx.device(), &mut encoder, source, &target),
        None => {
            encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
                label: Some("wavesplat clear"),
                color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                    view: &target,
                    resolve_target: None,
                    depth_slice: None,
                    ops: wgpu::Operations {
                        load: wgpu::LoadOp::Clear(wgpu::Color::BLACK),
                        store: wgpu::StoreOp::Store,
                    },
                })],
                ..Default::default()
            });
        }
    }
    g.ctx.queue().submit([encoder.finish()]);
}

impl ApplicationHandler for App {
    fn resumed(&mut self, event_loop: &ActiveEventLoop) {
        if self.gfx.is_some() || self.error.is_some() {
            return;
        }
        if let Err(e) = self.init(event_loop) {
            self.fail(event_loop, e);
            return;
        }
        if let Some(g) = &self.gfx {
            g.window.request_redraw();
        }
    }

    fn window_event(&mut self, event_loop: &ActiveEventLoop, _id: WindowId, event: WindowEvent) {
        match event {
            WindowEvent::CloseRequested => event_loop.exit(),
            WindowEvent::Resized(size) if size.width > 0 && size.height > 0 => {
                self.controls.view_changed = true;
            }
            WindowEvent::ModifiersChanged(m) => {
                self.input(event_loop, Input::Shift(m.state().shift_key()))
            }
            WindowEvent::CursorMoved { position, .. } => {
                self.input(event_loop, Input::CursorMoved(position.x, position.y))
            }
            WindowEvent::MouseInput {
                state,
                button: MouseButton::Left,
                ..
            } => self.input(
                event_loop,
                Input::LeftButton(state == ElementState::Pressed),
            ),
            WindowEvent::MouseWheel { delta, .. } => {
                let lines = match delta {
                    MouseScrollDelta::LineDelta(_, y) => y as f64,
                    MouseScrollDelta::PixelDelta(p) => p.y / 40.0,
                };
                if lines.is_finite() {
                    self.input(event_loop, Input::Wheel(lines));
                }
            }
            WindowEvent::KeyboardInput { event, .. } if event.state == ElementState::Pressed => {
                let key = match &event.logical_key {
                    Key::Named(NamedKey::Escape) => Some(KeyPress::Escape),
                    Key::Named(NamedKey::F1) => Some(KeyPress::Help),
                    Key::Character(s) => s
                        .chars()
                        .next()
                        .map(|c| KeyPress::Char(c.to_ascii_lowercase())),
                    _ => None,
                };
                if let Some(k) = key {
                    self.input(event_loop, Input::Key(k));
                }
            }
            WindowEvent::RedrawRequested => {
                if let Err(e) = self.redraw() {
                    self.fail(event_loop, e);
                    return;
                }
                if self
                    .options
                    .exit_after_frames
                    .is_some_and(|n| self.drawn >= n)
                {
                    event_loop.exit();
                }
            }
            _ => {}
        }
    }

    fn about_to_wait(&mut self, event_loop: &ActiveEventLoop) {
        if self.error.is_some() || event_loop.exiting() {
            return;
        }
        if let Err(e) = self.run_script(event_loop) {
            self.fail(event_loop, e);
            return;
        }
        let Some(g) = &self.gfx else {
            return;
        };
        let busy = !self.converged || self.controls.view_changed || self.controls.image_changed;
        let scripted = !self.script.commands.is_empty() || self.options.exit_after_frames.is_some();
        if busy || scripted {
            g.window.request_redraw();
            event_loop.set_control_flow(ControlFlow::Poll);
        } else {
            // Converged: check back now and then for packets a view change asked for.
            let next = self.last_draw + Duration::from_millis(100);
            if Instant::now() >= next {
                g.window.request_redraw();
            }
            event_loop.set_control_flow(ControlFlow::WaitUntil(next));
        }
    }
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
