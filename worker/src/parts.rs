//! Bricked jobs and time series spread over workers. The worker that leases a bricked job
//! whose source is a file on shared storage *coordinates* it: it plans the volume ([`BrickPlan::new`]: the depth,
//! the whole's offset or colour transform), adds one part per brick to the queue to score it,
//! allocates the whole's rate from the parts' score summaries ([`allocate`]), adds one part per
//! brick to code it (a byte target: one round per trial of the search), fetches the chosen
//! files and commits the bricked volume to the cache once, as any job delivers. A time series
//! on shared storage is coordinated the same way ([`coordinate_series`]): its parts are the
//! *units* of a [`SeriesPlan`] (every temporal component's bricks), allocated as one process
//! allocates them.
//!
//! Any worker leases parts. The coordinator runs parts itself while it waits, so one worker
//! alone still finishes the job, and every extra worker takes bricks off it. A part's result
//! goes back to the orchestrator (`FinishPart`) and the coordinator fetches it
//! (`FetchResult`). A part whose worker dies is leased again alone; a coordinator that dies is
//! replaced by the next worker to lease the job, whose parts are already known (`SubmitParts`
//! leaves them as they are), so bricks done before are not compressed again.

use crate::{fail, heartbeat_loop, options, output_failure, write_output, Output, Shared};
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Duration;
use wavesplat_compressor::bricked::{
    allocate, allocate_units, BrickError, BrickPlan, BrickSource, BrickWork, CodedBrick, KeptTops,
    SharedChoices, Spill, SpilledBrick, TopMemory, TOP_BUDGET,
};
use wavesplat_compressor::colorspace::ColorTransform;
use wavesplat_compressor::encode::{ScoreSummary, StopFlag, Target};
use wavesplat_compressor::reader::region::RegionReader;
use wavesplat_compressor::series::{
    open_series_path_channel, SeriesError, SeriesInput, SeriesPlan,
};
use wavesplat_orchestrator_client::model::{
    is_worker_name, Failure, FailureKind, JobSpec, PartColor, PartSpec, PartStep, Source,
};
use wavesplat_orchestrator_client::{convert, Client, HeldLease, CHUNK_BYTES};
use wavesplat_proto::pb;

/// How often a coordinator with nothing to run asks after its parts: this, growing to
/// [`MAX_POLL`] while none finishes.
const POLL: Duration = Duration::from_millis(200);
const MAX_POLL: Duration = Duration::from_secs(1);

/// What a worker needs to run parts: its orchestrator client, pool and name.
#[derive(Clone)]
pub(crate) struct PartRunner {
    pub orch: Client,
    pub pool: Arc<rayon::ThreadPool>,
    pub worker: String,
    /// Testing aid: pause this long before reporting a part's result (ms).
    pub pause_ms: u64,
    /// The source the last part read, kept open for the next: a worker takes the parts of
    /// one volume in a row, and opening a compressed file (`.nii.gz`) inflates it whole.
    pub opened: Arc<std::sync::Mutex<Option<OpenedSource>>>,
    /// The tops its score parts kept ([`PartRunner::tops`]).
    pub tops: PartTops,
}

/// The tops a worker's score parts kept, by the parent (bricked job) they are of, so that its
/// encode parts of the same bricks code from them instead of reading and transforming the
/// brick again (without refinement: `--effort fast`); the queue hands a brick's encode part to
/// the worker that last scored or coded it (`PartSpec::prefer_worker`). The tops of up to
/// [`TOPS_PARENTS`] parents are kept at once (a batch of bricked jobs runs on the same workers,
/// their parts interleaved), all within one memory budget ([`TopMemory`], [`TOP_BUDGET`], or
/// less where a held job's memory limit leaves less: then the others' tops are dropped until
/// what is held fits); beyond it they go to a temporary file. A parent's tops are dropped (and their temporary
/// file) when a part of a parent not held comes and the slots are full (the least recently
/// used go), or when no part used them for [`TOPS_IDLE`].
pub(crate) type PartTops = Arc<std::sync::Mutex<PartTopsHeld>>;

/// How long a worker keeps the tops of a parent no part used: longer than a bricked job's
/// pause between its rounds of parts (its allocation, and the slowest brick of the round
/// before).
pub(crate) const TOPS_IDLE: Duration = Duration::from_secs(120);

/// How many parents' tops a worker keeps at once. Every worker holding a parent (planning it,
/// then waiting on its parts) spreads parts to all workers, so a worker sees the parts of up
/// to as many parents as there are workers; beyond this count the least recently used parent's
/// tops go, and parents taking turns then drop each other's before they are used (six jobs on
/// six workers kept 34–240 of 384 encode parts' tops with four, 323–360 with sixteen:
/// BENCHMARKS.md). Their memory and disk are bounded by the shared budgets, not by this count.
pub(crate) const TOPS_PARENTS: usize = 16;

/// The tops a worker holds: up to [`TOPS_PARENTS`] parents', and the memory they share.
pub(crate) struct PartTopsHeld {
    parents: Vec<PartTopsOf>,
    memory: Arc<TopMemory>,
}

impl Default for PartTopsHeld {
    fn default() -> Self {
        PartTopsHeld {
            parents: Vec::new(),
            memory: Arc::new(TopMemory::new(TOP_BUDGET)),
        }
    }
}

impl PartTopsHeld {
    /// The shared memory's budget: the smallest of the held parents' own (each what its job's
    /// memory limit leaves for tops, at most [`TOP_BUDGET`]), so that all parents' tops
    /// together stay within what one of them may hold.
    fn limit_memory(&self) {
        let budget = self.parents.iter().map(|t| t.tops.budget()).min();
        self.memory
            .set_budget(budget.unwrap_or(TOP_BUDGET).min(TOP_BUDGET));
    }

    /// Drops the tops that no part used for `idle`, and sets the shared budget from those left.
    fn drop_idle(&mut self, idle: Duration) {
        self.parents.retain(|t| t.used.elapsed() < idle);
        self.limit_memory();
    }

    /// The tops kept for the parts of `parent`: the ones kept so far, or new ones from `make`
    /// drawing on the shared memory (in place of the least recently used parent's when
    /// [`TOPS_PARENTS`] are held). Tops no part used for [`TOPS_IDLE`] go first.
    fn of_parent(&mut self, parent: u64, make: impl FnOnce() -> KeptTops) -> Arc<KeptTops> {
        self.drop_idle(TOPS_IDLE);
        let used = std::time::Instant::now();
        if let Some(kept) = self.parents.iter_mut().find(|t| t.parent == parent) {
            kept.used = used;
            return kept.tops.clone();
        }
        if self.parents.len() >= TOPS_PARENTS {
            // The least recently used go first, so that their memory is free for the new.
            let least_used = (0..self.parents.len())
                .min_by_key(|&i| self.parents[i].used)
                .unwrap_or(0);
            self.parents.swap_remove(least_used);
        }
        let tops = Arc::new(make().sharing(self.memory.clone()));
        self.parents.push(PartTopsOf {
            parent,
            tops: tops.clone(),
            used,
        });
        self.limit_memory();
        // A job under a tighter memory limit than those held came: the others' tops in memory
        // go, the least recently used first, until what is held in memory fits its budget
        // (tops in the temporary file hold only their metadata there, counted, never refused).
        let in_memory =
            |held: &[PartTopsOf]| -> u64 { held.iter().map(|t| t.tops.budgeted_bytes()).sum() };
        while in_memory(&self.parents) > self.memory.budget() {
            let Some(least_used) = (0..self.parents.len())
                .filter(|&i| {
                    self.parents[i].parent != parent && self.parents[i].tops.budgeted_bytes() > 0
                })
                .min_by_key(|&i| self.parents[i].used)
            else {
                break;
            };
            let dropped = self.parents.swap_remove(least_used);
            tracing::info!(
                parent = dropped.parent,
                budget = self.memory.budget(),
                "dropping the tops kept for a job: a job under a tighter memory limit came"
            );
        }
        self.limit_memory();
        tops
    }
}

/// The tops kept for one parent's parts, and when a part last used them.
pub(crate) struct PartTopsOf {
    parent: u64,
    tops: Arc<KeptTops>,
    used: std::time::Instant,
}

/// Drops the tops in `slot` that no part used for `idle`.
pub(crate) fn release_idle_tops(slot: &PartTops, idle: Duration) {
    slot.lock()
        .unwrap_or_else(|p| p.into_inner())
        .drop_idle(idle);
}

/// A part's source kept open, with what it was opened for.
pub(crate) struct OpenedSource {
    key: String,
    opened: Opened,
}

/// What a source is kept open under: the file, its hash, layout and channel, and how it was
/// opened.
fn opened_key(spec: &JobSpec, series: bool) -> String {
    format!(
        "{:?}|{:?}|{:?}|{:?}|{series}",
        spec.source, spec.sha256, spec.raw, spec.channel
    )
}

/// A source open for parts: one volume read by region, or a time series.
#[derive(Clone)]
enum Opened {
    Volume(Arc<RegionReader>),
    Series(Arc<SeriesInput>),
}

impl PartRunner {
    /// The tops kept for the parts of `parent`: the ones kept so far, or new ones from `make`
    /// drawing on the worker's shared memory (in place of the least recently used parent's
    /// when [`TOPS_PARENTS`] are held).
    fn tops(&self, parent: u64, make: impl FnOnce() -> KeptTops) -> Arc<KeptTops> {
        let mut held = self.tops.lock().unwrap_or_else(|p| p.into_inner());
        held.of_parent(parent, make)
    }

    /// `spec`'s source opened as a volume (`series` false) or a time series: the one kept
    /// open if it is the same, or a new one (kept in its place).
    fn opened(&self, spec: &JobSpec, series: bool) -> Result<Opened, Failure> {
        let key = opened_key(spec, series);
        if let Ok(slot) = self.opened.lock() {
            if let Some(o) = slot.as_ref().filter(|o| o.key == key) {
                return Ok(o.opened.clone());
            }
        }
        let opened = if series {
            Opened::Series(Arc::new(open_series(spec)?))
        } else {
            Opened::Volume(Arc::new(open_source(spec)?))
        };
        if let Ok(mut slot) = self.opened.lock() {
            *slot = Some(OpenedSource {
                key,
                opened: opened.clone(),
            });
        }
        Ok(opened)
    }

    /// The reader of `spec`'s source, one volume.
    fn source(&self, spec: &JobSpec) -> Result<Arc<RegionReader>, Failure> {
        match self.opened(spec, false)? {
            Opened::Volume(r) => Ok(r),
            Opened::Series(_) => Err(fail(FailureKind::Worker, "a series opened as a volume")),
        }
    }

    /// `spec`'s source opened as a time series (and kept open) when it is one; `None` when it
    /// is one volume.
    pub(crate) fn series_if(&self, spec: &JobSpec) -> Result<Option<Arc<SeriesInput>>, Failure> {
        let Source::Path(p) = &spec.source else {
            return Ok(None);
        };
        let raw = spec.raw.as_ref().map(options::raw_spec);
        let input = open_series_path_channel(p, raw.as_ref(), crate::channel(spec));
        let Some(input) = input.map_err(series_failure)? else {
            return Ok(None);
        };
        let input = Arc::new(input);
        if let Ok(mut slot) = self.opened.lock() {
            *slot = Some(OpenedSource {
                key: opened_key(spec, true),
                opened: Opened::Series(input.clone()),
            });
        }
        Ok(Some(input))
    }

    /// `spec`'s source as a time series.
    fn series(&self, spec: &JobSpec) -> Result<Arc<SeriesInput>, Failure> {
        match self.opened(spec, true)? {
            Opened::Series(s) => Ok(s),
            Opened::Volume(_) => Err(fail(FailureKind::Worker, "a volume opened as a series")),
        }
    }
}

/// The length of `spec`'s source: a file's, or the sum of a directory's or a detached
/// header's files (as its hash covers them, [`crate::archive::source_listing`]).
fn source_bytes(spec: &JobSpec) -> Option<u64> {
    match &spec.source {
        Source::Path(p) => crate::archive::source_listing(p, spec.raw.is_some())
            .ok()
            .map(|l| l.byte_len()),
        Source::Upload { .. } => None,
    }
}

/// Opens a part's (or a coordinator's) source: a file on shared storage read by region.
fn open_source(spec: &JobSpec) -> Result<RegionReader, Failure> {
    let Source::Path(p) = &spec.source else {
        return Err(fail(
            FailureKind::InvalidInput,
            "the bricks of a job are spread over workers only from a source on shared storage",
        ));
    };
    let raw = spec.raw.as_ref().map(options::raw_spec);
    RegionReader::open_channel(p, raw.as_ref(), crate::channel(spec)).map_err(|e| {
        let kind = if p.is_file() {
            FailureKind::InvalidInput
        } else {
            FailureKind::SourceUnavailable
        };
        fail(kind, format!("{}: {e}", p.display()))
    })
}

/// Opens a time series on shared storage (a 4D file, a directory of time steps, a DICOM
/// cine); a source that is one volume is refused.
pub(crate) fn open_series(spec: &JobSpec) -> Result<SeriesInput, Failure> {
    let Source::Path(p) = &spec.source else {
        return Err(fail(
            FailureKind::InvalidInput,
            "a time series is spread over workers only from shared storage",
        ));
    };
    let raw = spec.raw.as_ref().map(options::raw_spec);
    match open_series_path_channel(p, raw.as_ref(), crate::channel(spec)) {
        Ok(Some(s)) => Ok(s),
        Ok(None) => Err(fail(
            FailureKind::InvalidInput,
            format!(
                "{}: one volume, not a time series: the file changed",
                p.display()
            ),
        )),
        Err(e) => Err(series_failure(e)),
    }
}

/// A series error as a job's failure: bad input, or a failed compression.
pub(crate) fn series_failure(e: SeriesError) -> Failure {
    match e {
        SeriesError::InvalidOption(_) | SeriesError::Read(_) | SeriesError::Mismatch { .. } => {
            fail(FailureKind::InvalidInput, e.to_string())
        }
        SeriesError::Brick(b) => brick_failure(*b),
        e => fail(FailureKind::Compress, e.to_string()),
    }
}

/// Temporal group of a series job that names none.
pub(crate) const SERIES_GROUP: usize = 8;

/// Brick edge of a series' components when the job names none: a time point up to 256 a side
/// is one plain file per component (as `compress` does).
pub(crate) const SERIES_BRICK: usize = 256;

/// The group and brick edge of a series job.
fn series_shape(spec: &JobSpec) -> (usize, usize) {
    (
        spec.options.time_group.unwrap_or(SERIES_GROUP),
        spec.options.brick.unwrap_or(SERIES_BRICK),
    )
}

fn brick_failure(e: BrickError) -> Failure {
    let kind = match e {
        BrickError::Read { .. } => FailureKind::InvalidInput,
        _ => FailureKind::Compress,
    };
    fail(kind, format!("{e:#}"))
}

/// The plan of a part: the parent's choices, nothing read.
fn part_plan(
    spec: &JobSpec,
    part: &PartSpec,
    source: &dyn BrickSource,
    stop: &StopFlag,
) -> Result<BrickPlan, Failure> {
    let mut opts = options::compress_options(&spec.options);
    opts.stop = stop.clone();
    let brick = spec.options.brick.ok_or_else(|| {
        fail(
            FailureKind::InvalidInput,
            "a part of a job that is not bricked",
        )
    })?;
    let choices = SharedChoices {
        levels: part.levels as usize,
        offset: part.offset,
        color: part.color.map(|c| ColorTransform {
            kind: opts.colorspace,
            basis: c.basis,
            mean: c.mean,
            importance: c.importance,
        }),
    };
    let plan = BrickPlan::with_choices(source, &opts, brick, choices).map_err(brick_failure)?;
    same_count("the source makes", plan.grid.len(), "bricks", part.of)?;
    Ok(plan)
}

/// Refuses a part whose source now makes another count of something than the part was
/// planned with ("the source makes 8 bricks, the part says 6: the file changed").
fn same_count(source_does: &str, found: usize, what: &str, planned: u32) -> Result<(), Failure> {
    if found == planned as usize {
        return Ok(());
    }
    Err(fail(
        FailureKind::InvalidInput,
        format!("{source_does} {found} {what}, the part says {planned}: the file changed"),
    ))
}

/// Runs one part on the pool: its result's bytes and the brick's voxels.
/// Computes a part; `stop` raised ends it at its next stage.
fn compute_part(
    runner: &PartRunner,
    spec: &JobSpec,
    part: &PartSpec,
    stop: &StopFlag,
) -> Result<(Vec<u8>, u64), Failure> {
    if let (Some(planned), now) = (part.source_bytes, source_bytes(spec)) {
        if now != Some(planned) {
            return Err(fail(
                FailureKind::InvalidInput,
                format!(
                    "the source changed since the job was planned: {planned} bytes then, {} now",
                    now.map_or("unreadable".to_string(), |n| format!("{n} bytes"))
                ),
            ));
        }
    }
    if let Some(points) = part.time_points {
        return compute_series_part(runner, spec, part, points, stop);
    }
    let source = runner.source(spec)?;
    let source: &RegionReader = &source;
    let plan = part_plan(spec, part, source, stop)?;
    let i = part.index as usize;
    let voxels = plan.grid[i].1.iter().map(|d| *d as u64).product();
    // A worker runs one part, one brick, at a time.
    let tops = runner.tops(part.parent, || {
        KeptTops::for_plan_bricks_at_once(&plan, 1).spilling_in(None)
    });
    let bytes = with_tops(part, &tops, || {
        run_step(
            part.step,
            || {
                plan.score_into(source, i, &tops, 0, plan.top_cap(i))
                    .map_err(brick_failure)
            },
            |count| {
                // A brick this worker did not score (its scorer died, or was busy) keeps its
                // top here on its first encode part, for the search's next trials.
                plan.encode_from(source, i, count, &tops, 0, plan.top_cap(i))
                    .map_err(brick_failure)
            },
        )
    })?;
    Ok((bytes, voxels))
}

/// Runs `step` with `tops`, saying where a score part kept its brick's top, and when an encode
/// part coded from a kept top.
fn with_tops(
    part: &PartSpec,
    tops: &KeptTops,
    step: impl FnOnce() -> Result<Vec<u8>, Failure>,
) -> Result<Vec<u8>, Failure> {
    let before = tops.counts().0;
    let (spilled, held) = (tops.spilled(), tops.memory_bytes());
    let bytes = step()?;
    if matches!(part.step, PartStep::Score { .. }) {
        let kept = if tops.spilled() > spilled {
            "in the temporary file"
        } else if tops.memory_bytes() > held {
            "in memory"
        } else {
            "nowhere"
        };
        tracing::info!(
            parent = part.parent,
            part = %part.label(),
            tops_in_memory = tops.memory_bytes(),
            "brick scored; its top kept {kept}"
        );
    }
    if tops.counts().0 > before {
        tracing::info!(
            parent = part.parent,
            part = %part.label(),
            "part coded from the top this worker kept when it scored or coded it"
        );
    }
    Ok(bytes)
}

/// A part's step run by `score` or `encode`: its result's bytes (a score summary, or the
/// brick's file).
fn run_step(
    step: PartStep,
    score: impl FnOnce() -> Result<ScoreSummary, Failure>,
    encode: impl FnOnce(Option<u64>) -> Result<(Vec<u8>, u64), Failure>,
) -> Result<Vec<u8>, Failure> {
    Ok(match step {
        PartStep::Score { energies } => score()?.to_bytes(energies),
        PartStep::Encode { count, .. } => encode(count)?.0,
    })
}

/// Runs one unit of a time series: the plan made again from the parent's choices, nothing
/// else read.
fn compute_series_part(
    runner: &PartRunner,
    spec: &JobSpec,
    part: &PartSpec,
    points: u32,
    stop: &StopFlag,
) -> Result<(Vec<u8>, u64), Failure> {
    let input = runner.series(spec)?;
    let series = input.source();
    same_count(
        "the source has",
        series.time_points(),
        "time points",
        points,
    )?;
    let (group, brick) = series_shape(spec);
    let mut opts = options::compress_options(&spec.options);
    opts.stop = stop.clone();
    let choices = SharedChoices {
        levels: part.levels as usize,
        offset: part.offset,
        color: None,
    };
    let plan =
        SeriesPlan::with_choices(series, &opts, group, brick, choices).map_err(series_failure)?;
    same_count("the series makes", plan.units.len(), "units", part.of)?;
    let u = part.index as usize;
    let (c, i) = plan.units[u];
    let voxels = plan.plans[c].grid[i].1.iter().map(|d| *d as u64).product();
    let tops = runner.tops(part.parent, || plan.kept_tops().spilling_in(None));
    let bytes = with_tops(part, &tops, || {
        run_step(
            part.step,
            || plan.score_into(series, u, &tops).map_err(brick_failure),
            |count| {
                plan.encode_from(series, u, count, &tops)
                    .map_err(brick_failure)
            },
        )
    })?;
    Ok((bytes, voxels))
}

/// Runs a leased part end to end: heartbeats, the work, and its result or failure reported.
pub(crate) async fn run_part_lease(runner: &PartRunner, lease: pb::Lease, spec: JobSpec) {
    let held = HeldLease::of(&lease);
    let (id, attempt) = (held.job_id, held.attempt);
    let Some(part) = spec.part.clone() else {
        return;
    };
    tracing::info!(
        job = id,
        attempt,
        parent = part.parent,
        part = %part.label(),
        "running part"
    );
    let shared = Arc::new(Shared::default());
    shared.set(0.1, part.label());
    let heartbeat = tokio::spawn(heartbeat_loop(
        runner.orch.clone(),
        held.clone(),
        runner.worker.clone(),
        Duration::from_millis(u64::from(lease.heartbeat_ms.max(50))),
        shared.clone(),
    ));
    let (pool, r, stop) = (runner.pool.clone(), runner.clone(), shared.stop.clone());
    let result =
        tokio::task::spawn_blocking(move || pool.install(|| compute_part(&r, &spec, &part, &stop)))
            .await
            .map_err(|e| fail(FailureKind::Worker, format!("part task: {e}")))
            .and_then(|r| r);
    if runner.pause_ms > 0 && result.is_ok() {
        shared.set(0.9, "paused (testing aid)");
        tokio::time::sleep(Duration::from_millis(runner.pause_ms)).await;
    }
    heartbeat.abort();
    if shared.lost_after(id, attempt, &result, true) {
        return;
    }
    match result {
        // Sent as any outcome is (refused, the lease lapses and the part runs again).
        Ok((bytes, voxels)) => {
            let worker = runner.worker.as_str();
            let send = || finish_part(runner.orch.clone(), &held, worker, &bytes, voxels);
            crate::until_answered(id, attempt, send).await;
        }
        Err(f) => fail_part(runner, &held, f).await,
    }
}

/// Reports that the part leased as `held` failed.
async fn fail_part(runner: &PartRunner, held: &HeldLease, f: Failure) {
    let (id, attempt) = (held.job_id, held.attempt);
    tracing::warn!(job = id, attempt, kind = f.kind.name(), reason = %f.message, "part failed");
    let outcome = wavesplat_orchestrator_client::model::Outcome::Failed(f);
    crate::report(&mut runner.orch.clone(), &runner.worker, held, outcome).await;
}

/// Sends the result of the part leased as `held` (`FinishPart`).
async fn finish_part(
    mut orch: Client,
    held: &HeldLease,
    worker: &str,
    bytes: &[u8],
    voxels: u64,
) -> Result<pb::Job, tonic::Status> {
    let head = pb::PartResult {
        job_id: held.job_id,
        attempt: held.attempt,
        worker: worker.to_string(),
        size: bytes.len() as u64,
        sha256: wavesplat_net::digest::sha256(bytes).to_vec(),
        voxels,
    };
    let mut messages = vec![pb::FinishPartRequest {
        msg: Some(pb::finish_part_request::Msg::Head(head)),
    }];
    messages.extend(bytes.chunks(CHUNK_BYTES).map(|c| pb::FinishPartRequest {
        msg: Some(pb::finish_part_request::Msg::Chunk(c.to_vec())),
    }));
    Ok(orch
        .finish_part(held.request(tokio_stream::iter(messages)))
        .await?
        .into_inner())
}

/// The coordinator's side: the parts of one bricked job, run through the queue.
struct RemoteBricks {
    runner: PartRunner,
    handle: tokio::runtime::Handle,
    parent: JobSpec,
    parent_id: u64,
    /// The parent's lease, which adding and polling parts and fetching their results present.
    parent_lease: HeldLease,
    shared: Arc<Shared>,
    /// The source file's length when planned (every part checks it).
    source_bytes: Option<u64>,
    /// A time series' time points (its parts are units of a [`SeriesPlan`]); `None` for bricks.
    time_points: Option<u32>,
    /// Why the parts could not finish, for the job's outcome.
    failure: std::sync::Mutex<Option<Failure>>,
    /// The worker that last scored or coded each brick (empty: not known), whom its next
    /// encode part prefers: it may hold the brick's kept top ([`PartTops`]). A worker that
    /// codes a brick it holds no top of keeps one on the way (within the top's cap), so after
    /// a scorer died or was busy, the brick's later trials go to the worker that took it over.
    top_held_by: std::sync::Mutex<Vec<String>>,
}

/// A part that is done: its id, its result's size and the worker that finished it.
struct DonePart {
    id: u64,
    bytes: u64,
    worker: String,
}

/// The parts could not finish; why is kept in [`RemoteBricks::failure`].
struct Stopped;

impl From<Stopped> for BrickError {
    fn from(_: Stopped) -> BrickError {
        BrickError::InvalidOption("the bricks' parts did not finish".into())
    }
}

impl RemoteBricks {
    fn stop(&self, f: Failure) -> Stopped {
        if let Ok(mut slot) = self.failure.lock() {
            slot.get_or_insert(f);
        }
        Stopped
    }

    /// Why the parts stopped, or `otherwise` when they did not.
    fn failure_or(&self, otherwise: Failure) -> Failure {
        self.failure
            .lock()
            .ok()
            .and_then(|mut f| f.take())
            .unwrap_or(otherwise)
    }

    /// Part `index` of `of`, doing `step` with the parent's choices `c`.
    fn part(&self, index: usize, of: usize, c: &SharedChoices, step: PartStep) -> JobSpec {
        JobSpec {
            part: Some(PartSpec {
                parent: self.parent_id,
                index: index as u32,
                of: of as u32,
                step,
                levels: c.levels as u32,
                offset: c.offset,
                color: c.color.as_ref().map(|t| PartColor {
                    basis: t.basis,
                    mean: t.mean,
                    importance: t.importance,
                }),
                source_bytes: self.source_bytes,
                time_points: self.time_points,
                prefer_worker: None,
            }),
            ..self.parent.clone()
        }
    }

    /// Every one of `of` parts scored: their summaries, in order.
    fn score_parts(
        &self,
        of: usize,
        choices: &SharedChoices,
        energies: bool,
    ) -> Result<Vec<ScoreSummary>, Stopped> {
        let parts: Vec<JobSpec> = (0..of)
            .map(|i| self.part(i, of, choices, PartStep::Score { energies }))
            .collect();
        let done = self.run_all(&parts, "scoring", 0.05, 0.3)?;
        *self.top_held_by.lock().unwrap_or_else(|p| p.into_inner()) =
            done.iter().map(|p| p.worker.clone()).collect();
        let mut summaries = Vec::with_capacity(done.len());
        for p in &done {
            let bytes = self.fetch(p.id)?;
            let s = ScoreSummary::from_bytes(&bytes)
                .map_err(|e| self.stop(fail(FailureKind::Worker, format!("part {}: {e}", p.id))))?;
            summaries.push(s);
        }
        Ok(summaries)
    }

    /// Every one of `of` parts coded keeping `counts` (`None`: all), in trial `trial`.
    /// `top_cap(i)` is part `i`'s top cap (`None`: it keeps no top): a worker that codes the
    /// brick at a count within it keeps its top, and the brick's next part prefers that
    /// worker.
    fn encode_parts(
        &self,
        of: usize,
        choices: &SharedChoices,
        counts: Option<&[u64]>,
        trial: usize,
        top_cap: &dyn Fn(usize) -> Option<u64>,
    ) -> Result<Vec<CodedBrick<u64>>, Stopped> {
        let top_held_by = self
            .top_held_by
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .clone();
        let parts: Vec<JobSpec> = (0..of)
            .map(|i| {
                let step = PartStep::Encode {
                    count: counts.map(|k| k[i]),
                    trial: trial as u32,
                };
                let mut spec = self.part(i, of, choices, step);
                if let (Some(part), Some(w)) = (spec.part.as_mut(), top_held_by.get(i)) {
                    part.prefer_worker = is_worker_name(w).then(|| w.clone());
                }
                spec
            })
            .collect();
        let stage = format!("coding (trial {trial})");
        let done = self.run_all(&parts, &stage, 0.3, 0.9)?;
        {
            // A coder keeps the brick's top where the count is within its cap (and the tops'
            // budget allows, which the planner cannot see); else the brick's top stays where
            // it was.
            let mut held = self.top_held_by.lock().unwrap_or_else(|p| p.into_inner());
            held.resize(of, String::new());
            for (i, p) in done.iter().enumerate() {
                let kept = counts.is_some_and(|k| top_cap(i).is_some_and(|cap| k[i] <= cap));
                if kept {
                    held[i] = p.worker.clone();
                }
            }
        }
        Ok(done
            .into_iter()
            .map(|p| CodedBrick {
                file: p.id,
                len: p.bytes,
                // Read from the file's header when it is fetched.
                kept: 0,
            })
            .collect())
    }

    /// The chosen parts' files fetched one at a time into a [`Spill`] in the scratch
    /// directory, each with the count its header says it kept and its length checked against
    /// what its part reported: memory holds one part's file at a time, however large the
    /// volume.
    fn gather(&self, chosen: &[CodedBrick<u64>]) -> Result<Vec<CodedBrick<SpilledBrick>>, Failure> {
        self.shared.set(0.9, "gathering the parts' files");
        let spill = Arc::new(Spill::new(None).map_err(spill_failure)?);
        chosen
            .iter()
            .map(|b| {
                let (bytes, kept) = self.fetch_kept(b)?;
                if bytes.len() as u64 != b.len {
                    return Err(fail(
                        FailureKind::Worker,
                        format!(
                            "part {}'s file has {} bytes, reported {}",
                            b.file,
                            bytes.len(),
                            b.len
                        ),
                    ));
                }
                let file = spill.push(&bytes).map_err(spill_failure)?;
                Ok(CodedBrick {
                    file,
                    len: b.len,
                    kept,
                })
            })
            .collect()
    }

    /// A chosen part's file fetched, with the count its header says it kept.
    fn fetch_kept(&self, b: &CodedBrick<u64>) -> Result<(Vec<u8>, u64), Failure> {
        let bytes = self.fetch(b.file).map_err(|Stopped| {
            self.failure_or(fail(FailureKind::Worker, "fetching a part's file failed"))
        })?;
        let kept = wavesplat_codec::format::parse_file(&bytes)
            .map_err(|e| fail(FailureKind::Worker, format!("part {}'s file: {e}", b.file)))?
            .header
            .kept;
        Ok((bytes, kept))
    }

    /// Adds `parts` (or polls them, if known) and waits until all are done, running parts
    /// itself while any is queued. `stage` names the step for progress, whose fraction goes
    /// from `from` to `to`.
    fn run_all(
        &self,
        parts: &[JobSpec],
        stage: &str,
        from: f32,
        to: f32,
    ) -> Result<Vec<DonePart>, Stopped> {
        let specs: Vec<pb::JobSpec> = parts.iter().map(convert::spec_to_pb).collect();
        // Each part's last known state; a done one is not asked after again.
        let mut known: Vec<Option<pb::PartState>> = vec![None; specs.len()];
        let state = |p: &pb::PartState| convert::state_name(p.state);
        let is_done = |p: &Option<pb::PartState>| p.as_ref().is_some_and(|p| state(p) == "done");
        let mut wait = POLL / 2;
        loop {
            if self.shared.lost.load(Ordering::SeqCst) {
                return Err(self.stop(fail(
                    FailureKind::Worker,
                    "the bricked job's lease was lost",
                )));
            }
            let open: Vec<usize> = (0..specs.len()).filter(|&i| !is_done(&known[i])).collect();
            let done_before = specs.len() - open.len();
            let mut answered = true;
            for batch in open.chunks(1024) {
                let mut orch = self.runner.orch.clone();
                let req = self.parent_lease.request(pb::SubmitPartsRequest {
                    parent_id: self.parent_id,
                    parent_attempt: self.parent_lease.attempt,
                    parts: batch.iter().map(|&i| specs[i].clone()).collect(),
                });
                match self.handle.block_on(orch.submit_parts(req)) {
                    Ok(r) => {
                        for (&i, p) in batch.iter().zip(r.into_inner().parts) {
                            known[i] = Some(p);
                        }
                    }
                    // Not held any more, or parts this orchestrator refuses: asking again
                    // would get the same answer.
                    Err(s)
                        if matches!(
                            s.code(),
                            tonic::Code::FailedPrecondition
                                | tonic::Code::InvalidArgument
                                | tonic::Code::PermissionDenied
                        ) =>
                    {
                        return Err(self.stop(fail(
                            FailureKind::Worker,
                            format!("adding parts: {}", s.message()),
                        )))
                    }
                    Err(s) => {
                        // The orchestrator may be restarting: ask again.
                        tracing::warn!(error = %s.message(), "adding parts failed; retrying");
                        answered = false;
                        break;
                    }
                }
            }
            if !answered {
                std::thread::sleep(POLL);
                continue;
            }
            if let Some((i, p)) = known.iter().enumerate().find_map(|(i, p)| {
                p.as_ref()
                    .filter(|p| matches!(state(p), "failed" | "cancelled"))
                    .map(|p| (i, p))
            }) {
                let kind = convert::failure_kind_from_pb(p.failure).unwrap_or(FailureKind::Worker);
                let label = parts[i]
                    .part
                    .as_ref()
                    .map(|p| p.label())
                    .unwrap_or_default();
                return Err(self.stop(fail(kind, format!("{label} {}: {}", state(p), p.error))));
            }
            let done = known.iter().filter(|p| is_done(p)).count();
            let running = known
                .iter()
                .flatten()
                .filter(|p| state(p) == "running")
                .count();
            let of = specs.len();
            self.shared.set(
                from + (to - from) * done as f32 / of.max(1) as f32,
                format!("{stage}: {done} of {of} bricks done, {running} running"),
            );
            if done == of {
                return Ok(known
                    .into_iter()
                    .flatten()
                    .map(|p| DonePart {
                        id: p.id,
                        bytes: p.output_bytes,
                        worker: p.worker,
                    })
                    .collect());
            }
            if self.run_one_part() {
                wait = POLL / 2;
            } else {
                // Nothing to run here: wait, longer while no part finishes elsewhere.
                wait = if done > done_before {
                    POLL / 2
                } else {
                    (wait * 3 / 2).min(MAX_POLL)
                };
                std::thread::sleep(wait);
            }
        }
    }

    /// Leases one part (of any bricked job) and runs it here; false if none was queued.
    fn run_one_part(&self) -> bool {
        let mut orch = self.runner.orch.clone();
        let req = pb::LeaseRequest {
            worker: self.runner.worker.clone(),
            parts_only: true,
        };
        let Ok(reply) = self.handle.block_on(orch.lease(req)) else {
            return false;
        };
        let Some(lease) = reply.into_inner().lease else {
            return false;
        };
        let held = HeldLease::of(&lease);
        match lease.spec.clone().map(convert::spec_from_pb) {
            Some(Ok(spec)) => self
                .handle
                .block_on(run_part_lease(&self.runner, lease, spec)),
            // As the worker's loop reports a lease it cannot read.
            Some(Err(e)) => {
                let f = fail(FailureKind::Worker, e.to_string());
                self.handle.block_on(fail_part(&self.runner, &held, f));
            }
            None => {
                let f = fail(FailureKind::Worker, "lease without a job spec");
                self.handle.block_on(fail_part(&self.runner, &held, f));
            }
        }
        true
    }

    /// The result of a done part.
    fn fetch(&self, part: u64) -> Result<Vec<u8>, Stopped> {
        let mut orch = self.runner.orch.clone();
        let req = self.parent_lease.request(pb::FetchResultRequest {
            parent_id: self.parent_id,
            parent_attempt: self.parent_lease.attempt,
            part_id: part,
        });
        let unavailable = |s: tonic::Status| {
            fail(
                FailureKind::Worker,
                format!("fetching the result of part {part}: {}", s.message()),
            )
        };
        let got = self.handle.block_on(async {
            let mut stream = orch.fetch_result(req).await?.into_inner();
            let mut bytes = Vec::new();
            while let Some(c) = stream.message().await? {
                bytes.extend_from_slice(&c.data);
            }
            Ok::<_, tonic::Status>(bytes)
        });
        got.map_err(|s| self.stop(unavailable(s)))
    }
}

impl BrickWork for RemoteBricks {
    /// The id of the part whose result is the brick's file.
    type File = u64;

    fn score_all(&self, plan: &BrickPlan) -> Result<Vec<ScoreSummary>, BrickError> {
        let energies = matches!(plan.target, Target::QvPercent(_));
        Ok(self.score_parts(plan.grid.len(), &plan.choices, energies)?)
    }

    fn encode_all(
        &self,
        plan: &BrickPlan,
        counts: Option<&[u64]>,
        trial: usize,
    ) -> Result<Vec<CodedBrick<u64>>, BrickError> {
        Ok(
            self.encode_parts(plan.grid.len(), &plan.choices, counts, trial, &|i| {
                plan.top_cap(i)
            })?,
        )
    }
}

/// Coordinates a bricked job whose source is on shared storage (its hash verified; `hashed`
/// the length of the bytes hashed, which every part checks the source against): returns the
/// bricked file and the volume's voxels. Runs on a blocking thread.
pub(crate) fn coordinate(
    runner: PartRunner,
    handle: tokio::runtime::Handle,
    spec: JobSpec,
    parent: HeldLease,
    hashed: Option<u64>,
    shared: Arc<Shared>,
) -> Result<(Output, u64), Failure> {
    let parent_id = parent.job_id;
    let brick = spec
        .options
        .brick
        .ok_or_else(|| fail(FailureKind::Worker, "not a bricked job"))?;
    let source = runner.source(&spec)?;
    let voxels = BrickSource::dims(&*source).iter().product::<u64>();
    shared.set(0.02, "planning the bricks");
    let mut opts = options::compress_options(&spec.options);
    opts.stop = shared.stop.clone();
    let pool = runner.pool.clone();
    let plan = pool.install(|| BrickPlan::new(&*source, &opts, brick).map_err(brick_failure))?;
    drop(source);
    tracing::info!(
        job = parent_id,
        bricks = plan.grid.len(),
        levels = plan.choices.levels,
        "bricks planned; spreading them over the queue"
    );
    let work = RemoteBricks {
        runner,
        handle,
        source_bytes: hashed,
        time_points: None,
        top_held_by: Default::default(),
        parent: spec,
        parent_id,
        parent_lease: parent,
        shared: shared.clone(),
        failure: std::sync::Mutex::new(None),
    };
    let allocated = allocate(&plan, &work).map_err(|e| work.failure_or(brick_failure(e)))?;
    let bricks = work.gather(&allocated.bricks)?;
    let file = write_output(|out| {
        plan.write_container(&bricks, out)
            .map(drop)
            .map_err(spill_failure)
    })?;
    Ok((file, voxels))
}

/// A failure of writing the gathered parts or the container: the scratch directory's (the
/// worker's) unless the parts' files are not what they claim.
fn spill_failure<E: Into<BrickError>>(e: E) -> Failure {
    match e.into() {
        BrickError::Spill(e) | BrickError::Output(e) => output_failure(e),
        e => fail(FailureKind::Worker, format!("the parts' files: {e}")),
    }
}

/// Coordinates a job whose source on shared storage is a time series: planned here
/// ([`SeriesPlan::new`], groups of the job's `time_group`), every unit (a temporal component's
/// brick) scored and coded as a part on any worker, the series' rate allocated over the units
/// as in one process, and the container assembled and committed once (`hashed` as for
/// [`coordinate`]). Returns the series file and its voxels over every time point. Runs on a
/// blocking thread.
// The allocation's closures return `allocate_units`' error type, which the compressor fixes.
#[allow(clippy::result_large_err)]
pub(crate) fn coordinate_series(
    runner: PartRunner,
    handle: tokio::runtime::Handle,
    spec: JobSpec,
    parent: HeldLease,
    hashed: Option<u64>,
    shared: Arc<Shared>,
) -> Result<(Output, u64), Failure> {
    let parent_id = parent.job_id;
    let input = runner.series(&spec)?;
    let series = input.source();
    let points = series.time_points();
    let voxels = series.dims().iter().product::<u64>() * points as u64;
    shared.set(0.02, format!("planning {points} time points"));
    let (group, brick) = series_shape(&spec);
    let mut opts = options::compress_options(&spec.options);
    opts.stop = shared.stop.clone();
    let pool = runner.pool.clone();
    let plan = pool
        .install(|| SeriesPlan::new(series, &opts, group, brick))
        .map_err(series_failure)?;
    tracing::info!(
        job = parent_id,
        time_points = points,
        components = plan.plans.len(),
        units = plan.units.len(),
        levels = plan.choices.levels,
        "series planned; spreading its units over the queue"
    );
    let work = RemoteBricks {
        runner,
        handle,
        source_bytes: hashed,
        time_points: Some(points as u32),
        top_held_by: Default::default(),
        parent: spec,
        parent_id,
        parent_lease: parent,
        shared: shared.clone(),
        failure: std::sync::Mutex::new(None),
    };
    let of = plan.units.len();
    let energies = matches!(plan.target, Target::QvPercent(_));
    let allocated = allocate_units(
        plan.target,
        of,
        plan.overhead,
        None,
        || {
            let summaries = work.score_parts(of, &plan.choices, energies)?;
            Ok(summaries)
        },
        |counts, trial| {
            let coded =
                work.encode_parts(of, &plan.choices, counts, trial, &|u| plan.unit_top_cap(u))?;
            Ok(coded)
        },
    )
    .map_err(|e| work.failure_or(brick_failure(e)))?;
    let units = work.gather(&allocated.bricks)?;
    let file = write_output(|out| {
        plan.write_container(series, &units, out)
            .map(drop)
            .map_err(|e| match e {
                SeriesError::Brick(e) => spill_failure(*e),
                e => series_failure(e),
            })
    })?;
    Ok((file, voxels))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A worker keeps the tops of up to [`TOPS_PARENTS`] parents at once: a parent's parts
    /// find the tops its earlier parts kept, whichever parents' parts ran between, and a
    /// parent beyond the slots takes the place of the one no part used for longest.
    #[test]
    fn tops_are_kept_per_parent_and_the_least_recently_used_go_first() {
        let slot = PartTops::default();
        let runner_tops = |parent: u64| {
            let mut held = slot.lock().unwrap();
            let budget = if parent == 200 { 1 << 10 } else { 1 << 20 };
            held.of_parent(parent, || KeptTops::new(budget))
        };
        let first: Vec<Arc<KeptTops>> = (0..TOPS_PARENTS as u64).map(runner_tops).collect();
        // Interleaved parts of the parents held find their own tops.
        for (parent, tops) in first.iter().enumerate().rev() {
            assert!(Arc::ptr_eq(tops, &runner_tops(parent as u64)), "{parent}");
        }
        // Parent 0 was used last (the loop ran backwards): a new parent takes the place of
        // the last one, which no part used for longest.
        let oldest = TOPS_PARENTS as u64 - 1;
        let newcomer = runner_tops(100);
        assert_eq!(slot.lock().unwrap().parents.len(), TOPS_PARENTS);
        assert!(Arc::ptr_eq(&first[0], &runner_tops(0)));
        assert!(Arc::ptr_eq(&newcomer, &runner_tops(100)));
        assert!(!Arc::ptr_eq(&first[oldest as usize], &runner_tops(oldest)));
        // Every parent's tops draw on the one memory of the worker; the tops no longer held
        // let go of it once no part holds them.
        drop((first, newcomer));
        let memory = slot.lock().unwrap().memory.clone();
        assert_eq!(Arc::strong_count(&memory), 2 + TOPS_PARENTS);
        assert_eq!(memory.budget(), 1 << 20);
        // A job under a tighter memory limit leaves less for tops: all parents' tops together
        // stay within it while it is held, and the whole budget comes back when none is held.
        let tight = runner_tops(200);
        assert_eq!(memory.budget(), 1 << 10);
        assert_eq!(tight.budget(), 1 << 10);
        drop(tight);
        // Idle, all are dropped, and with them their claims on the memory.
        release_idle_tops(&slot, Duration::ZERO);
        assert_eq!(memory.budget(), TOP_BUDGET);
        assert!(slot.lock().unwrap().parents.is_empty());
        assert_eq!(Arc::strong_count(&memory), 2);
        assert_eq!(memory.used(), 0);
    }

    /// A job under a memory limit too tight for the tops other jobs' parts kept on this worker
    /// has them dropped when its first part comes (the least recently used first), so that
    /// what the worker holds keeps to the tightest limit held; tops that fit stay.
    #[test]
    fn a_job_under_a_tighter_memory_limit_drops_the_tops_that_exceed_it() {
        use wavesplat_compressor::encode::{CompressOptions, Effort};
        use wavesplat_compressor::phantom::Phantom;
        let v = Phantom::Ct.generate([48, 40, 32]);
        let opts = CompressOptions {
            target: Target::Fraction(0.05),
            ..Effort::Fast.options()
        };
        let plan = BrickPlan::new(&v, &opts, 16).unwrap();
        let slot = PartTops::default();
        let dir = tempfile::tempdir().unwrap();
        let tops_of = |parent: u64, budget: u64| {
            let mut held = slot.lock().unwrap();
            held.of_parent(parent, || {
                KeptTops::new(budget).spilling_in(Some(dir.path()))
            })
        };
        // Two jobs' parts keep the tops of some bricks each.
        let keep = |tops: &KeptTops, bricks: std::ops::Range<usize>| {
            for i in bricks {
                plan.score_into(&v, i, tops, 0, plan.top_cap(i)).unwrap();
            }
            tops.memory_bytes()
        };
        let first = keep(&tops_of(1, 1 << 20), 0..4);
        let second = keep(&tops_of(2, 1 << 20), 4..6);
        assert!(first > second && second > 0, "{first} {second}");
        let memory = slot.lock().unwrap().memory.clone();
        assert_eq!(memory.used(), first + second);
        // Job 1's parts ran last.
        tops_of(1, 1 << 20);
        // A job whose limit leaves room for job 1's tops but not for both: job 2's go (used
        // least recently), job 1's stay.
        let roomy = tops_of(3, first + second - 1);
        assert_eq!(memory.used(), first);
        let held = |p: u64| slot.lock().unwrap().parents.iter().any(|t| t.parent == p);
        assert!(held(1) && !held(2) && held(3));
        drop(roomy);
        // A job whose limit leaves nothing for tops: every other job's that holds any go (job
        // 3's hold nothing and may stay).
        let tight = tops_of(4, 0);
        assert_eq!(memory.used(), 0);
        assert!(!held(1) && held(4));
        // Its own parts keep their tops in the temporary file: only their metadata in memory.
        keep(&tight, 0..2);
        assert!(tight.spilled() == 2 && tight.budgeted_bytes() == 0);
        assert_eq!(memory.used(), tight.memory_bytes());
        drop(tight);
        // That metadata is no reason to drop the tops of the next job, nor its own: the next
        // job's go to the temporary file too while the tight job is held.
        let next = tops_of(5, 1 << 20);
        keep(&next, 2..3);
        assert!(held(4) && held(5));
        assert_eq!(next.spilled(), 1);
        assert_eq!(memory.budget(), 0);
    }
}
