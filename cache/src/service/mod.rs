//! The gRPC `Cache` service: request handling on top of [`Store`] and [`Priority`]. Heavy work
//! (validating and storing an upload) runs on the blocking pool. A refinement session is one
//! task per stream that owns the unsent-packet queue: it reads client messages (view changes,
//! holdings, credit) and sends packets through a bounded channel, so it only produces as fast as
//! the client consumes; with a byte credit (the client pulls) it also never has more than the
//! credit in flight (plus the one packet that may overshoot it, paid back from later grants), so
//! a view change reorders everything the client has not yet asked for. A request that does not
//! decode, or is over the message-size limit, ends the stream with the client fault's status.
//! A session does not wait for its view's plan to start: it sends the header and the first
//! packets in file order (the global significance order) while the plan runs on a bounded
//! pool, then the rest in the view's order.
//!
//! This module holds the service and its requests; `session` holds a refinement stream's state
//! and loop, and the planning of its view on the planner pool.

mod session;

use crate::convert;
use crate::error::CacheError;
use crate::store::{validate_name, OpenVolume, Store, Upload};
use session::{plan, Session};
use std::collections::HashMap;
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use tokio::sync::{mpsc, watch, Semaphore};
use tokio_stream::wrappers::ReceiverStream;
use tokio_stream::Stream;
use tonic::{Request, Response, Status, Streaming};
use wavesplat_net::deadline::request_deadline;
use wavesplat_net::status::client_fault;
use wavesplat_net::Caller;
use wavesplat_proto::pb;
use wavesplat_proto::pb::cache_server::Cache;

/// Largest upload chunk message (bytes).
pub const MAX_CHUNK_BYTES: usize = 4 << 20;
/// Responses buffered per refinement stream before the server waits for the client.
pub const STREAM_BUFFER: usize = 4;
/// Largest `FirstPackets` budget (bytes).
pub const MAX_FIRST_PACKETS_BYTES: u64 = 16 << 20;
/// While a new stream's view is being planned it sends packets in file order, up to this
/// share of the volume's bytes (1/64; always at least one packet): the coarse start every view
/// needs, small enough that a view whose plan differs much from the global order loses little.
const UNPLANNED_SHARE: u64 = 64;

/// Limits per caller (its token's identity, or its address without authentication).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Fairness {
    /// Refinement streams one caller may have open at once.
    pub max_streams_per_caller: usize,
    /// Uploads one caller may have in progress at once; more wait their turn (so one caller
    /// cannot take every upload slot).
    pub max_uploads_per_caller: usize,
    /// Longest wait for an upload's next message once it holds an upload slot: an upload that
    /// sends nothing for this long ends (`DeadlineExceeded`, nothing stored) and frees its
    /// slot, so idle uploads cannot hold every slot for ever.
    pub upload_idle: std::time::Duration,
}

impl Default for Fairness {
    fn default() -> Self {
        Fairness {
            max_streams_per_caller: 64,
            max_uploads_per_caller: 4,
            upload_idle: std::time::Duration::from_secs(120),
        }
    }
}

/// Open streams and upload slots per caller.
#[derive(Debug, Default)]
struct Open {
    streams: HashMap<String, usize>,
    uploads: HashMap<String, Arc<Semaphore>>,
}

/// A stream counted against its caller until dropped.
struct Slot {
    open: Arc<Mutex<Open>>,
    caller: String,
}

impl Drop for Slot {
    fn drop(&mut self) {
        if let Ok(mut o) = self.open.lock() {
            if let Some(n) = o.streams.get_mut(&self.caller) {
                *n -= 1;
                if *n == 0 {
                    o.streams.remove(&self.caller);
                }
            }
        }
    }
}

fn caller<T>(request: &Request<T>) -> String {
    request
        .extensions()
        .get::<Caller>()
        .map_or_else(|| "unknown".to_string(), |c| c.identity.clone())
}

/// The service implementation.
#[derive(Debug, Clone)]
pub struct CacheService {
    store: Store,
    /// Becomes `true` when the server shuts down: open refinement streams then end (a viewer
    /// keeps its stream open while it may still change the view, so graceful shutdown would
    /// otherwise wait for it forever).
    stopping: watch::Receiver<bool>,
    /// Upload slots (`Limits::max_concurrent_uploads`).
    uploads: Arc<Semaphore>,
    /// Bytes uploads may hold in memory (`Limits::max_buffered_bytes`), one permit a byte.
    buffered: Arc<Semaphore>,
    fairness: Fairness,
    open: Arc<Mutex<Open>>,
    /// View plans running at once (one per two cores, at least one): a burst of session starts
    /// finishes its plans in arrival order rather than all of them together, late, and leaves
    /// the other cores to the streams that are sending (with one planner per core, 64 starts
    /// on two cores had a first-packet p99 of 40–58 ms; with one, 20–30 ms: BENCHMARKS.md).
    /// Small volumes' plans skip it ([`CHEAP_PLAN_PACKETS`]).
    planners: Arc<Semaphore>,
}

impl CacheService {
    /// A service over `store` that ends its streams once `stopping` becomes `true`.
    pub fn new(store: Store, stopping: watch::Receiver<bool>) -> CacheService {
        Self::with_fairness(store, stopping, Fairness::default())
    }

    /// The same, with per-caller limits.
    pub fn with_fairness(
        store: Store,
        stopping: watch::Receiver<bool>,
        fairness: Fairness,
    ) -> CacheService {
        let limits = *store.limits();
        let bytes = usize::try_from(limits.max_buffered_bytes)
            .unwrap_or(usize::MAX)
            .min(Semaphore::MAX_PERMITS);
        CacheService {
            store,
            stopping,
            uploads: Arc::new(Semaphore::new(limits.max_concurrent_uploads)),
            buffered: Arc::new(Semaphore::new(bytes)),
            fairness,
            open: Arc::default(),
            planners: Arc::new(Semaphore::new(
                std::thread::available_parallelism().map_or(1, |n| (n.get() / 2).max(1)),
            )),
        }
    }

    /// Counts a refinement stream against its caller, or refuses it over the caller's limit.
    fn stream_slot<T>(&self, request: &Request<T>) -> Result<Slot, Status> {
        let caller = caller(request);
        let limit = self.fairness.max_streams_per_caller;
        let mut open = self
            .open
            .lock()
            .map_err(|_| Status::internal("caller table poisoned"))?;
        let n = open.streams.entry(caller.clone()).or_insert(0);
        if *n >= limit {
            return Err(CacheError::Busy(format!(
                "{caller} has {n} refinement streams open; the limit per caller is {limit}"
            ))
            .into());
        }
        *n += 1;
        Ok(Slot {
            open: self.open.clone(),
            caller,
        })
    }

    /// The caller's upload slots.
    fn upload_slots<T>(&self, request: &Request<T>) -> Result<Arc<Semaphore>, Status> {
        let limit = self.fairness.max_uploads_per_caller.max(1);
        let mut open = self
            .open
            .lock()
            .map_err(|_| Status::internal("caller table poisoned"))?;
        if open.uploads.len() > 4096 {
            open.uploads.retain(|_, s| s.available_permits() < limit);
        }
        Ok(open
            .uploads
            .entry(caller(request))
            .or_insert_with(|| Arc::new(Semaphore::new(limit)))
            .clone())
    }
}

/// Reads the next message of a client stream; a message the client got wrong is its fault.
async fn next_message<T>(
    s: &mut (impl Stream<Item = Result<T, Status>> + Unpin),
) -> Result<Option<T>, Status> {
    use tokio_stream::StreamExt;
    s.next().await.transpose().map_err(client_fault)
}

/// Set when a handler is dropped before it finished (the client went away or its deadline
/// passed): work it handed to the blocking pool then rolls back instead of committing.
#[derive(Default)]
struct AbandonGuard {
    flag: Arc<AtomicBool>,
    disarmed: bool,
}

impl AbandonGuard {
    fn flag(&self) -> Arc<AtomicBool> {
        self.flag.clone()
    }
    fn disarm(mut self) {
        self.disarmed = true;
    }
}

impl Drop for AbandonGuard {
    fn drop(&mut self) {
        if !self.disarmed {
            self.flag.store(true, Ordering::SeqCst);
        }
    }
}

async fn blocking<T: Send + 'static>(
    f: impl FnOnce() -> Result<T, CacheError> + Send + 'static,
) -> Result<T, Status> {
    tokio::task::spawn_blocking(f)
        .await
        .map_err(|e| Status::internal(format!("task failed: {e}")))?
        .map_err(Status::from)
}

type RefineStream = Pin<Box<dyn Stream<Item = Result<pb::RefineResponse, Status>> + Send>>;

#[tonic::async_trait]
impl Cache for CacheService {
    async fn ingest(
        &self,
        request: Request<Streaming<pb::IngestRequest>>,
    ) -> Result<Response<pb::IngestResponse>, Status> {
        // The deadline is honoured up to the commit: if it passes (or the client goes away and
        // this handler is dropped) before, nothing is stored. A reply lost after the commit
        // leaves the volume stored; ingest is idempotent, so repeating it returns the volume
        // with `existed`.
        let deadline = request_deadline(request.metadata());
        let caller_slots = self.upload_slots(&request)?;
        let abandoned = AbandonGuard::default();
        let mut inbound = request.into_inner();
        let start = match next_message(&mut inbound).await?.and_then(|m| m.msg) {
            Some(pb::ingest_request::Msg::Start(s)) => s,
            _ => {
                return Err(CacheError::InvalidRequest(
                    "the first ingest message must be `start`".into(),
                )
                .into())
            }
        };
        validate_name(&start.name)?;
        let declared = convert::sha256(&start.sha256)?;
        let limit = self.store.limits().max_upload_bytes;
        if start.total_size > limit {
            return Err(CacheError::TooLarge {
                what: "upload",
                size: start.total_size,
                limit,
            }
            .into());
        }
        // Uploads beyond the caller's or the server's limit wait here without reading their
        // stream (the transport's flow control holds the client back).
        let _caller_slot = caller_slots
            .acquire_owned()
            .await
            .map_err(|_| Status::unavailable("the cache is shutting down"))?;
        let _slot = self
            .uploads
            .clone()
            .acquire_owned()
            .await
            .map_err(|_| Status::unavailable("the cache is shutting down"))?;
        let store = self.store.clone();
        let name = start.name;
        let total = start.total_size;
        let mut upload = blocking(move || Upload::begin(&store, &name, declared, total)).await?;
        let mut held: Option<(u64, tokio::sync::OwnedSemaphorePermit)> = None;
        let idle = self.fairness.upload_idle;
        loop {
            let Ok(m) = tokio::time::timeout(idle, next_message(&mut inbound)).await else {
                tracing::debug!(
                    received = upload.received(),
                    "an upload sent nothing for {idle:?}"
                );
                return Err(Status::deadline_exceeded(format!(
                    "the upload sent nothing for {} s; nothing was stored",
                    idle.as_secs_f64()
                )));
            };
            let Some(m) = m? else { break };
            let chunk = match m.msg {
                Some(pb::ingest_request::Msg::Chunk(c)) => c,
                _ => {
                    return Err(CacheError::InvalidRequest(
                        "only `chunk` messages may follow `start`".into(),
                    )
                    .into())
                }
            };
            // Reserve what the upload may hold from now on before it holds it; an upload waits
            // only while it holds no reservation, so uploads cannot starve each other.
            let need = upload.memory_need();
            if held.as_ref().map_or(0, |h| h.0) != need {
                held = None;
                if need > 0 {
                    let permits = u32::try_from(need).unwrap_or(u32::MAX);
                    let permit = self
                        .buffered
                        .clone()
                        .acquire_many_owned(permits)
                        .await
                        .map_err(|_| Status::unavailable("the cache is shutting down"))?;
                    held = Some((need, permit));
                }
            }
            upload = blocking(move || {
                upload.push(&chunk)?;
                Ok(upload)
            })
            .await?;
        }
        drop(held);
        let flag = abandoned.flag();
        let done = blocking(move || {
            upload.finish(|| {
                if flag.load(Ordering::SeqCst) {
                    Some(CacheError::Cancelled("the client went away".into()))
                } else if deadline.is_some_and(|d| std::time::Instant::now() >= d) {
                    Some(CacheError::DeadlineExceeded(
                        "the upload was complete but its deadline passed before the commit; \
                         nothing was stored"
                            .into(),
                    ))
                } else {
                    None
                }
            })
        })
        .await?;
        abandoned.disarm();
        Ok(Response::new(pb::IngestResponse {
            volume: Some(convert::volume_info(&done.volume)),
            existed: done.existed,
        }))
    }

    async fn list(
        &self,
        _request: Request<pb::ListRequest>,
    ) -> Result<Response<pb::ListResponse>, Status> {
        let store = self.store.clone();
        let volumes = blocking(move || store.list()).await?;
        Ok(Response::new(pb::ListResponse {
            volumes: volumes.iter().map(convert::volume_info).collect(),
        }))
    }

    async fn describe(
        &self,
        request: Request<pb::DescribeRequest>,
    ) -> Result<Response<pb::VolumeInfo>, Status> {
        let key = convert::volume_key(request.into_inner().volume)?;
        let store = self.store.clone();
        let meta = blocking(move || store.describe(&key)).await?;
        Ok(Response::new(convert::volume_info(&meta)))
    }

    async fn delete(
        &self,
        request: Request<pb::DeleteRequest>,
    ) -> Result<Response<pb::DeleteResponse>, Status> {
        let key = convert::volume_key(request.into_inner().volume)?;
        let store = self.store.clone();
        let id = blocking(move || store.delete(&key)).await?;
        Ok(Response::new(pb::DeleteResponse { id }))
    }

    async fn header(
        &self,
        request: Request<pb::DescribeRequest>,
    ) -> Result<Response<pb::VolumeHeader>, Status> {
        let key = convert::volume_key(request.into_inner().volume)?;
        let store = self.store.clone();
        let (volume, name) =
            blocking(move || Ok((store.open_volume(store.resolve(&key)?)?, key))).await?;
        Ok(Response::new(convert::volume_header(
            &named(&volume, &name),
            &volume.index,
        )))
    }

    async fn packet_table(
        &self,
        request: Request<pb::DescribeRequest>,
    ) -> Result<Response<pb::PacketTableResponse>, Status> {
        let key = convert::volume_key(request.into_inner().volume)?;
        let store = self.store.clone();
        let volume = blocking(move || store.open_volume(store.resolve(&key)?)).await?;
        Ok(Response::new(pb::PacketTableResponse {
            packets: volume
                .index
                .packets
                .iter()
                .map(convert::packet_entry)
                .collect(),
        }))
    }

    async fn first_packets(
        &self,
        request: Request<pb::FirstPacketsRequest>,
    ) -> Result<Response<pb::FirstPacketsResponse>, Status> {
        let req = request.into_inner();
        let key = convert::volume_key(req.volume)?;
        if req.max_bytes > MAX_FIRST_PACKETS_BYTES {
            return Err(CacheError::TooLarge {
                what: "first-packets budget",
                size: req.max_bytes,
                limit: MAX_FIRST_PACKETS_BYTES,
            }
            .into());
        }
        let store = self.store.clone();
        let resp = blocking(move || {
            let volume = store.open_volume(store.resolve(&key)?)?;
            if volume.index.bricked.is_some() {
                return Err(CacheError::Unsupported(
                    "a bricked volume's first packets are one brick's: its packets are \
                     streamed by Refine, whose header message carries its bricks"
                        .into(),
                ));
            }
            if volume.index.series.is_some() {
                return Err(CacheError::Unsupported(
                    "a time series' first packets are one component's: a time point is \
                     streamed by Refine (its view's time_point), whose header message carries \
                     every component's bricks"
                        .into(),
                ));
            }
            // The budget counts each packet as it goes on the wire (its fields and framing,
            // ~10 bytes beside its data): counting the data alone let a response at the most
            // a client may ask for outgrow the server's message limit on small packets.
            let mut packets = Vec::new();
            let mut used = 0u64;
            for (i, p) in volume.index.packets.iter().enumerate() {
                let packet = pb::Packet {
                    id: i as u32,
                    tile: p.tile,
                    layer: p.layer,
                    data: volume.packet(i as u32)?,
                    priority: 0.0,
                };
                let wire = wavesplat_proto::repeated_entry_len(&packet) as u64;
                if !packets.is_empty() && used + wire > req.max_bytes {
                    break;
                }
                used += wire;
                packets.push(packet);
            }
            Ok(pb::FirstPacketsResponse {
                header: volume.index.header_bytes.clone(),
                packets,
            })
        })
        .await?;
        Ok(Response::new(resp))
    }

    type RefineStream = RefineStream;

    async fn refine(
        &self,
        request: Request<Streaming<pb::RefineRequest>>,
    ) -> Result<Response<Self::RefineStream>, Status> {
        let slot = self.stream_slot(&request)?;
        let mut inbound = request.into_inner();
        let start = match next_message(&mut inbound).await?.and_then(|m| m.msg) {
            Some(pb::refine_request::Msg::Start(s)) => s,
            _ => {
                return Err(CacheError::InvalidRequest(
                    "the first refine message must be `start`".into(),
                )
                .into())
            }
        };
        let key = convert::volume_key(start.volume)?;
        let time_point = convert::time_point(start.view.as_ref());
        let spec = convert::view_spec(start.view)?;
        let store = self.store.clone();
        let (volume, name) = blocking(move || {
            let volume = store.open_volume(store.resolve(&key)?)?;
            Ok((volume, key))
        })
        .await?;
        // Refused before the stream starts (a later view's is refused when it is planned).
        let points = volume.index.time_points();
        if time_point >= points {
            return Err(CacheError::InvalidRequest(format!(
                "time point {time_point}: the volume has {points} (0..={})",
                points - 1
            ))
            .into());
        }
        let mut session = Session::new(
            volume.clone(),
            name,
            start.credit_bytes,
            self.planners.clone(),
        );
        session.visible_only = start.visible_only;
        session.hold(&start.have)?;
        session.unplanned();
        let planning = tokio::spawn(plan(self.planners.clone(), volume, spec, time_point));
        let (tx, rx) = mpsc::channel(STREAM_BUFFER);
        let stopping = self.stopping.clone();
        tokio::spawn(async move {
            session
                .run(inbound, planning, tx, !start.have_header, stopping)
                .await;
            drop(slot);
        });
        Ok(Response::new(Box::pin(ReceiverStream::new(rx))))
    }
}

/// The record of an opened volume, named as the request named it.
fn named(volume: &OpenVolume, key: &crate::VolumeKey) -> crate::VolumeMeta {
    match key {
        crate::VolumeKey::Name(n) => volume.meta.clone().named(n),
        crate::VolumeKey::Id(_) => volume.meta.clone(),
    }
}

#[cfg(test)]
mod tests {
    use super::session::Ranking;
    use super::session::CHEAP_PLAN_PACKETS;
    use super::*;
    use crate::Limits;
    use pb::refine_response::Msg;
    use std::time::Duration;
    use wavesplat_codec::view::ViewSpec;

    fn open_test_volume(dir: &std::path::Path) -> Arc<OpenVolume> {
        open_test_volume_tiled(dir, 8)
    }

    /// A 32³ phantom in tiles of `tile` voxels, 3 layers each (tiles of 8 give fewer packets
    /// than [`CHEAP_PLAN_PACKETS`], tiles of 4 more).
    fn open_test_volume_tiled(dir: &std::path::Path, tile: usize) -> Arc<OpenVolume> {
        use wavesplat_compressor::encode::{compress, CompressOptions, Target, TileChoice};
        let vol = wavesplat_compressor::phantom::Phantom::SheppLogan.generate([32, 32, 32]);
        let bytes = compress(
            &vol,
            &CompressOptions {
                target: Target::Fraction(0.1),
                tile: TileChoice::Size(tile),
                layers: Some(3),
                levels: Some(2),
                ..Default::default()
            },
            &|_, _| {},
        )
        .unwrap()
        .bytes;
        let store = Store::open(dir, Limits::default()).unwrap();
        let id = store.ingest("v", &bytes, None).unwrap().volume.id;
        store.open_volume(id).unwrap()
    }

    /// Runs a session whose plan is `planning`, with a client that sends nothing more; returns
    /// what arrives until `quiet` passes without a message.
    async fn serve(
        volume: &Arc<OpenVolume>,
        visible_only: bool,
        planning: tokio::task::JoinHandle<Result<Ranking, Status>>,
    ) -> (
        tokio::task::JoinHandle<()>,
        mpsc::Receiver<Result<pb::RefineResponse, Status>>,
    ) {
        let planners = Arc::new(Semaphore::new(1));
        let mut session = Session::new(volume.clone(), crate::VolumeKey::Id(1), 0, planners);
        session.visible_only = visible_only;
        session.unplanned();
        let (tx, rx) = mpsc::channel(STREAM_BUFFER);
        let (_stop_tx, stopping) = watch::channel(false);
        let inbound = tokio_stream::pending::<Result<pb::RefineRequest, Status>>();
        let task = tokio::spawn(async move {
            let _keep = _stop_tx;
            session.run(inbound, planning, tx, true, stopping).await;
        });
        (task, rx)
    }

    async fn drain(
        rx: &mut mpsc::Receiver<Result<pb::RefineResponse, Status>>,
        quiet: Duration,
    ) -> Vec<Msg> {
        let mut got = Vec::new();
        while let Ok(Some(m)) = tokio::time::timeout(quiet, rx.recv()).await {
            got.push(m.expect("no error").msg.expect("a message"));
            if matches!(got.last(), Some(Msg::Done(_))) {
                break;
            }
        }
        got
    }

    fn packets(msgs: &[Msg]) -> Vec<&pb::Packet> {
        msgs.iter()
            .filter_map(|m| match m {
                Msg::Packet(p) => Some(p),
                _ => None,
            })
            .collect()
    }

    #[tokio::test]
    async fn a_stream_sends_its_first_packets_before_its_view_is_planned() {
        let dir = tempfile::tempdir().unwrap();
        let volume = open_test_volume(dir.path());
        let index = &volume.index.packets;
        let total: u64 = index.iter().map(|p| u64::from(p.len)).sum();
        let largest = index.iter().map(|p| u64::from(p.len)).max().unwrap();
        assert!(index.len() > 64, "{} packets", index.len());

        // A plan that never comes: the header, then file order within the unplanned budget,
        // and no `done` (the view's own order has not been sent).
        let (task, mut rx) = serve(&volume, false, tokio::spawn(std::future::pending())).await;
        let got = drain(&mut rx, Duration::from_millis(300)).await;
        assert!(matches!(got.first(), Some(Msg::Header(_))), "header first");
        let early = packets(&got);
        assert!(!early.is_empty(), "nothing sent before the plan");
        let ids: Vec<u32> = early.iter().map(|p| p.id).collect();
        assert_eq!(
            ids,
            (0..ids.len() as u32).collect::<Vec<_>>(),
            "not file order"
        );
        let bytes: u64 = early.iter().map(|p| p.data.len() as u64).sum();
        assert!(
            bytes <= total / UNPLANNED_SHARE + largest,
            "{bytes} bytes unplanned of {total}"
        );
        assert!(early.len() < index.len());
        assert!(
            !got.iter().any(|m| matches!(m, Msg::Done(_))),
            "done before the plan"
        );
        task.abort();

        // Once the plan arrives, the rest follows in the view's descending priority, each
        // packet once.
        let spec = ViewSpec::single(wavesplat_codec::view::View::new(0.7, 0.4, 48, 48));
        let planned = Ranking::new(&volume.index, &spec, 0).unwrap();
        let (gate_tx, gate_rx) = tokio::sync::oneshot::channel::<()>();
        let planning = tokio::spawn(async move {
            let _ = gate_rx.await;
            Ok(planned)
        });
        let (_task, mut rx) = serve(&volume, false, planning).await;
        let mut got = drain(&mut rx, Duration::from_millis(300)).await;
        let early = packets(&got).len();
        gate_tx.send(()).unwrap();
        got.extend(drain(&mut rx, Duration::from_secs(10)).await);
        assert!(
            matches!(got.last(), Some(Msg::Done(_))),
            "no done after the plan"
        );
        let all = packets(&got);
        let mut ids: Vec<u32> = all.iter().map(|p| p.id).collect();
        let rest: Vec<f64> = all[early..].iter().map(|p| p.priority).collect();
        assert!(
            rest.windows(2).all(|w| w[0] >= w[1]),
            "planned packets not in descending priority"
        );
        ids.sort_unstable();
        assert_eq!(
            ids,
            (0..index.len() as u32).collect::<Vec<_>>(),
            "each packet once"
        );
    }

    /// With every planner busy, a small volume's plan still runs (its queue would cost more
    /// than the plan) and a large one's waits for a planner.
    #[tokio::test]
    async fn only_plans_of_large_volumes_wait_for_a_planner() {
        let dir = tempfile::tempdir().unwrap();
        let small = open_test_volume(dir.path());
        let large_dir = tempfile::tempdir().unwrap();
        let large = open_test_volume_tiled(large_dir.path(), 4);
        assert!(small.index.packets.len() <= CHEAP_PLAN_PACKETS);
        assert!(large.index.packets.len() > CHEAP_PLAN_PACKETS);
        let spec = ViewSpec::single(wavesplat_codec::view::View::new(0.7, 0.4, 48, 48));
        let busy = Arc::new(Semaphore::new(0));
        let planned =
            tokio::time::timeout(Duration::from_secs(10), plan(busy.clone(), small, spec, 0)).await;
        assert!(
            matches!(planned, Ok(Ok(_))),
            "the small volume's plan waited"
        );
        let waiting = tokio::time::timeout(
            Duration::from_millis(300),
            plan(busy.clone(), large.clone(), spec, 0),
        )
        .await;
        assert!(
            waiting.is_err(),
            "the large volume's plan ran without a planner"
        );
        busy.add_permits(1);
        let planned =
            tokio::time::timeout(Duration::from_secs(10), plan(busy, large, spec, 0)).await;
        assert!(
            matches!(planned, Ok(Ok(_))),
            "no plan once a planner was free"
        );
    }

    #[tokio::test]
    async fn a_visible_only_stream_sends_nothing_before_its_view_is_planned() {
        let dir = tempfile::tempdir().unwrap();
        let volume = open_test_volume(dir.path());
        let (task, mut rx) = serve(&volume, true, tokio::spawn(std::future::pending())).await;
        let got = drain(&mut rx, Duration::from_millis(300)).await;
        assert_eq!(got.len(), 1, "{} messages", got.len());
        assert!(matches!(got[0], Msg::Header(_)));
        task.abort();
    }

    #[tokio::test]
    async fn a_view_the_planner_refuses_ends_the_stream_with_its_status() {
        let dir = tempfile::tempdir().unwrap();
        let volume = open_test_volume(dir.path());
        let planning =
            tokio::spawn(async { Err(Status::invalid_argument("the view cannot be planned")) });
        let (_task, mut rx) = serve(&volume, true, planning).await;
        let mut last = None;
        while let Ok(Some(m)) = tokio::time::timeout(Duration::from_secs(10), rx.recv()).await {
            last = Some(m);
        }
        let status = last.expect("a message").expect_err("an error last");
        assert_eq!(status.code(), tonic::Code::InvalidArgument);
    }

    /// A packet the client drops before the stream's first plan arrives stays out of that view:
    /// the plan's arrival is no view change (the end-to-end test
    /// `dropped_packets_come_back_after_a_view_change` saw it sent again when the plan came
    /// after the drop). The next view change queues it again.
    #[tokio::test]
    async fn a_packet_dropped_before_the_first_plan_stays_out_of_that_view() {
        let dir = tempfile::tempdir().unwrap();
        let volume = open_test_volume(dir.path());
        let planners = Arc::new(Semaphore::new(1));
        let mut session = Session::new(volume.clone(), crate::VolumeKey::Id(1), 0, planners);
        session.unplanned();
        let first = session.queue.peek().expect("packets in file order");
        session.hold(&[first]).unwrap();
        session.release(&[first]).unwrap();
        let spec = ViewSpec::single(wavesplat_codec::view::View::new(0.7, 0.4, 48, 48));
        let priority = Ranking::new(&volume.index, &spec, 0).unwrap();
        session.reorder(priority.clone());
        assert!(!session.queue.contains(first));
        assert_eq!(session.queue.len(), volume.index.packets.len() - 1);
        session.change_view(priority);
        assert!(session.queue.contains(first));
        assert_eq!(session.queue.len(), volume.index.packets.len());
    }

    /// Holdings take packets out of the queue wherever they are in it, once however often
    /// they are named (repeated, or again in later messages): the packets left go out in the
    /// same order, none held goes out, and the count left is exact.
    #[tokio::test]
    async fn holdings_leave_the_rest_of_the_queue_in_order() {
        let dir = tempfile::tempdir().unwrap();
        let volume = open_test_volume(dir.path());
        let n = volume.index.packets.len() as u32;
        assert!(n >= 6, "{n} packets");
        let planners = Arc::new(Semaphore::new(1));
        let spec = ViewSpec::single(wavesplat_codec::view::View::new(0.7, 0.4, 48, 48));
        let priority = Ranking::new(&volume.index, &spec, 0).unwrap();
        let order = |held: &[u32]| {
            let mut s = Session::new(volume.clone(), crate::VolumeKey::Id(1), 0, planners.clone());
            s.hold(held).unwrap();
            s.reorder(priority.clone());
            std::iter::from_fn(|| s.queue.pop().map(|(_, id)| id)).collect::<Vec<_>>()
        };
        let all = order(&[]);
        assert_eq!(all.len(), n as usize);
        let (first, middle, last) = (all[0], all[all.len() / 2], all[all.len() - 1]);
        let mut session =
            Session::new(volume.clone(), crate::VolumeKey::Id(1), 0, planners.clone());
        session.reorder(priority.clone());
        session.hold(&[middle, middle, last]).unwrap();
        session.hold(&[]).unwrap();
        session.hold(&[middle, first]).unwrap();
        assert_eq!(session.queue.len(), all.len() - 3);
        assert!(!session.queue.contains(middle) && !session.queue.contains(first));
        let mut left = Vec::new();
        while let Some((_, id)) = session.queue.pop() {
            left.push(id);
        }
        let expected: Vec<u32> = all
            .iter()
            .copied()
            .filter(|id| ![first, middle, last].contains(id))
            .collect();
        assert_eq!(left, expected);
        assert!(session.queue.is_empty());
        assert!(
            session.hold(&[n]).is_err(),
            "an id past the volume's packets"
        );
    }

    /// A bricked volume's stream sends nothing before its view is planned: its file order is
    /// its first brick's, which the view may not see. One volume's stream sends its first
    /// packets in file order meanwhile.
    #[test]
    fn a_bricked_volume_waits_for_its_plan() {
        use wavesplat_compressor::bricked::compress_bricked;
        use wavesplat_compressor::encode::{CompressOptions, Target};
        let dir = tempfile::tempdir().unwrap();
        let vol = wavesplat_compressor::phantom::Phantom::SheppLogan.generate([40, 36, 32]);
        let opts = CompressOptions {
            target: Target::Fraction(0.1),
            ..Default::default()
        };
        let bytes = compress_bricked(&vol, &opts, 20, &|_| {}).unwrap().bytes;
        let store = Store::open(dir.path(), Limits::default()).unwrap();
        let id = store.ingest("b", &bytes, None).unwrap().volume.id;
        let bricked = store.open_volume(id).unwrap();
        assert!(bricked.index.bricked.is_some());
        let whole = open_test_volume(&dir.path().join("whole"));
        for (volume, sends) in [(bricked, false), (whole, true)] {
            let planners = Arc::new(Semaphore::new(1));
            let mut session = Session::new(volume, crate::VolumeKey::Id(1), 0, planners);
            session.unplanned();
            assert_eq!(session.may_send_queued(), sends);
        }
    }
}
