//! The volume type: any dimensions (odd and non-power-of-two included), one intensity channel or
//! three colour channels, f32 samples, voxel spacing, and (when the source says) where the voxel
//! grid sits in the patient: its [`Placement`] (origin and axis directions in DICOM's LPS frame).
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
    /// The placement's origin or directions are not finite, or the directions are not
    /// orthonormal within [`PLACEMENT_TOLERANCE`].
    #[error("volume placement: {0}")]
    Placement(String),
    /// A box asked of a larger whole (a brick) does not lie within it (see
    /// [`VolumeError::check_within`]).
    #[error("{0}")]
    OutsideWhole(String),
}

impl VolumeError {
    /// Checks that the box at `origin` of `dims` voxels lies within a whole of `whole`
    /// ([`VolumeError::OutsideWhole`] otherwise).
    pub fn check_within(
        origin: [u64; 3],
        dims: [usize; 3],
        whole: [u64; 3],
    ) -> Result<(), VolumeError> {
        let outside = (0..3).any(|a| {
            origin[a]
                .checked_add(dims[a] as u64)
                .is_none_or(|e| e > whole[a])
        });
        if outside {
            return Err(VolumeError::OutsideWhole(format!(
                "a box at {origin:?} of {dims:?} voxels does not lie within the whole's {whole:?}"
            )));
        }
        Ok(())
    }
}

/// How far from orthonormal the axis directions of a [`Placement`] may be (|‖dᵢ‖ − 1| and
/// |dᵢ·dⱼ|): DICOM writes direction cosines as decimal strings of limited precision (often 6
/// digits, sometimes fewer), so exact orthonormality cannot be required; a sheared grid is
/// far beyond this.
pub const PLACEMENT_TOLERANCE: f64 = 1e-3;

/// Largest |origin| coordinate accepted (mm): a kilometre is beyond any scanner.
pub const MAX_ORIGIN_MM: f64 = 1e6;

/// Where the voxel grid sits in patient space, in the DICOM patient coordinate system (LPS:
/// +x towards the patient's left, +y posterior, +z superior; millimetres). Voxel (i, j, k) is
/// at `origin + i·sx·directions[0] + j·sy·directions[1] + k·sz·directions[2]`, with (sx, sy, sz)
/// the volume's spacing. Readers of formats in other frames (NIfTI's RAS, NRRD's
/// `right-anterior-superior`) convert to LPS.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Placement {
    /// Patient position of the centre of voxel (0, 0, 0), mm.
    pub origin: [f64; 3],
    /// Unit direction (LPS) of each voxel axis: `directions[0]` is the direction of increasing x.
    pub directions: [[f64; 3]; 3],
}

impl Placement {
    /// Axis-aligned placement: voxel axes along L, P, S, voxel (0, 0, 0) at the origin.
    pub fn identity() -> Placement {
        Placement {
            origin: [0.0; 3],
            directions: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        }
    }

    /// Checks that everything is finite, |origin| ≤ [`MAX_ORIGIN_MM`], and the directions are
    /// orthonormal within [`PLACEMENT_TOLERANCE`] (either handedness: a mirrored grid is a
    /// valid, if unusual, acquisition).
    pub fn validate(&self) -> Result<(), VolumeError> {
        let bad = |m: String| Err(VolumeError::Placement(m));
        if self
            .origin
            .iter()
            .any(|v| !v.is_finite() || v.abs() > MAX_ORIGIN_MM)
        {
            return bad(format!(
                "origin {:?} must be finite and within ±{MAX_ORIGIN_MM} mm",
                self.origin
            ));
        }
        if self.directions.iter().flatten().any(|v| !v.is_finite()) {
            return bad(format!("directions {:?} are not finite", self.directions));
        }
        let d = &self.directions;
        let dot = |a: &[f64; 3], b: &[f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
        for i in 0..3 {
            let n = dot(&d[i], &d[i]).sqrt();
            if (n - 1.0).abs() > PLACEMENT_TOLERANCE {
                return bad(format!(
                    "direction of axis {i} {:?} has length {n}, expected 1 (±{PLACEMENT_TOLERANCE})",
                    d[i]
                ));
            }
            for j in i + 1..3 {
                let c = dot(&d[i], &d[j]);
                if c.abs() > PLACEMENT_TOLERANCE {
                    return bad(format!(
                        "directions of axes {i} and {j} are not orthogonal (cosine {c}; a sheared grid, e.g. a tilted gantry, is not supported)"
                    ));
                }
            }
        }
        Ok(())
    }

    /// The patient position (LPS, mm) of voxel (i, j, k) for a grid of `spacing`.
    pub fn position(&self, spacing: [f32; 3], ijk: [f64; 3]) -> [f64; 3] {
        let mut p = self.origin;
        for a in 0..3 {
            let step = ijk[a] * f64::from(spacing[a]);
            for (c, pc) in p.iter_mut().enumerate() {
                *pc += step * self.directions[a][c];
            }
        }
        p
    }

    /// The closest anatomical label of each axis direction, e.g. `["L", "P", "S"]` for the
    /// identity, `["R", "A", "S"]` for a RAS-stored volume (the letter of the dominant
    /// component; oblique axes get the dominant one too).
    pub fn axis_labels(&self) -> [&'static str; 3] {
        self.directions.map(|d| {
            let (mut best, mut mag) = (0, -1.0);
            for (c, v) in d.iter().enumerate() {
                if v.abs() > mag {
                    (best, mag) = (c, v.abs());
                }
            }
            let pos = d[best] >= 0.0;
            match (best, pos) {
                (0, true) => "L",
                (0, false) => "R",
                (1, true) => "P",
                (1, false) => "A",
                (_, true) => "S",
                (_, false) => "I",
            }
        })
    }
}

/// A scalar or RGB volume with f32 samples.
#[derive(Debug, Clone, PartialEq)]
pub struct Volume {
    dims: [usize; 3],
    spacing: [f32; 3],
    channels: Vec<Vec<f32>>,
    placement: Option<Placement>,
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
            placement: None,
        })
    }

    /// The same volume placed in patient space (validated by [`Placement::validate`]).
    pub fn with_placement(mut self, placement: Placement) -> Result<Self, VolumeError> {
        placement.validate()?;
        self.placement = Some(placement);
        Ok(self)
    }

    /// Where the grid sits in patient space, when the source said.
    pub fn placement(&self) -> Option<&Placement> {
        self.placement.as_ref()
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
    fn placement_is_validated() {
        let v = Volume::new([1, 1, 1], [1.0; 3], vec![vec![0.0]]).unwrap();
        assert!(v.placement().is_none());
        let p = Placement {
            origin: [-10.0, 20.5, 3.0],
            directions: [[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]],
        };
        let v = v.with_placement(p).unwrap();
        assert_eq!(v.placement(), Some(&p));
        assert_eq!(p.axis_labels(), ["P", "R", "S"]);
        assert_eq!(
            p.position([2.0, 3.0, 0.5], [1.0, 1.0, 2.0]),
            [-10.0 - 3.0, 20.5 + 2.0, 4.0]
        );
        let mut bad = p;
        bad.origin[1] = f64::NAN;
        assert!(matches!(bad.validate(), Err(VolumeError::Placement(_))));
        let mut bad = p;
        bad.directions[2] = [0.0, 0.0, 0.0];
        assert!(bad.validate().unwrap_err().to_string().contains("length"));
        let mut bad = p;
        bad.directions[2] = [0.0, 0.3, 0.954];
        assert!(bad
            .validate()
            .unwrap_err()
            .to_string()
            .contains("orthogonal"));
        let mut bad = p;
        bad.origin[0] = 1e300;
        assert!(bad.validate().is_err());
        // A mirrored (left-handed) frame is valid.
        let mut m = Placement::identity();
        m.directions[2] = [0.0, 0.0, -1.0];
        assert!(m.validate().is_ok());
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
