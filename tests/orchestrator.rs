//! End-to-end tests of the orchestrator: the real `wavesplat` binary as cache, orchestrator and
//! workers on loopback, sled in tempdirs, archives of small phantom volumes written as raw
//! (naming convention) and NIfTI files. Short leases (2 s) keep the suite fast; every wait is
//! bounded.

mod common;

use common::jobs::{finished as all_finished, list, name, wait_for};
use common::{Proc, TestCluster};
use std::collections::HashSet;
use std::path::Path;
use std::process::{Command, Output};

use wavesplat_client::{CacheClient, RefineRequest, VolumeKey};
use wavesplat_codec::format::packet::decode_packet;
use wavesplat_codec::view::ViewSpec;
use wavesplat_compressor::phantom::Phantom;
use wavesplat_fixtures::write_nifti;
use wavesplat_orchestrator_client::convert::state_name;
use wavesplat_proto::pb;
use wavesplat_viewer::View;

const BIN: &str = env!("CARGO_BIN_EXE_wavesplat");
const DIMS: [usize; 3] = [24, 24, 24];

/// The orchestrator's timings here: leases of 2 s, so a killed worker's job runs again soon.
const ORCH_TIMING: [&str; 8] = [
    "--lease-secs",
    "2",
    "--heartbeat-ms",
    "300",
    "--retry-base-ms",
    "200",
    "--poll-ms",
    "100",
];

fn cli(args: &[&str]) -> Output {
    Command::new(BIN).args(args).output().unwrap()
}

/// Runs the CLI and requires success; returns its stdout.
fn cli_ok(args: &[&str]) -> String {
    let out = cli(args);
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        out.status.success(),
        "{args:?} failed: {stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    stdout
}

fn submit(dir: &Path, orch: &str, extra: &[&str]) -> String {
    let mut args = vec![
        "archive",
        "submit",
        dir.to_str().unwrap(),
        "--orchestrator",
        orch,
        "--detach",
        "--levels",
        "2",
    ];
    args.extend_from_slice(extra);
    cli_ok(&args)
}

fn write_f32(path: &Path, samples: &[f32]) {
    let bytes: Vec<u8> = samples.iter().flat_map(|v| v.to_le_bytes()).collect();
    std::fs::write(path, bytes).unwrap();
}

fn phantom(p: Phantom, dims: [usize; 3]) -> Vec<f32> {
    p.generate(dims).to_interleaved()
}

fn raw_name(name: &str, dims: [usize; 3], suffix: &str) -> String {
    format!("{name}_{}x{}x{}_{suffix}.raw", dims[0], dims[1], dims[2])
}

/// Writes `n` good volumes named `{prefix}{i}` cycling through raw scalar, raw RGB and NIfTI
/// (depths differ, so contents differ: identical content would be one job).
fn write_good(dir: &Path, prefix: &str, n: usize) -> Vec<String> {
    std::fs::create_dir_all(dir).unwrap();
    (0..n)
        .map(|i| {
            let name = format!("{prefix}{i}");
            let dims = [DIMS[0], DIMS[1], DIMS[2] + 2 * i];
            match i % 3 {
                0 => write_f32(
                    &dir.join(raw_name(&name, dims, "f32")),
                    &phantom(Phantom::SheppLogan, dims),
                ),
                1 => {
                    let rgb: Vec<u8> = phantom(Phantom::RgbHead, dims)
                        .iter()
                        .map(|v| (v.clamp(0.0, 1.0) * 255.0) as u8)
                        .collect();
                    std::fs::write(dir.join(raw_name(&name, dims, "u8_rgb")), rgb).unwrap();
                }
                _ => write_nifti(
                    &dir.join(format!("{name}.nii")),
                    dims,
                    &phantom(Phantom::Spheres, dims),
                ),
            }
            name
        })
        .collect()
}

/// Whether a listed job is a part of a bricked job.
fn is_part(j: &pb::Job) -> bool {
    j.spec.as_ref().is_some_and(|s| s.part.is_some())
}

/// Whether a listed job is an encode part of a bricked job (the other parts score).
fn is_encode_part(j: &pb::Job) -> bool {
    j.spec
        .as_ref()
        .and_then(|s| s.part.as_ref())
        .is_some_and(|p| matches!(p.step, Some(pb::part_spec::Step::Encode(_))))
}

/// The fast bricked byte target the kept-top tests submit: 24³ bricks, `--effort fast`,
/// `target` bytes (depth 2, as [`submit`] asks); and its job options, for the one-process file.
fn submit_fast_bricked(
    dir: &Path,
    orch: &str,
    target: u64,
) -> wavesplat_orchestrator_client::model::JobOptions {
    use wavesplat_orchestrator_client::model::{Effort, JobOptions, TargetSpec};
    let bytes = target.to_string();
    let args = [
        "--brick",
        "24",
        "--effort",
        "fast",
        "--target-bytes",
        &bytes,
    ];
    submit(dir, orch, &args);
    JobOptions {
        levels: Some(2),
        brick: Some(24),
        effort: Effort::Fast,
        target: TargetSpec::Bytes(target),
        ..Default::default()
    }
}

/// The bricked file one process makes from `source` with a job's options (depth 2, as
/// [`submit`] asks), bricks of `brick` and `target`.
fn one_process_file(
    source: &dyn wavesplat_compressor::bricked::BrickSource,
    brick: usize,
    target: wavesplat_orchestrator_client::model::TargetSpec,
) -> Vec<u8> {
    let options = wavesplat_orchestrator_client::model::JobOptions {
        levels: Some(2),
        brick: Some(brick),
        target,
        ..Default::default()
    };
    one_process_file_with(source, &options)
}

/// The bricked file one process makes from `source` with a job's `options` (their brick).
fn one_process_file_with(
    source: &dyn wavesplat_compressor::bricked::BrickSource,
    options: &wavesplat_orchestrator_client::model::JobOptions,
) -> Vec<u8> {
    let opts = wavesplat_worker::options::compress_options(options);
    let brick = options.brick.expect("a bricked job's options");
    wavesplat_compressor::bricked::compress_bricked(source, &opts, brick, &|_| {})
        .unwrap()
        .bytes
}

/// The series file one process makes of the 4D NIfTI at `path` with a job's options (depth 2,
/// as [`submit`] asks), temporal groups of `group` and `fraction` of the coefficients.
fn one_process_series(path: &Path, group: usize, fraction: f64) -> Vec<u8> {
    let options = wavesplat_orchestrator_client::model::JobOptions {
        levels: Some(2),
        time_group: Some(group),
        target: wavesplat_orchestrator_client::model::TargetSpec::Fraction(fraction),
        ..Default::default()
    };
    let opts = wavesplat_worker::options::compress_options(&options);
    let reader =
        wavesplat_compressor::reader::region::RegionReader::open_series(path, None).unwrap();
    wavesplat_compressor::series::compress_series(&reader, &opts, group, 256, &|_| {})
        .unwrap()
        .bytes
}

/// Every worker whose log is in `logs` ran at least one part.
fn each_ran_a_part(logs: &[std::path::PathBuf]) {
    for log in logs {
        let text = std::fs::read_to_string(log).unwrap();
        assert!(
            text.contains("running part"),
            "{} ran no part:\n{text}",
            log.display()
        );
    }
}

/// The cache holds one volume, and its content is `file` (by SHA-256).
async fn assert_cache_holds_only(cache: &str, file: &[u8]) {
    assert_cache_holds_only_these(cache, &[file]).await;
}

/// The cache holds exactly `files` (by sha256, in any order): a volume committed once each.
async fn assert_cache_holds_only_these(cache: &str, files: &[&[u8]]) {
    let sha = |f: &[u8]| wavesplat_net::digest::hex(&wavesplat_net::digest::sha256(f));
    let mut expected: Vec<String> = files.iter().map(|f| sha(f)).collect();
    expected.sort();
    let mut client = CacheClient::connect(cache).await.unwrap();
    let mut cached: Vec<String> = client
        .list()
        .await
        .unwrap()
        .into_iter()
        .map(|v| v.sha256)
        .collect();
    cached.sort();
    assert_eq!(cached, expected, "not the one-process files");
}

async fn jobs(url: &str) -> Vec<pb::Job> {
    list(url).await.expect("the orchestrator answers")
}

/// Every volume in the cache, each streamed in full and decoded; names must be unique.
async fn cache_volumes_decode(cache: &str) -> Vec<String> {
    let mut c = CacheClient::connect(cache).await.unwrap();
    let mut names = Vec::new();
    for v in c.list().await.unwrap() {
        let request = RefineRequest::new(
            VolumeKey::Name(v.name.clone()),
            ViewSpec::single(View::new(0.4, 0.7, 32, 32)),
        );
        let got = c.refine_collect(request, None).await.unwrap();
        assert!(got.done);
        assert_eq!(got.packets.len(), v.packet_count as usize, "{}", v.name);
        let h = got.header.unwrap().header;
        for p in &got.packets {
            decode_packet(&h, &p.data).unwrap();
        }
        names.push(v.name);
    }
    let unique: HashSet<&String> = names.iter().collect();
    assert_eq!(unique.len(), names.len(), "a volume was stored twice");
    names.sort();
    names
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn archive_is_compressed_into_the_cache_and_bad_files_fail_alone() {
    let cl = TestCluster::start(&ORCH_TIMING);
    let (o, c) = (cl.orch.url(), cl.cache.url());
    // Three archives with different families / colour spaces; one is uploaded, not shared.
    let a = cl.root.join("a");
    let b = cl.root.join("b");
    let u = cl.root.join("u");
    let mut good = write_good(&a, "a", 3);
    good.extend(write_good(&b, "b", 3));
    good.extend(write_good(&u, "u", 2));
    // Bad input: wrong size for the dims in the name, NaN, a garbage NIfTI.
    std::fs::write(a.join("short_24x24x24_u8.raw"), [0u8; 100]).unwrap();
    let mut nan = phantom(Phantom::SheppLogan, [8, 8, 8]);
    nan[77] = f32::NAN;
    write_f32(&b.join("nan_8x8x8_f32.raw"), &nan);
    std::fs::write(b.join("garbage.nii"), b"not a nifti file at all").unwrap();

    let logs = [cl.root.join("w1.log"), cl.root.join("w2.log")];
    let _w1 = cl.worker("w1", 0, Some(&logs[0]));
    let _w2 = cl.worker("w2", 0, Some(&logs[1]));
    submit(&a, &o, &["--family", "haar", "--colorspace", "rgb"]);
    submit(
        &b,
        &o,
        &[
            "--family",
            "cubic",
            "--colorspace",
            "yiq",
            "--coder",
            "range",
        ],
    );
    submit(&u, &o, &["--upload", "--colorspace", "pca"]);

    let js = wait_for(&o, 45, "all jobs finished", all_finished).await;
    assert_eq!(js.len(), good.len() + 3);
    for j in &js {
        let n = name(j);
        if good.iter().any(|g| g == n) {
            assert_eq!(state_name(j.state), "done", "{n}: {}", j.error);
        } else {
            assert_eq!(state_name(j.state), "failed", "{n}");
            assert_eq!(j.failure, pb::FailureKind::InvalidInput as i32, "{n}");
            assert_eq!(j.attempts, 1, "invalid input is not retried");
            let want = match n {
                "short" => "need exactly",
                "nan" => "non-finite",
                _ => "garbage.nii",
            };
            assert!(j.error.contains(want), "{n}: {}", j.error);
        }
    }
    let mut want = good.clone();
    want.sort();
    assert_eq!(cache_volumes_decode(&c).await, want);
    // The workers' logs (files, not terminals) record each job's outcome, in plain text.
    let log: String = logs
        .iter()
        .map(|p| std::fs::read_to_string(p).unwrap())
        .collect();
    assert!(
        !log.contains('\u{1b}'),
        "colour codes in a log file: {log:?}"
    );
    assert_eq!(
        log.matches("delivered").count(),
        good.len(),
        "one delivery line per good job: {log}"
    );
    assert!(log.matches("attempt failed").count() >= 3, "{log}");

    // Resubmitting skips everything already known.
    let out = submit(&a, &o, &["--family", "haar", "--colorspace", "rgb"]);
    assert!(out.contains("0 submitted, 4 already known"), "{out}");
    // Retrying a failed job runs it again (and it fails again, for the same reason).
    let short = js.iter().find(|j| name(j) == "short").unwrap().id;
    cli_ok(&["jobs", "retry", &short.to_string(), "--orchestrator", &o]);
    let js = wait_for(&o, 20, "retried job failed again", |js| {
        js.iter()
            .any(|j| j.id == short && state_name(j.state) == "failed" && j.attempts == 1)
    })
    .await;
    assert_eq!(js.len(), good.len() + 3);
    // `jobs list` shows every job.
    let out = cli(&["jobs", "list", "--orchestrator", &o]);
    assert_eq!(
        String::from_utf8_lossy(&out.stdout).lines().count(),
        js.len()
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_killed_workers_lease_is_reclaimed_and_the_job_lands_once() {
    let cl = TestCluster::start(&ORCH_TIMING);
    let (o, c) = (cl.orch.url(), cl.cache.url());
    let dir = cl.root.join("arch");
    let good = write_good(&dir, "v", 3);
    // This worker compresses, then hangs before uploading: SIGKILL it there.
    let stuck = cl.worker("doomed", 60_000, None);
    submit(&dir, &o, &[]);
    let js = wait_for(&o, 20, "a job held by the doomed worker", |js| {
        js.iter()
            .any(|j| j.worker == "doomed" && j.stage.contains("paused"))
    })
    .await;
    let victim = js.iter().find(|j| j.worker == "doomed").unwrap().id;
    stuck.kill();
    let _w = cl.worker("rescuer", 0, None);
    let js = wait_for(&o, 30, "all done", |js| {
        js.len() == 3 && js.iter().all(|j| state_name(j.state) == "done")
    })
    .await;
    let v = js.iter().find(|j| j.id == victim).unwrap();
    assert_eq!(v.attempts, 2, "reclaimed once");
    assert!(v.error.contains("stopped heartbeating"), "{}", v.error);
    let mut want = good;
    want.sort();
    assert_eq!(cache_volumes_decode(&c).await, want);
}

/// A job cancelled while its worker compresses it stops there: the worker's compression ends
/// at its next stage, not after running on for a result nobody takes, and the worker is free
/// for the next job.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_cancelled_while_it_compresses_stops_its_worker() {
    let cl = TestCluster::start(&ORCH_TIMING);
    let (o, c) = (cl.orch.url(), cl.cache.url());
    let big = cl.root.join("big");
    std::fs::create_dir_all(&big).unwrap();
    // Some seconds of work on one thread: two depths compared, six refinement rounds.
    let dims = [160, 144, 128];
    write_f32(
        &big.join(raw_name("big", dims, "f32")),
        &phantom(Phantom::SheppLogan, dims),
    );
    let args = ["--orchestrator", &o, "--detach", "--effort", "best"];
    let mut submit_big = vec!["archive", "submit", big.to_str().unwrap()];
    submit_big.extend_from_slice(&args);
    submit_big.extend_from_slice(&["--target-bytes", "60000"]);
    cli_ok(&submit_big);
    let log = cl.root.join("worker.log");
    let _w = cl.worker("w", 0, Some(&log));
    let js = wait_for(&o, 60, "the job in its compression", |js| {
        js.iter().any(|j| {
            state_name(j.state) == "running"
                && ["transform", "depth", "scoring", "refinement", "entropy"]
                    .iter()
                    .any(|s| j.stage.contains(s))
        })
    })
    .await;
    let id = js[0].id.to_string();
    let out = cli_ok(&["jobs", "cancel", &id, "--orchestrator", &o]);
    assert!(out.contains("cancelled"), "{out}");
    // The worker says its compression stopped (before, it compressed to the end and then
    // threw the result away).
    let stopped = "compression stopped before it finished";
    let end = std::time::Instant::now() + std::time::Duration::from_secs(120);
    let text = loop {
        let text = std::fs::read_to_string(&log).unwrap_or_default();
        let ended = ["ended before it finished", "result discarded"];
        if ended.iter().any(|e| text.contains(e)) || std::time::Instant::now() > end {
            break text;
        }
        tokio::time::sleep(std::time::Duration::from_millis(100)).await;
    };
    assert!(text.contains(stopped), "the worker's log: {text}");
    assert!(!text.contains("result discarded"), "{text}");
    // The same worker takes the next job.
    let small = cl.root.join("small");
    let good = write_good(&small, "s", 1);
    submit(&small, &o, &[]);
    let js = wait_for(&o, 60, "the next job done", |js| {
        js.iter()
            .any(|j| name(j) == good[0] && state_name(j.state) == "done")
    })
    .await;
    let big = js.iter().find(|j| j.id.to_string() == id).unwrap();
    assert_eq!(state_name(big.state), "cancelled");
    assert_eq!(cache_volumes_decode(&c).await, good);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn orchestrator_restart_keeps_the_queue_and_cancel_retry_work() {
    let mut cl = TestCluster::start(&ORCH_TIMING);
    let c = cl.cache.url();
    let dir = cl.root.join("arch");
    let good = write_good(&dir, "r", 6);
    let o = cl.orch.url();
    submit(&dir, &o, &[]);
    // Cancel one queued job before any worker runs.
    let js = jobs(&o).await;
    assert_eq!(js.len(), 6);
    let cancelled = js[1].id;
    let out = cli_ok(&[
        "jobs",
        "cancel",
        &cancelled.to_string(),
        "--orchestrator",
        &o,
    ]);
    assert!(out.contains("cancelled"), "{out}");

    // A slow worker, so the run is still going when the orchestrator dies.
    let _w = cl.worker("w", 400, None);
    let before = wait_for(&o, 20, "two jobs done", |js| {
        js.iter().filter(|j| state_name(j.state) == "done").count() >= 2
    })
    .await;
    assert!(
        !all_finished(&before),
        "the run ended before the orchestrator was killed"
    );
    cl.restart_orchestrator();
    let after = jobs(&o).await;
    assert_eq!(after.len(), 6);
    for (b, a) in before.iter().zip(&after) {
        assert_eq!(b.id, a.id);
        if matches!(state_name(b.state), "done" | "cancelled") {
            assert_eq!(a.state, b.state, "job {} changed across the restart", a.id);
        }
    }
    let js = wait_for(&o, 40, "the run completes", all_finished).await;
    for j in &js {
        let want = if j.id == cancelled {
            "cancelled"
        } else {
            "done"
        };
        assert_eq!(state_name(j.state), want, "{}: {}", name(j), j.error);
    }
    // Cancelling a finished job is refused; retrying the cancelled one completes it.
    let done = js.iter().find(|j| j.id != cancelled).unwrap().id;
    let out = cli(&["jobs", "cancel", &done.to_string(), "--orchestrator", &o]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("is done"));
    cli_ok(&[
        "jobs",
        "retry",
        &cancelled.to_string(),
        "--orchestrator",
        &o,
    ]);
    wait_for(&o, 20, "the retried job is done", |js| {
        js.iter().all(|j| state_name(j.state) == "done")
    })
    .await;
    let mut want = good;
    want.sort();
    assert_eq!(cache_volumes_decode(&c).await, want);
}

/// The README's second submit (the same archive, other options): without a new name each job
/// fails saying how to keep both; with `--name-suffix` every volume lands beside the first, and
/// a retried job shows no stale error while it waits.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_same_archive_with_other_options_lands_under_a_suffix() {
    let cl = TestCluster::start(&ORCH_TIMING);
    let (o, c) = (cl.orch.url(), cl.cache.url());
    let a = cl.root.join("a");
    let good = write_good(&a, "s", 2);
    submit(&a, &o, &[]);
    let _w = cl.worker("w", 0, None);
    wait_for(&o, 45, "the first submission done", all_finished).await;
    submit(&a, &o, &["--family", "cubic"]);
    let js = wait_for(&o, 45, "the clashing submission finished", |js| {
        js.len() == 2 * good.len() && all_finished(js)
    })
    .await;
    let failed: Vec<&pb::Job> = js
        .iter()
        .filter(|j| state_name(j.state) == "failed")
        .collect();
    assert_eq!(failed.len(), good.len(), "{js:?}");
    for j in &failed {
        assert!(j.error.contains("--name-suffix"), "{}", j.error);
    }
    let out = cli_ok(&[
        "jobs",
        "retry",
        &failed[0].id.to_string(),
        "--orchestrator",
        &o,
    ]);
    assert!(
        !out.contains("already has"),
        "a retried job keeps its old error: {out}"
    );
    submit(&a, &o, &["--family", "cubic", "--name-suffix", "_cubic"]);
    wait_for(&o, 60, "the suffixed submission done", |js| {
        js.len() == 3 * good.len()
            && js.iter().filter(|j| state_name(j.state) == "done").count() == 2 * good.len()
            && all_finished(js)
    })
    .await;
    let mut want: Vec<String> = good
        .iter()
        .flat_map(|g| [g.clone(), format!("{g}_cubic")])
        .collect();
    want.sort();
    assert_eq!(cache_volumes_decode(&c).await, want);
}

/// `archive submit --brick N`: a worker compresses the volume as a bricked volume, reading a
/// raw file on shared storage brick by brick (an uploaded one from the worker's temporary copy
/// of it), and
/// the cache holds one bricked volume per job, exactly as `compress_bricked` makes it with the
/// job's options, even when the first worker is killed before its upload. A bricked job asks for
/// linear or haar: the cubic family is refused at submission.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_bricked_job_lands_as_one_bricked_volume_once() {
    use wavesplat_compressor::bricked::compress_bricked;
    use wavesplat_orchestrator_client::model::JobOptions;
    let cl = TestCluster::start(&ORCH_TIMING);
    let (o, c) = (cl.orch.url(), cl.cache.url());
    let dims = [48, 40, 36];
    let samples = phantom(Phantom::SheppLogan, dims);
    let shared = cl.root.join("shared");
    let uploaded = cl.root.join("uploaded");
    for (dir, name) in [(&shared, "big"), (&uploaded, "sent")] {
        std::fs::create_dir_all(dir).unwrap();
        write_f32(&dir.join(raw_name(name, dims, "f32")), &samples);
    }
    let refused = cli(&[
        "archive",
        "submit",
        shared.to_str().unwrap(),
        "--orchestrator",
        &o,
        "--detach",
        "--brick",
        "24",
        "--family",
        "cubic",
    ]);
    assert!(!refused.status.success());
    assert!(
        String::from_utf8_lossy(&refused.stderr).contains("cubic"),
        "{}",
        String::from_utf8_lossy(&refused.stderr)
    );
    // This worker coordinates the job, runs all its parts (it is alone), then hangs before
    // uploading: SIGKILL it there.
    let stuck = cl.worker("doomed", 60_000, None);
    submit(&shared, &o, &["--brick", "24"]);
    wait_for(&o, 60, "the doomed worker holding the bricked job", |js| {
        js.iter()
            .any(|j| j.worker == "doomed" && j.stage.contains("paused"))
    })
    .await;
    stuck.kill();
    let _w = cl.worker("rescuer", 0, None);
    submit(&uploaded, &o, &["--brick", "24", "--upload"]);
    let js = wait_for(&o, 90, "both bricked jobs done", |js| {
        let whole: Vec<_> = js.iter().filter(|j| !is_part(j)).collect();
        whole.len() == 2 && whole.iter().all(|j| state_name(j.state) == "done")
    })
    .await;
    let big = js.iter().find(|j| name(j) == "big" && !is_part(j)).unwrap();
    assert_eq!(big.attempts, 2, "reclaimed once");
    // The file on shared storage was spread over parts (8 bricks scored, 8 coded), each run
    // once: the rescuer found them done and only gathered them; the upload was not.
    let parts: Vec<_> = js.iter().filter(|j| is_part(j)).collect();
    assert_eq!(parts.len(), 16, "{parts:?}");
    for p in &parts {
        assert_eq!(
            p.spec.as_ref().unwrap().part.as_ref().unwrap().parent,
            big.id
        );
        assert_eq!((state_name(p.state), p.attempts), ("done", 1), "{p:?}");
    }

    let options = JobOptions {
        levels: Some(2),
        brick: Some(24),
        ..JobOptions::default()
    };
    let volume = Phantom::SheppLogan.generate(dims);
    let expected = compress_bricked(
        &volume,
        &wavesplat_worker::options::compress_options(&options),
        24,
        &|_| {},
    )
    .unwrap();
    assert_eq!(expected.manifest.bricks.len(), 8);
    let expected_sha = wavesplat_net::digest::hex(&wavesplat_net::digest::sha256(&expected.bytes));
    let mut client = CacheClient::connect(&c).await.unwrap();
    let listed = client.list().await.unwrap();
    assert_eq!(listed.len(), 2, "one volume per job: {listed:?}");
    for v in &listed {
        assert_eq!(v.sha256, expected_sha, "{}: not the bricked file", v.name);
        let h = client
            .header(&VolumeKey::Name(v.name.clone()))
            .await
            .unwrap();
        assert_eq!(h.bricks.len(), 8, "{}", v.name);
        assert_eq!(h.header.geometry.dims, dims);
    }
}

/// Two workers share one bricked job: each runs some of its bricks, a byte target's search
/// runs its trials as rounds of parts, and the volume lands once, byte for byte the file one
/// process makes.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_bricked_job_spreads_its_bricks_over_workers() {
    use wavesplat_orchestrator_client::model::TargetSpec;
    let cl = TestCluster::start(&ORCH_TIMING);
    let (o, c) = (cl.orch.url(), cl.cache.url());
    let dims = [48, 40, 36];
    let shared = cl.root.join("shared");
    std::fs::create_dir_all(&shared).unwrap();
    write_f32(
        &shared.join(raw_name("spread", dims, "f32")),
        &phantom(Phantom::SheppLogan, dims),
    );
    let logs = [cl.root.join("w1.log"), cl.root.join("w2.log")];
    // Each part held 300 ms before it is reported, so that a worker slow to start polling
    // (a loaded machine: one CI run saw w2 run every part) still finds parts queued while the
    // other holds its own.
    let slow_parts = ["--pause-before-part-report-ms", "300"];
    let _w1 = Proc::worker_with(&o, &c, "w1", &slow_parts, Some(&logs[0]));
    let _w2 = Proc::worker_with(&o, &c, "w2", &slow_parts, Some(&logs[1]));
    let target = 7_000u64;
    submit(
        &shared,
        &o,
        &["--brick", "24", "--target-bytes", &target.to_string()],
    );
    let js = wait_for(&o, 120, "the bricked job done", |js| {
        js.iter()
            .any(|j| !is_part(j) && state_name(j.state) == "done")
    })
    .await;
    let parent = js.iter().find(|j| !is_part(j)).unwrap();
    let parts: Vec<_> = js.iter().filter(|j| is_part(j)).collect();
    let trials: HashSet<u32> = parts
        .iter()
        .filter_map(|p| match p.spec.as_ref()?.part.as_ref()?.step {
            Some(pb::part_spec::Step::Encode(ref e)) => Some(e.trial),
            _ => None,
        })
        .collect();
    assert_eq!(
        parts.len(),
        8 * (1 + trials.len()),
        "8 bricks scored, 8 per trial"
    );
    assert!(parts.iter().all(|p| state_name(p.state) == "done"));
    // `jobs list` shows the job and counts its parts; `--parts` lists them, labelled.
    let listed = cli_ok(&["jobs", "list", "--orchestrator", &o]);
    assert_eq!(listed.lines().count(), 2, "{listed}");
    assert!(
        listed.contains(&format!("({} parts of bricked or series jobs", parts.len())),
        "{listed}"
    );
    let all = cli_ok(&["jobs", "list", "--parts", "--orchestrator", &o]);
    assert_eq!(all.lines().count(), 1 + parts.len(), "{all}");
    assert!(all.contains("(part of 1: brick 8/8 scoring)"), "{all}");
    for log in &logs {
        let text = std::fs::read_to_string(log).unwrap();
        let ran = text.lines().filter(|l| l.contains("running part")).count();
        assert!(ran > 0, "{} ran no part:\n{text}", log.display());
    }

    let expected = one_process_file(
        &Phantom::SheppLogan.generate(dims),
        24,
        TargetSpec::Bytes(target),
    );
    let got = expected.len() as u64;
    assert!(got <= target && got as f64 >= 0.98 * target as f64, "{got}");
    assert_eq!(parent.output_bytes, got);
    assert_cache_holds_only(&c, &expected).await;
}

/// Two bricked jobs without refinement (`--effort fast`) in flight at once over two workers,
/// their parts interleaved: each worker keeps the tops of the bricks it scores, of both jobs,
/// and codes its encode parts of those bricks (every trial of a byte target's search) from them
/// instead of transforming the brick again; each volume is the file one process makes.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn fast_bricked_jobs_in_flight_together_code_their_bricks_from_the_tops_their_workers_kept() {
    let cl = TestCluster::start(&ORCH_TIMING);
    let (o, c) = (cl.orch.url(), cl.cache.url());
    let volumes = [[56, 48, 40], [48, 56, 40]];
    let shared = cl.root.join("shared");
    std::fs::create_dir_all(&shared).unwrap();
    for (i, dims) in volumes.iter().enumerate() {
        write_f32(
            &shared.join(raw_name(&format!("fast{i}"), *dims, "f32")),
            &phantom(Phantom::Ct, *dims),
        );
    }
    let logs = [cl.root.join("w1.log"), cl.root.join("w2.log")];
    let _w1 = cl.worker("w1", 0, Some(&logs[0]));
    let _w2 = cl.worker("w2", 0, Some(&logs[1]));
    let options = submit_fast_bricked(&shared, &o, 9_000);
    let js = wait_for(&o, 180, "both bricked jobs done", |js| {
        js.iter()
            .filter(|j| !is_part(j) && state_name(j.state) == "done")
            .count()
            == 2
    })
    .await;
    let encodes = js.iter().filter(|j| is_encode_part(j)).count();
    let scores = js.iter().filter(|j| is_part(j)).count() - encodes;
    assert_eq!(scores, 24, "3 × 2 × 2 bricks of each volume scored");
    assert!(encodes >= scores, "every brick coded: {encodes}");
    // Per worker: its encode parts of bricks (parent, brick) it scored or coded in an earlier
    // part, and the parts it coded from a kept top. Only such a brick can be coded from its
    // top, and every such part is but where the brick's share is beyond the top kept, whichever
    // job's part it ran before. How many of the encode parts find their scorer depends on
    // timing (a worker that runs out of its own parts takes the other's): the queue's
    // preference itself is tested in `queue_contract`.
    let field = |line: &str, name: &str| -> Option<u64> {
        line.split(&format!("{name}="))
            .nth(1)?
            .split(' ')
            .next()?
            .parse()
            .ok()
    };
    let brick = |line: &str, step: &str| -> Option<(u64, u32)> {
        let rest = line.split("part=brick ").nth(1)?;
        let index = rest
            .contains(step)
            .then(|| rest.split('/').next()?.parse().ok())??;
        Some((field(line, "parent")?, index))
    };
    let mut from_tops_all = 0;
    let mut parents_run = HashSet::new();
    for log in &logs {
        let text = std::fs::read_to_string(log).unwrap();
        let running: Vec<&str> = text
            .lines()
            .filter(|l| l.contains("running part"))
            .collect();
        let scored: HashSet<(u64, u32)> =
            running.iter().filter_map(|l| brick(l, "scoring")).collect();
        parents_run.extend(scored.iter().map(|(p, _)| *p));
        let mut seen = scored.clone();
        let mut own = 0;
        for b in running.iter().filter_map(|l| brick(l, "coding")) {
            own += usize::from(!seen.insert(b));
        }
        let from_tops = text
            .lines()
            .filter(|l| l.contains("part coded from the top this worker kept"))
            .count();
        assert!(
            from_tops <= own && 4 * from_tops >= 3 * own,
            "{}: {from_tops} of its {own} encode parts of bricks it scored or coded before \
             coded from a kept top:\n{text}",
            log.display()
        );
        from_tops_all += from_tops;
    }
    assert!(from_tops_all > 0, "no part coded from a kept top");
    assert_eq!(parents_run.len(), 2, "both jobs' bricks scored");

    let expected: Vec<Vec<u8>> = volumes
        .iter()
        .map(|dims| one_process_file_with(&Phantom::Ct.generate(*dims), &options))
        .collect();
    let expected: Vec<&[u8]> = expected.iter().map(Vec::as_slice).collect();
    assert_cache_holds_only_these(&c, &expected).await;
}

/// The setup of the takeover tests: the CT phantom of `dims` written as `name`, a fast
/// bricked byte target of 9 000 B submitted (24³ bricks), its only worker `w1` (logging to
/// `log`) SIGKILLed once every brick is scored. `w1` pauses 400 ms before reporting each
/// part, so that it has reported no encode part when it is killed (the poll that sees the
/// last score part done comes within 100 ms). Returns the job's options and brick count.
async fn scored_then_scorer_killed(
    cl: &TestCluster,
    name: &str,
    dims: [usize; 3],
    log: Option<&Path>,
) -> (wavesplat_orchestrator_client::model::JobOptions, usize) {
    let o = cl.orch.url();
    let shared = cl.root.join("shared");
    std::fs::create_dir_all(&shared).unwrap();
    write_f32(
        &shared.join(raw_name(name, dims, "f32")),
        &phantom(Phantom::Ct, dims),
    );
    let w1 = cl.worker("w1", 400, log);
    let options = submit_fast_bricked(&shared, &o, 9_000);
    let bricks = dims.iter().map(|d| d.div_ceil(24)).product::<usize>();
    wait_for(&o, 120, "every brick scored", |js| {
        js.iter()
            .filter(|j| is_part(j) && !is_encode_part(j) && state_name(j.state) == "done")
            .count()
            == bricks
    })
    .await;
    w1.kill();
    (options, bricks)
}

/// A bricked byte target (several trials) whose only worker dies once every brick is scored:
/// the worker that takes over scored none of them, so it transforms each brick once, on its
/// first encode part of it, and codes the search's later trials from the top it kept then
/// (before, it transformed every brick again in every trial); the volume is the file one
/// process makes.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_worker_taking_over_bricks_it_did_not_score_transforms_each_once() {
    let cl = TestCluster::start(&ORCH_TIMING);
    let (o, c) = (cl.orch.url(), cl.cache.url());
    let dims = [56, 48, 40];
    let logs = [cl.root.join("w1.log"), cl.root.join("w2.log")];
    let (options, bricks) = scored_then_scorer_killed(&cl, "handover", dims, Some(&logs[0])).await;
    let _w2 = cl.worker("w2", 0, Some(&logs[1]));
    let js = wait_for(&o, 180, "the bricked job done", |js| {
        js.iter()
            .any(|j| !is_part(j) && state_name(j.state) == "done")
    })
    .await;
    for j in js.iter().filter(|j| !is_part(j)) {
        assert_eq!(state_name(j.state), "done", "{}: {}", name(j), j.error);
    }
    let text = std::fs::read_to_string(&logs[1]).unwrap();
    let coded: Vec<&str> = text
        .lines()
        .filter(|l| l.contains("running part") && l.contains("coding"))
        .filter_map(|l| l.split("part=brick ").nth(1)?.split('/').next())
        .collect();
    let distinct: HashSet<&str> = coded.iter().copied().collect();
    let again = coded.len() - distinct.len();
    assert!(
        again >= bricks,
        "the search's later trials ran on the second worker: {} encode parts of {} bricks\n{text}",
        coded.len(),
        distinct.len()
    );
    let from_tops = text
        .lines()
        .filter(|l| l.contains("part coded from the top this worker kept"))
        .count();
    assert!(
        from_tops <= again && 4 * from_tops >= 3 * again,
        "{from_tops} of {again} encode parts of bricks coded before coded from a kept top\n{text}"
    );
    assert_cache_holds_only(
        &c,
        &one_process_file_with(&Phantom::Ct.generate(dims), &options),
    )
    .await;
}

/// When the scorer of every brick died, two workers share the takeover, and each keeps the
/// tops of the bricks it codes within their caps: as the orchestrator lists them, every
/// encode part prefers the worker that holds its brick's top (the one that last coded it at a
/// count within the brick's cap, else the dead scorer), and after the first trial most name
/// a worker that took its brick over. The job lands as the one-process file.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bricks_taken_over_prefer_the_worker_that_coded_them_last() {
    let cl = TestCluster::start(&ORCH_TIMING);
    let (o, c) = (cl.orch.url(), cl.cache.url());
    let dims = [56, 48, 40];
    let (options, bricks) = scored_then_scorer_killed(&cl, "handover2", dims, None).await;
    let _w2 = cl.worker("w2", 0, None);
    let _w3 = cl.worker("w3", 0, None);
    let js = wait_for(&o, 180, "the bricked job done", |js| {
        js.iter()
            .any(|j| !is_part(j) && state_name(j.state) == "done")
    })
    .await;
    for j in js.iter().filter(|j| !is_part(j)) {
        assert_eq!(state_name(j.state), "done", "{}: {}", name(j), j.error);
    }
    // (brick, trial) → (count, preferred worker, the worker that finished it).
    let mut parts = std::collections::BTreeMap::new();
    for j in js.iter().filter(|j| is_encode_part(j)) {
        let part = j.spec.as_ref().unwrap().part.as_ref().unwrap();
        let Some(pb::part_spec::Step::Encode(e)) = &part.step else {
            unreachable!()
        };
        assert_eq!(state_name(j.state), "done", "{}", name(j));
        parts.insert(
            (part.index, e.trial),
            (e.count, part.prefer_worker.clone(), j.worker.clone()),
        );
    }
    let mut trials: Vec<u32> = parts.keys().map(|&(_, t)| t).collect();
    trials.sort_unstable();
    trials.dedup();
    assert!(
        trials.len() >= 2,
        "the search ran a second trial: {parts:?}"
    );
    // A coder keeps a brick's top where the count is within the brick's cap (the plan's, as
    // the planner computes it): the brick's holder then, whom its next part prefers.
    let plan = wavesplat_compressor::bricked::BrickPlan::new(
        &Phantom::Ct.generate(dims),
        &wavesplat_worker::options::compress_options(&options),
        24,
    )
    .unwrap();
    let mut holder: Vec<String> = vec!["w1".into(); bricks];
    let mut taken_over = 0;
    for &t in &trials {
        for brick in 0..bricks {
            let (count, prefer, done_by) = &parts[&(brick as u32, t)];
            assert_eq!(
                prefer, &holder[brick],
                "brick {brick}, trial {t}: prefers {prefer:?}, its top held by {:?}",
                holder[brick]
            );
            taken_over += usize::from(holder[brick] != "w1");
            assert!(
                done_by == "w2" || done_by == "w3",
                "brick {brick}, trial {t}: done by {done_by:?}"
            );
            let cap = plan.top_cap(brick).expect("fast bricks keep tops");
            if count.is_some_and(|k| k <= cap) {
                holder[brick] = done_by.clone();
            }
        }
    }
    // Had the parts not followed the takeover, every one would prefer the dead scorer.
    assert!(
        taken_over >= bricks,
        "{taken_over} encode parts preferred a worker that took its brick over"
    );
    assert_cache_holds_only(
        &c,
        &one_process_file_with(&Phantom::Ct.generate(dims), &options),
    )
    .await;
}

/// A job carries `archive submit --memory-limit` to its workers, which keep to it: a bricked
/// job whose limit leaves nothing beside one brick has its bricks coded by transforming them
/// again on a worker that would otherwise keep their tops, and lands as the one-process file;
/// a volume no brick of which fits the limit fails, saying what it needs, instead of running
/// out of memory on a worker.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_keeps_to_its_memory_limit_on_the_workers() {
    use wavesplat_compressor::bricked::{BrickError, BrickPlan};
    use wavesplat_compressor::encode::CompressError;
    use wavesplat_orchestrator_client::model::{Effort, JobOptions, TargetSpec};
    let cl = TestCluster::start(&ORCH_TIMING);
    let (o, c) = (cl.orch.url(), cl.cache.url());
    let dims = [48, 48, 32];
    let shared = cl.root.join("shared");
    std::fs::create_dir_all(&shared).unwrap();
    let volume = Phantom::Ct.generate(dims);
    write_f32(
        &shared.join(raw_name("tight", dims, "f32")),
        &volume.to_interleaved(),
    );
    let log = cl.root.join("w1.log");
    let _w1 = cl.worker("w1", 0, Some(&log));
    let target = 9_000u64;
    let mut options = JobOptions {
        levels: Some(2),
        brick: Some(24),
        effort: Effort::Fast,
        target: TargetSpec::Bytes(target),
        memory_limit: Some(1),
        ..Default::default()
    };
    // What one brick needs, by the compressor's own estimate: a limit of exactly that leaves
    // nothing for kept tops on a worker of one thread.
    let refused = BrickPlan::new(
        &volume,
        &wavesplat_worker::options::compress_options(&options),
        24,
    )
    .err();
    let Some(BrickError::Compress { source, .. }) = refused else {
        panic!("a limit of one byte is refused: {refused:?}");
    };
    let CompressError::MemoryLimit { needed, .. } = *source else {
        panic!("refused for memory: {source}");
    };
    options.memory_limit = Some(needed);
    submit(
        &shared,
        &o,
        &[
            "--brick",
            "24",
            "--effort",
            "fast",
            "--target-bytes",
            &target.to_string(),
            "--memory-limit",
            &needed.to_string(),
        ],
    );
    let js = wait_for(&o, 180, "the bricked job done", all_finished).await;
    for j in &js {
        assert_eq!(state_name(j.state), "done", "{}: {}", name(j), j.error);
    }
    let text = std::fs::read_to_string(&log).unwrap();
    let coded = text
        .lines()
        .filter(|l| l.contains("running part") && l.contains("coding"))
        .count();
    assert!(
        coded >= 8,
        "every brick coded on the one worker: {coded}\n{text}"
    );
    // Every brick's top went to the temporary file, none to memory (where an unlimited job
    // keeps them: `fast_bricked_jobs_in_flight_together…`).
    let scored: Vec<&str> = text
        .lines()
        .filter(|l| l.contains("brick scored; its top kept"))
        .collect();
    assert!(scored.len() >= 8, "{text}");
    assert!(
        scored
            .iter()
            .all(|l| l.contains("kept in the temporary file")),
        "a top kept in memory beyond the job's memory limit:\n{text}"
    );
    assert_cache_holds_only(&c, &one_process_file_with(&volume, &options)).await;

    // The same volume under a limit no brick fits: refused by the compressor on the worker,
    // saying so (a permanent failure, not retried).
    let out = cli(&[
        "archive",
        "submit",
        shared.to_str().unwrap(),
        "--orchestrator",
        &o,
        "--detach",
        "--levels",
        "2",
        "--name-suffix=-small",
        "--memory-limit",
        "1M",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let js = wait_for(&o, 120, "the second job finished", all_finished).await;
    let failed: Vec<_> = js
        .iter()
        .filter(|j| !is_part(j) && name(j).ends_with("-small"))
        .collect();
    assert_eq!(failed.len(), 1);
    let j = failed[0];
    assert_eq!(state_name(j.state), "failed", "{}", j.error);
    assert!(
        j.error.contains("bytes of memory") && j.error.contains("the limit is 1048576 bytes"),
        "{}",
        j.error
    );
    assert_eq!(j.attempts, 1, "not retried: {}", j.error);
}

/// A bricked job (32³ bricks) of a 64³ f32 raw file on shared storage named after `name`.
fn bricked_parent(name: &str, sha: u8) -> wavesplat_orchestrator_client::model::JobSpec {
    use wavesplat_orchestrator_client::model::{JobOptions, JobSpec, Source};
    JobSpec {
        name: name.into(),
        source: Source::Path(format!("/shared/{name}_64x64x64_f32.raw").into()),
        sha256: [sha; 32],
        raw: None,
        channel: None,
        options: JobOptions {
            brick: Some(32),
            ..JobOptions::default()
        },
        part: None,
    }
}

/// The lease `worker` takes next (there must be a job to take).
async fn lease_as(c: &mut wavesplat_orchestrator_client::Client, worker: &str) -> pb::Lease {
    c.lease(pb::LeaseRequest {
        worker: worker.into(),
        parts_only: false,
    })
    .await
    .unwrap()
    .into_inner()
    .lease
    .expect("a job to lease")
}

/// The parts' RPCs from the other side of the wire, as a worker that does not follow the
/// rules would call them: parts only for the job one holds, only as its spec; results only
/// complete and as announced, only through `FinishPart`, only to the holder of the parent;
/// cancelling a bricked job cancels its parts.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_parts_rpcs_hold_their_rules_against_a_raw_client() {
    use tonic::Code;
    use wavesplat_orchestrator_client::model::{JobSpec, PartSpec, PartStep};
    use wavesplat_orchestrator_client::{self as client, convert};
    let cl = TestCluster::start(&ORCH_TIMING);
    let mut c = client::connect(&cl.orch.url()).await.unwrap();
    let parent_spec = bricked_parent("large", 5);
    client::submit(&mut c, &parent_spec, None).await.unwrap();
    let lease = lease_as(&mut c, "coord").await;
    let (pid, pat) = (lease.job_id, lease.attempt);
    let held = client::HeldLease::of(&lease);
    let part = |index: u32| JobSpec {
        part: Some(PartSpec {
            parent: pid,
            index,
            of: 8,
            step: PartStep::Score { energies: false },
            levels: 2,
            offset: Some(0.0),
            color: None,
            source_bytes: None,
            time_points: None,
            prefer_worker: None,
        }),
        ..parent_spec.clone()
    };
    let ask = |attempt: u32, specs: Vec<JobSpec>| {
        held.request(pb::SubmitPartsRequest {
            parent_id: pid,
            parent_attempt: attempt,
            parts: specs.iter().map(convert::spec_to_pb).collect(),
        })
    };
    let code = |r: Result<tonic::Response<pb::SubmitPartsResponse>, tonic::Status>| {
        r.map(|_| ()).unwrap_err().code()
    };
    assert_eq!(
        code(c.submit_parts(ask(pat + 1, vec![part(0)])).await),
        Code::FailedPrecondition
    );
    let renamed = JobSpec {
        name: "other".into(),
        ..part(0)
    };
    assert_eq!(
        code(c.submit_parts(ask(pat, vec![renamed])).await),
        Code::InvalidArgument
    );
    let mut elsewhere = part(0);
    elsewhere.part.as_mut().unwrap().parent = pid + 7;
    assert_eq!(
        code(c.submit_parts(ask(pat, vec![elsewhere])).await),
        Code::InvalidArgument
    );
    assert_eq!(
        code(c.submit_parts(ask(pat, vec![parent_spec.clone()])).await),
        Code::InvalidArgument
    );
    let mut outside = part(0);
    outside.part.as_mut().unwrap().index = 8;
    assert_eq!(
        code(c.submit_parts(ask(pat, vec![outside])).await),
        Code::InvalidArgument
    );
    let submitted = client::submit(&mut c, &part(0), None).await;
    assert_eq!(
        submitted.unwrap_err().code(),
        Code::InvalidArgument,
        "a part is not submitted as a job"
    );
    let states = c
        .submit_parts(ask(pat, vec![part(0), part(1)]))
        .await
        .unwrap()
        .into_inner()
        .parts;
    assert_eq!(states.len(), 2);
    assert!(states.iter().all(|p| state_name(p.state) == "queued"));
    let again = c
        .submit_parts(ask(pat, vec![part(0), part(1)]))
        .await
        .unwrap()
        .into_inner()
        .parts;
    assert_eq!(
        again.iter().map(|p| p.id).collect::<Vec<_>>(),
        states.iter().map(|p| p.id).collect::<Vec<_>>(),
        "asking again polls the same parts"
    );

    let p = c
        .lease(pb::LeaseRequest {
            worker: "w".into(),
            parts_only: true,
        })
        .await
        .unwrap()
        .into_inner()
        .lease
        .unwrap();
    assert_eq!(p.job_id, states[0].id);
    let held_part = client::HeldLease::of(&p);
    let finish = c
        .finish(held_part.request(pb::FinishRequest {
            job_id: p.job_id,
            attempt: p.attempt,
            worker: "w".into(),
            outcome: Some(pb::finish_request::Outcome::Delivered(pb::Delivered {
                sha256: "0".repeat(64),
                ..Default::default()
            })),
        }))
        .await;
    assert_eq!(
        finish.unwrap_err().code(),
        Code::InvalidArgument,
        "a part's result needs FinishPart"
    );
    let result = b"a brick's summary".to_vec();
    let send = |size: u64, sha: Vec<u8>, chunks: Vec<Vec<u8>>, attempt: u32| {
        let mut m = vec![pb::FinishPartRequest {
            msg: Some(pb::finish_part_request::Msg::Head(pb::PartResult {
                job_id: p.job_id,
                attempt,
                worker: "w".into(),
                size,
                sha256: sha,
                voxels: 1,
            })),
        }];
        m.extend(chunks.into_iter().map(|c| pb::FinishPartRequest {
            msg: Some(pb::finish_part_request::Msg::Chunk(c)),
        }));
        held_part.request(tokio_stream::iter(m))
    };
    let sha = wavesplat_net::digest::sha256(&result).to_vec();
    let n = result.len() as u64;
    for (size, digest, chunks, attempt) in [
        (n, sha.clone(), vec![result[..5].to_vec()], p.attempt),
        (n, sha.clone(), vec![result.clone(), vec![0]], p.attempt),
        (n, vec![0; 32], vec![result.clone()], p.attempt),
        (n, sha.clone(), vec![result.clone()], p.attempt + 1),
        (1 << 40, sha.clone(), vec![result.clone()], p.attempt),
    ] {
        let r = c.finish_part(send(size, digest, chunks, attempt)).await;
        assert!(r.is_err(), "size {size}, attempt {attempt}: accepted");
    }
    let fetch = |attempt: u32, part: u64| {
        held.request(pb::FetchResultRequest {
            parent_id: pid,
            parent_attempt: attempt,
            part_id: part,
        })
    };
    let none = c.fetch_result(fetch(pat, p.job_id)).await;
    assert_eq!(
        none.map(|_| ()).unwrap_err().code(),
        Code::FailedPrecondition,
        "no result yet"
    );
    let done = c
        .finish_part(send(
            n,
            sha.clone(),
            vec![result[..4].to_vec(), result[4..].to_vec()],
            p.attempt,
        ))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(state_name(done.state), "done");
    assert_eq!(done.output_bytes, n);
    assert!(
        c.fetch_result(fetch(pat + 1, p.job_id)).await.is_err(),
        "not the parent's holder"
    );
    assert!(
        c.fetch_result(fetch(pat, pid)).await.is_err(),
        "the parent is no part"
    );
    let mut got = Vec::new();
    let mut s = c
        .fetch_result(fetch(pat, p.job_id))
        .await
        .unwrap()
        .into_inner();
    while let Some(chunk) = s.message().await.unwrap() {
        got.extend_from_slice(&chunk.data);
    }
    assert_eq!(got, result);

    c.cancel_job(pb::JobRef { id: pid }).await.unwrap();
    let js = jobs(&cl.orch.url()).await;
    let state_of = |id: u64| state_name(js.iter().find(|j| j.id == id).unwrap().state);
    assert_eq!(state_of(states[0].id), "done");
    assert_eq!(
        state_of(states[1].id),
        "cancelled",
        "a bricked job's parts go with it"
    );
}

/// Cancelling a bricked job while its worker adds parts over several connections at once: the
/// cancel (the job and its parts) and each addition (checked against the job's lease) are one
/// step each, so whatever was added before the cancel is cancelled with it and nothing is added
/// after it: no part of the job is left to run.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cancelling_a_bricked_job_while_its_parts_are_added_leaves_none_to_run() {
    use tonic::Code;
    use wavesplat_orchestrator_client::model::{JobSpec, PartSpec, PartStep};
    use wavesplat_orchestrator_client::{self as client, convert, HeldLease};
    let cl = TestCluster::start(&ORCH_TIMING);
    let url = cl.orch.url();
    let mut c = client::connect(&url).await.unwrap();
    let mut added = 0;
    for round in 0..8u32 {
        let parent_spec = bricked_parent(&format!("large{round}"), round as u8 + 1);
        client::submit(&mut c, &parent_spec, None).await.unwrap();
        let lease = lease_as(&mut c, "coord").await;
        let held = HeldLease::of(&lease);
        let pid = held.job_id;
        let mut adders = Vec::new();
        for w in 0..4u32 {
            let (url, held, parent_spec) = (url.clone(), held.clone(), parent_spec.clone());
            adders.push(tokio::spawn(async move {
                let mut c = client::connect(&url).await.unwrap();
                let part = |index: u32| JobSpec {
                    part: Some(PartSpec {
                        parent: held.job_id,
                        index,
                        of: 128,
                        step: PartStep::Score { energies: false },
                        levels: 2,
                        offset: Some(0.0),
                        color: None,
                        source_bytes: None,
                        time_points: None,
                        prefer_worker: None,
                    }),
                    ..parent_spec.clone()
                };
                // Calls of eight parts each: a call whose lease was checked before the cancel
                // must still add none after it.
                for call in 0..4u32 {
                    let first = w * 32 + call * 8;
                    let req = pb::SubmitPartsRequest {
                        parent_id: held.job_id,
                        parent_attempt: held.attempt,
                        parts: (first..first + 8)
                            .map(|k| convert::spec_to_pb(&part(k)))
                            .collect(),
                    };
                    if let Err(s) = c.submit_parts(held.request(req)).await {
                        assert_eq!(s.code(), Code::FailedPrecondition, "{s:?}");
                        return;
                    }
                }
            }));
        }
        tokio::time::sleep(std::time::Duration::from_millis(u64::from(round) * 3)).await;
        c.cancel_job(pb::JobRef { id: pid }).await.unwrap();
        for a in adders {
            a.await.unwrap();
        }
        let parts: Vec<pb::Job> = jobs(&url)
            .await
            .into_iter()
            .filter(|j| {
                j.spec
                    .as_ref()
                    .and_then(|s| s.part.as_ref())
                    .is_some_and(|p| p.parent == pid)
            })
            .collect();
        added += parts.len();
        let live: Vec<u64> = parts
            .iter()
            .filter(|j| !matches!(state_name(j.state), "cancelled" | "failed" | "done"))
            .map(|j| j.id)
            .collect();
        assert!(
            live.is_empty(),
            "round {round}: parts {live:?} live after their job was cancelled"
        );
    }
    assert!(added > 0, "no part was added before a cancel in 8 rounds");
    let left = c
        .lease(pb::LeaseRequest {
            worker: "late".into(),
            parts_only: true,
        })
        .await
        .unwrap()
        .into_inner()
        .lease;
    assert!(left.is_none(), "a part to run: {left:?}");
}

/// A bricked job cancelled while its parts run goes with its parts in one step (none left to
/// run, the done ones' results dropped); retried, its next attempt runs every part again and
/// the volume lands, byte for byte the file one process makes.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_cancelled_bricked_job_retried_runs_its_parts_again_and_lands() {
    use wavesplat_orchestrator_client::model::TargetSpec;
    let cl = TestCluster::start(&ORCH_TIMING);
    let (o, c) = (cl.orch.url(), cl.cache.url());
    let dims = [48, 40, 36];
    let shared = cl.root.join("shared");
    std::fs::create_dir_all(&shared).unwrap();
    write_f32(
        &shared.join(raw_name("again", dims, "f32")),
        &phantom(Phantom::SheppLogan, dims),
    );
    let slow_parts = ["--pause-before-part-report-ms", "400"];
    let _w = Proc::worker_with(&o, &c, "w1", &slow_parts, None);
    submit(&shared, &o, &["--brick", "24"]);
    let js = wait_for(&o, 60, "some of the bricked job's parts done", |js| {
        js.iter()
            .filter(|j| is_part(j) && state_name(j.state) == "done")
            .count()
            >= 2
    })
    .await;
    let parent = js.iter().find(|j| !is_part(j)).unwrap().id;
    let mut orch = wavesplat_orchestrator_client::connect(&o).await.unwrap();
    let cancelled = orch
        .cancel_job(pb::JobRef { id: parent })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(state_name(cancelled.state), "cancelled");
    let js = jobs(&o).await;
    let parts: Vec<&pb::Job> = js.iter().filter(|j| is_part(j)).collect();
    assert!(
        parts
            .iter()
            .all(|j| matches!(state_name(j.state), "done" | "cancelled")),
        "a part left to run: {parts:?}"
    );
    let done_before = parts
        .iter()
        .filter(|j| state_name(j.state) == "done")
        .count();
    assert!(done_before >= 2, "{parts:?}");
    // Let the worker learn of the cancel (at its next heartbeat), then retry.
    tokio::time::sleep(std::time::Duration::from_millis(800)).await;
    orch.retry_job(pb::JobRef { id: parent }).await.unwrap();
    let js = wait_for(&o, 120, "the retried bricked job done", |js| {
        js.iter()
            .any(|j| j.id == parent && matches!(state_name(j.state), "done" | "failed"))
    })
    .await;
    let job = js.iter().find(|j| j.id == parent).unwrap();
    assert_eq!(state_name(job.state), "done", "{}", job.error);
    let volume = Phantom::SheppLogan.generate(dims);
    let expected = one_process_file(&volume, 24, TargetSpec::Fraction(0.05));
    assert_cache_holds_only(&c, &expected).await;
}

/// The orchestrator is SIGKILLed and restarted while a bricked job's parts run: the worker
/// keeps going (its reports retried until the orchestrator answers), and the volume lands
/// once, the file one process makes.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_bricked_job_survives_an_orchestrator_restart_midway() {
    use wavesplat_orchestrator_client::model::TargetSpec;
    let mut cl = TestCluster::start(&ORCH_TIMING);
    let (o, c) = (cl.orch.url(), cl.cache.url());
    let dims = [96, 72, 48];
    let shared = cl.root.join("shared");
    std::fs::create_dir_all(&shared).unwrap();
    write_f32(
        &shared.join(raw_name("midway", dims, "f32")),
        &phantom(Phantom::Spheres, dims),
    );
    let _w = cl.worker("w", 0, None);
    submit(&shared, &o, &["--brick", "24", "--target-fraction", "0.04"]);
    wait_for(&o, 60, "some of the bricks scored", |js| {
        js.iter()
            .filter(|j| is_part(j) && state_name(j.state) == "done")
            .count()
            >= 3
    })
    .await;
    cl.restart_orchestrator();
    let js = wait_for(&o, 120, "the bricked job done", |js| {
        js.iter()
            .any(|j| !is_part(j) && state_name(j.state) == "done")
    })
    .await;
    let parts: Vec<_> = js.iter().filter(|j| is_part(j)).collect();
    assert_eq!(parts.len(), 2 * 24, "{} parts", parts.len());
    assert!(parts.iter().all(|p| p.attempts <= 2), "{parts:?}");
    let expected = one_process_file(
        &Phantom::Spheres.generate(dims),
        24,
        TargetSpec::Fraction(0.04),
    );
    assert_cache_holds_only(&c, &expected).await;
}

/// A worker SIGKILLed while it runs one brick's part: only that part runs again (its lease
/// lapses), the worker planning the job is not disturbed, and the volume lands once, the file
/// one process makes.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_part_whose_worker_dies_runs_again_alone() {
    use wavesplat_orchestrator_client::model::TargetSpec;
    let cl = TestCluster::start(&ORCH_TIMING);
    let (o, c) = (cl.orch.url(), cl.cache.url());
    let dims = [96, 96, 64];
    let shared = cl.root.join("shared");
    std::fs::create_dir_all(&shared).unwrap();
    write_f32(
        &shared.join(raw_name("victim", dims, "f32")),
        &phantom(Phantom::SheppLogan, dims),
    );
    let _planner = cl.worker("planner", 0, None);
    submit(&shared, &o, &["--brick", "32", "--target-fraction", "0.03"]);
    wait_for(&o, 30, "the planner holding the bricked job", |js| {
        js.iter().any(|j| !is_part(j) && j.worker == "planner")
    })
    .await;
    // This worker computes a part, then hangs before reporting it: SIGKILL it there.
    let doomed = Proc::worker_with(
        &o,
        &c,
        "doomed",
        &["--pause-before-part-report-ms", "60000"],
        None,
    );
    let held = |j: &pb::Job| is_part(j) && j.worker == "doomed" && j.stage.contains("paused");
    let js = wait_for(&o, 60, "a part held by the doomed worker", |js| {
        js.iter().any(held)
    })
    .await;
    let victim = js.iter().find(|j| held(j)).unwrap().id;
    doomed.kill();
    let js = wait_for(&o, 120, "the bricked job done", |js| {
        js.iter()
            .any(|j| !is_part(j) && state_name(j.state) == "done")
    })
    .await;
    let parent = js.iter().find(|j| !is_part(j)).unwrap();
    assert_eq!(parent.attempts, 1, "the planner was not disturbed");
    let v = js.iter().find(|j| j.id == victim).unwrap();
    assert_eq!(
        (state_name(v.state), v.attempts),
        ("done", 2),
        "the killed part ran again: {v:?}"
    );
    assert!(v.error.contains("stopped heartbeating"), "{}", v.error);
    let parts: Vec<_> = js.iter().filter(|j| is_part(j)).collect();
    assert_eq!(parts.len(), 2 * 18);
    let again: Vec<u64> = parts
        .iter()
        .filter(|p| p.attempts != 1)
        .map(|p| p.id)
        .collect();
    assert!(
        again.iter().all(|id| *id == victim
            || parts
                .iter()
                .any(|p| p.id == *id && p.error.contains("stopped heartbeating"))),
        "only parts of the killed worker ran twice: {again:?}"
    );
    let expected = one_process_file(
        &Phantom::SheppLogan.generate(dims),
        32,
        TargetSpec::Fraction(0.03),
    );
    assert_cache_holds_only(&c, &expected).await;
}

/// A colour volume's bricks spread over two workers share the whole's PCA colour transform,
/// carried to every part in its spec: the volume lands as the one-process file.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_colour_bricked_job_spread_over_workers_makes_the_one_process_file() {
    use wavesplat_compressor::reader::decode_raw;
    use wavesplat_orchestrator_client::model::{RawLayout, SampleType, TargetSpec};
    let cl = TestCluster::start(&ORCH_TIMING);
    let (o, c) = (cl.orch.url(), cl.cache.url());
    let dims = [40, 36, 30];
    let shared = cl.root.join("shared");
    std::fs::create_dir_all(&shared).unwrap();
    let rgb: Vec<u8> = phantom(Phantom::RgbHead, dims)
        .iter()
        .map(|v| (v.clamp(0.0, 1.0) * 255.0) as u8)
        .collect();
    std::fs::write(shared.join(raw_name("colour", dims, "u8_rgb")), &rgb).unwrap();
    let _w1 = cl.worker("w1", 0, None);
    let _w2 = cl.worker("w2", 0, None);
    submit(&shared, &o, &["--brick", "20", "--target-fraction", "0.04"]);
    let js = wait_for(&o, 120, "the colour bricked job done", |js| {
        js.iter()
            .any(|j| !is_part(j) && state_name(j.state) == "done")
    })
    .await;
    assert_eq!(js.iter().filter(|j| is_part(j)).count(), 16);
    let layout = RawLayout {
        dims,
        dtype: SampleType::U8,
        big_endian: false,
        channels: 3,
    };
    let volume = decode_raw(&rgb, &wavesplat_worker::options::raw_spec(&layout)).unwrap();
    let expected = one_process_file(&volume, 20, TargetSpec::Fraction(0.04));
    assert_cache_holds_only(&c, &expected).await;
}

/// The cache is SIGKILLed while a bricked job's planning worker is about to commit it: the
/// commit fails (the cache is unreachable), the job is leased again, its bricks are found
/// done (none is compressed again), and once the cache is back the volume lands once.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_bricked_job_commits_once_after_a_cache_kill() {
    let mut cl = TestCluster::start(&ORCH_TIMING);
    let (o, c) = (cl.orch.url(), cl.cache.url());
    let dims = [48, 40, 36];
    let shared = cl.root.join("shared");
    std::fs::create_dir_all(&shared).unwrap();
    write_f32(
        &shared.join(raw_name("committed", dims, "f32")),
        &phantom(Phantom::SheppLogan, dims),
    );
    let _w = cl.worker("planner", 2_000, None);
    submit(&shared, &o, &["--brick", "24"]);
    wait_for(&o, 60, "the planner about to commit", |js| {
        js.iter().any(|j| !is_part(j) && j.stage.contains("paused"))
    })
    .await;
    cl.kill_cache();
    wait_for(&o, 30, "the commit failed", |js| {
        js.iter().any(|j| !is_part(j) && j.error.contains("cache"))
    })
    .await;
    cl.start_cache_again();
    let js = wait_for(&o, 60, "the bricked job done", |js| {
        js.iter()
            .any(|j| !is_part(j) && state_name(j.state) == "done")
    })
    .await;
    let parent = js.iter().find(|j| !is_part(j)).unwrap();
    assert!(parent.attempts >= 2, "{parent:?}");
    let parts: Vec<_> = js.iter().filter(|j| is_part(j)).collect();
    assert_eq!(parts.len(), 16);
    assert!(parts.iter().all(|p| p.attempts == 1), "no brick ran twice");
    let mut client = CacheClient::connect(&c).await.unwrap();
    let listed = client.list().await.unwrap();
    assert_eq!(listed.len(), 1, "{listed:?}");
    assert_eq!(listed[0].name, "committed");
}

/// A gzip-compressed NIfTI file's bricks spread over two workers (each keeps the inflated file
/// open across the parts it takes): the volume lands as the file one process makes from it,
/// and so does the same file uploaded (read by region from the worker's temporary copy).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_compressed_nifti_bricked_job_spread_over_workers() {
    use std::io::Write;
    use wavesplat_compressor::reader::region::RegionReader;
    use wavesplat_orchestrator_client::model::TargetSpec;
    let cl = TestCluster::start(&ORCH_TIMING);
    let (o, c) = (cl.orch.url(), cl.cache.url());
    let dims = [48, 40, 36];
    let shared = cl.root.join("shared");
    std::fs::create_dir_all(&shared).unwrap();
    let plain = cl.root.join("head.nii");
    write_nifti(&plain, dims, &phantom(Phantom::Spheres, dims));
    let gz = shared.join("head.nii.gz");
    let mut e = flate2::write::GzEncoder::new(
        std::fs::File::create(&gz).unwrap(),
        flate2::Compression::fast(),
    );
    e.write_all(&std::fs::read(&plain).unwrap()).unwrap();
    e.finish().unwrap();
    let _w1 = cl.worker("w1", 0, None);
    let _w2 = cl.worker("w2", 0, None);
    submit(&shared, &o, &["--brick", "24", "--target-fraction", "0.05"]);
    wait_for(&o, 120, "the bricked job done", |js| {
        js.iter()
            .any(|j| !is_part(j) && state_name(j.state) == "done")
    })
    .await;
    let reader = RegionReader::open(&gz, None).unwrap();
    let expected = one_process_file(&reader, 24, TargetSpec::Fraction(0.05));
    assert_cache_holds_only(&c, &expected).await;
    // The same file uploaded: the worker streams it to a temporary file and reads its bricks
    // from there (never holding it whole), into the same bytes.
    let uploaded = cl.root.join("uploaded");
    std::fs::create_dir_all(&uploaded).unwrap();
    std::fs::copy(&gz, uploaded.join("sent.nii.gz")).unwrap();
    submit(
        &uploaded,
        &o,
        &["--brick", "24", "--target-fraction", "0.05", "--upload"],
    );
    wait_for(&o, 120, "the uploaded bricked job done", |js| {
        js.iter()
            .filter(|j| !is_part(j) && state_name(j.state) == "done")
            .count()
            == 2
    })
    .await;
    let mut client = CacheClient::connect(&c).await.unwrap();
    let listed = client.list().await.unwrap();
    assert_eq!(listed.len(), 2, "{listed:?}");
    let sha = wavesplat_net::digest::hex(&wavesplat_net::digest::sha256(&expected));
    assert!(listed.iter().all(|v| v.sha256 == sha), "{listed:?}");
}

/// Sources of several files in `dir`, the same Shepp–Logan samples of `dims` (rounded: the
/// DICOM slices are 16-bit): a DICOM series directory `ct` and a detached MetaImage header
/// `head.mhd` with its data file. Returns their paths.
fn series_and_detached_header(
    dir: &Path,
    dims: [usize; 3],
) -> (std::path::PathBuf, std::path::PathBuf, std::path::PathBuf) {
    use wavesplat_codec::volume::Volume;
    use wavesplat_fixtures::{
        write_dicom_series, write_metaimage, write_tiff_stack, DicomOptions, Layout,
    };
    let series = dir.join("ct");
    std::fs::create_dir_all(&series).unwrap();
    let samples: Vec<f32> = phantom(Phantom::SheppLogan, dims)
        .iter()
        .map(|x| x.round())
        .collect();
    let v = Volume::new(dims, [1.0, 1.0, 1.0], vec![samples]).unwrap();
    let dicom = DicomOptions {
        layout: Layout::U16,
        ..Default::default()
    };
    write_dicom_series(&series, &v, &dicom);
    let header = write_metaimage(dir, "head", &v, Layout::F32, false, true);
    // A directory of TIFF slices, z1.tif … z30.tif.
    let stack = write_tiff_stack(dir, "scope", &v, Layout::U16, true, true);
    (series, header, stack)
}

/// A DICOM series directory, a detached MetaImage header (its data in another file) and a
/// directory of TIFF slices on shared storage: their bricked jobs are hashed file by file and spread over the workers like
/// a single file's (parts read slice ranges and regions, nobody holds the volume), and each
/// lands as the file one process makes from the same source.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_dicom_series_and_a_detached_header_spread_their_bricks_over_workers() {
    use wavesplat_compressor::reader::region::RegionReader;
    use wavesplat_orchestrator_client::model::TargetSpec;
    let cl = TestCluster::start(&ORCH_TIMING);
    let (o, c) = (cl.orch.url(), cl.cache.url());
    let dims = [40, 36, 30];
    let shared = cl.root.join("shared");
    let (series, header, stack) = series_and_detached_header(&shared, dims);
    assert!(
        shared.join("head.raw").is_file(),
        "a detached header's data file"
    );
    let logs = [cl.root.join("w1.log"), cl.root.join("w2.log")];
    let _w1 = cl.worker("w1", 0, Some(&logs[0]));
    let _w2 = cl.worker("w2", 0, Some(&logs[1]));
    submit(&shared, &o, &["--brick", "20", "--target-fraction", "0.05"]);
    let js = wait_for(&o, 180, "every bricked job done", all_finished).await;
    let (parts, js): (Vec<_>, Vec<_>) = js.into_iter().partition(is_part);
    assert_eq!(js.len(), 3, "one job per volume");
    for j in js.iter().chain(&parts) {
        assert_eq!(state_name(j.state), "done", "{}: {}", name(j), j.error);
    }
    for j in &js {
        let mine = parts
            .iter()
            .filter(|p| {
                p.spec
                    .as_ref()
                    .and_then(|s| s.part.as_ref())
                    .is_some_and(|p| p.parent == j.id)
            })
            .count();
        // 2 × 2 × 2 bricks, scored and coded.
        assert_eq!(mine, 16, "{}: its bricks ran as parts", name(j));
    }
    each_ran_a_part(&logs);
    let mut client = CacheClient::connect(&c).await.unwrap();
    let listed = client.list().await.unwrap();
    assert_eq!(listed.len(), 3, "{listed:?}");
    for (source, wanted) in [(&series, "ct"), (&header, "head"), (&stack, "scope")] {
        let reader = RegionReader::open(source, None).unwrap();
        let one = one_process_file(&reader, 20, TargetSpec::Fraction(0.05));
        let got = listed
            .iter()
            .find(|l| l.name == wanted)
            .unwrap_or_else(|| panic!("{wanted} in {listed:?}"));
        assert_eq!(
            got.sha256,
            wavesplat_net::digest::hex(&wavesplat_net::digest::sha256(&one)),
            "{wanted}: not the one-process file"
        );
    }
}

/// Multi-file sources uploaded as bricked jobs (`--upload --brick`): a DICOM series, a
/// detached MetaImage header and a directory of TIFF slices are unpacked file by file into the worker's scratch directory as
/// they stream (never held whole) and land as the file one process makes from the same
/// source; an uploaded 4D NIfTI is refused with what to do instead, bricked or not. The
/// worker, started with `--scratch-dir`, removes there the upload a dead worker left, and
/// leaves no upload of its own behind.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn uploaded_bundles_unpack_as_they_stream_and_an_uploaded_series_is_refused() {
    use wavesplat_compressor::reader::region::RegionReader;
    use wavesplat_fixtures::write_nifti_series;
    use wavesplat_orchestrator_client::model::TargetSpec;
    let cl = TestCluster::start(&ORCH_TIMING);
    let (o, c) = (cl.orch.url(), cl.cache.url());
    let dims = [40, 36, 30];
    let up = cl.root.join("up");
    let (series, header, stack) = series_and_detached_header(&up, dims);
    // Time series: one submitted bricked, one whole.
    let cines = [cl.root.join("cine_b"), cl.root.join("cine_w")];
    let points: Vec<Vec<f32>> = (0..3)
        .map(|t| {
            phantom(Phantom::Spheres, [16, 16, 8])
                .iter()
                .map(|x| x * (1.0 + t as f32))
                .collect()
        })
        .collect();
    for (dir, name) in cines.iter().zip(["beat_b.nii", "beat_w.nii"]) {
        std::fs::create_dir_all(dir).unwrap();
        write_nifti_series(&dir.join(name), [16, 16, 8], &points, Some(40.0), false);
    }
    // What a killed worker left: an upload whose lock nobody holds.
    let scratch = cl.root.join("scratch");
    let stale = scratch.join("wavesplat-upload-x1Yz");
    std::fs::create_dir_all(stale.join("source")).unwrap();
    std::fs::write(stale.join(".lock"), b"").unwrap();
    std::fs::write(stale.join("source/source.raw"), b"left behind").unwrap();
    let log = cl.root.join("w1.log");
    let _w = Proc::worker_with(
        &o,
        &c,
        "w1",
        &["--scratch-dir", scratch.to_str().unwrap(), "--log", "info"],
        Some(&log),
    );
    let bricked = ["--brick", "20", "--target-fraction", "0.05", "--upload"];
    submit(&up, &o, &bricked);
    submit(&cines[0], &o, &bricked);
    submit(&cines[1], &o, &["--target-fraction", "0.05", "--upload"]);
    let js = wait_for(&o, 180, "every uploaded job finished", |js| {
        js.len() == 5 && all_finished(js)
    })
    .await;
    let state = |wanted: &str| {
        let j = js
            .iter()
            .find(|j| name(j) == wanted)
            .unwrap_or_else(|| panic!("{wanted}: {js:?}"));
        (state_name(j.state), j.error.clone())
    };
    for wanted in ["beat_b", "beat_w"] {
        let (s, error) = state(wanted);
        assert_eq!(s, "failed", "{wanted}");
        assert!(
            error.contains("a time series of 3 time points, uploaded")
                && error.contains("without --upload"),
            "{wanted}: {error}"
        );
    }
    let mut client = CacheClient::connect(&c).await.unwrap();
    let listed = client.list().await.unwrap();
    assert_eq!(listed.len(), 3, "{listed:?}");
    for (source, wanted) in [(&series, "ct"), (&header, "head"), (&stack, "scope")] {
        assert_eq!(state(wanted).0, "done", "{wanted}: {}", state(wanted).1);
        let reader = RegionReader::open(source, None).unwrap();
        let one = one_process_file(&reader, 20, TargetSpec::Fraction(0.05));
        let got = listed.iter().find(|l| l.name == wanted).unwrap();
        assert_eq!(
            got.sha256,
            wavesplat_net::digest::hex(&wavesplat_net::digest::sha256(&one)),
            "{wanted}: not the one-process file"
        );
    }
    let text = std::fs::read_to_string(&log).unwrap();
    assert_eq!(
        text.matches("uploaded bundle unpacked").count(),
        3,
        "every bundle unpacked as it streamed:\n{text}"
    );
    assert!(
        !stale.exists(),
        "the dead worker's upload is removed:\n{text}"
    );
    let left: Vec<_> = std::fs::read_dir(&scratch)
        .unwrap()
        .flatten()
        .map(|e| e.file_name())
        .filter(|n| n.to_string_lossy().starts_with("wavesplat-upload-"))
        .collect();
    assert!(
        left.is_empty(),
        "uploads left in the scratch directory: {left:?}"
    );
}

/// A volume on shared storage submitted without `--brick` that would not fit a worker's memory
/// whole (`archive submit --memory-limit`) is submitted as a bricked job by itself, saying so,
/// at the largest side of which a brick fits; its bricks spread over both workers and it lands
/// as the file one process makes in those bricks. A volume that fits stays whole.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_volume_too_large_for_a_worker_is_submitted_as_bricks_by_itself() {
    use wavesplat_compressor::reader::region::RegionReader;
    use wavesplat_orchestrator_client::model::TargetSpec;
    let cl = TestCluster::start(&ORCH_TIMING);
    let (o, c) = (cl.orch.url(), cl.cache.url());
    let shared = cl.root.join("shared");
    std::fs::create_dir_all(&shared).unwrap();
    let dims = [128, 128, 128];
    let big = shared.join(raw_name("big", dims, "f32"));
    write_f32(&big, &phantom(Phantom::SheppLogan, dims));
    let small_dims = [32, 32, 24];
    let small = shared.join(raw_name("small", small_dims, "f32"));
    write_f32(&small, &phantom(Phantom::SheppLogan, small_dims));
    let logs = [cl.root.join("w1.log"), cl.root.join("w2.log")];
    let _w1 = cl.worker("w1", 0, Some(&logs[0]));
    let _w2 = cl.worker("w2", 0, Some(&logs[1]));
    // By the estimate the 128³ whole at depth 2 needs ~175 MB, a 64³ brick much less (64 MB of
    // it the process's): 160 MiB takes a brick, not the whole.
    let out = cli(&[
        "archive",
        "submit",
        shared.to_str().unwrap(),
        "--orchestrator",
        &o,
        "--detach",
        "--levels",
        "2",
        "--target-fraction",
        "0.05",
        "--memory-limit",
        "160M",
    ]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        out.status.success(),
        "{}: {stderr}{}",
        out.status,
        String::from_utf8_lossy(&out.stdout)
    );
    assert!(
        stderr.contains("big_128x128x128_f32.raw")
            && stderr.contains("bricks of at most 64 voxels a side")
            && stderr.contains("--memory-limit"),
        "{stderr}"
    );
    assert!(
        !stderr.contains("small_"),
        "the small volume fits: {stderr}"
    );
    let js = wait_for(&o, 180, "both jobs done", all_finished).await;
    let (parts, js): (Vec<_>, Vec<_>) = js.into_iter().partition(is_part);
    assert_eq!(js.len(), 2, "one job per volume");
    for j in js.iter().chain(&parts) {
        assert_eq!(state_name(j.state), "done", "{}: {}", name(j), j.error);
    }
    // 2 × 2 × 2 bricks of the large volume, scored and coded; none of the small one.
    assert_eq!(parts.len(), 16, "the large volume's bricks ran as parts");
    each_ran_a_part(&logs);
    let mut client = CacheClient::connect(&c).await.unwrap();
    let listed = client.list().await.unwrap();
    let got = listed
        .iter()
        .find(|l| l.name == "big")
        .unwrap_or_else(|| panic!("big in {listed:?}"));
    let (_, layout) = wavesplat_worker::archive::parse_raw_name("big_128x128x128_f32.raw").unwrap();
    let raw = wavesplat_worker::options::raw_spec(&layout);
    let reader = RegionReader::open(&big, Some(&raw)).unwrap();
    let one = one_process_file(&reader, 64, TargetSpec::Fraction(0.05));
    assert_eq!(
        got.sha256,
        wavesplat_net::digest::hex(&wavesplat_net::digest::sha256(&one)),
        "not the one-process file in 64³ bricks"
    );
}

/// The source file changes while its bricks are being compressed: the next part refuses it,
/// and the job fails for good saying so, instead of mixing two files' bricks in the cache.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_source_changed_midway_fails_the_bricked_job_clearly() {
    let cl = TestCluster::start(&ORCH_TIMING);
    let (o, c) = (cl.orch.url(), cl.cache.url());
    let dims = [48, 40, 36];
    let shared = cl.root.join("shared");
    std::fs::create_dir_all(&shared).unwrap();
    let file = shared.join(raw_name("moving", dims, "f32"));
    write_f32(&file, &phantom(Phantom::SheppLogan, dims));
    let _w = Proc::worker_with(
        &o,
        &c,
        "w",
        &["--pause-before-part-report-ms", "1500"],
        None,
    );
    submit(&shared, &o, &["--brick", "24"]);
    wait_for(&o, 60, "a part paused", |js| {
        js.iter().any(|j| is_part(j) && j.stage.contains("paused"))
    })
    .await;
    // Replaced by a longer file under the same name.
    write_f32(&file, &phantom(Phantom::SheppLogan, [48, 40, 40]));
    let js = wait_for(&o, 60, "the bricked job failed", |js| {
        js.iter()
            .any(|j| !is_part(j) && state_name(j.state) == "failed")
    })
    .await;
    let parent = js.iter().find(|j| !is_part(j)).unwrap();
    assert!(
        parent
            .error
            .contains("the source changed since the job was planned"),
        "{}",
        parent.error
    );
    let mut client = CacheClient::connect(&c).await.unwrap();
    assert!(
        client.list().await.unwrap().is_empty(),
        "nothing was delivered"
    );
}

/// A plain job whose source changed between submission and the worker's read fails as the
/// submitter's error, and its failure does not say the SHA-256 the worker found: whoever
/// submits a path could otherwise learn the hash of any file a worker can read.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_changed_source_fails_without_telling_its_hash() {
    let cl = TestCluster::start(&ORCH_TIMING);
    let (o, c) = (cl.orch.url(), cl.cache.url());
    let dims = [20, 18, 16];
    let shared = cl.root.join("shared");
    std::fs::create_dir_all(&shared).unwrap();
    let file = shared.join(raw_name("edited", dims, "f32"));
    write_f32(&file, &phantom(Phantom::SheppLogan, dims));
    submit(&shared, &o, &[]);
    // Edited in place before any worker reads it.
    let edited = phantom(Phantom::Spheres, dims);
    write_f32(&file, &edited);
    let found = wavesplat_net::digest::hex(&wavesplat_net::digest::sha256(
        &std::fs::read(&file).unwrap(),
    ));
    let _w = Proc::worker(&o, &c, "w", 0, None);
    let js = wait_for(&o, 60, "the job failed", |js| {
        js.iter().any(|j| state_name(j.state) == "failed")
    })
    .await;
    let job = js.iter().find(|j| state_name(j.state) == "failed").unwrap();
    assert!(
        job.error.contains("the source changed since submission"),
        "{}",
        job.error
    );
    assert!(!job.error.contains(&found), "{}", job.error);
    let mut client = CacheClient::connect(&c).await.unwrap();
    assert!(client.list().await.unwrap().is_empty(), "nothing delivered");
}

/// A time series in an archive is one job and one volume in the cache: a 4D NIfTI, a DICOM cine
/// (slices repeated at several trigger times) and, with `--time-steps`, a directory of numbered
/// time steps are each compressed into one series file, its units (temporal components) scored
/// and coded as parts spread over two workers (the NIfTI's: the same bytes `compress_series`
/// makes in one process with the job's options), committed once, and each
/// time point streams from the cache with its own components only; a directory whose steps
/// repeat a number is skipped, saying so.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_time_series_in_an_archive_is_one_volume_in_the_cache() {
    use wavesplat_codec::volume::Volume;
    use wavesplat_compressor::phantom::beating;
    use wavesplat_fixtures::{write_dicom_cine, write_nifti_series, DicomOptions, Layout};
    const POINTS: usize = 5;
    let cl = TestCluster::start(&ORCH_TIMING);
    let (o, c) = (cl.orch.url(), cl.cache.url());
    let dir = cl.root.join("cines");
    std::fs::create_dir_all(&dir).unwrap();
    let dims = [24, 20, 12];
    // Integer-valued time points (the DICOM cine's samples are 16-bit).
    let volumes: Vec<Volume> = (0..POINTS)
        .map(|t| {
            let v = beating(dims, t, POINTS).unwrap();
            let data = v.channel(0).iter().map(|x| x.max(0.0).round()).collect();
            Volume::new(dims, [1.0, 1.0, 1.0], vec![data]).unwrap()
        })
        .collect();
    let samples: Vec<Vec<f32>> = volumes.iter().map(|v| v.channel(0).to_vec()).collect();
    write_nifti_series(&dir.join("heart.nii"), dims, &samples, Some(40.0), false);
    let ms: Vec<f64> = (0..POINTS).map(|t| t as f64 * 40.0).collect();
    let o_dicom = DicomOptions {
        layout: Layout::U16,
        ..Default::default()
    };
    write_dicom_cine(&dir.join("cine"), &volumes, &ms, &o_dicom);
    std::fs::create_dir_all(dir.join("run")).unwrap();
    for (t, v) in samples.iter().enumerate() {
        write_nifti(&dir.join(format!("run/step_{:04}.nii", 10 * t)), dims, v);
    }
    std::fs::create_dir_all(dir.join("broken")).unwrap();
    write_nifti(&dir.join("broken/a_1.nii"), dims, &samples[0]);
    write_nifti(&dir.join("broken/b_1.nii"), dims, &samples[1]);
    let logs = [cl.root.join("w1.log"), cl.root.join("w2.log")];
    let _w1 = cl.worker("w1", 0, Some(&logs[0]));
    let _w2 = cl.worker("w2", 0, Some(&logs[1]));
    let out = cli(&[
        "archive",
        "submit",
        dir.to_str().unwrap(),
        "--orchestrator",
        &o,
        "--detach",
        "--levels",
        "2",
        "--time-steps",
        "--time-group",
        "4",
        "--target-fraction",
        "0.2",
    ]);
    let said = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(out.status.success(), "{said}");
    assert!(
        said.contains("skipped") && said.contains("broken") && said.contains("step"),
        "{said}"
    );
    let js = wait_for(&o, 120, "the series done", all_finished).await;
    let (parts, js): (Vec<_>, Vec<_>) = js.into_iter().partition(is_part);
    assert_eq!(js.len(), 3, "one job per series");
    for j in js.iter().chain(&parts) {
        assert_eq!(state_name(j.state), "done", "{}: {}", name(j), j.error);
    }
    // Each series' units (a temporal component each: 2 groups of 4 and 1 make 5) were scored
    // and coded as parts, and both workers ran some.
    for j in &js {
        let units: Vec<&pb::PartSpec> = parts
            .iter()
            .filter_map(|p| p.spec.as_ref()?.part.as_ref())
            .filter(|p| p.parent == j.id)
            .collect();
        assert!(units.len() >= 10, "{}: {} parts", name(j), units.len());
        assert!(
            units
                .iter()
                .all(|p| p.time_points == POINTS as u32 && p.of == 5),
            "{}: {units:?}",
            name(j)
        );
    }
    each_ran_a_part(&logs);
    let all = cli_ok(&["jobs", "list", "--parts", "--orchestrator", &o]);
    assert!(all.contains("series unit 5/5 scoring"), "{all}");
    // The NIfTI's series is what one process makes of the same time points and options.
    let one = one_process_series(&dir.join("heart.nii"), 4, 0.2);
    let mut client = CacheClient::connect(&c).await.unwrap();
    let listed = client.list().await.unwrap();
    assert_eq!(listed.len(), 3, "{listed:?}");
    let heart = listed.iter().find(|v| v.name == "heart").expect("heart");
    assert_eq!(
        heart.sha256,
        wavesplat_net::digest::hex(&wavesplat_net::digest::sha256(&one)),
        "not the one-process series"
    );
    for v in &listed {
        for t in [0u32, 3] {
            let request = RefineRequest::new(
                VolumeKey::Name(v.name.clone()),
                ViewSpec::single(View::new(0.4, 0.7, 32, 32)),
            )
            .at_time_point(t);
            let got = client.refine_collect(request, None).await.unwrap();
            assert!(got.done);
            let h = got.header.unwrap();
            let m = h.series.as_ref().expect("a series");
            assert_eq!(m.points.len(), POINTS, "{}", v.name);
            assert!(!got.packets.is_empty());
            assert!(
                (got.packets.len() as u32) < v.packet_count,
                "{} t {t}: every component's packets",
                v.name
            );
        }
    }
}

/// A time series' coordinator SIGKILLed while it holds one of the series' parts: the job's
/// lease lapses, the next worker takes it over with the parts already added, and the series
/// lands once, the bytes one process makes.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_series_job_survives_its_coordinators_death() {
    use wavesplat_compressor::phantom::beating;
    use wavesplat_fixtures::write_nifti_series;
    const POINTS: usize = 6;
    let cl = TestCluster::start(&ORCH_TIMING);
    let (o, c) = (cl.orch.url(), cl.cache.url());
    let dir = cl.root.join("shared");
    std::fs::create_dir_all(&dir).unwrap();
    let dims = [32, 28, 16];
    let samples: Vec<Vec<f32>> = (0..POINTS)
        .map(|t| beating(dims, t, POINTS).unwrap().channel(0).to_vec())
        .collect();
    let path = dir.join("beat.nii");
    write_nifti_series(&path, dims, &samples, Some(50.0), false);
    // It computes a part, then hangs before reporting it: SIGKILL it there.
    let doomed = Proc::worker_with(
        &o,
        &c,
        "doomed",
        &["--pause-before-part-report-ms", "60000"],
        None,
    );
    submit(&dir, &o, &["--time-group", "4", "--target-fraction", "0.1"]);
    let held = |j: &pb::Job| is_part(j) && j.worker == "doomed" && j.stage.contains("paused");
    let js = wait_for(&o, 60, "a part held by the doomed coordinator", |js| {
        js.iter().any(held)
    })
    .await;
    let parent = js.iter().find(|j| !is_part(j)).unwrap().id;
    assert_eq!(
        js.iter().find(|j| j.id == parent).unwrap().worker,
        "doomed",
        "it coordinates the series"
    );
    doomed.kill();
    let _next = cl.worker("next", 0, None);
    let js = wait_for(&o, 120, "the series done", |js| {
        js.iter()
            .any(|j| j.id == parent && state_name(j.state) == "done")
    })
    .await;
    let job = js.iter().find(|j| j.id == parent).unwrap();
    assert_eq!(job.attempts, 2, "taken over once: {job:?}");
    let one = one_process_series(&path, 4, 0.1);
    assert_eq!(job.output_bytes, one.len() as u64);
    assert_cache_holds_only(&c, &one).await;
}
