//! View geometry, the vocabulary shared by the renderer, the cache and the client: what a viewer
//! looks at ([`View`], [`ViewSpec`]) with its one validation, the orthographic [`Camera`] that
//! maps volume coordinates (voxel (i, j, k) at (i, j, k)) through the voxel spacing to physical
//! space and on to continuous screen coordinates, the
//! depth cue resolved against the data ([`ResolvedCue`]), the three multiview cameras and type
//! permutations (§3.1), and in [`visibility`] the per-band and per-tile weights of what a view
//! sees of the coefficients (by which the cache ranks packets and the viewer orders its splats).
//! The splat renderer and the reference ray caster both resolve views here, so they see exactly
//! the same view.
//!
//! A view is given by spherical angles (α, β) as in §3.1 of the paper:
//! u = (−sin α, cos α, 0), v = (−cos α sin β, −sin α sin β, cos β), view direction n = u × v
//! (= (cos α cos β, sin α cos β, sin β)), or by an explicit orthonormal pair (u, v) (needed for
//! the third multiview, which is not a spherical view). Screen coordinates are continuous pixel
//! coordinates: pixel (ix, iy) covers [ix, ix+1] × [iy, iy+1], row 0 at the top.
//!
//! **Physical units.** The view lives in physical space (the units of the voxel spacing, mm for
//! medical data): a voxel index point x is at y = S(x − c), S = diag(spacing), c the volume
//! centre (dims − 1)/2, and maps to X = W/2 + zoom·(y·u − pan_u), Y = H/2 − zoom·(y·v − pan_v),
//! so the image is centred on the volume centre unless panned. `zoom` is pixels per unit of
//! spacing (pixels per voxel for cubic unit voxels); by default it fits the volume's physical
//! bounding sphere (radius |S·dims|/2) into the smaller image side. Rays travel along n in
//! physical space, which is the index-space direction S⁻¹n per unit of length
//! ([`Camera::ray`]); a voxel step along axis a moves the image by zoom·s_a·(u_a, −v_a)
//! ([`Camera::index_axes`]). Pan is in units of spacing and a depth-cue extinction per unit of
//! spacing, so an anisotropic volume renders as its physical shape, never squashed.

use crate::layout::Geometry;
use thiserror::Error;

pub mod bricked;
pub mod patient;
pub mod priority;
pub mod visibility;

/// Largest image side accepted (per view; a multiview image is three of them side by side).
pub const MAX_IMAGE_SIDE: usize = 8192;
/// Largest accepted |angle| (radians) and |pan| (voxels): beyond it f64 angles lose their
/// fractional part and a pan puts the volume astronomically far off screen.
pub const MAX_ABS_PARAM: f64 = 1e6;
/// Largest accepted zoom (pixels per voxel along the volume's widest-spaced axis).
pub const MAX_ZOOM: f64 = 1e4;
/// Largest accepted depth-cue extinction (per unit of spacing): e^(−1000) already underflows f64
/// after one unit, so larger values change nothing.
pub const MAX_CUE_K: f64 = 1e3;

/// Invalid view parameters.
#[derive(Debug, Error, PartialEq)]
#[non_exhaustive]
pub enum ViewError {
    /// An angle, zoom, pan or cue parameter is NaN or infinite.
    #[error("view parameter {0} is not finite")]
    NotFinite(&'static str),
    /// An angle or pan beyond [`MAX_ABS_PARAM`].
    #[error("view parameter {what} = {} must satisfy |{what}| <= {max}", Readable(*.value), max = Readable(MAX_ABS_PARAM))]
    OutOfRange {
        /// Which parameter.
        what: &'static str,
        /// Its value.
        value: f64,
    },
    /// Image size is zero or larger than [`MAX_IMAGE_SIDE`].
    #[error("image size {width}x{height} must be within 1..={max} on each side", max = MAX_IMAGE_SIDE)]
    BadSize {
        /// Width.
        width: usize,
        /// Height.
        height: usize,
    },
    /// Zoom must be positive and at most [`MAX_ZOOM`] pixels per voxel.
    #[error("zoom {} must be positive and give at most {max} pixels per voxel", Readable(*.0), max = Readable(MAX_ZOOM))]
    BadZoom(f64),
    /// The explicit basis is not orthonormal.
    #[error("the explicit view basis (u, v) is not orthonormal")]
    NotOrthonormal,
    /// The cue extinction must be within [0, [`MAX_CUE_K`]].
    #[error("cue extinction k = {} must be within [0, {max}] per unit of spacing", Readable(*.0), max = Readable(MAX_CUE_K))]
    BadExtinction(f64),
    /// Depth cueing is not defined for multiview (the cue would rotate with each view).
    #[error("depth cueing cannot be combined with multiview")]
    CueWithMultiview,
    /// Zero cue direction vector.
    #[error("the cue direction vector is zero")]
    ZeroCueDirection,
}

/// A number as people read it in a message: plain for ordinary magnitudes, in scientific
/// notation for huge or tiny ones (Rust's `Display` for `f64` never uses an exponent, so
/// `1e300` would print as 301 digits).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Readable(pub f64);

impl std::fmt::Display for Readable {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let a = self.0.abs();
        if self.0.is_finite() && a != 0.0 && !(1e-4..1e6).contains(&a) {
            write!(f, "{:e}", self.0)
        } else {
            write!(f, "{}", self.0)
        }
    }
}

/// How the view is oriented.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Orientation {
    /// Spherical angles (α, β) in radians (paper §3.1).
    Angles {
        /// α.
        alpha: f64,
        /// β.
        beta: f64,
    },
    /// Explicit orthonormal screen axes (u right, v up); n = u × v.
    Basis {
        /// Screen right.
        u: [f64; 3],
        /// Screen up.
        v: [f64; 3],
    },
}

/// Direction of the depth-cue light.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum CueDirection {
    /// Along the view direction n (light plane on the viewer's side): the emission–absorption
    /// image with constant attenuation.
    View,
    /// Eq. 12 of the paper taken literally: L ∝ (−cos α_l cos β_l, sin α_l cos β_l, sin β_l).
    /// (Note: eq. 12 differs from the view direction n(α, β) by the sign of x, so
    /// (α_l, β_l) = (α, β) is *not* the view direction; use [`CueDirection::View`] for that.)
    Angles {
        /// α_l.
        alpha: f64,
        /// β_l.
        beta: f64,
    },
    /// Any direction (normalised internally): the light travels along this vector.
    Vector([f64; 3]),
}

/// Exponential depth cueing: every point is weighted by e^(−k·dist) with dist its physical
/// distance from the light plane (see [`ResolvedCue`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Cue {
    /// Extinction per unit of spacing (per voxel for unit spacing), ≥ 0.
    pub k: f64,
    /// Light direction.
    pub direction: CueDirection,
}

impl Cue {
    /// The extinction a volume's depth cueing takes when none is given: 2 / the length of the
    /// volume's physical diagonal, so that along the longest path through the volume the far
    /// end is weighted e^(−2) ≈ 14 % of the near end (the light-facing side), whatever the
    /// volume's size and spacing. Its units are those of `k`: per unit of spacing.
    pub fn default_extinction(geometry: &Geometry) -> f64 {
        let diagonal = (0..3)
            .map(|a| (geometry.dims[a] as f64 * f64::from(geometry.spacing[a])).powi(2))
            .sum::<f64>()
            .sqrt();
        (2.0 / diagonal.max(1e-9)).min(MAX_CUE_K)
    }
}

/// What to render: orientation, image size, zoom, pan and optional depth cue.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct View {
    /// Orientation.
    pub orientation: Orientation,
    /// Image width (pixels; per view for multiview).
    pub width: usize,
    /// Image height.
    pub height: usize,
    /// Pixels per unit of spacing (per mm for medical data); `None` fits the volume's
    /// bounding sphere.
    pub zoom: Option<f64>,
    /// Pan (units of spacing along u and v) of the image centre away from the volume centre.
    pub pan: [f64; 2],
    /// Depth cueing.
    pub cue: Option<Cue>,
}

impl View {
    /// A view from spherical angles with default zoom, no pan, no cue.
    pub fn new(alpha: f64, beta: f64, width: usize, height: usize) -> View {
        View {
            orientation: Orientation::Angles { alpha, beta },
            width,
            height,
            zoom: None,
            pan: [0.0; 2],
            cue: None,
        }
    }

    /// Same view with an explicit zoom.
    pub fn with_zoom(mut self, zoom: f64) -> View {
        self.zoom = Some(zoom);
        self
    }

    /// Same view with a pan (units of spacing along u, v).
    pub fn with_pan(mut self, pan: [f64; 2]) -> View {
        self.pan = pan;
        self
    }

    /// Same view with depth cueing.
    pub fn with_cue(mut self, cue: Cue) -> View {
        self.cue = Some(cue);
        self
    }
}

/// A resolved orthographic camera for a volume of given dimensions and voxel spacing.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Camera {
    /// Screen right (unit, physical space aligned with the volume's axes).
    pub u: [f64; 3],
    /// Screen up.
    pub v: [f64; 3],
    /// View direction u × v (rays travel along n).
    pub n: [f64; 3],
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// Pixels per unit of spacing.
    pub zoom: f64,
    /// Pan in units of spacing along (u, v).
    pub pan: [f64; 2],
    /// Volume centre (dims − 1)/2 (voxel indices).
    pub center: [f64; 3],
    /// Voxel spacing along x, y, z.
    pub spacing: [f64; 3],
}

/// Dot product.
pub fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// Cross product.
pub fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// The screen axes (u, v) of spherical angles (α, β).
pub fn basis_from_angles(alpha: f64, beta: f64) -> ([f64; 3], [f64; 3]) {
    let (sa, ca) = alpha.sin_cos();
    let (sb, cb) = beta.sin_cos();
    ([-sa, ca, 0.0], [-ca * sb, -sa * sb, cb])
}

fn finite3(x: [f64; 3], what: &'static str) -> Result<(), ViewError> {
    if x.iter().all(|c| c.is_finite()) {
        Ok(())
    } else {
        Err(ViewError::NotFinite(what))
    }
}

impl View {
    /// Checks every parameter that does not depend on the volume: image size, finite angles,
    /// zoom and pan within range, an orthonormal explicit basis, a valid cue. The one validation
    /// of a view: the renderer, the cache and the client all call it.
    pub fn validate(&self) -> Result<(), ViewError> {
        self.basis().map(|_| ())
    }

    /// Validates and returns the screen axes (u, v).
    fn basis(&self) -> Result<([f64; 3], [f64; 3]), ViewError> {
        if self.width == 0
            || self.height == 0
            || self.width > MAX_IMAGE_SIDE
            || self.height > MAX_IMAGE_SIDE
        {
            return Err(ViewError::BadSize {
                width: self.width,
                height: self.height,
            });
        }
        let (u, v) = match self.orientation {
            Orientation::Angles { alpha, beta } => {
                bounded(alpha, "alpha")?;
                bounded(beta, "beta")?;
                basis_from_angles(alpha, beta)
            }
            Orientation::Basis { u, v } => {
                finite3(u, "basis")?;
                finite3(v, "basis")?;
                if (dot(u, u) - 1.0).abs() > 1e-9
                    || (dot(v, v) - 1.0).abs() > 1e-9
                    || dot(u, v).abs() > 1e-9
                {
                    return Err(ViewError::NotOrthonormal);
                }
                (u, v)
            }
        };
        bounded(self.pan[0], "pan")?;
        bounded(self.pan[1], "pan")?;
        match self.zoom {
            Some(z) if !z.is_finite() => return Err(ViewError::NotFinite("zoom")),
            Some(z) if z <= 0.0 => return Err(ViewError::BadZoom(z)),
            _ => {}
        }
        if let Some(cue) = &self.cue {
            if !cue.k.is_finite() || !(0.0..=MAX_CUE_K).contains(&cue.k) {
                return Err(ViewError::BadExtinction(cue.k));
            }
            match cue.direction {
                CueDirection::View => {}
                CueDirection::Angles { alpha, beta } => {
                    bounded(alpha, "cue angle")?;
                    bounded(beta, "cue angle")?;
                }
                CueDirection::Vector(w) => {
                    finite3(w, "cue direction")?;
                    let n = dot(w, w).sqrt();
                    if n == 0.0 || !n.is_finite() {
                        return Err(ViewError::ZeroCueDirection);
                    }
                }
            }
        }
        Ok((u, v))
    }
}

fn bounded(x: f64, what: &'static str) -> Result<(), ViewError> {
    if !x.is_finite() {
        Err(ViewError::NotFinite(what))
    } else if x.abs() > MAX_ABS_PARAM {
        Err(ViewError::OutOfRange { what, value: x })
    } else {
        Ok(())
    }
}

impl Camera {
    /// Resolves `view` for a volume of `geometry` (its dimensions and voxel spacing),
    /// validating every parameter.
    pub fn new(view: &View, geometry: &Geometry) -> Result<Camera, ViewError> {
        let (u, v) = view.basis()?;
        let dims = geometry.dims;
        let spacing = geometry.spacing_f64();
        if spacing.iter().any(|s| !(s.is_finite() && *s > 0.0)) {
            return Err(ViewError::NotFinite("spacing"));
        }
        let widest = spacing.iter().fold(0.0f64, |m, s| m.max(*s));
        // The library's default fits the volume's bounding sphere: every view of it, at any
        // angle, on screen at one scale. The commands fit tighter ([`Camera::fitting_zoom`]).
        let radius = (0.5
            * (0..3)
                .map(|a| (dims[a] as f64 * spacing[a]).powi(2))
                .sum::<f64>()
                .sqrt())
        .max(0.5 * widest);
        let zoom = match view.zoom {
            Some(z) => z,
            None => view.width.min(view.height) as f64 / (2.0 * radius),
        };
        if !(zoom.is_finite() && zoom > 0.0) || zoom * widest > MAX_ZOOM {
            return Err(ViewError::BadZoom(zoom));
        }
        let center = [
            0.5 * (dims[0] as f64 - 1.0),
            0.5 * (dims[1] as f64 - 1.0),
            0.5 * (dims[2] as f64 - 1.0),
        ];
        Ok(Camera {
            u,
            v,
            n: cross(u, v),
            width: view.width,
            height: view.height,
            zoom,
            pan: view.pan,
            center,
            spacing,
        })
    }

    /// The zoom that fits the ellipsoid inscribed in the volume's box, as this camera projects
    /// it, into its image, plus the reach of the splines (two voxels): an axis view shows the
    /// whole box filling the shorter side; an oblique one shows what a head or a body in the
    /// box occupies, the box's empty corners possibly off screen. What `render` and `view` use
    /// when no zoom is given (the bounding sphere left a head at a third of the image).
    pub fn fitting_zoom(&self, geometry: &Geometry) -> f64 {
        let dims = geometry.dims;
        let widest = self.spacing.iter().fold(0.0f64, |m, s| m.max(*s));
        let half_extent = |w: [f64; 3]| {
            0.5 * (0..3)
                .map(|a| (w[a] * dims[a] as f64 * self.spacing[a]).powi(2))
                .sum::<f64>()
                .sqrt()
                + 2.0 * widest
        };
        (self.width as f64 / (2.0 * half_extent(self.u)))
            .min(self.height as f64 / (2.0 * half_extent(self.v)))
    }

    /// Screen axis directions in physical space: (e_x, e_y) = (u, −v).
    pub fn screen_axes(&self) -> ([f64; 3], [f64; 3]) {
        (self.u, [-self.v[0], -self.v[1], -self.v[2]])
    }

    /// Screen axes per voxel step, (S·u, −S·v): a unit step along index axis a moves a point
    /// by zoom·(S·u)_a pixels right and zoom·(−S·v)_a pixels down. Equal to
    /// [`Camera::screen_axes`] for unit spacing.
    pub fn index_axes(&self) -> ([f64; 3], [f64; 3]) {
        let s = self.spacing;
        (
            [s[0] * self.u[0], s[1] * self.u[1], s[2] * self.u[2]],
            [-s[0] * self.v[0], -s[1] * self.v[1], -s[2] * self.v[2]],
        )
    }

    /// The ray direction in voxel indices per unit of physical length, S⁻¹·n: a ray p + t·ray()
    /// through index point p has travelled t units of spacing (mm) at parameter t.
    pub fn ray(&self) -> [f64; 3] {
        let s = self.spacing;
        [self.n[0] / s[0], self.n[1] / s[1], self.n[2] / s[2]]
    }

    /// Physical volume of one voxel, det S (the factor by which a footprint's integral grows
    /// over that of the same coefficients on unit voxels).
    pub fn voxel_volume(&self) -> f64 {
        self.spacing.iter().product()
    }

    /// Physical offset S(x − c) of a voxel index point from the volume centre.
    fn physical(&self, x: [f64; 3]) -> [f64; 3] {
        [
            self.spacing[0] * (x[0] - self.center[0]),
            self.spacing[1] * (x[1] - self.center[1]),
            self.spacing[2] * (x[2] - self.center[2]),
        ]
    }

    /// Continuous screen coordinates (X, Y) of a volume point (voxel indices).
    pub fn to_screen(&self, x: [f64; 3]) -> [f64; 2] {
        let d = self.physical(x);
        [
            0.5 * self.width as f64 + self.zoom * (dot(d, self.u) - self.pan[0]),
            0.5 * self.height as f64 - self.zoom * (dot(d, self.v) - self.pan[1]),
        ]
    }

    /// The volume point (voxel indices) on the plane through the volume centre seen at screen
    /// point (X, Y).
    pub fn from_screen(&self, xs: f64, ys: f64) -> [f64; 3] {
        let a = (xs - 0.5 * self.width as f64) / self.zoom + self.pan[0];
        let b = self.pan[1] - (ys - 0.5 * self.height as f64) / self.zoom;
        [
            self.center[0] + (a * self.u[0] + b * self.v[0]) / self.spacing[0],
            self.center[1] + (a * self.u[1] + b * self.v[1]) / self.spacing[1],
            self.center[2] + (a * self.u[2] + b * self.v[2]) / self.spacing[2],
        ]
    }
}

/// Clips the ray p + t·n to the box [lo, hi] (per axis): the parameter interval (t0, t1) inside
/// it, or `None` when the ray misses it.
pub fn clip_ray(p: [f64; 3], n: [f64; 3], lo: [f64; 3], hi: [f64; 3]) -> Option<(f64, f64)> {
    let mut t0 = f64::NEG_INFINITY;
    let mut t1 = f64::INFINITY;
    for a in 0..3 {
        if n[a].abs() < 1e-300 {
            if p[a] < lo[a] || p[a] > hi[a] {
                return None;
            }
        } else {
            let ta = (lo[a] - p[a]) / n[a];
            let tb = (hi[a] - p[a]) / n[a];
            t0 = t0.max(ta.min(tb));
            t1 = t1.min(ta.max(tb));
        }
    }
    (t1 > t0).then_some((t0, t1))
}

impl Camera {
    /// Physical length of the ray through screen point (X, Y) inside the voxel box
    /// [−½, n − ½]³ of a volume of dimensions `dims` (what a constant added to every voxel
    /// contributes to the pixel, e.g. a colour transform's mean).
    pub fn chord(&self, dims: [usize; 3], xs: f64, ys: f64) -> f64 {
        self.clip_to_voxels(dims, xs, ys)
            .map_or(0.0, |(_, t0, t1)| t1 - t0)
    }

    /// The ray through screen point (X, Y): its origin and the parameter interval (physical
    /// length along [`Camera::ray`]) inside the voxel box [−½, n − ½]³, or `None` when it
    /// misses the box.
    fn clip_to_voxels(&self, dims: [usize; 3], xs: f64, ys: f64) -> Option<([f64; 3], f64, f64)> {
        let lo = [-0.5; 3];
        let hi = dims.map(|n| n as f64 - 0.5);
        let p = self.from_screen(xs, ys);
        clip_ray(p, self.ray(), lo, hi).map(|(t0, t1)| (p, t0, t1))
    }

    /// What a constant of 1 added to every voxel of a volume of order-`order` splines
    /// contributes to the ray through screen point (X, Y): the line integral, weighted by the
    /// cue when there is one, of Π_a s_a(x_a), where s_a sums the centred B-splines of the
    /// axis's voxels ([`constant_profile`]). Haar's profile is the voxel box, so this is
    /// [`Camera::chord`] (or [`Camera::cued_chord`]) there. A spline's profile falls from 1 to
    /// 0 over order/2 voxels beyond the outer voxels' centres: measured on the voxel box
    /// instead, a constant (an offset, a colour transform's mean) drew a frame of the wrong
    /// sign around the volume's silhouette.
    ///
    /// The integrand is a polynomial between the ray's crossings of the profiles' knots
    /// (integers within order/2 of a face), of degree ≤ 3·(order − 1): 5-point Gauss–Legendre
    /// is exact on each such piece without a cue; with one, pieces are cut to at most half a
    /// unit of the cue's exponent. Where every profile is 1 the closed form is used.
    pub fn spline_chord(
        &self,
        dims: [usize; 3],
        order: usize,
        xs: f64,
        ys: f64,
        cue: Option<&ResolvedCue>,
    ) -> f64 {
        if !(2..=8).contains(&order) {
            return match cue {
                Some(c) => self.cued_chord(dims, xs, ys, c),
                None => self.chord(dims, xs, ys),
            };
        }
        let h = 0.5 * order as f64;
        let lo = [-h; 3];
        let hi = dims.map(|n| n as f64 - 1.0 + h);
        let p = self.from_screen(xs, ys);
        let r = self.ray();
        let Some((t0, t1)) = clip_ray(p, r, lo, hi) else {
            return 0.0;
        };
        if cue.is_none() && single_face_shells(p, r, dims, h, (t0, t1)) {
            // Each end crosses one face's ramp alone: a profile integrates over its ramp
            // [−h, h − 1] to h − ½, what the voxel box's [−½, h − 1] measures.
            return self.chord(dims, xs, ys);
        }
        // At most 2 ends and 2·order knots per axis (a stack array: this runs for every pixel).
        let mut cuts = [0.0f64; 2 + 3 * 2 * 8];
        let mut count = 2;
        cuts[0] = t0;
        cuts[1] = t1;
        for a in 0..3 {
            if r[a].abs() < 1e-300 {
                continue;
            }
            let n = dims[a] as f64;
            // Integer knots where the profile is not 1: [−h, h − 1] and [n − h, n − 1 + h].
            let low = (-h as i64)..=(h as i64 - 1);
            let high = ((n - h) as i64)..=((n - 1.0 + h) as i64);
            for q in low.chain(high) {
                let t = (q as f64 - p[a]) / r[a];
                if t > t0 && t < t1 && count < cuts.len() {
                    cuts[count] = t;
                    count += 1;
                }
            }
        }
        let cuts = &mut cuts[..count];
        cuts.sort_unstable_by(f64::total_cmp);
        let at = |t: f64| [p[0] + t * r[0], p[1] + t * r[1], p[2] + t * r[2]];
        let exponent = |x: [f64; 3]| cue.map_or(0.0, |c| c.k * c.dist(x).max(0.0));
        let inner = |x: [f64; 3]| {
            (0..3).all(|a| {
                let (lo, hi) = core_slab(h, dims[a]);
                (lo..=hi).contains(&x[a])
            })
        };
        let mut total = 0.0;
        for w in cuts.windows(2) {
            let (ta, tb) = (w[0], w[1]);
            let len = tb - ta;
            if len <= 0.0 {
                continue;
            }
            let (ea, eb) = (exponent(at(ta)), exponent(at(tb)));
            if inner(at(0.5 * (ta + tb))) {
                total += exp_segment(len, ea, eb);
                continue;
            }
            let pieces = ((eb - ea).abs() / 0.5).ceil().clamp(1.0, 256.0) as usize;
            let step = len / pieces as f64;
            for i in 0..pieces {
                let mid = ta + (i as f64 + 0.5) * step;
                for (node, weight) in GAUSS_LEGENDRE_5 {
                    let x = at(mid + 0.5 * step * node);
                    total += 0.5 * step * weight * profiles(order, dims, x) * (-exponent(x)).exp();
                }
            }
        }
        total
    }

    /// The depth-cued counterpart of [`Camera::chord`]: ∫ e^(−k·dist) along the ray's path
    /// through the voxel box, in closed form (the box lies behind every light-facing face, so
    /// the weight there is the plain exponential of a distance linear along the ray). It is
    /// what a constant added to every voxel contributes to a depth-cued pixel.
    pub fn cued_chord(&self, dims: [usize; 3], xs: f64, ys: f64, cue: &ResolvedCue) -> f64 {
        let Some((p, t0, t1)) = self.clip_to_voxels(dims, xs, ys) else {
            return 0.0;
        };
        let r = self.ray();
        let at = |t: f64| [p[0] + t * r[0], p[1] + t * r[1], p[2] + t * r[2]];
        // Exponents at both ends (dist ≥ 0 inside the box; clamp rounding).
        let a = cue.k * cue.dist(at(t0)).max(0.0);
        let b = cue.k * cue.dist(at(t1)).max(0.0);
        exp_segment(t1 - t0, a, b)
    }
}

/// Whether the ray p + t·r, inside the spline's outer box over (t0, t1), meets the ramps of
/// one axis at a time at each end: it passes through the core box, where every profile is 1
/// (per axis the slab [h − 1, n − h]), at most one axis enters its slab after t0, and at most
/// one leaves it before t1.
fn single_face_shells(p: [f64; 3], r: [f64; 3], dims: [usize; 3], h: f64, t: (f64, f64)) -> bool {
    const EPS: f64 = 1e-9;
    let (mut late, mut early) = (0, 0);
    let (mut core_in, mut core_out) = (f64::NEG_INFINITY, f64::INFINITY);
    for a in 0..3 {
        let (lo, hi) = core_slab(h, dims[a]);
        if lo > hi {
            return false;
        }
        if r[a].abs() < 1e-300 {
            if p[a] < lo || p[a] > hi {
                return false;
            }
            continue;
        }
        let (ta, tb) = ((lo - p[a]) / r[a], (hi - p[a]) / r[a]);
        let (enter, leave) = (ta.min(tb), ta.max(tb));
        core_in = core_in.max(enter);
        core_out = core_out.min(leave);
        late += usize::from(enter > t.0 + EPS);
        early += usize::from(leave < t.1 - EPS);
    }
    core_in < core_out && late <= 1 && early <= 1
}

/// Where along an axis of `n` voxels the profile of half-support `h` is 1: [h − 1, n − h]
/// (empty when the axis is shorter than the ramps).
fn core_slab(h: f64, n: usize) -> (f64, f64) {
    (h - 1.0, n as f64 - h)
}

/// ∫ e^(−e(t)) over a segment of length `len` along which the exponent e runs linearly from
/// `a` to `b`: len·(e^−a − e^−b)/(b − a) = len·e^−a·(1 − e^−d)/d, with −expm1 for small d.
fn exp_segment(len: f64, a: f64, b: f64) -> f64 {
    let d = b - a;
    if d.abs() < 1e-12 {
        len * (-a).exp()
    } else {
        len * (-a).exp() * (-(-d).exp_m1()) / d
    }
}

/// Nodes on [−1, 1] and weights of 5-point Gauss–Legendre quadrature (exact to degree 9).
const GAUSS_LEGENDRE_5: [(f64, f64); 5] = [
    (0.0, 0.568_888_888_888_888_9),
    (-0.538_469_310_105_683_1, 0.478_628_670_499_366_5),
    (0.538_469_310_105_683_1, 0.478_628_670_499_366_5),
    (-0.906_179_845_938_664, 0.236_926_885_056_189_1),
    (0.906_179_845_938_664, 0.236_926_885_056_189_1),
];

/// The sum at `x` of the order-`order` centred B-splines of the `n` voxels 0..n of an axis:
/// the profile along that axis of a constant of 1 in every voxel (the voxel box for Haar; for
/// the splines 1 between the voxels order/2 − 1 from either end, falling to 0 over order/2
/// voxels beyond the outer voxels' centres).
pub fn constant_profile(order: usize, n: usize, x: f64) -> f64 {
    let h = 0.5 * order as f64;
    if n == 0 || x <= -h || x >= n as f64 - 1.0 + h {
        return 0.0;
    }
    let first = (x - h).floor().max(0.0) as usize;
    let last = ((x + h).ceil() as usize).min(n - 1);
    (first..=last)
        .map(|k| centred_bspline(order, x - k as f64))
        .sum()
}

/// The product of the three axes' [`constant_profile`]s at `x`: a constant of 1 in every
/// voxel of a spline volume, evaluated there.
fn profiles(order: usize, dims: [usize; 3], x: [f64; 3]) -> f64 {
    (0..3)
        .map(|a| constant_profile(order, dims[a], x[a]))
        .product()
}

/// The centred cardinal B-spline of `order` at `x` (closed forms for the orders the families
/// use, the recursion otherwise).
fn centred_bspline(order: usize, x: f64) -> f64 {
    let a = x.abs();
    match order {
        1 => f64::from(u8::from((-0.5..0.5).contains(&x))),
        2 => (1.0 - a).max(0.0),
        4 if a < 1.0 => 2.0 / 3.0 - a * a + 0.5 * a * a * a,
        4 if a < 2.0 => (2.0 - a).powi(3) / 6.0,
        4 => 0.0,
        _ => crate::family::bspline(order, x + 0.5 * order as f64),
    }
}

/// What a client looks at: a view, alone or as the first of the three multiview images.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ViewSpec {
    /// The (first) view.
    pub view: View,
    /// Whether the three multiview images are rendered.
    pub multiview: bool,
}

impl ViewSpec {
    /// A single view.
    pub fn single(view: View) -> ViewSpec {
        ViewSpec {
            view,
            multiview: false,
        }
    }

    /// Validates the view ([`View::validate`]); depth cueing is not defined for multiview.
    pub fn validate(&self) -> Result<(), ViewError> {
        self.view.validate()?;
        if self.multiview && self.view.cue.is_some() {
            return Err(ViewError::CueWithMultiview);
        }
        Ok(())
    }

    /// The cameras of the spec for a volume of `geometry`: one, or the three multiview
    /// cameras.
    pub fn cameras(&self, geometry: &Geometry) -> Result<Vec<Camera>, ViewError> {
        self.validate()?;
        if self.multiview {
            Ok(multiview_cameras(&self.view, geometry)?.to_vec())
        } else {
            Ok(vec![Camera::new(&self.view, geometry)?])
        }
    }
}

/// Multiview (§3.1): for view k (0, 1, 2) and type t, the view-1 type whose footprint to use
/// and its sign. View 2 has screen axes (u₂, v₂) = (R₂u, R₂v) with R₂(x, y, z) = (−y, x, z),
/// view 3 uses R₃(x, y, z) = (z, y, −x). The view-k footprint of a type-t basis b_t is the
/// view-1 footprint of b_t∘R_k: the basis of the type t' with the per-axis factors permuted
/// (view 2 swaps x and y, view 3 swaps x and z) and, since one factor is reflected (view 2: the
/// x factor, view 3: the z factor), negated when that factor is ψ and ψ is odd about its centre
/// (`Family::psi_is_odd`: Haar only; linear and cubic ψ are even). The paper's Table 1 is the
/// same rule with the inverse rotation.
pub fn multiview_map(view: usize, kind: u8, psi_is_odd: bool) -> (u8, f32) {
    let bx = (kind >> 2) & 1;
    let by = (kind >> 1) & 1;
    let bz = kind & 1;
    match view {
        1 => {
            // b(R₂x) = β_x(−y) β_y(x) β_z(z): x factor ← β_y, y factor ← reflected β_x.
            let t = (by << 2) | (bx << 1) | bz;
            let neg = psi_is_odd && bx == 1;
            (t, if neg { -1.0 } else { 1.0 })
        }
        2 => {
            // b(R₃x) = β_x(z) β_y(y) β_z(−x): x factor ← reflected β_z, z factor ← β_x.
            let t = (bz << 2) | (by << 1) | bx;
            let neg = psi_is_odd && bz == 1;
            (t, if neg { -1.0 } else { 1.0 })
        }
        _ => (kind, 1.0),
    }
}

/// The three multiview cameras (u₁, v₁), (R₂u₁, R₂v₁), (R₃u₁, R₃v₁) for `view` (all with the
/// first camera's zoom).
pub fn multiview_cameras(view: &View, geometry: &Geometry) -> Result<[Camera; 3], ViewError> {
    let c1 = Camera::new(view, geometry)?;
    let (u, v) = (c1.u, c1.v);
    let r2 = |w: [f64; 3]| [-w[1], w[0], w[2]];
    let r3 = |w: [f64; 3]| [w[2], w[1], -w[0]];
    let mk = |u: [f64; 3], v: [f64; 3]| -> Result<Camera, ViewError> {
        let mut vw = *view;
        vw.orientation = Orientation::Basis { u, v };
        vw.zoom = Some(c1.zoom);
        Camera::new(&vw, geometry)
    };
    Ok([c1, mk(r2(u), r2(v))?, mk(r3(u), r3(v))?])
}

/// sin(πx)/(πx), exact at 0: the transform of a unit box, i.e. of a pixel's area.
pub fn sinc(x: f64) -> f64 {
    if x.abs() < 1e-5 {
        let y = std::f64::consts::PI * x;
        1.0 - y * y / 6.0
    } else {
        (std::f64::consts::PI * x).sin() / (std::f64::consts::PI * x)
    }
}

/// A resolved depth cue: the light's distance gradient `l` in voxel indices (S·l̂ for the unit
/// physical light direction l̂ and spacing S, so that l·x is a physical distance; l̂ itself for
/// unit spacing), and per axis the data's light-facing face `planes[a]` (the low face −j/2 when
/// l_a ≥ 0, the high face (n_a − 1) + j/2 when l_a < 0, in voxel indices: j/2 beyond the outer
/// voxel centres, where the order-j spline of the data ends). The attenuating medium is the
/// data: a point behind every light-facing face has the weight e^(−k·dist(x)),
/// dist(x) = l·x − d0 ≥ 0 with d0 = l·planes (1 at the front corner);
/// a point in front of a face has weight 0 — the volume is zero there, but the basis functions
/// of a periodic spline transform reach into that margin and only cancel to zero, and an
/// exponential cue would amplify their residue by e^(+k·distance).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ResolvedCue {
    /// Extinction per unit of spacing.
    pub k: f64,
    /// Distance gradient in voxel indices, S·l̂ (unit for unit spacing).
    pub l: [f64; 3],
    /// Plane offset l·planes.
    pub d0: f64,
    /// Light-facing face per axis (no face where l_a = 0).
    pub planes: [f64; 3],
}

impl ResolvedCue {
    /// Physical distance of `x` (voxel indices) from the light plane through the front corner.
    pub fn dist(&self, x: [f64; 3]) -> f64 {
        dot(self.l, x) - self.d0
    }

    /// Whether `x` lies in front of some light-facing face (outside the medium).
    pub fn in_front(&self, x: [f64; 3]) -> bool {
        (0..3).any(|a| {
            (self.l[a] > 0.0 && x[a] < self.planes[a]) || (self.l[a] < 0.0 && x[a] > self.planes[a])
        })
    }

    /// The cue weight of a point: 0 in front of the data, e^(−k·dist) behind.
    pub fn weight(&self, x: [f64; 3]) -> f64 {
        if self.in_front(x) {
            0.0
        } else {
            (-self.k * self.dist(x).max(0.0)).exp()
        }
    }

    /// Where a 1D support [lo, hi] along axis `a` lies relative to the light-facing face.
    pub fn side(&self, a: usize, lo: f64, hi: f64) -> CueSide {
        let p = self.planes[a];
        if self.l[a] > 0.0 {
            if hi <= p {
                CueSide::Front
            } else if lo >= p {
                CueSide::Behind
            } else {
                CueSide::Straddle
            }
        } else if self.l[a] < 0.0 {
            if lo >= p {
                CueSide::Front
            } else if hi <= p {
                CueSide::Behind
            } else {
                CueSide::Straddle
            }
        } else {
            CueSide::Behind
        }
    }
}

/// Position of a support along one axis relative to that axis' light-facing face.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CueSide {
    /// Wholly in front of the face: weight 0.
    Front,
    /// Wholly behind it (or the light is perpendicular to the axis): exponential weight.
    Behind,
    /// Across the face.
    Straddle,
}

/// Resolves a cue for a camera (whose view direction L may be, and whose spacing scales the
/// distances) and geometry: the light-facing faces of the data and the distance offset (see
/// [`ResolvedCue`]). The light direction is physical.
pub fn resolve_cue(
    cue: &Cue,
    camera: &Camera,
    geometry: &crate::layout::Geometry,
) -> Result<ResolvedCue, ViewError> {
    if !cue.k.is_finite() || !(0.0..=MAX_CUE_K).contains(&cue.k) {
        return Err(ViewError::BadExtinction(cue.k));
    }
    let l = match cue.direction {
        CueDirection::View => camera.n,
        CueDirection::Angles { alpha, beta } => {
            if !alpha.is_finite() || !beta.is_finite() {
                return Err(ViewError::NotFinite("cue angle"));
            }
            let (sa, ca) = alpha.sin_cos();
            let (sb, cb) = beta.sin_cos();
            [-ca * cb, sa * cb, sb]
        }
        CueDirection::Vector(w) => {
            finite3(w, "cue direction")?;
            w
        }
    };
    let norm = dot(l, l).sqrt();
    if norm == 0.0 || !norm.is_finite() {
        return Err(ViewError::ZeroCueDirection);
    }
    let s = camera.spacing;
    let l = [s[0] * l[0] / norm, s[1] * l[1] / norm, s[2] * l[2] / norm];
    let half = 0.5 * geometry.family.order() as f64;
    let mut planes = [0.0; 3];
    for a in 0..3 {
        planes[a] = if l[a] >= 0.0 {
            -half
        } else {
            geometry.dims[a] as f64 - 1.0 + half
        };
    }
    Ok(ResolvedCue {
        k: cue.k,
        l,
        d0: dot(l, planes),
        planes,
    })
}

#[cfg(test)]
mod readable_tests {
    use super::*;

    #[test]
    fn huge_and_tiny_values_are_written_with_an_exponent() {
        assert_eq!(Readable(1e300).to_string(), "1e300");
        assert_eq!(Readable(-2.5e-9).to_string(), "-2.5e-9");
        assert_eq!(Readable(0.66).to_string(), "0.66");
        assert_eq!(Readable(0.0).to_string(), "0");
        let e = bounded(1e300, "alpha").unwrap_err().to_string();
        assert!(e.len() < 80 && e.contains("1e300"), "{e}");
    }
}

#[cfg(test)]
mod fitting_tests {
    use super::*;
    use crate::family::Family;

    #[test]
    fn the_fitting_zoom_fills_an_axis_view_and_is_tighter_than_the_sphere() {
        let g = crate::layout::Geometry::new([40, 60, 20], Family::Linear, 2, 0).unwrap();
        let axis = Camera::new(&View::new(0.0, 0.0, 256, 128), &g).unwrap();
        let fit = axis.fitting_zoom(&g);
        // The axis view's screen axes are two of the volume's: the box (+2 voxels per side)
        // fills one image side exactly and fits the other.
        let (ex, ey) = axis.screen_axes();
        let extent = |e: [f64; 3]| (0..3).map(|a| e[a].abs() * g.dims[a] as f64).sum::<f64>();
        let (w, h) = (extent(ex) + 4.0, extent(ey) + 4.0);
        let expected = (256.0 / w).min(128.0 / h);
        assert!(
            (fit - expected).abs() < 1e-9 * expected,
            "{fit} vs {expected}"
        );
        assert!(
            fit > axis.zoom,
            "tighter than the bounding sphere's {}",
            axis.zoom
        );
        // Oblique views fit at least as tightly as the sphere, and every fit is finite.
        for (a, b) in [
            (0.66, 0.91),
            (1.0, -0.3),
            (0.0, std::f64::consts::FRAC_PI_2),
        ] {
            let c = Camera::new(&View::new(a, b, 64, 64), &g).unwrap();
            let z = c.fitting_zoom(&g);
            assert!(z.is_finite() && z >= c.zoom, "({a}, {b}): {z} < {}", c.zoom);
        }
        let voxel = crate::layout::Geometry::new([1, 1, 1], Family::Haar, 0, 0).unwrap();
        let c = Camera::new(&View::new(0.3, 0.2, 32, 32), &voxel).unwrap();
        assert!(c.fitting_zoom(&voxel).is_finite());
    }
}

#[cfg(test)]
mod spline_chord_tests {
    use super::*;
    use crate::family::Family;

    /// The profiles against the B-spline recursion summed over the voxels, and their integral
    /// (n: each B-spline integrates to 1), for 1, 2, 3 and 9 voxels.
    #[test]
    fn constant_profiles_sum_the_voxels_b_splines() {
        for order in [1, 2, 4] {
            let h = 0.5 * order as f64;
            for n in [1usize, 2, 3, 9] {
                let mut integral = 0.0;
                let steps = 40_000;
                let (a, b) = (-h - 1.0, n as f64 + h);
                let dx = (b - a) / steps as f64;
                for i in 0..steps {
                    let x = a + (i as f64 + 0.5) * dx;
                    let want: f64 = (0..n)
                        .map(|k| crate::family::bspline(order, x - k as f64 + h))
                        .sum();
                    let got = constant_profile(order, n, x);
                    assert!((got - want).abs() < 1e-12, "order {order} n {n} x {x}");
                    integral += got * dx;
                }
                assert!(
                    (integral - n as f64).abs() < 1e-3,
                    "order {order} n {n}: {integral}"
                );
            }
        }
    }

    /// The chord of rays across the image against a 5 000-step midpoint sum of the profiles' product
    /// along the ray (weighted by the cue), for both spline orders; on, near and off the axes;
    /// with no cue, a gentle one and a stiff one; 1-voxel, thin and non-cubic boxes.
    #[test]
    fn spline_chords_are_the_line_integrals_of_the_profiles() {
        for (family, order) in [(Family::Linear, 2), (Family::Cubic, 4)] {
            for dims in [[1, 1, 1], [2, 7, 3], [9, 5, 6]] {
                let g = Geometry::new(dims, family, 0, 0).unwrap();
                for (a, b) in [(0.0, 0.0), (1e-6, 0.0), (0.66, 0.91), (2.5, -0.4)] {
                    let view = View::new(a, b, 12, 10);
                    let cam = Camera::new(&view, &g).unwrap();
                    for k in [None, Some(0.3), Some(6.0)] {
                        let cue = k.map(|k| {
                            let c = Cue {
                                k,
                                direction: CueDirection::View,
                            };
                            resolve_cue(&c, &cam, &g).unwrap()
                        });
                        // Every 0.9 of a pixel: rays through the core, grazing an edge, in a
                        // ramp only, and missing the volume.
                        let points = (0..14 * 12)
                            .map(|i| (0.3 + 0.9 * (i % 14) as f64, 0.2 + 0.9 * (i / 14) as f64));
                        for (xs, ys) in points {
                            let got = cam.spline_chord(dims, order, xs, ys, cue.as_ref());
                            let want = brute_force(&cam, dims, order, xs, ys, cue.as_ref());
                            assert!(
                                (got - want).abs() <= 1e-5 * want.abs().max(1.0),
                                "{family} {dims:?} ({a}, {b}) k {k:?} at ({xs}, {ys}): \
                                 {got} vs {want}"
                            );
                        }
                    }
                }
            }
        }
    }

    fn brute_force(
        cam: &Camera,
        dims: [usize; 3],
        order: usize,
        xs: f64,
        ys: f64,
        cue: Option<&ResolvedCue>,
    ) -> f64 {
        let h = 0.5 * order as f64;
        let p = cam.from_screen(xs, ys);
        let r = cam.ray();
        let lo = [-h; 3];
        let hi = dims.map(|n| n as f64 - 1.0 + h);
        let Some((t0, t1)) = clip_ray(p, r, lo, hi) else {
            return 0.0;
        };
        let steps = 5_000;
        let dt = (t1 - t0) / steps as f64;
        (0..steps)
            .map(|i| {
                let t = t0 + (i as f64 + 0.5) * dt;
                let x = [p[0] + t * r[0], p[1] + t * r[1], p[2] + t * r[2]];
                let w = cue.map_or(1.0, |c| (-c.k * c.dist(x).max(0.0)).exp());
                profiles(order, dims, x) * w * dt
            })
            .sum()
    }
}
