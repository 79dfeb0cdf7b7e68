//! Splat planning: from a view and coefficients to [`SplatRecord`]s in a [`FootprintAtlas`].
//!
//! The [`Planner`] resolves a [`ViewSpec`] into a [`ViewPlan`]: the cameras (one, or the three
//! multiview cameras of §3.1, which share one footprint set by type permutation when the voxel
//! spacing is the same along the axes the permutation swaps, and have a set each otherwise:
//! swapping two axes of differently spaced voxels is not a symmetry of the data), the resolved
//! depth cue, and the footprint tables of the view, flattened into an atlas. Footprint sets are
//! cached per view like RustFFT's planner caches plans. A [`ViewPlan`] turns coefficients into
//! records: each coefficient is projected to its basis centre on the screen, the (level, type)
//! footprint is placed at the nearest subpixel phase (see [`crate::footprint`]) and records whose
//! box misses the screen are counted and dropped. When the geometry's periodic images reach the
//! volume, coefficients are first clipped to its box ([`crate::pieces::BoxClip`]): those wholly
//! inside stay one splat, the others become pieces. With depth cueing the coefficients are split
//! into cued pieces ([`crate::pieces::expand`], or the clip's pieces with their cue weights). The
//! tables of the factor triples that occur are built on first use and appended to the atlas: at
//! once by default, or, for a frame loop that must not stall
//! ([`ViewPlan::build_tables_in_background`]), on a thread of the plan's own while the coefficients
//! that need them wait ([`ViewPlan::take_deferred`]).

use crate::backend::{AccumulationBackend, FootprintAtlas, Layout, SplatRecord, TableRef};
use crate::footprint::{AxisFactor, Footprint, FootprintParams, FootprintSet};
use crate::pieces::{self, check_coefficient, BoxClip, Clipped, Expansions, Piece};
use crate::RenderError;
use rayon::prelude::*;
use rustc_hash::{FxHashMap as HashMap, FxHashSet as HashSet};
use std::sync::mpsc::{channel, Receiver, Sender};
use std::sync::Arc;
use wavesplat_codec::family::Family;
use wavesplat_codec::format::packet::Coefficient;
use wavesplat_codec::layout::{Band, Geometry};
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
    /// Subpixel phases per axis (even; position error ≤ 1/(2S) pixel); `None` takes the
    /// family's default, [`PlanOptions::default_subpixel`].
    pub subpixel: Option<usize>,
    /// Largest FFT side for a footprint (S is halved until the footprint fits); `None` takes
    /// the family's default, [`PlanOptions::default_max_fft`].
    pub max_fft: Option<usize>,
    /// Footprint sets kept in the planner's cache.
    pub cache_size: usize,
    /// Clip coefficients to the volume's box when periodic images reach it (exact; see
    /// [`crate::pieces`]). Off, each coefficient is one splat at its image nearest the volume
    /// centre: what a preview draws (no factor tables to wait for).
    pub clip: bool,
}

impl PlanOptions {
    /// Subpixel phases that bring every view to ≥ 50 dB against the exact line integral with
    /// gradient placement: 16 for Haar, whose box edges leave a kink the gradient cannot
    /// correct (S = 8 measured 46.7 dB on a 96² axis view, S = 16 56.8–65.8 dB), 8 for the
    /// smooth splines (66–72 dB). Haar tables are small, so the doubling costs little.
    pub fn default_subpixel(family: Family) -> usize {
        match family {
            Family::Haar => 16,
            _ => 8,
        }
    }

    /// Largest FFT side: 1024 for Haar, 768 for the splines. A Haar footprint wider than
    /// 1024/16 = 64 px (a coarse level on a large image) would otherwise drop to S = 8 and its
    /// box edges cost accuracy (Haar M = 5 on 32³ in a 96² image: 47.7 dB at 768, 66.6 dB at
    /// 1024, for about three times the planning time of that view).
    pub fn default_max_fft(family: Family) -> usize {
        match family {
            Family::Haar => 1024,
            _ => 768,
        }
    }

    /// The largest FFT side used for `family`.
    pub fn max_fft_for(&self, family: Family) -> usize {
        self.max_fft
            .unwrap_or_else(|| Self::default_max_fft(family))
    }

    /// The subpixel phases used for `family` in a view with screen axes `ex`, `ey` per voxel
    /// step (`Camera::index_axes`) at `zoom` pixels per unit of spacing: the requested ones,
    /// else the family's default raised for minified views ([`minified_subpixel`]).
    pub fn subpixel_for_view(
        &self,
        family: Family,
        zoom: f64,
        ex: [f64; 3],
        ey: [f64; 3],
    ) -> usize {
        self.subpixel.unwrap_or_else(|| {
            Self::default_subpixel(family).max(minified_subpixel(family, zoom, ex, ey))
        })
    }
}

/// Table samples per standard deviation of the narrowest footprint a view draws (a level-0
/// φ along every axis, √(j/12) voxels for B-splines of order j, projected), the least a default
/// view's tables take. Where voxels are smaller than pixels the pixel-averaged footprints'
/// sides are as steep as the footprints are narrow, and the phase tables' residual (second
/// order in the sample spacing after the gradient correction) grows as 1/(S·width)². Measured
/// on the axis views of voxel-scale noise against exact line integrals
/// (`axis_views_match_exact_line_integrals_at_every_scale`) at S = 8: linear 55 dB at 0.45
/// pixels per voxel, 42 dB at 0.2, 36 dB at 0.13; cubic 48.6 dB at 0.3. Linear at 0.13 with
/// S = 16 / 32: 55.8 / 63.8 dB. Two samples per deviation keep the default S = 8 from 0.62
/// (linear) and 0.44 (cubic) pixels per voxel up on the axes, less obliquely.
const SAMPLES_PER_DEVIATION: f64 = 2.0;

/// Most phases per axis [`minified_subpixel`] asks for: S = 32 holds the linear family's axis
/// views at 64 dB at 0.13 pixels per voxel; S = 64 would plan a 256³ volume's 48² thumbnail in
/// about four times as long again (S² phases per table).
const MAX_MINIFIED_SUBPIXEL: usize = 32;

/// The S that puts at least `SAMPLES_PER_DEVIATION` (2) samples in a standard deviation of the
/// narrowest footprint of `family` in a view with screen axes `ex`, `ey` per voxel step at
/// `zoom`: a power of two (placing a record then takes a mask and a shift instead of two
/// divisions, `Footprint::place_with_residual`), at most `MAX_MINIFIED_SUBPIXEL` (32); 2 when
/// that width is not a positive number.
pub fn minified_subpixel(family: Family, zoom: f64, ex: [f64; 3], ey: [f64; 3]) -> usize {
    let deviation = (family.order() as f64 / 12.0).sqrt();
    let width = |e: [f64; 3]| zoom * deviation * e.iter().map(|v| v.abs()).sum::<f64>();
    let narrowest = width(ex).min(width(ey));
    if !(narrowest.is_finite() && narrowest > 0.0) {
        return 2;
    }
    let s = (SAMPLES_PER_DEVIATION / narrowest)
        .ceil()
        .min(MAX_MINIFIED_SUBPIXEL as f64) as usize;
    s.next_power_of_two().clamp(2, MAX_MINIFIED_SUBPIXEL)
}

impl Default for PlanOptions {
    fn default() -> Self {
        PlanOptions {
            placement: Placement::Gradient,
            subpixel: None,
            max_fft: None,
            cache_size: 8,
            clip: true,
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
    /// Splats left out because their footprint vanishes in this view (a ψ along the direction
    /// of a view along an axis: [`crate::footprint::VANISHING`]), summed over views.
    pub vanished: usize,
    /// Pixel updates performed.
    pub pixel_updates: u64,
}

#[derive(Debug, Clone, PartialEq)]
struct CacheKey {
    params: [u64; 13],
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
            p.voxel_volume.to_bits(),
        ],
    }
}

/// Whether the multiview cameras can draw with the first camera's tables (§3.1's type
/// permutation): view 2 swaps the x and y factors, view 3 the x and z factors, so their spacings
/// must agree.
fn shares_tables(spec: &ViewSpec, spacing: [f32; 3]) -> bool {
    !spec.multiview || (spacing[0] == spacing[1] && spacing[0] == spacing[2])
}

/// A view spec resolved for a volume: its cameras, its depth cue and the parameters of the
/// footprint sets it draws with.
#[derive(Debug, Clone)]
pub struct ResolvedView {
    /// One camera, or the three multiview cameras.
    pub cameras: Vec<Camera>,
    /// The resolved depth cue.
    pub cue: Option<ResolvedCue>,
    /// One footprint set shared by every camera, or one per camera.
    pub footprints: Vec<FootprintParams>,
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
        self.insert(set.clone());
        set
    }

    /// The footprint parameters of `spec` for `geometry` (with its cameras and resolved cue):
    /// what [`Planner::plan`] builds or finds tables for: one set, or one per multiview camera
    /// when they cannot share (see the module documentation).
    pub fn params(
        &self,
        geometry: &Geometry,
        spec: &ViewSpec,
    ) -> Result<ResolvedView, RenderError> {
        let cameras = spec.cameras(geometry)?;
        let cue = match &spec.view.cue {
            Some(c) => Some(resolve_cue(c, &cameras[0], geometry)?),
            None => None,
        };
        let sets = if shares_tables(spec, geometry.spacing) {
            1
        } else {
            cameras.len()
        };
        let params = cameras[..sets]
            .iter()
            .map(|camera| {
                let (ex, ey) = camera.index_axes();
                FootprintParams {
                    family: geometry.family,
                    levels: geometry.levels,
                    ex,
                    ey,
                    zoom: camera.zoom,
                    voxel_volume: camera.voxel_volume(),
                    subpixel: self
                        .options
                        .subpixel_for_view(geometry.family, camera.zoom, ex, ey),
                    max_fft: self.options.max_fft_for(geometry.family),
                    cue: cue.map(|c| (c.k, c.l)),
                    gradient: self.options.placement == Placement::Gradient,
                }
            })
            .collect();
        Ok(ResolvedView {
            cameras,
            cue,
            footprints: params,
        })
    }

    /// Whether the footprints for every one of `params` are in the cache (planning them is
    /// then cheap).
    pub fn is_cached(&self, params: &[FootprintParams]) -> bool {
        params.iter().all(|p| {
            let key = key_of(p);
            self.cache.iter().any(|(k, _)| *k == key)
        })
    }

    /// Puts footprints built elsewhere (e.g. on a background thread) into the cache.
    pub fn insert(&mut self, set: Arc<FootprintSet>) {
        let key = key_of(&set.params);
        self.cache.retain(|(k, _)| *k != key);
        self.cache.push((key, set));
        while self.cache.len() > self.options.cache_size.max(1) {
            self.cache.remove(0);
        }
    }

    /// Resolves `spec` for `geometry` with `channels` channels.
    pub fn plan(
        &mut self,
        geometry: &Geometry,
        spec: &ViewSpec,
        channels: usize,
    ) -> Result<ViewPlan, RenderError> {
        let ResolvedView {
            cameras,
            cue,
            footprints,
        } = self.params(geometry, spec)?;
        let sets: Vec<Arc<FootprintSet>> = footprints.iter().map(|p| self.footprints(p)).collect();
        let mut atlas = FootprintAtlas::new();
        atlas.reserve_for(sets.iter().flat_map(|set| set.tables.iter().flatten()));
        let tables = sets
            .iter()
            .map(|set| {
                set.tables
                    .iter()
                    .map(|t| t.as_ref().map(|f| atlas.push(f)))
                    .collect()
            })
            .collect();
        Ok(ViewPlan {
            geometry: *geometry,
            spec: *spec,
            cameras,
            cue,
            channels,
            expansions: cue.map(|_| Expansions::new(geometry)),
            clip: (self.options.clip && geometry.clips_to_box()).then(|| BoxClip::new(geometry)),
            factor_tables: vec![HashMap::default(); sets.len()],
            sets,
            atlas,
            tables,
            builder: None,
            deferred: Vec::new(),
            built_inline: 0,
            stood_in: HashSet::default(),
            stand_ins_drawn: 0,
            stand_in_tables: Vec::new(),
            centres: Centres::new(geometry),
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
    /// Clipping to the box, when the geometry's periodic images reach the volume.
    clip: Option<BoxClip>,
    /// Footprint sets: one shared by every camera, or one per camera.
    sets: Vec<Arc<FootprintSet>>,
    /// Per set, the uncued tables by `level · 8 + kind`.
    tables: Vec<Vec<Option<TableRef>>>,
    /// Per set, the tables of cued pieces by factor triple.
    factor_tables: Vec<HashMap<[AxisFactor; 3], TableRef>>,
    /// The background builder of cued tables, when enabled.
    builder: Option<TableBuilder>,
    /// Indices (into the last `splats` call's coefficients) left out for want of a table.
    deferred: Vec<usize>,
    /// Cued tables built on the calling thread so far.
    built_inline: usize,
    /// Coefficients (band, position, channel) drawn with a stand-in while their cued tables
    /// are built.
    stood_in: HashSet<(Band, [u32; 3], u8)>,
    /// Stand-ins drawn so far.
    stand_ins_drawn: usize,
    /// Uncued tables of the view for stand-ins, by `level · 8 + kind` (empty: no stand-ins).
    stand_in_tables: Vec<Option<TableRef>>,
    /// Basis centres by band and position.
    centres: Centres,
}

/// Coefficients per parallel planning task.
const CHUNK: usize = 1024;

/// [`Geometry::basis_center`] tabulated per axis, level and φ/ψ by position, so that planning a
/// coefficient looks its centre up instead of computing it (a division and a `round` per axis,
/// the largest share of the per-coefficient work); the values are the same f64s.
#[derive(Debug, Clone)]
struct Centres {
    /// By `(level · 2 + wavelet) · 3 + axis`: the centre of each position of that band axis.
    along: Vec<Vec<f64>>,
}

impl Centres {
    fn new(geometry: &Geometry) -> Centres {
        let levels = geometry.levels;
        let mut along = Vec::with_capacity((levels + 1) * 6);
        for level in 0..=levels {
            for wavelet in [false, true] {
                for a in 0..3 {
                    let n = geometry.padded[a] >> level;
                    along.push(
                        (0..n)
                            .map(|k| geometry.basis_center_along(a, level, k, wavelet))
                            .collect(),
                    );
                }
            }
        }
        Centres { along }
    }

    /// The centre of a coefficient already checked against the geometry (`check_coefficient`).
    #[inline]
    fn of(&self, band: Band, pos: [u32; 3]) -> [f64; 3] {
        std::array::from_fn(|a| {
            let wavelet = band.is_wavelet_along(a) as usize;
            self.along[(band.level as usize * 2 + wavelet) * 3 + a][pos[a] as usize]
        })
    }
}

/// A cued table request or result: footprint set index and factor triple.
type TableKey = (usize, [AxisFactor; 3]);

/// Builds cued tables on a thread of its own (a one-thread rayon pool, so its parallel loops
/// never queue ahead of the caller's splat batches on the global pool); ends when dropped.
#[derive(Debug)]
struct TableBuilder {
    requests: Sender<Vec<TableKey>>,
    results: Receiver<Vec<(TableKey, Arc<Footprint>)>>,
    /// Requested and not yet received.
    pending: HashSet<TableKey>,
}

impl TableBuilder {
    fn start(sets: Vec<Arc<FootprintSet>>) -> TableBuilder {
        let (requests, jobs) = channel::<Vec<TableKey>>();
        let (done, results) = channel();
        std::thread::spawn(move || {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(1)
                .thread_name(|_| "wavesplat-cue-tables".into())
                .build()
                .ok();
            // Ends when the plan (the sender) is dropped or stops listening.
            while let Ok(keys) = jobs.recv() {
                let build = || {
                    let mut out = Vec::with_capacity(keys.len());
                    for (set, group) in group_by_set(&keys) {
                        let tables = sets[set].factor_footprints(&group);
                        out.extend(group.into_iter().zip(tables).map(|(t, f)| ((set, t), f)));
                    }
                    out
                };
                let started = std::time::Instant::now();
                let built = match &pool {
                    Some(pool) => pool.install(build),
                    None => build(),
                };
                tracing::debug!(
                    tables = built.len(),
                    ms = started.elapsed().as_secs_f64() * 1e3,
                    "built factor tables in the background"
                );
                if done.send(built).is_err() {
                    break;
                }
            }
        });
        TableBuilder {
            requests,
            results,
            pending: HashSet::default(),
        }
    }
}

/// Triples grouped by their footprint set (in first-seen order).
fn group_by_set(keys: &[TableKey]) -> Vec<(usize, Vec<[AxisFactor; 3]>)> {
    let mut groups: Vec<(usize, Vec<[AxisFactor; 3]>)> = Vec::new();
    for (set, t) in keys {
        match groups.iter_mut().find(|(s, _)| s == set) {
            Some((_, g)) => g.push(*t),
            None => groups.push((*set, vec![*t])),
        }
    }
    groups
}

impl ViewPlan {
    /// The footprint tables the plan draws with (to cache them in another planner).
    pub fn footprint_sets(&self) -> Vec<Arc<FootprintSet>> {
        self.sets.clone()
    }

    /// From now on, cued tables missing for a batch are built on a background thread instead of
    /// the caller's: the coefficients that need them are left out of the batch and listed by
    /// [`ViewPlan::take_deferred`] until [`ViewPlan::poll_tables`] has the tables. For frame
    /// loops; a single render keeps the default (build at once, splat everything).
    pub fn build_tables_in_background(&mut self) {
        if self.builder.is_none() {
            self.builder = Some(TableBuilder::start(self.sets.clone()));
        }
    }

    /// Installs the cued tables the background builder has finished; returns how many.
    pub fn poll_tables(&mut self) -> usize {
        let Some(b) = &mut self.builder else {
            return 0;
        };
        let mut arrived = Vec::new();
        while let Ok(built) = b.results.try_recv() {
            arrived.extend(built);
        }
        for ((set, triple), f) in &arrived {
            b.pending.remove(&(*set, *triple));
            let t = self.atlas.push(f);
            self.factor_tables[*set].insert(*triple, t);
        }
        arrived.len()
    }

    /// The relative cost of drawing `c` in this view, given the cost `weight(level)` of one
    /// splat of a level: one splat, or with clipping the sum over its pieces.
    pub fn weigh(&self, c: &Coefficient, weight: impl Fn(u8) -> f64) -> f64 {
        match &self.clip {
            Some(b) if c.band.level as usize <= self.geometry.levels => b.weigh(c, weight),
            _ => weight(c.band.level),
        }
    }

    /// Whether coefficients are clipped to the volume's box (see [`crate::pieces`]): the view
    /// then draws pieces with factor tables even without a cue.
    pub fn clips(&self) -> bool {
        self.clip.is_some()
    }

    /// Whether cued tables are being built in the background.
    pub fn tables_pending(&self) -> bool {
        self.builder.as_ref().is_some_and(|b| !b.pending.is_empty())
    }

    /// The indices (into the coefficients of the last [`ViewPlan::splats`] call) left out
    /// because their cued tables are still being built (always empty unless
    /// [`ViewPlan::build_tables_in_background`] was called).
    pub fn take_deferred(&mut self) -> Vec<usize> {
        std::mem::take(&mut self.deferred)
    }

    /// Cued tables built on the calling thread (inside [`ViewPlan::splats`]) so far.
    pub fn tables_built_inline(&self) -> usize {
        self.built_inline
    }

    /// Stand-ins while cued tables are built: a coefficient left waiting is drawn at once with
    /// its uncued table weighted by the cue at its centre (a coarse image rather than none); when
    /// it is drawn for real, its stand-in is taken back (the same record negated: accumulation
    /// is additive, so the image ends exactly as if there had been none, up to f32 rounding).
    fn stand_ins(
        &mut self,
        coefficients: &[Coefficient],
        waiting: &HashSet<usize>,
        out: &mut Vec<SplatRecord>,
    ) {
        let (Some(cue), Some(camera)) = (self.cue, self.cameras.first()) else {
            return;
        };
        if self.stand_in_tables.is_empty() {
            return;
        }
        let size = (self.spec.view.width, self.spec.view.height);
        for (i, c) in coefficients.iter().enumerate() {
            let key = (c.band, c.pos, c.channel);
            let sign = if waiting.contains(&i) {
                if !self.stood_in.insert(key) {
                    continue;
                }
                self.stand_ins_drawn += 1;
                1.0
            } else if self.stood_in.remove(&key) {
                -1.0
            } else {
                continue;
            };
            let Some(t) = self.stand_in_tables[c.band.level as usize * 8 + c.band.kind as usize]
            else {
                continue;
            };
            let pos = [c.pos[0] as usize, c.pos[1] as usize, c.pos[2] as usize];
            let centre = self.geometry.basis_center(c.band, pos);
            let value = (sign * c.value as f64 * cue.weight(centre)) as f32;
            if value != 0.0 {
                let scr = camera.to_screen(centre);
                place(&t, &self.atlas, scr, value, c.channel as u16, 0, size, out);
            }
        }
    }

    /// Gives the plan the uncued tables of its view (any placement and phases: previews do) to
    /// draw stand-ins with while cued tables are built in the background.
    pub fn set_stand_in_tables(&mut self, set: &FootprintSet) {
        self.stand_in_tables = set
            .tables
            .iter()
            .map(|t| t.as_ref().map(|f| self.atlas.push(f)))
            .collect();
    }

    /// Stand-ins drawn so far (coefficients drawn approximately while their cued tables were
    /// built).
    pub fn stand_ins_drawn(&self) -> usize {
        self.stand_ins_drawn
    }

    /// Forgets the stand-ins drawn so far (the accumulation restarted without them).
    pub fn forget_stand_ins(&mut self) {
        self.stood_in.clear();
    }

    /// Which set camera `k` draws with, and whether it goes through the first camera's tables
    /// by type permutation.
    fn set_of(&self, k: usize) -> (usize, bool) {
        if self.sets.len() == 1 {
            (0, k > 0)
        } else {
            (k, false)
        }
    }
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
    let (a, x0, dx) = Footprint::place_with_residual(t.s, t.cx, scr[0]);
    let (b, y0, dy) = Footprint::place_with_residual(t.s, t.cy, scr[1]);
    let idx = (b * t.s + a) as u32;
    let phase = (t.first_phase + idx) as usize;
    // The phase keeps a box of its samples (`footprint::TRIM`); its gradient phases the same.
    let [ox, oy] = atlas.origins.get(phase).copied().unwrap_or([0, 0]);
    let x0 = (x0 + ox as i64).clamp(i32::MIN as i64, i32::MAX as i64) as i32;
    let y0 = (y0 + oy as i64).clamp(i32::MIN as i64, i32::MAX as i64) as i32;
    let rect = &atlas.phases[phase];
    let (w, h) = (size.0 as i64, size.1 as i64);
    if rect.cols == 0
        || rect.rows == 0
        || (x0 as i64) >= w
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
    /// is an error and nothing is appended); counts what was planned and skipped in `stats` (a
    /// coefficient counts as splatted in a view when any of its pieces reaches the screen).
    pub fn splats(
        &mut self,
        coefficients: &[Coefficient],
        out: &mut Vec<SplatRecord>,
        stats: &mut RenderStats,
    ) -> Result<(), RenderError> {
        for c in coefficients {
            check_coefficient(c, &self.geometry, self.channels)?;
        }
        // Clipped to the box, a coefficient is one splat where it lies wholly inside and pieces
        // elsewhere; unclipped, with a cue every coefficient is split into cued pieces and
        // without one each is one splat at its image nearest the volume centre.
        let (clipped, pieces): (Option<Vec<Clipped>>, Vec<(usize, Piece)>) =
            match (&self.clip, &self.cue, &self.expansions) {
                (Some(b), cue, _) => {
                    let (c, p) = b.clip(coefficients, cue.as_ref());
                    (Some(c), p)
                }
                (None, Some(cue), Some(e)) => {
                    (None, pieces::expand(coefficients, &self.geometry, cue, e))
                }
                _ => (None, Vec::new()),
            };
        let whole = self.cue.is_none();
        let odd = self.geometry.family.psi_is_odd();
        let size = (self.spec.view.width, self.spec.view.height);
        let views = self.cameras.len();
        // Tables of the factor triples that first occur (first-use order: deterministic).
        let triples: Vec<Vec<([AxisFactor; 3], f32)>> = (0..views)
            .map(|k| {
                let (_, permuted) = self.set_of(k);
                pieces
                    .iter()
                    .map(|(_, p)| {
                        if permuted {
                            view_triple(&p.factors, k, odd)
                        } else {
                            (p.factors, 1.0)
                        }
                    })
                    .collect()
            })
            .collect();
        self.deferred.clear();
        self.poll_tables();
        let mut waiting: HashSet<usize> = HashSet::default();
        for (k, view_triples) in triples.iter().enumerate() {
            let (set, _) = self.set_of(k);
            let mut missing: Vec<[AxisFactor; 3]> = Vec::new();
            for ((i, _), (t, _)) in pieces.iter().zip(view_triples) {
                if !self.factor_tables[set].contains_key(t) {
                    if self.builder.is_some() {
                        waiting.insert(*i);
                    }
                    if !missing.contains(t) {
                        missing.push(*t);
                    }
                }
            }
            if missing.is_empty() {
                continue;
            }
            match &mut self.builder {
                Some(b) => {
                    let new: Vec<TableKey> = missing
                        .into_iter()
                        .map(|t| (set, t))
                        .filter(|key| b.pending.insert(*key))
                        .collect();
                    // A builder that died (it panicked) leaves its coefficients waiting;
                    // `tables_pending` stays true and the caller sees no progress.
                    if !new.is_empty() {
                        let _ = b.requests.send(new);
                    }
                }
                None => {
                    tracing::debug!(
                        set,
                        tables = missing.len(),
                        pieces = pieces.len(),
                        "building factor tables inline"
                    );
                    let built = self.sets[set].factor_footprints(&missing);
                    self.built_inline += missing.len();
                    for (key, f) in missing.iter().zip(built) {
                        let t = self.atlas.push(&f);
                        self.factor_tables[set].insert(*key, t);
                    }
                }
            }
        }
        if !waiting.is_empty() {
            self.deferred = waiting.iter().copied().collect();
            self.deferred.sort_unstable();
        }
        stats.coefficients += coefficients.len() - waiting.len();
        if self.builder.is_some() {
            self.stand_ins(coefficients, &waiting, out);
        }
        for (k, camera) in self.cameras.iter().enumerate() {
            let (set, permuted) = self.set_of(k);
            let tables = &self.tables[set];
            let clipped = clipped.as_deref();
            let planned: Vec<(Vec<SplatRecord>, usize, usize)> = coefficients
                .par_chunks(CHUNK)
                .enumerate()
                .map(|(ci, chunk)| {
                    let mut out = Vec::with_capacity(chunk.len() * 3);
                    let (mut placed, mut vanished) = (0usize, 0usize);
                    for (j, c) in chunk.iter().enumerate() {
                        let centre = match clipped.map(|cl| cl[ci * CHUNK + j]) {
                            Some(Clipped::Whole(centre)) => centre,
                            Some(Clipped::Split) => continue,
                            None if whole => self.centres.of(c.band, c.pos),
                            None => continue,
                        };
                        let (kind, sign) = if permuted {
                            multiview_map(k, c.band.kind, odd)
                        } else {
                            (c.band.kind, 1.0)
                        };
                        // Every (level, kind) of a checked coefficient has a table unless
                        // its footprint vanishes in this view.
                        let Some(t) = tables[c.band.level as usize * 8 + kind as usize] else {
                            vanished += 1;
                            continue;
                        };
                        let scr = camera.to_screen(centre);
                        let value = c.value * sign;
                        let (channel, view) = (c.channel as u16, k as u16);
                        if place(&t, &self.atlas, scr, value, channel, view, size, &mut out) {
                            placed += 1;
                        }
                    }
                    (out, placed, vanished)
                })
                .collect();
            let (mut placed_here, mut vanished_here) = (0, 0);
            for (records, placed, vanished) in planned {
                out.extend(records);
                placed_here += placed;
                vanished_here += vanished;
            }
            // Split coefficients: placed when any piece is. A coefficient's pieces are
            // consecutive; chunks of pieces are placed on the pool and their records appended
            // in order (the same records in the same order as one pass would make), each
            // chunk counting the coefficients it placed and the first and last of them, so a
            // coefficient whose pieces straddle two chunks counts once.
            let factor_tables = &self.factor_tables[set];
            let atlas = &self.atlas;
            let waiting = &waiting;
            let placed_pieces: Vec<PlacedPieces> = pieces
                .par_chunks(CHUNK)
                .zip(triples[k].par_chunks(CHUNK))
                .map(|(chunk, chunk_triples)| {
                    let mut records = Vec::with_capacity(chunk.len() * 3);
                    let mut placed = 0usize;
                    let mut ends: Option<(usize, usize)> = None;
                    for ((i, p), (triple, sign)) in chunk.iter().zip(chunk_triples) {
                        // A deferred coefficient is drawn whole later, when all its tables
                        // are here.
                        if waiting.contains(i) {
                            continue;
                        }
                        let t = factor_tables[triple];
                        let scr = camera.to_screen(p.centre);
                        let value = (p.value * *sign as f64) as f32;
                        let on = place(
                            &t,
                            atlas,
                            scr,
                            value,
                            p.channel as u16,
                            k as u16,
                            size,
                            &mut records,
                        );
                        if on && ends.is_none_or(|(_, last)| *i != last) {
                            placed += 1;
                            ends = Some((ends.map_or(*i, |(first, _)| first), *i));
                        }
                    }
                    (records, placed, ends)
                })
                .collect();
            let mut last = usize::MAX;
            for (records, placed, ends) in placed_pieces {
                out.extend(records);
                if let Some((first, end)) = ends {
                    placed_here += placed - usize::from(first == last);
                    last = end;
                }
            }
            stats.splatted += placed_here;
            stats.vanished += vanished_here;
            stats.skipped += coefficients.len() - waiting.len() - placed_here - vanished_here;
        }
        Ok(())
    }
}

/// Most coefficients planned and accumulated at a time by [`ViewPlan::splat_in_batches`]. Every
/// batch's records are summed before the next batch is planned, and the record and batch
/// buffers are reused, so their pages are faulted in once. A one-shot `render` is cold (every
/// page fresh): on two cores MNI at 1.25 % (165 k coefficients, 256²) was done 50 ms after the
/// request in batches of 2^16, 56 ms in one batch; MNI at 5 % (639 k, 512²) 245 ms against 254
/// (2^14) and 284 (2^20).
pub const SPLAT_BATCH: usize = 1 << 16;

/// The reusable buffers of [`ViewPlan::splat_in_batches`]: one batch's records, and the
/// coefficients of short runs gathered into one batch. Keep one between calls (the one-shot
/// [`crate::Renderer`] does) and their pages stay faulted in.
#[derive(Debug, Default)]
pub struct SplatBuffers {
    records: Vec<SplatRecord>,
    batch: Vec<Coefficient>,
}

impl ViewPlan {
    /// Plans and accumulates every coefficient of `runs` (consecutive runs, such as a file's
    /// packets, in order) into `backend`, at most `batch_size` coefficients at a time (short
    /// runs are gathered into one batch, a long one is cut), with `buffers` reused: the image
    /// equals one [`ViewPlan::splats`] of them all and one accumulation, up to the order of f32
    /// additions, without holding every record at once (three per coefficient for a family
    /// with gradient tables: 12 MB for 165 k coefficients). Counts into `stats`, pixel updates
    /// included.
    pub fn splat_in_batches<'a>(
        &mut self,
        runs: impl IntoIterator<Item = &'a [Coefficient]>,
        backend: &mut dyn AccumulationBackend,
        batch_size: usize,
        buffers: &mut SplatBuffers,
        stats: &mut RenderStats,
    ) -> Result<(), RenderError> {
        let batch_size = batch_size.max(1);
        let SplatBuffers { records, batch } = buffers;
        batch.clear();
        let mut flush = |plan: &mut ViewPlan,
                         part: &[Coefficient],
                         stats: &mut RenderStats|
         -> Result<(), RenderError> {
            records.clear();
            plan.splats(part, records, stats)?;
            stats.pixel_updates += backend.accumulate(&plan.atlas, records)?;
            Ok(())
        };
        let mut runs = runs.into_iter().peekable();
        while let Some(run) = runs.next() {
            if !batch.is_empty() && batch.len() + run.len() > batch_size {
                flush(self, batch, stats)?;
                batch.clear();
            }
            // A run that fills a batch alone, or that no following run joins (the last one, or
            // one whose successor would not fit beside it: the one-shot renderer's single
            // run), is splatted from where it lies instead of being copied into the batch.
            let alone = batch.is_empty()
                && runs
                    .peek()
                    .is_none_or(|next| run.len() + next.len() > batch_size);
            if run.len() >= batch_size || alone {
                for part in run.chunks(batch_size) {
                    flush(self, part, stats)?;
                }
            } else {
                batch.extend_from_slice(run);
            }
        }
        if !batch.is_empty() {
            flush(self, batch, stats)?;
            batch.clear();
        }
        Ok(())
    }
}

/// The records of a chunk of cued pieces, how many coefficients they placed, and the first and
/// last of those (input indices).
type PlacedPieces = (Vec<SplatRecord>, usize, Option<(usize, usize)>);

/// A piece's factor triple as seen in multiview view `k` through the first view's tables (the
/// triple counterpart of `codec::view::multiview_map`): view 2 takes (y, reflected x, z), view 3
/// (reflected z, y, x); the sign is that of a reflected odd ψ.
fn view_triple(f: &[AxisFactor; 3], k: usize, psi_is_odd: bool) -> ([AxisFactor; 3], f32) {
    match k {
        1 => {
            let (rx, s) = f[0].reflected(psi_is_odd);
            ([f[1], rx, f[2]], s)
        }
        2 => {
            let (rz, s) = f[2].reflected(psi_is_odd);
            ([rz, f[1], f[0]], s)
        }
        _ => (*f, 1.0),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The minified rule: the family's default at a pixel per voxel and up, more phases as the
    /// view is minified (powers of two, never fewer for a smaller zoom), capped, and 2 for
    /// widths that are not positive numbers; an explicit request always wins.
    #[test]
    fn minified_views_get_finer_phases() {
        let axis = ([1.0, 0.0, 0.0], [0.0, -1.0, 0.0]);
        let oblique = ([0.6, 0.8, 0.0], [0.48, -0.36, -0.8]);
        let options = PlanOptions::default();
        for family in [Family::Haar, Family::Linear, Family::Cubic] {
            let default = PlanOptions::default_subpixel(family);
            for (ex, ey) in [axis, oblique] {
                assert_eq!(options.subpixel_for_view(family, 1.0, ex, ey), default);
                assert_eq!(options.subpixel_for_view(family, 40.0, ex, ey), default);
                let mut last = 0;
                for zoom in [2.0, 1.0, 0.5, 0.3, 0.2, 0.13, 0.05, 1e-3, 1e-9] {
                    let s = minified_subpixel(family, zoom, ex, ey);
                    assert!(s.is_power_of_two() && s >= last && s <= MAX_MINIFIED_SUBPIXEL);
                    last = s;
                }
                assert_eq!(last, MAX_MINIFIED_SUBPIXEL);
            }
            // The axis view's footprints are the narrower, so it never gets fewer phases.
            assert!(
                minified_subpixel(family, 0.2, axis.0, axis.1)
                    >= minified_subpixel(family, 0.2, oblique.0, oblique.1)
            );
            for zoom in [0.0, -1.0, f64::NAN, f64::INFINITY] {
                assert_eq!(minified_subpixel(family, zoom, axis.0, axis.1), 2, "{zoom}");
            }
            let asked = PlanOptions {
                subpixel: Some(2),
                ..PlanOptions::default()
            };
            assert_eq!(asked.subpixel_for_view(family, 0.01, axis.0, axis.1), 2);
        }
        // Linear axis views: 16 at 0.45 pixels per voxel (55 dB at 8), 32 at 0.13 (36 dB at 8).
        assert_eq!(minified_subpixel(Family::Linear, 0.45, axis.0, axis.1), 16);
        assert_eq!(minified_subpixel(Family::Linear, 0.13, axis.0, axis.1), 32);
    }

    /// The tabulated centres are `Geometry::basis_center`'s values, bit for bit, for every
    /// position of every band: odd, thin and margined grids, each family.
    #[test]
    fn centre_tables_equal_basis_centres() {
        for (dims, family, levels, margin) in [
            ([13, 8, 5], Family::Linear, 2, 3),
            ([1, 1, 1], Family::Haar, 0, 0),
            ([30, 23, 17], Family::Cubic, 2, 8),
            ([64, 4, 9], Family::Haar, 2, 0),
        ] {
            let g = Geometry::new(dims, family, levels, margin).unwrap();
            let centres = Centres::new(&g);
            for band in g.bands() {
                let bd = g.band_dims(band);
                for z in 0..bd[2] {
                    for y in 0..bd[1] {
                        for x in 0..bd[0] {
                            let pos = [x as u32, y as u32, z as u32];
                            let want = g.basis_center(band, [x, y, z]);
                            let got = centres.of(band, pos);
                            assert_eq!(got.map(f64::to_bits), want.map(f64::to_bits));
                        }
                    }
                }
            }
        }
    }
}
