//! Bounded load test on loopback: one in-process cache (sled in a tempdir) holding a
//! Shepp–Logan phantom, then rounds of 1, 32 and 64 concurrent refinement streams started at
//! once (each a different view, each reading every packet). Prints a CSV: clients, packets/s,
//! MB/s, first-packet latency p50/p99 (ms, from opening the stream to its first packet), wall
//! time; on stderr, the CPU time of planning one view (the bulk of a session start). No
//! assertions; figures go to BENCHMARKS.md.
//!
//! `cargo run --release -p wavesplat-cache --example load [EDGE] [ROUNDS]`

use std::time::{Duration, Instant};
use wavesplat_cache::{Limits, Store};
use wavesplat_client::{CacheClient, RefineEvent, RefineRequest, VolumeKey};
use wavesplat_codec::view::ViewSpec;
use wavesplat_compressor::encode::{compress, CompressOptions, Target, TileChoice};
use wavesplat_compressor::phantom::Phantom;
use wavesplat_viewer::View;

async fn one_stream(url: String, key: VolumeKey, i: usize) -> (Duration, u64, u64) {
    let mut c = CacheClient::connect(&url).await.expect("connect");
    let view = ViewSpec::single(View::new(0.1 * i as f64, 0.05 * i as f64, 256, 256));
    let t0 = Instant::now();
    let mut s = c
        .refine(RefineRequest::new(key, view))
        .await
        .expect("refine");
    let mut first = None;
    let (mut packets, mut bytes) = (0u64, 0u64);
    while let Some(e) = s.next().await.expect("stream") {
        match e {
            RefineEvent::Packet(p) => {
                first.get_or_insert_with(|| t0.elapsed());
                packets += 1;
                bytes += p.data.len() as u64;
            }
            RefineEvent::Done { .. } => break,
            RefineEvent::Header(_) => {}
        }
    }
    (first.unwrap_or_default(), packets, bytes)
}

fn percentile(sorted: &[Duration], p: f64) -> f64 {
    let i = ((sorted.len() as f64 - 1.0) * p).round() as usize;
    sorted[i].as_secs_f64() * 1e3
}

#[tokio::main]
async fn main() {
    let args: Vec<String> = std::env::args().collect();
    let edge: usize = args.get(1).and_then(|a| a.parse().ok()).unwrap_or(96);
    let rounds: usize = args.get(2).and_then(|a| a.parse().ok()).unwrap_or(3);
    let vol = Phantom::SheppLogan.generate([edge; 3]);
    let bytes = compress(
        &vol,
        &CompressOptions {
            target: Target::Fraction(0.1),
            tile: TileChoice::Size(16),
            layers: Some(4),
            levels: Some(3),
            ..Default::default()
        },
        &|_, _| {},
    )
    .expect("compress")
    .bytes;
    // Where a session start's CPU goes: planning its view (visibility weights, per-packet
    // priorities), timed here without the network.
    let header = wavesplat_codec::format::parse_file(&bytes).unwrap().header;
    let plan = |i: usize| {
        let view = ViewSpec::single(View::new(0.1 * i as f64, 0.05 * i as f64, 256, 256));
        wavesplat_cache::priority::Priority::new(&header, &view).unwrap()
    };
    let t = Instant::now();
    plan(0);
    let first = t.elapsed();
    let t = Instant::now();
    for i in 1..=64 {
        std::hint::black_box(plan(i));
    }
    eprintln!(
        "view planning (Priority::new): first {:.2} ms (builds per-family tables), then {:.3} ms per view",
        first.as_secs_f64() * 1e3,
        t.elapsed().as_secs_f64() * 1e3 / 64.0
    );
    let dir = tempfile::tempdir().unwrap();
    let store = Store::open(dir.path(), Limits::default()).unwrap();
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let url = format!("http://{}", listener.local_addr().unwrap());
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let options = wavesplat_cache::ServeOptions {
        fairness: wavesplat_cache::service::Fairness {
            max_streams_per_caller: 1024,
            ..Default::default()
        },
        ..Default::default()
    };
    let server = tokio::spawn(wavesplat_cache::serve_with(
        listener,
        store,
        options,
        async {
            let _ = stopped.await;
        },
    ));
    let mut c = CacheClient::connect(&url).await.unwrap();
    let info = c.ingest("phantom", &bytes).await.unwrap().volume;
    eprintln!(
        "volume {edge}^3: {} bytes, {} packets, {} tiles",
        info.file_bytes, info.packet_count, info.tile_count
    );
    println!(
        "clients,rounds,packets_per_s,mb_per_s,first_packet_p50_ms,first_packet_p99_ms,wall_s"
    );
    for clients in [1usize, 32, 64] {
        let mut firsts = Vec::new();
        let (mut packets, mut total) = (0u64, 0u64);
        let t0 = Instant::now();
        for _ in 0..rounds {
            let tasks: Vec<_> = (0..clients)
                .map(|i| tokio::spawn(one_stream(url.clone(), VolumeKey::Id(info.id), i)))
                .collect();
            for t in tasks {
                let (f, p, b) = t.await.unwrap();
                firsts.push(f);
                packets += p;
                total += b;
            }
        }
        let wall = t0.elapsed().as_secs_f64();
        firsts.sort();
        println!(
            "{clients},{rounds},{:.0},{:.2},{:.2},{:.2},{:.3}",
            packets as f64 / wall,
            total as f64 / wall / 1e6,
            percentile(&firsts, 0.5),
            percentile(&firsts, 0.99),
            wall
        );
    }
    let _ = stop.send(());
    server.await.unwrap().unwrap();
}
