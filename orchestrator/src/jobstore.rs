//! Where the queue lives: the [`JobStore`] contract every RPC goes through, and its embedded
//! implementation ([`EmbeddedQueue`]: the in-memory [`Queue`] under one mutex, written through
//! to sled and flushed before answering). The PostgreSQL implementation is
//! [`crate::postgres::PostgresQueue`]. Both apply the same per-job [`crate::queue::rules`]; they differ in
//! where jobs are held and how concurrent orchestrators are kept apart (one process with a
//! mutex, or row locks in a shared database).

use crate::error::OrchestratorError;
use crate::model::{Job, JobId, JobSpec, JobState, Outcome};
use crate::queue::{new_lease_token, rules, Clock, Queue, QueueOptions, Submitted};
use crate::store::Store;
use std::sync::{Mutex, MutexGuard};

/// The answer to a lease request.
#[derive(Debug, Clone, PartialEq)]
pub struct Leased {
    /// The job now leased to the caller, if any was runnable.
    pub job: Option<Job>,
    /// When no job was leased: milliseconds until the next queued job becomes runnable
    /// (`None`: nothing queued, or a job was leased).
    pub next_runnable_in: Option<u64>,
}

/// Counts of jobs by state, for the start-up log line.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct StateCounts {
    /// Queued (including those backing off).
    pub queued: u64,
    /// Leased to a worker.
    pub running: u64,
    /// Delivered.
    pub done: u64,
    /// Failed for good.
    pub failed: u64,
    /// Cancelled.
    pub cancelled: u64,
}

impl StateCounts {
    fn add(&mut self, state: &JobState) {
        match state {
            JobState::Queued { .. } => self.queued += 1,
            JobState::Running { .. } => self.running += 1,
            JobState::Done { .. } => self.done += 1,
            JobState::Failed(_) => self.failed += 1,
            JobState::Cancelled => self.cancelled += 1,
        }
    }
}

/// The storage contract of the orchestrator: every change is durable when the call returns
/// (heartbeats excepted: a lost heartbeat costs at most a reclaimed lease), and concurrent
/// callers (RPCs of one orchestrator, or several orchestrators over one database) never lease
/// one job twice or apply an outcome to a lease that lapsed.
///
/// Every change on a lease presents the lease's token (`token`, as the worker sent it): the
/// running lease named without it is refused ([`OrchestratorError::NotLeaseHolder`]) and
/// nothing changes. A job with parts that ends (done, failed for good, cancelled) cancels its
/// queued and running parts and drops their results in the same step
/// ([`crate::queue::rules::ends_parts`]); parts are added only while their parent's lease is
/// held, checked in the step that adds them ([`JobStore::submit_parts`]).
#[tonic::async_trait]
pub trait JobStore: Send + Sync + 'static {
    /// The timing and retry policy.
    fn options(&self) -> &QueueOptions;

    /// Adds a job (storing `upload`, the source's bytes, under the spec's hash), or returns the
    /// known one with the same content hash, layout, options and name.
    async fn submit(
        &self,
        spec: JobSpec,
        upload: Option<Vec<u8>>,
    ) -> Result<Submitted, OrchestratorError>;

    /// Leases the oldest runnable job to `worker` (with `parts_only`, the oldest part of a
    /// bricked job), with a new secret token (the leased job's
    /// [`JobState::lease_token`], whose [`crate::model::LeaseToken::secret`] is known in the job returned
    /// here only; the store keeps its digest).
    async fn lease(&self, worker: &str, parts_only: bool) -> Result<Leased, OrchestratorError>;

    /// Extends a held lease and records progress.
    async fn heartbeat(
        &self,
        id: JobId,
        attempt: u32,
        token: &[u8],
        progress: f32,
        stage: &str,
    ) -> Result<Job, OrchestratorError>;

    /// Records the outcome of a held attempt; a delivered job's uploaded source is dropped
    /// unless another unfinished job needs it, and a job with parts that ends settles them
    /// (see the trait's docs).
    async fn finish(
        &self,
        id: JobId,
        attempt: u32,
        token: &[u8],
        outcome: Outcome,
    ) -> Result<Job, OrchestratorError>;

    /// Adds the parts `specs` of `parent`, whose lease `attempt` the caller holds (presenting
    /// `token`), or polls them if known; returns them in the order asked. The lease and every
    /// spec are checked in the same step that adds them, so nothing is added once the parent
    /// was cancelled, failed or reclaimed, nor when any spec is refused. A known part that
    /// ended before this attempt of the parent first asked for it runs again
    /// ([`crate::queue::rules::ask_for_part`]).
    async fn submit_parts(
        &self,
        parent: JobId,
        attempt: u32,
        token: &[u8],
        specs: Vec<JobSpec>,
    ) -> Result<Vec<Job>, OrchestratorError>;

    /// Cancels a queued or running job, and with it (in the same step) its queued and running
    /// parts and its parts' results.
    async fn cancel(&self, id: JobId) -> Result<Job, OrchestratorError>;

    /// Queues a failed or cancelled job again with a fresh attempt budget.
    async fn retry(&self, id: JobId) -> Result<Job, OrchestratorError>;

    /// Reclaims every lapsed lease (a job with parts that fails for good settles them, as in
    /// [`JobStore::finish`]); returns how many.
    async fn reap(&self) -> Result<usize, OrchestratorError>;

    /// One job.
    async fn get(&self, id: JobId) -> Result<Job, OrchestratorError>;

    /// Every job, by id.
    async fn list(&self) -> Result<Vec<Job>, OrchestratorError>;

    /// Up to `limit` jobs whose ids follow `after`, by id: a page of [`JobStore::list`] read
    /// from the store as such (an index range), not cut from the whole list.
    async fn list_after(&self, after: JobId, limit: usize) -> Result<Vec<Job>, OrchestratorError>;

    /// The uploaded source with this hash.
    async fn upload(&self, sha256: &[u8; 32]) -> Result<Option<Vec<u8>>, OrchestratorError>;

    /// Stores (durably) the result of part `id` of the bricked job `parent`, replacing any
    /// earlier attempt's, if `attempt` (presenting `token`) holds the part's live lease at that
    /// moment (checked and stored as one step): a worker whose lease expired or was taken while
    /// it uploaded cannot replace the result of the attempt that finished the part
    /// (`LeaseLost`), nor can a part cancelled with its parent store one.
    async fn put_result(
        &self,
        parent: JobId,
        id: JobId,
        attempt: u32,
        token: &[u8],
        bytes: Vec<u8>,
    ) -> Result<(), OrchestratorError>;

    /// The result of part `id` of `parent`.
    async fn result(&self, parent: JobId, id: JobId) -> Result<Option<Vec<u8>>, OrchestratorError>;

    /// Drops the results of `parent`'s parts; returns how many. (A job with parts that ends
    /// drops them itself; this is for callers that are done with them earlier.)
    async fn drop_results(&self, parent: JobId) -> Result<usize, OrchestratorError>;

    /// Jobs by state.
    async fn counts(&self) -> Result<StateCounts, OrchestratorError> {
        let mut c = StateCounts::default();
        for j in self.list().await? {
            c.add(&j.state);
        }
        Ok(c)
    }

    /// Makes everything written so far durable (at shutdown).
    async fn close(&self) -> Result<(), OrchestratorError>;
}

/// The embedded store: the queue in memory behind one mutex, every change written through to
/// sled and flushed before the call returns. One orchestrator process owns the database
/// directory.
pub struct EmbeddedQueue {
    options: QueueOptions,
    queue: Mutex<Queue>,
    store: Store,
    clock: Clock,
}

impl EmbeddedQueue {
    /// Loads the queue from `store`; running leases get a fresh lease of grace, since their
    /// workers could not heartbeat while no orchestrator was up. What a crash left of a parent's
    /// end is finished: its live parts cancelled ([`Queue::restore`]), its parts' results
    /// dropped.
    pub fn open(
        store: Store,
        cfg: QueueOptions,
        clock: Clock,
    ) -> Result<EmbeddedQueue, OrchestratorError> {
        let options = cfg.validate()?;
        let jobs = store.load()?;
        let (queue, changed) = Queue::restore(options, jobs, clock());
        store.put(&changed)?;
        // The ended parents the queue knows parts of (not a scan of every stored result).
        for parent in queue.parents_with_parts() {
            if queue.get(parent).is_ok_and(rules::ends_parts) {
                store.drop_results(parent)?;
            }
        }
        Ok(EmbeddedQueue {
            options,
            queue: Mutex::new(queue),
            store,
            clock,
        })
    }

    fn lock(&self) -> MutexGuard<'_, Queue> {
        // A panic while holding the lock cannot leave the queue half-updated in a way that
        // matters more than stopping service would; keep serving.
        self.queue.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn now(&self) -> u64 {
        (self.clock)()
    }

    /// Applies `f` to the queue under its lock and writes the job it changed through, with
    /// what ending it settles in the same step: its parts ([`Queue::settle_parts`]) and their
    /// results, and a delivered job's uploaded source.
    async fn change(
        &self,
        f: impl FnOnce(&mut Queue, u64) -> Result<Job, OrchestratorError>,
    ) -> Result<Job, OrchestratorError> {
        let job = {
            let mut q = self.lock();
            let now = self.now();
            let job = f(&mut q, now)?;
            self.write_through(&mut q, std::slice::from_ref(&job), now)?;
            if matches!(job.state, JobState::Done { .. }) {
                self.store.release_blob(&job, q.jobs())?;
            }
            job
        };
        self.store.flush().await?;
        Ok(job)
    }

    /// Writes `changed` through (under the queue's lock `q`), each job that ends its parts
    /// ([`rules::ends_parts`]) followed by its settled parts and the drop of their results.
    /// The parent is written first, so that a crash part-way leaves what [`Queue::restore`]
    /// finishes; `changed` may already hold settled parts (a reap), which settle no further.
    fn write_through(
        &self,
        q: &mut Queue,
        changed: &[Job],
        now: u64,
    ) -> Result<(), OrchestratorError> {
        for job in changed {
            self.store.put(std::slice::from_ref(job))?;
            if rules::ends_parts(job) {
                let parts = q.settle_parts(job, now);
                self.store.put(&parts)?;
                self.store.drop_results(job.id)?;
            }
        }
        Ok(())
    }
}

#[tonic::async_trait]
impl JobStore for EmbeddedQueue {
    fn options(&self) -> &QueueOptions {
        &self.options
    }

    async fn submit(
        &self,
        spec: JobSpec,
        upload: Option<Vec<u8>>,
    ) -> Result<Submitted, OrchestratorError> {
        let uploaded = upload.is_some();
        let sha256 = spec.sha256;
        let submitted = {
            let mut q = self.lock();
            // The source is written under the queue's lock, so a job of the same source that
            // finishes meanwhile cannot remove it between this write and this job's insert;
            // and it is removed again where nothing takes it (an invalid job, or one known
            // and done already), as the PostgreSQL store never writes it then.
            if let Some(bytes) = &upload {
                self.store.put_blob(&sha256, bytes)?;
            }
            let s = q.submit(spec, self.now());
            if uploaded {
                self.store.drop_blob_unless_needed(&sha256, q.jobs())?;
            }
            let s = s?;
            if !s.existed {
                self.store.put(std::slice::from_ref(&s.job))?;
            }
            s
        };
        // A known job wrote nothing (a bricked job's worker polls its parts this way).
        if uploaded || !submitted.existed {
            self.store.flush().await?;
        }
        Ok(submitted)
    }

    async fn lease(&self, worker: &str, parts_only: bool) -> Result<Leased, OrchestratorError> {
        let token = new_lease_token()?;
        let leased = {
            let mut q = self.lock();
            let now = self.now();
            let (job, changed) = q.lease(worker, parts_only, token, now);
            self.write_through(&mut q, &changed, now)?;
            // Only an idle worker needs to know when the next backoff ends.
            let next_runnable_in = match job {
                None => q.next_runnable_in(now),
                Some(_) => None,
            };
            Leased {
                job,
                next_runnable_in,
            }
        };
        if leased.job.is_some() {
            self.store.flush().await?;
        }
        Ok(leased)
    }

    async fn heartbeat(
        &self,
        id: JobId,
        attempt: u32,
        token: &[u8],
        progress: f32,
        stage: &str,
    ) -> Result<Job, OrchestratorError> {
        let mut q = self.lock();
        let job = q.heartbeat(id, attempt, token, progress, stage, self.now())?;
        // Not flushed: see the store's docs.
        self.store.put(std::slice::from_ref(&job))?;
        Ok(job)
    }

    async fn finish(
        &self,
        id: JobId,
        attempt: u32,
        token: &[u8],
        outcome: Outcome,
    ) -> Result<Job, OrchestratorError> {
        self.change(|q, now| q.finish(id, attempt, token, outcome, now))
            .await
    }

    async fn submit_parts(
        &self,
        parent: JobId,
        attempt: u32,
        token: &[u8],
        specs: Vec<JobSpec>,
    ) -> Result<Vec<Job>, OrchestratorError> {
        let (parts, changed) = {
            // Under the queue's lock, as every change: a cancel, a reap or an outcome of the
            // parent comes wholly before this check or wholly after these parts are added
            // (and then settles them).
            let mut q = self.lock();
            // Whether a result is stored matters only for a done part (`ask_for_part`).
            let done = q.done_parts(parent);
            let with_results = self.store.result_ids_among(parent, done)?;
            let (parts, changed) =
                q.submit_parts(parent, attempt, token, specs, &with_results, self.now())?;
            self.store.put(&changed)?;
            (parts, changed)
        };
        // Parts all known and unchanged (a poll) wrote nothing.
        if !changed.is_empty() {
            self.store.flush().await?;
        }
        Ok(parts)
    }

    async fn cancel(&self, id: JobId) -> Result<Job, OrchestratorError> {
        self.change(|q, now| q.cancel(id, now)).await
    }

    async fn retry(&self, id: JobId) -> Result<Job, OrchestratorError> {
        self.change(|q, now| q.retry(id, now)).await
    }

    async fn reap(&self) -> Result<usize, OrchestratorError> {
        let changed = {
            let mut q = self.lock();
            let now = self.now();
            let changed = q.reap(now);
            self.write_through(&mut q, &changed, now)?;
            changed
        };
        if !changed.is_empty() {
            self.store.flush().await?;
        }
        // The leases reclaimed (queued again or failed), not the parts they cancelled.
        let reclaimed = changed
            .iter()
            .filter(|j| !matches!(j.state, JobState::Cancelled))
            .count();
        Ok(reclaimed)
    }

    async fn get(&self, id: JobId) -> Result<Job, OrchestratorError> {
        self.lock().get(id).cloned()
    }

    async fn list(&self) -> Result<Vec<Job>, OrchestratorError> {
        Ok(self.lock().jobs().cloned().collect())
    }

    async fn list_after(&self, after: JobId, limit: usize) -> Result<Vec<Job>, OrchestratorError> {
        Ok(self.lock().jobs_after(after).take(limit).cloned().collect())
    }

    async fn upload(&self, sha256: &[u8; 32]) -> Result<Option<Vec<u8>>, OrchestratorError> {
        Ok(self.store.blob(sha256)?.map(|b| b.to_vec()))
    }

    async fn put_result(
        &self,
        parent: JobId,
        id: JobId,
        attempt: u32,
        token: &[u8],
        bytes: Vec<u8>,
    ) -> Result<(), OrchestratorError> {
        {
            // Under the queue's lock: no lease can change between the check and the write.
            let q = self.lock();
            rules::check_held(q.get(id)?, attempt, token, self.now())?;
            self.store.put_result(parent, id, &bytes)?;
        }
        self.store.flush().await
    }

    async fn result(&self, parent: JobId, id: JobId) -> Result<Option<Vec<u8>>, OrchestratorError> {
        Ok(self.store.result(parent, id)?.map(|b| b.to_vec()))
    }

    async fn drop_results(&self, parent: JobId) -> Result<usize, OrchestratorError> {
        let n = self.store.drop_results(parent)?;
        if n > 0 {
            self.store.flush().await?;
        }
        Ok(n)
    }

    async fn close(&self) -> Result<(), OrchestratorError> {
        self.store.flush().await
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::{JobOptions, Source};
    use std::sync::Arc;

    #[tokio::test]
    async fn a_delivered_upload_is_dropped_unless_another_job_needs_it() {
        let dir = tempfile::tempdir().unwrap();
        let q = EmbeddedQueue::open(
            Store::open(dir.path()).unwrap(),
            QueueOptions::default(),
            Arc::new(|| 1000),
        )
        .unwrap();
        let spec = |name: &str| JobSpec {
            name: name.into(),
            source: Source::Upload { size: 3 },
            sha256: [7; 32],
            raw: None,
            channel: None,
            options: JobOptions::default(),
            part: None,
        };
        q.submit(spec("a"), Some(vec![1, 2, 3])).await.unwrap();
        q.submit(spec("b"), Some(vec![1, 2, 3])).await.unwrap();
        assert_eq!(q.counts().await.unwrap().queued, 2);
        let a = q.lease("w", false).await.unwrap().job.unwrap();
        let delivered = || {
            Outcome::Delivered(crate::model::Delivery {
                cache_volume_id: 1,
                output_bytes: 1,
                voxels: 1,
                existed: false,
                sha256: "ab".repeat(32),
            })
        };
        let token = |j: &Job| j.state.lease_token().unwrap().secret().unwrap().to_vec();
        q.finish(a.id, 1, &token(&a), delivered()).await.unwrap();
        assert!(
            q.upload(&[7; 32]).await.unwrap().is_some(),
            "b still needs it"
        );
        let b = q.lease("w", false).await.unwrap().job.unwrap();
        q.finish(b.id, 1, &token(&b), delivered()).await.unwrap();
        assert!(q.upload(&[7; 32]).await.unwrap().is_none());
    }

    /// A crash between writing a cancelled parent and settling its parts leaves the parent
    /// ended, a part queued and a part's result stored: opening the store finishes the step.
    #[tokio::test]
    async fn opening_finishes_what_a_crash_left_of_a_parents_end() {
        use crate::model::{PartSpec, PartStep};
        let dir = tempfile::tempdir().unwrap();
        let parent = JobSpec {
            name: "bricked".into(),
            source: Source::Path("/shared/b.nii".into()),
            sha256: [3; 32],
            raw: None,
            channel: None,
            options: JobOptions {
                brick: Some(16),
                ..JobOptions::default()
            },
            part: None,
        };
        let part = |index: u32| JobSpec {
            part: Some(PartSpec {
                parent: 1,
                index,
                of: 2,
                step: PartStep::Score { energies: false },
                levels: 2,
                offset: None,
                color: None,
                source_bytes: None,
                time_points: None,
                prefer_worker: None,
            }),
            ..parent.clone()
        };
        let (p0, p1) = (
            crate::queue::rules::new_job(2, part(0), 10),
            crate::queue::rules::new_job(3, part(1), 10),
        );
        let mut cancelled = crate::queue::rules::new_job(1, parent, 10);
        cancelled.state = JobState::Cancelled;
        {
            let store = Store::open(dir.path()).unwrap();
            store.put(&[cancelled, p0, p1]).unwrap();
            store.put_result(1, 2, &[1, 2, 3]).unwrap();
            store.put_result(9, 3, &[4]).unwrap();
            store.flush().await.unwrap();
        }
        let q = EmbeddedQueue::open(
            Store::open(dir.path()).unwrap(),
            QueueOptions::default(),
            Arc::new(|| 1000),
        )
        .unwrap();
        for id in [2, 3] {
            assert_eq!(q.get(id).await.unwrap().state, JobState::Cancelled);
        }
        assert_eq!(q.result(1, 2).await.unwrap(), None);
        assert_eq!(
            q.result(9, 3).await.unwrap(),
            Some(vec![4]),
            "results of a job not known to have ended stay"
        );
        assert!(q.lease("w", true).await.unwrap().job.is_none());
    }
}
