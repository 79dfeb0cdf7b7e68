//! Time series end to end through the real `wavesplat` binary: a 4D NIfTI (gzip, with a time
//! step), a 4D raw file and a directory of time steps are each compressed with one command
//! into one series file; `info` shows the time points and their times, `decompress
//! --time-point` gives back a time point, `render --time-point` and `--time-points` draw them
//! (PNGs through one window and an animated PNG); a DICOM cine (slices repeated at several
//! trigger times) compresses the same way; `--time-point` takes one volume out at
//! compression; bad series are refused with the problem named.

mod common;

use std::path::Path;
use std::process::{Command, Output};
use wavesplat_codec::volume::Volume;
use wavesplat_compressor::phantom::beating;
use wavesplat_fixtures::{write_dicom_cine, write_nifti, write_nifti_series, DicomOptions, Layout};

const BIN: &str = env!("CARGO_BIN_EXE_wavesplat");
const DIMS: [usize; 3] = [24, 20, 12];

fn cli(args: &[&str]) -> Output {
    Command::new(BIN).args(args).output().unwrap()
}

fn cli_ok(args: &[&str]) -> String {
    let out = cli(args);
    let text = common::text(&out);
    assert!(out.status.success(), "{args:?} failed: {text}");
    text
}

fn cli_err(args: &[&str]) -> String {
    let out = cli(args);
    let text = common::text(&out);
    assert!(!out.status.success(), "{args:?} succeeded: {text}");
    text
}

fn points(n: usize) -> Vec<Volume> {
    (0..n).map(|t| beating(DIMS, t, n).unwrap()).collect()
}

/// PSNR (peak 400, the phantom's brightest) of a decompressed raw f32 file against `v`.
fn psnr_of(raw: &Path, v: &Volume) -> f64 {
    let got = common::read_f32(raw);
    wavesplat_codec::metrics::psnr_db(v.channel(0), &got, 400.0)
}

/// The frame count of an animated PNG's `acTL` chunk.
fn apng_frames(path: &Path) -> u32 {
    let b = std::fs::read(path).unwrap();
    let at = b
        .windows(4)
        .position(|w| w == b"acTL")
        .expect("an acTL chunk");
    u32::from_be_bytes(b[at + 4..at + 8].try_into().unwrap())
}

#[test]
fn a_4d_nifti_compresses_into_one_series_file_that_info_decompress_and_render_read() {
    let dir = tempfile::tempdir().unwrap();
    let d = |n: &str| dir.path().join(n).to_string_lossy().into_owned();
    let vols = points(6);
    let samples: Vec<Vec<f32>> = vols.iter().map(|v| v.channel(0).to_vec()).collect();
    write_nifti_series(
        &dir.path().join("cine.nii.gz"),
        DIMS,
        &samples,
        Some(40.0),
        true,
    );
    // `info` of the source lists its time points.
    let info = cli_ok(&["info", &d("cine.nii.gz")]);
    assert!(
        info.contains("a time series of 6 time points of 24x20x12 x1")
            && info.contains("0.0400 s apart"),
        "{info}"
    );
    let out = cli_ok(&[
        "compress",
        &d("cine.nii.gz"),
        "--target-fraction",
        "0.15",
        "-o",
        &d("c.wsp"),
    ]);
    assert!(
        out.contains("a time series of 6 time points in groups of 8"),
        "{out}"
    );
    let info = cli_ok(&["info", &d("c.wsp")]);
    assert!(
        info.contains("time points 6, from 0.0000 s to 0.2000 s, 0.0400 s apart"),
        "{info}"
    );
    assert!(info.contains("time point 5 at 0.2000 s"), "{info}");
    for t in [0, 3, 5] {
        let raw = d(&format!("t{t}.raw"));
        cli_ok(&[
            "decompress",
            &d("c.wsp"),
            "--time-point",
            &t.to_string(),
            "-o",
            &raw,
        ]);
        let db = psnr_of(Path::new(&raw), &vols[t]);
        assert!(db > 35.0, "time point {t}: {db:.2} dB");
        // Not another time point's volume: the heart moves between them.
        let other = psnr_of(Path::new(&raw), &vols[(t + 3) % 6]);
        assert!(
            db > other + 3.0,
            "time point {t}: {db:.2} dB, against another {other:.2}"
        );
    }
    let one = cli_ok(&[
        "render",
        &d("c.wsp"),
        "--time-point",
        "4",
        "--size",
        "48x40",
        "-o",
        &d("t4.png"),
    ]);
    assert!(one.contains("time point 4 of 6 at 0.160 s"), "{one}");
    let many = cli_ok(&[
        "render",
        &d("c.wsp"),
        "--time-points",
        "1..4",
        "--size",
        "48x40",
        "-o",
        &d("frames"),
    ]);
    assert!(many.contains("wrote 4 time points (1..=4) of 6"), "{many}");
    for t in 1..=4 {
        assert!(dir.path().join(format!("frames/t{t:04}.png")).exists());
    }
    assert!(!dir.path().join("frames/t0000.png").exists());
    assert_eq!(apng_frames(&dir.path().join("frames/animation.png")), 4);
    // Out of range, and options that do not apply, are refused by name.
    let e = cli_err(&[
        "render",
        &d("c.wsp"),
        "--time-point",
        "6",
        "-o",
        &d("x.png"),
    ]);
    assert!(e.contains("has 6 time points"), "{e}");
    let e = cli_err(&[
        "render",
        &d("c.wsp"),
        "--time-points",
        "2..9",
        "-o",
        &d("f2"),
    ]);
    assert!(e.contains("0..=5"), "{e}");
    let e = cli_err(&["render", &d("c.wsp"), "--reference", "-o", &d("x.png")]);
    assert!(e.contains("time series"), "{e}");
    // Drawn progressively (the frame loop the window uses), a time point ends at its one-pass
    // image.
    let raw = |name: &str, extra: &[&str]| {
        let mut args = vec![
            "render",
            &d("c.wsp")[..],
            "--time-point",
            "4",
            "--size",
            "48x40",
        ]
        .into_iter()
        .map(String::from)
        .collect::<Vec<_>>();
        args.extend(extra.iter().map(|s| s.to_string()));
        args.extend(["--raw".into(), d(name), "-o".into(), d("p.png")]);
        let refs: Vec<&str> = args.iter().map(String::as_str).collect();
        cli_ok(&refs);
        common::read_f32(&dir.path().join(name))
    };
    let (one, progressive) = (
        raw("one.f32", &[]),
        raw("prog.f32", &["--progressive", "--cpu"]),
    );
    let db = wavesplat_codec::metrics::snr_db(&one, &progressive);
    assert!(db > 90.0, "{db:.1} dB");
    // One time point taken out at compression is a plain volume file.
    cli_ok(&[
        "compress",
        &d("cine.nii.gz"),
        "--time-point",
        "2",
        "--target-fraction",
        "0.15",
        "-o",
        &d("one.wsp"),
    ]);
    let info = cli_ok(&["info", &d("one.wsp")]);
    assert!(!info.contains("time series"), "{info}");
    cli_ok(&["decompress", &d("one.wsp"), "-o", &d("one.raw")]);
    let db = psnr_of(&dir.path().join("one.raw"), &vols[2]);
    let other = psnr_of(&dir.path().join("one.raw"), &vols[5]);
    assert!(
        db > 28.0 && db > other + 3.0,
        "{db:.2} dB, against another {other:.2}"
    );
    let e = cli_err(&[
        "compress",
        &d("cine.nii.gz"),
        "--time-point",
        "6",
        "-o",
        &d("x.wsp"),
    ]);
    assert!(e.contains("6 time points"), "{e}");
    let e = cli_err(&[
        "decompress",
        &d("one.wsp"),
        "--time-point",
        "1",
        "-o",
        &d("x.raw"),
    ]);
    assert!(e.contains("one volume"), "{e}");
}

#[test]
fn a_4d_raw_file_and_a_directory_of_steps_compress_with_one_command() {
    let dir = tempfile::tempdir().unwrap();
    let d = |n: &str| dir.path().join(n).to_string_lossy().into_owned();
    let vols = points(4);
    let bytes: Vec<u8> = vols
        .iter()
        .flat_map(|v| {
            v.channel(0)
                .iter()
                .flat_map(|x| (x.max(0.0) as u16).to_le_bytes())
        })
        .collect();
    std::fs::write(dir.path().join("cine.raw"), &bytes).unwrap();
    let dims = format!("{},{},{},4", DIMS[0], DIMS[1], DIMS[2]);
    let out = cli_ok(&[
        "compress",
        &d("cine.raw"),
        "--dims",
        &dims,
        "--dtype",
        "u16",
        "--target-fraction",
        "0.15",
        "-o",
        &d("r.wsp"),
    ]);
    assert!(out.contains("a time series of 4 time points"), "{out}");
    let info = cli_ok(&["info", &d("r.wsp")]);
    assert!(info.contains("no times in the source"), "{info}");
    // One time point too many for the file's size.
    let dims5 = format!("{},{},{},5", DIMS[0], DIMS[1], DIMS[2]);
    let e = cli_err(&[
        "compress",
        &d("cine.raw"),
        "--dims",
        &dims5,
        "--dtype",
        "u16",
        "-o",
        &d("x.wsp"),
    ]);
    assert!(e.contains("bytes"), "{e}");

    let steps = dir.path().join("steps");
    std::fs::create_dir(&steps).unwrap();
    for (t, v) in vols.iter().enumerate() {
        write_nifti(
            &steps.join(format!("step_{:04}.nii", t * 10)),
            DIMS,
            v.channel(0),
        );
    }
    let info = cli_ok(&["info", &d("steps")]);
    assert!(
        info.contains("a time series of 4 time points") && info.contains("no times"),
        "{info}"
    );
    let out = cli_ok(&[
        "compress",
        &d("steps"),
        "--target-fraction",
        "0.15",
        "--time-group",
        "2",
        "-o",
        &d("s.wsp"),
    ]);
    assert!(
        out.contains("a time series of 4 time points in groups of 2"),
        "{out}"
    );
    cli_ok(&[
        "decompress",
        &d("s.wsp"),
        "--time-point",
        "3",
        "-o",
        &d("s3.raw"),
    ]);
    assert!(psnr_of(&dir.path().join("s3.raw"), &vols[3]) > 35.0);
    // A missing step is named, not skipped.
    std::fs::remove_file(steps.join("step_0020.nii")).unwrap();
    let e = cli_err(&["compress", &d("steps"), "-o", &d("x.wsp")]);
    assert!(e.contains("step 20 is missing"), "{e}");
    // --time-group must be a power of two; --time-point needs a series.
    std::fs::write(dir.path().join("one.raw"), &bytes[..bytes.len() / 4]).unwrap();
    let e = cli_err(&[
        "compress",
        &d("cine.raw"),
        "--dims",
        &dims,
        "--dtype",
        "u16",
        "--time-group",
        "3",
        "-o",
        &d("x.wsp"),
    ]);
    assert!(e.contains("power of two"), "{e}");
    let one = format!("{},{},{}", DIMS[0], DIMS[1], DIMS[2]);
    let e = cli_err(&[
        "compress",
        &d("one.raw"),
        "--dims",
        &one,
        "--dtype",
        "u16",
        "--time-point",
        "0",
        "-o",
        &d("x.wsp"),
    ]);
    assert!(e.contains("one volume"), "{e}");
}

#[test]
fn a_dicom_cine_compresses_with_one_command_and_plays_its_trigger_times() {
    let dir = tempfile::tempdir().unwrap();
    let d = |n: &str| dir.path().join(n).to_string_lossy().into_owned();
    // Integer-valued time points (16-bit samples).
    let vols: Vec<Volume> = points(5)
        .into_iter()
        .map(|v| {
            let data = v.channel(0).iter().map(|x| x.max(0.0).round()).collect();
            Volume::new(DIMS, [1.25, 1.25, 4.0], vec![data]).unwrap()
        })
        .collect();
    let ms = [0.0, 41.5, 83.0, 124.5, 166.0];
    let o = DicomOptions {
        layout: Layout::U16,
        ..Default::default()
    };
    write_dicom_cine(&dir.path().join("cine"), &vols, &ms, &o);
    let info = cli_ok(&["info", &d("cine")]);
    assert!(
        info.contains("a time series of 5 time points") && info.contains("0.0415 s apart"),
        "{info}"
    );
    let out = cli_ok(&[
        "compress",
        &d("cine"),
        "--target-fraction",
        "0.15",
        "-o",
        &d("c.wsp"),
    ]);
    assert!(out.contains("a time series of 5 time points"), "{out}");
    assert!(out.contains("time step 0.0415 s"), "{out}");
    let info = cli_ok(&["info", &d("c.wsp")]);
    assert!(
        info.contains("time points 5, from 0.0000 s to 0.1660 s"),
        "{info}"
    );
    assert!(info.contains("spacing 1.25 x 1.25 x 4"), "{info}");
    cli_ok(&[
        "decompress",
        &d("c.wsp"),
        "--time-point",
        "3",
        "-o",
        &d("t3.raw"),
    ]);
    let db = psnr_of(&dir.path().join("t3.raw"), &vols[3]);
    assert!(db > 35.0, "{db:.2} dB");
    // One time point taken out of the cine.
    cli_ok(&[
        "compress",
        &d("cine"),
        "--time-point",
        "4",
        "--target-fraction",
        "0.15",
        "-o",
        &d("one.wsp"),
    ]);
    cli_ok(&["decompress", &d("one.wsp"), "-o", &d("one.raw")]);
    let (db, other) = (
        psnr_of(&dir.path().join("one.raw"), &vols[4]),
        psnr_of(&dir.path().join("one.raw"), &vols[1]),
    );
    assert!(
        db > 28.0 && db > other + 3.0,
        "{db:.2} dB, against another {other:.2}"
    );
}

/// A multi-frame DICOM cine (one slice over time, Frame Time) compresses with one command into
/// a series of one-slice time points at its frame times; each decoded time point is its frame.
#[test]
fn a_multiframe_dicom_cine_compresses_into_a_series_of_its_frames() {
    let dir = tempfile::tempdir().unwrap();
    let d = |n: &str| dir.path().join(n).to_string_lossy().into_owned();
    // Eight frames of a 40×36 slice: the beating phantom's middle slice over one beat.
    let frames: Vec<Vec<f32>> = (0..8)
        .map(|t| {
            let v = beating([40, 36, 9], t, 8).unwrap();
            v.channel(0)[4 * 40 * 36..5 * 40 * 36]
                .iter()
                .map(|x| x.max(0.0).round())
                .collect()
        })
        .collect();
    let stacked = Volume::new([40, 36, 8], [0.8, 0.8, 6.0], vec![frames.concat()]).unwrap();
    let o = DicomOptions {
        layout: Layout::U16,
        ..Default::default()
    };
    wavesplat_fixtures::write_dicom_cine_file(&dir.path().join("cine.dcm"), &stacked, 25.0, &o);
    let info = cli_ok(&["info", &d("cine.dcm")]);
    assert!(
        info.contains("a time series of 8 time points of 40x36x1")
            && info.contains("0.0250 s apart"),
        "{info}"
    );
    cli_ok(&[
        "compress",
        &d("cine.dcm"),
        "--target-fraction",
        "0.5",
        "-o",
        &d("cine.wsp"),
    ]);
    for t in [0usize, 5] {
        cli_ok(&[
            "decompress",
            &d("cine.wsp"),
            "--time-point",
            &t.to_string(),
            "-o",
            &d("t.raw"),
        ]);
        let got = common::read_f32(&dir.path().join("t.raw"));
        let psnr = wavesplat_codec::metrics::psnr_db(&frames[t], &got, 400.0);
        assert!(psnr > 35.0, "time point {t}: {psnr:.1} dB");
    }
}
