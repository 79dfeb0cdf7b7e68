//! The README's PostgreSQL queue deployment ("The queue on PostgreSQL: stateless
//! orchestrators") across hosts: one network namespace per host (a database host, two
//! orchestrators, a cache, two workers, an operator's machine), TLS everywhere (the database
//! with `sslmode=verify-full`, the services with the test's CA), the README's tokens, the
//! database password from `PGPASSWORD`. An archive is submitted to both orchestrators; one is
//! SIGKILLed mid-archive and the other finishes; every good volume is delivered once and the
//! broken file fails with its reason. A plaintext connection to the database is refused.
//!
//! Needs root, iproute2 and PostgreSQL's server binaries, as CI has (set
//! `WAVESPLAT_SKIP_NETNS=1` to skip it knowingly on a machine without namespaces).

mod common;

use common::jobs::{deliveries, finished};
use common::netns::Net;
use common::pki::{pki, secret};
use common::text;
use std::path::Path;
use std::time::{Duration, Instant};
use wavesplat_client::{ConnectOptions, Credentials};
use wavesplat_compressor::phantom::Phantom;
use wavesplat_fixtures::write_nifti;
use wavesplat_harness::postgres::{PostgresServer, PostgresSetup, PASSWORD};
use wavesplat_orchestrator_client as client;
use wavesplat_orchestrator_client::convert::state_name;
use wavesplat_proto::pb;

const SUBNET: &str = "10.210.0";
const HOSTS: [&str; 7] = ["db", "orch1", "orch2", "cache", "worker1", "worker2", "ops"];

fn ip_of(host: &str) -> String {
    let i = HOSTS.iter().position(|h| *h == host).unwrap();
    format!("{SUBNET}.{}", 10 + i)
}

/// Jobs as the operator sees them, through both orchestrators.
fn jobs(net: &Net, ca: &Path, token: &str, urls: &str) -> Option<Vec<pb::Job>> {
    let options = ConnectOptions {
        ca: Some(ca.to_path_buf()),
        credentials: Credentials::token(token).unwrap(),
    };
    let urls = urls.to_string();
    net.on_host("ops", move || {
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .unwrap();
        rt.block_on(async move {
            let mut c = client::connect_with(&urls, &options).await.ok()?;
            client::list(&mut c).await.ok()
        })
    })
}

fn wait_for(
    net: &Net,
    ca: &Path,
    token: &str,
    urls: &str,
    what: &str,
    pred: impl Fn(&[pb::Job]) -> bool,
) -> Vec<pb::Job> {
    let end = Instant::now() + Duration::from_secs(120);
    loop {
        let js = jobs(net, ca, token, urls);
        if let Some(js) = &js {
            if pred(js) {
                return js.clone();
            }
        }
        assert!(
            Instant::now() < end,
            "timed out waiting for {what}: {js:#?}"
        );
        std::thread::sleep(Duration::from_millis(200));
    }
}

#[test]
fn stateless_orchestrators_over_postgres_run_across_hosts() {
    if std::env::var_os("WAVESPLAT_SKIP_NETNS").is_some() {
        eprintln!("skipped: WAVESPLAT_SKIP_NETNS is set");
        return;
    }
    let mut net = Net::create("wsq", SUBNET, &HOSTS);
    let root = tempfile::tempdir().unwrap();
    let dir = |host: &str| {
        let d = root.path().join(host);
        std::fs::create_dir_all(&d).unwrap();
        d
    };
    let servers = ["db", "orch1", "orch2", "cache"];
    let server_dirs: Vec<_> = servers.iter().map(|h| dir(h)).collect();
    let pairs: Vec<(&str, String, &Path)> = servers
        .iter()
        .zip(&server_dirs)
        .map(|(h, d)| (*h, ip_of(h), d.as_path()))
        .collect();
    let ca_pem = pki(&pairs);
    for h in HOSTS {
        std::fs::write(dir(h).join("ca.pem"), &ca_pem).unwrap();
    }

    // The database host: TLS only, password authentication.
    let db_dir = dir("db");
    let pg = PostgresServer::start_with(PostgresSetup {
        listen: Some(ip_of("db")),
        tls: Some((db_dir.join("db.crt"), db_dir.join("db.key"))),
        netns: Some(net.ns("db")),
    })
    .unwrap();
    pg.create_database("queue").unwrap();
    let queue_url = format!(
        "{}?sslmode=verify-full&sslrootcert=ca.pem",
        pg.url_at("db", "queue")
    );

    let (workers, ops, orch_read) = (secret("workers"), secret("ops"), secret("orchestrator"));
    let tokens = format!(
        "workers worker,ingest {workers}\nops admin {ops}\norchestrator read {orch_read}\n"
    );
    for h in ["cache", "orch1", "orch2"] {
        std::fs::write(dir(h).join("tokens"), &tokens).unwrap();
    }
    let cache_args = [
        "serve",
        "cache",
        "--db",
        "cache.db",
        "--addr",
        "0.0.0.0:50051",
        "--tls-cert",
        "cache.crt",
        "--tls-key",
        "cache.key",
        "--tokens",
        "tokens",
    ];
    let cache = net.serve("cache", &dir("cache"), "cache", &cache_args, None);
    net.keep(cache);

    // A plaintext connection to the database is refused, with a reason.
    let plain = net.run(
        "orch1",
        &dir("orch1"),
        &[
            "serve",
            "orchestrator",
            "--queue",
            &format!("{}?sslmode=disable", pg.url_at("db", "queue")),
            "--addr",
            "127.0.0.1:0",
        ],
        None,
    );
    assert!(!plain.status.success(), "{}", text(&plain));
    let said = String::from_utf8_lossy(&plain.stderr);
    assert!(
        said.contains("no encryption") || said.contains("pg_hba"),
        "{}",
        text(&plain)
    );
    assert!(!said.contains(PASSWORD), "the password leaked: {said}");

    let mut orchs = Vec::new();
    for h in ["orch1", "orch2"] {
        let (crt, key) = (format!("{h}.crt"), format!("{h}.key"));
        let args = [
            "serve",
            "orchestrator",
            "--queue",
            &queue_url,
            "--addr",
            "0.0.0.0:50052",
            "--tls-cert",
            &crt,
            "--tls-key",
            &key,
            "--tokens",
            "tokens",
            "--cache",
            "https://cache:50051",
            "--ca",
            "ca.pem",
            "--lease-secs",
            "10",
            "--heartbeat-ms",
            "300",
            "--poll-ms",
            "100",
        ];
        orchs.push(net.serve_with_env(
            h,
            &dir(h),
            "orchestrator",
            &args,
            Some(&orch_read),
            &[("PGPASSWORD", PASSWORD)],
        ));
    }
    let both = "https://orch1:50052,https://orch2:50052";

    // The archive on storage every worker sees at the same path.
    let archive = root.path().join("archive");
    std::fs::create_dir_all(&archive).unwrap();
    let good: Vec<String> = (0..8)
        .map(|i| {
            let dims = [20, 18, 14 + 2 * i];
            let p = [Phantom::SheppLogan, Phantom::Spheres][i % 2];
            write_nifti(
                &archive.join(format!("q{i}.nii")),
                dims,
                &p.generate(dims).to_interleaved(),
            );
            format!("q{i}")
        })
        .collect();
    std::fs::write(archive.join("broken.nii"), b"not a nifti file").unwrap();
    let submit = net.run(
        "ops",
        &dir("ops"),
        &[
            "archive",
            "submit",
            archive.to_str().unwrap(),
            "--orchestrator",
            both,
            "--ca",
            "ca.pem",
            "--detach",
            "--levels",
            "2",
        ],
        Some(&ops),
    );
    assert!(submit.status.success(), "{}", text(&submit));

    for w in ["worker1", "worker2"] {
        let child = net.spawn(
            w,
            &dir(w),
            "worker",
            &[
                "worker",
                "--orchestrator",
                both,
                "--cache",
                "https://cache:50051",
                "--ca",
                "ca.pem",
                "--threads",
                "1",
                "--id",
                w,
                "--pause-before-upload-ms",
                "400",
            ],
            Some(&workers),
        );
        net.keep(child);
    }
    let ca = dir("ops").join("ca.pem");
    // This process's threads on the ops host read the root's /etc/hosts: addresses, not names.
    let both_ip = format!(
        "https://{}:50052,https://{}:50052",
        ip_of("orch1"),
        ip_of("orch2")
    );
    let before = wait_for(&net, &ca, &ops, &both_ip, "two jobs done", |js| {
        js.iter().filter(|j| state_name(j.state) == "done").count() >= 2
    });
    assert!(!finished(&before), "the archive finished before the kill");
    let mut orch1 = orchs.remove(0);
    orch1.kill().unwrap();
    orch1.wait().unwrap();
    let js = wait_for(&net, &ca, &ops, &both_ip, "the archive finished", finished);
    assert_eq!(js.len(), good.len() + 1);
    for j in &js {
        let name = &j.spec.as_ref().unwrap().name;
        if name == "broken" {
            assert_eq!(state_name(j.state), "failed");
            assert!(j.error.contains("broken.nii"), "{}", j.error);
        } else {
            assert_eq!(state_name(j.state), "done", "{name}: {}", j.error);
        }
    }
    let mut log = String::new();
    let mut failed_over = 0;
    for w in ["worker1", "worker2"] {
        let own = std::fs::read_to_string(dir(w).join("worker.log")).unwrap();
        failed_over += usize::from(own.contains("failing over"));
        log.push_str(&own);
    }
    let deliveries = deliveries(&log, &good);
    for g in &good {
        assert_eq!(deliveries.get(g), Some(&1), "{g}: {deliveries:?}");
    }
    assert!(
        failed_over >= 1,
        "no worker moved to the second orchestrator"
    );
    let log = std::fs::read_to_string(dir("orch2").join("orchestrator.log")).unwrap();
    assert!(!log.contains(PASSWORD), "the password leaked into the log");
    net.keep(orchs.remove(0));
}
