//! One storage contract, two implementations: the same scenarios run against the embedded
//! store (sled in a tempdir) and the PostgreSQL store (a real server started by the test, one
//! database per scenario), through the [`JobStore`] interface the orchestrator's RPCs use, with
//! a clock the test drives. Two PostgreSQL stores over one database stand for two orchestrators.

mod common;

use std::collections::HashSet;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use wavesplat_harness::postgres::PostgresServer;
use wavesplat_orchestrator::model::{
    Delivery, Failure, FailureKind, Job, JobOptions, JobSpec, JobState, Outcome, Source,
};
use wavesplat_orchestrator::queue::QueueOptions;
use wavesplat_orchestrator::service::Clock;
use wavesplat_orchestrator::store::Store;
use wavesplat_orchestrator::{EmbeddedQueue, JobStore, OrchestratorError, PostgresQueue};

fn options() -> QueueOptions {
    QueueOptions {
        lease_ms: 1000,
        heartbeat_ms: 200,
        max_attempts: 3,
        backoff_base_ms: 100,
        backoff_max_ms: 1000,
    }
}

fn spec(n: u32) -> JobSpec {
    let mut sha = [0u8; 32];
    sha[..4].copy_from_slice(&(n + 1).to_be_bytes());
    JobSpec {
        name: format!("v{n}"),
        source: Source::Path(format!("/data/v{n}.nii").into()),
        sha256: sha,
        raw: None,
        channel: None,
        options: JobOptions::default(),
        part: None,
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

fn failed(kind: FailureKind) -> Outcome {
    Outcome::Failed(Failure {
        kind,
        message: format!("{} trouble", kind.name()),
    })
}

/// A clock the test sets.
#[derive(Clone, Default)]
struct TestClock(Arc<AtomicU64>);

impl TestClock {
    fn clock(&self) -> Clock {
        let t = self.0.clone();
        Arc::new(move || t.load(Ordering::SeqCst))
    }
    fn set(&self, ms: u64) {
        self.0.store(ms, Ordering::SeqCst);
    }
}

/// Makes fresh stores of one kind: `open()` gives a store over a new empty queue, `reopen()`
/// a second store over the same queue (another orchestrator, or the same after a restart).
#[tonic::async_trait]
trait Backend {
    async fn open(&mut self, clock: &TestClock) -> Arc<dyn JobStore>;
    async fn reopen(&mut self, clock: &TestClock) -> Arc<dyn JobStore>;
    /// Everything the last queue opened keeps at rest, as bytes (its files; its tables' rows),
    /// to look for what must not be there.
    fn at_rest(&self) -> Vec<u8>;
}

struct Embedded {
    dirs: Vec<tempfile::TempDir>,
    last: Option<Arc<dyn JobStore>>,
}

#[tonic::async_trait]
impl Backend for Embedded {
    async fn open(&mut self, clock: &TestClock) -> Arc<dyn JobStore> {
        self.dirs.push(tempfile::tempdir().unwrap());
        self.last = None;
        self.reopen(clock).await
    }
    async fn reopen(&mut self, clock: &TestClock) -> Arc<dyn JobStore> {
        // One process owns a sled directory: the old store is closed first.
        if let Some(old) = self.last.take() {
            old.close().await.unwrap();
            drop(old);
        }
        let dir = self.dirs.last().unwrap().path().to_path_buf();
        let mut tries = 0;
        let store = loop {
            match Store::open(&dir) {
                Ok(s) => break s,
                Err(e) if tries < 250 => {
                    tries += 1;
                    let _ = e;
                    tokio::time::sleep(std::time::Duration::from_millis(20)).await
                }
                Err(e) => panic!("reopening the embedded store: {e}"),
            }
        };
        let q: Arc<dyn JobStore> =
            Arc::new(EmbeddedQueue::open(store, options(), clock.clock()).unwrap());
        self.last = Some(q.clone());
        q
    }
    fn at_rest(&self) -> Vec<u8> {
        fn read_all(dir: &std::path::Path, out: &mut Vec<u8>) {
            for entry in std::fs::read_dir(dir).unwrap() {
                let path = entry.unwrap().path();
                if path.is_dir() {
                    read_all(&path, out);
                } else {
                    out.extend(std::fs::read(&path).unwrap());
                }
            }
        }
        let mut out = Vec::new();
        read_all(self.dirs.last().unwrap().path(), &mut out);
        out
    }
}

struct Postgres {
    server: PostgresServer,
    databases: usize,
}

impl Postgres {
    fn url(&self) -> String {
        self.server
            .url_with_password(&format!("contract{}", self.databases))
    }
}

#[tonic::async_trait]
impl Backend for Postgres {
    async fn open(&mut self, clock: &TestClock) -> Arc<dyn JobStore> {
        self.databases += 1;
        self.server
            .create_database(&format!("contract{}", self.databases))
            .unwrap();
        self.reopen(clock).await
    }
    async fn reopen(&mut self, clock: &TestClock) -> Arc<dyn JobStore> {
        let q = PostgresQueue::connect(&self.url(), Default::default())
            .await
            .unwrap()
            .with_options(options())
            .with_clock(clock.clock());
        Arc::new(q)
    }
    fn at_rest(&self) -> Vec<u8> {
        self.server
            .psql(
                &format!("contract{}", self.databases),
                "SELECT coalesce(encode(lease_token, 'hex'), '') || ' ' || job::text FROM jobs",
            )
            .unwrap()
            .into_bytes()
    }
}

fn lease_lost(e: &OrchestratorError) -> bool {
    matches!(e, OrchestratorError::LeaseLost { .. })
}

/// The token of the lease `j` was leased under (as the worker got it).
fn tok(j: &Job) -> Vec<u8> {
    j.state
        .lease_token()
        .and_then(|t| t.secret())
        .expect("a job just leased holds its token's secret")
        .to_vec()
}

async fn submit_deduplicates_by_content_options_and_name(b: &mut dyn Backend) {
    let clock = TestClock::default();
    let q = b.open(&clock).await;
    let a = q.submit(spec(1), None).await.unwrap();
    assert!(!a.existed);
    assert_eq!(a.job.state, JobState::Queued { not_before_ms: 0 });
    let again = q.submit(spec(1), None).await.unwrap();
    assert!(again.existed);
    assert_eq!(again.job.id, a.job.id);
    let mut renamed = spec(1);
    renamed.name = "other".into();
    assert!(!q.submit(renamed, None).await.unwrap().existed);
    let mut opts = spec(1);
    opts.options.bits = 7;
    assert!(!q.submit(opts, None).await.unwrap().existed);
    let mut bad = spec(2);
    bad.name = String::new();
    let e = q.submit(bad, None).await.unwrap_err();
    assert!(matches!(e, OrchestratorError::InvalidRequest(_)), "{e}");
    assert_eq!(q.list().await.unwrap().len(), 3);
    assert!(matches!(
        q.get(999).await,
        Err(OrchestratorError::NotFound(999))
    ));
}

/// A page read from the store (`list_after`: what `ListJobs` pages by) is the whole list's
/// slice after its cursor, in id order, at most its limit.
async fn pages_read_from_the_store_are_slices_of_the_whole_list(b: &mut dyn Backend) {
    let clock = TestClock::default();
    let q = b.open(&clock).await;
    for n in 100..107 {
        q.submit(spec(n), None).await.unwrap();
    }
    let all: Vec<u64> = q.list().await.unwrap().iter().map(|j| j.id).collect();
    assert_eq!(all.len(), 7);
    for after in [0, all[2], all[6], all[6] + 1000, u64::MAX] {
        for limit in [1, 3, 100] {
            let page: Vec<u64> = q
                .list_after(after, limit)
                .await
                .unwrap()
                .iter()
                .map(|j| j.id)
                .collect();
            let want: Vec<u64> = all
                .iter()
                .copied()
                .filter(|&id| id > after)
                .take(limit)
                .collect();
            assert_eq!(page, want, "after {after}, limit {limit}");
        }
    }
    // Paging through with a cursor lists every job once.
    let (mut cursor, mut seen) = (0, Vec::new());
    loop {
        let page = q.list_after(cursor, 2).await.unwrap();
        let Some(last) = page.last() else { break };
        cursor = last.id;
        seen.extend(page.iter().map(|j| j.id));
    }
    assert_eq!(seen, all);
}

async fn leases_are_fifo_and_exclusive_across_stores(b: &mut dyn Backend, stores: usize) {
    let clock = TestClock::default();
    let first = b.open(&clock).await;
    let mut qs = vec![first];
    for _ in 1..stores {
        qs.push(b.reopen(&clock).await);
    }
    for n in 0..40 {
        qs[0].submit(spec(n), None).await.unwrap();
    }
    // One lease alone takes the oldest.
    let oldest = qs[0].lease("solo", false).await.unwrap().job.unwrap();
    assert_eq!(oldest.spec.name, "v0");
    assert_eq!(oldest.attempts, 1);
    // Eight callers at once over every store lease the rest, each job once.
    let mut tasks = Vec::new();
    for w in 0..8 {
        let q = qs[w % qs.len()].clone();
        tasks.push(tokio::spawn(async move {
            let mut got = Vec::new();
            while let Some(j) = q.lease(&format!("w{w}"), false).await.unwrap().job {
                got.push(j.id);
            }
            got
        }));
    }
    let mut all = vec![oldest.id];
    for t in tasks {
        all.extend(t.await.unwrap());
    }
    let unique: HashSet<u64> = all.iter().copied().collect();
    assert_eq!(all.len(), 40, "{all:?}");
    assert_eq!(unique.len(), 40, "a job was leased twice: {all:?}");
    let leased = qs[qs.len() - 1].lease("late", false).await.unwrap();
    assert!(leased.job.is_none());
    assert_eq!(leased.next_runnable_in, None);
}

async fn an_expired_lease_is_reclaimed_and_the_stale_worker_refused(b: &mut dyn Backend) {
    let clock = TestClock::default();
    let q = b.open(&clock).await;
    let other = b.reopen(&clock).await;
    q.submit(spec(1), None).await.unwrap();
    let job = q.lease("w1", false).await.unwrap().job.unwrap();
    clock.set(900);
    other
        .heartbeat(job.id, 1, &tok(&job), 0.5, "transform")
        .await
        .unwrap();
    clock.set(1500);
    assert_eq!(
        q.reap().await.unwrap(),
        0,
        "the heartbeat extended the lease"
    );
    let running = other.get(job.id).await.unwrap();
    assert!(
        matches!(&running.state, JobState::Running { progress, stage, .. } if *progress == 0.5 && stage == "transform"),
        "{:?}",
        running.state
    );
    clock.set(1900);
    assert_eq!(other.reap().await.unwrap(), 1);
    let j = q.get(job.id).await.unwrap();
    assert_eq!(
        j.state,
        JobState::Queued {
            not_before_ms: 2000
        }
    );
    assert!(j
        .last_failure
        .unwrap()
        .message
        .contains("stopped heartbeating"));
    let wait = q.lease("w2", false).await.unwrap();
    assert!(wait.job.is_none(), "backing off");
    assert_eq!(wait.next_runnable_in, Some(100));
    clock.set(2000);
    let again = other.lease("w2", false).await.unwrap().job.unwrap();
    assert_eq!(again.attempts, 2);
    let e = q
        .heartbeat(job.id, 1, &tok(&job), 0.9, "x")
        .await
        .unwrap_err();
    assert!(lease_lost(&e), "{e}");
    let e = q
        .finish(job.id, 1, &tok(&job), delivered())
        .await
        .unwrap_err();
    assert!(lease_lost(&e), "{e}");
    clock.set(2010);
    let done = other
        .finish(job.id, 2, &tok(&again), delivered())
        .await
        .unwrap();
    assert!(matches!(done.state, JobState::Done { run_ms: 10, .. }));
    // A finished lease cannot be finished again (a duplicate report after a retry).
    let e = q
        .finish(job.id, 2, &tok(&again), delivered())
        .await
        .unwrap_err();
    assert!(lease_lost(&e), "{e}");
}

async fn failures_back_off_retry_and_stop(b: &mut dyn Backend) {
    let clock = TestClock::default();
    let q = b.open(&clock).await;
    q.submit(spec(1), None).await.unwrap();
    q.submit(spec(2), None).await.unwrap();
    let mut now = 0;
    // The token of job 2's first lease.
    let mut stale = Vec::new();
    for attempt in 1..=3 {
        clock.set(now);
        let j = q.lease("w", false).await.unwrap().job.unwrap();
        assert_eq!((j.id, j.attempts), (1, attempt));
        let j = q
            .finish(1, attempt, &tok(&j), failed(FailureKind::CacheUnavailable))
            .await
            .unwrap();
        match j.state {
            JobState::Queued { not_before_ms } => {
                assert!(attempt < 3);
                assert_eq!(not_before_ms, now + (100 << (attempt - 1)));
                now = not_before_ms;
            }
            JobState::Failed(f) => {
                assert_eq!(attempt, 3);
                assert!(f.message.contains("after 3 attempts"), "{}", f.message);
            }
            s => panic!("{s:?}"),
        }
        // Job 2 is leased between job 1's attempts and left running.
        if attempt == 1 {
            let two = q.lease("w", false).await.unwrap().job.unwrap();
            assert_eq!(two.id, 2);
            q.finish(2, 1, &tok(&two), failed(FailureKind::InvalidInput))
                .await
                .unwrap();
            stale = tok(&two);
        }
    }
    let two = q.get(2).await.unwrap();
    assert!(
        matches!(two.state, JobState::Failed(_)),
        "permanent: not retried"
    );
    assert_eq!(two.attempts, 1);
    // Retry gives a fresh budget and no stale error; cancel stops queued and running jobs.
    let r = q.retry(2).await.unwrap();
    assert_eq!(
        (r.attempts - r.retried_at, r.last_failure.is_none()),
        (0, true)
    );
    let e = q.retry(2).await.unwrap_err();
    assert!(matches!(e, OrchestratorError::InvalidState { .. }), "{e}");
    let running = q.lease("w", false).await.unwrap().job.unwrap();
    assert_eq!(running.id, 2);
    // The retried job's attempt number goes on (2), never handed out again: the worker of
    // attempt 1 (cancelled while running, say) cannot take the new lease for its own.
    assert_eq!(running.attempts, 2);
    let e = q.heartbeat(2, 1, &stale, 0.1, "s").await.unwrap_err();
    assert!(lease_lost(&e), "{e}");
    let e = q.finish(2, 1, &stale, delivered()).await.unwrap_err();
    assert!(lease_lost(&e), "{e}");
    q.heartbeat(2, 2, &tok(&running), 0.1, "s").await.unwrap();
    q.cancel(2).await.unwrap();
    let e = q
        .heartbeat(2, 2, &tok(&running), 0.1, "s")
        .await
        .unwrap_err();
    assert!(lease_lost(&e) && e.to_string().contains("cancelled"), "{e}");
    let e = q.cancel(2).await.unwrap_err();
    assert!(matches!(e, OrchestratorError::InvalidState { .. }), "{e}");
    let c = q.counts().await.unwrap();
    assert_eq!((c.failed, c.cancelled, c.queued), (1, 1, 0));
    // Retried again: its budget counts from here, its attempt numbers go on.
    let r = q.retry(2).await.unwrap();
    assert_eq!((r.attempts, r.retried_at), (2, 2));
}

async fn uploads_live_until_no_unfinished_job_needs_them(b: &mut dyn Backend) {
    let clock = TestClock::default();
    let q = b.open(&clock).await;
    let big: Vec<u8> = (0..(2 << 20) + 17).map(|i| (i * 7 % 251) as u8).collect();
    let up = |name: &str, sha: u8, size: usize| JobSpec {
        name: name.into(),
        source: Source::Upload { size: size as u64 },
        sha256: [sha; 32],
        raw: None,
        channel: None,
        options: JobOptions::default(),
        part: None,
    };
    q.submit(up("a", 1, big.len()), Some(big.clone()))
        .await
        .unwrap();
    q.submit(up("b", 1, big.len()), Some(big.clone()))
        .await
        .unwrap();
    q.submit(up("empty", 2, 0), Some(Vec::new())).await.unwrap();
    assert_eq!(q.upload(&[1; 32]).await.unwrap().as_deref(), Some(&big[..]));
    assert_eq!(q.upload(&[2; 32]).await.unwrap(), Some(Vec::new()));
    assert_eq!(q.upload(&[3; 32]).await.unwrap(), None);
    let a = q.lease("w", false).await.unwrap().job.unwrap();
    q.finish(a.id, 1, &tok(&a), delivered()).await.unwrap();
    assert!(
        q.upload(&[1; 32]).await.unwrap().is_some(),
        "b still needs it"
    );
    let b2 = q.lease("w", false).await.unwrap().job.unwrap();
    q.finish(b2.id, 1, &tok(&b2), delivered()).await.unwrap();
    assert_eq!(q.upload(&[1; 32]).await.unwrap(), None);
    // A source that no job takes is not kept: a job refused as invalid, and one known and
    // done already (submitted again with its upload).
    assert!(q.submit(up("", 4, 3), Some(vec![1, 2, 3])).await.is_err());
    assert_eq!(q.upload(&[4; 32]).await.unwrap(), None);
    let again = q
        .submit(up("a", 1, big.len()), Some(big.clone()))
        .await
        .unwrap();
    assert!(again.existed);
    assert_eq!(q.upload(&[1; 32]).await.unwrap(), None);
}

async fn a_second_store_sees_every_acknowledged_change(b: &mut dyn Backend) {
    let clock = TestClock::default();
    let q = b.open(&clock).await;
    for n in 0..5 {
        q.submit(spec(n), None).await.unwrap();
    }
    let j = q.lease("w", false).await.unwrap().job.unwrap();
    q.finish(j.id, 1, &tok(&j), delivered()).await.unwrap();
    q.cancel(3).await.unwrap();
    let held = q.lease("w", false).await.unwrap().job.unwrap();
    let before = q.list().await.unwrap();
    drop(q);
    let after = b.reopen(&clock).await.list().await.unwrap();
    assert_eq!(before.len(), after.len());
    for (x, y) in before.iter().zip(&after) {
        assert_eq!((x.id, &x.spec, x.attempts), (y.id, &y.spec, y.attempts));
        if x.id != held.id {
            assert_eq!(x.state, y.state);
        }
    }
}

/// Eight workers at once lease and report 600 jobs to the end (over every store): nothing
/// hangs, nothing is done twice.
async fn many_workers_finish_an_archive(b: &mut dyn Backend, stores: usize) {
    let clock = TestClock::default();
    let mut qs = vec![b.open(&clock).await];
    for _ in 1..stores {
        qs.push(b.reopen(&clock).await);
    }
    for n in 0..600 {
        qs[0].submit(spec(n), None).await.unwrap();
    }
    let mut tasks = Vec::new();
    for w in 0..8 {
        let q = qs[w % qs.len()].clone();
        tasks.push(tokio::spawn(async move {
            let mut done = Vec::new();
            while let Some(j) = q.lease(&format!("w{w}"), false).await.unwrap().job {
                let t = tok(&j);
                q.heartbeat(j.id, j.attempts, &t, 0.5, "half")
                    .await
                    .unwrap();
                q.finish(j.id, j.attempts, &t, delivered()).await.unwrap();
                done.push(j.id);
            }
            done
        }));
    }
    let all = tokio::time::timeout(std::time::Duration::from_secs(120), async {
        let mut all = Vec::new();
        for t in tasks {
            all.extend(t.await.unwrap());
        }
        all
    })
    .await
    .expect("eight workers did not finish 600 jobs in 120 s: a hang");
    let unique: HashSet<u64> = all.iter().copied().collect();
    assert_eq!((all.len(), unique.len()), (600, 600));
    assert_eq!(qs[0].counts().await.unwrap().done, 600);
}

/// Parts of bricked jobs: a worker waiting on its parts leases only parts (the oldest one, past
/// older whole jobs); a part's result is kept, replaced by a later attempt's, seen by a second
/// store, and dropped with its bricked job's other results only.
async fn parts_lease_apart_and_their_results_live_until_dropped(b: &mut dyn Backend) {
    use wavesplat_orchestrator::model::{PartSpec, PartStep};
    let clock = TestClock::default();
    let q = b.open(&clock).await;
    let bricked = |n: u32| JobSpec {
        options: JobOptions {
            brick: Some(16),
            ..JobOptions::default()
        },
        ..spec(n)
    };
    let part = |parent: u64, index: u32| JobSpec {
        part: Some(PartSpec {
            parent,
            index,
            of: 2,
            step: PartStep::Score { energies: false },
            levels: 2,
            offset: Some(0.5),
            color: None,
            source_bytes: None,
            time_points: None,
            prefer_worker: None,
        }),
        ..bricked(1)
    };
    let whole = q.submit(spec(0), None).await.unwrap().job;
    let parent = q.submit(bricked(1), None).await.unwrap().job;
    assert!(
        q.lease("idle", true).await.unwrap().job.is_none(),
        "no parts yet"
    );
    let p0 = q.submit(part(parent.id, 0), None).await.unwrap().job;
    let p1 = q.submit(part(parent.id, 1), None).await.unwrap().job;
    assert!(q.submit(part(parent.id, 1), None).await.unwrap().existed);
    let got = q.lease("coordinator", true).await.unwrap().job.unwrap();
    assert_eq!(got.id, p0.id, "the oldest part, not the older whole jobs");
    let next = q.lease("any", false).await.unwrap().job.unwrap();
    assert_eq!(
        next.id, whole.id,
        "a plain lease takes the oldest job of any kind"
    );
    let got1 = q.lease("other", true).await.unwrap().job.unwrap();
    assert_eq!(got1.id, p1.id);
    let (t0, t1) = (tok(&got), tok(&got1));
    q.put_result(parent.id, p0.id, 1, &t0, vec![1; 10])
        .await
        .unwrap();
    q.put_result(parent.id, p0.id, 1, &t0, vec![2; 3])
        .await
        .unwrap();
    q.put_result(parent.id + 100, p1.id, 1, &t1, vec![9])
        .await
        .unwrap();
    let big: Vec<u8> = (0..(3 << 20) + 5).map(|i| (i % 253) as u8).collect();
    q.put_result(parent.id, p1.id, 1, &t1, big.clone())
        .await
        .unwrap();
    assert_eq!(q.result(parent.id, p0.id).await.unwrap(), Some(vec![2; 3]));
    // Only the attempt holding the part's live lease stores a result: not another attempt,
    // not once the part is done (a stale worker cannot replace the finished part's result).
    let e = q
        .put_result(parent.id, p0.id, 2, &t0, vec![7])
        .await
        .unwrap_err();
    assert!(lease_lost(&e), "{e}");
    q.finish(p0.id, 1, &t0, delivered()).await.unwrap();
    let e = q
        .put_result(parent.id, p0.id, 1, &t0, vec![7])
        .await
        .unwrap_err();
    assert!(lease_lost(&e), "{e}");
    assert_eq!(q.result(parent.id, p0.id).await.unwrap(), Some(vec![2; 3]));
    drop(q);
    let other = b.reopen(&clock).await;
    assert_eq!(other.result(parent.id, p1.id).await.unwrap(), Some(big));
    assert_eq!(other.result(parent.id, 999).await.unwrap(), None);
    assert_eq!(other.drop_results(parent.id).await.unwrap(), 2);
    assert_eq!(other.result(parent.id, p0.id).await.unwrap(), None);
    assert_eq!(
        other.result(parent.id + 100, p1.id).await.unwrap(),
        Some(vec![9]),
        "another job's results stay"
    );
}

/// A part that prefers a worker goes to that worker's lease before older jobs, and to any
/// other's when it is the oldest; a done job names the worker that finished it; the preference
/// is not part of a part's identity.
async fn a_part_goes_first_to_the_worker_it_prefers(b: &mut dyn Backend) {
    use wavesplat_orchestrator::model::{JobState, PartSpec, PartStep};
    let clock = TestClock::default();
    let q = b.open(&clock).await;
    let bricked = JobSpec {
        options: JobOptions {
            brick: Some(16),
            ..JobOptions::default()
        },
        ..spec(1)
    };
    let part = |parent: u64, index: u32, prefer: Option<&str>| JobSpec {
        part: Some(PartSpec {
            parent,
            index,
            of: 4,
            step: PartStep::Encode {
                count: Some(10),
                trial: 0,
            },
            levels: 2,
            offset: Some(0.5),
            color: None,
            source_bytes: None,
            time_points: None,
            prefer_worker: prefer.map(str::to_string),
        }),
        ..bricked.clone()
    };
    let parent = q.submit(bricked.clone(), None).await.unwrap().job;
    let leased = q.lease("coordinator", false).await.unwrap().job.unwrap();
    assert_eq!(leased.id, parent.id);
    let p0 = q.submit(part(parent.id, 0, None), None).await.unwrap().job;
    let p1 = q
        .submit(part(parent.id, 1, Some("w2")), None)
        .await
        .unwrap()
        .job;
    let p2 = q
        .submit(part(parent.id, 2, Some("w1")), None)
        .await
        .unwrap()
        .job;
    let p3 = q
        .submit(part(parent.id, 3, Some("w2")), None)
        .await
        .unwrap()
        .job;
    let again = q
        .submit(part(parent.id, 1, Some("w9")), None)
        .await
        .unwrap();
    assert!(again.existed, "another preference is the same part");
    assert_eq!(again.job.id, p1.id);
    let w1 = q.lease("w1", true).await.unwrap().job.unwrap();
    assert_eq!(w1.id, p2.id, "w1's own part before the older ones");
    let w2 = q.lease("w2", true).await.unwrap().job.unwrap();
    assert_eq!(w2.id, p1.id, "w2's oldest own part");
    let w3 = q.lease("w3", true).await.unwrap().job.unwrap();
    assert_eq!(w3.id, p0.id, "no part prefers w3: the oldest");
    let w1 = q.lease("w1", true).await.unwrap().job.unwrap();
    assert_eq!(
        w1.id, p3.id,
        "w1 takes w2's part when nothing else is queued"
    );
    let done = q
        .finish(w1.id, w1.attempts, &tok(&w1), delivered())
        .await
        .unwrap();
    match done.state {
        JobState::Done { worker, .. } => assert_eq!(worker, "w1"),
        other => panic!("not done: {other:?}"),
    }
    drop(q);
    let seen = b.reopen(&clock).await.get(p3.id).await.unwrap();
    assert!(
        matches!(seen.state, JobState::Done { ref worker, .. } if worker == "w1"),
        "{:?}",
        seen.state
    );
}

/// A bricked job (bricks of 16) of `spec(n)`.
fn bricked(n: u32) -> JobSpec {
    JobSpec {
        options: JobOptions {
            brick: Some(16),
            ..JobOptions::default()
        },
        ..spec(n)
    }
}

/// Part `index` (a score step, of 128) of the bricked job `parent`, whose spec is `bricked(n)`.
fn part_of(parent: u64, n: u32, index: u32) -> JobSpec {
    use wavesplat_orchestrator::model::{PartSpec, PartStep};
    JobSpec {
        part: Some(PartSpec {
            parent,
            index,
            of: 128,
            step: PartStep::Score { energies: false },
            levels: 2,
            offset: Some(0.5),
            color: None,
            source_bytes: None,
            time_points: None,
            prefer_worker: None,
        }),
        ..bricked(n)
    }
}

fn not_holder(e: &OrchestratorError) -> bool {
    matches!(e, OrchestratorError::NotLeaseHolder { .. })
}

/// The parts of `parent` among `jobs`, by id.
fn parts_of(jobs: Vec<Job>, parent: u64) -> Vec<Job> {
    jobs.into_iter()
        .filter(|j| j.spec.part.as_ref().is_some_and(|p| p.parent == parent))
        .collect()
}

/// Whether a part ended before its parent's running attempt asked for it is decided by attempt
/// numbers, not by clocks: a part that fails for good at an orchestrator whose clock is 5 s
/// behind the one that leased its parent, after the parent's attempt added it, stays failed
/// when that attempt polls it (it was revived by the times); the parent's next attempt runs it
/// again.
async fn a_part_ended_under_its_parents_attempt_stays_ended_whatever_the_clocks(
    b: &mut dyn Backend,
) {
    let (ahead, behind) = (TestClock::default(), TestClock::default());
    ahead.set(10_000);
    behind.set(5_000);
    let q = b.open(&ahead).await;
    let parent = q.submit(bricked(1), None).await.unwrap().job;
    let p = q.lease("coordinator", false).await.unwrap().job.unwrap();
    assert_eq!(p.id, parent.id);
    let tp = tok(&p);
    let asked = || vec![part_of(p.id, 1, 0)];
    let added = q
        .submit_parts(p.id, p.attempts, &tp, asked())
        .await
        .unwrap();
    // The part's worker leases it, then reports through the orchestrator behind: the part fails
    // for good there.
    let x = q.lease("w", true).await.unwrap().job.unwrap();
    assert_eq!(x.id, added[0].id);
    drop(q);
    let q = b.reopen(&behind).await;
    q.finish(
        x.id,
        x.attempts,
        &tok(&x),
        failed(FailureKind::InvalidInput),
    )
    .await
    .unwrap();
    let ended = q.get(x.id).await.unwrap();
    assert_eq!(ended.state.name(), "failed");
    assert!(ended.updated_ms < 10_000, "written by the clock behind");
    // The parent's worker polls through the orchestrator ahead: the part failed, and stays so.
    drop(q);
    let q = b.reopen(&ahead).await;
    let polled = q
        .submit_parts(p.id, p.attempts, &tp, asked())
        .await
        .unwrap();
    assert_eq!(polled[0].id, x.id);
    assert_eq!(
        polled[0].state.name(),
        "failed",
        "a part that failed under this attempt of its parent was queued again"
    );
    assert_eq!(q.get(x.id).await.unwrap().state.name(), "failed");
    // The parent's next attempt asks again, and the part runs again.
    q.cancel(p.id).await.unwrap();
    q.retry(p.id).await.unwrap();
    let p2 = q.lease("coordinator", false).await.unwrap().job.unwrap();
    assert_eq!((p2.id, p2.attempts), (p.id, 2));
    let polled = q
        .submit_parts(p2.id, p2.attempts, &tok(&p2), asked())
        .await
        .unwrap();
    assert_eq!(polled[0].state.name(), "queued");
    assert_eq!(polled[0].asked_by_attempt, 2);
}

/// A lease is held by its token alone: the right job and attempt with no token, another
/// lease's, a zeroed, a shortened, a lengthened or a changed one are refused as not the
/// holder on every change on a lease (heartbeat, outcome, adding parts, a part's result) and
/// change nothing; every lease draws its own; a restart (or another orchestrator) knows them.
async fn a_lease_is_held_only_with_its_token(b: &mut dyn Backend) {
    let clock = TestClock::default();
    let q = b.open(&clock).await;
    let parent = q.submit(bricked(1), None).await.unwrap().job;
    q.submit(spec(2), None).await.unwrap();
    let p = q.lease("coordinator", false).await.unwrap().job.unwrap();
    assert_eq!(p.id, parent.id);
    let other = q.lease("other", false).await.unwrap().job.unwrap();
    let (tp, to) = (tok(&p), tok(&other));
    assert_eq!(tp.len(), 16);
    assert_ne!(tp, to, "each lease draws its own token");
    assert_ne!(tp, vec![0; 16]);
    let mut flipped = tp.clone();
    flipped[15] ^= 1;
    let wrong = [
        Vec::new(),
        vec![0; 16],
        to.clone(),
        tp[..15].to_vec(),
        [tp.clone(), vec![0]].concat(),
        flipped,
    ];
    for w in &wrong {
        let e = q
            .heartbeat(p.id, p.attempts, w, 0.9, "stolen")
            .await
            .unwrap_err();
        assert!(not_holder(&e), "{e}");
        let e = q
            .finish(p.id, p.attempts, w, delivered())
            .await
            .unwrap_err();
        assert!(not_holder(&e), "{e}");
        let e = q
            .finish(p.id, p.attempts, w, failed(FailureKind::InvalidInput))
            .await
            .unwrap_err();
        assert!(not_holder(&e), "{e}");
        let e = q
            .submit_parts(p.id, p.attempts, w, vec![part_of(p.id, 1, 0)])
            .await
            .unwrap_err();
        assert!(not_holder(&e), "{e}");
    }
    assert_eq!(q.get(p.id).await.unwrap(), p, "refused: nothing changed");
    assert_eq!(q.list().await.unwrap().len(), 2, "no part added");
    // The holder adds a part; the part's lease is held by its own token.
    let parts = q
        .submit_parts(p.id, p.attempts, &tp, vec![part_of(p.id, 1, 0)])
        .await
        .unwrap();
    let x = q.lease("w", true).await.unwrap().job.unwrap();
    assert_eq!(x.id, parts[0].id);
    let tx = tok(&x);
    for w in [&tp, &Vec::new()] {
        let e = q
            .put_result(p.id, x.id, x.attempts, w, vec![1, 2])
            .await
            .unwrap_err();
        assert!(not_holder(&e), "{e}");
    }
    assert_eq!(q.result(p.id, x.id).await.unwrap(), None);
    assert_eq!(q.get(x.id).await.unwrap(), x);
    q.put_result(p.id, x.id, x.attempts, &tx, vec![1, 2])
        .await
        .unwrap();
    q.heartbeat(p.id, p.attempts, &tp, 0.5, "parts")
        .await
        .unwrap();
    // After a restart (or at another orchestrator) every lease's token is what it was. The
    // store keeps each token's digest, never its secret.
    drop(q);
    let q = b.reopen(&clock).await;
    let rest = b.at_rest();
    let holds = |needle: &[u8]| rest.windows(needle.len()).any(|w| w == needle);
    for (job, secret) in [(&p, &tp), (&other, &to), (&x, &tx)] {
        let hex = wavesplat_net::digest::hex(secret);
        assert!(
            !holds(secret) && !holds(hex.as_bytes()),
            "job {}'s secret is stored",
            job.id
        );
        let digest = wavesplat_net::digest::hex(&wavesplat_net::digest::sha256(secret));
        assert!(
            holds(digest.as_bytes()),
            "job {}'s digest is not stored",
            job.id
        );
        let read = q.get(job.id).await.unwrap();
        let stored = read.state.lease_token().expect("running");
        assert_eq!(stored.secret(), None);
        assert!(stored.matches(secret));
    }
    let e = q
        .heartbeat(other.id, other.attempts, &tp, 0.1, "s")
        .await
        .unwrap_err();
    assert!(not_holder(&e), "{e}");
    q.heartbeat(other.id, other.attempts, &to, 0.1, "s")
        .await
        .unwrap();
    q.finish(x.id, x.attempts, &tx, delivered()).await.unwrap();
    q.finish(other.id, other.attempts, &to, delivered())
        .await
        .unwrap();
}

/// Cancelling a bricked job cancels its queued and running parts and drops their results in
/// the same step (a done part stays done, its result gone); the parent's worker adds no part
/// after it, the part's worker stores no result; retried, the parent's next attempt (with a new
/// token) adds the same parts again and every one runs again; once it lands, their results go.
async fn cancelling_a_parent_settles_its_parts_and_a_retry_runs_them_again(b: &mut dyn Backend) {
    let clock = TestClock::default();
    clock.set(1000);
    let q = b.open(&clock).await;
    let parent = q.submit(bricked(1), None).await.unwrap().job;
    let p = q.lease("coordinator", false).await.unwrap().job.unwrap();
    let tp = tok(&p);
    let specs = |n: u32| (0..n).map(|i| part_of(parent.id, 1, i)).collect::<Vec<_>>();
    let parts = q
        .submit_parts(p.id, p.attempts, &tp, specs(3))
        .await
        .unwrap();
    assert!(parts.iter().all(|j| j.state.name() == "queued"));
    let ids: Vec<u64> = parts.iter().map(|j| j.id).collect();
    let done = q.lease("w1", true).await.unwrap().job.unwrap();
    let td = tok(&done);
    q.put_result(parent.id, done.id, done.attempts, &td, vec![5; 4])
        .await
        .unwrap();
    q.finish(done.id, done.attempts, &td, delivered())
        .await
        .unwrap();
    let running = q.lease("w2", true).await.unwrap().job.unwrap();
    let tr = tok(&running);
    assert_eq!(
        q.cancel(parent.id).await.unwrap().state,
        JobState::Cancelled
    );
    let states = |jobs: Vec<Job>| jobs.iter().map(|j| j.state.name()).collect::<Vec<_>>();
    let now_parts = parts_of(q.list().await.unwrap(), parent.id);
    assert_eq!(states(now_parts), ["done", "cancelled", "cancelled"]);
    assert_eq!(
        q.result(parent.id, done.id).await.unwrap(),
        None,
        "dropped with the parent"
    );
    let e = q
        .put_result(parent.id, running.id, running.attempts, &tr, vec![1])
        .await
        .unwrap_err();
    assert!(lease_lost(&e), "{e}");
    assert_eq!(q.result(parent.id, running.id).await.unwrap(), None);
    let e = q
        .heartbeat(running.id, running.attempts, &tr, 0.5, "s")
        .await
        .unwrap_err();
    assert!(lease_lost(&e), "{e}");
    let e = q
        .submit_parts(p.id, p.attempts, &tp, specs(4))
        .await
        .unwrap_err();
    assert!(lease_lost(&e), "{e}");
    assert_eq!(
        q.list().await.unwrap().len(),
        4,
        "no part added after the cancel"
    );
    assert!(q.lease("any", false).await.unwrap().job.is_none());

    // A part is not retried alone: its parent's retry runs it again.
    let e = q.retry(running.id).await.unwrap_err();
    assert!(matches!(e, OrchestratorError::InvalidRequest(_)), "{e}");

    clock.set(2000);
    q.retry(parent.id).await.unwrap();
    let p2 = q.lease("coordinator", false).await.unwrap().job.unwrap();
    assert_eq!((p2.id, p2.attempts), (parent.id, 2));
    let tp2 = tok(&p2);
    assert_ne!(tp2, tp, "a new lease, a new token");
    let e = q
        .submit_parts(p2.id, p2.attempts, &tp, specs(3))
        .await
        .unwrap_err();
    assert!(not_holder(&e), "{e}");
    let again = q
        .submit_parts(p2.id, p2.attempts, &tp2, specs(3))
        .await
        .unwrap();
    assert_eq!(again.iter().map(|j| j.id).collect::<Vec<_>>(), ids);
    assert_eq!(states(again), ["queued", "queued", "queued"]);
    let mut ran = Vec::new();
    while let Some(j) = q.lease("w", true).await.unwrap().job {
        let t = tok(&j);
        q.put_result(parent.id, j.id, j.attempts, &t, vec![j.id as u8])
            .await
            .unwrap();
        q.finish(j.id, j.attempts, &t, delivered()).await.unwrap();
        ran.push(j.id);
    }
    ran.sort_unstable();
    assert_eq!(ran, ids, "every part ran again");
    let polled = q
        .submit_parts(p2.id, p2.attempts, &tp2, specs(3))
        .await
        .unwrap();
    assert_eq!(states(polled), ["done", "done", "done"]);
    for &id in &ids {
        assert_eq!(q.result(parent.id, id).await.unwrap(), Some(vec![id as u8]));
    }
    q.finish(p2.id, p2.attempts, &tp2, delivered())
        .await
        .unwrap();
    for &id in &ids {
        assert_eq!(
            q.result(parent.id, id).await.unwrap(),
            None,
            "the landed job's parts' results go"
        );
    }
    drop(q);
    let q = b.reopen(&clock).await;
    assert_eq!(
        states(parts_of(q.list().await.unwrap(), parent.id)),
        ["done", "done", "done"]
    );
    assert_eq!(q.result(parent.id, ids[0]).await.unwrap(), None);
}

/// A bricked job that fails for good, by its worker's outcome or by its last lease lapsing,
/// cancels its live parts and drops its parts' results in that step; a lapse it is retried
/// after keeps them for its next attempt.
async fn a_parent_that_fails_drops_its_parts_results(b: &mut dyn Backend) {
    let clock = TestClock::default();
    let q = b.open(&clock).await;
    let a = q.submit(bricked(1), None).await.unwrap().job;
    let pa = q.lease("coordinator", false).await.unwrap().job.unwrap();
    let specs = |parent: u64, n: u32| vec![part_of(parent, n, 0), part_of(parent, n, 1)];
    let parts = q
        .submit_parts(a.id, pa.attempts, &tok(&pa), specs(a.id, 1))
        .await
        .unwrap();
    let x = q.lease("w", true).await.unwrap().job.unwrap();
    q.put_result(a.id, x.id, x.attempts, &tok(&x), vec![1; 8])
        .await
        .unwrap();
    q.finish(x.id, x.attempts, &tok(&x), delivered())
        .await
        .unwrap();
    let ended = q
        .finish(
            pa.id,
            pa.attempts,
            &tok(&pa),
            failed(FailureKind::InvalidInput),
        )
        .await
        .unwrap();
    assert_eq!(ended.state.name(), "failed");
    assert_eq!(q.result(a.id, x.id).await.unwrap(), None);
    assert_eq!(q.get(parts[1].id).await.unwrap().state, JobState::Cancelled);

    let c = q.submit(bricked(3), None).await.unwrap().job;
    let mut now = 0;
    let pc = q.lease("coordinator", false).await.unwrap().job.unwrap();
    assert_eq!(pc.id, c.id);
    let parts = q
        .submit_parts(c.id, pc.attempts, &tok(&pc), specs(c.id, 3))
        .await
        .unwrap();
    let y = q.lease("w", true).await.unwrap().job.unwrap();
    q.put_result(c.id, y.id, y.attempts, &tok(&y), vec![2; 8])
        .await
        .unwrap();
    q.finish(y.id, y.attempts, &tok(&y), delivered())
        .await
        .unwrap();
    for attempt in 1..=3 {
        now += 1000;
        clock.set(now);
        assert_eq!(q.reap().await.unwrap(), 1, "the parent alone lapsed");
        match q.get(c.id).await.unwrap().state {
            JobState::Queued { not_before_ms } => {
                assert!(attempt < 3);
                assert_eq!(
                    q.result(c.id, y.id).await.unwrap(),
                    Some(vec![2; 8]),
                    "kept for the next attempt"
                );
                assert_eq!(q.get(parts[1].id).await.unwrap().state.name(), "queued");
                now = not_before_ms;
                clock.set(now);
                let again = q.lease("coordinator", false).await.unwrap().job.unwrap();
                assert_eq!(again.id, c.id);
            }
            JobState::Failed(f) => {
                assert_eq!(attempt, 3, "{}", f.message);
            }
            s => panic!("{s:?}"),
        }
    }
    assert_eq!(q.result(c.id, y.id).await.unwrap(), None);
    assert_eq!(q.get(parts[1].id).await.unwrap().state, JobState::Cancelled);
    assert!(q.lease("any", true).await.unwrap().job.is_none());
}

/// Cancelling a bricked job while its worker adds parts at once (over every store): whatever
/// was added before the cancel is cancelled with it, nothing is added after it, and no part of
/// the job is left to run.
async fn cancel_racing_submit_parts_leaves_no_live_part(b: &mut dyn Backend, stores: usize) {
    let clock = TestClock::default();
    let mut qs = vec![b.open(&clock).await];
    for _ in 1..stores {
        qs.push(b.reopen(&clock).await);
    }
    // Parts added before their job's cancel, over every round (the race is run, not won by
    // the cancel every time).
    let mut added = 0;
    for round in 0..12u32 {
        let n = 10 + round;
        let parent = qs[0].submit(bricked(n), None).await.unwrap().job.id;
        let p = qs[0]
            .lease("coordinator", false)
            .await
            .unwrap()
            .job
            .unwrap();
        assert_eq!(p.id, parent);
        let (attempt, token) = (p.attempts, tok(&p));
        let mut adders = Vec::new();
        for w in 0..4u32 {
            let (q, token) = (qs[w as usize % qs.len()].clone(), token.clone());
            adders.push(tokio::spawn(async move {
                // Calls of eight parts each (the last one known already): a call whose lease
                // was checked before the cancel must still add none after it.
                for call in 0..4u32 {
                    let first = w * 28 + call * 7;
                    let mut specs: Vec<JobSpec> =
                        (first..first + 7).map(|i| part_of(parent, n, i)).collect();
                    specs.push(part_of(parent, n, 120 + w));
                    match q.submit_parts(parent, attempt, &token, specs).await {
                        Ok(_) => {}
                        Err(e) => {
                            assert!(lease_lost(&e), "{e}");
                            return;
                        }
                    }
                }
            }));
        }
        let canceller = qs[qs.len() - 1].clone();
        let cancel = tokio::spawn(async move {
            tokio::task::yield_now().await;
            canceller.cancel(parent).await.unwrap()
        });
        for a in adders {
            a.await.unwrap();
        }
        assert_eq!(cancel.await.unwrap().state, JobState::Cancelled);
        let live: Vec<u64> = parts_of(qs[0].list().await.unwrap(), parent)
            .into_iter()
            .filter(|j| !j.state.is_terminal())
            .map(|j| j.id)
            .collect();
        assert!(
            live.is_empty(),
            "round {round}: parts {live:?} live after their job was cancelled"
        );
        added += parts_of(qs[0].list().await.unwrap(), parent).len();
    }
    assert!(added > 0, "no part was added before a cancel in 12 rounds");
    assert!(qs[0].lease("late", true).await.unwrap().job.is_none());
}

async fn contract(b: &mut dyn Backend, stores: usize) {
    a_part_goes_first_to_the_worker_it_prefers(b).await;
    parts_lease_apart_and_their_results_live_until_dropped(b).await;
    submit_deduplicates_by_content_options_and_name(b).await;
    pages_read_from_the_store_are_slices_of_the_whole_list(b).await;
    leases_are_fifo_and_exclusive_across_stores(b, stores).await;
    failures_back_off_retry_and_stop(b).await;
    uploads_live_until_no_unfinished_job_needs_them(b).await;
    a_second_store_sees_every_acknowledged_change(b).await;
    many_workers_finish_an_archive(b, stores).await;
    a_lease_is_held_only_with_its_token(b).await;
    a_part_ended_under_its_parents_attempt_stays_ended_whatever_the_clocks(b).await;
    cancelling_a_parent_settles_its_parts_and_a_retry_runs_them_again(b).await;
    a_parent_that_fails_drops_its_parts_results(b).await;
    cancel_racing_submit_parts_leaves_no_live_part(b, stores).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn the_embedded_store_keeps_the_contract() {
    let mut b = Embedded {
        dirs: Vec::new(),
        last: None,
    };
    contract(&mut b, 1).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn the_postgres_store_keeps_the_contract_with_two_orchestrators() {
    let mut b = Postgres {
        server: PostgresServer::start().unwrap(),
        databases: 0,
    };
    contract(&mut b, 2).await;
    an_expired_lease_is_reclaimed_and_the_stale_worker_refused(&mut b).await;

    // A refused change leaves no transaction open: a dropped one keeps its row locked until
    // sqlx rolls it back in the background, and a lease right after skips the locked job.
    let clock = TestClock::default();
    let q = b.open(&clock).await;
    let other = b.reopen(&clock).await;
    q.submit(spec(1), None).await.unwrap();
    for round in 0..12 {
        assert!(q.retry(1).await.is_err(), "a queued job cannot be retried");
        let leased = other.lease("w", false).await.unwrap().job;
        assert_eq!(
            leased.map(|j| j.id),
            Some(1),
            "round {round}: the job was skipped"
        );
        other.cancel(1).await.unwrap();
        other.retry(1).await.unwrap();
    }
}

/// A database written before tokens were stored as digests (schema version 4: a running
/// lease's secret itself in `lease_token`) has them hashed by the next orchestrator to start,
/// and the lease's holder goes on with the secret it has.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_lease_token_stored_by_an_older_build_is_hashed_at_start_and_still_held() {
    let mut b = Postgres {
        server: PostgresServer::start().unwrap(),
        databases: 0,
    };
    let clock = TestClock::default();
    let q = b.open(&clock).await;
    let job = q.submit(spec(1), None).await.unwrap().job;
    let leased = q.lease("w", false).await.unwrap().job.unwrap();
    let secret = tok(&leased);
    drop(q);
    let db = format!("contract{}", b.databases);
    let hex = wavesplat_net::digest::hex(&secret);
    b.server
        .psql(
            &db,
            &format!(
                "UPDATE jobs SET lease_token = decode('{hex}', 'hex') WHERE id = {}; \
                 DELETE FROM _sqlx_migrations WHERE version = 5",
                job.id
            ),
        )
        .unwrap();
    let holds =
        |rest: &[u8], needle: &str| rest.windows(needle.len()).any(|w| w == needle.as_bytes());
    assert!(
        holds(&b.at_rest(), &hex),
        "the older build's form is in place"
    );
    let q = b.reopen(&clock).await;
    let rest = b.at_rest();
    let digest = wavesplat_net::digest::hex(&wavesplat_net::digest::sha256(&secret));
    assert!(!holds(&rest, &hex) && holds(&rest, &digest));
    q.heartbeat(job.id, leased.attempts, &secret, 0.5, "s")
        .await
        .unwrap();
    let mut wrong = secret.clone();
    wrong[0] ^= 1;
    let e = q
        .heartbeat(job.id, leased.attempts, &wrong, 0.5, "s")
        .await
        .unwrap_err();
    assert!(matches!(e, OrchestratorError::NotLeaseHolder { .. }), "{e}");
    q.finish(job.id, leased.attempts, &secret, delivered())
        .await
        .unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_embedded_lease_lapses_and_is_reclaimed() {
    // The embedded store has one owner: "another orchestrator" is the same store here.
    struct Same(Embedded);
    #[tonic::async_trait]
    impl Backend for Same {
        async fn open(&mut self, clock: &TestClock) -> Arc<dyn JobStore> {
            self.0.open(clock).await
        }
        async fn reopen(&mut self, _clock: &TestClock) -> Arc<dyn JobStore> {
            self.0.last.clone().unwrap()
        }
        fn at_rest(&self) -> Vec<u8> {
            self.0.at_rest()
        }
    }
    let mut b = Same(Embedded {
        dirs: Vec::new(),
        last: None,
    });
    an_expired_lease_is_reclaimed_and_the_stale_worker_refused(&mut b).await;
}

/// Starting against a database that is not there fails with a message naming it, and a
/// malformed URL is refused before connecting.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_queue_urls_are_clear_errors() {
    let server = PostgresServer::start().unwrap();
    let e = PostgresQueue::connect(&server.url_with_password("nosuchdb"), Default::default())
        .await
        .unwrap_err()
        .to_string();
    assert!(e.contains("nosuchdb"), "{e}");
    assert!(
        !e.contains(wavesplat_harness::postgres::PASSWORD),
        "password leaked: {e}"
    );
    let e = PostgresQueue::connect("postgres://[::1", Default::default())
        .await
        .unwrap_err()
        .to_string();
    assert!(e.contains("queue URL"), "{e}");
    let wrong = format!(
        "postgres://postgres:wrong@127.0.0.1:{}/postgres",
        server.port()
    );
    let e = PostgresQueue::connect(&wrong, Default::default())
        .await
        .unwrap_err()
        .to_string();
    assert!(e.contains("password"), "{e}");
    assert!(!e.contains("wrong@"), "password leaked: {e}");
}

/// A CA and a certificate for `localhost` in `dir`; returns (CA file, cert, key).
fn test_pki(dir: &std::path::Path) -> (std::path::PathBuf, std::path::PathBuf, std::path::PathBuf) {
    let ca = common::pki::pki(&[("localhost", "127.0.0.1".into(), dir)]);
    std::fs::write(dir.join("ca.pem"), ca).unwrap();
    (
        dir.join("ca.pem"),
        dir.join("localhost.crt"),
        dir.join("localhost.key"),
    )
}

/// With `sslmode=verify-full` the queue talks to the database over TLS and checks its
/// certificate: the right CA connects, another CA is refused, and a server that takes only TLS
/// refuses a plaintext connection.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tls_to_the_database_is_verified() {
    let dir = tempfile::tempdir().unwrap();
    let (ca, cert, key) = test_pki(dir.path());
    let other = tempfile::tempdir().unwrap();
    let (other_ca, _, _) = test_pki(other.path());
    let server = PostgresServer::start_with(wavesplat_harness::postgres::PostgresSetup {
        tls: Some((cert, key)),
        ..Default::default()
    })
    .unwrap();
    server.create_database("tls").unwrap();
    let password = wavesplat_harness::postgres::PASSWORD;
    let url = |mode: &str, ca: &std::path::Path| {
        format!(
            "postgres://postgres:{password}@localhost:{}/tls?sslmode={mode}&sslrootcert={}",
            server.port(),
            ca.display()
        )
    };
    let q = PostgresQueue::connect(&url("verify-full", &ca), Default::default())
        .await
        .unwrap();
    q.submit(spec(1), None).await.unwrap();
    assert_eq!(q.list().await.unwrap().len(), 1);
    let e = PostgresQueue::connect(&url("verify-full", &other_ca), Default::default())
        .await
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("certificate") || e.contains("Certificate"),
        "{e}"
    );
    let e = PostgresQueue::connect(&url("disable", &ca), Default::default())
        .await
        .unwrap_err()
        .to_string();
    assert!(e.contains("no encryption") || e.contains("pg_hba"), "{e}");
}
