//! The fuzz targets' bodies, shared by the cargo-fuzz binaries (`fuzz_targets/`) and the stable
//! test that replays the kept corpora (`tests/fuzz_corpus.rs`). Each takes arbitrary bytes and
//! must return (an `Err` is fine) without panicking, hanging or allocating beyond the decode
//! budget.

use wavesplat_codec::format::packet::{decode_packet_within, DecodeBudget};
use wavesplat_codec::format::{parse_file, parse_prelude, Header};

/// What one fuzz input may cost: a packet of at most 1 M coefficients (24 MiB).
pub const BUDGET: DecodeBudget = DecodeBudget {
    max_coefficients: 1 << 20,
    max_bytes: 64 << 20,
};

/// A whole file: header, directory, every packet.
pub fn file(data: &[u8]) {
    let _ = parse_prelude(data);
    if let Ok(f) = parse_file(data) {
        for p in &f.packets {
            let _ = decode_packet_within(&f.header, p, &BUDGET);
        }
    }
}

/// One packet against a fixed header.
pub fn packet(header: &Header, data: &[u8]) {
    let _ = decode_packet_within(header, data, &BUDGET);
}

/// A raw volume: the first 8 bytes choose the layout (dims 1..=64, dtype, endianness,
/// channels), the rest are the samples.
pub fn raw(data: &[u8]) {
    use wavesplat_compressor::reader::{decode_raw, Endian, RawDtype, RawSpec};
    if data.len() < 8 {
        return;
    }
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

/// A NIfTI-1 file (plain or gzip), through the reader's path interface.
pub fn nifti(data: &[u8]) {
    let Ok(mut f) = tempfile::Builder::new().suffix(".nii").tempfile() else {
        return;
    };
    if std::io::Write::write_all(&mut f, data).is_ok() {
        let _ = wavesplat_compressor::reader::read_nifti(f.path());
    }
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
            if let Ok(spec) = wavesplat_orchestrator::convert::spec_from_pb(s) {
                let _ = spec.validate();
            }
        }
    }
    let _ = pb::ListJobsRequest::decode(data);
    let _ = pb::JobRef::decode(data);
    let _ = pb::LeaseRequest::decode(data);
    let _ = pb::HeartbeatRequest::decode(data);
    if let Ok(m) = pb::FinishRequest::decode(data) {
        let _ = wavesplat_orchestrator::convert::outcome_from_pb(m.outcome);
    }
    let _ = pb::FetchSourceRequest::decode(data);
}
