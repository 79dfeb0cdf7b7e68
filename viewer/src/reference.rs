//! The reference renderer, ground truth for every accuracy figure: X-ray line integrals (and the
//! emission–absorption integral with constant attenuation for depth cueing) of the volume
//! *reconstructed* from a set of coefficients.
//!
//! When periodic images of the basis functions reach the volume (a small or zero margin, see
//! [`crate::pieces`]), the volume is the periodic reconstruction's spline restricted to the
//! level-0 coefficients in the box: the codec's periodic synthesis on the padded grid, the box
//! then copied into a zero-margined grid. Otherwise the volume is what the splats draw:
//! Σ_c w_c b_c with every basis function b_c taken once, at
//! its periodic image nearest the volume centre (`Geometry::basis_center`). It is reconstructed
//! by the codec's synthesis on a grid extended by a margin wider than any support, each
//! coefficient moved to its nearest image there, so nothing wraps (on the padded grid itself the
//! synthesis is periodic: with small margins the periodic reconstruction differs from the
//! splatted function near the faces, by the tails that wrap around — a property of the boundary
//! handling, measured in BENCHMARKS.md, not of the splats). The grid is evaluated as the
//! function f(x) = Σ_k v_k Π_a φ^\[j\](x_a − (k_a − origin_a) + j/2) over its voxels k (Haar: unit
//! boxes centred on the voxels). Haar rays are integrated exactly by
//! voxel traversal (Amanatides–Woo), including the exact integral of the exponential cue over
//! each voxel segment; linear and cubic rays by composite Simpson sampling of the tensor B-spline
//! with step ≤ 1/8 voxel (configurable). Each pixel averages `supersample²` rays on a uniform
//! (midpoint) sub-grid, because splats integrate over the pixel area. Rows run on rayon. Rays
//! run through the voxel grid along the camera's index-space direction and are parameterised by
//! physical length, so with anisotropic spacing a line integral is in the spacing's units, the
//! same quantity the splats draw. Views along an axis without a cue need no rays: their image
//! is computed in closed form for every family ([`spline_axis_exact`]).

use crate::image::Image;
use crate::RenderError;
use rayon::prelude::*;
use wavesplat_codec::dwt::{inverse_3d, pad_channel, samples_to_coefficients, Dwt1d};
use wavesplat_codec::family::Family;
use wavesplat_codec::format::packet::Coefficient;
use wavesplat_codec::layout::Geometry;
use wavesplat_codec::view::{clip_ray as clip, dot, resolve_cue, Camera, ResolvedCue, View};

/// The padded reconstructed grid of every channel.
#[derive(Debug, Clone)]
pub struct PaddedVolume {
    /// Geometry of the decomposition.
    pub geometry: Geometry,
    /// Per channel, the padded voxel grid (x fastest).
    pub channels: Vec<Vec<f64>>,
}

impl PaddedVolume {
    /// Reconstructs `channels` channels from a set of coefficients (missing ones are zero),
    /// each basis function at its periodic image nearest the volume centre, on a grid extended
    /// so that none wraps (see the module documentation).
    pub fn from_coefficients(
        coefficients: &[Coefficient],
        geometry: &Geometry,
        channels: usize,
    ) -> Result<PaddedVolume, RenderError> {
        let g = geometry;
        if g.splats_clip_to_box() {
            // The periodic reconstruction, restricted to the box (what clipped splats draw).
            let mut data = vec![vec![0.0f64; g.coefficient_count()]; channels];
            for c in coefficients {
                crate::pieces::check_coefficient(c, g, channels)?;
                let pos = c.pos.map(|p| p as usize);
                data[c.channel as usize][g.linear_index(c.band, pos)] += c.value as f64;
            }
            let mut dwt = Dwt1d::new(g.family);
            for ch in data.iter_mut() {
                inverse_3d(ch, g, &mut dwt);
            }
            return Ok(boxed(&data, g));
        }
        let block = 1usize << g.levels;
        let reach = (0..=g.levels)
            .flat_map(|l| [g.half_support_1d(l, false), g.half_support_1d(l, true)])
            .fold(0.0f64, f64::max);
        let w = ((reach.ceil() as usize + 1).div_ceil(block)) * block;
        let extended = Geometry {
            padded: g.padded.map(|p| p + 2 * w),
            origin: g.origin.map(|o| o + w),
            ..*g
        };
        let mut data = vec![vec![0.0f64; extended.coefficient_count()]; channels];
        for c in coefficients {
            crate::pieces::check_coefficient(c, g, channels)?;
            let level = c.band.level as usize;
            let mut pos = [0usize; 3];
            for a in 0..3 {
                let k = c.pos[a] as usize;
                let raw = g.raw_center_1d(level, k, c.band.is_wavelet_along(a));
                let period = g.padded[a] as f64;
                let centre = g.origin[a] as f64 + 0.5 * (g.dims[a] as f64 - 1.0);
                // The image basis_center picks: raw − n·P; on the extended grid it sits w
                // further on.
                let n = ((raw - centre) / period).round() as i64;
                let shifted = k as i64 + (w as i64 - n * g.padded[a] as i64) / (1i64 << level);
                pos[a] = shifted as usize;
            }
            data[c.channel as usize][extended.linear_index(c.band, pos)] += c.value as f64;
        }
        let mut dwt = Dwt1d::new(g.family);
        for ch in data.iter_mut() {
            inverse_3d(ch, &extended, &mut dwt);
        }
        Ok(PaddedVolume {
            geometry: extended,
            channels: data,
        })
    }

    /// The spline through the voxel samples of an unmodified volume (padded, prefiltered to
    /// spline coefficients for the cubic family).
    pub fn from_volume(channels: &[Vec<f32>], geometry: &Geometry) -> PaddedVolume {
        let channels: Vec<Vec<f64>> = channels
            .iter()
            .map(|c| {
                let mut d = pad_channel(c, geometry);
                samples_to_coefficients(&mut d, geometry);
                d
            })
            .collect();
        if geometry.splats_clip_to_box() {
            return boxed(&channels, geometry);
        }
        PaddedVolume {
            geometry: *geometry,
            channels,
        }
    }
}

/// The box of padded grids (spline coefficients on `geometry`'s padded grid) copied into a
/// grid with a zero margin wider than a level-0 B-spline's support, so that the spline of the
/// box's coefficients is evaluated whole and nothing outside the box contributes.
fn boxed(channels: &[Vec<f64>], geometry: &Geometry) -> PaddedVolume {
    let g = geometry;
    let w = g.family.order() + 2;
    let out = Geometry {
        padded: g.dims.map(|d| d + 2 * w),
        origin: [w; 3],
        ..*g
    };
    let [px, py, _] = g.padded;
    let [qx, qy, _] = out.padded;
    let [nx, ny, nz] = g.dims;
    let channels = channels
        .iter()
        .map(|src| {
            let mut dst = vec![0.0f64; out.padded.iter().product()];
            for z in 0..nz {
                for y in 0..ny {
                    let s = g.origin[0] + px * (g.origin[1] + y + py * (g.origin[2] + z));
                    let d = w + qx * (w + y + qy * (w + z));
                    dst[d..d + nx].copy_from_slice(&src[s..s + nx]);
                }
            }
            dst
        })
        .collect();
    PaddedVolume {
        geometry: out,
        channels,
    }
}

/// Accuracy settings of the reference renderer.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ReferenceOptions {
    /// Rays per pixel side (the pixel averages supersample² rays).
    pub supersample: usize,
    /// Sampling step along rays for the spline families (voxels, ≤ 1/8 recommended).
    pub step: f64,
}

impl Default for ReferenceOptions {
    fn default() -> Self {
        ReferenceOptions {
            supersample: 4,
            step: 0.125,
        }
    }
}

/// Renders the reference image of `volume` for `view` (multiview not supported here: render
/// each view's camera separately with [`render_reference_camera`]).
pub fn render_reference(
    volume: &PaddedVolume,
    view: &View,
    options: &ReferenceOptions,
) -> Result<Image, RenderError> {
    let camera = Camera::new(view, &volume.geometry)?;
    let cue = match &view.cue {
        Some(c) => Some(resolve_cue(c, &camera, &volume.geometry)?),
        None => None,
    };
    Ok(render_reference_camera(volume, &camera, cue, options))
}

/// Reference rendering for a resolved camera and cue.
pub fn render_reference_camera(
    volume: &PaddedVolume,
    camera: &Camera,
    cue: Option<ResolvedCue>,
    options: &ReferenceOptions,
) -> Image {
    if cue.is_none() {
        if let Some(img) = spline_axis_exact(volume, camera) {
            return img;
        }
    }
    render_rays(volume, camera, cue, options)
}

/// The supersampled ray image: each pixel the mean of `supersample²` line integrals (exact
/// voxel traversal for Haar, Simpson along the tensor B-spline otherwise).
fn render_rays(
    volume: &PaddedVolume,
    camera: &Camera,
    cue: Option<ResolvedCue>,
    options: &ReferenceOptions,
) -> Image {
    let g = &volume.geometry;
    let nch = volume.channels.len();
    let mut image = Image::new(camera.width, camera.height, nch);
    let ss = options.supersample.max(1);
    let step = if options.step.is_finite() && options.step > 0.0 {
        options.step.min(0.5)
    } else {
        0.125
    };
    // Rays are parameterised by physical length; a step of `step` voxels along the axis the ray
    // crosses fastest is this much length.
    let ray = camera.ray();
    let step = step / ray.iter().fold(0.0f64, |m, r| m.max(r.abs()));
    let width = camera.width;
    let bbox = significant_box(volume);
    image
        .data
        .par_chunks_mut((width * nch).max(1))
        .enumerate()
        .for_each(|(iy, row)| {
            let mut acc = vec![0.0f64; nch];
            for ix in 0..width {
                acc.iter_mut().for_each(|a| *a = 0.0);
                for sy in 0..ss {
                    for sx in 0..ss {
                        let xs = ix as f64 + (sx as f64 + 0.5) / ss as f64;
                        let ys = iy as f64 + (sy as f64 + 0.5) / ss as f64;
                        let p = camera.from_screen(xs, ys);
                        match g.family {
                            Family::Haar => haar_ray(volume, p, ray, cue.as_ref(), &mut acc),
                            _ if bbox.is_none() => {}
                            f => spline_ray(
                                volume,
                                f,
                                p,
                                ray,
                                cue.as_ref(),
                                step,
                                bbox.unwrap_or_default(),
                                &mut acc,
                            ),
                        }
                    }
                }
                let norm = 1.0 / (ss * ss) as f64;
                for c in 0..nch {
                    row[ix * nch + c] = (acc[c] * norm) as f32;
                }
            }
        });
    image
}

/// The axes of a view along a coordinate axis: (ray, screen x, screen y) as volume axes, or
/// `None` for other views. Within 1e-12 of an axis (≈ 1.4 µrad) a voxel edge moves < 1e-3 px
/// across the whole padded volume, far below what the supersampled path resolves.
fn axis_view(camera: &Camera) -> Option<(usize, usize, usize)> {
    let on_axis = |x: f64| x.abs() >= 1.0 - 1e-12;
    let ray = (0..3).find(|a| on_axis(camera.n[*a]))?;
    let ax = (0..3).find(|a| on_axis(camera.u[*a]))?;
    let ay = (0..3).find(|a| on_axis(camera.v[*a]))?;
    (ax != ray && ay != ray && ax != ay).then_some((ray, ax, ay))
}

/// The cardinal B-spline of order `m` (degree m − 1, support [0, m)) at `x`, by its
/// truncated-power formula (1/(m−1)!) Σₖ (−1)ᵏ C(m, k) (x − k)₊^(m−1): a closed form that
/// shares nothing with the codec's filters or the renderer's tables.
fn cardinal_bspline(m: usize, x: f64) -> f64 {
    if x < 0.0 || x >= m as f64 {
        return 0.0;
    }
    let (mut sum, mut binomial, mut factorial) = (0.0, 1.0, 1.0);
    for k in 0..=m {
        let t = x - k as f64;
        if t >= 0.0 {
            let sign = if k % 2 == 0 { 1.0 } else { -1.0 };
            sum += sign * binomial * t.powi(m as i32 - 1);
        }
        binomial = binomial * (m - k) as f64 / (k + 1) as f64;
    }
    for i in 1..m {
        factorial *= i as f64;
    }
    sum / factorial
}

/// ∫₋∞ˣ of the cardinal B-spline of order `j`: Σ_{i ≥ 0} of the order-(j + 1) spline at
/// x − i (its derivative telescopes to the order-j spline), 0 below its support and 1 above.
fn cardinal_bspline_integral(j: usize, x: f64) -> f64 {
    if x <= 0.0 {
        return 0.0;
    }
    if x >= j as f64 {
        return 1.0;
    }
    (0..=x.floor() as usize)
        .map(|i| cardinal_bspline(j + 1, x - i as f64))
        .sum()
}

/// Per pixel along one screen axis, the first voxel index (on the padded grid) and the
/// pixel-area average of each voxel's B-spline over the pixel: the pixel's interval [lo, hi]
/// along volume axis `axis` (in grid coordinates, where voxel k's spline covers (k, k + j)),
/// each spline's integral over it divided by its length.
fn axis_weights(
    camera: &Camera,
    geometry: &Geometry,
    axis: usize,
    pixels: usize,
    screen_x: bool,
) -> Vec<(usize, Vec<f64>)> {
    let j = geometry.family.order();
    let shift = geometry.origin[axis] as f64 + 0.5 * j as f64;
    let grid = |s: f64| {
        let p = if screen_x {
            camera.from_screen(s, 0.5 * camera.height as f64)
        } else {
            camera.from_screen(0.5 * camera.width as f64, s)
        };
        p[axis] + shift
    };
    let n = geometry.padded[axis] as i64;
    (0..pixels)
        .map(|px| {
            let (a, b) = (grid(px as f64), grid(px as f64 + 1.0));
            let (lo, hi) = (a.min(b), a.max(b));
            let first = ((lo.floor() as i64) - j as i64 + 1).clamp(0, n);
            let last = (hi.ceil() as i64).clamp(0, n);
            let weights = (first..last)
                .map(|k| {
                    let k = k as f64;
                    (cardinal_bspline_integral(j, hi - k) - cardinal_bspline_integral(j, lo - k))
                        / (hi - lo)
                })
                .collect();
            (first as usize, weights)
        })
        .collect()
}

/// The exact pixel-area-averaged image of a volume of any family (Haar's box is the order-1
/// B-spline) for a view along a coordinate axis (no cue): the line integral of each voxel's
/// spline along the ray is its integral, 1 voxel, so the projection is the column sums' 2-D spline, and a pixel's
/// average of it is separable: Σ over columns of the sum times the two screen axes' averages of
/// the splines over the pixel (closed-form antiderivatives, [`cardinal_bspline_integral`]). No
/// ray sampling and no supersampling: the ground truth the splats are held to on the axes,
/// where their sampling errors line up with the pixel grid (and Haar's box edges with the
/// pixels' edges, which rays resolve only slowly). `None` for other views.
pub fn spline_axis_exact(volume: &PaddedVolume, camera: &Camera) -> Option<Image> {
    let (ray, ax, ay) = axis_view(camera)?;
    let g = &volume.geometry;
    let nch = volume.channels.len();
    let stride = [1usize, g.padded[0], g.padded[0] * g.padded[1]];
    let (nx, ny) = (g.padded[ax], g.padded[ay]);
    let length = camera.spacing[ray];
    let wx = axis_weights(camera, g, ax, camera.width, true);
    let wy = axis_weights(camera, g, ay, camera.height, false);
    let mut data = vec![0.0f32; camera.width * camera.height * nch];
    for (c, ch) in volume.channels.iter().enumerate() {
        // Column sums along the ray, times the length of a voxel along it.
        let cols: Vec<f64> = (0..nx * ny)
            .into_par_iter()
            .map(|i| {
                let (kx, ky) = (i % nx, i / nx);
                let base = kx * stride[ax] + ky * stride[ay];
                length
                    * (0..g.padded[ray])
                        .map(|k| ch[base + k * stride[ray]])
                        .sum::<f64>()
            })
            .collect();
        // Along screen x per column row, then along screen y.
        let rows: Vec<f64> = (0..ny)
            .into_par_iter()
            .flat_map_iter(|ky| {
                let line = &cols[ky * nx..(ky + 1) * nx];
                wx.iter().map(move |(first, w)| {
                    w.iter()
                        .zip(&line[*first..])
                        .map(|(w, v)| w * v)
                        .sum::<f64>()
                })
            })
            .collect();
        let width = camera.width;
        for (py, (first, w)) in wy.iter().enumerate() {
            for px in 0..width {
                let v: f64 = w
                    .iter()
                    .enumerate()
                    .map(|(i, w)| w * rows[(first + i) * width + px])
                    .sum();
                data[(py * width + px) * nch + c] = v as f32;
            }
        }
    }
    Some(Image {
        width: camera.width,
        height: camera.height,
        channels: nch,
        data,
    })
}

/// Bounding box (inclusive voxel ranges) of the voxels of any channel above 1e-6 of the
/// largest magnitude (below that a voxel changes a line integral by < 1e-6 relative): the
/// spline rays are only sampled where the volume lives. `None` for an all-zero volume.
fn significant_box(vol: &PaddedVolume) -> Option<[[usize; 2]; 3]> {
    let g = &vol.geometry;
    let max = vol
        .channels
        .iter()
        .flat_map(|c| c.iter())
        .fold(0.0f64, |m, v| m.max(v.abs()));
    if max == 0.0 || !max.is_finite() {
        return None;
    }
    let thr = 1e-6 * max;
    let mut b = [[usize::MAX, 0]; 3];
    let (px, py) = (g.padded[0], g.padded[1]);
    for ch in &vol.channels {
        for (i, v) in ch.iter().enumerate() {
            if v.abs() > thr {
                let c = [i % px, (i / px) % py, i / (px * py)];
                for a in 0..3 {
                    b[a][0] = b[a][0].min(c[a]);
                    b[a][1] = b[a][1].max(c[a]);
                }
            }
        }
    }
    Some(b)
}

/// ∫ over a segment of length `len` of e^(−k·d), d linear from `da` to `db` (both ≥ 0 up to
/// rounding): never overflows.
fn cued_segment(len: f64, da: f64, db: f64, k: f64) -> f64 {
    let m = da.min(db).max(0.0);
    let x = k * (db - da).abs();
    let boxf = if x < 1e-6 {
        1.0 - 0.5 * x + x * x / 6.0
    } else {
        -(-x).exp_m1() / x
    };
    len * (-k * m).exp() * boxf
}

/// Exact line integral through the Haar box grid (voxel k centred at k − origin).
fn haar_ray(
    vol: &PaddedVolume,
    p: [f64; 3],
    n: [f64; 3],
    cue: Option<&ResolvedCue>,
    acc: &mut [f64],
) {
    let g = &vol.geometry;
    // Grid coordinates: q = x + origin + 0.5, voxel k covers [k, k+1).
    let q = [
        p[0] + g.origin[0] as f64 + 0.5,
        p[1] + g.origin[1] as f64 + 0.5,
        p[2] + g.origin[2] as f64 + 0.5,
    ];
    let hi = [g.padded[0] as f64, g.padded[1] as f64, g.padded[2] as f64];
    let Some((t0, t1)) = clip(q, n, [0.0; 3], hi) else {
        return;
    };
    let mut cell = [0i64; 3];
    let mut stepv = [0i64; 3];
    let mut tmax = [f64::INFINITY; 3];
    let mut tdelta = [f64::INFINITY; 3];
    for a in 0..3 {
        // Locate the starting cell from a point slightly inside the segment.
        let x = q[a] + n[a] * (t0 + 1e-9 * (t1 - t0).min(1.0));
        cell[a] = (x.floor() as i64).clamp(0, g.padded[a] as i64 - 1);
        if n[a] > 1e-300 {
            stepv[a] = 1;
            tmax[a] = (cell[a] as f64 + 1.0 - q[a]) / n[a];
            tdelta[a] = 1.0 / n[a];
        } else if n[a] < -1e-300 {
            stepv[a] = -1;
            tmax[a] = (cell[a] as f64 - q[a]) / n[a];
            tdelta[a] = -1.0 / n[a];
        }
    }
    let mut t = t0;
    let stride = [1usize, g.padded[0], g.padded[0] * g.padded[1]];
    loop {
        let a = if tmax[0] <= tmax[1] && tmax[0] <= tmax[2] {
            0
        } else if tmax[1] <= tmax[2] {
            1
        } else {
            2
        };
        let tn = tmax[a].min(t1);
        if tn > t {
            let idx = cell[0] as usize * stride[0]
                + cell[1] as usize * stride[1]
                + cell[2] as usize * stride[2];
            let w = match cue {
                None => tn - t,
                Some(c) => {
                    // A cell lies wholly on one side of each face (faces at cell borders).
                    let tm = 0.5 * (t + tn);
                    let pm = [p[0] + n[0] * tm, p[1] + n[1] * tm, p[2] + n[2] * tm];
                    if c.in_front(pm) {
                        0.0
                    } else {
                        let pa = [p[0] + n[0] * t, p[1] + n[1] * t, p[2] + n[2] * t];
                        let da = c.dist(pa);
                        let db = da + dot(c.l, n) * (tn - t);
                        cued_segment(tn - t, da, db, c.k)
                    }
                }
            };
            for (ch, a) in vol.channels.iter().zip(acc.iter_mut()) {
                *a += w * ch[idx];
            }
        }
        if tmax[a] >= t1 {
            break;
        }
        t = tn;
        cell[a] += stepv[a];
        if cell[a] < 0 || cell[a] >= g.padded[a] as i64 {
            break;
        }
        tmax[a] += tdelta[a];
    }
}

/// B-spline weights φ(u + i), i = 0..j, for the fractional part u ∈ [0, 1).
fn weights(j: usize, u: f64, w: &mut [f64; 4]) {
    match j {
        2 => {
            w[0] = u;
            w[1] = 1.0 - u;
        }
        4 => {
            let u2 = u * u;
            let u3 = u2 * u;
            let v = 1.0 - u;
            w[0] = u3 / 6.0;
            w[1] = (-3.0 * u3 + 3.0 * u2 + 3.0 * u + 1.0) / 6.0;
            w[2] = (3.0 * u3 - 6.0 * u2 + 4.0) / 6.0;
            w[3] = v * v * v / 6.0;
        }
        _ => {
            w[0] = 1.0;
        }
    }
}

/// Where along the ray p + t·n (t in [t0, t1]) a depth cue leaves anything to integrate, and
/// the sampling step that resolves it: the part behind every light-facing face (in front of
/// one the weight is 0, so the jump sits at an end of the interval instead of between two
/// samples), cut where the weight has fallen by e^(−[`CUE_CUT`]) from its largest value on the
/// ray (the weight e^(−k·dist) is exponential in t: dist changes by l·n per unit of t), with
/// the step at most 1/(8·k·|l·n|) so Simpson resolves the exponential (relative error ~1e-6).
/// Without the cut a stiff cue (k = 1e3 per voxel) would need ~10⁵ samples per voxel of ray.
/// `None`: the ray never enters the medium.
fn cued_interval(
    c: &ResolvedCue,
    p: [f64; 3],
    n: [f64; 3],
    t0: f64,
    t1: f64,
    step: f64,
) -> Option<(f64, f64, f64)> {
    let (mut a, mut b) = (t0, t1);
    for ax in 0..3 {
        // Behind the face: l·(x − plane) ≥ 0 along this axis.
        let s = c.l[ax].signum();
        if c.l[ax] == 0.0 {
            continue;
        }
        let (x0, d) = (s * (p[ax] - c.planes[ax]), s * n[ax]);
        if d == 0.0 {
            if x0 < 0.0 {
                return None;
            }
        } else if d > 0.0 {
            a = a.max(-x0 / d);
        } else {
            b = b.min(-x0 / d);
        }
    }
    if a >= b {
        return None;
    }
    let rate = c.k * dot(c.l, n);
    if rate > 0.0 {
        b = b.min(a + CUE_CUT / rate);
    } else if rate < 0.0 {
        a = a.max(b + CUE_CUT / rate);
    }
    let step = if rate != 0.0 {
        step.min(0.125 / rate.abs())
    } else {
        step
    };
    Some((a, b, step))
}

/// A cued ray is cut where its weight has fallen to e^(−40) ≈ 4e-18 of its largest value on the
/// ray: below the f64 resolution of the ray's sum.
const CUE_CUT: f64 = 40.0;

/// Simpson integration of the tensor B-spline along the ray.
fn spline_ray(
    vol: &PaddedVolume,
    family: Family,
    p: [f64; 3],
    n: [f64; 3],
    cue: Option<&ResolvedCue>,
    step: f64,
    bbox: [[usize; 2]; 3],
    acc: &mut [f64],
) {
    let g = &vol.geometry;
    let j = family.order();
    let hj = 0.5 * j as f64;
    // Grid coordinates: gq = x + origin + j/2; voxel k contributes φ(gq − k) on (k, k + j).
    let q = [
        p[0] + g.origin[0] as f64 + hj,
        p[1] + g.origin[1] as f64 + hj,
        p[2] + g.origin[2] as f64 + hj,
    ];
    let lo = [bbox[0][0] as f64, bbox[1][0] as f64, bbox[2][0] as f64];
    let hi = [
        (bbox[0][1] + j) as f64,
        (bbox[1][1] + j) as f64,
        (bbox[2][1] + j) as f64,
    ];
    let Some((t0, t1)) = clip(q, n, lo, hi) else {
        return;
    };
    let (t0, t1, step) = match cue {
        Some(c) => match cued_interval(c, p, n, t0, t1, step) {
            Some(x) => x,
            None => return,
        },
        None => (t0, t1, step),
    };
    let mut count = ((t1 - t0) / step).ceil() as usize;
    count += count % 2;
    let count = count.max(2);
    let h = (t1 - t0) / count as f64;
    let stride = [1i64, g.padded[0] as i64, (g.padded[0] * g.padded[1]) as i64];
    let pd = [g.padded[0] as i64, g.padded[1] as i64, g.padded[2] as i64];
    let mut wts = [[0.0f64; 4]; 3];
    let mut base = [0i64; 3];
    let nch = vol.channels.len();
    let mut val = [0.0f64; 8];
    for s in 0..=count {
        let t = t0 + h * s as f64;
        let simpson = if s == 0 || s == count {
            1.0
        } else if s % 2 == 1 {
            4.0
        } else {
            2.0
        };
        let mut weight = simpson * h / 3.0;
        if let Some(c) = cue {
            // Inside the medium by construction of the interval (see `cued_interval`): no
            // face test, which rounding could fail at the interval's first sample.
            let x = [p[0] + n[0] * t, p[1] + n[1] * t, p[2] + n[2] * t];
            weight *= (-c.k * c.dist(x).max(0.0)).exp();
        }
        for a in 0..3 {
            let x = q[a] + n[a] * t;
            let f = x.floor();
            weights(j, x - f, &mut wts[a]);
            base[a] = f as i64;
        }
        for (c, ch) in vol.channels.iter().enumerate().take(8) {
            let mut sum = 0.0;
            for iz in 0..j {
                let kz = base[2] - iz as i64;
                if kz < 0 || kz >= pd[2] {
                    continue;
                }
                for iy in 0..j {
                    let ky = base[1] - iy as i64;
                    if ky < 0 || ky >= pd[1] {
                        continue;
                    }
                    let wzy = wts[2][iz] * wts[1][iy];
                    let row = (ky * stride[1] + kz * stride[2]) as usize;
                    let mut rs = 0.0;
                    for ix in 0..j {
                        let kx = base[0] - ix as i64;
                        if kx >= 0 && kx < pd[0] {
                            rs += wts[0][ix] * ch[row + kx as usize];
                        }
                    }
                    sum += wzy * rs;
                }
            }
            val[c] = sum;
        }
        for c in 0..nch.min(8) {
            acc[c] += weight * val[c];
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use wavesplat_codec::dwt::decompose_channel;
    use wavesplat_codec::view::{Cue, CueDirection};

    /// The Haar axis image as the reference first computed it, independently of the B-spline
    /// closed form: the projection is constant on each column of cells (their sum along the ray),
    /// so a pixel is the area-weighted sum of the column rectangles it overlaps, mapped to the
    /// screen by the camera. `None` for other views.
    fn haar_overlap_areas(volume: &PaddedVolume, camera: &Camera) -> Option<Image> {
        let (ray, ax, ay) = axis_view(camera)?;
        let g = &volume.geometry;
        let nch = volume.channels.len();
        let stride = [1usize, g.padded[0], g.padded[0] * g.padded[1]];
        // Column sums (cells along the ray).
        let (nx, ny) = (g.padded[ax], g.padded[ay]);
        let mut cols = vec![0.0f64; nx * ny * nch];
        for (c, ch) in volume.channels.iter().enumerate() {
            for j in 0..ny {
                for i in 0..nx {
                    let mut sum = 0.0;
                    for k in 0..g.padded[ray] {
                        sum += ch[i * stride[ax] + j * stride[ay] + k * stride[ray]];
                    }
                    cols[(j * nx + i) * nch + c] = sum;
                }
            }
        }
        // Screen interval of cell i along a screen axis: its volume interval mapped by the camera.
        let span = |axis: usize, i: usize, screen_x: bool| -> (f64, f64) {
            let lo = i as f64 - g.origin[axis] as f64 - 0.5;
            let mut p = camera.center;
            p[axis] = lo;
            let a = camera.to_screen(p);
            p[axis] = lo + 1.0;
            let b = camera.to_screen(p);
            let (a, b) = if screen_x { (a[0], b[0]) } else { (a[1], b[1]) };
            (a.min(b), a.max(b))
        };
        // Overlap lengths of each cell with each pixel along one screen axis.
        let overlaps =
            |axis: usize, n: usize, pixels: usize, screen_x: bool| -> Vec<Vec<(usize, f64)>> {
                (0..n)
                    .map(|i| {
                        let (a, b) = span(axis, i, screen_x);
                        let first = a.floor().max(0.0) as usize;
                        let last = (b.ceil().max(0.0) as usize).min(pixels);
                        (first..last)
                            .filter_map(|p| {
                                let o = b.min(p as f64 + 1.0) - a.max(p as f64);
                                (o > 0.0).then_some((p, o))
                            })
                            .collect()
                    })
                    .collect()
            };
        let ox = overlaps(ax, nx, camera.width, true);
        let oy = overlaps(ay, ny, camera.height, false);
        // Inside a column the line integral is its sum times the cells' length along the ray; a
        // pixel averages it over its unit area, i.e. weights each column by the overlap area in
        // pixels.
        let length = camera.spacing[ray];
        let mut acc = vec![0.0f64; camera.width * camera.height * nch];
        for j in 0..ny {
            for i in 0..nx {
                for &(py, wy) in &oy[j] {
                    for &(px, wx) in &ox[i] {
                        let w = wx * wy;
                        for c in 0..nch {
                            acc[(py * camera.width + px) * nch + c] +=
                                w * length * cols[(j * nx + i) * nch + c];
                        }
                    }
                }
            }
        }
        Some(Image {
            width: camera.width,
            height: camera.height,
            channels: nch,
            data: acc.into_iter().map(|v| v as f32).collect(),
        })
    }

    /// The closed-form B-spline against the cubic weights of the Simpson path (which evaluate
    /// φ(u + i) by the usual polynomial pieces): the same values, and splines of every order
    /// sum to one over the integer translates and integrate to one.
    #[test]
    fn cardinal_bsplines_are_partitions_of_unity() {
        for i in 0..=40 {
            let u = i as f64 / 40.0 * 0.999;
            let mut w = [0.0; 4];
            weights(4, u, &mut w);
            for (k, wk) in w.iter().enumerate() {
                let closed = cardinal_bspline(4, u + k as f64);
                assert!((closed - wk).abs() < 1e-13, "u={u} k={k}: {closed} vs {wk}");
            }
            for m in 1..=5 {
                let sum: f64 = (0..=m).map(|k| cardinal_bspline(m, u + k as f64)).sum();
                assert!((sum - 1.0).abs() < 1e-12, "order {m} at {u}: {sum}");
            }
        }
        for j in 1..=4 {
            assert_eq!(cardinal_bspline_integral(j, j as f64), 1.0);
            // Symmetric about j/2, and a midpoint sum of the spline agrees.
            let half = cardinal_bspline_integral(j, 0.5 * j as f64);
            assert!((half - 0.5).abs() < 1e-12, "order {j}: {half}");
            let x = 0.37 * j as f64;
            let steps = 20_000;
            let midpoint: f64 = (0..steps)
                .map(|i| {
                    cardinal_bspline(j, (i as f64 + 0.5) * x / steps as f64) * x / steps as f64
                })
                .sum();
            assert!((midpoint - cardinal_bspline_integral(j, x)).abs() < 1e-7);
        }
    }

    /// The exact axis image against the supersampled ray reference on a random volume, for
    /// every family, each axis (one of them flipped), a zoom that puts voxel edges between
    /// pixels and a pan: the rays' midpoint rule converges to it (their error at 32² rays per
    /// pixel is a tenth of that at 4², and within 1e-4 of the peak; not fourfold per doubling,
    /// since a spline's kink at a fixed distance from a sub-cell edge common to both grids
    /// errs the same at S and 2S), which it would not if the closed form were off by any shift
    /// or scale. For Haar it also equals the cells' overlap areas computed on the screen.
    #[test]
    fn exact_axis_images_are_what_the_rays_converge_to() {
        let n = 10;
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let data: Vec<f32> = (0..n * n * n)
            .map(|_| {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                (state >> 40) as f32 / (1u64 << 24) as f32
            })
            .collect();
        for family in [Family::Haar, Family::Linear, Family::Cubic] {
            let g = Geometry::new([n; 3], family, 1, 2).unwrap();
            let coeffs = Coefficient::all_of(&g, 0, &decompose_channel(&data, &g));
            let vol = PaddedVolume::from_coefficients(&coeffs, &g, 1).unwrap();
            for (alpha, beta) in [
                (0.0, 0.0),
                (std::f64::consts::FRAC_PI_2, 0.0),
                (0.0, -std::f64::consts::FRAC_PI_2),
            ] {
                let view = View::new(alpha, beta, 17, 13)
                    .with_zoom(1.37)
                    .with_pan([0.41, -0.23]);
                let camera = Camera::new(&view, &vol.geometry).unwrap();
                let exact = spline_axis_exact(&vol, &camera).expect("an axis view");
                let peak = exact.data.iter().fold(0.0f32, |m, v| m.max(v.abs()));
                assert!(peak > 1.0, "{family} ({alpha},{beta}): peak {peak}");
                if family == Family::Haar {
                    let boxes = haar_overlap_areas(&vol, &camera).unwrap();
                    for (a, b) in exact.data.iter().zip(&boxes.data) {
                        assert!((a - b).abs() <= 1e-5 * peak, "{a} vs {b}");
                    }
                    continue;
                }
                let error = |supersample: usize| {
                    let options = ReferenceOptions {
                        supersample,
                        step: 0.0625,
                    };
                    let rays = render_rays(&vol, &camera, None, &options);
                    rays.data
                        .iter()
                        .zip(&exact.data)
                        .fold(0.0f64, |m, (a, b)| m.max((a - b).abs() as f64))
                };
                let (e4, e32) = (error(4), error(32));
                eprintln!("{family} ({alpha},{beta}): errors {e4:e} {e32:e} of {peak}");
                assert!(
                    e32 < e4 / 10.0 && e32 < 1e-4 * peak as f64,
                    "{family} ({alpha},{beta}): errors {e4:e} {e32:e} of {peak}"
                );
            }
        }
    }

    /// Stiff depth cues (up to k = 1e3 per voxel, where e^(−k·t) falls by 1e-434 over one
    /// voxel) are resolved by the spline rays at the default step: the image equals one sampled
    /// eight times finer within 1e-3 of its peak (the sampling error of the 1/8-voxel step across
    /// the linear spline's kinks, 3e-4 at k = 0.5), for lights along two axes.
    /// (A fixed 1/8-voxel step would miss k = 20 and 1e3 by orders of magnitude.)
    #[test]
    fn stiff_cue_is_resolved_at_the_default_step() {
        let n = 8;
        let g = Geometry::new([n; 3], Family::Linear, 1, 2).unwrap();
        let c = 0.5 * (n as f64 - 1.0);
        let data: Vec<f32> = (0..n * n * n)
            .map(|i| {
                let p = [i % n, (i / n) % n, i / (n * n)].map(|x| (x as f64 - c) / 3.0);
                // Non-zero faces: the stiff cue sees the data at the light-facing corner.
                (0.5 + (1.0 - p.iter().map(|x| x * x).sum::<f64>()).max(0.0)) as f32
            })
            .collect();
        let coeffs = Coefficient::all_of(&g, 0, &decompose_channel(&data, &g));
        let vol = PaddedVolume::from_coefficients(&coeffs, &g, 1).unwrap();
        for k in [0.5, 20.0, 1e3] {
            // Lights along an axis: the light plane is a face, so a stiff cue leaves the
            // front layer (through a corner it would leave nothing above f64's underflow).
            for direction in [
                CueDirection::Vector([0.0, 0.0, 1.0]),
                CueDirection::Vector([0.0, -1.0, 0.0]),
            ] {
                let view = View::new(0.66, 0.91, 6, 6).with_cue(Cue { k, direction });
                let at = |step: f64| {
                    let o = ReferenceOptions {
                        supersample: 1,
                        step,
                    };
                    render_reference(&vol, &view, &o).unwrap()
                };
                let coarse = at(0.125);
                let fine = at(0.125 / (8.0 * k));
                let peak = fine.data.iter().fold(0.0f32, |m, v| m.max(v.abs()));
                assert!(peak > 0.0 && peak.is_finite(), "k={k}: peak {peak}");
                let err = coarse
                    .data
                    .iter()
                    .zip(&fine.data)
                    .fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
                assert!(err <= 1e-3 * peak, "k={k} {direction:?}: {err} of {peak}");
            }
        }
    }
}
