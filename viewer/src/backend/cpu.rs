//! The CPU accumulation backend: records are binned into 64×64 screen tiles and the tiles are
//! summed in parallel (rayon), each into its own f32 buffer visiting its records in input
//! order, so the image is bit-identical for any number of threads. The image persists between
//! `accumulate` calls (progressive refinement adds to it).

use super::{check_record, AccumulationBackend, BackendError, FootprintAtlas, Layout, SplatRecord};
use crate::image::Image;
use rayon::prelude::*;

/// Screen tile side (pixels).
pub const TILE: usize = 64;

/// Accumulates on the CPU.
#[derive(Debug, Default)]
pub struct CpuBackend {
    layout: Option<Layout>,
    image: Vec<f32>,
}

impl CpuBackend {
    /// A backend with no target yet.
    pub fn new() -> CpuBackend {
        CpuBackend::default()
    }
}

impl AccumulationBackend for CpuBackend {
    fn name(&self) -> String {
        "cpu".into()
    }

    fn begin(&mut self, layout: Layout) -> Result<(), BackendError> {
        layout.validate()?;
        self.image.clear();
        self.image
            .resize(layout.total_width() * layout.height * layout.channels, 0.0);
        self.layout = Some(layout);
        Ok(())
    }

    fn accumulate(
        &mut self,
        atlas: &FootprintAtlas,
        records: &[SplatRecord],
    ) -> Result<u64, BackendError> {
        let layout = self
            .layout
            .ok_or_else(|| BackendError::Layout("accumulate before begin".into()))?;
        for r in records {
            check_record(r, atlas, &layout)?;
        }
        Ok(accumulate(&mut self.image, &layout, atlas, records))
    }

    fn read(&mut self) -> Result<Image, BackendError> {
        let layout = self
            .layout
            .ok_or_else(|| BackendError::Layout("read before begin".into()))?;
        Ok(Image {
            width: layout.total_width(),
            height: layout.height,
            channels: layout.channels,
            data: self.image.clone(),
        })
    }
}

/// Columns [lo, hi) of view `v` in the whole target and the record's clipped pixel box.
fn clipped(r: &SplatRecord, rect: &super::PhaseRect, layout: &Layout) -> Option<[i64; 4]> {
    let (w, h) = (layout.width as i64, layout.height as i64);
    let xa = (r.x0 as i64).max(0);
    let xb = (r.x0 as i64 + rect.cols as i64).min(w);
    let ya = (r.y0 as i64).max(0);
    let yb = (r.y0 as i64 + rect.rows as i64).min(h);
    if xa >= xb || ya >= yb {
        return None;
    }
    let off = r.view as i64 * w;
    Some([xa + off, xb + off, ya, yb])
}

/// Adds `records` (already checked) into `image`; returns the pixel updates.
fn accumulate(
    image: &mut [f32],
    layout: &Layout,
    atlas: &FootprintAtlas,
    records: &[SplatRecord],
) -> u64 {
    let width = layout.total_width();
    let height = layout.height;
    let channels = layout.channels;
    let tiles_x = width.div_ceil(TILE);
    let tiles_y = height.div_ceil(TILE);
    // Bin into tiles (in input order).
    let mut bins: Vec<Vec<u32>> = vec![Vec::new(); tiles_x * tiles_y];
    for (i, r) in records.iter().enumerate() {
        let rect = &atlas.phases[r.phase as usize];
        let Some([xa, xb, ya, yb]) = clipped(r, rect, layout) else {
            continue;
        };
        for ty in (ya as usize / TILE)..=((yb - 1) as usize / TILE) {
            for tx in (xa as usize / TILE)..=((xb - 1) as usize / TILE) {
                bins[ty * tiles_x + tx].push(i as u32);
            }
        }
    }
    let results: Vec<(Vec<f32>, u64)> = bins
        .par_iter()
        .enumerate()
        .map(|(t, bin)| {
            let tx = (t % tiles_x) * TILE;
            let ty = (t / tiles_x) * TILE;
            let tw = TILE.min(width - tx);
            let th = TILE.min(height - ty);
            let mut buf = vec![0.0f32; tw * th * channels];
            let mut updates = 0u64;
            for &i in bin {
                let r = &records[i as usize];
                let rect = &atlas.phases[r.phase as usize];
                let Some([xa, xb, ya, yb]) = clipped(r, rect, layout) else {
                    continue;
                };
                let x0 = r.x0 as i64 + r.view as i64 * layout.width as i64;
                let xa = xa.max(tx as i64);
                let xb = xb.min((tx + tw) as i64);
                let ya = ya.max(ty as i64);
                let yb = yb.min((ty + th) as i64);
                if xa >= xb || ya >= yb {
                    continue;
                }
                let n = (xb - xa) as usize;
                let ch = r.channel as usize;
                let data = &atlas.data[rect.offset as usize..];
                let cols = rect.cols as usize;
                for y in ya..yb {
                    let src = (y - r.y0 as i64) as usize * cols + (xa - x0) as usize;
                    let dst = ((y as usize - ty) * tw + (xa as usize - tx)) * channels + ch;
                    let srow = &data[src..src + n];
                    if channels == 1 {
                        for (d, v) in buf[dst..dst + n].iter_mut().zip(srow) {
                            *d += r.value * v;
                        }
                    } else {
                        for (k, v) in srow.iter().enumerate() {
                            buf[dst + k * channels] += r.value * v;
                        }
                    }
                }
                updates += (n * (yb - ya) as usize) as u64;
            }
            (buf, updates)
        })
        .collect();
    let mut total = 0u64;
    for (t, (buf, updates)) in results.into_iter().enumerate() {
        if updates == 0 {
            continue;
        }
        total += updates;
        let tx = (t % tiles_x) * TILE;
        let ty = (t / tiles_x) * TILE;
        let tw = TILE.min(width - tx);
        let th = TILE.min(height - ty);
        for y in 0..th {
            let dst = ((ty + y) * width + tx) * channels;
            for (d, s) in image[dst..dst + tw * channels]
                .iter_mut()
                .zip(&buf[y * tw * channels..(y + 1) * tw * channels])
            {
                *d += s;
            }
        }
    }
    total
}
