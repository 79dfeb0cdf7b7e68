//! Raw files: the samples are the whole file after the spec's `header_bytes`, described by the
//! caller's [`RawSpec`] (sizes, channels, sample type, byte order, spacing), which is validated
//! here as the raw reader does.

use std::path::Path;

use super::super::{Opened, Source};
use super::{stored_at, stored_bytes};
use crate::reader::{RawSpec, ReadError};
use wavesplat_codec::volume::VolumeError;

pub(super) fn open_raw(path: &Path, spec: &RawSpec) -> Result<Opened, ReadError> {
    if spec.channels != 1 && spec.channels != 3 {
        return Err(ReadError::ChannelCount(spec.channels));
    }
    if spec.spacing.iter().any(|s| !(s.is_finite() && *s > 0.0)) {
        return Err(ReadError::Volume(VolumeError::Spacing(spec.spacing)));
    }
    if spec.dims.contains(&0) {
        return Err(ReadError::Volume(VolumeError::ZeroDimension(spec.dims)));
    }
    if spec.time_points == 0 {
        return Err(ReadError::Region {
            path: path.to_path_buf(),
            reason: "a raw series of 0 time points".into(),
        });
    }
    let size = spec.dtype.size();
    let (frame, expected) = stored_bytes(path, spec.dims, spec.channels, size, spec.time_points)?;
    let sample = spec.dtype.sample();
    // A raw file must be exactly as large as its description, its header's bytes and the
    // samples (as `read_raw` requires).
    let total = expected
        .checked_add(spec.header_bytes)
        .ok_or(ReadError::TooLarge {
            dims: spec.dims,
            channels: spec.channels,
            bytes_per_sample: size,
        })?;
    let len = std::fs::metadata(path)
        .map_err(|e| ReadError::io(path, e))?
        .len();
    if len != total {
        return Err(ReadError::SizeMismatch {
            path: Some(path.to_path_buf()),
            expected: total,
            actual: len,
            header_bytes: spec.header_bytes,
            dims: spec.dims,
            channels: spec.channels,
            dtype: spec.dtype,
            bytes_per_sample: size as u8,
            time_points: spec.time_points,
        });
    }
    Ok(Opened {
        dims: spec.dims,
        channels: spec.channels,
        spacing: spec.spacing,
        placement: None,
        source: Source::Stored(super::super::Stored {
            frame,
            ..stored_at(path, spec.header_bytes, expected, sample, spec.endian)?
        }),
        time_points: spec.time_points,
        time_step: None,
    })
}
