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
    Delivery, Failure, FailureKind, JobOptions, JobSpec, JobState, Outcome, Source,
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
}

fn lease_lost(e: &OrchestratorError) -> bool {
    matches!(e, OrchestratorError::LeaseLost { .. })
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
    other.heartbeat(job.id, 1, 0.5, "transform").await.unwrap();
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
    let e = q.heartbeat(job.id, 1, 0.9, "x").await.unwrap_err();
    assert!(lease_lost(&e), "{e}");
    let e = q.finish(job.id, 1, delivered()).await.unwrap_err();
    assert!(lease_lost(&e), "{e}");
    clock.set(2010);
    let done = other.finish(job.id, 2, delivered()).await.unwrap();
    assert!(matches!(done.state, JobState::Done { run_ms: 10, .. }));
    // A finished lease cannot be finished again (a duplicate report after a retry).
    let e = q.finish(job.id, 2, delivered()).await.unwrap_err();
    assert!(lease_lost(&e), "{e}");
}

async fn failures_back_off_retry_and_stop(b: &mut dyn Backend) {
    let clock = TestClock::default();
    let q = b.open(&clock).await;
    q.submit(spec(1), None).await.unwrap();
    q.submit(spec(2), None).await.unwrap();
    let mut now = 0;
    for attempt in 1..=3 {
        clock.set(now);
        let j = q.lease("w", false).await.unwrap().job.unwrap();
        assert_eq!((j.id, j.attempts), (1, attempt));
        let j = q
            .finish(1, attempt, failed(FailureKind::CacheUnavailable))
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
            q.finish(2, 1, failed(FailureKind::InvalidInput))
                .await
                .unwrap();
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
    let e = q.heartbeat(2, 1, 0.1, "s").await.unwrap_err();
    assert!(lease_lost(&e), "{e}");
    let e = q.finish(2, 1, delivered()).await.unwrap_err();
    assert!(lease_lost(&e), "{e}");
    q.heartbeat(2, 2, 0.1, "s").await.unwrap();
    q.cancel(2).await.unwrap();
    let e = q.heartbeat(2, 2, 0.1, "s").await.unwrap_err();
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
    q.finish(a.id, 1, delivered()).await.unwrap();
    assert!(
        q.upload(&[1; 32]).await.unwrap().is_some(),
        "b still needs it"
    );
    let b2 = q.lease("w", false).await.unwrap().job.unwrap();
    q.finish(b2.id, 1, delivered()).await.unwrap();
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
    q.finish(j.id, 1, delivered()).await.unwrap();
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
                q.heartbeat(j.id, j.attempts, 0.5, "half").await.unwrap();
                q.finish(j.id, j.attempts, delivered()).await.unwrap();
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
    q.put_result(parent.id, p0.id, 1, vec![1; 10])
        .await
        .unwrap();
    q.put_result(parent.id, p0.id, 1, vec![2; 3]).await.unwrap();
    q.put_result(parent.id + 100, p1.id, 1, vec![9])
        .await
        .unwrap();
    let big: Vec<u8> = (0..(3 << 20) + 5).map(|i| (i % 253) as u8).collect();
    q.put_result(parent.id, p1.id, 1, big.clone())
        .await
        .unwrap();
    assert_eq!(q.result(parent.id, p0.id).await.unwrap(), Some(vec![2; 3]));
    // Only the attempt holding the part's live lease stores a result: not another attempt,
    // not once the part is done (a stale worker cannot replace the finished part's result).
    let e = q
        .put_result(parent.id, p0.id, 2, vec![7])
        .await
        .unwrap_err();
    assert!(lease_lost(&e), "{e}");
    q.finish(p0.id, 1, delivered()).await.unwrap();
    let e = q
        .put_result(parent.id, p0.id, 1, vec![7])
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
    let done = q.finish(w1.id, w1.attempts, delivered()).await.unwrap();
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

async fn contract(b: &mut dyn Backend, stores: usize) {
    a_part_goes_first_to_the_worker_it_prefers(b).await;
    parts_lease_apart_and_their_results_live_until_dropped(b).await;
    submit_deduplicates_by_content_options_and_name(b).await;
    leases_are_fifo_and_exclusive_across_stores(b, stores).await;
    failures_back_off_retry_and_stop(b).await;
    uploads_live_until_no_unfinished_job_needs_them(b).await;
    a_second_store_sees_every_acknowledged_change(b).await;
    many_workers_finish_an_archive(b, stores).await;
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
