//! Authentication by bearer tokens with roles, and the access rule of every RPC.
//!
//! A token file has one token a line: `IDENTITY ROLES SECRET`, ROLES comma-separated from
//! `read` (list, describe, stream), `ingest` (add volumes, nothing else: what a worker needs at
//! the cache), `write` (ingest and delete), `worker` (lease, heartbeat, finish) and `admin`
//! (submit, cancel, retry; implies every other role). Blank lines and `#`
//! comments are ignored. Secrets are at least 16 bytes; only their SHA-256 is kept, and a
//! presented token is compared with every known one in constant time ([`subtle`]), so neither
//! the position of the first differing byte nor which token matched shows in the timing.
//!
//! Servers add [`AuthLayer`] with their method → role rule: a request without a known token is
//! refused `UNAUTHENTICATED`, one whose token lacks the role `PERMISSION_DENIED`, before any
//! handler runs. The caller ([`Caller`]) is put into the request's extensions for handlers that
//! apply per-identity limits. Clients send the token with [`Credentials`], read from a file or
//! the environment (`WAVESPLAT_TOKEN`), never from the command line.

use sha2::{Digest, Sha256};
use std::future::Future;
use std::path::Path;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};
use subtle::ConstantTimeEq;
use thiserror::Error;
use tonic::metadata::{Ascii, MetadataValue};
use tonic::transport::server::TcpConnectInfo;
use tonic::Status;

/// The environment variable clients read their token from.
pub const TOKEN_ENV: &str = "WAVESPLAT_TOKEN";
/// Shortest accepted secret (bytes).
pub const MIN_SECRET_BYTES: usize = 16;

/// Errors reading tokens.
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum AuthError {
    /// The token file could not be read.
    #[error("reading the token file {path}: {source}")]
    Read {
        /// The file.
        path: String,
        /// Why.
        #[source]
        source: std::io::Error,
    },
    /// A line of the token file is malformed.
    #[error("token file line {line}: {reason}")]
    Syntax {
        /// 1-based line number.
        line: usize,
        /// What is wrong.
        reason: String,
    },
    /// A client token is unusable.
    #[error("token: {0}")]
    Token(String),
}

/// What a token allows.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Role {
    /// List, describe, read headers and packets, stream; list and watch jobs.
    Read,
    /// Add volumes (idempotent by content), nothing else: a worker's role at the cache.
    Ingest,
    /// Ingest and delete volumes (implies `ingest`).
    Write,
    /// Lease jobs, heartbeat, report outcomes, fetch uploaded sources.
    Worker,
    /// Submit, cancel and retry jobs; implies every role.
    Admin,
}

impl Role {
    /// Parses `read`, `write`, `worker` or `admin`.
    pub fn from_name(name: &str) -> Option<Role> {
        match name.trim().to_ascii_lowercase().as_str() {
            "read" => Some(Role::Read),
            "ingest" => Some(Role::Ingest),
            "write" => Some(Role::Write),
            "worker" => Some(Role::Worker),
            "admin" => Some(Role::Admin),
            _ => None,
        }
    }

    /// The name.
    pub fn name(self) -> &'static str {
        match self {
            Role::Read => "read",
            Role::Ingest => "ingest",
            Role::Write => "write",
            Role::Worker => "worker",
            Role::Admin => "admin",
        }
    }

    fn bit(self) -> u8 {
        match self {
            Role::Read => 1,
            Role::Write => 2,
            Role::Worker => 4,
            Role::Admin => 8,
            Role::Ingest => 16,
        }
    }

    /// The bits of the roles that grant this one: itself, `admin`, and for `ingest` also
    /// `write`.
    fn granted_by(self) -> u8 {
        let implied = match self {
            Role::Ingest => Role::Write.bit(),
            _ => 0,
        };
        self.bit() | implied | Role::Admin.bit()
    }
}

/// Who made a request: an authenticated identity, or (without authentication) the peer.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Caller {
    /// The token's identity, or `peer:ADDRESS` without authentication.
    pub identity: String,
    roles: u8,
}

impl Caller {
    /// A caller with every role (servers without authentication).
    pub fn unrestricted(identity: String) -> Caller {
        Caller {
            identity,
            roles: 0x1f,
        }
    }

    /// Whether the caller may act in `role`.
    pub fn has(&self, role: Role) -> bool {
        self.roles & role.granted_by() != 0
    }
}

#[derive(Debug, Clone)]
struct Entry {
    identity: String,
    roles: u8,
    digest: [u8; 32],
}

/// The tokens a server accepts.
#[derive(Debug, Clone, Default)]
pub struct Tokens {
    entries: Vec<Entry>,
}

impl Tokens {
    /// Parses a token file's text.
    pub fn parse(text: &str) -> Result<Tokens, AuthError> {
        let mut entries: Vec<Entry> = Vec::new();
        for (i, line) in text.lines().enumerate() {
            let syntax = |reason: String| AuthError::Syntax {
                line: i + 1,
                reason,
            };
            let line = line.trim();
            if line.is_empty() || line.starts_with('#') {
                continue;
            }
            let fields: Vec<&str> = line.split_whitespace().collect();
            let [identity, roles, secret] = fields[..] else {
                return Err(syntax(format!(
                    "expected `IDENTITY ROLES SECRET`, found {} fields",
                    fields.len()
                )));
            };
            let mut bits = 0;
            for r in roles.split(',') {
                let role = Role::from_name(r).ok_or_else(|| {
                    syntax(format!(
                        "role {r:?}; allowed read, ingest, write, worker, admin"
                    ))
                })?;
                bits |= role.bit();
            }
            if secret.len() < MIN_SECRET_BYTES {
                return Err(syntax(format!(
                    "the secret of {identity:?} has {} bytes; at least {MIN_SECRET_BYTES}",
                    secret.len()
                )));
            }
            let digest: [u8; 32] = Sha256::digest(secret.as_bytes()).into();
            if entries.iter().any(|e| e.digest == digest) {
                return Err(syntax(format!("the secret of {identity:?} is used twice")));
            }
            entries.push(Entry {
                identity: identity.to_string(),
                roles: bits,
                digest,
            });
        }
        Ok(Tokens { entries })
    }

    /// Reads a token file.
    pub fn load(path: &Path) -> Result<Tokens, AuthError> {
        let text = std::fs::read_to_string(path).map_err(|source| AuthError::Read {
            path: path.display().to_string(),
            source,
        })?;
        Tokens::parse(&text)
    }

    /// Number of tokens.
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// The caller a secret identifies, comparing it with every token in constant time.
    pub fn authenticate(&self, secret: &str) -> Option<Caller> {
        let digest: [u8; 32] = Sha256::digest(secret.as_bytes()).into();
        let mut found: Option<&Entry> = None;
        for e in &self.entries {
            if bool::from(e.digest.ct_eq(&digest)) {
                found = Some(e);
            }
        }
        found.map(|e| Caller {
            identity: e.identity.clone(),
            roles: e.roles,
        })
    }
}

/// Who may call a method.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Access {
    /// Anyone (health checks).
    Public,
    /// Callers with this role.
    Role(Role),
}

/// A service's rule: the access of a request path (`/package.Service/Method`).
pub type Policy = fn(&str) -> Access;

/// Authenticates every request and checks it against the service's [`Policy`]; with no tokens
/// (authentication off) every caller is [`Caller::unrestricted`], identified by its address.
#[derive(Debug, Clone)]
pub struct AuthLayer {
    tokens: Option<Arc<Tokens>>,
    policy: Policy,
}

impl AuthLayer {
    /// A layer checking `tokens` (or none) against `policy`.
    pub fn new(tokens: Option<Arc<Tokens>>, policy: Policy) -> AuthLayer {
        AuthLayer { tokens, policy }
    }
}

impl<S> tower::Layer<S> for AuthLayer {
    type Service = Auth<S>;
    fn layer(&self, inner: S) -> Auth<S> {
        Auth {
            inner,
            tokens: self.tokens.clone(),
            policy: self.policy,
        }
    }
}

/// The service [`AuthLayer`] makes.
#[derive(Debug, Clone)]
pub struct Auth<S> {
    inner: S,
    tokens: Option<Arc<Tokens>>,
    policy: Policy,
}

type BoxFuture<T> = Pin<Box<dyn Future<Output = T> + Send>>;

fn bearer(headers: &http::HeaderMap) -> Option<&str> {
    let v = headers.get("authorization")?.to_str().ok()?;
    v.strip_prefix("Bearer ").map(str::trim)
}

impl<S, B, R> tower::Service<http::Request<B>> for Auth<S>
where
    S: tower::Service<http::Request<B>, Response = http::Response<R>>,
    S::Future: Send + 'static,
    R: Default + Send + 'static,
    S::Error: Send + 'static,
{
    type Response = http::Response<R>;
    type Error = S::Error;
    type Future = BoxFuture<Result<http::Response<R>, S::Error>>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), S::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, mut req: http::Request<B>) -> Self::Future {
        let access = (self.policy)(req.uri().path());
        let caller = match &self.tokens {
            None => {
                let peer = req
                    .extensions()
                    .get::<TcpConnectInfo>()
                    .and_then(|c| c.remote_addr())
                    .map_or_else(|| "unknown".to_string(), |a| a.ip().to_string());
                Ok(Caller::unrestricted(format!("peer:{peer}")))
            }
            Some(tokens) => match bearer(req.headers()).and_then(|t| tokens.authenticate(t)) {
                Some(c) => Ok(c),
                None if access == Access::Public => Ok(Caller {
                    identity: "anonymous".into(),
                    roles: 0,
                }),
                None => Err(Status::unauthenticated(
                    "a valid token is required (`authorization: Bearer TOKEN`)",
                )),
            },
        };
        let checked = caller.and_then(|c| match access {
            Access::Role(role) if !c.has(role) => Err(Status::permission_denied(format!(
                "{} lacks the {} role for {}",
                c.identity,
                role.name(),
                req.uri().path()
            ))),
            _ => Ok(c),
        });
        match checked {
            Ok(c) => {
                req.extensions_mut().insert(c);
                let fut = self.inner.call(req);
                Box::pin(fut)
            }
            Err(status) => {
                tracing::debug!(path = req.uri().path(), %status, "refused");
                Box::pin(async move { Ok(status.into_http()) })
            }
        }
    }
}

/// The token a client sends (`authorization: Bearer TOKEN` on every request).
#[derive(Debug, Clone, Default)]
pub struct Credentials {
    header: Option<MetadataValue<Ascii>>,
}

impl Credentials {
    /// No token.
    pub fn none() -> Credentials {
        Credentials::default()
    }

    /// A token given as a value.
    pub fn token(secret: &str) -> Result<Credentials, AuthError> {
        let secret = secret.trim();
        if secret.is_empty() {
            return Err(AuthError::Token("empty token".into()));
        }
        let header = format!("Bearer {secret}")
            .parse()
            .map_err(|_| AuthError::Token("the token must be printable ASCII".into()))?;
        Ok(Credentials {
            header: Some(header),
        })
    }

    /// The token from `file` (its first line) if given, else from `WAVESPLAT_TOKEN`, else
    /// none.
    pub fn from_file_or_env(file: Option<&Path>) -> Result<Credentials, AuthError> {
        if let Some(path) = file {
            let text = std::fs::read_to_string(path).map_err(|source| AuthError::Read {
                path: path.display().to_string(),
                source,
            })?;
            return Credentials::token(text.lines().next().unwrap_or(""));
        }
        match std::env::var(TOKEN_ENV) {
            Ok(t) if !t.trim().is_empty() => Credentials::token(&t),
            _ => Ok(Credentials::none()),
        }
    }

    /// Whether a token is set.
    pub fn is_set(&self) -> bool {
        self.header.is_some()
    }
}

impl tonic::service::Interceptor for Credentials {
    fn call(&mut self, mut req: tonic::Request<()>) -> Result<tonic::Request<()>, Status> {
        if let Some(h) = &self.header {
            req.metadata_mut().insert("authorization", h.clone());
        }
        Ok(req)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const FILE: &str = "# who roles secret\n\
        viewer read 0123456789abcdef-viewer\n\
        ops write,worker 0123456789abcdef-ops\n\
        \n\
        root admin 0123456789abcdef-root\n";

    #[test]
    fn tokens_parse_authenticate_and_carry_roles() {
        let t = Tokens::parse(FILE).unwrap();
        assert_eq!(t.len(), 3);
        let v = t.authenticate("0123456789abcdef-viewer").unwrap();
        assert_eq!(v.identity, "viewer");
        assert!(v.has(Role::Read) && !v.has(Role::Write) && !v.has(Role::Admin));
        let o = t.authenticate("0123456789abcdef-ops").unwrap();
        assert!(o.has(Role::Write) && o.has(Role::Worker) && !o.has(Role::Read));
        // `write` implies `ingest`; `ingest` grants nothing else.
        assert!(o.has(Role::Ingest));
        let i = Tokens::parse("w worker,ingest 0123456789abcdef-w")
            .unwrap()
            .authenticate("0123456789abcdef-w")
            .unwrap();
        assert!(i.has(Role::Ingest) && i.has(Role::Worker));
        assert!(!i.has(Role::Write) && !i.has(Role::Read) && !i.has(Role::Admin));
        let r = t.authenticate("0123456789abcdef-root").unwrap();
        assert!([
            Role::Read,
            Role::Ingest,
            Role::Write,
            Role::Worker,
            Role::Admin
        ]
        .iter()
        .all(|&x| r.has(x)));
        for bad in [
            "",
            "0123456789abcdef-viewe",
            "0123456789abcdef-viewerx",
            "x",
        ] {
            assert!(t.authenticate(bad).is_none(), "{bad:?}");
        }
    }

    #[test]
    fn bad_token_files_are_refused_with_the_line() {
        for (text, want) in [
            ("a read", "line 1"),
            ("a reader 0123456789abcdef", "role"),
            ("a read short", "at least 16"),
            ("a read 0123456789abcdef\nb write 0123456789abcdef", "twice"),
        ] {
            let e = Tokens::parse(text).unwrap_err().to_string();
            assert!(e.contains(want), "{text:?}: {e}");
        }
    }

    #[test]
    fn credentials_come_from_a_file_or_the_environment() {
        let dir = std::env::temp_dir().join(format!("wavesplat-net-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let f = dir.join("token");
        std::fs::write(&f, "0123456789abcdef-viewer\n").unwrap();
        let c = Credentials::from_file_or_env(Some(&f)).unwrap();
        assert!(c.is_set());
        assert!(Credentials::token(" ").is_err());
        assert!(Credentials::token("a\u{7f}b").is_err());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
