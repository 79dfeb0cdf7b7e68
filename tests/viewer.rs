//! The client side end to end: a cache on loopback (in process, sled in a tempdir), volumes
//! rendered from it by the render session through the cache source, compared with the same
//! volume rendered from its file; a view change and a cache restart mid-stream; the memory
//! bound over the network; and `wavesplat render --cache` against `wavesplat render FILE` (one
//! pass) and `wavesplat render FILE --progressive` (the frame loop).

mod common;

use std::time::{Duration, Instant};
use wavesplat_cache::Limits;
use wavesplat_client::{CacheClient, VolumeKey};
use wavesplat_codec::format::packet::{decode_packet, Coefficient};
use wavesplat_codec::format::{parse_file, Header};
use wavesplat_codec::view::{View, ViewSpec};
use wavesplat_compressor::encode::CompressOptions;
use wavesplat_compressor::phantom::Phantom;
use wavesplat_harness::LocalCache;
use wavesplat_viewer::session::{RenderSession, SessionOptions, COEFFICIENT_BYTES};
use wavesplat_viewer::source::{CacheSource, CacheSourceOptions, FileSource, PacketSource};
use wavesplat_viewer::{CpuBackend, FrameLoop, Image};

fn wsp(phantom: Phantom, n: usize) -> Vec<u8> {
    let options = CompressOptions {
        layers: Some(3),
        ..common::phantom_options(0.08)
    };
    common::phantom_file(phantom, [n; 3], &options)
}

fn all(bytes: &[u8]) -> (Header, Vec<Coefficient>) {
    let file = parse_file(bytes).unwrap();
    let c = file
        .packets
        .iter()
        .flat_map(|p| decode_packet(&file.header, p).unwrap().coefficients)
        .collect();
    (file.header, c)
}

/// Adds `bytes` as `name` to the cache at `url`.
fn ingest(url: &str, name: &str, bytes: &[u8]) {
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    rt.block_on(async {
        let mut c = CacheClient::connect(url).await.unwrap();
        c.ingest(name, bytes).await.unwrap();
    });
}

/// Adds every packet the source delivers (waiting for the network) until it is done.
fn drain<S: PacketSource + ?Sized>(
    source: &mut S,
    session: &mut RenderSession<CpuBackend>,
) -> usize {
    let start = Instant::now();
    let mut n = 0;
    loop {
        match source.try_next() {
            Some(p) => {
                session.add_packet(p.id, &p.data).unwrap();
                n += 1;
            }
            None if source.status().done => {
                // Done is set after the last packet is queued: one more look.
                if let Some(p) = source.try_next() {
                    session.add_packet(p.id, &p.data).unwrap();
                    n += 1;
                    continue;
                }
                return n;
            }
            None => std::thread::sleep(Duration::from_millis(1)),
        }
        assert!(start.elapsed() < Duration::from_secs(60), "stream stalled");
    }
}

#[test]
fn rendering_from_the_cache_equals_rendering_from_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let server = LocalCache::start(dir.path()).unwrap();
    for (name, phantom, n) in [
        ("shepp", Phantom::SheppLogan, 40),
        ("rgb", Phantom::RgbHead, 32),
    ] {
        let bytes = wsp(phantom, n);
        ingest(&server.url, name, &bytes);
        let (header, coeffs) = all(&bytes);
        for spec in [
            ViewSpec::single(View::new(0.66, 0.91, 80, 64)),
            ViewSpec {
                view: View::new(0.2, 0.1, 48, 48),
                multiview: true,
            },
        ] {
            let unlimited = SessionOptions {
                max_batch: usize::MAX,
                ..Default::default()
            };
            let mut images = Vec::new();
            let (mut cache_source, h) = CacheSource::open(
                &server.url,
                VolumeKey::Name(name.into()),
                spec,
                CacheSourceOptions::default(),
            )
            .unwrap();
            assert_eq!(h.header, header);
            let mut file_source = FileSource::open(bytes.clone(), &spec).unwrap();
            for source in [&mut cache_source as &mut dyn PacketSource, &mut file_source] {
                let mut s =
                    RenderSession::new(header.clone(), spec, CpuBackend::new(), unlimited).unwrap();
                let got = drain(source, &mut s);
                assert_eq!(got, file_source_count(&bytes), "{name}: packets delivered");
                // One batch with everything: the same records in the same order, but for the
                // pieces clipped at the box's faces, which wait for their factor tables (built
                // in the background) and are drawn when they arrive.
                s.step(Duration::from_secs(3600)).unwrap();
                let start = Instant::now();
                while s.pending() > 0 {
                    assert_eq!(s.pending(), s.waiting_for_tables());
                    assert!(
                        start.elapsed() < Duration::from_secs(120),
                        "no factor tables"
                    );
                    std::thread::sleep(Duration::from_millis(5));
                    s.step(Duration::from_secs(3600)).unwrap();
                }
                images.push(s.image().unwrap());
            }
            // The pieces waiting for tables are added in the order their tables arrive: f32
            // sums in another order (a packet missing or twice is far above this).
            let e = images[0].relative_difference(&images[1]);
            assert!(
                e <= 1e-5,
                "{name} multiview={}: cache vs file {e:e}",
                spec.multiview
            );
            let e = images[1].relative_difference(
                &wavesplat_viewer::open::display_image(&header, &coeffs, &spec).unwrap(),
            );
            assert!(e <= 1e-5, "{name}: file vs one-shot {e:e}");
        }
    }
}

fn file_source_count(bytes: &[u8]) -> usize {
    parse_file(bytes).unwrap().packets.len()
}

#[test]
fn a_view_change_and_a_cache_restart_mid_stream_lose_nothing_and_repeat_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let server = LocalCache::start(dir.path()).unwrap();
    let bytes = wsp(Phantom::SheppLogan, 48);
    ingest(&server.url, "v", &bytes);
    let (header, coeffs) = all(&bytes);
    let total = file_source_count(&bytes);
    let (a, b) = (
        ViewSpec::single(View::new(0.0, 0.0, 64, 64)),
        ViewSpec::single(View::new(1.2, 0.4, 64, 64)),
    );
    let options = CacheSourceOptions {
        credit_bytes: 2048,
        ..Default::default()
    };
    let (source, _) =
        CacheSource::open(&server.url, VolumeKey::Name("v".into()), a, options).unwrap();
    let session =
        RenderSession::new(header.clone(), a, CpuBackend::new(), Default::default()).unwrap();
    let mut f = FrameLoop::new(session, source);
    let mut seen = std::collections::HashSet::new();
    let mut take = |f: &mut FrameLoop<CpuBackend, CacheSource>, n: usize| {
        let start = Instant::now();
        let mut got = 0;
        while got < n {
            match f.source.try_next() {
                Some(p) => {
                    assert!(seen.insert(p.id), "packet {} received twice", p.id);
                    // The cache source decodes on its own thread: what it hands over is what
                    // decoding the bytes gives.
                    let d = decode_packet(&header, &p.data).unwrap();
                    assert_eq!(
                        p.decoded,
                        Some((d.tile, d.coefficients)),
                        "packet {} arrives decoded",
                        p.id
                    );
                    f.session.add_packet(p.id, &p.data).unwrap();
                    got += 1;
                }
                None if f.source.status().done && got > 0 => break,
                None => std::thread::sleep(Duration::from_millis(1)),
            }
            assert!(
                start.elapsed() < Duration::from_secs(60),
                "stalled at {got}"
            );
        }
    };
    take(&mut f, total / 4);
    f.set_view(b).unwrap();
    take(&mut f, total / 4);
    // Restart the cache on the same address: the source reconnects and resumes.
    let (dir_path, addr) = (server.dir().to_path_buf(), server.addr.to_string());
    server.stop().unwrap();
    let server = LocalCache::start_with(&dir_path, &addr, Limits::default()).unwrap();
    take(&mut f, total);
    assert_eq!(seen.len(), total, "every packet exactly once");
    assert!(f.source.status().reconnects >= 1);
    while f.session.pending() > 0 {
        f.session.step(Duration::from_secs(60)).unwrap();
    }
    let e =
        f.session.image().unwrap().relative_difference(
            &wavesplat_viewer::open::display_image(&header, &coeffs, &b).unwrap(),
        );
    assert!(e <= 1e-5, "{e:e}");
    drop(f);
    drop(server);
}

#[test]
fn the_memory_bound_holds_over_the_network() {
    let dir = tempfile::tempdir().unwrap();
    let server = LocalCache::start(dir.path()).unwrap();
    let bytes = wsp(Phantom::SheppLogan, 56);
    ingest(&server.url, "big", &bytes);
    let (header, coeffs) = all(&bytes);
    let bound = coeffs.len() * COEFFICIENT_BYTES / 5;
    let (a, b) = (
        ViewSpec::single(View::new(0.66, 0.91, 64, 64)),
        ViewSpec::single(View::new(2.0, -0.3, 64, 64)),
    );
    let options = SessionOptions {
        memory_bound: Some(bound),
        transient_bytes: 32 << 10,
        ..Default::default()
    };
    let (source, _) = CacheSource::open(
        &server.url,
        VolumeKey::Name("big".into()),
        a,
        CacheSourceOptions::default(),
    )
    .unwrap();
    let session = RenderSession::new(header.clone(), a, CpuBackend::new(), options).unwrap();
    let mut f = FrameLoop::new(session, source);
    for spec in [a, b] {
        if spec != a {
            f.set_view(spec).unwrap();
        }
        let start = Instant::now();
        loop {
            let r = f.frame(Duration::from_millis(10)).unwrap();
            assert!(f.session.stats().retained_bytes <= bound);
            if r.idle() && f.source.status().done {
                // Done, and nothing arrived after the frame took its packets (one that did is
                // taken in, not dropped).
                match f.source.try_next() {
                    None => break,
                    Some(p) => f.session.add_from_source(p).unwrap(),
                }
            }
            if r.idle() {
                std::thread::sleep(Duration::from_millis(1));
            }
            assert!(start.elapsed() < Duration::from_secs(120), "stalled");
        }
        let e = f.session.image().unwrap().relative_difference(
            &wavesplat_viewer::open::display_image(&header, &coeffs, &spec).unwrap(),
        );
        assert!(e <= 1e-5, "{e:e}");
    }
    assert!(f.session.stats().packets_dropped > 0);
}

#[test]
fn the_render_command_gives_the_same_image_from_the_cache_and_from_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let server = LocalCache::start(&dir.path().join("db")).unwrap();
    let bytes = wsp(Phantom::RgbHead, 32);
    let file = dir.path().join("v.wsp");
    std::fs::write(&file, &bytes).unwrap();
    ingest(&server.url, "head", &bytes);
    let bin = env!("CARGO_BIN_EXE_wavesplat");
    let raw = |args: &[&str], out: &str| -> (Vec<f32>, String) {
        let png = dir.path().join(format!("{out}.png"));
        let raw = dir.path().join(format!("{out}.f32"));
        let o = std::process::Command::new(bin)
            .arg("render")
            .args(args)
            .args(["--size", "64x48", "--alpha", "0.3", "--beta", "0.2", "-o"])
            .arg(&png)
            .arg("--raw")
            .arg(&raw)
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let data = std::fs::read(&raw)
            .unwrap()
            .chunks(4)
            .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
            .collect();
        let said = String::from_utf8_lossy(&o.stdout).into_owned();
        (data, said + &String::from_utf8_lossy(&o.stderr))
    };
    // A whole local file is drawn in one pass, and (no backend asked for) on the CPU without
    // probing for a GPU: the render is done before a device would be open. --progressive
    // takes the frame loop, as the cache's stream always does.
    let (from_file, said) = raw(&[file.to_str().unwrap()], "file");
    assert!(said.contains("in one pass"), "{said}");
    assert!(
        said.contains("drawn on the CPU before a GPU device would be open"),
        "{said}"
    );
    let (progressive, said) = raw(&[file.to_str().unwrap(), "--progressive"], "frames");
    assert!(said.contains("frames in"), "{said}");
    let (from_cache, _) = raw(&["--cache", &server.url, "--volume", "head"], "cache");
    let to_image = |d: Vec<f32>| Image {
        width: 64,
        height: 48,
        channels: 3,
        data: d,
    };
    let from_file = to_image(from_file);
    // Frames group the splats by timing, so the sums agree to f32 rounding.
    let e = to_image(from_cache).relative_difference(&from_file);
    assert!(e <= 1e-5, "{e:e}");
    let e = to_image(progressive).relative_difference(&from_file);
    assert!(e <= 1e-5, "{e:e}");
}

/// A cache source with a byte budget stops within it, in order, and is done; a view set after
/// the budget is spent is done too (nothing more will come), instead of waiting for a `done`
/// from a stream it no longer reads.
#[test]
fn a_byte_budget_ends_the_stream_and_a_later_view_change_is_done_at_once() {
    let dir = tempfile::tempdir().unwrap();
    let server = LocalCache::start(dir.path()).unwrap();
    let bytes = wsp(Phantom::SheppLogan, 48);
    ingest(&server.url, "v", &bytes);
    let total_bytes: u64 = parse_file(&bytes)
        .unwrap()
        .packets
        .iter()
        .map(|p| p.len() as u64)
        .sum();
    let budget = total_bytes / 4;
    let a = ViewSpec::single(View::new(0.3, 0.2, 64, 64));
    let options = CacheSourceOptions {
        credit_bytes: 2048,
        byte_budget: Some(budget),
        ..Default::default()
    };
    let (mut source, header) =
        CacheSource::open(&server.url, VolumeKey::Name("v".into()), a, options).unwrap();
    let mut session =
        RenderSession::new(header.header, a, CpuBackend::new(), Default::default()).unwrap();
    let n = drain(&mut source, &mut session);
    let status = source.status();
    assert!(n > 0 && status.done, "{status:?}");
    assert!(
        status.bytes <= budget + 2048,
        "{} bytes for a budget of {budget}",
        status.bytes
    );
    source.set_view(&ViewSpec::single(View::new(1.2, 0.4, 64, 64)));
    let start = Instant::now();
    while !source.status().done {
        assert!(
            start.elapsed() < Duration::from_secs(10),
            "a view set after the budget was spent never finished: {:?}",
            source.status()
        );
        std::thread::sleep(Duration::from_millis(5));
    }
    assert!(source.try_next().is_none());
}

/// A view magnified beyond `--max-pixels-per-voxel` (here 40 pixels a voxel against the default
/// bound of 16) is drawn at the bound and magnified back: the image written has the size asked
/// for, says so, and holds to the exact line integrals (the ray caster on the file's
/// coefficients) within the splats' accuracy standard, for every family, on a phantom whose
/// edges are as sharp as its voxels; the frame loop and multiview's first panel give the
/// same image as one pass.
#[test]
fn a_magnified_view_is_drawn_at_the_bound_and_holds_to_the_line_integrals() {
    use wavesplat_codec::family::Family;
    use wavesplat_viewer::{render_reference, PaddedVolume, ReferenceOptions};
    let dir = tempfile::tempdir().unwrap();
    let snr = |reference: &[f32], image: &[f32]| -> f64 {
        assert_eq!(reference.len(), image.len());
        let (mut signal, mut noise) = (0.0f64, 0.0f64);
        for (r, i) in reference.iter().zip(image) {
            signal += f64::from(*r) * f64::from(*r);
            noise += (f64::from(*r) - f64::from(*i)).powi(2);
        }
        10.0 * (signal / noise.max(1e-300)).log10()
    };
    let (w, h) = (200, 160);
    // Measured: every pixel drawn 87 / 78 / 78 dB, bounded to 16 pixels a voxel 63.3 / 58.5 /
    // 50.7 dB (to 8: 52.8 / 49.7 / 41.4).
    for (family, levels, floor_db) in [
        (Family::Linear, 2, 60.0),
        (Family::Cubic, 2, 55.0),
        (Family::Haar, 3, 48.0),
    ] {
        let options = CompressOptions {
            family,
            levels: Some(levels),
            ..common::phantom_options(0.2)
        };
        let bytes = common::phantom_file(Phantom::SheppLogan, [24, 28, 20], &options);
        let file = dir.path().join(format!("{family:?}.wsp"));
        std::fs::write(&file, &bytes).unwrap();
        let (header, coeffs) = all(&bytes);
        let volume = PaddedVolume::from_coefficients(&coeffs, &header.geometry, 1).unwrap();
        let view = View::new(0.4, 0.3, w, h)
            .with_zoom(40.0)
            .with_pan([1.5, -2.0]);
        let exact = ReferenceOptions {
            supersample: 4,
            step: 0.05,
        };
        let reference = render_reference(&volume, &view, &exact).unwrap();
        let draw = |extra: &[&str], tag: &str| -> (Vec<f32>, String) {
            let raw = dir.path().join(format!("{family:?}-{tag}.f32"));
            let size = format!("{w}x{h}");
            let mut args = vec![
                file.to_str().unwrap(),
                "--cpu",
                "--size",
                &size,
                "--zoom",
                "40",
                "--pan",
                "1.5,-2",
                "--alpha",
                "0.4",
                "--beta",
                "0.3",
                "-o",
                "out.png",
                "--raw",
                raw.to_str().unwrap(),
            ];
            args.extend_from_slice(extra);
            let o = common::render_in(dir.path(), &args);
            assert!(o.status.success(), "{}", common::text(&o));
            (common::read_f32(&raw), common::text(&o))
        };
        let (every, said) = draw(&["--max-pixels-per-voxel", "0"], "every");
        assert!(!said.contains("drawn at"), "{said}");
        let every_db = snr(&reference.data, &every);
        assert!(
            every_db >= 75.0,
            "{family:?}: every pixel drawn {every_db:.1} dB"
        );
        // 40 pixels a voxel bounded to 16: drawn at 80 × 64, magnified 2.5 times.
        let (bounded, said) = draw(&[], "bounded");
        assert!(said.contains("drawn at 80x64 and magnified"), "{said}");
        let db = snr(&reference.data, &bounded);
        assert!(db >= floor_db, "{family:?}: bounded {db:.1} dB");
        let (frames, said) = draw(&["--progressive"], "frames");
        assert!(said.contains("drawn at 80x64"), "{said}");
        // The frame loop sums the splats in other groups: equal to f32 rounding (cubic's
        // wide footprints sum the most terms a pixel).
        let e = common::relative_difference(&bounded, &frames);
        assert!(e <= 1e-4, "{family:?}: frame loop against one pass {e:e}");
        let (multiview, said) = draw(&["--multiview"], "multiview");
        assert!(said.contains("drawn at 240x64"), "{said}");
        assert_eq!(multiview.len(), 3 * w * h);
        let first: Vec<f32> = multiview
            .chunks(3 * w)
            .flat_map(|row| row[..w].iter().copied())
            .collect();
        let e = common::relative_difference(&bounded, &first);
        assert!(e <= 1e-5, "{family:?}: multiview's first panel {e:e}");
    }
}
