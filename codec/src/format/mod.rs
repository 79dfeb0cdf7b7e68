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
pub mod fast;
pub mod index;
pub mod packet;
mod paper;
pub mod quant;
pub mod sigmap;

use crate::entropy::bits::{BitReader, BitWriter};
use crate::entropy::huffman::HuffmanCode;
use crate::entropy::EntropyError;
use crate::family::Family;
use crate::layout::{Band, Geometry, LayoutError, MAX_LEVELS};
use crate::volume::Placement;
use bytes::{ByteReader, ByteWriter};
use thiserror::Error;

/// File magic.
pub const MAGIC: &[u8; 4] = b"WSPL";
/// Current format version (4: the header carries the volume's placement in patient space; 5:
/// an intensity volume's offset, the value subtracted before the transform; 6: the sigmap
/// coder codes each magnitude in the context of its lower neighbours' magnitudes; 7: the fast
/// coder, [`CoderKind::Fast`]; 8: the coarse layer, [`Header::coarse_layer`]).
pub const VERSION: u16 = 8;

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

/// Errors reading or writing the format.
#[derive(Debug, Error, PartialEq)]
#[non_exhaustive]
pub enum FormatError {
    /// Not a wavesplat file.
    #[error("not a wavesplat file: magic bytes are {0:02x?}, expected \"WSPL\"")]
    BadMagic(Vec<u8>),
    /// A version this build cannot read (files older than [`OLDEST_READABLE_VERSION`] must be
    /// compressed again from their source).
    #[error("unsupported format version {found}; this build reads versions {OLDEST_READABLE_VERSION} to {supported}{}", if *found < *supported { " (the file was written by an older wavesplat: compress the source volume again)" } else { " (the file was written by a newer wavesplat)" })]
    UnsupportedVersion {
        /// Version in the file.
        found: u16,
        /// Version supported.
        supported: u16,
    },
    /// A bricked container ([`bricked`]) where a plain file was expected: its bricks are
    /// plain files, read through [`bricked::parse_bricked`].
    #[error("a bricked volume (format version {}): each brick is a volume of its own, read through the bricked container", bricked::BRICKED_VERSION)]
    Bricked,
    /// Input ended early.
    #[error("truncated {what}: needed {needed} more bytes, {available} available")]
    Truncated {
        /// Structure being read.
        what: &'static str,
        /// Bytes needed.
        needed: u64,
        /// Bytes available.
        available: u64,
    },
    /// A checksum did not match.
    #[error("{what} checksum mismatch: stored {stored:#010x}, computed {computed:#010x}")]
    Checksum {
        /// Structure being checked.
        what: &'static str,
        /// Stored CRC.
        stored: u32,
        /// Computed CRC.
        computed: u32,
    },
    /// A field is out of range or inconsistent.
    #[error("invalid {what}: {detail}")]
    Invalid {
        /// Structure being read.
        what: &'static str,
        /// What was wrong.
        detail: String,
    },
    /// A size limit was exceeded.
    #[error("{what} of {size} bytes exceeds the limit of {limit}")]
    TooLarge {
        /// Structure.
        what: &'static str,
        /// Its size.
        size: u64,
        /// The limit.
        limit: u64,
    },
    /// Decoding would cost more than the caller's budget allows.
    #[error("decoding needs {need} {what}, over the budget of {budget}")]
    OverBudget {
        /// What is counted.
        what: &'static str,
        /// What the input declares it needs.
        need: u64,
        /// The budget.
        budget: u64,
    },
    /// Entropy-coded data was malformed.
    #[error("entropy-coded data: {0}")]
    Entropy(#[from] EntropyError),
    /// Geometry was invalid.
    #[error(transparent)]
    Layout(#[from] LayoutError),
}

pub(crate) fn invalid(what: &'static str, detail: impl Into<String>) -> FormatError {
    FormatError::Invalid {
        what,
        detail: detail.into(),
    }
}

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
    fn code(self) -> u8 {
        match self {
            ColorKind::Intensity => 0,
            ColorKind::Rgb => 1,
            ColorKind::Yiq => 2,
            ColorKind::Pca => 3,
        }
    }
    fn from_code(c: u8) -> Option<Self> {
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
    /// The exact largest magnitude w₀ in the substream.
    pub w0: f32,
    /// The delta factor Δ (0 when the substream has a single distinct magnitude).
    pub delta: f32,
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

/// Everything a packet needs to decode, plus volume-level facts for tools.
#[derive(Debug, Clone, PartialEq)]
pub struct Header {
    /// Geometry: dims, padding, levels, family and voxel spacing (mm when the source said; the
    /// units of the source otherwise).
    pub geometry: Geometry,
    /// Zero margin used to build the padded grid.
    pub margin: usize,
    /// Where the voxel grid sits in patient space (DICOM LPS), when the source said.
    pub placement: Option<Placement>,
    /// Number of channels (1 or 3).
    pub channels: usize,
    /// Colour transform.
    pub color: ColorInfo,
    /// Value range of the source volume (RGB / intensity units).
    pub value_range: [f32; 2],
    /// Entropy coder.
    pub coder: CoderKind,
    /// Quantization bits P (1..=16).
    pub bits: u8,
    /// Tile edge length in voxels of the padded grid (a multiple of 2^M).
    pub tile: usize,
    /// Score upper bound of each quality layer (layer 0 first; non-increasing; may be +∞).
    /// f64: scores are squared magnitudes times basis norms and overflow f32 for large data.
    /// With [`Header::coarse_layer`], entry 0 is +∞ and the score layers are 1, 2, ….
    pub layer_bounds: Vec<f64>,
    /// Layer 0 holds each tile's scaling band (the coarsest, φφφ at level M), whatever the
    /// coefficients' scores, and the later layers split the other bands by score: the first
    /// packets of a stream then draw a coarse picture of the whole volume rather than its
    /// largest coefficients, which are sparse fine splats. Version 8 and later; needs at least
    /// two layers.
    pub coarse_layer: bool,
    /// Smallest score S = E·I of a kept coefficient (rounded down); with the basis norm and the
    /// importance it gives each substream's smallest magnitude (see
    /// [`Header::magnitude_threshold`]).
    pub score_threshold: f64,
    /// Per (channel, band index) parameters; `None` for substreams without coefficients.
    pub substreams: Vec<Option<SubstreamParams>>,
    /// Huffman tables (present iff `coder == Huffman`).
    pub tables: Option<HuffmanTables>,
    /// The fast coder's tables (present iff `coder == Fast`).
    pub fast_tables: Option<fast::FastTables>,
    /// Total energy Σ E(w) of all coefficients of all channels (the denominator of Q_V).
    pub total_energy: f64,
    /// Number of coefficients kept in the file.
    pub kept: u64,
    /// The format version the packets are coded in: [`VERSION`] for what this build writes,
    /// the file's for what it reads (the sigmap coder's syntax depends on it, see
    /// [`MAGNITUDE_CONTEXTS_VERSION`]).
    pub version: u16,
}

impl Header {
    /// Voxel spacing (the geometry's).
    pub fn spacing(&self) -> [f32; 3] {
        self.geometry.spacing
    }

    /// Number of tiles along each axis.
    pub fn tile_counts(&self) -> [usize; 3] {
        let p = self.geometry.padded;
        [
            p[0].div_ceil(self.tile),
            p[1].div_ceil(self.tile),
            p[2].div_ceil(self.tile),
        ]
    }

    /// Total number of tiles.
    pub fn tile_count(&self) -> usize {
        self.tile_counts().iter().product()
    }

    /// Tile origin (voxels of the padded grid) of tile `t`.
    pub fn tile_origin(&self, t: usize) -> [usize; 3] {
        let c = self.tile_counts();
        [
            (t % c[0]) * self.tile,
            ((t / c[0]) % c[1]) * self.tile,
            (t / (c[0] * c[1])) * self.tile,
        ]
    }

    /// Tile containing coefficient `pos` of `band`.
    pub fn tile_of(&self, band: Band, pos: [usize; 3]) -> usize {
        let c = self.tile_counts();
        let l = band.level as usize;
        let t = [
            (pos[0] << l) / self.tile,
            (pos[1] << l) / self.tile,
            (pos[2] << l) / self.tile,
        ];
        t[0] + c[0] * (t[1] + c[1] * t[2])
    }

    /// Number of substreams (channels × bands).
    pub fn substream_count(&self) -> usize {
        self.channels * self.geometry.band_count()
    }

    /// Substream id of (channel, band).
    pub fn substream_id(&self, channel: usize, band: Band) -> usize {
        channel * self.geometry.band_count()
            + self
                .geometry
                .band_index(band)
                .expect("band exists in this geometry")
    }

    /// Inverse of [`Header::substream_id`].
    pub fn substream_of(&self, id: usize) -> (usize, Band) {
        let nb = self.geometry.band_count();
        (id / nb, self.geometry.bands()[id % nb])
    }

    /// Importance of a channel.
    pub fn importance(&self, channel: usize) -> f64 {
        self.color.importance[channel.min(2)]
    }

    /// Magnitude at which a substream's quantization chain starts in a packet of `layer`:
    /// min(w₀, √(bound_layer / (‖basis‖²·I))).
    pub fn chain_start(&self, substream: usize, layer: usize) -> f64 {
        let Some(params) = self.substreams.get(substream).copied().flatten() else {
            return 0.0;
        };
        let w0 = params.w0 as f64;
        let (channel, band) = self.substream_of(substream);
        let weight = self.geometry.basis_norm2(band) * self.importance(channel);
        let bound = self.layer_bounds.get(layer).copied().unwrap_or(0.0);
        if weight > 0.0 && bound.is_finite() {
            w0.min((bound / weight).sqrt())
        } else {
            w0
        }
    }

    /// Smallest magnitude a kept coefficient of `substream` can have: √(threshold / (‖basis‖²·I)).
    pub fn magnitude_threshold(&self, substream: usize) -> f64 {
        let (channel, band) = self.substream_of(substream);
        let weight = self.geometry.basis_norm2(band) * self.importance(channel);
        if weight > 0.0 {
            (self.score_threshold / weight).sqrt()
        } else {
            0.0
        }
    }

    fn write_version(&self, w: &mut ByteWriter, version: u16) {
        let g = &self.geometry;
        for d in g.dims {
            w.varint(d as u64);
        }
        for s in g.spacing {
            w.f32(s);
        }
        match &self.placement {
            _ if version < 4 => {}
            None => w.u8(0),
            Some(p) => {
                w.u8(1);
                for v in p.origin.iter().chain(p.directions.iter().flatten()) {
                    w.f64(*v);
                }
            }
        }
        w.u8(self.channels as u8);
        w.u8(g.family.code());
        w.u8(g.levels as u8);
        w.varint(self.margin as u64);
        w.u8(self.color.kind.code());
        if self.channels == 3 {
            for row in self.color.basis {
                for v in row {
                    w.f64(v);
                }
            }
            for v in self.color.mean {
                w.f64(v);
            }
        } else if version >= 5 {
            w.f64(self.color.mean[0]);
        }
        for v in &self.color.importance[..self.channels] {
            w.f64(*v);
        }
        w.f32(self.value_range[0]);
        w.f32(self.value_range[1]);
        w.u8(match self.coder {
            CoderKind::Huffman => 0,
            CoderKind::Range => 1,
            CoderKind::Sigmap => 2,
            CoderKind::Fast => 3,
        });
        w.u8(self.bits);
        w.varint(self.tile as u64);
        w.u8(self.layer_bounds.len() as u8);
        for b in &self.layer_bounds {
            w.f64(*b);
        }
        if version >= COARSE_LAYER_VERSION {
            w.u8(u8::from(self.coarse_layer));
        }
        w.f64(self.score_threshold);
        // Presence bitmap, then parameters of the present substreams.
        let mut bitmap = vec![0u8; self.substreams.len().div_ceil(8)];
        for (i, s) in self.substreams.iter().enumerate() {
            if s.is_some() {
                bitmap[i / 8] |= 1 << (i % 8);
            }
        }
        w.bytes(&bitmap);
        for s in self.substreams.iter().flatten() {
            w.f32(s.w0);
            w.f32(s.delta);
        }
        w.f64(self.total_energy);
        w.varint(self.kept);
        if let Some(t) = &self.tables {
            let mut bw = BitWriter::new();
            for code in [&t.tag, &t.run, &t.position, &t.value] {
                code.write_lengths(&mut bw);
            }
            let blob = bw.finish();
            w.varint(blob.len() as u64);
            w.bytes(&blob);
        }
        if let Some(t) = &self.fast_tables {
            let mut bw = BitWriter::new();
            t.write(&mut bw);
            let blob = bw.finish();
            w.varint(blob.len() as u64);
            w.bytes(&blob);
        }
    }

    fn read(r: &mut ByteReader, version: u16) -> Result<Header, FormatError> {
        const W: &str = "header";
        let mut dims = [0usize; 3];
        for d in &mut dims {
            *d = r.varint_max(1 << 24, "dimension")? as usize;
        }
        crate::volume::checked_voxels(dims).map_err(|e| invalid(W, e.to_string()))?;
        let spacing = [r.f32()?, r.f32()?, r.f32()?];
        if spacing.iter().any(|s| !(s.is_finite() && *s > 0.0)) {
            return Err(invalid(
                W,
                format!("voxel spacing {spacing:?} must be positive"),
            ));
        }
        let placement = match if version < 4 { 0 } else { r.u8()? } {
            0 => None,
            1 => {
                let mut p = Placement::identity();
                for v in p.origin.iter_mut().chain(p.directions.iter_mut().flatten()) {
                    *v = r.f64()?;
                }
                p.validate().map_err(|e| invalid(W, e.to_string()))?;
                Some(p)
            }
            f => return Err(invalid(W, format!("placement flag {f}; 0 or 1 allowed"))),
        };
        let channels = r.u8()? as usize;
        if channels != 1 && channels != 3 {
            return Err(invalid(W, format!("{channels} channels; 1 or 3 allowed")));
        }
        let fam_code = r.u8()?;
        let family = Family::from_code(fam_code)
            .ok_or_else(|| invalid(W, format!("unknown wavelet family code {fam_code}")))?;
        let levels = r.u8()? as usize;
        if levels > MAX_LEVELS {
            return Err(invalid(W, format!("{levels} levels; at most {MAX_LEVELS}")));
        }
        let margin = r.varint_max(MAX_MARGIN as u64, "margin")? as usize;
        let geometry = Geometry::new(dims, family, levels, margin)?.with_spacing(spacing)?;
        let kind_code = r.u8()?;
        let kind = ColorKind::from_code(kind_code)
            .ok_or_else(|| invalid(W, format!("unknown colour space code {kind_code}")))?;
        if (kind == ColorKind::Intensity) != (channels == 1) {
            return Err(invalid(
                W,
                format!("colour space {} with {channels} channels", kind.name()),
            ));
        }
        let mut color = ColorInfo::intensity();
        color.kind = kind;
        if channels == 3 {
            for row in &mut color.basis {
                for v in row.iter_mut() {
                    *v = r.f64()?;
                }
            }
            for v in &mut color.mean {
                *v = r.f64()?;
            }
        } else if version >= 5 {
            color.mean[0] = r.f64()?;
        }
        for v in &mut color.importance[..channels] {
            *v = r.f64()?;
        }
        let all = color
            .basis
            .iter()
            .flatten()
            .chain(&color.mean)
            .chain(&color.importance);
        if all.clone().any(|v| !v.is_finite()) || color.importance.iter().any(|v| *v < 0.0) {
            return Err(invalid(
                W,
                "colour transform has non-finite or negative values",
            ));
        }
        let value_range = [r.f32()?, r.f32()?];
        if !(value_range[0].is_finite() && value_range[1].is_finite()) {
            return Err(invalid(W, "value range is not finite"));
        }
        let coder = match r.u8()? {
            0 => CoderKind::Huffman,
            1 => CoderKind::Range,
            2 => CoderKind::Sigmap,
            3 if version >= FAST_CODER_VERSION => CoderKind::Fast,
            c => return Err(invalid(W, format!("unknown coder code {c}"))),
        };
        let bits = r.u8()?;
        if !(1..=16).contains(&bits) {
            return Err(invalid(
                W,
                format!("quantization bits P = {bits}; allowed 1..=16"),
            ));
        }
        let tile = r.varint_max(1 << 24, "tile size")? as usize;
        let block = 1usize << levels;
        if tile < block || !tile.is_multiple_of(block) {
            return Err(invalid(
                W,
                format!("tile size {tile} must be a positive multiple of 2^M = {block}"),
            ));
        }
        let nl = r.u8()? as usize;
        if nl == 0 || nl > MAX_LAYERS {
            return Err(invalid(W, format!("{nl} layers; allowed 1..={MAX_LAYERS}")));
        }
        let mut layer_bounds = Vec::with_capacity(nl);
        for _ in 0..nl {
            let b = r.f64()?;
            if b.is_nan() || b < 0.0 || layer_bounds.last().is_some_and(|p: &f64| b > *p) {
                return Err(invalid(
                    W,
                    "layer bounds must be non-negative and non-increasing",
                ));
            }
            layer_bounds.push(b);
        }
        let coarse_layer = if version >= COARSE_LAYER_VERSION {
            match r.u8()? {
                0 => false,
                1 if nl >= 2 && geometry.levels > 0 => true,
                1 => {
                    return Err(invalid(
                        W,
                        format!(
                            "a coarse layer needs two layers or more and a decomposition;                              {nl} layers, M = {}",
                            geometry.levels
                        ),
                    ))
                }
                v => return Err(invalid(W, format!("coarse layer flag {v}; allowed 0 or 1"))),
            }
        } else {
            false
        };
        let score_threshold = r.f64()?;
        if !(score_threshold.is_finite() && score_threshold >= 0.0) {
            return Err(invalid(
                W,
                "score threshold must be finite and non-negative",
            ));
        }
        let nsub = channels * geometry.band_count();
        let bitmap = r.take(nsub.div_ceil(8))?.to_vec();
        let mut substreams = Vec::with_capacity(nsub);
        for i in 0..nsub {
            if bitmap[i / 8] & (1 << (i % 8)) != 0 {
                let (w0, delta) = (r.f32()?, r.f32()?);
                if !(w0.is_finite() && delta.is_finite() && w0 >= 0.0 && delta >= 0.0) {
                    return Err(invalid(W, format!("substream {i}: w0 {w0}, delta {delta}")));
                }
                substreams.push(Some(SubstreamParams { w0, delta }));
            } else {
                substreams.push(None);
            }
        }
        let total_energy = r.f64()?;
        if !(total_energy.is_finite() && total_energy >= 0.0) {
            return Err(invalid(W, "total energy must be finite and non-negative"));
        }
        let kept = r.varint()?;
        let tables = if coder == CoderKind::Huffman {
            let n = r.varint_max(1 << 20, "table blob length")? as usize;
            let blob = r.take(n)?;
            let mut br = BitReader::new(blob);
            let tag = HuffmanCode::read_lengths(&mut br, nsub)?;
            let run = HuffmanCode::read_lengths(&mut br, CATEGORY_ALPHABET)?;
            let position = HuffmanCode::read_lengths(&mut br, CATEGORY_ALPHABET)?;
            let value = HuffmanCode::read_lengths(&mut br, CATEGORY_ALPHABET)?;
            Some(HuffmanTables {
                tag,
                run,
                position,
                value,
            })
        } else {
            None
        };
        let fast_tables = if coder == CoderKind::Fast {
            let n = r.varint_max(1 << 20, "table blob length")? as usize;
            let blob = r.take(n)?;
            Some(fast::FastTables::read(&mut BitReader::new(blob))?)
        } else {
            None
        };
        Ok(Header {
            geometry,
            margin,
            placement,
            channels,
            color,
            value_range,
            coder,
            bits,
            tile,
            layer_bounds,
            coarse_layer,
            score_threshold,
            substreams,
            tables,
            fast_tables,
            total_energy,
            kept,
            version,
        })
    }
}

/// A parsed file: the header and the location of each packet.
#[derive(Debug, Clone)]
pub struct WspFile<'a> {
    /// The header.
    pub header: Header,
    /// Bytes of the header section (magic to header CRC), for size reports.
    pub header_bytes: usize,
    /// Bytes of the packet directory.
    pub directory_bytes: usize,
    /// Each packet's bytes, in file order.
    pub packets: Vec<&'a [u8]>,
}

/// Checks that a whole file's packets, holding `held` coefficients in all, hold what the header
/// declares (`Header::kept`).
pub fn check_kept(header: &Header, held: u64) -> Result<(), FormatError> {
    if held == header.kept {
        return Ok(());
    }
    Err(invalid(
        "file",
        format!(
            "the header declares {} kept coefficients but the packets hold {held}{}",
            header.kept,
            if held < header.kept {
                " (packets are missing)"
            } else {
                ""
            }
        ),
    ))
}

/// Serializes the header section (magic, version, header, CRC).
pub fn write_header_section(header: &Header) -> Vec<u8> {
    write_header_section_version(header, VERSION)
}

fn write_header_section_version(header: &Header, version: u16) -> Vec<u8> {
    let mut hw = ByteWriter::new();
    header.write_version(&mut hw, version);
    let hb = hw.into_bytes();
    let mut w = ByteWriter::new();
    w.bytes(MAGIC);
    w.u16(version);
    w.u32(hb.len() as u32);
    w.bytes(&hb);
    w.u32(crc32fast::hash(&hb));
    w.into_bytes()
}

/// Parses a header section, returning the header and the bytes it used.
pub fn read_header_section(bytes: &[u8]) -> Result<(Header, usize), FormatError> {
    let mut r = ByteReader::new(bytes, "file header");
    let version = read_magic_and_version(&mut r, bytes)?;
    check_version(version)?;
    let len = header_length(r.u32()?)?;
    let hb = r.take(len)?;
    let stored = r.u32()?;
    let computed = crc32fast::hash(hb);
    if stored != computed {
        return Err(FormatError::Checksum {
            what: "header",
            stored,
            computed,
        });
    }
    let mut hr = ByteReader::new(hb, "header");
    let header = Header::read(&mut hr, version)?;
    if hr.remaining() != 0 {
        return Err(invalid(
            "header",
            format!("{} unexpected trailing bytes", hr.remaining()),
        ));
    }
    Ok((header, r.position()))
}

/// Reads the magic (refused unless [`MAGIC`]) and the format version at the start of `bytes`
/// (`r` reads them).
pub(crate) fn read_magic_and_version(
    r: &mut ByteReader<'_>,
    bytes: &[u8],
) -> Result<u16, FormatError> {
    let magic = r
        .take(4)
        .map_err(|_| FormatError::BadMagic(bytes.iter().take(4).copied().collect()))?;
    if magic != MAGIC {
        return Err(FormatError::BadMagic(magic.to_vec()));
    }
    r.u16()
}

/// Refuses a version this build cannot read.
fn check_version(version: u16) -> Result<(), FormatError> {
    if (OLDEST_READABLE_VERSION..=VERSION).contains(&version) {
        Ok(())
    } else if version == bricked::BRICKED_VERSION {
        Err(FormatError::Bricked)
    } else {
        Err(FormatError::UnsupportedVersion {
            found: version,
            supported: VERSION,
        })
    }
}

/// The header section's declared length, refused beyond [`MAX_HEADER_BYTES`].
fn header_length(len: u32) -> Result<usize, FormatError> {
    let len = len as usize;
    if len > MAX_HEADER_BYTES {
        return Err(FormatError::TooLarge {
            what: "header",
            size: len as u64,
            limit: MAX_HEADER_BYTES as u64,
        });
    }
    Ok(len)
}

/// Writes a whole file from a header and encoded packets (see [`packet::encode_packets`]).
pub fn write_file(header: &Header, packets: &[Vec<u8>]) -> Vec<u8> {
    write_file_body(write_header_section(header), packets)
}

/// Writes a whole file in an older version of the format, for readers that have not been
/// updated. Refuses what that version cannot hold (a placement before version 4, an intensity
/// offset before version 5) rather than dropping it.
pub fn write_file_version(
    header: &Header,
    packets: &[Vec<u8>],
    version: u16,
) -> Result<Vec<u8>, FormatError> {
    check_version(version)?;
    if version < 4 && header.placement.is_some() {
        return Err(invalid(
            "header",
            format!("format version {version} cannot hold the volume's placement"),
        ));
    }
    if header.coder == CoderKind::Sigmap
        && (version >= MAGNITUDE_CONTEXTS_VERSION) != (header.version >= MAGNITUDE_CONTEXTS_VERSION)
    {
        return Err(invalid(
            "header",
            format!(
                "sigmap packets coded for format version {} do not decode as version {version} \
                 (the magnitude contexts differ): encode them with that version",
                header.version
            ),
        ));
    }
    if version < FAST_CODER_VERSION && header.coder == CoderKind::Fast {
        return Err(invalid(
            "header",
            format!("format version {version} has no fast coder"),
        ));
    }
    if version < COARSE_LAYER_VERSION && header.coarse_layer {
        return Err(invalid(
            "header",
            format!(
                "format version {version} has no coarse layer: compress with --no-coarse-layer"
            ),
        ));
    }
    if version < 5 && header.channels == 1 && header.color.mean[0] != 0.0 {
        return Err(invalid(
            "header",
            format!("format version {version} cannot hold an intensity offset"),
        ));
    }
    Ok(write_file_body(
        write_header_section_version(header, version),
        packets,
    ))
}

fn write_file_body(header_section: Vec<u8>, packets: &[Vec<u8>]) -> Vec<u8> {
    let mut out = header_section;
    let mut d = ByteWriter::new();
    d.varint(packets.len() as u64);
    for p in packets {
        d.varint(p.len() as u64);
    }
    let db = d.into_bytes();
    out.extend_from_slice(&db);
    out.extend_from_slice(&crc32fast::hash(&db).to_le_bytes());
    for p in packets {
        out.extend_from_slice(p);
    }
    out
}

/// What precedes a file's packets: the header section and the packet directory.
#[derive(Debug, Clone)]
pub struct Prelude {
    /// The header.
    pub header: Header,
    /// Bytes of the header section (magic to header CRC).
    pub header_bytes: usize,
    /// Bytes of the packet directory (with its CRC).
    pub directory_bytes: usize,
    /// Each packet's length, in file order.
    pub packet_lengths: Vec<usize>,
}

impl Prelude {
    /// Bytes before the first packet.
    pub fn len(&self) -> usize {
        self.header_bytes + self.directory_bytes
    }

    /// Whether the prelude is empty (never: a header section has at least 14 bytes).
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Size of the whole file the directory describes.
    pub fn file_bytes(&self) -> u64 {
        self.len() as u64 + self.packet_lengths.iter().map(|&l| l as u64).sum::<u64>()
    }
}

/// Parses the header section and the packet directory from the start of a file as it arrives:
/// `Ok(None)` means the bytes end before the directory does (call again with more); an error is
/// final, and comes as early as the bytes allow (wrong magic after 1 byte, an oversized header
/// length after 10).
pub fn parse_prelude(bytes: &[u8]) -> Result<Option<Prelude>, FormatError> {
    let n = bytes.len().min(MAGIC.len());
    if bytes[..n] != MAGIC[..n] {
        return Err(FormatError::BadMagic(bytes[..n].to_vec()));
    }
    if bytes.len() < 10 {
        return Ok(None);
    }
    let mut r = ByteReader::new(&bytes[4..10], "file header");
    let version = r.u16()?;
    check_version(version)?;
    let len = header_length(r.u32()?)?;
    if bytes.len() < 14 + len {
        return Ok(None);
    }
    let (header, header_bytes) = read_header_section(&bytes[..14 + len])?;
    match read_directory(&header, &bytes[header_bytes..]) {
        Ok((packet_lengths, directory_bytes)) => Ok(Some(Prelude {
            header,
            header_bytes,
            directory_bytes,
            packet_lengths,
        })),
        // The directory is read to its end: running out of bytes means "more to come".
        Err(FormatError::Truncated { .. }) => Ok(None),
        Err(e) => Err(e),
    }
}

/// Reads the packet directory at the start of `rest`: the packet lengths and the directory's
/// size with its CRC.
fn read_directory(header: &Header, rest: &[u8]) -> Result<(Vec<usize>, usize), FormatError> {
    let mut r = ByteReader::new(rest, "packet directory");
    let max_packets = header.tile_count() as u64 * header.layer_bounds.len() as u64;
    let count = r.varint_max(max_packets, "packet count")? as usize;
    // Each directory entry takes at least one byte: bound the allocation by the input.
    if count > r.remaining() {
        return Err(FormatError::Truncated {
            what: "packet directory",
            needed: count as u64,
            available: r.remaining() as u64,
        });
    }
    let mut lens = Vec::with_capacity(count);
    for _ in 0..count {
        lens.push(r.varint_max(MAX_PACKET_BYTES as u64, "packet length")? as usize);
    }
    let dir_len = r.position();
    let stored = r.u32()?;
    let computed = crc32fast::hash(&rest[..dir_len]);
    if stored != computed {
        return Err(FormatError::Checksum {
            what: "packet directory",
            stored,
            computed,
        });
    }
    Ok((lens, dir_len + 4))
}

/// Parses a file's header and packet directory (packets are checked when decoded).
pub fn parse_file(bytes: &[u8]) -> Result<WspFile<'_>, FormatError> {
    let (header, used) = read_header_section(bytes)?;
    let (lens, directory_bytes) = read_directory(&header, &bytes[used..])?;
    let mut r = ByteReader::new(&bytes[used + directory_bytes..], "packets");
    let mut packets = Vec::with_capacity(lens.len());
    for len in lens {
        packets.push(r.take(len)?);
    }
    if r.remaining() != 0 {
        return Err(invalid(
            "file",
            format!("{} trailing bytes after the last packet", r.remaining()),
        ));
    }
    Ok(WspFile {
        header,
        header_bytes: used,
        directory_bytes,
        packets,
    })
}
