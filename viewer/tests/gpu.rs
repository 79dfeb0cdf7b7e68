//! The wgpu backend against the CPU backend (issue 12): the same splat records, planned
//! progressively in significance order, summed by both; images compared by the conventional
//! SNR (10·log10). Every family, multiview, depth cueing and RGB; order and chunk independence
//! of the fixed-point sums; the display pass against the PNG mapping; refused input.
//!
//! The GPU tests need an adapter (Mesa's lavapipe will do). Without one they skip with a
//! printed reason, unless `WAVESPLAT_REQUIRE_GPU=1` (CI sets it): then they fail.

use std::sync::Arc;
use wavesplat_codec::dwt::decompose_channel;
use wavesplat_codec::family::Family;
use wavesplat_codec::format::packet::Coefficient;
use wavesplat_codec::layout::Geometry;
use wavesplat_codec::metrics::snr_db;
use wavesplat_viewer::backend::gpu::wgpu;
use wavesplat_viewer::backend::gpu::{AdapterRequest, ColorMap, DisplayOptions, GpuOptions};
use wavesplat_viewer::backend::{
    select, AccumulationBackend, BackendChoice, BackendError, CpuBackend, FootprintAtlas,
    GpuBackend, GpuContext, Layout, SplatRecord,
};
use wavesplat_viewer::plan::ViewPlan;
use wavesplat_viewer::ViewSpec;
use wavesplat_viewer::{Cue, CueDirection, Image, PlanOptions, Planner, RenderStats, View};

/// The context, or `None` (with the reason printed) when there is no adapter and the
/// environment does not require one.
fn gpu() -> Option<Arc<GpuContext>> {
    match GpuContext::new() {
        Ok(ctx) => {
            eprintln!("adapter: {:?}", ctx.info());
            Some(ctx)
        }
        Err(e) => {
            if std::env::var("WAVESPLAT_REQUIRE_GPU").as_deref() == Ok("1") {
                panic!("WAVESPLAT_REQUIRE_GPU=1 but no GPU adapter: {e}");
            }
            eprintln!("skipped: {e} (set WAVESPLAT_REQUIRE_GPU=1 to fail instead)");
            None
        }
    }
}

/// A deterministic hash of a voxel to [−1, 1).
fn noise(x: usize, y: usize, z: usize, seed: u64) -> f64 {
    let mut h = (x as u64) ^ ((y as u64) << 20) ^ ((z as u64) << 40) ^ seed.wrapping_mul(0x9e37);
    h = h.wrapping_add(0x9e3779b97f4a7c15);
    h = (h ^ (h >> 30)).wrapping_mul(0xbf58476d1ce4e5b9);
    h = (h ^ (h >> 27)).wrapping_mul(0x94d049bb133111eb);
    h ^= h >> 31;
    (h >> 11) as f64 / (1u64 << 52) as f64 - 1.0
}

/// A textured blob with noise everywhere (non-zero faces, every coefficient non-zero).
fn volume(dims: [usize; 3], seed: u64) -> Vec<f32> {
    let mut out = Vec::with_capacity(dims[0] * dims[1] * dims[2]);
    for z in 0..dims[2] {
        for y in 0..dims[1] {
            for x in 0..dims[0] {
                let p = [x, y, z].map(|v| v as f64);
                let d: f64 = (0..3)
                    .map(|a| ((p[a] - 0.5 * dims[a] as f64) / (0.4 * dims[a] as f64)).powi(2))
                    .sum();
                let blob = if d < 1.0 { 2.0 * (1.0 - d) } else { 0.0 };
                out.push((blob + 0.3 * noise(x, y, z, seed)) as f32);
            }
        }
    }
    out
}

/// Dimensions of the test volumes: 118 272 voxels, none a power of two.
const DIMS: [usize; 3] = [56, 48, 44];

/// Geometry and coefficients of `channels` volumes (channel c from seed c).
fn coefficients(family: Family, channels: usize) -> (Geometry, Vec<Coefficient>) {
    let g = Geometry::new(DIMS, family, 3, 0).unwrap();
    let mut all = Vec::new();
    for c in 0..channels {
        let vol = volume(DIMS, c as u64);
        all.extend(Coefficient::all_of(
            &g,
            c as u8,
            &decompose_channel(&vol, &g),
        ));
    }
    // Significance order, as a file or the cache delivers them.
    all.sort_by(|a, b| b.value.abs().total_cmp(&a.value.abs()));
    (g, all)
}

/// The planned view and its records in three progressive batches (1 %, 10 %, the rest of
/// the coefficients); the atlas grows between batches when depth cueing adds tables.
struct Planned {
    plan: ViewPlan,
    batches: Vec<(usize, Vec<SplatRecord>)>,
}

impl Planned {
    /// The atlas as a batch planned with `samples` of it saw it (the atlas only grows, so a
    /// prefix is exactly that).
    fn atlas_for(&self, samples: usize) -> FootprintAtlas {
        let mut atlas = self.plan.atlas().clone();
        atlas.data.truncate(samples);
        atlas
            .phases
            .retain(|r| (r.offset + r.cols * r.rows) as usize <= samples);
        atlas
    }
}

fn plan(g: &Geometry, coeffs: &[Coefficient], spec: &ViewSpec, channels: usize) -> Planned {
    let mut planner = Planner::new(PlanOptions::default());
    let mut plan = planner.plan(g, spec, channels).unwrap();
    let n = coeffs.len();
    let mut batches = Vec::new();
    let mut start = 0;
    for end in [n / 100, n / 10, n] {
        let mut records = Vec::new();
        plan.splats(
            &coeffs[start..end],
            &mut records,
            &mut RenderStats::default(),
        )
        .unwrap();
        batches.push((plan.atlas().data.len(), records));
        start = end;
    }
    Planned { plan, batches }
}

/// A GPU backend that has accumulated every batch of `p` (with the whole atlas).
fn accumulated(ctx: &Arc<GpuContext>, p: &Planned) -> GpuBackend {
    let mut gpu = GpuBackend::new(ctx.clone()).unwrap();
    gpu.begin(p.plan.layout()).unwrap();
    for (_, r) in &p.batches {
        gpu.accumulate(&p.plan.atlas(), r).unwrap();
    }
    gpu
}

/// Both backends over the batches (each batch sees the atlas as it was when planned; the
/// atlas only grows, so a prefix is exactly that). Pixel update counts must agree.
fn render_both(ctx: &Arc<GpuContext>, p: &Planned) -> (Image, Image, usize) {
    let mut cpu = CpuBackend::new();
    let mut gpu = GpuBackend::new(ctx.clone()).unwrap();
    let layout = p.plan.layout();
    cpu.begin(layout).unwrap();
    gpu.begin(layout).unwrap();
    let mut count = 0;
    for (samples, records) in &p.batches {
        let atlas = p.atlas_for(*samples);
        let a = cpu.accumulate(&atlas, records).unwrap();
        let b = gpu.accumulate(&atlas, records).unwrap();
        assert_eq!(a, b, "pixel updates");
        count += records.len();
    }
    (cpu.read().unwrap(), gpu.read().unwrap(), count)
}

fn view() -> View {
    View::new(0.66, 0.91, 100, 84)
}

/// The most significant cubic coefficients the views other than the plain single one draw.
/// All 129 024 cubic coefficients are 29 M records a view (their footprints' pieces), two
/// minutes on lavapipe, six for multiview; the 12 000 largest are ~1 M records a view.
const CUBIC_SUBSET: usize = 12_000;

/// GPU = CPU within 50 dB for `spec` and every family; returns the SNRs. `cubic_subset`: draw
/// only the most significant cubic coefficients (every one otherwise).
fn check_families(
    ctx: &Arc<GpuContext>,
    spec: &ViewSpec,
    channels: usize,
    cubic_subset: Option<usize>,
) -> Vec<f64> {
    let mut out = Vec::new();
    for family in Family::ALL {
        let (g, mut coeffs) = coefficients(family, channels);
        let nonzero = coeffs.iter().filter(|c| c.value != 0.0).count();
        assert!(nonzero >= 100_000, "{nonzero} non-zero coefficients");
        if let (Family::Cubic, Some(n)) = (family, cubic_subset) {
            coeffs.truncate(n);
        }
        let p = plan(&g, &coeffs, spec, channels);
        let (cpu, gpu, records) = render_both(ctx, &p);
        assert!(records >= 100_000);
        assert!(cpu.data.iter().any(|v| *v != 0.0));
        let snr = snr_db(&cpu.data, &gpu.data);
        eprintln!(
            "{family} {}x{}x{}: {} coefficients, {records} records, GPU vs CPU SNR {snr:.1} dB",
            cpu.width,
            cpu.height,
            cpu.channels,
            coeffs.len()
        );
        assert!(snr >= 50.0, "{family}: {snr} dB");
        out.push(snr);
    }
    out
}

/// Single view, every family: GPU = CPU ≥ 50 dB with > 10⁵ coefficients.
#[test]
fn gpu_matches_cpu_for_every_family() {
    let Some(ctx) = gpu() else { return };
    check_families(&ctx, &ViewSpec::single(view()), 1, None);
}

/// Multiview (three views side by side), every family (the cubic one's `CUBIC_SUBSET`).
#[test]
fn gpu_matches_cpu_multiview() {
    let Some(ctx) = gpu() else { return };
    let spec = ViewSpec {
        view: view(),
        multiview: true,
    };
    check_families(&ctx, &spec, 1, Some(CUBIC_SUBSET));
}

/// Depth cueing (the atlas grows while the view lasts), every family (the cubic one's
/// `CUBIC_SUBSET`).
#[test]
fn gpu_matches_cpu_depth_cued() {
    let Some(ctx) = gpu() else { return };
    let spec = ViewSpec::single(view().with_cue(Cue {
        k: 0.08,
        direction: CueDirection::Angles {
            alpha: 0.3,
            beta: 1.2,
        },
    }));
    check_families(&ctx, &spec, 1, Some(CUBIC_SUBSET));
}

/// Three channels (RGB), multiview, linear family.
#[test]
fn gpu_matches_cpu_rgb() {
    let Some(ctx) = gpu() else { return };
    let (g, coeffs) = coefficients(Family::Linear, 3);
    let spec = ViewSpec {
        view: View::new(1.2, 0.4, 64, 72),
        multiview: true,
    };
    let p = plan(&g, &coeffs, &spec, 3);
    let (cpu, gpu, _) = render_both(&ctx, &p);
    for c in 0..3 {
        let snr = snr_db(&cpu.channel(c).data, &gpu.channel(c).data);
        eprintln!("rgb channel {c}: SNR {snr:.1} dB");
        assert!(snr >= 50.0, "channel {c}: {snr}");
    }
}

/// The fixed-point sums do not depend on the order of the records, on how they are cut into
/// calls or on the dispatch chunk size: bit-identical images.
#[test]
fn gpu_sums_are_order_and_chunk_independent() {
    let Some(ctx) = gpu() else { return };
    let (g, coeffs) = coefficients(Family::Cubic, 1);
    let p = plan(&g, &coeffs[..CUBIC_SUBSET], &ViewSpec::single(view()), 1);
    let records: Vec<SplatRecord> = p.batches.iter().flat_map(|b| b.1.clone()).collect();
    let layout = p.plan.layout();
    let mut a = GpuBackend::new(ctx.clone()).unwrap();
    a.begin(layout).unwrap();
    a.accumulate(&p.plan.atlas(), &records).unwrap();
    let first = a.read().unwrap();
    let mut reversed = records.clone();
    reversed.reverse();
    let mut b = GpuBackend::with_options(
        ctx.clone(),
        GpuOptions {
            max_chunk: 777,
            wait: false,
            max_atlas_binding: None,
        },
    )
    .unwrap();
    b.begin(layout).unwrap();
    // The same total in one call: same exponent, so the same integers.
    b.accumulate(&p.plan.atlas(), &reversed).unwrap();
    assert_eq!(a.scale_exponent(), b.scale_exponent());
    assert!(first.data.iter().any(|v| *v != 0.0));
    assert_eq!(first.data, b.read().unwrap().data);
    // `begin` clears: the same again on a reused target.
    b.begin(layout).unwrap();
    b.accumulate(&p.plan.atlas(), &records).unwrap();
    assert_eq!(first.data, b.read().unwrap().data);
}

/// A first batch far lighter than the next forces the sums to be rescaled (the exponent
/// drops); the image still matches the CPU's.
#[test]
fn gpu_rescales_when_the_mass_grows() {
    let Some(ctx) = gpu() else { return };
    let (g, coeffs) = coefficients(Family::Linear, 1);
    let p = plan(&g, &coeffs, &ViewSpec::single(view()), 1);
    let records: Vec<SplatRecord> = p.batches.iter().flat_map(|b| b.1.clone()).collect();
    let light: Vec<SplatRecord> = records[..2000]
        .iter()
        .map(|r| SplatRecord {
            value: r.value * 1e-9,
            ..*r
        })
        .collect();
    let layout = p.plan.layout();
    let mut cpu = CpuBackend::new();
    let mut gpu = GpuBackend::new(ctx).unwrap();
    cpu.begin(layout).unwrap();
    gpu.begin(layout).unwrap();
    for batch in [&light[..], &records[..]] {
        cpu.accumulate(&p.plan.atlas(), batch).unwrap();
        gpu.accumulate(&p.plan.atlas(), batch).unwrap();
    }
    let e_after_light = {
        let mut probe = GpuBackend::new(gpu.context().clone()).unwrap();
        probe.begin(layout).unwrap();
        probe.accumulate(&p.plan.atlas(), &light).unwrap();
        probe.scale_exponent().unwrap()
    };
    assert!(gpu.scale_exponent().unwrap() < e_after_light - 20);
    let snr = snr_db(&cpu.read().unwrap().data, &gpu.read().unwrap().data);
    eprintln!("after a rescale: SNR {snr:.1} dB");
    assert!(snr >= 50.0, "{snr}");
}

fn byte_diffs(a: &[u8], b: &[u8]) -> (u8, usize) {
    assert_eq!(a.len(), b.len());
    let max = a
        .iter()
        .zip(b)
        .map(|(x, y)| x.abs_diff(*y))
        .max()
        .unwrap_or(0);
    (max, a.iter().zip(b).filter(|(x, y)| x != y).count())
}

/// The display pass maps the sums as the PNG writer does: grey multiview with the automatic
/// window, and RGB through a colour matrix and per-pixel offsets with a given window. Bytes
/// differ by at most one level (f32 against f64 at rounding ties), rarely.
#[test]
fn display_matches_the_png_mapping() {
    let Some(ctx) = gpu() else { return };
    // Grey, multiview, automatic window.
    let (g, coeffs) = coefficients(Family::Haar, 1);
    let spec = ViewSpec {
        view: view(),
        multiview: true,
    };
    let p = plan(&g, &coeffs[..20_000], &spec, 1);
    let (cpu, _, _) = render_both(&ctx, &p);
    let mut gpu = accumulated(&ctx, &p);
    let texture = gpu.display(&DisplayOptions::default()).unwrap();
    assert_eq!((texture.width(), texture.height()), (300, 84));
    let shown = gpu.read_display().unwrap();
    let own = gpu.read().unwrap().to_rgba8(None).unwrap();
    let (max, n) = byte_diffs(&shown, &own);
    eprintln!("grey display vs its own image's PNG mapping: max {max}, {n} bytes differ");
    assert!(max <= 1 && n * 100 <= shown.len(), "max {max}, {n} differ");
    let reference = cpu.to_rgba8(None).unwrap();
    let (max, n) = byte_diffs(&shown, &reference);
    eprintln!("grey display vs the CPU backend's PNG mapping: max {max}, {n} bytes differ");
    assert!(max <= 1 && n * 100 <= shown.len(), "max {max}, {n} differ");
    assert!(shown
        .chunks_exact(4)
        .all(|px| px[3] == 255 && px[0] == px[1] && px[1] == px[2]));

    // RGB through a colour matrix with offsets, given window.
    let (g, coeffs) = coefficients(Family::Linear, 3);
    let p = plan(&g, &coeffs[..30_000], &ViewSpec::single(view()), 3);
    let (cpu, _, _) = render_both(&ctx, &p);
    let mut gpu = accumulated(&ctx, &p);
    let offset: Vec<f32> = (0..cpu.width * cpu.height * 3)
        .map(|i| (i % 97) as f32 * 0.3)
        .collect();
    let colour = ColorMap {
        matrix: Some([
            [1.0, 0.956, 0.621],
            [1.0, -0.272, -0.647],
            [1.0, -1.106, 1.703],
        ]),
        offset: Some(offset.into()),
    };
    let mapped = colour.apply(&cpu).unwrap();
    let window = mapped.percentiles(2.0, 97.0);
    let options = DisplayOptions {
        window: Some(window),
        colour: Some(colour),
        grid: None,
    };
    gpu.display(&options).unwrap();
    let shown = gpu.read_display().unwrap();
    let reference = mapped.to_rgba8(Some(window)).unwrap();
    let (max, n) = byte_diffs(&shown, &reference);
    eprintln!("rgb display vs CPU colour map + PNG mapping: max {max}, {n} bytes differ");
    assert!(max <= 1 && n * 100 <= shown.len(), "max {max}, {n} differ");
    let distinct: std::collections::BTreeSet<u8> = shown.iter().copied().collect();
    assert!(distinct.len() > 100, "the image is not flat");
}

/// The display pass lays multiview's three panels out as a window does (2×2 with an empty
/// cell, a column, a row) as `arrange` + the PNG mapping do on the host, and refuses a grid
/// that cannot hold the views or a colour map that does not fit the image.
#[test]
fn display_lays_views_out_in_a_grid() {
    use wavesplat_viewer::window::controls::arrange;
    let Some(ctx) = gpu() else { return };
    let (g, coeffs) = coefficients(Family::Linear, 1);
    let spec = ViewSpec {
        view: view(),
        multiview: true,
    };
    let p = plan(&g, &coeffs[..20_000], &spec, 1);
    let mut gpu = accumulated(&ctx, &p);
    let image = gpu.read().unwrap();
    let window = image.percentiles(1.0, 99.0);
    for grid in [(2, 2), (1, 3), (3, 1)] {
        let options = DisplayOptions {
            window: Some(window),
            colour: None,
            grid: Some(grid),
        };
        let texture = gpu.display(&options).unwrap();
        let size = (texture.width() as usize, texture.height() as usize);
        let shown = gpu.read_display().unwrap();
        let reference = arrange(image.clone(), grid);
        assert_eq!(size, (reference.width, reference.height), "{grid:?}");
        let (max, n) = byte_diffs(&shown, &reference.to_rgba8(Some(window)).unwrap());
        eprintln!("grid {grid:?}: max {max}, {n} bytes differ");
        assert!(
            max <= 1 && n * 100 <= shown.len(),
            "{grid:?}: max {max}, {n} differ"
        );
    }
    for grid in [(1, 2), (2, 1), (0, 3)] {
        let options = DisplayOptions {
            window: Some(window),
            colour: None,
            grid: Some(grid),
        };
        assert!(
            matches!(gpu.display(&options), Err(BackendError::Display(_))),
            "{grid:?}"
        );
    }
    let bad = [
        ColorMap {
            matrix: Some([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]),
            offset: None,
        },
        ColorMap {
            matrix: None,
            offset: Some(vec![0.0; 7].into()),
        },
    ];
    for colour in bad {
        let options = DisplayOptions {
            colour: Some(colour),
            ..Default::default()
        };
        assert!(matches!(
            gpu.display(&options),
            Err(BackendError::Display(_))
        ));
    }
}

/// The automatic window from the device's samples is the host's `auto_window` of the shown
/// values: exactly (to f32 rounding) in an image of up to `MAX_WINDOW_SAMPLES` pixels, and
/// within 1 % of its width from every n-th pixel of a larger one; a flat (empty) image gets the
/// host's black window too.
#[test]
fn auto_window_from_device_samples_matches_the_host() {
    use wavesplat_viewer::backend::gpu::MAX_WINDOW_SAMPLES;
    let Some(ctx) = gpu() else { return };
    let (g, coeffs) = coefficients(Family::Linear, 1);
    let mut gpu = GpuBackend::new(ctx).unwrap();
    for (w, h, exact) in [(200, 150, true), (330, 270, false)] {
        assert_eq!(w * h <= MAX_WINDOW_SAMPLES, exact);
        let spec = ViewSpec::single(View::new(0.5, 0.3, w, h));
        let p = plan(&g, &coeffs[..30_000], &spec, 1);
        gpu.begin(p.plan.layout()).unwrap();
        let empty = gpu.auto_window(None).unwrap();
        assert_eq!(empty, gpu.read().unwrap().resolve_window(None).unwrap());
        for (_, r) in &p.batches {
            gpu.accumulate(&p.plan.atlas(), r).unwrap();
        }
        let offsets: Vec<f32> = (0..w * h).map(|i| (i % 13) as f32 * 0.05).collect();
        let colour = ColorMap {
            matrix: None,
            offset: Some(offsets.into()),
        };
        let host = colour.apply(&gpu.read().unwrap()).unwrap();
        let (lo, hi) = host.resolve_window(None).unwrap();
        let (dlo, dhi) = gpu.auto_window(Some(&colour)).unwrap();
        let tolerance = if exact { 1e-5 } else { 1e-2 } * (hi - lo);
        eprintln!("{w}x{h}: host ({lo}, {hi}), device samples ({dlo}, {dhi})");
        assert!(
            (dlo - lo).abs() <= tolerance && (dhi - hi).abs() <= tolerance,
            "{w}x{h}: host ({lo}, {hi}), device ({dlo}, {dhi})"
        );
    }
}

/// An atlas larger than what the device binds at once is read a window at a time (a 128 MB
/// binding limit is reached by a 160×120 multiview of a small volume): with windows of 64 KB
/// the sums are the very integers of one binding, for a multiview and a depth-cued view whose
/// atlas grows between batches; a table longer than half a window is refused, not misread.
#[test]
fn atlas_windows_give_the_sums_of_one_binding() {
    let Some(ctx) = gpu() else { return };
    let (g, coeffs) = coefficients(Family::Linear, 1);
    let cued = View::new(0.4, 0.7, 72, 64).with_cue(Cue {
        k: 0.03,
        direction: CueDirection::View,
    });
    for spec in [
        ViewSpec {
            view: view(),
            multiview: true,
        },
        ViewSpec::single(cued),
    ] {
        let p = plan(&g, &coeffs[..30_000], &spec, 1);
        let bytes = p.plan.atlas().data.len() * 4;
        assert!(
            bytes > 8 * 65_536,
            "atlas of {bytes} bytes: no windows to test"
        );
        let images: Vec<Image> = [None, Some(65_536)]
            .into_iter()
            .map(|max_atlas_binding| {
                let options = GpuOptions {
                    max_atlas_binding,
                    ..GpuOptions::default()
                };
                let mut gpu = GpuBackend::with_options(ctx.clone(), options).unwrap();
                gpu.begin(p.plan.layout()).unwrap();
                for (samples, records) in &p.batches {
                    gpu.accumulate(&p.atlas_for(*samples), records).unwrap();
                }
                gpu.read().unwrap()
            })
            .collect();
        assert_eq!(images[0].data, images[1].data, "{spec:?}");
        assert!(images[0].data.iter().any(|v| *v != 0.0));
    }
    let p = plan(&g, &coeffs[..2_000], &ViewSpec::single(view()), 1);
    let longest = p
        .plan
        .atlas()
        .phases
        .iter()
        .map(|r| r.cols * r.rows)
        .max()
        .unwrap() as u64;
    let options = GpuOptions {
        max_atlas_binding: Some((longest * 4).next_power_of_two() / 2),
        ..GpuOptions::default()
    };
    let mut gpu = GpuBackend::with_options(ctx, options).unwrap();
    gpu.begin(p.plan.layout()).unwrap();
    let all: Vec<SplatRecord> = p.batches.iter().flat_map(|(_, r)| r.clone()).collect();
    assert!(matches!(
        gpu.accumulate(&p.plan.atlas(), &all),
        Err(BackendError::Range(_))
    ));
}

/// Bad input is refused with typed errors, never a panic or a device error.
#[test]
fn gpu_refuses_bad_input() {
    let Some(ctx) = gpu() else { return };
    let (g, coeffs) = coefficients(Family::Haar, 1);
    let p = plan(&g, &coeffs[..100], &ViewSpec::single(view()), 1);
    let atlas = &p.plan.atlas();
    let good = p.batches[2].1[0];
    let mut b = GpuBackend::new(ctx).unwrap();
    assert!(matches!(
        b.accumulate(atlas, &[good]),
        Err(BackendError::Layout(_))
    ));
    assert!(matches!(b.read(), Err(BackendError::Layout(_))));
    b.begin(p.plan.layout()).unwrap();
    let bad_phase = SplatRecord {
        phase: atlas.phases.len() as u32,
        ..good
    };
    assert!(matches!(
        b.accumulate(atlas, &[good, bad_phase]),
        Err(BackendError::Phase { .. })
    ));
    let bad_view = SplatRecord { view: 1, ..good };
    assert!(matches!(
        b.accumulate(atlas, &[bad_view]),
        Err(BackendError::Target { .. })
    ));
    let nan = SplatRecord {
        value: f32::NAN,
        ..good
    };
    assert_eq!(
        b.accumulate(atlas, &[good, nan]),
        Err(BackendError::NotFinite { index: 1 })
    );
    // Far off screen: nothing added, no overflow in the shader's clipping.
    let far = [
        SplatRecord {
            x0: i32::MAX,
            y0: i32::MIN,
            ..good
        },
        SplatRecord {
            x0: i32::MIN,
            y0: i32::MAX - 3,
            ..good
        },
    ];
    assert_eq!(b.accumulate(atlas, &far).unwrap(), 0);
    assert!(b.read().unwrap().data.iter().all(|v| *v == 0.0));
    assert!(b
        .begin(Layout {
            width: 1 << 20,
            height: 1 << 20,
            channels: 1,
            views: 1,
        })
        .is_err());
    b.begin(Layout {
        width: 8,
        height: 8,
        channels: 2,
        views: 1,
    })
    .unwrap();
    assert!(matches!(
        b.display(&DisplayOptions::default()),
        Err(BackendError::Display(_))
    ));
    // The backend still works after all that.
    b.begin(p.plan.layout()).unwrap();
    assert!(b.accumulate(atlas, &[good]).unwrap() > 0);
    assert!(b.read().unwrap().data.iter().any(|v| *v != 0.0));
}

/// An adapter that does not exist is a typed error (whatever the machine has).
#[test]
fn missing_adapter_is_a_typed_error() {
    let request = AdapterRequest {
        name: Some("no such adapter 7f3a".into()),
        ..AdapterRequest::from_env()
    };
    match GpuContext::request(&request) {
        Err(BackendError::NoAdapter(m)) => assert!(m.contains("no such adapter 7f3a"), "{m}"),
        other => panic!("expected NoAdapter, got {other:?}"),
    }
}

/// `--cpu` gives the CPU backend; the default never picks a software adapter.
#[test]
fn selection_policy() {
    let cpu = select(BackendChoice::Cpu).unwrap();
    assert_eq!(cpu.backend.name(), "cpu");
    let auto = select(BackendChoice::Auto).unwrap();
    eprintln!("auto: {}", auto.reason);
    match wavesplat_viewer::backend::gpu::probe_adapter() {
        Ok(info) if info.device_type != wgpu::DeviceType::Cpu => {
            assert!(auto.backend.name().starts_with("gpu"), "{}", auto.reason)
        }
        _ => assert_eq!(auto.backend.name(), "cpu", "{}", auto.reason),
    }
}

/// The render session drives the GPU backend through the trait (boxed, as `select` gives it):
/// progressive frames with a small budget end on the CPU session's image.
#[test]
fn session_on_the_gpu_backend_matches_the_cpu_one() {
    use std::time::Duration;
    use wavesplat_compressor::encode::{compress, CompressOptions, Target};
    use wavesplat_compressor::phantom::Phantom;
    use wavesplat_viewer::session::RenderSession;
    let Some(ctx) = gpu() else { return };
    let bytes = compress(
        &Phantom::SheppLogan.generate([40, 36, 44]),
        &CompressOptions {
            target: Target::Fraction(0.1),
            refine: None,
            ..Default::default()
        },
        &|_, _| {},
    )
    .unwrap()
    .bytes;
    let file = wavesplat_codec::format::parse_file(&bytes).unwrap();
    let spec = ViewSpec {
        view: View::new(0.4, 1.1, 90, 70),
        multiview: true,
    };
    let gpu_backend: Box<dyn AccumulationBackend> = Box::new(GpuBackend::new(ctx).unwrap());
    let backends: [Box<dyn AccumulationBackend>; 2] = [Box::new(CpuBackend::new()), gpu_backend];
    let mut images = Vec::new();
    for backend in backends {
        let name = backend.name();
        let mut session =
            RenderSession::new(file.header.clone(), spec, backend, Default::default()).unwrap();
        for (id, p) in file.packets.iter().enumerate() {
            session.add_packet(id as u32, p).unwrap();
        }
        let mut frames = 0;
        while session.pending() > 0 {
            session.step(Duration::from_millis(5)).unwrap();
            frames += 1;
        }
        eprintln!("{name}: {frames} frames");
        assert!(frames > 1, "{name}: refinement took one frame");
        images.push(session.image().unwrap());
    }
    let snr = snr_db(&images[0].data, &images[1].data);
    eprintln!("session image, GPU vs CPU: SNR {snr:.1} dB");
    assert!(snr >= 50.0, "{snr}");
}

/// What a window shows with the GPU backend, made on the device (`device_display`), against
/// what it showed before, made on the host (the session's image, `arrange`, the window): an
/// intensity volume with an offset (air at −1000 times the path length), a colour volume (the
/// inverse basis and the origin colour), multiview in a 2×2 grid, the automatic window narrowed
/// and moved as the contrast and level keys do. A host backend has no device image.
#[test]
fn session_device_display_matches_the_host_path() {
    use std::time::Duration;
    use wavesplat_compressor::encode::{compress, CompressOptions, Target};
    use wavesplat_compressor::phantom::Phantom;
    use wavesplat_viewer::session::RenderSession;
    use wavesplat_viewer::window::controls::arrange;
    let Some(ctx) = gpu() else { return };
    let adjust = |(lo, hi): (f64, f64)| {
        let (c, w) = (0.5 * (lo + hi) + 0.1 * (hi - lo), 0.35 * (hi - lo));
        (c - w, c + w)
    };
    // The RGB head on a coloured background, so that its origin colour is not black.
    let dims = [36, 40, 30];
    let head = Phantom::RgbHead.generate(dims);
    let background = [40.0, 70.0, 20.0];
    let rgb = wavesplat_codec::volume::Volume::new(
        dims,
        head.spacing(),
        (0..3)
            .map(|c| head.channel(c).iter().map(|v| v + background[c]).collect())
            .collect(),
    )
    .unwrap();
    let ct = Phantom::Ct.generate(dims);
    let cases = [
        ("ct", &ct, false, (1, 1), false),
        ("ct", &ct, true, (2, 2), true),
        ("rgb", &rgb, false, (1, 1), true),
        ("rgb", &rgb, true, (1, 3), false),
    ];
    for (phantom, volume, multiview, grid, narrowed) in cases {
        let bytes = compress(
            volume,
            &CompressOptions {
                target: Target::Fraction(0.1),
                refine: None,
                ..Default::default()
            },
            &|_, _| {},
        )
        .unwrap()
        .bytes;
        let file = wavesplat_codec::format::parse_file(&bytes).unwrap();
        let mean = file.header.color.mean;
        assert!(
            mean.iter().any(|m| *m != 0.0),
            "{phantom}: no offset to show"
        );
        let spec = ViewSpec {
            view: View::new(0.4, 1.1, 64, 52),
            multiview,
        };
        let backend: Box<dyn AccumulationBackend> = Box::new(GpuBackend::new(ctx.clone()).unwrap());
        let mut session =
            RenderSession::new(file.header.clone(), spec, backend, Default::default()).unwrap();
        for (id, p) in file.packets.iter().enumerate() {
            session.add_packet(id as u32, p).unwrap();
        }
        while session.pending() > 0 {
            session.step(Duration::from_millis(20)).unwrap();
        }
        let host = session.image().unwrap();
        let window = match narrowed {
            true => adjust(host.resolve_window(None).unwrap()),
            false => host.resolve_window(None).unwrap(),
        };
        let reference = arrange(host, grid);
        let texture = session
            .device_display(|auto| if narrowed { adjust(auto) } else { auto }, grid)
            .unwrap()
            .expect("the GPU backend shows on the device")
            .clone();
        assert_eq!(
            (texture.width() as usize, texture.height() as usize),
            (reference.width, reference.height)
        );
        let shown = ctx.read_rgba8(&texture).unwrap();
        let (max, n) = byte_diffs(&shown, &reference.to_rgba8(Some(window)).unwrap());
        eprintln!("{phantom}, multiview {multiview}, grid {grid:?}: max {max}, {n} bytes differ");
        assert!(max <= 1 && n * 100 <= shown.len(), "max {max}, {n} differ");
        let distinct: std::collections::BTreeSet<u8> = shown.iter().copied().collect();
        assert!(distinct.len() > 30, "the image is not flat");
    }
    let cpu: Box<dyn AccumulationBackend> = Box::new(CpuBackend::new());
    let bytes = compress(
        &Phantom::Ct.generate([20, 20, 20]),
        &CompressOptions::default(),
        &|_, _| {},
    )
    .unwrap()
    .bytes;
    let file = wavesplat_codec::format::parse_file(&bytes).unwrap();
    let mut session = RenderSession::new(
        file.header,
        ViewSpec::single(View::new(0.0, 0.0, 16, 16)),
        cpu,
        Default::default(),
    )
    .unwrap();
    assert!(session.device_display(|w| w, (1, 1)).unwrap().is_none());
}
