#![no_main]
#[path = "../meter.rs"]
mod meter;
#[path = "../targets.rs"]
mod targets;
use std::sync::OnceLock;
use wavesplat_codec::format::{parse_file, Header};

/// The header of the kept sample file for this coder (`corpus/headers/fast.wsp`).
fn header() -> &'static Header {
    static H: OnceLock<Header> = OnceLock::new();
    H.get_or_init(|| {
        let bytes = include_bytes!("../corpus/headers/fast.wsp");
        parse_file(bytes)
            .expect("the kept sample file parses")
            .header
    })
}

libfuzzer_sys::fuzz_target!(|data: &[u8]| { targets::packet(header(), data) });
