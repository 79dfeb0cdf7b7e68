//! Meeting a byte target: the decomposition depth (the default and shallower ones, compared by
//! their X-ray views), the refined set's size predicted from one refit and topped up or cut,
//! and the rate search on the number of kept coefficients against the size the real encoder
//! writes.

use super::encoder::finish;
use super::options::{
    deepest_compared, default_levels, CompressError, CompressOptions, Compressed, DepthSearch,
    Stage,
};
use super::prepare::{code, margin_for_faces, prepare, Coded, Prepared, Ranked};
use crate::refine::{pad_f32, RefineOptions};
use wavesplat_codec::format::CoderKind;
use wavesplat_codec::layout::Geometry;
use wavesplat_codec::volume::Volume;

/// File size guess per kept coefficient for the automatic tiling: measured bytes per kept
/// coefficient are ~0.7–0.9 for the sigmap coder (~0.1 more for the fast coder) and 2–3 for
/// the paper's syntaxes.
pub(super) fn bytes_per_coefficient_guess(coder: CoderKind) -> u64 {
    if coder.quantizes_by_threshold() {
        1
    } else {
        3
    }
}

/// The expected size of a file keeping `kept` coefficients with `coder`, from which its
/// automatic tiling is chosen.
pub(super) fn expected_bytes(kept: usize, coder: CoderKind) -> u64 {
    (kept as u64)
        .saturating_mul(bytes_per_coefficient_guess(coder))
        .max(64)
}

/// The depths a byte target compares first when none is given: the family's default
/// ([`default_levels`]) and, when it is at least 2, one level less (then shallower ones while
/// the shallowest wins and its file affords the next coarse band, [`worth_going_shallower`];
/// deeper ones while the deepest wins over a shallower one, up to [`deepest_compared`]). Which one codes a volume
/// better depends on the rate and on the data: on the test set (BENCHMARKS.md, issue 14) the
/// shallower depth gains 0.5–1.3 dB Q_I at 1.25–5.85 % on most volumes and loses up to 38 dB
/// at 0.07 % (a coarse band too large to afford), while a CT volume keeps preferring the
/// deeper one at every rate; a deeper one than the default never won there, but does on large
/// volumes smooth at their finest scales ([`deepest_compared`]).
pub(super) fn depth_candidates(dims: [usize; 3], opts: &CompressOptions) -> Vec<usize> {
    match opts.levels {
        Some(m) => vec![m],
        None => {
            let d = default_levels(dims, opts.family);
            if d >= 2 && opts.depth_search == DepthSearch::Compare {
                vec![d, d - 1]
            } else {
                vec![d]
            }
        }
    }
}

/// A byte target whose file at depth M keeps at least this share of the coefficients the
/// coarse band of depth M − 1 would hold (per channel) tries M − 1 too: a band 8× larger
/// than M's only pays once the budget nearly affords it. On the test set at M = 2 against
/// M = 1 (refined files, Q_I): the MNI volume plus an offset and its 16-bit variant at 5.85 %
/// (ratio 1.0) gain 2.0–2.1 dB at M = 1; the slabs and aniso at 5.85 % (0.65) lose 0.5–2.3 dB,
/// the RGB phantom at 5.85 % (0.57) 0.4 dB (and its oracle files' views ranked M = 1 first),
/// the first two at 1.25 % (0.24) 1.3 dB, the MNI volume at 1.25 % (0.12) 6 dB.
pub(crate) const SHALLOWER_KEPT: f64 = 0.8;

/// Whether a file of `kept` coefficients over `channels` at `geometry`'s depth M makes depth
/// M − 1 worth a try ([`SHALLOWER_KEPT`]; never below M = 1).
pub fn worth_going_shallower(kept: u64, channels: usize, geometry: &Geometry) -> bool {
    affords_coarse_band(
        kept,
        channels,
        geometry.coefficient_count(),
        geometry.levels,
    )
}

/// Whether `kept` coefficients over `channels` on a grid of `count` coefficients per channel
/// at depth `m` make depth m − 1 worth a try ([`SHALLOWER_KEPT`] of its coarse band).
fn affords_coarse_band(kept: u64, channels: usize, count: usize, m: usize) -> bool {
    if m < 2 || channels == 0 {
        return false;
    }
    // The coarse band of M − 1 on this grid (the shallower grid is at most this large).
    let coarse = count as f64 / 8f64.powi(m as i32 - 1);
    kept as f64 / channels as f64 >= SHALLOWER_KEPT * coarse
}

/// The depth a predicted search goes to from a file of `kept` coefficients at `geometry`'s
/// depth: one level shallower while that many coefficients would afford the next coarse band
/// (the grid's size taken for the shallower grids': each step of the comparison's rule, taken
/// at once instead of compressing at every depth between).
pub(super) fn predicted_depth(kept: u64, channels: usize, geometry: &Geometry) -> usize {
    let count = geometry.coefficient_count();
    let mut m = geometry.levels;
    while affords_coarse_band(kept, channels, count, m) {
        m -= 1;
    }
    m
}

/// Byte target. Per candidate depth ([`depth_candidates`]) the oracle's order is searched for
/// the largest prefix that fits ([`oracle_to_bytes`]) and that file's three axis X-ray views
/// are compared with the volume's ([`Prepared::view_error`]); the depth whose views come closer
/// is kept (the default on a tie); while the shallowest depth compared wins and its file
/// affords the next coarse band ([`worth_going_shallower`]), one level less is compared too
/// (where the target's bytes predict a depth two or more levels below the default, the
/// comparison starts there instead: [`compared_from_bytes`]).
/// The oracle's ranking of depths predicted the refined files' ranking at all but one point
/// measured (BENCHMARKS.md), at the cost of one more oracle pass per depth. With refinement,
/// [`refine_to_bytes`] then starts from the chosen prefix's size.
pub(super) fn compress_to_bytes(
    volume: &Volume,
    opts: &CompressOptions,
    target: u64,
    progress: &(dyn Fn(Stage, f64) + Sync),
) -> Result<Compressed, CompressError> {
    let depths = depth_candidates(volume.dims(), opts);
    let comparing = depths.len() > 1;
    let mut trials = 0usize;
    let mut best: Option<(f64, Prepared, Ranked, Compressed, Option<f64>)> = None;
    let mut too_small: Option<CompressError> = None;
    let mut depths = depths;
    let mut next = 0;
    // A predicted depth is chosen from the target's bytes where they decide it
    // ([`depth_from_bytes`]), else from one probe of the default depth ([`Searched`]); the
    // default depth is searched in full only if it is kept, or if the predicted one turns out
    // not to fit the target (`fallback`).
    let predicting =
        !comparing && opts.depth_search == DepthSearch::Predict && opts.levels.is_none();
    let mut probed = false;
    let mut fallback: Option<usize> = None;
    // The default depth's grid, while the depth searched was guessed from the target's bytes
    // alone: its file's count checks the guess.
    let mut unseen: Option<Geometry> = None;
    let mut guess: Option<usize> = None;
    // The coded channels and their views, shared by the depths compared.
    let coded = code(volume, opts, comparing, progress)?;
    if comparing && opts.levels.is_none() {
        depths = compared_from_bytes(volume, opts, &coded, depths, target)?;
    }
    if predicting {
        let default = depths[0];
        if let Some((levels, kept, geometry)) =
            depth_from_bytes(volume, opts, &coded, default, target)?
        {
            tracing::debug!(to = levels, kept, "predicted depth from the target's bytes");
            depths = vec![levels];
            probed = true;
            fallback = Some(default);
            guess = Some(kept);
            unseen = Some(geometry);
        }
    }
    while next < depths.len() {
        let m = depths[next];
        next += 1;
        let o = CompressOptions {
            levels: Some(m),
            ..opts.clone()
        };
        // Compared depths hold no padded targets (the scoring needs only the views): two
        // transforms are held at once, and the winner's targets are built afterwards.
        opts.stop.check()?;
        if comparing {
            progress(Stage::Depth(m), 0.0);
        }
        let prepared = prepare(volume, &o, &coded, !comparing, progress)?;
        // A target too small for one depth may fit the other (their headers and coarse bands
        // differ); it is an error only when it fits neither.
        let probe = predicting && !probed;
        probed = true;
        let searched = oracle_to_bytes(&prepared, &o, target, guess, probe, &mut trials, progress);
        let (ranked, plain, slope) = match searched {
            Ok(Searched::Found(ranked, plain, slope)) => {
                let plain = *plain;
                fallback = None;
                // A depth guessed from the bytes that the file's count would not have chosen
                // (it spends more bits per coefficient than guessed): one level deeper, with
                // its own probe's rule after it.
                if let Some(g) = unseen.take() {
                    let count = g.coefficient_count();
                    let kept = filling_count(&plain, slope, &o, target, prepared.nonzero);
                    if !affords_coarse_band(kept, volume.channel_count(), count, m + 1) {
                        tracing::debug!(levels = m, kept, "guessed too shallow");
                        depths.push(m + 1);
                        guess = Some(kept as usize);
                        continue;
                    }
                }
                (ranked, plain, slope)
            }
            Ok(Searched::Shallower { levels, kept }) => {
                tracing::debug!(from = m, to = levels, kept, "predicted depth from a probe");
                depths.push(levels);
                fallback = Some(m);
                guess = Some(kept);
                continue;
            }
            // (A predicted shallower depth that does not fit leaves the deeper file kept, or
            // has the deeper depth searched after all.)
            Err(e @ CompressError::TargetTooSmall { .. })
                if comparing || best.is_some() || fallback.is_some() =>
            {
                if let Some(deeper) = fallback.take() {
                    depths.push(deeper);
                    guess = None;
                }
                tracing::debug!(levels = m, error = %e, "depth candidate does not fit");
                // The error names the smallest file of any depth.
                let smaller = |a: &CompressError, b: &CompressError| match (a, b) {
                    (
                        CompressError::TargetTooSmall { minimum: x, .. },
                        CompressError::TargetTooSmall { minimum: y, .. },
                    ) => x < y,
                    _ => false,
                };
                if too_small.as_ref().is_none_or(|t| smaller(&e, t)) {
                    too_small = Some(e);
                }
                continue;
            }
            Err(e) => return Err(e),
        };
        if !comparing {
            // A predicted depth goes shallower while the file affords the next coarse band
            // (the comparison's own rule for trying it), and takes it unseen.
            let to = if opts.depth_search == DepthSearch::Predict && opts.levels.is_none() {
                let kept = filling_count(&plain, slope, &o, target, prepared.nonzero);
                predicted_depth(kept, prepared.channels, &prepared.geometry)
            } else {
                m
            };
            best = Some((0.0, prepared, ranked, plain, slope));
            if to < m {
                depths.push(to);
                continue;
            }
            break;
        }
        let error = prepared.view_error(&plain);
        tracing::debug!(
            levels = m,
            bytes = plain.stats.bytes,
            kept = plain.stats.kept,
            view_error = error,
            "depth candidate"
        );
        if best.as_ref().is_none_or(|b| error < b.0) {
            best = Some((error, prepared, ranked, plain, slope));
        }
        // The shallowest depth so far won: one level less may be better still, when its
        // coarse band is affordable. The deepest so far won over a shallower one: one level
        // more may be better still (a volume smooth at its finest scales), up to
        // [`deepest_compared`].
        if next == depths.len() {
            let deepest = depths.iter().copied().max().unwrap_or(m);
            let shallowest = depths.iter().copied().min().unwrap_or(m);
            if let Some((_, p, _, c, _)) = &best {
                if p.geometry.levels == shallowest
                    && worth_going_shallower(c.stats.kept, p.channels, &p.geometry)
                {
                    depths.push(shallowest - 1);
                } else if p.geometry.levels == deepest
                    && deepest < deepest_compared(volume.dims(), opts.family)
                {
                    depths.push(deepest + 1);
                }
            }
        }
    }
    let Some((_, mut prepared, ranked, plain, slope)) = best else {
        return Err(too_small.unwrap_or_else(|| {
            CompressError::InvalidOption("no decomposition depth to try".to_string())
        }));
    };
    prepared.views = Vec::new();
    if comparing && opts.refine.is_some() {
        prepared.targets = coded
            .channels(volume)
            .iter()
            .map(|c| pad_f32(c, &prepared.geometry))
            .collect();
    }
    drop(coded);
    let k0 = plain.stats.kept as usize;
    // Every non-zero coefficient fits: what is left of the target goes to a finer quantizer.
    if k0 > 0 && ranked.complete && k0 >= ranked.sorted.len() {
        let plain = finer_steps_to_bytes(
            &prepared,
            &ranked,
            plain,
            opts,
            target,
            &mut trials,
            progress,
        )?;
        return Ok(finish(&prepared, &ranked, plain));
    }
    let Some(r) = &opts.refine else {
        return Ok(finish(&prepared, &ranked, plain));
    };
    if k0 == 0 {
        return Ok(finish(&prepared, &ranked, plain));
    }
    if r.one_set {
        return refine_one_set_to_bytes(
            &prepared,
            ranked,
            plain,
            slope,
            r,
            opts,
            target,
            &mut trials,
            progress,
        );
    }
    refine_to_bytes(
        &prepared,
        ranked,
        plain,
        r,
        opts,
        target,
        &mut trials,
        progress,
    )
}

/// Whether the unrefined file is searched as a size guide ([`GUIDE_FILL`], [`GUIDE_BRACKET`]):
/// one refined set follows ([`RefineOptions::one_set`]) and the depth is predicted (compared
/// depths' views are compared at equal bytes).
fn sized_by_guide(opts: &CompressOptions) -> bool {
    opts.refine.is_some_and(|r| r.one_set) && opts.depth_search == DepthSearch::Predict
}

/// The count of coefficients that fills `target` bytes, as the depth rules read it: the
/// searched file's, or where that file is a size guide that may stop short of the target or
/// just over it ([`GUIDE_NEAR`], [`GUIDE_BRACKET`]), its count extrapolated to the target at
/// the measured `slope` or [`THRESHOLD_SIZE_SLOPE`] (so that the depth does not depend on
/// where the guide stopped).
fn filling_count(
    plain: &Compressed,
    slope: Option<f64>,
    opts: &CompressOptions,
    target: u64,
    nonzero: u64,
) -> u64 {
    let kept = plain.stats.kept;
    if !sized_by_guide(opts) || plain.stats.bytes == 0 {
        return kept;
    }
    let fill = target as f64 / plain.stats.bytes as f64;
    (count_at(kept as usize, fill, slope.unwrap_or(THRESHOLD_SIZE_SLOPE)) as u64)
        .clamp(kept.min(1), nonzero.max(kept))
}

/// Finest quantizer step the search below tries, relative to the one `--step` gives.
const FINEST_STEP: f64 = 1.0 / 65536.0;

/// Step-search encodings after the halvings: each bisects the ratio between the finest step
/// that fits and the coarsest that does not (log scale), so four of them land within 2^(1/16)
/// of the step that fills the target.
const STEP_BISECTIONS: usize = 4;

/// When a file keeps every non-zero coefficient (`plain`: all of `ranked`) and still falls short
/// of `target`, the bytes left go to a finer quantizer: the step (relative to each band's
/// smallest kept magnitude, `--step`) is halved while the file fits, then bisected between the
/// last fitting and the first overflowing step. Without this the file stopped where the
/// selection ran out, with the quantizer's error of up to half the smallest coefficient on every
/// value (a single slice at 20 % of its bytes came out at 5 % and 29 dB PSNR). Returns the
/// fullest file that fits (`plain` when none of the finer ones does).
fn finer_steps_to_bytes(
    prepared: &Prepared,
    ranked: &Ranked,
    plain: Compressed,
    opts: &CompressOptions,
    target: u64,
    trials: &mut usize,
    progress: &(dyn Fn(Stage, f64) + Sync),
) -> Result<Compressed, CompressError> {
    if !opts.coder.quantizes_by_threshold() || !leaves_room(plain.stats.bytes, target) {
        return Ok(plain);
    }
    let k = plain.stats.kept as usize;
    let mut run = |step: f64| {
        opts.stop.check()?;
        *trials += 1;
        progress(Stage::Encode(*trials), 0.0);
        let o = CompressOptions {
            step,
            ..opts.clone()
        };
        Ok::<_, CompressError>(prepared.encode(ranked, k, &o, target, false))
    };
    // (step, file) that fits, and the coarsest step found to overflow.
    let mut fits = (opts.step, plain);
    let mut overflows: Option<f64> = None;
    let mut step = opts.step;
    while step > opts.step * FINEST_STEP {
        step /= 2.0;
        let c = run(step)?;
        tracing::debug!(step, bytes = c.stats.bytes, target, "finer quantizer");
        if c.stats.bytes > target {
            overflows = Some(step);
            break;
        }
        fits = (step, c);
        if !leaves_room(fits.1.stats.bytes, target) {
            return Ok(fits.1);
        }
    }
    let Some(mut over) = overflows else {
        return Ok(fits.1);
    };
    for _ in 0..STEP_BISECTIONS {
        let step = (fits.0 * over).sqrt();
        let c = run(step)?;
        tracing::debug!(step, bytes = c.stats.bytes, target, "finer quantizer");
        if c.stats.bytes > target {
            over = step;
        } else {
            fits = (step, c);
            if !leaves_room(fits.1.stats.bytes, target) {
                break;
            }
        }
    }
    Ok(fits.1)
}

/// Whether a file of `bytes` leaves more than 3 % of `target` unused.
fn leaves_room(bytes: u64, target: u64) -> bool {
    (bytes as f64) < CLOSE_BELOW * target as f64
}

/// Bits per kept coefficient a file is taken to spend when a depth is predicted from the
/// target's bytes alone ([`depth_from_bytes`]): the MRI's files spend 4.9–5.3 at 0.07–5.85 %.
const GUESSED_BITS_PER_COEFFICIENT: f64 = 5.0;

/// A predicted depth decided before any transform, when the target's bytes decide it: if the
/// count a target affords at [`GUESSED_BITS_PER_COEFFICIENT`] gives a depth shallower than
/// `default` ([`predicted_depth`]), that depth, the guessed count and the default depth's grid
/// (whose rule the file's count is checked against) are returned; otherwise (`None`) the
/// default depth's probe decides ([`oracle_to_bytes`]). Saves the default depth's transform,
/// ranking and probe. The guess is checked both ways by the searched file's own count: one
/// level deeper where it would not have chosen this depth, shallower where it affords the next
/// coarse band ([`compress_to_bytes`]). So a guess near the rule's threshold costs a search at
/// the wrong depth only where it is wrong, where a probe of the default depth costs its
/// transform, ranking and one encoding every time. On the effort study's 32 points (files of
/// 4.3–5.8 bits per coefficient) the guess alone took the 8 points a probe used to decide, to
/// the same depths, none corrected (BENCHMARKS.md, "Compression effort").
fn depth_from_bytes(
    volume: &Volume,
    opts: &CompressOptions,
    coded: &Coded,
    default: usize,
    target: u64,
) -> Result<Option<(usize, usize, Geometry)>, CompressError> {
    let margin = opts
        .margin
        .unwrap_or_else(|| margin_for_faces(coded.structured_faces, opts.family, default));
    let geometry = Geometry::new(volume.dims(), opts.family, default, margin)?;
    let channels = volume.channel_count();
    let kept = target as f64 * 8.0 / GUESSED_BITS_PER_COEFFICIENT;
    let levels = predicted_depth(kept as u64, channels, &geometry);
    Ok((levels < default).then_some((levels, kept as usize, geometry)))
}

/// The depths a comparison starts from ([`depth_candidates`]'s default `d` and `d − 1`), moved
/// to the depth p the target's bytes predict ([`depth_from_bytes`]) and the one above it where
/// p lies two or more levels below the default. The comparison walks from its first two
/// depths towards the better one (shallower while the shallowest wins and affords the next
/// coarse band, deeper while the deepest wins), so started from the default it compared every
/// depth down to p at the high rates of the large volumes (a transform, a scoring and a rate
/// search of the whole file each: 1.2 s of mni-offset's 6.5 s at 5.85 %); started at p it
/// reaches the same depth wherever the views' error falls and then rises with depth, and can
/// only reach a shallower one where the default's neighbour did not afford it.
fn compared_from_bytes(
    volume: &Volume,
    opts: &CompressOptions,
    coded: &Coded,
    depths: Vec<usize>,
    target: u64,
) -> Result<Vec<usize>, CompressError> {
    let Some(&default) = depths.first() else {
        return Ok(depths);
    };
    Ok(
        match depth_from_bytes(volume, opts, coded, default, target)? {
            Some((p, _, _)) if p + 1 < default => {
                tracing::debug!(
                    from = default,
                    to = p,
                    "compared depths start at the predicted depth"
                );
                vec![p + 1, p]
            }
            _ => depths,
        },
    )
}

/// What [`oracle_to_bytes`] found: the ranking and its fullest file that fits (a size guide's
/// may lie just over the target, [`Fitted`]), or (a probe for a predicted depth) the shallower
/// depth the target's estimated count affords.
enum Searched {
    /// The ranking, its file, and the search's local size slope ([`Fitted::slope`]).
    Found(Ranked, Box<Compressed>, Option<f64>),
    /// The depth to search instead, and the count the probe estimated for the target (the
    /// shallower search's first guess).
    Shallower { levels: usize, kept: usize },
}

/// Log–log slope of a file's size against its count of kept coefficients that a single trial
/// extrapolates with where the coder is one of the paper's syntaxes ([`step_slope`]), and a
/// probe for a predicted depth extrapolates its trial with (the depth rule was measured so).
const SIZE_SLOPE: f64 = 0.9;

/// The oracle's order searched for the largest prefix that fits `target` bytes, on a candidate
/// list grown 4× whenever the search runs off its end; the first trial at `guess` coefficients
/// (`None`: a guess from the target's bytes). With `probe` (a predicted depth's default), the
/// first trial's size is extrapolated to the target's count first, and if that count affords a
/// shallower depth ([`predicted_depth`]) the search stops there: the full search at this depth
/// (3–7 encodings of the whole file, about half of `--effort fast`'s time at 5.85 %) would
/// only have been the input of the same rule.
fn oracle_to_bytes(
    prepared: &Prepared,
    opts: &CompressOptions,
    target: u64,
    guess: Option<usize>,
    probe: bool,
    trials: &mut usize,
    progress: &(dyn Fn(Stage, f64) + Sync),
) -> Result<Searched, CompressError> {
    let n = prepared.nonzero as usize;
    // Candidates: 4 per target byte for the sigmap and fast coders (they code ~1.1–1.5
    // coefficients per byte on real data), 1 per byte for the paper's syntaxes.
    let per_byte = if opts.coder.quantizes_by_threshold() {
        4
    } else {
        1
    };
    let mut cap = (target.saturating_mul(per_byte) as usize)
        .max(1024)
        .min(n.max(1));
    // A threshold coder's first trial at the bits per coefficient the depth is guessed with:
    // 1 byte a coefficient started the MRI's searches at 0.07–0.15 % at 53–65 % of the
    // target, and every depth's search at 0.6–0.7 at every rate, a trial more each.
    let guess = guess.unwrap_or_else(|| {
        if opts.coder.quantizes_by_threshold() {
            (target as f64 * 8.0 / GUESSED_BITS_PER_COEFFICIENT) as usize
        } else {
            (target / bytes_per_coefficient_guess(opts.coder)) as usize
        }
    });
    let mut probe = probe;
    loop {
        opts.stop.check()?;
        let ranked = prepared.ranked(cap);
        let mut known = None;
        if std::mem::take(&mut probe) && !ranked.sorted.is_empty() {
            let k = guess.clamp(1, ranked.sorted.len());
            *trials += 1;
            progress(Stage::Encode(*trials), 0.0);
            let first = prepared.encode(&ranked, k, opts, target, false);
            let ratio = target as f64 / first.stats.bytes.max(1) as f64;
            let kept = count_at(k, ratio, SIZE_SLOPE).clamp(1, n.max(1));
            let levels = predicted_depth(kept as u64, prepared.channels, &prepared.geometry);
            if levels < prepared.geometry.levels {
                return Ok(Searched::Shallower { levels, kept });
            }
            known = Some(first);
        }
        // Where one refined set follows, this file is a size guide (and a fallback): a looser
        // fill, or two trials closely either side of the target, save trials of the whole file.
        // Not where depths are compared: their files' views are compared at equal bytes.
        let guide = sized_by_guide(opts);
        let search = RateSearch {
            target,
            guess,
            known,
            fill: if guide { GUIDE_FILL } else { FILE_FILL },
            guide,
            slope: step_slope(opts),
        };
        let Fitted { file: plain, slope } =
            fit_bytes(prepared, &ranked, opts, search, trials, progress)?;
        let len = ranked.sorted.len();
        if ranked.complete || (plain.stats.kept as usize) < len || cap >= n {
            return Ok(Searched::Found(ranked, Box::new(plain), slope));
        }
        cap = cap.saturating_mul(4).min(n);
    }
}

/// Refinements a byte target may run (each is ~36 applications of the synthesis and its
/// transpose; the rate searches between them only run the entropy coder).
const MAX_REFINEMENTS: usize = 3;

/// A whole refined set this close to the target ends the search: one below it is topped up
/// with the coefficients that would join it next ([`Refined::extension`]), one above it cut to
/// the target. Measured on the MNI volume at 1.25 % against a set refined to fill the target
/// (Q_I 91.80): topping up 1.8 % or 5 % of the bytes gave 91.84 and 91.74, cutting 4 % 91.78
/// (8 %: 91.70, 13 %: 91.57); on mni-offset at 5.85 % a 4.4 % cut lost 0.17 dB. Another
/// refinement costs as much as the first.
const CLOSE_BELOW: f64 = 0.97;
const CLOSE_ABOVE: f64 = 1.03;

/// The byte target's refinement: a refined set codes at a different size from the oracle's
/// prefix it came from (usually smaller: refitted values are smaller and about a fifth of them
/// are pruned), and neither cutting it to the target nor topping it up by much is as good as
/// refining a set of the right size. So the size K of the first set comes from one refit of
/// the oracle's set ([`predicted_set_size`]), the refined set of K is encoded whole, and
/// while it misses the target by more than [`CLOSE_BELOW`]–[`CLOSE_ABOVE`], K is moved by a
/// secant step on log size against log K ([`next_set_size`]), for at most
/// [`MAX_REFINEMENTS`] refinements. A set within that window is topped up or cut to the target
/// (unless it already fills 98.5–100 %). Otherwise the fullest candidate is kept (a whole set,
/// an overflowing set cut to the target, or on the last attempt the set topped up), unless it
/// fills less than 98 % of the target and less than the unrefined file, which is then kept
/// instead.
#[allow(clippy::too_many_arguments)]
fn refine_to_bytes(
    prepared: &Prepared,
    ranked: Ranked,
    plain: Compressed,
    r: &RefineOptions,
    opts: &CompressOptions,
    target: u64,
    trials: &mut usize,
    progress: &(dyn Fn(Stage, f64) + Sync),
) -> Result<Compressed, CompressError> {
    let n = prepared.nonzero as usize;
    let goal = 0.99 * target as f64;
    // (K, bytes of the whole refined set of K), by K.
    let mut sizes: Vec<(usize, u64)> = Vec::new();
    let mut best: Option<(Compressed, Ranked)> = None;
    let fuller = |best: &Option<(Compressed, Ranked)>, c: &Compressed| {
        best.as_ref()
            .is_none_or(|(b, _)| c.stats.bytes > b.stats.bytes)
    };
    let k0 = plain.stats.kept as usize;
    opts.stop.check()?;
    progress(Stage::Refine, 0.0);
    let mut k = predicted_set_size(
        k0,
        plain.stats.bytes,
        prepared.pilot(&ranked, k0, r),
        target,
        n,
    );

    // The oracle's order, grown when K needs more candidates (`ranked` stays `plain`'s).
    let mut candidates: Option<Ranked> = None;
    for attempt in 0..MAX_REFINEMENTS {
        // The refinement reads the top K; the oracle's order beyond its extension follows.
        let wanted = (k + k / 4).min(n);
        let source = candidates.as_ref().unwrap_or(&ranked);
        if source.sorted.len() < wanted && !source.complete {
            candidates = Some(prepared.ranked(wanted));
        }
        let source = candidates.as_ref().unwrap_or(&ranked);
        opts.stop.check()?;
        progress(Stage::Refine, attempt as f64 / MAX_REFINEMENTS as f64);
        let k_set = k.min(source.sorted.len());
        let refined = prepared.refined(source, k_set, r, k_set.div_ceil(4));
        let count = refined.refined;
        if count == 0 {
            break;
        }
        opts.stop.check()?;
        *trials += 1;
        progress(Stage::Encode(*trials), 0.0);
        let whole = prepared.encode(&refined, count, opts, target, false);
        let bytes = whole.stats.bytes;
        tracing::debug!(k, count, bytes, target, "refined set encoded whole");
        sizes.push((k, bytes));
        let last = attempt + 1 == MAX_REFINEMENTS;
        let close = close_to_target(bytes, target);
        // Close to the target, or out of refinements: top the set up with the coefficients
        // that would join it next, or cut it to the target.
        let fit = |whole: Compressed, trials: &mut usize| {
            let search = RateSearch {
                target,
                guess: count,
                known: Some(whole),
                fill: FILE_FILL,
                guide: false,
                slope: step_slope(opts),
            };
            fit_bytes(prepared, &refined, opts, search, trials, progress).map(|f| f.file)
        };
        let candidate = if bytes <= target {
            if (bytes as f64) < 0.985 * target as f64 && (last || close) {
                fit(whole, trials)
            } else {
                Ok(whole)
            }
        } else {
            fit(whole, trials)
        };
        // A refined set that cannot be cut to the target leaves the oracle's file standing
        // (a stop asked for ends the compression).
        let candidate = match candidate {
            Ok(c) => c,
            Err(CompressError::Stopped) => return Err(CompressError::Stopped),
            Err(_) => break,
        };
        if fuller(&best, &candidate) {
            best = Some((candidate, refined));
        }
        if close {
            break;
        }
        let next = next_set_size(&sizes, goal, n);
        if sizes.iter().any(|&(sk, _)| sk == next) {
            break;
        }
        k = next;
    }
    // The refinements' arrays are not needed for the final file.
    prepared.scratch.clear();
    match best {
        Some((b, refined)) if refined_file_stands(&b, &plain, target) => {
            Ok(finish(prepared, &refined, b))
        }
        _ => Ok(finish(prepared, &ranked, plain)),
    }
}

/// Whether a refined file is kept rather than the unrefined `plain` one: it fills 98 % of the
/// target, or at least as much as `plain` does.
fn refined_file_stands(refined: &Compressed, plain: &Compressed, target: u64) -> bool {
    fills_most_of(refined, target) || refined.stats.bytes >= plain.stats.bytes
}

/// Whether a file fills 98 % of the target: a refined file that does stands whatever the
/// unrefined one fills ([`refined_file_stands`]).
fn fills_most_of(file: &Compressed, target: u64) -> bool {
    file.stats.bytes as f64 >= 0.98 * target as f64
}

/// The size of [`RefineOptions::one_set`]'s refined set over the count of the unrefined file
/// that fills the target. A refit prunes about a fifth of a set and shrinks the rest, so the
/// set codes to about the target; this much makes it overshoot a little at most points
/// (cutting costs less than topping up: [`CLOSE_BELOW`]).
const ONE_SET_GROWTH: f64 = 1.25;

/// A byte target's refinement with [`RefineOptions::one_set`]: one refined set,
/// [`ONE_SET_GROWTH`] times the unrefined file's count, fitted to the target by the rate search
/// (cut, or topped up with the oracle's next coefficients). The unrefined file is kept where
/// the refined one fills less than 98 % of the target and less than it.
#[allow(clippy::too_many_arguments)]
fn refine_one_set_to_bytes(
    prepared: &Prepared,
    mut ranked: Ranked,
    plain: Compressed,
    slope: Option<f64>,
    r: &RefineOptions,
    opts: &CompressOptions,
    target: u64,
    trials: &mut usize,
    progress: &(dyn Fn(Stage, f64) + Sync),
) -> Result<Compressed, CompressError> {
    let n = prepared.nonzero as usize;
    // The count that would fill the target, from the guide's (searched to [`GUIDE_FILL`] or
    // [`GUIDE_BRACKET`]) at the slope its search measured around the target.
    let k0 = filling_count(&plain, slope, opts, target, prepared.nonzero) as usize;
    let slope = slope.unwrap_or(THRESHOLD_SIZE_SLOPE);
    let k = ((k0 as f64 * ONE_SET_GROWTH).ceil() as usize).clamp(1, n.max(1));
    opts.stop.check()?;
    progress(Stage::Refine, 0.0);
    // A search cuts the set or tops it up by a few per cent: what lies further down the
    // oracle's order (at high rates most of the grid) is not copied behind the refined set.
    let room = (k + k / 4).max(k0);
    if ranked.sorted.len() > room {
        ranked.truncate(room);
    }
    let grown = (ranked.sorted.len() < k && !ranked.complete).then(|| prepared.ranked(room));
    let source = grown.as_ref().unwrap_or(&ranked);
    let k_set = k.min(source.sorted.len());
    let refined = prepared.refined(source, k_set, r, 0);
    // The refinement's arrays are not needed for the rate search.
    prepared.scratch.clear();
    let count = refined.refined;
    if count == 0 {
        let plain = guide_filled(
            prepared, &ranked, plain, slope, opts, target, trials, progress,
        )?;
        return Ok(finish(prepared, &ranked, plain));
    }
    // Refined values code in about [`REFINED_BYTES`] times the bytes of as many exact ones:
    // the first trial is the count whose refined file would fill the middle of the accepted
    // sizes, or the whole set where the prune left fewer.
    let aim = (1.0 + FILE_FILL) / 2.0 / REFINED_BYTES;
    let search = RateSearch {
        target,
        guess: count.min(count_at(k0, aim, slope)),
        known: None,
        fill: FILE_FILL,
        guide: false,
        slope,
    };
    let fitted = fit_bytes(prepared, &refined, opts, search, trials, progress).map(|f| f.file);
    opts.stop.check()?;
    if let Ok(b) = &fitted {
        if fills_most_of(b, target) {
            tracing::debug!(
                k,
                count,
                bytes = b.stats.bytes,
                target,
                "one refined set fitted"
            );
            return Ok(finish(prepared, &refined, fitted?));
        }
    }
    // A refined file short of the target is weighed against the unrefined one searched to
    // the full fill.
    let plain = guide_filled(
        prepared, &ranked, plain, slope, opts, target, trials, progress,
    )?;
    match fitted {
        Ok(b) if refined_file_stands(&b, &plain, target) => Ok(finish(prepared, &refined, b)),
        _ => Ok(finish(prepared, &ranked, plain)),
    }
}

/// The size guide's file (searched to [`GUIDE_FILL`], or only until [`GUIDE_BRACKET`] or a file
/// just over the target, [`GUIDE_NEAR`]) taken to the full fill, where it stands in for the
/// one refined set.
#[allow(clippy::too_many_arguments)]
fn guide_filled(
    prepared: &Prepared,
    ranked: &Ranked,
    plain: Compressed,
    slope: f64,
    opts: &CompressOptions,
    target: u64,
    trials: &mut usize,
    progress: &(dyn Fn(Stage, f64) + Sync),
) -> Result<Compressed, CompressError> {
    let search = RateSearch {
        target,
        guess: plain.stats.kept as usize,
        known: Some(plain),
        fill: FILE_FILL,
        guide: false,
        slope,
    };
    Ok(fit_bytes(prepared, ranked, opts, search, trials, progress)?.file)
}

/// The count whose file is `ratio` times the size of one of `k` coefficients, along a
/// log–log `slope` of size against count.
fn count_at(k: usize, ratio: f64, slope: f64) -> usize {
    (k as f64 * ratio.powf(1.0 / slope)).round() as usize
}

/// The final refined set's size over the survivors of its first refit ([`Prepared::pilot`]),
/// at the larger K the prediction moves to: 0.95–1.05 around it over the test set's volumes
/// and sizes, a little above 1 on average, so the first set tends to overshoot (cutting costs
/// less than topping up; BENCHMARKS.md, "One refinement per byte target").
pub(super) const PILOT_KEEP: f64 = 1.0;

/// Log–log slope of a file's size against its number of coefficients, as fitted to the
/// refined sets of the test set (the oracle's prefixes grow a little faster, ~0.9).
pub(super) const REFINED_SIZE_SLOPE: f64 = 0.85;

/// The first refined-set size a byte target tries: the oracle's prefix of `k0` coefficients
/// fills `bytes0`; a refinement of K keeps about PILOT_KEEP·`survivors`/`k0`·K of them, whose
/// file is about `bytes0`·(kept/`k0`)^REFINED_SIZE_SLOPE. Solved for `target` (BENCHMARKS.md,
/// "One refinement per byte target", for where it lands).
pub(super) fn predicted_set_size(
    k0: usize,
    bytes0: u64,
    survivors: usize,
    target: u64,
    n: usize,
) -> usize {
    if k0 == 0 || survivors == 0 || bytes0 == 0 {
        return k0.clamp(1, n.max(1));
    }
    // A pilot keeping less than half (never seen: 0.80–0.99 on the test set) is not trusted
    // further: the candidate lists stay within what `memory_estimate` counts.
    let keep = (PILOT_KEEP * survivors as f64 / k0 as f64).max(0.5);
    let grow = (target as f64 / bytes0 as f64).powf(1.0 / REFINED_SIZE_SLOPE);
    ((k0 as f64 * grow / keep).round() as usize).clamp(1, n.max(1))
}

/// Whether a whole refined set of `bytes` ends the search for a `target` (see [`CLOSE_BELOW`]).
pub(super) fn close_to_target(bytes: u64, target: u64) -> bool {
    let (b, t) = (bytes as f64, target as f64);
    b >= CLOSE_BELOW * t && b <= CLOSE_ABOVE * t
}

/// Growth of a whole refined set's file size with K (log–log slope): about 1, since a refined
/// set keeps a steady ~4/5 of K (measured on the MNI volume between K = 157 k and 192 k: 1.04).
const REFINED_SLOPE: f64 = 1.0;

/// The next refined-set size for a byte goal from the sizes of whole refined sets tried so far:
/// a secant step on log bytes against log K between the tightest sets below and above the
/// goal, or from the nearest one with [`REFINED_SLOPE`].
pub(super) fn next_set_size(sizes: &[(usize, u64)], goal: f64, n: usize) -> usize {
    let below = sizes
        .iter()
        .filter(|&&(_, b)| (b as f64) <= goal)
        .max_by_key(|&&(k, _)| k)
        .copied();
    let above = sizes
        .iter()
        .filter(|&&(_, b)| (b as f64) > goal)
        .min_by_key(|&&(k, _)| k)
        .copied();
    let step = |(k, b): (usize, u64), slope: f64| -> f64 {
        ((k.max(1) as f64).ln() + (goal.ln() - (b.max(1) as f64).ln()) / slope).exp()
    };
    let k = match (below, above) {
        (Some((lk, lb)), Some((hk, hb))) if hk > lk + 1 && hb > lb => {
            let slope = log_log_slope((lk.max(1), lb.max(1)), (hk, hb));
            (step((lk, lb), slope.clamp(0.3, 3.0)).round() as usize).clamp(lk + 1, hk - 1)
        }
        (Some(p), Some(_)) => p.0,
        (Some(p), None) => (step(p, REFINED_SLOPE).ceil() as usize).max(p.0 + 1),
        (None, Some(p)) => {
            (step(p, REFINED_SLOPE).floor() as usize).clamp(1, p.0.saturating_sub(1).max(1))
        }
        (None, None) => 1,
    };
    k.clamp(1, n.max(1))
}

/// Largest trial files of a rate search before it settles for the best one found.
const MAX_TRIALS: usize = 24;

/// How full a file the rate search settles for: the target to 0.2 % where the granularity
/// allows.
const FILE_FILL: f64 = 0.998;

/// The bytes of a refined set's prefix over those of the oracle's prefix of as many
/// coefficients: 0.995–1.037 at the effort study's 32 points, 1.011 at the median (each first
/// refined trial aimed at the oracle's count). The first refined trial aims this much lower.
const REFINED_BYTES: f64 = 1.011;

/// How full the unrefined file is searched where [`RefineOptions::one_set`] refines after it
/// (with a predicted depth): that file only sizes the refined set ([`refine_one_set_to_bytes`],
/// which extrapolates its count to the target); where the refined file falls short it is
/// searched on to [`FILE_FILL`] before the two are weighed ([`guide_filled`]). Its search
/// ends on a file within [`GUIDE_NEAR`] of the target on either side.
const GUIDE_FILL: f64 = 1.0 / GUIDE_NEAR;

/// A size guide's search ends on a file this close to the target, under or over it: one trial
/// extrapolated at [`THRESHOLD_SIZE_SLOPE`] sizes the refined set within ~1 % wherever the
/// local slope lies between 0.95 and 1.25 (what the effort study's volumes show), and at
/// 1.25 % and 5.85 % of their bytes the first trial lands within 7 % at 11 of 16 points.
const GUIDE_NEAR: f64 = 1.08;

/// Log–log slope of a file's size against its count of kept coefficients that the threshold
/// coders' searches step with ([`step_slope`]), and a size guide extrapolates with where its
/// search did not measure one: the effort study's unrefined files grow as K^0.95 to K^1.37
/// around the target (median 1.05; the finer quantizer steps that more coefficients bring
/// cost bits on every one), more steeply than [`SIZE_SLOPE`].
const THRESHOLD_SIZE_SLOPE: f64 = 1.05;

/// The slope a search's one-sided steps take: [`THRESHOLD_SIZE_SLOPE`] for the threshold
/// coders (whose files grow so), [`SIZE_SLOPE`] for the paper's syntaxes.
fn step_slope(opts: &CompressOptions) -> f64 {
    if opts.coder.quantizes_by_threshold() {
        THRESHOLD_SIZE_SLOPE
    } else {
        SIZE_SLOPE
    }
}

/// A size guide's search also ends once a fitting and an overflowing trial lie within this
/// factor of the target on either side: the count that fills the target is then interpolated
/// between them on log size against log count (within ~1 % of the one the search would have
/// landed on at mni-offset 5.85 %), which is all the refined set needs of it.
const GUIDE_BRACKET: f64 = 1.25;

/// What a rate search ([`fit_bytes`]) looks for and where it starts.
struct RateSearch {
    /// Bytes the file may take.
    pub(super) target: u64,
    /// Prefix length of the first trial.
    pub(super) guess: usize,
    /// A file of this ranking already encoded (its prefix length is its kept count): it
    /// counts as the first trial.
    pub(super) known: Option<Compressed>,
    /// How full a file ends the search ([`FILE_FILL`] but for a size guide).
    pub(super) fill: f64,
    /// A size guide ([`GUIDE_BRACKET`]): the search also ends once the target is bracketed
    /// closely.
    pub(super) guide: bool,
    /// The log–log slope of size against count a step from one side takes ([`SIZE_SLOPE`]
    /// unless an earlier search of the same volume measured it).
    pub(super) slope: f64,
}

/// A rate search's result: the fullest file that fits (a size guide's: the file it ended on,
/// which may lie over the target by up to [`GUIDE_NEAR`]), and the log–log slope of size
/// against count between the closest trials on either side of the target (where there were
/// both).
pub(super) struct Fitted {
    pub(super) file: Compressed,
    pub(super) slope: Option<f64>,
}

/// The rate search: the largest prefix of `ranked` whose file fits `target` bytes, stopping
/// at the first that fills [`FILE_FILL`] of it. Sizes grow smoothly (about as K^0.9) with the
/// number K of kept coefficients, so each trial interpolates log size against log K between
/// the tightest fitting and overflowing trials (extrapolating from the one known side first),
/// and every third step bisects to guarantee progress unless the last step at least halved
/// its distance to the aim (a secant closing in from one side leaves the other bound far, so
/// a bisection there would throw away a step that nearly landed). Typically 2–6 trials.
fn fit_bytes(
    prepared: &Prepared,
    ranked: &Ranked,
    opts: &CompressOptions,
    search: RateSearch,
    trials: &mut usize,
    progress: &(dyn Fn(Stage, f64) + Sync),
) -> Result<Fitted, CompressError> {
    let RateSearch {
        target,
        guess,
        mut known,
        fill,
        guide,
        slope: one_sided,
    } = search;
    let len = ranked.sorted.len();
    let mut run = |k: usize| {
        *trials += 1;
        progress(Stage::Encode(*trials), 0.0);
        prepared.encode(ranked, k, opts, target, false)
    };
    let goal = fill * target as f64;
    // Steps aim at the middle of the accepted sizes: aiming at its lower edge, the secant
    // creeps up on it a few coefficients at a time.
    let aim = (1.0 + fill) / 2.0 * target as f64;
    // Fitting (k, bytes) and overflowing (k, bytes) bounds.
    let mut lo: Option<(usize, u64)> = None;
    let mut hi: Option<(usize, u64)> = None;
    let mut best: Option<Compressed> = None;
    // The trial over the target a size guide ended on (within [`GUIDE_NEAR`]).
    let mut over: Option<Compressed> = None;
    let mut k = guess.clamp(len.min(1), len);
    // How far the last two trials' sizes were from the aim (log ratio).
    let mut misses = [f64::INFINITY; 2];
    // The fitting (overflowing) trial before `lo` (`hi`): with it a one-sided step takes the
    // slope the file showed there.
    let mut lo_before: Option<(usize, u64)> = None;
    let mut hi_before: Option<(usize, u64)> = None;
    // Trials in a row that moved the same bound (+ `lo`, − `hi`): the other one is stale.
    let mut same_side = 0i32;
    for step in 0..MAX_TRIALS {
        opts.stop.check()?;
        let c = match known.take() {
            Some(c) if (c.stats.kept as usize) <= len => {
                k = c.stats.kept as usize;
                c
            }
            _ => run(k),
        };
        let bytes = c.stats.bytes;
        tracing::trace!(k, bytes, target, "rate search trial");
        misses = [misses[1], ((bytes.max(1) as f64) / aim).ln().abs()];
        let t = target as f64;
        // A size guide ends on a file just over the target too (not on every coefficient: a
        // file of all of them that overflows is the finer quantizers' search's to take on).
        if guide && bytes > target && k < len && bytes as f64 <= t * GUIDE_NEAR {
            over = Some(c);
            break;
        }
        if bytes <= target {
            if lo.is_none_or(|(lk, _)| k > lk) {
                lo_before = lo;
                lo = Some((k, bytes));
                same_side = same_side.max(0) + 1;
            }
            if best.as_ref().is_none_or(|b| bytes > b.stats.bytes) {
                best = Some(c);
            }
        } else if hi.is_none_or(|(hk, _)| k < hk) {
            hi_before = hi;
            hi = Some((k, bytes));
            same_side = same_side.min(0) - 1;
        }
        if best.as_ref().is_some_and(|b| b.stats.bytes as f64 >= goal) {
            break;
        }
        if guide
            && lo.is_some_and(|(_, lb)| lb as f64 * GUIDE_BRACKET >= t)
            && hi.is_some_and(|(_, hb)| hb as f64 <= t * GUIDE_BRACKET)
        {
            break;
        }
        let log_k = |bytes_at: u64, k_at: usize, slope: f64| -> f64 {
            (k_at.max(1) as f64).ln() + (aim.ln() - (bytes_at.max(1) as f64).ln()) / slope
        };
        let next = match (lo, hi) {
            (Some((lk, _)), _) if lk >= len => break,
            (_, Some((0 | 1, _))) => break,
            (Some((lk, _)), Some((hk, _))) if hk <= lk + 1 => break,
            (Some(l), Some(h)) => bracket_next(l, h, aim, same_side, step, misses),
            (Some((lk, lb)), None) => {
                let slope = one_sided_slope(lo_before, (lk, lb), one_sided);
                let x = log_k(lb, lk, slope).exp().ceil() as usize;
                x.clamp(lk + 1, len)
            }
            (None, Some((hk, hb))) => {
                let slope = one_sided_slope(hi_before, (hk, hb), one_sided);
                let x = log_k(hb, hk, slope).exp().floor() as usize;
                x.clamp(1, hk - 1)
            }
            (None, None) => break,
        };
        k = next;
    }
    let slope = match (lo, hi) {
        (Some((lk, lb)), Some((hk, hb))) if hk > lk && hb > lb && lb > 0 => {
            let s = log_log_slope((lk, lb), (hk, hb));
            (s.is_finite() && s > 0.0).then_some(s.clamp(0.3, 3.0))
        }
        _ => None,
    };
    match over.or(best) {
        Some(file) => Ok(Fitted { file, slope }),
        None => {
            let smallest = run(len.min(1));
            if smallest.stats.bytes <= target {
                Ok(Fitted {
                    file: smallest,
                    slope,
                })
            } else {
                Err(CompressError::TargetTooSmall {
                    target,
                    minimum: smallest.stats.bytes,
                })
            }
        }
    }
}

/// A rate search's next count between a fitting trial `lo` and an overflowing one `hi` (at
/// least two counts apart), at its `step` with the last two trials' `misses` (log distance to
/// the aim): the middle every third step unless the last one halved its miss, or where the
/// sizes do not grow across the bracket; else [`bracketed_step`], kept strictly inside.
fn bracket_next(
    lo: (usize, u64),
    hi: (usize, u64),
    aim: f64,
    same_side: i32,
    step: usize,
    misses: [f64; 2],
) -> usize {
    let ((lk, lb), (hk, hb)) = (lo, hi);
    let closing_in = misses[1] <= misses[0] / 2.0;
    if (step % 3 == 2 && !closing_in) || hb <= lb {
        lk + (hk - lk) / 2
    } else {
        bracketed_step(lo, hi, aim, same_side).clamp(lk + 1, hk - 1)
    }
}

/// The log–log slope of size against count between two (count, bytes) trials (not finite
/// where a count or a size is 0 or the counts are equal).
fn log_log_slope((k0, b0): (usize, u64), (k1, b1): (usize, u64)) -> f64 {
    ((b1 as f64).ln() - (b0 as f64).ln()) / ((k1 as f64).ln() - (k0 as f64).ln())
}

/// A rate search's step between a fitting trial `(lk, lb)` and an overflowing one `(hk, hb)`
/// (`hb` > `lb`): the count where the line through them on log size against log count meets
/// `aim`. Where `same_side` trials in a row moved the same bound (the line keeps landing on
/// one side: sizes that grow faster or slower than it between the trials), the stale bound's
/// distance to the aim counts half as much for each one past the second, so that the step
/// moves towards it (the Illinois variant of false position). The slope is not clamped: the
/// caller keeps the step strictly inside the bracket. (Clamped to 3, a bracket across a
/// jump in size, 8 % over 70 coefficients on a 1.2 kB file, crept down one coefficient per
/// trial.)
fn bracketed_step(lo: (usize, u64), hi: (usize, u64), aim: f64, same_side: i32) -> usize {
    let (lk, lb) = lo;
    let (hk, hb) = hi;
    let x0 = (lk.max(1) as f64).ln();
    let x1 = (hk.max(1) as f64).ln();
    let mut f0 = (lb.max(1) as f64 / aim).ln();
    let mut f1 = (hb.max(1) as f64 / aim).ln();
    // From the third trial in a row on the same side, each halves the stale bound's weight
    // (after two, the line usually lands: a second trial on one side is most often a step
    // that closed in from far).
    let stale = 0.5f64.powi((same_side.abs() - 2).clamp(0, 30));
    if same_side > 0 {
        f1 *= stale;
    } else {
        f0 *= stale;
    }
    if !f0.is_finite() || !f1.is_finite() || f1 <= f0 {
        return lk + (hk - lk) / 2;
    }
    (x0 - f0 * (x1 - x0) / (f1 - f0)).exp().round() as usize
}

/// The log–log slope a one-sided step of a rate search takes from `at`: the slope the file
/// showed between it and the trial `before` it on the same side where that is gentler than
/// `model` (a step at `model` would creep towards the target), else `model` (a steeper file
/// overshoots at `model` into a bracket, which the next step interpolates).
fn one_sided_slope(before: Option<(usize, u64)>, at: (usize, u64), model: f64) -> f64 {
    let Some((pk, pb)) = before else {
        return model;
    };
    let (k, b) = at;
    if pk == k || pb == 0 || b == 0 {
        return model;
    }
    let measured = log_log_slope((pk, pb), (k, b));
    if measured.is_finite() && measured > 0.0 {
        measured.clamp(0.3, model)
    } else {
        model
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::encode::{Effort, Target};
    use crate::phantom::Phantom;

    /// A size guide's search ends on a file within [`GUIDE_NEAR`] of the target on either
    /// side, or once a fitting and an overflowing trial lie within [`GUIDE_BRACKET`] of it
    /// (then with the slope between them), in no more trials than the full search from the same
    /// start; taken on ([`guide_filled`]) it fills the target as the full search does, and the
    /// count it extrapolates to the target lies within 10 % of the full search's. From first
    /// guesses on both sides of the target, far and near.
    #[test]
    fn a_size_guide_stops_near_the_target_or_once_it_is_bracketed() {
        let v = Phantom::SheppLogan.generate([40, 36, 32]);
        let target = 6_000;
        let opts = CompressOptions {
            target: Target::Bytes(target),
            levels: Some(3),
            ..Effort::Fast.options()
        };
        let none = |_: Stage, _: f64| {};
        let coded = code(&v, &opts, false, &none).unwrap();
        let p = prepare(&v, &opts, &coded, true, &none).unwrap();
        let ranked = p.ranked(p.nonzero as usize);
        let full = |guess: usize, guide: bool, trials: &mut usize| {
            let search = RateSearch {
                target,
                guess,
                known: None,
                fill: if guide { GUIDE_FILL } else { FILE_FILL },
                guide,
                slope: THRESHOLD_SIZE_SLOPE,
            };
            fit_bytes(&p, &ranked, &opts, search, trials, &none).unwrap()
        };
        let mut ended_over = 0;
        for guess in [500, 3_000, 8_000, 9_200, 9_600, 12_000, 40_000] {
            let (mut guide_trials, mut full_trials) = (0, 0);
            let guided = full(guess, true, &mut guide_trials);
            let filled = full(guess, false, &mut full_trials);
            let t = target as f64;
            let bytes = guided.file.stats.bytes as f64;
            if bytes > t {
                ended_over += 1;
                assert!(bytes <= GUIDE_NEAR * t, "{guess}: {bytes}");
            } else if bytes < GUIDE_FILL * t {
                assert!(bytes * GUIDE_BRACKET >= t, "{guess}: {bytes}");
                assert!(guided.slope.is_some(), "{guess}: no bracket");
            }
            assert!(
                guide_trials <= full_trials,
                "{guess}: {guide_trials} > {full_trials}"
            );
            let f = filled.file.stats;
            assert!(f.bytes as f64 >= FILE_FILL * t, "{guess}");
            // The count the guide extrapolates lies near the one that fills the target.
            let k0 = filling_count(&guided.file, guided.slope, &opts, target, p.nonzero) as f64;
            let k = f.kept as f64;
            assert!(
                k0 >= k * 0.9 && k0 <= k * 1.1,
                "{guess}: extrapolated {k0} against {k}"
            );
            let mut more = 0;
            let slope = guided.slope.unwrap_or(THRESHOLD_SIZE_SLOPE);
            let taken_on = guide_filled(
                &p,
                &ranked,
                guided.file,
                slope,
                &opts,
                target,
                &mut more,
                &none,
            )
            .unwrap();
            let b = taken_on.stats.bytes as f64;
            assert!(b <= t && b >= FILE_FILL * t, "{guess}: {b}");
        }
        // The point of the new rule: a start just over the target ends there.
        assert!(ended_over > 0);
    }

    /// The line through two fresh bounds on log size against log count: where the sizes
    /// follow a power law exactly, the step lands on the aim's count.
    #[test]
    fn a_bracketed_step_interpolates_log_size_against_log_count() {
        let size = |k: usize| (3.0 * (k as f64).powf(1.2)).round() as u64;
        let aim = size(5000) as f64;
        for same_side in [-2, -1, 1, 2] {
            let k = bracketed_step((4000, size(4000)), (7000, size(7000)), aim, same_side);
            assert!(k.abs_diff(5000) <= 2, "{same_side}: {k}");
        }
        // Not increasing: the middle.
        assert_eq!(bracketed_step((100, 900), (200, 900), 900.0, 1), 150);
    }

    /// From the third trial in a row on one side, the step moves towards the stale bound
    /// (halving its weight each time), and never leaves the bracket (the caller keeps it
    /// strictly inside).
    #[test]
    fn a_bracket_stale_on_one_side_is_approached() {
        let lo = (1000, 960);
        let hi = (2000, 2400);
        let plain = bracketed_step(lo, hi, 1000.0, 2);
        let mut last = plain;
        for n in 3..12 {
            let k = bracketed_step(lo, hi, 1000.0, n);
            assert!(k >= last && k <= 2000, "{n}: {k} after {last}");
            last = k;
        }
        assert!(last > plain + 500);
        let mut last = plain;
        for n in 3..12 {
            let k = bracketed_step(lo, hi, 1000.0, -n);
            assert!(k <= last && k >= 1000, "{n}: {k} after {last}");
            last = k;
        }
        assert!(last < plain);
    }

    /// A bracket across a jump in size (a 1.2 kB file that grows 8 % over 70 coefficients, as
    /// aniso at 0.15 % does): the search's bracket phase, stepped by [`fit_bytes`]'s own rule
    /// ([`bracket_next`]), ends on a file that fills the target in a few trials, where a slope
    /// clamped to 3 crept down one coefficient per trial.
    #[test]
    fn a_bracket_across_a_jump_in_size_closes_in_a_few_trials() {
        let size = |k: usize| -> u64 {
            let smooth = 0.25 * k as f64;
            let jump = if k > 4850 { 1.08 } else { 1.0 };
            (smooth * jump).round() as u64
        };
        let target = 1213u64;
        let aim = (1.0 + FILE_FILL) / 2.0 * target as f64;
        let mut lo = (4780, size(4780));
        let mut hi = (4921, size(4921));
        let mut same_side = -1;
        let mut misses = [f64::INFINITY; 2];
        let mut trials = 0;
        for step in 0.. {
            assert!(step < 24, "no end after {trials} trials");
            if hi.0 <= lo.0 + 1 || lo.1 as f64 >= FILE_FILL * target as f64 {
                break;
            }
            let k = bracket_next(lo, hi, aim, same_side, step, misses);
            trials += 1;
            let b = size(k);
            misses = [misses[1], (b as f64 / aim).ln().abs()];
            if b <= target {
                lo = (k, b);
                same_side = same_side.max(0) + 1;
            } else {
                hi = (k, b);
                same_side = same_side.min(0) - 1;
            }
        }
        // It ends on a file that fills the target as a search's must, below the jump.
        assert!(
            lo.1 <= target && lo.1 as f64 >= FILE_FILL * target as f64,
            "{lo:?}"
        );
        assert!(trials <= 6, "{trials} trials");
    }

    /// A one-sided step takes the slope its side showed where that is gentler than the model
    /// (floored at 0.3), else the model's.
    #[test]
    fn a_one_sided_step_takes_a_gentler_measured_slope() {
        let model = THRESHOLD_SIZE_SLOPE;
        assert_eq!(one_sided_slope(None, (1000, 900), model), model);
        // Sizes growing as K^0.5 between the two trials.
        let gentle = one_sided_slope(Some((1000, 900)), (4000, 1800), model);
        assert!((gentle - 0.5).abs() < 1e-9, "{gentle}");
        // Steeper than the model, flat, shrinking, or the same count: the model.
        assert_eq!(
            one_sided_slope(Some((1000, 900)), (2000, 2700), model),
            model
        );
        assert_eq!(
            one_sided_slope(Some((1000, 900)), (2000, 900), model),
            model
        );
        assert_eq!(
            one_sided_slope(Some((1000, 900)), (2000, 800), model),
            model
        );
        assert_eq!(
            one_sided_slope(Some((1000, 900)), (1000, 950), model),
            model
        );
        // Nearly flat: floored.
        assert_eq!(one_sided_slope(Some((1000, 900)), (8000, 910), model), 0.3);
        // From above (the trial before is the larger one): the same slope.
        let above = one_sided_slope(Some((4000, 1800)), (1000, 900), model);
        assert!((above - 0.5).abs() < 1e-9, "{above}");
    }
}
