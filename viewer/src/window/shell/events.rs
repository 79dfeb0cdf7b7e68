//! Input to the window: winit's events (keys, mouse, resize, redraw requests) and the script's
//! commands turned into the controls' inputs and what they ask of the window (quit, help,
//! screenshots), and the event loop's pacing between frames.

use super::{report, window_size, App};
use crate::window::controls::{arrange, grid, image_size, size_w, Input, KeyPress, Reaction, HELP};
use crate::window::script::Command;
use crate::window::{Context, Result, WindowError};
use std::path::Path;
use std::time::{Duration, Instant};
use winit::application::ApplicationHandler;
use winit::dpi::PhysicalSize;
use winit::event::{ElementState, MouseButton, MouseScrollDelta, WindowEvent};
use winit::event_loop::{ActiveEventLoop, ControlFlow};
use winit::keyboard::{Key, NamedKey};
use winit::window::WindowId;

impl App {
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

    pub(super) fn screenshot(&mut self, path: &Path) -> Result<()> {
        let frames = self
            .frames
            .as_mut()
            .ok_or_else(|| WindowError::Invalid("nothing is shown yet".into()))?;
        // The image shown: a played time point's kept image, else the session's.
        let kept = self
            .cached_point
            .and_then(|t| self.time_images.get(t, frames.session.spec()).cloned());
        let image = match kept {
            Some(image) => image,
            None => frames.session.image().context("reading the image")?,
        };
        let window = Some(self.controls.state.display_window(&image));
        // At the image's size for the window, magnified back where the view was drawn
        // smaller (`--max-pixels-per-voxel`).
        let multiview = self.controls.state.multiview;
        let (w, h) = image_size(window_size(self.view_size), multiview, self.view_max_image);
        let image = crate::magnify::magnify(&image, if multiview { 3 } else { 1 }, w, h);
        arrange(image, grid(window_size(self.view_size), multiview))
            .write_png(path, window)
            .with_context(|| format!("writing {}", path.display()))
    }

    /// Window pixels per unit of spacing of the current view (for panning by the cursor):
    /// the camera's zoom scaled from its image to the window's panel, which differ where the
    /// image is drawn smaller (a drag, `--max-image`, `--max-pixels-per-voxel`).
    fn current_zoom(&self) -> f64 {
        let panel = size_w(window_size(self.view_size), self.controls.state.multiview);
        self.frames
            .as_ref()
            .and_then(|f| {
                f.session
                    .plan()
                    .cameras
                    .first()
                    .map(|c| c.zoom * panel / c.width.max(1) as f64)
            })
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
                    if !self.converged || self.controls.view_changed || self.controls.time_changed {
                        return Ok(());
                    }
                }
                Command::Played(n) => {
                    if self.playback.map_or(0, |p| p.advanced) < n {
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
                    Key::Named(NamedKey::ArrowLeft) => Some(KeyPress::Left),
                    Key::Named(NamedKey::ArrowRight) => Some(KeyPress::Right),
                    Key::Named(NamedKey::Space) => Some(KeyPress::Char(' ')),
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
        let busy = !self.converged
            || self.controls.view_changed
            || self.controls.image_changed
            || self.controls.time_changed;
        let scripted = !self.script.commands.is_empty() || self.options.exit_after_frames.is_some();
        if busy || scripted {
            g.window.request_redraw();
            event_loop.set_control_flow(ControlFlow::Poll);
        } else {
            // Converged: check back now and then for packets a view change asked for, and
            // when a playing series' interval is over.
            let mut next = self.last_draw + Duration::from_millis(100);
            if let Some(t) = self.controls.state.time.as_ref().filter(|t| t.playing) {
                next = next.min(self.last_time_switch + Duration::from_secs_f64(1.0 / t.fps));
            }
            if Instant::now() >= next {
                g.window.request_redraw();
            }
            event_loop.set_control_flow(ControlFlow::WaitUntil(next));
        }
    }
}
