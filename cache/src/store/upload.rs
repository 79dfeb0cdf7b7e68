//! An upload: the volume streamed to `volumes/ID.part` and validated as it arrives (the header
//! and directory as soon as they are complete, every packet as soon as its bytes are), then
//! synced, renamed and committed by the store in one transaction. A bricked container is read
//! the same way front to back: its manifest section first, then each brick as a `.wsp` of its
//! own (checked against its manifest entry and CRC), its packets numbered after the previous
//! bricks'.

use super::id_from;
use super::io;
use super::now_ms;
use super::validate::{check_kept, check_packet_size, index_packet, validate_name, Limits};
use super::Committed;
use super::Ingested;
use super::Store;
use crate::bucket::Bucket;
use crate::error::CacheError;
use crate::model::{
    encode_bricks, encode_packets, encode_series, BrickedIndex, IndexBrick, PacketMeta,
    SeriesIndex, VolumeKey, VolumeMeta,
};
use sha2::{Digest, Sha256};
use std::fs::File;
use std::io::Write;
use std::path::PathBuf;
use wavesplat_codec::format::bricked::{is_bricked, parse_manifest, Manifest, MAX_MANIFEST_BYTES};
use wavesplat_codec::format::series::{
    is_series, parse_manifest as parse_series_manifest, SeriesManifest,
    MAX_MANIFEST_BYTES as SERIES_MAX_MANIFEST_BYTES,
};
use wavesplat_codec::format::{parse_prelude, Header, Prelude};
use wavesplat_codec::view::bricked::{check_brick, whole_header};

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
    /// The upload read as one volume file.
    volume: ContainerReader,
    /// Every packet so far, numbered across bricks and components; offsets from the upload's
    /// start.
    packets: Vec<PacketMeta>,
    kept: bool,
}

impl Drop for Sink {
    fn drop(&mut self) {
        if !self.kept {
            let _ = std::fs::remove_file(&self.part);
        }
    }
}

/// What an upload holds.
#[derive(Debug)]
enum Layout {
    /// One volume (a `.wsp` file).
    Single,
    /// A bricked container: its manifest and the bricks read so far.
    Bricked(Box<BrickedUpload>),
    /// A series container: its manifest and the components read so far.
    Series(Box<SeriesUpload>),
}

/// What a complete volume file of an upload holds, besides its header.
#[derive(Debug)]
enum Stored {
    /// One volume of this many packets.
    Single(usize),
    Bricked(BrickedIndex),
    Series(SeriesIndex),
}

#[derive(Debug)]
struct SeriesUpload {
    manifest: SeriesManifest,
    /// The component being read (`None`: every one is read).
    component: Option<Box<ContainerReader>>,
    /// The whole header of component 0 (once read).
    first: Option<Header>,
    bricks: Vec<IndexBrick>,
    components: Vec<std::ops::Range<usize>>,
    /// Whether each component read so far is a bricked container.
    bricked: Vec<bool>,
    /// CRC-32 of the current component's bytes so far.
    crc: crc32fast::Hasher,
}

/// One volume file of an upload read front to back: a `.wsp`, a bricked container or (the
/// upload itself, not a component of one) a series container whose components are read by
/// readers of their own.
#[derive(Debug)]
struct ContainerReader {
    /// Where it starts in the upload, its length, and the bytes of it read so far.
    base: u64,
    len: u64,
    read: u64,
    /// Whether it may be a series (the upload itself).
    top: bool,
    /// Its first bytes, until they say whether it is one volume or a container and, for a
    /// container, until its manifest section is complete.
    head: Vec<u8>,
    /// What the head said: `None` while it is incomplete.
    layout: Option<Layout>,
    /// The `.wsp` being read: the whole file, or the current brick of a bricked container.
    reader: Option<WspReader>,
}

#[derive(Debug)]
struct BrickedUpload {
    manifest: Manifest,
    bricks: Vec<IndexBrick>,
    /// CRC-32 of the current brick's bytes so far.
    crc: crc32fast::Hasher,
}

/// One `.wsp` inside an upload (the whole upload, or one brick), validated as its bytes
/// arrive: the header and directory as soon as they are complete, every packet as soon as its
/// bytes are.
#[derive(Debug)]
struct WspReader {
    /// Its length, and the bytes of it read so far.
    len: u64,
    read: u64,
    /// Its brick (`None`: the upload is one volume).
    brick: Option<usize>,
    prelude_buf: Vec<u8>,
    /// `prelude_buf`'s length when it was last parsed (and found short).
    prelude_tried: usize,
    /// Times the prelude was parsed.
    prelude_parses: u32,
    prelude: Option<Prelude>,
    header_bytes: Vec<u8>,
    packet_buf: Vec<u8>,
    /// Its packets read so far.
    packets: usize,
    /// Coefficients its packets so far hold.
    held: u64,
    /// Where its next packet starts in the upload.
    offset: u64,
}

impl WspReader {
    fn new(start: u64, len: u64, brick: Option<usize>) -> WspReader {
        WspReader {
            len,
            read: 0,
            brick,
            prelude_buf: Vec::new(),
            prelude_tried: 0,
            prelude_parses: 0,
            prelude: None,
            header_bytes: Vec::new(),
            packet_buf: Vec::new(),
            packets: 0,
            held: 0,
            offset: start,
        }
    }

    /// "brick 3: " for a brick, nothing for one volume (a prefix of messages).
    fn which(&self) -> String {
        self.brick.map_or(String::new(), |b| format!("brick {b}: "))
    }

    /// The prelude, header bytes and packet count of a complete `.wsp` whose packets hold what
    /// its header declares.
    fn complete(&mut self) -> Result<(Prelude, Vec<u8>, usize), CacheError> {
        let complete = self
            .prelude
            .as_ref()
            .is_some_and(|p| self.packets == p.packet_lengths.len());
        let Some(prelude) = self.prelude.take().filter(|_| complete) else {
            return Err(CacheError::InvalidUpload(format!(
                "{}the upload ends inside its header, directory or a packet",
                self.which()
            )));
        };
        check_kept(&prelude, self.held)?;
        Ok((
            prelude,
            std::mem::take(&mut self.header_bytes),
            self.packets,
        ))
    }

    /// Validates the next bytes of this `.wsp` (no more than it has left), appending its
    /// packets' index entries to `packets`.
    fn feed(
        &mut self,
        data: &[u8],
        limits: &Limits,
        packets: &mut Vec<PacketMeta>,
    ) -> Result<(), CacheError> {
        self.read += data.len() as u64;
        if self.prelude.is_none() {
            self.prelude_buf.extend_from_slice(data);
            // Parsed again only once the bytes have grown by half (or 64 bytes) since the last
            // try, at the end of this file's bytes, or at the size limit: an upload sent a byte
            // a message would otherwise parse its whole header and directory again per byte
            // (quadratic in a directory of millions of packets). Bytes past the prelude wait
            // here until then and go to the packets below.
            let len = self.prelude_buf.len();
            let due = len >= self.prelude_tried + (self.prelude_tried / 2).max(64)
                || self.read >= self.len
                || len as u64 >= limits.max_prelude_bytes;
            if !due {
                return Ok(());
            }
            self.prelude_tried = len;
            self.prelude_parses += 1;
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
            if p.file_bytes() != self.len {
                return Err(CacheError::InvalidUpload(match self.brick {
                    None => format!(
                        "the packet directory describes a file of {} bytes, the upload \
                         declares {}",
                        p.file_bytes(),
                        self.len
                    ),
                    Some(b) => format!(
                        "brick {b}: its packet directory describes {} bytes, the manifest {}",
                        p.file_bytes(),
                        self.len
                    ),
                }));
            }
            for &len in &p.packet_lengths {
                check_packet_size(len, limits)?;
            }
            let rest = std::mem::take(&mut self.prelude_buf);
            self.header_bytes = rest[..p.header_bytes].to_vec();
            packets.reserve(p.packet_lengths.len());
            self.offset += p.len() as u64;
            let used = p.len();
            self.prelude = Some(p);
            return self.feed_packets(&rest[used..], limits, packets);
        }
        self.feed_packets(data, limits, packets)
    }

    fn feed_packets(
        &mut self,
        mut data: &[u8],
        limits: &Limits,
        packets: &mut Vec<PacketMeta>,
    ) -> Result<(), CacheError> {
        while !data.is_empty() {
            let n = self.feed_packets_some(data, limits, packets)?;
            data = &data[n..];
        }
        Ok(())
    }

    /// Takes bytes of the current packet from `data`, checks the packet when complete, and
    /// returns how many bytes it took.
    fn feed_packets_some(
        &mut self,
        data: &[u8],
        limits: &Limits,
        packets: &mut Vec<PacketMeta>,
    ) -> Result<usize, CacheError> {
        let Some(p) = &self.prelude else {
            return Ok(0);
        };
        let i = self.packets;
        let Some(&len) = p.packet_lengths.get(i) else {
            return Err(CacheError::InvalidUpload(format!(
                "{}bytes after the last packet",
                self.which()
            )));
        };
        if self.packet_buf.is_empty() {
            self.packet_buf.reserve_exact(len);
        }
        let take = (len - self.packet_buf.len()).min(data.len());
        self.packet_buf.extend_from_slice(&data[..take]);
        if self.packet_buf.len() == len {
            let (meta, held) = index_packet(p, i, &self.packet_buf, self.offset, &limits.decode)
                .map_err(|e| match (self.brick, e) {
                    (Some(b), CacheError::InvalidUpload(m)) => {
                        CacheError::InvalidUpload(format!("brick {b}: {m}"))
                    }
                    (_, e) => e,
                })?;
            self.offset += len as u64;
            packets.push(meta);
            self.packets += 1;
            self.held += held;
            self.packet_buf.clear();
        }
        // Progress: bytes taken, or (a packet of zero bytes) the packet count advanced.
        Ok(take)
    }

    /// The bytes this `.wsp` may hold in memory from now on.
    fn memory_need(&self, limits: &Limits) -> u64 {
        match &self.prelude {
            None => self.len.min(limits.max_prelude_bytes),
            Some(p) => p.packet_lengths[self.packets..]
                .iter()
                .copied()
                .max()
                .unwrap_or(0) as u64,
        }
    }
}

/// Bytes of a bricked container before its manifest: magic, version, manifest length.
const CONTAINER_LEAD: usize = 4 + 2 + 4;

impl Sink {
    fn new(id: u64, part: PathBuf, file: File, total: u64) -> Sink {
        Sink {
            id,
            part,
            file,
            volume: ContainerReader::new(0, total, true),
            packets: Vec::new(),
            kept: false,
        }
    }
}

impl ContainerReader {
    fn new(base: u64, len: u64, top: bool) -> ContainerReader {
        ContainerReader {
            base,
            len,
            read: 0,
            top,
            head: Vec::new(),
            layout: None,
            reader: None,
        }
    }

    /// What a complete file holds: the header (a bricked volume's: the whole's; a series': its
    /// time point 0's), the header bytes clients get (a container's: its manifest section) and
    /// its bricks or components.
    fn complete(&mut self) -> Result<(Header, Vec<u8>, Stored), CacheError> {
        match self.layout.take() {
            Some(Layout::Single) => {
                let Some(r) = self.reader.as_mut() else {
                    return Err(CacheError::InvalidUpload(
                        "the upload ends inside its header".into(),
                    ));
                };
                let (prelude, header_bytes, count) = r.complete()?;
                Ok((prelude.header, header_bytes, Stored::Single(count)))
            }
            Some(Layout::Bricked(b)) if b.bricks.len() == b.manifest.bricks.len() => {
                let header = whole_header(&b.manifest, &b.bricks[0].header);
                let b = *b;
                Ok((
                    header,
                    std::mem::take(&mut self.head),
                    Stored::Bricked(BrickedIndex {
                        manifest: b.manifest,
                        bricks: b.bricks,
                    }),
                ))
            }
            Some(Layout::Bricked(b)) => Err(CacheError::InvalidUpload(format!(
                "the upload ends inside brick {} of {}",
                b.bricks.len(),
                b.manifest.bricks.len()
            ))),
            Some(Layout::Series(s)) if s.components.len() == s.manifest.components.len() => {
                let s = *s;
                let index = SeriesIndex {
                    manifest: s.manifest,
                    bricks: s.bricks,
                    components: s.components,
                    bricked: s.bricked,
                };
                let header = index.whole_header()?;
                Ok((
                    header,
                    std::mem::take(&mut self.head),
                    Stored::Series(index),
                ))
            }
            Some(Layout::Series(s)) => Err(CacheError::InvalidUpload(format!(
                "the upload ends inside component {} of {}",
                s.components.len(),
                s.manifest.components.len()
            ))),
            None => Err(CacheError::InvalidUpload(
                "the upload ends inside its header".into(),
            )),
        }
    }

    /// Validates the next bytes of the file (no more than it has left).
    fn feed(
        &mut self,
        mut data: &[u8],
        limits: &Limits,
        packets: &mut Vec<PacketMeta>,
    ) -> Result<(), CacheError> {
        while !data.is_empty() {
            let taken = if let Some(Layout::Series(s)) = &mut self.layout {
                s.feed(data, limits, packets)?
            } else {
                match self.reader.as_mut() {
                    Some(r) => {
                        let take = (r.len - r.read).min(data.len() as u64) as usize;
                        if let Some(Layout::Bricked(b)) = &mut self.layout {
                            b.crc.update(&data[..take]);
                        }
                        r.feed(&data[..take], limits, packets)?;
                        if r.read == r.len && r.brick.is_some() {
                            self.end_brick(packets)?;
                        }
                        take
                    }
                    None => match self.feed_head(data, limits, packets)? {
                        Some(n) => n,
                        None => continue,
                    },
                }
            };
            if taken == 0 {
                return Err(CacheError::InvalidUpload(
                    "bytes after the last brick".into(),
                ));
            }
            self.read += taken as u64;
            data = &data[taken..];
        }
        Ok(())
    }

    /// Takes bytes of the file's head from `data` (no more than it needs, so that what
    /// follows reaches the first `.wsp` reader); returns how many, or `None` when it took none
    /// but decided the layout (the reader takes `data` next).
    fn feed_head(
        &mut self,
        data: &[u8],
        limits: &Limits,
        packets: &mut Vec<PacketMeta>,
    ) -> Result<Option<usize>, CacheError> {
        if self.layout.is_some() {
            // Every brick read: nothing may follow.
            return Ok(Some(0));
        }
        let series = is_series(&self.head);
        let need = if self.head.len() < 6 {
            6
        } else if series && !self.top {
            return Err(CacheError::InvalidUpload(
                "a component of a series is itself a series".into(),
            ));
        } else if !is_bricked(&self.head) && !series {
            // One volume: its reader takes the head's bytes, then the rest.
            let mut r = WspReader::new(self.base, self.len, None);
            r.feed(&std::mem::take(&mut self.head), limits, packets)?;
            self.reader = Some(r);
            self.layout = Some(Layout::Single);
            // Nothing of `data` taken: the reader takes it next.
            return Ok(None);
        } else if self.head.len() < CONTAINER_LEAD {
            CONTAINER_LEAD
        } else {
            let len = u32::from_le_bytes(self.head[6..10].try_into().expect("4 bytes")) as u64;
            let section = CONTAINER_LEAD as u64 + len + 4;
            let (what, max) = if series {
                ("series manifest", SERIES_MAX_MANIFEST_BYTES)
            } else {
                ("bricked manifest", MAX_MANIFEST_BYTES)
            };
            let limit = limits.max_prelude_bytes.min(max as u64);
            if section > limit {
                return Err(CacheError::TooLarge {
                    what,
                    size: section,
                    limit,
                });
            }
            section as usize
        };
        let take = (need - self.head.len()).min(data.len());
        self.head.extend_from_slice(&data[..take]);
        if self.head.len() == need && need > CONTAINER_LEAD {
            if series {
                self.begin_components()?;
            } else {
                self.begin_bricks()?;
            }
        }
        Ok(Some(take))
    }

    /// The manifest section is complete: parses the manifest (checked against the upload's
    /// size) and starts reading its first brick. Bricks must follow the manifest section in
    /// manifest order without gaps, as the container writer lays them out: the upload is read
    /// once, front to back.
    fn begin_bricks(&mut self) -> Result<(), CacheError> {
        let manifest = parse_manifest(&self.head, self.len)?;
        let spans: Vec<(u64, u64)> = manifest
            .bricks
            .iter()
            .map(|b| (b.offset, b.length))
            .collect();
        self.check_laid_out("brick", &spans)?;
        let first = &manifest.bricks[0];
        self.reader = Some(WspReader::new(
            self.base + first.offset,
            first.length,
            Some(0),
        ));
        self.layout = Some(Layout::Bricked(Box::new(BrickedUpload {
            manifest,
            bricks: Vec::new(),
            crc: crc32fast::Hasher::new(),
        })));
        Ok(())
    }

    /// The series manifest section is complete: parses it (checked against the upload's size)
    /// and starts reading its first component, laid out as bricks are.
    fn begin_components(&mut self) -> Result<(), CacheError> {
        let manifest = parse_series_manifest(&self.head, self.len)?;
        let spans: Vec<(u64, u64)> = manifest
            .components
            .iter()
            .map(|c| (c.offset, c.length))
            .collect();
        self.check_laid_out("component", &spans)?;
        let first = &manifest.components[0];
        let component = ContainerReader::new(self.base + first.offset, first.length, false);
        self.layout = Some(Layout::Series(Box::new(SeriesUpload {
            manifest,
            component: Some(Box::new(component)),
            first: None,
            bricks: Vec::new(),
            components: Vec::new(),
            bricked: Vec::new(),
            crc: crc32fast::Hasher::new(),
        })));
        Ok(())
    }

    /// Checks that the parts at `spans` (offset, length from the container's start) follow
    /// the manifest section in order, without gaps, to the container's end, none empty.
    fn check_laid_out(&self, what: &str, spans: &[(u64, u64)]) -> Result<(), CacheError> {
        let mut at = self.head.len() as u64;
        for (i, &(offset, length)) in spans.iter().enumerate() {
            if length == 0 {
                return Err(CacheError::InvalidUpload(format!(
                    "{what} {i} is empty: every {what} is a volume file"
                )));
            }
            if offset != at {
                return Err(CacheError::InvalidUpload(format!(
                    "{what} {i} starts at byte {offset}, not where the previous one ends \
                     ({at}): a cache takes {what}s laid out in manifest order"
                )));
            }
            at += length;
        }
        if at != self.len {
            return Err(CacheError::InvalidUpload(format!(
                "the {what}s end at byte {at}, the upload declares {}",
                self.len
            )));
        }
        Ok(())
    }

    /// The current brick's bytes are all read: checks it (complete, its CRC, its header against
    /// the manifest and the first brick), records it, and starts reading the next one.
    fn end_brick(&mut self, packets: &[PacketMeta]) -> Result<(), CacheError> {
        let (Some(r), Some(Layout::Bricked(b))) = (self.reader.as_mut(), self.layout.as_mut())
        else {
            return Ok(());
        };
        let i = b.bricks.len();
        let (prelude, header_bytes, count) = r.complete()?;
        let entry = &b.manifest.bricks[i];
        let computed = std::mem::take(&mut b.crc).finalize();
        if computed != entry.crc {
            return Err(CacheError::InvalidUpload(format!(
                "brick {i}: CRC-32 {computed:08x}, the manifest says {:08x}",
                entry.crc
            )));
        }
        let first = b.bricks.first().map_or(&prelude.header, |f| &f.header);
        check_brick(i, entry, &prelude.header, first, b.manifest.channels)?;
        b.bricks.push(IndexBrick {
            header: prelude.header,
            header_bytes,
            origin: entry.origin,
            first_packet: first_packet(packets, count)?,
            packets: count as u32,
        });
        self.reader = b
            .manifest
            .bricks
            .get(i + 1)
            .map(|e| WspReader::new(self.base + e.offset, e.length, Some(i + 1)));
        Ok(())
    }

    /// The bytes this file may hold in memory from now on.
    fn memory_need(&self, limits: &Limits) -> u64 {
        if let Some(Layout::Series(s)) = &self.layout {
            return s.component.as_ref().map_or(0, |c| c.memory_need(limits));
        }
        match &self.reader {
            Some(r) => r.memory_need(limits),
            None if self.layout.is_none() => self.len.min(limits.max_prelude_bytes),
            None => 0,
        }
    }
}

/// The id of the first of the last `count` packets of `packets`, checked to number in `u32`.
fn first_packet(packets: &[PacketMeta], count: usize) -> Result<u32, CacheError> {
    u32::try_from(packets.len() - count)
        .ok()
        .filter(|_| u32::try_from(packets.len()).is_ok())
        .ok_or_else(|| CacheError::InvalidUpload("more than 2^32 packets in one volume".into()))
}

impl SeriesUpload {
    /// Feeds the current component the bytes of `data` it has left; returns how many it took
    /// (0: every component is read).
    fn feed(
        &mut self,
        data: &[u8],
        limits: &Limits,
        packets: &mut Vec<PacketMeta>,
    ) -> Result<usize, CacheError> {
        let i = self.components.len();
        let Some(c) = self.component.as_mut() else {
            return Ok(0);
        };
        let take = (c.len - c.read).min(data.len() as u64) as usize;
        self.crc.update(&data[..take]);
        c.feed(&data[..take], limits, packets)
            .map_err(|e| in_component(i, e))?;
        if c.read == c.len {
            self.end_component(packets)
                .map_err(|e| in_component(i, e))?;
        }
        Ok(take)
    }

    /// The current component's bytes are all read: checks it (complete, its CRC, its space
    /// against the series'), records its bricks, and starts reading the next one.
    fn end_component(&mut self, packets: &[PacketMeta]) -> Result<(), CacheError> {
        let Some(mut c) = self.component.take() else {
            return Ok(());
        };
        let i = self.components.len();
        let entry = &self.manifest.components[i];
        let computed = std::mem::take(&mut self.crc).finalize();
        if computed != entry.crc {
            return Err(CacheError::InvalidUpload(format!(
                "CRC-32 {computed:08x}, the manifest says {:08x}",
                entry.crc
            )));
        }
        let (header, header_bytes, stored) = c.complete()?;
        let space = &self.manifest.space;
        if header.geometry.dims != space.dims.map(|d| d as usize)
            || header.channels != space.channels
        {
            return Err(CacheError::InvalidUpload(format!(
                "{:?} with {} channel(s); the series is {:?} with {}",
                header.geometry.dims, header.channels, space.dims, space.channels
            )));
        }
        if let Some(first) = &self.first {
            // Offsets differ between components (a time point weights them); the family, the
            // colour space and its basis may not.
            let shown = |h: &Header| (h.geometry.family, h.color.kind, h.color.basis);
            if shown(&header) != shown(first) {
                return Err(CacheError::InvalidUpload(
                    "its wavelet family or colour space differs from component 0's".into(),
                ));
            }
        }
        let start = self.bricks.len();
        self.bricked.push(matches!(stored, Stored::Bricked(_)));
        match stored {
            Stored::Single(count) => self.bricks.push(IndexBrick {
                header: header.clone(),
                header_bytes,
                origin: [0; 3],
                first_packet: first_packet(packets, count)?,
                packets: count as u32,
            }),
            Stored::Bricked(b) => self.bricks.extend(b.bricks),
            Stored::Series(_) => {
                return Err(CacheError::InvalidUpload("a series in a series".into()))
            }
        }
        self.components.push(start..self.bricks.len());
        self.first.get_or_insert(header);
        self.component = self
            .manifest
            .components
            .get(i + 1)
            .map(|e| Box::new(ContainerReader::new(e.offset, e.length, false)));
        Ok(())
    }
}

/// Names component `i` in an upload error about it.
fn in_component(i: usize, e: CacheError) -> CacheError {
    match e {
        CacheError::InvalidUpload(m) => CacheError::InvalidUpload(format!("component {i}: {m}")),
        e => e,
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
            Some(Sink::new(id, part, file, total))
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
            .map_or(0, |s| s.volume.memory_need(&self.store.limits))
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
            s.volume.feed(chunk, &self.store.limits, &mut s.packets)?;
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
                let (header, header_bytes, stored) = s.volume.complete()?;
                s.file.sync_all().map_err(|e| io("syncing an upload", e))?;
                let id = s.id;
                let path = store.file_path(id, "wsp");
                std::fs::rename(&s.part, &path).map_err(|e| io("storing an upload", e))?;
                s.kept = true;
                if let Ok(dir) = File::open(&*store.files) {
                    let _ = dir.sync_all();
                }
                let section_bytes = header_bytes.len();
                store.headers.insert(id.to_be_bytes(), header_bytes)?;
                store
                    .index
                    .insert(id.to_be_bytes(), encode_packets(&s.packets))?;
                match &stored {
                    Stored::Bricked(b) => {
                        store
                            .bricks
                            .insert(id.to_be_bytes(), encode_bricks(&b.bricks))?;
                    }
                    Stored::Series(s) => {
                        store.bricks.insert(id.to_be_bytes(), encode_series(s))?;
                    }
                    Stored::Single(_) => {}
                }
                store.db.flush()?;
                if let Some(e) = abandon() {
                    store.remove_data(id)?;
                    return Err(e);
                }
                let mut meta = VolumeMeta::from_header(
                    id,
                    vec![self.name.clone()],
                    hash,
                    now_ms(),
                    self.total,
                    &header,
                    section_bytes,
                    &s.packets,
                );
                match &stored {
                    Stored::Bricked(b) => {
                        meta.describe_bricks(section_bytes, &b.bricks, b.manifest.kept())
                    }
                    Stored::Series(s) => {
                        meta.describe_bricks(section_bytes, &s.bricks, s.manifest.kept())
                    }
                    Stored::Single(_) => {}
                }
                meta
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
                // A bricked container or a series is published in its own version of the
                // indexed layout.
                let bricked = !matches!(s.volume.complete()?.2, Stored::Single(_));
                let file = bytes::Bytes::from(
                    std::fs::read(&s.part).map_err(|e| io("reading an upload back", e))?,
                );
                // The object is the indexed layout's head and index, then the file as it was
                // uploaded: sent as those two pieces, so the file is held once, not copied
                // behind its index.
                let prefix = if bricked {
                    // The published layout of a bricked volume or a series (versions 2 and 3
                    // of the indexed layout): its manifest, every brick's header and index.
                    wavesplat_codec::format::index::indexed_layout_prefix(&file)?
                } else {
                    wavesplat_codec::format::index::indexed_prefix(self.total, &s.packets)?
                };
                Some(object_store::PutPayload::from_iter([
                    bytes::Bytes::from(prefix),
                    file,
                ]))
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

#[cfg(test)]
mod tests {
    use super::*;

    /// A file of many tiny tiles: a header and packet directory of several kilobytes.
    fn many_packets() -> Vec<u8> {
        use wavesplat_compressor::encode::{compress, CompressOptions, Target, TileChoice};
        let vol = wavesplat_compressor::phantom::Phantom::SheppLogan.generate([40, 40, 40]);
        compress(
            &vol,
            &CompressOptions {
                target: Target::Fraction(0.2),
                tile: TileChoice::Size(2),
                levels: Some(1),
                ..Default::default()
            },
            &|_, _| {},
        )
        .unwrap()
        .bytes
    }

    /// A `.wsp` fed a byte at a time is indexed exactly as when fed whole, and its header and
    /// directory are parsed a handful of times, not once per byte.
    #[test]
    fn a_file_fed_a_byte_at_a_time_is_indexed_the_same_parsing_its_prelude_a_few_times() {
        let bytes = many_packets();
        let limits = Limits::default();
        let prelude = parse_prelude(&bytes).unwrap().unwrap();
        assert!(
            prelude.len() > 4 << 10,
            "a prelude of {} bytes",
            prelude.len()
        );
        let len = bytes.len() as u64;
        let mut whole = WspReader::new(0, len, None);
        let mut whole_packets = Vec::new();
        whole.feed(&bytes, &limits, &mut whole_packets).unwrap();
        let mut bytewise = WspReader::new(0, len, None);
        let mut packets = Vec::new();
        for b in bytes.chunks(1) {
            bytewise.feed(b, &limits, &mut packets).unwrap();
        }
        assert_eq!(packets, whole_packets);
        assert_eq!(packets.len(), prelude.packet_lengths.len());
        let (_, header, count) = bytewise.complete().unwrap();
        assert_eq!(count, packets.len());
        assert_eq!(header, whole.complete().unwrap().1);
        assert!(
            bytewise.prelude_parses <= 16,
            "the prelude of {} bytes parsed {} times",
            prelude.len(),
            bytewise.prelude_parses
        );
        // Cut short anywhere, it is incomplete, never accepted.
        let mut cut = WspReader::new(0, len, None);
        cut.feed(&bytes[..prelude.len() - 1], &limits, &mut Vec::new())
            .unwrap();
        assert!(cut.complete().is_err());
    }
}
