//! End-to-end tests of the readers through the real `wavesplat` binary: an archive mixing
//! DICOM (a series directory and a multi-frame file), NRRD (attached gzip, detached raw),
//! MetaImage (`.mha`, `.mhd` + raw), NIfTI, Zarr (an OME-Zarr image; an array uploaded) and
//! raw files is compressed through the
//! orchestrator (path sources, and a bundle upload), the unreadable volumes fail their jobs
//! with the reason and the rest land in the cache with their spacing and placement; and
//! `compress` + `info` show the geometry of a DICOM series.

mod common;

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::time::{Duration, Instant};
use wavesplat_client::{CacheClient, VolumeKey};
use wavesplat_codec::volume::{Placement, Volume};
use wavesplat_compressor::phantom::Phantom;
use wavesplat_fixtures::{
    write_dicom_multiframe, write_dicom_series, write_metaimage, write_nifti, write_nrrd,
    write_zarr, write_zarr_channels, DicomEncoding, DicomOptions, Layout, NrrdEncoding,
};
use wavesplat_orchestrator_client as client;
use wavesplat_orchestrator_client::convert::state_name;
use wavesplat_proto::pb;

const BIN: &str = env!("CARGO_BIN_EXE_wavesplat");

fn cli(args: &[&str]) -> Output {
    Command::new(BIN).args(args).output().unwrap()
}

fn cli_ok(args: &[&str]) -> String {
    let out = cli(args);
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        out.status.success(),
        "{args:?} failed: {stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    stdout
}

/// An integer-valued CT-like phantom in HU (−1024 .. ~1000) placed obliquely.
fn ct(dims: [usize; 3], spacing: [f32; 3]) -> Volume {
    let p = Phantom::SheppLogan.generate(dims);
    let data = p
        .channel(0)
        .iter()
        .map(|v| (v * 8.0).round() - 1024.0)
        .collect();
    Volume::new(dims, spacing, vec![data])
        .unwrap()
        .with_placement(Placement {
            origin: [-100.0, 50.5, 200.0],
            directions: [[0.6, 0.8, 0.0], [-0.8, 0.6, 0.0], [0.0, 0.0, 1.0]],
        })
        .unwrap()
}

/// Writes the mixed archive under `dir`; returns (good volume names with their source
/// volumes, bad volume names with a word their failure must contain).
#[allow(clippy::type_complexity)]
fn write_archive(dir: &Path) -> (Vec<(String, Volume)>, Vec<(String, &'static str)>) {
    let mut good = Vec::new();
    let v = ct([20, 18, 12], [0.7, 0.7, 2.5]);
    write_dicom_series(
        &dir.join("ct/series1"),
        &v,
        &DicomOptions {
            intercept: -1024.0,
            slope: 1.0,
            layout: Layout::U16,
            ..DicomOptions::default()
        },
    );
    // Stored values are v + 1024 ≥ 0 as u16; the reader applies the intercept back.
    good.push(("ct/series1".to_string(), v.clone()));
    let v = ct([16, 16, 10], [0.9, 0.9, 1.5]);
    std::fs::create_dir_all(dir.join("ct/enhanced")).unwrap();
    write_dicom_multiframe(
        &dir.join("ct/enhanced/mf.dcm"),
        &v,
        &DicomOptions {
            encoding: DicomEncoding::RleLossless,
            series_uid: "1.2.826.0.1.3680043.9.7433.1.2".into(),
            ..DicomOptions::default()
        },
    );
    good.push(("ct/enhanced".into(), v));
    let v = ct([17, 15, 11], [1.0, 1.0, 3.0]);
    write_nrrd(
        dir,
        "nrrd_gz",
        &v,
        Layout::I16,
        NrrdEncoding::Gzip,
        false,
        "RAS",
    );
    good.push(("nrrd_gz".into(), v));
    let v = ct([15, 17, 9], [0.5, 0.5, 1.0]);
    write_nrrd(
        dir,
        "nrrd_det",
        &v,
        Layout::I16,
        NrrdEncoding::Raw,
        true,
        "LPS",
    );
    good.push(("nrrd_det".into(), v));
    let v = ct([14, 16, 13], [0.8, 0.8, 0.8]);
    write_metaimage(dir, "mr", &v, Layout::I16, true, false);
    good.push(("mr".into(), v));
    let v = ct([16, 14, 12], [1.2, 1.2, 2.0]);
    write_metaimage(dir, "mr_det", &v, Layout::F32, false, true);
    good.push(("mr_det".into(), v));
    let dims = [16, 16, 14];
    let p = Phantom::Spheres.generate(dims);
    write_nifti(&dir.join("spheres.nii"), dims, p.channel(0));
    good.push(("spheres".into(), p.clone()));
    // Different content from the NIfTI (identical content would land once in the cache).
    let p = Phantom::SheppLogan.generate([16, 16, 15]);
    let bytes: Vec<u8> = p.channel(0).iter().flat_map(|v| v.to_le_bytes()).collect();
    std::fs::write(dir.join("raw_16x16x15_f32.raw"), bytes).unwrap();
    good.push(("raw".into(), p));

    // An OME-Zarr image (its spacing in its scale), read chunk by chunk.
    let c = ct([18, 14, 11], [0.4, 0.4, 1.6]);
    let v = Volume::new(c.dims(), c.spacing(), vec![c.channel(0).to_vec()]).unwrap();
    write_zarr(&dir.join("scope/cells.ome.zarr"), &v, [8, 8, 4], true);
    good.push(("scope/cells".into(), v));
    // An OME-Zarr image of two channels (c, z, y, x): a volume per channel, each its own
    // values (their ranges tell them apart in the cache).
    let c0 = ct([12, 10, 9], [0.5, 0.5, 1.0]);
    let c0 = Volume::new(c0.dims(), c0.spacing(), vec![c0.channel(0).to_vec()]).unwrap();
    let c1: Vec<f32> = c0.channel(0).iter().map(|v| 3.0 * v + 5000.0).collect();
    let c1 = Volume::new(c0.dims(), c0.spacing(), vec![c1]).unwrap();
    write_zarr_channels(
        &dir.join("scope/two.ome.zarr"),
        &[&c0, &c1],
        [8, 8, 4],
        true,
    );
    good.push(("scope/two/c0".into(), c0));
    good.push(("scope/two/c1".into(), c1));

    // Unreadable: a series with a missing slice, an NRRD claiming a huge volume, a MetaImage
    // with zero spacing.
    let v = ct([8, 8, 6], [1.0, 1.0, 2.0]);
    let files = write_dicom_series(
        &dir.join("ct/gappy"),
        &v,
        &DicomOptions {
            series_uid: "1.2.826.0.1.3680043.9.7433.1.3".into(),
            intercept: -2048.0,
            ..DicomOptions::default()
        },
    );
    // Remove a middle slice (file names do not follow position; z = 3 is files[3]).
    std::fs::remove_file(&files[3]).unwrap();
    std::fs::write(
        dir.join("huge.nrrd"),
        "NRRD0004\ntype: uint8\ndimension: 3\nsizes: 100000 100000 100000\nencoding: raw\n\nxx",
    )
    .unwrap();
    let mut mha = b"ObjectType = Image\nNDims = 3\nDimSize = 2 2 2\nElementSpacing = 1 0 1\nElementType = MET_UCHAR\nElementDataFile = LOCAL\n".to_vec();
    mha.extend_from_slice(&[0; 8]);
    std::fs::write(dir.join("flat.mha"), mha).unwrap();
    let bad = vec![
        ("ct/gappy".to_string(), "missing"),
        ("huge".to_string(), "huge.nrrd"),
        ("flat".to_string(), "ElementSpacing"),
    ];
    (good, bad)
}

async fn wait_all_finished(url: &str, n: usize, secs: u64) -> Vec<pb::Job> {
    let end = Instant::now() + Duration::from_secs(secs);
    loop {
        if let Ok(mut c) = client::connect(url).await {
            if let Ok(js) = client::list(&mut c).await {
                let finished = js
                    .iter()
                    .filter(|j| matches!(state_name(j.state), "done" | "failed" | "cancelled"))
                    .count();
                if js.len() == n && finished == n {
                    return js;
                }
                if Instant::now() > end {
                    let states: Vec<String> = js
                        .iter()
                        .map(|j| {
                            let name = &j.spec.as_ref().unwrap().name;
                            format!("{} {name} {} {}", j.id, state_name(j.state), j.error)
                        })
                        .collect();
                    panic!("timed out waiting for {n} finished jobs: {states:#?}");
                }
            }
        }
        assert!(Instant::now() <= end, "timed out");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_archive_of_every_format_compresses_and_bad_volumes_fail_alone() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let archive = root.join("archive");
    let (good, bad) = write_archive(&archive);
    // A second archive, uploaded: a DICOM series travels as one bundle.
    let up = root.join("up");
    let v_up = ct([12, 10, 7], [0.6, 0.6, 1.2]);
    write_dicom_series(
        &up.join("series"),
        &v_up,
        &DicomOptions {
            series_uid: "1.2.826.0.1.3680043.9.7433.1.4".into(),
            ..DicomOptions::default()
        },
    );

    let cluster = common::TestCluster::start(&[
        "--lease-secs",
        "5",
        "--heartbeat-ms",
        "300",
        "--poll-ms",
        "100",
    ]);
    let (o, c) = (cluster.orch.url(), cluster.cache.url());
    let _worker = cluster.worker("w", 0, None);
    let common = ["--orchestrator", &o, "--detach", "--levels", "2"];
    let mut args = vec!["archive", "submit", archive.to_str().unwrap()];
    args.extend_from_slice(&common);
    let out = cli_ok(&args);
    assert!(
        out.contains(&format!("{} submitted", good.len() + bad.len())),
        "{out}"
    );
    // A Zarr array travels as one bundle of its metadata and chunks.
    let v_zarr = Phantom::Spheres.generate([13, 11, 9]);
    write_zarr(&up.join("plain.zarr"), &v_zarr, [5, 5, 5], false);
    let mut args = vec!["archive", "submit", up.to_str().unwrap(), "--upload"];
    args.extend_from_slice(&common);
    cli_ok(&args);

    let n = good.len() + bad.len() + 2;
    let js = wait_all_finished(&o, n, 120).await;
    for j in &js {
        let name = j.spec.as_ref().unwrap().name.as_str();
        if let Some((_, why)) = bad.iter().find(|(b, _)| b == name) {
            assert_eq!(state_name(j.state), "failed", "{name}");
            assert_eq!(j.failure, pb::FailureKind::InvalidInput as i32, "{name}");
            assert!(j.error.contains(why), "{name}: {}", j.error);
        } else {
            assert_eq!(state_name(j.state), "done", "{name}: {}", j.error);
        }
    }

    // The cache holds every good volume with the spacing and placement of its source.
    let mut cache = CacheClient::connect(&c).await.unwrap();
    let mut expect: Vec<(String, Volume)> = good.clone();
    expect.push(("series".into(), v_up));
    expect.push(("plain".into(), v_zarr));
    for (name, v) in &expect {
        let h = cache
            .header(&VolumeKey::Name(name.clone()))
            .await
            .unwrap_or_else(|e| panic!("{name}: {e}"))
            .header;
        assert_eq!(h.geometry.dims, v.dims(), "{name}");
        for a in 0..3 {
            assert!(
                (h.spacing()[a] - v.spacing()[a]).abs() <= 1e-5 * v.spacing()[a],
                "{name}: {:?} vs {:?}",
                h.spacing(),
                v.spacing()
            );
        }
        match (v.placement(), h.placement) {
            (Some(want), Some(got)) => {
                for i in 0..3 {
                    assert!((want.origin[i] - got.origin[i]).abs() < 1e-4, "{name}");
                    for k in 0..3 {
                        assert!((want.directions[i][k] - got.directions[i][k]).abs() < 1e-6);
                    }
                }
            }
            (None, None) => {}
            (w, g) => panic!("{name}: placement {w:?} vs {g:?}"),
        }
        // Values keep their units: the CT volumes' range is in HU; each channel of a Zarr
        // array its own.
        if name.starts_with("ct/")
            || name.starts_with("nrrd")
            || name == "series"
            || name.starts_with("scope/two/")
        {
            let (lo, hi) = v.value_range();
            assert!(
                (h.value_range[0] - lo).abs() < 1e-3 && (h.value_range[1] - hi).abs() < 1e-3,
                "{name}: {:?}",
                h.value_range
            );
            assert!(lo <= -1000.0 || name == "scope/two/c1", "{name}");
        }
    }
    let stored = cache.list().await.unwrap();
    assert_eq!(stored.len(), expect.len());
}

/// The channels of a Zarr array submitted as bricked jobs to one worker, which keeps a source
/// open between parts: each channel's bricks read its own channel (the cache holds the files
/// `compress --channel` makes); a store that cannot be listed is said and the rest submitted.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bricked_jobs_of_the_channels_of_a_zarr_array_each_read_their_own() {
    let tmp = tempfile::tempdir().unwrap();
    let archive = tmp.path().join("archive");
    let c0 = ct([20, 18, 12], [0.5, 0.5, 1.0]);
    let c0 = Volume::new(c0.dims(), c0.spacing(), vec![c0.channel(0).to_vec()]).unwrap();
    // Another picture, not the first's samples scaled (which code to the same packets).
    let spheres = Phantom::Spheres.generate(c0.dims());
    let c1: Vec<f32> = spheres
        .channel(0)
        .iter()
        .map(|v| 400.0 * v + 9000.0)
        .collect();
    let c1 = Volume::new(c0.dims(), c0.spacing(), vec![c1]).unwrap();
    write_zarr_channels(&archive.join("two.ome.zarr"), &[&c0, &c1], [8, 8, 8], true);
    // A store whose files cannot be listed (a link back to itself): its metadata opens, so the
    // scan finds it, but it cannot be hashed; said, and the rest submitted.
    let looped = archive.join("loop.zarr");
    write_zarr(&looped, &c0, [8, 8, 8], false);
    std::os::unix::fs::symlink(&looped, looped.join("again")).unwrap();
    let cluster = common::TestCluster::start(&["--poll-ms", "100"]);
    let (o, c) = (cluster.orch.url(), cluster.cache.url());
    let _worker = cluster.worker("w", 0, None);
    let submitted = cli(&[
        "archive",
        "submit",
        archive.to_str().unwrap(),
        "--orchestrator",
        &o,
        "--detach",
        "--brick",
        "8",
        "--levels",
        "1",
    ]);
    let out = String::from_utf8_lossy(&submitted.stdout);
    let err = String::from_utf8_lossy(&submitted.stderr);
    assert!(!submitted.status.success(), "{out}\n{err}");
    assert!(
        out.contains("2 submitted") && out.contains("1 not read"),
        "{out}"
    );
    assert!(out.contains("as two/c1 submitted as job"), "{out}");
    assert!(
        err.contains("loop.zarr") && err.contains("not submitted"),
        "{err}"
    );
    // The two bricked jobs (their parts are jobs too) finished.
    let end = Instant::now() + Duration::from_secs(120);
    let parents = loop {
        let mut cl = client::connect(&o).await.unwrap();
        let parents: Vec<pb::Job> = client::list(&mut cl)
            .await
            .unwrap()
            .into_iter()
            .filter(|j| j.spec.as_ref().is_some_and(|s| s.part.is_none()))
            .collect();
        let finished = |j: &pb::Job| matches!(state_name(j.state), "done" | "failed" | "cancelled");
        if parents.len() == 2 && parents.iter().all(finished) {
            break parents;
        }
        assert!(Instant::now() < end, "timed out: {parents:#?}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    };
    for j in &parents {
        let spec = j.spec.as_ref().unwrap();
        assert_eq!(state_name(j.state), "done", "{}: {}", spec.name, j.error);
        assert_eq!(spec.channel, Some(u32::from(spec.name == "two/c1")));
    }
    let mut cache = CacheClient::connect(&c).await.unwrap();
    // Each is the file `compress --channel` makes of its channel, byte for byte.
    let listed = cache.list().await.unwrap();
    for (ch, name) in ["two/c0", "two/c1"].iter().enumerate() {
        let file = tmp.path().join(format!("c{ch}.wspx"));
        cli_ok(&[
            "compress",
            archive.join("two.ome.zarr").to_str().unwrap(),
            "--channel",
            &ch.to_string(),
            "--brick",
            "8",
            "--levels",
            "1",
            "-o",
            file.to_str().unwrap(),
        ]);
        let sha = wavesplat_net::digest::sha256(&std::fs::read(&file).unwrap());
        let cached = listed.iter().find(|v| v.name == *name).expect("cached");
        assert_eq!(cached.sha256, wavesplat_net::digest::hex(&sha), "{name}");
    }
    for (name, v) in [("two/c0", &c0), ("two/c1", &c1)] {
        let h = cache
            .header(&VolumeKey::Name(name.into()))
            .await
            .unwrap_or_else(|e| panic!("{name}: {e}"))
            .header;
        assert_eq!(h.geometry.dims, v.dims(), "{name}");
        let (lo, hi) = v.value_range();
        assert!(
            (h.value_range[0] - lo).abs() < 1e-3 && (h.value_range[1] - hi).abs() < 1e-3,
            "{name}: {:?} against {lo}..{hi}",
            h.value_range
        );
    }
}

#[test]
fn compress_and_info_show_the_geometry_of_a_dicom_series() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("series");
    let v = ct([16, 12, 8], [0.7, 0.7, 2.5]);
    write_dicom_series(
        &dir,
        &v,
        &DicomOptions {
            intercept: -1024.0,
            layout: Layout::U16,
            ..DicomOptions::default()
        },
    );
    let out: PathBuf = tmp.path().join("s.wsp");
    cli_ok(&[
        "compress",
        dir.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
        "--levels",
        "2",
    ]);
    let info = cli_ok(&["info", out.to_str().unwrap()]);
    assert!(info.contains("spacing 0.7 x 0.7 x 2.5"), "{info}");
    assert!(
        info.contains("origin      (-100.000, 50.500, 200.000) mm"),
        "{info}"
    );
    assert!(
        info.contains("axis z      (+0.000000, +0.000000, +1.000000) LPS, towards S"),
        "{info}"
    );
    assert!(info.contains("towards P"), "{info}");
    // Bricked, the series is read by slice ranges (a brick decodes only its slices' files)
    // and decodes to what the whole file decodes to, within the coding error.
    let bricked: PathBuf = tmp.path().join("b.wsp");
    let c = cli_ok(&[
        "compress",
        dir.to_str().unwrap(),
        "-o",
        bricked.to_str().unwrap(),
        "--levels",
        "2",
        "--brick",
        "8",
        "--target-fraction",
        "1",
    ]);
    assert!(c.contains("4 bricks"), "{c}");
    let decoded = tmp.path().join("b.raw");
    cli_ok(&[
        "decompress",
        bricked.to_str().unwrap(),
        "-o",
        decoded.to_str().unwrap(),
    ]);
    let got = read_raw_image(&decoded);
    let snr = wavesplat_codec::metrics::snr_db(v.channel(0), &got);
    assert!(snr > 40.0, "bricked DICOM series decoded at {snr:.1} dB");
    // Raw input takes --spacing; a header format refuses it.
    let raw = tmp.path().join("r.raw");
    std::fs::write(&raw, vec![7u8; 4 * 4 * 4]).unwrap();
    cli_ok(&[
        "compress",
        raw.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
        "--dims",
        "4,4,4",
        "--dtype",
        "u8",
        "--spacing",
        "0.5,0.5,3",
        "--levels",
        "1",
    ]);
    let info = cli_ok(&["info", out.to_str().unwrap()]);
    assert!(info.contains("spacing 0.5 x 0.5 x 3"), "{info}");
    assert!(info.contains("orientation unknown"), "{info}");
    let e = cli(&[
        "compress",
        dir.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
        "--spacing",
        "1,1,1",
    ]);
    assert!(!e.status.success());
    // An unreadable slice: the error names the file and the problem.
    let f = std::fs::read_dir(&dir)
        .unwrap()
        .next()
        .unwrap()
        .unwrap()
        .path();
    let mut b = vec![0u8; 128];
    b.extend_from_slice(b"DICM\x02\x00\x00\x00garbage");
    std::fs::write(&f, b).unwrap();
    let e = cli(&[
        "compress",
        dir.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
    ]);
    assert!(!e.status.success());
    let msg = String::from_utf8_lossy(&e.stderr);
    let fname = f.file_name().unwrap().to_string_lossy().into_owned();
    assert!(msg.contains(&fname), "{msg}");
}

/// Reads a `render --raw` image (little-endian f32).
fn read_raw_image(path: &Path) -> Vec<f32> {
    std::fs::read(path)
        .unwrap()
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect()
}

/// Named patient views and physical zoom through the binary: an axial NRRD series (identity
/// placement, 0.8 × 0.8 × 2.5 mm voxels) rendered `--view anterior` is the view (α, β) =
/// (−π/2, 0) by the table in `codec::view::patient`; `--view superior` differs from it; a
/// file whose source gave no orientation refuses a named view with the reason; and `--zoom`
/// is in pixels per mm: twice the zoom doubles the drawn extent.
#[test]
fn named_views_and_zoom_in_millimetres() {
    let tmp = tempfile::tempdir().unwrap();
    let v = ct([24, 20, 10], [0.8, 0.8, 2.5])
        .with_placement(Placement::identity())
        .unwrap();
    let nrrd = write_nrrd(
        tmp.path(),
        "axial",
        &v,
        Layout::I16,
        NrrdEncoding::Raw,
        false,
        "LPS",
    );
    let wsp = tmp.path().join("axial.wsp");
    let path = |name: &str| tmp.path().join(name).to_str().unwrap().to_string();
    cli_ok(&[
        "compress",
        nrrd.to_str().unwrap(),
        "-o",
        wsp.to_str().unwrap(),
        "--levels",
        "2",
    ]);
    let render = |extra: &[&str], name: &str| -> Vec<f32> {
        let raw = path(&format!("{name}.raw"));
        let png = path(&format!("{name}.png"));
        let mut args = vec![
            "render",
            wsp.to_str().unwrap(),
            "--size",
            "48x48",
            "--cpu",
            "-o",
            &png,
            "--raw",
            &raw,
        ];
        args.extend_from_slice(extra);
        cli_ok(&args);
        read_raw_image(Path::new(&raw))
    };
    let named = render(&["--view", "anterior", "--zoom", "1.2"], "anterior");
    let angles = render(
        &[
            "--alpha",
            "-1.5707963267948966",
            "--beta",
            "0",
            "--zoom",
            "1.2",
        ],
        "angles",
    );
    let peak = angles.iter().fold(0.0f32, |m, x| m.max(x.abs()));
    assert!(peak > 0.0);
    let diff = named
        .iter()
        .zip(&angles)
        .fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
    assert!(
        diff <= 1e-4 * peak,
        "anterior vs its angles: {diff} of {peak}"
    );
    let superior = render(&["--view", "superior", "--zoom", "1.2"], "superior");
    let diff = superior
        .iter()
        .zip(&angles)
        .fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
    assert!(diff > 0.1 * peak, "superior equals anterior");
    // Zoom in px/mm: the anterior image's silhouette (the air at −1024 HU fills the box; rows
    // above 20 % of the peak, past the compression's ringing outside it) spans the volume's
    // physical height (10 × 2.5 mm) times the zoom: 30 px at 1.2 px/mm, 15 at 0.6.
    let rows = |img: &[f32], thr: f32| -> usize {
        (0..48)
            .filter(|y| img[y * 48..(y + 1) * 48].iter().any(|v| v.abs() > thr))
            .count()
    };
    let zoomed = render(&["--view", "anterior", "--zoom", "0.6"], "zoomed");
    let (tall, short) = (rows(&named, 0.2 * peak), rows(&zoomed, 0.2 * peak));
    assert!(
        (28..=32).contains(&tall) && (14..=17).contains(&short),
        "rows at 1.2 px/mm {tall}, at 0.6 px/mm {short}"
    );
    // No orientation: a raw file refuses a named view and says why.
    let raw = tmp.path().join("r.raw");
    std::fs::write(&raw, vec![7u8; 8 * 8 * 8]).unwrap();
    let unplaced = tmp.path().join("r.wsp");
    cli_ok(&[
        "compress",
        raw.to_str().unwrap(),
        "-o",
        unplaced.to_str().unwrap(),
        "--dims",
        "8,8,8",
        "--dtype",
        "u8",
        "--levels",
        "1",
    ]);
    let out = cli(&[
        "render",
        unplaced.to_str().unwrap(),
        "--view",
        "anterior",
        "-o",
        &path("x.png"),
    ]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        err.contains("orientation in the patient is unknown"),
        "{err}"
    );
}

/// `compress --channel C` of a Zarr array of several channels writes what the same channel
/// in a NIfTI file writes, byte for byte, whole and in bricks; without a choice, or with a
/// channel it lacks, it is refused saying how many it holds.
#[test]
fn a_channel_of_a_zarr_array_compresses_as_that_channel_in_nifti() {
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path();
    let dims = [17, 13, 11];
    let channels = [
        Phantom::SheppLogan.generate(dims),
        Phantom::Spheres.generate(dims),
        Phantom::Blobs.generate(dims),
    ];
    let refs: Vec<&Volume> = channels.iter().collect();
    let store = d.join("three.ome.zarr");
    write_zarr_channels(&store, &refs, [8, 8, 8], true);
    let store_s = store.to_str().unwrap();
    let out = d.join("x.wsp");
    for (extra, want) in [
        (&[][..], "3 channels"),
        (&["--channel", "3"][..], "channel 3"),
    ] {
        let mut args = vec!["compress", store_s, "-o", out.to_str().unwrap()];
        args.extend_from_slice(extra);
        let o = cli(&args);
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success(), "{extra:?}");
        assert!(
            err.contains(want) && err.contains("--channel"),
            "{extra:?}: {err}"
        );
        assert!(!out.exists(), "{extra:?}: an output was written");
    }
    for c in [1, 2] {
        let nii = d.join(format!("c{c}.nii"));
        write_nifti(&nii, dims, channels[c].channel(0));
        for bricks in [&[][..], &["--brick", "8"][..]] {
            let ext = if bricks.is_empty() { "wsp" } else { "wspx" };
            let mut outputs = Vec::new();
            for (input, chosen) in [(store_s, Some(c)), (nii.to_str().unwrap(), None)] {
                let out = d.join(format!("{c}-{}.{ext}", outputs.len()));
                let c_arg = c.to_string();
                let mut args = vec!["compress", input, "-o", out.to_str().unwrap()];
                if chosen.is_some() {
                    args.extend(["--channel", c_arg.as_str()]);
                }
                args.extend_from_slice(bricks);
                cli_ok(&args);
                outputs.push(std::fs::read(&out).unwrap());
            }
            assert!(
                outputs[0] == outputs[1],
                "channel {c} {bricks:?}: the Zarr array's file differs"
            );
        }
    }
}

/// Writes `channels` (f32 volumes of `dims`) as a multi-file OME-TIFF in `dir`: the planes in
/// the `DimensionOrder` XYZCT (each channel's slices in turn) split over three files, placed by
/// `xml_file`'s XML (`acq.ome.tif`, the first, or an OME companion file beside them); the other
/// files hold `BinaryOnly` pointers to it. Returns the path to read the dataset from.
fn write_multi_file_ome(
    dir: &Path,
    dims: [usize; 3],
    channels: &[Vec<f32>],
    xml_file: &str,
) -> PathBuf {
    use tiff::encoder::{colortype::Gray32Float, TiffEncoder};
    let [nx, ny, nz] = dims;
    let planes: Vec<&[f32]> = channels.iter().flat_map(|c| c.chunks(nx * ny)).collect();
    let cut = [0, planes.len() / 3, 2 * planes.len() / 3, planes.len()];
    let names = ["acq.ome.tif", "acq_1.ome.tif", "acq_2.ome.tif"];
    let tiff_data: String = (0..3)
        .map(|f| {
            let (c, z) = (cut[f] / nz, cut[f] % nz);
            format!(
                r#"<TiffData FirstZ="{z}" FirstC="{c}" IFD="0" PlaneCount="{}"><UUID FileName="{}">urn:uuid:{f}</UUID></TiffData>"#,
                cut[f + 1] - cut[f],
                names[f]
            )
        })
        .collect();
    let xml = format!(
        r#"<?xml version="1.0" encoding="UTF-8"?><OME UUID="urn:uuid:x"><Image ID="Image:0"><Pixels ID="Pixels:0" DimensionOrder="XYZCT" Type="float" SizeX="{nx}" SizeY="{ny}" SizeZ="{nz}" SizeC="{}" SizeT="1" PhysicalSizeX="1000" PhysicalSizeY="1000" PhysicalSizeZ="1000">{tiff_data}</Pixels></Image></OME>"#,
        channels.len()
    );
    let pointer = format!(r#"<OME><BinaryOnly MetadataFile="{xml_file}"/></OME>"#);
    for f in 0..3 {
        let file = std::fs::File::create(dir.join(names[f])).unwrap();
        let mut e = TiffEncoder::new(file).unwrap();
        for (k, plane) in planes[cut[f]..cut[f + 1]].iter().enumerate() {
            let mut image = e.new_image::<Gray32Float>(nx as u32, ny as u32).unwrap();
            if k == 0 {
                let desc = if names[f] == xml_file { &xml } else { &pointer };
                let tag = tiff::tags::Tag::ImageDescription;
                image.encoder().write_tag(tag, desc.as_str()).unwrap();
            }
            image.write_data(plane).unwrap();
        }
    }
    if !names.contains(&xml_file) {
        std::fs::write(dir.join(xml_file), &xml).unwrap();
    }
    dir.join(xml_file)
}

/// `compress` reads a channel of a multi-file OME-TIFF, from the file holding its XML or from
/// its OME companion file, as it reads the same samples in a NIfTI file: the same file, byte
/// for byte, whole and in bricks (each brick's slices read from whichever file holds them); a
/// part given alone is refused, naming the file to read.
#[test]
fn a_channel_of_a_multi_file_ome_tiff_compresses_as_that_channel_in_nifti() {
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path();
    let dims = [17, 13, 11];
    let channels: Vec<Vec<f32>> = [Phantom::SheppLogan, Phantom::Blobs]
        .iter()
        .map(|p| p.generate(dims).channel(0).to_vec())
        .collect();
    let mut inputs = Vec::new();
    for (dir, xml_file) in [
        ("holder", "acq.ome.tif"),
        ("companion", "set.companion.ome"),
    ] {
        std::fs::create_dir_all(d.join(dir)).unwrap();
        inputs.push(write_multi_file_ome(
            &d.join(dir),
            dims,
            &channels,
            xml_file,
        ));
    }
    for c in 0..2 {
        let nii = d.join(format!("c{c}.nii"));
        write_nifti(&nii, dims, &channels[c]);
        for bricks in [&[][..], &["--brick", "8"][..]] {
            let ext = if bricks.is_empty() { "wsp" } else { "wspx" };
            let mut outputs = Vec::new();
            let c_arg = c.to_string();
            for input in inputs.iter().chain([&nii]) {
                let out = d.join(format!("{c}-{}.{ext}", outputs.len()));
                let mut args = vec![
                    "compress",
                    input.to_str().unwrap(),
                    "-o",
                    out.to_str().unwrap(),
                ];
                if input != &nii {
                    args.extend(["--channel", c_arg.as_str()]);
                }
                args.extend_from_slice(bricks);
                cli_ok(&args);
                outputs.push(std::fs::read(&out).unwrap());
            }
            assert!(
                outputs[0] == outputs[2] && outputs[1] == outputs[2],
                "channel {c} {bricks:?}: the OME-TIFF's file differs from the NIfTI's"
            );
        }
    }
    let part = d.join("holder/acq_1.ome.tif");
    let o = cli(&[
        "compress",
        part.to_str().unwrap(),
        "--channel",
        "0",
        "-o",
        d.join("p.wsp").to_str().unwrap(),
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && err.contains("read from acq.ome.tif"),
        "{err}"
    );
}

/// `compress` reads a Zarr array as it reads the same samples in a NIfTI file: the same file,
/// byte for byte, whole and in bricks read chunk by chunk; and a Zarr array with a time axis
/// as the same series a 4D NIfTI holds.
#[test]
fn a_zarr_array_compresses_as_the_same_samples_in_nifti() {
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path();
    let v = Phantom::SheppLogan.generate([21, 19, 17]);
    write_zarr(&d.join("v.zarr"), &v, [8, 8, 8], false);
    write_nifti(&d.join("v.nii"), v.dims(), v.channel(0));
    for bricks in [&[][..], &["--brick", "8"][..]] {
        let mut outputs = Vec::new();
        for input in ["v.zarr", "v.nii"] {
            let out = d.join(format!(
                "{input}.{}",
                if bricks.is_empty() { "wsp" } else { "wspx" }
            ));
            let mut args = vec![
                "compress".to_string(),
                d.join(input).to_str().unwrap().into(),
            ];
            args.extend(["-o".into(), out.to_str().unwrap().into()]);
            args.extend(bricks.iter().map(|s| s.to_string()));
            let args: Vec<&str> = args.iter().map(String::as_str).collect();
            cli_ok(&args);
            outputs.push(std::fs::read(&out).unwrap());
        }
        assert!(
            outputs[0] == outputs[1],
            "{bricks:?}: the Zarr array's file differs"
        );
    }
    // Two time points, z, y, x each, one chunk each (the Zarr v2 layout, uncompressed).
    let series = d.join("s.zarr");
    std::fs::create_dir_all(&series).unwrap();
    let [nx, ny, nz] = v.dims();
    std::fs::write(
        series.join(".zarray"),
        format!(
            r#"{{"zarr_format": 2, "shape": [2, {nz}, {ny}, {nx}], "chunks": [1, {nz}, {ny}, {nx}],
                "dtype": "<f4", "compressor": null, "fill_value": 0.0, "order": "C",
                "filters": null}}"#
        ),
    )
    .unwrap();
    let points: Vec<Vec<f32>> = (0..2)
        .map(|t| v.channel(0).iter().map(|s| s + 100.0 * t as f32).collect())
        .collect();
    for (t, p) in points.iter().enumerate() {
        let bytes: Vec<u8> = p.iter().flat_map(|s| s.to_le_bytes()).collect();
        std::fs::write(series.join(format!("{t}.0.0.0")), bytes).unwrap();
    }
    wavesplat_fixtures::write_nifti_series(&d.join("s.nii"), v.dims(), &points, None, false);
    let mut outputs = Vec::new();
    for input in ["s.zarr", "s.nii"] {
        let out = d.join(format!("{input}.wsp"));
        cli_ok(&[
            "compress",
            d.join(input).to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
        ]);
        let info = cli_ok(&["info", out.to_str().unwrap()]);
        assert!(info.contains("time points 2"), "{input}: {info}");
        outputs.push(std::fs::read(&out).unwrap());
    }
    assert!(outputs[0] == outputs[1], "the Zarr series' file differs");
}
