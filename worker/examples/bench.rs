//! Throughput of the orchestrator: 20 tiny volumes (raw f32 Shepp–Logan, 16×16×(16..=35)),
//! one in-process cache and orchestrator on loopback, 1 then 2 in-process workers (one
//! compression thread each). Writes CSV to stdout (or the file given as the first argument):
//! workers, jobs, wall seconds, jobs/s, voxels/s, mean attempt time (lease → finish) and the
//! queue overhead per job (wall × workers / jobs − mean attempt time).
//!
//! `cargo run --release -p wavesplat-worker --example bench -- bench.csv`

use std::io::Write;
use std::time::{Duration, Instant};
use wavesplat_compressor::phantom::Phantom;
use wavesplat_orchestrator::{JobOptions, QueueOptions, ServiceOptions, Store};
use wavesplat_orchestrator_client as client;
use wavesplat_orchestrator_client::convert::state_name;
use wavesplat_worker::archive;
use wavesplat_worker::WorkerOptions;

const JOBS: usize = 20;

async fn run(workers: usize) -> String {
    let dir = tempfile::tempdir().unwrap();
    let arch = dir.path().join("arch");
    std::fs::create_dir(&arch).unwrap();
    for i in 0..JOBS {
        let dims = [16, 16, 16 + i];
        let v = Phantom::SheppLogan.generate(dims).to_interleaved();
        let bytes: Vec<u8> = v.iter().flat_map(|x| x.to_le_bytes()).collect();
        let name = format!("v{i}_{}x{}x{}_f32.raw", dims[0], dims[1], dims[2]);
        std::fs::write(arch.join(name), bytes).unwrap();
    }
    let cache_store =
        wavesplat_cache::Store::open(dir.path().join("cache"), Default::default()).unwrap();
    let cl = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let cache_url = format!("http://{}", cl.local_addr().unwrap());
    tokio::spawn(wavesplat_cache::serve(
        cl,
        cache_store,
        std::future::pending(),
    ));
    let store = Store::open(dir.path().join("orch")).unwrap();
    let ol = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let orch_url = format!("http://{}", ol.local_addr().unwrap());
    let config = ServiceOptions {
        queue: QueueOptions {
            lease_ms: 10_000,
            heartbeat_ms: 1_000,
            ..QueueOptions::default()
        },
        poll_ms: 20,
        ..ServiceOptions::default()
    };
    tokio::spawn(wavesplat_orchestrator::serve(
        ol,
        store,
        config,
        std::future::pending(),
    ));
    tokio::time::sleep(Duration::from_millis(100)).await;

    let start = Instant::now();
    let mut c = client::connect(&orch_url).await.unwrap();
    let scan = archive::scan(&arch).unwrap();
    let opts = JobOptions {
        levels: Some(2),
        ..JobOptions::default()
    };
    for f in &scan.found {
        let (spec, _) = archive::job_spec(f, &opts, false).unwrap();
        client::submit(&mut c, &spec, None).await.unwrap();
    }
    let submitted = start.elapsed().as_secs_f64();
    for w in 0..workers {
        let cfg = WorkerOptions {
            connect: Default::default(),
            orchestrator: orch_url.clone(),
            cache: cache_url.clone(),
            threads: 1,
            id: format!("bench-{w}"),
            max_jobs: None,
            pause_before_upload_ms: 0,
            pause_before_part_report_ms: 0,
        };
        tokio::spawn(wavesplat_worker::run(cfg, std::future::pending()));
    }
    let jobs = loop {
        let js = client::list(&mut c).await.unwrap();
        if js.iter().all(|j| state_name(j.state) == "done") {
            break js;
        }
        tokio::time::sleep(Duration::from_millis(5)).await;
    };
    let wall = start.elapsed().as_secs_f64();
    let voxels: u64 = jobs.iter().map(|j| j.voxels).sum();
    let mean_run = jobs.iter().map(|j| j.run_ms as f64).sum::<f64>() / JOBS as f64 / 1000.0;
    let overhead = wall * workers as f64 / JOBS as f64 - mean_run;
    format!(
        "{workers},{JOBS},{wall:.3},{:.2},{:.0},{:.4},{:.4},{:.4}",
        JOBS as f64 / wall,
        voxels as f64 / wall,
        submitted / JOBS as f64,
        mean_run,
        overhead
    )
}

fn main() {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap();
    let mut out = String::from(
        "workers,jobs,wall_s,jobs_per_s,voxels_per_s,submit_s_per_job,mean_attempt_s,queue_overhead_s_per_job\n",
    );
    for w in [1, 2] {
        let line = rt.block_on(run(w));
        eprintln!("{line}");
        out.push_str(&line);
        out.push('\n');
    }
    match std::env::args().nth(1) {
        Some(p) => std::fs::write(&p, out).unwrap(),
        None => std::io::stdout().write_all(out.as_bytes()).unwrap(),
    }
}
