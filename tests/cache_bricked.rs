//! Bricked volumes in a cache node (embedded store): ingested as one volume (the container read
//! front to back, every brick checked), kept across a restart, streamed by `Refine` with its
//! bricks' headers and its packets ranked across bricks, and drawn by `render --cache` as the
//! local file is drawn (multiview too); a view zoomed into one corner is sent the packets of
//! the bricks it sees and no other, read on the wire by a plain client; damaged uploads are
//! refused naming the brick.

mod common;

use common::{read_f32, text};
use std::process::Command;
use wavesplat_cache::{CacheError, Limits, Store};
use wavesplat_client::{CacheClient, RefineRequest, VolumeKey};
use wavesplat_codec::format::bricked::{parse_bricked, write_bricked};
use wavesplat_codec::view::bricked::BrickedVisibility;
use wavesplat_codec::view::{View, ViewSpec};
use wavesplat_compressor::phantom::Phantom;
use wavesplat_harness::LocalCache;

const BIN: &str = env!("CARGO_BIN_EXE_wavesplat");

/// An 80×72×64 Shepp–Logan phantom in bricks of 40 (eight bricks).
fn bricked_file() -> Vec<u8> {
    let volume = Phantom::SheppLogan.generate([80, 72, 64]);
    wavesplat_compressor::bricked::compress_bricked(
        &volume,
        &common::phantom_options(0.2),
        40,
        &|_| {},
    )
    .unwrap()
    .bytes
}

/// A 32² view along −z zoomed into one corner of the whole (the `render` arguments of the
/// first test's "corner").
fn corner_view() -> ViewSpec {
    ViewSpec::single(
        View::new(
            -std::f64::consts::FRAC_PI_2,
            -std::f64::consts::FRAC_PI_2,
            32,
            32,
        )
        .with_zoom(4.0)
        .with_pan([-20.0, 18.0]),
    )
}

use common::{render_in as render, runtime};

/// `render --cache` of a bricked volume ends at the local file's progressive image: the whole
/// volume, a view zoomed into one corner, a near-axis view and a depth-cued one.
#[test]
fn a_bricked_volume_renders_from_the_cache_as_from_its_file() {
    let wsp = bricked_file();
    let tmp = tempfile::tempdir().unwrap();
    std::fs::write(tmp.path().join("b.wsp"), &wsp).unwrap();
    let server = LocalCache::start(&tmp.path().join("db")).unwrap();
    let ingest = Command::new(BIN)
        .args([
            "cache",
            "ingest",
            "b.wsp",
            "--name",
            "big",
            "--cache",
            &server.url,
        ])
        .current_dir(tmp.path())
        .output()
        .unwrap();
    assert!(ingest.status.success(), "{}", text(&ingest));
    let show = Command::new(BIN)
        .args(["cache", "show", "big", "--cache", &server.url])
        .output()
        .unwrap();
    assert!(
        String::from_utf8_lossy(&show.stdout).contains("bricks      8"),
        "{}",
        text(&show)
    );
    let views: [(&str, &[&str]); 5] = [
        ("whole", &["--size", "64x48"]),
        (
            "corner",
            &[
                "--alpha=-1.5707963267948966",
                "--beta=-1.5707963267948966",
                "--zoom",
                "4",
                "--pan=-20,18",
                "--size",
                "32x32",
            ],
        ),
        (
            "near-axis",
            &["--alpha", "1e-7", "--beta", "1.5707962", "--size", "40x40"],
        ),
        (
            "cued",
            &[
                "--alpha", "0.5", "--beta", "0.3", "--cue-k", "0.2", "--size", "48x48",
            ],
        ),
        // The node ranks each brick by what any panel sees of it.
        (
            "multiview",
            &[
                "--multiview",
                "--alpha",
                "0.4",
                "--beta",
                "0.3",
                "--size",
                "40x32",
            ],
        ),
    ];
    for (name, view) in views {
        let cached = format!("{name}-cache.f32");
        let local = format!("{name}-local.f32");
        let mut args = vec![
            "--cache",
            &server.url,
            "--volume",
            "big",
            "--cpu",
            "-o",
            "c.png",
            "--raw",
            &cached,
        ];
        args.extend_from_slice(view);
        let out = render(tmp.path(), &args);
        assert!(out.status.success(), "{name}: {}", text(&out));
        let mut args = vec![
            "b.wsp",
            "--cpu",
            "--progressive",
            "-o",
            "l.png",
            "--raw",
            &local,
        ];
        args.extend_from_slice(view);
        let out = render(tmp.path(), &args);
        assert!(out.status.success(), "{name}: {}", text(&out));
        let (c, l) = (
            read_f32(&tmp.path().join(&cached)),
            read_f32(&tmp.path().join(&local)),
        );
        assert!(l.iter().any(|v| *v != 0.0), "{name}: the image is empty");
        let snr = wavesplat_codec::metrics::snr_db(&l, &c);
        assert!(snr > 90.0, "{name}: cache against file {snr:.1} dB");
    }
}

/// Read on the wire by a plain client: the header message carries every brick's header and
/// the packets are numbered brick after brick; the whole view is sent every packet once; a view
/// zoomed into one corner is sent packets of the bricks it sees only, and fewer than half.
#[test]
fn a_view_of_one_corner_is_sent_only_the_bricks_it_sees() {
    let wsp = bricked_file();
    let manifest = parse_bricked(&wsp).unwrap().manifest;
    let tmp = tempfile::tempdir().unwrap();
    let server = LocalCache::start(tmp.path()).unwrap();
    let rt = runtime();
    let mut c = rt.block_on(CacheClient::connect(&server.url)).unwrap();
    rt.block_on(c.ingest("big", &wsp)).unwrap();
    let whole = ViewSpec::single(View::new(0.4, 0.3, 48, 48));
    let all = rt
        .block_on(c.refine_collect(
            RefineRequest::new(VolumeKey::Name("big".into()), whole),
            None,
        ))
        .unwrap();
    assert!(all.done);
    let header = all.header.expect("the header comes first");
    assert_eq!(header.bricks.len(), manifest.bricks.len());
    assert_eq!(
        header.header.geometry.dims,
        manifest.dims.map(|d| d as usize),
        "the header is the whole's"
    );
    let total: u32 = header.bricks.iter().map(|b| b.packets).sum();
    assert_eq!(total, header.info.packet_count);
    let mut ids: Vec<u32> = all.packets.iter().map(|p| p.id).collect();
    ids.sort_unstable();
    assert_eq!(ids, (0..total).collect::<Vec<_>>(), "every packet once");

    let corner = corner_view();
    let bricks: Vec<_> = header
        .bricks
        .iter()
        .map(|b| (&b.header, b.origin))
        .collect();
    let seen = BrickedVisibility::new(&corner, &header.header.geometry, &bricks).unwrap();
    let seen_bricks: Vec<usize> = (0..bricks.len()).filter(|&b| seen.sees(b)).collect();
    assert!(
        !seen_bricks.is_empty() && seen_bricks.len() <= 2,
        "the corner sees bricks {seen_bricks:?}"
    );
    let brick_of = |id: u32| {
        let mut first = 0;
        for (k, b) in header.bricks.iter().enumerate() {
            if id < first + b.packets {
                return k;
            }
            first += b.packets;
        }
        panic!("packet {id} past the last brick")
    };
    for visible_only in [false, true] {
        let request =
            RefineRequest::new(VolumeKey::Name("big".into()), corner).visible_only(visible_only);
        let got = rt.block_on(c.refine_collect(request, None)).unwrap();
        assert!(got.done);
        assert!(!got.packets.is_empty());
        for p in &got.packets {
            let b = brick_of(p.id);
            assert!(
                seen_bricks.contains(&b),
                "packet {} of brick {b} sent for a view that sees only {seen_bricks:?}",
                p.id
            );
        }
        assert!(got.packets.len() < total as usize / 2);
    }
}

/// The store at `path` opened again after its last handle was dropped. sled's lock on the
/// directory is released by its background flusher shortly after the drop, not at it (a
/// reopen at once failed once in a full CI run with "could not acquire lock … WouldBlock"),
/// so a lock refusal is retried for up to 10 s; any other error fails at once.
fn reopen(path: &std::path::Path) -> Store {
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(10);
    loop {
        match Store::open(path, Limits::default()) {
            Ok(store) => return store,
            Err(e)
                if format!("{e:?}").contains("WouldBlock")
                    && std::time::Instant::now() < deadline =>
            {
                std::thread::sleep(std::time::Duration::from_millis(50));
            }
            Err(e) => panic!("reopening the store: {e:?}"),
        }
    }
}

/// The store keeps a bricked volume across a restart (the same bricks, headers and packets);
/// damaged, cut or padded uploads are refused, naming what is wrong, and leave nothing behind.
#[test]
fn the_store_keeps_bricked_volumes_and_refuses_damaged_ones() {
    let wsp = bricked_file();
    let file = parse_bricked(&wsp).unwrap();
    let tmp = tempfile::tempdir().unwrap();
    let (volume, packets) = {
        let store = Store::open(tmp.path(), Limits::default()).unwrap();
        let v = store.ingest("big", &wsp, None).unwrap().volume;
        assert_eq!(v.dims, [80, 72, 64]);
        assert_eq!(v.coefficients, file.manifest.kept());
        assert_eq!(v.file_bytes, wsp.len() as u64);
        (v.id, store.index(v.id).unwrap().packets.len())
    };
    let store = reopen(tmp.path());
    let index = store.index(volume).unwrap();
    let b = index
        .bricked
        .as_ref()
        .expect("still bricked after a restart");
    assert_eq!(b.bricks.len(), 8);
    assert_eq!(index.packets.len(), packets);
    let mut next = 0;
    for (k, brick) in b.bricks.iter().enumerate() {
        let entry = &file.manifest.bricks[k];
        assert_eq!(brick.origin, entry.origin);
        assert_eq!(brick.first_packet, next);
        assert_eq!(brick.header.geometry.dims, entry.dims);
        next += brick.packets;
        // Each packet lies inside its brick's bytes and reads back as stored.
        for id in brick.first_packet..next {
            let p = &index.packets[id as usize];
            assert!(
                p.offset >= entry.offset
                    && p.offset + u64::from(p.len) <= entry.offset + entry.length
            );
            assert_eq!(index.brick_of(id), k);
            let bytes = store.packet(volume, id).unwrap();
            assert_eq!(
                bytes,
                wsp[p.offset as usize..(p.offset + u64::from(p.len)) as usize]
            );
        }
    }
    assert_eq!(next as usize, packets);

    let before = store.data_bytes().unwrap();
    let last = file.manifest.bricks.last().unwrap();
    let mut damaged = wsp.clone();
    // A byte inside the last brick's packets: its CRC (or its packet) no longer matches.
    damaged[(last.offset + last.length - 3) as usize] ^= 0x10;
    let mut padded = wsp.clone();
    padded.push(0);
    // A container whose first brick has no bytes (its manifest otherwise consistent).
    let mut manifest = file.manifest.clone();
    let mut bricks: Vec<&[u8]> = (0..manifest.bricks.len())
        .map(|i| file.brick_bytes(i).unwrap())
        .collect();
    bricks[0] = &[];
    let empty_brick = write_bricked(&mut manifest, &bricks).unwrap();
    for (name, bytes, expect) in [
        ("damaged", &damaged[..], "brick 7"),
        ("cut", &wsp[..wsp.len() - 10], "brick"),
        ("cut-in-manifest", &wsp[..40], "upload ends"),
        ("padded", &padded[..], "bricks end at byte"),
        ("empty-brick", &empty_brick[..], "brick 0 is empty"),
    ] {
        let e = store.ingest(name, bytes, None).unwrap_err();
        assert!(
            matches!(e, CacheError::InvalidUpload(_) | CacheError::Format(_))
                && format!("{e}: {e:?}").contains(expect),
            "{name}: {e}"
        );
        assert!(store.describe(&VolumeKey::Name(name.into())).is_err());
    }
    assert_eq!(store.data_bytes().unwrap(), before, "nothing left behind");
}

/// Nodes over an object store (`serve cache --store file://…`) keep a bricked volume in the
/// published layout and serve it as a node with its own store does: the same manifest, brick
/// headers and packets (for the corner: only its bricks'), from the node that ingested it and
/// from a cold node over the same store.
#[test]
fn nodes_over_an_object_store_serve_bricked_volumes_alike() {
    let wsp = bricked_file();
    let tmp = tempfile::tempdir().unwrap();
    let path = |p: &str| tmp.path().join(p).to_str().unwrap().to_string();
    let store_url = format!("file://{}", path("bucket"));
    let (mut own, own_url) = common::spawn_server(&[
        "serve",
        "cache",
        "--addr",
        "127.0.0.1:0",
        "--db",
        &path("own"),
    ]);
    let (mut first, first_url) = common::spawn_server(&[
        "serve",
        "cache",
        "--addr",
        "127.0.0.1:0",
        "--db",
        &path("n1"),
        "--store",
        &store_url,
    ]);
    let rt = runtime();
    for url in [&own_url, &first_url] {
        let mut c = rt.block_on(CacheClient::connect(url)).unwrap();
        rt.block_on(c.ingest("big", &wsp)).unwrap();
    }
    let (mut cold, cold_url) = common::spawn_server(&[
        "serve",
        "cache",
        "--addr",
        "127.0.0.1:0",
        "--db",
        &path("n2"),
        "--store",
        &store_url,
    ]);
    let corner = corner_view();
    for spec in [ViewSpec::single(View::new(0.4, 0.3, 48, 48)), corner] {
        let collect = |url: &str| {
            let mut c = rt.block_on(CacheClient::connect(url)).unwrap();
            let request = RefineRequest::new(VolumeKey::Name("big".into()), spec);
            let got = rt.block_on(c.refine_collect(request, None)).unwrap();
            assert!(got.done, "{url}");
            let h = got.header.expect("a header");
            let bricks: Vec<(Vec<u8>, [u64; 3], u32)> = h
                .bricks
                .iter()
                .map(|b| (format!("{:?}", b.header).into_bytes(), b.origin, b.packets))
                .collect();
            let packets: Vec<(u32, Vec<u8>)> =
                got.packets.into_iter().map(|p| (p.id, p.data)).collect();
            (h.bytes, h.info.packet_count, bricks, packets)
        };
        let reference = collect(&own_url);
        assert_eq!(reference.2.len(), 8);
        assert!(!reference.3.is_empty());
        for url in [&first_url, &cold_url] {
            let got = collect(url);
            assert_eq!(got.0, reference.0, "{url}: the manifest section");
            assert_eq!(got.1, reference.1, "{url}: the packet count");
            assert!(got.2 == reference.2, "{url}: the bricks");
            // The same packets with the same bytes (their order may differ among near ties:
            // the published layout keeps packet energies in bfloat16, a node's own store in
            // f64; and how many go out in file order before the view is planned is timing).
            let sorted = |v: &[(u32, Vec<u8>)]| {
                let mut v = v.to_vec();
                v.sort();
                v
            };
            assert!(sorted(&got.3) == sorted(&reference.3), "{url}: the packets");
        }
    }
    for child in [&mut own, &mut first, &mut cold] {
        let _ = child.kill();
        let _ = child.wait();
    }
}
