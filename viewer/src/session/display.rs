//! What a session shows: the accumulated image in the volume's display space (path lengths and
//! colour kept while the view stays), on the GPU backend's device without a readback, the
//! preview's last image while the exact tables catch up, and the raw coded channels.

use super::{RenderSession, SessionError};
use crate::backend::gpu::DisplayOptions;
use crate::backend::AccumulationBackend;
use crate::color;
use crate::image::Image;

impl<B: AccumulationBackend> RenderSession<B> {
    /// The image so far in the volume's display space (RGB for colour volumes; views side by
    /// side).
    ///
    /// Right after a preview is replaced by the exact tables, this is the preview's last image
    /// until the exact tables have drawn as many coefficients (or everything queued).
    pub fn image(&mut self) -> Result<Image, SessionError> {
        if self.showing_preview() {
            return Ok(self.shown_preview.as_ref().expect("shown").0.clone());
        }
        let raw = self.backend.read()?;
        self.lengths_for(raw.width, raw.height);
        let lengths = self.path_lengths.as_ref().expect("made above");
        Ok(lengths.apply(&raw, &self.header)?)
    }

    /// The image so far as the GPU backend shows it on the device it accumulated on (no image
    /// crosses the bus): [`RenderSession::image`]'s values through `window` (given the
    /// automatic window, it returns the one to show), its views in `grid` panels (columns,
    /// rows) ([`crate::backend::gpu::GpuBackend::display`]). `None` when the backend accumulates on the host, or
    /// while the preview's last image is what [`RenderSession::image`] shows: show that then.
    pub fn device_display(
        &mut self,
        window: impl FnOnce((f64, f64)) -> (f64, f64),
        grid: (usize, usize),
    ) -> Result<Option<&wgpu::Texture>, SessionError> {
        if self.showing_preview() || self.backend.gpu().is_none() {
            return Ok(None);
        }
        let layout = self.plan.layout();
        self.lengths_for(layout.total_width(), layout.height);
        if self.device_colour.is_none() {
            let lengths = self.path_lengths.as_ref().expect("made above");
            self.device_colour = Some(lengths.color_map(&self.header)?);
        }
        let colour = self.device_colour.clone().flatten();
        let gpu = self.backend.gpu().expect("checked above");
        let auto = gpu.auto_window(colour.as_ref())?;
        let options = DisplayOptions {
            window: Some(window(auto)),
            colour,
            grid: Some(grid),
        };
        Ok(Some(gpu.display(&options)?))
    }

    /// Whether [`RenderSession::image`] shows the preview's last image now: until the exact
    /// tables have drawn as many coefficients as it had and none waits for its factor tables,
    /// or everything queued. (The coefficients that wait are the pieces clipped at the box's
    /// faces, the coarse levels among them: an exact image without them, however many others
    /// it holds, drew 3.6 dB where the preview showed 35.8.)
    fn showing_preview(&mut self) -> bool {
        if let Some((_, drawn)) = &self.shown_preview {
            let behind = self.stats.splatted_in_view < *drawn || !self.waiting.is_empty();
            if behind && self.pending() > 0 {
                return true;
            }
            self.shown_preview = None;
        }
        false
    }

    /// Makes `path_lengths` those of the current view for an image of `width` × `height` (kept
    /// while the view and the size stay).
    fn lengths_for(&mut self, width: usize, height: usize) {
        let (cameras, cue) = (&self.plan.cameras, self.plan.cue.as_ref());
        let kept = self
            .path_lengths
            .as_ref()
            .is_some_and(|l| l.matches(cameras, cue, width, height));
        if !kept {
            self.path_lengths = Some(color::PathLengths::new(
                &self.header,
                cameras,
                cue,
                width,
                height,
            ));
            self.device_colour = None;
        }
    }

    /// The image so far in the coded channels (what the backend accumulated).
    pub fn raw_image(&mut self) -> Result<Image, SessionError> {
        Ok(self.backend.read()?)
    }
}
