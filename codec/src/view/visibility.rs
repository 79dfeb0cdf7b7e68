//! What a view sees of the coefficients, per band and per tile: the weights by which the cache
//! ranks packets (visible energy per byte) and the viewer orders its splats (largest visible
//! energy first).
//!
//! Per band, the fraction of the basis energy that survives X-ray projection (Fourier
//! projection-slice + Parseval: ∫ over the slice plane ⊥ n of |b̂|², times the pixel-area filter,
//! over ∫ |b̂|² in 3D; ~0 for a ψ along the view direction). Per tile and level, the part of the
//! tile's projected box that lies on screen (0 off screen), times the squared depth-cue
//! attenuation of the tile's nearest point. Multiview sums over its three cameras.

use super::{resolve_cue, sinc, Camera, ResolvedCue, ViewError, ViewSpec};
use crate::family::Family;
use crate::format::Header;
use crate::layout::{Band, Geometry};
use std::sync::{Arc, OnceLock};

/// Half width (cycles per voxel, level 0) and step of the slice-plane integration grid.
const GRID_RADIUS: f64 = 3.0;
const GRID_STEP: f64 = 1.0 / 16.0;

/// Per-camera weights.
#[derive(Debug, Clone)]
struct CameraWeights {
    /// Visible fraction of the basis energy per band (indexed like `Geometry::bands`).
    band_weight: Vec<f64>,
    /// On-screen fraction × cue attenuation² per (tile, level): index tile·(M+1) + level.
    tile_factor: Vec<f64>,
}

/// The visibility weights of one view spec for one volume (build once per view change).
#[derive(Debug, Clone)]
pub struct Visibility {
    geometry: Geometry,
    cams: Vec<CameraWeights>,
    /// Each (tile, level)'s box ([`tile_box`]), tile·(M+1) + level: they depend on the volume
    /// alone, so the bricks of one shape share them ([`Visibility::with_cameras`]), and
    /// computing them is most of a brick's tile factors.
    boxes: TileBoxes,
}

/// The boxes of every (tile, level) of one volume shape, and the tile edge they are for.
#[derive(Debug, Clone)]
struct TileBoxes {
    tile: usize,
    boxes: Arc<Vec<([f64; 3], [f64; 3])>>,
}

impl TileBoxes {
    fn of(header: &Header) -> TileBoxes {
        let levels = header.geometry.levels + 1;
        let boxes = (0..header.tile_count())
            .flat_map(|t| (0..levels).map(move |level| tile_box(header, t, level)))
            .collect();
        TileBoxes {
            tile: header.tile,
            boxes: Arc::new(boxes),
        }
    }
}

impl Visibility {
    /// Plans `spec` for the volume of `header`.
    pub fn new(header: &Header, spec: &ViewSpec) -> Result<Visibility, ViewError> {
        Visibility::with_cameras(header, spec, &spec.cameras(&header.geometry)?, None)
    }

    /// [`Visibility::new`] with the band weights of `like`: a visibility of the same view
    /// moved by a pan (the same orientation, zoom and cue) of a volume of the same family,
    /// depth and spacing, on which the band weights alone depend. The bricks of one volume
    /// share them: the slice-plane integration is the bulk of a visibility's cost (~10 ms a
    /// camera), the tile factors are the bricks' own. Falls back to [`Visibility::new`] when
    /// `like` is of another family, depth or spacing, or has another number of cameras.
    pub fn new_like(
        header: &Header,
        spec: &ViewSpec,
        like: &Visibility,
    ) -> Result<Visibility, ViewError> {
        Visibility::with_cameras(header, spec, &spec.cameras(&header.geometry)?, Some(like))
    }

    /// The visibility of `spec`'s view (its cue) through `cameras` (one per image of the
    /// view, each possibly moved by a pan of its own, as a bricked volume's multiview panels
    /// are in a brick), with the band weights of `like` where it fits ([`Visibility::new_like`]).
    pub fn with_cameras(
        header: &Header,
        spec: &ViewSpec,
        cameras: &[Camera],
        like: Option<&Visibility>,
    ) -> Result<Visibility, ViewError> {
        spec.validate()?;
        let g = header.geometry;
        let boxes = match like {
            Some(l) if l.is_shape_of(header) => l.boxes.clone(),
            _ => TileBoxes::of(header),
        };
        let like = like.filter(|l| {
            l.geometry.family == g.family
                && l.geometry.levels == g.levels
                && l.geometry.spacing == g.spacing
                && l.cams.len() == cameras.len()
        });
        let mut cams = Vec::with_capacity(cameras.len());
        for (k, cam) in cameras.iter().enumerate() {
            let cue = match &spec.view.cue {
                Some(c) => Some(resolve_cue(c, cam, &g)?),
                None => None,
            };
            cams.push(CameraWeights {
                band_weight: match like {
                    Some(l) => l.cams[k].band_weight.clone(),
                    None => band_weights(&g, cam),
                },
                tile_factor: tile_factors(&boxes.boxes, cam, cue.as_ref()),
            });
        }
        Ok(Visibility {
            geometry: g,
            cams,
            boxes,
        })
    }

    /// Whether this is a visibility of a volume of `header`'s shape (geometry and tile edge),
    /// whose tile boxes [`Visibility::with_cameras`] takes as they are.
    pub fn is_shape_of(&self, header: &Header) -> bool {
        self.geometry == header.geometry && self.boxes.tile == header.tile
    }

    /// The fraction of a unit-energy coefficient's energy seen in this view when it lies in
    /// `band` and tile `tile` (summed over the cameras; 0 for an unknown band or tile).
    pub fn weight(&self, band: Band, tile: usize) -> f64 {
        let Some(b) = self.geometry.band_index(band) else {
            return 0.0;
        };
        let t = tile * (self.geometry.levels + 1) + band.level as usize;
        self.cams
            .iter()
            .map(|c| c.band_weight[b] * c.tile_factor.get(t).copied().unwrap_or(0.0))
            .sum()
    }

    /// Energy of a packet of tile `tile` whose summary declares `energy` per band, as seen in
    /// this view (image energy up to a per-view constant; 0 when not finite).
    pub fn visible_energy(&self, tile: usize, summary: &[(Band, f64)]) -> f64 {
        let total: f64 = summary.iter().map(|(b, e)| e * self.weight(*b, tile)).sum();
        if total.is_finite() {
            total
        } else {
            0.0
        }
    }
}

/// What ranks a packet: its tile, its energy summary and its size.
#[derive(Debug, Clone, Copy)]
pub struct PacketFacts<'a> {
    /// Tile index.
    pub tile: usize,
    /// Energy per band.
    pub summary: &'a [(Band, f64)],
    /// Size in bytes.
    pub bytes: usize,
}

/// Sending order of packets for a view: descending visible energy per byte (the JPIP-style
/// rate–distortion slope), ties (including everything invisible) in file order. `packets` are in
/// file order; the result lists their indices.
pub fn packet_order(visibility: &Visibility, packets: &[PacketFacts<'_>]) -> Vec<u32> {
    let mut keyed: Vec<(f64, u32)> = packets
        .iter()
        .enumerate()
        .map(|(i, p)| {
            (
                visibility.visible_energy(p.tile, p.summary) / p.bytes.max(1) as f64,
                i as u32,
            )
        })
        .collect();
    keyed.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
    keyed.into_iter().map(|(_, i)| i).collect()
}

/// Fraction of each band's basis energy left in the projection of `cam` (per unit of depth,
/// with the pixel-area filter): h·∫_plane |Πₐ ĥₐ(η)|² sinc²(σ/(s z)) sinc²(ρ/(s z)) dσ dρ /
/// Πₐ ‖hₐ‖², η = (σ·S u + ρ·S v)/h, with ĥ the level-0 φ̂ or ψ̂, s = 2^level, z the zoom, S the
/// spacing and h its smallest entry: the slice plane of the physical projection seen in index
/// frequencies (σ, ρ in cycles per h). The grid is refined by the spacing's anisotropy (up to 4×)
/// so that its step along every index axis stays near the unit-spacing one. The weights rank
/// bands within one view, so constant factors (det S) are left out.
///
/// The integrand factors: |φ̂|² and |ψ̂|² come from a per-family table ([`spectrum`]), the
/// pixel filter is one sinc² per grid line and level, per grid point the eight φ/ψ patterns are
/// multiplied once for all bands, and the point symmetry of the integrand halves the grid. This
/// is the bulk of a view's planning (each stream start and view change in the cache):
/// evaluating the transforms at every grid point cost ~10 ms per camera.
pub fn band_weights(g: &Geometry, cam: &Camera) -> Vec<f64> {
    let fam = g.family;
    let table = spectrum(fam);
    let h = cam.spacing.iter().fold(f64::INFINITY, |m, s| m.min(*s));
    let widest = cam.spacing.iter().fold(0.0f64, |m, s| m.max(*s));
    let refine = (widest / h).ceil().clamp(1.0, 4.0);
    let step = GRID_STEP / refine;
    let su: [f64; 3] = std::array::from_fn(|a| cam.spacing[a] / h * cam.u[a]);
    let sv: [f64; 3] = std::array::from_fn(|a| cam.spacing[a] / h * cam.v[a]);
    let zh = cam.zoom * h;
    let n = (2.0 * GRID_RADIUS / step).round() as usize;
    let grid: Vec<f64> = (0..=n).map(|i| -GRID_RADIUS + i as f64 * step).collect();
    let bands = g.bands();
    let top = bands.iter().map(|b| b.level as usize).max().unwrap_or(0);
    // filter[level][i] = sinc²(grid[i] / (s z h)).
    let filter: Vec<Vec<f64>> = (0..=top)
        .map(|level| {
            let s = (1u64 << level) as f64;
            grid.iter()
                .map(|x| {
                    let f = sinc(x / (s * zh));
                    f * f
                })
                .collect()
        })
        .collect();
    let mut acc = vec![0.0; bands.len()];
    // The integrand is even in η (|ĥ|² and sinc² are) and the grid symmetric about 0: each
    // point below the centre stands for its mirror.
    let half = n / 2;
    let mut filtered = vec![0.0; top + 1];
    for (i, &sigma) in grid.iter().enumerate().take(half + 1) {
        for (j, &rho) in grid.iter().enumerate() {
            let weight = match (i == half && n.is_multiple_of(2), j.cmp(&half)) {
                (false, _) => 2.0,
                (true, std::cmp::Ordering::Less) => 2.0,
                (true, std::cmp::Ordering::Equal) => 1.0,
                (true, std::cmp::Ordering::Greater) => continue,
            };
            let mut p = [0.0; 3];
            let mut q = [0.0; 3];
            for a in 0..3 {
                let eta = sigma * su[a] + rho * sv[a];
                (p[a], q[a]) = table.at(fam, eta);
            }
            let pattern: [f64; 8] = std::array::from_fn(|kind| {
                weight
                    * (0..3)
                        .map(|a| if kind & (4 >> a) != 0 { q[a] } else { p[a] })
                        .product::<f64>()
            });
            for (l, f) in filtered.iter_mut().enumerate() {
                *f = filter[l][i] * filter[l][j];
            }
            for (b, band) in bands.iter().enumerate() {
                acc[b] += pattern[band.kind as usize & 7] * filtered[band.level as usize];
            }
        }
    }
    bands
        .iter()
        .zip(acc)
        .map(|(band, a)| dilation4(band) * a * step * step / g.basis_norm2(*band))
        .collect()
}

/// (2^level)⁴: the level's dilation 2^level of the slice integral over the 3D basis energy
/// `Geometry::basis_norm2`, which carries (2^level)³.
fn dilation4(band: &Band) -> f64 {
    ((1u64 << band.level) as f64).powi(4)
}

/// |φ̂(η)|² and |ψ̂(η)|² (κ = 0) of one family at η = 0, h, 2h, … up to [`SPECTRUM_MAX`], for
/// linear interpolation (both are even in η: the bases are real). With h = 1/2048 the
/// interpolation error is below 1e-6 of the peak, far under the integration grid's own.
struct Spectrum {
    phi: Vec<f64>,
    psi: Vec<f64>,
}

/// Largest |η| tabulated: the grid radius times the largest |Sₐuₐ| + |Sₐvₐ| / h (√2 for
/// isotropic spacing; up to √2 × the spacing's anisotropy), covering anisotropy up to 3.7;
/// larger arguments are evaluated directly.
const SPECTRUM_MAX: f64 = 16.0;
const SPECTRUM_STEP: f64 = 1.0 / 2048.0;

impl Spectrum {
    fn new(fam: Family) -> Spectrum {
        let n = (SPECTRUM_MAX / SPECTRUM_STEP).ceil() as usize + 2;
        let (phi, psi) = (0..n)
            .map(|k| {
                let eta = k as f64 * SPECTRUM_STEP;
                (
                    fam.phi_hat(eta, 0.0).norm_sqr(),
                    fam.psi_hat(eta, 0.0).norm_sqr(),
                )
            })
            .unzip();
        Spectrum { phi, psi }
    }

    /// (|φ̂(η)|², |ψ̂(η)|²).
    fn at(&self, fam: Family, eta: f64) -> (f64, f64) {
        let x = eta.abs() / SPECTRUM_STEP;
        let k = x.floor();
        let i = k as usize;
        if !(x.is_finite()) || i + 1 >= self.phi.len() {
            return (
                fam.phi_hat(eta, 0.0).norm_sqr(),
                fam.psi_hat(eta, 0.0).norm_sqr(),
            );
        }
        let t = x - k;
        (
            self.phi[i] + t * (self.phi[i + 1] - self.phi[i]),
            self.psi[i] + t * (self.psi[i + 1] - self.psi[i]),
        )
    }
}

/// The table of `fam`, built on first use.
fn spectrum(fam: Family) -> &'static Spectrum {
    static TABLES: [OnceLock<Spectrum>; 3] = [OnceLock::new(), OnceLock::new(), OnceLock::new()];
    let slot = Family::ALL
        .iter()
        .position(|f| *f == fam)
        .expect("every family is in Family::ALL");
    TABLES[slot].get_or_init(|| Spectrum::new(fam))
}

/// Volume-space box (min, max corners) holding every basis support of level `level` whose
/// coefficient belongs to tile `t`. Centres are placed as the renderer places them (the periodic
/// image nearest the volume centre, `Geometry::basis_center`), so coarse bases of an edge tile
/// may land on the other side of the volume.
pub fn tile_box(header: &Header, t: usize, level: usize) -> ([f64; 3], [f64; 3]) {
    let g = &header.geometry;
    let o = header.tile_origin(t);
    let s = 1usize << level;
    let reach = g
        .half_support_1d(level, true)
        .max(g.half_support_1d(level, false));
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for a in 0..3 {
        let k0 = o[a].div_ceil(s);
        let k1 = (o[a] + header.tile)
            .div_ceil(s)
            .min(g.padded[a].div_ceil(s));
        let period = g.padded[a] as f64;
        let centre = g.origin[a] as f64 + 0.5 * (g.dims[a] as f64 - 1.0);
        for k in k0..k1.max(k0 + 1) {
            for wavelet in [false, true] {
                let raw = g.raw_center_1d(level, k, wavelet);
                let c = raw - period * ((raw - centre) / period).round() - g.origin[a] as f64;
                lo[a] = lo[a].min(c - reach);
                hi[a] = hi[a].max(c + reach);
            }
        }
    }
    (lo, hi)
}

/// The on-screen fraction × cue attenuation² of each (tile, level) box of `boxes` for `cam`.
fn tile_factors(
    boxes: &[([f64; 3], [f64; 3])],
    cam: &Camera,
    cue: Option<&ResolvedCue>,
) -> Vec<f64> {
    let (w, h) = (cam.width as f64, cam.height as f64);
    let mut out = Vec::with_capacity(boxes.len());
    for &(lo, hi) in boxes {
        let mut x = [f64::INFINITY, f64::NEG_INFINITY];
        let mut y = [f64::INFINITY, f64::NEG_INFINITY];
        let mut near = f64::INFINITY;
        for c in 0..8 {
            let p = [
                if c & 1 == 0 { lo[0] } else { hi[0] },
                if c & 2 == 0 { lo[1] } else { hi[1] },
                if c & 4 == 0 { lo[2] } else { hi[2] },
            ];
            let sp = cam.to_screen(p);
            x = [x[0].min(sp[0]), x[1].max(sp[0])];
            y = [y[0].min(sp[1]), y[1].max(sp[1])];
            if let Some(cue) = cue {
                near = near.min(cue.dist(p));
            }
        }
        let ox = (x[1].min(w) - x[0].max(0.0)).max(0.0);
        let oy = (y[1].min(h) - y[0].max(0.0)).max(0.0);
        let area = ((x[1] - x[0]) * (y[1] - y[0])).max(1e-12);
        let mut f = (ox * oy / area).min(1.0);
        if let Some(cue) = cue {
            let att = (-cue.k * near.max(0.0)).exp();
            f *= att * att;
        }
        out.push(f);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::view::View;

    #[test]
    fn psi_along_the_view_direction_is_invisible() {
        let g = Geometry::new([32, 32, 32], Family::Cubic, 2, 4).unwrap();
        // α = β = 0: n = (1, 0, 0), rays along x.
        let cam = Camera::new(&View::new(0.0, 0.0, 64, 64), &g).unwrap();
        let w = band_weights(&g, &cam);
        let weight = |level, kind| w[g.band_index(Band { level, kind }).unwrap()];
        // ψ along x (kind bit 4) vanishes; ψ along y survives.
        assert!(
            weight(1, 4) < 1e-6 * weight(1, 2),
            "{} vs {}",
            weight(1, 4),
            weight(1, 2)
        );
        assert!(weight(2, 0) > weight(2, 2));
        // Rays along z: now ψ along z (bit 1) vanishes and ψ along x does not.
        let cam = Camera::new(&View::new(0.0, std::f64::consts::FRAC_PI_2, 64, 64), &g).unwrap();
        let w = band_weights(&g, &cam);
        let weight = |level, kind| w[g.band_index(Band { level, kind }).unwrap()];
        assert!(weight(1, 1) < 1e-6 * weight(1, 4));
    }

    /// The integral of [`band_weights`] evaluated term by term (no table, no symmetry).
    fn direct_band_weights(g: &Geometry, cam: &Camera) -> Vec<f64> {
        let fam = g.family;
        let h = cam.spacing.iter().fold(f64::INFINITY, |m, s| m.min(*s));
        let widest = cam.spacing.iter().fold(0.0f64, |m, s| m.max(*s));
        let step = GRID_STEP / (widest / h).ceil().clamp(1.0, 4.0);
        let su: [f64; 3] = std::array::from_fn(|a| cam.spacing[a] / h * cam.u[a]);
        let sv: [f64; 3] = std::array::from_fn(|a| cam.spacing[a] / h * cam.v[a]);
        let zh = cam.zoom * h;
        let n = (2.0 * GRID_RADIUS / step).round() as i64;
        let bands = g.bands();
        let mut acc = vec![0.0; bands.len()];
        for i in 0..=n {
            let sigma = -GRID_RADIUS + i as f64 * step;
            for j in 0..=n {
                let rho = -GRID_RADIUS + j as f64 * step;
                for (b, band) in bands.iter().enumerate() {
                    let s = (1u64 << band.level) as f64;
                    let prod: f64 = (0..3)
                        .map(|a| {
                            let eta = sigma * su[a] + rho * sv[a];
                            if band.is_wavelet_along(a) {
                                fam.psi_hat(eta, 0.0).norm_sqr()
                            } else {
                                fam.phi_hat(eta, 0.0).norm_sqr()
                            }
                        })
                        .product();
                    let pix = sinc(sigma / (s * zh)) * sinc(rho / (s * zh));
                    acc[b] += prod * pix * pix;
                }
            }
        }
        bands
            .iter()
            .zip(acc)
            .map(|(band, a)| dilation4(band) * a * step * step / g.basis_norm2(*band))
            .collect()
    }

    #[test]
    fn band_weights_match_the_direct_integral() {
        for (fam, levels, spacing) in [
            (Family::Haar, 3, [1.0, 1.0, 1.0]),
            (Family::Linear, 2, [0.5, 0.7, 1.2]),
            (Family::Cubic, 2, [1.0, 1.0, 3.0]),
        ] {
            let g = Geometry::new([24, 20, 16], fam, levels, 4)
                .unwrap()
                .with_spacing(spacing)
                .unwrap();
            for (alpha, beta, px) in [(0.3, 0.2, 48), (1.1, -0.7, 200), (0.0, 0.0, 16)] {
                let cam = Camera::new(&View::new(alpha, beta, px, px), &g).unwrap();
                let (fast, direct) = (band_weights(&g, &cam), direct_band_weights(&g, &cam));
                let top = direct.iter().cloned().fold(0.0, f64::max);
                for (b, (f, d)) in fast.iter().zip(&direct).enumerate() {
                    assert!(
                        (f - d).abs() <= 1e-6 * top,
                        "{fam:?} {spacing:?} view ({alpha}, {beta}) band {b}: {f} vs {d}"
                    );
                }
            }
        }
    }

    #[test]
    fn the_spectrum_table_matches_the_transforms() {
        for fam in Family::ALL {
            let t = spectrum(fam);
            let peak = fam.phi_hat(0.0, 0.0).norm_sqr();
            for k in 0..2000 {
                // Off the table's nodes, inside and beyond its range, both signs.
                let eta = (k as f64 * 0.0091 - 0.7) * if k % 2 == 0 { 1.0 } else { -1.0 };
                let (p, q) = t.at(fam, eta);
                let (pe, qe) = (
                    fam.phi_hat(eta, 0.0).norm_sqr(),
                    fam.psi_hat(eta, 0.0).norm_sqr(),
                );
                assert!(
                    (p - pe).abs() <= 1e-6 * peak,
                    "{fam:?} φ at {eta}: {p} vs {pe}"
                );
                assert!(
                    (q - qe).abs() <= 1e-6 * peak,
                    "{fam:?} ψ at {eta}: {q} vs {qe}"
                );
            }
        }
    }
}
