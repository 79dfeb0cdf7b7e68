//! Refinement streams: the request that opens one, the stream of events it delivers, and the
//! control handle that changes the view, reports holdings and grants credit mid-stream.

use crate::{convert, ClientError, Packet, VolumeHeader, VolumeKey};
use tokio::sync::mpsc;
use tonic::Streaming;
use wavesplat_codec::view::ViewSpec;
use wavesplat_proto::pb;

/// Client messages buffered before `send` waits.
const CONTROL_BUFFER: usize = 16;

/// How to open a refinement stream.
#[derive(Debug, Clone, PartialEq)]
pub struct RefineRequest {
    /// The volume.
    pub volume: VolumeKey,
    /// The view to rank packets for.
    pub view: ViewSpec,
    /// Packets already held (never sent).
    pub have: Vec<u32>,
    /// The client already has the header.
    pub have_header: bool,
    /// Initial byte credit; 0 = no flow control (the server sends as fast as it can).
    pub credit_bytes: u64,
    /// Only the packets the view sees (see [`RefineRequest::visible_only`]).
    pub visible_only: bool,
    /// Of a time series, the time point shown (0 for any other volume).
    pub time_point: u32,
}

impl RefineRequest {
    /// A stream for `view` of `volume`, holding nothing, without flow control.
    pub fn new(volume: VolumeKey, view: ViewSpec) -> RefineRequest {
        RefineRequest {
            volume,
            view,
            have: Vec::new(),
            have_header: false,
            credit_bytes: 0,
            visible_only: false,
            time_point: 0,
        }
    }

    /// Of a time series, show time point `t` (its components' packets only).
    pub fn at_time_point(mut self, t: u32) -> RefineRequest {
        self.time_point = t;
        self
    }

    /// Send only the packets each view sees (on screen, in a band its projection does not
    /// cancel); the rest wait for a view that sees them, and `Done` means everything visible
    /// was sent. What an interactive viewer wants; collecting a whole volume does not.
    pub fn visible_only(mut self, yes: bool) -> RefineRequest {
        self.visible_only = yes;
        self
    }

    /// Pull with an initial credit of `bytes` (renew it with [`RefineControl::grant`]).
    pub fn with_credit(mut self, bytes: u64) -> RefineRequest {
        self.credit_bytes = bytes;
        self
    }

    /// Resume: these packets (and the header, if `have_header`) are already held.
    pub fn holding(mut self, have: Vec<u32>, have_header: bool) -> RefineRequest {
        self.have = have;
        self.have_header = have_header;
        self
    }
}

/// What a refinement stream delivers.
#[derive(Debug, Clone)]
pub enum RefineEvent {
    /// The volume's header (first, unless the client said it has it).
    Header(Box<VolumeHeader>),
    /// A packet.
    Packet(Packet),
    /// Everything the current view ranks has been sent; the stream stays open for view
    /// changes (which may queue dropped packets again) until the client closes it.
    Done {
        /// Packets sent on this stream.
        sent: u32,
        /// Bytes of packet data sent on this stream.
        bytes: u64,
        /// View changes the server had applied when it said this: a `Done` whose count is
        /// below the view changes sent is about an earlier view.
        views: u32,
    },
}

/// Sends control messages on an open stream (cloneable; usable from any task).
#[derive(Debug, Clone)]
pub struct RefineControl {
    tx: mpsc::Sender<pb::RefineRequest>,
    /// The time point the stream's views are of (a time series'; 0 otherwise).
    time_point: std::sync::Arc<std::sync::atomic::AtomicU32>,
}

impl RefineControl {
    async fn send(&self, msg: pb::refine_request::Msg) -> Result<(), ClientError> {
        self.tx
            .send(pb::RefineRequest { msg: Some(msg) })
            .await
            .map_err(|_| ClientError::Closed)
    }

    /// Ranks what is not yet sent for a new view (of the stream's time point).
    pub async fn set_view(&self, view: &ViewSpec) -> Result<(), ClientError> {
        let t = self.time_point.load(std::sync::atomic::Ordering::Relaxed);
        self.set_view_at(view, t).await
    }

    /// Ranks what is not yet sent for a new view of time point `t` of a time series (later
    /// views keep it).
    pub async fn set_view_at(&self, view: &ViewSpec, t: u32) -> Result<(), ClientError> {
        let v = convert::view_message(view, t)
            .map_err(|e| ClientError::Protocol(format!("view cannot be sent: {e}")))?;
        self.time_point
            .store(t, std::sync::atomic::Ordering::Relaxed);
        self.send(pb::refine_request::Msg::View(v)).await
    }

    /// Reports packets now held (`have`: never to be sent) and dropped (`dropped`: sent again
    /// when a later view ranks them).
    pub async fn holdings(&self, have: Vec<u32>, dropped: Vec<u32>) -> Result<(), ClientError> {
        self.send(pb::refine_request::Msg::Holdings(pb::Holdings {
            have,
            dropped,
        }))
        .await
    }

    /// Adds `bytes` to the stream's credit. The server sends while the credit is positive and
    /// counts each packet's whole size, so the last packet's overshoot is owed: renew by what
    /// was consumed (a grant that only pays the debt back sends nothing).
    pub async fn grant(&self, bytes: u64) -> Result<(), ClientError> {
        self.send(pb::refine_request::Msg::Credit(pb::Credit { bytes }))
            .await
    }
}

/// An open refinement stream.
#[derive(Debug)]
pub struct RefineStream {
    control: RefineControl,
    inbound: Streaming<pb::RefineResponse>,
}

impl RefineStream {
    /// The next event; `None` when the server closed the stream.
    pub async fn next(&mut self) -> Result<Option<RefineEvent>, ClientError> {
        use pb::refine_response::Msg;
        loop {
            let Some(m) = self.inbound.message().await? else {
                return Ok(None);
            };
            return Ok(Some(match m.msg {
                Some(Msg::Header(h)) => RefineEvent::Header(Box::new(convert::volume_header(h)?)),
                Some(Msg::Packet(p)) => RefineEvent::Packet(convert::packet(p)),
                Some(Msg::Done(d)) => RefineEvent::Done {
                    sent: d.sent,
                    bytes: d.bytes,
                    views: d.views,
                },
                // An empty message from a newer server: skip it.
                None => continue,
            }));
        }
    }

    /// The control handle of this stream.
    pub fn control(&self) -> &RefineControl {
        &self.control
    }
}

pub(crate) async fn open(
    client: &mut pb::cache_client::CacheClient<crate::Transport>,
    request: RefineRequest,
) -> Result<RefineStream, ClientError> {
    let view = convert::view_message(&request.view, request.time_point)
        .map_err(|e| ClientError::Protocol(format!("view cannot be sent: {e}")))?;
    let (tx, rx) = mpsc::channel(CONTROL_BUFFER);
    let start = pb::RefineRequest {
        msg: Some(pb::refine_request::Msg::Start(pb::RefineStart {
            volume: Some(convert::volume_ref(&request.volume)),
            view: Some(view),
            have: request.have,
            have_header: request.have_header,
            credit_bytes: request.credit_bytes,
            visible_only: request.visible_only,
        })),
    };
    tx.send(start).await.map_err(|_| ClientError::Closed)?;
    let inbound = client
        .refine(tokio_stream::wrappers::ReceiverStream::new(rx))
        .await?
        .into_inner();
    Ok(RefineStream {
        control: RefineControl {
            tx,
            time_point: std::sync::Arc::new(request.time_point.into()),
        },
        inbound,
    })
}
