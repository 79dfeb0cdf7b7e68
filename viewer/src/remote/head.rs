//! The head of a published volume: its header and packet index read in one request (more when
//! they are larger), from the indexed layout or a plain `.wsp` (header and directory, packets
//! then in file order), checked against the object's size.

use super::object::Object;
use crate::source::{SourceError, SourceStatus};
use bytes::Bytes;
use std::sync::Mutex;
use wavesplat_codec::format::index::{
    read_indexed_head, HeadRead, IndexedHead, PacketMeta, HEAD_READ_BYTES,
};
use wavesplat_codec::format::{parse_prelude, FormatError, Header};

/// The volume's head as read: the indexed layout, or a plain `.wsp` (header and directory only:
/// packets are then requested in file order, all of them).
pub(super) struct Head {
    /// The object's first bytes as read for the head (packets inside them need no request).
    pub(super) first: Bytes,
    pub(super) header: Header,
    pub(super) packets: Vec<PacketMeta>,
    /// Where packet offsets start in the object.
    pub(super) base: u64,
    pub(super) object_bytes: u64,
    pub(super) indexed: bool,
}

pub(super) async fn read_head(
    object: &Object,
    url: &str,
    status: &Mutex<SourceStatus>,
) -> Result<Head, SourceError> {
    let (first, object_bytes) = object.read(Some(0..HEAD_READ_BYTES)).await?;
    let mut bytes = first.to_vec();
    count(status, bytes.len() as u64);
    let corrupt = |e: FormatError| SourceError::Remote(format!("{url}: {e}"));
    if bytes.starts_with(wavesplat_codec::format::MAGIC) {
        // A plain .wsp: header and directory, packets in file order.
        loop {
            if let Some(p) = parse_prelude(&bytes).map_err(corrupt)? {
                let mut offset = p.len() as u64;
                let packets = p
                    .packet_lengths
                    .iter()
                    .map(|&len| {
                        let m = PacketMeta {
                            tile: 0,
                            layer: 0,
                            len: len as u32,
                            offset,
                            summary: Vec::new(),
                        };
                        offset += len as u64;
                        m
                    })
                    .collect();
                if p.file_bytes() != object_bytes {
                    return Err(SourceError::Remote(format!(
                        "{url} holds {object_bytes} bytes, its directory describes {}",
                        p.file_bytes()
                    )));
                }
                return Ok(Head {
                    first: Bytes::from(bytes),
                    header: p.header,
                    packets,
                    base: 0,
                    object_bytes,
                    indexed: false,
                });
            }
            if bytes.len() as u64 >= object_bytes {
                return Err(SourceError::Remote(format!(
                    "{url} ends inside its header or directory"
                )));
            }
            let end = (bytes.len() as u64 * 2).min(object_bytes);
            let (more, _) = object.read(Some(bytes.len() as u64..end)).await?;
            count(status, more.len() as u64);
            bytes.extend_from_slice(&more);
        }
    }
    let head: IndexedHead = loop {
        match read_indexed_head(&bytes).map_err(corrupt)? {
            HeadRead::Indexed(h) => break *h,
            HeadRead::Need(n) if n as u64 > object_bytes || n <= bytes.len() => {
                return Err(SourceError::Remote(format!(
                    "{url} ends inside its head ({object_bytes} bytes)"
                )))
            }
            HeadRead::Need(n) => {
                let (more, _) = object.read(Some(bytes.len() as u64..n as u64)).await?;
                count(status, more.len() as u64);
                bytes.extend_from_slice(&more);
            }
        }
    };
    if head.object_bytes() != object_bytes {
        return Err(SourceError::Remote(format!(
            "{url} holds {object_bytes} bytes, its head describes {}: truncated or not this volume",
            head.object_bytes()
        )));
    }
    Ok(Head {
        first: Bytes::from(bytes),
        header: head.header,
        packets: head.packets,
        base: head.wsp_offset,
        object_bytes,
        indexed: true,
    })
}

fn count(status: &Mutex<SourceStatus>, bytes: u64) {
    let mut s = status.lock().unwrap_or_else(|e| e.into_inner());
    s.requests += 1;
    s.received_bytes += bytes;
}
