//! The wgpu accumulation backend and its display pass. [`GpuContext`] owns the adapter, device
//! and queue (headless, or from an adapter a window chose for its surface); [`GpuBackend`] sums
//! [`SplatRecord`]s on the device and maps the sums to an RGBA8 texture for display.
//!
//! **Data flow.** The [`FootprintAtlas`] is uploaded once per generation and extended in place
//! as it grows (depth-cued tables are appended while a view lasts); the buffers double when
//! they fill. Records are streamed into a buffer in chunks that respect the device's binding
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
//! colour matrix and per-pixel offset (the coded colour space back to RGB) and the
//! window/level of [`Image::write_png`] into an `Rgba8Unorm` storage texture (views side by
//! side as accumulated). The automatic window reads the image back and takes its percentiles
//! on the host, exactly as `write_png`; a window that shows many frames can pass one. A window
//! builds its [`GpuContext`] with [`GpuContext::from_adapter`] (the adapter it chose for its
//! surface) and draws the texture [`GpuBackend::display`] returns, e.g. with
//! `wgpu::util::TextureBlitter` (the bytes are the PNG's: linear, so blit to a non-sRGB view).
//!
//! **Cost.** The scatter with atomics suits a GPU. On a software adapter (lavapipe) the atomics
//! run one lane at a time, and the backend is 5–15× slower than the CPU backend on the same
//! records (BENCHMARKS.md, issue 12): [`super::select`] does not pick it there by default.

use super::{check_record, AccumulationBackend, BackendError, FootprintAtlas, Layout, SplatRecord};
use crate::image::Image;
use bytemuck::{Pod, Zeroable};
use std::sync::{Arc, Mutex};

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
    pad: u32,
}

/// Uniform of the display pass. Twin of `DisplayUniform` in `shaders/display.wgsl`.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct DisplayUniform {
    total_width: u32,
    height: u32,
    channels: u32,
    flags: u32,
    inv_scale: f32,
    low: f32,
    inv_range: f32,
    pad: f32,
    matrix: [[f32; 4]; 3],
}

fn device_error(what: &str, e: impl std::fmt::Display) -> BackendError {
    BackendError::Device(format!("{what}: {e}"))
}

/// The wgpu instance, adapter, device and queue a [`GpuBackend`] runs on. Device errors that
/// wgpu reports outside a call (validation, loss) are kept and returned by the next call of
/// every backend on this context instead of panicking.
#[derive(Debug)]
pub struct GpuContext {
    instance: wgpu::Instance,
    adapter: wgpu::Adapter,
    device: wgpu::Device,
    queue: wgpu::Queue,
    info: wgpu::AdapterInfo,
    fault: Arc<Mutex<Option<String>>>,
    /// Set when the device is lost, for any reason (a driver reset, or `destroy`).
    lost: Arc<std::sync::atomic::AtomicBool>,
}

/// Which adapter to ask wgpu for.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct AdapterRequest {
    /// Backends to look on.
    pub backends: wgpu::Backends,
    /// Take the first adapter whose name contains this (any case).
    pub name: Option<String>,
    /// Power preference when no name is given.
    pub power: wgpu::PowerPreference,
}

impl AdapterRequest {
    /// From the environment as wgpu reads it: `WGPU_BACKEND` (e.g. `vulkan`, `gl`; default
    /// all), `WGPU_ADAPTER_NAME`, `WGPU_POWER_PREF`.
    pub fn from_env() -> AdapterRequest {
        AdapterRequest {
            backends: wgpu::Backends::from_env().unwrap_or(wgpu::Backends::all()),
            name: std::env::var("WGPU_ADAPTER_NAME").ok(),
            power: wgpu::PowerPreference::from_env().unwrap_or_default(),
        }
    }

    fn instance(&self) -> wgpu::Instance {
        let mut desc = wgpu::InstanceDescriptor::new_without_display_handle_from_env();
        desc.backends = self.backends;
        wgpu::Instance::new(desc)
    }

    /// The adapter, or [`BackendError::NoAdapter`] saying what was looked for.
    fn adapter(&self, instance: &wgpu::Instance) -> Result<wgpu::Adapter, BackendError> {
        if let Some(name) = &self.name {
            let want = name.to_lowercase();
            let adapters = pollster::block_on(instance.enumerate_adapters(self.backends));
            let names: Vec<String> = adapters.iter().map(|a| a.get_info().name).collect();
            return adapters
                .into_iter()
                .find(|a| a.get_info().name.to_lowercase().contains(&want))
                .ok_or_else(|| {
                    BackendError::NoAdapter(format!(
                        "no adapter named like {name:?} among {names:?} (backends {:?})",
                        self.backends
                    ))
                });
        }
        pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions {
            power_preference: self.power,
            ..Default::default()
        }))
        .map_err(|e| BackendError::NoAdapter(format!("{e} (backends {:?})", self.backends)))
    }
}

/// The adapter [`GpuContext::new`] would take, without opening a device.
pub fn probe_adapter() -> Result<wgpu::AdapterInfo, BackendError> {
    let request = AdapterRequest::from_env();
    Ok(request.adapter(&request.instance())?.get_info())
}

impl GpuContext {
    /// A headless context on the adapter wgpu finds (`WGPU_BACKEND`, `WGPU_ADAPTER_NAME` and
    /// `WGPU_POWER_PREF` honoured); [`BackendError::NoAdapter`] when there is none.
    pub fn new() -> Result<Arc<GpuContext>, BackendError> {
        GpuContext::request(&AdapterRequest::from_env())
    }

    /// A headless context on the adapter `request` names.
    pub fn request(request: &AdapterRequest) -> Result<Arc<GpuContext>, BackendError> {
        let instance = request.instance();
        let adapter = request.adapter(&instance)?;
        GpuContext::from_adapter(instance, adapter)
    }

    /// A context on `adapter` of `instance` (a window passes the adapter it chose for its
    /// surface). The device gets the adapter's limits and no optional feature.
    pub fn from_adapter(
        instance: wgpu::Instance,
        adapter: wgpu::Adapter,
    ) -> Result<Arc<GpuContext>, BackendError> {
        let info = adapter.get_info();
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("wavesplat"),
            required_features: wgpu::Features::empty(),
            required_limits: adapter.limits(),
            ..Default::default()
        }))
        .map_err(|e| device_error("requesting a device", e))?;
        let fault = Arc::new(Mutex::new(None::<String>));
        let f = fault.clone();
        device.on_uncaptured_error(Arc::new(move |e: wgpu::Error| {
            tracing::error!("wgpu: {e}");
            if let Ok(mut slot) = f.lock() {
                slot.get_or_insert_with(|| e.to_string());
            }
        }));
        let f = fault.clone();
        let lost = Arc::new(std::sync::atomic::AtomicBool::new(false));
        let l = lost.clone();
        device.set_device_lost_callback(move |reason, message| {
            l.store(true, std::sync::atomic::Ordering::SeqCst);
            if reason != wgpu::DeviceLostReason::Destroyed {
                tracing::error!("wgpu device lost: {message}");
                if let Ok(mut slot) = f.lock() {
                    slot.get_or_insert_with(|| format!("device lost: {message}"));
                }
            }
        });
        tracing::info!(
            "wgpu adapter: {} ({:?}, {:?})",
            info.name,
            info.backend,
            info.device_type
        );
        Ok(Arc::new(GpuContext {
            instance,
            adapter,
            device,
            queue,
            info,
            fault,
            lost,
        }))
    }

    /// The instance (a window creates its surface from it).
    pub fn instance(&self) -> &wgpu::Instance {
        &self.instance
    }

    /// The adapter.
    pub fn adapter(&self) -> &wgpu::Adapter {
        &self.adapter
    }

    /// The device.
    pub fn device(&self) -> &wgpu::Device {
        &self.device
    }

    /// The queue.
    pub fn queue(&self) -> &wgpu::Queue {
        &self.queue
    }

    /// What the adapter is.
    pub fn info(&self) -> &wgpu::AdapterInfo {
        &self.info
    }

    /// Whether the adapter is a software device running on the CPU (lavapipe, WARP, …).
    pub fn is_software(&self) -> bool {
        self.info.device_type == wgpu::DeviceType::Cpu
    }

    /// Whether the device is lost (or reported an error): nothing drawn on it shows any
    /// more, and a window recreates its context.
    pub fn is_lost(&self) -> bool {
        self.lost.load(std::sync::atomic::Ordering::SeqCst) || self.check().is_err()
    }

    /// Destroys the device, as a driver reset would lose it (for tests of recovery).
    pub fn lose_device(&self) {
        self.device.destroy();
        let _ = self.device.poll(wgpu::PollType::Poll);
    }

    /// The first device error wgpu reported, if any (the context is unusable after one).
    fn check(&self) -> Result<(), BackendError> {
        match self.fault.lock() {
            Ok(slot) => match slot.as_ref() {
                Some(m) => Err(BackendError::Device(m.clone())),
                None => Ok(()),
            },
            Err(_) => Err(BackendError::Device("error state poisoned".into())),
        }
    }

    /// Blocks until the queue is idle.
    fn wait(&self) -> Result<(), BackendError> {
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| device_error("waiting for the queue", e))?;
        self.check()
    }

    fn buffer(&self, label: &str, size: u64, usage: wgpu::BufferUsages) -> wgpu::Buffer {
        self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size,
            usage,
            mapped_at_creation: false,
        })
    }

    /// Copies `size` bytes of `source` to the host.
    fn read_buffer(&self, source: &wgpu::Buffer, size: u64) -> Result<Vec<u8>, BackendError> {
        let staging = self.buffer(
            "wavesplat readback",
            size,
            wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        );
        let mut encoder = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor::default());
        encoder.copy_buffer_to_buffer(source, 0, &staging, 0, size);
        self.queue.submit([encoder.finish()]);
        self.map_read(&staging)
    }

    /// Maps a MAP_READ buffer after the queue is idle and copies it out.
    fn map_read(&self, staging: &wgpu::Buffer) -> Result<Vec<u8>, BackendError> {
        let slice = staging.slice(..);
        let (tx, rx) = std::sync::mpsc::channel();
        slice.map_async(wgpu::MapMode::Read, move |r| {
            let _ = tx.send(r);
        });
        self.wait()?;
        rx.recv()
            .map_err(|e| device_error("mapping a buffer", e))?
            .map_err(|e| device_error("mapping a buffer", e))?;
        let bytes = slice
            .get_mapped_range()
            .map_err(|e| device_error("reading a mapped buffer", e))?
            .to_vec();
        staging.unmap();
        Ok(bytes)
    }

    /// Largest storage buffer binding this device allows (bytes).
    fn max_binding(&self) -> u64 {
        let l = self.device.limits();
        l.max_storage_buffer_binding_size.min(l.max_buffer_size)
    }
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
}

impl Default for GpuOptions {
    fn default() -> Self {
        GpuOptions {
            max_chunk: DEFAULT_CHUNK,
            wait: true,
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

/// The display pass's texture and what it needs.
#[derive(Debug)]
struct Display {
    texture: wgpu::Texture,
    size: (u32, u32),
}

/// How the display pass maps the image to colours.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct DisplayOptions {
    /// Values mapped to 0 and 255 (`None`: `Image::auto_window`, as `write_png`).
    pub window: Option<(f64, f64)>,
    /// Colour transform of a 3-channel image (`None`: channels shown as they are).
    pub colour: Option<ColourMap>,
}

/// A colour transform applied before the window: `rgb = matrix · c + offset(pixel)`.
#[derive(Debug, Clone, PartialEq)]
pub struct ColourMap {
    /// Row-major 3×3 matrix.
    pub matrix: [[f32; 3]; 3],
    /// Per-pixel RGB offsets of the whole target (total width × height × 3), e.g. the colour
    /// mean times the ray's chord through the volume; `None`: no offset.
    pub offset: Option<Vec<f32>>,
}

impl ColourMap {
    /// The host twin of the display pass's colour transform (for the automatic window and
    /// for tests).
    pub fn apply(&self, image: &Image) -> Result<Image, BackendError> {
        let pixels = image.width * image.height;
        if image.channels != 3 {
            return Err(BackendError::Display(format!(
                "a colour map needs 3 channels, the image has {}",
                image.channels
            )));
        }
        if let Some(o) = &self.offset {
            if o.len() != pixels * 3 {
                return Err(BackendError::Display(format!(
                    "colour offsets hold {} values for {} pixels",
                    o.len(),
                    pixels
                )));
            }
        }
        let mut out = image.clone();
        for (p, px) in out.data.chunks_exact_mut(3).enumerate() {
            let c = [px[0], px[1], px[2]];
            for r in 0..3 {
                let m = self.matrix[r];
                px[r] = m[0] * c[0]
                    + m[1] * c[1]
                    + m[2] * c[2]
                    + self.offset.as_ref().map_or(0.0, |o| o[3 * p + r]);
            }
        }
        Ok(out)
    }
}

/// Accumulates splat records on a wgpu device (see the module doc).
#[derive(Debug)]
pub struct GpuBackend {
    ctx: Arc<GpuContext>,
    options: GpuOptions,
    accumulate: wgpu::ComputePipeline,
    display: wgpu::ComputePipeline,
    params: wgpu::Buffer,
    records: wgpu::Buffer,
    records_capacity: usize,
    atlas: DeviceAtlas,
    target: Option<Target>,
    shown: Option<Display>,
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
            include_str!("shaders/accumulate.wgsl"),
            "accumulate",
        );
        let display = pipeline(
            &ctx,
            "wavesplat display",
            include_str!("shaders/display.wgsl"),
            "display",
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
        ctx.check()?;
        Ok(GpuBackend {
            ctx,
            options,
            accumulate,
            display,
            params,
            records,
            records_capacity,
            atlas,
            target: None,
            shown: None,
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
        let max = self.ctx.max_binding();
        let upload = |buffer: &mut wgpu::Buffer, done: usize, bytes: &[u8], unit: usize, label| {
            let need = bytes.len() as u64;
            if need > max {
                return Err(BackendError::Range(format!(
                    "{label} of {need} bytes exceeds the device's binding limit of {max}"
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
            "wavesplat atlas",
        )?;
        upload(
            &mut a.phases,
            a.phases_len,
            bytemuck::cast_slice(&atlas.phases),
            std::mem::size_of::<super::PhaseRect>(),
            "wavesplat phases",
        )?;
        a.data_len = atlas.data.len();
        a.phases_len = atlas.phases.len();
        Ok(())
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

    /// The display texture (`Rgba8Unorm`, total width × height, views side by side) from the
    /// image accumulated so far; also usable as a texture binding (a window draws it).
    pub fn display(&mut self, options: &DisplayOptions) -> Result<&wgpu::Texture, BackendError> {
        self.ctx.check()?;
        let layout = self
            .target
            .as_ref()
            .ok_or_else(|| BackendError::Layout("display before begin".into()))?
            .layout;
        let channels = layout.channels;
        if channels != 1 && channels != 3 {
            return Err(BackendError::Display(format!(
                "{channels} channels (1 or 3 can be shown)"
            )));
        }
        let (w, h) = (layout.total_width() as u32, layout.height as u32);
        let max_side = self.ctx.device.limits().max_texture_dimension_2d;
        if w > max_side || h > max_side {
            return Err(BackendError::Display(format!(
                "{w}x{h} exceeds the device's texture limit of {max_side}"
            )));
        }
        if let Some(c) = &options.colour {
            if channels != 3 {
                return Err(BackendError::Display(format!(
                    "a colour map needs 3 channels, the image has {channels}"
                )));
            }
            if let Some(o) = &c.offset {
                if o.len() != w as usize * h as usize * 3 {
                    return Err(BackendError::Display(format!(
                        "colour offsets hold {} values for {w}x{h} pixels",
                        o.len()
                    )));
                }
            }
        }
        let window = match options.window {
            Some(win) => Image::new(1, 1, 1)
                .resolve_window(Some(win))
                .map_err(|e| BackendError::Display(e.to_string()))?,
            None => {
                let mut image = self.read()?;
                if let Some(c) = &options.colour {
                    image = c.apply(&image)?;
                }
                image
                    .resolve_window(None)
                    .map_err(|e| BackendError::Display(e.to_string()))?
            }
        };
        let t = self.target.as_ref().expect("checked above");
        let mut matrix = [[0.0f32; 4]; 3];
        let mut flags = 0;
        if let Some(c) = &options.colour {
            flags |= 1;
            for r in 0..3 {
                matrix[r][..3].copy_from_slice(&c.matrix[r]);
            }
            if c.offset.is_some() {
                flags |= 2;
            }
        }
        let uniform = DisplayUniform {
            total_width: w,
            height: h,
            channels: channels as u32,
            flags,
            inv_scale: 2f32.powi(-t.exp.unwrap_or(0)),
            low: window.0 as f32,
            inv_range: (1.0 / (window.1 - window.0)) as f32,
            pad: 0.0,
            matrix,
        };
        let ub = self.ctx.buffer(
            "wavesplat display params",
            std::mem::size_of::<DisplayUniform>() as u64,
            wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
        );
        self.ctx
            .queue
            .write_buffer(&ub, 0, bytemuck::bytes_of(&uniform));
        let offsets: &[f32] = options
            .colour
            .as_ref()
            .and_then(|c| c.offset.as_deref())
            .unwrap_or(&[0.0]);
        let ob = self.ctx.buffer(
            "wavesplat colour offsets",
            (offsets.len() * 4) as u64,
            STORAGE,
        );
        self.ctx
            .queue
            .write_buffer(&ob, 0, bytemuck::cast_slice(offsets));
        if self.shown.as_ref().is_none_or(|d| d.size != (w, h)) {
            let texture = self.ctx.device.create_texture(&wgpu::TextureDescriptor {
                label: Some("wavesplat display"),
                size: wgpu::Extent3d {
                    width: w,
                    height: h,
                    depth_or_array_layers: 1,
                },
                mip_level_count: 1,
                sample_count: 1,
                dimension: wgpu::TextureDimension::D2,
                format: wgpu::TextureFormat::Rgba8Unorm,
                usage: wgpu::TextureUsages::STORAGE_BINDING
                    | wgpu::TextureUsages::TEXTURE_BINDING
                    | wgpu::TextureUsages::COPY_SRC,
                view_formats: &[],
            });
            self.shown = Some(Display {
                texture,
                size: (w, h),
            });
        }
        let shown = self.shown.as_ref().expect("created above");
        let view = shown
            .texture
            .create_view(&wgpu::TextureViewDescriptor::default());
        let bind = self
            .ctx
            .device
            .create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("wavesplat display"),
                layout: &self.display.get_bind_group_layout(0),
                entries: &[
                    wgpu::BindGroupEntry {
                        binding: 0,
                        resource: ub.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: 1,
                        resource: t.sums.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: 2,
                        resource: ob.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: 3,
                        resource: wgpu::BindingResource::TextureView(&view),
                    },
                ],
            });
        let mut encoder = self
            .ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor::default());
        {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor::default());
            pass.set_pipeline(&self.display);
            pass.set_bind_group(0, &bind, &[]);
            pass.dispatch_workgroups(w.div_ceil(8), h.div_ceil(8), 1);
        }
        self.ctx.queue.submit([encoder.finish()]);
        self.ctx.check()?;
        Ok(&shown.texture)
    }

    /// The display texture's pixels (RGBA8 rows, no padding), after [`GpuBackend::display`].
    pub fn read_display(&mut self) -> Result<Vec<u8>, BackendError> {
        let shown = self
            .shown
            .as_ref()
            .ok_or_else(|| BackendError::Display("read_display before display".into()))?;
        let (w, h) = shown.size;
        let row = w as u64 * 4;
        let padded = row.next_multiple_of(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT as u64);
        let staging = self.ctx.buffer(
            "wavesplat display readback",
            padded * h as u64,
            wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        );
        let mut encoder = self
            .ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor::default());
        encoder.copy_texture_to_buffer(
            shown.texture.as_image_copy(),
            wgpu::TexelCopyBufferInfo {
                buffer: &staging,
                layout: wgpu::TexelCopyBufferLayout {
                    offset: 0,
                    bytes_per_row: Some(padded as u32),
                    rows_per_image: Some(h),
                },
            },
            wgpu::Extent3d {
                width: w,
                height: h,
                depth_or_array_layers: 1,
            },
        );
        self.ctx.queue.submit([encoder.finish()]);
        let bytes = self.ctx.map_read(&staging)?;
        Ok(bytes
            .chunks_exact(padded as usize)
            .flat_map(|r| &r[..row as usize])
            .copied()
            .collect())
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
                        resource: self.atlas.data.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: 4,
                        resource: t.sums.as_entire_binding(),
                    },
                ],
            });
        let max_dim = self
            .ctx
            .device
            .limits()
            .max_compute_workgroups_per_dimension as usize;
        for part in records.chunks(chunk) {
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
                pad: 0,
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
                let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor::default());
                pass.set_pipeline(&self.accumulate);
                pass.set_bind_group(0, &bind, &[]);
                pass.dispatch_workgroups(gx as u32, gy as u32, 1);
            }
            self.ctx.queue.submit([encoder.finish()]);
        }
        if self.options.wait {
            self.ctx.wait()?;
        }
        self.ctx.check()?;
        Ok(updates)
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
    use super::*;
    use std::mem::{offset_of, size_of};

    /// (WGSL struct, Rust size, Rust member offsets) of every struct shared with a shader.
    fn twins() -> Vec<(&'static str, &'static str, usize, Vec<usize>)> {
        vec![
            (
                include_str!("shaders/accumulate.wgsl"),
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
                include_str!("shaders/accumulate.wgsl"),
                "PhaseRect",
                size_of::<super::super::PhaseRect>(),
                vec![0, 4, 8],
            ),
            (
                include_str!("shaders/accumulate.wgsl"),
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
                    offset_of!(AccumulateParams, pad),
                ],
            ),
            (
                include_str!("shaders/display.wgsl"),
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
                    offset_of!(DisplayUniform, pad),
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
