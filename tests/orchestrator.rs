//! End-to-end tests of the orchestrator: the real `wavesplat` binary as cache, orchestrator and
//! workers on loopback, sled in tempdirs, archives of small phantom volumes written as raw
//! (naming convention) and NIfTI files. Short leases (2 s) keep the suite fast; every wait is
//! bounded.

mod common;

use common::jobs::{finished as all_finished, list, name, wait_for};
use common::TestCluster;
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
/// raw file on shared storage brick by brick (an uploaded one is decoded whole and split), and
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
    // This worker compresses, then hangs before uploading: SIGKILL it there.
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
        js.len() == 2 && js.iter().all(|j| state_name(j.state) == "done")
    })
    .await;
    let big = js.iter().find(|j| name(j) == "big").unwrap();
    assert_eq!(big.attempts, 2, "reclaimed once");

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
