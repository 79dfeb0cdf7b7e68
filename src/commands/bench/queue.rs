//! `wavesplat bench queue`: the job queue's own speed, without compression. For the embedded
//! store (one orchestrator) and PostgreSQL (one and two orchestrators over one database, a
//! throwaway server started here), all on loopback in this process: submitting an archive of
//! N tiny jobs as `archive submit` does (one RPC per job), then W workers that lease and
//! report each job at once (leases per second: the queue's ceiling), then the latency of a
//! tiny job from submission to done with idle workers polling. Writes `queue.csv` and prints a
//! table. Nothing is asserted; the tests assert the queue's behaviour.

use anyhow::{bail, Context, Result};
use clap::Args;
use std::io::Write;
use std::path::PathBuf;
use std::time::{Duration, Instant};
use wavesplat_harness::postgres::PostgresServer;
use wavesplat_orchestrator::model::{JobOptions, JobSpec, Source};
use wavesplat_orchestrator::{Backend, PostgresQueue, QueueOptions, ServiceOptions, Store};
use wavesplat_orchestrator_client as client;
use wavesplat_proto::pb;
use wavesplat_viewer::walk::percentile;

/// Arguments of `wavesplat bench queue`.
#[derive(Args, Debug)]
pub struct QueueBenchArgs {
    /// Directory for `queue.csv`.
    #[arg(long, default_value = "wavesplat-queue-bench")]
    pub out: PathBuf,
    /// Jobs in the archive.
    #[arg(long, default_value_t = 10_000)]
    pub jobs: usize,
    /// Workers leasing at once.
    #[arg(long, default_value_t = 8)]
    pub workers: usize,
    /// Tiny jobs whose submission-to-done latency is measured (one at a time).
    #[arg(long, default_value_t = 200)]
    pub latency_jobs: usize,
    /// How often an idle worker asks again, in ms (the orchestrator's --poll-ms).
    #[arg(long, default_value_t = 50)]
    pub poll_ms: u64,
    /// Leave PostgreSQL out (no server installed).
    #[arg(long)]
    pub no_postgres: bool,
}

struct Row {
    store: &'static str,
    orchestrators: usize,
    submit_s: f64,
    leases_s: f64,
    latency_ms: Vec<f64>,
}

fn spec(i: usize, tag: &str) -> JobSpec {
    let mut sha = [0u8; 32];
    sha[..8].copy_from_slice(&(i as u64 + 1).to_be_bytes());
    sha[8] = tag.len() as u8;
    JobSpec {
        name: format!("{tag}{i}"),
        source: Source::Path(format!("/archive/{tag}{i}.nii").into()),
        sha256: sha,
        raw: None,
        channel: None,
        options: JobOptions::default(),
        part: None,
    }
}

fn delivered() -> pb::finish_request::Outcome {
    pb::finish_request::Outcome::Delivered(pb::Delivered {
        cache_volume_id: 1,
        output_bytes: 1,
        voxels: 1,
        existed: false,
        sha256: "ab".repeat(32),
    })
}

/// Starts one in-process orchestrator per backend; returns their URLs.
async fn serve_all(backends: Vec<Backend>, cfg: ServiceOptions) -> Result<Vec<String>> {
    let mut urls = Vec::new();
    for b in backends {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
        urls.push(format!("http://{}", listener.local_addr()?));
        tokio::spawn(async move {
            if let Err(e) =
                wavesplat_orchestrator::serve(listener, b, cfg, std::future::pending()).await
            {
                tracing::error!(error = %e, "bench orchestrator stopped");
            }
        });
    }
    Ok(urls)
}

/// A worker that leases and reports at once until `stop_when_idle` finds nothing queued.
async fn fake_worker(url: String, id: String, stop_when_idle: bool) -> Result<usize> {
    let mut c = client::connect(&url).await?;
    let mut n = 0;
    loop {
        let r = c
            .lease(pb::LeaseRequest {
                worker: id.clone(),
                parts_only: false,
            })
            .await?
            .into_inner();
        let Some(lease) = r.lease else {
            if stop_when_idle {
                return Ok(n);
            }
            tokio::time::sleep(Duration::from_millis(u64::from(r.retry_after_ms.max(1)))).await;
            continue;
        };
        c.finish(client::HeldLease::of(&lease).request(pb::FinishRequest {
            job_id: lease.job_id,
            attempt: lease.attempt,
            worker: id.clone(),
            outcome: Some(delivered()),
        }))
        .await?;
        n += 1;
    }
}

async fn measure(store: &'static str, urls: Vec<String>, a: &QueueBenchArgs) -> Result<Row> {
    let mut c = client::connect(&urls[0]).await?;
    let t = Instant::now();
    for i in 0..a.jobs {
        client::submit(&mut c, &spec(i, "a"), None).await?;
    }
    let submit_s = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let tasks: Vec<_> = (0..a.workers)
        .map(|w| {
            // Worker w starts at orchestrator w mod n and fails over to the others.
            let mut order: Vec<&str> = urls.iter().map(String::as_str).collect();
            order.rotate_left(w % urls.len());
            tokio::spawn(fake_worker(order.join(","), format!("w{w}"), true))
        })
        .collect();
    let mut leased = 0;
    for task in tasks {
        leased += task.await??;
    }
    let leases_s = t.elapsed().as_secs_f64();
    if leased != a.jobs {
        bail!("{store}: {leased} of {} jobs leased", a.jobs);
    }
    // Latency: idle workers polling; one tiny job at a time.
    let idle: Vec<_> = (0..a.workers)
        .map(|w| {
            let url = urls[w % urls.len()].clone();
            tokio::spawn(fake_worker(url, format!("idle{w}"), false))
        })
        .collect();
    let mut latency_ms = Vec::with_capacity(a.latency_jobs);
    for i in 0..a.latency_jobs {
        // Submissions spread over the poll interval: one right after the last job's done
        // would always land just after the idle workers asked.
        let spread = (i as u64 * 7919) % a.poll_ms.max(1);
        tokio::time::sleep(Duration::from_millis(spread)).await;
        let t = Instant::now();
        let job = client::submit(&mut c, &spec(i, "lat"), None)
            .await?
            .job
            .context("no job")?;
        loop {
            let j = c.get_job(pb::JobRef { id: job.id }).await?.into_inner();
            if client::convert::state_name(j.state) == "done" {
                break;
            }
            tokio::time::sleep(Duration::from_millis(1)).await;
        }
        latency_ms.push(t.elapsed().as_secs_f64() * 1e3);
    }
    for t in idle {
        t.abort();
    }
    Ok(Row {
        store,
        orchestrators: urls.len(),
        submit_s,
        leases_s,
        latency_ms,
    })
}

/// Runs the subcommand.
pub fn run(a: QueueBenchArgs) -> Result<()> {
    if a.jobs == 0 || a.workers == 0 {
        bail!("--jobs and --workers must be at least 1");
    }
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let cfg = ServiceOptions {
        queue: QueueOptions::default(),
        poll_ms: a.poll_ms.max(1),
        max_upload_bytes: 1 << 20,
    };
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?;
    let mut rows = Vec::new();
    outln!(
        "{} jobs, {} workers leasing and reporting at once, latency of {} tiny jobs (idle workers poll every {} ms)",
        a.jobs,
        a.workers,
        a.latency_jobs,
        a.poll_ms
    );
    let dir = tempfile::tempdir()?;
    rows.push(rt.block_on(async {
        let store = Store::open(dir.path().join("sled"))?;
        let urls = serve_all(vec![store.into()], cfg).await?;
        measure("sled", urls, &a).await
    })?);
    let pg = if a.no_postgres {
        None
    } else {
        Some(PostgresServer::start().context("starting PostgreSQL (or give --no-postgres)")?)
    };
    if let Some(pg) = &pg {
        for n in [1usize, 2] {
            let db = format!("bench{n}");
            pg.create_database(&db)?;
            let url = pg.url_with_password(&db);
            rows.push(rt.block_on(async {
                let mut backends = Vec::new();
                for _ in 0..n {
                    backends.push(
                        PostgresQueue::connect(&url, Default::default())
                            .await?
                            .into(),
                    );
                }
                let urls = serve_all(backends, cfg).await?;
                measure("postgres", urls, &a).await
            })?);
        }
    }
    let path = a.out.join("queue.csv");
    let mut f =
        std::fs::File::create(&path).with_context(|| format!("creating {}", path.display()))?;
    writeln!(
        f,
        "store,orchestrators,workers,jobs,submit_s,submits_per_s,leases_s,leases_per_s,latency_p50_ms,latency_p95_ms,latency_max_ms"
    )?;
    outln!(
        "{:<9} {:>5} {:>10} {:>10} {:>11} {:>11} {:>9}",
        "store",
        "orch",
        "submit/s",
        "leases/s",
        "lat p50 ms",
        "lat p95 ms",
        "max ms"
    );
    for r in &rows {
        let p = |q: f64| percentile(&r.latency_ms, q).unwrap_or(f64::NAN);
        let (p50, p95, max) = (p(50.0), p(95.0), p(100.0));
        writeln!(
            f,
            "{},{},{},{},{:.3},{:.1},{:.3},{:.1},{:.2},{:.2},{:.2}",
            r.store,
            r.orchestrators,
            a.workers,
            a.jobs,
            r.submit_s,
            a.jobs as f64 / r.submit_s,
            r.leases_s,
            a.jobs as f64 / r.leases_s,
            p50,
            p95,
            max
        )?;
        outln!(
            "{:<9} {:>5} {:>10.0} {:>10.0} {:>11.1} {:>11.1} {:>9.1}",
            r.store,
            r.orchestrators,
            a.jobs as f64 / r.submit_s,
            a.jobs as f64 / r.leases_s,
            p50,
            p95,
            max
        );
    }
    outln!("wrote {}", path.display());
    drop(rt);
    Ok(())
}
