//! The exact analysis and the spline interpolation prefilter by recursive filters, in f64, on
//! panels of lines that move together.
//!
//! The analysis step inverts the synthesis' 2×2 polyphase matrix M = [[Pe, Qe], [Po, Qo]]:
//! M⁻¹ = adj(M) / det(M). The adjugate holds the primal filters' phases, a short FIR; the
//! determinant det = Pe·Qo − Qe·Po is a Laurent polynomial of the half-rate shift, symmetric
//! about its centre for the B-spline families (an Euler–Frobenius polynomial: linear's is the
//! cubic interpolation symbol, 1 + 4z⁻¹ + z⁻², up to a factor), whose roots come in pairs r,
//! 1/r on the negative real axis. So 1/det is a gain and, per root r inside the unit circle,
//! a causal and an anti-causal first-order recursion y[n] = x[n] + r·y[n ∓ 1]; on a periodic
//! line each starts from the exact periodic sum Σ_k r^k x[∓k] / (1 − r^N), cut where |r|^k
//! falls below f64's resolution. The cubic interpolation prefilter is the same all-pole
//! filter of its own symmetric FIR. What M⁻¹ computes is exactly what the FFT path of
//! [`super::Dwt1d`] computes per frequency (that path stays the reference; tests compare
//! both to rounding), at O(taps) per sample instead of O(log N).
//!
//! Lines are filtered as *panels*: a line's samples are rows, and each row holds that sample
//! of several lines (the x samples of a slab's rows for y and z, eight rows transposed for
//! x), so every operation is an axpy over a row that the compiler vectorizes, where one line
//! at a time would be a chain of dependent multiply–adds. Results do not depend on the thread
//! count: each panel is computed the same way whatever thread runs it.

use super::for_each_chunk;
use super::lanes::weighted_row_sum;
use crate::family::Family;
use multiversion::multiversion;

/// Below this, r^k no longer changes an f64 sum of samples of ordinary size (2⁻⁵⁶).
const TAIL: f64 = 1.4e-17;

/// x rows that one x-axis panel transposes together.
const X_LINES: usize = 32;

/// Samples of an output row that [`adjugate_rows`] sums over all its taps at once.
const LANES: usize = 8;

/// The most taps of one adjugate row (cubic's: 6 + 5).
const MAX_TAPS: usize = 16;

/// Columns of one y or z panel (its rows are this many samples of as many lines).
const STRIP: usize = 64;

/// 1 / (gain · Π_r (1 − r z⁻¹)(1 − r z)): the inverse of a symmetric Laurent polynomial whose
/// roots are real and off the unit circle.
#[derive(Debug, Clone)]
pub(crate) struct AllPole {
    /// The roots inside the unit circle.
    poles: Vec<f64>,
    /// The polynomial's value is `gain` · Π (1 − r z⁻¹)(1 − r z).
    gain: f64,
}

impl AllPole {
    /// The inverse of S(z) = Σ_{k=−K..K} `symmetric[K + k]` z^k, if its coefficients are
    /// symmetric and its roots real and off the unit circle (None otherwise: the caller keeps
    /// the FFT path).
    pub(crate) fn of_symmetric(symmetric: &[f64]) -> Option<AllPole> {
        let len = symmetric.len();
        if len.is_multiple_of(2) {
            return None;
        }
        let k = len / 2;
        let scale = symmetric.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        if scale == 0.0
            || (0..len).any(|i| (symmetric[i] - symmetric[len - 1 - i]).abs() > 1e-12 * scale)
        {
            return None;
        }
        if k == 0 {
            return Some(AllPole {
                poles: Vec::new(),
                gain: symmetric[0],
            });
        }
        // z^K·S(z) = Σ_j symmetric[j] z^j, a polynomial of degree 2K: its roots are the
        // eigenvalues of its companion matrix.
        let degree = 2 * k;
        let lead = symmetric[degree];
        let companion = nalgebra::DMatrix::from_fn(degree, degree, |row, col| {
            if row == 0 {
                -symmetric[degree - 1 - col] / lead
            } else if row == col + 1 {
                1.0
            } else {
                0.0
            }
        });
        let roots = companion.complex_eigenvalues();
        let value = |z: f64| symmetric.iter().rev().fold(0.0, |acc, c| acc * z + c);
        let slope = |z: f64| {
            symmetric
                .iter()
                .enumerate()
                .skip(1)
                .rev()
                .fold(0.0, |acc, (j, c)| acc * z + j as f64 * c)
        };
        let mut poles = Vec::with_capacity(k);
        for root in roots.iter() {
            if root.im.abs() > 1e-9 * root.norm().max(1.0) {
                return None;
            }
            if root.re.abs() < 1.0 - 1e-9 {
                // Newton's polish in f64 on the polynomial itself.
                let mut z = root.re;
                for _ in 0..4 {
                    let d = slope(z);
                    if d == 0.0 {
                        break;
                    }
                    z -= value(z) / d;
                }
                poles.push(z);
            }
        }
        if poles.len() != k {
            return None;
        }
        poles.sort_by(|a, b| b.abs().total_cmp(&a.abs()));
        let gain = lead * poles.iter().map(|r| -1.0 / r).product::<f64>();
        let all_pole = AllPole { poles, gain };
        // The factored form must give back every coefficient.
        let mut expanded = vec![gain];
        for r in &all_pole.poles {
            // × (1 − r z⁻¹)(1 − r z) = −r z⁻¹ + (1 + r²) − r z, coefficients from z^-m up.
            let mut next = vec![0.0; expanded.len() + 2];
            for (i, c) in expanded.iter().enumerate() {
                next[i] += -r * c;
                next[i + 1] += (1.0 + r * r) * c;
                next[i + 2] += -r * c;
            }
            expanded = next;
        }
        let close = expanded
            .iter()
            .zip(symmetric)
            .all(|(a, b)| (a - b).abs() <= 1e-10 * scale);
        close.then_some(all_pole)
    }

    /// The polynomial's constant factor.
    pub(crate) fn gain(&self) -> f64 {
        self.gain
    }

    /// Applies Π_r 1 / ((1 − r z⁻¹)(1 − r z)) (not the gain) along the rows of `panel` (`len`
    /// rows of `width` samples, periodic), in place; `row` is one row of scratch.
    fn apply(&self, panel: &mut [f64], width: usize, row: &mut Vec<f64>) {
        let len = panel.len() / width;
        for &r in &self.poles {
            recursion_pair(panel, width, len, r, row);
        }
        debug_assert_eq!(panel.len(), len * width);
    }
}

/// Terms of the periodic start of a recursion with pole `r` on a line of `len` samples: the
/// whole period where r^len still counts, else until |r|^k < [`TAIL`].
fn start_terms(r: f64, len: usize) -> usize {
    let a = r.abs();
    if a < TAIL {
        return 1;
    }
    let cut = (TAIL.ln() / a.ln()).ceil() as usize;
    cut.clamp(1, len)
}

/// The causal then the anti-causal recursion of one pole along the rows of a periodic panel.
#[multiversion(targets("x86_64+avx2"))]
fn recursion_pair(panel: &mut [f64], width: usize, len: usize, r: f64, start: &mut Vec<f64>) {
    let terms = start_terms(r, len);
    // Σ_{k ≥ 0} r^k x[n − k·s] over the infinite periodic extension folds to the first `len`
    // terms times 1 / (1 − r^len); with fewer terms r^len is below the resolution.
    let fold = if terms == len {
        1.0 / (1.0 - r.powi(len as i32))
    } else {
        1.0
    };
    // Causal: y[0] = Σ_k r^k x[−k].
    periodic_start(panel, width, r, terms, fold, |k| (len - k) % len, start);
    panel[..width].copy_from_slice(start);
    for n in 1..len {
        let (before, rest) = panel.split_at_mut(n * width);
        let prev = &before[(n - 1) * width..];
        for (y, p) in rest[..width].iter_mut().zip(prev) {
            *y += r * p;
        }
    }
    // Anti-causal: y[len − 1] = Σ_k r^k x[len − 1 + k].
    periodic_start(panel, width, r, terms, fold, |k| (len - 1 + k) % len, start);
    panel[(len - 1) * width..].copy_from_slice(start);
    for n in (0..len - 1).rev() {
        let (head, after) = panel.split_at_mut((n + 1) * width);
        let next = &after[..width];
        for (y, p) in head[n * width..].iter_mut().zip(next) {
            *y += r * p;
        }
    }
}

/// `start` ← fold · Σ_{k < terms} r^k · (panel row `row_of(k)`): a recursion's periodic
/// start, row by row of `width` samples. Inlined into [`recursion_pair`].
#[inline(always)]
fn periodic_start(
    panel: &[f64],
    width: usize,
    r: f64,
    terms: usize,
    fold: f64,
    row_of: impl Fn(usize) -> usize,
    start: &mut Vec<f64>,
) {
    start.clear();
    start.resize(width, 0.0);
    let mut w = fold;
    for k in 0..terms {
        let src = row_of(k);
        for (s, v) in start.iter_mut().zip(&panel[src * width..(src + 1) * width]) {
            *s += w * v;
        }
        w *= r;
    }
}

/// One output row of the adjugate FIR: Σ over `taps` of weight · the input row of that phase
/// at `(k + offset) mod h`.
#[derive(Debug, Clone, Copy)]
struct Tap {
    /// 0: the even samples (E); 1: the odd samples (O).
    phase: usize,
    /// The input index is `k + offset` (mod the half length).
    offset: isize,
    weight: f64,
}

/// The recursive analysis of one family (see the module's doc).
#[derive(Debug, Clone)]
pub struct RecursiveAnalysis {
    /// Taps of the scaling half and of the wavelet half (the adjugate's rows, divided by the
    /// determinant's gain and advanced by its centre).
    scaling: Vec<Tap>,
    wavelet: Vec<Tap>,
    det: AllPole,
}

/// Per-thread buffers of the panel kernels.
#[derive(Debug, Default)]
pub(crate) struct PanelScratch {
    panel: Vec<f64>,
    out: Vec<f64>,
    row: Vec<f64>,
}

impl RecursiveAnalysis {
    /// The analysis for the filters `p` (φ) and `q` (ψ), or None where the determinant is not
    /// of the symmetric, real-rooted kind (then the FFT path applies).
    pub fn new(p: &[f64], q: &[f64]) -> Option<RecursiveAnalysis> {
        let phase =
            |f: &[f64], e: usize| -> Vec<f64> { f.iter().skip(e).step_by(2).copied().collect() };
        let (pe, po, qe, qo) = (phase(p, 0), phase(p, 1), phase(q, 0), phase(q, 1));
        let product = |a: &[f64], b: &[f64]| {
            let mut out = vec![0.0; a.len() + b.len() - 1];
            for (i, x) in a.iter().enumerate() {
                for (j, y) in b.iter().enumerate() {
                    out[i + j] += x * y;
                }
            }
            out
        };
        let (a, b) = (product(&pe, &qo), product(&qe, &po));
        let mut det = vec![0.0; a.len().max(b.len())];
        for (i, v) in a.iter().enumerate() {
            det[i] += v;
        }
        for (i, v) in b.iter().enumerate() {
            det[i] -= v;
        }
        // det(z) = Σ_j det[j] z^−j = z^−centre · S(z), S symmetric.
        let scale = det.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let first = det.iter().position(|v| v.abs() > 1e-14 * scale)?;
        let last = det.iter().rposition(|v| v.abs() > 1e-14 * scale)?;
        let symmetric = &det[first..=last];
        let all_pole = AllPole::of_symmetric(symmetric)?;
        let centre = (first + symmetric.len() / 2) as isize;
        let g = all_pole.gain();
        // Scaling = (Qo·E − Qe·O) / det, wavelet = (−Po·E + Pe·O) / det; (F·x)[k] =
        // Σ_i f[i] x[k − i], and dividing by z^−centre reads index k + centre.
        let taps = |even: &[f64], even_sign: f64, odd: &[f64], odd_sign: f64| -> Vec<Tap> {
            let mut list = Vec::new();
            for (i, w) in even.iter().enumerate() {
                list.push(Tap {
                    phase: 0,
                    offset: centre - i as isize,
                    weight: even_sign * w / g,
                });
            }
            for (i, w) in odd.iter().enumerate() {
                list.push(Tap {
                    phase: 1,
                    offset: centre - i as isize,
                    weight: odd_sign * w / g,
                });
            }
            list.retain(|t| t.weight != 0.0);
            list
        };
        let (scaling, wavelet) = (taps(&qo, 1.0, &qe, -1.0), taps(&po, -1.0, &pe, 1.0));
        (scaling.len() <= MAX_TAPS && wavelet.len() <= MAX_TAPS).then_some(RecursiveAnalysis {
            scaling,
            wavelet,
            det: all_pole,
        })
    }

    /// The analysis of `family`'s filters.
    pub fn of(family: Family) -> Option<RecursiveAnalysis> {
        RecursiveAnalysis::new(&family.scaling_filter(), &family.wavelet_filter())
    }

    /// One analysis step of every line of a panel: `len` rows (`len` even) of `width`
    /// samples, row t at `src[t * stride..]`. The result goes to `out` (`len` contiguous rows
    /// of `width`): rows 0..len/2 the scaling coefficients, the rest the wavelet ones.
    fn analyze_panel(
        &self,
        src: &[f64],
        stride: usize,
        len: usize,
        width: usize,
        out: &mut Vec<f64>,
        row: &mut Vec<f64>,
    ) {
        let h = len / 2;
        out.resize(len * width, 0.0);
        let (scaling, wavelet) = out.split_at_mut(h * width);
        adjugate_rows(src, stride, width, h, &self.scaling, scaling);
        adjugate_rows(src, stride, width, h, &self.wavelet, wavelet);
        self.det.apply(scaling, width, row);
        self.det.apply(wavelet, width, row);
    }

    /// One analysis step of one line (even length), in place: `[scaling | wavelet]`.
    pub fn analyze_line(&self, line: &mut [f64]) {
        let (mut out, mut row) = (Vec::new(), Vec::new());
        self.analyze_panel(line, 1, line.len(), 1, &mut out, &mut row);
        line.copy_from_slice(&out);
    }
}

/// out row k ← Σ_taps weight · input row (2·((k + offset) mod h) + phase), for k < h; input
/// row t is `width` samples at `src[t * stride..]`. Each output row is summed over its taps
/// [`LANES`] samples at a time in registers and stored once; the terms are added in tap
/// order from zero, whatever the width, so a line gives the same bits alone or in a panel.
#[multiversion(targets("x86_64+avx2"))]
fn adjugate_rows(
    src: &[f64],
    stride: usize,
    width: usize,
    h: usize,
    taps: &[Tap],
    out: &mut [f64],
) {
    let hi = h as isize;
    let mut starts = [0usize; MAX_TAPS];
    let starts = &mut starts[..taps.len()];
    for (k, dst) in out.chunks_exact_mut(width).enumerate() {
        for (start, tap) in starts.iter_mut().zip(taps) {
            let m = (k as isize + tap.offset).rem_euclid(hi) as usize;
            *start = (2 * m + tap.phase) * stride;
        }
        weighted_row_sum::<_, _, LANES>(dst, || {
            starts
                .iter()
                .zip(taps)
                .map(|(start, tap)| (&src[*start..], tap.weight))
        });
    }
}

/// The operation [`for_each_panel`] applies: `op(src, stride, len, width, scratch)` filters
/// `len` rows of `width` samples, row t at `src[t * stride..]`, into `scratch.out`.
type PanelOp<'a> = dyn Fn(&[f64], usize, usize, usize, &mut PanelScratch) + Sync + 'a;

/// Applies `op` to every line along `axis` of the block `block` (a corner of the array of
/// dimensions `full`, x fastest), as panels, and puts each result back where its lines lie:
/// - x lines: [`X_LINES`] rows of a slab transposed into one panel, the result transposed
///   back;
/// - y lines: a [`STRIP`]-wide column strip of one slab's block, read in place;
/// - z lines: per y row, a strip gathered across the slabs and its result written back.
fn for_each_panel(
    data: &mut [f64],
    full: [usize; 3],
    block: [usize; 3],
    axis: usize,
    op: &PanelOp,
) {
    let len = block[axis];
    let (row, plane) = (full[0], full[0] * full[1]);
    let width = block[0];
    match axis {
        0 => for_each_chunk(
            data,
            plane,
            block[2],
            PanelScratch::default,
            |s, _, slab| {
                let mut panel = std::mem::take(&mut s.panel);
                let mut y0 = 0;
                while y0 < block[1] {
                    let lines = X_LINES.min(block[1] - y0);
                    panel.resize(len * lines, 0.0);
                    let rows = &mut slab[y0 * row..];
                    transpose_rows_into_panel(rows, row, len, lines, &mut panel);
                    op(&panel, lines, len, lines, s);
                    transpose_panel_into_rows(&s.out, len, lines, rows, row);
                    y0 += lines;
                }
                s.panel = panel;
            },
        ),
        1 => for_each_chunk(
            data,
            plane,
            block[2],
            PanelScratch::default,
            |s, _, slab| {
                let mut x0 = 0;
                while x0 < width {
                    let w = STRIP.min(width - x0);
                    op(&slab[x0..], row, len, w, s);
                    for y in 0..len {
                        slab[y * row + x0..y * row + x0 + w]
                            .copy_from_slice(&s.out[y * w..(y + 1) * w]);
                    }
                    x0 += w;
                }
            },
        ),
        _ => {
            // Each y row's z lines form a panel (z rows of x samples, one plane apart) that
            // depends on nothing else: as `len` disjoint row borrows, one per plane, filtered
            // strip by strip and written straight back.
            let mut panels: Vec<Vec<&mut [f64]>> =
                (0..block[1]).map(|_| Vec::with_capacity(len)).collect();
            for slab in data.chunks_mut(plane).take(len) {
                for (panel, row) in panels.iter_mut().zip(slab.chunks_mut(row)) {
                    panel.push(&mut row[..width]);
                }
            }
            for_each_chunk(
                &mut panels,
                1,
                block[1],
                PanelScratch::default,
                |s, _, panel| {
                    let rows = &mut panel[0];
                    let mut input = std::mem::take(&mut s.panel);
                    let mut x0 = 0;
                    while x0 < width {
                        let w = STRIP.min(width - x0);
                        // The strip gathered first: row copies stream from memory, where the
                        // taps' reads of several planes at once stall on each first touch.
                        input.clear();
                        for r in rows.iter() {
                            input.extend_from_slice(&r[x0..x0 + w]);
                        }
                        op(&input, w, len, w, s);
                        for (r, o) in rows.iter_mut().zip(s.out.chunks_exact(w)) {
                            r[x0..x0 + w].copy_from_slice(o);
                        }
                        x0 += w;
                    }
                    s.panel = input;
                },
            );
        }
    }
}

/// Samples of a line that one step of the x panels' transposes moves for every line at once:
/// the panel rows it writes (or reads) then stay in L1 together, where a whole line at a time
/// strides across the panel and touches a new cache line per sample.
const TRANSPOSE_TILE: usize = 8;

/// `panel[n · lines + j] = rows[j · row + n]` for the first `len` samples of `lines` rows
/// `row` apart: x lines as the rows of a panel, tile by tile.
fn transpose_rows_into_panel(
    rows: &[f64],
    row: usize,
    len: usize,
    lines: usize,
    panel: &mut [f64],
) {
    for n0 in (0..len).step_by(TRANSPOSE_TILE) {
        let n1 = (n0 + TRANSPOSE_TILE).min(len);
        let tile = &mut panel[n0 * lines..n1 * lines];
        for j in 0..lines {
            let line = &rows[j * row + n0..j * row + n1];
            for (k, v) in line.iter().enumerate() {
                tile[k * lines + j] = *v;
            }
        }
    }
}

/// The inverse of [`transpose_rows_into_panel`]: `rows[j · row + n] = panel[n · lines + j]`.
fn transpose_panel_into_rows(
    panel: &[f64],
    len: usize,
    lines: usize,
    rows: &mut [f64],
    row: usize,
) {
    for n0 in (0..len).step_by(TRANSPOSE_TILE) {
        let n1 = (n0 + TRANSPOSE_TILE).min(len);
        let tile = &panel[n0 * lines..n1 * lines];
        for j in 0..lines {
            let line = &mut rows[j * row + n0..j * row + n1];
            for (k, v) in line.iter_mut().enumerate() {
                *v = tile[k * lines + j];
            }
        }
    }
}

/// Forward 3D non-standard transform by recursive filters, in place (Mallat layout); the same
/// result as the FFT path to rounding.
pub(crate) fn forward_3d(
    data: &mut [f64],
    full: [usize; 3],
    levels: usize,
    analysis: &RecursiveAnalysis,
) {
    let op = |src: &[f64], stride: usize, len: usize, width: usize, s: &mut PanelScratch| {
        analysis.analyze_panel(src, stride, len, width, &mut s.out, &mut s.row)
    };
    for level in 1..=levels {
        let block = [
            full[0] >> (level - 1),
            full[1] >> (level - 1),
            full[2] >> (level - 1),
        ];
        for axis in 0..3 {
            for_each_panel(data, full, block, axis, &op);
        }
    }
}

/// The periodic interpolation prefilter along every axis by the all-pole inverse of the
/// sampling FIR `taps` (centred, symmetric), in place.
pub(crate) fn prefilter_3d(data: &mut [f64], full: [usize; 3], filter: &AllPole) {
    let inverse_gain = 1.0 / filter.gain();
    let op = |src: &[f64], stride: usize, len: usize, width: usize, s: &mut PanelScratch| {
        s.out.clear();
        for t in 0..len {
            s.out.extend(
                src[t * stride..t * stride + width]
                    .iter()
                    .map(|v| v * inverse_gain),
            );
        }
        filter.apply(&mut s.out, width, &mut s.row);
    };
    for axis in 0..3 {
        for_each_panel(data, full, full, axis, &op);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dwt::{Dwt1d, LineScratch};
    use rand::{Rng, SeedableRng};

    #[test]
    fn every_family_s_determinant_factors_into_real_poles() {
        for family in Family::ALL {
            let analysis = RecursiveAnalysis::of(family).expect("a recursive analysis");
            let expected = match family {
                Family::Haar => 0,
                Family::Linear => 1,
                Family::Cubic => 3,
            };
            assert_eq!(analysis.det.poles.len(), expected, "{family}");
            for r in &analysis.det.poles {
                assert!(*r < 0.0 && *r > -1.0, "{family}: pole {r}");
            }
        }
        // Linear's determinant is −(z + 4 + z⁻¹)/3: the pole is √3 − 2.
        let linear = RecursiveAnalysis::of(Family::Linear).unwrap();
        assert!((linear.det.poles[0] - (3f64.sqrt() - 2.0)).abs() < 1e-15);
    }

    #[test]
    fn a_polynomial_that_is_not_symmetric_or_has_complex_roots_is_refused() {
        assert!(AllPole::of_symmetric(&[1.0, 2.0]).is_none());
        assert!(AllPole::of_symmetric(&[1.0, 4.0, 2.0]).is_none());
        // z + 1 + z⁻¹ has its roots on the unit circle (complex): no stable recursion.
        assert!(AllPole::of_symmetric(&[1.0, 1.0, 1.0]).is_none());
        assert!(AllPole::of_symmetric(&[0.0, 0.0, 0.0]).is_none());
        assert!(AllPole::of_symmetric(&[2.5]).is_some());
    }

    /// Every line length from 2 up, every family: the recursive step equals the FFT step.
    #[test]
    fn one_line_equals_the_fft_analysis() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(17);
        for family in Family::ALL {
            let analysis = RecursiveAnalysis::of(family).unwrap();
            let mut fft = Dwt1d::new(family);
            for n in (2..=80).step_by(2).chain([128, 224, 258, 512]) {
                fft.plan(n);
                let x: Vec<f64> = (0..n).map(|_| rng.gen_range(-1.0..1.0)).collect();
                let mut want = x.clone();
                fft.analyze(&mut want, &mut LineScratch::default());
                let mut got = x.clone();
                analysis.analyze_line(&mut got);
                let err = got
                    .iter()
                    .zip(&want)
                    .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
                assert!(err < 1e-12, "{family} n={n}: max error {err}");
            }
        }
    }

    /// The x panels' transposes put every sample of the lines where the panel wants it and
    /// back, whatever the line length against the tile.
    #[test]
    fn the_tiled_transposes_move_each_sample_once_and_invert_each_other() {
        // Lengths below, at and across the tile, rows longer than the lines (a block's corner).
        for (len, lines, row) in [
            (1, 1, 1),
            (7, 3, 9),
            (8, 32, 8),
            (13, 5, 20),
            (197, 32, 197),
        ] {
            let rows: Vec<f64> = (0..lines * row).map(|i| i as f64).collect();
            let mut panel = vec![f64::NAN; len * lines];
            transpose_rows_into_panel(&rows, row, len, lines, &mut panel);
            for n in 0..len {
                for j in 0..lines {
                    assert_eq!(
                        panel[n * lines + j],
                        rows[j * row + n],
                        "{len} {lines} {row}"
                    );
                }
            }
            let mut back = vec![-1.0; lines * row];
            transpose_panel_into_rows(&panel, len, lines, &mut back, row);
            for (i, v) in back.iter().enumerate() {
                let expected = if i % row < len { rows[i] } else { -1.0 };
                assert_eq!(*v, expected, "{len} {lines} {row}: sample {i}");
            }
        }
    }

    /// Panels of several widths give each of their lines what one line alone gives.
    #[test]
    fn a_panel_filters_each_of_its_lines_alone() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(19);
        let analysis = RecursiveAnalysis::of(Family::Cubic).unwrap();
        for (len, width) in [(2usize, 3usize), (6, 1), (10, 5), (64, 17)] {
            let panel: Vec<f64> = (0..len * width).map(|_| rng.gen_range(-1.0..1.0)).collect();
            let (mut together, mut row) = (Vec::new(), Vec::new());
            analysis.analyze_panel(&panel, width, len, width, &mut together, &mut row);
            for x in 0..width {
                let mut line: Vec<f64> = (0..len).map(|n| panel[n * width + x]).collect();
                analysis.analyze_line(&mut line);
                for n in 0..len {
                    assert_eq!(line[n], together[n * width + x], "len {len} width {width}");
                }
            }
        }
    }
}
