//! The wavesplat renderer: X-ray images rendered directly from decoded wavelet coefficients by
//! wavelet splatting (Lippert, Gross & Kurmann, EG'97, §2.3 and §3), never expanding the volume.
//!
//! - [`footprint`]: footprints by Fourier projection-slice (rustfft), mipmapped levels, the
//!   depth-cued factor tables;
//! - [`pieces`]: the depth-cue expansion of coefficients (split at the data's light-facing faces);
//! - [`plan`]: the [`Planner`] and [`plan::ViewPlan`]: views and coefficients to splat records
//!   in a footprint atlas;
//! - [`backend`]: the [`AccumulationBackend`] trait that sums records, the CPU backend, the
//!   wgpu backend with its display pass, and [`backend::select`];
//! - [`session`]: the progressive [`RenderSession`]: packets in, splats by visible energy within
//!   a time budget, view changes, a memory bound;
//! - [`source`]: where packets come from ([`source::FileSource`], [`source::CacheSource`] over
//!   gRPC on its own thread, pulled with credit);
//! - [`frame`]: the frame loop: drain packets, splat within a frame's budget;
//! - [`color`]: images in the coded channels back to display values (RGB; an intensity
//!   volume's offset × path length);
//! - [`walk`]: scripted view paths through the frame loop, paced like a display, recorded per
//!   frame (the demo and `bench refine`);
//! - [`splat`]: the one-shot [`Renderer`] (plan + a backend, the CPU one by default);
//! - [`reference`]: the ground-truth ray caster on the reconstructed volume;
//! - [`image`]: the [`Image`] type, PNG with window/level, raw f32 output;
//! - [`magnify`]: magnified views drawn at a bounded number of pixels a voxel, magnified back.
//!
//! ```no_run
//! use wavesplat_viewer::{Renderer, RenderOptions, View};
//! # fn demo(coeffs: &[wavesplat_codec::format::packet::Coefficient],
//! #         geometry: &wavesplat_codec::layout::Geometry) -> Result<(), wavesplat_viewer::RenderError> {
//! let mut renderer = Renderer::new(RenderOptions::default());
//! let image = renderer.render(coeffs, geometry, &View::new(0.66, 0.91, 256, 256))?;
//! # let _ = image; Ok(()) }
//! ```

pub mod backend;
pub mod bricked;
pub mod color;
pub mod footprint;
pub mod frame;
pub mod image;
pub mod magnify;
pub mod open;
pub mod pieces;
pub mod plan;
pub mod reference;
pub mod remote;
pub mod series;
pub mod session;
pub mod source;
pub mod splat;
pub mod walk;
pub mod window;

pub use backend::{AccumulationBackend, BackendError, CpuBackend};
pub use frame::{FrameLoop, FrameReport, RunError, RunOutcome, RunToEnd};
pub use image::{Image, ImageError};
pub use plan::{Placement, PlanOptions, Planner};
pub use reference::{
    render_reference, render_reference_camera, spline_axis_exact, PaddedVolume, ReferenceOptions,
};
pub use session::{RenderSession, SessionError, SessionOptions};
pub use source::{CacheSource, FileSource, PacketSource, SourceStatus};
pub use splat::{RenderOptions, RenderStats, Renderer};
pub use wavesplat_codec::view::{
    Camera, Cue, CueDirection, Orientation, View, ViewError, ViewSpec,
};

use thiserror::Error;
use wavesplat_codec::layout::Band;

/// Errors of the renderer.
#[derive(Debug, Error, PartialEq)]
#[non_exhaustive]
pub enum RenderError {
    /// Invalid view.
    #[error(transparent)]
    View(#[from] ViewError),
    /// A coefficient's channel is out of range.
    #[error("coefficient channel {channel} out of range (renderer has {channels} channels)")]
    Channel {
        /// Channel of the coefficient.
        channel: u8,
        /// Channels rendered.
        channels: usize,
    },
    /// A band that does not exist in the geometry.
    #[error("band {0:?} does not exist in this geometry")]
    Band(Band),
    /// A position outside its band.
    #[error("position {pos:?} outside band {band:?}")]
    Position {
        /// Band.
        band: Band,
        /// Position.
        pos: [u32; 3],
    },
    /// A coefficient value is NaN or infinite.
    #[error("coefficient value is not finite")]
    NotFinite,
    /// Unsupported combination of options.
    #[error("unsupported: {0}")]
    Unsupported(&'static str),
    /// The accumulation backend failed.
    #[error("accumulation backend: {0}")]
    Backend(#[from] BackendError),
}
