//! The services on loopback in this process: `LocalStack` for `demo` and `bench refine` (the
//! cache (sled), optionally the orchestrator (with delivery checks against that cache) and one
//! worker, each on its own port of 127.0.0.1, on one tokio runtime), and `LocalCache`, one cache
//! node on a runtime of its own thread, which the end-to-end tests start, stop and restart at
//! the same address. They are the same servers `wavesplat serve …` and `wavesplat worker` run;
//! only the wiring is local. Dropping either shuts it down gracefully (streams end, stores
//! flush).

use anyhow::{Context, Result};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::Duration;
use tokio::sync::watch;
use wavesplat_cache::store::{Limits, Store};

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
            let config = wavesplat_orchestrator::service::ServiceOptions {
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
            let cfg = wavesplat_worker::WorkerOptions {
                orchestrator: url.clone(),
                cache: cache_url.clone(),
                threads,
                id: "demo-worker".into(),
                max_jobs: None,
                pause_before_upload_ms: 0,
                pause_before_part_report_ms: 0,
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

/// One cache node in this process, on a runtime of its own thread, so that synchronous and
/// asynchronous tests alike can start it, stop it and start it again on the same store and
/// address.
pub struct LocalCache {
    /// `http://127.0.0.1:PORT`.
    pub url: String,
    /// The address it listens on.
    pub addr: SocketAddr,
    /// Its store, shared with the server (for tests that look inside).
    pub store: Store,
    dir: PathBuf,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    thread: Option<std::thread::JoinHandle<Result<()>>>,
}

impl LocalCache {
    /// A node on a fresh port of 127.0.0.1 with its store in `dir`.
    pub fn start(dir: &Path) -> Result<LocalCache> {
        LocalCache::start_with(dir, "127.0.0.1:0", Limits::default())
    }

    /// A node on `addr` (retried until the address is free again, for a restart) with its
    /// store in `dir` under `limits`.
    pub fn start_with(dir: &Path, addr: &str, limits: Limits) -> Result<LocalCache> {
        LocalCache::start_serving(dir, addr, limits, wavesplat_cache::ServeOptions::default())
    }

    /// [`LocalCache::start_with`], served with `options` (TLS, tokens, exposure).
    pub fn start_serving(
        dir: &Path,
        addr: &str,
        limits: Limits,
        options: wavesplat_cache::ServeOptions,
    ) -> Result<LocalCache> {
        let store = Store::open(dir, limits)
            .with_context(|| format!("opening the cache store in {}", dir.display()))?;
        let (stop, stop_rx) = tokio::sync::oneshot::channel::<()>();
        let (ready_tx, ready_rx) = std::sync::mpsc::channel();
        let served = store.clone();
        let bind = addr.to_string();
        let thread = std::thread::Builder::new()
            .name("wavesplat-local-cache".into())
            .spawn(move || -> Result<()> {
                let runtime = tokio::runtime::Builder::new_multi_thread()
                    .worker_threads(2)
                    .enable_all()
                    .build()
                    .context("starting the async runtime")?;
                runtime.block_on(async move {
                    let started = std::time::Instant::now();
                    let listener = loop {
                        match tokio::net::TcpListener::bind(&bind).await {
                            Ok(l) => break l,
                            Err(e) if started.elapsed() > Duration::from_secs(30) => {
                                return Err(anyhow::Error::new(e)
                                    .context(format!("binding the cache on {bind}")));
                            }
                            Err(_) => tokio::time::sleep(Duration::from_millis(20)).await,
                        }
                    };
                    let _ = ready_tx.send(listener.local_addr()?);
                    wavesplat_cache::serve_with(listener, served, options, async {
                        let _ = stop_rx.await;
                    })
                    .await
                    .context("the cache server failed")
                })
            })
            .context("starting the cache's thread")?;
        let addr = match ready_rx.recv() {
            Ok(a) => a,
            Err(_) => {
                return Err(match thread.join() {
                    Ok(Err(e)) => e,
                    _ => anyhow::anyhow!("the cache's thread ended before it listened"),
                })
            }
        };
        Ok(LocalCache {
            url: format!("http://{addr}"),
            addr,
            store,
            dir: dir.to_path_buf(),
            stop: Some(stop),
            thread: Some(thread),
        })
    }

    /// The directory of its store.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Stops the node gracefully and reports a failure it had.
    pub fn stop(mut self) -> Result<()> {
        self.stop_now()
    }

    /// [`LocalCache::stop`] from async code: waits for the node's thread without blocking the
    /// caller's runtime, so clients on that runtime can finish their streams while the node
    /// shuts down gracefully.
    pub async fn stop_async(mut self) -> Result<()> {
        let Some(thread) = self.signal_stop() else {
            return Ok(());
        };
        match tokio::task::spawn_blocking(move || thread.join()).await {
            Ok(joined) => outcome(joined),
            Err(_) => Err(anyhow::anyhow!("the cache's thread could not be joined")),
        }
    }

    /// Tells the server to stop; returns its thread unless that was done before.
    fn signal_stop(&mut self) -> Option<std::thread::JoinHandle<Result<()>>> {
        if let Some(s) = self.stop.take() {
            let _ = s.send(());
        }
        self.thread.take()
    }

    fn stop_now(&mut self) -> Result<()> {
        self.signal_stop().map_or(Ok(()), |t| outcome(t.join()))
    }
}

/// The node's result from its joined thread.
fn outcome(joined: std::thread::Result<Result<()>>) -> Result<()> {
    joined.unwrap_or_else(|_| Err(anyhow::anyhow!("the cache's thread panicked")))
}

impl Drop for LocalCache {
    fn drop(&mut self) {
        if tokio::runtime::Handle::try_current().is_ok() {
            // Dropped on an async runtime (an async test that failed before its stop): joining
            // here could wait on clients only this runtime drives. Stop the node and let its
            // thread end on its own.
            self.signal_stop();
            return;
        }
        if let Err(e) = self.stop_now() {
            tracing::warn!(error = %e, "stopping the local cache");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use wavesplat_client::blocking::CacheClient;
    use wavesplat_compressor::encode::{compress, CompressOptions, Target};
    use wavesplat_compressor::phantom::Phantom;

    fn small_file() -> Vec<u8> {
        compress(
            &Phantom::Spheres.generate([16; 3]),
            &CompressOptions {
                target: Target::Fraction(0.1),
                refine: None,
                ..Default::default()
            },
            &|_, _| {},
        )
        .unwrap()
        .bytes
    }

    #[test]
    fn a_local_cache_keeps_its_volumes_across_a_restart_on_the_same_address() {
        let dir = tempfile::tempdir().unwrap();
        let bytes = small_file();
        let node = LocalCache::start(dir.path()).unwrap();
        let ingested = CacheClient::connect(&node.url)
            .unwrap()
            .ingest("spheres", &bytes)
            .unwrap();
        let addr = node.addr.to_string();
        node.stop().unwrap();
        // Stopped: nothing answers there any more.
        assert!(CacheClient::connect(&format!("http://{addr}"))
            .and_then(|mut c| c.list())
            .is_err());
        let again = LocalCache::start_with(dir.path(), &addr, Limits::default()).unwrap();
        assert_eq!(again.addr.to_string(), addr);
        let listed = CacheClient::connect(&again.url).unwrap().list().unwrap();
        assert_eq!(listed.len(), 1);
        assert_eq!(listed[0].name, "spheres");
        assert_eq!(listed[0].id, ingested.volume.id);
    }

    #[test]
    fn a_local_cache_on_a_store_in_use_fails_with_the_reason() {
        let dir = tempfile::tempdir().unwrap();
        let _first = LocalCache::start(dir.path()).unwrap();
        let second = LocalCache::start(dir.path());
        let e = format!("{:#}", second.err().expect("the store is locked"));
        assert!(e.contains("opening the cache store"), "{e}");
    }
}
