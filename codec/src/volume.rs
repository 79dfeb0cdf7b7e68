//! The volume type: any dimensions (odd and non-power-of-two included), one intensity channel or
//! three colour channels, f32 samples, voxel spacing.
//!
//! Samples are stored planar (one `Vec<f32>` per channel, x fastest, then y, then z) because every
//! stage after the colour transform works on one channel at a time. Construction validates sizes
//! and rejects non-finite samples, so that nothing downstream has to.

use thiserror::Error;

/// Largest number of voxels a volume may have (per channel): 2^31, a 2048×1024×1024 volume.
pub const MAX_VOXELS: usize = 1 << 31;

/// Errors from building a volume.
#[derive(Debug, Error, PartialEq)]
#[non_exhaustive]
pub enum VolumeError {
    /// A dimension is zero.
    #[error("volume dimensions must be at least 1 in every axis, got {0:?}")]
    ZeroDimension([usize; 3]),
    /// Too many voxels for this implementation.
    #[error("volume {dims:?} has {voxels} voxels, more than the supported {max}")]
    TooLarge {
        /// Requested dimensions.
        dims: [usize; 3],
        /// Their product.
        voxels: u128,
        /// The limit.
        max: usize,
    },
    /// Only 1 (intensity) or 3 (RGB) channels are supported.
    #[error("a volume has 1 (intensity) or 3 (RGB) channels, got {0}")]
    ChannelCount(usize),
    /// A channel's sample count does not match the dimensions.
    #[error("channel {channel} has {got} samples, dimensions {dims:?} need {expected}")]
    SampleCount {
        /// Which channel.
        channel: usize,
        /// Samples present.
        got: usize,
        /// Samples required.
        expected: usize,
        /// The dimensions.
        dims: [usize; 3],
    },
    /// NaN or ±Inf in the input.
    #[error("channel {channel} has a non-finite sample ({value}) at voxel ({x}, {y}, {z}); NaN and Inf are not valid volume data")]
    NonFinite {
        /// Which channel.
        channel: usize,
        /// Voxel coordinates.
        x: usize,
        /// Voxel coordinates.
        y: usize,
        /// Voxel coordinates.
        z: usize,
        /// The offending value.
        value: f32,
    },
    /// Spacing must be positive and finite.
    #[error("voxel spacing must be positive and finite, got {0:?}")]
    Spacing([f32; 3]),
}

/// A scalar or RGB volume with f32 samples.
#[derive(Debug, Clone, PartialEq)]
pub struct Volume {
    dims: [usize; 3],
    spacing: [f32; 3],
    channels: Vec<Vec<f32>>,
}

impl Volume {
    /// Builds a volume from planar channels (x fastest). Validates everything.
    pub fn new(
        dims: [usize; 3],
        spacing: [f32; 3],
        channels: Vec<Vec<f32>>,
    ) -> Result<Self, VolumeError> {
        let expected = checked_voxels(dims)?;
        if channels.len() != 1 && channels.len() != 3 {
            return Err(VolumeError::ChannelCount(channels.len()));
        }
        if spacing.iter().any(|s| !(s.is_finite() && *s > 0.0)) {
            return Err(VolumeError::Spacing(spacing));
        }
        for (c, data) in channels.iter().enumerate() {
            if data.len() != expected {
                return Err(VolumeError::SampleCount {
                    channel: c,
                    got: data.len(),
                    expected,
                    dims,
                });
            }
            if let Some(i) = data.iter().position(|v| !v.is_finite()) {
                let (x, y, z) = (
                    i % dims[0],
                    (i / dims[0]) % dims[1],
                    i / (dims[0] * dims[1]),
                );
                return Err(VolumeError::NonFinite {
                    channel: c,
                    x,
                    y,
                    z,
                    value: data[i],
                });
            }
        }
        Ok(Volume {
            dims,
            spacing,
            channels,
        })
    }

    /// Builds a volume from interleaved samples (x fastest, channels interleaved per voxel).
    pub fn from_interleaved(
        dims: [usize; 3],
        spacing: [f32; 3],
        channel_count: usize,
        data: &[f32],
    ) -> Result<Self, VolumeError> {
        let n = checked_voxels(dims)?;
        if channel_count != 1 && channel_count != 3 {
            return Err(VolumeError::ChannelCount(channel_count));
        }
        if data.len() != n * channel_count {
            return Err(VolumeError::SampleCount {
                channel: 0,
                got: data.len(),
                expected: n * channel_count,
                dims,
            });
        }
        let channels = (0..channel_count)
            .map(|c| {
                data.iter()
                    .skip(c)
                    .step_by(channel_count)
                    .copied()
                    .collect()
            })
            .collect();
        Volume::new(dims, spacing, channels)
    }

    /// Samples interleaved per voxel (x fastest).
    pub fn to_interleaved(&self) -> Vec<f32> {
        let n = self.voxel_count();
        let c = self.channels.len();
        let mut out = vec![0.0; n * c];
        for (ci, ch) in self.channels.iter().enumerate() {
            for (i, v) in ch.iter().enumerate() {
                out[i * c + ci] = *v;
            }
        }
        out
    }

    /// Dimensions (x, y, z).
    pub fn dims(&self) -> [usize; 3] {
        self.dims
    }

    /// Voxel spacing (x, y, z).
    pub fn spacing(&self) -> [f32; 3] {
        self.spacing
    }

    /// Number of channels (1 or 3).
    pub fn channel_count(&self) -> usize {
        self.channels.len()
    }

    /// One channel's samples (x fastest).
    pub fn channel(&self, c: usize) -> &[f32] {
        &self.channels[c]
    }

    /// All channels.
    pub fn channels(&self) -> &[Vec<f32>] {
        &self.channels
    }

    /// Consumes the volume, returning its channels.
    pub fn into_channels(self) -> Vec<Vec<f32>> {
        self.channels
    }

    /// Voxels per channel.
    pub fn voxel_count(&self) -> usize {
        self.dims[0] * self.dims[1] * self.dims[2]
    }

    /// Linear index of voxel (x, y, z).
    pub fn index(&self, x: usize, y: usize, z: usize) -> usize {
        x + self.dims[0] * (y + self.dims[1] * z)
    }

    /// Minimum and maximum over all channels.
    pub fn value_range(&self) -> (f32, f32) {
        let mut lo = f32::INFINITY;
        let mut hi = f32::NEG_INFINITY;
        for ch in &self.channels {
            for v in ch {
                lo = lo.min(*v);
                hi = hi.max(*v);
            }
        }
        (lo, hi)
    }
}

/// Voxel count of `dims`, validated against zero and [`MAX_VOXELS`].
pub fn checked_voxels(dims: [usize; 3]) -> Result<usize, VolumeError> {
    if dims.contains(&0) {
        return Err(VolumeError::ZeroDimension(dims));
    }
    // Checked: three usize factors can overflow even u128.
    let voxels = dims
        .iter()
        .try_fold(1u128, |acc, d| acc.checked_mul(*d as u128))
        .unwrap_or(u128::MAX);
    if voxels > MAX_VOXELS as u128 {
        return Err(VolumeError::TooLarge {
            dims,
            voxels,
            max: MAX_VOXELS,
        });
    }
    Ok(voxels as usize)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rejects_bad_input() {
        assert!(matches!(
            Volume::new([0, 1, 1], [1.0; 3], vec![vec![]]),
            Err(VolumeError::ZeroDimension(_))
        ));
        assert!(matches!(
            Volume::new([2, 1, 1], [1.0; 3], vec![vec![0.0, f32::NAN]]),
            Err(VolumeError::NonFinite { x: 1, .. })
        ));
        assert!(matches!(
            Volume::new([1, 1, 1], [1.0; 3], vec![vec![f32::INFINITY]]),
            Err(VolumeError::NonFinite { .. })
        ));
        assert!(matches!(
            Volume::new([1, 1, 1], [1.0; 3], vec![vec![0.0], vec![0.0]]),
            Err(VolumeError::ChannelCount(2))
        ));
        assert!(matches!(
            Volume::new([1, 1, 2], [1.0; 3], vec![vec![0.0]]),
            Err(VolumeError::SampleCount { .. })
        ));
        assert!(matches!(
            Volume::new([1, 1, 1], [0.0, 1.0, 1.0], vec![vec![0.0]]),
            Err(VolumeError::Spacing(_))
        ));
        assert!(matches!(
            checked_voxels([usize::MAX, usize::MAX, 2]),
            Err(VolumeError::TooLarge { .. })
        ));
        assert!(matches!(
            checked_voxels([1 << 20, 1 << 20, 4]),
            Err(VolumeError::TooLarge { .. })
        ));
    }

    #[test]
    fn interleaving_round_trips() {
        let data: Vec<f32> = (0..2 * 3 * 3).map(|i| i as f32).collect();
        let v = Volume::from_interleaved([2, 3, 1], [1.0; 3], 3, &data).unwrap();
        assert_eq!(v.channel(1)[0], 1.0);
        assert_eq!(v.channel(2)[1], 5.0);
        assert_eq!(v.to_interleaved(), data);
    }
}
