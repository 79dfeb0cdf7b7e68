//! Least-squares refinement of the kept set: the refit equals a dense least-squares solve,
//! refinement lowers the reconstruction error of the same number of coefficients, and the
//! coefficients it proposes to add next fill what the refined set leaves unexplained.

use nalgebra::{DMatrix, DVector};
use wavesplat_codec::dwt::{
    coefficients_to_samples, decompose_channel, inverse_3d, pad_channel, reconstruct_channel, Dwt1d,
};
use wavesplat_codec::family::Family;
use wavesplat_codec::layout::Geometry;
use wavesplat_codec::volume::Volume;
use wavesplat_compressor::phantom::Phantom;
use wavesplat_compressor::refine::{refine, refine_extended, KeptValue, RefineOptions};

/// The `k` coefficients of largest energy w²·‖b‖².
fn top_k(g: &Geometry, coeffs: &[f64], k: usize) -> Vec<KeptValue> {
    let mut all: Vec<(f64, usize)> = coeffs
        .iter()
        .enumerate()
        .filter(|(_, w)| **w != 0.0)
        .map(|(i, w)| (w * w * g.basis_norm2(g.locate(i).0), i))
        .collect();
    all.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
    all.truncate(k);
    all.iter()
        .map(|(_, i)| KeptValue {
            channel: 0,
            index: *i as u32,
            value: coeffs[*i] as f32,
        })
        .collect()
}

fn dense(g: &Geometry, kept: &[KeptValue]) -> Vec<f64> {
    let mut c = vec![0.0; g.coefficient_count()];
    for k in kept {
        c[k.index as usize] = k.value as f64;
    }
    c
}

/// Refines a single-channel selection of `vol` with importance 1.
fn refine_one(
    g: &Geometry,
    vol: &Volume,
    kept: &[KeptValue],
    opts: &RefineOptions,
) -> Vec<KeptValue> {
    refine(g, &[vol.channel(0).to_vec()], &[1.0], kept, opts)
}

/// Zeroes the padded-grid samples the renderer never draws: outside the volume's box when it
/// clips to it.
fn seen(g: &Geometry, samples: &mut [f64]) {
    if !g.clips_to_box() {
        return;
    }
    let [px, py, _] = g.padded;
    for (i, v) in samples.iter_mut().enumerate() {
        let p = [i % px, (i / px) % py, i / (px * py)];
        if (0..3).any(|a| p[a] < g.origin[a] || p[a] >= g.origin[a] + g.dims[a]) {
            *v = 0.0;
        }
    }
}

fn error2(a: &[f32], b: &[f32]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (*x as f64 - *y as f64).powi(2))
        .sum()
}

/// With no thresholding rounds and enough CG iterations, the refitted values are the dense
/// least-squares solution (nalgebra SVD on the explicit synthesis matrix) on the same support.
#[test]
fn refit_matches_dense_least_squares() {
    // [7, 5, 3] pads to [8, 6, 4] without a margin: the renderer clips to the box, so the
    // least squares count only the samples inside it.
    for (family, dims) in [
        (Family::Linear, [8, 6, 4]),
        (Family::Cubic, [8, 6, 4]),
        (Family::Linear, [7, 5, 3]),
        (Family::Cubic, [7, 5, 3]),
    ] {
        let vol = Phantom::SheppLogan.generate(dims);
        let g = Geometry::new(dims, family, 1, 0).unwrap();
        let coeffs = decompose_channel(vol.channel(0), &g);
        let kept = top_k(&g, &coeffs, 40);
        let opts = RefineOptions {
            rounds: 0,
            cg_iterations: 300,
            ..RefineOptions::default()
        };
        let out = refine_one(&g, &vol, &kept, &opts);
        assert!(
            !out.is_empty() && out.len() <= kept.len(),
            "{family} {dims:?}"
        );
        // Columns of R for the returned support.
        let n = g.coefficient_count();
        let mut planner = Dwt1d::new(family);
        let mut r = DMatrix::<f64>::zeros(n, out.len());
        for (col, k) in out.iter().enumerate() {
            let mut e = vec![0.0; n];
            e[k.index as usize] = 1.0;
            inverse_3d(&mut e, &g, &mut planner);
            coefficients_to_samples(&mut e, &g);
            seen(&g, &mut e);
            r.set_column(col, &DVector::from_vec(e));
        }
        let f = DVector::from_vec(pad_channel(vol.channel(0), &g));
        let x = r.clone().svd(true, true).solve(&f, 1e-13).unwrap();
        // The refinement runs in single precision: its fit must be as good as the dense
        // solution's (to f32 accuracy), and for the well-conditioned linear family on a grid
        // without padding so must the values (the cubic normal equations are too
        // ill-conditioned for f32 values, and where samples outside the box do not count, the
        // coefficients at its edge are too weakly held for them).
        let got = DVector::from_iterator(out.len(), out.iter().map(|k| k.value as f64));
        let best = (&f - &r * &x).norm_squared();
        let fit = (&f - &r * &got).norm_squared();
        assert!(
            fit <= best * (1.0 + 1e-4) + 1e-9 * f.norm_squared(),
            "{family}: residual {fit} vs dense {best}"
        );
        if family == Family::Linear && g.padded == g.dims {
            let scale = x.amax();
            for (k, want) in out.iter().zip(x.iter()) {
                assert!(
                    (k.value as f64 - want).abs() <= 2e-5 * scale,
                    "{family}: index {} refit {} vs dense {want}",
                    k.index,
                    k.value
                );
            }
        }
    }
}

/// Refinement never sends more coefficients than asked, keeps every value above the oracle's
/// threshold, and reconstructs the volume better than the oracle's own K coefficients: the
/// default refinement, and the fast effort's one refit of one conjugate-gradient step.
#[test]
fn refinement_beats_thresholding_at_equal_count() {
    for (family, opts) in [
        (Family::Linear, RefineOptions::default()),
        (Family::Cubic, RefineOptions::default()),
        (Family::Linear, RefineOptions::ONE_SET),
        (Family::Cubic, RefineOptions::ONE_SET),
    ] {
        let dims = [24, 20, 16];
        let vol = Phantom::SheppLogan.generate(dims);
        let margin = Geometry::separating_margin(family, 2);
        let g = Geometry::new(dims, family, 2, margin).unwrap();
        let coeffs = decompose_channel(vol.channel(0), &g);
        let k = g.coefficient_count() / 40;
        let kept = top_k(&g, &coeffs, k);
        let threshold = kept
            .iter()
            .map(|s| (s.value as f64).powi(2) * g.basis_norm2(g.locate(s.index as usize).0))
            .fold(f64::INFINITY, f64::min);
        let out = refine_one(&g, &vol, &kept, &opts);
        assert!(out.len() <= k, "{family}: {} > {k}", out.len());
        for s in &out {
            let score = (s.value as f64).powi(2) * g.basis_norm2(g.locate(s.index as usize).0);
            assert!(score >= threshold, "{family}: {score} < {threshold}");
        }
        // The oracle's own best out.len() coefficients (pruning may have dropped some).
        let same_count = top_k(&g, &coeffs, out.len());
        let plain = error2(
            vol.channel(0),
            &reconstruct_channel(&dense(&g, &same_count), &g),
        );
        let refined = error2(vol.channel(0), &reconstruct_channel(&dense(&g, &out), &g));
        let gain_db = 10.0 * (plain / refined).log10();
        eprintln!(
            "{family}: {} of {k} kept, {gain_db:.2} dB better",
            out.len()
        );
        assert!(gain_db > 0.2, "{family}: refinement gained {gain_db:.2} dB");
    }
}

/// Haar is orthogonal within and across levels: the selection comes back unchanged.
#[test]
fn haar_selection_is_returned_unchanged() {
    let dims = [16, 16, 16];
    let vol = Phantom::SheppLogan.generate(dims);
    let g = Geometry::new(dims, Family::Haar, 3, 0).unwrap();
    let coeffs = decompose_channel(vol.channel(0), &g);
    let kept = top_k(&g, &coeffs, 200);
    let out = refine_one(&g, &vol, &kept, &RefineOptions::default());
    let mut a: Vec<(u32, f32)> = kept.iter().map(|k| (k.index, k.value)).collect();
    let mut b: Vec<(u32, f32)> = out.iter().map(|k| (k.index, k.value)).collect();
    a.sort_by_key(|x| x.0);
    b.sort_by_key(|x| x.0);
    assert_eq!(a, b);
}

/// The compressor reports whether the kept values were refined, and the transform's non-zero
/// count is the same either way (not the size of the refined set).
#[test]
fn compress_reports_refinement() {
    use wavesplat_compressor::encode::{compress, CompressOptions, Target};
    let vol = Phantom::SheppLogan.generate([20, 20, 20]);
    let run = |refine: Option<RefineOptions>| {
        compress(
            &vol,
            &CompressOptions {
                target: Target::Fraction(0.02),
                refine,
                ..Default::default()
            },
            &|_, _| {},
        )
        .unwrap()
        .stats
    };
    let refined = run(Some(RefineOptions::default()));
    let plain = run(None);
    assert!(refined.refined && !plain.refined);
    assert_eq!(refined.nonzero_coefficients, plain.nonzero_coefficients);
    assert!(refined.kept <= plain.kept && refined.nonzero_coefficients > plain.kept);
}

/// The extension of a refined set: coefficients outside it, scoring below all of it, in
/// decreasing score order; adding its first tenth of the set's size lowers the error of the
/// refined set, and lowers it more than adding as many of the oracle's next coefficients with
/// their exact values (those repeat what the refitted neighbours already carry). Errors in f64
/// on what the renderer draws, the box when it clips to it (the codec's reference synthesis,
/// not the refinement's f32 transforms). Non-zero faces (CT-like, no margin) and a thin,
/// non-power-of-two slab too.
#[test]
fn the_extension_tops_up_a_refined_set_better_than_the_oracles_next_values() {
    let cases = [
        (Phantom::SheppLogan, [24, 20, 16], Family::Linear, 2, true),
        (Phantom::SheppLogan, [24, 20, 16], Family::Cubic, 2, true),
        (Phantom::Ct, [30, 22, 13], Family::Linear, 2, false),
        (Phantom::Spheres, [40, 36, 5], Family::Linear, 1, false),
    ];
    for (phantom, dims, family, levels, separated) in cases {
        let what = format!("{phantom:?} {dims:?} {family}");
        let vol = phantom.generate(dims);
        let margin = if separated {
            Geometry::separating_margin(family, levels)
        } else {
            0
        };
        let g = Geometry::new(dims, family, levels, margin).unwrap();
        let coeffs = decompose_channel(vol.channel(0), &g);
        let k = g.coefficient_count() / 30;
        let kept = top_k(&g, &coeffs, k);
        let score =
            |s: &KeptValue| (s.value as f64).powi(2) * g.basis_norm2(g.locate(s.index as usize).0);
        let out = refine_extended(
            &g,
            &[vol.channel(0).to_vec()],
            &[1.0],
            &kept,
            &RefineOptions::default(),
            k / 4,
        );
        assert!(!out.kept.is_empty(), "{what}");
        assert!(
            out.first_survivors > 0 && out.first_survivors <= k,
            "{what}: {} survivors of {k}",
            out.first_survivors
        );
        assert!(out.extension.len() <= k / 4, "{what}");
        let floor = out.kept.iter().map(score).fold(f64::INFINITY, f64::min);
        let in_set: std::collections::HashSet<u32> = out.kept.iter().map(|s| s.index).collect();
        for pair in out.extension.windows(2) {
            assert!(
                score(&pair[0]) >= score(&pair[1]),
                "{what}: extension out of order"
            );
        }
        for s in &out.extension {
            assert!(s.value.is_finite() && s.value != 0.0, "{what}");
            assert!(
                !in_set.contains(&s.index),
                "{what}: {} already kept",
                s.index
            );
            assert!(
                score(s) < floor,
                "{what}: extension scores {} >= {floor}",
                score(s)
            );
        }
        let e = (out.kept.len() / 10).max(1);
        assert!(
            out.extension.len() >= e,
            "{what}: extension {} < {e}",
            out.extension.len()
        );
        let oracle_next: Vec<KeptValue> = top_k(&g, &coeffs, k + k / 2)
            .into_iter()
            .filter(|s| !in_set.contains(&s.index))
            .take(e)
            .collect();
        assert_eq!(oracle_next.len(), e, "{what}");
        // On what the renderer draws: the padded grid, or the box when it clips to it.
        let target = pad_channel(vol.channel(0), &g);
        let mut planner = Dwt1d::new(family);
        let mut error_of = |extra: &[KeptValue]| {
            let all: Vec<KeptValue> = out.kept.iter().chain(extra).copied().collect();
            let mut samples = dense(&g, &all);
            inverse_3d(&mut samples, &g, &mut planner);
            coefficients_to_samples(&mut samples, &g);
            for (s, t) in samples.iter_mut().zip(&target) {
                *s -= t;
            }
            seen(&g, &mut samples);
            samples.iter().map(|r| r * r).sum::<f64>()
        };
        let alone = error_of(&[]);
        let extended = error_of(&out.extension[..e]);
        let oracle = error_of(&oracle_next);
        assert!(
            extended < alone && extended < oracle,
            "{what}: refined {alone:.4e}, + extension {extended:.4e}, + oracle {oracle:.4e}"
        );
    }
}
