//! gRPC contracts of wavesplat (package `wavesplat.v1`, `proto/wavesplat/v1/*.proto`), compiled at
//! build time by `protox` (pure Rust, no `protoc`) and `tonic-prost-build`. Only the generated
//! code is exposed, as [`pb`]; every crate converts these types to its own domain types in one
//! place, so the wire format stays at the edge.

/// Generated messages, the `cache_client::CacheClient` and the `cache_server::CacheServer`, the
/// `orchestrator_client::OrchestratorClient` and the `orchestrator_server::OrchestratorServer`.
#[allow(missing_docs, clippy::all, clippy::pedantic)]
pub mod pb {
    tonic::include_proto!("wavesplat.v1");
}
