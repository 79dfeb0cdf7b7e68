//! The cache's typed errors and their single mapping to gRPC statuses: bad input (upload, view,
//! request shape) is `InvalidArgument`, a missing volume `NotFound`, a name clash
//! `AlreadyExists`, a concurrent change `Aborted`, a limit on concurrent work `ResourceExhausted`,
//! an abandoned request `DeadlineExceeded` / `Cancelled`, an object store that fails or cannot
//! be reached `Unavailable` (the client may retry), storage trouble `Internal` (so is an object
//! store's refusal that a retry would not change). Messages carry the bad value and the allowed range.

use thiserror::Error;
use wavesplat_codec::format::FormatError;

/// Errors of the cache library.
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum CacheError {
    /// No volume with this id or name.
    #[error("no volume {0}")]
    NotFound(String),
    /// A different volume already uses this name.
    #[error("a different volume named {0:?} already exists")]
    NameTaken(String),
    /// The request is malformed (missing field, bad view, out-of-range value).
    #[error("invalid request: {0}")]
    InvalidRequest(String),
    /// The upload is not acceptable (size, checksum, truncated, or not a valid .wsp file).
    #[error("invalid upload: {0}")]
    InvalidUpload(String),
    /// The upload is not a valid .wsp file.
    #[error("invalid .wsp file: {0}")]
    Format(#[from] FormatError),
    /// A size limit was exceeded.
    #[error("{what} of {size} bytes exceeds the limit of {limit} bytes")]
    TooLarge {
        /// What was too large.
        what: &'static str,
        /// Its size.
        size: u64,
        /// The limit.
        limit: u64,
    },
    /// The store failed.
    #[error("storage: {0}")]
    Storage(#[from] sled::Error),
    /// Stored metadata could not be read back (corruption).
    #[error("corrupt store entry: {0}")]
    Corrupt(String),
    /// A file of the store could not be read or written.
    #[error("storage file: {0}")]
    Io(String),
    /// The object store failed or could not be reached; the request may be repeated.
    #[error("object store: {0}")]
    Bucket(String),
    /// The object store refused a request for a reason that repeating it does not change (a
    /// key the backend cannot hold, no permission, a request it does not take).
    #[error("object store refused: {0}")]
    BucketRefused(String),
    /// A concurrent change got in the way; the request may be repeated.
    #[error("conflict: {0}")]
    Conflict(String),
    /// The client's deadline passed before the request could complete; nothing was changed.
    #[error("deadline exceeded: {0}")]
    DeadlineExceeded(String),
    /// The client went away before the request could complete; nothing was changed.
    #[error("cancelled: {0}")]
    Cancelled(String),
    /// A limit on concurrent work was reached (per client or for the server).
    #[error("busy: {0}")]
    Busy(String),
    /// The request cannot be served for this volume (it names what can).
    #[error("not supported: {0}")]
    Unsupported(String),
    /// The request's credentials do not allow it.
    #[error("permission denied: {0}")]
    PermissionDenied(String),
    /// The server may not run as configured (exposure without TLS and authentication).
    #[error("{0}")]
    Security(String),
    /// A transport-level failure (binding, serving).
    #[error("transport: {0}")]
    Transport(#[from] tonic::transport::Error),
}

impl From<sled::transaction::TransactionError<CacheError>> for CacheError {
    fn from(e: sled::transaction::TransactionError<CacheError>) -> Self {
        match e {
            sled::transaction::TransactionError::Abort(e) => e,
            sled::transaction::TransactionError::Storage(e) => CacheError::Storage(e),
        }
    }
}

impl From<CacheError> for tonic::Status {
    fn from(e: CacheError) -> Self {
        let msg = e.to_string();
        match e {
            CacheError::NotFound(_) => tonic::Status::not_found(msg),
            CacheError::NameTaken(_) => tonic::Status::already_exists(msg),
            CacheError::InvalidRequest(_)
            | CacheError::InvalidUpload(_)
            | CacheError::Format(_)
            | CacheError::TooLarge { .. } => tonic::Status::invalid_argument(msg),
            CacheError::Conflict(_) => tonic::Status::aborted(msg),
            CacheError::Bucket(_) => {
                tracing::warn!(error = %msg, "object store unavailable");
                tonic::Status::unavailable(msg)
            }
            CacheError::DeadlineExceeded(_) => tonic::Status::deadline_exceeded(msg),
            CacheError::Cancelled(_) => tonic::Status::cancelled(msg),
            CacheError::Busy(_) => tonic::Status::resource_exhausted(msg),
            CacheError::PermissionDenied(_) => tonic::Status::permission_denied(msg),
            CacheError::Unsupported(_) => tonic::Status::failed_precondition(msg),
            CacheError::Storage(_)
            | CacheError::Corrupt(_)
            | CacheError::Io(_)
            | CacheError::BucketRefused(_)
            | CacheError::Security(_)
            | CacheError::Transport(_) => {
                tracing::error!(error = %msg, "internal error");
                tonic::Status::internal(msg)
            }
        }
    }
}
