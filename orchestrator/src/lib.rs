//! The wavesplat orchestrator: durable batch compression of a volume archive.
//!
//! A gRPC service (`wavesplat.v1.Orchestrator`, plus the standard health service) keeps a queue
//! of jobs — in sled, or in PostgreSQL shared by any number of orchestrators — one job compresses one volume with given options and delivers the `.wsp`
//! result to a coefficient cache. Stateless workers lease jobs, heartbeat with progress, and
//! report a delivery or a typed failure; a lease that stops heartbeating is reclaimed and the
//! job runs elsewhere; transient failures retry with exponential backoff up to a limit.
//!
//! - [`model`]: jobs, specs, states, failures (plain Rust, serialisable for the store), and
//!   [`convert`], their `pb` conversions: both from `wavesplat-orchestrator-client`, which
//!   workers and the CLI link instead of this server;
//! - [`queue`]: the queue logic with an explicit clock (unit tested without sleeping): the
//!   per-job [`queue::rules`] both stores apply, and the in-memory index of the embedded store;
//! - [`jobstore`]: the [`JobStore`] contract and the embedded implementation over
//!   [`store`], the sled layout and durability rules; [`postgres`]: the same contract over a
//!   PostgreSQL database (row locks, `SKIP LOCKED` leases, versioned migrations);
//! - [`service`]: the tonic service; [`error`]: the one place for the `tonic::Status` mapping;
//! - [`check`]: confirming a worker's delivery with the cache before a job is done;
//!
//! The worker and archive scanning (which reads volume files to find and hash them) live in
//! their own crate (`wavesplat-worker`): this one links no encoder and no reader.
//!
//! ```no_run
//! # async fn demo() -> Result<(), wavesplat_orchestrator::OrchestratorError> {
//! let store = wavesplat_orchestrator::Store::open("orchestrator.db")?;
//! let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
//! let config = wavesplat_orchestrator::ServiceOptions::default();
//! wavesplat_orchestrator::serve(listener, store, config, async {
//!     let _ = tokio::signal::ctrl_c().await;
//! })
//! .await?;
//! # Ok(()) }
//! ```

pub mod check;
pub mod error;
pub mod jobstore;
pub mod postgres;
pub mod queue;
pub mod service;
pub mod store;

pub use check::DeliveryCheck;
pub use error::OrchestratorError;
pub use jobstore::{EmbeddedQueue, JobStore, Leased};
pub use model::{Job, JobId, JobOptions, JobSpec, JobState, TargetSpec};
pub use postgres::{PostgresOptions, PostgresQueue};
pub use queue::QueueOptions;
pub use service::{OrchestratorService, ServiceOptions};
use std::future::Future;
use std::time::Duration;
pub use store::Store;
use tokio_stream::wrappers::TcpListenerStream;
use wavesplat_net::{Access, Role};
pub use wavesplat_orchestrator_client::{convert, model};
use wavesplat_proto::pb::orchestrator_server::OrchestratorServer;

/// Where the queue is kept: the embedded sled store (one orchestrator owns its directory) or a
/// PostgreSQL database (any number of stateless orchestrators share it).
pub enum Backend {
    /// The sled store; the queue is loaded into memory at start.
    Embedded(Store),
    /// A PostgreSQL database, already migrated ([`PostgresQueue::connect`]).
    Postgres(PostgresQueue),
}

impl From<Store> for Backend {
    fn from(s: Store) -> Backend {
        Backend::Embedded(s)
    }
}

impl From<PostgresQueue> for Backend {
    fn from(q: PostgresQueue) -> Backend {
        Backend::Postgres(q)
    }
}

impl Backend {
    /// The job store over this backend with the queue policy `cfg` and the wall clock.
    pub fn into_job_store(
        self,
        cfg: QueueOptions,
    ) -> Result<std::sync::Arc<dyn JobStore>, OrchestratorError> {
        Ok(match self {
            Backend::Embedded(store) => {
                std::sync::Arc::new(EmbeddedQueue::open(store, cfg, queue::system_clock())?)
            }
            Backend::Postgres(q) => std::sync::Arc::new(q.with_options(cfg.validate()?)),
        })
    }
}

/// How an orchestrator server runs.
#[derive(Debug, Clone, Default)]
pub struct ServeOptions {
    /// TLS, tokens, and whether to allow exposure without them.
    pub security: wavesplat_net::Security,
    /// Confirm deliveries with this cache before marking jobs done.
    pub delivery_check: Option<DeliveryCheck>,
}

/// The access rule of every orchestrator RPC: submitting, cancelling and retrying need
/// `admin`; leasing, heartbeats, outcomes, uploaded sources and the parts of bricked jobs
/// `worker`; listing `read`;
/// health checks are public; anything unknown needs `admin`.
pub fn access(path: &str) -> Access {
    match path.strip_prefix("/wavesplat.v1.Orchestrator/") {
        Some("Submit" | "CancelJob" | "RetryJob") => Access::Role(Role::Admin),
        Some(
            "Lease" | "Heartbeat" | "Finish" | "FetchSource" | "SubmitParts" | "FinishPart"
            | "FetchResult",
        ) => Access::Role(Role::Worker),
        Some("ListJobs" | "GetJob") => Access::Role(Role::Read),
        _ if path.starts_with("/grpc.health.v1.Health/") => Access::Public,
        _ => Access::Role(Role::Admin),
    }
}

/// Serves the orchestrator on `listener` (loopback, plaintext, no authentication, deliveries
/// taken on the worker's word) until `shutdown` completes; see [`serve_with`].
pub async fn serve(
    listener: tokio::net::TcpListener,
    store: impl Into<Backend>,
    config: ServiceOptions,
    shutdown: impl Future<Output = ()> + Send,
) -> Result<(), OrchestratorError> {
    serve_with(listener, store, config, ServeOptions::default(), shutdown).await
}

/// Serves the orchestrator on `listener` until `shutdown` completes, then waits for in-flight
/// requests and flushes the store. Expired leases are also reclaimed every heartbeat interval.
/// Refuses a non-loopback listener without TLS and tokens unless `options.security.insecure`.
pub async fn serve_with(
    listener: tokio::net::TcpListener,
    store: impl Into<Backend>,
    config: ServiceOptions,
    options: ServeOptions,
    shutdown: impl Future<Output = ()> + Send,
) -> Result<(), OrchestratorError> {
    let addr = options
        .security
        .check_listener(&listener)
        .map_err(OrchestratorError::Security)?;
    let store = store.into().into_job_store(config.queue)?;
    let mut service = OrchestratorService::new(store, config).await?;
    if let Some(check) = options.delivery_check.clone() {
        service = service.with_delivery_check(check);
    }
    let (health, health_service) = tonic_health::server::health_reporter();
    health
        .set_serving::<OrchestratorServer<OrchestratorService>>()
        .await;
    let reaper = tokio::spawn({
        let service = service.clone();
        let every = Duration::from_millis(config.queue.heartbeat_ms.max(10));
        async move {
            let mut tick = tokio::time::interval(every);
            loop {
                tick.tick().await;
                if let Err(e) = service.reap().await {
                    tracing::error!(error = %e, "reclaiming expired leases");
                }
            }
        }
    });
    let server = OrchestratorServer::new(service.clone())
        .max_decoding_message_size(wavesplat_orchestrator_client::CHUNK_BYTES + (1 << 20))
        .max_encoding_message_size(wavesplat_orchestrator_client::CHUNK_BYTES + (1 << 20));
    let builder = options.security.server_builder()?;
    tracing::info!(
        %addr,
        tls = options.security.tls.is_some(),
        auth = options.security.tokens.is_some(),
        checks_deliveries = options.delivery_check.is_some(),
        "orchestrator serving"
    );
    let result = builder
        .layer(wavesplat_net::status::ClientFaultLayer)
        .layer(options.security.auth_layer(access))
        .add_service(health_service)
        .add_service(server)
        .serve_with_incoming_shutdown(TcpListenerStream::new(listener), shutdown)
        .await;
    reaper.abort();
    if let Err(e) = service.close().await {
        tracing::error!(error = %e, "flushing the orchestrator store");
    }
    result?;
    tracing::info!("orchestrator stopped");
    Ok(())
}
