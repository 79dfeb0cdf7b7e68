//! Command-line behaviour of the real `wavesplat` binary that users meet in shells: output into a
//! pipe whose reader has gone away (`wavesplat info f.wsp | head -1`) ends without a panic and
//! with the status a shell gives a program killed by SIGPIPE.

use std::process::{Command, Stdio};

const BIN: &str = env!("CARGO_BIN_EXE_wavesplat");

/// Runs `wavesplat ARGS` with stdout a pipe already closed at the reading end, so that every
/// write fails with EPIPE; returns (exit code, stderr).
fn run_into_closed_pipe(args: &[&str]) -> (Option<i32>, String) {
    let (reader, writer) = std::io::pipe().expect("pipe");
    drop(reader);
    let out = Command::new(BIN)
        .args(args)
        .stdout(Stdio::from(writer))
        .stderr(Stdio::piped())
        .output()
        .expect("run wavesplat");
    (
        out.status.code(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn output_into_a_closed_pipe_ends_quietly_with_the_sigpipe_status() {
    let dir = tempfile::tempdir().expect("tempdir");
    let raw = dir.path().join("p.raw");
    let wsp = dir.path().join("p.wsp");
    let raw_s = raw.to_str().expect("utf-8 path");
    let wsp_s = wsp.to_str().expect("utf-8 path");
    let status = Command::new(BIN)
        .args(["phantom", "spheres", "--dims", "16,16,16", "-o", raw_s])
        .output()
        .expect("run phantom");
    assert!(status.status.success(), "phantom failed: {status:?}");

    // compress prints a summary after writing its file; info prints the whole report.
    let (code, stderr) = run_into_closed_pipe(&[
        "compress",
        raw_s,
        "--dims",
        "16,16,16",
        "--dtype",
        "f32",
        "--target-fraction",
        "0.1",
        "-o",
        wsp_s,
    ]);
    // Not success: the command's output was lost (141 = 128 + SIGPIPE, as a shell reports).
    assert_eq!(code, Some(141), "compress into a closed pipe: {stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert!(wsp.exists(), "the file is written before the summary");

    let (code, stderr) = run_into_closed_pipe(&["info", wsp_s]);
    assert_eq!(code, Some(141), "info into a closed pipe: {stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
}
