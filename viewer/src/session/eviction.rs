//! The memory bound of a session: retained (already splatted) packets beyond it are dropped,
//! least visible energy per byte first (each packet's energy summed once per view, as it is
//! queued), and the ids of those a source can send again noted for it.

use super::RenderSession;
use crate::backend::AccumulationBackend;

impl<B: AccumulationBackend> RenderSession<B> {
    /// Drops retained packets beyond the memory bound, least visible energy per byte first.
    pub(super) fn evict(&mut self) {
        let Some(bound) = self.options.memory_bound else {
            return;
        };
        if self.stats.retained_bytes <= bound {
            return;
        }
        let mut candidates: Vec<(f64, u32)> = self
            .packets
            .iter()
            .filter(|(_, h)| h.queued == 0)
            .map(|(id, h)| (h.visible / h.bytes().max(1) as f64, *id))
            .collect();
        candidates.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        for (_, id) in candidates {
            if self.stats.retained_bytes <= bound {
                break;
            }
            if let Some(h) = self.packets.remove(&id) {
                self.stats.retained_bytes -= h.bytes();
                self.stats.packets_held -= 1;
                self.stats.coefficients_held -= h.coefficients.len();
                self.stats.packets_dropped += 1;
                if h.wire_bytes > 0 {
                    self.dropped.push(id);
                }
            }
        }
    }
}
