//! Volume names of every valid length in a node over a `file://` object store: names of 1 to
//! 255 bytes (ASCII and multi-byte UTF-8) are ingested, listed, described, streamed and deleted
//! (a long name's key is split into path segments a file system takes); a bucket whose names an
//! earlier release wrote is read as it is, beside names written now; and a store's refusal that
//! a retry does not mend reaches the client as `Internal`, not `Unavailable`.

use std::path::Path;
use wavesplat_cache::{Limits, Store};
use wavesplat_client::{CacheClient, ClientError, RefineRequest, VolumeKey};
use wavesplat_codec::view::{View, ViewSpec};
use wavesplat_compressor::encode::{compress, CompressOptions, Target, TileChoice};
use wavesplat_compressor::phantom::Phantom;
use wavesplat_net::digest::{hex, sha256};

/// The lengths to check: the shortest, the longest a key of one segment takes on a file
/// system (126 bytes, 252 hex digits), either side of 255 hex digits, and the longest.
const LENGTHS: [usize; 6] = [1, 126, 127, 128, 200, 255];

/// A small volume's `.wsp` bytes; `fraction` makes different contents.
fn small_volume(fraction: f64) -> Vec<u8> {
    let vol = Phantom::SheppLogan.generate([16, 16, 16]);
    let options = CompressOptions {
        target: Target::Fraction(fraction),
        tile: TileChoice::Size(8),
        levels: Some(2),
        ..Default::default()
    };
    compress(&vol, &options, &|_, _| {}).unwrap().bytes
}

/// A name of `len` bytes made of `c` (UTF-8 of any width), with ASCII to make up the length.
fn name_of(c: char, len: usize) -> String {
    let n = len / c.len_utf8();
    let name = format!(
        "{}{}",
        c.to_string().repeat(n),
        "x".repeat(len % c.len_utf8())
    );
    assert_eq!(name.len(), len);
    name
}

/// A node over the object store at `url`, serving on loopback until the returned sender is
/// dropped or sent to; its URL.
async fn node(dir: &Path, url: &str) -> (tokio::sync::oneshot::Sender<()>, String) {
    let store = Store::open_bucket(dir, url, Limits::default(), 1 << 20)
        .await
        .unwrap();
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    tokio::spawn(async move {
        wavesplat_cache::serve(listener, store, async {
            let _ = stopped.await;
        })
        .await
        .unwrap();
    });
    (stop, format!("http://{addr}"))
}

/// Packets as (id, bytes).
type Packets = Vec<(u32, Vec<u8>)>;

/// The packets a whole-volume view is streamed, ordered by id; asserts the stream ends `done`
/// with a header naming `name`.
async fn streamed(c: &mut CacheClient, name: &str) -> Packets {
    let spec = ViewSpec::single(View::new(0.4, 0.3, 32, 32));
    let request = RefineRequest::new(VolumeKey::Name(name.into()), spec);
    let got = c.refine_collect(request, None).await.unwrap();
    assert!(got.done, "{name}");
    assert_eq!(got.header.expect("a header").info.name, name);
    let mut packets: Packets = got.packets.into_iter().map(|p| (p.id, p.data)).collect();
    packets.sort();
    assert!(!packets.is_empty(), "{name}");
    packets
}

/// Every regular file under `dir`, relative to it.
fn files_under(dir: &Path) -> Vec<String> {
    let mut out = Vec::new();
    let mut todo = vec![dir.to_path_buf()];
    while let Some(d) = todo.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let e = e.unwrap();
            if e.file_type().unwrap().is_dir() {
                todo.push(e.path());
            } else {
                let p = e.path();
                out.push(p.strip_prefix(dir).unwrap().to_string_lossy().to_string());
            }
        }
    }
    out.sort();
    out
}

/// Whether a client call failed as `NotFound`.
fn not_found(e: ClientError) -> bool {
    e.code() == Some(tonic::Code::NotFound)
}

/// Names of 1, 126, 127, 128, 200 and 255 bytes, of 1- to 4-byte characters and with a `/`,
/// over two contents: each ingested, listed under its name, described, streamed as the other
/// names of its content are, and deleted; at the end the store holds no file (nor a long name's
/// directories).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn names_of_every_valid_length_live_in_a_file_store() {
    let tmp = tempfile::tempdir().unwrap();
    let bucket = tmp.path().join("bucket");
    let url = format!("file://{}", bucket.display());
    let (_stop, node_url) = node(&tmp.path().join("node"), &url).await;
    let mut c = CacheClient::connect(&node_url).await.unwrap();

    let contents = [small_volume(0.1), small_volume(0.3)];
    let mut named: Vec<(String, usize)> = Vec::new();
    for len in LENGTHS {
        named.push((name_of('a', len), 0));
        if len >= 3 {
            named.push((format!("a/ {}", "b".repeat(len - 3)), 0));
        }
        for ch in ['é', '水', '🌊'] {
            if len >= ch.len_utf8() {
                named.push((name_of(ch, len), 1));
            }
        }
    }
    let mut ids = [0u64; 2];
    for (name, content) in &named {
        let ingested = c.ingest(name, &contents[*content]).await.unwrap();
        assert_eq!(ingested.volume.name, *name);
        ids[*content] = ingested.volume.id;
    }
    assert_ne!(ids[0], ids[1]);

    let mut want: Vec<(String, u64)> = named.iter().map(|(n, i)| (n.clone(), ids[*i])).collect();
    want.sort();
    let listed: Vec<(String, u64)> = c
        .list()
        .await
        .unwrap()
        .into_iter()
        .map(|v| (v.name, v.id))
        .collect();
    assert_eq!(listed, want);

    let mut reference: [Option<Packets>; 2] = [None, None];
    for (name, content) in &named {
        let info = c.describe(&VolumeKey::Name(name.clone())).await.unwrap();
        assert_eq!((&info.name, info.id), (name, ids[*content]));
        let packets = streamed(&mut c, name).await;
        match &reference[*content] {
            Some(r) => assert!(packets == *r, "{name}: other packets than its content's"),
            None => reference[*content] = Some(packets),
        }
    }

    for (i, (name, _)) in named.iter().enumerate() {
        c.delete(&VolumeKey::Name(name.clone())).await.unwrap();
        let gone = c
            .describe(&VolumeKey::Name(name.clone()))
            .await
            .unwrap_err();
        assert!(not_found(gone), "{name}");
        assert_eq!(c.list().await.unwrap().len(), named.len() - i - 1);
    }
    assert_eq!(files_under(&bucket), Vec::<String>::new());
    let names_dir = bucket.join("names");
    assert!(
        !names_dir.exists() || std::fs::read_dir(&names_dir).unwrap().next().is_none(),
        "directories left under names/"
    );
}

/// A bucket as an earlier release wrote it on a file system (a volume object, and name records
/// under one segment of the name's hex: names of up to 126 bytes, the longest such a key could
/// be written for) is read by a cold node: listed, described and streamed; names of every
/// length ingested beside them, names an earlier release gave keys exactly as it did; all
/// deleted, the volume with its last name.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_bucket_an_earlier_release_wrote_is_read_beside_new_names() {
    let tmp = tempfile::tempdir().unwrap();
    let bucket = tmp.path().join("bucket");
    let wsp = small_volume(0.1);
    let sha = sha256(&wsp);
    // The layout of earlier releases, written here as they wrote it.
    let old_key = |name: &str| format!("names/{}", hex(name.as_bytes()));
    let record = [&b"WSPN\x01"[..], &sha[..]].concat();
    let old = ["old".to_string(), name_of('é', 126), name_of('z', 126)];
    std::fs::create_dir_all(bucket.join("volumes")).unwrap();
    std::fs::create_dir_all(bucket.join("names")).unwrap();
    std::fs::write(
        bucket.join(format!("volumes/{}.wspx", hex(&sha))),
        wavesplat_codec::format::index::indexed_layout(&wsp).unwrap(),
    )
    .unwrap();
    for name in &old {
        std::fs::write(bucket.join(old_key(name)), &record).unwrap();
    }

    let url = format!("file://{}", bucket.display());
    let (_stop, node_url) = node(&tmp.path().join("node"), &url).await;
    let mut c = CacheClient::connect(&node_url).await.unwrap();
    let mut want: Vec<String> = old.to_vec();
    want.sort();
    let listed: Vec<String> = c
        .list()
        .await
        .unwrap()
        .into_iter()
        .map(|v| v.name)
        .collect();
    assert_eq!(listed, want);
    let reference = streamed(&mut c, &old[0]).await;
    for name in &old {
        let info = c.describe(&VolumeKey::Name(name.clone())).await.unwrap();
        assert_eq!((&info.name, &info.sha256), (name, &hex(&sha)));
        assert!(streamed(&mut c, name).await == reference, "{name}");
    }

    // Names of every length added to the same content; the short ones keyed as before.
    let added: Vec<String> = LENGTHS.iter().map(|&len| name_of('n', len)).collect();
    for name in &added {
        let ingested = c.ingest(name, &wsp).await.unwrap();
        assert!(ingested.existed, "{name}");
        if name.len() <= 126 {
            assert!(bucket.join(old_key(name)).is_file(), "{name}");
        }
    }
    want.extend(added.iter().cloned());
    want.sort();
    let listed: Vec<String> = c
        .list()
        .await
        .unwrap()
        .into_iter()
        .map(|v| v.name)
        .collect();
    assert_eq!(listed, want);
    for name in &added {
        assert!(streamed(&mut c, name).await == reference, "{name}");
    }

    for name in old.iter().chain(&added) {
        c.delete(&VolumeKey::Name(name.clone())).await.unwrap();
        assert!(not_found(
            c.describe(&VolumeKey::Name(name.clone()))
                .await
                .unwrap_err()
        ));
    }
    assert!(c.list().await.unwrap().is_empty());
    assert_eq!(files_under(&bucket), Vec::<String>::new());
}

/// A store that refuses a request for good (here a file where the names' directory should be,
/// which no retry mends) fails the ingest as `Internal` naming the refusal, not as
/// `Unavailable`, which tells a client to try again.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_refusal_of_the_store_is_not_reported_as_unavailable() {
    let tmp = tempfile::tempdir().unwrap();
    let bucket = tmp.path().join("bucket");
    let url = format!("file://{}", bucket.display());
    let (_stop, node_url) = node(&tmp.path().join("node"), &url).await;
    std::fs::write(bucket.join("names"), b"not a directory").unwrap();
    let mut c = CacheClient::connect(&node_url).await.unwrap();
    let e = c.ingest("v", &small_volume(0.1)).await.unwrap_err();
    assert_eq!(e.code(), Some(tonic::Code::Internal), "{e}");
    assert!(e.to_string().contains("object store refused"), "{e}");
}
