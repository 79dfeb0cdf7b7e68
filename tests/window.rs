//! `wavesplat view` in a real window under a virtual X server (Xvfb): it opens, renders,
//! reacts to a synthetic drag and keys (its `--script` feeds them through the same handlers as
//! real events), what reaches the screen (an ImageMagick `import` of the root window) shows the
//! volume, and it closes cleanly. Without Xvfb, or without a graphics driver for the window
//! (Mesa's Vulkan driver), these tests skip with a printed reason, unless
//! `WAVESPLAT_REQUIRE_GPU=1` (CI sets it, and `.ci/run` installs both): then they fail.

mod common;

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};
use wavesplat_compressor::encode::CompressOptions;
use wavesplat_compressor::phantom::Phantom;

const BIN: &str = env!("CARGO_BIN_EXE_wavesplat");

fn required() -> bool {
    std::env::var("WAVESPLAT_REQUIRE_GPU").as_deref() == Ok("1")
}

/// Skips (prints why and returns true) or, when required, fails.
fn skip(reason: &str) -> bool {
    if required() {
        panic!("WAVESPLAT_REQUIRE_GPU=1 but {reason}");
    }
    eprintln!("skipped: {reason} (set WAVESPLAT_REQUIRE_GPU=1 to fail instead)");
    true
}

fn on_path(tool: &str) -> bool {
    std::env::var_os("PATH")
        .is_some_and(|p| std::env::split_paths(&p).any(|d| d.join(tool).is_file()))
}

/// A private Xvfb server, stopped on drop.
struct Xvfb {
    child: Child,
    display: String,
}

impl Drop for Xvfb {
    fn drop(&mut self) {
        // SIGTERM, so that the server removes its lock file and socket (after SIGKILL they
        // stay behind, and a later server must tell them from live ones).
        let pid = rustix::process::Pid::from_child(&self.child);
        let _ = rustix::process::kill_process(pid, rustix::process::Signal::TERM);
        let deadline = Instant::now() + Duration::from_secs(5);
        while matches!(self.child.try_wait(), Ok(None)) && Instant::now() < deadline {
            std::thread::sleep(Duration::from_millis(20));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Xvfb {
    /// Starts Xvfb on a display number it picks itself (`-displayfd`): the server takes the
    /// first number whose lock file it can create, and writes it once it accepts connections.
    /// Choosing the number here instead raced with the tests running beside this one (two
    /// servers started for one number, one exits, and its test draws on the other's server
    /// until that test ends: "XIO: fatal IO error 11").
    fn start() -> Option<Xvfb> {
        if !on_path("Xvfb") {
            return None;
        }
        let mut child = Command::new("Xvfb")
            .args([
                "-displayfd",
                "1",
                "-screen",
                "0",
                "1024x768x24",
                "-nolisten",
                "tcp",
            ])
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .ok()?;
        let stdout = child.stdout.take()?;
        let (sender, receiver) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            use std::io::BufRead;
            let mut line = String::new();
            let _ = std::io::BufReader::new(stdout).read_line(&mut line);
            let _ = sender.send(line);
        });
        let display = receiver
            .recv_timeout(Duration::from_secs(20))
            .ok()
            .and_then(|line| line.trim().parse::<u32>().ok());
        let Some(n) = display else {
            let _ = child.kill();
            let _ = child.wait();
            return None;
        };
        Some(Xvfb {
            child,
            display: format!(":{n}"),
        })
    }
}

fn wsp(phantom: Phantom, dims: [usize; 3]) -> Vec<u8> {
    let options = CompressOptions {
        layers: Some(3),
        ..common::phantom_options(0.1)
    };
    common::phantom_file(phantom, dims, &options)
}

/// A PNG as 8-bit grey levels (the mean of R, G and B), with its size.
fn grey(path: &Path) -> (usize, usize, Vec<f64>) {
    let mut decoder =
        png::Decoder::new(std::fs::File::open(path).unwrap_or_else(|e| panic!("{path:?}: {e}")));
    decoder.set_transformations(png::Transformations::EXPAND | png::Transformations::STRIP_16);
    let mut reader = decoder.read_info().unwrap();
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).unwrap();
    let channels = info.color_type.samples();
    let (w, h) = (info.width as usize, info.height as usize);
    let data = buf[..info.buffer_size()]
        .chunks(channels)
        .map(|px| match channels {
            1 | 2 => px[0] as f64,
            _ => (px[0] as f64 + px[1] as f64 + px[2] as f64) / 3.0,
        })
        .collect();
    (w, h, data)
}

/// Mean and variance of the `w`×`h` region at the top left of an image of width `stride`.
fn stats(data: &[f64], stride: usize, w: usize, h: usize) -> (f64, f64) {
    let v: Vec<f64> = (0..h)
        .flat_map(|y| data[y * stride..y * stride + w].iter().copied())
        .collect();
    let n = v.len() as f64;
    let mean = v.iter().sum::<f64>() / n;
    (
        mean,
        v.iter().map(|x| (x - mean) * (x - mean)).sum::<f64>() / n,
    )
}

/// The standard output of a `view` that exited successfully with its view converged.
fn converged_output(child: Child) -> String {
    let (status, stdout, stderr) = finish(child);
    assert!(
        status.success(),
        "exit {status}\nstdout {stdout}\nstderr {stderr}"
    );
    assert!(stdout.contains(", converged"), "{stdout}");
    stdout
}

/// The first line of `text` that contains `needle`.
fn line_with<'a>(text: &'a str, needle: &str) -> &'a str {
    text.lines()
        .find(|l| l.contains(needle))
        .unwrap_or_else(|| panic!("no line with {needle:?} in {text}"))
}

fn wait_for(path: &Path, child: &mut Child, what: &str) {
    let deadline = Instant::now() + Duration::from_secs(180);
    while !path.exists() {
        if let Ok(Some(status)) = child.try_wait() {
            let mut err = String::new();
            if let Some(mut e) = child.stderr.take() {
                let _ = std::io::Read::read_to_string(&mut e, &mut err);
            }
            panic!("wavesplat view exited ({status}) before {what}: {err}");
        }
        if Instant::now() > deadline {
            let _ = child.kill();
            panic!("wavesplat view did not reach {what}");
        }
        std::thread::sleep(Duration::from_millis(50));
    }
}

fn finish(mut child: Child) -> (std::process::ExitStatus, String, String) {
    let deadline = Instant::now() + Duration::from_secs(180);
    loop {
        if let Ok(Some(_)) = child.try_wait() {
            break;
        }
        if Instant::now() > deadline {
            let _ = child.kill();
            break;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    let o = child.wait_with_output().unwrap();
    (
        o.status,
        String::from_utf8_lossy(&o.stdout).into_owned(),
        String::from_utf8_lossy(&o.stderr).into_owned(),
    )
}

/// A private Xvfb on which a wgpu surface can be made, or `None` after [`skip`]ping with the
/// reason: no Xvfb, or no graphics driver for the window (Xvfb without Mesa's Vulkan driver
/// fails at "creating a wgpu surface").
fn display_for_window() -> Option<Xvfb> {
    let Some(x) = Xvfb::start() else {
        skip("no Xvfb to open a window on");
        return None;
    };
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("probe.wsp");
    std::fs::write(&file, wsp(Phantom::SheppLogan, [8, 8, 8])).unwrap();
    let child = spawn_view(&x.display, &file, "16x16", &["--exit-after-frames", "1"]);
    let (status, _, err) = finish(child);
    if !status.success() && (err.contains("wgpu surface") || err.contains("adapter")) {
        let reason = err.lines().last().unwrap_or("").to_string();
        skip(&format!(
            "no graphics driver for a window on Xvfb ({reason}); apt-get install \
             mesa-vulkan-drivers"
        ));
        return None;
    }
    Some(x)
}

/// `view FILE --size SIZE ARGS…` on `display`, started.
fn spawn_view(display: &str, file: &Path, size: &str, args: &[&str]) -> Child {
    let mut all = vec![file.to_str().unwrap(), "--size", size];
    all.extend_from_slice(args);
    view(display, &all).spawn().unwrap()
}

fn view(display: &str, args: &[&str]) -> Command {
    let mut c = Command::new(BIN);
    c.arg("view")
        .args(args)
        .env("DISPLAY", display)
        .env(
            "WGPU_BACKEND",
            std::env::var("WGPU_BACKEND").unwrap_or("vulkan".into()),
        )
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    c
}

#[test]
fn the_window_renders_turns_under_a_drag_and_closes_cleanly() {
    let Some(x) = display_for_window() else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("head.wsp");
    std::fs::write(&file, wsp(Phantom::SheppLogan, [40, 32, 24])).unwrap();
    let p = |name: &str| -> PathBuf { dir.path().join(name) };
    let s = |name: &str| p(name).to_str().unwrap().to_string();
    let script = format!(
        "converge; screenshot {}; signal {}; await {}; drag 40,60 130,80; converge; \
         screenshot {}; key c; converge; screenshot {}; key m; converge; screenshot {}; wheel 3;          frames 3; key r; converge; screenshot {}; resize 200x100; converge; quit",
        s("a.png"),
        s("shown"),
        s("go"),
        s("b.png"),
        s("cue.png"),
        s("c.png"),
        s("r.png"),
    );
    let child = spawn_view(
        &x.display,
        &file,
        "160x120",
        &["--script", &script, "--screenshot", &s("final.png")],
    );
    let mut child = child;
    wait_for(&p("shown"), &mut child, "its first converged image");
    // What the X server shows: the window sits at the top left of the root window (no window
    // manager), so its region of a root screenshot must look like the image it drew.
    let root = if on_path("import") {
        let o = Command::new("import")
            .args(["-display", &x.display, "-window", "root"])
            .arg(p("root.png"))
            .output()
            .unwrap();
        assert!(
            o.status.success(),
            "import: {}",
            String::from_utf8_lossy(&o.stderr)
        );
        Some(grey(&p("root.png")))
    } else {
        if required() {
            let _ = child.kill();
            panic!("WAVESPLAT_REQUIRE_GPU=1 but ImageMagick's import is missing");
        }
        eprintln!("no ImageMagick import: the screen itself is not checked");
        None
    };
    std::fs::write(p("go"), b"").unwrap();
    let (status, stdout, stderr) = finish(child);
    assert!(
        status.success(),
        "exit {status}\nstdout {stdout}\nstderr {stderr}"
    );
    assert!(stdout.contains("converged"), "{stdout}");

    let (aw, ah, a) = grey(&p("a.png"));
    assert_eq!((aw, ah), (160, 120), "the image follows the window");
    let (mean_a, var_a) = stats(&a, aw, aw, ah);
    assert!(
        var_a > 100.0,
        "the first image shows no volume: variance {var_a}"
    );
    let (bw, bh, b) = grey(&p("b.png"));
    assert_eq!((bw, bh), (aw, ah));
    let (_, var_b) = stats(&b, bw, bw, bh);
    assert!(var_b > 100.0, "after the drag: variance {var_b}");
    let diff = a.iter().zip(&b).map(|(x, y)| (x - y).abs()).sum::<f64>() / a.len() as f64;
    assert!(
        diff > 4.0,
        "the drag did not turn the volume: mean |a-b| = {diff}"
    );
    // Multiview in a 160×120 window: three 80×60 panels in a 2×2 grid (a row of three would
    // give each view a 53-pixel width), the fourth cell empty.
    let (cw, ch, c) = grey(&p("c.png"));
    assert_eq!((cw, ch), (160, 120), "multiview layout {cw}x{ch}");
    let quadrant = |qx: usize, qy: usize| -> Vec<f64> {
        (0..60)
            .flat_map(|y| (0..80).map(move |x| (qy * 60 + y) * 160 + qx * 80 + x))
            .map(|i| c[i])
            .collect()
    };
    for (qx, qy) in [(0, 0), (1, 0), (0, 1)] {
        let q = quadrant(qx, qy);
        assert!(
            stats(&q, 80, 80, 60).1 > 100.0,
            "panel ({qx}, {qy}) is empty"
        );
    }
    // The empty cell holds no image: flat (the level of zero under the panels' window).
    assert!(
        stats(&quadrant(1, 1), 80, 80, 60).1 < 1.0,
        "the empty cell is not flat"
    );
    // Depth cueing (C) changes the image of the same view.
    let (dw, dh, d) = grey(&p("cue.png"));
    assert_eq!((dw, dh), (bw, bh));
    let cued = b.iter().zip(&d).map(|(x, y)| (x - y).abs()).sum::<f64>() / b.len() as f64;
    assert!(cued > 1.0, "C did not cue: mean |b-cue| = {cued}");
    // Reset: back to the first view and layout.
    let (rw, rh, r) = grey(&p("r.png"));
    assert_eq!((rw, rh), (aw, ah));
    let back = a.iter().zip(&r).map(|(x, y)| (x - y).abs()).sum::<f64>() / a.len() as f64;
    assert!(
        back < 1.0,
        "R did not restore the first view: mean |a-r| = {back}"
    );
    // The image follows a resize; the last image is written at exit.
    let (fw, fh, f) = grey(&p("final.png"));
    assert_eq!((fw, fh), (200, 100));
    assert!(stats(&f, fw, fw, fh).1 > 100.0);

    if let Some((rw, rh, r)) = root {
        assert!(rw >= aw && rh >= ah, "root {rw}x{rh}");
        let (mean_r, var_r) = stats(&r, rw, aw, ah);
        assert!(
            var_r > 100.0,
            "the screen shows no volume: variance {var_r}"
        );
        assert!(
            (mean_r - mean_a).abs() < 8.0 && (var_r / var_a - 1.0).abs() < 0.2,
            "the screen ({mean_r:.1}, {var_r:.0}) differs from the image ({mean_a:.1}, {var_a:.0})"
        );
    }
}

/// At a workstation's window size on the CPU backend, a resting view gets the frame: the
/// 96³ phantom at 800×600 converges with most of the time spent refining (where showing a
/// large image on a software device left each 16.6 ms frame about a millisecond of splatting,
/// and convergence took ~90 s), and the window says how it got there.
#[test]
fn a_resting_window_at_800x600_gives_refinement_the_frame() {
    let Some(x) = display_for_window() else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("phantom.wsp");
    std::fs::write(&file, wsp(Phantom::SheppLogan, [96, 96, 72])).unwrap();
    let child = spawn_view(
        &x.display,
        &file,
        "800x600",
        &["--cpu", "--script", "converge; quit"],
    );
    let stdout = converged_output(child);
    // "view: the last view converged 1.23 s after it changed, 87 % of that refining, 9 images shown"
    let line = line_with(&stdout, "the last view converged");
    let number_before = |word: &str| -> f64 {
        let head = &line[..line
            .find(word)
            .unwrap_or_else(|| panic!("{word} in {line}"))];
        head.split_whitespace()
            .last()
            .and_then(|w| w.parse().ok())
            .unwrap_or_else(|| panic!("a number before {word} in {line}"))
    };
    let share = number_before("% of that refining");
    let shown = number_before("images shown");
    assert!(
        share >= 50.0,
        "refinement had only {share} % of the time to convergence: {line}"
    );
    assert!(shown >= 1.0, "{line}");
}

/// A drag on the CPU backend draws each of its views smaller (`--drag-max-image`), shown
/// stretched to the window, and the view it ends on is drawn at the window's size again and
/// converges: every frame of a drag is a new view, and a full-size one took 200 ms a frame at
/// 1920×1080 (the frame times are figures, in BENCHMARKS.md, not asserted here).
#[test]
fn a_drag_draws_smaller_images_and_the_view_it_ends_on_converges_at_full_size() {
    let Some(x) = display_for_window() else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("phantom.wsp");
    std::fs::write(&file, wsp(Phantom::SheppLogan, [64, 64, 48])).unwrap();
    let shot = dir.path().join("end.png");
    let script = format!(
        "converge; drag 200,150 500,300 over 12; converge; screenshot {}; quit",
        shot.display()
    );
    let child = spawn_view(
        &x.display,
        &file,
        "800x600",
        &["--cpu", "--drag-max-image", "200", "--script", &script],
    );
    let stdout = converged_output(child);
    // "view: 12 frames while dragging, images up to 200x150, frame time median …"
    let line = line_with(&stdout, "frames while dragging");
    let words: Vec<&str> = line.split_whitespace().collect();
    let frames: u64 = words[1].parse().unwrap_or_else(|_| panic!("{line}"));
    assert!(frames >= 12, "one frame a move: {line}");
    let size = words
        .iter()
        .position(|w| *w == "to")
        .and_then(|i| words.get(i + 1))
        .map(|w| w.trim_end_matches(','))
        .unwrap_or_else(|| panic!("{line}"));
    let (w, h) = size.split_once('x').unwrap_or_else(|| panic!("{line}"));
    let (w, h): (usize, usize) = (w.parse().unwrap(), h.parse().unwrap());
    assert!(
        w.max(h) <= 200 && w * 3 == h * 4,
        "dragged images keep the window's shape within 200 px: {line}"
    );
    let (sw, sh, end) = grey(&shot);
    assert_eq!((sw, sh), (800, 600), "the view it ended on, at full size");
    assert!(stats(&end, sw, sw, sh).1 > 10.0, "no volume at the end");
}

/// A bricked volume in the window at 800×600 on the CPU: its bricks are drawn as one image, in
/// a single view and, after M, in multiview (three 400×300 panels in a 2×2 grid, each showing
/// the volume), and the view converges after a drag.
#[test]
fn a_bricked_volume_converges_in_the_window_in_single_and_multiview() {
    let Some(x) = display_for_window() else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("bricked.wsp");
    let volume = Phantom::SheppLogan.generate([64, 64, 48]);
    let bricked = wavesplat_compressor::bricked::compress_bricked(
        &volume,
        &common::phantom_options(0.05),
        32,
        &|_| {},
    )
    .unwrap();
    assert_eq!(bricked.manifest.bricks.len(), 8);
    std::fs::write(&file, &bricked.bytes).unwrap();
    let (single, multi) = (dir.path().join("single.png"), dir.path().join("multi.png"));
    let script = format!(
        "converge; screenshot {}; key m; converge; drag 200,150 400,250 over 6; converge; \
         screenshot {}; quit",
        single.display(),
        multi.display()
    );
    let child = spawn_view(
        &x.display,
        &file,
        "800x600",
        &["--cpu", "--script", &script],
    );
    let (status, stdout, stderr) = finish(child);
    assert!(
        status.success(),
        "exit {status}\nstdout {stdout}\nstderr {stderr}"
    );
    assert!(stdout.contains("converged"), "{stdout}");
    assert!(line_with(&stdout, "the last view converged").contains("images shown"));
    let (w, h, img) = grey(&single);
    assert_eq!((w, h), (800, 600), "a single view at the window's size");
    assert!(stats(&img, w, w, h).1 > 10.0, "no volume in {single:?}");
    let (w, h, img) = grey(&multi);
    assert_eq!((w, h), (800, 600), "multiview at the window's size");
    let panel = |qx: usize, qy: usize| -> Vec<f64> {
        (0..300)
            .flat_map(|y| (0..400).map(move |x| (qy * 300 + y) * 800 + qx * 400 + x))
            .map(|i| img[i])
            .collect()
    };
    for (qx, qy) in [(0, 0), (1, 0), (0, 1)] {
        let var = stats(&panel(qx, qy), 400, 400, 300).1;
        assert!(
            var > 10.0,
            "multiview panel ({qx}, {qy}) is empty: variance {var}"
        );
    }
}

#[test]
fn the_window_closes_after_a_set_number_of_frames_and_refuses_cueing_in_multiview() {
    let Some(x) = display_for_window() else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("rgb.wsp");
    std::fs::write(&file, wsp(Phantom::RgbHead, [24, 24, 17])).unwrap();
    let shot = dir.path().join("last.png");
    let child = spawn_view(
        &x.display,
        &file,
        "64x48",
        &[
            "--multiview",
            "--script",
            "key c; key ]",
            "--frame-ms",
            "8",
            "--exit-after-frames",
            "12",
            "--screenshot",
            shot.to_str().unwrap(),
        ],
    );
    let (status, stdout, stderr) = finish(child);
    assert!(
        status.success(),
        "exit {status}\nstdout {stdout}\nstderr {stderr}"
    );
    assert!(stdout.contains("12 frames drawn"), "{stdout}");
    assert!(
        stderr.contains("does not combine with multiview"),
        "{stderr}"
    );
    let (w, h, img) = grey(&shot);
    assert_eq!((w, h), (3 * 64, 48));
    assert!(stats(&img, w, w, h).1 > 10.0, "no volume in {shot:?}");
}

#[test]
fn without_a_display_the_window_fails_with_a_reason() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("s.wsp");
    std::fs::write(&file, wsp(Phantom::Spheres, [16, 16, 16])).unwrap();
    let o = Command::new(BIN)
        .arg("view")
        .arg(&file)
        .env_remove("DISPLAY")
        .env_remove("WAYLAND_DISPLAY")
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(1));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("error: opening the display"), "{err}");
    assert!(!err.contains("panicked"), "{err}");
}

/// A lost graphics device (destroyed by the script, as a driver reset would lose it): the
/// window recreates its context, the session draws what it holds again, and the image comes
/// back the same — with the CPU backend (only the display is recreated) and with the GPU one
/// (the accumulation too).
#[test]
fn the_window_recovers_from_a_lost_graphics_device() {
    let Some(x) = display_for_window() else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("head.wsp");
    std::fs::write(&file, wsp(Phantom::SheppLogan, [24, 20, 16])).unwrap();
    for backend in ["--cpu", "--gpu"] {
        let p = |name: &str| -> PathBuf { dir.path().join(format!("{backend}-{name}")) };
        let s = |name: &str| p(name).to_str().unwrap().to_string();
        let script = format!(
            "converge; screenshot {}; lose-device; frames 3; converge; screenshot {}; quit",
            s("before.png"),
            s("after.png"),
        );
        let child = view(
            &x.display,
            &[
                file.to_str().unwrap(),
                backend,
                "--size",
                "96x80",
                "--script",
                &script,
            ],
        )
        .spawn()
        .unwrap();
        let (status, stdout, stderr) = finish(child);
        assert!(
            status.success(),
            "{backend}: exit {status}\nstdout {stdout}\nstderr {stderr}"
        );
        assert!(
            stderr.contains("graphics device lost") && stderr.contains("recovered"),
            "{backend}: {stderr}"
        );
        assert!(
            !stderr.contains("cannot be reopened"),
            "{backend}: fell back to the CPU: {stderr}"
        );
        let (w, h, a) = grey(&p("before.png"));
        let (w2, h2, b) = grey(&p("after.png"));
        assert_eq!((w, h), (w2, h2));
        let (_, var_b) = stats(&b, w, w, h);
        assert!(var_b > 100.0, "{backend}: no volume after the recovery");
        let diff = a.iter().zip(&b).map(|(x, y)| (x - y).abs()).sum::<f64>() / a.len() as f64;
        assert!(
            diff < 1.0,
            "{backend}: the image changed across the recovery: mean |a-b| = {diff}"
        );
    }
}

/// With the GPU backend the window shows the image the display pass made on the device (no
/// image crosses the bus): what the X server shows is, pixel for pixel, the screenshot the
/// host makes of the same state (the session's image, the 2×2 multiview grid, the window
/// narrowed by the contrast key), as it is with the CPU backend, whose image is uploaded. (This
/// multiview's atlas, 135 MB, is larger than lavapipe binds at once: it is read in windows.)
#[test]
fn the_screen_shows_the_device_image_of_the_gpu_backend() {
    let Some(x) = display_for_window() else {
        return;
    };
    if !on_path("import") {
        assert!(
            !required(),
            "WAVESPLAT_REQUIRE_GPU=1 but ImageMagick's import is missing"
        );
        eprintln!("skipped: no ImageMagick import to read the screen");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("ct.wsp");
    std::fs::write(&file, wsp(Phantom::Ct, [40, 32, 24])).unwrap();
    for (backend, shown_by) in [
        ("--gpu", "made there by the display pass"),
        ("--cpu", "from the host"),
    ] {
        let p = |name: &str| -> PathBuf { dir.path().join(format!("{backend}-{name}")) };
        let s = |name: &str| p(name).to_str().unwrap().to_string();
        let script = format!(
            "key m; key 1; converge; frames 3; screenshot {}; signal {}; await {}; quit",
            s("shot.png"),
            s("shown"),
            s("go"),
        );
        let mut child = view(
            &x.display,
            &[
                file.to_str().unwrap(),
                backend,
                "--size",
                "160x120",
                "--script",
                &script,
            ],
        )
        .spawn()
        .unwrap();
        wait_for(&p("shown"), &mut child, "its converged image");
        let o = Command::new("import")
            .args(["-display", &x.display, "-window", "root"])
            .arg(p("root.png"))
            .output()
            .unwrap();
        std::fs::write(p("go"), b"").unwrap();
        let (status, stdout, stderr) = finish(child);
        assert!(
            o.status.success(),
            "import: {}",
            String::from_utf8_lossy(&o.stderr)
        );
        assert!(
            status.success(),
            "{backend}: exit {status}\nstdout {stdout}\nstderr {stderr}"
        );
        assert!(stderr.contains(shown_by), "{backend}: {stderr}");
        let (w, h, shot) = grey(&p("shot.png"));
        assert_eq!(
            (w, h),
            (160, 120),
            "{backend}: multiview 2x2 of 80x60 panels"
        );
        assert!(stats(&shot, w, w, h).1 > 100.0, "{backend}: no volume");
        let (rw, _, root) = grey(&p("root.png"));
        let mut worst = 0.0f64;
        let mut total = 0.0;
        for y in 0..h {
            for x in 0..w {
                let d = (root[y * rw + x] - shot[y * w + x]).abs();
                worst = worst.max(d);
                total += d;
            }
        }
        let mean = total / (w * h) as f64;
        eprintln!("{backend}: screen vs screenshot: max {worst}, mean {mean:.3}");
        assert!(
            worst <= 1.0 && mean < 0.05,
            "{backend}: the screen differs from the screenshot: max {worst}, mean {mean}"
        );
    }
}

/// A time series plays in the window: space starts it, every time point it moves to is drawn
/// (and shown converged before it moves on, at this size), a time point drawn before in the
/// same view is shown again from its kept image, the arrows step while paused; the screenshot
/// of a paused time point (kept or drawn) is that time point's `render` image.
#[test]
fn a_time_series_plays_steps_and_pauses_in_the_window() {
    let Some(x) = display_for_window() else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("cine.wsp");
    let out = Command::new(BIN)
        .args([
            "compress",
            "--phantom",
            "beating",
            "--dims",
            "32,32,12,8",
            "--target-fraction",
            "0.1",
            "-o",
        ])
        .arg(&file)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", common::text(&out));
    let shot = dir.path().join("paused.png");
    // After R (the view reset, the same view): the session itself draws the time point shown.
    let drawn = dir.path().join("reset.png");
    let script = format!(
        "converge; key space; played 10; key space; key right; key right; converge; screenshot {}; \
         key r; converge; screenshot {}; quit",
        shot.display(),
        drawn.display()
    );
    let child = spawn_view(
        &x.display,
        &file,
        "128x128",
        &[
            "--cpu",
            "--fps",
            "40",
            "--time-point",
            "1",
            "--script",
            &script,
        ],
    );
    let (status, stdout, stderr) = finish(child);
    assert!(
        status.success(),
        "exit {status}\nstdout {stdout}\nstderr {stderr}"
    );
    let played = line_with(&stdout, "view: played");
    let n: u64 = played
        .split_whitespace()
        .nth(2)
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("{played}"));
    assert!(n >= 10, "{played}");
    let converged: u64 = played
        .split(", ")
        .last()
        .and_then(|s| s.split_whitespace().next())
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("{played}"));
    assert!(
        converged >= 9,
        "most time points are left converged: {played}"
    );
    // After the first loop (8 time points) the time points come back in the same view: shown
    // from their kept images.
    let kept = line_with(&stdout, "drawn before in this view");
    let k: u64 = kept
        .split_whitespace()
        .nth(1)
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("{kept}"));
    assert!(k >= 2, "{kept}");
    // Paused after 10 moves from time point 1, then two steps on: time point 13 mod 8 = 5.
    let rendered = dir.path().join("t5.png");
    let out = Command::new(BIN)
        .args([
            "render",
            "--time-point",
            "5",
            "--size",
            "128x128",
            "--cpu",
            "-o",
        ])
        .arg(&rendered)
        .arg(&file)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", common::text(&out));
    let (_, _, want) = grey(&rendered);
    for path in [&shot, &drawn] {
        let (w, h, shown) = grey(path);
        assert_eq!((w, h), (128, 128));
        let diff = shown
            .iter()
            .zip(&want)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        assert!(
            diff <= 2.0,
            "{path:?}: the paused time point is time point 5's image: {diff}"
        );
    }
}

/// The beating phantom (32×32×12, six time points, 10 %, groups of `group`) compressed into
/// `dir/cine.wsp`.
fn beating_cine(dir: &Path, group: &str) -> std::path::PathBuf {
    let file = dir.join("cine.wsp");
    let out = Command::new(BIN)
        .args([
            "compress",
            "--phantom",
            "beating",
            "--dims",
            "32,32,12,6",
            "--target-fraction",
            "0.1",
            "--time-group",
            group,
            "-o",
        ])
        .arg(&file)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", common::text(&out));
    file
}

/// `cache ingest FILE --name cine` into the cache at `url`.
fn ingest_cine(file: &Path, url: &str) {
    let out = Command::new(BIN)
        .args(["cache", "ingest"])
        .arg(file)
        .args(["--name", "cine", "--cache", url])
        .env_remove("WAVESPLAT_CA")
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", common::text(&out));
}

/// The first number on the line of `stdout` that contains `needle`, the `nth` word.
fn count_on(stdout: &str, needle: &str, nth: usize) -> u64 {
    let line = line_with(stdout, needle);
    line.split_whitespace()
        .nth(nth)
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("{line}"))
}

/// Asserts the 96² screenshot `shot` is time point `t`'s `render` image of `file` (within two
/// grey levels).
fn shows_time_point(shot: &Path, file: &Path, t: usize) {
    let rendered = shot.with_file_name(format!("t{t}.png"));
    let out = Command::new(BIN)
        .args([
            "render",
            "--time-point",
            &t.to_string(),
            "--size",
            "96x96",
            "--cpu",
            "-o",
        ])
        .arg(&rendered)
        .arg(file)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", common::text(&out));
    let (_, _, want) = grey(&rendered);
    let (w, h, shown) = grey(shot);
    assert_eq!((w, h), (96, 96));
    let diff = shown
        .iter()
        .zip(&want)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f64::max);
    assert!(
        diff <= 2.0,
        "the paused time point is time point {t}'s image: {diff}"
    );
}

/// A time series in a cache node plays in the window as its file does: each time point a
/// stream of its own components' packets, opened ahead while the one before rests (at one time
/// point per second); the screenshot of a paused time point is that time point's `render`
/// image of the file.
#[test]
fn a_time_series_plays_from_a_cache_in_the_window() {
    let Some(x) = display_for_window() else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let file = beating_cine(dir.path(), "4");
    let server = wavesplat_harness::LocalCache::start(&dir.path().join("db")).unwrap();
    ingest_cine(&file, &server.url);
    plays_and_steps(
        &x.display,
        &["--cache", &server.url, "--volume", "cine"],
        dir.path(),
        &file,
    );
}

/// Plays the six-time-point `file`'s series from `source` in the window at one time point
/// per second (slow enough that each rests converged: the next is opened ahead), pauses after
/// 8 moves and steps once, and checks: played through, the first loop's moves (all but the
/// first time point's) went to time points opened ahead, and the screenshot of the time point
/// paused on (9 mod 6 = 3) is its `render` image of the file, drawn that way.
fn plays_and_steps(display: &str, source: &[&str], dir: &Path, file: &Path) {
    let shot = dir.join("paused.png");
    let script = format!(
        "converge; key space; played 8; key space; key right; converge; screenshot {}; quit",
        shot.display()
    );
    let mut args = source.to_vec();
    args.extend([
        "--size", "96x96", "--cpu", "--fps", "1", "--script", &script,
    ]);
    let child = view(display, &args)
        .env_remove("WAVESPLAT_CA")
        .spawn()
        .unwrap();
    let (status, stdout, stderr) = finish(child);
    assert!(
        status.success(),
        "exit {status}\nstdout {stdout}\nstderr {stderr}"
    );
    assert!(count_on(&stdout, "view: played", 2) >= 8, "{stdout}");
    assert!(count_on(&stdout, "opened ahead", 1) >= 3, "{stdout}");
    shows_time_point(&shot, file, 3);
}

/// A time series plays on when the cache node it streams from is killed: two nodes over one
/// object store (`file://`), the window given both; paused after three moves (the time points
/// seen so far came from the first node), the first node is killed, and playing on opens the
/// time points not yet seen on the second. The loop is played through and the screenshot of
/// the time point paused on afterwards is that time point's `render` image of the file.
#[test]
fn a_time_series_plays_on_when_its_cache_node_is_killed() {
    let Some(x) = display_for_window() else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let path = |p: &str| dir.path().join(p).to_str().unwrap().to_string();
    let file = beating_cine(dir.path(), "2");
    let store = format!("file://{}", path("bucket"));
    let node = |db: &str| {
        let db = path(db);
        common::spawn_server(&[
            "serve",
            "cache",
            "--addr",
            "127.0.0.1:0",
            "--db",
            &db,
            "--store",
            &store,
        ])
    };
    let (mut first, first_url) = node("n1");
    let (mut second, second_url) = node("n2");
    ingest_cine(&file, &first_url);
    let (ready, go) = (dir.path().join("ready"), dir.path().join("go"));
    let shot = dir.path().join("paused.png");
    // Three moves from time point 0 (t1..t3 opened on the first node), paused; after the kill
    // on to nine moves in all (t4, t5 opened on the second node, then t0..t3 again), paused on
    // t3, one step on to t4.
    let script = format!(
        "converge; key space; played 3; key space; signal {}; await {}; key space; played 9; \
         key space; key right; converge; screenshot {}; quit",
        ready.display(),
        go.display(),
        shot.display()
    );
    let urls = format!("{first_url},{second_url}");
    let mut child = view(
        &x.display,
        &[
            "--cache", &urls, "--volume", "cine", "--size", "96x96", "--cpu", "--fps", "20",
            "--script", &script,
        ],
    )
    .env_remove("WAVESPLAT_CA")
    .spawn()
    .unwrap();
    let started = std::time::Instant::now();
    while !ready.exists() {
        if let Ok(Some(status)) = child.try_wait() {
            panic!("the window ended before playing: {status}");
        }
        assert!(
            started.elapsed().as_secs() < 120,
            "no pause after three moves"
        );
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    let _ = first.kill();
    let _ = first.wait();
    std::fs::write(&go, b"").unwrap();
    let (status, stdout, stderr) = finish(child);
    let _ = second.kill();
    let _ = second.wait();
    assert!(
        status.success(),
        "exit {status}\nstdout {stdout}\nstderr {stderr}"
    );
    assert!(count_on(&stdout, "view: played", 2) >= 9, "{stdout}");
    shows_time_point(&shot, &file, 4);
}

/// A published time series plays in the window from its URL (range requests to a plain web
/// server) as from its cache: each time point's components fetched when it is first shown or
/// opened ahead while the one before rests, and after the first loop nothing more is fetched;
/// the screenshot of a paused time point is that time point's `render` image of the file.
#[test]
fn a_published_time_series_plays_from_its_url_in_the_window() {
    let Some(x) = display_for_window() else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let file = beating_cine(dir.path(), "4");
    let published = dir.path().join("cine.wspx");
    let out = Command::new(BIN)
        .arg("publish")
        .arg(&file)
        .arg("-o")
        .arg(&published)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", common::text(&out));
    let server = common::http::TinyServer::start(
        vec![("/cine.wspx", std::fs::read(&published).unwrap())],
        &[],
    );
    let url = format!("http://{}/cine.wspx", server.url);
    plays_and_steps(&x.display, &[&url], dir.path(), &file);
    // Each of the six time points' streams was opened once, in the first loop: an opening
    // reads the head in one request of HEAD_READ_BYTES, more than this small file, so a time point
    // opened again in the second loop would take the bytes served past six files.
    let size = std::fs::metadata(&published).unwrap().len();
    assert!(size <= wavesplat_codec::format::index::HEAD_READ_BYTES);
    assert!(
        server.served() <= 6 * size,
        "{} bytes served of a {size}-byte file",
        server.served()
    );
}
