//! Codes a `.wsp` file's coefficients again with each entropy coder (the same coefficients, the
//! same quantizers and packets) and prints each coder's file bytes and their breakdown, then
//! checks that every recoded file decodes to the original's coefficients: bytes at equal
//! coefficients, coder against coder, without running the compressor.
//!
//! `cargo run --release -p wavesplat-codec --example recode -- FILE.wsp [--version N] [CODER ...]`
//! (coders by name: `sigmap`, `fast`, `range`, `huffman`; default `sigmap fast`; the format
//! version coded for: the current one unless `--version` says; `--write PREFIX` writes each
//! recoded file as PREFIX.CODER.wsp).

use wavesplat_codec::format::packet::{decode_packet, decoded_inputs, encode_packets, Coefficient};
use wavesplat_codec::format::{parse_file, write_file, CoderKind};

/// FNV-1a over each coefficient's fields, packets in order, coefficients sorted within a
/// packet (a coder may order a packet's coefficients its own way).
fn hash_packets(packets: &[Vec<Coefficient>]) -> u64 {
    let mut hash = 0xcbf2_9ce4_8422_2325u64;
    for p in packets {
        let mut keys: Vec<[u32; 7]> = p
            .iter()
            .map(|c| {
                [
                    c.channel.into(),
                    c.band.level.into(),
                    c.band.kind.into(),
                    c.pos[0],
                    c.pos[1],
                    c.pos[2],
                    c.value.to_bits(),
                ]
            })
            .collect();
        keys.sort_unstable();
        for word in keys.iter().flatten() {
            hash = (hash ^ u64::from(*word)).wrapping_mul(0x100_0000_01b3);
        }
    }
    hash
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let Some(path) = args.get(1) else {
        return Err("usage: recode FILE.wsp [CODER ...]".into());
    };
    let mut version = wavesplat_codec::format::VERSION;
    let mut write_prefix = None;
    let mut names: Vec<&str> = Vec::new();
    let mut rest = args[2..].iter();
    while let Some(a) = rest.next() {
        if a == "--write" {
            write_prefix = Some(rest.next().ok_or("--write needs a prefix")?.clone());
        } else if a == "--version" {
            version = rest.next().ok_or("--version needs a number")?.parse()?;
        } else {
            names.push(a);
        }
    }
    if names.is_empty() {
        names = vec!["sigmap", "fast"];
    }
    let bytes = std::fs::read(path)?;
    let file = parse_file(&bytes)?;
    let inputs = decoded_inputs(&file)?;
    let count: usize = inputs.iter().map(|i| i.coefficients.len()).sum();
    let want: Vec<_> = inputs.iter().map(|i| i.coefficients.clone()).collect();
    let want_hash = hash_packets(&want);
    println!(
        "{path}: {} bytes, {} coder, {count} coefficients in {} packets",
        bytes.len(),
        file.header.coder.name(),
        inputs.len()
    );
    for name in names {
        let coder = CoderKind::from_name(name).ok_or_else(|| format!("no coder {name:?}"))?;
        let mut header = file.header.clone();
        header.coder = coder;
        header.version = version;
        let encoded = encode_packets(&mut header, &inputs);
        let out = write_file(&header, &encoded.packets);
        let b = encoded.breakdown;
        println!(
            "{name:>8}: {:>9} bytes (positions {:.0}, signs {:.0}, values {:.0}, framing {})",
            out.len(),
            b.position_bits / 8.0,
            b.sign_bits / 8.0,
            b.value_bits / 8.0,
            b.framing_bytes,
        );
        if let Some(prefix) = &write_prefix {
            std::fs::write(format!("{prefix}.{name}.wsp"), &out)?;
        }
        let recoded = parse_file(&out)?;
        println!("{name:>8}: header {} bytes", recoded.header_bytes);
        let mut got = Vec::with_capacity(recoded.packets.len());
        for p in &recoded.packets {
            got.push(decode_packet(&recoded.header, p)?.coefficients);
        }
        let same = hash_packets(&got) == want_hash;
        if !same {
            return Err(format!("{name}: the recoded file decodes to other coefficients").into());
        }
    }
    Ok(())
}
