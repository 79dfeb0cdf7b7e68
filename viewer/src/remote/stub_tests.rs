//! The range reader against a scripted web server ([`super::stub`]): what it does when the
//! server pauses it, breaks a body, sends more than asked, changes the file, compresses it or
//! refuses a presigned URL, and that no credential of the URL reaches a message.

use super::object::{Object, Pacing};
use super::stub::{reply, serve, volume, Action, Stub};
use super::{RangeSource, RangeSourceOptions};
use crate::source::PacketSource;
use std::sync::{Arc, OnceLock};
use std::time::{Duration, Instant};
use wavesplat_codec::view::{View, ViewSpec};

/// Reads paced for a test: short pauses, a short read timeout.
const QUICK: Pacing = Pacing {
    attempts: 3,
    first_pause: Duration::from_millis(20),
    read_timeout: Duration::from_millis(300),
    outage_pause: Duration::from_millis(200),
};

/// [`QUICK`] with a read timeout that a loaded machine's scheduling cannot reach by accident,
/// for the tests that time a stall against it.
const PATIENT: Pacing = Pacing {
    read_timeout: Duration::from_secs(1),
    ..QUICK
};

/// Runs `f` to its end on a runtime of its own.
fn block<F: std::future::Future>(f: F) -> F::Output {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .expect("a runtime")
        .block_on(f)
}

/// 100 bytes, each its own offset.
fn hundred() -> Vec<u8> {
    (0..100u8).collect()
}

/// A 503 with `Retry-After: 1` is waited out a second, not the first pause of the back-off.
#[test]
fn retry_after_is_waited_out() {
    let data = hundred();
    let stub = Stub::start(move |n, seen| {
        if n == 0 {
            reply(
                "503 Service Unavailable",
                &["Retry-After: 1".into()],
                b"busy",
            )
        } else {
            serve(&data, seen, &[])
        }
    });
    let object = Object::open(&format!("{}/v.wspx", stub.base), None).unwrap();
    let asked = Instant::now();
    let (bytes, total) = block(object.read(Some(10..20))).unwrap();
    let waited = asked.elapsed();
    assert_eq!(&bytes[..], &hundred()[10..20]);
    assert_eq!(total, 100);
    assert!(
        waited >= Duration::from_millis(950),
        "asked again after {waited:?}, the server said a second"
    );
    assert_eq!(stub.seen().len(), 2);
}

/// A `Retry-After` longer than a back-off's longest pause is not waited out silently inside the
/// read: the read ends at once, saying how long the server asks to wait (capped), for the
/// caller to show and wait (a browse pauses; an open fails with the reason).
#[test]
fn a_long_retry_after_ends_the_read_saying_so() {
    let stub = Stub::start(|_, _| {
        reply(
            "503 Service Unavailable",
            &["Retry-After: 120".into()],
            b"maintenance",
        )
    });
    let object = Object::open(&format!("{}/v.wspx", stub.base), None).unwrap();
    let asked = Instant::now();
    let e = block(object.read(Some(10..20))).unwrap_err();
    assert!(
        asked.elapsed() < Duration::from_secs(5),
        "{:?}",
        asked.elapsed()
    );
    assert!(!e.is_final(), "{e}");
    assert_eq!(e.retry_after(), Some(Duration::from_secs(60)));
    assert!(e.to_string().contains("asks to wait 60 s"), "{e}");
    assert_eq!(stub.seen().len(), 1);
}

/// A whole-object read (`fetch_wsp`) whose body breaks midway asks for the rest from where it
/// broke (`Range: bytes=N-`), not for all of it again.
#[test]
fn a_whole_read_resumes_where_its_body_broke() {
    let data: Vec<u8> = (0..200_000u32).map(|i| (i * 7 % 251) as u8).collect();
    let half = 80_000;
    let served = data.clone();
    let stub = Stub::start(move |n, seen| {
        if n == 0 {
            let mut head = format!(
                "HTTP/1.1 200 OK\r\nContent-Length: {}\r\n\r\n",
                served.len()
            )
            .into_bytes();
            head.extend_from_slice(&served[..half]);
            vec![Action::Write(head), Action::Close]
        } else {
            serve(&served, seen, &[])
        }
    });
    let object = Object::open(&format!("{}/v.wsp", stub.base), None).unwrap();
    let (bytes, total) = block(object.read(None)).unwrap();
    assert_eq!(total, data.len() as u64);
    assert!(
        bytes[..] == data[..],
        "the bytes put together are the file's"
    );
    let seen = stub.seen();
    assert_eq!(seen.len(), 2, "{seen:?}");
    assert_eq!(seen[0].range(), None);
    let (from, to) = seen[1]
        .range()
        .expect("the second request asks for a range");
    let last = data.len() as u64 - 1;
    assert!(
        from > 0 && from <= half as u64 && to.is_none_or(|to| to == last),
        "{seen:?}"
    );
}

/// A body that stalls is given up after the read timeout, not after a total timeout, and asked
/// for again from where it stalled.
#[test]
fn a_stalled_body_is_asked_for_again_from_where_it_stalled() {
    let data: Vec<u8> = (0..1000u32).map(|i| (i % 251) as u8).collect();
    let served = data.clone();
    let stub = Stub::start(move |n, seen| {
        if n == 0 {
            let mut head = b"HTTP/1.1 206 Partial Content\r\nContent-Range: bytes 0-999/1000\r\n\
                             Content-Length: 1000\r\n\r\n"
                .to_vec();
            head.extend_from_slice(&served[..400]);
            vec![
                Action::Write(head),
                Action::Sleep(Duration::from_secs(8)),
                Action::Close,
            ]
        } else {
            serve(&served, seen, &[])
        }
    });
    let object = Object::open_paced(&format!("{}/v.wspx", stub.base), None, PATIENT).unwrap();
    let asked = Instant::now();
    let (bytes, total) = block(object.read(Some(0..1000))).unwrap();
    assert!(
        asked.elapsed() < Duration::from_secs(6),
        "{:?}",
        asked.elapsed()
    );
    assert_eq!((&bytes[..], total), (&data[..], 1000));
    let seen = stub.seen();
    assert_eq!(seen.len(), 2);
    assert_eq!(seen[1].range(), Some((400, Some(999))));
}

/// A slow but steady body is read to its end in one request, however many read timeouts it
/// takes in all.
#[test]
fn a_slow_steady_body_is_read_to_its_end() {
    let data: Vec<u8> = (0..1000u32).map(|i| (i % 251) as u8).collect();
    let served = data.clone();
    let stub = Stub::start(move |_, _| {
        let mut actions = vec![Action::Write(
            b"HTTP/1.1 206 Partial Content\r\nContent-Range: bytes 0-999/1000\r\n\
              Content-Length: 1000\r\n\r\n"
                .to_vec(),
        )];
        for chunk in served.chunks(25) {
            actions.push(Action::Write(chunk.to_vec()));
            actions.push(Action::Sleep(Duration::from_millis(100)));
        }
        actions
    });
    let object = Object::open_paced(&format!("{}/v.wspx", stub.base), None, PATIENT).unwrap();
    let asked = Instant::now();
    let (bytes, _) = block(object.read(Some(0..1000))).unwrap();
    assert!(asked.elapsed() > PATIENT.read_timeout * 3);
    assert_eq!(&bytes[..], &data[..]);
    assert_eq!(stub.seen().len(), 1);
}

/// A 200 to a range is refused unless the range is from the start and holds the whole object
/// (a small object served whole is as good).
#[test]
fn a_whole_object_answers_a_range_only_when_it_fits_it() {
    let data = hundred();
    let stub = Stub::start(move |_, _| reply("200 OK", &[], &data));
    let object = Object::open(&format!("{}/v.wspx", stub.base), None).unwrap();
    let (bytes, total) = block(object.read(Some(0..65536))).unwrap();
    assert_eq!((&bytes[..], total), (&hundred()[..], 100));
    let e = block(object.read(Some(10..20)))
        .map(|(b, t)| (b.len(), t))
        .unwrap_err()
        .to_string();
    assert!(e.contains("ignores Range"), "{e}");
    let e = block(object.read(Some(0..50)))
        .map(|(b, t)| (b.len(), t))
        .unwrap_err()
        .to_string();
    assert!(e.contains("ignores Range"), "{e}");
}

/// A 206 that says or sends more than was asked for is refused, however it does it: a
/// `Content-Range` past the end asked, a `Content-Length` larger than the range, a chunked
/// body longer than its `Content-Range`.
#[test]
fn a_range_answered_with_more_than_asked_is_refused() {
    let data = hundred();
    let cases: Vec<(&str, Vec<u8>)> = vec![
        (
            "range past the end asked",
            [
                b"HTTP/1.1 206 Partial Content\r\nContent-Range: bytes 10-29/100\r\n\
                  Content-Length: 20\r\n\r\n" as &[u8],
                &data[10..30],
            ]
            .concat(),
        ),
        (
            "length past the range",
            [
                b"HTTP/1.1 206 Partial Content\r\nContent-Range: bytes 10-19/100\r\n\
                  Content-Length: 20\r\n\r\n" as &[u8],
                &data[10..30],
            ]
            .concat(),
        ),
        (
            "chunked body past the range",
            [
                b"HTTP/1.1 206 Partial Content\r\nContent-Range: bytes 10-19/100\r\n\
                  Transfer-Encoding: chunked\r\n\r\n1e\r\n" as &[u8],
                &data[10..40],
                b"\r\n0\r\n\r\n",
            ]
            .concat(),
        ),
    ];
    for (name, answer) in cases {
        let stub = Stub::start(move |_, _| vec![Action::Write(answer.clone())]);
        let object = Object::open(&format!("{}/v.wspx", stub.base), None).unwrap();
        let got = block(object.read(Some(10..20)));
        assert!(got.is_err(), "{name}: {:?}", got.map(|(b, t)| (b.len(), t)));
    }
}

/// A file changed on the server after it was opened is refused, saying so: another strong
/// `ETag` or another size (compared from each answer's headers: no `If-Match` is sent, which
/// some servers answer with a 412 even when the `ETag` matches).
#[test]
fn a_file_changed_on_the_server_is_refused_saying_so() {
    type Answer = fn(&[u8], &super::stub::Seen) -> Vec<Action>;
    let cases: [(&str, Answer); 2] = [
        ("another ETag", |data, seen| {
            serve(data, seen, &["ETag: \"v2\"".into()])
        }),
        ("another size", |data, seen| {
            serve(&[data, data].concat(), seen, &["ETag: \"v1\"".into()])
        }),
    ];
    for (name, later) in cases {
        let stub = Stub::start(move |n, seen| {
            let data = hundred();
            if n == 0 {
                serve(&data, seen, &["ETag: \"v1\"".into()])
            } else {
                later(&data, seen)
            }
        });
        let object = Object::open(&format!("{}/v.wspx", stub.base), None).unwrap();
        block(object.read(Some(0..10))).unwrap();
        let e = block(object.read(Some(10..20)))
            .map(|(b, t)| (b.len(), t))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("changed on the server since it was opened: reopen it"),
            "{name}: {e}"
        );
        let seen = stub.seen();
        assert_eq!(seen.len(), 2, "{name}: a change is not asked again");
        assert_eq!(seen[1].header("if-match"), None, "{name}");
    }
}

/// An object in a store changed after it was opened is refused, saying so.
#[test]
fn an_object_changed_in_its_store_is_refused_saying_so() {
    use object_store::{ObjectStoreExt, PutPayload};
    let store = Arc::new(object_store::memory::InMemory::new());
    let path = object_store::path::Path::from("v.wspx");
    block(store.put(&path, PutPayload::from(hundred()))).unwrap();
    let object = Object::store(store.clone(), path.clone());
    block(object.read(Some(0..10))).unwrap();
    block(store.put(&path, PutPayload::from(hundred()))).unwrap();
    let e = block(object.read(Some(10..20)))
        .map(|(b, t)| (b.len(), t))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("changed on the server since it was opened"),
        "{e}"
    );
}

/// The reader asks for the bytes as they are (`Accept-Encoding: identity`) and refuses a body
/// sent compressed, naming its encoding.
#[test]
fn a_compressed_body_is_refused_naming_its_encoding() {
    let data = hundred();
    let stub = Stub::start(move |_, seen| serve(&data, seen, &["Content-Encoding: gzip".into()]));
    let object = Object::open(&format!("{}/v.wspx", stub.base), None).unwrap();
    let e = block(object.read(Some(0..10)))
        .map(|(b, t)| (b.len(), t))
        .unwrap_err()
        .to_string();
    assert!(e.contains("gzip"), "{e}");
    assert_eq!(stub.seen()[0].header("accept-encoding"), Some("identity"));
}

/// A 403 with an S3 XML error body (an expired presigned URL) says its code and message, and
/// that a presigned URL may have expired.
#[test]
fn an_expired_presigned_url_says_why() {
    let stub = Stub::start(|_, _| {
        reply(
            "403 Forbidden",
            &["Content-Type: application/xml".into()],
            b"<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n<Error><Code>AccessDenied</Code>\
              <Message>Request has expired</Message><RequestId>42</RequestId></Error>",
        )
    });
    let object = Object::open(&format!("{}/v.wspx?X-Amz-Signature=abc", stub.base), None).unwrap();
    let e = block(object.read(Some(0..10)))
        .map(|(b, t)| (b.len(), t))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("403 Forbidden")
            && e.contains("AccessDenied")
            && e.contains("Request has expired")
            && e.contains("a presigned URL may have expired"),
        "{e}"
    );
    assert!(!e.contains("42"), "only the code and message: {e}");
}

/// Where the head's requests end in `object` (a volume in the indexed layout): requests from
/// there on are for packets.
fn head_end(object: &[u8]) -> u64 {
    use wavesplat_codec::format::index::{read_indexed_head, HeadRead, HEAD_READ_BYTES};
    match read_indexed_head(&object[..HEAD_READ_BYTES as usize]) {
        Ok(HeadRead::Need(n)) => (n as u64).max(HEAD_READ_BYTES),
        _ => HEAD_READ_BYTES,
    }
}

/// The whole view of the test volume, read from `url` until done, failed or `limit`: whether
/// the source was seen not connected (with a problem) on the way, and its last status.
fn browse(url: &str, pacing: Pacing, limit: Duration) -> (bool, crate::source::SourceStatus, u64) {
    let spec = ViewSpec::single(View::new(0.3, 0.2, 32, 32));
    let (mut source, _) =
        RangeSource::open_paced(url, None, spec, RangeSourceOptions::default(), pacing).unwrap();
    let started = Instant::now();
    let (mut unreachable, mut packets) = (false, 0u64);
    loop {
        while source.try_next().is_some() {
            packets += 1;
        }
        let s = source.status();
        unreachable |= !s.connected && s.problem.is_some();
        if s.failed.is_some()
            || (s.done && source.try_next().is_none())
            || started.elapsed() > limit
        {
            return (unreachable, s, packets);
        }
        std::thread::sleep(Duration::from_millis(5));
    }
}

/// A server that answers 503 for longer than a request's attempts take (after the head) does
/// not end the browse: the source reports itself not connected, with the problem, waits and
/// asks again, and ends with every packet.
#[test]
fn an_outage_longer_than_the_attempts_does_not_end_the_browse() {
    let data = volume();
    let head_end = head_end(data);
    let from: OnceLock<Instant> = OnceLock::new();
    let stub = Stub::start(move |_, seen| {
        let packets = seen.range().is_some_and(|(a, _)| a >= head_end);
        let down =
            packets && from.get_or_init(Instant::now).elapsed() < Duration::from_millis(1500);
        if down {
            reply("503 Service Unavailable", &[], b"")
        } else {
            serve(data, seen, &[])
        }
    });
    let (unreachable, status, packets) = browse(
        &format!("{}/v.wspx", stub.base),
        QUICK,
        Duration::from_secs(60),
    );
    assert_eq!(status.failed, None);
    assert!(unreachable, "the outage was not reported: {status:?}");
    assert!(
        status.done && status.connected && status.problem.is_none() && status.reconnects >= 1,
        "{status:?}"
    );
    assert_eq!(packets, status.packets);
    assert!(packets > 0);
}

/// Credentials in the URL (a password, a presigned query) reach no message: not a head that
/// cannot be read, not a packet that does not decode.
#[test]
fn credentials_in_the_url_reach_no_message() {
    let mut altered = volume().to_vec();
    let at = altered.len() - 10;
    altered[at] ^= 0x5a;
    let files: Vec<(&str, Vec<u8>)> = vec![
        ("/garbage.wspx", vec![7u8; 300]),
        ("/altered.wspx", altered),
    ];
    let stub = Stub::start(move |_, seen| {
        let path = seen.target.split('?').next().unwrap_or_default();
        match files.iter().find(|(p, _)| *p == path) {
            Some((_, data)) => serve(data, seen, &[]),
            None => reply("404 Not Found", &[], b""),
        }
    });
    let secret = |file: &str| {
        stub.base.replacen("http://", "http://reader:hunter2@", 1)
            + file
            + "?X-Amz-Credential=AKIDEXAMPLE&X-Amz-Signature=0badc0ffee&token=opensesame"
    };
    let leaks = |m: &str| {
        ["hunter2", "0badc0ffee", "opensesame", "AKIDEXAMPLE"]
            .iter()
            .any(|s| m.contains(s))
    };
    let spec = ViewSpec::single(View::new(0.3, 0.2, 32, 32));
    let e = RangeSource::open(
        &secret("/garbage.wspx"),
        None,
        spec,
        RangeSourceOptions::default(),
    )
    .map(|_| ())
    .unwrap_err()
    .to_string();
    assert!(e.contains("garbage.wspx") && !leaks(&e), "{e}");
    let (_, status, _) = browse(&secret("/altered.wspx"), QUICK, Duration::from_secs(30));
    let failed = status.failed.expect("the altered packet is refused");
    assert!(
        failed.contains("altered.wspx") && !leaks(&failed),
        "{failed}"
    );
}

/// A file gone from the server while it is browsed (404) stops the source, saying so: only
/// what may pass is asked for again.
#[test]
fn a_file_gone_while_browsed_stops_the_source() {
    let data = volume();
    let head_end = head_end(data);
    let stub = Stub::start(move |_, seen| {
        if seen.range().is_some_and(|(a, _)| a < head_end) {
            serve(data, seen, &[])
        } else {
            reply("404 Not Found", &[], b"")
        }
    });
    let (_, status, _) = browse(
        &format!("{}/v.wspx", stub.base),
        QUICK,
        Duration::from_secs(30),
    );
    let failed = status.failed.expect("a 404 stops the source");
    assert!(failed.contains("404 Not Found"), "{failed}");
}
