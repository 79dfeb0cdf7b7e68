//! Times decoding a `.wsp` file's packets on one thread, packet after packet (no pool), and
//! prints coefficients per second: the per-core decoding figure, and a loop to profile.
//!
//! `cargo run --release -p wavesplat-codec --example decode -- FILE.wsp [REPEAT]`

use std::time::Instant;
use wavesplat_codec::format::{packet::decode_packet, parse_file};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let Some(path) = args.get(1) else {
        return Err("usage: decode FILE.wsp [REPEAT]".into());
    };
    let repeat: usize = args.get(2).map_or(Ok(20), |s| s.parse())?.max(1);
    let bytes = std::fs::read(path)?;
    let file = parse_file(&bytes)?;
    let mut times = Vec::with_capacity(repeat);
    let mut count = 0usize;
    let mut checksum = 0f64;
    for _ in 0..repeat {
        let t = Instant::now();
        count = 0;
        for p in &file.packets {
            let d = decode_packet(&file.header, p)?;
            count += d.coefficients.len();
            checksum += d.coefficients.iter().map(|c| c.value as f64).sum::<f64>();
        }
        times.push(t.elapsed().as_secs_f64());
    }
    times.sort_by(f64::total_cmp);
    let median = times[times.len() / 2];
    println!(
        "{count} coefficients in {} packets: min {:.2} ms, median {:.2} ms, {:.1} M coefficients/s on one thread (checksum {checksum:.6e})",
        file.packets.len(),
        times[0] * 1e3,
        median * 1e3,
        count as f64 / median / 1e6
    );
    Ok(())
}
