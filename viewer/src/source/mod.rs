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

mod cache;
mod feed;
pub(crate) mod file;

pub use cache::{CacheSource, CacheSourceOptions};
pub(crate) use feed::{packet_source_via_feed, Control, Feed, PacketSender};
pub use file::FileSource;

use std::ops::Range;
use std::path::PathBuf;
use wavesplat_client::ClientError;
use wavesplat_codec::format::packet::{decode_packet, Coefficient};
use wavesplat_codec::format::{FormatError, Header};
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
    /// The view asks what this volume cannot be drawn with (e.g. multiview of a bricked
    /// volume, drawn in one pass only).
    #[error("{0}")]
    Unsupported(String),
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

/// A packet's tile and coefficients, `None` when it did not decode.
type Decoded = Option<(usize, Vec<Coefficient>)>;

/// Decodes a packet for the session; one that fails to decode goes on as bytes and the session
/// reports it.
fn decode_for_session(header: &Header, data: &[u8]) -> Decoded {
    decode_packet(header, data)
        .ok()
        .map(|d| (d.tile, d.coefficients))
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
