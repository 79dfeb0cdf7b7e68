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

use crate::backend::gpu::{ColorMap, DisplayOptions};
use crate::backend::{AccumulationBackend, BackendError, SplatRecord};
use crate::color;
use crate::image::Image;
use crate::plan::{PlanOptions, Planner, RenderStats, ViewPlan};
use crate::source::SourcePacket;
use crate::RenderError;
use std::collections::HashMap;
use std::sync::mpsc::{Receiver, TryRecvError};
use std::time::{Duration, Instant};
use thiserror::Error;
use wavesplat_codec::format::packet::{decode_packet, Coefficient};
use wavesplat_codec::format::{FormatError, Header};
use wavesplat_codec::layout::{Band, Geometry};
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
}

/// Bucket queue: half-octaves of visible energy.
const BUCKETS: usize = 4400;
const BUCKET_OFFSET: i64 = 2200;

#[derive(Debug, Default)]
struct BucketQueue {
    buckets: Vec<Vec<(u32, u32)>>,
    top: usize,
    len: usize,
}

impl BucketQueue {
    fn new() -> BucketQueue {
        BucketQueue {
            buckets: vec![Vec::new(); BUCKETS],
            top: 0,
            len: 0,
        }
    }

    fn clear(&mut self) {
        for b in &mut self.buckets[..=self.top] {
            b.clear();
        }
        self.top = 0;
        self.len = 0;
    }

    fn push(&mut self, bucket: usize, entry: (u32, u32)) {
        self.buckets[bucket].push(entry);
        self.top = self.top.max(bucket);
        self.len += 1;
    }

    /// Entries, highest buckets first, until their summed `weight` reaches `allowance` (at
    /// least `min` entries, at most `max`); returns the weight taken.
    fn pop_weighted(
        &mut self,
        allowance: f64,
        (min, max): (usize, usize),
        mut weight: impl FnMut((u32, u32)) -> f64,
        out: &mut Vec<(u32, u32)>,
    ) -> f64 {
        out.clear();
        let mut taken = 0.0;
        while self.len > 0 && out.len() < max && (out.len() < min || taken < allowance) {
            let b = &mut self.buckets[self.top];
            if let Some(e) = b.pop() {
                taken += weight(e);
                out.push(e);
                self.len -= 1;
            }
            if b.is_empty() && self.top > 0 {
                while self.top > 0 && self.buckets[self.top].is_empty() {
                    self.top -= 1;
                }
            }
        }
        taken
    }
}

/// The first guess of the cost per unit of splat weight, before anything was measured (only
/// reported: the first batch with a new backend or tables is a probe of `min_batch`
/// coefficients, whose time becomes the estimate).
const INITIAL_COST_PER_WEIGHT: f64 = 2e-7;

/// The relative cost of splatting a coefficient of `level` (1 = finest) at `zoom` pixels per
/// voxel: its footprint's area in pixels, which grows fourfold per level and with the square
/// of the zoom, plus a fixed part per coefficient (projection, binning, record).
pub fn splat_weight(level: u8, zoom: f64) -> f64 {
    let side = zoom.clamp(1e-3, 1e3) * 2f64.powi(i32::from(level.clamp(1, 16)) - 1);
    side * side + 1.0
}

/// A coefficient's visible energy from its squared value and its band's (energy scale,
/// visibility weight), multiplied in that order.
#[inline]
fn energy(c: &Coefficient, (scale, weight): (f64, f64)) -> f64 {
    let v = c.value as f64;
    v * v * scale * weight
}

/// The queue bucket of a visible energy; `None` when the view cannot see it.
#[inline]
fn bucket_of(energy: f64) -> Option<usize> {
    if energy.is_nan() || energy <= 0.0 {
        return None;
    }
    if energy.is_infinite() {
        return Some(BUCKETS - 1);
    }
    Some((half_octave(energy) + BUCKET_OFFSET).clamp(0, BUCKETS as i64 - 1) as usize)
}

/// ⌊2·log2 x⌋ of a positive finite `x`, from its bits: twice the binary exponent, plus one
/// when the mantissa is at least √2. Requeuing a view's coefficients takes one per coefficient,
/// and `log2` and `floor` are library calls on the baseline x86-64 target (they were 40 % of a
/// 565 k-coefficient requeue). Subnormals take the `log2` path.
#[inline]
fn half_octave(x: f64) -> i64 {
    let bits = x.to_bits();
    let biased = ((bits >> 52) & 0x7ff) as i64;
    if biased == 0 {
        return (2.0 * x.log2()).floor() as i64;
    }
    let mantissa = f64::from_bits((bits & ((1u64 << 52) - 1)) | (1023u64 << 52));
    2 * (biased - 1023) + i64::from(mantissa >= std::f64::consts::SQRT_2)
}

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

/// The exact plan of `spec` when its tables are cached, previews are off or the view is
/// depth-cued (its tables are built per piece on demand); otherwise the preview's plan.
/// Returns whether the plan is exact.
fn plan_or_preview(
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
    building: Option<Receiver<Result<ViewPlan, RenderError>>>,
    /// Whether the view is being turned ([`RenderSession::set_view_turning`]).
    turning: bool,
    visibility: Visibility,
    backend: B,
    /// Basis norm² × importance per (channel, band index).
    energy_scale: Vec<f64>,
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
        let g = header.geometry;
        let mut planner = Planner::new(options.plan);
        let mut preview = options.preview.map(Planner::new);
        let (plan, exact) =
            plan_or_preview(&mut planner, preview.as_mut(), &g, &spec, header.channels)?;
        let visibility = Visibility::new(&header, &spec)?;
        let bands = g.bands();
        let energy_scale = (0..header.channels)
            .flat_map(|c| {
                let importance = header.importance(c);
                bands
                    .iter()
                    .map(move |b| g.basis_norm2(*b) * importance)
                    .collect::<Vec<_>>()
            })
            .collect();
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
            packets: HashMap::new(),
            queue: BucketQueue::new(),
            waiting: Vec::new(),
            path_lengths: None,
            device_colour: None,
            shown_preview: None,
            dropped: Vec::new(),
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

    /// The volume's header.
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
        std::mem::take(&mut self.dropped)
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

    /// Decodes and queues a packet (a packet already held is ignored).
    pub fn add_packet(&mut self, id: u32, bytes: &[u8]) -> Result<(), SessionError> {
        if self.packets.contains_key(&id) {
            return Ok(());
        }
        let d = decode_packet(&self.header, bytes)
            .map_err(|source| SessionError::Packet { id, source })?;
        self.add_decoded(id, bytes.len(), d.tile, d.coefficients)
    }

    /// Takes a packet as its source handed it over: already decoded, or as bytes.
    pub fn add_from_source(&mut self, p: SourcePacket) -> Result<(), SessionError> {
        match p.decoded {
            Some((tile, coefficients)) => self.add_decoded(p.id, p.data.len(), tile, coefficients),
            None => self.add_packet(p.id, &p.data),
        }
    }

    /// Takes packet `id` (of `wire_bytes` bytes) that its source already decoded into the
    /// coefficients of `tile`: the same as [`RenderSession::add_packet`] without decoding on
    /// this thread.
    pub fn add_decoded(
        &mut self,
        id: u32,
        wire_bytes: usize,
        tile: usize,
        coefficients: Vec<Coefficient>,
    ) -> Result<(), SessionError> {
        if self.packets.contains_key(&id) {
            return Ok(());
        }
        self.stats.packets_received += 1;
        self.stats.bytes_received += wire_bytes as u64;
        self.insert(id, tile, coefficients, wire_bytes)
    }

    /// Queues coefficients that did not come in a packet (a local source or a test); they are
    /// held per tile under local ids, like packets that cannot be asked for again.
    pub fn add_coefficients(&mut self, coefficients: Vec<Coefficient>) -> Result<(), SessionError> {
        for c in &coefficients {
            crate::pieces::check_coefficient(c, &self.header.geometry, self.header.channels)?;
        }
        let mut by_tile: std::collections::BTreeMap<usize, Vec<Coefficient>> = Default::default();
        for c in coefficients {
            let pos = [c.pos[0] as usize, c.pos[1] as usize, c.pos[2] as usize];
            by_tile
                .entry(self.header.tile_of(c.band, pos))
                .or_default()
                .push(c);
        }
        for (tile, cs) in by_tile {
            // Local ids count down from u32::MAX; one a packet already holds is skipped (a
            // replaced entry would leave its bytes counted).
            let mut id = self.next_local_id;
            while self.packets.contains_key(&id) {
                id = id.wrapping_sub(1);
            }
            self.next_local_id = id.wrapping_sub(1);
            self.insert(id, tile, cs, 0)?;
        }
        Ok(())
    }

    fn insert(
        &mut self,
        id: u32,
        tile: usize,
        coefficients: Vec<Coefficient>,
        wire_bytes: usize,
    ) -> Result<(), SessionError> {
        for c in &coefficients {
            crate::pieces::check_coefficient(c, &self.header.geometry, self.header.channels)?;
        }
        self.stats.coefficients_received += coefficients.len() as u64;
        let mut held = Held {
            tile,
            coefficients,
            queued: 0,
            wire_bytes,
            fresh: false,
        };
        self.enqueue(id, &mut held);
        let bytes = held.bytes();
        if held.queued == 0 {
            self.stats.retained_bytes += bytes;
        } else {
            self.stats.transient_bytes += bytes;
            held.fresh = true;
            self.fresh_bytes += bytes;
        }
        self.stats.packets_held += 1;
        self.stats.coefficients_held += held.coefficients.len();
        self.packets.insert(id, held);
        self.note_peak();
        self.evict();
        Ok(())
    }

    fn note_peak(&mut self) {
        self.stats.peak_bytes = self
            .stats
            .peak_bytes
            .max(self.stats.retained_bytes + self.stats.transient_bytes);
    }

    /// The energy coefficient `c` of a packet of tile `tile` shows in the current view (what
    /// orders the queue and eviction); `None` for a band the volume does not have.
    fn visible_energy(&self, c: &Coefficient, tile: usize) -> Option<f64> {
        self.energy_factors(c, tile).map(|f| energy(c, f))
    }

    /// The energy scale of `c`'s channel and band and the view's visibility weight of its
    /// band in tile `tile`: what `energy` multiplies its squared value by.
    fn energy_factors(&self, c: &Coefficient, tile: usize) -> Option<(f64, f64)> {
        let b = self.header.geometry.band_index(c.band)?;
        let nb = self.header.geometry.band_count();
        Some((
            self.energy_scale[c.channel as usize * nb + b],
            self.visibility.weight(c.band, tile),
        ))
    }

    /// Queues the visible coefficients of a held packet for the current view.
    fn enqueue(&mut self, id: u32, held: &mut Held) {
        held.queued = 0;
        // A packet's coefficients come substream by substream (channel, band): the factors of
        // `visible_energy` are looked up once per run of them.
        let mut run: Option<((u8, Band), (f64, f64))> = None;
        for (i, c) in held.coefficients.iter().enumerate() {
            let factors = match run {
                Some((key, factors)) if key == (c.channel, c.band) => factors,
                _ => {
                    let Some(factors) = self.energy_factors(c, held.tile) else {
                        continue;
                    };
                    run = Some(((c.channel, c.band), factors));
                    factors
                }
            };
            let e = energy(c, factors);
            match bucket_of(e) {
                Some(k) => {
                    self.queue.push(k, (id, i as u32));
                    held.queued += 1;
                }
                None => self.stats.invisible_in_view += 1,
            }
        }
    }

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
        let visibility = Visibility::new(&self.header, &spec)?;
        let (plan, exact) = plan_or_preview(
            &mut self.planner,
            self.preview.as_mut(),
            &self.header.geometry,
            &spec,
            self.header.channels,
        )?;
        if !exact {
            self.stats.previews += 1;
        }
        self.visibility = visibility;
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
    fn restart(&mut self) -> Result<(), SessionError> {
        self.shown_preview = None;
        self.backend.begin(self.plan.layout())?;
        self.plan.forget_stand_ins();
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

    /// Plans `spec` exactly on a background thread: the footprint tables and the atlas the
    /// backend reads (copying tables into an atlas is itself too long for a frame).
    fn build_in_background(&mut self, spec: ViewSpec) {
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
            let plan_it = || Planner::new(options).plan(&geometry, &spec, channels);
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
        let plan = match arrived {
            Some(Ok(plan)) => {
                for set in plan.footprint_sets() {
                    self.planner.insert(set);
                }
                Some(plan)
            }
            // Planning the view failed there: plan here, which reports the error.
            Some(Err(_)) | None => None,
        };
        if self.exact {
            return Ok(());
        }
        let spec = self.plan.spec;
        match plan {
            Some(plan) if plan.spec == spec => {
                self.plan = plan;
            }
            Some(_) => {
                if !self.turning {
                    self.build_in_background(spec);
                }
                return Ok(());
            }
            None => {
                self.plan =
                    self.planner
                        .plan(&self.header.geometry, &spec, self.header.channels)?;
            }
        }
        // A clipped view's pieces need factor tables: built off the frame thread, as in
        // `plan_or_preview` (a cued view never comes through a preview).
        if self.plan.clips() {
            self.plan.build_tables_in_background();
        }
        // What the preview shows now (the backend still holds it; the exact plan has the same
        // cameras) stays on screen until the exact tables catch up.
        let preview = match self.stats.splatted_in_view {
            0 => None,
            n => Some((self.image()?, n)),
        };
        self.exact = true;
        self.restart()?;
        self.shown_preview = preview;
        Ok(())
    }

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
            self.backend.prepare(&self.plan.atlas)?;
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
            let plan = &self.plan;
            let take = |(p, i): (u32, u32)| {
                let c = packets[&p].coefficients[i as usize];
                coefficients.push(c);
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
            self.records.clear();
            let mut stats = RenderStats::default();
            self.plan
                .splats(&coefficients, &mut self.records, &mut stats)?;
            self.backend.accumulate(&self.plan.atlas, &self.records)?;
            // Coefficients whose cued tables are still being built wait (still queued) and are
            // drawn when the tables arrive.
            let deferred = self.plan.take_deferred();
            // What waits was not drawn: its weight is not part of what was timed.
            let waiting_weight: f64 = deferred.iter().map(|&i| weights[i]).sum();
            let weight = (weight - waiting_weight).max(0.0);
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
                self.measured[kind] = per > 0.0 && !self.records.is_empty();
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
            report.records += self.records.len();
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

    /// Installs the depth-cue tables the plan's builder finished and queues again what waited
    /// for them (what still misses a table is set aside again by the next batch).
    fn poll_cue_tables(&mut self) {
        if self.plan.poll_tables() == 0 && (self.waiting.is_empty() || self.plan.tables_pending()) {
            return;
        }
        for (id, i) in std::mem::take(&mut self.waiting) {
            let Some(held) = self.packets.get(&id) else {
                continue;
            };
            let bucket = self
                .visible_energy(&held.coefficients[i as usize], held.tile)
                .and_then(bucket_of);
            // It was visible when queued; the same view sees it the same way.
            self.queue.push(bucket.unwrap_or(0), (id, i));
        }
    }

    /// Drops retained packets beyond the memory bound, least visible energy per byte first.
    fn evict(&mut self) {
        let Some(bound) = self.options.memory_bound else {
            return;
        };
        if self.stats.retained_bytes <= bound {
            return;
        }
        let mut candidates: Vec<(f64, u32)> = self
            .packets
            .iter()
            .filter(|(_, h)| h.queued == 0)
            .map(|(id, h)| {
                let e: f64 = h
                    .coefficients
                    .iter()
                    .filter_map(|c| self.visible_energy(c, h.tile))
                    .sum();
                (e / h.bytes().max(1) as f64, *id)
            })
            .collect();
        candidates.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        for (_, id) in candidates {
            if self.stats.retained_bytes <= bound {
                break;
            }
            if let Some(h) = self.packets.remove(&id) {
                self.stats.retained_bytes -= h.bytes();
                self.stats.packets_held -= 1;
                self.stats.coefficients_held -= h.coefficients.len();
                self.stats.packets_dropped += 1;
                if h.wire_bytes > 0 {
                    self.dropped.push(id);
                }
            }
        }
    }

    /// The image so far in the volume's display space (RGB for colour volumes; views side by
    /// side).
    ///
    /// Right after a preview is replaced by the exact tables, this is the preview's last image
    /// until the exact tables have drawn as many coefficients (or everything queued).
    pub fn image(&mut self) -> Result<Image, SessionError> {
        if self.showing_preview() {
            return Ok(self.shown_preview.as_ref().expect("shown").0.clone());
        }
        let raw = self.backend.read()?;
        self.lengths_for(raw.width, raw.height);
        let lengths = self.path_lengths.as_ref().expect("made above");
        Ok(lengths.apply(&raw, &self.header)?)
    }

    /// The image so far as the GPU backend shows it on the device it accumulated on (no image
    /// crosses the bus): [`RenderSession::image`]'s values through `window` (given the
    /// automatic window, it returns the one to show), its views in `grid` panels (columns,
    /// rows) ([`crate::backend::gpu::GpuBackend::display`]). `None` when the backend accumulates on the host, or
    /// while the preview's last image is what [`RenderSession::image`] shows: show that then.
    pub fn device_display(
        &mut self,
        window: impl FnOnce((f64, f64)) -> (f64, f64),
        grid: (usize, usize),
    ) -> Result<Option<&wgpu::Texture>, SessionError> {
        if self.showing_preview() || self.backend.gpu().is_none() {
            return Ok(None);
        }
        let layout = self.plan.layout();
        self.lengths_for(layout.total_width(), layout.height);
        if self.device_colour.is_none() {
            let lengths = self.path_lengths.as_ref().expect("made above");
            self.device_colour = Some(lengths.color_map(&self.header)?);
        }
        let colour = self.device_colour.clone().flatten();
        let gpu = self.backend.gpu().expect("checked above");
        let auto = gpu.auto_window(colour.as_ref())?;
        let options = DisplayOptions {
            window: Some(window(auto)),
            colour,
            grid: Some(grid),
        };
        Ok(Some(gpu.display(&options)?))
    }

    /// Whether [`RenderSession::image`] shows the preview's last image now: until the exact
    /// tables have drawn as many coefficients as it had, or everything queued.
    fn showing_preview(&mut self) -> bool {
        if let Some((_, drawn)) = &self.shown_preview {
            if self.stats.splatted_in_view < *drawn && self.pending() > 0 {
                return true;
            }
            self.shown_preview = None;
        }
        false
    }

    /// Makes `path_lengths` those of the current view for an image of `width` × `height` (kept
    /// while the view and the size stay).
    fn lengths_for(&mut self, width: usize, height: usize) {
        let (cameras, cue) = (&self.plan.cameras, self.plan.cue.as_ref());
        let kept = self
            .path_lengths
            .as_ref()
            .is_some_and(|l| l.matches(cameras, cue, width, height));
        if !kept {
            self.path_lengths = Some(color::PathLengths::new(
                &self.header,
                cameras,
                cue,
                width,
                height,
            ));
            self.device_colour = None;
        }
    }

    /// The image so far in the coded channels (what the backend accumulated).
    pub fn raw_image(&mut self) -> Result<Image, SessionError> {
        Ok(self.backend.read()?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The bit-level ⌊2·log2 x⌋ against libm's `log2` over powers of two (exact there), a
    /// pseudo-random sweep of positive numbers, subnormals and the extremes; values within 1e-9
    /// of a boundary (x = 2^k or √2·2^k), where `log2`'s own rounding decides, are skipped.
    #[test]
    fn half_octaves_from_bits_equal_the_floor_of_twice_log2() {
        let reference = |x: f64| (2.0 * x.log2()).floor() as i64;
        for k in -1074..=1023 {
            let x = if k >= -1022 {
                f64::from_bits(((k + 1023) as u64) << 52)
            } else {
                f64::from_bits(1u64 << (k + 1074))
            };
            assert_eq!(half_octave(x), 2 * i64::from(k), "2^{k}");
        }
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        let mut checked = 0;
        for _ in 0..200_000 {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            let x = f64::from_bits(state >> 1);
            if !x.is_finite() || x <= 0.0 {
                continue;
            }
            // Near a boundary of ⌊2·log2 x⌋ (x = 2^k or √2·2^k) the reference's rounding decides.
            let h = 2.0 * x.log2();
            if ((h - h.floor()) - 0.0).abs() < 1e-9 || (h.floor() + 1.0 - h).abs() < 1e-9 {
                continue;
            }
            assert_eq!(half_octave(x), reference(x), "{x:e}");
            checked += 1;
        }
        assert!(checked > 100_000);
        for x in [
            f64::MIN_POSITIVE,
            f64::MIN_POSITIVE / 3.0,
            5e-324,
            1.0,
            1.5,
            std::f64::consts::SQRT_2 * (1.0 - 1e-6),
            std::f64::consts::SQRT_2 * (1.0 + 1e-6),
            0.7,
            3.0,
        ] {
            assert_eq!(half_octave(x), reference(x), "{x:e}");
        }
        // log2(f64::MAX) rounds up to 1024: the bits give the true ⌊2·log2⌋ = 2·1023 + 1.
        assert_eq!(half_octave(f64::MAX), 2047);
        assert_eq!(bucket_of(0.0), None);
        assert_eq!(bucket_of(f64::NAN), None);
        assert_eq!(bucket_of(f64::INFINITY), Some(BUCKETS - 1));
        assert_eq!(bucket_of(1.0), Some(BUCKET_OFFSET as usize));
    }
}
