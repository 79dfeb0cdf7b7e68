//! The periodic semi-orthogonal B-spline wavelet transform, 1D and 3D non-standard.
//!
//! Reconstruction uses the primal two-scale filters (p for φ, q for ψ; eq. 4 and 6): a level's
//! fine coefficients are c0 = (↑c1) ∗ p + (↑d1) ∗ q, circularly. Decomposition is the exact
//! inverse of that synthesis, which for semi-orthogonal wavelets is the orthogonal projection
//! onto V and W (the duals). The duals have infinite support, so instead of truncating them we
//! invert the 2×2 polyphase matrix of the synthesis exactly: [`forward_3d`] by recursive filters
//! ([`recursive`]: the adjugate's FIR, then the determinant's inverse as first-order recursions),
//! and, as the reference it is tested against, [`forward_3d_fft`] per frequency of a length-N/2
//! FFT, both exact to rounding. A dense Gram-matrix projection is kept in the tests as the naive
//! reference of the FFT path.
//!
//! Voxel values are *samples* of the spline: the volume is the function
//! f(x) = Σ c_k φ(x − k + j/2) whose values at the voxel centres are the voxels (f(k) = v_k).
//! For Haar and linear, φ at the integers is a Kronecker delta and c = v; for the cubic family
//! the coefficients come from the exact (periodic, FFT) B-spline interpolation prefilter
//! ([`samples_to_coefficients`]) and samples are recovered by the 3-tap FIR
//! ([`coefficients_to_samples`]). This keeps the energy oracle, which measures the function,
//! in step with errors measured on voxels, and makes the X-ray of f the X-ray of the data.
//!
//! The 3D transform is the non-standard tensor product: per level, every x line, then every y
//! line, then every z line of the current scaling block is split into a scaling half and a
//! wavelet half (in place, Mallat layout; see [`crate::layout`]), then the scaling octant
//! recurses. Lines are independent; with the `rayon` feature they run on the rayon pool and the
//! result is bit-identical to the sequential run.

pub mod bridge;
pub mod fast;
mod lanes;
pub mod recursive;

use crate::family::Family;
use crate::layout::Geometry;
use num_complex::Complex64;
use rustfft::{Fft, FftPlanner};
use std::collections::HashMap;
use std::sync::Arc;

/// Everything needed to transform lines of one length with one family.
struct LinePlan {
    half: usize,
    fft: Arc<dyn Fft<f64>>,
    ifft: Arc<dyn Fft<f64>>,
    /// Per frequency n, the analysis in the spectrum of the line read as complex pairs
    /// (Z = E + i·O, E and O the spectra of its even and odd samples): the spectrum of
    /// (scaling + i·wavelet) is α[n]·Z[n] + β[n]·conj(Z[−n]). With [[a, b], [c, d]] the inverse
    /// of the polyphase matrix [[Pe, Qe], [Po, Qo]] divided by `half` (folding in the inverse
    /// FFT's normalization): α = (a + d + i(c − b))/2, β = (a − d + i(b + c))/2.
    alpha_beta: Vec<(Complex64, Complex64)>,
}

/// A planner for 1D transforms of one family; plans are built once per line length.
pub struct Dwt1d {
    family: Family,
    p: Vec<f64>,
    q: Vec<f64>,
    plans: HashMap<usize, LinePlan>,
    /// The same analysis by recursive filters, what [`forward_3d`] runs (every family has one).
    recursive: Option<recursive::RecursiveAnalysis>,
}

impl Dwt1d {
    /// A planner for `family`.
    pub fn new(family: Family) -> Dwt1d {
        Dwt1d {
            family,
            p: family.scaling_filter(),
            q: family.wavelet_filter(),
            plans: HashMap::new(),
            recursive: recursive::RecursiveAnalysis::of(family),
        }
    }

    /// The family this planner transforms with.
    pub fn family(&self) -> Family {
        self.family
    }

    /// Builds (or reuses) the plan for even length `len`.
    fn plan(&mut self, len: usize) -> &LinePlan {
        assert!(
            len >= 2 && len.is_multiple_of(2),
            "line length {len} must be even"
        );
        let (p, q) = (&self.p, &self.q);
        self.plans.entry(len).or_insert_with(|| {
            let half = len / 2;
            let mut planner = FftPlanner::<f64>::new();
            let fft = planner.plan_fft_forward(half);
            let ifft = planner.plan_fft_inverse(half);
            let symbol = |filter: &[f64], parity: usize, n: usize| -> Complex64 {
                filter
                    .iter()
                    .enumerate()
                    .filter(|(i, _)| i % 2 == parity)
                    .map(|(i, c)| {
                        let k = (i / 2) % half;
                        let angle = -2.0 * std::f64::consts::PI * (n * k) as f64 / half as f64;
                        Complex64::from_polar(*c, angle)
                    })
                    .sum()
            };
            let i = Complex64::i();
            let alpha_beta = (0..half)
                .map(|n| {
                    let (pe, qe) = (symbol(p, 0, n), symbol(q, 0, n));
                    let (po, qo) = (symbol(p, 1, n), symbol(q, 1, n));
                    let det = pe * qo - qe * po;
                    let s = 1.0 / (det * half as f64);
                    let [a, b, c, d] = [qo * s, -qe * s, -po * s, pe * s];
                    ((a + d + i * (c - b)) * 0.5, (a - d + i * (b + c)) * 0.5)
                })
                .collect();
            LinePlan {
                half,
                fft,
                ifft,
                alpha_beta,
            }
        })
    }

    /// Prepares plans for every line length a 3D transform of `geometry` needs, so that the
    /// per-line calls can share `&self` across threads.
    pub fn prepare(&mut self, geometry: &Geometry) {
        for level in 1..=geometry.levels {
            for a in 0..3 {
                self.plan(geometry.padded[a] >> (level - 1));
            }
        }
    }

    /// One analysis step in place: `line` (even length, prepared) becomes
    /// `[scaling coefficients | wavelet coefficients]`.
    ///
    /// The even and odd samples are real, so one complex FFT of the line read as complex pairs
    /// (even + i·odd) carries both their spectra, and since the scaling and wavelet halves
    /// come out real, one inverse FFT of (scaling + i·wavelet) returns both: two FFTs of half
    /// the line's length per step instead of four.
    pub fn analyze(&self, line: &mut [f64], scratch: &mut LineScratch) {
        let plan = self
            .plans
            .get(&line.len())
            .expect("Dwt1d::prepare was not called for this length");
        let h = plan.half;
        scratch.resize(h, plan.fft.get_inplace_scratch_len());
        let (pairs, halves) = (&mut scratch.even, &mut scratch.odd);
        for (z, pair) in pairs.iter_mut().zip(line.chunks_exact(2)) {
            *z = Complex64::new(pair[0], pair[1]);
        }
        plan.fft.process_with_scratch(pairs, &mut scratch.fft);
        let ab = &plan.alpha_beta;
        halves[0] = ab[0].0 * pairs[0] + ab[0].1 * pairs[0].conj();
        for n in 1..h {
            halves[n] = ab[n].0 * pairs[n] + ab[n].1 * pairs[h - n].conj();
        }
        plan.ifft.process_with_scratch(halves, &mut scratch.fft);
        let (c1, d1) = line.split_at_mut(h);
        for ((c, d), v) in c1.iter_mut().zip(d1).zip(halves.iter()) {
            *c = v.re;
            *d = v.im;
        }
    }

    /// One synthesis step in place: `[scaling | wavelet]` becomes the finer scaling
    /// coefficients, by the circular FIR two-scale relation.
    pub fn synthesize(&self, line: &mut [f64], scratch: &mut LineScratch) {
        synthesize_with(&self.p, &self.q, line, &mut scratch.real);
    }
}

/// Circular synthesis c0[(2k + i) mod n] += c1[k] p[i] + d1[k] q[i].
fn synthesize_with(p: &[f64], q: &[f64], line: &mut [f64], out: &mut Vec<f64>) {
    let n = line.len();
    let h = n / 2;
    out.clear();
    out.resize(n, 0.0);
    for k in 0..h {
        let (c, d) = (line[k], line[h + k]);
        for (i, pi) in p.iter().enumerate() {
            out[(2 * k + i) % n] += c * pi;
        }
        for (i, qi) in q.iter().enumerate() {
            out[(2 * k + i) % n] += d * qi;
        }
    }
    line.copy_from_slice(out);
}

/// Transpose of [`synthesize_with`]: c1[k] = Σ_i c0[(2k + i) mod n] p[i], d1[k] likewise with q
/// (inner products with the primal filters; not the analysis, which uses the duals).
fn synthesize_adjoint_with(p: &[f64], q: &[f64], line: &mut [f64], out: &mut Vec<f64>) {
    let n = line.len();
    let h = n / 2;
    out.clear();
    out.resize(n, 0.0);
    for k in 0..h {
        let mut c = 0.0;
        for (i, pi) in p.iter().enumerate() {
            c += line[(2 * k + i) % n] * pi;
        }
        let mut d = 0.0;
        for (i, qi) in q.iter().enumerate() {
            d += line[(2 * k + i) % n] * qi;
        }
        out[k] = c;
        out[h + k] = d;
    }
    line.copy_from_slice(out);
}

/// Reusable per-thread buffers for line transforms.
#[derive(Default)]
pub struct LineScratch {
    even: Vec<Complex64>,
    odd: Vec<Complex64>,
    fft: Vec<Complex64>,
    real: Vec<f64>,
}

impl LineScratch {
    fn resize(&mut self, half: usize, fft_scratch: usize) {
        self.even.resize(half, Complex64::default());
        self.odd.resize(half, Complex64::default());
        self.fft.resize(fft_scratch, Complex64::default());
    }
}

/// Elements of each of the z axis's two batch buffers (8 MB of f64 each).
const BATCH_ELEMENTS: usize = 1 << 20;

/// Runs `f(state, i, chunk)` on the first `count` chunks of `size` elements of `data` (on the
/// rayon pool with the `rayon` feature; each worker's `state` starts from `init`).
fn for_each_chunk<T: Send, S>(
    data: &mut [T],
    size: usize,
    count: usize,
    init: impl Fn() -> S + Sync + Send,
    f: impl Fn(&mut S, usize, &mut [T]) + Sync + Send,
) {
    #[cfg(feature = "rayon")]
    {
        use rayon::prelude::*;
        data.par_chunks_mut(size)
            .take(count)
            .enumerate()
            .for_each_init(init, |s, (i, chunk)| f(s, i, chunk));
    }
    #[cfg(not(feature = "rayon"))]
    {
        let mut s = init();
        for (i, chunk) in data.chunks_mut(size).take(count).enumerate() {
            f(&mut s, i, chunk);
        }
    }
}

/// Applies `op` to every line along `axis` of the block `block` (a corner of the array of
/// dimensions `full`, x fastest). Each line is handed to `op` contiguous:
/// - x lines are rows of the array, transformed where they lie;
/// - y lines of one z slab are gathered into a panel (one line per x) that stays in the
///   core's cache, transformed, and put back, slab by slab;
/// - z lines are gathered per y row from every slab (one line per x), transformed and turned
///   back into rows in a bounded batch buffer, then each slab takes its rows back.
///
/// Every line is computed the same way whatever thread runs it, so the result does not depend
/// on the thread count.
fn for_each_line(
    data: &mut [f64],
    full: [usize; 3],
    block: [usize; 3],
    axis: usize,
    op: &(dyn Fn(&mut [f64], &mut LineScratch) + Sync),
) {
    let len = block[axis];
    let (row, plane) = (full[0], full[0] * full[1]);
    let width = block[0];
    match axis {
        0 => for_each_chunk(data, plane, block[2], LineScratch::default, |s, _, slab| {
            for y in 0..block[1] {
                op(&mut slab[y * row..y * row + len], s);
            }
        }),
        1 => for_each_chunk(
            data,
            plane,
            block[2],
            <(LineScratch, Vec<f64>)>::default,
            |(s, lines), _, slab| {
                lines.resize(width * len, 0.0);
                for y in 0..len {
                    for (x, v) in slab[y * row..y * row + width].iter().enumerate() {
                        lines[x * len + y] = *v;
                    }
                }
                for line in lines.chunks_mut(len) {
                    op(line, s);
                }
                for y in 0..len {
                    for (x, v) in slab[y * row..y * row + width].iter_mut().enumerate() {
                        *v = lines[x * len + y];
                    }
                }
            },
        ),
        _ => {
            let per_y = width * len;
            let batch = (BATCH_ELEMENTS / per_y.max(1)).clamp(1, block[1].max(1));
            let mut lines = vec![0.0f64; batch * per_y];
            let mut rows = vec![0.0f64; batch * per_y];
            let mut y0 = 0;
            while y0 < block[1] {
                let count = batch.min(block[1] - y0);
                let shared = &*data;
                // One y row: its z lines gathered (one per x), transformed, and laid out as
                // the rows its slabs take back (z-major).
                let one_row =
                    |s: &mut LineScratch, i: usize, lines: &mut [f64], rows: &mut [f64]| {
                        let y = y0 + i;
                        for z in 0..len {
                            let src = &shared[z * plane + y * row..z * plane + y * row + width];
                            for (x, v) in src.iter().enumerate() {
                                lines[x * len + z] = *v;
                            }
                        }
                        for line in lines.chunks_mut(len) {
                            op(line, s);
                        }
                        for (x, line) in lines.chunks(len).enumerate() {
                            for (z, v) in line.iter().enumerate() {
                                rows[z * width + x] = *v;
                            }
                        }
                    };
                let (lines, rows) = (&mut lines[..count * per_y], &mut rows[..count * per_y]);
                #[cfg(feature = "rayon")]
                {
                    use rayon::prelude::*;
                    lines
                        .par_chunks_mut(per_y)
                        .zip(rows.par_chunks_mut(per_y))
                        .enumerate()
                        .for_each_init(LineScratch::default, |s, (i, (l, r))| one_row(s, i, l, r));
                }
                #[cfg(not(feature = "rayon"))]
                {
                    let mut s = LineScratch::default();
                    for (i, (l, r)) in lines
                        .chunks_mut(per_y)
                        .zip(rows.chunks_mut(per_y))
                        .enumerate()
                    {
                        one_row(&mut s, i, l, r);
                    }
                }
                let rows = &*rows;
                for_each_chunk(
                    data,
                    plane,
                    len,
                    || (),
                    |_, z, slab| {
                        for i in 0..count {
                            let at = (y0 + i) * row;
                            let from = i * per_y + z * width;
                            slab[at..at + width].copy_from_slice(&rows[from..from + width]);
                        }
                    },
                );
                y0 += count;
            }
        }
    }
}

/// Applies a line step fine to coarse: levels 1..=M, axes x, y, z, each on the current scaling
/// block (the order of the forward transform and of the synthesis' transpose).
fn fine_to_coarse(
    data: &mut [f64],
    geometry: &Geometry,
    op: &(dyn Fn(&mut [f64], &mut LineScratch) + Sync),
) {
    assert_eq!(data.len(), geometry.coefficient_count());
    let full = geometry.padded;
    for level in 1..=geometry.levels {
        let block = [
            full[0] >> (level - 1),
            full[1] >> (level - 1),
            full[2] >> (level - 1),
        ];
        for axis in 0..3 {
            for_each_line(data, full, block, axis, op);
        }
    }
}

/// Forward 3D non-standard transform of a padded channel, in place (Mallat layout), by
/// recursive filters on panels of lines ([`recursive`]).
pub fn forward_3d(data: &mut [f64], geometry: &Geometry, planner: &mut Dwt1d) {
    assert_eq!(data.len(), geometry.coefficient_count());
    match &planner.recursive {
        Some(analysis) => recursive::forward_3d(data, geometry.padded, geometry.levels, analysis),
        None => forward_3d_fft(data, geometry, planner),
    }
}

/// Forward 3D non-standard transform by the FFT analysis of each line: the reference that
/// [`forward_3d`] is tested against (the same result to rounding, several times slower).
pub fn forward_3d_fft(data: &mut [f64], geometry: &Geometry, planner: &mut Dwt1d) {
    planner.prepare(geometry);
    let planner = &*planner;
    fine_to_coarse(data, geometry, &|line, s| planner.analyze(line, s));
}

/// Inverse 3D non-standard transform, in place: coefficients (Mallat layout) to the padded
/// voxel grid.
pub fn inverse_3d(data: &mut [f64], geometry: &Geometry, planner: &mut Dwt1d) {
    assert_eq!(data.len(), geometry.coefficient_count());
    planner.prepare(geometry);
    let planner = &*planner;
    let full = geometry.padded;
    for level in (1..=geometry.levels).rev() {
        let block = [
            full[0] >> (level - 1),
            full[1] >> (level - 1),
            full[2] >> (level - 1),
        ];
        for axis in (0..3).rev() {
            for_each_line(data, full, block, axis, &|line, s| {
                planner.synthesize(line, s)
            });
        }
    }
}

/// Transpose of [`inverse_3d`], in place: padded grid to, per basis function, the inner product
/// Σ_x data(x)·b(x) over the grid points (with `coefficients_to_samples` folded in by the caller).
/// Used by least-squares refitting of a sparse coefficient set.
pub fn inverse_3d_adjoint(data: &mut [f64], geometry: &Geometry, planner: &Dwt1d) {
    fine_to_coarse(data, geometry, &|line, s| {
        synthesize_adjoint_with(&planner.p, &planner.q, line, &mut s.real)
    });
}

/// Copies a channel of the volume into the zero-padded grid of `geometry` (as f64).
pub fn pad_channel(channel: &[f32], geometry: &Geometry) -> Vec<f64> {
    pad_channel_as(channel, geometry, f64::from)
}

/// Copies a channel of the volume into the zero-padded grid of `geometry`, each sample
/// converted by `convert` (`f64::from` for [`pad_channel`]; the identity for f32 work).
pub fn pad_channel_as<T: Copy + Default + Send + Sync>(
    channel: &[f32],
    geometry: &Geometry,
    convert: impl Fn(f32) -> T + Sync + Send,
) -> Vec<T> {
    let [nx, ny, nz] = geometry.dims;
    let [px, py, _] = geometry.padded;
    let [ox, oy, oz] = geometry.origin;
    // Written out in full rather than allocated zeroed: zeroed pages are mapped lazily, first
    // to the shared zero page on a read, and the transform's first write to each of them
    // then cost a copy-on-write fault and a TLB shootdown across the pool's threads. The
    // planes are written by the pool's threads together.
    let n = geometry.coefficient_count();
    let mut out: Vec<T> = Vec::with_capacity(n);
    #[cfg(feature = "rayon")]
    {
        use rayon::prelude::*;
        out.par_extend(rayon::iter::repeat_n(T::default(), n));
    }
    #[cfg(not(feature = "rayon"))]
    out.resize(n, T::default());
    let plane = px * py;
    for_each_chunk(
        &mut out,
        plane,
        n / plane.max(1),
        || (),
        |_, pz, slab| {
            let Some(z) = pz.checked_sub(oz).filter(|z| *z < nz) else {
                return;
            };
            for y in 0..ny {
                let src = nx * (y + ny * z);
                let dst = ox + px * (oy + y);
                for (o, v) in slab[dst..dst + nx].iter_mut().zip(&channel[src..src + nx]) {
                    *o = convert(*v);
                }
            }
        },
    );
    out
}

/// Cuts the volume out of a padded grid (inverse of [`pad_channel`]).
pub fn crop_channel(padded: &[f64], geometry: &Geometry) -> Vec<f32> {
    let [nx, ny, nz] = geometry.dims;
    let [px, py, _] = geometry.padded;
    let [ox, oy, oz] = geometry.origin;
    let mut out = vec![0.0f32; nx * ny * nz];
    for z in 0..nz {
        for y in 0..ny {
            let dst = nx * (y + ny * z);
            let src = ox + px * ((oy + y) + py * (oz + z));
            for x in 0..nx {
                out[dst + x] = padded[src + x] as f32;
            }
        }
    }
    out
}

/// Values of the centred φ at the integers, φ(d + j/2) for d = −r..=r: the FIR that samples a
/// spline at the voxel centres. A single 1 for Haar and linear.
pub fn interpolation_taps(family: Family) -> Vec<f64> {
    let j = family.order() as f64;
    let r = family.order() as i64;
    let taps: Vec<f64> = (-r..=r).map(|d| family.phi(d as f64 + 0.5 * j)).collect();
    let first = taps.iter().position(|t| *t != 0.0).unwrap_or(0);
    let last = taps.iter().rposition(|t| *t != 0.0).unwrap_or(0);
    taps[first..=last].to_vec()
}

/// Converts voxel samples (padded grid) into spline coefficients in place: the exact periodic
/// interpolation prefilter, per axis, by the all-pole inverse of the sampling FIR (for cubic,
/// 6 / (z + 4 + z⁻¹): one pole, √3 − 2, causal and anti-causal). No-op for Haar and linear.
pub fn samples_to_coefficients(data: &mut [f64], geometry: &Geometry) {
    let taps = interpolation_taps(geometry.family);
    if taps.len() == 1 {
        return;
    }
    match recursive::AllPole::of_symmetric(&taps) {
        Some(filter) => recursive::prefilter_3d(data, geometry.padded, &filter),
        None => samples_to_coefficients_fft(data, geometry),
    }
}

/// [`samples_to_coefficients`] by division by the FIR's symbol in the DFT domain (the cubic
/// symbol (4 + 2cos ω)/6 ≥ 1/3 never vanishes): the reference it is tested against.
pub fn samples_to_coefficients_fft(data: &mut [f64], geometry: &Geometry) {
    let taps = interpolation_taps(geometry.family);
    if taps.len() == 1 {
        return;
    }
    let r = (taps.len() / 2) as i64;
    for axis in 0..3 {
        let len = geometry.padded[axis];
        let mut planner = FftPlanner::<f64>::new();
        let fft = planner.plan_fft_forward(len);
        let ifft = planner.plan_fft_inverse(len);
        let symbol: Vec<f64> = (0..len)
            .map(|n| {
                taps.iter()
                    .enumerate()
                    .map(|(i, t)| {
                        let d = i as i64 - r;
                        t * (2.0 * std::f64::consts::PI * (n as i64 * d) as f64 / len as f64).cos()
                    })
                    .sum::<f64>()
                    * len as f64
            })
            .collect();
        let op = |line: &mut [f64], s: &mut LineScratch| {
            s.even.clear();
            s.even.extend(line.iter().map(|v| Complex64::new(*v, 0.0)));
            s.fft.resize(
                fft.get_inplace_scratch_len()
                    .max(ifft.get_inplace_scratch_len()),
                Complex64::default(),
            );
            fft.process_with_scratch(&mut s.even, &mut s.fft);
            for (c, d) in s.even.iter_mut().zip(&symbol) {
                *c /= *d;
            }
            ifft.process_with_scratch(&mut s.even, &mut s.fft);
            for (v, c) in line.iter_mut().zip(&s.even) {
                *v = c.re;
            }
        };
        for_each_line(data, geometry.padded, geometry.padded, axis, &op);
    }
}

/// Samples the spline at the voxel centres in place (inverse of [`samples_to_coefficients`]):
/// circular convolution with [`interpolation_taps`] along each axis. No-op for Haar and linear.
pub fn coefficients_to_samples(data: &mut [f64], geometry: &Geometry) {
    let taps = interpolation_taps(geometry.family);
    if taps.len() == 1 {
        return;
    }
    for axis in 0..3 {
        let op = |line: &mut [f64], s: &mut LineScratch| {
            sample_with(&taps, line, &mut s.real);
            line.copy_from_slice(&s.real);
        };
        for_each_line(data, geometry.padded, geometry.padded, axis, &op);
    }
}

/// Circular convolution of `line` with the centred `taps` into `out`.
fn sample_with(taps: &[f64], line: &[f64], out: &mut Vec<f64>) {
    let n = line.len() as i64;
    let r = (taps.len() / 2) as i64;
    out.clear();
    out.extend((0..n).map(|i| {
        taps.iter()
            .enumerate()
            .map(|(t, w)| w * line[(i + t as i64 - r).rem_euclid(n) as usize])
            .sum::<f64>()
    }));
}

/// One periodic line of voxel samples of the level-`level` φ (`wavelet` false) or ψ with index 0,
/// on a line of `len` voxels (a multiple of 2^level): the unit coefficient synthesized down to
/// level 0 and, for cubic, sampled at the voxel centres (with `sampled`; otherwise the level-0
/// B-spline coefficients).
pub fn unit_basis_line(
    family: Family,
    len: usize,
    level: usize,
    wavelet: bool,
    sampled: bool,
) -> Vec<f64> {
    let mut line = vec![0.0; len];
    line[if wavelet { len >> level } else { 0 }] = 1.0;
    let planner = Dwt1d::new(family);
    let mut scratch = LineScratch::default();
    for l in (1..=level).rev() {
        planner.synthesize(&mut line[..len >> (l - 1)], &mut scratch);
    }
    if sampled {
        let mut out = Vec::new();
        sample_with(&interpolation_taps(family), &line, &mut out);
        out
    } else {
        line
    }
}

/// Convenience: pads a channel (voxel samples), converts it to spline coefficients and returns
/// its wavelet coefficients (Mallat layout).
pub fn decompose_channel(channel: &[f32], geometry: &Geometry) -> Vec<f64> {
    let mut data = pad_channel(channel, geometry);
    samples_to_coefficients(&mut data, geometry);
    forward_3d(&mut data, geometry, &mut Dwt1d::new(geometry.family));
    data
}

/// Convenience: reconstructs a channel's voxel samples (cropped to the volume) from all its
/// wavelet coefficients.
pub fn reconstruct_channel(coefficients: &[f64], geometry: &Geometry) -> Vec<f32> {
    let mut data = coefficients.to_vec();
    inverse_3d(&mut data, geometry, &mut Dwt1d::new(geometry.family));
    coefficients_to_samples(&mut data, geometry);
    crop_channel(&data, geometry)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::layout::Band;
    use rand::{Rng, SeedableRng};

    fn rel_l2(a: &[f64], b: &[f64]) -> f64 {
        let num: f64 = a.iter().zip(b).map(|(x, y)| (x - y).powi(2)).sum();
        let den: f64 = b.iter().map(|y| y * y).sum::<f64>().max(1e-300);
        (num / den).sqrt()
    }

    /// Periodic Gram matrix of the level-0 translates φ(x − k) on a circle of length n.
    fn gram0(fam: Family, n: usize) -> Vec<Vec<f64>> {
        let j = fam.order() as i64;
        let mut g = vec![vec![0.0; n]; n];
        for a in 0..n {
            for lag in -(j)..=j {
                let b = (a as i64 + lag).rem_euclid(n as i64) as usize;
                g[a][b] += fam.phi_autocorrelation(lag);
            }
        }
        g
    }

    #[test]
    fn analysis_is_the_orthogonal_projection() {
        // Naive reference: the detail part of the decomposition, as a function, must be
        // orthogonal (in L2 of the circle) to every coarse scaling function, and the two parts
        // must add up to the input. Checked with the dense periodic Gram matrix.
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        for fam in Family::ALL {
            for n in [2usize, 4, 6, 16, 34] {
                let x: Vec<f64> = (0..n).map(|_| rng.gen_range(-1.0..1.0)).collect();
                let mut planner = Dwt1d::new(fam);
                planner.plan(n);
                let mut y = x.clone();
                let mut s = LineScratch::default();
                planner.analyze(&mut y, &mut s);
                let h = n / 2;
                let mut coarse = y.clone();
                coarse[h..].iter_mut().for_each(|v| *v = 0.0);
                let mut detail = y.clone();
                detail[..h].iter_mut().for_each(|v| *v = 0.0);
                planner.synthesize(&mut coarse, &mut s);
                planner.synthesize(&mut detail, &mut s);
                let sum: Vec<f64> = coarse.iter().zip(&detail).map(|(a, b)| a + b).collect();
                assert!(rel_l2(&sum, &x) < 1e-12, "{fam} n={n}");
                let g = gram0(fam, n);
                for k in 0..h {
                    let mut basis = vec![0.0; n];
                    basis[k] = 1.0;
                    planner.synthesize(&mut basis, &mut s);
                    let ip: f64 = (0..n)
                        .map(|a| (0..n).map(|b| detail[a] * g[a][b] * basis[b]).sum::<f64>())
                        .sum();
                    assert!(ip.abs() < 1e-12, "{fam} n={n} k={k}: {ip}");
                }
            }
        }
    }

    /// ⟨inverse(c), s⟩ = ⟨c, adjoint(s)⟩ for random c, s: the adjoint is the exact transpose
    /// (checked on non-cubic padded grids and every depth).
    #[test]
    fn inverse_adjoint_is_the_transpose() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        for fam in Family::ALL {
            for (dims, levels) in [
                ([6usize, 10, 4], 1usize),
                ([12, 8, 20], 2),
                ([16, 16, 8], 3),
            ] {
                let g = Geometry::new(dims, fam, levels, 0).unwrap();
                let n = g.coefficient_count();
                let c: Vec<f64> = (0..n).map(|_| rng.gen_range(-1.0..1.0)).collect();
                let s: Vec<f64> = (0..n).map(|_| rng.gen_range(-1.0..1.0)).collect();
                let mut planner = Dwt1d::new(fam);
                let mut rc = c.clone();
                inverse_3d(&mut rc, &g, &mut planner);
                let mut rts = s.clone();
                inverse_3d_adjoint(&mut rts, &g, &planner);
                let lhs: f64 = rc.iter().zip(&s).map(|(a, b)| a * b).sum();
                let rhs: f64 = c.iter().zip(&rts).map(|(a, b)| a * b).sum();
                assert!(
                    (lhs - rhs).abs() <= 1e-10 * lhs.abs().max(1.0),
                    "{fam} {dims:?} M={levels}: {lhs} vs {rhs}"
                );
            }
        }
    }

    #[test]
    fn perfect_reconstruction_3d_all_families_and_levels() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        for fam in Family::ALL {
            for dims in [
                [1usize, 1, 7],
                [5, 6, 7],
                [8, 8, 8],
                [3, 17, 4],
                [16, 9, 12],
            ] {
                let vol: Vec<f32> = (0..dims.iter().product())
                    .map(|_| rng.gen_range(-100.0..100.0))
                    .collect();
                for levels in 0..=Geometry::max_levels(dims) {
                    let g = Geometry::new(dims, fam, levels, 1).unwrap();
                    let coeffs = decompose_channel(&vol, &g);
                    let back = reconstruct_channel(&coeffs, &g);
                    let a: Vec<f64> = back.iter().map(|v| *v as f64).collect();
                    let b: Vec<f64> = vol.iter().map(|v| *v as f64).collect();
                    let e = rel_l2(&a, &b);
                    // f32 output of an f64 transform: limited by the final rounding to f32.
                    assert!(e < 1e-6, "{fam} {dims:?} M={levels}: rel L2 {e}");
                    // And in f64, without the f32 round trip:
                    let mut data = coeffs.clone();
                    inverse_3d(&mut data, &g, &mut Dwt1d::new(fam));
                    coefficients_to_samples(&mut data, &g);
                    let padded = pad_channel(&vol, &g);
                    let e64 = rel_l2(&data, &padded);
                    assert!(e64 < 1e-12, "{fam} {dims:?} M={levels}: f64 rel L2 {e64}");
                }
            }
        }
    }

    /// The 3D transform by recursive filters against the FFT reference: every family, odd and
    /// one-voxel dimensions, every depth, and values from tiny to huge (relative to the
    /// volume's own size: both are linear).
    #[test]
    fn the_recursive_3d_transform_equals_the_fft_one() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(23);
        for fam in Family::ALL {
            for dims in [
                [1usize, 1, 1],
                [1, 1, 9],
                [5, 6, 7],
                [3, 17, 4],
                [33, 20, 9],
            ] {
                for levels in 0..=Geometry::max_levels(dims) {
                    for magnitude in [1e-30, 1.0, 1e30] {
                        let g = Geometry::new(dims, fam, levels, 1).unwrap();
                        let vol: Vec<f32> = (0..dims.iter().product())
                            .map(|_| rng.gen_range(-1.0f32..1.0) * magnitude as f32)
                            .collect();
                        let mut want = pad_channel(&vol, &g);
                        samples_to_coefficients_fft(&mut want, &g);
                        forward_3d_fft(&mut want, &g, &mut Dwt1d::new(fam));
                        let mut got = pad_channel(&vol, &g);
                        samples_to_coefficients(&mut got, &g);
                        forward_3d(&mut got, &g, &mut Dwt1d::new(fam));
                        let e = rel_l2(&got, &want);
                        assert!(e < 1e-13, "{fam} {dims:?} M={levels} ×{magnitude}: {e}");
                    }
                }
            }
            // A constant and a zero volume stay exact.
            let g = Geometry::new([12, 10, 6], fam, 1, 0).unwrap();
            let zero = decompose_channel(&[0.0; 720], &g);
            assert!(zero.iter().all(|v| *v == 0.0), "{fam}");
        }
    }

    #[test]
    fn interpolation_prefilter_inverts_sampling() {
        assert_eq!(interpolation_taps(Family::Haar), vec![1.0]);
        assert_eq!(interpolation_taps(Family::Linear), vec![1.0]);
        let t = interpolation_taps(Family::Cubic);
        assert_eq!(t.len(), 3);
        assert!((t[1] - 2.0 / 3.0).abs() < 1e-15 && (t[0] - 1.0 / 6.0).abs() < 1e-15);
        let g = Geometry::new([7, 5, 3], Family::Cubic, 0, 0).unwrap();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let v: Vec<f64> = (0..105).map(|_| rng.gen_range(-5.0..5.0)).collect();
        let mut c = v.clone();
        samples_to_coefficients(&mut c, &g);
        // Independent check: the spline through c, evaluated at voxel centres, gives v.
        let f = |x: usize, y: usize, z: usize| -> f64 {
            let mut s = 0.0;
            for (i, ci) in c.iter().enumerate() {
                let (a, b, d) = (i % 7, (i / 7) % 5, i / 35);
                let w = |p: usize, q: usize, n: usize| {
                    // periodic distance
                    let mut dd = p as f64 - q as f64;
                    if dd > n as f64 / 2.0 {
                        dd -= n as f64;
                    }
                    if dd < -(n as f64) / 2.0 {
                        dd += n as f64;
                    }
                    Family::Cubic.phi(dd + 2.0)
                };
                s += ci * w(x, a, 7) * w(y, b, 5) * w(z, d, 3);
            }
            s
        };
        for (x, y, z) in [(0, 0, 0), (3, 2, 1), (6, 4, 2)] {
            assert!((f(x, y, z) - v[x + 7 * (y + 5 * z)]).abs() < 1e-9);
        }
        coefficients_to_samples(&mut c, &g);
        assert!(rel_l2(&c, &v) < 1e-13);
    }

    #[test]
    fn constant_volume_lives_in_the_scaling_band() {
        for fam in Family::ALL {
            let g = Geometry::new([8, 8, 8], fam, 2, 0).unwrap();
            let coeffs = decompose_channel(&vec![3.0; 512], &g);
            for (i, c) in coeffs.iter().enumerate() {
                let (band, _) = g.locate(i);
                if band.kind != 0 {
                    assert!(c.abs() < 1e-10, "{fam} {band:?} {c}");
                }
            }
            let b0 = Band { level: 2, kind: 0 };
            let c = coeffs[g.linear_index(b0, [0, 0, 0])];
            // Partition of unity: Σ φ(x − k) = 1, so a constant c has coefficient c at every level.
            assert!((c - 3.0).abs() < 1e-10, "{fam} {c}");
        }
    }
}
