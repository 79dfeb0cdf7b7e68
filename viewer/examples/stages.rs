//! Where the time of one image goes, stage by stage, for a `.wsp` file on the CPU backend:
//! `cargo run --release -p wavesplat-viewer --example stages -- FILE [SIZE] [REPEAT]`.
//!
//! Prints the median of REPEAT runs (default 9) at a SIZE² oblique view (default 256) of:
//! the whole path from the file's bytes in memory to the exact image (packets decoded, the view
//! planned by a fresh planner, records made, records accumulated); planning alone for a new
//! view (a planner cache miss, as on each step of an orbit) and for a cached one; and, for a
//! planned view, making the records and accumulating them, with pixel updates per second (one
//! update per record and covered pixel); the whole path again as the one call `render` makes for
//! a whole local file (`open::draw_whole_file`: decoding and planning together). Last, a hash of the image's bits, to show that two
//! builds draw the same image. The figures are in BENCHMARKS.md ("Bytes to image").
use std::time::Instant;
use wavesplat_codec::view::ViewSpec;
use wavesplat_viewer::backend::AccumulationBackend;
use wavesplat_viewer::open::{draw_whole_file, load_coefficients};
use wavesplat_viewer::{CpuBackend, PlanOptions, Planner, RenderStats, View};

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn ms(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let Some(path) = args.get(1) else {
        return Err("usage: stages FILE.wsp [SIZE] [REPEAT]".into());
    };
    let size: usize = args.get(2).map_or(Ok(256), |s| s.parse())?;
    let repeat: usize = args.get(3).map_or(Ok(9), |s| s.parse())?.max(1);
    let bytes = std::fs::read(path)?;
    let view = View::new(0.66, 0.91, size, size);
    let spec = ViewSpec::single(view);

    // Bytes in memory to the exact image.
    let mut whole = Vec::new();
    let mut parts = [Vec::new(), Vec::new(), Vec::new(), Vec::new()];
    for _ in 0..repeat {
        let t = Instant::now();
        let (header, coefficients) = load_coefficients(&bytes, None, None)?;
        let decoded = ms(t);
        let mut plan =
            Planner::new(PlanOptions::default()).plan(&header.geometry, &spec, header.channels)?;
        let planned = ms(t);
        let mut records = Vec::new();
        plan.splats(&coefficients, &mut records, &mut RenderStats::default())?;
        let recorded = ms(t);
        let mut backend = CpuBackend::new();
        backend.begin(plan.layout())?;
        backend.accumulate(&plan.atlas(), &records)?;
        std::hint::black_box(backend.read()?);
        let done = ms(t);
        whole.push(done);
        for (k, v) in [
            decoded,
            planned - decoded,
            recorded - planned,
            done - recorded,
        ]
        .into_iter()
        .enumerate()
        {
            parts[k].push(v);
        }
    }
    let [decode, plan, record, accumulate] = parts.map(median);
    println!(
        "bytes to exact image: {:.1} ms (decode {decode:.1}, plan {plan:.1}, records {record:.1}, accumulate {accumulate:.1})",
        median(whole)
    );

    // The same path as one call: decoding and planning together, then the splatting.
    let mut backend = CpuBackend::new();
    let mut runs = Vec::with_capacity(repeat);
    for _ in 0..repeat {
        let t = Instant::now();
        let w = draw_whole_file(&bytes, &spec, &mut backend)?;
        runs.push((ms(t), w));
    }
    let whole_ms = median(runs.iter().map(|(t, _)| *t).collect());
    let together = median(
        runs.iter()
            .map(|(_, w)| w.decode_and_plan.as_secs_f64() * 1e3)
            .collect(),
    );
    let splat = median(
        runs.iter()
            .map(|(_, w)| w.splat.as_secs_f64() * 1e3)
            .collect(),
    );
    println!(
        "one pass (draw_whole_file): {whole_ms:.1} ms (decode and plan together {together:.1}, splat {splat:.1})"
    );

    let (header, coefficients) = load_coefficients(&bytes, None, None)?;
    let (geometry, channels) = (header.geometry, header.channels);
    // A new view per run (a fresh planner: nothing cached), then the same view again.
    let fresh: Vec<f64> = (0..repeat)
        .map(|i| {
            let spec = ViewSpec::single(View::new(0.66 + 0.01 * i as f64, 0.91, size, size));
            let t = Instant::now();
            let plan = Planner::new(PlanOptions::default()).plan(&geometry, &spec, channels);
            let elapsed = ms(t);
            plan.map(|_| elapsed)
        })
        .collect::<Result<_, _>>()?;
    let mut planner = Planner::new(PlanOptions::default());
    planner.plan(&geometry, &spec, channels)?;
    let cached: Vec<f64> = (0..repeat)
        .map(|_| {
            let t = Instant::now();
            planner.plan(&geometry, &spec, channels).map(|_| ms(t))
        })
        .collect::<Result<_, _>>()?;
    println!(
        "plan: new view {:.1} ms, cached view {:.2} ms (M = {})",
        median(fresh),
        median(cached),
        geometry.levels
    );

    // A planned view: records and accumulation of every coefficient.
    let mut plan = planner.plan(&geometry, &spec, channels)?;
    let mut backend = CpuBackend::new();
    let mut records = Vec::new();
    let (mut record_ms, mut accumulate_ms) = (Vec::new(), Vec::new());
    let mut updates = 0;
    for _ in 0..repeat {
        records.clear();
        let t = Instant::now();
        plan.splats(&coefficients, &mut records, &mut RenderStats::default())?;
        record_ms.push(ms(t));
        backend.begin(plan.layout())?;
        let t = Instant::now();
        updates = backend.accumulate(&plan.atlas(), &records)?;
        accumulate_ms.push(ms(t));
    }
    let accumulate = median(accumulate_ms);
    println!(
        "{} coefficients, {} records: records {:.1} ms, accumulate {accumulate:.1} ms ({:.2} G pixel updates/s, {:.0} per record)",
        coefficients.len(),
        records.len(),
        median(record_ms),
        updates as f64 / accumulate / 1e6,
        updates as f64 / records.len().max(1) as f64
    );
    let image = backend.read()?;
    // FNV-1a over the bits: equal hashes, equal images.
    let hash = image.data.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, v| {
        (h ^ v.to_bits() as u64).wrapping_mul(0x0000_0100_0000_01b3)
    });
    println!("image hash {hash:016x}");
    Ok(())
}
