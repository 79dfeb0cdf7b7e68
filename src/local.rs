//! The services on loopback in this process, for `demo` and `bench refine`: the cache (sled),
//! optionally the orchestrator (with delivery checks against that cache) and one worker, each
//! on its own port of 127.0.0.1, on one tokio runtime. They are the same servers `wavesplat
//! serve …` and `wavesplat worker` run; only the wiring is local. Dropping the stack shuts
//! them down gracefully (streams end, stores flush).

use anyhow::{Context, Result};
use std::path::Path;
use tokio::sync::watch;

/// Services running in this process.
pub struct LocalStack {
    runtime: tokio::runtime::Runtime,
    stop: watch::Sender<bool>,
    tasks: Vec<tokio::task::JoinHandle<Result<()>>>,
    /// `http://127.0.0.1:PORT` of the cache.
    pub cache_url: String,
    /// `http://127.0.0.1:PORT` of the orchestrator, when started.
    pub orchestrator_url: Option<String>,
}

async fn stopped(mut rx: watch::Receiver<bool>) {
    let _ = rx.wait_for(|s| *s).await;
}

impl LocalStack {
    /// Starts the cache on `db/cache` and, with `batch`, the orchestrator on
    /// `db/orchestrator` and a worker with `threads` compression threads (0: one per core).
    pub fn start(db: &Path, batch: bool, threads: usize) -> Result<LocalStack> {
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .thread_name("wavesplat-local")
            .build()
            .context("starting the async runtime")?;
        // Lazy gRPC clients (the delivery check, the worker's) need the runtime as context.
        let _context = runtime.enter();
        let (stop, stop_rx) = watch::channel(false);
        let mut tasks = Vec::new();
        let cache_store = wavesplat_cache::store::Store::open(
            db.join("cache"),
            wavesplat_cache::store::Limits::default(),
        )
        .with_context(|| format!("opening the cache database in {}", db.display()))?;
        let cache_listener = runtime
            .block_on(tokio::net::TcpListener::bind("127.0.0.1:0"))
            .context("binding the cache on loopback")?;
        let cache_url = format!("http://{}", cache_listener.local_addr()?);
        tasks.push(runtime.spawn({
            let stop = stopped(stop_rx.clone());
            async move {
                wavesplat_cache::serve(cache_listener, cache_store, stop)
                    .await
                    .context("the cache server failed")
            }
        }));
        let mut orchestrator_url = None;
        if batch {
            let store = wavesplat_orchestrator::store::Store::open(db.join("orchestrator"))
                .with_context(|| {
                    format!("opening the orchestrator database in {}", db.display())
                })?;
            let listener = runtime
                .block_on(tokio::net::TcpListener::bind("127.0.0.1:0"))
                .context("binding the orchestrator on loopback")?;
            let url = format!("http://{}", listener.local_addr()?);
            let options = wavesplat_orchestrator::ServeOptions {
                delivery_check: Some(wavesplat_orchestrator::DeliveryCheck::new(
                    &cache_url,
                    &Default::default(),
                )?),
                ..Default::default()
            };
            let config = wavesplat_orchestrator::service::ServiceConfig {
                poll_ms: 200,
                ..Default::default()
            };
            tasks.push(runtime.spawn({
                let stop = stopped(stop_rx.clone());
                async move {
                    wavesplat_orchestrator::serve_with(listener, store, config, options, stop)
                        .await
                        .context("the orchestrator server failed")
                }
            }));
            let cfg = wavesplat_worker::WorkerConfig {
                orchestrator: url.clone(),
                cache: cache_url.clone(),
                threads,
                id: "demo-worker".into(),
                max_jobs: None,
                pause_before_upload_ms: 0,
                connect: Default::default(),
            };
            tasks.push(runtime.spawn({
                let stop = stopped(stop_rx.clone());
                async move {
                    wavesplat_worker::run(cfg, stop)
                        .await
                        .context("the worker failed")
                }
            }));
            orchestrator_url = Some(url);
        }
        drop(_context);
        Ok(LocalStack {
            runtime,
            stop,
            tasks,
            cache_url,
            orchestrator_url,
        })
    }

    /// Runs `f` on the stack's runtime.
    pub fn block_on<F: std::future::Future>(&self, f: F) -> F::Output {
        self.runtime.block_on(f)
    }

    /// Stops the services and reports the first failure any of them had.
    pub fn shutdown(mut self) -> Result<()> {
        self.stop_all()
    }

    fn stop_all(&mut self) -> Result<()> {
        let _ = self.stop.send(true);
        let tasks = std::mem::take(&mut self.tasks);
        let mut first = Ok(());
        for t in tasks {
            let r = self
                .runtime
                .block_on(t)
                .context("a service task panicked")
                .and_then(|r| r);
            if first.is_ok() {
                first = r;
            }
        }
        first
    }
}

impl Drop for LocalStack {
    fn drop(&mut self) {
        if let Err(e) = self.stop_all() {
            tracing::warn!(error = %e, "stopping the local services");
        }
    }
}
