//! Display values: images rendered in a volume's coded channels back to what the volume holds.
//! The coding is affine per voxel — an offset (an intensity volume's face median, a colour
//! volume's origin colour) subtracted, then for colour a linear projection (YIQ, PCA, RGB) — so
//! per pixel value = M⁻¹·c + offset·length, with M the header's colour basis (identity for
//! intensity) and length the ray's path through the volume (the offset was subtracted from every
//! voxel it crossed; with depth cueing, the cued length ∫ e^(−k·dist) along that path),
//! averaged over the pixel as the splats are; `codec::format::ColorInfo::to_rgb` holds the
//! formula and `codec::view::Camera::chord` / `cued_chord` the length.

use crate::backend::gpu::ColorMap;
use crate::image::Image;
use crate::RenderError;
use std::sync::Arc;
use wavesplat_codec::format::Header;
use wavesplat_codec::view::{resolve_cue, Camera, ResolvedCue, ViewSpec};

/// Converts `image` (views side by side, one camera each, rendered with depth cue `cue` if
/// any) to display values: RGB for a colour volume, the intensity plus its offset's share for
/// an intensity volume (unchanged when the offset is zero).
pub fn to_rgb(
    image: &Image,
    header: &Header,
    cameras: &[Camera],
    cue: Option<&ResolvedCue>,
) -> Result<Image, RenderError> {
    let lengths = PathLengths::new(header, cameras, cue, image.width, image.height);
    lengths.apply(image, header)
}

/// The path length through the volume of every pixel of an image (views side by side), for
/// one view: what an offset or origin colour contributes per pixel, the line integral of a
/// constant in every voxel of the file's spline family ([`Camera::spline_chord`]). Computing
/// it samples every silhouette pixel, so a session keeps it while the view and the image size
/// stay the same ([`PathLengths::matches`]).
#[derive(Debug, Clone)]
pub struct PathLengths {
    cameras: Vec<Camera>,
    cue: Option<ResolvedCue>,
    width: usize,
    height: usize,
    /// Per view, the pixels' (cued) path lengths, row-major; empty when nothing was subtracted.
    lengths: Vec<Vec<f64>>,
}

impl PathLengths {
    /// The path lengths `header`'s offset needs (none when it subtracted nothing).
    pub fn new(
        header: &Header,
        cameras: &[Camera],
        cue: Option<&ResolvedCue>,
        width: usize,
        height: usize,
    ) -> PathLengths {
        let views = cameras.len().max(1);
        let w = width / views;
        let dims = header.geometry.dims;
        let order = header.geometry.family.order();
        let lengths = if has_offset(header) {
            cameras
                .iter()
                .map(|cam| {
                    pixel_chords(w, height, order > 1, |xs, ys| {
                        cam.spline_chord(dims, order, xs, ys, cue)
                    })
                })
                .collect()
        } else {
            Vec::new()
        };
        PathLengths {
            cameras: cameras.to_vec(),
            cue: cue.copied(),
            width,
            height,
            lengths,
        }
    }

    /// Whether these lengths are the ones for this view and image size.
    pub fn matches(
        &self,
        cameras: &[Camera],
        cue: Option<&ResolvedCue>,
        width: usize,
        height: usize,
    ) -> bool {
        self.cameras == cameras
            && self.cue.as_ref() == cue
            && self.width == width
            && self.height == height
    }

    /// `image` in display values ([`to_rgb`]) with these lengths.
    pub fn apply(&self, image: &Image, header: &Header) -> Result<Image, RenderError> {
        // The header's channel count is 1 exactly for intensity (checked on read).
        let channels = header.channels;
        if image.channels != channels || (channels == 1 && !has_offset(header)) {
            return Ok(image.clone());
        }
        if (image.width, image.height) != (self.width, self.height) {
            return Err(RenderError::Unsupported(
                "path lengths computed for another image size",
            ));
        }
        let inv = inverse_basis(header)?;
        let mut out = Image::new(image.width, image.height, channels);
        for y in 0..image.height {
            for x in 0..image.width {
                let c = [0, 1, 2].map(|k| {
                    if k < channels {
                        image.get(x, y, k) as f64
                    } else {
                        0.0
                    }
                });
                let rgb = header.color.to_rgb(&inv, c, self.length_at(x, y));
                for (r, v) in rgb.iter().take(channels).enumerate() {
                    out.data[(y * image.width + x) * channels + r] = *v as f32;
                }
            }
        }
        Ok(out)
    }
}

impl PathLengths {
    /// The path length of pixel (`x`, `y`) of the whole image (0 when nothing was subtracted).
    fn length_at(&self, x: usize, y: usize) -> f64 {
        let w = (self.width / self.cameras.len().max(1)).max(1);
        match self.lengths.get(x / w) {
            Some(view) => view[y * w + x % w],
            None => 0.0,
        }
    }

    /// The display pass's twin of [`PathLengths::apply`] for `header`: the inverse colour
    /// basis as the matrix and `mean · length` as the per-pixel offsets; `None` when the image
    /// is shown as accumulated (an intensity volume with nothing subtracted).
    pub fn color_map(&self, header: &Header) -> Result<Option<ColorMap>, RenderError> {
        let channels = header.channels;
        let offsets = has_offset(header);
        if channels == 1 && !offsets {
            return Ok(None);
        }
        let matrix = if channels == 3 {
            Some(inverse_basis(header)?.map(|row| row.map(|v| v as f32)))
        } else {
            None
        };
        let offset = if offsets {
            let mean = header.color.mean;
            let mut out = Vec::with_capacity(self.width * self.height * channels);
            for y in 0..self.height {
                for x in 0..self.width {
                    let len = self.length_at(x, y);
                    out.extend(mean[..channels].iter().map(|m| (m * len) as f32));
                }
            }
            Some(Arc::from(out))
        } else {
            None
        };
        Ok(Some(ColorMap { matrix, offset }))
    }
}

/// The inverse of the header's colour basis (refused when singular).
fn inverse_basis(header: &Header) -> Result<[[f64; 3]; 3], RenderError> {
    header.color.inverse_basis().ok_or(RenderError::Unsupported(
        "the header's colour basis is singular",
    ))
}

/// Whether the header's coding subtracted anything per voxel (an offset or origin colour).
fn has_offset(header: &Header) -> bool {
    header.color.mean[..header.channels.min(3)]
        .iter()
        .any(|m| *m != 0.0)
}

/// [`to_rgb`] for an image rendered for `spec`: its cameras and its resolved depth cue.
pub fn to_rgb_for_spec(
    image: &Image,
    header: &Header,
    spec: &ViewSpec,
) -> Result<Image, RenderError> {
    let cameras = spec.cameras(&header.geometry)?;
    let cue = match &spec.view.cue {
        Some(c) => Some(resolve_cue(c, &cameras[0], &header.geometry)?),
        None => None,
    };
    to_rgb(image, header, &cameras, cue.as_ref())
}

/// Sub-pixels per side where a pixel's chord with kinks (Haar's voxel box) is averaged by
/// sampling.
const CHORD_SAMPLES: usize = 16;

/// Gauss–Legendre nodes on [0, 1] and weights (4 points) for a pixel's smooth chord (a spline
/// profile's: its line integral is C¹ for linear, C³ for cubic, so a product rule of 4×4
/// points averages it to far below the splats' own error, at 16 evaluations where the
/// midpoint grid takes 256).
const PIXEL_GAUSS_4: [(f64, f64); 4] = [
    (0.069_431_844_202_973_7, 0.173_927_422_568_726_9),
    (0.330_009_478_207_571_9, 0.326_072_577_431_273_1),
    (0.669_990_521_792_428_1, 0.326_072_577_431_273_1),
    (0.930_568_155_797_026_3, 0.173_927_422_568_726_9),
];

/// The (cued) chord length `chord(xs, ys)` through the volume averaged over each pixel of a
/// `w`×`h` view (row major), rows on rayon. The chord is continuous in the screen position
/// and linear away from the silhouette and the projected box edges (Haar's voxel box: kinks
/// along them; a spline's profile (`smooth`): curved within order/2 voxels of a face): where
/// it is linear across a pixel its average is its value at the centre, which then equals the
/// mean of the corners; a pixel where the two differ by more than 1e-7 of the values holds a
/// kink or a curve (or the curvature of a stiff cue) and is averaged on a 16×16 midpoint grid
/// (kinks), or by 4×4-point Gauss–Legendre (`smooth`). (The value at the centre alone is off
/// by up to half a pixel of chord slope on every silhouette pixel: 44 dB on a constant colour
/// volume in PCA space, against 60+ dB with the average.)
fn pixel_chords(
    w: usize,
    h: usize,
    smooth: bool,
    chord: impl Fn(f64, f64) -> f64 + Sync,
) -> Vec<f64> {
    use rayon::prelude::*;
    let corner: Vec<f64> = (0..=h)
        .into_par_iter()
        .flat_map_iter(|y| (0..=w).map(move |x| (x, y)))
        .map(|(x, y)| chord(x as f64, y as f64))
        .collect();
    let at = |x: usize, y: usize| corner[y * (w + 1) + x];
    (0..h)
        .into_par_iter()
        .flat_map_iter(|y| (0..w).map(move |x| (x, y)))
        .map(|(x, y)| {
            let centre = chord(x as f64 + 0.5, y as f64 + 0.5);
            let corners = [at(x, y), at(x + 1, y), at(x, y + 1), at(x + 1, y + 1)];
            let mean = 0.25 * corners.iter().sum::<f64>();
            let scale = corners.iter().fold(centre.abs(), |m, c| m.max(c.abs()));
            if (centre - mean).abs() <= 1e-7 * scale.max(1.0) {
                return centre;
            }
            let (x, y) = (x as f64, y as f64);
            if smooth {
                let mut sum = 0.0;
                for (sy, wy) in PIXEL_GAUSS_4 {
                    for (sx, wx) in PIXEL_GAUSS_4 {
                        sum += wx * wy * chord(x + sx, y + sy);
                    }
                }
                return sum;
            }
            let s = CHORD_SAMPLES;
            let mut sum = 0.0;
            for sy in 0..s {
                for sx in 0..s {
                    let xs = x + (sx as f64 + 0.5) / s as f64;
                    let ys = y + (sy as f64 + 0.5) / s as f64;
                    sum += chord(xs, ys);
                }
            }
            sum / (s * s) as f64
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use wavesplat_codec::view::View;

    /// The pixel chords are the pixel-area averages of the chord: against a 64×64 sampling of
    /// every pixel, within 2e-3 voxels on silhouette pixels, where the centre value alone is off
    /// by far more; and the chords sum to the box's physical volume over the pixel area (zoom²),
    /// for cubic and for anisotropic voxels.
    #[test]
    fn pixel_chords_average_the_chord_over_the_pixel() {
        for spacing in [[1.0f32; 3], [0.7, 1.3, 2.5]] {
            pixel_chords_for(spacing);
        }
    }

    /// The average of `chord` over pixel (x, y) on a 64×64 midpoint grid.
    fn fine_average(chord: &dyn Fn(f64, f64) -> f64, x: usize, y: usize) -> f64 {
        let n = 64;
        let mut sum = 0.0;
        for sy in 0..n {
            for sx in 0..n {
                let xs = x as f64 + (sx as f64 + 0.5) / n as f64;
                let ys = y as f64 + (sy as f64 + 0.5) / n as f64;
                sum += chord(xs, ys);
            }
        }
        sum / (n * n) as f64
    }

    /// A spline's smooth chord by 4×4 Gauss–Legendre points per curved pixel: against a
    /// 64×64 sampling of every pixel, within 1e-4 of the largest chord, for the linear and
    /// cubic profiles, with and without a cue, on anisotropic voxels.
    #[test]
    fn smooth_pixel_chords_average_the_spline_chord_over_the_pixel() {
        let dims = [9, 5, 7];
        let (w, h) = (24, 20);
        for (family, order) in [
            (wavesplat_codec::family::Family::Linear, 2),
            (wavesplat_codec::family::Family::Cubic, 4),
        ] {
            let g = wavesplat_codec::layout::Geometry::new(dims, family, 0, 0)
                .unwrap()
                .with_spacing([0.7, 1.3, 2.5])
                .unwrap();
            let cam = Camera::new(&View::new(0.66, 0.91, w, h), &g).unwrap();
            let cue = wavesplat_codec::view::Cue {
                k: 0.4,
                direction: wavesplat_codec::view::CueDirection::View,
            };
            let cue = resolve_cue(&cue, &cam, &g).unwrap();
            for cue in [None, Some(&cue)] {
                let chord = |xs: f64, ys: f64| cam.spline_chord(dims, order, xs, ys, cue);
                let chords = pixel_chords(w, h, true, chord);
                let peak = chords.iter().fold(0.0f64, |m, c| m.max(*c));
                assert!(peak > 0.0);
                for y in 0..h {
                    for x in 0..w {
                        let avg = fine_average(&chord, x, y);
                        let got = chords[y * w + x];
                        assert!(
                            (got - avg).abs() < 1e-4 * peak,
                            "order {order}, cue {}, pixel ({x}, {y}): {got} vs {avg}",
                            cue.is_some()
                        );
                    }
                }
            }
        }
    }

    fn pixel_chords_for(spacing: [f32; 3]) {
        let dims = [9, 5, 7];
        let (w, h) = (24, 20);
        let g = wavesplat_codec::layout::Geometry::new(
            dims,
            wavesplat_codec::family::Family::Linear,
            0,
            0,
        )
        .unwrap()
        .with_spacing(spacing)
        .unwrap();
        let cam = Camera::new(&View::new(0.66, 0.91, w, h), &g).unwrap();
        let chords = pixel_chords(w, h, false, |xs, ys| cam.chord(dims, xs, ys));
        let mut worst_centre = 0.0f64;
        let mut total = 0.0;
        for y in 0..h {
            for x in 0..w {
                let avg = fine_average(&|xs, ys| cam.chord(dims, xs, ys), x, y);
                let got = chords[y * w + x];
                assert!((got - avg).abs() < 2e-3, "pixel ({x}, {y}): {got} vs {avg}");
                let centre = cam.chord(dims, x as f64 + 0.5, y as f64 + 0.5);
                worst_centre = worst_centre.max((centre - avg).abs());
                total += got;
            }
        }
        assert!(worst_centre > 0.05, "the test view has silhouette pixels");
        let volume = (0..3)
            .map(|a| dims[a] as f64 * f64::from(spacing[a]))
            .product::<f64>();
        let area = total / (cam.zoom * cam.zoom);
        assert!((area - volume).abs() < 1e-3 * volume, "{area} vs {volume}");
    }
}
