//! Chui–Wang semi-orthogonal B-spline wavelet families (paper §2.2) and their closed-form
//! Fourier transforms (eq. 5, 10, 11).
//!
//! A family of order `j` has the cardinal B-spline φ of order `j` (support `[0, j]`, eq. 3–4) as
//! scaling function and the wavelet ψ(x) = Σ q_k φ(2x − k), k = 0..3j−2 (eq. 6, support
//! `[0, 2j − 1]`). Haar is `j = 1`, linear `j = 2`, cubic `j = 4`. The two-scale relation of φ is
//! φ(x) = Σ p_k φ(2x − k) with p_k = C(j, k) / 2^(j−1).
//!
//! The Fourier transforms use the convention F(f) = ∫ h(x) e^(−i2πfx) dx, so that the box on
//! `[0, 1)` transforms to (1 − e^(−i2πf)) / (i2πf) as in eq. 5. They optionally include an
//! exponential depth cue e^(−κ(x − x_near)) where `x_near` is the end of the support nearest to
//! the light (`0` for κ ≥ 0, the right end for κ < 0): every exponent is then ≤ 0 on the support,
//! so stiff cueing only underflows towards 0 and never overflows (DESIGN.md, §3.2 of the paper).
//! The removable singularity of (1 − e^(−s))/s at s → 0 is evaluated by its power series.

use num_complex::Complex64;
use std::f64::consts::PI;

/// A wavelet family: the order of the B-spline it is built on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Family {
    /// Order 1: box scaling function, Haar wavelet. ψ is odd about its centre.
    Haar,
    /// Order 2: hat scaling function, piecewise-linear wavelet. ψ is even about its centre.
    Linear,
    /// Order 4: cubic B-spline scaling function, cubic spline wavelet. ψ is even about its centre.
    Cubic,
}

impl Family {
    /// All families, in order of increasing smoothness.
    pub const ALL: [Family; 3] = [Family::Haar, Family::Linear, Family::Cubic];

    /// The B-spline order `j` (1, 2 or 4).
    pub fn order(self) -> usize {
        match self {
            Family::Haar => 1,
            Family::Linear => 2,
            Family::Cubic => 4,
        }
    }

    /// The code used in the bitstream header.
    pub fn code(self) -> u8 {
        self.order() as u8
    }

    /// Inverse of [`Family::code`].
    pub fn from_code(code: u8) -> Option<Family> {
        match code {
            1 => Some(Family::Haar),
            2 => Some(Family::Linear),
            4 => Some(Family::Cubic),
            _ => None,
        }
    }

    /// Lower-case name as used on the command line.
    pub fn name(self) -> &'static str {
        match self {
            Family::Haar => "haar",
            Family::Linear => "linear",
            Family::Cubic => "cubic",
        }
    }

    /// Parses a family name (`haar`, `linear`, `cubic`).
    pub fn from_name(name: &str) -> Option<Family> {
        Family::ALL.into_iter().find(|f| f.name() == name)
    }

    /// Two-scale coefficients p_k of φ (k = 0..=j): φ(x) = Σ p_k φ(2x − k).
    pub fn scaling_filter(self) -> Vec<f64> {
        let j = self.order();
        let scale = 2f64.powi(j as i32 - 1);
        (0..=j).map(|k| binomial(j, k) / scale).collect()
    }

    fn index(self) -> usize {
        match self {
            Family::Haar => 0,
            Family::Linear => 1,
            Family::Cubic => 2,
        }
    }

    /// Filters and norms, computed once per family (the B-spline recursion behind them is
    /// exponential in the order, and energies are needed per coefficient).
    fn constants(self) -> &'static Constants {
        static TABLE: std::sync::OnceLock<[Constants; 3]> = std::sync::OnceLock::new();
        &TABLE.get_or_init(|| Family::ALL.map(Constants::compute))[self.index()]
    }

    /// Two-scale coefficients q_k of ψ (k = 0..=3j−2), eq. 6:
    /// q_k = (−1)^k / 2^(j−1) Σ_{l=0..j} C(j, l) φ^[2j](k + 1 − l).
    pub fn wavelet_filter(self) -> Vec<f64> {
        self.constants().q.clone()
    }

    fn compute_wavelet_filter(self) -> Vec<f64> {
        let j = self.order();
        let scale = 2f64.powi(j as i32 - 1);
        (0..=(3 * j - 2))
            .map(|k| {
                let s: f64 = (0..=j)
                    .map(|l| binomial(j, l) * bspline(2 * j, (k + 1) as f64 - l as f64))
                    .sum();
                if k % 2 == 0 {
                    s / scale
                } else {
                    -s / scale
                }
            })
            .collect()
    }

    /// Support length of φ (its support is `[0, j]`).
    pub fn phi_support(self) -> f64 {
        self.order() as f64
    }

    /// Support length of ψ (its support is `[0, 2j − 1]`).
    pub fn psi_support(self) -> f64 {
        (2 * self.order() - 1) as f64
    }

    /// True when ψ is odd about the centre of its support (reflection negates it), false when
    /// it is even. Derived from the filter: q is antisymmetric for odd `j`, symmetric for even.
    pub fn psi_is_odd(self) -> bool {
        let q = self.wavelet_filter();
        let n = q.len();
        (0..n).all(|k| (q[k] + q[n - 1 - k]).abs() < 1e-12)
    }

    /// φ(x), the cardinal B-spline of order `j` (support `[0, j]`).
    pub fn phi(self, x: f64) -> f64 {
        bspline(self.order(), x)
    }

    /// ψ(x) = Σ q_k φ(2x − k).
    pub fn psi(self, x: f64) -> f64 {
        self.constants()
            .q
            .iter()
            .enumerate()
            .map(|(k, q)| q * self.phi(2.0 * x - k as f64))
            .sum()
    }

    /// Autocorrelation of φ at integer lag `k`: ∫ φ(x) φ(x + k) dx = φ^[2j](j + k).
    pub fn phi_autocorrelation(self, k: i64) -> f64 {
        let j = self.order();
        bspline(2 * j, j as f64 + k as f64)
    }

    /// ‖φ‖² (level 0, undilated).
    pub fn phi_norm2(self) -> f64 {
        self.constants().phi_norm2
    }

    /// ‖ψ‖² (undilated): ½ Σ q_n q_n' a(n − n') with a the autocorrelation of φ.
    pub fn psi_norm2(self) -> f64 {
        self.constants().psi_norm2
    }

    fn compute_psi_norm2(self, q: &[f64]) -> f64 {
        let mut s = 0.0;
        for (n, qn) in q.iter().enumerate() {
            for (m, qm) in q.iter().enumerate() {
                s += qn * qm * self.phi_autocorrelation(n as i64 - m as i64);
            }
        }
        0.5 * s
    }

    /// Fourier transform of the (optionally cued) scaling function:
    /// ∫ φ(x) e^(−κ(x − x_near)) e^(−i2πfx) dx, with `x_near = 0` for κ ≥ 0 and `j` for κ < 0
    /// (eq. 5 for κ = 0, eq. 10 otherwise).
    pub fn phi_hat(self, f: f64, kappa: f64) -> Complex64 {
        phi_hat_order(self.order(), f, kappa)
    }

    /// Fourier transform of the (optionally cued) wavelet:
    /// ∫ ψ(x) e^(−κ(x − x_near)) e^(−i2πfx) dx, with `x_near = 0` for κ ≥ 0 and `2j − 1` for
    /// κ < 0 (eq. 11 for κ = 0; the cued form weights each fine-scale term by its own offset so
    /// that no factor exceeds 1).
    pub fn psi_hat(self, f: f64, kappa: f64) -> Complex64 {
        let j = self.order();
        let q = &self.constants().q;
        let half = phi_hat_order(j, 0.5 * f, 0.5 * kappa);
        let mut acc = Complex64::new(0.0, 0.0);
        for (n, qn) in q.iter().enumerate() {
            let n = n as f64;
            let weight = if kappa >= 0.0 {
                (-kappa * n / 2.0).exp()
            } else {
                (kappa * (2.0 * j as f64 - 1.0 - (j as f64 + n) / 2.0)).exp()
            };
            let phase = Complex64::from_polar(1.0, -PI * f * n);
            acc += phase * (qn * weight);
        }
        acc * half * 0.5
    }
}

/// Per-family constants, computed once.
struct Constants {
    q: Vec<f64>,
    phi_norm2: f64,
    psi_norm2: f64,
}

impl Constants {
    fn compute(family: Family) -> Constants {
        let q = family.compute_wavelet_filter();
        Constants {
            phi_norm2: family.phi_autocorrelation(0),
            psi_norm2: family.compute_psi_norm2(&q),
            q,
        }
    }
}

impl std::fmt::Display for Family {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// Binomial coefficient as f64 (small arguments only).
fn binomial(n: usize, k: usize) -> f64 {
    if k > n {
        return 0.0;
    }
    let mut r = 1.0;
    for i in 0..k {
        r = r * (n - i) as f64 / (i + 1) as f64;
    }
    r
}

/// Cardinal B-spline of order `j` with support `[0, j]`, by the recursion of eq. 4.
pub fn bspline(j: usize, x: f64) -> f64 {
    if j == 0 {
        return 0.0;
    }
    if j == 1 {
        return if (0.0..1.0).contains(&x) { 1.0 } else { 0.0 };
    }
    if x <= 0.0 || x >= j as f64 {
        return 0.0;
    }
    let jm1 = (j - 1) as f64;
    x / jm1 * bspline(j - 1, x) + (j as f64 - x) / jm1 * bspline(j - 1, x - 1.0)
}

/// (1 − e^(−s)) / s = ∫₀¹ e^(−sx) dx, accurate for all `s` with Re(s) ≥ 0, including the
/// removable singularity at s = 0 (power series Σ (−s)^n / (n + 1)! for |s| < 1/2).
pub fn box_transform(s: Complex64) -> Complex64 {
    if s.norm() < 0.5 {
        // Horner on Σ_{n=0}^{N} (−s)^n / (n+1)!; 24 terms leave < 0.5^24 / 25! of truncation.
        let mut acc = Complex64::new(0.0, 0.0);
        for n in (0..24).rev() {
            acc = acc * (-s) / ((n + 2) as f64) + 1.0;
        }
        // The loop computes 1 + (−s)/2 (1 + (−s)/3 (...)) = Σ (−s)^n / (n+1)!.
        acc
    } else {
        (Complex64::new(1.0, 0.0) - (-s).exp()) / s
    }
}

/// Cued B-spline transform for order `j` (see [`Family::phi_hat`]).
fn phi_hat_order(j: usize, f: f64, kappa: f64) -> Complex64 {
    let w = 2.0 * PI * f;
    let one = if kappa >= 0.0 {
        box_transform(Complex64::new(kappa, w))
    } else {
        // e^κ (1 − e^(−κ − i2πf)) / (κ + i2πf) = e^(−i2πf) · E(−κ − i2πf): evaluated where the
        // real part is positive, so nothing overflows.
        Complex64::from_polar(1.0, -w) * box_transform(Complex64::new(-kappa, -w))
    };
    one.powi(j as i32)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Gauss–Legendre quadrature on [a, b] (integer ends) with `per_unit` panels per unit
    /// length, so that panel edges fall on the half-integer knots of φ and ψ: exact for the
    /// piecewise polynomials, and an independent way to integrate them times exponentials.
    fn integrate(a: f64, b: f64, per_unit: usize, g: impl Fn(f64) -> Complex64) -> Complex64 {
        let panels = ((b - a) * per_unit as f64).round() as usize;
        // 5-point Gauss–Legendre nodes and weights.
        let nodes = [
            0.0,
            -0.538_469_310_105_683_1,
            0.538_469_310_105_683_1,
            -0.906_179_845_938_664,
            0.906_179_845_938_664,
        ];
        let weights = [
            0.568_888_888_888_888_9,
            0.478_628_670_499_366_47,
            0.478_628_670_499_366_47,
            0.236_926_885_056_189_08,
            0.236_926_885_056_189_08,
        ];
        let h = (b - a) / panels as f64;
        let mut acc = Complex64::new(0.0, 0.0);
        for p in 0..panels {
            let lo = a + p as f64 * h;
            for (x, w) in nodes.iter().zip(weights) {
                acc += g(lo + 0.5 * h * (x + 1.0)) * (w * 0.5 * h);
            }
        }
        acc
    }

    #[test]
    fn filters_match_known_values() {
        assert_eq!(Family::Haar.scaling_filter(), vec![1.0, 1.0]);
        assert_eq!(Family::Haar.wavelet_filter(), vec![1.0, -1.0]);
        let q = Family::Linear.wavelet_filter();
        let expect = [1.0, -6.0, 10.0, -6.0, 1.0];
        for (a, b) in q.iter().zip(expect) {
            assert!((a - b / 12.0).abs() < 1e-15, "{q:?}");
        }
        assert_eq!(Family::Cubic.wavelet_filter().len(), 11);
        assert!(Family::Haar.psi_is_odd());
        assert!(!Family::Linear.psi_is_odd());
        assert!(!Family::Cubic.psi_is_odd());
    }

    #[test]
    fn wavelets_have_vanishing_moments_and_are_orthogonal_to_coarse_scaling() {
        for fam in Family::ALL {
            let j = fam.order();
            // ψ has j vanishing moments; ⟨ψ(x), φ(x − k)⟩ = 0 for all k (semi-orthogonality).
            for moment in 0..j {
                let m = integrate(0.0, fam.psi_support(), 200, |x| {
                    Complex64::new(fam.psi(x) * x.powi(moment as i32), 0.0)
                });
                assert!(m.norm() < 1e-9, "{fam} moment {moment}: {m}");
            }
            for k in -(2 * j as i64)..(2 * j as i64) {
                let ip = integrate(-10.0, 10.0, 100, |x| {
                    Complex64::new(fam.psi(x) * fam.phi(x - k as f64), 0.0)
                });
                assert!(ip.norm() < 1e-9, "{fam} <psi, phi(.-{k})> = {ip}");
            }
        }
    }

    #[test]
    fn norms_match_quadrature() {
        for fam in Family::ALL {
            let np = integrate(0.0, fam.phi_support(), 200, |x| {
                Complex64::new(fam.phi(x).powi(2), 0.0)
            });
            let nq = integrate(0.0, fam.psi_support(), 200, |x| {
                Complex64::new(fam.psi(x).powi(2), 0.0)
            });
            assert!((np.re - fam.phi_norm2()).abs() < 1e-9, "{fam}");
            assert!((nq.re - fam.psi_norm2()).abs() < 1e-9, "{fam}");
        }
    }

    #[test]
    fn fourier_transforms_match_quadrature_with_and_without_cue() {
        for fam in Family::ALL {
            for &kappa in &[0.0, 0.3, -0.7, 5.0, -12.0] {
                for &f in &[0.0, 0.05, 0.37, 1.0, 2.3] {
                    let x_phi = if kappa >= 0.0 { 0.0 } else { fam.phi_support() };
                    let x_psi = if kappa >= 0.0 { 0.0 } else { fam.psi_support() };
                    let num_phi = integrate(0.0, fam.phi_support(), 200, |x| {
                        Complex64::from_polar(
                            fam.phi(x) * (-kappa * (x - x_phi)).exp(),
                            -2.0 * PI * f * x,
                        )
                    });
                    let num_psi = integrate(0.0, fam.psi_support(), 200, |x| {
                        Complex64::from_polar(
                            fam.psi(x) * (-kappa * (x - x_psi)).exp(),
                            -2.0 * PI * f * x,
                        )
                    });
                    let a = fam.phi_hat(f, kappa);
                    let b = fam.psi_hat(f, kappa);
                    assert!(
                        (a - num_phi).norm() < 1e-9,
                        "{fam} k={kappa} f={f}: {a} vs {num_phi}"
                    );
                    assert!(
                        (b - num_psi).norm() < 1e-9,
                        "{fam} k={kappa} f={f}: {b} vs {num_psi}"
                    );
                }
            }
        }
    }

    #[test]
    fn removable_singularity_is_accurate_near_zero() {
        // Independent reference: Gauss–Legendre of ∫₀¹ e^(−sx) dx (smooth, so quadrature is
        // accurate to rounding), compared at |s| ∈ {0, 1e-12, 1e-8, 1e-4} in several directions.
        for &r in &[0.0, 1e-12, 1e-8, 1e-4, 0.49, 0.51] {
            for &ang in &[0.0, 0.7, std::f64::consts::FRAC_PI_2, 2.0] {
                let s = Complex64::from_polar(r, ang);
                let s = Complex64::new(s.re.abs(), s.im);
                let reference = integrate(0.0, 1.0, 4, |x| (-s * x).exp());
                let got = box_transform(s);
                let rel = (got - reference).norm() / reference.norm();
                assert!(rel < 1e-12, "s={s}: {got} vs {reference} rel {rel}");
            }
        }
    }

    #[test]
    fn stiff_cueing_stays_finite() {
        for fam in Family::ALL {
            for &kappa in &[1e-12, 5.0, 50.0, 1e3, 3.2e4, 1e300, -1e3, -1e300] {
                for &f in &[0.0, 0.5, 7.25, 1e6] {
                    let a = fam.phi_hat(f, kappa);
                    let b = fam.psi_hat(f, kappa);
                    assert!(a.re.is_finite() && a.im.is_finite(), "{fam} {kappa} {f}");
                    assert!(b.re.is_finite() && b.im.is_finite(), "{fam} {kappa} {f}");
                }
            }
        }
    }
}
