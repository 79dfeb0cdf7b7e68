//! Replays the fuzz targets' kept corpora (`fuzz/corpus/TARGET/`, seeds and anything the fuzzer
//! found worth keeping) through the same target bodies, on the stable toolchain: every input
//! must be handled without a panic. The coverage-guided runs themselves use `cargo +nightly
//! fuzz run TARGET` (see BENCHMARKS.md for executions and findings).

#[path = "../fuzz/targets.rs"]
mod targets;

use std::path::{Path, PathBuf};
use wavesplat_codec::format::parse_file;

fn corpus(target: &str) -> Vec<(PathBuf, Vec<u8>)> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("fuzz/corpus")
        .join(target);
    let mut out: Vec<(PathBuf, Vec<u8>)> = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|e| {
            let p = e.unwrap().path();
            let b = std::fs::read(&p).unwrap();
            (p, b)
        })
        .collect();
    out.sort();
    assert!(!out.is_empty(), "empty corpus {}", dir.display());
    out
}

#[test]
fn every_kept_input_of_every_target_is_handled() {
    let mut total = 0;
    for (target, run) in [
        ("file", targets::file as fn(&[u8])),
        ("raw", targets::raw),
        ("nifti", targets::nifti),
        ("grpc", targets::grpc),
    ] {
        for (_, data) in corpus(target) {
            run(&data);
            total += 1;
        }
    }
    for coder in ["sigmap", "range", "huffman"] {
        let bytes = std::fs::read(
            Path::new(env!("CARGO_MANIFEST_DIR")).join(format!("fuzz/corpus/headers/{coder}.wsp")),
        )
        .unwrap();
        let header = parse_file(&bytes).unwrap().header;
        for (_, data) in corpus(&format!("packet_{coder}")) {
            targets::packet(&header, &data);
            total += 1;
        }
    }
    assert!(total >= 20, "{total} inputs");
}

#[test]
fn the_packet_seeds_are_valid_packets_of_their_headers() {
    // So the fuzzer starts from inputs that reach the decoders' depths.
    for coder in ["sigmap", "range", "huffman"] {
        let bytes = std::fs::read(
            Path::new(env!("CARGO_MANIFEST_DIR")).join(format!("fuzz/corpus/headers/{coder}.wsp")),
        )
        .unwrap();
        let header = parse_file(&bytes).unwrap().header;
        for (p, data) in corpus(&format!("packet_{coder}")) {
            if p.file_name()
                .is_some_and(|n| n.to_string_lossy().starts_with('p'))
            {
                wavesplat_codec::format::packet::decode_packet(&header, &data)
                    .unwrap_or_else(|e| panic!("{}: {e}", p.display()));
            }
        }
    }
}
