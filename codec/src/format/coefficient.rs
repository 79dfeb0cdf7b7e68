//! What every coder of packets shares: the coefficient (channel, band, position, value), a
//! packet to encode, a packet's framing (what a decoder is handed), where its bits went, and the bounds a decoder puts on a packet's declared
//! count before it allocates. The dispatcher (`packet`) and the coders (`paper`, `sigmap`,
//! `fast`) all import these from here, and none from another.

use super::Header;
use crate::layout::Band;

/// Most coefficients a packet may declare per payload byte (plus one byte's worth), so that a
/// small hostile packet cannot make the decoder allocate and loop for a huge declared count.
/// The Huffman and range syntaxes spend at least one bit per coefficient; the sigmap coder's
/// adaptive contexts can spend less on very regular data (and its range coder drops trailing
/// zero bytes), so it pads its payload with zero bytes, which decode as if absent, up to this
/// bound.
pub(crate) const MAX_COEFFICIENTS_PER_PAYLOAD_BYTE: usize = 64;

/// Most coefficients a packet decoder reserves room for before decoding any.
pub(crate) const INITIAL_CAPACITY: usize = 1 << 16;

/// One coefficient: which channel and band, its position in the band grid, its value.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Coefficient {
    /// Channel (0 for intensity volumes).
    pub channel: u8,
    /// Band (level, type).
    pub band: Band,
    /// Position in the band's coefficient grid (global, not tile-local).
    pub pos: [u32; 3],
    /// Value.
    pub value: f32,
}

impl Coefficient {
    /// The coefficient of `value` at `cell` of a tile's band region whose first cell is
    /// `origin` (the coders work in tile-local cells; a coefficient's position is global).
    #[inline]
    pub(crate) fn in_region(
        channel: u8,
        band: Band,
        origin: [u32; 3],
        cell: [u32; 3],
        value: f32,
    ) -> Coefficient {
        Coefficient {
            channel,
            band,
            pos: [
                cell[0] + origin[0],
                cell[1] + origin[1],
                cell[2] + origin[2],
            ],
            value,
        }
    }

    /// Every coefficient of one channel's dense (Mallat-layout) array, in array order, zeros
    /// included: what a lossless stream of that channel would deliver.
    pub fn all_of(
        geometry: &crate::layout::Geometry,
        channel: u8,
        values: &[f64],
    ) -> Vec<Coefficient> {
        values
            .iter()
            .enumerate()
            .map(|(i, v)| {
                let (band, pos) = geometry.locate(i);
                Coefficient {
                    channel,
                    band,
                    pos: pos.map(|p| p as u32),
                    value: *v as f32,
                }
            })
            .collect()
    }
}

/// A packet to encode: one tile's coefficients (exact values) in coding order.
#[derive(Debug, Clone)]
pub struct PacketInput {
    /// Tile index.
    pub tile: usize,
    /// Quality layer (rank of this packet within its tile).
    pub layer: usize,
    /// Coefficients in coding order.
    pub coefficients: Vec<Coefficient>,
}

/// Where the bits of the encoded packets went (paper Fig. 16).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct SizeBreakdown {
    /// Bits spent on run tags and run lengths (type, depth, channel).
    pub tag_bits: f64,
    /// Bits spent on positions.
    pub position_bits: f64,
    /// Bits spent on signs.
    pub sign_bits: f64,
    /// Bits spent on value steps.
    pub value_bits: f64,
    /// Framing bytes (packet headers, summaries, lengths, checksums).
    pub framing_bytes: u64,
}

/// A tile's region of a band of `level`: its origin in band cells and its extent (0 along an
/// axis where the tile holds none of the band).
pub(super) fn region_extent(
    header: &Header,
    tile: usize,
    level: u8,
    band_dims: [usize; 3],
) -> ([u32; 3], [u32; 3]) {
    let origin = header.tile_origin(tile);
    let l = level as usize;
    let mut lo = [0u32; 3];
    let mut hi = [0u32; 3];
    for a in 0..3 {
        let o = origin[a] >> l;
        let end = ((origin[a] + header.tile) >> l).min(band_dims[a]);
        lo[a] = o as u32;
        hi[a] = end.saturating_sub(o) as u32;
    }
    (lo, hi)
}

/// A packet's framing: everything but the coded coefficients (cheap to read: a viewer or a
/// cache ranks packets by it before decoding any).
#[derive(Debug, Clone, PartialEq)]
pub struct PacketFraming<'a> {
    /// Tile index.
    pub tile: usize,
    /// Layer.
    pub layer: usize,
    /// Declared coefficient count (checked against the payload size and the tile's capacity).
    pub count: usize,
    /// Energy per band (as `packet::DecodedPacket::summary`).
    pub summary: Vec<(Band, f64)>,
    /// The coded coefficients.
    pub payload: &'a [u8],
}
