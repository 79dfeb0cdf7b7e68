//! The display pass of the GPU backend: the accumulated fixed-point sums converted to floats,
//! through an optional colour matrix and per-pixel offset (the coded colour space back to RGB)
//! and the window/level of `Image::write_png`, into an `Rgba8Unorm` texture a window draws.

use super::super::{AccumulationBackend, BackendError};
use super::GpuBackend;
use super::STORAGE;
use crate::image::Image;
use bytemuck::{Pod, Zeroable};

/// Uniform of the display pass. Twin of `DisplayUniform` in `shaders/display.wgsl`.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub(super) struct DisplayUniform {
    pub(super) total_width: u32,
    pub(super) height: u32,
    pub(super) channels: u32,
    pub(super) flags: u32,
    pub(super) inv_scale: f32,
    pub(super) low: f32,
    pub(super) inv_range: f32,
    pub(super) pad: f32,
    pub(super) matrix: [[f32; 4]; 3],
}

/// The display pass's texture and what it needs.
#[derive(Debug)]
pub(super) struct Display {
    texture: wgpu::Texture,
    size: (u32, u32),
}

/// How the display pass maps the image to colours.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct DisplayOptions {
    /// Values mapped to 0 and 255 (`None`: `Image::auto_window`, as `write_png`).
    pub window: Option<(f64, f64)>,
    /// Colour transform of a 3-channel image (`None`: channels shown as they are).
    pub colour: Option<ColorMap>,
}

/// A colour transform applied before the window: `rgb = matrix · c + offset(pixel)`.
#[derive(Debug, Clone, PartialEq)]
pub struct ColorMap {
    /// Row-major 3×3 matrix.
    pub matrix: [[f32; 3]; 3],
    /// Per-pixel RGB offsets of the whole target (total width × height × 3), e.g. the colour
    /// mean times the ray's chord through the volume; `None`: no offset.
    pub offset: Option<Vec<f32>>,
}

impl ColorMap {
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

impl GpuBackend {
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
