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
//! or dropped connection, an answer silent for the read timeout, 5xx, 429), a few times with
//! growing jittered pauses or after the server's `Retry-After`, a broken body from where it
//! broke. When every attempt failed the source does not stop: it puts those packets back at the
//! head of its queue, reports itself not connected with the problem, waits and goes on, and the
//! frame loop gives up only after its patience ([`crate::frame::RunToEnd::patience`]). What
//! will not pass fails at once, saying why ([`RangeError`]): a status names its code (the
//! server's page is not printed, at most a line of plain text or an XML error's code and
//! message), an `https://` URL to a server that does not speak TLS says so, a certificate from
//! an unknown CA says to pass `--ca`, a file changed on the server since it was opened (another
//! size or `ETag`) says to reopen it, a compressed body names its encoding. `s3://` URLs go
//! through the object-store client (as the cache's bucket store does), which signs requests.
//!
//! A URL may carry credentials (a password, a presigned query): messages and logs show it
//! [`redacted`].

mod fetch;
mod head;
mod object;
#[cfg(test)]
mod stub;
#[cfg(test)]
mod stub_tests;

use crate::session::BrickedVolume;
pub use crate::source::RangeError;
use crate::source::{packet_source_via_feed, Feed, SourceError, SourceStatus};
use fetch::Fetch;
use head::read_head;
use object::{Object, Pacing};
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
/// trust for `https://`. A transfer that breaks goes on from where it broke.
pub fn fetch_wsp(url: &str, ca: Option<&Path>) -> Result<Vec<u8>, SourceError> {
    let object = Object::open(url, ca)?;
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .map_err(|e| SourceError::Thread(e.to_string()))?;
    let (mut bytes, _) = runtime.block_on(object.read_vec(None))?;
    if !bytes.starts_with(wavesplat_codec::format::index::INDEXED_MAGIC) {
        return Ok(bytes);
    }
    // The head checked and the object's length held to what it declares, as for a local file;
    // the `.wsp` is the object's tail, moved to the front in place.
    let wsp = wsp_of_indexed(&bytes)
        .map_err(|e| SourceError::Remote(format!("{}: {e}", redacted(url))))?
        .len();
    bytes.drain(..bytes.len() - wsp);
    Ok(bytes)
}

/// Whether `s` names a volume to browse by range requests rather than a local file (its
/// scheme in any case, as URLs allow).
pub fn is_remote(s: &str) -> bool {
    ["http://", "https://", "s3://", "s3a://"]
        .iter()
        .any(|p| s.get(..p.len()).is_some_and(|h| h.eq_ignore_ascii_case(p)))
}

/// `url` as messages and logs show it: a user and password replaced by `***`, every query value by
/// `***` (the names kept: `X-Amz-Signature=***`; an item without a value is `***` whole), any
/// fragment dropped. What does not parse as a URL is shown up to its query, without what
/// precedes an `@` in its authority.
pub fn redacted(url: &str) -> String {
    let Ok(mut parsed) = url::Url::parse(url) else {
        let cut = url.split(['?', '#']).next().unwrap_or_default();
        return match cut.split_once("://") {
            Some((scheme, rest)) => {
                let (authority, path) = rest.split_at(rest.find('/').unwrap_or(rest.len()));
                let host = authority.rsplit_once('@').map_or(authority, |(_, h)| h);
                format!("{scheme}://{host}{path}")
            }
            None => cut.to_string(),
        };
    };
    if parsed.password().is_some() {
        // Only a URL that cannot have one refuses a password.
        let _ = parsed.set_password(Some("***"));
    }
    if !parsed.username().is_empty() {
        // A token is often given as the user name alone (`https://TOKEN@host/…`).
        let _ = parsed.set_username("***");
    }
    if let Some(query) = parsed.query() {
        let masked: Vec<String> = query
            .split('&')
            .filter_map(|item| match item.split_once('=') {
                Some((name, _)) => Some(format!("{name}=***")),
                None if item.is_empty() => None,
                None => Some("***".to_string()),
            })
            .collect();
        parsed.set_query(Some(&masked.join("&")));
    }
    parsed.set_fragment(None);
    parsed.to_string()
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
        RangeSource::open_paced(url, ca, spec, options, Pacing::default())
    }

    /// [`RangeSource::open`] with the reads paced as `pacing` says.
    fn open_paced(
        url: &str,
        ca: Option<&Path>,
        spec: ViewSpec,
        options: RangeSourceOptions,
        pacing: Pacing,
    ) -> Result<(RangeSource, Header), SourceError> {
        spec.validate()?;
        let object = Object::open_paced(url, ca, pacing)?;
        let shown = redacted(url);
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .map_err(|e| SourceError::Thread(e.to_string()))?;
        let status = Arc::new(Mutex::new(SourceStatus {
            connected: true,
            ..Default::default()
        }));
        let head = runtime.block_on(read_head(&object, &shown, &status, options.time_point))?;
        if !head.indexed {
            tracing::warn!(
                url = %shown,
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
            url: shown,
            object,
            options,
            requested: HashSet::new(),
            queue: Vec::new(),
            status: status.clone(),
            head,
            view: None,
            views: 0,
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
        assert!(is_remote("HTTPS://cdn.example/a/v.wspx"));
        assert!(is_remote("Http://cdn.example/a/v.wspx"));
        assert!(is_remote("S3://bucket/v.wspx"));
        assert!(!is_remote("v.wspx"));
        assert!(!is_remote("/data/http://x"));
        assert!(!is_remote("ht"));
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

    /// Messages show a URL with its user, password and query values replaced, its query names
    /// kept.
    #[test]
    fn urls_are_shown_without_their_credentials() {
        assert_eq!(
            redacted(
                "https://reader:pw@cdn.example/a/v.wspx?X-Amz-Signature=abc&X-Amz-Expires=300&t"
            ),
            "https://***:***@cdn.example/a/v.wspx?X-Amz-Signature=***&X-Amz-Expires=***&***"
        );
        assert_eq!(
            redacted("https://ghp_secret@host.example/v.wspx"),
            "https://***@host.example/v.wspx"
        );
        assert_eq!(
            redacted("https://cdn.example/v.wspx?token="),
            "https://cdn.example/v.wspx?token=***"
        );
        assert_eq!(redacted("s3://bucket/dir/v.wspx"), "s3://bucket/dir/v.wspx");
        assert_eq!(
            redacted("http://127.0.0.1:8080/v.wspx#key=1"),
            "http://127.0.0.1:8080/v.wspx"
        );
        assert_eq!(
            redacted("http://u:p@[::1/v.wspx?sig=1"),
            "http://[::1/v.wspx"
        );
        assert_eq!(redacted("v.wspx?sig=1"), "v.wspx");
    }
}
