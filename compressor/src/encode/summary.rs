//! The oracle's scores of a volume, summarised for a bricked rate allocation: this module owns
//! [`ScoreSummary`] (one brick's or one volume's, sparse, and its bytes on the wire) and
//! [`SummedScores`] (their sum, dense, from which the one global threshold is chosen).
//!
//! A summary counts coefficients (and sums their energy) per absolute score bin
//! ([`crate::select::Histogram`]'s 65 536 bins, 256 per halving of the score), the same for
//! every volume, so that summaries of several volumes (the bricks of one) add up to what the
//! oracle would see for the whole. A brick's scores fill a few thousand to a few tens of
//! thousands of those bins, and the planner holds one summary per brick, so a summary keeps
//! only its filled bins, as varints (~3–4 bytes a bin against the dense form's 8): 512 kB a
//! brick dense would be 17 GB for the 32 768 bricks of an 8192³ volume in 256³ bricks.

use crate::select::Histogram;

/// One volume's (or brick's) score histogram, its filled bins only.
#[derive(Debug, Clone, PartialEq)]
pub struct ScoreSummary {
    /// Filled bins in ascending order, each as two varints: the empty bins skipped since the
    /// previous filled one (since bin 0 for the first), and its count.
    filled: Vec<u8>,
    /// Filled bins.
    bins: usize,
    /// Energy per filled bin (same order), or empty when not kept (only a Q_V target needs
    /// them).
    energies: Vec<f64>,
    /// Coefficients of the padded grid, all channels.
    pub total_coefficients: u64,
    /// Energy of the coefficients the oracle may keep (without importance): all of them but
    /// a bridge's wholly outside the box.
    pub total_energy: f64,
    /// Selectable (non-zero) coefficients.
    pub nonzero: u64,
    /// Coefficients counted in the bins.
    positive: u64,
}

impl ScoreSummary {
    /// The summary of a dense histogram and the volume's totals.
    pub(crate) fn from_histogram(
        histogram: &Histogram,
        total_coefficients: u64,
        total_energy: f64,
        nonzero: u64,
    ) -> ScoreSummary {
        let (counts, energies) = (histogram.counts(), histogram.energies());
        let mut s = ScoreSummary {
            filled: Vec::new(),
            bins: 0,
            energies: Vec::new(),
            total_coefficients,
            total_energy,
            nonzero,
            positive: histogram.positive,
        };
        let mut next = 0usize;
        for b in 0..counts.len() {
            let e = energies.get(b).copied();
            if counts[b] != 0 || e.is_some_and(|e| e != 0.0) {
                s.push_bin(b - next, counts[b], e);
                next = b + 1;
            }
        }
        s.filled.shrink_to_fit();
        s.energies.shrink_to_fit();
        s
    }

    fn push_bin(&mut self, gap: usize, count: u64, energy: Option<f64>) {
        put_varint(&mut self.filled, gap as u64);
        put_varint(&mut self.filled, count);
        if let Some(e) = energy {
            self.energies.push(e);
        }
        self.bins += 1;
    }

    /// The filled bins, lowest score first: (bin, count, energy when kept).
    pub fn bins(&self) -> impl Iterator<Item = (usize, u64, Option<f64>)> + '_ {
        let mut r = self.filled.as_slice();
        let mut next = 0usize;
        (0..self.bins).map_while(move |i| {
            // Written by `push_bin` only, so the varints are whole.
            let b = next + take_varint(&mut r)? as usize;
            let c = take_varint(&mut r)?;
            next = b + 1;
            Some((b, c, self.energies.get(i).copied()))
        })
    }

    /// Coefficients in bins above `cut`, and in bin `cut`.
    pub fn count_above_and_at(&self, cut: usize) -> (u64, u64) {
        let (mut above, mut at) = (0u64, 0u64);
        for (b, c, _) in self.bins() {
            if b > cut {
                above += c;
            } else if b == cut {
                at = c;
            }
        }
        (above, at)
    }

    /// Whether the per-bin energies are kept (a summary of no bin has all it needs).
    pub fn has_energies(&self) -> bool {
        self.energies.len() == self.bins
    }

    /// The same summary without its per-bin energies (what a target other than Q_V needs).
    pub fn without_energies(mut self) -> ScoreSummary {
        self.energies = Vec::new();
        self
    }

    /// Bytes the summary holds on the heap.
    pub fn heap_bytes(&self) -> usize {
        self.filled.capacity() + self.energies.capacity() * std::mem::size_of::<f64>()
    }
}

/// Why bytes are not a [`ScoreSummary`].
#[derive(Debug, thiserror::Error)]
#[error("not a score summary: {0}")]
pub struct SummaryBytesError(String);

/// The start of [`ScoreSummary::to_bytes`]: a tag and its version.
const SUMMARY_MAGIC: &[u8; 8] = b"WSSCORE1";

impl ScoreSummary {
    /// The summary as bytes, to hand from the worker that scored a brick to the one that
    /// allocates the rate: a tag, the totals, then every non-empty bin as varints (its distance
    /// from the last, its count) and, with `energies` (only a Q_V target needs them), its
    /// energy. Energies the summary does not keep are not written (the flag says so).
    pub fn to_bytes(&self, energies: bool) -> Vec<u8> {
        let energies = energies && self.has_energies();
        let mut out = Vec::with_capacity(48 + self.filled.len() + self.energies.len() * 8);
        out.extend_from_slice(SUMMARY_MAGIC);
        out.extend_from_slice(&self.total_coefficients.to_le_bytes());
        out.extend_from_slice(&self.total_energy.to_le_bytes());
        out.extend_from_slice(&self.nonzero.to_le_bytes());
        out.extend_from_slice(&self.positive.to_le_bytes());
        out.push(u8::from(energies));
        put_varint(&mut out, self.bins as u64);
        let mut next = 0usize;
        for (b, c, e) in self.bins() {
            put_varint(&mut out, (b - next) as u64);
            put_varint(&mut out, c);
            if energies {
                out.extend_from_slice(&e.unwrap_or(0.0).to_le_bytes());
            }
            next = b + 1;
        }
        out
    }

    /// Reads [`ScoreSummary::to_bytes`]'s output back, checking its tag, length and bins.
    pub fn from_bytes(bytes: &[u8]) -> Result<ScoreSummary, SummaryBytesError> {
        let bad = |what: &str| SummaryBytesError(what.to_string());
        let mut r = bytes;
        if r.len() < 41 || &r[..8] != SUMMARY_MAGIC {
            return Err(bad("wrong tag or version, or cut short"));
        }
        let u64_at = |at: usize| u64::from_le_bytes(r[at..at + 8].try_into().unwrap_or([0; 8]));
        let mut s = ScoreSummary {
            filled: Vec::new(),
            bins: 0,
            energies: Vec::new(),
            total_coefficients: u64_at(8),
            total_energy: f64::from_bits(u64_at(16)),
            nonzero: u64_at(24),
            positive: u64_at(32),
        };
        let with_energies = match r[40] {
            0 => false,
            1 => true,
            _ => return Err(bad("energy flag")),
        };
        r = &r[41..];
        let bins = Histogram::BINS as u64;
        let filled = take_varint(&mut r).ok_or_else(|| bad("cut short"))?;
        if filled > bins {
            return Err(bad("more bins than there are"));
        }
        let (mut next, mut binned) = (0u64, 0u64);
        for _ in 0..filled {
            let gap = take_varint(&mut r).ok_or_else(|| bad("cut short"))?;
            let b = next
                .checked_add(gap)
                .filter(|b| *b < bins)
                .ok_or_else(|| bad("bin out of range"))?;
            let count = take_varint(&mut r).ok_or_else(|| bad("cut short"))?;
            binned = binned
                .checked_add(count)
                .filter(|n| *n <= s.total_coefficients)
                .ok_or_else(|| bad("totals disagree with the bins"))?;
            let energy = if with_energies {
                let (e, rest) = r.split_at_checked(8).ok_or_else(|| bad("cut short"))?;
                r = rest;
                let e = f64::from_le_bytes(e.try_into().unwrap_or([0; 8]));
                if !(e.is_finite() && e >= 0.0) {
                    return Err(bad("a bin's energy is negative or not finite"));
                }
                Some(e)
            } else {
                None
            };
            s.push_bin(gap as usize, count, energy);
            next = b + 1;
        }
        if !r.is_empty() {
            return Err(bad("bytes after the last bin"));
        }
        s.filled.shrink_to_fit();
        s.energies.shrink_to_fit();
        let totals_agree = s.total_energy.is_finite()
            && s.total_energy >= 0.0
            && s.positive == binned
            && s.nonzero == binned;
        if !totals_agree {
            return Err(bad("totals disagree with the bins"));
        }
        Ok(s)
    }
}

/// Summaries added up (the bricks of one volume): dense, one per allocation, so that the
/// global threshold is found by one walk down the bins.
pub struct SummedScores {
    histogram: Histogram,
    /// Coefficients of the padded grids, all channels.
    pub total_coefficients: u64,
    /// Energy of the coefficients the oracle may keep (without importance), the summaries'
    /// totals added.
    pub total_energy: f64,
    /// Selectable (non-zero) coefficients.
    pub nonzero: u64,
}

impl Default for SummedScores {
    fn default() -> Self {
        SummedScores::new()
    }
}

impl SummedScores {
    /// The sum of no summary.
    pub fn new() -> SummedScores {
        SummedScores {
            histogram: Histogram::empty(),
            total_coefficients: 0,
            total_energy: 0.0,
            nonzero: 0,
        }
    }

    /// Adds a volume's summary: the sum then describes its coefficients too.
    pub fn add(&mut self, summary: &ScoreSummary) {
        for (b, c, e) in summary.bins() {
            self.histogram.add_to_bin(b, c, e.unwrap_or(0.0));
        }
        // Saturating: summaries read from bytes are checked against their own bins, not
        // against each other's sums.
        let h = &mut self.histogram;
        h.positive = h.positive.saturating_add(summary.positive);
        self.total_coefficients = self
            .total_coefficients
            .saturating_add(summary.total_coefficients);
        self.total_energy += summary.total_energy;
        self.nonzero = self.nonzero.saturating_add(summary.nonzero);
    }

    /// The lowest score bin holding one of the top `k` coefficients (bin 0 when there are
    /// fewer than `k`).
    pub fn cut_for_count(&self, k: u64) -> usize {
        self.histogram.cut_for_count(k)
    }

    /// Coefficients per score bin, lowest score first.
    pub fn counts(&self) -> &[u64] {
        self.histogram.counts()
    }

    /// Energy per score bin (sums in a thread-dependent order: a guide, not exact).
    pub fn energies(&self) -> &[f64] {
        self.histogram.energies()
    }
}

/// LEB128, as protobuf writes integers (by hand: two small loops, not worth a crate).
fn put_varint(out: &mut Vec<u8>, mut v: u64) {
    while v >= 0x80 {
        out.push((v as u8) | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
}

fn take_varint(r: &mut &[u8]) -> Option<u64> {
    let mut v = 0u64;
    for (i, &byte) in r.iter().enumerate().take(10) {
        if i == 9 && byte > 1 {
            // Past 64 bits.
            return None;
        }
        v |= u64::from(byte & 0x7f) << (7 * i);
        if byte & 0x80 == 0 {
            *r = &r[i + 1..];
            return Some(v);
        }
    }
    None
}
