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
    let mut decoded = Vec::with_capacity(file.packets.len());
    for _ in 0..repeat {
        decoded.clear();
        let t = Instant::now();
        for p in &file.packets {
            decoded.push(decode_packet(&file.header, p)?);
        }
        times.push(t.elapsed().as_secs_f64());
    }
    // Order, positions and value bits of the last run: any change in what is decoded changes
    // the hash (FNV-1a over each coefficient's fields).
    let mut count = 0usize;
    let mut hash = 0xcbf2_9ce4_8422_2325u64;
    for c in decoded.iter().flat_map(|d| &d.coefficients) {
        count += 1;
        for word in [c.channel.into(), c.band.level.into(), c.band.kind.into()]
            .into_iter()
            .chain(c.pos)
            .chain([c.value.to_bits()])
        {
            hash = (hash ^ u64::from(word)).wrapping_mul(0x100_0000_01b3);
        }
    }
    times.sort_by(f64::total_cmp);
    let median = times[times.len() / 2];
    println!(
        "{count} coefficients in {} packets: min {:.2} ms, median {:.2} ms, {:.1} M coefficients/s on one thread (hash {hash:016x})",
        file.packets.len(),
        times[0] * 1e3,
        median * 1e3,
        count as f64 / median / 1e6
    );
    Ok(())
}
