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

/// Planning settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlanOptions {
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

/// Places a footprint centred at screen (X, Y): the record's phase and first pixel.
fn place(t: &TableRef, scr: [f64; 2]) -> (u32, i32, i32) {
    let (a, x0) = Footprint::place(t.s, t.cx, scr[0]);
    let (b, y0) = Footprint::place(t.s, t.cy, scr[1]);
    (
        t.first_phase + (b * t.s + a) as u32,
        x0.clamp(i32::MIN as i64, i32::MAX as i64) as i32,
        y0.clamp(i32::MIN as i64, i32::MAX as i64) as i32,
    )
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

    /// Whether a record covers part of the screen.
    fn on_screen(&self, r: &SplatRecord) -> bool {
        let rect = &self.atlas.phases[r.phase as usize];
        let (w, h) = (self.spec.view.width as i64, self.spec.view.height as i64);
        (r.x0 as i64) < w
            && (r.y0 as i64) < h
            && r.x0 as i64 + rect.cols as i64 > 0
            && r.y0 as i64 + rect.rows as i64 > 0
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
        for (k, camera) in self.cameras.iter().enumerate() {
            let planned: Vec<Option<SplatRecord>> = coefficients
                .par_iter()
                .map(|c| {
                    let (kind, sign) = multiview_map(k, c.band.kind, odd);
                    let t = self.tables[c.band.level as usize * 8 + kind as usize]?;
                    let pos = [c.pos[0] as usize, c.pos[1] as usize, c.pos[2] as usize];
                    let scr = camera.to_screen(self.geometry.basis_center(c.band, pos));
                    let (phase, x0, y0) = place(&t, scr);
                    let r = SplatRecord {
                        x0,
                        y0,
                        phase,
                        value: c.value * sign,
                        channel: c.channel as u16,
                        view: k as u16,
                    };
                    self.on_screen(&r).then_some(r)
                })
                .collect();
            for r in planned {
                match r {
                    Some(r) => {
                        out.push(r);
                        stats.splatted += 1;
                    }
                    None => stats.skipped += 1,
                }
            }
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
        for s in &cued {
            let t = self.cued_tables[&s.factors];
            let (phase, x0, y0) = place(&t, camera.to_screen(s.centre));
            let r = SplatRecord {
                x0,
                y0,
                phase,
                value: s.value as f32,
                channel: s.channel as u16,
                view: 0,
            };
            if self.on_screen(&r) {
                out.push(r);
                stats.splatted += 1;
            } else {
                stats.skipped += 1;
            }
        }
        Ok(())
    }
}
