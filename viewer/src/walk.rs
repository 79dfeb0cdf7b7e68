//! Scripted walks through the frame loop: a view path (rests, turns, zooms) driven frame by
//! frame as a user's drag would drive it, paced like a display (a frame that finishes early
//! waits for the next tick, so the network gets the time a real viewer gives it), recording
//! per-frame figures and, optionally, each frame's image. The demo and `bench refine` score
//! the images against the reference renderer afterwards, so scoring never slows the walk.

use crate::backend::AccumulationBackend;
use crate::frame::FrameLoop;
use crate::image::Image;
use crate::session::SessionError;
use crate::source::PacketSource;
use std::time::{Duration, Instant};
use wavesplat_codec::layout::Geometry;
use wavesplat_codec::view::{Camera, Orientation, ViewError, ViewSpec};

/// One stop of a path: a view held for some frames.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PathStep {
    /// The view.
    pub spec: ViewSpec,
    /// Frames to hold it (the most, with `until_converged`).
    pub frames: usize,
    /// End the step early once the image is converged: everything the source has is splatted
    /// with exact tables and the source has nothing more to send.
    pub until_converged: bool,
}

impl PathStep {
    /// Holds `spec` until converged, for at most `max_frames`.
    pub fn rest(spec: ViewSpec, max_frames: usize) -> PathStep {
        PathStep {
            spec,
            frames: max_frames,
            until_converged: true,
        }
    }
}

/// A turn of `spec` from the angles (α, β) by (Δα, Δβ) radians in `steps` equal steps of
/// `frames_per_step` frames each (a drag delivering a new view every few frames). The last
/// step is the end view.
pub fn turn(
    spec: ViewSpec,
    from: [f64; 2],
    by: [f64; 2],
    steps: usize,
    frames_per_step: usize,
) -> Vec<PathStep> {
    let steps = steps.max(1);
    (1..=steps)
        .map(|i| {
            let f = i as f64 / steps as f64;
            let mut s = spec;
            s.view.orientation = Orientation::Angles {
                alpha: from[0] + f * by[0],
                beta: from[1] + f * by[1],
            };
            PathStep {
                spec: s,
                frames: frames_per_step.max(1),
                until_converged: false,
            }
        })
        .collect()
}

/// A zoom from `spec` to `zoom` pixels per unit of spacing and `pan` (units of spacing along
/// the screen axes) for a volume of `geometry`, geometric in zoom and linear in pan, in `steps`
/// steps of `frames_per_step` frames.
pub fn zoom_to(
    spec: ViewSpec,
    geometry: &Geometry,
    zoom: f64,
    pan: [f64; 2],
    steps: usize,
    frames_per_step: usize,
) -> Result<Vec<PathStep>, ViewError> {
    let steps = steps.max(1);
    let z0 = match spec.view.zoom {
        Some(z) => z,
        None => Camera::new(&spec.view, geometry)?.zoom,
    };
    let p0 = spec.view.pan;
    Ok((1..=steps)
        .map(|i| {
            let f = i as f64 / steps as f64;
            let mut s = spec;
            s.view.zoom = Some(z0 * (zoom / z0).powf(f));
            s.view.pan = [p0[0] + f * (pan[0] - p0[0]), p0[1] + f * (pan[1] - p0[1])];
            PathStep {
                spec: s,
                frames: frames_per_step.max(1),
                until_converged: false,
            }
        })
        .collect())
}

/// How to walk.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WalkOptions {
    /// Frame budget (and the display tick the walk is paced to).
    pub frame: Duration,
    /// Keep every frame's image (display space) in the samples.
    pub capture: bool,
    /// Wait at most this long in a step for a source that is neither done nor sending.
    pub stall_limit: Duration,
}

impl WalkOptions {
    /// A walk at `frame` per frame, capturing images.
    pub fn new(frame: Duration) -> WalkOptions {
        WalkOptions {
            frame,
            capture: true,
            stall_limit: Duration::from_secs(10),
        }
    }
}

/// One frame of a walk.
#[derive(Debug, Clone)]
pub struct FrameSample {
    /// Frame number from 1.
    pub frame: u64,
    /// Index of the path step the frame belongs to.
    pub step: usize,
    /// Frame number within its step, from 1.
    pub frame_in_step: u64,
    /// Time from the start of the walk to the end of this frame's work.
    pub t: Duration,
    /// Time the frame's work took (against the budget).
    pub frame_time: Duration,
    /// Packets received so far.
    pub packets: u64,
    /// Bytes of packets received so far.
    pub bytes: u64,
    /// Coefficients held by the session.
    pub coefficients_held: usize,
    /// Coefficients splatted into the current view's image.
    pub splatted: u64,
    /// Coefficients splatted in this frame.
    pub splatted_this_frame: usize,
    /// Coefficients held but not splatted because this view does not see them (zero visible
    /// energy: work the scene leaves out).
    pub invisible: u64,
    /// Splat batches in this frame.
    pub batches: usize,
    /// Batches that ended past the frame's deadline (at most 1).
    pub batches_past_deadline: usize,
    /// Coefficients queued at the end of the frame.
    pub pending: usize,
    /// Whether the frame used the view's exact footprint tables.
    pub exact: bool,
    /// Whether the image was converged at the end of this frame (nothing pending, nothing more
    /// coming).
    pub converged: bool,
    /// Whether the memory bound was what stopped the session taking packets.
    pub memory_full: bool,
    /// The image (display space), when capturing.
    pub image: Option<Image>,
}

impl FrameSample {
    /// The CSV columns of [`FrameSample::csv_row`].
    pub const CSV_COLUMNS: &'static str = "frame,step,t_ms,frame_ms,packets,bytes,coefficients_held,splatted,splatted_this_frame,invisible,batches,batches_past_deadline,pending,exact,converged,memory_full";

    /// The sample's figures as one CSV row (no image), in the order of
    /// [`FrameSample::CSV_COLUMNS`].
    pub fn csv_row(&self) -> String {
        format!(
            "{},{},{:.3},{:.3},{},{},{},{},{},{},{},{},{},{},{},{}",
            self.frame,
            self.step,
            self.t.as_secs_f64() * 1e3,
            self.frame_time.as_secs_f64() * 1e3,
            self.packets,
            self.bytes,
            self.coefficients_held,
            self.splatted,
            self.splatted_this_frame,
            self.invisible,
            self.batches,
            self.batches_past_deadline,
            self.pending,
            self.exact,
            self.converged,
            self.memory_full
        )
    }
}

/// Walk failures.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum WalkError {
    /// The session refused a view or a packet.
    #[error(transparent)]
    Session(#[from] SessionError),
    /// The source neither sent anything nor finished for too long.
    #[error("the packet source stalled for {waited:?} at step {step}: {problem}")]
    Stalled {
        /// The step.
        step: usize,
        /// How long it waited.
        waited: Duration,
        /// What the source said.
        problem: String,
    },
}

/// Walks `path` through `frames`: each step sets its view (if it differs from the current
/// one) and runs frames until its frame count or, for a rest, convergence.
pub fn walk<B: AccumulationBackend, S: PacketSource>(
    frames: &mut FrameLoop<B, S>,
    path: &[PathStep],
    options: &WalkOptions,
) -> Result<Vec<FrameSample>, WalkError> {
    let start = Instant::now();
    let mut out = Vec::new();
    let mut n = 0u64;
    for (i, step) in path.iter().enumerate() {
        if *frames.session.spec() != step.spec {
            frames.set_view(step.spec)?;
        }
        let mut stalled_since: Option<Instant> = None;
        let mut k = 0u64;
        while (k as usize) < step.frames.max(1) {
            let tick = Instant::now();
            let report = frames.frame(options.frame)?;
            let t = start.elapsed();
            n += 1;
            k += 1;
            let status = frames.source_status();
            let stats = frames.session.stats();
            let converged = report.idle() && status.done;
            let image = if options.capture {
                Some(frames.session.image()?)
            } else {
                None
            };
            out.push(FrameSample {
                frame: n,
                step: i,
                frame_in_step: k,
                t,
                frame_time: report.elapsed,
                packets: status.packets,
                bytes: status.bytes,
                coefficients_held: stats.coefficients_held,
                splatted: stats.splatted_in_view,
                splatted_this_frame: report.coefficients,
                invisible: stats.invisible_in_view,
                batches: report.batches,
                batches_past_deadline: report.batches_past_deadline,
                pending: report.pending,
                exact: report.exact,
                converged,
                memory_full: frames.session.memory_full(),
                image,
            });
            if converged && step.until_converged {
                break;
            }
            // A rest waiting on a source that sends nothing: give up after the stall limit
            // rather than spin forever (the caller reports the source's problem).
            if report.idle() && !status.done {
                let since = *stalled_since.get_or_insert_with(Instant::now);
                if since.elapsed() > options.stall_limit {
                    return Err(WalkError::Stalled {
                        step: i,
                        waited: since.elapsed(),
                        problem: status.problem.unwrap_or_else(|| "no packets".into()),
                    });
                }
            } else {
                stalled_since = None;
            }
            // Pace to the display tick.
            if let Some(rest) = options.frame.checked_sub(tick.elapsed()) {
                std::thread::sleep(rest);
            }
        }
    }
    Ok(out)
}

/// The p-th percentile (0..=100, nearest rank) of `values`; None when empty.
pub fn percentile(values: &[f64], p: f64) -> Option<f64> {
    if values.is_empty() {
        return None;
    }
    let mut v: Vec<f64> = values.iter().copied().filter(|x| !x.is_nan()).collect();
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    let rank = ((p.clamp(0.0, 100.0) / 100.0) * v.len() as f64).ceil() as usize;
    Some(v[rank.clamp(1, v.len()) - 1])
}

#[cfg(test)]
mod tests {
    use super::*;
    use wavesplat_codec::view::View;

    #[test]
    fn a_turn_ends_at_the_target_view() {
        let s = ViewSpec::single(View::new(0.1, 0.2, 8, 8));
        let t = turn(s, [0.1, 0.2], [1.0, -0.5], 4, 2);
        assert_eq!(t.len(), 4);
        let angles = |p: &PathStep| match p.spec.view.orientation {
            Orientation::Angles { alpha, beta } => (alpha, beta),
            _ => panic!("a turn gives angles"),
        };
        let (a, b) = angles(&t[3]);
        assert!((a - 1.1).abs() < 1e-12 && (b + 0.3).abs() < 1e-12);
        assert!((angles(&t[0]).0 - 0.35).abs() < 1e-12);
        assert!(t.iter().all(|p| p.frames == 2 && !p.until_converged));
    }

    #[test]
    fn a_zoom_is_geometric_and_ends_at_the_target() {
        let s = ViewSpec::single(View::new(0.0, 0.0, 64, 64).with_zoom(1.0));
        let g = Geometry::new([32, 32, 32], wavesplat_codec::family::Family::Linear, 1, 0).unwrap();
        let z = zoom_to(s, &g, 4.0, [8.0, -8.0], 2, 1).unwrap();
        assert!((z[0].spec.view.zoom.unwrap() - 2.0).abs() < 1e-12);
        assert!((z[1].spec.view.zoom.unwrap() - 4.0).abs() < 1e-12);
        assert_eq!(z[1].spec.view.pan, [8.0, -8.0]);
    }

    #[test]
    fn percentiles_use_the_nearest_rank() {
        let v: Vec<f64> = (1..=100).map(f64::from).collect();
        assert_eq!(percentile(&v, 50.0), Some(50.0));
        assert_eq!(percentile(&v, 95.0), Some(95.0));
        assert_eq!(percentile(&v, 100.0), Some(100.0));
        assert_eq!(percentile(&v, 0.0), Some(1.0));
        assert_eq!(percentile(&[], 50.0), None);
        assert_eq!(percentile(&[f64::NAN, 3.0], 50.0), Some(3.0));
    }
}
