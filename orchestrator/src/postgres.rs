//! The queue in PostgreSQL: the [`JobStore`] contract over a database that any number of
//! stateless orchestrators share. Each change is one transaction that locks the rows it
//! changes (`SELECT … FOR UPDATE`; leases and reaping with `SKIP LOCKED`, so orchestrators
//! never wait on each other's rows), applies the same [`rules`] as the embedded store, and
//! commits before the RPC is answered. A job with parts and its parts are locked parent
//! first, in every transaction that touches both (adding parts, ending the parent: cancelling
//! its live parts and dropping their results). A running lease's token is the `lease_token`
//! column (the SHA-256 of its secret), never part of the `job` record. Uploaded sources are rows of the `uploads` table.
//! The schema is created and upgraded at start by versioned migrations (`migrations/`, run
//! under sqlx's advisory lock, so orchestrators starting together apply each once).
//!
//! sqlx rather than tokio-postgres: its connection options read the URL, `PGPASSWORD`, the
//! other `PG*` variables and `.pgpass` the way libpq does, speak TLS through rustls when the
//! URL's `sslmode` asks for it, come with a pool that reconnects after the database
//! restarts, and carry the migration runner, so none of that is written here.

use crate::error::OrchestratorError;
use crate::jobstore::{JobStore, Leased, StateCounts};
use crate::model::{Job, JobId, JobSpec, JobState, LeaseToken, Outcome, Source};
use crate::queue::{new_lease_token, rules, system_clock, Clock, QueueOptions, Submitted};
use sqlx::migrate::{Migration, MigrationSource, MigrationType, Migrator};
use sqlx::postgres::{PgConnectOptions, PgPool, PgPoolOptions};
use sqlx::types::Json;
use sqlx::{Postgres, Row, Transaction};
use std::borrow::Cow;
use std::collections::HashSet;
use std::future::Future;
use std::pin::Pin;
use std::str::FromStr;
use std::time::Duration;

/// Rows of one uploaded source hold at most this many bytes.
const UPLOAD_CHUNK: usize = 1 << 20;

/// How the orchestrator connects to the database.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PostgresOptions {
    /// Connections in the pool.
    pub max_connections: u32,
    /// Longest wait for a connection before a request fails as unavailable.
    pub acquire_timeout: Duration,
}

impl Default for PostgresOptions {
    fn default() -> Self {
        PostgresOptions {
            max_connections: 16,
            acquire_timeout: Duration::from_secs(5),
        }
    }
}

/// The schema's versions, applied in order at start.
#[derive(Debug)]
struct Migrations;

type Resolved<'s> =
    Pin<Box<dyn Future<Output = Result<Vec<Migration>, sqlx::error::BoxDynError>> + Send + 's>>;

impl<'s> MigrationSource<'s> for Migrations {
    fn resolve(self) -> Resolved<'s> {
        Box::pin(async {
            Ok(vec![
                Migration::new(
                    1,
                    Cow::Borrowed("jobs and uploads"),
                    MigrationType::Simple,
                    Cow::Borrowed(include_str!("../migrations/0001_jobs.sql")),
                    false,
                ),
                Migration::new(
                    2,
                    Cow::Borrowed("results of bricked jobs' parts"),
                    MigrationType::Simple,
                    Cow::Borrowed(include_str!("../migrations/0002_results.sql")),
                    false,
                ),
                Migration::new(
                    3,
                    Cow::Borrowed("queued parts by their preferred worker"),
                    MigrationType::Simple,
                    Cow::Borrowed(include_str!("../migrations/0003_preferred_parts.sql")),
                    false,
                ),
                Migration::new(
                    4,
                    Cow::Borrowed("lease tokens, and parts by their parent"),
                    MigrationType::Simple,
                    Cow::Borrowed(include_str!("../migrations/0004_lease_tokens.sql")),
                    false,
                ),
                Migration::new(
                    5,
                    Cow::Borrowed("lease tokens stored as their digests"),
                    MigrationType::Simple,
                    Cow::Borrowed(include_str!("../migrations/0005_lease_token_digests.sql")),
                    false,
                ),
            ])
        })
    }
}

/// The queue in a PostgreSQL database.
#[derive(Clone)]
pub struct PostgresQueue {
    pool: PgPool,
    options: QueueOptions,
    clock: Clock,
}

impl std::fmt::Debug for PostgresQueue {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PostgresQueue")
            .field("options", &self.options)
            .finish_non_exhaustive()
    }
}

fn db(e: sqlx::Error) -> OrchestratorError {
    OrchestratorError::Database(e.to_string())
}

fn ms(v: u64) -> i64 {
    i64::try_from(v).unwrap_or(i64::MAX)
}

/// Commits `tx` when `result` is a success, else rolls it back at once (dropped, sqlx would
/// roll it back only when the pool next hands out the connection, and until then its rows stay
/// locked and every lease skips them).
async fn end<T>(
    tx: Transaction<'static, Postgres>,
    result: Result<T, OrchestratorError>,
) -> Result<T, OrchestratorError> {
    match result {
        Ok(v) => {
            tx.commit().await.map_err(db)?;
            Ok(v)
        }
        Err(e) => {
            let _ = tx.rollback().await;
            Err(e)
        }
    }
}

impl PostgresQueue {
    /// Connects to the database at `url` (`postgres://user@host:port/db?sslmode=require`;
    /// a password from the URL, `PGPASSWORD` or `.pgpass`), applies the schema's migrations and
    /// warns when this host's clock and the database's differ by more than a quarter lease
    /// (lease expiry compares times written by different orchestrators).
    pub async fn connect(
        url: &str,
        options: PostgresOptions,
    ) -> Result<PostgresQueue, OrchestratorError> {
        let connect = PgConnectOptions::from_str(url).map_err(|e| {
            OrchestratorError::InvalidRequest(format!("queue URL {}: {e}", redact(url)))
        })?;
        // One connection first: the pool retries until its timeout and then reports only
        // that it timed out, hiding the cause (refused, unknown host, TLS, password).
        let probe = sqlx::ConnectOptions::connect(&connect).await.map_err(|e| {
            OrchestratorError::Database(format!("connecting to {}: {e}", redact(url)))
        })?;
        let _ = sqlx::Connection::close(probe).await;
        let pool = PgPoolOptions::new()
            .max_connections(options.max_connections.max(1))
            .acquire_timeout(options.acquire_timeout)
            .connect_with(connect)
            .await
            .map_err(|e| {
                OrchestratorError::Database(format!("connecting to {}: {e}", redact(url)))
            })?;
        let migrator = Migrator::new(Migrations)
            .await
            .map_err(|e| OrchestratorError::Database(format!("reading migrations: {e}")))?;
        migrator
            .run(&pool)
            .await
            .map_err(|e| OrchestratorError::Database(format!("migrating the schema: {e}")))?;
        let queue = PostgresQueue {
            pool,
            options: QueueOptions::default(),
            clock: system_clock(),
        };
        tracing::info!(url = %redact(url), "queue in PostgreSQL");
        Ok(queue)
    }

    /// The same database with the queue policy `options`.
    pub fn with_options(mut self, options: QueueOptions) -> PostgresQueue {
        self.options = options;
        self
    }

    /// The same database read against `clock` (tests drive time with it).
    pub fn with_clock(mut self, clock: Clock) -> PostgresQueue {
        self.clock = clock;
        self
    }

    /// This host's clock minus the database's, in ms.
    pub async fn clock_skew_ms(&self) -> Result<i64, OrchestratorError> {
        let before = (self.clock)();
        let row = sqlx::query("SELECT (extract(epoch FROM clock_timestamp()) * 1000)::int8")
            .fetch_one(&self.pool)
            .await
            .map_err(db)?;
        let after = (self.clock)();
        let theirs: i64 = row.try_get(0).map_err(db)?;
        Ok(ms((before + after) / 2) - theirs)
    }

    /// Warns when this host's clock is off the database's by more than a quarter lease.
    pub async fn check_clock(&self) -> Result<(), OrchestratorError> {
        let skew = self.clock_skew_ms().await?;
        if skew.unsigned_abs() > self.options.lease_ms / 4 {
            tracing::warn!(
                skew_ms = skew,
                lease_ms = self.options.lease_ms,
                "this host's clock is off the database's by more than a quarter lease: \
                 orchestrators over one database must keep their clocks in step (NTP)"
            );
        }
        Ok(())
    }

    fn now(&self) -> u64 {
        (self.clock)()
    }

    async fn begin(&self) -> Result<Transaction<'static, Postgres>, OrchestratorError> {
        self.pool.begin().await.map_err(db)
    }

    /// Writes `job` back to its row with every derived column; a running lease's token goes to
    /// its own column (`lease_token`, the secret's SHA-256: [`LeaseToken::stored`]), not into
    /// the `job` record.
    async fn write(
        tx: &mut Transaction<'static, Postgres>,
        job: &Job,
    ) -> Result<(), OrchestratorError> {
        let token = job.state.lease_token().map(|t| t.stored().to_vec());
        let record: Cow<'_, Job> = match token {
            None => Cow::Borrowed(job),
            Some(_) => {
                let mut j = job.clone();
                if let JobState::Running { lease_token, .. } = &mut j.state {
                    *lease_token = None;
                }
                Cow::Owned(j)
            }
        };
        let (not_before, lease_expires, worker) = match &job.state {
            JobState::Queued { not_before_ms } => (Some(ms(*not_before_ms)), None, None),
            JobState::Running {
                lease_expires_ms,
                worker,
                ..
            } => (None, Some(ms(*lease_expires_ms)), Some(worker.as_str())),
            _ => (None, None, None),
        };
        sqlx::query(
            "UPDATE jobs SET state = $2, not_before_ms = $3, lease_expires_ms = $4, worker = $5,
                 attempts = $6, error = $7, updated_ms = $8, job = $9, lease_token = $10
             WHERE id = $1",
        )
        .bind(ms(job.id))
        .bind(job.state.name())
        .bind(not_before)
        .bind(lease_expires)
        .bind(worker)
        .bind(i32::try_from(job.attempts).unwrap_or(i32::MAX))
        .bind(job.last_failure.as_ref().map(|f| f.message.as_str()))
        .bind(ms(job.updated_ms))
        .bind(Json(record.as_ref()))
        .bind(token)
        .execute(&mut **tx)
        .await
        .map_err(db)?;
        Ok(())
    }

    /// The job of a row selected with its `job` and `lease_token` columns.
    fn job_of(row: &sqlx::postgres::PgRow) -> Result<Job, OrchestratorError> {
        let corrupt = |e: sqlx::Error| OrchestratorError::Corrupt(format!("job record: {e}"));
        let Json(mut job): Json<Job> = row.try_get("job").map_err(corrupt)?;
        let token: Option<Vec<u8>> = row.try_get("lease_token").map_err(corrupt)?;
        if let JobState::Running { lease_token, .. } = &mut job.state {
            *lease_token = token.as_deref().and_then(LeaseToken::from_stored);
        }
        Ok(job)
    }

    /// Locks job `id` in `tx`.
    async fn locked(
        tx: &mut Transaction<'static, Postgres>,
        id: JobId,
    ) -> Result<Job, OrchestratorError> {
        let row = sqlx::query("SELECT job, lease_token FROM jobs WHERE id = $1 FOR UPDATE")
            .bind(ms(id))
            .fetch_optional(&mut **tx)
            .await
            .map_err(db)?
            .ok_or(OrchestratorError::NotFound(id))?;
        Self::job_of(&row)
    }

    /// Serialises changes to one uploaded source (storing it, dropping it) for the rest of
    /// `tx`.
    async fn lock_upload(
        tx: &mut Transaction<'static, Postgres>,
        sha256: &[u8; 32],
    ) -> Result<(), OrchestratorError> {
        let mut key = [0u8; 8];
        key.copy_from_slice(&sha256[..8]);
        sqlx::query("SELECT pg_advisory_xact_lock($1)")
            .bind(i64::from_be_bytes(key))
            .execute(&mut **tx)
            .await
            .map_err(db)?;
        Ok(())
    }

    /// Locks job `id`, applies `f` at the current time, writes it back with what ending it
    /// settles ([`PostgresQueue::settle`], a delivered upload's source) and commits: one
    /// transaction, rolled back whole when any step fails.
    async fn change(
        &self,
        id: JobId,
        f: impl FnOnce(&mut Job, u64) -> Result<(), OrchestratorError> + Send,
    ) -> Result<Job, OrchestratorError> {
        let mut tx = self.begin().await?;
        let clock = self.clock.clone();
        let t = &mut tx;
        let result = async move {
            let mut job = Self::locked(t, id).await?;
            // The time once the row is ours: a change that waited for the lock is judged (a
            // lease's expiry, its extension) at when it happens.
            let now = clock();
            f(&mut job, now)?;
            Self::write(t, &job).await?;
            Self::settle(t, &job, now).await?;
            if matches!(job.state, JobState::Done { .. })
                && matches!(job.spec.source, Source::Upload { .. })
            {
                Self::lock_upload(t, &job.spec.sha256).await?;
                sqlx::query(
                    "DELETE FROM uploads WHERE sha256 = $1 AND NOT EXISTS (
                         SELECT 1 FROM jobs
                         WHERE sha256 = $1 AND upload AND state <> 'done' AND id <> $2)",
                )
                .bind(&job.spec.sha256[..])
                .bind(ms(job.id))
                .execute(&mut **t)
                .await
                .map_err(db)?;
            }
            Ok(job)
        }
        .await;
        end(tx, result).await
    }

    /// If `parent` (locked and written in `tx`) has ended ([`rules::ends_parts`]): cancels its
    /// queued and running parts, locked parent first (as every transaction that touches a
    /// parent and its parts), and drops its parts' results, in `tx`.
    async fn settle(
        tx: &mut Transaction<'static, Postgres>,
        parent: &Job,
        now: u64,
    ) -> Result<(), OrchestratorError> {
        if !rules::ends_parts(parent) {
            return Ok(());
        }
        // By the index `jobs_parts`.
        let rows = sqlx::query(
            "SELECT job, lease_token FROM jobs
             WHERE job->'spec' ? 'part' AND (job->'spec'->'part'->>'parent')::bigint = $1
                 AND state IN ('queued', 'running')
             ORDER BY id FOR UPDATE",
        )
        .bind(ms(parent.id))
        .fetch_all(&mut **tx)
        .await
        .map_err(db)?;
        for row in rows {
            let mut part = Self::job_of(&row)?;
            if rules::settle_part(parent, &mut part, now) {
                Self::write(tx, &part).await?;
            }
        }
        sqlx::query("DELETE FROM results WHERE parent = $1")
            .bind(ms(parent.id))
            .execute(&mut **tx)
            .await
            .map_err(db)?;
        Ok(())
    }

    /// Inserts `spec` (validated, whose key is `key`) as a new job in `tx`, a part asked for
    /// by its parent's attempt `asked_by_attempt` (0 for a job that is no part); `None` when a
    /// job with that key was committed meanwhile.
    async fn insert_new(
        tx: &mut Transaction<'static, Postgres>,
        spec: JobSpec,
        key: &str,
        asked_by_attempt: u32,
        now: u64,
    ) -> Result<Option<Job>, OrchestratorError> {
        let id: i64 = sqlx::query("SELECT nextval(pg_get_serial_sequence('jobs', 'id'))")
            .fetch_one(&mut **tx)
            .await
            .and_then(|r| r.try_get(0))
            .map_err(db)?;
        let job = Job {
            asked_by_attempt,
            ..rules::new_job(id as u64, spec, now)
        };
        let inserted = sqlx::query(
            "INSERT INTO jobs (id, dedup_key, name, state, not_before_ms, attempts, sha256,
                               upload, created_ms, updated_ms, job)
             VALUES ($1, $2, $3, 'queued', $4, 0, $5, $6, $4, $4, $7)
             ON CONFLICT (dedup_key) DO NOTHING",
        )
        .bind(id)
        .bind(key)
        .bind(&job.spec.name)
        .bind(ms(now))
        .bind(&job.spec.sha256[..])
        .bind(matches!(job.spec.source, Source::Upload { .. }))
        .bind(Json(&job))
        .execute(&mut **tx)
        .await
        .map_err(db)?
        .rows_affected();
        Ok((inserted > 0).then_some(job))
    }

    /// [`JobStore::submit_parts`] in `tx`: the parent locked and its lease checked, then every
    /// spec, then the parts added or polled (locked in the order asked, after the parent).
    async fn add_parts(
        tx: &mut Transaction<'static, Postgres>,
        parent: JobId,
        attempt: u32,
        token: &[u8],
        specs: Vec<JobSpec>,
        now: u64,
    ) -> Result<Vec<Job>, OrchestratorError> {
        let holder = Self::locked(tx, parent).await?;
        rules::check_held(&holder, attempt, token, now)?;
        for spec in &specs {
            rules::check_part_of(&holder, spec)?;
        }
        let with_results: HashSet<i64> =
            sqlx::query_scalar("SELECT job_id FROM results WHERE parent = $1")
                .bind(ms(parent))
                .fetch_all(&mut **tx)
                .await
                .map_err(db)?
                .into_iter()
                .collect();
        let mut parts = Vec::with_capacity(specs.len());
        for spec in specs {
            let key = spec.dedup_key();
            // Read without a lock: a poll names every part, and locking them all would hide the
            // queued ones from leases (SKIP LOCKED) until it commits. Only a part that this
            // step changes is locked (each part once an attempt, when the attempt first asks
            // for it), and judged again under the lock, with whether its result is stored read
            // again too: its worker may have stored it and finished since.
            let known = sqlx::query("SELECT job, lease_token FROM jobs WHERE dedup_key = $1")
                .bind(&key)
                .fetch_optional(&mut **tx)
                .await
                .map_err(db)?;
            let job = match known {
                Some(row) => {
                    let mut job = Self::job_of(&row)?;
                    let has_result = with_results.contains(&ms(job.id));
                    if rules::ask_for_part(&mut job.clone(), attempt, has_result, now) {
                        job = Self::locked(tx, job.id).await?;
                        let has_result: bool = sqlx::query_scalar(
                            "SELECT EXISTS (SELECT 1 FROM results WHERE parent = $1 AND job_id = $2)",
                        )
                        .bind(ms(parent))
                        .bind(ms(job.id))
                        .fetch_one(&mut **tx)
                        .await
                        .map_err(db)?;
                        if rules::ask_for_part(&mut job, attempt, has_result, now) {
                            Self::write(tx, &job).await?;
                        }
                    }
                    job
                }
                // Parts are added only under their parent's lock: no other transaction adds
                // this one meanwhile.
                None => Self::insert_new(tx, spec, &key, attempt, now)
                    .await?
                    .ok_or_else(|| {
                        OrchestratorError::Database(format!("part {key} added twice at once"))
                    })?,
            };
            parts.push(job);
        }
        Ok(parts)
    }

    /// Reclaims job `id` in `tx` if its lease lapsed by `now` and no other transaction holds
    /// it; settles its parts if it failed for good. Returns whether it was reclaimed.
    async fn reap_one(
        tx: &mut Transaction<'static, Postgres>,
        options: &QueueOptions,
        id: i64,
        now: u64,
    ) -> Result<bool, OrchestratorError> {
        let row = sqlx::query(
            "SELECT job, lease_token FROM jobs
             WHERE id = $1 AND state = 'running' AND lease_expires_ms <= $2
             FOR UPDATE SKIP LOCKED",
        )
        .bind(id)
        .bind(ms(now))
        .fetch_optional(&mut **tx)
        .await
        .map_err(db)?;
        let Some(row) = row else {
            return Ok(false);
        };
        let mut job = Self::job_of(&row)?;
        if !rules::expire(options, &mut job, now) {
            return Ok(false);
        }
        Self::write(tx, &job).await?;
        Self::settle(tx, &job, now).await?;
        Ok(true)
    }

    async fn existing(
        tx: &mut Transaction<'static, Postgres>,
        key: &str,
    ) -> Result<Option<Job>, OrchestratorError> {
        sqlx::query("SELECT job, lease_token FROM jobs WHERE dedup_key = $1")
            .bind(key)
            .fetch_optional(&mut **tx)
            .await
            .map_err(db)?
            .map(|r| Self::job_of(&r))
            .transpose()
    }
}

/// The URL without its password (user info or a `password` query parameter), for messages and
/// logs.
fn redact(url: &str) -> String {
    let Ok(mut u) = url::Url::parse(url) else {
        return "(unparsable URL)".into();
    };
    if u.password().is_some() {
        let _ = u.set_password(Some("***"));
    }
    if u.query_pairs().any(|(k, _)| k == "password") {
        let pairs: Vec<(String, String)> = u
            .query_pairs()
            .map(|(k, v)| {
                let v = if k == "password" {
                    "***".into()
                } else {
                    v.into_owned()
                };
                (k.into_owned(), v)
            })
            .collect();
        u.query_pairs_mut().clear().extend_pairs(pairs);
    }
    u.to_string()
}

#[tonic::async_trait]
impl JobStore for PostgresQueue {
    fn options(&self) -> &QueueOptions {
        &self.options
    }

    async fn submit(
        &self,
        spec: JobSpec,
        upload: Option<Vec<u8>>,
    ) -> Result<Submitted, OrchestratorError> {
        let spec = spec.validate()?;
        let key = spec.dedup_key();
        let mut tx = self.begin().await?;
        if let Some(job) = Self::existing(&mut tx, &key).await? {
            tx.rollback().await.map_err(db)?;
            return Ok(Submitted { job, existed: true });
        }
        if let Some(bytes) = &upload {
            Self::lock_upload(&mut tx, &spec.sha256).await?;
            let chunks: Vec<&[u8]> = if bytes.is_empty() {
                vec![&[]]
            } else {
                bytes.chunks(UPLOAD_CHUNK).collect()
            };
            for (seq, chunk) in chunks.into_iter().enumerate() {
                sqlx::query(
                    "INSERT INTO uploads (sha256, seq, data) VALUES ($1, $2, $3)
                     ON CONFLICT (sha256, seq) DO NOTHING",
                )
                .bind(&spec.sha256[..])
                .bind(i32::try_from(seq).unwrap_or(i32::MAX))
                .bind(chunk)
                .execute(&mut *tx)
                .await
                .map_err(db)?;
            }
        }
        let now = self.now();
        let Some(job) = Self::insert_new(&mut tx, spec, &key, 0, now).await? else {
            // Another orchestrator committed the same job since we looked.
            tx.rollback().await.map_err(db)?;
            let mut tx = self.begin().await?;
            let job = Self::existing(&mut tx, &key).await?.ok_or_else(|| {
                OrchestratorError::Database(format!("job {key} vanished while submitting"))
            })?;
            tx.commit().await.map_err(db)?;
            return Ok(Submitted { job, existed: true });
        };
        tx.commit().await.map_err(db)?;
        Ok(Submitted {
            job,
            existed: false,
        })
    }

    async fn lease(&self, worker: &str, parts_only: bool) -> Result<Leased, OrchestratorError> {
        let token = new_lease_token()?;
        let now = self.now();
        let mut tx = self.begin().await?;
        // The oldest part that prefers this worker (`rules::preferred_worker`; by the index
        // `jobs_queued_preferring`), else the oldest runnable job (by `jobs_queued`).
        let preferred = sqlx::query(
            "SELECT job, lease_token FROM jobs WHERE state = 'queued' AND not_before_ms <= $1
                 AND job->'spec'->'part'->>'prefer_worker' = $2
             ORDER BY id LIMIT 1 FOR UPDATE SKIP LOCKED",
        )
        .bind(ms(now))
        .bind(worker)
        .fetch_optional(&mut *tx)
        .await
        .map_err(db)?;
        let row = match preferred {
            Some(row) => Some(row),
            None => sqlx::query(
                "SELECT job, lease_token FROM jobs WHERE state = 'queued' AND not_before_ms <= $1
                     AND (NOT $2 OR job->'spec' ? 'part')
                 ORDER BY id LIMIT 1 FOR UPDATE SKIP LOCKED",
            )
            .bind(ms(now))
            .bind(parts_only)
            .fetch_optional(&mut *tx)
            .await
            .map_err(db)?,
        };
        let job = match row {
            Some(row) => {
                let mut job = Self::job_of(&row)?;
                rules::start(&self.options, &mut job, worker, token, now);
                Self::write(&mut tx, &job).await?;
                Some(job)
            }
            None => None,
        };
        // Only an idle worker needs to know when the next backoff ends.
        let next: Option<i64> = if job.is_none() {
            sqlx::query("SELECT min(not_before_ms) FROM jobs WHERE state = 'queued'")
                .fetch_one(&mut *tx)
                .await
                .and_then(|r| r.try_get(0))
                .map_err(db)?
        } else {
            None
        };
        tx.commit().await.map_err(db)?;
        Ok(Leased {
            job,
            next_runnable_in: next.map(|t| (t.max(0) as u64).saturating_sub(now)),
        })
    }

    async fn heartbeat(
        &self,
        id: JobId,
        attempt: u32,
        token: &[u8],
        progress: f32,
        stage: &str,
    ) -> Result<Job, OrchestratorError> {
        let cfg = self.options;
        let stage = stage.to_string();
        self.change(id, move |job, now| {
            rules::heartbeat(&cfg, job, attempt, token, progress, &stage, now)
        })
        .await
    }

    async fn finish(
        &self,
        id: JobId,
        attempt: u32,
        token: &[u8],
        outcome: Outcome,
    ) -> Result<Job, OrchestratorError> {
        let cfg = self.options;
        self.change(id, move |job, now| {
            rules::finish(&cfg, job, attempt, token, outcome, now)
        })
        .await
    }

    async fn submit_parts(
        &self,
        parent: JobId,
        attempt: u32,
        token: &[u8],
        specs: Vec<JobSpec>,
    ) -> Result<Vec<Job>, OrchestratorError> {
        let specs = specs
            .into_iter()
            .map(|s| s.validate().map_err(OrchestratorError::from))
            .collect::<Result<Vec<JobSpec>, OrchestratorError>>()?;
        let now = self.now();
        let mut tx = self.begin().await?;
        let result = Self::add_parts(&mut tx, parent, attempt, token, specs, now).await;
        end(tx, result).await
    }

    async fn cancel(&self, id: JobId) -> Result<Job, OrchestratorError> {
        self.change(id, rules::cancel).await
    }

    async fn retry(&self, id: JobId) -> Result<Job, OrchestratorError> {
        self.change(id, rules::retry).await
    }

    async fn reap(&self) -> Result<usize, OrchestratorError> {
        let now = self.now();
        // One transaction per lapsed lease: a parent that fails for good locks its parts
        // after itself, as cancelling it does, and never while holding another job's row.
        let ids: Vec<i64> = sqlx::query_scalar(
            "SELECT id FROM jobs WHERE state = 'running' AND lease_expires_ms <= $1 ORDER BY id",
        )
        .bind(ms(now))
        .fetch_all(&self.pool)
        .await
        .map_err(db)?;
        let mut changed = 0;
        for id in ids {
            let mut tx = self.begin().await?;
            let result = Self::reap_one(&mut tx, &self.options, id, now).await;
            match end(tx, result).await {
                Ok(true) => changed += 1,
                Ok(false) => {}
                // The database gone: the next pass tries them all again.
                Err(e @ OrchestratorError::Database(_)) => return Err(e),
                // One job that cannot be reclaimed (a record this build cannot read) does not
                // keep the others' leases from lapsing.
                Err(e) => tracing::warn!(job = id, error = %e, "a lapsed lease not reclaimed"),
            }
        }
        Ok(changed)
    }

    async fn get(&self, id: JobId) -> Result<Job, OrchestratorError> {
        let row = sqlx::query("SELECT job, lease_token FROM jobs WHERE id = $1")
            .bind(ms(id))
            .fetch_optional(&self.pool)
            .await
            .map_err(db)?
            .ok_or(OrchestratorError::NotFound(id))?;
        Self::job_of(&row)
    }

    async fn list(&self) -> Result<Vec<Job>, OrchestratorError> {
        sqlx::query("SELECT job, lease_token FROM jobs ORDER BY id")
            .fetch_all(&self.pool)
            .await
            .map_err(db)?
            .iter()
            .map(Self::job_of)
            .collect()
    }

    async fn list_after(&self, after: JobId, limit: usize) -> Result<Vec<Job>, OrchestratorError> {
        // Ids are BIGINT: nothing follows one past its range.
        let Ok(after) = i64::try_from(after) else {
            return Ok(Vec::new());
        };
        let limit = i64::try_from(limit).unwrap_or(i64::MAX);
        sqlx::query("SELECT job, lease_token FROM jobs WHERE id > $1 ORDER BY id LIMIT $2")
            .bind(after)
            .bind(limit)
            .fetch_all(&self.pool)
            .await
            .map_err(db)?
            .iter()
            .map(Self::job_of)
            .collect()
    }

    async fn put_result(
        &self,
        parent: JobId,
        id: JobId,
        attempt: u32,
        token: &[u8],
        bytes: Vec<u8>,
    ) -> Result<(), OrchestratorError> {
        // The part's row locked for the check and the write: no lease changes in between (and
        // a parent that ends meanwhile cancels the part after this commits, dropping the
        // result with it).
        let now = self.now();
        let mut tx = self.begin().await?;
        let t = &mut tx;
        let result = async move {
            let job = Self::locked(t, id).await?;
            rules::check_held(&job, attempt, token, now)?;
            sqlx::query(
                "INSERT INTO results (parent, job_id, data) VALUES ($1, $2, $3)
                 ON CONFLICT (parent, job_id) DO UPDATE SET data = EXCLUDED.data",
            )
            .bind(ms(parent))
            .bind(ms(id))
            .bind(bytes)
            .execute(&mut **t)
            .await
            .map_err(db)?;
            Ok(())
        }
        .await;
        end(tx, result).await
    }

    async fn result(&self, parent: JobId, id: JobId) -> Result<Option<Vec<u8>>, OrchestratorError> {
        let row = sqlx::query("SELECT data FROM results WHERE parent = $1 AND job_id = $2")
            .bind(ms(parent))
            .bind(ms(id))
            .fetch_optional(&self.pool)
            .await
            .map_err(db)?;
        row.map(|r| r.try_get::<Vec<u8>, _>(0).map_err(db))
            .transpose()
    }

    async fn drop_results(&self, parent: JobId) -> Result<usize, OrchestratorError> {
        let done = sqlx::query("DELETE FROM results WHERE parent = $1")
            .bind(ms(parent))
            .execute(&self.pool)
            .await
            .map_err(db)?;
        Ok(done.rows_affected() as usize)
    }

    async fn upload(&self, sha256: &[u8; 32]) -> Result<Option<Vec<u8>>, OrchestratorError> {
        let rows = sqlx::query("SELECT data FROM uploads WHERE sha256 = $1 ORDER BY seq")
            .bind(&sha256[..])
            .fetch_all(&self.pool)
            .await
            .map_err(db)?;
        if rows.is_empty() {
            return Ok(None);
        }
        let mut bytes = Vec::new();
        for row in rows {
            let chunk: &[u8] = row.try_get(0).map_err(db)?;
            bytes.extend_from_slice(chunk);
        }
        Ok(Some(bytes))
    }

    async fn counts(&self) -> Result<StateCounts, OrchestratorError> {
        let rows = sqlx::query("SELECT state, count(*) FROM jobs GROUP BY state")
            .fetch_all(&self.pool)
            .await
            .map_err(db)?;
        let mut c = StateCounts::default();
        for row in rows {
            let state: &str = row.try_get(0).map_err(db)?;
            let n: i64 = row.try_get(1).map_err(db)?;
            let n = n.max(0) as u64;
            match state {
                "queued" => c.queued += n,
                "running" => c.running += n,
                "done" => c.done += n,
                "failed" => c.failed += n,
                _ => c.cancelled += n,
            }
        }
        Ok(c)
    }

    async fn close(&self) -> Result<(), OrchestratorError> {
        // Every change was committed before its call returned.
        self.pool.close().await;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::redact;

    #[test]
    fn passwords_never_reach_messages() {
        for url in [
            "postgres://queue:hunter2@db:5432/jobs",
            "postgres://queue@db/jobs?password=hunter2&sslmode=require",
        ] {
            let shown = redact(url);
            assert!(!shown.contains("hunter2"), "{shown}");
            assert!(shown.contains("db") && shown.contains("jobs"), "{shown}");
        }
        assert!(redact("postgres://db/jobs?sslmode=require").contains("sslmode=require"));
        assert_eq!(redact("not a url"), "(unparsable URL)");
    }
}
