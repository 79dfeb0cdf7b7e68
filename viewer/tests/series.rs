//! A time point of a series renders like that volume: its image, the weighted sum of its
//! components' images, against the reference ray caster of the original time point, in
//! oblique, axis and near-axis views, cued and multiview, with plain and bricked components;
//! at equal bytes, time points compressed together draw better than each compressed alone;
//! a time point needs no byte of another group.

mod common;

use wavesplat_codec::family::Family;
use wavesplat_codec::format::series::parse_series;
use wavesplat_codec::layout::Geometry;
use wavesplat_codec::metrics::snr_db;
use wavesplat_codec::view::{Cue, CueDirection, View, ViewSpec};
use wavesplat_codec::volume::Volume;
use wavesplat_compressor::encode::{CompressOptions, Target};
use wavesplat_compressor::phantom::beating;
use wavesplat_compressor::series::{compress_series, VolumeSeries};
use wavesplat_viewer::series::{draw_series_point, SeriesDrawError};
use wavesplat_viewer::{CpuBackend, Image};

const DIMS: [usize; 3] = [32, 28, 20];

fn cine(points: usize) -> VolumeSeries {
    let v = (0..points)
        .map(|t| beating(DIMS, t, points).unwrap())
        .collect();
    VolumeSeries::new(v, None).unwrap()
}

fn views() -> Vec<(&'static str, ViewSpec)> {
    let v = |a, b| View::new(a, b, 64, 56);
    let single = ViewSpec::single;
    vec![
        ("oblique", single(v(0.66, 0.91))),
        ("axis", single(v(0.0, 0.0))),
        ("near axis", single(v(0.003, -0.002))),
        (
            "cued",
            single(v(0.66, 0.91).with_cue(Cue {
                k: 0.08,
                direction: CueDirection::View,
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

/// The view at the volume's fitting zoom (so that the reference draws the same picture).
fn fitted(spec: &ViewSpec, g: &Geometry) -> ViewSpec {
    let mut s = *spec;
    let z = s
        .cameras(g)
        .unwrap()
        .iter()
        .map(|c| c.fitting_zoom(g))
        .fold(f64::INFINITY, f64::min);
    s.view.zoom = Some(z);
    s
}

/// SNR of time point `t` of `bytes` against the reference of `volume` for `spec`.
fn snr(bytes: &[u8], t: usize, volume: &Volume, g: &Geometry, spec: &ViewSpec) -> f64 {
    let spec = fitted(spec, g);
    let drawn = draw_series_point(bytes, t, &spec, &mut CpuBackend::new()).unwrap();
    snr_db(
        &common::reference_image(volume, g, &spec).data,
        &drawn.image.data,
    )
}

/// Every coefficient of every component: each time point's image, summed from its group's
/// components with their weights, is the original time point's line integrals, in every kind
/// of view, with the components whole and in bricks (a wrong weight, sign or component costs
/// tens of dB).
#[test]
fn every_coefficient_draws_every_time_point() {
    let s = cine(6);
    let opts = CompressOptions {
        target: Target::All,
        refine: None,
        ..CompressOptions::default()
    };
    for (group, brick) in [(4, 256), (2, 16)] {
        let c = compress_series(&s, &opts, group, brick, &|_| {}).unwrap();
        let g = Geometry::new(DIMS, Family::Linear, c.levels, 0).unwrap();
        for t in [0, 3, 5] {
            for (name, spec) in views() {
                let db = snr(&c.bytes, t, &s.volumes()[t], &g, &spec);
                assert!(
                    db > 45.0,
                    "group {group}, brick {brick}, t {t}, {name}: {db:.2} dB"
                );
            }
        }
    }
}

/// At the same bytes, a cine compressed in groups of 8 draws every time point better than the
/// same cine with each time point compressed alone (what does not move is stored once).
#[test]
fn at_equal_bytes_time_points_compressed_together_draw_better() {
    let s = cine(8);
    let opts = CompressOptions {
        target: Target::Bytes(30_000),
        ..CompressOptions::default()
    };
    let alone = compress_series(&s, &opts, 1, 256, &|_| {}).unwrap();
    let together = compress_series(&s, &opts, 8, 256, &|_| {}).unwrap();
    let spec = ViewSpec::single(View::new(0.66, 0.91, 64, 56));
    let mean = |bytes: &[u8], levels: usize| {
        let g = Geometry::new(DIMS, Family::Linear, levels, 0).unwrap();
        (0..8)
            .map(|t| snr(bytes, t, &s.volumes()[t], &g, &spec))
            .sum::<f64>()
            / 8.0
    };
    let (a, b) = (
        mean(&alone.bytes, alone.levels),
        mean(&together.bytes, together.levels),
    );
    eprintln!("alone {a:.2} dB, together {b:.2} dB");
    assert!(b > a + 1.0, "alone {a:.2} dB, together {b:.2} dB");
}

/// A time point takes only its own group's components: damage to another group's bytes does
/// not touch it, and is caught when a time point of that group is drawn; a time point the
/// series does not have is an error naming the count.
#[test]
fn a_time_point_needs_no_byte_of_another_group() {
    let s = cine(4);
    let opts = CompressOptions {
        target: Target::Fraction(0.1),
        ..CompressOptions::default()
    };
    let c = compress_series(&s, &opts, 2, 256, &|_| {}).unwrap();
    let m = parse_series(&c.bytes).unwrap().manifest;
    let mut damaged = c.bytes.clone();
    let second = &m.components[2];
    damaged[(second.offset + second.length / 2) as usize] ^= 0x40;
    let spec = ViewSpec::single(View::new(0.4, 0.3, 32, 32));
    let good = draw_series_point(&c.bytes, 1, &spec, &mut CpuBackend::new()).unwrap();
    let same = draw_series_point(&damaged, 1, &spec, &mut CpuBackend::new()).unwrap();
    assert_eq!(good.image.data, same.image.data);
    assert_eq!(same.bytes, m.point_bytes(1));
    let e = draw_series_point(&damaged, 2, &spec, &mut CpuBackend::new()).unwrap_err();
    assert!(e.to_string().contains("reading the series"), "{e}");
    let e = draw_series_point(&c.bytes, 4, &spec, &mut CpuBackend::new()).unwrap_err();
    assert!(
        matches!(
            e,
            SeriesDrawError::NoTimePoint {
                asked: 4,
                points: 4
            }
        ),
        "{e}"
    );
}

/// Frames until the source is done, nothing is pending and the tables are exact.
fn run_to_end(
    f: &mut wavesplat_viewer::frame::FrameLoop<CpuBackend, wavesplat_viewer::source::FileSource>,
) -> Image {
    use std::time::Duration;
    use wavesplat_viewer::source::PacketSource;
    for _ in 0..100_000 {
        let r = f.frame(Duration::from_millis(20)).unwrap();
        if r.idle() && f.source.status().done {
            return f.session.image().unwrap();
        }
        if r.pending == 0 && r.packets == 0 && !r.exact {
            f.session.wait_exact(Duration::from_millis(50)).unwrap();
        }
    }
    panic!("no progress");
}

/// A time point drawn progressively, as `render --progressive` and the window draw it (one
/// session over its components' bricks, weighted as they are decoded, the weighted offset
/// drawn once), ends at its one-pass image (> 90 dB: f32 sums in another order), with plain
/// and bricked components, in oblique, axis, cued and multiview views; it receives its group's
/// bytes only.
#[test]
fn a_time_point_drawn_progressively_ends_at_its_one_pass_image() {
    use wavesplat_viewer::frame::FrameLoop;
    use wavesplat_viewer::session::{RenderSession, SessionOptions};
    use wavesplat_viewer::source::{FileSource, PacketSource};
    let s = cine(6);
    let opts = CompressOptions {
        target: Target::Fraction(0.1),
        ..CompressOptions::default()
    };
    for (group, brick) in [(4, 256), (2, 16)] {
        let c = compress_series(&s, &opts, group, brick, &|_| {}).unwrap();
        let g = Geometry::new(DIMS, Family::Linear, 0, 0).unwrap();
        let m = parse_series(&c.bytes).unwrap().manifest;
        for (name, spec) in views() {
            let spec = fitted(&spec, &g);
            for t in [1, 5] {
                let one = draw_series_point(&c.bytes, t, &spec, &mut CpuBackend::new()).unwrap();
                let source = FileSource::open_series_point(c.bytes.clone(), t, &spec).unwrap();
                let volume = source
                    .bricked_volume()
                    .expect("a time point is drawn as bricks");
                let session = RenderSession::new_bricked(
                    volume,
                    spec,
                    CpuBackend::new(),
                    SessionOptions::default(),
                )
                .unwrap();
                let mut f = FrameLoop::new(session, source);
                let image = run_to_end(&mut f);
                let db = snr_db(&one.image.data, &image.data);
                assert!(
                    db > 90.0,
                    "group {group}, brick {brick}, {name}, t {t}: {db:.1} dB"
                );
                assert!(f.source.status().bytes <= m.point_bytes(t));
            }
        }
    }
}

/// Playing a series replaces the time point a session draws: the next one's parts are planned
/// at once with the tables the last one built (no preview), and its image ends at its own
/// one-pass image, nothing of the last time point left in it.
#[test]
fn a_session_moves_to_another_time_point_keeping_its_tables() {
    use wavesplat_viewer::frame::FrameLoop;
    use wavesplat_viewer::session::{RenderSession, SessionOptions};
    use wavesplat_viewer::source::FileSource;
    let s = cine(8);
    let opts = CompressOptions {
        target: Target::Fraction(0.1),
        ..CompressOptions::default()
    };
    let c = compress_series(&s, &opts, 4, 256, &|_| {}).unwrap();
    let g = Geometry::new(DIMS, Family::Linear, 0, 0).unwrap();
    let spec = fitted(&ViewSpec::single(View::new(0.66, 0.91, 64, 56)), &g);
    let options = SessionOptions {
        preview: Some(SessionOptions::default_preview()),
        ..SessionOptions::default()
    };
    let source = FileSource::open_series_point(c.bytes.clone(), 2, &spec).unwrap();
    let volume = source.bricked_volume().unwrap();
    let session = RenderSession::new_bricked(volume, spec, CpuBackend::new(), options).unwrap();
    let mut f = FrameLoop::new(session, source);
    run_to_end(&mut f);
    for t in [3, 6, 0] {
        let previews = f.session.stats().previews;
        let source = FileSource::open_series_point(c.bytes.clone(), t, &spec).unwrap();
        f.session
            .replace_bricked_volume(source.bricked_volume().unwrap())
            .unwrap();
        f.source = source;
        assert!(
            f.session.is_exact(),
            "time point {t} is planned with the cached tables"
        );
        let image = run_to_end(&mut f);
        assert_eq!(f.session.stats().previews, previews, "time point {t}");
        let one = draw_series_point(&c.bytes, t, &spec, &mut CpuBackend::new()).unwrap();
        let db = snr_db(&one.image.data, &image.data);
        assert!(db > 90.0, "time point {t}: {db:.1} dB");
    }
}
