//! Command-line behaviour of the real `wavesplat` binary that users meet in shells: output into a
//! pipe whose reader has gone away (`wavesplat info f.wsp | head -1`) ends without a panic and
//! with the status a shell gives a program killed by SIGPIPE; first-hour mistakes (a compressed
//! file to compress, a volume to render, a missing output directory, a database in use) are
//! explained; help says what the commands take.

mod common;

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

fn run(args: &[&str]) -> std::process::Output {
    Command::new(BIN)
        .args(args)
        .output()
        .expect("run wavesplat")
}

fn err(o: &std::process::Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

fn out(o: &std::process::Output) -> String {
    String::from_utf8_lossy(&o.stdout).into_owned()
}

/// A small compressed phantom and its raw source in `dir`.
fn phantom_files(dir: &std::path::Path) -> (String, String) {
    let raw = dir.join("p.raw").to_str().unwrap().to_string();
    let wsp = dir.join("p.wsp").to_str().unwrap().to_string();
    assert!(
        run(&["phantom", "spheres", "--dims", "16,16,16", "-o", &raw])
            .status
            .success()
    );
    let c = run(&[
        "compress", &raw, "--dims", "16,16,16", "--dtype", "f32", "-o", &wsp,
    ]);
    assert!(c.status.success(), "{}", err(&c));
    // What the fraction counts is printed as a percentage of all coefficients.
    assert!(out(&c).contains(" %; "), "{}", out(&c));
    (raw, wsp)
}

/// Errors people meet in their first hour say what is wrong and what to do.
#[test]
fn first_hour_mistakes_are_explained() {
    let dir = tempfile::tempdir().unwrap();
    let (raw, wsp) = phantom_files(dir.path());
    let o = dir.path().join("o.wsp");
    let o = o.to_str().unwrap();

    // Compressing a compressed file.
    let e = run(&["compress", &wsp, "-o", o]);
    assert!(!e.status.success());
    assert!(err(&e).contains("already a compressed"), "{}", err(&e));

    // The raw phantom compressed to `o` with further options.
    let compress_raw = |options: &[&str]| {
        let mut args = vec!["compress", &raw, "--dims", "16,16,16", "--dtype", "f32"];
        args.extend_from_slice(options);
        args.extend(["-o", o]);
        run(&args)
    };

    // A negative fraction reaches the validation instead of clap's "unexpected argument '-0'".
    let e = compress_raw(&["--target-fraction", "-0.5"]);
    assert!(!e.status.success());
    assert!(
        err(&e).contains("-0.5") && err(&e).contains("(0, 1]"),
        "{}",
        err(&e)
    );

    // An output directory that does not exist is refused before any work.
    let e = run(&["render", &wsp, "-o", "/nonexistent-dir/a.png"]);
    assert!(!e.status.success());
    assert!(err(&e).contains("does not exist"), "{}", err(&e));
    // So are an output that is a directory, the PNG and the raw floats at one path, a frame
    // time past what a clock can hold (it panicked), and a screenshot into no directory.
    let d = dir.path().to_str().unwrap();
    let png = dir.path().join("a.png");
    let png = png.to_str().unwrap();
    for (args, says) in [
        (vec!["render", &wsp, "-o", d], "is a directory"),
        (vec!["render", &wsp, "-o", png, "--raw", png], "both name"),
        (
            vec![
                "render",
                &wsp,
                "-o",
                png,
                "--progressive",
                "--frame-ms",
                "1e23",
            ],
            "--frame-ms",
        ),
        (
            vec![
                "render",
                &wsp,
                "-o",
                png,
                "--progressive",
                "--budget-ms",
                "1e23",
            ],
            "--budget-ms",
        ),
        (
            vec!["view", &wsp, "--screenshot", "/nonexistent-dir/s.png"],
            "does not exist",
        ),
    ] {
        let e = run(&args);
        assert!(!e.status.success(), "{args:?}");
        assert!(err(&e).contains(says), "{args:?}: {}", err(&e));
        assert!(!err(&e).contains("panicked"), "{args:?}: {}", err(&e));
    }
    // A view panned off the volume draws an empty image and says why.
    let off = run(&["render", &wsp, "-o", png, "--pan", "1000,0"]);
    assert!(off.status.success(), "{}", err(&off));
    assert!(
        err(&off).contains("sees none of the volume"),
        "{}",
        err(&off)
    );
    let on = run(&["render", &wsp, "-o", png]);
    assert!(!err(&on).contains("sees none"), "{}", err(&on));

    // A volume that is not compressed, given to info, render or decompress.
    std::fs::write(
        dir.path().join("head.dcm"),
        [vec![0u8; 128], b"DICM".to_vec(), vec![0u8; 64]].concat(),
    )
    .unwrap();
    let dcm = dir.path().join("head.dcm");
    for cmd in ["info", "render", "decompress"] {
        let mut args = vec![cmd, dcm.to_str().unwrap()];
        if cmd != "info" {
            args.extend(["-o", o]);
        }
        let e = run(&args);
        assert!(!e.status.success(), "{cmd}");
        assert!(
            err(&e).contains("DICOM volume, not a compressed one") && err(&e).contains("compress"),
            "{cmd}: {}",
            err(&e)
        );
    }
    // Raw samples: not a wavesplat file, compress them first.
    let e = run(&["info", &raw]);
    assert!(err(&e).contains("not a wavesplat file"), "{}", err(&e));

    // An effort that does not exist is named with the ones that do; each that does compresses
    // to the byte target.
    let compress = |effort: &str| compress_raw(&["--target-bytes", "2000", "--effort", effort]);
    let e = compress("slow");
    assert!(!e.status.success());
    assert!(
        err(&e).contains("slow") && err(&e).contains("fast, default, best"),
        "{}",
        err(&e)
    );
    for effort in ["fast", "default", "best"] {
        let e = compress(effort);
        assert!(e.status.success(), "{effort}: {}", err(&e));
        assert!(std::fs::metadata(o).unwrap().len() <= 2000, "{effort}");
    }
}

/// A second server on a database another process holds says so, once.
#[test]
fn a_database_in_use_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("db");
    let args = [
        "serve",
        "cache",
        "--addr",
        "127.0.0.1:0",
        "--db",
        db.to_str().unwrap(),
    ];
    let (mut first, _) = common::spawn_server(&args);
    let second = run(&args);
    let _ = first.kill();
    let _ = first.wait();
    assert!(!second.status.success());
    let e = err(&second);
    assert!(e.contains("in use by another process"), "{e}");
    assert_eq!(e.matches("in use").count(), 1, "{e}");
    assert!(!e.contains("WouldBlock"), "{e}");
}

/// Help that was stale: what compress reads, what cache does, what bench throughput reads,
/// and how α and β turn the volume.
#[test]
fn help_says_what_the_commands_take() {
    let top = out(&run(&["--help"]));
    assert!(top.contains("DICOM") && top.contains("NRRD"), "{top}");
    assert!(top.contains("`show`"), "{top}");
    let bench = out(&run(&["bench", "throughput", "--help"]));
    assert!(bench.contains("NRRD") && bench.contains("DICOM"), "{bench}");
    let render = out(&run(&["render", "--help"]));
    assert!(
        render.contains("y–z plane") && render.contains("--token-file"),
        "{render}"
    );
    let compress = out(&run(&["compress", "--help"]));
    assert!(compress.contains("padded grid"), "{compress}");
}

/// `bench refine` runs on the backend asked for (so one machine's GPU and CPU figures come from
/// the same command) and refuses both at once.
#[test]
fn bench_refine_takes_the_backend_asked_for() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out_dir = dir.path().join("refine");
    let o = run(&[
        "bench",
        "refine",
        "--cpu",
        "--size",
        "16",
        "--image",
        "32",
        "--budgets",
        "8",
        "--links",
        "unlimited",
        "--rest-frames",
        "20",
        "--no-table4",
        "--out",
        out_dir.to_str().expect("utf-8 path"),
    ]);
    assert!(o.status.success(), "{}", err(&o));
    let said = out(&o);
    assert!(said.contains("backend: cpu backend (asked for)"), "{said}");
    let summary = std::fs::read_to_string(out_dir.join("summary.csv")).expect("summary.csv");
    assert_eq!(summary.lines().count(), 2, "{summary}");

    let both = run(&["bench", "refine", "--cpu", "--gpu"]);
    assert_eq!(both.status.code(), Some(2));
    assert!(err(&both).contains("cannot be used with"), "{}", err(&both));
}

/// Negative pairs parse: `--pan -40,30` and `--cue-dir -1.2,0.3` are values, not flags, and
/// the pan moves the picture (the image differs from the centred one).
#[test]
fn negative_pairs_parse_as_values() {
    let dir = tempfile::tempdir().unwrap();
    let (_, wsp) = phantom_files(dir.path());
    let png = |name: &str| dir.path().join(name).to_str().unwrap().to_string();
    let centred = run(&[
        "render",
        &wsp,
        "--cpu",
        "--size",
        "32x32",
        "-o",
        &png("c.png"),
    ]);
    assert!(centred.status.success(), "{}", err(&centred));
    let panned = run(&[
        "render",
        &wsp,
        "--cpu",
        "--size",
        "32x32",
        "--pan",
        "-4,3",
        "--cue-k",
        "0.05",
        "--cue-dir",
        "-1.2,-0.3",
        "-o",
        &png("p.png"),
    ]);
    assert!(panned.status.success(), "{}", err(&panned));
    let a = std::fs::read(png("c.png")).unwrap();
    let b = std::fs::read(png("p.png")).unwrap();
    assert_ne!(a, b, "the pan and the cue change the picture");
    // A cue direction without cueing is refused, not ignored.
    let dir_only = run(&[
        "render",
        &wsp,
        "--cpu",
        "--size",
        "32x32",
        "--cue-dir",
        "-1.2,-0.3",
        "-o",
        &png("d.png"),
    ]);
    assert!(!dir_only.status.success());
    assert!(
        err(&dir_only).contains("give --cue-k"),
        "{}",
        err(&dir_only)
    );
}

/// Logs carry no ANSI colour codes into files and pipes (a worker's log file), nor where
/// `NO_COLOR` asks for none.
#[test]
fn logs_into_a_pipe_have_no_colour_codes() {
    // A client connecting to a closed port logs its connection attempts at trace level.
    let closed = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let url = format!("http://{}", closed.local_addr().unwrap());
    drop(closed);
    let o = Command::new(BIN)
        .args(["--log", "trace", "cache", "list", "--cache", &url])
        .output()
        .expect("run wavesplat");
    let e = err(&o);
    assert!(!o.status.success());
    assert!(e.contains("TRACE"), "no log lines to check: {e}");
    assert!(!e.contains('\u{1b}'), "escape codes in a pipe: {e:?}");
}

/// A command that probes for a GPU prints nothing about the session's runtime directory where
/// there is none (Mesa's device-select layer and libwayland did, twice, reading as a failure).
#[test]
fn probing_for_a_gpu_without_a_runtime_directory_prints_no_error() {
    let dir = tempfile::tempdir().unwrap();
    let (_, wsp) = phantom_files(dir.path());
    let png = dir.path().join("g.png");
    let o = Command::new(BIN)
        .args(["render", &wsp, "--progressive", "--size", "32x32", "-o"])
        .arg(&png)
        .env_remove("XDG_RUNTIME_DIR")
        .env_remove("NODEVICE_SELECT")
        .env_remove("WAYLAND_DISPLAY")
        .output()
        .expect("run wavesplat");
    assert!(o.status.success(), "{}", err(&o));
    let e = err(&o);
    assert!(!e.contains("XDG_RUNTIME_DIR"), "{e}");
    assert!(!e.contains("error"), "{e}");
}

/// Help states the library's defaults (a stale "4 rounds" stayed after the default changed),
/// names every phantom, and a raw file named by the archive's convention compresses without
/// --dims and --dtype, as `archive submit` reads it.
#[test]
fn help_states_the_defaults_and_raw_names_carry_their_layout() {
    let rounds = wavesplat_compressor::refine::RefineOptions::default().rounds;
    for args in [
        &["compress", "--help"][..],
        &["archive", "submit", "--help"][..],
    ] {
        let o = run(args);
        let text = out(&o);
        assert!(
            text.contains(&format!("(default {rounds}")),
            "{args:?} does not state {rounds} rounds: {text}"
        );
        assert!(!text.contains("RefineOptions"), "{args:?}: {text}");
    }
    let help = out(&run(&["compress", "--help"]));
    for name in wavesplat_compressor::phantom::Phantom::names() {
        assert!(help.contains(name), "compress --help omits {name}");
    }
    let dir = tempfile::tempdir().unwrap();
    let raw = dir.path().join("head_20x16x12_f32.raw");
    let raw_s = raw.to_str().unwrap();
    let made = run(&["phantom", "shepp-logan", "--dims", "20,16,12", "-o", raw_s]);
    assert!(made.status.success(), "{}", err(&made));
    let wsp = dir.path().join("head.wsp");
    let c = run(&["compress", raw_s, "-o", wsp.to_str().unwrap()]);
    assert!(c.status.success(), "{}", err(&c));
    let info = run(&["info", wsp.to_str().unwrap()]);
    assert!(
        out(&info).contains("20x16x12") || out(&info).contains("20 x 16 x 12"),
        "{}",
        out(&info)
    );
}

/// A `.wspx` written by `publish` is a file `info`, `render` and `decompress` read as they
/// read the `.wsp` inside it; a cut one is refused saying so.
#[test]
fn a_published_file_reads_locally() {
    let dir = tempfile::tempdir().unwrap();
    let (_, wsp) = phantom_files(dir.path());
    let wspx = dir.path().join("p.wspx");
    let wspx_s = wspx.to_str().unwrap();
    let p = run(&["publish", &wsp, "-o", wspx_s]);
    assert!(p.status.success(), "{}", err(&p));
    let a = run(&["info", &wsp]);
    let b = run(&["info", wspx_s]);
    assert!(b.status.success(), "{}", err(&b));
    assert_eq!(out(&a), out(&b).replace(wspx_s, &wsp));
    let png = dir.path().join("x.png");
    let r = run(&[
        "render",
        wspx_s,
        "--cpu",
        "--size",
        "24x24",
        "-o",
        png.to_str().unwrap(),
    ]);
    assert!(r.status.success(), "{}", err(&r));
    let bytes = std::fs::read(&wspx).unwrap();
    let cut = dir.path().join("cut.wspx");
    std::fs::write(&cut, &bytes[..bytes.len() - 7]).unwrap();
    let c = run(&["info", cut.to_str().unwrap()]);
    assert!(!c.status.success());
    assert!(err(&c).contains("cut short"), "{}", err(&c));
}

/// `cache list` says when each volume was made as a date and time (UTC), not milliseconds
/// since 1970.
#[test]
fn cache_list_shows_creation_times_people_read() {
    let dir = tempfile::tempdir().unwrap();
    let (_, wsp) = phantom_files(dir.path());
    let db = dir.path().join("db");
    let (mut server, addr) = common::spawn_server(&[
        "serve",
        "cache",
        "--db",
        db.to_str().unwrap(),
        "--addr",
        "127.0.0.1:0",
    ]);
    let url = format!("http://{addr}");
    let i = run(&["cache", "ingest", &wsp, "--name", "p", "--cache", &url]);
    assert!(i.status.success(), "{}", err(&i));
    let l = run(&["cache", "list", "--cache", &url]);
    let _ = server.kill();
    let _ = server.wait();
    assert!(l.status.success(), "{}", err(&l));
    let listed = out(&l);
    let created = listed
        .split('\t')
        .find_map(|f| f.strip_prefix("created="))
        .unwrap_or_else(|| panic!("no created= field in {listed}"));
    // e.g. 2026-11-28T17:00:34Z
    let b = created.trim().as_bytes();
    assert_eq!(b.len(), 20, "{created}");
    assert!(
        b[4] == b'-' && b[7] == b'-' && b[10] == b'T' && b[13] == b':' && b[19] == b'Z',
        "{created}"
    );
    assert!(created.starts_with("20"), "{created}");
}

/// An error about an input names its path once ("reading X: X is not …" said it twice).
#[test]
fn a_bad_input_is_named_once() {
    let dir = tempfile::tempdir().unwrap();
    let raw = dir.path().join("unnamed.raw");
    std::fs::write(&raw, [0u8; 64]).unwrap();
    let o = run(&[
        "compress",
        raw.to_str().unwrap(),
        "-o",
        dir.path().join("o.wsp").to_str().unwrap(),
    ]);
    assert!(!o.status.success());
    let e = err(&o);
    assert_eq!(e.matches(raw.to_str().unwrap()).count(), 1, "{e}");
    assert!(e.contains("--dims"), "{e}");
}

/// A single slice (one voxel thin, so its transform has no level) is kept whole by default,
/// with a note saying why, and rendered face-on as an image viewer shows it: x to the right,
/// y down. Before, 5 % of its pixels were kept and it was drawn edge-on at a corner.
#[test]
fn a_single_slice_is_kept_whole_and_shown_face_on() {
    let dir = tempfile::tempdir().unwrap();
    let (w, h) = (48usize, 32usize);
    // Four quadrants of distinct values: top-left 1.0, top-right 0.6, bottom-left 0.3,
    // bottom-right 0.1 (y counts rows downwards), with a fine ripple as real images have (the
    // quantizer's step follows the smallest kept magnitude).
    let value = |x: usize, y: usize| {
        let base = match (x < w / 2, y < h / 2) {
            (true, true) => 1.0f32,
            (false, true) => 0.6,
            (true, false) => 0.3,
            (false, false) => 0.1,
        };
        base + 0.001 * ((x + 2 * y) % 5) as f32
    };
    let mut bytes = Vec::new();
    for y in 0..h {
        for x in 0..w {
            bytes.extend_from_slice(&value(x, y).to_le_bytes());
        }
    }
    let raw = dir.path().join(format!("slice_{w}x{h}x1_f32.raw"));
    std::fs::write(&raw, bytes).unwrap();
    let wsp = dir.path().join("slice.wsp");
    let c = run(&[
        "compress",
        raw.to_str().unwrap(),
        "-o",
        wsp.to_str().unwrap(),
    ]);
    assert!(c.status.success(), "{}", err(&c));
    assert!(err(&c).contains("one voxel thin"), "{}", err(&c));
    // "kept K of N coefficients (P %; Z non-zero)": every non-zero one, K = Z.
    let summary = out(&c);
    let kept = summary
        .split("kept ")
        .nth(1)
        .and_then(|s| s.split(' ').next())
        .unwrap_or_else(|| panic!("no kept count in {summary}"));
    let non_zero = summary
        .split(" %; ")
        .nth(1)
        .and_then(|s| s.split(' ').next())
        .unwrap_or_else(|| panic!("no non-zero count in {summary}"));
    assert_eq!(kept, non_zero, "{summary}");
    let (iw, ih) = (2 * w, 2 * h);
    let png = dir.path().join("slice.png");
    let f32s = dir.path().join("slice.f32");
    let r = run(&[
        "render",
        wsp.to_str().unwrap(),
        "--size",
        &format!("{iw}x{ih}"),
        "-o",
        png.to_str().unwrap(),
        "--raw",
        f32s.to_str().unwrap(),
        "--cpu",
    ]);
    assert!(r.status.success(), "{}", err(&r));
    let image: Vec<f32> = std::fs::read(&f32s)
        .unwrap()
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
        .collect();
    assert_eq!(image.len(), iw * ih);
    // The pixel over a quadrant's centre: the slice fills most of the image, centred.
    let at = |fx: f64, fy: f64| {
        let px = (iw as f64 / 2.0 + (fx - 0.5) * 0.8 * iw as f64) as usize;
        let py = (ih as f64 / 2.0 + (fy - 0.5) * 0.8 * ih as f64) as usize;
        image[py * iw + px] as f64
    };
    let (tl, tr, bl, br) = (
        at(0.25, 0.25),
        at(0.75, 0.25),
        at(0.25, 0.75),
        at(0.75, 0.75),
    );
    assert!(tl > 0.0, "top-left {tl}");
    for (name, got, want) in [
        ("top-right", tr, 0.6),
        ("bottom-left", bl, 0.3),
        ("bottom-right", br, 0.1),
    ] {
        assert!(
            (got / tl - want).abs() < 0.05,
            "{name}/top-left = {} (want {want}); quadrants {tl} {tr} {bl} {br}",
            got / tl
        );
    }
}

/// `--cue-k auto` takes the extinction from the volume (2 / its diagonal: the far end of the
/// longest path weighted e^-2), says which it took, and draws what that explicit k draws; a
/// value that is not an extinction is refused naming `auto`.
#[test]
fn cue_k_auto_takes_its_scale_from_the_volume() {
    let dir = tempfile::tempdir().unwrap();
    let (_raw, wsp) = phantom_files(dir.path());
    let png = |n: &str| dir.path().join(n).to_str().unwrap().to_string();
    let auto = run(&[
        "render",
        &wsp,
        "--cpu",
        "--size",
        "32x32",
        "--cue-k",
        "auto",
        "-o",
        &png("a.png"),
    ]);
    assert!(auto.status.success(), "{}", err(&auto));
    // The phantom is 16³ at unit spacing: diagonal 16·√3.
    let want = 2.0 / (16.0 * 3f64.sqrt());
    let said = out(&auto);
    let k: f64 = said
        .split("depth cueing: k = ")
        .nth(1)
        .and_then(|s| s.split(' ').next())
        .and_then(|s| s.parse().ok())
        .unwrap_or_else(|| panic!("no k in {said}"));
    assert!((k - want).abs() < 1e-5, "k {k}, want {want}");
    let explicit = run(&[
        "render",
        &wsp,
        "--cpu",
        "--size",
        "32x32",
        "--cue-k",
        &format!("{want}"),
        "-o",
        &png("e.png"),
    ]);
    assert!(explicit.status.success(), "{}", err(&explicit));
    let plain = run(&[
        "render",
        &wsp,
        "--cpu",
        "--size",
        "32x32",
        "-o",
        &png("p.png"),
    ]);
    assert!(plain.status.success(), "{}", err(&plain));
    let [a, e, p] = ["a.png", "e.png", "p.png"].map(|n| std::fs::read(png(n)).unwrap());
    assert_eq!(a, e, "auto draws what its k draws");
    assert_ne!(a, p, "auto cues");
    let bad = run(&["render", &wsp, "--cue-k", "strong", "-o", &png("b.png")]);
    assert!(!bad.status.success());
    assert!(err(&bad).contains("auto"), "{}", err(&bad));
}

/// `compress --brick` writes one bricked file from a raw file read brick by brick; `info`
/// lists its bricks and `render` draws it (the same picture as the unbricked file, within the
/// accuracy of their different coefficient sets); options the bricked path does not have are
/// refused saying so.
/// A volume that does not fit the memory limit whole is bricked without `--brick`, at the
/// largest side whose bricks (one per thread) fit, and renders; the same file without a limit
/// (it fits the memory available) is compressed whole as before.
#[test]
fn a_volume_over_the_memory_limit_is_bricked_by_itself() {
    let dir = tempfile::tempdir().unwrap();
    let path = |n: &str| dir.path().join(n).to_str().unwrap().to_string();
    let n = 128usize;
    let ball: Vec<u8> = (0..n * n * n)
        .map(|i| {
            let (x, y, z) = (i % n, i / n % n, i / (n * n));
            let r2 = [x, y, z]
                .iter()
                .map(|&c| (c as f64 - 63.5).powi(2))
                .sum::<f64>();
            if r2 < 40.0 * 40.0 {
                200
            } else {
                0
            }
        })
        .collect();
    let raw = path("ball_128x128x128_u8.raw");
    std::fs::write(&raw, &ball).unwrap();
    // The whole needs ~203 MB by the estimate, a 64³ brick ~114 MB of which 64 MB once per
    // process: two threads' bricks fit 180 MB, the whole does not.
    let c = run(&[
        "compress",
        &raw,
        "--memory-limit",
        "180M",
        "-o",
        &path("b.wsp"),
    ]);
    assert!(c.status.success(), "{}", err(&c));
    assert!(
        err(&c).contains("bricks of at most 64 voxels a side")
            && err(&c).contains("--memory-limit"),
        "{}",
        err(&c)
    );
    assert!(out(&c).contains("8 bricks"), "{}", out(&c));
    let info = run(&["info", &path("b.wsp")]);
    assert!(out(&info).contains("bricked container"), "{}", out(&info));
    // The bricks' depth and coder, shared by all of them.
    assert!(
        out(&info).contains("coding      linear (order 2), levels M = ")
            && out(&info).contains(", every brick"),
        "{}",
        out(&info)
    );
    let r = run(&[
        "render",
        &path("b.wsp"),
        "--cpu",
        "--size",
        "64x64",
        "-o",
        &path("b.png"),
    ]);
    assert!(r.status.success(), "{}", err(&r));
    assert!(out(&r).contains("8 of 8 bricks drawn"), "{}", out(&r));
    // Below what even the smallest bricks need on two threads: refused, saying what they need
    // and that one thread fits; run on one thread it compresses.
    let on_threads = |threads: &str, limit: &str| {
        Command::new(BIN)
            .env("RAYON_NUM_THREADS", threads)
            .args(["compress", &raw, "--memory-limit", limit, "-o"])
            .arg(path("t.wsp"))
            .output()
            .unwrap()
    };
    let refused = on_threads("2", "120M");
    assert!(!refused.status.success());
    assert!(
        err(&refused).contains("in the smallest bricks (32³, 2 at a time on 2 thread(s)")
            && err(&refused).contains("give --memory-limit")
            && err(&refused).contains("or one thread (RAYON_NUM_THREADS=1 needs"),
        "{}",
        err(&refused)
    );
    let one = on_threads("1", "120M");
    assert!(one.status.success(), "{}", err(&one));
    assert!(out(&one).contains("bricks"), "{}", out(&one));
    let none = on_threads("1", "64M");
    assert!(!none.status.success());
    assert!(
        err(&none).contains("give --memory-limit") && !err(&none).contains("or one thread"),
        "{}",
        err(&none)
    );
    let w = run(&["compress", &raw, "-o", &path("w.wsp")]);
    assert!(w.status.success(), "{}", err(&w));
    assert!(!err(&w).contains("bricks of at most"), "{}", err(&w));
    // A phantom is probed the same way (its size is known without reading anything).
    let p = run(&[
        "compress",
        "--phantom",
        "spheres",
        "--dims",
        "128,128,128",
        "--memory-limit",
        "180M",
        "-o",
        &path("p.wsp"),
    ]);
    assert!(p.status.success(), "{}", err(&p));
    assert!(
        err(&p).contains("bricks of at most 64 voxels a side"),
        "{}",
        err(&p)
    );
    assert!(out(&p).contains("8 bricks"), "{}", out(&p));
    let info = run(&["info", &path("w.wsp")]);
    assert!(!out(&info).contains("bricked"), "{}", out(&info));
}

/// `--brick N` with a memory limit one brick of N does not fit is refused before any brick is
/// scored, saying what one brick needs and what to change, and leaves no checkpoint to resume
/// (running again could not help); the limit the message names is enough.
#[test]
fn bricks_that_do_not_fit_the_memory_limit_are_refused_before_any_is_compressed() {
    let dir = tempfile::tempdir().unwrap();
    let out_path = dir.path().join("b.wsp");
    let compress = |limit: &str| {
        run(&[
            "compress",
            "--phantom",
            "ct",
            "--dims",
            "64,64,48",
            "--brick",
            "32",
            "--effort",
            "fast",
            "--target-fraction",
            "0.05",
            "--memory-limit",
            limit,
            "-o",
            out_path.to_str().unwrap(),
        ])
    };
    let refused = compress("1M");
    assert!(!refused.status.success());
    let e = err(&refused);
    assert!(
        e.contains("one brick needs more memory than --memory-limit")
            && e.contains("smaller --brick")
            && e.contains("the limit is 1048576 bytes")
            && !e.contains("run the same command again")
            && !e.contains("panicked"),
        "{e}"
    );
    let left: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
    assert!(left.is_empty(), "{left:?}");
    // What one brick needs, by the message, is a limit it fits.
    let needed = e
        .split("compressing needs about ")
        .nth(1)
        .and_then(|r| r.split(' ').next())
        .and_then(|n| n.parse::<u64>().ok())
        .unwrap_or_else(|| panic!("no estimate in {e}"));
    let fits = compress(&needed.to_string());
    assert!(fits.status.success(), "{}", err(&fits));
    assert!(out(&fits).contains("8 bricks"), "{}", out(&fits));
}

/// A bricked compression killed midway (SIGKILL, as a reboot or the OOM killer would) leaves
/// the bricks it finished in OUTPUT.checkpoint; the same command run again says it resumes,
/// writes the file an uninterrupted run writes, byte for byte, and removes the checkpoint.
/// With --no-resume it starts over instead, and still writes that file.
#[test]
fn a_killed_bricked_compression_resumes_where_it_stopped() {
    killed_and_resumed(&[
        "--phantom",
        "shepp-logan",
        "--dims",
        "96,96,80",
        "--brick",
        "16",
        "--target-fraction",
        "0.05",
    ]);
}

/// The same for a colour volume at a byte target: the resumed run takes the whole's colour
/// transform, the depth and the rate search's start from the checkpoint's plan, and the
/// coded bricks of the trials it finished, and still writes the uninterrupted run's file.
#[test]
fn a_killed_colour_bricked_compression_at_a_byte_target_resumes() {
    killed_and_resumed(&[
        "--phantom",
        "rgb-head",
        "--dims",
        "64,64,48",
        "--brick",
        "16",
        "--target-bytes",
        "20000",
    ]);
}

/// The same without refinement (`--effort fast`) at a byte target, where the uninterrupted run
/// codes every brick from the top its score pass kept, and the resumed one codes the bricks
/// not yet coded from the tops the checkpoint kept (it says so): both write one file.
#[test]
fn a_killed_fast_bricked_compression_at_a_byte_target_resumes() {
    killed_and_resumed(&[
        "--phantom",
        "ct",
        "--dims",
        "96,80,64",
        "--brick",
        "16",
        "--effort",
        "fast",
        "--target-bytes",
        "30000",
    ]);
}

/// Runs `wavesplat ARGS` and kills it (SIGKILL) once `checkpoint` holds a coded brick.
fn kill_once_a_brick_is_coded(args: &[String], checkpoint: &std::path::Path) {
    kill_once_the_checkpoint_holds(args, checkpoint, &["brick-"]);
}

/// Runs `args` and kills the run once its checkpoint holds an entry named with each of
/// `prefixes`.
fn kill_once_the_checkpoint_holds(
    args: &[String],
    checkpoint: &std::path::Path,
    prefixes: &[&str],
) {
    let mut child = Command::new(BIN)
        .args(args)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let coded = || {
        std::fs::read_dir(checkpoint).is_ok_and(|entries| {
            let names: Vec<String> = entries
                .flatten()
                .map(|e| e.file_name().to_string_lossy().into_owned())
                .filter(|n| !n.ends_with(".tmp"))
                .collect();
            prefixes
                .iter()
                .all(|p| names.iter().any(|n| n.starts_with(p)))
        })
    };
    let start = std::time::Instant::now();
    while !coded() {
        assert!(
            child.try_wait().unwrap().is_none(),
            "finished before it could be killed"
        );
        assert!(start.elapsed().as_secs() < 300, "no brick coded");
        std::thread::sleep(std::time::Duration::from_millis(1));
    }
    child.kill().unwrap();
    child.wait().unwrap();
}

/// A killed run's checkpoint survives a run again under a memory limit its bricks do not fit:
/// that run is refused saying the finished bricks are kept, and the run after it, without
/// the limit, resumes from them and writes the uninterrupted run's file.
#[test]
fn a_memory_refusal_keeps_the_checkpoint_of_an_earlier_run() {
    let dir = tempfile::tempdir().unwrap();
    let path = |n: &str| dir.path().join(n).to_str().unwrap().to_string();
    let args = |out: &str, extra: &[&str]| -> Vec<String> {
        [
            "compress",
            "--phantom",
            "shepp-logan",
            "--dims",
            "96,96,80",
            "--brick",
            "16",
            "--target-fraction",
            "0.05",
            "-o",
            out,
        ]
        .iter()
        .chain(extra)
        .map(|s| s.to_string())
        .collect()
    };
    let checkpoint = dir.path().join("k.wsp.checkpoint");
    kill_once_a_brick_is_coded(&args(&path("k.wsp"), &[]), &checkpoint);
    let refused = Command::new(BIN)
        .args(args(&path("k.wsp"), &["--memory-limit", "1M"]))
        .output()
        .unwrap();
    assert!(!refused.status.success());
    assert!(
        err(&refused).contains("the limit is 1048576 bytes")
            && err(&refused).contains("run the same command again"),
        "{}",
        err(&refused)
    );
    assert!(checkpoint.exists(), "the earlier run's bricks are kept");
    let again = Command::new(BIN)
        .args(args(&path("k.wsp"), &[]))
        .output()
        .unwrap();
    assert!(again.status.success(), "{}", err(&again));
    assert!(out(&again).contains("resuming"), "{}", out(&again));
    assert!(!checkpoint.exists());
    let fresh = Command::new(BIN)
        .args(args(&path("fresh.wsp"), &[]))
        .output()
        .unwrap();
    assert!(fresh.status.success(), "{}", err(&fresh));
    assert_eq!(
        std::fs::read(path("k.wsp")).unwrap(),
        std::fs::read(path("fresh.wsp")).unwrap()
    );
}

/// An input rewritten in place between the killed run and the run again, with its length and
/// modification time kept (as a copy that keeps times would leave it), is not the checkpoint's:
/// the run again reads the whole input, finds its digest changed, starts over and writes the
/// new contents' file. Both a rewrite the key's 16 sampled blocks see (every row reversed) and
/// one they do not (one sample between them). Unchanged, the input is resumed from.
#[test]
fn a_checkpoint_is_resumed_only_from_an_input_of_the_same_bytes() {
    let dir = tempfile::tempdir().unwrap();
    let path = |n: &str| dir.path().join(n).to_str().unwrap().to_string();
    let raw = path("head_64x64x48_f32.raw");
    let made = run(&["phantom", "shepp-logan", "--dims", "64,64,48", "-o", &raw]);
    assert!(made.status.success(), "{}", err(&made));
    let args = |out: &str| -> Vec<String> {
        [
            "compress",
            &raw,
            "--brick",
            "16",
            "--target-fraction",
            "0.05",
            "-o",
            out,
        ]
        .iter()
        .map(|s| s.to_string())
        .collect()
    };
    let run_args = |args: Vec<String>| Command::new(BIN).args(args).output().unwrap();
    let checkpoint = dir.path().join("k.wsp.checkpoint");
    let kill = || {
        kill_once_the_checkpoint_holds(&args(&path("k.wsp")), &checkpoint, &["brick-", "content"])
    };
    let fresh_of_now = |name: &str| {
        let fresh = run_args(args(&path(name)));
        assert!(fresh.status.success(), "{}", err(&fresh));
        std::fs::read(path(name)).unwrap()
    };
    kill();
    let again = run_args(args(&path("k.wsp")));
    assert!(again.status.success(), "{}", err(&again));
    assert!(out(&again).contains("resuming"), "{}", out(&again));
    let mut before = fresh_of_now("a.wsp");
    assert_eq!(std::fs::read(path("k.wsp")).unwrap(), before);
    std::fs::remove_file(path("k.wsp")).unwrap();

    // Every row reversed along x; then one sample at byte 8 192 (the key's blocks of 4 KiB
    // over these 786 432 bytes start at 0 and 52 155, so it lies in neither).
    let reversed = |bytes: &mut Vec<u8>| {
        let rows: Vec<u8> = bytes
            .chunks(64 * 4)
            .flat_map(|row| row.chunks(4).rev().flatten().copied().collect::<Vec<u8>>())
            .collect();
        *bytes = rows;
    };
    let one_sample = |bytes: &mut Vec<u8>| {
        let at = 8192;
        let sample = f32::from_le_bytes(bytes[at..at + 4].try_into().unwrap());
        bytes[at..at + 4].copy_from_slice(&(sample + 100.0).to_le_bytes());
    };
    /// A change of the input's bytes in place.
    type Rewrite<'a> = &'a dyn Fn(&mut Vec<u8>);
    let rewrites: [Rewrite; 2] = [&reversed, &one_sample];
    for (k, rewrite) in rewrites.into_iter().enumerate() {
        kill();
        let modified = std::fs::metadata(&raw).unwrap().modified().unwrap();
        let mut bytes = std::fs::read(&raw).unwrap();
        let old = bytes.clone();
        rewrite(&mut bytes);
        assert_ne!(bytes, old);
        std::fs::write(&raw, &bytes).unwrap();
        let file = std::fs::File::options().write(true).open(&raw).unwrap();
        file.set_modified(modified).unwrap();
        drop(file);
        assert_eq!(
            std::fs::metadata(&raw).unwrap().modified().unwrap(),
            modified
        );
        let again = run_args(args(&path("k.wsp")));
        assert!(again.status.success(), "{}", err(&again));
        assert!(!out(&again).contains("resuming"), "{k}: {}", out(&again));
        // The sampled blocks tell the first apart by the key; the second only the digest does.
        let said = ["of another input", "contents changed"][k];
        assert!(err(&again).contains(said), "{k}: {}", err(&again));
        assert!(!checkpoint.exists());
        let want = fresh_of_now("b.wsp");
        assert_eq!(std::fs::read(path("k.wsp")).unwrap(), want, "{k}");
        assert_ne!(want, before, "{k}");
        before = want;
        std::fs::remove_file(path("k.wsp")).unwrap();
    }
}

/// Compresses with `options` once uninterrupted, then killed once a brick is coded and run
/// again (it resumes), then killed again and run with --no-resume (it starts over): both
/// runs again write the uninterrupted file and leave no checkpoint or unfinished output.
fn killed_and_resumed(options: &[&str]) {
    let fast = options.contains(&"fast");
    let dir = tempfile::tempdir().unwrap();
    let path = |n: &str| dir.path().join(n).to_str().unwrap().to_string();
    let args = |out: &str| {
        std::iter::once("compress")
            .chain(options.iter().copied())
            .chain(["-o", out])
            .map(str::to_string)
            .collect::<Vec<_>>()
    };
    let whole = Command::new(BIN)
        .args(args(&path("whole.wsp")))
        .output()
        .unwrap();
    assert!(whole.status.success(), "{}", err(&whole));
    let want = std::fs::read(path("whole.wsp")).unwrap();
    let checkpoint = dir.path().join("k.wsp.checkpoint");
    // Killed once the checkpoint holds a coded brick (tens of bricks: far from done).
    let kill_midway = || {
        kill_once_a_brick_is_coded(&args(&path("k.wsp")), &checkpoint);
        assert!(!dir.path().join("k.wsp").exists());
    };
    kill_midway();
    let resumed = Command::new(BIN)
        .args(args(&path("k.wsp")))
        .output()
        .unwrap();
    assert!(resumed.status.success(), "{}", err(&resumed));
    assert!(
        out(&resumed).contains("resuming from") && out(&resumed).contains("k.wsp.checkpoint"),
        "{}",
        out(&resumed)
    );
    assert_eq!(std::fs::read(path("k.wsp")).unwrap(), want);
    // Killed once a brick was coded, so after every brick was scored: without refinement
    // every brick's top is in the checkpoint, and none of them is transformed again.
    assert_eq!(
        out(&resumed).contains("with their kept tops"),
        fast,
        "{}",
        out(&resumed)
    );
    assert!(
        !checkpoint.exists(),
        "the checkpoint is removed once the file is written"
    );
    // The killed run's unfinished output (SIGKILL is not caught) is removed by the run again.
    let left: Vec<String> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.ends_with(".partial"))
        .collect();
    assert!(left.is_empty(), "{left:?}");
    assert!(
        out(&resumed).contains("left by the interrupted run"),
        "{}",
        out(&resumed)
    );
    std::fs::remove_file(path("k.wsp")).unwrap();
    kill_midway();
    let mut fresh = args(&path("k.wsp"));
    fresh.push("--no-resume".into());
    let over = Command::new(BIN).args(fresh).output().unwrap();
    assert!(over.status.success(), "{}", err(&over));
    assert!(!out(&over).contains("resuming"), "{}", out(&over));
    assert_eq!(std::fs::read(path("k.wsp")).unwrap(), want);
    assert!(!checkpoint.exists());
    let partial = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .any(|n| n.ends_with(".partial"));
    assert!(
        !partial,
        "--no-resume removes the killed run's unfinished output too"
    );
}

#[test]
fn a_bricked_volume_is_compressed_listed_and_rendered() {
    let dir = tempfile::tempdir().unwrap();
    let path = |n: &str| dir.path().join(n).to_str().unwrap().to_string();
    let raw = path("head_40x36x32_f32.raw");
    assert!(
        run(&["phantom", "shepp-logan", "--dims", "40,36,32", "-o", &raw])
            .status
            .success()
    );
    let c = run(&[
        "compress",
        &raw,
        "--brick",
        "20",
        "--target-fraction",
        "0.2",
        "-o",
        &path("b.wsp"),
    ]);
    assert!(c.status.success(), "{}", err(&c));
    assert!(out(&c).contains("8 bricks"), "{}", out(&c));
    assert!(!out(&c).contains("note: the manifest"), "{}", out(&c));
    // Written under a temporary name and renamed: nothing else is left beside it, and it has
    // the permissions a plainly written file gets (readable by a web server), not a temporary
    // file's owner-only ones.
    let beside: Vec<String> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n != "head_40x36x32_f32.raw" && n != "b.wsp")
        .collect();
    assert!(beside.is_empty(), "{beside:?}");
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        std::fs::write(path("plain"), b"x").unwrap();
        let mode = |n: &str| std::fs::metadata(path(n)).unwrap().permissions().mode() & 0o777;
        assert_eq!(mode("b.wsp"), mode("plain"));
        std::fs::remove_file(path("plain")).unwrap();
        // Written through a link to an existing file: the link stays, the file keeps its mode.
        std::fs::write(path("kept.wsp"), b"old").unwrap();
        std::fs::set_permissions(path("kept.wsp"), std::fs::Permissions::from_mode(0o640)).unwrap();
        std::os::unix::fs::symlink(path("kept.wsp"), path("link.wsp")).unwrap();
        let l = run(&["compress", &raw, "--brick", "20", "-o", &path("link.wsp")]);
        assert!(l.status.success(), "{}", err(&l));
        let meta = std::fs::symlink_metadata(path("link.wsp")).unwrap();
        assert!(meta.file_type().is_symlink());
        assert_eq!(mode("kept.wsp"), 0o640);
        assert!(std::fs::read(path("kept.wsp"))
            .unwrap()
            .starts_with(b"WSPL"));
        for n in ["kept.wsp", "link.wsp"] {
            std::fs::remove_file(path(n)).unwrap();
        }
    }
    // A bricked compression whose output directory is missing is refused, naming it.
    let missing = run(&[
        "compress",
        &raw,
        "--brick",
        "20",
        "-o",
        &path("no/such/dir/b.wsp"),
    ]);
    assert!(!missing.status.success());
    assert!(err(&missing).contains("no/such/dir"), "{}", err(&missing));
    // Small bricks at a small byte target with the fast coder: the headers (its tables) take
    // most of the file, and the summary says so and what leaves more.
    let small = run(&[
        "compress",
        &raw,
        "--brick",
        "10",
        "--coder",
        "fast",
        "--target-bytes",
        "20000",
        "-o",
        &path("small.wsp"),
    ]);
    assert!(small.status.success(), "{}", err(&small));
    assert!(
        out(&small).contains("note: the manifest and the bricks' headers take")
            && out(&small).contains("fast coder's tables")
            && out(&small).contains("larger bricks (--brick)"),
        "{}",
        out(&small)
    );
    // The phantom read brick by brick (generated a box at a time, never whole) makes the same
    // file as the phantom written out and read brick by brick from the file.
    let p = run(&[
        "compress",
        "--phantom",
        "shepp-logan",
        "--dims",
        "40,36,32",
        "--brick",
        "20",
        "--target-fraction",
        "0.2",
        "-o",
        &path("p.wsp"),
    ]);
    assert!(p.status.success(), "{}", err(&p));
    assert_eq!(
        std::fs::read(path("p.wsp")).unwrap(),
        std::fs::read(path("b.wsp")).unwrap()
    );
    let info = run(&["info", &path("b.wsp")]);
    assert!(out(&info).contains("bricks      8"), "{}", out(&info));
    assert!(
        out(&info).contains("the manifest and their headers"),
        "{}",
        out(&info)
    );
    assert!(
        out(&info).contains("brick 7: at 20,18,16"),
        "{}",
        out(&info)
    );
    // Where the bytes went, over every brick: the parts sum to the file, and the share of
    // coefficients in the bricks' padding is named.
    let listed = out(&info);
    let parts: f64 = [
        "header + tables",
        "packet directory",
        "packet framing/summary",
        "type/depth/channel",
        "positions",
        "signs",
        "values",
    ]
    .iter()
    .map(|name| {
        let line = listed
            .lines()
            .find(|l| l.trim_start().starts_with(name))
            .unwrap_or_else(|| panic!("no {name} in {listed}"));
        line.trim_start()[name.len()..]
            .split_whitespace()
            .next()
            .and_then(|v| v.parse::<f64>().ok())
            .unwrap_or_else(|| panic!("{line}"))
    })
    .sum();
    let bytes = std::fs::metadata(path("b.wsp")).unwrap().len() as f64;
    assert!((parts - bytes).abs() <= 8.0, "{parts} of {bytes}: {listed}");
    assert!(
        listed.contains("of the kept coefficients")
            && listed.contains("sit in the bricks' padding"),
        "{listed}"
    );
    let w = run(&[
        "compress",
        &raw,
        "--target-fraction",
        "0.2",
        "-o",
        &path("w.wsp"),
    ]);
    assert!(w.status.success(), "{}", err(&w));
    for (file, img) in [("b.wsp", "b.f32"), ("w.wsp", "w.f32")] {
        let r = run(&[
            "render",
            &path(file),
            "--cpu",
            "--size",
            "48x48",
            "-o",
            &path("x.png"),
            "--raw",
            &path(img),
        ]);
        assert!(r.status.success(), "{}", err(&r));
    }
    let read = |n: &str| -> Vec<f32> {
        std::fs::read(path(n))
            .unwrap()
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
            .collect()
    };
    let snr = wavesplat_codec::metrics::snr_db(&read("w.f32"), &read("b.f32"));
    assert!(snr > 25.0, "bricked against whole: {snr:.1} dB");
    // `decompress` writes the bricked volume brick by brick, every row in its place: as close
    // to the original as the unbricked file's (a brick or a row out of place costs tens of dB).
    for (file, raw_out) in [("b.wsp", "b.raw"), ("w.wsp", "w.raw")] {
        let d = run(&["decompress", &path(file), "-o", &path(raw_out)]);
        assert!(d.status.success(), "{}", err(&d));
    }
    // A damaged brick is refused and nothing half-written is left.
    let mut damaged = std::fs::read(path("b.wsp")).unwrap();
    let last = damaged.len() - 3;
    damaged[last] ^= 0x5a;
    std::fs::write(path("bad.wsp"), &damaged).unwrap();
    let bad = run(&["decompress", &path("bad.wsp"), "-o", &path("bad.raw")]);
    assert!(!bad.status.success());
    assert!(err(&bad).contains("brick"), "{}", err(&bad));
    assert!(!dir.path().join("bad.raw").exists());
    assert!(!dir.path().join("bad.raw.partial").exists());
    // A failed decode leaves an earlier file of that name as it was.
    std::fs::write(path("keep.raw"), b"earlier").unwrap();
    assert!(
        !run(&["decompress", &path("bad.wsp"), "-o", &path("keep.raw")])
            .status
            .success()
    );
    assert_eq!(std::fs::read(path("keep.raw")).unwrap(), b"earlier");
    let again = run(&["decompress", &path("b.wsp"), "-o", &path("b2.raw")]);
    assert!(out(&again).contains("8 bricks"), "{}", out(&again));
    // The same bricks behind the first container version's manifest (explicit entries, what
    // earlier builds wrote) read the same: `info` names the version, `decompress` writes the
    // same volume.
    {
        use wavesplat_codec::format::bricked::{
            parse_bricked, write_bricked, BRICKED_VERSION, EXPLICIT_BRICKED_VERSION,
        };
        let bytes = std::fs::read(path("b.wsp")).unwrap();
        let f = parse_bricked(&bytes).unwrap();
        assert_eq!(f.manifest.version, BRICKED_VERSION);
        let bricks: Vec<&[u8]> = (0..f.manifest.bricks.len())
            .map(|i| f.brick_bytes(i).unwrap())
            .collect();
        let mut old = f.manifest.clone();
        old.version = EXPLICIT_BRICKED_VERSION;
        let old_bytes = write_bricked(&mut old, &bricks).unwrap();
        assert!(old_bytes.len() > bytes.len());
        std::fs::write(path("b9.wsp"), &old_bytes).unwrap();
        let info = run(&["info", &path("b9.wsp")]);
        assert!(out(&info).contains("(version 9)"), "{}", out(&info));
        let d = run(&["decompress", &path("b9.wsp"), "-o", &path("b9.raw")]);
        assert!(d.status.success(), "{}", err(&d));
        assert_eq!(
            std::fs::read(path("b9.raw")).unwrap(),
            std::fs::read(path("b2.raw")).unwrap()
        );
    }
    let original = read("head_40x36x32_f32.raw");
    let (bricked, whole) = (read("b.raw"), read("w.raw"));
    assert_eq!(bricked.len(), original.len());
    let (sb, sw) = (
        wavesplat_codec::metrics::snr_db(&original, &bricked),
        wavesplat_codec::metrics::snr_db(&original, &whole),
    );
    assert!(
        sb > 20.0 && sb > sw - 3.0,
        "decoded bricked {sb:.1} dB, whole {sw:.1} dB"
    );
    // Drawn progressively, through the frame loop, the bricked file ends at its one-pass image
    // (f32 sums in another order).
    let progressive = run(&[
        "render",
        &path("b.wsp"),
        "--cpu",
        "--progressive",
        "--size",
        "48x48",
        "-o",
        &path("y.png"),
        "--raw",
        &path("y.f32"),
    ]);
    assert!(progressive.status.success(), "{}", err(&progressive));
    let snr = wavesplat_codec::metrics::snr_db(&read("b.f32"), &read("y.f32"));
    assert!(snr > 90.0, "progressive against one pass: {snr:.1} dB");
    // Multiview progressively (each panel moved into the bricks by its own pan) ends at the
    // one-pass multiview image.
    for (name, extra) in [
        ("one-pass", &[][..]),
        ("progressive", &["--progressive"][..]),
    ] {
        let (b_wsp, m_png) = (path("b.wsp"), path("m.png"));
        let raw = path(&format!("m-{name}.f32"));
        let mut args = vec![
            "render",
            &b_wsp,
            "--cpu",
            "--multiview",
            "--size",
            "40x40",
            "-o",
            &m_png,
            "--raw",
            &raw,
        ];
        args.extend_from_slice(extra);
        let drawn = run(&args);
        assert!(drawn.status.success(), "{name}: {}", err(&drawn));
    }
    let (one_pass, progressive) = (read("m-one-pass.f32"), read("m-progressive.f32"));
    assert_eq!(one_pass.len(), 3 * 40 * 40, "three panels");
    assert!(one_pass.iter().any(|v| *v != 0.0));
    let snr = wavesplat_codec::metrics::snr_db(&one_pass, &progressive);
    assert!(
        snr > 90.0,
        "multiview progressive against one pass: {snr:.1} dB"
    );
    // Published (the indexed layout of every brick; browsing it is tests/range_browse.rs), and
    // read back locally as the same volume. (Cache nodes serve it too: tests/cache_bricked.rs.)
    let published = run(&["publish", &path("b.wsp"), "-o", &path("b.wspx")]);
    assert!(published.status.success(), "{}", err(&published));
    let info = run(&["info", &path("b.wspx")]);
    assert!(out(&info).contains("bricks      8"), "{}", out(&info));
}

/// Stopped by Ctrl-C (SIGINT) or SIGTERM while it writes a bricked file, `compress` removes its
/// unfinished file (a stopped compression of a large volume would otherwise leave a hidden file
/// about the output's size): only the checkpoint it resumes from is left, said on stderr, and
/// the status says it was interrupted.
#[cfg(unix)]
#[test]
fn an_interrupted_compress_leaves_no_unfinished_file() {
    for signal in ["-INT", "-TERM"] {
        let dir = tempfile::tempdir().unwrap();
        let output = dir.path().join("big.wsp");
        let mut child = Command::new(BIN)
            .args([
                "compress",
                "--phantom",
                "ct",
                "--dims",
                "160,160,160",
                "--brick",
                "32",
            ])
            .args(["--target-fraction", "0.5", "-o"])
            .arg(&output)
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        let unfinished = || {
            std::fs::read_dir(dir.path())
                .unwrap()
                .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
                .collect::<Vec<_>>()
        };
        let started = std::time::Instant::now();
        while unfinished().is_empty() {
            assert!(
                child.try_wait().unwrap().is_none(),
                "compress ended before it could be interrupted"
            );
            assert!(
                started.elapsed().as_secs() < 120,
                "no unfinished file appeared"
            );
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
        std::thread::sleep(std::time::Duration::from_millis(200));
        let killed = Command::new("kill")
            .args([signal, &child.id().to_string()])
            .status()
            .unwrap();
        assert!(killed.success());
        let done = child.wait_with_output().unwrap();
        let stderr = String::from_utf8_lossy(&done.stderr).into_owned();
        assert_eq!(done.status.code(), Some(130), "{signal}: {stderr}");
        assert!(
            stderr.contains("removed the unfinished"),
            "{signal}: {stderr}"
        );
        // The checkpoint stays on purpose, and the message says what to do with it.
        assert!(
            stderr.contains("big.wsp.checkpoint: run the same command again"),
            "{signal}: {stderr}"
        );
        assert_eq!(
            unfinished(),
            vec!["big.wsp.checkpoint".to_string()],
            "{signal}"
        );
    }
}

/// An output that is the input (by its name, or through a link) is refused before anything is
/// written, the input left as it was; a bricked file decoded into a device writes in place and
/// leaves the device a device; decoded through a link, the link stays a link.
#[test]
fn outputs_never_replace_the_input_or_a_device() {
    use std::os::unix::fs::FileTypeExt;
    let dir = tempfile::tempdir().unwrap();
    let path = |n: &str| dir.path().join(n).to_str().unwrap().to_string();
    let (raw, wsp) = phantom_files(dir.path());
    let raw_before = std::fs::read(&raw).unwrap();
    let wsp_before = std::fs::read(&wsp).unwrap();
    std::os::unix::fs::symlink(&raw, path("raw-link")).unwrap();
    let refused: [Vec<&str>; 6] = [
        vec![
            "compress", &raw, "--dims", "16,16,16", "--dtype", "f32", "-o", &raw,
        ],
        vec![
            "compress", &raw, "--dims", "16,16,16", "--dtype", "f32", "-o",
        ],
        vec!["decompress", &wsp, "-o", &wsp],
        vec!["publish", &wsp, "-o", &wsp],
        vec!["render", &wsp, "--cpu", "--size", "8x8", "-o", &wsp],
        vec![
            "render", &wsp, "--cpu", "--size", "8x8", "-o", "x.png", "--raw", &wsp,
        ],
    ];
    let link = path("raw-link");
    for mut args in refused {
        if args.last() == Some(&"-o") {
            args.push(&link);
        }
        let o = run(&args);
        assert!(!o.status.success(), "{args:?} succeeded");
        assert!(err(&o).contains("is the input"), "{args:?}: {}", err(&o));
    }
    assert_eq!(std::fs::read(&raw).unwrap(), raw_before);
    assert_eq!(std::fs::read(&wsp).unwrap(), wsp_before);
    // A bricked file into a character device (a null device made here) and through a link.
    let bricked = path("b.wsp");
    let c = run(&[
        "compress", &raw, "--dims", "16,16,16", "--dtype", "f32", "--brick", "8", "-o", &bricked,
    ]);
    assert!(c.status.success(), "{}", err(&c));
    let device = path("null");
    let made = Command::new("mknod")
        .args([&device, "c", "1", "3"])
        .status()
        .is_ok_and(|s| s.success());
    if made {
        let d = run(&["decompress", &bricked, "-o", &device]);
        assert!(d.status.success(), "{}", err(&d));
        let meta = std::fs::symlink_metadata(&device).unwrap();
        assert!(meta.file_type().is_char_device(), "{meta:?}");
        assert!(!std::path::Path::new(&path("null.partial")).exists());
    }
    std::os::unix::fs::symlink(path("decoded.f32"), path("decoded-link")).unwrap();
    let d = run(&["decompress", &bricked, "-o", &path("decoded-link")]);
    assert!(d.status.success(), "{}", err(&d));
    let meta = std::fs::symlink_metadata(path("decoded-link")).unwrap();
    assert!(meta.file_type().is_symlink());
    assert_eq!(
        std::fs::metadata(path("decoded.f32")).unwrap().len(),
        16 * 16 * 16 * 4
    );
}

/// Unfinished outputs that killed runs left beside the output are removed by the next run that
/// writes there; one a live run holds (locked) stays, and so does a fresh one.
#[test]
fn unfinished_outputs_of_killed_runs_are_removed() {
    let dir = tempfile::tempdir().unwrap();
    let path = |n: &str| dir.path().join(n).to_str().unwrap().to_string();
    let (raw, _) = phantom_files(dir.path());
    let old = |n: &str| {
        std::fs::write(path(n), b"half a file").unwrap();
        let t = std::time::SystemTime::now() - std::time::Duration::from_secs(3600);
        std::fs::File::options()
            .write(true)
            .open(path(n))
            .unwrap()
            .set_modified(t)
            .unwrap();
    };
    old(".wavesplat-killed.partial");
    old(".wavesplat-live.partial");
    let live = std::fs::File::open(path(".wavesplat-live.partial")).unwrap();
    live.lock().unwrap();
    std::fs::write(path(".wavesplat-fresh.partial"), b"just made").unwrap();
    old("unrelated.partial");
    let c = run(&[
        "compress",
        &raw,
        "--dims",
        "16,16,16",
        "--dtype",
        "f32",
        "-o",
        &path("out.wsp"),
    ]);
    assert!(c.status.success(), "{}", err(&c));
    assert!(
        out(&c).contains(".wavesplat-killed.partial, left by an interrupted run"),
        "{}",
        out(&c)
    );
    let exists = |n: &str| std::path::Path::new(&path(n)).exists();
    assert!(!exists(".wavesplat-killed.partial"));
    assert!(exists(".wavesplat-live.partial"));
    assert!(exists(".wavesplat-fresh.partial"));
    assert!(exists("unrelated.partial"));
    drop(live);
}

/// `compress` of the 16³ phantom of [`phantom_files`] in 8³ bricks with `flags`, into `dir`.
fn compress_bricked_phantom(dir: &std::path::Path, flags: &[&str]) -> std::process::Output {
    let (raw, _) = phantom_files(dir);
    let o = dir.join("b.wsp");
    let mut args = vec![
        "compress", &raw, "--dims", "16,16,16", "--dtype", "f32", "--brick", "8",
    ];
    args.extend_from_slice(flags);
    args.extend(["-o", o.to_str().unwrap()]);
    let c = run(&args);
    assert!(c.status.success(), "{}", err(&c));
    c
}

/// A bricked selection of every coefficient scores nothing and knows no totals: its summary
/// says what it kept without a share of nothing.
#[test]
fn a_bricked_lossless_selection_says_what_it_kept() {
    let dir = tempfile::tempdir().unwrap();
    let c = compress_bricked_phantom(dir.path(), &["--lossless-selection"]);
    assert!(
        out(&c).contains("coefficients (every non-zero one)"),
        "{}",
        out(&c)
    );
    assert!(!out(&c).contains(" of 0 coefficients"), "{}", out(&c));
}

/// Options a bricked volume does not apply are named in a warning, not silently dropped.
#[test]
fn options_a_bricked_volume_ignores_are_named() {
    let dir = tempfile::tempdir().unwrap();
    let c = compress_bricked_phantom(dir.path(), &["--margin", "0", "--no-coarse-layer"]);
    let warned = "--margin, --no-coarse-layer not applied to a bricked volume";
    assert!(err(&c).contains(warned), "{}", err(&c));
}

/// A bricked compression of samples that cannot be (NaN) says so once, names no brick it did
/// not read, and leaves no checkpoint nor a hint to run again (it could not succeed).
#[test]
fn a_bricked_volume_with_nan_is_refused_once_without_a_checkpoint() {
    let dir = tempfile::tempdir().unwrap();
    let raw = dir.path().join("nan.raw");
    let mut samples = vec![1f32; 20 * 20 * 20];
    samples[10 + 20 * 10 + 400 * 11] = f32::NAN;
    std::fs::write(
        &raw,
        samples
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect::<Vec<u8>>(),
    )
    .unwrap();
    let o = dir.path().join("n.wsp");
    let c = run(&[
        "compress",
        raw.to_str().unwrap(),
        "--dims",
        "20,20,20",
        "--dtype",
        "f32",
        "--brick",
        "8",
        "-o",
        o.to_str().unwrap(),
    ]);
    assert!(!c.status.success());
    let e = err(&c);
    assert_eq!(
        e.matches("non-finite sample (NaN) at voxel (10, 10, 11)")
            .count(),
        1,
        "{e}"
    );
    assert!(!e.contains("run the same command again"), "{e}");
    assert!(!dir.path().join("n.wsp.checkpoint").exists());
    assert!(!o.exists());
}

/// A time point of a bricked volume that is no series is refused, as of a plain volume.
#[test]
fn a_time_point_of_a_bricked_volume_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    compress_bricked_phantom(dir.path(), &[]);
    let b = dir.path().join("b.wsp");
    let png = dir.path().join("t.png");
    let r = run(&[
        "render",
        b.to_str().unwrap(),
        "--cpu",
        "--size",
        "16x16",
        "--time-point",
        "5",
        "-o",
        png.to_str().unwrap(),
    ]);
    assert!(!r.status.success());
    assert!(err(&r).contains("apply to a time series"), "{}", err(&r));
}

/// A slice in bricks keeps every non-zero voxel by default, as a slice compressed whole does
/// (it kept the default 5 %: the brightest pixels only).
#[test]
fn a_bricked_slice_keeps_every_voxel_by_default() {
    let dir = tempfile::tempdir().unwrap();
    let raw = dir.path().join("slice.f32");
    let o = dir.path().join("s.wsp");
    assert!(run(&[
        "phantom",
        "shepp-logan",
        "--dims",
        "1,40,30",
        "-o",
        raw.to_str().unwrap()
    ])
    .status
    .success());
    let c = run(&[
        "compress",
        raw.to_str().unwrap(),
        "--dims",
        "1,40,30",
        "--dtype",
        "f32",
        "--brick",
        "8",
        "-o",
        o.to_str().unwrap(),
    ]);
    assert!(c.status.success(), "{}", err(&c));
    assert!(err(&c).contains("one voxel thin"), "{}", err(&c));
    assert!(out(&c).contains("(every non-zero one)"), "{}", out(&c));
}

/// The coefficients `info --packets` lists, summed per brick (a bricked file) and over the
/// components (a time series), against the counts the file's manifest gives.
#[test]
fn info_lists_the_packets_of_bricks_and_of_a_series_components() {
    let dir = tempfile::tempdir().unwrap();
    let path = |n: &str| dir.path().join(n).to_str().unwrap().to_string();
    let packet_coefficients = |line: &str| -> Option<u64> {
        let words: Vec<&str> = line.split_whitespace().collect();
        let at = words.iter().position(|w| *w == "coefficients")?;
        (words.first() == Some(&"packet")).then(|| words[at - 1].parse().unwrap())
    };
    let c = run(&[
        "compress",
        "--phantom",
        "ct",
        "--dims",
        "48,40,36",
        "--brick",
        "32",
        "--target-coefficients",
        "3000",
        "-o",
        &path("b.wsp"),
    ]);
    assert!(c.status.success(), "{}", err(&c));
    let info = run(&["info", &path("b.wsp"), "--packets"]);
    assert!(info.status.success(), "{}", err(&info));
    // Each brick's line, then its packets: their counts sum to the brick's.
    let (mut bricks, mut total) = (0, 0u64);
    let mut current: Option<(u64, u64)> = None;
    let check = |current: Option<(u64, u64)>| {
        if let Some((kept, listed)) = current {
            assert_eq!(listed, kept, "{}", out(&info));
        }
    };
    for line in out(&info).lines() {
        let t = line.trim_start();
        if t.starts_with("brick ") && t.ends_with(" coefficients") {
            check(current.take());
            let kept = t.split_whitespace().rev().nth(1).unwrap().parse().unwrap();
            current = Some((kept, 0));
            bricks += 1;
            total += kept;
        } else if let Some(n) = packet_coefficients(t) {
            current.as_mut().expect("a packet under a brick").1 += n;
        }
    }
    check(current);
    assert_eq!(bricks, 8, "{}", out(&info));
    // The count after the last comma of `info`'s line starting with `label`.
    let kept_on = |text: &str, label: &str| -> u64 {
        text.lines()
            .find(|l| l.starts_with(label))
            .and_then(|l| {
                l.split(", ")
                    .last()?
                    .split_whitespace()
                    .next()?
                    .parse()
                    .ok()
            })
            .unwrap_or_else(|| panic!("{text}"))
    };
    let kept = kept_on(&out(&info), "bricks ");
    assert_eq!(total, kept, "{}", out(&info));
    assert_eq!(kept, 3000, "{}", out(&info));

    let s = run(&[
        "compress",
        "--phantom",
        "beating",
        "--dims",
        "24,24,12,4",
        "-o",
        &path("s.wsp"),
    ]);
    assert!(s.status.success(), "{}", err(&s));
    let plain = run(&["info", &path("s.wsp")]);
    let kept = kept_on(&out(&plain), "components");
    let info = run(&["info", &path("s.wsp"), "--packets"]);
    assert!(info.status.success(), "{}", err(&info));
    let listed: u64 = out(&info)
        .lines()
        .filter_map(|l| packet_coefficients(l.trim_start()))
        .sum();
    assert_eq!(listed, kept, "{}", out(&info));
    assert_eq!(
        out(&info).matches("component c").count(),
        4,
        "{}",
        out(&info)
    );
}
