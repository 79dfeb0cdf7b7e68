//! The Fourier projection-slice: a basis function's 3D transform sampled on the view's slice,
//! depth-cued per axis, times the pixel box, inverse-FFT'd and cropped to its support, for every
//! (level, type) of a view; grid sizes and support radii.

use super::FineTable;
use super::FootprintParams;
use num_complex::Complex64;
use rayon::prelude::*;
use rustfft::FftPlanner;
use std::f64::consts::PI;
use wavesplat_codec::family::{box_transform, Family};
use wavesplat_codec::view::sinc;

/// The 1D transforms of a family with its wavelet filter cached and factored (the codec's
/// `psi_hat` recomputes the filter from order-2j B-splines at every call, far too slow for
/// millions of samples, and sums Σ q_n z^n, which cancels catastrophically near f = 0 where it
/// vanishes like f^j). Here Q(z) = Σ q_n z^n is divided exactly by its j-fold zero at z = 1,
/// Q(z) = (1 − z)^j P(z), and 1 − e^(−x) = x·E(x) is evaluated by the codec's stable
/// `box_transform`; so ψ̂ keeps full relative precision down to f = 0. Same function as
/// `Family::psi_hat` (cued relative to the support end nearest the light), checked in tests.
#[derive(Debug, Clone)]
pub struct Transforms {
    family: Family,
    /// P(z) coefficients.
    p: Vec<f64>,
    /// q_(N−n) = sign · q_n.
    sign: f64,
}

impl Transforms {
    /// Caches the factored filter of `family`.
    pub fn new(family: Family) -> Transforms {
        let j = family.order();
        let mut c = family.wavelet_filter();
        for _ in 0..j {
            // Q = (1 − z) P: p_n = q_n + p_(n−1); the last coefficient is the remainder (≈ 0).
            let mut acc = 0.0;
            for v in c.iter_mut() {
                acc += *v;
                *v = acc;
            }
            c.pop();
        }
        Transforms {
            family,
            p: c,
            sign: if family.psi_is_odd() { -1.0 } else { 1.0 },
        }
    }

    /// The family.
    pub fn family(&self) -> Family {
        self.family
    }

    /// ∫ φ(x) e^(−κ(x − x_near)) e^(−i2πfx) dx (uncentred, as `Family::phi_hat`).
    pub fn phi_hat(&self, f: f64, kappa: f64) -> Complex64 {
        self.family.phi_hat(f, kappa)
    }

    /// ∫ ψ(x) e^(−κ(x − x_near)) e^(−i2πfx) dx (uncentred, as `Family::psi_hat`).
    pub fn psi_hat(&self, f: f64, kappa: f64) -> Complex64 {
        let j = self.family.order() as i32;
        let half = self.family.phi_hat(0.5 * f, 0.5 * kappa);
        // s/2 with s = κ + i2πf; Q evaluated at ζ = e^(−s/2) (κ ≥ 0) or, reversed, at
        // e^(+s/2) (κ < 0), so |ζ| ≤ 1 and nothing overflows.
        let h = Complex64::new(0.5 * kappa, PI * f);
        let (x, pre) = if kappa >= 0.0 {
            (h, Complex64::new(1.0, 0.0))
        } else {
            let n = (self.p.len() + j as usize - 1) as f64;
            (-h, Complex64::from_polar(self.sign, -PI * f * n))
        };
        let zeta = (-x).exp();
        let one_minus = x * box_transform(x);
        let mut poly = Complex64::new(0.0, 0.0);
        for c in self.p.iter().rev() {
            poly = poly * zeta + *c;
        }
        pre * one_minus.powi(j) * poly * half * 0.5
    }
}

/// 1D transform of the centred, level-m dilated φ or ψ at frequency ξ (cycles per voxel), with
/// cue exponent κ (already multiplied by 2^m): 2^m · ĥ(2^m ξ, κ) · e^{+i2π 2^m ξ c}.
pub fn axis_transform(
    tf: &Transforms,
    level: usize,
    wavelet: bool,
    xi: f64,
    kappa: f64,
) -> Complex64 {
    let s = (1u64 << level) as f64;
    let f = s * xi;
    let j = tf.family.order() as f64;
    let (h, c) = if wavelet {
        (tf.psi_hat(f, kappa), 0.5 * (2.0 * j - 1.0))
    } else {
        (tf.phi_hat(f, kappa), 0.5 * j)
    };
    h * Complex64::from_polar(s, 2.0 * PI * f * c)
}

/// The uncued (κ = 0) level-m φ and ψ axis transforms at ξ, `[φ, ψ]`: the values of
/// [`axis_transform`] with κ = 0, from one sine–cosine pair instead of six. Centred, the
/// transforms are closed forms in the half angle πf/2 (f = 2^m ξ): with z = e^(−iπf),
/// 2^m φ̂ = 2^m sinc(f)^j, and 2^m ψ̂ = 2^(m−1) (2i sin(πf/2))^j sinc(f/2)^j P(z) e^(iπf(j−1)), where
/// P is [`Transforms`]'s factored filter (1 − z = e^(−iπf/2) 2i sin(πf/2) and
/// E(iπf) = e^(−iπf/2) sinc(f/2) collect into the last factor). No term cancels, so both keep full
/// relative precision down to f = 0. Evaluating the spectra of a view's footprints is most of
/// planning it, and there every sample needs both transforms on each of the three axes.
pub fn axis_transforms_uncued(tf: &Transforms, level: usize, xi: f64) -> [Complex64; 2] {
    let s = (1u64 << level) as f64;
    let f = s * xi;
    let j = tf.family.order() as i32;
    let half = 0.5 * PI * f;
    let (sh, ch) = half.sin_cos();
    let sinc_half = if half.abs() < 1e-8 {
        1.0 - half * half / 6.0
    } else {
        sh / half
    };
    let sinc_full = sinc_half * ch;
    let phi = Complex64::new(s * sinc_full.powi(j), 0.0);
    // z = e^(−iπf) from the half angle: cos πf = 1 − 2 sin²(πf/2), sin πf = 2 sin cos.
    let zeta = Complex64::new(1.0 - 2.0 * sh * sh, -2.0 * sh * ch);
    let mut poly = Complex64::new(0.0, 0.0);
    for c in tf.p.iter().rev() {
        poly = poly * zeta + *c;
    }
    let turn = zeta.conj().powi(j - 1);
    let psi = Complex64::new(0.0, 2.0 * sh).powi(j) * (0.5 * s * sinc_half.powi(j)) * poly * turn;
    [phi, psi]
}

/// The 3D transform of the centred level-m basis of type `kind` at ξ (cycles per voxel), cued
/// with κ = k·L̂·2^m per axis (zero without cue).
pub fn basis_transform(
    family: Family,
    level: usize,
    kind: u8,
    xi: [f64; 3],
    kappa: [f64; 3],
) -> Complex64 {
    let tf = Transforms::new(family);
    (0..3)
        .map(|a| axis_transform(&tf, level, kind & (4 >> a) != 0, xi[a], kappa[a]))
        .product()
}

/// The pixel-averaged footprint spectrum P̂(σ, ρ) (σ, ρ in cycles per pixel).
pub fn footprint_spectrum(
    p: &FootprintParams,
    level: usize,
    kind: u8,
    sigma: f64,
    rho: f64,
) -> Complex64 {
    let xi = [
        p.zoom * (sigma * p.ex[0] + rho * p.ey[0]),
        p.zoom * (sigma * p.ex[1] + rho * p.ey[1]),
        p.zoom * (sigma * p.ex[2] + rho * p.ey[2]),
    ];
    let kappa = cue_kappa(p, level);
    basis_transform(p.family, level, kind, xi, kappa)
        * (p.zoom * p.zoom * p.voxel_volume * sinc(sigma) * sinc(rho))
}

fn cue_kappa(p: &FootprintParams, level: usize) -> [f64; 3] {
    match p.cue {
        None => [0.0; 3],
        Some((k, l)) => {
            let s = (1u64 << level) as f64;
            [k * l[0] * s, k * l[1] * s, k * l[2] * s]
        }
    }
}

/// Half extents (pixels) of the pixel-widened projected support of a level-m type.
pub fn support_radius(p: &FootprintParams, level: usize, kind: u8) -> (f64, f64) {
    let s = (1u64 << level) as f64;
    let mut rx = 0.5;
    let mut ry = 0.5;
    for a in 0..3 {
        let h = 0.5
            * s
            * if kind & (4 >> a) != 0 {
                p.family.psi_support()
            } else {
                p.family.phi_support()
            };
        rx += p.zoom * h * p.ex[a].abs();
        ry += p.zoom * h * p.ey[a].abs();
    }
    (rx, ry)
}

/// Smallest n ≥ m (and even) whose prime factors are 2, 3, 5.
fn nice(m: usize) -> usize {
    let mut n = m.max(2);
    loop {
        if n.is_multiple_of(2) {
            let mut k = n;
            for p in [2, 3, 5] {
                while k.is_multiple_of(p) {
                    k /= p;
                }
            }
            if k == 1 {
                return n;
            }
        }
        n += 1;
    }
}

/// Table samples per standard deviation of a level's narrowest component that a table with
/// fewer phases must keep ([`level_subpixel`]). A footprint many pixels wide is smooth at the
/// pixel scale: placing it up to 1/(2S) pixel off, corrected to first order by the gradient
/// records, leaves an error of second order in 1/(S·σ), so its phases buy nothing and each
/// halving of S quarters its FFT. Without this a magnified view (a 10×10×15 volume at 256², 16
/// pixels per voxel) planned 1080×1350 FFTs for its coarsest level: 1.5 s for 2 888
/// coefficients.
const WIDE_SAMPLES_PER_DEVIATION: f64 = 8.0;

/// The phases a level's tables need when built on their own: `p.subpixel`, halved (down to
/// one) while the level's narrowest component keeps [`WIDE_SAMPLES_PER_DEVIATION`] samples per
/// standard deviation. That component is the level's φ, or for its wavelets the φ one level
/// finer that they are made of (the level-0 φ at level 0): 2^(max(m−1, 0))·√(j/12) voxels,
/// projected onto the screen axes (deviations add in quadrature over the voxel axes). Haar is
/// left at `p.subpixel`: a box's edge stays a pixel sharp at any magnification, and placing it
/// 1/(2S) pixel off is a first-order error the gradient records cannot correct (a 10×10×15
/// noise volume at 16 pixels per voxel on the axis: 46.7 dB against the exact image at the
/// requested S, 27.2 dB at one phase).
pub fn level_subpixel(p: &FootprintParams, level: usize) -> usize {
    if p.family == Family::Haar {
        return p.subpixel.max(1);
    }
    let deviation =
        (p.family.order() as f64 / 12.0).sqrt() * (1u64 << level.saturating_sub(1)) as f64;
    let projected = |e: [f64; 3]| p.zoom * deviation * e.iter().map(|v| v * v).sum::<f64>().sqrt();
    let narrowest = projected(p.ex).min(projected(p.ey));
    let mut s = p.subpixel.max(1);
    if !narrowest.is_finite() {
        return s;
    }
    while s > 1 && ((s / 2) as f64) * narrowest >= WIDE_SAMPLES_PER_DEVIATION {
        s /= 2;
    }
    s
}

/// FFT sizes and the subpixel factor for a level (largest type), asking for `s` phases (1, or
/// made even; halved while the grid would exceed `p.max_fft`, to no fewer than 2).
pub(super) fn sizes(p: &FootprintParams, level: usize, s: usize) -> (usize, usize, usize) {
    let mut rx: f64 = 0.0;
    let mut ry: f64 = 0.0;
    for kind in 0..8u8 {
        let (a, b) = support_radius(p, level, kind);
        rx = rx.max(a);
        ry = ry.max(b);
    }
    let mut s = s.max(1);
    if s > 1 {
        s += s % 2;
    }
    let need = |s: usize, r: f64| nice((s as f64 * (2.0 * r + 3.0)).ceil() as usize);
    while s > 2 && need(s, rx).max(need(s, ry)) > p.max_fft.max(16) {
        s = (s / 2).max(2);
        s += s % 2;
    }
    (s, need(s, rx), need(s, ry))
}

/// Computes the fine tables of the given types at `level` by FFT (all with the same S).
pub fn compute_fine(p: &FootprintParams, level: usize, kinds: &[u8]) -> Vec<FineTable> {
    compute_fine_at(p, level, kinds, p.subpixel)
}

/// [`compute_fine`] asking for `s` phases instead of `p.subpixel` (see [`sizes`]).
pub fn compute_fine_at(
    p: &FootprintParams,
    level: usize,
    kinds: &[u8],
    s: usize,
) -> Vec<FineTable> {
    let (s, nx, ny) = sizes(p, level, s);
    compute_fine_with(p, level, kinds, s, nx, ny)
}

pub(super) fn signed(k: usize, n: usize) -> f64 {
    if k < n / 2 {
        k as f64
    } else {
        k as f64 - n as f64
    }
}

/// The first row of an `n`-row frequency grid (rows at [`signed`] frequencies) whose mirror row,
/// at the negated frequency, is an earlier row: rows from here on can be filled from their
/// mirrors, since the spectra here are of real functions (conjugate-symmetric). Row 0 is its
/// own mirror and an even grid's Nyquist row has none, so they and the rows of positive
/// frequency come before it.
fn first_mirrored_row(n: usize) -> usize {
    (n - n / 2 + 1).min(n)
}

/// The column at the negated frequency of column `k` of an `n`-column grid, when the grid has
/// one.
#[inline]
fn mirror_column(k: usize, n: usize) -> Option<usize> {
    let m = (n - k) % n;
    (signed(m, n) == -signed(k, n)).then_some(m)
}

/// The columns of a frequency grid's row to evaluate for the spectrum of a real function: every
/// column in the rows before [`first_mirrored_row`], and in the mirrored rows after it only
/// those without a mirror (Nyquist);
/// [`fill_mirrored_rows`] fills the rest. A factor is a real function, so its transform at −ξ
/// is the conjugate of that at ξ, and in the floating point too, up to a zero's sign
/// (`conjugate_symmetry_is_exact` in tests/footprint.rs); products of such transforms too.
pub(super) struct MirroredGrid {
    nx: usize,
    ny: usize,
    head: usize,
    every: Vec<usize>,
    unmirrored: Vec<usize>,
}

impl MirroredGrid {
    /// The plan of an `nx` × `ny` grid.
    pub(super) fn new(nx: usize, ny: usize) -> MirroredGrid {
        MirroredGrid {
            nx,
            ny,
            head: first_mirrored_row(ny),
            every: (0..nx).collect(),
            unmirrored: (0..nx)
                .filter(|&kx| mirror_column(kx, nx).is_none())
                .collect(),
        }
    }

    /// The columns of row `ky` to evaluate.
    pub(super) fn columns(&self, ky: usize) -> &[usize] {
        if ky < self.head {
            &self.every
        } else {
            &self.unmirrored
        }
    }

    /// Fills the columns of the mirrored rows that [`MirroredGrid::columns`] left out (row-major
    /// `grid`), as the conjugates of their mirrors.
    pub(super) fn fill_mirrored_rows(&self, grid: &mut [Complex64]) {
        let (nx, ny) = (self.nx, self.ny);
        let (first, rest) = grid.split_at_mut(self.head * nx);
        let first = &*first;
        rest.par_chunks_mut(nx).enumerate().for_each(|(i, row)| {
            let my = ny - (self.head + i);
            let mirror = &first[my * nx..(my + 1) * nx];
            for (kx, v) in row.iter_mut().enumerate() {
                if let Some(mx) = mirror_column(kx, nx) {
                    *v = mirror[mx].conj();
                }
            }
        });
    }
}

/// As [`compute_fine`] with explicit S and FFT sizes.
pub fn compute_fine_with(
    p: &FootprintParams,
    level: usize,
    kinds: &[u8],
    s: usize,
    nx: usize,
    ny: usize,
) -> Vec<FineTable> {
    let tf = Transforms::new(p.family);
    let kappa = cue_kappa(p, level);
    let nk = kinds.len();
    // Spectra of every requested type, row-major [ky][kx], evaluated together so that the six
    // 1D transforms per sample are shared.
    let mut spectra: Vec<Vec<Complex64>> = vec![vec![Complex64::new(0.0, 0.0); nx * ny]; nk];
    // The spectra are of real functions (products of real factors' transforms and the pixel
    // box's): the mirrored rows are filled from their mirrors ([`MirroredGrid`]).
    let mirrored = MirroredGrid::new(nx, ny);
    // Row ky of every type, for the row's task to fill in place.
    let mut rows: Vec<Vec<&mut [Complex64]>> = (0..ny).map(|_| Vec::with_capacity(nk)).collect();
    for spectrum in spectra.iter_mut() {
        for (row, slice) in rows.iter_mut().zip(spectrum.chunks_mut(nx)) {
            row.push(slice);
        }
    }
    // The pixel box's transform along each screen axis.
    let sinc_x: Vec<f64> = (0..nx)
        .map(|kx| sinc(signed(kx, nx) * s as f64 / nx as f64))
        .collect();
    rows.into_par_iter().enumerate().for_each(|(ky, mut out)| {
        let rho = signed(ky, ny) * s as f64 / ny as f64;
        let sinc_rho = sinc(rho);
        for &kx in mirrored.columns(ky) {
            let sigma = signed(kx, nx) * s as f64 / nx as f64;
            let mut f1 = [[Complex64::new(0.0, 0.0); 2]; 3];
            for a in 0..3 {
                let xi = p.zoom * (sigma * p.ex[a] + rho * p.ey[a]);
                f1[a] = if kappa[a] == 0.0 {
                    axis_transforms_uncued(&tf, level, xi)
                } else {
                    [
                        axis_transform(&tf, level, false, xi, kappa[a]),
                        axis_transform(&tf, level, true, xi, kappa[a]),
                    ]
                };
            }
            let w = p.zoom * p.zoom * p.voxel_volume * sinc_x[kx] * sinc_rho;
            for (t, kind) in kinds.iter().enumerate() {
                let bx = (kind >> 2) as usize & 1;
                let by = (kind >> 1) as usize & 1;
                let bz = *kind as usize & 1;
                out[t][kx] = f1[0][bx] * f1[1][by] * f1[2][bz] * w;
            }
        }
    });
    for spectrum in spectra.iter_mut() {
        mirrored.fill_mirrored_rows(spectrum);
    }
    spectra
        .into_par_iter()
        .zip(kinds.par_iter())
        .map(|(mut spec, kind)| {
            let (rx, ry) = support_radius(p, level, *kind);
            inverse_and_crop(&mut spec, &Crop::new(s, nx, ny, rx, ry))
        })
        .collect()
}

/// The crop of an inverse transform of an nx × ny grid at S samples per pixel: the support
/// radius (rx, ry) pixels plus one sample each side, centred, and the scale of the
/// unnormalized inverse FFTs.
pub(super) struct Crop {
    s: usize,
    nx: usize,
    ny: usize,
    hx: usize,
    hy: usize,
    scale: f64,
}

impl Crop {
    pub(super) fn new(s: usize, nx: usize, ny: usize, rx: f64, ry: f64) -> Crop {
        Crop {
            s,
            nx,
            ny,
            hx: ((rx * s as f64).ceil() as usize + 1).min(nx / 2 - 1),
            hy: ((ry * s as f64).ceil() as usize + 1).min(ny / 2 - 1),
            scale: (s * s) as f64 / (nx * ny) as f64,
        }
    }

    /// Columns and rows kept.
    fn size(&self) -> (usize, usize) {
        (2 * self.hx + 1, 2 * self.hy + 1)
    }

    /// The grid column of kept column `i` (the centre at column 0, wrapped).
    fn column(&self, i: usize, nx: usize) -> usize {
        (i as i64 - self.hx as i64).rem_euclid(nx as i64) as usize
    }

    /// The grid row of kept row `i`.
    fn row(&self, i: usize, ny: usize) -> usize {
        (i as i64 - self.hy as i64).rem_euclid(ny as i64) as usize
    }

    /// The table of the kept samples.
    fn table(&self, s: usize, data: Vec<f64>) -> FineTable {
        FineTable::centred(s, self.hx, self.hy, data)
    }
}

/// The real part of the inverse 2D FFT of a spectrum (row-major, nx × ny, rows at [`signed`]
/// frequencies), cropped as `crop` says: the support radius (rx, ry) pixels plus one sample
/// with the centre in the middle.
///
/// The spectra here are of real functions: every entry of a row of negative frequency is the
/// conjugate of its mirror (the row and column at the negated frequencies), except in an even
/// grid's Nyquist column, which has no mirror on the grid ([`MirroredGrid`]). The real part of
/// the inverse is the inverse of the spectrum's Hermitian part (X + conj X(−k))/2, which saves
/// half of each pass:
/// - rows: only the rows of frequency 0 to the Nyquist row are transformed; a mirrored row's
///   transform is its mirror's conjugate plus the Nyquist column's difference times (−1)ˣ, so
///   the Hermitian part of the column at row m is the row's own value plus half that
///   difference's conjugate;
/// - columns: the Hermitian parts of two columns have real inverses, so one complex FFT of the
///   first plus i times the second returns both (real and imaginary part).
///
/// Equal to transforming every row and column in full and keeping the real part, up to
/// rounding (`hermitian_inverse_equals_the_full_one` below).
pub(super) fn inverse_and_crop(spec: &mut [Complex64], crop: &Crop) -> FineTable {
    let (s, nx, ny) = (crop.s, crop.nx, crop.ny);
    // An odd grid's frequencies run from −(n+1)/2 to (n−1)/2 ([`signed`]): rows and columns
    // without mirrors in the middle of the grid. The planner's grids are even ([`nice`]).
    if nx % 2 == 1 || ny % 2 == 1 {
        return inverse_in_full(spec, crop);
    }
    let mut planner = FftPlanner::<f64>::new();
    let fx = planner.plan_fft_inverse(nx);
    let fy = planner.plan_fft_inverse(ny);
    let zero = Complex64::new(0.0, 0.0);
    // Rows 0..=ny/2 are transformed; row m's mirror is ny − m.
    let half = ny / 2;
    let n = nx / 2;
    // Per transformed row m with a mirror (0 < m < ny/2, the mirror ny − m), the Nyquist
    // column's departure from conjugate symmetry, conj(X[ny − m][N] − conj X[m][N]) / 2, taken
    // before the rows are transformed in place.
    let correction: Vec<Complex64> = (0..=half)
        .map(|m| {
            if m > 0 && m < half {
                (spec[(ny - m) * nx + n] - spec[m * nx + n].conj()).conj() * 0.5
            } else {
                zero
            }
        })
        .collect();
    // Every transformed row in one call (one scratch buffer for all of them).
    fx.process(&mut spec[..(half + 1) * nx]);
    let (cw, ch) = crop.size();
    let mut data = vec![0.0; cw * ch];
    let mut scratch = vec![zero; fy.get_inplace_scratch_len()];
    let mut col = vec![zero; ny];
    // The Hermitian part of output column `ox` at every row, added to `col` times `weight`
    // (1 or i).
    let add_column = |col: &mut [Complex64], ox: usize, weight: Complex64| {
        let sign = if ox.is_multiple_of(2) { 1.0 } else { -1.0 };
        for m in 0..=half {
            let v = spec[m * nx + ox];
            let mirror = (ny - m) % ny;
            let h = if mirror == m {
                Complex64::new(v.re, 0.0)
            } else {
                v + correction[m] * sign
            };
            col[m] += h * weight;
            if mirror != m {
                col[mirror] += h.conj() * weight;
            }
        }
    };
    for first in (0..cw).step_by(2) {
        col.fill(zero);
        add_column(&mut col, crop.column(first, nx), Complex64::new(1.0, 0.0));
        let second = first + 1 < cw;
        if second {
            add_column(
                &mut col,
                crop.column(first + 1, nx),
                Complex64::new(0.0, 1.0),
            );
        }
        fy.process_with_scratch(&mut col, &mut scratch);
        for iy in 0..ch {
            let v = col[crop.row(iy, ny)];
            data[iy * cw + first] = v.re * crop.scale;
            if second {
                data[iy * cw + first + 1] = v.im * crop.scale;
            }
        }
    }
    crop.table(s, data)
}

/// [`inverse_and_crop`] the long way: every row and kept column transformed in full, the real
/// part kept (for grids of an odd size, whose frequencies are not symmetric about zero).
fn inverse_in_full(spec: &mut [Complex64], crop: &Crop) -> FineTable {
    let (s, nx, ny) = (crop.s, crop.nx, crop.ny);
    let mut planner = FftPlanner::<f64>::new();
    let (fx, fy) = (planner.plan_fft_inverse(nx), planner.plan_fft_inverse(ny));
    fx.process(spec);
    let (cw, ch) = crop.size();
    let mut data = vec![0.0; cw * ch];
    let mut col = vec![Complex64::new(0.0, 0.0); ny];
    for ix in 0..cw {
        let ox = crop.column(ix, nx);
        for (y, c) in col.iter_mut().enumerate() {
            *c = spec[y * nx + ox];
        }
        fy.process(&mut col);
        for iy in 0..ch {
            data[iy * cw + ix] = col[crop.row(iy, ny)].re * crop.scale;
        }
    }
    crop.table(s, data)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The half-pass inverse against the full one, on spectra of real functions with the
    /// unmirrored entries (row 0, the Nyquist row and column) arbitrary, as the evaluated
    /// spectra have them: sizes down to 4 × 4 and crops up to the whole grid; odd sizes take
    /// the full path.
    #[test]
    fn hermitian_inverse_equals_the_full_one() {
        let mut state = 0x853c_49e6_748f_ea9bu64;
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 11) as f64 / (1u64 << 53) as f64 - 0.5
        };
        for (nx, ny, rx, ry) in [
            (4, 4, 0.1, 0.1),
            (4, 6, 0.1, 0.1),
            (6, 6, 1.0, 1.0),
            (8, 7, 0.3, 0.8),
            (10, 8, 0.4, 0.4),
            (30, 24, 1.2, 0.9),
            (48, 64, 10.0, 10.0),
        ] {
            let s = 2;
            let mut spec: Vec<Complex64> = (0..nx * ny)
                .map(|_| Complex64::new(next(), next()))
                .collect();
            // Conjugate mirrors where both the row and the column have one.
            for ky in 0..ny {
                let my = (ny - ky) % ny;
                if signed(my, ny) != -signed(ky, ny) || my >= ky {
                    continue;
                }
                for kx in 0..nx {
                    if let Some(mx) = mirror_column(kx, nx) {
                        spec[ky * nx + kx] = spec[my * nx + mx].conj();
                    }
                }
            }
            let crop = Crop::new(s, nx, ny, rx, ry);
            let want = inverse_in_full(&mut spec.clone(), &crop);
            let got = inverse_and_crop(&mut spec, &crop);
            assert_eq!((got.nx, got.ny), (want.nx, want.ny));
            let peak = want.data.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            for (g, w) in got.data.iter().zip(&want.data) {
                assert!(
                    (g - w).abs() <= 1e-13 * peak.max(1.0),
                    "{nx}×{ny}: {g} against {w}"
                );
            }
        }
    }

    /// The closed forms against the general transforms (complex exponentials and the
    /// cancellation-free box transform), for every family, level 0–4 and frequencies from 0
    /// through tiny ones to several cycles per voxel, both signs.
    #[test]
    fn uncued_axis_transforms_equal_the_general_ones() {
        let mut freqs = vec![0.0, 1e-300, 1e-12, 1e-9, 1e-8, 1.1e-8, 1e-6, 1e-3, 0.0625];
        freqs.extend((1..400).map(|k| k as f64 * 0.0173));
        freqs.extend([0.5, 1.0, 1.5, 2.0, 3.0, 7.25]);
        for family in [Family::Haar, Family::Linear, Family::Cubic] {
            let tf = Transforms::new(family);
            for level in 0..5 {
                for &f in &freqs {
                    for xi in [f, -f] {
                        let [phi, psi] = axis_transforms_uncued(&tf, level, xi);
                        let want_phi = axis_transform(&tf, level, false, xi, 0.0);
                        let want_psi = axis_transform(&tf, level, true, xi, 0.0);
                        let scale = (1u64 << level) as f64;
                        for (got, want, what) in [(phi, want_phi, "φ"), (psi, want_psi, "ψ")] {
                            let err = (got - want).norm();
                            assert!(
                                err <= 1e-13 * scale.max(want.norm())
                                    && err <= 1e-12 * want.norm() + 1e-300,
                                "{family} level {level} {what} at ξ = {xi:e}: {got} against {want}"
                            );
                        }
                    }
                }
            }
        }
    }
}
