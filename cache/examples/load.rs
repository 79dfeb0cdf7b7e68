//! Bounded load test on loopback: one in-process cache (sled in a tempdir) holding a
//! Shepp–Logan phantom, then rounds of 1, 32 and 64 concurrent refinement streams started at
//! once (each a different view, each reading every packet), first in plaintext without tokens,
//! then over TLS with tokens (a CA and certificate made here with rcgen, a `read` token), on
//! the same store in the same process. Prints a CSV: transport, clients, packets/s, MB/s,
//! connect p50/p99 (TCP, and for TLS the handshake), first-packet latency p50/p99 (ms, from
//! opening the stream to its first packet) and from the start of connecting, wall time; on
//! stderr, the CPU time of planning one view (the bulk of a session start). No assertions;
//! figures go to BENCHMARKS.md.
//!
//! With `WAVESPLAT_LOAD_STORE=s3://BUCKET/PREFIX` (and the `AWS_*` variables), two more rows
//! sets: one node over that object store, then two nodes over it with the clients alternating
//! between them (in this process, on the same cores: what the bucket path costs a node, not how
//! nodes scale).
//!
//! With `WAVESPLAT_LOAD_URLS=http://A,http://B`, only rows against those nodes (started
//! elsewhere, e.g. each pinned to a core with `taskset`), the clients alternating between them.
//!
//! `cargo run --release -p wavesplat-cache --example load [EDGE] [ROUNDS]`

use std::sync::Arc;
use std::time::{Duration, Instant};
use wavesplat_cache::{Limits, Store};
use wavesplat_client::{
    CacheClient, ConnectOptions, Credentials, RefineEvent, RefineRequest, VolumeKey,
};
use wavesplat_codec::view::ViewSpec;
use wavesplat_compressor::encode::{compress, CompressOptions, Target, TileChoice};
use wavesplat_compressor::phantom::Phantom;
use wavesplat_net::{Security, Tokens};
use wavesplat_viewer::View;

const READ_TOKEN: &str = "0123456789abcdef-load-read";

/// One stream's times: connecting, first packet after opening the stream, first packet after
/// starting to connect; and its packets and bytes.
struct StreamTimes {
    connect: Duration,
    first: Duration,
    first_from_connect: Duration,
    packets: u64,
    bytes: u64,
}

async fn one_stream(url: String, options: ConnectOptions, key: VolumeKey, i: usize) -> StreamTimes {
    let t_connect = Instant::now();
    let mut c = CacheClient::connect_with(&url, &options)
        .await
        .expect("connect");
    let connect = t_connect.elapsed();
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
                first.get_or_insert_with(|| (t0.elapsed(), t_connect.elapsed()));
                packets += 1;
                bytes += p.data.len() as u64;
            }
            RefineEvent::Done { .. } => break,
            RefineEvent::Header(_) => {}
        }
    }
    let (first, first_from_connect) = first.unwrap_or_default();
    StreamTimes {
        connect,
        first,
        first_from_connect,
        packets,
        bytes,
    }
}

/// A CA and a certificate for 127.0.0.1 signed by it, written into `dir`; returns the CA's
/// path and the server's TLS settings.
fn pki(dir: &std::path::Path) -> (std::path::PathBuf, tonic::transport::ServerTlsConfig) {
    let mut ca_params = rcgen::CertificateParams::new(Vec::<String>::new()).unwrap();
    ca_params.is_ca = rcgen::IsCa::Ca(rcgen::BasicConstraints::Unconstrained);
    let ca_key = rcgen::KeyPair::generate().unwrap();
    let ca = ca_params.self_signed(&ca_key).unwrap();
    let params = rcgen::CertificateParams::new(vec!["127.0.0.1".to_string()]).unwrap();
    let key = rcgen::KeyPair::generate().unwrap();
    let cert = params.signed_by(&key, &ca, &ca_key).unwrap();
    let (ca_path, cert_path, key_path) = (
        dir.join("ca.pem"),
        dir.join("cert.pem"),
        dir.join("key.pem"),
    );
    std::fs::write(&ca_path, ca.pem()).unwrap();
    std::fs::write(&cert_path, cert.pem()).unwrap();
    std::fs::write(&key_path, key.serialize_pem()).unwrap();
    (
        ca_path,
        wavesplat_net::tls::server_tls(&cert_path, &key_path).unwrap(),
    )
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
        wavesplat_cache::Priority::new(&header, &view).unwrap()
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
    let store = Store::open(dir.path().join("db"), Limits::default()).unwrap();
    let (ca, tls) = pki(dir.path());
    let tokens = Arc::new(
        Tokens::parse(&format!(
            "load read {READ_TOKEN}\nadmin admin 0123456789abcdef-load-admin\n"
        ))
        .unwrap(),
    );
    println!(
        "transport,clients,rounds,packets_per_s,mb_per_s,connect_p50_ms,connect_p99_ms,first_packet_p50_ms,first_packet_p99_ms,first_from_connect_p99_ms,wall_s"
    );
    let mut id = None;
    let mut external: Vec<String> = Vec::new();
    let mut configurations = vec![
        (
            "plaintext",
            vec![store.clone()],
            Security::default(),
            ConnectOptions::default(),
        ),
        (
            "tls+tokens",
            vec![store.clone()],
            Security {
                tls: Some(tls),
                tokens: Some(tokens),
                insecure: false,
            },
            ConnectOptions {
                ca: Some(ca.clone()),
                credentials: Credentials::token(READ_TOKEN).unwrap(),
            },
        ),
    ];
    if let Ok(url) = std::env::var("WAVESPLAT_LOAD_STORE") {
        let node = |n: &str| {
            let path = dir.path().join(n);
            let url = url.clone();
            async move {
                Store::open_bucket(path, &url, Limits::default(), 256 << 20)
                    .await
                    .unwrap()
            }
        };
        let one = node("node1").await;
        let two = node("node2").await;
        configurations.push((
            "bucket-1-node",
            vec![one.clone()],
            Security::default(),
            ConnectOptions::default(),
        ));
        configurations.push((
            "bucket-2-nodes",
            vec![one, two],
            Security::default(),
            ConnectOptions::default(),
        ));
    }
    if let Ok(list) = std::env::var("WAVESPLAT_LOAD_URLS") {
        // Nodes started elsewhere (e.g. pinned to cores with taskset): plaintext rows only.
        configurations.clear();
        configurations.push((
            "external",
            Vec::new(),
            Security::default(),
            ConnectOptions::default(),
        ));
        external = list.split(',').map(str::to_string).collect();
    }
    for (transport, nodes, security, options) in configurations {
        let mut urls = external.clone();
        let mut servers = Vec::new();
        for node in nodes {
            let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
            let port = listener.local_addr().unwrap().port();
            urls.push(match transport {
                "tls+tokens" => format!("https://127.0.0.1:{port}"),
                _ => format!("http://127.0.0.1:{port}"),
            });
            let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
            let serve_options = wavesplat_cache::ServeOptions {
                security: security.clone(),
                fairness: wavesplat_cache::service::Fairness {
                    max_streams_per_caller: 1024,
                    ..Default::default()
                },
            };
            let server = tokio::spawn(wavesplat_cache::serve_with(
                listener,
                node,
                serve_options,
                async {
                    let _ = stopped.await;
                },
            ));
            servers.push((stop, server));
        }
        // Ingest is idempotent by content; the TLS rows read what the plaintext rows ingested
        // (their token may only read).
        let volume = match (transport, id) {
            ("tls+tokens", Some(id)) => id,
            _ => {
                let mut c = CacheClient::connect_with(&urls[0], &options).await.unwrap();
                let info = c.ingest("phantom", &bytes).await.unwrap().volume;
                eprintln!(
                    "{transport}: volume {edge}^3: {} bytes, {} packets, {} tiles",
                    info.file_bytes, info.packet_count, info.tile_count
                );
                *id.insert(info.id)
            }
        };
        for clients in [1usize, 32, 64] {
            let (mut connects, mut firsts, mut from_connect) = (Vec::new(), Vec::new(), Vec::new());
            let (mut packets, mut total) = (0u64, 0u64);
            let t0 = Instant::now();
            for _ in 0..rounds {
                let tasks: Vec<_> = (0..clients)
                    .map(|i| {
                        tokio::spawn(one_stream(
                            urls[i % urls.len()].clone(),
                            options.clone(),
                            VolumeKey::Id(volume),
                            i,
                        ))
                    })
                    .collect();
                for t in tasks {
                    let s = t.await.unwrap();
                    connects.push(s.connect);
                    firsts.push(s.first);
                    from_connect.push(s.first_from_connect);
                    packets += s.packets;
                    total += s.bytes;
                }
            }
            let wall = t0.elapsed().as_secs_f64();
            connects.sort();
            firsts.sort();
            from_connect.sort();
            println!(
                "{transport},{clients},{rounds},{:.0},{:.2},{:.2},{:.2},{:.2},{:.2},{:.2},{:.3}",
                packets as f64 / wall,
                total as f64 / wall / 1e6,
                percentile(&connects, 0.5),
                percentile(&connects, 0.99),
                percentile(&firsts, 0.5),
                percentile(&firsts, 0.99),
                percentile(&from_connect, 0.99),
                wall
            );
        }
        for (stop, server) in servers {
            let _ = stop.send(());
            server.await.unwrap().unwrap();
        }
    }
}
