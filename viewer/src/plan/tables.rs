//! The tables a plan draws with beyond its footprint sets: cued factor tables built on a thread
//! of the plan's own while the coefficients that need them wait (each built once for all the
//! plans of one view that share a [`SharedFactorTables`]: a bricked volume's bricks), the
//! stand-ins drawn meanwhile with uncued tables (taken back when the real splat comes), and
//! which set each camera uses.

use super::splat::place;
use super::{TableKey, ViewPlan};
use crate::backend::{FootprintAtlas, SplatRecord, TableRef};
use crate::footprint::{AxisFactor, Footprint, FootprintSet};
use rustc_hash::FxHashMap as HashMap;
use rustc_hash::FxHashSet as HashSet;
use std::sync::mpsc::{channel, Receiver, Sender};
use std::sync::{Arc, Mutex, RwLock, Weak};
use wavesplat_codec::format::packet::Coefficient;

/// A factor table's key across plans: its footprint set (by address: the plans of one view take
/// their sets from one planner, and the store keeps each set alive, so an address names one
/// set) and its factor triple.
type SharedKey = (usize, [AxisFactor; 3]);

/// Factor tables shared by the plans of one view that draw with the same footprint sets (the
/// bricks of a bricked volume: their clipped pieces cut by faces at the same offsets need the
/// same tables). The first plan that misses a table has its builder build it; the others wait
/// for it here instead of building it again.
#[derive(Debug, Default)]
pub struct SharedFactorTables {
    inner: Mutex<SharedInner>,
}

#[derive(Debug, Default)]
struct SharedInner {
    built: HashMap<SharedKey, SharedTable>,
    requested: HashSet<SharedKey>,
    /// The sets named by address, kept alive while their address is a key.
    sets: HashMap<usize, Arc<FootprintSet>>,
}

/// A factor table built for one of the plans and where it was stored: a plan whose atlas is
/// that one takes the stored table instead of storing it again.
#[derive(Debug)]
struct SharedTable {
    footprint: Arc<Footprint>,
    stored: Weak<RwLock<FootprintAtlas>>,
    at: TableRef,
}

impl SharedFactorTables {
    fn lock(&self) -> std::sync::MutexGuard<'_, SharedInner> {
        // A plan that panicked while holding the lock left a consistent map (only inserts).
        self.inner.lock().unwrap_or_else(|e| e.into_inner())
    }
}

fn shared_key(set: &Arc<FootprintSet>, triple: [AxisFactor; 3]) -> SharedKey {
    (Arc::as_ptr(set) as usize, triple)
}

/// Builds cued tables on a thread of its own (a one-thread rayon pool, so its parallel loops
/// never queue ahead of the caller's splat batches on the global pool); ends when dropped.
#[derive(Debug)]
pub(super) struct TableBuilder {
    pub(super) requests: Sender<Vec<TableKey>>,
    results: Receiver<Vec<(TableKey, Arc<Footprint>)>>,
    /// Waited for and not yet received.
    pub(super) pending: HashSet<TableKey>,
    /// Of `pending`, those this builder was asked for (the rest another plan's builder makes).
    pub(super) asked: HashSet<TableKey>,
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
            asked: HashSet::default(),
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
        // What another plan's builder made for this plan's waiting coefficients.
        if let Some(shared) = &self.shared_tables {
            let shared = shared.lock();
            for &(set, triple) in &b.pending {
                if arrived.iter().any(|(k, _)| *k == (set, triple)) {
                    continue;
                }
                if let Some(t) = shared.built.get(&shared_key(&self.sets[set], triple)) {
                    arrived.push(((set, triple), t.footprint.clone()));
                }
            }
        }
        for (key, _) in &arrived {
            b.pending.remove(key);
            b.asked.remove(key);
        }
        let count = arrived.len();
        for ((set, triple), f) in arrived {
            self.install_table(set, triple, f);
        }
        count
    }

    /// Stores a factor table built for this plan and hands it to the plans sharing its tables.
    pub(super) fn install_table(&mut self, set: usize, triple: [AxisFactor; 3], f: Arc<Footprint>) {
        if self.factor_tables[set].contains_key(&triple) {
            return;
        }
        let key = shared_key(&self.sets[set], triple);
        let shared = self.shared_tables.clone();
        let mut shared = shared.as_ref().map(|s| s.lock());
        // Stored by a plan with this atlas already: taken, not stored twice.
        let stored = shared
            .as_ref()
            .and_then(|s| s.built.get(&key))
            .and_then(|t| {
                (t.stored
                    .upgrade()
                    .is_some_and(|a| Arc::ptr_eq(&a, &self.atlas)))
                .then_some(t.at)
            });
        let at = match stored {
            Some(at) => at,
            None => self.atlas_mut().push(&f),
        };
        self.factor_tables[set].insert(triple, at);
        if let Some(shared) = &mut shared {
            shared.sets.insert(key.0, self.sets[set].clone());
            shared.built.entry(key).or_insert(SharedTable {
                footprint: f,
                stored: Arc::downgrade(&self.atlas),
                at,
            });
        }
    }

    /// Takes factor tables from `shared` and builds each missing one there once for every plan
    /// sharing it (see [`SharedFactorTables`]); for the plans of one view drawn with the sets
    /// of one planner. Tables this plan waited for from the plans it shared with before are
    /// asked of its own builder now: the plan that was to build them may be gone.
    pub fn share_factor_tables(&mut self, shared: Arc<SharedFactorTables>) {
        if let Some(b) = &mut self.builder {
            let orphaned: Vec<TableKey> = b.pending.difference(&b.asked).copied().collect();
            if !orphaned.is_empty() {
                b.asked.extend(orphaned.iter().copied());
                let _ = b.requests.send(orphaned);
            }
        }
        self.shared_tables = Some(shared);
    }

    /// Of `missing` triples of set `set`: installs those the shared tables hold, and returns the
    /// rest, each with whether this plan is the one to request it (no other plan did).
    pub(super) fn take_shared(
        &mut self,
        set: usize,
        missing: Vec<[AxisFactor; 3]>,
    ) -> Vec<([AxisFactor; 3], bool)> {
        let Some(shared) = self.shared_tables.clone() else {
            return missing.into_iter().map(|t| (t, true)).collect();
        };
        let mut rest = Vec::new();
        let mut found = Vec::new();
        {
            let mut shared = shared.lock();
            for t in missing {
                let key = shared_key(&self.sets[set], t);
                match shared.built.get(&key) {
                    Some(table) => found.push((t, table.footprint.clone())),
                    None => {
                        let first = shared.requested.insert(key);
                        if first {
                            shared.sets.insert(key.0, self.sets[set].clone());
                        }
                        rest.push((t, first));
                    }
                }
            }
        }
        for (t, f) in found {
            if let Some(b) = &mut self.builder {
                b.pending.remove(&(set, t));
            }
            self.install_table(set, t, f);
        }
        rest
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
    pub(super) fn stand_ins(
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
        let shared_atlas = self.atlas.clone();
        let atlas = shared_atlas.read().unwrap_or_else(|e| e.into_inner());
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
                place(&t, &atlas, scr, value, c.channel as u16, 0, size, out);
            }
        }
    }

    /// Gives the plan the uncued tables of its view (any placement and phases: previews do) to
    /// draw stand-ins with while cued tables are built in the background.
    pub fn set_stand_in_tables(&mut self, set: &FootprintSet) {
        self.stand_in_tables = set
            .tables
            .iter()
            .map(|t| t.as_ref().map(|f| self.atlas_mut().push(f)))
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
    pub(super) fn set_of(&self, k: usize) -> (usize, bool) {
        if self.sets.len() == 1 {
            (0, k > 0)
        } else {
            (k, false)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::plan::{PlanOptions, Planner, RenderStats};
    use wavesplat_codec::dwt::decompose_channel;
    use wavesplat_codec::family::Family;
    use wavesplat_codec::layout::Geometry;
    use wavesplat_codec::view::{View, ViewSpec};

    /// A thin box with no margin (its pieces are clipped at the faces, so drawing it needs
    /// factor tables) and all its coefficients.
    fn clipped_box() -> (Geometry, Vec<Coefficient>) {
        let dims = [24, 20, 8];
        let g = Geometry::new(dims, Family::Linear, 3, 0).unwrap();
        assert!(g.clips_to_box());
        let data: Vec<f32> = (0..dims.iter().product::<usize>())
            .map(|i| 3.0 + ((i as f32) * 0.37).sin())
            .collect();
        (g, Coefficient::all_of(&g, 0, &decompose_channel(&data, &g)))
    }

    /// Two plans of `spec` from one planner sharing one set of factor tables (as a bricked
    /// volume's bricks do), and the planner.
    fn two_sharing_plans(g: &Geometry, spec: &ViewSpec) -> (ViewPlan, ViewPlan, Planner) {
        let mut planner = Planner::new(PlanOptions::default());
        let mut first = planner.plan(g, spec, 1).unwrap();
        let mut second = planner.plan(g, spec, 1).unwrap();
        let shared = Arc::new(SharedFactorTables::default());
        first.share_factor_tables(shared.clone());
        second.share_factor_tables(shared);
        (first, second, planner)
    }

    /// Plans of one view from one planner (a bricked volume's bricks) store their tables in
    /// one atlas; a plan of another view gets its own; a factor table built for one plan is
    /// taken by the others that share the tables, without being built or stored again, and the
    /// records are those a plan of its own makes.
    #[test]
    fn plans_of_one_view_share_their_atlas_and_factor_tables() {
        let (g, coefficients) = clipped_box();
        let spec = ViewSpec::single(View::new(0.4, 0.3, 96, 80));
        let (mut first, mut second, mut planner) = two_sharing_plans(&g, &spec);
        assert!(first.clips());
        assert!(first.shares_atlas_with(&second));
        let other = planner
            .plan(&g, &ViewSpec::single(View::new(1.1, 0.3, 96, 80)), 1)
            .unwrap();
        assert!(!other.shares_atlas_with(&first));

        let (mut a, mut b) = (Vec::new(), Vec::new());
        first
            .splats(&coefficients, &mut a, &mut RenderStats::default())
            .unwrap();
        let built = first.tables_built_inline();
        assert!(built > 0, "a clipped box needs factor tables");
        let stored = first.atlas().data.len();
        second
            .splats(&coefficients, &mut b, &mut RenderStats::default())
            .unwrap();
        assert_eq!(second.tables_built_inline(), 0);
        assert_eq!(second.atlas().data.len(), stored);
        assert_eq!(a, b);

        // A plan alone builds the same tables and draws the same records.
        let mut alone = Planner::new(PlanOptions::default())
            .plan(&g, &spec, 1)
            .unwrap();
        let mut c = Vec::new();
        alone
            .splats(&coefficients, &mut c, &mut RenderStats::default())
            .unwrap();
        assert_eq!(alone.tables_built_inline(), built);
        assert_eq!(a, c);
    }

    /// A plan waiting for a table another plan's builder was asked for still gets it when the
    /// sharing is replaced (as a new view's plans arrive): it asks its own builder then.
    #[test]
    fn a_table_waited_for_from_another_plan_comes_after_the_sharing_is_replaced() {
        let (g, coefficients) = clipped_box();
        let spec = ViewSpec::single(View::new(0.4, 0.3, 96, 80));
        let (mut first, mut second, _) = two_sharing_plans(&g, &spec);
        first.build_tables_in_background();
        second.build_tables_in_background();
        let mut out = Vec::new();
        first
            .splats(&coefficients, &mut out, &mut RenderStats::default())
            .unwrap();
        second
            .splats(&coefficients, &mut out, &mut RenderStats::default())
            .unwrap();
        assert!(second.tables_pending());
        // The plan that was asked is gone before it shared anything.
        drop(first);
        second.share_factor_tables(Arc::new(SharedFactorTables::default()));
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(60);
        while second.tables_pending() {
            second.poll_tables();
            assert!(std::time::Instant::now() < deadline, "tables never came");
            std::thread::sleep(std::time::Duration::from_millis(5));
        }
        assert!(!second.take_deferred().is_empty());
        // Every table is here now: nothing is left out of a batch.
        second
            .splats(&coefficients, &mut out, &mut RenderStats::default())
            .unwrap();
        assert!(second.take_deferred().is_empty());
        assert!(!second.tables_pending());
    }
}
