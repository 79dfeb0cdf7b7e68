//! The wavesplat worker: a stateless loop that leases a job, heartbeats with progress while it reads,
//! compresses (on its own rayon pool) and uploads the result to the cache, then reports the
//! outcome. Every failure is classified ([`FailureKind`]) so the orchestrator knows whether a
//! retry can help. A worker that loses its lease (expired, or the job was cancelled) stops its
//! compression at the next stage (the options' `StopFlag`) and reports nothing; a worker
//! killed mid-job simply stops heartbeating and the job runs elsewhere.
//! Cache ingest is idempotent by content hash and the compressor is deterministic, so a job
//! that ran twice lands once. A job with a brick size compresses a bricked volume on the
//! worker's pool; a file on shared storage is then hashed in pieces and read brick by brick,
//! never whole.
//!
//! The worker is its own crate so that the orchestrator server links no encoder: the job's
//! options are the orchestrator's domain types, mapped to the compressor's in [`options`].
//!
//! ```no_run
//! # async fn demo() -> Result<(), wavesplat_worker::WorkerError> {
//! let cfg = wavesplat_worker::WorkerOptions {
//!     orchestrator: "http://127.0.0.1:50052".into(),
//!     cache: "http://127.0.0.1:50051".into(),
//!     threads: 2,
//!     id: wavesplat_worker::default_worker_id(),
//!     max_jobs: None,
//!     pause_before_upload_ms: 0,
//!     pause_before_part_report_ms: 0,
//!     connect: Default::default(),
//! };
//! wavesplat_worker::run(cfg, async { let _ = tokio::signal::ctrl_c().await; }).await?;
//! # Ok(()) }
//! ```

pub mod archive;
pub mod options;
mod parts;

use std::future::Future;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;
use thiserror::Error;
use tonic::Code;
use wavesplat_client::{CacheClient, ConnectOptions};
use wavesplat_codec::volume::Volume;
use wavesplat_compressor::bricked::{compress_bricked_to, BrickError, BrickSource, BrickStage};
use wavesplat_compressor::encode::{compress, Stage, StopFlag};
use wavesplat_compressor::reader::region::RegionReader;
use wavesplat_compressor::reader::{
    decode_raw, decode_source_channel, keep_channel, unpack_bundle, ReadError, SourceFiles,
    SourceListing,
};
use wavesplat_net::digest::sha256;
use wavesplat_orchestrator_client::convert;
use wavesplat_orchestrator_client::model::{
    Delivery, Failure, FailureKind, JobSpec, Outcome, Source,
};
use wavesplat_orchestrator_client::{self as client, Client, HeldLease};
use wavesplat_proto::pb;

/// Worker settings.
#[derive(Debug, Clone)]
pub struct WorkerOptions {
    /// Orchestrator URL (`http://HOST:PORT`).
    pub orchestrator: String,
    /// Cache URL.
    pub cache: String,
    /// Compression threads (rayon pool size; 0: one per core).
    pub threads: usize,
    /// Identity shown in job listings.
    pub id: String,
    /// Stop after this many jobs (`None`: run until shut down).
    pub max_jobs: Option<usize>,
    /// Testing aid: pause this long after compressing, before uploading (ms).
    pub pause_before_upload_ms: u64,
    /// Testing aid: pause this long after computing a part of a bricked job, before reporting
    /// its result (ms).
    pub pause_before_part_report_ms: u64,
    /// CA and token for both services (the token needs the `worker` role at the orchestrator
    /// and `ingest` at the cache).
    pub connect: ConnectOptions,
}

/// Errors that stop a worker (job failures are reported to the orchestrator instead).
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum WorkerError {
    /// The orchestrator client could not be set up.
    #[error(transparent)]
    Orchestrator(#[from] wavesplat_orchestrator_client::ClientError),
    /// The thread pool could not be built.
    #[error("thread pool: {0}")]
    Pool(#[from] rayon::ThreadPoolBuildError),
    /// The cache client could not be set up.
    #[error(transparent)]
    Cache(#[from] wavesplat_client::ClientError),
}

/// A default worker identity: host name and process id.
pub fn default_worker_id() -> String {
    let host = std::env::var("HOSTNAME")
        .ok()
        .or_else(|| std::fs::read_to_string("/etc/hostname").ok())
        .map(|h| h.trim().to_string())
        .filter(|h| !h.is_empty())
        .unwrap_or_else(|| "worker".into());
    format!("{host}-{}", std::process::id())
}

struct Ctx {
    cfg: WorkerOptions,
    orch: Client,
    cache: CacheClient,
    pool: Arc<rayon::ThreadPool>,
    /// The source its parts read last, kept open ([`parts::PartRunner::opened`]).
    opened: Arc<Mutex<Option<parts::OpenedSource>>>,
    /// The tops its score parts kept ([`parts::PartRunner::tops`]).
    tops: parts::PartTops,
}

/// Runs the worker until `shutdown` completes (checked between jobs, so a running job is
/// finished first) or `max_jobs` jobs were run.
pub async fn run(
    cfg: WorkerOptions,
    shutdown: impl Future<Output = ()> + Send,
) -> Result<(), WorkerError> {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(cfg.threads)
        .thread_name(|i| format!("compress-{i}"))
        .build()?;
    let orch = client::connect_lazy(&cfg.orchestrator, &cfg.connect)?;
    let cache = CacheClient::connect_lazy(&cfg.cache, &cfg.connect)?;
    let mut ctx = Ctx {
        cfg,
        orch,
        cache,
        pool: Arc::new(pool),
        opened: Default::default(),
        tops: Default::default(),
    };
    tokio::pin!(shutdown);
    let mut done = 0usize;
    let mut backoff = wavesplat_net::backoff::Backoff::default();
    tracing::info!(worker = %ctx.cfg.id, scratch = %tempfile::env::temp_dir().display(), "worker started");
    remove_stale_uploads();
    loop {
        if ctx.cfg.max_jobs.is_some_and(|m| done >= m) {
            break;
        }
        let req = pb::LeaseRequest {
            worker: ctx.cfg.id.clone(),
            parts_only: false,
        };
        let reply = tokio::select! {
            _ = &mut shutdown => break,
            r = ctx.orch.lease(req) => r,
        };
        let wait = match reply {
            Err(status) => {
                tracing::warn!(error = %status.message(), "orchestrator unreachable; retrying");
                backoff.next_delay()
            }
            Ok(r) => {
                backoff.reset();
                let r = r.into_inner();
                match r.lease {
                    Some(lease) => {
                        run_lease(&mut ctx, lease).await;
                        done += 1;
                        continue;
                    }
                    None => {
                        parts::release_idle_tops(&ctx.tops, parts::TOPS_IDLE);
                        Duration::from_millis(u64::from(r.retry_after_ms.max(10)))
                    }
                }
            }
        };
        tokio::select! {
            _ = &mut shutdown => break,
            _ = tokio::time::sleep(wait) => {}
        }
    }
    tracing::info!(worker = %ctx.cfg.id, jobs = done, "worker stopped");
    Ok(())
}

/// Progress shared between the job and its heartbeat task, and the lease's loss: the
/// heartbeat raises `stop` with it, so that the compression ends at its next stage instead of
/// running on for a result nobody takes (a cancelled job's worker is free again at once).
pub(crate) struct Shared {
    progress: Mutex<(f32, String)>,
    lost: AtomicBool,
    pub(crate) stop: StopFlag,
}

impl Default for Shared {
    fn default() -> Shared {
        Shared {
            progress: Mutex::default(),
            lost: AtomicBool::new(false),
            stop: StopFlag::new(),
        }
    }
}

impl Shared {
    /// Whether the lease was lost; if so, logs how the work of `job` ended (`part` for a part
    /// of a spread job): its result discarded, or its work ended early (stopped or failed).
    pub(crate) fn lost_after<T>(
        &self,
        job: u64,
        attempt: u32,
        outcome: &Result<T, Failure>,
        part: bool,
    ) -> bool {
        if !self.lost.load(Ordering::SeqCst) {
            return false;
        }
        let whose = if part { "part's " } else { "" };
        match outcome {
            Ok(_) => tracing::warn!(job, attempt, "lease lost; {whose}result discarded"),
            Err(f) => tracing::warn!(
                job,
                attempt,
                reason = %f.message,
                "lease lost; {whose}work ended before it finished"
            ),
        }
        true
    }

    /// The lease is lost: the result will not be taken, and the work stops.
    fn lose(&self) {
        self.lost.store(true, Ordering::SeqCst);
        self.stop.stop();
    }

    /// Reports a stage; the fraction never goes back (the compressor's stages repeat: a byte
    /// target's rate trials, a second decomposition depth).
    pub(crate) fn set(&self, p: f32, stage: impl Into<String>) {
        if let Ok(mut g) = self.progress.lock() {
            *g = (g.0.max(p), stage.into());
        }
    }
}

fn stage_progress(stage: Stage, f: f64) -> (f32, String) {
    let f = f.clamp(0.0, 1.0) as f32;
    match stage {
        Stage::Color => (0.1, "colour transform".into()),
        Stage::Transform(c) => (0.1 + 0.4 * f, format!("wavelet transform, channel {c}")),
        Stage::Sort => (0.5 + 0.1 * f, "scoring".into()),
        Stage::Refine => (0.55, "refinement".into()),
        Stage::Encode(t) => (0.6 + 0.3 * f, format!("entropy coding (trial {t})")),
        Stage::Depth(m) => (0.05, format!("trying decomposition depth M = {m}")),
    }
}

impl Ctx {
    fn part_runner(&self) -> parts::PartRunner {
        parts::PartRunner {
            orch: self.orch.clone(),
            pool: self.pool.clone(),
            worker: self.cfg.id.clone(),
            pause_ms: self.cfg.pause_before_part_report_ms,
            opened: self.opened.clone(),
            tops: self.tops.clone(),
        }
    }
}

async fn run_lease(ctx: &mut Ctx, lease: pb::Lease) {
    let held = HeldLease::of(&lease);
    let (id, attempt) = (held.job_id, held.attempt);
    let spec = match lease.spec.clone().map(convert::spec_from_pb) {
        Some(Ok(s)) => Ok(s),
        Some(Err(e)) => Err(e.to_string()),
        None => Err("lease without a job spec".to_string()),
    };
    if let Ok(spec) = &spec {
        if spec.part.is_some() {
            return parts::run_part_lease(&ctx.part_runner(), lease, spec.clone()).await;
        }
    }
    // A source kept open for parts is let go before a job of its own (a bricked job opens its
    // source again, once).
    if let Ok(mut opened) = ctx.opened.lock() {
        opened.take();
    }
    tracing::info!(job = id, attempt, "running");
    let shared = Arc::new(Shared::default());
    let heartbeat = tokio::spawn(heartbeat_loop(
        ctx.orch.clone(),
        held.clone(),
        ctx.cfg.id.clone(),
        Duration::from_millis(u64::from(lease.heartbeat_ms.max(50))),
        shared.clone(),
    ));
    let outcome = match spec {
        Ok(spec) => execute(ctx, &held, &spec, &shared).await,
        Err(message) => Err(Failure {
            kind: FailureKind::Worker,
            message,
        }),
    };
    heartbeat.abort();
    if shared.lost_after(id, attempt, &outcome, false) {
        return;
    }
    let outcome = match outcome {
        Ok(d) => Outcome::Delivered(d),
        Err(f) => {
            tracing::warn!(job = id, attempt, kind = f.kind.name(), reason = %f.message, "attempt failed");
            Outcome::Failed(f)
        }
    };
    report(&mut ctx.orch, &ctx.cfg.id, &held, outcome).await;
}

/// Heartbeats the lease `held` every `every` with the progress in `shared` until aborted, or
/// until the orchestrator says the lease is lost (then `shared.lost` is set).
async fn heartbeat_loop(
    mut orch: Client,
    held: HeldLease,
    worker: String,
    every: Duration,
    shared: Arc<Shared>,
) {
    let (id, attempt) = (held.job_id, held.attempt);
    loop {
        tokio::time::sleep(every).await;
        let (progress, stage) = shared
            .progress
            .lock()
            .map(|g| g.clone())
            .unwrap_or_default();
        let req = pb::HeartbeatRequest {
            job_id: id,
            attempt,
            worker: worker.clone(),
            progress,
            stage,
        };
        match orch.heartbeat(held.request(req)).await {
            Ok(r) if !r.get_ref().keep_going => {
                tracing::warn!(job = id, reason = %r.get_ref().reason, "lease lost; stopping its work");
                shared.lose();
                return;
            }
            Ok(_) => {}
            // The orchestrator does not take this worker for the lease's holder (its token is
            // not the lease's): nothing it reports will be accepted.
            Err(s) if s.code() == Code::PermissionDenied => {
                tracing::warn!(job = id, attempt, error = %s.message(), "lease refused; stopping its work");
                shared.lose();
                return;
            }
            // The orchestrator may be restarting: keep working, keep trying.
            Err(s) => tracing::debug!(job = id, error = %s.message(), "heartbeat failed"),
        }
    }
}

/// Reports the outcome of the lease `held`, retrying while the orchestrator is unreachable (it
/// may be restarting).
async fn report(orch: &mut Client, worker: &str, held: &HeldLease, outcome: Outcome) {
    let (id, attempt) = (held.job_id, held.attempt);
    let outcome = match outcome {
        Outcome::Delivered(d) => pb::finish_request::Outcome::Delivered(pb::Delivered {
            cache_volume_id: d.cache_volume_id,
            output_bytes: d.output_bytes,
            voxels: d.voxels,
            existed: d.existed,
            sha256: d.sha256,
        }),
        Outcome::Failed(f) => pb::finish_request::Outcome::Failure(pb::Failure {
            kind: convert::failure_kind_to_pb(f.kind) as i32,
            message: f.message,
        }),
    };
    let req = pb::FinishRequest {
        job_id: id,
        attempt,
        worker: worker.to_string(),
        outcome: Some(outcome),
    };
    let orch = &*orch;
    until_answered(id, attempt, || {
        let (mut orch, req) = (orch.clone(), req.clone());
        let req = held.request(req);
        async move { orch.finish(req).await.map(|r| r.into_inner()) }
    })
    .await;
}

/// Sends a job's outcome with `send`, again while the orchestrator does not answer (it may be
/// restarting), for up to 10 minutes; a refusal (the lease lost, the job unknown, the request
/// invalid, the lease or the worker not recognised) ends it. Logs how it ended.
async fn until_answered<F, Fut>(id: u64, attempt: u32, mut send: F)
where
    F: FnMut() -> Fut,
    Fut: Future<Output = Result<pb::Job, tonic::Status>>,
{
    let deadline = tokio::time::Instant::now() + Duration::from_secs(600);
    let mut wait = Duration::from_millis(100);
    loop {
        match send().await {
            Ok(j) => {
                tracing::info!(
                    job = id,
                    attempt,
                    state = convert::state_name(j.state),
                    "reported"
                );
                return;
            }
            Err(s)
                if matches!(
                    s.code(),
                    Code::FailedPrecondition
                        | Code::NotFound
                        | Code::InvalidArgument
                        | Code::PermissionDenied
                ) =>
            {
                tracing::warn!(job = id, attempt, error = %s.message(), "outcome refused");
                return;
            }
            Err(s) if tokio::time::Instant::now() >= deadline => {
                tracing::error!(job = id, attempt, error = %s.message(), "giving up reporting");
                return;
            }
            Err(s) => {
                tracing::warn!(job = id, error = %s.message(), "reporting failed; retrying");
                tokio::time::sleep(wait).await;
                wait = (wait * 2).min(Duration::from_secs(2));
            }
        }
    }
}

fn fail(kind: FailureKind, message: impl Into<String>) -> Failure {
    Failure {
        kind,
        message: message.into(),
    }
}

async fn fetch_source(ctx: &mut Ctx, held: &HeldLease, spec: &JobSpec) -> Result<Vec<u8>, Failure> {
    match &spec.source {
        Source::Path(p) => {
            let (p, raw) = (p.clone(), spec.raw.is_some());
            tokio::task::spawn_blocking(move || {
                crate::archive::source_bytes(&p, raw).map_err(|e| {
                    fail(
                        FailureKind::SourceUnavailable,
                        format!("cannot read {}: {e}", p.display()),
                    )
                })
            })
            .await
            .map_err(|e| fail(FailureKind::Worker, format!("reading task: {e}")))?
        }
        Source::Upload { size } => {
            let mut stream = upload_stream(ctx, held).await?;
            let mut bytes = Vec::with_capacity((*size).min(1 << 30) as usize);
            while let Some(c) = stream.message().await.map_err(upload_unavailable)? {
                bytes.extend_from_slice(&c.data);
            }
            Ok(bytes)
        }
    }
}

/// The stream of the uploaded source of the job leased as `held` from the orchestrator.
async fn upload_stream(
    ctx: &mut Ctx,
    held: &HeldLease,
) -> Result<tonic::Streaming<pb::SourceChunk>, Failure> {
    Ok(ctx
        .orch
        .fetch_source(held.request(pb::FetchSourceRequest {
            job_id: held.job_id,
            attempt: held.attempt,
        }))
        .await
        .map_err(upload_unavailable)?
        .into_inner())
}

fn upload_unavailable(s: tonic::Status) -> Failure {
    fail(
        FailureKind::SourceUnavailable,
        format!("fetching the uploaded source: {}", s.message()),
    )
}

/// The whole volume of a job's source on shared storage, read in place by region (the job's
/// channel of it).
fn read_in_place(spec: &JobSpec) -> Result<Volume, Failure> {
    let Source::Path(path) = &spec.source else {
        return Err(fail(FailureKind::Worker, "an upload read in place"));
    };
    let invalid = |e: ReadError| {
        fail(
            FailureKind::InvalidInput,
            format!("{}: {e}", path.display()),
        )
    };
    let raw = spec.raw.as_ref().map(options::raw_spec);
    let reader = RegionReader::open_channel(path, raw.as_ref(), channel(spec)).map_err(invalid)?;
    reader.read_region([0; 3], reader.dims()).map_err(invalid)
}

/// The one channel a job reads of its source, if it chose one.
pub(crate) fn channel(spec: &JobSpec) -> Option<usize> {
    spec.channel.map(|c| c as usize)
}

fn decode(spec: &JobSpec, bytes: Vec<u8>) -> Result<Volume, Failure> {
    let invalid = |e: &dyn std::fmt::Display| fail(FailureKind::InvalidInput, e.to_string());
    match (&spec.raw, &spec.source) {
        (Some(layout), _) => {
            let raw = options::raw_spec(layout);
            let origin = std::path::PathBuf::from(&spec.name);
            decode_raw(&bytes, &raw)
                .and_then(|v| keep_channel(v, channel(spec), &origin))
                .map_err(|e| invalid(&e))
        }
        // A file with a header, or a bundle of a volume's files; read from the verified bytes.
        (None, source) => {
            let origin = match source {
                Source::Path(p) => p.clone(),
                Source::Upload { .. } => std::path::PathBuf::from(&spec.name),
            };
            let src = SourceFiles::from_bytes(bytes, &origin).map_err(|e| invalid(&e))?;
            decode_source_channel(&src, None, channel(spec)).map_err(|e| match (e, source) {
                (ReadError::TimeSeries { points, .. }, Source::Upload { .. }) => {
                    uploaded_series_refused(&origin.display().to_string(), points)
                }
                (e, _) => invalid(&e),
            })
        }
    }
}

/// A job compressed whole (not bricked, not a time series) on a path whose compression would
/// need more than its memory limit, refused from its raw layout or its file's header alone,
/// before the source is read (reading and decoding it whole could already pass the limit). A
/// compressed file (`.gz`), which only reading inflates, an upload and a header that cannot be
/// read are left to the compressor's own check after decoding.
fn refuse_over_memory_limit(spec: &JobSpec) -> Result<(), Failure> {
    let (Some(limit), None, Source::Path(path)) =
        (spec.options.memory_limit, spec.options.brick, &spec.source)
    else {
        return Ok(());
    };
    let raw = spec.raw.as_ref().map(options::raw_spec);
    if archive::is_series_source(path, raw.as_ref()) {
        return Ok(());
    }
    let (dims, channels) = match &spec.raw {
        // Raw samples are decoded with all their channels, one kept after.
        Some(r) => (r.dims, r.channels),
        None if path
            .extension()
            .is_some_and(|e| e.eq_ignore_ascii_case("gz")) =>
        {
            return Ok(())
        }
        None => match RegionReader::open_channel(path, None, channel(spec)) {
            Ok(r) => (r.dims(), r.channels()),
            Err(_) => return Ok(()),
        },
    };
    let opts = options::compress_options(&spec.options);
    match wavesplat_compressor::encode::memory_estimate(dims, channels, &opts) {
        Ok((needed, detail)) if needed > limit => Err(fail(
            FailureKind::Compress,
            wavesplat_compressor::encode::CompressError::MemoryLimit {
                needed,
                limit,
                detail,
            }
            .to_string(),
        )),
        _ => Ok(()),
    }
}

/// Whether the job's source is on shared storage, read in place (a bricked volume brick by
/// brick, a time series time point by time point, a Zarr store by its chunks) and hashes,
/// streamed file by file ([`archive::source_digest`]), to the submitted SHA-256: its bytes are
/// then never held whole. Any source on a path: a raw or single-file volume, a detached
/// header and its data, a DICOM series directory (read by slice ranges), a 4D file or a
/// directory of time steps. A Zarr store compressed whole is read in place too: gathered, its
/// files would be held twice (as bytes and as a store in memory), all its channels for the
/// one a job reads. Returns the length of the bytes hashed when they match (`None`: not read
/// in place).
async fn hashed_in_place(spec: &JobSpec) -> Option<u64> {
    let Source::Path(p) = &spec.source else {
        return None;
    };
    let raw = spec.raw.as_ref().map(options::raw_spec);
    let zarr = spec.raw.is_none() && p.is_dir() && wavesplat_compressor::reader::zarr::is_store(p);
    if spec.options.brick.is_none() && !zarr && !archive::is_series_source(p, raw.as_ref()) {
        return None;
    }
    let (p, raw) = (p.clone(), spec.raw.is_some());
    let hashed = tokio::task::spawn_blocking(move || archive::source_digest(&p, raw)).await;
    match hashed {
        Ok(Ok((h, len))) if h == spec.sha256 => Some(len),
        _ => None,
    }
}

/// A job of a bricked volume (`--brick`) whose source is not read in place, on the worker's
/// pool: an uploaded one, read by region from the worker's temporary copy
/// ([`UploadedFile`]), or decoded whole and split when its bytes were fetched. (A source
/// on shared storage is read brick by brick by the workers its bricks are spread over,
/// [`parts::coordinate`].) Returns the bricked file and the volume's voxel count.
fn compress_bricked_job(
    source: &dyn BrickSource,
    brick: usize,
    opts: &wavesplat_compressor::encode::CompressOptions,
    sh: &Shared,
) -> Result<(Output, u64), Failure> {
    let voxels = source.dims().iter().product::<u64>();
    sh.set(0.05, "reading bricks");
    let report = |stage: BrickStage| {
        let p = match stage {
            BrickStage::Scored { done, of } => 0.05 + 0.25 * done as f32 / of.max(1) as f32,
            BrickStage::Compressed { done, of, .. } => 0.3 + 0.6 * done as f32 / of.max(1) as f32,
        };
        sh.set(p, stage.to_string());
    };
    // The coded bricks wait in the scratch directory, and the container is written there:
    // a bricked file may be larger than the worker's memory.
    let file = write_output(|out| {
        compress_bricked_to(source, opts, brick, &report, None, None, out)
            .map(drop)
            .map_err(|e| match e {
                BrickError::Spill(e) | BrickError::Output(e) => output_failure(e),
                e => fail(FailureKind::Compress, e.to_string()),
            })
    })?;
    Ok((file, voxels))
}

/// The job's output written by `write` to a temporary file in the scratch directory, not to
/// memory: a bricked volume or a series may be larger than the worker's memory.
pub(crate) fn write_output(
    write: impl FnOnce(&mut dyn std::io::Write) -> Result<(), Failure>,
) -> Result<Output, Failure> {
    let mut out = std::io::BufWriter::new(tempfile::tempfile().map_err(output_failure)?);
    write(&mut out)?;
    let file = out
        .into_inner()
        .map_err(|e| output_failure(e.into_error()))?;
    Ok(Output::File(file))
}

/// A compressed volume on its way to the cache: in memory, or in a temporary file in the
/// scratch directory (a bricked volume or a series, which may be larger than memory), sent
/// from there chunk by chunk.
pub(crate) enum Output {
    Bytes(Vec<u8>),
    File(std::fs::File),
}

impl Output {
    fn len(&self) -> Result<u64, Failure> {
        match self {
            Output::Bytes(b) => Ok(b.len() as u64),
            Output::File(f) => f.metadata().map(|m| m.len()).map_err(output_failure),
        }
    }
}

/// A failure to keep a job's output (or its coded parts) in the scratch directory: the worker's
/// fault (its disk), retried elsewhere.
pub(crate) fn output_failure(e: std::io::Error) -> Failure {
    fail(
        FailureKind::Worker,
        format!("keeping the compressed file in the scratch directory: {e}"),
    )
}

/// An uploaded source of a bricked job, streamed to disk as it arrives (and hashed on the
/// way), so that the worker never holds it whole: its bricks are read by region, as from
/// shared storage. A single file is named for its format (by the job's layout or name, else
/// its first bytes), which is how the region reader knows it; a bundle of several files (a
/// detached header and its data, a DICOM series) is unpacked file by file as it streams
/// ([`unpack_bundle`]), and `path` is what opens it (the series' directory, or the header).
/// The directory goes when this is dropped.
struct UploadedFile {
    /// Held (and locked) while the upload is in use; closed before the directory goes.
    _lock: std::fs::File,
    _dir: tempfile::TempDir,
    /// The directory the upload's files are in.
    source: std::path::PathBuf,
    /// What opens it: the single file, a bundle's header or its series' directory.
    path: std::path::PathBuf,
    sha256: [u8; 32],
}

/// Prefix of an upload's temporary directory. Each holds [`UPLOAD_LOCK`], locked by its worker
/// for as long as it lives: a worker starting removes those whose lock it can take (their
/// worker is gone: [`remove_stale_uploads`]).
const UPLOAD_DIR_PREFIX: &str = "wavesplat-upload-";

/// The lock file in an upload's temporary directory.
const UPLOAD_LOCK: &str = ".lock";

async fn fetch_upload_to_file(
    ctx: &mut Ctx,
    held: &HeldLease,
    spec: &JobSpec,
    size: u64,
) -> Result<UploadedFile, Failure> {
    let dir = tempfile::Builder::new()
        .prefix(UPLOAD_DIR_PREFIX)
        .tempdir()
        .map_err(scratch)?;
    let lock = std::fs::File::create(dir.path().join(UPLOAD_LOCK)).map_err(scratch)?;
    lock.try_lock().map_err(|e| scratch(e.into()))?;
    // The upload's own files go beside the lock, in a directory of their own (a bundle may
    // name any file).
    let source = dir.path().join("source");
    std::fs::create_dir(&source).map_err(scratch)?;
    // The disk side runs on a blocking thread reading the chunks as a stream, so that a
    // bundle is unpacked as it arrives rather than written whole and copied. It owns the
    // directory until it is done, so that nothing removes the directory under it.
    let (tx, rx) = tokio::sync::mpsc::channel::<Vec<u8>>(16);
    let (raw, name) = (spec.raw.is_some(), spec.name.clone());
    let sink = tokio::task::spawn_blocking(move || {
        let stored = store_upload(&mut ChunkReader::new(rx), &source, raw, &name);
        (dir, source, stored)
    });
    let mut digest = wavesplat_net::digest::Sha256Pieces::default();
    let received = async {
        let mut stream = upload_stream(ctx, held).await?;
        let mut written = 0u64;
        while let Some(c) = stream.message().await.map_err(upload_unavailable)? {
            written = written.saturating_add(c.data.len() as u64);
            if written > size {
                return Err(fail(
                    FailureKind::InvalidInput,
                    format!("the uploaded source is longer than the {size} bytes submitted"),
                ));
            }
            digest.update(&c.data);
            if tx.send(c.data).await.is_err() {
                // The disk side stopped: it says why.
                break;
            }
        }
        Ok(())
    }
    .await;
    drop(tx);
    let (dir, source, stored) = sink
        .await
        .map_err(|e| fail(FailureKind::Worker, format!("storing the upload: {e}")))?;
    received?;
    let path = stored?;
    Ok(UploadedFile {
        _lock: lock,
        _dir: dir,
        source,
        path,
        sha256: digest.finish(),
    })
}

/// A failure of this worker's own disk while it keeps an upload (worth a retry elsewhere).
fn scratch(e: std::io::Error) -> Failure {
    fail(
        FailureKind::Worker,
        format!("keeping the uploaded source in a temporary directory: {e}"),
    )
}

/// The blocking reader of an upload's chunks as they arrive ([`fetch_upload_to_file`]).
struct ChunkReader {
    rx: tokio::sync::mpsc::Receiver<Vec<u8>>,
    chunk: Vec<u8>,
    at: usize,
}

impl ChunkReader {
    fn new(rx: tokio::sync::mpsc::Receiver<Vec<u8>>) -> ChunkReader {
        ChunkReader {
            rx,
            chunk: Vec::new(),
            at: 0,
        }
    }
}

impl std::io::Read for ChunkReader {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        while self.at == self.chunk.len() {
            match self.rx.blocking_recv() {
                Some(c) => (self.chunk, self.at) = (c, 0),
                None => return Ok(0),
            }
        }
        let n = buf.len().min(self.chunk.len() - self.at);
        buf[..n].copy_from_slice(&self.chunk[self.at..self.at + n]);
        self.at += n;
        Ok(n)
    }
}

/// Writes an upload read from `r` into `dir`: a bundle (never for raw samples) unpacked into
/// its files, anything else as one file named for its format. Returns what opens it.
fn store_upload(
    r: &mut dyn std::io::Read,
    dir: &std::path::Path,
    raw: bool,
    job_name: &str,
) -> Result<std::path::PathBuf, Failure> {
    use std::io::{Read, Write};
    let mut head = Vec::with_capacity(512);
    r.take(512).read_to_end(&mut head).map_err(scratch)?;
    let mut rest = std::io::Cursor::new(&head).chain(r);
    if !raw && head.starts_with(wavesplat_compressor::reader::BUNDLE_MAGIC) {
        let unpacked = unpack_bundle(&mut rest, dir).map_err(|e| {
            // A malformed bundle is the submitter's; the disk failing is this worker's (and
            // worth a retry elsewhere).
            let kind = match e {
                ReadError::Bundle(_) => FailureKind::InvalidInput,
                _ => FailureKind::Worker,
            };
            fail(kind, format!("{job_name}: the uploaded bundle: {e}"))
        })?;
        tracing::info!(
            source = job_name,
            files = unpacked.files,
            bytes = unpacked.bytes,
            "uploaded bundle unpacked into a temporary directory"
        );
        return Ok(unpacked.primary);
    }
    let path = dir.join(upload_file_name(raw, job_name, &head));
    let mut file = std::io::BufWriter::new(std::fs::File::create(&path).map_err(scratch)?);
    std::io::copy(&mut rest, &mut file).map_err(scratch)?;
    file.flush().map_err(scratch)?;
    Ok(path)
}

/// Removes the upload directories ([`UPLOAD_DIR_PREFIX`]) in the temporary directory that
/// workers no longer running left behind (killed before they could clean up): those whose
/// lock file ([`UPLOAD_LOCK`]) this process can lock, which no live worker holds, on this host
/// or another sharing the directory. A directory without a lock file (one being created) is
/// left alone. Returns how many were removed.
pub fn remove_stale_uploads() -> usize {
    let Ok(entries) = std::fs::read_dir(tempfile::env::temp_dir()) else {
        return 0;
    };
    let mut removed = 0;
    for e in entries.flatten() {
        let name = e.file_name();
        if !name.to_string_lossy().starts_with(UPLOAD_DIR_PREFIX)
            || !e.file_type().is_ok_and(|t| t.is_dir())
        {
            continue;
        }
        let Ok(lock) = std::fs::File::open(e.path().join(UPLOAD_LOCK)) else {
            continue;
        };
        if lock.try_lock().is_err() {
            continue;
        }
        if std::fs::remove_dir_all(e.path()).is_ok() {
            tracing::info!(path = %e.path().display(), "removed an upload a dead worker left");
            removed += 1;
        }
    }
    removed
}

/// Refuses an upload whose header names a data file outside what was uploaded (an absolute
/// path, `..`, or a file the upload did not carry): the region reader would otherwise read
/// whatever file on this host the name points at, and deliver it to the cache. `primary` is
/// the uploaded header (or single file) in `dir`; a directory (a DICOM series) lists only its
/// own files.
fn confined(primary: &std::path::Path, dir: &std::path::Path, raw: bool) -> Result<(), Failure> {
    if raw || primary.is_dir() {
        return Ok(());
    }
    let refused = |m: String| fail(FailureKind::InvalidInput, m);
    let listing = SourceListing::list(primary, None).map_err(|e| {
        refused(format!(
            "the uploaded header names a file the upload does not carry, or cannot be read: {e}"
        ))
    })?;
    let root = std::fs::canonicalize(dir)
        .map_err(|e| fail(FailureKind::Worker, format!("the upload's directory: {e}")))?;
    for (name, path, _) in listing.files.iter().skip(1) {
        let inside = std::fs::canonicalize(path).is_ok_and(|p| p.starts_with(&root));
        if !inside {
            return Err(refused(format!(
                "the uploaded header names the data file {name:?}, which the upload does not \
                 carry: an uploaded header's data must come with it (archive submit \
                 --upload sends the files a header names beside it)"
            )));
        }
    }
    Ok(())
}

/// The name an uploaded source's temporary copy is given, which is how the region reader
/// knows its format: found as the in-memory decoder finds it, by the job's layout for raw
/// samples (whatever their first bytes look like), else by the job's name, else by the
/// source's first bytes (`head`).
fn upload_file_name(raw: bool, job_name: &str, head: &[u8]) -> &'static str {
    use wavesplat_compressor::reader::Format;
    if raw {
        return "source.raw";
    }
    let format = Format::from_name(std::path::Path::new(job_name)).or(Format::sniff(head));
    match format {
        Some(Format::Nifti) if head.starts_with(&[0x1f, 0x8b]) => "source.nii.gz",
        Some(Format::Nifti) => "source.nii",
        Some(Format::Nrrd) => "source.nrrd",
        Some(Format::MetaImage) => "source.mha",
        Some(Format::Dicom) => "source.dcm",
        Some(Format::Tiff) => "source.tif",
        // A store is several files, uploaded as a bundle; one alone is no volume.
        Some(Format::Zarr) => "source.zarr",
        None => "source.raw",
    }
}

/// The reader of an uploaded source's temporary copy (see [`UploadedFile`]).
fn open_upload(spec: &JobSpec, f: &UploadedFile) -> Result<RegionReader, Failure> {
    confined(&f.path, &f.source, spec.raw.is_some())?;
    let raw = spec.raw.as_ref().map(options::raw_spec);
    RegionReader::open_channel(&f.path, raw.as_ref(), channel(spec)).map_err(|e| match e {
        ReadError::TimeSeries { points, .. } => uploaded_series_refused(&spec.name, points),
        e => fail(FailureKind::InvalidInput, format!("{}: {e}", spec.name)),
    })
}

/// Why an uploaded time series fails its job (`name`: the source in the message), read in
/// memory or from the upload's temporary copy alike.
fn uploaded_series_refused(name: &str, points: usize) -> Failure {
    fail(
        FailureKind::InvalidInput,
        format!(
            "{name}: a time series of {points} time points, uploaded: workers compress a time \
             series read from shared storage (submit it without --upload), or compress it \
             locally and `cache ingest` the file"
        ),
    )
}

async fn execute(
    ctx: &mut Ctx,
    held: &HeldLease,
    spec: &JobSpec,
    shared: &Arc<Shared>,
) -> Result<Delivery, Failure> {
    let id = held.job_id;
    shared.set(0.0, "reading");
    // A whole volume over the job's memory limit is refused before its bytes are read.
    let early = spec.clone();
    tokio::task::spawn_blocking(move || refuse_over_memory_limit(&early))
        .await
        .map_err(|e| {
            fail(
                FailureKind::Worker,
                format!("checking the memory limit: {e}"),
            )
        })??;
    // A bricked job's file verified without holding it (its bricks are read from it), or the
    // source's bytes read and verified.
    let in_place = hashed_in_place(spec).await;
    // An uploaded source of a bricked job goes to a temporary file, not to memory.
    let mut uploaded = None;
    let bytes = if in_place.is_some() {
        Vec::new()
    } else if let (Some(_), Source::Upload { size }) = (spec.options.brick, &spec.source) {
        uploaded = Some(fetch_upload_to_file(ctx, held, spec, *size).await?);
        Vec::new()
    } else {
        fetch_source(ctx, held, spec).await?
    };
    let got = match &uploaded {
        Some(f) => f.sha256,
        None => sha256(&bytes),
    };
    if in_place.is_none() && got != spec.sha256 {
        // The hash found goes to the worker's log, not to the job's failure: whoever submits a
        // path could otherwise learn the SHA-256 of any file the worker can read (and confirm
        // a guess of its content).
        tracing::warn!(
            job = id,
            found = %wavesplat_net::digest::hex(&got),
            submitted = %wavesplat_net::digest::hex(&spec.sha256),
            "the source's SHA-256 is not the submitted one"
        );
        return Err(fail(
            FailureKind::InvalidInput,
            format!(
                "the source changed since submission: its SHA-256 is not the submitted {} \
                 (the one found is in the worker's log)",
                wavesplat_net::digest::hex(&spec.sha256)
            ),
        ));
    }
    let mut opts = options::compress_options(&spec.options);
    opts.stop = shared.stop.clone();
    let job_spec = spec.clone();
    let pool = ctx.pool.clone();
    let sh = shared.clone();
    let (runner, handle) = (ctx.part_runner(), tokio::runtime::Handle::current());
    let parent = held.clone();
    // The length of the source as hashed, which every part of a spread job checks the source
    // against (an uploaded source is never spread).
    let hashed = match &spec.source {
        Source::Path(_) => Some(in_place.unwrap_or(bytes.len() as u64)),
        Source::Upload { .. } => None,
    };
    let compressed = tokio::task::spawn_blocking(move || {
        if runner.series_if(&job_spec)?.is_some() {
            // A time series on shared storage: its units spread over the workers.
            drop(bytes);
            return parts::coordinate_series(runner, handle, job_spec, parent, hashed, sh);
        }
        if in_place.is_some() && job_spec.options.brick.is_some() {
            // A bricked volume on shared storage: its bricks spread over the workers.
            return parts::coordinate(runner, handle, job_spec, parent, hashed, sh);
        }
        if let Some(brick) = job_spec.options.brick {
            if let Some(f) = uploaded {
                let reader = open_upload(&job_spec, &f)?;
                return pool.install(|| compress_bricked_job(&reader, brick, &opts, &sh));
            }
            let volume = decode(&job_spec, bytes)?;
            return pool.install(|| compress_bricked_job(&volume, brick, &opts, &sh));
        }
        let volume = match in_place {
            // A Zarr store on shared storage, verified: read in place, its channel only.
            Some(_) => read_in_place(&job_spec)?,
            None => decode(&job_spec, bytes)?,
        };
        let voxels = volume.voxel_count() as u64;
        sh.set(0.05, "compressing");
        let progress = |stage: Stage, f: f64| {
            let (p, s) = stage_progress(stage, f);
            sh.set(p, s);
        };
        pool.install(|| compress(&volume, &opts, &progress))
            .map(|c| (Output::Bytes(c.bytes), voxels))
            .map_err(|e| fail(FailureKind::Compress, e.to_string()))
    })
    .await
    .map_err(|e| fail(FailureKind::Worker, format!("compression task: {e}")))??;
    let (file, voxels) = compressed;
    if ctx.cfg.pause_before_upload_ms > 0 {
        shared.set(0.9, "paused (testing aid)");
        tokio::time::sleep(Duration::from_millis(ctx.cfg.pause_before_upload_ms)).await;
    }
    if shared.lost.load(Ordering::SeqCst) {
        return Err(fail(FailureKind::Worker, "lease lost before upload"));
    }
    shared.set(0.9, "uploading");
    let output_bytes = file.len()?;
    let r = match file {
        Output::Bytes(b) => ctx.cache.ingest_owned(&spec.name, b).await,
        Output::File(f) => ctx.cache.ingest_file(&spec.name, f).await,
    }
    .map_err(|e| ingest_failure(&spec.name, e))?;
    let v = r.volume;
    tracing::info!(job = id, name = %spec.name, cache_id = v.id, bytes = output_bytes, existed = r.existed, "delivered");
    Ok(Delivery {
        cache_volume_id: v.id,
        output_bytes,
        voxels,
        existed: r.existed,
        sha256: v.sha256,
    })
}

/// Why delivering `name` to the cache failed, as the job's failure.
fn ingest_failure(name: &str, e: wavesplat_client::ClientError) -> Failure {
    if let wavesplat_client::ClientError::UploadRead(e) = e {
        return output_failure(e);
    }
    if e.code() == Some(Code::AlreadyExists) {
        // The same files compressed again with other options: say what to do.
        return fail(
            FailureKind::CacheRejected,
            format!(
                "the cache already has a volume named {name:?} with other content: submit with \
                 --name-suffix (e.g. _cubic) or --name-prefix to keep both, or remove it first \
                 (wavesplat cache rm {name})"
            ),
        );
    }
    let kind = match e.code() {
        Some(Code::InvalidArgument | Code::FailedPrecondition) => FailureKind::CacheRejected,
        _ => FailureKind::CacheUnavailable,
    };
    fail(kind, format!("cache ingest of {name:?}: {e}"))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An uploaded header may name only data the upload carried: an absolute path, a path out
    /// of the upload's directory and a file the upload lacks are refused (the region reader
    /// would read them from this host), a data file inside it is taken.
    #[test]
    fn an_uploaded_header_reads_no_file_outside_the_upload() {
        let outside = tempfile::tempdir().unwrap();
        let secret = outside.path().join("secret.raw");
        std::fs::write(&secret, [7u8; 4]).unwrap();
        let root = tempfile::tempdir().unwrap();
        let dir = root.path().join("source");
        std::fs::create_dir_all(dir.join("data")).unwrap();
        std::fs::write(dir.join("data/v.raw"), [1u8; 4]).unwrap();
        std::fs::write(root.path().join("beside.raw"), [1u8; 4]).unwrap();
        let header = |data: &str| {
            let h = dir.join("v.mhd");
            std::fs::write(
                &h,
                format!(
                    "ObjectType = Image\nNDims = 3\nDimSize = 2 2 1\nElementType = \
                     MET_UCHAR\nElementDataFile = {data}\n"
                ),
            )
            .unwrap();
            h
        };
        for data in [secret.to_str().unwrap(), "../beside.raw", "missing.raw"] {
            let e = confined(&header(data), &dir, false).unwrap_err();
            assert_eq!(e.kind, FailureKind::InvalidInput, "{data}");
            assert!(
                e.message.contains("does not carry"),
                "{data}: {}",
                e.message
            );
        }
        confined(&header("data/v.raw"), &dir, false).unwrap();
        // Raw samples and a DICOM directory name no other file.
        confined(&dir.join("data/v.raw"), &dir, true).unwrap();
        confined(&dir, &dir, false).unwrap();
    }

    /// A whole volume over its job's memory limit is refused from its raw layout or its
    /// header before any sample is read (here: a raw file that does not exist, and a header
    /// whose data file is sparse, 2 GiB of nothing on disk); under the limit, or bricked, it
    /// goes on to be read.
    #[test]
    fn a_whole_volume_over_its_memory_limit_is_refused_before_its_source_is_read() {
        use wavesplat_orchestrator_client::model::{JobOptions, RawLayout, SampleType};
        let dir = tempfile::tempdir().unwrap();
        let spec = |path: std::path::PathBuf, raw: Option<RawLayout>, limit, brick| JobSpec {
            name: "v".into(),
            source: Source::Path(path),
            sha256: [0; 32],
            raw,
            channel: None,
            options: JobOptions {
                memory_limit: limit,
                brick,
                ..JobOptions::default()
            },
            part: None,
        };
        let layout = Some(RawLayout {
            dims: [1024, 1024, 1024],
            dtype: SampleType::U16,
            big_endian: false,
            channels: 1,
        });
        let absent = dir.path().join("absent_1024x1024x1024_u16.raw");
        let refused =
            refuse_over_memory_limit(&spec(absent.clone(), layout.clone(), Some(8 << 30), None))
                .unwrap_err();
        assert_eq!(refused.kind, FailureKind::Compress);
        assert!(
            refused.message.contains("bytes of memory")
                && refused
                    .message
                    .contains(&format!("the limit is {} bytes", 8u64 << 30)),
            "{}",
            refused.message
        );
        // A header names the dimensions; its data file is not read.
        std::fs::File::create(dir.path().join("big.raw"))
            .unwrap()
            .set_len(2 << 30)
            .unwrap();
        let mhd = dir.path().join("big.mhd");
        std::fs::write(
            &mhd,
            "ObjectType = Image\nNDims = 3\nDimSize = 1024 1024 1024\nElementType = MET_USHORT\n\
             ElementDataFile = big.raw\n",
        )
        .unwrap();
        let refused = refuse_over_memory_limit(&spec(mhd, None, Some(8 << 30), None));
        assert!(refused.is_err_and(|f| f.kind == FailureKind::Compress));
        // Within the limit, without one, or bricked: nothing refused here.
        for (limit, brick) in [
            (Some(1u64 << 50), None),
            (None, None),
            (Some(8 << 30), Some(256)),
        ] {
            refuse_over_memory_limit(&spec(absent.clone(), layout.clone(), limit, brick)).unwrap();
        }
    }

    /// A worker starting removes the uploads whose lock nobody holds (their worker died), and
    /// leaves those of live workers and any directory without a lock file.
    #[test]
    fn only_uploads_of_dead_workers_are_removed() {
        let tmp = tempfile::env::temp_dir();
        let made = |tag: &str, lock: bool| {
            let d = tmp.join(format!(
                "{UPLOAD_DIR_PREFIX}test-{}-{tag}",
                std::process::id()
            ));
            std::fs::create_dir_all(d.join("source")).unwrap();
            if lock {
                std::fs::write(d.join(UPLOAD_LOCK), b"").unwrap();
            }
            d
        };
        let (dead, live, unlocked) = (made("dead", true), made("live", true), made("new", false));
        let held = std::fs::File::open(live.join(UPLOAD_LOCK)).unwrap();
        held.try_lock().unwrap();
        remove_stale_uploads();
        assert!(!dead.exists());
        assert!(live.exists() && unlocked.exists());
        drop(held);
        std::fs::remove_dir_all(live).unwrap();
        std::fs::remove_dir_all(unlocked).unwrap();
    }

    /// An upload's temporary copy is named for its format as the in-memory decoder finds it:
    /// raw samples stay raw even when their first bytes look like gzip or a header.
    #[test]
    fn an_uploaded_copy_is_named_for_its_format() {
        let gzip = [0x1f, 0x8b, 8, 0];
        assert_eq!(upload_file_name(true, "ct", &gzip), "source.raw");
        assert_eq!(
            upload_file_name(true, "ct.nrrd", b"NRRD0004\n"),
            "source.raw"
        );
        assert_eq!(upload_file_name(false, "ct", &gzip), "source.nii.gz");
        assert_eq!(upload_file_name(false, "ct", b"NRRD0004\n"), "source.nrrd");
        assert_eq!(
            upload_file_name(false, "head.mha", b"no header"),
            "source.mha"
        );
        assert_eq!(upload_file_name(false, "ct.nii", &[0; 8]), "source.nii");
        assert_eq!(upload_file_name(false, "ct", &[0; 8]), "source.raw");
    }

    #[test]
    fn reported_progress_never_goes_back_when_stages_repeat() {
        let shared = Shared::default();
        let mut seen = Vec::new();
        for (stage, f) in [
            (Stage::Depth(3), 0.0),
            (Stage::Transform(0), 0.5),
            (Stage::Encode(2), 1.0),
            (Stage::Depth(2), 0.0),
            (Stage::Transform(0), 0.0),
            (Stage::Refine, 0.0),
            (Stage::Encode(5), 1.0),
        ] {
            let (p, s) = stage_progress(stage, f);
            shared.set(p, s);
            seen.push(shared.progress.lock().unwrap().clone());
        }
        assert!(seen.windows(2).all(|w| w[1].0 >= w[0].0), "{seen:?}");
        assert_eq!(seen[3].1, "trying decomposition depth M = 2");
        assert!((seen[6].0 - 0.9).abs() < 1e-6, "{seen:?}");
    }
}
