//! The head of a published volume: its header and packet index read in one request (more when
//! they are larger), from the indexed layout or a plain `.wsp` (header and directory, packets
//! then in file order), checked against the object's size; a bricked volume's manifest and
//! every brick's header and index, its packets numbered as one volume's.

use super::object::Object;
use crate::session::{BrickedVolume, SessionBrick};
use crate::source::file::{check_display, check_session_brick};
use crate::source::{SourceError, SourceStatus};
use bytes::Bytes;
use std::sync::Mutex;
use wavesplat_codec::format::index::{
    read_indexed_head, BrickedHead, HeadRead, IndexedHead, PacketMeta, SeriesHead, HEAD_READ_BYTES,
};
use wavesplat_codec::format::{parse_prelude, FormatError, Header};
use wavesplat_codec::view::bricked::{series_brick_header, whole_header};

/// The volume's head as read: the indexed layout, or a plain `.wsp` (header and directory only:
/// packets are then requested in file order, all of them). A bricked volume's packets are
/// numbered brick after brick (global ids, as a session numbers them); its header is the
/// whole's.
pub(super) struct Head {
    /// The object's first bytes as read for the head (packets inside them need no request).
    pub(super) first: Bytes,
    pub(super) header: Header,
    /// Per packet; offsets are from `base` (a bricked volume's: from the container's start).
    pub(super) packets: Vec<PacketMeta>,
    /// A bricked volume's bricks (empty for one volume).
    pub(super) bricks: Vec<SessionBrick>,
    /// Each packet's brick (empty for one volume).
    pub(super) packet_brick: Vec<u32>,
    /// Each brick's weight (of a time point of a series; empty otherwise: 1).
    pub(super) weights: Vec<f32>,
    /// Of a series, its manifest.
    pub(super) series: Option<Box<wavesplat_codec::format::series::SeriesManifest>>,
    /// Where packet offsets start in the object.
    pub(super) base: u64,
    pub(super) object_bytes: u64,
    pub(super) indexed: bool,
}

/// Reads the head of the volume `object`; of a time series, as time point `time_point` (0 for
/// any other volume). `url` names it in messages (redacted: [`super::redacted`]). Every read
/// after the first is held to the object the first saw ([`Object::read`]).
pub(super) async fn read_head(
    object: &Object,
    url: &str,
    status: &Mutex<SourceStatus>,
    time_point: usize,
) -> Result<Head, SourceError> {
    let (mut bytes, object_bytes) = object.read_vec(Some(0..HEAD_READ_BYTES)).await?;
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
                    bricks: Vec::new(),
                    packet_brick: Vec::new(),
                    weights: Vec::new(),
                    series: None,
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
    // The head, and the object length it declares (either layout).
    let (head, declared) = loop {
        let read = read_indexed_head(&bytes).map_err(corrupt)?;
        let declared = match &read {
            HeadRead::Indexed(h) => h.object_bytes(),
            HeadRead::Bricked(h) => h.object_bytes(),
            HeadRead::Series(h) => h.object_bytes(),
            HeadRead::Need(n) if *n as u64 > object_bytes || *n <= bytes.len() => {
                return Err(SourceError::Remote(format!(
                    "{url} ends inside its head ({object_bytes} bytes)"
                )))
            }
            HeadRead::Need(n) => {
                let (more, _) = object.read(Some(bytes.len() as u64..*n as u64)).await?;
                count(status, more.len() as u64);
                bytes.extend_from_slice(&more);
                continue;
            }
        };
        break (read, declared);
    };
    if declared != object_bytes {
        return Err(SourceError::Remote(format!(
            "{url} holds {object_bytes} bytes, its head describes {declared}: truncated or not this volume"
        )));
    }
    let head: IndexedHead = match head {
        HeadRead::Indexed(h) => *h,
        _ if time_point != 0 && !matches!(head, HeadRead::Series(_)) => {
            return Err(SourceError::Unsupported(format!(
                "{url}: time point {time_point} of a volume that is not a time series"
            )))
        }
        HeadRead::Bricked(h) => return Head::bricked(Bytes::from(bytes), *h, object_bytes, url),
        HeadRead::Series(h) => {
            return Head::series(Bytes::from(bytes), *h, object_bytes, url, time_point)
        }
        // The loop above ends only with a head; an incomplete one is an error, not a panic.
        HeadRead::Need(n) => {
            return Err(SourceError::Remote(format!(
                "{url}: its head needs its first {n} bytes, more than were read"
            )))
        }
    };
    Ok(Head {
        first: Bytes::from(bytes),
        header: head.header,
        packets: head.packets,
        bricks: Vec::new(),
        packet_brick: Vec::new(),
        weights: Vec::new(),
        series: None,
        base: head.wsp_offset,
        object_bytes,
        indexed: true,
    })
}

impl Head {
    /// The header packet `id` decodes with (its brick's, for a bricked volume).
    pub(super) fn header_of(&self, id: u32) -> &Header {
        match self.packet_brick.get(id as usize) {
            Some(&b) => &self.bricks[b as usize].header,
            None => &self.header,
        }
    }

    /// The weight packet `id`'s values are scaled by (1 but in a time point of a series).
    pub(super) fn weight_of(&self, id: u32) -> f32 {
        self.packet_brick
            .get(id as usize)
            .and_then(|&b| self.weights.get(b as usize))
            .copied()
            .unwrap_or(1.0)
    }

    /// A published series' head as time point `t`: the bricks of the components it names, in
    /// its order, served as one bricked volume (as [`crate::source::FileSource::open_series_point`]
    /// serves a file's): packets numbered brick after brick, their energies scaled by their
    /// component's weight² and their values by the weight; the whole's offset the weighted
    /// sum of the components'.
    fn series(
        first: Bytes,
        head: SeriesHead,
        object_bytes: u64,
        url: &str,
        t: usize,
    ) -> Result<Head, SourceError> {
        let m = &head.manifest;
        let bad = |m: String| SourceError::Remote(format!("{url}: {m}"));
        let point = m.points.get(t).ok_or_else(|| {
            SourceError::Unsupported(format!(
                "{url}: time point {t}: the series has {}",
                m.points.len()
            ))
        })?;
        let first_brick = head
            .bricks
            .first()
            .ok_or_else(|| bad("a series of no bricks".into()))?;
        let series_header =
            series_brick_header(&m.space, first_brick.brick.header.clone(), head.bricked[0])
                .map_err(|e| bad(e.to_string()))?;
        let mut packets = Vec::new();
        let mut packet_brick = Vec::new();
        let mut bricks: Vec<SessionBrick> = Vec::new();
        let mut weights = Vec::new();
        let mut offset = 0f64;
        for &(c, weight) in &point.terms {
            let of_c: Vec<&wavesplat_codec::format::index::SeriesBrick> =
                head.bricks.iter().filter(|b| b.component == c).collect();
            let Some(b0) = of_c.first() else {
                return Err(bad(format!("component {c} has no bricks")));
            };
            offset += f64::from(weight) * b0.brick.header.color.mean[0];
            let w2 = f64::from(weight) * f64::from(weight);
            for b in of_c {
                let index =
                    u32::try_from(bricks.len()).map_err(|_| bad("too many bricks".into()))?;
                for p in &b.brick.packets {
                    let mut p = p.clone();
                    p.offset += b.offset;
                    p.summary.iter_mut().for_each(|(_, e)| *e *= w2);
                    packets.push(p);
                    packet_brick.push(index);
                }
                bricks.push(SessionBrick {
                    header: b.brick.header.clone(),
                    origin: b.origin,
                    packets: b.brick.packets.len() as u32,
                });
                weights.push(weight);
            }
        }
        if u32::try_from(packets.len()).is_err() {
            return Err(bad(format!(
                "{} packets, more than a source numbers",
                packets.len()
            )));
        }
        let header = crate::bricked::time_point_header(&series_header, m.space.spacing, offset);
        for (i, b) in bricks.iter_mut().enumerate() {
            b.header.color.mean[0] = offset;
            check_display(i, &b.header, &header)?;
        }
        Ok(Head {
            first,
            header,
            packets,
            bricks,
            packet_brick,
            weights,
            series: Some(Box::new(head.manifest)),
            base: head.wsp_offset,
            object_bytes,
            indexed: true,
        })
    }

    /// The volume as a session draws it, when it is bricked.
    pub(super) fn bricked_volume(&self) -> Option<BrickedVolume> {
        if self.bricks.is_empty() {
            return None;
        }
        Some(BrickedVolume {
            whole: self.header.clone(),
            bricks: self.bricks.clone(),
        })
    }

    /// A published bricked volume's head: every brick checked against the manifest and the
    /// first brick, its packets numbered after the previous bricks'.
    fn bricked(
        first: Bytes,
        head: BrickedHead,
        object_bytes: u64,
        url: &str,
    ) -> Result<Head, SourceError> {
        let m = &head.manifest;
        let Some(first_brick) = head.bricks.first() else {
            return Err(SourceError::Remote(format!(
                "{url}: a bricked volume of no bricks"
            )));
        };
        let mut packets = Vec::new();
        let mut packet_brick = Vec::new();
        let mut bricks = Vec::with_capacity(head.bricks.len());
        for (i, (b, entry)) in head.bricks.iter().zip(&m.bricks).enumerate() {
            check_session_brick(i, entry, &b.header, &first_brick.header, m.channels)?;
            let index = u32::try_from(i)
                .map_err(|_| SourceError::Remote(format!("{url}: too many bricks")))?;
            for p in &b.packets {
                packets.push(PacketMeta {
                    offset: entry.offset + p.offset,
                    ..p.clone()
                });
                packet_brick.push(index);
            }
            bricks.push(SessionBrick {
                header: b.header.clone(),
                origin: entry.origin,
                packets: b.packets.len() as u32,
            });
        }
        if u32::try_from(packets.len()).is_err() {
            return Err(SourceError::Remote(format!(
                "{url}: {} packets, more than a source numbers",
                packets.len()
            )));
        }
        Ok(Head {
            first,
            header: whole_header(m, &first_brick.header),
            packets,
            bricks,
            packet_brick,
            weights: Vec::new(),
            series: None,
            base: head.wsp_offset,
            object_bytes,
            indexed: true,
        })
    }
}

fn count(status: &Mutex<SourceStatus>, bytes: u64) {
    let mut s = status.lock().unwrap_or_else(|e| e.into_inner());
    s.requests += 1;
    s.received_bytes += bytes;
}
