//! The tonic service: each RPC converts and checks its request ([`crate::convert`]), asks the
//! [`JobStore`] (which makes the change durable before returning) and converts the answer. It
//! holds no queue state of its own, so orchestrators over one shared store are interchangeable.
//! A worker RPC on a lease takes the lease's token from the request metadata
//! ([`wavesplat_orchestrator_client::LEASE_TOKEN_METADATA`]) and the store checks it.

use crate::check::DeliveryCheck;
use crate::convert;
use crate::error::OrchestratorError;
use crate::jobstore::JobStore;
use crate::model::{LeaseToken, Outcome, Source};
use crate::queue::QueueOptions;
use std::pin::Pin;
use std::sync::Arc;
use tokio_stream::Stream;
use tonic::{Request, Response, Status, Streaming};
use wavesplat_net::digest::hex;
use wavesplat_net::status::client_fault;
use wavesplat_orchestrator_client::lease_token_of;
use wavesplat_proto::pb;
use wavesplat_proto::pb::orchestrator_server::Orchestrator;

pub use crate::queue::{system_clock, Clock};
pub use wavesplat_orchestrator_client::CHUNK_BYTES;

/// Service settings.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ServiceOptions {
    /// Lease, heartbeat and retry policy.
    pub queue: QueueOptions,
    /// Longest a worker waits before asking again when nothing is runnable (ms).
    pub poll_ms: u64,
    /// Largest accepted upload (bytes).
    pub max_upload_bytes: u64,
}

impl Default for ServiceOptions {
    fn default() -> Self {
        ServiceOptions {
            queue: QueueOptions::default(),
            poll_ms: 1000,
            max_upload_bytes: 1 << 30,
        }
    }
}

struct Shared {
    store: Arc<dyn JobStore>,
    cfg: ServiceOptions,
}

/// The `wavesplat.v1.Orchestrator` service.
#[derive(Clone)]
pub struct OrchestratorService {
    shared: Arc<Shared>,
    check: Option<DeliveryCheck>,
}

impl OrchestratorService {
    /// Builds the service over `store` (whose queue policy wins over `cfg.queue`).
    pub async fn new(
        store: Arc<dyn JobStore>,
        cfg: ServiceOptions,
    ) -> Result<OrchestratorService, OrchestratorError> {
        let counts = store.counts().await?;
        tracing::info!(
            queued = counts.queued,
            running = counts.running,
            done = counts.done,
            failed = counts.failed,
            cancelled = counts.cancelled,
            "queue restored"
        );
        Ok(OrchestratorService {
            shared: Arc::new(Shared { store, cfg }),
            check: None,
        })
    }

    /// Confirms every delivery with the cache before marking a job done.
    pub fn with_delivery_check(mut self, check: DeliveryCheck) -> OrchestratorService {
        self.check = Some(check);
        self
    }

    fn store(&self) -> &dyn JobStore {
        self.shared.store.as_ref()
    }

    fn max_attempts(&self) -> u32 {
        self.store().options().max_attempts
    }

    /// Reclaims expired leases now (the server also does this periodically).
    pub async fn reap(&self) -> Result<usize, OrchestratorError> {
        self.store().reap().await
    }

    /// Makes everything written so far durable (at shutdown).
    pub async fn close(&self) -> Result<(), OrchestratorError> {
        self.store().close().await
    }

    async fn submit_inner(
        &self,
        mut stream: Streaming<pb::SubmitRequest>,
    ) -> Result<pb::SubmitResponse, Status> {
        let first = stream
            .message()
            .await
            .map_err(client_fault)?
            .ok_or_else(|| Status::invalid_argument("empty submit stream"))?;
        let Some(pb::submit_request::Msg::Spec(spec)) = first.msg else {
            return Err(Status::invalid_argument(
                "the first submit message must be `spec`",
            ));
        };
        let spec = convert::spec_from_pb(spec).map_err(OrchestratorError::from)?;
        if spec.part.is_some() {
            return Err(Status::invalid_argument(
                "a part of a bricked job is added by the worker that holds the job \
                 (SubmitParts), not submitted",
            ));
        }
        let mut upload = None;
        if let Source::Upload { size } = spec.source {
            let limit = self.shared.cfg.max_upload_bytes;
            if size > limit {
                return Err(Status::invalid_argument(format!(
                    "upload of {size} bytes exceeds the limit of {limit} bytes"
                )));
            }
            let bytes = read_announced(&mut stream, size, "upload", |m| match m.msg {
                Some(pb::submit_request::Msg::Chunk(c)) => Ok(c),
                _ => Err("a second `spec` in one upload"),
            })
            .await?;
            let got = wavesplat_net::digest::sha256(&bytes);
            if got != spec.sha256 {
                return Err(Status::invalid_argument(format!(
                    "upload checksum {} does not match the announced {}",
                    hex(&got),
                    hex(&spec.sha256)
                )));
            }
            upload = Some(bytes);
        }
        let submitted = self.store().submit(spec, upload).await?;
        if !submitted.existed {
            tracing::info!(job = submitted.job.id, name = %submitted.job.spec.name, "submitted");
        }
        Ok(pb::SubmitResponse {
            job: Some(convert::job_to_pb(&submitted.job, self.max_attempts())),
            existed: submitted.existed,
        })
    }
}

type SourceStream = Pin<Box<dyn Stream<Item = Result<pb::SourceChunk, Status>> + Send>>;

/// Most bytes of jobs one `ListJobs` reply carries (its page), well below the message limit:
/// a queue of many thousand jobs (a large bricked job adds one per brick and trial) is listed
/// page by page instead of failing as one reply over the limit.
pub const LIST_PAGE_BYTES: usize = 1 << 20;

/// Jobs read from the store at a time while a `ListJobs` page fills.
const LIST_BATCH: usize = 256;

/// Adds `jobs` (in id order, following the page's) to `page` while whole jobs fit
/// `page_bytes` as encoded (at least one in a page), `bytes` counting the page's so far; true
/// once one did not (the page is full and `more` set).
fn fill_page(
    page: &mut pb::ListJobsResponse,
    bytes: &mut usize,
    jobs: &[crate::model::Job],
    max_attempts: u32,
    page_bytes: usize,
) -> bool {
    for j in jobs {
        let job = convert::job_to_pb(j, max_attempts);
        let wire = wavesplat_proto::repeated_entry_len(&job);
        if !page.jobs.is_empty() && *bytes + wire > page_bytes {
            page.more = true;
            return true;
        }
        *bytes += wire;
        page.jobs.push(job);
    }
    false
}

/// The page of `jobs` (in id order) after `after`: whole jobs up to `page_bytes` as encoded
/// (at least one), and whether more follow.
#[cfg(test)]
fn list_page(
    jobs: &[crate::model::Job],
    after: u64,
    max_attempts: u32,
    page_bytes: usize,
) -> pb::ListJobsResponse {
    let mut page = pb::ListJobsResponse::default();
    let after: Vec<_> = jobs.iter().filter(|j| j.id > after).cloned().collect();
    fill_page(&mut page, &mut 0, &after, max_attempts, page_bytes);
    page
}

/// Parts one `SubmitParts` call may name (its reply stays well below the message limit).
pub const MAX_PARTS_PER_CALL: usize = 4096;

impl OrchestratorService {
    /// Refuses unless job `id` is running as `attempt` and `token` is that lease's
    /// ([`crate::queue::rules::check_holder`]).
    async fn held(&self, id: u64, attempt: u32, token: &[u8]) -> Result<crate::model::Job, Status> {
        let job = self.store().get(id).await?;
        crate::queue::rules::check_holder(&job, attempt, token)?;
        Ok(job)
    }

    async fn submit_parts_inner(
        &self,
        token: &[u8],
        r: pb::SubmitPartsRequest,
    ) -> Result<pb::SubmitPartsResponse, Status> {
        if r.parts.len() > MAX_PARTS_PER_CALL {
            return Err(Status::invalid_argument(format!(
                "{} parts in one call; at most {MAX_PARTS_PER_CALL}",
                r.parts.len()
            )));
        }
        // Which jobs are spread over parts is the worker's choice (a bricked volume, a time
        // series: the orchestrator reads no source). The store checks the parent's lease and
        // that each spec is the parent's part in the step that adds them.
        let specs = r
            .parts
            .into_iter()
            .map(convert::spec_from_pb)
            .collect::<Result<Vec<_>, _>>()
            .map_err(OrchestratorError::from)?;
        let parts = self
            .store()
            .submit_parts(r.parent_id, r.parent_attempt, token, specs)
            .await?;
        Ok(pb::SubmitPartsResponse {
            parts: parts.iter().map(part_state).collect(),
        })
    }

    async fn finish_part_inner(
        &self,
        token: &[u8],
        mut stream: Streaming<pb::FinishPartRequest>,
    ) -> Result<pb::Job, Status> {
        let Some(pb::finish_part_request::Msg::Head(head)) = stream
            .message()
            .await
            .map_err(client_fault)?
            .and_then(|m| m.msg)
        else {
            return Err(Status::invalid_argument(
                "the first FinishPart message must be `head`",
            ));
        };
        let (id, attempt) = (head.job_id, head.attempt);
        let job = self.held(id, attempt, token).await?;
        let Some(part) = &job.spec.part else {
            return Err(Status::invalid_argument(format!(
                "job {id} is not a part of a bricked job"
            )));
        };
        let size = head.size;
        let limit = wavesplat_orchestrator_client::model::MAX_PART_RESULT_BYTES;
        if size as usize > limit {
            return Err(Status::invalid_argument(format!(
                "a part's result of {size} bytes exceeds the limit of {limit} bytes (use \
                 smaller bricks)"
            )));
        }
        let bytes = read_announced(&mut stream, size, "result", |m| match m.msg {
            Some(pb::finish_part_request::Msg::Chunk(c)) => Ok(c),
            _ => Err("a second `head` in one result"),
        })
        .await?;
        let sha = wavesplat_net::digest::sha256(&bytes);
        if head.sha256 != sha {
            return Err(Status::invalid_argument(
                "the result's SHA-256 does not match the announced one",
            ));
        }
        self.store()
            .put_result(part.parent, id, attempt, token, bytes)
            .await?;
        let delivery = crate::model::Delivery {
            cache_volume_id: 0,
            output_bytes: size,
            voxels: head.voxels,
            existed: false,
            sha256: hex(&sha),
        };
        let job = self
            .store()
            .finish(id, attempt, token, Outcome::Delivered(delivery))
            .await?;
        tracing::debug!(job = id, attempt, worker = %head.worker, bytes = size, "part finished");
        Ok(convert::job_to_pb(&job, self.max_attempts()))
    }
}

/// The chunks that follow a stream's first message: exactly `size` bytes (`what` names them
/// in errors), each message's bytes given by `chunk` (or why the message does not belong).
/// Memory is reserved for at most 64 MiB up front, whatever the announced size.
async fn read_announced<M>(
    stream: &mut Streaming<M>,
    size: u64,
    what: &str,
    chunk: impl Fn(M) -> Result<Vec<u8>, &'static str>,
) -> Result<Vec<u8>, Status> {
    let mut bytes = Vec::with_capacity(size.min(64 << 20) as usize);
    while let Some(m) = stream.message().await.map_err(client_fault)? {
        let c = chunk(m).map_err(Status::invalid_argument)?;
        if bytes.len() as u64 + c.len() as u64 > size {
            return Err(Status::invalid_argument(format!(
                "{what} longer than the announced {size} bytes"
            )));
        }
        bytes.extend_from_slice(&c);
    }
    if bytes.len() as u64 != size {
        return Err(Status::invalid_argument(format!(
            "{what} truncated: {} of {size} bytes",
            bytes.len()
        )));
    }
    Ok(bytes)
}

/// `bytes` as a stream of chunks of at most [`CHUNK_BYTES`].
fn chunked(bytes: &[u8]) -> SourceStream {
    let chunks: Vec<Result<pb::SourceChunk, Status>> = bytes
        .chunks(CHUNK_BYTES)
        .map(|c| Ok(pb::SourceChunk { data: c.to_vec() }))
        .collect();
    Box::pin(tokio_stream::iter(chunks))
}

/// Where one part stands, for the worker that waits on it.
fn part_state(job: &crate::model::Job) -> pb::PartState {
    // A done part names the worker that finished it (whom the brick's next part prefers).
    let j = convert::job_to_pb(job, 0);
    pb::PartState {
        id: j.id,
        state: j.state,
        worker: j.worker,
        progress: j.progress,
        output_bytes: j.output_bytes,
        failure: j.failure,
        // Cut to its first 240 characters (a failure's message may hold 4 000): a reply on
        // 1 024 parts stays far below the message limit whatever their failures said.
        error: j.error.chars().take(PART_ERROR_CHARS).collect(),
    }
}

/// Characters of a part's last failure a `PartState` carries.
const PART_ERROR_CHARS: usize = 240;

#[tonic::async_trait]
impl Orchestrator for OrchestratorService {
    async fn submit(
        &self,
        request: Request<Streaming<pb::SubmitRequest>>,
    ) -> Result<Response<pb::SubmitResponse>, Status> {
        Ok(Response::new(
            self.submit_inner(request.into_inner()).await?,
        ))
    }

    async fn list_jobs(
        &self,
        request: Request<pb::ListJobsRequest>,
    ) -> Result<Response<pb::ListJobsResponse>, Status> {
        // The page is read from the store batch by batch from its cursor: a page costs the
        // jobs it holds, not the whole queue.
        let mut after = request.into_inner().after_id;
        let (mut page, mut bytes) = (pb::ListJobsResponse::default(), 0);
        loop {
            let batch = self.store().list_after(after, LIST_BATCH).await?;
            if fill_page(
                &mut page,
                &mut bytes,
                &batch,
                self.max_attempts(),
                LIST_PAGE_BYTES,
            ) || batch.len() < LIST_BATCH
            {
                return Ok(Response::new(page));
            }
            after = batch.last().map_or(after, |j| j.id);
        }
    }

    async fn get_job(&self, request: Request<pb::JobRef>) -> Result<Response<pb::Job>, Status> {
        let job = self.store().get(request.into_inner().id).await?;
        Ok(Response::new(convert::job_to_pb(&job, self.max_attempts())))
    }

    async fn cancel_job(&self, request: Request<pb::JobRef>) -> Result<Response<pb::Job>, Status> {
        let id = request.into_inner().id;
        // Its parts go with it, in the same step (the worker that held it stops at its next
        // heartbeat).
        let job = self.store().cancel(id).await?;
        tracing::info!(job = id, "cancelled");
        Ok(Response::new(convert::job_to_pb(&job, self.max_attempts())))
    }

    async fn retry_job(&self, request: Request<pb::JobRef>) -> Result<Response<pb::Job>, Status> {
        let id = request.into_inner().id;
        let job = self.store().retry(id).await?;
        tracing::info!(job = id, "queued again");
        Ok(Response::new(convert::job_to_pb(&job, self.max_attempts())))
    }

    async fn lease(
        &self,
        request: Request<pb::LeaseRequest>,
    ) -> Result<Response<pb::LeaseResponse>, Status> {
        let r = request.into_inner();
        let worker: String = r.worker.chars().take(200).collect();
        let leased = self.store().lease(&worker, r.parts_only).await?;
        let poll_ms = self.shared.cfg.poll_ms;
        let Some(job) = leased.job else {
            let retry_after = leased
                .next_runnable_in
                .map_or(poll_ms, |d| d.clamp(1, poll_ms));
            return Ok(Response::new(pb::LeaseResponse {
                lease: None,
                retry_after_ms: retry_after.min(u32::MAX as u64) as u32,
            }));
        };
        let Some(secret) = job.state.lease_token().and_then(LeaseToken::secret) else {
            return Err(Status::internal(format!(
                "job {} was leased without its token's secret",
                job.id
            )));
        };
        tracing::info!(job = job.id, attempt = job.attempts, %worker, "leased");
        let cfg = self.store().options();
        Ok(Response::new(pb::LeaseResponse {
            lease: Some(pb::Lease {
                job_id: job.id,
                attempt: job.attempts,
                spec: Some(convert::spec_to_pb(&job.spec)),
                lease_ms: cfg.lease_ms.min(u32::MAX as u64) as u32,
                heartbeat_ms: cfg.heartbeat_ms.min(u32::MAX as u64) as u32,
                lease_token: secret.to_vec(),
            }),
            retry_after_ms: 0,
        }))
    }

    async fn heartbeat(
        &self,
        request: Request<pb::HeartbeatRequest>,
    ) -> Result<Response<pb::HeartbeatResponse>, Status> {
        let token = lease_token_of(&request);
        let r = request.into_inner();
        // A stranger (no token, or another) is refused with an error; the holder of a lease
        // that was lost is told to stop.
        let reply = match self
            .store()
            .heartbeat(r.job_id, r.attempt, &token, r.progress, &r.stage)
            .await
        {
            Ok(_) => pb::HeartbeatResponse {
                keep_going: true,
                reason: String::new(),
            },
            Err(e @ (OrchestratorError::LeaseLost { .. } | OrchestratorError::NotFound(_))) => {
                pb::HeartbeatResponse {
                    keep_going: false,
                    reason: e.to_string(),
                }
            }
            Err(e) => return Err(e.into()),
        };
        Ok(Response::new(reply))
    }

    async fn finish(
        &self,
        request: Request<pb::FinishRequest>,
    ) -> Result<Response<pb::Job>, Status> {
        let token = lease_token_of(&request);
        let r = request.into_inner();
        let outcome = convert::outcome_from_pb(r.outcome).map_err(OrchestratorError::from)?;
        let (id, attempt) = (r.job_id, r.attempt);
        if let Outcome::Delivered(d) = &outcome {
            // Only the holder gets a delivery checked with the cache.
            let spec = self.held(id, attempt, &token).await?.spec;
            if spec.part.is_some() {
                return Err(Status::invalid_argument(format!(
                    "job {id} is a part of a bricked job: its result comes with FinishPart"
                )));
            }
            if let Some(check) = &self.check {
                if let Err(e) = check.confirm(&spec.name, d).await {
                    tracing::warn!(job = id, attempt, worker = %r.worker, error = %e, "delivery refused");
                    return Err(e.into());
                }
            }
        }
        // A job with parts that ends (landed, or failed for good) drops their results in the
        // same step.
        let job = self.store().finish(id, attempt, &token, outcome).await?;
        tracing::info!(
            job = id,
            attempt,
            worker = %r.worker,
            state = job.state.name(),
            error = %job.last_failure.as_ref().map_or("", |f| f.message.as_str()),
            "attempt finished"
        );
        Ok(Response::new(convert::job_to_pb(&job, self.max_attempts())))
    }

    type FetchSourceStream = SourceStream;

    async fn fetch_source(
        &self,
        request: Request<pb::FetchSourceRequest>,
    ) -> Result<Response<Self::FetchSourceStream>, Status> {
        let token = lease_token_of(&request);
        let r = request.into_inner();
        let job = self.held(r.job_id, r.attempt, &token).await?;
        if !matches!(job.spec.source, Source::Upload { .. }) {
            return Err(Status::invalid_argument(format!(
                "job {} reads its source from a path, not an upload",
                r.job_id
            )));
        }
        let sha = job.spec.sha256;
        let blob = self
            .store()
            .upload(&sha)
            .await?
            .ok_or_else(|| Status::internal(format!("upload {} is missing", hex(&sha))))?;
        Ok(Response::new(chunked(&blob)))
    }

    async fn submit_parts(
        &self,
        request: Request<pb::SubmitPartsRequest>,
    ) -> Result<Response<pb::SubmitPartsResponse>, Status> {
        let token = lease_token_of(&request);
        Ok(Response::new(
            self.submit_parts_inner(&token, request.into_inner())
                .await?,
        ))
    }

    async fn finish_part(
        &self,
        request: Request<Streaming<pb::FinishPartRequest>>,
    ) -> Result<Response<pb::Job>, Status> {
        let token = lease_token_of(&request);
        Ok(Response::new(
            self.finish_part_inner(&token, request.into_inner()).await?,
        ))
    }

    type FetchResultStream = SourceStream;

    async fn fetch_result(
        &self,
        request: Request<pb::FetchResultRequest>,
    ) -> Result<Response<Self::FetchResultStream>, Status> {
        let token = lease_token_of(&request);
        let r = request.into_inner();
        self.held(r.parent_id, r.parent_attempt, &token).await?;
        let part = self.store().get(r.part_id).await?;
        if part
            .spec
            .part
            .as_ref()
            .is_none_or(|p| p.parent != r.parent_id)
        {
            return Err(Status::invalid_argument(format!(
                "job {} is not a part of job {}",
                r.part_id, r.parent_id
            )));
        }
        let bytes = self
            .store()
            .result(r.parent_id, r.part_id)
            .await?
            .ok_or_else(|| {
                Status::failed_precondition(format!(
                    "part {} has no result (it is {})",
                    r.part_id,
                    part.state.name()
                ))
            })?;
        Ok(Response::new(chunked(&bytes)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::{Failure, FailureKind, JobOptions, JobSpec};
    use crate::queue::rules;

    fn job(id: u64) -> crate::model::Job {
        let spec = JobSpec {
            name: format!("volume {id} with a name of some length"),
            source: Source::Path(format!("/archive/study/{id}.nii.gz").into()),
            sha256: [id as u8; 32],
            raw: None,
            channel: None,
            options: JobOptions::default(),
            part: None,
        };
        rules::new_job(id, spec, 0)
    }

    /// A list longer than a page comes in pages of whole jobs within the page's bytes, in id
    /// order, each page after the last one's id, the last saying nothing more follows.
    #[test]
    fn jobs_are_listed_in_pages_within_their_bytes() {
        let jobs: Vec<_> = (1..=500).map(job).collect();
        let page_bytes = 4096;
        let (mut listed, mut after, mut pages) = (Vec::new(), 0, 0);
        loop {
            let page = list_page(&jobs, after, 3, page_bytes);
            let bytes = prost::Message::encoded_len(&pb::ListJobsResponse {
                jobs: page.jobs.clone(),
                more: false,
            });
            assert!(bytes <= page_bytes, "a page of {bytes} bytes");
            assert!(!page.jobs.is_empty());
            pages += 1;
            after = page.jobs.last().unwrap().id;
            listed.extend(page.jobs.iter().map(|j| j.id));
            if !page.more {
                break;
            }
        }
        assert!(pages > 10, "{pages} pages");
        assert_eq!(listed, (1..=500).collect::<Vec<u64>>());
        // A page smaller than one job still lists it; past the last id, nothing.
        let one = list_page(&jobs, 0, 3, 1);
        assert_eq!((one.jobs.len(), one.more), (1, true));
        let none = list_page(&jobs, 500, 3, page_bytes);
        assert_eq!((none.jobs.len(), none.more), (0, false));
    }

    /// `ListJobs` reads its page from the store batch by batch from the cursor: a queue of
    /// more jobs than a batch is listed whole, in id order, from any cursor.
    #[tokio::test]
    async fn list_jobs_reads_its_page_from_the_cursor_across_batches() {
        use crate::jobstore::EmbeddedQueue;
        use crate::store::Store;
        let dir = tempfile::tempdir().unwrap();
        let queue = EmbeddedQueue::open(
            Store::open(dir.path()).unwrap(),
            QueueOptions::default(),
            Arc::new(|| 1000),
        )
        .unwrap();
        let n = 2 * LIST_BATCH + 37;
        for i in 0..n {
            let mut spec = job(1).spec;
            spec.name = format!("volume {i}");
            spec.sha256 = [(i % 251) as u8; 32];
            queue.submit(spec, None).await.unwrap();
        }
        let service = OrchestratorService::new(Arc::new(queue), ServiceOptions::default())
            .await
            .unwrap();
        let list = |after: u64| {
            let service = &service;
            async move {
                service
                    .list_jobs(Request::new(pb::ListJobsRequest { after_id: after }))
                    .await
                    .unwrap()
                    .into_inner()
            }
        };
        let all = list(0).await;
        assert!(!all.more);
        let ids: Vec<u64> = all.jobs.iter().map(|j| j.id).collect();
        assert_eq!(ids.len(), n);
        assert!(ids.windows(2).all(|w| w[0] < w[1]));
        let cursor = ids[LIST_BATCH + 5];
        let rest = list(cursor).await;
        assert_eq!(
            rest.jobs.iter().map(|j| j.id).collect::<Vec<_>>(),
            ids[LIST_BATCH + 6..].to_vec()
        );
        assert!(list(ids[n - 1]).await.jobs.is_empty());
    }

    /// A part's state carries only the start of a long failure message, so that a reply on
    /// many parts stays small.
    #[test]
    fn a_parts_state_carries_the_start_of_its_failure() {
        let mut j = job(7);
        j.last_failure = Some(Failure {
            kind: FailureKind::Worker,
            message: "é".repeat(4000),
        });
        let s = part_state(&j);
        assert_eq!(s.error.chars().count(), PART_ERROR_CHARS);
        assert!(s.error.chars().all(|c| c == 'é'));
    }
}
