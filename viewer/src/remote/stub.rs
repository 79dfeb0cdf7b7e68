//! A scripted web server for the range reader's tests (std::net, a thread per connection,
//! keep-alive): each request is answered by the test's script, given the request and its
//! number, with bytes to write, pauses and an early close, so that a test can answer 503 with
//! `Retry-After`, stall a body, send more bytes than asked, change the file between requests
//! or break a body midway. Every request is kept for the test to look at. Written here because
//! a server library (hyper, axum) answers with well-formed responses only: what these tests
//! need is the malformed and stalled ones.

use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::Duration;

/// One request as the server read it.
#[derive(Debug, Clone)]
pub(super) struct Seen {
    /// The request target (path and query).
    pub(super) target: String,
    /// Its headers, names in lower case.
    pub(super) headers: Vec<(String, String)>,
}

impl Seen {
    /// The value of header `name` (lower case), if sent.
    pub(super) fn header(&self, name: &str) -> Option<&str> {
        self.headers
            .iter()
            .find(|(k, _)| k == name)
            .map(|(_, v)| v.as_str())
    }

    /// The `Range: bytes=A-B` asked for, as (A, B when given).
    pub(super) fn range(&self) -> Option<(u64, Option<u64>)> {
        let (a, b) = self
            .header("range")?
            .strip_prefix("bytes=")?
            .split_once('-')?;
        Some((a.parse().ok()?, b.parse().ok()))
    }
}

/// What the server does in answer to a request, in order.
pub(super) enum Action {
    /// Writes these bytes.
    Write(Vec<u8>),
    /// Waits this long.
    Sleep(Duration),
    /// Closes the connection.
    Close,
}

/// The script: the answer to request number `n` (from 0, over every connection).
type Script = dyn Fn(usize, &Seen) -> Vec<Action> + Send + Sync;

/// A scripted server on a loopback port.
pub(super) struct Stub {
    /// `http://127.0.0.1:PORT`.
    pub(super) base: String,
    seen: Arc<Mutex<Vec<Seen>>>,
}

impl Stub {
    /// Starts a server answering each request as `script` says.
    pub(super) fn start(
        script: impl Fn(usize, &Seen) -> Vec<Action> + Send + Sync + 'static,
    ) -> Stub {
        let listener = TcpListener::bind("127.0.0.1:0").expect("bind a loopback port");
        let base = format!("http://{}", listener.local_addr().expect("its address"));
        let seen = Arc::new(Mutex::new(Vec::new()));
        let script: Arc<Script> = Arc::new(script);
        let count = Arc::new(AtomicUsize::new(0));
        let kept = seen.clone();
        // Lives as long as the test process.
        std::thread::spawn(move || {
            for stream in listener.incoming() {
                let Ok(stream) = stream else { continue };
                let (script, count, kept) = (script.clone(), count.clone(), kept.clone());
                std::thread::spawn(move || connection(stream, &*script, &count, &kept));
            }
        });
        Stub { base, seen }
    }

    /// The requests answered so far, in order.
    pub(super) fn seen(&self) -> Vec<Seen> {
        self.seen.lock().unwrap_or_else(|e| e.into_inner()).clone()
    }
}

/// Reads requests off one connection and answers them.
fn connection(mut s: TcpStream, script: &Script, count: &AtomicUsize, kept: &Mutex<Vec<Seen>>) {
    let _ = s.set_read_timeout(Some(Duration::from_secs(30)));
    let mut buf = Vec::new();
    loop {
        let end = loop {
            if let Some(i) = buf.windows(4).position(|w| w == b"\r\n\r\n") {
                break i + 4;
            }
            let mut chunk = [0u8; 4096];
            match s.read(&mut chunk) {
                Ok(0) | Err(_) => return,
                Ok(n) => buf.extend_from_slice(&chunk[..n]),
            }
        };
        let head = String::from_utf8_lossy(&buf[..end]).into_owned();
        buf.drain(..end);
        let mut lines = head.split("\r\n");
        let target = lines
            .next()
            .and_then(|l| l.split(' ').nth(1))
            .unwrap_or_default()
            .to_string();
        let headers = lines
            .filter_map(|l| l.split_once(':'))
            .map(|(k, v)| (k.trim().to_ascii_lowercase(), v.trim().to_string()))
            .collect();
        let seen = Seen { target, headers };
        kept.lock()
            .unwrap_or_else(|e| e.into_inner())
            .push(seen.clone());
        let n = count.fetch_add(1, Ordering::SeqCst);
        for action in script(n, &seen) {
            match action {
                Action::Write(bytes) => {
                    if s.write_all(&bytes).is_err() {
                        return;
                    }
                }
                Action::Sleep(d) => std::thread::sleep(d),
                Action::Close => {
                    let _ = s.shutdown(std::net::Shutdown::Write);
                    return;
                }
            }
        }
    }
}

/// A response: status line `status`, the headers given, `Content-Length` and the body.
pub(super) fn reply(status: &str, headers: &[String], body: &[u8]) -> Vec<Action> {
    let mut head = format!("HTTP/1.1 {status}\r\n");
    for h in headers {
        head.push_str(h);
        head.push_str("\r\n");
    }
    head.push_str(&format!("Content-Length: {}\r\n\r\n", body.len()));
    let mut bytes = head.into_bytes();
    bytes.extend_from_slice(body);
    vec![Action::Write(bytes)]
}

/// `data` served as a file: the range asked for (206, cut at its end) or all of it (200),
/// with the headers given.
pub(super) fn serve(data: &[u8], seen: &Seen, headers: &[String]) -> Vec<Action> {
    let len = data.len() as u64;
    match seen.range() {
        None => reply("200 OK", headers, data),
        Some((a, _)) if a >= len => reply(
            "416 Range Not Satisfiable",
            &[format!("Content-Range: bytes */{len}")],
            b"",
        ),
        Some((a, b)) => {
            let b = b.unwrap_or(len - 1).min(len - 1);
            let mut h = headers.to_vec();
            h.push(format!("Content-Range: bytes {a}-{b}/{len}"));
            reply("206 Partial Content", &h, &data[a as usize..=b as usize])
        }
    }
}

/// A volume in the indexed layout larger than the head's first request (the 64³ Shepp–Logan
/// phantom, tiles of 8), made once.
pub(super) fn volume() -> &'static [u8] {
    static VOLUME: OnceLock<Vec<u8>> = OnceLock::new();
    VOLUME.get_or_init(|| {
        use wavesplat_compressor::encode::{compress, CompressOptions, Target, TileChoice};
        let wsp = compress(
            &wavesplat_compressor::phantom::Phantom::SheppLogan.generate([64, 64, 64]),
            &CompressOptions {
                target: Target::Fraction(0.3),
                tile: TileChoice::Size(8),
                refine: None,
                ..Default::default()
            },
            &|_, _| {},
        )
        .expect("compress the phantom")
        .bytes;
        let object = wavesplat_codec::format::index::indexed_layout(&wsp).expect("index it");
        assert!(
            object.len() as u64 > 2 * wavesplat_codec::format::index::HEAD_READ_BYTES,
            "the test volume is {} bytes: all of it comes with the head",
            object.len()
        );
        object
    })
}
