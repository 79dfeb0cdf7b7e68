//! The compression pipeline (paper Fig. 10): colour transform → 3D wavelet transform per channel
//! → oracle (score S = E·I, eq. 14; keep the most significant coefficients to meet a target) →
//! quality layers and tiles → significance order with spatial clustering → quantization and
//! entropy coding into packets (`wavesplat_codec::format`).
//!
//! Coefficients are never sorted wholesale: the oracle's order is materialised only for its top
//! candidates ([`crate::select`]). A byte target is met by a rate search on the number of kept
//! coefficients that measures the size the real encoder writes (the estimate is the written
//! size), interpolating log size against log count (typically 3–7 trial encodings); with
//! refinement, one refit of the oracle's set predicts the size of the set to refine, and the
//! refined set is topped up or cut to the target (a second or third refinement only when it
//! lands more than 3 % off, `rate::refine_to_bytes`). The encoder returns its own
//! reconstruction (the decoder's view of every kept coefficient), so callers can check a decode
//! bit for bit and compute Q_E without decoding.
//!
//! Its parts, each a module of its own: `options` (what is asked and returned), `prepare` (the
//! transform and the oracle), `encoder` (a prepared volume to a file), `memory` (the estimate
//! and cap) `rate` (the byte target: depth, refined set size, rate search), `summary` (the
//! scores summarised for a bricked allocation) and `top` (a score pass that keeps the top
//! coefficients, so that a brick is coded without being transformed again).

mod encoder;
mod memory;
mod options;
mod prepare;
mod rate;
mod summary;
mod top;

pub use memory::{memory_estimate, PROCESS_MEMORY};
pub use options::{
    deepest_compared, default_levels, CompressError, CompressOptions, CompressStats, Compressed,
    DepthSearch, Effort, Stage, StopFlag, Target, TileChoice, LAYER_GROWTH,
};
pub(crate) use prepare::axis_views;
pub(crate) use prepare::band_norms;
use prepare::{code, prepare};
pub use prepare::{default_margin, COARSE_LAYER_MIN_LEVELS, STRUCTURED_FACES};
pub use rate::worth_going_shallower;
pub(crate) use rate::SHALLOWER_KEPT;
use rate::{compress_to_bytes, expected_bytes};
pub use summary::{ScoreSummary, SummaryBytesError, SummedScores};
pub use top::{score_keeping_top, KeptTop, TopBytesError, TOP_DISK_SHARE};
use wavesplat_codec::volume::Volume;

/// Compresses a volume. `progress(stage, fraction)` is called as work proceeds. With the
/// options' [`StopFlag`] raised before it returns, it ends with [`CompressError::Stopped`]
/// (at the next stage: a stage under way finishes first).
pub fn compress(
    volume: &Volume,
    opts: &CompressOptions,
    progress: &(dyn Fn(Stage, f64) + Sync),
) -> Result<Compressed, CompressError> {
    let compressed = compress_counting(volume, opts, progress, CountFill::Exact)?;
    opts.stop.check()?;
    Ok(compressed)
}

/// How a refined count target (a count, a fraction, a Q_V) meets its count.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum CountFill {
    /// The count asked for: the set refined is grown by what a pilot refit keeps, and its
    /// survivors cut or topped up to the count ([`count_set_size`]). A user's target.
    Exact,
    /// The refined top of the count, less what the refit prunes: a brick's share of a bricked
    /// volume's byte target, whose rate search and its starting ratio count on the prune
    /// (`bricked::REFINED_PER_ORACLE`).
    Pruned,
}

/// [`compress`], with a count target met as `fill` says.
pub(crate) fn compress_counting(
    volume: &Volume,
    opts: &CompressOptions,
    progress: &(dyn Fn(Stage, f64) + Sync),
    fill: CountFill,
) -> Result<Compressed, CompressError> {
    let (needed, detail) = memory_estimate(volume.dims(), volume.channel_count(), opts)?;
    tracing::debug!(bytes = needed, detail, "memory estimate");
    if let Some(limit) = opts.memory_limit {
        if needed > limit {
            return Err(CompressError::MemoryLimit {
                needed,
                limit,
                detail,
            });
        }
    }
    check_layer_growth(opts)?;
    if let Target::Bytes(b) = opts.target {
        return compress_to_bytes(volume, opts, b, progress);
    }
    let coded = code(volume, opts, false, progress)?;
    let prepared = prepare(volume, opts, &coded, true, progress)?;
    drop(coded);
    let n = prepared.nonzero as usize;
    let k = match opts.target {
        Target::All => n,
        Target::Coefficients(c) => (c as usize).min(n),
        Target::Fraction(f) => {
            if !(f > 0.0 && f <= 1.0) {
                return Err(CompressError::InvalidOption(format!(
                    "target fraction {f}; allowed (0, 1]"
                )));
            }
            ((f * prepared.total_coefficients as f64).round() as usize).min(n)
        }
        Target::QvPercent(q) => {
            if !(q > 0.0 && q <= 100.0) {
                return Err(CompressError::InvalidOption(format!(
                    "target Q_V {q} %; allowed (0, 100]"
                )));
            }
            // Energies (without importance) accumulated in score order.
            let goal = q / 100.0 * prepared.selectable_energy;
            let cap = prepared.histogram.count_for_energy(goal) as usize;
            let ranked = prepared.ranked(cap);
            let mut acc = 0.0;
            let mut k = ranked.sorted.len();
            for (i, s) in ranked.sorted.iter().enumerate() {
                acc += (s.value as f64).powi(2)
                    * prepared.norms[prepared.band_of[s.index as usize] as usize];
                if acc >= goal * (1.0 - 1e-12) {
                    k = i + 1;
                    break;
                }
            }
            k
        }
        Target::Bytes(b) => return compress_to_bytes(volume, opts, b, progress),
    };
    opts.stop.check()?;
    let ranked = match &opts.refine {
        Some(r) if k > 0 && k < n && fill == CountFill::Pruned => {
            progress(Stage::Refine, 0.0);
            prepared.refined(&prepared.ranked(k), k, r, 0)
        }
        Some(r) if k > 0 && k < n => {
            progress(Stage::Refine, 0.0);
            // The prune drops the values whose refit scores fell below the set's smallest
            // score: a fifth of the set on MNI. A count is what the user asked for, so the
            // set refined is grown by what a pilot refit of the top k keeps, and its
            // survivors are cut to k or topped up by the few that would join them next
            // ([`count_set_size`]).
            let pilot = prepared.ranked(k);
            let survivors = prepared.pilot(&pilot, k, r);
            let grown = count_set_size(k, survivors, n);
            let ranked = if grown > k {
                prepared.ranked(grown)
            } else {
                pilot
            };
            let refined = prepared.refined(&ranked, grown, r, k.div_ceil(8));
            tracing::debug!(
                k,
                survivors,
                grown,
                refined = refined.refined,
                "a count target's refined set"
            );
            refined
        }
        _ => prepared.ranked(k),
    };
    let k = k.min(ranked.sorted.len());
    opts.stop.check()?;
    progress(Stage::Encode(0), 0.0);
    let expected = expected_bytes(k, opts.coder);
    Ok(prepared.encode(&ranked, k, opts, expected, true))
}

/// The size of the set a count target of `k` refines, where a pilot refit of the top `k` kept
/// `survivors` of them above their smallest score: grown by their share (not below half, as
/// [`rate::predicted_set_size`] trusts it), so that the refinement keeps about `k`.
fn count_set_size(k: usize, survivors: usize, n: usize) -> usize {
    let keep = (survivors as f64 / k.max(1) as f64).clamp(0.5, 1.0);
    ((k as f64 / keep).ceil() as usize).clamp(k, n.max(k))
}

/// Refuses a layer growth that is not a finite number above 1.
fn check_layer_growth(opts: &CompressOptions) -> Result<(), CompressError> {
    if !(opts.layer_growth.is_finite() && opts.layer_growth > 1.0) {
        return Err(CompressError::InvalidOption(format!(
            "layer growth {}; allowed: a finite number above 1",
            opts.layer_growth
        )));
    }
    Ok(())
}

/// The transform and the oracle's scores of `volume` under `opts` (its depth, family, colour
/// space and margin), without selecting or coding anything: the first pass of a bricked
/// volume's rate allocation.
pub fn score_summary(
    volume: &Volume,
    opts: &CompressOptions,
    progress: &(dyn Fn(Stage, f64) + Sync),
) -> Result<ScoreSummary, CompressError> {
    scored(volume, opts, progress).map(|(_, summary)| summary)
}

/// The prepared volume (transform and scores) of `volume` under `opts` and its score
/// summary: what [`score_summary`] and [`score_keeping_top`] share.
fn scored(
    volume: &Volume,
    opts: &CompressOptions,
    progress: &(dyn Fn(Stage, f64) + Sync),
) -> Result<(prepare::Prepared, ScoreSummary), CompressError> {
    let coded = code(volume, opts, false, progress)?;
    let prepared = prepare(volume, opts, &coded, false, progress)?;
    let summary = ScoreSummary::from_histogram(
        &prepared.histogram,
        prepared.total_coefficients,
        prepared.selectable_energy,
        prepared.nonzero,
    );
    Ok((prepared, summary))
}

#[cfg(test)]
mod tests {
    use super::prepare::{choose_tiling, AUTO_THREE_LAYERS_BYTES, AUTO_TWO_LAYERS_BYTES};
    use super::rate::{
        close_to_target, depth_candidates, next_set_size, predicted_depth, predicted_set_size,
        PILOT_KEEP, REFINED_SIZE_SLOPE,
    };
    use super::*;
    use crate::colorspace::face_activity;
    use crate::phantom::Phantom;
    use wavesplat_codec::family::Family;
    use wavesplat_codec::layout::Geometry;

    /// Automatic tiling keeps files below [`AUTO_TWO_LAYERS_BYTES`] to one quality layer, then
    /// two, then three; an explicit layer count always wins, and explicit tiles keep three.
    #[test]
    fn automatic_layers_follow_the_expected_size() {
        let g = Geometry::new([200, 230, 190], Family::Linear, 3, 0).unwrap();
        let layers = |choice, layers, bytes| choose_tiling(&g, choice, layers, bytes).1;
        for bytes in [0, 900, 9_000, 100_000, AUTO_TWO_LAYERS_BYTES - 1] {
            assert_eq!(layers(TileChoice::Auto, None, bytes), 1, "{bytes}");
        }
        assert_eq!(layers(TileChoice::Auto, None, AUTO_TWO_LAYERS_BYTES), 2);
        assert_eq!(
            layers(TileChoice::Auto, None, AUTO_THREE_LAYERS_BYTES - 1),
            2
        );
        assert_eq!(layers(TileChoice::Auto, None, AUTO_THREE_LAYERS_BYTES), 3);
        assert_eq!(layers(TileChoice::Auto, None, u64::MAX), 3);
        assert_eq!(layers(TileChoice::Auto, Some(4), 900), 4);
        assert_eq!(layers(TileChoice::Size(64), None, 900), 3);
        assert_eq!(layers(TileChoice::Single, None, 1 << 30), 1);
    }

    /// Volumes whose faces are flat (zero, a constant, an offset head, the RGB phantom's black
    /// background) get the separating margin; slabs cut through a head or a body get none; an
    /// explicit margin always wins.
    #[test]
    fn the_default_margin_follows_what_the_faces_carry() {
        let sep = Geometry::separating_margin(Family::Linear, 3);
        let flat = [
            Phantom::SheppLogan.generate([40, 36, 30]),
            Phantom::Zero.generate([16, 16, 16]),
            Phantom::Constant(-1000.0).generate([16, 8, 4]),
            Phantom::RgbHead.generate([24, 24, 24]),
        ];
        for v in &flat {
            assert_eq!(default_margin(v, Family::Linear, 3), sep, "{:?}", v.dims());
        }
        // Every 8th slice of a Shepp–Logan head, then 8 slices through its middle: faces cut
        // through the head.
        let head = Phantom::SheppLogan.generate([48, 48, 48]);
        let slab: Vec<f32> = head.channel(0)[48 * 48 * 20..48 * 48 * 28].to_vec();
        let slab = Volume::new([48, 48, 8], [1.0; 3], vec![slab]).unwrap();
        assert!(face_activity(slab.channel(0), slab.dims()) > STRUCTURED_FACES);
        assert_eq!(default_margin(&slab, Family::Linear, 3), 0);
        assert_eq!(
            default_margin(&Phantom::Ct.generate([40, 32, 24]), Family::Cubic, 2),
            0
        );
        let explicit = CompressOptions {
            margin: Some(5),
            target: Target::Fraction(0.2),
            ..Default::default()
        };
        let c = compress(&slab, &explicit, &|_, _| {}).unwrap();
        assert_eq!(c.header.margin, 5);
        let c = compress(&slab, &CompressOptions::default(), &|_, _| {}).unwrap();
        assert_eq!(c.header.margin, 0);
    }

    #[test]
    fn a_refined_set_close_to_the_target_ends_the_search() {
        let t = 100_000;
        assert!(close_to_target(t, t));
        assert!(close_to_target(97_000, t) && close_to_target(103_000, t));
        assert!(!close_to_target(96_999, t) && !close_to_target(103_001, t));
        assert!(!close_to_target(0, t));
    }

    #[test]
    fn a_byte_target_compares_the_default_depth_with_one_less_unless_given() {
        let bytes = |levels| CompressOptions {
            target: Target::Bytes(1000),
            levels,
            ..Default::default()
        };
        assert_eq!(depth_candidates([64, 64, 64], &bytes(None)), vec![3, 2]);
        assert_eq!(depth_candidates([64, 64, 64], &bytes(Some(4))), vec![4]);
        // Two slices allow one level: nothing shallower to try.
        assert_eq!(depth_candidates([64, 64, 2], &bytes(None)), vec![1]);
        assert_eq!(depth_candidates([1, 1, 40], &bytes(None)), vec![0]);
        let cubic = CompressOptions {
            family: Family::Cubic,
            ..bytes(None)
        };
        assert_eq!(depth_candidates([64, 64, 64], &cubic), vec![2, 1]);
        // Comparing holds two transforms: the estimate covers them.
        let (one, _) = memory_estimate([64, 64, 64], 1, &bytes(Some(3))).unwrap();
        let (two, _) = memory_estimate([64, 64, 64], 1, &bytes(None)).unwrap();
        assert!(two > one, "{two} <= {one}");
    }

    /// A predicted depth (the fast effort) tries no second depth: the default one where the
    /// file cannot afford a shallower coarse band, shallower where it can, as the comparison
    /// would go; a given depth is kept as given.
    #[test]
    fn a_predicted_depth_goes_shallower_only_where_the_file_affords_it() {
        let v = crate::phantom::Phantom::SheppLogan.generate([32, 32, 32]);
        let levels = |bytes: u64, given: Option<usize>| {
            let o = CompressOptions {
                target: Target::Bytes(bytes),
                levels: given,
                ..Effort::Fast.options()
            };
            assert_eq!(depth_candidates([32, 32, 32], &o), vec![given.unwrap_or(3)]);
            let c = compress(&v, &o, &|_, _| {}).unwrap();
            assert!(c.stats.bytes <= bytes);
            c.header.geometry.levels
        };
        assert_eq!(levels(1_000, None), 3);
        let high = levels(40_000, None);
        assert!(high < 3, "{high}");
        assert_eq!(levels(40_000, Some(3)), 3);
    }

    /// The fast effort refines one set per byte target: its file fills the target as the
    /// unrefined one does (98 % or more, never over) and reconstructs the volume better at
    /// those bytes, on smooth and noisy content, one channel and three, linear and cubic. The
    /// errors are the decoder's (the file's own coefficients, synthesised in f64).
    #[test]
    fn the_fast_effort_refines_one_set_and_draws_better_at_equal_bytes() {
        let error2 = |v: &Volume, c: &Compressed| -> f64 {
            let coefficients: Vec<_> = c.reconstruction.concat();
            let d = crate::decode::reconstruct(&c.header, &coefficients).unwrap();
            (0..v.channel_count())
                .map(|ch| {
                    v.channel(ch)
                        .iter()
                        .zip(d.channel(ch))
                        .map(|(a, b)| (*a as f64 - *b as f64).powi(2))
                        .sum::<f64>()
                })
                .sum()
        };
        for (name, v, family) in [
            (
                "shepp",
                Phantom::SheppLogan.generate([40, 36, 32]),
                Family::Linear,
            ),
            ("ct", Phantom::Ct.generate([36, 30, 21]), Family::Cubic),
            (
                "rgb",
                Phantom::RgbHead.generate([32, 28, 24]),
                Family::Linear,
            ),
        ] {
            for bytes in [1_500, 6_000] {
                let run = |refine: Option<crate::refine::RefineOptions>| {
                    let o = CompressOptions {
                        target: Target::Bytes(bytes),
                        family,
                        refine,
                        ..Effort::Fast.options()
                    };
                    compress(&v, &o, &|_, _| {}).unwrap()
                };
                let fast = run(Effort::Fast.refine());
                let plain = run(None);
                assert!(fast.stats.refined && !plain.stats.refined, "{name} {bytes}");
                for c in [&fast, &plain] {
                    assert!(c.stats.bytes <= bytes, "{name} {bytes}: {}", c.stats.bytes);
                }
                assert!(
                    fast.stats.bytes as f64 >= 0.98 * bytes as f64,
                    "{name} {bytes}: {}",
                    fast.stats.bytes
                );
                let gain = 10.0 * (error2(&v, &plain) / error2(&v, &fast)).log10();
                assert!(gain > 0.1, "{name} {bytes}: {gain:.2} dB");
            }
        }
    }

    /// Samples near ±f32::MAX give coarse coefficients beyond f32: compressing them is refused
    /// with a typed error naming the samples' magnitude (it used to write a file whose header
    /// no reader took), at every target and effort; samples a little smaller still compress
    /// to a file that decodes to finite values.
    #[test]
    fn coefficients_beyond_f32_are_refused_not_written() {
        let dims = [11, 10, 9];
        let noise = |scale: f32| {
            let mut state = 0x2545_f491_4f6c_dd1d_u64;
            let samples: Vec<f32> = (0..dims.iter().product::<usize>())
                .map(|_| {
                    state = state
                        .wrapping_mul(6_364_136_223_846_793_005)
                        .wrapping_add(1);
                    ((state >> 40) as f32 / (1u64 << 24) as f32 * 2.0 - 1.0) * scale
                })
                .collect();
            Volume::new(dims, [1.0; 3], vec![samples]).unwrap()
        };
        let huge = noise(3.0e38);
        for opts in [
            Effort::Fast.options(),
            Effort::Default.options(),
            CompressOptions {
                target: Target::All,
                ..Effort::Fast.options()
            },
        ] {
            let opts = CompressOptions {
                target: match opts.target {
                    Target::All => Target::All,
                    _ => Target::Bytes(3_000),
                },
                ..opts
            };
            match compress(&huge, &opts, &|_, _| {}) {
                Err(CompressError::CoefficientOverflow { largest }) => {
                    assert!(largest > 2.9e38 && largest.is_finite(), "{largest}")
                }
                other => panic!("{:?}", other.map(|c| c.stats.bytes)),
            }
        }
        let large = noise(1.0e36);
        let c = compress(
            &large,
            &CompressOptions {
                target: Target::Bytes(3_000),
                ..Effort::Fast.options()
            },
            &|_, _| {},
        )
        .unwrap();
        let d = crate::decode::decompress(&c.bytes).unwrap();
        assert!(d.channel(0).iter().all(|v| v.is_finite()));
    }

    /// The fast effort's depth, guessed from the target's bytes or from one probe of the
    /// default depth, is the depth its rule gives from the full search's count at each depth
    /// (searched one depth at a time, as before the shortcuts), on smooth data (few bits per
    /// coefficient), on colour, and on noise (many bits per coefficient: a depth guessed from
    /// the bytes comes out too shallow and is searched one level deeper); targets where the
    /// count lands within a quarter of the rule's threshold are left out (there a probe and
    /// the full search may fall either side). Each file fits its target.
    #[test]
    fn the_fast_effort_predicts_the_depth_the_full_search_rule_gives() {
        let rule = |v: &Volume, bytes: u64| -> Option<usize> {
            let mut m = default_levels(v.dims(), Family::Linear);
            loop {
                let o = CompressOptions {
                    target: Target::Bytes(bytes),
                    levels: Some(m),
                    ..Effort::Fast.options()
                };
                let c = compress(v, &o, &|_, _| {}).ok()?;
                let g = &c.header.geometry;
                let channels = v.channel_count();
                if m >= 2 {
                    let coarse = g.coefficient_count() as f64 / 8f64.powi(m as i32 - 1);
                    let ratio = c.stats.kept as f64
                        / channels as f64
                        / (super::rate::SHALLOWER_KEPT * coarse);
                    if ratio > 0.75 && ratio < 1.33 {
                        return None;
                    }
                }
                let to = predicted_depth(c.stats.kept, channels, g);
                if to >= m {
                    return Some(m);
                }
                m = to;
            }
        };
        let mut compared = 0;
        for (name, v) in [
            ("shepp", Phantom::SheppLogan.generate([40, 36, 32])),
            ("rgb", Phantom::RgbHead.generate([32, 32, 32])),
            ("noise", Phantom::Noise { seed: 3 }.generate([32, 32, 32])),
        ] {
            for bytes in [400, 1_500, 4_000, 9_000, 20_000, 45_000] {
                let Some(want) = rule(&v, bytes) else {
                    continue;
                };
                let o = CompressOptions {
                    target: Target::Bytes(bytes),
                    ..Effort::Fast.options()
                };
                let c = compress(&v, &o, &|_, _| {}).unwrap();
                assert!(c.stats.bytes <= bytes, "{name} {bytes}: {}", c.stats.bytes);
                assert_eq!(c.header.geometry.levels, want, "{name} at {bytes} bytes");
                compared += 1;
            }
        }
        assert!(compared >= 10, "{compared} targets compared");
    }

    /// The first refined-set size falls back to the oracle's when the pilot tells nothing,
    /// grows as fewer of the oracle's set survive its refit (at most 2×) and as the target
    /// grows against the oracle's file, inverts its own size model, and stays within the
    /// non-zero count.
    #[test]
    fn the_first_refined_set_size_follows_the_pilots_survivors() {
        let n = 1_000_000;
        assert_eq!(predicted_set_size(1000, 0, 900, 1000, n), 1000);
        assert_eq!(predicted_set_size(1000, 1000, 0, 1000, n), 1000);
        assert_eq!(predicted_set_size(0, 1000, 0, 1000, n), 1);
        let all_survive = predicted_set_size(1000, 1000, 1000, 1000, n);
        assert_eq!(all_survive, (1000.0 / PILOT_KEEP).round() as usize);
        let fewer = predicted_set_size(1000, 1000, 800, 1000, n);
        assert!(fewer > all_survive, "{fewer} <= {all_survive}");
        let larger_target = predicted_set_size(1000, 1000, 800, 1100, n);
        assert!(larger_target > fewer, "{larger_target} <= {fewer}");
        let kept = PILOT_KEEP * 0.8 * larger_target as f64;
        let bytes = 1000.0 * (kept / 1000.0).powf(REFINED_SIZE_SLOPE);
        assert!((bytes / 1100.0 - 1.0).abs() < 0.005, "{bytes}");
        // A pilot keeping almost nothing is trusted only down to half.
        assert_eq!(predicted_set_size(1000, 1000, 10, 1000, n), 2000);
        assert_eq!(predicted_set_size(1000, 1000, 800, 1000, 1100), 1100);
    }

    #[test]
    fn the_set_size_search_steps_towards_the_goal_and_never_repeats_a_size() {
        let n = 1_000_000;
        // One set below the goal: grow K by the byte ratio (slope 1), at least by one.
        assert!((1250..=1251).contains(&next_set_size(&[(1000, 800)], 1000.0, n)));
        assert_eq!(next_set_size(&[(1000, 999)], 1000.0, n), 1002);
        // One above: shrink, never to the same K or below 1.
        assert!((499..=500).contains(&next_set_size(&[(1000, 2000)], 1000.0, n)));
        assert_eq!(next_set_size(&[(1, 5000)], 1000.0, n), 1);
        // A bracket: the secant on log–log lands strictly inside it.
        let k = next_set_size(&[(1000, 800), (2000, 1600)], 1000.0, n);
        assert!((1249..=1251).contains(&k), "{k}");
        let k = next_set_size(&[(1000, 900), (1010, 1100)], 1000.0, n);
        assert!(k > 1000 && k < 1010, "{k}");
        // Adjacent sizes leave nothing between them: the lower one is returned (already tried,
        // which ends the search).
        assert_eq!(next_set_size(&[(1000, 900), (1001, 1100)], 1000.0, n), 1000);
        // Never beyond the candidates.
        assert_eq!(next_set_size(&[(900_000, 100)], 1000.0, n), n);
    }
}
