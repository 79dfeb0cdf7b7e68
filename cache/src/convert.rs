//! The one place where generated `pb` types meet the cache's domain types: requests are parsed
//! into typed values (with range checks that need no store), results are turned into messages.

use crate::error::CacheError;
use crate::model::{VolumeKey, VolumeMeta};
use crate::priority::ViewSpec;
use wavesplat_proto::pb;
use wavesplat_viewer::{Cue, CueDirection, View};

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

/// Builds a volume reference from a key.
pub fn volume_ref(key: &VolumeKey) -> pb::VolumeRef {
    pb::VolumeRef {
        key: Some(match key {
            VolumeKey::Id(id) => pb::volume_ref::Key::Id(*id),
            VolumeKey::Name(n) => pb::volume_ref::Key::Name(n.clone()),
        }),
    }
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
    spec.validate()?;
    Ok(spec)
}

/// Builds a view message (for clients).
pub fn view_message(spec: &ViewSpec) -> pb::ViewSpec {
    let v = &spec.view;
    let (alpha, beta) = match v.orientation {
        wavesplat_viewer::Orientation::Angles { alpha, beta } => (alpha, beta),
        // Not expressible on the wire; clients only build angle views.
        wavesplat_viewer::Orientation::Basis { .. } => (f64::NAN, f64::NAN),
    };
    pb::ViewSpec {
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
