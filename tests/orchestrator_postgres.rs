//! End-to-end tests of the orchestrator over PostgreSQL: a real server (`initdb` into a
//! tempdir, started and crashed by the test), the real `wavesplat` binary as cache, stateless
//! orchestrators (`serve orchestrator --queue postgres://…`, the password from `PGPASSWORD`)
//! and workers given every orchestrator's URL. Nothing is mocked.

mod common;

use common::jobs::{deliveries, finished, list, name, wait_for};
use common::Proc;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Duration;
use wavesplat_compressor::phantom::Phantom;
use wavesplat_fixtures::write_nifti;
use wavesplat_harness::postgres::{PostgresServer, PASSWORD};
use wavesplat_harness::process::ServerProcess;
use wavesplat_orchestrator_client as client;
use wavesplat_orchestrator_client::convert::state_name;
use wavesplat_proto::pb;

const BIN: &str = env!("CARGO_BIN_EXE_wavesplat");

/// Writes `n` good volumes of distinct content, cycling through NIfTI, raw f32 and raw RGB
/// (the naming convention), and one broken file; returns the good names.
fn write_archive(dir: &Path, n: usize) -> Vec<String> {
    std::fs::create_dir_all(dir).unwrap();
    let names = (0..n)
        .map(|i| {
            let dims = [20, 20, 16 + 2 * i];
            let name = format!("v{i}");
            let raw = |suffix: &str| dir.join(format!("{name}_20x20x{}_{suffix}.raw", dims[2]));
            match i % 3 {
                0 => write_nifti(
                    &dir.join(format!("{name}.nii")),
                    dims,
                    &Phantom::SheppLogan.generate(dims).to_interleaved(),
                ),
                1 => {
                    let v = Phantom::Spheres.generate(dims).to_interleaved();
                    let bytes: Vec<u8> = v.iter().flat_map(|x| x.to_le_bytes()).collect();
                    std::fs::write(raw("f32"), bytes).unwrap();
                }
                _ => {
                    let rgb: Vec<u8> = Phantom::RgbHead
                        .generate(dims)
                        .to_interleaved()
                        .iter()
                        .map(|v| (v.clamp(0.0, 1.0) * 255.0) as u8)
                        .collect();
                    std::fs::write(raw("u8_rgb"), rgb).unwrap();
                }
            }
            name
        })
        .collect();
    std::fs::write(dir.join("broken.nii"), b"not a nifti file at all").unwrap();
    names
}

/// `wavesplat serve orchestrator --queue URL` on a free port; its log goes to `log`.
fn orchestrator(url: &str, log: &Path) -> Proc {
    let mut command = Command::new(BIN);
    command
        .args([
            "serve",
            "orchestrator",
            "--addr",
            "127.0.0.1:0",
            "--queue",
            url,
        ])
        .args(["--lease-secs", "10", "--heartbeat-ms", "300"])
        .args(["--retry-base-ms", "200", "--poll-ms", "100"])
        .env("PGPASSWORD", PASSWORD)
        .stderr(std::fs::File::create(log).unwrap());
    let (child, addr) = ServerProcess::start(command)
        .unwrap_or_else(|e| {
            panic!(
                "{e:#}: {}",
                std::fs::read_to_string(log).unwrap_or_default()
            )
        })
        .into_parts();
    Proc { child, addr }
}

struct Setup {
    _dir: tempfile::TempDir,
    root: PathBuf,
    pg: PostgresServer,
    url: String,
    cache: Proc,
}

fn setup() -> Setup {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().to_path_buf();
    let pg = PostgresServer::start().unwrap();
    pg.create_database("queue").unwrap();
    let url = pg.url("queue");
    let cache = Proc::cache(&root.join("cache.db"));
    Setup {
        _dir: dir,
        root,
        pg,
        url,
        cache,
    }
}

fn submit(dir: &Path, orchestrators: &str) {
    let out = Command::new(BIN)
        .args(["archive", "submit", dir.to_str().unwrap()])
        .args(["--orchestrator", orchestrators, "--detach", "--levels", "2"])
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", common::text(&out));
}

/// Each good job done, the broken one failed with its reason, and every good volume delivered
/// exactly once (the workers' logs, one `delivered` line per delivery) and stored once.
async fn check_outcome(good: &[String], js: &[pb::Job], logs: &[PathBuf], cache: &str) {
    assert_eq!(js.len(), good.len() + 1, "{js:?}");
    for j in js {
        if name(j) == "broken" {
            assert_eq!(state_name(j.state), "failed");
            assert!(j.error.contains("broken.nii"), "{}", j.error);
            assert_eq!(j.attempts, 1, "invalid input is not retried");
        } else {
            assert_eq!(state_name(j.state), "done", "{}: {}", name(j), j.error);
        }
    }
    let log: String = logs
        .iter()
        .map(|p| std::fs::read_to_string(p).unwrap_or_default())
        .collect();
    let deliveries = deliveries(&log, good);
    for g in good {
        assert_eq!(
            deliveries.get(g).copied().unwrap_or(0),
            1,
            "{g} delivered other than once: {log}"
        );
    }
    let mut c = wavesplat_client::CacheClient::connect(cache).await.unwrap();
    let mut names: Vec<String> = c
        .list()
        .await
        .unwrap()
        .into_iter()
        .map(|v| v.name)
        .collect();
    names.sort();
    let mut want = good.to_vec();
    want.sort();
    assert_eq!(names, want);
}

fn worker(urls: &str, cache: &str, id: &str, log: &Path) -> Proc {
    let child = Command::new(BIN)
        .args(["worker", "--orchestrator", urls, "--cache", cache])
        .args([
            "--threads",
            "1",
            "--id",
            id,
            "--pause-before-upload-ms",
            "300",
        ])
        .env("NO_COLOR", "1")
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(log).unwrap())
        .spawn()
        .unwrap();
    Proc {
        child,
        addr: String::new(),
    }
}

/// Two orchestrators over one database, three workers that know both: one orchestrator is
/// SIGKILLed mid-archive and the other finishes it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_orchestrators_share_the_queue_and_one_dies_mid_archive() {
    let s = setup();
    let good = write_archive(&s.root.join("arch"), 9);
    let o1 = orchestrator(&s.url, &s.root.join("o1.log"));
    let o2 = orchestrator(&s.url, &s.root.join("o2.log"));
    let both = format!("{},{}", o1.url(), o2.url());
    submit(&s.root.join("arch"), &both);
    // Both orchestrators see the same queue.
    let (a, b) = (
        list(&o1.url()).await.unwrap(),
        list(&o2.url()).await.unwrap(),
    );
    assert_eq!(a.len(), good.len() + 1);
    assert_eq!(a, b);
    let logs: Vec<PathBuf> = (0..3).map(|i| s.root.join(format!("w{i}.log"))).collect();
    let _workers: Vec<Proc> = (0..3)
        .map(|i| worker(&both, &s.cache.url(), &format!("w{i}"), &logs[i]))
        .collect();
    let before = wait_for(&o2.url(), 60, "three jobs done", |js| {
        js.iter().filter(|j| state_name(j.state) == "done").count() >= 3
    })
    .await;
    assert!(!finished(&before), "the archive finished before the kill");
    o1.kill();
    let js = wait_for(&o2.url(), 120, "the archive finished", finished).await;
    check_outcome(&good, &js, &logs, &s.cache.url()).await;
    // The workers were talking to the first orchestrator and moved to the second.
    let failed_over = logs
        .iter()
        .filter(|p| {
            std::fs::read_to_string(p)
                .unwrap_or_default()
                .contains("failing over")
        })
        .count();
    assert!(failed_over >= 1, "no worker failed over");
    // The queue is plain SQL for operators.
    let done =
        s.pg.psql("queue", "SELECT count(*) FROM jobs WHERE state = 'done'")
            .unwrap();
    assert_eq!(done.trim(), good.len().to_string());
}

/// The database crashes mid-archive (an immediate shutdown: no checkpoint) and comes back:
/// the orchestrator answers with clear errors meanwhile, then the archive finishes with every
/// job delivered once.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_database_restarts_mid_archive_and_progress_resumes() {
    let mut s = setup();
    let good = write_archive(&s.root.join("arch"), 6);
    let olog = s.root.join("o.log");
    let o = orchestrator(&s.url, &olog);
    submit(&s.root.join("arch"), &o.url());
    let logs: Vec<PathBuf> = (0..2).map(|i| s.root.join(format!("w{i}.log"))).collect();
    let _workers: Vec<Proc> = (0..2)
        .map(|i| worker(&o.url(), &s.cache.url(), &format!("w{i}"), &logs[i]))
        .collect();
    wait_for(&o.url(), 60, "two jobs done", |js| {
        js.iter().filter(|j| state_name(j.state) == "done").count() >= 2
    })
    .await;
    s.pg.crash().unwrap();
    let mut c = client::connect(&o.url()).await.unwrap();
    let e = client::list(&mut c).await.unwrap_err();
    assert_eq!(e.code(), tonic::Code::Unavailable, "{e:?}");
    assert!(e.message().contains("queue database"), "{}", e.message());
    tokio::time::sleep(Duration::from_secs(2)).await;
    s.pg.resume().unwrap();
    let js = wait_for(&o.url(), 120, "the archive finished", finished).await;
    check_outcome(&good, &js, &logs, &s.cache.url()).await;
    drop(o);
    let olog = std::fs::read_to_string(&olog).unwrap();
    assert!(olog.contains("queue database"), "{olog}");
}

/// Starting without a store names both choices; an unreachable database is reported with its
/// cause (not a pool's timeout), without the password.
#[test]
fn a_missing_or_unreachable_queue_is_a_clear_error() {
    let out = Command::new(BIN)
        .args(["serve", "orchestrator", "--addr", "127.0.0.1:0"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let said = String::from_utf8_lossy(&out.stderr);
    assert!(said.contains("--db") && said.contains("--queue"), "{said}");
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let out = Command::new(BIN)
        .args(["serve", "orchestrator", "--addr", "127.0.0.1:0", "--queue"])
        .arg(format!(
            "postgres://wavesplat:s3cret@127.0.0.1:{port}/queue"
        ))
        .output()
        .unwrap();
    assert!(!out.status.success());
    let said = String::from_utf8_lossy(&out.stderr);
    assert!(said.contains("refused"), "{said}");
    // The cause itself, not the pool's "timed out".
    assert!(!said.contains("timed out"), "{said}");
    assert!(!said.contains("s3cret"), "the password leaked: {said}");
}
