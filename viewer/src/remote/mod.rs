//! Browsing a published volume by byte ranges, with no wavesplat server: a [`RangeSource`] reads
//! a volume in the indexed layout (`wavesplat publish`, or the objects cache nodes keep in a
//! bucket) from any HTTP server, CDN or S3-compatible bucket.
//!
//! The header and the packet index come in one request (two when they are larger than the first
//! request's 64 KiB). The packets the current view sees are then requested in the order the
//! cache would send them (visible energy per byte, `codec::view::visibility::packet_order`), the
//! next few in the order whose bytes neighbour each other coalesced into one range, at most
//! [`RangeSourceOptions::in_flight`] requests at once. Bytes that came with the head are never
//! asked for again: packets inside them need no request, and the range of a packet that starts
//! inside them begins where they end. A view change reorders what is not yet requested. Every
//! range is checked: its length, then each packet's framing and CRC as it is decoded on the
//! network thread; a server that returns less than asked or altered bytes stops the source with
//! an error that says so ([`SourceStatus::failed`]).
//!
//! `http(s)://` URLs are read with reqwest: plain GET with `Range`, TLS verified against the CA
//! given (PEM, `--ca`) or else the system's roots. Only what may pass is tried again (a refused
//! or dropped connection, a timeout, 5xx, 429), a few times with short pauses; what will not
//! pass fails at once, saying why ([`RangeError`]): a status names its code (the server's page
//! is not printed, at most a line of plain text), an `https://` URL to a server that does not
//! speak TLS says so, a certificate from an unknown CA says to pass `--ca`. `s3://` URLs go
//! through the object-store client (as the cache's bucket store does), which signs requests.

mod fetch;
mod head;
mod object;

use crate::session::BrickedVolume;
pub use crate::source::RangeError;
use crate::source::{packet_source_via_feed, Feed, SourceError, SourceStatus};
use fetch::Fetch;
use head::read_head;
use object::Object;
use std::collections::HashSet;
use std::path::Path;
use std::sync::{Arc, Mutex};
use wavesplat_codec::format::index::wsp_of_indexed;
use wavesplat_codec::format::Header;
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
    /// Of a time series, the time point drawn (the packets of the components it names; 0 for
    /// any other volume).
    pub time_point: usize,
}

impl Default for RangeSourceOptions {
    fn default() -> Self {
        RangeSourceOptions {
            in_flight: 4,
            max_request_bytes: 512 << 10,
            lookahead: 64,
            visible_only: true,
            queue_bytes: 256 << 10,
            time_point: 0,
        }
    }
}

/// Packets fetched by range on a background thread (see the module documentation).
#[derive(Debug)]
pub struct RangeSource {
    feed: Feed,
    /// The volume as a session draws it, when it is bricked (or a time point of a series).
    bricked: Option<Box<BrickedVolume>>,
    /// Of a time series, its manifest.
    series: Option<Box<wavesplat_codec::format::series::SeriesManifest>>,
}

/// The `.wsp` bytes of the volume at `url` (the whole object, without the index in front when
/// it is in the indexed layout): for a reference render of everything. `ca`: the PEM CA to
/// trust for `https://`.
pub fn fetch_wsp(url: &str, ca: Option<&Path>) -> Result<Vec<u8>, SourceError> {
    let object = Object::open(url, ca)?;
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .map_err(|e| SourceError::Thread(e.to_string()))?;
    let (bytes, _) = runtime.block_on(object.read(None))?;
    if !bytes.starts_with(wavesplat_codec::format::index::INDEXED_MAGIC) {
        return Ok(bytes.to_vec());
    }
    // The head checked and the object's length held to what it declares, as for a local file.
    wsp_of_indexed(&bytes)
        .map(<[u8]>::to_vec)
        .map_err(|e| SourceError::Remote(format!("{url}: {e}")))
}

/// Whether `s` names a volume to browse by range requests rather than a local file.
pub fn is_remote(s: &str) -> bool {
    ["http://", "https://", "s3://", "s3a://"]
        .iter()
        .any(|p| s.starts_with(p))
}

impl RangeSource {
    /// Reads the head of the volume at `url` and starts fetching the packets `spec` sees;
    /// `ca`: the PEM CA to trust for `https://` (else the system's roots).
    pub fn open(
        url: &str,
        ca: Option<&Path>,
        spec: ViewSpec,
        options: RangeSourceOptions,
    ) -> Result<(RangeSource, Header), SourceError> {
        spec.validate()?;
        let object = Object::open(url, ca)?;
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .map_err(|e| SourceError::Thread(e.to_string()))?;
        let status = Arc::new(Mutex::new(SourceStatus {
            connected: true,
            ..Default::default()
        }));
        let head = runtime.block_on(read_head(&object, url, &status, options.time_point))?;
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
        let bricked = head.bricked_volume().map(Box::new);
        let series = head.series.clone();
        let mut fetch = Fetch {
            url: url.to_string(),
            object,
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
        Ok((
            RangeSource {
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

packet_source_via_feed!(RangeSource);

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn remote_names_are_recognised() {
        assert!(is_remote("https://cdn.example/a/v.wspx"));
        assert!(is_remote("s3://bucket/v.wspx"));
        assert!(!is_remote("v.wspx"));
        assert!(!is_remote("/data/http://x"));
        let open = |url| Object::open(url, None);
        assert!(open("http://host/").is_err(), "no file name");
        assert!(open("ftp://host/v.wspx").is_err());
        assert!(open("http://host/dir/v.wspx").is_ok());
        assert!(open("https://host/dir/v.wspx").is_ok());
        let ca = Path::new("/nonexistent/ca.pem");
        assert_eq!(
            Object::open("http://host/v.wspx", Some(ca)).err(),
            Some(RangeError::CaWithoutTls)
        );
        assert!(matches!(
            Object::open("https://host/v.wspx", Some(ca)),
            Err(RangeError::Ca { .. })
        ));
    }
}
