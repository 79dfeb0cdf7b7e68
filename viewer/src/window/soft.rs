//! The window's display on a software graphics device: the host image, stretched to the window
//! by nearest sample (bilinear where it is magnified three times or more), written to the window's shared-memory buffer (softbuffer) instead of drawn
//! as a texture over a wgpu surface. On Mesa's llvmpipe, drawing and presenting a 1920×1080
//! surface cost 27–68 ms a frame, above a 60 Hz budget before anything was splatted; written
//! here it costs 2–6 ms (the `present_ms` of the window's `image shown` trace events). It owns
//! the pixel buffer and the stretch; which display a window takes is the shell's choice.

use super::{Result, WindowError};
use rayon::prelude::*;
use std::num::NonZeroU32;
use std::sync::Arc;
use winit::dpi::PhysicalSize;
use winit::event_loop::OwnedDisplayHandle;
use winit::window::Window;

/// The window's softbuffer surface and the image it shows.
pub(super) struct SoftDisplay {
    surface: softbuffer::Surface<OwnedDisplayHandle, Arc<Window>>,
    /// The image as 0x00RRGGBB words, row-major, and its size.
    image: Vec<u32>,
    width: usize,
    height: usize,
}

impl SoftDisplay {
    /// Opens a softbuffer surface on `window` of the display `display`.
    pub(super) fn new(display: &OwnedDisplayHandle, window: Arc<Window>) -> Result<SoftDisplay> {
        let context = softbuffer::Context::new(display.clone()).map_err(|e| {
            failed(
                "opening the display for drawing from the host (softbuffer)",
                e,
            )
        })?;
        let surface = softbuffer::Surface::new(&context, window)
            .map_err(|e| failed("creating the window's host-drawn surface (softbuffer)", e))?;
        Ok(SoftDisplay {
            surface,
            image: Vec::new(),
            width: 0,
            height: 0,
        })
    }

    /// Takes the image to show: 0x00RRGGBB words, rows of `width` pixels, display-ready
    /// values (shown as they are, as on a non-sRGB surface).
    pub(super) fn set_image(&mut self, words: Vec<u32>, width: usize, height: usize) {
        self.image = words;
        self.width = width;
        self.height = height;
    }

    /// Writes the image stretched over a window of `size` (black without an image) and shows it;
    /// `smooth`: interpolated wherever it is magnified (a view at rest), else only from
    /// [`BILINEAR_FROM`] times.
    pub(super) fn present(&mut self, size: PhysicalSize<u32>, smooth: bool) -> Result<()> {
        let (Some(w), Some(h)) = (NonZeroU32::new(size.width), NonZeroU32::new(size.height)) else {
            return Ok(());
        };
        self.surface
            .resize(w, h)
            .map_err(|e| failed("resizing the window's host-drawn surface", e))?;
        let mut buffer = self
            .surface
            .buffer_mut()
            .map_err(|e| failed("reaching the window's host-drawn surface", e))?;
        stretch(
            &self.image,
            (self.width, self.height),
            &mut buffer,
            (w.get() as usize, h.get() as usize),
            smooth,
        );
        buffer
            .present()
            .map_err(|e| failed("showing the window's host-drawn surface", e))
    }
}

/// A softbuffer error with the step that failed (its errors are not `Send`: their text is kept).
fn failed(what: &str, e: softbuffer::SoftBufferError) -> WindowError {
    WindowError::Failed {
        what: what.to_string(),
        source: e.to_string().into(),
    }
}

/// Fills `out` (`out_size`, row-major) with `image` (`size`) stretched by nearest sample: output
/// pixel (x, y) takes the image pixel whose cell holds the output pixel's centre, as a texture
/// drawn over the whole window with nearest filtering; black where there is no image. Magnified
/// [`BILINEAR_FROM`] times or more in both axes, or at all when `smooth`, it interpolates
/// instead.
pub(super) fn stretch(
    image: &[u32],
    size: (usize, usize),
    out: &mut [u32],
    out_size: (usize, usize),
    smooth: bool,
) {
    let (w, h) = size;
    let (ow, oh) = out_size;
    if w == 0 || h == 0 || image.len() < w * h {
        out.fill(0);
        return;
    }
    let magnified = ow > w && oh > h;
    if (smooth && magnified) || (ow >= BILINEAR_FROM * w && oh >= BILINEAR_FROM * h) {
        return stretch_bilinear(image, size, out, out_size);
    }
    let source = |o: usize, n: usize, on: usize| ((2 * o + 1) * n / (2 * on)).min(n - 1);
    let columns: Vec<usize> = (0..ow).map(|x| source(x, w, ow)).collect();
    out.par_chunks_mut(ow.max(1))
        .take(oh)
        .enumerate()
        .for_each(|(y, row)| {
            let line = &image[source(y, h, oh) * w..][..w];
            if ow == w {
                row.copy_from_slice(line);
            } else {
                for (p, &x) in row.iter_mut().zip(&columns) {
                    *p = line[x];
                }
            }
        });
}

/// The magnification (in both axes) from which [`stretch`] interpolates on every frame: below
/// it a nearest sample's blocks are at most two pixels wide, and nearest is cheaper on the drag
/// frames that show a half-size image (a view at rest is interpolated at any magnification).
const BILINEAR_FROM: usize = 3;

/// [`stretch`] by bilinear interpolation of each 8-bit channel, about the pixels' centres
/// (the edge held beyond the outermost ones), as a texture drawn with linear filtering.
fn stretch_bilinear(
    image: &[u32],
    size: (usize, usize),
    out: &mut [u32],
    out_size: (usize, usize),
) {
    let (w, h) = size;
    let (ow, oh) = out_size;
    // The lower source sample of output position `o` and the upper one's weight in 1/256.
    let taps = |o: usize, n: usize, on: usize| -> (usize, usize, u32) {
        let s = ((o as f64 + 0.5) * n as f64 / on as f64 - 0.5).clamp(0.0, (n - 1) as f64);
        let lo = s.floor() as usize;
        (
            lo,
            (lo + 1).min(n - 1),
            ((s - lo as f64) * 256.0).round() as u32,
        )
    };
    let columns: Vec<(usize, usize, u32)> = (0..ow).map(|x| taps(x, w, ow)).collect();
    let mix = |a: u32, b: u32, t: u32| -> u32 {
        let channel = |shift: u32| {
            let (x, y) = ((a >> shift) & 0xff, (b >> shift) & 0xff);
            ((x * (256 - t) + y * t + 128) >> 8) << shift
        };
        channel(16) | channel(8) | channel(0)
    };
    out.par_chunks_mut(ow.max(1))
        .take(oh)
        .enumerate()
        .for_each(|(y, row)| {
            let (y0, y1, ty) = taps(y, h, oh);
            let (top, bottom) = (&image[y0 * w..][..w], &image[y1 * w..][..w]);
            for (p, &(x0, x1, tx)) in row.iter_mut().zip(&columns) {
                *p = mix(
                    mix(top[x0], top[x1], tx),
                    mix(bottom[x0], bottom[x1], tx),
                    ty,
                );
            }
        });
}

#[cfg(test)]
mod tests {
    use super::stretch;

    #[test]
    fn a_view_at_rest_is_interpolated_at_any_magnification() {
        let image = [0x000000u32, 0x808080, 0x000000, 0x808080]; // 2 × 2
        let mut nearest = vec![0u32; 16];
        stretch(&image, (2, 2), &mut nearest, (4, 4), false);
        assert!(nearest.iter().all(|&p| p == 0 || p == 0x808080));
        let mut smooth = vec![0u32; 16];
        stretch(&image, (2, 2), &mut smooth, (4, 4), true);
        // Columns 1 and 2 lie between the two samples: a quarter and three quarters of grey.
        assert_eq!(&smooth[..4], &[0, 0x202020, 0x606060, 0x808080]);
        // Not magnified: the same either way.
        let mut same = vec![0u32; 4];
        stretch(&image, (2, 2), &mut same, (2, 2), true);
        assert_eq!(same, image);
    }

    #[test]
    fn a_large_magnification_interpolates_each_channel() {
        // 2 × 1: black and white (grey levels in all three channels); magnified 4 × 4 times.
        let image = [0x000000u32, 0xffffff];
        let mut out = vec![0u32; 8 * 4];
        stretch(&image, (2, 1), &mut out, (8, 4), false);
        let grey = |p: u32| (p & 0xff, (p >> 8) & 0xff, (p >> 16) & 0xff);
        for row in out.chunks(8) {
            // Centres at 0.5 + k: the first and last two outputs hold the edges, between them
            // a ramp (source position (x + 0.5) / 4 − 0.5).
            assert_eq!(grey(row[0]), (0, 0, 0));
            assert_eq!(grey(row[7]), (255, 255, 255));
            let ramp: Vec<u32> = row.iter().map(|&p| p & 0xff).collect();
            assert!(ramp.windows(2).all(|w| w[0] <= w[1]), "{ramp:?}");
            assert_eq!(ramp[4] & 0xff, 159); // s = 0.625: 0.625 × 255
            assert!(row
                .iter()
                .all(|&p| grey(p).0 == grey(p).1 && grey(p).1 == grey(p).2));
        }
    }

    #[test]
    fn stretching_takes_the_nearest_sample_and_keeps_an_equal_size() {
        let image: Vec<u32> = (0..6).collect(); // 3 × 2
        let mut same = vec![9; 6];
        stretch(&image, (3, 2), &mut same, (3, 2), false);
        assert_eq!(same, image);
        let mut double = vec![9; 24]; // 6 × 4
        stretch(&image, (3, 2), &mut double, (6, 4), false);
        assert_eq!(
            double,
            [0, 0, 1, 1, 2, 2, 0, 0, 1, 1, 2, 2, 3, 3, 4, 4, 5, 5, 3, 3, 4, 4, 5, 5]
        );
        let mut shrunk = vec![9; 1];
        stretch(&image, (3, 2), &mut shrunk, (1, 1), false);
        assert_eq!(shrunk, [4]);
        let mut odd = vec![9; 5 * 3];
        stretch(&image, (3, 2), &mut odd, (5, 3), false);
        // Columns 0..5 of 5 map to 0, 0, 1, 2, 2; rows 0..3 of 3 to 0, 1, 1.
        assert_eq!(&odd[..5], &[0, 0, 1, 2, 2]);
        assert_eq!(&odd[10..], &[3, 3, 4, 5, 5]);
        let mut none = vec![9; 4];
        stretch(&[], (0, 0), &mut none, (2, 2), false);
        assert_eq!(none, [0; 4]);
    }
}
