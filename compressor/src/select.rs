//! Picking the most significant coefficients without sorting them all: this module owns the
//! per-coefficient band map and the exact top-K selection the oracle and the refinement use.
//!
//! A volume of 512³ voxels has ~150 M coefficients per channel, of which a byte target keeps a
//! few hundred thousand. Sorting every (score, channel, index) triple would cost 24 bytes and a
//! full sort per coefficient; instead one parallel pass builds a histogram of the scores over
//! the high bits of their f32 representation (monotone in the score), the bin where the top K
//! end is found from the counts, and a second pass collects only the coefficients at or above
//! that bin, which are then sorted. The result is exactly the top K under the total order
//! (score descending, then channel, then index), so it does not depend on the thread count.

use rayon::prelude::*;
use wavesplat_codec::layout::Geometry;

/// Coefficients per parallel work item (fixed, so that sums do not depend on the thread count).
pub(crate) const CHUNK: usize = 1 << 16;

/// Histogram bins: the top 16 bits of a positive f32 (sign bit clear).
const BINS: usize = 1 << 16;

/// The band index ([`Geometry::bands`] order) of every coefficient of one channel, one byte each.
pub(crate) fn band_map(geometry: &Geometry) -> Vec<u8> {
    let m = geometry.levels;
    let p = geometry.padded;
    // Per axis and coordinate: the finest level whose upper half holds it (M + 1: none).
    let axis_level: Vec<Vec<u8>> = (0..3)
        .map(|a| {
            (0..p[a])
                .map(|c| {
                    (1..=m)
                        .find(|l| c >= p[a] >> l)
                        .map_or(m as u8 + 1, |l| l as u8)
                })
                .collect()
        })
        .collect();
    let plane = p[0] * p[1];
    let mut out = vec![0u8; geometry.coefficient_count()];
    out.par_chunks_mut(plane).enumerate().for_each(|(z, s)| {
        let lz = axis_level[2][z];
        for y in 0..p[1] {
            let ly = axis_level[1][y];
            for x in 0..p[0] {
                let lx = axis_level[0][x];
                let level = lx.min(ly).min(lz);
                s[x + p[0] * y] = if level as usize > m {
                    0
                } else {
                    let kind = ((lx == level) as usize) << 2
                        | ((ly == level) as usize) << 1
                        | (lz == level) as usize;
                    (1 + (m - level as usize) * 7 + kind - 1) as u8
                };
            }
        }
    });
    out
}

/// `len` zeros, written before anything reads them: a zeroed allocation (`vec![0; n]`,
/// calloc) maps the kernel's zero page on the first read, and the first write to each of its
/// pages then copies it and flushes the other threads' TLBs (a third of a small volume's
/// scoring time went to those interrupts, for the accumulators below). The zero is opaque to
/// the compiler, which would otherwise turn a fill with zeros back into a zeroed allocation.
/// (`crate::refine::written` does the same for grid-sized arrays, writing in parallel.)
fn written_zeros<T: Copy + Default>(len: usize) -> Vec<T> {
    let mut v = Vec::with_capacity(len);
    v.resize(len, std::hint::black_box(T::default()));
    v
}

/// The scores a selection ranks: `score(c, i)` of coefficient `i` of channel `c` (negative:
/// never selected). Any `Fn(usize, usize) -> f64` is one; a scorer that finds a coefficient's
/// position from its index can walk a run of them instead ([`Scores::for_each`]).
pub(crate) trait Scores: Sync {
    /// The score of coefficient `i` of channel `c`.
    fn score(&self, c: usize, i: usize) -> f64;

    /// `f(i, self.score(c, i))` for every `i` of `range`, in order, with the same scores.
    #[inline]
    fn for_each(&self, c: usize, range: std::ops::Range<usize>, mut f: impl FnMut(usize, f64)) {
        for i in range {
            f(i, self.score(c, i));
        }
    }
}

impl<F: Fn(usize, usize) -> f64 + Sync> Scores for F {
    #[inline]
    fn score(&self, c: usize, i: usize) -> f64 {
        self(c, i)
    }
}

/// A selected coefficient: score, channel, index.
pub(crate) type Pick = (f64, u8, u32);

/// The total order of picks: score descending, then channel, then index.
pub(crate) fn pick_order(a: &Pick, b: &Pick) -> std::cmp::Ordering {
    b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)).then(a.2.cmp(&b.2))
}

fn bin(score: f64) -> usize {
    // Scores are ≥ 0 here (+0.0 has bits 0); the bits of a non-negative f32 grow with it.
    ((score as f32).to_bits() >> 15) as usize
}

/// Counts (and sums of `energy`) per score bin over every selectable coefficient.
/// Counts are exact; the per-bin energies are summed in a thread-dependent order and only guide
/// how many coefficients to collect ([`Histogram::count_for_energy`]).
pub(crate) struct Histogram {
    counts: Vec<u64>,
    energies: Vec<f64>,
    /// Selectable coefficients (score ≥ 0).
    pub positive: u64,
    /// The `energy` of the selectable coefficients (0 without `energy`), summed exactly as
    /// the encoder's total: in fixed chunks, in chunk order (thread-count independent).
    pub selected_energy: f64,
}

/// One pass over `n` coefficients of each of `channels` channels: `score(c, i)` (negative:
/// never selected, e.g. a zero coefficient) and, when given, `energy(c, i)` (without it the
/// per-bin energies stay empty and [`Histogram::count_for_energy`] must not be asked). Generic
/// rather than `dyn`, so that the closures are inlined into the pass over every coefficient.
pub(crate) fn histogram<S, E>(channels: usize, n: usize, score: &S, energy: Option<&E>) -> Histogram
where
    S: Scores,
    E: Fn(usize, usize) -> f64 + Sync,
{
    let chunks = n.div_ceil(CHUNK);
    let jobs = channels * chunks;
    let energy_bins = if energy.is_some() { BINS } else { 0 };
    // One or two accumulators per thread, not one per chunk: each is 0.5 MB of counts (and as
    // much of energies), and on a small volume making and merging them was most of the pass;
    // each written before it is read ([`written_zeros`]).
    let min_len = (jobs / (2 * rayon::current_num_threads())).max(1);
    let zeroed = || (written_zeros(BINS), written_zeros(energy_bins), Vec::new());
    // Each job's energy sum is kept with its job number, so that the total is summed in job
    // order whatever thread summed each job.
    let (counts, energies, mut job_energies) = (0..jobs)
        .into_par_iter()
        .with_min_len(min_len)
        .fold(
            zeroed,
            |(mut counts, mut energies, mut job_energies), job| {
                let (c, chunk) = (job / chunks, job % chunks);
                let range = chunk * CHUNK..((chunk + 1) * CHUNK).min(n);
                let mut job_energy = 0.0f64;
                score.for_each(c, range, |i, s| {
                    if s >= 0.0 {
                        let b = bin(s);
                        counts[b] += 1;
                        if let Some(energy) = energy {
                            let e = energy(c, i);
                            energies[b] += e;
                            job_energy += e;
                        }
                    }
                });
                if energy.is_some() {
                    job_energies.push((job, job_energy));
                }
                (counts, energies, job_energies)
            },
        )
        .reduce(zeroed, |(mut c1, mut e1, mut j1), (c2, e2, j2)| {
            for (a, b) in c1.iter_mut().zip(&c2) {
                *a += b;
            }
            for (a, b) in e1.iter_mut().zip(&e2) {
                *a += b;
            }
            j1.extend(j2);
            (c1, e1, j1)
        });
    job_energies.sort_unstable_by_key(|(job, _)| *job);
    let positive = counts.iter().sum();
    Histogram {
        counts,
        energies,
        positive,
        selected_energy: job_energies.iter().map(|(_, e)| e).sum(),
    }
}

impl Histogram {
    /// A histogram of nothing.
    pub(crate) fn empty() -> Histogram {
        Histogram {
            counts: vec![0; BINS],
            energies: vec![0.0; BINS],
            positive: 0,
            selected_energy: 0.0,
        }
    }

    /// A histogram that holds no bins at all (for a prepared volume whose scores are spent,
    /// [`crate::encode::KeptTop`]): only its totals may be read.
    pub(crate) fn none() -> Histogram {
        Histogram {
            counts: Vec::new(),
            energies: Vec::new(),
            positive: 0,
            selected_energy: 0.0,
        }
    }

    /// Bins in all.
    pub(crate) const BINS: usize = BINS;

    /// Coefficients per score bin.
    pub(crate) fn counts(&self) -> &[u64] {
        &self.counts
    }

    /// Energy per score bin (approximate sums; empty when none were asked for).
    pub(crate) fn energies(&self) -> &[f64] {
        &self.energies
    }

    /// Adds `count` coefficients of total energy `energy` to bin `b` (an energy is dropped
    /// when the histogram keeps none).
    pub(crate) fn add_to_bin(&mut self, b: usize, count: u64, energy: f64) {
        self.counts[b] = self.counts[b].saturating_add(count);
        if let Some(e) = self.energies.get_mut(b) {
            *e += energy;
        }
    }

    /// The lowest bin that must be collected for the top `k`.
    pub(crate) fn cut_for_count(&self, k: u64) -> usize {
        let mut acc = 0u64;
        for b in (0..BINS).rev() {
            acc += self.counts[b];
            if acc >= k {
                return b;
            }
        }
        0
    }

    /// The number of coefficients to collect so that the top ones reach `goal` energy: down to
    /// the bin where the energy accumulated from the top reaches it, and one occupied bin more
    /// (the per-bin sums are approximate).
    pub(crate) fn count_for_energy(&self, goal: f64) -> u64 {
        let (mut acc, mut count) = (0.0, 0u64);
        let mut reached = false;
        for b in (0..BINS).rev() {
            if reached && self.counts[b] > 0 {
                return count + self.counts[b];
            }
            // A histogram without energies collects everything.
            acc += self.energies.get(b).copied().unwrap_or(0.0);
            count += self.counts[b];
            reached |= acc >= goal * (1.0 - 1e-9);
        }
        count
    }
}

/// The top `k` selectable coefficients (score ≥ 0), sorted by [`pick_order`] (fewer when fewer
/// are selectable). `hist` must come from [`histogram`] with the same `score`.
pub(crate) fn top_k<S>(
    hist: &Histogram,
    channels: usize,
    n: usize,
    k: usize,
    score: &S,
) -> Vec<Pick>
where
    S: Scores,
{
    if k == 0 {
        return Vec::new();
    }
    let cut = hist.cut_for_count(k as u64);
    let parts = collect_from(channels, n, cut, usize::MAX, score).0;
    best_of(parts, k)
}

/// Every selectable coefficient whose score bin is at least `floor_bin`, per chunk, and how
/// many there are. Once more than `limit` are collected the remaining chunks collect nothing
/// (the count then exceeds `limit`).
fn collect_from<S>(
    channels: usize,
    n: usize,
    floor_bin: usize,
    limit: usize,
    score: &S,
) -> (Vec<Vec<Pick>>, usize)
where
    S: Scores,
{
    use std::sync::atomic::{AtomicUsize, Ordering};
    let collected = AtomicUsize::new(0);
    let chunks = n.div_ceil(CHUNK);
    let parts: Vec<Vec<Pick>> = (0..channels * chunks)
        .into_par_iter()
        .map(|job| {
            if collected.load(Ordering::Relaxed) > limit {
                return Vec::new();
            }
            let (c, chunk) = (job / chunks, job % chunks);
            let mut out = Vec::new();
            score.for_each(c, chunk * CHUNK..((chunk + 1) * CHUNK).min(n), |i, s| {
                if s >= 0.0 && bin(s) >= floor_bin {
                    out.push((s, c as u8, i as u32));
                }
            });
            collected.fetch_add(out.len(), Ordering::Relaxed);
            out
        })
        .collect();
    (parts, collected.into_inner())
}

/// The top `k` of the collected `parts`, sorted by [`pick_order`]: a counting sort by score bin
/// (descending), then each bin sorted on its own as far as the top `k` reach. A score's bin
/// never falls as the score grows, so bins in descending order, each in [`pick_order`], are
/// the picks in [`pick_order`]. A byte target collects a few million candidates; one
/// comparison sort of them all was half of a high-rate compression's scoring.
fn best_of(parts: Vec<Vec<Pick>>, k: usize) -> Vec<Pick> {
    let total: usize = parts.iter().map(Vec::len).sum();
    let zeroed = || written_zeros::<usize>(BINS);
    let counts = parts
        .par_iter()
        .fold(zeroed, |mut counts, part| {
            for p in part {
                counts[bin(p.0)] += 1;
            }
            counts
        })
        .reduce(zeroed, |mut a, b| {
            for (a, b) in a.iter_mut().zip(&b) {
                *a += b;
            }
            a
        });
    let (Some(lowest), Some(highest)) = (
        counts.iter().position(|&c| c > 0),
        counts.iter().rposition(|&c| c > 0),
    ) else {
        return Vec::new();
    };
    // Slot j holds bin `highest - j`; `starts[j]` is where its picks begin, `starts[slots]`
    // is `total`.
    let slots = highest - lowest + 1;
    let mut starts = vec![0usize; slots + 1];
    for j in 0..slots {
        starts[j + 1] = starts[j] + counts[highest - j];
    }
    // Scattered by ranges of slots of about equal counts, one task each: every task reads
    // all the picks and writes its own part of the output.
    let mut picks: Vec<Pick> = vec![(0.0, 0, 0); total];
    let tasks = rayon::current_num_threads().clamp(1, slots);
    let mut bounds: Vec<usize> = (0..=tasks)
        .map(|t| starts.partition_point(|&s| s < total * t / tasks))
        .collect();
    bounds[tasks] = slots;
    bounds.dedup();
    let mut ranges: Vec<(usize, usize, &mut [Pick])> = Vec::with_capacity(bounds.len());
    let mut rest = &mut picks[..];
    for w in bounds.windows(2) {
        let (head, tail) = rest.split_at_mut(starts[w[1]] - starts[w[0]]);
        ranges.push((w[0], w[1], head));
        rest = tail;
    }
    ranges.into_par_iter().for_each(|(from, to, out)| {
        let base = starts[from];
        let mut next: Vec<usize> = starts[from..to].iter().map(|s| s - base).collect();
        for p in parts.iter().flatten() {
            let j = highest - bin(p.0);
            if (from..to).contains(&j) {
                out[next[j - from]] = *p;
                next[j - from] += 1;
            }
        }
    });
    drop(parts);
    // The bins the top `k` reach, each sorted (the last one whole, then cut). `starts` begins
    // at 0 and ends at `total`, so `reach` is a slot boundary.
    let reach = starts.partition_point(|&s| s < k.min(total));
    let mut bins: Vec<&mut [Pick]> = Vec::with_capacity(reach);
    let mut rest = &mut picks[..starts[reach]];
    for j in 0..reach {
        let (head, tail) = rest.split_at_mut(starts[j + 1] - starts[j]);
        bins.push(head);
        rest = tail;
    }
    bins.into_par_iter().for_each(|b| {
        if b.len() > CHUNK {
            b.par_sort_unstable_by(pick_order);
        } else {
            b.sort_unstable_by(pick_order);
        }
    });
    picks.truncate(k);
    picks
}

/// Every coefficient with a score ≥ 0 (`score(c, i)`, negative: not selected), sorted by
/// [`pick_order`]: collected in parallel and sorted by score bin as [`top_k_from_floor`] does.
/// A refined set of 1.7 M coefficients (the MNI grid at 5.85 %) took 45 ms to collect in one
/// pass of the masks and 90 ms to sort by comparisons on this 2-core machine.
pub(crate) fn all_sorted<S>(channels: usize, n: usize, score: &S) -> Vec<Pick>
where
    S: Scores,
{
    let (parts, total) = collect_from(channels, n, 0, usize::MAX, score);
    best_of(parts, total)
}

/// Histogram bins per halving of the score: a bin keeps the top 8 of an f32's 23 mantissa bits.
pub(crate) const BINS_PER_OCTAVE: usize = 256;

/// The top `k` selectable coefficients as [`top_k`] returns them, in one pass instead of two,
/// when a floor on their scores is known: every coefficient whose score bin is at least
/// `floor_bin` is collected, and when at least `k` are, the top `k` of those are the top `k`
/// of all (every coefficient left out scores lower than each collected one). Returns `None`
/// (the caller runs [`histogram`] and [`top_k`]) when fewer than `k` reach the floor, or when
/// more than `limit` do (the floor was too low to be worth collecting from).
pub(crate) fn top_k_from_floor<S>(
    channels: usize,
    n: usize,
    k: usize,
    floor_bin: usize,
    limit: usize,
    score: &S,
) -> Option<Vec<Pick>>
where
    S: Scores,
{
    if k == 0 {
        return Some(Vec::new());
    }
    let (parts, total) = collect_from(channels, n, floor_bin, limit, score);
    if total < k || total > limit {
        return None;
    }
    Some(best_of(parts, k))
}

/// The histogram bin of a score (for a floor to pass to [`top_k_from_floor`]).
pub(crate) fn score_bin(score: f64) -> usize {
    bin(score.max(0.0))
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use wavesplat_codec::family::Family;

    #[test]
    fn band_map_agrees_with_locate() {
        for (dims, levels) in [([5usize, 6, 7], 1usize), ([16, 9, 12], 2), ([1, 1, 9], 0)] {
            let g = Geometry::new(dims, Family::Linear, levels, 3).unwrap();
            let map = band_map(&g);
            for (i, b) in map.iter().enumerate() {
                let (band, _) = g.locate(i);
                assert_eq!(*b as usize, g.band_index(band).unwrap(), "{dims:?} {i}");
            }
        }
    }

    /// The score v² of every non-zero value, −1 (never selected) for a zero.
    fn squared_scores(values: &[Vec<f64>]) -> impl Fn(usize, usize) -> f64 + Sync + '_ {
        |c: usize, i: usize| {
            let v = values[c][i];
            if v == 0.0 {
                -1.0
            } else {
                v * v
            }
        }
    }

    #[test]
    fn top_k_equals_a_full_sort() {
        // Few distinct values: many ties, resolved by channel and index; with 3, bins of more
        // than a chunk (sorted in parallel).
        for distinct in [50, 3] {
            top_k_equals_a_full_sort_with(distinct);
        }
    }

    fn top_k_equals_a_full_sort_with(distinct: u32) {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let n = 3 * CHUNK + 17;
        let values: Vec<Vec<f64>> = (0..2)
            .map(|_| {
                (0..n)
                    .map(|_| rng.gen_range(0..distinct) as f64 * 0.25)
                    .collect()
            })
            .collect();
        let score = squared_scores(&values);
        let hist = histogram(2, n, &score, Some(&|c: usize, i: usize| values[c][i]));
        let mut all: Vec<Pick> = (0..2)
            .flat_map(|c| (0..n).map(move |i| (c, i)))
            .filter(|(c, i)| score(*c, *i) >= 0.0)
            .map(|(c, i)| (score(c, i), c as u8, i as u32))
            .collect();
        all.sort_by(pick_order);
        assert_eq!(hist.positive as usize, all.len());
        // Without energies (the refinement's picks) the counts, and so the picks, are the same.
        let counts_only = histogram(2, n, &score, None::<&fn(usize, usize) -> f64>);
        assert_eq!(counts_only.positive, hist.positive);
        for k in [1usize, 7, 1000, 50_000, all.len(), all.len() + 5] {
            let got = top_k(&hist, 2, n, k, &score);
            assert_eq!(got, all[..k.min(all.len())].to_vec(), "k = {k}");
            assert_eq!(top_k(&counts_only, 2, n, k, &score), got, "k = {k}");
        }
        // Every selectable one, in the same order (zeros, scored −1, left out).
        assert_eq!(all_sorted(2, n, &score), all);
        // The energy cut covers the goal.
        let total: f64 = all.iter().map(|p| p.0.sqrt()).sum();
        let goal = 0.5 * total;
        let count = hist.count_for_energy(goal) as usize;
        let picked: f64 = all[..count].iter().map(|p| p.0.sqrt()).sum();
        assert!(picked >= goal);
    }

    /// From any floor, the one-pass selection returns exactly the two-pass top K, or declines.
    #[test]
    fn top_k_from_a_floor_equals_top_k_or_declines() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let n = 2 * CHUNK + 301;
        let values: Vec<Vec<f64>> = (0..2)
            .map(|_| {
                (0..n)
                    .map(|_| rng.gen_range(0..400) as f64 * rng.gen_range(0.0..1.0f64).powi(4))
                    .collect()
            })
            .collect();
        let score = squared_scores(&values);
        let hist = histogram(2, n, &score, None::<&fn(usize, usize) -> f64>);
        for k in [1usize, 50, 5000, 60_000] {
            let want = top_k(&hist, 2, n, k, &score);
            let kth = want.last().map_or(0.0, |p| p.0);
            let mut answered = 0;
            for octaves in [0usize, 1, 3, 40] {
                for floor in [
                    score_bin(kth) + 1,
                    score_bin(kth).saturating_sub(octaves * BINS_PER_OCTAVE),
                ] {
                    match top_k_from_floor(2, n, k, floor, 4 * n, &score) {
                        Some(got) => {
                            assert_eq!(got, want, "k = {k}, floor {floor}");
                            answered += 1;
                        }
                        // Declining is right only when fewer than k reach the floor.
                        None => assert!(floor > score_bin(kth), "k = {k}, floor {floor}"),
                    }
                }
            }
            assert!(answered > 0);
            // A limit below what the floor collects declines.
            assert_eq!(
                top_k_from_floor(2, n, k, 0, k.saturating_sub(1), &score),
                None
            );
        }
    }
}
