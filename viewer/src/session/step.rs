//! Steps of a session: queued coefficients splatted largest visible energy first within a time
//! budget, in batches sized by a running estimate of the cost per unit of splat weight (kept
//! apart for preview and exact tables), no batch but the first started past the deadline.

use super::{Clock, RenderSession, SessionError, StepReport, SystemClock};
use crate::backend::AccumulationBackend;
use crate::plan::RenderStats;
use std::time::Duration;

/// The relative cost of splatting a coefficient of `level` (1 = finest) at `zoom` pixels per
/// voxel: its footprint's area in pixels, which grows fourfold per level and with the square
/// of the zoom, plus a fixed part per coefficient (projection, binning, record).
pub fn splat_weight(level: u8, zoom: f64) -> f64 {
    let side = zoom.clamp(1e-3, 1e3) * 2f64.powi(i32::from(level.clamp(1, 16)) - 1);
    side * side + 1.0
}

impl<B: AccumulationBackend> RenderSession<B> {
    /// Splats queued coefficients for at most about `budget` (see [`RenderSession::step_with`]).
    pub fn step(&mut self, budget: Duration) -> Result<StepReport, SessionError> {
        self.step_with(budget, &SystemClock::default())
    }

    /// Splats queued coefficients, largest visible energy first, in batches sized to what is
    /// left of `budget` by the running cost estimate; no batch but the first starts after the
    /// deadline (a step draws when something is queued, a minimal batch if no time is left).
    pub fn step_with(
        &mut self,
        budget: Duration,
        clock: &dyn Clock,
    ) -> Result<StepReport, SessionError> {
        let start = clock.now();
        let deadline = start + budget;
        self.poll_exact()?;
        self.poll_cue_tables();
        let mut report = StepReport::default();
        let mut batch = Vec::new();
        let mut coefficients = Vec::new();
        let mut weights: Vec<f64> = Vec::new();
        while self.queue.len > 0 {
            // A new plan's tables reach the backend before the batch is sized and timed: the
            // upload takes from what is left of the budget instead of running past it, and
            // the running estimate measures splatting alone.
            self.backend.prepare(&self.plan.atlas())?;
            let now = clock.now();
            // The first batch runs whatever is left (a minimal one when nothing is): a step
            // always draws when something is queued.
            if now >= deadline && report.batches > 0 {
                break;
            }
            let left = deadline.saturating_sub(now).as_secs_f64();
            let kind = usize::from(self.exact);
            let packets = &self.packets;
            // Pixels per voxel (the footprint side of a finest coefficient): the zoom per unit
            // of spacing times the voxel's mean side.
            let zoom = self
                .plan
                .cameras
                .first()
                .map_or(1.0, |c| c.zoom * c.voxel_volume().cbrt());
            coefficients.clear();
            weights.clear();
            // Each popped entry's coefficient is looked up once: queued for the batch and
            // weighed for the allowance (the weight kept for the timing below).
            let (plan, bricks) = (&self.plan, self.bricks.as_ref());
            let take = |(p, i): (u32, u32)| {
                let c = packets[&p].coefficients[i as usize];
                coefficients.push(c);
                let plan = bricks.and_then(|b| b.plan_of(p)).unwrap_or(plan);
                let w = plan.weigh(&c, |level| splat_weight(level, zoom));
                weights.push(w);
                w
            };
            // Until a batch has been timed, one of `min_batch` coefficients: a guess would be
            // too long on a slow backend and too short on a fast one.
            let allowance = if self.measured[kind] {
                left / self.cost[kind].max(1e-15)
            } else {
                0.0
            };
            let weight = self.queue.pop_weighted(
                allowance,
                (self.options.min_batch.max(1), self.options.max_batch.max(1)),
                take,
                &mut batch,
            );
            let mut stats = RenderStats::default();
            // Coefficients whose cued tables are still being built wait (still queued) and are
            // drawn when the tables arrive.
            let (deferred, records) = if self.bricks.is_some() {
                self.draw_bricked(&batch, &coefficients, &mut stats)?
            } else {
                self.records.clear();
                self.plan
                    .splats(&coefficients, &mut self.records, &mut stats)?;
                self.backend.accumulate(&self.plan.atlas(), &self.records)?;
                (self.plan.take_deferred(), self.records.len())
            };
            // What waits was not drawn: its weight is not part of what was timed.
            let waiting_weight: f64 = deferred.iter().map(|&i| weights[i]).sum();
            let weight = (weight - waiting_weight).max(0.0);
            report.deferred += deferred.len();
            for &i in deferred.iter().rev() {
                self.waiting.push(batch.swap_remove(i));
            }
            for (p, _) in &batch {
                if let Some(h) = self.packets.get_mut(p) {
                    h.queued -= 1;
                    if h.queued == 0 {
                        let b = h.bytes();
                        self.stats.transient_bytes -= b;
                        self.stats.retained_bytes += b;
                        self.fresh_bytes -= h.settle();
                    }
                }
            }
            let end = clock.now();
            let per = if weight > 0.0 {
                (end.saturating_sub(now)).as_secs_f64() / weight
            } else {
                0.0
            };
            // Running estimate: quick to follow a slower backend, slower to trust a faster one.
            let c = &mut self.cost[kind];
            *c = if !self.measured[kind] {
                // A probe that drew nothing (all waiting for tables) measured nothing.
                self.measured[kind] = per > 0.0 && records > 0;
                if self.measured[kind] {
                    per
                } else {
                    *c
                }
            } else if per == 0.0 {
                *c
            } else if per > *c {
                0.5 * *c + 0.5 * per
            } else {
                0.8 * *c + 0.2 * per
            };
            self.stats.splatted_in_view += batch.len() as u64;
            report.coefficients += batch.len();
            report.records += records;
            report.batches += 1;
            if end > deadline {
                report.overran = true;
                break;
            }
        }
        self.evict();
        report.remaining = self.pending();
        report.elapsed = clock.now().saturating_sub(start);
        Ok(report)
    }
}
