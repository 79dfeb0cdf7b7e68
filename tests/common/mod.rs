//! Helpers shared by the end-to-end tests: running the real `wavesplat` binary as a server.

#![allow(dead_code)]

pub mod netns;

use std::io::{BufRead, BufReader, Read};
use std::process::{Child, Command, Stdio};

/// Starts `wavesplat ARGS` (a server bound to port 0) and returns the child and the address it
/// announced on its first stdout line (`listening on ADDR`).
pub fn spawn_server(args: &[&str]) -> (Child, String) {
    spawn(args, Stdio::null())
}

/// [`spawn_server`] with the server's stderr kept: [`stop_and_read_stderr`] reads it.
pub fn spawn_server_with_stderr(args: &[&str]) -> (Child, String) {
    spawn(args, Stdio::piped())
}

/// Kills a server started by [`spawn_server_with_stderr`] and returns what it wrote on stderr.
pub fn stop_and_read_stderr(mut child: Child) -> String {
    let _ = child.kill();
    let _ = child.wait();
    let mut err = String::new();
    if let Some(mut e) = child.stderr.take() {
        let _ = e.read_to_string(&mut err);
    }
    err
}

fn spawn(args: &[&str], stderr: Stdio) -> (Child, String) {
    let mut child = Command::new(env!("CARGO_BIN_EXE_wavesplat"))
        .args(args)
        .env_remove("WAVESPLAT_TOKENS_FILE")
        .stdout(Stdio::piped())
        .stderr(stderr)
        .spawn()
        .unwrap();
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    let addr = line
        .trim()
        .strip_prefix("listening on ")
        .unwrap_or_else(|| panic!("unexpected server output {line:?}"))
        .to_string();
    (child, addr)
}

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
    assert_eq!(a.len(), b.len());
    let peak = a.iter().fold(0f32, |m, x| m.max(x.abs()));
    assert!(peak > 0.0);
    a.iter().zip(b).fold(0f32, |m, (x, y)| m.max((x - y).abs())) / peak
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
