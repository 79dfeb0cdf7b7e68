//! The wgpu accumulation backend and its display pass. [`GpuContext`] owns the adapter, device
//! and queue (headless, or from an adapter a window chose for its surface); [`GpuBackend`] sums
//! [`SplatRecord`]s on the device and maps the sums to an RGBA8 texture for display.
//!
//! **Data flow.** The [`FootprintAtlas`] is uploaded once per generation and extended in place
//! as it grows (depth-cued tables are appended while a view lasts); the buffers double when
//! they fill. An atlas larger than the device binds at once (lavapipe binds 128 MB; a 160×120
//! multiview of a small volume needs 135 MB) is bound a window at a time, the records grouped
//! by the window their table lies in (windows of the binding limit, every half window). Records are streamed into a buffer in chunks that respect the device's binding
//! size and dispatch limits, and a compute shader (`shaders/accumulate.wgsl`) adds each
//! record's clipped footprint box into the target: a workgroup of 64 invocations takes 8
//! records, 8 invocations per record striding over its pixels.
//!
//! **Precision: integer atomics on a 64-bit fixed-point target.** Each target value is a
//! two's-complement 64-bit integer in units of 2^−e, stored as two u32 words; a splat sample
//! `value · s` is rounded to that grid (the product itself is the f32 product the CPU backend
//! forms) and added to the low word with an atomic, the carry going into the high word with a
//! second atomic (only when non-zero). Integer addition is associative, so the image is the
//! same for any order of records, any chunking and any adapter: reproducible, and no
//! `FLOAT32_BLENDABLE` or 64-bit atomics feature is needed. The exponent e is chosen from the
//! coefficients' bound: the host keeps the *mass* M = Σ |value| · max|phase| over the records
//! accumulated since `begin`, which bounds every pixel's |sum|, and sets e so that M · 2^e ≤
//! 2^(61−16): 16 bits of headroom for later batches. When a later batch would take M · 2^e
//! above 2^61, the sums are shifted right (rounded, on the host: rare) and e lowered, so
//! nothing ever overflows. The grid step is then ≈ M · 2^−45: for 10⁵–10⁶ splats about 2^−28
//! of the largest single term, below f32's own rounding of the CPU backend's running sums, so
//! GPU and CPU images agree to well above the required 50 dB (tests/gpu.rs). Float blending
//! was the alternative: as fast on a real GPU, but its result depends on the blend order and
//! format support, and it rounds like the CPU path rather than better.
//!
//! **Display.** `shaders/display.wgsl` converts the sums to floats, applies an optional 3×3
//! colour matrix and per-pixel offset (the coded values back to what the volume holds) and the
//! window/level of [`Image::write_png`] into an `Rgba8Unorm` storage texture, the views laid out
//! side by side or in a grid of panels. The automatic window takes the percentiles of
//! `write_png` on the host, from at most [`MAX_WINDOW_SAMPLES`] values the device picks out (all
//! of a smaller image), so showing a frame moves no image across the bus. A window builds its
//! [`GpuContext`] with [`GpuContext::from_adapter`] (the adapter it chose for its surface) and
//! draws the texture [`GpuBackend::display`] returns, e.g. with `wgpu::util::TextureBlitter`
//! (the bytes are the PNG's: linear, so blit to a non-sRGB view).
//!
//! **Cost.** The scatter with atomics suits a GPU. On a software adapter (lavapipe) the atomics
//! run one lane at a time, and the backend is 5–15× slower than the CPU backend on the same
//! records (BENCHMARKS.md, issue 12): [`super::select`] does not pick it there by default.
//!
//! Its parts: `context` (adapter, device and queue, and device loss), `display` (the display
//! pass: sums to an RGBA8 texture with window/level and the colour inverse); this module holds
//! the accumulation.

mod context;
mod display;

use super::{check_record, AccumulationBackend, BackendError, FootprintAtlas, Layout, SplatRecord};
use crate::image::Image;
use bytemuck::{Pod, Zeroable};
pub use context::{probe_adapter, AdapterRequest, GpuContext};
pub use display::{ColorMap, DisplayOptions, MAX_WINDOW_SAMPLES};
use display::{Display, Offsets};
use std::sync::Arc;
/// The wgpu this backend is built on (a window must use the same version).
pub use wgpu;

/// Bits of headroom left above the mass of the first batch (the mass may grow 2^16-fold
/// before the sums are rescaled).
const HEADROOM_BITS: i32 = 16;
/// Sums stay below 2^LIMIT_BITS in magnitude (two bits spare below i64's range).
const LIMIT_BITS: i32 = 61;
/// Largest target side and footprint side the shader handles (keeps its i32 sums exact).
const MAX_SIDE: usize = 1 << 24;
/// Records per workgroup (`RECORDS_PER_GROUP` in accumulate.wgsl).
const RECORDS_PER_GROUP: usize = 8;
/// Default largest chunk of records per dispatch.
const DEFAULT_CHUNK: usize = 1 << 20;
/// Exponent range of the fixed-point scale (2^e stays a normal f32).
const EXP_RANGE: i32 = 120;

/// Uniform of the accumulation pass. Twin of `Params` in `shaders/accumulate.wgsl`.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct AccumulateParams {
    width: u32,
    height: u32,
    channels: u32,
    total_width: u32,
    count: u32,
    groups_x: u32,
    scale: f32,
    atlas_base: u32,
}

/// Settings of a [`GpuBackend`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct GpuOptions {
    /// Largest number of records per dispatch (further capped by the device's limits).
    pub max_chunk: usize,
    /// `accumulate` returns only when the device has added the records (default), so a
    /// caller that times it (the session's cost estimate) sees the real cost; `false` leaves
    /// the work queued (it is waited for by `read` and the display pass).
    pub wait: bool,
    /// Largest window of the atlas bound at once, in bytes (`None`: the device's binding
    /// limit; a smaller one tests the windows on any device).
    pub max_atlas_binding: Option<u64>,
}

impl Default for GpuOptions {
    fn default() -> Self {
        GpuOptions {
            max_chunk: DEFAULT_CHUNK,
            wait: true,
            max_atlas_binding: None,
        }
    }
}

/// What is on the device of the current atlas.
#[derive(Debug)]
struct DeviceAtlas {
    generation: Option<u64>,
    data: wgpu::Buffer,
    /// Samples uploaded.
    data_len: usize,
    phases: wgpu::Buffer,
    /// Phases uploaded.
    phases_len: usize,
    /// max |sample| per phase.
    peak: Vec<f32>,
}

/// The accumulation target.
#[derive(Debug)]
struct Target {
    layout: Layout,
    sums: wgpu::Buffer,
    /// Bytes of `sums`.
    bytes: u64,
    /// Fixed-point exponent: a sum `v` means `v · 2^−e` (set by the first non-zero batch).
    exp: Option<i32>,
    /// Σ |value| · max|phase| since `begin`: bounds every pixel's |sum|.
    mass: f64,
}

/// Accumulates splat records on a wgpu device (see the module doc).
#[derive(Debug)]
pub struct GpuBackend {
    ctx: Arc<GpuContext>,
    options: GpuOptions,
    accumulate: wgpu::ComputePipeline,
    display: wgpu::ComputePipeline,
    /// The display pass's `sample` entry point (the automatic window's values).
    sample: wgpu::ComputePipeline,
    params: wgpu::Buffer,
    records: wgpu::Buffer,
    records_capacity: usize,
    atlas: DeviceAtlas,
    target: Option<Target>,
    shown: Option<Display>,
    offsets: Option<Offsets>,
    /// Bound as the display pass's offsets when a colour map has none.
    no_offsets: wgpu::Buffer,
}

fn pipeline(ctx: &GpuContext, label: &str, source: &str, entry: &str) -> wgpu::ComputePipeline {
    let module = ctx
        .device
        .create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some(label),
            source: wgpu::ShaderSource::Wgsl(source.into()),
        });
    ctx.device
        .create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some(label),
            layout: None,
            module: &module,
            entry_point: Some(entry),
            compilation_options: Default::default(),
            cache: None,
        })
}

const STORAGE: wgpu::BufferUsages = wgpu::BufferUsages::STORAGE.union(wgpu::BufferUsages::COPY_DST);

/// A window of the atlas bound for some records: its first sample, its samples, the records.
type AtlasWindow<'r> = (u64, u64, std::borrow::Cow<'r, [SplatRecord]>);

impl GpuBackend {
    /// A backend on `ctx` with default options.
    pub fn new(ctx: Arc<GpuContext>) -> Result<GpuBackend, BackendError> {
        GpuBackend::with_options(ctx, GpuOptions::default())
    }

    /// A backend on `ctx`.
    pub fn with_options(
        ctx: Arc<GpuContext>,
        options: GpuOptions,
    ) -> Result<GpuBackend, BackendError> {
        ctx.check()?;
        let accumulate = pipeline(
            &ctx,
            "wavesplat accumulate",
            include_str!("../shaders/accumulate.wgsl"),
            "accumulate",
        );
        let display = pipeline(
            &ctx,
            "wavesplat display",
            include_str!("../shaders/display.wgsl"),
            "display",
        );
        let sample = pipeline(
            &ctx,
            "wavesplat display samples",
            include_str!("../shaders/display.wgsl"),
            "sample",
        );
        let params = ctx.buffer(
            "wavesplat params",
            std::mem::size_of::<AccumulateParams>() as u64,
            wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
        );
        let records_capacity = 1024;
        let records = ctx.buffer(
            "wavesplat records",
            (records_capacity * std::mem::size_of::<SplatRecord>()) as u64,
            STORAGE,
        );
        let atlas = DeviceAtlas {
            generation: None,
            data: ctx.buffer("wavesplat atlas", 4096, STORAGE),
            data_len: 0,
            phases: ctx.buffer("wavesplat phases", 4096, STORAGE),
            phases_len: 0,
            peak: Vec::new(),
        };
        let no_offsets = ctx.buffer("wavesplat no offsets", 16, STORAGE);
        ctx.check()?;
        Ok(GpuBackend {
            ctx,
            options,
            accumulate,
            display,
            sample,
            params,
            records,
            records_capacity,
            atlas,
            target: None,
            shown: None,
            offsets: None,
            no_offsets,
        })
    }

    /// The context.
    pub fn context(&self) -> &Arc<GpuContext> {
        &self.ctx
    }

    /// Blocks until the device has done all the work queued so far.
    pub fn wait(&self) -> Result<(), BackendError> {
        self.ctx.wait()
    }

    /// The fixed-point exponent e (a sum `v` means `v · 2^−e`); `None` before any non-zero
    /// splat.
    pub fn scale_exponent(&self) -> Option<i32> {
        self.target.as_ref().and_then(|t| t.exp)
    }

    /// Records per dispatch: the option, capped by the binding size and the dispatch grid.
    fn chunk_len(&self) -> usize {
        let l = self.ctx.device.limits();
        let by_binding = (self.ctx.max_binding() / std::mem::size_of::<SplatRecord>() as u64)
            .min(usize::MAX as u64) as usize;
        let dim = l.max_compute_workgroups_per_dimension as usize;
        let by_grid = dim.saturating_mul(dim).saturating_mul(RECORDS_PER_GROUP);
        self.options.max_chunk.min(by_binding).min(by_grid).max(1)
    }

    /// Brings the device atlas up to `atlas`: fresh for a new generation, else the appended
    /// tail only (buffers double when full).
    fn sync_atlas(&mut self, atlas: &FootprintAtlas) -> Result<(), BackendError> {
        let a = &mut self.atlas;
        if a.generation != Some(atlas.generation)
            || atlas.data.len() < a.data_len
            || atlas.phases.len() < a.phases_len
        {
            a.generation = Some(atlas.generation);
            a.data_len = 0;
            a.phases_len = 0;
            a.peak.clear();
        }
        if atlas.data.len() == a.data_len && atlas.phases.len() == a.phases_len {
            return Ok(());
        }
        for (i, p) in atlas.phases.iter().enumerate().skip(a.phases_len) {
            let end = p.offset as u64 + p.cols as u64 * p.rows as u64;
            if end > atlas.data.len() as u64 {
                return Err(BackendError::Layout(format!(
                    "atlas phase {i} ({p:?}) ends past the atlas's {} samples",
                    atlas.data.len()
                )));
            }
            let s = &atlas.data[p.offset as usize..end as usize];
            a.peak.push(s.iter().fold(0.0f32, |m, x| m.max(x.abs())));
        }
        // The samples are bound a window at a time (see `accumulate`): their buffer may grow to
        // the device's buffer limit; the phases are bound whole.
        let binding = self.ctx.max_binding();
        let buffer_limit = self.ctx.device.limits().max_buffer_size;
        let upload =
            |buffer: &mut wgpu::Buffer, done: usize, bytes: &[u8], unit: usize, max: u64, label| {
                let need = bytes.len() as u64;
                if need > max {
                    return Err(BackendError::Range(format!(
                        "{label} of {need} bytes exceeds the device's limit of {max}"
                    )));
                }
                let from = if need > buffer.size() {
                    let size = need.next_power_of_two().min(max).max(need);
                    *buffer = self.ctx.buffer(label, size.max(4096), STORAGE);
                    0
                } else {
                    done * unit
                };
                if from < bytes.len() {
                    self.ctx
                        .queue
                        .write_buffer(buffer, from as u64, &bytes[from..]);
                }
                Ok(())
            };
        upload(
            &mut a.data,
            a.data_len,
            bytemuck::cast_slice(&atlas.data),
            4,
            buffer_limit,
            "wavesplat atlas",
        )?;
        upload(
            &mut a.phases,
            a.phases_len,
            bytemuck::cast_slice(&atlas.phases),
            std::mem::size_of::<super::PhaseRect>(),
            binding,
            "wavesplat phases",
        )?;
        a.data_len = atlas.data.len();
        a.phases_len = atlas.phases.len();
        Ok(())
    }

    /// The records grouped by the window of the atlas they read, as (first sample, samples,
    /// records): one window holding the whole atlas when it fits the binding limit (or
    /// `max_atlas_binding`), else windows of that size starting every half window, each record
    /// in the one that starts at or before its table by less than half a window (so a table
    /// up to half a window long lies inside). The sums are integers, so the order the groups
    /// are added in changes nothing.
    fn atlas_windows<'r>(
        &self,
        atlas: &FootprintAtlas,
        records: &'r [SplatRecord],
    ) -> Result<Vec<AtlasWindow<'r>>, BackendError> {
        let len = self.atlas.data_len as u64;
        let align =
            (u64::from(self.ctx.device.limits().min_storage_buffer_offset_alignment) / 4).max(1);
        let limit = self
            .options
            .max_atlas_binding
            .unwrap_or(u64::MAX)
            .min(self.ctx.max_binding());
        let window = (limit / 4 / align * align).max(2 * align);
        if len <= window {
            return Ok(vec![(0, len, records.into())]);
        }
        let step = window / 2 / align * align;
        let mut groups: std::collections::BTreeMap<u64, Vec<SplatRecord>> = Default::default();
        for r in records {
            let rect = &atlas.phases[r.phase as usize];
            let start = u64::from(rect.offset);
            let end = start + u64::from(rect.cols) * u64::from(rect.rows);
            let base = start / step * step;
            if end > base + window {
                return Err(BackendError::Range(format!(
                    "a footprint table of {} samples does not fit the device's atlas window of \
                     {window} samples",
                    end - start
                )));
            }
            groups.entry(base).or_default().push(*r);
        }
        Ok(groups
            .into_iter()
            .map(|(base, g)| (base, window.min(len - base), g.into()))
            .collect())
    }

    /// Raises the mass by `mass`, choosing or lowering the exponent so that no sum can
    /// overflow (the sums are shifted on the host when the exponent drops).
    fn reserve(&mut self, mass: f64) -> Result<(), BackendError> {
        let t = self
            .target
            .as_mut()
            .ok_or_else(|| BackendError::Layout("accumulate before begin".into()))?;
        let total = t.mass + mass;
        if total <= 0.0 {
            return Ok(());
        }
        let fit = |m: f64| {
            (LIMIT_BITS - HEADROOM_BITS - m.log2().ceil() as i32).clamp(-EXP_RANGE, EXP_RANGE)
        };
        let limit = 2f64.powi(LIMIT_BITS);
        let exp = match t.exp {
            None => fit(total),
            Some(e) if total * 2f64.powi(e) <= limit => e,
            Some(e) => {
                let e2 = fit(total);
                let shift = (e - e2) as u32;
                let sums = read_sums(&self.ctx, t)?;
                let half = 1i128 << (shift - 1).min(120);
                let words: Vec<u32> = sums
                    .iter()
                    .flat_map(|&v| {
                        let v = if shift >= 64 {
                            0
                        } else {
                            ((v as i128 + half) >> shift) as i64
                        };
                        [v as u32, (v >> 32) as u32]
                    })
                    .collect();
                self.ctx
                    .queue
                    .write_buffer(&t.sums, 0, bytemuck::cast_slice(&words));
                tracing::debug!("gpu target rescaled by 2^-{shift}");
                e2
            }
        };
        if total * 2f64.powi(exp) > limit {
            return Err(BackendError::Range(format!(
                "splat mass {total:e} exceeds the fixed-point target's range"
            )));
        }
        t.exp = Some(exp);
        t.mass = total;
        Ok(())
    }
}

/// The target's sums as i64 (waits for the queue).
fn read_sums(ctx: &GpuContext, t: &Target) -> Result<Vec<i64>, BackendError> {
    let bytes = ctx.read_buffer(&t.sums, t.bytes)?;
    Ok(bytes
        .chunks_exact(8)
        .map(|w| i64::from_le_bytes(w.try_into().expect("8 bytes")))
        .collect())
}

/// Pixels of `r`'s phase inside its view (what the shader adds).
fn clipped_area(r: &SplatRecord, rect: &super::PhaseRect, layout: &Layout) -> u64 {
    let (w, h) = (layout.width as i64, layout.height as i64);
    let cols = (rect.cols as i64).min(MAX_SIDE as i64);
    let rows = (rect.rows as i64).min(MAX_SIDE as i64);
    let xa = (r.x0 as i64).max(0);
    let xb = (r.x0 as i64 + cols).min(w);
    let ya = (r.y0 as i64).max(0);
    let yb = (r.y0 as i64 + rows).min(h);
    if xa >= xb || ya >= yb {
        0
    } else {
        ((xb - xa) * (yb - ya)) as u64
    }
}

impl AccumulationBackend for GpuBackend {
    fn name(&self) -> String {
        format!("gpu ({}, {:?})", self.ctx.info.name, self.ctx.info.backend)
    }

    fn begin(&mut self, layout: Layout) -> Result<(), BackendError> {
        self.ctx.check()?;
        layout.validate()?;
        if layout.total_width() > MAX_SIDE || layout.height > MAX_SIDE || layout.channels > 0xffff {
            return Err(BackendError::Layout(format!(
                "{layout:?} exceeds {MAX_SIDE} pixels a side or 65535 channels"
            )));
        }
        let values = (layout.total_width() * layout.height * layout.channels) as u64;
        let bytes = values * 8;
        if 2 * values > u32::MAX as u64 || bytes > self.ctx.max_binding() {
            return Err(BackendError::Range(format!(
                "a target of {values} values ({bytes} bytes) exceeds the device's limits"
            )));
        }
        let reuse = self.target.take().filter(|t| t.bytes == bytes);
        let sums = match reuse {
            Some(t) => {
                let mut encoder = self
                    .ctx
                    .device
                    .create_command_encoder(&wgpu::CommandEncoderDescriptor::default());
                encoder.clear_buffer(&t.sums, 0, None);
                self.ctx.queue.submit([encoder.finish()]);
                t.sums
            }
            None => self.ctx.buffer(
                "wavesplat target",
                bytes,
                wgpu::BufferUsages::STORAGE
                    | wgpu::BufferUsages::COPY_SRC
                    | wgpu::BufferUsages::COPY_DST,
            ),
        };
        self.target = Some(Target {
            layout,
            sums,
            bytes,
            exp: None,
            mass: 0.0,
        });
        self.ctx.check()
    }

    fn accumulate(
        &mut self,
        atlas: &FootprintAtlas,
        records: &[SplatRecord],
    ) -> Result<u64, BackendError> {
        self.ctx.check()?;
        let layout = self
            .target
            .as_ref()
            .ok_or_else(|| BackendError::Layout("accumulate before begin".into()))?
            .layout;
        for r in records {
            check_record(r, atlas, &layout)?;
        }
        self.sync_atlas(atlas)?;
        let mut updates = 0u64;
        let mut mass = 0.0f64;
        for (index, r) in records.iter().enumerate() {
            if !r.value.is_finite() {
                return Err(BackendError::NotFinite { index });
            }
            let area = clipped_area(r, &atlas.phases[r.phase as usize], &layout);
            if area > 0 {
                updates += area;
                mass += r.value.abs() as f64 * self.atlas.peak[r.phase as usize] as f64;
            }
        }
        if updates == 0 {
            return Ok(0);
        }
        self.reserve(mass)?;
        let t = self.target.as_ref().expect("checked above");
        let Some(exp) = t.exp else {
            // Every weight or sample is zero: nothing to add.
            return Ok(updates);
        };
        let chunk = self.chunk_len();
        let need = records.len().min(chunk);
        if need > self.records_capacity {
            self.records_capacity = need.next_power_of_two().min(chunk);
            self.records = self.ctx.buffer(
                "wavesplat records",
                (self.records_capacity * std::mem::size_of::<SplatRecord>()) as u64,
                STORAGE,
            );
        }
        let max_dim = self
            .ctx
            .device
            .limits()
            .max_compute_workgroups_per_dimension as usize;
        for (base, samples, group) in self.atlas_windows(atlas, records)? {
            let bind = self
                .ctx
                .device
                .create_bind_group(&wgpu::BindGroupDescriptor {
                    label: Some("wavesplat accumulate"),
                    layout: &self.accumulate.get_bind_group_layout(0),
                    entries: &[
                        wgpu::BindGroupEntry {
                            binding: 0,
                            resource: self.params.as_entire_binding(),
                        },
                        wgpu::BindGroupEntry {
                            binding: 1,
                            resource: self.records.as_entire_binding(),
                        },
                        wgpu::BindGroupEntry {
                            binding: 2,
                            resource: self.atlas.phases.as_entire_binding(),
                        },
                        wgpu::BindGroupEntry {
                            binding: 3,
                            resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                                buffer: &self.atlas.data,
                                offset: base * 4,
                                size: std::num::NonZeroU64::new(samples.max(1) * 4),
                            }),
                        },
                        wgpu::BindGroupEntry {
                            binding: 4,
                            resource: t.sums.as_entire_binding(),
                        },
                    ],
                });
            for part in group.chunks(chunk) {
                let groups = part.len().div_ceil(RECORDS_PER_GROUP);
                let gx = groups.min(max_dim);
                let gy = groups.div_ceil(gx);
                let params = AccumulateParams {
                    width: layout.width as u32,
                    height: layout.height as u32,
                    channels: layout.channels as u32,
                    total_width: layout.total_width() as u32,
                    count: part.len() as u32,
                    groups_x: gx as u32,
                    scale: 2f32.powi(exp),
                    atlas_base: base as u32,
                };
                self.ctx
                    .queue
                    .write_buffer(&self.params, 0, bytemuck::bytes_of(&params));
                self.ctx
                    .queue
                    .write_buffer(&self.records, 0, bytemuck::cast_slice(part));
                let mut encoder = self
                    .ctx
                    .device
                    .create_command_encoder(&wgpu::CommandEncoderDescriptor::default());
                {
                    let mut pass =
                        encoder.begin_compute_pass(&wgpu::ComputePassDescriptor::default());
                    pass.set_pipeline(&self.accumulate);
                    pass.set_bind_group(0, &bind, &[]);
                    pass.dispatch_workgroups(gx as u32, gy as u32, 1);
                }
                self.ctx.queue.submit([encoder.finish()]);
            }
        }
        if self.options.wait {
            self.ctx.wait()?;
        }
        self.ctx.check()?;
        Ok(updates)
    }

    fn prepare(&mut self, atlas: &FootprintAtlas) -> Result<(), BackendError> {
        self.ctx.check()?;
        self.sync_atlas(atlas)
    }

    fn gpu(&mut self) -> Option<&mut GpuBackend> {
        Some(self)
    }

    fn read(&mut self) -> Result<Image, BackendError> {
        self.ctx.check()?;
        let t = self
            .target
            .as_ref()
            .ok_or_else(|| BackendError::Layout("read before begin".into()))?;
        let layout = t.layout;
        let mut image = Image::new(layout.total_width(), layout.height, layout.channels);
        if let Some(e) = t.exp {
            let unit = 2f64.powi(-e);
            for (d, v) in image.data.iter_mut().zip(read_sums(&self.ctx, t)?) {
                *d = (v as f64 * unit) as f32;
            }
        }
        Ok(image)
    }
}

#[cfg(test)]
mod tests {
    use super::display::DisplayUniform;
    use super::*;
    use std::mem::{offset_of, size_of};

    /// (WGSL struct, Rust size, Rust member offsets) of every struct shared with a shader.
    fn twins() -> Vec<(&'static str, &'static str, usize, Vec<usize>)> {
        vec![
            (
                include_str!("../shaders/accumulate.wgsl"),
                "Record",
                size_of::<SplatRecord>(),
                vec![
                    offset_of!(SplatRecord, x0),
                    offset_of!(SplatRecord, y0),
                    offset_of!(SplatRecord, phase),
                    offset_of!(SplatRecord, value),
                    offset_of!(SplatRecord, channel),
                ],
            ),
            (
                include_str!("../shaders/accumulate.wgsl"),
                "PhaseRect",
                size_of::<super::super::PhaseRect>(),
                vec![0, 4, 8],
            ),
            (
                include_str!("../shaders/accumulate.wgsl"),
                "Params",
                size_of::<AccumulateParams>(),
                vec![
                    offset_of!(AccumulateParams, width),
                    offset_of!(AccumulateParams, height),
                    offset_of!(AccumulateParams, channels),
                    offset_of!(AccumulateParams, total_width),
                    offset_of!(AccumulateParams, count),
                    offset_of!(AccumulateParams, groups_x),
                    offset_of!(AccumulateParams, scale),
                    offset_of!(AccumulateParams, atlas_base),
                ],
            ),
            (
                include_str!("../shaders/display.wgsl"),
                "DisplayUniform",
                size_of::<DisplayUniform>(),
                vec![
                    offset_of!(DisplayUniform, total_width),
                    offset_of!(DisplayUniform, height),
                    offset_of!(DisplayUniform, channels),
                    offset_of!(DisplayUniform, flags),
                    offset_of!(DisplayUniform, inv_scale),
                    offset_of!(DisplayUniform, low),
                    offset_of!(DisplayUniform, inv_range),
                    offset_of!(DisplayUniform, view_width),
                    offset_of!(DisplayUniform, cols),
                    offset_of!(DisplayUniform, out_width),
                    offset_of!(DisplayUniform, out_height),
                    offset_of!(DisplayUniform, stride),
                    offset_of!(DisplayUniform, samples),
                    offset_of!(DisplayUniform, pad),
                    offset_of!(DisplayUniform, pad) + 4,
                    offset_of!(DisplayUniform, pad) + 8,
                    offset_of!(DisplayUniform, matrix),
                    offset_of!(DisplayUniform, matrix) + 16,
                    offset_of!(DisplayUniform, matrix) + 32,
                ],
            ),
        ]
    }

    /// Every struct shared with a shader has its WGSL twin's size and member offsets.
    #[test]
    fn shader_structs_match_their_wgsl_twins() {
        for (source, name, size, offsets) in twins() {
            let module = naga::front::wgsl::parse_str(source).expect("shader parses");
            let (members, span) = module
                .types
                .iter()
                .find_map(|(_, ty)| match (&ty.name, &ty.inner) {
                    (Some(n), naga::TypeInner::Struct { members, span }) if n == name => {
                        Some((members.clone(), *span))
                    }
                    _ => None,
                })
                .unwrap_or_else(|| panic!("struct {name} in the shader"));
            assert_eq!(span as usize, size, "{name}: size");
            let wgsl: Vec<usize> = members.iter().map(|m| m.offset as usize).collect();
            assert_eq!(wgsl, offsets, "{name}: member offsets");
        }
    }

    /// The record's `channel` and `view` are the low and high halves of the shader's u32.
    #[test]
    fn channel_and_view_pack_into_one_word() {
        let r = SplatRecord {
            x0: -3,
            y0: 7,
            phase: 11,
            value: 1.5,
            channel: 2,
            view: 1,
        };
        let words: &[u32] = bytemuck::cast_slice(std::slice::from_ref(&r));
        assert_eq!(words[4] & 0xffff, 2);
        assert_eq!(words[4] >> 16, 1);
        assert_eq!(words[0] as i32, -3);
    }
}
