//! Running one case: rendering the splats (of an exact decomposition or of a compressed and
//! decoded file) against the reference ray caster, measuring the scale-free error, and judging
//! the result into its row, with a panic caught as that case's failure.

use super::inputs::reference_options;
use super::report::Row;
use super::{Case, Criterion, Outcome};
use anyhow::{bail, Result};
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::time::Instant;
use wavesplat_codec::dwt::decompose_channel;
use wavesplat_codec::family::Family;
use wavesplat_codec::format::packet::Coefficient;
use wavesplat_codec::format::parse_file;
use wavesplat_codec::layout::Geometry;
use wavesplat_codec::metrics::snr_db;
use wavesplat_codec::volume::Volume;
use wavesplat_compressor::encode::{compress, CompressOptions};
use wavesplat_viewer::color::to_rgb_for_spec;
use wavesplat_viewer::open::load_coefficients;
use wavesplat_viewer::{
    render_reference, Image, PaddedVolume, ReferenceOptions, RenderOptions, Renderer, View,
    ViewSpec,
};

/// Splats every coefficient of channel data `data` (exact decomposition with the files'
/// default margin) with renderer `options`, and renders the reference on the volume they
/// reconstruct.
pub(super) fn renderer_case(
    dims: [usize; 3],
    data: &[f32],
    family: Family,
    levels: usize,
    view: &View,
    reference: ReferenceOptions,
    options: RenderOptions,
) -> Result<Outcome> {
    let g = Geometry::new(
        dims,
        family,
        levels,
        Geometry::separating_margin(family, levels),
    )?;
    let coeffs = Coefficient::all_of(&g, 0, &decompose_channel(data, &g));
    let vol = PaddedVolume::from_coefficients(&coeffs, &g, 1)?;
    let mut r = Renderer::new(options);
    let image = r.render(&coeffs, &g, view)?;
    let reference = render_reference(&vol, view, &reference)?;
    Ok(Outcome::Images {
        image,
        reference,
        scale: None,
    })
}

/// Compresses `volume`, decodes the whole file, splats it (back to RGB for colour) and renders
/// the reference on the original volume.
pub(super) fn pipeline_case(
    volume: &Volume,
    opts: &CompressOptions,
    view: &View,
) -> Result<Outcome> {
    let c = compress(volume, opts, &|_, _| {})?;
    let header = parse_file(&c.bytes)?.header;
    let (_, coeffs) = load_coefficients(&c.bytes, None, None)?;
    let mut r = Renderer::new(RenderOptions {
        channels: header.channels,
        ..RenderOptions::default()
    });
    let coded = r.render(&coeffs, &header.geometry, view)?;
    let image = to_rgb_for_spec(&coded, &header, &ViewSpec::single(*view))?;
    // Haar boxes are the voxels on any grid; for the splines the function of the complete
    // transform with one translate per basis function (as the renderer draws), which differs
    // from the voxel spline near the faces by the boundary handling (a property of the margin,
    // measured in BENCHMARKS.md, not of the numerics judged here). The file codes an intensity
    // volume less its offset and draws the offset as offset × the box's path length, so the
    // spline reference is the complete transform of the volume less the offset, with the
    // offset's path lengths added the same way.
    let g = &header.geometry;
    let spline_intensity = g.family != Family::Haar && volume.channel_count() == 1;
    let original = if spline_intensity {
        let offset = header.color.mean[0];
        let shifted: Vec<f32> = volume
            .channel(0)
            .iter()
            .map(|v| (f64::from(*v) - offset) as f32)
            .collect();
        let exact = Coefficient::all_of(g, 0, &decompose_channel(&shifted, g));
        PaddedVolume::from_coefficients(&exact, g, 1)?
    } else {
        PaddedVolume::from_volume(volume.channels(), g)
    };
    let reference = render_reference(
        &original,
        view,
        &reference_options(header.geometry.family, 0.0),
    )?;
    let reference = if spline_intensity {
        to_rgb_for_spec(&reference, &header, &ViewSpec::single(*view))?
    } else {
        reference
    };
    Ok(Outcome::Images {
        image,
        reference,
        scale: None,
    })
}

/// A depth-cued renderer case whose max_rel is taken against the peak of the *un-cued*
/// reference: the splats sum terms of the coefficients' own scale in f32, so their absolute
/// precision is set by the un-cued image however much the cue takes away.
pub(super) fn cue_case(
    dims: [usize; 3],
    data: &[f32],
    family: Family,
    view: &View,
) -> Result<Outcome> {
    let k = view.cue.map_or(0.0, |c| c.k);
    let Outcome::Images {
        image, reference, ..
    } = renderer_case(
        dims,
        data,
        family,
        2,
        view,
        reference_options(family, k),
        RenderOptions::default(),
    )?
    else {
        bail!("a renderer case renders");
    };
    let plain = View { cue: None, ..*view };
    let g = Geometry::new(dims, family, 2, Geometry::separating_margin(family, 2))?;
    let coeffs = Coefficient::all_of(&g, 0, &decompose_channel(data, &g));
    let vol = PaddedVolume::from_coefficients(&coeffs, &g, 1)?;
    let uncued = render_reference(&vol, &plain, &reference_options(family, 0.0))?;
    let scale = uncued
        .data
        .iter()
        .fold(0.0f64, |m, v| m.max((*v as f64).abs()));
    Ok(Outcome::Images {
        image,
        reference,
        scale: Some(scale),
    })
}

/// Scale-free error of `image` against `reference`: (max_rel, SNR dB, non-finite count).
fn measure(image: &Image, reference: &Image, scale: Option<f64>) -> (f64, f64, usize) {
    let non_finite = image
        .data
        .iter()
        .chain(&reference.data)
        .filter(|v| !v.is_finite())
        .count();
    if image.data.len() != reference.data.len() {
        return (f64::INFINITY, f64::NEG_INFINITY, non_finite);
    }
    let peak = scale.unwrap_or_else(|| {
        reference
            .data
            .iter()
            .fold(0.0f64, |m, v| m.max((*v as f64).abs()))
    });
    let max_err = image
        .data
        .iter()
        .zip(&reference.data)
        .fold(0.0f64, |m, (a, b)| m.max((*a as f64 - *b as f64).abs()));
    let max_rel = if max_err == 0.0 {
        0.0
    } else if peak == 0.0 {
        f64::INFINITY
    } else {
        max_err / peak
    };
    // SNR is meaningless against a black reference (−∞ for any non-zero image): NaN, written
    // as an empty field.
    let snr = if reference.data.iter().all(|v| *v == 0.0) {
        f64::NAN
    } else {
        snr_db(&reference.data, &image.data)
    };
    (max_rel, snr, non_finite)
}

fn panic_message(p: &(dyn std::any::Any + Send)) -> String {
    p.downcast_ref::<&str>()
        .map(|s| s.to_string())
        .or_else(|| p.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "non-string panic".into())
}

/// Runs one case under `catch_unwind` (a panic is that case's failure) and judges it.
pub fn run_case(c: &Case) -> Row {
    let t = Instant::now();
    let result = catch_unwind(AssertUnwindSafe(|| (c.run)()));
    let mut row = Row {
        category: c.category,
        name: c.name.clone(),
        params: c.params.clone(),
        outcome: String::new(),
        max_rel: f64::NAN,
        snr_db: f64::NAN,
        non_finite: 0,
        pass: false,
        excluded: false,
        criterion: c.criterion.describe(),
        seconds: 0.0,
    };
    match result {
        Err(p) => row.outcome = format!("panicked: {}", panic_message(p.as_ref())),
        Ok(Err(e)) => row.outcome = format!("error: {e:#}"),
        Ok(Ok(Outcome::Rejected(msg))) => {
            row.pass = c.criterion == Criterion::Refused;
            row.outcome = format!("rejected: {msg}");
        }
        Ok(Ok(Outcome::Images {
            image,
            reference,
            scale,
        })) => {
            let (max_rel, snr, non_finite) = measure(&image, &reference, scale);
            row.max_rel = max_rel;
            row.snr_db = snr;
            row.non_finite = non_finite;
            row.outcome = "rendered".into();
            row.pass = non_finite == 0
                && match c.criterion {
                    // No SNR against a black reference: max_rel alone decides (relative to
                    // the case's scale, or 0 only for an exactly black image).
                    Criterion::Match { snr_db, max_rel: m } => {
                        (snr.is_nan() || snr >= snr_db) && max_rel <= m
                    }
                    Criterion::NoWorseThanZero => snr >= 0.0 || (snr.is_nan() && max_rel == 0.0),
                    Criterion::Refused => {
                        row.outcome = "accepted invalid input".into();
                        false
                    }
                };
        }
    }
    if let (Some(why), false) = (c.known, row.pass) {
        row.outcome = format!("{} (known: {why})", row.outcome);
    }
    row.seconds = t.elapsed().as_secs_f64();
    row
}

/// The row of a known failure left out of `--quick`.
pub fn excluded_row(c: &Case) -> Row {
    Row {
        category: c.category,
        name: c.name.clone(),
        params: c.params.clone(),
        outcome: format!(
            "excluded from --quick: {}",
            c.known.unwrap_or("known failure")
        ),
        max_rel: f64::NAN,
        snr_db: f64::NAN,
        non_finite: 0,
        pass: false,
        excluded: true,
        criterion: c.criterion.describe(),
        seconds: 0.0,
    }
}
