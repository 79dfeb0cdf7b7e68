//! The client of the wavesplat coefficient cache: everything a workstation or a worker says to
//! a cache, in domain types. The generated gRPC types stay inside this crate ([`convert`]).
//!
//! - [`CacheClient`]: list and describe volumes, fetch a header (parsed and validated by the
//!   codec), ingest a `.wsp` file, delete, and open a view-dependent refinement stream;
//! - [`RefineStream`]: the packets of one volume in the order of the current view, pulled with a
//!   byte credit the client renews as it consumes (so little is in flight and a view change
//!   reorders the rest), with view changes and holdings (what the client has, what it dropped)
//!   sent on the same stream; [`RefineControl`] is a cloneable handle for those messages;
//! - [`blocking`]: the same calls for synchronous callers, over a private runtime.
//!
//! ```no_run
//! # async fn demo() -> Result<(), wavesplat_client::ClientError> {
//! use wavesplat_client::{CacheClient, RefineEvent, RefineRequest, VolumeKey};
//! use wavesplat_codec::view::{View, ViewSpec};
//! let mut cache = CacheClient::connect("http://127.0.0.1:50051").await?;
//! let request = RefineRequest::new(VolumeKey::Name("head".into()), ViewSpec::single(View::new(0.3, 0.2, 256, 256)));
//! let mut stream = cache.refine(request.with_credit(256 << 10)).await?;
//! while let Some(event) = stream.next().await? {
//!     if let RefineEvent::Packet(p) = event {
//!         stream.control().grant(p.data.len() as u64).await?; // consumed: ask for as much again
//!     }
//! }
//! # Ok(()) }
//! ```

pub mod blocking;
pub mod convert;
mod refine;

pub use refine::{RefineControl, RefineEvent, RefineRequest, RefineStream};

use thiserror::Error;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::Channel;
use wavesplat_codec::format::{read_header_section, FormatError, Header};
pub use wavesplat_net::{ConnectOptions, Credentials, VolumeKey};
use wavesplat_proto::pb;

/// Upload chunk size.
pub const CHUNK_BYTES: usize = 1 << 20;
/// Largest message accepted from a cache (a packet is at most this big).
pub const MAX_MESSAGE_BYTES: usize = 64 << 20;

/// Errors of the cache client.
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum ClientError {
    /// The URL is not a cache address.
    #[error("invalid cache URL {url:?}: {reason}")]
    Url {
        /// The URL given.
        url: String,
        /// What is wrong with it.
        reason: String,
    },
    /// Could not connect (the message includes the causes: refused, TLS handshake, ...).
    #[error("cannot connect to the cache at {url}: {reason}")]
    Connect {
        /// The URL.
        url: String,
        /// What went wrong, with its causes.
        reason: String,
    },
    /// The cache answered with an error status.
    #[error("cache: {code:?}: {message}")]
    Status {
        /// gRPC status code.
        code: tonic::Code,
        /// The server's message.
        message: String,
    },
    /// The cache sent something the protocol does not allow.
    #[error("cache protocol: {0}")]
    Protocol(String),
    /// The header the cache sent does not parse.
    #[error("the cache sent an invalid header: {0}")]
    Header(#[from] FormatError),
    /// The refinement stream's request side is closed (the stream ended).
    #[error("the refinement stream is closed")]
    Closed,
    /// The file being uploaded could not be read (nothing was stored).
    #[error("reading the file to upload: {0}")]
    UploadRead(#[source] std::io::Error),
}

impl ClientError {
    /// Whether the node failed (unreachable, unavailable, overloaded, an internal error), as
    /// opposed to answering about the request (not found, refused), which another node over the
    /// same store would answer too.
    pub fn is_node_failure(&self) -> bool {
        use tonic::Code;
        match self {
            ClientError::Connect { .. } => true,
            ClientError::Status { code, .. } => matches!(
                code,
                Code::Unavailable
                    | Code::Unknown
                    | Code::Internal
                    | Code::Cancelled
                    | Code::DeadlineExceeded
                    | Code::ResourceExhausted
            ),
            _ => false,
        }
    }

    /// The gRPC status code, when the cache answered with one.
    pub fn code(&self) -> Option<tonic::Code> {
        match self {
            ClientError::Status { code, .. } => Some(*code),
            _ => None,
        }
    }
}

impl From<tonic::Status> for ClientError {
    fn from(s: tonic::Status) -> Self {
        ClientError::Status {
            code: s.code(),
            message: s.message().to_string(),
        }
    }
}

/// What the cache answered to an upload.
fn ingested(r: pb::IngestResponse) -> Result<Ingested, ClientError> {
    Ok(Ingested {
        volume: convert::volume_info(
            r.volume
                .ok_or_else(|| ClientError::Protocol("ingest returned no volume".into()))?,
        )?,
        existed: r.existed,
    })
}

/// `file`'s length and SHA-256, read from its start; the file is handed back rewound.
fn hash_file(mut file: std::fs::File) -> std::io::Result<(std::fs::File, u64, [u8; 32])> {
    use std::io::{Seek, SeekFrom};
    file.seek(SeekFrom::Start(0))?;
    let mut total = 0;
    let sha256 = wavesplat_net::digest::sha256_stream(|w| {
        total = std::io::copy(&mut file, w)?;
        Ok::<_, std::io::Error>(())
    })?;
    file.seek(SeekFrom::Start(0))?;
    Ok((file, total, sha256))
}

/// What the cache says about a stored volume.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct VolumeInfo {
    /// Cache-assigned id.
    pub id: u64,
    /// Name.
    pub name: String,
    /// Volume dimensions (x, y, z).
    pub dims: [u32; 3],
    /// Channels.
    pub channels: u32,
    /// Wavelet family name.
    pub family: String,
    /// Decomposition depth.
    pub levels: u32,
    /// Size of the file.
    pub file_bytes: u64,
    /// Size of the header section.
    pub header_bytes: u64,
    /// Sum of the packet sizes.
    pub packet_bytes: u64,
    /// Creation time (ms since the Unix epoch).
    pub created_unix_ms: u64,
    /// Packets.
    pub packet_count: u32,
    /// Tiles.
    pub tile_count: u32,
    /// Quality layers.
    pub layer_count: u32,
    /// Tile edge (voxels of the padded grid).
    pub tile: u32,
    /// Coefficients in the file.
    pub coefficients: u64,
    /// SHA-256 of the file, lower-case hex.
    pub sha256: String,
}

/// A volume's header: its facts, the parsed header and the header section's bytes.
#[derive(Debug, Clone)]
pub struct VolumeHeader {
    /// The cache's facts.
    pub info: VolumeInfo,
    /// The parsed, validated header (a bricked volume's: the whole's, for views).
    pub header: Header,
    /// The header section as stored (magic to header CRC; a bricked volume's: its container's
    /// manifest section).
    pub bytes: Vec<u8>,
    /// A bricked volume's bricks, or every component's bricks of a time series, in the order
    /// of their packets' ids (empty for one volume).
    pub bricks: Vec<BrickHeader>,
    /// A time series' manifest: its time points, each a weighted sum of components (`header`
    /// is then the one every time point is drawn with).
    pub series: Option<Box<wavesplat_codec::format::series::SeriesManifest>>,
}

/// One brick of a bricked volume as the cache describes it.
#[derive(Debug, Clone)]
pub struct BrickHeader {
    /// Its header (what its packets decode with).
    pub header: Header,
    /// Its first voxel in the whole.
    pub origin: [u64; 3],
    /// Its packets (their ids follow the previous bricks').
    pub packets: u32,
    /// Of a time series: its component (0 otherwise).
    pub component: usize,
}

/// One packet as the cache sent it.
#[derive(Debug, Clone, PartialEq)]
pub struct Packet {
    /// Index of the packet in file order.
    pub id: u32,
    /// Tile.
    pub tile: u32,
    /// Quality layer.
    pub layer: u32,
    /// The packet's bytes (decode with `wavesplat_codec::format::packet::decode_packet`).
    pub data: Vec<u8>,
    /// Visible energy per byte the server ranked it by for the current view.
    pub priority: f64,
}

/// One row of a volume's packet table (file order).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PacketEntry {
    /// Tile.
    pub tile: u32,
    /// Quality layer.
    pub layer: u32,
    /// Size in bytes.
    pub bytes: u32,
    /// Energy of its coefficients.
    pub energy: f64,
}

/// The outcome of an ingest.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Ingested {
    /// The stored volume.
    pub volume: VolumeInfo,
    /// Identical content was already stored (nothing was written).
    pub existed: bool,
}

/// The transport under the generated client: a channel that adds the caller's token.
pub type Transport = InterceptedService<Channel, Credentials>;

/// An async client of one cache.
#[derive(Debug, Clone)]
pub struct CacheClient {
    inner: pb::cache_client::CacheClient<Transport>,
    /// The URL, for explaining transport failures (a plaintext URL against a TLS server).
    url: std::sync::Arc<str>,
}

impl CacheClient {
    /// Connects to a cache at `url` (`http://HOST:PORT`, `https://HOST:PORT` or `HOST:PORT`)
    /// without a token, trusting the system's roots for TLS.
    pub async fn connect(url: &str) -> Result<CacheClient, ClientError> {
        Self::connect_with(url, &ConnectOptions::default()).await
    }

    /// Connects to a cache at `url` with `options`.
    pub async fn connect_with(
        url: &str,
        options: &ConnectOptions,
    ) -> Result<CacheClient, ClientError> {
        let (url, endpoint) = endpoint(url, options)?;
        let channel = endpoint.connect().await.map_err(|e| ClientError::Connect {
            reason: wavesplat_net::tls::explain_connect_error(&url, &e),
            url: url.clone(),
        })?;
        Ok(CacheClient::over(channel, &url, options))
    }

    /// A client that connects on first use and reconnects after failures (for long-lived
    /// callers such as workers, which may start before the cache does).
    pub fn connect_lazy(url: &str, options: &ConnectOptions) -> Result<CacheClient, ClientError> {
        let (url, endpoint) = endpoint(url, options)?;
        Ok(CacheClient::over(endpoint.connect_lazy(), &url, options))
    }

    /// The result of a call, its failure explained ([`CacheClient::explained`]).
    async fn checked<T>(&self, r: Result<T, tonic::Status>) -> Result<T, ClientError> {
        match r {
            Ok(t) => Ok(t),
            Err(s) => Err(self.explained(s.into()).await),
        }
    }

    /// A failed call's error, a status from the transport explained for this client's URL
    /// ([`wavesplat_net::tls::explain_status`]: a plaintext URL against a TLS server).
    async fn explained(&self, e: ClientError) -> ClientError {
        match e {
            ClientError::Status { code, message } => {
                wavesplat_net::tls::explain_status(&self.url, tonic::Status::new(code, message))
                    .await
                    .into()
            }
            e => e,
        }
    }

    fn over(channel: Channel, url: &str, options: &ConnectOptions) -> CacheClient {
        let channel = InterceptedService::new(channel, options.credentials.clone());
        let inner = pb::cache_client::CacheClient::new(channel)
            .max_decoding_message_size(MAX_MESSAGE_BYTES)
            .max_encoding_message_size(CHUNK_BYTES + (1 << 20));
        CacheClient {
            inner,
            url: url.into(),
        }
    }

    /// Every stored volume, ordered by name.
    pub async fn list(&mut self) -> Result<Vec<VolumeInfo>, ClientError> {
        let r = self.inner.list(pb::ListRequest {}).await;
        let r = self.checked(r).await?.into_inner();
        r.volumes.into_iter().map(convert::volume_info).collect()
    }

    /// One volume's facts.
    pub async fn describe(&mut self, key: &VolumeKey) -> Result<VolumeInfo, ClientError> {
        let r = self
            .inner
            .describe(pb::DescribeRequest {
                volume: Some(convert::volume_ref(key)),
            })
            .await;
        let r = self.checked(r).await?;
        convert::volume_info(r.into_inner())
    }

    /// A volume's header (parsed and validated).
    pub async fn header(&mut self, key: &VolumeKey) -> Result<VolumeHeader, ClientError> {
        let r = self
            .inner
            .header(pb::DescribeRequest {
                volume: Some(convert::volume_ref(key)),
            })
            .await;
        let r = self.checked(r).await?;
        convert::volume_header(r.into_inner())
    }

    /// A volume's packet table (file order).
    pub async fn packet_table(&mut self, key: &VolumeKey) -> Result<Vec<PacketEntry>, ClientError> {
        let r = self
            .inner
            .packet_table(pb::DescribeRequest {
                volume: Some(convert::volume_ref(key)),
            })
            .await;
        let r = self.checked(r).await?;
        Ok(r.into_inner()
            .packets
            .into_iter()
            .map(|p| PacketEntry {
                tile: p.tile,
                layer: p.layer,
                bytes: p.bytes,
                energy: p.energy,
            })
            .collect())
    }

    /// Removes a volume; returns its id.
    pub async fn delete(&mut self, key: &VolumeKey) -> Result<u64, ClientError> {
        let r = self
            .inner
            .delete(pb::DeleteRequest {
                volume: Some(convert::volume_ref(key)),
            })
            .await;
        let r = self.checked(r).await?;
        Ok(r.into_inner().id)
    }

    /// Uploads a `.wsp` file under `name` (in chunks, with its SHA-256). Copies it once: a
    /// caller that owns the bytes gives them to [`CacheClient::ingest_owned`] instead.
    pub async fn ingest(&mut self, name: &str, bytes: &[u8]) -> Result<Ingested, ClientError> {
        self.ingest_owned(name, bytes.to_vec()).await
    }

    /// Uploads a `.wsp` file under `name`, as [`CacheClient::ingest`] does, taking the bytes:
    /// each chunk's message is made as the transport takes it, so the upload costs a chunk or
    /// two of memory beyond the file, not the file again.
    pub async fn ingest_owned(
        &mut self,
        name: &str,
        bytes: Vec<u8>,
    ) -> Result<Ingested, ClientError> {
        let msgs = convert::ingest_messages(name, bytes);
        let r = self.inner.ingest(tokio_stream::iter(msgs)).await;
        ingested(self.checked(r).await?.into_inner())
    }

    /// Uploads the `.wsp` file `file` (read from its start) under `name`, as
    /// [`CacheClient::ingest`] does, without holding it: one pass reads it for its SHA-256,
    /// a second sends it chunk by chunk as the transport takes them, so that the upload costs a
    /// few chunks of memory whatever the file's size. A file that changes between the passes
    /// fails the cache's hash check and is not stored.
    pub async fn ingest_file(
        &mut self,
        name: &str,
        file: std::fs::File,
    ) -> Result<Ingested, ClientError> {
        let (file, total, sha256) = tokio::task::spawn_blocking(move || hash_file(file))
            .await
            .map_err(|e| ClientError::UploadRead(std::io::Error::other(e)))?
            .map_err(ClientError::UploadRead)?;
        let (chunks, read_error) = convert::file_chunks(file, total);
        let msgs = tokio_stream::StreamExt::chain(
            tokio_stream::once(convert::ingest_start(name, total, sha256)),
            chunks,
        );
        let r = self.inner.ingest(msgs).await;
        // A read that failed ended the stream early, which the cache refused as short: the
        // read's error is the one to report.
        if let Some(e) = read_error.lock().unwrap_or_else(|p| p.into_inner()).take() {
            return Err(ClientError::UploadRead(e));
        }
        ingested(self.checked(r).await?.into_inner())
    }

    /// The header and the first packets in global significance order, up to `max_bytes`.
    pub async fn first_packets(
        &mut self,
        key: &VolumeKey,
        max_bytes: u64,
    ) -> Result<(Header, Vec<Packet>), ClientError> {
        let r = self
            .inner
            .first_packets(pb::FirstPacketsRequest {
                volume: Some(convert::volume_ref(key)),
                max_bytes,
            })
            .await;
        let r = self.checked(r).await?.into_inner();
        let (header, _) = read_header_section(&r.header)?;
        Ok((header, r.packets.into_iter().map(convert::packet).collect()))
    }

    /// Opens a view-dependent refinement stream.
    pub async fn refine(&mut self, request: RefineRequest) -> Result<RefineStream, ClientError> {
        match refine::open(&mut self.inner, request).await {
            Err(e) => Err(self.explained(e).await),
            ok => ok,
        }
    }

    /// Streams packets for one view until the server is done or `max_bytes` of packet data
    /// arrived (then the stream is dropped). No flow control: a convenience for tools and tests.
    pub async fn refine_collect(
        &mut self,
        request: RefineRequest,
        max_bytes: Option<u64>,
    ) -> Result<Collected, ClientError> {
        let mut stream = self.refine(request).await?;
        let mut out = Collected::default();
        let mut bytes = 0u64;
        while let Some(event) = stream.next().await? {
            match event {
                RefineEvent::Header(h) => out.header = Some(*h),
                RefineEvent::Packet(p) => {
                    bytes += p.data.len() as u64;
                    out.packets.push(p);
                    if max_bytes.is_some_and(|m| bytes >= m) {
                        break;
                    }
                }
                RefineEvent::Done { .. } => {
                    out.done = true;
                    break;
                }
            }
        }
        Ok(out)
    }
}

/// What [`CacheClient::refine_collect`] received.
#[derive(Debug, Clone, Default)]
pub struct Collected {
    /// The header, if sent.
    pub header: Option<VolumeHeader>,
    /// Packets in arrival order.
    pub packets: Vec<Packet>,
    /// Whether the server said `done`.
    pub done: bool,
}

/// The endpoint of a cache URL, with the connection settings every client uses.
fn endpoint(
    url: &str,
    options: &ConnectOptions,
) -> Result<(String, tonic::transport::Endpoint), ClientError> {
    options.endpoint(url).map_err(|e| ClientError::Url {
        url: url.to_string(),
        reason: e.to_string(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn urls_are_normalised_or_refused() {
        let o = ConnectOptions::default();
        assert_eq!(endpoint("h:1", &o).unwrap().0, "http://h:1");
        assert_eq!(endpoint("http://h:1", &o).unwrap().0, "http://h:1");
        assert_eq!(endpoint("https://h:1", &o).unwrap().0, "https://h:1");
        assert!(endpoint("", &o).is_err());
        assert!(endpoint("ftp://h:1", &o).is_err());
        assert!(endpoint("http://", &o).is_err());
    }
}
