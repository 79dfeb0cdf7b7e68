//! End-to-end tests of the coefficient cache: a real server on loopback (in-process for the
//! protocol tests, the real `wavesplat` binary for the SIGKILL tests), sled in a tempdir.

mod common;

use std::collections::HashSet;
use std::process::Child;
use tonic::transport::Channel;
use tonic::Code;
use wavesplat_cache::client::{self, refine_collect, refine_start};
use wavesplat_cache::{Limits, Store, ViewSpec, VolumeKey};
use wavesplat_codec::format::packet::{decode_packet, Coefficient};
use wavesplat_codec::format::read_header_section;
use wavesplat_codec::metrics::q_i_paper_db;
use wavesplat_compressor::encode::{compress, CompressOptions, Target, TileChoice};
use wavesplat_compressor::phantom::Phantom;
use wavesplat_proto::pb;
use wavesplat_proto::pb::cache_client::CacheClient;
use wavesplat_viewer::{RenderOptions, Renderer, View};

fn test_file(dims: [usize; 3]) -> Vec<u8> {
    let vol = Phantom::SheppLogan.generate(dims);
    compress(
        &vol,
        &CompressOptions {
            target: Target::Fraction(0.05),
            tile: TileChoice::Size(16),
            layers: Some(4),
            levels: Some(3),
            // The oracle's own coefficients: the ordering tests compare packet orders, and a
            // least-squares refit is tuned for the whole set rather than for its prefixes.
            refine: None,
            ..Default::default()
        },
        &|_, _| {},
    )
    .expect("compress")
    .bytes
}

/// An in-process server on 127.0.0.1:0 with its store in a tempdir.
struct TestServer {
    url: String,
    _dir: tempfile::TempDir,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    task: tokio::task::JoinHandle<()>,
}

impl TestServer {
    async fn start() -> TestServer {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(dir.path(), Limits::default()).unwrap();
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let url = format!("http://{}", listener.local_addr().unwrap());
        let (tx, rx) = tokio::sync::oneshot::channel();
        let task = tokio::spawn(async move {
            wavesplat_cache::serve(listener, store, async {
                let _ = rx.await;
            })
            .await
            .unwrap();
        });
        TestServer {
            url,
            _dir: dir,
            stop: Some(tx),
            task,
        }
    }

    async fn client(&self) -> CacheClient<Channel> {
        client::connect(&self.url).await.unwrap()
    }

    async fn stop(mut self) {
        let _ = self.stop.take().unwrap().send(());
        self.task.await.unwrap();
    }
}

fn sorted(mut c: Vec<Coefficient>) -> Vec<Coefficient> {
    c.sort_by(|a, b| {
        (a.channel, a.band, a.pos)
            .cmp(&(b.channel, b.band, b.pos))
            .then(a.value.total_cmp(&b.value))
    });
    c
}

fn decode_all(header: &[u8], packets: &[pb::Packet]) -> Vec<Coefficient> {
    let (h, _) = read_header_section(header).unwrap();
    packets
        .iter()
        .flat_map(|p| decode_packet(&h, &p.data).unwrap().coefficients)
        .collect()
}

fn spec(view: View) -> ViewSpec {
    ViewSpec {
        view,
        multiview: false,
    }
}

async fn volume_names(c: &mut CacheClient<Channel>) -> Vec<String> {
    let l = c.list(pb::ListRequest {}).await.unwrap().into_inner();
    l.volumes.into_iter().map(|v| v.name).collect()
}

#[tokio::test]
async fn ingest_list_stream_decode_round_trip() {
    let bytes = test_file([48, 48, 48]);
    let (_, want) = wavesplat_compressor::decode::decode_coefficients(&bytes).unwrap();
    let server = TestServer::start().await;
    let mut c = server.client().await;

    let r = client::ingest(&mut c, "shepp", &bytes).await.unwrap();
    assert!(!r.existed);
    let info = r.volume.unwrap();
    assert_eq!(info.dims, vec![48, 48, 48]);
    assert_eq!(info.file_bytes, bytes.len() as u64);
    // Idempotent: identical content again.
    let again = client::ingest(&mut c, "shepp", &bytes).await.unwrap();
    assert!(again.existed);
    assert_eq!(again.volume.unwrap().id, info.id);
    assert_eq!(volume_names(&mut c).await, vec!["shepp".to_string()]);

    let key = VolumeKey::Name("shepp".into());
    let got = refine_collect(
        &mut c,
        &key,
        &spec(View::new(0.66, 0.91, 64, 64)),
        vec![],
        None,
    )
    .await
    .unwrap();
    assert!(got.done);
    assert_eq!(got.packets.len(), info.packet_count as usize);
    let ids: HashSet<u32> = got.packets.iter().map(|p| p.id).collect();
    assert_eq!(ids.len(), got.packets.len(), "a packet was sent twice");
    let have = decode_all(got.header.as_ref().unwrap(), &got.packets);
    assert_eq!(sorted(have), sorted(want));

    // Thumbnail packets: the global-order prefix.
    let first = c
        .first_packets(pb::FirstPacketsRequest {
            volume: Some(wavesplat_cache::convert::volume_ref(&key)),
            max_bytes: 2000,
        })
        .await
        .unwrap()
        .into_inner();
    assert!(!first.packets.is_empty());
    assert!(first
        .packets
        .iter()
        .enumerate()
        .all(|(i, p)| p.id == i as u32));

    let d = c
        .delete(pb::DeleteRequest {
            volume: Some(wavesplat_cache::convert::volume_ref(&key)),
        })
        .await
        .unwrap();
    assert_eq!(d.into_inner().id, info.id);
    assert!(volume_names(&mut c).await.is_empty());
    server.stop().await;
}

/// Q_I (dB, eq. 18) of the image from the packets of `order` that fit in `budget` bytes.
fn q_i_after(
    header: &wavesplat_codec::format::Header,
    packets: &[Vec<u8>],
    order: &[u32],
    budget: usize,
    view: &View,
    reference: &[f32],
) -> (f64, usize) {
    let mut used = 0;
    let mut coeffs = Vec::new();
    for id in order {
        let p = &packets[*id as usize];
        if used + p.len() > budget {
            continue;
        }
        used += p.len();
        coeffs.extend(decode_packet(header, p).unwrap().coefficients);
    }
    let img = Renderer::new(RenderOptions::default())
        .render(&coeffs, &header.geometry, view)
        .unwrap();
    (q_i_paper_db(reference, &img.data), used)
}

#[tokio::test]
async fn view_dependent_order_beats_global_order() {
    let bytes = test_file([48, 48, 48]);
    let file = wavesplat_codec::format::parse_file(&bytes).unwrap();
    let header = file.header.clone();
    let packets: Vec<Vec<u8>> = file.packets.iter().map(|p| p.to_vec()).collect();
    let all: Vec<Coefficient> = packets
        .iter()
        .flat_map(|p| decode_packet(&header, p).unwrap().coefficients)
        .collect();
    let total: usize = packets.iter().map(|p| p.len()).sum();
    let global: Vec<u32> = (0..packets.len() as u32).collect();

    let server = TestServer::start().await;
    let mut c = server.client().await;
    client::ingest(&mut c, "shepp", &bytes).await.unwrap();
    let key = VolumeKey::Name("shepp".into());

    let fit = 64.0 / (48.0f64 * 3f64.sqrt());
    let cases = [
        ("axis-aligned (rays along x)", View::new(0.0, 0.0, 64, 64)),
        ("oblique", View::new(0.66, 0.91, 64, 64)),
        (
            "zoomed corner (4x, panned)",
            View::new(0.0, 0.0, 64, 64)
                .with_zoom(4.0 * fit)
                .with_pan([-14.0, 14.0]),
        ),
    ];
    for (name, view) in cases {
        let reference = Renderer::new(RenderOptions::default())
            .render(&all, &header.geometry, &view)
            .unwrap()
            .data;
        let got = refine_collect(&mut c, &key, &spec(view), vec![], None)
            .await
            .unwrap();
        let order: Vec<u32> = got.packets.iter().map(|p| p.id).collect();
        for budget in [total / 8, total / 4, total / 2] {
            let (q_view, used_v) = q_i_after(&header, &packets, &order, budget, &view, &reference);
            let (q_global, used_g) =
                q_i_after(&header, &packets, &global, budget, &view, &reference);
            println!(
                "{name}: after {budget} of {total} bytes: Q_I view-dependent {q_view:.2} dB \
                 ({used_v} B), global {q_global:.2} dB ({used_g} B)"
            );
            assert!(
                q_view > q_global,
                "{name} at {budget} B: view-dependent {q_view:.2} dB <= global {q_global:.2} dB"
            );
        }
    }
    server.stop().await;
}

#[tokio::test]
async fn nothing_sent_twice_across_view_change_and_reconnect() {
    let bytes = test_file([48, 48, 48]);
    let server = TestServer::start().await;
    let mut c = server.client().await;
    let info = client::ingest(&mut c, "shepp", &bytes)
        .await
        .unwrap()
        .volume
        .unwrap();
    let key = VolumeKey::Id(info.id);
    // A small HTTP/2 window, so the client's reading pace holds the server back (the whole
    // volume would otherwise fit in the default 64 KiB window and be sent before the view
    // change arrives).
    let channel = tonic::transport::Endpoint::from_shared(server.url.clone())
        .unwrap()
        .initial_stream_window_size(Some(1024))
        .connect()
        .await
        .unwrap();
    let mut c = CacheClient::new(channel);
    let view_a = spec(View::new(0.0, 0.0, 64, 64));
    let view_b = spec(View::new(1.2, 0.4, 96, 64).with_zoom(3.0));

    let (tx, rx) = tokio::sync::mpsc::channel(4);
    tx.send(refine_start(&key, &view_a, vec![], false))
        .await
        .unwrap();
    let mut stream = c
        .refine(tokio_stream::wrappers::ReceiverStream::new(rx))
        .await
        .unwrap()
        .into_inner();
    let mut received: Vec<pb::Packet> = Vec::new();
    let mut header = None;
    while received.len() < 20 {
        match stream.message().await.unwrap().unwrap().msg {
            Some(pb::refine_response::Msg::Header(h)) => header = Some(h.header),
            Some(pb::refine_response::Msg::Packet(p)) => {
                received.push(p);
                if received.len() == 8 {
                    tx.send(pb::RefineRequest {
                        msg: Some(pb::refine_request::Msg::View(
                            wavesplat_cache::convert::view_message(&view_b),
                        )),
                    })
                    .await
                    .unwrap();
                }
            }
            other => panic!("unexpected {other:?}"),
        }
    }
    drop(stream);
    drop(tx);
    assert!(header.is_some());

    // Reconnect with the client's holdings: the rest, exactly once, no header.
    let have: Vec<u32> = received.iter().map(|p| p.id).collect();
    let (tx, rx) = tokio::sync::mpsc::channel(4);
    tx.send(refine_start(&key, &view_b, have, true))
        .await
        .unwrap();
    let mut stream = c
        .refine(tokio_stream::wrappers::ReceiverStream::new(rx))
        .await
        .unwrap()
        .into_inner();
    loop {
        match stream.message().await.unwrap().unwrap().msg {
            Some(pb::refine_response::Msg::Packet(p)) => received.push(p),
            Some(pb::refine_response::Msg::Done(_)) => break,
            other => panic!("unexpected {other:?}"),
        }
    }
    let ids: HashSet<u32> = received.iter().map(|p| p.id).collect();
    assert_eq!(ids.len(), received.len(), "a packet was sent twice");
    assert_eq!(ids.len(), info.packet_count as usize);
    let (_, want) = wavesplat_compressor::decode::decode_coefficients(&bytes).unwrap();
    assert_eq!(
        sorted(decode_all(&header.unwrap(), &received)),
        sorted(want)
    );
    server.stop().await;
}

fn refine_view(key: &VolumeKey, v: pb::ViewSpec) -> pb::RefineRequest {
    let mut r = refine_start(key, &spec(View::new(0.0, 0.0, 8, 8)), vec![], false);
    if let Some(pb::refine_request::Msg::Start(s)) = &mut r.msg {
        s.view = Some(v);
    }
    r
}

#[tokio::test]
async fn malformed_requests_get_errors_and_leave_the_store_unchanged() {
    let bytes = test_file([24, 24, 24]);
    let server = TestServer::start().await;
    let mut c = server.client().await;
    client::ingest(&mut c, "ok", &bytes).await.unwrap();
    let key = VolumeKey::Name("ok".into());
    let good = wavesplat_cache::convert::view_message(&spec(View::new(0.0, 0.0, 32, 32)));

    let refine_code = |req: pb::RefineRequest| {
        let mut c = c.clone();
        async move {
            let r = c.refine(tokio_stream::iter(vec![req])).await;
            match r {
                Err(s) => s.code(),
                Ok(mut s) => match s.get_mut().message().await {
                    Err(s) => s.code(),
                    Ok(_) => Code::Ok,
                },
            }
        }
    };
    let huge = pb::ViewSpec {
        width: 100_000,
        height: 100_000,
        ..good
    };
    assert_eq!(
        refine_code(refine_view(&key, huge)).await,
        Code::InvalidArgument
    );
    let nan = pb::ViewSpec {
        alpha: f64::NAN,
        ..good
    };
    assert_eq!(
        refine_code(refine_view(&key, nan)).await,
        Code::InvalidArgument
    );
    let zoom = pb::ViewSpec { zoom: -1.0, ..good };
    assert_eq!(
        refine_code(refine_view(&key, zoom)).await,
        Code::InvalidArgument
    );
    assert_eq!(
        refine_code(refine_view(&VolumeKey::Id(987_654), good)).await,
        Code::NotFound
    );
    let mut bad_have = refine_view(&key, good);
    if let Some(pb::refine_request::Msg::Start(s)) = &mut bad_have.msg {
        s.have = vec![1_000_000];
    }
    assert_eq!(refine_code(bad_have).await, Code::InvalidArgument);
    let no_start = pb::RefineRequest {
        msg: Some(pb::refine_request::Msg::View(good)),
    };
    assert_eq!(refine_code(no_start).await, Code::InvalidArgument);

    let describe = c
        .describe(pb::DescribeRequest {
            volume: Some(wavesplat_cache::convert::volume_ref(&VolumeKey::Name(
                "nope".into(),
            ))),
        })
        .await;
    assert_eq!(describe.unwrap_err().code(), Code::NotFound);
    let delete = c.delete(pb::DeleteRequest { volume: None }).await;
    assert_eq!(delete.unwrap_err().code(), Code::InvalidArgument);

    // Uploads: truncated, wrong checksum, not a .wsp file, oversized declaration, no start.
    let mut truncated = client::ingest_messages("t", &bytes);
    truncated.pop();
    let mut wrong_sum = client::ingest_messages("w", &bytes);
    if let Some(pb::ingest_request::Msg::Start(s)) = &mut wrong_sum[0].msg {
        s.sha256[0] ^= 1;
    }
    let mut garbage_bytes = bytes.clone();
    let n = garbage_bytes.len();
    garbage_bytes[n / 2] ^= 0x55;
    let garbage = client::ingest_messages("g", &garbage_bytes);
    let mut oversized = client::ingest_messages("o", &bytes);
    if let Some(pb::ingest_request::Msg::Start(s)) = &mut oversized[0].msg {
        s.total_size = u64::MAX;
    }
    let no_start = client::ingest_messages("n", &bytes)[1..].to_vec();
    let bad_name = client::ingest_messages("", &bytes);
    for (what, msgs) in [
        ("truncated", truncated),
        ("wrong checksum", wrong_sum),
        ("corrupt file", garbage),
        ("oversized", oversized),
        ("no start", no_start),
        ("empty name", bad_name),
    ] {
        let r = c.ingest(tokio_stream::iter(msgs)).await;
        assert_eq!(r.unwrap_err().code(), Code::InvalidArgument, "{what}");
    }
    assert_eq!(volume_names(&mut c).await, vec!["ok".to_string()]);
    server.stop().await;
}

/// The real binary, serving on 127.0.0.1:0 (the bound address is read from its stdout).
struct Process {
    child: Child,
    url: String,
}

impl Process {
    fn start(db: &std::path::Path) -> Process {
        let db = db.to_str().expect("utf-8 temp path");
        let (child, addr) =
            common::spawn_server(&["serve", "cache", "--addr", "127.0.0.1:0", "--db", db]);
        Process {
            url: format!("http://{addr}"),
            child,
        }
    }

    fn kill(mut self) {
        // SIGKILL: no shutdown path runs.
        self.child.kill().unwrap();
        self.child.wait().unwrap();
    }
}

impl Drop for Process {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

async fn stream_all(url: &str, name: &str) -> (Vec<u8>, Vec<pb::Packet>) {
    let mut c = client::connect(url).await.unwrap();
    let got = refine_collect(
        &mut c,
        &VolumeKey::Name(name.into()),
        &spec(View::new(0.3, 0.2, 32, 32)),
        vec![],
        None,
    )
    .await
    .unwrap();
    assert!(got.done);
    (got.header.unwrap(), got.packets)
}

#[tokio::test]
async fn sigkill_during_ingest_and_streaming_leaves_no_partial_volume() {
    let a = test_file([48, 48, 48]);
    let b = test_file([40, 40, 40]);
    let (_, want_a) = wavesplat_compressor::decode::decode_coefficients(&a).unwrap();
    let dir = tempfile::tempdir().unwrap();

    let server = Process::start(dir.path());
    let mut c = client::connect(&server.url).await.unwrap();
    client::ingest(&mut c, "a", &a).await.unwrap();
    // Start uploading b, send half of it, and kill the server mid-upload.
    let msgs = client::ingest_messages("b", &b);
    let (tx, rx) = tokio::sync::mpsc::channel(16);
    let mut c2 = c.clone();
    let upload = tokio::spawn(async move {
        c2.ingest(tokio_stream::wrappers::ReceiverStream::new(rx))
            .await
    });
    tx.send(msgs[0].clone()).await.unwrap();
    let half = b.len() / 2;
    tx.send(pb::IngestRequest {
        msg: Some(pb::ingest_request::Msg::Chunk(b[..half].to_vec())),
    })
    .await
    .unwrap();
    // A round trip on the same connection, so the upload is in flight at the server.
    assert_eq!(volume_names(&mut c).await, vec!["a".to_string()]);
    server.kill();
    assert!(upload.await.unwrap().is_err());
    drop(tx);

    let server = Process::start(dir.path());
    let mut c = client::connect(&server.url).await.unwrap();
    assert_eq!(volume_names(&mut c).await, vec!["a".to_string()]);
    let (h, p) = stream_all(&server.url, "a").await;
    assert_eq!(sorted(decode_all(&h, &p)), sorted(want_a.clone()));

    // Kill during streaming.
    let (tx, rx) = tokio::sync::mpsc::channel(4);
    tx.send(refine_start(
        &VolumeKey::Name("a".into()),
        &spec(View::new(0.0, 0.0, 32, 32)),
        vec![],
        false,
    ))
    .await
    .unwrap();
    let mut stream = c
        .refine(tokio_stream::wrappers::ReceiverStream::new(rx))
        .await
        .unwrap()
        .into_inner();
    for _ in 0..5 {
        stream.message().await.unwrap().unwrap();
    }
    server.kill();
    drop(stream);

    let server = Process::start(dir.path());
    let mut c = client::connect(&server.url).await.unwrap();
    assert_eq!(volume_names(&mut c).await, vec!["a".to_string()]);
    let (h, p) = stream_all(&server.url, "a").await;
    assert_eq!(sorted(decode_all(&h, &p)), sorted(want_a));
    // The store still accepts b after the crash.
    client::ingest(&mut c, "b", &b).await.unwrap();
    assert_eq!(
        volume_names(&mut c).await,
        vec!["a".to_string(), "b".to_string()]
    );
    server.kill();
}
