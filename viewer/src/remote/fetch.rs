//! The range source's network task: the packets the current view sees ordered as the cache
//! would send them (those that came with the head first), neighbours in the file coalesced into
//! one range, a few requests in flight, each range checked and its packets decoded and queued
//! for the session; view changes reorder what is not yet requested. A bricked volume's packets
//! are ranked across its bricks as a bricked file's are (each brick by its own view of the
//! whole); a brick the view does not see is not fetched. A range that failed every attempt
//! (the server unreachable, or busy) goes back to the head of the queue while the source reports
//! itself not connected and waits, longer while it goes on; what cannot pass (another file, a
//! status that says no, bytes that are not the volume's) stops the source.

use super::head::Head;
use super::object::{backoff, Object, ReadError};
use super::RangeSourceOptions;
use crate::source::{Control, PacketSender, SourceError, SourcePacket, SourceStatus};
use bytes::Bytes;
use futures_util::stream::FuturesUnordered;
use futures_util::StreamExt;
use std::collections::HashSet;
use std::ops::Range;
use std::sync::{Arc, Mutex};
use tokio::sync::mpsc;
use wavesplat_codec::format::packet::decode_packet;
use wavesplat_codec::view::bricked::{bricked_packet_order, BrickPacket};
use wavesplat_codec::view::priority::Priority;
use wavesplat_codec::view::ViewSpec;

/// The network task's state.
pub(super) struct Fetch {
    /// The URL as messages show it (redacted).
    pub(super) url: String,
    pub(super) object: Object,
    pub(super) options: RangeSourceOptions,
    /// Packets requested (and not dropped by the session since).
    pub(super) requested: HashSet<u32>,
    /// Packets still to request, in sending order.
    pub(super) queue: Vec<u32>,
    pub(super) status: Arc<Mutex<SourceStatus>>,
    pub(super) head: Head,
    /// The view the queue was last planned for, and how many views were applied: a request
    /// that failed after another view came is planned again with it, not put back first.
    pub(super) view: Option<ViewSpec>,
    pub(super) views: u64,
}

/// One coalesced request: its byte range in the object and the packets in it.
struct Request {
    range: Range<u64>,
    packets: Vec<u32>,
    /// Bytes at the range's start that came with the head: only the rest is requested (none
    /// when it is all of them).
    held: u64,
    /// [`Fetch::views`] when it was made.
    view: u64,
}

impl Request {
    /// Inside the bytes read with the head: no request needed.
    fn local(&self) -> bool {
        self.held >= self.range.end - self.range.start
    }
}

impl Fetch {
    fn update(&self, f: impl FnOnce(&mut SourceStatus)) {
        let mut s = self.status.lock().unwrap_or_else(|e| e.into_inner());
        f(&mut s);
    }

    /// Whether packet `i` lies inside the bytes read with the head.
    fn is_local(&self, i: u32) -> bool {
        let p = &self.head.packets[i as usize];
        self.head.base + p.offset + p.len as u64 <= self.head.first.len() as u64
    }

    /// Orders what is not yet requested for `spec` (only what it sees, when asked and the
    /// index says). Packets that came with the head go first, in that order: they cost no
    /// request, and being the start of the file they are its most significant packets, so the
    /// first image needs no round trip after the head's.
    pub(super) fn plan(&mut self, spec: &ViewSpec) -> Result<(), SourceError> {
        self.view = Some(*spec);
        self.plan_remote(spec)?;
        let (local, remote): (Vec<u32>, Vec<u32>) =
            self.queue.iter().partition(|&&i| self.is_local(i));
        self.queue = local.into_iter().chain(remote).collect();
        Ok(())
    }

    fn plan_remote(&mut self, spec: &ViewSpec) -> Result<(), SourceError> {
        let packets = &self.head.packets;
        if !self.head.indexed {
            self.queue = (0..packets.len() as u32)
                .filter(|i| !self.requested.contains(i))
                .collect();
            return Ok(());
        }
        if !self.head.bricks.is_empty() {
            let bricks: Vec<(&wavesplat_codec::format::Header, [u64; 3])> = self
                .head
                .bricks
                .iter()
                .map(|b| (&b.header, b.origin))
                .collect();
            let keyed = bricked_packet_order(
                spec,
                &self.head.header.geometry,
                &bricks,
                packets
                    .iter()
                    .zip(&self.head.packet_brick)
                    .map(|(p, &b)| BrickPacket {
                        brick: b as usize,
                        tile: p.tile as usize,
                        summary: &p.summary,
                        bytes: p.len as usize,
                    }),
            )?;
            self.queue = keyed
                .into_iter()
                .filter(|(e, i)| {
                    !self.requested.contains(i) && (!self.options.visible_only || *e > 0.0)
                })
                .map(|(_, i)| i)
                .collect();
            return Ok(());
        }
        let priority = Priority::new(&self.head.header, spec)?;
        self.queue = priority
            .order(packets)
            .into_iter()
            .filter(|i| !self.requested.contains(i))
            .filter(|&i| {
                !self.options.visible_only || priority.visible_energy(&packets[i as usize]) > 0.0
            })
            .collect();
        Ok(())
    }

    /// Takes the next request off the queue: its head packet, grown over the packets next to
    /// it in the file (ids are file order and packets are contiguous) that are among the next
    /// few in the sending order, so nothing is fetched that the view does not want.
    fn next_request(&mut self) -> Option<Request> {
        let first = *self.queue.first()?;
        let look = self.queue.len().min(self.options.lookahead.max(1));
        let wanted: std::collections::HashMap<u32, usize> = self.queue[..look]
            .iter()
            .enumerate()
            .map(|(k, &id)| (id, k))
            .collect();
        let len = |i: u32| self.head.packets[i as usize].len as u64;
        // Packets that came with the head are not mixed with ones still to fetch.
        let local = self.is_local(first);
        let wanted: std::collections::HashMap<u32, usize> = wanted
            .into_iter()
            .filter(|(id, _)| self.is_local(*id) == local)
            .collect();
        let (mut lo, mut hi) = (first, first);
        let mut bytes = len(first);
        loop {
            let right = hi.checked_add(1).filter(|r| {
                wanted.contains_key(r) && bytes + len(*r) <= self.options.max_request_bytes
            });
            let left = lo.checked_sub(1).filter(|l| {
                wanted.contains_key(l) && bytes + len(*l) <= self.options.max_request_bytes
            });
            match (right, left) {
                (Some(r), _) => {
                    hi = r;
                    bytes += len(r);
                }
                (None, Some(l)) => {
                    lo = l;
                    bytes += len(l);
                }
                (None, None) => break,
            }
        }
        let packets: Vec<u32> = (lo..=hi).collect();
        let mut taken: Vec<usize> = packets.iter().map(|id| wanted[id]).collect();
        taken.sort_unstable();
        for k in taken.into_iter().rev() {
            self.queue.remove(k);
        }
        for &p in &packets {
            self.requested.insert(p);
        }
        let start = self.head.base + self.head.packets[lo as usize].offset;
        let last = &self.head.packets[hi as usize];
        let end = self.head.base + last.offset + last.len as u64;
        let held = (self.head.first.len() as u64).clamp(start, end) - start;
        Some(Request {
            range: start..end,
            packets,
            held,
            view: self.views,
        })
    }

    /// Puts the packets of a request not made back at the head of the queue, in order.
    fn unrequest(&mut self, req: Request) {
        for id in &req.packets {
            self.requested.remove(id);
        }
        self.queue.splice(0..0, req.packets);
    }

    /// Puts the packets of a request that failed back to be asked for again: at the head of the
    /// queue, or, where another view came since it was made, where that view's plan puts them
    /// (it may not see them at all).
    fn put_back(&mut self, req: Request) {
        let replan = (req.view != self.views).then_some(self.view).flatten();
        self.unrequest(req);
        if let Some(spec) = replan {
            if let Err(e) = self.plan(&spec) {
                tracing::warn!(error = %e, "planning a view for range requests");
            }
        }
    }

    fn apply(&mut self, c: Control) {
        match c {
            Control::View(spec) => {
                self.views += 1;
                if let Err(e) = self.plan(&spec) {
                    tracing::warn!(error = %e, "planning a view for range requests");
                }
                self.update(SourceStatus::view_applied);
            }
            Control::Dropped(ids) => {
                for id in ids {
                    self.requested.remove(&id);
                }
            }
        }
    }

    pub(super) async fn run(mut self, tx: PacketSender, mut ctl: mpsc::UnboundedReceiver<Control>) {
        let mut flight = FuturesUnordered::new();
        let mut first_packet = true;
        // While the server cannot be reached: when to ask again, and the failures in a row.
        let mut paused_until: Option<tokio::time::Instant> = None;
        let mut outages = 0u32;
        loop {
            if paused_until.is_some_and(|t| tokio::time::Instant::now() >= t) {
                paused_until = None;
            }
            while flight.len() < self.options.in_flight.max(1) {
                let Some(req) = self.next_request() else {
                    break;
                };
                // While paused only what came with the head is handed on.
                if paused_until.is_some() && !req.local() {
                    self.unrequest(req);
                    break;
                }
                let object = self.object.clone();
                let first = self.head.first.clone();
                flight.push(async move {
                    let (start, end) = (req.range.start as usize, req.range.end as usize);
                    let got = if req.local() {
                        Ok(first.slice(start..end))
                    } else {
                        // Only what the head did not bring; what it did goes in front.
                        let from = req.range.start + req.held;
                        let tail = object.read(Some(from..req.range.end)).await;
                        tail.map(|(tail, _)| {
                            if req.held == 0 {
                                tail
                            } else {
                                let mut all = first[start..start + req.held as usize].to_vec();
                                all.extend_from_slice(&tail);
                                Bytes::from(all)
                            }
                        })
                    };
                    (req, got)
                });
            }
            let idle = flight.is_empty();
            self.update(|s| s.done = idle && self.queue.is_empty());
            let resume = paused_until;
            tokio::select! {
                c = ctl.recv() => match c {
                    Some(c) => self.apply(c),
                    None => return,
                },
                Some((req, got)) = flight.next(), if !idle => {
                    let remote = !req.local();
                    match got {
                        Err(e) if !e.is_final() => {
                            if paused_until.is_none() {
                                outages += 1;
                            }
                            let pause = backoff(self.object.pacing.outage_pause, outages)
                                .max(e.retry_after().unwrap_or_default());
                            let until = tokio::time::Instant::now() + pause;
                            paused_until = Some(paused_until.map_or(until, |t| t.max(until)));
                            tracing::warn!(
                                url = %self.url, error = %e, ?pause,
                                "range requests failed; asking again after a pause"
                            );
                            let problem = format!(
                                "{} unreachable, asking again in {:.1} s: {e}",
                                self.url,
                                pause.as_secs_f64()
                            );
                            self.put_back(req);
                            self.update(|s| {
                                s.connected = false;
                                s.problem = Some(problem);
                            });
                        }
                        got => {
                            if remote && got.is_ok() && outages > 0 {
                                outages = 0;
                                paused_until = None;
                                self.update(|s| {
                                    s.connected = true;
                                    s.problem = None;
                                    s.reconnects += 1;
                                });
                            }
                            match self.deliver(req, got, &tx, &mut first_packet).await {
                                Ok(true) => {}
                                Ok(false) => return,
                                Err(e) => {
                                    tracing::error!(url = %self.url, error = %e, "range source stopped");
                                    self.update(|s| {
                                        s.connected = false;
                                        s.problem = Some(e.clone());
                                        s.failed = Some(e);
                                    });
                                    return;
                                }
                            }
                        }
                    }
                }
                _ = tokio::time::sleep_until(resume.unwrap_or_else(tokio::time::Instant::now)),
                    if resume.is_some() => {}
            }
        }
    }

    /// Checks a response, decodes its packets and hands them on; false when the session went
    /// away, an error when the server's bytes cannot be this volume's.
    async fn deliver(
        &mut self,
        req: Request,
        got: Result<Bytes, ReadError>,
        tx: &PacketSender,
        first_packet: &mut bool,
    ) -> Result<bool, String> {
        let data =
            got.map_err(|e| format!("fetching bytes {:?} of {}: {e}", req.range, self.url))?;
        let want = req.range.end - req.range.start;
        self.update(|s| {
            if !req.local() {
                s.requests += 1;
                s.received_bytes += (data.len() as u64).saturating_sub(req.held);
            }
            if *first_packet {
                s.requests_before_first_packet = s.requests;
            }
        });
        *first_packet = false;
        if data.len() as u64 != want {
            return Err(format!(
                "{} answered {} bytes for the range {:?} of {want}: truncated or changed on the server",
                self.url,
                data.len(),
                req.range
            ));
        }
        for id in req.packets {
            let p = &self.head.packets[id as usize];
            let start = (self.head.base + p.offset - req.range.start) as usize;
            let bytes = data[start..start + p.len as usize].to_vec();
            let mut d = decode_packet(self.head.header_of(id), &bytes)
                .map_err(|e| format!("packet {id} of {}: {e}", self.url))?;
            let weight = self.head.weight_of(id);
            if weight != 1.0 {
                d.coefficients.iter_mut().for_each(|c| c.value *= weight);
            }
            if self.head.indexed && (d.tile as u32 != p.tile || d.layer as u32 != p.layer) {
                return Err(format!(
                    "packet {id} of {} is tile {} layer {}, its index says tile {} layer {}",
                    self.url, d.tile, d.layer, p.tile, p.layer
                ));
            }
            let len = bytes.len() as u64;
            let packet = SourcePacket {
                id,
                data: bytes,
                decoded: Some((d.tile, d.coefficients)),
            };
            if tx.send(packet).await.is_err() {
                return Ok(false);
            }
            self.update(|s| {
                s.packets += 1;
                s.bytes += len;
            });
        }
        Ok(true)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use object_store::path::Path as ObjectPath;
    use wavesplat_codec::format::index::{read_indexed_head, HeadRead};
    use wavesplat_codec::view::View;

    /// A fetch over a published phantom (no network: planning and coalescing only).
    fn fetch(first_bytes: usize) -> Fetch {
        use wavesplat_compressor::encode::{compress, CompressOptions, Target, TileChoice};
        let wsp = compress(
            &wavesplat_compressor::phantom::Phantom::SheppLogan.generate([48, 48, 48]),
            &CompressOptions {
                target: Target::Fraction(0.2),
                tile: TileChoice::Size(8),
                refine: None,
                ..Default::default()
            },
            &|_, _| {},
        )
        .unwrap()
        .bytes;
        let object = wavesplat_codec::format::index::indexed_layout(&wsp).unwrap();
        let HeadRead::Indexed(h) = read_indexed_head(&object).unwrap() else {
            panic!("head incomplete")
        };
        Fetch {
            url: "test".into(),
            object: Object::store(
                Arc::new(object_store::memory::InMemory::new()),
                ObjectPath::from("v.wspx"),
            ),
            options: RangeSourceOptions::default(),
            requested: HashSet::new(),
            queue: Vec::new(),
            status: Arc::new(Mutex::new(SourceStatus::default())),
            view: None,
            views: 0,
            head: Head {
                first: Bytes::copy_from_slice(&object[..first_bytes.min(object.len())]),
                object_bytes: h.object_bytes(),
                header: h.header,
                packets: h.packets,
                bricks: Vec::new(),
                packet_brick: Vec::new(),
                weights: Vec::new(),
                series: None,
                base: h.wsp_offset,
                indexed: true,
            },
        }
    }

    #[test]
    fn a_corner_asks_for_less_and_a_view_change_reorders_only_what_is_left() {
        let mut f = fetch(0);
        let n = f.head.packets.len();
        let whole = ViewSpec::single(View::new(0.3, 0.2, 64, 64));
        f.plan(&whole).unwrap();
        assert_eq!(f.queue.len(), n, "the whole volume is in view");
        let mut corner_view = View::new(0.0, 0.0, 64, 64);
        corner_view.zoom = Some(6.0);
        corner_view.pan = [20.0, 20.0];
        let corner = ViewSpec::single(corner_view);
        f.plan(&corner).unwrap();
        assert!(
            f.queue.len() < n * 3 / 4,
            "{} of {n} for a corner",
            f.queue.len()
        );
        // Requests are runs of neighbouring packets, each wanted, none twice.
        let mut seen = HashSet::new();
        let first = f.next_request().unwrap();
        for w in first.packets.windows(2) {
            assert_eq!(w[1], w[0] + 1);
        }
        let p = &f.head.packets;
        assert_eq!(
            first.range.start,
            f.head.base + p[first.packets[0] as usize].offset
        );
        seen.extend(first.packets.iter().copied());
        // Back to the whole view: what was requested is not asked again, the rest is.
        f.plan(&whole).unwrap();
        assert_eq!(f.queue.len(), n - seen.len());
        assert!(f.queue.iter().all(|i| !seen.contains(i)));
        // A dropped packet may be asked for again after the next view change.
        let dropped = first.packets[0];
        f.apply(Control::Dropped(vec![dropped]));
        f.plan(&whole).unwrap();
        assert!(f.queue.contains(&dropped));
    }

    #[test]
    fn a_failed_request_goes_back_first_or_where_a_newer_view_puts_it() {
        let whole = ViewSpec::single(View::new(0.3, 0.2, 64, 64));
        let mut corner_view = View::new(0.0, 0.0, 64, 64);
        corner_view.zoom = Some(6.0);
        corner_view.pan = [20.0, 20.0];
        let corner = ViewSpec::single(corner_view);
        // No view since it was made: back at the head of the queue, in order.
        let mut f = fetch(0);
        f.plan(&whole).unwrap();
        let r = f.next_request().unwrap();
        let packets = r.packets.clone();
        f.put_back(r);
        assert_eq!(&f.queue[..packets.len()], &packets[..]);
        assert!(packets.iter().all(|p| !f.requested.contains(p)));
        // Another view since: where that view's plan puts it, as if never asked for.
        let mut f = fetch(0);
        f.plan(&whole).unwrap();
        let r = f.next_request().unwrap();
        f.apply(Control::View(corner));
        f.put_back(r);
        let mut fresh = fetch(0);
        fresh.plan(&corner).unwrap();
        assert_eq!(f.queue, fresh.queue);
        assert!(f.requested.is_empty());
    }

    #[test]
    fn packets_that_came_with_the_head_go_first_and_alone() {
        let mut f = fetch(usize::MAX);
        let end = f.head.base + f.head.packets[3].offset + f.head.packets[3].len as u64;
        f.head.first = f.head.first.slice(..end as usize);
        f.plan(&ViewSpec::single(View::new(0.3, 0.2, 64, 64)))
            .unwrap();
        assert!(f.queue[..4].iter().all(|&i| i < 4), "{:?}", &f.queue[..6]);
        let r = f.next_request().unwrap();
        assert!(
            r.local() && r.packets.iter().all(|&i| i < 4),
            "{:?}",
            r.packets
        );
        let mut next = f.next_request().unwrap();
        while next.local() {
            next = f.next_request().unwrap();
        }
        assert!(next.packets.iter().all(|&i| i >= 4));
    }

    /// A packet that begins inside the bytes read with the head is asked for from where they
    /// end: the request holds that prefix, and only the rest goes over the wire.
    #[test]
    fn a_packet_across_the_head_is_asked_for_from_its_end() {
        let mut f = fetch(usize::MAX);
        let p = &f.head.packets[2];
        let (start, len) = (f.head.base + p.offset, p.len as u64);
        assert!(len > 2, "the test needs a packet of a few bytes");
        f.head.first = f.head.first.slice(..(start + len / 2) as usize);
        f.plan(&ViewSpec::single(View::new(0.3, 0.2, 64, 64)))
            .unwrap();
        let mut r = f.next_request().unwrap();
        while r.local() {
            r = f.next_request().unwrap();
        }
        while !r.packets.contains(&2) {
            r = f.next_request().unwrap();
        }
        assert_eq!(r.range.start, start, "{:?}", r.packets);
        assert_eq!(r.held, len / 2);
        assert!(!r.local());
    }
}
