//! The frame loop, headless: one [`FrameLoop::frame`] per displayed frame drains the packets
//! that arrived (as far as the session takes them, and in at most half the frame while there
//! is something to splat), reports dropped packets back to the source,
//! then splats as many coefficients as fit in what is left of the frame's budget, largest
//! visible energy first, from the session's running cost estimate. A view change restarts the
//! accumulation from the most important coefficients held and asks the source for the rest in
//! the new order. The window and `wavesplat render` both drive this loop.
//!
//! Batches are planned to end by a share of the budget (the *fill*) that the loop corrects
//! after every frame that used its share: down by a fifth when the frame ran past its budget,
//! up by half a percent when it did not. At equilibrium about 0.5 / (20 + 0.5) ≈ 2.4 % of the
//! busy frames run past their budget, whatever the backend's cost noise, so the budget holds
//! at p95 where a fixed share holds only for the noise it was tuned to.

use crate::backend::AccumulationBackend;
use crate::session::{Clock, RenderSession, SessionError, StepReport, SystemClock};
use crate::source::{PacketSource, SourceStatus};
use std::time::Duration;
use wavesplat_codec::view::ViewSpec;

/// What one frame did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct FrameReport {
    /// Packets taken from the source.
    pub packets: usize,
    /// Coefficients splatted.
    pub coefficients: usize,
    /// Splat records accumulated.
    pub records: usize,
    /// Batches run.
    pub batches: usize,
    /// Batches that ended past the deadline (at most 1).
    pub batches_past_deadline: usize,
    /// Coefficients still queued at the end of the frame.
    pub pending: usize,
    /// Whether the view is drawn with its exact tables (false while a preview is shown).
    pub exact: bool,
    /// Time the frame took.
    pub elapsed: Duration,
}

impl FrameReport {
    /// Whether the frame had nothing left to do (everything held is splatted with the view's
    /// exact tables).
    pub fn idle(&self) -> bool {
        self.pending == 0 && self.packets == 0 && self.exact
    }
}

/// The fill a loop starts with: batches planned to end by 85 % of the budget.
const FILL_START: f64 = 0.85;
/// The fill's bounds: at least 30 % of a frame splats, at most 95 % is planned.
const FILL_RANGE: (f64, f64) = (0.3, 0.95);
/// The fill's correction after a frame past its budget, and after a busy frame within it.
const FILL_DOWN: f64 = 0.8;
const FILL_UP: f64 = 1.005;

/// A session and its packet source, driven frame by frame.
#[derive(Debug)]
pub struct FrameLoop<B: AccumulationBackend, S: PacketSource> {
    /// The render session.
    pub session: RenderSession<B>,
    /// The packet source.
    pub source: S,
    /// The share of the budget the next frame's batches are planned to fill.
    fill: f64,
}

impl<B: AccumulationBackend, S: PacketSource> FrameLoop<B, S> {
    /// Drives `session` with packets from `source`.
    pub fn new(session: RenderSession<B>, source: S) -> FrameLoop<B, S> {
        FrameLoop {
            session,
            source,
            fill: FILL_START,
        }
    }

    /// The share of the budget the next frame's batches are planned to fill.
    pub fn fill(&self) -> f64 {
        self.fill
    }

    /// Changes the view (session first: it validates; then the source reorders).
    pub fn set_view(&mut self, spec: ViewSpec) -> Result<(), SessionError> {
        self.session.set_view(spec)?;
        let dropped = self.session.take_dropped();
        self.source.dropped(dropped);
        self.source.set_view(&spec);
        Ok(())
    }

    /// One frame of at most about `budget` with the real clock.
    pub fn frame(&mut self, budget: Duration) -> Result<FrameReport, SessionError> {
        self.frame_with(budget, &SystemClock::default())
    }

    /// One frame: drain arrived packets, then splat until the deadline (no batch starts after
    /// it, so at most one ends past it).
    pub fn frame_with(
        &mut self,
        budget: Duration,
        clock: &dyn Clock,
    ) -> Result<FrameReport, SessionError> {
        let start = clock.now();
        // Batches are sized to end by the fill's share of the budget: a batch's cost is
        // predicted from a running estimate, and the margin absorbs its error so the frame
        // itself ends in time (no batch still starts after the full budget).
        let deadline = start + budget;
        let splat_deadline = start + budget.mul_f64(self.fill);
        let mut report = FrameReport::default();
        self.session.poll_exact()?;
        // Taking packets (decoding them) may use at most half of the frame while there is
        // something to splat: the image keeps refining (and is never left blank after a view
        // change) while a burst of packets arrives.
        let intake_until = start + budget / 2;
        loop {
            // The limit is checked before each packet: once anything is queued, taking more
            // stops at half the frame, so a first frame whose packets are slow to take (a
            // file's, decoded here, 5–13 ms each) still splats the first of them.
            while self.session.wants_packets() {
                let until = if self.session.pending() == 0 {
                    splat_deadline
                } else {
                    intake_until.min(splat_deadline)
                };
                if clock.now() >= until {
                    break;
                }
                let Some(p) = self.source.try_next() else {
                    break;
                };
                self.session.add_from_source(p)?;
                report.packets += 1;
            }
            let dropped = self.session.take_dropped();
            if !dropped.is_empty() {
                self.source.dropped(dropped);
            }
            let now = clock.now();
            if self.session.pending() == 0 || now >= splat_deadline {
                break;
            }
            let step: StepReport = self.session.step_with(splat_deadline - now, clock)?;
            report.coefficients += step.coefficients;
            report.records += step.records;
            report.batches += step.batches;
            report.batches_past_deadline += usize::from(step.overran);
            if step.overran || clock.now() >= splat_deadline {
                break;
            }
        }
        let dropped = self.session.take_dropped();
        if !dropped.is_empty() {
            self.source.dropped(dropped);
        }
        report.pending = self.session.pending();
        report.exact = self.session.is_exact();
        let end = clock.now();
        report.elapsed = end.saturating_sub(start);
        // Correct the fill by the frames that used their share (idle frames say nothing of
        // what the work costs).
        if end > deadline {
            self.fill *= FILL_DOWN;
        } else if end >= splat_deadline {
            self.fill *= FILL_UP;
        }
        self.fill = self.fill.clamp(FILL_RANGE.0, FILL_RANGE.1);
        Ok(report)
    }

    /// The source's status.
    pub fn source_status(&self) -> SourceStatus {
        self.source.status()
    }
}
