//! Whole files: writing a header section, packet directory and packets (in the current or an
//! older version), and reading them back, either from a complete file ([`parse_file`]) or from
//! the start of one as it arrives ([`parse_prelude`]).

use super::bytes::{ByteReader, ByteWriter};
use super::header::{
    check_version, header_length, read_header_section, write_header_section,
    write_header_section_version,
};
use super::{
    invalid, CoderKind, FormatError, Header, COARSE_LAYER_VERSION, COMPACT_HEADER_VERSION,
    FAST_CODER_VERSION, FAST_CONTEXTS_VERSION, MAGIC, MAGNITUDE_CONTEXTS_VERSION, MAX_PACKET_BYTES,
    PRIORS_VERSION, RANS_VERSION,
};

/// A parsed file: the header and the location of each packet.
#[derive(Debug, Clone)]
pub struct WspFile<'a> {
    /// The header.
    pub header: Header,
    /// Bytes of the header section (magic to header CRC), for size reports.
    pub header_bytes: usize,
    /// Bytes of the packet directory.
    pub directory_bytes: usize,
    /// Each packet's bytes, in file order.
    pub packets: Vec<&'a [u8]>,
}

/// Checks that a whole file's packets, holding `held` coefficients in all, hold what the header
/// declares (`Header::kept`).
pub fn check_kept(header: &Header, held: u64) -> Result<(), FormatError> {
    if held == header.kept {
        return Ok(());
    }
    Err(invalid(
        "file",
        format!(
            "the header declares {} kept coefficients but the packets hold {held}{}",
            header.kept,
            if held < header.kept {
                " (packets are missing)"
            } else {
                ""
            }
        ),
    ))
}

/// Writes a whole file from a header and encoded packets (see
/// [`packet::encode_packets`](super::packet::encode_packets)).
pub fn write_file(header: &Header, packets: &[Vec<u8>]) -> Vec<u8> {
    write_file_body(write_header_section(header), packets)
}

/// Writes a whole file in an older version of the format, for readers that have not been
/// updated. Refuses what that version cannot hold (a placement before version 4, an intensity
/// offset before version 5) rather than dropping it.
pub fn write_file_version(
    header: &Header,
    packets: &[Vec<u8>],
    version: u16,
) -> Result<Vec<u8>, FormatError> {
    check_version(version)?;
    if version < 4 && header.placement.is_some() {
        return Err(invalid(
            "header",
            format!("format version {version} cannot hold the volume's placement"),
        ));
    }
    if header.coder == CoderKind::Sigmap
        && (version >= MAGNITUDE_CONTEXTS_VERSION) != (header.version >= MAGNITUDE_CONTEXTS_VERSION)
    {
        return Err(invalid(
            "header",
            format!(
                "sigmap packets coded for format version {} do not decode as version {version} \
                 (the magnitude contexts differ): encode them with that version",
                header.version
            ),
        ));
    }
    if version < FAST_CODER_VERSION && header.coder == CoderKind::Fast {
        return Err(invalid(
            "header",
            format!("format version {version} has no fast coder"),
        ));
    }
    if header.coder == CoderKind::Fast
        && header
            .fast_tables
            .as_ref()
            .is_some_and(|t| !t.decode_as(version))
    {
        return Err(invalid(
            "header",
            format!(
                "fast-coder packets coded for format version {} do not decode as version \
                 {version} (version {RANS_VERSION} codes them by rANS, version \
                 {FAST_CONTEXTS_VERSION} codes occupancy with the face contexts): encode them \
                 with that version",
                header.version
            ),
        ));
    }
    if version < COARSE_LAYER_VERSION && header.coarse_layer {
        return Err(invalid(
            "header",
            format!(
                "format version {version} has no coarse layer: compress with --no-coarse-layer"
            ),
        ));
    }
    if version < 5 && header.channels == 1 && header.color.mean[0] != 0.0 {
        return Err(invalid(
            "header",
            format!("format version {version} cannot hold an intensity offset"),
        ));
    }
    if header.coder == CoderKind::Sigmap
        && (version >= PRIORS_VERSION) != (header.version >= PRIORS_VERSION)
    {
        return Err(invalid(
            "header",
            format!(
                "sigmap packets coded for format version {} do not decode as version {version} \
                 (version {PRIORS_VERSION} starts their models from trained priors): encode them \
                 with that version",
                header.version
            ),
        ));
    }
    if version < COMPACT_HEADER_VERSION
        && header
            .substreams
            .iter()
            .flatten()
            .any(|s| !s.w0.is_finite())
    {
        return Err(invalid(
            "header",
            format!(
                "format version {version} sends every substream's largest magnitude, and this \
                 file's packets were quantized without some (version \
                 {COMPACT_HEADER_VERSION}): compress with --format-version {version}"
            ),
        ));
    }
    Ok(write_file_body(
        write_header_section_version(header, version),
        packets,
    ))
}

fn write_file_body(header_section: Vec<u8>, packets: &[Vec<u8>]) -> Vec<u8> {
    let mut out = header_section;
    let mut d = ByteWriter::new();
    d.varint(packets.len() as u64);
    for p in packets {
        d.varint(p.len() as u64);
    }
    let db = d.into_bytes();
    out.extend_from_slice(&db);
    out.extend_from_slice(&crc32fast::hash(&db).to_le_bytes());
    for p in packets {
        out.extend_from_slice(p);
    }
    out
}

/// What precedes a file's packets: the header section and the packet directory.
#[derive(Debug, Clone)]
pub struct Prelude {
    /// The header.
    pub header: Header,
    /// Bytes of the header section (magic to header CRC).
    pub header_bytes: usize,
    /// Bytes of the packet directory (with its CRC).
    pub directory_bytes: usize,
    /// Each packet's length, in file order.
    pub packet_lengths: Vec<usize>,
}

impl Prelude {
    /// Bytes before the first packet.
    pub fn len(&self) -> usize {
        self.header_bytes + self.directory_bytes
    }

    /// Whether the prelude is empty (never: a header section has at least 14 bytes).
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Size of the whole file the directory describes.
    pub fn file_bytes(&self) -> u64 {
        self.len() as u64 + self.packet_lengths.iter().map(|&l| l as u64).sum::<u64>()
    }
}

/// Parses the header section and the packet directory from the start of a file as it arrives:
/// `Ok(None)` means the bytes end before the directory does (call again with more); an error is
/// final, and comes as early as the bytes allow (wrong magic after 1 byte, an oversized header
/// length after 10).
pub fn parse_prelude(bytes: &[u8]) -> Result<Option<Prelude>, FormatError> {
    let n = bytes.len().min(MAGIC.len());
    if bytes[..n] != MAGIC[..n] {
        return Err(FormatError::BadMagic(bytes[..n].to_vec()));
    }
    if bytes.len() < 10 {
        return Ok(None);
    }
    let mut r = ByteReader::new(&bytes[4..10], "file header");
    let version = r.u16()?;
    check_version(version)?;
    let len = header_length(r.u32()?)?;
    if bytes.len() < 14 + len {
        return Ok(None);
    }
    let (header, header_bytes) = read_header_section(&bytes[..14 + len])?;
    match read_directory(&header, &bytes[header_bytes..]) {
        Ok((packet_lengths, directory_bytes)) => Ok(Some(Prelude {
            header,
            header_bytes,
            directory_bytes,
            packet_lengths,
        })),
        // The directory is read to its end: running out of bytes means "more to come".
        Err(FormatError::Truncated { .. }) => Ok(None),
        Err(e) => Err(e),
    }
}

/// Reads the packet directory at the start of `rest`: the packet lengths and the directory's
/// size with its CRC.
fn read_directory(header: &Header, rest: &[u8]) -> Result<(Vec<usize>, usize), FormatError> {
    let mut r = ByteReader::new(rest, "packet directory");
    let max_packets = header.tile_count() as u64 * header.layer_bounds.len() as u64;
    let count = r.varint_max(max_packets, "packet count")? as usize;
    // Each directory entry takes at least one byte: bound the allocation by the input.
    if count > r.remaining() {
        return Err(FormatError::Truncated {
            what: "packet directory",
            needed: count as u64,
            available: r.remaining() as u64,
        });
    }
    let mut lens = Vec::with_capacity(count);
    for _ in 0..count {
        lens.push(r.varint_max(MAX_PACKET_BYTES as u64, "packet length")? as usize);
    }
    let dir_len = r.position();
    let stored = r.u32()?;
    let computed = crc32fast::hash(&rest[..dir_len]);
    if stored != computed {
        return Err(FormatError::Checksum {
            what: "packet directory",
            stored,
            computed,
        });
    }
    Ok((lens, dir_len + 4))
}

/// Parses a file's header and packet directory (packets are checked when decoded).
pub fn parse_file(bytes: &[u8]) -> Result<WspFile<'_>, FormatError> {
    let (header, used) = read_header_section(bytes)?;
    let (lens, directory_bytes) = read_directory(&header, &bytes[used..])?;
    let mut r = ByteReader::new(&bytes[used + directory_bytes..], "packets");
    let mut packets = Vec::with_capacity(lens.len());
    for len in lens {
        packets.push(r.take(len)?);
    }
    if r.remaining() != 0 {
        return Err(invalid(
            "file",
            format!("{} trailing bytes after the last packet", r.remaining()),
        ));
    }
    Ok(WspFile {
        header,
        header_bytes: used,
        directory_bytes,
        packets,
    })
}
