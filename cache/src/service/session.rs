//! One refinement stream: its volume held open, the unsent-packet queue in the view's order,
//! the client's credit, holdings and view changes read from the same stream, `done` announced
//! per view; and the planning of a view on the bounded planner pool (small volumes plan at once).
//! A bricked volume's packets are ranked together, each by its brick's view of the whole
//! ([`wavesplat_codec::view::bricked`]); a brick the view does not see sends nothing in that
//! view.

use super::named;
use super::{blocking, next_message, UNPLANNED_SHARE};
use crate::convert;
use crate::error::CacheError;
use crate::model::{PacketMeta, VolumeIndex};
use crate::store::OpenVolume;
use std::collections::HashSet;
use std::sync::Arc;
use tokio::sync::{mpsc, watch, Semaphore};
use tokio_stream::Stream;
use tonic::Status;
use wavesplat_codec::view::bricked::BrickedVisibility;
use wavesplat_codec::view::priority::Priority;
use wavesplat_codec::view::{ViewError, ViewSpec};
use wavesplat_proto::pb;

/// Volumes with at most this many packets plan in well under a millisecond (0.37 ms at 180
/// packets): their plans skip the planner pool, whose queue would cost more than the plan.
pub(super) const CHEAP_PLAN_PACKETS: usize = 512;

/// What one view ranks a volume's packets by.
#[derive(Debug, Clone)]
pub(super) enum Ranking {
    /// One volume: its visibility.
    Whole(Priority),
    /// A bricked volume: each brick's visibility in its frame (none off the image).
    Bricked(BrickedVisibility),
    /// A time point of a series: the bricks of the components it names, seen as a bricked
    /// volume's are; each packet's energy scaled by its component's weight squared (the time
    /// point is the weighted sum of its components), other components' packets not sent.
    Series {
        seen: BrickedVisibility,
        /// Per brick of the series: its index among the time point's bricks and its weight².
        bricks: Vec<Option<(usize, f64)>>,
    },
}

impl Ranking {
    /// The ranking of `spec` at time point `time_point` (0 for a volume that is not a series)
    /// for the volume of `index`.
    pub(super) fn new(
        index: &VolumeIndex,
        spec: &ViewSpec,
        time_point: usize,
    ) -> Result<Ranking, CacheError> {
        let points = index.time_points();
        if time_point >= points {
            return Err(CacheError::InvalidRequest(format!(
                "time point {time_point}: the volume has {points} (0..={})",
                points - 1
            )));
        }
        let invalid = |e: ViewError| CacheError::InvalidRequest(e.to_string());
        Ok(match (&index.bricked, &index.series) {
            (Some(b), _) => {
                let bricks: Vec<_> = b.bricks.iter().map(|k| (&k.header, k.origin)).collect();
                Ranking::Bricked(
                    BrickedVisibility::new(spec, &index.header.geometry, &bricks)
                        .map_err(invalid)?,
                )
            }
            (None, Some(s)) => {
                let mut seen_bricks = Vec::new();
                let mut bricks = vec![None; s.bricks.len()];
                for &(c, weight) in &s.manifest.points[time_point].terms {
                    for k in s.components[c].clone() {
                        let b = &s.bricks[k];
                        bricks[k] = Some((seen_bricks.len(), f64::from(weight).powi(2)));
                        seen_bricks.push((&b.header, b.origin));
                    }
                }
                Ranking::Series {
                    seen: BrickedVisibility::new(spec, &index.header.geometry, &seen_bricks)
                        .map_err(invalid)?,
                    bricks,
                }
            }
            (None, None) => Ranking::Whole(Priority::new(&index.header, spec).map_err(invalid)?),
        })
    }

    /// The visible energy of packet `id` (`p`) of the volume of `index`; `None` for a packet of
    /// a brick off the image (not sent in this view).
    fn visible_energy(&self, index: &VolumeIndex, id: u32, p: &PacketMeta) -> Option<f64> {
        match self {
            Ranking::Whole(priority) => Some(priority.visible_energy(p)),
            Ranking::Bricked(seen) => {
                seen.visible_energy(index.brick_of(id), p.tile as usize, &p.summary)
            }
            Ranking::Series { seen, bricks } => {
                let (brick, w2) = bricks[index.brick_of(id)]?;
                seen.visible_energy(brick, p.tile as usize, &p.summary)
                    .map(|e| e * w2)
            }
        }
    }
}

/// Plans `spec` for `volume` on the blocking pool, once one of `planners`' permits is free
/// (at once for a small volume, [`CHEAP_PLAN_PACKETS`]).
pub(super) async fn plan(
    planners: Arc<Semaphore>,
    volume: Arc<OpenVolume>,
    spec: ViewSpec,
    time_point: usize,
) -> Result<Ranking, Status> {
    let _permit = if volume.index.packets.len() <= CHEAP_PLAN_PACKETS {
        None
    } else {
        Some(
            planners
                .acquire_owned()
                .await
                .map_err(|_| Status::internal("the planner pool is closed"))?,
        )
    };
    blocking(move || Ranking::new(&volume.index, &spec, time_point)).await
}

/// A byte count from the wire as a signed credit (larger ones are as good as unbounded).
fn credit_i64(bytes: u64) -> i64 {
    i64::try_from(bytes).unwrap_or(i64::MAX)
}

/// A stream's unsent packets in priority order, lowest first (the next one is popped from the
/// end). A packet the client says it holds is unmarked in place and skipped when its turn
/// comes, so a holdings message costs what it names, not a pass over the whole queue: a client
/// sending holdings without end cannot make the server rescan a million-packet queue per message.
#[derive(Debug, Default)]
pub(super) struct SendQueue {
    order: Vec<(f64, u32)>,
    /// Per packet id: in `order` and still to be sent.
    queued: Vec<bool>,
    /// How many are.
    pending: usize,
}

impl SendQueue {
    /// The queue of `order` (distinct ids below `packets`, lowest priority first).
    fn set(&mut self, order: Vec<(f64, u32)>, packets: usize) {
        self.queued.clear();
        self.queued.resize(packets, false);
        for (_, id) in &order {
            self.queued[*id as usize] = true;
        }
        self.pending = order.len();
        self.order = order;
    }

    /// Takes `id` out, if it is queued.
    fn remove(&mut self, id: u32) {
        if let Some(q) = self.queued.get_mut(id as usize) {
            if std::mem::take(q) {
                self.pending -= 1;
            }
        }
    }

    /// The next packet to send and its priority.
    pub(super) fn pop(&mut self) -> Option<(f64, u32)> {
        while let Some((priority, id)) = self.order.pop() {
            if std::mem::take(&mut self.queued[id as usize]) {
                self.pending -= 1;
                return Some((priority, id));
            }
        }
        None
    }

    /// The id [`Self::pop`] would give.
    #[cfg(test)]
    pub(super) fn peek(&self) -> Option<u32> {
        let queued = &self.queued;
        self.order
            .iter()
            .rev()
            .map(|(_, id)| *id)
            .find(|id| queued[*id as usize])
    }

    /// Whether `id` is still to be sent.
    #[cfg(test)]
    pub(super) fn contains(&self, id: u32) -> bool {
        self.queued.get(id as usize).copied().unwrap_or(false)
    }

    /// Packets still to be sent.
    #[cfg(test)]
    pub(super) fn len(&self) -> usize {
        self.pending
    }

    /// Whether nothing is left to send.
    pub(super) fn is_empty(&self) -> bool {
        self.pending == 0
    }
}

/// One refinement stream's state. It holds its volume open: a deletion during the stream does
/// not cut it short.
pub(super) struct Session {
    pub(super) volume: Arc<OpenVolume>,
    pub(super) name: crate::VolumeKey,
    /// Packets the client holds or was sent.
    pub(super) held: HashSet<u32>,
    /// Packets the client dropped since the last view change: queued again only by the next
    /// one (not by the first plan of the same view arriving after the drop).
    pub(super) released: HashSet<u32>,
    /// Unsent packets in the order they go.
    pub(super) queue: SendQueue,
    pub(super) sent: u32,
    pub(super) bytes: u64,
    /// Byte credit, when the client pulls (`None`: no flow control): what it granted less what
    /// was sent. A packet goes out only while it is positive and its whole size is counted, so
    /// the credit turns negative by the last packet's overshoot, which later grants pay back
    /// before anything more is sent: at most one packet beyond what the client granted.
    pub(super) credit: Option<i64>,
    /// Queue only what the current view sees.
    pub(super) visible_only: bool,
    /// View changes applied on this stream.
    pub(super) views: u32,
    /// Bytes the stream may still send in file order before its view is planned (`None`: the
    /// queue is in the view's order).
    pub(super) unplanned: Option<u64>,
    pub(super) planners: Arc<Semaphore>,
}

impl Session {
    pub(super) fn new(
        volume: Arc<OpenVolume>,
        name: crate::VolumeKey,
        credit_bytes: u64,
        planners: Arc<Semaphore>,
    ) -> Session {
        Session {
            volume,
            name,
            held: HashSet::new(),
            released: HashSet::new(),
            queue: SendQueue::default(),
            sent: 0,
            bytes: 0,
            credit: (credit_bytes > 0).then(|| credit_i64(credit_bytes)),
            visible_only: false,
            views: 0,
            unplanned: None,
            planners,
        }
    }

    /// Queues the packets not held in file order, to send while the view is planned: up to
    /// 1/[`UNPLANNED_SHARE`] of the volume's bytes, nothing for a visible-only stream (it may
    /// not send what the view cannot see, which only the plan knows) nor for a bricked volume
    /// (its file order is its first brick's, which the view may not see: a view is sent only
    /// the bricks it sees).
    pub(super) fn unplanned(&mut self) {
        let packets = &self.volume.index.packets;
        self.unplanned = Some(
            if self.visible_only || self.volume.index.bricks().is_some() {
                0
            } else {
                (self.volume.meta.packet_bytes / UNPLANNED_SHARE).max(1)
            },
        );
        let held = &self.held;
        // Pops come from the end: file order is the reversed ids.
        let order = (0..packets.len() as u32)
            .rev()
            .filter(|i| !held.contains(i))
            .map(|i| (0.0, i))
            .collect();
        self.queue.set(order, packets.len());
    }

    /// Whether the queue may be sent from now: planned, or within the unplanned budget.
    pub(super) fn may_send_queued(&self) -> bool {
        !self.queue.is_empty() && self.unplanned.is_none_or(|b| b > 0)
    }

    fn check_ids(&self, ids: &[u32], what: &str) -> Result<(), CacheError> {
        let n = self.volume.index.packets.len();
        match ids.iter().find(|i| **i as usize >= n) {
            Some(bad) => Err(CacheError::InvalidRequest(format!(
                "{what} packet id {bad} out of range 0..{n}"
            ))),
            None => Ok(()),
        }
    }

    pub(super) fn hold(&mut self, ids: &[u32]) -> Result<(), CacheError> {
        self.check_ids(ids, "held")?;
        for &id in ids {
            self.held.insert(id);
            self.queue.remove(id);
        }
        Ok(())
    }

    /// The client no longer holds `ids`; they are queued again at the next view change.
    pub(super) fn release(&mut self, ids: &[u32]) -> Result<(), CacheError> {
        self.check_ids(ids, "dropped")?;
        for id in ids {
            self.held.remove(id);
            self.released.insert(*id);
        }
        Ok(())
    }

    /// The client changed the view: what it dropped may be sent again, in the new order.
    pub(super) fn change_view(&mut self, priority: Ranking) {
        self.released.clear();
        self.reorder(priority);
        self.views = self.views.wrapping_add(1);
    }

    /// Whether the client's credit allows another packet now.
    fn may_send(&self) -> bool {
        self.credit.is_none_or(|c| c > 0)
    }

    /// Queues what the client neither holds nor dropped in this view, in `priority`'s order
    /// (visible energy per byte); a bricked volume's bricks off the image queue nothing.
    pub(super) fn reorder(&mut self, priority: Ranking) {
        let (held, released) = (&self.held, &self.released);
        let index = &self.volume.index;
        let mut q: Vec<(f64, u32)> = index
            .packets
            .iter()
            .enumerate()
            .filter_map(|(i, p)| {
                let id = i as u32;
                if held.contains(&id) || released.contains(&id) {
                    return None;
                }
                let energy = priority.visible_energy(index, id, p)?;
                (!self.visible_only || energy > 0.0).then(|| (energy / f64::from(p.len.max(1)), id))
            })
            .collect();
        // Ascending priority, ties: later file position first, so pops give file order.
        q.sort_by(|a, b| a.0.total_cmp(&b.0).then(b.1.cmp(&a.1)));
        self.queue.set(q, index.packets.len());
        self.unplanned = None;
    }

    /// Handles a client message; `Err` ends the stream with that status.
    async fn handle(&mut self, msg: pb::RefineRequest) -> Result<(), Status> {
        match msg.msg {
            Some(pb::refine_request::Msg::View(v)) => {
                let time_point = convert::time_point(Some(&v));
                let spec = convert::view_spec(Some(v))?;
                let priority =
                    plan(self.planners.clone(), self.volume.clone(), spec, time_point).await?;
                self.change_view(priority);
                tracing::debug!(volume = self.volume.meta.id, "view changed");
                Ok(())
            }
            Some(pb::refine_request::Msg::Holdings(h)) => {
                self.release(&h.dropped)?;
                Ok(self.hold(&h.have)?)
            }
            Some(pb::refine_request::Msg::Credit(c)) => {
                if let Some(credit) = &mut self.credit {
                    *credit = credit.saturating_add(credit_i64(c.bytes));
                }
                Ok(())
            }
            Some(pb::refine_request::Msg::Start(_)) => Err(CacheError::InvalidRequest(
                "`start` may only be the first message of a stream".into(),
            )
            .into()),
            None => Err(CacheError::InvalidRequest(
                "an empty RefineRequest: a message after `start` carries a view, holdings or \
                 credit"
                    .into(),
            )
            .into()),
        }
    }

    async fn next_packet(&mut self) -> Result<Option<pb::Packet>, CacheError> {
        // Nothing queued is held: `hold` takes packets out of the queue, and an order is made
        // of what is not held.
        let Some((priority, id)) = self.queue.pop() else {
            return Ok(None);
        };
        // Read before marking it held: a read that fails (a bucket gone for a moment) ends
        // the stream with an error, and the client's holdings on its next stream say what it
        // has.
        let data = self.volume.read_packet(id).await?.to_vec();
        self.held.insert(id);
        let p = &self.volume.index.packets[id as usize];
        self.sent += 1;
        self.bytes += data.len() as u64;
        if let Some(credit) = &mut self.credit {
            // Not forgiven below zero: the overshoot is owed.
            *credit = credit.saturating_sub(credit_i64(data.len() as u64));
        }
        if let Some(budget) = &mut self.unplanned {
            *budget = budget.saturating_sub(data.len() as u64);
        }
        Ok(Some(pb::Packet {
            id,
            tile: p.tile,
            layer: p.layer,
            data,
            priority,
        }))
    }

    /// Serves the stream: the header (unless the client has it), then packets as the client
    /// takes them; `planning` yields the plan of the starting view (until it does, the queue is
    /// the unplanned one and `done` is not announced).
    pub(super) async fn run(
        mut self,
        mut inbound: impl Stream<Item = Result<pb::RefineRequest, Status>> + Unpin,
        mut planning: tokio::task::JoinHandle<Result<Ranking, Status>>,
        tx: mpsc::Sender<Result<pb::RefineResponse, Status>>,
        send_header: bool,
        mut stopping: watch::Receiver<bool>,
    ) {
        use pb::refine_response::Msg;
        if send_header {
            let header =
                convert::volume_header(&named(&self.volume, &self.name), &self.volume.index);
            let msg = pb::RefineResponse {
                msg: Some(Msg::Header(header)),
            };
            if tx.send(Ok(msg)).await.is_err() {
                return;
            }
        }
        let mut inbound_open = true;
        let mut planned = false;
        // `done` is announced whenever the queue runs dry; the stream stays open while the
        // client may still send (a view change can queue dropped packets again).
        let mut announced = false;
        loop {
            if self.queue.is_empty() && planned {
                if !announced {
                    let done = pb::RefineDone {
                        sent: self.sent,
                        bytes: self.bytes,
                        views: self.views,
                    };
                    let msg = pb::RefineResponse {
                        msg: Some(Msg::Done(done)),
                    };
                    if tx.send(Ok(msg)).await.is_err() {
                        return;
                    }
                    tracing::debug!(
                        volume = self.volume.meta.id,
                        sent = self.sent,
                        "refinement done"
                    );
                    announced = true;
                }
                if !inbound_open {
                    return;
                }
            }
            if !inbound_open && !self.may_send() {
                // Out of credit with the request side closed: no grant can come, so nothing
                // more can be sent. The stream ends here (with what the credit allowed) rather
                // than waiting on a client that can no longer speak, which kept the caller's
                // stream slot and the volume open until the server stopped.
                tracing::debug!(
                    volume = self.volume.meta.id,
                    sent = self.sent,
                    "out of credit with the requests closed: the stream ends"
                );
                return;
            }
            tokio::select! {
                biased;
                _ = async { stopping.wait_for(|s| *s).await.map(|_| ()) } => {
                    let _ = tx.send(Err(Status::unavailable("the cache is shutting down"))).await;
                    return;
                }
                plan = &mut planning, if !planned => {
                    planned = true;
                    match plan.map_err(|e| Status::internal(format!("planning failed: {e}"))) {
                        Ok(Ok(priority)) => self.reorder(priority),
                        Ok(Err(status)) | Err(status) => {
                            let _ = tx.send(Err(status)).await;
                            return;
                        }
                    }
                }
                msg = next_message(&mut inbound), if inbound_open => match msg {
                    Ok(Some(m)) => {
                        // A new view is a new refinement: it is announced done again (at once
                        // when everything was already sent), so the client knows the view has
                        // nothing more coming.
                        let new_view = matches!(m.msg, Some(pb::refine_request::Msg::View(_)));
                        if let Err(status) = self.handle(m).await {
                            let _ = tx.send(Err(status)).await;
                            return;
                        }
                        if new_view && !planned {
                            // The new view's plan replaced the starting one's, which is left to
                            // finish unread (aborting it would free its planner slot while its
                            // blocking work still ran).
                            planned = true;
                        }
                        announced &= self.queue.is_empty() && !new_view;
                    }
                    Ok(None) => inbound_open = false,
                    // A message that does not decode or is over the size limit (a client
                    // status from `next_message`), or a client that went away (nobody to
                    // tell): the stream ends with that status, never as if it were complete.
                    Err(status) => {
                        tracing::debug!(%status, "reading a refinement request failed");
                        let _ = tx.send(Err(status)).await;
                        return;
                    }
                },
                permit = tx.reserve(), if self.may_send() && self.may_send_queued() => {
                    let Ok(permit) = permit else { return };
                    match self.next_packet().await {
                        Ok(Some(p)) => permit.send(Ok(pb::RefineResponse { msg: Some(Msg::Packet(p)) })),
                        Ok(None) => {}
                        Err(e) => {
                            permit.send(Err(e.into()));
                            return;
                        }
                    }
                }
                // Nothing left to wait for (no plan coming, no request, nothing to send).
                else => return,
            }
        }
    }
}
