//! Display colour: images rendered in a volume's coded colour space (YIQ, PCA or RGB with a
//! mean removed) back to RGB. The projection is linear, so per pixel rgb = M⁻¹·c + mean·length,
//! with M the header's colour basis and length the ray's path through the volume (the mean was
//! subtracted from every voxel it crossed; with depth cueing, the cued length
//! ∫ e^(−k·dist) along that path); `codec::format::ColorInfo::to_rgb` holds the formula and
//! `codec::view::Camera::chord` / `cued_chord` the length.

use crate::image::Image;
use crate::RenderError;
use wavesplat_codec::format::{ColorKind, Header};
use wavesplat_codec::view::{resolve_cue, Camera, ResolvedCue, ViewSpec};

/// Converts `image` (views side by side, one camera each, rendered with depth cue `cue` if
/// any) to RGB; intensity images pass through unchanged.
pub fn to_rgb(
    image: &Image,
    header: &Header,
    cameras: &[Camera],
    cue: Option<&ResolvedCue>,
) -> Result<Image, RenderError> {
    if header.color.kind == ColorKind::Intensity || image.channels != 3 {
        return Ok(image.clone());
    }
    let inv = header
        .color
        .inverse_basis()
        .ok_or(RenderError::Unsupported(
            "the header's colour basis is singular",
        ))?;
    let has_mean = header.color.mean.iter().any(|m| *m != 0.0);
    let views = cameras.len().max(1);
    let w = image.width / views;
    let mut out = Image::new(image.width, image.height, 3);
    for y in 0..image.height {
        for x in 0..image.width {
            let c = [0, 1, 2].map(|k| image.get(x, y, k) as f64);
            let len = match cameras.get(x / w.max(1)) {
                Some(cam) if has_mean => {
                    let (xs, ys) = ((x % w) as f64 + 0.5, y as f64 + 0.5);
                    match cue {
                        Some(c) => cam.cued_chord(header.geometry.dims, xs, ys, c),
                        None => cam.chord(header.geometry.dims, xs, ys),
                    }
                }
                _ => 0.0,
            };
            let rgb = header.color.to_rgb(&inv, c, len);
            for (r, v) in rgb.iter().enumerate() {
                out.data[(y * image.width + x) * 3 + r] = *v as f32;
            }
        }
    }
    Ok(out)
}

/// [`to_rgb`] for an image rendered for `spec`: its cameras and its resolved depth cue.
pub fn to_rgb_for_spec(
    image: &Image,
    header: &Header,
    spec: &ViewSpec,
) -> Result<Image, RenderError> {
    let cameras = spec.cameras(header.geometry.dims)?;
    let cue = match &spec.view.cue {
        Some(c) => Some(resolve_cue(c, &cameras[0], &header.geometry)?),
        None => None,
    };
    to_rgb(image, header, &cameras, cue.as_ref())
}
