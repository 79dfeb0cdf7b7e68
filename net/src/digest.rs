//! How services and clients identify content: the SHA-256 of a volume's bytes (a source in the
//! job queue, a `.wsp` in the cache) and its lowercase hex form in logs, messages and object
//! names. Hex through the `hex` crate.

use sha2::{Digest, Sha256};

/// SHA-256 of `bytes`.
pub fn sha256(bytes: &[u8]) -> [u8; 32] {
    Sha256::digest(bytes).into()
}

/// SHA-256 of the file at `path`, read in pieces of 1 MiB (never whole in memory).
pub fn sha256_file(path: &std::path::Path) -> std::io::Result<[u8; 32]> {
    use std::io::Read;
    let mut file = std::fs::File::open(path)?;
    let mut hasher = Sha256::new();
    let mut buf = vec![0u8; 1 << 20];
    loop {
        match file.read(&mut buf) {
            Ok(0) => return Ok(hasher.finalize().into()),
            Ok(n) => hasher.update(&buf[..n]),
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
}

/// SHA-256 of whatever `write` writes to the writer it is given (bytes streamed from several
/// files, say), never held.
pub fn sha256_stream<E>(
    write: impl FnOnce(&mut dyn std::io::Write) -> Result<(), E>,
) -> Result<[u8; 32], E> {
    let mut hasher = Sha256::new();
    write(&mut hasher)?;
    Ok(hasher.finalize().into())
}

/// Lowercase hex of `bytes`.
pub fn hex(bytes: &[u8]) -> String {
    hex::encode(bytes)
}

/// The bytes of hex text `s` (either case); `None` when it is not an even number of hex digits.
pub fn unhex(s: &str) -> Option<Vec<u8>> {
    hex::decode(s).ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_file_hashes_in_pieces_as_its_bytes_do() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("f");
        let bytes: Vec<u8> = (0..(3 << 20) + 17).map(|i| (i * 7 % 251) as u8).collect();
        std::fs::write(&path, &bytes).unwrap();
        assert_eq!(sha256_file(&path).unwrap(), sha256(&bytes));
        assert!(sha256_file(&dir.path().join("missing")).is_err());
    }

    #[test]
    fn the_digest_of_nothing_is_the_known_one_and_hex_round_trips() {
        assert_eq!(
            hex(&sha256(b"")),
            "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855"
        );
        assert_eq!(unhex(&hex(b"a/b c")).unwrap(), b"a/b c");
        assert_eq!(unhex("0A0b").unwrap(), vec![10, 11]);
        assert!(unhex("abc").is_none());
        assert!(unhex("zz").is_none());
    }
}
