//! Splat footprints by Fourier projection-slice (paper §2.3): this module owns the tables that
//! the accumulator copies into the image, one per (level, type) for a given view.
//!
//! The pixel-area-averaged footprint of a centred level-m basis function b in screen pixels has
//! the 2D Fourier transform (σ, ρ in cycles per pixel)
//! P̂(σ, ρ) = zoom² · det S · B(zoom·(σ e_x + ρ e_y)) · sinc(σ) sinc(ρ),
//! where e_x, e_y are the screen axes per voxel step (S·u and −S·v for the voxel spacing S: the
//! basis drawn in physical space is b(S⁻¹y), whose projection's slice is det S · B(S·ω), so an
//! anisotropic volume still needs one table per type, level and view), zoom is pixels per unit
//! of spacing, and B is the 3D transform of the centred basis (product over axes of the codec's 1D
//! transforms, recentred by e^{+i2πξc}, c = j/2 for φ and (2j−1)/2 for ψ, dilated by 2^m) and
//! the sincs are the pixel box, so a table sample is the *average over a pixel* of the line
//! integrals — Haar's transform is not band-limited, so this and oversampling matter. The slice is
//! sampled on a grid of spacing S/N cycles per pixel and inverse-FFT'd (rustfft, f64), giving the
//! footprint on a grid of spacing 1/S pixel (S = subpixel phases, default 8, halved while the FFT
//! would exceed `max_fft` per side), with period N/S pixels larger than the projected support
//! plus margin (no wraparound); the real part is kept and the table cropped to the support.
//!
//! **Mipmap.** Level-M tables are computed once per view; a level-m table (r = 2^(M−m)) is
//! derived exactly as T_m(X) = r^(−3) Σ_{a,b<r} T_M(r·X + o_a, r·Y + o_b), o_a = a − (r−1)/2
//! pixels: the level-m basis is the level-M one shrunk by r (its projection scales by 1/r), and
//! the integral over one level-m-scale pixel is the sum of r×r level-M-scale pixel integrals (each
//! being the area r² times our per-area average): box filter, then subsample by r. S is kept even
//! so the half-pixel offsets fall on the grid.
//!
//! **Subpixel placement.** A splat centred at continuous screen X reads, for pixel ix, the table
//! sample nearest its exact offset ix + ½ − X, i.e. it uses the nearest of S × S phase tables (the
//! fine table split by phase). No interpolation, hence no blur; the position error is at most
//! 1/(2S) pixel per axis, and it is the same for every pixel of a splat (no shape distortion).
//!
//! **Depth cueing** (§3.2): the cued footprints use κ_a = k·L̂_a·2^m per axis (the codec cues
//! each 1D factor relative to its support end nearest the light, so no exponent is positive).
//! The cue is cut at the data's light-facing faces, so a table is keyed by its three axis
//! factors ([`AxisFactor`]: a cued level-m φ/ψ, or a level-0 φ across a face); the tables a
//! rendering needs are built on first use, grouped by level so that each distinct 1D factor is
//! evaluated once per FFT grid, and kept with the view's set.

use num_complex::Complex64;
use rayon::prelude::*;
use rustfft::FftPlanner;
use std::f64::consts::PI;
use wavesplat_codec::family::{box_transform, Family};
pub use wavesplat_codec::view::sinc;

/// Parameters of one footprint set (all levels and types for one view).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FootprintParams {
    /// Wavelet family.
    pub family: Family,
    /// Decomposition depth M.
    pub levels: usize,
    /// Screen x axis per voxel step, S·u (unit for unit spacing; `Camera::index_axes`).
    pub ex: [f64; 3],
    /// Screen y axis per voxel step, −S·v.
    pub ey: [f64; 3],
    /// Pixels per unit of spacing.
    pub zoom: f64,
    /// Physical volume of a voxel, det S (1 for unit spacing).
    pub voxel_volume: f64,
    /// Requested subpixel phases per axis (even, ≥ 2).
    pub subpixel: usize,
    /// Largest FFT side.
    pub max_fft: usize,
    /// Depth cue: extinction k (per unit of spacing) and the distance gradient in voxel indices
    /// (`ResolvedCue::l`: the unit light direction for unit spacing).
    pub cue: Option<(f64, [f64; 3])>,
    /// Also build the tables' gradients (for [`Footprint::grad_x`] / [`Footprint::grad_y`]).
    pub gradient: bool,
}

/// A footprint on the fine grid: sample (ix, iy) is the pixel-averaged projection at offset
/// ((ix − cx)/S, (iy − cy)/S) pixels from the basis centre.
#[derive(Debug, Clone, PartialEq)]
pub struct FineTable {
    /// Subpixel phases per pixel.
    pub s: usize,
    /// Width.
    pub nx: usize,
    /// Height.
    pub ny: usize,
    /// Centre column.
    pub cx: usize,
    /// Centre row.
    pub cy: usize,
    /// Samples, row-major.
    pub data: Vec<f64>,
}

impl FineTable {
    /// A table of (2·cx + 1) × (2·cy + 1) samples centred on the basis centre.
    fn centred(s: usize, cx: usize, cy: usize, data: Vec<f64>) -> FineTable {
        debug_assert_eq!(data.len(), (2 * cx + 1) * (2 * cy + 1));
        FineTable {
            s,
            nx: 2 * cx + 1,
            ny: 2 * cy + 1,
            cx,
            cy,
            data,
        }
    }

    /// Sample at signed fine indices (zero outside).
    pub fn get(&self, ix: i64, iy: i64) -> f64 {
        if ix < 0 || iy < 0 || ix >= self.nx as i64 || iy >= self.ny as i64 {
            0.0
        } else {
            self.data[iy as usize * self.nx + ix as usize]
        }
    }

    /// The derivative along `axis` (0: x, 1: y) per pixel, by central differences on the fine
    /// grid (spacing 1/S pixel; zero outside the table).
    pub fn derivative(&self, axis: usize) -> FineTable {
        let half_s = 0.5 * self.s as f64;
        let mut data = Vec::with_capacity(self.data.len());
        for iy in 0..self.ny as i64 {
            for ix in 0..self.nx as i64 {
                let (d0, d1) = if axis == 0 {
                    (self.get(ix - 1, iy), self.get(ix + 1, iy))
                } else {
                    (self.get(ix, iy - 1), self.get(ix, iy + 1))
                };
                data.push((d1 - d0) * half_s);
            }
        }
        FineTable {
            s: self.s,
            nx: self.nx,
            ny: self.ny,
            cx: self.cx,
            cy: self.cy,
            data,
        }
    }

    /// Value at a pixel offset (X, Y) from the centre (nearest sample).
    pub fn at(&self, x: f64, y: f64) -> f64 {
        let ix = (x * self.s as f64).round() as i64 + self.cx as i64;
        let iy = (y * self.s as f64).round() as i64 + self.cy as i64;
        self.get(ix, iy)
    }
}

/// One phase of a footprint: the samples of the fine table at pixel spacing.
#[derive(Debug, Clone, PartialEq)]
pub struct Phase {
    /// Columns.
    pub cols: usize,
    /// Rows.
    pub rows: usize,
    /// Samples, row-major.
    pub data: Vec<f32>,
}

/// A footprint ready for accumulation: S × S phase tables.
#[derive(Debug, Clone, PartialEq)]
pub struct Footprint {
    /// Subpixel phases per axis.
    pub s: usize,
    /// Centre column of the fine table.
    pub cx: usize,
    /// Centre row of the fine table.
    pub cy: usize,
    /// Phase (a, b) at index b·S + a: fine samples (k·S + a, l·S + b).
    pub phases: Vec<Phase>,
    /// ∂/∂x of the footprint per pixel, split into phases like `phases` (empty unless the
    /// footprint was built with gradients): a splat placed δ pixels from its exact position
    /// adds δ times this (first-order correction of the subpixel residual).
    pub grad_x: Vec<Phase>,
    /// ∂/∂y likewise.
    pub grad_y: Vec<Phase>,
}

/// Splits a fine table into its S × S phases.
fn split_phases(t: &FineTable) -> Vec<Phase> {
    let s = t.s;
    let mut phases = Vec::with_capacity(s * s);
    for b in 0..s {
        for a in 0..s {
            let cols = (t.nx + s - 1 - a) / s;
            let rows = (t.ny + s - 1 - b) / s;
            let mut data = Vec::with_capacity(cols * rows);
            for l in 0..rows {
                for k in 0..cols {
                    data.push(t.data[(l * s + b) * t.nx + k * s + a] as f32);
                }
            }
            phases.push(Phase { cols, rows, data });
        }
    }
    phases
}

impl Footprint {
    /// Splits a fine table into its phases (no gradients).
    pub fn from_fine(t: &FineTable) -> Footprint {
        Footprint {
            s: t.s,
            cx: t.cx,
            cy: t.cy,
            phases: split_phases(t),
            grad_x: Vec::new(),
            grad_y: Vec::new(),
        }
    }

    /// Splits a fine table and its gradient into phases.
    pub fn with_gradient(t: &FineTable) -> Footprint {
        Footprint {
            grad_x: split_phases(&t.derivative(0)),
            grad_y: split_phases(&t.derivative(1)),
            ..Footprint::from_fine(t)
        }
    }

    /// From a fine table, with gradients when `gradient`.
    pub fn build(t: &FineTable, gradient: bool) -> Footprint {
        if gradient {
            Footprint::with_gradient(t)
        } else {
            Footprint::from_fine(t)
        }
    }

    /// The subpixel residual of a placement: the exact centre minus where the chosen phase puts
    /// it, in pixels (|residual| ≤ 1/(2S)).
    #[inline]
    pub fn residual(s: usize, centre: f64) -> f64 {
        let d = (s as f64 * (centre - 0.5)).round();
        (d / s as f64 + 0.5) - centre
    }

    /// Placement along one axis of a splat centred at continuous screen coordinate `centre`:
    /// returns (phase, first pixel) such that pixel `first + k` reads column k of the phase.
    #[inline]
    pub fn place(s: usize, c: usize, centre: f64) -> (usize, i64) {
        let d = (s as f64 * (centre - 0.5)).round() as i64;
        let t = c as i64 - d;
        let a = t.rem_euclid(s as i64);
        let q = (t - a) / s as i64;
        (a as usize, -q)
    }
}

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

/// FFT sizes and the subpixel factor for a level (largest type).
fn sizes(p: &FootprintParams, level: usize) -> (usize, usize, usize) {
    let mut rx: f64 = 0.0;
    let mut ry: f64 = 0.0;
    for kind in 0..8u8 {
        let (a, b) = support_radius(p, level, kind);
        rx = rx.max(a);
        ry = ry.max(b);
    }
    let mut s = p.subpixel.max(2);
    s += s % 2;
    let need = |s: usize, r: f64| nice((s as f64 * (2.0 * r + 3.0)).ceil() as usize);
    while s > 2 && need(s, rx).max(need(s, ry)) > p.max_fft.max(16) {
        s = (s / 2).max(2);
        s += s % 2;
    }
    (s, need(s, rx), need(s, ry))
}

/// Computes the fine tables of the given types at `level` by FFT (all with the same S).
pub fn compute_fine(p: &FootprintParams, level: usize, kinds: &[u8]) -> Vec<FineTable> {
    let (s, nx, ny) = sizes(p, level);
    compute_fine_with(p, level, kinds, s, nx, ny)
}

fn signed(k: usize, n: usize) -> f64 {
    if k < n / 2 {
        k as f64
    } else {
        k as f64 - n as f64
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
    let rows: Vec<Vec<Vec<Complex64>>> = (0..ny)
        .into_par_iter()
        .map(|ky| {
            let rho = signed(ky, ny) * s as f64 / ny as f64;
            let mut out = vec![vec![Complex64::new(0.0, 0.0); nx]; nk];
            for kx in 0..nx {
                let sigma = signed(kx, nx) * s as f64 / nx as f64;
                let mut f1 = [[Complex64::new(0.0, 0.0); 2]; 3];
                for a in 0..3 {
                    let xi = p.zoom * (sigma * p.ex[a] + rho * p.ey[a]);
                    f1[a][0] = axis_transform(&tf, level, false, xi, kappa[a]);
                    f1[a][1] = axis_transform(&tf, level, true, xi, kappa[a]);
                }
                let w = p.zoom * p.zoom * p.voxel_volume * sinc(sigma) * sinc(rho);
                for (t, kind) in kinds.iter().enumerate() {
                    let bx = (kind >> 2) as usize & 1;
                    let by = (kind >> 1) as usize & 1;
                    let bz = *kind as usize & 1;
                    out[t][kx] = f1[0][bx] * f1[1][by] * f1[2][bz] * w;
                }
            }
            out
        })
        .collect();
    for (ky, row) in rows.into_iter().enumerate() {
        for (t, r) in row.into_iter().enumerate() {
            spectra[t][ky * nx..(ky + 1) * nx].copy_from_slice(&r);
        }
    }
    spectra
        .into_par_iter()
        .zip(kinds.par_iter())
        .map(|(mut spec, kind)| {
            let (rx, ry) = support_radius(p, level, *kind);
            inverse_and_crop(&mut spec, s, nx, ny, rx, ry)
        })
        .collect()
}

/// Derives the level-`level` table of `kind` from the level-`from` table (mipmap, see the module
/// documentation for the exact scale factor r^(−3)).
pub fn mipmap(
    p: &FootprintParams,
    top: &FineTable,
    from: usize,
    level: usize,
    kind: u8,
) -> FineTable {
    let r = 1usize << (from - level);
    let s = top.s;
    let (rx, ry) = support_radius(p, level, kind);
    let hx = (rx * s as f64).ceil() as usize + 1;
    let hy = (ry * s as f64).ceil() as usize + 1;
    let (cw, ch) = (2 * hx + 1, 2 * hy + 1);
    // Offsets of the r sub-pixels in fine samples: S·(a − (r−1)/2), integral since S is even.
    let offs: Vec<i64> = (0..r)
        .map(|a| (s as i64 * (2 * a as i64 - (r as i64 - 1))) / 2)
        .collect();
    // Horizontal box sums on every row of the top table.
    let mut hsum = vec![0.0f64; top.ny * cw];
    for y in 0..top.ny {
        for i in 0..cw {
            let base = top.cx as i64 + r as i64 * (i as i64 - hx as i64);
            hsum[y * cw + i] = offs.iter().map(|o| top.get(base + o, y as i64)).sum();
        }
    }
    let norm = 1.0 / (r * r * r) as f64;
    let mut data = vec![0.0; cw * ch];
    for jy in 0..ch {
        let base = top.cy as i64 + r as i64 * (jy as i64 - hy as i64);
        for i in 0..cw {
            let mut acc = 0.0;
            for o in &offs {
                let y = base + o;
                if y >= 0 && (y as usize) < top.ny {
                    acc += hsum[y as usize * cw + i];
                }
            }
            data[jy * cw + i] = acc * norm;
        }
    }
    FineTable::centred(s, hx, hy, data)
}

/// All footprints of one view: index `level · 8 + kind` (levels 0..=M; level 0 unused unless
/// M = 0). With depth cueing the tables are per axis-factor triple instead, built on first use
/// (which triples occur depends on where the coefficients lie relative to the light-facing
/// faces) and kept here for the next rendering of the same view.
#[derive(Debug)]
pub struct FootprintSet {
    /// The parameters they were built for.
    pub params: FootprintParams,
    /// Tables (`None` for (level, kind) pairs that do not occur; all `None` when cued).
    pub tables: Vec<Option<Footprint>>,
    /// Cued tables by factor triple.
    pub factor_tables:
        std::sync::Mutex<std::collections::HashMap<[AxisFactor; 3], std::sync::Arc<Footprint>>>,
    /// The 1D factor transforms on the frequency grids of the factor tables, kept for the next
    /// triples of the same view (evaluating them is most of a table's cost).
    factor_grids: FactorGrids,
}

/// A factor's transform on a level's frequency grid.
type FactorGrid = std::sync::Arc<Vec<Complex64>>;

/// Per (FFT grid level, axis, factor): the factor's transform on that level's frequency grid;
/// per level: the pixel box's.
#[derive(Debug, Default)]
pub struct FactorGrids {
    factors: std::sync::Mutex<std::collections::HashMap<(usize, usize, AxisFactor), FactorGrid>>,
    pixel: std::sync::Mutex<std::collections::HashMap<usize, std::sync::Arc<Vec<f64>>>>,
}

impl FootprintSet {
    /// Builds every table: level M by FFT and finer levels by mipmap (nothing up front when
    /// cued: see [`FootprintSet::factor_tables`]).
    pub fn build(p: &FootprintParams) -> FootprintSet {
        let m = p.levels;
        let mut tables: Vec<Option<Footprint>> = vec![None; (m + 1) * 8];
        let all: Vec<u8> = (0..8).collect();
        let wavelets: Vec<u8> = (1..8).collect();
        if p.cue.is_some() {
            // Built on demand per factor triple.
        } else if m == 0 {
            for level in (if m == 0 { 0 } else { 1 })..=m {
                let kinds = if level == m { &all } else { &wavelets };
                for (t, kind) in compute_fine(p, level, kinds).iter().zip(kinds) {
                    tables[level * 8 + *kind as usize] = Some(Footprint::build(t, p.gradient));
                }
            }
        } else {
            let top = compute_fine(p, m, &all);
            for (t, kind) in top.iter().zip(&all) {
                tables[m * 8 + *kind as usize] = Some(Footprint::build(t, p.gradient));
                if *kind != 0 {
                    for level in 1..m {
                        let f = mipmap(p, t, m, level, *kind);
                        tables[level * 8 + *kind as usize] = Some(Footprint::build(&f, p.gradient));
                    }
                }
            }
        }
        FootprintSet {
            params: *p,
            tables,
            factor_tables: Default::default(),
            factor_grids: FactorGrids::default(),
        }
    }

    /// The cued tables for `keys`, computing (in parallel) and caching the missing ones.
    pub fn factor_footprints(&self, keys: &[[AxisFactor; 3]]) -> Vec<std::sync::Arc<Footprint>> {
        let missing: Vec<[AxisFactor; 3]> = {
            let map = self.factor_tables.lock().unwrap_or_else(|e| e.into_inner());
            keys.iter()
                .filter(|k| !map.contains_key(*k))
                .copied()
                .collect()
        };
        let built: Vec<([AxisFactor; 3], Footprint)> = missing
            .iter()
            .zip(compute_factor_tables_with(
                &self.params,
                &missing,
                &self.factor_grids,
            ))
            .map(|(k, t)| (*k, Footprint::build(&t, self.params.gradient)))
            .collect();
        let mut map = self.factor_tables.lock().unwrap_or_else(|e| e.into_inner());
        for (k, f) in built {
            map.insert(k, std::sync::Arc::new(f));
        }
        keys.iter().map(|k| map[k].clone()).collect()
    }

    /// The table of a band, if any.
    pub fn get(&self, level: usize, kind: u8) -> Option<&Footprint> {
        self.tables
            .get(level * 8 + kind as usize)
            .and_then(|t| t.as_ref())
    }
}

/// One axis factor of a splat piece (see [`crate::pieces`]): a whole level-m φ or ψ, or a
/// level-0 φ cut to part of its support (at a face of the data's box). With depth cueing each
/// factor is cued from the end of its (kept) support nearest the light, so no exponent is
/// positive.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum AxisFactor {
    /// Level-`level` φ (`wavelet` false) or ψ, whole.
    Basis {
        /// Level m.
        level: u8,
        /// ψ rather than φ.
        wavelet: bool,
    },
    /// Level-0 φ kept on [a, b] (voxels relative to its centre; −j/2 ≤ a < b ≤ j/2, not the
    /// whole support), zero elsewhere.
    Cut {
        /// Start of the kept part.
        a: i8,
        /// End of the kept part.
        b: i8,
    },
}

impl AxisFactor {
    /// Half the support length in voxels (of the whole φ for a cut).
    pub fn half_support(self, family: Family) -> f64 {
        match self {
            AxisFactor::Basis { level, wavelet, .. } => {
                0.5 * (1u64 << level) as f64
                    * if wavelet {
                        family.psi_support()
                    } else {
                        family.phi_support()
                    }
            }
            AxisFactor::Cut { .. } => 0.5 * family.phi_support(),
        }
    }

    /// The factor mirrored about its centre (what a multiview reflection makes of it), with the
    /// sign a mirrored odd ψ takes.
    pub fn reflected(self, psi_is_odd: bool) -> (AxisFactor, f32) {
        match self {
            AxisFactor::Basis { wavelet, .. } => {
                (self, if wavelet && psi_is_odd { -1.0 } else { 1.0 })
            }
            AxisFactor::Cut { a, b } => (AxisFactor::Cut { a: -b, b: -a }, 1.0),
        }
    }

    /// The centred 1D transform at ξ cycles per voxel, for extinction `k` per voxel and light
    /// direction component `la` along this axis.
    pub fn transform(self, tf: &Transforms, xi: f64, k: f64, la: f64) -> Complex64 {
        let kl = k * la;
        match self {
            AxisFactor::Basis { level, wavelet } => {
                axis_transform(tf, level as usize, wavelet, xi, kl * (1u64 << level) as f64)
            }
            AxisFactor::Cut { a, b } => CutFactor::new(tf.family(), a, b, k, la).at(xi),
        }
    }
}

/// Gauss–Legendre nodes and weights on [−1, 1] (Newton on the Legendre recurrence).
fn gauss_legendre(n: usize) -> Vec<(f64, f64)> {
    (0..n)
        .map(|i| {
            let mut x = (PI * (i as f64 + 0.75) / (n as f64 + 0.5)).cos();
            let mut dp = 1.0;
            for _ in 0..100 {
                let (mut p0, mut p1) = (1.0, x);
                for k in 2..=n {
                    let p2 = ((2 * k - 1) as f64 * x * p1 - (k - 1) as f64 * p0) / k as f64;
                    p0 = p1;
                    p1 = p2;
                }
                dp = n as f64 * (x * p1 - p0) / (x * x - 1.0);
                let dx = p1 / dp;
                x -= dx;
                if dx.abs() < 1e-15 {
                    break;
                }
            }
            (x, 2.0 / ((1.0 - x * x) * dp * dp))
        })
        .collect()
}

/// One polynomial piece of a cut factor: ∫₀^len Q(t) e^(σt) dt times a constant, with t
/// measured from the piece's end nearest the light.
#[derive(Debug, Clone)]
struct Piece {
    /// Q's monomial coefficients in t.
    q: Vec<f64>,
    len: f64,
    /// Position (relative to the factor's centre) where t = 0.
    origin: f64,
    /// +1 when u = origin + t, −1 when u = origin − t.
    dir: f64,
}

/// The transform of a level-0 φ kept on [a, b] (relative to its centre) and cued from the end of
/// [a, b] nearest the light, prepared for many frequencies: ∫_a^b φ_c(u) h(u) e^(−i2πξu) du with
/// h(u) = e^(−k·l_a·(u − u_ref)), u_ref = a when l_a ≥ 0 and b when l_a < 0 (so h ≤ 1). φ is a
/// polynomial between its knots, so each piece is ∫ Q(t) e^(σt) dt with Re σ ≤ 0: by the closed
/// form [e^(σt) Σ_m (−1)^m Q⁽ᵐ⁾(t)/σ^(m+1)] when |σ|·len ≥ 1 (no cancellation there), and by
/// 8-point Gauss–Legendre below (an entire integrand of small variation: exact to rounding). No
/// exponent is positive, whatever k. With k = 0 it is simply the truncated B-spline (a face of
/// the data's box cutting it).
#[derive(Debug, Clone)]
pub struct CutFactor {
    pieces: Vec<Piece>,
    kl: f64,
    uref: f64,
}

impl CutFactor {
    /// Prepares the factor for `family`, kept on [a, b] (clamped to the support), extinction
    /// `k` per voxel and light direction component `la` along the axis.
    pub fn new(family: Family, a: i8, b: i8, k: f64, la: f64) -> CutFactor {
        let kl = k * la;
        let positive = la >= 0.0;
        let half = 0.5 * family.phi_support();
        let (lo, hi) = ((a as f64).max(-half), (b as f64).min(half));
        let uref = if positive { lo } else { hi };
        let mut cuts: Vec<f64> = (0..=family.order()).map(|i| -half + i as f64).collect();
        cuts.push(lo);
        cuts.push(hi);
        cuts.retain(|c| *c >= lo && *c <= hi);
        cuts.sort_by(f64::total_cmp);
        cuts.dedup();
        let deg = family.order() - 1;
        let mut pieces = Vec::new();
        for w in cuts.windows(2) {
            let (a, b) = (w[0], w[1]);
            if b - a <= 1e-12 {
                continue;
            }
            let (origin, dir) = if positive { (a, 1.0) } else { (b, -1.0) };
            let len = b - a;
            // Fit Q(t) = φ(origin + dir·t + half) exactly (degree ≤ 3) from deg + 1 samples
            // strictly inside the piece (so φ's one-sided polynomial is the one sampled).
            let ts: Vec<f64> = (0..=deg)
                .map(|i| len * (i as f64 + 0.5) / (deg + 1) as f64)
                .collect();
            let vals: Vec<f64> = ts
                .iter()
                .map(|t| family.phi(origin + dir * t + half))
                .collect();
            pieces.push(Piece {
                q: solve_vandermonde(&ts, &vals),
                len,
                origin,
                dir,
            });
        }
        CutFactor { pieces, kl, uref }
    }

    /// The transform at ξ cycles per voxel.
    pub fn at(&self, xi: f64) -> Complex64 {
        use std::sync::OnceLock;
        static NODES: OnceLock<Vec<(f64, f64)>> = OnceLock::new();
        let nodes = NODES.get_or_init(|| gauss_legendre(8));
        let omega = 2.0 * PI * xi;
        let mut acc = Complex64::new(0.0, 0.0);
        for p in &self.pieces {
            // Constant factor at t = 0: weight e^(−kl(origin − u_ref)) ≤ 1 and phase.
            let c =
                Complex64::from_polar((-self.kl * (p.origin - self.uref)).exp(), -omega * p.origin);
            if c.norm() == 0.0 {
                continue;
            }
            let sigma = Complex64::new(-self.kl * p.dir, -omega * p.dir);
            let integral = if sigma.norm() * p.len < 1.0 {
                let mut sum = Complex64::new(0.0, 0.0);
                for (x, w) in nodes {
                    let t = 0.5 * p.len * (x + 1.0);
                    let q = p.q.iter().rev().fold(0.0, |acc, c| acc * t + c);
                    sum += (sigma * t).exp() * (q * w * 0.5 * p.len);
                }
                sum
            } else {
                // Σ_m (−1)^m Q^(m)(t) / σ^(m+1), at t = len (times e^(σ len)) minus at t = 0.
                let antideriv = |t: f64| -> Complex64 {
                    let mut deriv = p.q.clone();
                    let mut out = Complex64::new(0.0, 0.0);
                    let mut sp = sigma;
                    let mut sign = 1.0;
                    while !deriv.is_empty() {
                        let v = deriv.iter().rev().fold(0.0, |acc, c| acc * t + c);
                        out += sign * v / sp;
                        sp *= sigma;
                        sign = -sign;
                        deriv = deriv
                            .iter()
                            .enumerate()
                            .skip(1)
                            .map(|(i, c)| c * i as f64)
                            .collect();
                    }
                    out
                };
                (sigma * p.len).exp() * antideriv(p.len) - antideriv(0.0)
            };
            acc += c * integral;
        }
        acc
    }
}

/// Solves the Vandermonde system Σ_j c_j t_i^j = v_i (Gaussian elimination with partial
/// pivoting; at most 4×4 here).
fn solve_vandermonde(ts: &[f64], vals: &[f64]) -> Vec<f64> {
    let n = ts.len();
    let mut m: Vec<Vec<f64>> = ts
        .iter()
        .zip(vals)
        .map(|(t, v)| {
            let mut row: Vec<f64> = (0..n).map(|j| t.powi(j as i32)).collect();
            row.push(*v);
            row
        })
        .collect();
    for col in 0..n {
        let piv = (col..n)
            .max_by(|a, b| m[*a][col].abs().total_cmp(&m[*b][col].abs()))
            .unwrap_or(col);
        m.swap(col, piv);
        for r in 0..n {
            if r != col && m[col][col] != 0.0 {
                let f = m[r][col] / m[col][col];
                for c in col..=n {
                    m[r][c] -= f * m[col][c];
                }
            }
        }
    }
    (0..n)
        .map(|i| {
            if m[i][i] != 0.0 {
                m[i][n] / m[i][i]
            } else {
                0.0
            }
        })
        .collect()
}

/// The centred transform of a level-0 φ kept on [a, b] at one frequency (see [`CutFactor`]).
pub fn cut_transform(family: Family, xi: f64, k: f64, la: f64, a: i8, b: i8) -> Complex64 {
    CutFactor::new(family, a, b, k, la).at(xi)
}

/// Highest level among a triple's factors (cuts are level 0).
fn factor_level(factors: &[AxisFactor; 3]) -> usize {
    factors
        .iter()
        .map(|f| match f {
            AxisFactor::Basis { level, .. } => *level as usize,
            AxisFactor::Cut { .. } => 0,
        })
        .max()
        .unwrap_or(0)
}

/// Fine tables of factor triples. Triples are grouped by their highest level, which fixes
/// the FFT grid ([`sizes`] of that level, large enough for any triple of the group); per group
/// every distinct 1D factor is evaluated once per axis on the grid and each triple's spectrum
/// is the product of three such arrays and the pixel box.
pub fn compute_factor_tables(p: &FootprintParams, keys: &[[AxisFactor; 3]]) -> Vec<FineTable> {
    compute_factor_tables_with(p, keys, &FactorGrids::default())
}

/// [`compute_factor_tables`] with the factor and pixel grids taken from (and added to) `grids`.
pub fn compute_factor_tables_with(
    p: &FootprintParams,
    keys: &[[AxisFactor; 3]],
    cache: &FactorGrids,
) -> Vec<FineTable> {
    let tf = Transforms::new(p.family);
    let (k, l) = p.cue.unwrap_or((0.0, [0.0; 3]));
    let mut out: Vec<Option<FineTable>> = vec![None; keys.len()];
    let mut levels: Vec<usize> = keys.iter().map(factor_level).collect();
    levels.sort_unstable();
    levels.dedup();
    for level in levels {
        let group: Vec<usize> = (0..keys.len())
            .filter(|i| factor_level(&keys[*i]) == level)
            .collect();
        let (s, nx, ny) = sizes(p, level);
        // Distinct factors per axis, each evaluated on the grid once per view.
        let mut grids: [Vec<(AxisFactor, FactorGrid)>; 3] = Default::default();
        for a in 0..3 {
            let mut distinct: Vec<AxisFactor> = group.iter().map(|i| keys[*i][a]).collect();
            distinct.sort_by_key(|f| format!("{f:?}"));
            distinct.dedup();
            let new: Vec<AxisFactor> = {
                let map = cache.factors.lock().unwrap_or_else(|e| e.into_inner());
                distinct
                    .iter()
                    .filter(|f| !map.contains_key(&(level, a, **f)))
                    .copied()
                    .collect()
            };
            let fresh: Vec<(AxisFactor, FactorGrid)> = new
                .into_par_iter()
                .map(|f| {
                    let cut = match f {
                        AxisFactor::Cut { a: lo, b: hi } => {
                            Some(CutFactor::new(p.family, lo, hi, k, l[a]))
                        }
                        _ => None,
                    };
                    let mut g = Vec::with_capacity(nx * ny);
                    for ky in 0..ny {
                        let rho = signed(ky, ny) * s as f64 / ny as f64;
                        for kx in 0..nx {
                            let sigma = signed(kx, nx) * s as f64 / nx as f64;
                            let xi = p.zoom * (sigma * p.ex[a] + rho * p.ey[a]);
                            g.push(match &cut {
                                Some(st) => st.at(xi),
                                None => f.transform(&tf, xi, k, l[a]),
                            });
                        }
                    }
                    (f, std::sync::Arc::new(g))
                })
                .collect();
            let mut map = cache.factors.lock().unwrap_or_else(|e| e.into_inner());
            for (f, g) in fresh {
                map.insert((level, a, f), g);
            }
            grids[a] = distinct
                .into_iter()
                .map(|f| (f, map[&(level, a, f)].clone()))
                .collect();
        }
        let pixel = cache
            .pixel
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .entry(level)
            .or_insert_with(|| {
                std::sync::Arc::new(
                    (0..nx * ny)
                        .map(|i| {
                            let rho = signed(i / nx, ny) * s as f64 / ny as f64;
                            let sigma = signed(i % nx, nx) * s as f64 / nx as f64;
                            p.zoom * p.zoom * p.voxel_volume * sinc(sigma) * sinc(rho)
                        })
                        .collect(),
                )
            })
            .clone();
        let tables: Vec<(usize, FineTable)> = group
            .par_iter()
            .map(|&i| {
                let key = keys[i];
                let find = |a: usize| -> &Vec<Complex64> {
                    &grids[a]
                        .iter()
                        .find(|(f, _)| *f == key[a])
                        .expect("factor grid")
                        .1
                };
                let (g0, g1, g2) = (find(0), find(1), find(2));
                let mut spec: Vec<Complex64> = (0..nx * ny)
                    .map(|j| g0[j] * g1[j] * g2[j] * pixel[j])
                    .collect();
                let mut rx = 0.5;
                let mut ry = 0.5;
                for (a, f) in key.iter().enumerate() {
                    let h = f.half_support(p.family);
                    rx += p.zoom * h * p.ex[a].abs();
                    ry += p.zoom * h * p.ey[a].abs();
                }
                (i, inverse_and_crop(&mut spec, s, nx, ny, rx, ry))
            })
            .collect();
        for (i, t) in tables {
            out[i] = Some(t);
        }
    }
    out.into_iter()
        .map(|t| t.expect("every key computed"))
        .collect()
}

/// Inverse 2D FFT of a spectrum (row-major, nx × ny), cropped to the support radius (rx, ry)
/// pixels plus one sample with the centre in the middle (only the kept columns are transformed).
fn inverse_and_crop(
    spec: &mut [Complex64],
    s: usize,
    nx: usize,
    ny: usize,
    rx: f64,
    ry: f64,
) -> FineTable {
    let mut planner = FftPlanner::<f64>::new();
    let fx = planner.plan_fft_inverse(nx);
    let fy = planner.plan_fft_inverse(ny);
    for row in spec.chunks_mut(nx) {
        fx.process(row);
    }
    let mut col = vec![Complex64::new(0.0, 0.0); ny];
    let scale = (s * s) as f64 / (nx * ny) as f64;
    let hx = ((rx * s as f64).ceil() as usize + 1).min(nx / 2 - 1);
    let hy = ((ry * s as f64).ceil() as usize + 1).min(ny / 2 - 1);
    let (cw, ch) = (2 * hx + 1, 2 * hy + 1);
    let mut data = vec![0.0; cw * ch];
    for ix in 0..cw {
        let ox = (ix as i64 - hx as i64).rem_euclid(nx as i64) as usize;
        for (y, c) in col.iter_mut().enumerate() {
            *c = spec[y * nx + ox];
        }
        fy.process(&mut col);
        for iy in 0..ch {
            let oy = (iy as i64 - hy as i64).rem_euclid(ny as i64) as usize;
            data[iy * cw + ix] = col[oy].re * scale;
        }
    }
    FineTable::centred(s, hx, hy, data)
}
