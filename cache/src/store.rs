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

use crate::bucket::Bucket;
use crate::error::CacheError;
use crate::model::{
    decode_packets, encode_packets, PacketMeta, VolumeIndex, VolumeKey, VolumeMeta,
};
use sha2::{Digest, Sha256};
use sled::transaction::{ConflictableTransactionError, TransactionError, Transactional};
use std::collections::HashMap;
use std::fs::File;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::{SystemTime, UNIX_EPOCH};
use wavesplat_codec::format::packet::{decode_packet_within, DecodeBudget};
use wavesplat_codec::format::{parse_file, parse_prelude, read_header_section, Prelude};

/// Limits applied to uploads.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Limits {
    /// Largest accepted upload (bytes).
    pub max_upload_bytes: u64,
    /// Largest accepted packet (bytes); bounds every streamed message.
    pub max_packet_bytes: u64,
    /// Largest header section plus packet directory (bytes).
    pub max_prelude_bytes: u64,
    /// Uploads validated at once; more wait their turn.
    pub max_concurrent_uploads: usize,
    /// Bytes all uploads together may hold in memory (the prelude, then the largest packet,
    /// of each); an upload waits until its share is free. At least `max_packet_bytes` and
    /// `max_prelude_bytes`.
    pub max_buffered_bytes: u64,
    /// What validating one packet may cost (checked against its declared count first).
    pub decode: DecodeBudget,
}

impl Default for Limits {
    fn default() -> Self {
        Limits {
            max_upload_bytes: 1 << 30,
            max_packet_bytes: 16 << 20,
            max_prelude_bytes: 16 << 20,
            max_concurrent_uploads: 16,
            max_buffered_bytes: 256 << 20,
            decode: DecodeBudget {
                max_coefficients: 1 << 24,
                max_bytes: 1 << 30,
            },
        }
    }
}

/// Longest volume name (bytes).
pub const MAX_NAME_BYTES: usize = 255;
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

/// A stored volume opened for reading: its record, header and index, and its data file.
#[derive(Debug)]
pub struct OpenVolume {
    /// The record.
    pub meta: VolumeMeta,
    /// Header and packet index.
    pub index: VolumeIndex,
    data: VolumeData,
}

/// Where an open volume's packets are read from.
#[derive(Debug)]
enum VolumeData {
    /// The node's own file.
    File(File),
    /// An object in a bucket (`wsp_offset`: where the `.wsp` starts in it).
    Bucket {
        bucket: Arc<Bucket>,
        sha256: [u8; 32],
        wsp_offset: u64,
    },
}

impl OpenVolume {
    fn entry(&self, packet: u32) -> Result<&PacketMeta, CacheError> {
        self.index.packets.get(packet as usize).ok_or_else(|| {
            CacheError::NotFound(format!("packet {packet} of volume {}", self.meta.id))
        })
    }

    /// One packet's bytes, from a blocking thread.
    pub fn packet(&self, packet: u32) -> Result<Vec<u8>, CacheError> {
        match &self.data {
            VolumeData::File(file) => self.read_file(file, packet),
            VolumeData::Bucket { bucket, .. } => {
                Ok(bucket.wait(self.read_packet(packet))?.to_vec())
            }
        }
    }

    fn read_file(&self, file: &File, packet: u32) -> Result<Vec<u8>, CacheError> {
        let p = self.entry(packet)?;
        let mut buf = vec![0u8; p.len as usize];
        read_at(file, &mut buf, p.offset).map_err(|e| {
            CacheError::Corrupt(format!(
                "reading packet {packet} of volume {}: {e}",
                self.meta.id
            ))
        })?;
        Ok(buf)
    }

    /// One packet's bytes, from an async task (a local file is read in place: one positioned
    /// read of a packet).
    pub async fn read_packet(&self, packet: u32) -> Result<bytes::Bytes, CacheError> {
        match &self.data {
            VolumeData::File(file) => Ok(self.read_file(file, packet)?.into()),
            VolumeData::Bucket {
                bucket,
                sha256,
                wsp_offset,
            } => {
                bucket
                    .read(
                        sha256,
                        self.meta.id,
                        packet,
                        &self.index.packets,
                        *wsp_offset,
                    )
                    .await
            }
        }
    }
}

#[cfg(unix)]
fn read_at(file: &File, buf: &mut [u8], offset: u64) -> std::io::Result<()> {
    std::os::unix::fs::FileExt::read_exact_at(file, buf, offset)
}

#[cfg(windows)]
fn read_at(file: &File, mut buf: &mut [u8], mut offset: u64) -> std::io::Result<()> {
    use std::os::windows::fs::FileExt;
    while !buf.is_empty() {
        match file.seek_read(buf, offset)? {
            0 => return Err(std::io::ErrorKind::UnexpectedEof.into()),
            n => {
                buf = &mut buf[n..];
                offset += n as u64;
            }
        }
    }
    Ok(())
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

/// Checks a volume name: 1..=255 bytes, no control characters.
pub fn validate_name(name: &str) -> Result<(), CacheError> {
    if name.is_empty() || name.len() > MAX_NAME_BYTES || name.chars().any(char::is_control) {
        return Err(CacheError::InvalidRequest(format!(
            "volume name {name:?} must be 1..={MAX_NAME_BYTES} bytes without control characters"
        )));
    }
    Ok(())
}

/// SHA-256 of some bytes.
pub fn sha256(bytes: &[u8]) -> [u8; 32] {
    Sha256::digest(bytes).into()
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

/// Decodes packet `i` and returns its index entry and the number of coefficients it holds.
fn index_packet(
    prelude: &Prelude,
    i: usize,
    bytes: &[u8],
    offset: u64,
    budget: &DecodeBudget,
) -> Result<(PacketMeta, u64), CacheError> {
    let d = decode_packet_within(&prelude.header, bytes, budget)
        .map_err(|e| CacheError::InvalidUpload(format!("packet {i}: {e}")))?;
    let held = d.coefficients.len() as u64;
    Ok((
        PacketMeta {
            tile: d.tile as u32,
            layer: d.layer as u32,
            len: bytes.len() as u32,
            offset,
            summary: d.summary,
        },
        held,
    ))
}

/// Refuses a file whose packets do not hold the coefficients its header declares.
fn check_kept(prelude: &Prelude, held: u64) -> Result<(), CacheError> {
    wavesplat_codec::format::check_kept(&prelude.header, held)
        .map_err(|e| CacheError::InvalidUpload(e.to_string()))
}

/// Validates a whole file: parses it, decodes every packet, and builds its index.
pub fn index_file(bytes: &[u8], limits: &Limits) -> Result<VolumeIndex, CacheError> {
    let file = parse_file(bytes)?;
    let prelude = Prelude {
        header: file.header.clone(),
        header_bytes: file.header_bytes,
        directory_bytes: file.directory_bytes,
        packet_lengths: file.packets.iter().map(|p| p.len()).collect(),
    };
    let mut packets = Vec::with_capacity(file.packets.len());
    let mut offset = prelude.len() as u64;
    let mut held = 0u64;
    for (i, p) in file.packets.iter().enumerate() {
        check_packet_size(p.len(), limits)?;
        let (meta, n) = index_packet(&prelude, i, p, offset, &limits.decode)?;
        packets.push(meta);
        held += n;
        offset += p.len() as u64;
    }
    check_kept(&prelude, held)?;
    Ok(VolumeIndex {
        header_bytes: bytes[..file.header_bytes].to_vec(),
        header: file.header,
        packets,
    })
}

fn check_packet_size(len: usize, limits: &Limits) -> Result<(), CacheError> {
    if len as u64 > limits.max_packet_bytes {
        return Err(CacheError::TooLarge {
            what: "packet",
            size: len as u64,
            limit: limits.max_packet_bytes,
        });
    }
    Ok(())
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
        for tree in [&self.headers, &self.index] {
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
                index: VolumeIndex {
                    header: v.head.header.clone(),
                    header_bytes: v.head.header_bytes.clone(),
                    packets: v.head.packets.clone(),
                },
                data: VolumeData::Bucket {
                    bucket: b.clone(),
                    sha256: v.sha256,
                    wsp_offset: v.head.wsp_offset,
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
        let (header, _) = read_header_section(&header_bytes)
            .map_err(|e| CacheError::Corrupt(format!("stored header of volume {id}: {e}")))?;
        let packets = decode_packets(&self.index.get(key)?.ok_or_else(missing)?, true)?;
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

/// An upload in progress: bytes are hashed, written to a file and validated as they arrive.
/// Dropping it before [`Upload::finish`] removes what it wrote.
#[derive(Debug)]
pub struct Upload {
    store: Store,
    name: String,
    declared: [u8; 32],
    total: u64,
    received: u64,
    hasher: Sha256,
    /// `None` when the declared content is already stored: the bytes are only hashed.
    sink: Option<Sink>,
}

#[derive(Debug)]
struct Sink {
    id: u64,
    part: PathBuf,
    file: File,
    prelude_buf: Vec<u8>,
    prelude: Option<Prelude>,
    header_bytes: Vec<u8>,
    packet_buf: Vec<u8>,
    packets: Vec<PacketMeta>,
    /// Coefficients the packets so far hold.
    held: u64,
    offset: u64,
    kept: bool,
}

impl Drop for Sink {
    fn drop(&mut self) {
        if !self.kept {
            let _ = std::fs::remove_file(&self.part);
        }
    }
}

impl Sink {
    /// The prelude of a complete upload whose packets hold what its header declares.
    fn complete(&mut self) -> Result<Prelude, CacheError> {
        let complete = self
            .prelude
            .as_ref()
            .is_some_and(|p| self.packets.len() == p.packet_lengths.len());
        let Some(prelude) = self.prelude.take().filter(|_| complete) else {
            return Err(CacheError::InvalidUpload(
                "the upload ends inside its header, directory or a packet".into(),
            ));
        };
        check_kept(&prelude, self.held)?;
        Ok(prelude)
    }

    /// Validates the next bytes of the file.
    fn feed(&mut self, data: &[u8], total: u64, limits: &Limits) -> Result<(), CacheError> {
        if self.prelude.is_none() {
            self.prelude_buf.extend_from_slice(data);
            let Some(p) = parse_prelude(&self.prelude_buf)? else {
                if self.prelude_buf.len() as u64 > limits.max_prelude_bytes {
                    return Err(CacheError::TooLarge {
                        what: "header and packet directory",
                        size: self.prelude_buf.len() as u64,
                        limit: limits.max_prelude_bytes,
                    });
                }
                return Ok(());
            };
            if p.len() as u64 > limits.max_prelude_bytes {
                return Err(CacheError::TooLarge {
                    what: "header and packet directory",
                    size: p.len() as u64,
                    limit: limits.max_prelude_bytes,
                });
            }
            if p.file_bytes() != total {
                return Err(CacheError::InvalidUpload(format!(
                    "the packet directory describes a file of {} bytes, the upload declares {total}",
                    p.file_bytes()
                )));
            }
            for &len in &p.packet_lengths {
                check_packet_size(len, limits)?;
            }
            let rest = std::mem::take(&mut self.prelude_buf);
            self.header_bytes = rest[..p.header_bytes].to_vec();
            self.packets.reserve_exact(p.packet_lengths.len());
            self.offset = p.len() as u64;
            let used = p.len();
            self.prelude = Some(p);
            return self.feed_packets(&rest[used..], limits);
        }
        self.feed_packets(data, limits)
    }

    fn feed_packets(&mut self, mut data: &[u8], limits: &Limits) -> Result<(), CacheError> {
        while !data.is_empty() {
            let n = self.feed_packets_some(data, limits)?;
            data = &data[n..];
        }
        Ok(())
    }

    /// Takes bytes of the current packet from `data`, checks the packet when complete, and
    /// returns how many bytes it took.
    fn feed_packets_some(&mut self, data: &[u8], limits: &Limits) -> Result<usize, CacheError> {
        let Some(p) = &self.prelude else {
            return Ok(0);
        };
        let i = self.packets.len();
        let Some(&len) = p.packet_lengths.get(i) else {
            return Err(CacheError::InvalidUpload(
                "bytes after the last packet".into(),
            ));
        };
        if self.packet_buf.is_empty() {
            self.packet_buf.reserve_exact(len);
        }
        let take = (len - self.packet_buf.len()).min(data.len());
        self.packet_buf.extend_from_slice(&data[..take]);
        if self.packet_buf.len() == len {
            let (meta, held) = index_packet(p, i, &self.packet_buf, self.offset, &limits.decode)?;
            self.offset += len as u64;
            self.packets.push(meta);
            self.held += held;
            self.packet_buf.clear();
        }
        // Progress: bytes taken, or (a packet of zero bytes) the packet count advanced.
        Ok(take)
    }

    /// The bytes this upload may hold in memory from now on.
    fn memory_need(&self, total: u64, limits: &Limits) -> u64 {
        match &self.prelude {
            None => total.min(limits.max_prelude_bytes),
            Some(p) => p.packet_lengths[self.packets.len()..]
                .iter()
                .copied()
                .max()
                .unwrap_or(0) as u64,
        }
    }
}

impl Upload {
    /// Starts an upload of `total` bytes under `name` whose SHA-256 is declared to be
    /// `declared`.
    pub fn begin(
        store: &Store,
        name: &str,
        declared: [u8; 32],
        total: u64,
    ) -> Result<Upload, CacheError> {
        validate_name(name)?;
        let limit = store.limits.max_upload_bytes;
        if total > limit {
            return Err(CacheError::TooLarge {
                what: "upload",
                size: total,
                limit,
            });
        }
        // A name taken by other content is refused before any byte is read (the commit checks
        // again).
        if let Some(b) = &store.bucket {
            if b.wait(b.name_target(name))?
                .is_some_and(|sha| sha != declared)
            {
                return Err(CacheError::NameTaken(name.to_string()));
            }
        } else if let Some(id) = store.names.get(name.as_bytes())? {
            if store.meta(id_from(&id)?)?.sha256 != declared {
                return Err(CacheError::NameTaken(name.to_string()));
            }
        }
        let sink = if store.has_content(&declared)? {
            None
        } else {
            let id = store.db.generate_id()?;
            let part = store.file_path(id, "part");
            let file = File::create(&part).map_err(|e| io("creating an upload file", e))?;
            Some(Sink {
                id,
                part,
                file,
                prelude_buf: Vec::new(),
                prelude: None,
                header_bytes: Vec::new(),
                packet_buf: Vec::new(),
                packets: Vec::new(),
                held: 0,
                offset: 0,
                kept: false,
            })
        };
        Ok(Upload {
            store: store.clone(),
            name: name.to_string(),
            declared,
            total,
            received: 0,
            hasher: Sha256::new(),
            sink,
        })
    }

    /// The bytes this upload may hold in memory until it ends or its next phase (the prelude,
    /// then the largest packet still to come); 0 when it only hashes.
    pub fn memory_need(&self) -> u64 {
        self.sink
            .as_ref()
            .map_or(0, |s| s.memory_need(self.total, &self.store.limits))
    }

    /// Bytes received so far.
    pub fn received(&self) -> u64 {
        self.received
    }

    /// Takes the next bytes of the file.
    pub fn push(&mut self, chunk: &[u8]) -> Result<(), CacheError> {
        if self.received + chunk.len() as u64 > self.total {
            return Err(CacheError::InvalidUpload(format!(
                "more data than the declared total size of {} bytes",
                self.total
            )));
        }
        self.hasher.update(chunk);
        self.received += chunk.len() as u64;
        if let Some(s) = &mut self.sink {
            s.file
                .write_all(chunk)
                .map_err(|e| io("writing an upload", e))?;
            s.feed(chunk, self.total, &self.store.limits)?;
        }
        Ok(())
    }

    /// Checks the upload is complete and matches its checksum, then stores it. `abandon` is
    /// asked last, before the commit: `Some(error)` (the client gave up or its deadline
    /// passed) rolls the upload back.
    pub fn finish(
        mut self,
        abandon: impl Fn() -> Option<CacheError>,
    ) -> Result<Ingested, CacheError> {
        if self.received != self.total {
            return Err(CacheError::InvalidUpload(format!(
                "truncated upload: received {} of {} bytes",
                self.received, self.total
            )));
        }
        let hash: [u8; 32] = std::mem::take(&mut self.hasher).finalize().into();
        if hash != self.declared {
            return Err(CacheError::InvalidUpload(format!(
                "checksum mismatch: declared SHA-256 {}, received content has {}",
                crate::model::hex(&self.declared),
                crate::model::hex(&hash)
            )));
        }
        let store = self.store.clone();
        if let Some(b) = store.bucket.clone() {
            return self.finish_in_bucket(&b, hash, abandon);
        }
        let meta = match self.sink.take() {
            None => {
                if let Some(e) = abandon() {
                    return Err(e);
                }
                let mut meta = blank_meta(&self.name, hash);
                meta.id = u64::MAX;
                meta
            }
            Some(mut s) => {
                let prelude = s.complete()?;
                s.file.sync_all().map_err(|e| io("syncing an upload", e))?;
                let id = s.id;
                let path = store.file_path(id, "wsp");
                std::fs::rename(&s.part, &path).map_err(|e| io("storing an upload", e))?;
                s.kept = true;
                if let Ok(dir) = File::open(&*store.files) {
                    let _ = dir.sync_all();
                }
                store
                    .headers
                    .insert(id.to_be_bytes(), std::mem::take(&mut s.header_bytes))?;
                store
                    .index
                    .insert(id.to_be_bytes(), encode_packets(&s.packets))?;
                store.db.flush()?;
                if let Some(e) = abandon() {
                    store.remove_data(id)?;
                    return Err(e);
                }
                VolumeMeta::from_header(
                    id,
                    vec![self.name.clone()],
                    hash,
                    now_ms(),
                    self.total,
                    &prelude.header,
                    prelude.header_bytes,
                    &s.packets,
                )
            }
        };
        let fresh = meta.id != u64::MAX;
        match store.commit(&meta, fresh) {
            Ok(Committed::New) => {
                tracing::info!(id = meta.id, name = %meta.name, bytes = self.total, "ingested volume");
                Ok(Ingested {
                    volume: meta,
                    existed: false,
                })
            }
            Ok(Committed::Existing(id)) => {
                if fresh {
                    store.remove_data(meta.id)?;
                }
                Ok(Ingested {
                    volume: store.meta(id)?.named(&self.name),
                    existed: true,
                })
            }
            Err(e) => {
                if fresh {
                    store.remove_data(meta.id)?;
                }
                Err(e)
            }
        }
    }
}

impl Upload {
    /// The end of an upload into a bucket: the validated file in the indexed layout, written once
    /// per content, then the name (see [`Bucket::commit`]).
    fn finish_in_bucket(
        mut self,
        bucket: &Bucket,
        hash: [u8; 32],
        abandon: impl Fn() -> Option<CacheError>,
    ) -> Result<Ingested, CacheError> {
        let object = match self.sink.take() {
            None => None,
            Some(mut s) => {
                s.complete()?;
                let mut object =
                    wavesplat_codec::format::index::indexed_prefix(self.total, &s.packets)?;
                let file = std::fs::read(&s.part).map_err(|e| io("reading an upload back", e))?;
                object.extend_from_slice(&file);
                Some(bytes::Bytes::from(object))
            }
        };
        if let Some(e) = abandon() {
            return Err(e);
        }
        let existed = bucket.wait(bucket.commit(&self.name, &hash, object))?;
        let volume = bucket.wait(bucket.describe(&VolumeKey::Name(self.name.clone())))?;
        tracing::info!(id = volume.id, name = %self.name, bytes = self.total, existed, bucket = %bucket.url(), "ingested volume");
        Ok(Ingested { volume, existed })
    }
}

fn blank_meta(name: &str, sha256: [u8; 32]) -> VolumeMeta {
    VolumeMeta {
        id: 0,
        name: name.to_string(),
        names: vec![name.to_string()],
        sha256,
        created_unix_ms: now_ms(),
        file_bytes: 0,
        header_bytes: 0,
        packet_bytes: 0,
        dims: [0; 3],
        channels: 0,
        family: String::new(),
        levels: 0,
        packet_count: 0,
        tile_count: 0,
        layer_count: 0,
        tile: 0,
        coefficients: 0,
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
    use super::*;

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
