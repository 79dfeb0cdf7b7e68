#![no_main]
#[path = "../meter.rs"]
mod meter;
#[path = "../targets.rs"]
mod targets;
libfuzzer_sys::fuzz_target!(|data: &[u8]| targets::zarr(data));
