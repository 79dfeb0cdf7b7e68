//! Packets into a session: decoded here or by their source, or loose coefficients held per
//! tile under local ids; each is checked, counted and queued for the current view, and the
//! memory bound enforced after it.

use super::{Held, RenderSession, SessionError};
use crate::backend::AccumulationBackend;
use crate::source::SourcePacket;
use crate::RenderError;
use wavesplat_codec::format::packet::{decode_packet, Coefficient};
use wavesplat_codec::format::FormatError;

/// The error of a packet id no brick of a bricked volume has.
fn unknown_packet(id: u32) -> SessionError {
    SessionError::Packet {
        id,
        source: FormatError::Invalid {
            what: "packet id",
            detail: "no brick of the volume has a packet of this id".into(),
        },
    }
}

impl<B: AccumulationBackend> RenderSession<B> {
    /// Decodes and queues a packet (a packet already held is ignored).
    pub fn add_packet(&mut self, id: u32, bytes: &[u8]) -> Result<(), SessionError> {
        if self.packets.contains_key(&id) {
            return Ok(());
        }
        let header = self.header_of(id).ok_or_else(|| unknown_packet(id))?;
        let d =
            decode_packet(header, bytes).map_err(|source| SessionError::Packet { id, source })?;
        self.add_decoded(id, bytes.len(), d.tile, d.coefficients)
    }

    /// Takes a packet as its source handed it over: already decoded, or as bytes.
    pub fn add_from_source(&mut self, p: SourcePacket) -> Result<(), SessionError> {
        match p.decoded {
            Some((tile, coefficients)) => self.add_decoded(p.id, p.data.len(), tile, coefficients),
            None => self.add_packet(p.id, &p.data),
        }
    }

    /// Takes packet `id` (of `wire_bytes` bytes) that its source already decoded into the
    /// coefficients of `tile`: the same as [`RenderSession::add_packet`] without decoding on
    /// this thread.
    pub fn add_decoded(
        &mut self,
        id: u32,
        wire_bytes: usize,
        tile: usize,
        coefficients: Vec<Coefficient>,
    ) -> Result<(), SessionError> {
        if self.packets.contains_key(&id) {
            return Ok(());
        }
        self.stats.packets_received += 1;
        self.stats.bytes_received += wire_bytes as u64;
        self.insert(id, tile, coefficients, wire_bytes)
    }

    /// Queues coefficients that did not come in a packet (a local source or a test); they are
    /// held per tile under local ids, like packets that cannot be asked for again.
    pub fn add_coefficients(&mut self, coefficients: Vec<Coefficient>) -> Result<(), SessionError> {
        if self.bricks.is_some() {
            return Err(SessionError::Render(RenderError::Unsupported(
                "loose coefficients in a bricked session (its packets name their brick)",
            )));
        }
        for c in &coefficients {
            crate::pieces::check_coefficient(c, &self.header.geometry, self.header.channels)?;
        }
        let mut by_tile: std::collections::BTreeMap<usize, Vec<Coefficient>> = Default::default();
        for c in coefficients {
            let pos = [c.pos[0] as usize, c.pos[1] as usize, c.pos[2] as usize];
            by_tile
                .entry(self.header.tile_of(c.band, pos))
                .or_default()
                .push(c);
        }
        for (tile, cs) in by_tile {
            // Local ids count down from u32::MAX; one a packet already holds is skipped (a
            // replaced entry would leave its bytes counted).
            let mut id = self.next_local_id;
            while self.packets.contains_key(&id) {
                id = id.wrapping_sub(1);
            }
            self.next_local_id = id.wrapping_sub(1);
            self.insert(id, tile, cs, 0)?;
        }
        Ok(())
    }

    fn insert(
        &mut self,
        id: u32,
        tile: usize,
        coefficients: Vec<Coefficient>,
        wire_bytes: usize,
    ) -> Result<(), SessionError> {
        let header = self.header_of(id).ok_or_else(|| unknown_packet(id))?;
        for c in &coefficients {
            crate::pieces::check_coefficient(c, &header.geometry, header.channels)?;
        }
        self.stats.coefficients_received += coefficients.len() as u64;
        let mut held = Held {
            tile,
            coefficients,
            queued: 0,
            wire_bytes,
            fresh: false,
            visible: 0.0,
        };
        self.enqueue(id, &mut held);
        let bytes = held.bytes();
        if held.queued == 0 {
            self.stats.retained_bytes += bytes;
        } else {
            self.stats.transient_bytes += bytes;
            held.fresh = true;
            self.fresh_bytes += bytes;
        }
        self.stats.packets_held += 1;
        self.stats.coefficients_held += held.coefficients.len();
        self.packets.insert(id, held);
        self.note_peak();
        self.evict();
        Ok(())
    }

    fn note_peak(&mut self) {
        self.stats.peak_bytes = self
            .stats
            .peak_bytes
            .max(self.stats.retained_bytes + self.stats.transient_bytes);
    }
}
