//! One displayed frame: a view change applied, the frame loop run within what the budget leaves
//! after the display's own cost (longer refinement slices while the view rests), the image
//! shown on the device or uploaded, presented, and the title kept up to date.

use super::surface::{present, shown_on_device, upload, upload_image};
use super::{report, window_size, App, Convergence, DragFrames, PLAYBACK_PATIENCE};
use crate::window::controls::{grid, TitleFacts};
use crate::window::{Context, Result};
use std::time::{Duration, Instant};

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

/// How long a converged time point must have left of its interval for the next one to be
/// opened ahead: about what opening a stream over a wide-area link takes.
const PREFETCH_SLACK: Duration = Duration::from_millis(100);

impl App {
    /// One displayed frame; a lost graphics device (found before the frame or by its failure)
    /// is recreated and the frame skipped.
    pub(super) fn redraw(&mut self) -> Result<()> {
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
        // A playing series moves on once its interval is over and the time point converged
        // (or it waited PLAYBACK_PATIENCE more): each time point is shown whole.
        if let Some(t) = self.controls.state.time.as_ref().filter(|t| t.playing) {
            let interval = Duration::from_secs_f64(1.0 / t.fps);
            let waited = self.last_time_switch.elapsed();
            if waited >= interval && (self.converged || waited >= interval + PLAYBACK_PATIENCE) {
                let p = self.playback.get_or_insert_with(Default::default);
                p.left_converged += u64::from(self.converged);
                self.controls.advance_time();
            }
        }
        let time_changed = std::mem::take(&mut self.controls.time_changed);
        let wanted = self
            .controls
            .state
            .time
            .as_ref()
            .map(|t| (t.point, t.playing));
        if let (Some((point, playing)), true) = (wanted, time_changed) {
            if playing {
                let p = self.playback.get_or_insert_with(Default::default);
                p.advanced += 1;
                p.playing += self.last_time_switch.elapsed();
                if self.cached_point.is_some() {
                    // The time point left was shown from its kept image.
                    p.kept_playing += self.last_time_switch.elapsed();
                }
            }
            self.last_time_switch = Instant::now();
            self.controls.image_changed = true;
            let spec = *frames.session.spec();
            if !self.controls.view_changed && self.time_images.get(point, &spec).is_some() {
                // Drawn converged in this view before: shown again as it was.
                self.cached_point = Some(point);
                self.converged = true;
                if playing {
                    self.playback.get_or_insert_with(Default::default).kept += 1;
                }
            } else {
                self.cached_point = None;
            }
        }
        // The session draws the time point shown, unless that one is kept from before and the
        // view stays.
        if let Some((point, _)) = wanted {
            let needs_session = self.cached_point.is_none() || self.controls.view_changed;
            if needs_session && point != self.session_point {
                let series = self.options.series.as_mut().ok_or_else(|| {
                    crate::window::WindowError::Invalid("a time state without a series".into())
                })?;
                let spec = *frames.session.spec();
                let (volume, source) = match self.prefetched.take().filter(|p| p.point == point) {
                    // Opened ahead (for this view, or turned to it now).
                    Some(mut p) => {
                        if p.spec != spec {
                            p.source.set_view(&spec);
                        }
                        self.playback
                            .get_or_insert_with(Default::default)
                            .opened_ahead += 1;
                        (p.volume, p.source)
                    }
                    None => (series.open)(point, &spec).map_err(|source| {
                        crate::window::WindowError::Failed {
                            what: format!("opening time point {point}"),
                            source,
                        }
                    })?,
                };
                frames
                    .session
                    .replace_bricked_volume(volume)
                    .context("drawing the next time point")?;
                frames.source = source;
                self.session_point = point;
                self.controls.image_changed = true;
                self.converged = false;
                self.last_view_change = Instant::now();
                self.view_refining = Duration::ZERO;
                self.view_shown = 0;
            }
            if needs_session {
                self.cached_point = None;
            }
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
        if self.cached_point.is_some() {
            return self.show_kept(size, start);
        }
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
        if self.converged && self.controls.state.time.is_some() {
            let spec = *frames.session.spec();
            if self.time_images.get(self.session_point, &spec).is_none() {
                let image = frames.session.image().context("reading the image")?;
                self.time_images.keep(self.session_point, spec, image);
            }
            // Only while it rests: a time point that converged after its interval is moved
            // on from at the next frame, and opening the next one ahead would only move the
            // open (it blocks this thread) a frame earlier.
            let slack = self
                .controls
                .state
                .time
                .as_ref()
                .map_or(Duration::ZERO, |t| {
                    Duration::from_secs_f64(1.0 / t.fps)
                        .saturating_sub(self.last_time_switch.elapsed())
                });
            if slack >= PREFETCH_SLACK {
                prefetch_next(
                    self.controls.state.time.as_ref(),
                    self.cached_point.is_some(),
                    self.session_point,
                    &self.time_images,
                    &mut self.prefetched,
                    self.options.series.as_mut(),
                    &spec,
                );
            }
        }
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
        present(g, size, !self.controls.interacting())?;
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
            let (title, state) = self.controls.state.title(&TitleFacts {
                frame_ms: self.frame_ms_avg,
                converged: self.converged,
                idle,
                recoveries: self.recoveries,
                image: self.last_image.unwrap_or((0, 0)),
                rest_display_ms: self.rest_display_ms,
                ..session_facts(&self.options.title, frames, &status)
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

    /// Shows the kept image of the time point being played (`cached_point`), with no session
    /// work: the display's cost only.
    fn show_kept(&mut self, size: winit::dpi::PhysicalSize<u32>, start: Instant) -> Result<()> {
        let (Some(g), Some(frames), Some(point)) =
            (self.gfx.as_mut(), self.frames.as_ref(), self.cached_point)
        else {
            return Ok(());
        };
        let spec = *frames.session.spec();
        if self.controls.image_changed {
            let image = self
                .time_images
                .get(point, &spec)
                .cloned()
                .ok_or_else(|| crate::window::WindowError::Invalid("no kept image".into()))?;
            let panels = grid(window_size(self.view_size), self.controls.state.multiview);
            let (w, h) = upload_image(g, image, &self.controls.state, panels)?;
            self.last_image = Some((w as usize, h as usize));
            self.controls.image_changed = false;
        }
        present(g, size, !self.controls.interacting())?;
        self.converged = true;
        self.drawn += 1;
        self.view_shown += 1;
        self.last_draw = Instant::now();
        let frame_ms = start.elapsed().as_secs_f64() * 1e3;
        self.frame_ms_avg = 0.9 * self.frame_ms_avg + 0.1 * frame_ms;
        if self.last_title.elapsed() > Duration::from_millis(250) {
            self.last_title = Instant::now();
            let status = frames.source_status();
            let (title, _) = self.controls.state.title(&TitleFacts {
                frame_ms: self.frame_ms_avg,
                recoveries: self.recoveries,
                image: self.last_image.unwrap_or((0, 0)),
                ..session_facts(&self.options.title, frames, &status)
            });
            g.window.set_title(&title);
        }
        Ok(())
    }
}

/// What the title says of the session and its source (`volume` names the volume), as a
/// converged, idle view with no other facts: the caller sets those it knows.
fn session_facts<'a>(
    volume: &'a str,
    frames: &super::Frames,
    status: &'a crate::source::SourceStatus,
) -> TitleFacts<'a> {
    let stats = frames.session.stats();
    TitleFacts {
        volume,
        held: stats.coefficients_held,
        splatted: stats.splatted_in_view,
        bytes: status.bytes,
        frame_ms: 0.0,
        connected: status.connected,
        problem: status.problem.as_deref(),
        converged: true,
        idle: true,
        memory_full: frames.session.memory_full(),
        recoveries: 0,
        image: (0, 0),
        rest_display_ms: None,
    }
}

/// While a playing series rests converged on a time point the session draws (`session_point`,
/// none shown from a kept image): opens the next one (unless its image is kept for `spec`, or
/// it is open already), so that its source fetches and decodes while this one is shown and
/// the move to it waits for nothing. A time point that fails to open here is opened again
/// (and its error reported) when the series moves to it.
fn prefetch_next(
    time: Option<&crate::window::controls::TimeState>,
    shown_kept: bool,
    session_point: usize,
    time_images: &super::TimeImages,
    prefetched: &mut Option<super::Prefetched>,
    series: Option<&mut super::SeriesPlayback>,
    spec: &wavesplat_codec::view::ViewSpec,
) {
    let Some(next) = time
        .filter(|t| t.playing && t.points > 1)
        .map(|t| (t.point + 1) % t.points)
    else {
        return;
    };
    if shown_kept
        || next == session_point
        || time_images.get(next, spec).is_some()
        || prefetched
            .as_ref()
            .is_some_and(|p| p.point == next && p.spec == *spec)
    {
        return;
    }
    let Some(series) = series else {
        return;
    };
    match (series.open)(next, spec) {
        Ok((volume, source)) => {
            *prefetched = Some(super::Prefetched {
                point: next,
                spec: *spec,
                volume,
                source,
            })
        }
        Err(e) => {
            tracing::debug!(point = next, error = %e, "opening the next time point ahead failed");
            *prefetched = None;
        }
    }
}
