//! The one place where the generated `pb` types meet the client's domain types: requests built
//! from domain values, responses checked and turned into domain values.

use crate::{BrickHeader, ClientError, Packet, VolumeHeader, VolumeInfo, VolumeKey};
use wavesplat_codec::format::bricked::parse_manifest;
use wavesplat_codec::format::read_header_section;
use wavesplat_codec::format::series::{is_series, parse_manifest as parse_series_manifest};
use wavesplat_codec::view::bricked::{check_brick, series_brick_header, whole_header};
use wavesplat_codec::view::{CueDirection, Orientation, ViewError, ViewSpec};
use wavesplat_proto::pb;

/// A volume reference message.
pub fn volume_ref(key: &VolumeKey) -> pb::VolumeRef {
    pb::VolumeRef {
        key: Some(match key {
            VolumeKey::Id(id) => pb::volume_ref::Key::Id(*id),
            VolumeKey::Name(n) => pb::volume_ref::Key::Name(n.clone()),
        }),
    }
}

/// A view message. Only spherical-angle views travel on the wire (the cache derives multiview
/// cameras itself); an explicit basis is refused here rather than sent as NaN.
/// `time_point`: of a time series, the time point shown (0 for any other volume).
pub fn view_message(spec: &ViewSpec, time_point: u32) -> Result<pb::ViewSpec, ViewError> {
    spec.validate()?;
    let v = &spec.view;
    let Orientation::Angles { alpha, beta } = v.orientation else {
        return Err(ViewError::NotFinite(
            "explicit basis (only angle views can be sent)",
        ));
    };
    Ok(pb::ViewSpec {
        alpha,
        beta,
        width: v.width as u32,
        height: v.height as u32,
        zoom: v.zoom.unwrap_or(0.0),
        pan_u: v.pan[0],
        pan_v: v.pan[1],
        multiview: spec.multiview,
        time_point,
        cue: v.cue.map(|c| pb::Cue {
            k: c.k,
            direction: Some(match c.direction {
                CueDirection::View => pb::cue::Direction::View(true),
                CueDirection::Angles { alpha, beta } => {
                    pb::cue::Direction::Angles(pb::LightAngles { alpha, beta })
                }
                CueDirection::Vector(w) => pb::cue::Direction::Vector(pb::Vec3 {
                    x: w[0],
                    y: w[1],
                    z: w[2],
                }),
            }),
        }),
    })
}

/// An upload's first message: its name, length and SHA-256.
pub(crate) fn ingest_start(name: &str, total_size: u64, sha256: [u8; 32]) -> pb::IngestRequest {
    pb::IngestRequest {
        msg: Some(pb::ingest_request::Msg::Start(pb::IngestStart {
            name: name.to_string(),
            total_size,
            sha256: sha256.to_vec(),
        })),
    }
}

/// The messages of an upload: `start` (with the bytes' SHA-256), then chunks, each copied out
/// of `bytes` only when the stream is asked for it.
pub(crate) fn ingest_messages(
    name: &str,
    bytes: Vec<u8>,
) -> impl Iterator<Item = pb::IngestRequest> + Send + 'static {
    use pb::ingest_request::Msg;
    let start = ingest_start(
        name,
        bytes.len() as u64,
        wavesplat_net::digest::sha256(&bytes),
    );
    let chunks = bytes.len().div_ceil(crate::CHUNK_BYTES);
    std::iter::once(start).chain((0..chunks).map(move |i| {
        let end = ((i + 1) * crate::CHUNK_BYTES).min(bytes.len());
        pb::IngestRequest {
            msg: Some(Msg::Chunk(bytes[i * crate::CHUNK_BYTES..end].to_vec())),
        }
    }))
}

/// Where a failed read of an uploaded file is left for the caller.
pub(crate) type ReadError = std::sync::Arc<std::sync::Mutex<Option<std::io::Error>>>;

/// The chunk messages of `total` bytes of `file` (from its cursor), read on a blocking thread a
/// chunk or two ahead of the transport. A read that fails, or a file shorter than `total`,
/// ends the stream early and leaves the error in the returned slot.
pub(crate) fn file_chunks(
    mut file: std::fs::File,
    total: u64,
) -> (
    impl tokio_stream::Stream<Item = pb::IngestRequest> + Send + 'static,
    ReadError,
) {
    use std::io::Read;
    let (tx, rx) = tokio::sync::mpsc::channel(2);
    let error = ReadError::default();
    let slot = error.clone();
    tokio::task::spawn_blocking(move || {
        let mut left = total;
        while left > 0 {
            let want = left.min(crate::CHUNK_BYTES as u64) as usize;
            let mut chunk = vec![0u8; want];
            if let Err(e) = file.read_exact(&mut chunk) {
                *slot.lock().unwrap_or_else(|p| p.into_inner()) = Some(e);
                return;
            }
            left -= want as u64;
            let msg = pb::IngestRequest {
                msg: Some(pb::ingest_request::Msg::Chunk(chunk)),
            };
            if tx.blocking_send(msg).is_err() {
                // The upload ended (refused, or the connection went): nothing to send to.
                return;
            }
        }
    });
    (tokio_stream::wrappers::ReceiverStream::new(rx), error)
}

/// A volume's facts, checked.
pub(crate) fn volume_info(v: pb::VolumeInfo) -> Result<VolumeInfo, ClientError> {
    let dims: [u32; 3] = v.dims.as_slice().try_into().map_err(|_| {
        ClientError::Protocol(format!(
            "volume {:?} has {} dimensions",
            v.name,
            v.dims.len()
        ))
    })?;
    Ok(VolumeInfo {
        id: v.id,
        name: v.name,
        dims,
        channels: v.channels,
        family: v.family,
        levels: v.levels,
        file_bytes: v.file_bytes,
        header_bytes: v.header_bytes,
        packet_bytes: v.packet_bytes,
        created_unix_ms: v.created_unix_ms,
        packet_count: v.packet_count,
        tile_count: v.tile_count,
        layer_count: v.layer_count,
        tile: v.tile,
        coefficients: v.coefficients,
        sha256: v.sha256,
    })
}

/// A header message, parsed by the codec.
pub fn volume_header(h: pb::VolumeHeader) -> Result<VolumeHeader, ClientError> {
    let info = volume_info(
        h.volume
            .ok_or_else(|| ClientError::Protocol("header without volume facts".into()))?,
    )?;
    if h.bricks.is_empty() {
        let (header, _) = read_header_section(&h.header)?;
        return Ok(VolumeHeader {
            info,
            header,
            bytes: h.header,
            bricks: Vec::new(),
            series: None,
        });
    }
    if is_series(&h.header) {
        return series_header(info, h.header, &h.bricks);
    }
    // A bricked volume: the manifest places the bricks (checked against the file's size), each
    // brick's header against its entry, and their packets against the volume's count.
    let manifest = parse_manifest(&h.header, info.file_bytes)?;
    if manifest.bricks.len() != h.bricks.len() {
        return Err(ClientError::Protocol(format!(
            "{} brick headers for a manifest of {} bricks",
            h.bricks.len(),
            manifest.bricks.len()
        )));
    }
    let mut bricks = Vec::with_capacity(h.bricks.len());
    let mut packets = 0u64;
    for (i, (b, entry)) in h.bricks.iter().zip(&manifest.bricks).enumerate() {
        let (header, _) = read_header_section(&b.header)?;
        let first = bricks.first().map_or(&header, |f: &BrickHeader| &f.header);
        check_brick(i, entry, &header, first, manifest.channels)?;
        packets += u64::from(b.packets);
        bricks.push(BrickHeader {
            header,
            origin: entry.origin,
            packets: b.packets,
            component: 0,
        });
    }
    check_packet_count(packets, &info)?;
    Ok(VolumeHeader {
        header: whole_header(&manifest, &bricks[0].header),
        info,
        bytes: h.header,
        bricks,
        series: None,
    })
}

fn check_packet_count(packets: u64, info: &VolumeInfo) -> Result<(), ClientError> {
    if packets != u64::from(info.packet_count) {
        return Err(ClientError::Protocol(format!(
            "the bricks have {packets} packets, the volume {}",
            info.packet_count
        )));
    }
    Ok(())
}

/// A time series' header message: its manifest (checked against the file's size) and every
/// component's bricks, component after component, each inside the whole with the series'
/// channels and component 0's family.
fn series_header(
    info: VolumeInfo,
    section: Vec<u8>,
    brick_messages: &[pb::BrickHeader],
) -> Result<VolumeHeader, ClientError> {
    let bad = |m: String| ClientError::Protocol(format!("series header: {m}"));
    let manifest = parse_series_manifest(&section, info.file_bytes)?;
    let space = &manifest.space;
    let mut bricks: Vec<BrickHeader> = Vec::with_capacity(brick_messages.len());
    let mut packets = 0u64;
    let mut first_bricked = false;
    for (i, b) in brick_messages.iter().enumerate() {
        let component = b.component as usize;
        let expected = bricks.last().map_or(0, |p| p.component);
        if component != expected && component != expected + 1 {
            return Err(bad(format!(
                "brick {i} is of component {component} after component {expected}"
            )));
        }
        let origin: [u64; 3] = b.origin.as_slice().try_into().map_err(|_| {
            bad(format!(
                "brick {i} has an origin of {} values",
                b.origin.len()
            ))
        })?;
        let (header, _) = read_header_section(&b.header)?;
        let fits = (0..3).all(|a| {
            origin[a]
                .checked_add(header.geometry.dims[a] as u64)
                .is_some_and(|end| end <= space.dims[a])
        });
        if !fits || header.channels != space.channels {
            return Err(bad(format!(
                "brick {i} at {origin:?}, {:?} with {} channel(s), is not inside the series' \
                 {:?} with {}",
                header.geometry.dims, header.channels, space.dims, space.channels
            )));
        }
        if let Some(first) = bricks.first() {
            if header.geometry.family != first.header.geometry.family {
                return Err(bad(format!(
                    "brick {i}'s wavelet family differs from brick 0's"
                )));
            }
        } else {
            first_bricked = b.bricked;
        }
        packets += u64::from(b.packets);
        bricks.push(BrickHeader {
            header,
            origin,
            packets: b.packets,
            component,
        });
    }
    // Each component's bricks tile the whole: drawn, overlapping bricks would add twice and
    // a gap would draw nothing.
    // (The bricks come component after component, checked above.)
    for group in bricks.chunk_by(|a, b| a.component == b.component) {
        let boxes: Vec<([u64; 3], [usize; 3])> = group
            .iter()
            .map(|b| (b.origin, b.header.geometry.dims))
            .collect();
        wavesplat_codec::format::bricked::check_tiling(space.dims, &boxes)
            .map_err(|e| bad(format!("component {}: {e}", group[0].component)))?;
    }
    let components = bricks.last().map_or(0, |b| b.component + 1);
    if components != manifest.components.len() {
        return Err(bad(format!(
            "bricks of {components} components; the manifest has {}",
            manifest.components.len()
        )));
    }
    check_packet_count(packets, &info)?;
    let header = series_brick_header(space, bricks[0].header.clone(), first_bricked)?;
    Ok(VolumeHeader {
        header,
        info,
        bytes: section,
        bricks,
        series: Some(Box::new(manifest)),
    })
}

/// A packet.
pub(crate) fn packet(p: pb::Packet) -> Packet {
    Packet {
        id: p.id,
        tile: p.tile,
        layer: p.layer,
        data: p.data,
        priority: p.priority,
    }
}
