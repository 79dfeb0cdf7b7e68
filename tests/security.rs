//! Services people can expose: TLS with certificates the test generates (rcgen), tokens with
//! roles on every RPC, the refusal to serve a reachable address unprotected, and deliveries
//! confirmed with the cache. In-process servers on loopback, sled in a tempdir.

use common::{phantom_file, phantom_options, TestCache};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use tonic::Code;
use wavesplat_cache::{Limits, Store};
use wavesplat_client::{CacheClient, ConnectOptions, Credentials, RefineRequest, VolumeKey};
use wavesplat_codec::view::{View, ViewSpec};
use wavesplat_compressor::encode::CompressOptions;
use wavesplat_compressor::phantom::Phantom;
use wavesplat_net::{Security, Tokens};
use wavesplat_orchestrator::{DeliveryCheck, ServiceOptions};
use wavesplat_orchestrator_client::model::{JobOptions, JobSpec, Source};
use wavesplat_orchestrator_client::{self as client, Client, HeldLease};
use wavesplat_proto::pb;

const READ: &str = "0123456789abcdef-read";
const WRITE: &str = "0123456789abcdef-write";
const WORKER: &str = "0123456789abcdef-worker";
const ADMIN: &str = "0123456789abcdef-admin";

fn tokens() -> Arc<Tokens> {
    Arc::new(
        Tokens::parse(&format!(
            "viewer read {READ}\nuploader write {WRITE}\nw1 worker,ingest {WORKER}\n\
             root admin {ADMIN}\n"
        ))
        .unwrap(),
    )
}

fn test_file(dims: [usize; 3]) -> Vec<u8> {
    let options = CompressOptions {
        levels: Some(2),
        ..phantom_options(0.05)
    };
    phantom_file(Phantom::SheppLogan, dims, &options)
}

/// A CA and a server certificate for 127.0.0.1 and localhost signed by it, as PEM files.
struct Pki {
    _dir: tempfile::TempDir,
    ca: PathBuf,
    cert: PathBuf,
    key: PathBuf,
}

fn pki() -> Pki {
    let dir = tempfile::tempdir().unwrap();
    let mut ca_params = rcgen::CertificateParams::new(Vec::<String>::new()).unwrap();
    ca_params.is_ca = rcgen::IsCa::Ca(rcgen::BasicConstraints::Unconstrained);
    ca_params
        .distinguished_name
        .push(rcgen::DnType::CommonName, "wavesplat test CA");
    let ca_key = rcgen::KeyPair::generate().unwrap();
    let ca = ca_params.self_signed(&ca_key).unwrap();
    let params =
        rcgen::CertificateParams::new(vec!["127.0.0.1".to_string(), "localhost".to_string()])
            .unwrap();
    let key = rcgen::KeyPair::generate().unwrap();
    let cert = params.signed_by(&key, &ca, &ca_key).unwrap();
    let write = |name: &str, text: String| {
        let p = dir.path().join(name);
        std::fs::write(&p, text).unwrap();
        p
    };
    Pki {
        ca: write("ca.pem", ca.pem()),
        cert: write("cert.pem", cert.pem()),
        key: write("key.pem", key.serialize_pem()),
        _dir: dir,
    }
}

fn options(ca: Option<&Path>, token: Option<&str>) -> ConnectOptions {
    ConnectOptions {
        ca: ca.map(Path::to_path_buf),
        credentials: token.map_or_else(Credentials::none, |t| Credentials::token(t).unwrap()),
    }
}

async fn client(url: &str, ca: Option<&Path>, token: Option<&str>) -> CacheClient {
    CacheClient::connect_with(url, &options(ca, token))
        .await
        .unwrap()
}

#[tokio::test]
async fn tls_round_trip_and_every_cache_rpc_checks_its_role() {
    let pki = pki();
    let security = Security {
        tls: Some(wavesplat_net::tls::server_tls(&pki.cert, &pki.key).unwrap()),
        tokens: Some(tokens()),
        insecure: false,
    };
    let cache = TestCache::secured(security);
    let url = format!("https://127.0.0.1:{}", cache.node.addr.port());
    let bytes = test_file([24, 24, 24]);
    let key = VolumeKey::Name("v".into());

    // Writing needs `write`: refused without a token, with a wrong one, and with `read`.
    for token in [None, Some("0123456789abcdef-wrong"), Some(READ)] {
        let mut c = client(&url, Some(&pki.ca), token).await;
        let want = if token == Some(READ) {
            Code::PermissionDenied
        } else {
            Code::Unauthenticated
        };
        assert_eq!(c.ingest("v", &bytes).await.unwrap_err().code(), Some(want));
        assert_eq!(c.delete(&key).await.unwrap_err().code(), Some(want));
        if token.is_none() {
            assert_eq!(
                c.list().await.unwrap_err().code(),
                Some(Code::Unauthenticated)
            );
        }
    }
    assert!(cache.node.store.list().unwrap().is_empty());
    assert_eq!(cache.node.store.data_bytes().unwrap(), 0);

    // `write` stores; it cannot read.
    let mut w = client(&url, Some(&pki.ca), Some(WRITE)).await;
    w.ingest("v", &bytes).await.unwrap();
    assert_eq!(
        w.list().await.unwrap_err().code(),
        Some(Code::PermissionDenied)
    );

    // `read` streams over TLS; the packets are the file's.
    let mut r = client(&url, Some(&pki.ca), Some(READ)).await;
    let view = ViewSpec::single(View::new(0.3, 0.2, 32, 32));
    let got = r
        .refine_collect(RefineRequest::new(key.clone(), view), None)
        .await
        .unwrap();
    assert!(got.done);
    let file = wavesplat_codec::format::parse_file(&bytes).unwrap();
    assert_eq!(got.packets.len(), file.packets.len());
    for p in &got.packets {
        assert_eq!(p.data, file.packets[p.id as usize]);
    }
    // Deleting with `read` changes nothing; `admin` may do anything.
    assert_eq!(
        r.delete(&key).await.unwrap_err().code(),
        Some(Code::PermissionDenied)
    );
    assert_eq!(cache.node.store.list().unwrap().len(), 1);
    let mut a = client(&url, Some(&pki.ca), Some(ADMIN)).await;
    a.delete(&key).await.unwrap();
    assert!(a.list().await.unwrap().is_empty());

    // Plaintext against the TLS server fails; so does TLS without the right CA.
    let plain = format!("http://127.0.0.1:{}", cache.node.addr.port());
    let mut p = client(&plain, None, Some(READ)).await;
    assert!(p.list().await.is_err());
    let other = pki_other();
    let e = CacheClient::connect_with(&url, &options(Some(&other.ca), Some(READ)))
        .await
        .unwrap_err();
    assert!(e.to_string().to_lowercase().contains("certificate"), "{e}");
    cache.stop().await;
}

fn pki_other() -> Pki {
    pki()
}

#[tokio::test]
async fn an_https_url_against_a_plaintext_server_fails_clearly() {
    let cache = TestCache::secured(Security::default());
    let pki = pki();
    let url = format!("https://127.0.0.1:{}", cache.node.addr.port());
    let e = CacheClient::connect_with(&url, &options(Some(&pki.ca), None))
        .await
        .unwrap_err();
    let msg = e.to_string();
    assert!(msg.contains(&url), "{msg}");
    assert!(
        msg.to_lowercase().contains("tls") || msg.to_lowercase().contains("handshake"),
        "the error should say the TLS handshake failed: {msg}"
    );
    // http:// stays plaintext and works.
    let mut c = client(
        &format!("http://127.0.0.1:{}", cache.node.addr.port()),
        None,
        None,
    )
    .await;
    assert!(c.list().await.unwrap().is_empty());
    cache.stop().await;
}

#[tokio::test]
async fn servers_refuse_a_reachable_address_without_tls_and_tokens() {
    let dir = tempfile::tempdir().unwrap();
    let store = Store::open(dir.path(), Limits::default()).unwrap();
    let listener = tokio::net::TcpListener::bind("0.0.0.0:0").await.unwrap();
    let only_tokens = wavesplat_cache::ServeOptions {
        security: Security {
            tokens: Some(tokens()),
            ..Default::default()
        },
        ..Default::default()
    };
    let e = wavesplat_cache::serve_with(listener, store, only_tokens, async {})
        .await
        .unwrap_err();
    assert!(e.to_string().contains("--insecure"), "{e}");
    let orch = wavesplat_orchestrator::Store::open(dir.path().join("orch")).unwrap();
    let listener = tokio::net::TcpListener::bind("0.0.0.0:0").await.unwrap();
    let e = wavesplat_orchestrator::serve_with(
        listener,
        orch,
        ServiceOptions::default(),
        Default::default(),
        async {},
    )
    .await
    .unwrap_err();
    assert!(e.to_string().contains("TLS and authentication"), "{e}");
    // --insecure says the network is trusted.
    let store = Store::open(dir.path().join("c2"), Limits::default()).unwrap();
    let listener = tokio::net::TcpListener::bind("0.0.0.0:0").await.unwrap();
    let insecure = wavesplat_cache::ServeOptions {
        security: Security {
            insecure: true,
            ..Default::default()
        },
        ..Default::default()
    };
    wavesplat_cache::serve_with(listener, store, insecure, async {})
        .await
        .unwrap();
}

async fn orch_client(url: &str, token: Option<&str>) -> Client {
    client::connect_with(url, &options(None, token))
        .await
        .unwrap()
}

fn job_ref(id: u64) -> pb::JobRef {
    pb::JobRef { id }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_orchestrator_rpc_checks_its_role_and_deliveries_are_confirmed() {
    // The cache the orchestrator checks deliveries against (plaintext on loopback, tokens on).
    let cache = TestCache::secured(Security {
        tokens: Some(tokens()),
        ..Default::default()
    });
    let cache_url = format!("http://{}", cache.node.addr);
    let dir = tempfile::tempdir().unwrap();
    let store = wavesplat_orchestrator::Store::open(dir.path()).unwrap();
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let url = format!("http://{}", listener.local_addr().unwrap());
    let opts = wavesplat_orchestrator::ServeOptions {
        security: Security {
            tokens: Some(tokens()),
            ..Default::default()
        },
        delivery_check: Some(DeliveryCheck::new(&cache_url, &options(None, Some(READ))).unwrap()),
    };
    tokio::spawn(wavesplat_orchestrator::serve_with(
        listener,
        store,
        ServiceOptions::default(),
        opts,
        std::future::pending(),
    ));
    let bytes = test_file([16, 16, 16]);
    let spec = JobSpec {
        name: "vol".into(),
        source: Source::Path("/nonexistent/vol_16x16x16_f32.raw".into()),
        sha256: [9; 32],
        raw: None,
        channel: None,
        options: JobOptions::default(),
        part: None,
    };

    // Submitting needs `admin`.
    for (token, want) in [
        (None, Code::Unauthenticated),
        (Some(READ), Code::PermissionDenied),
        (Some(WORKER), Code::PermissionDenied),
    ] {
        let mut c = orch_client(&url, token).await;
        let e = client::submit(&mut c, &spec, None).await.unwrap_err();
        assert_eq!(e.code(), want, "{token:?}");
        assert_eq!(c.cancel_job(job_ref(1)).await.unwrap_err().code(), want);
        assert_eq!(c.retry_job(job_ref(1)).await.unwrap_err().code(), want);
    }
    let mut admin = orch_client(&url, Some(ADMIN)).await;
    assert!(client::list(&mut admin).await.unwrap().is_empty());
    let job = client::submit(&mut admin, &spec, None)
        .await
        .unwrap()
        .job
        .unwrap();

    // Leasing, heartbeats and outcomes need `worker`.
    let lease = pb::LeaseRequest {
        worker: "fake".into(),
        parts_only: false,
    };
    for (token, want) in [
        (None, Code::Unauthenticated),
        (Some(READ), Code::PermissionDenied),
        (Some(WRITE), Code::PermissionDenied),
    ] {
        let mut c = orch_client(&url, token).await;
        assert_eq!(c.lease(lease.clone()).await.unwrap_err().code(), want);
        let hb = pb::HeartbeatRequest {
            job_id: job.id,
            attempt: 1,
            ..Default::default()
        };
        assert_eq!(c.heartbeat(hb).await.unwrap_err().code(), want);
        let fin = pb::FinishRequest {
            job_id: job.id,
            attempt: 1,
            ..Default::default()
        };
        assert_eq!(c.finish(fin).await.unwrap_err().code(), want);
        // So do the parts of bricked jobs.
        let parts = pb::SubmitPartsRequest {
            parent_id: job.id,
            parent_attempt: 1,
            parts: Vec::new(),
        };
        assert_eq!(c.submit_parts(parts).await.unwrap_err().code(), want);
        let head = pb::FinishPartRequest {
            msg: Some(pb::finish_part_request::Msg::Head(pb::PartResult {
                job_id: job.id,
                attempt: 1,
                ..Default::default()
            })),
        };
        let finished = c.finish_part(tokio_stream::iter(vec![head])).await;
        assert_eq!(finished.unwrap_err().code(), want);
        let fetch = pb::FetchResultRequest {
            parent_id: job.id,
            parent_attempt: 1,
            part_id: job.id,
        };
        let fetched = c.fetch_result(fetch).await.map(|_| ());
        assert_eq!(fetched.unwrap_err().code(), want);
        if token.is_some() {
            // Reading is allowed to `read` only (and admin).
            let l = c.list_jobs(pb::ListJobsRequest::default()).await;
            assert_eq!(l.is_ok(), token == Some(READ));
        }
    }
    let state =
        |jobs: Vec<pb::Job>| wavesplat_orchestrator_client::convert::state_name(jobs[0].state);
    assert_eq!(state(client::list(&mut admin).await.unwrap()), "queued");

    // A worker lease, then a made-up delivery: refused, the job stays running.
    let mut w = orch_client(&url, Some(WORKER)).await;
    let l = w.lease(lease).await.unwrap().into_inner().lease.unwrap();
    let held = HeldLease::of(&l);
    let finish = |d: pb::Delivered| {
        held.request(pb::FinishRequest {
            job_id: l.job_id,
            attempt: l.attempt,
            worker: "fake".into(),
            outcome: Some(pb::finish_request::Outcome::Delivered(d)),
        })
    };
    let fake = pb::Delivered {
        cache_volume_id: 42,
        output_bytes: 10,
        voxels: 10,
        existed: false,
        sha256: "00".repeat(32),
    };
    let e = w.finish(finish(fake.clone())).await.unwrap_err();
    assert_eq!(e.code(), Code::FailedPrecondition, "{e:?}");
    assert_eq!(state(client::list(&mut admin).await.unwrap()), "running");
    // Real content under the job's name, but the worker lies about its id: still refused.
    let mut cw = client(&cache_url, None, Some(WORKER)).await;
    let stored = cw.ingest("vol", &bytes).await.unwrap().volume;
    // A worker's token adds content and nothing else: it cannot delete.
    let e = cw.delete(&VolumeKey::Name("vol".into())).await.unwrap_err();
    assert_eq!(e.code(), Some(Code::PermissionDenied), "{e}");
    assert_eq!(cache.node.store.list().unwrap().len(), 1);
    let lie = pb::Delivered {
        cache_volume_id: stored.id + 1,
        sha256: stored.sha256.clone(),
        ..fake.clone()
    };
    assert_eq!(
        w.finish(finish(lie)).await.unwrap_err().code(),
        Code::FailedPrecondition
    );
    // The truth is accepted.
    let truth = pb::Delivered {
        cache_volume_id: stored.id,
        sha256: stored.sha256.clone(),
        output_bytes: bytes.len() as u64,
        ..fake
    };
    w.finish(finish(truth)).await.unwrap();
    assert_eq!(state(client::list(&mut admin).await.unwrap()), "done");
    cache.stop().await;
}

/// Job ids and attempts are public (any reader lists them), so a lease is held by its token
/// alone: another client with a `worker` token that names a running lease (job and attempt, read
/// with GetJob) without its token, or with a made-up one, is refused on every RPC that acts on
/// a lease (PermissionDenied) and changes nothing; the token is in no job listing; the worker
/// the lease was granted to goes on with it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_worker_token_does_not_hold_another_workers_lease() {
    use prost::Message;
    use wavesplat_orchestrator_client::convert;
    use wavesplat_orchestrator_client::model::{PartSpec, PartStep};
    let dir = tempfile::tempdir().unwrap();
    let store = wavesplat_orchestrator::Store::open(dir.path()).unwrap();
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let url = format!("http://{}", listener.local_addr().unwrap());
    let opts = wavesplat_orchestrator::ServeOptions {
        security: Security {
            tokens: Some(tokens()),
            ..Default::default()
        },
        delivery_check: None,
    };
    tokio::spawn(wavesplat_orchestrator::serve_with(
        listener,
        store,
        ServiceOptions::default(),
        opts,
        std::future::pending(),
    ));
    let source = b"the uploaded volume".to_vec();
    let uploaded = JobSpec {
        name: "uploaded".into(),
        source: Source::Upload {
            size: source.len() as u64,
        },
        sha256: wavesplat_net::digest::sha256(&source),
        raw: None,
        channel: None,
        options: JobOptions::default(),
        part: None,
    };
    let bricked = JobSpec {
        name: "bricked".into(),
        source: Source::Path("/shared/large_64x64x64_f32.raw".into()),
        sha256: [5; 32],
        raw: None,
        channel: None,
        options: JobOptions {
            brick: Some(32),
            ..JobOptions::default()
        },
        part: None,
    };
    let mut admin = orch_client(&url, Some(ADMIN)).await;
    client::submit(&mut admin, &uploaded, Some(&source))
        .await
        .unwrap();
    client::submit(&mut admin, &bricked, None).await.unwrap();

    // Worker A leases both jobs.
    let mut a = orch_client(&url, Some(WORKER)).await;
    let lease = || async {
        let req = pb::LeaseRequest {
            worker: "a".into(),
            parts_only: false,
        };
        let l = orch_client(&url, Some(WORKER))
            .await
            .lease(req)
            .await
            .unwrap()
            .into_inner()
            .lease
            .unwrap();
        assert_eq!(l.lease_token.len(), 16);
        l
    };
    let (l1, l2) = (lease().await, lease().await);
    let (h1, h2) = (HeldLease::of(&l1), HeldLease::of(&l2));
    assert_ne!(h1.token(), h2.token());

    // A reader sees the leases' jobs and attempts, never their tokens.
    let mut reader = orch_client(&url, Some(READ)).await;
    let got = reader
        .get_job(job_ref(l1.job_id))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(
        (got.attempts, convert::state_name(got.state)),
        (1, "running")
    );
    let listed = reader
        .list_jobs(pb::ListJobsRequest::default())
        .await
        .unwrap()
        .into_inner();
    for wire in [got.encode_to_vec(), listed.encode_to_vec()] {
        for t in [h1.token(), h2.token()] {
            assert!(
                !wire.windows(t.len()).any(|w| w == t),
                "a token in a job listing"
            );
        }
    }

    // Worker B names A's leases as read, with no token or a made-up one: refused.
    let mut b = orch_client(&url, Some(WORKER)).await;
    let before = client::list(&mut reader).await.unwrap();
    let forged = [
        HeldLease::new(l1.job_id, l1.attempt, Vec::new()),
        HeldLease::new(l1.job_id, l1.attempt, vec![0; 16]),
        HeldLease::new(l1.job_id, l1.attempt, h2.token().to_vec()),
    ];
    #[track_caller]
    fn denied(r: Result<(), tonic::Status>) {
        let e = r.unwrap_err();
        assert_eq!(e.code(), Code::PermissionDenied, "{e:?}");
    }
    for f in &forged {
        let hb = pb::HeartbeatRequest {
            job_id: l1.job_id,
            attempt: l1.attempt,
            worker: "b".into(),
            progress: 0.9,
            stage: "stolen".into(),
        };
        // Without metadata at all, and with the forged token.
        denied(b.heartbeat(hb.clone()).await.map(drop));
        denied(b.heartbeat(f.request(hb)).await.map(drop));
        for outcome in [
            pb::finish_request::Outcome::Failure(pb::Failure {
                kind: pb::FailureKind::InvalidInput as i32,
                message: "stolen".into(),
            }),
            pb::finish_request::Outcome::Delivered(pb::Delivered {
                cache_volume_id: 1,
                output_bytes: 1,
                voxels: 1,
                existed: false,
                sha256: "00".repeat(32),
            }),
        ] {
            let fin = pb::FinishRequest {
                job_id: l1.job_id,
                attempt: l1.attempt,
                worker: "b".into(),
                outcome: Some(outcome),
            };
            denied(b.finish(f.request(fin)).await.map(drop));
        }
        let fetch = pb::FetchSourceRequest {
            job_id: l1.job_id,
            attempt: l1.attempt,
        };
        denied(b.fetch_source(f.request(fetch)).await.map(drop));
        // The same forgeries on the bricked job's lease (another lease's token: the first's).
        let forged_token = if f.token() == h2.token() {
            h1.token()
        } else {
            f.token()
        };
        let on_parent = HeldLease::new(l2.job_id, l2.attempt, forged_token.to_vec());
        let parts = pb::SubmitPartsRequest {
            parent_id: l2.job_id,
            parent_attempt: l2.attempt,
            parts: Vec::new(),
        };
        denied(b.submit_parts(on_parent.request(parts)).await.map(drop));
        let fetch = pb::FetchResultRequest {
            parent_id: l2.job_id,
            parent_attempt: l2.attempt,
            part_id: l2.job_id,
        };
        denied(b.fetch_result(on_parent.request(fetch)).await.map(drop));
    }
    assert_eq!(
        client::list(&mut reader).await.unwrap(),
        before,
        "refused: nothing changed"
    );

    // A adds a part and leases it; B cannot report it or read the parent's results.
    let part = JobSpec {
        part: Some(PartSpec {
            parent: l2.job_id,
            index: 0,
            of: 8,
            step: PartStep::Score { energies: false },
            levels: 2,
            offset: Some(0.0),
            color: None,
            source_bytes: None,
            time_points: None,
            prefer_worker: None,
        }),
        ..bricked.clone()
    };
    let add = pb::SubmitPartsRequest {
        parent_id: l2.job_id,
        parent_attempt: l2.attempt,
        parts: vec![convert::spec_to_pb(&part)],
    };
    let states = a
        .submit_parts(h2.request(add))
        .await
        .unwrap()
        .into_inner()
        .parts;
    let x = a
        .lease(pb::LeaseRequest {
            worker: "a".into(),
            parts_only: true,
        })
        .await
        .unwrap()
        .into_inner()
        .lease
        .unwrap();
    assert_eq!(x.job_id, states[0].id);
    let hx = HeldLease::of(&x);
    let result = b"a brick's summary".to_vec();
    let report = |held: &HeldLease| {
        let head = pb::PartResult {
            job_id: x.job_id,
            attempt: x.attempt,
            worker: "b".into(),
            size: result.len() as u64,
            sha256: wavesplat_net::digest::sha256(&result).to_vec(),
            voxels: 1,
        };
        held.request(tokio_stream::iter(vec![
            pb::FinishPartRequest {
                msg: Some(pb::finish_part_request::Msg::Head(head)),
            },
            pb::FinishPartRequest {
                msg: Some(pb::finish_part_request::Msg::Chunk(result.clone())),
            },
        ]))
    };
    for forged in [
        HeldLease::new(x.job_id, x.attempt, Vec::new()),
        HeldLease::new(x.job_id, x.attempt, h2.token().to_vec()),
    ] {
        denied(b.finish_part(report(&forged)).await.map(drop));
    }
    let part_now = reader
        .get_job(job_ref(x.job_id))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(convert::state_name(part_now.state), "running");
    let done = a.finish_part(report(&hx)).await.unwrap().into_inner();
    assert_eq!(convert::state_name(done.state), "done");
    let fetch = pb::FetchResultRequest {
        parent_id: l2.job_id,
        parent_attempt: l2.attempt,
        part_id: x.job_id,
    };
    denied(b.fetch_result(fetch).await.map(drop));
    let mut got = Vec::new();
    let mut s = a
        .fetch_result(h2.request(fetch))
        .await
        .unwrap()
        .into_inner();
    while let Some(c) = s.message().await.unwrap() {
        got.extend_from_slice(&c.data);
    }
    assert_eq!(got, result);

    // A goes on with its own leases.
    let hb = pb::HeartbeatRequest {
        job_id: l1.job_id,
        attempt: l1.attempt,
        worker: "a".into(),
        progress: 0.5,
        stage: "working".into(),
    };
    assert!(
        a.heartbeat(h1.request(hb))
            .await
            .unwrap()
            .into_inner()
            .keep_going
    );
    let mut src = a
        .fetch_source(h1.request(pb::FetchSourceRequest {
            job_id: l1.job_id,
            attempt: l1.attempt,
        }))
        .await
        .unwrap()
        .into_inner();
    let mut bytes = Vec::new();
    while let Some(c) = src.message().await.unwrap() {
        bytes.extend_from_slice(&c.data);
    }
    assert_eq!(bytes, source);
    let fin = pb::FinishRequest {
        job_id: l1.job_id,
        attempt: l1.attempt,
        worker: "a".into(),
        outcome: Some(pb::finish_request::Outcome::Failure(pb::Failure {
            kind: pb::FailureKind::InvalidInput as i32,
            message: "not a volume".into(),
        })),
    };
    let ended = a.finish(h1.request(fin)).await.unwrap().into_inner();
    assert_eq!(convert::state_name(ended.state), "failed");
}

mod common;

/// Starts `wavesplat serve cache` on loopback with TLS from `pki` and the tokens of `tokens`;
/// returns the child and the server's https:// URL.
fn spawn_tls_cache(pki: &Pki, tokens: &Path, db: &Path) -> (std::process::Child, String) {
    let (child, addr) = common::spawn_server(&[
        "serve",
        "cache",
        "--addr",
        "127.0.0.1:0",
        "--db",
        db.to_str().unwrap(),
        "--tls-cert",
        pki.cert.to_str().unwrap(),
        "--tls-key",
        pki.key.to_str().unwrap(),
        "--tokens",
        tokens.to_str().unwrap(),
    ]);
    let port = addr.rsplit(':').next().unwrap();
    (child, format!("https://127.0.0.1:{port}"))
}

#[test]
fn the_binary_serves_tls_with_tokens_and_its_clients_take_the_token_from_the_environment() {
    let pki = pki();
    let dir = tempfile::tempdir().unwrap();
    let tokens = dir.path().join("tokens");
    std::fs::write(
        &tokens,
        format!("viewer read {READ}\nuploader write {WRITE}\n"),
    )
    .unwrap();
    let wsp = dir.path().join("v.wsp");
    std::fs::write(&wsp, test_file([16, 16, 16])).unwrap();
    let db = dir.path().join("db");
    let (mut child, url) = spawn_tls_cache(&pki, &tokens, &db);
    let run = |args: &[&str], token: &str| {
        std::process::Command::new(env!("CARGO_BIN_EXE_wavesplat"))
            .args(args)
            .args(["--cache", &url, "--ca", pki.ca.to_str().unwrap()])
            .env("WAVESPLAT_TOKEN", token)
            .output()
            .unwrap()
    };
    let wsp_arg = wsp.to_str().unwrap();
    let denied = run(&["cache", "ingest", wsp_arg], READ);
    assert!(!denied.status.success());
    assert!(String::from_utf8_lossy(&denied.stderr).contains("PermissionDenied"));
    assert!(run(&["cache", "ingest", wsp_arg], WRITE).status.success());
    let list = run(&["cache", "list"], READ);
    assert!(list.status.success());
    assert!(String::from_utf8_lossy(&list.stdout).starts_with("v\t"));
    let _ = child.kill();
    let _ = child.wait();
}

fn wavesplat(args: &[&str], token: Option<&str>) -> std::process::Output {
    let mut c = std::process::Command::new(env!("CARGO_BIN_EXE_wavesplat"));
    c.args(args)
        .env_remove("WAVESPLAT_TOKEN")
        .env_remove("WAVESPLAT_CA");
    if let Some(t) = token {
        c.env("WAVESPLAT_TOKEN", t);
    }
    c.output().unwrap()
}

fn stderr(o: &std::process::Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// The orchestrator reads its arguments (and makes its delivery check) before its runtime
/// starts; it used to exit 101 ("there is no reactor running") and so never checked anything.
#[test]
fn the_orchestrator_binary_with_a_cache_url_starts_and_refuses_unconfirmed_deliveries() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("orch");
    let (mut child, addr) = common::spawn_server(&[
        "serve",
        "orchestrator",
        "--db",
        db.to_str().unwrap(),
        "--addr",
        "127.0.0.1:0",
        "--cache",
        "http://127.0.0.1:1",
    ]);
    let url = format!("http://{addr}");
    let rt = tokio::runtime::Runtime::new().unwrap();
    rt.block_on(async {
        let mut c = orch_client(&url, None).await;
        let spec = JobSpec {
            name: "vol".into(),
            source: Source::Path("/nonexistent/vol_16x16x16_f32.raw".into()),
            sha256: [9; 32],
            raw: None,
            channel: None,
            options: JobOptions::default(),
            part: None,
        };
        client::submit(&mut c, &spec, None).await.unwrap();
        let l = c
            .lease(pb::LeaseRequest {
                worker: "w".into(),
                parts_only: false,
            })
            .await
            .unwrap()
            .into_inner()
            .lease
            .unwrap();
        let made_up = pb::FinishRequest {
            job_id: l.job_id,
            attempt: l.attempt,
            worker: "w".into(),
            outcome: Some(pb::finish_request::Outcome::Delivered(pb::Delivered {
                cache_volume_id: 424242,
                output_bytes: 10,
                voxels: 10,
                existed: false,
                sha256: "00".repeat(32),
            })),
        };
        // The cache cannot confirm it (it is unreachable): the job is not done.
        let e = c
            .finish(HeldLease::of(&l).request(made_up))
            .await
            .unwrap_err();
        assert_eq!(e.code(), Code::Unavailable, "{e:?}");
        let jobs = client::list(&mut c).await.unwrap();
        assert_eq!(
            wavesplat_orchestrator_client::convert::state_name(jobs[0].state),
            "running"
        );
    });
    let _ = child.kill();
    let _ = child.wait();
}

fn token_tokens_file(dir: &Path) -> PathBuf {
    let tokens = dir.join("tokens");
    std::fs::write(
        &tokens,
        format!("viewer read {READ}\nuploader write {WRITE}\nw1 worker,ingest {WORKER}\n"),
    )
    .unwrap();
    tokens
}

/// `render --cache` and `view --cache` present a token like every other client command
/// (`WAVESPLAT_TOKEN` or `--token-file`) and take `--ca` for https:// URLs.
#[test]
fn render_from_a_cache_with_tokens_takes_the_token_and_the_ca() {
    let pki = pki();
    let dir = tempfile::tempdir().unwrap();
    let tokens = token_tokens_file(dir.path());
    let wsp = dir.path().join("v.wsp");
    std::fs::write(&wsp, test_file([16, 16, 16])).unwrap();
    let db = dir.path().join("db");
    let (mut child, url) = spawn_tls_cache(&pki, &tokens, &db);
    let ca = pki.ca.to_str().unwrap();
    let ingest = wavesplat(
        &[
            "cache",
            "ingest",
            wsp.to_str().unwrap(),
            "--cache",
            &url,
            "--ca",
            ca,
        ],
        Some(WORKER),
    );
    assert!(ingest.status.success(), "{}", stderr(&ingest));
    let out = dir.path().join("out.png");
    let render = |token: Option<&str>, extra: &[&str]| {
        let mut args = vec![
            "render",
            "--cache",
            &url,
            "--volume",
            "v",
            "--ca",
            ca,
            "--size",
            "32x32",
            "-o",
            out.to_str().unwrap(),
        ];
        args.extend_from_slice(extra);
        wavesplat(&args, token)
    };
    let none = render(None, &[]);
    assert!(!none.status.success());
    assert!(
        stderr(&none).contains("Unauthenticated"),
        "{}",
        stderr(&none)
    );
    let ok = render(Some(READ), &[]);
    assert!(ok.status.success(), "{}", stderr(&ok));
    assert!(out.exists());
    let token_file = dir.path().join("viewer.token");
    std::fs::write(&token_file, format!("{READ}\n")).unwrap();
    let from_file = render(None, &["--token-file", token_file.to_str().unwrap()]);
    assert!(from_file.status.success(), "{}", stderr(&from_file));
    // `view` takes the same flags (parsing only: no display here).
    let help = wavesplat(&["view", "--help"], None);
    let help = String::from_utf8_lossy(&help.stdout);
    assert!(
        help.contains("--token-file") && help.contains("--ca"),
        "{help}"
    );
    // A worker's token (`ingest`) cannot delete through the CLI either.
    let rm = wavesplat(
        &["cache", "rm", "v", "--cache", &url, "--ca", ca],
        Some(WORKER),
    );
    assert!(!rm.status.success());
    assert!(stderr(&rm).contains("PermissionDenied"), "{}", stderr(&rm));
    let _ = child.kill();
    let _ = child.wait();
}

/// A file whose header declares coefficients its packets do not hold renders or decompresses
/// to nothing: refused, saying so.
#[test]
fn render_and_decompress_refuse_a_file_without_the_packets_its_header_declares() {
    let bytes = test_file([16, 16, 16]);
    let file = wavesplat_codec::format::parse_file(&bytes).unwrap();
    let empty = wavesplat_codec::format::write_file(&file.header, &[]);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("empty.wsp");
    std::fs::write(&path, &empty).unwrap();
    let p = path.to_str().unwrap();
    let png = dir.path().join("x.png");
    for args in [
        vec!["render", p, "-o", png.to_str().unwrap()],
        vec![
            "decompress",
            p,
            "-o",
            dir.path().join("x.f32").to_str().unwrap(),
        ],
    ] {
        let o = wavesplat(&args, None);
        assert!(!o.status.success(), "{args:?}");
        assert!(stderr(&o).contains("declares"), "{args:?}: {}", stderr(&o));
    }
    assert!(!png.exists());
}

/// What an operator is told at start: a warning, once, for each unprotected setting.
#[test]
fn servers_warn_once_at_start_when_unprotected() {
    let dir = tempfile::tempdir().unwrap();
    let tokens = token_tokens_file(dir.path());
    let db = dir.path().join("a");
    let (child, _) = common::spawn_server_with_stderr(&[
        "serve",
        "cache",
        "--addr",
        "127.0.0.1:0",
        "--db",
        db.to_str().unwrap(),
    ]);
    let err = common::stop_and_read_stderr(child);
    assert_eq!(err.matches("warning:").count(), 1, "{err}");
    assert!(err.contains("without tokens"), "{err}");
    let db = dir.path().join("b");
    let (child, _) = common::spawn_server_with_stderr(&[
        "serve",
        "orchestrator",
        "--addr",
        "127.0.0.1:0",
        "--db",
        db.to_str().unwrap(),
        "--tokens",
        tokens.to_str().unwrap(),
    ]);
    let err = common::stop_and_read_stderr(child);
    assert_eq!(err.matches("warning:").count(), 1, "{err}");
    assert!(err.contains("plaintext"), "{err}");
}

/// A refused exposure is refused before anything is bound or announced.
#[test]
fn an_exposed_address_is_refused_before_listening() {
    let dir = tempfile::tempdir().unwrap();
    for service in ["cache", "orchestrator"] {
        let db = dir.path().join(service);
        let o = wavesplat(
            &[
                "serve",
                service,
                "--addr",
                "0.0.0.0:0",
                "--db",
                db.to_str().unwrap(),
            ],
            None,
        );
        assert!(!o.status.success());
        let out = String::from_utf8_lossy(&o.stdout);
        assert!(!out.contains("listening on"), "{service}: {out}");
        assert!(stderr(&o).contains("refusing"), "{}", stderr(&o));
    }
}

/// A plaintext client against a TLS server is told what to do.
#[test]
fn a_plaintext_client_against_a_tls_server_is_told_to_use_https() {
    let pki = pki();
    let dir = tempfile::tempdir().unwrap();
    let tokens = token_tokens_file(dir.path());
    let db = dir.path().join("db");
    let (mut child, url) = spawn_tls_cache(&pki, &tokens, &db);
    let plain = url.replace("https://", "http://");
    let o = wavesplat(&["cache", "list", "--cache", &plain], Some(READ));
    assert!(!o.status.success());
    assert!(
        stderr(&o).contains("speaks TLS: use https:// and --ca"),
        "{}",
        stderr(&o)
    );
    let _ = child.kill();
    let _ = child.wait();
}

/// Values far out of range are echoed readably, not as hundreds of digits.
#[test]
fn huge_view_values_are_echoed_readably() {
    let dir = tempfile::tempdir().unwrap();
    let wsp = dir.path().join("v.wsp");
    std::fs::write(&wsp, test_file([16, 16, 16])).unwrap();
    let o = wavesplat(
        &[
            "render",
            wsp.to_str().unwrap(),
            "--alpha",
            "1e300",
            "-o",
            dir.path().join("x.png").to_str().unwrap(),
        ],
        None,
    );
    assert!(!o.status.success());
    let e = stderr(&o);
    assert!(e.contains("1e300"), "{e}");
    assert!(!e.contains("0000000000"), "{e}");
}
