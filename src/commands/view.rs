//! `wavesplat view`: the workstation window. A winit window shows the progressive render
//! session of a volume from a `.wsp` file or a cache, driven by the same frame loop as
//! `wavesplat render`: each displayed frame drains the packets that arrived and splats what fits
//! in the frame budget, then the session's image is uploaded to a texture and blitted to the
//! window's wgpu surface. This module owns the window's state (view angles, zoom, pan, multiview,
//! depth cue, budget), the mapping of mouse and keys onto it, the title that shows the session's
//! state, surface upkeep (resize, minimise, lost or outdated surfaces) and a small input script
//! that feeds synthetic events through the same handlers as real ones (tests and demos).

use super::render::{open, Opened, ViewArgs};
use anyhow::{anyhow, bail, Context, Result};
use clap::Args;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};
use wavesplat_codec::format::Header;
use wavesplat_codec::layout::Geometry;
use wavesplat_codec::view::patient::angles_of;
use wavesplat_codec::view::{
    Camera, Cue, CueDirection, Orientation, View, ViewSpec, MAX_IMAGE_SIDE,
};
use wavesplat_viewer::backend::{
    select, AccumulationBackend, BackendChoice, GpuBackend, GpuContext,
};
use wavesplat_viewer::session::RenderSession;
use wavesplat_viewer::source::PacketSource;
use wavesplat_viewer::{CpuBackend, FrameLoop};
use winit::application::ApplicationHandler;
use winit::dpi::PhysicalSize;
use winit::event::{ElementState, MouseButton, MouseScrollDelta, WindowEvent};
use winit::event_loop::{ActiveEventLoop, ControlFlow, EventLoop};
use winit::keyboard::{Key, NamedKey};
use winit::window::{Window, WindowId};

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
    /// [shift]`, `wheel LINES`, `key K` (a letter, `+`, `-`, `[`, `]`, `esc`, `f1`),
    /// `resize WxH`, `screenshot PATH`, `signal PATH` (create the file), `await PATH` (wait
    /// until it exists), `lose-device` (destroy the graphics device, as a driver reset would
    /// lose it: the window recreates it), `quit`.
    #[arg(long)]
    pub script: Option<String>,
}

/// Runs the subcommand.
pub fn run(a: ViewWindowArgs) -> Result<()> {
    a.view.spec()?;
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
    let script = match &a.script {
        Some(s) => Script::parse(&match s.strip_prefix('@') {
            Some(path) => {
                std::fs::read_to_string(path).with_context(|| format!("reading script {path}"))?
            }
            None => s.clone(),
        })?,
        None => Script::default(),
    };
    let (header, opened, spec) = open(&a.view, None)?;
    let source: Box<dyn PacketSource> = match opened {
        Opened::File { source } => source,
        Opened::Remote { source, .. } => Box::new(source),
        Opened::Cache { source, .. } => Box::new(source),
    };
    let event_loop = EventLoop::new().context(
        "opening the display (no X11 display? set DISPLAY, or use `wavesplat render` headless)",
    )?;
    let state = ViewState::from_args(&a, &spec)?;
    let mut app = App {
        applied: state.clone(),
        view_size: PhysicalSize::new(0, 0),
        state,
        args: a,
        pending: Some((header, source)),
        gfx: None,
        display: None,
        gpu_backend: false,
        recoveries: 0,
        frames: None,
        script,
        error: None,
        drawn: 0,
        shots: 0,
        input: InputState::default(),
        dirty_view: true,
        dirty_image: true,
        last_title: Instant::now() - Duration::from_secs(1),
        frame_ms_avg: 0.0,
        display_ms_avg: 0.0,
        converged: false,
        last_report_idle: false,
        last_draw: Instant::now(),
        last_image: None,
    };
    event_loop
        .run_app(&mut app)
        .context("running the window's event loop")?;
    if let Some(e) = app.error.take() {
        return Err(e);
    }
    if let (Some(path), Some(frames)) = (&app.args.screenshot, app.frames.as_mut()) {
        let image = frames.session.image().context("reading the image")?;
        let window = app.state.display_window(&image)?;
        arrange(image, grid(app.view_size, app.state.multiview))
            .write_png(path, window)
            .with_context(|| format!("writing {}", path.display()))?;
    }
    if let Some(frames) = &app.frames {
        let stats = frames.session.stats();
        let status = frames.source_status();
        outln!(
            "view: {} frames drawn, {} coefficients held, {} splatted, {} bytes received, {}",
            app.drawn,
            stats.coefficients_held,
            stats.splatted_in_view,
            status.bytes,
            if app.converged {
                "converged"
            } else {
                "refining"
            }
        );
    }
    Ok(())
}

/// What the user controls.
#[derive(Debug, Clone, PartialEq)]
struct ViewState {
    alpha: f64,
    beta: f64,
    /// Zoom relative to the zoom that fits the volume in the window.
    zoom_factor: f64,
    /// An absolute zoom from the command line (pixels per voxel), scaled by `zoom_factor`.
    zoom_abs: Option<f64>,
    pan: [f64; 2],
    multiview: bool,
    cue_on: bool,
    cue_k: f64,
    cue_dir: CueDirection,
    budget_ms: f64,
    /// Display window width relative to the automatic one (`Image::auto_window`).
    contrast: f64,
    /// Display window centre, offset from the automatic one in units of its width.
    level: f64,
    initial: Option<Box<ViewState>>,
}

impl ViewState {
    fn from_args(a: &ViewWindowArgs, spec: &ViewSpec) -> Result<ViewState> {
        let v = &spec.view;
        // The window turns the view by its angles; a named patient view is one when the
        // volume's axes are the patient's up to a rotation about z (always for axial series).
        let (alpha, beta) = match v.orientation {
            Orientation::Angles { alpha, beta } => (alpha, beta),
            Orientation::Basis { u, v } => angles_of(u, v).with_context(|| {
                format!(
                    "--view {}: in this volume's placement the named view is not a spherical \
                     view (α, β) the window can turn; use `wavesplat render --view` for it",
                    a.view.view.as_deref().unwrap_or("?")
                )
            })?,
        };
        let (cue_k, cue_dir) = match &v.cue {
            Some(c) => (c.k, c.direction),
            None => (0.02, CueDirection::View),
        };
        let mut s = ViewState {
            alpha,
            beta,
            zoom_factor: 1.0,
            // Only a zoom given on the command line is absolute (the spec's is the fitted one).
            zoom_abs: a.view.zoom,
            pan: v.pan,
            multiview: spec.multiview,
            cue_on: v.cue.is_some(),
            cue_k,
            cue_dir,
            budget_ms: a.frame_ms,
            contrast: 1.0,
            level: 0.0,
            initial: None,
        };
        s.initial = Some(Box::new(s.clone()));
        Ok(s)
    }

    /// The display window (lo, hi) for `image`: the automatic one (`Image::auto_window`)
    /// narrowed or widened by the contrast and moved by the level; `None` while both are at
    /// their defaults.
    fn display_window(&self, image: &wavesplat_viewer::Image) -> Result<Option<(f64, f64)>> {
        if self.contrast == 1.0 && self.level == 0.0 {
            return Ok(None);
        }
        let (lo, hi) = image.resolve_window(None)?;
        let width = hi - lo;
        let centre = 0.5 * (lo + hi) + self.level * width;
        let half = 0.5 * width * self.contrast;
        Ok(Some((centre - half, centre + half)))
    }

    /// The next light direction for depth cueing: the view direction, then light from +x, +y
    /// and +z of the volume.
    fn next_cue_dir(&self) -> CueDirection {
        match self.cue_dir {
            CueDirection::View => CueDirection::Vector([1.0, 0.0, 0.0]),
            CueDirection::Vector([x, _, _]) if x > 0.5 => CueDirection::Vector([0.0, 1.0, 0.0]),
            CueDirection::Vector([_, y, _]) if y > 0.5 => CueDirection::Vector([0.0, 0.0, 1.0]),
            _ => CueDirection::View,
        }
    }

    /// The view spec for a window of `size` (physical pixels), image sides capped at `max`.
    fn spec(&self, size: PhysicalSize<u32>, max: usize, geometry: &Geometry) -> Result<ViewSpec> {
        let (w, h) = image_size(size, self.multiview, max);
        let mut view = View::new(self.alpha, self.beta, w, h).with_pan(self.pan);
        // Fitted once, to the axis view, so the scale stays while the volume turns.
        let fit = Camera::new(&View::new(0.0, 0.0, w, h), geometry)?.fitting_zoom(geometry);
        let zoom = self
            .zoom_abs
            .map_or(fit, |z| z * w as f64 / size_w(size, self.multiview));
        view = view.with_zoom((zoom * self.zoom_factor).clamp(1e-6, 1e5));
        if self.cue_on && self.cue_k > 0.0 {
            view = view.with_cue(Cue {
                k: self.cue_k,
                direction: self.cue_dir,
            });
        }
        let spec = ViewSpec {
            view,
            multiview: self.multiview,
        };
        spec.validate().context("invalid view")?;
        Ok(spec)
    }
}

/// Columns and rows of multiview's three panels in a window of `size`: a row, a column or a
/// 2×2 grid (one cell empty), whichever gives the panels the longest short side, so that the
/// views fill the window's shape (three thin strips in a square window left each volume a
/// third of its width). A tie keeps the row.
fn panel_grid(size: PhysicalSize<u32>) -> (usize, usize) {
    let (w, h) = (f64::from(size.width.max(1)), f64::from(size.height.max(1)));
    let side = |(c, r): (usize, usize)| (w / c as f64).min(h / r as f64);
    [(2, 2), (1, 3), (3, 1)]
        .into_iter()
        .max_by(|a, b| side(*a).total_cmp(&side(*b)))
        .expect("three layouts")
}

/// The panel grid of a view: one cell, or multiview's [`panel_grid`].
fn grid(size: PhysicalSize<u32>, multiview: bool) -> (usize, usize) {
    if multiview {
        panel_grid(size)
    } else {
        (1, 1)
    }
}

/// Multiview's image (three panels side by side, as the renderer makes it) laid out as `cols`
/// × `rows` panels for the window; an empty cell holds zeros (the panels' background).
fn arrange(
    image: wavesplat_viewer::Image,
    (cols, rows): (usize, usize),
) -> wavesplat_viewer::Image {
    if cols * rows == 1 || cols == 3 {
        return image;
    }
    let (pw, ph, c) = (image.width / 3, image.height, image.channels);
    let width = cols * pw;
    let mut data = vec![0.0f32; width * rows * ph * c];
    for k in 0..3 {
        let (cx, cy) = (k % cols, k / cols);
        for y in 0..ph {
            let src = (y * image.width + k * pw) * c;
            let dst = ((cy * ph + y) * width + cx * pw) * c;
            data[dst..dst + pw * c].copy_from_slice(&image.data[src..src + pw * c]);
        }
    }
    wavesplat_viewer::Image {
        width,
        height: rows * ph,
        channels: c,
        data,
    }
}

fn size_w(size: PhysicalSize<u32>, multiview: bool) -> f64 {
    let w = f64::from(size.width) / grid(size, multiview).0 as f64;
    w.max(1.0)
}

/// The image size (per view) for a window: the window's pixels per view, scaled down evenly
/// so no side exceeds `max`.
fn image_size(size: PhysicalSize<u32>, multiview: bool, max: usize) -> (usize, usize) {
    let w = size_w(size, multiview);
    let h = (f64::from(size.height) / grid(size, multiview).1 as f64).max(1.0);
    let scale = (max as f64 / w).min(max as f64 / h).min(1.0);
    (
        ((w * scale).round() as usize).clamp(1, max),
        ((h * scale).round() as usize).clamp(1, max),
    )
}

/// Wraps an angle into (−π, π].
fn wrap(a: f64) -> f64 {
    let t = std::f64::consts::TAU;
    let r = a.rem_euclid(t);
    if r > std::f64::consts::PI {
        r - t
    } else {
        r
    }
}

/// A key the window reacts to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum KeyPress {
    Char(char),
    Escape,
    Help,
}

/// One input event, from winit or from the script.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Input {
    CursorMoved(f64, f64),
    LeftButton(bool),
    Shift(bool),
    Wheel(f64),
    Key(KeyPress),
}

#[derive(Debug, Default)]
struct InputState {
    cursor: Option<(f64, f64)>,
    dragging: bool,
    shift: bool,
}

/// One script command.
#[derive(Debug, Clone, PartialEq)]
enum Command {
    Frames(u64),
    Converge,
    Inputs(Vec<Input>),
    Resize(u32, u32),
    Screenshot(PathBuf),
    Signal(PathBuf),
    Await(PathBuf),
    LoseDevice,
    Quit,
}

/// The synthetic input script.
#[derive(Debug, Default)]
struct Script {
    commands: std::collections::VecDeque<Command>,
    /// Frames drawn when the current `frames N` or `resize` started.
    waiting_since: Option<u64>,
}

fn point(s: &str) -> Result<(f64, f64)> {
    let (x, y) = s
        .split_once(',')
        .ok_or_else(|| anyhow!("expected X,Y, got {s:?}"))?;
    let p = (x.trim().parse::<f64>()?, y.trim().parse::<f64>()?);
    if !p.0.is_finite() || !p.1.is_finite() {
        bail!("coordinates must be finite, got {s:?}");
    }
    Ok(p)
}

impl Script {
    fn parse(text: &str) -> Result<Script> {
        let mut commands = std::collections::VecDeque::new();
        for raw in text.split([';', '\n']) {
            let words: Vec<&str> = raw.split_whitespace().collect();
            let Some((&verb, rest)) = words.split_first() else {
                continue;
            };
            let one = || -> Result<&str> {
                match rest {
                    [x] => Ok(x),
                    _ => bail!("script: `{verb}` takes one argument, in {raw:?}"),
                }
            };
            let c = match verb {
                "frames" => Command::Frames(one()?.parse().context("script: frames N")?),
                "converge" => Command::Converge,
                "drag" => {
                    let (from, to, shift) = match rest {
                        [a, b] => (point(a)?, point(b)?, false),
                        [a, b, m] if *m == "shift" => (point(a)?, point(b)?, true),
                        _ => bail!("script: drag X0,Y0 X1,Y1 [shift], in {raw:?}"),
                    };
                    let mut v = vec![Input::Shift(shift), Input::CursorMoved(from.0, from.1)];
                    v.push(Input::LeftButton(true));
                    for i in 1..=8 {
                        let t = i as f64 / 8.0;
                        v.push(Input::CursorMoved(
                            from.0 + t * (to.0 - from.0),
                            from.1 + t * (to.1 - from.1),
                        ));
                    }
                    v.push(Input::LeftButton(false));
                    v.push(Input::Shift(false));
                    Command::Inputs(v)
                }
                "wheel" => {
                    let l: f64 = one()?.parse().context("script: wheel LINES")?;
                    if !l.is_finite() {
                        bail!("script: wheel needs a finite number");
                    }
                    Command::Inputs(vec![Input::Wheel(l)])
                }
                "key" => {
                    let k = one()?;
                    let key = match k.to_lowercase().as_str() {
                        "esc" | "escape" => KeyPress::Escape,
                        "f1" => KeyPress::Help,
                        s if s.chars().count() == 1 => {
                            KeyPress::Char(s.chars().next().unwrap_or('?'))
                        }
                        _ => bail!("script: unknown key {k:?}"),
                    };
                    Command::Inputs(vec![Input::Key(key)])
                }
                "resize" => {
                    let s = one()?;
                    let (w, h) = s
                        .split_once('x')
                        .and_then(|(w, h)| Some((w.parse().ok()?, h.parse().ok()?)))
                        .ok_or_else(|| anyhow!("script: resize WxH, got {s:?}"))?;
                    Command::Resize(w, h)
                }
                "screenshot" => Command::Screenshot(one()?.into()),
                "signal" => Command::Signal(one()?.into()),
                "await" => Command::Await(one()?.into()),
                "quit" => Command::Quit,
                "lose-device" => Command::LoseDevice,
                _ => bail!("script: unknown command {verb:?} in {raw:?}"),
            };
            commands.push_back(c);
        }
        Ok(Script {
            commands,
            waiting_since: None,
        })
    }
}

/// The window, its surface and what draws to it.
struct Gfx {
    // Field order is drop order: the surface goes before the window it draws to.
    surface: wgpu::Surface<'static>,
    config: wgpu::SurfaceConfiguration,
    blitter: wgpu::util::TextureBlitter,
    texture: Option<(wgpu::Texture, wgpu::TextureView)>,
    ctx: Arc<GpuContext>,
    window: Arc<Window>,
}

type Frames = FrameLoop<Box<dyn AccumulationBackend>, Box<dyn PacketSource>>;

struct App {
    args: ViewWindowArgs,
    state: ViewState,
    /// The last state whose view the renderer took.
    applied: ViewState,
    /// The window size that view was made for.
    view_size: PhysicalSize<u32>,
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
    error: Option<anyhow::Error>,
    drawn: u64,
    shots: u64,
    input: InputState,
    dirty_view: bool,
    dirty_image: bool,
    last_title: Instant,
    frame_ms_avg: f64,
    display_ms_avg: f64,
    converged: bool,
    last_report_idle: bool,
    last_draw: Instant,
    last_image: Option<(usize, usize)>,
}

/// Lost graphics devices a window recreates before it gives up.
const MAX_RECOVERIES: u32 = 8;

const HELP: &str = "wavesplat view: left-drag rotates (alpha, beta); shift-drag pans; wheel zooms;
  M multiview, C depth cue on/off, [ ] cue extinction down/up, D cue light direction (view,
  +x, +y, +z), + - frame budget up/down, 1 2 display window narrower/wider, 3 4 level
  down/up, 0 automatic window/level, R reset the view, S screenshot (PNG), H or F1 this help,
  Esc or Q quit";

impl App {
    fn fail(&mut self, event_loop: &ActiveEventLoop, e: anyhow::Error) {
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
        let g = open_display(&display, window.clone())?;
        let ctx = g.ctx.clone();
        self.display = Some(display);
        let size = window.inner_size();
        let (header, source) = self
            .pending
            .take()
            .ok_or_else(|| anyhow!("the window was created twice"))?;
        let choice = match (self.args.gpu, self.args.cpu) {
            (true, _) => BackendChoice::Gpu,
            (_, true) => BackendChoice::Cpu,
            _ => BackendChoice::Auto,
        };
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
        eprintln!(
            "backend: {reason}; display on {} ({:?})",
            ctx.info().name,
            ctx.info().backend
        );
        let spec = self
            .state
            .spec(size_or_one(size), self.args.max_image, &header.geometry)?;
        let session = RenderSession::new(header, spec, backend, self.args.view.session_options())
            .context("starting the render session")?;
        let mut frames = FrameLoop::new(session, source);
        frames.set_view(spec).context("setting the view")?;
        self.frames = Some(frames);
        self.gfx = Some(g);
        self.view_size = size;
        self.dirty_view = false;
        Ok(())
    }

    fn initial_window_size(&self) -> (u32, u32) {
        let (w, h) = self
            .args
            .view
            .size
            .split_once(['x', ','])
            .and_then(|(w, h)| Some((w.trim().parse::<u32>().ok()?, h.trim().parse::<u32>().ok()?)))
            .unwrap_or((256, 256));
        let w = if self.state.multiview {
            w.saturating_mul(3)
        } else {
            w
        };
        (w.clamp(1, 8192), h.clamp(1, 8192))
    }

    /// Applies one input event (real or scripted).
    fn input(&mut self, event_loop: &ActiveEventLoop, input: Input) {
        match input {
            Input::Shift(s) => self.input.shift = s,
            Input::LeftButton(down) => self.input.dragging = down,
            Input::CursorMoved(x, y) => {
                if let (true, Some((px, py))) = (self.input.dragging, self.input.cursor) {
                    let (dx, dy) = (x - px, y - py);
                    if self.input.shift {
                        let zoom = self.current_zoom();
                        self.state.pan[0] -= dx / zoom;
                        self.state.pan[1] -= dy / zoom;
                        self.state.pan = self.state.pan.map(|p| p.clamp(-1e5, 1e5));
                    } else {
                        self.state.alpha = wrap(self.state.alpha + dx * 0.01);
                        self.state.beta = wrap(self.state.beta + dy * 0.01);
                    }
                    self.dirty_view = true;
                }
                self.input.cursor = Some((x, y));
            }
            Input::Wheel(lines) => {
                self.state.zoom_factor =
                    (self.state.zoom_factor * 1.1f64.powf(lines)).clamp(0.05, 50.0);
                self.dirty_view = true;
            }
            Input::Key(k) => self.key(event_loop, k),
        }
    }

    fn key(&mut self, event_loop: &ActiveEventLoop, k: KeyPress) {
        match k {
            KeyPress::Escape | KeyPress::Char('q') => event_loop.exit(),
            KeyPress::Help | KeyPress::Char('h') => eprintln!("{HELP}"),
            KeyPress::Char('m') => {
                self.state.multiview = !self.state.multiview;
                if self.state.multiview && self.state.cue_on {
                    self.state.cue_on = false;
                    eprintln!("multiview: depth cueing is off (the two do not combine)");
                }
                self.dirty_view = true;
            }
            KeyPress::Char('c') => {
                if self.state.multiview {
                    eprintln!("depth cueing does not combine with multiview (M leaves it)");
                } else {
                    self.state.cue_on = !self.state.cue_on;
                    self.dirty_view = true;
                }
            }
            KeyPress::Char('[') => {
                self.state.cue_k = (self.state.cue_k / 1.25).max(1e-4);
                self.dirty_view |= self.state.cue_on;
            }
            KeyPress::Char(']') => {
                self.state.cue_k = (self.state.cue_k * 1.25).min(10.0);
                self.dirty_view |= self.state.cue_on;
            }
            KeyPress::Char('d') => {
                self.state.cue_dir = self.state.next_cue_dir();
                self.dirty_view |= self.state.cue_on;
            }
            KeyPress::Char('1') => {
                self.state.contrast = (self.state.contrast * 0.8).max(1e-3);
                self.dirty_image = true;
            }
            KeyPress::Char('2') => {
                self.state.contrast = (self.state.contrast * 1.25).min(1e3);
                self.dirty_image = true;
            }
            KeyPress::Char('3') => {
                self.state.level = (self.state.level - 0.05).max(-10.0);
                self.dirty_image = true;
            }
            KeyPress::Char('4') => {
                self.state.level = (self.state.level + 0.05).min(10.0);
                self.dirty_image = true;
            }
            KeyPress::Char('0') => {
                self.state.contrast = 1.0;
                self.state.level = 0.0;
                self.dirty_image = true;
            }
            KeyPress::Char('+' | '=') => {
                self.state.budget_ms = (self.state.budget_ms * 1.25).min(1000.0);
            }
            KeyPress::Char('-' | '_') => {
                self.state.budget_ms = (self.state.budget_ms / 1.25).max(1.0);
            }
            KeyPress::Char('r') => {
                if let Some(initial) = self.state.initial.clone() {
                    self.state = *initial.clone();
                    self.state.initial = Some(initial);
                }
                self.dirty_view = true;
            }
            KeyPress::Char('s') => {
                self.shots += 1;
                let secs = std::time::SystemTime::now()
                    .duration_since(std::time::UNIX_EPOCH)
                    .map_or(0, |d| d.as_secs());
                let path = self
                    .args
                    .shot_dir
                    .join(format!("wavesplat-{secs}-{}.png", self.shots));
                match self.screenshot(&path) {
                    Ok(()) => eprintln!("screenshot: {}", path.display()),
                    Err(e) => eprintln!("screenshot failed: {e:#}"),
                }
            }
            KeyPress::Char(_) => {}
        }
        self.last_title = Instant::now() - Duration::from_secs(1);
    }

    fn screenshot(&mut self, path: &Path) -> Result<()> {
        let frames = self
            .frames
            .as_mut()
            .ok_or_else(|| anyhow!("nothing is shown yet"))?;
        let image = frames.session.image().context("reading the image")?;
        let window = self.state.display_window(&image)?;
        arrange(image, grid(self.view_size, self.state.multiview))
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
                    if !self.converged || self.dirty_view {
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
                tracing::warn!("a frame failed on a lost graphics device: {e:#}");
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
            bail!(
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
        let g = open_display(&display, window).context("recreating the graphics device")?;
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
        eprintln!("recovered: display on {}", g.ctx.info().name);
        self.gfx = Some(g);
        self.dirty_image = true;
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
        if size != self.view_size {
            self.dirty_view = true;
        }
        if self.dirty_view {
            let geometry = frames.session.header().geometry;
            let spec = match self.state.spec(size, self.args.max_image, &geometry) {
                Ok(spec) => {
                    self.applied = self.state.clone();
                    spec
                }
                Err(e) => {
                    // A view the input asked for that the renderer refuses: keep the last one.
                    eprintln!("view not changed: {e:#}");
                    self.state = self.applied.clone();
                    self.state.spec(size, self.args.max_image, &geometry)?
                }
            };
            frames.set_view(spec).context("changing the view")?;
            self.view_size = size;
            self.dirty_view = false;
            self.dirty_image = true;
            self.converged = false;
        }
        let budget_ms = (self.state.budget_ms - self.display_ms_avg).max(1.0);
        let report = frames
            .frame(Duration::from_secs_f64(budget_ms / 1e3))
            .context("rendering a frame")?;
        let status = frames.source_status();
        let idle = report.idle();
        self.converged = idle && status.done;
        if report.coefficients > 0 || report.packets > 0 {
            self.dirty_image = true;
        }
        let display_start = Instant::now();
        if self.dirty_image {
            let image = frames.session.image().context("reading the image")?;
            let window = self.state.display_window(&image)?;
            let image = arrange(image, grid(self.view_size, self.state.multiview));
            let rgba = image.to_rgba8(window).context("converting the image")?;
            let (w, h) = (image.width as u32, image.height as u32);
            if g.texture.as_ref().map(|(t, _)| (t.width(), t.height())) != Some((w, h)) {
                let t = g.ctx.device().create_texture(&wgpu::TextureDescriptor {
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
                });
                let v = t.create_view(&wgpu::TextureViewDescriptor::default());
                g.texture = Some((t, v));
            }
            if let Some((t, _)) = &g.texture {
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
            }
            self.last_image = Some((image.width, image.height));
            self.dirty_image = false;
        }
        present(g, size)?;
        let display_ms = display_start.elapsed().as_secs_f64() * 1e3;
        let frame_ms = start.elapsed().as_secs_f64() * 1e3;
        self.display_ms_avg = 0.8 * self.display_ms_avg + 0.2 * display_ms.min(1e3);
        self.frame_ms_avg = if self.drawn == 0 {
            frame_ms
        } else {
            0.9 * self.frame_ms_avg + 0.1 * frame_ms
        };
        self.drawn += 1;
        self.last_draw = Instant::now();
        if idle != self.last_report_idle || self.last_title.elapsed() > Duration::from_millis(250) {
            self.last_report_idle = idle;
            self.last_title = Instant::now();
            let stats = frames.session.stats();
            let mut state = if !status.connected {
                format!(
                    "cache unreachable, reconnecting ({})",
                    status.problem.as_deref().unwrap_or("no answer")
                )
            } else if self.converged {
                "converged".to_string()
            } else if idle {
                "waiting for data".to_string()
            } else {
                "refining".to_string()
            };
            if frames.session.memory_full() {
                // What is held stops growing here: say so rather than stall silently.
                state.push_str(", memory bound reached");
            }
            if self.recoveries > 0 {
                state.push_str(&format!(
                    ", recovered from {} lost graphics device(s)",
                    self.recoveries
                ));
            }
            let (iw, ih) = self.last_image.unwrap_or((0, 0));
            g.window.set_title(&format!(
                "wavesplat — {} — {} held, {} splatted, {} received — {:.1} ms/frame (budget {:.1}) — {}{}{}{} — {iw}x{ih}",
                self.args.view.describe(),
                stats.coefficients_held,
                stats.splatted_in_view,
                human_bytes(status.bytes),
                self.frame_ms_avg,
                self.state.budget_ms,
                state,
                if self.state.multiview { " — multiview" } else { "" },
                if self.state.cue_on {
                    let dir = match self.state.cue_dir {
                        CueDirection::View => String::new(),
                        CueDirection::Vector(v) => format!(" from {v:?}"),
                        CueDirection::Angles { alpha, beta } => {
                            format!(" from α={alpha:.2}, β={beta:.2}")
                        }
                    };
                    format!(" — cue k={:.4}{dir}", self.state.cue_k)
                } else {
                    String::new()
                },
                if self.state.contrast != 1.0 || self.state.level != 0.0 {
                    format!(
                        " — window ×{:.2}, level {:+.2}",
                        self.state.contrast, self.state.level
                    )
                } else {
                    String::new()
                },
            ));
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
        .ok_or_else(|| anyhow!("the surface offers no texture format"))?;
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
            .ok_or_else(|| anyhow!("the surface is not supported by the adapter"))?
    };
    if size.width > 0 && size.height > 0 {
        surface.configure(ctx.device(), &config);
    }
    let blitter = wgpu::util::TextureBlitter::new(ctx.device(), format);
    Ok(Gfx {
        surface,
        config,
        blitter,
        texture: None,
        ctx,
        window,
    })
}

fn size_or_one(s: PhysicalSize<u32>) -> PhysicalSize<u32> {
    PhysicalSize::new(s.width.max(1), s.height.max(1))
}

fn human_bytes(b: u64) -> String {
    match b {
        0..=9_999 => format!("{b} B"),
        10_000..=9_999_999 => format!("{:.1} kB", b as f64 / 1e3),
        _ => format!("{:.1} MB", b as f64 / 1e6),
    }
}

/// Draws the image texture over the whole surface and presents it, reconfiguring the surface
/// when it is outdated and recreating it when it is lost.
fn present(g: &mut Gfx, size: PhysicalSize<u32>) -> Result<()> {
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
        other => bail!("the window's surface failed: {other:?}"),
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
                self.dirty_view = true;
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
                if self.args.exit_after_frames.is_some_and(|n| self.drawn >= n) {
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
        let busy = !self.converged || self.dirty_view || self.dirty_image;
        let scripted = !self.script.commands.is_empty() || self.args.exit_after_frames.is_some();
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

#[cfg(test)]
mod tests {
    use super::*;

    fn state() -> ViewState {
        ViewState {
            alpha: 0.0,
            beta: 0.0,
            zoom_factor: 1.0,
            zoom_abs: None,
            pan: [0.0; 2],
            multiview: false,
            cue_on: true,
            cue_k: 0.02,
            cue_dir: CueDirection::View,
            budget_ms: 16.6,
            contrast: 1.0,
            level: 0.0,
            initial: None,
        }
    }

    fn ramp() -> wavesplat_viewer::Image {
        let mut img = wavesplat_viewer::Image::new(100, 1, 1);
        for (i, v) in img.data.iter_mut().enumerate() {
            *v = i as f32;
        }
        img
    }

    #[test]
    fn window_and_level_scale_and_move_the_automatic_window() {
        let mut s = state();
        let img = ramp();
        assert_eq!(s.display_window(&img).unwrap(), None);
        let (lo, hi) = img.resolve_window(None).unwrap();
        s.contrast = 0.5;
        let (a, b) = s.display_window(&img).unwrap().unwrap();
        assert!(((b - a) - 0.5 * (hi - lo)).abs() < 1e-9);
        assert!((0.5 * (a + b) - 0.5 * (lo + hi)).abs() < 1e-9);
        s.level = 0.1;
        let (c, d) = s.display_window(&img).unwrap().unwrap();
        assert!((0.5 * (c + d) - 0.5 * (lo + hi) - 0.1 * (hi - lo)).abs() < 1e-9);
        // A narrower window maps the same pixels to more contrast.
        let auto = img.to_rgba8(None).unwrap();
        let narrow = img.to_rgba8(Some((a, b))).unwrap();
        let spread = |px: &[u8]| px[4 * 60] as i32 - px[4 * 40] as i32;
        assert!(spread(&narrow) > spread(&auto));
    }

    #[test]
    fn the_cue_direction_cycles_through_the_axes_and_back_to_the_view() {
        let mut s = state();
        let mut seen = Vec::new();
        for _ in 0..4 {
            s.cue_dir = s.next_cue_dir();
            seen.push(s.cue_dir);
        }
        assert_eq!(
            seen,
            vec![
                CueDirection::Vector([1.0, 0.0, 0.0]),
                CueDirection::Vector([0.0, 1.0, 0.0]),
                CueDirection::Vector([0.0, 0.0, 1.0]),
                CueDirection::View
            ]
        );
        // Every direction makes a valid depth-cued view.
        let g = Geometry::new([16, 16, 16], wavesplat_codec::family::Family::Linear, 1, 0).unwrap();
        for d in seen {
            s.cue_dir = d;
            let spec = s.spec(PhysicalSize::new(64, 48), 64, &g).unwrap();
            assert_eq!(spec.view.cue.map(|c| c.direction), Some(d));
        }
    }

    #[test]
    fn multiview_panels_take_the_window_shape() {
        assert_eq!(panel_grid(PhysicalSize::new(256, 256)), (2, 2));
        assert_eq!(panel_grid(PhysicalSize::new(768, 256)), (3, 1));
        assert_eq!(panel_grid(PhysicalSize::new(200, 800)), (1, 3));
        // In a square window each panel is half the window, not a third of its width.
        assert_eq!(
            image_size(PhysicalSize::new(256, 256), true, 1024),
            (128, 128)
        );
        assert_eq!(
            image_size(PhysicalSize::new(256, 256), false, 1024),
            (256, 256)
        );
        // Three 2×1 panels (values 1, 2, 3) laid out as a 2×2 grid: the fourth cell zeros.
        let strip = wavesplat_viewer::Image {
            width: 6,
            height: 1,
            channels: 1,
            data: vec![1.0, 1.0, 2.0, 2.0, 3.0, 3.0],
        };
        let g = arrange(strip.clone(), (2, 2));
        assert_eq!((g.width, g.height), (4, 2));
        assert_eq!(g.data, vec![1.0, 1.0, 2.0, 2.0, 3.0, 3.0, 0.0, 0.0]);
        let c = arrange(strip.clone(), (1, 3));
        assert_eq!((c.width, c.height), (2, 3));
        assert_eq!(c.data, vec![1.0, 1.0, 2.0, 2.0, 3.0, 3.0]);
        assert_eq!(arrange(strip.clone(), (3, 1)).data, strip.data);
    }
}
