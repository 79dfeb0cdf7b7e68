//! How services and clients identify content: the SHA-256 of a volume's bytes (a source in the
//! job queue, a `.wsp` in the cache) and its lowercase hex form in logs, messages and object
//! names. Hex through the `hex` crate.

use sha2::{Digest, Sha256};

/// SHA-256 of `bytes`.
pub fn sha256(bytes: &[u8]) -> [u8; 32] {
    Sha256::digest(bytes).into()
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

/// SHA-256 of bytes given piece by piece, as they arrive (a source streamed to a file).
#[derive(Default)]
pub struct Sha256Pieces(Sha256);

impl Sha256Pieces {
    /// Adds the next piece.
    pub fn update(&mut self, piece: &[u8]) {
        self.0.update(piece);
    }

    /// The digest of all pieces, in order.
    pub fn finish(self) -> [u8; 32] {
        self.0.finalize().into()
    }
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
    fn a_file_streamed_in_pieces_hashes_as_its_bytes_do() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("f");
        let bytes: Vec<u8> = (0..(3 << 20) + 17).map(|i| (i * 7 % 251) as u8).collect();
        std::fs::write(&path, &bytes).unwrap();
        let streamed = |p: &std::path::Path| {
            sha256_stream(|w| std::io::copy(&mut std::fs::File::open(p)?, w).map(|_| ()))
        };
        assert_eq!(streamed(&path).unwrap(), sha256(&bytes));
        assert!(streamed(&dir.path().join("missing")).is_err());
        let mut pieces = Sha256Pieces::default();
        for piece in bytes.chunks(65_521) {
            pieces.update(piece);
        }
        assert_eq!(pieces.finish(), sha256(&bytes));
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
