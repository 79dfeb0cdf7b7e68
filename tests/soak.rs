//! Soak test, bounded in time: 32 clients stream with view changes and a small credit while
//! volumes are ingested and deleted, and the cache (the real binary) is SIGKILLed and restarted
//! twice. Every client resumes with what it holds and ends with every packet of its volume,
//! byte for byte; no acknowledged volume is lost.

mod common;

use std::collections::BTreeMap;
use std::process::Child;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use wavesplat_client::{CacheClient, ClientError, RefineEvent, RefineRequest, VolumeKey};
use wavesplat_codec::format::parse_file;
use wavesplat_codec::view::{View, ViewSpec};
use wavesplat_compressor::encode::CompressOptions;
use wavesplat_compressor::phantom::Phantom;

const CLIENTS: usize = 32;
const LIMIT: Duration = Duration::from_secs(100);

fn file(dims: [usize; 3], fraction: f64) -> Vec<u8> {
    let options = CompressOptions {
        layers: Some(2),
        levels: Some(3),
        ..common::phantom_options(fraction)
    };
    common::phantom_file(Phantom::SheppLogan, dims, &options)
}

fn start(db: &std::path::Path) -> (Child, String) {
    let server = common::cache_process(db);
    let url = server.url();
    (server.into_parts().0, url)
}

fn view(i: usize, k: usize) -> ViewSpec {
    ViewSpec::single(View::new(
        0.4 * i as f64 + 0.9 * k as f64,
        0.3 * k as f64,
        48,
        48,
    ))
}

/// One attempt: streams until done (`Ok(true)`), keeping what arrives in `held`.
async fn attempt(
    url: &str,
    name: &str,
    i: usize,
    held: &mut BTreeMap<u32, Vec<u8>>,
    received: &AtomicUsize,
) -> Result<bool, ClientError> {
    let mut c = CacheClient::connect(url).await?;
    let req = RefineRequest::new(VolumeKey::Name(name.into()), view(i, held.len()))
        .with_credit(8 << 10)
        .holding(held.keys().copied().collect(), false);
    let mut s = c.refine(req).await?;
    let mut n = 0usize;
    while let Some(e) = s.next().await? {
        match e {
            RefineEvent::Packet(p) => {
                s.control().grant(p.data.len() as u64).await?;
                held.insert(p.id, p.data);
                received.fetch_add(1, Ordering::SeqCst);
                n += 1;
                if n.is_multiple_of(7) {
                    s.control().set_view(&view(i, n)).await?;
                }
                tokio::time::sleep(Duration::from_millis(8)).await;
            }
            RefineEvent::Done { .. } => return Ok(true),
            RefineEvent::Header(_) => {}
        }
    }
    Ok(false)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn thirty_two_clients_survive_ingests_deletes_and_two_sigkills() {
    let t0 = Instant::now();
    let dir = tempfile::tempdir().unwrap();
    let bases: Vec<Vec<u8>> = [[40, 40, 40], [48, 40, 32], [32, 48, 40]]
        .into_iter()
        .map(|d| file(d, 0.15))
        .collect();
    let (child, url0) = start(dir.path());
    let child = Arc::new(Mutex::new(child));
    let url = Arc::new(Mutex::new(url0.clone()));
    let mut c = CacheClient::connect(&url0).await.unwrap();
    for (k, b) in bases.iter().enumerate() {
        c.ingest(&format!("base{k}"), b).await.unwrap();
    }

    // Clients.
    let bases = Arc::new(bases);
    let received = Arc::new(AtomicUsize::new(0));
    let mut clients = Vec::new();
    for i in 0..CLIENTS {
        let (url, bases, received) = (url.clone(), bases.clone(), received.clone());
        clients.push(tokio::spawn(async move {
            let k = i % bases.len();
            let mut held = BTreeMap::new();
            let mut attempts = 0;
            loop {
                assert!(t0.elapsed() < LIMIT, "client {i} did not finish");
                let u = url.lock().unwrap().clone();
                attempts += 1;
                if let Ok(true) = attempt(&u, &format!("base{k}"), i, &mut held, &received).await {
                    break;
                }
                tokio::time::sleep(Duration::from_millis(50)).await;
            }
            (k, held, attempts)
        }));
    }

    // Ingests and deletes of other volumes, recorded as acknowledged.
    let stop = Arc::new(AtomicBool::new(false));
    let ingester = {
        let (url, stop) = (url.clone(), stop.clone());
        tokio::spawn(async move {
            let mut must_exist: BTreeMap<String, String> = BTreeMap::new();
            let mut k = 0usize;
            while !stop.load(Ordering::SeqCst) {
                let u = url.lock().unwrap().clone();
                let Ok(mut c) = CacheClient::connect(&u).await else {
                    tokio::time::sleep(Duration::from_millis(50)).await;
                    continue;
                };
                let name = format!("tmp{k}");
                let bytes = file([24, 24, 16 + (k % 9)], 0.2);
                if let Ok(r) = c.ingest(&name, &bytes).await {
                    must_exist.insert(name, r.volume.sha256);
                }
                // Delete every other acknowledged volume.
                if k % 2 == 1 {
                    let victim = format!("tmp{}", k - 1);
                    if must_exist.contains_key(&victim) {
                        match c.delete(&VolumeKey::Name(victim.clone())).await {
                            Ok(_) => {
                                must_exist.remove(&victim);
                            }
                            // The delete may or may not have happened: no promise either way.
                            Err(_) => {
                                must_exist.remove(&victim);
                            }
                        }
                    }
                }
                k += 1;
            }
            (must_exist, k)
        })
    };

    // Two SIGKILLs while all that runs, each once the clients have made some progress (so
    // streams are cut mid-way, whatever the machine's speed).
    for _ in 0..2 {
        let mark = received.load(Ordering::SeqCst) + 3 * CLIENTS;
        while received.load(Ordering::SeqCst) < mark {
            assert!(t0.elapsed() < LIMIT, "the clients made no progress");
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
        {
            let mut ch = child.lock().unwrap();
            ch.kill().unwrap();
            ch.wait().unwrap();
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
        let (new, u) = start(dir.path());
        *child.lock().unwrap() = new;
        *url.lock().unwrap() = u;
    }

    let mut resumed = 0;
    for t in clients {
        let (k, held, attempts) = t.await.unwrap();
        let parsed = parse_file(&bases[k]).unwrap();
        assert_eq!(held.len(), parsed.packets.len(), "client of base{k}");
        for (id, data) in &held {
            assert_eq!(data.as_slice(), parsed.packets[*id as usize], "packet {id}");
        }
        resumed += usize::from(attempts > 1);
    }
    stop.store(true, Ordering::SeqCst);
    let (must_exist, ingests) = ingester.await.unwrap();
    let u = url.lock().unwrap().clone();
    let mut c = CacheClient::connect(&u).await.unwrap();
    let listed: BTreeMap<String, String> = c
        .list()
        .await
        .unwrap()
        .into_iter()
        .map(|v| (v.name, v.sha256))
        .collect();
    for (name, sha) in &must_exist {
        assert_eq!(listed.get(name), Some(sha), "acknowledged {name} lost");
    }
    for k in 0..3 {
        assert!(listed.contains_key(&format!("base{k}")));
    }
    assert!(ingests > 4, "only {ingests} ingests ran");
    assert!(resumed > 0, "no client was cut off by a kill");
    let _ = child.lock().unwrap().kill();
    assert!(t0.elapsed() < LIMIT);
}
