//! The caller's deadline: gRPC sends it as the `grpc-timeout` header (`<digits><unit>`, unit
//! `H`, `M`, `S`, `m`, `u` or `n`); a handler that does slow work after reading the request
//! (validating an upload) checks it before committing, so a request whose deadline passed
//! changes nothing.

use std::time::{Duration, Instant};
use tonic::metadata::MetadataMap;

/// Parses a `grpc-timeout` value.
pub fn parse_timeout(v: &str) -> Option<Duration> {
    if v.len() < 2 || v.len() > 9 {
        return None;
    }
    let (digits, unit) = v.split_at(v.len() - 1);
    if !digits.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    let n: u64 = digits.parse().ok()?;
    Some(match unit {
        "H" => Duration::from_secs(n.checked_mul(3600)?),
        "M" => Duration::from_secs(n.checked_mul(60)?),
        "S" => Duration::from_secs(n),
        "m" => Duration::from_millis(n),
        "u" => Duration::from_micros(n),
        "n" => Duration::from_nanos(n),
        _ => return None,
    })
}

/// The deadline of a request received now (`None`: the caller set none, or sent nonsense).
pub fn request_deadline(metadata: &MetadataMap) -> Option<Instant> {
    let v = metadata.get("grpc-timeout")?.to_str().ok()?;
    Instant::now().checked_add(parse_timeout(v)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn timeouts_parse_in_every_unit_and_nonsense_is_ignored() {
        assert_eq!(parse_timeout("2H"), Some(Duration::from_secs(7200)));
        assert_eq!(parse_timeout("3M"), Some(Duration::from_secs(180)));
        assert_eq!(parse_timeout("5S"), Some(Duration::from_secs(5)));
        assert_eq!(parse_timeout("250m"), Some(Duration::from_millis(250)));
        assert_eq!(parse_timeout("7u"), Some(Duration::from_micros(7)));
        assert_eq!(parse_timeout("9n"), Some(Duration::from_nanos(9)));
        for bad in ["", "S", "5", "5x", "-5S", "1234567890S", "5 S"] {
            assert_eq!(parse_timeout(bad), None, "{bad:?}");
        }
        let mut m = MetadataMap::new();
        assert!(request_deadline(&m).is_none());
        m.insert("grpc-timeout", "100m".parse().unwrap());
        let d = request_deadline(&m).unwrap();
        assert!(d > Instant::now());
    }
}
