//! The window's life: the window, its surface, device and render session created when the
//! application resumes, a failure that ends the event loop, and a lost graphics device
//! recreated on the same window (with the accumulation backend when it was on that device).

use super::surface::{attach_soft_display, open_display, shown_on_device};
use super::{window_size, App};
use crate::backend::{select, AccumulationBackend, BackendChoice, GpuBackend};
use crate::session::RenderSession;
use crate::window::{Context, Result, WindowError};
use crate::{CpuBackend, FrameLoop};
use std::sync::Arc;
use std::time::Instant;
use winit::dpi::PhysicalSize;
use winit::event_loop::ActiveEventLoop;
use winit::window::Window;

/// Lost graphics devices a window recreates before it gives up.
const MAX_RECOVERIES: u32 = 8;

impl App {
    pub(super) fn fail(&mut self, event_loop: &ActiveEventLoop, e: WindowError) {
        if self.error.is_none() {
            self.error = Some(e);
        }
        event_loop.exit();
    }

    /// Creates the window, its surface and device, and the render session.
    pub(super) fn init(&mut self, event_loop: &ActiveEventLoop) -> Result<()> {
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
        let session = match self.options.bricked.clone() {
            Some(bricked) => {
                RenderSession::new_bricked(bricked, spec, backend, self.options.session)
            }
            None => RenderSession::new(header, spec, backend, self.options.session),
        }
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

    /// Recreates the graphics context on the same window after the device was lost, and the
    /// accumulation backend with it when it was on that device (on the CPU backend if the GPU
    /// one cannot be had again); the session keeps what it holds and draws it again.
    pub(super) fn recover(&mut self) -> Result<()> {
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
}
