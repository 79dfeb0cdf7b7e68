//! The working memory a compression needs, estimated before any is allocated, so a volume too
//! large for the cap is refused with the figure instead of running out of memory.

use super::options::{deepest_compared, default_levels, CompressError, CompressOptions, Target};
use super::rate::depth_candidates;
use wavesplat_codec::family::Family;
use wavesplat_codec::format::CoderKind;
use wavesplat_codec::layout::Geometry;

/// What [`memory_estimate`] counts once per process whatever the volume: the binary, the
/// thread pool and small tables (~30 MB measured on a 128³ volume). Compressing several
/// bricks at once needs it once, the rest of each brick's estimate per brick.
pub const PROCESS_MEMORY: u64 = 64 << 20;

/// The peak memory [`compress`] needs for a volume of `dims` × `channels` with `opts`, in bytes,
/// counting the input volume (f32 samples) and, per coefficient of the padded grid: the f64
/// transform of one channel (8 B), the f32 coefficients (4 B per channel), the band map (1 B)
/// and, with refinement, the padded targets, values, gradients and mask (13 B per channel)
/// plus two work arrays (8 B); then the candidate list and the encoder's per-coefficient
/// copies (~200 B per candidate). A byte target that compares depths holds two transforms at
/// once, on the grid of the deepest depth it may compare. Measured peaks stay below it
/// (BENCHMARKS.md, issue 14).
pub fn memory_estimate(
    dims: [usize; 3],
    channels: usize,
    opts: &CompressOptions,
) -> Result<(u64, String), CompressError> {
    // A byte target without a given depth compares two ([`depth_candidates`]) and may go
    // deeper than the default ([`deepest_compared`]), whose margin and padding make the
    // largest grid: the estimate takes that one.
    let comparing =
        matches!(opts.target, Target::Bytes(_)) && depth_candidates(dims, opts).len() > 1;
    let levels = match opts.levels {
        Some(m) => m,
        None if comparing => deepest_compared(dims, opts.family),
        None => default_levels(dims, opts.family),
    };
    // The larger grid of the two defaults (see `default_margin`): an upper bound.
    let margin = opts
        .margin
        .unwrap_or_else(|| Geometry::separating_margin(opts.family, levels));
    let g = Geometry::new(dims, opts.family, levels, margin)?;
    let n = g.coefficient_count() as u64;
    let v = dims.iter().map(|d| *d as u64).product::<u64>();
    let c = channels as u64;
    let input = 4 * v * c;
    // The colour transform's output, or an intensity volume's shifted copy (its offset).
    let colour = 4 * v * c;
    let refining = opts.refine.is_some() && opts.family != Family::Haar;
    // Held from the transform to the end: coefficients, band map, padded targets.
    let persistent = 4 * n * c + n + if refining { 4 * n * c } else { 0 };
    // A comparison holds two transforms while the second one is scored (without padded
    // targets; counted at the largest grid), and the scoring synthesizes one channel.
    let held = if comparing {
        persistent.max(2 * (4 * n * c + n) + 4 * n)
    } else {
        persistent
    };
    let all = n * c;
    let candidates = match opts.target {
        Target::Bytes(b) => b.saturating_mul(4).min(all),
        Target::Fraction(f) => ((2.0 * f * all as f64) as u64).min(all),
        Target::Coefficients(k) => k.saturating_mul(2).min(all),
        Target::All | Target::QvPercent(_) => all,
    };
    // Candidate lists of 24 B an entry held at once by a byte target's search: the oracle's
    // order, its grown copy, the refined order being tried and the best one so far (4 × 24 B),
    // plus the refined set's sorted (channel, index) pairs (8 B). Counting two lists instead
    // put the estimate 11 % under the measured peak of a 512³ volume (5.25 GB against 5.92).
    let lists = candidates.saturating_mul(104);
    let prepare = colour + 8 * n + (32 << 20);
    let refine = if refining { 9 * n * c + 8 * n } else { 0 };
    // Packet inputs, clustering items, reconstruction and Q_E pairs per kept coefficient; the
    // fast coder also holds every packet's symbols (8 B, about 1.3 per coefficient) while it
    // fits its tables.
    let per_kept = if opts.coder == CoderKind::Fast {
        161
    } else {
        150
    };
    let encode = (candidates / 2).saturating_mul(per_kept);
    let base = PROCESS_MEMORY;
    let total = base + input + held + prepare.max(lists + refine.max(encode));
    let detail = format!(
        "{} coefficients per channel on the padded {}x{}x{} grid, {} channel(s){}",
        n,
        g.padded[0],
        g.padded[1],
        g.padded[2],
        channels,
        if refining { ", refined" } else { "" }
    );
    Ok((total, detail))
}
