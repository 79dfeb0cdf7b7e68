//! What a view change costs the frame thread before any splat: a session holding every packet
//! of a `.wsp` file (drawn to the end at an oblique 256² view on the CPU backend) is set to the
//! same view again and again, so the tables come from the planner's cache and what is timed is
//! the visibility weights and queuing every held coefficient again by its visible energy (the
//! same work as when a view's exact tables arrive):
//! `cargo run --release -p wavesplat-viewer --example requeue -- FILE [REPEAT]`.
//! The figures are in BENCHMARKS.md ("A real GPU").
use std::time::{Duration, Instant};
use wavesplat_codec::view::{View, ViewSpec};
use wavesplat_viewer::session::{RenderSession, SessionOptions};
use wavesplat_viewer::source::FileSource;
use wavesplat_viewer::{CpuBackend, FrameLoop};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let Some(path) = args.get(1) else {
        return Err("usage: requeue FILE.wsp [REPEAT]".into());
    };
    let repeat: usize = args.get(2).map_or(Ok(49), |s| s.parse())?.max(1);
    let bytes = std::fs::read(path)?;
    let header = wavesplat_codec::format::parse_file(&bytes)?.header;
    let spec = ViewSpec::single(View::new(0.66, 0.91, 256, 256));
    let session = RenderSession::new(header, spec, CpuBackend::new(), SessionOptions::default())?;
    let mut frames = FrameLoop::new(session, FileSource::open(bytes, &spec)?);
    loop {
        let r = frames.frame(Duration::from_millis(100))?;
        if r.idle() && frames.source_status().done {
            break;
        }
    }
    let mut ms = Vec::with_capacity(repeat);
    for _ in 0..repeat {
        let t = Instant::now();
        frames.session.set_view(spec)?;
        ms.push(t.elapsed().as_secs_f64() * 1e3);
    }
    ms.sort_by(f64::total_cmp);
    println!(
        "view change with {} coefficients held: min {:.2} ms, median {:.2} ms",
        frames.session.stats().coefficients_held,
        ms[0],
        ms[ms.len() / 2]
    );
    Ok(())
}
