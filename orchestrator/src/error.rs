//! The orchestrator's typed errors and their single mapping to gRPC statuses: bad requests are
//! `InvalidArgument`, unknown jobs `NotFound`, actions the job's state forbids (and lost
//! leases, deliveries the cache does not confirm) `FailedPrecondition`, a request on a running
//! lease without its token `PermissionDenied`, an unreachable cache
//! or queue database `Unavailable`, storage trouble `Internal`. Jobs are named by their id (`model::JobId`, a
//! `u64`), so this module needs nothing from the others.

use thiserror::Error;

/// Errors of the orchestrator library.
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum OrchestratorError {
    /// No job with this id.
    #[error("no job {0}")]
    NotFound(u64),
    /// The request is malformed or a value is out of range.
    #[error("invalid request: {0}")]
    InvalidRequest(String),
    /// The job's state does not allow the action.
    #[error("job {id} is {state}; {action} needs {allowed}")]
    InvalidState {
        /// The job.
        id: u64,
        /// Its state.
        state: &'static str,
        /// What was asked.
        action: &'static str,
        /// The states that allow it.
        allowed: &'static str,
    },
    /// The caller does not hold the job's lease (it expired and was reclaimed, the job was
    /// cancelled, or the attempt is stale).
    #[error("lease on job {id} attempt {attempt} is not held: {reason}")]
    LeaseLost {
        /// The job.
        id: u64,
        /// The attempt claimed.
        attempt: u32,
        /// Why.
        reason: String,
    },
    /// The caller names the running lease (job and attempt) but not its token: it is not the
    /// worker the lease was granted to.
    #[error("lease on job {id} attempt {attempt}: the lease token is missing or wrong")]
    NotLeaseHolder {
        /// The job.
        id: u64,
        /// The attempt claimed.
        attempt: u32,
    },
    /// No randomness for a lease token (the operating system's generator failed).
    #[error("drawing a lease token: {0}")]
    Entropy(String),
    /// The store failed.
    #[error("storage: {0}")]
    Storage(#[from] sled::Error),
    /// The PostgreSQL queue could not be reached or refused a statement (transient: callers
    /// retry; the message names the cause).
    #[error("queue database: {0}")]
    Database(String),
    /// A stored record could not be read back.
    #[error("corrupt store entry: {0}")]
    Corrupt(String),
    /// A service could not be reached (URL, TLS setup, connection).
    #[error("cannot connect to {0}")]
    Connect(String),
    /// The server may not run as configured (exposure without TLS and authentication).
    #[error("{0}")]
    Security(String),
    /// A worker's reported delivery is not what the cache holds.
    #[error("delivery not confirmed by the cache: {0}")]
    Unconfirmed(String),
    /// The cache could not be asked to confirm a delivery.
    #[error("cannot confirm the delivery with the cache: {0}")]
    CacheUnavailable(String),
    /// A transport-level failure (binding, serving).
    #[error("transport: {0}")]
    Transport(#[from] tonic::transport::Error),
}

impl From<wavesplat_orchestrator_client::ClientError> for OrchestratorError {
    fn from(e: wavesplat_orchestrator_client::ClientError) -> Self {
        use wavesplat_orchestrator_client::ClientError;
        match e {
            ClientError::InvalidRequest(m) => OrchestratorError::InvalidRequest(m),
            ClientError::Connect(m) => OrchestratorError::Connect(m),
            other => OrchestratorError::InvalidRequest(other.to_string()),
        }
    }
}

impl From<OrchestratorError> for tonic::Status {
    fn from(e: OrchestratorError) -> Self {
        let msg = e.to_string();
        match e {
            OrchestratorError::NotFound(_) => tonic::Status::not_found(msg),
            OrchestratorError::NotLeaseHolder { .. } => tonic::Status::permission_denied(msg),
            OrchestratorError::InvalidRequest(_) => tonic::Status::invalid_argument(msg),
            OrchestratorError::InvalidState { .. }
            | OrchestratorError::LeaseLost { .. }
            | OrchestratorError::Unconfirmed(_) => tonic::Status::failed_precondition(msg),
            OrchestratorError::CacheUnavailable(_)
            | OrchestratorError::Connect(_)
            | OrchestratorError::Database(_) => tonic::Status::unavailable(msg),
            OrchestratorError::Storage(_)
            | OrchestratorError::Security(_)
            | OrchestratorError::Corrupt(_)
            | OrchestratorError::Entropy(_)
            | OrchestratorError::Transport(_) => {
                tracing::error!(error = %msg, "internal error");
                tonic::Status::internal(msg)
            }
        }
    }
}
