//! Packets: self-contained runs of one tile's coefficients. This module frames them and sends
//! each to its coder: the paper's syntax (`paper`, Huffman or range), the significance maps
//! (`sigmap`) or the fast coder (`fast`); the types they share live in `coefficient`.
//!
//! Framing: tile (varint), layer (u8), coefficient count (varint), energy summary, payload length
//! (varint), payload, CRC-32 of everything before it. The summary is a bit mask of the bands with
//! energy (⌈bands/8⌉ bytes, band b in bit b % 8 of byte b / 8); if any, the largest code
//! c = round(8·log2(energy)) as i16, then per band in the mask one byte, the amount its code lies
//! below the largest (energies more than 2^−31.9 below the packet's largest band read back as
//! that floor, which no priority can tell apart from nothing).

use super::bytes::{ByteReader, ByteWriter};
pub use super::coefficient::PacketFraming;
use super::coefficient::MAX_COEFFICIENTS_PER_PAYLOAD_BYTE;
pub use super::coefficient::{Coefficient, PacketInput, SizeBreakdown};
use super::{invalid, CoderKind, FormatError, Header};
use crate::layout::Band;

/// Result of encoding a set of packets.
#[derive(Debug, Clone)]
pub struct EncodedPackets {
    /// Packet bytes, in input order.
    pub packets: Vec<Vec<u8>>,
    /// The decoder's view of every packet's coefficients (quantized values), in input order.
    pub reconstruction: Vec<Vec<Coefficient>>,
    /// Where the payload bits went. Exact for Huffman; for the range coder the per-element split
    /// is the adaptive models' ideal cost, scaled to the actual payload size.
    pub breakdown: SizeBreakdown,
}

/// What decoding may cost a caller that decodes what others send: coefficients, and bytes of
/// memory for them (and, for a whole volume, for its reconstruction). Checked against what a
/// packet or file *declares* before anything is allocated or decoded, so a small hostile input
/// is refused at once with an error saying what it would have cost.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct DecodeBudget {
    /// Most coefficients one decode call may produce.
    pub max_coefficients: u64,
    /// Most bytes of memory one decode call may allocate for its results.
    pub max_bytes: u64,
}

impl Default for DecodeBudget {
    /// 256 M coefficients and 8 GiB: any volume this machine class compresses, while a
    /// hostile file declaring far more is refused.
    fn default() -> Self {
        DecodeBudget {
            max_coefficients: 1 << 28,
            max_bytes: 8 << 30,
        }
    }
}

impl DecodeBudget {
    /// No limit beyond the format's own bounds.
    pub const UNLIMITED: DecodeBudget = DecodeBudget {
        max_coefficients: u64::MAX,
        max_bytes: u64::MAX,
    };

    /// Checks `count` coefficients against the budget.
    pub fn check_coefficients(&self, count: u64) -> Result<(), FormatError> {
        let bytes = count.saturating_mul(std::mem::size_of::<Coefficient>() as u64);
        if count > self.max_coefficients {
            return Err(FormatError::OverBudget {
                what: "coefficients",
                need: count,
                budget: self.max_coefficients,
            });
        }
        self.check_bytes(bytes)
    }

    /// Checks `bytes` of memory against the budget.
    pub fn check_bytes(&self, bytes: u64) -> Result<(), FormatError> {
        if bytes > self.max_bytes {
            return Err(FormatError::OverBudget {
                what: "bytes of memory",
                need: bytes,
                budget: self.max_bytes,
            });
        }
        Ok(())
    }
}

/// The coefficient count a packet declares (after checking its framing and checksum, without
/// decoding its payload).
pub fn declared_count(header: &Header, bytes: &[u8]) -> Result<u64, FormatError> {
    Ok(read_framing(header, bytes)?.count as u64)
}

/// A decoded packet.
#[derive(Debug, Clone, PartialEq)]
pub struct DecodedPacket {
    /// Tile index.
    pub tile: usize,
    /// Layer.
    pub layer: usize,
    /// Energy (Σ w̃²·‖basis‖²·I over channels) per band with coefficients in this packet.
    pub summary: Vec<(Band, f64)>,
    /// Coefficients (quantized values).
    pub coefficients: Vec<Coefficient>,
    /// Where this packet's bits went (see [`SizeBreakdown`]).
    pub breakdown: SizeBreakdown,
}

/// Code for an energy in the summary: round(8·log2(E)), clamped to i16; 0 energy is omitted.
fn energy_code(e: f64) -> i16 {
    (8.0 * e.log2()).round().clamp(-32767.0, 32767.0) as i16
}

fn energy_from_code(c: i32) -> f64 {
    (c as f64 / 8.0).exp2()
}

/// Per-band energy summary of reconstructed coefficients.
fn summarize(header: &Header, coeffs: &[Coefficient]) -> Vec<(usize, f64)> {
    let nb = header.geometry.band_count();
    let mut e = vec![0.0f64; nb];
    for c in coeffs {
        let bi = header.geometry.band_index(c.band).expect("valid band");
        e[bi] += (c.value as f64).powi(2)
            * header.geometry.basis_norm2(c.band)
            * header.importance(c.channel as usize);
    }
    e.into_iter()
        .enumerate()
        .filter(|(_, v)| *v > 0.0 && v.is_finite())
        .collect()
}

fn frame(header: &Header, input: &PacketInput, recon: &[Coefficient], payload: &[u8]) -> Vec<u8> {
    let mut w = ByteWriter::new();
    w.varint(input.tile as u64);
    w.u8(input.layer as u8);
    w.varint(input.coefficients.len() as u64);
    let summary = summarize(header, recon);
    let nb = header.geometry.band_count();
    let mut mask = vec![0u8; nb.div_ceil(8)];
    for (bi, _) in &summary {
        mask[bi / 8] |= 1 << (bi % 8);
    }
    mask.iter().for_each(|m| w.u8(*m));
    if let Some(top) = summary.iter().map(|(_, e)| energy_code(*e)).max() {
        w.u16(top as u16);
        for (_, e) in &summary {
            w.u8((top as i32 - energy_code(*e) as i32).clamp(0, 255) as u8);
        }
    }
    w.varint(payload.len() as u64);
    w.bytes(payload);
    let crc = crc32fast::hash(w.as_slice());
    let mut bytes = w.into_bytes();
    bytes.extend_from_slice(&crc.to_le_bytes());
    bytes
}

/// Frames coded payloads (in input order) into packets, adding their framing bytes to
/// `breakdown`.
fn frame_all(
    header: &Header,
    inputs: &[PacketInput],
    payloads: Vec<Vec<u8>>,
    reconstruction: Vec<Vec<Coefficient>>,
    mut breakdown: SizeBreakdown,
) -> EncodedPackets {
    let packets = inputs
        .iter()
        .zip(&payloads)
        .zip(&reconstruction)
        .map(|((input, payload), recon)| {
            let framed = frame(header, input, recon, payload);
            breakdown.framing_bytes += (framed.len() - payload.len()) as u64;
            framed
        })
        .collect();
    EncodedPackets {
        packets,
        reconstruction,
        breakdown,
    }
}

/// Quantizes and entropy-codes packets. For the Huffman coder the tables are fitted to these
/// packets and stored into `header.tables`; `header.substreams` must already hold the
/// quantization parameters of every substream that appears.
pub fn encode_packets(header: &mut Header, inputs: &[PacketInput]) -> EncodedPackets {
    // A header that names no plain version is written as the current one
    // (`write_header_section`): code its packets for that version too.
    if !super::is_plain_version(header.version) {
        header.version = super::VERSION;
    }
    header.fast_tables = None;
    let (payloads, reconstruction, breakdown) = match header.coder {
        CoderKind::Huffman | CoderKind::Range => super::paper::encode_packets(header, inputs),
        CoderKind::Sigmap => {
            header.tables = None;
            // Packets are independent: code them in parallel, keep them in input order.
            let code = |input: &PacketInput| {
                super::sigmap::encode(header, input.tile, input.layer, &input.coefficients)
            };
            #[cfg(feature = "rayon")]
            let coded: Vec<_> = {
                use rayon::prelude::*;
                inputs.par_iter().map(code).collect()
            };
            #[cfg(not(feature = "rayon"))]
            let coded: Vec<_> = inputs.iter().map(code).collect();
            let mut breakdown = SizeBreakdown::default();
            let mut payloads = Vec::with_capacity(inputs.len());
            let mut reconstruction = Vec::with_capacity(inputs.len());
            for (payload, recon, bd) in coded {
                breakdown.tag_bits += bd.tag_bits;
                breakdown.position_bits += bd.position_bits;
                breakdown.sign_bits += bd.sign_bits;
                breakdown.value_bits += bd.value_bits;
                payloads.push(payload);
                reconstruction.push(recon);
            }
            (payloads, reconstruction, breakdown)
        }
        CoderKind::Fast => {
            header.tables = None;
            super::fast::encode_packets(header, inputs)
        }
    };
    frame_all(header, inputs, payloads, reconstruction, breakdown)
}

/// Reads and validates a packet's framing and checksum without decoding its coefficients.
pub fn read_framing<'a>(
    header: &Header,
    bytes: &'a [u8],
) -> Result<PacketFraming<'a>, FormatError> {
    const W: &str = "packet";
    if bytes.len() < 4 {
        return Err(FormatError::Truncated {
            what: W,
            needed: 4,
            available: bytes.len() as u64,
        });
    }
    let (body, crc) = bytes.split_at(bytes.len() - 4);
    let stored = u32::from_le_bytes([crc[0], crc[1], crc[2], crc[3]]);
    let computed = crc32fast::hash(body);
    if stored != computed {
        return Err(FormatError::Checksum {
            what: W,
            stored,
            computed,
        });
    }
    let mut r = ByteReader::new(body, W);
    let tile = r.varint_max(header.tile_count() as u64 - 1, "tile")? as usize;
    let layer = r.u8()? as usize;
    if layer >= header.layer_bounds.len() {
        return Err(invalid(
            W,
            format!("layer {layer} of {}", header.layer_bounds.len()),
        ));
    }
    let count = r.varint()?;
    let nb = header.geometry.band_count();
    let mut present = Vec::with_capacity(nb);
    for byte in 0..nb.div_ceil(8) {
        let m = r.u8()?;
        for bit in 0..8 {
            if m & (1 << bit) != 0 {
                let bi = 8 * byte + bit;
                if bi >= nb {
                    return Err(invalid(W, format!("summary names band {bi} of {nb}")));
                }
                present.push(bi);
            }
        }
    }
    let bands = header.geometry.bands();
    let mut summary = Vec::with_capacity(present.len());
    if !present.is_empty() {
        let top = r.u16()? as i16 as i32;
        for bi in present {
            let code = top - r.u8()? as i32;
            summary.push((bands[bi], energy_from_code(code)));
        }
    }
    let plen = r.varint()? as usize;
    let payload = r.take(plen)?;
    if r.remaining() != 0 {
        return Err(invalid(W, "bytes after the payload"));
    }
    // Bound the count by the payload (the encoders guarantee it: one bit per coefficient for the
    // paper's syntaxes, MAX_COEFFICIENTS_PER_PAYLOAD_BYTE for sigmap), and by the tile's
    // capacity: the wavelet transform is critically sampled, so a tile holds at most as many
    // coefficients per channel as it has voxels of the padded grid.
    let origin = header.tile_origin(tile);
    let capacity = (0..3)
        .map(|a| {
            let end = (origin[a] + header.tile).min(header.geometry.padded[a]);
            end.saturating_sub(origin[a]) as u64
        })
        .fold(header.channels as u64, u64::saturating_mul);
    let per_byte = match header.coder {
        CoderKind::Sigmap => MAX_COEFFICIENTS_PER_PAYLOAD_BYTE as u64,
        CoderKind::Huffman | CoderKind::Range | CoderKind::Fast => 8,
    };
    if count > per_byte.saturating_mul(plen as u64 + 1) || count > capacity {
        return Err(invalid(
            W,
            format!("{count} coefficients in a {plen}-byte payload (tile capacity {capacity})"),
        ));
    }
    Ok(PacketFraming {
        tile,
        layer,
        count: count as usize,
        summary,
        payload,
    })
}

/// Decodes one packet given the header, within the default [`DecodeBudget`]. Validates
/// framing, checksum, every index and every position; never panics on any input.
pub fn decode_packet(header: &Header, bytes: &[u8]) -> Result<DecodedPacket, FormatError> {
    decode_packet_within(header, bytes, &DecodeBudget::default())
}

/// Every packet of `file` decoded as an encoder's input (its tile, layer and coefficients):
/// what coding a file's coefficients again takes (`codec/examples/recode.rs`, `encode.rs`).
pub fn decoded_inputs(file: &super::WspFile<'_>) -> Result<Vec<PacketInput>, FormatError> {
    file.packets
        .iter()
        .map(|p| {
            let d = decode_packet(&file.header, p)?;
            Ok(PacketInput {
                tile: d.tile,
                layer: d.layer,
                coefficients: d.coefficients,
            })
        })
        .collect()
}

/// Decodes one packet given the header, refusing it before decoding if its declared count is
/// over `budget`.
pub fn decode_packet_within(
    header: &Header,
    bytes: &[u8],
    budget: &DecodeBudget,
) -> Result<DecodedPacket, FormatError> {
    let framing = read_framing(header, bytes)?;
    budget.check_coefficients(framing.count as u64)?;
    let plen = framing.payload.len();
    let mut breakdown = SizeBreakdown {
        framing_bytes: (bytes.len() - plen) as u64,
        ..SizeBreakdown::default()
    };
    let decode: PayloadDecoder = match header.coder {
        CoderKind::Huffman | CoderKind::Range => super::paper::decode,
        CoderKind::Sigmap => super::sigmap::decode,
        CoderKind::Fast => super::fast::decode,
    };
    let coefficients = decode(header, &framing, &mut breakdown)?;
    Ok(DecodedPacket {
        tile: framing.tile,
        layer: framing.layer,
        summary: framing.summary,
        coefficients,
        breakdown,
    })
}

/// What each coder's decoder is: the coefficients of a packet whose framing is read (exactly
/// `packet.count` of them, or an error), adding where the payload's bits went to the breakdown.
pub(crate) type PayloadDecoder =
    fn(&Header, &PacketFraming<'_>, &mut SizeBreakdown) -> Result<Vec<Coefficient>, FormatError>;

/// A packet that failed to decode, with its index in the file.
#[derive(Debug, thiserror::Error)]
#[error("packet {index}: {source}")]
pub struct PacketError {
    /// Packet index in the file.
    pub index: usize,
    /// What was wrong.
    #[source]
    pub source: FormatError,
}

/// Decodes `packets`, each on its own (in parallel with the `rayon` feature), within the
/// default [`DecodeBudget`]; the result is in input order. Errors name the packet's file index,
/// `first_index` being that of `packets[0]`.
pub fn decode_packets(
    header: &Header,
    packets: &[&[u8]],
    first_index: usize,
) -> Result<Vec<Vec<Coefficient>>, PacketError> {
    decode_packets_within(header, packets, first_index, &DecodeBudget::default())
}

/// [`decode_packets`] with a budget for all the packets together, checked against their
/// declared counts before any is decoded.
pub fn decode_packets_within(
    header: &Header,
    packets: &[&[u8]],
    first_index: usize,
    budget: &DecodeBudget,
) -> Result<Vec<Vec<Coefficient>>, PacketError> {
    let mut total = 0u64;
    for (i, p) in packets.iter().enumerate() {
        let fail = |source| PacketError {
            index: first_index + i,
            source,
        };
        total = total.saturating_add(declared_count(header, p).map_err(fail)?);
        budget.check_coefficients(total).map_err(fail)?;
    }
    let one = |(i, p): (usize, &&[u8])| {
        decode_packet_within(header, p, &DecodeBudget::UNLIMITED)
            .map(|d| d.coefficients)
            .map_err(|source| PacketError {
                index: first_index + i,
                source,
            })
    };
    #[cfg(feature = "rayon")]
    {
        use rayon::prelude::*;
        packets.par_iter().enumerate().map(one).collect()
    }
    #[cfg(not(feature = "rayon"))]
    {
        packets.iter().enumerate().map(one).collect()
    }
}
