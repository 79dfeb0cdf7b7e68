//! Domain types of the cache, independent of gRPC and sled: which volume a request names, the
//! stored facts about a volume, and the per-packet index (tile, layer, size and energy summary)
//! the priority math works on. Also the compact binary encoding of these records in the store
//! (bounds-checked reads through the codec's byte reader, so a corrupt entry is an error).

use crate::error::CacheError;
use wavesplat_codec::format::bricked::{parse_manifest, Manifest};
use wavesplat_codec::format::bytes::{ByteReader, ByteWriter};
use wavesplat_codec::format::series::SeriesManifest;
use wavesplat_codec::format::{read_header_section, Header};

pub use wavesplat_net::VolumeKey;

/// Longest volume name (bytes): the store validates names against it, and the bucket's keys
/// are laid out for names up to it.
pub const MAX_NAME_BYTES: usize = 255;

/// Facts about a stored volume (the commit record of an ingest).
#[derive(Debug, Clone, PartialEq)]
pub struct VolumeMeta {
    /// Store-assigned id.
    pub id: u64,
    /// The name the volume was asked for by (its first name when listed by id).
    pub name: String,
    /// Every name of the volume, in the order they were given (identical content ingested
    /// under another name adds a name; deleting a name removes it, the last one the volume).
    pub names: Vec<String>,
    /// SHA-256 of the uploaded file.
    pub sha256: [u8; 32],
    /// Creation time (ms since the Unix epoch).
    pub created_unix_ms: u64,
    /// Size of the file.
    pub file_bytes: u64,
    /// Size of the header section.
    pub header_bytes: u64,
    /// Sum of packet sizes.
    pub packet_bytes: u64,
    /// Volume dimensions.
    pub dims: [u32; 3],
    /// Channels.
    pub channels: u32,
    /// Wavelet family name.
    pub family: String,
    /// Decomposition depth.
    pub levels: u32,
    /// Packets.
    pub packet_count: u32,
    /// Tiles.
    pub tile_count: u32,
    /// Quality layers.
    pub layer_count: u32,
    /// Tile edge (padded-grid voxels).
    pub tile: u32,
    /// Coefficients kept in the file.
    pub coefficients: u64,
}

impl VolumeMeta {
    /// A volume's record from its header and index.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn from_header(
        id: u64,
        names: Vec<String>,
        sha256: [u8; 32],
        created_unix_ms: u64,
        file_bytes: u64,
        header: &wavesplat_codec::format::Header,
        header_bytes: usize,
        packets: &[PacketMeta],
    ) -> VolumeMeta {
        let h = header;
        VolumeMeta {
            id,
            name: names.first().cloned().unwrap_or_default(),
            names,
            sha256,
            created_unix_ms,
            file_bytes,
            header_bytes: header_bytes as u64,
            packet_bytes: packets.iter().map(|p| p.len as u64).sum(),
            dims: h.geometry.dims.map(|d| d as u32),
            channels: h.channels as u32,
            family: h.geometry.family.name().to_string(),
            levels: h.geometry.levels as u32,
            packet_count: packets.len() as u32,
            tile_count: h.tile_count() as u32,
            layer_count: h.layer_bounds.len() as u32,
            tile: h.tile as u32,
            coefficients: h.kept,
        }
    }

    /// Makes a record made from a bricked volume's whole header (`from_header`) describe its
    /// bricks: their levels, tiles and coefficients, and the header bytes of the manifest
    /// section (`section_bytes`) and every brick.
    /// (A series' record: the bricks of every component, and the coefficients of all.)
    pub(crate) fn describe_bricks(
        &mut self,
        section_bytes: usize,
        bricks: &[IndexBrick],
        kept: u64,
    ) {
        let first = &bricks[0].header;
        self.levels = first.geometry.levels as u32;
        self.tile_count = bricks
            .iter()
            .map(|k| k.header.tile_count() as u64)
            .sum::<u64>()
            .min(u64::from(u32::MAX)) as u32;
        self.coefficients = kept;
        self.header_bytes = section_bytes as u64
            + bricks
                .iter()
                .map(|k| k.header_bytes.len() as u64)
                .sum::<u64>();
    }

    /// SHA-256 as lower-case hex.
    pub fn sha256_hex(&self) -> String {
        wavesplat_net::digest::hex(&self.sha256)
    }

    /// This record as seen through one of its names.
    pub fn named(mut self, name: &str) -> VolumeMeta {
        name.clone_into(&mut self.name);
        self
    }

    pub(crate) fn encode(&self) -> Vec<u8> {
        let mut w = ByteWriter::new();
        w.u8(2); // record version
        w.u64(self.id);
        w.varint(self.names.len() as u64);
        for n in &self.names {
            w.varint(n.len() as u64);
            w.bytes(n.as_bytes());
        }
        w.bytes(&self.sha256);
        for v in [
            self.created_unix_ms,
            self.file_bytes,
            self.header_bytes,
            self.packet_bytes,
            self.coefficients,
        ] {
            w.u64(v);
        }
        for v in [
            self.dims[0],
            self.dims[1],
            self.dims[2],
            self.channels,
            self.levels,
            self.packet_count,
            self.tile_count,
            self.layer_count,
            self.tile,
        ] {
            w.u32(v);
        }
        w.varint(self.family.len() as u64);
        w.bytes(self.family.as_bytes());
        w.into_bytes()
    }

    pub(crate) fn decode(bytes: &[u8]) -> Result<VolumeMeta, CacheError> {
        let corrupt = |e: wavesplat_codec::format::FormatError| {
            CacheError::Corrupt(format!("volume record: {e}"))
        };
        let mut r = ByteReader::new(bytes, "volume record");
        let version = r.u8().map_err(corrupt)?;
        if version != 1 && version != 2 {
            return Err(CacheError::Corrupt(format!(
                "volume record version {version}, expected 1 or 2"
            )));
        }
        let id = r.u64().map_err(corrupt)?;
        // Version 1 has one name; version 2 a list.
        let count = if version == 1 {
            1
        } else {
            r.varint_max(1 << 20, "name count").map_err(corrupt)? as usize
        };
        let mut names = Vec::with_capacity(count.min(r.remaining()));
        for _ in 0..count {
            let n = r.varint_max(4096, "name length").map_err(corrupt)? as usize;
            names.push(string(r.take(n).map_err(corrupt)?)?);
        }
        let name = names
            .first()
            .cloned()
            .ok_or_else(|| CacheError::Corrupt("volume record without a name".into()))?;
        let mut sha256 = [0u8; 32];
        sha256.copy_from_slice(r.take(32).map_err(corrupt)?);
        let mut u64s = [0u64; 5];
        for v in &mut u64s {
            *v = r.u64().map_err(corrupt)?;
        }
        let mut u32s = [0u32; 9];
        for v in &mut u32s {
            *v = r.u32().map_err(corrupt)?;
        }
        let n = r.varint_max(64, "family length").map_err(corrupt)? as usize;
        let family = string(r.take(n).map_err(corrupt)?)?;
        Ok(VolumeMeta {
            id,
            name,
            names,
            sha256,
            created_unix_ms: u64s[0],
            file_bytes: u64s[1],
            header_bytes: u64s[2],
            packet_bytes: u64s[3],
            coefficients: u64s[4],
            dims: [u32s[0], u32s[1], u32s[2]],
            channels: u32s[3],
            levels: u32s[4],
            packet_count: u32s[5],
            tile_count: u32s[6],
            layer_count: u32s[7],
            tile: u32s[8],
            family,
        })
    }
}

fn string(b: &[u8]) -> Result<String, CacheError> {
    String::from_utf8(b.to_vec()).map_err(|_| CacheError::Corrupt("non-UTF-8 string".into()))
}

pub use wavesplat_codec::format::index::PacketMeta;

/// A volume's decoded header and its packet index (packet id = index in file order). The
/// store's encoding of the index (with the packets' offsets) is its own tree's format.
#[derive(Debug, Clone)]
pub struct VolumeIndex {
    /// The parsed header (a bricked volume's: the whole's, for views and listings).
    pub header: Header,
    /// The header section bytes (what clients need to decode packets); a bricked volume's:
    /// its container's manifest section.
    pub header_bytes: Vec<u8>,
    /// Per packet, in file order (a bricked volume's: brick after brick, offsets from the
    /// container's start).
    pub packets: Vec<PacketMeta>,
    /// A bricked volume's bricks.
    pub bricked: Option<Box<BrickedIndex>>,
    /// A time series' components and their bricks (its `header` is its time point 0's).
    pub series: Option<Box<SeriesIndex>>,
}

impl VolumeIndex {
    /// The bricks of a bricked volume or of every component of a series, in packet order
    /// (`None` for one volume).
    pub fn bricks(&self) -> Option<&[IndexBrick]> {
        match (&self.bricked, &self.series) {
            (Some(b), _) => Some(&b.bricks),
            (None, Some(s)) => Some(&s.bricks),
            (None, None) => None,
        }
    }

    /// The brick packet `id` belongs to (0 for one volume).
    pub fn brick_of(&self, id: u32) -> usize {
        self.bricks().map_or(0, |bricks| {
            bricks
                .partition_point(|k| k.first_packet <= id)
                .saturating_sub(1)
        })
    }

    /// Time points (1 for a volume that is not a series).
    pub fn time_points(&self) -> usize {
        self.series.as_ref().map_or(1, |s| s.manifest.points.len())
    }
}

/// A time series as the store keeps it: its manifest and every component's bricks (a plain
/// component is one brick of the whole's size at the origin), component after component.
#[derive(Debug, Clone)]
pub struct SeriesIndex {
    /// The parsed series manifest.
    pub manifest: SeriesManifest,
    /// Every component's bricks, in component order; packets numbered brick after brick.
    pub bricks: Vec<IndexBrick>,
    /// Each component's bricks (a range of `bricks`).
    pub components: Vec<std::ops::Range<usize>>,
    /// Whether each component is a bricked container (else a plain `.wsp`, its one brick).
    pub bricked: Vec<bool>,
}

impl SeriesIndex {
    /// The header time points are drawn with: component 0's whole header (a bricked one's
    /// made as [`wavesplat_codec::view::bricked::whole_header`] makes it) with the series'
    /// placement, as [`wavesplat_codec::view::bricked::series_header`] makes it from the file.
    pub fn whole_header(&self) -> Result<Header, wavesplat_codec::format::FormatError> {
        wavesplat_codec::view::bricked::series_brick_header(
            &self.manifest.space,
            self.bricks[self.components[0].start].header.clone(),
            self.bricked[0],
        )
    }

    /// The component brick `brick` belongs to.
    pub fn component_of(&self, brick: usize) -> usize {
        self.components
            .partition_point(|r| r.start <= brick)
            .saturating_sub(1)
    }
}

/// Encodes a series' bricks: per component its brick count, per brick its origin, header and
/// packet count (the series manifest is stored on its own).
pub(crate) fn encode_series(s: &SeriesIndex) -> Vec<u8> {
    let mut w = ByteWriter::new();
    w.u8(2); // record version (1: a bricked volume's, `encode_bricks`)
    w.u32(s.components.len() as u32);
    for (r, bricked) in s.components.iter().zip(&s.bricked) {
        w.u32(r.len() as u32);
        w.u8(u8::from(*bricked));
    }
    for b in &s.bricks {
        for o in b.origin {
            w.u64(o);
        }
        write_brick(&mut w, b);
    }
    w.into_bytes()
}

/// Decodes what [`encode_series`] wrote for the series of `manifest_section` (of a container of
/// `file_bytes` bytes), checking the counts against the manifest.
pub(crate) fn decode_series(
    manifest_section: &[u8],
    file_bytes: u64,
    bytes: &[u8],
) -> Result<SeriesIndex, CacheError> {
    let corrupt = |e: String| CacheError::Corrupt(format!("stored series: {e}"));
    let manifest = wavesplat_codec::format::series::parse_manifest(manifest_section, file_bytes)
        .map_err(|e| corrupt(e.to_string()))?;
    let mut r = ByteReader::new(bytes, "stored series");
    let version = r.u8()?;
    if version != 2 {
        return Err(corrupt(format!("record version {version}")));
    }
    let n = r.u32()? as usize;
    if n != manifest.components.len() {
        return Err(corrupt(format!(
            "{n} components for a manifest of {}",
            manifest.components.len()
        )));
    }
    let mut components = Vec::with_capacity(n);
    let mut bricked = Vec::with_capacity(n);
    let mut at = 0usize;
    for _ in 0..n {
        let count = r.u32()? as usize;
        if count == 0 || count > bytes.len() {
            return Err(corrupt(format!("a component of {count} bricks")));
        }
        components.push(at..at + count);
        bricked.push(match r.u8()? {
            0 => false,
            1 => true,
            f => return Err(corrupt(format!("component kind {f}"))),
        });
        at += count;
    }
    let mut bricks = Vec::with_capacity(at.min(bytes.len()));
    let mut first_packet = 0u32;
    for _ in 0..at {
        let origin = [r.u64()?, r.u64()?, r.u64()?];
        bricks.push(read_brick(&mut r, origin, &mut first_packet, &corrupt)?);
    }
    Ok(SeriesIndex {
        manifest,
        bricks,
        components,
        bricked,
    })
}

/// The bricks of a bricked volume as the store keeps them: the manifest and each brick's header.
#[derive(Debug, Clone)]
pub struct BrickedIndex {
    /// The parsed manifest.
    pub manifest: Manifest,
    /// Each brick, in manifest order.
    pub bricks: Vec<IndexBrick>,
}

/// One brick of a stored bricked volume.
#[derive(Debug, Clone)]
pub struct IndexBrick {
    /// Its header.
    pub header: Header,
    /// Its header section bytes (what clients decode its packets with).
    pub header_bytes: Vec<u8>,
    /// Its first voxel in the whole.
    pub origin: [u64; 3],
    /// The volume-wide id of its first packet.
    pub first_packet: u32,
    /// Its packets.
    pub packets: u32,
}

/// One stored brick: its header section (length and bytes) and its packet count.
fn write_brick(w: &mut ByteWriter, b: &IndexBrick) {
    w.u32(b.header_bytes.len() as u32);
    w.bytes(&b.header_bytes);
    w.u32(b.packets);
}

/// Reads what [`write_brick`] wrote, for a brick at `origin` whose packets are numbered from
/// `first_packet` (advanced past them).
fn read_brick(
    r: &mut ByteReader<'_>,
    origin: [u64; 3],
    first_packet: &mut u32,
    corrupt: &dyn Fn(String) -> CacheError,
) -> Result<IndexBrick, CacheError> {
    let len = r.u32()? as usize;
    let header_bytes = r.take(len)?.to_vec();
    let (header, _) = read_header_section(&header_bytes).map_err(|e| corrupt(e.to_string()))?;
    let packets = r.u32()?;
    let brick = IndexBrick {
        header,
        header_bytes,
        origin,
        first_packet: *first_packet,
        packets,
    };
    *first_packet = first_packet
        .checked_add(packets)
        .ok_or_else(|| corrupt("more than 2^32 packets".into()))?;
    Ok(brick)
}

/// Encodes the bricks' headers and packet counts (the manifest is stored on its own).
pub(crate) fn encode_bricks(bricks: &[IndexBrick]) -> Vec<u8> {
    let mut w = ByteWriter::new();
    w.u8(1); // record version
    w.u32(bricks.len() as u32);
    for b in bricks {
        write_brick(&mut w, b);
    }
    w.into_bytes()
}

/// Decodes what [`encode_bricks`] wrote for the volume of `manifest` (the manifest section of a
/// container of `file_bytes` bytes), checking the bricks against the manifest.
pub(crate) fn decode_bricks(
    manifest_section: &[u8],
    file_bytes: u64,
    bytes: &[u8],
) -> Result<BrickedIndex, CacheError> {
    let corrupt = |e: String| CacheError::Corrupt(format!("stored bricks: {e}"));
    let manifest =
        parse_manifest(manifest_section, file_bytes).map_err(|e| corrupt(e.to_string()))?;
    let mut r = ByteReader::new(bytes, "stored bricks");
    let version = r.u8()?;
    if version != 1 {
        return Err(corrupt(format!("record version {version}")));
    }
    let n = r.u32()? as usize;
    if n != manifest.bricks.len() {
        return Err(corrupt(format!(
            "{n} bricks for a manifest of {}",
            manifest.bricks.len()
        )));
    }
    let mut bricks = Vec::with_capacity(n);
    let mut first_packet = 0u32;
    for entry in &manifest.bricks {
        bricks.push(read_brick(
            &mut r,
            entry.origin,
            &mut first_packet,
            &corrupt,
        )?);
    }
    Ok(BrickedIndex { manifest, bricks })
}

/// Encodes a packet index.
pub(crate) fn encode_packets(packets: &[PacketMeta]) -> Vec<u8> {
    wavesplat_codec::format::index::encode_packets(packets)
}

/// Decodes a packet index (`with_offsets`: the current form; without, the form of stores that
/// kept packets in sled, read once to migrate them).
pub(crate) fn decode_packets(
    bytes: &[u8],
    with_offsets: bool,
) -> Result<Vec<PacketMeta>, CacheError> {
    wavesplat_codec::format::index::decode_packets(bytes, with_offsets)
        .map_err(|e| CacheError::Corrupt(format!("packet index: {e}")))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn records_round_trip() {
        let m = VolumeMeta {
            id: 7,
            name: "brain".into(),
            names: vec!["brain".into(), "copy".into()],
            sha256: [3; 32],
            created_unix_ms: 1,
            file_bytes: 2,
            header_bytes: 3,
            packet_bytes: 4,
            dims: [5, 6, 7],
            channels: 1,
            family: "cubic".into(),
            levels: 3,
            packet_count: 9,
            tile_count: 8,
            layer_count: 2,
            tile: 16,
            coefficients: 100,
        };
        assert_eq!(VolumeMeta::decode(&m.encode()).unwrap(), m);
        // A version-1 record (one name, no count) still reads.
        let one = VolumeMeta {
            names: vec!["brain".into()],
            ..m.clone()
        };
        let mut v1 = one.encode();
        assert_eq!((v1[0], v1[9]), (2, 1));
        v1[0] = 1;
        v1.remove(9);
        assert_eq!(VolumeMeta::decode(&v1).unwrap(), one);
        assert!(VolumeMeta::decode(&m.encode()[..20]).is_err());
        // The packet index's encoding is the codec's (tested there); a corrupt one is an error.
        assert!(decode_packets(&[0xff], true).is_err());
    }
}
