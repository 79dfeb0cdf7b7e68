//! Where packets come from: the [`PacketSource`] trait the frame loop polls (never blocking),
//! a [`FileSource`] that serves a local `.wsp` file in the order the cache would send it for the
//! current view, and a [`CacheSource`] that pulls packets from a cache over gRPC on its own
//! thread; the errors of every source ([`SourceError`], and [`RangeError`], the range reader's
//! of `remote`, here so that sources share one error type without `remote` and this module
//! importing each other).
//!
//! The cache source runs a tokio runtime on a background thread. It opens a refinement stream
//! with a small byte credit, hands each packet to the session through a bounded queue and only
//! then renews the credit by the packet's size, so what is in flight stays within the credit
//! plus the queue and a view change reorders the rest within a few packets. View changes and
//! dropped packets (the session's memory bound) go to the cache on the same stream. If the
//! connection fails it keeps what it has, says so in its status (with the cache's own status
//! when the cache ended the stream: `Unavailable` naming its object store, say), and
//! reconnects with backoff, telling the cache what it holds so nothing is sent twice.

use futures_util::stream::{FuturesOrdered, StreamExt};
use std::collections::{HashMap, HashSet};
use std::ops::Range;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::sync::{mpsc, OwnedSemaphorePermit, Semaphore};
use wavesplat_client::{
    CacheClient, ClientError, ConnectOptions, RefineEvent, RefineRequest, RefineStream,
    VolumeHeader, VolumeKey,
};
use wavesplat_codec::format::packet::{decode_packet, read_framing, Coefficient};
use wavesplat_codec::format::{check_kept, parse_file, FormatError, Header};
use wavesplat_codec::layout::Band;
use wavesplat_codec::view::visibility::{packet_order, PacketFacts, Visibility};
use wavesplat_codec::view::{ViewError, ViewSpec};

/// A packet as a source delivers it.
#[derive(Debug, Clone, PartialEq)]
pub struct SourcePacket {
    /// Index of the packet in file order.
    pub id: u32,
    /// Its bytes.
    pub data: Vec<u8>,
    /// Its tile and coefficients, when the source decoded it already (the file and cache
    /// sources do, off the frame thread or ahead of it, so the frame thread only queues them).
    pub decoded: Option<(usize, Vec<Coefficient>)>,
}

/// What a source reports about itself.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct SourceStatus {
    /// Connected (always true for a file).
    pub connected: bool,
    /// Everything the current view ranks has been delivered.
    pub done: bool,
    /// Packets delivered.
    pub packets: u64,
    /// Bytes delivered.
    pub bytes: u64,
    /// Reconnections after a failure.
    pub reconnects: u64,
    /// Packets the cache sent although they were held (stays 0: a stream starts with the
    /// holdings, also after a reconnection); such packets are not delivered again.
    pub resent: u64,
    /// The last problem, while it lasts (e.g. "cache unreachable, retrying: …").
    pub problem: Option<String>,
    /// Why the source stopped for good (bytes that cannot be the volume's); nothing more comes.
    pub failed: Option<String>,
    /// Requests made (range sources: the head's included).
    pub requests: u64,
    /// Requests made before the first packet's bytes arrived (range sources).
    pub requests_before_first_packet: u64,
    /// Bytes received over the network (range sources: the head's and coalescing gaps
    /// included).
    pub received_bytes: u64,
    /// Size of the whole object (range sources).
    pub object_bytes: u64,
    /// View changes the network thread has applied (sources fed by one): its `done` is about
    /// the last of them, so a view change it has not applied yet is not done.
    pub views_applied: u64,
}

impl SourceStatus {
    /// A network thread took the session's new view: nothing of it is done yet.
    pub fn view_applied(&mut self) {
        self.done = false;
        self.views_applied += 1;
    }
}

/// A source of packets for a render session.
pub trait PacketSource: Send {
    /// The next packet that has arrived, if any (never blocks).
    fn try_next(&mut self) -> Option<SourcePacket>;
    /// The view changed: rank what is not yet delivered for it (dropped packets become
    /// eligible again).
    fn set_view(&mut self, spec: &ViewSpec);
    /// The session dropped these packets (memory bound): they may be delivered again after a
    /// later view change.
    fn dropped(&mut self, ids: Vec<u32>);
    /// Status for display.
    fn status(&self) -> SourceStatus;
}

/// Errors opening a source.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum SourceError {
    /// The file is not a valid `.wsp` file.
    #[error(transparent)]
    Format(#[from] FormatError),
    /// The view is invalid.
    #[error(transparent)]
    View(#[from] ViewError),
    /// The cache could not be reached or refused.
    #[error(transparent)]
    Client(#[from] ClientError),
    /// A volume browsed by range requests could not be read: its bytes are not what they
    /// should be.
    #[error("{0}")]
    Remote(String),
    /// A volume browsed by range requests could not be read: the server's answer, or none.
    #[error(transparent)]
    Range(#[from] RangeError),
    /// The background thread could not be started.
    #[error("cannot start the network thread: {0}")]
    Thread(String),
}

/// Why a published volume could not be read: what the server answered, or why no answer came.
/// The URL is not repeated here: whoever reports the error names it.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum RangeError {
    /// The URL cannot name a published volume.
    #[error("{0}")]
    Url(String),
    /// The CA certificate could not be used.
    #[error("the CA certificate {}: {reason}", .path.display())]
    Ca {
        /// The PEM file.
        path: PathBuf,
        /// What is wrong with it.
        reason: String,
    },
    /// A CA certificate was given for a plaintext URL (as the cache's client, this refuses
    /// rather than let a user believe the transfer is verified).
    #[error(
        "a CA certificate was given (--ca or WAVESPLAT_CA) for a plaintext http:// URL; use \
         https://, or give no CA"
    )]
    CaWithoutTls,
    /// The server answered with a status other than the bytes asked for.
    #[error("the server answered {status}{}", excerpt_suffix(.excerpt))]
    Status {
        /// The status code and its reason ("404 Not Found").
        status: String,
        /// The first line of a plain-text body, cut short (an HTML page is not repeated).
        excerpt: Option<String>,
    },
    /// An `https://` URL to a server that does not answer in TLS.
    #[error(
        "the server does not speak TLS: it answered the TLS handshake with something else (a \
         plaintext HTTP server? then try http://)"
    )]
    NotTls,
    /// The server's certificate is not signed by a CA this client trusts.
    #[error(
        "the server's certificate is not signed by a trusted CA (UnknownIssuer): {}",
        match .ca {
            Some(ca) => format!("it is not signed by the CA given ({}); pass the CA that signed it with --ca", ca.display()),
            None => "pass the CA that signed it with --ca PEM (or WAVESPLAT_CA)".to_string(),
        }
    )]
    UnknownIssuer {
        /// The CA that was given, if any.
        ca: Option<PathBuf>,
    },
    /// TLS failed otherwise (a certificate for another name or expired, a handshake refused).
    #[error("TLS failed: {0}")]
    Tls(String),
    /// The server could not be reached, or the transfer broke, every time it was tried.
    #[error("{reason} (tried {attempts} times)")]
    Transfer {
        /// The last failure.
        reason: String,
        /// Attempts made.
        attempts: u32,
    },
    /// The server answered a request for part of the object with all of it.
    #[error(
        "the server ignores Range requests (asked for bytes {}..{}, it answered the whole \
         object); serve the volume from a server that honours Range",
        .asked.start, .asked.end
    )]
    RangeIgnored {
        /// The range asked for.
        asked: Range<u64>,
    },
    /// The server answered other bytes than those asked for.
    #[error("asked for bytes {}..{}, the server answered {answer:?}", .asked.start, .asked.end)]
    ContentRange {
        /// The range asked for.
        asked: Range<u64>,
        /// Its `Content-Range`.
        answer: String,
    },
    /// The object store (`s3://`) failed.
    #[error("{0}")]
    Store(String),
}

fn excerpt_suffix(excerpt: &Option<String>) -> String {
    excerpt
        .as_deref()
        .map(|e| format!(": {e:?}"))
        .unwrap_or_default()
}

/// Where a packet lies in a file and what ranks it.
#[derive(Debug, Clone)]
struct FilePacket {
    range: std::ops::Range<usize>,
    tile: usize,
    summary: Vec<(Band, f64)>,
}

/// A local `.wsp` file served packet by packet in the cache's order for the current view
/// (visible energy per byte), optionally only up to a byte budget, each packet decoded when it
/// is handed over, together with the next few in parallel (every source hands the session
/// decoded packets).
#[derive(Debug)]
pub struct FileSource {
    bytes: Vec<u8>,
    header: Header,
    /// Byte range and framing of each packet.
    packets: Vec<FilePacket>,
    order: Vec<u32>,
    cursor: usize,
    delivered: Vec<bool>,
    budget: Option<u64>,
    status: SourceStatus,
    /// Packets decoded ahead of their delivery, by id (`None`: it did not decode).
    ahead: HashMap<u32, Decoded>,
}

/// A packet's tile and coefficients, `None` when it did not decode.
type Decoded = Option<(usize, Vec<Coefficient>)>;

/// Decodes a packet for the session; one that fails to decode goes on as bytes and the session
/// reports it.
fn decode_for_session(header: &Header, data: &[u8]) -> Decoded {
    decode_packet(header, data)
        .ok()
        .map(|d| (d.tile, d.coefficients))
}

/// Packets a file source decodes at once, in parallel, when the next one is not decoded yet:
/// per core, so that every core decodes while the frame thread takes packets.
const DECODE_AHEAD_PER_THREAD: usize = 2;

impl FileSource {
    /// Parses `bytes` (the whole file) and ranks its packets for `spec`.
    pub fn open(bytes: Vec<u8>, spec: &ViewSpec) -> Result<FileSource, SourceError> {
        let (header, ranges) = {
            let file = parse_file(&bytes)?;
            let base = bytes.as_ptr() as usize;
            let ranges: Vec<std::ops::Range<usize>> = file
                .packets
                .iter()
                .map(|p| {
                    let start = p.as_ptr() as usize - base;
                    start..start + p.len()
                })
                .collect();
            (file.header, ranges)
        };
        let mut packets = Vec::with_capacity(ranges.len());
        let mut held = 0u64;
        for r in ranges {
            let f = read_framing(&header, &bytes[r.clone()])?;
            held = held.saturating_add(f.count as u64);
            packets.push(FilePacket {
                range: r,
                tile: f.tile,
                summary: f.summary,
            });
        }
        // The packets must hold what the header declares: missing or cut packets would
        // otherwise render as a blank or partial image.
        check_kept(&header, held)?;
        let n = packets.len();
        let mut s = FileSource {
            bytes,
            header,
            packets,
            order: Vec::new(),
            cursor: 0,
            delivered: vec![false; n],
            budget: None,
            status: SourceStatus {
                connected: true,
                ..Default::default()
            },
            ahead: HashMap::new(),
        };
        s.rank(spec)?;
        Ok(s)
    }

    /// Delivers at most `bytes` bytes of packets (the first packet always).
    pub fn with_byte_budget(mut self, bytes: Option<u64>) -> FileSource {
        self.budget = bytes;
        self
    }

    /// The file's header.
    pub fn header(&self) -> &Header {
        &self.header
    }

    /// The whole file.
    pub fn file_bytes(&self) -> &[u8] {
        &self.bytes
    }

    /// Number of packets in the file.
    pub fn packet_count(&self) -> usize {
        self.packets.len()
    }

    /// Decodes the packet at the cursor and the next ones in order (those not decoded yet),
    /// [`DECODE_AHEAD_PER_THREAD`] per core, in parallel: on this thread and scoped threads of
    /// its own, not on the rayon pool, whose threads the background planner may hold for the
    /// length of a table build (a frame thread waiting for them would stall).
    fn decode_ahead(&mut self) {
        let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
        // The cursor has moved past the packet being delivered.
        let next: Vec<u32> = self.order[self.cursor - 1..]
            .iter()
            .copied()
            .filter(|id| !self.ahead.contains_key(id))
            .take(DECODE_AHEAD_PER_THREAD * threads)
            .collect();
        let (header, bytes, packets) = (&self.header, &self.bytes, &self.packets);
        let decode = |ids: &[u32]| -> Vec<(u32, Decoded)> {
            ids.iter()
                .map(|&id| {
                    let data = &bytes[packets[id as usize].range.clone()];
                    (id, decode_for_session(header, data))
                })
                .collect()
        };
        // Packet i goes to thread i mod threads: the one needed now to this thread, first.
        let share =
            |t: usize| -> Vec<u32> { next.iter().copied().skip(t).step_by(threads).collect() };
        let decoded = std::thread::scope(|scope| {
            let helpers: Vec<_> = (1..threads.min(next.len()))
                .map(|t| {
                    let ids = share(t);
                    scope.spawn(move || decode(&ids))
                })
                .collect();
            let mut all = decode(&share(0));
            for h in helpers {
                // A decoder that panicked leaves its packets to be decoded again when asked.
                if let Ok(d) = h.join() {
                    all.extend(d);
                }
            }
            all
        });
        self.ahead.extend(decoded);
    }

    fn rank(&mut self, spec: &ViewSpec) -> Result<(), SourceError> {
        let vis = Visibility::new(&self.header, spec)?;
        let keyed: Vec<PacketFacts> = self
            .packets
            .iter()
            .map(|p| PacketFacts {
                tile: p.tile,
                summary: &p.summary,
                bytes: p.range.len(),
            })
            .collect();
        self.order = packet_order(&vis, &keyed)
            .into_iter()
            .filter(|i| !self.delivered[*i as usize])
            .collect();
        // What was decoded for the old order may come much later now: let it go, so that the
        // source never holds more than one parallel round of decoded packets.
        self.ahead.clear();
        self.cursor = 0;
        self.status.done = self.order.is_empty();
        Ok(())
    }
}

impl PacketSource for FileSource {
    fn try_next(&mut self) -> Option<SourcePacket> {
        let id = *self.order.get(self.cursor)?;
        let range = self.packets[id as usize].range.clone();
        if self.status.packets > 0
            && self
                .budget
                .is_some_and(|b| self.status.bytes + range.len() as u64 > b)
        {
            self.status.done = true;
            return None;
        }
        self.cursor += 1;
        self.delivered[id as usize] = true;
        self.status.packets += 1;
        self.status.bytes += range.len() as u64;
        self.status.done = self.cursor >= self.order.len();
        let data = self.bytes[range].to_vec();
        // Decoded here, as the network sources decode on their threads, so the session takes
        // every source's packets one way: this one and the next few in order at once, in
        // parallel. A packet that does not decode goes on as bytes: the session then reports
        // the error with the packet's id.
        if !self.ahead.contains_key(&id) {
            self.decode_ahead();
        }
        let decoded = self.ahead.remove(&id).flatten();
        Some(SourcePacket { id, data, decoded })
    }

    fn set_view(&mut self, spec: &ViewSpec) {
        // The spec was validated by the session; a failure here leaves the old order.
        let _ = self.rank(spec);
    }

    fn dropped(&mut self, ids: Vec<u32>) {
        for id in ids {
            if let Some(d) = self.delivered.get_mut(id as usize) {
                *d = false;
            }
        }
    }

    fn status(&self) -> SourceStatus {
        self.status.clone()
    }
}

/// Settings of a cache source.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CacheSourceOptions {
    /// Byte credit: what the cache may have in flight beyond what the session has taken.
    pub credit_bytes: u64,
    /// Bytes of packets queued between the network thread and the session (a packet larger
    /// than this passes alone). In bytes, not packets: a queue of a few packets throttled a
    /// file of small packets to a few packets per frame, however fast the link.
    pub queue_bytes: u64,
    /// Stop after this many bytes of packets (None: everything the view ranks).
    pub byte_budget: Option<u64>,
    /// Simulated link speed in bytes per second (None: as fast as the connection goes). Each
    /// packet is handed to the session only once its bytes would have crossed a link of this
    /// speed after the previous one: bandwidth, no latency (for benchmarks over loopback). The
    /// link carries up to `credit_bytes` ahead while the source's thread decodes, as a real one
    /// does.
    pub link_bytes_per_second: Option<u64>,
    /// Ask only for the packets the current view sees; the rest come after a view change
    /// that sees them (default: yes; an off-screen or cancelled band is never sent for
    /// nothing).
    pub visible_only: bool,
}

impl Default for CacheSourceOptions {
    fn default() -> Self {
        CacheSourceOptions {
            credit_bytes: 64 << 10,
            queue_bytes: 64 << 10,
            byte_budget: None,
            link_bytes_per_second: None,
            visible_only: true,
        }
    }
}

/// What the session tells a network source's thread.
pub(crate) enum Control {
    /// The view changed.
    View(ViewSpec),
    /// The session dropped these packets.
    Dropped(Vec<u32>),
}

/// The session's end of a source fed by a network thread (the cache's, the range reader's):
/// packets arrive on a bounded channel, view changes and dropped packets go back on another,
/// and the thread's status is shared. Dropping it closes the control channel, which ends the
/// thread's task, and joins the thread.
#[derive(Debug)]
pub(crate) struct Feed {
    rx: mpsc::UnboundedReceiver<(SourcePacket, OwnedSemaphorePermit)>,
    /// The queue's room in bytes (closed when the feed is dropped, so that a task waiting
    /// for room ends).
    room: Arc<Semaphore>,
    ctl: Option<mpsc::UnboundedSender<Control>>,
    status: Arc<Mutex<SourceStatus>>,
    thread: Option<std::thread::JoinHandle<()>>,
    /// View changes sent to the thread (see [`SourceStatus::views_applied`]).
    views_sent: u64,
}

/// The network thread's end of a feed's queue: packets wait for the session there up to a
/// byte bound (a packet larger than the bound passes alone, when the queue is empty).
#[derive(Debug, Clone)]
pub(crate) struct PacketSender {
    tx: mpsc::UnboundedSender<(SourcePacket, OwnedSemaphorePermit)>,
    room: Arc<Semaphore>,
    bound: u32,
}

/// The session went away.
#[derive(Debug)]
pub(crate) struct QueueClosed;

/// Room reserved in the queue for one packet.
#[derive(Debug)]
pub(crate) struct QueueSlot {
    tx: mpsc::UnboundedSender<(SourcePacket, OwnedSemaphorePermit)>,
    permit: OwnedSemaphorePermit,
}

impl PacketSender {
    /// Waits until the queue has room for a packet of `bytes` bytes.
    pub(crate) async fn reserve(&self, bytes: usize) -> Result<QueueSlot, QueueClosed> {
        let need = (bytes.min(self.bound as usize) as u32).max(1);
        let permit = self
            .room
            .clone()
            .acquire_many_owned(need)
            .await
            .map_err(|_| QueueClosed)?;
        Ok(QueueSlot {
            tx: self.tx.clone(),
            permit,
        })
    }

    /// Waits for room, then queues `packet`.
    pub(crate) async fn send(&self, packet: SourcePacket) -> Result<(), QueueClosed> {
        self.reserve(packet.data.len()).await?.send(packet)
    }
}

impl QueueSlot {
    /// Queues `packet` in the room reserved (freed when the session takes it).
    pub(crate) fn send(self, packet: SourcePacket) -> Result<(), QueueClosed> {
        self.tx.send((packet, self.permit)).map_err(|_| QueueClosed)
    }
}

impl Feed {
    /// Runs `task` (given the packet sender and the control receiver) on a thread named
    /// `name`, on `runtime`, with a queue of `queue_bytes` bytes of packets; `status` is what
    /// it reports.
    pub(crate) fn start<F>(
        name: &str,
        runtime: tokio::runtime::Runtime,
        queue_bytes: u64,
        status: Arc<Mutex<SourceStatus>>,
        task: impl FnOnce(PacketSender, mpsc::UnboundedReceiver<Control>) -> F + Send + 'static,
    ) -> Result<Feed, SourceError>
    where
        F: std::future::Future<Output = ()>,
    {
        let bound =
            queue_bytes.clamp(1, Semaphore::MAX_PERMITS.min(u32::MAX as usize) as u64) as u32;
        let room = Arc::new(Semaphore::new(bound as usize));
        let (tx, rx) = mpsc::unbounded_channel();
        let sender = PacketSender {
            tx,
            room: room.clone(),
            bound,
        };
        let (ctl, ctl_rx) = mpsc::unbounded_channel();
        let thread = std::thread::Builder::new()
            .name(name.into())
            .spawn(move || runtime.block_on(task(sender, ctl_rx)))
            .map_err(|e| SourceError::Thread(e.to_string()))?;
        Ok(Feed {
            rx,
            room,
            ctl: Some(ctl),
            status,
            thread: Some(thread),
            views_sent: 0,
        })
    }

    fn send(&self, c: Control) {
        if let Some(ctl) = &self.ctl {
            let _ = ctl.send(c);
        }
    }
}

impl PacketSource for Feed {
    fn try_next(&mut self) -> Option<SourcePacket> {
        // Dropping the permit gives the packet's room back.
        self.rx.try_recv().ok().map(|(packet, _room)| packet)
    }

    fn set_view(&mut self, spec: &ViewSpec) {
        self.views_sent += 1;
        self.send(Control::View(*spec));
    }

    fn dropped(&mut self, ids: Vec<u32>) {
        if !ids.is_empty() {
            self.send(Control::Dropped(ids));
        }
    }

    fn status(&self) -> SourceStatus {
        let mut s = self
            .status
            .lock()
            .map(|s| s.clone())
            .unwrap_or_else(|e| e.into_inner().clone());
        // Until the thread has applied the last view change, its `done` is about an earlier
        // view (a session that read it would stop with the new view unfinished).
        if s.views_applied < self.views_sent {
            s.done = false;
        }
        // Nor is it done while packets it delivered wait in the queue: the thread marks
        // `done` after queuing the last one (read after the status, so a `done` seen here
        // sees that packet), and a frame that found the queue empty a moment before would
        // otherwise take the view for converged with them untaken.
        if !self.rx.is_empty() {
            s.done = false;
        }
        s
    }
}

impl Drop for Feed {
    fn drop(&mut self) {
        // Closing the control channel ends the network task.
        self.ctl = None;
        self.room.close();
        self.rx.close();
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// Packets pulled from a cache by a background thread (see the module documentation).
#[derive(Debug)]
pub struct CacheSource {
    feed: Feed,
}

impl std::fmt::Debug for Control {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Control::View(_) => f.write_str("View"),
            Control::Dropped(ids) => write!(f, "Dropped({})", ids.len()),
        }
    }
}

impl CacheSource {
    /// Connects to the cache at `url` (plaintext or TLS by its scheme, no token), fetches the
    /// header of `volume` and starts pulling its packets in the order of `spec`.
    pub fn open(
        url: &str,
        volume: VolumeKey,
        spec: ViewSpec,
        options: CacheSourceOptions,
    ) -> Result<(CacheSource, VolumeHeader), SourceError> {
        CacheSource::open_with(url, &ConnectOptions::default(), volume, spec, options)
    }

    /// [`CacheSource::open`] with a CA and a token (`connect`), used for the first connection
    /// and every reconnection. `url` may name several cache nodes over one store,
    /// comma-separated: the first that answers is used, and when its stream fails the source
    /// continues on the next one with what it holds, so nothing is sent twice.
    pub fn open_with(
        url: &str,
        connect: &ConnectOptions,
        volume: VolumeKey,
        spec: ViewSpec,
        options: CacheSourceOptions,
    ) -> Result<(CacheSource, VolumeHeader), SourceError> {
        spec.validate()?;
        let urls: Vec<String> = url
            .split(',')
            .map(str::trim)
            .filter(|u| !u.is_empty())
            .map(str::to_string)
            .collect();
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .map_err(|e| SourceError::Thread(e.to_string()))?;
        let (client, stream, header, node) = runtime.block_on(async {
            let mut last = None;
            for (i, u) in urls.iter().enumerate() {
                // The stream brings the header as its first message, so opening costs one
                // round trip after connecting, not a header request and then a stream.
                let attempt = async {
                    let mut client = CacheClient::connect_with(u, connect).await?;
                    let mut stream = client
                        .refine(stream_request(&volume, spec, Vec::new(), false, &options))
                        .await?;
                    match stream.next().await? {
                        Some(RefineEvent::Header(h)) => Ok::<_, ClientError>((client, stream, *h)),
                        Some(_) => Err(ClientError::Protocol(
                            "the stream did not begin with the volume's header".into(),
                        )),
                        None => Err(ClientError::Protocol(
                            "the stream ended before the volume's header".into(),
                        )),
                    }
                };
                match attempt.await {
                    Ok((c, s, h)) => return Ok((c, s, h, i)),
                    // A node that answers that the volume is missing speaks for the store.
                    Err(e) if urls.len() == 1 || !e.is_node_failure() => return Err(e),
                    Err(e) => {
                        tracing::warn!(node = %u, error = %e, "cache node unavailable; trying the next");
                        last = Some(e);
                    }
                }
            }
            Err(last.unwrap_or_else(|| ClientError::Url {
                url: String::new(),
                reason: "no cache URL given".into(),
            }))
        })?;
        let status = Arc::new(Mutex::new(SourceStatus {
            connected: true,
            ..Default::default()
        }));
        let task = Pull {
            urls,
            node,
            connect: connect.clone(),
            volume,
            view: spec,
            options,
            held: HashSet::new(),
            status: status.clone(),
            link_free: None,
            header: Arc::new(header.header.clone()),
        };
        let feed = Feed::start(
            "wavesplat-cache-source",
            runtime,
            options.queue_bytes,
            status,
            move |tx, ctl| task.run(client, Some(stream), tx, ctl),
        )?;
        Ok((CacheSource { feed }, header))
    }
}

impl PacketSource for CacheSource {
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

/// The request that opens a stream of `volume` for `view`, holding `held` (and the header if
/// `have_header`), with the source's credit and visibility settings.
fn stream_request(
    volume: &VolumeKey,
    view: ViewSpec,
    held: Vec<u32>,
    have_header: bool,
    options: &CacheSourceOptions,
) -> RefineRequest {
    RefineRequest::new(volume.clone(), view)
        .holding(held, have_header)
        .with_credit(options.credit_bytes.max(1))
        .visible_only(options.visible_only)
}

/// The network task's state.
struct Pull {
    /// The cache nodes, tried in turn.
    urls: Vec<String>,
    /// The node in use.
    node: usize,
    /// CA and token for every (re)connection.
    connect: ConnectOptions,
    volume: VolumeKey,
    view: ViewSpec,
    options: CacheSourceOptions,
    /// Packets delivered to the session and not dropped.
    held: HashSet<u32>,
    status: Arc<Mutex<SourceStatus>>,
    /// When the simulated link finishes carrying the last packet.
    link_free: Option<tokio::time::Instant>,
    /// The volume's header (to decode packets off the runtime's thread).
    header: Arc<Header>,
}

/// A packet on its way to the session: crossing the simulated link, then decoding.
type Decoding = std::pin::Pin<
    Box<dyn std::future::Future<Output = Result<SourcePacket, tokio::task::JoinError>> + Send>,
>;

/// How a stream ended.
enum Ended {
    /// The session went away: stop.
    Closed,
    /// The connection failed: reconnect.
    Failed(String),
}

impl Pull {
    fn update(&self, f: impl FnOnce(&mut SourceStatus)) {
        let mut s = self.status.lock().unwrap_or_else(|e| e.into_inner());
        f(&mut s);
    }

    /// Streams until the session goes away, starting with `opened` (a stream already open on
    /// `client`, its header taken) and reconnecting when a stream fails.
    async fn run(
        mut self,
        client: CacheClient,
        mut opened: Option<RefineStream>,
        tx: PacketSender,
        mut ctl: mpsc::UnboundedReceiver<Control>,
    ) {
        let mut client = Some(client);
        let mut backoff = Duration::from_millis(100);
        loop {
            let c = match client.take() {
                Some(c) => c,
                None => match CacheClient::connect_with(&self.urls[self.node], &self.connect).await
                {
                    Ok(c) => c,
                    Err(e) => {
                        self.update(|s| {
                            s.connected = false;
                            s.problem = Some(format!("cache unreachable, retrying: {e}"));
                        });
                        if self.next_node() {
                            continue;
                        }
                        if self.wait(backoff, &mut ctl).await {
                            return;
                        }
                        backoff = (backoff * 2).min(Duration::from_secs(2));
                        continue;
                    }
                },
            };
            match self.stream(c, opened.take(), &tx, &mut ctl).await {
                Ended::Closed => return,
                Ended::Failed(e) => {
                    tracing::warn!(error = %e, "cache stream failed; reconnecting");
                    self.update(|s| {
                        s.connected = false;
                        s.reconnects += 1;
                        s.problem = Some(format!("connection lost, reconnecting: {e}"));
                    });
                    if self.next_node() {
                        continue;
                    }
                    if self.wait(backoff, &mut ctl).await {
                        return;
                    }
                    backoff = (backoff * 2).min(Duration::from_secs(2));
                }
            }
        }
    }

    /// Takes the session's new view: the next stream starts at it, and it is not done until
    /// the cache says so (a `done` of the view before must not end it, also while
    /// reconnecting).
    fn apply_view(&mut self, v: ViewSpec) {
        self.view = v;
        self.update(SourceStatus::view_applied);
    }

    /// Moves on to the next cache node; true when there is another one to try at once (after a
    /// round of all of them, the caller backs off).
    fn next_node(&mut self) -> bool {
        if self.urls.len() < 2 {
            return false;
        }
        self.node = (self.node + 1) % self.urls.len();
        tracing::warn!(node = %self.urls[self.node], "continuing on another cache node");
        self.node != 0
    }

    /// Waits `d` while applying control messages; true when the session went away.
    async fn wait(&mut self, d: Duration, ctl: &mut mpsc::UnboundedReceiver<Control>) -> bool {
        let sleep = tokio::time::sleep(d);
        tokio::pin!(sleep);
        loop {
            tokio::select! {
                _ = &mut sleep => return false,
                c = ctl.recv() => match c {
                    None => return true,
                    Some(Control::View(v)) => self.apply_view(v),
                    Some(Control::Dropped(ids)) => for id in ids { self.held.remove(&id); },
                },
            }
        }
    }

    /// When a packet of `len` bytes read now has crossed the simulated link; `None` without
    /// a link or when it is due within a timer tick.
    fn link_arrival(&mut self, len: usize) -> Option<tokio::time::Instant> {
        let rate = self.options.link_bytes_per_second.filter(|r| *r > 0)?;
        let now = tokio::time::Instant::now();
        let window = Duration::from_secs_f64(self.options.credit_bytes as f64 / rate as f64);
        let begin = link_start(self.link_free, now, window);
        let arrives = begin + Duration::from_secs_f64(len as f64 / rate as f64);
        self.link_free = Some(arrives);
        // Timers tick in milliseconds: a sleep for each small packet capped a link at about
        // a packet per millisecond, whatever its speed. A packet due within a tick goes at
        // once; the link's clock still advances by each packet, so the rate holds.
        (arrives > now + Duration::from_millis(1)).then_some(arrives)
    }

    fn budget_left(&self) -> bool {
        self.budget_left_beyond(0)
    }

    /// Whether the byte budget has room beyond what was delivered and `in_flight` more bytes.
    fn budget_left_beyond(&self, in_flight: u64) -> bool {
        let bytes = self.status.lock().map(|s| s.bytes).unwrap_or(0);
        self.options
            .byte_budget
            .is_none_or(|b| bytes + in_flight < b)
    }

    /// Runs one stream: `opened` if given (opened for the current view while connecting),
    /// else a new one on `client` that resumes with what the session holds.
    async fn stream(
        &mut self,
        mut client: CacheClient,
        opened: Option<RefineStream>,
        tx: &PacketSender,
        ctl: &mut mpsc::UnboundedReceiver<Control>,
    ) -> Ended {
        let mut stream = match opened {
            Some(s) => s,
            None => {
                let mut held: Vec<u32> = self.held.iter().copied().collect();
                held.sort_unstable();
                let request = stream_request(&self.volume, self.view, held, true, &self.options);
                match client.refine(request).await {
                    Ok(s) => s,
                    Err(e) => return Ended::Failed(e.to_string()),
                }
            }
        };
        self.update(|s| {
            s.connected = true;
            s.problem = None;
        });
        // Packets are decoded on the blocking pool, several at once, and handed over in the
        // order they came: one thread decoding them in turn carried ~3 M coefficients/s, less
        // than a 20 Mbit/s link brings (BENCHMARKS.md, "A real GPU"). Half the cores at most:
        // the rest splat, and on two cores a second decoder slowed the session's refinement.
        let mut decoding: FuturesOrdered<Decoding> = FuturesOrdered::new();
        let parallel =
            std::thread::available_parallelism().map_or(1, |n| (n.get() / 2).clamp(1, 8));
        // The next decoded packet, waiting for room in the session's queue.
        let mut pending: Option<SourcePacket> = None;
        // Bytes received and not yet handed over (decoding or pending).
        let mut in_flight: u64 = 0;
        // View changes sent on this stream (each stream starts at the current view).
        let mut views_sent: u32 = 0;
        // The cache said the current view is done; it is, once what it sent is handed over.
        let mut done_after_delivery = false;
        loop {
            // Done once everything received is handed over: when the cache said so, or when
            // the byte budget is spent (also for a view set after it was).
            if pending.is_none()
                && decoding.is_empty()
                && (done_after_delivery || !self.budget_left())
            {
                done_after_delivery = false;
                self.update(|s| s.done = true);
            }
            let want_more = decoding.len() + usize::from(pending.is_some()) < parallel
                && self.budget_left_beyond(in_flight);
            let pending_bytes = pending.as_ref().map_or(0, |p| p.data.len());
            tokio::select! {
                biased;
                c = ctl.recv() => match c {
                    None => return Ended::Closed,
                    Some(Control::View(v)) => {
                        done_after_delivery = false;
                        self.apply_view(v);
                        views_sent = views_sent.wrapping_add(1);
                        if let Err(e) = stream.control().set_view(&v).await {
                            return Ended::Failed(end_status(&mut stream, e).await);
                        }
                    }
                    Some(Control::Dropped(ids)) => {
                        for id in &ids {
                            self.held.remove(id);
                        }
                        if let Err(e) = stream.control().holdings(Vec::new(), ids).await {
                            return Ended::Failed(end_status(&mut stream, e).await);
                        }
                    }
                },
                slot = tx.reserve(pending_bytes), if pending.is_some() => {
                    let Ok(slot) = slot else { return Ended::Closed };
                    let p = pending.take().expect("pending packet");
                    let len = p.data.len() as u64;
                    in_flight = in_flight.saturating_sub(len);
                    self.held.insert(p.id);
                    self.update(|s| {
                        s.packets += 1;
                        s.bytes += len;
                    });
                    if slot.send(p).is_err() {
                        return Ended::Closed;
                    }
                    if let Err(e) = stream.control().grant(len).await {
                        return Ended::Failed(end_status(&mut stream, e).await);
                    }
                }
                decoded = decoding.next(), if pending.is_none() && !decoding.is_empty() => {
                    match decoded {
                        Some(Ok(p)) => pending = Some(p),
                        // A decoder that panicked: asking for the packet again would repeat
                        // it, so the source stops and says why.
                        Some(Err(e)) => {
                            self.update(|s| {
                                s.problem = Some(format!("decoding a packet failed: {e}"));
                            });
                            return Ended::Closed;
                        }
                        None => {}
                    }
                }
                ev = stream.next(), if want_more => match ev {
                    Ok(Some(RefineEvent::Packet(p))) => {
                        if !self.held.contains(&p.id) {
                            in_flight += p.data.len() as u64;
                            // It crosses the simulated link (if any) and is decoded off this
                            // loop, so packets that arrived before it are handed over
                            // meanwhile; a packet that fails to decode goes on as bytes and
                            // the session reports it.
                            let arrives = self.link_arrival(p.data.len());
                            let header = Arc::clone(&self.header);
                            decoding.push_back(Box::pin(async move {
                                if let Some(t) = arrives {
                                    tokio::time::sleep_until(t).await;
                                }
                                tokio::task::spawn_blocking(move || {
                                    let decoded = decode_for_session(&header, &p.data);
                                    SourcePacket { id: p.id, data: p.data, decoded }
                                })
                                .await
                            }));
                        } else {
                            self.update(|s| s.resent += 1);
                        }
                    }
                    // A `done` for a view before the last one sent is stale: the new view
                    // has its own.
                    Ok(Some(RefineEvent::Done { views, .. })) => {
                        if views == views_sent {
                            done_after_delivery = true;
                        }
                    }
                    Ok(Some(RefineEvent::Header(_))) => {}
                    Ok(None) => return Ended::Failed("the cache closed the stream".into()),
                    Err(e) => return Ended::Failed(e.to_string()),
                },
            }
        }
    }
}

/// How long a stream whose request side closed is read for the status the cache ended it with.
const END_STATUS_WAIT: Duration = Duration::from_secs(5);

/// Why `stream` ended, when a message to the cache could not be sent on it (`e`). Its request
/// side closes as soon as the cache ends the stream, and the cache's status (`Unavailable`
/// when its object store fails, say) comes only after the packets it sent before, which may
/// still be in flight: the rest of the stream is read for that status, so the source reports
/// the cache's reason rather than that the stream closed. Packets read here are not delivered
/// nor held, so the next stream sends them.
async fn end_status(stream: &mut RefineStream, e: ClientError) -> String {
    if !matches!(e, ClientError::Closed) {
        return e.to_string();
    }
    let rest = async {
        loop {
            match stream.next().await {
                Ok(Some(_)) => {}
                Ok(None) => return "the cache closed the stream".to_string(),
                Err(status) => return status.to_string(),
            }
        }
    };
    tokio::time::timeout(END_STATUS_WAIT, rest)
        .await
        .unwrap_or_else(|_| e.to_string())
}

/// When a packet starts across the simulated link: when the link came free (`free`) if this
/// thread asks for it no later than the credit window's crossing time (`window`) after that,
/// else now. A real link keeps carrying the bytes the cache has credit for while the receiving
/// thread decodes the previous packet, so a thread that comes back a little late finds the
/// packet already across; one that comes back later than a window's worth of bytes found the
/// link idle (the cache had nothing it could send), and the packet starts now.
fn link_start(
    free: Option<tokio::time::Instant>,
    now: tokio::time::Instant,
    window: Duration,
) -> tokio::time::Instant {
    match free {
        Some(f) if f + window >= now => f,
        _ => now,
    }
}

impl<T: PacketSource + ?Sized> PacketSource for Box<T> {
    fn try_next(&mut self) -> Option<SourcePacket> {
        (**self).try_next()
    }
    fn set_view(&mut self, spec: &ViewSpec) {
        (**self).set_view(spec)
    }
    fn dropped(&mut self, ids: Vec<u32>) {
        (**self).dropped(ids)
    }
    fn status(&self) -> SourceStatus {
        (**self).status()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use wavesplat_codec::view::View;

    /// A feed whose thread has queued its last packet and said it is done is not done to the
    /// session until that packet is taken.
    #[test]
    fn a_feed_is_not_done_while_its_queue_holds_packets() {
        let runtime = tokio::runtime::Builder::new_current_thread()
            .build()
            .expect("runtime");
        let status = Arc::new(Mutex::new(SourceStatus::default()));
        let shared = status.clone();
        let (queued_tx, queued_rx) = std::sync::mpsc::channel();
        let mut feed = Feed::start("test-feed", runtime, 1 << 16, status, move |tx, mut ctl| {
            async move {
                let packet = SourcePacket {
                    id: 7,
                    data: vec![0; 16],
                    decoded: None,
                };
                if tx.send(packet).await.is_ok() {
                    shared.lock().expect("status").done = true;
                    let _ = queued_tx.send(());
                }
                // Runs until the feed is dropped.
                while ctl.recv().await.is_some() {}
            }
        })
        .expect("feed");
        queued_rx.recv().expect("the packet was queued");
        assert!(!feed.status().done, "done with a packet still queued");
        let p = feed.try_next().expect("the queued packet");
        assert_eq!(p.id, 7);
        assert!(feed.status().done);
    }

    /// The simulated link runs on while the thread decodes, by up to a credit window: a packet
    /// asked for late but within the window starts when the link came free, one asked for
    /// after a longer pause starts when asked, and a busy link delays it.
    #[test]
    fn the_link_carries_a_credit_window_ahead_of_a_busy_thread() {
        let now = tokio::time::Instant::now();
        let ms = Duration::from_millis;
        let window = ms(50);
        assert_eq!(link_start(None, now, window), now);
        // Busy until later: the packet waits for the link.
        assert_eq!(link_start(Some(now + ms(30)), now, window), now + ms(30));
        // Came free 20 ms ago, thread busy: the packet crossed meanwhile.
        assert_eq!(link_start(Some(now - ms(20)), now, window), now - ms(20));
        assert_eq!(link_start(Some(now - ms(50)), now, window), now - ms(50));
        // Idle for longer than a window: nothing was in flight, it starts now.
        assert_eq!(link_start(Some(now - ms(51)), now, window), now);
    }

    /// A fed source is not done after a view change until its thread has applied it: a thread
    /// that said `done` for the old view and has not yet read the change must not end the new
    /// view (a render once stopped there with the new view unfinished, under load).
    #[test]
    fn a_view_change_is_not_done_before_the_thread_applies_it() {
        let runtime = tokio::runtime::Builder::new_current_thread()
            .build()
            .unwrap();
        let status = Arc::new(Mutex::new(SourceStatus::default()));
        let (go_tx, go_rx) = std::sync::mpsc::channel::<()>();
        let shared = status.clone();
        let mut feed = Feed::start(
            "test-feed",
            runtime,
            1,
            status,
            move |_tx, mut ctl| async move {
                shared.lock().unwrap().done = true;
                // Hold the change back until the test says so, then apply it (done again).
                let _ = tokio::task::spawn_blocking(move || go_rx.recv()).await;
                if let Some(Control::View(_)) = ctl.recv().await {
                    let mut s = shared.lock().unwrap();
                    s.views_applied += 1;
                    s.done = true;
                }
                while ctl.recv().await.is_some() {}
            },
        )
        .unwrap();
        let until = |f: &Feed, done: bool| {
            for _ in 0..2000 {
                if f.status().done == done {
                    return true;
                }
                std::thread::sleep(Duration::from_millis(1));
            }
            false
        };
        assert!(until(&feed, true), "the first view is done");
        feed.set_view(&ViewSpec::single(View::new(1.0, 0.5, 8, 8)));
        let early = feed.status().done;
        // Let the thread go before asserting, so that a failure does not leave it waiting.
        go_tx.send(()).unwrap();
        assert!(!early, "done before the change was applied");
        assert!(until(&feed, true), "the applied change is done");
    }
}
