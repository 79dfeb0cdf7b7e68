//! A lease on the wire: the token the orchestrator grants with each lease (`Lease.lease_token`)
//! and how a worker's RPC on the lease carries it (the request metadata
//! [`LEASE_TOKEN_METADATA`]). A job's id and attempt are public (any reader lists them); the
//! token is what shows that the caller is the worker the lease was granted to.

use tonic::metadata::MetadataValue;
use tonic::Request;
use wavesplat_proto::pb;

/// The request metadata key (binary) under which a worker RPC carries the token of the lease it
/// acts on: Heartbeat, Finish, FetchSource and FinishPart the leased job's, SubmitParts and
/// FetchResult the parent's.
pub const LEASE_TOKEN_METADATA: &str = "wavesplat-lease-token-bin";

/// `message` as a request carrying the lease token `token`.
pub fn with_lease_token<T>(message: T, token: &[u8]) -> Request<T> {
    let mut request = Request::new(message);
    request
        .metadata_mut()
        .insert_bin(LEASE_TOKEN_METADATA, MetadataValue::from_bytes(token));
    request
}

/// The lease token `request` carries (empty when it carries none or one that does not decode,
/// which matches no lease).
pub fn lease_token_of<T>(request: &Request<T>) -> Vec<u8> {
    request
        .metadata()
        .get_bin(LEASE_TOKEN_METADATA)
        .and_then(|v| v.to_bytes().ok())
        .map(|b| b.to_vec())
        .unwrap_or_default()
}

/// A lease as its holder names it on the RPCs that act on it: the job, the attempt and the
/// lease's token. Its `Debug` shows no token.
#[derive(Clone, PartialEq, Eq)]
pub struct HeldLease {
    /// The leased job.
    pub job_id: u64,
    /// The lease's attempt.
    pub attempt: u32,
    /// The lease's token, as granted.
    token: Vec<u8>,
}

impl HeldLease {
    /// The lease of `job_id` at `attempt` whose token is `token`.
    pub fn new(job_id: u64, attempt: u32, token: Vec<u8>) -> HeldLease {
        HeldLease {
            job_id,
            attempt,
            token,
        }
    }

    /// The lease a `Lease` reply grants.
    pub fn of(lease: &pb::Lease) -> HeldLease {
        HeldLease::new(lease.job_id, lease.attempt, lease.lease_token.clone())
    }

    /// The lease's token.
    pub fn token(&self) -> &[u8] {
        &self.token
    }

    /// `message` as a request on this lease (carrying its token).
    pub fn request<T>(&self, message: T) -> Request<T> {
        with_lease_token(message, &self.token)
    }
}

impl std::fmt::Debug for HeldLease {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("HeldLease")
            .field("job_id", &self.job_id)
            .field("attempt", &self.attempt)
            .finish_non_exhaustive()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_request_carries_the_token_and_debug_hides_it() {
        let held = HeldLease::new(7, 2, vec![0xab; 16]);
        let r = held.request(pb::HeartbeatRequest::default());
        assert_eq!(lease_token_of(&r), vec![0xab; 16]);
        assert!(lease_token_of(&Request::new(())).is_empty());
        let shown = format!("{held:?}");
        assert!(
            shown.contains("job_id: 7") && !shown.contains("171"),
            "{shown}"
        );
    }
}
