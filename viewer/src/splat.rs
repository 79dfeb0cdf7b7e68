//! Accumulation of wavelet splats (paper §2.3, §3): this module owns the [`Renderer`] — its
//! footprint planner/cache, the projection of each coefficient to the screen, the screen-tile
//! binning and the rayon-parallel accumulation — and the multiview (§3.1) type permutations.
//!
//! Each coefficient is projected to its basis centre on the screen, the (level, type) footprint
//! is placed at the nearest subpixel phase (see [`crate::footprint`]) and its pixel box is tested
//! against the image: splats wholly off screen are counted and cost nothing more. The others are
//! binned into 64×64 screen tiles; tiles are accumulated in parallel, each with its own f32
//! buffer, visiting its splats in input order, so the image is bit-identical for any number of
//! threads. With depth cueing each coefficient is also multiplied by the eq. 13 distance weight
//! e^(−k·dist(x_near)), x_near the corner of its support box nearest the light; coefficients
//! whose support crosses a light-facing face of the data are split there (see
//! `splat_view_cued`).
//!
//! **Multiview.** View 2 has screen axes (u₂, v₂) = (R₂u, R₂v) with R₂(x, y, z) = (−y, x, z), and
//! view 3 uses R₃(x, y, z) = (z, y, −x) (the paper's §3.1 formulas). The view-k footprint of a
//! type-t basis b_t is the view-1 footprint of b_t∘R_k, which is the basis of the type t' with
//! the per-axis factors permuted (view 2 swaps x and y, view 3 swaps x and z) and, since one
//! factor is reflected (view 2: the x factor, view 3: the z factor), negated when that factor is
//! ψ and ψ is odd about its centre (`Family::psi_is_odd`: Haar only; linear and cubic ψ are
//! even, so no negations). The paper's Table 1 is the same rule with the inverse rotation.

use crate::footprint::{AxisFactor, Footprint, FootprintParams, FootprintSet};
use crate::image::Image;
use crate::RenderError;
use rayon::prelude::*;
use std::sync::Arc;
use wavesplat_codec::dwt::unit_basis_line;
use wavesplat_codec::format::packet::Coefficient;
use wavesplat_codec::layout::Geometry;
use wavesplat_codec::view::{
    multiview_cameras, multiview_map, resolve_cue, Camera, CueSide, ResolvedCue, View,
};

/// Screen tile side (pixels).
pub const TILE: usize = 64;

/// Renderer settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RenderOptions {
    /// Channels of the output (coefficients must have `channel < channels`).
    pub channels: usize,
    /// Subpixel phases per axis (even; position error ≤ 1/(2S) pixel).
    pub subpixel: usize,
    /// Largest FFT side for a footprint (S is halved until the footprint fits).
    pub max_fft: usize,
    /// Footprint sets kept in the planner's cache.
    pub cache_size: usize,
}

impl Default for RenderOptions {
    fn default() -> Self {
        RenderOptions {
            channels: 1,
            subpixel: 8,
            max_fft: 768,
            cache_size: 8,
        }
    }
}

/// Counters of one rendering.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct RenderStats {
    /// Coefficients given.
    pub coefficients: usize,
    /// Splats accumulated (at least partly on screen), summed over views.
    pub splatted: usize,
    /// Splats skipped because their footprint misses the screen.
    pub skipped: usize,
    /// Pixel updates performed.
    pub pixel_updates: u64,
}

/// Checks that a coefficient addresses an existing band position and channel.
pub fn check_coefficient(
    c: &Coefficient,
    geometry: &Geometry,
    channels: usize,
) -> Result<(), RenderError> {
    if c.channel as usize >= channels {
        return Err(RenderError::Channel {
            channel: c.channel,
            channels,
        });
    }
    if geometry.band_index(c.band).is_none() {
        return Err(RenderError::Band(c.band));
    }
    let bd = geometry.band_dims(c.band);
    if (0..3).any(|a| c.pos[a] as usize >= bd[a]) {
        return Err(RenderError::Position {
            band: c.band,
            pos: c.pos,
        });
    }
    if !c.value.is_finite() {
        return Err(RenderError::NotFinite);
    }
    Ok(())
}

#[derive(Debug, Clone, Copy)]
struct Splat {
    table: u32,
    phase: u16,
    x0: i32,
    y0: i32,
    value: f32,
    channel: u8,
}

#[derive(Debug, Clone, PartialEq)]
struct CacheKey {
    params: [u64; 12],
}

fn key_of(p: &FootprintParams) -> CacheKey {
    let (k, l) = p.cue.unwrap_or((-1.0, [0.0; 3]));
    CacheKey {
        params: [
            p.family.code() as u64 | ((p.levels as u64) << 8) | ((p.subpixel as u64) << 16),
            p.ex[0].to_bits(),
            p.ex[1].to_bits(),
            p.ex[2].to_bits(),
            p.ey[0].to_bits(),
            p.ey[1].to_bits(),
            p.ey[2].to_bits(),
            p.zoom.to_bits() ^ (p.max_fft as u64).rotate_left(40),
            k.to_bits(),
            l[0].to_bits(),
            l[1].to_bits(),
            l[2].to_bits(),
        ],
    }
}

/// The CPU splat renderer with its footprint planner (footprints are cached per view, like
/// RustFFT's planner caches plans).
#[derive(Debug, Default)]
pub struct Renderer {
    options: RenderOptions,
    cache: Vec<(CacheKey, Arc<FootprintSet>)>,
}

impl Renderer {
    /// A renderer with the given options.
    pub fn new(options: RenderOptions) -> Renderer {
        Renderer {
            options,
            cache: Vec::new(),
        }
    }

    /// The options.
    pub fn options(&self) -> &RenderOptions {
        &self.options
    }

    fn params(
        &self,
        camera: &Camera,
        geometry: &Geometry,
        cue: Option<&ResolvedCue>,
    ) -> FootprintParams {
        let (ex, ey) = camera.screen_axes();
        FootprintParams {
            family: geometry.family,
            levels: geometry.levels,
            ex,
            ey,
            zoom: camera.zoom,
            subpixel: self.options.subpixel,
            max_fft: self.options.max_fft,
            cue: cue.map(|c| (c.k, c.l)),
        }
    }

    /// The footprint set for a view (from the cache or freshly planned).
    pub fn footprints(&mut self, p: &FootprintParams) -> Arc<FootprintSet> {
        let key = key_of(p);
        if let Some(i) = self.cache.iter().position(|(k, _)| *k == key) {
            let entry = self.cache.remove(i);
            let set = entry.1.clone();
            self.cache.push(entry);
            return set;
        }
        let set = Arc::new(FootprintSet::build(p));
        self.cache.push((key, set.clone()));
        while self.cache.len() > self.options.cache_size.max(1) {
            self.cache.remove(0);
        }
        set
    }

    /// Renders the coefficients for `view`.
    pub fn render(
        &mut self,
        coefficients: &[Coefficient],
        geometry: &Geometry,
        view: &View,
    ) -> Result<Image, RenderError> {
        Ok(self.render_with_stats(coefficients, geometry, view)?.0)
    }

    /// Renders and reports counters.
    pub fn render_with_stats(
        &mut self,
        coefficients: &[Coefficient],
        geometry: &Geometry,
        view: &View,
    ) -> Result<(Image, RenderStats), RenderError> {
        let camera = Camera::new(view, geometry.dims)?;
        let cue = match &view.cue {
            Some(c) => Some(resolve_cue(c, &camera, geometry)?),
            None => None,
        };
        self.render_camera(coefficients, geometry, &camera, cue)
    }

    /// Renders for a resolved camera (and cue).
    pub fn render_camera(
        &mut self,
        coefficients: &[Coefficient],
        geometry: &Geometry,
        camera: &Camera,
        cue: Option<ResolvedCue>,
    ) -> Result<(Image, RenderStats), RenderError> {
        let p = self.params(camera, geometry, cue.as_ref());
        let set = self.footprints(&p);
        let mut stats = RenderStats {
            coefficients: coefficients.len(),
            ..Default::default()
        };
        let img = splat_view(
            coefficients,
            geometry,
            camera,
            cue.as_ref(),
            &set,
            self.options.channels,
            0,
            &mut stats,
        )?;
        Ok((img, stats))
    }

    /// Three views side by side (width 3W) from one footprint set (§3.1). Depth cueing is not
    /// supported in multiview (the cue would rotate with each view).
    pub fn render_multiview(
        &mut self,
        coefficients: &[Coefficient],
        geometry: &Geometry,
        view: &View,
    ) -> Result<(Image, RenderStats), RenderError> {
        let views = self.render_multiview_views(coefficients, geometry, view)?;
        let mut stats = views.1;
        stats.coefficients = coefficients.len();
        Ok((Image::hconcat(&views.0), stats))
    }

    /// The three multiview images separately.
    pub fn render_multiview_views(
        &mut self,
        coefficients: &[Coefficient],
        geometry: &Geometry,
        view: &View,
    ) -> Result<(Vec<Image>, RenderStats), RenderError> {
        if view.cue.is_some() {
            return Err(RenderError::Unsupported("depth cueing with multiview"));
        }
        let cams = multiview_cameras(view, geometry.dims)?;
        let p = self.params(&cams[0], geometry, None);
        let set = self.footprints(&p);
        let mut stats = RenderStats {
            coefficients: coefficients.len(),
            ..Default::default()
        };
        let mut out = Vec::with_capacity(3);
        for (k, cam) in cams.iter().enumerate() {
            out.push(splat_view(
                coefficients,
                geometry,
                cam,
                None,
                &set,
                self.options.channels,
                k,
                &mut stats,
            )?);
        }
        Ok((out, stats))
    }
}

/// Projects, bins and accumulates one view. `mv` selects the multiview permutation (0 = none).
fn splat_view(
    coefficients: &[Coefficient],
    geometry: &Geometry,
    camera: &Camera,
    cue: Option<&ResolvedCue>,
    set: &FootprintSet,
    channels: usize,
    mv: usize,
    stats: &mut RenderStats,
) -> Result<Image, RenderError> {
    if let Some(cue) = cue {
        return splat_view_cued(coefficients, geometry, camera, cue, set, channels, stats);
    }
    let (w, h) = (camera.width as i64, camera.height as i64);
    let odd = geometry.family.psi_is_odd();
    // Project every coefficient (parallel, order preserved).
    let projected: Vec<Result<Option<Splat>, RenderError>> = coefficients
        .par_iter()
        .map(|c| {
            check_coefficient(c, geometry, channels)?;
            let level = c.band.level as usize;
            let (kind, sign) = multiview_map(mv, c.band.kind, odd);
            let table = level * 8 + kind as usize;
            let Some(fp) = set.tables.get(table).and_then(|t| t.as_ref()) else {
                return Err(RenderError::Band(c.band));
            };
            let pos = [c.pos[0] as usize, c.pos[1] as usize, c.pos[2] as usize];
            let centre = geometry.basis_center(c.band, pos);
            let scr = camera.to_screen(centre);
            let (a, x0) = Footprint::place(fp.s, fp.cx, scr[0]);
            let (b, y0) = Footprint::place(fp.s, fp.cy, scr[1]);
            let ph = &fp.phases[b * fp.s + a];
            if x0 >= w || y0 >= h || x0 + ph.cols as i64 <= 0 || y0 + ph.rows as i64 <= 0 {
                return Ok(None);
            }
            let value = c.value as f64 * sign as f64;
            Ok(Some(Splat {
                table: table as u32,
                phase: (b * fp.s + a) as u16,
                x0: x0 as i32,
                y0: y0 as i32,
                value: value as f32,
                channel: c.channel,
            }))
        })
        .collect();
    let mut splats = Vec::with_capacity(projected.len());
    for p in projected {
        match p? {
            Some(s) => splats.push(s),
            None => stats.skipped += 1,
        }
    }
    stats.splatted += splats.len();
    let tables: Vec<&Footprint> = set
        .tables
        .iter()
        .map(|t| t.as_ref().unwrap_or(&EMPTY))
        .collect();
    Ok(accumulate(&splats, &tables, camera, channels, stats))
}

static EMPTY: Footprint = Footprint {
    s: 0,
    cx: 0,
    cy: 0,
    phases: Vec::new(),
};

/// Bins splats into screen tiles and accumulates the tiles in parallel (each tile visits its
/// splats in input order, so the image does not depend on the thread count).
fn accumulate(
    splats: &[Splat],
    tables: &[&Footprint],
    camera: &Camera,
    channels: usize,
    stats: &mut RenderStats,
) -> Image {
    let (w, h) = (camera.width as i64, camera.height as i64);
    let tiles_x = camera.width.div_ceil(TILE);
    let tiles_y = camera.height.div_ceil(TILE);
    // Bin into tiles (in input order).
    let mut bins: Vec<Vec<u32>> = vec![Vec::new(); tiles_x * tiles_y];
    for (i, s) in splats.iter().enumerate() {
        let ph = &tables[s.table as usize].phases[s.phase as usize];
        let tx0 = (s.x0.max(0) as usize) / TILE;
        let ty0 = (s.y0.max(0) as usize) / TILE;
        let tx1 = (((s.x0 as i64 + ph.cols as i64 - 1).min(w - 1)) as usize) / TILE;
        let ty1 = (((s.y0 as i64 + ph.rows as i64 - 1).min(h - 1)) as usize) / TILE;
        for ty in ty0..=ty1 {
            for tx in tx0..=tx1 {
                bins[ty * tiles_x + tx].push(i as u32);
            }
        }
    }
    let width = camera.width;
    let height = camera.height;
    let results: Vec<(Vec<f32>, u64)> = bins
        .par_iter()
        .enumerate()
        .map(|(t, bin)| {
            let tx = (t % tiles_x) * TILE;
            let ty = (t / tiles_x) * TILE;
            let tw = TILE.min(width - tx);
            let th = TILE.min(height - ty);
            let mut buf = vec![0.0f32; tw * th * channels];
            let mut updates = 0u64;
            for &i in bin {
                let s = &splats[i as usize];
                let ph = &tables[s.table as usize].phases[s.phase as usize];
                let xa = (s.x0 as i64).max(tx as i64);
                let xb = (s.x0 as i64 + ph.cols as i64).min((tx + tw) as i64);
                let ya = (s.y0 as i64).max(ty as i64);
                let yb = (s.y0 as i64 + ph.rows as i64).min((ty + th) as i64);
                if xa >= xb || ya >= yb {
                    continue;
                }
                let n = (xb - xa) as usize;
                let ch = s.channel as usize;
                for y in ya..yb {
                    let src = (y - s.y0 as i64) as usize * ph.cols + (xa - s.x0 as i64) as usize;
                    let dst = ((y as usize - ty) * tw + (xa as usize - tx)) * channels + ch;
                    let srow = &ph.data[src..src + n];
                    if channels == 1 {
                        for (d, v) in buf[dst..dst + n].iter_mut().zip(srow) {
                            *d += s.value * v;
                        }
                    } else {
                        for (k, v) in srow.iter().enumerate() {
                            buf[dst + k * channels] += s.value * v;
                        }
                    }
                }
                updates += (n * (yb - ya) as usize) as u64;
            }
            (buf, updates)
        })
        .collect();
    let mut image = Image::new(width, height, channels);
    for (t, (buf, updates)) in results.into_iter().enumerate() {
        stats.pixel_updates += updates;
        let tx = (t % tiles_x) * TILE;
        let ty = (t / tiles_x) * TILE;
        let tw = TILE.min(width - tx);
        let th = TILE.min(height - ty);
        for y in 0..th {
            let dst = ((ty + y) * width + tx) * channels;
            image.data[dst..dst + tw * channels]
                .copy_from_slice(&buf[y * tw * channels..(y + 1) * tw * channels]);
        }
    }
    image
}

/// Level-0 expansion of the level-`level` φ (or ψ) with index 0: the B-spline coefficients
/// a_l with b = Σ a_l φ₀(· − l), as (offset of φ₀'s centre from b's centre, a_l) — the
/// synthesis filters applied `level` times to a unit coefficient (no wrap: the line is longer
/// than the support).
fn level0_expansion(geometry: &Geometry, level: usize, wavelet: bool) -> Vec<(f64, f64)> {
    if level == 0 {
        return vec![(0.0, 1.0)];
    }
    let len = (4 * geometry.family.order()) << level;
    let line = unit_basis_line(geometry.family, len, level, wavelet, false);
    let centre = geometry.raw_center_1d(level, 0, wavelet);
    line.iter()
        .enumerate()
        .filter(|(_, v)| **v != 0.0)
        .map(|(i, v)| (i as f64 - centre, *v))
        .collect()
}

/// One cued splat before placement: factor triple, centre in volume coordinates, weighted
/// value, channel.
struct CuedSplat {
    factors: [AxisFactor; 3],
    centre: [f64; 3],
    value: f64,
    channel: u8,
}

/// Depth-cued projection and accumulation. The cue weight is cut at the data's light-facing
/// faces (see [`ResolvedCue`]), which makes it a product of per-axis factors: along each axis a
/// basis factor lies behind its face (exponential, cued from its near end), in front of it
/// (weight 0: no splat) or across it. A coefficient with no factor across a face is one splat
/// with the matching table. One whose support crosses a face along some axes is split there
/// into level-0 B-splines (its exact refinement, `level0_expansion`): those wholly behind are
/// ordinary cued factors, those in front are dropped, and the few across the face (one for
/// linear, three for cubic, none for Haar) have their own transform
/// ([`crate::footprint::StraddleFactor`]). Each splat carries the weight e^(−k·dist) of its
/// support's near corner (the face itself for a straddling factor), so no exponent is
/// positive.
fn splat_view_cued(
    coefficients: &[Coefficient],
    geometry: &Geometry,
    camera: &Camera,
    cue: &ResolvedCue,
    set: &FootprintSet,
    channels: usize,
    stats: &mut RenderStats,
) -> Result<Image, RenderError> {
    let (w, h) = (camera.width as i64, camera.height as i64);
    let family = geometry.family;
    let half0 = 0.5 * family.phi_support();
    let expansions: Vec<[Vec<(f64, f64)>; 2]> = (0..=geometry.levels)
        .map(|l| {
            [
                level0_expansion(geometry, l, false),
                level0_expansion(geometry, l, true),
            ]
        })
        .collect();
    let near_of = |a: usize, lo: f64, hi: f64| if cue.l[a] >= 0.0 { lo } else { hi };
    let weight_of = |near: [f64; 3]| (-cue.k * cue.dist(near).max(0.0)).exp();
    let projected: Vec<Result<Vec<CuedSplat>, RenderError>> = coefficients
        .par_iter()
        .map(|c| {
            check_coefficient(c, geometry, channels)?;
            let level = c.band.level as usize;
            let centre = geometry.basis_center(
                c.band,
                [c.pos[0] as usize, c.pos[1] as usize, c.pos[2] as usize],
            );
            // Per axis: the choices of (factor, centre, coefficient, near point).
            let mut choices: [Vec<(AxisFactor, f64, f64, f64)>; 3] = Default::default();
            for a in 0..3 {
                let wavelet = c.band.is_wavelet_along(a);
                let half = geometry.half_support_1d(level, wavelet);
                let (lo, hi) = (centre[a] - half, centre[a] + half);
                match cue.side(a, lo, hi) {
                    CueSide::Front => return Ok(Vec::new()),
                    CueSide::Behind => {
                        let f = AxisFactor::Basis {
                            level: level as u8,
                            wavelet,
                        };
                        choices[a].push((f, centre[a], 1.0, near_of(a, lo, hi)));
                        continue;
                    }
                    CueSide::Straddle => {}
                }
                for (offset, coef) in &expansions[level][wavelet as usize] {
                    let c0 = centre[a] + offset;
                    let (lo0, hi0) = (c0 - half0, c0 + half0);
                    match cue.side(a, lo0, hi0) {
                        CueSide::Front => {}
                        CueSide::Behind => choices[a].push((
                            AxisFactor::Basis {
                                level: 0,
                                wavelet: false,
                            },
                            c0,
                            *coef,
                            near_of(a, lo0, hi0),
                        )),
                        CueSide::Straddle => choices[a].push((
                            AxisFactor::Straddle {
                                offset: (c0 - cue.planes[a]).round() as i8,
                            },
                            c0,
                            *coef,
                            cue.planes[a],
                        )),
                    }
                }
            }
            let mut out = Vec::with_capacity(choices.iter().map(Vec::len).product());
            for x in &choices[0] {
                for y in &choices[1] {
                    for z in &choices[2] {
                        let value = c.value as f64 * x.2 * y.2 * z.2 * weight_of([x.3, y.3, z.3]);
                        if value != 0.0 {
                            out.push(CuedSplat {
                                factors: [x.0, y.0, z.0],
                                centre: [x.1, y.1, z.1],
                                value,
                                channel: c.channel,
                            });
                        }
                    }
                }
            }
            Ok(out)
        })
        .collect();
    let mut cued = Vec::new();
    for p in projected {
        cued.extend(p?);
    }
    // Tables for the factor triples that occur (first-use order, deterministic).
    let mut index: std::collections::HashMap<[AxisFactor; 3], u32> = Default::default();
    let mut keys = Vec::new();
    let table_of: Vec<u32> = cued
        .iter()
        .map(|s| {
            *index.entry(s.factors).or_insert_with(|| {
                keys.push(s.factors);
                (keys.len() - 1) as u32
            })
        })
        .collect();
    let footprints = set.factor_footprints(&keys);
    let tables: Vec<&Footprint> = footprints.iter().map(|f| f.as_ref()).collect();
    let mut splats = Vec::with_capacity(cued.len());
    for (s, t) in cued.iter().zip(table_of) {
        let fp = tables[t as usize];
        let scr = camera.to_screen(s.centre);
        let (a, x0) = Footprint::place(fp.s, fp.cx, scr[0]);
        let (b, y0) = Footprint::place(fp.s, fp.cy, scr[1]);
        let ph = &fp.phases[b * fp.s + a];
        if x0 >= w || y0 >= h || x0 + ph.cols as i64 <= 0 || y0 + ph.rows as i64 <= 0 {
            stats.skipped += 1;
            continue;
        }
        splats.push(Splat {
            table: t,
            phase: (b * fp.s + a) as u16,
            x0: x0 as i32,
            y0: y0 as i32,
            value: s.value as f32,
            channel: s.channel,
        });
    }
    stats.splatted += splats.len();
    Ok(accumulate(&splats, &tables, camera, channels, stats))
}
