//! Validates the WGSL shaders of the GPU backend with naga at build time, so a shader error
//! fails `cargo build` (with the error shown against the source) instead of a test run.

use std::path::Path;

const SHADERS: [&str; 2] = ["accumulate.wgsl", "display.wgsl"];

fn main() {
    let dir = Path::new("src/backend/shaders");
    for name in SHADERS {
        let path = dir.join(name);
        println!("cargo:rerun-if-changed={}", path.display());
        let source = std::fs::read_to_string(&path)
            .unwrap_or_else(|e| panic!("reading {}: {e}", path.display()));
        let shown = path.display().to_string();
        let module = naga::front::wgsl::parse_str(&source).unwrap_or_else(|e| {
            panic!(
                "WGSL parse error\n{}",
                e.emit_to_string_with_path(&source, &shown)
            )
        });
        naga::valid::Validator::new(
            naga::valid::ValidationFlags::all(),
            naga::valid::Capabilities::empty(),
        )
        .validate(&module)
        .unwrap_or_else(|e| {
            panic!(
                "WGSL validation error\n{}",
                e.emit_to_string_with_path(&source, &shown)
            )
        });
    }
}
