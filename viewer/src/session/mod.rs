//! The progressive render session: the engine that `wavesplat render` and `wavesplat view`
//! drive. It holds the volume's header, the coefficients received so far (grouped by packet)
//! and an accumulation image in some [`AccumulationBackend`].
//!
//! - **Adding packets** decodes them and queues their coefficients; rendering is linear, so only
//!   new coefficients are ever splatted onto the image.
//! - **Priority.** Queued coefficients are taken largest visible energy first: w²·‖basis‖² times
//!   the view's visibility weight of their band and tile (`codec::view::visibility`) times the
//!   channel's importance, bucketed by half-octaves (a bucket queue: O(1) per coefficient, no
//!   sort on the path of a rotation). Coefficients the view cannot see at all (off-screen tiles)
//!   are never queued.
//! - **A view change** restarts the accumulation and queues everything held again, so the next
//!   step draws the most important coefficients first: the image is coarse but correct at once
//!   and never blank for long.
//! - **New views at once.** Exact footprint tables for a view no planner cache holds take tens
//!   to hundreds of milliseconds (BENCHMARKS.md, issue 11), more than a frame. With
//!   [`SessionOptions::preview`] the session then draws with cheap preview tables (nearest
//!   phase, S = 2: a few milliseconds) while a background thread builds the exact ones; the
//!   next step after they arrive restarts the accumulation with them. An orbiting view is
//!   thus always drawn within its frame, and a resting one ends exact
//!   ([`RenderSession::is_exact`]). Depth-cued views build their tables per piece on demand and
//!   are planned exactly at once.
//! - **Steps** take a time budget and do as much as fits, in batches sized from a running
//!   estimate of the cost for this backend (planning + accumulation) per unit of footprint
//!   weight ([`splat_weight`]: a coefficient one level coarser, or seen at twice the zoom,
//!   covers four times the pixels),
//!   kept apart for preview and exact tables (their costs differ several-fold, and the first
//!   batch after a switch must not be sized by the other's); a step starts no batch after its
//!   deadline, so at most one batch ends past it.
//! - **Memory.** With a bound, retained coefficients beyond it are dropped, least visible energy
//!   per byte first, once they have been splatted (their contribution stays in the image); the
//!   dropped packet ids are handed to the source so the cache sends them again after a later
//!   view change. Decoded but not yet splatted coefficients are bounded separately
//!   ([`SessionOptions::transient_bytes`]). A bound of 0 is the paper's "network computer"
//!   (§4): the session then keeps only the footprint tables and the image.

mod bricks;
mod display;
mod eviction;
mod exact;
mod intake;
mod queue;
mod step;
mod view;

pub use bricks::{BrickedVolume, SessionBrick};
pub use step::splat_weight;

use crate::backend::gpu::ColorMap;
use crate::backend::{AccumulationBackend, BackendError, SplatRecord};
use crate::color;
use crate::image::Image;
use crate::plan::{PlanOptions, Planner, ViewPlan};
use crate::RenderError;
use queue::BucketQueue;
use std::collections::HashMap;
use std::sync::mpsc::Receiver;
use std::time::{Duration, Instant};
use thiserror::Error;
use view::plan_or_preview;
use wavesplat_codec::format::packet::Coefficient;
use wavesplat_codec::format::{FormatError, Header};
use wavesplat_codec::view::visibility::Visibility;
use wavesplat_codec::view::{ViewError, ViewSpec};

/// Bytes a held coefficient costs (what the memory bound counts).
pub const COEFFICIENT_BYTES: usize = std::mem::size_of::<Coefficient>();

/// Errors of a render session.
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum SessionError {
    /// Rendering failed (bad view, bad coefficient).
    #[error(transparent)]
    Render(#[from] RenderError),
    /// A packet does not decode.
    #[error("packet {id}: {source}")]
    Packet {
        /// Packet id.
        id: u32,
        /// Why.
        #[source]
        source: FormatError,
    },
    /// A bricked volume's bricks cannot share one session.
    #[error(transparent)]
    Volume(FormatError),
}

impl From<BackendError> for SessionError {
    fn from(e: BackendError) -> Self {
        SessionError::Render(RenderError::Backend(e))
    }
}

impl From<ViewError> for SessionError {
    fn from(e: ViewError) -> Self {
        SessionError::Render(RenderError::View(e))
    }
}

/// Session settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SessionOptions {
    /// Footprint planning.
    pub plan: PlanOptions,
    /// Largest retained coefficient memory in bytes (`None`: unbounded; `Some(0)`: keep
    /// nothing, the network computer).
    pub memory_bound: Option<usize>,
    /// Largest memory of newly taken coefficients waiting to be splatted: the session stops
    /// asking for packets beyond it (at least one packet is always accepted). Packets held
    /// from before a view change or a switch to exact tables, queued again to be drawn anew,
    /// do not count: they are in memory already, and counting them held back the rest of the
    /// stream until they were drawn again.
    pub transient_bytes: usize,
    /// Smallest batch (coefficients).
    pub min_batch: usize,
    /// Largest batch (coefficients).
    pub max_batch: usize,
    /// Planning for a new view while its exact tables are built in the background (`None`:
    /// plan exactly before drawing; see the module documentation).
    pub preview: Option<PlanOptions>,
}

impl SessionOptions {
    /// The preview planning a viewer uses while it turns: nearest phase, one phase (S = 1:
    /// placed to the nearest pixel), every coefficient one splat (no clipping to the box).
    /// Every frame of a drag plans a new view: at S = 2 a 512×288 image of the MRI took ~10 ms
    /// more a frame to plan (median drag frame 25–29 ms at 1920×1080 on two cores, 16.7 ms at
    /// S = 1).
    pub fn default_preview() -> PlanOptions {
        PlanOptions {
            placement: crate::plan::Placement::Nearest,
            subpixel: Some(1),
            // Each coefficient one splat: a preview never waits for factor tables.
            clip: false,
            ..PlanOptions::default()
        }
    }
}

impl Default for SessionOptions {
    fn default() -> Self {
        SessionOptions {
            plan: PlanOptions::default(),
            memory_bound: None,
            transient_bytes: 8 << 20,
            min_batch: 32,
            max_batch: 1 << 20,
            preview: None,
        }
    }
}

/// A monotonic clock (injectable, so the frame budget logic can be tested without sleeping).
pub trait Clock {
    /// Time since an arbitrary origin.
    fn now(&self) -> Duration;
}

/// The real clock.
#[derive(Debug, Clone, Copy)]
pub struct SystemClock(Instant);

impl Default for SystemClock {
    fn default() -> Self {
        SystemClock(Instant::now())
    }
}

impl Clock for SystemClock {
    fn now(&self) -> Duration {
        self.0.elapsed()
    }
}

/// What a step did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct StepReport {
    /// Coefficients taken from the queue.
    pub coefficients: usize,
    /// Coefficients set aside to wait for their factor tables (built in the background).
    pub deferred: usize,
    /// Splat records accumulated.
    pub records: usize,
    /// Batches run.
    pub batches: usize,
    /// Batches started after the deadline (always 0).
    pub started_late: usize,
    /// Whether the last batch ended past the deadline (at most one batch does).
    pub overran: bool,
    /// Coefficients still queued.
    pub remaining: usize,
    /// Time spent.
    pub elapsed: Duration,
}

/// Counters of a session.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct SessionStats {
    /// Packets received.
    pub packets_received: u64,
    /// Bytes of packets received.
    pub bytes_received: u64,
    /// Coefficients received.
    pub coefficients_received: u64,
    /// Packets held now.
    pub packets_held: usize,
    /// Coefficients held now (retained and waiting).
    pub coefficients_held: usize,
    /// Bytes of retained (already splatted) coefficients.
    pub retained_bytes: usize,
    /// Bytes of coefficients waiting to be splatted.
    pub transient_bytes: usize,
    /// Largest retained + transient bytes seen.
    pub peak_bytes: usize,
    /// Coefficients splatted since the view was set.
    pub splatted_in_view: u64,
    /// Coefficients the view cannot see (never queued) since the view was set.
    pub invisible_in_view: u64,
    /// Packets dropped to stay within the memory bound.
    pub packets_dropped: u64,
    /// View changes.
    pub view_changes: u64,
    /// Views drawn with preview tables first (their exact tables built in the background).
    pub previews: u64,
    /// Previews replaced by their exact tables: each restarts the image from the coefficients
    /// held, so packets dropped under the memory bound must be delivered again.
    pub exact_redraws: u64,
}

/// The first guess of the cost per unit of splat weight, before anything was measured (only
/// reported: the first batch with a new backend or tables is a probe of `min_batch`
/// coefficients, whose time becomes the estimate).
const INITIAL_COST_PER_WEIGHT: f64 = 2e-7;

/// One packet's coefficients.
#[derive(Debug)]
struct Held {
    tile: usize,
    coefficients: Vec<Coefficient>,
    /// Coefficients of this packet still queued in the current view.
    queued: usize,
    /// Size of the packet on the wire.
    wire_bytes: usize,
    /// Taken and not yet wholly splatted since (counted in `RenderSession::fresh_bytes`).
    fresh: bool,
    /// The visible energy of its coefficients in the current view (set as they are queued for
    /// it): what the memory bound drops the least of first, read there without going over
    /// every coefficient held again.
    visible: f64,
}

impl Held {
    fn bytes(&self) -> usize {
        self.coefficients.len() * COEFFICIENT_BYTES
    }

    /// Marks the packet as no longer waiting since it was taken; returns the bytes that leave
    /// `RenderSession::fresh_bytes` (0 when it was not fresh).
    fn settle(&mut self) -> usize {
        if std::mem::take(&mut self.fresh) {
            self.bytes()
        } else {
            0
        }
    }
}

/// A progressive render session over one volume (see the module documentation).
pub struct RenderSession<B: AccumulationBackend> {
    header: Header,
    options: SessionOptions,
    planner: Planner,
    plan: ViewPlan,
    /// Planner of previews (`None`: previews off).
    preview: Option<Planner>,
    /// Whether `plan` has the exact tables (false while a preview is shown).
    exact: bool,
    /// Exact tables being built on a background thread, and for which parameters.
    building: Option<Receiver<Result<exact::Plans, RenderError>>>,
    /// Whether the view is being turned ([`RenderSession::set_view_turning`]).
    turning: bool,
    /// The view's visibility weights (`None` for a bricked volume: each brick has its own).
    visibility: Option<Visibility>,
    backend: B,
    /// Basis norm² × importance per (channel, band index).
    energy_scale: Vec<f64>,
    /// The bricks of a bricked volume (`None`: one volume, drawn with `plan`).
    bricks: Option<bricks::Bricks>,
    packets: HashMap<u32, Held>,
    queue: BucketQueue,
    /// Queue entries set aside until the plan's background builder has their cued tables.
    waiting: Vec<(u32, u32)>,
    /// Per-pixel path lengths of the last displayed view (kept while the view stays).
    path_lengths: Option<color::PathLengths>,
    /// The display pass's colour map for those lengths (`Some(None)`: shown as accumulated;
    /// `None`: not made yet).
    device_colour: Option<Option<ColorMap>>,
    /// The preview's last image and how many coefficients it had drawn, shown after the exact
    /// tables arrived until they have drawn as many: a switch from preview to exact tables
    /// restarts the accumulation, which would otherwise dip to a coarser image for a few frames.
    shown_preview: Option<(Image, u64)>,
    dropped: Vec<u32>,
    /// Ids dropped before the exact tables last restarted the accumulation and not yet taken:
    /// that restart threw away the image they were drawn in, so the source must send them
    /// again (those dropped after it stay in the image, in `dropped`).
    dropped_before_redraw: Vec<u32>,
    stats: SessionStats,
    /// Bytes of the packets taken and not yet wholly splatted since (what
    /// [`SessionOptions::transient_bytes`] bounds).
    fresh_bytes: usize,
    /// Seconds per unit of splat weight (planning + accumulation), running estimates for
    /// preview (0) and exact (1) tables.
    cost: [f64; 2],
    /// Whether `cost` has been measured (per table kind, as `cost`).
    measured: [bool; 2],
    records: Vec<SplatRecord>,
    next_local_id: u32,
}

impl<B: AccumulationBackend> std::fmt::Debug for RenderSession<B> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RenderSession")
            .field("backend", &self.backend.name())
            .field("spec", &self.plan.spec)
            .field("stats", &self.stats)
            .finish()
    }
}

impl<B: AccumulationBackend> RenderSession<B> {
    /// A session for the volume of `header`, looking at `spec`, accumulating with `backend`.
    pub fn new(
        header: Header,
        spec: ViewSpec,
        backend: B,
        options: SessionOptions,
    ) -> Result<RenderSession<B>, SessionError> {
        RenderSession::build(header, spec, backend, options, None)
    }

    /// A session for `header`'s volume, or for the whole of `bricks` (`header` the whole's).
    fn build(
        header: Header,
        spec: ViewSpec,
        backend: B,
        options: SessionOptions,
        mut bricks: Option<bricks::Bricks>,
    ) -> Result<RenderSession<B>, SessionError> {
        let g = header.geometry;
        let mut planner = Planner::new(options.plan);
        let mut preview = options.preview.map(Planner::new);
        let (plan, exact, visibility) = match bricks.as_mut() {
            None => {
                let (plan, exact) =
                    plan_or_preview(&mut planner, preview.as_mut(), &g, &spec, header.channels)?;
                (plan, exact, Some(Visibility::new(&header, &spec)?))
            }
            Some(b) => {
                // The whole's plan holds the cameras, cue and layout the display uses; its
                // geometry has no transform, so it has no footprint worth a table.
                let plan = planner.plan(&g, &spec, header.channels)?;
                let exact =
                    view::plan_parts(b, &mut planner, preview.as_mut(), &spec, header.channels)?;
                (plan, exact, None)
            }
        };
        let energy_scale = bricks::energy_scale(&header);
        let mut s = RenderSession {
            header,
            options,
            planner,
            plan,
            preview,
            exact,
            building: None,
            turning: false,
            visibility,
            backend,
            energy_scale,
            bricks,
            packets: HashMap::new(),
            queue: BucketQueue::new(),
            waiting: Vec::new(),
            path_lengths: None,
            device_colour: None,
            shown_preview: None,
            dropped: Vec::new(),
            dropped_before_redraw: Vec::new(),
            stats: SessionStats::default(),
            fresh_bytes: 0,
            cost: [INITIAL_COST_PER_WEIGHT; 2],
            measured: [false; 2],
            records: Vec::new(),
            next_local_id: u32::MAX,
        };
        s.backend.begin(s.plan.layout())?;
        if !exact {
            s.stats.previews += 1;
            s.build_in_background(spec);
        }
        Ok(s)
    }

    /// The plans coefficients are drawn with: the view's, or those of the bricks it sees.
    fn plans_mut(&mut self) -> Vec<&mut ViewPlan> {
        match &mut self.bricks {
            None => vec![&mut self.plan],
            Some(b) => b.plans_mut().collect(),
        }
    }

    /// The header packet `id` decodes with: the volume's, or its brick's (`None`: a bricked
    /// volume has no packet of that id).
    fn header_of(&self, id: u32) -> Option<&Header> {
        match &self.bricks {
            None => Some(&self.header),
            Some(b) => b.part_of(id).map(|k| &b.parts[k].header),
        }
    }

    /// The volume's header (a bricked volume's: the whole's).
    pub fn header(&self) -> &Header {
        &self.header
    }

    /// The current view.
    pub fn spec(&self) -> &ViewSpec {
        &self.plan.spec
    }

    /// The resolved view (cameras, atlas).
    pub fn plan(&self) -> &ViewPlan {
        &self.plan
    }

    /// The backend's name.
    pub fn backend_name(&self) -> String {
        self.backend.name()
    }

    /// Counters.
    pub fn stats(&self) -> SessionStats {
        self.stats
    }

    /// Coefficients waiting to be splatted in this view (including those waiting for their
    /// depth-cue tables).
    pub fn pending(&self) -> usize {
        self.queue.len + self.waiting.len()
    }

    /// Of [`RenderSession::pending`], the coefficients set aside until their factor tables
    /// (depth-cued, or pieces clipped at the box's faces) are built in the background.
    pub fn waiting_for_tables(&self) -> usize {
        self.waiting.len()
    }

    /// The running estimate of the cost of one unit of [`splat_weight`] with the current
    /// tables (preview or exact).
    pub fn cost_per_weight(&self) -> Duration {
        Duration::from_secs_f64(self.cost[usize::from(self.exact)])
    }

    /// Whether the session takes another packet now (the transient budget is not used up).
    pub fn wants_packets(&self) -> bool {
        self.fresh_bytes < self.options.transient_bytes.max(1)
    }

    /// Whether the memory bound is full: what is retained has reached it.
    pub fn memory_full(&self) -> bool {
        self.options
            .memory_bound
            .is_some_and(|b| self.stats.retained_bytes + COEFFICIENT_BYTES > b)
    }

    /// Packet ids dropped since the last call (to tell the source, which asks for them again
    /// after a view change).
    pub fn take_dropped(&mut self) -> Vec<u32> {
        let mut ids = std::mem::take(&mut self.dropped_before_redraw);
        ids.append(&mut self.dropped);
        ids
    }

    /// Packet ids dropped (and not yet taken) before the exact tables last replaced a preview:
    /// that redraw started from what the session holds, so these are missing from the image
    /// until the source sends them again. Those dropped after it are left for
    /// [`RenderSession::take_dropped`]: they are in the image, and sending them again before
    /// the next view change would draw them twice.
    pub fn take_dropped_before_redraw(&mut self) -> Vec<u32> {
        std::mem::take(&mut self.dropped_before_redraw)
    }

    /// Whether packet `id` is held.
    pub fn holds(&self, id: u32) -> bool {
        self.packets.contains_key(&id)
    }

    /// Ids of the packets held.
    pub fn held_ids(&self) -> Vec<u32> {
        let mut v: Vec<u32> = self.packets.keys().copied().collect();
        v.sort_unstable();
        v
    }
}
