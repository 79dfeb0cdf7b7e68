//! A bricked volume renders like the whole: against the unbricked file's image of the same
//! coefficients budget, and against the reference ray caster of the original volume, in
//! oblique, axis and near-axis views, panned and zoomed, multiview and depth-cued; a view that
//! sees one brick draws no other.

mod common;

use wavesplat_codec::family::Family;
use wavesplat_codec::layout::Geometry;
use wavesplat_codec::metrics::snr_db;
use wavesplat_codec::view::{Cue, CueDirection, View, ViewSpec};
use wavesplat_compressor::bricked::compress_bricked;
use wavesplat_compressor::encode::{compress, CompressOptions, Target};
use wavesplat_compressor::phantom::Phantom;
use wavesplat_viewer::bricked::draw_bricked_file;
use wavesplat_viewer::open::draw_whole_file;
use wavesplat_viewer::CpuBackend;

fn views() -> Vec<(&'static str, ViewSpec)> {
    let v = |a, b| View::new(a, b, 72, 64);
    let single = ViewSpec::single;
    vec![
        ("oblique", single(v(0.66, 0.91))),
        ("axis", single(v(0.0, 0.0))),
        ("near axis", single(v(0.003, -0.002))),
        ("from above", single(v(0.2, std::f64::consts::FRAC_PI_2))),
        (
            "zoomed and panned",
            single(v(0.4, 0.3).with_zoom(3.0).with_pan([-4.0, 3.0])),
        ),
        (
            "cued",
            single(v(0.66, 0.91).with_cue(Cue {
                k: 0.06,
                direction: CueDirection::View,
            })),
        ),
        (
            "cued from the side",
            single(v(0.3, 0.2).with_cue(Cue {
                k: 0.1,
                direction: CueDirection::Vector([0.8, -0.36, 0.48]),
            })),
        ),
        (
            "multiview",
            ViewSpec {
                view: v(0.4, 0.3),
                multiview: true,
            },
        ),
    ]
}

/// The fitting zoom of the whole, so that both files draw the same picture.
fn fitted(spec: &ViewSpec, g: &Geometry) -> ViewSpec {
    let mut s = *spec;
    if s.view.zoom.is_none() {
        let z = s
            .cameras(g)
            .unwrap()
            .iter()
            .map(|c| c.fitting_zoom(g))
            .fold(f64::INFINITY, f64::min);
        s.view.zoom = Some(z);
    }
    s
}

/// The SNR of the unbricked file's image and of the bricked file's against the reference ray
/// caster of `volume` (geometry `g`), for `spec` at the whole's fitting zoom.
fn whole_and_bricked_snr(
    volume: &wavesplat_codec::volume::Volume,
    g: &Geometry,
    spec: &ViewSpec,
    whole: &[u8],
    bricked: &[u8],
) -> (f64, f64) {
    let spec = fitted(spec, g);
    let w = draw_whole_file(whole, &spec, &mut CpuBackend::new()).unwrap();
    let b = draw_bricked_file(bricked, &spec, &mut CpuBackend::new()).unwrap();
    let truth = common::reference_image(volume, g, &spec);
    (
        snr_db(&truth.data, &w.image.data),
        snr_db(&truth.data, &b.image.data),
    )
}

/// Every coefficient of every brick against the reference ray caster of the original volume:
/// the bricks' images, moved into place, cut at their faces and cue-scaled, add up to the
/// whole's line integrals in every kind of view, as closely as the unbricked file of every
/// coefficient does (within 1 dB, or above 50 dB; a misplaced brick or a wrong cue scale costs
/// tens of dB).
#[test]
fn every_coefficient_of_the_bricks_draws_the_whole() {
    let dims = [40, 36, 32];
    let volume = Phantom::SheppLogan.generate(dims);
    for family in [Family::Haar, Family::Linear] {
        // Every nonzero coefficient at a fine step: at the default step each brick's
        // quantizer scales with its own smallest coefficient (Haar leaves exact zeros, so a
        // brick of few blocks quantizes coarsely), and what is tested here is the bricks'
        // placement, not their quantizers.
        let opts = CompressOptions {
            family,
            target: Target::All,
            step: 1e-4,
            refine: None,
            ..CompressOptions::default()
        };
        let bricked = compress_bricked(&volume, &opts, 20, &|_| {}).unwrap();
        assert_eq!(bricked.manifest.bricks.len(), 8);
        let whole = compress(
            &volume,
            &CompressOptions {
                levels: Some(bricked.levels),
                margin: Some(0),
                ..opts.clone()
            },
            &|_, _| {},
        )
        .unwrap();
        let g = Geometry::new(dims, family, bricked.levels, 0).unwrap();
        for (name, spec) in views() {
            let (sw, sb) = whole_and_bricked_snr(&volume, &g, &spec, &whole.bytes, &bricked.bytes);
            eprintln!("{family} {name}: whole {sw:.2} dB, bricked {sb:.2} dB");
            assert!(
                sb >= (sw - 1.0).min(50.0),
                "{family} {name}: whole {sw:.2} dB, bricked {sb:.2} dB"
            );
        }
    }
}

/// Cubic bricks are refused (they do not draw the whole accurately yet), naming the family.
#[test]
fn cubic_bricks_are_refused_naming_the_family() {
    let volume = Phantom::SheppLogan.generate([24, 24, 24]);
    let opts = CompressOptions {
        family: Family::Cubic,
        ..CompressOptions::default()
    };
    let e = compress_bricked(&volume, &opts, 12, &|_| {}).unwrap_err();
    assert!(e.to_string().contains("cubic"), "{e}");
}

/// A manifest that claims three channels over bricks of one is refused when drawn in one pass,
/// as the progressive reader refuses it, instead of drawing the bricks as if it had said one.
#[test]
fn a_manifest_whose_channels_are_not_its_bricks_is_refused() {
    use wavesplat_codec::format::bricked::{parse_bricked, write_bricked};
    let volume = Phantom::SheppLogan.generate([40, 36, 32]);
    let opts = CompressOptions {
        target: Target::Fraction(0.05),
        ..CompressOptions::default()
    };
    let bytes = compress_bricked(&volume, &opts, 20, &|_| {}).unwrap().bytes;
    let spec = ViewSpec::single(View::new(0.3, 0.2, 32, 32));
    assert!(draw_bricked_file(&bytes, &spec, &mut CpuBackend::new()).is_ok());
    let file = parse_bricked(&bytes).unwrap();
    let bricks: Vec<&[u8]> = (0..file.manifest.bricks.len())
        .map(|i| file.brick_bytes(i).unwrap())
        .collect();
    let mut liar = file.manifest.clone();
    liar.channels = 3;
    let lying = write_bricked(&mut liar, &bricks).unwrap();
    assert!(draw_bricked_file(&lying, &spec, &mut CpuBackend::new()).is_err());
}

/// A view zoomed into one corner of the volume decodes and draws that corner's brick only.
#[test]
fn a_view_of_one_brick_draws_no_other() {
    let dims = [40, 36, 32];
    let volume = Phantom::SheppLogan.generate(dims);
    let opts = CompressOptions {
        target: Target::Fraction(0.05),
        ..CompressOptions::default()
    };
    let bricked = compress_bricked(&volume, &opts, 20, &|_| {}).unwrap();
    // Along z, centred on the brick at the origin (x, y < 20, 18), a few voxels wide.
    let view = common::origin_corner_view();
    let b = draw_bricked_file(
        &bricked.bytes,
        &ViewSpec::single(view),
        &mut CpuBackend::new(),
    )
    .unwrap();
    assert_eq!(b.bricks, 8);
    assert_eq!(b.drawn, 2, "the two bricks along the rays at the corner");
    assert!(b.image.data.iter().any(|v| *v != 0.0));
}

/// At equal bytes, a CT-like volume in 32³ bricks (air at −1000 round a body cut by the first
/// and last slices, noise) draws nearly as accurately as the unbricked file, against the
/// reference ray caster of the original: in oblique views and in views along an axis, where a
/// ray runs inside one brick face for its whole length and any seam adds up. Bricks with
/// offsets of their own drew a half-voxel step at every face, and a brick padded with nothing
/// (a periodic step across it) spent its bytes on its faces.
#[test]
fn bricks_at_equal_bytes_draw_nearly_as_well_as_the_whole() {
    let dims = [96, 96, 64];
    let volume = Phantom::Ct.generate(dims);
    let opts = CompressOptions {
        target: Target::Bytes(60_000),
        ..CompressOptions::default()
    };
    let bricked = compress_bricked(&volume, &opts, 32, &|_| {}).unwrap();
    assert_eq!(bricked.manifest.bricks.len(), 18);
    let whole = compress(
        &volume,
        &CompressOptions {
            target: Target::Bytes(bricked.bytes.len() as u64),
            ..opts.clone()
        },
        &|_, _| {},
    )
    .unwrap();
    let g = Geometry::new(dims, Family::Linear, 0, 0).unwrap();
    let mut gaps = Vec::new();
    for (name, spec) in views() {
        let (sw, sb) = whole_and_bricked_snr(&volume, &g, &spec, &whole.bytes, &bricked.bytes);
        eprintln!(
            "{name}: whole {sw:.2} dB ({} B), bricked {sb:.2} dB ({} B)",
            whole.bytes.len(),
            bricked.bytes.len()
        );
        // Measured: 1.1–3.8 dB below the whole, 2.0 dB on average. Until the offset came back
        // as the spline's line integral (2026-12-05) both drew a frame round the silhouette
        // (32.7 dB along an axis) that hid part of the gap: then 0.0–3.5 dB, 1.1 on average;
        // with per-brick offsets and no bridge, 0.1–4.4 dB and 2.2 dB on average.
        assert!(
            sb >= sw - 4.0,
            "{name}: whole {sw:.2} dB, bricked {sb:.2} dB"
        );
        gaps.push(sw - sb);
    }
    let mean = gaps.iter().sum::<f64>() / gaps.len() as f64;
    assert!(
        mean <= 2.3,
        "bricked {mean:.2} dB below the whole on average: {gaps:?}"
    );
}
