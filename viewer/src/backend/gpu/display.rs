//! The display pass of the GPU backend: the accumulated fixed-point sums converted to floats,
//! through an optional colour matrix and per-pixel offset (the coded values back to what the
//! volume holds), laid out as a grid of panels and mapped through the window/level of
//! `Image::write_png` into an `Rgba8Unorm` texture a window draws. The automatic window is
//! computed on the host from at most [`MAX_WINDOW_SAMPLES`] pixels the device picks out (all of
//! them in images up to that size), so a frame moves no image across the bus.

use super::super::BackendError;
use super::GpuBackend;
use super::STORAGE;
use crate::image::Image;
use bytemuck::{Pod, Zeroable};
use std::sync::Arc;

pub use crate::image::MAX_WINDOW_SAMPLES;

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
    pub(super) view_width: u32,
    pub(super) cols: u32,
    pub(super) out_width: u32,
    pub(super) out_height: u32,
    pub(super) stride: u32,
    pub(super) samples: u32,
    pub(super) pad: [u32; 3],
    pub(super) matrix: [[f32; 4]; 3],
}

/// The display pass's texture, its pipelines' inputs that persist between frames.
#[derive(Debug)]
pub(super) struct Display {
    texture: wgpu::Texture,
    size: (u32, u32),
}

/// The per-pixel offsets last uploaded, kept while the colour map holds the same ones.
#[derive(Debug)]
pub(super) struct Offsets {
    values: Arc<[f32]>,
    buffer: wgpu::Buffer,
}

/// How the display pass maps the image to colours.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct DisplayOptions {
    /// Values mapped to 0 and 255 (`None`: the automatic window, see
    /// [`GpuBackend::auto_window`]).
    pub window: Option<(f64, f64)>,
    /// Colour transform and offsets (`None`: channels shown as they are).
    pub colour: Option<ColorMap>,
    /// Panels per row and rows the views are laid out in (`None`: side by side, as
    /// accumulated). A cell past the last view shows the value 0.
    pub grid: Option<(usize, usize)>,
}

/// A transform applied before the window: `value = matrix · c + offset(pixel)`.
#[derive(Debug, Clone, PartialEq)]
pub struct ColorMap {
    /// Row-major 3×3 matrix (3-channel images only; `None`: the identity).
    pub matrix: Option<[[f32; 3]; 3]>,
    /// Per-pixel offsets of the whole target (total width × height × channels), e.g. the
    /// intensity offset or colour mean times the ray's chord through the volume; `None`: none.
    /// Shared, so that a map kept between frames is uploaded once.
    pub offset: Option<Arc<[f32]>>,
}

impl ColorMap {
    /// Refuses a map that does not fit an image of `pixels` × `channels`.
    fn check(&self, pixels: usize, channels: usize) -> Result<(), BackendError> {
        if self.matrix.is_some() && channels != 3 {
            return Err(BackendError::Display(format!(
                "a colour matrix needs 3 channels, the image has {channels}"
            )));
        }
        if let Some(o) = &self.offset {
            if o.len() != pixels * channels {
                return Err(BackendError::Display(format!(
                    "offsets hold {} values for {pixels} pixels of {channels} channels",
                    o.len()
                )));
            }
        }
        Ok(())
    }

    /// The host twin of the display pass's transform (for tests and host-side display).
    pub fn apply(&self, image: &Image) -> Result<Image, BackendError> {
        let channels = image.channels;
        self.check(image.width * image.height, channels)?;
        let mut out = image.clone();
        for (p, px) in out.data.chunks_exact_mut(channels).enumerate() {
            if let Some(m) = &self.matrix {
                let c = [px[0], px[1], px[2]];
                for r in 0..3 {
                    px[r] = m[r][0] * c[0] + m[r][1] * c[1] + m[r][2] * c[2];
                }
            }
            if let Some(o) = &self.offset {
                for (r, v) in px.iter_mut().enumerate() {
                    *v += o[channels * p + r];
                }
            }
        }
        Ok(out)
    }
}

/// What both display entry points are given: the target's layout and the colour map.
struct Inputs {
    uniform: DisplayUniform,
    pixels: usize,
}

impl GpuBackend {
    /// Checks the target and `colour`, and fills the uniform's layout and colour fields.
    fn display_inputs(&self, colour: Option<&ColorMap>) -> Result<Inputs, BackendError> {
        self.ctx.check()?;
        let t = self
            .target
            .as_ref()
            .ok_or_else(|| BackendError::Layout("display before begin".into()))?;
        let layout = t.layout;
        let channels = layout.channels;
        if channels != 1 && channels != 3 {
            return Err(BackendError::Display(format!(
                "{channels} channels (1 or 3 can be shown)"
            )));
        }
        let pixels = layout.total_width() * layout.height;
        if let Some(c) = colour {
            c.check(pixels, channels)?;
        }
        let mut matrix = [[0.0f32; 4]; 3];
        let mut flags = 0;
        if let Some(c) = colour {
            if let Some(m) = &c.matrix {
                flags |= 1;
                for r in 0..3 {
                    matrix[r][..3].copy_from_slice(&m[r]);
                }
            }
            if c.offset.is_some() {
                flags |= 2;
            }
        }
        Ok(Inputs {
            uniform: DisplayUniform {
                total_width: layout.total_width() as u32,
                height: layout.height as u32,
                channels: channels as u32,
                flags,
                inv_scale: 2f32.powi(-t.exp.unwrap_or(0)),
                low: 0.0,
                inv_range: 1.0,
                view_width: layout.width as u32,
                cols: layout.views as u32,
                out_width: layout.total_width() as u32,
                out_height: layout.height as u32,
                stride: 1,
                samples: 0,
                pad: [0; 3],
                matrix,
            },
            pixels,
        })
    }

    /// The offsets buffer of `colour` (uploaded when it holds other offsets than the last).
    fn offsets_buffer(&mut self, colour: Option<&ColorMap>) -> wgpu::Buffer {
        let Some(values) = colour.and_then(|c| c.offset.as_ref()) else {
            // Bound but not read (flag bit 1 clear).
            return self.no_offsets.clone();
        };
        if let Some(o) = &self.offsets {
            if Arc::ptr_eq(&o.values, values) {
                return o.buffer.clone();
            }
        }
        let buffer = self
            .ctx
            .buffer("wavesplat offsets", (values.len() * 4) as u64, STORAGE);
        self.ctx
            .queue
            .write_buffer(&buffer, 0, bytemuck::cast_slice(values));
        self.offsets = Some(Offsets {
            values: values.clone(),
            buffer: buffer.clone(),
        });
        buffer
    }

    fn uniform_buffer(&self, uniform: &DisplayUniform) -> wgpu::Buffer {
        let ub = self.ctx.buffer(
            "wavesplat display params",
            std::mem::size_of::<DisplayUniform>() as u64,
            wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
        );
        self.ctx
            .queue
            .write_buffer(&ub, 0, bytemuck::bytes_of(uniform));
        ub
    }

    /// The bind group of a display entry point: the uniform, the sums, the offsets and the
    /// entry point's output.
    fn bind_display(
        &self,
        pipeline: &wgpu::ComputePipeline,
        uniform: &wgpu::Buffer,
        offsets: &wgpu::Buffer,
        output: wgpu::BindGroupEntry,
    ) -> wgpu::BindGroup {
        let t = self.target.as_ref().expect("checked by display_inputs");
        self.ctx
            .device
            .create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("wavesplat display"),
                layout: &pipeline.get_bind_group_layout(0),
                entries: &[
                    wgpu::BindGroupEntry {
                        binding: 0,
                        resource: uniform.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: 1,
                        resource: t.sums.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: 2,
                        resource: offsets.as_entire_binding(),
                    },
                    output,
                ],
            })
    }

    /// The automatic window ([`Image::resolve_window`] of `None`) of the image as the display
    /// pass shows it through `colour`: computed from every pixel of an image up to
    /// [`MAX_WINDOW_SAMPLES`] pixels, else from every n-th; only those values leave the device.
    pub fn auto_window(&mut self, colour: Option<&ColorMap>) -> Result<(f64, f64), BackendError> {
        let mut inputs = self.display_inputs(colour)?;
        let stride = inputs.pixels.div_ceil(MAX_WINDOW_SAMPLES).max(1);
        let samples = inputs.pixels.div_ceil(stride);
        inputs.uniform.stride = stride as u32;
        inputs.uniform.samples = samples as u32;
        let channels = inputs.uniform.channels as usize;
        let ub = self.uniform_buffer(&inputs.uniform);
        let ob = self.offsets_buffer(colour);
        let bytes = (samples * channels * 4) as u64;
        let out = self.ctx.buffer(
            "wavesplat window samples",
            bytes,
            wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
        );
        let bind = self.bind_display(
            &self.sample,
            &ub,
            &ob,
            wgpu::BindGroupEntry {
                binding: 4,
                resource: out.as_entire_binding(),
            },
        );
        let mut encoder = self
            .ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor::default());
        {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor::default());
            pass.set_pipeline(&self.sample);
            pass.set_bind_group(0, &bind, &[]);
            pass.dispatch_workgroups((samples as u32).div_ceil(64), 1, 1);
        }
        self.ctx.queue.submit([encoder.finish()]);
        let read = self.ctx.read_buffer(&out, bytes)?;
        let mut image = Image::new(samples, 1, channels);
        image.data = bytemuck::pod_collect_to_vec(&read);
        image
            .resolve_window(None)
            .map_err(|e| BackendError::Display(e.to_string()))
    }

    /// The display texture (`Rgba8Unorm`; the views side by side, or `options.grid`'s panels)
    /// from the image accumulated so far; also usable as a texture binding (a window draws it).
    pub fn display(&mut self, options: &DisplayOptions) -> Result<&wgpu::Texture, BackendError> {
        let mut inputs = self.display_inputs(options.colour.as_ref())?;
        let (view_w, h) = (inputs.uniform.view_width, inputs.uniform.height);
        let views = inputs.uniform.total_width / view_w;
        let (cols, rows) = match options.grid {
            None => (views as usize, 1),
            Some((c, r)) => (c, r),
        };
        if cols == 0 || rows == 0 || cols * rows < views as usize {
            return Err(BackendError::Display(format!(
                "a grid of {cols}x{rows} panels cannot hold {views} views"
            )));
        }
        let (w, oh) = (
            u32::try_from(cols).ok().and_then(|c| c.checked_mul(view_w)),
            u32::try_from(rows).ok().and_then(|r| r.checked_mul(h)),
        );
        let max_side = self.ctx.device.limits().max_texture_dimension_2d;
        let (w, oh) = match (w, oh) {
            (Some(w), Some(oh)) if w <= max_side && oh <= max_side => (w, oh),
            _ => {
                return Err(BackendError::Display(format!(
                    "{cols}x{rows} panels of {view_w}x{h} exceed the device's texture limit of \
                     {max_side}"
                )))
            }
        };
        let window = match options.window {
            Some(win) => Image::new(1, 1, 1)
                .resolve_window(Some(win))
                .map_err(|e| BackendError::Display(e.to_string()))?,
            None => self.auto_window(options.colour.as_ref())?,
        };
        inputs.uniform.low = window.0 as f32;
        inputs.uniform.inv_range = (1.0 / (window.1 - window.0)) as f32;
        inputs.uniform.cols = cols as u32;
        inputs.uniform.out_width = w;
        inputs.uniform.out_height = oh;
        let ub = self.uniform_buffer(&inputs.uniform);
        let ob = self.offsets_buffer(options.colour.as_ref());
        if self.shown.as_ref().is_none_or(|d| d.size != (w, oh)) {
            let texture = self.ctx.device.create_texture(&wgpu::TextureDescriptor {
                label: Some("wavesplat display"),
                size: wgpu::Extent3d {
                    width: w,
                    height: oh,
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
                size: (w, oh),
            });
        }
        let shown = self.shown.as_ref().expect("created above");
        let view = shown
            .texture
            .create_view(&wgpu::TextureViewDescriptor::default());
        let bind = self.bind_display(
            &self.display,
            &ub,
            &ob,
            wgpu::BindGroupEntry {
                binding: 3,
                resource: wgpu::BindingResource::TextureView(&view),
            },
        );
        let mut encoder = self
            .ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor::default());
        {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor::default());
            pass.set_pipeline(&self.display);
            pass.set_bind_group(0, &bind, &[]);
            pass.dispatch_workgroups(w.div_ceil(8), oh.div_ceil(8), 1);
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
        self.ctx.read_rgba8(&shown.texture)
    }
}
