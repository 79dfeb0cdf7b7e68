//! The client side of the wavesplat orchestrator, and the job vocabulary it shares with the
//! server: what a job asks for, where it stands and how an attempt ended ([`model`]), their
//! conversions to and from the wire types ([`convert`]), and connecting (TLS and the token),
//! submitting and listing over gRPC ([`connect`], [`submit`], [`list`]), over one orchestrator
//! or failing over between several ([`failover`]), and the token a worker's RPCs on a lease
//! carry ([`lease`]). Workers, the CLI and
//! the tests link this crate; the server (`wavesplat-orchestrator`, with its store) links it
//! for the model, so a client never links sled or the server's health service.

pub mod connect;
pub mod convert;
pub mod error;
pub mod failover;
pub mod lease;
pub mod model;

pub use connect::{connect, connect_lazy, connect_with, list, submit, Client};
pub use error::ClientError;
pub use lease::{lease_token_of, with_lease_token, HeldLease, LEASE_TOKEN_METADATA};
pub use model::{Job, JobId, JobOptions, JobSpec, JobState, TargetSpec};

/// The largest chunk of an uploaded source in one gRPC message (submit and fetch).
pub const CHUNK_BYTES: usize = 1 << 20;
