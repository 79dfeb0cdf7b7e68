//! Volumes in an object store (S3 and its compatibles, or a shared file system), so that any
//! number of stateless cache nodes can serve one archive.
//!
//! Layout under the store's prefix:
//! - `volumes/<sha256>.wspx`: one immutable object per content, the uploaded `.wsp` in the
//!   indexed layout (`wavesplat_codec::format::index`): a reader has the header and the whole
//!   packet index (tiles, layers, the energy summaries the planner weighs) after one ranged
//!   request (two when they are larger than the first request), then fetches packets by range;
//!   a bricked volume is its container in the bricked indexed layout (version 2: the manifest,
//!   then every brick's header and index), its packets numbered brick after brick;
//! - `names/<key of the name>`: one small object per name holding the content hash, written
//!   with `If-None-Match: *`, so two nodes that ingest the same volume at once store it once and
//!   the same name cannot point at two contents. The key is the name's bytes in lowercase hex:
//!   one path segment for a name of up to 126 bytes (252 digits: with the local store's `#N`
//!   staging suffix, within the 255 bytes a file system, or SeaweedFS, allows a segment); a
//!   longer name's hex in segments of 200 digits, each but the last followed by `-`
//!   (`names/<200 digits>-/<200 digits>-/<the rest>`), so that no segment is too long and no
//!   name's file is another name's directory. A listing reads every name back from its key.
//!   Earlier releases keyed every name by one segment, which AWS S3 takes for any valid name
//!   (a file system refused names of 127 bytes or more, SeaweedFS of 128 or more): a long
//!   name's record is also looked for, listed and deleted under that segment, where the
//!   backend takes such a key.
//!
//! A volume's id is the first 63 bits of its SHA-256, the same on every node. Names are read
//! from the bucket on every lookup (a delete on one node is seen by the others at once); what a
//! node keeps is only a cache of immutable facts: parsed heads and name records by ETag, and a
//! bounded memory cache of packet bytes. A cold node serves from the bucket alone. Unlike the
//! embedded store, a stream whose volume another node deletes ends (not found) at the first
//! packet it has to read from the bucket.
//!
//! The object-store client is async; the store's methods are called on blocking threads (the
//! service's `blocking`), which wait on the runtime's handle. Packet reads on the refinement
//! stream's task are async ([`Bucket::read`]).

use crate::error::CacheError;
use crate::model::{
    BrickedIndex, IndexBrick, PacketMeta, SeriesIndex, VolumeIndex, VolumeKey, VolumeMeta,
    MAX_NAME_BYTES,
};
use bytes::Bytes;
use futures_util::{StreamExt, TryStreamExt};
use object_store::path::Path as ObjectPath;
use object_store::{ObjectStore, ObjectStoreExt, PutMode, PutOptions, PutPayload};
use std::collections::HashMap;
use std::num::NonZeroUsize;
use std::ops::Range;
use std::sync::{Arc, Mutex};
use wavesplat_codec::format::bricked::manifest_section;
use wavesplat_codec::format::index::{
    read_indexed_head, BrickedHead, HeadRead, IndexedHead, SeriesHead, HEAD_READ_BYTES,
};
use wavesplat_codec::view::bricked::{check_brick, whole_header};
use wavesplat_net::digest::{hex, unhex};

/// Name records fetched at once when listing.
const LIST_CONCURRENCY: usize = 16;
/// Parsed heads kept per node.
const HEADS_KEPT: usize = 256;

/// One request to the store may take this long (a packet is at most 16 MiB: 3.2 MB/s).
const REQUEST_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(5);
/// Connecting to the store may take this long.
const CONNECT_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(3);
/// A failing request is retried for this long at most.
const RETRY_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(4);

/// A cold node reads a volume's packets in one request up to this size (see [`Bucket::read`]).
pub const WHOLE_READ_BYTES: u64 = 8 << 20;

/// Magic of a name record.
const NAME_MAGIC: &[u8; 4] = b"WSPN";

/// A name whose hex has at most this many digits (a name of up to 126 bytes) is keyed by one
/// path segment, as every release has keyed it: with the local store's staging suffix (`#N`)
/// it stays within a file system's 255 bytes per file name.
const SINGLE_SEGMENT_HEX: usize = 252;
/// A longer name's hex is split into segments of this many digits.
const SEGMENT_HEX: usize = 200;
/// Ends every segment of a long name's key but the last (never a hex digit: a file's name is
/// never a directory's).
const SEGMENT_CONTINUES: char = '-';

/// A volume stored in a bucket, as a node has it open.
#[derive(Debug)]
pub struct BucketVolume {
    /// Its content hash.
    pub sha256: [u8; 32],
    /// Header and index (packet offsets within the `.wsp` or bricked container).
    pub index: VolumeIndex,
    /// Where the `.wsp` or container starts in the object (add it to a packet's offset).
    pub wsp_offset: u64,
    /// Length of the `.wsp` or container.
    pub wsp_bytes: u64,
    /// When the object was written (ms since the Unix epoch).
    pub created_unix_ms: u64,
}

impl BucketVolume {
    /// An opened object of one volume.
    fn whole(sha256: [u8; 32], h: IndexedHead, created_unix_ms: u64) -> BucketVolume {
        BucketVolume {
            sha256,
            index: VolumeIndex {
                header: h.header,
                header_bytes: h.header_bytes,
                packets: h.packets,
                bricked: None,
                series: None,
            },
            wsp_offset: h.wsp_offset,
            wsp_bytes: h.wsp_bytes,
            created_unix_ms,
        }
    }

    /// An opened object of a bricked volume (the indexed layout's version 2): its bricks
    /// checked against the manifest and the first brick, its packets numbered brick after
    /// brick with offsets from the container's start, and the manifest section clients get
    /// as the volume's header bytes.
    fn bricked(
        sha256: [u8; 32],
        h: BrickedHead,
        created_unix_ms: u64,
    ) -> Result<BucketVolume, CacheError> {
        let m = &h.manifest;
        let first = h
            .bricks
            .first()
            .map(|b| b.header.clone())
            .ok_or_else(|| CacheError::Corrupt("a bricked volume of no bricks".into()))?;
        let mut packets = Vec::new();
        let mut bricks = Vec::with_capacity(h.bricks.len());
        for (i, (b, entry)) in h.bricks.into_iter().zip(&m.bricks).enumerate() {
            check_brick(i, entry, &b.header, &first, m.channels)?;
            let first_packet = u32::try_from(packets.len())
                .ok()
                .filter(|n| n.checked_add(b.packets.len() as u32).is_some())
                .ok_or_else(|| CacheError::Corrupt("more than 2^32 packets".into()))?;
            bricks.push(IndexBrick {
                header: b.header,
                header_bytes: b.header_bytes,
                origin: entry.origin,
                first_packet,
                packets: b.packets.len() as u32,
            });
            packets.extend(b.packets.into_iter().map(|p| PacketMeta {
                offset: entry.offset + p.offset,
                ..p
            }));
        }
        Ok(BucketVolume {
            sha256,
            index: VolumeIndex {
                header: whole_header(m, &first),
                header_bytes: manifest_section(m),
                packets,
                bricked: Some(Box::new(BrickedIndex {
                    manifest: h.manifest,
                    bricks,
                })),
                series: None,
            },
            wsp_offset: h.wsp_offset,
            wsp_bytes: h.wsp_bytes,
            created_unix_ms,
        })
    }

    /// An opened object of a time series (the indexed layout's version 3): every component's
    /// bricks, their packets numbered brick after brick with offsets from the container's
    /// start, and the manifest section clients get as the volume's header bytes.
    fn series(
        sha256: [u8; 32],
        h: SeriesHead,
        created_unix_ms: u64,
    ) -> Result<BucketVolume, CacheError> {
        let mut packets = Vec::new();
        let mut bricks = Vec::with_capacity(h.bricks.len());
        let mut components: Vec<std::ops::Range<usize>> = Vec::new();
        for b in h.bricks {
            if components.len() == b.component {
                components.push(bricks.len()..bricks.len());
            }
            let first_packet = u32::try_from(packets.len())
                .ok()
                .filter(|n| n.checked_add(b.brick.packets.len() as u32).is_some())
                .ok_or_else(|| CacheError::Corrupt("more than 2^32 packets".into()))?;
            bricks.push(IndexBrick {
                header: b.brick.header,
                header_bytes: b.brick.header_bytes,
                origin: b.origin,
                first_packet,
                packets: b.brick.packets.len() as u32,
            });
            if let Some(r) = components.last_mut() {
                r.end = bricks.len();
            }
            packets.extend(b.brick.packets.into_iter().map(|p| PacketMeta {
                offset: b.offset + p.offset,
                ..p
            }));
        }
        let series = SeriesIndex {
            manifest: h.manifest,
            bricks,
            components,
            bricked: h.bricked,
        };
        let header = series.whole_header()?;
        Ok(BucketVolume {
            sha256,
            index: VolumeIndex {
                header,
                header_bytes: wavesplat_codec::format::series::manifest_section(&series.manifest),
                packets,
                bricked: None,
                series: Some(Box::new(series)),
            },
            wsp_offset: h.wsp_offset,
            wsp_bytes: h.wsp_bytes,
            created_unix_ms,
        })
    }

    fn object_bytes(&self) -> u64 {
        self.wsp_offset + self.wsp_bytes
    }
}

/// The store's handle on a bucket; cheap to share.
#[derive(Debug)]
pub struct Bucket {
    store: Arc<dyn ObjectStore>,
    prefix: ObjectPath,
    url: String,
    runtime: tokio::runtime::Handle,
    /// Name records by location, with their ETag: immutable once written.
    names: Mutex<HashMap<String, NameRecord>>,
    heads: Mutex<lru::LruCache<[u8; 32], Arc<BucketVolume>>>,
    /// Content hashes by id, as this node has seen them (the mapping never changes; whether the
    /// content still exists is asked of the store).
    ids: Mutex<HashMap<u64, [u8; 32]>>,
    packets: Mutex<PacketCache>,
}

/// A name object's ETag and the content it points at.
type NameRecord = (Option<String>, [u8; 32]);

/// Packet bytes by (volume id, packet), least recently used dropped first, bounded in bytes.
#[derive(Debug)]
struct PacketCache {
    entries: lru::LruCache<(u64, u32), Bytes>,
    bytes: u64,
    limit: u64,
}

impl PacketCache {
    fn get(&mut self, key: (u64, u32)) -> Option<Bytes> {
        self.entries.get(&key).cloned()
    }

    fn put(&mut self, key: (u64, u32), data: Bytes) {
        if data.len() as u64 > self.limit {
            return;
        }
        self.bytes += data.len() as u64;
        if let Some(old) = self.entries.put(key, data) {
            self.bytes -= old.len() as u64;
        }
        while self.bytes > self.limit {
            match self.entries.pop_lru() {
                Some((_, old)) => self.bytes -= old.len() as u64,
                None => break,
            }
        }
    }
}

/// A volume id from its content hash: the first 63 bits, the same on every node.
pub fn content_id(sha256: &[u8; 32]) -> u64 {
    let mut b = [0u8; 8];
    b.copy_from_slice(&sha256[..8]);
    u64::from_be_bytes(b) >> 1
}

impl Bucket {
    /// Opens the object store at `url` (`s3://bucket/prefix`, with endpoint, region and
    /// credentials from the standard `AWS_*` variables, or `file:///path`) and checks that it
    /// answers. `read_cache_bytes` bounds the node's memory cache of packet bytes. Must be called
    /// within a tokio runtime, whose handle the store's blocking methods then wait on.
    pub fn open(url: &str, read_cache_bytes: u64) -> Result<Bucket, CacheError> {
        wavesplat_net::tls::install_crypto_provider();
        let runtime = tokio::runtime::Handle::try_current().map_err(|_| {
            CacheError::Bucket("the object store must be opened within a tokio runtime".into())
        })?;
        let (store, prefix) = object_store_for(url)?;
        Ok(Bucket::over(store, prefix, url, runtime, read_cache_bytes))
    }

    /// A bucket over an opened object store: its keys under `prefix`, `url` naming it in
    /// messages.
    fn over(
        store: Arc<dyn ObjectStore>,
        prefix: ObjectPath,
        url: &str,
        runtime: tokio::runtime::Handle,
        read_cache_bytes: u64,
    ) -> Bucket {
        Bucket {
            store,
            prefix,
            url: url.to_string(),
            runtime,
            names: Mutex::new(HashMap::new()),
            ids: Mutex::new(HashMap::new()),
            heads: Mutex::new(lru::LruCache::new(
                NonZeroUsize::new(HEADS_KEPT).expect("non-zero"),
            )),
            packets: Mutex::new(PacketCache {
                entries: lru::LruCache::unbounded(),
                bytes: 0,
                limit: read_cache_bytes,
            }),
        }
    }

    /// Lists the names once, so that a wrong endpoint, bucket or credentials fail at start.
    pub async fn probe(&self) -> Result<(), CacheError> {
        let names = self.path("names");
        self.store
            .list_with_delimiter(Some(&names))
            .await
            .map_err(|e| self.failed("listing", &names, e))?;
        Ok(())
    }

    /// The store's URL as given.
    pub fn url(&self) -> &str {
        &self.url
    }

    fn path(&self, rest: &str) -> ObjectPath {
        let mut p = self.prefix.clone();
        for part in rest.split('/') {
            p = p.clone().join(part);
        }
        p
    }

    fn volume_path(&self, sha256: &[u8; 32]) -> ObjectPath {
        self.path(&format!("volumes/{}.wspx", hex(sha256)))
    }

    /// Where a name's record is (see the module's layout).
    fn name_path(&self, name: &str) -> ObjectPath {
        name_segments(name)
            .into_iter()
            .fold(self.path("names"), |p, segment| p.join(segment))
    }

    /// Where earlier releases kept the record of a name too long for one segment now: one
    /// segment of its whole hex. `None` for a name keyed by that segment still.
    fn legacy_name_path(&self, name: &str) -> Option<ObjectPath> {
        let digits = hex(name.as_bytes());
        (digits.len() > SINGLE_SEGMENT_HEX).then(|| self.path("names").join(digits))
    }

    /// The error of a failed request to the store: a missing object as [`CacheError::NotFound`],
    /// a failure that may pass when the request is repeated as [`CacheError::Bucket`], any other
    /// (a key the backend cannot hold, no permission, a request it does not take) as
    /// [`CacheError::BucketRefused`].
    fn failed(&self, what: &str, path: &ObjectPath, e: object_store::Error) -> CacheError {
        match e {
            object_store::Error::NotFound { .. } => {
                CacheError::NotFound(format!("object {path} in {}", self.url))
            }
            e if transient(&e) => CacheError::Bucket(format!("{what} {path} in {}: {e}", self.url)),
            e => CacheError::BucketRefused(format!("{what} {path} in {}: {e}", self.url)),
        }
    }

    /// Runs `f` to completion from a blocking thread.
    pub fn wait<T>(&self, f: impl std::future::Future<Output = T>) -> T {
        self.runtime.block_on(f)
    }

    /// The content a name points at, read from the bucket (never cached: deletes are seen).
    pub(crate) async fn name_target(&self, name: &str) -> Result<Option<[u8; 32]>, CacheError> {
        Ok(self.find_name(name).await?.map(|(_, sha)| sha))
    }

    /// Where a name's record is and the content it points at, read from the bucket: under the
    /// name's key, else (a long name) under the key earlier releases gave it, which a backend
    /// that cannot hold such a key refuses. `None` where neither is, and for a name no volume
    /// can have (empty or longer than [`MAX_NAME_BYTES`]), whose key is not asked for.
    async fn find_name(&self, name: &str) -> Result<Option<(ObjectPath, [u8; 32])>, CacheError> {
        if name.is_empty() || name.len() > MAX_NAME_BYTES {
            return Ok(None);
        }
        let path = self.name_path(name);
        if let Some(sha) = self.read_name(&path, name).await? {
            return Ok(Some((path, sha)));
        }
        let Some(legacy) = self.legacy_name_path(name) else {
            return Ok(None);
        };
        match self.read_name(&legacy, name).await {
            Ok(found) => Ok(found.map(|sha| (legacy, sha))),
            // A backend that refuses such a key (a file system, SeaweedFS) holds no record
            // under it.
            Err(CacheError::BucketRefused(_)) => Ok(None),
            Err(e) => Err(e),
        }
    }

    /// The content that the record of `name` at `path` points at; `None` where there is none.
    async fn read_name(
        &self,
        path: &ObjectPath,
        name: &str,
    ) -> Result<Option<[u8; 32]>, CacheError> {
        match self.store.get(path).await {
            Ok(r) => {
                let bytes = r
                    .bytes()
                    .await
                    .map_err(|e| self.failed("reading", path, e))?;
                Ok(Some(parse_name_record(&bytes, name)?))
            }
            Err(object_store::Error::NotFound { .. }) => Ok(None),
            Err(e) => Err(self.failed("reading", path, e)),
        }
    }

    /// Deletes a name's record, under its key and (a long name) under the key earlier releases
    /// gave it; a record already gone is no error.
    async fn delete_name(&self, name: &str) -> Result<(), CacheError> {
        let legacy = self.legacy_name_path(name);
        for path in std::iter::once(self.name_path(name)).chain(legacy.clone()) {
            match self.store.delete(&path).await {
                Ok(()) | Err(object_store::Error::NotFound { .. }) => {}
                Err(e) => match self.failed("deleting", &path, e) {
                    // A key the backend cannot hold holds no record.
                    CacheError::BucketRefused(_) if Some(&path) == legacy.as_ref() => {}
                    e => return Err(e),
                },
            }
        }
        Ok(())
    }

    fn remember(&self, sha256: &[u8; 32]) {
        if let Ok(mut ids) = self.ids.lock() {
            ids.insert(content_id(sha256), *sha256);
        }
    }

    /// The content hash of the volume with this id, if stored: one HEAD request when this node
    /// has seen the id, else a listing of the volumes.
    pub async fn content_of_id(&self, id: u64) -> Result<Option<[u8; 32]>, CacheError> {
        let known = self.ids.lock().ok().and_then(|ids| ids.get(&id).copied());
        if let Some(sha) = known {
            return Ok(self.has_content(&sha).await?.then_some(sha));
        }
        let dir = self.path("volumes");
        // Every hash of this id starts with these hex digits (the id is the first 63 bits).
        let lead = hex(&(id << 1).to_be_bytes());
        let lead = &lead[..15];
        let listed = self.list_under(&dir).await?;
        for o in listed {
            let Some(file) = o.location.filename() else {
                continue;
            };
            let Some(stem) = file.strip_suffix(".wspx") else {
                continue;
            };
            if !stem.starts_with(lead) {
                continue;
            }
            if let Some(sha) = unhex(stem).and_then(|v| <[u8; 32]>::try_from(v).ok()) {
                if content_id(&sha) == id {
                    self.remember(&sha);
                    return Ok(Some(sha));
                }
            }
        }
        Ok(None)
    }

    /// Every object under `dir`.
    async fn list_under(
        &self,
        dir: &ObjectPath,
    ) -> Result<Vec<object_store::ObjectMeta>, CacheError> {
        self.store
            .list(Some(dir))
            .try_collect()
            .await
            .map_err(|e| self.failed("listing", dir, e))
    }

    /// Every name with the content it points at, ordered by name, each read back from its key.
    async fn all_names(&self) -> Result<Vec<(String, [u8; 32])>, CacheError> {
        let dir = self.path("names");
        let listed = self.list_under(&dir).await?;
        let dir = &dir;
        let mut out: Vec<(String, bool, [u8; 32])> = futures_util::stream::iter(listed)
            .map(|o| async move {
                let Some((name, current)) = o.location.prefix_match(dir).and_then(|parts| {
                    let segments: Vec<String> = parts.map(|p| p.as_ref().to_string()).collect();
                    name_of_key(&segments)
                }) else {
                    tracing::warn!(object = %o.location, "an object under names/ that is not a name");
                    return Ok(None);
                };
                let key = o.location.to_string();
                if let Some((etag, sha)) = self.names.lock().ok().and_then(|m| m.get(&key).cloned())
                {
                    if etag.is_some() && etag == o.e_tag {
                        return Ok(Some((name, current, sha)));
                    }
                }
                match self.read_name(&o.location, &name).await? {
                    Some(sha) => {
                        self.remember(&sha);
                        if let Ok(mut m) = self.names.lock() {
                            m.insert(key, (o.e_tag.clone(), sha));
                        }
                        Ok(Some((name, current, sha)))
                    }
                    // Deleted since the listing.
                    None => Ok(None),
                }
            })
            .buffer_unordered(LIST_CONCURRENCY)
            .try_filter_map(|x| async move { Ok::<_, CacheError>(x) })
            .try_collect()
            .await?;
        // A name under both its key and the one of earlier releases counts once, with the
        // record a lookup finds first (its key's).
        out.sort_by(|a, b| a.0.cmp(&b.0).then(b.1.cmp(&a.1)));
        out.dedup_by(|later, first| later.0 == first.0);
        Ok(out.into_iter().map(|(name, _, sha)| (name, sha)).collect())
    }

    /// Resolves a key to its content hash.
    pub async fn locate(&self, key: &VolumeKey) -> Result<[u8; 32], CacheError> {
        let found = match key {
            VolumeKey::Name(n) => self.name_target(n).await?,
            VolumeKey::Id(id) => self.content_of_id(*id).await?,
        };
        if let Some(sha) = &found {
            self.remember(sha);
        }
        found.ok_or_else(|| CacheError::NotFound(key.to_string()))
    }

    /// Whether this content is stored.
    pub async fn has_content(&self, sha256: &[u8; 32]) -> Result<bool, CacheError> {
        let path = self.volume_path(sha256);
        match self.store.head(&path).await {
            Ok(_) => Ok(true),
            Err(object_store::Error::NotFound { .. }) => Ok(false),
            Err(e) => Err(self.failed("checking", &path, e)),
        }
    }

    /// Opens a volume: its head from the node's cache or the bucket (one or two ranged reads).
    pub async fn open_volume(&self, sha256: &[u8; 32]) -> Result<Arc<BucketVolume>, CacheError> {
        if let Some(v) = self
            .heads
            .lock()
            .ok()
            .and_then(|mut h| h.get(sha256).cloned())
        {
            return Ok(v);
        }
        let path = self.volume_path(sha256);
        let first = self
            .store
            .get_opts(
                &path,
                object_store::GetOptions {
                    range: Some(object_store::GetRange::Bounded(0..HEAD_READ_BYTES)),
                    ..Default::default()
                },
            )
            .await
            .map_err(|e| self.failed("reading", &path, e))?;
        let created_unix_ms = first.meta.last_modified.timestamp_millis().max(0) as u64;
        let object_bytes = first.meta.size;
        let mut bytes = first
            .bytes()
            .await
            .map_err(|e| self.failed("reading", &path, e))?
            .to_vec();
        let corrupt = |e: &dyn std::fmt::Display| {
            CacheError::Corrupt(format!("the head of {path} in {}: {e}", self.url))
        };
        let v = loop {
            match read_indexed_head(&bytes).map_err(|e| corrupt(&e))? {
                HeadRead::Indexed(h) => break BucketVolume::whole(*sha256, *h, created_unix_ms),
                HeadRead::Bricked(h) => {
                    break BucketVolume::bricked(*sha256, *h, created_unix_ms)
                        .map_err(|e| corrupt(&e))?
                }
                HeadRead::Series(h) => {
                    break BucketVolume::series(*sha256, *h, created_unix_ms)
                        .map_err(|e| corrupt(&e))?
                }
                HeadRead::Need(n) if (n as u64) > object_bytes || n <= bytes.len() => {
                    return Err(CacheError::Corrupt(format!(
                        "{path} in {} ends inside its head ({object_bytes} bytes)",
                        self.url
                    )))
                }
                HeadRead::Need(n) => {
                    let more = self
                        .store
                        .get_range(&path, bytes.len() as u64..n as u64)
                        .await
                        .map_err(|e| self.failed("reading", &path, e))?;
                    bytes.extend_from_slice(&more);
                }
            }
        };
        if v.object_bytes() != object_bytes {
            return Err(CacheError::Corrupt(format!(
                "{path} in {} holds {object_bytes} bytes, its head describes {}",
                self.url,
                v.object_bytes()
            )));
        }
        let v = Arc::new(v);
        if let Ok(mut h) = self.heads.lock() {
            h.put(*sha256, v.clone());
        }
        Ok(v)
    }

    /// Every name of a content, ordered.
    async fn names_of(&self, sha256: &[u8; 32]) -> Result<Vec<String>, CacheError> {
        Ok(self
            .all_names()
            .await?
            .into_iter()
            .filter(|(_, s)| s == sha256)
            .map(|(n, _)| n)
            .collect())
    }

    /// The record of an opened volume for streaming: its facts without its list of names (which
    /// would cost a listing of all names per stream).
    pub fn stream_meta(&self, v: &BucketVolume) -> VolumeMeta {
        meta_of(v, Vec::new())
    }

    /// The record of a volume seen through `key` (with every name it has).
    pub async fn describe(&self, key: &VolumeKey) -> Result<VolumeMeta, CacheError> {
        let sha = self.locate(key).await?;
        let names = self.names_of(&sha).await?;
        if names.is_empty() {
            return Err(CacheError::NotFound(key.to_string()));
        }
        let v = self.open_volume(&sha).await?;
        let mut meta = meta_of(&v, names);
        if let VolumeKey::Name(n) = key {
            meta = meta.named(n);
        }
        Ok(meta)
    }

    /// Every volume under each of its names, ordered by name.
    pub async fn list(&self) -> Result<Vec<VolumeMeta>, CacheError> {
        let names = self.all_names().await?;
        let mut by_content: HashMap<[u8; 32], Vec<String>> = HashMap::new();
        for (n, sha) in &names {
            by_content.entry(*sha).or_default().push(n.clone());
        }
        let mut out = Vec::with_capacity(names.len());
        for (n, sha) in &names {
            let v = match self.open_volume(sha).await {
                Ok(v) => v,
                // A name whose content was deleted meanwhile (or never finished): not listed.
                Err(CacheError::NotFound(_)) => continue,
                Err(e) => return Err(e),
            };
            out.push(meta_of(&v, by_content[sha].clone()).named(n));
        }
        Ok(out)
    }

    /// Deletes a name (the volume goes with its last name) or, by id, the volume with all its
    /// names; returns the id.
    pub async fn delete(&self, key: &VolumeKey) -> Result<u64, CacheError> {
        let sha = self.locate(key).await?;
        let remove = match key {
            VolumeKey::Name(n) => vec![n.clone()],
            VolumeKey::Id(_) => self.names_of(&sha).await?,
        };
        for n in &remove {
            self.delete_name(n).await?;
        }
        let gone = self.names_of(&sha).await?.is_empty();
        if gone {
            let path = self.volume_path(&sha);
            match self.store.delete(&path).await {
                Ok(()) | Err(object_store::Error::NotFound { .. }) => {}
                Err(e) => return Err(self.failed("deleting", &path, e)),
            }
            if let Ok(mut h) = self.heads.lock() {
                h.pop(&sha);
            }
        }
        tracing::info!(id = content_id(&sha), ?remove, volume_removed = gone, bucket = %self.url, "deleted");
        Ok(content_id(&sha))
    }

    /// Stores a validated upload: the volume object (once per content, `If-None-Match: *`), then
    /// the name (the same way). Returns whether the content was there already. A name that
    /// points at other content is refused. If the content was deleted by another node between
    /// the two writes, it is written again, so a name never points at nothing.
    pub async fn commit(
        &self,
        name: &str,
        sha256: &[u8; 32],
        object: Option<PutPayload>,
    ) -> Result<bool, CacheError> {
        let found = self.find_name(name).await?;
        if let Some((_, existing)) = &found {
            if existing != sha256 {
                return Err(CacheError::NameTaken(name.to_string()));
            }
        }
        let mut existed = true;
        if let Some(object) = &object {
            existed = !self.put_volume(sha256, object.clone()).await?;
        } else if !self.has_content(sha256).await? {
            return Err(CacheError::Conflict(
                "the identical content was deleted during the upload; upload it again".into(),
            ));
        }
        let path = match found {
            // A long name that an earlier release keyed by one segment keeps that record.
            Some((legacy, _)) if Some(&legacy) == self.legacy_name_path(name).as_ref() => legacy,
            _ => {
                let path = self.name_path(name);
                if !self.create(&path, Bytes::from(name_record(sha256))).await?
                    && self.name_target(name).await? != Some(*sha256)
                {
                    return Err(CacheError::NameTaken(name.to_string()));
                }
                path
            }
        };
        if !self.has_content(sha256).await? {
            match &object {
                Some(object) => {
                    self.put_volume(sha256, object.clone()).await?;
                }
                None => {
                    let _ = self.store.delete(&path).await;
                    return Err(CacheError::Conflict(
                        "the identical content was deleted during the upload; upload it again"
                            .into(),
                    ));
                }
            }
        }
        Ok(existed)
    }

    /// Writes a volume object unless it exists; true if this call wrote it.
    async fn put_volume(&self, sha256: &[u8; 32], object: PutPayload) -> Result<bool, CacheError> {
        self.create(&self.volume_path(sha256), object).await
    }

    /// Writes an object with `If-None-Match: *`; true if this call wrote it, false if it
    /// existed.
    async fn create(
        &self,
        path: &ObjectPath,
        data: impl Into<PutPayload>,
    ) -> Result<bool, CacheError> {
        match self
            .store
            .put_opts(path, data.into(), PutOptions::from(PutMode::Create))
            .await
        {
            Ok(_) => Ok(true),
            Err(object_store::Error::AlreadyExists { .. }) => Ok(false),
            Err(e) => Err(self.failed("writing", path, e)),
        }
    }

    /// Packet `packet` of a volume object (its index `packets`, the `.wsp` at `wsp_offset`),
    /// through the node's packet cache. A miss on a volume whose packets together take at most
    /// [`WHOLE_READ_BYTES`] and a quarter of the cache reads all its packets in one request (a
    /// cold node would otherwise make a request per packet); otherwise just this packet's range.
    pub async fn read(
        &self,
        sha256: &[u8; 32],
        id: u64,
        packet: u32,
        packets: &[PacketMeta],
        wsp_offset: u64,
    ) -> Result<Bytes, CacheError> {
        let cached = |c: &mut PacketCache| c.get((id, packet));
        if let Some(b) = self.packets.lock().ok().and_then(|mut c| cached(&mut c)) {
            return Ok(b);
        }
        let p = packets
            .get(packet as usize)
            .ok_or_else(|| CacheError::NotFound(format!("packet {packet} of volume {id}")))?;
        // `packets` holds `p`, so it has a first and a last packet.
        let last = &packets[packets.len() - 1];
        let all = packets[0].offset..last.offset + last.len as u64;
        let limit = self.packets.lock().map(|c| c.limit).unwrap_or(0);
        let whole = all.end - all.start <= WHOLE_READ_BYTES.min(limit / 4);
        let range = if whole {
            wsp_offset + all.start..wsp_offset + all.end
        } else {
            wsp_offset + p.offset..wsp_offset + p.offset + p.len as u64
        };
        let data = self.read_range(sha256, range.clone()).await?;
        if !whole {
            if let Ok(mut c) = self.packets.lock() {
                c.put((id, packet), data.clone());
            }
            return Ok(data);
        }
        let slice = |m: &PacketMeta| {
            let start = (m.offset - all.start) as usize;
            data.slice(start..start + m.len as usize)
        };
        if let Ok(mut c) = self.packets.lock() {
            for (i, m) in packets.iter().enumerate() {
                c.put((id, i as u32), slice(m));
            }
        }
        Ok(slice(p))
    }

    /// Bytes `range` of a volume object, checked to be all of them.
    async fn read_range(&self, sha256: &[u8; 32], range: Range<u64>) -> Result<Bytes, CacheError> {
        let path = self.volume_path(sha256);
        let want = range.end - range.start;
        let data = self
            .store
            .get_range(&path, range)
            .await
            .map_err(|e| self.failed("reading", &path, e))?;
        if data.len() as u64 != want {
            return Err(CacheError::Corrupt(format!(
                "{path} in {}: a range of {want} bytes came back with {}",
                self.url,
                data.len()
            )));
        }
        Ok(data)
    }

    /// Bytes of all volume objects.
    pub async fn data_bytes(&self) -> Result<u64, CacheError> {
        let dir = self.path("volumes");
        let listed = self.list_under(&dir).await?;
        Ok(listed.iter().map(|o| o.size).sum())
    }
}

/// The record of an opened volume under `names`.
fn meta_of(v: &BucketVolume, names: Vec<String>) -> VolumeMeta {
    let h = &v.index;
    let mut meta = VolumeMeta::from_header(
        content_id(&v.sha256),
        names,
        v.sha256,
        v.created_unix_ms,
        v.wsp_bytes,
        &h.header,
        h.header_bytes.len(),
        &h.packets,
    );
    if let Some(b) = &h.bricked {
        meta.describe_bricks(h.header_bytes.len(), &b.bricks, b.manifest.kept());
    }
    if let Some(s) = &h.series {
        meta.describe_bricks(h.header_bytes.len(), &s.bricks, s.manifest.kept());
    }
    meta
}

/// The segments of a name's key under `names/` (see the module's layout).
fn name_segments(name: &str) -> Vec<String> {
    let digits = hex(name.as_bytes());
    if digits.len() <= SINGLE_SEGMENT_HEX {
        return vec![digits];
    }
    // Hex digits are ASCII: every split falls between characters.
    let mut segments: Vec<String> = (0..digits.len())
        .step_by(SEGMENT_HEX)
        .map(|i| {
            let mut s = digits[i..(i + SEGMENT_HEX).min(digits.len())].to_string();
            s.push(SEGMENT_CONTINUES);
            s
        })
        .collect();
    if let Some(last) = segments.last_mut() {
        last.pop();
    }
    segments
}

/// The name that a key's segments under `names/` hold, and whether they are its key (else the
/// single segment earlier releases gave a long name); `None` for segments that are neither.
fn name_of_key(segments: &[String]) -> Option<(String, bool)> {
    let digits: String = segments
        .iter()
        .map(|s| s.strip_suffix(SEGMENT_CONTINUES).unwrap_or(s))
        .collect();
    let name = String::from_utf8(unhex(&digits)?).ok()?;
    if name_segments(&name) == segments {
        Some((name, true))
    } else if segments.len() == 1 && segments[0] == hex(name.as_bytes()) {
        Some((name, false))
    } else {
        None
    }
}

fn name_record(sha256: &[u8; 32]) -> Vec<u8> {
    let mut out = Vec::with_capacity(37);
    out.extend_from_slice(NAME_MAGIC);
    out.push(1);
    out.extend_from_slice(sha256);
    out
}

fn parse_name_record(bytes: &[u8], name: &str) -> Result<[u8; 32], CacheError> {
    match bytes {
        [m0, m1, m2, m3, 1, sha @ ..] if [*m0, *m1, *m2, *m3] == *NAME_MAGIC && sha.len() == 32 => {
            let mut out = [0u8; 32];
            out.copy_from_slice(sha);
            Ok(out)
        }
        _ => Err(CacheError::Corrupt(format!(
            "the record of name {name:?} ({} bytes) is not a name record",
            bytes.len()
        ))),
    }
}

/// Whether a failed request to the store may succeed when repeated: the store did not answer,
/// timed out or dropped the connection, or answered with a server error (5xx), a timeout (408)
/// or too many requests (429). A client error status (a key too long, a bad request), a file
/// system's refusal (a file name too long, a file where a directory should be, no space, no
/// permission) and a request the backend does not take are not. A failure this cannot place
/// counts as one that may pass.
fn transient(e: &object_store::Error) -> bool {
    if !matches!(e, object_store::Error::Generic { .. }) {
        return false;
    }
    let mut cause: Option<&(dyn std::error::Error + 'static)> = Some(e);
    while let Some(c) = cause {
        if c.is::<object_store::client::HttpError>() {
            return true;
        }
        if let Some(status) = http_status(c) {
            return !(400..500).contains(&status) || status == 408 || status == 429;
        }
        if let Some(io) = c.downcast_ref::<std::io::Error>() {
            use std::io::ErrorKind as K;
            return matches!(
                io.kind(),
                K::TimedOut
                    | K::Interrupted
                    | K::WouldBlock
                    | K::ConnectionRefused
                    | K::ConnectionReset
                    | K::ConnectionAborted
                    | K::NotConnected
                    | K::BrokenPipe
                    | K::UnexpectedEof
                    | K::ResourceBusy
                    | K::StaleNetworkFileHandle
            );
        }
        cause = c.source();
    }
    true
}

/// The status of the HTTP response that `cause` reports, as `object_store` words it (its
/// request error type, which holds the code, is not public).
fn http_status(cause: &dyn std::error::Error) -> Option<u16> {
    let text = cause.to_string();
    let rest = text.strip_prefix("Server returned non-2xx status code: ")?;
    rest.get(..3)?.parse().ok()
}

/// The object store and prefix a URL names.
fn object_store_for(url: &str) -> Result<(Arc<dyn ObjectStore>, ObjectPath), CacheError> {
    let parsed = url::Url::parse(url)
        .map_err(|e| CacheError::InvalidRequest(format!("store URL {url:?}: {e}")))?;
    let bad = |e: object_store::Error| CacheError::Bucket(format!("store {url}: {e}"));
    match parsed.scheme() {
        "s3" | "s3a" => {
            use object_store::aws::AmazonS3ConfigKey;
            use object_store::ClientConfigKey;
            // A store that stops answering surfaces within seconds as `Unavailable` to the
            // client (which resumes, on this node or another) rather than after the library's
            // default of minutes of retries.
            let store = object_store::aws::AmazonS3Builder::from_env()
                .with_url(url)
                // As configuration keys: `with_client_options` would drop what the `AWS_*`
                // variables set (AWS_ALLOW_HTTP among them).
                .with_config(
                    AmazonS3ConfigKey::Client(ClientConfigKey::Timeout),
                    format!("{}s", REQUEST_TIMEOUT.as_secs()),
                )
                .with_config(
                    AmazonS3ConfigKey::Client(ClientConfigKey::ConnectTimeout),
                    format!("{}s", CONNECT_TIMEOUT.as_secs()),
                )
                .with_retry(object_store::RetryConfig {
                    max_retries: 2,
                    retry_timeout: RETRY_TIMEOUT,
                    ..Default::default()
                })
                .build()
                .map_err(bad)?;
            let prefix = ObjectPath::parse(parsed.path().trim_matches('/')).map_err(|e| {
                CacheError::InvalidRequest(format!("store URL {url:?}: prefix: {e}"))
            })?;
            Ok((Arc::new(store), prefix))
        }
        "file" => {
            let dir = parsed.to_file_path().map_err(|()| {
                CacheError::InvalidRequest(format!("store URL {url:?}: not a local path"))
            })?;
            std::fs::create_dir_all(&dir).map_err(|e| {
                CacheError::Io(format!(
                    "creating the store directory {}: {e}",
                    dir.display()
                ))
            })?;
            // Directories left empty by a delete go with it (a long name's key is a path of
            // directories of its own).
            let store = object_store::local::LocalFileSystem::new_with_prefix(&dir)
                .map_err(bad)?
                .with_automatic_cleanup(true);
            Ok((Arc::new(store), ObjectPath::default()))
        }
        other => Err(CacheError::InvalidRequest(format!(
            "store URL {url:?}: scheme {other:?}; use s3://bucket/prefix or file:///path"
        ))),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ids_come_from_the_content_and_names_round_trip() {
        let mut sha = [0u8; 32];
        sha[0] = 0xff;
        assert_eq!(content_id(&sha), 0x7f80_0000_0000_0000);
        assert!(content_id(&[0xff; 32]) < u64::MAX);
        assert_eq!(parse_name_record(&name_record(&sha), "n").unwrap(), sha);
        assert!(parse_name_record(b"WSPN\x02", "n").is_err());
        assert_eq!(unhex(&hex(b"a/b c")).unwrap(), b"a/b c");
        assert!(unhex("abc").is_none());
    }

    /// Names of `len` bytes: ASCII and, where the length allows, 2-, 3- and 4-byte UTF-8
    /// characters (with ASCII to make up the length), and a `/` and spaces.
    fn names_of_length(len: usize) -> Vec<String> {
        let mut out = vec!["a".repeat(len)];
        for c in ['é', '水', '🌊'] {
            let n = len / c.len_utf8();
            if n > 0 {
                out.push(format!(
                    "{}{}",
                    c.to_string().repeat(n),
                    "x".repeat(len % c.len_utf8())
                ));
            }
        }
        if len >= 3 {
            out.push(format!("a/ {}", "b".repeat(len - 3)));
        }
        for n in &out {
            assert_eq!(n.len(), len, "{n}");
        }
        out
    }

    /// The layout of name keys, pinned: what earlier releases wrote stays, long names split.
    #[test]
    fn short_names_keep_their_key_and_long_ones_are_split() {
        // The keys every release wrote: one segment of lowercase hex, up to 126 bytes.
        assert_eq!(name_segments("a"), vec!["61".to_string()]);
        assert_eq!(name_segments("a/b c"), vec![hex(b"a/b c")]);
        assert_eq!(name_segments(&"z".repeat(126)), vec!["7a".repeat(126)]);
        // Longer: segments of 200 digits, each but the last marked.
        assert_eq!(
            name_segments(&"z".repeat(127)),
            vec![format!("{}-", "7a".repeat(100)), "7a".repeat(27)]
        );
        assert_eq!(
            name_segments(&"z".repeat(255)),
            vec![
                format!("{}-", "7a".repeat(100)),
                format!("{}-", "7a".repeat(100)),
                "7a".repeat(55)
            ]
        );
        for len in 1..=MAX_NAME_BYTES {
            for name in names_of_length(len) {
                let segments = name_segments(&name);
                // With the local store's `#N` staging suffix, within a file name's 255 bytes.
                assert!(segments.iter().all(|s| s.len() + 3 <= 255), "{name}");
                assert_eq!(name_of_key(&segments), Some((name.clone(), true)));
                let whole = vec![hex(name.as_bytes())];
                assert_eq!(name_of_key(&whole), Some((name.clone(), len <= 126)));
            }
        }
        // Keys that no name has: a segment marked last, a long name's segments unmarked, a
        // short name split, a segment of odd length, uppercase, bytes that are not UTF-8.
        let long = name_segments(&"z".repeat(200));
        let unmarked: Vec<String> = long.iter().map(|s| s.replace('-', "")).collect();
        for bad in [
            vec!["61-".to_string()],
            unmarked,
            vec!["61-".to_string(), "62".to_string()],
            vec!["6".to_string()],
            vec!["6A".to_string()],
            vec!["ff".to_string()],
            vec![],
        ] {
            assert_eq!(name_of_key(&bad), None, "{bad:?}");
        }
    }

    /// Which store failures are `Unavailable` (a retry may mend them) and which are refusals.
    #[tokio::test]
    async fn failures_that_a_retry_may_mend_are_told_from_refusals() {
        use object_store::client::{HttpError, HttpErrorKind};
        let generic =
            |source: Box<dyn std::error::Error + Send + Sync>| object_store::Error::Generic {
                store: "test",
                source,
            };
        let io = |kind| Box::new(std::io::Error::new(kind, "test"));
        for (e, retry) in [
            (
                generic(Box::new(HttpError::new(
                    HttpErrorKind::Connect,
                    io(std::io::ErrorKind::Other),
                ))),
                true,
            ),
            (
                generic(Box::new(HttpError::new(
                    HttpErrorKind::Timeout,
                    io(std::io::ErrorKind::Other),
                ))),
                true,
            ),
            (generic(io(std::io::ErrorKind::TimedOut)), true),
            (generic(io(std::io::ErrorKind::ConnectionReset)), true),
            // A cause this cannot place.
            (generic("something else".into()), true),
            (generic(io(std::io::ErrorKind::InvalidFilename)), false),
            (generic(io(std::io::ErrorKind::NotADirectory)), false),
            (generic(io(std::io::ErrorKind::StorageFull)), false),
            (
                object_store::Error::PermissionDenied {
                    path: "p".into(),
                    source: io(std::io::ErrorKind::Other),
                },
                false,
            ),
            (
                object_store::Error::NotImplemented {
                    operation: "o".into(),
                    implementer: "i".into(),
                },
                false,
            ),
        ] {
            assert_eq!(transient(&e), retry, "{e}");
        }

        // A local store's refusal of a file name too long, as the bucket reports it: not
        // `Unavailable`.
        let dir = tempfile::tempdir().unwrap();
        let url = format!("file://{}", dir.path().display());
        let bucket = Bucket::open(&url, 0).unwrap();
        let path = bucket.path(&"7a".repeat(200));
        let e = bucket.store.get(&path).await.unwrap_err();
        assert!(!transient(&e), "{e}");
        let e = bucket.failed("reading", &path, e);
        assert!(matches!(e, CacheError::BucketRefused(_)), "{e}");
        assert_eq!(tonic::Status::from(e).code(), tonic::Code::Internal);
        let e = CacheError::Bucket("down".into());
        assert_eq!(tonic::Status::from(e).code(), tonic::Code::Unavailable);
    }

    /// An S3 endpoint that answers every request with `status` and an S3 error body.
    async fn answering(status: &'static str) -> String {
        use tokio::io::{AsyncReadExt, AsyncWriteExt};
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let url = format!("http://{}", listener.local_addr().unwrap());
        tokio::spawn(async move {
            while let Ok((mut conn, _)) = listener.accept().await {
                tokio::spawn(async move {
                    let mut request = Vec::new();
                    let mut buf = [0u8; 4096];
                    while !request.windows(4).any(|w| w == b"\r\n\r\n") {
                        match conn.read(&mut buf).await {
                            Ok(0) | Err(_) => return,
                            Ok(n) => request.extend_from_slice(&buf[..n]),
                        }
                    }
                    let body = "<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n\
                        <Error><Code>KeyTooLongError</Code><Message>test</Message></Error>";
                    let response = format!(
                        "HTTP/1.1 {status}\r\ncontent-type: application/xml\r\n\
                         content-length: {}\r\nconnection: close\r\n\r\n{body}",
                        body.len()
                    );
                    let _ = conn.write_all(response.as_bytes()).await;
                });
            }
        });
        url
    }

    /// How an S3 client's failures are placed, from real responses: a client error (a key too
    /// long) is a refusal, a server error, a throttled request or no answer may pass.
    #[tokio::test]
    async fn s3_statuses_are_placed_by_their_code() {
        let s3 = |endpoint: &str| {
            object_store::aws::AmazonS3Builder::new()
                .with_endpoint(endpoint)
                .with_allow_http(true)
                .with_region("us-east-1")
                .with_bucket_name("archive")
                .with_access_key_id("id")
                .with_secret_access_key("secret")
                .with_retry(object_store::RetryConfig {
                    max_retries: 0,
                    retry_timeout: std::time::Duration::from_secs(1),
                    ..Default::default()
                })
                .build()
                .unwrap()
        };
        let path = ObjectPath::from("names/61");
        for (status, retry) in [
            ("400 Bad Request", false),
            ("405 Method Not Allowed", false),
            ("429 Too Many Requests", true),
            ("500 Internal Server Error", true),
            ("503 Service Unavailable", true),
        ] {
            let store = s3(&answering(status).await);
            let e = store.get(&path).await.unwrap_err();
            assert!(
                matches!(e, object_store::Error::Generic { .. }),
                "{status}: {e}"
            );
            assert_eq!(transient(&e), retry, "{status}: {e}");
            let e = store
                .put(&path, PutPayload::from_static(b"x"))
                .await
                .unwrap_err();
            assert_eq!(transient(&e), retry, "{status}: {e}");
        }
        // Nothing listening.
        let closed = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let url = format!("http://{}", closed.local_addr().unwrap());
        drop(closed);
        let e = s3(&url).get(&path).await.unwrap_err();
        assert!(transient(&e), "{e}");
    }

    /// A small volume's `.wsp` bytes.
    fn small_volume() -> Vec<u8> {
        use wavesplat_compressor::encode::{compress, CompressOptions, Target, TileChoice};
        let vol = wavesplat_compressor::phantom::Phantom::SheppLogan.generate([16, 16, 16]);
        let options = CompressOptions {
            target: Target::Fraction(0.1),
            tile: TileChoice::Size(8),
            levels: Some(2),
            ..Default::default()
        };
        compress(&vol, &options, &|_, _| {}).unwrap().bytes
    }

    /// A bucket as an earlier release left it on S3 (which takes a segment of any length up to
    /// its 1024-byte keys): long names' records under one segment of their whole hex. Read,
    /// listed once, described, kept when ingested again and deleted; names added beside them
    /// are keyed in segments.
    #[tokio::test]
    async fn long_names_an_earlier_release_keyed_by_one_segment_are_read() {
        let store: Arc<dyn ObjectStore> = Arc::new(object_store::memory::InMemory::new());
        let prefix = ObjectPath::from("archive");
        let bucket = || {
            Bucket::over(
                store.clone(),
                prefix.clone(),
                "memory://archive",
                tokio::runtime::Handle::current(),
                1 << 20,
            )
        };
        let wsp = small_volume();
        let sha = wavesplat_net::digest::sha256(&wsp);
        let object = wavesplat_codec::format::index::indexed_layout(&wsp).unwrap();
        let old_key = |name: &str| format!("archive/names/{}", hex(name.as_bytes()));
        let old: Vec<String> = [1, 126, 127, 200, 255]
            .into_iter()
            .flat_map(names_of_length)
            .collect();
        store
            .put(
                &ObjectPath::from(format!("archive/volumes/{}.wspx", hex(&sha))),
                object.into(),
            )
            .await
            .unwrap();
        for name in &old {
            let key = ObjectPath::from(old_key(name));
            store.put(&key, name_record(&sha).into()).await.unwrap();
        }

        let b = bucket();
        let listed = b.list().await.unwrap();
        let mut want = old.clone();
        want.sort();
        let names: Vec<String> = listed.iter().map(|m| m.name.clone()).collect();
        assert_eq!(names, want);
        assert!(listed.iter().all(|m| m.names == want));
        for name in &old {
            let key = VolumeKey::Name(name.clone());
            assert_eq!(b.locate(&key).await.unwrap(), sha, "{name}");
            assert_eq!(b.describe(&key).await.unwrap().name, *name);
        }

        // Ingested again under an old name: the record stays where it is, alone.
        let long = &old[old.len() - 1];
        assert!(b.commit(long, &sha, None).await.unwrap());
        // Other content may not take it.
        assert!(matches!(
            b.commit(long, &[7; 32], Some(PutPayload::from_static(b"x")))
                .await,
            Err(CacheError::NameTaken(_))
        ));
        // A new long name is keyed in segments; both kinds are listed.
        let new = "n".repeat(255);
        assert!(b.commit(&new, &sha, None).await.unwrap());
        let keys: Vec<String> = store
            .list(Some(&ObjectPath::from("archive/names")))
            .map_ok(|o| o.location.to_string())
            .try_collect()
            .await
            .unwrap();
        assert_eq!(keys.len(), old.len() + 1, "{keys:?}");
        assert!(keys.contains(&old_key(long)), "{keys:?}");
        let segments = name_segments(&new).join("/");
        assert!(
            keys.contains(&format!("archive/names/{segments}")),
            "{keys:?}"
        );
        // A name under both keys (a node of each release naming it at once) counts once.
        store
            .put(&ObjectPath::from(old_key(&new)), name_record(&sha).into())
            .await
            .unwrap();
        assert_eq!(bucket().list().await.unwrap().len(), old.len() + 1);

        // Deleted under either key; the volume goes with the last name.
        b.delete(&VolumeKey::Name(new.clone())).await.unwrap();
        assert!(b.name_target(&new).await.unwrap().is_none());
        for name in &old[1..] {
            b.delete(&VolumeKey::Name(name.clone())).await.unwrap();
            assert!(b.name_target(name).await.unwrap().is_none(), "{name}");
        }
        assert!(b.has_content(&sha).await.unwrap());
        b.delete(&VolumeKey::Name(old[0].clone())).await.unwrap();
        assert!(!b.has_content(&sha).await.unwrap());
        let left: Vec<object_store::ObjectMeta> = store.list(None).try_collect().await.unwrap();
        assert!(left.is_empty(), "{left:?}");
    }

    #[test]
    fn packet_cache_stays_within_its_bytes() {
        let mut c = PacketCache {
            entries: lru::LruCache::unbounded(),
            bytes: 0,
            limit: 10,
        };
        c.put((0, 0), Bytes::from(vec![0u8; 4]));
        c.put((0, 1), Bytes::from(vec![0u8; 4]));
        assert!(c.get((0, 0)).is_some());
        c.put((0, 2), Bytes::from(vec![0u8; 4]));
        assert!(c.bytes <= 10);
        assert!(c.get((0, 1)).is_none(), "least recently used goes first");
        assert!(c.get((0, 0)).is_some() && c.get((0, 2)).is_some());
        c.put((0, 3), Bytes::from(vec![0u8; 11]));
        assert!(c.get((0, 3)).is_none(), "larger than the cache: not kept");
    }
}
