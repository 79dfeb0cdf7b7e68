//! Axis factors of splat pieces: a whole level-m φ or ψ, or a level-0 φ cut at a face of the
//! data's box, each depth-cued from its support end nearest the light; the closed-form and
//! quadrature transforms of cut factors, and the tables of factor triples, grouped by level so
//! each distinct factor is evaluated once per FFT grid.

use super::slice::{
    axis_transform, inverse_and_crop, level_subpixel, signed, sizes, Crop, MirroredGrid, Transforms,
};
use super::FineTable;
use super::FootprintParams;
use num_complex::Complex64;
use rayon::prelude::*;
use std::f64::consts::PI;
use wavesplat_codec::family::Family;
use wavesplat_codec::view::sinc;

/// A factor's transform on a level's frequency grid.
type FactorGrid = std::sync::Arc<Vec<Complex64>>;

/// Per (FFT grid level, axis, factor): the factor's transform on that level's frequency grid;
/// per level: the pixel box's.
#[derive(Debug, Default)]
pub struct FactorGrids {
    factors: std::sync::Mutex<std::collections::HashMap<(usize, usize, AxisFactor), FactorGrid>>,
    pixel: std::sync::Mutex<std::collections::HashMap<usize, std::sync::Arc<Vec<f64>>>>,
}

/// One axis factor of a splat piece (see [`crate::pieces`]): a whole level-m φ or ψ, or a
/// level-0 φ cut to part of its support (at a face of the data's box). With depth cueing each
/// factor is cued from the end of its (kept) support nearest the light, so no exponent is
/// positive.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
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
    /// Q's monomial coefficients in t (degree ≤ 3): the first `terms` of them.
    q: [f64; 4],
    terms: usize,
    len: f64,
    /// Position (relative to the factor's centre) where t = 0.
    origin: f64,
    /// +1 when u = origin + t, −1 when u = origin − t.
    dir: f64,
    /// The constant factor's magnitude e^(−kl(origin − u_ref)) (its phase follows ξ).
    weight: f64,
    /// Per Gauss–Legendre node: t, the real part's e^(Re σ · t) (σ's real part does not depend
    /// on ξ), and Q(t)·w·len/2. What [`CutFactor::at`] computes at every frequency from the
    /// same operands, computed once.
    nodes: [(f64, f64, f64); GAUSS_NODES],
}

/// Gauss–Legendre nodes of a cut factor's short pieces.
const GAUSS_NODES: usize = 8;

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
            let coefficients = solve_vandermonde(&ts, &vals);
            debug_assert!(coefficients.len() <= 4, "B-splines here are at most cubic");
            let terms = coefficients.len().min(4);
            let mut q = [0.0; 4];
            q[..terms].copy_from_slice(&coefficients[..terms]);
            let horner = |t: f64| q[..terms].iter().rev().fold(0.0, |acc, c| acc * t + c);
            let sigma_re = -kl * dir;
            let nodes = gauss_nodes().map(|(x, w)| {
                let t = 0.5 * len * (x + 1.0);
                (t, (sigma_re * t).exp(), horner(t) * w * 0.5 * len)
            });
            pieces.push(Piece {
                q,
                terms,
                len,
                origin,
                dir,
                weight: (-kl * (origin - uref)).exp(),
                nodes,
            });
        }
        CutFactor { pieces, kl }
    }

    /// The transform at ξ cycles per voxel.
    pub fn at(&self, xi: f64) -> Complex64 {
        let omega = 2.0 * PI * xi;
        let mut acc = Complex64::new(0.0, 0.0);
        for p in &self.pieces {
            // Constant factor at t = 0: weight e^(−kl(origin − u_ref)) ≤ 1 and phase. It is
            // zero exactly when its weight is (its larger part keeps at least 0.7 of it).
            if p.weight == 0.0 {
                continue;
            }
            let c = Complex64::from_polar(p.weight, -omega * p.origin);
            let sigma = Complex64::new(-self.kl * p.dir, -omega * p.dir);
            let integral = if sigma.norm() * p.len < 1.0 {
                let mut sum = Complex64::new(0.0, 0.0);
                for &(t, real, qw) in &p.nodes {
                    // e^(σt), as `Complex64::exp` forms it, from the node's real part.
                    let e = if real.is_finite() {
                        let im = sigma.im * t;
                        Complex64::new(real * im.cos(), real * im.sin())
                    } else {
                        (sigma * t).exp()
                    };
                    sum += e * qw;
                }
                sum
            } else {
                // Σ_m (−1)^m Q^(m)(t) / σ^(m+1), at t = len (times e^(σ len)) minus at t = 0.
                let antideriv = |t: f64| -> Complex64 {
                    let mut deriv = p.q;
                    let mut out = Complex64::new(0.0, 0.0);
                    let mut sp = sigma;
                    let mut sign = 1.0;
                    for terms in (1..=p.terms).rev() {
                        let v = deriv[..terms].iter().rev().fold(0.0, |acc, c| acc * t + c);
                        out += sign * v / sp;
                        sp *= sigma;
                        sign = -sign;
                        for i in 1..terms {
                            deriv[i - 1] = deriv[i] * i as f64;
                        }
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

/// The Gauss–Legendre nodes and weights of a cut factor's short pieces, computed once.
fn gauss_nodes() -> [(f64, f64); GAUSS_NODES] {
    use std::sync::OnceLock;
    static NODES: OnceLock<[(f64, f64); GAUSS_NODES]> = OnceLock::new();
    *NODES.get_or_init(|| {
        let mut nodes = [(0.0, 0.0); GAUSS_NODES];
        nodes.copy_from_slice(&gauss_legendre(GAUSS_NODES));
        nodes
    })
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
        let (s, nx, ny) = sizes(p, level, level_subpixel(p, level));
        let mirrored = MirroredGrid::new(nx, ny);
        // Distinct factors per axis, each evaluated on the grid once per view.
        let mut grids: [Vec<(AxisFactor, FactorGrid)>; 3] = Default::default();
        for a in 0..3 {
            let mut distinct: Vec<AxisFactor> = group.iter().map(|i| keys[*i][a]).collect();
            distinct.sort_unstable();
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
                    // Row by row on the pool: a view's first cued batch brings only a few
                    // new factors, too few to keep the cores busy one factor each. A factor
                    // is a real function: the rows of negative frequency ρ whose mirror row
                    // is on the grid are filled from it ([`MirroredGrid`]), halving the
                    // evaluations.
                    let mut g = vec![Complex64::new(0.0, 0.0); nx * ny];
                    g.par_chunks_mut(nx).enumerate().for_each(|(ky, row)| {
                        let rho = signed(ky, ny) * s as f64 / ny as f64;
                        for &kx in mirrored.columns(ky) {
                            let sigma = signed(kx, nx) * s as f64 / nx as f64;
                            let xi = p.zoom * (sigma * p.ex[a] + rho * p.ey[a]);
                            row[kx] = match &cut {
                                Some(st) => st.at(xi),
                                None => f.transform(&tf, xi, k, l[a]),
                            };
                        }
                    });
                    mirrored.fill_mirrored_rows(&mut g);
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
                        .into_par_iter()
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
                (
                    i,
                    inverse_and_crop(&mut spec, &Crop::new(s, nx, ny, rx, ry)),
                )
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
