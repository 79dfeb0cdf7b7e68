//! Browsing a published volume by byte ranges, with no wavesplat server: a [`RangeSource`] reads
//! a volume in the indexed layout (`wavesplat publish`, or the objects cache nodes keep in a
//! bucket) from any HTTP server, CDN or S3-compatible bucket.
//!
//! The header and the packet index come in one request (two when they are larger than the first
//! request's 64 KiB). The packets the current view sees are then requested in the order the
//! cache would send them (visible energy per byte, `codec::view::visibility::packet_order`), the
//! next few in the order whose bytes neighbour each other coalesced into one range, at most
//! [`RangeSourceOptions::in_flight`] requests at once. Bytes that came with the head are never
//! asked for again: packets inside them need no request, and the range of a packet that starts
//! inside them begins where they end. A view change reorders what is not yet requested. Every
//! range is checked: its length, then each packet's framing and CRC as it is decoded on the
//! network thread; a server that returns less than asked or altered bytes stops the source with
//! an error that says so ([`SourceStatus::failed`]).
//!
//! `http(s)://` URLs are read with reqwest: plain GET with `Range`, TLS verified against the CA
//! given (PEM, `--ca`) or else the system's roots. Only what may pass is tried again (a refused
//! or dropped connection, a timeout, 5xx, 429), a few times with short pauses; what will not
//! pass fails at once, saying why ([`RangeError`]): a status names its code (the server's page
//! is not printed, at most a line of plain text), an `https://` URL to a server that does not
//! speak TLS says so, a certificate from an unknown CA says to pass `--ca`. `s3://` URLs go
//! through the object-store client (as the cache's bucket store does), which signs requests.

pub use crate::source::RangeError;
use crate::source::{
    packet_source_via_feed, Control, Feed, PacketSender, SourceError, SourcePacket, SourceStatus,
};
use bytes::Bytes;
use futures_util::stream::FuturesUnordered;
use futures_util::StreamExt;
use object_store::path::Path as ObjectPath;
use object_store::ObjectStore;
use std::collections::HashSet;
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::sync::mpsc;
use wavesplat_codec::format::index::{
    read_indexed_head, HeadRead, IndexedHead, PacketMeta, HEAD_READ_BYTES,
};
use wavesplat_codec::format::packet::decode_packet;
use wavesplat_codec::format::{parse_prelude, FormatError, Header};
use wavesplat_codec::view::priority::Priority;
use wavesplat_codec::view::ViewSpec;

/// Settings of a range source.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RangeSourceOptions {
    /// Requests in flight at once.
    pub in_flight: usize,
    /// Largest coalesced request (bytes); a larger packet is requested alone.
    pub max_request_bytes: u64,
    /// How far down the sending order to look for neighbours of the packet at its head.
    pub lookahead: usize,
    /// Request only what the current view sees (as the cache does).
    pub visible_only: bool,
    /// Bytes of packets decoded and queued for the session ahead of it (a packet larger than
    /// this passes alone).
    pub queue_bytes: u64,
}

impl Default for RangeSourceOptions {
    fn default() -> Self {
        RangeSourceOptions {
            in_flight: 4,
            max_request_bytes: 512 << 10,
            lookahead: 64,
            visible_only: true,
            queue_bytes: 256 << 10,
        }
    }
}

/// Packets fetched by range on a background thread (see the module documentation).
#[derive(Debug)]
pub struct RangeSource {
    feed: Feed,
}

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
enum Object {
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
    fn open(url: &str, ca: Option<&Path>) -> Result<Object, RangeError> {
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
    async fn read(&self, range: Option<Range<u64>>) -> Result<(Bytes, u64), RangeError> {
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

/// The `.wsp` bytes of the volume at `url` (the whole object, without the index in front when
/// it is in the indexed layout): for a reference render of everything. `ca`: the PEM CA to
/// trust for `https://`.
pub fn fetch_wsp(url: &str, ca: Option<&Path>) -> Result<Vec<u8>, SourceError> {
    let object = Object::open(url, ca)?;
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .map_err(|e| SourceError::Thread(e.to_string()))?;
    let (bytes, _) = runtime.block_on(object.read(None))?;
    if !bytes.starts_with(wavesplat_codec::format::index::INDEXED_MAGIC) {
        return Ok(bytes.to_vec());
    }
    match read_indexed_head(&bytes).map_err(|e| SourceError::Remote(format!("{url}: {e}")))? {
        HeadRead::Indexed(h) if h.object_bytes() == bytes.len() as u64 => {
            Ok(bytes[h.wsp_offset as usize..].to_vec())
        }
        _ => Err(SourceError::Remote(format!(
            "{url}: the object does not hold what its head describes"
        ))),
    }
}

/// Whether `s` names a volume to browse by range requests rather than a local file.
pub fn is_remote(s: &str) -> bool {
    ["http://", "https://", "s3://", "s3a://"]
        .iter()
        .any(|p| s.starts_with(p))
}

/// The volume's head as read: the indexed layout, or a plain `.wsp` (header and directory only:
/// packets are then requested in file order, all of them).
struct Head {
    /// The object's first bytes as read for the head (packets inside them need no request).
    first: Bytes,
    header: Header,
    packets: Vec<PacketMeta>,
    /// Where packet offsets start in the object.
    base: u64,
    object_bytes: u64,
    indexed: bool,
}

async fn read_head(
    object: &Object,
    url: &str,
    status: &Mutex<SourceStatus>,
) -> Result<Head, SourceError> {
    let (first, object_bytes) = object.read(Some(0..HEAD_READ_BYTES)).await?;
    let mut bytes = first.to_vec();
    count(status, bytes.len() as u64);
    let corrupt = |e: FormatError| SourceError::Remote(format!("{url}: {e}"));
    if bytes.starts_with(wavesplat_codec::format::MAGIC) {
        // A plain .wsp: header and directory, packets in file order.
        loop {
            if let Some(p) = parse_prelude(&bytes).map_err(corrupt)? {
                let mut offset = p.len() as u64;
                let packets = p
                    .packet_lengths
                    .iter()
                    .map(|&len| {
                        let m = PacketMeta {
                            tile: 0,
                            layer: 0,
                            len: len as u32,
                            offset,
                            summary: Vec::new(),
                        };
                        offset += len as u64;
                        m
                    })
                    .collect();
                if p.file_bytes() != object_bytes {
                    return Err(SourceError::Remote(format!(
                        "{url} holds {object_bytes} bytes, its directory describes {}",
                        p.file_bytes()
                    )));
                }
                return Ok(Head {
                    first: Bytes::from(bytes),
                    header: p.header,
                    packets,
                    base: 0,
                    object_bytes,
                    indexed: false,
                });
            }
            if bytes.len() as u64 >= object_bytes {
                return Err(SourceError::Remote(format!(
                    "{url} ends inside its header or directory"
                )));
            }
            let end = (bytes.len() as u64 * 2).min(object_bytes);
            let (more, _) = object.read(Some(bytes.len() as u64..end)).await?;
            count(status, more.len() as u64);
            bytes.extend_from_slice(&more);
        }
    }
    let head: IndexedHead = loop {
        match read_indexed_head(&bytes).map_err(corrupt)? {
            HeadRead::Indexed(h) => break *h,
            HeadRead::Need(n) if n as u64 > object_bytes || n <= bytes.len() => {
                return Err(SourceError::Remote(format!(
                    "{url} ends inside its head ({object_bytes} bytes)"
                )))
            }
            HeadRead::Need(n) => {
                let (more, _) = object.read(Some(bytes.len() as u64..n as u64)).await?;
                count(status, more.len() as u64);
                bytes.extend_from_slice(&more);
            }
        }
    };
    if head.object_bytes() != object_bytes {
        return Err(SourceError::Remote(format!(
            "{url} holds {object_bytes} bytes, its head describes {}: truncated or not this volume",
            head.object_bytes()
        )));
    }
    Ok(Head {
        first: Bytes::from(bytes),
        header: head.header,
        packets: head.packets,
        base: head.wsp_offset,
        object_bytes,
        indexed: true,
    })
}

fn count(status: &Mutex<SourceStatus>, bytes: u64) {
    let mut s = status.lock().unwrap_or_else(|e| e.into_inner());
    s.requests += 1;
    s.received_bytes += bytes;
}

impl RangeSource {
    /// Reads the head of the volume at `url` and starts fetching the packets `spec` sees;
    /// `ca`: the PEM CA to trust for `https://` (else the system's roots).
    pub fn open(
        url: &str,
        ca: Option<&Path>,
        spec: ViewSpec,
        options: RangeSourceOptions,
    ) -> Result<(RangeSource, Header), SourceError> {
        spec.validate()?;
        let object = Object::open(url, ca)?;
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .map_err(|e| SourceError::Thread(e.to_string()))?;
        let status = Arc::new(Mutex::new(SourceStatus {
            connected: true,
            ..Default::default()
        }));
        let head = runtime.block_on(read_head(&object, url, &status))?;
        if !head.indexed {
            tracing::warn!(
                %url,
                "a plain .wsp: every packet is fetched in file order (`wavesplat publish` writes \
                 the indexed layout, which lets a view fetch only what it sees)"
            );
        }
        status
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .object_bytes = head.object_bytes;
        let header = head.header.clone();
        let mut fetch = Fetch {
            url: url.to_string(),
            object,
            options,
            requested: HashSet::new(),
            queue: Vec::new(),
            status: status.clone(),
            head,
        };
        fetch.plan(&spec)?;
        let feed = Feed::start(
            "wavesplat-range-source",
            runtime,
            options.queue_bytes,
            status,
            move |tx, ctl| fetch.run(tx, ctl),
        )?;
        Ok((RangeSource { feed }, header))
    }
}

packet_source_via_feed!(RangeSource);

/// The network task's state.
struct Fetch {
    url: String,
    object: Object,
    options: RangeSourceOptions,
    /// Packets requested (and not dropped by the session since).
    requested: HashSet<u32>,
    /// Packets still to request, in sending order.
    queue: Vec<u32>,
    status: Arc<Mutex<SourceStatus>>,
    head: Head,
}

/// One coalesced request: its byte range in the object and the packets in it.
struct Request {
    range: Range<u64>,
    packets: Vec<u32>,
    /// Bytes at the range's start that came with the head: only the rest is requested (none
    /// when it is all of them).
    held: u64,
}

impl Request {
    /// Inside the bytes read with the head: no request needed.
    fn local(&self) -> bool {
        self.held >= self.range.end - self.range.start
    }
}

impl Fetch {
    fn update(&self, f: impl FnOnce(&mut SourceStatus)) {
        let mut s = self.status.lock().unwrap_or_else(|e| e.into_inner());
        f(&mut s);
    }

    /// Whether packet `i` lies inside the bytes read with the head.
    fn is_local(&self, i: u32) -> bool {
        let p = &self.head.packets[i as usize];
        self.head.base + p.offset + p.len as u64 <= self.head.first.len() as u64
    }

    /// Orders what is not yet requested for `spec` (only what it sees, when asked and the
    /// index says). Packets that came with the head go first, in that order: they cost no
    /// request, and being the start of the file they are its most significant packets, so the
    /// first image needs no round trip after the head's.
    fn plan(&mut self, spec: &ViewSpec) -> Result<(), SourceError> {
        self.plan_remote(spec)?;
        let (local, remote): (Vec<u32>, Vec<u32>) =
            self.queue.iter().partition(|&&i| self.is_local(i));
        self.queue = local.into_iter().chain(remote).collect();
        Ok(())
    }

    fn plan_remote(&mut self, spec: &ViewSpec) -> Result<(), SourceError> {
        let packets = &self.head.packets;
        if !self.head.indexed {
            self.queue = (0..packets.len() as u32)
                .filter(|i| !self.requested.contains(i))
                .collect();
            return Ok(());
        }
        let priority = Priority::new(&self.head.header, spec)?;
        self.queue = priority
            .order(packets)
            .into_iter()
            .filter(|i| !self.requested.contains(i))
            .filter(|&i| {
                !self.options.visible_only || priority.visible_energy(&packets[i as usize]) > 0.0
            })
            .collect();
        Ok(())
    }

    /// Takes the next request off the queue: its head packet, grown over the packets next to
    /// it in the file (ids are file order and packets are contiguous) that are among the next
    /// few in the sending order, so nothing is fetched that the view does not want.
    fn next_request(&mut self) -> Option<Request> {
        let first = *self.queue.first()?;
        let look = self.queue.len().min(self.options.lookahead.max(1));
        let wanted: std::collections::HashMap<u32, usize> = self.queue[..look]
            .iter()
            .enumerate()
            .map(|(k, &id)| (id, k))
            .collect();
        let len = |i: u32| self.head.packets[i as usize].len as u64;
        // Packets that came with the head are not mixed with ones still to fetch.
        let local = self.is_local(first);
        let wanted: std::collections::HashMap<u32, usize> = wanted
            .into_iter()
            .filter(|(id, _)| self.is_local(*id) == local)
            .collect();
        let (mut lo, mut hi) = (first, first);
        let mut bytes = len(first);
        loop {
            let right = hi.checked_add(1).filter(|r| {
                wanted.contains_key(r) && bytes + len(*r) <= self.options.max_request_bytes
            });
            let left = lo.checked_sub(1).filter(|l| {
                wanted.contains_key(l) && bytes + len(*l) <= self.options.max_request_bytes
            });
            match (right, left) {
                (Some(r), _) => {
                    hi = r;
                    bytes += len(r);
                }
                (None, Some(l)) => {
                    lo = l;
                    bytes += len(l);
                }
                (None, None) => break,
            }
        }
        let packets: Vec<u32> = (lo..=hi).collect();
        let mut taken: Vec<usize> = packets.iter().map(|id| wanted[id]).collect();
        taken.sort_unstable();
        for k in taken.into_iter().rev() {
            self.queue.remove(k);
        }
        for &p in &packets {
            self.requested.insert(p);
        }
        let start = self.head.base + self.head.packets[lo as usize].offset;
        let last = &self.head.packets[hi as usize];
        let end = self.head.base + last.offset + last.len as u64;
        let held = (self.head.first.len() as u64).clamp(start, end) - start;
        Some(Request {
            range: start..end,
            packets,
            held,
        })
    }

    fn apply(&mut self, c: Control) {
        match c {
            Control::View(spec) => {
                if let Err(e) = self.plan(&spec) {
                    tracing::warn!(error = %e, "planning a view for range requests");
                }
                self.update(SourceStatus::view_applied);
            }
            Control::Dropped(ids) => {
                for id in ids {
                    self.requested.remove(&id);
                }
            }
        }
    }

    async fn run(mut self, tx: PacketSender, mut ctl: mpsc::UnboundedReceiver<Control>) {
        let mut flight = FuturesUnordered::new();
        let mut first_packet = true;
        loop {
            while flight.len() < self.options.in_flight.max(1) {
                let Some(req) = self.next_request() else {
                    break;
                };
                let object = self.object.clone();
                let first = self.head.first.clone();
                flight.push(async move {
                    let (start, end) = (req.range.start as usize, req.range.end as usize);
                    let got = if req.local() {
                        Ok(first.slice(start..end))
                    } else {
                        // Only what the head did not bring; what it did goes in front.
                        let from = req.range.start + req.held;
                        let tail = object.read(Some(from..req.range.end)).await;
                        tail.map(|(tail, _)| {
                            if req.held == 0 {
                                tail
                            } else {
                                let mut all = first[start..start + req.held as usize].to_vec();
                                all.extend_from_slice(&tail);
                                Bytes::from(all)
                            }
                        })
                    };
                    (req, got)
                });
            }
            let idle = flight.is_empty();
            self.update(|s| s.done = idle && self.queue.is_empty());
            tokio::select! {
                c = ctl.recv() => match c {
                    Some(c) => self.apply(c),
                    None => return,
                },
                Some((req, got)) = flight.next(), if !idle => {
                    match self.deliver(req, got, &tx, &mut first_packet).await {
                        Ok(true) => {}
                        Ok(false) => return,
                        Err(e) => {
                            tracing::error!(url = %self.url, error = %e, "range source stopped");
                            self.update(|s| {
                                s.connected = false;
                                s.problem = Some(e.clone());
                                s.failed = Some(e);
                            });
                            return;
                        }
                    }
                }
            }
        }
    }

    /// Checks a response, decodes its packets and hands them on; false when the session went
    /// away, an error when the server's bytes cannot be this volume's.
    async fn deliver(
        &mut self,
        req: Request,
        got: Result<Bytes, RangeError>,
        tx: &PacketSender,
        first_packet: &mut bool,
    ) -> Result<bool, String> {
        let data =
            got.map_err(|e| format!("fetching bytes {:?} of {}: {e}", req.range, self.url))?;
        let want = req.range.end - req.range.start;
        self.update(|s| {
            if !req.local() {
                s.requests += 1;
                s.received_bytes += (data.len() as u64).saturating_sub(req.held);
            }
            if *first_packet {
                s.requests_before_first_packet = s.requests;
            }
        });
        *first_packet = false;
        if data.len() as u64 != want {
            return Err(format!(
                "{} answered {} bytes for the range {:?} of {want}: truncated or changed on the server",
                self.url,
                data.len(),
                req.range
            ));
        }
        for id in req.packets {
            let p = &self.head.packets[id as usize];
            let start = (self.head.base + p.offset - req.range.start) as usize;
            let bytes = data[start..start + p.len as usize].to_vec();
            let d = decode_packet(&self.head.header, &bytes)
                .map_err(|e| format!("packet {id} of {}: {e}", self.url))?;
            if self.head.indexed && (d.tile as u32 != p.tile || d.layer as u32 != p.layer) {
                return Err(format!(
                    "packet {id} of {} is tile {} layer {}, its index says tile {} layer {}",
                    self.url, d.tile, d.layer, p.tile, p.layer
                ));
            }
            let len = bytes.len() as u64;
            let packet = SourcePacket {
                id,
                data: bytes,
                decoded: Some((d.tile, d.coefficients)),
            };
            if tx.send(packet).await.is_err() {
                return Ok(false);
            }
            self.update(|s| {
                s.packets += 1;
                s.bytes += len;
            });
        }
        Ok(true)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use wavesplat_codec::view::View;

    /// A fetch over a published phantom (no network: planning and coalescing only).
    fn fetch(first_bytes: usize) -> Fetch {
        use wavesplat_compressor::encode::{compress, CompressOptions, Target, TileChoice};
        let wsp = compress(
            &wavesplat_compressor::phantom::Phantom::SheppLogan.generate([48, 48, 48]),
            &CompressOptions {
                target: Target::Fraction(0.2),
                tile: TileChoice::Size(8),
                refine: None,
                ..Default::default()
            },
            &|_, _| {},
        )
        .unwrap()
        .bytes;
        let object = wavesplat_codec::format::index::indexed_layout(&wsp).unwrap();
        let HeadRead::Indexed(h) = read_indexed_head(&object).unwrap() else {
            panic!("head incomplete")
        };
        Fetch {
            url: "test".into(),
            object: Object::Store {
                store: Arc::new(object_store::memory::InMemory::new()),
                path: ObjectPath::from("v.wspx"),
            },
            options: RangeSourceOptions::default(),
            requested: HashSet::new(),
            queue: Vec::new(),
            status: Arc::new(Mutex::new(SourceStatus::default())),
            head: Head {
                first: Bytes::copy_from_slice(&object[..first_bytes.min(object.len())]),
                object_bytes: h.object_bytes(),
                header: h.header,
                packets: h.packets,
                base: h.wsp_offset,
                indexed: true,
            },
        }
    }

    #[test]
    fn a_corner_asks_for_less_and_a_view_change_reorders_only_what_is_left() {
        let mut f = fetch(0);
        let n = f.head.packets.len();
        let whole = ViewSpec::single(View::new(0.3, 0.2, 64, 64));
        f.plan(&whole).unwrap();
        assert_eq!(f.queue.len(), n, "the whole volume is in view");
        let mut corner_view = View::new(0.0, 0.0, 64, 64);
        corner_view.zoom = Some(6.0);
        corner_view.pan = [20.0, 20.0];
        let corner = ViewSpec::single(corner_view);
        f.plan(&corner).unwrap();
        assert!(
            f.queue.len() < n * 3 / 4,
            "{} of {n} for a corner",
            f.queue.len()
        );
        // Requests are runs of neighbouring packets, each wanted, none twice.
        let mut seen = HashSet::new();
        let first = f.next_request().unwrap();
        for w in first.packets.windows(2) {
            assert_eq!(w[1], w[0] + 1);
        }
        let p = &f.head.packets;
        assert_eq!(
            first.range.start,
            f.head.base + p[first.packets[0] as usize].offset
        );
        seen.extend(first.packets.iter().copied());
        // Back to the whole view: what was requested is not asked again, the rest is.
        f.plan(&whole).unwrap();
        assert_eq!(f.queue.len(), n - seen.len());
        assert!(f.queue.iter().all(|i| !seen.contains(i)));
        // A dropped packet may be asked for again after the next view change.
        let dropped = first.packets[0];
        f.apply(Control::Dropped(vec![dropped]));
        f.plan(&whole).unwrap();
        assert!(f.queue.contains(&dropped));
    }

    #[test]
    fn packets_that_came_with_the_head_go_first_and_alone() {
        let mut f = fetch(usize::MAX);
        let end = f.head.base + f.head.packets[3].offset + f.head.packets[3].len as u64;
        f.head.first = f.head.first.slice(..end as usize);
        f.plan(&ViewSpec::single(View::new(0.3, 0.2, 64, 64)))
            .unwrap();
        assert!(f.queue[..4].iter().all(|&i| i < 4), "{:?}", &f.queue[..6]);
        let r = f.next_request().unwrap();
        assert!(
            r.local() && r.packets.iter().all(|&i| i < 4),
            "{:?}",
            r.packets
        );
        let mut next = f.next_request().unwrap();
        while next.local() {
            next = f.next_request().unwrap();
        }
        assert!(next.packets.iter().all(|&i| i >= 4));
    }

    /// A packet that begins inside the bytes read with the head is asked for from where they
    /// end: the request holds that prefix, and only the rest goes over the wire.
    #[test]
    fn a_packet_across_the_head_is_asked_for_from_its_end() {
        let mut f = fetch(usize::MAX);
        let p = &f.head.packets[2];
        let (start, len) = (f.head.base + p.offset, p.len as u64);
        assert!(len > 2, "the test needs a packet of a few bytes");
        f.head.first = f.head.first.slice(..(start + len / 2) as usize);
        f.plan(&ViewSpec::single(View::new(0.3, 0.2, 64, 64)))
            .unwrap();
        let mut r = f.next_request().unwrap();
        while r.local() {
            r = f.next_request().unwrap();
        }
        while !r.packets.contains(&2) {
            r = f.next_request().unwrap();
        }
        assert_eq!(r.range.start, start, "{:?}", r.packets);
        assert_eq!(r.held, len / 2);
        assert!(!r.local());
    }

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

    #[test]
    fn remote_names_are_recognised() {
        assert!(is_remote("https://cdn.example/a/v.wspx"));
        assert!(is_remote("s3://bucket/v.wspx"));
        assert!(!is_remote("v.wspx"));
        assert!(!is_remote("/data/http://x"));
        let open = |url| Object::open(url, None);
        assert!(open("http://host/").is_err(), "no file name");
        assert!(open("ftp://host/v.wspx").is_err());
        assert!(open("http://host/dir/v.wspx").is_ok());
        assert!(open("https://host/dir/v.wspx").is_ok());
        let ca = Path::new("/nonexistent/ca.pem");
        assert_eq!(
            Object::open("http://host/v.wspx", Some(ca)).err(),
            Some(RangeError::CaWithoutTls)
        );
        assert!(matches!(
            Object::open("https://host/v.wspx", Some(ca)),
            Err(RangeError::Ca { .. })
        ));
    }
}
