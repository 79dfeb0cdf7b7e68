//! Transport security: TLS (rustls, through tonic) for servers and clients, the one place that
//! turns a URL into an endpoint, and the rule that keeps a server from being exposed by
//! accident.
//!
//! - `http://HOST:PORT` (or `HOST:PORT`) is plaintext; `https://HOST:PORT` is TLS, verified
//!   against the CA file given (`--ca`) or, without one, the system's roots. An `https://` URL
//!   never falls back to plaintext, so against a plaintext server it fails, saying so.
//! - A server serves TLS with a certificate chain and key in PEM ([`server_tls`]).
//! - [`check_exposure`]: a server bound to a non-loopback address needs TLS and authentication
//!   unless told `--insecure`.
//! - [`explain_connect_error`], [`explain_status`]: a client's transport failure in words — a
//!   TLS server reached in plaintext, a plaintext server reached over TLS, or a web server that
//!   is no wavesplat service (a published volume is browsed by its URL instead).

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::Duration;
use thiserror::Error;
use tonic::transport::{Certificate, ClientTlsConfig, Endpoint, Identity, ServerTlsConfig};

/// Errors setting up transport security.
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum TlsError {
    /// A PEM file could not be read.
    #[error("reading {what} {path}: {source}")]
    Read {
        /// What the file is.
        what: &'static str,
        /// The file.
        path: PathBuf,
        /// Why.
        #[source]
        source: std::io::Error,
    },
    /// The URL is not a service address.
    #[error("invalid URL {url:?}: {reason}")]
    Url {
        /// The URL.
        url: String,
        /// What is wrong.
        reason: String,
    },
    /// Serving on a reachable address without TLS and authentication.
    #[error(
        "refusing to serve on {addr} without {missing}: anyone who can reach it could read or \
         change everything. Give --tls-cert/--tls-key and --tokens, bind a loopback address, \
         or pass --insecure if the network is trusted"
    )]
    Exposed {
        /// The address.
        addr: SocketAddr,
        /// What is missing.
        missing: &'static str,
    },
}

fn read(what: &'static str, path: &Path) -> Result<Vec<u8>, TlsError> {
    std::fs::read(path).map_err(|source| TlsError::Read {
        what,
        path: path.to_path_buf(),
        source,
    })
}

/// A server's TLS settings from a PEM certificate chain and a PEM private key.
pub fn server_tls(cert: &Path, key: &Path) -> Result<ServerTlsConfig, TlsError> {
    let identity = Identity::from_pem(read("certificate", cert)?, read("private key", key)?);
    Ok(ServerTlsConfig::new().identity(identity))
}

/// The endpoint of a service URL with the settings every client uses: TLS for `https://`
/// (against the PEM CA `ca`, or the system's roots), plaintext for `http://`. Returns the
/// normalised URL too.
pub fn endpoint(url: &str, ca: Option<&Path>) -> Result<(String, Endpoint), TlsError> {
    let bad = |reason: &str| TlsError::Url {
        url: url.to_string(),
        reason: reason.to_string(),
    };
    let trimmed = url.trim();
    if trimmed.is_empty() {
        return Err(bad("empty"));
    }
    let (tls, url) = match trimmed.split_once("://") {
        None => (false, format!("http://{trimmed}")),
        Some(("http", rest)) if !rest.is_empty() => (false, trimmed.to_string()),
        Some(("https", rest)) if !rest.is_empty() => (true, trimmed.to_string()),
        Some(_) => {
            return Err(bad(
                "expected http://HOST:PORT, https://HOST:PORT or HOST:PORT",
            ))
        }
    };
    let mut ep = Endpoint::from_shared(url.clone())
        .map_err(|e| bad(&e.to_string()))?
        .connect_timeout(Duration::from_secs(5))
        .tcp_nodelay(true);
    if tls {
        let mut cfg = ClientTlsConfig::new().assume_http2(true);
        cfg = match ca {
            Some(ca) => cfg.ca_certificate(Certificate::from_pem(read("CA certificate", ca)?)),
            None => cfg.with_native_roots(),
        };
        ep = ep.tls_config(cfg).map_err(|e| bad(&e.to_string()))?;
    } else if ca.is_some() {
        return Err(bad(
            "a CA certificate was given for a plaintext http:// URL; use https://",
        ));
    }
    Ok((url, ep))
}

/// The chain of causes of a transport error, for people (tonic's own message is only
/// "transport error"): tells a TLS handshake that failed against a plaintext server apart from
/// a refused connection.
pub fn describe(e: &(dyn std::error::Error + 'static)) -> String {
    let mut out = e.to_string();
    let mut source = e.source();
    while let Some(s) = source {
        let m = s.to_string();
        if !out.contains(&m) {
            out.push_str(": ");
            out.push_str(&m);
        }
        source = s.source();
    }
    out
}

/// Why connecting to `url` failed, for people: the causes ([`describe`]), and for an
/// `https://` URL whose server does not answer in TLS, or refuses HTTP/2 in the handshake (a web
/// server), that likely cause in words.
pub fn explain_connect_error(url: &str, e: &(dyn std::error::Error + 'static)) -> String {
    let causes = describe(e);
    if !url.starts_with("https://") {
        causes
    } else if causes.contains("InvalidContentType") || causes.contains("corrupt message") {
        format!(
            "TLS handshake failed: the server did not answer in TLS (is it serving plaintext? \
             then use http://) ({causes})"
        )
    } else if causes.contains("NoApplicationProtocol") {
        format!(
            "the server at {url} is not a wavesplat cache or orchestrator (it refused HTTP/2, \
             which gRPC needs: a web server?); for a published .wspx use render or view with \
             its URL ({causes})"
        )
    } else {
        causes
    }
}

/// How long [`speaks_tls`] waits for the server's first bytes.
const PROBE_TIMEOUT: Duration = Duration::from_secs(2);

/// What a server answered a plaintext gRPC client's first bytes with.
#[derive(Debug, Clone, PartialEq, Eq)]
enum Answer {
    /// A TLS alert: the server speaks TLS.
    Tls,
    /// An HTTP/1 status line (a web server): the line.
    Http1(String),
}

/// What the server at `url` (a plaintext `http://` or bare URL) answers: sends the HTTP/2
/// connection preface, as a plaintext gRPC client does, and looks at the first bytes back. A TLS
/// server answers bytes it cannot parse with a TLS alert record (content type 21, version 3.x);
/// an HTTP/1 server (a web server) with a status line ("HTTP/1.1 400 Bad Request"); a plaintext
/// HTTP/2 server with a SETTINGS frame. Written here because no library tells these apart after
/// the fact: the gRPC client only reports "h2 protocol error" or "transport error".
async fn probe(url: &str) -> Option<Answer> {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let authority = url
        .trim()
        .strip_prefix("http://")
        .or_else(|| (!url.contains("://")).then_some(url.trim()))?;
    let authority = authority.split('/').next().unwrap_or(authority);
    let probe = async {
        let mut s = tokio::net::TcpStream::connect(authority).await.ok()?;
        s.write_all(b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n")
            .await
            .ok()?;
        let mut first = Vec::new();
        let mut buf = [0u8; 128];
        // A status line is short; a TLS record's header is 5 bytes.
        while first.len() < 3 || (first.starts_with(b"HTTP/") && !first.contains(&b'\n')) {
            let n = s.read(&mut buf).await.ok()?;
            if n == 0 || first.len() >= 256 {
                break;
            }
            first.extend_from_slice(&buf[..n]);
        }
        Some(first)
    };
    let first = tokio::time::timeout(PROBE_TIMEOUT, probe).await.ok()??;
    match first.as_slice() {
        [21 | 22, 3, ..] => Some(Answer::Tls),
        line if line.starts_with(b"HTTP/1") => {
            let line = String::from_utf8_lossy(line);
            let line = line.lines().next().unwrap_or_default().trim();
            Some(Answer::Http1(line.chars().take(80).collect()))
        }
        _ => None,
    }
}

/// Whether the server at `url` (a plaintext `http://` or bare URL) answers in TLS: it answers
/// the HTTP/2 connection preface with a TLS alert.
pub async fn speaks_tls(url: &str) -> bool {
    probe(url).await == Some(Answer::Tls)
}

/// A status of a call to `url` explained for people: a plaintext client whose call failed at
/// the transport (tonic says "h2 protocol error" or "transport error") against a server that
/// speaks TLS is told to use `https://` and `--ca`; a call to a web server (it answered HTTP/1,
/// over TLS not HTTP/2, or HTTP/2 without a gRPC status), that it is no wavesplat service and a
/// published volume is browsed by its URL. Other statuses are returned unchanged.
pub async fn explain_status(url: &str, status: tonic::Status) -> tonic::Status {
    let transport = matches!(
        status.code(),
        tonic::Code::Unknown | tonic::Code::Internal | tonic::Code::Unavailable
    );
    // An HTTP/2 server that is not gRPC (a web server): tonic maps its HTTP status, or fails
    // to read its page as gRPC messages.
    let message = status.message();
    let not_grpc = message.contains("grpc-status header missing")
        || (message.contains("while receiving response with status")
            && !message.contains("with status: 200"));
    if !transport && !not_grpc {
        return status;
    }
    let not_ours = |answered: &str| {
        tonic::Status::unavailable(format!(
            "the server at {url} is not a wavesplat cache or orchestrator ({answered}: a web \
             server?); for a published .wspx use render or view with its URL (the call failed: \
             {})",
            status.message()
        ))
    };
    if not_grpc {
        let http = match message.rfind("status: ") {
            Some(i) => format!("it answered HTTP {} without gRPC", &message[i + 8..]),
            None => "it answered HTTP without gRPC".to_string(),
        };
        return not_ours(&http);
    }
    if url.trim().starts_with("https://") {
        return if status.message().contains("h2 protocol error") {
            not_ours("it did not answer in HTTP/2, as gRPC does")
        } else {
            status
        };
    }
    match probe(url).await {
        Some(Answer::Tls) => tonic::Status::unavailable(format!(
            "the server at {url} speaks TLS: use https:// and --ca (the call failed: {})",
            status.message()
        )),
        Some(Answer::Http1(line)) => not_ours(&format!("it answered {line}")),
        None => status,
    }
}

/// Refuses a non-loopback `addr` without both TLS and authentication, unless `insecure`.
pub fn check_exposure(
    addr: SocketAddr,
    tls: bool,
    auth: bool,
    insecure: bool,
) -> Result<(), TlsError> {
    if insecure || addr.ip().is_loopback() {
        return Ok(());
    }
    let missing = match (tls, auth) {
        (true, true) => return Ok(()),
        (false, false) => "TLS and authentication",
        (false, true) => "TLS",
        (true, false) => "authentication",
    };
    Err(TlsError::Exposed { addr, missing })
}

/// Makes ring the process's TLS crypto provider (once; later calls do nothing). HTTP clients that
/// bring no provider of their own (the object-store client) need one installed; tonic's TLS uses
/// ring too, so the process has one provider.
pub fn install_crypto_provider() {
    let _ = rustls::crypto::ring::default_provider().install_default();
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn urls_pick_the_transport_and_bad_ones_are_refused() {
        assert_eq!(endpoint("h:1", None).unwrap().0, "http://h:1");
        assert_eq!(endpoint("http://h:1", None).unwrap().0, "http://h:1");
        assert_eq!(endpoint("https://h:1", None).unwrap().0, "https://h:1");
        for bad in ["", "ftp://h:1", "http://", "https://"] {
            assert!(endpoint(bad, None).is_err(), "{bad:?}");
        }
        let e = endpoint("http://h:1", Some(Path::new("/nonexistent.pem"))).unwrap_err();
        assert!(e.to_string().contains("https"), "{e}");
        let e = endpoint("https://h:1", Some(Path::new("/nonexistent.pem"))).unwrap_err();
        assert!(e.to_string().contains("CA certificate"), "{e}");
    }

    /// A plaintext gRPC call to a web server (it answers the HTTP/2 preface with an HTTP/1.1
    /// status line, as nginx does) is explained as such, not as "h2 protocol error".
    #[tokio::test]
    async fn a_web_server_is_told_apart_from_a_cache() {
        use std::io::{Read, Write};
        let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let url = format!("http://{}", listener.local_addr().unwrap());
        std::thread::spawn(move || {
            if let Ok((mut s, _)) = listener.accept() {
                let mut buf = [0u8; 64];
                let _ = s.read(&mut buf);
                let _ = s.write_all(
                    b"HTTP/1.1 400 Bad Request\r\nContent-Type: text/html\r\n\r\n<html></html>",
                );
            }
        });
        let failed = tonic::Status::internal("h2 protocol error: http2 error");
        let explained = explain_status(&url, failed).await;
        let m = explained.message();
        assert!(
            m.contains("not a wavesplat cache") && m.contains("HTTP/1.1 400 Bad Request"),
            "{m}"
        );
        assert!(m.contains("render or view"), "{m}");
        assert!(!speaks_tls(&url).await, "nobody listens any more");
        // An HTTP/2 web server answers a gRPC call with its page (as nginx with http2 does).
        let failed = tonic::Status::internal(
            "protocol error: received message with invalid compression flag: 60 (valid flags \
             are 0 and 1) while receiving response with status: 404 Not Found",
        );
        let m = explain_status(&url, failed).await.message().to_string();
        assert!(
            m.contains("not a wavesplat cache") && m.contains("HTTP 404 Not Found without gRPC"),
            "{m}"
        );
    }

    #[test]
    fn exposure_needs_tls_and_auth_or_insecure() {
        let public: SocketAddr = "0.0.0.0:1".parse().unwrap();
        let local: SocketAddr = "127.0.0.1:1".parse().unwrap();
        assert!(check_exposure(local, false, false, false).is_ok());
        assert!(check_exposure(public, true, true, false).is_ok());
        assert!(check_exposure(public, false, false, true).is_ok());
        for (tls, auth) in [(false, false), (true, false), (false, true)] {
            let e = check_exposure(public, tls, auth, false).unwrap_err();
            assert!(e.to_string().contains("--insecure"), "{e}");
        }
    }
}
