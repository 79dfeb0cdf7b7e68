//! The file source: a local `.wsp` file served packet by packet in the order the cache would
//! send it for the current view (visible energy per byte), up to an optional byte budget, the
//! next few packets decoded ahead in parallel.

use super::{decode_for_session, Decoded, PacketSource, SourceError, SourcePacket, SourceStatus};
use std::collections::HashMap;
use wavesplat_codec::format::packet::read_framing;
use wavesplat_codec::format::{check_kept, parse_file, Header};
use wavesplat_codec::layout::Band;
use wavesplat_codec::view::visibility::{packet_order, PacketFacts, Visibility};
use wavesplat_codec::view::ViewSpec;

/// Where a packet lies in a file and what ranks it.
#[derive(Debug, Clone)]
struct FilePacket {
    range: std::ops::Range<usize>,
    tile: usize,
    summary: Vec<(Band, f64)>,
}

/// A local `.wsp` file served packet by packet in the cache's order for the current view
/// (visible energy per byte), optionally only up to a byte budget, each packet decoded when it
/// is handed over, together with the next few in parallel (every source hands the session
/// decoded packets).
#[derive(Debug)]
pub struct FileSource {
    bytes: Vec<u8>,
    header: Header,
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
    /// Parses `bytes` (the whole file) and ranks its packets for `spec`.
    pub fn open(bytes: Vec<u8>, spec: &ViewSpec) -> Result<FileSource, SourceError> {
        let (header, ranges) = {
            let file = parse_file(&bytes)?;
            let base = bytes.as_ptr() as usize;
            let ranges: Vec<std::ops::Range<usize>> = file
                .packets
                .iter()
                .map(|p| {
                    let start = p.as_ptr() as usize - base;
                    start..start + p.len()
                })
                .collect();
            (file.header, ranges)
        };
        let mut packets = Vec::with_capacity(ranges.len());
        let mut held = 0u64;
        for r in ranges {
            let f = read_framing(&header, &bytes[r.clone()])?;
            held = held.saturating_add(f.count as u64);
            packets.push(FilePacket {
                range: r,
                tile: f.tile,
                summary: f.summary,
            });
        }
        // The packets must hold what the header declares: missing or cut packets would
        // otherwise render as a blank or partial image.
        check_kept(&header, held)?;
        let n = packets.len();
        let mut s = FileSource {
            bytes,
            header,
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
        let (header, bytes, packets) = (&self.header, &self.bytes, &self.packets);
        let decode = |ids: &[u32]| -> Vec<(u32, Decoded)> {
            ids.iter()
                .map(|&id| {
                    let data = &bytes[packets[id as usize].range.clone()];
                    (id, decode_for_session(header, data))
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
        self.order = packet_order(&vis, &keyed)
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
