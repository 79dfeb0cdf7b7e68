//! The quantizers. The paper's (eq. 15–17), `Chain`: per substream (channel, level, type) the magnitudes, in
//! coding order, are coded as integer steps δ of the delta factor Δ from the previous
//! *reconstructed* magnitude (closed loop, so errors do not accumulate down the sequence).
//!
//! The chain accumulates the integer sum K of the steps and reconstructs |w̃| = start − K·Δ, so
//! encoder and decoder agree bit for bit. Steps are signed, because spatial clustering breaks the
//! monotone order. Δ = 0 (a single coefficient, or equal magnitudes) codes every step as 0.
//!
//! The threshold quantizer of the sigmap and fast coders, `Quantizer`: uniform steps above a
//! substream's lower magnitude bound in a layer, capped by its upper one.

use super::{invalid, FormatError, Header};

/// Largest |K| a chain may reach (keeps start − K·Δ exact in the integer part).
const MAX_STEPS: i64 = 1 << 52;

/// Δ of eq. 15: the largest gap between consecutive magnitudes of a significance-sorted
/// sequence, divided by 2^P. `magnitudes` may be in any order; the gaps are taken after sorting
/// them in decreasing order.
pub fn delta_factor(magnitudes: &[f64], bits: u8) -> f64 {
    let mut m: Vec<f64> = magnitudes.iter().map(|v| v.abs()).collect();
    m.sort_by(|a, b| b.total_cmp(a));
    let gap = m.windows(2).map(|w| w[0] - w[1]).fold(0.0, f64::max);
    gap / 2f64.powi(bits as i32)
}

/// A closed-loop delta chain for one substream within one packet.
#[derive(Debug, Clone)]
pub struct Chain {
    start: f64,
    delta: f64,
    steps: i64,
}

impl Chain {
    /// A chain starting at magnitude `start` with delta factor `delta`.
    pub fn new(start: f64, delta: f64) -> Chain {
        Chain {
            start,
            delta,
            steps: 0,
        }
    }

    fn value(&self) -> f64 {
        self.start - self.steps as f64 * self.delta
    }

    /// Quantizes `magnitude`: returns the step δ to transmit and the reconstructed magnitude.
    pub fn encode(&mut self, magnitude: f64) -> (i64, f64) {
        if self.delta <= 0.0 {
            return (0, self.value());
        }
        let target = ((self.start - magnitude) / self.delta).round();
        let target = target.clamp(-(MAX_STEPS as f64), MAX_STEPS as f64) as i64;
        let step = target - self.steps;
        self.steps = target;
        (step, self.value())
    }

    /// Applies a received step δ; returns the reconstructed magnitude.
    pub fn decode(&mut self, step: i64) -> Result<f64, FormatError> {
        if self.delta <= 0.0 && step != 0 {
            return Err(invalid("packet", "non-zero step in a substream with Δ = 0"));
        }
        let next = self
            .steps
            .checked_add(step)
            .filter(|s| s.abs() <= MAX_STEPS)
            .ok_or_else(|| invalid("packet", "quantization step out of range"))?;
        self.steps = next;
        Ok(self.value())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn closed_loop_error_stays_below_half_delta() {
        let mags: Vec<f64> = (0..1000)
            .map(|i| 100.0 * (-(i as f64) / 150.0).exp())
            .collect();
        for bits in [1u8, 3, 8, 16] {
            let d = delta_factor(&mags, bits);
            let mut enc = Chain::new(mags[0], d);
            let mut dec = Chain::new(mags[0], d);
            for m in &mags {
                let (step, rec) = enc.encode(*m);
                assert!((rec - m).abs() <= 0.5 * d + 1e-9, "P={bits}: {rec} vs {m}");
                assert_eq!(dec.decode(step).unwrap(), rec);
            }
        }
    }

    #[test]
    fn zero_delta_and_garbage_steps() {
        assert_eq!(delta_factor(&[5.0], 3), 0.0);
        assert_eq!(delta_factor(&[5.0, 5.0, 5.0], 3), 0.0);
        let mut c = Chain::new(5.0, 0.0);
        assert_eq!(c.encode(5.0), (0, 5.0));
        assert!(c.decode(1).is_err());
        let mut c = Chain::new(1.0, 1e-3);
        assert!(c.decode(i64::MAX).is_err());
        assert!(c.decode(MAX_STEPS + 1).is_err());
    }
}

/// A substream's magnitude quantizer in one layer: lower and upper magnitude bounds and step.
/// The upper bound (the layer's score bound, at most the substream's largest magnitude w0)
/// caps reconstructions, so magnitudes that all sit within one step of the lower bound (a
/// single coefficient, such as a constant volume's one scaling coefficient) come back as w0
/// rather than lb + Δ/2, which is 1.5 × their value when Δ = lb, as lossless selection at the
/// default step has it. Shared by the sigmap and fast coders.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Quantizer {
    lb: f64,
    /// Largest magnitude the substream can have in this layer (≥ lb).
    ub: f64,
    step: f64,
}

impl Quantizer {
    /// The quantizer of substream `sub` in `layer`.
    pub(crate) fn of(header: &Header, sub: usize, layer: usize) -> Quantizer {
        let params = header.substreams[sub].expect("present substream");
        // The coarse layer holds its band's coefficients of every score: down to the threshold.
        let lb = if layer + 1 < header.layer_bounds.len() && !(header.coarse_layer && layer == 0) {
            header.chain_start(sub, layer + 1)
        } else {
            header.magnitude_threshold(sub)
        };
        // A layer below whose bound is +∞ (empty layers have such bounds) says nothing about
        // this one's lower bound, and nor does a cap the file does not send (w₀ = +∞, which
        // `chain_start` then returns): the substream's smallest magnitude is the bound.
        let lb = if lb.is_finite() {
            lb
        } else {
            header.magnitude_threshold(sub)
        };
        let lb = lb.max(0.0);
        let ub = header.chain_start(sub, layer).max(lb);
        Quantizer {
            lb,
            ub,
            step: params.delta as f64,
        }
    }

    /// The magnitude of step q: the middle of its interval, within the substream's bounds.
    #[inline]
    fn reconstruct(&self, q: u64) -> f64 {
        (self.lb + (q as f64 + 0.5) * self.step).min(self.ub)
    }

    /// The step of a magnitude and its reconstruction (the exact f32 bits when Δ = 0).
    pub(crate) fn quantize(&self, magnitude: f64) -> (u64, f64) {
        if self.step > 0.0 {
            let q = ((magnitude - self.lb) / self.step).floor().clamp(0.0, 1e15) as u64;
            (q, self.reconstruct(q))
        } else {
            ((magnitude as f32).to_bits() as u64, magnitude as f32 as f64)
        }
    }

    /// The value of a decoded step and sign, refusing steps no encoder writes and values
    /// that are not finite.
    #[inline(always)]
    pub(crate) fn signed_value(&self, q: u64, negative: bool) -> Result<f32, FormatError> {
        // The reason travels as a `&'static str` and the error is built out of line: a
        // `FormatError` carried through every call kept this from inlining in the decoders'
        // loops (41 instructions a coefficient, 8 % of the fast decoder's).
        let magnitude = self.magnitude(q).map_err(refused)?;
        // −magnitude, by flipping the sign bit as negation does, without a branch on the sign
        // (as unpredictable as the data).
        let value = f64::from_bits(magnitude.to_bits() ^ (u64::from(negative) << 63)) as f32;
        if value.is_finite() {
            Ok(value)
        } else {
            Err(refused("decoded value is not finite"))
        }
    }

    /// The magnitude of a decoded step, or why no encoder writes that step.
    #[inline(always)]
    fn magnitude(&self, q: u64) -> Result<f64, &'static str> {
        if self.step > 0.0 {
            if q > 1_000_000_000_000_000 {
                return Err("quantized magnitude out of range");
            }
            Ok(self.reconstruct(q))
        } else {
            let bits = u32::try_from(q).map_err(|_| "exact magnitude out of range")?;
            Ok(f32::from_bits(bits) as f64)
        }
    }
}

/// A packet's step refused by [`Quantizer::signed_value`], for `why`.
#[cold]
#[inline(never)]
fn refused(why: &'static str) -> FormatError {
    invalid("packet", why)
}
