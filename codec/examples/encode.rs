//! Times coding a `.wsp` file's coefficients again with its own coder, and prints coefficients
//! per second (run it with `RAYON_NUM_THREADS=1` for one core's figure): the per-core cost of one
//! trial of a rate search's entropy coding, and a loop to profile. The coded bytes must equal
//! the file's packets (the coefficients are the decoder's, so quantization is exact).
//!
//! `cargo run --release -p wavesplat-codec --features rayon --example encode -- FILE.wsp [REPEAT]`

use std::time::Instant;
use wavesplat_codec::format::packet::{decoded_inputs, encode_packets};
use wavesplat_codec::format::parse_file;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let Some(path) = args.get(1) else {
        return Err("usage: encode FILE.wsp [REPEAT]".into());
    };
    let repeat: usize = args.get(2).map_or(Ok(10), |s| s.parse())?.max(1);
    let bytes = std::fs::read(path)?;
    let file = parse_file(&bytes)?;
    let inputs = decoded_inputs(&file)?;
    let count: usize = inputs.iter().map(|i| i.coefficients.len()).sum();
    let mut times = Vec::with_capacity(repeat);
    let mut same = true;
    for _ in 0..repeat {
        let mut header = file.header.clone();
        let t = Instant::now();
        let coded = encode_packets(&mut header, &inputs);
        times.push(t.elapsed().as_secs_f64());
        same &= coded.packets.len() == file.packets.len()
            && coded
                .packets
                .iter()
                .zip(&file.packets)
                .all(|(c, p)| c[..] == p[..]);
    }
    times.sort_by(f64::total_cmp);
    let median = times[times.len() / 2];
    println!(
        "{count} coefficients in {} packets, {} coder: min {:.2} ms, median {:.2} ms, {:.1} M coefficients/s ; packets {}",
        inputs.len(),
        file.header.coder.name(),
        times[0] * 1e3,
        median * 1e3,
        count as f64 / median / 1e6,
        if same { "identical" } else { "DIFFER" }
    );
    if !same {
        return Err("the coded packets differ from the file's".into());
    }
    Ok(())
}
