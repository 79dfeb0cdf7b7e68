//! A published object and the client that reads it: byte ranges over HTTP(S) with reqwest
//! (TLS verified against a given CA or the system's roots, what may pass tried again a few times
//! with growing, jittered pauses or as long as the server's `Retry-After` says, what will not
//! failing at once with its reason) or through an object store for `s3://` URLs.
//!
//! Every answer is held to what was asked: a 206 to its range (`Content-Range` and
//! `Content-Length` no longer than asked, the body as long as its `Content-Range`, read with a
//! cap), a 200 only to a read of the whole object (or of a range from its start that holds all
//! of it), never a compressed body. The object's size and strong `ETag` as first seen are kept:
//! a later answer for another size or `ETag` means the file changed on the server, which no
//! retry mends (no `If-Match` is sent: each answer's headers are compared instead, and some
//! servers and S3 gateways answer 412 to an `ETag` that matches). A body that breaks or stalls (no byte for the
//! read timeout) is asked for again from where it broke.

use super::{redacted, RangeError};
use crate::source::SourceError;
use bytes::Bytes;
use object_store::path::Path as ObjectPath;
use object_store::ObjectStore;
use reqwest::header::{self, HeaderMap};
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::{Arc, OnceLock};
use std::time::{Duration, SystemTime};

/// Attempts of an HTTP request that fails in a way that may pass (counted again after any
/// attempt that brought bytes).
const HTTP_ATTEMPTS: u32 = 5;
/// The pause before the second attempt, doubled before each next one (jittered, see
/// [`backoff`]).
const HTTP_FIRST_PAUSE: Duration = Duration::from_millis(250);
/// The longest pause of a back-off.
pub(super) const MAX_PAUSE: Duration = Duration::from_secs(10);
/// The longest `Retry-After` waited for.
const RETRY_AFTER_CAP: Duration = Duration::from_secs(60);
/// How long connecting may take (as the cache's client).
const HTTP_CONNECT_TIMEOUT: Duration = Duration::from_secs(5);
/// How long an answer may stay silent (its headers, or the next bytes of its body) before the
/// attempt is given up; a slow but steady transfer takes as long as it needs.
const HTTP_READ_TIMEOUT: Duration = Duration::from_secs(20);
/// The first pause of a browse after a read failed every attempt (doubled up to
/// [`MAX_PAUSE`] while the failures go on).
const OUTAGE_FIRST_PAUSE: Duration = Duration::from_secs(1);
/// Longest excerpt of an error body (characters).
const EXCERPT_CHARS: usize = 160;
/// Most bytes of an error body read for its excerpt.
const EXCERPT_BYTES: usize = 1024;
/// Most bytes reserved ahead for a body from its announced length (a larger one grows as it
/// comes).
const RESERVE_CAP: u64 = 64 << 20;

/// How an object's reads are paced: the defaults above; tests shorten them.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct Pacing {
    /// Attempts of an HTTP request that fails in a way that may pass.
    pub(super) attempts: u32,
    /// The pause before the second attempt (doubled before each next one).
    pub(super) first_pause: Duration,
    /// How long an answer may stay silent.
    pub(super) read_timeout: Duration,
    /// The first pause of a browse after a read failed every attempt.
    pub(super) outage_pause: Duration,
}

impl Default for Pacing {
    fn default() -> Self {
        Pacing {
            attempts: HTTP_ATTEMPTS,
            first_pause: HTTP_FIRST_PAUSE,
            read_timeout: HTTP_READ_TIMEOUT,
            outage_pause: OUTAGE_FIRST_PAUSE,
        }
    }
}

/// A published object and the client that reads it.
#[derive(Clone)]
pub(super) struct Object {
    kind: Kind,
    /// The object as its first answer described it (shared by every clone).
    first: Arc<OnceLock<Version>>,
    /// How its reads are paced.
    pub(super) pacing: Pacing,
}

#[derive(Clone)]
enum Kind {
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

/// What identifies one version of the object: its size, its strong `ETag` and its
/// `Last-Modified` (compared only when neither answer has a strong `ETag`).
#[derive(Debug, Clone, PartialEq, Eq)]
struct Version {
    size: u64,
    etag: Option<String>,
    last_modified: Option<String>,
}

/// Why a read failed.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub(super) enum ReadError {
    /// What the server answered, or why no answer came (final).
    #[error(transparent)]
    Range(#[from] RangeError),
    /// The server could not be reached, or the transfer broke, every time it was tried: it
    /// may pass later.
    #[error(
        "{reason} (tried {attempts} times{})",
        .retry_after.map_or(String::new(), |w| format!("; the server asks to wait {} s", w.as_secs()))
    )]
    Transfer {
        /// The last failure.
        reason: String,
        /// Attempts made.
        attempts: u32,
        /// How long the server asked to wait (`Retry-After`, capped), if it said.
        retry_after: Option<Duration>,
    },
    /// The object is not the one first read.
    #[error("URL changed on the server since it was opened: reopen it ({0})")]
    Changed(String),
    /// The body came compressed: its bytes are not the file's.
    #[error(
        "the server sent the body with Content-Encoding {0:?}, not the file's bytes as they are; \
         serve the volume without compression"
    )]
    Encoded(String),
    /// The server announced or sent more bytes than asked for.
    #[error("asked for bytes {}..{}, the server {said}", .asked.start, .asked.end)]
    Length {
        /// The range asked for.
        asked: Range<u64>,
        /// What it announced or sent.
        said: String,
    },
}

impl ReadError {
    /// Whether asking again later cannot help (a transfer that failed every attempt, or an
    /// object store's own failure after its retries, may pass).
    pub(super) fn is_final(&self) -> bool {
        !matches!(
            self,
            ReadError::Transfer { .. } | ReadError::Range(RangeError::Store(_))
        )
    }

    /// How long the server asked to wait before asking again, if it said.
    pub(super) fn retry_after(&self) -> Option<Duration> {
        match self {
            ReadError::Transfer { retry_after, .. } => *retry_after,
            _ => None,
        }
    }
}

impl From<ReadError> for SourceError {
    fn from(e: ReadError) -> Self {
        match e {
            ReadError::Range(e) => SourceError::Range(e),
            ReadError::Transfer {
                reason, attempts, ..
            } => SourceError::Range(RangeError::Transfer { reason, attempts }),
            e => SourceError::Remote(e.to_string()),
        }
    }
}

/// How one attempt of an HTTP request failed.
enum Attempt {
    /// It may pass when tried again (after `retry_after`, when the server said).
    Again {
        reason: String,
        retry_after: Option<Duration>,
    },
    /// It will not.
    Final(ReadError),
}

impl Attempt {
    /// A failure that may pass, the server having said nothing of when.
    fn again(reason: String) -> Attempt {
        Attempt::Again {
            reason,
            retry_after: None,
        }
    }
}

impl From<RangeError> for Attempt {
    fn from(e: RangeError) -> Self {
        Attempt::Final(e.into())
    }
}

impl From<ReadError> for Attempt {
    fn from(e: ReadError) -> Self {
        Attempt::Final(e)
    }
}

/// What a failed HTTP request's error means: TLS failures are final, the rest may pass.
fn classify(e: reqwest::Error, ca: Option<&Path>) -> Attempt {
    let e = e.without_url();
    let causes = wavesplat_net::tls::describe(&e);
    if causes.contains("InvalidContentType") || causes.contains("corrupt message") {
        RangeError::NotTls.into()
    } else if causes.contains("UnknownIssuer") {
        RangeError::UnknownIssuer {
            ca: ca.map(Path::to_path_buf),
        }
        .into()
    } else if [
        "invalid peer certificate",
        "received fatal alert",
        "peer is incompatible",
    ]
    .iter()
    .any(|m| causes.contains(m))
    {
        RangeError::Tls(causes).into()
    } else {
        Attempt::again(causes)
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
    (start <= end && end < u64::MAX).then_some((start, end + 1, total))
}

/// A pause of about `first` doubled `attempt - 1` times (at most [`MAX_PAUSE`]), jittered
/// between half of it and all of it so that clients that failed together do not come back
/// together.
pub(super) fn backoff(first: Duration, attempt: u32) -> Duration {
    let full = first
        .saturating_mul(1 << attempt.saturating_sub(1).min(20))
        .min(MAX_PAUSE);
    full / 2 + full.mul_f64(random_fraction() / 2.0)
}

/// A number in [0, 1) that differs from call to call (std's randomly keyed hasher, so no
/// dependency for a pause's jitter).
fn random_fraction() -> f64 {
    use std::hash::BuildHasher;
    let h = std::collections::hash_map::RandomState::new().hash_one(std::time::Instant::now());
    (h >> 11) as f64 / (1u64 << 53) as f64
}

/// A `Retry-After` value (delta-seconds or an HTTP-date) as the wait from `now`, at most
/// [`RETRY_AFTER_CAP`]; `None` when it is neither.
fn retry_after(value: &str, now: SystemTime) -> Option<Duration> {
    let value = value.trim();
    let wait = if !value.is_empty() && value.bytes().all(|b| b.is_ascii_digit()) {
        // Digits past u64 are a wait past any cap.
        Duration::from_secs(value.parse().unwrap_or(u64::MAX))
    } else {
        http_date(value)?
            .duration_since(now)
            .unwrap_or(Duration::ZERO)
    };
    Some(wait.min(RETRY_AFTER_CAP))
}

/// An HTTP-date in any of its three forms (`Sun, 06 Nov 1994 08:49:37 GMT`, `Sunday,
/// 06-Nov-94 08:49:37 GMT`, `Sun Nov  6 08:49:37 1994`), by the `httpdate` crate (hyper's).
fn http_date(value: &str) -> Option<SystemTime> {
    httpdate::parse_http_date(value).ok()
}

/// A header's value as text, if it has one.
fn header_text(headers: &HeaderMap, name: header::HeaderName) -> Option<&str> {
    headers
        .get(name)
        .and_then(|v| v.to_str().ok())
        .map(str::trim)
}

/// The object version an answer describes, for an object of `size` bytes.
fn version_of(headers: &HeaderMap, size: u64) -> Version {
    Version {
        size,
        etag: header_text(headers, header::ETAG)
            .filter(|e| !e.starts_with("W/"))
            .map(str::to_string),
        last_modified: header_text(headers, header::LAST_MODIFIED).map(str::to_string),
    }
}

/// Refuses a body with a `Content-Encoding` other than `identity`: its bytes are not the
/// file's.
fn check_encoding(headers: &HeaderMap) -> Result<(), ReadError> {
    let Some(value) = headers.get(header::CONTENT_ENCODING) else {
        return Ok(());
    };
    let text = String::from_utf8_lossy(value.as_bytes());
    if text
        .split(',')
        .map(str::trim)
        .all(|t| t.is_empty() || t.eq_ignore_ascii_case("identity"))
    {
        return Ok(());
    }
    Err(ReadError::Encoded(
        text.trim()
            .chars()
            .filter(|c| !c.is_control())
            .take(40)
            .collect(),
    ))
}

/// The text of the first `<tag>…</tag>` in `xml`, entities undone.
fn xml_text(xml: &str, tag: &str) -> Option<String> {
    let open = format!("<{tag}>");
    let from = xml.find(&open)? + open.len();
    let to = from + xml[from..].find(&format!("</{tag}>"))?;
    let text = xml[from..to]
        .replace("&lt;", "<")
        .replace("&gt;", ">")
        .replace("&quot;", "\"")
        .replace("&apos;", "'")
        .replace("&amp;", "&");
    let text = text.trim();
    (!text.is_empty()).then(|| text.to_string())
}

/// What an error body says, cut short: the first line of plain text, or an XML error's
/// `<Code>` and `<Message>` (as S3 and its compatibles answer); nothing for any other body
/// (an HTML error page says no more than its status) or a compressed one.
async fn excerpt(mut response: reqwest::Response) -> Option<String> {
    let kind = header_text(response.headers(), header::CONTENT_TYPE)
        .unwrap_or_default()
        .to_ascii_lowercase();
    let kind = kind
        .split(';')
        .next()
        .unwrap_or_default()
        .trim()
        .to_string();
    let xml = kind == "application/xml" || kind == "text/xml" || kind.ends_with("+xml");
    if !(xml || kind == "text/plain") || check_encoding(response.headers()).is_err() {
        return None;
    }
    let mut body = Vec::new();
    while body.len() < EXCERPT_BYTES {
        match response.chunk().await {
            Ok(Some(c)) => body.extend_from_slice(&c),
            _ => break,
        }
    }
    body.truncate(EXCERPT_BYTES);
    let text = String::from_utf8_lossy(&body);
    let said = if xml {
        match (xml_text(&text, "Code"), xml_text(&text, "Message")) {
            (Some(c), Some(m)) => format!("{c}: {m}"),
            (Some(t), None) | (None, Some(t)) => t,
            (None, None) => return None,
        }
    } else {
        text.lines()
            .map(str::trim)
            .find(|l| !l.is_empty())?
            .to_string()
    };
    Some(
        said.chars()
            .filter(|c| !c.is_control())
            .take(EXCERPT_CHARS)
            .collect(),
    )
}

/// A read over HTTP in progress: what is asked and what has come.
struct Progress {
    /// The first byte asked for.
    start: u64,
    /// One past the last byte asked for (`None`: to the object's end).
    end: Option<u64>,
    /// The bytes received, from `start`.
    buf: Vec<u8>,
    /// The object's size, once an answer said it.
    size: Option<u64>,
}

impl Progress {
    /// The object's size when everything asked for (cut at the object's end) has come.
    fn done(&self) -> Option<u64> {
        let size = self.size?;
        let end = self.end.map_or(size, |e| e.min(size));
        (self.start + self.buf.len() as u64 >= end).then_some(size)
    }
}

/// Reads `response`'s body onto `buf`: at most `want` bytes (more is refused, as `asked` says),
/// exactly `want` when `exact` (fewer: the transfer broke, and may pass when asked again for
/// the rest). What came before a failure stays in `buf`.
async fn read_body(
    response: &mut reqwest::Response,
    buf: &mut Vec<u8>,
    want: Option<u64>,
    exact: bool,
    asked: Range<u64>,
    ca: Option<&Path>,
) -> Result<(), Attempt> {
    let start = buf.len();
    if let Some(w) = want {
        buf.reserve(w.min(RESERVE_CAP) as usize);
    }
    loop {
        match response.chunk().await {
            Ok(Some(c)) => {
                let got = (buf.len() - start + c.len()) as u64;
                if let Some(w) = want.filter(|&w| got > w) {
                    return Err(ReadError::Length {
                        asked,
                        said: format!("sent more than the {w} bytes it announced"),
                    }
                    .into());
                }
                buf.extend_from_slice(&c);
            }
            Ok(None) => break,
            Err(e) => return Err(classify(e, ca)),
        }
    }
    let got = (buf.len() - start) as u64;
    match want {
        Some(w) if exact && got < w => Err(Attempt::again(format!(
            "the body ended after {got} of its {w} bytes"
        ))),
        _ => Ok(()),
    }
}

impl Object {
    /// The object at `url`: `http(s)://host/dir/file` (any web server or CDN; TLS verified
    /// against the PEM CA `ca`, else the system's roots) or `s3://bucket/key` (endpoint,
    /// region and credentials from the `AWS_*` variables).
    pub(super) fn open(url: &str, ca: Option<&Path>) -> Result<Object, RangeError> {
        Object::open_paced(url, ca, Pacing::default())
    }

    /// [`Object::open`] with its reads paced as `pacing` says.
    pub(super) fn open_paced(
        url: &str,
        ca: Option<&Path>,
        pacing: Pacing,
    ) -> Result<Object, RangeError> {
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
        let kind = match parsed.scheme() {
            "http" | "https" => {
                if parsed.path().ends_with('/') || parsed.path().is_empty() {
                    return Err(RangeError::Url("no file name".into()));
                }
                // No total timeout: a whole object on a slow link takes what it takes, and
                // an answer that stalls is given up after the read timeout.
                let mut builder = reqwest::Client::builder()
                    .connect_timeout(HTTP_CONNECT_TIMEOUT)
                    .read_timeout(pacing.read_timeout)
                    .referer(false)
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
                Kind::Http {
                    client,
                    url: parsed,
                    ca: ca.map(Path::to_path_buf),
                }
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
                // The builder's errors quote the URL as given: they are shown with it redacted.
                let store = builder
                    .with_url(url)
                    .build()
                    .map_err(|e| RangeError::Store(e.to_string().replace(url, &redacted(url))))?;
                let path = ObjectPath::from_url_path(parsed.path())
                    .map_err(|e| RangeError::Url(format!("key: {e}")))?;
                Kind::Store {
                    store: Arc::new(store),
                    path,
                }
            }
            other => {
                return Err(RangeError::Url(format!(
                    "scheme {other:?}; use http(s)://… or s3://bucket/key"
                )))
            }
        };
        Ok(Object {
            kind,
            first: Arc::new(OnceLock::new()),
            pacing,
        })
    }

    /// The object at `path` in `store`.
    #[cfg(test)]
    pub(super) fn store(store: Arc<dyn ObjectStore>, path: ObjectPath) -> Object {
        Object {
            kind: Kind::Store { store, path },
            first: Arc::new(OnceLock::new()),
            pacing: Pacing::default(),
        }
    }

    /// Bytes `range` of the object (the server cuts it at the object's end), or the whole
    /// object for `None`; and the object's size. Every answer is held to the object as the
    /// first described it ([`ReadError::Changed`] otherwise).
    pub(super) async fn read(&self, range: Option<Range<u64>>) -> Result<(Bytes, u64), ReadError> {
        let (bytes, size) = self.read_vec(range).await?;
        Ok((Bytes::from(bytes), size))
    }

    /// [`Object::read`] into a vector of its own.
    pub(super) async fn read_vec(
        &self,
        range: Option<Range<u64>>,
    ) -> Result<(Vec<u8>, u64), ReadError> {
        match &self.kind {
            Kind::Http { client, url, ca } => {
                self.read_http(client, url, ca.as_deref(), range).await
            }
            Kind::Store { store, path } => self.read_store(store.as_ref(), path, range).await,
        }
    }

    /// Holds an answer's `version` to the object's first: a change is final.
    fn check(&self, version: Version) -> Result<(), ReadError> {
        let first = self.first.get_or_init(|| version.clone());
        if first.size != version.size {
            return Err(ReadError::Changed(format!(
                "it held {} bytes, now {}",
                first.size, version.size
            )));
        }
        match (&first.etag, &version.etag) {
            (Some(a), Some(b)) if a != b => {
                Err(ReadError::Changed(format!("its ETag was {a}, now {b}")))
            }
            (None, None) => match (&first.last_modified, &version.last_modified) {
                (Some(a), Some(b)) if a != b => {
                    Err(ReadError::Changed(format!("last modified {a}, now {b}")))
                }
                _ => Ok(()),
            },
            _ => Ok(()),
        }
    }

    /// [`Object::read_vec`] over HTTP: attempts that may pass are tried again (after the
    /// server's `Retry-After`, or a growing jittered pause), each from where the last one's
    /// bytes ended; the count of attempts starts over after one that brought bytes.
    async fn read_http(
        &self,
        client: &reqwest::Client,
        url: &reqwest::Url,
        ca: Option<&Path>,
        range: Option<Range<u64>>,
    ) -> Result<(Vec<u8>, u64), ReadError> {
        let mut got = Progress {
            start: range.as_ref().map_or(0, |r| r.start),
            end: range.map(|r| r.end),
            buf: Vec::new(),
            size: None,
        };
        if got.end.is_some_and(|e| e <= got.start) {
            return Ok((Vec::new(), self.first.get().map_or(0, |v| v.size)));
        }
        let mut attempt = 1;
        // The furthest byte any attempt reached: the count starts over only past it (a resume
        // answered from the start again does not).
        let mut furthest = 0;
        loop {
            match self.http_once(client, url, ca, &mut got).await {
                Ok(()) => {
                    if let Some(size) = got.done() {
                        return Ok((got.buf, size));
                    }
                    // Part of what was asked: the rest is asked for next.
                    attempt = 1;
                }
                Err(Attempt::Final(e)) => return Err(e),
                Err(Attempt::Again {
                    reason,
                    retry_after,
                }) => {
                    // A body that broke after its last byte is whole.
                    if let Some(size) = got.done() {
                        return Ok((got.buf, size));
                    }
                    if got.buf.len() > furthest {
                        furthest = got.buf.len();
                        attempt = 1;
                    }
                    // A server that asks for a longer wait than a back-off's is not waited for
                    // here, silently: the caller says so (a browse pauses, showing why).
                    let long_wait = retry_after.is_some_and(|w| w > MAX_PAUSE);
                    if attempt >= self.pacing.attempts.max(1) || long_wait {
                        return Err(ReadError::Transfer {
                            reason,
                            attempts: attempt,
                            retry_after,
                        });
                    }
                    let pause = backoff(self.pacing.first_pause, attempt)
                        .max(retry_after.unwrap_or_default());
                    tracing::info!(
                        url = %redacted(url.as_str()), attempt, %reason, ?pause,
                        "range request failed, trying again"
                    );
                    tokio::time::sleep(pause).await;
                    attempt += 1;
                }
            }
        }
    }

    /// One attempt of an HTTP GET for what `got` still lacks, its bytes added to `got`.
    async fn http_once(
        &self,
        client: &reqwest::Client,
        url: &reqwest::Url,
        ca: Option<&Path>,
        got: &mut Progress,
    ) -> Result<(), Attempt> {
        // A whole read whose size is not known yet cannot say where to resume: it starts over.
        if got.end.is_none() && got.size.is_none() {
            got.buf.clear();
        }
        let from = got.start + got.buf.len() as u64;
        let end = match (got.end, got.size) {
            (Some(e), Some(s)) => Some(e.min(s)),
            (e, s) => e.or(s),
        };
        let mut request = client
            .get(url.clone())
            .header(header::ACCEPT_ENCODING, "identity");
        if let Some(end) = end {
            request = request.header(header::RANGE, format!("bytes={from}-{}", end - 1));
        }
        // No If-Match: every answer's size and ETag are compared with the first's anyway
        // (`check`), and some servers answer 412 to an ETag that matches.
        let mut response = request.send().await.map_err(|e| classify(e, ca))?;
        let status = response.status();
        match (status, end) {
            (reqwest::StatusCode::PARTIAL_CONTENT, Some(end)) => {
                let asked = from..end;
                let answer = header_text(response.headers(), header::CONTENT_RANGE)
                    .unwrap_or_default()
                    .to_string();
                let (start, stop, size) = match content_range(&answer) {
                    Some((s, e, Some(t))) if s == from && e <= end && e <= t => (s, e, t),
                    _ => return Err(RangeError::ContentRange { asked, answer }.into()),
                };
                check_encoding(response.headers())?;
                self.check(version_of(response.headers(), size))?;
                let want = stop - start;
                if let Some(n) = response.content_length().filter(|&n| n != want) {
                    return Err(ReadError::Length {
                        asked,
                        said: format!(
                            "announced {n} bytes (Content-Length) for the {want} of its \
                             Content-Range"
                        ),
                    }
                    .into());
                }
                got.size = Some(size);
                read_body(&mut response, &mut got.buf, Some(want), true, asked, ca).await
            }
            (reqwest::StatusCode::OK, _) => {
                let length = response.content_length();
                // The whole object: asked for, or as good as a range from its start that
                // holds all of it; else the server ignores ranges (refused unread).
                let whole =
                    got.start == 0 && got.end.is_none_or(|e| length.is_some_and(|n| n <= e));
                if !whole {
                    let asked = from..end.unwrap_or(from);
                    return Err(RangeError::RangeIgnored { asked }.into());
                }
                check_encoding(response.headers())?;
                if let Some(n) = length {
                    self.check(version_of(response.headers(), n))?;
                }
                got.buf.clear();
                got.size = length;
                let cap = length.or(got.end);
                let asked = 0..cap.unwrap_or(u64::MAX);
                read_body(
                    &mut response,
                    &mut got.buf,
                    cap,
                    length.is_some(),
                    asked,
                    ca,
                )
                .await?;
                if length.is_none() {
                    let n = got.buf.len() as u64;
                    self.check(version_of(response.headers(), n))?;
                    got.size = Some(n);
                }
                Ok(())
            }
            (s, _)
                if (s.is_server_error()
                    && s != reqwest::StatusCode::NOT_IMPLEMENTED
                    && s != reqwest::StatusCode::HTTP_VERSION_NOT_SUPPORTED)
                    || s == reqwest::StatusCode::TOO_MANY_REQUESTS
                    || s == reqwest::StatusCode::REQUEST_TIMEOUT =>
            {
                Err(Attempt::Again {
                    reason: format!("the server answered {s}"),
                    retry_after: header_text(response.headers(), header::RETRY_AFTER)
                        .and_then(|v| retry_after(v, SystemTime::now())),
                })
            }
            (s, _) => {
                let status = if s == reqwest::StatusCode::FORBIDDEN {
                    format!("{s} (a presigned URL may have expired)")
                } else {
                    s.to_string()
                };
                Err(RangeError::Status {
                    status,
                    excerpt: excerpt(response).await,
                }
                .into())
            }
        }
    }

    /// [`Object::read_vec`] from an object store (which retries on its own): the size and
    /// `ETag` held to the first (no `If-Match`: some S3 gateways refuse a matching one).
    async fn read_store(
        &self,
        store: &dyn ObjectStore,
        path: &ObjectPath,
        range: Option<Range<u64>>,
    ) -> Result<(Vec<u8>, u64), ReadError> {
        let options = object_store::GetOptions {
            range: range.clone().map(object_store::GetRange::Bounded),
            ..Default::default()
        };
        let failed = |e: object_store::Error| {
            let status = |s: &str| {
                ReadError::Range(RangeError::Status {
                    status: s.into(),
                    excerpt: None,
                })
            };
            match e {
                object_store::Error::NotFound { .. } => status("404 Not Found"),
                object_store::Error::PermissionDenied { .. } => status("403 Forbidden"),
                object_store::Error::Unauthenticated { .. } => status("401 Unauthorized"),
                object_store::Error::Precondition { .. } => {
                    ReadError::Changed("its ETag no longer matches".into())
                }
                e => ReadError::Range(RangeError::Store(e.to_string())),
            }
        };
        let got = store.get_opts(path, options).await.map_err(failed)?;
        let size = got.meta.size;
        self.check(Version {
            size,
            etag: got.meta.e_tag.clone().filter(|e| !e.starts_with("W/")),
            last_modified: None,
        })?;
        let bytes = got.bytes().await.map_err(failed)?;
        if let Some(r) = range.filter(|r| bytes.len() as u64 > r.end.saturating_sub(r.start)) {
            return Err(ReadError::Length {
                asked: r,
                said: format!("sent {} bytes", bytes.len()),
            });
        }
        Ok((Vec::from(bytes), size))
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

    /// `Retry-After` as seconds or as an HTTP-date in any of its forms, capped at a minute;
    /// a date past is no wait, and anything else is not a `Retry-After`.
    #[test]
    fn retry_after_reads_seconds_and_dates() {
        let now = SystemTime::UNIX_EPOCH + Duration::from_secs(784_111_777); // 06 Nov 1994 08:49:37
        assert_eq!(retry_after("3", now), Some(Duration::from_secs(3)));
        assert_eq!(retry_after(" 120 ", now), Some(RETRY_AFTER_CAP));
        assert_eq!(
            retry_after("99999999999999999999999", now),
            Some(RETRY_AFTER_CAP)
        );
        for date in [
            "Sun, 06 Nov 1994 08:49:47 GMT",
            "Sunday, 06-Nov-94 08:49:47 GMT",
            "Sun Nov  6 08:49:47 1994",
        ] {
            assert_eq!(
                retry_after(date, now),
                Some(Duration::from_secs(10)),
                "{date}"
            );
        }
        assert_eq!(
            retry_after("Sun, 06 Nov 1994 08:00:00 GMT", now),
            Some(Duration::ZERO)
        );
        assert_eq!(
            retry_after("Tue, 01 Mar 2044 00:00:00 GMT", now),
            Some(RETRY_AFTER_CAP)
        );
        assert_eq!(
            http_date("Tue, 29 Feb 2000 12:00:00 GMT"),
            Some(SystemTime::UNIX_EPOCH + Duration::from_secs(951_825_600))
        );
        for bad in ["", "soon", "-5", "Sun, 32 Nov 1994 08:49:37 GMT", "1.5"] {
            assert_eq!(retry_after(bad, now), None, "{bad:?}");
        }
    }

    /// Pauses double from the first up to [`MAX_PAUSE`], each jittered between half and all
    /// of its step, and not all the same.
    #[test]
    fn pauses_grow_jittered_up_to_their_cap() {
        let first = Duration::from_millis(250);
        for attempt in 1..40 {
            let full = (first * 2u32.pow((attempt - 1).min(10))).min(MAX_PAUSE);
            let p = backoff(first, attempt);
            assert!(p >= full / 2 && p <= full, "attempt {attempt}: {p:?}");
        }
        let pauses: std::collections::HashSet<Duration> =
            (0..20).map(|_| backoff(MAX_PAUSE, 1)).collect();
        assert!(pauses.len() > 1, "no jitter: {pauses:?}");
    }

    /// An XML error body reads as its code and message; a compressed one is not read.
    #[test]
    fn xml_error_bodies_read_as_code_and_message() {
        let body = "<?xml version=\"1.0\"?><Error><Code>AccessDenied</Code>\
                    <Message>Request has expired &amp; more</Message></Error>";
        assert_eq!(xml_text(body, "Code").as_deref(), Some("AccessDenied"));
        assert_eq!(
            xml_text(body, "Message").as_deref(),
            Some("Request has expired & more")
        );
        assert_eq!(xml_text(body, "RequestId"), None);
        let mut headers = HeaderMap::new();
        assert!(check_encoding(&headers).is_ok());
        headers.insert(header::CONTENT_ENCODING, "identity".parse().unwrap());
        assert!(check_encoding(&headers).is_ok());
        headers.insert(header::CONTENT_ENCODING, "br".parse().unwrap());
        assert_eq!(
            check_encoding(&headers),
            Err(ReadError::Encoded("br".into()))
        );
    }
}
