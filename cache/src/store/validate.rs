//! What an upload must satisfy before the store keeps it: the limits (sizes, counts, concurrent
//! uploads), a volume name's rules, the content hash, and the index of a file checked packet by
//! packet against its prelude.

use crate::error::CacheError;
use crate::model::{PacketMeta, VolumeIndex};
use wavesplat_codec::format::packet::{decode_packet_within, DecodeBudget};
use wavesplat_codec::format::{parse_file, Prelude};

/// Limits applied to uploads.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Limits {
    /// Largest accepted upload (bytes).
    pub max_upload_bytes: u64,
    /// Largest accepted packet (bytes); bounds every streamed message.
    pub max_packet_bytes: u64,
    /// Largest header section plus packet directory (bytes).
    pub max_prelude_bytes: u64,
    /// Uploads validated at once; more wait their turn.
    pub max_concurrent_uploads: usize,
    /// Bytes all uploads together may hold in memory (the prelude, then the largest packet,
    /// of each); an upload waits until its share is free. At least `max_packet_bytes` and
    /// `max_prelude_bytes`.
    pub max_buffered_bytes: u64,
    /// What validating one packet may cost (checked against its declared count first).
    pub decode: DecodeBudget,
}

impl Default for Limits {
    fn default() -> Self {
        Limits {
            max_upload_bytes: 1 << 30,
            max_packet_bytes: 16 << 20,
            max_prelude_bytes: 16 << 20,
            max_concurrent_uploads: 16,
            max_buffered_bytes: 256 << 20,
            decode: DecodeBudget {
                max_coefficients: 1 << 24,
                max_bytes: 1 << 30,
            },
        }
    }
}

pub use crate::model::MAX_NAME_BYTES;

/// Checks a volume name: 1..=255 bytes, no control characters.
pub fn validate_name(name: &str) -> Result<(), CacheError> {
    if name.is_empty() || name.len() > MAX_NAME_BYTES || name.chars().any(char::is_control) {
        return Err(CacheError::InvalidRequest(format!(
            "volume name {name:?} must be 1..={MAX_NAME_BYTES} bytes without control characters"
        )));
    }
    Ok(())
}

/// Decodes packet `i` and returns its index entry and the number of coefficients it holds.
pub(super) fn index_packet(
    prelude: &Prelude,
    i: usize,
    bytes: &[u8],
    offset: u64,
    budget: &DecodeBudget,
) -> Result<(PacketMeta, u64), CacheError> {
    let d = decode_packet_within(&prelude.header, bytes, budget)
        .map_err(|e| CacheError::InvalidUpload(format!("packet {i}: {e}")))?;
    let held = d.coefficients.len() as u64;
    Ok((
        PacketMeta {
            tile: d.tile as u32,
            layer: d.layer as u32,
            len: bytes.len() as u32,
            offset,
            summary: d.summary,
        },
        held,
    ))
}

/// Refuses a file whose packets do not hold the coefficients its header declares.
pub(super) fn check_kept(prelude: &Prelude, held: u64) -> Result<(), CacheError> {
    wavesplat_codec::format::check_kept(&prelude.header, held)
        .map_err(|e| CacheError::InvalidUpload(e.to_string()))
}

/// Validates a whole file of one volume: parses it, decodes every packet, and builds its index
/// (a bricked container is validated as it is uploaded, [`super::Upload`]).
pub fn index_file(bytes: &[u8], limits: &Limits) -> Result<VolumeIndex, CacheError> {
    let file = parse_file(bytes)?;
    let prelude = Prelude {
        header: file.header.clone(),
        header_bytes: file.header_bytes,
        directory_bytes: file.directory_bytes,
        packet_lengths: file.packets.iter().map(|p| p.len()).collect(),
    };
    let mut packets = Vec::with_capacity(file.packets.len());
    let mut offset = prelude.len() as u64;
    let mut held = 0u64;
    for (i, p) in file.packets.iter().enumerate() {
        check_packet_size(p.len(), limits)?;
        let (meta, n) = index_packet(&prelude, i, p, offset, &limits.decode)?;
        packets.push(meta);
        held += n;
        offset += p.len() as u64;
    }
    check_kept(&prelude, held)?;
    Ok(VolumeIndex {
        header_bytes: bytes[..file.header_bytes].to_vec(),
        header: file.header,
        packets,
        bricked: None,
        series: None,
    })
}

pub(super) fn check_packet_size(len: usize, limits: &Limits) -> Result<(), CacheError> {
    if len as u64 > limits.max_packet_bytes {
        return Err(CacheError::TooLarge {
            what: "packet",
            size: len as u64,
            limit: limits.max_packet_bytes,
        });
    }
    Ok(())
}
