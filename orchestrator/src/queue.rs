//! The job queue's logic, in memory and free of I/O: submission with de-duplication, leases
//! with expiry, heartbeats, outcomes, retry with exponential backoff, cancellation. Time is a
//! parameter (`now`, unix ms), so tests drive the clock directly. The rules of one job's
//! changes ([`rules`]) are shared by both stores; [`Queue`] is the in-memory index the embedded
//! store keeps, whose every mutation returns the jobs it changed so that exactly those are
//! persisted (see [`crate::store`]).

use crate::error::OrchestratorError;
use crate::model::{Job, JobId, JobSpec, JobState, LeaseToken, Outcome, LEASE_TOKEN_BYTES};
use std::collections::{BTreeMap, HashMap, HashSet};
use std::sync::Arc;
use std::time::{SystemTime, UNIX_EPOCH};

/// A clock giving unix milliseconds (injectable for tests).
pub type Clock = Arc<dyn Fn() -> u64 + Send + Sync>;

/// The wall clock.
pub fn system_clock() -> Clock {
    Arc::new(|| {
        SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map_or(0, |d| d.as_millis() as u64)
    })
}

/// A new lease's token: 128 bits from the operating system's CSPRNG.
pub fn new_lease_token() -> Result<LeaseToken, OrchestratorError> {
    use rand::RngCore;
    let mut bytes = [0u8; LEASE_TOKEN_BYTES];
    rand::rngs::OsRng
        .try_fill_bytes(&mut bytes)
        .map_err(|e| OrchestratorError::Entropy(e.to_string()))?;
    Ok(LeaseToken::from_secret(bytes))
}

/// Timing and retry policy.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct QueueOptions {
    /// A lease lapses this long after the last heartbeat (ms).
    pub lease_ms: u64,
    /// Workers heartbeat this often (ms).
    pub heartbeat_ms: u64,
    /// Attempts (leases) before a job fails for good.
    pub max_attempts: u32,
    /// Backoff before the second attempt (ms); doubles per attempt.
    pub backoff_base_ms: u64,
    /// Longest backoff (ms).
    pub backoff_max_ms: u64,
}

impl Default for QueueOptions {
    fn default() -> Self {
        QueueOptions {
            lease_ms: 30_000,
            heartbeat_ms: 5_000,
            max_attempts: 3,
            backoff_base_ms: 2_000,
            backoff_max_ms: 60_000,
        }
    }
}

impl QueueOptions {
    /// Checks the values.
    pub fn validate(self) -> Result<QueueOptions, OrchestratorError> {
        if self.lease_ms == 0 || self.heartbeat_ms == 0 || self.heartbeat_ms >= self.lease_ms {
            return Err(OrchestratorError::InvalidRequest(format!(
                "heartbeat {} ms and lease {} ms: need 0 < heartbeat < lease",
                self.heartbeat_ms, self.lease_ms
            )));
        }
        if self.max_attempts == 0 {
            return Err(OrchestratorError::InvalidRequest(
                "max attempts 0; must be at least 1".into(),
            ));
        }
        Ok(self)
    }

    /// Backoff after `attempts` failed attempts.
    pub fn backoff_ms(&self, attempts: u32) -> u64 {
        let shift = attempts.saturating_sub(1).min(30);
        self.backoff_base_ms
            .saturating_mul(1 << shift)
            .min(self.backoff_max_ms)
    }
}

/// The result of a submission.
#[derive(Debug, Clone, PartialEq)]
pub struct Submitted {
    /// The job (new or existing).
    pub job: Job,
    /// True if an identical job was already known.
    pub existed: bool,
}

/// The rules of one job's state changes, shared by every store: the in-memory [`Queue`] of the
/// sled store applies them under its mutex, the PostgreSQL store to a row it holds locked.
pub mod rules {
    use super::QueueOptions;
    use crate::error::OrchestratorError;
    use crate::model::{Failure, FailureKind, Job, JobId, JobSpec, JobState, LeaseToken, Outcome};

    /// A new job, queued now.
    pub fn new_job(id: JobId, spec: JobSpec, now: u64) -> Job {
        Job {
            id,
            spec,
            state: JobState::Queued { not_before_ms: now },
            attempts: 0,
            retried_at: 0,
            asked_by_attempt: 0,
            last_failure: None,
            created_ms: now,
            updated_ms: now,
        }
    }

    /// Whether `job` is queued and may be leased at `now`.
    pub fn runnable(job: &Job, now: u64) -> bool {
        matches!(job.state, JobState::Queued { not_before_ms } if not_before_ms <= now)
    }

    /// The worker `job` prefers, if it is a part that names one (the worker that last scored
    /// or coded its brick, which may hold what coding it needs): that worker's lease takes it
    /// before older jobs.
    pub fn preferred_worker(job: &Job) -> Option<&str> {
        job.spec.part.as_ref()?.prefer_worker.as_deref()
    }

    /// Whether `job` holds a lease that lapsed by `now`.
    pub fn expired(job: &Job, now: u64) -> bool {
        matches!(job.state, JobState::Running { lease_expires_ms, .. } if lease_expires_ms <= now)
    }

    /// Reclaims `job`'s lapsed lease: queued again with backoff, or failed once its attempts
    /// are used up. Returns false (and changes nothing) if the lease has not lapsed.
    pub fn expire(cfg: &QueueOptions, job: &mut Job, now: u64) -> bool {
        let JobState::Running { worker, .. } = &job.state else {
            return false;
        };
        let worker = worker.clone();
        if !expired(job, now) {
            return false;
        }
        let failure = Failure {
            kind: FailureKind::LeaseExpired,
            message: format!("worker {worker:?} stopped heartbeating (lease expired)"),
        };
        tracing::warn!(job = job.id, %worker, "lease expired; reclaiming");
        fail_attempt(cfg, job, failure, now);
        true
    }

    /// Records a failed attempt: queued again with backoff, or failed for good.
    pub fn fail_attempt(cfg: &QueueOptions, job: &mut Job, failure: Failure, now: u64) {
        let used = job.attempts.saturating_sub(job.retried_at);
        job.state = if failure.kind.is_permanent() || used >= cfg.max_attempts {
            let mut f = failure.clone();
            if !failure.kind.is_permanent() {
                f.message = format!("{} (after {used} attempts)", f.message);
            }
            JobState::Failed(f)
        } else {
            JobState::Queued {
                not_before_ms: now + cfg.backoff_ms(used),
            }
        };
        job.last_failure = Some(failure);
        job.updated_ms = now;
    }

    /// Leases a runnable `job` to `worker`: a new attempt with the secret `token`, running
    /// until `now + lease_ms`.
    pub fn start(cfg: &QueueOptions, job: &mut Job, worker: &str, token: LeaseToken, now: u64) {
        job.attempts += 1;
        job.state = JobState::Running {
            worker: worker.to_string(),
            attempt: job.attempts,
            lease_expires_ms: now + cfg.lease_ms,
            started_ms: now,
            progress: 0.0,
            stage: "leased".into(),
            lease_token: Some(token),
        };
        job.updated_ms = now;
    }

    /// Checks that `attempt` is `job`'s running attempt and `token` that lease's token
    /// (compared in constant time), expiry aside. A lease that is not running under `attempt`
    /// is [`OrchestratorError::LeaseLost`]; the running one named without its token
    /// [`OrchestratorError::NotLeaseHolder`].
    pub fn check_holder(job: &Job, attempt: u32, token: &[u8]) -> Result<(), OrchestratorError> {
        let lost = |reason: String| OrchestratorError::LeaseLost {
            id: job.id,
            attempt,
            reason,
        };
        match &job.state {
            JobState::Running {
                attempt: a,
                lease_token,
                ..
            } if *a == attempt => {
                if lease_token.as_ref().is_some_and(|t| t.matches(token)) {
                    Ok(())
                } else {
                    Err(OrchestratorError::NotLeaseHolder {
                        id: job.id,
                        attempt,
                    })
                }
            }
            JobState::Running { attempt: a, .. } => Err(lost(format!(
                "the job was reclaimed and is now attempt {a}"
            ))),
            JobState::Cancelled => Err(lost("the job was cancelled".into())),
            s => Err(lost(format!("the job is {}", s.name()))),
        }
    }

    /// Checks that `attempt`, presenting `token`, holds `job`'s live lease
    /// ([`check_holder`], and the lease has not expired by `now`).
    pub fn check_held(
        job: &Job,
        attempt: u32,
        token: &[u8],
        now: u64,
    ) -> Result<(), OrchestratorError> {
        check_holder(job, attempt, token)?;
        match &job.state {
            JobState::Running {
                lease_expires_ms, ..
            } if *lease_expires_ms <= now => Err(OrchestratorError::LeaseLost {
                id: job.id,
                attempt,
                reason: "the lease expired".into(),
            }),
            _ => Ok(()),
        }
    }

    /// Extends a held lease and records progress.
    pub fn heartbeat(
        cfg: &QueueOptions,
        job: &mut Job,
        attempt: u32,
        token: &[u8],
        progress: f32,
        stage: &str,
        now: u64,
    ) -> Result<(), OrchestratorError> {
        check_held(job, attempt, token, now)?;
        if let JobState::Running {
            lease_expires_ms,
            progress: p,
            stage: s,
            ..
        } = &mut job.state
        {
            *lease_expires_ms = now + cfg.lease_ms;
            *p = if progress.is_finite() {
                progress.clamp(0.0, 1.0)
            } else {
                0.0
            };
            *s = stage.chars().take(200).collect();
        }
        Ok(())
    }

    /// Records the outcome of a held attempt.
    pub fn finish(
        cfg: &QueueOptions,
        job: &mut Job,
        attempt: u32,
        token: &[u8],
        outcome: Outcome,
        now: u64,
    ) -> Result<(), OrchestratorError> {
        check_held(job, attempt, token, now)?;
        let (started, worker) = match &job.state {
            JobState::Running {
                started_ms, worker, ..
            } => (*started_ms, worker.clone()),
            _ => (now, String::new()),
        };
        match outcome {
            Outcome::Delivered(delivery) => {
                job.state = JobState::Done {
                    delivery,
                    run_ms: now.saturating_sub(started),
                    worker,
                };
                job.updated_ms = now;
            }
            Outcome::Failed(f) => fail_attempt(cfg, job, f, now),
        }
        Ok(())
    }

    /// Cancels a queued or running job.
    pub fn cancel(job: &mut Job, now: u64) -> Result<(), OrchestratorError> {
        match job.state {
            JobState::Queued { .. } | JobState::Running { .. } => {
                job.state = JobState::Cancelled;
                job.updated_ms = now;
                Ok(())
            }
            _ => Err(OrchestratorError::InvalidState {
                id: job.id,
                state: job.state.name(),
                action: "cancel",
                allowed: "queued or running",
            }),
        }
    }

    /// Queues a failed or cancelled job again with a fresh attempt budget. Its attempt count
    /// goes on from where it was: a worker still holding an earlier attempt (cancelled while
    /// running) must not find its attempt number handed out again.
    pub fn retry(job: &mut Job, now: u64) -> Result<(), OrchestratorError> {
        // A part runs again when its parent's next attempt asks for it (`ask_for_part`); one
        // retried alone could store a result under a parent that has ended.
        if let Some(part) = &job.spec.part {
            return Err(OrchestratorError::InvalidRequest(format!(
                "job {} is a part of job {}: retry that job, which runs again the parts it needs",
                job.id, part.parent
            )));
        }
        match job.state {
            JobState::Failed(_) | JobState::Cancelled => {
                requeue(job, now);
                Ok(())
            }
            _ => Err(OrchestratorError::InvalidState {
                id: job.id,
                state: job.state.name(),
                action: "retry",
                allowed: "failed or cancelled",
            }),
        }
    }

    /// Queues `job` now with a fresh attempt budget and no old error.
    fn requeue(job: &mut Job, now: u64) {
        job.state = JobState::Queued { not_before_ms: now };
        job.retried_at = job.attempts;
        // The old failure is history: a retried job shows no error until it fails again
        // (with the reason of that attempt).
        job.last_failure = None;
        job.updated_ms = now;
    }

    /// Whether `job` is a job that may have parts (not a part itself) and has ended: done,
    /// failed for good or cancelled. Its parts are then settled ([`settle_part`]) and their
    /// results dropped, in the same step that ended it.
    pub fn ends_parts(job: &Job) -> bool {
        job.spec.part.is_none() && job.state.is_terminal()
    }

    /// Cancels `part` if it is queued or running and its parent `parent` has ended
    /// ([`ends_parts`]): nobody will take its result. Returns whether it changed.
    pub fn settle_part(parent: &Job, part: &mut Job, now: u64) -> bool {
        let live = matches!(
            part.state,
            JobState::Queued { .. } | JobState::Running { .. }
        );
        if !(ends_parts(parent) && live) {
            return false;
        }
        part.state = JobState::Cancelled;
        part.updated_ms = now;
        true
    }

    /// Checks that `spec` may be added as a part of `parent`: `parent` is no part itself, and
    /// `spec` is its spec with `part` naming it.
    pub fn check_part_of(parent: &Job, spec: &JobSpec) -> Result<(), OrchestratorError> {
        if parent.spec.part.is_some() {
            return Err(OrchestratorError::InvalidRequest(format!(
                "job {} is a part: parts have no parts",
                parent.id
            )));
        }
        let ok = spec.part.as_ref().is_some_and(|p| p.parent == parent.id)
            && parent.spec.is_parent_of(spec);
        if !ok {
            return Err(OrchestratorError::InvalidRequest(format!(
                "a part of job {} must be its spec with `part` naming it",
                parent.id
            )));
        }
        Ok(())
    }

    /// Records that the running attempt `parent_attempt` of a part's parent asks for the known
    /// `part` (adds or polls it), and queues it again if it ended before that attempt first
    /// asked for it (under an earlier attempt of the parent, which runs again: retried, or
    /// taken over after a crash) and its work is needed again: it failed or was cancelled, or
    /// it was done but its result is gone (`has_result` false: dropped when the parent failed
    /// or was cancelled). One that ended after this attempt asked for it stays as it is: the
    /// worker polling it learns that it failed. Compares attempt numbers, never the times two
    /// orchestrators' clocks wrote. Returns whether it changed (to be written).
    pub fn ask_for_part(part: &mut Job, parent_attempt: u32, has_result: bool, now: u64) -> bool {
        if part.asked_by_attempt >= parent_attempt {
            return false;
        }
        let again = match part.state {
            JobState::Failed(_) | JobState::Cancelled => true,
            JobState::Done { .. } => !has_result,
            _ => false,
        };
        if again {
            requeue(part, now);
        }
        part.asked_by_attempt = parent_attempt;
        true
    }
}

/// The in-memory queue (the sled store keeps it behind a mutex and writes changes through).
#[derive(Debug, Clone)]
pub struct Queue {
    cfg: QueueOptions,
    jobs: BTreeMap<JobId, Job>,
    keys: HashMap<String, JobId>,
    next_id: JobId,
    /// The parts that prefer a worker, by worker ([`rules::preferred_worker`]): a hint that leasing
    /// reads instead of scanning the queue. A part is dropped from it when a lease finds it
    /// out of the queue (it then goes to whoever leases it, should it be queued again).
    preferring: HashMap<String, std::collections::BTreeSet<JobId>>,
    /// The parts of each job that has any, by the parent's id, in the order they were added:
    /// what ending a parent settles ([`Queue::settle_parts`]).
    parts: HashMap<JobId, Vec<JobId>>,
}

impl Queue {
    /// An empty queue.
    pub fn new(cfg: QueueOptions) -> Queue {
        Queue {
            cfg,
            jobs: BTreeMap::new(),
            keys: HashMap::new(),
            next_id: 1,
            preferring: HashMap::new(),
            parts: HashMap::new(),
        }
    }

    /// Rebuilds the queue from stored jobs after a restart. Running leases get a fresh
    /// `lease_ms` of grace, since their workers could not heartbeat while we were down. The
    /// live parts of a job that ended are cancelled ([`Queue::settle_parts`]): ending a parent
    /// writes the parent first, so a crash between its write and its parts' leaves exactly
    /// this to finish. Returns the queue and the jobs it changed.
    pub fn restore(cfg: QueueOptions, jobs: Vec<Job>, now: u64) -> (Queue, Vec<Job>) {
        let mut q = Queue::new(cfg);
        let mut changed = Vec::new();
        for mut job in jobs {
            if let JobState::Running {
                lease_expires_ms, ..
            } = &mut job.state
            {
                *lease_expires_ms = (*lease_expires_ms).max(now + cfg.lease_ms);
                changed.push(job.clone());
            }
            q.next_id = q.next_id.max(job.id + 1);
            q.keys.insert(job.spec.dedup_key(), job.id);
            q.note_preference(&job);
            q.note_part(&job);
            q.jobs.insert(job.id, job);
        }
        let ended: Vec<Job> = q
            .parts
            .keys()
            .filter_map(|id| q.jobs.get(id))
            .filter(|j| rules::ends_parts(j))
            .cloned()
            .collect();
        let settled: Vec<Job> = ended
            .iter()
            .flat_map(|parent| q.settle_parts(parent, now))
            .collect();
        // A running part settled here was also given grace above: keep the later copy.
        let ids: HashSet<JobId> = settled.iter().map(|j| j.id).collect();
        changed.retain(|j| !ids.contains(&j.id));
        changed.extend(settled);
        (q, changed)
    }

    /// Records `job` among its parent's parts, if it is a part.
    fn note_part(&mut self, job: &Job) {
        if let Some(p) = &job.spec.part {
            self.parts.entry(p.parent).or_default().push(job.id);
        }
    }

    /// Cancels the live parts of `parent` if it has ended ([`rules::settle_part`]); returns the
    /// parts changed. The embedded store calls this under its lock in the step that ends the
    /// parent (and drops the parts' results there too).
    pub fn settle_parts(&mut self, parent: &Job, now: u64) -> Vec<Job> {
        if !rules::ends_parts(parent) {
            return Vec::new();
        }
        let Some(ids) = self.parts.get(&parent.id) else {
            return Vec::new();
        };
        let mut changed = Vec::new();
        for id in ids {
            if let Some(part) = self.jobs.get_mut(id) {
                if rules::settle_part(parent, part, now) {
                    changed.push(part.clone());
                }
            }
        }
        changed
    }

    /// The jobs that have parts.
    pub fn parents_with_parts(&self) -> Vec<JobId> {
        self.parts.keys().copied().collect()
    }

    /// The ids of `parent`'s parts that are done.
    pub fn done_parts(&self, parent: JobId) -> Vec<JobId> {
        self.parts.get(&parent).map_or_else(Vec::new, |ids| {
            ids.iter()
                .copied()
                .filter(|id| {
                    self.jobs
                        .get(id)
                        .is_some_and(|j| matches!(j.state, JobState::Done { .. }))
                })
                .collect()
        })
    }

    /// Records `job` under the worker it prefers, if it is a queued part that prefers one.
    fn note_preference(&mut self, job: &Job) {
        if let (Some(w), JobState::Queued { .. }) = (rules::preferred_worker(job), &job.state) {
            self.preferring
                .entry(w.to_string())
                .or_default()
                .insert(job.id);
        }
    }

    /// The policy.
    pub fn config(&self) -> &QueueOptions {
        &self.cfg
    }

    /// One job.
    pub fn get(&self, id: JobId) -> Result<&Job, OrchestratorError> {
        self.jobs.get(&id).ok_or(OrchestratorError::NotFound(id))
    }

    fn get_mut(&mut self, id: JobId) -> Result<&mut Job, OrchestratorError> {
        self.jobs
            .get_mut(&id)
            .ok_or(OrchestratorError::NotFound(id))
    }

    /// Every job by id.
    pub fn jobs(&self) -> impl Iterator<Item = &Job> {
        self.jobs.values()
    }

    /// The jobs whose ids follow `after`, by id.
    pub fn jobs_after(&self, after: JobId) -> impl Iterator<Item = &Job> {
        use std::ops::Bound::{Excluded, Unbounded};
        self.jobs
            .range((Excluded(after), Unbounded))
            .map(|(_, j)| j)
    }

    /// Adds a job, or returns the known one with the same content hash, layout, options and
    /// name.
    pub fn submit(&mut self, spec: JobSpec, now: u64) -> Result<Submitted, OrchestratorError> {
        let spec = spec.validate()?;
        let key = spec.dedup_key();
        if let Some(id) = self.keys.get(&key) {
            if let Some(job) = self.jobs.get(id) {
                return Ok(Submitted {
                    job: job.clone(),
                    existed: true,
                });
            }
        }
        let id = self.next_id;
        self.next_id += 1;
        let job = rules::new_job(id, spec, now);
        self.keys.insert(key, id);
        self.note_preference(&job);
        self.note_part(&job);
        self.jobs.insert(id, job.clone());
        Ok(Submitted {
            job,
            existed: false,
        })
    }

    /// Adds the parts `specs` of `parent` for its lease `attempt` presenting `token`, or polls
    /// them if known, as one step: the lease is checked ([`rules::check_held`]) and every
    /// spec ([`rules::check_part_of`]) before anything changes, so a refused call adds nothing.
    /// A known part that ended before this attempt of the parent asked for it runs again
    /// ([`rules::ask_for_part`]; `with_results`: the parent's parts whose results are stored).
    /// Returns the parts in the order asked and every job changed.
    pub fn submit_parts(
        &mut self,
        parent: JobId,
        attempt: u32,
        token: &[u8],
        specs: Vec<JobSpec>,
        with_results: &HashSet<JobId>,
        now: u64,
    ) -> Result<(Vec<Job>, Vec<Job>), OrchestratorError> {
        let holder = self.get(parent)?;
        rules::check_held(holder, attempt, token, now)?;
        let specs = specs
            .into_iter()
            .map(|spec| {
                let spec = spec.validate()?;
                rules::check_part_of(holder, &spec)?;
                Ok(spec)
            })
            .collect::<Result<Vec<JobSpec>, OrchestratorError>>()?;
        let (mut parts, mut changed) = (Vec::with_capacity(specs.len()), Vec::new());
        for spec in specs {
            let s = self.submit(spec, now)?;
            let job = self.get_mut(s.job.id)?;
            if !s.existed {
                job.asked_by_attempt = attempt;
                changed.push(job.clone());
                parts.push(job.clone());
                continue;
            }
            let has_result = with_results.contains(&job.id);
            if rules::ask_for_part(job, attempt, has_result, now) {
                changed.push(job.clone());
            }
            parts.push(job.clone());
        }
        Ok((parts, changed))
    }

    /// Reclaims every lease that expired by `now` (see [`rules::expire`]); a job with parts
    /// that fails for good settles them ([`Queue::settle_parts`]). Returns the changed jobs,
    /// each parent before its parts.
    pub fn reap(&mut self, now: u64) -> Vec<Job> {
        let cfg = self.cfg;
        let expired: Vec<Job> = self
            .jobs
            .values_mut()
            .filter_map(|job| rules::expire(&cfg, job, now).then(|| job.clone()))
            .collect();
        let mut changed = Vec::with_capacity(expired.len());
        for job in expired {
            let parts = self.settle_parts(&job, now);
            changed.push(job);
            changed.extend(parts);
        }
        // A part whose lease lapsed with its parent's was cloned before the parent settled it:
        // each job once (parents before their parts, as first seen), as it now stands, so
        // that the store is written what the queue holds.
        let mut seen = std::collections::HashSet::new();
        changed.retain(|j| seen.insert(j.id));
        for j in &mut changed {
            if let Some(now_held) = self.jobs.get(&j.id) {
                j.clone_from(now_held);
            }
        }
        changed
    }

    /// Leases the oldest runnable job (only parts of bricked jobs with `parts_only`) to
    /// `worker` with the secret `token` (reclaiming expired leases first), the oldest of the
    /// parts that prefer it first ([`rules::preferred_worker`]). Returns the leased job (if
    /// any) and every job changed.
    pub fn lease(
        &mut self,
        worker: &str,
        parts_only: bool,
        token: LeaseToken,
        now: u64,
    ) -> (Option<Job>, Vec<Job>) {
        let mut changed = self.reap(now);
        let cfg = self.cfg;
        let takes = |j: &Job| rules::runnable(j, now) && (!parts_only || j.spec.part.is_some());
        let jobs = &self.jobs;
        let mut chosen = None;
        if let Some(ids) = self.preferring.get_mut(worker) {
            ids.retain(|id| {
                jobs.get(id)
                    .is_some_and(|j| matches!(j.state, JobState::Queued { .. }))
            });
            chosen = ids
                .iter()
                .copied()
                .find(|id| jobs.get(id).is_some_and(takes));
            if ids.is_empty() {
                self.preferring.remove(worker);
            }
        }
        let chosen = chosen.or_else(|| jobs.values().find(|j| takes(j)).map(|j| j.id));
        let Some(job) = chosen.and_then(|id| self.jobs.get_mut(&id)) else {
            return (None, changed);
        };
        // Leased: out of the hint, whichever worker it preferred.
        if let Some(w) = rules::preferred_worker(job) {
            if let Some(ids) = self.preferring.get_mut(w) {
                ids.remove(&job.id);
                if ids.is_empty() {
                    self.preferring.remove(w);
                }
            }
        }
        rules::start(&cfg, job, worker, token, now);
        let job = job.clone();
        changed.push(job.clone());
        (Some(job), changed)
    }

    /// Milliseconds until the next queued job becomes runnable (`None`: none queued).
    pub fn next_runnable_in(&self, now: u64) -> Option<u64> {
        self.jobs
            .values()
            .filter_map(|j| match j.state {
                JobState::Queued { not_before_ms } => Some(not_before_ms.saturating_sub(now)),
                _ => None,
            })
            .min()
    }

    /// Extends a lease (`attempt`, presenting `token`) and records progress.
    pub fn heartbeat(
        &mut self,
        id: JobId,
        attempt: u32,
        token: &[u8],
        progress: f32,
        stage: &str,
        now: u64,
    ) -> Result<Job, OrchestratorError> {
        let cfg = self.cfg;
        let job = self.get_mut(id)?;
        rules::heartbeat(&cfg, job, attempt, token, progress, stage, now)?;
        Ok(job.clone())
    }

    /// Records the outcome of a leased attempt (presenting `token`). A job with parts that
    /// ends leaves them to [`Queue::settle_parts`], which the store calls in the same step.
    pub fn finish(
        &mut self,
        id: JobId,
        attempt: u32,
        token: &[u8],
        outcome: Outcome,
        now: u64,
    ) -> Result<Job, OrchestratorError> {
        let cfg = self.cfg;
        let job = self.get_mut(id)?;
        rules::finish(&cfg, job, attempt, token, outcome, now)?;
        Ok(job.clone())
    }

    /// Cancels a queued or running job (its parts: [`Queue::settle_parts`], as for
    /// [`Queue::finish`]).
    pub fn cancel(&mut self, id: JobId, now: u64) -> Result<Job, OrchestratorError> {
        let job = self.get_mut(id)?;
        rules::cancel(job, now)?;
        Ok(job.clone())
    }

    /// Queues a failed or cancelled job again with a fresh attempt budget.
    pub fn retry(&mut self, id: JobId, now: u64) -> Result<Job, OrchestratorError> {
        let job = self.get_mut(id)?;
        rules::retry(job, now)?;
        Ok(job.clone())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::{Delivery, Failure, FailureKind, JobOptions, Source};

    fn spec(n: u8) -> JobSpec {
        JobSpec {
            name: format!("v{n}"),
            source: Source::Path(format!("/data/v{n}.nii").into()),
            sha256: [n; 32],
            raw: None,
            channel: None,
            options: JobOptions::default(),
            part: None,
        }
    }

    /// The token every lease in these tests gets, and its bytes.
    static T: std::sync::LazyLock<LeaseToken> =
        std::sync::LazyLock::new(|| LeaseToken::from_secret(TB));
    const TB: [u8; LEASE_TOKEN_BYTES] = [7; LEASE_TOKEN_BYTES];

    fn cfg() -> QueueOptions {
        QueueOptions {
            lease_ms: 1000,
            heartbeat_ms: 200,
            max_attempts: 3,
            backoff_base_ms: 100,
            backoff_max_ms: 1000,
        }
    }

    fn delivered() -> Outcome {
        Outcome::Delivered(Delivery {
            cache_volume_id: 1,
            output_bytes: 10,
            voxels: 8,
            existed: false,
            sha256: "ab".repeat(32),
        })
    }

    #[test]
    fn submit_deduplicates_by_content_options_and_name() {
        let mut q = Queue::new(cfg());
        let a = q.submit(spec(1), 0).unwrap();
        assert!(!a.existed);
        let mut moved = spec(1);
        moved.source = Source::Upload { size: 3 };
        let b = q.submit(moved.clone(), 5).unwrap();
        assert!(b.existed);
        assert_eq!(b.job.id, a.job.id);
        // The same content delivered under another name is another job.
        let mut renamed = moved;
        renamed.name = "other".into();
        assert!(!q.submit(renamed, 5).unwrap().existed);
        let mut other_opts = spec(1);
        other_opts.options.bits = 6;
        assert!(!q.submit(other_opts, 5).unwrap().existed);
        assert!(!q.submit(spec(2), 5).unwrap().existed);
        let mut bad = spec(3);
        bad.options.bits = 17;
        let e = q.submit(bad, 5).unwrap_err();
        assert!(e.to_string().contains("bits 17"), "{e}");
    }

    #[test]
    fn lease_is_fifo_and_exclusive() {
        let mut q = Queue::new(cfg());
        q.submit(spec(1), 0).unwrap();
        q.submit(spec(2), 0).unwrap();
        let (a, _) = q.lease("w1", false, *T, 10);
        let (b, _) = q.lease("w2", false, *T, 10);
        let (c, _) = q.lease("w3", false, *T, 10);
        assert_eq!(a.unwrap().id, 1);
        assert_eq!(b.unwrap().id, 2);
        assert!(c.is_none());
    }

    #[test]
    fn expired_lease_is_reclaimed_and_the_stale_worker_is_refused() {
        let mut q = Queue::new(cfg());
        q.submit(spec(1), 0).unwrap();
        let (job, _) = q.lease("w1", false, *T, 0);
        let job = job.unwrap();
        // Heartbeats keep it alive past the original expiry.
        q.heartbeat(job.id, 1, &TB, 0.5, "transform", 900).unwrap();
        assert!(q.reap(1500).is_empty());
        // Silence: expired at 1900.
        let changed = q.reap(1900);
        assert_eq!(changed.len(), 1);
        assert_eq!(
            changed[0].state,
            JobState::Queued {
                not_before_ms: 1900 + 100
            }
        );
        assert_eq!(
            changed[0].last_failure.as_ref().unwrap().kind,
            FailureKind::LeaseExpired
        );
        // Backoff: not runnable yet.
        assert!(q.lease("w2", false, *T, 1950).0.is_none());
        let (again, _) = q.lease("w2", false, *T, 2000);
        assert_eq!(again.unwrap().attempts, 2);
        // The old worker's heartbeat and outcome are refused.
        assert!(matches!(
            q.heartbeat(1, 1, &TB, 0.9, "x", 2010),
            Err(OrchestratorError::LeaseLost { .. })
        ));
        assert!(q.finish(1, 1, &TB, delivered(), 2010).is_err());
        let done = q.finish(1, 2, &TB, delivered(), 2020).unwrap();
        assert!(matches!(done.state, JobState::Done { run_ms: 20, .. }));
    }

    #[test]
    fn transient_failures_back_off_then_fail_with_the_reason() {
        let mut q = Queue::new(cfg());
        q.submit(spec(1), 0).unwrap();
        let fail = || {
            Outcome::Failed(Failure {
                kind: FailureKind::CacheUnavailable,
                message: "connection refused".into(),
            })
        };
        let mut now = 0;
        for attempt in 1..=3u32 {
            let (j, _) = q.lease("w", false, *T, now);
            assert_eq!(j.unwrap().attempts, attempt);
            let j = q.finish(1, attempt, &TB, fail(), now).unwrap();
            match j.state {
                JobState::Queued { not_before_ms } => {
                    assert_eq!(not_before_ms - now, 100 << (attempt - 1));
                    now = not_before_ms;
                }
                JobState::Failed(f) => {
                    assert_eq!(attempt, 3);
                    assert!(f.message.contains("connection refused"));
                    assert!(f.message.contains("3 attempts"));
                }
                s => panic!("unexpected {s:?}"),
            }
        }
    }

    #[test]
    fn permanent_failures_are_not_retried() {
        let mut q = Queue::new(cfg());
        q.submit(spec(1), 0).unwrap();
        q.lease("w", false, *T, 0);
        let j = q
            .finish(
                1,
                1,
                &TB,
                Outcome::Failed(Failure {
                    kind: FailureKind::InvalidInput,
                    message: "NaN at voxel 3".into(),
                }),
                5,
            )
            .unwrap();
        assert_eq!(j.state.name(), "failed");
        // Retry queues it again with a fresh budget.
        let j = q.retry(1, 10).unwrap();
        assert_eq!((j.attempts, j.retried_at), (1, 1));
        assert_eq!(j.state, JobState::Queued { not_before_ms: 10 });
        assert_eq!(j.last_failure, None, "a retried job keeps no old error");
        assert!(q.retry(1, 10).is_err());
    }

    #[test]
    fn cancel_stops_queued_and_running_jobs() {
        let mut q = Queue::new(cfg());
        q.submit(spec(1), 0).unwrap();
        q.submit(spec(2), 0).unwrap();
        q.lease("w", false, *T, 0);
        q.cancel(1, 1).unwrap();
        q.cancel(2, 1).unwrap();
        assert!(q.lease("w", false, *T, 2).0.is_none());
        let e = q.heartbeat(1, 1, &TB, 0.1, "s", 3).unwrap_err();
        assert!(e.to_string().contains("cancelled"), "{e}");
        assert!(q.finish(1, 1, &TB, delivered(), 3).is_err());
        assert!(matches!(
            q.cancel(1, 4),
            Err(OrchestratorError::InvalidState { .. })
        ));
        assert!(matches!(q.get(9), Err(OrchestratorError::NotFound(9))));
    }

    /// The running lease named without its token is refused as not held by the caller and
    /// changes nothing; a stale attempt is a lost lease whatever token it presents.
    #[test]
    fn a_lease_is_held_by_its_token() {
        let mut q = Queue::new(cfg());
        q.submit(spec(1), 0).unwrap();
        let (job, _) = q.lease("w", false, *T, 0);
        let job = job.unwrap();
        for wrong in [
            &[][..],
            &[7; 15][..],
            &[8; LEASE_TOKEN_BYTES][..],
            &[7; 17][..],
        ] {
            let e = q.heartbeat(1, 1, wrong, 0.5, "s", 10).unwrap_err();
            assert!(
                matches!(e, OrchestratorError::NotLeaseHolder { id: 1, attempt: 1 }),
                "{e}"
            );
            let e = q.finish(1, 1, wrong, delivered(), 10).unwrap_err();
            assert!(matches!(e, OrchestratorError::NotLeaseHolder { .. }), "{e}");
        }
        assert_eq!(q.get(1).unwrap(), &job, "nothing changed");
        assert!(matches!(
            q.heartbeat(1, 2, &TB, 0.5, "s", 10),
            Err(OrchestratorError::LeaseLost { .. })
        ));
        q.heartbeat(1, 1, &TB, 0.5, "s", 10).unwrap();
    }

    /// A parent on its last attempt and one of its parts lapse in the same pass: the parent
    /// fails for good and cancels the part, and what the pass hands to the store holds each
    /// once, parent first, as the queue now has them (not the part's requeued copy after its
    /// cancelled one).
    #[test]
    fn a_part_lapsing_with_its_failing_parent_is_written_once_as_settled() {
        use crate::model::{PartSpec, PartStep};
        let parent_spec = JobSpec {
            options: JobOptions {
                brick: Some(16),
                ..JobOptions::default()
            },
            ..spec(1)
        };
        let mut q = Queue::new(cfg());
        q.submit(parent_spec.clone(), 0).unwrap();
        // Two lapsed attempts (reaped by the next lease), then the third.
        let mut now = 0;
        for attempt in 1..=3u32 {
            let (j, _) = q.lease("coord", false, *T, now);
            assert_eq!(j.unwrap().attempts, attempt);
            now += 1000;
            if attempt < 3 {
                q.reap(now);
                now += 1000;
            }
        }
        now -= 1000;
        let part = JobSpec {
            part: Some(PartSpec {
                parent: 1,
                index: 0,
                of: 4,
                step: PartStep::Score { energies: false },
                levels: 2,
                offset: Some(0.5),
                color: None,
                source_bytes: None,
                time_points: None,
                prefer_worker: None,
            }),
            ..parent_spec
        };
        let (parts, _) = q
            .submit_parts(1, 3, &TB, vec![part], &HashSet::new(), now)
            .unwrap();
        let part_id = parts[0].id;
        let (leased, _) = q.lease("w", true, *T, now);
        assert_eq!(leased.unwrap().id, part_id);
        let changed = q.reap(now + 1000);
        let ids: Vec<JobId> = changed.iter().map(|j| j.id).collect();
        assert_eq!(ids, [1, part_id], "each once, the parent first");
        assert_eq!(changed[0].state.name(), "failed");
        assert_eq!(changed[1].state, JobState::Cancelled);
        assert_eq!(
            q.get(part_id).unwrap(),
            &changed[1],
            "the store gets what the queue has"
        );
    }

    /// A part runs again when its parent's next attempt asks for it if it ended before (under
    /// an earlier attempt) and its work is needed: failed or cancelled, or done without a
    /// stored result; whatever the times say.
    #[test]
    fn a_part_is_revived_when_its_work_is_needed_again() {
        let mut part = rules::new_job(2, spec(2), 0);
        part.state = JobState::Done {
            delivery: match delivered() {
                Outcome::Delivered(d) => d,
                Outcome::Failed(_) => unreachable!(),
            },
            run_ms: 1,
            worker: "w".into(),
        };
        part.asked_by_attempt = 1;
        part.updated_ms = 500;
        let mut kept = part.clone();
        assert!(
            !rules::ask_for_part(&mut kept, 1, false, 600),
            "done after attempt 1 asked for it"
        );
        assert!(
            rules::ask_for_part(&mut kept, 2, true, 600),
            "attempt 2 asks"
        );
        assert_eq!(kept.state, part.state, "its result is kept");
        assert_eq!(kept.asked_by_attempt, 2);
        // Ended later than the parent's next attempt started by a clock, earlier by the
        // attempts: it runs again.
        assert!(rules::ask_for_part(&mut part, 2, false, 100));
        assert_eq!(part.state, JobState::Queued { not_before_ms: 100 });
        part.state = JobState::Cancelled;
        assert!(
            !rules::ask_for_part(&mut part, 2, false, 130),
            "cancelled after attempt 2 asked for it"
        );
        assert_eq!(part.state, JobState::Cancelled);
    }

    #[test]
    fn restore_keeps_states_and_gives_running_leases_grace() {
        let mut q = Queue::new(cfg());
        q.submit(spec(1), 0).unwrap();
        q.submit(spec(2), 0).unwrap();
        q.lease("w", false, *T, 0);
        let jobs: Vec<Job> = q.jobs().cloned().collect();
        let (mut r, changed) = Queue::restore(cfg(), jobs, 5000);
        assert_eq!(changed.len(), 1);
        assert!(r.reap(5500).is_empty());
        assert!(r.heartbeat(1, 1, &TB, 0.5, "s", 5600).is_ok());
        assert_eq!(r.submit(spec(3), 5700).unwrap().job.id, 3);
        assert!(r.submit(spec(2), 5700).unwrap().existed);
    }
}
