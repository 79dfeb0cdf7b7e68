//! The planner: a view spec resolved for a volume (cameras, depth cue, the parameters of its
//! footprint sets, one shared by the multiview cameras when the spacing allows) and planned into
//! a [`ViewPlan`], with the footprint sets cached per view.

use super::{Centres, Placement, PlanOptions, SharedAtlas, ViewPlan};
use crate::backend::{FootprintAtlas, TableRef};
use crate::footprint::{FootprintParams, FootprintSet};
use crate::pieces::{BoxClip, Expansions};
use crate::RenderError;
use rustc_hash::{FxHashMap as HashMap, FxHashSet as HashSet};
use std::sync::{Arc, RwLock, Weak};
use wavesplat_codec::layout::Geometry;
use wavesplat_codec::view::{resolve_cue, Camera, ResolvedCue, ViewSpec};

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
    /// Atlases of live plans by their footprint sets (weak: a plan dropped frees its atlas).
    atlases: Vec<AtlasBase>,
}

/// An atlas some live plans share and where the uncued tables of its sets are in it.
#[derive(Debug)]
struct AtlasBase {
    sets: Vec<Arc<FootprintSet>>,
    atlas: Weak<RwLock<FootprintAtlas>>,
    tables: Vec<Vec<Option<TableRef>>>,
}

impl Planner {
    /// A planner with the given options.
    pub fn new(options: PlanOptions) -> Planner {
        Planner {
            options,
            cache: Vec::new(),
            atlases: Vec::new(),
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

    /// The atlas holding `sets` and their tables in it: the atlas of a live plan made with the
    /// same sets (the bricks of a bricked volume in one view: one copy of the tables instead of
    /// one per brick), else a new one.
    fn atlas_for(
        &mut self,
        sets: &[Arc<FootprintSet>],
    ) -> (SharedAtlas, Vec<Vec<Option<TableRef>>>) {
        self.atlases.retain(|base| base.atlas.strong_count() > 0);
        let same = |base: &AtlasBase| {
            base.sets.len() == sets.len()
                && base.sets.iter().zip(sets).all(|(a, b)| Arc::ptr_eq(a, b))
        };
        if let Some(base) = self.atlases.iter().find(|b| same(b)) {
            if let Some(atlas) = base.atlas.upgrade() {
                return (atlas, base.tables.clone());
            }
        }
        let mut atlas = FootprintAtlas::new();
        atlas.reserve_for(sets.iter().flat_map(|set| set.tables.iter().flatten()));
        let tables: Vec<Vec<Option<TableRef>>> = sets
            .iter()
            .map(|set| {
                set.tables
                    .iter()
                    .map(|t| t.as_ref().map(|f| atlas.push(f)))
                    .collect()
            })
            .collect();
        let atlas = Arc::new(RwLock::new(atlas));
        self.atlases.push(AtlasBase {
            sets: sets.to_vec(),
            atlas: Arc::downgrade(&atlas),
            tables: tables.clone(),
        });
        (atlas, tables)
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
        let (atlas, tables) = self.atlas_for(&sets);
        Ok(ViewPlan {
            geometry: *geometry,
            spec: *spec,
            cameras,
            cue,
            channels,
            expansions: cue.map(|_| Expansions::new(geometry)),
            clip: (self.options.clip && geometry.splats_clip_to_box())
                .then(|| BoxClip::new(geometry)),
            factor_tables: vec![HashMap::default(); sets.len()],
            sets,
            atlas,
            tables,
            builder: None,
            shared_tables: None,
            deferred: Vec::new(),
            built_inline: 0,
            stood_in: HashSet::default(),
            stand_ins_drawn: 0,
            stand_in_tables: Vec::new(),
            centres: Centres::new(geometry),
        })
    }
}
