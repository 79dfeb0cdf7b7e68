//! The frame loop, headless: one [`FrameLoop::frame`] per displayed frame drains the packets
//! that arrived (as far as the session takes them, and in at most half the frame while there
//! is something to splat), reports dropped packets back to the source,
//! then splats as many coefficients as fit in what is left of the frame's budget, largest
//! visible energy first, from the session's running cost estimate. A view change restarts the
//! accumulation from the most important coefficients held and asks the source for the rest in
//! the new order. The window drives this loop frame by frame; [`FrameLoop::run_to_end`] runs it
//! until everything arrived is drawn (what `wavesplat render` does).
//!
//! Batches are planned to end by a share of the budget (the *fill*) that the loop corrects
//! after every frame that used its share: down by a fifth when the frame ran past its budget,
//! up by half a percent when it did not. At equilibrium about 0.5 / (20 + 0.5) ≈ 2.4 % of the
//! busy frames run past their budget, whatever the backend's cost noise, so the budget holds
//! at p95 where a fixed share holds only for the noise it was tuned to.

use crate::backend::AccumulationBackend;
use crate::session::{Clock, RenderSession, SessionError, StepReport, SystemClock};
use crate::source::{PacketSource, SourceStatus};
use std::time::{Duration, Instant};
use thiserror::Error;
use wavesplat_codec::view::ViewSpec;

/// How [`FrameLoop::run_to_end`] runs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RunToEnd {
    /// Each frame's budget.
    pub frame: Duration,
    /// Stop after this long even if more is to come (`None`: when the source is done and
    /// everything it sent is drawn with the exact tables).
    pub deadline: Option<Duration>,
    /// How long the source may stay unreachable before the run gives up (a restarting cache
    /// takes seconds; its stream resumes with what the viewer holds).
    pub patience: Duration,
}

/// What [`FrameLoop::run_to_end`] did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RunOutcome {
    /// Frames run.
    pub frames: u64,
    /// Time from the start of the run to its end.
    pub elapsed: Duration,
    /// Time from the start to the end of the first frame with anything splatted.
    pub first_image: Option<Duration>,
}

/// Why a run stopped before its end.
#[derive(Debug, Error)]
pub enum RunError {
    /// The session refused a packet or a step.
    #[error(transparent)]
    Session(#[from] SessionError),
    /// The source failed for good.
    #[error("{0}")]
    SourceFailed(String),
    /// The source stayed unreachable longer than the run's patience.
    #[error("the source has been unreachable for {} s: {problem}", .patience.as_secs())]
    Unreachable {
        /// The patience that ran out.
        patience: Duration,
        /// The source's last problem.
        problem: String,
    },
}

/// What one frame did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct FrameReport {
    /// Packets taken from the source.
    pub packets: usize,
    /// Coefficients splatted.
    pub coefficients: usize,
    /// Coefficients set aside to wait for their factor tables (built in the background).
    pub deferred: usize,
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

    /// Whether the frame drew anything new (took packets or splatted coefficients).
    pub fn changed_image(&self) -> bool {
        self.coefficients > 0 || self.packets > 0
    }

    /// This frame and `next`, run after it, as one: their work added up, the state at the end
    /// (`pending`, `exact`) `next`'s.
    pub fn followed_by(&self, next: &FrameReport) -> FrameReport {
        FrameReport {
            packets: self.packets + next.packets,
            coefficients: self.coefficients + next.coefficients,
            deferred: self.deferred + next.deferred,
            records: self.records + next.records,
            batches: self.batches + next.batches,
            batches_past_deadline: self.batches_past_deadline + next.batches_past_deadline,
            elapsed: self.elapsed + next.elapsed,
            ..*next
        }
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
    /// Whether the session dropped packets (memory bound) since the source last ranked.
    dropped_since_rank: bool,
    /// The session's [`SessionStats::exact_redraws`] when last looked at.
    exact_redraws: u64,
}

impl<B: AccumulationBackend, S: PacketSource> FrameLoop<B, S> {
    /// Drives `session` with packets from `source`.
    pub fn new(session: RenderSession<B>, source: S) -> FrameLoop<B, S> {
        FrameLoop {
            session,
            source,
            fill: FILL_START,
            dropped_since_rank: false,
            exact_redraws: 0,
        }
    }

    /// The share of the budget the next frame's batches are planned to fill.
    pub fn fill(&self) -> f64 {
        self.fill
    }

    /// After a frame that `report` describes: when only the background planner has work (the
    /// preview is drawn, nothing queued, no packets), waits for it up to `timeout` instead of
    /// letting the caller spin on a core the planner needs.
    pub fn wait_if_only_planning(
        &mut self,
        report: &FrameReport,
        timeout: Duration,
    ) -> Result<(), SessionError> {
        if report.pending == 0 && report.packets == 0 && !report.exact {
            self.session.wait_exact(timeout)?;
            self.after_exact_redraw();
        }
        Ok(())
    }

    /// Changes the view (session first: it validates; then the source reorders).
    pub fn set_view(&mut self, spec: ViewSpec) -> Result<(), SessionError> {
        self.session.set_view(spec)?;
        self.after_view_change(&spec);
        Ok(())
    }

    /// [`FrameLoop::set_view`] for one step of a drag ([`RenderSession::set_view_turning`]).
    pub fn set_view_turning(&mut self, spec: ViewSpec) -> Result<(), SessionError> {
        self.session.set_view_turning(spec)?;
        self.after_view_change(&spec);
        Ok(())
    }

    /// The view stopped turning ([`RenderSession::settle`]).
    pub fn settle(&mut self) {
        self.session.settle();
    }

    fn after_view_change(&mut self, spec: &ViewSpec) {
        let dropped = self.session.take_dropped();
        self.rank_again(dropped, spec);
        self.exact_redraws = self.session.stats().exact_redraws;
    }

    /// Hands `dropped` to the source and has it rank what it has not delivered (those
    /// included) for `spec`.
    fn rank_again(&mut self, dropped: Vec<u32>, spec: &ViewSpec) {
        self.source.dropped(dropped);
        self.source.set_view(spec);
        self.dropped_since_rank = false;
    }

    /// Hands the session's dropped packets to the source.
    fn pass_dropped(&mut self) {
        let dropped = self.session.take_dropped();
        if !dropped.is_empty() {
            self.dropped_since_rank = true;
            self.source.dropped(dropped);
        }
    }

    /// After the exact tables replaced a preview, the image is drawn again from what the
    /// session holds: packets it dropped under the memory bound before that redraw are asked
    /// for again, as after a view change (else a bound below the volume's coefficients left
    /// the image blank). Those dropped after it are drawn already and wait for a later view
    /// change (sent again now, they would be drawn twice).
    fn after_exact_redraw(&mut self) {
        let redraws = self.session.stats().exact_redraws;
        if redraws != self.exact_redraws {
            self.exact_redraws = redraws;
            let lost = self.session.take_dropped_before_redraw();
            if self.dropped_since_rank || !lost.is_empty() {
                let spec = *self.session.spec();
                self.rank_again(lost, &spec);
            }
        }
    }

    /// One frame of at most about `budget` with the real clock.
    pub fn frame(&mut self, budget: Duration) -> Result<FrameReport, SessionError> {
        self.frame_with(budget, &SystemClock::default())
    }

    /// One frame: drain arrived packets, then splat until the deadline (no batch starts after
    /// it, so at most one ends past it; a frame that has splatted nothing by then splats one
    /// batch, so that every frame with something queued draws).
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
        self.after_exact_redraw();
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
            self.pass_dropped();
            let now = clock.now();
            // Past the deadline a frame still splats once if it has splatted nothing: taking a
            // packet (5–13 ms to decode) can outlast a short frame, and frames that each take
            // one and stop would leave the image blank however many of them run.
            let late = now >= splat_deadline;
            if self.session.pending() == 0 || (late && report.coefficients > 0) {
                break;
            }
            let step: StepReport = self
                .session
                .step_with(splat_deadline.saturating_sub(now), clock)?;
            report.coefficients += step.coefficients;
            report.deferred += step.deferred;
            report.records += step.records;
            report.batches += step.batches;
            report.batches_past_deadline += usize::from(step.overran);
            self.after_exact_redraw();
            if late || step.overran || clock.now() >= splat_deadline {
                break;
            }
        }
        self.pass_dropped();
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

    /// Runs frames until the source is done and everything it sent is drawn with the exact
    /// tables (or `run.deadline`), calling `on_frame` after each with the frame's number
    /// (from 1), its report and the time since the run started. A frame with nothing to splat
    /// waits for the background planner (up to a frame) or the network (2 ms) instead of
    /// spinning on a core they need.
    pub fn run_to_end<E: From<RunError>>(
        &mut self,
        run: &RunToEnd,
        mut on_frame: impl FnMut(&mut Self, u64, &FrameReport, Duration) -> Result<(), E>,
    ) -> Result<RunOutcome, E> {
        let start = Instant::now();
        let mut outcome = RunOutcome {
            frames: 0,
            elapsed: Duration::ZERO,
            first_image: None,
        };
        let mut unreachable_since: Option<Instant> = None;
        loop {
            let report = self.frame(run.frame).map_err(RunError::from)?;
            outcome.frames += 1;
            if outcome.first_image.is_none() && self.session.stats().splatted_in_view > 0 {
                outcome.first_image = Some(start.elapsed());
            }
            on_frame(self, outcome.frames, &report, start.elapsed())?;
            let status = self.source_status();
            if let Some(f) = status.failed {
                return Err(RunError::SourceFailed(f).into());
            }
            if run.deadline.is_some_and(|d| start.elapsed() >= d) {
                break;
            }
            self.wait_if_only_planning(&report, run.frame)
                .map_err(RunError::from)?;
            if report.idle() {
                if status.done {
                    break;
                }
                if status.connected {
                    unreachable_since = None;
                } else if unreachable_since.get_or_insert_with(Instant::now).elapsed()
                    > run.patience
                {
                    return Err(RunError::Unreachable {
                        patience: run.patience,
                        problem: status.problem.unwrap_or_default(),
                    }
                    .into());
                }
                std::thread::sleep(Duration::from_millis(2));
            } else {
                unreachable_since = None;
            }
        }
        outcome.elapsed = start.elapsed();
        Ok(outcome)
    }

    /// The source's status.
    pub fn source_status(&self) -> SourceStatus {
        self.source.status()
    }
}
