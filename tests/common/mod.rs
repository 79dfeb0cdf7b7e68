//! Helpers shared by the end-to-end tests: the volumes they compress ([`phantom_file`]), the
//! one way to start a cache in the test's process ([`TestCache`], over the harness's
//! `LocalCache`) or the real `wavesplat` binary as a server ([`spawn_server`], through
//! `wavesplat_harness::process`), raw upload messages, a NIfTI writer, and reading images.

#![allow(dead_code)]

pub mod http;
pub mod jobs;
pub mod netns;
pub mod pki;

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use tonic::transport::Channel;
use wavesplat_cache::{Limits, ServeOptions};
use wavesplat_client::CacheClient;
use wavesplat_compressor::encode::{compress, CompressOptions, Target, TileChoice};
use wavesplat_compressor::phantom::Phantom;
use wavesplat_harness::process::ServerProcess;
use wavesplat_harness::LocalCache;
use wavesplat_proto::pb;
use wavesplat_proto::pb::cache_client::CacheClient as WireClient;

/// The options the end-to-end tests compress with: `fraction` of the coefficients in 16³
/// tiles, keeping the oracle's own coefficients (no least-squares refit: the ordering tests
/// compare packet orders, and a refit is tuned for the whole set rather than its prefixes).
/// Tests set layers, levels or tiles on top (`..phantom_options(f)`).
pub fn phantom_options(fraction: f64) -> CompressOptions {
    CompressOptions {
        target: Target::Fraction(fraction),
        tile: TileChoice::Size(16),
        refine: None,
        ..Default::default()
    }
}

/// The `.wsp` bytes of `phantom` at `dims` compressed with `options`.
pub fn phantom_file(phantom: Phantom, dims: [usize; 3], options: &CompressOptions) -> Vec<u8> {
    compress(&phantom.generate(dims), options, &|_, _| {})
        .expect("compress")
        .bytes
}

/// A cache in the test's process (the harness's `LocalCache` on a thread of its own) with its
/// store in a temporary directory that lives as long as it does.
pub struct TestCache {
    /// `http://127.0.0.1:PORT`.
    pub url: String,
    /// The node (its store, its address).
    pub node: LocalCache,
    /// Where the store lives.
    pub dir: tempfile::TempDir,
}

impl TestCache {
    /// A node with the default limits, plaintext on loopback.
    pub fn start() -> TestCache {
        TestCache::start_with(Limits::default(), ServeOptions::default())
    }

    /// A node under `limits`, served with `options` (TLS, tokens).
    pub fn start_with(limits: Limits, options: ServeOptions) -> TestCache {
        let dir = tempfile::tempdir().unwrap();
        let node = LocalCache::start_serving(dir.path(), "127.0.0.1:0", limits, options).unwrap();
        TestCache {
            url: node.url.clone(),
            node,
            dir,
        }
    }

    /// A node with the default limits served with `security` (TLS, tokens).
    pub fn secured(security: wavesplat_net::Security) -> TestCache {
        let options = ServeOptions {
            security,
            ..Default::default()
        };
        TestCache::start_with(Limits::default(), options)
    }

    /// The domain client.
    pub async fn client(&self) -> CacheClient {
        CacheClient::connect(&self.url).await.unwrap()
    }

    /// The generated client, for requests the domain client would never send.
    pub async fn wire(&self) -> WireClient<Channel> {
        WireClient::connect(self.url.clone()).await.unwrap()
    }

    /// Stops the node gracefully (clients on the caller's runtime may finish their streams).
    pub async fn stop(self) {
        self.node.stop_async().await.unwrap();
    }
}

/// The messages of an upload as the domain client sends them (`start`, then chunks of
/// `chunk` bytes), for tests that corrupt, cut or replay them.
pub fn ingest_messages(name: &str, bytes: &[u8], chunk: usize) -> Vec<pb::IngestRequest> {
    use pb::ingest_request::Msg;
    let mut out = vec![pb::IngestRequest {
        msg: Some(Msg::Start(pb::IngestStart {
            name: name.to_string(),
            total_size: bytes.len() as u64,
            sha256: wavesplat_cache::store::sha256(bytes).to_vec(),
        })),
    }];
    out.extend(bytes.chunks(chunk).map(|c| pb::IngestRequest {
        msg: Some(Msg::Chunk(c.to_vec())),
    }));
    out
}

/// Starts `wavesplat ARGS` (a server bound to port 0) and returns the child and the address it
/// announced on its first stdout line (`listening on ADDR`), through the harness's
/// `ServerProcess`.
pub fn spawn_server(args: &[&str]) -> (Child, String) {
    ServerProcess::spawn(Path::new(env!("CARGO_BIN_EXE_wavesplat")), args)
        .unwrap()
        .into_parts()
}

/// `wavesplat serve cache` on a fresh loopback port with its store in `db` (a real process, for
/// tests that kill and restart it).
pub fn cache_process(db: &Path) -> ServerProcess {
    let db = db.to_str().expect("utf-8 temp path");
    ServerProcess::spawn(
        Path::new(env!("CARGO_BIN_EXE_wavesplat")),
        &["serve", "cache", "--addr", "127.0.0.1:0", "--db", db],
    )
    .unwrap()
}

/// [`spawn_server`] with the server's stderr kept: [`stop_and_read_stderr`] reads it.
pub fn spawn_server_with_stderr(args: &[&str]) -> (Child, String) {
    ServerProcess::spawn_with_stderr(Path::new(env!("CARGO_BIN_EXE_wavesplat")), args)
        .unwrap()
        .into_parts()
}

#[allow(unused_imports)]
pub use wavesplat_harness::process::stop_and_read_stderr;

/// A finished command's status and output, for assertion messages.
/// `wavesplat render ARGS` run in `dir`, without a CA from the environment.
pub fn render_in(dir: &Path, args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_wavesplat"))
        .arg("render")
        .args(args)
        .current_dir(dir)
        .env_remove("WAVESPLAT_CA")
        .output()
        .unwrap()
}

/// A single-threaded runtime for a test's client calls.
pub fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap()
}

pub fn text(o: &std::process::Output) -> String {
    format!(
        "status {:?}\nstdout:\n{}\nstderr:\n{}",
        o.status.code(),
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

/// A raw little-endian f32 image as `render --raw` writes it.
pub fn read_f32(path: &std::path::Path) -> Vec<f32> {
    std::fs::read(path)
        .unwrap()
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect()
}

/// The largest difference of two images relative to the first's peak (which must be > 0).
pub fn relative_difference(a: &[f32], b: &[f32]) -> f32 {
    assert!(a.iter().any(|x| *x != 0.0), "a black first image");
    wavesplat_viewer::image::max_relative_difference(b, a) as f32
}

/// Waits until a render recording into `dir/record` has received some bytes (its frames.csv's
/// byte column), and returns how many.
pub fn wait_for_bytes(dir: &std::path::Path) -> u64 {
    let csv = dir.join("record").join("frames.csv");
    let waited = std::time::Instant::now();
    loop {
        let bytes = std::fs::read_to_string(&csv)
            .unwrap_or_default()
            .lines()
            .skip(1)
            .filter_map(|l| l.split(',').nth(4)?.parse::<u64>().ok())
            .max()
            .unwrap_or(0);
        if bytes > 0 {
            return bytes;
        }
        assert!(
            waited.elapsed() < std::time::Duration::from_secs(60),
            "no bytes reached the viewer"
        );
        std::thread::sleep(std::time::Duration::from_millis(5));
    }
}

/// A `wavesplat` child process, SIGKILLed when dropped: a server with the address it announced,
/// or a worker (no address).
pub struct Proc {
    /// The process.
    pub child: Child,
    /// `HOST:PORT` a server listens on; empty for a worker.
    pub addr: String,
}

impl Proc {
    /// Starts a server and reads its bound address from the `listening on` line.
    pub fn server(args: &[&str]) -> Proc {
        let (child, addr) = spawn_server(args);
        Proc { child, addr }
    }

    /// `http://ADDR`.
    pub fn url(&self) -> String {
        format!("http://{}", self.addr)
    }

    /// `wavesplat serve cache` on a free loopback port with its store in `db`.
    pub fn cache(db: &Path) -> Proc {
        Proc::server(&[
            "serve",
            "cache",
            "--addr",
            "127.0.0.1:0",
            "--db",
            db.to_str().unwrap(),
        ])
    }

    /// `wavesplat serve orchestrator` on `addr` with its database in `db` and `args` after.
    pub fn orchestrator(db: &Path, addr: &str, args: &[&str]) -> Proc {
        let db = db.to_str().unwrap();
        let mut all = vec!["serve", "orchestrator", "--addr", addr, "--db", db];
        all.extend_from_slice(args);
        Proc::server(&all)
    }

    /// A worker with one compression thread that waits `pause_ms` before each upload; its
    /// log (stderr, a file as a service manager would keep it) goes to `log` when given.
    pub fn worker(orch: &str, cache: &str, id: &str, pause_ms: u64, log: Option<&Path>) -> Proc {
        let pause = pause_ms.to_string();
        Proc::worker_with(orch, cache, id, &["--pause-before-upload-ms", &pause], log)
    }

    /// A worker with one compression thread and `extra` arguments (testing aids); its log
    /// goes to `log` when given.
    pub fn worker_with(
        orch: &str,
        cache: &str,
        id: &str,
        extra: &[&str],
        log: Option<&Path>,
    ) -> Proc {
        let stderr = match log {
            Some(p) => Stdio::from(std::fs::File::create(p).unwrap()),
            None => Stdio::null(),
        };
        let child = Command::new(env!("CARGO_BIN_EXE_wavesplat"))
            .args(["worker", "--orchestrator", orch, "--cache", cache])
            .args(["--threads", "1", "--id", id])
            .args(extra)
            .stdout(Stdio::null())
            .stderr(stderr)
            .spawn()
            .unwrap();
        Proc {
            child,
            addr: String::new(),
        }
    }

    /// SIGKILL: no shutdown path runs.
    pub fn kill(mut self) {
        self.child.kill().unwrap();
        self.child.wait().unwrap();
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A cache and an orchestrator as real `wavesplat` processes on loopback ports, their stores
/// in a temporary directory (`root`, where tests also write their archives); workers are
/// added with [`TestCluster::worker`].
pub struct TestCluster {
    _dir: tempfile::TempDir,
    /// The temporary directory.
    pub root: PathBuf,
    /// The cache (`root/cache.db`).
    pub cache: Proc,
    /// The orchestrator (`root/orch.db`).
    pub orch: Proc,
    orch_args: Vec<String>,
}

impl TestCluster {
    /// Starts both servers; `orch_args` (lease, heartbeat, retry and poll timings) go to the
    /// orchestrator, now and on a restart.
    pub fn start(orch_args: &[&str]) -> TestCluster {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().to_path_buf();
        let cache = Proc::cache(&root.join("cache.db"));
        let orch = Proc::orchestrator(&root.join("orch.db"), "127.0.0.1:0", orch_args);
        TestCluster {
            _dir: dir,
            root,
            cache,
            orch,
            orch_args: orch_args.iter().map(|a| a.to_string()).collect(),
        }
    }

    /// A worker of this cluster (see [`Proc::worker`]).
    pub fn worker(&self, id: &str, pause_ms: u64, log: Option<&Path>) -> Proc {
        Proc::worker(&self.orch.url(), &self.cache.url(), id, pause_ms, log)
    }

    /// SIGKILLs the orchestrator and starts it again on the same address (workers know only
    /// that) over the same database.
    pub fn restart_orchestrator(&mut self) {
        self.orch.child.kill().unwrap();
        self.orch.child.wait().unwrap();
        let args: Vec<&str> = self.orch_args.iter().map(String::as_str).collect();
        // Replacing drops the killed process's `Proc`, whose second kill finds it gone.
        self.orch = Proc::orchestrator(&self.root.join("orch.db"), &self.orch.addr, &args);
    }

    /// SIGKILLs the cache (it stays down until [`TestCluster::start_cache_again`]).
    pub fn kill_cache(&mut self) {
        let _ = self.cache.child.kill();
        let _ = self.cache.child.wait();
    }

    /// Starts the cache again on its address over its store.
    pub fn start_cache_again(&mut self) {
        let db = self.root.join("cache.db");
        self.cache = Proc::server(&[
            "serve",
            "cache",
            "--addr",
            &self.cache.addr,
            "--db",
            db.to_str().unwrap(),
        ]);
    }
}
