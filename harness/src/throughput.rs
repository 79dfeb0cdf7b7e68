//! `bench throughput`: throughput of the pipeline stages on one machine, written as CSV and a
//! table: compression (voxels/s), packet decoding (coefficients/s) and splatting (splats/s,
//! pixel updates/s, and the share of the accumulation loop's speed over the same view's own
//! footprints) per family, the paper's timing case, and the accumulation loop's ceiling at
//! fixed footprint sizes.
//! Timings are medians of repeated runs; nothing here is asserted (benchmarks are not tests).

use anyhow::Result;
use std::io::Write;
use std::path::PathBuf;
use std::time::Instant;
use wavesplat_codec::family::Family;
use wavesplat_codec::format::packet::Coefficient;
use wavesplat_codec::format::parse_file;
use wavesplat_codec::layout::Geometry;
use wavesplat_codec::view::ViewSpec;
use wavesplat_codec::volume::Volume;
use wavesplat_compressor::encode::{compress, CompressOptions, Target};
use wavesplat_viewer::open::load_coefficients;
use wavesplat_viewer::{PlanOptions, Planner, RenderOptions, RenderStats, Renderer, View};

/// What `bench throughput` measures.
pub struct ThroughputBench {
    /// The volume.
    pub volume: Volume,
    /// Fraction of coefficients kept.
    pub fraction: f64,
    /// Repetitions per measurement (the median is reported).
    pub repeat: usize,
    /// CSV output.
    pub output: PathBuf,
}

/// The median of `v` (the upper one for an even count).
pub fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Runs `bench throughput`, writing the CSV and printing the table to `say`.
pub fn run(bench: &ThroughputBench, say: &mut dyn Write) -> Result<()> {
    let volume = &bench.volume;
    let voxels = volume.voxel_count() as f64;
    let threads = rayon::current_num_threads();
    let mut csv = std::fs::File::create(&bench.output)?;
    writeln!(
        csv,
        "stage,family,threads,size,seconds,items,items_per_second"
    )?;
    writeln!(
        say,
        "{} voxels, {} threads, keep {} of the coefficients, median of {}",
        volume.voxel_count(),
        threads,
        bench.fraction,
        bench.repeat
    )?;
    for family in Family::ALL {
        // Throughput of the paper's pipeline: the oracle's coefficients, no least-squares
        // refinement (which costs ~40 extra synthesis/transpose passes; see BENCHMARKS.md).
        let opts = CompressOptions {
            family,
            target: Target::Fraction(bench.fraction),
            refine: None,
            ..Default::default()
        };
        let mut times = Vec::new();
        let mut last = None;
        for _ in 0..bench.repeat.max(1) {
            let t = Instant::now();
            last = Some(compress(volume, &opts, &|_, _| {})?);
            times.push(t.elapsed().as_secs_f64());
        }
        let c = last.expect("at least one run");
        let s = median(times);
        writeln!(
            csv,
            "compress,{family},{threads},-,{s:.4},{voxels},{:.0}",
            voxels / s
        )?;
        writeln!(
            say,
            "{family:7} compress  {:8.3} s  {:12.0} voxels/s  ({} bytes)",
            s,
            voxels / s,
            c.bytes.len()
        )?;

        let mut times = Vec::new();
        let mut n = 0usize;
        for _ in 0..bench.repeat.max(1) {
            let t = Instant::now();
            let (_, coeffs) = load_coefficients(&c.bytes, None, None)?;
            times.push(t.elapsed().as_secs_f64());
            n = coeffs.len();
        }
        let s = median(times);
        writeln!(
            csv,
            "decode,{family},{threads},-,{s:.4},{n},{:.0}",
            n as f64 / s
        )?;
        writeln!(
            say,
            "{family:7} decode    {:8.4} s  {:12.0} coefficients/s",
            s,
            n as f64 / s
        )?;

        let header = parse_file(&c.bytes)?.header;
        let (_, coeffs) = load_coefficients(&c.bytes, None, None)?;
        let mut renderer = Renderer::new(RenderOptions::default());
        for size in [256usize, 512] {
            let view = View::new(0.66, 0.91, size, size);
            renderer.render(&coeffs, &header.geometry, &view)?; // footprints built once
            let mut times = Vec::new();
            let mut updates = 0;
            for _ in 0..bench.repeat.max(1) {
                let t = Instant::now();
                let (_, stats) = renderer.render_with_stats(&coeffs, &header.geometry, &view)?;
                times.push(t.elapsed().as_secs_f64());
                updates = stats.pixel_updates;
            }
            let s = median(times);
            let ceiling = view_ceiling(&coeffs, &header.geometry, &view, bench.repeat.max(1))?;
            writeln!(
                csv,
                "splat,{family},{threads},{size},{s:.4},{},{:.0}",
                coeffs.len(),
                coeffs.len() as f64 / s
            )?;
            writeln!(
                csv,
                "accumulate_loop_view,{family},1,{size},{:.4},{},{:.0}",
                ceiling.seconds, ceiling.updates, ceiling.per_second
            )?;
            writeln!(
                csv,
                "pixel_updates,{family},{threads},{size},{s:.4},{updates},{:.0}",
                updates as f64 / s
            )?;
            writeln!(
                say,
                "{family:7} splat {size}² {:8.4} s  {:12.0} splats/s  {:12.0} pixel updates/s \
                 ({:.0} % of the loop's {:.0} per core at this view's footprints)",
                s,
                coeffs.len() as f64 / s,
                updates as f64 / s,
                100.0 * updates as f64 / s / threads as f64 / ceiling.per_second,
                ceiling.per_second
            )?;
        }
    }
    paper_case(say, volume, &mut csv, bench.repeat.max(1))?;
    accumulation_bandwidth(say, &mut csv, bench.repeat.max(1))?;
    writeln!(say, "wrote {}", bench.output.display())?;
    Ok(())
}

/// The paper's timing case (Table 4): 170 761 coefficients rendered at 160×180 (Haar, M = 3),
/// and splats/s per level of the same set.
fn paper_case(
    say: &mut dyn Write,
    volume: &Volume,
    csv: &mut std::fs::File,
    repeat: usize,
) -> Result<()> {
    let opts = CompressOptions {
        family: Family::Haar,
        levels: Some(3),
        target: Target::Coefficients(170_761),
        refine: None,
        ..Default::default()
    };
    let c = compress(volume, &opts, &|_, _| {})?;
    let header = parse_file(&c.bytes)?.header;
    let (_, coeffs) = load_coefficients(&c.bytes, None, None)?;
    let mut renderer = Renderer::new(RenderOptions::default());
    let view = View::new(0.66, 0.91, 160, 180);
    renderer.render(&coeffs, &header.geometry, &view)?;
    let mut times = Vec::new();
    for _ in 0..repeat {
        let t = Instant::now();
        renderer.render(&coeffs, &header.geometry, &view)?;
        times.push(t.elapsed().as_secs_f64());
    }
    let s = median(times);
    writeln!(
        csv,
        "paper_case,haar,{},160x180,{s:.4},{},{:.0}",
        rayon::current_num_threads(),
        coeffs.len(),
        coeffs.len() as f64 / s
    )?;
    writeln!(say,
        "paper case: {} Haar coefficients (M=3) at 160x180 in {:.1} ms (paper: 4.01 s on an R10000)",
        coeffs.len(),
        s * 1e3
    )?;
    for level in 1..=header.geometry.levels as u8 {
        let subset: Vec<_> = coeffs
            .iter()
            .filter(|k| k.band.level == level)
            .copied()
            .collect();
        if subset.is_empty() {
            continue;
        }
        let mut times = Vec::new();
        for _ in 0..repeat {
            let t = Instant::now();
            renderer.render(&subset, &header.geometry, &view)?;
            times.push(t.elapsed().as_secs_f64());
        }
        let s = median(times);
        writeln!(
            csv,
            "splat_level_{level},haar,{},160x180,{s:.4},{},{:.0}",
            rayon::current_num_threads(),
            subset.len(),
            subset.len() as f64 / s
        )?;
        writeln!(
            say,
            "  level {level}: {:8} splats  {:12.0} splats/s",
            subset.len(),
            subset.len() as f64 / s
        )?;
    }
    Ok(())
}

/// The accumulation loop's speed on one view's own footprints.
struct ViewCeiling {
    seconds: f64,
    updates: u64,
    per_second: f64,
}

/// Records of one view sampled for [`view_ceiling`]: enough to hold every common footprint
/// shape in proportion, few enough for the loop to run from the first-level cache's
/// neighbourhood like [`accumulation_bandwidth`]'s single footprint does not.
const CEILING_SAMPLE: usize = 4096;

/// The limit of one view's splatting: [`accumulation_bandwidth`]'s loop (scaled footprint rows
/// added into a 64×64 f32 tile, one record at a time, single thread) run over the view's own
/// footprint tables: every k-th record of the view (their phases, sizes and weights, clipped
/// to the tile), each at an offset that keeps it inside the tile. A footprint of 7 × 7 pixels
/// (a linear 256² view of the MRI at its finest level) costs per row what one of 48 × 48 does,
/// so the fixed-size ceilings above flatter small views; this one has the view's shapes and no
/// projection, binning, grouping or clipping.
fn view_ceiling(
    coefficients: &[Coefficient],
    geometry: &Geometry,
    view: &View,
    repeat: usize,
) -> Result<ViewCeiling> {
    const TILE: usize = 64;
    let mut plan =
        Planner::new(PlanOptions::default()).plan(geometry, &ViewSpec::single(*view), 1)?;
    let mut records = Vec::new();
    plan.splats(coefficients, &mut records, &mut RenderStats::default())?;
    let step = records.len().div_ceil(CEILING_SAMPLE).max(1);
    // (table offset, columns, rows, weight) of the sampled records, clipped to the tile.
    let sample: Vec<(usize, usize, usize, usize, f32)> = records
        .iter()
        .step_by(step)
        .map(|r| {
            let rect = plan.atlas().phases[r.phase as usize];
            let cols = (rect.cols as usize).min(TILE);
            let rows = (rect.rows as usize).min(TILE);
            (
                rect.offset as usize,
                rect.cols as usize,
                cols,
                rows,
                r.value,
            )
        })
        .collect();
    let updates_per_pass: u64 = sample.iter().map(|s| (s.2 * s.3) as u64).sum();
    let passes = (20_000_000 / updates_per_pass.max(1)).max(1) as usize;
    let mut tile = vec![0.0f32; TILE * TILE];
    // A ceiling is what the loop can reach: the fastest of at least three runs (the pool's
    // threads, just done splatting, can still hold a core for the first).
    let mut times = Vec::new();
    for _ in 0..repeat.max(3) {
        let t = Instant::now();
        for pass in 0..passes {
            for (n, &(offset, stride, cols, rows, w)) in sample.iter().enumerate() {
                let k = n + pass;
                let (ox, oy) = ((k * 7) % (TILE - cols + 1), (k * 13) % (TILE - rows + 1));
                for r in 0..rows {
                    let row = &mut tile[(oy + r) * TILE + ox..(oy + r) * TILE + ox + cols];
                    let src = &plan.atlas().data[offset + r * stride..offset + r * stride + cols];
                    for (d, s) in row.iter_mut().zip(src) {
                        *d += w * s;
                    }
                }
            }
        }
        times.push(t.elapsed().as_secs_f64());
    }
    std::hint::black_box(&tile);
    let seconds = times.into_iter().fold(f64::INFINITY, f64::min);
    let updates = updates_per_pass * passes as u64;
    Ok(ViewCeiling {
        seconds,
        updates,
        per_second: updates as f64 / seconds,
    })
}

/// The limit to compare splatting against: the same accumulation loop (scaled footprint rows
/// added into an f32 tile) with no projection, binning or table lookup, single thread.
fn accumulation_bandwidth(
    say: &mut dyn Write,
    csv: &mut std::fs::File,
    repeat: usize,
) -> Result<()> {
    const TILE: usize = 64;
    for side in [4usize, 16, 48] {
        let footprint: Vec<f32> = (0..side * side).map(|i| (i % 7) as f32 * 0.1).collect();
        let mut tile = vec![0.0f32; TILE * TILE];
        let splats = 2_000_000 / (side * side) * 16;
        let mut times = Vec::new();
        for _ in 0..repeat {
            let t = Instant::now();
            for n in 0..splats {
                let (ox, oy) = ((n * 7) % (TILE - side + 1), (n * 13) % (TILE - side + 1));
                let w = 1.0 + (n % 3) as f32;
                for r in 0..side {
                    let row = &mut tile[(oy + r) * TILE + ox..(oy + r) * TILE + ox + side];
                    for (d, s) in row.iter_mut().zip(&footprint[r * side..(r + 1) * side]) {
                        *d += w * s;
                    }
                }
            }
            times.push(t.elapsed().as_secs_f64());
        }
        std::hint::black_box(&tile);
        let s = median(times);
        let updates = (splats * side * side) as f64;
        writeln!(
            csv,
            "accumulate_loop,-,1,{side}x{side},{s:.4},{updates},{:.0}",
            updates / s
        )?;
        writeln!(say,
            "accumulation loop, {side}x{side} footprints: {:12.0} pixel updates/s per core ({:.1} GB/s read+write, L1-resident tile)",
            updates / s,
            updates * 12.0 / s / 1e9
        )?;
    }
    Ok(())
}
