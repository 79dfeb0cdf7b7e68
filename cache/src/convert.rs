//! The one place where generated `pb` types meet the cache's domain types: requests are parsed
//! into typed values (with range checks that need no store), results are turned into messages.

use crate::error::CacheError;
use crate::model::{PacketMeta, VolumeIndex, VolumeKey, VolumeMeta};
use wavesplat_codec::view::{Cue, CueDirection, View, ViewSpec};
use wavesplat_proto::pb;

/// Parses a volume reference.
pub fn volume_key(r: Option<pb::VolumeRef>) -> Result<VolumeKey, CacheError> {
    match r.and_then(|r| r.key) {
        Some(pb::volume_ref::Key::Id(id)) => Ok(VolumeKey::Id(id)),
        Some(pb::volume_ref::Key::Name(n)) => Ok(VolumeKey::Name(n)),
        None => Err(CacheError::InvalidRequest(
            "missing volume reference (id or name)".into(),
        )),
    }
}

/// A volume's header message: its facts, its header section and, for a bricked volume or a
/// time series, its bricks' headers (a series': each with its component and origin).
pub fn volume_header(meta: &VolumeMeta, index: &VolumeIndex) -> pb::VolumeHeader {
    pb::VolumeHeader {
        volume: Some(volume_info(meta)),
        header: index.header_bytes.clone(),
        bricks: match (&index.bricked, &index.series) {
            (Some(b), _) => b
                .bricks
                .iter()
                .map(|k| pb::BrickHeader {
                    header: k.header_bytes.clone(),
                    packets: k.packets,
                    ..Default::default()
                })
                .collect(),
            (None, Some(s)) => s
                .bricks
                .iter()
                .enumerate()
                .map(|(i, k)| {
                    let component = s.component_of(i);
                    pb::BrickHeader {
                        header: k.header_bytes.clone(),
                        packets: k.packets,
                        component: component as u32,
                        origin: k.origin.to_vec(),
                        bricked: s.bricked[component],
                    }
                })
                .collect(),
            (None, None) => Vec::new(),
        },
    }
}

/// The time point a view asks for (checked against the volume when it is planned).
pub fn time_point(v: Option<&pb::ViewSpec>) -> usize {
    v.map_or(0, |v| v.time_point as usize)
}

/// Parses and range-checks a view.
pub fn view_spec(v: Option<pb::ViewSpec>) -> Result<ViewSpec, CacheError> {
    let v = v.ok_or_else(|| CacheError::InvalidRequest("missing view".into()))?;
    let mut view = View::new(v.alpha, v.beta, v.width as usize, v.height as usize)
        .with_pan([v.pan_u, v.pan_v]);
    if v.zoom != 0.0 {
        view = view.with_zoom(v.zoom);
    }
    if let Some(c) = v.cue {
        let direction = match c.direction {
            None | Some(pb::cue::Direction::View(_)) => CueDirection::View,
            Some(pb::cue::Direction::Angles(a)) => CueDirection::Angles {
                alpha: a.alpha,
                beta: a.beta,
            },
            Some(pb::cue::Direction::Vector(w)) => CueDirection::Vector([w.x, w.y, w.z]),
        };
        view = view.with_cue(Cue { k: c.k, direction });
    }
    let spec = ViewSpec {
        view,
        multiview: v.multiview,
    };
    spec.validate()
        .map_err(|e| CacheError::InvalidRequest(e.to_string()))?;
    Ok(spec)
}

/// A packet table entry.
pub fn packet_entry(p: &PacketMeta) -> pb::PacketEntry {
    pb::PacketEntry {
        tile: p.tile,
        layer: p.layer,
        bytes: p.len,
        energy: p.summary.iter().map(|(_, e)| e).sum(),
    }
}

/// Parses a declared SHA-256.
pub fn sha256(b: &[u8]) -> Result<[u8; 32], CacheError> {
    b.try_into().map_err(|_| {
        CacheError::InvalidRequest(format!("sha256 must be 32 bytes, got {} bytes", b.len()))
    })
}

/// A volume's facts as a message.
pub fn volume_info(m: &VolumeMeta) -> pb::VolumeInfo {
    pb::VolumeInfo {
        id: m.id,
        name: m.name.clone(),
        dims: m.dims.to_vec(),
        channels: m.channels,
        family: m.family.clone(),
        levels: m.levels,
        file_bytes: m.file_bytes,
        header_bytes: m.header_bytes,
        packet_bytes: m.packet_bytes,
        created_unix_ms: m.created_unix_ms,
        packet_count: m.packet_count,
        tile_count: m.tile_count,
        layer_count: m.layer_count,
        tile: m.tile,
        coefficients: m.coefficients,
        sha256: m.sha256_hex(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn message(alpha: f64, width: u32, zoom: f64, pan_u: f64) -> pb::ViewSpec {
        pb::ViewSpec {
            alpha,
            beta: 0.0,
            width,
            height: 10,
            zoom,
            pan_u,
            pan_v: 0.0,
            multiview: false,
            cue: None,
            time_point: 0,
        }
    }

    #[test]
    fn bad_views_are_rejected() {
        assert!(view_spec(Some(message(0.3, 10, 0.0, 0.0))).is_ok());
        let cued = pb::ViewSpec {
            multiview: true,
            cue: Some(pb::Cue {
                k: 0.1,
                direction: None,
            }),
            ..message(0.0, 10, 0.0, 0.0)
        };
        for m in [
            message(f64::NAN, 10, 0.0, 0.0),
            message(1e9, 10, 0.0, 0.0),
            message(0.0, 100_000, 0.0, 0.0),
            message(0.0, 0, 0.0, 0.0),
            message(0.0, 10, -1.0, 0.0),
            message(0.0, 10, 0.0, f64::INFINITY),
            cued,
        ] {
            assert!(
                matches!(view_spec(Some(m)), Err(CacheError::InvalidRequest(_))),
                "{m:?}"
            );
        }
        assert!(view_spec(None).is_err());
    }
}
