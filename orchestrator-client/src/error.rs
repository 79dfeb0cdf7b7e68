//! The client's typed errors: a job spec, option or wire message that is not valid, and an
//! orchestrator that cannot be reached. The server maps them into its own errors (and so into
//! gRPC statuses); callers report them with the URL or value named in the message.

use thiserror::Error;

/// Errors of the orchestrator client and of the job model's validation.
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum ClientError {
    /// The request is malformed or a value is out of range.
    #[error("invalid request: {0}")]
    InvalidRequest(String),
    /// The orchestrator could not be reached (URL, TLS setup, connection).
    #[error("cannot connect to {0}")]
    Connect(String),
}
