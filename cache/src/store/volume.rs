//! An opened volume: its parsed header, packet index and file (or, for a bucket node, its object),
//! with positioned reads of packet ranges; kept in the store's cache of opened volumes.

use crate::bucket::Bucket;
use crate::error::CacheError;
use crate::model::{PacketMeta, VolumeIndex, VolumeMeta};
use std::fs::File;
use std::sync::Arc;

/// A stored volume opened for reading: its record, header and index, and its data file.
#[derive(Debug)]
pub struct OpenVolume {
    /// The record.
    pub meta: VolumeMeta,
    /// Header and packet index.
    pub index: VolumeIndex,
    pub(super) data: VolumeData,
}

/// Where an open volume's packets are read from.
#[derive(Debug)]
pub(super) enum VolumeData {
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
