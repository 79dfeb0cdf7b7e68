//! Rendered images and their output: the [`Image`] type (f32, channels interleaved, row 0 at
//! the top), crops and side-by-side concatenation, PNG writing with window/level (automatic
//! from the percentiles of the image's foreground by default; the same mapping to RGBA8 bytes is what a display
//! shows) and the raw f32 writer used for measurements
//! (H rows of W little-endian f32, channels interleaved); and the one measure by which the
//! tests compare an image with its reference ([`max_relative_difference`]).

use rayon::prelude::*;
use std::io::Write;
use std::path::Path;
use thiserror::Error;

/// Errors writing images.
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum ImageError {
    /// I/O failure.
    #[error("image I/O: {0}")]
    Io(#[from] std::io::Error),
    /// PNG encoder failure.
    #[error("PNG encoding: {0}")]
    Png(#[from] png::EncodingError),
    /// PNG supports 1 (grey) or 3 (RGB) channels here.
    #[error("cannot write {0} channels as PNG (1 or 3 supported)")]
    Channels(usize),
    /// Invalid window.
    #[error("window [{0}, {1}] is empty or not finite")]
    BadWindow(f64, f64),
    /// Frames that cannot make one animation.
    #[error("{0}")]
    Frames(String),
}

/// The largest |image − reference| over the largest |reference| (samples of equal count, in the
/// same order): 0 for identical images, ∞-free for a black reference (the denominator is at
/// least 1e-300).
pub fn max_relative_difference(image: &[f32], reference: &[f32]) -> f64 {
    assert_eq!(image.len(), reference.len(), "images of different sizes");
    let peak = reference.iter().fold(0.0f64, |m, x| m.max(x.abs() as f64));
    image
        .iter()
        .zip(reference)
        .fold(0.0f64, |e, (x, y)| e.max((*x as f64 - *y as f64).abs()))
        / peak.max(1e-300)
}

/// Pixels the automatic window is computed from on every image a display shows: every one in
/// an image up to this size, else every n-th (row-major), enough for its percentiles to within
/// a fraction of a grey level ([`Image::sampled_window`]; the GPU display pass picks the same).
pub const MAX_WINDOW_SAMPLES: usize = 1 << 16;

/// A float image, channels interleaved, row-major, row 0 at the top.
#[derive(Debug, Clone, PartialEq)]
pub struct Image {
    /// Width.
    pub width: usize,
    /// Height.
    pub height: usize,
    /// Channels per pixel.
    pub channels: usize,
    /// Pixels (width · height · channels).
    pub data: Vec<f32>,
}

impl Image {
    /// A zero image.
    pub fn new(width: usize, height: usize, channels: usize) -> Image {
        Image {
            width,
            height,
            channels,
            data: vec![0.0; width * height * channels],
        }
    }

    /// [`max_relative_difference`] of this image against `reference`, which must have the same
    /// width, height and channels (panics otherwise: comparing images of two shapes is a bug of
    /// the caller).
    pub fn relative_difference(&self, reference: &Image) -> f64 {
        assert_eq!(
            (self.width, self.height, self.channels),
            (reference.width, reference.height, reference.channels),
            "images of different shapes"
        );
        max_relative_difference(&self.data, &reference.data)
    }

    /// Value of channel `c` at pixel (x, y).
    pub fn get(&self, x: usize, y: usize, c: usize) -> f32 {
        self.data[(y * self.width + x) * self.channels + c]
    }

    /// One channel as its own image.
    pub fn channel(&self, c: usize) -> Image {
        Image {
            width: self.width,
            height: self.height,
            channels: 1,
            data: self
                .data
                .iter()
                .skip(c)
                .step_by(self.channels.max(1))
                .copied()
                .collect(),
        }
    }

    /// The sub-image at (x0, y0) of size w × h (clipped to the image).
    pub fn crop(&self, x0: usize, y0: usize, w: usize, h: usize) -> Image {
        let x1 = (x0 + w).min(self.width);
        let y1 = (y0 + h).min(self.height);
        let (w, h) = (x1.saturating_sub(x0), y1.saturating_sub(y0));
        let mut out = Image::new(w, h, self.channels);
        for y in 0..h {
            let src = ((y0 + y) * self.width + x0) * self.channels;
            let dst = y * w * self.channels;
            out.data[dst..dst + w * self.channels]
                .copy_from_slice(&self.data[src..src + w * self.channels]);
        }
        out
    }

    /// Images of equal height and channels side by side.
    pub fn hconcat(images: &[Image]) -> Image {
        let height = images.iter().map(|i| i.height).max().unwrap_or(0);
        let channels = images.iter().map(|i| i.channels).max().unwrap_or(1);
        let width: usize = images.iter().map(|i| i.width).sum();
        let mut out = Image::new(width, height, channels);
        let mut x0 = 0;
        for im in images {
            for y in 0..im.height {
                for x in 0..im.width {
                    for c in 0..im.channels {
                        out.data[((y * width) + x0 + x) * channels + c] = im.get(x, y, c);
                    }
                }
            }
            x0 += im.width;
        }
        out
    }

    /// The `lo`/`hi` percentiles (0..=100) of all finite samples.
    pub fn percentiles(&self, lo: f64, hi: f64) -> (f64, f64) {
        let mut v: Vec<f32> = self
            .data
            .iter()
            .copied()
            .filter(|x| x.is_finite())
            .collect();
        if v.is_empty() {
            return (0.0, 1.0);
        }
        // Two selections instead of a sort: the window calls this on every displayed frame.
        let n = v.len();
        let mut at = |p: f64| {
            let i = ((p.clamp(0.0, 100.0) / 100.0) * (n - 1) as f64).round() as usize;
            *v.select_nth_unstable_by(i, |a, b| a.total_cmp(b)).1 as f64
        };
        (at(lo), at(hi))
    }

    /// The automatic window: the 2nd and 99.5th percentiles of the image's foreground, the
    /// pixels more than 5 % of the way from the background (the 1st percentile of all pixels)
    /// to the brightest (the 99.9th). A projection is mostly background, so percentiles of all
    /// pixels put the window's top inside the object and show it as a saturated blob; over the
    /// foreground the object's own range fills the grey scale and the background stays black.
    /// An image with almost no foreground (< 0.5 % of its pixels) falls back to the 1st and 99th
    /// percentiles of all pixels.
    pub fn auto_window(&self) -> (f64, f64) {
        let (background, top) = self.percentiles(1.0, 99.9);
        let cut = background + 0.05 * (top - background);
        let mut foreground: Vec<f32> = self
            .data
            .iter()
            .copied()
            .filter(|x| x.is_finite() && f64::from(*x) > cut)
            .collect();
        if foreground.len() * 200 < self.data.len().max(1) {
            return self.percentiles(1.0, 99.0);
        }
        let n = foreground.len();
        let mut at = |p: f64| {
            let i = ((p / 100.0) * (n - 1) as f64).round() as usize;
            *foreground
                .select_nth_unstable_by(i, |a, b| a.total_cmp(b))
                .1 as f64
        };
        (at(2.0), at(99.5))
    }

    /// The window [`Image::write_png`] uses: `window` when given (checked), else
    /// [`Image::auto_window`]; a flat image (an empty view, nothing splatted yet) gets the unit
    /// above its value, so it shows black rather than mid-grey.
    pub fn resolve_window(&self, window: Option<(f64, f64)>) -> Result<(f64, f64), ImageError> {
        let (mut lo, mut hi) = window.unwrap_or_else(|| self.auto_window());
        if window.is_some() && (!lo.is_finite() || !hi.is_finite() || hi <= lo) {
            return Err(ImageError::BadWindow(lo, hi));
        }
        if hi.partial_cmp(&lo) != Some(std::cmp::Ordering::Greater) {
            if !lo.is_finite() {
                lo = 0.0;
            }
            hi = lo + 1.0;
        }
        Ok((lo, hi))
    }

    /// The automatic window ([`Image::resolve_window`] of `None`) from every n-th pixel of an
    /// image larger than [`MAX_WINDOW_SAMPLES`] pixels (all of a smaller one): what a display
    /// computes for every image it shows, where the selections over all of a workstation-sized
    /// image would cost tens of milliseconds of the frame.
    pub fn sampled_window(&self) -> (f64, f64) {
        let pixels = self.width * self.height;
        let stride = pixels.div_ceil(MAX_WINDOW_SAMPLES).max(1);
        let window = if stride == 1 {
            self.resolve_window(None)
        } else {
            let c = self.channels.max(1);
            let data: Vec<f32> = self
                .data
                .chunks_exact(c)
                .step_by(stride)
                .flatten()
                .copied()
                .collect();
            Image {
                width: data.len() / c,
                height: 1,
                channels: c,
                data,
            }
            .resolve_window(None)
        };
        // Without a window given, resolving never fails.
        window.unwrap_or((0.0, 1.0))
    }

    /// A value mapped through the window `(lo, hi)` to 0..=255 (non-finite values to 0).
    pub fn level(x: f32, (lo, hi): (f64, f64)) -> u8 {
        let t = ((x as f64 - lo) / (hi - lo)).clamp(0.0, 1.0);
        if t.is_finite() {
            // `round` without a libm call (bit for bit): a display converts millions of
            // pixels a frame.
            crate::footprint::round_half_away(t * 255.0) as u8
        } else {
            0
        }
    }

    /// The image as RGBA8 rows (grey repeated in R, G and B; alpha 255) through a window as
    /// [`Image::write_png`] maps it: what a display shows.
    pub fn to_rgba8(&self, window: Option<(f64, f64)>) -> Result<Vec<u8>, ImageError> {
        let mut out = vec![255u8; self.width * self.height * 4];
        self.for_each_rgb(window, out.as_chunks_mut::<4>().0, |d, rgb| {
            d[..3].copy_from_slice(&rgb)
        })?;
        Ok(out)
    }

    /// The image as one 0x00RRGGBB word per pixel through a window, as [`Image::to_rgba8`]
    /// maps it: what a window's host-drawn buffer takes.
    pub fn to_rgb_words(&self, window: Option<(f64, f64)>) -> Result<Vec<u32>, ImageError> {
        let mut out = vec![0u32; self.width * self.height];
        self.for_each_rgb(window, &mut out, |d, [r, g, b]| {
            *d = u32::from_be_bytes([0, r, g, b])
        })?;
        Ok(out)
    }

    /// Writes each pixel's grey (repeated) or RGB levels through `window` ([`Image::level`])
    /// into its element of `out` (one per pixel, row-major) with `put`, rows in parallel: a
    /// workstation window converts two million pixels a frame.
    fn for_each_rgb<T: Send>(
        &self,
        window: Option<(f64, f64)>,
        out: &mut [T],
        put: impl Fn(&mut T, [u8; 3]) + Sync,
    ) -> Result<(), ImageError> {
        if self.channels != 1 && self.channels != 3 {
            return Err(ImageError::Channels(self.channels));
        }
        let w = self.resolve_window(window)?;
        let c = self.channels;
        let row = self.width.max(1);
        out.par_chunks_mut(row)
            .zip(self.data.par_chunks(c * row))
            .for_each(|(dst, src)| {
                for (d, px) in dst.iter_mut().zip(src.chunks_exact(c)) {
                    let rgb = if c == 1 {
                        [Image::level(px[0], w); 3]
                    } else {
                        [0, 1, 2].map(|k| Image::level(px[k], w))
                    };
                    put(d, rgb);
                }
            });
        Ok(())
    }

    /// Writes an 8-bit PNG (grey or RGB) mapping `window = (low, high)` to 0..255; `None`
    /// uses [`Image::auto_window`].
    pub fn write_png(&self, path: &Path, window: Option<(f64, f64)>) -> Result<(), ImageError> {
        let colour = match self.channels {
            1 => png::ColorType::Grayscale,
            3 => png::ColorType::Rgb,
            c => return Err(ImageError::Channels(c)),
        };
        let w = self.resolve_window(window)?;
        let bytes: Vec<u8> = self.data.iter().map(|x| Image::level(*x, w)).collect();
        let file = std::io::BufWriter::new(std::fs::File::create(path)?);
        let mut enc = png::Encoder::new(file, self.width as u32, self.height as u32);
        enc.set_color(colour);
        enc.set_depth(png::BitDepth::Eight);
        let mut writer = enc.write_header()?;
        writer.write_image_data(&bytes)?;
        Ok(())
    }

    /// Writes `frames` (of one size and channel count, at least one) as an animated PNG
    /// (APNG: every viewer that does not animate shows the first frame) through one `window`
    /// (a series is compared across its frames), each shown `delay_ms` milliseconds, looping.
    pub fn write_animated_png(
        frames: &[Image],
        path: &Path,
        window: (f64, f64),
        delay_ms: u16,
    ) -> Result<(), ImageError> {
        let first = frames
            .first()
            .ok_or(ImageError::Frames("an animation of no frames".into()))?;
        if frames
            .iter()
            .any(|f| (f.width, f.height, f.channels) != (first.width, first.height, first.channels))
        {
            return Err(ImageError::Frames("frames of different sizes".into()));
        }
        let colour = match first.channels {
            1 => png::ColorType::Grayscale,
            3 => png::ColorType::Rgb,
            c => return Err(ImageError::Channels(c)),
        };
        let w = first.resolve_window(Some(window))?;
        let file = std::io::BufWriter::new(std::fs::File::create(path)?);
        let mut enc = png::Encoder::new(file, first.width as u32, first.height as u32);
        enc.set_color(colour);
        enc.set_depth(png::BitDepth::Eight);
        enc.set_animated(frames.len() as u32, 0)?;
        enc.set_frame_delay(delay_ms.max(1), 1000)?;
        let mut writer = enc.write_header()?;
        for f in frames {
            let bytes: Vec<u8> = f.data.iter().map(|x| Image::level(*x, w)).collect();
            writer.write_image_data(&bytes)?;
        }
        writer.finish()?;
        Ok(())
    }

    /// Writes H rows of W little-endian f32 (channels interleaved).
    pub fn write_raw(&self, path: &Path) -> Result<(), ImageError> {
        let mut file = std::io::BufWriter::new(std::fs::File::create(path)?);
        for x in &self.data {
            file.write_all(&x.to_le_bytes())?;
        }
        file.flush()?;
        Ok(())
    }
}

#[cfg(test)]
mod window_tests {
    use super::*;

    /// The window's host-drawn words carry the display's RGBA bytes pixel for pixel (grey and
    /// RGB, a NaN and values outside the window included), and other channel counts are
    /// refused by both.
    #[test]
    fn rgb_words_pack_the_rgba_bytes() {
        for channels in [1, 3] {
            let mut img = Image::new(5, 3, channels);
            for (i, v) in img.data.iter_mut().enumerate() {
                *v = i as f32 * 0.37 - 2.0;
            }
            img.data[4] = f32::NAN;
            for window in [None, Some((-1.0, 3.0))] {
                let rgba = img.to_rgba8(window).unwrap();
                let words = img.to_rgb_words(window).unwrap();
                assert_eq!(words.len(), 15);
                for (w, p) in words.iter().zip(rgba.chunks_exact(4)) {
                    assert_eq!(p[3], 255);
                    assert_eq!(*w, u32::from_be_bytes([0, p[0], p[1], p[2]]));
                }
            }
        }
        let two = Image::new(2, 2, 2);
        assert!(matches!(two.to_rgba8(None), Err(ImageError::Channels(2))));
        assert!(matches!(
            two.to_rgb_words(None),
            Err(ImageError::Channels(2))
        ));
    }

    /// The sampled window of a workstation-sized image (a projection: a bright disc on a dark
    /// background, with a NaN) is within a grey level of the window over every pixel, and a
    /// small image's is exactly that window.
    #[test]
    fn the_sampled_window_matches_the_full_one_within_a_grey_level() {
        let (w, h) = (1920, 1080);
        let mut data: Vec<f32> = (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as f32 - 960.0, (i / w) as f32 - 540.0);
                let r2 = (x * x + y * y) / (400.0 * 400.0);
                0.01 + (1.0 - r2).max(0.0).sqrt() * (1.0 + 0.3 * (x / 37.0).sin())
            })
            .collect();
        data[12345] = f32::NAN;
        let big = Image {
            width: w,
            height: h,
            channels: 1,
            data,
        };
        let (lo, hi) = big.resolve_window(None).unwrap();
        let (a, b) = big.sampled_window();
        let level = (hi - lo) / 255.0;
        assert!(
            (a - lo).abs() < level && (b - hi).abs() < level,
            "sampled ({a}, {b}) against ({lo}, {hi})"
        );
        let small = Image {
            width: 200,
            height: 100,
            channels: 3,
            data: (0..200 * 100 * 3).map(|i| (i % 977) as f32).collect(),
        };
        assert_eq!(small.sampled_window(), small.resolve_window(None).unwrap());
    }

    #[test]
    fn an_empty_view_shows_black_and_a_window_maps_its_ends() {
        let empty = Image {
            width: 4,
            height: 2,
            channels: 1,
            data: vec![0.0; 8],
        };
        let rgba = empty.to_rgba8(None).unwrap();
        assert!(rgba
            .chunks_exact(4)
            .all(|p| p[0] == 0 && p[1] == 0 && p[2] == 0 && p[3] == 255));
        let ramp = Image {
            width: 101,
            height: 1,
            channels: 1,
            data: (0..101).map(|i| i as f32).collect(),
        };
        let rgba = ramp.to_rgba8(None).unwrap();
        assert_eq!(rgba[0], 0);
        assert_eq!(rgba[100 * 4], 255);
    }

    /// A projection of a ball on a large background: the dome's values crowd near its top.
    fn dome(n: usize) -> Image {
        let c = (n as f32 - 1.0) / 2.0;
        let r = n as f32 / 4.0;
        let data = (0..n * n)
            .map(|i| {
                let (x, y) = ((i % n) as f32 - c, (i / n) as f32 - c);
                let d2 = r * r - x * x - y * y;
                if d2 > 0.0 {
                    1000.0 * d2.sqrt()
                } else {
                    0.0
                }
            })
            .collect();
        Image {
            width: n,
            height: n,
            channels: 1,
            data,
        }
    }

    #[test]
    fn the_automatic_window_spreads_the_object_not_the_background() {
        let img = dome(200);
        let (lo, hi) = img.resolve_window(None).unwrap();
        let max = img.data.iter().fold(0f32, |m, &x| m.max(x)) as f64;
        assert!(lo > 0.0 && hi <= max, "({lo}, {hi}) for values 0..{max}");
        let inside: Vec<u8> = img
            .data
            .iter()
            .filter(|&&x| x > 0.0)
            .map(|&x| Image::level(x, (lo, hi)))
            .collect();
        let saturated = inside.iter().filter(|&&v| v == 255).count();
        assert!(
            saturated * 100 <= inside.len(),
            "{saturated} of {} object pixels saturated",
            inside.len()
        );
        // The object's median is mid-grey, not near white; the background stays black.
        let mut sorted = inside.clone();
        sorted.sort_unstable();
        let median = sorted[sorted.len() / 2];
        assert!((96..=224).contains(&median), "median grey {median}");
        assert_eq!(Image::level(0.0, (lo, hi)), 0);
        // With (almost) no foreground: all pixels' 1st and 99th percentiles.
        let mut speck = Image {
            width: 100,
            height: 100,
            channels: 1,
            data: vec![0.0; 10_000],
        };
        speck.data[5] = 1.0;
        assert_eq!(speck.auto_window(), speck.percentiles(1.0, 99.0));
    }
}
