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
//! - `names/<hex of the name>`: one small object per name holding the content hash, written
//!   with `If-None-Match: *`, so two nodes that ingest the same volume at once store it once and
//!   the same name cannot point at two contents.
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
        let bucket = Bucket {
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
        };
        Ok(bucket)
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

    fn name_path(&self, name: &str) -> ObjectPath {
        self.path(&format!("names/{}", hex(name.as_bytes())))
    }

    fn failed(&self, what: &str, path: &ObjectPath, e: object_store::Error) -> CacheError {
        match e {
            object_store::Error::NotFound { .. } => {
                CacheError::NotFound(format!("object {path} in {}", self.url))
            }
            e => CacheError::Bucket(format!("{what} {path} in {}: {e}", self.url)),
        }
    }

    /// Runs `f` to completion from a blocking thread.
    pub fn wait<T>(&self, f: impl std::future::Future<Output = T>) -> T {
        self.runtime.block_on(f)
    }

    /// The content a name points at, read from the bucket (never cached: deletes are seen).
    pub(crate) async fn name_target(&self, name: &str) -> Result<Option<[u8; 32]>, CacheError> {
        let path = self.name_path(name);
        match self.store.get(&path).await {
            Ok(r) => {
                let bytes = r
                    .bytes()
                    .await
                    .map_err(|e| self.failed("reading", &path, e))?;
                Ok(Some(parse_name_record(&bytes, name)?))
            }
            Err(object_store::Error::NotFound { .. }) => Ok(None),
            Err(e) => Err(self.failed("reading", &path, e)),
        }
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

    /// Every name with the content it points at, ordered by name.
    async fn all_names(&self) -> Result<Vec<(String, [u8; 32])>, CacheError> {
        let dir = self.path("names");
        let listed = self.list_under(&dir).await?;
        let mut out: Vec<(String, [u8; 32])> = futures_util::stream::iter(listed)
            .map(|o| async move {
                let Some(name) = o
                    .location
                    .filename()
                    .and_then(unhex)
                    .and_then(|b| String::from_utf8(b).ok())
                else {
                    tracing::warn!(object = %o.location, "an object under names/ that is not a name");
                    return Ok(None);
                };
                let key = o.location.to_string();
                if let Some((etag, sha)) = self.names.lock().ok().and_then(|m| m.get(&key).cloned())
                {
                    if etag.is_some() && etag == o.e_tag {
                        return Ok(Some((name, sha)));
                    }
                }
                match self.name_target(&name).await? {
                    Some(sha) => {
                        self.remember(&sha);
                        if let Ok(mut m) = self.names.lock() {
                            m.insert(key, (o.e_tag.clone(), sha));
                        }
                        Ok(Some((name, sha)))
                    }
                    // Deleted since the listing.
                    None => Ok(None),
                }
            })
            .buffer_unordered(LIST_CONCURRENCY)
            .try_filter_map(|x| async move { Ok::<_, CacheError>(x) })
            .try_collect()
            .await?;
        out.sort();
        Ok(out)
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
            let path = self.name_path(n);
            match self.store.delete(&path).await {
                Ok(()) | Err(object_store::Error::NotFound { .. }) => {}
                Err(e) => return Err(self.failed("deleting", &path, e)),
            }
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
        if let Some(existing) = self.name_target(name).await? {
            if existing != *sha256 {
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
        let path = self.name_path(name);
        if !self.create(&path, Bytes::from(name_record(sha256))).await?
            && self.name_target(name).await? != Some(*sha256)
        {
            return Err(CacheError::NameTaken(name.to_string()));
        }
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
            let store = object_store::local::LocalFileSystem::new_with_prefix(&dir).map_err(bad)?;
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
