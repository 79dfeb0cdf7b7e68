//! The tables a plan draws with beyond its footprint sets: cued factor tables built on a thread
//! of the plan's own while the coefficients that need them wait, the stand-ins drawn meanwhile
//! with uncued tables (taken back when the real splat comes), and which set each camera uses.

use super::splat::place;
use super::{TableKey, ViewPlan};
use crate::backend::SplatRecord;
use crate::footprint::{AxisFactor, Footprint, FootprintSet};
use rustc_hash::FxHashSet as HashSet;
use std::sync::mpsc::{channel, Receiver, Sender};
use std::sync::Arc;
use wavesplat_codec::format::packet::Coefficient;

/// Builds cued tables on a thread of its own (a one-thread rayon pool, so its parallel loops
/// never queue ahead of the caller's splat batches on the global pool); ends when dropped.
#[derive(Debug)]
pub(super) struct TableBuilder {
    pub(super) requests: Sender<Vec<TableKey>>,
    results: Receiver<Vec<(TableKey, Arc<Footprint>)>>,
    /// Requested and not yet received.
    pub(super) pending: HashSet<TableKey>,
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
    pub(super) fn set_of(&self, k: usize) -> (usize, bool) {
        if self.sets.len() == 1 {
            (0, k > 0)
        } else {
            (k, false)
        }
    }
}
