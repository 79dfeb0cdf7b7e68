//! Exact tables in the background: a view drawn with preview tables has its exact plan built on
//! a thread of its own (a one-thread pool, off the frame thread's), and the session installs it
//! when it arrives, keeping the preview's last image on screen until the exact tables catch up.

use super::{RenderSession, SessionError};
use crate::backend::AccumulationBackend;
use crate::plan::{Planner, ViewPlan};
use crate::RenderError;
use std::sync::mpsc::TryRecvError;
use std::time::Duration;
use wavesplat_codec::view::ViewSpec;

impl<B: AccumulationBackend> RenderSession<B> {
    /// Plans `spec` exactly on a background thread: the footprint tables and the atlas the
    /// backend reads (copying tables into an atlas is itself too long for a frame).
    pub(super) fn build_in_background(&mut self, spec: ViewSpec) {
        // A bricked volume's bricks are placed here (cheap); a view that cannot be placed is
        // planned on the frame thread when the builder reports back, which reports the error.
        let parts = match &self.bricks {
            None => Ok(Vec::new()),
            Some(b) => b.jobs(&spec),
        };
        let (tx, rx) = std::sync::mpsc::channel();
        let (options, geometry, channels) = (
            *self.planner.options(),
            self.header.geometry,
            self.header.channels,
        );
        std::thread::spawn(move || {
            // Planning runs parallel loops; on rayon's global pool they would queue ahead of
            // the frame thread's splat batches and stall frames (on two cores, for the whole
            // build). A one-thread pool of its own keeps the global pool free for splatting.
            let plan_it = || -> Result<Plans, RenderError> {
                let mut planner = Planner::new(options);
                let whole = planner.plan(&geometry, &spec, channels)?;
                let parts = parts?
                    .iter()
                    .map(|job| {
                        job.as_ref()
                            .map(|(g, frame)| {
                                let plan = planner.plan(g, &frame.spec, channels)?;
                                Ok::<_, RenderError>(super::bricks::in_frame(plan, frame))
                            })
                            .transpose()
                    })
                    .collect::<Result<_, _>>()?;
                Ok(Plans { whole, parts })
            };
            let plan = match rayon::ThreadPoolBuilder::new()
                .num_threads(1)
                .thread_name(|_| "wavesplat-planner".into())
                .build()
            {
                Ok(pool) => pool.install(plan_it),
                Err(_) => plan_it(),
            };
            // The receiver may be gone (session dropped): nothing to do then.
            let _ = tx.send(plan);
        });
        self.building = Some(rx);
    }

    /// Takes an exact plan the background thread finished: installs it when it is for the
    /// current view (restarting the accumulation), keeps its tables for later otherwise and
    /// starts on the current view. Every step does this; call it between steps when nothing is
    /// queued.
    pub fn poll_exact(&mut self) -> Result<(), SessionError> {
        self.take_exact(None)
    }

    /// Like [`RenderSession::poll_exact`], but waits up to `timeout` for the exact plan being
    /// built: a caller with nothing else to do (a preview fully drawn, no packets) blocks here
    /// instead of spinning on a core the builder needs.
    pub fn wait_exact(&mut self, timeout: Duration) -> Result<(), SessionError> {
        self.take_exact(Some(timeout))
    }

    fn take_exact(&mut self, wait: Option<Duration>) -> Result<(), SessionError> {
        use std::sync::mpsc::RecvTimeoutError;
        let arrived = match (&self.building, wait) {
            (None, _) => return Ok(()),
            (Some(rx), None) => match rx.try_recv() {
                Ok(plan) => Some(plan),
                Err(TryRecvError::Empty) => return Ok(()),
                // The builder thread died (it panicked): plan exactly here instead.
                Err(TryRecvError::Disconnected) => None,
            },
            (Some(rx), Some(timeout)) => match rx.recv_timeout(timeout) {
                Ok(plan) => Some(plan),
                Err(RecvTimeoutError::Timeout) => return Ok(()),
                Err(RecvTimeoutError::Disconnected) => None,
            },
        };
        self.building = None;
        let plans = match arrived {
            Some(Ok(plans)) => {
                for set in std::iter::once(&plans.whole)
                    .chain(plans.parts.iter().flatten())
                    .flat_map(ViewPlan::footprint_sets)
                {
                    self.planner.insert(set);
                }
                Some(plans)
            }
            // Planning the view failed there: plan here, which reports the error.
            Some(Err(_)) | None => None,
        };
        if self.exact {
            return Ok(());
        }
        let spec = self.plan.spec;
        match plans {
            Some(plans) if plans.whole.spec == spec => {
                self.plan = plans.whole;
                if let Some(b) = &mut self.bricks {
                    for (part, plan) in b.parts.iter_mut().zip(plans.parts) {
                        if let (Some(view), Some(plan)) = (part.view.as_mut(), plan) {
                            view.plan = plan;
                        }
                    }
                    b.share_tables();
                }
            }
            Some(_) => {
                if !self.turning {
                    self.build_in_background(spec);
                }
                return Ok(());
            }
            None => {
                let (g, channels) = (self.header.geometry, self.header.channels);
                self.plan = self.planner.plan(&g, &spec, channels)?;
                if let Some(b) = &mut self.bricks {
                    let planner = &mut self.planner;
                    b.set_view(&spec, &mut |g, s| Ok((planner.plan(g, s, channels)?, true)))?;
                }
            }
        }
        // A clipped view's pieces need factor tables: built off the frame thread, as in
        // `plan_or_preview` (a cued view never comes through a preview).
        for plan in self.plans_mut() {
            if plan.clips() {
                plan.build_tables_in_background();
            }
        }
        // What the preview shows now (the backend still holds it; the exact plan has the same
        // cameras) stays on screen until the exact tables catch up.
        let preview = match self.stats.splatted_in_view {
            0 => None,
            n => Some((self.image()?, n)),
        };
        self.exact = true;
        self.restart()?;
        let mut lost = std::mem::take(&mut self.dropped);
        self.dropped_before_redraw.append(&mut lost);
        self.stats.exact_redraws += 1;
        self.shown_preview = preview;
        Ok(())
    }
}

/// What the background builder plans: the whole's plan and, for a bricked volume, every
/// brick's (`None` for a brick off the image).
pub(super) struct Plans {
    pub(super) whole: ViewPlan,
    pub(super) parts: Vec<Option<ViewPlan>>,
}
