//! A published object and the client that reads it: byte ranges over HTTP(S) with reqwest
//! (TLS verified against a given CA or the system's roots, what may pass tried again a few times
//! with short pauses, what will not failing at once with its reason) or through an object store
//! for `s3://` URLs.

use super::RangeError;
use bytes::Bytes;
use object_store::path::Path as ObjectPath;
use object_store::ObjectStore;
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

/// Attempts of an HTTP request that fails in a way that may pass.
const HTTP_ATTEMPTS: u32 = 5;
/// The pause before the second attempt, doubled before each next one (0.1 + 0.2 + 0.4 + 0.8 s
/// in all).
const HTTP_FIRST_PAUSE: Duration = Duration::from_millis(100);
/// How long connecting may take (as the cache's client).
const HTTP_CONNECT_TIMEOUT: Duration = Duration::from_secs(5);
/// How long one request may take, body included (a coalesced request is at most 512 KiB).
const HTTP_REQUEST_TIMEOUT: Duration = Duration::from_secs(60);
/// Longest excerpt of a plain-text error body (characters).
const EXCERPT_CHARS: usize = 160;

/// A published object and the client that reads it.
#[derive(Clone)]
pub(super) enum Object {
    /// Any web server or CDN: GET with `Range`.
    Http {
        client: reqwest::Client,
        url: reqwest::Url,
        /// The CA given, for messages.
        ca: Option<PathBuf>,
    },
    /// An object store (S3 and compatibles), through its client.
    Store {
        store: Arc<dyn ObjectStore>,
        path: ObjectPath,
    },
}

/// How one attempt of an HTTP request failed.
enum Attempt {
    /// It may pass when tried again.
    Again(String),
    /// It will not.
    Final(RangeError),
}

/// What a failed HTTP request's error means: TLS failures are final, the rest may pass.
fn classify(e: reqwest::Error, ca: Option<&Path>) -> Attempt {
    let e = e.without_url();
    let causes = wavesplat_net::tls::describe(&e);
    if causes.contains("InvalidContentType") || causes.contains("corrupt message") {
        Attempt::Final(RangeError::NotTls)
    } else if causes.contains("UnknownIssuer") {
        Attempt::Final(RangeError::UnknownIssuer {
            ca: ca.map(Path::to_path_buf),
        })
    } else if [
        "invalid peer certificate",
        "received fatal alert",
        "peer is incompatible",
    ]
    .iter()
    .any(|m| causes.contains(m))
    {
        Attempt::Final(RangeError::Tls(causes))
    } else {
        Attempt::Again(causes)
    }
}

/// `Content-Range: bytes START-END/TOTAL` as (START, END + 1, TOTAL when known).
fn content_range(value: &str) -> Option<(u64, u64, Option<u64>)> {
    let (range, total) = value.trim().strip_prefix("bytes ")?.split_once('/')?;
    let (start, end) = range.split_once('-')?;
    let (start, end): (u64, u64) = (start.trim().parse().ok()?, end.trim().parse().ok()?);
    let total = match total.trim() {
        "*" => None,
        t => Some(t.parse().ok()?),
    };
    (start <= end).then_some((start, end + 1, total))
}

/// The first line of a plain-text body, cut short; nothing for any other body (an HTML error
/// page says no more than its status).
async fn excerpt(mut response: reqwest::Response) -> Option<String> {
    let plain = response
        .headers()
        .get(reqwest::header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|t| t.trim_start().starts_with("text/plain"));
    if !plain {
        return None;
    }
    let mut body = Vec::new();
    while body.len() < 1024 {
        match response.chunk().await {
            Ok(Some(c)) => body.extend_from_slice(&c),
            _ => break,
        }
    }
    let text = String::from_utf8_lossy(&body);
    let line = text.lines().map(str::trim).find(|l| !l.is_empty())?;
    Some(
        line.chars()
            .filter(|c| !c.is_control())
            .take(EXCERPT_CHARS)
            .collect(),
    )
}

impl Object {
    /// The object at `url`: `http(s)://host/dir/file` (any web server or CDN; TLS verified
    /// against the PEM CA `ca`, else the system's roots) or `s3://bucket/key` (endpoint,
    /// region and credentials from the `AWS_*` variables).
    pub(super) fn open(url: &str, ca: Option<&Path>) -> Result<Object, RangeError> {
        wavesplat_net::tls::install_crypto_provider();
        let parsed = url::Url::parse(url).map_err(|e| RangeError::Url(e.to_string()))?;
        let ca_error = |ca: &Path, reason: String| RangeError::Ca {
            path: ca.to_path_buf(),
            reason,
        };
        if parsed.scheme() == "http" && ca.is_some() {
            return Err(RangeError::CaWithoutTls);
        }
        let pem = match ca {
            Some(ca) => Some(std::fs::read(ca).map_err(|e| ca_error(ca, e.to_string()))?),
            None => None,
        };
        match parsed.scheme() {
            "http" | "https" => {
                if parsed.path().ends_with('/') || parsed.path().is_empty() {
                    return Err(RangeError::Url("no file name".into()));
                }
                let mut builder = reqwest::Client::builder()
                    .connect_timeout(HTTP_CONNECT_TIMEOUT)
                    .timeout(HTTP_REQUEST_TIMEOUT)
                    .user_agent(concat!("wavesplat/", env!("CARGO_PKG_VERSION")));
                // Only the CA given, as the cache's client trusts it.
                if let Some(ca) = ca {
                    let certs =
                        reqwest::Certificate::from_pem_bundle(pem.as_deref().unwrap_or_default())
                            .map_err(|e| ca_error(ca, wavesplat_net::tls::describe(&e)))?;
                    if certs.is_empty() {
                        return Err(ca_error(ca, "no PEM certificate in it".into()));
                    }
                    builder = builder.tls_certs_only(certs);
                }
                let client = builder
                    .build()
                    .map_err(|e| RangeError::Tls(wavesplat_net::tls::describe(&e)))?;
                Ok(Object::Http {
                    client,
                    url: parsed,
                    ca: ca.map(Path::to_path_buf),
                })
            }
            "s3" | "s3a" => {
                let mut builder = object_store::aws::AmazonS3Builder::from_env();
                if let Some(ca) = ca {
                    // The client settings the AWS_* variables give, and the CA alone.
                    let mut options = object_store::ClientOptions::new();
                    for (key, value) in std::env::vars() {
                        if let Some(key) = key.strip_prefix("AWS_") {
                            if let Ok(object_store::aws::AmazonS3ConfigKey::Client(k)) =
                                format!("aws_{}", key.to_ascii_lowercase()).parse()
                            {
                                options = options.with_config(k, value);
                            }
                        }
                    }
                    let certs = object_store::Certificate::from_pem_bundle(
                        pem.as_deref().unwrap_or_default(),
                    )
                    .map_err(|e| ca_error(ca, e.to_string()))?;
                    if certs.is_empty() {
                        return Err(ca_error(ca, "no PEM certificate in it".into()));
                    }
                    for c in certs {
                        options = options.with_root_certificate(c);
                    }
                    builder =
                        builder.with_client_options(options.with_no_system_certificates(true));
                }
                let store = builder
                    .with_url(url)
                    .build()
                    .map_err(|e| RangeError::Store(e.to_string()))?;
                let path = ObjectPath::from_url_path(parsed.path())
                    .map_err(|e| RangeError::Url(format!("key: {e}")))?;
                Ok(Object::Store {
                    store: Arc::new(store),
                    path,
                })
            }
            other => Err(RangeError::Url(format!(
                "scheme {other:?}; use http(s)://… or s3://bucket/key"
            ))),
        }
    }

    /// Bytes `range` of the object (the server cuts it at the object's end), or the whole
    /// object for `None`; and the object's size.
    pub(super) async fn read(&self, range: Option<Range<u64>>) -> Result<(Bytes, u64), RangeError> {
        match self {
            Object::Http { client, url, ca } => {
                let mut pause = HTTP_FIRST_PAUSE;
                let mut attempt = 1;
                loop {
                    match Self::http_once(client, url, ca.as_deref(), range.clone()).await {
                        Ok(got) => return Ok(got),
                        Err(Attempt::Final(e)) => return Err(e),
                        Err(Attempt::Again(reason)) if attempt >= HTTP_ATTEMPTS => {
                            return Err(RangeError::Transfer {
                                reason,
                                attempts: attempt,
                            })
                        }
                        Err(Attempt::Again(reason)) => {
                            tracing::info!(
                                %url, attempt, %reason,
                                "range request failed, trying again"
                            );
                            tokio::time::sleep(pause).await;
                            pause *= 2;
                            attempt += 1;
                        }
                    }
                }
            }
            Object::Store { store, path } => {
                let options = object_store::GetOptions {
                    range: range.map(object_store::GetRange::Bounded),
                    ..Default::default()
                };
                let failed = |e: object_store::Error| {
                    let status = |s: &str| RangeError::Status {
                        status: s.into(),
                        excerpt: None,
                    };
                    match e {
                        object_store::Error::NotFound { .. } => status("404 Not Found"),
                        object_store::Error::PermissionDenied { .. } => status("403 Forbidden"),
                        object_store::Error::Unauthenticated { .. } => status("401 Unauthorized"),
                        e => RangeError::Store(e.to_string()),
                    }
                };
                let got = store.get_opts(path, options).await.map_err(failed)?;
                let size = got.meta.size;
                Ok((got.bytes().await.map_err(failed)?, size))
            }
        }
    }

    /// One attempt of an HTTP GET (see [`Object::read`]).
    async fn http_once(
        client: &reqwest::Client,
        url: &reqwest::Url,
        ca: Option<&Path>,
        range: Option<Range<u64>>,
    ) -> Result<(Bytes, u64), Attempt> {
        let mut request = client.get(url.clone());
        if let Some(r) = &range {
            request = request.header(
                reqwest::header::RANGE,
                format!("bytes={}-{}", r.start, r.end.saturating_sub(1)),
            );
        }
        let response = request.send().await.map_err(|e| classify(e, ca))?;
        let status = response.status();
        let body = |response: reqwest::Response| async move {
            response.bytes().await.map_err(|e| classify(e, ca))
        };
        match (status, range) {
            (reqwest::StatusCode::PARTIAL_CONTENT, Some(asked)) => {
                let answer = response
                    .headers()
                    .get(reqwest::header::CONTENT_RANGE)
                    .and_then(|v| v.to_str().ok())
                    .unwrap_or_default()
                    .to_string();
                match content_range(&answer) {
                    Some((start, _, Some(total))) if start == asked.start => {
                        Ok((body(response).await?, total))
                    }
                    _ => Err(Attempt::Final(RangeError::ContentRange { asked, answer })),
                }
            }
            (reqwest::StatusCode::OK, None) => {
                let bytes = body(response).await?;
                let size = bytes.len() as u64;
                Ok((bytes, size))
            }
            // The whole object for a range from its start that holds all of it: as good.
            (reqwest::StatusCode::OK, Some(asked))
                if asked.start == 0
                    && response.content_length().is_some_and(|n| n <= asked.end) =>
            {
                let bytes = body(response).await?;
                let size = bytes.len() as u64;
                Ok((bytes, size))
            }
            (reqwest::StatusCode::OK, Some(asked)) => {
                Err(Attempt::Final(RangeError::RangeIgnored { asked }))
            }
            (s, _)
                if s.is_server_error()
                    || s == reqwest::StatusCode::TOO_MANY_REQUESTS
                    || s == reqwest::StatusCode::REQUEST_TIMEOUT =>
            {
                Err(Attempt::Again(format!("the server answered {s}")))
            }
            (s, _) => Err(Attempt::Final(RangeError::Status {
                status: s.to_string(),
                excerpt: excerpt(response).await,
            })),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn content_ranges_and_statuses_read_as_said() {
        assert_eq!(
            content_range("bytes 0-65535/284442"),
            Some((0, 65536, Some(284442)))
        );
        assert_eq!(content_range("bytes 10-19/*"), Some((10, 20, None)));
        for bad in ["", "bytes 5-4/10", "items 0-1/2", "bytes 0-x/2"] {
            assert_eq!(content_range(bad), None, "{bad:?}");
        }
        let page = RangeError::Status {
            status: "404 Not Found".into(),
            excerpt: None,
        };
        assert_eq!(page.to_string(), "the server answered 404 Not Found");
        let plain = RangeError::Status {
            status: "403 Forbidden".into(),
            excerpt: Some("private".into()),
        };
        assert_eq!(
            plain.to_string(),
            "the server answered 403 Forbidden: \"private\""
        );
        assert!(RangeError::UnknownIssuer { ca: None }
            .to_string()
            .contains("--ca"));
    }
}
