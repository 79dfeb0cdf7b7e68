//! Browsing published volumes by range requests from a plain web server (nginx, started here on
//! loopback; no wavesplat server): `wavesplat publish` writes the indexed layout, `render
//! http://…` draws the same image as the local file (identical on the order-independent GPU
//! backend, within f32 summation order on the CPU one) after one request before the first packet,
//! a zoomed corner fetches a fraction of the bytes, a plain `.wsp` URL works (fetched whole),
//! and a file cut short or altered on the server is refused with a message that says so; over
//! TLS, the CA given with `--ca` (or `WAVESPLAT_CA`) is trusted and a certificate from another
//! is refused at once, saying to pass `--ca`.
//!
//! From the other side of the wire, a web server of the test's own (std::net, counting what it
//! serves): a whole view fetches no byte twice (the head's first request ends inside a packet),
//! a missing file is reported by its status and URL without the server's HTML page, `https://`
//! to a plaintext server fails on the first connection saying the server does not speak TLS,
//! and `cache list` against a web server says it is not a wavesplat cache.
//!
//! The nginx parts need `nginx` on the PATH (Debian's package). Without it they say so and pass
//! unless WAVESPLAT_REQUIRE_OBJECT_STORE=1 (set by `.ci/run`, which installs it).

mod common;

use common::http::TinyServer;
use common::{read_f32, relative_difference, render_in as render, text};
use std::path::Path;
use std::process::{Child, Command, Output, Stdio};
use std::sync::OnceLock;
use std::time::{Duration, Instant};
use wavesplat_codec::format::index::{
    indexed_layout, read_indexed_head, wsp_of_indexed, HeadRead, HEAD_READ_BYTES,
};
use wavesplat_compressor::phantom::Phantom;

const BIN: &str = env!("CARGO_BIN_EXE_wavesplat");

/// The test volume (the 128×112×96 Shepp–Logan phantom at a tenth of its coefficients, tiles
/// of 16: 1 309 packets, ~280 KB) as a `.wsp` and in the indexed layout, made once.
fn volume() -> &'static (Vec<u8>, Vec<u8>) {
    static VOLUME: OnceLock<(Vec<u8>, Vec<u8>)> = OnceLock::new();
    VOLUME.get_or_init(|| {
        let wsp = common::phantom_file(
            Phantom::SheppLogan,
            [128, 112, 96],
            &common::phantom_options(0.1),
        );
        let wspx = indexed_layout(&wsp).unwrap();
        (wsp, wspx)
    })
}

/// Whether nginx is here; without it a test says so and passes, unless CI requires it.
fn have_nginx() -> bool {
    if Command::new("nginx").arg("-v").output().is_ok() {
        return true;
    }
    assert!(
        std::env::var_os("WAVESPLAT_REQUIRE_OBJECT_STORE").is_none(),
        "nginx is not on the PATH (Debian: apt-get install nginx)"
    );
    eprintln!("skipped: nginx is not on the PATH (Debian: apt-get install nginx)");
    false
}

/// nginx serving `root` on a free loopback port; killed on drop.
struct WebServer {
    child: Child,
    url: String,
}

impl Drop for WebServer {
    /// Stops nginx by SIGTERM, so that its master stops its worker (SIGKILL would leave the
    /// worker running, orphaned); SIGKILL only when it has not stopped within seconds.
    fn drop(&mut self) {
        let _ = Command::new("kill")
            .args(["-TERM", &self.child.id().to_string()])
            .status();
        let asked = Instant::now();
        while asked.elapsed() < Duration::from_secs(5) {
            if let Ok(Some(_)) = self.child.try_wait() {
                return;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// nginx serving `root` on a free loopback port; with `tls` (certificate and key, PEM) over
/// TLS. nginx cannot listen on port 0 and say which port it got, so the test binds the port
/// and hands nginx the listening socket (as its stdin, named in the `NGINX` variable: nginx's
/// own inheritance of sockets across binary upgrades): the port is never released, so no other
/// process can take it between the test choosing it and nginx serving it.
fn start_nginx(dir: &Path, root: &Path, tls: Option<(&Path, &Path)>) -> WebServer {
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let port = listener.local_addr().unwrap().port();
    let conf = dir.join("nginx.conf");
    std::fs::create_dir_all(dir.join("logs")).unwrap();
    std::fs::write(
        &conf,
        format!(
            "daemon off;\nworker_processes 1;\npid {d}/nginx.pid;\nerror_log {d}/logs/error.log;\n\
             events {{ worker_connections 64; }}\n\
             http {{ access_log {d}/logs/access.log; \
             client_body_temp_path {d}/body; proxy_temp_path {d}/proxy; \
             fastcgi_temp_path {d}/fastcgi; uwsgi_temp_path {d}/uwsgi; scgi_temp_path {d}/scgi; \
             server {{ listen 127.0.0.1:{port}{ssl}; root {r}; {certs} }} }}\n",
            d = dir.display(),
            r = root.display(),
            ssl = if tls.is_some() { " ssl" } else { "" },
            certs = match tls {
                Some((cert, key)) => format!(
                    "ssl_certificate {}; ssl_certificate_key {};",
                    cert.display(),
                    key.display()
                ),
                None => String::new(),
            }
        ),
    )
    .unwrap();
    let child = Command::new("nginx")
        .arg("-c")
        .arg(&conf)
        .arg("-p")
        .arg(dir)
        .env("NGINX", "0;")
        .stdin(Stdio::from(std::os::fd::OwnedFd::from(listener)))
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let started = Instant::now();
    while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
        assert!(
            started.elapsed() < Duration::from_secs(20),
            "nginx did not start: {}",
            std::fs::read_to_string(dir.join("logs/error.log")).unwrap_or_default()
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    WebServer {
        child,
        url: format!(
            "{}://127.0.0.1:{port}",
            if tls.is_some() { "https" } else { "http" }
        ),
    }
}

/// "range requests: R (F before the first packet), B of T bytes fetched (P %)" as (R, F, B, T).
fn range_line(out: &Output) -> (u64, u64, u64, u64) {
    let stdout = String::from_utf8_lossy(&out.stdout);
    let line = stdout
        .lines()
        .find(|l| l.starts_with("range requests: "))
        .unwrap_or_else(|| panic!("{}", text(out)));
    let nums: Vec<u64> = line
        .split(|c: char| !c.is_ascii_digit())
        .filter_map(|s| s.parse().ok())
        .collect();
    (nums[0], nums[1], nums[2], nums[3])
}

#[test]
fn published_volumes_browse_by_range_requests_from_a_web_server() {
    if !have_nginx() {
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let www = tmp.path().join("www");
    std::fs::create_dir_all(&www).unwrap();
    let wsp = &volume().0;
    std::fs::write(www.join("vol.wsp"), wsp).unwrap();
    let publish = Command::new(BIN)
        .args(["publish", "vol.wsp", "-o", "vol.wspx"])
        .current_dir(&www)
        .output()
        .unwrap();
    assert!(publish.status.success(), "{}", text(&publish));
    let wspx = std::fs::read(www.join("vol.wspx")).unwrap();
    assert_eq!(
        &wspx[wspx.len() - wsp.len()..],
        &wsp[..],
        "the .wsp follows unchanged"
    );
    // Cut short, and one byte of the last packet changed.
    std::fs::write(www.join("cut.wspx"), &wspx[..wspx.len() - 100]).unwrap();
    let mut altered = wspx.clone();
    let at = altered.len() - 10;
    altered[at] ^= 0x5a;
    std::fs::write(www.join("altered.wspx"), &altered).unwrap();
    let server = start_nginx(&tmp.path().join("nginx"), &www, None);
    let dir = tmp.path();

    let size = ["--size", "96x96"];
    let local = render(
        dir,
        &[
            &["www/vol.wsp", "-o", "local.png", "--raw", "local.f32"][..],
            &size,
        ]
        .concat(),
    );
    assert!(local.status.success(), "{}", text(&local));
    let local_image = read_f32(&dir.join("local.f32"));

    // The whole view: the file's image, one request before the first packet, every byte once.
    let url = format!("{}/vol.wspx", server.url);
    let remote = render(
        dir,
        &[
            &[url.as_str(), "-o", "remote.png", "--raw", "remote.f32"][..],
            &size,
        ]
        .concat(),
    );
    assert!(remote.status.success(), "{}", text(&remote));
    let (requests, before_first, fetched, object) = range_line(&remote);
    assert_eq!(object, wspx.len() as u64);
    assert_eq!(
        before_first, 1,
        "the head, the index and the first packets in one request"
    );
    assert!(requests >= 2);
    assert!(
        fetched <= object,
        "{fetched} bytes fetched for an object of {object}: some twice"
    );
    // The CPU backend adds in f32 in arrival order, so a different order differs by rounding
    // (1e-6 of the peak measured); a missing or doubled packet differs by far more.
    let d = relative_difference(&local_image, &read_f32(&dir.join("remote.f32")));
    assert!(
        d <= 1e-5,
        "the browsed image differs from the file's by {d} of the peak"
    );

    // On the GPU backend, whose fixed-point sums do not depend on the order of the splats,
    // the browsed image is the file's (≤ 1e-6 of the peak; measured: identical). Without a
    // graphics driver this part is skipped, unless WAVESPLAT_REQUIRE_GPU=1 (as in CI).
    let gpu_local = render(
        dir,
        &[
            &["www/vol.wsp", "--gpu", "-o", "gl.png", "--raw", "gl.f32"][..],
            &size,
        ]
        .concat(),
    );
    if gpu_local.status.success() {
        let gpu_remote = render(
            dir,
            &[
                &[url.as_str(), "--gpu", "-o", "gr.png", "--raw", "gr.f32"][..],
                &size,
            ]
            .concat(),
        );
        assert!(gpu_remote.status.success(), "{}", text(&gpu_remote));
        let d = relative_difference(
            &read_f32(&dir.join("gl.f32")),
            &read_f32(&dir.join("gr.f32")),
        );
        assert!(
            d <= 1e-6,
            "on the GPU the browsed image differs by {d} of the peak"
        );
    } else {
        assert!(
            std::env::var_os("WAVESPLAT_REQUIRE_GPU").is_none(),
            "no GPU backend: {}",
            text(&gpu_local)
        );
        eprintln!("skipped the GPU comparison: {}", text(&gpu_local));
    }

    // A zoomed corner fetches a fraction of the bytes.
    let corner = render(
        dir,
        &[
            &[
                url.as_str(),
                "--zoom",
                "8",
                "--pan",
                "44,40",
                "-o",
                "corner.png",
            ][..],
            &size,
        ]
        .concat(),
    );
    assert!(corner.status.success(), "{}", text(&corner));
    let (_, _, corner_bytes, _) = range_line(&corner);
    assert!(
        corner_bytes < object * 3 / 4,
        "a zoomed corner fetched {corner_bytes} of {object} bytes"
    );
    eprintln!(
        "zoomed corner: {corner_bytes} of {object} bytes ({:.0} %)",
        100.0 * corner_bytes as f64 / object as f64
    );

    // A plain .wsp URL: fetched whole, in file order, the same image.
    let plain_url = format!("{}/vol.wsp", server.url);
    let plain = render(
        dir,
        &[
            &[plain_url.as_str(), "-o", "plain.png", "--raw", "plain.f32"][..],
            &size,
        ]
        .concat(),
    );
    assert!(plain.status.success(), "{}", text(&plain));
    let d = relative_difference(&local_image, &read_f32(&dir.join("plain.f32")));
    assert!(
        d <= 1e-5,
        "the plain file's image differs by {d} of the peak"
    );

    // Cut short or altered on the server: refused, saying why, and no image written.
    let cut = render(
        dir,
        &[
            &[format!("{}/cut.wspx", server.url).as_str(), "-o", "cut.png"][..],
            &size,
        ]
        .concat(),
    );
    assert!(!cut.status.success(), "{}", text(&cut));
    let err = String::from_utf8_lossy(&cut.stderr);
    assert!(err.contains("truncated"), "{err}");
    assert!(!dir.join("cut.png").exists());
    let bad = render(
        dir,
        &[
            &[
                format!("{}/altered.wspx", server.url).as_str(),
                "-o",
                "altered.png",
            ][..],
            &size,
        ]
        .concat(),
    );
    assert!(!bad.status.success(), "{}", text(&bad));
    let err = String::from_utf8_lossy(&bad.stderr);
    assert!(
        err.contains("packet") && err.contains("altered.wspx"),
        "{err}"
    );
    assert!(!dir.join("altered.png").exists());

    // A missing file names the URL.
    let missing = render(
        dir,
        &[
            &[
                format!("{}/nothing.wspx", server.url).as_str(),
                "-o",
                "m.png",
            ][..],
            &size,
        ]
        .concat(),
    );
    assert!(!missing.status.success());
    let err = String::from_utf8_lossy(&missing.stderr);
    assert!(err.contains("nothing.wspx"), "{err}");
}

/// The render's stderr, for messages.
fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// The default (whole) view fetches every byte at most once, counted where they are sent: the
/// head's first request (64 KiB) ends inside a packet, whose range must begin where that
/// request ended rather than be fetched again from its start. What the render reports as
/// fetched is what the server sent.
/// A whole indexed object held in memory (a local `.wspx`) gives back the `.wsp` it was made
/// of; cut or extended, it is refused.
#[test]
fn the_wsp_inside_a_whole_indexed_object_is_given_back() {
    use wavesplat_codec::format::FormatError;
    let (wsp, object) = volume();
    assert_eq!(wsp_of_indexed(object).unwrap(), &wsp[..]);
    let whole = object.len() as u64;
    assert!(matches!(
        wsp_of_indexed(&object[..object.len() - 7]),
        Err(FormatError::Truncated { needed, available, .. }) if needed == whole && available == whole - 7
    ));
    let mut longer = object.clone();
    longer.push(0);
    assert!(matches!(
        wsp_of_indexed(&longer),
        Err(FormatError::Invalid { .. })
    ));
    assert!(
        wsp_of_indexed(wsp).is_err(),
        "a plain .wsp is no indexed object"
    );
}

#[test]
fn a_whole_view_fetches_no_byte_twice() {
    let wspx = &volume().1;
    let HeadRead::Indexed(head) = read_indexed_head(wspx).unwrap() else {
        panic!("the head is larger than the test expects")
    };
    let straddles = head.packets.iter().any(|p| {
        let start = head.wsp_offset + p.offset;
        start < HEAD_READ_BYTES && start + p.len as u64 > HEAD_READ_BYTES
    });
    assert!(
        straddles,
        "the test volume should have a packet across the first request's end"
    );
    let server = TinyServer::start(vec![("/vol.wspx", wspx.clone())], &[]);
    let tmp = tempfile::tempdir().unwrap();
    let url = format!("http://{}/vol.wspx", server.url);
    let out = render(tmp.path(), &[&url, "--size", "96x96", "-o", "v.png"]);
    assert!(out.status.success(), "{}", text(&out));
    let served = server.served();
    let object = wspx.len() as u64;
    eprintln!(
        "whole view: the server sent {served} of {object} bytes ({:.2} %) over {} connections",
        100.0 * served as f64 / object as f64,
        server.connections()
    );
    assert!(
        served <= object,
        "the server sent {served} bytes of a {object}-byte object: some twice"
    );
    let (_, _, fetched, reported_object) = range_line(&out);
    assert_eq!(reported_object, object);
    assert_eq!(fetched, served, "the bytes reported are the bytes sent");
}

/// A missing file is reported by its status and its URL, without the server's HTML page and
/// without asking again; a plain-text answer is quoted, its first line only.
#[test]
fn a_missing_volume_is_reported_by_status_and_url_not_by_its_page() {
    let server = TinyServer::start(Vec::new(), &["/private.wspx"]);
    let tmp = tempfile::tempdir().unwrap();
    let url = format!("http://{}/nothing.wspx", server.url);
    let out = render(tmp.path(), &[&url, "--size", "32x32", "-o", "m.png"]);
    assert!(!out.status.success(), "{}", text(&out));
    let err = stderr(&out);
    assert!(err.contains("404 Not Found") && err.contains(&url), "{err}");
    assert!(
        !err.contains('<') && !err.contains("nginx"),
        "the HTML page was printed: {err}"
    );
    assert_eq!(server.connections(), 1, "a 404 is not asked again: {err}");
    assert!(!tmp.path().join("m.png").exists());

    let url = format!("http://{}/private.wspx", server.url);
    let out = render(tmp.path(), &[&url, "--size", "32x32", "-o", "p.png"]);
    assert!(!out.status.success(), "{}", text(&out));
    let err = stderr(&out);
    assert!(
        err.contains("403 Forbidden") && err.contains("Access denied: this bucket is private."),
        "{err}"
    );
    assert!(!err.contains("Request id"), "only the first line: {err}");
}

/// `https://` to a plaintext web server fails on its first connection (a failed TLS handshake
/// does not pass when tried again), saying that the server does not speak TLS and to try
/// `http://`.
#[test]
fn https_to_a_plaintext_server_fails_at_once_saying_so() {
    let server = TinyServer::start(vec![("/vol.wspx", volume().1.clone())], &[]);
    let tmp = tempfile::tempdir().unwrap();
    let url = format!("https://{}/vol.wspx", server.url);
    let out = render(tmp.path(), &[&url, "--size", "32x32", "-o", "t.png"]);
    assert!(!out.status.success(), "{}", text(&out));
    let err = stderr(&out);
    assert!(
        err.contains("does not speak TLS") && err.contains("http://"),
        "{err}"
    );
    assert!(
        server.connections() <= 2,
        "{} connections: the handshake was tried again ({err})",
        server.connections()
    );
    assert_eq!(server.served(), 0);
}

/// `cache list` pointed at a web server says that it is not a wavesplat cache and what it
/// answered, and where a published volume goes instead.
#[test]
fn cache_list_against_a_web_server_says_it_is_not_a_cache() {
    let server = TinyServer::start(Vec::new(), &[]);
    let out = Command::new(BIN)
        .args([
            "cache",
            "list",
            "--cache",
            &format!("http://{}", server.url),
        ])
        .env_remove("WAVESPLAT_CA")
        .env_remove("WAVESPLAT_TOKEN")
        .output()
        .unwrap();
    assert!(!out.status.success(), "{}", text(&out));
    let err = stderr(&out);
    assert!(
        err.contains("not a wavesplat cache") && err.contains("HTTP/1.1 400 Bad Request"),
        "{err}"
    );
    assert!(err.contains("render or view"), "{err}");
}

/// A CA and a server certificate for 127.0.0.1 and localhost signed by it, written to `dir`:
/// returns the paths of the CA's certificate, the server's and its key.
fn make_certificates(
    dir: &Path,
    name: &str,
) -> (std::path::PathBuf, std::path::PathBuf, std::path::PathBuf) {
    let mut ca_params = rcgen::CertificateParams::new(Vec::<String>::new()).unwrap();
    ca_params.is_ca = rcgen::IsCa::Ca(rcgen::BasicConstraints::Unconstrained);
    ca_params
        .distinguished_name
        .push(rcgen::DnType::CommonName, format!("range test CA {name}"));
    let ca_key = rcgen::KeyPair::generate().unwrap();
    let ca = ca_params.self_signed(&ca_key).unwrap();
    let params =
        rcgen::CertificateParams::new(vec!["127.0.0.1".to_string(), "localhost".to_string()])
            .unwrap();
    let key = rcgen::KeyPair::generate().unwrap();
    let cert = params.signed_by(&key, &ca, &ca_key).unwrap();
    let paths = (
        dir.join(format!("{name}-ca.pem")),
        dir.join(format!("{name}-server.pem")),
        dir.join(format!("{name}-server.key")),
    );
    std::fs::write(&paths.0, ca.pem()).unwrap();
    std::fs::write(&paths.1, cert.pem()).unwrap();
    std::fs::write(&paths.2, key.serialize_pem()).unwrap();
    paths
}

/// Over TLS (nginx with a certificate from a CA of the test's own): without `--ca` the
/// certificate is refused at once with a message that says to pass `--ca`; with `--ca`, or
/// `WAVESPLAT_CA`, the volume is browsed and draws the file's image; a CA that did not sign the
/// certificate is refused, naming it.
#[test]
fn the_ca_given_is_trusted_for_https() {
    if !have_nginx() {
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let www = dir.join("www");
    std::fs::create_dir_all(&www).unwrap();
    let (wsp, wspx) = volume();
    std::fs::write(www.join("vol.wsp"), wsp).unwrap();
    std::fs::write(www.join("vol.wspx"), wspx).unwrap();
    let (ca, cert, key) = make_certificates(dir, "ours");
    let (other_ca, _, _) = make_certificates(dir, "other");
    let server = start_nginx(&dir.join("nginx"), &www, Some((&cert, &key)));
    let url = format!("{}/vol.wspx", server.url);
    assert!(url.starts_with("https://"));
    let size = ["--size", "64x64"];

    let untrusted = render(dir, &[&[url.as_str(), "-o", "u.png"][..], &size].concat());
    assert!(!untrusted.status.success(), "{}", text(&untrusted));
    let err = stderr(&untrusted);
    assert!(
        err.contains("UnknownIssuer") && err.contains("--ca"),
        "{err}"
    );
    assert!(!err.contains("retries"), "{err}");

    let local = render(
        dir,
        &[&["www/vol.wsp", "-o", "l.png", "--raw", "l.f32"][..], &size].concat(),
    );
    assert!(local.status.success(), "{}", text(&local));
    let ca_arg = ca.to_str().unwrap();
    let trusted = render(
        dir,
        &[
            &[
                url.as_str(),
                "--ca",
                ca_arg,
                "-o",
                "t.png",
                "--raw",
                "t.f32",
            ][..],
            &size,
        ]
        .concat(),
    );
    assert!(trusted.status.success(), "{}", text(&trusted));
    let d = relative_difference(&read_f32(&dir.join("l.f32")), &read_f32(&dir.join("t.f32")));
    assert!(d <= 1e-5, "the image over TLS differs by {d} of the peak");
    let (_, _, fetched, object) = range_line(&trusted);
    assert!(fetched <= object, "{fetched} of {object}");

    let from_env = Command::new(BIN)
        .args(["render", url.as_str(), "-o", "e.png", "--size", "64x64"])
        .current_dir(dir)
        .env("WAVESPLAT_CA", &ca)
        .output()
        .unwrap();
    assert!(from_env.status.success(), "{}", text(&from_env));

    let wrong = render(
        dir,
        &[
            &[
                url.as_str(),
                "--ca",
                other_ca.to_str().unwrap(),
                "-o",
                "w.png",
            ][..],
            &size,
        ]
        .concat(),
    );
    assert!(!wrong.status.success(), "{}", text(&wrong));
    let err = stderr(&wrong);
    assert!(
        err.contains("not signed by the CA given") && err.contains("other-ca.pem"),
        "{err}"
    );
}

/// A bricked volume (80×72×64 in 40³ bricks: 8), published: its head names every brick; the
/// object gives the container back and a damaged index or a cut object is refused. Browsed by
/// range requests it is drawn as one volume: the whole view ends at the local file's image, and
/// a view zoomed into one corner fetches the head and the bytes of at most the two bricks along
/// its rays (of eight), ending at the local file's image of that corner; multiview ends at the
/// local file's multiview image.
#[test]
fn a_published_bricked_volume_browses_as_one() {
    use wavesplat_codec::format::index::BrickedHead;
    let volume = Phantom::SheppLogan.generate([80, 72, 64]);
    let bricked = wavesplat_compressor::bricked::compress_bricked(
        &volume,
        &common::phantom_options(0.2),
        40,
        &|_| {},
    )
    .unwrap();
    let wsp = bricked.bytes;
    let wspx = indexed_layout(&wsp).unwrap();
    let head: BrickedHead = match read_indexed_head(&wspx).unwrap() {
        HeadRead::Bricked(h) => *h,
        _ => panic!("a bricked volume's head is not read as bricked"),
    };
    assert_eq!(head.bricks.len(), 8);
    assert_eq!(head.object_bytes(), wspx.len() as u64);
    assert_eq!(wsp_of_indexed(&wspx).unwrap(), &wsp[..]);
    assert!(
        wsp_of_indexed(&wspx[..wspx.len() - 5]).is_err(),
        "cut short"
    );
    let mut damaged = wspx.clone();
    damaged[30] ^= 0x40;
    assert!(read_indexed_head(&damaged).is_err(), "a damaged index");
    // Every packet the head places starts where its brick's bytes say.
    for (b, brick) in head.bricks.iter().enumerate() {
        let entry = &head.manifest.bricks[b];
        for i in 0..brick.packets.len() {
            let at = head.packet_offset(b, i).unwrap();
            assert!(at >= head.wsp_offset + entry.offset);
            assert!(at < head.wsp_offset + entry.offset + entry.length);
        }
    }
    let largest_two: u64 = {
        let mut lengths: Vec<u64> = head.manifest.bricks.iter().map(|b| b.length).collect();
        lengths.sort_unstable();
        lengths.iter().rev().take(2).sum()
    };

    let tmp = tempfile::tempdir().unwrap();
    std::fs::write(tmp.path().join("b.wsp"), &wsp).unwrap();
    let corner = [
        "--alpha=-1.5707963267948966",
        "--beta=-1.5707963267948966",
        "--zoom",
        "4",
        "--pan=-20,18",
        "--size",
        "32x32",
    ];
    let whole = ["--size", "48x48"];
    let multiview = [
        "--multiview",
        "--alpha",
        "0.4",
        "--beta",
        "0.3",
        "--size",
        "40x32",
    ];
    for (name, view) in [
        ("whole", &whole[..]),
        ("corner", &corner[..]),
        ("multiview", &multiview[..]),
    ] {
        let server = TinyServer::start(vec![("/b.wspx", wspx.clone())], &[]);
        let url = format!("http://{}/b.wspx", server.url);
        let remote = format!("{name}-remote.f32");
        let local = format!("{name}-local.f32");
        let mut args = vec![url.as_str(), "--cpu", "-o", "r.png", "--raw", &remote];
        args.extend_from_slice(view);
        let out = render(tmp.path(), &args);
        assert!(out.status.success(), "{name}: {}", text(&out));
        let mut args = vec![
            "b.wsp",
            "--cpu",
            "--progressive",
            "-o",
            "l.png",
            "--raw",
            &local,
        ];
        args.extend_from_slice(view);
        let out_local = render(tmp.path(), &args);
        assert!(out_local.status.success(), "{}", text(&out_local));
        let (r, l) = (
            read_f32(&tmp.path().join(&remote)),
            read_f32(&tmp.path().join(&local)),
        );
        assert!(l.iter().any(|v| *v != 0.0), "{name}: the image is empty");
        let snr = wavesplat_codec::metrics::snr_db(&l, &r);
        assert!(snr > 90.0, "{name}: remote against local {snr:.1} dB");
        let served = server.served();
        let (_, _, fetched, object) = range_line(&out);
        assert_eq!(object, wspx.len() as u64);
        assert_eq!(
            fetched, served,
            "{name}: the bytes reported are the bytes sent"
        );
        eprintln!(
            "{name}: {served} of {object} bytes fetched ({:.1} %)",
            100.0 * served as f64 / object as f64
        );
        if name == "corner" {
            assert!(
                served <= HEAD_READ_BYTES + largest_two,
                "a corner fetched {served} bytes: more than the head and two bricks ({})",
                HEAD_READ_BYTES + largest_two
            );
        } else {
            assert!(
                served <= object,
                "the whole view fetched {served} bytes: some twice"
            );
        }
    }
}

/// A series' indexed layout with component 0's second brick given its first brick's origin,
/// the index's CRC made to match (the origins are one-byte varints here).
fn second_brick_on_the_first(wspx: &[u8]) -> Vec<u8> {
    use wavesplat_codec::format::index::INDEXED_HEAD_BYTES;
    let index_len = u32::from_le_bytes(wspx[14..18].try_into().unwrap()) as usize;
    let mut out = wspx.to_vec();
    let index = &mut out[INDEXED_HEAD_BYTES..INDEXED_HEAD_BYTES + index_len];
    let mut at = 0usize;
    let varint = |at: &mut usize, index: &[u8]| {
        let (mut v, mut shift) = (0u64, 0);
        loop {
            let b = index[*at];
            *at += 1;
            v |= u64::from(b & 0x7f) << shift;
            shift += 7;
            if b & 0x80 == 0 {
                return v;
            }
        }
    };
    varint(&mut at, index); // components
    at += 1; // component 0's kind
    assert!(varint(&mut at, index) >= 2, "component 0 has two bricks");
    let first = at;
    for _ in 0..5 {
        varint(&mut at, index); // origin, offset, length
    }
    for _ in 0..2 {
        let len = varint(&mut at, index) as usize; // header section, packet index
        at += len;
    }
    let second = at;
    let origin: Vec<u8> = index[first..first + 3].to_vec();
    assert!(origin
        .iter()
        .chain(&index[second..second + 3])
        .all(|b| b & 0x80 == 0));
    assert_ne!(
        &index[second..second + 3],
        &origin[..],
        "the bricks' origins differ"
    );
    index[second..second + 3].copy_from_slice(&origin);
    let crc = crc32fast::hash(index);
    out[18..22].copy_from_slice(&crc.to_le_bytes());
    out
}

/// A published time series (the indexed layout's version 3) browses one time point at a time:
/// its head lists every component's bricks; `render URL --time-point t` draws what the local
/// file's time point draws and fetches, beyond the head, only the bytes of the components the
/// time point names; a time point past the end is refused by name.
#[test]
fn a_published_series_browses_one_time_point_at_a_time() {
    use wavesplat_codec::format::index::SeriesHead;
    use wavesplat_compressor::series::{compress_series, VolumeSeries};
    const POINTS: usize = 6;
    let volumes = (0..POINTS)
        .map(|t| wavesplat_compressor::phantom::beating([48, 40, 24], t, POINTS).unwrap())
        .collect();
    let s = VolumeSeries::new(volumes, None).unwrap();
    let wsp = compress_series(&s, &common::phantom_options(0.3), 4, 24, &|_| {})
        .unwrap()
        .bytes;
    let wspx = indexed_layout(&wsp).unwrap();
    let head: SeriesHead = match read_indexed_head(&wspx).unwrap() {
        HeadRead::Series(h) => *h,
        _ => panic!("a series' head is not read as a series"),
    };
    assert_eq!(head.object_bytes(), wspx.len() as u64);
    assert_eq!(wsp_of_indexed(&wspx).unwrap(), &wsp[..]);
    assert_eq!(head.bricked.len(), head.manifest.components.len());
    assert!(head.bricked.iter().all(|b| *b), "bricked components");
    assert!(head.bricks.len() > head.manifest.components.len());
    // Every brick's packets lie inside its component.
    for b in &head.bricks {
        let c = &head.manifest.components[b.component];
        for p in &b.brick.packets {
            let at = b.offset + p.offset;
            assert!(at >= c.offset && at + p.len as u64 <= c.offset + c.length);
        }
    }
    let mut damaged = wspx.clone();
    damaged[30] ^= 0x40;
    assert!(read_indexed_head(&damaged).is_err(), "a damaged index");
    // An index whose bricks do not tile the series (component 0's second brick moved onto its
    // first, the index signed again) is refused: drawn, it would add one brick twice and
    // leave a hole.
    let moved = second_brick_on_the_first(&wspx);
    let e = read_indexed_head(&moved).unwrap_err().to_string();
    assert!(e.contains("overlaps") || e.contains("voxels"), "{e}");

    let tmp = tempfile::tempdir().unwrap();
    std::fs::write(tmp.path().join("s.wsp"), &wsp).unwrap();
    for t in [0usize, 3, 5] {
        let server = TinyServer::start(vec![("/s.wspx", wspx.clone())], &[]);
        let url = format!("http://{}/s.wspx", server.url);
        let tp = t.to_string();
        let view = ["--alpha", "0.5", "--beta", "0.2", "--size", "48x40"];
        let mut args = vec![url.as_str(), "--time-point", &tp, "--cpu", "-o", "r.png"];
        args.extend_from_slice(&["--raw", "remote.f32"]);
        args.extend_from_slice(&view);
        let out = render(tmp.path(), &args);
        assert!(out.status.success(), "t {t}: {}", text(&out));
        let mut args = vec!["s.wsp", "--time-point", &tp, "--cpu", "--progressive"];
        args.extend_from_slice(&["-o", "l.png", "--raw", "local.f32"]);
        args.extend_from_slice(&view);
        let out_local = render(tmp.path(), &args);
        assert!(out_local.status.success(), "{}", text(&out_local));
        let (r, l) = (
            read_f32(&tmp.path().join("remote.f32")),
            read_f32(&tmp.path().join("local.f32")),
        );
        assert!(l.iter().any(|v| *v != 0.0), "t {t}: the image is empty");
        let snr = wavesplat_codec::metrics::snr_db(&l, &r);
        assert!(snr > 90.0, "t {t}: remote against local {snr:.1} dB");
        let served = server.served();
        let own = head.manifest.point_bytes(t);
        assert!(
            served <= head.wsp_offset + HEAD_READ_BYTES + own,
            "t {t} fetched {served} bytes: more than the head and its components ({own})"
        );
        assert!(own < wsp.len() as u64, "t {t} names every component");
    }
    let server = TinyServer::start(vec![("/s.wspx", wspx.clone())], &[]);
    let url = format!("http://{}/s.wspx", server.url);
    let out = render(
        tmp.path(),
        &[&url, "--time-point", "6", "--cpu", "-o", "x.png"],
    );
    let said = text(&out);
    assert!(
        !out.status.success() && said.contains("time point 6"),
        "{said}"
    );
}
