//! The file source: a local `.wsp` file served packet by packet in the order the cache would
//! send it for the current view (visible energy per byte), up to an optional byte budget, the
//! next few packets decoded ahead in parallel. A bricked file is served as one volume: its
//! bricks' packets under global ids (brick by brick in file order), ranked together by each
//! brick's view of the whole; a brick whose box the view does not see sends nothing.

use super::{decode_for_session, Decoded, PacketSource, SourceError, SourcePacket, SourceStatus};
use crate::bricked::{check_brick, same_display};
use crate::session::{BrickedVolume, SessionBrick};
use std::collections::HashMap;
use wavesplat_codec::format::bricked::{is_bricked, parse_bricked, BrickEntry};
use wavesplat_codec::format::packet::read_framing;
use wavesplat_codec::format::{check_kept, parse_file, FormatError, Header};
use wavesplat_codec::layout::Band;
use wavesplat_codec::view::bricked::{bricked_packet_order, whole_header, BrickPacket};
use wavesplat_codec::view::visibility::{packet_order, PacketFacts, Visibility};
use wavesplat_codec::view::ViewSpec;

/// Where a packet lies in a file and what ranks it.
#[derive(Debug, Clone)]
struct FilePacket {
    range: std::ops::Range<usize>,
    tile: usize,
    summary: Vec<(Band, f64)>,
    /// Its brick (0 in a file of one volume).
    brick: usize,
}

/// A brick of a bricked file: its header and first voxel in the whole; in a time point of a
/// series, the weight its component has in the time point (1 otherwise).
#[derive(Debug, Clone)]
struct FileBrick {
    header: Header,
    origin: [u64; 3],
    weight: f32,
}

/// A local `.wsp` file served packet by packet in the cache's order for the current view
/// (visible energy per byte), optionally only up to a byte budget, each packet decoded when it
/// is handed over, together with the next few in parallel (every source hands the session
/// decoded packets).
#[derive(Debug)]
pub struct FileSource {
    bytes: Vec<u8>,
    /// The volume's header (a bricked file's: the whole's).
    header: Header,
    /// The bricks of a bricked file (empty for one volume).
    bricks: Vec<FileBrick>,
    /// Byte range and framing of each packet.
    packets: Vec<FilePacket>,
    order: Vec<u32>,
    cursor: usize,
    delivered: Vec<bool>,
    budget: Option<u64>,
    status: SourceStatus,
    /// Packets decoded ahead of their delivery, by id (`None`: it did not decode).
    ahead: HashMap<u32, Decoded>,
}

/// Packets a file source decodes at once, in parallel, when the next one is not decoded yet:
/// per core, so that every core decodes while the frame thread takes packets.
const DECODE_AHEAD_PER_THREAD: usize = 2;

impl FileSource {
    /// Parses `bytes` (the whole file, one volume or bricked) and ranks its packets for
    /// `spec` (a bricked file's view is of its whole: [`crate::bricked::whole_geometry`]).
    pub fn open(bytes: Vec<u8>, spec: &ViewSpec) -> Result<FileSource, SourceError> {
        if is_bricked(&bytes) {
            return FileSource::open_bricked(bytes, spec);
        }
        let (header, ranges) = {
            let file = parse_file(&bytes)?;
            (file.header, ranges_in(&bytes, &file.packets))
        };
        let packets = framed(&header, &bytes, ranges, 0)?;
        FileSource::with_packets(bytes, header, Vec::new(), packets, spec)
    }

    /// [`FileSource::open`] of a bricked file: every brick's header and packets read (each
    /// brick checked against the manifest and the first brick), the whole's header made.
    fn open_bricked(bytes: Vec<u8>, spec: &ViewSpec) -> Result<FileSource, SourceError> {
        let (header, bricks, packets) = {
            let file = parse_bricked(&bytes)?;
            let m = &file.manifest;
            let mut bricks = Vec::with_capacity(m.bricks.len());
            let mut packets = Vec::new();
            for (i, entry) in m.bricks.iter().enumerate() {
                let f = parse_file(file.brick_bytes(i)?)?;
                let first = bricks.first().map_or(&f.header, |b: &FileBrick| &b.header);
                check_session_brick(i, entry, &f.header, first, m.channels)?;
                let ranges = ranges_in(&bytes, &f.packets);
                packets.extend(framed(&f.header, &bytes, ranges, i)?);
                bricks.push(FileBrick {
                    header: f.header,
                    origin: entry.origin,
                    weight: 1.0,
                });
            }
            let Some(first) = bricks.first() else {
                return Err(FormatError::Invalid {
                    what: "bricked manifest",
                    detail: "no bricks".into(),
                }
                .into());
            };
            (whole_header(m, &first.header), bricks, packets)
        };
        if u32::try_from(packets.len()).is_err() {
            return Err(FormatError::Invalid {
                what: "bricked file",
                detail: format!("{} packets, more than a source numbers", packets.len()),
            }
            .into());
        }
        FileSource::with_packets(bytes, header, bricks, packets, spec)
    }

    /// Time point `t` of a series file ([`wavesplat_codec::format::series`]) served as one
    /// volume for `spec` (of the whole: [`wavesplat_codec::view::bricked::series_header`]'s geometry): the
    /// bricks of the components it names (a plain component is one brick of the whole's size)
    /// under global ids in component order, each packet's values scaled by its component's
    /// weight as it is decoded and its energy by the weight² as it is ranked. The time point's
    /// offset, the components' offsets so weighted, is the whole's (and every brick's, as a
    /// session draws the offset once for the whole). Only the named components are read.
    pub fn open_series_point(
        bytes: Vec<u8>,
        t: usize,
        spec: &ViewSpec,
    ) -> Result<FileSource, SourceError> {
        use wavesplat_codec::format::series::parse_series;
        let (header, bricks, packets) = {
            let file = parse_series(&bytes)?;
            let m = &file.manifest;
            let point = m.points.get(t).ok_or_else(|| FormatError::Invalid {
                what: "series manifest",
                detail: format!("time point {t}; the series has {}", m.points.len()),
            })?;
            let dims = m.space.dims.map(|d| d as usize);
            let mut bricks: Vec<FileBrick> = Vec::new();
            let mut packets = Vec::new();
            let mut offset = 0f64;
            let mut whole: Option<Header> = None;
            for &(c, weight) in &point.terms {
                let data = file.component_bytes(c)?;
                // (header, origin, packets' byte ranges) of each brick of the component.
                let mut parts: Vec<(Header, [u64; 3], Vec<std::ops::Range<usize>>)> = Vec::new();
                let component_whole = if is_bricked(data) {
                    let cf = parse_bricked(data)?;
                    let cm = &cf.manifest;
                    for (i, entry) in cm.bricks.iter().enumerate() {
                        let f = parse_file(cf.brick_bytes(i)?)?;
                        let first = parts.first().map_or(&f.header, |p| &p.0);
                        check_session_brick(i, entry, &f.header, first, cm.channels)?;
                        let ranges = ranges_in(&bytes, &f.packets);
                        parts.push((f.header, entry.origin, ranges));
                    }
                    let first = &parts.first().ok_or_else(|| FormatError::Invalid {
                        what: "series component",
                        detail: format!("component {c} has no bricks"),
                    })?;
                    whole_header(cm, &first.0)
                } else {
                    let f = parse_file(data)?;
                    let ranges = ranges_in(&bytes, &f.packets);
                    parts.push((f.header.clone(), [0; 3], ranges));
                    f.header
                };
                if component_whole.geometry.dims != dims
                    || component_whole.channels != m.space.channels
                {
                    return Err(FormatError::Invalid {
                        what: "series component",
                        detail: format!(
                            "component {c} is {:?} with {} channel(s); the series is {dims:?} \
                             with {}",
                            component_whole.geometry.dims,
                            component_whole.channels,
                            m.space.channels
                        ),
                    }
                    .into());
                }
                offset += f64::from(weight) * component_whole.color.mean[0];
                whole.get_or_insert(component_whole);
                for (header, origin, ranges) in parts {
                    let brick = bricks.len();
                    let mut framed_packets = framed(&header, &bytes, ranges, brick)?;
                    let w2 = f64::from(weight) * f64::from(weight);
                    for p in &mut framed_packets {
                        p.summary.iter_mut().for_each(|(_, e)| *e *= w2);
                    }
                    packets.extend(framed_packets);
                    bricks.push(FileBrick {
                        header,
                        origin,
                        weight,
                    });
                }
            }
            let mut header = whole.expect("a time point names at least one component");
            header.placement = m.space.placement;
            let header = crate::bricked::time_point_header(&header, m.space.spacing, offset);
            for b in &mut bricks {
                b.header.color.mean[0] = offset;
                check_display(0, &b.header, &header)?;
            }
            (header, bricks, packets)
        };
        if u32::try_from(packets.len()).is_err() {
            return Err(FormatError::Invalid {
                what: "series time point",
                detail: format!("{} packets, more than a source numbers", packets.len()),
            }
            .into());
        }
        FileSource::with_packets(bytes, header, bricks, packets, spec)
    }

    fn with_packets(
        bytes: Vec<u8>,
        header: Header,
        bricks: Vec<FileBrick>,
        packets: Vec<FilePacket>,
        spec: &ViewSpec,
    ) -> Result<FileSource, SourceError> {
        let n = packets.len();
        let mut s = FileSource {
            bytes,
            header,
            bricks,
            packets,
            order: Vec::new(),
            cursor: 0,
            delivered: vec![false; n],
            budget: None,
            status: SourceStatus {
                connected: true,
                ..Default::default()
            },
            ahead: HashMap::new(),
        };
        s.rank(spec)?;
        Ok(s)
    }

    /// A bricked file as a session draws it ([`crate::session::RenderSession::new_bricked`]);
    /// `None` for a file of one volume.
    pub fn bricked_volume(&self) -> Option<BrickedVolume> {
        if self.bricks.is_empty() {
            return None;
        }
        let mut counts = vec![0u32; self.bricks.len()];
        for p in &self.packets {
            counts[p.brick] += 1;
        }
        Some(BrickedVolume {
            whole: self.header.clone(),
            bricks: self
                .bricks
                .iter()
                .zip(counts)
                .map(|(b, packets)| SessionBrick {
                    header: b.header.clone(),
                    origin: b.origin,
                    packets,
                })
                .collect(),
        })
    }

    /// The weight packet `id`'s values are scaled by (1 but in a series' time point).
    fn weight_of(&self, id: u32) -> f32 {
        self.bricks
            .get(self.packets[id as usize].brick)
            .map_or(1.0, |b| b.weight)
    }

    /// The header packet `id` decodes with.
    fn header_of(&self, id: u32) -> &Header {
        match self.bricks.get(self.packets[id as usize].brick) {
            Some(b) => &b.header,
            None => &self.header,
        }
    }

    /// Delivers at most `bytes` bytes of packets (the first packet always).
    pub fn with_byte_budget(mut self, bytes: Option<u64>) -> FileSource {
        self.budget = bytes;
        self
    }

    /// The file's header.
    pub fn header(&self) -> &Header {
        &self.header
    }

    /// The whole file.
    pub fn file_bytes(&self) -> &[u8] {
        &self.bytes
    }

    /// Number of packets in the file.
    pub fn packet_count(&self) -> usize {
        self.packets.len()
    }

    /// Decodes the packet at the cursor and the next ones in order (those not decoded yet),
    /// [`DECODE_AHEAD_PER_THREAD`] per core, in parallel: on this thread and scoped threads of
    /// its own, not on the rayon pool, whose threads the background planner may hold for the
    /// length of a table build (a frame thread waiting for them would stall).
    fn decode_ahead(&mut self) {
        let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
        // The cursor has moved past the packet being delivered.
        let next: Vec<u32> = self.order[self.cursor - 1..]
            .iter()
            .copied()
            .filter(|id| !self.ahead.contains_key(id))
            .take(DECODE_AHEAD_PER_THREAD * threads)
            .collect();
        let (bytes, packets) = (&self.bytes, &self.packets);
        let this = &*self;
        let decode = |ids: &[u32]| -> Vec<(u32, Decoded)> {
            ids.iter()
                .map(|&id| {
                    let data = &bytes[packets[id as usize].range.clone()];
                    let mut decoded = decode_for_session(this.header_of(id), data);
                    let weight = this.weight_of(id);
                    if let (Some((_, coefficients)), true) = (decoded.as_mut(), weight != 1.0) {
                        coefficients.iter_mut().for_each(|c| c.value *= weight);
                    }
                    (id, decoded)
                })
                .collect()
        };
        // Packet i goes to thread i mod threads: the one needed now to this thread, first.
        let share =
            |t: usize| -> Vec<u32> { next.iter().copied().skip(t).step_by(threads).collect() };
        let decoded = std::thread::scope(|scope| {
            let helpers: Vec<_> = (1..threads.min(next.len()))
                .map(|t| {
                    let ids = share(t);
                    scope.spawn(move || decode(&ids))
                })
                .collect();
            let mut all = decode(&share(0));
            for h in helpers {
                // A decoder that panicked leaves its packets to be decoded again when asked.
                if let Ok(d) = h.join() {
                    all.extend(d);
                }
            }
            all
        });
        self.ahead.extend(decoded);
    }

    fn rank(&mut self, spec: &ViewSpec) -> Result<(), SourceError> {
        let order = if self.bricks.is_empty() {
            let vis = Visibility::new(&self.header, spec)?;
            let keyed: Vec<PacketFacts> = self
                .packets
                .iter()
                .map(|p| PacketFacts {
                    tile: p.tile,
                    summary: &p.summary,
                    bytes: p.range.len(),
                })
                .collect();
            packet_order(&vis, &keyed)
        } else {
            self.bricked_order(spec)?
        };
        self.order = order
            .into_iter()
            .filter(|i| !self.delivered[*i as usize])
            .collect();
        // What was decoded for the old order may come much later now: let it go, so that the
        // source never holds more than one parallel round of decoded packets.
        self.ahead.clear();
        self.cursor = 0;
        self.status.done = self.order.is_empty();
        Ok(())
    }
}

impl FileSource {
    /// A bricked file's packets for `spec` by visible energy per byte, each brick's seen by its
    /// own view of the whole (scaled by its cue factor²), ties in file order; the packets of a
    /// brick the view does not see are left out.
    fn bricked_order(&self, spec: &ViewSpec) -> Result<Vec<u32>, SourceError> {
        let bricks: Vec<(&Header, [u64; 3])> =
            self.bricks.iter().map(|b| (&b.header, b.origin)).collect();
        let packets = self.packets.iter().map(|p| BrickPacket {
            brick: p.brick,
            tile: p.tile,
            summary: &p.summary,
            bytes: p.range.len(),
        });
        let keyed = bricked_packet_order(spec, &self.header.geometry, &bricks, packets)?;
        Ok(keyed.into_iter().map(|(_, i)| i).collect())
    }
}

/// Checks brick `i` (manifest entry `entry`, header `header`) against the manifest and the
/// first brick, for a session that draws every brick into one image.
pub(crate) fn check_session_brick(
    i: usize,
    entry: &BrickEntry,
    header: &Header,
    first: &Header,
    channels: usize,
) -> Result<(), SourceError> {
    check_display(i, header, first)?;
    check_brick(i, entry, header, first, channels)?;
    Ok(())
}

/// Checks that brick `i` (header `header`) shows its values as the first brick does, so that a
/// session can draw both into one image.
pub(crate) fn check_display(i: usize, header: &Header, first: &Header) -> Result<(), SourceError> {
    if !same_display(header, first) {
        // The bricks of one volume share the whole's offset or colour transform in this
        // version; older files of the bricked format gave each brick its own.
        let remedy = ", or compress it again with this version, whose bricks share the whole's \
                      offset and colour transform";
        return Err(SourceError::Unsupported(format!(
            "brick {i} of this bricked volume subtracts another offset or colour basis than \
             its first brick, so its bricks cannot be drawn into one image progressively; \
             render a local copy in one pass (without --progressive, --bytes, --budget-ms, \
             --record or --client-memory){remedy}"
        )));
    }
    Ok(())
}

/// The byte ranges of `packets` (slices of `bytes`) in `bytes`.
fn ranges_in(bytes: &[u8], packets: &[&[u8]]) -> Vec<std::ops::Range<usize>> {
    let base = bytes.as_ptr() as usize;
    packets
        .iter()
        .map(|p| {
            let start = p.as_ptr() as usize - base;
            start..start + p.len()
        })
        .collect()
}

/// The packets at `ranges` of `bytes` with their framing (tile, energy summary), of brick
/// `brick`; what they hold must be what `header` declares (missing or cut packets would
/// otherwise render as a blank or partial image).
fn framed(
    header: &Header,
    bytes: &[u8],
    ranges: Vec<std::ops::Range<usize>>,
    brick: usize,
) -> Result<Vec<FilePacket>, SourceError> {
    let mut packets = Vec::with_capacity(ranges.len());
    let mut held = 0u64;
    for r in ranges {
        let f = read_framing(header, &bytes[r.clone()])?;
        held = held.saturating_add(f.count as u64);
        packets.push(FilePacket {
            range: r,
            tile: f.tile,
            summary: f.summary,
            brick,
        });
    }
    check_kept(header, held)?;
    Ok(packets)
}

impl PacketSource for FileSource {
    fn try_next(&mut self) -> Option<SourcePacket> {
        let id = *self.order.get(self.cursor)?;
        let range = self.packets[id as usize].range.clone();
        if self.status.packets > 0
            && self
                .budget
                .is_some_and(|b| self.status.bytes + range.len() as u64 > b)
        {
            self.status.done = true;
            return None;
        }
        self.cursor += 1;
        self.delivered[id as usize] = true;
        self.status.packets += 1;
        self.status.bytes += range.len() as u64;
        self.status.done = self.cursor >= self.order.len();
        let data = self.bytes[range].to_vec();
        // Decoded here, as the network sources decode on their threads, so the session takes
        // every source's packets one way: this one and the next few in order at once, in
        // parallel. A packet that does not decode goes on as bytes: the session then reports
        // the error with the packet's id.
        if !self.ahead.contains_key(&id) {
            self.decode_ahead();
        }
        let decoded = self.ahead.remove(&id).flatten();
        Some(SourcePacket { id, data, decoded })
    }

    fn set_view(&mut self, spec: &ViewSpec) {
        // The spec was validated by the session; a failure here leaves the old order.
        let _ = self.rank(spec);
    }

    fn dropped(&mut self, ids: Vec<u32>) {
        for id in ids {
            if let Some(d) = self.delivered.get_mut(id as usize) {
                *d = false;
            }
        }
    }

    fn status(&self) -> SourceStatus {
        self.status.clone()
    }
}
