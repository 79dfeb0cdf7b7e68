//! The crate boundaries that carry the design, checked over `cargo tree`: the servers (cache,
//! orchestrator) and the two clients (cache, orchestrator) link the format and the protocol, never the renderer, the
//! encoder or their heavy dependencies (FFT, PNG, GPU, windowing), so a server can run on a
//! machine without a GPU stack and the client side can depend on the client without a cycle.
//! The encoder is linked by the worker (and the binary) only.

use std::collections::BTreeSet;
use std::process::Command;

/// The packages (names only) in the normal-dependency tree of `package`, features as that
/// package alone would build them.
fn dependencies(package: &str) -> BTreeSet<String> {
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let out = Command::new(cargo)
        .args([
            "tree",
            "--offline",
            "-e",
            "normal",
            "--prefix",
            "none",
            "-f",
            "{p}",
            "-p",
        ])
        .arg(package)
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .expect("running cargo tree");
    assert!(
        out.status.success(),
        "cargo tree -p {package} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout)
        .lines()
        .filter_map(|l| l.split_whitespace().next())
        .map(str::to_string)
        .collect()
}

fn assert_excludes(package: &str, forbidden: &[&str]) {
    let deps = dependencies(package);
    assert!(
        deps.contains(package),
        "{package} not in its own tree: {deps:?}"
    );
    let found: Vec<&&str> = forbidden.iter().filter(|f| deps.contains(**f)).collect();
    assert!(found.is_empty(), "{package} links {found:?}");
}

/// What no server and no client library may link.
const RENDERING_AND_ENCODING: &[&str] = &[
    "wavesplat-viewer",
    "wavesplat-compressor",
    "rustfft",
    "nalgebra",
    "png",
    "wgpu",
    "winit",
];

#[test]
fn the_cache_server_links_neither_renderer_nor_encoder() {
    assert_excludes(
        "wavesplat-cache",
        &[RENDERING_AND_ENCODING, &["wavesplat-client"]].concat(),
    );
}

#[test]
fn the_orchestrator_server_links_neither_renderer_nor_encoder() {
    assert_excludes(
        "wavesplat-orchestrator",
        &[
            RENDERING_AND_ENCODING,
            &["wavesplat-worker", "wavesplat-cache"],
        ]
        .concat(),
    );
}

#[test]
fn the_worker_links_the_encoder_but_no_renderer_or_server() {
    let deps = dependencies("wavesplat-worker");
    assert!(deps.contains("wavesplat-compressor"), "{deps:?}");
    assert!(deps.contains("wavesplat-orchestrator-client"), "{deps:?}");
    assert_excludes(
        "wavesplat-worker",
        &[
            "wavesplat-viewer",
            "wavesplat-cache",
            "wavesplat-orchestrator",
            "sled",
            "sqlx",
            "tonic-health",
            "png",
            "wgpu",
            "winit",
        ],
    );
}

#[test]
fn the_orchestrator_client_links_neither_renderer_nor_encoder_nor_server() {
    assert_excludes(
        "wavesplat-orchestrator-client",
        &[
            RENDERING_AND_ENCODING,
            &[
                "wavesplat-orchestrator",
                "wavesplat-cache",
                "wavesplat-client",
                "sled",
                "sqlx",
                "tonic-health",
            ],
        ]
        .concat(),
    );
}

#[test]
fn the_cache_client_links_neither_renderer_nor_encoder_nor_server() {
    assert_excludes(
        "wavesplat-client",
        &[RENDERING_AND_ENCODING, &["wavesplat-cache", "sled", "sqlx"]].concat(),
    );
}

#[test]
fn the_codec_links_no_service_renderer_or_wire_protocol() {
    // rustfft and nalgebra are the codec's own (the exact analysis transform), behind its
    // `transform` feature.
    assert_excludes(
        "wavesplat-codec",
        &[
            "wavesplat-viewer",
            "wavesplat-compressor",
            "png",
            "wgpu",
            "winit",
            "tokio",
            "tonic",
            "prost",
            "wavesplat-proto",
        ],
    );
}

#[test]
fn the_renderer_does_not_link_the_encoder_or_a_server() {
    // Nor, without its `window` feature, the windowing library: a headless user or another
    // front-end gets the window's state, input and script without winit.
    assert_excludes(
        "wavesplat-viewer",
        &[
            "wavesplat-compressor",
            "wavesplat-cache",
            "sled",
            "sqlx",
            "winit",
            "wavesplat-harness",
        ],
    );
}

/// The servers, the clients, the worker and the libraries they share: none may link the
/// harness or the test fixtures.
const SERVICE_CRATES: &[&str] = &[
    "wavesplat-cache",
    "wavesplat-orchestrator",
    "wavesplat-orchestrator-client",
    "wavesplat-worker",
    "wavesplat-client",
    "wavesplat-compressor",
    "wavesplat-net",
];

#[test]
fn only_the_binary_and_the_tests_link_the_harness() {
    for package in SERVICE_CRATES {
        assert_excludes(package, &["wavesplat-harness"]);
    }
    assert!(dependencies("wavesplat").contains("wavesplat-harness"));
}

#[test]
fn the_test_fixtures_are_linked_by_no_shipped_crate() {
    // The volume writers panic on I/O errors: tests and examples only (dev-dependencies).
    let shipped = ["wavesplat", "wavesplat-viewer", "wavesplat-harness"];
    for package in SERVICE_CRATES.iter().chain(&shipped) {
        assert_excludes(package, &["wavesplat-fixtures"]);
    }
}

#[test]
fn the_object_store_clients_bring_no_second_crypto_provider() {
    // tonic's TLS uses ring; a second provider (aws-lc-rs, the object-store client's default)
    // would make rustls refuse to pick one at run time.
    for package in ["wavesplat-cache", "wavesplat-viewer", "wavesplat"] {
        assert_excludes(package, &["aws-lc-rs", "aws-lc-sys"]);
    }
}
