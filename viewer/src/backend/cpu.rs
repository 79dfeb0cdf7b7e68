//! The CPU accumulation backend: records are binned into 64×64 screen tiles (in chunks of
//! records, the chunks in parallel) and the tiles are summed in parallel (rayon), each into its
//! own f32 buffer visiting its records in input order, so the image is bit-identical for any
//! number of threads. A footprint and its gradient records, which cover the same pixels, are
//! summed in one sweep. The image persists between `accumulate` calls (progressive refinement
//! adds to it).

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

/// Consecutive records that cover the same pixels: a footprint and its two gradient
/// corrections (the planner emits them one after the other with the same corner, channel,
/// view and table shape). A group is summed in one sweep over its pixels, each pixel taking the
/// records' products in their input order, so the sums are bit-identical to one sweep per
/// record while the image is read and written once instead of once per record.
#[derive(Debug, Clone, Copy)]
struct Group {
    /// Index of the first record.
    first: u32,
    /// Records in the group (1 to [`MAX_GROUP`]).
    len: u32,
    /// The clipped box in the whole target: columns [xa, xb), rows [ya, yb).
    bounds: [i64; 4],
}

/// Most records summed in one sweep.
const MAX_GROUP: usize = 3;

/// Records grouped and binned per chunk of this many, the chunks in parallel. A group cut by
/// a chunk's end becomes two groups, which sum the same: each pixel still takes the products
/// in input order.
const BIN_CHUNK: usize = 8192;

/// One chunk's groups and, per tile, the indices of those that reach it (in input order).
struct Binned {
    groups: Vec<Group>,
    bins: Vec<Vec<u32>>,
}

/// Splits `records` (the first of them at index `first` of all records) into groups in input
/// order, dropping those wholly off the target.
fn groups(
    records: &[SplatRecord],
    first: usize,
    atlas: &FootprintAtlas,
    layout: &Layout,
) -> Vec<Group> {
    let mut out = Vec::with_capacity(records.len() / 2);
    let mut i = 0;
    while i < records.len() {
        let r = &records[i];
        let rect = &atlas.phases[r.phase as usize];
        let mut len = 1;
        while len < MAX_GROUP && i + len < records.len() {
            let q = &records[i + len];
            let qr = &atlas.phases[q.phase as usize];
            if (q.x0, q.y0, q.channel, q.view) != (r.x0, r.y0, r.channel, r.view)
                || (qr.cols, qr.rows) != (rect.cols, rect.rows)
            {
                break;
            }
            len += 1;
        }
        if let Some(bounds) = clipped(r, rect, layout) {
            out.push(Group {
                first: (first + i) as u32,
                len: len as u32,
                bounds,
            });
        }
        i += len;
    }
    out
}

/// Adds `N` records' samples into the tile buffer: `rows` rows of `n` pixels, row `y` at
/// buffer index `dst0 + y · stride` (channel stride `channels`) and sample offset `y · cols` in
/// each member's table (the tables run on past the group's last sample, to the atlas's end).
/// Each pixel takes the members' products in order, d + v₀a + v₁b + …, which rounds exactly as
/// one sweep per record.
#[allow(clippy::too_many_arguments)] // the group's geometry, spelled out for the hot loop
fn sweep<const N: usize>(
    buf: &mut [f32],
    channels: usize,
    n: usize,
    rows: usize,
    (dst0, stride): (usize, usize),
    cols: usize,
    members: [(&[f32], f32); N],
) {
    let values = members.map(|(_, v)| v);
    let tables = members.map(|(t, _)| t);
    if channels == 1 && sweep_quads(buf, n, rows, (dst0, stride), cols, tables, values) {
        return;
    }
    for y in 0..rows {
        let (d, s) = (dst0 + y * stride, y * cols);
        let samples = tables.map(|t| &t[s..]);
        if channels == 1 {
            sweep_row(&mut buf[d..], n, samples, values);
        } else {
            for i in 0..n {
                let d = &mut buf[d + i * channels];
                let mut acc = *d;
                for k in 0..N {
                    acc += values[k] * samples[k][i];
                }
                *d = acc;
            }
        }
    }
}

/// [`sweep`] of a single-channel tile where every row may be read and written as whole quads
/// (the last row, which reaches furthest into the tile buffer and into each table, has room
/// for its last quad); returns false, having done nothing, where it may not. Each row is cut
/// into quads once (`as_chunks`, so the loop over them needs no bounds checks), and a row's
/// last 1–3 pixels are summed as a quad whose lanes past the row add +0.0: the products there
/// are masked to zero bits, which leaves those pixels bit for bit as they were (a tile starts at
/// +0.0 and a sum is −0.0 only when both terms are, so no pixel holds −0.0, and x + 0.0 = x for
/// every other x). The mask is one `and` per lane; a select by lane index compiled to scalar
/// multiplies and shuffles.
#[inline(always)]
fn sweep_quads<const N: usize>(
    buf: &mut [f32],
    n: usize,
    rows: usize,
    (dst0, stride): (usize, usize),
    cols: usize,
    tables: [&[f32]; N],
    values: [f32; N],
) -> bool {
    if rows == 0 || n == 0 {
        return true;
    }
    let whole = n / 4;
    let rest = n % 4;
    let padded = (whole + usize::from(rest > 0)) * 4;
    let last = rows - 1;
    if dst0 + last * stride + padded > buf.len()
        || tables.iter().any(|t| last * cols + padded > t.len())
    {
        return false;
    }
    // Opaque to the optimizer, which would otherwise turn each masked lane back into a branch
    // around a scalar load and multiply.
    let mask: [u32; 4] =
        std::hint::black_box(std::array::from_fn(|l| if l < rest { u32::MAX } else { 0 }));
    for y in 0..rows {
        let d = dst0 + y * stride;
        let s = y * cols;
        let (dst, _) = buf[d..d + padded].as_chunks_mut::<4>();
        let src = tables.map(|t| t[s..s + padded].as_chunks::<4>().0);
        let (body, tail) = dst.split_at_mut(whole);
        if whole >= 4 {
            // A long row as one run of pixels, vectorized along the run (quad by quad, the
            // optimizer vectorizes across every four quads, transposing them: 30 % slower for
            // a cubic 512² view).
            let body = body.as_flattened_mut();
            let src_body = src.map(|q| &q[..whole].as_flattened()[..body.len()]);
            for (i, pixel) in body.iter_mut().enumerate() {
                let mut acc = *pixel;
                for k in 0..N {
                    acc += values[k] * src_body[k][i];
                }
                *pixel = acc;
            }
        } else {
            // A short row quad by quad: one vector operation per member and quad.
            let src_body = src.map(|q| &q[..body.len()]);
            for (i, quad) in body.iter_mut().enumerate() {
                let mut acc = *quad;
                for k in 0..N {
                    let q = &src_body[k][i];
                    for l in 0..4 {
                        acc[l] += values[k] * q[l];
                    }
                }
                *quad = acc;
            }
        }
        if let Some(quad) = tail.first_mut() {
            let mut acc = *quad;
            for k in 0..N {
                let q = &src[k][whole];
                for l in 0..4 {
                    acc[l] += f32::from_bits((values[k] * q[l]).to_bits() & mask[l]);
                }
            }
            *quad = acc;
        }
    }
    true
}

/// One row of [`sweep`] for a single-channel tile: `n` pixels from `dst[0]` on, four at a time.
/// Footprint rows are short (~12 pixels for a linear 256² view), so the last 1–3 pixels would
/// cost as much as the rest one at a time; where the buffer and the tables run on for four more
/// values they are summed as four, the lanes past the row adding 0.0. That leaves those pixels
/// bit for bit as they were: a tile starts at +0.0 and a sum is −0.0 only when both terms are,
/// so no pixel holds −0.0, and x + 0.0 = x for every other x (NaN stays NaN).
#[inline(always)]
fn sweep_row<const N: usize>(dst: &mut [f32], n: usize, src: [&[f32]; N], values: [f32; N]) {
    let lanes = |dst: &mut [f32], at: usize, live: usize| {
        let mut acc: [f32; 4] = dst[at..at + 4].try_into().expect("four");
        for k in 0..N {
            let s: &[f32; 4] = src[k][at..at + 4].try_into().expect("four");
            for l in 0..4 {
                let p = values[k] * s[l];
                acc[l] += if l < live { p } else { 0.0 };
            }
        }
        dst[at..at + 4].copy_from_slice(&acc);
    };
    let full = n / 4 * 4;
    for at in (0..full).step_by(4) {
        lanes(dst, at, 4);
    }
    let rest = n - full;
    if rest == 0 {
        return;
    }
    if dst.len() >= full + 4 && src.iter().all(|t| t.len() >= full + 4) {
        lanes(dst, full, rest);
    } else {
        for i in full..n {
            let mut acc = dst[i];
            for k in 0..N {
                acc += values[k] * src[k][i];
            }
            dst[i] = acc;
        }
    }
}

/// Adds `records` (already checked) into `image`; returns the pixel updates (one per record
/// and covered pixel).
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
    let tiles = tiles_x * tiles_y;
    let chunks: Vec<Binned> = records
        .par_chunks(BIN_CHUNK)
        .enumerate()
        .map(|(c, chunk)| {
            let groups = groups(chunk, c * BIN_CHUNK, atlas, layout);
            let mut bins: Vec<Vec<u32>> = vec![Vec::new(); tiles];
            for (g, group) in groups.iter().enumerate() {
                let [xa, xb, ya, yb] = group.bounds;
                for ty in (ya as usize / TILE)..=((yb - 1) as usize / TILE) {
                    for tx in (xa as usize / TILE)..=((xb - 1) as usize / TILE) {
                        bins[ty * tiles_x + tx].push(g as u32);
                    }
                }
            }
            Binned { groups, bins }
        })
        .collect();
    let results: Vec<(Vec<f32>, u64)> = (0..tiles)
        .into_par_iter()
        .map(|t| {
            let tx = (t % tiles_x) * TILE;
            let ty = (t / tiles_x) * TILE;
            let tw = TILE.min(width - tx);
            let th = TILE.min(height - ty);
            // A tile no record reaches costs nothing (small batches, such as one brick's of a
            // bricked volume, reach a few tiles of a large image).
            if chunks.iter().all(|chunk| chunk.bins[t].is_empty()) {
                return (Vec::new(), 0);
            }
            let mut buf = vec![0.0f32; tw * th * channels];
            let mut updates = 0u64;
            let binned = chunks
                .iter()
                .flat_map(|chunk| chunk.bins[t].iter().map(|&g| &chunk.groups[g as usize]));
            for group in binned {
                let [xa, xb, ya, yb] = group.bounds;
                let xa = xa.max(tx as i64);
                let xb = xb.min((tx + tw) as i64);
                let ya = ya.max(ty as i64);
                let yb = yb.min((ty + th) as i64);
                if xa >= xb || ya >= yb {
                    continue;
                }
                let first = group.first as usize;
                let members = &records[first..first + group.len as usize];
                let r = &members[0];
                let x0 = r.x0 as i64 + r.view as i64 * layout.width as i64;
                let n = (xb - xa) as usize;
                let ch = r.channel as usize;
                let cols = atlas.phases[r.phase as usize].cols as usize;
                // Each member's samples from the group's first covered row and column on.
                let start = (ya - r.y0 as i64) as usize * cols + (xa - x0) as usize;
                let rows = (yb - ya) as usize;
                let table = |k: usize| {
                    let off = atlas.phases[members[k].phase as usize].offset as usize + start;
                    (&atlas.data[off..], members[k].value)
                };
                let dst0 = ((ya as usize - ty) * tw + (xa as usize - tx)) * channels + ch;
                let row = (dst0, tw * channels);
                match members.len() {
                    1 => sweep(&mut buf, channels, n, rows, row, cols, [table(0)]),
                    2 => sweep(&mut buf, channels, n, rows, row, cols, [table(0), table(1)]),
                    _ => sweep(
                        &mut buf,
                        channels,
                        n,
                        rows,
                        row,
                        cols,
                        [table(0), table(1), table(2)],
                    ),
                }
                updates += (members.len() * n * rows) as u64;
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::backend::PhaseRect;
    use proptest::prelude::*;

    /// Every record summed on its own into the whole image, in input order: what the tiled,
    /// grouped sum must equal bit for bit (a tile starts at zero, and 0 + x = x).
    fn one_at_a_time(
        layout: &Layout,
        atlas: &FootprintAtlas,
        records: &[SplatRecord],
    ) -> (Vec<f32>, u64) {
        let width = layout.total_width();
        let mut image = vec![0.0f32; width * layout.height * layout.channels];
        let mut updates = 0;
        for r in records {
            let rect = atlas.phases[r.phase as usize];
            for row in 0..rect.rows as i64 {
                for col in 0..rect.cols as i64 {
                    let (x, y) = (r.x0 as i64 + col, r.y0 as i64 + row);
                    if x < 0 || y < 0 || x >= layout.width as i64 || y >= layout.height as i64 {
                        continue;
                    }
                    let x = x as usize + r.view as usize * layout.width;
                    let sample =
                        atlas.data[(rect.offset as i64 + row * rect.cols as i64 + col) as usize];
                    image[(y as usize * width + x) * layout.channels + r.channel as usize] +=
                        r.value * sample;
                    updates += 1;
                }
            }
        }
        (image, updates)
    }

    /// The backend's sum of `records` against [`one_at_a_time`]: its pixel updates, the
    /// reference's, and how many values differ in any bit.
    fn against_one_at_a_time(
        layout: &Layout,
        atlas: &FootprintAtlas,
        records: &[SplatRecord],
    ) -> (u64, u64, usize) {
        let mut image = vec![0.0f32; layout.total_width() * layout.height * layout.channels];
        let updates = accumulate(&mut image, layout, atlas, records);
        let (expected, expected_updates) = one_at_a_time(layout, atlas, records);
        let differ = image
            .iter()
            .zip(&expected)
            .filter(|(a, b)| a.to_bits() != b.to_bits())
            .count();
        (updates, expected_updates, differ)
    }

    /// An atlas of `shapes` (each shape three times, as a footprint phase and its two
    /// gradient phases are) with samples from `seed`.
    fn atlas(shapes: &[(u32, u32)], seed: u64) -> FootprintAtlas {
        let mut atlas = FootprintAtlas::new();
        let mut state = seed | 1;
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 40) as f32 / (1u64 << 24) as f32 - 0.5
        };
        for &(cols, rows) in shapes {
            for _ in 0..3 {
                atlas.phases.push(PhaseRect {
                    offset: atlas.data.len() as u32,
                    cols,
                    rows,
                });
                atlas.data.extend((0..cols * rows).map(|_| next()));
            }
        }
        atlas
    }

    /// More records than one binning chunk holds, in groups of three that the chunks' ends
    /// cut (a lone record first shifts them): the sum is still bit for bit the records summed
    /// one at a time.
    #[test]
    fn groups_cut_by_binning_chunks_sum_the_same() {
        let layout = Layout {
            width: 97,
            height: 83,
            channels: 1,
            views: 1,
        };
        let atlas = atlas(&[(9, 7), (13, 11), (5, 5)], 7);
        let mut records = vec![SplatRecord {
            x0: 3,
            y0: 4,
            phase: 6,
            value: 0.5,
            channel: 0,
            view: 0,
        }];
        let mut k = 0u32;
        while records.len() < 3 * BIN_CHUNK + 5 {
            let shape = k % 2;
            for member in 0..3 {
                records.push(SplatRecord {
                    x0: (k * 37 % 110) as i32 - 10,
                    y0: (k * 53 % 95) as i32 - 8,
                    phase: shape * 3 + member,
                    value: 1.0 + (k % 17) as f32 * 0.25 - member as f32,
                    channel: 0,
                    view: 0,
                });
            }
            k += 1;
        }
        assert!(records.len() > 3 * BIN_CHUNK, "several chunks");
        const { assert!(BIN_CHUNK % 3 != 1, "a chunk's end cuts a group") };
        let (updates, expected_updates, differ) = against_one_at_a_time(&layout, &atlas, &records);
        assert_eq!(updates, expected_updates);
        assert_eq!(differ, 0, "{differ} values differ");
    }

    proptest! {
        #[test]
        fn grouped_tiles_equal_records_summed_one_at_a_time(
            width in 1usize..150,
            height in 1usize..150,
            channels in prop::sample::select(vec![1usize, 3]),
            views in 1usize..=3,
            shapes in prop::collection::vec((1u32..40, 1u32..40), 1..6),
            seed in any::<u64>(),
            runs in prop::collection::vec(
                (any::<u16>(), 1usize..=4, -45i32..160, -45i32..160, any::<u8>(), -4.0f32..4.0),
                0..300,
            ),
        ) {
            let layout = Layout { width, height, channels, views };
            let atlas = atlas(&shapes, seed);
            // Runs of 1 to 4 records with one corner, channel and view, reading the phases
            // of one shape (a run of 4 is a group of 3 and one more); the odd run's last
            // record reads another shape, which must split the group.
            let mut records = Vec::new();
            for (n, &(pick, len, x0, y0, target, value)) in runs.iter().enumerate() {
                let shape = pick as usize % shapes.len();
                for k in 0..len {
                    let other = n % 5 == 0 && k + 1 == len && k > 0;
                    let shape = if other { (shape + 1) % shapes.len() } else { shape };
                    records.push(SplatRecord {
                        x0,
                        y0,
                        phase: (shape * 3 + k % 3) as u32,
                        value: value * (k as f32 + 1.0),
                        channel: (target as usize % channels) as u16,
                        view: (target as usize / 3 % views) as u16,
                    });
                }
            }
            let (updates, expected_updates, differ) =
                against_one_at_a_time(&layout, &atlas, &records);
            prop_assert_eq!(updates, expected_updates);
            prop_assert_eq!(differ, 0, "{} values differ", differ);
        }
    }
}
