//! Planning and accumulation in batches: a run of coefficients planned and summed into a backend
//! a bounded batch at a time, short runs gathered and long ones cut, with reusable buffers.

use super::{RenderStats, ViewPlan};
use crate::backend::{AccumulationBackend, SplatRecord};
use crate::RenderError;
use wavesplat_codec::format::packet::Coefficient;

/// Most coefficients planned and accumulated at a time by [`ViewPlan::splat_in_batches`]. Every
/// batch's records are summed before the next batch is planned, and the record and batch
/// buffers are reused, so their pages are faulted in once. A one-shot `render` is cold (every
/// page fresh): on two cores MNI at 1.25 % (165 k coefficients, 256²) was done 50 ms after the
/// request in batches of 2^16, 56 ms in one batch; MNI at 5 % (639 k, 512²) 245 ms against 254
/// (2^14) and 284 (2^20).
pub const SPLAT_BATCH: usize = 1 << 16;

/// The reusable buffers of [`ViewPlan::splat_in_batches`]: one batch's records, and the
/// coefficients of short runs gathered into one batch. Keep one between calls (the one-shot
/// [`crate::Renderer`] does) and their pages stay faulted in.
#[derive(Debug, Default)]
pub struct SplatBuffers {
    records: Vec<SplatRecord>,
    batch: Vec<Coefficient>,
}

impl ViewPlan {
    /// Plans and accumulates every coefficient of `runs` (consecutive runs, such as a file's
    /// packets, in order) into `backend`, at most `batch_size` coefficients at a time (short
    /// runs are gathered into one batch, a long one is cut), with `buffers` reused: the image
    /// equals one [`ViewPlan::splats`] of them all and one accumulation, up to the order of f32
    /// additions, without holding every record at once (three per coefficient for a family
    /// with gradient tables: 12 MB for 165 k coefficients). Counts into `stats`, pixel updates
    /// included.
    pub fn splat_in_batches<'a>(
        &mut self,
        runs: impl IntoIterator<Item = &'a [Coefficient]>,
        backend: &mut dyn AccumulationBackend,
        batch_size: usize,
        buffers: &mut SplatBuffers,
        stats: &mut RenderStats,
    ) -> Result<(), RenderError> {
        let batch_size = batch_size.max(1);
        let SplatBuffers { records, batch } = buffers;
        batch.clear();
        let mut flush = |plan: &mut ViewPlan,
                         part: &[Coefficient],
                         stats: &mut RenderStats|
         -> Result<(), RenderError> {
            records.clear();
            plan.splats(part, records, stats)?;
            stats.pixel_updates += backend.accumulate(&plan.atlas(), records)?;
            Ok(())
        };
        let mut runs = runs.into_iter().peekable();
        while let Some(run) = runs.next() {
            if !batch.is_empty() && batch.len() + run.len() > batch_size {
                flush(self, batch, stats)?;
                batch.clear();
            }
            // A run that fills a batch alone, or that no following run joins (the last one, or
            // one whose successor would not fit beside it: the one-shot renderer's single
            // run), is splatted from where it lies instead of being copied into the batch.
            let alone = batch.is_empty()
                && runs
                    .peek()
                    .is_none_or(|next| run.len() + next.len() > batch_size);
            if run.len() >= batch_size || alone {
                for part in run.chunks(batch_size) {
                    flush(self, part, stats)?;
                }
            } else {
                batch.extend_from_slice(run);
            }
        }
        if !batch.is_empty() {
            flush(self, batch, stats)?;
            batch.clear();
        }
        Ok(())
    }
}
