//! The GPU context: an adapter (asked for headless, or the one a window chose for its surface),
//! its device and queue, buffer read-back, and whether the device was lost (a driver reset, or
//! `lose_device` in tests and scripts).

use super::super::BackendError;
use std::sync::{Arc, Mutex};

fn device_error(what: &str, e: impl std::fmt::Display) -> BackendError {
    BackendError::Device(format!("{what}: {e}"))
}

/// The wgpu instance, adapter, device and queue a [`GpuBackend`] runs on. Device errors that
/// wgpu reports outside a call (validation, loss) are kept and returned by the next call of
/// every backend on this context instead of panicking.
#[derive(Debug)]
pub struct GpuContext {
    pub(super) instance: wgpu::Instance,
    pub(super) adapter: wgpu::Adapter,
    pub(super) device: wgpu::Device,
    pub(super) queue: wgpu::Queue,
    pub(super) info: wgpu::AdapterInfo,
    pub(super) fault: Arc<Mutex<Option<String>>>,
    /// Set when the device is lost, for any reason (a driver reset, or `destroy`).
    pub(super) lost: Arc<std::sync::atomic::AtomicBool>,
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
    pub(super) fn check(&self) -> Result<(), BackendError> {
        match self.fault.lock() {
            Ok(slot) => match slot.as_ref() {
                Some(m) => Err(BackendError::Device(m.clone())),
                None => Ok(()),
            },
            Err(_) => Err(BackendError::Device("error state poisoned".into())),
        }
    }

    /// Blocks until the queue is idle.
    pub(super) fn wait(&self) -> Result<(), BackendError> {
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| device_error("waiting for the queue", e))?;
        self.check()
    }

    pub(super) fn buffer(&self, label: &str, size: u64, usage: wgpu::BufferUsages) -> wgpu::Buffer {
        self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size,
            usage,
            mapped_at_creation: false,
        })
    }

    /// Copies `size` bytes of `source` to the host.
    pub(super) fn read_buffer(
        &self,
        source: &wgpu::Buffer,
        size: u64,
    ) -> Result<Vec<u8>, BackendError> {
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

    /// The pixels of an RGBA8 `texture` of this device (rows without padding): what a
    /// display texture shows.
    pub fn read_rgba8(&self, texture: &wgpu::Texture) -> Result<Vec<u8>, BackendError> {
        if texture.format().block_copy_size(None) != Some(4) {
            return Err(BackendError::Display(format!(
                "{:?} is not a 4-byte-per-pixel format",
                texture.format()
            )));
        }
        let (w, h) = (texture.width(), texture.height());
        let row = w as u64 * 4;
        let padded = row.next_multiple_of(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT as u64);
        let staging = self.buffer(
            "wavesplat display readback",
            padded * h as u64,
            wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        );
        let mut encoder = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor::default());
        encoder.copy_texture_to_buffer(
            texture.as_image_copy(),
            wgpu::TexelCopyBufferInfo {
                buffer: &staging,
                layout: wgpu::TexelCopyBufferLayout {
                    offset: 0,
                    bytes_per_row: Some(padded as u32),
                    rows_per_image: Some(h),
                },
            },
            texture.size(),
        );
        self.queue.submit([encoder.finish()]);
        let bytes = self.map_read(&staging)?;
        Ok(bytes
            .chunks_exact(padded as usize)
            .flat_map(|r| &r[..row as usize])
            .copied()
            .collect())
    }

    /// Largest storage buffer binding this device allows (bytes).
    pub(super) fn max_binding(&self) -> u64 {
        let l = self.device.limits();
        l.max_storage_buffer_binding_size.min(l.max_buffer_size)
    }
}
