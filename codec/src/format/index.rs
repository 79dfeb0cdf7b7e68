//! The packet index and the indexed layout a volume is stored and published in.
//!
//! A `.wsp` file's directory holds only packet lengths; where each packet's tile and layer are and
//! how much energy it carries per band (what a view-dependent sender plans with) is known only by
//! decoding the packets. The index ([`PacketMeta`] per packet) records those facts once, at
//! ingest. The **indexed layout** (`.wspx`) puts the index in front of the unchanged `.wsp`
//! bytes, so a reader that fetches byte ranges (an object store, a web server, a CDN) has the
//! header and the whole index after one request (two when they exceed the first request's size)
//! and then fetches exactly the packets it wants:
//!
//! ```text
//! "WSPX" | layout version u16 | .wsp length u64 | index length u32 | index CRC-32
//! index: packet count, first packet's offset in the .wsp (varints; the packets follow each
//!        other), per packet tile, layer, length, band count (varints) and per band
//!        level·8 + type (u8) and its energy as a bfloat16 (u16: 8 exponent bits, 7 of mantissa)
//! the .wsp file, byte for byte
//! ```
//!
//! The energies only rank packets (visible energy per byte), so 0.4 % precision is plenty and
//! keeps the index near 3 bytes per band of a packet; the cache's own index keeps f64.
//!
//! A bricked container ([`crate::format::bricked`], format version 9 or 11) is published the same way
//! as layout version 2: one object, the index of every brick in front of the unchanged
//! container, so a reader has the manifest, every brick's header and every packet's place
//! after one or two requests, and then fetches only the packets (of the bricks) a view sees:
//!
//! ```text
//! "WSPX" | 2 u16 | container length u64 | index length u32 | index CRC-32
//! index: brick count (varint); per brick in manifest order: its .wsp header section's length
//!        (varint) and bytes (a copy: its own lies inside the container), its compact index's
//!        length (varint) and bytes (as above; offsets within the brick's .wsp)
//! the bricked container, byte for byte (its manifest first)
//! ```
//!
//! A time series ([`crate::format::series`], format version 10) is published as layout version 3,
//! the same way: every component's bricks (a plain component is one brick) indexed in front of
//! the unchanged container, so a reader of one time point fetches the packets of the components
//! it names and no other:
//!
//! ```text
//! "WSPX" | 3 u16 | container length u64 | index length u32 | index CRC-32
//! index: component count (varint); per component in manifest order: its kind (u8: 0 a plain
//!        .wsp, 1 a bricked container), its brick count (varint) and per brick its first
//!        voxel in the whole (3 varints), its .wsp's offset in the component and its length
//!        (varints), its header section (length varint and bytes) and its compact index
//! the series container, byte for byte (its manifest first)
//! ```
//!
//! One object rather than a manifest plus an object per brick: a published volume stays one
//! file to copy, serve and cache, and a reader still needs no request per brick before its
//! first image (all headers come with the head).
//!
//! Every read is bounds-checked and the index is checked against the `.wsp` it fronts: packets lie
//! after the header, inside the file, without overlapping.

use crate::format::bricked::{
    is_bricked, parse_bricked, parse_manifest, Manifest, MAX_MANIFEST_BYTES,
};
use crate::format::bytes::{ByteReader, ByteWriter};
use crate::format::{read_header_section, FormatError, Header, MAGIC};
use crate::layout::Band;

/// Magic bytes of the indexed layout.
pub const INDEXED_MAGIC: &[u8; 4] = b"WSPX";
/// The indexed layout's version (of one volume).
pub const INDEXED_VERSION: u16 = 1;
/// The indexed layout's version for a bricked container.
pub const BRICKED_INDEXED_VERSION: u16 = 2;
/// The indexed layout's version for a time series.
pub const SERIES_INDEXED_VERSION: u16 = 3;
/// Bytes before the index: magic, version, `.wsp` length, index length, index CRC.
pub const INDEXED_HEAD_BYTES: usize = 4 + 2 + 8 + 4 + 4;
/// What a range reader asks for first: the head, the index and the `.wsp` header of most
/// volumes fit (the rest comes in a second request, [`HeadRead::Need`]).
pub const HEAD_READ_BYTES: u64 = 64 << 10;
/// Largest index accepted (bytes).
pub const MAX_INDEX_BYTES: u32 = 256 << 20;

/// What a sender knows about one packet without reading it.
#[derive(Debug, Clone, PartialEq)]
pub struct PacketMeta {
    /// Tile index.
    pub tile: u32,
    /// Layer (rank within the tile).
    pub layer: u32,
    /// Size in bytes.
    pub len: u32,
    /// Where it starts in the `.wsp` file.
    pub offset: u64,
    /// Energy Σ w²‖basis‖²·I per band (from the packet's own summary).
    pub summary: Vec<(Band, f64)>,
}

/// Encodes a packet index.
pub fn encode_packets(packets: &[PacketMeta]) -> Vec<u8> {
    let mut w = ByteWriter::new();
    w.varint(packets.len() as u64);
    for p in packets {
        w.varint(p.tile as u64);
        w.varint(p.layer as u64);
        w.varint(p.len as u64);
        w.varint(p.offset);
        w.varint(p.summary.len() as u64);
        for (band, e) in &p.summary {
            w.u8(band.level);
            w.u8(band.kind);
            w.f64(*e);
        }
    }
    w.into_bytes()
}

/// Decodes a packet index (`with_offsets`: the current form; without, a form without offsets
/// that old cache stores kept).
pub fn decode_packets(bytes: &[u8], with_offsets: bool) -> Result<Vec<PacketMeta>, FormatError> {
    let mut r = ByteReader::new(bytes, "packet index");
    let n = r.varint_max(1 << 28, "packets")? as usize;
    let mut out = Vec::with_capacity(n.min(r.remaining()));
    for _ in 0..n {
        out.push(read_entry(
            &mut r,
            |r| if with_offsets { r.varint() } else { Ok(0) },
            |r| {
                let level = r.u8()?;
                let kind = r.u8()?;
                let e = r.f64()?;
                Ok((Band { level, kind }, e))
            },
        )?);
    }
    expect_end(&r)?;
    Ok(out)
}

/// An index entry, as both forms of the index store it: tile, layer and packet length; then
/// its offset, as `offset` reads it (the compact form and the old one store none); then its
/// energy summary, each (band, energy) pair read by `pair`.
fn read_entry(
    r: &mut ByteReader,
    offset: impl FnOnce(&mut ByteReader) -> Result<u64, FormatError>,
    pair: impl FnMut(&mut ByteReader) -> Result<(Band, f64), FormatError>,
) -> Result<PacketMeta, FormatError> {
    let tile = r.varint_max(u32::MAX as u64, "tile")? as u32;
    let layer = r.varint_max(u32::MAX as u64, "layer")? as u32;
    let len = r.varint_max(u32::MAX as u64, "len")? as u32;
    let offset = offset(r)?;
    let summary = read_summary(r, pair)?;
    Ok(PacketMeta {
        tile,
        layer,
        len,
        offset,
        summary,
    })
}

/// An index entry's energy summary: its length, then that many (band, energy) pairs, each read
/// by `pair` (the two forms of the index store them differently).
fn read_summary(
    r: &mut ByteReader,
    mut pair: impl FnMut(&mut ByteReader) -> Result<(Band, f64), FormatError>,
) -> Result<Vec<(Band, f64)>, FormatError> {
    let ns = r.varint_max(1 << 16, "summary")? as usize;
    let mut summary = Vec::with_capacity(ns.min(r.remaining()));
    for _ in 0..ns {
        summary.push(pair(r)?);
    }
    Ok(summary)
}

/// An error unless `r` has read the whole index: nothing may follow the last entry.
fn expect_end(r: &ByteReader) -> Result<(), FormatError> {
    if r.remaining() != 0 {
        return Err(invalid(format!(
            "{} bytes after the last packet entry",
            r.remaining()
        )));
    }
    Ok(())
}

fn invalid(detail: String) -> FormatError {
    FormatError::Invalid {
        what: "indexed layout",
        detail,
    }
}

/// An energy as a bfloat16 (round to nearest).
fn to_bf16(e: f64) -> u16 {
    let bits = (e as f32).to_bits();
    let rounded = bits.wrapping_add(0x7fff + ((bits >> 16) & 1));
    (rounded >> 16) as u16
}

fn from_bf16(b: u16) -> f64 {
    f64::from(f32::from_bits(u32::from(b) << 16))
}

/// The layout's compact index (offsets implied: the packets follow each other).
fn encode_compact(packets: &[PacketMeta]) -> Result<Vec<u8>, FormatError> {
    let mut w = ByteWriter::new();
    w.varint(packets.len() as u64);
    w.varint(packets.first().map_or(0, |p| p.offset));
    let mut next = packets.first().map_or(0, |p| p.offset);
    for (i, p) in packets.iter().enumerate() {
        if p.offset != next {
            return Err(invalid(format!(
                "packet {i} starts at {} where the one before it ends at {next}",
                p.offset
            )));
        }
        next += p.len as u64;
        w.varint(p.tile as u64);
        w.varint(p.layer as u64);
        w.varint(p.len as u64);
        w.varint(p.summary.len() as u64);
        for (band, e) in &p.summary {
            if band.level > 31 || band.kind > 7 {
                return Err(invalid(format!("band {band:?} of packet {i}")));
            }
            w.u8(band.level * 8 + band.kind);
            w.u16(to_bf16(*e));
        }
    }
    Ok(w.into_bytes())
}

fn decode_compact(bytes: &[u8]) -> Result<Vec<PacketMeta>, FormatError> {
    let mut r = ByteReader::new(bytes, "packet index");
    let n = r.varint_max(1 << 28, "packets")? as usize;
    let mut offset = r.varint()?;
    let mut out = Vec::with_capacity(n.min(r.remaining()));
    for _ in 0..n {
        let entry = read_entry(
            &mut r,
            |_| Ok(offset),
            |r| {
                let b = r.u8()?;
                let e = from_bf16(r.u16()?);
                Ok((
                    Band {
                        level: b / 8,
                        kind: b % 8,
                    },
                    e,
                ))
            },
        )?;
        offset = offset
            .checked_add(entry.len as u64)
            .ok_or_else(|| invalid("packet offsets overflow".into()))?;
        out.push(entry);
    }
    expect_end(&r)?;
    Ok(out)
}

/// The bytes in front of a `.wsp` file of `wsp_bytes` bytes in the indexed layout: the head and
/// the index. The packets must follow each other in the file, as in every `.wsp`.
pub fn indexed_prefix(wsp_bytes: u64, packets: &[PacketMeta]) -> Result<Vec<u8>, FormatError> {
    let index = encode_compact(packets)?;
    Ok(prefix_with(INDEXED_VERSION, wsp_bytes, &index))
}

/// The head (magic, `version`, lengths, CRC) and `index`.
fn prefix_with(version: u16, wsp_bytes: u64, index: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(INDEXED_HEAD_BYTES + index.len());
    out.extend_from_slice(INDEXED_MAGIC);
    out.extend_from_slice(&version.to_le_bytes());
    out.extend_from_slice(&wsp_bytes.to_le_bytes());
    out.extend_from_slice(&(index.len() as u32).to_le_bytes());
    out.extend_from_slice(&crc32fast::hash(index).to_le_bytes());
    out.extend_from_slice(index);
    out
}

/// The index of a whole `.wsp` file: every packet decoded once (which also checks it), and the
/// file refused when its packets do not hold the coefficients its header declares.
pub fn index_file(bytes: &[u8]) -> Result<Vec<PacketMeta>, FormatError> {
    let file = crate::format::parse_file(bytes)?;
    let base = bytes.as_ptr() as usize;
    let mut held = 0u64;
    let mut out = Vec::with_capacity(file.packets.len());
    for p in &file.packets {
        let d = crate::format::packet::decode_packet(&file.header, p)?;
        held += d.coefficients.len() as u64;
        out.push(PacketMeta {
            tile: d.tile as u32,
            layer: d.layer as u32,
            len: p.len() as u32,
            offset: (p.as_ptr() as usize - base) as u64,
            summary: d.summary,
        });
    }
    crate::format::check_kept(&file.header, held)?;
    Ok(out)
}

/// A `.wsp` file in the indexed layout (see the module documentation); a bricked container in
/// its version 2, every brick's packets decoded once (which checks them).
pub fn indexed_layout(wsp: &[u8]) -> Result<Vec<u8>, FormatError> {
    let mut out = indexed_layout_prefix(wsp)?;
    out.extend_from_slice(wsp);
    Ok(out)
}

/// What [`indexed_layout`] puts in front of `wsp`: the head and the index (the layout is this,
/// then `wsp` unchanged), for a writer that sends the two apart instead of copying the file.
pub fn indexed_layout_prefix(wsp: &[u8]) -> Result<Vec<u8>, FormatError> {
    if crate::format::series::is_series(wsp) {
        return series_indexed_prefix(wsp);
    }
    if is_bricked(wsp) {
        let file = parse_bricked(wsp)?;
        let mut w = ByteWriter::new();
        w.varint(file.manifest.bricks.len() as u64);
        for i in 0..file.manifest.bricks.len() {
            let brick = file.brick_bytes(i)?;
            write_brick_index(&mut w, brick)?;
        }
        return prefix_within(
            BRICKED_INDEXED_VERSION,
            "bricked packet index",
            &w.into_bytes(),
            wsp,
        );
    }
    indexed_prefix(wsp.len() as u64, &index_file(wsp)?)
}

/// [`indexed_layout_prefix`] of a series container (layout version 3): every component's
/// bricks indexed, every packet decoded once.
fn series_indexed_prefix(container: &[u8]) -> Result<Vec<u8>, FormatError> {
    let file = crate::format::series::parse_series(container)?;
    let mut w = ByteWriter::new();
    w.varint(file.manifest.components.len() as u64);
    for c in 0..file.manifest.components.len() {
        let data = file.component_bytes(c)?;
        // (origin, offset in the component, length) of each brick's .wsp.
        let bricks: Vec<([u64; 3], u64, u64)> = if is_bricked(data) {
            let b = parse_bricked(data)?;
            b.manifest
                .bricks
                .iter()
                .map(|e| (e.origin, e.offset, e.length))
                .collect()
        } else {
            vec![([0; 3], 0, data.len() as u64)]
        };
        w.u8(u8::from(is_bricked(data)));
        w.varint(bricks.len() as u64);
        for (origin, offset, length) in bricks {
            for o in origin {
                w.varint(o);
            }
            w.varint(offset);
            w.varint(length);
            write_brick_index(&mut w, &data[offset as usize..(offset + length) as usize])?;
        }
    }
    prefix_within(
        SERIES_INDEXED_VERSION,
        "series packet index",
        &w.into_bytes(),
        container,
    )
}

/// One brick's entry in a bricked or series index: its `.wsp` header section (length and
/// bytes) and its compact packet index (length and bytes), every packet decoded once.
fn write_brick_index(w: &mut ByteWriter, brick: &[u8]) -> Result<(), FormatError> {
    let (_, header_len) = read_header_section(brick)?;
    let index = encode_compact(&index_file(brick)?)?;
    w.varint(header_len as u64);
    w.bytes(&brick[..header_len]);
    w.varint(index.len() as u64);
    w.bytes(&index);
    Ok(())
}

/// The head and `index` (bounded, `what` it is) of a container in the indexed layout's
/// `version`.
fn prefix_within(
    version: u16,
    what: &'static str,
    index: &[u8],
    container: &[u8],
) -> Result<Vec<u8>, FormatError> {
    if index.len() > MAX_INDEX_BYTES as usize {
        return Err(FormatError::TooLarge {
            what,
            size: index.len() as u64,
            limit: MAX_INDEX_BYTES as u64,
        });
    }
    Ok(prefix_with(version, container.len() as u64, index))
}

/// The `.wsp` inside a whole indexed object held in memory (what [`indexed_layout`] wrote, read
/// back from a local file): its head and index checked, and the object's length held to what
/// the head declares (a cut or extended object is refused).
pub fn wsp_of_indexed(object: &[u8]) -> Result<&[u8], FormatError> {
    let len = object.len() as u64;
    let truncated = |total: u64| FormatError::Truncated {
        what: "indexed layout",
        needed: total,
        available: len,
    };
    let (total, wsp_offset) = match read_indexed_head(object)? {
        HeadRead::Indexed(h) => (h.object_bytes(), h.wsp_offset),
        HeadRead::Bricked(h) => (h.object_bytes(), h.wsp_offset),
        HeadRead::Series(h) => (h.object_bytes(), h.wsp_offset),
        HeadRead::Need(n) => return Err(truncated(n as u64)),
    };
    if len < total {
        return Err(truncated(total));
    }
    if len > total {
        return Err(invalid(format!(
            "{len} bytes where the head declares {total}"
        )));
    }
    Ok(&object[wsp_offset as usize..])
}

/// An indexed volume's header and index, read from the start of its object.
#[derive(Debug, Clone)]
pub struct IndexedHead {
    /// The parsed `.wsp` header.
    pub header: Header,
    /// The `.wsp` header section's bytes (what a packet decoder needs).
    pub header_bytes: Vec<u8>,
    /// Per packet, in file order; offsets are within the `.wsp`.
    pub packets: Vec<PacketMeta>,
    /// Where the `.wsp` starts in the object (add it to a packet's offset).
    pub wsp_offset: u64,
    /// Length of the `.wsp`.
    pub wsp_bytes: u64,
}

impl IndexedHead {
    /// Bytes of the whole object.
    pub fn object_bytes(&self) -> u64 {
        self.wsp_offset + self.wsp_bytes
    }

    /// Packet `i`'s byte range in the object.
    pub fn packet_range(&self, i: usize) -> Option<std::ops::Range<u64>> {
        let p = self.packets.get(i)?;
        let start = self.wsp_offset + p.offset;
        Some(start..start + p.len as u64)
    }
}

/// What reading the start of an object gave.
#[derive(Debug, Clone)]
pub enum HeadRead {
    /// The first `n` bytes of the object are needed (more than were given).
    Need(usize),
    /// The header and index.
    Indexed(Box<IndexedHead>),
    /// A bricked container's manifest and every brick's header and index.
    Bricked(Box<BrickedHead>),
    /// A series container's manifest and every component's bricks' headers and indexes.
    Series(Box<SeriesHead>),
}

/// One brick of a component of a published series: where it is, its header and packet index.
#[derive(Debug, Clone)]
pub struct SeriesBrick {
    /// Its component.
    pub component: usize,
    /// Its first voxel in the whole.
    pub origin: [u64; 3],
    /// Where its `.wsp` starts in the container.
    pub offset: u64,
    /// Its header and packets (offsets within its `.wsp`).
    pub brick: IndexedBrick,
}

/// A published series' head: the container's manifest and every component's bricks.
#[derive(Debug, Clone)]
pub struct SeriesHead {
    /// The manifest (component offsets are within the container).
    pub manifest: crate::format::series::SeriesManifest,
    /// Whether each component is a bricked container (else a plain `.wsp`, its one brick).
    pub bricked: Vec<bool>,
    /// Every component's bricks, component after component.
    pub bricks: Vec<SeriesBrick>,
    /// Where the container starts in the object.
    pub wsp_offset: u64,
    /// Length of the container.
    pub wsp_bytes: u64,
}

impl SeriesHead {
    /// Bytes of the whole object.
    pub fn object_bytes(&self) -> u64 {
        self.wsp_offset + self.wsp_bytes
    }
}

/// One brick of a published bricked volume: its header and packet index.
#[derive(Debug, Clone)]
pub struct IndexedBrick {
    /// The brick's parsed `.wsp` header (its geometry is the brick's).
    pub header: Header,
    /// Its `.wsp` header section's bytes.
    pub header_bytes: Vec<u8>,
    /// Per packet, in file order; offsets are within the brick's `.wsp`.
    pub packets: Vec<PacketMeta>,
}

/// A published bricked volume's head: the container's manifest, each brick's header and index.
#[derive(Debug, Clone)]
pub struct BrickedHead {
    /// The manifest (brick offsets are within the container).
    pub manifest: Manifest,
    /// The bricks, in manifest order.
    pub bricks: Vec<IndexedBrick>,
    /// Where the container starts in the object.
    pub wsp_offset: u64,
    /// Length of the container.
    pub wsp_bytes: u64,
}

impl BrickedHead {
    /// Bytes of the whole object.
    pub fn object_bytes(&self) -> u64 {
        self.wsp_offset + self.wsp_bytes
    }

    /// Where packet `i` of brick `brick` starts in the object (`None` past the last).
    pub fn packet_offset(&self, brick: usize, i: usize) -> Option<u64> {
        let p = self.bricks.get(brick)?.packets.get(i)?;
        Some(self.wsp_offset + self.manifest.bricks[brick].offset + p.offset)
    }
}

/// Largest `.wsp` an indexed head may declare (an exbibyte).
const MAX_WSP_BYTES: u64 = 1 << 60;

/// Reads an indexed volume's head from the first bytes of its object: the header and index, or
/// how many bytes from the start are needed for them.
pub fn read_indexed_head(bytes: &[u8]) -> Result<HeadRead, FormatError> {
    let n = bytes.len().min(4);
    if bytes[..n] != INDEXED_MAGIC[..n] {
        return Err(if bytes[..n] == MAGIC[..n] {
            invalid(
                "a plain .wsp file, not the indexed layout (`wavesplat publish` writes it)".into(),
            )
        } else {
            FormatError::BadMagic(bytes[..n].to_vec())
        });
    }
    if bytes.len() < INDEXED_HEAD_BYTES {
        return Ok(HeadRead::Need(INDEXED_HEAD_BYTES));
    }
    let mut r = ByteReader::new(&bytes[4..INDEXED_HEAD_BYTES], "indexed layout head");
    let version = r.u16()?;
    if !(INDEXED_VERSION..=SERIES_INDEXED_VERSION).contains(&version) {
        return Err(FormatError::UnsupportedVersion {
            found: version,
            supported: SERIES_INDEXED_VERSION,
        });
    }
    let wsp_bytes = r.u64()?;
    let index_len = r.u32()?;
    let stored = r.u32()?;
    if index_len > MAX_INDEX_BYTES {
        return Err(invalid(format!(
            "an index of {index_len} bytes (at most {MAX_INDEX_BYTES})"
        )));
    }
    // Bounded so that the object's length (index and .wsp) and every offset in it fit in u64:
    // the head's fields are not under the index's CRC.
    if wsp_bytes > MAX_WSP_BYTES {
        return Err(invalid(format!(
            "a .wsp of {wsp_bytes} bytes (at most {MAX_WSP_BYTES})"
        )));
    }
    let wsp_offset = INDEXED_HEAD_BYTES + index_len as usize;
    // The .wsp header section: magic, version u16, length u32, header, CRC.
    let section_start = wsp_offset;
    if bytes.len() < section_start + 10 {
        return Ok(HeadRead::Need(section_start + 10 + 4096));
    }
    let len_bytes: [u8; 4] = bytes[section_start + 6..section_start + 10]
        .try_into()
        .map_err(|_| invalid("header length".into()))?;
    let declared = u32::from_le_bytes(len_bytes);
    // Bounded before anything is fetched for it: a hostile length would ask for gigabytes.
    let declared = if version != INDEXED_VERSION {
        let (what, max) = if version == SERIES_INDEXED_VERSION {
            ("series manifest", crate::format::series::MAX_MANIFEST_BYTES)
        } else {
            ("bricked manifest", MAX_MANIFEST_BYTES)
        };
        if declared as usize > max {
            return Err(FormatError::TooLarge {
                what,
                size: declared as u64,
                limit: max as u64,
            });
        }
        declared as usize
    } else {
        crate::format::header::header_length(declared)?
    };
    let section = 14usize.saturating_add(declared);
    if section as u64 > wsp_bytes {
        return Err(invalid(format!(
            "a header section of {section} bytes in a .wsp of {wsp_bytes}"
        )));
    }
    let need = section_start + section;
    if bytes.len() < need {
        return Ok(HeadRead::Need(need));
    }
    let index = &bytes[INDEXED_HEAD_BYTES..wsp_offset];
    let computed = crc32fast::hash(index);
    if computed != stored {
        return Err(FormatError::Checksum {
            what: "packet index",
            stored,
            computed,
        });
    }
    if version == SERIES_INDEXED_VERSION {
        let manifest =
            crate::format::series::parse_manifest(&bytes[section_start..need], wsp_bytes)?;
        let (bricked, bricks) = decode_series_index(index, &manifest)?;
        return Ok(HeadRead::Series(Box::new(SeriesHead {
            manifest,
            bricked,
            bricks,
            wsp_offset: wsp_offset as u64,
            wsp_bytes,
        })));
    }
    if version == BRICKED_INDEXED_VERSION {
        let manifest = parse_manifest(&bytes[section_start..need], wsp_bytes)?;
        let bricks = decode_brick_index(index, &manifest)?;
        return Ok(HeadRead::Bricked(Box::new(BrickedHead {
            manifest,
            bricks,
            wsp_offset: wsp_offset as u64,
            wsp_bytes,
        })));
    }
    let packets = decode_compact(index)?;
    let (header, header_len) = read_header_section(&bytes[section_start..need])?;
    check_packets(&packets, header_len as u64, wsp_bytes)?;
    Ok(HeadRead::Indexed(Box::new(IndexedHead {
        header,
        header_bytes: bytes[section_start..section_start + header_len].to_vec(),
        packets,
        wsp_offset: wsp_offset as u64,
        wsp_bytes,
    })))
}

/// The bricks' headers and indexes of a bricked layout, each checked against its manifest
/// entry: as many bricks, each header's dimensions the entry's, its packets inside its bytes.
fn decode_brick_index(index: &[u8], manifest: &Manifest) -> Result<Vec<IndexedBrick>, FormatError> {
    let mut r = ByteReader::new(index, "bricked packet index");
    let n = r.varint_max(manifest.bricks.len() as u64, "bricks")? as usize;
    if n != manifest.bricks.len() {
        return Err(invalid(format!(
            "an index of {n} bricks for a manifest of {}",
            manifest.bricks.len()
        )));
    }
    let mut bricks = Vec::with_capacity(n);
    for (i, entry) in manifest.bricks.iter().enumerate() {
        let brick = read_brick_index(&mut r, index.len(), entry.length, &format!("brick {i}"))?;
        if brick.header.geometry.dims != entry.dims {
            return Err(invalid(format!(
                "brick {i}'s header has dimensions {:?}, the manifest {:?}",
                brick.header.geometry.dims, entry.dims
            )));
        }
        bricks.push(brick);
    }
    expect_end(&r)?;
    Ok(bricks)
}

/// The components' bricks of a series layout, each checked: as many components as the
/// manifest, each brick's `.wsp` inside its component, after the previous brick's, its header
/// inside the whole with the series' channels, its packets inside its bytes.
fn decode_series_index(
    index: &[u8],
    manifest: &crate::format::series::SeriesManifest,
) -> Result<(Vec<bool>, Vec<SeriesBrick>), FormatError> {
    let mut r = ByteReader::new(index, "series packet index");
    let n = r.varint_max(manifest.components.len() as u64, "components")? as usize;
    if n != manifest.components.len() {
        return Err(invalid(format!(
            "an index of {n} components for a manifest of {}",
            manifest.components.len()
        )));
    }
    let space = &manifest.space;
    let mut kinds = Vec::with_capacity(n);
    let mut bricks = Vec::new();
    for (c, entry) in manifest.components.iter().enumerate() {
        let bricked = match r.u8()? {
            0 => false,
            1 => true,
            k => return Err(invalid(format!("component {c} of kind {k}"))),
        };
        kinds.push(bricked);
        let count = r.varint_max(index.len() as u64, "bricks")? as usize;
        if count == 0 || (!bricked && count != 1) {
            return Err(invalid(format!("component {c} of {count} bricks")));
        }
        let mut end = 0u64;
        let mut boxes = Vec::with_capacity(count.min(1 << 16));
        for k in 0..count {
            let origin = [r.varint()?, r.varint()?, r.varint()?];
            let offset = r.varint()?;
            let length = r.varint()?;
            let stop = offset.checked_add(length);
            if offset < end || stop.is_none_or(|s| s > entry.length) || (!bricked && offset != 0) {
                return Err(invalid(format!(
                    "brick {k} of component {c} at {offset}..+{length} leaves its component \
                     of {} bytes or overlaps the previous brick",
                    entry.length
                )));
            }
            end = offset + length;
            let brick = read_brick_index(
                &mut r,
                index.len(),
                length,
                &format!("brick {k} of component {c}"),
            )?;
            let header = &brick.header;
            let inside = (0..3).all(|a| {
                origin[a]
                    .checked_add(header.geometry.dims[a] as u64)
                    .is_some_and(|e| e <= space.dims[a])
            });
            if !inside || header.channels != space.channels {
                return Err(invalid(format!(
                    "brick {k} of component {c} at {origin:?}, {:?} with {} channel(s), is not \
                     inside the series' {:?} with {}",
                    header.geometry.dims, header.channels, space.dims, space.channels
                )));
            }
            boxes.push((origin, header.geometry.dims));
            bricks.push(SeriesBrick {
                component: c,
                origin,
                offset: entry.offset + offset,
                brick,
            });
        }
        // The bricks (a plain component's one) tile the series' whole, as a bricked file's
        // manifest is checked.
        crate::format::bricked::check_tiling(space.dims, &boxes)
            .map_err(|e| invalid(format!("component {c}: {e}")))?;
    }
    expect_end(&r)?;
    Ok((kinds, bricks))
}

/// Reads one brick's entry of a bricked or series index (`what` names it in errors): its
/// header section, whose header must fill it, and its compact index, whose packets must lie
/// inside the brick's `length` bytes; lengths bounded by the index's `index_len`.
fn read_brick_index(
    r: &mut ByteReader<'_>,
    index_len: usize,
    length: u64,
    what: &str,
) -> Result<IndexedBrick, FormatError> {
    let len = r.varint_max(index_len as u64, "header length")? as usize;
    let section = r.take(len)?;
    let (header, header_len) = read_header_section(section)?;
    if header_len != len {
        return Err(invalid(format!(
            "{what}'s header section holds {len} bytes, its header {header_len}"
        )));
    }
    let packets_len = r.varint_max(index_len as u64, "index length")? as usize;
    let packets = decode_compact(r.take(packets_len)?)?;
    check_packets(&packets, header_len as u64, length)?;
    Ok(IndexedBrick {
        header,
        header_bytes: section.to_vec(),
        packets,
    })
}

/// Checks that packets lie after the header, inside the file, in order and without overlap.
fn check_packets(
    packets: &[PacketMeta],
    header_len: u64,
    wsp_bytes: u64,
) -> Result<(), FormatError> {
    let mut end = header_len;
    for (i, p) in packets.iter().enumerate() {
        let stop = p.offset.checked_add(p.len as u64);
        match stop {
            Some(stop) if p.offset >= end && stop <= wsp_bytes => end = stop,
            _ => {
                return Err(invalid(format!(
                    "packet {i} at {}..+{} does not follow packet {} or leaves the .wsp of {wsp_bytes} bytes",
                    p.offset,
                    p.len,
                    i.saturating_sub(1)
                )))
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn index_round_trips_and_rejects_junk() {
        let p = vec![PacketMeta {
            tile: 3,
            layer: 1,
            len: 99,
            offset: 1234,
            summary: vec![(Band { level: 2, kind: 5 }, 1.5)],
        }];
        assert_eq!(decode_packets(&encode_packets(&p), true).unwrap(), p);
        assert!(decode_packets(&[0xff], true).is_err());
        let mut trailing = encode_packets(&p);
        trailing.push(0);
        assert!(decode_packets(&trailing, true).is_err());
    }

    #[test]
    fn compact_index_round_trips_within_bfloat16_precision() {
        let p = |offset, len, e: f64| PacketMeta {
            tile: 7,
            layer: 2,
            len,
            offset,
            summary: vec![
                (Band { level: 3, kind: 7 }, e),
                (Band { level: 0, kind: 0 }, 0.0),
            ],
        };
        let packets = vec![p(100, 10, 1.2345e-7), p(110, 5, 9.87e12)];
        let back = decode_compact(&encode_compact(&packets).unwrap()).unwrap();
        for (a, b) in packets.iter().zip(&back) {
            assert_eq!(
                (a.tile, a.layer, a.len, a.offset),
                (b.tile, b.layer, b.len, b.offset)
            );
            for ((ba, ea), (bb, eb)) in a.summary.iter().zip(&b.summary) {
                assert_eq!(ba, bb);
                assert!((ea - eb).abs() <= ea.abs() * 4e-3, "{ea} {eb}");
            }
        }
        assert!(
            encode_compact(&[p(100, 10, 1.0), p(111, 5, 1.0)]).is_err(),
            "a gap"
        );
        let mut trailing = encode_compact(&packets).unwrap();
        trailing.push(0);
        assert!(decode_compact(&trailing).is_err());
    }

    #[test]
    fn packets_must_lie_in_order_inside_the_file() {
        let at = |offset, len| PacketMeta {
            tile: 0,
            layer: 0,
            len,
            offset,
            summary: vec![],
        };
        assert!(check_packets(&[at(20, 10), at(30, 5)], 20, 35).is_ok());
        assert!(
            check_packets(&[at(10, 10)], 20, 35).is_err(),
            "inside the header"
        );
        assert!(
            check_packets(&[at(20, 10), at(25, 5)], 20, 35).is_err(),
            "overlap"
        );
        assert!(
            check_packets(&[at(30, 10)], 20, 35).is_err(),
            "past the end"
        );
        assert!(
            check_packets(&[at(u64::MAX, 10)], 20, 35).is_err(),
            "overflow"
        );
    }

    #[test]
    fn head_asks_for_what_it_lacks_and_refuses_plain_files() {
        assert!(
            matches!(read_indexed_head(b"WS"), Ok(HeadRead::Need(n)) if n == INDEXED_HEAD_BYTES)
        );
        let e = read_indexed_head(b"WSPL\x07\x00").unwrap_err().to_string();
        assert!(e.contains("wavesplat publish"), "{e}");
        assert!(matches!(
            read_indexed_head(b"GIF8"),
            Err(FormatError::BadMagic(_))
        ));
        let prefix = indexed_prefix(100, &[]).unwrap();
        assert!(matches!(read_indexed_head(&prefix), Ok(HeadRead::Need(_))));
        // A declared .wsp length past any real one (the head is not under the CRC) is
        // refused before any sum with it can overflow.
        let huge = indexed_prefix(u64::MAX, &[]).unwrap();
        let e = read_indexed_head(&huge).unwrap_err().to_string();
        assert!(e.contains("18446744073709551615"), "{e}");
        let mut bad = prefix.clone();
        bad[4] = 9;
        assert!(matches!(
            read_indexed_head(&bad),
            Err(FormatError::UnsupportedVersion { found: 9, .. })
        ));
    }
}
