//! The header and its section: the [`Header`] a packet needs to decode, its accessors, and
//! reading and writing it in each supported format version (magic, version, length, header,
//! CRC-32), with the version and size checks a reader applies before trusting it.

use super::bytes::{ByteReader, ByteWriter};
use super::{
    bricked, fast, invalid, CoderKind, ColorInfo, ColorKind, FormatError, HuffmanTables,
    SubstreamParams, CATEGORY_ALPHABET, COARSE_LAYER_VERSION, COMPACT_HEADER_VERSION,
    FAST_CODER_VERSION, MAGIC, MAX_CAP_STEPS, MAX_HEADER_BYTES, MAX_LAYERS, MAX_MARGIN, VERSION,
};
use crate::entropy::bits::{BitReader, BitWriter};
use crate::entropy::huffman::HuffmanCode;
use crate::family::Family;
use crate::layout::{Band, Geometry, MAX_LEVELS};
use crate::volume::Placement;

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
    /// [`MAGNITUDE_CONTEXTS_VERSION`](super::MAGNITUDE_CONTEXTS_VERSION)).
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
        magnitude_threshold(&self.geometry, &self.color, self.score_threshold, substream)
    }

    fn write_version(&self, w: &mut ByteWriter, version: u16) {
        let g = &self.geometry;
        for d in g.dims {
            w.varint(d as u64);
        }
        let compact = version >= COMPACT_HEADER_VERSION;
        let number = |w: &mut ByteWriter, v: f64| {
            if compact {
                write_number(w, v);
            } else {
                w.f64(v);
            }
        };
        if compact {
            write_spacing(w, g.spacing);
        } else {
            for s in g.spacing {
                w.f32(s);
            }
        }
        match &self.placement {
            _ if version < 4 => {}
            None => w.u8(0),
            Some(p) => {
                w.u8(1);
                for v in p.origin.iter().chain(p.directions.iter().flatten()) {
                    number(w, *v);
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
                    number(w, v);
                }
            }
            for v in self.color.mean {
                number(w, v);
            }
        } else if version >= 5 {
            number(w, self.color.mean[0]);
        }
        for v in &self.color.importance[..self.channels] {
            number(w, *v);
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
            number(w, *b);
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
        if compact && self.coder.quantizes_by_threshold() {
            self.write_predicted_deltas(w);
        } else {
            for s in self.substreams.iter().flatten() {
                w.f32(s.w0);
                w.f32(s.delta);
            }
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

    /// The substreams' parameters in the compact header, for a coder that quantizes by the
    /// threshold: the step scale (a [`write_number`]), then per present substream Δ as the
    /// zigzag varint of its bits' difference from [`predicted_delta`]'s and the cap w₀ as a
    /// varint: 0 for none (+∞), 1 for an f32 that follows, 2 + n for the cap n sixteenths of
    /// Δ above the smallest magnitude ([`SubstreamParams::cap_at`]). The scale is the first
    /// substream's Δ over its smallest magnitude (rounded to f32), so a file written at one
    /// step (the compressor's `--step`) has differences of 0 or ±1 bit: one byte each. What
    /// the compressor writes takes two bytes a substream; any Δ and w₀ still round-trip
    /// exactly, at up to nine.
    fn write_predicted_deltas(&self, w: &mut ByteWriter) {
        let scale = self
            .substreams
            .iter()
            .enumerate()
            .find_map(|(i, s)| {
                let t = self.magnitude_threshold(i);
                let s = s.filter(|s| s.delta > 0.0 && t > 0.0 && t.is_finite())?;
                let scale = (s.delta as f64 / t) as f32 as f64;
                scale.is_finite().then_some(scale)
            })
            .unwrap_or(0.0);
        write_number(w, scale);
        for (i, s) in self.substreams.iter().enumerate() {
            let Some(s) = s else { continue };
            let threshold = self.magnitude_threshold(i);
            let predicted = predicted_delta(threshold, scale);
            let difference = s.delta.to_bits() as i64 - predicted.to_bits() as i64;
            w.varint(((difference << 1) ^ (difference >> 63)) as u64);
            if s.w0 == f32::INFINITY {
                w.varint(0);
            } else if let Some(steps) = s.cap_steps(threshold) {
                w.varint(2 + steps as u64);
            } else {
                w.varint(1);
                w.f32(s.w0);
            }
        }
    }

    fn read(r: &mut ByteReader, version: u16) -> Result<Header, FormatError> {
        const W: &str = "header";
        let mut dims = [0usize; 3];
        for d in &mut dims {
            *d = r.varint_max(1 << 24, "dimension")? as usize;
        }
        crate::volume::checked_voxels(dims).map_err(|e| invalid(W, e.to_string()))?;
        let compact = version >= COMPACT_HEADER_VERSION;
        let number = |r: &mut ByteReader| {
            if compact {
                read_number(r)
            } else {
                r.f64()
            }
        };
        let spacing = if compact {
            read_spacing(r)?
        } else {
            [r.f32()?, r.f32()?, r.f32()?]
        };
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
                    *v = number(r)?;
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
                    *v = number(r)?;
                }
            }
            for v in &mut color.mean {
                *v = number(r)?;
            }
        } else if version >= 5 {
            color.mean[0] = number(r)?;
        }
        for v in &mut color.importance[..channels] {
            *v = number(r)?;
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
            let b = number(r)?;
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
                            "a coarse layer needs two layers or more and a decomposition; \
                             {nl} layers, M = {}",
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
        let predicted = compact && coder.quantizes_by_threshold();
        let scale = if predicted { read_number(r)? } else { 0.0 };
        if !(scale.is_finite() && scale >= 0.0) {
            return Err(invalid(W, format!("step scale {scale}")));
        }
        let mut substreams = Vec::with_capacity(nsub);
        for i in 0..nsub {
            if bitmap[i / 8] & (1 << (i % 8)) != 0 {
                let (w0, delta) = if predicted {
                    let t = magnitude_threshold(&geometry, &color, score_threshold, i);
                    let zigzag = r.varint_max(u32::MAX as u64 * 2 + 1, "delta difference")?;
                    let difference = (zigzag >> 1) as i64 ^ -((zigzag & 1) as i64);
                    let bits = predicted_delta(t, scale).to_bits() as i64 + difference;
                    // Finite and not negative (−0.0 included, which version 12 holds too).
                    let delta = u32::try_from(bits)
                        .ok()
                        .filter(|b| *b <= f32::MAX.to_bits() || *b == (-0.0f32).to_bits())
                        .map_or(f32::NAN, f32::from_bits);
                    let cap = r.varint_max(2 + MAX_CAP_STEPS as u64, "cap")?;
                    let w0 = match cap {
                        0 => f32::INFINITY,
                        1 => match r.f32()? {
                            w0 if w0.is_finite() => w0,
                            w0 => return Err(invalid(W, format!("substream {i}: w0 {w0}"))),
                        },
                        n => SubstreamParams::cap_at(t, delta, n as u32 - 2),
                    };
                    (w0, delta)
                } else {
                    (r.f32()?, r.f32()?)
                };
                let w0_fine = w0.is_finite() || (predicted && w0 == f32::INFINITY);
                if !(w0_fine && delta.is_finite() && w0 >= 0.0 && delta >= 0.0) {
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
            Some(fast::FastTables::read(&mut BitReader::new(blob), version)?)
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

/// Smallest magnitude a kept coefficient of `substream` can have under `score_threshold`:
/// √(threshold / (‖basis‖²·I)), 0 where the weight is 0. The compressor's quantizer steps
/// and the compact header's predicted Δ both come from it, so they agree bit for bit.
pub fn magnitude_threshold(
    geometry: &Geometry,
    color: &ColorInfo,
    score_threshold: f64,
    substream: usize,
) -> f64 {
    let nb = geometry.band_count();
    let band = geometry.bands()[substream % nb];
    let weight = geometry.basis_norm2(band) * color.importance[(substream / nb).min(2)];
    if weight > 0.0 {
        (score_threshold / weight).sqrt()
    } else {
        0.0
    }
}

/// The Δ a threshold-quantizing encoder gives a substream whose smallest magnitude is
/// `threshold` at step `scale` (but where [`SubstreamParams::of_magnitudes`] floors it): the
/// compact header codes each Δ as its difference from this.
fn predicted_delta(threshold: f64, scale: f64) -> f32 {
    // 0 · ∞ (a substream whose threshold magnitude overflows) is a NaN whose bits Rust does not
    // pin down across platforms: predict 0 there, so that every reader decodes the same Δ.
    let predicted = scale * threshold;
    if predicted.is_nan() {
        0.0
    } else {
        predicted as f32
    }
}

/// A compact header's number: one tag byte, and for the tags that need them the value's f32 or
/// f64 bytes. Header fields are mostly 0, 1, −1 or +∞ (offsets, importances, placement
/// directions, the first layer bound), which then take one byte instead of eight.
mod number_tag {
    pub const ZERO: u8 = 0;
    pub const ONE: u8 = 1;
    pub const MINUS_ONE: u8 = 2;
    pub const INFINITY: u8 = 3;
    pub const F32: u8 = 4;
    pub const F64: u8 = 5;
}

fn write_number(w: &mut ByteWriter, v: f64) {
    use number_tag::*;
    let bits = v.to_bits();
    if bits == 0f64.to_bits() {
        w.u8(ZERO);
    } else if bits == 1f64.to_bits() {
        w.u8(ONE);
    } else if bits == (-1f64).to_bits() {
        w.u8(MINUS_ONE);
    } else if bits == f64::INFINITY.to_bits() {
        w.u8(INFINITY);
    } else if (v as f32 as f64).to_bits() == bits {
        w.u8(F32);
        w.f32(v as f32);
    } else {
        w.u8(F64);
        w.f64(v);
    }
}

fn read_number(r: &mut ByteReader) -> Result<f64, FormatError> {
    use number_tag::*;
    Ok(match r.u8()? {
        ZERO => 0.0,
        ONE => 1.0,
        MINUS_ONE => -1.0,
        INFINITY => f64::INFINITY,
        F32 => r.f32()? as f64,
        F64 => r.f64()?,
        tag => {
            return Err(invalid(
                "header",
                format!("number tag {tag}; 0 to {F64} allowed"),
            ))
        }
    })
}

/// The compact header's voxel spacing: a tag (0: unit spacing, 1: one f32 for every axis, 2:
/// one f32 per axis), then the f32s it names.
fn write_spacing(w: &mut ByteWriter, spacing: [f32; 3]) {
    let bits = spacing.map(f32::to_bits);
    if bits == [1f32.to_bits(); 3] {
        w.u8(0);
    } else if bits[1] == bits[0] && bits[2] == bits[0] {
        w.u8(1);
        w.f32(spacing[0]);
    } else {
        w.u8(2);
        for s in spacing {
            w.f32(s);
        }
    }
}

fn read_spacing(r: &mut ByteReader) -> Result<[f32; 3], FormatError> {
    Ok(match r.u8()? {
        0 => [1.0; 3],
        1 => [r.f32()?; 3],
        2 => [r.f32()?, r.f32()?, r.f32()?],
        tag => {
            return Err(invalid(
                "header",
                format!("spacing tag {tag}; 0 to 2 allowed"),
            ))
        }
    })
}

/// Serializes the header section (magic, version, header, CRC) in the version its packets were
/// coded for ([`Header::version`]; [`VERSION`] for a header that names no plain version), so
/// that a file read and written again keeps the version its packets decode in.
pub fn write_header_section(header: &Header) -> Vec<u8> {
    let version = if super::is_plain_version(header.version) {
        header.version
    } else {
        VERSION
    };
    write_header_section_version(header, version)
}

pub(super) fn write_header_section_version(header: &Header, version: u16) -> Vec<u8> {
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
pub(super) fn check_version(version: u16) -> Result<(), FormatError> {
    if super::is_plain_version(version) {
        Ok(())
    } else if bricked::is_bricked_version(version) {
        Err(FormatError::Bricked)
    } else if version == super::series::SERIES_VERSION {
        Err(FormatError::Series)
    } else {
        Err(FormatError::UnsupportedVersion {
            found: version,
            supported: VERSION,
        })
    }
}

/// The header section's declared length, refused beyond [`MAX_HEADER_BYTES`].
pub(super) fn header_length(len: u32) -> Result<usize, FormatError> {
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
