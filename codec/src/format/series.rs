//! The series container (format version 10): a time-varying volume (a cine, a 4D series,
//! simulation time steps) as one file. It holds *components*, each a complete volume file of
//! its own (a plain version 8 `.wsp` or a version 9 or 11 bricked container), and describes every
//! time point as a weighted sum of components: with a wavelet along time, a group's time points
//! share a low-pass component and each adds its own few detail components, so what neighbouring
//! time points share is stored once. Rendering is linear in the data, so a time point's image is
//! the same weighted sum of its components' images, and a reader that wants time point t takes
//! only the bytes of the components it names: no byte of another group.
//!
//! Layout: magic `WSPL`, version 10 (u16), manifest length (u32), the manifest, its CRC-32, then
//! the components' bytes in manifest order. The manifest: the whole's space (dimensions,
//! channels, spacing, placement, as a bricked manifest holds them), whether the times are known
//! (from the source) or only the order, the temporal group size, the components (offset,
//! length, CRC-32, kept coefficients), then each time point's time and terms (component, weight).
//! A build that reads versions up to 9 refuses such a file as written by a newer wavesplat. The
//! manifest is untrusted input: counts, weights, times and ranges are checked before anything
//! is allocated from them; each component's bytes are checked against their CRC when taken.

use super::bricked::{read_section, read_space, write_section, write_space, Space};
use super::bytes::{ByteReader, ByteWriter};
use super::{FormatError, MAGIC};

/// The format version of a series container.
pub const SERIES_VERSION: u16 = 10;

/// Most time points one series may hold.
pub const MAX_TIME_POINTS: usize = 1 << 20;

/// Most components one series may hold.
pub const MAX_COMPONENTS: usize = 1 << 21;

/// Most components one time point may sum (a wavelet along time over groups of up to 2^15).
pub const MAX_TERMS: usize = 16;

/// Largest accepted manifest (bytes).
pub const MAX_MANIFEST_BYTES: usize = 256 << 20;

/// Where one component's bytes are.
#[derive(Debug, Clone, PartialEq)]
pub struct ComponentEntry {
    /// Offset of its file's bytes from the start of the container.
    pub offset: u64,
    /// Length of its file's bytes.
    pub length: u64,
    /// CRC-32 of those bytes.
    pub crc: u32,
    /// Coefficients it keeps (for listings and budgets).
    pub kept: u64,
}

/// One time point: when it was taken and the components it is the sum of.
#[derive(Debug, Clone, PartialEq)]
pub struct TimePoint {
    /// Its time in seconds (its index when the source gave no times).
    pub time: f64,
    /// (component, weight): the time point is Σ weight · component.
    pub terms: Vec<(usize, f32)>,
}

/// What describes a series.
#[derive(Debug, Clone, PartialEq)]
pub struct SeriesManifest {
    /// Every time point's dimensions, channels, spacing and placement.
    pub space: Space,
    /// Whether the times are the source's (seconds) or only the time points' indices.
    pub times_known: bool,
    /// The temporal group size the components were made with (1: each time point alone).
    pub group: usize,
    /// The components, in the order their bytes follow the manifest.
    pub components: Vec<ComponentEntry>,
    /// The time points in order.
    pub points: Vec<TimePoint>,
}

impl SeriesManifest {
    /// Coefficients kept over all components.
    pub fn kept(&self) -> u64 {
        // Saturating: the entries' counts are the file's word, not checked against the parts.
        self.components
            .iter()
            .fold(0, |t, c| t.saturating_add(c.kept))
    }

    /// Bytes of the components time point `t` needs (0 for a time point it does not hold).
    pub fn point_bytes(&self, t: usize) -> u64 {
        self.points.get(t).map_or(0, |p| {
            p.terms
                .iter()
                .map(|(c, _)| self.components[*c].length)
                .sum()
        })
    }
}

/// A parsed series container: the manifest and the bytes it indexes.
#[derive(Debug)]
pub struct SeriesFile<'a> {
    /// The manifest.
    pub manifest: SeriesManifest,
    bytes: &'a [u8],
}

impl<'a> SeriesFile<'a> {
    /// The file bytes of component `c`, checked against their CRC.
    pub fn component_bytes(&self, c: usize) -> Result<&'a [u8], FormatError> {
        let e = self
            .manifest
            .components
            .get(c)
            .ok_or_else(|| bad(format!("no component {c}")))?;
        // In range: checked by `parse_series`.
        let data = &self.bytes[e.offset as usize..(e.offset + e.length) as usize];
        let computed = crc32fast::hash(data);
        if computed != e.crc {
            return Err(FormatError::Checksum {
                what: "series component",
                stored: e.crc,
                computed,
            });
        }
        Ok(data)
    }
}

/// Whether `bytes` start as a series container (magic and version 10).
pub fn is_series(bytes: &[u8]) -> bool {
    bytes.len() >= 6
        && &bytes[..4] == MAGIC
        && u16::from_le_bytes([bytes[4], bytes[5]]) == SERIES_VERSION
}

fn bad(detail: impl Into<String>) -> FormatError {
    FormatError::Invalid {
        what: "series manifest",
        detail: detail.into(),
    }
}

/// Writes a container: `manifest` (whose components' `offset`, `length` and `crc` are filled
/// in here) followed by `components`, one volume file each in manifest order. The manifest is
/// checked as a reader checks it, so a writer cannot make a file its readers refuse.
pub fn write_series(
    manifest: &mut SeriesManifest,
    components: &[&[u8]],
) -> Result<Vec<u8>, FormatError> {
    let placed: Vec<(u64, u32)> = components
        .iter()
        .map(|b| (b.len() as u64, crc32fast::hash(b)))
        .collect();
    let mut out = place_components(manifest, &placed)?;
    out.reserve(placed.iter().map(|p| p.0 as usize).sum());
    for b in components {
        out.extend_from_slice(b);
    }
    Ok(out)
}

/// Fills in `manifest`'s offsets, lengths and CRCs for components of (length, CRC-32)
/// `components` in manifest order, and returns the manifest section the container starts
/// with (checked as a reader checks it): the components' bytes follow it, in that order.
/// (What [`write_series`] does for bytes in memory, for a writer that streams them.)
pub fn place_components(
    manifest: &mut SeriesManifest,
    components: &[(u64, u32)],
) -> Result<Vec<u8>, FormatError> {
    if components.len() != manifest.components.len() {
        return Err(bad(format!(
            "{} components for {} manifest entries",
            components.len(),
            manifest.components.len()
        )));
    }
    let manifest_len = manifest_bytes(manifest).len();
    let mut offset = (4 + 2 + 4 + manifest_len + 4) as u64;
    for (e, (len, crc)) in manifest.components.iter_mut().zip(components) {
        e.offset = offset;
        e.length = *len;
        e.crc = *crc;
        offset += len;
    }
    let section = write_section(SERIES_VERSION, &manifest_bytes(manifest));
    // Refuse to write what readers would refuse.
    parse_manifest(&section, offset)?;
    Ok(section)
}

/// The manifest section of a series container (magic, version 10, manifest length, manifest,
/// CRC): what a reader of its components needs first, and what a cache sends as its header.
pub fn manifest_section(m: &SeriesManifest) -> Vec<u8> {
    write_section(SERIES_VERSION, &manifest_bytes(m))
}

fn manifest_bytes(m: &SeriesManifest) -> Vec<u8> {
    let mut w = ByteWriter::new();
    write_space(&mut w, &m.space);
    w.u8(u8::from(m.times_known));
    w.u32(m.group as u32);
    w.u32(m.components.len() as u32);
    for c in &m.components {
        w.u64(c.offset);
        w.u64(c.length);
        w.u32(c.crc);
        w.u64(c.kept);
    }
    w.u32(m.points.len() as u32);
    for p in &m.points {
        w.f64(p.time);
        w.u8(p.terms.len() as u8);
        for (c, weight) in &p.terms {
            w.u32(*c as u32);
            w.f32(*weight);
        }
    }
    w.into_bytes()
}

/// Parses and validates a whole container.
pub fn parse_series(bytes: &[u8]) -> Result<SeriesFile<'_>, FormatError> {
    let manifest = parse_manifest(bytes, bytes.len() as u64)?;
    Ok(SeriesFile { manifest, bytes })
}

/// Parses and validates the manifest at the start of a container of `container_bytes` bytes
/// from `bytes`, its first bytes (at least the manifest section): every component's bytes
/// inside the file and after the manifest, in order without overlap; every time point a sum of
/// 1..=[`MAX_TERMS`] distinct components with finite non-zero weights; every component used;
/// times finite and strictly increasing.
pub fn parse_manifest(bytes: &[u8], container_bytes: u64) -> Result<SeriesManifest, FormatError> {
    let (mb, data_start, _) = read_section(
        bytes,
        &[SERIES_VERSION],
        MAX_MANIFEST_BYTES,
        "series manifest",
    )?;
    let mut m = ByteReader::new(mb, "series manifest");
    let space = read_space(&mut m, "series manifest")?;
    let times_known = match m.u8()? {
        0 => false,
        1 => true,
        f => return Err(bad(format!("times flag {f}"))),
    };
    let group = m.u32()? as usize;
    if group == 0 || group > 1 << (MAX_TERMS - 1) {
        return Err(bad(format!("temporal group {group}")));
    }
    let count = m.u32()? as usize;
    const COMPONENT_BYTES: usize = 8 + 8 + 4 + 8;
    if count == 0 || count > MAX_COMPONENTS || count * COMPONENT_BYTES > m.remaining() {
        return Err(bad(format!(
            "{count} components in {} bytes",
            m.remaining()
        )));
    }
    let mut components = Vec::with_capacity(count);
    let mut next = data_start;
    for c in 0..count {
        let offset = m.u64()?;
        let length = m.u64()?;
        let end = offset.checked_add(length);
        if offset < next || end.is_none_or(|e| e > container_bytes) {
            return Err(FormatError::Truncated {
                what: "series component",
                needed: offset.saturating_add(length),
                available: container_bytes,
            });
        }
        if length == 0 {
            return Err(bad(format!("component {c} is empty")));
        }
        next = offset + length;
        let crc = m.u32()?;
        let kept = m.u64()?;
        components.push(ComponentEntry {
            offset,
            length,
            crc,
            kept,
        });
    }
    let points_count = m.u32()? as usize;
    // Each time point takes at least 8 + 1 + 8 bytes.
    if points_count == 0 || points_count > MAX_TIME_POINTS || points_count * 17 > m.remaining() {
        return Err(bad(format!(
            "{points_count} time points in {} bytes",
            m.remaining()
        )));
    }
    let mut points: Vec<TimePoint> = Vec::with_capacity(points_count);
    let mut used = vec![false; count];
    for t in 0..points_count {
        let time = m.f64()?;
        if !time.is_finite() || points.last().is_some_and(|p| p.time >= time) {
            return Err(bad(format!(
                "time point {t} at {time}: times must be finite and increasing"
            )));
        }
        let n = m.u8()? as usize;
        if n == 0 || n > MAX_TERMS {
            return Err(bad(format!("time point {t} sums {n} components")));
        }
        let mut terms = Vec::with_capacity(n);
        for _ in 0..n {
            let c = m.u32()? as usize;
            let weight = m.f32()?;
            if c >= count || terms.iter().any(|(o, _)| *o == c) {
                return Err(bad(format!(
                    "time point {t} names component {c} (of {count}) twice or out of range"
                )));
            }
            if !weight.is_finite() || weight == 0.0 {
                return Err(bad(format!("time point {t}: weight {weight}")));
            }
            used[c] = true;
            terms.push((c, weight));
        }
        points.push(TimePoint { time, terms });
    }
    if m.remaining() != 0 {
        return Err(bad(format!("{} unexpected trailing bytes", m.remaining())));
    }
    if let Some(c) = used.iter().position(|u| !u) {
        return Err(bad(format!("component {c} belongs to no time point")));
    }
    Ok(SeriesManifest {
        space,
        times_known,
        group,
        components,
        points,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::volume::Placement;

    fn sample() -> (SeriesManifest, Vec<Vec<u8>>) {
        let comps: Vec<Vec<u8>> = (0..3).map(|i| vec![i as u8 + 1; 20 + i]).collect();
        let h = std::f32::consts::FRAC_1_SQRT_2;
        let m = SeriesManifest {
            space: Space {
                dims: [16, 12, 5],
                channels: 1,
                spacing: [1.0, 1.0, 2.0],
                placement: Some(Placement::identity()),
            },
            times_known: true,
            group: 2,
            components: (0..3)
                .map(|_| ComponentEntry {
                    offset: 0,
                    length: 0,
                    crc: 0,
                    kept: 5,
                })
                .collect(),
            points: vec![
                TimePoint {
                    time: 0.0,
                    terms: vec![(0, h), (1, h)],
                },
                TimePoint {
                    time: 0.04,
                    terms: vec![(0, h), (1, -h)],
                },
                TimePoint {
                    time: 0.08,
                    terms: vec![(2, 1.0)],
                },
            ],
        };
        (m, comps)
    }

    fn write(m: &SeriesManifest, comps: &[Vec<u8>]) -> Result<Vec<u8>, FormatError> {
        let files: Vec<&[u8]> = comps.iter().map(Vec::as_slice).collect();
        write_series(&mut m.clone(), &files)
    }

    #[test]
    fn a_series_round_trips_and_each_component_is_checked() {
        let (m, comps) = sample();
        let bytes = write(&m, &comps).unwrap();
        assert!(is_series(&bytes));
        assert!(!super::super::bricked::is_bricked(&bytes));
        let f = parse_series(&bytes).unwrap();
        assert_eq!(f.manifest.points, m.points);
        assert_eq!(f.manifest.space, m.space);
        assert_eq!(f.manifest.kept(), 15);
        for (c, b) in comps.iter().enumerate() {
            assert_eq!(f.component_bytes(c).unwrap(), b.as_slice());
        }
        assert_eq!(f.manifest.point_bytes(0), 41);
        assert_eq!(f.manifest.point_bytes(2), 22);
        // The manifest alone (what a range reader fetches first) parses with the file's size.
        let first = f.manifest.components[0].offset as usize;
        assert_eq!(
            parse_manifest(&bytes[..first], bytes.len() as u64).unwrap(),
            f.manifest
        );
        let mut flipped = bytes.clone();
        let last = flipped.len() - 1;
        flipped[last] ^= 1;
        assert!(matches!(
            parse_series(&flipped).unwrap().component_bytes(2),
            Err(FormatError::Checksum { .. })
        ));
        // A build that reads plain files only says it is a newer format.
        assert!(crate::format::parse_file(&bytes).is_err());
    }

    #[test]
    fn hostile_series_manifests_are_refused() {
        let (m, comps) = sample();
        let bytes = write(&m, &comps).unwrap();
        for cut in 0..bytes.len() {
            if let Ok(f) = parse_series(&bytes[..cut]) {
                panic!("a cut at {cut} parsed: {:?}", f.manifest);
            }
        }
        let refused = |edit: &dyn Fn(&mut SeriesManifest)| {
            let mut bad = m.clone();
            edit(&mut bad);
            write(&bad, &comps).expect_err("written")
        };
        let e = refused(&|m| m.points[1].time = 0.0);
        assert!(e.to_string().contains("increasing"), "{e}");
        refused(&|m| m.points[0].time = f64::NAN);
        refused(&|m| m.points[0].terms[0].1 = f32::INFINITY);
        refused(&|m| m.points[0].terms[0].1 = 0.0);
        refused(&|m| m.points[0].terms[1].0 = 0);
        refused(&|m| m.points[2].terms[0].0 = 3);
        refused(&|m| m.points[0].terms.clear());
        let e = refused(&|m| m.points.truncate(2));
        assert!(e.to_string().contains("no time point"), "{e}");
        refused(&|m| m.group = 0);
        refused(&|m| m.space.dims[0] = 0);
        // A component whose range leaves the file, or overlaps the previous one.
        let good = parse_series(&bytes).unwrap().manifest;
        let mut long = good.clone();
        long.components[2].length += 1;
        let section = |m: &SeriesManifest| write_section(SERIES_VERSION, &manifest_bytes(m));
        let total = bytes.len() as u64;
        assert!(matches!(
            parse_manifest(&section(&long), total),
            Err(FormatError::Truncated { .. })
        ));
        let mut overlapping = good.clone();
        overlapping.components[1].offset -= 1;
        assert!(parse_manifest(&section(&overlapping), total).is_err());
        assert!(parse_manifest(&section(&good), total).is_ok());
        // Counts of kept coefficients past any real one add up without overflowing.
        let mut liar = good.clone();
        liar.components[0].kept = u64::MAX;
        liar.components[1].kept = u64::MAX;
        let parsed = parse_manifest(&section(&liar), total).unwrap();
        assert_eq!(parsed.kept(), u64::MAX);
        // A manifest whose CRC does not match.
        let mut flipped = bytes.clone();
        flipped[14] ^= 1;
        assert!(matches!(
            parse_series(&flipped),
            Err(FormatError::Checksum { .. })
        ));
    }
}
