//! Helpers shared by the end-to-end tests: running the real `wavesplat` binary as a server
//! (through `wavesplat_harness::process`), and reading its images.

#![allow(dead_code)]

pub mod netns;

use std::path::Path;
use std::process::Child;
use wavesplat_harness::process::ServerProcess;

/// Starts `wavesplat ARGS` (a server bound to port 0) and returns the child and the address it
/// announced on its first stdout line (`listening on ADDR`), through the harness's
/// `ServerProcess`.
pub fn spawn_server(args: &[&str]) -> (Child, String) {
    ServerProcess::spawn(Path::new(env!("CARGO_BIN_EXE_wavesplat")), args)
        .unwrap()
        .into_parts()
}

/// [`spawn_server`] with the server's stderr kept: [`stop_and_read_stderr`] reads it.
pub fn spawn_server_with_stderr(args: &[&str]) -> (Child, String) {
    ServerProcess::spawn_with_stderr(Path::new(env!("CARGO_BIN_EXE_wavesplat")), args)
        .unwrap()
        .into_parts()
}

#[allow(unused_imports)]
pub use wavesplat_harness::process::stop_and_read_stderr;

/// A finished command's status and output, for assertion messages.
pub fn text(o: &std::process::Output) -> String {
    format!(
        "status {:?}\nstdout:\n{}\nstderr:\n{}",
        o.status.code(),
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

/// A raw little-endian f32 image as `render --raw` writes it.
pub fn read_f32(path: &std::path::Path) -> Vec<f32> {
    std::fs::read(path)
        .unwrap()
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect()
}

/// The largest difference of two images relative to the first's peak (which must be > 0).
pub fn relative_difference(a: &[f32], b: &[f32]) -> f32 {
    assert!(a.iter().any(|x| *x != 0.0), "a black first image");
    wavesplat_viewer::image::max_relative_difference(b, a) as f32
}

/// Waits until a render recording into `dir/record` has received some bytes (its frames.csv's
/// byte column), and returns how many.
pub fn wait_for_bytes(dir: &std::path::Path) -> u64 {
    let csv = dir.join("record").join("frames.csv");
    let waited = std::time::Instant::now();
    loop {
        let bytes = std::fs::read_to_string(&csv)
            .unwrap_or_default()
            .lines()
            .skip(1)
            .filter_map(|l| l.split(',').nth(4)?.parse::<u64>().ok())
            .max()
            .unwrap_or(0);
        if bytes > 0 {
            return bytes;
        }
        assert!(
            waited.elapsed() < std::time::Duration::from_secs(60),
            "no bytes reached the viewer"
        );
        std::thread::sleep(std::time::Duration::from_millis(5));
    }
}
