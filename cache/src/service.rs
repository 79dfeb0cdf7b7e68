//! The gRPC `Cache` service: request handling on top of [`Store`] and [`Priority`]. Heavy work
//! (validating and storing an upload) runs on the blocking pool. A refinement session is one
//! task per stream that owns the unsent-packet queue: it reads client messages (view changes,
//! holdings, credit) and sends packets through a bounded channel, so it only produces as fast as
//! the client consumes; with a byte credit (the client pulls) it also never has more than the
//! credit in flight, so a view change reorders everything the client has not yet asked for.

use crate::convert;
use crate::error::CacheError;
use crate::model::{VolumeIndex, VolumeMeta};
use crate::priority::Priority;
use crate::store::{validate_name, Store};
use std::collections::HashSet;
use std::pin::Pin;
use tokio::sync::{mpsc, watch};
use tokio_stream::wrappers::ReceiverStream;
use tokio_stream::Stream;
use tonic::{Request, Response, Status, Streaming};
use wavesplat_proto::pb;
use wavesplat_proto::pb::cache_server::Cache;

/// Largest upload chunk message (bytes).
pub const MAX_CHUNK_BYTES: usize = 4 << 20;
/// Responses buffered per refinement stream before the server waits for the client.
pub const STREAM_BUFFER: usize = 4;
/// Largest `FirstPackets` budget (bytes).
pub const MAX_FIRST_PACKETS_BYTES: u64 = 16 << 20;

/// The service implementation.
#[derive(Debug, Clone)]
pub struct CacheService {
    store: Store,
    /// Becomes `true` when the server shuts down: open refinement streams then end (a viewer
    /// keeps its stream open while it may still change the view, so graceful shutdown would
    /// otherwise wait for it forever).
    stopping: watch::Receiver<bool>,
}

impl CacheService {
    /// A service over `store` that ends its streams once `stopping` becomes `true`.
    pub fn new(store: Store, stopping: watch::Receiver<bool>) -> CacheService {
        CacheService { store, stopping }
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
        let mut inbound = request.into_inner();
        let start = match inbound.message().await?.and_then(|m| m.msg) {
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
        let total = start.total_size as usize;
        let mut data = Vec::with_capacity(total.min(64 << 20));
        while let Some(m) = inbound.message().await? {
            match m.msg {
                Some(pb::ingest_request::Msg::Chunk(c)) => {
                    if data.len() + c.len() > total {
                        return Err(CacheError::InvalidUpload(format!(
                            "more data than the declared total size of {total} bytes"
                        ))
                        .into());
                    }
                    data.extend_from_slice(&c);
                }
                _ => {
                    return Err(CacheError::InvalidRequest(
                        "only `chunk` messages may follow `start`".into(),
                    )
                    .into())
                }
            }
        }
        if data.len() != total {
            return Err(CacheError::InvalidUpload(format!(
                "truncated upload: received {} of {total} bytes",
                data.len()
            ))
            .into());
        }
        let store = self.store.clone();
        let name = start.name;
        let done = blocking(move || store.ingest(&name, &data, Some(declared))).await?;
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
        let (meta, index) = blocking(move || {
            let id = store.resolve(&key)?;
            Ok((store.meta(id)?, store.index(id)?))
        })
        .await?;
        Ok(Response::new(pb::VolumeHeader {
            volume: Some(convert::volume_info(&meta)),
            header: index.header_bytes,
        }))
    }

    async fn packet_table(
        &self,
        request: Request<pb::DescribeRequest>,
    ) -> Result<Response<pb::PacketTableResponse>, Status> {
        let key = convert::volume_key(request.into_inner().volume)?;
        let store = self.store.clone();
        let index = blocking(move || store.index(store.resolve(&key)?)).await?;
        Ok(Response::new(pb::PacketTableResponse {
            packets: index.packets.iter().map(convert::packet_entry).collect(),
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
            let id = store.resolve(&key)?;
            let index = store.index(id)?;
            let mut packets = Vec::new();
            let mut used = 0u64;
            for (i, p) in index.packets.iter().enumerate() {
                if !packets.is_empty() && used + p.len as u64 > req.max_bytes {
                    break;
                }
                used += p.len as u64;
                packets.push(pb::Packet {
                    id: i as u32,
                    tile: p.tile,
                    layer: p.layer,
                    data: store.packet(id, i as u32)?,
                    priority: 0.0,
                });
            }
            Ok(pb::FirstPacketsResponse {
                header: index.header_bytes,
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
        let mut inbound = request.into_inner();
        let start = match inbound.message().await?.and_then(|m| m.msg) {
            Some(pb::refine_request::Msg::Start(s)) => s,
            _ => {
                return Err(CacheError::InvalidRequest(
                    "the first refine message must be `start`".into(),
                )
                .into())
            }
        };
        let key = convert::volume_key(start.volume)?;
        let spec = convert::view_spec(start.view)?;
        let store = self.store.clone();
        let (meta, index, priority) = blocking(move || {
            let id = store.resolve(&key)?;
            let meta = store.meta(id)?;
            let index = store.index(id)?;
            let priority = Priority::new(&index.header, &spec)?;
            Ok((meta, index, priority))
        })
        .await?;
        let mut session = Session::new(self.store.clone(), meta, index, start.credit_bytes);
        session.hold(&start.have)?;
        session.reorder(priority);
        let (tx, rx) = mpsc::channel(STREAM_BUFFER);
        tokio::spawn(session.run(inbound, tx, !start.have_header, self.stopping.clone()));
        Ok(Response::new(Box::pin(ReceiverStream::new(rx))))
    }
}

/// One refinement stream's state.
struct Session {
    store: Store,
    meta: VolumeMeta,
    index: VolumeIndex,
    /// Packets the client holds or was sent.
    held: HashSet<u32>,
    /// Unsent packets, lowest priority first (the next one is popped from the end).
    queue: Vec<(f64, u32)>,
    sent: u32,
    bytes: u64,
    /// Byte credit left, when the client pulls (`None`: no flow control).
    credit: Option<u64>,
}

impl Session {
    fn new(store: Store, meta: VolumeMeta, index: VolumeIndex, credit_bytes: u64) -> Session {
        Session {
            store,
            meta,
            index,
            held: HashSet::new(),
            queue: Vec::new(),
            sent: 0,
            bytes: 0,
            credit: (credit_bytes > 0).then_some(credit_bytes),
        }
    }

    fn check_ids(&self, ids: &[u32], what: &str) -> Result<(), CacheError> {
        let n = self.index.packets.len();
        match ids.iter().find(|i| **i as usize >= n) {
            Some(bad) => Err(CacheError::InvalidRequest(format!(
                "{what} packet id {bad} out of range 0..{n}"
            ))),
            None => Ok(()),
        }
    }

    fn hold(&mut self, ids: &[u32]) -> Result<(), CacheError> {
        self.check_ids(ids, "held")?;
        self.held.extend(ids.iter().copied());
        self.queue.retain(|(_, id)| !self.held.contains(id));
        Ok(())
    }

    /// The client no longer holds `ids`; they are queued again at the next view change.
    fn release(&mut self, ids: &[u32]) -> Result<(), CacheError> {
        self.check_ids(ids, "dropped")?;
        for id in ids {
            self.held.remove(id);
        }
        Ok(())
    }

    /// Whether the client's credit allows another packet now.
    fn may_send(&self) -> bool {
        self.credit.is_none_or(|c| c > 0)
    }

    fn reorder(&mut self, priority: Priority) {
        let held = &self.held;
        let mut q: Vec<(f64, u32)> = self
            .index
            .packets
            .iter()
            .enumerate()
            .filter(|(i, _)| !held.contains(&(*i as u32)))
            .map(|(i, p)| (priority.priority(p), i as u32))
            .collect();
        // Ascending priority, ties: later file position first, so pops give file order.
        q.sort_by(|a, b| a.0.total_cmp(&b.0).then(b.1.cmp(&a.1)));
        self.queue = q;
    }

    /// Handles a client message; `Err` ends the stream with that status.
    async fn handle(&mut self, msg: pb::RefineRequest) -> Result<(), Status> {
        match msg.msg {
            Some(pb::refine_request::Msg::View(v)) => {
                let spec = convert::view_spec(Some(v))?;
                let header = self.index.header.clone();
                let priority = blocking(move || Priority::new(&header, &spec)).await?;
                self.reorder(priority);
                tracing::debug!(volume = self.meta.id, "view changed");
                Ok(())
            }
            Some(pb::refine_request::Msg::Holdings(h)) => {
                self.release(&h.dropped)?;
                Ok(self.hold(&h.have)?)
            }
            Some(pb::refine_request::Msg::Credit(c)) => {
                if let Some(credit) = &mut self.credit {
                    *credit = credit.saturating_add(c.bytes);
                }
                Ok(())
            }
            Some(pb::refine_request::Msg::Start(_)) | None => Err(CacheError::InvalidRequest(
                "`start` may only be the first message".into(),
            )
            .into()),
        }
    }

    fn next_packet(&mut self) -> Result<Option<pb::Packet>, CacheError> {
        while let Some((priority, id)) = self.queue.pop() {
            if !self.held.insert(id) {
                continue;
            }
            let p = &self.index.packets[id as usize];
            let data = self.store.packet(self.meta.id, id)?;
            self.sent += 1;
            self.bytes += data.len() as u64;
            if let Some(credit) = &mut self.credit {
                *credit = credit.saturating_sub(data.len() as u64);
            }
            return Ok(Some(pb::Packet {
                id,
                tile: p.tile,
                layer: p.layer,
                data,
                priority,
            }));
        }
        Ok(None)
    }

    async fn run(
        mut self,
        mut inbound: Streaming<pb::RefineRequest>,
        tx: mpsc::Sender<Result<pb::RefineResponse, Status>>,
        send_header: bool,
        mut stopping: watch::Receiver<bool>,
    ) {
        use pb::refine_response::Msg;
        if send_header {
            let header = pb::VolumeHeader {
                volume: Some(convert::volume_info(&self.meta)),
                header: self.index.header_bytes.clone(),
            };
            let msg = pb::RefineResponse {
                msg: Some(Msg::Header(header)),
            };
            if tx.send(Ok(msg)).await.is_err() {
                return;
            }
        }
        let mut inbound_open = true;
        // `done` is announced whenever the queue runs dry; the stream stays open while the
        // client may still send (a view change can queue dropped packets again).
        let mut announced = false;
        loop {
            if self.queue.is_empty() {
                if !announced {
                    let done = pb::RefineDone {
                        sent: self.sent,
                        bytes: self.bytes,
                    };
                    let msg = pb::RefineResponse {
                        msg: Some(Msg::Done(done)),
                    };
                    if tx.send(Ok(msg)).await.is_err() {
                        return;
                    }
                    tracing::debug!(volume = self.meta.id, sent = self.sent, "refinement done");
                    announced = true;
                }
                if !inbound_open {
                    return;
                }
            }
            tokio::select! {
                biased;
                _ = async { stopping.wait_for(|s| *s).await.map(|_| ()) } => {
                    let _ = tx.send(Err(Status::unavailable("the cache is shutting down"))).await;
                    return;
                }
                msg = inbound.message(), if inbound_open => match msg {
                    Ok(Some(m)) => {
                        if let Err(status) = self.handle(m).await {
                            let _ = tx.send(Err(status)).await;
                            return;
                        }
                        announced &= self.queue.is_empty();
                    }
                    Ok(None) => inbound_open = false,
                    Err(status) => {
                        tracing::debug!(%status, "refinement client went away");
                        return;
                    }
                },
                permit = tx.reserve(), if self.may_send() && !self.queue.is_empty() => {
                    let Ok(permit) = permit else { return };
                    match self.next_packet() {
                        Ok(Some(p)) => permit.send(Ok(pb::RefineResponse { msg: Some(Msg::Packet(p)) })),
                        Ok(None) => {}
                        Err(e) => {
                            permit.send(Err(e.into()));
                            return;
                        }
                    }
                }
                // Out of credit and the client can no longer grant any.
                else => return,
            }
        }
    }
}
