//! An upload: the volume streamed to `volumes/ID.part` and validated as it arrives (the header
//! and directory as soon as they are complete, every packet as soon as its bytes are), then
//! synced, renamed and committed by the store in one transaction.

use super::id_from;
use super::io;
use super::now_ms;
use super::validate::{check_kept, check_packet_size, index_packet, validate_name, Limits};
use super::Committed;
use super::Ingested;
use super::Store;
use crate::bucket::Bucket;
use crate::error::CacheError;
use crate::model::{encode_packets, PacketMeta, VolumeKey, VolumeMeta};
use sha2::{Digest, Sha256};
use std::fs::File;
use std::io::Write;
use std::path::PathBuf;
use wavesplat_codec::format::{parse_prelude, Prelude};

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
                wavesplat_net::digest::hex(&self.declared),
                wavesplat_net::digest::hex(&hash)
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

pub(super) fn blank_meta(name: &str, sha256: [u8; 32]) -> VolumeMeta {
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
