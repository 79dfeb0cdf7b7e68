//! The store: metadata in sled, each volume's bytes in a file of its own.
//!
//! sled trees: `volumes` (id → [`VolumeMeta`], the commit record, with every name of the
//! volume), `names` (name → id), `hashes` (SHA-256 → id), `headers` (id → header section) and
//! `packet_index` (id → packet index with offsets). The packets live in `volumes/ID.wsp`, the
//! uploaded file as is: deleting a volume deletes its file, so its space is free at once (sled
//! reclaims its own, small, records lazily), and a refinement stream that opened the file keeps
//! reading it after a deletion.
//!
//! An upload ([`Upload`]) streams to `volumes/ID.part` and is validated as it arrives (the
//! header and directory as soon as they are complete, every packet as soon as its bytes are):
//! junk is refused after its first bytes and at most the prelude or one packet is held in
//! memory. At the end the file is synced and renamed, its header and index written, then the
//! `volumes`/`names`/`hashes` entries are committed in one transaction and flushed. A crash
//! before the commit leaves only unreferenced data, which [`Store::open`] deletes, so a half
//! volume is never visible. Identical content (same SHA-256) is stored once: ingesting it
//! under a new name adds the name, under a name it already has returns it unchanged, so
//! concurrent or repeated identical ingests all succeed. Deletion commits the removal of the
//! records first, then drops the data.
//!
//! Its parts: `validate` (the limits, names and the checks an upload's bytes pass), `upload`
//! (a volume streamed to disk and validated as it arrives), `volume` (an opened volume: parsed
//! header, index and file, read by ranges); this module holds the store's records.

mod upload;
mod validate;
mod volume;

use crate::bucket::Bucket;
use crate::error::CacheError;
use crate::model::{
    decode_bricks, decode_packets, decode_series, encode_packets, VolumeIndex, VolumeKey,
    VolumeMeta,
};
use sled::transaction::{ConflictableTransactionError, TransactionError, Transactional};
use std::collections::HashMap;
use std::fs::File;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::{SystemTime, UNIX_EPOCH};
pub use upload::Upload;
pub use validate::{index_file, validate_name, Limits, MAX_NAME_BYTES};
pub use volume::OpenVolume;
use volume::VolumeData;
use wavesplat_codec::format::bricked::is_bricked;
use wavesplat_codec::format::read_header_section;
use wavesplat_codec::format::series::is_series;
use wavesplat_codec::view::bricked::whole_header;
pub use wavesplat_net::digest::sha256;

/// Volumes whose index and open file are kept in memory.
const OPEN_VOLUMES: usize = 256;

/// The outcome of an ingest.
#[derive(Debug, Clone, PartialEq)]
pub struct Ingested {
    /// The stored volume (named as the ingest named it).
    pub volume: VolumeMeta,
    /// True if identical content was already stored (nothing written; the name was added to
    /// it if new).
    pub existed: bool,
}

/// Handle to the store; cheap to clone.
#[derive(Clone, Debug)]
pub struct Store {
    db: sled::Db,
    volumes: sled::Tree,
    names: sled::Tree,
    hashes: sled::Tree,
    headers: sled::Tree,
    index: sled::Tree,
    /// A bricked volume's bricks (their headers and packet counts); its `headers` entry is the
    /// container's manifest section.
    bricks: sled::Tree,
    files: Arc<PathBuf>,
    limits: Limits,
    open: Arc<Mutex<HashMap<u64, Arc<OpenVolume>>>>,
    /// The object store volumes live in, when not in this node's files (sled then holds
    /// nothing; `files` holds uploads in progress).
    bucket: Option<Arc<Bucket>>,
}

fn id_from(bytes: &[u8]) -> Result<u64, CacheError> {
    let b: [u8; 8] = bytes
        .get(..8)
        .and_then(|s| s.try_into().ok())
        .ok_or_else(|| CacheError::Corrupt(format!("id of {} bytes", bytes.len())))?;
    Ok(u64::from_be_bytes(b))
}

fn io(what: &str, e: std::io::Error) -> CacheError {
    CacheError::Io(format!("{what}: {e}"))
}

fn now_ms() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_millis() as u64)
        .unwrap_or(0)
}

/// How a commit ended.
enum Committed {
    /// A new volume.
    New,
    /// The content was stored already (under `id`); the name was added or already its own.
    Existing(u64),
}

impl Store {
    /// Opens (or creates) the store at `path` and removes data left by interrupted ingests or
    /// deletions.
    pub fn open(path: impl AsRef<Path>, limits: Limits) -> Result<Store, CacheError> {
        let path = path.as_ref();
        let db = sled::Config::new().path(path).open()?;
        let files = path.join("volumes");
        std::fs::create_dir_all(&files).map_err(|e| io("creating the volume directory", e))?;
        let limits = Limits {
            max_buffered_bytes: limits
                .max_buffered_bytes
                .max(limits.max_packet_bytes)
                .max(limits.max_prelude_bytes),
            max_concurrent_uploads: limits.max_concurrent_uploads.max(1),
            ..limits
        };
        let store = Store {
            volumes: db.open_tree("volumes")?,
            names: db.open_tree("names")?,
            hashes: db.open_tree("hashes")?,
            headers: db.open_tree("headers")?,
            index: db.open_tree("packet_index")?,
            bricks: db.open_tree("bricks")?,
            db,
            files: Arc::new(files),
            limits,
            open: Arc::new(Mutex::new(HashMap::new())),
            bucket: None,
        };
        store.migrate_sled_packets()?;
        let removed = store.collect_garbage()?;
        if removed > 0 {
            tracing::warn!(removed, "removed data of interrupted ingests or deletions");
        }
        Ok(store)
    }

    /// Opens a node over the object store at `url` (see [`crate::bucket`]): volumes and names
    /// live there, shared by every node over the same store; `path` holds only this node's
    /// uploads in progress. `read_cache_bytes` bounds the node's memory cache of packets. Must be
    /// called within a tokio runtime; checks that the store answers.
    pub async fn open_bucket(
        path: impl AsRef<Path>,
        url: &str,
        limits: Limits,
        read_cache_bytes: u64,
    ) -> Result<Store, CacheError> {
        let bucket = Bucket::open(url, read_cache_bytes)?;
        bucket.probe().await?;
        let path = path.as_ref().to_path_buf();
        tokio::task::spawn_blocking(move || {
            let mut store = Store::open(&path, limits)?;
            store.bucket = Some(Arc::new(bucket));
            Ok(store)
        })
        .await
        .map_err(|e| CacheError::Io(format!("opening the node's directory: {e}")))?
    }

    /// The object store's URL, when volumes live in one.
    pub fn bucket_url(&self) -> Option<&str> {
        self.bucket.as_deref().map(Bucket::url)
    }

    /// The upload limits.
    pub fn limits(&self) -> &Limits {
        &self.limits
    }

    fn file_path(&self, id: u64, ext: &str) -> PathBuf {
        self.files.join(format!("{id:016x}.{ext}"))
    }

    /// Stores that kept packets in sled (trees `index` and `packets`) get a data file per
    /// committed volume; the old trees are then dropped.
    fn migrate_sled_packets(&self) -> Result<(), CacheError> {
        let old_index = self.db.open_tree("index")?;
        let old_packets = self.db.open_tree("packets")?;
        if old_index.is_empty() && old_packets.is_empty() {
            return Ok(());
        }
        let mut migrated = 0;
        for kv in self.volumes.iter() {
            let (k, _) = kv?;
            let id = id_from(&k)?;
            if self.index.contains_key(k.as_ref())? {
                continue;
            }
            let missing = || CacheError::Corrupt(format!("volume {id} has a record but no data"));
            let header = self.headers.get(k.as_ref())?.ok_or_else(missing)?;
            let mut packets =
                decode_packets(&old_index.get(k.as_ref())?.ok_or_else(missing)?, false)?;
            let mut bytes = header.to_vec();
            for (i, p) in packets.iter_mut().enumerate() {
                let mut key = [0u8; 12];
                key[..8].copy_from_slice(&k);
                key[8..].copy_from_slice(&(i as u32).to_be_bytes());
                let data = old_packets.get(key)?.ok_or_else(missing)?;
                p.offset = bytes.len() as u64;
                bytes.extend_from_slice(&data);
            }
            let part = self.file_path(id, "part");
            std::fs::write(&part, &bytes).map_err(|e| io("migrating a volume", e))?;
            File::open(&part)
                .and_then(|f| f.sync_all())
                .map_err(|e| io("migrating a volume", e))?;
            std::fs::rename(&part, self.file_path(id, "wsp"))
                .map_err(|e| io("migrating a volume", e))?;
            self.index.insert(k, encode_packets(&packets))?;
            migrated += 1;
        }
        self.db.flush()?;
        old_index.clear()?;
        old_packets.clear()?;
        self.db.flush()?;
        tracing::info!(migrated, "moved packets from sled into volume files");
        Ok(())
    }

    /// Deletes headers, indexes and files of ids without a commit record, and unfinished
    /// uploads; returns the number of entries removed. Only safe while no ingest is in flight
    /// (called at open).
    fn collect_garbage(&self) -> Result<usize, CacheError> {
        let mut removed = 0;
        for tree in [&self.headers, &self.index, &self.bricks] {
            let mut dead = Vec::new();
            for kv in tree.iter() {
                let (k, _) = kv?;
                if !self.volumes.contains_key(k.as_ref())? {
                    dead.push(k);
                }
            }
            removed += dead.len();
            let mut batch = sled::Batch::default();
            for k in dead {
                batch.remove(k);
            }
            tree.apply_batch(batch)?;
        }
        let entries = std::fs::read_dir(&*self.files).map_err(|e| io("listing volume files", e))?;
        for e in entries {
            let path = e.map_err(|e| io("listing volume files", e))?.path();
            let keep = match (
                path.extension().and_then(|x| x.to_str()),
                path.file_stem()
                    .and_then(|s| s.to_str())
                    .and_then(|s| u64::from_str_radix(s, 16).ok()),
            ) {
                (Some("wsp"), Some(id)) => self.volumes.contains_key(id.to_be_bytes())?,
                _ => false,
            };
            if !keep {
                std::fs::remove_file(&path).map_err(|e| io("removing a stale file", e))?;
                removed += 1;
            }
        }
        self.db.flush()?;
        Ok(removed)
    }

    /// Resolves a key to an id.
    pub fn resolve(&self, key: &VolumeKey) -> Result<u64, CacheError> {
        if let Some(b) = &self.bucket {
            return Ok(crate::bucket::content_id(&b.wait(b.locate(key))?));
        }
        let id = match key {
            VolumeKey::Id(id) => *id,
            VolumeKey::Name(name) => match self.names.get(name.as_bytes())? {
                Some(v) => id_from(&v)?,
                None => return Err(CacheError::NotFound(key.to_string())),
            },
        };
        if self.volumes.contains_key(id.to_be_bytes())? {
            Ok(id)
        } else {
            Err(CacheError::NotFound(key.to_string()))
        }
    }

    /// Whether content with this SHA-256 is stored.
    pub fn has_content(&self, sha256: &[u8; 32]) -> Result<bool, CacheError> {
        if let Some(b) = &self.bucket {
            return b.wait(b.has_content(sha256));
        }
        Ok(self.hashes.contains_key(sha256)?)
    }

    /// Stores a whole `.wsp` file under `name` (see [`Upload`]; `declared_sha256`, if given,
    /// must match the content).
    pub fn ingest(
        &self,
        name: &str,
        bytes: &[u8],
        declared_sha256: Option<[u8; 32]>,
    ) -> Result<Ingested, CacheError> {
        let declared = declared_sha256.unwrap_or_else(|| sha256(bytes));
        let mut upload = Upload::begin(self, name, declared, bytes.len() as u64)?;
        upload.push(bytes)?;
        upload.finish(|| None)
    }

    /// Makes a volume visible, or adds `name` to identical content already stored: one
    /// transaction over volumes, names and hashes. Without `fresh` data, only the latter.
    fn commit(&self, meta: &VolumeMeta, fresh: bool) -> Result<Committed, CacheError> {
        let id = meta.id.to_be_bytes();
        let name = meta.name.as_bytes();
        let r: Result<Committed, TransactionError<CacheError>> =
            (&self.volumes, &self.names, &self.hashes).transaction(|(volumes, names, hashes)| {
                let abort = |e: CacheError| Err(ConflictableTransactionError::Abort(e));
                let named = names.get(name)?;
                if let Some(existing) = hashes.get(meta.sha256)? {
                    match named {
                        Some(n) if n == existing => {}
                        Some(_) => return abort(CacheError::NameTaken(meta.name.clone())),
                        None => {
                            let Some(record) = volumes.get(&existing)? else {
                                return abort(CacheError::Corrupt(
                                    "a content hash without its volume".into(),
                                ));
                            };
                            let mut m = match VolumeMeta::decode(&record) {
                                Ok(m) => m,
                                Err(e) => return abort(e),
                            };
                            m.names.push(meta.name.clone());
                            volumes.insert(&existing, m.encode())?;
                            names.insert(name, &existing)?;
                        }
                    }
                    let existing = match id_from(&existing) {
                        Ok(id) => id,
                        Err(e) => return abort(e),
                    };
                    return Ok(Committed::Existing(existing));
                }
                if !fresh {
                    return abort(CacheError::Conflict(
                        "the identical content was deleted during the upload; upload it again"
                            .into(),
                    ));
                }
                if named.is_some() {
                    return abort(CacheError::NameTaken(meta.name.clone()));
                }
                volumes.insert(&id, meta.encode())?;
                names.insert(name, &id)?;
                hashes.insert(&meta.sha256, &id)?;
                Ok(Committed::New)
            });
        let committed = r?;
        self.db.flush()?;
        if let Committed::Existing(id) = committed {
            self.forget(id);
        }
        Ok(committed)
    }

    /// Removes the header, index and file of `id`.
    fn remove_data(&self, id: u64) -> Result<(), CacheError> {
        self.forget(id);
        self.headers.remove(id.to_be_bytes())?;
        self.index.remove(id.to_be_bytes())?;
        self.bricks.remove(id.to_be_bytes())?;
        for ext in ["wsp", "part"] {
            match std::fs::remove_file(self.file_path(id, ext)) {
                Ok(()) => {}
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
                Err(e) => return Err(io("removing a volume file", e)),
            }
        }
        Ok(())
    }

    fn forget(&self, id: u64) {
        if let Ok(mut open) = self.open.lock() {
            open.remove(&id);
        }
    }

    /// One volume's record.
    pub fn meta(&self, id: u64) -> Result<VolumeMeta, CacheError> {
        if let Some(b) = &self.bucket {
            return b.wait(b.describe(&VolumeKey::Id(id)));
        }
        match self.volumes.get(id.to_be_bytes())? {
            Some(v) => VolumeMeta::decode(&v),
            None => Err(CacheError::NotFound(VolumeKey::Id(id).to_string())),
        }
    }

    /// Describes a volume (named as `key` names it).
    pub fn describe(&self, key: &VolumeKey) -> Result<VolumeMeta, CacheError> {
        if let Some(b) = &self.bucket {
            return b.wait(b.describe(key));
        }
        let meta = self.meta(self.resolve(key)?)?;
        Ok(match key {
            VolumeKey::Name(n) => meta.named(n),
            VolumeKey::Id(_) => meta,
        })
    }

    /// Every volume under each of its names, ordered by name.
    pub fn list(&self) -> Result<Vec<VolumeMeta>, CacheError> {
        if let Some(b) = &self.bucket {
            return b.wait(b.list());
        }
        let mut out = Vec::new();
        let mut metas: HashMap<u64, VolumeMeta> = HashMap::new();
        for kv in self.names.iter() {
            let (name, id) = kv?;
            let id = id_from(&id)?;
            let meta = match metas.get(&id) {
                Some(m) => m.clone(),
                None => {
                    let m = self.meta(id)?;
                    metas.insert(id, m.clone());
                    m
                }
            };
            out.push(meta.named(&String::from_utf8_lossy(&name)));
        }
        Ok(out)
    }

    /// Deletes a name (the volume goes with its last name) or, by id, the volume with all its
    /// names; returns the volume's id.
    pub fn delete(&self, key: &VolumeKey) -> Result<u64, CacheError> {
        if let Some(b) = &self.bucket {
            let id = b.wait(b.delete(key))?;
            self.forget(id);
            return Ok(id);
        }
        let meta = self.describe(key)?;
        let id = meta.id.to_be_bytes();
        let remove: Vec<String> = match key {
            VolumeKey::Name(n) => vec![n.clone()],
            VolumeKey::Id(_) => meta.names.clone(),
        };
        let r: Result<bool, TransactionError<CacheError>> =
            (&self.volumes, &self.names, &self.hashes).transaction(|(volumes, names, hashes)| {
                let Some(record) = volumes.get(id)? else {
                    return Err(ConflictableTransactionError::Abort(CacheError::NotFound(
                        key.to_string(),
                    )));
                };
                let mut m =
                    VolumeMeta::decode(&record).map_err(ConflictableTransactionError::Abort)?;
                for n in &remove {
                    if names.get(n.as_bytes())?.as_deref() == Some(&id[..]) {
                        names.remove(n.as_bytes())?;
                    }
                }
                m.names.retain(|n| !remove.contains(n));
                if m.names.is_empty() {
                    volumes.remove(&id)?;
                    hashes.remove(&m.sha256)?;
                    Ok(true)
                } else {
                    volumes.insert(&id, m.encode())?;
                    Ok(false)
                }
            });
        let gone = r?;
        self.db.flush()?;
        self.forget(meta.id);
        if gone {
            self.remove_data(meta.id)?;
            self.db.flush()?;
        }
        tracing::info!(id = meta.id, ?remove, volume_removed = gone, "deleted");
        Ok(meta.id)
    }

    /// A volume's header and packet index.
    pub fn index(&self, id: u64) -> Result<VolumeIndex, CacheError> {
        Ok(self.open_volume(id)?.index.clone())
    }

    /// Opens a volume for reading (cached: the header is parsed and the index decoded once per
    /// volume, not per request).
    pub fn open_volume(&self, id: u64) -> Result<Arc<OpenVolume>, CacheError> {
        if let Some(b) = &self.bucket {
            // Whether the volume still exists is the bucket's to say (another node may have
            // deleted it): one HEAD request; the parsed head is cached by content.
            let sha = b
                .wait(b.content_of_id(id))?
                .ok_or_else(|| CacheError::NotFound(VolumeKey::Id(id).to_string()))?;
            if let Some(v) = self.open.lock().ok().and_then(|o| o.get(&id).cloned()) {
                return Ok(v);
            }
            let v = b.wait(b.open_volume(&sha))?;
            let opened = Arc::new(OpenVolume {
                meta: b.stream_meta(&v),
                index: v.index.clone(),
                data: VolumeData::Bucket {
                    bucket: b.clone(),
                    sha256: v.sha256,
                    wsp_offset: v.wsp_offset,
                },
            });
            self.keep_open(id, &opened);
            return Ok(opened);
        }
        if let Some(v) = self.open.lock().ok().and_then(|o| o.get(&id).cloned()) {
            return Ok(v);
        }
        let meta = self.meta(id)?;
        let key = id.to_be_bytes();
        let missing = || CacheError::Corrupt(format!("volume {id} has a record but no data"));
        let header_bytes = self.headers.get(key)?.ok_or_else(missing)?.to_vec();
        let (header, bricked, series) = if is_bricked(&header_bytes) {
            let stored = self.bricks.get(key)?.ok_or_else(missing)?;
            let b = decode_bricks(&header_bytes, meta.file_bytes, &stored)?;
            let first = &b.bricks[0].header;
            (whole_header(&b.manifest, first), Some(Box::new(b)), None)
        } else if is_series(&header_bytes) {
            let stored = self.bricks.get(key)?.ok_or_else(missing)?;
            let s = decode_series(&header_bytes, meta.file_bytes, &stored)?;
            let header = s
                .whole_header()
                .map_err(|e| CacheError::Corrupt(format!("stored series {id}: {e}")))?;
            (header, None, Some(Box::new(s)))
        } else {
            let (header, _) = read_header_section(&header_bytes)
                .map_err(|e| CacheError::Corrupt(format!("stored header of volume {id}: {e}")))?;
            (header, None, None)
        };
        let packets = decode_packets(&self.index.get(key)?.ok_or_else(missing)?, true)?;
        let bricks = bricked
            .as_ref()
            .map(|b| &b.bricks)
            .or(series.as_ref().map(|s| &s.bricks));
        if let Some(bricks) = bricks {
            let counted: u64 = bricks.iter().map(|k| u64::from(k.packets)).sum();
            if counted != packets.len() as u64 {
                return Err(CacheError::Corrupt(format!(
                    "volume {id}: its bricks have {counted} packets, its index {}",
                    packets.len()
                )));
            }
        }
        let file = match File::open(self.file_path(id, "wsp")) {
            Ok(f) => f,
            // Deleted meanwhile.
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                return Err(CacheError::NotFound(VolumeKey::Id(id).to_string()))
            }
            Err(e) => return Err(io("opening a volume file", e)),
        };
        let v = Arc::new(OpenVolume {
            meta,
            index: VolumeIndex {
                header,
                header_bytes,
                packets,
                bricked,
                series,
            },
            data: VolumeData::File(file),
        });
        // Only while still committed (a deletion may have raced this open).
        if self.volumes.contains_key(key)? {
            self.keep_open(id, &v);
        }
        Ok(v)
    }

    /// Keeps an opened volume for the next request (at most [`OPEN_VOLUMES`]).
    fn keep_open(&self, id: u64, v: &Arc<OpenVolume>) {
        if let Ok(mut open) = self.open.lock() {
            if open.len() >= OPEN_VOLUMES {
                if let Some(k) = open.keys().next().copied() {
                    open.remove(&k);
                }
            }
            open.insert(id, v.clone());
        }
    }

    /// One packet's bytes.
    pub fn packet(&self, id: u64, packet: u32) -> Result<Vec<u8>, CacheError> {
        self.open_volume(id)?.packet(packet)
    }

    /// Bytes of volume data on disk (finished and unfinished files), for tests and reports.
    pub fn data_bytes(&self) -> Result<u64, CacheError> {
        if let Some(b) = &self.bucket {
            return b.wait(b.data_bytes());
        }
        let mut total = 0;
        for e in std::fs::read_dir(&*self.files).map_err(|e| io("listing volume files", e))? {
            let meta = e
                .and_then(|e| e.metadata())
                .map_err(|e| io("listing volume files", e))?;
            total += meta.len();
        }
        Ok(total)
    }

    /// Flushes everything to disk.
    pub fn flush(&self) -> Result<(), CacheError> {
        self.db.flush()?;
        Ok(())
    }
}

/// Flushes the store when the last server handle goes away.
#[derive(Debug)]
pub struct FlushGuard(pub Store);

impl Drop for FlushGuard {
    fn drop(&mut self) {
        if let Err(e) = self.0.flush() {
            tracing::error!(error = %e, "flushing the store on shutdown failed");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::upload::blank_meta;
    use super::*;
    use wavesplat_codec::format::parse_file;

    fn test_file() -> Vec<u8> {
        use wavesplat_compressor::encode::{compress, CompressOptions, Target, TileChoice};
        let vol = wavesplat_compressor::phantom::Phantom::SheppLogan.generate([24, 24, 24]);
        compress(
            &vol,
            &CompressOptions {
                target: Target::Fraction(0.05),
                tile: TileChoice::Size(16),
                layers: Some(3),
                levels: Some(2),
                ..Default::default()
            },
            &|_, _| {},
        )
        .unwrap()
        .bytes
    }

    #[test]
    fn crash_before_commit_leaves_nothing_visible() {
        let dir = tempfile::tempdir().unwrap();
        let bytes = test_file();
        {
            let store = Store::open(dir.path(), Limits::default()).unwrap();
            // Interrupted ingests: one still uploading, one stored but not committed.
            std::fs::write(store.file_path(98, "part"), &bytes[..100]).unwrap();
            let index = index_file(&bytes, &Limits::default()).unwrap();
            std::fs::write(store.file_path(99, "wsp"), &bytes).unwrap();
            store
                .headers
                .insert(99u64.to_be_bytes(), index.header_bytes)
                .unwrap();
            store
                .index
                .insert(99u64.to_be_bytes(), encode_packets(&index.packets))
                .unwrap();
            store.flush().unwrap();
            assert!(store.data_bytes().unwrap() > bytes.len() as u64);
        }
        let store = Store::open(dir.path(), Limits::default()).unwrap();
        assert!(store.list().unwrap().is_empty());
        assert_eq!(store.data_bytes().unwrap(), 0);
        assert!(store.headers.is_empty() && store.index.is_empty());
        let a = store.ingest("a", &bytes, None).unwrap();
        assert!(!a.existed);
        let b = store.ingest("b", &bytes, Some(sha256(&bytes))).unwrap();
        assert!(b.existed);
        assert_eq!(b.volume.id, a.volume.id);
        assert_eq!(b.volume.names, vec!["a".to_string(), "b".to_string()]);
        assert!(store.ingest("c", &bytes, Some([0; 32])).is_err());
        assert!(matches!(
            store.ingest("a", &bytes[..bytes.len() - 1], None),
            Err(CacheError::NameTaken(_))
        ));
        assert!(store.ingest("d", &bytes[..bytes.len() - 1], None).is_err());
        assert_eq!(store.list().unwrap().len(), 2);
        store.delete(&VolumeKey::Id(a.volume.id)).unwrap();
        assert!(store.list().unwrap().is_empty());
        assert_eq!(store.data_bytes().unwrap(), 0);
    }

    #[test]
    fn stores_that_kept_packets_in_sled_are_migrated() {
        let dir = tempfile::tempdir().unwrap();
        let bytes = test_file();
        let index = index_file(&bytes, &Limits::default()).unwrap();
        let file = parse_file(&bytes).unwrap();
        {
            // The previous layout: packets in a `packets` tree, the index without offsets.
            let db = sled::open(dir.path()).unwrap();
            let id = 5u64.to_be_bytes();
            let mut meta = blank_meta("old", sha256(&bytes));
            meta.id = 5;
            meta.packet_count = file.packets.len() as u32;
            db.open_tree("volumes")
                .unwrap()
                .insert(id, meta.encode())
                .unwrap();
            db.open_tree("names").unwrap().insert("old", &id).unwrap();
            db.open_tree("hashes")
                .unwrap()
                .insert(meta.sha256, &id)
                .unwrap();
            db.open_tree("headers")
                .unwrap()
                .insert(id, index.header_bytes.clone())
                .unwrap();
            let mut w = wavesplat_codec::format::bytes::ByteWriter::new();
            w.varint(index.packets.len() as u64);
            for p in &index.packets {
                for v in [p.tile as u64, p.layer as u64, p.len as u64] {
                    w.varint(v);
                }
                w.varint(p.summary.len() as u64);
                for (band, e) in &p.summary {
                    w.u8(band.level);
                    w.u8(band.kind);
                    w.f64(*e);
                }
            }
            db.open_tree("index")
                .unwrap()
                .insert(id, w.into_bytes())
                .unwrap();
            let packets = db.open_tree("packets").unwrap();
            for (i, p) in file.packets.iter().enumerate() {
                let mut k = [0u8; 12];
                k[..8].copy_from_slice(&id);
                k[8..].copy_from_slice(&(i as u32).to_be_bytes());
                packets.insert(k, *p).unwrap();
            }
            db.flush().unwrap();
        }
        let store = Store::open(dir.path(), Limits::default()).unwrap();
        let v = store
            .open_volume(store.resolve(&VolumeKey::Name("old".into())).unwrap())
            .unwrap();
        for (i, p) in file.packets.iter().enumerate() {
            assert_eq!(v.packet(i as u32).unwrap(), *p);
        }
        assert!(store.db.open_tree("packets").unwrap().is_empty());
    }
}
