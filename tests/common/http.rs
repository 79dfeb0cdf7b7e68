//! A web server of the tests' own ([`TinyServer`]): files served by path with `Range`
//! honoured, and the answers nginx gives to what it does not serve, for range browsing from
//! any test without nginx.

use std::collections::HashMap;
use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

/// A web server of the test's own on a loopback port (a thread per connection, keep-alive): it
/// serves `files` by path honouring `Range` (206 with `Content-Range`, 416 past the end),
/// answers any other path with a 404 and an HTML page as nginx does (`denied` paths: 403 with
/// a line of plain text), and anything that is not an HTTP/1 request — a TLS handshake, the
/// HTTP/2 preface — with nginx's 400. It counts the connections it accepted and the bytes of
/// files it sent.
pub struct TinyServer {
    /// `host:port`.
    pub url: String,
    connections: Arc<AtomicU64>,
    served: Arc<AtomicU64>,
}

/// nginx's 404 page.
const NOT_FOUND_PAGE: &str = "<html>\r\n<head><title>404 Not Found</title></head>\r\n<body>\r\n\
    <center><h1>404 Not Found</h1></center>\r\n<hr><center>nginx/1.22.1</center>\r\n</body>\r\n</html>\r\n";

impl TinyServer {
    /// Serves `files` (path, bytes), `denied` paths answered 403.
    pub fn start(files: Vec<(&str, Vec<u8>)>, denied: &[&str]) -> TinyServer {
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let url = format!("127.0.0.1:{}", listener.local_addr().unwrap().port());
        let files: Arc<HashMap<String, Vec<u8>>> =
            Arc::new(files.into_iter().map(|(p, b)| (p.to_string(), b)).collect());
        let denied: Arc<Vec<String>> = Arc::new(denied.iter().map(|d| d.to_string()).collect());
        let connections = Arc::new(AtomicU64::new(0));
        let served = Arc::new(AtomicU64::new(0));
        let (c, sv) = (connections.clone(), served.clone());
        // Lives as long as the test process.
        std::thread::spawn(move || {
            for stream in listener.incoming() {
                let Ok(stream) = stream else { continue };
                c.fetch_add(1, Ordering::SeqCst);
                let (files, denied, sv) = (files.clone(), denied.clone(), sv.clone());
                std::thread::spawn(move || serve_connection(stream, &files, &denied, &sv));
            }
        });
        TinyServer {
            url,
            connections,
            served,
        }
    }

    /// Connections accepted so far.
    pub fn connections(&self) -> u64 {
        self.connections.load(Ordering::SeqCst)
    }

    /// Bytes of files sent so far.
    pub fn served(&self) -> u64 {
        self.served.load(Ordering::SeqCst)
    }
}

fn respond(s: &mut TcpStream, status: &str, headers: &[String], body: &[u8]) -> bool {
    let mut head = format!("HTTP/1.1 {status}\r\nServer: tiny\r\n");
    for h in headers {
        head.push_str(h);
        head.push_str("\r\n");
    }
    head.push_str(&format!("Content-Length: {}\r\n\r\n", body.len()));
    s.write_all(head.as_bytes()).is_ok() && s.write_all(body).is_ok()
}

/// Answers nginx's 400 and closes as nginx does: the write side first, then what the client
/// still sends is read and dropped, so that it reads the answer before the connection ends.
fn bad_request(mut s: TcpStream) {
    let page = "<html>\r\n<head><title>400 Bad Request</title></head>\r\n</html>\r\n";
    let _ = respond(
        &mut s,
        "400 Bad Request",
        &["Content-Type: text/html".into(), "Connection: close".into()],
        page.as_bytes(),
    );
    let _ = s.shutdown(std::net::Shutdown::Write);
    let mut sink = [0u8; 4096];
    while matches!(s.read(&mut sink), Ok(n) if n > 0) {}
}

fn serve_connection(
    mut s: TcpStream,
    files: &HashMap<String, Vec<u8>>,
    denied: &[String],
    served: &AtomicU64,
) {
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    let mut buf = Vec::new();
    loop {
        let end = loop {
            if let Some(i) = buf.windows(4).position(|w| w == b"\r\n\r\n") {
                break Some(i + 4);
            }
            if buf.first().is_some_and(|b: &u8| !b.is_ascii_uppercase()) {
                break None;
            }
            let mut chunk = [0u8; 4096];
            match s.read(&mut chunk) {
                Ok(0) | Err(_) => return,
                Ok(n) => buf.extend_from_slice(&chunk[..n]),
            }
        };
        let Some(end) = end else {
            return bad_request(s);
        };
        let head = String::from_utf8_lossy(&buf[..end]).into_owned();
        buf.drain(..end);
        let mut lines = head.split("\r\n");
        let mut request = lines.next().unwrap_or_default().split(' ');
        let (method, path) = (request.next().unwrap_or(""), request.next().unwrap_or(""));
        if method != "GET" {
            return bad_request(s);
        }
        let range = lines
            .filter_map(|l| l.split_once(':'))
            .find(|(k, _)| k.trim().eq_ignore_ascii_case("range"))
            .and_then(|(_, v)| {
                let (a, b) = v.trim().strip_prefix("bytes=")?.split_once('-')?;
                Some((a.parse::<u64>().ok()?, b.parse::<u64>().ok()))
            });
        let ok = match files.get(path) {
            Some(data) => {
                let len = data.len() as u64;
                match range {
                    None => {
                        served.fetch_add(len, Ordering::SeqCst);
                        respond(&mut s, "200 OK", &[], data)
                    }
                    Some((a, _)) if a >= len => respond(
                        &mut s,
                        "416 Range Not Satisfiable",
                        &[format!("Content-Range: bytes */{len}")],
                        b"",
                    ),
                    Some((a, b)) => {
                        let b = b.unwrap_or(len - 1).min(len - 1);
                        let body = &data[a as usize..=b as usize];
                        served.fetch_add(body.len() as u64, Ordering::SeqCst);
                        respond(
                            &mut s,
                            "206 Partial Content",
                            &[format!("Content-Range: bytes {a}-{b}/{len}")],
                            body,
                        )
                    }
                }
            }
            None if denied.iter().any(|d| d == path) => respond(
                &mut s,
                "403 Forbidden",
                &["Content-Type: text/plain; charset=utf-8".into()],
                b"Access denied: this bucket is private.\n\nRequest id 1234\n",
            ),
            None => respond(
                &mut s,
                "404 Not Found",
                &["Content-Type: text/html".into()],
                NOT_FOUND_PAGE.as_bytes(),
            ),
        };
        if !ok {
            return;
        }
    }
}
