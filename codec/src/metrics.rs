//! Quality metrics, each named for what it is so the paper's units and the conventional ones are
//! never mixed (DESIGN.md: "the paper's dB are doubled").
//!
//! - [`q_i_paper_db`]: Q_I of eq. 18, `20·log10(Σ ref² / Σ err²)` — 20 × the log of an *energy*
//!   ratio, twice the usual SNR. Use it to compare with the paper.
//! - [`snr_db`]: the conventional `10·log10(Σ ref² / Σ err²)` (= Q_I / 2).
//! - [`psnr_db`]: `10·log10(peak² / MSE)`.
//! - [`q_v_percent`] (eq. 19) and [`q_e_percent`] (eq. 20): energy ratios in percent.
//!
//! All sums are in f64. A perfect match gives +∞ dB; an all-zero reference with a non-zero
//! error gives −∞.

/// Σ ref² and Σ (img − ref)² in f64.
fn energies<T: Copy + Into<f64>>(reference: &[T], image: &[T]) -> (f64, f64) {
    assert_eq!(
        reference.len(),
        image.len(),
        "metric inputs differ in length"
    );
    let mut e_ref = 0.0;
    let mut e_err = 0.0;
    for (r, i) in reference.iter().zip(image) {
        let (r, i): (f64, f64) = ((*r).into(), (*i).into());
        e_ref += r * r;
        e_err += (i - r) * (i - r);
    }
    (e_ref, e_err)
}

fn ratio_db(scale: f64, num: f64, den: f64) -> f64 {
    if den == 0.0 {
        f64::INFINITY
    } else if num == 0.0 {
        f64::NEG_INFINITY
    } else {
        scale * (num / den).log10()
    }
}

/// Q_I exactly as eq. 18 of the paper: `20·log10(Σ ref² / Σ (img − ref)²)` over all pixels and
/// colour components. Paper units: twice the conventional SNR.
pub fn q_i_paper_db<T: Copy + Into<f64>>(reference: &[T], image: &[T]) -> f64 {
    let (r, e) = energies(reference, image);
    ratio_db(20.0, r, e)
}

/// Conventional SNR: `10·log10(Σ ref² / Σ (img − ref)²)`.
pub fn snr_db<T: Copy + Into<f64>>(reference: &[T], image: &[T]) -> f64 {
    let (r, e) = energies(reference, image);
    ratio_db(10.0, r, e)
}

/// Conventional PSNR: `10·log10(peak² / MSE)`.
pub fn psnr_db<T: Copy + Into<f64>>(reference: &[T], image: &[T], peak: f64) -> f64 {
    let (_, e) = energies(reference, image);
    let mse = e / reference.len().max(1) as f64;
    ratio_db(10.0, peak * peak, mse)
}

/// Q_V of eq. 19: the energy of the kept coefficients as a percentage of the energy of all
/// coefficients (energies E(w) = w²·‖basis‖²).
pub fn q_v_percent(kept_energy: f64, total_energy: f64) -> f64 {
    if total_energy == 0.0 {
        100.0
    } else {
        100.0 * kept_energy / total_energy
    }
}

/// Q_E of eq. 20–21: the energy of the quantization residuals E(w − w̃) as a percentage of the
/// energy of the coefficients, given `(w, w̃, ‖basis‖²·importance-free weight)` triples.
pub fn q_e_percent(pairs: impl IntoIterator<Item = (f64, f64, f64)>) -> f64 {
    let mut res = 0.0;
    let mut tot = 0.0;
    for (w, wq, norm2) in pairs {
        res += (w - wq) * (w - wq) * norm2;
        tot += w * w * norm2;
    }
    if tot == 0.0 {
        0.0
    } else {
        100.0 * res / tot
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paper_db_is_twice_conventional() {
        let r = [1.0f32, 2.0, 3.0];
        let i = [1.1f32, 1.9, 3.0];
        let q = q_i_paper_db(&r, &i);
        let s = snr_db(&r, &i);
        assert!((q - 2.0 * s).abs() < 1e-9);
        // Independent: Σr² = 14, Σe² = 0.02 → 10 log10(700).
        assert!((s - 10.0 * 700f64.log10()).abs() < 1e-4, "{s}");
        assert_eq!(snr_db(&r, &r), f64::INFINITY);
        assert_eq!(snr_db(&[0.0f32], &[1.0]), f64::NEG_INFINITY);
        let p = psnr_db(&[0.0f32, 0.0], &[1.0, 1.0], 255.0);
        assert!((p - 20.0 * 255f64.log10()).abs() < 1e-9);
    }

    #[test]
    fn energy_ratios() {
        assert_eq!(q_v_percent(50.0, 200.0), 25.0);
        let qe = q_e_percent([(2.0, 1.0, 1.0), (0.0, 0.0, 5.0), (1.0, 1.0, 2.0)]);
        // residual 1, total 4 + 2 = 6.
        assert!((qe - 100.0 / 6.0).abs() < 1e-12);
    }
}
