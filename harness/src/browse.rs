//! Browsing a cached volume the way the demo and `bench refine` do: a fresh render session on
//! the chosen backend fed by the cache's refinement stream (previews on), walked along a view
//! path; the one probe of the adapters that picks that backend, and the reference ray caster's
//! settings used to score the frames.

use anyhow::{Context, Result};
use std::time::Duration;
use wavesplat_client::VolumeKey;
use wavesplat_codec::format::Header;
use wavesplat_codec::view::ViewSpec;
use wavesplat_viewer::backend::{select, AccumulationBackend, BackendChoice};
use wavesplat_viewer::session::{RenderSession, SessionOptions};
use wavesplat_viewer::source::{CacheSource, CacheSourceOptions};
use wavesplat_viewer::walk::{walk, FrameSample, PathStep, WalkOptions};
use wavesplat_viewer::{FrameLoop, ReferenceOptions};

/// The reference renderer's settings for scoring: 2×2 rays per pixel and a quarter-voxel step
/// (a quarter of the default's rays at half its samples per ray; its own error is far below
/// the compressed images' error it scores, see BENCHMARKS.md).
pub fn reference_options() -> ReferenceOptions {
    ReferenceOptions {
        supersample: 2,
        step: 0.25,
    }
}

/// Opens the backend `choice` asks for once (`Auto`: the GPU only on a hardware adapter) and
/// returns which one it is with the reason in words, so that the sessions that follow do not
/// probe again and a GPU asked for but missing fails before them.
pub fn probe_backend(choice: BackendChoice) -> Result<(BackendChoice, String)> {
    let probe = select(choice).context("choosing the accumulation backend")?;
    let choice = if probe.backend.name().starts_with("cpu") {
        BackendChoice::Cpu
    } else {
        BackendChoice::Gpu
    };
    Ok((choice, probe.reason))
}

/// A frame loop fed by a cache, on whichever backend was chosen.
pub type CacheFrameLoop = FrameLoop<Box<dyn AccumulationBackend>, CacheSource>;

/// A fresh session on `backend` for `spec`, fed by the cache's stream of `name` (previews on).
pub fn open_frame_loop(
    url: &str,
    name: &str,
    spec: ViewSpec,
    options: CacheSourceOptions,
    backend: BackendChoice,
) -> Result<(Header, CacheFrameLoop)> {
    let (source, header) =
        CacheSource::open(url, VolumeKey::Name(name.to_string()), spec, options)?;
    let selected = select(backend).context("choosing the accumulation backend")?;
    let session = RenderSession::new(
        header.header.clone(),
        spec,
        selected.backend,
        SessionOptions {
            preview: Some(SessionOptions::default_preview()),
            ..SessionOptions::default()
        },
    )?;
    Ok((header.header, FrameLoop::new(session, source)))
}

/// Opens `name` at the cache and walks `path` with a fresh session on `backend`; returns the
/// volume's header, the backend's name and the frames.
pub fn browse(
    url: &str,
    name: &str,
    spec: ViewSpec,
    path: &[PathStep],
    frame: Duration,
    backend: BackendChoice,
) -> Result<(Header, String, Vec<FrameSample>)> {
    let (header, mut frames) =
        open_frame_loop(url, name, spec, CacheSourceOptions::default(), backend)?;
    let backend = frames.session.backend_name();
    let samples = walk(&mut frames, path, &WalkOptions::new(frame))?;
    Ok((header, backend, samples))
}
