//! Splat planning: from a view and coefficients to [`SplatRecord`]s in a [`FootprintAtlas`].
//!
//! The [`Planner`] resolves a [`ViewSpec`] into a [`ViewPlan`]: the cameras (one, or the three
//! multiview cameras of §3.1, which share one footprint set by type permutation), the resolved
//! depth cue, and the footprint tables of the view, flattened into an atlas. Footprint sets are
//! cached per view like RustFFT's planner caches plans. A [`ViewPlan`] turns coefficients into
//! records: each coefficient is projected to its basis centre on the screen, the (level, type)
//! footprint is placed at the nearest subpixel phase (see [`crate::footprint`]) and records
//! whose box misses the screen are counted and dropped. With depth cueing the coefficients are
//! first expanded ([`crate::cue::expand`]) and the tables of the factor triples that occur are
//! built on first use and appended to the atlas.

use crate::backend::{FootprintAtlas, Layout, SplatRecord, TableRef};
use crate::cue::{self, check_coefficient, Expansions};
use crate::footprint::{AxisFactor, Footprint, FootprintParams, FootprintSet};
use crate::RenderError;
use rayon::prelude::*;
use std::collections::HashMap;
use std::sync::Arc;
use wavesplat_codec::format::packet::Coefficient;
use wavesplat_codec::layout::Geometry;
use wavesplat_codec::view::{multiview_map, resolve_cue, Camera, ResolvedCue, ViewSpec};

/// How a footprint is placed at a splat's exact screen position.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Placement {
    /// The nearest of the S × S subpixel phases (one record per splat; position error up to
    /// 1/(2S) pixel, which adds up coherently where many centres share a phase, e.g. along the
    /// rays of an axis-aligned view).
    Nearest,
    /// The nearest phase plus the first-order correction of the residual: two more records
    /// reading the footprint's gradient tables, weighted by the residual (error second order
    /// in 1/S; three records per splat and three times the table memory).
    Gradient,
}

/// Planning settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlanOptions {
    /// How footprints are placed.
    pub placement: Placement,
    /// Subpixel phases per axis (even; position error ≤ 1/(2S) pixel).
    pub subpixel: usize,
    /// Largest FFT side for a footprint (S is halved until the footprint fits).
    pub max_fft: usize,
    /// Footprint sets kept in the planner's cache.
    pub cache_size: usize,
}

impl Default for PlanOptions {
    fn default() -> Self {
        PlanOptions {
            placement: Placement::Gradient,
            subpixel: 8,
            max_fft: 768,
            cache_size: 8,
        }
    }
}

/// Counters of planning (and accumulation, filled in by the caller).
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

#[derive(Debug, Clone, PartialEq)]
struct CacheKey {
    params: [u64; 12],
}

fn key_of(p: &FootprintParams) -> CacheKey {
    let (k, l) = p.cue.unwrap_or((-1.0, [0.0; 3]));
    CacheKey {
        params: [
            p.family.code() as u64
                | ((p.levels as u64) << 8)
                | ((p.subpixel as u64) << 16)
                | ((p.gradient as u64) << 48),
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

/// Plans views, caching footprint sets.
#[derive(Debug, Default)]
pub struct Planner {
    options: PlanOptions,
    cache: Vec<(CacheKey, Arc<FootprintSet>)>,
}

impl Planner {
    /// A planner with the given options.
    pub fn new(options: PlanOptions) -> Planner {
        Planner {
            options,
            cache: Vec::new(),
        }
    }

    /// The options.
    pub fn options(&self) -> &PlanOptions {
        &self.options
    }

    /// The footprint set for `p` (from the cache or freshly built).
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

    /// Resolves `spec` for `geometry` with `channels` channels.
    pub fn plan(
        &mut self,
        geometry: &Geometry,
        spec: &ViewSpec,
        channels: usize,
    ) -> Result<ViewPlan, RenderError> {
        let cameras = spec.cameras(geometry.dims)?;
        let cue = match &spec.view.cue {
            Some(c) => Some(resolve_cue(c, &cameras[0], geometry)?),
            None => None,
        };
        let (ex, ey) = cameras[0].screen_axes();
        let params = FootprintParams {
            family: geometry.family,
            levels: geometry.levels,
            ex,
            ey,
            zoom: cameras[0].zoom,
            subpixel: self.options.subpixel,
            max_fft: self.options.max_fft,
            cue: cue.map(|c| (c.k, c.l)),
            gradient: self.options.placement == Placement::Gradient,
        };
        let set = self.footprints(&params);
        let mut atlas = FootprintAtlas::new();
        let tables = set
            .tables
            .iter()
            .map(|t| t.as_ref().map(|f| atlas.push(f)))
            .collect();
        Ok(ViewPlan {
            geometry: *geometry,
            spec: *spec,
            cameras,
            cue,
            channels,
            expansions: cue.map(|_| Expansions::new(geometry)),
            set,
            atlas,
            tables,
            cued_tables: HashMap::new(),
        })
    }
}

/// One view resolved for planning: cameras, cue, footprints (as an atlas).
#[derive(Debug)]
pub struct ViewPlan {
    /// The volume's geometry.
    pub geometry: Geometry,
    /// The view.
    pub spec: ViewSpec,
    /// One camera, or the three multiview cameras.
    pub cameras: Vec<Camera>,
    /// The resolved depth cue.
    pub cue: Option<ResolvedCue>,
    /// Channels of the image.
    pub channels: usize,
    /// Every footprint of the view (grows with cued factor triples).
    pub atlas: FootprintAtlas,
    expansions: Option<Expansions>,
    set: Arc<FootprintSet>,
    /// Uncued tables by `level · 8 + kind`.
    tables: Vec<Option<TableRef>>,
    /// Cued tables by factor triple.
    cued_tables: HashMap<[AxisFactor; 3], TableRef>,
}

/// Places a footprint centred at screen (X, Y) with weight `value`: the record at the nearest
/// phase, and with gradient tables the two records correcting the residual (skipped when the
/// residual is exactly zero). Records wholly off the screen are not produced; returns whether
/// any part is on screen.
fn place(
    t: &TableRef,
    atlas: &FootprintAtlas,
    scr: [f64; 2],
    value: f32,
    channel: u16,
    view: u16,
    size: (usize, usize),
    out: &mut Vec<SplatRecord>,
) -> bool {
    let (a, x0) = Footprint::place(t.s, t.cx, scr[0]);
    let (b, y0) = Footprint::place(t.s, t.cy, scr[1]);
    let idx = (b * t.s + a) as u32;
    let x0 = x0.clamp(i32::MIN as i64, i32::MAX as i64) as i32;
    let y0 = y0.clamp(i32::MIN as i64, i32::MAX as i64) as i32;
    let rect = &atlas.phases[(t.first_phase + idx) as usize];
    let (w, h) = (size.0 as i64, size.1 as i64);
    if (x0 as i64) >= w
        || (y0 as i64) >= h
        || x0 as i64 + rect.cols as i64 <= 0
        || y0 as i64 + rect.rows as i64 <= 0
    {
        return false;
    }
    let record = |phase: u32, value: f32| SplatRecord {
        x0,
        y0,
        phase,
        value,
        channel,
        view,
    };
    out.push(record(t.first_phase + idx, value));
    if let Some(g) = t.grad_first {
        let ss = (t.s * t.s) as u32;
        let dx = Footprint::residual(t.s, scr[0]);
        let dy = Footprint::residual(t.s, scr[1]);
        if dx != 0.0 {
            out.push(record(g + idx, (value as f64 * dx) as f32));
        }
        if dy != 0.0 {
            out.push(record(g + ss + idx, (value as f64 * dy) as f32));
        }
    }
    true
}

impl ViewPlan {
    /// The accumulation target of this view.
    pub fn layout(&self) -> Layout {
        Layout {
            width: self.spec.view.width,
            height: self.spec.view.height,
            channels: self.channels,
            views: self.cameras.len(),
        }
    }

    /// Appends the records of `coefficients` to `out` (each validated: an invalid coefficient
    /// is an error and nothing is appended); counts what was planned and skipped in `stats`.
    pub fn splats(
        &mut self,
        coefficients: &[Coefficient],
        out: &mut Vec<SplatRecord>,
        stats: &mut RenderStats,
    ) -> Result<(), RenderError> {
        for c in coefficients {
            check_coefficient(c, &self.geometry, self.channels)?;
        }
        stats.coefficients += coefficients.len();
        if let Some(cue) = self.cue {
            return self.cued_splats(coefficients, &cue, out, stats);
        }
        let odd = self.geometry.family.psi_is_odd();
        let size = (self.spec.view.width, self.spec.view.height);
        for (k, camera) in self.cameras.iter().enumerate() {
            let planned: Vec<(Vec<SplatRecord>, usize)> = coefficients
                .par_chunks(1024)
                .map(|chunk| {
                    let mut out = Vec::with_capacity(chunk.len() * 3);
                    let mut placed = 0usize;
                    for c in chunk {
                        let (kind, sign) = multiview_map(k, c.band.kind, odd);
                        let Some(t) = self.tables[c.band.level as usize * 8 + kind as usize] else {
                            continue;
                        };
                        let pos = [c.pos[0] as usize, c.pos[1] as usize, c.pos[2] as usize];
                        let scr = camera.to_screen(self.geometry.basis_center(c.band, pos));
                        let value = c.value * sign;
                        let (channel, view) = (c.channel as u16, k as u16);
                        if place(&t, &self.atlas, scr, value, channel, view, size, &mut out) {
                            placed += 1;
                        }
                    }
                    (out, placed)
                })
                .collect();
            let mut placed_here = 0;
            for (records, placed) in planned {
                out.extend(records);
                placed_here += placed;
            }
            stats.splatted += placed_here;
            stats.skipped += coefficients.len() - placed_here;
        }
        Ok(())
    }

    fn cued_splats(
        &mut self,
        coefficients: &[Coefficient],
        cue: &ResolvedCue,
        out: &mut Vec<SplatRecord>,
        stats: &mut RenderStats,
    ) -> Result<(), RenderError> {
        let expansions = self
            .expansions
            .as_ref()
            .ok_or(RenderError::Unsupported("cue without expansions"))?;
        let cued = cue::expand(coefficients, &self.geometry, cue, expansions);
        // Tables for the factor triples that first occur here (first-use order: deterministic).
        let mut missing: Vec<[AxisFactor; 3]> = Vec::new();
        for s in &cued {
            if !self.cued_tables.contains_key(&s.factors) && !missing.contains(&s.factors) {
                missing.push(s.factors);
            }
        }
        if !missing.is_empty() {
            for (key, f) in missing.iter().zip(self.set.factor_footprints(&missing)) {
                let t = self.atlas.push(&f);
                self.cued_tables.insert(*key, t);
            }
        }
        let camera = &self.cameras[0];
        let size = (self.spec.view.width, self.spec.view.height);
        for s in &cued {
            let t = self.cued_tables[&s.factors];
            let scr = camera.to_screen(s.centre);
            let value = s.value as f32;
            if place(&t, &self.atlas, scr, value, s.channel as u16, 0, size, out) {
                stats.splatted += 1;
            } else {
                stats.skipped += 1;
            }
        }
        Ok(())
    }
}
