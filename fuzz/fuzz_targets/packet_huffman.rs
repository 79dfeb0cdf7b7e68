#![no_main]
#[path = "../meter.rs"]
mod meter;
#[path = "../targets.rs"]
mod targets;

/// The header of the kept sample file for this coder.
static HEADER: targets::KeptHeader =
    targets::KeptHeader::new(include_bytes!("../corpus/headers/huffman.wsp"));

libfuzzer_sys::fuzz_target!(|data: &[u8]| targets::packet(HEADER.get(), data));
