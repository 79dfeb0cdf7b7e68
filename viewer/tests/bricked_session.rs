//! A bricked file drawn progressively, as `render --progressive` and the frame loop draw it: one
//! session over every brick, fed by the file source in view order. Once everything is drawn
//! with exact tables the image is the one-pass image of the bricks (itself checked against the
//! reference ray caster in `bricked.rs`), in oblique, axis, near-axis, zoomed and depth-cued
//! views, after view changes and under a memory bound, and in multiview (each panel moved into
//! a brick by its own pan); a view that sees one corner fetches the packets of the bricks there
//! only, in multiview those of the bricks any panel sees; mismatched bricks are refused with a
//! reason.

mod common;

use std::collections::BTreeSet;
use std::time::Duration;
use wavesplat_codec::family::Family;
use wavesplat_codec::layout::Geometry;
use wavesplat_codec::metrics::snr_db;
use wavesplat_codec::view::{Cue, CueDirection, View, ViewSpec};
use wavesplat_compressor::bricked::compress_bricked;
use wavesplat_compressor::encode::{CompressOptions, Target};
use wavesplat_compressor::phantom::Phantom;
use wavesplat_viewer::bricked::draw_bricked_file;
use wavesplat_viewer::frame::FrameLoop;
use wavesplat_viewer::session::{BrickedVolume, RenderSession, SessionOptions};
use wavesplat_viewer::source::{FileSource, PacketSource};
use wavesplat_viewer::{CpuBackend, Image};

const DIMS: [usize; 3] = [40, 36, 32];

fn bricked_file(family: Family) -> Vec<u8> {
    let volume = Phantom::SheppLogan.generate(DIMS);
    let opts = CompressOptions {
        family,
        target: Target::Fraction(0.08),
        ..CompressOptions::default()
    };
    let b = compress_bricked(&volume, &opts, 20, &|_| {}).unwrap();
    assert_eq!(b.manifest.bricks.len(), 8);
    b.bytes
}

/// `spec` at the whole's fitting zoom when it has none (both paths then draw one picture).
fn fitted(spec: ViewSpec) -> ViewSpec {
    let g = Geometry::new(DIMS, Family::Linear, 0, 0).unwrap();
    let mut s = spec;
    if s.view.zoom.is_none() {
        s.view.zoom = Some(s.cameras(&g).unwrap()[0].fitting_zoom(&g));
    }
    s
}

fn views() -> Vec<(&'static str, ViewSpec)> {
    let v = |a, b| View::new(a, b, 96, 80);
    vec![
        ("oblique", v(0.66, 0.91)),
        ("axis", v(0.0, 0.0)),
        ("near axis", v(0.003, -0.002)),
        (
            "zoomed and panned",
            v(0.4, 0.3).with_zoom(3.0).with_pan([-4.0, 3.0]),
        ),
        (
            "cued",
            v(0.66, 0.91).with_cue(Cue {
                k: 0.06,
                direction: CueDirection::View,
            }),
        ),
        (
            "stiffly cued from the side",
            v(0.3, 0.2).with_cue(Cue {
                k: 0.5,
                direction: CueDirection::Vector([0.8, -0.36, 0.48]),
            }),
        ),
    ]
    .into_iter()
    .map(|(n, v)| (n, fitted(ViewSpec::single(v))))
    .collect()
}

fn session_loop(
    bytes: &[u8],
    spec: ViewSpec,
    options: SessionOptions,
) -> (FrameLoop<CpuBackend, FileSource>, BrickedVolume) {
    let source = FileSource::open(bytes.to_vec(), &spec).unwrap();
    let volume = source.bricked_volume().expect("a bricked file");
    let session =
        RenderSession::new_bricked(volume.clone(), spec, CpuBackend::new(), options).unwrap();
    (FrameLoop::new(session, source), volume)
}

/// Frames until the source is done, nothing is pending and the tables are exact; returns the
/// image.
fn run_to_end(f: &mut FrameLoop<CpuBackend, FileSource>) -> Image {
    for _ in 0..100_000 {
        let r = f.frame(Duration::from_millis(20)).unwrap();
        assert!(r.batches_past_deadline <= 1);
        if r.idle() && f.source.status().done {
            return f.session.image().unwrap();
        }
        if r.pending == 0 && r.packets == 0 && !r.exact {
            // A preview fully drawn: its exact tables are being built.
            f.session.wait_exact(Duration::from_millis(50)).unwrap();
        }
    }
    panic!("no progress");
}

fn with_preview() -> SessionOptions {
    SessionOptions {
        preview: Some(SessionOptions::default_preview()),
        ..SessionOptions::default()
    }
}

/// Which bricks the ids name (the bricks' packets are numbered brick by brick).
fn bricks_of(volume: &BrickedVolume, ids: &[u32]) -> BTreeSet<usize> {
    ids.iter()
        .map(|&id| {
            (0..volume.bricks.len())
                .find(|&b| {
                    let first = volume.global_id(b, 0).unwrap_or(u32::MAX);
                    id >= first && id - first < volume.bricks[b].packets
                })
                .expect("an id of some brick")
        })
        .collect()
}

/// Drawn progressively to the end, a bricked file's image is its one-pass image (f32 sums in
/// another order: > 90 dB), in every kind of single view and both families; the first frame
/// already shows something.
#[test]
fn a_progressive_session_ends_at_the_one_pass_image() {
    for family in [Family::Haar, Family::Linear] {
        let bytes = bricked_file(family);
        for (name, spec) in views() {
            let one_pass = draw_bricked_file(&bytes, &spec, &mut CpuBackend::new()).unwrap();
            let (mut f, _) = session_loop(&bytes, spec, with_preview());
            f.frame(Duration::from_millis(5)).unwrap();
            let first = f.session.image().unwrap();
            assert!(
                first.data.iter().any(|v| *v != 0.0),
                "{family} {name}: blank first frame"
            );
            let image = run_to_end(&mut f);
            let snr = snr_db(&one_pass.image.data, &image.data);
            assert!(snr > 90.0, "{family} {name}: {snr:.1} dB against one pass");
            let stats = f.session.stats();
            // Every coefficient is drawn, or left out as one the view cannot see (a wavelet
            // along the direction of a view along an axis projects to zero).
            assert_eq!(
                (stats.splatted_in_view + stats.invisible_in_view) as usize,
                one_pass.coefficients,
                "{family} {name}"
            );
        }
    }
}

/// A view change restarts the accumulation over every brick held: the second view's image is
/// its one-pass image, with no packet sent twice; the same under a memory bound that drops
/// packets (they are asked for again after the view change).
#[test]
fn view_changes_and_a_memory_bound_keep_the_image_exact() {
    let bytes = bricked_file(Family::Linear);
    let all = views();
    let (first, second) = (all[0].1, all[4].1);
    let expected = draw_bricked_file(&bytes, &second, &mut CpuBackend::new()).unwrap();
    for bound in [None, Some(40_000)] {
        let options = SessionOptions {
            memory_bound: bound,
            ..with_preview()
        };
        let (mut f, _) = session_loop(&bytes, first, options);
        run_to_end(&mut f);
        f.set_view(second).unwrap();
        let image = run_to_end(&mut f);
        let snr = snr_db(&expected.image.data, &image.data);
        assert!(snr > 90.0, "bound {bound:?}: {snr:.1} dB against one pass");
        let stats = f.session.stats();
        if bound.is_some() {
            assert!(stats.packets_dropped > 0, "the bound dropped nothing");
            assert!(stats.retained_bytes <= 40_000);
        } else {
            assert_eq!(f.source.status().resent, 0);
            assert_eq!(stats.packets_received, f.source.status().packets);
        }
    }
}

/// Zoomed into the corner at the origin, looking along z: the file source sends packets of the
/// two bricks along the rays there and of no other, and the image is the one-pass image.
#[test]
fn a_view_of_one_corner_fetches_only_the_bricks_it_sees() {
    let bytes = bricked_file(Family::Linear);
    let view = common::origin_corner_view();
    let spec = ViewSpec::single(view);
    let one_pass = draw_bricked_file(&bytes, &spec, &mut CpuBackend::new()).unwrap();
    assert_eq!(one_pass.drawn, 2);
    let (mut f, volume) = session_loop(&bytes, spec, SessionOptions::default());
    let image = run_to_end(&mut f);
    let held = f.session.held_ids();
    let seen = bricks_of(&volume, &held);
    assert_eq!(seen.len(), 2, "packets of bricks {seen:?}");
    let total: u32 = volume.bricks.iter().map(|b| b.packets).sum();
    assert!((held.len() as u32) < total);
    let snr = snr_db(&one_pass.image.data, &image.data);
    assert!(snr > 90.0, "{snr:.1} dB against one pass");
}

/// Multiview of a bricked file drawn progressively ends at its one-pass image (which places
/// each panel in the bricks by its own code, `draw_bricked_file`), in oblique, near-axis and
/// zoomed-and-panned views, both families; every coefficient is drawn (in a panel that sees
/// it) or counted invisible; a view change from a single view to multiview and back keeps the
/// image exact.
#[test]
fn multiview_of_a_bricked_file_ends_at_the_one_pass_image() {
    let multi = |v: View| {
        fitted(ViewSpec {
            view: v,
            multiview: true,
        })
    };
    let specs = [
        ("oblique", multi(View::new(0.66, 0.91, 64, 56))),
        ("near axis", multi(View::new(0.003, -0.002, 48, 48))),
        (
            "zoomed and panned",
            multi(
                View::new(0.4, 0.3, 48, 40)
                    .with_zoom(3.0)
                    .with_pan([-4.0, 3.0]),
            ),
        ),
    ];
    for family in [Family::Haar, Family::Linear] {
        let bytes = bricked_file(family);
        for (name, spec) in specs {
            let one_pass = draw_bricked_file(&bytes, &spec, &mut CpuBackend::new()).unwrap();
            assert_eq!(one_pass.image.width, 3 * spec.view.width);
            assert!(
                one_pass.image.data.iter().any(|v| *v != 0.0),
                "{family} {name}: the one-pass image is empty"
            );
            let (mut f, _) = session_loop(&bytes, spec, with_preview());
            let image = run_to_end(&mut f);
            assert_eq!(image.width, one_pass.image.width, "{family} {name}");
            let snr = snr_db(&one_pass.image.data, &image.data);
            assert!(snr > 90.0, "{family} {name}: {snr:.1} dB against one pass");
            let stats = f.session.stats();
            assert_eq!(
                (stats.splatted_in_view + stats.invisible_in_view) as usize,
                one_pass.coefficients,
                "{family} {name}: every coefficient drawn or invisible"
            );
            // Each third of the image is one panel: each matches its one-pass panel on its own
            // (a panel drawn with another panel's pan would not).
            let w = spec.view.width;
            for panel in 0..3 {
                let cut = |img: &Image| -> Vec<f32> {
                    img.data
                        .chunks(img.width * img.channels)
                        .flat_map(|row| {
                            row[panel * w * img.channels..(panel + 1) * w * img.channels].to_vec()
                        })
                        .collect()
                };
                let (a, b) = (cut(&one_pass.image), cut(&image));
                if a.iter().all(|v| *v == 0.0) {
                    assert!(b.iter().all(|v| *v == 0.0), "{family} {name} panel {panel}");
                    continue;
                }
                let snr = snr_db(&a, &b);
                assert!(snr > 90.0, "{family} {name} panel {panel}: {snr:.1} dB");
            }
        }
    }
    // Single view → multiview → single view in one session.
    let bytes = bricked_file(Family::Linear);
    let single = views()[0].1;
    let multi = multi(single.view);
    let (mut f, _) = session_loop(&bytes, single, with_preview());
    run_to_end(&mut f);
    for spec in [multi, single] {
        let expected = draw_bricked_file(&bytes, &spec, &mut CpuBackend::new()).unwrap();
        f.set_view(spec).unwrap();
        let image = run_to_end(&mut f);
        let snr = snr_db(&expected.image.data, &image.data);
        assert!(snr > 90.0, "multiview {}: {snr:.1} dB", spec.multiview);
    }
}

/// Zoomed into the corner at the origin in multiview: the first panel sees the two bricks along
/// its rays there, the other panels (turned about the volume's centre) see others; the file
/// source sends the packets of exactly the bricks the one-pass drawing draws, and the image is
/// the one-pass image.
#[test]
fn a_multiview_of_one_corner_fetches_the_bricks_any_panel_sees() {
    let bytes = bricked_file(Family::Linear);
    let spec = ViewSpec {
        view: common::origin_corner_view(),
        multiview: true,
    };
    let one_pass = draw_bricked_file(&bytes, &spec, &mut CpuBackend::new()).unwrap();
    let single =
        draw_bricked_file(&bytes, &ViewSpec::single(spec.view), &mut CpuBackend::new()).unwrap();
    assert!(
        one_pass.drawn > single.drawn && one_pass.drawn < one_pass.bricks,
        "panels see {} of {} bricks, the first alone {}",
        one_pass.drawn,
        one_pass.bricks,
        single.drawn
    );
    let (mut f, volume) = session_loop(&bytes, spec, SessionOptions::default());
    let image = run_to_end(&mut f);
    let seen = bricks_of(&volume, &f.session.held_ids());
    assert_eq!(seen.len(), one_pass.drawn, "packets of bricks {seen:?}");
    let snr = snr_db(&one_pass.image.data, &image.data);
    assert!(snr > 90.0, "{snr:.1} dB against one pass");
}

/// Loose coefficients (which name no brick) and ids of no brick are refused.
#[test]
fn packets_of_no_brick_are_refused() {
    let bytes = bricked_file(Family::Linear);
    let single = fitted(ViewSpec::single(View::new(0.4, 0.3, 64, 64)));
    let source = FileSource::open(bytes, &single).unwrap();
    let volume = source.bricked_volume().unwrap();
    let mut s = RenderSession::new_bricked(
        volume.clone(),
        single,
        CpuBackend::new(),
        Default::default(),
    )
    .unwrap();
    let total: u32 = volume.bricks.iter().map(|b| b.packets).sum();
    let e = s.add_packet(total, &[0u8; 16]).unwrap_err();
    assert!(e.to_string().contains("no brick"), "{e}");
    assert!(s.add_coefficients(Vec::new()).is_err());
    assert_eq!(volume.global_id(0, volume.bricks[0].packets), None);
}

/// Bricks that would be shown otherwise (another colour coding than the first brick's) cannot
/// share one accumulation: the session refuses them, naming the brick.
#[test]
fn bricks_coded_otherwise_are_refused() {
    let bytes = bricked_file(Family::Linear);
    let single = fitted(ViewSpec::single(View::new(0.4, 0.3, 64, 64)));
    let source = FileSource::open(bytes, &single).unwrap();
    let mut volume = source.bricked_volume().unwrap();
    volume.bricks[3].header.color.mean[0] += 7.0;
    let e = RenderSession::new_bricked(volume, single, CpuBackend::new(), Default::default())
        .unwrap_err();
    assert!(e.to_string().contains("brick 3"), "{e}");
}

/// The bricks of a colour volume share the whole's colour transform (its faces' median colour
/// and the basis of its colour moments), so they draw into one image progressively: in RGB, YIQ
/// and PCA, the progressive image ends at the one-pass image of the bricks, and that image is
/// the unbricked file's picture within the accuracy of their different coefficient sets.
#[test]
fn a_colour_volume_s_bricks_draw_into_one_image() {
    use wavesplat_compressor::colorspace::ColorSpaceKind;
    use wavesplat_compressor::encode::compress;
    let volume = Phantom::RgbHead.generate(DIMS);
    let spec = fitted(ViewSpec::single(View::new(0.66, 0.91, 96, 80)));
    for kind in [
        ColorSpaceKind::Pca,
        ColorSpaceKind::Rgb,
        ColorSpaceKind::Yiq,
    ] {
        let opts = CompressOptions {
            target: Target::Fraction(0.08),
            colorspace: kind,
            ..CompressOptions::default()
        };
        let bytes = compress_bricked(&volume, &opts, 20, &|_| {}).unwrap().bytes;
        let (mut f, bricked) = session_loop(&bytes, spec, SessionOptions::default());
        let first = &bricked.bricks[0].header.color;
        assert!(
            bricked
                .bricks
                .iter()
                .all(|b| b.header.color.basis == first.basis && b.header.color.mean == first.mean),
            "{kind:?}: the bricks code their colours alike"
        );
        let progressive = run_to_end(&mut f);
        let one_pass = draw_bricked_file(&bytes, &spec, &mut CpuBackend::new())
            .unwrap()
            .image;
        assert_eq!(progressive.channels, 3);
        let snr = snr_db(&one_pass.data, &progressive.data);
        assert!(
            snr > 100.0,
            "{kind:?}: progressive against one pass {snr:.1} dB"
        );
        let whole = compress(&volume, &opts, &|_, _| {}).unwrap().bytes;
        let whole_image =
            wavesplat_viewer::open::draw_whole_file(&whole, &spec, &mut CpuBackend::new())
                .unwrap()
                .image;
        let whole_snr = snr_db(&whole_image.data, &one_pass.data);
        eprintln!("{kind:?}: progressive against one pass {snr:.1} dB, bricked against whole {whole_snr:.1} dB");
        assert!(
            whole_snr > 20.0,
            "{kind:?}: bricked against whole {whole_snr:.1} dB"
        );
    }
}

/// The bricks of one volume share their band weights, and those of one shape their tile boxes:
/// a brick's visibility made with another brick's band weights ([`Visibility::new_like`]), or
/// as a session makes it (`brick_visibility`, boxes by shape), weighs every band and tile as
/// its own computed from scratch, in plain and cued views.
#[test]
fn bricks_share_band_weights_exactly() {
    use wavesplat_codec::view::visibility::Visibility;
    use wavesplat_viewer::bricked::{brick_frame, brick_visibility, whole_frame};
    // Bricks of 16 over 40 × 36 × 32: three shapes along x and y (16, 16, 8 and 16, 16, 4).
    let opts = CompressOptions {
        target: Target::Fraction(0.08),
        ..CompressOptions::default()
    };
    let volume = Phantom::SheppLogan.generate(DIMS);
    let bytes = compress_bricked(&volume, &opts, 16, &|_| {}).unwrap().bytes;
    let whole = Geometry::new(DIMS, Family::Linear, 0, 0).unwrap();
    for (name, spec) in views() {
        let source = FileSource::open(bytes.clone(), &spec).unwrap();
        let volume = source.bricked_volume().unwrap();
        let (camera, cue) = whole_frame(&spec, &whole).unwrap();
        let mut like: Option<Visibility> = None;
        let mut shapes = Vec::new();
        for b in &volume.bricks {
            let g = &b.header.geometry;
            let Some(frame) =
                brick_frame(&spec, (&camera, cue.as_ref()), &whole, g, b.origin).unwrap()
            else {
                continue;
            };
            let own = Visibility::new(&b.header, &frame.spec).unwrap();
            // Shared as a session shares them: band weights, and tile boxes by brick shape.
            let by_shape = brick_visibility(&b.header, &frame, &mut shapes).unwrap();
            let Some(l) = &like else {
                like = Some(own);
                continue;
            };
            let shared = Visibility::new_like(&b.header, &frame.spec, l).unwrap();
            for band in g.bands() {
                for tile in 0..b.header.tile_count() {
                    let x = own.weight(band, tile);
                    for y in [shared.weight(band, tile), by_shape.weight(band, tile)] {
                        assert!(
                            (x - y).abs() <= 1e-12 * x.abs().max(1e-300),
                            "{name}: {band:?} tile {tile}: {x} against {y}"
                        );
                    }
                }
            }
        }
        assert!(like.is_some(), "{name}: no brick on the image");
        assert!(shapes.len() > 1, "{name}: bricks of one shape only");
    }
}
