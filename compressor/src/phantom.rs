//! Built-in synthetic volumes for tests, benchmarks and the `demo`: the 3D modified Shepp–Logan
//! head phantom, nested spheres, a classified RGB head (skin white, brain red, tumour blue, like
//! the paper's Fig. 5), constants and seeded noise. Every phantom is deterministic (noise uses a
//! seeded ChaCha generator), works for any dimensions (1×1×1, odd, non-power-of-two), maps the
//! box to the normalised cube [-1, 1]³ axis by axis (so anisotropic boxes stretch the shapes),
//! samples at voxel centres, has unit spacing, and uses the 0..=255 scale of 8-bit data
//! ([`PHANTOM_MAX`]) so that metrics resemble those of real volumes, except the CT body, which
//! uses Hounsfield units (air −1000) like a real CT.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use wavesplat_codec::volume::{checked_voxels, Volume, VolumeError, MAX_VOXELS};

/// Upper end of the phantoms' value scale (that of 8-bit data); the lower end is 0.
pub const PHANTOM_MAX: f32 = 255.0;

/// A built-in synthetic volume.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Phantom {
    /// The 3D modified Shepp–Logan head (10 ellipsoids, Toft's higher-contrast intensities),
    /// scaled so that the brightest region (the skull, intensity 1.0) is 255. Intensity.
    SheppLogan,
    /// A large sphere holding smaller spheres of different values and sizes, down to one a few
    /// voxels across. Intensity, 0..=255.
    Spheres,
    /// A classified RGB head: white skin shell, red brain with dark-red ventricles, a blue
    /// tumour, black background. Three channels, 0..=255.
    RgbHead,
    /// Every voxel has this value (non-finite values are replaced by 0). Intensity.
    Constant(f32),
    /// All zero. Intensity.
    Zero,
    /// A CT-like body in Hounsfield units: air at −1000 outside an elliptic body that runs
    /// through the whole z range (the first and last slices cut through it, as in a real CT),
    /// fat −90, soft tissue 40, two lungs −820, a vertebra 700, ribs 900, seeded noise (σ 12 in
    /// the body, 4 in air). Intensity, negative values.
    Ct,
    /// Two broad Gaussian blobs (σ 0.375 and 0.1875 of the half box, peaks 200 and 80), smooth
    /// at every scale: the kind of volume a deeper transform codes better than the default
    /// depth (an oversampled acquisition). Intensity, 0..=255.
    Blobs,
    /// Independent uniform noise in [0, 255) from a ChaCha8 generator with this seed, in
    /// storage order. Intensity.
    Noise {
        /// Generator seed.
        seed: u64,
    },
}

/// A phantom of any size (more voxels than one [`Volume`] holds, too) as a source of boxes:
/// nothing is generated until a box is asked for ([`Phantom::try_generate_region`]), so a
/// 2048³ phantom is compressed brick by brick in the memory of one brick.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PhantomVolume {
    /// Which phantom.
    pub phantom: Phantom,
    /// The whole's dimensions.
    pub dims: [u64; 3],
}

/// One ellipsoid: intensity, semi-axes, centre, Euler angles (degrees, phi/theta/psi).
struct Ellipsoid {
    value: f64,
    axes: [f64; 3],
    centre: [f64; 3],
    euler_deg: [f64; 3],
}

/// The modified Shepp–Logan ellipsoids (Toft 1996 intensities; geometry of the 3D extension by
/// Kak & Slaney as tabulated in the widely used `phantom3d`). Columns: A, a, b, c, x0, y0, z0,
/// phi, theta, psi.
const SHEPP_LOGAN: [[f64; 10]; 10] = [
    [1.0, 0.6900, 0.920, 0.810, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    [-0.8, 0.6624, 0.874, 0.780, 0.0, -0.0184, 0.0, 0.0, 0.0, 0.0],
    [-0.2, 0.1100, 0.310, 0.220, 0.22, 0.0, 0.0, -18.0, 0.0, 10.0],
    [-0.2, 0.1600, 0.410, 0.280, -0.22, 0.0, 0.0, 18.0, 0.0, 10.0],
    [0.1, 0.2100, 0.250, 0.410, 0.0, 0.35, -0.15, 0.0, 0.0, 0.0],
    [0.1, 0.0460, 0.046, 0.050, 0.0, 0.1, 0.25, 0.0, 0.0, 0.0],
    [0.1, 0.0460, 0.046, 0.050, 0.0, -0.1, 0.25, 0.0, 0.0, 0.0],
    [0.1, 0.0460, 0.023, 0.050, -0.08, -0.605, 0.0, 0.0, 0.0, 0.0],
    [0.1, 0.0230, 0.023, 0.020, 0.0, -0.606, 0.0, 0.0, 0.0, 0.0],
    [0.1, 0.0230, 0.046, 0.020, 0.06, -0.605, 0.0, 0.0, 0.0, 0.0],
];

/// Margin of zeros kept around the phantom: voxel centres map to [-1-m, 1+m] with this m, so
/// ellipsoids touching ±1 still leave empty border voxels.
const MARGIN: f64 = 0.05;

/// A compiled ellipsoid test: `inside(p)` for a point in normalised coordinates.
struct Compiled {
    value: f64,
    rot: [[f64; 3]; 3],
    centre: [f64; 3],
    inv_axes_sq: [f64; 3],
}

impl Compiled {
    fn new(e: &Ellipsoid) -> Compiled {
        let [phi, theta, psi] = e.euler_deg.map(f64::to_radians);
        let (sp, cp) = phi.sin_cos();
        let (st, ct) = theta.sin_cos();
        let (ss, cs) = psi.sin_cos();
        // The Euler rotation (x-convention) of `phantom3d`: the point is rotated, then compared
        // with the centre and semi-axes.
        let rot = [
            [cs * cp - ct * sp * ss, cs * sp + ct * cp * ss, ss * st],
            [-ss * cp - ct * sp * cs, -ss * sp + ct * cp * cs, cs * st],
            [st * sp, -st * cp, ct],
        ];
        Compiled {
            value: e.value,
            rot,
            centre: e.centre,
            inv_axes_sq: e.axes.map(|a| 1.0 / (a * a)),
        }
    }

    fn contains(&self, p: [f64; 3]) -> bool {
        let mut s = 0.0;
        for i in 0..3 {
            let r = self.rot[i][0] * p[0] + self.rot[i][1] * p[1] + self.rot[i][2] * p[2];
            let d = r - self.centre[i];
            s += d * d * self.inv_axes_sq[i];
        }
        s <= 1.0
    }
}

fn shepp_logan_ellipsoids() -> Vec<Compiled> {
    SHEPP_LOGAN
        .iter()
        .map(|r| {
            Compiled::new(&Ellipsoid {
                value: r[0],
                axes: [r[1], r[2], r[3]],
                centre: [r[4], r[5], r[6]],
                euler_deg: [r[7], r[8], r[9]],
            })
        })
        .collect()
}

fn sphere(value: f64, radius: f64, centre: [f64; 3]) -> Compiled {
    Compiled::new(&Ellipsoid {
        value,
        axes: [radius; 3],
        centre,
        euler_deg: [0.0; 3],
    })
}

/// Voxel count of `dims`, validated; unlike a plain product it cannot overflow.
fn voxel_count(dims: [usize; 3]) -> Result<usize, VolumeError> {
    let product = dims.iter().try_fold(1usize, |acc, d| acc.checked_mul(*d));
    match product {
        Some(_) => checked_voxels(dims),
        None if dims.contains(&0) => checked_voxels(dims),
        None => Err(VolumeError::TooLarge {
            dims,
            voxels: u128::MAX,
            max: MAX_VOXELS,
        }),
    }
}

/// Normalised coordinate of voxel centre `i` of `n` along one axis.
fn coord(i: u64, n: u64) -> f64 {
    ((2.0 * i as f64 + 1.0) / n as f64 - 1.0) * (1.0 + MARGIN)
}

/// Which box of which whole a generated volume covers: the phantom is defined on `whole` and
/// the box at `origin` of `dims` is evaluated (the whole itself at origin 0).
#[derive(Debug, Clone, Copy)]
struct Region {
    whole: [u64; 3],
    origin: [u64; 3],
    dims: [usize; 3],
}

impl Region {
    /// Index in the whole's storage order (x fastest) of the box's voxel (0, y, z): where a row
    /// of the box starts in a generator's sequence.
    fn row_start(&self, y: usize, z: usize) -> u128 {
        let [wx, wy, _] = self.whole.map(u128::from);
        let [ox, oy, oz] = self.origin.map(u128::from);
        ox + wx * ((oy + y as u128) + wy * (oz + z as u128))
    }
}

/// Fills one channel of `r` by evaluating `f` at every voxel centre (parallel over z-slices; the
/// result does not depend on the thread count, nor on which box of the whole is asked for).
fn fill<F>(r: Region, f: F) -> Vec<f32>
where
    F: Fn([f64; 3]) -> f32 + Sync,
{
    let [nx, ny, nz] = r.dims;
    let mut out = vec![0.0f32; nx * ny * nz];
    out.par_chunks_mut((nx * ny).max(1))
        .enumerate()
        .for_each(|(z, slice)| {
            let pz = coord(r.origin[2] + z as u64, r.whole[2]);
            for y in 0..ny {
                let py = coord(r.origin[1] + y as u64, r.whole[1]);
                for x in 0..nx {
                    slice[x + nx * y] = f([coord(r.origin[0] + x as u64, r.whole[0]), py, pz]);
                }
            }
        });
    out
}

/// Fills one channel of `r` from a seeded ChaCha8 sequence that draws `words` 32-bit words per
/// voxel in the whole's storage order, `f` turning a voxel's value `v` and its words into the
/// sample. Each row of the box starts its generator at the row's word position, so any box
/// holds exactly the samples the whole generated in order would (a brick of a 2048³ phantom
/// costs no more than its own voxels).
fn fill_seeded<F>(r: Region, seed: u64, words: u128, values: Vec<f32>, f: F) -> Vec<f32>
where
    F: Fn(f32, &mut ChaCha8Rng) -> f32 + Sync,
{
    let [nx, ny, _] = r.dims;
    let mut out = values;
    out.par_chunks_mut((nx * ny).max(1))
        .enumerate()
        .for_each(|(z, slice)| {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            for (y, row) in slice.chunks_mut(nx.max(1)).enumerate() {
                rng.set_word_pos(r.row_start(y, z) * words);
                for v in row {
                    *v = f(*v, &mut rng);
                }
            }
        });
    out
}

impl Phantom {
    /// Generates the phantom at `dims` (unit spacing).
    ///
    /// # Panics
    ///
    /// If `dims` has a zero or exceeds [`MAX_VOXELS`];
    /// use [`Phantom::try_generate`] to get an error instead.
    pub fn generate(&self, dims: [usize; 3]) -> Volume {
        match self.try_generate(dims) {
            Ok(v) => v,
            Err(e) => panic!("cannot generate phantom {self:?}: {e}"),
        }
    }

    /// Generates the phantom at `dims` (unit spacing), or reports invalid dimensions.
    pub fn try_generate(&self, dims: [usize; 3]) -> Result<Volume, VolumeError> {
        self.try_generate_region(dims.map(|d| d as u64), [0; 3], dims)
    }

    /// Generates the box at `origin` of `dims` of the phantom defined on `whole` (unit spacing):
    /// exactly the voxels [`Phantom::try_generate`] gives the whole there, without generating
    /// the rest, so a whole of any size (beyond what one volume holds) can be read brick by
    /// brick. Reports a box that is empty, too large or outside the whole.
    pub fn try_generate_region(
        &self,
        whole: [u64; 3],
        origin: [u64; 3],
        dims: [usize; 3],
    ) -> Result<Volume, VolumeError> {
        let n = voxel_count(dims)?;
        VolumeError::check_within(origin, dims, whole)?;
        let r = Region {
            whole,
            origin,
            dims,
        };
        let scale = f64::from(PHANTOM_MAX);
        let channels = match *self {
            Phantom::SheppLogan => {
                let ell = shepp_logan_ellipsoids();
                vec![fill(r, |p| {
                    let v: f64 = ell.iter().filter(|e| e.contains(p)).map(|e| e.value).sum();
                    // Sums like 1 - 0.8 - 0.2 are 0 up to rounding: clamp to the scale.
                    (v.clamp(0.0, 1.0) * scale) as f32
                })]
            }
            Phantom::Spheres => {
                // Painted in order: later spheres replace earlier ones.
                let spheres = [
                    sphere(60.0, 0.85, [0.0, 0.0, 0.0]),
                    sphere(255.0, 0.35, [-0.35, -0.3, 0.1]),
                    sphere(120.0, 0.25, [0.4, 0.25, -0.2]),
                    sphere(0.0, 0.15, [-0.35, -0.3, 0.1]),
                    sphere(200.0, 0.12, [0.3, -0.45, 0.45]),
                    sphere(180.0, 0.06, [0.0, 0.55, 0.3]),
                ];
                vec![fill(r, |p| {
                    let mut v = 0.0;
                    for s in &spheres {
                        if s.contains(p) {
                            v = s.value;
                        }
                    }
                    v as f32
                })]
            }
            Phantom::RgbHead => {
                let ell = shepp_logan_ellipsoids();
                let tumour = sphere(0.0, 0.15, [0.25, 0.3, 0.2]);
                // A thicker skin than the skull of Shepp–Logan, so that it survives coarse grids.
                let brain = Compiled::new(&Ellipsoid {
                    value: 0.0,
                    axes: [0.69 * 0.88, 0.92 * 0.88, 0.81 * 0.88],
                    centre: [0.0, -0.0184, 0.0],
                    euler_deg: [0.0; 3],
                });
                // Classes: 0 background, 1 skin, 2 brain, 3 ventricle, 4 tumour.
                let class = fill(r, |p| {
                    if tumour.contains(p) && brain.contains(p) {
                        4.0
                    } else if ell[2].contains(p) || ell[3].contains(p) {
                        3.0
                    } else if brain.contains(p) {
                        2.0
                    } else if ell[0].contains(p) {
                        1.0
                    } else {
                        0.0
                    }
                });
                const COLOURS: [[f32; 3]; 5] = [
                    [0.0, 0.0, 0.0],
                    [255.0, 255.0, 255.0],
                    [220.0, 30.0, 30.0],
                    [110.0, 10.0, 10.0],
                    [30.0, 40.0, 230.0],
                ];
                (0..3)
                    .map(|c| {
                        class
                            .iter()
                            .map(|k| COLOURS[*k as usize][c])
                            .collect::<Vec<f32>>()
                    })
                    .collect()
            }
            Phantom::Constant(v) => {
                let v = if v.is_finite() { v } else { 0.0 };
                vec![vec![v; n]]
            }
            Phantom::Zero => vec![vec![0.0; n]],
            Phantom::Ct => {
                let lungs = [-0.38, 0.38].map(|x| {
                    Compiled::new(&Ellipsoid {
                        value: -820.0,
                        axes: [0.28, 0.38, 1.6],
                        centre: [x, -0.05, 0.0],
                        euler_deg: [0.0; 3],
                    })
                });
                let hu = fill(r, |p| {
                    let [x, y, z] = p;
                    let ellipse = |a: f64, b: f64| (x / a).powi(2) + (y / (b + 0.05 * z)).powi(2);
                    let mut v = -1000.0;
                    if ellipse(0.85, 0.62) <= 1.0 {
                        v = -90.0;
                    }
                    if ellipse(0.78, 0.55) <= 1.0 {
                        v = 40.0;
                        if ellipse(0.74, 0.51) > 1.0 && (9.0 * y.atan2(x) + 6.0 * z).cos() > 0.55 {
                            v = 900.0;
                        }
                    }
                    if lungs.iter().any(|l| l.contains(p)) {
                        v = -820.0;
                    }
                    if (x / 0.09).powi(2) + ((y - 0.42) / 0.09).powi(2) <= 1.0 {
                        v = 700.0;
                    }
                    v as f32
                });
                // Four words per voxel: sum of uniforms, a cheap deterministic near-Gaussian.
                vec![fill_seeded(r, 14, 4, hu, |v, rng| {
                    let sigma = if v > -950.0 { 12.0 } else { 4.0 };
                    let g: f32 = (0..4).map(|_| rng.gen::<f32>() - 0.5).sum::<f32>() * 1.73;
                    (v + sigma * g).round()
                })]
            }
            Phantom::Blobs => vec![fill(r, |p| {
                let r2 = p[0] * p[0] + p[1] * p[1] + p[2] * p[2];
                let q2 = (p[0] - 0.3125).powi(2) + (p[1] + 0.2083).powi(2) + p[2] * p[2];
                (200.0 * (-r2 / (2.0 * 0.375 * 0.375)).exp()
                    + 80.0 * (-q2 / (2.0 * 0.1875 * 0.1875)).exp()) as f32
            })],
            Phantom::Noise { seed } => {
                vec![fill_seeded(r, seed, 1, vec![0.0; n], |_, rng| {
                    rng.gen::<f32>() * PHANTOM_MAX
                })]
            }
        };
        Volume::new(dims, [1.0; 3], channels)
    }

    /// Parses a phantom name (case-insensitive, `_` and `-` interchangeable): `shepp-logan`,
    /// `spheres`, `rgb-head`, `constant` (value 128; `constant:V` for another value), `zero`, `ct`,
    /// `blobs`, `noise` (seed 0; `noise:SEED` for another seed).
    pub fn from_name(name: &str) -> Option<Phantom> {
        let name = name.trim().to_ascii_lowercase().replace('_', "-");
        let (base, arg) = match name.split_once([':', '=']) {
            Some((b, a)) => (b.to_string(), Some(a.trim().to_string())),
            None => (name, None),
        };
        match (base.as_str(), arg) {
            ("shepp-logan" | "shepplogan" | "shepp", None) => Some(Phantom::SheppLogan),
            ("spheres", None) => Some(Phantom::Spheres),
            ("rgb-head" | "rgbhead", None) => Some(Phantom::RgbHead),
            ("zero" | "zeros", None) => Some(Phantom::Zero),
            ("ct", None) => Some(Phantom::Ct),
            ("blobs", None) => Some(Phantom::Blobs),
            ("constant", None) => Some(Phantom::Constant(128.0)),
            ("constant", Some(a)) => a
                .parse::<f32>()
                .ok()
                .filter(|v| v.is_finite())
                .map(Phantom::Constant),
            ("noise", None) => Some(Phantom::Noise { seed: 0 }),
            ("noise", Some(a)) => a.parse::<u64>().ok().map(|seed| Phantom::Noise { seed }),
            _ => None,
        }
    }

    /// The base names accepted by [`Phantom::from_name`].
    pub fn names() -> &'static [&'static str] {
        &[
            "shepp-logan",
            "spheres",
            "rgb-head",
            "constant",
            "zero",
            "ct",
            "blobs",
            "noise",
        ]
    }

    /// Number of channels the phantom has (3 for [`Phantom::RgbHead`], else 1).
    pub fn channel_count(&self) -> usize {
        match self {
            Phantom::RgbHead => 3,
            _ => 1,
        }
    }
}

/// The beating phantom: time point `t` of `points` of a cine-like series at `dims` (unit
/// spacing), with a known motion. A torso (ellipsoid, value 100) holds a static spine (300)
/// and a heart (ellipsoid, 250) around a blood pool (400) whose radii scale by
/// s(t) = 1 + 0.2·sin(2πt/points), once over the series; seeded noise (uniform, ±4) differs
/// at every voxel and time point. What does not move is the same at every time point except
/// for the noise, as in a cine MR.
pub fn beating(dims: [usize; 3], t: usize, points: usize) -> Result<Volume, VolumeError> {
    let n = checked_voxels(dims)?;
    let s = beating_scale(t, points);
    let [nx, ny, nz] = dims.map(|d| d as f64);
    let norm = |i: usize, n: f64| (2.0 * (i as f64 + 0.5) / n) - 1.0;
    let inside = |p: [f64; 3], c: [f64; 3], r: [f64; 3]| {
        (0..3).map(|a| ((p[a] - c[a]) / r[a]).powi(2)).sum::<f64>() <= 1.0
    };
    let mut rng = ChaCha8Rng::seed_from_u64(0xbea7 ^ (t as u64).wrapping_mul(0x9e37_79b9));
    let mut data = Vec::with_capacity(n);
    for z in 0..dims[2] {
        for y in 0..dims[1] {
            for x in 0..dims[0] {
                let p = [norm(x, nx), norm(y, ny), norm(z, nz)];
                let mut v = 0.0;
                if inside(p, [0.0; 3], [0.9, 0.7, 0.95]) {
                    v = 100.0;
                    if inside(p, [0.0, -0.45, 0.0], [0.15, 0.15, 0.9]) {
                        v = 300.0;
                    }
                    let heart = [0.15, 0.15, 0.0];
                    if inside(p, heart, [0.35 * s, 0.3 * s, 0.5 * s]) {
                        v = 250.0;
                    }
                    if inside(p, heart, [0.22 * s, 0.18 * s, 0.35 * s]) {
                        v = 400.0;
                    }
                }
                data.push((v + rng.gen_range(-4.0..4.0)) as f32);
            }
        }
    }
    Volume::new(dims, [1.0; 3], vec![data])
}

/// The beating phantom's scale s(t) of its heart's radii at time point `t` of `points`.
pub fn beating_scale(t: usize, points: usize) -> f64 {
    1.0 + 0.2 * (2.0 * std::f64::consts::PI * t as f64 / points.max(1) as f64).sin()
}

#[cfg(test)]
mod tests {
    use super::*;

    const ODD_DIMS: [[usize; 3]; 6] = [
        [1, 1, 1],
        [2, 1, 1],
        [1, 7, 1],
        [5, 3, 9],
        [17, 12, 10],
        [33, 32, 31],
    ];

    #[test]
    fn every_phantom_any_dims_is_valid() {
        for name in Phantom::names() {
            let p = Phantom::from_name(name).unwrap();
            for dims in ODD_DIMS {
                let v = p.generate(dims);
                assert_eq!(v.dims(), dims);
                assert_eq!(v.channel_count(), p.channel_count());
                let (lo, hi) = v.value_range();
                // The CT body is in Hounsfield units (air −1000, bone 900, plus noise).
                let range = if p == Phantom::Ct {
                    -1100.0..=1100.0
                } else {
                    0.0..=PHANTOM_MAX
                };
                assert!(
                    range.contains(&lo) && range.contains(&hi),
                    "{name} {dims:?}: {lo}..{hi}"
                );
            }
        }
        assert!(Phantom::Zero.try_generate([0, 1, 1]).is_err());
        assert!(Phantom::Zero
            .try_generate([usize::MAX, usize::MAX, 1])
            .is_err());
    }

    #[test]
    fn deterministic() {
        for name in Phantom::names() {
            let p = Phantom::from_name(name).unwrap();
            assert_eq!(p.generate([9, 8, 7]), p.generate([9, 8, 7]));
        }
        let a = Phantom::Noise { seed: 1 }.generate([8, 8, 8]);
        let b = Phantom::Noise { seed: 2 }.generate([8, 8, 8]);
        assert_ne!(a, b);
    }

    #[test]
    fn noise_is_the_generator_drawn_in_storage_order() {
        // Independent of the row-wise word positions: one generator drawn voxel after voxel.
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let expected: Vec<f32> = (0..7 * 5 * 3)
            .map(|_| rng.gen::<f32>() * PHANTOM_MAX)
            .collect();
        let v = Phantom::Noise { seed: 3 }.generate([7, 5, 3]);
        assert_eq!(v.channel(0), expected.as_slice());
    }

    #[test]
    fn every_box_of_a_whole_is_that_box_of_the_generated_whole() {
        let whole = [17, 12, 10];
        let boxes = [
            ([0, 0, 0], whole),
            ([3, 2, 1], [9, 7, 5]),
            ([16, 11, 9], [1, 1, 1]),
            ([0, 5, 0], [17, 1, 10]),
        ];
        for name in Phantom::names() {
            let p = Phantom::from_name(name).unwrap();
            let full = p.generate(whole);
            for (origin, dims) in boxes {
                let region = p
                    .try_generate_region(whole.map(|d| d as u64), origin, dims)
                    .unwrap();
                let cropped = crate::bricked::crop(&full, origin, dims).unwrap();
                assert_eq!(region, cropped, "{name} at {origin:?} of {dims:?}");
            }
        }
    }

    #[test]
    fn a_box_of_a_whole_beyond_one_volume_is_generated_alone() {
        // 2^33 voxels in the whole: only the box is generated, at its place in the sequence.
        let whole = [2048u64, 2048, 2048];
        let origin = [2040, 2047, 2046];
        let v = Phantom::Noise { seed: 5 }
            .try_generate_region(whole, origin, [8, 1, 2])
            .unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let at = origin[0] as u128 + 2048 * (origin[1] as u128 + 2048 * origin[2] as u128);
        rng.set_word_pos(at);
        let first: Vec<f32> = (0..8).map(|_| rng.gen::<f32>() * PHANTOM_MAX).collect();
        assert_eq!(&v.channel(0)[..8], first.as_slice());
        // The CT's body runs through every slice: the last slice is not air everywhere.
        let ct = Phantom::Ct
            .try_generate_region(whole, [896, 896, 2047], [256, 256, 1])
            .unwrap();
        assert!(ct.value_range().1 > 0.0);
        for (origin, dims) in [
            ([2041, 0, 0], [8, 1, 1]),
            ([0, 0, u64::MAX], [1, 1, 1]),
            ([0, 0, 0], [0, 1, 1]),
        ] {
            assert!(
                Phantom::Zero
                    .try_generate_region(whole, origin, dims)
                    .is_err(),
                "{origin:?} {dims:?}"
            );
        }
    }

    #[test]
    fn shepp_logan_structure() {
        let n = 64;
        let v = Phantom::SheppLogan.generate([n, n, n]);
        let at = |x: usize, y: usize, z: usize| v.channel(0)[v.index(x, y, z)];
        // Zero margin on every face.
        for a in 0..n {
            for b in 0..n {
                assert_eq!(at(0, a, b), 0.0);
                assert_eq!(at(n - 1, a, b), 0.0);
                assert_eq!(at(a, 0, b), 0.0);
                assert_eq!(at(a, n - 1, b), 0.0);
                assert_eq!(at(a, b, 0), 0.0);
                assert_eq!(at(a, b, n - 1), 0.0);
            }
        }
        // Brain (1 - 0.8 = 0.2) at the centre, skull (1.0) near the top of the y axis.
        assert!((at(n / 2, n / 2, n / 2) - 0.2 * 255.0).abs() < 1e-3);
        let (_, hi) = v.value_range();
        assert_eq!(hi, 255.0);
        // The grey levels of the modified phantom: background and ventricles 0, brain 0.2,
        // small features 0.3, skull 1.0.
        let mut levels: Vec<i32> = v.channel(0).iter().map(|x| x.round() as i32).collect();
        levels.sort_unstable();
        levels.dedup();
        assert_eq!(levels, [0, 51, 77, 255]);
        // 1×1×1 samples the centre.
        let one = Phantom::SheppLogan.generate([1, 1, 1]);
        assert!((one.channel(0)[0] - 51.0).abs() < 1e-3);
    }

    #[test]
    fn rgb_head_classes() {
        let v = Phantom::RgbHead.generate([40, 40, 40]);
        let mut colours: Vec<[i32; 3]> = (0..v.voxel_count())
            .map(|i| [0, 1, 2].map(|c| v.channel(c)[i] as i32))
            .collect();
        colours.sort_unstable();
        colours.dedup();
        assert!(colours.contains(&[255, 255, 255]), "skin");
        assert!(colours.contains(&[220, 30, 30]), "brain");
        assert!(colours.contains(&[30, 40, 230]), "tumour");
        assert!(colours.contains(&[0, 0, 0]), "background");
    }

    #[test]
    fn names_parse() {
        assert_eq!(Phantom::from_name("Shepp_Logan"), Some(Phantom::SheppLogan));
        assert_eq!(
            Phantom::from_name("constant:2.5"),
            Some(Phantom::Constant(2.5))
        );
        assert_eq!(
            Phantom::from_name("noise=7"),
            Some(Phantom::Noise { seed: 7 })
        );
        assert_eq!(Phantom::from_name("constant:nan"), None);
        assert_eq!(Phantom::from_name("spheres:1"), None);
        assert_eq!(Phantom::from_name("banana"), None);
        let c = Phantom::Constant(f32::NAN).generate([2, 2, 2]);
        assert_eq!(c.value_range(), (0.0, 0.0));
    }
}
