//! Least-squares refinement of the kept coefficients: this module owns the step between the
//! energy oracle and quantization that makes the K coefficients we send fit the volume better.
//!
//! The oracle (paper eq. 14) keeps the K coefficients of largest energy w²·‖b‖² and sends their
//! exact values. That is optimal for an orthonormal basis, but B-spline wavelets are only
//! *semi*-orthogonal: levels are mutually orthogonal, translates within a level are not (the
//! cubic φ Gram symbol ranges over a factor of 18 per axis). Dropping a coefficient then also
//! removes part of what its kept neighbours needed, and the kept values are no longer the best
//! ones for the kept set. Measured on the 128³ MNI volume at 30 000 coefficients (linear / cubic):
//! thresholding gives 22.3 / 19.9 dB volume SNR, a refit of the values 22.6 / 22.1 dB, and four
//! rounds of iterative hard thresholding with refits 22.9 / 23.3 dB.
//!
//! Algorithm (on the padded voxel grid, per channel weighted by its colour importance; where
//! the grid leaves less room than the separating margin, [`Geometry::clips_to_box`], the
//! residual counts only the samples inside the box, since nothing outside is ever drawn; with
//! a wider margin it counts the margin's too, which the renderer now clips as well):
//! 1. refit: minimise ‖f − R c‖² over the values of the kept set S, where R is the synthesis to
//!    voxel samples (inverse transform, then the cubic sampling FIR), by conjugate gradients on
//!    the normal equations, Jacobi-preconditioned with the exact per-band diagonal of RᵀR;
//! 2. iterative hard thresholding: c ← H_K(c + D⁻¹Rᵀ(f − R c)), H_K keeping the K largest by the
//!    oracle's score, then refit; repeated `rounds` times;
//! 3. prune: refitted values whose score fell below the selection threshold are dropped and the
//!    rest refitted (repeated while anything drops, up to [`PRUNE_REFITS`] times, then a last
//!    prune), so every sent value lies above its band's quantizer threshold exactly as with
//!    plain thresholding;
//! 4. on request, the extension: the best coefficients outside the set, valued one gradient
//!    step from its fit ([`Refined::extension`]), for a byte target to top the set up with.
//!
//! The conjugate-gradient refit carries the full (unmasked) gradient Rᵀ(f − R c) along with its
//! masked residual, so each iterative-hard-thresholding round reads its candidates from the refit
//! before it instead of paying another synthesis and transpose. Everything runs in f32 on the
//! codec's panel transforms ([`FastTransform`]) with five dense arrays per channel (target,
//! values, gradient, search direction, work) and a mask; the K best candidates are picked by
//! the histogram selection of [`crate::select`], never by sorting the whole grid.
//!
//! Sums are taken in fixed-size chunks, so the result does not depend on the thread count.
//! Written here because no crate does sparse least squares against a custom wavelet operator;
//! the transforms themselves are the codec's.

use crate::select::{
    all_sorted, histogram, pick_order, score_bin, top_k, top_k_from_floor, BINS_PER_OCTAVE, CHUNK,
};
use crate::visible::Visible;
use rayon::prelude::*;
use wavesplat_codec::dwt::fast::FastTransform;
use wavesplat_codec::dwt::{pad_channel_as, unit_basis_line};
use wavesplat_codec::family::Family;
use wavesplat_codec::layout::Geometry;

/// Settings of [`refine`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RefineOptions {
    /// Rounds of iterative hard thresholding (0: only refit the oracle's selection).
    pub rounds: usize,
    /// Conjugate-gradient iterations per refit.
    pub cg_iterations: usize,
    /// Refits after a prune, while the prune drops values (a last prune without refit may
    /// follow): [`PRUNE_REFITS`] by default.
    pub prune_refits: usize,
    /// A byte target refines one set, of a size guessed from the unrefined file that fills it,
    /// and fits that set to the target by the rate search (no pilot refit, no second set); the
    /// bricks of a bricked volume do not refine (each is coded from the top its scoring pass
    /// kept). [`RefineOptions::ONE_SET`], the fast effort's.
    pub one_set: bool,
}

impl Default for RefineOptions {
    fn default() -> Self {
        RefineOptions {
            rounds: 3,
            cg_iterations: 2,
            prune_refits: PRUNE_REFITS,
            one_set: false,
        }
    }
}

impl RefineOptions {
    /// The cheapest refinement that pays (`--effort fast`): one refit of one conjugate-gradient
    /// step (four transforms), one prune, one set per byte target. On the test set it gains
    /// 0.5–2.3 dB Q_I over the oracle's values for about a third more time (BENCHMARKS.md,
    /// "Compression effort").
    pub const ONE_SET: RefineOptions = RefineOptions {
        rounds: 0,
        cg_iterations: 1,
        prune_refits: 0,
        one_set: true,
    };
}

/// A kept coefficient: channel, linear (Mallat) index and value.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct KeptValue {
    /// Channel.
    pub channel: u8,
    /// Index in the channel's coefficient array.
    pub index: u32,
    /// Value.
    pub value: f32,
}

/// CG iterations between restarts from the true gradient (single precision drifts).
const RESTART: usize = 16;

/// Refits after prunes. Each refit after the first drops only a few hundredths of the set; a
/// third one (6 of the 42 transforms a refinement ran with it) moved Q_I by 0.01 dB on average
/// over the test set (worst 0.08 dB, within what neighbouring set sizes give) for 13 % of the
/// CPU.
pub const PRUNE_REFITS: usize = 2;

/// Σ over the periodic 1D grid of length `n` of the squared samples of the level-`level` φ
/// (`wavelet` false) or ψ: the 1D factor of the diagonal of RᵀR.
fn sample_norm2_1d(family: Family, n: usize, level: usize, wavelet: bool) -> f64 {
    unit_basis_line(family, n, level, wavelet, true)
        .iter()
        .map(|v| v * v)
        .sum()
}

/// The operator R (coefficients → padded voxel samples), its transpose and the Jacobi diagonal.
struct Operator<'a> {
    fast: FastTransform,
    /// Applications of R and Rᵀ so far (each is one 3D transform).
    applications: std::cell::Cell<usize>,
    /// 1 / diag(RᵀR) per band index.
    inv_diag: Vec<f32>,
    /// Band index of every coefficient.
    band_of: &'a [u8],
    /// The samples the residual counts: the volume's box on the padded grid when the renderer
    /// clips to it (then nothing outside is ever drawn), else `None` (the whole grid).
    seen: Option<SeenBox>,
}

/// The volume's box on the padded grid: row length, rows per plane, and per axis its start and
/// end (exclusive).
#[derive(Debug, Clone, Copy)]
struct SeenBox {
    padded: [usize; 3],
    lo: [usize; 3],
    hi: [usize; 3],
}

impl SeenBox {
    /// Whether row `y` of plane `z` crosses the box; then its samples `lo[0]..hi[0]` lie in it.
    fn row_inside(&self, y: usize, z: usize) -> bool {
        (self.lo[1]..self.hi[1]).contains(&y) && (self.lo[2]..self.hi[2]).contains(&z)
    }

    /// Zeroes the samples of plane `z` (rows of `padded[0]`) outside the box.
    fn restrict_plane(&self, z: usize, plane: &mut [f32]) {
        for (y, line) in plane.chunks_mut(self.padded[0]).enumerate() {
            if self.row_inside(y, z) {
                line[..self.lo[0]].fill(0.0);
                line[self.hi[0]..].fill(0.0);
            } else {
                line.fill(0.0);
            }
        }
    }
}

impl<'a> Operator<'a> {
    fn new(geometry: &Geometry, band_of: &'a [u8]) -> Operator<'a> {
        let inv_diag = geometry
            .bands()
            .iter()
            .map(|b| {
                let d: f64 = (0..3)
                    .map(|a| {
                        sample_norm2_1d(
                            geometry.family,
                            geometry.padded[a],
                            b.level as usize,
                            b.is_wavelet_along(a),
                        )
                    })
                    .product();
                (1.0 / d) as f32
            })
            .collect();
        let seen = geometry.clips_to_box().then(|| SeenBox {
            padded: geometry.padded,
            lo: geometry.origin,
            hi: std::array::from_fn(|a| geometry.origin[a] + geometry.dims[a]),
        });
        Operator {
            fast: FastTransform::new(geometry),
            applications: std::cell::Cell::new(0),
            inv_diag,
            band_of,
            seen,
        }
    }

    /// `out` ← Rᵀ(f − R c).
    fn gradient(&self, target: &[f32], c: &[f32], out: &mut [f32]) {
        out.par_iter_mut().zip(c).for_each(|(o, c)| *o = *c);
        self.applications.set(self.applications.get() + 2);
        let plane = self.fast.geometry().padded[0] * self.fast.geometry().padded[1];
        // The residual f − R c, counted only inside the box when the renderer clips to it.
        let seen = &self.seen;
        self.fast.normal_with(out, &|z, r| {
            let f = &target[z * plane..(z + 1) * plane];
            r.iter_mut().zip(f).for_each(|(r, f)| *r = f - *r);
            if let Some(b) = seen {
                b.restrict_plane(z, r);
            }
        });
    }

    /// `data` ← RᵀR `data`, with R's samples restricted to the box when the renderer clips.
    fn normal(&self, data: &mut [f32]) {
        self.applications.set(self.applications.get() + 2);
        let seen = &self.seen;
        self.fast.normal_with(data, &|z, r| {
            if let Some(b) = seen {
                b.restrict_plane(z, r);
            }
        });
    }

    /// Preconditioned CG on RᵀR c = Rᵀf over the entries of `mask`, from the current `c`
    /// (zero outside the mask). Leaves the full gradient Rᵀ(f − R c) at the final `c` in `g`;
    /// `p` and `work` are scratch.
    ///
    /// The set is ~2 % of the grid, and c and the search direction p are zero outside it, so
    /// everything but the transforms and the full gradient's update runs over the set's
    /// indices alone (listed per [`CHUNK`], so every sum adds the same terms in the same order
    /// as a pass over the whole grid would, and the result does not depend on the thread count).
    #[allow(clippy::too_many_arguments)]
    fn refit(
        &self,
        target: &[f32],
        c: &mut [f32],
        mask: &[bool],
        iterations: usize,
        g: &mut [f32],
        p: &mut [f32],
        work: &mut [f32],
    ) {
        let set: Vec<Vec<u32>> = mask
            .par_chunks(CHUNK)
            .map(|m| (0..m.len() as u32).filter(|i| m[*i as usize]).collect())
            .collect();
        self.gradient(target, c, g);
        let inv = &self.inv_diag;
        let band_of = self.band_of;
        // z = M⁻¹ r with r = mask ∘ g; p ← z + β p over the set (zero elsewhere); returns r·z.
        let precondition = |p: &mut [f32], g: &[f32], beta: f32| -> f64 {
            let parts: Vec<f64> = p
                .par_chunks_mut(CHUNK)
                .zip(g.par_chunks(CHUNK))
                .zip(band_of.par_chunks(CHUNK).zip(set.par_iter()))
                .map(|((p, g), (b, set))| {
                    let mut rz = 0.0f64;
                    for &i in set {
                        let i = i as usize;
                        let z = g[i] * inv[b[i] as usize];
                        rz += z as f64 * g[i] as f64;
                        p[i] = z + beta * p[i];
                    }
                    rz
                })
                .collect();
            parts.iter().sum()
        };
        p.par_iter_mut().for_each(|v| *v = 0.0);
        let mut rz = precondition(p, g, 0.0);
        for iteration in 0..iterations {
            if iteration > 0 && iteration % RESTART == 0 {
                // Long runs in single precision: replace the recurrence's drifting gradient by
                // the true one and restart from steepest descent.
                self.gradient(target, c, g);
                rz = precondition(p, g, 0.0);
            }
            if rz <= 0.0 || !rz.is_finite() {
                break;
            }
            // work ← p (zero outside the set), then RᵀR p; with it ⟨p, RᵀRp⟩ over the set.
            work.par_chunks_mut(CHUNK)
                .zip(p.par_chunks(CHUNK).zip(set.par_iter()))
                .for_each(|(w, (p, set))| {
                    w.fill(0.0);
                    for &i in set {
                        w[i as usize] = p[i as usize];
                    }
                });
            self.normal(work);
            let pap: f64 = {
                let parts: Vec<f64> = p
                    .par_chunks(CHUNK)
                    .zip(work.par_chunks(CHUNK).zip(set.par_iter()))
                    .map(|(p, (w, set))| {
                        set.iter()
                            .map(|&i| p[i as usize] as f64 * w[i as usize] as f64)
                            .sum::<f64>()
                    })
                    .collect();
                parts.iter().sum()
            };
            if pap <= 0.0 || !pap.is_finite() {
                break;
            }
            let alpha = (rz / pap) as f32;
            // The step (the gradient everywhere, c over the set), and in the same pass the new
            // r·z = Σ over the set of g²·D⁻¹ (β needs that sum before p can be updated).
            let rz_next: f64 = {
                let parts: Vec<f64> = c
                    .par_chunks_mut(CHUNK)
                    .zip(g.par_chunks_mut(CHUNK))
                    .zip(p.par_chunks(CHUNK).zip(work.par_chunks(CHUNK)))
                    .zip(band_of.par_chunks(CHUNK).zip(set.par_iter()))
                    .map(|(((c, g), (p, ap)), (b, set))| {
                        for (g, ap) in g.iter_mut().zip(ap.iter()) {
                            *g -= alpha * ap;
                        }
                        let mut rz = 0.0f64;
                        for &i in set {
                            let i = i as usize;
                            c[i] += alpha * p[i];
                            rz += (g[i] as f64).powi(2) * inv[b[i] as usize] as f64;
                        }
                        rz
                    })
                    .collect();
                parts.iter().sum()
            };
            let beta = (rz_next / rz) as f32;
            rz = precondition(p, g, beta);
        }
    }
}

/// Refines `kept` (the oracle's selection, any order) against the channels' voxel samples
/// (after the colour transform, unpadded). `importance[c]` weighs channel c as in the oracle.
/// Returns the refined set sorted by decreasing score w²·‖b‖²·I (ties by channel, index); it
/// holds at most `kept.len()` coefficients, all with score ≥ the smallest score in `kept`.
pub fn refine(
    geometry: &Geometry,
    samples: &[Vec<f32>],
    importance: &[f64],
    kept: &[KeptValue],
    opts: &RefineOptions,
) -> Vec<KeptValue> {
    refine_extended(geometry, samples, importance, kept, opts, 0).kept
}

/// [`refine`], also returning up to `extension` coefficients that would join the refined set
/// next ([`Refined::extension`]).
pub fn refine_extended(
    geometry: &Geometry,
    samples: &[Vec<f32>],
    importance: &[f64],
    kept: &[KeptValue],
    opts: &RefineOptions,
    extension: usize,
) -> Refined {
    let band_of = crate::select::band_map(geometry);
    let targets: Vec<Vec<f32>> = samples.iter().map(|s| pad_f32(s, geometry)).collect();
    refine_with(
        geometry,
        &band_of,
        None,
        &targets,
        importance,
        kept,
        opts,
        Output::Set { extension },
        &Scratch::default(),
    )
}

/// How far [`refine_with`] goes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Output {
    /// Only the first refit of the given set, to count its survivors (a byte target's
    /// estimate of what a refinement of that size keeps): `kept` and `extension` stay empty
    /// (for Haar, which needs no refit, every value survives).
    Pilot,
    /// The whole refinement, with up to `extension` coefficients that would join it next.
    Set { extension: usize },
}

/// A refinement's result ([`refine_extended`]).
#[derive(Debug, Clone, PartialEq)]
pub struct Refined {
    /// The refined set, by decreasing score (as [`refine`] returns it).
    pub kept: Vec<KeptValue>,
    /// The coefficients that would join the set next, by decreasing score, each scoring below
    /// every value of `kept`: outside the set, the value one gradient step in the Jacobi metric
    /// gives from the final fit (the candidate an iterative-hard-thresholding round would
    /// read), so it fills what the refined values leave unexplained instead of repeating what
    /// they already carry, as the exact (oracle) value would.
    pub extension: Vec<KeptValue>,
    /// How many of the given set's values still reach its smallest score after the first
    /// refit: about 0.95–1.05 times the size of the final set (BENCHMARKS.md, "One refinement
    /// per byte target").
    pub first_survivors: usize,
}

/// [`refine`] with the band map ([`crate::select::band_map`] of `geometry`) supplied, the
/// samples already padded ([`pad_f32`]) and its dense arrays taken from (and given back to)
/// `scratch`.
///
/// A refit moves a fifth or so of a top-K set below the K-th score, so about four fifths of
/// `kept` survive the prune (a byte target grows K until the survivors fill it).
#[allow(clippy::too_many_arguments)]
pub(crate) fn refine_with(
    geometry: &Geometry,
    band_of: &[u8],
    visible: Option<&Visible>,
    targets: &[Vec<f32>],
    importance: &[f64],
    kept: &[KeptValue],
    opts: &RefineOptions,
    output: Output,
    scratch: &Scratch,
) -> Refined {
    let k = kept.len();
    let channels = targets.len();
    let norms = crate::encode::band_norms(geometry);
    // The oracle's score, counting only the seen energy where that is asked for.
    let score_of = |c: usize, i: usize, v: f32| {
        let v = v as f64;
        let band = band_of[i];
        let seen = Visible::share(visible, i, band);
        if seen == 0.0 {
            // Wholly outside the box: never drawn, never a candidate (as the oracle's score).
            return -1.0;
        }
        v * v * norms[band as usize] * importance[c] * seen
    };
    if k == 0 || geometry.family == Family::Haar {
        // Haar is orthonormal up to per-band scale: thresholding is already optimal.
        if output == Output::Pilot {
            return Refined {
                kept: Vec::new(),
                extension: Vec::new(),
                first_survivors: k,
            };
        }
        return Refined {
            kept: sorted(&score_of, kept.to_vec()),
            extension: Vec::new(),
            first_survivors: k,
        };
    }
    let started = std::time::Instant::now();
    let op = Operator::new(geometry, band_of);
    let threshold = kept
        .iter()
        .map(|s| score_of(s.channel as usize, s.index as usize, s.value))
        .fold(f64::INFINITY, f64::min);
    let n = geometry.coefficient_count();
    let mut arrays = Arrays::take(scratch, channels, n);
    let Arrays {
        values,
        masks,
        grads,
        p,
        work,
        ..
    } = &mut arrays;
    for s in kept {
        values[s.channel as usize][s.index as usize] = s.value;
        masks[s.channel as usize][s.index as usize] = true;
    }
    let refit_all = |values: &mut [Vec<f32>],
                     masks: &[Vec<bool>],
                     grads: &mut [Vec<f32>],
                     p: &mut [f32],
                     work: &mut [f32]| {
        for c in 0..channels {
            op.refit(
                &targets[c],
                &mut values[c],
                &masks[c],
                opts.cg_iterations,
                &mut grads[c],
                p,
                work,
            );
        }
    };
    refit_all(values, masks, grads, p, work);
    // Kept values whose refit scores reach the threshold (the rest will be pruned).
    let survivors = |values: &[Vec<f32>], masks: &[Vec<bool>], threshold: f64| -> usize {
        (0..channels)
            .map(|c| {
                values[c]
                    .par_iter()
                    .zip(masks[c].par_iter())
                    .enumerate()
                    .filter(|(i, (v, m))| **m && score_of(c, *i, **v) >= threshold)
                    .count()
            })
            .sum()
    };
    let first_survivors = survivors(values, masks, threshold);
    let extension = match output {
        Output::Pilot => {
            return Refined {
                kept: Vec::new(),
                extension: Vec::new(),
                first_survivors,
            }
        }
        Output::Set { extension } => extension,
    };
    let mut floor_bin = score_bin(threshold).saturating_sub(BINS_PER_OCTAVE / 2);
    for _ in 0..opts.rounds {
        // Candidates: one gradient step in the Jacobi metric from the current fit (the refit
        // left the gradient there). Keep the K best over all channels (deterministic ties).
        let candidate =
            |c: usize, i: usize| values[c][i] + grads[c][i] * op.inv_diag[band_of[i] as usize];
        let score = |c: usize, i: usize| {
            let v = candidate(c, i);
            if v == 0.0 {
                -1.0
            } else {
                score_of(c, i, v)
            }
        };
        // One pass from a floor half an octave below the last cut (the oracle's threshold at
        // first): the same picks as the histogram's two passes, which run when it declines.
        let picks =
            top_k_from_floor(channels, n, k, floor_bin, 4 * k, &score).unwrap_or_else(|| {
                let hist = histogram(channels, n, &score, None::<&fn(usize, usize) -> f64>);
                top_k(&hist, channels, n, k, &score)
            });
        if let Some(last) = picks.last() {
            floor_bin = score_bin(last.0).saturating_sub(BINS_PER_OCTAVE / 2);
        }
        let chosen: Vec<(u8, u32, f32)> = picks
            .iter()
            .map(|(_, c, i)| (*c, *i, candidate(*c as usize, *i as usize)))
            .collect();
        for c in 0..channels {
            masks[c].par_iter_mut().for_each(|m| *m = false);
            values[c].par_iter_mut().for_each(|v| *v = 0.0);
        }
        for (c, i, v) in chosen {
            masks[c as usize][i as usize] = true;
            values[c as usize][i as usize] = v;
        }
        refit_all(values, masks, grads, p, work);
        let alive = survivors(values, masks, threshold);
        tracing::debug!(k, alive, "refinement round");
    }
    // Prune values that fell below the threshold and refit the rest, until nothing falls
    // below (at most `prune_refits` refits; a last prune without refit may follow).
    // Whether the gradient in `grads` is that of the final values (a last prune without refit
    // leaves it stale).
    let mut gradient_current = true;
    for pass in 0..=opts.prune_refits {
        let mut pruned = false;
        for c in 0..channels {
            let dropped: usize = values[c]
                .par_iter_mut()
                .zip(masks[c].par_iter_mut())
                .enumerate()
                .map(|(i, (v, m))| {
                    if *m && score_of(c, i, *v) < threshold {
                        *m = false;
                        *v = 0.0;
                        1
                    } else {
                        0
                    }
                })
                .sum();
            pruned |= dropped > 0;
        }
        if !pruned {
            break;
        }
        if pass == opts.prune_refits {
            gradient_current = false;
            break;
        }
        refit_all(values, masks, grads, p, work);
    }
    tracing::debug!(
        kept = k,
        transforms = op.applications.get(),
        seconds = started.elapsed().as_secs_f64(),
        "refinement"
    );
    // The set in score order. Its scores are at least the threshold (lower ones were pruned),
    // so none is negative and `all_sorted` leaves none out.
    let (values_now, masks_now) = (&*values, &*masks);
    let kept: Vec<KeptValue> = all_sorted(channels, n, &|c: usize, i: usize| {
        if masks_now[c][i] {
            score_of(c, i, values_now[c][i])
        } else {
            -1.0
        }
    })
    .into_par_iter()
    .map(|(_, channel, index)| KeptValue {
        channel,
        index,
        value: values_now[channel as usize][index as usize],
    })
    .collect();
    if extension == 0 || kept.is_empty() {
        return Refined {
            kept,
            extension: Vec::new(),
            first_survivors,
        };
    }
    if !gradient_current {
        for c in 0..channels {
            op.gradient(&targets[c], &values[c], &mut grads[c]);
        }
    }
    // Outside the set, scoring below its smallest score (so the set followed by the extension
    // stays in decreasing score order, which the encoder's quantizer threshold relies on).
    let floor = kept
        .last()
        .map(|s| score_of(s.channel as usize, s.index as usize, s.value))
        .unwrap_or(f64::INFINITY);
    let candidate = |c: usize, i: usize| grads[c][i] * op.inv_diag[band_of[i] as usize];
    let score = |c: usize, i: usize| {
        let v = candidate(c, i);
        if masks[c][i] || v == 0.0 || !v.is_finite() {
            return -1.0;
        }
        let s = score_of(c, i, v);
        if s < floor {
            s
        } else {
            -1.0
        }
    };
    let hist = histogram(channels, n, &score, None::<&fn(usize, usize) -> f64>);
    let extension = top_k(&hist, channels, n, extension, &score)
        .into_iter()
        .map(|(_, c, i)| KeptValue {
            channel: c,
            index: i,
            value: candidate(c as usize, i as usize),
        })
        .collect();
    Refined {
        kept,
        extension,
        first_survivors,
    }
}

/// `n` copies of `value`, written out rather than allocated zeroed. Zeroed allocations are
/// mapped lazily: a read before the first write maps the shared zero page, and the write then
/// costs a copy-on-write fault and a TLB shootdown across the pool's threads, per page. The
/// refinement's arrays are read before they are written (a search direction, a mask); on the
/// MNI grid those faults were ~8 % of a compression's samples. The pages are written by the
/// pool's threads together (each first write of a page is a fault the kernel serves).
pub(crate) fn written<T: Clone + Send + Sync>(n: usize, value: T) -> Vec<T> {
    let mut v = Vec::with_capacity(n);
    v.par_extend(rayon::iter::repeat_n(value, n));
    v
}

/// Dense grid-sized arrays kept from one refinement (or view comparison) to the next on the
/// same grid. A byte target runs a pilot refit, one to three refinements and a view comparison
/// per depth, each needing five to six arrays of the padded grid (51 MB each on the MNI
/// volume); freed in between, every one came back as fresh pages whose first writes were
/// kernel faults (~100 ms of one thread per refinement on the MNI volume).
#[derive(Debug, Default)]
pub(crate) struct Scratch {
    floats: std::sync::Mutex<Vec<Vec<f32>>>,
    flags: std::sync::Mutex<Vec<Vec<bool>>>,
}

impl Scratch {
    /// An array of `n` copies of `value`: a kept one of that length refilled, else a new one.
    pub(crate) fn floats(&self, n: usize, value: f32) -> Vec<f32> {
        Scratch::take(&self.floats, n, value)
    }

    /// [`Scratch::floats`] for flags.
    pub(crate) fn flags(&self, n: usize, value: bool) -> Vec<bool> {
        Scratch::take(&self.flags, n, value)
    }

    /// Keeps arrays for a later [`Scratch::floats`].
    pub(crate) fn keep_floats(&self, arrays: impl IntoIterator<Item = Vec<f32>>) {
        lock(&self.floats).extend(arrays);
    }

    /// Keeps arrays for a later [`Scratch::flags`].
    pub(crate) fn keep_flags(&self, arrays: impl IntoIterator<Item = Vec<bool>>) {
        lock(&self.flags).extend(arrays);
    }

    /// Drops every kept array.
    pub(crate) fn clear(&self) {
        lock(&self.floats).clear();
        lock(&self.flags).clear();
    }

    fn take<T: Copy + Send + Sync>(
        pool: &std::sync::Mutex<Vec<Vec<T>>>,
        n: usize,
        value: T,
    ) -> Vec<T> {
        let kept = {
            let mut pool = lock(pool);
            let at = pool.iter().position(|v| v.len() == n);
            at.map(|i| pool.swap_remove(i))
        };
        match kept {
            Some(mut v) => {
                v.par_iter_mut().for_each(|x| *x = value);
                v
            }
            None => written(n, value),
        }
    }
}

/// The refinement's dense arrays, taken from a [`Scratch`] and given back to it when dropped.
struct Arrays<'s> {
    scratch: &'s Scratch,
    /// Values per channel (zero outside the set).
    values: Vec<Vec<f32>>,
    /// The set per channel.
    masks: Vec<Vec<bool>>,
    /// The full gradient Rᵀ(f − R c) per channel.
    grads: Vec<Vec<f32>>,
    /// The search direction.
    p: Vec<f32>,
    /// Work array of the transforms.
    work: Vec<f32>,
}

impl<'s> Arrays<'s> {
    fn take(scratch: &'s Scratch, channels: usize, n: usize) -> Arrays<'s> {
        Arrays {
            scratch,
            values: (0..channels).map(|_| scratch.floats(n, 0.0)).collect(),
            masks: (0..channels).map(|_| scratch.flags(n, false)).collect(),
            grads: (0..channels).map(|_| scratch.floats(n, 0.0)).collect(),
            p: scratch.floats(n, 0.0),
            work: scratch.floats(n, 0.0),
        }
    }
}

impl Drop for Arrays<'_> {
    fn drop(&mut self) {
        let floats = std::mem::take(&mut self.values)
            .into_iter()
            .chain(std::mem::take(&mut self.grads))
            .chain([std::mem::take(&mut self.p), std::mem::take(&mut self.work)]);
        self.scratch.keep_floats(floats);
        self.scratch.keep_flags(std::mem::take(&mut self.masks));
    }
}

fn lock<T>(m: &std::sync::Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// Copies a channel into the zero-padded grid of `geometry`, in f32.
pub(crate) fn pad_f32(channel: &[f32], geometry: &Geometry) -> Vec<f32> {
    pad_channel_as(channel, geometry, |v| v)
}

fn sorted(
    score_of: &(dyn Fn(usize, usize, f32) -> f64 + Sync),
    list: Vec<KeptValue>,
) -> Vec<KeptValue> {
    let mut keyed: Vec<((f64, u8, u32), f32)> = list
        .into_iter()
        .map(|s| {
            let score = score_of(s.channel as usize, s.index as usize, s.value);
            ((score, s.channel, s.index), s.value)
        })
        .collect();
    keyed.par_sort_unstable_by(|a, b| pick_order(&a.0, &b.0));
    keyed
        .into_iter()
        .map(|((_, channel, index), value)| KeptValue {
            channel,
            index,
            value,
        })
        .collect()
}
