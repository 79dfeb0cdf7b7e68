//! The window's surface: a graphics context opened for the window (a software display attached
//! when the image is made on the host), a host image uploaded to the texture drawn, the texture
//! blitted to the surface and presented, with the surface's upkeep (lost, outdated, minimised).

use super::{report, Frames, Gfx};
use crate::backend::GpuContext;
use crate::window::controls::{arrange, ViewState};
use crate::window::soft::SoftDisplay;
use crate::window::{Context, Result, WindowError};
use std::sync::Arc;
use winit::dpi::PhysicalSize;
use winit::window::Window;

/// Whether the window draws the display pass's texture: the GPU backend's image, shown where
/// it was accumulated. Not on an sRGB-only surface: the pass writes linear `Rgba8Unorm`, which
/// such a surface would brighten (host images are uploaded as sRGB there).
pub(super) fn shown_on_device(gpu_backend: bool, g: &Gfx) -> bool {
    gpu_backend && !g.config.format.is_srgb()
}

/// Uploads the session's host image, arranged in `panels` and mapped through the state's
/// window, to the texture the window draws; returns its size.
pub(super) fn upload(
    g: &mut Gfx,
    frames: &mut Frames,
    state: &ViewState,
    panels: (usize, usize),
) -> Result<(u32, u32)> {
    let image = frames.session.image().context("reading the image")?;
    upload_image(g, image, state, panels)
}

/// Uploads `image` (a host image: the session's, or a time point's kept from before) as the
/// texture shown, through the state's display window.
pub(super) fn upload_image(
    g: &mut Gfx,
    image: crate::Image,
    state: &ViewState,
    panels: (usize, usize),
) -> Result<(u32, u32)> {
    let window = Some(state.display_window(&image));
    let image = arrange(image, panels);
    let (w, h) = (image.width as u32, image.height as u32);
    if let Some(soft) = g.soft.as_mut() {
        let words = image.to_rgb_words(window).context("converting the image")?;
        soft.set_image(words, image.width, image.height);
        return Ok((w, h));
    }
    let rgba = image.to_rgba8(window).context("converting the image")?;
    if g.uploaded.as_ref().map(|t| (t.width(), t.height())) != Some((w, h)) {
        g.uploaded = Some(g.ctx.device().create_texture(&wgpu::TextureDescriptor {
            label: Some("wavesplat view image"),
            size: wgpu::Extent3d {
                width: w,
                height: h,
                depth_or_array_layers: 1,
            },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: if g.config.format.is_srgb() {
                wgpu::TextureFormat::Rgba8UnormSrgb
            } else {
                wgpu::TextureFormat::Rgba8Unorm
            },
            usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
            view_formats: &[],
        }));
    }
    let t = g.uploaded.clone().expect("made above");
    g.ctx.queue().write_texture(
        t.as_image_copy(),
        &rgba,
        wgpu::TexelCopyBufferLayout {
            offset: 0,
            bytes_per_row: Some(4 * w),
            rows_per_image: Some(h),
        },
        t.size(),
    );
    let v = t.create_view(&wgpu::TextureViewDescriptor::default());
    g.texture = Some((t, v));
    Ok((w, h))
}

/// Opens a graphics context that can draw to `window` and configures the window's surface on
/// it (at start, and again after the device was lost).
pub(super) fn open_display(
    display: &winit::event_loop::OwnedDisplayHandle,
    window: Arc<Window>,
) -> Result<Gfx> {
    let instance = wgpu::Instance::new(wgpu::InstanceDescriptor::new_with_display_handle_from_env(
        Box::new(display.clone()),
    ));
    let surface = instance
        .create_surface(window.clone())
        .context("creating a wgpu surface for the window")?;
    let adapter = pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions {
        power_preference: wgpu::PowerPreference::from_env().unwrap_or_default(),
        compatible_surface: Some(&surface),
        ..Default::default()
    }))
    .context("no graphics adapter can draw to this window (WGPU_BACKEND chooses the API)")?;
    let ctx = GpuContext::from_adapter(instance, adapter).context("opening the graphics device")?;
    let size = window.inner_size();
    let caps = surface.get_capabilities(ctx.adapter());
    let format = caps
        .formats
        .iter()
        .copied()
        .find(|f| !f.is_srgb())
        .or_else(|| caps.formats.first().copied())
        .ok_or_else(|| WindowError::Invalid("the surface offers no texture format".into()))?;
    let config = wgpu::SurfaceConfiguration {
        usage: wgpu::TextureUsages::RENDER_ATTACHMENT,
        format,
        width: size.width.max(1),
        height: size.height.max(1),
        present_mode: wgpu::PresentMode::AutoVsync,
        desired_maximum_frame_latency: 2,
        alpha_mode: caps
            .alpha_modes
            .first()
            .copied()
            .unwrap_or(wgpu::CompositeAlphaMode::Auto),
        view_formats: vec![],
        ..surface
            .get_default_config(ctx.adapter(), size.width.max(1), size.height.max(1))
            .ok_or_else(|| {
                WindowError::Invalid("the surface is not supported by the adapter".into())
            })?
    };
    if size.width > 0 && size.height > 0 {
        surface.configure(ctx.device(), &config);
    }
    // Linear filtering: an image drawn smaller than the window (a drag, or a view magnified
    // beyond `--max-pixels-per-voxel`) is shown interpolated, not in blocks.
    let blitter = wgpu::util::TextureBlitterBuilder::new(ctx.device(), format)
        .sample_type(wgpu::FilterMode::Linear)
        .build();
    Ok(Gfx {
        soft: None,
        surface,
        config,
        blitter,
        texture: None,
        uploaded: None,
        ctx,
        window,
    })
}

/// Shows the image through a [`SoftDisplay`] when the image is made on the host and the
/// window's device is a software one (unless `WAVESPLAT_DISPLAY=device`): drawing a texture on
/// it costs more than a frame at a workstation's window size.
pub(super) fn attach_soft_display(
    g: &mut Gfx,
    display: &winit::event_loop::OwnedDisplayHandle,
    gpu_backend: bool,
) {
    let forced_device = std::env::var("WAVESPLAT_DISPLAY").is_ok_and(|v| v == "device");
    if gpu_backend || forced_device || !g.ctx.is_software() {
        return;
    }
    match SoftDisplay::new(display, g.window.clone()) {
        Ok(soft) => g.soft = Some(soft),
        // The wgpu surface still shows the image, only more slowly.
        Err(e) => tracing::warn!(
            "drawing through {} instead of from the host: {}",
            g.ctx.info().name,
            report(&e)
        ),
    }
}

/// Draws the image texture over the whole surface and presents it, reconfiguring the surface
/// when it is outdated and recreating it when it is lost.
pub(super) fn present(g: &mut Gfx, size: PhysicalSize<u32>, smooth: bool) -> Result<()> {
    if let Some(soft) = g.soft.as_mut() {
        return soft.present(size, smooth);
    }
    if (g.config.width, g.config.height) != (size.width, size.height) {
        g.config.width = size.width;
        g.config.height = size.height;
        g.surface.configure(g.ctx.device(), &g.config);
    }
    let frame = match g.surface.get_current_texture() {
        wgpu::CurrentSurfaceTexture::Success(t) => t,
        wgpu::CurrentSurfaceTexture::Suboptimal(t) => {
            // Draw this one, then reconfigure for the next.
            draw(g, &t);
            g.ctx.queue().present(t);
            g.surface.configure(g.ctx.device(), &g.config);
            return Ok(());
        }
        wgpu::CurrentSurfaceTexture::Timeout | wgpu::CurrentSurfaceTexture::Occluded => {
            return Ok(());
        }
        wgpu::CurrentSurfaceTexture::Outdated => {
            g.surface.configure(g.ctx.device(), &g.config);
            return Ok(());
        }
        wgpu::CurrentSurfaceTexture::Lost => {
            tracing::warn!("window surface lost; recreating it");
            g.surface = g
                .ctx
                .instance()
                .create_surface(g.window.clone())
                .context("recreating the window's surface")?;
            g.surface.configure(g.ctx.device(), &g.config);
            return Ok(());
        }
        other => fail!("the window's surface failed: {other:?}"),
    };
    draw(g, &frame);
    g.ctx.queue().present(frame);
    Ok(())
}

fn draw(g: &Gfx, frame: &wgpu::SurfaceTexture) {
    let target = frame
        .texture
        .create_view(&wgpu::TextureViewDescriptor::default());
    let mut encoder = g
        .ctx
        .device()
        .create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("wavesplat view"),
        });
    match &g.texture {
        Some((_, source)) => g
            .blitter
            .copy(g.ctx.device(), &mut encoder, source, &target),
        None => {
            encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
                label: Some("wavesplat clear"),
                color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                    view: &target,
                    resolve_target: None,
                    depth_slice: None,
                    ops: wgpu::Operations {
                        load: wgpu::LoadOp::Clear(wgpu::Color::BLACK),
                        store: wgpu::StoreOp::Store,
                    },
                })],
                ..Default::default()
            });
        }
    }
    g.ctx.queue().submit([encoder.finish()]);
}
