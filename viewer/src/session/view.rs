//! View changes of a session: the plan of a new view (exact when its tables are at hand, else a
//! preview's while the exact one is built), a view being turned or settling, a replaced
//! backend, and the restart that queues everything held again for the current plan.

use super::bricks::Bricks;
use super::{RenderSession, SessionError, INITIAL_COST_PER_WEIGHT};
use crate::backend::AccumulationBackend;
use crate::plan::{Planner, ViewPlan};
use wavesplat_codec::layout::Geometry;
use wavesplat_codec::view::visibility::Visibility;
use wavesplat_codec::view::ViewSpec;

/// The exact plan of `spec` when its tables are cached, previews are off or the view is
/// depth-cued (its tables are built per piece on demand); otherwise the preview's plan.
/// Returns whether the plan is exact.
pub(super) fn plan_or_preview(
    planner: &mut Planner,
    preview: Option<&mut Planner>,
    geometry: &Geometry,
    spec: &ViewSpec,
    channels: usize,
) -> Result<(ViewPlan, bool), SessionError> {
    let resolved = planner.params(geometry, spec)?;
    match preview {
        Some(p) if resolved.cue.is_none() && !planner.is_cached(&resolved.footprints) => {
            Ok((p.plan(geometry, spec, channels)?, false))
        }
        _ => {
            let mut plan = planner.plan(geometry, spec, channels)?;
            // A cued (or clipped) view's tables are built per factor triple on first use, off
            // the frame thread, so a frame never waits for them; what waits for a cued table is
            // drawn meanwhile with the preview's uncued tables (cheap to build here).
            if plan.cue.is_some() || plan.clips() {
                plan.build_tables_in_background();
                if let Some(p) = preview {
                    let mut uncued = *spec;
                    uncued.view.cue = None;
                    if let Some(params) = p.params(geometry, &uncued)?.footprints.first() {
                        plan.set_stand_in_tables(&p.footprints(params));
                    }
                }
            }
            Ok((plan, true))
        }
    }
}

/// The first `plan_or_preview` of every brick (for a new session or a view change).
pub(super) fn plan_parts(
    bricks: &mut Bricks,
    planner: &mut Planner,
    mut preview: Option<&mut Planner>,
    spec: &ViewSpec,
    channels: usize,
) -> Result<bool, SessionError> {
    bricks.set_view(spec, &mut |g, s| {
        plan_or_preview(planner, preview.as_deref_mut(), g, s, channels)
    })
}

impl<B: AccumulationBackend> RenderSession<B> {
    /// Changes the view: restarts the accumulation and queues everything held again, largest
    /// visible energy first. Without exact tables at hand (and with previews on) the view is
    /// drawn with preview tables until the exact ones are built.
    pub fn set_view(&mut self, spec: ViewSpec) -> Result<(), SessionError> {
        self.turning = false;
        self.change_view(spec)
    }

    /// [`RenderSession::set_view`] for one step of a view being turned (a drag): drawn with
    /// the preview's tables, no exact tables built for it (the next step replaces it before
    /// they would arrive, and their build would take a core from the frames); until
    /// [`RenderSession::settle`] or the next [`RenderSession::set_view`].
    pub fn set_view_turning(&mut self, spec: ViewSpec) -> Result<(), SessionError> {
        self.turning = true;
        self.change_view(spec)
    }

    /// The view stopped turning: its exact tables are built from now on.
    pub fn settle(&mut self) {
        if std::mem::take(&mut self.turning) && !self.exact && self.building.is_none() {
            self.build_in_background(self.plan.spec);
        }
    }

    fn change_view(&mut self, spec: ViewSpec) -> Result<(), SessionError> {
        let (g, channels) = (self.header.geometry, self.header.channels);
        let (plan, exact) = match &mut self.bricks {
            None => {
                let visibility = Visibility::new(&self.header, &spec)?;
                let (plan, exact) = plan_or_preview(
                    &mut self.planner,
                    self.preview.as_mut(),
                    &g,
                    &spec,
                    channels,
                )?;
                self.visibility = Some(visibility);
                (plan, exact)
            }
            Some(b) => {
                // The whole's plan first: it checks the view before any brick is planned.
                let plan = self.planner.plan(&g, &spec, channels)?;
                let exact =
                    plan_parts(b, &mut self.planner, self.preview.as_mut(), &spec, channels)?;
                (plan, exact)
            }
        };
        if !exact {
            self.stats.previews += 1;
        }
        self.exact = exact;
        self.plan = plan;
        self.stats.view_changes += 1;
        self.restart()?;
        if !exact && self.building.is_none() && !self.turning {
            self.build_in_background(spec);
        }
        Ok(())
    }

    /// Replaces the accumulation backend (a window whose graphics device was lost opens a new
    /// one) and draws everything held again on it; returns the old backend. The running cost
    /// estimates start over: the new backend's speed is not the old one's.
    pub fn replace_backend(&mut self, backend: B) -> Result<B, SessionError> {
        let old = std::mem::replace(&mut self.backend, backend);
        self.cost = [INITIAL_COST_PER_WEIGHT; 2];
        self.measured = [false; 2];
        self.restart()?;
        Ok(old)
    }

    /// Whether the current view is drawn with its exact tables (not a preview).
    pub fn is_exact(&self) -> bool {
        self.exact
    }

    /// Restarts the accumulation of the current plan and queues everything held again.
    pub(super) fn restart(&mut self) -> Result<(), SessionError> {
        self.shown_preview = None;
        self.backend.begin(self.plan.layout())?;
        for plan in self.plans_mut() {
            plan.forget_stand_ins();
        }
        self.queue.clear();
        self.waiting.clear();
        self.stats.splatted_in_view = 0;
        self.stats.invisible_in_view = 0;
        let mut packets = std::mem::take(&mut self.packets);
        let (mut retained, mut transient) = (0, 0);
        for (id, held) in packets.iter_mut() {
            self.enqueue(*id, held);
            if held.queued == 0 {
                retained += held.bytes();
                // Invisible in this view: nothing of it waits any more.
                self.fresh_bytes -= held.settle();
            } else {
                transient += held.bytes();
            }
        }
        self.packets = packets;
        self.stats.retained_bytes = retained;
        self.stats.transient_bytes = transient;
        Ok(())
    }
}
