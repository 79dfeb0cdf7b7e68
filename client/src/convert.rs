//! The one place where the generated `pb` types meet the client's domain types: requests built
//! from domain values, responses checked and turned into domain values.

use crate::{BrickHeader, ClientError, Packet, VolumeHeader, VolumeInfo, VolumeKey};
use wavesplat_codec::format::bricked::parse_manifest;
use wavesplat_codec::format::read_header_section;
use wavesplat_codec::view::bricked::{check_brick, whole_header};
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
pub fn view_message(spec: &ViewSpec) -> Result<pb::ViewSpec, ViewError> {
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

/// The messages of an upload: `start`, then chunks.
pub(crate) fn ingest_messages(
    name: &str,
    bytes: &[u8],
    sha256: [u8; 32],
) -> Vec<pb::IngestRequest> {
    use pb::ingest_request::Msg;
    let mut out = vec![pb::IngestRequest {
        msg: Some(Msg::Start(pb::IngestStart {
            name: name.to_string(),
            total_size: bytes.len() as u64,
            sha256: sha256.to_vec(),
        })),
    }];
    out.extend(bytes.chunks(crate::CHUNK_BYTES).map(|c| pb::IngestRequest {
        msg: Some(Msg::Chunk(c.to_vec())),
    }));
    out
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
pub(crate) fn volume_header(h: pb::VolumeHeader) -> Result<VolumeHeader, ClientError> {
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
        });
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
        });
    }
    if packets != u64::from(info.packet_count) {
        return Err(ClientError::Protocol(format!(
            "the bricks have {packets} packets, the volume {}",
            info.packet_count
        )));
    }
    Ok(VolumeHeader {
        header: whole_header(&manifest, &bricks[0].header),
        info,
        bytes: h.header,
        bricks,
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
