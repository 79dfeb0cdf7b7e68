//! Plumbing every wavesplat service and client shares, so that each concern lives in one place:
//!
//! - [`status`]: client faults answered with client statuses — an undecodable request is
//!   `INVALID_ARGUMENT` (tonic says `INTERNAL`), a message over the size limit
//!   `RESOURCE_EXHAUSTED` (tonic says `OUT_OF_RANGE`);
//! - [`deadline`]: the caller's deadline (`grpc-timeout`) as an instant a handler can honour;
//! - [`tls`]: TLS for servers and clients, the one place a URL becomes an endpoint, and the
//!   rule against exposing a server by accident;
//! - [`auth`]: bearer tokens with roles (read, ingest, write, worker, admin), checked in
//!   constant time by a layer in front of every service, and the clients' credentials;
//! - [`volume`]: how services and clients name a volume (`VolumeKey`: an id or a name);
//! - [`digest`]: content identity, the SHA-256 of a volume's bytes and its hex form;
//! - [`backoff`]: exponential backoff between retries.
//!
//! A server combines them in [`Security`].

pub mod auth;
pub mod backoff;
pub mod deadline;
pub mod digest;
pub mod status;
pub mod tls;
pub mod volume;

pub use auth::{Access, AuthLayer, Caller, Credentials, Policy, Role, Tokens};
pub use tls::TlsError;
pub use volume::VolumeKey;

use std::path::PathBuf;
use std::sync::Arc;
use tonic::transport::{Endpoint, ServerTlsConfig};

/// How a client reaches a service: the CA that signs its certificate (for `https://` URLs; the
/// system's roots without one) and the token to send.
#[derive(Debug, Clone, Default)]
pub struct ConnectOptions {
    /// PEM CA certificate for `https://` URLs.
    pub ca: Option<PathBuf>,
    /// The token sent with every request.
    pub credentials: Credentials,
}

impl ConnectOptions {
    /// The endpoint of `url` ([`tls::endpoint`]) and its normalised form.
    pub fn endpoint(&self, url: &str) -> Result<(String, Endpoint), TlsError> {
        tls::endpoint(url, self.ca.as_deref())
    }
}

/// How a server protects itself.
#[derive(Debug, Clone, Default)]
pub struct Security {
    /// TLS settings (`None`: plaintext).
    pub tls: Option<ServerTlsConfig>,
    /// Accepted tokens (`None`: no authentication).
    pub tokens: Option<Arc<Tokens>>,
    /// Serve on a non-loopback address without TLS and authentication anyway.
    pub insecure: bool,
}

impl Security {
    /// Checks that serving on `addr` is allowed ([`tls::check_exposure`]).
    pub fn check(&self, addr: std::net::SocketAddr) -> Result<(), TlsError> {
        tls::check_exposure(
            addr,
            self.tls.is_some(),
            self.tokens.is_some(),
            self.insecure,
        )
    }

    /// The address `listener` is bound to, once serving there is allowed ([`Security::check`]);
    /// the error says which (the address unreadable, or the exposure refused).
    pub fn check_listener(
        &self,
        listener: &tokio::net::TcpListener,
    ) -> Result<std::net::SocketAddr, String> {
        let addr = listener
            .local_addr()
            .map_err(|e| format!("listener address: {e}"))?;
        self.check(addr).map_err(|e| e.to_string())?;
        Ok(addr)
    }

    /// A tonic server builder, with TLS when it is configured.
    pub fn server_builder(&self) -> Result<tonic::transport::Server, tonic::transport::Error> {
        let builder = tonic::transport::Server::builder();
        match self.tls.clone() {
            Some(tls) => builder.tls_config(tls),
            None => Ok(builder),
        }
    }

    /// What an operator should be told, once at start, about serving on `addr` with these
    /// settings: nothing with TLS and tokens; otherwise who can read or change what.
    pub fn warnings(&self, addr: std::net::SocketAddr) -> Vec<String> {
        let tls = self.tls.is_some();
        let auth = self.tokens.is_some();
        let reach = if addr.ip().is_loopback() {
            "anyone with an account on this machine".to_string()
        } else {
            format!("anyone who can reach {addr}")
        };
        match (tls, auth) {
            (true, true) => Vec::new(),
            (false, false) => vec![format!(
                "warning: serving plaintext without tokens: {reach} can read and change \
                 everything (give --tls-cert/--tls-key and --tokens; see the README's \
                 \"Securing the services\")"
            )],
            (false, true) => vec![format!(
                "warning: tokens are required but travel in plaintext: {reach} on the path can \
                 read them and the data (give --tls-cert/--tls-key)"
            )],
            (true, false) => vec![format!(
                "warning: serving TLS without tokens: {reach} can read and change everything \
                 (give --tokens)"
            )],
        }
    }

    /// The authentication layer for a service with `policy`.
    pub fn auth_layer(&self, policy: Policy) -> AuthLayer {
        AuthLayer::new(self.tokens.clone(), policy)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn unprotected_servers_are_warned_about_and_protected_ones_not() {
        let addr: std::net::SocketAddr = "127.0.0.1:1".parse().unwrap();
        assert_eq!(Security::default().warnings(addr).len(), 1);
        let plain_tokens = Security {
            tokens: Some(Arc::new(Tokens::parse("a read 0123456789abcdef").unwrap())),
            ..Default::default()
        };
        let w = plain_tokens.warnings(addr);
        assert_eq!(w.len(), 1);
        assert!(w[0].contains("plaintext"), "{w:?}");
    }
}
