//! The one-shot renderer: [`Renderer`] plans a view ([`crate::plan`]) and sums the records with
//! an accumulation backend (the CPU one, [`crate::backend::CpuBackend`], unless given another)
//! into a fresh image. For progressive,
//! time-budgeted rendering use [`crate::session::RenderSession`], which drives the same planner
//! and any backend.
//!
//! **Multiview.** View 2 has screen axes (u₂, v₂) = (R₂u, R₂v) with R₂(x, y, z) = (−y, x, z), and
//! view 3 uses R₃(x, y, z) = (z, y, −x) (the paper's §3.1 formulas); all three use the first
//! view's footprint set through `codec::view::multiview_map` (types permuted, negated where the
//! reflected factor is an odd ψ).

use crate::backend::{AccumulationBackend, CpuBackend};
use crate::image::Image;
use crate::plan::{Placement, PlanOptions, Planner, SplatBuffers, SPLAT_BATCH};
use crate::RenderError;
use wavesplat_codec::format::packet::Coefficient;
use wavesplat_codec::layout::Geometry;
use wavesplat_codec::view::{Camera, Orientation, View, ViewSpec};

pub use crate::plan::RenderStats;

/// Renderer settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RenderOptions {
    /// Channels of the output (coefficients must have `channel < channels`).
    pub channels: usize,
    /// How footprints are placed at exact positions.
    pub placement: Placement,
    /// Subpixel phases per axis (even; position error ≤ 1/(2S) pixel); `None`: the family's
    /// default ([`crate::PlanOptions::default_subpixel`]).
    pub subpixel: Option<usize>,
    /// Largest FFT side for a footprint (S is halved until the footprint fits); `None`: the
    /// family's default ([`crate::PlanOptions::default_max_fft`]).
    pub max_fft: Option<usize>,
    /// Footprint sets kept in the planner's cache.
    pub cache_size: usize,
}

impl Default for RenderOptions {
    fn default() -> Self {
        let p = PlanOptions::default();
        RenderOptions {
            channels: 1,
            placement: p.placement,
            subpixel: p.subpixel,
            max_fft: p.max_fft,
            cache_size: p.cache_size,
        }
    }
}

impl RenderOptions {
    /// The planning part of the options.
    pub fn plan(&self) -> PlanOptions {
        PlanOptions {
            placement: self.placement,
            subpixel: self.subpixel,
            max_fft: self.max_fft,
            cache_size: self.cache_size,
            clip: true,
        }
    }
}

/// The splat renderer: its footprint planner and an accumulation backend.
pub struct Renderer {
    options: RenderOptions,
    planner: Planner,
    backend: Box<dyn AccumulationBackend>,
    /// Kept between renders, so that their pages are faulted in once.
    buffers: SplatBuffers,
}

impl std::fmt::Debug for Renderer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Renderer")
            .field("options", &self.options)
            .field("planner", &self.planner)
            .field("backend", &self.backend.name())
            .finish()
    }
}

impl Default for Renderer {
    fn default() -> Self {
        Renderer::new(RenderOptions::default())
    }
}

impl Renderer {
    /// A renderer with the given options, accumulating on the CPU.
    pub fn new(options: RenderOptions) -> Renderer {
        Renderer::with_backend(options, Box::new(CpuBackend::new()))
    }

    /// A renderer accumulating with `backend`.
    pub fn with_backend(options: RenderOptions, backend: Box<dyn AccumulationBackend>) -> Renderer {
        Renderer {
            options,
            planner: Planner::new(options.plan()),
            backend,
            buffers: SplatBuffers::default(),
        }
    }

    /// The accumulation backend's name.
    pub fn backend_name(&self) -> String {
        self.backend.name()
    }

    /// The options.
    pub fn options(&self) -> &RenderOptions {
        &self.options
    }

    /// The planner (its footprint cache).
    pub fn planner(&mut self) -> &mut Planner {
        &mut self.planner
    }

    /// Renders the coefficients for `view`, in the coded channels (before a colour transform
    /// is undone or an offset added back: [`crate::color::to_rgb_for_spec`]).
    pub fn render(
        &mut self,
        coefficients: &[Coefficient],
        geometry: &Geometry,
        view: &View,
    ) -> Result<Image, RenderError> {
        Ok(self.render_with_stats(coefficients, geometry, view)?.0)
    }

    /// Renders and reports counters.
    pub fn render_with_stats(
        &mut self,
        coefficients: &[Coefficient],
        geometry: &Geometry,
        view: &View,
    ) -> Result<(Image, RenderStats), RenderError> {
        self.render_spec(coefficients, geometry, &ViewSpec::single(*view))
    }

    /// Renders a view spec (multiview: the three images side by side).
    pub fn render_spec(
        &mut self,
        coefficients: &[Coefficient],
        geometry: &Geometry,
        spec: &ViewSpec,
    ) -> Result<(Image, RenderStats), RenderError> {
        let mut plan = self.planner.plan(geometry, spec, self.options.channels)?;
        let mut stats = RenderStats::default();
        self.backend.begin(plan.layout())?;
        plan.splat_in_batches(
            [coefficients],
            self.backend.as_mut(),
            SPLAT_BATCH,
            &mut self.buffers,
            &mut stats,
        )?;
        Ok((self.backend.read()?, stats))
    }

    /// Renders for a resolved camera (no depth cue).
    pub fn render_camera(
        &mut self,
        coefficients: &[Coefficient],
        geometry: &Geometry,
        camera: &Camera,
    ) -> Result<(Image, RenderStats), RenderError> {
        let view = View {
            orientation: Orientation::Basis {
                u: camera.u,
                v: camera.v,
            },
            width: camera.width,
            height: camera.height,
            zoom: Some(camera.zoom),
            pan: camera.pan,
            cue: None,
        };
        self.render_with_stats(coefficients, geometry, &view)
    }

    /// Three views side by side (width 3W) from one footprint set (§3.1). Depth cueing is not
    /// supported in multiview (the cue would rotate with each view).
    pub fn render_multiview(
        &mut self,
        coefficients: &[Coefficient],
        geometry: &Geometry,
        view: &View,
    ) -> Result<(Image, RenderStats), RenderError> {
        let spec = ViewSpec {
            view: *view,
            multiview: true,
        };
        self.render_spec(coefficients, geometry, &spec)
    }

    /// The three multiview images separately.
    pub fn render_multiview_views(
        &mut self,
        coefficients: &[Coefficient],
        geometry: &Geometry,
        view: &View,
    ) -> Result<(Vec<Image>, RenderStats), RenderError> {
        let (img, stats) = self.render_multiview(coefficients, geometry, view)?;
        let views = (0..3)
            .map(|k| img.crop(k * view.width, 0, view.width, view.height))
            .collect();
        Ok((views, stats))
    }
}
