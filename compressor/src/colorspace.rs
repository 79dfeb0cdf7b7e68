//! Colour-space decorrelation of RGB volumes before compression (paper §4.2, Table 2): the
//! volume is projected onto three vectors C₁, C₂, C₃ and each gets a global importance I(C) that
//! multiplies the wavelet energy in the significance score S = E·I (eq. 14). Three spaces: RGB
//! (identity), NTSC YIQ (not orthonormal, the inverse is the exact matrix inverse) and PCA /
//! Karhunen–Loève (eigenvectors of the 3×3 matrix of colour second moments, descending). The
//! importances are the weights that make S measure the error in RGB: an error e in channel Cᵢ
//! comes back as e times column i of the inverse, so Iᵢ is that column's squared norm (1 for
//! the orthonormal RGB and PCA bases; the paper's perceptual YIQ weights 4, 1.5, 0.6 lose
//! 1.4 dB Q_I on a classified RGB volume, see BENCHMARKS.md). The colour subtracted before
//! projecting is the median colour of the volume's faces ([`face_median`]), not the mean: the
//! wavelet grid is zero-padded, so whatever value the faces keep becomes a step along every
//! face that costs coefficients at every level (a black background stays zero, air at −1000 HU
//! becomes zero); intensity volumes get the same offset (`codec::format::ColorInfo::mean`).
//! The PCA fit accumulates in f64 and always yields an orthonormal basis without NaN, also for
//! degenerate volumes (grey: rank 1; one colour: zero moments; repeated eigenvalues). Intensity
//! volumes skip this step.

use nalgebra::{Matrix3, SymmetricEigen, Vector3};
use thiserror::Error;
use wavesplat_codec::volume::{Volume, VolumeError};

/// Errors from the colour transform.
#[derive(Debug, Error, PartialEq)]
#[non_exhaustive]
pub enum ColorError {
    /// Colour transforms need a 3-channel (RGB) volume.
    #[error("a colour transform needs a 3-channel (RGB) volume, got {0} channel(s)")]
    NotRgb(usize),
    /// The transformed samples do not form a valid volume (e.g. they overflow f32).
    #[error("colour transform produced an invalid volume: {0}")]
    Volume(#[from] VolumeError),
}

/// Which colour space to compress in.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum ColorSpaceKind {
    /// No projection (the origin colour is still subtracted); importances 1, 1, 1.
    #[default]
    Rgb,
    /// NTSC YIQ; importances are the channels' RGB error weights.
    Yiq,
    /// Principal components of the volume's colours (second moments about the faces' median
    /// colour); importances 1 (0 for a component without energy).
    Pca,
}

impl ColorSpaceKind {
    /// Parses `rgb`, `yiq` or `pca` (case-insensitive; `klt` and `eigen` mean PCA).
    pub fn from_name(name: &str) -> Option<ColorSpaceKind> {
        match name.trim().to_ascii_lowercase().as_str() {
            "rgb" => Some(ColorSpaceKind::Rgb),
            "yiq" => Some(ColorSpaceKind::Yiq),
            "pca" | "klt" | "eigen" => Some(ColorSpaceKind::Pca),
            _ => None,
        }
    }

    /// The names accepted by [`ColorSpaceKind::from_name`] (canonical ones).
    pub fn names() -> &'static [&'static str] {
        &["rgb", "yiq", "pca"]
    }

    /// The canonical name.
    pub fn name(self) -> &'static str {
        match self {
            ColorSpaceKind::Rgb => "rgb",
            ColorSpaceKind::Yiq => "yiq",
            ColorSpaceKind::Pca => "pca",
        }
    }
}

/// The NTSC RGB → YIQ matrix (rows Y, I, Q).
pub const YIQ_MATRIX: [[f64; 3]; 3] = [
    [0.299, 0.587, 0.114],
    [0.596, -0.274, -0.322],
    [0.211, -0.523, 0.312],
];

/// The paper's perceptual importances of Y, I, Q (NTSC bandwidth conventions, Table 2); the
/// compressor uses the RGB error weights instead ([`ColorTransform::yiq`]).
pub const YIQ_PAPER_IMPORTANCE: [f64; 3] = [4.0, 1.5, 0.6];

const IDENTITY: [[f64; 3]; 3] = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];

/// A fitted colour transform: `c_i = basis[i] · (rgb − mean)`, inverse
/// `rgb = inverse_matrix() · c + mean`.
#[derive(Debug, Clone, PartialEq)]
pub struct ColorTransform {
    /// Which space this is.
    pub kind: ColorSpaceKind,
    /// Row i is the vector Cᵢ in RGB (the projection applied to get channel i).
    pub basis: [[f64; 3]; 3],
    /// Colour subtracted before projecting: the faces' median colour ([`ColorTransform::fit`];
    /// zero for the fixed [`ColorTransform::rgb`] and [`ColorTransform::yiq`]).
    pub mean: [f64; 3],
    /// Importance I(Cᵢ) of each channel (paper Table 2).
    pub importance: [f64; 3],
}

impl ColorTransform {
    /// The identity (RGB) transform.
    pub fn rgb() -> ColorTransform {
        ColorTransform {
            kind: ColorSpaceKind::Rgb,
            basis: IDENTITY,
            mean: [0.0; 3],
            importance: [1.0; 3],
        }
    }

    /// The NTSC YIQ transform, with the RGB error weights of its channels as importances.
    pub fn yiq() -> ColorTransform {
        let mut t = ColorTransform {
            kind: ColorSpaceKind::Yiq,
            basis: YIQ_MATRIX,
            mean: [0.0; 3],
            importance: [1.0; 3],
        };
        t.importance = rgb_error_weights(&t.inverse_matrix());
        t
    }

    /// Fits a transform of `kind` to an RGB volume: the origin is the faces' median colour, and
    /// PCA's basis depends on the data.
    pub fn fit(kind: ColorSpaceKind, volume: &Volume) -> Result<ColorTransform, ColorError> {
        if volume.channel_count() != 3 {
            return Err(ColorError::NotRgb(volume.channel_count()));
        }
        let mean = face_colour(volume);
        let moments = match kind {
            ColorSpaceKind::Pca => second_moments(volume, mean),
            _ => [[0.0; 3]; 3],
        };
        Ok(ColorTransform::with_origin(kind, mean, &moments))
    }

    /// The transform of `kind` about the colour `mean`; PCA's basis from the colour second
    /// moments about `mean` (`moments`, E[(x − mean)(x − mean)ᵀ]; the fixed spaces ignore
    /// them). A bricked volume's bricks share the transform made from the whole's faces and
    /// moments, gathered brick by brick.
    pub fn with_origin(
        kind: ColorSpaceKind,
        mean: [f64; 3],
        moments: &[[f64; 3]; 3],
    ) -> ColorTransform {
        match kind {
            ColorSpaceKind::Rgb => ColorTransform {
                mean,
                ..ColorTransform::rgb()
            },
            ColorSpaceKind::Yiq => ColorTransform {
                mean,
                ..ColorTransform::yiq()
            },
            ColorSpaceKind::Pca => {
                let (basis, energy) = pca_basis(moments);
                // Orthonormal: every channel's error comes back to RGB at weight 1; a channel
                // with no energy (beyond rounding) is never worth a coefficient.
                let importance = energy.map(|e| if e > 0.0 { 1.0 } else { 0.0 });
                ColorTransform {
                    kind,
                    basis,
                    mean,
                    importance,
                }
            }
        }
    }

    /// Projects an RGB volume into the C₁..C₃ space (3 channels, same dims and spacing).
    pub fn forward(&self, volume: &Volume) -> Result<Volume, ColorError> {
        if volume.channel_count() != 3 {
            return Err(ColorError::NotRgb(volume.channel_count()));
        }
        apply(volume, &self.basis, self.mean, [0.0; 3])
    }

    /// Maps a volume in the C₁..C₃ space back to RGB.
    pub fn inverse(&self, channels: &Volume) -> Result<Volume, ColorError> {
        if channels.channel_count() != 3 {
            return Err(ColorError::NotRgb(channels.channel_count()));
        }
        apply(channels, &self.inverse_matrix(), [0.0; 3], self.mean)
    }

    /// Projects one RGB colour into the C space.
    pub fn forward_pixel(&self, rgb: [f64; 3]) -> [f64; 3] {
        let d = [0, 1, 2].map(|j| rgb[j] - self.mean[j]);
        mat_vec(&self.basis, d)
    }

    /// Maps one colour from the C space back to RGB (`inverse_matrix() · c + mean`).
    pub fn inverse_pixel(&self, c: [f64; 3]) -> [f64; 3] {
        let v = mat_vec(&self.inverse_matrix(), c);
        [0, 1, 2].map(|j| v[j] + self.mean[j])
    }

    /// Maps a line integral of the C channels back to RGB. The projection is linear, so an
    /// X-ray image rendered in C space equals `basis · ∫rgb − basis · mean · L`; this returns
    /// `inverse_matrix() · c + mean · path_length`, where `path_length` is the length L of the
    /// ray inside the volume (in the same units as the integral).
    pub fn inverse_integral(&self, c: [f64; 3], path_length: f64) -> [f64; 3] {
        let v = mat_vec(&self.inverse_matrix(), c);
        [0, 1, 2].map(|j| v[j] + self.mean[j] * path_length)
    }

    /// The exact inverse of [`ColorTransform::basis`]: its transpose when the basis is
    /// orthonormal (RGB, PCA), the general 3×3 inverse otherwise (YIQ). A singular basis (never
    /// produced by [`ColorTransform::fit`]) gives non-finite entries.
    pub fn inverse_matrix(&self) -> [[f64; 3]; 3] {
        if orthonormality_error(&self.basis) <= 1e-12 {
            return transpose(&self.basis);
        }
        let m = &self.basis;
        let cof = |r0: usize, r1: usize, c0: usize, c1: usize| {
            m[r0][c0] * m[r1][c1] - m[r0][c1] * m[r1][c0]
        };
        // Adjugate (transposed cofactor matrix).
        let adj = [
            [cof(1, 2, 1, 2), -cof(0, 2, 1, 2), cof(0, 1, 1, 2)],
            [-cof(1, 2, 0, 2), cof(0, 2, 0, 2), -cof(0, 1, 0, 2)],
            [cof(1, 2, 0, 1), -cof(0, 2, 0, 1), cof(0, 1, 0, 1)],
        ];
        let det = m[0][0] * adj[0][0] + m[0][1] * adj[1][0] + m[0][2] * adj[2][0];
        adj.map(|row| row.map(|v| v / det))
    }
}

fn mat_vec(m: &[[f64; 3]; 3], v: [f64; 3]) -> [f64; 3] {
    [0, 1, 2].map(|i| m[i][0] * v[0] + m[i][1] * v[1] + m[i][2] * v[2])
}

fn transpose(m: &[[f64; 3]; 3]) -> [[f64; 3]; 3] {
    [0, 1, 2].map(|i| [0, 1, 2].map(|j| m[j][i]))
}

/// Largest deviation of `m · mᵀ` from the identity.
fn orthonormality_error(m: &[[f64; 3]; 3]) -> f64 {
    let mut err: f64 = 0.0;
    for i in 0..3 {
        for j in 0..3 {
            let d: f64 = (0..3).map(|k| m[i][k] * m[j][k]).sum();
            let want = if i == j { 1.0 } else { 0.0 };
            err = err.max((d - want).abs());
        }
    }
    if err.is_nan() {
        f64::INFINITY
    } else {
        err
    }
}

/// `out_i = m[i] · (x − sub) + add_i`, per voxel, in f64.
fn apply(
    volume: &Volume,
    m: &[[f64; 3]; 3],
    sub: [f64; 3],
    add: [f64; 3],
) -> Result<Volume, ColorError> {
    let n = volume.voxel_count();
    let ch = volume.channels();
    let mut out: Vec<Vec<f32>> = (0..3).map(|_| Vec::with_capacity(n)).collect();
    for v in 0..n {
        let x = [0, 1, 2].map(|j| f64::from(ch[j][v]) - sub[j]);
        for (i, o) in out.iter_mut().enumerate() {
            o.push((m[i][0] * x[0] + m[i][1] * x[1] + m[i][2] * x[2] + add[i]) as f32);
        }
    }
    let out = Volume::new(volume.dims(), volume.spacing(), out)?;
    Ok(match volume.placement() {
        Some(p) => out.with_placement(*p)?,
        None => out,
    })
}

/// Squared column norms of a colour transform's inverse: the weight at which an error in each
/// channel comes back to RGB (for uncorrelated channel errors, the RGB squared error is
/// Σᵢ ‖column i‖² eᵢ²).
fn rgb_error_weights(inverse: &[[f64; 3]; 3]) -> [f64; 3] {
    [0, 1, 2].map(|i| (0..3).map(|r| inverse[r][i] * inverse[r][i]).sum())
}

/// The median of a channel's samples on the six faces of its volume (the lower middle value of
/// an even count, so it is one of the samples: a face of air at exactly −1000 gives −1000).
/// This is what the compressor subtracts before the transform, so that the faces end near zero
/// on the zero-padded wavelet grid.
pub fn face_median(channel: &[f32], dims: [usize; 3]) -> f64 {
    let [nx, ny, nz] = dims;
    if channel.len() != nx * ny * nz || channel.is_empty() {
        return 0.0;
    }
    let at = |x: usize, y: usize, z: usize| channel[(z * ny + y) * nx + x];
    let mut face: Vec<f32> = Vec::new();
    for z in [0, nz - 1] {
        for y in 0..ny {
            for x in 0..nx {
                face.push(at(x, y, z));
            }
        }
    }
    for z in 0..nz {
        for y in [0, ny - 1] {
            for x in 0..nx {
                face.push(at(x, y, z));
            }
        }
        for y in 0..ny {
            for x in [0, nx - 1] {
                face.push(at(x, y, z));
            }
        }
    }
    median_or_zero(&mut face)
}

/// The median of `samples` (reordered in place; the lower middle of an even count), or 0 when
/// there are none or it is not finite: an offset that is safe to subtract.
pub fn median_or_zero(samples: &mut [f32]) -> f64 {
    if samples.is_empty() {
        return 0.0;
    }
    let mid = (samples.len() - 1) / 2;
    let (_, m, _) = samples.select_nth_unstable_by(mid, f32::total_cmp);
    let m = f64::from(*m);
    if m.is_finite() {
        m
    } else {
        0.0
    }
}

/// How much structure a channel's faces carry: the RMS of the face samples' deviation from
/// their median over the RMS of every sample's deviation from it (0 for faces that are
/// constant; near 1 where the volume is cut through its content). 0 for an empty or constant
/// channel.
pub fn face_activity(channel: &[f32], dims: [usize; 3]) -> f64 {
    let [nx, ny, nz] = dims;
    if channel.len() != nx * ny * nz || channel.is_empty() {
        return 0.0;
    }
    let m = face_median(channel, dims);
    let sq = |v: f32| {
        let d = f64::from(v) - m;
        if d.is_finite() {
            d * d
        } else {
            0.0
        }
    };
    let all: f64 = channel.iter().map(|v| sq(*v)).sum();
    // Each face voxel once: the z faces whole, then the y and x faces of the slices between.
    let at = |x: usize, y: usize, z: usize| channel[(z * ny + y) * nx + x];
    let (mut face, mut faces) = (0.0f64, 0usize);
    let mut add = |v: f32| {
        face += sq(v);
        faces += 1;
    };
    for z in 0..nz {
        let whole = z == 0 || z + 1 == nz;
        for y in 0..ny {
            if whole || y == 0 || y + 1 == ny {
                (0..nx).for_each(|x| add(at(x, y, z)));
            } else {
                add(at(0, y, z));
                if nx > 1 {
                    add(at(nx - 1, y, z));
                }
            }
        }
    }
    if all <= 0.0 || faces == 0 {
        return 0.0;
    }
    ((face / faces as f64) / (all / channel.len() as f64)).sqrt()
}

/// [`face_median`] of each colour channel.
fn face_colour(volume: &Volume) -> [f64; 3] {
    [0, 1, 2].map(|c| face_median(volume.channel(c), volume.dims()))
}

/// Colour second moments about `origin`, E[(x − o)(x − o)ᵀ] (divided by N), in f64.
pub(crate) fn second_moments(volume: &Volume, origin: [f64; 3]) -> [[f64; 3]; 3] {
    let ch = volume.channels();
    let n = volume.voxel_count() as f64;
    let mut m = [[0.0f64; 3]; 3];
    for v in 0..volume.voxel_count() {
        let x = [0, 1, 2].map(|c| f64::from(ch[c][v]) - origin[c]);
        for i in 0..3 {
            for j in i..3 {
                m[i][j] += x[i] * x[j];
            }
        }
    }
    for i in 0..3 {
        for j in i..3 {
            m[i][j] /= n;
            m[j][i] = m[i][j];
        }
    }
    m
}

/// Eigen-decomposition of a symmetric positive semi-definite 3×3 matrix: rows of the returned
/// basis are orthonormal eigenvectors sorted by eigenvalue (descending), with the eigenvalues
/// (values below the numerical noise floor set to 0). Never returns NaN.
fn pca_basis(cov: &[[f64; 3]; 3]) -> ([[f64; 3]; 3], [f64; 3]) {
    let finite = cov.iter().flatten().all(|v| v.is_finite());
    let scale = cov.iter().flatten().fold(0.0f64, |a, v| a.max(v.abs()));
    if !finite || scale == 0.0 {
        // Black volume (or unusable statistics): nothing to decorrelate.
        return (IDENTITY, [0.0; 3]);
    }
    // Work on the normalised matrix so that tiny or huge variances behave alike.
    let m = Matrix3::from_fn(|i, j| cov[i][j] / scale);
    let eig = SymmetricEigen::new(m);
    let mut pairs: Vec<(f64, Vector3<f64>)> = (0..3)
        .map(|k| {
            let l = eig.eigenvalues[k];
            let v: Vector3<f64> = eig.eigenvectors.column(k).into_owned();
            (if l.is_finite() { l } else { 0.0 }, v)
        })
        .collect();
    pairs.sort_by(|a, b| b.0.total_cmp(&a.0));

    let vectors: Vec<[f64; 3]> = pairs.iter().map(|(_, v)| [v[0], v[1], v[2]]).collect();
    let basis = orthonormalize([vectors[0], vectors[1], vectors[2]]);

    // The Rayleigh quotient of each final vector (equals the eigenvalue; exact for
    // re-orthonormalised vectors too), with the noise floor removed.
    let floor = 1e-12 * 3.0;
    let energy = [0, 1, 2].map(|i| {
        let b = Vector3::from(basis[i]);
        let l = (b.transpose() * m * b)[(0, 0)].abs();
        if l <= floor || !l.is_finite() {
            0.0
        } else {
            l * scale
        }
    });
    (basis, energy)
}

/// Modified Gram–Schmidt in the given order; a vector that is (nearly) dependent on the earlier
/// ones, or not finite, is replaced by the standard basis vector with the largest residual.
/// Signs are made deterministic (largest-magnitude component positive).
fn orthonormalize(vs: [[f64; 3]; 3]) -> [[f64; 3]; 3] {
    let mut out: Vec<Vector3<f64>> = Vec::with_capacity(3);
    for v in vs {
        let candidate = Vector3::from(v);
        let residual = |mut w: Vector3<f64>, out: &[Vector3<f64>]| {
            // Two passes for accuracy ("twice is enough").
            for _ in 0..2 {
                for u in out {
                    w -= *u * u.dot(&w);
                }
            }
            w
        };
        let mut w = if candidate.iter().all(|x| x.is_finite()) {
            residual(candidate, &out)
        } else {
            Vector3::zeros()
        };
        let norm = w.norm();
        if norm.is_nan() || norm <= 1e-6 {
            w = (0..3)
                .map(|k| residual(Vector3::ith(k, 1.0), &out))
                .max_by(|a, b| a.norm().total_cmp(&b.norm()))
                .unwrap_or_else(|| Vector3::ith(0, 1.0));
        }
        w /= w.norm();
        let big = (0..3)
            .max_by(|a, b| w[*a].abs().total_cmp(&w[*b].abs()))
            .unwrap_or(0);
        if w[big] < 0.0 {
            w = -w;
        }
        out.push(w);
    }
    [0, 1, 2].map(|i| [out[i][0], out[i][1], out[i][2]])
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn rgb_volume(dims: [usize; 3], f: impl Fn(usize) -> [f32; 3]) -> Volume {
        let n = dims.iter().product();
        let data: Vec<f32> = (0..n).flat_map(&f).collect();
        Volume::from_interleaved(dims, [1.0; 3], 3, &data).unwrap()
    }

    fn random_volume(seed: u64) -> Volume {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let dims = [7, 6, 5];
        let n: usize = dims.iter().product();
        let data: Vec<f32> = (0..n)
            .flat_map(|_| {
                let a: f32 = rng.gen::<f32>() * 200.0;
                let b: f32 = rng.gen::<f32>() * 30.0;
                let c: f32 = rng.gen::<f32>() * 5.0;
                [a + b, 0.5 * a - b + c, 0.2 * a + c + 10.0]
            })
            .collect();
        Volume::from_interleaved(dims, [1.0; 3], 3, &data).unwrap()
    }

    fn moments(v: &Volume, origin: [f64; 3]) -> [[f64; 3]; 3] {
        // Naive reference (every pair, no symmetry).
        let n = v.voxel_count() as f64;
        let mut ss = [[0.0f64; 3]; 3];
        for i in 0..v.voxel_count() {
            let x = [0, 1, 2].map(|c| f64::from(v.channel(c)[i]) - origin[c]);
            for a in 0..3 {
                for b in 0..3 {
                    ss[a][b] += x[a] * x[b];
                }
            }
        }
        ss.map(|row| row.map(|x| x / n))
    }

    fn assert_orthonormal(t: &ColorTransform) {
        let e = orthonormality_error(&t.basis);
        assert!(e <= 1e-12, "orthonormality error {e}: {:?}", t.basis);
    }

    fn assert_no_nan(t: &ColorTransform) {
        let all = t
            .basis
            .iter()
            .flatten()
            .chain(t.mean.iter())
            .chain(t.importance.iter());
        for v in all {
            assert!(v.is_finite(), "{t:?}");
        }
    }

    fn assert_round_trip(t: &ColorTransform, v: &Volume) {
        let c = t.forward(v).unwrap();
        let back = t.inverse(&c).unwrap();
        let (lo, hi) = v.value_range();
        let scale = lo.abs().max(hi.abs()).max(1e-30);
        for ch in 0..3 {
            for (a, b) in v.channel(ch).iter().zip(back.channel(ch)) {
                assert!((a - b).abs() <= 1e-5 * scale, "{:?}: {a} vs {b}", t.kind);
            }
        }
    }

    #[test]
    fn names() {
        for n in ColorSpaceKind::names() {
            assert_eq!(ColorSpaceKind::from_name(n).unwrap().name(), *n);
        }
        assert_eq!(ColorSpaceKind::from_name("PCA"), Some(ColorSpaceKind::Pca));
        assert_eq!(ColorSpaceKind::from_name("hsv"), None);
    }

    #[test]
    fn round_trip_every_kind() {
        let v = random_volume(3);
        for kind in [
            ColorSpaceKind::Rgb,
            ColorSpaceKind::Yiq,
            ColorSpaceKind::Pca,
        ] {
            let t = ColorTransform::fit(kind, &v).unwrap();
            assert_eq!(t.kind, kind);
            assert_no_nan(&t);
            assert_round_trip(&t, &v);
            // Pixel versions agree with the matrix.
            let p = [12.0, -3.0, 100.0];
            let q = t.inverse_pixel(t.forward_pixel(p));
            for j in 0..3 {
                assert!((p[j] - q[j]).abs() < 1e-9);
            }
        }
        let origin = face_colour(&v);
        assert!(origin.iter().all(|o| *o > 0.0), "{origin:?}");
        let rgb = ColorTransform::fit(ColorSpaceKind::Rgb, &v).unwrap();
        assert_eq!(rgb.importance, [1.0; 3]);
        assert_eq!(rgb.mean, origin);
        let shifted = rgb.forward(&v).unwrap();
        for c in 0..3 {
            for (a, b) in v.channel(c).iter().zip(shifted.channel(c)) {
                assert!((f64::from(*a) - origin[c] - f64::from(*b)).abs() < 1e-4);
            }
        }
        let yiq = ColorTransform::fit(ColorSpaceKind::Yiq, &v).unwrap();
        assert_eq!(yiq.basis, YIQ_MATRIX);
        assert_eq!(yiq.importance, ColorTransform::yiq().importance);
        assert_eq!(yiq.mean, origin);
        let pca = ColorTransform::fit(ColorSpaceKind::Pca, &v).unwrap();
        assert_eq!(pca.importance, [1.0; 3]);
        assert_eq!(pca.mean, origin);
    }

    #[test]
    fn face_activity_separates_flat_faces_from_cut_ones() {
        let dims = [9, 7, 5];
        let n = 9 * 7 * 5;
        let interior = |i: usize| {
            let (x, y, z) = (i % 9, (i / 9) % 7, i / 63);
            x > 0 && y > 0 && z > 0 && x < 8 && y < 6 && z < 4
        };
        // Constant faces around anything: 0 (whatever the constant).
        let flat: Vec<f32> = (0..n)
            .map(|i| {
                if interior(i) {
                    (i % 7) as f32 * 30.0
                } else {
                    -1000.0
                }
            })
            .collect();
        assert_eq!(face_activity(&flat, dims), 0.0);
        // The same pattern everywhere: the faces carry what the inside does (near 1).
        let cut: Vec<f32> = (0..n).map(|i| (i % 7) as f32 * 30.0).collect();
        let a = face_activity(&cut, dims);
        assert!((0.8..1.25).contains(&a), "{a}");
        // Degenerate: constant, empty, a line of voxels (all faces), a NaN ignored.
        assert_eq!(face_activity(&vec![3.0; n], dims), 0.0);
        assert_eq!(face_activity(&[], [0, 1, 1]), 0.0);
        assert!((face_activity(&[0.0, 5.0, 1.0, 9.0], [1, 1, 4]) - 1.0).abs() < 1e-12);
        let mut with_nan = cut.clone();
        with_nan[40] = f32::NAN;
        assert!(face_activity(&with_nan, dims).is_finite());
    }

    #[test]
    fn face_median_reads_only_the_faces() {
        // 5×4×3 (x fastest): 54 face voxels, 6 interior ones (z = 1, 0 < y < 3, 0 < x < 4).
        // Six face voxels hold 9.0, the rest 1.0; interior voxels hold 1000 and must not count.
        let dims = [5, 4, 3];
        let index = |x: usize, y: usize, z: usize| (z * 4 + y) * 5 + x;
        let mut ch = vec![1.0f32; 60];
        for i in [0, 7, 13, 20, 44, 59] {
            ch[i] = 9.0;
        }
        for y in 1..3 {
            for x in 1..4 {
                ch[index(x, y, 1)] = 1000.0;
            }
        }
        assert_eq!(face_median(&ch, dims), 1.0);
        // Only interior voxels differ: the faces decide.
        let mut air = vec![-1000.0f32; 60];
        air[index(2, 2, 1)] = 40.0;
        assert_eq!(face_median(&air, dims), -1000.0);
        // A single voxel is its own face; an empty or mis-sized channel gives 0.
        assert_eq!(face_median(&[7.5], [1, 1, 1]), 7.5);
        assert_eq!(face_median(&[], [0, 1, 1]), 0.0);
        assert_eq!(face_median(&[1.0, 2.0], [3, 1, 1]), 0.0);
        // Even count: the lower middle sample.
        assert_eq!(face_median(&[4.0, 2.0], [2, 1, 1]), 2.0);
    }

    #[test]
    fn importances_weigh_channel_errors_as_they_return_to_rgb() {
        // An error e in channel i alone comes back to RGB with squared norm I_i e².
        let v = random_volume(5);
        for kind in [
            ColorSpaceKind::Rgb,
            ColorSpaceKind::Yiq,
            ColorSpaceKind::Pca,
        ] {
            let t = ColorTransform::fit(kind, &v).unwrap();
            let p = [40.0, 120.0, 7.0];
            let c = t.forward_pixel(p);
            for i in 0..3 {
                let e = 0.25;
                let mut ce = c;
                ce[i] += e;
                let back = t.inverse_pixel(ce);
                let err2: f64 = (0..3).map(|j| (back[j] - p[j]).powi(2)).sum();
                let want = t.importance[i] * e * e;
                assert!(
                    (err2 - want).abs() <= 1e-9 * want,
                    "{kind:?} {i}: {err2} vs {want}"
                );
            }
        }
        // YIQ's Q channel comes back much stronger than its Y channel.
        let yiq = ColorTransform::yiq();
        assert!(
            yiq.importance[2] > yiq.importance[0],
            "{:?}",
            yiq.importance
        );
    }

    #[test]
    fn yiq_inverse_is_exact() {
        let t = ColorTransform::yiq();
        let inv = t.inverse_matrix();
        for i in 0..3 {
            for j in 0..3 {
                let d: f64 = (0..3).map(|k| inv[i][k] * YIQ_MATRIX[k][j]).sum();
                let want = if i == j { 1.0 } else { 0.0 };
                assert!((d - want).abs() < 1e-14, "{i},{j}: {d}");
            }
        }
        // White maps to (1, ~0, ~0) and back.
        let w = t.forward_pixel([1.0; 3]);
        assert!((w[0] - 1.0).abs() < 1e-12 && w[1].abs() < 1e-12 && w[2].abs() < 1e-12);
    }

    #[test]
    fn pca_diagonalises_the_colour_moments() {
        let v = random_volume(11);
        let t = ColorTransform::fit(ColorSpaceKind::Pca, &v).unwrap();
        assert_orthonormal(&t);
        let m = moments(&v, t.mean);
        assert_eq!(t.mean, face_colour(&v));
        let (basis, energy) = pca_basis(&second_moments(&v, t.mean));
        assert_eq!(basis, t.basis);
        assert!(energy[0] >= energy[1] && energy[1] >= energy[2] && energy[2] > 0.0);
        let scale = energy[0];
        // bᵢᵀ M bⱼ = λᵢ δᵢⱼ: the basis diagonalises the second moments.
        for i in 0..3 {
            for j in 0..3 {
                let s: f64 = (0..3)
                    .flat_map(|a| (0..3).map(move |b| (a, b)))
                    .map(|(a, b)| t.basis[i][a] * m[a][b] * t.basis[j][b])
                    .sum();
                let want = if i == j { energy[i] } else { 0.0 };
                assert!((s - want).abs() <= 1e-9 * scale, "{i},{j}: {s} vs {want}");
            }
        }
        // Trace is preserved.
        let tr = m[0][0] + m[1][1] + m[2][2];
        let sum: f64 = energy.iter().sum();
        assert!((tr - sum).abs() <= 1e-9 * tr);
        // The forward channels are uncorrelated about zero (the origin subtracted) and the
        // first carries the most
        // energy (its mean square is λ₁).
        let c = t.forward(&v).unwrap();
        let dot = |a: &[f32], b: &[f32]| {
            a.iter()
                .zip(b)
                .map(|(x, y)| f64::from(*x) * f64::from(*y))
                .sum::<f64>()
                / a.len() as f64
        };
        for i in 0..3 {
            for j in 0..i {
                assert!(dot(c.channel(i), c.channel(j)).abs() < 1e-4 * scale);
            }
        }
        assert!(dot(c.channel(0), c.channel(0)) >= dot(c.channel(1), c.channel(1)));
        assert!((dot(c.channel(0), c.channel(0)) - energy[0]).abs() < 1e-4 * energy[0]);
    }

    #[test]
    fn black_background_stays_zero() {
        // A classified volume: most voxels black, a few painted. The colour mean is not
        // subtracted, so black maps to zero in every channel.
        let v = rgb_volume([6, 5, 4], |i| match i % 7 {
            0 => [200.0, 60.0, 50.0],
            1 => [90.0, 40.0, 30.0],
            2 => [120.0, 180.0, 255.0],
            _ => [0.0, 0.0, 0.0],
        });
        let t = ColorTransform::fit(ColorSpaceKind::Pca, &v).unwrap();
        let c = t.forward(&v).unwrap();
        for i in (0..v.voxel_count()).filter(|i| i % 7 > 2) {
            for ch in 0..3 {
                assert_eq!(c.channel(ch)[i], 0.0);
            }
        }
        assert_round_trip(&t, &v);
    }

    #[test]
    fn grey_volume_is_rank_one() {
        let v = rgb_volume([5, 4, 3], |i| {
            let g = (i * 37 % 251) as f32;
            [g, g, g]
        });
        let t = ColorTransform::fit(ColorSpaceKind::Pca, &v).unwrap();
        assert_no_nan(&t);
        assert_orthonormal(&t);
        assert_eq!(t.importance, [1.0, 0.0, 0.0]);
        let s = 1.0 / 3f64.sqrt();
        for j in 0..3 {
            assert!((t.basis[0][j] - s).abs() < 1e-12, "{:?}", t.basis);
        }
        assert_round_trip(&t, &v);
    }

    #[test]
    fn constant_volumes() {
        // Any one colour (black, a colour, a single voxel) is the faces' colour: it is the
        // origin, every coded channel is zero and nothing is worth a coefficient.
        for (dims, colour) in [
            ([3, 3, 3], [0.0f32; 3]),
            ([3, 3, 3], [10.0, 200.0, 3.5]),
            ([1, 1, 1], [1.0, 2.0, 3.0]),
        ] {
            let v = rgb_volume(dims, |_| colour);
            let t = ColorTransform::fit(ColorSpaceKind::Pca, &v).unwrap();
            assert_no_nan(&t);
            assert_orthonormal(&t);
            assert_eq!(t.importance, [0.0; 3]);
            assert_eq!(t.mean, colour.map(f64::from));
            assert_eq!(t.forward(&v).unwrap().value_range(), (0.0, 0.0));
            assert_round_trip(&t, &v);
        }
        // One colour inside black faces: rank one, all of it in the first channel.
        let colour = [10.0f32, 200.0, 3.5];
        let v = rgb_volume([3, 3, 3], |i| if i == 13 { colour } else { [0.0; 3] });
        let t = ColorTransform::fit(ColorSpaceKind::Pca, &v).unwrap();
        assert_eq!(t.mean, [0.0; 3]);
        assert_eq!(t.importance, [1.0, 0.0, 0.0]);
        let c = t.forward(&v).unwrap();
        let norm = colour.iter().map(|x| x * x).sum::<f32>().sqrt();
        assert!((c.channel(0)[13] - norm).abs() <= 1e-5 * norm);
        for ch in 1..3 {
            assert!(c.channel(ch)[13].abs() <= 1e-5 * norm);
        }
        assert_round_trip(&t, &v);
    }

    #[test]
    fn repeated_eigenvalues() {
        // Second moments diag(4, 1, 1) in a rotated frame, and isotropic ones.
        let q = orthonormalize([[1.0, 2.0, 2.0], [2.0, 1.0, -2.0], [2.0, -2.0, 1.0]]);
        let m: [[f64; 3]; 3] = [0, 1, 2].map(|a| {
            [0, 1, 2].map(|b| (0..3).map(|k| [4.0, 1.0, 1.0][k] * q[k][a] * q[k][b]).sum())
        });
        let (basis, energy) = pca_basis(&m);
        assert!(orthonormality_error(&basis) <= 1e-12, "{basis:?}");
        for (got, want) in energy.iter().zip([4.0, 1.0, 1.0]) {
            assert!((got - want).abs() < 1e-9, "{energy:?}");
        }
        // The leading vector is q₀ up to sign.
        let d: f64 = (0..3).map(|j| basis[0][j] * q[0][j]).sum();
        assert!((d.abs() - 1.0).abs() < 1e-9);
        let (basis, energy) = pca_basis(&IDENTITY);
        assert!(orthonormality_error(&basis) <= 1e-12);
        for l in energy {
            assert!((l - 1.0).abs() < 1e-12);
        }
        // Through a volume: a factorial design about black faces round-trips.
        let mut pts = Vec::new();
        for a in [-2.0, 2.0] {
            for b in [-1.0, 1.0] {
                for c in [-1.0, 1.0] {
                    let p: [f64; 3] = [0, 1, 2].map(|j| a * q[0][j] + b * q[1][j] + c * q[2][j]);
                    pts.push(p.map(|x| x as f32));
                }
            }
        }
        let v = rgb_volume([2, 2, 2], |i| pts[i]);
        let t = ColorTransform::fit(ColorSpaceKind::Pca, &v).unwrap();
        assert_no_nan(&t);
        assert_orthonormal(&t);
        assert_round_trip(&t, &v);
    }

    #[test]
    fn orthonormalize_handles_degenerate_input() {
        let b = orthonormalize([[1.0, 1.0, 0.0], [2.0, 2.0, 0.0], [f64::NAN, 0.0, 0.0]]);
        assert!(orthonormality_error(&b) <= 1e-12, "{b:?}");
        let b = orthonormalize([[0.0; 3]; 3]);
        assert!(orthonormality_error(&b) <= 1e-12, "{b:?}");
    }

    #[test]
    fn rejects_intensity_volumes_and_maps_integrals() {
        let v = Volume::new([2, 1, 1], [1.0; 3], vec![vec![1.0, 2.0]]).unwrap();
        for kind in [
            ColorSpaceKind::Rgb,
            ColorSpaceKind::Yiq,
            ColorSpaceKind::Pca,
        ] {
            assert_eq!(
                ColorTransform::fit(kind, &v).unwrap_err(),
                ColorError::NotRgb(1)
            );
        }
        assert!(ColorTransform::yiq().forward(&v).is_err());
        assert!(ColorTransform::yiq().inverse(&v).is_err());

        // A line integral through L voxels of constant colour maps back to L × colour.
        let t = ColorTransform::fit(ColorSpaceKind::Pca, &random_volume(5)).unwrap();
        let colour = [30.0, 60.0, 90.0];
        let l = 7.0;
        let c = t.forward_pixel(colour).map(|x| x * l);
        let back = t.inverse_integral(c, l);
        for j in 0..3 {
            assert!((back[j] - colour[j] * l).abs() < 1e-9);
        }
    }
}
