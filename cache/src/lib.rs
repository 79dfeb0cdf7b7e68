//! The wavesplat coefficient cache: stores compressed volumes (`.wsp`) as tiles and packets in
//! sled and serves them over gRPC (`wavesplat.v1.Cache` plus the standard health service),
//! streaming each viewer the packets that improve *its* view fastest and never one it holds
//! (view-dependent selective refinement, the paper's future work; JPIP is the model).
//!
//! - [`store`]: metadata in sled, each volume's bytes in a file; streamed, incrementally
//!   validated, atomic ingest (commit record), names, deletion, recovery;
//! - the sending order, by visible energy per byte, is [`Priority`] from
//!   `wavesplat_codec::view::priority`, which range-request readers share;
//! - [`service`]: the tonic service and the per-stream refinement session;
//! - [`convert`] / [`error`]: the one place for `pb` conversions / `tonic::Status` mapping;
//!
//! ```no_run
//! # async fn demo() -> Result<(), wavesplat_cache::CacheError> {
//! let store = wavesplat_cache::Store::open("cache.db", Default::default())?;
//! let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
//! wavesplat_cache::serve(listener, store, async { let _ = tokio::signal::ctrl_c().await; }).await?;
//! # Ok(()) }
//! ```

pub mod bucket;
pub mod convert;
pub mod error;
pub mod model;
pub mod service;
pub mod store;

pub use error::CacheError;
pub use model::{PacketMeta, VolumeIndex, VolumeKey, VolumeMeta};
pub use store::{Limits, Store};
pub use wavesplat_codec::view::priority::Priority;

use std::future::Future;
use tokio_stream::wrappers::TcpListenerStream;
use wavesplat_net::{Access, Role};
use wavesplat_proto::pb::cache_server::CacheServer;

/// How a cache server runs: its security and its per-caller limits.
#[derive(Debug, Clone, Default)]
pub struct ServeOptions {
    /// TLS, tokens, and whether to allow exposure without them.
    pub security: wavesplat_net::Security,
    /// Limits per caller identity.
    pub fairness: service::Fairness,
}

/// The access rule of every cache RPC: reading needs `read`, adding a volume `ingest` (which
/// `write` implies), deleting `write`; health checks are public; anything unknown needs
/// `admin`.
pub fn access(path: &str) -> Access {
    match path.strip_prefix("/wavesplat.v1.Cache/") {
        Some("Ingest") => Access::Role(Role::Ingest),
        Some("Delete") => Access::Role(Role::Write),
        Some("List" | "Describe" | "FirstPackets" | "Header" | "PacketTable" | "Refine") => {
            Access::Role(Role::Read)
        }
        _ if path.starts_with("/grpc.health.v1.Health/") => Access::Public,
        _ => Access::Role(Role::Admin),
    }
}

/// Serves the cache on `listener` (loopback, plaintext, no authentication) until `shutdown`
/// completes; see [`serve_with`].
pub async fn serve(
    listener: tokio::net::TcpListener,
    store: Store,
    shutdown: impl Future<Output = ()> + Send,
) -> Result<(), CacheError> {
    serve_with(listener, store, ServeOptions::default(), shutdown).await
}

/// Serves the cache on `listener` until `shutdown` completes, then ends open refinement
/// streams, waits for in-flight requests and flushes the store. Refuses a non-loopback
/// listener without TLS and tokens unless `options.security.insecure`.
pub async fn serve_with(
    listener: tokio::net::TcpListener,
    store: Store,
    options: ServeOptions,
    shutdown: impl Future<Output = ()> + Send,
) -> Result<(), CacheError> {
    let addr = options
        .security
        .check_listener(&listener)
        .map_err(CacheError::Security)?;
    let _flush = store::FlushGuard(store.clone());
    let limits = *store.limits();
    let (health, health_service) = tonic_health::server::health_reporter();
    health
        .set_serving::<CacheServer<service::CacheService>>()
        .await;
    let (stopping_tx, stopping) = tokio::sync::watch::channel(false);
    let cache = CacheServer::new(service::CacheService::with_fairness(
        store,
        stopping,
        options.fairness,
    ))
    .max_decoding_message_size(service::MAX_CHUNK_BYTES + 1024)
    .max_encoding_message_size(
        (limits.max_packet_bytes as usize).max(service::MAX_FIRST_PACKETS_BYTES as usize)
            + (1 << 20),
    );
    let builder = options.security.server_builder()?;
    tracing::info!(
        %addr,
        tls = options.security.tls.is_some(),
        auth = options.security.tokens.is_some(),
        "cache serving"
    );
    builder
        .layer(wavesplat_net::status::ClientFaultLayer)
        .layer(options.security.auth_layer(access))
        .add_service(health_service)
        .add_service(cache)
        .serve_with_incoming_shutdown(TcpListenerStream::new(listener), async move {
            shutdown.await;
            let _ = stopping_tx.send(true);
        })
        .await?;
    tracing::info!("cache stopped");
    Ok(())
}
