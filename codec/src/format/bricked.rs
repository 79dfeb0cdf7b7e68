//! The bricked container (format version 11, and 9 read): one logical volume stored as
//! bricks, each a complete `.wsp` file of its own (a plain file: its own transform, header
//! and packets), behind a manifest that places every brick inside the whole. A volume larger
//! than one process can transform is compressed brick by brick (and brick jobs run on any
//! worker), while readers still see one volume: its dimensions, spacing and placement are the
//! manifest's; each brick's header holds the brick's own. Bricks tile the whole without
//! overlap, so an image of the whole (linear in the data) is the sum of the bricks' images,
//! each clipped to its own box.
//!
//! Layout: magic `WSPL`, version (u16), manifest length (u32), the manifest, its CRC-32, then
//! the bricks' bytes in manifest order. The manifest holds the whole's dimensions, channels,
//! spacing and placement, the brick edge and the brick count, then one entry per brick:
//! - version 11 (written): the bricks are the grid of the brick edge ([`brick_grid`], x
//!   fastest) in that order, their bytes back to back, so an entry is only the brick's length
//!   (40 bits), CRC-32 and count kept (40 bits), 14 bytes;
//! - version 9 (the first, still read): each entry places its brick explicitly (origin,
//!   dimensions, offset, length, CRC, count), 64 bytes, and any tiling is accepted.
//!
//! On MNI in 64³ bricks at 87 kB the compact manifest is 2.4 kB smaller (of the file's 3 %).
//! A build that reads versions up to 8 refuses either as "written by a newer wavesplat"
//! ([`FormatError::UnsupportedVersion`]); one that reads version 9 only refuses version 11 the
//! same way. A plain (unbricked) volume is still written as a plain file, so every existing
//! file, figure and reader stays valid. The manifest is untrusted input like the rest: counts,
//! sizes, offsets and the tiling are checked before anything is allocated from them, and each
//! brick's bytes carry a CRC-32 checked when the brick is taken
//! ([`BrickedFile::brick_bytes`]).

use super::bytes::{ByteReader, ByteWriter};
use super::{FormatError, Header, MAGIC};
use crate::volume::Placement;

/// The format version of the bricked containers this build writes: the compact manifest
/// (bricks on the grid of [`brick_grid`], entries of length, CRC and count only).
pub const BRICKED_VERSION: u16 = 11;

/// The first bricked container's version, still read: every entry places its brick (origin,
/// dimensions, offset) explicitly, 64 bytes each.
pub const EXPLICIT_BRICKED_VERSION: u16 = 9;

/// Bytes of a compact manifest's entry: length (40 bits), CRC-32, count kept (40 bits). Fixed
/// widths keep the manifest's length known before any brick is coded (what a byte target sets
/// aside).
const COMPACT_ENTRY_BYTES: usize = 5 + 4 + 5;

/// Largest brick length or count a compact entry holds (40 bits).
pub const MAX_COMPACT_FIELD: u64 = (1 << 40) - 1;

/// Most bricks one container may hold (a 8192³ volume in 256³ bricks has 32 768).
pub const MAX_BRICKS: usize = 1 << 20;

/// Largest accepted manifest (bytes).
pub const MAX_MANIFEST_BYTES: usize = 64 << 20;

/// The smallest brick edge a bricked volume is split with: below it the per-brick header and
/// the cut supports cost more than a brick saves.
pub const MIN_BRICK: usize = 8;

/// Largest side of the whole volume along one axis.
pub const MAX_SIDE: u64 = 1 << 20;

/// Where one brick lies in the whole and where its bytes are.
#[derive(Debug, Clone, PartialEq)]
pub struct BrickEntry {
    /// Its first voxel in the whole (x, y, z).
    pub origin: [u64; 3],
    /// Its dimensions.
    pub dims: [usize; 3],
    /// Offset of its `.wsp` bytes from the start of the container.
    pub offset: u64,
    /// Length of its `.wsp` bytes.
    pub length: u64,
    /// CRC-32 of those bytes.
    pub crc: u32,
    /// Coefficients it keeps (its header's count, for listings and budgets).
    pub kept: u64,
}

/// What describes the whole volume.
#[derive(Debug, Clone, PartialEq)]
pub struct Manifest {
    /// The whole volume's dimensions.
    pub dims: [u64; 3],
    /// Channels (every brick has as many).
    pub channels: usize,
    /// Voxel spacing (every brick has the same).
    pub spacing: [f32; 3],
    /// Placement of the whole in patient space (voxel (0, 0, 0) of the whole).
    pub placement: Option<Placement>,
    /// The nominal brick edge the volume was split with (bricks may be smaller: each axis is
    /// split into near-equal parts no longer than this).
    pub brick: usize,
    /// The bricks, in the order their bytes follow the manifest.
    pub bricks: Vec<BrickEntry>,
    /// The container's format version: [`BRICKED_VERSION`] (bricks on the grid, compact
    /// entries) or [`EXPLICIT_BRICKED_VERSION`] (explicit entries), as read or to be written.
    pub version: u16,
}

impl Manifest {
    /// Voxels of the whole (may exceed what one process transforms).
    pub fn voxels(&self) -> u128 {
        self.dims.iter().map(|d| *d as u128).product()
    }

    /// Coefficients kept over all bricks.
    pub fn kept(&self) -> u64 {
        // Saturating: the entries' counts are the file's word, not checked against the bricks.
        self.bricks.iter().fold(0, |t, b| t.saturating_add(b.kept))
    }
}

/// A parsed bricked container: the manifest and the bytes it indexes.
#[derive(Debug)]
pub struct BrickedFile<'a> {
    /// The manifest.
    pub manifest: Manifest,
    bytes: &'a [u8],
}

impl<'a> BrickedFile<'a> {
    /// The `.wsp` bytes of brick `i`, checked against their CRC.
    pub fn brick_bytes(&self, i: usize) -> Result<&'a [u8], FormatError> {
        let b = self
            .manifest
            .bricks
            .get(i)
            .ok_or_else(|| FormatError::Invalid {
                what: "bricked manifest",
                detail: format!("no brick {i}"),
            })?;
        // In range: checked by `parse_bricked`.
        let data = &self.bytes[b.offset as usize..(b.offset + b.length) as usize];
        let computed = crc32fast::hash(data);
        if computed != b.crc {
            return Err(FormatError::Checksum {
                what: "brick",
                stored: b.crc,
                computed,
            });
        }
        Ok(data)
    }
}

impl BrickedFile<'_> {
    /// Every brick's header and the length of its header section, in grid order (each brick
    /// checked against its CRC).
    pub fn brick_headers(&self) -> Result<Vec<(Header, usize)>, FormatError> {
        (0..self.manifest.bricks.len())
            .map(|i| super::read_header_section(self.brick_bytes(i)?))
            .collect()
    }

    /// What the container spends outside its bricks' packets: the manifest's section and every
    /// brick's header section (which carries the fast coder's tables, where used), in bytes,
    /// given the bricks' headers ([`BrickedFile::brick_headers`]).
    pub fn overhead_bytes(&self, headers: &[(Header, usize)]) -> u64 {
        let bricks: u64 = self.manifest.bricks.iter().map(|b| b.length).sum();
        let sections: u64 = headers.iter().map(|(_, used)| *used as u64).sum();
        (self.bytes.len() as u64).saturating_sub(bricks) + sections
    }
}

/// The section a container of format `version` starts with: magic, version, the manifest's
/// length (u32), the manifest `mb`, its CRC-32.
pub(super) fn write_section(version: u16, mb: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(4 + 2 + 4 + mb.len() + 4);
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&version.to_le_bytes());
    out.extend_from_slice(&(mb.len() as u32).to_le_bytes());
    out.extend_from_slice(mb);
    out.extend_from_slice(&crc32fast::hash(mb).to_le_bytes());
    out
}

/// Reads what [`write_section`] wrote at the start of `bytes`, refusing another magic or
/// version than `versions` (the first is the one this build writes), a manifest longer than
/// `max` and a CRC that does not match (`what` names the manifest); returns the manifest's
/// bytes, where the data after the section starts, and the version found.
pub(super) fn read_section<'a>(
    bytes: &'a [u8],
    versions: &[u16],
    max: usize,
    what: &'static str,
) -> Result<(&'a [u8], u64, u16), FormatError> {
    let mut r = ByteReader::new(bytes, what);
    let found = super::read_magic_and_version(&mut r, bytes)?;
    if !versions.contains(&found) {
        return Err(FormatError::UnsupportedVersion {
            found,
            supported: versions[0],
        });
    }
    let len = r.u32()? as usize;
    if len > max {
        return Err(FormatError::TooLarge {
            what,
            size: len as u64,
            limit: max as u64,
        });
    }
    let mb = r.take(len)?;
    let stored = r.u32()?;
    let computed = crc32fast::hash(mb);
    if stored != computed {
        return Err(FormatError::Checksum {
            what,
            stored,
            computed,
        });
    }
    Ok((mb, r.position() as u64, found))
}

/// Whether `version` is a bricked container's.
pub fn is_bricked_version(version: u16) -> bool {
    version == BRICKED_VERSION || version == EXPLICIT_BRICKED_VERSION
}

/// Whether `bytes` start as a bricked container (magic and version 9 or 11).
pub fn is_bricked(bytes: &[u8]) -> bool {
    bytes.len() >= 6
        && &bytes[..4] == MAGIC
        && is_bricked_version(u16::from_le_bytes([bytes[4], bytes[5]]))
}

/// The near-equal split of `len` voxels into parts of at most `brick`: ⌈len/brick⌉ parts
/// whose sizes differ by at most one (so no part is a sliver: a 257-voxel axis in 256-voxel
/// bricks is 129 + 128, not 256 + 1, whose one-voxel brick would have no wavelet level).
/// Returns (start, size) per part.
pub fn split_axis(len: u64, brick: usize) -> Vec<(u64, usize)> {
    let brick = brick.max(1) as u64;
    let parts = len.div_ceil(brick).max(1);
    let base = len / parts;
    let extra = len % parts;
    let mut out = Vec::with_capacity(parts as usize);
    let mut start = 0;
    for p in 0..parts {
        let size = base + u64::from(p < extra);
        out.push((start, size as usize));
        start += size;
    }
    out
}

/// Whether a volume of `dims` split with edge `brick` can be a bricked file: the edge and every
/// side at most [`MAX_SIDE`], at most [`MAX_BRICKS`] bricks. Checked before [`brick_grid`] is
/// made (a tiny edge over a huge volume would be billions of bricks); the error says why.
pub fn check_bricking(dims: [u64; 3], brick: usize) -> Result<(), String> {
    if brick == 0 || brick as u64 > MAX_SIDE {
        return Err(format!(
            "brick edge {brick}; allowed 1..={MAX_SIDE} (a brick as large as the volume is \
             the volume itself: leave out --brick)"
        ));
    }
    if let Some(d) = dims.iter().find(|&&d| d == 0 || d > MAX_SIDE) {
        return Err(format!(
            "a side of {d} voxels; a bricked volume's sides are 1..={MAX_SIDE} voxels"
        ));
    }
    let count: u128 = dims
        .iter()
        .map(|&d| u128::from(d.div_ceil(brick as u64).max(1)))
        .product();
    if count > MAX_BRICKS as u128 {
        return Err(format!(
            "{count} bricks of edge {brick} for {}x{}x{} voxels; at most {MAX_BRICKS}: give a \
             larger brick edge",
            dims[0], dims[1], dims[2]
        ));
    }
    Ok(())
}

/// The bricks of a volume of `dims` split with edge `brick`: (origin, dims) in x-fastest
/// order, the order [`write_bricked`] expects.
pub fn brick_grid(dims: [u64; 3], brick: usize) -> Vec<([u64; 3], [usize; 3])> {
    let [xs, ys, zs] = dims.map(|d| split_axis(d, brick));
    let mut out = Vec::with_capacity(xs.len() * ys.len() * zs.len());
    for (z0, dz) in &zs {
        for (y0, dy) in &ys {
            for (x0, dx) in &xs {
                out.push(([*x0, *y0, *z0], [*dx, *dy, *dz]));
            }
        }
    }
    out
}

/// Writes a container: `manifest` (whose entries' `offset`, `length` and `crc` are filled in
/// here) followed by `bricks`, one `.wsp` file each in manifest order.
pub fn write_bricked(manifest: &mut Manifest, bricks: &[&[u8]]) -> Result<Vec<u8>, FormatError> {
    let placed: Vec<(u64, u32)> = bricks
        .iter()
        .map(|b| (b.len() as u64, crc32fast::hash(b)))
        .collect();
    let section = place_bricks(manifest, &placed)?;
    let total = section.len() + placed.iter().map(|p| p.0 as usize).sum::<usize>();
    let mut out = Vec::with_capacity(total);
    out.extend_from_slice(&section);
    for b in bricks {
        out.extend_from_slice(b);
    }
    Ok(out)
}

/// Fills in `manifest`'s offsets, lengths and CRCs for bricks of (length, CRC-32) `bricks` in
/// manifest order, and returns the manifest section the container starts with: the bricks'
/// bytes follow it, in that order. (What [`write_bricked`] does for bytes in memory, for a
/// writer that streams the bricks from elsewhere.)
pub fn place_bricks(
    manifest: &mut Manifest,
    bricks: &[(u64, u32)],
) -> Result<Vec<u8>, FormatError> {
    if bricks.len() != manifest.bricks.len() {
        return Err(FormatError::Invalid {
            what: "bricked manifest",
            detail: format!(
                "{} bricks for {} manifest entries",
                bricks.len(),
                manifest.bricks.len()
            ),
        });
    }
    if manifest.version == BRICKED_VERSION {
        let grid = brick_grid(manifest.dims, manifest.brick);
        let on_grid = grid.len() == manifest.bricks.len()
            && grid
                .iter()
                .zip(&manifest.bricks)
                .all(|(g, e)| g.0 == e.origin && g.1 == e.dims);
        if !on_grid {
            return Err(bad(
                "a compact manifest's bricks must be the grid of its brick edge, in order",
            ));
        }
        if let Some((len, _)) = bricks.iter().find(|b| b.0 > MAX_COMPACT_FIELD) {
            return Err(bad(format!(
                "a brick of {len} bytes; at most {MAX_COMPACT_FIELD}"
            )));
        }
        if let Some(e) = manifest.bricks.iter().find(|e| e.kept > MAX_COMPACT_FIELD) {
            return Err(bad(format!("a brick keeping {} coefficients", e.kept)));
        }
    } else if manifest.version != EXPLICIT_BRICKED_VERSION {
        return Err(FormatError::UnsupportedVersion {
            found: manifest.version,
            supported: BRICKED_VERSION,
        });
    }
    // Offsets depend on the manifest's length, which does not depend on their values (fixed
    // width fields).
    let manifest_len = manifest_bytes(manifest).len();
    let mut offset = (4 + 2 + 4 + manifest_len + 4) as u64;
    for (e, (len, crc)) in manifest.bricks.iter_mut().zip(bricks) {
        e.offset = offset;
        e.length = *len;
        e.crc = *crc;
        offset += len;
    }
    let section = manifest_section(manifest);
    debug_assert_eq!(section.len(), 4 + 2 + 4 + manifest_len + 4);
    Ok(section)
}

/// The manifest section a container of `manifest` starts with (magic, version, manifest
/// length, manifest, CRC-32): what [`parse_manifest`] reads, byte for byte as
/// [`write_bricked`] wrote it.
pub fn manifest_section(manifest: &Manifest) -> Vec<u8> {
    write_section(manifest.version, &manifest_bytes(manifest))
}

/// A little-endian 40-bit field (the value is below 2^40: checked by [`place_bricks`]).
fn write_u40(w: &mut ByteWriter, v: u64) {
    w.bytes(&v.to_le_bytes()[..5]);
}

fn read_u40(r: &mut ByteReader<'_>) -> Result<u64, FormatError> {
    let b = r.take(5)?;
    Ok(b.iter().rev().fold(0u64, |v, x| (v << 8) | u64::from(*x)))
}

fn manifest_bytes(m: &Manifest) -> Vec<u8> {
    let mut w = ByteWriter::new();
    write_space(&mut w, &m.space());
    w.u32(m.brick as u32);
    w.u32(m.bricks.len() as u32);
    if m.version == BRICKED_VERSION {
        for b in &m.bricks {
            write_u40(&mut w, b.length);
            w.u32(b.crc);
            write_u40(&mut w, b.kept);
        }
        return w.into_bytes();
    }
    for b in &m.bricks {
        for o in b.origin {
            w.u64(o);
        }
        for d in b.dims {
            w.u32(d as u32);
        }
        w.u64(b.offset);
        w.u64(b.length);
        w.u32(b.crc);
        w.u64(b.kept);
    }
    w.into_bytes()
}

/// What places a logical volume (a bricked one, or each time point of a series): the whole's
/// dimensions, channels, spacing and placement, as their manifests hold them.
#[derive(Debug, Clone, PartialEq)]
pub struct Space {
    /// The whole volume's dimensions.
    pub dims: [u64; 3],
    /// Channels.
    pub channels: usize,
    /// Voxel spacing.
    pub spacing: [f32; 3],
    /// Placement in patient space (of voxel (0, 0, 0)).
    pub placement: Option<Placement>,
}

impl Manifest {
    /// The whole's dimensions, channels, spacing and placement.
    pub fn space(&self) -> Space {
        Space {
            dims: self.dims,
            channels: self.channels,
            spacing: self.spacing,
            placement: self.placement,
        }
    }
}

/// Writes `space` as a manifest holds it.
pub(super) fn write_space(w: &mut ByteWriter, space: &Space) {
    for d in space.dims {
        w.u64(d);
    }
    w.u8(space.channels as u8);
    for s in space.spacing {
        w.f32(s);
    }
    match &space.placement {
        None => w.u8(0),
        Some(p) => {
            w.u8(1);
            for o in p.origin {
                w.f64(o);
            }
            for d in p.directions.iter().flatten() {
                w.f64(*d);
            }
        }
    }
}

/// Reads and checks what [`write_space`] wrote (`what` names the manifest in errors).
pub(super) fn read_space(m: &mut ByteReader<'_>, what: &'static str) -> Result<Space, FormatError> {
    let bad = |detail: String| FormatError::Invalid { what, detail };
    let mut dims = [0u64; 3];
    for d in &mut dims {
        *d = m.u64()?;
        if *d == 0 || *d > MAX_SIDE {
            return Err(bad(format!("whole dimension {d}; allowed 1..={MAX_SIDE}")));
        }
    }
    let channels = m.u8()? as usize;
    if channels != 1 && channels != 3 {
        return Err(bad(format!("{channels} channels; 1 or 3 allowed")));
    }
    let mut spacing = [0f32; 3];
    for s in &mut spacing {
        *s = m.f32()?;
        if !(s.is_finite() && *s > 0.0) {
            return Err(bad(format!("spacing {s}")));
        }
    }
    let placement = match m.u8()? {
        0 => None,
        1 => {
            let mut origin = [0f64; 3];
            for o in &mut origin {
                *o = m.f64()?;
            }
            let mut directions = [[0f64; 3]; 3];
            for d in directions.iter_mut().flatten() {
                *d = m.f64()?;
            }
            if origin
                .iter()
                .chain(directions.iter().flatten())
                .any(|v| !v.is_finite())
            {
                return Err(bad("placement not finite".into()));
            }
            Some(Placement { origin, directions })
        }
        f => return Err(bad(format!("placement flag {f}"))),
    };
    Ok(Space {
        dims,
        channels,
        spacing,
        placement,
    })
}

fn bad(detail: impl Into<String>) -> FormatError {
    FormatError::Invalid {
        what: "bricked manifest",
        detail: detail.into(),
    }
}

/// Parses and validates a container's manifest: the whole's dimensions, every brick inside
/// them, the bricks tiling the whole exactly (their voxel counts sum to the whole's and none
/// overlaps another), every brick's bytes inside the file.
pub fn parse_bricked(bytes: &[u8]) -> Result<BrickedFile<'_>, FormatError> {
    let manifest = parse_manifest(bytes, bytes.len() as u64)?;
    Ok(BrickedFile { manifest, bytes })
}

/// Parses and validates the manifest at the start of a container of `container_bytes` bytes
/// from `bytes`, its first bytes (at least the manifest section: what a reader fetching byte
/// ranges has), with the checks of [`parse_bricked`].
pub fn parse_manifest(bytes: &[u8], container_bytes: u64) -> Result<Manifest, FormatError> {
    let (mb, data_start, version) = read_section(
        bytes,
        &[BRICKED_VERSION, EXPLICIT_BRICKED_VERSION],
        MAX_MANIFEST_BYTES,
        "bricked manifest",
    )?;
    let mut m = ByteReader::new(mb, "bricked manifest");
    let Space {
        dims,
        channels,
        spacing,
        placement,
    } = read_space(&mut m, "bricked manifest")?;
    let brick = m.u32()? as usize;
    if brick == 0 {
        return Err(bad("brick edge 0"));
    }
    let count = m.u32()? as usize;
    let bricks = if version == BRICKED_VERSION {
        compact_entries(&mut m, dims, brick, count, data_start, container_bytes)?
    } else {
        explicit_entries(&mut m, dims, count, data_start, container_bytes)?
    };
    Ok(Manifest {
        dims,
        channels,
        spacing,
        placement,
        brick,
        bricks,
        version,
    })
}

/// Refuses a brick of `length` bytes at `offset` that runs past a container of
/// `container_bytes`.
fn check_inside(offset: u64, length: u64, container_bytes: u64) -> Result<(), FormatError> {
    if offset
        .checked_add(length)
        .is_none_or(|e| e > container_bytes)
    {
        return Err(FormatError::Truncated {
            what: "brick",
            needed: offset.saturating_add(length),
            available: container_bytes,
        });
    }
    Ok(())
}

/// The entries of a version 9 manifest (`count` of them in `m`), each placing its brick
/// explicitly: every brick inside the whole, the bricks tiling it exactly (their voxel counts
/// sum to the whole's and none overlaps another), every brick's bytes inside the container's
/// `container_bytes` after `data_start`.
fn explicit_entries(
    m: &mut ByteReader<'_>,
    dims: [u64; 3],
    count: usize,
    data_start: u64,
    container_bytes: u64,
) -> Result<Vec<BrickEntry>, FormatError> {
    // Each entry is 68 bytes: refuse a count the manifest cannot hold before allocating.
    const ENTRY_BYTES: usize = 3 * 8 + 3 * 4 + 8 + 8 + 4 + 8;
    if count == 0 || count > MAX_BRICKS || count * ENTRY_BYTES != m.remaining() {
        return Err(bad(format!(
            "{count} bricks in {} bytes of entries",
            m.remaining()
        )));
    }
    let mut bricks = Vec::with_capacity(count);
    for _ in 0..count {
        let mut origin = [0u64; 3];
        for o in &mut origin {
            *o = m.u64()?;
        }
        let mut bd = [0usize; 3];
        for (a, d) in bd.iter_mut().enumerate() {
            *d = m.u32()? as usize;
            if *d == 0 || origin[a].checked_add(*d as u64).is_none_or(|e| e > dims[a]) {
                return Err(bad(format!(
                    "a brick at {origin:?} of {bd:?} leaves the whole {dims:?}"
                )));
            }
        }
        let offset = m.u64()?;
        let length = m.u64()?;
        if offset < data_start {
            return Err(bad(format!(
                "a brick at byte {offset}, inside the manifest"
            )));
        }
        check_inside(offset, length, container_bytes)?;
        let crc = m.u32()?;
        let kept = m.u64()?;
        bricks.push(BrickEntry {
            origin,
            dims: bd,
            offset,
            length,
            crc,
            kept,
        });
    }
    let boxes: Vec<([u64; 3], [usize; 3])> = bricks.iter().map(|b| (b.origin, b.dims)).collect();
    check_tiling(dims, &boxes)?;
    Ok(bricks)
}

/// Refuses boxes (origin, dimensions; each inside `whole`, checked by the caller) that do not
/// tile `whole`: their voxels must sum to the whole's and none may overlap another.
pub fn check_tiling(whole: [u64; 3], bricks: &[([u64; 3], [usize; 3])]) -> Result<(), FormatError> {
    let voxels: u128 = bricks
        .iter()
        .map(|(_, d)| d.iter().map(|&d| d as u128).product::<u128>())
        .sum();
    let all: u128 = whole.iter().map(|&d| u128::from(d)).product();
    if voxels != all {
        return Err(bad(format!(
            "the bricks hold {voxels} voxels, the whole {whole:?} has {all}"
        )));
    }
    check_no_overlap(bricks)
}

/// Most cells the bricks' faces may cut the whole into for [`check_no_overlap`] (2 MiB of
/// bits): a grid of bricks makes one cell per brick, at most [`MAX_BRICKS`].
const MAX_FACE_CELLS: u128 = 1 << 24;

/// Refuses bricks of which two overlap. The whole is cut into cells by every brick face along
/// each axis (the coordinates compressed), and each brick marks the cells it covers; a cell
/// marked twice is an overlap. That costs the number of cells, one per brick for a grid of
/// bricks, where comparing boxes pairwise cost the square of the bricks whenever many share a
/// row (a million bricks at one x made minutes of work out of a 64 MiB manifest). Bricks whose
/// faces cut the whole into more than [`MAX_FACE_CELLS`] cells (no writer's grid does) are
/// refused as not a grid.
fn check_no_overlap(bricks: &[([u64; 3], [usize; 3])]) -> Result<(), FormatError> {
    let cuts: [Vec<u64>; 3] = std::array::from_fn(|a| {
        let mut c: Vec<u64> = bricks
            .iter()
            .flat_map(|(origin, dims)| [origin[a], origin[a] + dims[a] as u64])
            .collect();
        c.sort_unstable();
        c.dedup();
        c
    });
    let n = cuts.each_ref().map(|c| c.len().saturating_sub(1));
    let cells = n.iter().map(|&c| c as u128).product::<u128>();
    if cells > MAX_FACE_CELLS {
        return Err(bad(format!(
            "{} bricks whose faces cut the whole into {cells} cells (at most {MAX_FACE_CELLS}): \
             not a grid of bricks",
            bricks.len()
        )));
    }
    let mut covered = vec![0u64; (cells as usize).div_ceil(64)];
    let at = |a: usize, x: u64| cuts[a].binary_search(&x).unwrap_or_else(|i| i);
    for (origin, dims) in bricks {
        let lo: [usize; 3] = std::array::from_fn(|a| at(a, origin[a]));
        let hi: [usize; 3] = std::array::from_fn(|a| at(a, origin[a] + dims[a] as u64));
        for z in lo[2]..hi[2] {
            for y in lo[1]..hi[1] {
                for x in lo[0]..hi[0] {
                    let cell = (z * n[1] + y) * n[0] + x;
                    let (word, bit) = (cell / 64, 1u64 << (cell % 64));
                    if covered[word] & bit != 0 {
                        return Err(bad(format!(
                            "the brick at {origin:?} of {dims:?} overlaps another"
                        )));
                    }
                    covered[word] |= bit;
                }
            }
        }
    }
    Ok(())
}

/// The entries of a compact manifest (`count` of them in `m`): each brick's box is the grid's
/// ([`brick_grid`] of the whole and the brick edge, which the count must match, checked before
/// anything is allocated from it), its offset where the previous one ends (the first at
/// `data_start`), every one inside the container's `container_bytes`.
fn compact_entries(
    m: &mut ByteReader<'_>,
    dims: [u64; 3],
    brick: usize,
    count: usize,
    data_start: u64,
    container_bytes: u64,
) -> Result<Vec<BrickEntry>, FormatError> {
    let cells: u128 = dims
        .iter()
        .map(|d| u128::from(d.div_ceil(brick as u64)))
        .product();
    if cells != count as u128 || count == 0 || count > MAX_BRICKS {
        return Err(bad(format!(
            "{count} bricks for a grid of {cells} ({dims:?} in bricks of {brick})"
        )));
    }
    if count * COMPACT_ENTRY_BYTES != m.remaining() {
        return Err(bad(format!(
            "{count} bricks in {} bytes of entries",
            m.remaining()
        )));
    }
    let mut offset = data_start;
    let mut bricks = Vec::with_capacity(count);
    for (origin, bd) in brick_grid(dims, brick) {
        let length = read_u40(m)?;
        let crc = m.u32()?;
        let kept = read_u40(m)?;
        check_inside(offset, length, container_bytes)?;
        bricks.push(BrickEntry {
            origin,
            dims: bd,
            offset,
            length,
            crc,
            kept,
        });
        offset += length;
    }
    Ok(bricks)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// What [`check_bricking`] lets through, a manifest can hold and its reader accepts; what
    /// it refuses (an edge past the stored field, a side past [`MAX_SIDE`], too many bricks) is
    /// refused without making the grid.
    #[test]
    fn bricking_is_checked_against_what_a_manifest_holds() {
        for (dims, brick) in [
            ([37, 53, 29], 16),
            ([MAX_SIDE, 1, 1], 1 << 14),
            ([5, 5, 5], 1 << 20),
        ] {
            check_bricking(dims, brick).unwrap();
            let (mut m, bricks) = manifest(dims, brick);
            let refs: Vec<&[u8]> = bricks.iter().map(|b| b.as_slice()).collect();
            let bytes = write_bricked(&mut m, &refs).unwrap();
            assert_eq!(parse_bricked(&bytes).unwrap().manifest.dims, dims);
        }
        for (dims, brick, says) in [
            ([37, 53, 29], 0, "brick edge 0"),
            ([37, 53, 29], (1 << 32) + 16, "brick edge"),
            ([MAX_SIDE + 1, 1, 1], 4096, "a side of 1048577"),
            ([20_000, 20_000, 20_000], 8, "15625000000 bricks"),
            ([1 << 20, 1 << 20, 1], 1, "bricks"),
        ] {
            let e = check_bricking(dims, brick).unwrap_err();
            assert!(e.contains(says), "{dims:?} / {brick}: {e}");
        }
    }

    /// A manifest of `dims` on the grid of `brick` in the compact version ([`BRICKED_VERSION`])
    /// and dummy bricks; `.version = EXPLICIT_BRICKED_VERSION` writes the old layout.
    fn manifest(dims: [u64; 3], brick: usize) -> (Manifest, Vec<Vec<u8>>) {
        let grid = brick_grid(dims, brick);
        let bricks: Vec<Vec<u8>> = (0..grid.len()).map(|i| vec![i as u8; 10 + i]).collect();
        let m = Manifest {
            dims,
            channels: 1,
            spacing: [1.0, 1.0, 2.5],
            placement: Some(Placement::identity()),
            brick,
            bricks: grid
                .into_iter()
                .map(|(origin, dims)| BrickEntry {
                    origin,
                    dims,
                    offset: 0,
                    length: 0,
                    crc: 0,
                    kept: 7,
                })
                .collect(),
            version: BRICKED_VERSION,
        };
        (m, bricks)
    }

    fn explicit(m: &Manifest) -> Manifest {
        Manifest {
            version: EXPLICIT_BRICKED_VERSION,
            ..m.clone()
        }
    }

    /// The container of `m` (a copy, its offsets filled in) and `bricks`.
    fn write(m: &Manifest, bricks: &[Vec<u8>]) -> Vec<u8> {
        let files: Vec<&[u8]> = bricks.iter().map(Vec::as_slice).collect();
        write_bricked(&mut m.clone(), &files).unwrap()
    }

    #[test]
    fn axes_split_into_near_equal_parts() {
        assert_eq!(split_axis(257, 256), vec![(0, 129), (129, 128)]);
        assert_eq!(split_axis(256, 256), vec![(0, 256)]);
        assert_eq!(split_axis(1, 256), vec![(0, 1)]);
        assert_eq!(split_axis(96, 32), vec![(0, 32), (32, 32), (64, 32)]);
        for len in 1..300u64 {
            for brick in [1, 7, 32, 100] {
                let parts = split_axis(len, brick);
                assert_eq!(parts.iter().map(|p| p.1 as u64).sum::<u64>(), len);
                assert!(parts.iter().all(|p| p.1 <= brick && p.1 > 0));
                let (lo, hi) = parts
                    .iter()
                    .fold((usize::MAX, 0), |(lo, hi), p| (lo.min(p.1), hi.max(p.1)));
                assert!(hi - lo <= 1, "{len} / {brick}: {parts:?}");
            }
        }
    }

    #[test]
    fn a_container_round_trips_and_every_brick_is_checked() {
        let (m, bricks) = manifest([70, 40, 33], 32);
        for version in [BRICKED_VERSION, EXPLICIT_BRICKED_VERSION] {
            let m = Manifest {
                version,
                ..m.clone()
            };
            round_trip(&m, &bricks);
        }
    }

    fn round_trip(m: &Manifest, bricks: &[Vec<u8>]) {
        let bytes = write(m, bricks);
        assert_eq!(u16::from_le_bytes([bytes[4], bytes[5]]), m.version);
        assert!(is_bricked(&bytes));
        let f = parse_bricked(&bytes).unwrap();
        assert_eq!(f.manifest.dims, m.dims);
        assert_eq!(f.manifest.placement, m.placement);
        assert_eq!(f.manifest.bricks.len(), bricks.len());
        for (i, b) in bricks.iter().enumerate() {
            assert_eq!(f.brick_bytes(i).unwrap(), b.as_slice());
        }
        // The manifest section made again from the parsed manifest is the file's, byte for
        // byte (a reader that keeps only the manifest can hand the section on).
        let section = manifest_section(&f.manifest);
        assert_eq!(section, bytes[..f.manifest.bricks[0].offset as usize]);
        // A flipped bit in a brick is caught when it is taken, in the manifest at once.
        let mut bad = bytes.clone();
        let last = bad.len() - 1;
        bad[last] ^= 1;
        let f = parse_bricked(&bad).unwrap();
        assert!(matches!(
            f.brick_bytes(bricks.len() - 1),
            Err(FormatError::Checksum { .. })
        ));
        let mut bad = bytes.clone();
        bad[12] ^= 1;
        assert!(matches!(
            parse_bricked(&bad),
            Err(FormatError::Checksum { .. })
        ));
    }

    /// Both versions describe the same container: the compact one's boxes and offsets (from
    /// the grid and the lengths) are the explicit one's, its manifest 14 bytes an entry
    /// instead of 64, and its bricks' bytes the same.
    #[test]
    fn the_compact_manifest_places_the_bricks_as_the_explicit_one() {
        let (m, bricks) = manifest([97, 40, 70], 32);
        let compact = parse_bricked(&write(&m, &bricks)).unwrap().manifest;
        let old_bytes = write(&explicit(&m), &bricks);
        let old = parse_bricked(&old_bytes).unwrap().manifest;
        assert_eq!(
            (compact.version, old.version),
            (BRICKED_VERSION, EXPLICIT_BRICKED_VERSION)
        );
        let shift = old.bricks[0].offset - compact.bricks[0].offset;
        assert_eq!(
            shift,
            (64 - COMPACT_ENTRY_BYTES as u64) * bricks.len() as u64
        );
        for (c, o) in compact.bricks.iter().zip(&old.bricks) {
            assert_eq!((c.origin, c.dims), (o.origin, o.dims));
            assert_eq!((c.length, c.crc, c.kept), (o.length, o.crc, o.kept));
            assert_eq!(c.offset + shift, o.offset);
        }
        // A compact manifest holds only the grid: other boxes, or values beyond 40 bits, are
        // refused when it is written.
        let mut off_grid = m.clone();
        off_grid.bricks.swap(0, 1);
        let files: Vec<&[u8]> = bricks.iter().map(Vec::as_slice).collect();
        assert!(write_bricked(&mut off_grid, &files).is_err());
        assert!(write_bricked(&mut explicit(&off_grid), &files).is_ok());
        let mut huge = m.clone();
        huge.bricks[0].kept = MAX_COMPACT_FIELD + 1;
        assert!(write_bricked(&mut huge, &files).is_err());
    }

    /// A compact manifest whose count is not its grid's, whose entries do not fill it, or
    /// whose lengths run past the container is refused (and nothing sized from it first).
    #[test]
    fn hostile_compact_manifests_are_refused() {
        let (m, bricks) = manifest([64, 64, 64], 32);
        let bytes = write(&m, &bricks);
        // The count (after magic, version, length, space and the brick edge) set to the
        // largest u32: refused by the grid, before any allocation.
        let space = {
            let mut w = ByteWriter::new();
            write_space(&mut w, &m.space());
            w.into_bytes().len()
        };
        let at = 4 + 2 + 4 + space + 4;
        let with_count = |count: u32| {
            let mut b = bytes.clone();
            b[at..at + 4].copy_from_slice(&count.to_le_bytes());
            let len = u32::from_le_bytes(b[6..10].try_into().unwrap()) as usize;
            let crc = crc32fast::hash(&b[10..10 + len]);
            b[10 + len..14 + len].copy_from_slice(&crc.to_le_bytes());
            b
        };
        assert!(parse_bricked(&with_count(8)).is_ok());
        for count in [0, 7, 9, u32::MAX] {
            assert!(parse_bricked(&with_count(count)).is_err(), "{count}");
        }
        // A brick edge whose grid has another count.
        let mut other = m.clone();
        other.brick = 16;
        assert!(parse_manifest(&manifest_section(&other), u64::MAX).is_err());
        // Lengths past the end of the container.
        assert!(parse_bricked(&bytes[..bytes.len() - 1]).is_err());
        for cut in 0..bytes.len() {
            let _ = parse_bricked(&bytes[..cut]);
        }
    }

    #[test]
    fn hostile_manifests_are_refused() {
        let (m, bricks) = manifest([64, 64, 64], 32);
        let m = explicit(&m);
        // Every cut of the file is an error, never a panic.
        let bytes = write(&m, &bricks);
        for cut in 0..bytes.len() {
            let _ = parse_bricked(&bytes[..cut]).map(|f| {
                for i in 0..f.manifest.bricks.len() {
                    let _ = f.brick_bytes(i);
                }
            });
        }
        assert!(parse_bricked(&bytes[..bytes.len() - 1]).is_err());
        // Overlapping bricks (two at the same place, one missing) and gaps are refused.
        let mut overlap = m.clone();
        overlap.bricks[1].origin = overlap.bricks[0].origin;
        assert!(parse_bricked(&write(&overlap, &bricks)).is_err());
        let mut gap = m.clone();
        gap.bricks[0].dims = [16, 32, 32];
        assert!(parse_bricked(&write(&gap, &bricks)).is_err());
        let mut outside = m.clone();
        outside.bricks[0].origin = [u64::MAX - 3, 0, 0];
        assert!(parse_bricked(&write(&outside, &bricks)).is_err());
        // Counts of kept coefficients past any real one add up without overflowing.
        let mut liar = m.clone();
        liar.bricks[0].kept = u64::MAX;
        liar.bricks[1].kept = u64::MAX;
        let f = write(&liar, &bricks);
        assert_eq!(parse_bricked(&f).unwrap().manifest.kept(), u64::MAX);
    }

    /// Bricks that share a row (every one at x = 0: comparing boxes pairwise would be
    /// quadratic) and bricks off any one grid (rows split at different places) are accepted as
    /// the tilings they are; one brick moved onto its neighbour is refused, as is a layout
    /// whose faces cut the whole into more cells than any grid of bricks.
    #[test]
    fn tilings_are_checked_by_the_cells_their_faces_cut() {
        let entry = |origin: [u64; 3], dims: [usize; 3]| BrickEntry {
            origin,
            dims,
            offset: 0,
            length: 0,
            crc: 0,
            kept: 1,
        };
        let layout = |dims: [u64; 3], bricks: Vec<BrickEntry>| {
            let files = vec![vec![1u8]; bricks.len()];
            let m = Manifest {
                dims,
                channels: 1,
                spacing: [1.0; 3],
                placement: None,
                brick: 1,
                bricks,
                version: EXPLICIT_BRICKED_VERSION,
            };
            parse_bricked(&write(&m, &files)).map(|f| f.manifest.bricks.len())
        };
        let (ny, nz) = (255u64, 257u64);
        let row: Vec<BrickEntry> = (0..ny * nz)
            .map(|i| entry([0, i / nz, i % nz], [1, 1, 1]))
            .collect();
        assert_eq!(
            layout([1, ny, nz], row.clone()).unwrap(),
            (ny * nz) as usize
        );
        // Two bricks at one place and one voxel left out: the voxel sum still matches.
        let mut twice = row;
        twice[1000].origin = twice[999].origin;
        let e = layout([1, ny, nz], twice).unwrap_err().to_string();
        assert!(e.contains("overlaps another"), "{e}");
        // Rows of a 64² slab each split at a different z: 64 × 64 cells for 128 bricks.
        let staggered: Vec<BrickEntry> = (0..64u64)
            .flat_map(|y| {
                let s = 1 + y as usize % 63;
                [
                    entry([0, y, 0], [1, 1, s]),
                    entry([0, y, s as u64], [1, 1, 64 - s]),
                ]
            })
            .collect();
        assert_eq!(layout([1, 64, 64], staggered).unwrap(), 128);
        // Sheets along x, each cut in four at its own y and z: a tiling, but its faces cut
        // 300³ cells, more than any grid of bricks makes.
        let n = 300u64;
        let sheets: Vec<BrickEntry> = (0..n)
            .flat_map(|x| {
                let (a, b) = (1 + x % (n - 1), 1 + (x * 7) % (n - 1));
                let (a_, b_) = (a as usize, b as usize);
                let rest = n as usize;
                [
                    entry([x, 0, 0], [1, a_, b_]),
                    entry([x, 0, b], [1, a_, rest - b_]),
                    entry([x, a, 0], [1, rest - a_, b_]),
                    entry([x, a, b], [1, rest - a_, rest - b_]),
                ]
            })
            .collect();
        let e = layout([n, n, n], sheets).unwrap_err().to_string();
        assert!(e.contains("cells"), "{e}");
    }

    /// The plain reader names a bricked file of either version as such (a build older than
    /// version 9 reads versions up to 8 and calls it newer; one that reads version 9 only
    /// calls a version 11 container newer). Plain files skip the containers' numbers: after
    /// version 8 comes 12.
    #[test]
    fn the_plain_reader_names_a_bricked_file() {
        let (m, bricks) = manifest([8, 8, 8], 8);
        for m in [m.clone(), explicit(&m)] {
            let bytes = write(&m, &bricks);
            assert!(matches!(
                super::super::parse_file(&bytes),
                Err(FormatError::Bricked)
            ));
        }
        // The containers' versions are never plain ones.
        for v in [EXPLICIT_BRICKED_VERSION, BRICKED_VERSION] {
            assert!(!super::super::is_plain_version(v));
        }
    }
}
