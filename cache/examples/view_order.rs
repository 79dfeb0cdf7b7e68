//! Q_I against bytes for the cache's view-dependent packet order versus the file's global
//! significance order, offline (same ranking code as the server, no network). Uses the real
//! MNI volume when given, else a phantom.
//!
//! `cargo run --release -p wavesplat-cache --example view_order -- [VOLUME.nii.gz] > out.csv`

use wavesplat_cache::model::PacketMeta;
use wavesplat_cache::Priority;
use wavesplat_codec::format::packet::{decode_packet, Coefficient};
use wavesplat_codec::format::parse_file;
use wavesplat_codec::metrics::q_i_paper_db;
use wavesplat_codec::view::ViewSpec;
use wavesplat_compressor::encode::{compress, CompressOptions, Target, TileChoice};
use wavesplat_compressor::phantom::Phantom;
use wavesplat_compressor::reader::read_volume;
use wavesplat_viewer::{RenderOptions, Renderer, View};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let volume = match std::env::args().nth(1) {
        Some(p) => read_volume(std::path::Path::new(&p), None)?,
        None => Phantom::SheppLogan.generate([96, 96, 96]),
    };
    let c = compress(
        &volume,
        &CompressOptions {
            target: Target::Fraction(0.02),
            tile: TileChoice::Size(32),
            layers: Some(4),
            ..Default::default()
        },
        &|_, _| {},
    )?;
    let file = parse_file(&c.bytes)?;
    let h = &file.header;
    let decoded: Vec<_> = file
        .packets
        .iter()
        .map(|p| decode_packet(h, p))
        .collect::<Result<_, _>>()?;
    let metas: Vec<PacketMeta> = decoded
        .iter()
        .zip(&file.packets)
        .map(|(d, p)| PacketMeta {
            tile: d.tile as u32,
            layer: d.layer as u32,
            len: p.len() as u32,
            offset: 0,
            summary: d.summary.clone(),
        })
        .collect();
    let all: Vec<Coefficient> = decoded
        .iter()
        .flat_map(|d| d.coefficients.clone())
        .collect();
    let total: usize = file.packets.iter().map(|p| p.len()).sum();
    let d = h.geometry.dims;
    let fit = 256.0 / ((d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) as f64).sqrt();
    let views = [
        ("axis-aligned", View::new(0.0, 0.0, 256, 256)),
        ("oblique", View::new(0.66, 0.91, 256, 256)),
        (
            "zoomed-corner",
            View::new(0.0, 0.0, 256, 256)
                .with_zoom(4.0 * fit)
                .with_pan([-(d[1] as f64) / 3.0, d[2] as f64 / 3.0]),
        ),
    ];
    println!("view,order,fraction_of_bytes,bytes,q_i_paper_db");
    let mut renderer = Renderer::new(RenderOptions::default());
    for (name, view) in views {
        let reference = renderer.render(&all, &h.geometry, &view)?.data;
        let spec = ViewSpec {
            view,
            multiview: false,
        };
        let dependent: Vec<usize> = Priority::new(h, &spec)?
            .order(&metas)
            .into_iter()
            .map(|i| i as usize)
            .collect();
        let global: Vec<usize> = (0..metas.len()).collect();
        for (label, order) in [("view-dependent", &dependent), ("global", &global)] {
            for frac in [0.02, 0.05, 0.1, 0.25, 0.5] {
                let budget = (frac * total as f64) as usize;
                let mut used = 0;
                let mut coeffs = Vec::new();
                for &i in order {
                    if used + file.packets[i].len() > budget {
                        continue;
                    }
                    used += file.packets[i].len();
                    coeffs.extend_from_slice(&decoded[i].coefficients);
                }
                let img = renderer.render(&coeffs, &h.geometry, &view)?;
                let q = q_i_paper_db(&reference, &img.data);
                println!("{name},{label},{frac},{used},{q:.3}");
            }
        }
    }
    Ok(())
}
