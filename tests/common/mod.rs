//! Helpers shared by the end-to-end tests: running the real `wavesplat` binary as a server.

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};

/// Starts `wavesplat ARGS` (a server bound to port 0) and returns the child and the address it
/// announced on its first stdout line (`listening on ADDR`).
pub fn spawn_server(args: &[&str]) -> (Child, String) {
    let mut child = Command::new(env!("CARGO_BIN_EXE_wavesplat"))
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
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
