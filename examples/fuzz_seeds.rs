//! Writes the seed corpora of the fuzz targets (`fuzz/corpus/TARGET/`) and the sample files the
//! packet targets decode against (`fuzz/corpus/headers/CODER.wsp`): small phantoms compressed
//! with each coder, their packets, raw and NIfTI volumes, and one message of every gRPC request.
//! The corpora are kept in the repository; rerun this only to reseed.
//!
//! `cargo run --example fuzz_seeds`

use prost::Message;
use std::path::Path;
use wavesplat_codec::format::{parse_file, CoderKind};
use wavesplat_compressor::encode::{compress, CompressOptions, Target, TileChoice};
use wavesplat_compressor::phantom::Phantom;
use wavesplat_proto::pb;

fn put(dir: &Path, name: &str, bytes: &[u8]) {
    std::fs::create_dir_all(dir).unwrap();
    std::fs::write(dir.join(name), bytes).unwrap();
}

fn main() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz/corpus");
    for (coder, name) in [
        (CoderKind::Sigmap, "sigmap"),
        (CoderKind::Range, "range"),
        (CoderKind::Huffman, "huffman"),
    ] {
        let vol = Phantom::SheppLogan.generate([12, 10, 8]);
        let bytes = compress(
            &vol,
            &CompressOptions {
                coder,
                target: Target::Fraction(0.2),
                tile: TileChoice::Size(8),
                layers: Some(2),
                levels: Some(2),
                refine: None,
                ..Default::default()
            },
            &|_, _| {},
        )
        .unwrap()
        .bytes;
        put(&root.join("headers"), &format!("{name}.wsp"), &bytes);
        put(&root.join("file"), &format!("{name}.wsp"), &bytes);
        let f = parse_file(&bytes).unwrap();
        for (i, p) in f.packets.iter().enumerate().take(4) {
            put(&root.join(format!("packet_{name}")), &format!("p{i}"), p);
        }
    }
    let mut raw = vec![7u8, 5, 3, 1, 0, 0, 0, 0];
    raw.extend((0..8 * 6 * 4 * 2).map(|i| (i * 37 % 251) as u8));
    put(&root.join("raw"), "u16", &raw);
    // A minimal NIfTI-1 file: 348-byte header, 4 bytes of extension flag, 2x2x2 u8 samples.
    let mut nii = vec![0u8; 352];
    nii[0..4].copy_from_slice(&348i32.to_le_bytes());
    for (i, d) in [3i16, 2, 2, 2, 1, 1, 1, 1].iter().enumerate() {
        nii[40 + 2 * i..42 + 2 * i].copy_from_slice(&d.to_le_bytes());
    }
    nii[70..72].copy_from_slice(&2i16.to_le_bytes()); // datatype: u8
    nii[72..74].copy_from_slice(&8i16.to_le_bytes()); // bitpix
    for (i, p) in [1f32, 1.0, 1.0, 1.0].iter().enumerate() {
        nii[76 + 4 * i..80 + 4 * i].copy_from_slice(&p.to_le_bytes());
    }
    nii[108..112].copy_from_slice(&352f32.to_le_bytes()); // vox_offset
    nii[344..348].copy_from_slice(b"n+1\0");
    nii.extend([1u8, 2, 3, 4, 5, 6, 7, 8]);
    put(&root.join("nifti"), "tiny.nii", &nii);
    let grpc = root.join("grpc");
    let view = pb::ViewSpec {
        alpha: 0.3,
        beta: 0.2,
        width: 64,
        height: 64,
        ..Default::default()
    };
    let volume = Some(pb::VolumeRef {
        key: Some(pb::volume_ref::Key::Name("head".into())),
    });
    put(
        &grpc,
        "refine_start",
        &pb::RefineRequest {
            msg: Some(pb::refine_request::Msg::Start(pb::RefineStart {
                volume: volume.clone(),
                view: Some(view),
                have: vec![1, 2, 3],
                have_header: true,
                credit_bytes: 1 << 16,
                visible_only: true,
            })),
        }
        .encode_to_vec(),
    );
    put(
        &grpc,
        "ingest_start",
        &pb::IngestRequest {
            msg: Some(pb::ingest_request::Msg::Start(pb::IngestStart {
                name: "head".into(),
                total_size: 1000,
                sha256: vec![1; 32],
            })),
        }
        .encode_to_vec(),
    );
    put(
        &grpc,
        "describe",
        &pb::DescribeRequest { volume }.encode_to_vec(),
    );
    put(
        &grpc,
        "submit_spec",
        &pb::SubmitRequest {
            msg: Some(pb::submit_request::Msg::Spec(pb::JobSpec {
                name: "ct/head".into(),
                source: Some(pb::job_spec::Source::Path("/data/ct/head.nii".into())),
                sha256: vec![2; 32],
                raw: Some(pb::RawLayout {
                    dims: vec![4, 4, 4],
                    dtype: "u16".into(),
                    big_endian: true,
                    channels: 1,
                }),
                options: Some(pb::CompressOptions {
                    family: "cubic".into(),
                    ..Default::default()
                }),
            })),
        }
        .encode_to_vec(),
    );
    put(
        &grpc,
        "finish",
        &pb::FinishRequest {
            job_id: 3,
            attempt: 1,
            worker: "w".into(),
            outcome: Some(pb::finish_request::Outcome::Delivered(pb::Delivered {
                cache_volume_id: 9,
                output_bytes: 100,
                voxels: 64,
                existed: false,
                sha256: "ab".repeat(32),
            })),
        }
        .encode_to_vec(),
    );
    println!("seeds written under {}", root.display());
}
