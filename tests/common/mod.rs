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
