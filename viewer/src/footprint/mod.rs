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

//!
//! Its parts: this module holds the tables (`FineTable`, `Footprint` and its phase tables, the
//! mipmap); `slice` computes them by Fourier projection-slice; `factor` owns the axis factors of
//! depth-cued and cut pieces and their tables; `set` holds a view's tables.

mod factor;
mod set;
mod slice;

pub use factor::{
    compute_factor_tables, compute_factor_tables_with, cut_transform, AxisFactor, CutFactor,
    FactorGrids,
};
pub use set::{FootprintSet, VANISHING};
pub use slice::{
    axis_transform, basis_transform, compute_fine, compute_fine_at, compute_fine_with,
    footprint_spectrum, level_subpixel, support_radius, Transforms,
};
use wavesplat_codec::family::Family;
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

    /// The largest magnitude of its samples (0 for an empty table; NaN samples are skipped).
    pub fn peak(&self) -> f64 {
        self.data.iter().fold(0.0, |m: f64, v| m.max(v.abs()))
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
        let (nx, ny) = (self.nx, self.ny);
        let mut data = Vec::with_capacity(self.data.len());
        // Row by row over slices (no per-sample bounds test): a neighbour outside the table
        // is 0, exactly as `get` gives it.
        let zero_row = vec![0.0f64; nx];
        for iy in 0..ny {
            let row = &self.data[iy * nx..(iy + 1) * nx];
            if axis == 0 {
                for ix in 0..nx {
                    let d0 = if ix > 0 { row[ix - 1] } else { 0.0 };
                    let d1 = if ix + 1 < nx { row[ix + 1] } else { 0.0 };
                    data.push((d1 - d0) * half_s);
                }
            } else {
                let above = if iy > 0 {
                    &self.data[(iy - 1) * nx..iy * nx]
                } else {
                    &zero_row[..]
                };
                let below = if iy + 1 < ny {
                    &self.data[(iy + 1) * nx..(iy + 2) * nx]
                } else {
                    &zero_row[..]
                };
                data.extend(above.iter().zip(below).map(|(d0, d1)| (d1 - d0) * half_s));
            }
        }
        FineTable {
            s: self.s,
            nx,
            ny,
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

/// One phase of a footprint: where its samples (the fine table's at pixel spacing, row-major)
/// lie in its [`Phases`] buffer, and which of them it keeps: the box from column `x0` and row
/// `y0` of the whole phase that holds every sample above [`TRIM`] of the table's peak.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Phase {
    /// First sample in [`Phases::data`].
    pub offset: usize,
    /// Columns kept.
    pub cols: usize,
    /// Rows kept.
    pub rows: usize,
    /// First column kept (of the whole phase, whose column 0 is the table's first).
    pub x0: usize,
    /// First row kept.
    pub y0: usize,
}

/// The S × S phases of one fine table, their samples in one buffer (a view minified far gets
/// S = 32 and a thousand phases per table: one allocation each cost a third of its planning).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Phases {
    /// The phases, phase (a, b) at index b·S + a.
    pub rects: Vec<Phase>,
    /// Every phase's samples, phase after phase.
    pub data: Vec<f32>,
}

impl Phases {
    /// Number of phases.
    pub fn len(&self) -> usize {
        self.rects.len()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.rects.is_empty()
    }
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
    pub phases: Phases,
    /// ∂/∂x of the footprint per pixel, split into phases like `phases` (empty unless the
    /// footprint was built with gradients): a splat placed δ pixels from its exact position
    /// adds δ times this (first-order correction of the subpixel residual).
    pub grad_x: Phases,
    /// ∂/∂y likewise.
    pub grad_y: Phases,
}

/// A table's samples at most this fraction of its peak are left out of its phases where they
/// border them: each phase keeps the smallest box of its samples that holds every larger one.
/// The footprints are compactly supported, but their computed tables carry tails of rounding
/// and of the pixel filter's spectrum far below that, and a phase's rectangle has corners
/// beyond an oblique footprint's hexagonal support: at 1e-6 a linear 256² view's finest
/// tables lose ~20 % of their samples and a cubic one's ~50 %, each sample that many fewer
/// pixel updates per splat. A sample left out changes its pixel by at most this fraction of
/// what the splat's largest sample adds, far below the tables' own error against exact line
/// integrals (60–80 dB on the MRI): the MRI's images with and without the trim differ at
/// 155–208 dB, at the f32 sums' rounding.
pub const TRIM: f64 = 1e-6;

/// Splits fine tables of one footprint (the table, or the table and its two gradients) into
/// their S × S phases, phase (a, b) at index b·S + a, each phase cut to the smallest box of its
/// samples that holds every sample above [`TRIM`] of its table's peak in any of the tables (a
/// footprint and its gradients share each box, so their records cover the same pixels and are
/// summed in one sweep); a phase with none keeps nothing. Finding a box reads only what it
/// leaves out and one sample more per row and side (rows from the top and the bottom until one
/// holds a sample above the floor, then each row's ends inwards), so that cutting costs less
/// than the copy it saves.
fn split_phases<'t>(tables: &[&'t FineTable]) -> Vec<Phases> {
    let t0 = tables[0];
    let s = t0.s;
    let floors: Vec<f64> = tables.iter().map(|t| TRIM * t.peak()).collect();
    let mut out: Vec<Phases> = tables
        .iter()
        .map(|t| Phases {
            rects: Vec::with_capacity(s * s),
            data: Vec::with_capacity(t.data.len()),
        })
        .collect();
    for b in 0..s {
        for a in 0..s {
            let cols = (t0.nx + s - 1 - a) / s;
            let rows = (t0.ny + s - 1 - b) / s;
            // Row l of the phase in table t: its sample k is row(t, l)[k·S].
            let row =
                |t: &'t FineTable, l: usize| -> &'t [f64] { &t.data[(l * s + b) * t.nx + a..] };
            let (mut k0, mut k1, mut l0, mut l1) = (cols, 0, rows, 0);
            for (&t, &floor) in tables.iter().zip(&floors) {
                let above = |k: usize, l: usize| row(t, l)[k * s].abs() > floor;
                let occupied = |l: usize| {
                    row(t, l)
                        .iter()
                        .step_by(s)
                        .take(cols)
                        .any(|v| v.abs() > floor)
                };
                let Some(top) = (0..rows).find(|&l| occupied(l)) else {
                    continue;
                };
                let bottom = (top..rows).rev().find(|&l| occupied(l)).unwrap_or(top);
                l0 = l0.min(top);
                l1 = l1.max(bottom + 1);
                for l in top..=bottom {
                    if let Some(k) = (0..k0.min(cols)).find(|&k| above(k, l)) {
                        k0 = k;
                    }
                    if let Some(k) = (k1..cols).rev().find(|&k| above(k, l)) {
                        k1 = k + 1;
                    }
                }
            }
            if k0 >= k1 || l0 >= l1 {
                (k0, k1, l0, l1) = (0, 0, 0, 0);
            }
            for (phases, &t) in out.iter_mut().zip(tables) {
                phases.rects.push(Phase {
                    offset: phases.data.len(),
                    cols: k1 - k0,
                    rows: l1 - l0,
                    x0: k0,
                    y0: l0,
                });
                for l in l0..l1 {
                    let row = row(t, l);
                    phases.data.extend((k0..k1).map(|k| row[k * s] as f32));
                }
            }
        }
    }
    out
}

impl Footprint {
    /// Splits a fine table into its phases (no gradients).
    pub fn from_fine(t: &FineTable) -> Footprint {
        Footprint {
            s: t.s,
            cx: t.cx,
            cy: t.cy,
            phases: split_phases(&[t]).pop().unwrap_or_default(),
            grad_x: Phases::default(),
            grad_y: Phases::default(),
        }
    }

    /// Splits a fine table and its gradient into phases (each phase and its two gradient
    /// phases cut to one box).
    pub fn with_gradient(t: &FineTable) -> Footprint {
        let (gx, gy) = (t.derivative(0), t.derivative(1));
        let [phases, grad_x, grad_y]: [Phases; 3] = split_phases(&[t, &gx, &gy])
            .try_into()
            .expect("three tables give three phase sets");
        Footprint {
            s: t.s,
            cx: t.cx,
            cy: t.cy,
            phases,
            grad_x,
            grad_y,
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

    /// Placement along one axis of a splat centred at continuous screen coordinate `centre`:
    /// returns (phase, first pixel) such that pixel `first + k` reads column k of the phase.
    #[inline]
    pub fn place(s: usize, c: usize, centre: f64) -> (usize, i64) {
        let (a, first, _) = Footprint::place_with_residual(s, c, centre);
        (a, first)
    }

    /// [`Footprint::place`] and the subpixel residual of that placement: the exact centre minus
    /// where the chosen phase puts it, in pixels (|residual| ≤ 1/(2S)).
    #[inline]
    pub fn place_with_residual(s: usize, c: usize, centre: f64) -> (usize, i64, f64) {
        let d = round_half_away(s as f64 * (centre - 0.5));
        let t = c as i64 - d as i64;
        // Every record is placed through here: the default S (8 or 16) is a power of two,
        // whose Euclidean remainder and floor quotient are a mask and a shift instead of two
        // 64-bit divisions (the same values for every t).
        let (a, q) = if s.is_power_of_two() {
            (t & (s as i64 - 1), t >> s.trailing_zeros())
        } else {
            let a = t.rem_euclid(s as i64);
            (a, (t - a) / s as i64)
        };
        (a as usize, -q, (d / s as f64 + 0.5) - centre)
    }
}

/// `x.round()` (half away from zero), bit for bit, without a call: the build's baseline
/// x86-64 has no rounding instruction, so `f64::round` is a libm call, ~4 % of a render's
/// planning time through [`Footprint::place_with_residual`].
#[inline]
pub(crate) fn round_half_away(x: f64) -> f64 {
    // From 2^52 on every f64 is an integer (and NaN and the infinities round to themselves).
    const INTEGRAL: f64 = 4_503_599_627_370_496.0;
    if x.is_nan() || x.abs() >= INTEGRAL {
        return x;
    }
    // Toward zero, exact below 2^52.
    let t = x as i64 as f64;
    // Exact: t and x share every bit above the binary point.
    let f = x - t;
    // Without branches (which way a centre rounds is as good as random): the step away from
    // zero, and the sign of x for a zero result (−0.3 rounds to −0.0; every other result
    // already has the sign of x).
    let up = f64::from(u8::from(f >= 0.5));
    let down = f64::from(u8::from(f <= -0.5));
    (t + up - down).copysign(x)
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

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// Placement as first written: `f64::round`, and the remainder and quotient by division.
    fn place_by_division(s: usize, c: usize, centre: f64) -> (usize, i64, f64) {
        let d = (s as f64 * (centre - 0.5)).round();
        let t = c as i64 - d as i64;
        let a = t.rem_euclid(s as i64);
        let q = (t - a) / s as i64;
        (a as usize, -q, (d / s as f64 + 0.5) - centre)
    }

    #[test]
    fn rounding_without_a_call_equals_f64_round_on_the_edges() {
        let edges = [
            0.0,
            -0.0,
            0.5,
            -0.5,
            1.5,
            2.5,
            -2.5,
            0.499_999_999_999_999_94,
            -0.499_999_999_999_999_94,
            4_503_599_627_370_495.5,
            4_503_599_627_370_496.0,
            -4_503_599_627_370_497.0,
            9.3e18,
            1e300,
            f64::MIN_POSITIVE,
            -5e-324,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NAN,
        ];
        for x in edges {
            let (ours, std) = (round_half_away(x), x.round());
            assert!(
                ours.to_bits() == std.to_bits() || (ours.is_nan() && std.is_nan()),
                "{x:e}: {ours:e} against {std:e}"
            );
        }
    }

    proptest! {
        #[test]
        fn rounding_without_a_call_equals_f64_round(bits in any::<u64>(), x in -1e7f64..1e7) {
            for x in [f64::from_bits(bits), x, x.trunc() + 0.5, x.trunc() - 0.5] {
                let (ours, std) = (round_half_away(x), x.round());
                prop_assert!(
                    ours.to_bits() == std.to_bits() || (ours.is_nan() && std.is_nan()),
                    "{:e}: {:e} against {:e}", x, ours, std
                );
            }
        }

        #[test]
        fn placement_by_mask_and_shift_equals_placement_by_division(
            log_s in 1u32..6,
            odd_s in 1usize..20,
            c in 0usize..400,
            centre in -5000.0f64..5000.0,
        ) {
            for s in [1usize << log_s, 2 * odd_s + 1, 2 * odd_s] {
                let (a, first, r) = Footprint::place_with_residual(s, c, centre);
                let (a0, first0, r0) = place_by_division(s, c, centre);
                prop_assert_eq!((a, first), (a0, first0), "S = {}", s);
                prop_assert_eq!(r.to_bits(), r0.to_bits(), "S = {}", s);
            }
        }
    }

    /// The derivative by its definition: central differences of `get`, zero outside.
    fn derivative_by_get(t: &FineTable, axis: usize) -> Vec<f64> {
        let mut out = Vec::new();
        for iy in 0..t.ny as i64 {
            for ix in 0..t.nx as i64 {
                let (d0, d1) = if axis == 0 {
                    (t.get(ix - 1, iy), t.get(ix + 1, iy))
                } else {
                    (t.get(ix, iy - 1), t.get(ix, iy + 1))
                };
                out.push((d1 - d0) * 0.5 * t.s as f64);
            }
        }
        out
    }

    #[test]
    fn derivative_is_the_central_difference_with_zeros_outside() {
        for (cx, cy) in [(0, 0), (0, 3), (4, 0), (1, 1), (7, 5)] {
            let n = (2 * cx + 1) * (2 * cy + 1);
            let data: Vec<f64> = (0..n)
                .map(|i| ((i * 7919) % 113) as f64 - 50.0 + (i as f64).sin())
                .collect();
            let t = FineTable::centred(4, cx, cy, data);
            for axis in 0..2 {
                let d = t.derivative(axis);
                assert_eq!((d.nx, d.ny, d.cx, d.cy, d.s), (t.nx, t.ny, t.cx, t.cy, t.s));
                let want = derivative_by_get(&t, axis);
                // Bit for bit: the same two samples, subtracted and scaled the same way.
                assert!(
                    d.data
                        .iter()
                        .zip(&want)
                        .all(|(a, b)| a.to_bits() == b.to_bits()),
                    "{cx}x{cy} axis {axis}"
                );
            }
        }
    }
}
