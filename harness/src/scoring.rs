//! Scoring walks against ground truth: the reference ray caster's image of the original,
//! uncompressed volume for each distinct view of a walk (one camera, or the three multiview
//! cameras side by side, with the walk's depth cue), and per frame Q_I in the paper's units
//! (eq. 18) and the conventional SNR against it. References are computed once per view and
//! after the walk, so scoring never slows the frames it scores.

use anyhow::{Context, Result};
use std::collections::HashMap;
use wavesplat_codec::layout::Geometry;
use wavesplat_codec::metrics::{q_i_paper_db, snr_db};
use wavesplat_codec::view::{resolve_cue, ViewSpec};
use wavesplat_codec::volume::Volume;
use wavesplat_viewer::walk::{FrameSample, PathStep};
use wavesplat_viewer::{render_reference_camera, Image, PaddedVolume, ReferenceOptions};

/// The original volume in the compressed file's geometry, ready for the reference renderer.
pub struct GroundTruth {
    padded: PaddedVolume,
    options: ReferenceOptions,
}

impl GroundTruth {
    /// `volume` laid out in `geometry` (the header's: same padding and family). `options`
    /// trades the reference's accuracy for its time (rays per pixel, step along rays).
    pub fn new(volume: &Volume, geometry: &Geometry, options: ReferenceOptions) -> GroundTruth {
        GroundTruth {
            padded: PaddedVolume::from_volume(volume.channels(), geometry),
            options,
        }
    }

    /// The reference image of `spec` (views side by side for multiview).
    pub fn image(&self, spec: &ViewSpec) -> Result<Image> {
        let g = &self.padded.geometry;
        let cameras = spec.cameras(g).context("reference cameras")?;
        let cue = match &spec.view.cue {
            Some(c) => Some(resolve_cue(c, &cameras[0], g).context("reference depth cue")?),
            None => None,
        };
        let images: Vec<Image> = cameras
            .iter()
            .map(|c| render_reference_camera(&self.padded, c, cue, &self.options))
            .collect();
        Ok(if images.len() == 1 {
            images.into_iter().next().expect("one image")
        } else {
            Image::hconcat(&images)
        })
    }
}

/// Quality of one frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameQuality {
    /// Q_I in the paper's units (dB).
    pub q_i: f64,
    /// Conventional SNR (dB).
    pub snr: f64,
}

/// Q_I and SNR of every sampled frame against the reference image of its view, with a cache
/// of reference images by path step, kept across walks of one path.
pub fn score_with(
    truth: &GroundTruth,
    path: &[PathStep],
    samples: &[FrameSample],
    references: &mut HashMap<usize, Image>,
) -> Result<Vec<Option<FrameQuality>>> {
    score_reporting(truth, path, samples, references, &mut |_, _| {})
}

/// The path step whose reference image sample `s` is scored against: steps with equal views
/// share one.
fn reference_key(path: &[PathStep], s: &FrameSample) -> usize {
    path.iter()
        .position(|p| p.spec == path[s.step].spec)
        .unwrap_or(s.step)
}

/// [`score_with`], calling `report(done, needed)` after each reference image it ray casts (the
/// slow part: seconds each for the demo's volumes).
pub fn score_reporting(
    truth: &GroundTruth,
    path: &[PathStep],
    samples: &[FrameSample],
    references: &mut HashMap<usize, Image>,
    report: &mut dyn FnMut(usize, usize),
) -> Result<Vec<Option<FrameQuality>>> {
    let needed: std::collections::HashSet<usize> = samples
        .iter()
        .filter(|s| s.image.is_some())
        .map(|s| reference_key(path, s))
        .filter(|k| !references.contains_key(k))
        .collect();
    let (needed, mut done) = (needed.len(), 0);
    let mut out = Vec::with_capacity(samples.len());
    for s in samples {
        let Some(img) = &s.image else {
            out.push(None);
            continue;
        };
        let key = reference_key(path, s);
        if let std::collections::hash_map::Entry::Vacant(v) = references.entry(key) {
            v.insert(truth.image(&path[key].spec)?);
            done += 1;
            report(done, needed);
        }
        let r = &references[&key];
        anyhow::ensure!(
            r.data.len() == img.data.len(),
            "frame {} is {}x{}x{}, its reference {}x{}x{}",
            s.frame,
            img.width,
            img.height,
            img.channels,
            r.width,
            r.height,
            r.channels
        );
        out.push(Some(FrameQuality {
            q_i: q_i_paper_db(&r.data, &img.data),
            snr: snr_db(&r.data, &img.data),
        }));
    }
    Ok(out)
}

/// Q_I of the frame `n` frames into path step `step` (its last frame if it had fewer).
pub fn q_i_at(
    samples: &[FrameSample],
    quality: &[Option<FrameQuality>],
    step: usize,
    n: u64,
) -> Option<f64> {
    samples
        .iter()
        .zip(quality)
        .rfind(|(s, _)| s.step == step && s.frame_in_step <= n)
        .and_then(|(_, q)| q.map(|q| q.q_i))
}
