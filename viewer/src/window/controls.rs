//! The window's state and input, independent of any windowing library: what the user controls
//! (`ViewState`: angles, zoom, pan, multiview, depth cue, frame budget, display window and
//! level), how multiview's panels fill a window of a given size, and `Controls`, which turns
//! input events (pointer, wheel, keys; from winit or from a script) into changes of that state
//! and tells the front-end what to do about them (`Reaction`). A second front-end reuses it, and
//! it is tested without a display.

use super::{Context, Result, WindowError};
use crate::Image;
use wavesplat_codec::layout::Geometry;
use wavesplat_codec::view::patient::angles_of;
use wavesplat_codec::view::{Camera, Cue, CueDirection, Orientation, View, ViewSpec};

/// A window's inner size in physical pixels.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct WindowSize {
    /// Width.
    pub width: u32,
    /// Height.
    pub height: u32,
}

impl WindowSize {
    /// A size.
    pub const fn new(width: u32, height: u32) -> WindowSize {
        WindowSize { width, height }
    }

    /// The size with no side below 1 (a minimised window).
    pub fn at_least_one(self) -> WindowSize {
        WindowSize::new(self.width.max(1), self.height.max(1))
    }
}

/// What the user controls.
#[derive(Debug, Clone, PartialEq)]
pub struct ViewState {
    pub alpha: f64,
    pub beta: f64,
    /// Zoom relative to the zoom that fits the volume in the window.
    pub zoom_factor: f64,
    /// An absolute zoom from the command line (pixels per voxel), scaled by `zoom_factor`.
    pub zoom_abs: Option<f64>,
    pub pan: [f64; 2],
    pub multiview: bool,
    pub cue_on: bool,
    pub cue_k: f64,
    pub cue_dir: CueDirection,
    pub budget_ms: f64,
    /// Display window width relative to the automatic one (`Image::auto_window`).
    pub contrast: f64,
    /// Display window centre, offset from the automatic one in units of its width.
    pub level: f64,
    /// A time series' time point and playback (`None`: one volume).
    pub time: Option<TimeState>,
    /// The most pixels a view draws across the volume's finest voxel before it is drawn
    /// smaller and shown stretched ([`crate::magnify::bounded`]); `None`: no bound.
    pub max_pixels_per_voxel: Option<f64>,
    initial: Option<Box<ViewState>>,
}

/// Where a time series is and whether it plays.
#[derive(Debug, Clone, PartialEq)]
pub struct TimeState {
    /// The time point shown.
    pub point: usize,
    /// Time points in the series.
    pub points: usize,
    /// Each time point's time in seconds, when the series has them.
    pub times: Option<Vec<f64>>,
    /// Whether it plays.
    pub playing: bool,
    /// Time points per second while it plays.
    pub fps: f64,
}

impl TimeState {
    /// The time point `step` away from the one shown, around the loop.
    fn stepped(&self, step: isize) -> usize {
        (self.point as isize + step).rem_euclid(self.points.max(1) as isize) as usize
    }

    /// The time point and its time, in words ("t 3/16, 0.120 s").
    pub fn describe(&self) -> String {
        let time = match &self.times {
            Some(t) => format!(", {:.3} s", t[self.point.min(t.len().saturating_sub(1))]),
            None => String::new(),
        };
        format!("t {}/{}{time}", self.point, self.points)
    }
}

impl ViewState {
    /// The state that shows `spec`: `zoom_abs` is a zoom the user gave (pixels per unit of
    /// spacing; `None`: the fitting zoom), `budget_ms` the frame budget, `cue_k` the extinction
    /// depth cueing starts with when the spec has none (the volume's
    /// [`Cue::default_extinction`]).
    pub fn new(
        spec: &ViewSpec,
        zoom_abs: Option<f64>,
        budget_ms: f64,
        cue_k: f64,
    ) -> Result<ViewState> {
        let v = &spec.view;
        // The window turns the view by its angles; a named patient view is one when the
        // volume's axes are the patient's up to a rotation about z (always for axial series).
        let (alpha, beta) = match v.orientation {
            Orientation::Angles { alpha, beta } => (alpha, beta),
            Orientation::Basis { u, v } => angles_of(u, v).ok_or_else(|| {
                WindowError::Invalid(
                    "in this volume's placement the named view is not a spherical view (α, β) \
                     the window can turn; use `wavesplat render --view` for it"
                        .into(),
                )
            })?,
        };
        let (cue_k, cue_dir) = match &v.cue {
            Some(c) => (c.k, c.direction),
            None => (cue_k, CueDirection::View),
        };
        let mut s = ViewState {
            alpha,
            beta,
            zoom_factor: 1.0,
            // Only a zoom given on the command line is absolute (the spec's is the fitted one).
            zoom_abs,
            pan: v.pan,
            multiview: spec.multiview,
            cue_on: v.cue.is_some(),
            cue_k,
            cue_dir,
            budget_ms,
            contrast: 1.0,
            level: 0.0,
            time: None,
            max_pixels_per_voxel: None,
            initial: None,
        };
        s.initial = Some(Box::new(s.clone()));
        Ok(s)
    }

    /// This state with views bounded to `max` pixels across the finest voxel (`None`: every
    /// pixel drawn), its reset state too.
    pub fn with_max_pixels_per_voxel(mut self, max: Option<f64>) -> ViewState {
        self.max_pixels_per_voxel = max;
        if let Some(initial) = self.initial.as_mut() {
            initial.max_pixels_per_voxel = max;
        }
        self
    }

    /// This state for a time series of `points` time points (at `times` seconds when known),
    /// showing `point`, playing at `fps` when asked to play.
    pub fn with_time(
        mut self,
        point: usize,
        points: usize,
        times: Option<Vec<f64>>,
        fps: f64,
    ) -> ViewState {
        self.time = Some(TimeState {
            point: point.min(points.saturating_sub(1)),
            points,
            times,
            playing: false,
            fps,
        });
        self.initial = Some(Box::new(ViewState {
            initial: None,
            ..self.clone()
        }));
        self
    }

    /// The display window (lo, hi) for `image`: the automatic one, from a sample of its pixels
    /// as the GPU display pass computes it ([`Image::sampled_window`]: every image shown needs
    /// one, and the selections over all pixels of a large window cost tens of ms), narrowed or
    /// widened by the contrast and moved by the level.
    pub fn display_window(&self, image: &Image) -> (f64, f64) {
        let auto = image.sampled_window();
        if self.contrast == 1.0 && self.level == 0.0 {
            return auto;
        }
        self.shown_window(auto)
    }

    /// The window shown for an image whose automatic window is `(lo, hi)`: its centre moved by
    /// the level and its width scaled by the contrast.
    pub fn shown_window(&self, (lo, hi): (f64, f64)) -> (f64, f64) {
        let width = hi - lo;
        let centre = 0.5 * (lo + hi) + self.level * width;
        let half = 0.5 * width * self.contrast;
        (centre - half, centre + half)
    }

    /// The next light direction for depth cueing: the view direction, then light from +x, +y
    /// and +z of the volume.
    pub fn next_cue_dir(&self) -> CueDirection {
        match self.cue_dir {
            CueDirection::View => CueDirection::Vector([1.0, 0.0, 0.0]),
            CueDirection::Vector([x, _, _]) if x > 0.5 => CueDirection::Vector([0.0, 1.0, 0.0]),
            CueDirection::Vector([_, y, _]) if y > 0.5 => CueDirection::Vector([0.0, 0.0, 1.0]),
            _ => CueDirection::View,
        }
    }

    /// The view spec for a window of `size` (physical pixels), image sides capped at `max`.
    pub fn spec(&self, size: WindowSize, max: usize, geometry: &Geometry) -> Result<ViewSpec> {
        let (w, h) = image_size(size, self.multiview, max);
        let mut view = View::new(self.alpha, self.beta, w, h).with_pan(self.pan);
        // Fitted once, to the axis view, so the scale stays while the volume turns.
        let fit = Camera::new(&View::new(0.0, 0.0, w, h), geometry)
            .context("invalid view")?
            .fitting_zoom(geometry);
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
        // A view magnified beyond the bound is drawn smaller; the display stretches it.
        if let Some(max) = self.max_pixels_per_voxel {
            if let Some(drawn) =
                crate::magnify::bounded(&spec, geometry, max).context("invalid view")?
            {
                return Ok(drawn);
            }
        }
        Ok(spec)
    }
}

/// Columns and rows of multiview's three panels in a window of `size`: a row, a column or a
/// 2×2 grid (one cell empty), whichever gives the panels the longest short side, so that the
/// views fill the window's shape (three thin strips in a square window left each volume a
/// third of its width). A tie keeps the row.
pub fn panel_grid(size: WindowSize) -> (usize, usize) {
    let (w, h) = (f64::from(size.width.max(1)), f64::from(size.height.max(1)));
    let side = |(c, r): (usize, usize)| (w / c as f64).min(h / r as f64);
    [(2, 2), (1, 3), (3, 1)]
        .into_iter()
        .max_by(|a, b| side(*a).total_cmp(&side(*b)))
        .expect("three layouts")
}

/// The panel grid of a view: one cell, or multiview's [`panel_grid`].
pub fn grid(size: WindowSize, multiview: bool) -> (usize, usize) {
    if multiview {
        panel_grid(size)
    } else {
        (1, 1)
    }
}

/// Multiview's image (three panels side by side, as the renderer makes it) laid out as `cols`
/// × `rows` panels for the window; an empty cell holds zeros (the panels' background).
pub fn arrange(image: Image, (cols, rows): (usize, usize)) -> Image {
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
    Image {
        width,
        height: rows * ph,
        channels: c,
        data,
    }
}

/// The width of one panel in window pixels (at least 1).
pub fn size_w(size: WindowSize, multiview: bool) -> f64 {
    let w = f64::from(size.width) / grid(size, multiview).0 as f64;
    w.max(1.0)
}

/// The image size (per view) for a window: the window's pixels per view, scaled down evenly
/// so no side exceeds `max`.
pub fn image_size(size: WindowSize, multiview: bool, max: usize) -> (usize, usize) {
    let w = size_w(size, multiview);
    let h = (f64::from(size.height) / grid(size, multiview).1 as f64).max(1.0);
    let scale = (max as f64 / w).min(max as f64 / h).min(1.0);
    (
        ((w * scale).round() as usize).clamp(1, max),
        ((h * scale).round() as usize).clamp(1, max),
    )
}

/// Wraps an angle into (−π, π].
pub fn wrap(a: f64) -> f64 {
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
pub enum KeyPress {
    /// A character key (lower case).
    Char(char),
    /// Escape.
    Escape,
    /// F1.
    Help,
    /// The left arrow (one time point back).
    Left,
    /// The right arrow (one time point on).
    Right,
}

/// One input event, from winit or from the script.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Input {
    /// The cursor moved to (x, y) in window pixels.
    CursorMoved(f64, f64),
    /// The left button went down (`true`) or up.
    LeftButton(bool),
    /// Shift went down or up.
    Shift(bool),
    /// The wheel turned by this many lines.
    Wheel(f64),
    /// A key was pressed.
    Key(KeyPress),
}

/// The pointer's state between events.
#[derive(Debug, Default)]
struct InputState {
    cursor: Option<(f64, f64)>,
    dragging: bool,
    shift: bool,
}

/// The keys, in words (H or F1 prints it).
pub const HELP: &str =
    "wavesplat view: left-drag rotates (alpha, beta); shift-drag pans; wheel zooms;
  M multiview, C depth cue on/off, [ ] cue extinction down/up, D cue light direction (view,
  +x, +y, +z), + - frame budget up/down, 1 2 display window narrower/wider, 3 4 level
  down/up, 0 automatic window/level, R reset the view, S screenshot (PNG), H or F1 this help,
  Esc or Q quit; a time series: space plays and pauses, left/right arrows (or , .) step";

/// What the front-end does after an input event.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Reaction {
    /// Nothing beyond the state change (see [`Controls::view_changed`] and
    /// [`Controls::image_changed`]).
    None,
    /// Close the window.
    Quit,
    /// Show [`HELP`].
    Help,
    /// Tell the user this.
    Note(&'static str),
    /// Save a screenshot.
    Screenshot,
}

/// The state and what input has changed since the front-end last looked.
#[derive(Debug)]
pub struct Controls {
    /// What the user controls now.
    pub state: ViewState,
    /// The last state whose view the renderer took (restored when the renderer refuses one).
    pub applied: ViewState,
    input: InputState,
    /// The view changed: the renderer needs a new view spec.
    pub view_changed: bool,
    /// Only the display (window, level) changed: the image needs converting again.
    pub image_changed: bool,
    /// The time point changed: the renderer needs the new time point's volume.
    pub time_changed: bool,
}

impl Controls {
    /// Controls starting at `state`.
    pub fn new(state: ViewState) -> Controls {
        Controls {
            applied: state.clone(),
            state,
            input: InputState::default(),
            view_changed: true,
            image_changed: true,
            time_changed: false,
        }
    }

    /// Moves a playing series to its next time point (the front-end's clock says when).
    pub fn advance_time(&mut self) {
        if let Some(t) = self.state.time.as_mut() {
            t.point = t.stepped(1);
            self.time_changed = true;
        }
    }

    /// Whether the user is in the middle of an interaction (a button held on the view): the
    /// view does not count as resting then, so frames keep to their budget.
    pub fn interacting(&self) -> bool {
        self.input.dragging
    }

    /// Applies one input event (real or scripted); `zoom` is the current view's pixels per unit
    /// of spacing (a shift-drag pans by the distance under the cursor).
    pub fn apply(&mut self, input: Input, zoom: f64) -> Reaction {
        match input {
            Input::Shift(s) => self.input.shift = s,
            Input::LeftButton(down) => self.input.dragging = down,
            Input::CursorMoved(x, y) => {
                if let (true, Some((px, py))) = (self.input.dragging, self.input.cursor) {
                    let (dx, dy) = (x - px, y - py);
                    if self.input.shift {
                        // The content follows the cursor: screen x grows with pan u's
                        // opposite, screen y (down) with pan v (`Camera::to_screen`).
                        self.state.pan[0] -= dx / zoom;
                        self.state.pan[1] += dy / zoom;
                        self.state.pan = self.state.pan.map(|p| p.clamp(-1e5, 1e5));
                    } else {
                        self.state.alpha = wrap(self.state.alpha + dx * 0.01);
                        self.state.beta = wrap(self.state.beta + dy * 0.01);
                    }
                    self.view_changed = true;
                }
                self.input.cursor = Some((x, y));
            }
            Input::Wheel(lines) => {
                self.state.zoom_factor =
                    (self.state.zoom_factor * 1.1f64.powf(lines)).clamp(0.05, 50.0);
                self.view_changed = true;
            }
            Input::Key(k) => return self.key(k),
        }
        Reaction::None
    }

    fn key(&mut self, k: KeyPress) -> Reaction {
        let s = &mut self.state;
        let step = match k {
            KeyPress::Left | KeyPress::Char(',') => Some(-1),
            KeyPress::Right | KeyPress::Char('.') => Some(1),
            _ => None,
        };
        if let (Some(step), Some(t)) = (step, s.time.as_mut()) {
            t.point = t.stepped(step);
            t.playing = false;
            self.time_changed = true;
            return Reaction::None;
        }
        match k {
            KeyPress::Char(' ') => match s.time.as_mut() {
                Some(t) => t.playing = !t.playing,
                None => return Reaction::Note("space plays a time series; this is one volume"),
            },
            KeyPress::Left | KeyPress::Right => {}
            KeyPress::Escape | KeyPress::Char('q') => return Reaction::Quit,
            KeyPress::Help | KeyPress::Char('h') => return Reaction::Help,
            KeyPress::Char('m') => {
                s.multiview = !s.multiview;
                self.view_changed = true;
                if s.multiview && s.cue_on {
                    s.cue_on = false;
                    return Reaction::Note(
                        "multiview: depth cueing is off (the two do not combine)",
                    );
                }
            }
            KeyPress::Char('c') => {
                if s.multiview {
                    return Reaction::Note(
                        "depth cueing does not combine with multiview (M leaves it)",
                    );
                }
                s.cue_on = !s.cue_on;
                self.view_changed = true;
            }
            KeyPress::Char('[') => {
                s.cue_k = (s.cue_k / 1.25).max(1e-4);
                self.view_changed |= s.cue_on;
            }
            KeyPress::Char(']') => {
                s.cue_k = (s.cue_k * 1.25).min(10.0);
                self.view_changed |= s.cue_on;
            }
            KeyPress::Char('d') => {
                s.cue_dir = s.next_cue_dir();
                self.view_changed |= s.cue_on;
            }
            KeyPress::Char('1') => {
                s.contrast = (s.contrast * 0.8).max(1e-3);
                self.image_changed = true;
            }
            KeyPress::Char('2') => {
                s.contrast = (s.contrast * 1.25).min(1e3);
                self.image_changed = true;
            }
            KeyPress::Char('3') => {
                s.level = (s.level - 0.05).max(-10.0);
                self.image_changed = true;
            }
            KeyPress::Char('4') => {
                s.level = (s.level + 0.05).min(10.0);
                self.image_changed = true;
            }
            KeyPress::Char('0') => {
                s.contrast = 1.0;
                s.level = 0.0;
                self.image_changed = true;
            }
            KeyPress::Char('+' | '=') => {
                s.budget_ms = (s.budget_ms * 1.25).min(1000.0);
            }
            KeyPress::Char('-' | '_') => {
                s.budget_ms = (s.budget_ms / 1.25).max(1.0);
            }
            KeyPress::Char('r') => {
                if let Some(initial) = s.initial.clone() {
                    // The view resets; the time point and playback stay.
                    let time = s.time.take();
                    *s = *initial.clone();
                    s.initial = Some(initial);
                    s.time = time;
                }
                self.view_changed = true;
            }
            KeyPress::Char('s') => return Reaction::Screenshot,
            KeyPress::Char(_) => {}
        }
        Reaction::None
    }
}

/// What the window's title reports besides the state the user controls.
#[derive(Debug, Clone, PartialEq)]
pub struct TitleFacts<'a> {
    /// The volume in words.
    pub volume: &'a str,
    /// Coefficients the session holds.
    pub held: usize,
    /// Coefficients splatted in this view.
    pub splatted: u64,
    /// Bytes received.
    pub bytes: u64,
    /// Average time of a displayed frame.
    pub frame_ms: f64,
    /// Whether the source reaches its server.
    pub connected: bool,
    /// The source's problem while it lasts.
    pub problem: Option<&'a str>,
    /// Whether the view has converged.
    pub converged: bool,
    /// Whether the last frame had nothing to do.
    pub idle: bool,
    /// Whether the client memory bound stops the session from holding more.
    pub memory_full: bool,
    /// Lost graphics devices recovered from.
    pub recoveries: u32,
    /// The image's size in pixels.
    pub image: (usize, usize),
    /// While the view rests and refines: about how often the image is shown (refinement gets
    /// the time between, so the display rate drops while it converges).
    pub rest_display_ms: Option<f64>,
}

/// A byte count for people: B, kB or MB.
pub fn human_bytes(b: u64) -> String {
    match b {
        0..=9_999 => format!("{b} B"),
        10_000..=9_999_999 => format!("{:.1} kB", b as f64 / 1e3),
        _ => format!("{:.1} MB", b as f64 / 1e6),
    }
}

impl ViewState {
    /// The window's title and, on its own, the session's state in words ("refining",
    /// "converged", …).
    pub fn title(&self, f: &TitleFacts) -> (String, String) {
        let mut state = if !f.connected {
            format!(
                "cache unreachable, reconnecting ({})",
                f.problem.unwrap_or("no answer")
            )
        } else if f.converged {
            "converged".to_string()
        } else if f.idle {
            "waiting for data".to_string()
        } else if let Some(ms) = f.rest_display_ms {
            format!("refining at rest, image every ~{ms:.0} ms")
        } else {
            "refining".to_string()
        };
        if f.memory_full {
            // What is held stops growing here: say so rather than stall silently.
            state.push_str(", memory bound reached");
        }
        if f.recoveries > 0 {
            state.push_str(&format!(
                ", recovered from {} lost graphics device(s)",
                f.recoveries
            ));
        }
        let cue = if self.cue_on {
            let dir = match self.cue_dir {
                CueDirection::View => String::new(),
                CueDirection::Vector(v) => format!(" from {v:?}"),
                CueDirection::Angles { alpha, beta } => format!(" from α={alpha:.2}, β={beta:.2}"),
            };
            format!(" — cue k={:.4}{dir}", self.cue_k)
        } else {
            String::new()
        };
        let window = if self.contrast != 1.0 || self.level != 0.0 {
            format!(" — window ×{:.2}, level {:+.2}", self.contrast, self.level)
        } else {
            String::new()
        };
        let (iw, ih) = f.image;
        let volume = match &self.time {
            Some(t) => format!(
                "{} — {}{}",
                f.volume,
                t.describe(),
                if t.playing { ", playing" } else { "" }
            ),
            None => f.volume.to_string(),
        };
        let title = format!(
            "wavesplat — {} — {} held, {} splatted, {} received — {:.1} ms/frame (budget {:.1}) — {}{}{}{} — {iw}x{ih}",
            volume,
            f.held,
            f.splatted,
            human_bytes(f.bytes),
            f.frame_ms,
            self.budget_ms,
            state,
            if self.multiview { " — multiview" } else { "" },
            cue,
            window,
        );
        (title, state)
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
            time: None,
            max_pixels_per_voxel: None,
            initial: None,
        }
    }

    fn ramp() -> Image {
        let mut img = Image::new(100, 1, 1);
        for (i, v) in img.data.iter_mut().enumerate() {
            *v = i as f32;
        }
        img
    }

    #[test]
    fn window_and_level_scale_and_move_the_automatic_window() {
        let mut s = state();
        let img = ramp();
        let (lo, hi) = img.resolve_window(None).unwrap();
        // A small image's window is computed from every pixel.
        assert_eq!(s.display_window(&img), (lo, hi));
        s.contrast = 0.5;
        let (a, b) = s.display_window(&img);
        assert!(((b - a) - 0.5 * (hi - lo)).abs() < 1e-9);
        assert!((0.5 * (a + b) - 0.5 * (lo + hi)).abs() < 1e-9);
        s.level = 0.1;
        let (c, d) = s.display_window(&img);
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
            let spec = s.spec(WindowSize::new(64, 48), 64, &g).unwrap();
            assert_eq!(spec.view.cue.map(|c| c.direction), Some(d));
        }
    }

    #[test]
    fn multiview_panels_take_the_window_shape() {
        assert_eq!(panel_grid(WindowSize::new(256, 256)), (2, 2));
        assert_eq!(panel_grid(WindowSize::new(768, 256)), (3, 1));
        assert_eq!(panel_grid(WindowSize::new(200, 800)), (1, 3));
        // In a square window each panel is half the window, not a third of its width.
        assert_eq!(
            image_size(WindowSize::new(256, 256), true, 1024),
            (128, 128)
        );
        assert_eq!(
            image_size(WindowSize::new(256, 256), false, 1024),
            (256, 256)
        );
        // Three 2×1 panels (values 1, 2, 3) laid out as a 2×2 grid: the fourth cell zeros.
        let strip = Image {
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

    fn controls() -> Controls {
        let mut s = state();
        s.initial = Some(Box::new(s.clone()));
        let mut c = Controls::new(s);
        c.view_changed = false;
        c.image_changed = false;
        c
    }

    #[test]
    fn a_drag_turns_the_view_and_a_shift_drag_pans_it_by_the_distance_under_the_cursor() {
        let mut c = controls();
        // Moving without the button pressed changes nothing.
        c.apply(Input::CursorMoved(10.0, 10.0), 2.0);
        c.apply(Input::CursorMoved(20.0, 10.0), 2.0);
        assert!(!c.view_changed);
        c.apply(Input::LeftButton(true), 2.0);
        c.apply(Input::CursorMoved(30.0, 15.0), 2.0);
        assert!(c.view_changed);
        assert!((c.state.alpha - 0.1).abs() < 1e-12);
        assert!((c.state.beta - 0.05).abs() < 1e-12);
        c.apply(Input::Shift(true), 2.0);
        c.apply(Input::CursorMoved(40.0, 25.0), 2.0);
        // 10 pixels at 2 pixels per unit: 5 units, the content following the cursor.
        assert_eq!(c.state.pan, [-5.0, 5.0]);
        assert!((c.state.alpha - 0.1).abs() < 1e-12);
        c.apply(Input::LeftButton(false), 2.0);
        c.apply(Input::CursorMoved(90.0, 90.0), 2.0);
        assert_eq!(c.state.pan, [-5.0, 5.0]);
    }

    #[test]
    fn keys_change_the_state_and_ask_the_front_end_for_what_only_it_can_do() {
        let mut c = controls();
        assert_eq!(
            c.apply(Input::Key(KeyPress::Char('q')), 1.0),
            Reaction::Quit
        );
        assert_eq!(c.apply(Input::Key(KeyPress::Escape), 1.0), Reaction::Quit);
        assert_eq!(c.apply(Input::Key(KeyPress::Help), 1.0), Reaction::Help);
        assert_eq!(
            c.apply(Input::Key(KeyPress::Char('s')), 1.0),
            Reaction::Screenshot
        );
        assert!(!c.view_changed && !c.image_changed);
        // Multiview turns the depth cue off and says so; C then refuses to turn it on.
        assert!(matches!(
            c.apply(Input::Key(KeyPress::Char('m')), 1.0),
            Reaction::Note(_)
        ));
        assert!(c.state.multiview && !c.state.cue_on && c.view_changed);
        assert!(matches!(
            c.apply(Input::Key(KeyPress::Char('c')), 1.0),
            Reaction::Note(_)
        ));
        assert!(!c.state.cue_on);
        // The display window changes the image, not the view.
        c.view_changed = false;
        c.apply(Input::Key(KeyPress::Char('1')), 1.0);
        assert!(c.image_changed && !c.view_changed);
        assert!((c.state.contrast - 0.8).abs() < 1e-12);
        // The budget stays within 1..=1000 ms.
        for _ in 0..100 {
            c.apply(Input::Key(KeyPress::Char('-')), 1.0);
        }
        assert_eq!(c.state.budget_ms, 1.0);
        // The wheel zooms within its bounds; R brings back the state at start.
        for _ in 0..200 {
            c.apply(Input::Wheel(3.0), 1.0);
        }
        assert_eq!(c.state.zoom_factor, 50.0);
        c.apply(Input::Key(KeyPress::Char('r')), 1.0);
        let mut start = state();
        start.initial = c.state.initial.clone();
        assert_eq!(c.state, start);
    }

    #[test]
    fn a_view_turned_past_a_half_turn_wraps_around() {
        assert!(
            (wrap(3.0 * std::f64::consts::PI / 2.0) + std::f64::consts::FRAC_PI_2).abs() < 1e-12
        );
        assert_eq!(wrap(std::f64::consts::PI), std::f64::consts::PI);
        assert!((wrap(-std::f64::consts::PI) - std::f64::consts::PI).abs() < 1e-12);
    }

    #[test]
    fn the_title_says_what_the_session_does_and_what_the_user_set() {
        let s = state();
        let facts = TitleFacts {
            volume: "head.wsp",
            held: 1200,
            splatted: 800,
            bytes: 12_345,
            frame_ms: 16.04,
            connected: true,
            problem: None,
            converged: false,
            idle: false,
            memory_full: false,
            recoveries: 0,
            image: (64, 48),
            rest_display_ms: None,
        };
        let (title, state) = s.title(&facts);
        assert_eq!(state, "refining");
        assert!(title.starts_with("wavesplat — head.wsp — 1200 held, 800 splatted, 12.3 kB received — 16.0 ms/frame (budget 16.6) — refining"), "{title}");
        assert!(
            title.contains(" — cue k=0.0200") && title.ends_with(" — 64x48"),
            "{title}"
        );
        assert!(
            !title.contains("multiview") && !title.contains("window ×"),
            "{title}"
        );
        let (_, state) = s.title(&TitleFacts {
            converged: true,
            memory_full: true,
            ..facts.clone()
        });
        assert_eq!(state, "converged, memory bound reached");
        let (_, state) = s.title(&TitleFacts {
            rest_display_ms: Some(120.4),
            ..facts.clone()
        });
        assert_eq!(state, "refining at rest, image every ~120 ms");
        let (_, state) = s.title(&TitleFacts {
            idle: true,
            recoveries: 2,
            ..facts.clone()
        });
        assert_eq!(
            state,
            "waiting for data, recovered from 2 lost graphics device(s)"
        );
        let (_, state) = s.title(&TitleFacts {
            connected: false,
            problem: Some("refused"),
            ..facts.clone()
        });
        assert_eq!(state, "cache unreachable, reconnecting (refused)");
        let mut set = s.clone();
        set.multiview = true;
        set.cue_on = false;
        set.contrast = 0.8;
        let (title, _) = set.title(&facts);
        assert!(
            title.contains(" — multiview") && title.contains(" — window ×0.80, level +0.00"),
            "{title}"
        );
        assert!(!title.contains("cue"), "{title}");
        assert_eq!(human_bytes(9_999), "9999 B");
        assert_eq!(human_bytes(25_000_000), "25.0 MB");
    }

    /// Space plays and pauses a series, the arrows (or , .) step around the loop and pause it,
    /// the clock's advance wraps, R keeps the time point; one volume says space has nothing to
    /// play; the title names the time point and its time.
    #[test]
    fn time_keys_play_pause_and_step_a_series() {
        let key = |c: &mut Controls, k| c.apply(Input::Key(k), 1.0);
        let mut one = Controls::new(state());
        assert!(matches!(
            key(&mut one, KeyPress::Char(' ')),
            Reaction::Note(_)
        ));
        assert!(!one.time_changed);
        let mut c = Controls::new(state().with_time(1, 4, Some(vec![0.0, 0.05, 0.1, 0.15]), 10.0));
        let time = |c: &Controls| c.state.time.clone().unwrap();
        key(&mut c, KeyPress::Char(' '));
        assert!(time(&c).playing && !c.time_changed);
        c.advance_time();
        c.advance_time();
        c.advance_time();
        assert_eq!(time(&c).point, 0, "the clock wraps around the loop");
        assert!(c.time_changed);
        c.time_changed = false;
        key(&mut c, KeyPress::Left);
        assert_eq!((time(&c).point, time(&c).playing), (3, false));
        assert!(c.time_changed);
        key(&mut c, KeyPress::Char('.'));
        key(&mut c, KeyPress::Right);
        assert_eq!(time(&c).point, 1);
        key(&mut c, KeyPress::Char('r'));
        assert_eq!(time(&c).point, 1, "a view reset keeps the time point");
        let facts = TitleFacts {
            volume: "cine.wsp",
            held: 0,
            splatted: 0,
            bytes: 0,
            frame_ms: 1.0,
            connected: true,
            problem: None,
            converged: true,
            idle: true,
            memory_full: false,
            recoveries: 0,
            image: (8, 8),
            rest_display_ms: None,
        };
        let (title, _) = c.state.title(&facts);
        assert!(title.contains("cine.wsp — t 1/4, 0.050 s"), "{title}");
        // Arrow keys on one volume do nothing.
        let before = one.state.clone();
        key(&mut one, KeyPress::Right);
        assert_eq!(one.state, before);
    }
}
