//! `wavesplat render`: X-ray images straight from the coefficients of a `.wsp` file by wavelet
//! splatting (the volume is never reconstructed). Optionally only a prefix of the stream (first
//! N coefficients or B bytes), multiview, depth cueing; PNG with window/level and raw f32 out.

use anyhow::{bail, Context, Result};
use clap::Args;
use std::path::PathBuf;
use wavesplat_codec::format::packet::decode_packets;
use wavesplat_codec::format::packet::Coefficient;
use wavesplat_codec::format::{parse_file, ColorKind, Header};
use wavesplat_codec::view::multiview_cameras;
use wavesplat_viewer::{Camera, Cue, CueDirection, Image, RenderOptions, Renderer, View};

/// Arguments of `wavesplat render`.
#[derive(Args, Debug)]
pub struct RenderArgs {
    /// The .wsp file.
    pub input: PathBuf,
    /// Azimuth α of the view (radians, paper §3.1).
    #[arg(long, default_value_t = 0.66, allow_negative_numbers = true)]
    pub alpha: f64,
    /// Elevation β of the view (radians).
    #[arg(long, default_value_t = 0.91, allow_negative_numbers = true)]
    pub beta: f64,
    /// Image size WxH (per view with --multiview).
    #[arg(long, default_value = "256x256")]
    pub size: String,
    /// Pixels per voxel (default: fit the volume).
    #[arg(long)]
    pub zoom: Option<f64>,
    /// Pan of the image centre from the volume centre, in voxels along the screen axes: X,Y.
    #[arg(long, allow_negative_numbers = true)]
    pub pan: Option<String>,
    /// Three views side by side from one set of footprints (paper §3.1).
    #[arg(long)]
    pub multiview: bool,
    /// Depth-cue extinction per voxel (paper §3.2); 0 disables.
    #[arg(long, default_value_t = 0.0)]
    pub cue_k: f64,
    /// Depth-cue direction α,β (default: along the view direction).
    #[arg(long, allow_negative_numbers = true)]
    pub cue_dir: Option<String>,
    /// Render only the first N coefficients of the stream.
    #[arg(long, conflicts_with = "bytes")]
    pub coefficients: Option<usize>,
    /// Render only the packets within the first B bytes of the file.
    #[arg(long)]
    pub bytes: Option<usize>,
    /// Output PNG.
    #[arg(short, long)]
    pub output: PathBuf,
    /// Also write the image as raw f32 (H rows of W little-endian floats; RGB interleaved).
    #[arg(long)]
    pub raw: Option<PathBuf>,
}

fn pair(s: &str, what: &str) -> Result<[f64; 2]> {
    let p: Vec<&str> = s.split(',').collect();
    if p.len() != 2 {
        bail!("{what} must be two numbers A,B, got {s:?}");
    }
    let a: f64 = p[0]
        .trim()
        .parse()
        .with_context(|| format!("{what}: {s:?}"))?;
    let b: f64 = p[1]
        .trim()
        .parse()
        .with_context(|| format!("{what}: {s:?}"))?;
    if !a.is_finite() || !b.is_finite() {
        bail!("{what} must be finite, got {s:?}");
    }
    Ok([a, b])
}

/// Maps an image rendered in the coded colour space back to RGB (see `ColorInfo::to_rgb`).
fn to_rgb(img: &Image, header: &Header, camera: &Camera) -> Result<Image> {
    let inv = header
        .color
        .inverse_basis()
        .context("the header's colour basis is singular")?;
    let has_mean = header.color.mean.iter().any(|m| *m != 0.0);
    let mut out = Image::new(img.width, img.height, 3);
    for y in 0..img.height {
        for x in 0..img.width {
            let c = [0, 1, 2].map(|k| img.get(x, y, k) as f64);
            let len = if has_mean {
                camera.chord(header.geometry.dims, x as f64 + 0.5, y as f64 + 0.5)
            } else {
                0.0
            };
            let rgb = header.color.to_rgb(&inv, c, len);
            for r in 0..3 {
                out.data[(y * img.width + x) * 3 + r] = rgb[r] as f32;
            }
        }
    }
    Ok(out)
}

/// Decodes the packets (or a prefix) of a file. Packets decode on their own, so they are decoded
/// in parallel, in batches of a few per thread so that a coefficient cap stops early.
pub fn load_coefficients(
    bytes: &[u8],
    max_coefficients: Option<usize>,
    max_bytes: Option<usize>,
) -> Result<(Header, Vec<Coefficient>)> {
    let file = parse_file(bytes)?;
    let mut used = file.header_bytes + file.directory_bytes;
    let mut prefix = 0usize;
    for p in &file.packets {
        if max_bytes.is_some_and(|b| used + p.len() > b) {
            break;
        }
        used += p.len();
        prefix += 1;
    }
    let batch = 4 * rayon::current_num_threads();
    let mut coeffs = Vec::new();
    let mut start = 0usize;
    while start < prefix && max_coefficients.is_none_or(|n| coeffs.len() < n) {
        let end = if max_coefficients.is_some() {
            (start + batch).min(prefix)
        } else {
            prefix
        };
        let decoded = decode_packets(&file.header, &file.packets[start..end], start)?;
        for d in decoded {
            if max_coefficients.is_some_and(|n| coeffs.len() >= n) {
                break;
            }
            coeffs.extend(d);
        }
        start = end;
    }
    if let Some(n) = max_coefficients {
        coeffs.truncate(n);
    }
    Ok((file.header, coeffs))
}

/// Runs the subcommand.
pub fn run(a: RenderArgs) -> Result<()> {
    let (w, h) = a
        .size
        .split_once(['x', ','])
        .and_then(|(w, h)| {
            Some((
                w.trim().parse::<usize>().ok()?,
                h.trim().parse::<usize>().ok()?,
            ))
        })
        .with_context(|| format!("--size must be WxH, got {:?}", a.size))?;
    if !a.cue_k.is_finite() || a.cue_k < 0.0 {
        bail!(
            "--cue-k must be a finite non-negative extinction per voxel, got {}",
            a.cue_k
        );
    }
    let bytes =
        std::fs::read(&a.input).with_context(|| format!("reading {}", a.input.display()))?;
    let (header, coeffs) = load_coefficients(&bytes, a.coefficients, a.bytes)
        .with_context(|| format!("decoding {}", a.input.display()))?;
    let mut view = View::new(a.alpha, a.beta, w, h);
    if let Some(z) = a.zoom {
        view = view.with_zoom(z);
    }
    if let Some(p) = &a.pan {
        view = view.with_pan(pair(p, "--pan")?);
    }
    if a.cue_k > 0.0 {
        let direction = match &a.cue_dir {
            Some(s) => {
                let [alpha, beta] = pair(s, "--cue-dir")?;
                CueDirection::Angles { alpha, beta }
            }
            None => CueDirection::View,
        };
        view = view.with_cue(Cue {
            k: a.cue_k,
            direction,
        });
    }
    let mut renderer = Renderer::new(RenderOptions {
        channels: header.channels,
        ..RenderOptions::default()
    });
    let g = &header.geometry;
    let start = std::time::Instant::now();
    let (image, cameras) = if a.multiview {
        let (views, _) = renderer.render_multiview_views(&coeffs, g, &view)?;
        (views, multiview_cameras(&view, g.dims)?.to_vec())
    } else {
        let img = renderer.render(&coeffs, g, &view)?;
        (vec![img], vec![Camera::new(&view, g.dims)?])
    };
    let elapsed = start.elapsed();
    let images: Vec<Image> = if header.color.kind == ColorKind::Intensity {
        image
    } else {
        image
            .iter()
            .zip(&cameras)
            .map(|(i, c)| to_rgb(i, &header, c))
            .collect::<Result<_>>()?
    };
    let out = if images.len() == 1 {
        images.into_iter().next().expect("one image")
    } else {
        Image::hconcat(&images)
    };
    out.write_png(&a.output, None)
        .with_context(|| format!("writing {}", a.output.display()))?;
    if let Some(r) = &a.raw {
        out.write_raw(r)
            .with_context(|| format!("writing {}", r.display()))?;
    }
    outln!(
        "wrote {} ({}x{}) from {} coefficients in {:.1} ms",
        a.output.display(),
        out.width,
        out.height,
        coeffs.len(),
        elapsed.as_secs_f64() * 1e3
    );
    Ok(())
}
