//! Faults of the cache found by trying it as a new user would, each reproduced here: concurrent
//! identical ingests, identical content under a second name, the deadline of an upload, uploads
//! held in memory, disk space never given back, and client faults answered as server faults.
//! In-process servers on loopback, sled in a tempdir.

mod common;

use common::{ingest_messages, phantom_file, phantom_options, TestCache};
use std::time::Duration;
use tonic::transport::Channel;
use tonic::Code;
use wavesplat_cache::store::Upload;
use wavesplat_cache::{CacheError, Limits, Store, VolumeKey as StoreKey};
use wavesplat_client::{CacheClient, RefineRequest, VolumeKey};
use wavesplat_codec::view::{View, ViewSpec};
use wavesplat_compressor::encode::CompressOptions;
use wavesplat_compressor::phantom::Phantom;
use wavesplat_proto::pb;

fn test_file(dims: [usize; 3], fraction: f64) -> Vec<u8> {
    let options = CompressOptions {
        layers: Some(3),
        levels: Some(3),
        ..phantom_options(fraction)
    };
    phantom_file(Phantom::SheppLogan, dims, &options)
}

async fn names(c: &mut CacheClient) -> Vec<String> {
    c.list()
        .await
        .unwrap()
        .into_iter()
        .map(|v| v.name)
        .collect()
}

/// An upload that holds an upload slot and then sends nothing is ended after the idle limit,
/// stores nothing, and frees its slot: the same caller's next upload (one slot per caller here)
/// lands. Before, it waited for ever, and a few such callers held every upload slot.
#[tokio::test]
async fn an_idle_upload_ends_and_frees_its_slot() {
    use wavesplat_cache::service::Fairness;
    let server = TestCache::start_with(
        Limits::default(),
        wavesplat_cache::ServeOptions {
            fairness: Fairness {
                max_uploads_per_caller: 1,
                upload_idle: Duration::from_secs(1),
                ..Fairness::default()
            },
            ..Default::default()
        },
    );
    let bytes = test_file([24, 24, 24], 0.05);
    let messages = ingest_messages("v", &bytes, 1000);
    let (tx, rx) = tokio::sync::mpsc::channel(8);
    // The start and one chunk, then silence with the stream left open.
    tx.send(messages[0].clone()).await.unwrap();
    tx.send(messages[1].clone()).await.unwrap();
    let mut wire = server.wire().await;
    let idle = tokio::time::timeout(
        Duration::from_secs(60),
        wire.ingest(tokio_stream::wrappers::ReceiverStream::new(rx)),
    )
    .await
    .expect("the idle upload never ended");
    let status = idle.expect_err("an idle upload stored");
    assert_eq!(status.code(), Code::DeadlineExceeded, "{status:?}");
    drop(tx);
    let mut c = server.client().await;
    assert!(names(&mut c).await.is_empty());
    let landed = tokio::time::timeout(Duration::from_secs(60), c.ingest("v", &bytes))
        .await
        .expect("the next upload waited on the idle one's slot");
    assert!(!landed.unwrap().existed);
    assert_eq!(names(&mut c).await, vec!["v".to_string()]);
    server.stop().await;
}

/// Bytes of everything under `dir`.
fn du(dir: &std::path::Path) -> u64 {
    let mut total = 0;
    for e in std::fs::read_dir(dir).unwrap() {
        let e = e.unwrap();
        let m = e.metadata().unwrap();
        total += if m.is_dir() { du(&e.path()) } else { m.len() };
    }
    total
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn concurrent_identical_ingests_all_succeed_and_land_once() {
    let bytes = test_file([32, 32, 32], 0.05);
    let server = TestCache::start();
    let mut tasks = Vec::new();
    for _ in 0..16 {
        let url = server.url.clone();
        let bytes = bytes.clone();
        tasks.push(tokio::spawn(async move {
            let mut c = CacheClient::connect(&url).await.unwrap();
            c.ingest("same", &bytes).await
        }));
    }
    let mut ids = Vec::new();
    let mut fresh = 0;
    for t in tasks {
        let r = t.await.unwrap().expect("every identical ingest succeeds");
        assert_eq!(r.volume.name, "same");
        fresh += usize::from(!r.existed);
        ids.push(r.volume.id);
    }
    assert_eq!(fresh, 1, "exactly one ingest stored the volume");
    assert!(ids.iter().all(|&i| i == ids[0]), "{ids:?}");
    assert_eq!(names(&mut server.client().await).await, vec!["same"]);
    // One file of data, exactly the upload's size: the losers left nothing behind.
    assert_eq!(server.node.store.data_bytes().unwrap(), bytes.len() as u64);
    server.stop().await;
}

#[tokio::test]
async fn identical_content_under_a_second_name_resolves_under_both() {
    let bytes = test_file([24, 24, 24], 0.05);
    let server = TestCache::start();
    let mut c = server.client().await;
    let a = c.ingest("archive/a", &bytes).await.unwrap();
    let b = c.ingest("archive/copy-of-a", &bytes).await.unwrap();
    assert!(!a.existed && b.existed);
    assert_eq!(a.volume.id, b.volume.id);
    assert_eq!(b.volume.name, "archive/copy-of-a");
    assert_eq!(
        names(&mut c).await,
        vec!["archive/a".to_string(), "archive/copy-of-a".to_string()]
    );
    // A third ingest under an existing name changes nothing.
    let again = c.ingest("archive/a", &bytes).await.unwrap();
    assert!(again.existed);
    assert_eq!(names(&mut c).await.len(), 2);
    for name in ["archive/a", "archive/copy-of-a"] {
        let key = VolumeKey::Name(name.into());
        assert_eq!(c.describe(&key).await.unwrap().name, name);
        let h = c.header(&key).await.unwrap();
        assert_eq!(h.info.id, a.volume.id);
    }
    // Deleting one name keeps the other (and the data); deleting the last drops the volume.
    c.delete(&VolumeKey::Name("archive/a".into()))
        .await
        .unwrap();
    let key = VolumeKey::Name("archive/copy-of-a".into());
    let view = ViewSpec::single(View::new(0.2, 0.1, 32, 32));
    let got = c
        .refine_collect(RefineRequest::new(key.clone(), view), None)
        .await
        .unwrap();
    assert!(got.done && !got.packets.is_empty());
    assert_eq!(server.node.store.data_bytes().unwrap(), bytes.len() as u64);
    c.delete(&key).await.unwrap();
    assert!(names(&mut c).await.is_empty());
    assert_eq!(server.node.store.data_bytes().unwrap(), 0);
    // A different file under a taken name is still refused.
    c.ingest("x", &bytes).await.unwrap();
    let other = test_file([24, 24, 20], 0.05);
    let e = c.ingest("x", &other).await.unwrap_err();
    assert_eq!(e.code(), Some(Code::AlreadyExists));
    server.stop().await;
}

#[test]
fn an_upload_abandoned_before_its_commit_stores_nothing() {
    let bytes = test_file([24, 24, 24], 0.05);
    let dir = tempfile::tempdir().unwrap();
    let store = Store::open(dir.path(), Limits::default()).unwrap();
    let hash = wavesplat_cache::store::sha256(&bytes);
    let mut up = Upload::begin(&store, "late", hash, bytes.len() as u64).unwrap();
    for c in bytes.chunks(1000) {
        up.push(c).unwrap();
    }
    let e = up
        .finish(|| Some(CacheError::DeadlineExceeded("test".into())))
        .unwrap_err();
    assert!(matches!(e, CacheError::DeadlineExceeded(_)), "{e}");
    assert!(store.list().unwrap().is_empty());
    assert_eq!(store.data_bytes().unwrap(), 0);
    assert!(store.resolve(&StoreKey::Name("late".into())).is_err());
    // The same upload without the deadline lands.
    assert!(!store.ingest("late", &bytes, Some(hash)).unwrap().existed);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_ingest_cut_short_by_its_deadline_can_be_repeated_and_lands_once() {
    // Whatever the deadline cut (the upload, the validation, or only the reply), the store
    // agrees with a repeat of the same ingest: it lands once, and says so.
    let bytes = test_file([48, 48, 48], 1.0);
    let server = TestCache::start();
    let mut wire = server.wire().await;
    for ms in [1u64, 10, 40, 150] {
        let name = format!("v{ms}");
        let mut req =
            tonic::Request::new(tokio_stream::iter(ingest_messages(&name, &bytes, 64 << 10)));
        req.set_timeout(Duration::from_millis(ms));
        let first = wire.ingest(req).await;
        let mut c = server.client().await;
        let again = c.ingest(&name, &bytes).await.unwrap();
        match first {
            Ok(r) => {
                assert!(again.existed);
                assert_eq!(r.into_inner().volume.unwrap().id, again.volume.id);
            }
            Err(s) => assert!(
                matches!(
                    s.code(),
                    Code::DeadlineExceeded | Code::Cancelled | Code::Unavailable
                ),
                "{s:?}"
            ),
        }
        assert_eq!(
            c.describe(&VolumeKey::Name(name)).await.unwrap().id,
            again.volume.id
        );
    }
    // Identical content: one volume under four names, one file.
    assert_eq!(server.node.store.data_bytes().unwrap(), bytes.len() as u64);
    server.stop().await;
}

#[tokio::test]
async fn junk_is_refused_from_its_first_chunk_while_the_client_is_still_sending() {
    let server = TestCache::start();
    let mut wire = server.wire().await;
    let total = 150u64 << 20;
    let (tx, rx) = tokio::sync::mpsc::channel(4);
    tx.send(pb::IngestRequest {
        msg: Some(pb::ingest_request::Msg::Start(pb::IngestStart {
            name: "junk".into(),
            total_size: total,
            sha256: vec![0; 32],
        })),
    })
    .await
    .unwrap();
    tx.send(pb::IngestRequest {
        msg: Some(pb::ingest_request::Msg::Chunk(vec![0x42; 1 << 20])),
    })
    .await
    .unwrap();
    // The stream stays open (149 MiB still to come): the answer must not wait for them (a
    // server that buffers the whole upload first never answers; the timeout turns that hang
    // into a failure).
    let r = tokio::time::timeout(
        Duration::from_secs(60),
        wire.ingest(tokio_stream::wrappers::ReceiverStream::new(rx)),
    )
    .await
    .expect("the server answers while the upload is still open");
    let s = r.unwrap_err();
    assert_eq!(s.code(), Code::InvalidArgument);
    assert!(s.message().contains("magic"), "{}", s.message());
    drop(tx);
    assert_eq!(server.node.store.data_bytes().unwrap(), 0);
    server.stop().await;
}

#[test]
fn an_upload_holds_at_most_its_prelude_or_largest_packet_in_memory() {
    let bytes = test_file([40, 40, 40], 0.3);
    let parsed = wavesplat_codec::format::parse_file(&bytes).unwrap();
    let largest = parsed.packets.iter().map(|p| p.len()).max().unwrap() as u64;
    assert!(
        largest * 4 < bytes.len() as u64,
        "the test needs several packets"
    );
    let dir = tempfile::tempdir().unwrap();
    let store = Store::open(dir.path(), Limits::default()).unwrap();
    let hash = wavesplat_cache::store::sha256(&bytes);
    let mut up = Upload::begin(&store, "v", hash, bytes.len() as u64).unwrap();
    let prelude = (parsed.header_bytes + parsed.directory_bytes) as u64;
    for (i, c) in bytes.chunks(777).enumerate() {
        up.push(c).unwrap();
        if up.received() >= prelude {
            assert!(
                up.memory_need() <= largest,
                "chunk {i}: {}",
                up.memory_need()
            );
        }
    }
    assert!(!up.finish(|| None).unwrap().existed);
    // What was written is the file, byte for byte.
    let v = store
        .open_volume(store.resolve(&StoreKey::Name("v".into())).unwrap())
        .unwrap();
    for (i, p) in parsed.packets.iter().enumerate() {
        assert_eq!(v.packet(i as u32).unwrap(), *p);
    }
}

#[test]
fn disk_space_is_given_back_by_deletes_and_rolled_back_ingests() {
    let dir = tempfile::tempdir().unwrap();
    let files: Vec<Vec<u8>> = (0..10).map(|i| test_file([40, 40, 24 + i], 0.5)).collect();
    let live: u64 = files[0].len() as u64;
    let store = Store::open(dir.path(), Limits::default()).unwrap();
    store.ingest("keep", &files[0], None).unwrap();
    let mut after_first = 0;
    for (round, f) in files[1..].iter().enumerate() {
        store.ingest("tmp", f, None).unwrap();
        store.delete(&StoreKey::Name("tmp".into())).unwrap();
        // Rolled back: a checksum mismatch and a corrupt packet.
        assert!(store.ingest("bad", f, Some([1; 32])).is_err());
        let mut corrupt = f.clone();
        let n = corrupt.len();
        corrupt[n - 10] ^= 0x55;
        assert!(store.ingest("bad", &corrupt, None).is_err());
        assert_eq!(store.data_bytes().unwrap(), live, "round {round}");
        store.flush().unwrap();
        if round == 0 {
            after_first = du(dir.path());
        }
    }
    let after = du(dir.path());
    // The volume data is exactly the live volume; sled's own records are small and do not
    // grow with the cycles beyond a bounded log.
    assert!(
        after <= after_first + (4 << 20),
        "{after} bytes on disk after 9 cycles, {after_first} after one"
    );
    drop(store);
    let store = Store::open(dir.path(), Limits::default()).unwrap();
    assert_eq!(store.data_bytes().unwrap(), live);
    assert_eq!(store.list().unwrap().len(), 1);
}

/// A message the Cache service cannot decode: field 1 of `DeleteRequest` is a message, here a
/// varint.
#[derive(Clone, PartialEq, prost::Message)]
struct Bogus {
    #[prost(uint64, tag = "1")]
    x: u64,
}

#[tokio::test]
async fn client_faults_get_client_statuses() {
    let server = TestCache::start();
    let channel = Channel::from_shared(server.url.clone())
        .unwrap()
        .connect()
        .await
        .unwrap();
    let mut grpc = tonic::client::Grpc::new(channel);
    grpc.ready().await.unwrap();
    let codec: tonic_prost::ProstCodec<Bogus, pb::DeleteResponse> =
        tonic_prost::ProstCodec::default();
    let e = grpc
        .unary(
            tonic::Request::new(Bogus { x: 7 }),
            http::uri::PathAndQuery::from_static("/wavesplat.v1.Cache/Delete"),
            codec,
        )
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument, "{e:?}");
    // Over the message size limit: a unary request, and a chunk inside an upload.
    let mut wire = server.wire().await;
    let e = wire
        .describe(pb::DescribeRequest {
            volume: Some(pb::VolumeRef {
                key: Some(pb::volume_ref::Key::Name("n".repeat(5 << 20))),
            }),
        })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::ResourceExhausted, "{e:?}");
    let mut msgs = ingest_messages("big", &[0u8; 16], 64 << 10);
    msgs[0].msg = Some(pb::ingest_request::Msg::Start(pb::IngestStart {
        name: "big".into(),
        total_size: 6 << 20,
        sha256: vec![0; 32],
    }));
    msgs.truncate(1);
    msgs.push(pb::IngestRequest {
        msg: Some(pb::ingest_request::Msg::Chunk(vec![b'W'; 6 << 20])),
    });
    let e = wire.ingest(tokio_stream::iter(msgs)).await.unwrap_err();
    assert_eq!(e.code(), Code::ResourceExhausted, "{e:?}");
    assert!(names(&mut server.client().await).await.is_empty());
    let _ = &server.dir;
    server.stop().await;
}
