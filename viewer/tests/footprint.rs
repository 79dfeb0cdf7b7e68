//! Footprint tests: the slice transform near zero frequency, the FFT path against a direct
//! projection, and the mipmap against directly computed finer levels.
mod common;

use num_complex::Complex64;
use std::f64::consts::PI;
use wavesplat_codec::family::Family;
use wavesplat_codec::view::basis_from_angles;
use wavesplat_viewer::footprint::{
    basis_transform, compute_fine, compute_fine_with, mipmap, FootprintParams, Transforms,
};

fn sinc_series(f: f64) -> f64 {
    let y = PI * f;
    if y.abs() < 1e-3 {
        1.0 - y * y / 6.0 + y.powi(4) / 120.0
    } else {
        y.sin() / y
    }
}

/// High-precision centred Haar transforms: φ̂ = sinc(f), ψ̂ = i (πf/2) sinc²(f/2).
fn haar_reference(level: usize, kind: u8, xi: [f64; 3]) -> Complex64 {
    let s = (1u64 << level) as f64;
    (0..3)
        .map(|a| {
            let f = s * xi[a];
            if kind & (4 >> a) != 0 {
                Complex64::new(0.0, s * PI * f / 2.0 * sinc_series(f / 2.0).powi(2))
            } else {
                Complex64::new(s * sinc_series(f), 0.0)
            }
        })
        .product()
}

fn params(family: Family, levels: usize, alpha: f64, beta: f64, zoom: f64) -> FootprintParams {
    let (u, v) = basis_from_angles(alpha, beta);
    FootprintParams {
        family,
        levels,
        ex: u,
        ey: [-v[0], -v[1], -v[2]],
        zoom,
        voxel_volume: 1.0,
        subpixel: 8,
        max_fft: 768,
        cue: None,
        gradient: false,
    }
}

/// Slice product at σ, ρ ∈ {0, 1e-12, 1e-8, 1e-4}: every Haar type and the scaling type of every
/// family agree with closed forms evaluated without cancellation to 1e-12 relative; the linear
/// and cubic wavelet types (whose transform vanishes like f^j at 0, and whose codec evaluation
/// Σ q_n e^(−iπfn) cancels there) agree to 1e-12 of the scaling-type magnitude.
#[test]
fn slice_transform_near_zero_is_accurate() {
    let p = params(Family::Haar, 2, 0.66, 0.91, 1.7);
    let vals = [0.0, 1e-12, 1e-8, 1e-4];
    for &sigma in &vals {
        for &rho in &vals {
            let xi = [
                p.zoom * (sigma * p.ex[0] + rho * p.ey[0]),
                p.zoom * (sigma * p.ex[1] + rho * p.ey[1]),
                p.zoom * (sigma * p.ex[2] + rho * p.ey[2]),
            ];
            for level in 0..=2 {
                for kind in 0..8u8 {
                    let got = basis_transform(Family::Haar, level, kind, xi, [0.0; 3]);
                    let want = haar_reference(level, kind, xi);
                    let err = (got - want).norm();
                    assert!(
                        err <= 1e-12 * want.norm() || (want.norm() == 0.0 && err == 0.0),
                        "haar L{level} t{kind} σ={sigma} ρ={rho}: {got} vs {want}"
                    );
                }
                for family in [Family::Linear, Family::Cubic] {
                    let j = family.order() as i32;
                    let s = (1u64 << level) as f64;
                    let want0: f64 = (0..3).map(|a| s * sinc_series(s * xi[a]).powi(j)).product();
                    let got0 = basis_transform(family, level, 0, xi, [0.0; 3]);
                    assert!((got0 - want0).norm() <= 1e-12 * want0, "{family} φφφ");
                    for kind in 1..8u8 {
                        let got = basis_transform(family, level, kind, xi, [0.0; 3]);
                        // Closed form of the centred ψ at these tiny f: O(f^j), so |got| must be
                        // at rounding level relative to the scaling type.
                        let small = (s * xi.iter().fold(0.0f64, |m, x| m.max(x.abs()))).powi(j);
                        assert!(
                            got.norm() <= 1e-12 * want0 + 10.0 * small * want0,
                            "{family} t{kind}: {got}"
                        );
                    }
                }
            }
        }
    }
}

#[test]
fn cached_psi_hat_matches_codec() {
    for family in Family::ALL {
        let tf = Transforms::new(family);
        for &f in &[0.0, 1e-9, 0.013, 0.37, 1.9, -2.7] {
            for &k in &[0.0, 0.3, -0.3, 7.0, -40.0] {
                let a = tf.psi_hat(f, k);
                let b = family.psi_hat(f, k);
                assert!(
                    (a - b).norm() <= 1e-13 * (1.0 + b.norm()),
                    "{family} f={f} κ={k}"
                );
            }
        }
    }
}

/// Pixel-averaged chord length through a cube of side 2^level centred at the origin.
fn box_projection(p: &FootprintParams, level: usize, x: f64, y: f64, sub: usize) -> f64 {
    let h = 0.5 * (1u64 << level) as f64;
    let dir = {
        let (ex, ey) = (p.ex, p.ey);
        // n = u × v with u = ex, v = −ey.
        let v = [-ey[0], -ey[1], -ey[2]];
        [
            ex[1] * v[2] - ex[2] * v[1],
            ex[2] * v[0] - ex[0] * v[2],
            ex[0] * v[1] - ex[1] * v[0],
        ]
    };
    let mut acc = 0.0;
    for sy in 0..sub {
        for sx in 0..sub {
            let px = (x - 0.5 + (sx as f64 + 0.5) / sub as f64) / p.zoom;
            let py = (y - 0.5 + (sy as f64 + 0.5) / sub as f64) / p.zoom;
            let o = [
                px * p.ex[0] + py * p.ey[0],
                px * p.ex[1] + py * p.ey[1],
                px * p.ex[2] + py * p.ey[2],
            ];
            let (mut t0, mut t1) = (f64::NEG_INFINITY, f64::INFINITY);
            for a in 0..3 {
                if dir[a].abs() < 1e-15 {
                    if o[a].abs() > h {
                        t1 = t0 - 1.0;
                    }
                    continue;
                }
                let ta = (-h - o[a]) / dir[a];
                let tb = (h - o[a]) / dir[a];
                t0 = t0.max(ta.min(tb));
                t1 = t1.min(ta.max(tb));
            }
            acc += (t1 - t0).max(0.0);
        }
    }
    acc / (sub * sub) as f64
}

/// The FFT footprint of the Haar scaling function equals the direct numerical projection
/// (pixel-averaged chord lengths, 48×48 rays per pixel) to 2e-3 of its peak.
#[test]
fn fft_footprint_matches_direct_projection() {
    let p = params(Family::Haar, 1, 0.66, 0.91, 2.0);
    let t = &compute_fine(&p, 1, &[0])[0];
    let peak = t.data.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let mut worst: f64 = 0.0;
    for iy in (0..t.ny).step_by(3) {
        for ix in (0..t.nx).step_by(3) {
            let x = (ix as f64 - t.cx as f64) / t.s as f64;
            let y = (iy as f64 - t.cy as f64) / t.s as f64;
            let direct = box_projection(&p, 1, x, y, 48);
            worst = worst.max((t.data[iy * t.nx + ix] - direct).abs());
        }
    }
    eprintln!(
        "FFT vs direct projection: max error {:.2e} of peak {peak:.3}",
        worst / peak
    );
    assert!(worst <= 2e-3 * peak, "{worst} vs peak {peak}");
}

/// Mipmapped level-m tables equal directly computed ones (3e-3 of the peak, worst Haar ψψψ; both carry the
/// band truncation of their own FFT).
#[test]
fn mipmap_matches_direct_levels() {
    for family in Family::ALL {
        let p = params(family, 3, 0.66, 0.91, 1.5);
        let top = compute_fine(&p, 3, &[0, 3, 5, 7]);
        for (t, kind) in top.iter().zip([0u8, 3, 5, 7]) {
            let kind = if kind == 0 { 1 } else { kind };
            let t = if kind == 1 {
                &compute_fine_with(&p, 3, &[1], t.s, 2 * (t.nx + 8), 2 * (t.ny + 8))[0]
            } else {
                t
            };
            for level in 1..3 {
                let derived = mipmap(&p, t, 3, level, kind);
                let direct = &compute_fine_with(&p, level, &[kind], t.s, 512, 512)[0];
                let peak = direct.data.iter().fold(0.0f64, |m, v| m.max(v.abs()));
                let mut worst: f64 = 0.0;
                for iy in 0..direct.ny {
                    for ix in 0..direct.nx {
                        let x = (ix as f64 - direct.cx as f64) / direct.s as f64;
                        let y = (iy as f64 - direct.cy as f64) / direct.s as f64;
                        worst =
                            worst.max((derived.at(x, y) - direct.data[iy * direct.nx + ix]).abs());
                    }
                }
                eprintln!(
                    "{family} t{kind} level {level} from 3: mipmap error {:.2e} of peak",
                    worst / peak
                );
                assert!(
                    worst <= 3e-3 * peak,
                    "{family} t{kind} L{level}: {worst} vs {peak}"
                );
            }
        }
    }
}

/// Each level mipmapped from the one above it, as a footprint set builds them, against each
/// level from the top at once: the same box sums (the cascade reads the level above only
/// inside its crop, where the top's samples outside a level's support are the FFT's ringing),
/// within 1e-6 of the peak for every family, depths to 5 and an axis and an oblique view.
#[test]
fn cascaded_mipmap_equals_the_direct_one() {
    // (A ψ along the ray integrates to zero: on an axis some tables are zero throughout.)
    let mut nonzero = 0;
    for family in Family::ALL {
        for (alpha, beta) in [(0.0, 0.0), (0.66, 0.91)] {
            let m = 5;
            let p = params(family, m, alpha, beta, 0.3);
            let top = compute_fine(&p, m, &[3, 7]);
            for (t, kind) in top.iter().zip([3u8, 7]) {
                let mut above: Option<wavesplat_viewer::footprint::FineTable> = None;
                for level in (1..m).rev() {
                    let cascaded = mipmap(&p, above.as_ref().unwrap_or(t), level + 1, level, kind);
                    let direct = mipmap(&p, t, m, level, kind);
                    assert_eq!((cascaded.nx, cascaded.ny), (direct.nx, direct.ny));
                    let peak = direct.data.iter().fold(0.0f64, |a, v| a.max(v.abs()));
                    let worst = cascaded
                        .data
                        .iter()
                        .zip(&direct.data)
                        .fold(0.0f64, |a, (c, d)| a.max((c - d).abs()));
                    nonzero += usize::from(peak > 0.0);
                    assert!(
                        worst <= 1e-6 * peak,
                        "{family} ({alpha},{beta}) t{kind} level {level}: {worst:e} of {peak:e}"
                    );
                    above = Some(cascaded);
                }
            }
        }
    }
    assert!(nonzero >= 30, "{nonzero} non-zero tables");
}

/// Composite Simpson on [a, b] with `n` (even) intervals.
fn simpson(a: f64, b: f64, n: usize, f: impl Fn(f64) -> Complex64) -> Complex64 {
    let h = (b - a) / n as f64;
    let mut s = f(a) + f(b);
    for i in 1..n {
        let w = if i % 2 == 1 { 4.0 } else { 2.0 };
        s += f(a + h * i as f64) * w;
    }
    s * (h / 3.0)
}

/// The transform of a level-0 B-spline cut to part of its support (at a face of the data's box),
/// cued from the kept part's end nearest the light (closed form and Gauss–Legendre on its pieces)
/// equals brute-force Simpson integration of the cut, cued integrand, split at the knots and the
/// cut, for both light directions, stiff and vanishing extinctions, every cut of linear and
/// cubic, and frequencies up to 9 cycles per voxel.
#[test]
fn cut_transform_matches_direct_integration() {
    use wavesplat_viewer::footprint::cut_transform;
    for family in [Family::Linear, Family::Cubic] {
        let half = 0.5 * family.phi_support();
        let h = half as i8;
        let mut cuts = Vec::new();
        for a in -h..h {
            for b in a + 1..=h {
                if (a, b) != (-h, h) {
                    cuts.push((a, b));
                }
            }
        }
        for &(ca, cb) in &cuts {
            for &(k, la) in &[
                (0.5, 0.6),
                (0.5, -0.6),
                (5.0, 0.9),
                (1e-12, -1.0),
                (1e3, 0.3),
            ] {
                for &xi in &[0.0, 1e-9, 0.3, 2.7, 9.1] {
                    let got = cut_transform(family, xi, k, la, ca, cb);
                    let (lo, hi) = (ca as f64, cb as f64);
                    let uref = if la >= 0.0 { lo } else { hi };
                    // Each piece lies inside or outside the kept part: classified by its midpoint.
                    let integrand = |u: f64, kept: bool| {
                        let w = if kept {
                            (-k * la * (u - uref)).exp()
                        } else {
                            0.0
                        };
                        Complex64::from_polar(family.phi(u + half) * w, -2.0 * PI * xi * u)
                    };
                    let mut knots: Vec<f64> =
                        (0..=family.order()).map(|i| -half + i as f64).collect();
                    knots.push(lo);
                    knots.push(hi);
                    knots.sort_by(f64::total_cmp);
                    let mut want = Complex64::new(0.0, 0.0);
                    for w in knots.windows(2) {
                        if w[1] > w[0] {
                            let mid = 0.5 * (w[0] + w[1]);
                            let behind = mid > lo && mid < hi;
                            // Enough intervals to resolve the stiffest decay (≥ 200 per e-fold).
                            let n =
                                4000 + 2 * (100.0 * k * la.abs() * (w[1] - w[0])).ceil() as usize;
                            want += simpson(w[0], w[1], n, |u| integrand(u, behind));
                        }
                    }
                    let err = (got - want).norm();
                    assert!(got.re.is_finite() && got.im.is_finite());
                    assert!(
                        err <= 1e-9 * want.norm().max(1e-3),
                        "{family} cut [{ca}, {cb}] k={k} la={la} xi={xi}: {got} vs {want}"
                    );
                }
            }
        }
    }
}

/// Every axis factor is a real function of position, so its transform at −ξ is the conjugate of
/// its transform at ξ; the factor grids of a cued view fill their negative-frequency rows from
/// that (`compute_factor_tables`), which draws the same image only if the floating-point
/// evaluation is conjugate-symmetric: the same numbers (a zero's sign aside, which no sum keeps).
/// Checked for whole φ and ψ of levels 0–3 and every cut, of each family, uncued, cued from
/// either side, stiff, at frequencies from 1e-300 to 50 cycles per voxel.
mod conjugate_symmetry {
    use super::*;
    use proptest::prelude::*;
    use wavesplat_viewer::footprint::{AxisFactor, Transforms};

    fn factors(family: Family) -> Vec<AxisFactor> {
        let mut out = Vec::new();
        for level in 0..4 {
            for wavelet in [false, true] {
                out.push(AxisFactor::Basis { level, wavelet });
            }
        }
        let h = (0.5 * family.phi_support()) as i8;
        for a in -h..h {
            for b in a + 1..=h {
                if (a, b) != (-h, h) {
                    out.push(AxisFactor::Cut { a, b });
                }
            }
        }
        out
    }

    /// The bits of a complex number, with −0.0 read as +0.0.
    fn bits(z: Complex64) -> (u64, u64) {
        ((z.re + 0.0).to_bits(), (z.im + 0.0).to_bits())
    }

    proptest! {
        #[test]
        fn conjugate_symmetry_is_exact(
            family in prop::sample::select(vec![Family::Haar, Family::Linear, Family::Cubic]),
            magnitude in -300.0f64..1.7,
            (k, la) in prop::sample::select(vec![
                (0.0, 0.0), (0.02, 0.7), (0.02, -0.7), (0.5, 1.0), (3.0, -0.2), (1e3, 0.3),
            ]),
        ) {
            let xi = 10f64.powf(magnitude);
            let tf = Transforms::new(family);
            for f in factors(family) {
                let plus = f.transform(&tf, xi, k, la);
                let minus = f.transform(&tf, -xi, k, la);
                prop_assert_eq!(
                    bits(minus),
                    bits(plus.conj()),
                    "{:?} of {} at ξ = {:e}, k = {}, l = {}: {} against {}",
                    f, family, xi, k, la, minus, plus
                );
            }
        }
    }
}

/// The phases keep a box of their samples (`footprint::TRIM`): for every family on an axis, a
/// few degrees off and obliquely, with and without gradients, each phase's kept samples are
/// the fine table's at the phase's grid points from its box's corner on, everything outside
/// the box is at most TRIM of its table's peak, a footprint and its two gradients share each
/// box, and obliquely the boxes leave samples out (the cubic family's most).
#[test]
fn phases_keep_every_sample_above_the_trim() {
    use wavesplat_viewer::footprint::{FineTable, Footprint, Phases, TRIM};
    // Every sample of phase (a, b) of `t`, kept or not, against what `phases` holds.
    let check = |t: &FineTable, phases: &Phases, what: &str| -> (usize, usize) {
        let (s, floor) = (t.s, TRIM * t.peak());
        let (mut kept, mut all) = (0, 0);
        for b in 0..s {
            for a in 0..s {
                let p = phases.rects[b * s + a];
                let cols = (t.nx + s - 1 - a) / s;
                let rows = (t.ny + s - 1 - b) / s;
                for l in 0..rows {
                    for k in 0..cols {
                        let v = t.data[(l * s + b) * t.nx + k * s + a];
                        all += 1;
                        let inside = (p.x0..p.x0 + p.cols).contains(&k)
                            && (p.y0..p.y0 + p.rows).contains(&l);
                        if inside {
                            kept += 1;
                            let got = phases.data[p.offset + (l - p.y0) * p.cols + (k - p.x0)];
                            assert_eq!(got, v as f32, "{what}: phase ({a},{b}) sample ({k},{l})");
                        } else {
                            assert!(
                                v.abs() <= floor,
                                "{what}: ({a},{b}) ({k},{l}) {v:e} left out"
                            );
                        }
                    }
                }
            }
        }
        (kept, all)
    };
    for family in [Family::Haar, Family::Linear, Family::Cubic] {
        for (alpha, beta) in [(0.0, 0.0), (0.05, 0.02), (0.66, 0.91)] {
            let p = params(family, 2, alpha, beta, 1.3);
            for t in compute_fine(&p, 1, &[1, 3, 7]) {
                let what = format!("{family} ({alpha},{beta})");
                let plain = Footprint::build(&t, false);
                let (kept, all) = check(&t, &plain.phases, &what);
                let f = Footprint::build(&t, true);
                for (g, p) in f.phases.rects.iter().zip(&plain.phases.rects) {
                    let inside = g.cols * g.rows > 0
                        && (g.x0 <= p.x0
                            && g.y0 <= p.y0
                            && p.x0 + p.cols <= g.x0 + g.cols
                            && p.y0 + p.rows <= g.y0 + g.rows);
                    assert!(p.cols * p.rows == 0 || inside, "{what}: {g:?} holds {p:?}");
                }
                let gx = t.derivative(0);
                let gy = t.derivative(1);
                check(&t, &f.phases, &what);
                check(&gx, &f.grad_x, &format!("{what} ∂x"));
                check(&gy, &f.grad_y, &format!("{what} ∂y"));
                for (i, r) in f.phases.rects.iter().enumerate() {
                    for g in [&f.grad_x.rects[i], &f.grad_y.rects[i]] {
                        assert_eq!((g.x0, g.y0, g.cols, g.rows), (r.x0, r.y0, r.cols, r.rows));
                    }
                }
                if (alpha, beta) == (0.66, 0.91) && family == Family::Cubic {
                    assert!(kept * 10 < all * 8, "{what}: kept {kept} of {all}");
                }
            }
        }
    }
}
