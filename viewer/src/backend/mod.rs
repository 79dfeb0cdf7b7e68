//! The interface between splat planning and accumulation: the [`FootprintAtlas`] (every
//! footprint phase of a view in one flat buffer, each with its offset and extent), the
//! [`SplatRecord`] (one placed, weighted phase: where, which phase, how much, which channel and
//! view) and the [`AccumulationBackend`] trait that adds records into an image. Planning
//! (`crate::plan`) produces records; a backend only sums them, so every backend (the CPU one,
//! the wgpu one in [`gpu`]) renders the same records into the same image up to float rounding.
//! [`select`] picks a backend for a [`BackendChoice`] and says why.

pub mod cpu;
pub mod gpu;

use crate::footprint::Footprint;
use crate::image::Image;
use thiserror::Error;

pub use cpu::CpuBackend;
pub use gpu::{GpuBackend, GpuContext};

/// Errors of an accumulation backend.
#[derive(Debug, Error, PartialEq)]
#[non_exhaustive]
pub enum BackendError {
    /// A record names a phase the atlas does not have.
    #[error("splat record names phase {phase} of an atlas with {phases}")]
    Phase {
        /// Phase index.
        phase: u32,
        /// Phases in the atlas.
        phases: usize,
    },
    /// A record's view or channel is outside the layout.
    #[error("splat record for view {view}, channel {channel} outside a layout of {views} view(s) and {channels} channel(s)")]
    Target {
        /// View of the record.
        view: u16,
        /// Channel of the record.
        channel: u16,
        /// Views of the layout.
        views: usize,
        /// Channels of the layout.
        channels: usize,
    },
    /// The layout is empty or too large.
    #[error("invalid image layout: {0}")]
    Layout(String),
    /// A device-side failure (GPU backends).
    #[error("device: {0}")]
    Device(String),
    /// No GPU adapter could be had (GPU backends).
    #[error("no GPU adapter: {0}")]
    NoAdapter(String),
    /// A record's weight is NaN or infinite.
    #[error("splat record {index} has a weight that is not finite")]
    NotFinite {
        /// Index of the record in its batch.
        index: usize,
    },
    /// The sums would exceed what the target can hold.
    #[error("out of range: {0}")]
    Range(String),
    /// The display pass cannot show the image as asked.
    #[error("display: {0}")]
    Display(String),
}

/// The accumulation target: `views` images of `width` × `height` side by side (multiview: 3),
/// each pixel with `channels` values.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Layout {
    /// Width of one view.
    pub width: usize,
    /// Height.
    pub height: usize,
    /// Channels per pixel.
    pub channels: usize,
    /// Views side by side (1 or 3).
    pub views: usize,
}

impl Layout {
    /// Width of the whole target.
    pub fn total_width(&self) -> usize {
        self.width * self.views
    }

    /// Checks sizes (non-zero, and small enough to index with 32 bits).
    pub fn validate(&self) -> Result<(), BackendError> {
        let pixels = (self.total_width() as u128) * (self.height as u128) * (self.channels as u128);
        if self.width == 0 || self.height == 0 || self.channels == 0 || self.views == 0 {
            return Err(BackendError::Layout(format!("{self:?} has an empty side")));
        }
        if pixels > u32::MAX as u128 {
            return Err(BackendError::Layout(format!(
                "{self:?} has {pixels} values"
            )));
        }
        Ok(())
    }
}

/// One phase of a footprint in the atlas: `rows` × `cols` samples from `offset`. Twin of
/// `PhaseRect` in `shaders/accumulate.wgsl`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
pub struct PhaseRect {
    /// First sample in [`FootprintAtlas::data`].
    pub offset: u32,
    /// Columns.
    pub cols: u32,
    /// Rows.
    pub rows: u32,
}

/// Every footprint phase of one view, flattened: what a backend reads. Append-only while the
/// view lasts (depth-cued tables are added as new factor triples appear), so a device copy can
/// be extended rather than re-uploaded; [`FootprintAtlas::generation`] changes when it is
/// replaced by a new view's atlas.
#[derive(Debug, Clone, Default)]
pub struct FootprintAtlas {
    /// Samples of every phase, row-major per phase.
    pub data: Vec<f32>,
    /// The phases.
    pub phases: Vec<PhaseRect>,
    /// Per phase, the first column and row it keeps of the whole phase
    /// ([`crate::footprint::Phase`]): a splat of it starts that many pixels right of and below
    /// where the whole phase would (host only; a backend reads the records, which carry it).
    pub origins: Vec<[u32; 2]>,
    /// Identifies the view the atlas belongs to (a new atlas gets a new value).
    pub generation: u64,
}

/// Where a footprint's phases start in the atlas and how to place it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TableRef {
    /// Index of the footprint's first phase.
    pub first_phase: u32,
    /// Subpixel phases per axis.
    pub s: usize,
    /// Centre column of the fine table.
    pub cx: usize,
    /// Centre row of the fine table.
    pub cy: usize,
    /// First phase of the x gradient (the y gradient follows S² phases later), if built.
    pub grad_first: Option<u32>,
}

/// Whether a footprint carries gradient tables (both of them).
fn has_gradient(f: &Footprint) -> bool {
    !f.grad_x.is_empty() && !f.grad_y.is_empty()
}

/// A footprint's phase tables in the order the atlas stores them: its phases, then its
/// gradient's when it has one.
fn stored_sets(f: &Footprint) -> impl Iterator<Item = &crate::footprint::Phases> {
    let sets = if has_gradient(f) { 3 } else { 1 };
    [&f.phases, &f.grad_x, &f.grad_y].into_iter().take(sets)
}

impl FootprintAtlas {
    /// An empty atlas with a fresh generation.
    pub fn new() -> FootprintAtlas {
        use std::sync::atomic::{AtomicU64, Ordering};
        static NEXT: AtomicU64 = AtomicU64::new(1);
        FootprintAtlas {
            generation: NEXT.fetch_add(1, Ordering::Relaxed),
            ..Default::default()
        }
    }

    /// Room for `footprints` to be pushed without the atlas growing (and copying) on the way.
    pub fn reserve_for<'a>(&mut self, footprints: impl IntoIterator<Item = &'a Footprint>) {
        let (mut phases, mut samples) = (0usize, 0usize);
        for set in footprints.into_iter().flat_map(stored_sets) {
            phases += set.len();
            samples += set.data.len();
        }
        self.phases.reserve(phases);
        self.origins.reserve(phases);
        self.data.reserve(samples);
    }

    /// Appends a footprint's phases (and its gradient's); returns where they are.
    pub fn push(&mut self, f: &Footprint) -> TableRef {
        let first_phase = self.phases.len() as u32;
        for set in stored_sets(f) {
            let base = self.data.len();
            self.phases.extend(set.rects.iter().map(|p| PhaseRect {
                offset: (base + p.offset) as u32,
                cols: p.cols as u32,
                rows: p.rows as u32,
            }));
            self.origins
                .extend(set.rects.iter().map(|p| [p.x0 as u32, p.y0 as u32]));
            self.data.extend_from_slice(&set.data);
        }
        TableRef {
            first_phase,
            s: f.s,
            cx: f.cx,
            cy: f.cy,
            grad_first: has_gradient(f).then_some(first_phase + f.phases.len() as u32),
        }
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        self.data.len() * 4 + self.phases.len() * std::mem::size_of::<PhaseRect>()
    }
}

/// One phase of a footprint placed on the screen with a weight: pixel (x0 + k, y0 + l) of view
/// `view` gets `value ·` sample (k, l) of the phase, in channel `channel`. Twin of `Record` in
/// `shaders/accumulate.wgsl` (which reads `channel` and `view` as one u32, channel in the low
/// half).
#[derive(Debug, Clone, Copy, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
pub struct SplatRecord {
    /// First column (relative to the view, may be negative).
    pub x0: i32,
    /// First row (may be negative).
    pub y0: i32,
    /// Phase index in the atlas.
    pub phase: u32,
    /// Weight (the coefficient, times any cue, sign or interpolation weight).
    pub value: f32,
    /// Channel.
    pub channel: u16,
    /// View (0 unless multiview).
    pub view: u16,
}

/// Sums splat records into an image. `begin` clears and sets the target, `accumulate` adds
/// records (in any number of calls: the image is their sum), `read` returns the image so far.
pub trait AccumulationBackend: Send {
    /// A short name for messages ("cpu", "gpu (lavapipe)", …).
    fn name(&self) -> String;
    /// Starts a new image (all zero) of `layout`.
    fn begin(&mut self, layout: Layout) -> Result<(), BackendError>;
    /// Adds `records`, reading footprints from `atlas`; returns the pixel updates done.
    fn accumulate(
        &mut self,
        atlas: &FootprintAtlas,
        records: &[SplatRecord],
    ) -> Result<u64, BackendError>;
    /// The image accumulated since `begin` (views side by side).
    fn read(&mut self) -> Result<Image, BackendError>;
    /// Brings whatever the backend keeps of `atlas` up to date ahead of `accumulate` (the GPU
    /// backend uploads new tables and scans their peaks here). A session calls it before it
    /// sizes and times a batch, so that a new view's upload is neither charged to the splats
    /// nor spent past the frame's deadline; `accumulate` still does it when it was not called.
    fn prepare(&mut self, atlas: &FootprintAtlas) -> Result<(), BackendError> {
        let _ = atlas;
        Ok(())
    }
    /// The GPU backend, whose image can be shown where it was accumulated
    /// ([`gpu::GpuBackend::display`]); `None` for one that accumulates on the host.
    fn gpu(&mut self) -> Option<&mut gpu::GpuBackend> {
        None
    }
}

impl<T: AccumulationBackend + ?Sized> AccumulationBackend for Box<T> {
    fn name(&self) -> String {
        (**self).name()
    }

    fn begin(&mut self, layout: Layout) -> Result<(), BackendError> {
        (**self).begin(layout)
    }

    fn accumulate(
        &mut self,
        atlas: &FootprintAtlas,
        records: &[SplatRecord],
    ) -> Result<u64, BackendError> {
        (**self).accumulate(atlas, records)
    }

    fn read(&mut self) -> Result<Image, BackendError> {
        (**self).read()
    }

    fn prepare(&mut self, atlas: &FootprintAtlas) -> Result<(), BackendError> {
        (**self).prepare(atlas)
    }

    fn gpu(&mut self) -> Option<&mut gpu::GpuBackend> {
        (**self).gpu()
    }
}

/// Checks a record against the atlas and the layout (what every backend must refuse).
pub fn check_record(
    r: &SplatRecord,
    atlas: &FootprintAtlas,
    layout: &Layout,
) -> Result<(), BackendError> {
    if r.phase as usize >= atlas.phases.len() {
        return Err(BackendError::Phase {
            phase: r.phase,
            phases: atlas.phases.len(),
        });
    }
    if r.view as usize >= layout.views || r.channel as usize >= layout.channels {
        return Err(BackendError::Target {
            view: r.view,
            channel: r.channel,
            views: layout.views,
            channels: layout.channels,
        });
    }
    Ok(())
}

/// Which accumulation backend to use.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum BackendChoice {
    /// The faster one here: the GPU backend on a hardware adapter, else the CPU backend.
    #[default]
    Auto,
    /// The CPU backend.
    Cpu,
    /// The GPU backend (an error when no adapter can be had).
    Gpu,
}

/// A backend picked by [`select`], and why it was picked.
pub struct Selected {
    /// The backend.
    pub backend: Box<dyn AccumulationBackend>,
    /// One line saying which backend and why (for the user, once).
    pub reason: String,
}

impl std::fmt::Debug for Selected {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Selected")
            .field("backend", &self.backend.name())
            .field("reason", &self.reason)
            .finish()
    }
}

/// Picks a backend. `Auto` takes the GPU backend only on a hardware adapter: a software one
/// (Mesa's lavapipe, WARP, SwiftShader) runs the same shaders on the CPU cores that the CPU
/// backend already uses well, and measured several times slower (BENCHMARKS.md, issue 12).
/// `WGPU_BACKEND`, `WGPU_ADAPTER_NAME` and `WGPU_POWER_PREF` choose the adapter as in wgpu.
pub fn select(choice: BackendChoice) -> Result<Selected, BackendError> {
    match choice {
        BackendChoice::Cpu => Ok(Selected {
            backend: Box::new(CpuBackend::new()),
            reason: "cpu backend (asked for)".into(),
        }),
        BackendChoice::Gpu => {
            let backend = GpuBackend::new(GpuContext::new()?)?;
            let reason = format!("{} (asked for)", backend.name());
            Ok(Selected {
                backend: Box::new(backend),
                reason,
            })
        }
        BackendChoice::Auto => match gpu::probe_adapter() {
            Ok(info) if info.device_type != wgpu::DeviceType::Cpu => {
                let ctx = GpuContext::new()?;
                let backend = GpuBackend::new(ctx)?;
                let reason = format!("{}: a hardware adapter", backend.name());
                Ok(Selected {
                    backend: Box::new(backend),
                    reason,
                })
            }
            Ok(info) => Ok(Selected {
                backend: Box::new(CpuBackend::new()),
                reason: format!(
                    "cpu backend: the GPU adapter ({}, {:?}) is a software device, slower than the CPU backend",
                    info.name, info.backend
                ),
            }),
            Err(e) => Ok(Selected {
                backend: Box::new(CpuBackend::new()),
                reason: format!("cpu backend: {e}"),
            }),
        },
    }
}
