//! The `.wsp` bitstream: a versioned header, a packet directory, then self-contained packets.
//!
//! ```text
//! "WSPL" | version u16 | header length u32 | header | header CRC-32
//! packet count (varint) | packet length (varint) × count | directory CRC-32
//! packet × count
//! ```
//!
//! The header carries everything a packet needs to decode on its own: dimensions, channels,
//! family, depth M, margin (hence the padded grid), the colour transform and importances, the
//! coder and its Huffman tables, the quantizer bits P, the per-substream (channel, level, type)
//! quantization parameters (w₀ and Δ of eq. 15–17), the tile size and the quality-layer score
//! thresholds. A packet holds a run of one tile's coefficients in significance order; it starts
//! with its tile, layer (its rank among the tile's packets), coefficient count and a summary of
//! its energy per band, and ends with a CRC-32. Quantization chains restart in every packet (from
//! the layer's magnitude bound), so any subset of packets decodes, and a prefix of a tile's
//! packets holds that tile's most significant coefficients.
//!
//! Every read from bytes is bounds-checked and every field range-checked: truncated, corrupted,
//! wrong-version or oversized input yields a [`FormatError`], never a panic.

pub mod bricked;
pub mod bytes;
mod coefficient;
mod error;
pub mod fast;
mod file;
mod header;
pub mod index;
pub(crate) mod morton;
pub mod packet;
mod paper;
pub mod quant;
pub mod series;
pub mod sigmap;

use crate::entropy::huffman::HuffmanCode;

pub(crate) use error::invalid;
pub use error::FormatError;
pub use file::{
    check_kept, parse_file, parse_prelude, write_file, write_file_version, Prelude, WspFile,
};
pub(crate) use header::read_magic_and_version;
pub use header::{magnitude_threshold, read_header_section, write_header_section, Header};

/// File magic.
pub const MAGIC: &[u8; 4] = b"WSPL";
/// Current format version (4: the header carries the volume's placement in patient space; 5:
/// an intensity volume's offset, the value subtracted before the transform; 6: the sigmap
/// coder codes each magnitude in the context of its lower neighbours' magnitudes; 7: the fast
/// coder, [`CoderKind::Fast`]; 8: the coarse layer, [`Header::coarse_layer`]; 12: the sigmap
/// coder's models start from trained priors, [`sigmap::priors`]; 13: the compact header,
/// [`COMPACT_HEADER_VERSION`]; 14: the fast coder codes its symbols by rANS,
/// [`RANS_VERSION`]; 15: the fast coder's occupancy contexts and steps in half octaves,
/// [`FAST_CONTEXTS_VERSION`]). Versions 9 to 11 are the bricked and series containers'
/// ([`bricked`], [`series`]), so the plain file's versions are [`is_plain_version`]'s.
pub const VERSION: u16 = 15;

/// First version whose fast coder codes the children of nodes of 4 and 8 cells on a side one
/// by one, in the context of the coded cells at each child's lower faces, and its steps of 14
/// or more in half octaves ([`fast`]). The other coders' packets are version 14's.
pub const FAST_CONTEXTS_VERSION: u16 = 15;

/// First version with the compact header: the packets' syntax is version 12's, the header
/// spends fewer bytes on what is usually a round number (unit spacing, importance 1, an
/// infinite layer bound, a zero offset: a tag byte instead of 8 or 12 bytes), codes each
/// substream's Δ as its difference from the Δ its score threshold predicts (one byte rather
/// than four), and a threshold coder's cap on reconstructions w₀ in sixteenths of Δ above the
/// substream's smallest magnitude, or none (one byte rather than four,
/// [`SubstreamParams::with_coarse_cap`]).
/// A small file or a brick is mostly header: 64³ bricks of MNI at 87 kB spent 10 % of the
/// file on their headers.
pub const COMPACT_HEADER_VERSION: u16 = 13;

/// First version whose fast coder codes its masks and step symbols by rANS with static
/// distributions ([`crate::entropy::rans`]) instead of prefix codes: fractional code lengths,
/// a few per cent fewer bytes ([`fast`]). The other coders' packets are version 13's.
pub const RANS_VERSION: u16 = 14;

/// First version whose sigmap packets start their models from the trained priors
/// ([`sigmap::priors`]).
pub const PRIORS_VERSION: u16 = 12;

/// The last plain version before the containers' numbers (9 to 11).
pub const LAST_UNPRIMED_VERSION: u16 = 8;

/// Whether a plain file (one volume, [`parse_file`]) of this version is readable here.
pub fn is_plain_version(version: u16) -> bool {
    (OLDEST_READABLE_VERSION..=LAST_UNPRIMED_VERSION).contains(&version)
        || (PRIORS_VERSION..=VERSION).contains(&version)
}

/// First version with the coarse layer ([`Header::coarse_layer`]).
pub const COARSE_LAYER_VERSION: u16 = 8;

/// First version with the fast coder ([`fast`]).
pub const FAST_CODER_VERSION: u16 = 7;

/// First version whose sigmap packets use the neighbour magnitude contexts ([`sigmap`]).
pub const MAGNITUDE_CONTEXTS_VERSION: u16 = 6;
/// Oldest version this build reads: version 3 is version 4 without the placement (read as
/// `None`), version 4 is version 5 without an intensity offset (read as 0), version 5 is
/// version 6 with each sigmap magnitude coded in its band's context only, so archives and
/// caches written before stay readable.
pub const OLDEST_READABLE_VERSION: u16 = 3;
/// Largest accepted header (bytes).
pub const MAX_HEADER_BYTES: usize = 16 << 20;
/// Largest accepted packet (bytes).
pub const MAX_PACKET_BYTES: usize = 256 << 20;
/// Largest number of quality layers.
pub const MAX_LAYERS: usize = 32;
/// Largest zero margin around the volume.
pub const MAX_MARGIN: usize = 4096;

/// How the volume's channels relate to RGB.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ColorKind {
    /// One intensity channel; no colour transform.
    Intensity,
    /// RGB channels, only the origin colour subtracted (importances 1, 1, 1).
    Rgb,
    /// NTSC YIQ (the importances are stored in the header; the compressor writes each
    /// channel's RGB error weight).
    Yiq,
    /// Principal components of the colours (importances stored in the header).
    Pca,
}

impl ColorKind {
    /// The byte that stands for it in a header.
    pub fn code(self) -> u8 {
        match self {
            ColorKind::Intensity => 0,
            ColorKind::Rgb => 1,
            ColorKind::Yiq => 2,
            ColorKind::Pca => 3,
        }
    }
    /// The kind a header's byte stands for (`None`: no kind).
    pub fn from_code(c: u8) -> Option<Self> {
        Some(match c {
            0 => ColorKind::Intensity,
            1 => ColorKind::Rgb,
            2 => ColorKind::Yiq,
            3 => ColorKind::Pca,
            _ => return None,
        })
    }
    /// Lower-case name.
    pub fn name(self) -> &'static str {
        match self {
            ColorKind::Intensity => "intensity",
            ColorKind::Rgb => "rgb",
            ColorKind::Yiq => "yiq",
            ColorKind::Pca => "pca",
        }
    }
}

/// The colour transform the channels were coded in: channel i = basis row i · (rgb − mean).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ColorInfo {
    /// Which colour space.
    pub kind: ColorKind,
    /// Rows are the vectors C1..C3 in RGB (identity for intensity volumes).
    pub basis: [[f64; 3]; 3],
    /// Colour subtracted before projecting; for an intensity volume, `mean[0]` is the value
    /// subtracted from every voxel (its faces' median), the others zero.
    pub mean: [f64; 3],
    /// Importance I(C) of each channel (eq. 14, Table 2); only the first is used for intensity.
    pub importance: [f64; 3],
}

impl ColorInfo {
    /// The inverse of the colour basis (YIQ is not orthonormal): rgb = inverse · c + mean.
    /// `None` when the basis is singular or not finite (a corrupt header).
    pub fn inverse_basis(&self) -> Option<[[f64; 3]; 3]> {
        let m = &self.basis;
        let c = |r0: usize, r1: usize, c0: usize, c1: usize| {
            m[r0][c0] * m[r1][c1] - m[r0][c1] * m[r1][c0]
        };
        let det = m[0][0] * c(1, 2, 1, 2) - m[0][1] * c(1, 2, 0, 2) + m[0][2] * c(1, 2, 0, 1);
        if !det.is_finite() || det.abs() < 1e-12 {
            return None;
        }
        let adj = [
            [c(1, 2, 1, 2), -c(0, 2, 1, 2), c(0, 1, 1, 2)],
            [-c(1, 2, 0, 2), c(0, 2, 0, 2), -c(0, 1, 0, 2)],
            [c(1, 2, 0, 1), -c(0, 2, 0, 1), c(0, 1, 0, 1)],
        ];
        Some(adj.map(|row| row.map(|v| v / det)))
    }

    /// Maps a line integral of the coded channels back to RGB. The projection is linear, so
    /// rgb = inverse · c + mean · length, with `length` the path length of the ray inside the
    /// volume (the mean was subtracted from every voxel it crossed). For intensity (identity
    /// basis) the first entry is the intensity integral, c₀ + offset · length.
    pub fn to_rgb(&self, inverse: &[[f64; 3]; 3], coded: [f64; 3], length: f64) -> [f64; 3] {
        let m = self.mean;
        [0, 1, 2].map(|r| {
            inverse[r][0] * coded[0]
                + inverse[r][1] * coded[1]
                + inverse[r][2] * coded[2]
                + m[r] * length
        })
    }

    /// The intensity (single-channel) case.
    pub fn intensity() -> ColorInfo {
        ColorInfo {
            kind: ColorKind::Intensity,
            basis: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            mean: [0.0; 3],
            importance: [1.0, 1.0, 1.0],
        }
    }
}

/// Which entropy coder the packets use.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CoderKind {
    /// The paper's scheme: run-length + static Huffman tables (in the header) for tags,
    /// Huffman-coded position and value deltas, a raw sign bit.
    Huffman,
    /// The same syntax with an adaptive binary arithmetic (range) coder, reset per packet.
    Range,
    /// Octree significance maps per substream + uniformly quantized magnitudes, adaptive range
    /// coded (see [`sigmap`]); the default.
    Sigmap,
    /// The sigmap coder's quantization and octree order with static Huffman tables (in the
    /// header) instead of adaptive contexts (see [`fast`]): several times faster to decode,
    /// for somewhat larger files.
    Fast,
}

impl CoderKind {
    /// Lower-case name.
    pub fn name(self) -> &'static str {
        match self {
            CoderKind::Huffman => "huffman",
            CoderKind::Range => "range",
            CoderKind::Sigmap => "sigmap",
            CoderKind::Fast => "fast",
        }
    }
    /// Whether the coder quantizes magnitudes by the sigmap coder's rule (steps of Δ above the
    /// layer's lower magnitude bound, Δ from the score threshold) rather than by the paper's
    /// eq. 15–17.
    pub fn quantizes_by_threshold(self) -> bool {
        matches!(self, CoderKind::Sigmap | CoderKind::Fast)
    }
    /// Parses a name.
    pub fn from_name(s: &str) -> Option<Self> {
        match s {
            "huffman" => Some(CoderKind::Huffman),
            "range" | "arithmetic" => Some(CoderKind::Range),
            "sigmap" => Some(CoderKind::Sigmap),
            "fast" => Some(CoderKind::Fast),
            _ => None,
        }
    }
}

/// Quantization parameters of one substream (channel, band): eq. 15–17.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SubstreamParams {
    /// The largest magnitude w₀ in the substream, which caps reconstructions: exact in the
    /// paper's coders and before [`COMPACT_HEADER_VERSION`]; from it, for a threshold coder,
    /// rounded up to a sixteenth of Δ above the smallest magnitude, or +∞ (no cap) where it
    /// lies more than 7¾ steps above it (see [`SubstreamParams::with_coarse_cap`]).
    pub w0: f32,
    /// The delta factor Δ (0 when the substream has a single distinct magnitude).
    pub delta: f32,
}

impl SubstreamParams {
    /// The parameters of a substream that keeps `magnitudes`, largest first (`None` when it
    /// keeps none): w₀ the largest; Δ, for a coder that quantizes by the threshold, the step
    /// `threshold_step` gives, floored at 2^−30 of w₀ so that q stays small even when
    /// near-zero coefficients are kept, and for the paper's coders Δ of eq. 15 at `bits` bits.
    pub fn of_magnitudes(
        magnitudes: &[f64],
        coder: CoderKind,
        bits: u8,
        threshold_step: impl FnOnce() -> f64,
    ) -> Option<SubstreamParams> {
        let w0 = *magnitudes.first()?;
        let delta = if coder.quantizes_by_threshold() {
            threshold_step().max(w0 * 2f64.powi(-30))
        } else {
            quant::delta_factor(magnitudes, bits)
        };
        Some(SubstreamParams {
            w0: w0 as f32,
            delta: delta as f32,
        })
    }
}

/// Sixteenths of Δ above the smallest magnitude the compact header can say a cap in (one byte
/// with its two tags, see [`SubstreamParams::cap_steps`]).
pub const MAX_CAP_STEPS: u32 = 125;

impl SubstreamParams {
    /// The cap `steps` sixteenths of Δ above `threshold` (the substream's smallest magnitude),
    /// computed alike by the compressor and the reader.
    pub fn cap_at(threshold: f64, delta: f32, steps: u32) -> f32 {
        (threshold + steps as f64 * delta as f64 / 16.0) as f32
    }

    /// Where this substream's w₀ lies above `threshold` in sixteenths of Δ, when it lies there
    /// exactly as [`SubstreamParams::cap_at`] computes it and within [`MAX_CAP_STEPS`].
    pub fn cap_steps(&self, threshold: f64) -> Option<u32> {
        let delta = self.delta as f64;
        if !(delta > 0.0 && delta.is_finite() && self.w0.is_finite() && threshold.is_finite()) {
            return None;
        }
        let steps = (16.0 * (self.w0 as f64 - threshold) / delta).round();
        if !(0.0..=MAX_CAP_STEPS as f64).contains(&steps) {
            return None;
        }
        let steps = steps as u32;
        (Self::cap_at(threshold, self.delta, steps).to_bits() == self.w0.to_bits()).then_some(steps)
    }

    /// The parameters the compact header sends for a threshold coder's substream whose
    /// smallest magnitude is `threshold`: the cap w₀ rounded up to the next sixteenth of Δ
    /// above it (one byte instead of four; a substream of one coefficient at the threshold,
    /// such as a constant volume's, keeps its exact value), or no cap (+∞) where w₀ lies more
    /// than [`MAX_CAP_STEPS`] sixteenths above: there the cap changed only the largest
    /// coefficient's reconstruction, whose error is then at most Δ/2 like every other's.
    pub fn with_coarse_cap(self, threshold: f64) -> SubstreamParams {
        let delta = self.delta as f64;
        // A substream of zero weight (a channel of importance 0) has no threshold magnitude,
        // and its cap also bounds the layers' chains (`Header::chain_start`): it stays exact.
        let w0 = if delta > 0.0 && delta.is_finite() && threshold > 0.0 && threshold.is_finite() {
            let steps = (16.0 * (self.w0 as f64 - threshold) / delta)
                .ceil()
                .max(0.0);
            if steps <= MAX_CAP_STEPS as f64 {
                Self::cap_at(threshold, self.delta, steps as u32)
            } else {
                f32::INFINITY
            }
        } else {
            self.w0
        };
        SubstreamParams { w0, ..self }
    }
}

/// The four static Huffman tables of the paper's coder.
#[derive(Debug, Clone, PartialEq)]
pub struct HuffmanTables {
    /// Substream id (channel × band) at the start of a run.
    pub tag: HuffmanCode,
    /// Run-length categories.
    pub run: HuffmanCode,
    /// Position-delta categories.
    pub position: HuffmanCode,
    /// Value-delta categories.
    pub value: HuffmanCode,
}

/// Alphabet of the magnitude-category tables.
pub const CATEGORY_ALPHABET: usize = 65;

#[cfg(test)]
mod tests {
    use super::SubstreamParams;

    /// The compact header's caps: rounded up to the next sixteenth of Δ above the threshold
    /// (never below w₀, less than a sixteenth above it), exact for a coefficient at the
    /// threshold, dropped far above it, and left exact where there is no threshold (a
    /// substream of zero weight, whose cap also bounds the layers' chains); a cap said in
    /// sixteenths reads back to the same f32.
    #[test]
    fn caps_round_up_to_sixteenths_of_delta_or_go() {
        let (t, delta) = (2.5f64, 0.75f32);
        for w0 in [2.5f32, 2.5001, 2.9, 4.0, 8.3] {
            let p = SubstreamParams { w0, delta }.with_coarse_cap(t);
            assert!(
                p.w0 >= w0 && (p.w0 - w0) as f64 <= delta as f64 / 16.0 + 1e-6,
                "{w0}"
            );
            let n = p.cap_steps(t).expect("a cap in sixteenths");
            assert_eq!(
                SubstreamParams::cap_at(t, delta, n).to_bits(),
                p.w0.to_bits()
            );
        }
        let lone = SubstreamParams { w0: 2.5, delta }.with_coarse_cap(t);
        assert_eq!(lone.w0, 2.5);
        let far = SubstreamParams { w0: 9.0, delta }.with_coarse_cap(t);
        assert_eq!(far.w0, f32::INFINITY);
        assert_eq!(far.cap_steps(t), None);
        for (w0, threshold) in [(9.0f32, 0.0), (9.0, f64::NAN)] {
            let kept = SubstreamParams { w0, delta }.with_coarse_cap(threshold);
            assert_eq!(kept.w0, w0, "threshold {threshold}");
        }
        assert_eq!(
            SubstreamParams {
                w0: 3.0,
                delta: 0.0
            }
            .with_coarse_cap(t)
            .w0,
            3.0
        );
        // A w0 off the sixteenths is said as an f32, not as steps.
        assert_eq!(SubstreamParams { w0: 2.6, delta }.cap_steps(t), None);
    }
}
