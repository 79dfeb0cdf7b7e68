//! The cache source: packets pulled from a cache over gRPC by a background thread with a byte
//! credit renewed as the session takes them, view changes and dropped packets sent on the same
//! stream, reconnection with backoff (on the next cache node when there are several), packets
//! decoded off the runtime's thread, and an optionally simulated link speed. A bricked volume's
//! packets (numbered brick after brick, ranked across bricks by the cache) decode with their
//! brick's header; [`CacheSource::bricked_volume`] is what a session draws them into.

use super::file::check_display;
use super::{
    decode_for_session, packet_source_via_feed, Control, Feed, PacketSender, SourceError,
    SourcePacket, SourceStatus,
};
use crate::session::{BrickedVolume, SessionBrick};
use futures_util::stream::{FuturesOrdered, StreamExt};
use std::collections::HashSet;
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::sync::mpsc;
use wavesplat_client::{
    CacheClient, ClientError, ConnectOptions, RefineEvent, RefineRequest, RefineStream,
    VolumeHeader, VolumeKey,
};
use wavesplat_codec::format::Header;
use wavesplat_codec::view::ViewSpec;

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
    /// Of a time series, the time point drawn (its components' packets only; 0 for any other
    /// volume).
    pub time_point: u32,
}

impl Default for CacheSourceOptions {
    fn default() -> Self {
        CacheSourceOptions {
            credit_bytes: 64 << 10,
            queue_bytes: 64 << 10,
            byte_budget: None,
            link_bytes_per_second: None,
            visible_only: true,
            time_point: 0,
        }
    }
}

/// Packets pulled from a cache by a background thread (see the module documentation).
#[derive(Debug)]
pub struct CacheSource {
    feed: Feed,
    /// The volume as a session draws it, when it is bricked (or a time point of a series).
    bricked: Option<Box<BrickedVolume>>,
    /// Of a time series, its manifest.
    series: Option<Box<wavesplat_codec::format::series::SeriesManifest>>,
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
        let (headers, bricked) = PacketHeaders::new(&header, options.time_point as usize)?;
        let headers = Arc::new(headers);
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
            headers,
        };
        let bricked = bricked.map(Box::new);
        let feed = Feed::start(
            "wavesplat-cache-source",
            runtime,
            options.queue_bytes,
            status,
            move |tx, ctl| task.run(client, Some(stream), tx, ctl),
        )?;
        let series = header.series.clone();
        Ok((
            CacheSource {
                feed,
                bricked,
                series,
            },
            header,
        ))
    }

    /// The volume as a session draws it ([`crate::session::RenderSession::new_bricked`]), when
    /// it is bricked; `None` for one volume.
    pub fn bricked_volume(&self) -> Option<BrickedVolume> {
        self.bricked.as_deref().cloned()
    }

    /// Of a time series, its manifest (its time points and their times); `None` otherwise.
    pub fn series(&self) -> Option<&wavesplat_codec::format::series::SeriesManifest> {
        self.series.as_deref()
    }
}

/// One brick as a stream's packets name it: its first packet's id on the wire, its header, the
/// weight its values are scaled by and its first packet's id in the session.
#[derive(Debug)]
struct PacketBrick {
    first: u32,
    packets: u32,
    header: Header,
    weight: f32,
    /// `None`: a brick of a series component the time point does not name.
    local_first: Option<u32>,
}

/// The headers a stream's packets decode with and the ids the session knows them by: one
/// volume's (ids as sent), each brick's for a bricked volume (ids numbered brick after brick),
/// and for a time point of a series each of its components' bricks, numbered in the session
/// brick after brick in the time point's order, values scaled by the component's weight.
#[derive(Debug)]
struct PacketHeaders {
    whole: Header,
    /// Per brick, ascending by `first`.
    bricks: Vec<PacketBrick>,
    /// (session id of its first packet, brick) for the bricks the session draws, ascending.
    by_local: Vec<(u32, usize)>,
}

impl PacketHeaders {
    /// The headers of the volume of `header` at `time_point` (of a series; 0 otherwise), and the
    /// volume as a session draws it when it is bricked or a series (its bricks checked to share
    /// one image).
    fn new(
        header: &VolumeHeader,
        time_point: usize,
    ) -> Result<(PacketHeaders, Option<BrickedVolume>), SourceError> {
        let mut first = 0u32;
        let mut bricks: Vec<PacketBrick> = header
            .bricks
            .iter()
            .map(|b| {
                let at = first;
                first = first.saturating_add(b.packets);
                PacketBrick {
                    first: at,
                    packets: b.packets,
                    header: b.header.clone(),
                    weight: 1.0,
                    local_first: header.series.is_none().then_some(at),
                }
            })
            .collect();
        let mut whole = header.header.clone();
        // The bricks the session draws, in its order: (brick, origin).
        let mut drawn: Vec<usize> = Vec::new();
        match &header.series {
            None => {
                if time_point != 0 {
                    return Err(SourceError::Unsupported(format!(
                        "time point {time_point} of a volume that is not a time series"
                    )));
                }
                drawn.extend(0..bricks.len());
            }
            Some(m) => {
                let point = m.points.get(time_point).ok_or_else(|| {
                    SourceError::Unsupported(format!(
                        "time point {time_point}: the series has {}",
                        m.points.len()
                    ))
                })?;
                let mut offset = 0f64;
                let mut local = 0u32;
                for &(c, weight) in &point.terms {
                    let of_c: Vec<usize> = (0..bricks.len())
                        .filter(|&k| header.bricks[k].component == c)
                        .collect();
                    let Some(&k0) = of_c.first() else {
                        return Err(SourceError::Client(ClientError::Protocol(format!(
                            "the cache's header has no bricks of component {c}"
                        ))));
                    };
                    offset += f64::from(weight) * bricks[k0].header.color.mean[0];
                    for k in of_c {
                        bricks[k].weight = weight;
                        bricks[k].local_first = Some(local);
                        local = local.saturating_add(bricks[k].packets);
                        drawn.push(k);
                    }
                }
                whole = crate::bricked::time_point_header(&whole, m.space.spacing, offset);
            }
        }
        let volume = if drawn.is_empty() {
            None
        } else {
            let volume = BrickedVolume {
                whole: whole.clone(),
                bricks: drawn
                    .iter()
                    .map(|&k| {
                        let mut h = bricks[k].header.clone();
                        if header.series.is_some() {
                            h.color.mean[0] = whole.color.mean[0];
                        }
                        SessionBrick {
                            header: h,
                            origin: header.bricks[k].origin,
                            packets: bricks[k].packets,
                        }
                    })
                    .collect(),
            };
            let first = &volume.bricks[0].header;
            for (i, b) in volume.bricks.iter().enumerate() {
                check_display(i, &b.header, first)?;
            }
            volume.check()?;
            Some(volume)
        };
        let mut by_local: Vec<(u32, usize)> = drawn
            .iter()
            .filter_map(|&k| bricks[k].local_first.map(|l| (l, k)))
            .collect();
        by_local.sort_unstable();
        Ok((
            PacketHeaders {
                whole,
                bricks,
                by_local,
            },
            volume,
        ))
    }

    /// The brick packet `id` (as sent) belongs to (`None` for one volume).
    fn brick(&self, id: u32) -> Option<&PacketBrick> {
        match self.bricks.partition_point(|b| b.first <= id) {
            0 => None,
            k => Some(&self.bricks[k - 1]),
        }
    }

    /// The header packet `id` (as sent) decodes with.
    fn header_of(&self, id: u32) -> &Header {
        self.brick(id).map_or(&self.whole, |b| &b.header)
    }

    /// The weight packet `id`'s (as sent) values are scaled by.
    fn weight_of(&self, id: u32) -> f32 {
        self.brick(id).map_or(1.0, |b| b.weight)
    }

    /// The session's id of packet `id` (as sent); `None` for a packet of a series component the
    /// time point does not name.
    fn local(&self, id: u32) -> Option<u32> {
        match self.brick(id) {
            None => Some(id),
            Some(b) => b.local_first.map(|l| l + (id - b.first)),
        }
    }

    /// The id on the wire of the session's packet `local`.
    fn global(&self, local: u32) -> u32 {
        match self.by_local.partition_point(|(l, _)| *l <= local) {
            0 => local,
            k => {
                let (l, brick) = self.by_local[k - 1];
                self.bricks[brick].first + (local - l)
            }
        }
    }
}

packet_source_via_feed!(CacheSource);

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
        .at_time_point(options.time_point)
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
    /// The headers packets decode with (off the runtime's thread).
    headers: Arc<PacketHeaders>,
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
        let mut backoff = wavesplat_net::backoff::Backoff::default();
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
                        if self.wait(backoff.next_delay(), &mut ctl).await {
                            return;
                        }
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
                    if self.wait(backoff.next_delay(), &mut ctl).await {
                        return;
                    }
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
                        let ids: Vec<u32> =
                            ids.into_iter().map(|id| self.headers.global(id)).collect();
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
                    self.held.insert(self.headers.global(p.id));
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
                        let Some(local) = self.headers.local(p.id) else {
                            return Ended::Failed(format!(
                                "the cache sent packet {} of a component time point {} does \
                                 not name",
                                p.id, self.options.time_point
                            ));
                        };
                        if !self.held.contains(&p.id) {
                            in_flight += p.data.len() as u64;
                            // It crosses the simulated link (if any) and is decoded off this
                            // loop, so packets that arrived before it are handed over
                            // meanwhile; a packet that fails to decode goes on as bytes and
                            // the session reports it.
                            let arrives = self.link_arrival(p.data.len());
                            let headers = Arc::clone(&self.headers);
                            decoding.push_back(Box::pin(async move {
                                if let Some(t) = arrives {
                                    tokio::time::sleep_until(t).await;
                                }
                                tokio::task::spawn_blocking(move || {
                                    let header = headers.header_of(p.id);
                                    let mut decoded = decode_for_session(header, &p.data);
                                    let weight = headers.weight_of(p.id);
                                    if let (Some((_, c)), true) = (decoded.as_mut(), weight != 1.0)
                                    {
                                        c.iter_mut().for_each(|c| c.value *= weight);
                                    }
                                    SourcePacket { id: local, data: p.data, decoded }
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

#[cfg(test)]
mod tests {
    use super::*;

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
}
