//! The wavesplat coefficient cache: stores compressed volumes (`.wsp`) as tiles and packets in
//! sled and serves them over gRPC (`wavesplat.v1.Cache` plus the standard health service),
//! streaming each viewer the packets that improve *its* view fastest and never one it holds
//! (view-dependent selective refinement, the paper's future work; JPIP is the model).
//!
//! - [`store`]: the sled layout, atomic ingest (batch + commit record), deletion, recovery;
//! - [`priority`]: the sending order, by visible energy per byte (the view's weights come from
//!   `wavesplat_codec::view::visibility`);
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

pub mod convert;
pub mod error;
pub mod model;
pub mod priority;
pub mod service;
pub mod store;

pub use error::CacheError;
pub use model::{PacketMeta, VolumeIndex, VolumeKey, VolumeMeta};
pub use priority::Priority;
pub use store::{Limits, Store};

use std::future::Future;
use tokio_stream::wrappers::TcpListenerStream;
use wavesplat_proto::pb::cache_server::CacheServer;

/// Serves the cache on `listener` until `shutdown` completes, then waits for in-flight
/// requests and flushes the store.
pub async fn serve(
    listener: tokio::net::TcpListener,
    store: Store,
    shutdown: impl Future<Output = ()> + Send,
) -> Result<(), CacheError> {
    let _flush = store::FlushGuard(store.clone());
    let limits = *store.limits();
    let (health, health_service) = tonic_health::server::health_reporter();
    health
        .set_serving::<CacheServer<service::CacheService>>()
        .await;
    let (stopping_tx, stopping) = tokio::sync::watch::channel(false);
    let cache = CacheServer::new(service::CacheService::new(store, stopping))
        .max_decoding_message_size(service::MAX_CHUNK_BYTES + 1024)
        .max_encoding_message_size(
            (limits.max_packet_bytes as usize).max(service::MAX_FIRST_PACKETS_BYTES as usize)
                + (1 << 20),
        );
    if let Ok(addr) = listener.local_addr() {
        tracing::info!(%addr, "cache serving");
    }
    tonic::transport::Server::builder()
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
