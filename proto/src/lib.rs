//! gRPC contracts of wavesplat (package `wavesplat.v1`, `proto/wavesplat/v1/*.proto`), compiled at
//! build time by `protox` (pure Rust, no `protoc`) and `tonic-prost-build`. The generated code
//! is exposed as [`pb`], with one size helper ([`repeated_entry_len`]) for servers that fill a
//! reply up to a byte budget; every crate converts these types to its own domain types in one
//! place, so the wire format stays at the edge.

/// Generated messages, the `cache_client::CacheClient` and the `cache_server::CacheServer`, the
/// `orchestrator_client::OrchestratorClient` and the `orchestrator_server::OrchestratorServer`.
#[allow(missing_docs, clippy::all, clippy::pedantic)]
pub mod pb {
    tonic::include_proto!("wavesplat.v1");
}

/// Bytes `message` takes as one entry of a repeated message field numbered below 16 (a reply's
/// `repeated Packet packets = 2`, `repeated Job jobs = 1`): its tag, its length and itself.
/// What a server counts to keep a reply it fills within a byte budget.
pub fn repeated_entry_len(message: &impl prost::Message) -> usize {
    let len = message.encoded_len();
    1 + prost::length_delimiter_len(len) + len
}
