//! Async client helpers over the generated `CacheClient`: connect, upload a file in chunks with
//! its checksum, and collect a refinement stream. Used by the `wavesplat cache` commands, the
//! tests and the load test; a viewer drives `refine` itself to change views mid-stream.

use crate::convert;
use crate::model::VolumeKey;
use crate::priority::ViewSpec;
use crate::store::sha256;
use tonic::transport::Channel;
use tonic::Status;
use wavesplat_proto::pb;
use wavesplat_proto::pb::cache_client::CacheClient;

/// Upload chunk size.
pub const CHUNK_BYTES: usize = 1 << 20;

/// Connects to a cache at `url` (e.g. `http://127.0.0.1:50051`).
pub async fn connect(url: &str) -> Result<CacheClient<Channel>, tonic::transport::Error> {
    let client = CacheClient::connect(url.to_string()).await?;
    Ok(client
        .max_decoding_message_size(64 << 20)
        .max_encoding_message_size(8 << 20))
}

/// The messages of an upload of `bytes` under `name`: `start`, then chunks.
pub fn ingest_messages(name: &str, bytes: &[u8]) -> Vec<pb::IngestRequest> {
    use pb::ingest_request::Msg;
    let mut out = vec![pb::IngestRequest {
        msg: Some(Msg::Start(pb::IngestStart {
            name: name.to_string(),
            total_size: bytes.len() as u64,
            sha256: sha256(bytes).to_vec(),
        })),
    }];
    out.extend(bytes.chunks(CHUNK_BYTES).map(|c| pb::IngestRequest {
        msg: Some(Msg::Chunk(c.to_vec())),
    }));
    out
}

/// Uploads a `.wsp` file.
pub async fn ingest(
    client: &mut CacheClient<Channel>,
    name: &str,
    bytes: &[u8],
) -> Result<pb::IngestResponse, Status> {
    let msgs = ingest_messages(name, bytes);
    Ok(client.ingest(tokio_stream::iter(msgs)).await?.into_inner())
}

/// The first message of a refinement stream.
pub fn refine_start(
    key: &VolumeKey,
    view: &ViewSpec,
    have: Vec<u32>,
    have_header: bool,
) -> pb::RefineRequest {
    pb::RefineRequest {
        msg: Some(pb::refine_request::Msg::Start(pb::RefineStart {
            volume: Some(convert::volume_ref(key)),
            view: Some(convert::view_message(view)),
            have,
            have_header,
        })),
    }
}

/// What a refinement stream delivered.
#[derive(Debug, Clone, Default)]
pub struct Refined {
    /// The header section, if sent.
    pub header: Option<Vec<u8>>,
    /// Packets in arrival order.
    pub packets: Vec<pb::Packet>,
    /// Whether the server said `done`.
    pub done: bool,
}

/// Streams packets for one view until `done` or until `max_bytes` of packet data arrived
/// (then the stream is dropped).
pub async fn refine_collect(
    client: &mut CacheClient<Channel>,
    key: &VolumeKey,
    view: &ViewSpec,
    have: Vec<u32>,
    max_bytes: Option<u64>,
) -> Result<Refined, Status> {
    let (tx, rx) = tokio::sync::mpsc::channel(4);
    tx.send(refine_start(key, view, have, false))
        .await
        .map_err(|_| Status::internal("request channel closed"))?;
    let mut stream = client
        .refine(tokio_stream::wrappers::ReceiverStream::new(rx))
        .await?
        .into_inner();
    let mut out = Refined::default();
    let mut bytes = 0u64;
    while let Some(m) = stream.message().await? {
        match m.msg {
            Some(pb::refine_response::Msg::Header(h)) => out.header = Some(h.header),
            Some(pb::refine_response::Msg::Packet(p)) => {
                bytes += p.data.len() as u64;
                out.packets.push(p);
                if max_bytes.is_some_and(|m| bytes >= m) {
                    break;
                }
            }
            Some(pb::refine_response::Msg::Done(_)) => {
                out.done = true;
                break;
            }
            None => {}
        }
    }
    drop(tx);
    Ok(out)
}
