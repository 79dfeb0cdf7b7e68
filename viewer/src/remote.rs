//! Browsing a published volume by byte ranges, with no wavesplat server: a [`RangeSource`] reads
//! a volume in the indexed layout (`wavesplat publish`, or the objects cache nodes keep in a
//! bucket) from any HTTP server, CDN or S3-compatible bucket.
//!
//! The header and the packet index come in one request (two when they are larger than the first
//! request's 64 KiB). The packets the current view sees are then requested in the order the
//! cache would send them (visible energy per byte, `codec::view::visibility::packet_order`), the
//! next few in the order whose bytes neighbour each other coalesced into one range, at most
//! [`RangeSourceOptions::in_flight`] requests at once. A view change reorders what is not yet
//! requested. Every range is checked: its length, then each packet's framing and CRC as it is
//! decoded on the network thread; a server that returns less than asked or altered bytes stops
//! the source with an error that says so ([`SourceStatus::failed`]).
//!
//! The object-store client (`object_store`, as the cache uses) gives S3 signing and HTTP range
//! requests with retries; its HTTP store speaks plain GET with `Range` to any web server.

use crate::source::{
    Control, Feed, PacketSender, PacketSource, SourceError, SourcePacket, SourceStatus,
};
use bytes::Bytes;
use futures_util::stream::FuturesUnordered;
use futures_util::StreamExt;
use object_store::path::Path as ObjectPath;
use object_store::{ObjectStore, ObjectStoreExt};
use std::collections::HashSet;
use std::ops::Range;
use std::sync::{Arc, Mutex};
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

/// The object store and the object's path a URL names: `http(s)://host/dir/file` (any web
/// server or CDN; plain GET with `Range`) or `s3://bucket/key` (endpoint, region and credentials
/// from the `AWS_*` variables).
fn store_for(url: &str) -> Result<(Arc<dyn ObjectStore>, ObjectPath), SourceError> {
    wavesplat_net::tls::install_crypto_provider();
    let parsed = url::Url::parse(url).map_err(|e| SourceError::Remote(format!("{url}: {e}")))?;
    let bad = |e: object_store::Error| SourceError::Remote(format!("{url}: {e}"));
    match parsed.scheme() {
        "http" | "https" => {
            let (dir, file) = match url.rfind('/') {
                Some(i) if i + 1 < url.len() && i > parsed.scheme().len() + 2 => {
                    (&url[..=i], &url[i + 1..])
                }
                _ => return Err(SourceError::Remote(format!("{url}: no file name"))),
            };
            let store = object_store::http::HttpBuilder::new()
                .with_url(dir)
                .with_client_options(object_store::ClientOptions::new().with_allow_http(true))
                .build()
                .map_err(bad)?;
            let path = ObjectPath::from_url_path(file)
                .map_err(|e| SourceError::Remote(format!("{url}: file name: {e}")))?;
            Ok((Arc::new(store), path))
        }
        "s3" | "s3a" => {
            let store = object_store::aws::AmazonS3Builder::from_env()
                .with_url(url)
                .build()
                .map_err(bad)?;
            let path = ObjectPath::from_url_path(parsed.path())
                .map_err(|e| SourceError::Remote(format!("{url}: key: {e}")))?;
            Ok((Arc::new(store), path))
        }
        other => Err(SourceError::Remote(format!(
            "{url}: scheme {other:?}; use http(s)://… or s3://bucket/key"
        ))),
    }
}

/// The `.wsp` bytes of the volume at `url` (the whole object, without the index in front when
/// it is in the indexed layout): for a reference render of everything.
pub fn fetch_wsp(url: &str) -> Result<Vec<u8>, SourceError> {
    let (store, path) = store_for(url)?;
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .map_err(|e| SourceError::Thread(e.to_string()))?;
    let bytes = runtime
        .block_on(async { store.get(&path).await?.bytes().await })
        .map_err(|e| SourceError::Remote(format!("reading {url}: {e}")))?;
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
    store: &dyn ObjectStore,
    path: &ObjectPath,
    url: &str,
    status: &Mutex<SourceStatus>,
) -> Result<Head, SourceError> {
    let failed = |e: object_store::Error| SourceError::Remote(format!("reading {url}: {e}"));
    let first = store
        .get_opts(
            path,
            object_store::GetOptions {
                range: Some(object_store::GetRange::Bounded(0..HEAD_READ_BYTES)),
                ..Default::default()
            },
        )
        .await
        .map_err(failed)?;
    let object_bytes = first.meta.size;
    let mut bytes = first.bytes().await.map_err(failed)?.to_vec();
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
            let more = store
                .get_range(path, bytes.len() as u64..end)
                .await
                .map_err(failed)?;
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
                let more = store
                    .get_range(path, bytes.len() as u64..n as u64)
                    .await
                    .map_err(failed)?;
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
    /// Reads the head of the volume at `url` and starts fetching the packets `spec` sees.
    pub fn open(
        url: &str,
        spec: ViewSpec,
        options: RangeSourceOptions,
    ) -> Result<(RangeSource, Header), SourceError> {
        spec.validate()?;
        let (store, path) = store_for(url)?;
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .map_err(|e| SourceError::Thread(e.to_string()))?;
        let status = Arc::new(Mutex::new(SourceStatus {
            connected: true,
            ..Default::default()
        }));
        let head = runtime.block_on(read_head(store.as_ref(), &path, url, &status))?;
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
            store,
            path,
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

impl PacketSource for RangeSource {
    fn try_next(&mut self) -> Option<SourcePacket> {
        self.feed.try_next()
    }

    fn set_view(&mut self, spec: &ViewSpec) {
        self.feed.set_view(spec);
    }

    fn dropped(&mut self, ids: Vec<u32>) {
        self.feed.dropped(ids);
    }

    fn status(&self) -> SourceStatus {
        self.feed.status()
    }
}

/// The network task's state.
struct Fetch {
    url: String,
    store: Arc<dyn ObjectStore>,
    path: ObjectPath,
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
    /// Inside the bytes read with the head: no request needed.
    local: bool,
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
        Some(Request {
            local: end <= self.head.first.len() as u64,
            range: start..end,
            packets,
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
                let store = self.store.clone();
                let path = self.path.clone();
                let first = self.head.first.clone();
                flight.push(async move {
                    let got = if req.local {
                        Ok(first.slice(req.range.start as usize..req.range.end as usize))
                    } else {
                        store.get_range(&path, req.range.clone()).await
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
        got: Result<Bytes, object_store::Error>,
        tx: &PacketSender,
        first_packet: &mut bool,
    ) -> Result<bool, String> {
        let data =
            got.map_err(|e| format!("fetching bytes {:?} of {}: {e}", req.range, self.url))?;
        let want = req.range.end - req.range.start;
        self.update(|s| {
            if !req.local {
                s.requests += 1;
                s.received_bytes += data.len() as u64;
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
            store: Arc::new(object_store::memory::InMemory::new()),
            path: ObjectPath::from("v.wspx"),
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
            r.local && r.packets.iter().all(|&i| i < 4),
            "{:?}",
            r.packets
        );
        let mut next = f.next_request().unwrap();
        while next.local {
            next = f.next_request().unwrap();
        }
        assert!(next.packets.iter().all(|&i| i >= 4));
    }

    #[test]
    fn remote_names_are_recognised() {
        assert!(is_remote("https://cdn.example/a/v.wspx"));
        assert!(is_remote("s3://bucket/v.wspx"));
        assert!(!is_remote("v.wspx"));
        assert!(!is_remote("/data/http://x"));
        assert!(store_for("http://host/").is_err(), "no file name");
        assert!(store_for("ftp://host/v.wspx").is_err());
        assert!(store_for("http://host/dir/v.wspx").is_ok());
    }
}
