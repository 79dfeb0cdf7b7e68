//! The sled-backed store. Trees: `volumes` (id → [`VolumeMeta`], the commit record), `names`
//! (name → id), `hashes` (SHA-256 → id), `headers` (id → header section), `index` (id → packet
//! index) and `packets` ((id, packet index) big-endian → packet bytes). An ingest first writes
//! the header, index and packets under a fresh id (one batch, flushed), then commits the
//! `volumes`/`names`/`hashes` entries in one transaction and flushes: a crash before the commit
//! leaves only unreferenced data, which [`Store::open`] deletes, so a half volume is never
//! visible. Deletion commits the removal of the records first, then drops the data.

use crate::error::CacheError;
use crate::model::{
    decode_packets, encode_packets, PacketMeta, VolumeIndex, VolumeKey, VolumeMeta,
};
use sha2::{Digest, Sha256};
use sled::transaction::{ConflictableTransactionError, TransactionError, Transactional};
use std::path::Path;
use std::time::{SystemTime, UNIX_EPOCH};
use wavesplat_codec::format::packet::decode_packet;
use wavesplat_codec::format::{parse_file, read_header_section};

/// Limits applied to uploads.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Limits {
    /// Largest accepted upload (bytes).
    pub max_upload_bytes: u64,
    /// Largest accepted packet (bytes); bounds every streamed message.
    pub max_packet_bytes: u64,
}

impl Default for Limits {
    fn default() -> Self {
        Limits {
            max_upload_bytes: 1 << 30,
            max_packet_bytes: 16 << 20,
        }
    }
}

/// Longest volume name (bytes).
pub const MAX_NAME_BYTES: usize = 255;

/// The outcome of an ingest.
#[derive(Debug, Clone, PartialEq)]
pub struct Ingested {
    /// The stored volume.
    pub volume: VolumeMeta,
    /// True if identical content was already stored (nothing written).
    pub existed: bool,
}

/// Handle to the store; cheap to clone (sled handles are reference counted).
#[derive(Clone, Debug)]
pub struct Store {
    db: sled::Db,
    volumes: sled::Tree,
    names: sled::Tree,
    hashes: sled::Tree,
    headers: sled::Tree,
    index: sled::Tree,
    packets: sled::Tree,
    limits: Limits,
}

fn packet_key(id: u64, packet: u32) -> [u8; 12] {
    let mut k = [0u8; 12];
    k[..8].copy_from_slice(&id.to_be_bytes());
    k[8..].copy_from_slice(&packet.to_be_bytes());
    k
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

/// Validates a whole file: parses it, decodes every packet, and builds its index.
pub fn index_file(bytes: &[u8], limits: &Limits) -> Result<VolumeIndex, CacheError> {
    let file = parse_file(bytes)?;
    let mut packets = Vec::with_capacity(file.packets.len());
    for (i, p) in file.packets.iter().enumerate() {
        if p.len() as u64 > limits.max_packet_bytes {
            return Err(CacheError::TooLarge {
                what: "packet",
                size: p.len() as u64,
                limit: limits.max_packet_bytes,
            });
        }
        let d = decode_packet(&file.header, p)
            .map_err(|e| CacheError::InvalidUpload(format!("packet {i}: {e}")))?;
        packets.push(PacketMeta {
            tile: d.tile as u32,
            layer: d.layer as u32,
            len: p.len() as u32,
            summary: d.summary,
        });
    }
    Ok(VolumeIndex {
        header_bytes: bytes[..file.header_bytes].to_vec(),
        header: file.header,
        packets,
    })
}

impl Store {
    /// Opens (or creates) the store at `path` and removes data left by interrupted ingests or
    /// deletions.
    pub fn open(path: impl AsRef<Path>, limits: Limits) -> Result<Store, CacheError> {
        let db = sled::Config::new().path(path).open()?;
        Self::with_db(db, limits)
    }

    fn with_db(db: sled::Db, limits: Limits) -> Result<Store, CacheError> {
        let store = Store {
            volumes: db.open_tree("volumes")?,
            names: db.open_tree("names")?,
            hashes: db.open_tree("hashes")?,
            headers: db.open_tree("headers")?,
            index: db.open_tree("index")?,
            packets: db.open_tree("packets")?,
            db,
            limits,
        };
        let removed = store.collect_garbage()?;
        if removed > 0 {
            tracing::warn!(removed, "removed data of interrupted ingests or deletions");
        }
        Ok(store)
    }

    /// The upload limits.
    pub fn limits(&self) -> &Limits {
        &self.limits
    }

    /// Deletes headers, indexes and packets of ids without a commit record; returns the number
    /// of entries removed. Only safe while no ingest is in flight (called at open).
    fn collect_garbage(&self) -> Result<usize, CacheError> {
        let mut removed = 0;
        for tree in [&self.headers, &self.index, &self.packets] {
            let mut dead = Vec::new();
            for kv in tree.iter() {
                let (k, _) = kv?;
                let id = id_from(&k)?;
                if !self.volumes.contains_key(id.to_be_bytes())? {
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
        self.db.flush()?;
        Ok(removed)
    }

    /// Resolves a key to an id.
    pub fn resolve(&self, key: &VolumeKey) -> Result<u64, CacheError> {
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

    /// Stores a `.wsp` file under `name` after checking it (size limit, `declared_sha256` if
    /// given, parse, every packet decodes). Identical content already stored is returned as is.
    pub fn ingest(
        &self,
        name: &str,
        bytes: &[u8],
        declared_sha256: Option<[u8; 32]>,
    ) -> Result<Ingested, CacheError> {
        validate_name(name)?;
        if bytes.len() as u64 > self.limits.max_upload_bytes {
            return Err(CacheError::TooLarge {
                what: "upload",
                size: bytes.len() as u64,
                limit: self.limits.max_upload_bytes,
            });
        }
        let hash = sha256(bytes);
        if let Some(declared) = declared_sha256 {
            if declared != hash {
                return Err(CacheError::InvalidUpload(format!(
                    "checksum mismatch: declared SHA-256 {}, received content has {}",
                    crate::model::hex(&declared),
                    crate::model::hex(&hash)
                )));
            }
        }
        if let Some(existing) = self.existing(&hash)? {
            return Ok(Ingested {
                volume: existing,
                existed: true,
            });
        }
        if self.names.contains_key(name.as_bytes())? {
            return Err(CacheError::NameTaken(name.to_string()));
        }
        let index = index_file(bytes, &self.limits)?;
        let id = self.db.generate_id()?;
        self.write_data(id, bytes, &index)?;
        let h = &index.header;
        let meta = VolumeMeta {
            id,
            name: name.to_string(),
            sha256: hash,
            created_unix_ms: SystemTime::now()
                .duration_since(UNIX_EPOCH)
                .map(|d| d.as_millis() as u64)
                .unwrap_or(0),
            file_bytes: bytes.len() as u64,
            header_bytes: index.header_bytes.len() as u64,
            packet_bytes: index.packets.iter().map(|p| p.len as u64).sum(),
            dims: h.geometry.dims.map(|d| d as u32),
            channels: h.channels as u32,
            family: h.geometry.family.name().to_string(),
            levels: h.geometry.levels as u32,
            packet_count: index.packets.len() as u32,
            tile_count: h.tile_count() as u32,
            layer_count: h.layer_bounds.len() as u32,
            tile: h.tile as u32,
            coefficients: h.kept,
        };
        match self.commit(&meta) {
            Ok(()) => {
                self.db.flush()?;
                tracing::info!(id, name, bytes = bytes.len(), "ingested volume");
                Ok(Ingested {
                    volume: meta,
                    existed: false,
                })
            }
            Err(e) => {
                // Lost a race (same content or name committed meanwhile): drop our data.
                self.remove_data(id)?;
                match (e, self.existing(&hash)?) {
                    (CacheError::InvalidUpload(_), Some(existing)) => Ok(Ingested {
                        volume: existing,
                        existed: true,
                    }),
                    (e, _) => Err(e),
                }
            }
        }
    }

    fn existing(&self, hash: &[u8; 32]) -> Result<Option<VolumeMeta>, CacheError> {
        match self.hashes.get(hash)? {
            Some(id) => self.meta(id_from(&id)?).map(Some),
            None => Ok(None),
        }
    }

    /// Writes header, index and packets of `id` (not yet visible) and flushes.
    pub(crate) fn write_data(
        &self,
        id: u64,
        bytes: &[u8],
        index: &VolumeIndex,
    ) -> Result<(), CacheError> {
        let file = parse_file(bytes)?;
        let mut batch = sled::Batch::default();
        for (i, p) in file.packets.iter().enumerate() {
            batch.insert(&packet_key(id, i as u32), *p);
        }
        self.packets.apply_batch(batch)?;
        self.headers
            .insert(id.to_be_bytes(), index.header_bytes.as_slice())?;
        self.index
            .insert(id.to_be_bytes(), encode_packets(&index.packets))?;
        self.db.flush()?;
        Ok(())
    }

    /// Makes `meta` visible: one transaction over volumes, names and hashes.
    pub(crate) fn commit(&self, meta: &VolumeMeta) -> Result<(), CacheError> {
        let record = meta.encode();
        let id = meta.id.to_be_bytes();
        let r: Result<(), TransactionError<CacheError>> =
            (&self.volumes, &self.names, &self.hashes).transaction(|(volumes, names, hashes)| {
                if names.get(meta.name.as_bytes())?.is_some() {
                    return Err(ConflictableTransactionError::Abort(CacheError::NameTaken(
                        meta.name.clone(),
                    )));
                }
                if hashes.get(meta.sha256)?.is_some() {
                    return Err(ConflictableTransactionError::Abort(
                        CacheError::InvalidUpload("content committed concurrently".into()),
                    ));
                }
                volumes.insert(&id, record.as_slice())?;
                names.insert(meta.name.as_bytes(), &id)?;
                hashes.insert(&meta.sha256, &id)?;
                Ok(())
            });
        Ok(r?)
    }

    fn remove_data(&self, id: u64) -> Result<(), CacheError> {
        let prefix = id.to_be_bytes();
        let mut batch = sled::Batch::default();
        for kv in self.packets.scan_prefix(prefix) {
            batch.remove(kv?.0);
        }
        self.packets.apply_batch(batch)?;
        self.headers.remove(prefix)?;
        self.index.remove(prefix)?;
        Ok(())
    }

    /// One volume's record.
    pub fn meta(&self, id: u64) -> Result<VolumeMeta, CacheError> {
        match self.volumes.get(id.to_be_bytes())? {
            Some(v) => VolumeMeta::decode(&v),
            None => Err(CacheError::NotFound(VolumeKey::Id(id).to_string())),
        }
    }

    /// Describes a volume.
    pub fn describe(&self, key: &VolumeKey) -> Result<VolumeMeta, CacheError> {
        self.meta(self.resolve(key)?)
    }

    /// Every volume, ordered by name.
    pub fn list(&self) -> Result<Vec<VolumeMeta>, CacheError> {
        let mut out = Vec::new();
        for kv in self.names.iter() {
            let (_, id) = kv?;
            out.push(self.meta(id_from(&id)?)?);
        }
        Ok(out)
    }

    /// Deletes a volume; returns its id.
    pub fn delete(&self, key: &VolumeKey) -> Result<u64, CacheError> {
        let meta = self.describe(key)?;
        let id = meta.id.to_be_bytes();
        let r: Result<(), TransactionError<CacheError>> =
            (&self.volumes, &self.names, &self.hashes).transaction(|(volumes, names, hashes)| {
                volumes.remove(&id)?;
                names.remove(meta.name.as_bytes())?;
                hashes.remove(&meta.sha256)?;
                Ok(())
            });
        r?;
        self.db.flush()?;
        self.remove_data(meta.id)?;
        self.db.flush()?;
        tracing::info!(id = meta.id, name = meta.name, "deleted volume");
        Ok(meta.id)
    }

    /// A volume's header and packet index.
    pub fn index(&self, id: u64) -> Result<VolumeIndex, CacheError> {
        let key = id.to_be_bytes();
        let missing = || CacheError::Corrupt(format!("volume {id} has a record but no data"));
        let header_bytes = self.headers.get(key)?.ok_or_else(missing)?.to_vec();
        let (header, _) = read_header_section(&header_bytes)
            .map_err(|e| CacheError::Corrupt(format!("stored header of volume {id}: {e}")))?;
        let packets = decode_packets(&self.index.get(key)?.ok_or_else(missing)?)?;
        Ok(VolumeIndex {
            header,
            header_bytes,
            packets,
        })
    }

    /// One packet's bytes.
    pub fn packet(&self, id: u64, packet: u32) -> Result<Vec<u8>, CacheError> {
        match self.packets.get(packet_key(id, packet))? {
            Some(v) => Ok(v.to_vec()),
            None => Err(CacheError::NotFound(format!(
                "packet {packet} of volume {id}"
            ))),
        }
    }

    /// Number of stored packet entries (all volumes, including unreferenced ones).
    pub fn packet_entries(&self) -> usize {
        self.packets.len()
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
        let packets;
        {
            let store = Store::open(dir.path(), Limits::default()).unwrap();
            let index = index_file(&bytes, &Limits::default()).unwrap();
            packets = index.packets.len();
            // Interrupted ingest: data written, no commit record.
            store.write_data(99, &bytes, &index).unwrap();
            assert_eq!(store.packet_entries(), packets);
        }
        let store = Store::open(dir.path(), Limits::default()).unwrap();
        assert!(store.list().unwrap().is_empty());
        assert_eq!(store.packet_entries(), 0);
        let a = store.ingest("a", &bytes, None).unwrap();
        assert!(!a.existed);
        let b = store.ingest("b", &bytes, Some(sha256(&bytes))).unwrap();
        assert!(b.existed);
        assert_eq!(b.volume, a.volume);
        assert_eq!(store.packet_entries(), packets);
        assert!(store.ingest("c", &bytes, Some([0; 32])).is_err());
        assert!(matches!(
            store.ingest("a", &bytes[..bytes.len() - 1], None),
            Err(CacheError::NameTaken(_))
        ));
        assert!(store.ingest("d", &bytes[..bytes.len() - 1], None).is_err());
        assert_eq!(store.list().unwrap().len(), 1);
        store.delete(&VolumeKey::Name("a".into())).unwrap();
        assert!(store.list().unwrap().is_empty());
        assert_eq!(store.packet_entries(), 0);
    }
}
