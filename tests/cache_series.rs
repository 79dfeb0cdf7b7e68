//! Time series in a cache node (embedded store): a series file ingested as one volume (its
//! manifest, then each component read front to back, plain or bricked, every one checked),
//! kept across a restart, each time point streamed by `Refine` (the view's `time_point`) with
//! only the packets of the components it names, and drawn by `render --cache --time-point` as
//! the local file's time point is drawn; read on the wire by a plain client; damaged uploads
//! refused naming the component.

mod common;

use common::{read_f32, text};
use std::collections::HashSet;
use std::process::Command;
use wavesplat_cache::{CacheError, Limits, Store};
use wavesplat_client::{CacheClient, RefineRequest, VolumeKey};
use wavesplat_codec::format::series::parse_series;
use wavesplat_codec::view::{View, ViewSpec};
use wavesplat_compressor::phantom::beating;
use wavesplat_compressor::series::{compress_series, VolumeSeries};
use wavesplat_harness::LocalCache;

const BIN: &str = env!("CARGO_BIN_EXE_wavesplat");
const DIMS: [usize; 3] = [32, 28, 16];
const POINTS: usize = 6;

/// A beating phantom of six time points compressed in temporal groups of 4; `brick`: its
/// components in bricks of that edge (larger than the volume: plain components).
fn series_file(brick: usize) -> Vec<u8> {
    let volumes = (0..POINTS)
        .map(|t| beating(DIMS, t, POINTS).unwrap())
        .collect();
    let times = (0..POINTS).map(|t| t as f64 * 0.05).collect();
    let s = VolumeSeries::new(volumes, Some(times)).unwrap();
    compress_series(&s, &common::phantom_options(0.3), 4, brick, &|_| {})
        .unwrap()
        .bytes
}

use common::{render_in as render, runtime};

/// `render --cache --time-point` of a series ends at the local file's progressive image of the
/// same time point, for plain and bricked components, a plain and a depth-cued view; time
/// points differ (the heart beats); a time point past the end and a time point of a volume
/// that is not a series are refused by name.
#[test]
fn a_time_point_renders_from_the_cache_as_from_its_file() {
    let tmp = tempfile::tempdir().unwrap();
    let server = LocalCache::start(&tmp.path().join("db")).unwrap();
    for (name, brick) in [("plain", 256), ("bricked", 16)] {
        let file = format!("{name}.wsp");
        std::fs::write(tmp.path().join(&file), series_file(brick)).unwrap();
        let ingest = Command::new(BIN)
            .args([
                "cache",
                "ingest",
                &file,
                "--name",
                name,
                "--cache",
                &server.url,
            ])
            .current_dir(tmp.path())
            .output()
            .unwrap();
        assert!(ingest.status.success(), "{}", text(&ingest));
        let views: [(&str, &[&str]); 2] = [
            (
                "plain",
                &["--alpha", "0.4", "--beta", "0.3", "--size", "48x40"],
            ),
            (
                "cued",
                &[
                    "--alpha", "1.2", "--beta", "-0.2", "--cue-k", "0.1", "--size", "40x40",
                ],
            ),
        ];
        let mut images = Vec::new();
        for t in ["0", "3", "5"] {
            for (view_name, view) in views {
                let what = format!("{name}, t {t}, {view_name}");
                let cached = format!("{name}-{t}-{view_name}-cache.f32");
                let local = format!("{name}-{t}-{view_name}-local.f32");
                let mut args = vec![
                    "--cache",
                    &server.url,
                    "--volume",
                    name,
                    "--time-point",
                    t,
                    "--cpu",
                    "-o",
                    "c.png",
                    "--raw",
                    &cached,
                ];
                args.extend_from_slice(view);
                let out = render(tmp.path(), &args);
                assert!(out.status.success(), "{what}: {}", text(&out));
                let mut args = vec![
                    file.as_str(),
                    "--time-point",
                    t,
                    "--cpu",
                    "--progressive",
                    "-o",
                    "l.png",
                    "--raw",
                    &local,
                ];
                args.extend_from_slice(view);
                let out = render(tmp.path(), &args);
                assert!(out.status.success(), "{what}: {}", text(&out));
                let (c, l) = (
                    read_f32(&tmp.path().join(&cached)),
                    read_f32(&tmp.path().join(&local)),
                );
                assert!(l.iter().any(|v| *v != 0.0), "{what}: the image is empty");
                let snr = wavesplat_codec::metrics::snr_db(&l, &c);
                assert!(snr > 90.0, "{what}: cache against file {snr:.1} dB");
                if view_name == "plain" {
                    images.push(c);
                }
            }
        }
        // Time points 0 and 3 are systole and diastole apart: the images differ (an image
        // compared with itself is above 90 dB).
        let apart = wavesplat_codec::metrics::snr_db(&images[0], &images[1]);
        assert!(apart < 60.0, "{name}: time points 0 and 3 at {apart:.1} dB");
    }
    let past = render(
        tmp.path(),
        &[
            "--cache",
            &server.url,
            "--volume",
            "plain",
            "--time-point",
            "6",
            "-o",
            "x.png",
        ],
    );
    let said = text(&past);
    assert!(
        !past.status.success() && said.contains("time point 6") && said.contains("has 6"),
        "{said}"
    );
}

/// Read on the wire by a plain client: the header message carries the series manifest and
/// every component's bricks; a time point is sent the packets of the components it names,
/// each once, and no other (its view's `time_point`), also after a view change to another
/// time point on the same stream; a time point past the end is an invalid request.
#[test]
fn a_time_point_is_sent_only_its_components_packets() {
    let wsp = series_file(16);
    let manifest = parse_series(&wsp).unwrap().manifest;
    let tmp = tempfile::tempdir().unwrap();
    let server = LocalCache::start(tmp.path()).unwrap();
    let rt = runtime();
    let mut c = rt.block_on(CacheClient::connect(&server.url)).unwrap();
    rt.block_on(c.ingest("cine", &wsp)).unwrap();
    let view = ViewSpec::single(View::new(0.4, 0.3, 48, 48));
    let key = VolumeKey::Name("cine".into());
    let first = rt
        .block_on(c.refine_collect(RefineRequest::new(key.clone(), view).at_time_point(0), None))
        .unwrap();
    let header = first.header.expect("the header comes first");
    assert_eq!(header.series.as_deref(), Some(&manifest));
    assert_eq!(header.header.geometry.dims, DIMS);
    let components = header.bricks.last().unwrap().component + 1;
    assert_eq!(components, manifest.components.len());
    assert!(
        header.bricks.len() > components,
        "the components are bricked: {} bricks",
        header.bricks.len()
    );
    // The packet ids of each component.
    let mut of_component: Vec<HashSet<u32>> = vec![HashSet::new(); components];
    let mut id = 0u32;
    for b in &header.bricks {
        of_component[b.component].extend(id..id + b.packets);
        id += b.packets;
    }
    assert_eq!(id, header.info.packet_count);
    for t in [0usize, 2, 5] {
        let got = rt
            .block_on(c.refine_collect(
                RefineRequest::new(key.clone(), view).at_time_point(t as u32),
                None,
            ))
            .unwrap();
        assert!(got.done, "t {t}");
        let named: HashSet<u32> = manifest.points[t]
            .terms
            .iter()
            .flat_map(|(c, _)| of_component[*c].iter().copied())
            .collect();
        let sent: Vec<u32> = got.packets.iter().map(|p| p.id).collect();
        let unique: HashSet<u32> = sent.iter().copied().collect();
        assert_eq!(unique.len(), sent.len(), "t {t}: a packet sent twice");
        assert_eq!(unique, named, "t {t}: exactly its components' packets");
        assert!(named.len() < id as usize, "t {t} names every component");
    }
    // A view change to another time point on one stream: what follows is the new one's.
    let got = rt
        .block_on(async {
            let mut s = c
                .refine(RefineRequest::new(key.clone(), view).at_time_point(0))
                .await?;
            s.control().set_view_at(&view, 4).await?;
            let mut ids = Vec::new();
            while let Some(ev) = s.next().await? {
                match ev {
                    wavesplat_client::RefineEvent::Packet(p) => ids.push(p.id),
                    // The time point 4 view's `done`.
                    wavesplat_client::RefineEvent::Done { views: 1, .. } => break,
                    wavesplat_client::RefineEvent::Done { .. }
                    | wavesplat_client::RefineEvent::Header(_) => {}
                }
            }
            Ok::<_, wavesplat_client::ClientError>(ids)
        })
        .unwrap();
    let both: HashSet<u32> = [0usize, 4]
        .iter()
        .flat_map(|t| manifest.points[*t].terms.iter())
        .flat_map(|(c, _)| of_component[*c].iter().copied())
        .collect();
    assert!(got.iter().all(|id| both.contains(id)), "{got:?}");
    let at4: HashSet<u32> = manifest.points[4]
        .terms
        .iter()
        .flat_map(|(c, _)| of_component[*c].iter().copied())
        .collect();
    let sent: HashSet<u32> = got.iter().copied().collect();
    assert!(at4.is_subset(&sent), "time point 4 was not sent whole");
    let past = rt.block_on(c.refine_collect(
        RefineRequest::new(key, view).at_time_point(POINTS as u32),
        None,
    ));
    let e = past.expect_err("time point past the end");
    assert_eq!(e.code(), Some(tonic::Code::InvalidArgument), "{e}");
}

/// The store keeps a series across a restart (the same manifest, bricks and packets); a
/// damaged component, a cut upload, bytes after the last component and a series nested in a
/// series are refused, naming what is wrong, and leave nothing behind.
#[test]
fn the_store_keeps_series_and_refuses_damaged_ones() {
    let wsp = series_file(16);
    let file = parse_series(&wsp).unwrap();
    let tmp = tempfile::tempdir().unwrap();
    let limits = Limits::default();
    let (id, packets, bricks) = {
        let store = Store::open(tmp.path(), limits).unwrap();
        let v = store.ingest("cine", &wsp, None).unwrap().volume;
        let open = store.open_volume(v.id).unwrap();
        let s = open.index.series.as_ref().expect("a series");
        assert_eq!(s.manifest, file.manifest);
        (v.id, open.index.packets.len(), s.bricks.len())
    };
    {
        let store = Store::open(tmp.path(), limits).unwrap();
        let open = store.open_volume(id).unwrap();
        let s = open
            .index
            .series
            .as_ref()
            .expect("a series after a restart");
        assert_eq!(s.manifest, file.manifest);
        assert_eq!(
            (open.index.packets.len(), s.bricks.len()),
            (packets, bricks)
        );
        assert_eq!(open.index.time_points(), POINTS);
        // Every packet reads back as the bytes the file holds at its offset.
        for (i, p) in open.index.packets.iter().enumerate() {
            let at = p.offset as usize;
            assert_eq!(
                open.packet(i as u32).unwrap(),
                wsp[at..at + p.len as usize].to_vec(),
                "packet {i}"
            );
        }
    }
    let store = Store::open(tmp.path(), limits).unwrap();
    let c1 = &file.manifest.components[1];
    let mut damaged = wsp.clone();
    damaged[(c1.offset + c1.length / 2) as usize] ^= 0x40;
    let refused = |bytes: &[u8], name: &str| -> String {
        match store.ingest(name, bytes, None) {
            Err(e @ (CacheError::InvalidUpload(_) | CacheError::Format(_))) => e.to_string(),
            Err(e) => panic!("{name}: {e}"),
            Ok(_) => panic!("{name} was taken"),
        }
    };
    let m = refused(&damaged, "damaged");
    assert!(m.contains("component 1"), "{m}");
    let m = refused(&wsp[..wsp.len() - 10], "cut");
    assert!(m.contains("series component"), "{m}");
    let mut long = wsp.clone();
    long.extend_from_slice(&[0; 8]);
    let m = refused(&long, "long");
    assert!(m.contains("end at byte") || m.contains("after"), "{m}");
    // A series whose component 0 is itself a series (the manifest checks out: each component
    // its bytes and CRC) is refused naming the nesting.
    let mut manifest = file.manifest.clone();
    let components: Vec<&[u8]> = manifest
        .components
        .iter()
        .enumerate()
        .map(|(c, e)| {
            if c == 0 {
                wsp.as_slice()
            } else {
                &wsp[e.offset as usize..(e.offset + e.length) as usize]
            }
        })
        .collect();
    let nested = wavesplat_codec::format::series::write_series(&mut manifest, &components).unwrap();
    let m = refused(&nested, "nested");
    assert!(
        m.contains("component 0: a component of a series is itself a series"),
        "{m}"
    );
    for name in ["damaged", "cut", "long", "nested"] {
        assert!(store.resolve(&VolumeKey::Name(name.into())).is_err());
    }
}

/// Nodes over an object store (a `file://` bucket: the series published in the indexed
/// layout's version 3) serve a series as a node with its own store does: the same manifest
/// section, bricks and packet count, and for each time point the same packets with the same
/// bytes, from the node that took the upload and from a cold one.
#[test]
fn nodes_over_an_object_store_serve_series_alike() {
    let wsp = series_file(16);
    let tmp = tempfile::tempdir().unwrap();
    let path = |p: &str| tmp.path().join(p).to_str().unwrap().to_string();
    let store_url = format!("file://{}", path("bucket"));
    let serve = |db: &str, store: Option<&str>| {
        let db = path(db);
        let mut args = vec!["serve", "cache", "--addr", "127.0.0.1:0", "--db", &db];
        if let Some(s) = store {
            args.extend_from_slice(&["--store", s]);
        }
        common::spawn_server(&args)
    };
    let (mut own, own_url) = serve("own", None);
    let (mut first, first_url) = serve("n1", Some(&store_url));
    let rt = runtime();
    for url in [&own_url, &first_url] {
        let mut c = rt.block_on(CacheClient::connect(url)).unwrap();
        rt.block_on(c.ingest("cine", &wsp)).unwrap();
    }
    let (mut cold, cold_url) = serve("n2", Some(&store_url));
    let view = ViewSpec::single(View::new(0.4, 0.3, 48, 48));
    for t in [0u32, 4] {
        let collect = |url: &str| {
            let mut c = rt.block_on(CacheClient::connect(url)).unwrap();
            let request = RefineRequest::new(VolumeKey::Name("cine".into()), view).at_time_point(t);
            let got = rt.block_on(c.refine_collect(request, None)).unwrap();
            assert!(got.done, "{url}");
            let h = got.header.expect("a header");
            let bricks: Vec<(String, [u64; 3], u32, usize)> = h
                .bricks
                .iter()
                .map(|b| (format!("{:?}", b.header), b.origin, b.packets, b.component))
                .collect();
            let mut packets: Vec<(u32, Vec<u8>)> =
                got.packets.into_iter().map(|p| (p.id, p.data)).collect();
            packets.sort();
            (h.bytes, h.info.packet_count, bricks, packets, h.series)
        };
        let reference = collect(&own_url);
        assert!(reference.4.is_some(), "a series");
        assert!(!reference.3.is_empty());
        for url in [&first_url, &cold_url] {
            let got = collect(url);
            assert_eq!(got.0, reference.0, "{url}: the manifest section");
            assert_eq!(got.1, reference.1, "{url}: the packet count");
            assert!(got.2 == reference.2, "{url}: the bricks");
            assert!(got.3 == reference.3, "{url}, t {t}: the packets");
        }
    }
    for child in [&mut own, &mut first, &mut cold] {
        let _ = child.kill();
        let _ = child.wait();
    }
}

/// A series' header message as a client checks it (read from the other side of the wire, as a
/// hostile or broken server could send it): the cache's own is taken; bricks of components out
/// of order, a brick outside the whole, an origin of two values, a component missing, a
/// packet count that does not add up, and a component whose bricks overlap or leave a hole are
/// each refused, naming the problem.
#[test]
fn a_clients_check_of_a_series_header_refuses_what_does_not_add_up() {
    use wavesplat_client::convert::volume_header;
    use wavesplat_proto::pb;
    let wsp = series_file(16);
    let tmp = tempfile::tempdir().unwrap();
    let server = LocalCache::start(tmp.path()).unwrap();
    let rt = runtime();
    let good: pb::VolumeHeader = rt.block_on(async {
        let mut c = CacheClient::connect(&server.url).await.unwrap();
        c.ingest("cine", &wsp).await.unwrap();
        let mut wire = pb::cache_client::CacheClient::connect(server.url.clone())
            .await
            .unwrap();
        wire.header(pb::DescribeRequest {
            volume: Some(pb::VolumeRef {
                key: Some(pb::volume_ref::Key::Name("cine".into())),
            }),
        })
        .await
        .unwrap()
        .into_inner()
    });
    let parsed = volume_header(good.clone()).unwrap();
    assert_eq!(parsed.series.as_ref().unwrap().points.len(), POINTS);
    let refused = |edit: &dyn Fn(&mut pb::VolumeHeader), want: &str| {
        let mut h = good.clone();
        edit(&mut h);
        let e = volume_header(h).expect_err(want).to_string();
        assert!(e.contains(want), "{want}: {e}");
    };
    let last = good.bricks.len() - 1;
    refused(&|h| h.bricks[last].component = 0, "after component");
    refused(&|h| h.bricks[0].origin = vec![30, 0, 0], "not inside");
    refused(&|h| h.bricks[0].origin = vec![0, 0], "origin of 2 values");
    refused(
        &|h| {
            let c = h.bricks[last].component;
            h.bricks.retain(|b| b.component != c);
        },
        "components; the manifest has",
    );
    refused(&|h| h.bricks[0].packets += 1, "packets, the volume");
    // Component 0's second brick moved onto its first: the voxels still add up, but drawn the
    // first would count twice and the second's place would stay empty.
    assert_eq!(good.bricks[1].component, 0);
    refused(
        &|h| h.bricks[1].origin = h.bricks[0].origin.clone(),
        "overlaps another",
    );
    // A brick dropped from component 0 (its packets moved to its neighbour): a hole.
    refused(
        &|h| {
            let gone = h.bricks.remove(1);
            h.bricks[0].packets += gone.packets;
        },
        "voxels",
    );
}
