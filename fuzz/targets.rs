//! The fuzz targets' bodies, shared by the cargo-fuzz binaries (`fuzz_targets/`) and the stable
//! test that replays the kept corpora (`tests/fuzz_corpus.rs`). Each takes arbitrary bytes and
//! must return (an `Err` is fine) without panicking, hanging or allocating beyond the decode
//! budget (packets, files) or [`alloc_bound`] (the readers, measured by the including crate's
//! `meter`, a counting global allocator: `fuzz/meter.rs` in the fuzz binaries).

// Each fuzz binary uses one target of this file.
#![allow(dead_code)]

use std::path::Path;
use wavesplat_codec::format::packet::{decode_packet_within, DecodeBudget};
use wavesplat_codec::format::{parse_file, parse_prelude, Header};
use wavesplat_compressor::reader::Format;

/// What one fuzz input may cost: a packet of at most 1 M coefficients (24 MiB).
pub const BUDGET: DecodeBudget = DecodeBudget {
    max_coefficients: 1 << 20,
    max_bytes: 64 << 20,
};

/// What one packet of a whole-file input may cost: 64 K coefficients (1.5 MiB), 128× what a
/// seed file's packet (one 8³ tile) holds. Every parse path is still reached (a packet over the
/// budget is refused at its header, as a larger budget would refuse a larger one), but a
/// mutated header can no longer make one execution decode a million coefficients, which kept
/// this target under 1 000 executions a second.
pub const FILE_BUDGET: DecodeBudget = DecodeBudget {
    max_coefficients: 1 << 16,
    max_bytes: 4 << 20,
};

/// A whole file: header, directory, every packet; or a container (bricked, version 9; a time
/// series, version 10): its manifest and the files it holds (at most 64, each as a plain file
/// or, in a series, a bricked container); or a published file (the indexed layout, versions 1
/// to 3): its head and index, and the file it fronts.
pub fn file(data: &[u8]) {
    let _ = wavesplat_codec::format::index::read_indexed_head(data);
    if let Ok(inner) = wavesplat_codec::format::index::wsp_of_indexed(data) {
        volume_file(inner);
    }
    volume_file(data);
}

fn volume_file(data: &[u8]) {
    plain_file(data);
    bricked_file(data);
    if let Ok(s) = wavesplat_codec::format::series::parse_series(data) {
        for c in 0..s.manifest.components.len().min(64) {
            if let Ok(component) = s.component_bytes(c) {
                plain_file(component);
                bricked_file(component);
            }
        }
    }
}

fn plain_file(data: &[u8]) {
    let _ = parse_prelude(data);
    if let Ok(f) = parse_file(data) {
        for p in &f.packets {
            let _ = decode_packet_within(&f.header, p, &FILE_BUDGET);
        }
    }
}

fn bricked_file(data: &[u8]) {
    if let Ok(b) = wavesplat_codec::format::bricked::parse_bricked(data) {
        for i in 0..b.manifest.bricks.len().min(64) {
            if let Ok(brick) = b.brick_bytes(i) {
                plain_file(brick);
            }
        }
    }
}

/// The header of a kept sample file (`corpus/headers/CODER.wsp`), parsed on first use: the
/// packet targets decode their inputs as packets of that file.
pub struct KeptHeader {
    bytes: &'static [u8],
    parsed: std::sync::OnceLock<Header>,
}

impl KeptHeader {
    /// The header of the file `bytes` (included at build time).
    pub const fn new(bytes: &'static [u8]) -> KeptHeader {
        KeptHeader {
            bytes,
            parsed: std::sync::OnceLock::new(),
        }
    }

    /// The parsed header.
    pub fn get(&self) -> &Header {
        self.parsed.get_or_init(|| {
            parse_file(self.bytes)
                .expect("the kept sample file parses")
                .header
        })
    }
}

/// One packet against a fixed header. Its last four bytes are replaced by the CRC-32 of the
/// rest, so that mutated inputs reach the decoder instead of stopping at the checksum (which
/// the codec's own tests cover).
pub fn packet(header: &Header, data: &[u8]) {
    let mut p = data.to_vec();
    if p.len() >= 4 {
        let body = p.len() - 4;
        let crc = crc32fast::hash(&p[..body]).to_le_bytes();
        p[body..].copy_from_slice(&crc);
    }
    let _ = decode_packet_within(header, &p, &BUDGET);
}

/// A raw volume: the first 8 bytes choose the layout (dims 1..=64, dtype, endianness,
/// channels), the rest are the samples.
pub fn raw(data: &[u8]) {
    if data.len() < 8 {
        return;
    }
    metered(data, || raw_layout(data));
}

fn raw_layout(data: &[u8]) {
    use wavesplat_compressor::reader::{decode_raw, Endian, RawDtype, RawSpec};
    let dims = [0, 1, 2].map(|a| 1 + (data[a] as usize % 64));
    let dtype = [RawDtype::U8, RawDtype::U16, RawDtype::I16, RawDtype::F32][data[3] as usize % 4];
    let mut spec = RawSpec::new(dims, dtype);
    spec.endian = if data[4] & 1 == 0 {
        Endian::Little
    } else {
        Endian::Big
    };
    spec.channels = if data[5] & 1 == 0 { 1 } else { 3 };
    let _ = decode_raw(&data[8..], &spec);
}

/// A NIfTI-1 file (plain or gzip), decoded from memory as `read_nifti` decodes a file's bytes.
pub fn nifti(data: &[u8]) {
    metered(data, || {
        let _ = wavesplat_compressor::reader::nifti::decode_nifti(Path::new("fuzz.nii"), data);
    });
}

/// A DICOM volume: one file (a slice or a multi-frame file), or a bundle of a series' slices
/// (`SourceFiles::to_bytes`), decoded from memory as `read_volume` decodes what it gathered.
///
/// The reader catches panics inside the DICOM crates and reports them as errors (dicom-rs's
/// RLE adapter indexes out of bounds on some malformed segment tables: corpus
/// `caught_rle_panic`). libFuzzer's panic hook aborts on every panic, caught or not, so while
/// this target runs, panics on its thread are not passed to the hook; one that escapes the
/// reader still fails the run (the fuzz macro aborts on it, the stable replay's test fails).
pub fn dicom(data: &[u8]) {
    use std::cell::Cell;
    thread_local!(static QUIET: Cell<bool> = const { Cell::new(false) });
    static HOOK: std::sync::Once = std::sync::Once::new();
    HOOK.call_once(|| {
        let previous = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            if !QUIET.with(Cell::get) {
                previous(info);
            }
        }));
    });
    QUIET.with(|q| q.set(true));
    source(data, "series", Format::Dicom);
    QUIET.with(|q| q.set(false));
}

/// An NRRD volume: an attached `.nrrd`, or a bundle of a detached header and its data file.
pub fn nrrd(data: &[u8]) {
    source(data, "fuzz.nhdr", Format::Nrrd);
}

/// A MetaImage volume: an attached `.mha`, or a bundle of a `.mhd` header and its data file.
pub fn metaimage(data: &[u8]) {
    source(data, "fuzz.mhd", Format::MetaImage);
}

/// A TIFF stack: a multi-page `.tif`, or a bundle of the slices of a stack directory; read
/// whole, then with a channel chosen (by the input's last byte) of channels stored as planes.
pub fn tiff(data: &[u8]) {
    source(data, "fuzz.tif", Format::Tiff);
    use wavesplat_compressor::reader::{decode_source_channel, SourceFiles};
    let channel = usize::from(data.last().copied().unwrap_or(0) % 4);
    metered(data, || {
        if let Ok(mut src) = SourceFiles::from_bytes(data.to_vec(), Path::new("fuzz.tif")) {
            src.format = Some(Format::Tiff);
            let _ = decode_source_channel(&src, None, Some(channel));
        }
    });
}

/// A Zarr store: a bundle of its files (metadata, chunks). A store may declare far more than
/// its bytes hold (a missing chunk is its fill value), so the heap is bounded by
/// [`alloc_bound`] plus what its metadata declares (`zarr::declared_bytes`); a store declaring
/// more than 64 MiB is decoded no further than its metadata (slow executions teach the fuzzer
/// nothing a small declaration does not). Decoded as a whole, then with a channel chosen.
pub fn zarr(data: &[u8]) {
    use wavesplat_compressor::reader::{decode_source, decode_source_channel, zarr, SourceFiles};
    let Ok(mut src) = SourceFiles::from_bytes(data.to_vec(), Path::new("fuzz.zarr")) else {
        return;
    };
    src.format = Some(Format::Zarr);
    let mut declared = 0;
    metered(data, || declared = zarr::declared_bytes(&src).unwrap_or(0));
    if declared > 64 << 20 {
        return;
    }
    let bound = alloc_bound(data.len()) + 2 * declared as usize;
    metered_within(data, bound, || {
        let _ = decode_source(&src, None);
    });
    // A channel chosen (by the input's last byte) of a store of several, as a job reads it.
    let channel = usize::from(data.last().copied().unwrap_or(0) % 4);
    metered_within(data, bound, || {
        let _ = decode_source_channel(&src, None, Some(channel));
    });
}

fn source(data: &[u8], origin: &str, format: Format) {
    use wavesplat_compressor::reader::{decode_source, SourceFiles};
    metered(data, || {
        if let Ok(mut src) = SourceFiles::from_bytes(data.to_vec(), Path::new(origin)) {
            src.format = Some(format);
            let _ = decode_source(&src, None);
        }
    });
}

/// Most heap a reader may hold at once for an input of `len` bytes: 16 MiB plus 8 KiB per
/// input byte. Decoded samples come to at most ~1032× the input (deflate's limit, which also
/// bounds DICOM's Deflated syntax; encapsulated DICOM frames are held to 1024× + 1 MiB), kept
/// once as bytes and once as f32 (4 bytes per 8-bit sample): ~5.2 K per input byte, the rest
/// is room for the parsers' working buffers. A header declaring more than its bytes can hold
/// must be refused before anything that large is allocated.
pub fn alloc_bound(len: usize) -> usize {
    (16 << 20) + 8192 * len
}

/// Runs a reader on `data` and checks its peak heap against [`alloc_bound`].
fn metered(data: &[u8], f: impl FnOnce()) {
    metered_within(data, alloc_bound(data.len()), f);
}

/// Runs a reader on `data` and checks its peak heap against `bound`.
fn metered_within(data: &[u8], bound: usize, f: impl FnOnce()) {
    let peak = crate::meter::peak_during(f);
    assert!(
        peak <= bound,
        "a {}-byte input took {peak} bytes of heap (bound {bound})",
        data.len()
    );
}

/// Every request message of both services, decoded from the same bytes and converted to the
/// domain types the handlers use.
pub fn grpc(data: &[u8]) {
    use prost::Message;
    use wavesplat_proto::pb;
    if let Ok(m) = pb::IngestRequest::decode(data) {
        if let Some(pb::ingest_request::Msg::Start(s)) = m.msg {
            let _ = wavesplat_cache::convert::sha256(&s.sha256);
            let _ = wavesplat_cache::store::validate_name(&s.name);
        }
    }
    for r in [
        pb::DescribeRequest::decode(data).ok().map(|m| m.volume),
        pb::DeleteRequest::decode(data).ok().map(|m| m.volume),
    ]
    .into_iter()
    .flatten()
    {
        let _ = wavesplat_cache::convert::volume_key(r);
    }
    let _ = pb::ListRequest::decode(data);
    if let Ok(m) = pb::FirstPacketsRequest::decode(data) {
        let _ = wavesplat_cache::convert::volume_key(m.volume);
    }
    if let Ok(m) = pb::RefineRequest::decode(data) {
        match m.msg {
            Some(pb::refine_request::Msg::Start(s)) => {
                let _ = wavesplat_cache::convert::volume_key(s.volume);
                let _ = wavesplat_cache::convert::view_spec(s.view);
            }
            Some(pb::refine_request::Msg::View(v)) => {
                let _ = wavesplat_cache::convert::view_spec(Some(v));
            }
            _ => {}
        }
    }
    if let Ok(m) = pb::SubmitRequest::decode(data) {
        if let Some(pb::submit_request::Msg::Spec(s)) = m.msg {
            if let Ok(spec) = wavesplat_orchestrator_client::convert::spec_from_pb(s) {
                let _ = spec.validate();
            }
        }
    }
    let _ = pb::ListJobsRequest::decode(data);
    let _ = pb::JobRef::decode(data);
    let _ = pb::LeaseRequest::decode(data);
    let _ = pb::HeartbeatRequest::decode(data);
    if let Ok(m) = pb::FinishRequest::decode(data) {
        let _ = wavesplat_orchestrator_client::convert::outcome_from_pb(m.outcome);
    }
    let _ = pb::FetchSourceRequest::decode(data);
}
