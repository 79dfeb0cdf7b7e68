//! The priority queue of a session: coefficients bucketed by half-octaves of the visible
//! energy the current view gives them (w²·‖basis‖² × band-and-tile visibility × channel
//! importance), a held packet's coefficients queued for the view, and what waited for its
//! depth-cue tables queued again once they arrive.

use super::bricks::Bricks;
use super::{Held, RenderSession};
use crate::backend::AccumulationBackend;
use wavesplat_codec::format::packet::Coefficient;
use wavesplat_codec::format::Header;
use wavesplat_codec::layout::Band;
use wavesplat_codec::view::visibility::Visibility;

/// Bucket queue: half-octaves of visible energy.
const BUCKETS: usize = 4400;
const BUCKET_OFFSET: i64 = 2200;

#[derive(Debug, Default)]
pub(super) struct BucketQueue {
    buckets: Vec<Vec<(u32, u32)>>,
    top: usize,
    pub(super) len: usize,
}

impl BucketQueue {
    pub(super) fn new() -> BucketQueue {
        BucketQueue {
            buckets: vec![Vec::new(); BUCKETS],
            top: 0,
            len: 0,
        }
    }

    pub(super) fn clear(&mut self) {
        for b in &mut self.buckets[..=self.top] {
            b.clear();
        }
        self.top = 0;
        self.len = 0;
    }

    pub(super) fn push(&mut self, bucket: usize, entry: (u32, u32)) {
        self.buckets[bucket].push(entry);
        self.top = self.top.max(bucket);
        self.len += 1;
    }

    /// Entries, highest buckets first, until their summed `weight` reaches `allowance` (at
    /// least `min` entries, at most `max`); returns the weight taken.
    pub(super) fn pop_weighted(
        &mut self,
        allowance: f64,
        (min, max): (usize, usize),
        mut weight: impl FnMut((u32, u32)) -> f64,
        out: &mut Vec<(u32, u32)>,
    ) -> f64 {
        out.clear();
        let mut taken = 0.0;
        while self.len > 0 && out.len() < max && (out.len() < min || taken < allowance) {
            let b = &mut self.buckets[self.top];
            if let Some(e) = b.pop() {
                taken += weight(e);
                out.push(e);
                self.len -= 1;
            }
            if b.is_empty() && self.top > 0 {
                while self.top > 0 && self.buckets[self.top].is_empty() {
                    self.top -= 1;
                }
            }
        }
        taken
    }
}

/// A coefficient's visible energy from its squared value and its band's (energy scale,
/// visibility weight), multiplied in that order.
#[inline]
fn energy(c: &Coefficient, (scale, weight): (f64, f64)) -> f64 {
    let v = c.value as f64;
    v * v * scale * weight
}

/// The queue bucket of a visible energy; `None` when the view cannot see it.
#[inline]
fn bucket_of(energy: f64) -> Option<usize> {
    if energy.is_nan() || energy <= 0.0 {
        return None;
    }
    if energy.is_infinite() {
        return Some(BUCKETS - 1);
    }
    Some((half_octave(energy) + BUCKET_OFFSET).clamp(0, BUCKETS as i64 - 1) as usize)
}

/// ⌊2·log2 x⌋ of a positive finite `x`, from its bits: twice the binary exponent, plus one
/// when the mantissa is at least √2. Requeuing a view's coefficients takes one per coefficient,
/// and `log2` and `floor` are library calls on the baseline x86-64 target (they were 40 % of a
/// 565 k-coefficient requeue). Subnormals take the `log2` path.
#[inline]
fn half_octave(x: f64) -> i64 {
    let bits = x.to_bits();
    let biased = ((bits >> 52) & 0x7ff) as i64;
    if biased == 0 {
        return (2.0 * x.log2()).floor() as i64;
    }
    let mantissa = f64::from_bits((bits & ((1u64 << 52) - 1)) | (1023u64 << 52));
    2 * (biased - 1023) + i64::from(mantissa >= std::f64::consts::SQRT_2)
}

/// What weighs the coefficients of one packet in the current view: its volume's (or brick's)
/// band indices, energy scales and visibility, and a factor for all (a brick's cue factor²).
pub(super) struct Lens<'a> {
    geometry: &'a wavesplat_codec::layout::Geometry,
    energy_scale: &'a [f64],
    visibility: &'a Visibility,
    factor: f64,
}

impl Lens<'_> {
    /// The energy scale of `c`'s channel and band (times the lens's factor) and the view's
    /// visibility weight of its band in tile `tile`: what `energy` multiplies its squared
    /// value by; `None` for a band the volume does not have.
    fn factors(&self, c: &Coefficient, tile: usize) -> Option<(f64, f64)> {
        let b = self.geometry.band_index(c.band)?;
        let nb = self.geometry.band_count();
        Some((
            self.energy_scale[c.channel as usize * nb + b] * self.factor,
            self.visibility.weight(c.band, tile),
        ))
    }
}

/// The lens of packet `id` (`None`: the view sees nothing of it: its brick is off the image,
/// or no brick has it); the session's fields are passed one by one so that its queue can be
/// changed while the lens is held.
pub(super) fn lens_of<'a>(
    header: &'a Header,
    energy_scale: &'a [f64],
    visibility: Option<&'a Visibility>,
    bricks: Option<&'a Bricks>,
    id: u32,
) -> Option<Lens<'a>> {
    match bricks {
        None => Some(Lens {
            geometry: &header.geometry,
            energy_scale,
            visibility: visibility?,
            factor: 1.0,
        }),
        Some(b) => {
            let part = &b.parts[b.part_of(id)?];
            let view = part.view.as_ref()?;
            let cue = f64::from(view.cue_scale);
            Some(Lens {
                geometry: &part.header.geometry,
                energy_scale: &part.energy_scale,
                visibility: &view.visibility,
                factor: cue * cue,
            })
        }
    }
}

impl<B: AccumulationBackend> RenderSession<B> {
    /// The lens of packet `id` in the current view.
    fn lens(&self, id: u32) -> Option<Lens<'_>> {
        lens_of(
            &self.header,
            &self.energy_scale,
            self.visibility.as_ref(),
            self.bricks.as_ref(),
            id,
        )
    }

    /// The energy coefficient `c` of packet `id` of tile `tile` shows in the current view
    /// (what orders the queue and eviction); `None` for a band the volume does not have, or a
    /// packet the view sees nothing of.
    pub(super) fn visible_energy(&self, id: u32, c: &Coefficient, tile: usize) -> Option<f64> {
        self.lens(id)?.factors(c, tile).map(|f| energy(c, f))
    }

    /// Queues the visible coefficients of a held packet for the current view, and sums their
    /// visible energy (`Held::visible`).
    pub(super) fn enqueue(&mut self, id: u32, held: &mut Held) {
        held.queued = 0;
        held.visible = 0.0;
        let Some(lens) = lens_of(
            &self.header,
            &self.energy_scale,
            self.visibility.as_ref(),
            self.bricks.as_ref(),
            id,
        ) else {
            self.stats.invisible_in_view += held.coefficients.len() as u64;
            return;
        };
        // A packet's coefficients come substream by substream (channel, band): the factors of
        // `visible_energy` are looked up once per run of them.
        let mut run: Option<((u8, Band), (f64, f64))> = None;
        for (i, c) in held.coefficients.iter().enumerate() {
            let factors = match run {
                Some((key, factors)) if key == (c.channel, c.band) => factors,
                _ => {
                    let Some(factors) = lens.factors(c, held.tile) else {
                        continue;
                    };
                    run = Some(((c.channel, c.band), factors));
                    factors
                }
            };
            let e = energy(c, factors);
            held.visible += e;
            match bucket_of(e) {
                Some(k) => {
                    self.queue.push(k, (id, i as u32));
                    held.queued += 1;
                }
                None => self.stats.invisible_in_view += 1,
            }
        }
    }

    /// Installs the depth-cue tables the plan's builder finished and queues again what waited
    /// for them (what still misses a table is set aside again by the next batch).
    pub(super) fn poll_cue_tables(&mut self) {
        let (mut arrived, mut pending) = (0, false);
        for plan in self.plans_mut() {
            arrived += plan.poll_tables();
            pending |= plan.tables_pending();
        }
        if arrived == 0 && (self.waiting.is_empty() || pending) {
            return;
        }
        for (id, i) in std::mem::take(&mut self.waiting) {
            let Some(held) = self.packets.get(&id) else {
                continue;
            };
            let bucket = self
                .visible_energy(id, &held.coefficients[i as usize], held.tile)
                .and_then(bucket_of);
            // It was visible when queued; the same view sees it the same way.
            self.queue.push(bucket.unwrap_or(0), (id, i));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The bit-level ⌊2·log2 x⌋ against libm's `log2` over powers of two (exact there), a
    /// pseudo-random sweep of positive numbers, subnormals and the extremes; values within 1e-9
    /// of a boundary (x = 2^k or √2·2^k), where `log2`'s own rounding decides, are skipped.
    #[test]
    fn half_octaves_from_bits_equal_the_floor_of_twice_log2() {
        let reference = |x: f64| (2.0 * x.log2()).floor() as i64;
        for k in -1074..=1023 {
            let x = if k >= -1022 {
                f64::from_bits(((k + 1023) as u64) << 52)
            } else {
                f64::from_bits(1u64 << (k + 1074))
            };
            assert_eq!(half_octave(x), 2 * i64::from(k), "2^{k}");
        }
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        let mut checked = 0;
        for _ in 0..200_000 {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            let x = f64::from_bits(state >> 1);
            if !x.is_finite() || x <= 0.0 {
                continue;
            }
            // Near a boundary of ⌊2·log2 x⌋ (x = 2^k or √2·2^k) the reference's rounding decides.
            let h = 2.0 * x.log2();
            if ((h - h.floor()) - 0.0).abs() < 1e-9 || (h.floor() + 1.0 - h).abs() < 1e-9 {
                continue;
            }
            assert_eq!(half_octave(x), reference(x), "{x:e}");
            checked += 1;
        }
        assert!(checked > 100_000);
        for x in [
            f64::MIN_POSITIVE,
            f64::MIN_POSITIVE / 3.0,
            5e-324,
            1.0,
            1.5,
            std::f64::consts::SQRT_2 * (1.0 - 1e-6),
            std::f64::consts::SQRT_2 * (1.0 + 1e-6),
            0.7,
            3.0,
        ] {
            assert_eq!(half_octave(x), reference(x), "{x:e}");
        }
        // log2(f64::MAX) rounds up to 1024: the bits give the true ⌊2·log2⌋ = 2·1023 + 1.
        assert_eq!(half_octave(f64::MAX), 2047);
        assert_eq!(bucket_of(0.0), None);
        assert_eq!(bucket_of(f64::NAN), None);
        assert_eq!(bucket_of(f64::INFINITY), Some(BUCKETS - 1));
        assert_eq!(bucket_of(1.0), Some(BUCKET_OFFSET as usize));
    }
}
