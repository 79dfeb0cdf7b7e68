//! Rendering a bricked volume ([`wavesplat_codec::format::bricked`]) as one: an X-ray image is
//! linear in the data and the bricks tile the whole, so the whole's image is the sum of the
//! bricks' images, each drawn by the ordinary splatting path with the whole's camera moved into
//! the brick's frame (the same zoom, a pan that puts the whole's centre where it belongs) and
//! clipped at the brick's faces, as a volume is clipped at its own. Depth cueing attenuates
//! from the whole's light-facing faces: a brick's own cue measures from its own faces, and the
//! two distances differ by a constant per brick, so its image is scaled by e^(−k·δ). Bricks
//! whose box projects off the image are neither decoded nor drawn. One planner serves every
//! brick (their footprint tables are the same for one view and depth). The geometry of placing
//! a view in the bricks is the codec's ([`wavesplat_codec::view::bricked`], which the cache
//! ranks with too), re-exported here.

use crate::backend::AccumulationBackend;
use crate::plan::{PlanOptions, Planner, SplatBuffers, SPLAT_BATCH};
use crate::{Image, RenderError, RenderStats};
use wavesplat_codec::format::bricked::{parse_bricked, BrickedFile};
use wavesplat_codec::format::packet::{decode_packets, PacketError};
use wavesplat_codec::format::{check_kept, parse_file, FormatError, Header};
use wavesplat_codec::layout::Geometry;
pub use wavesplat_codec::view::bricked::{
    brick_frame, brick_frames, brick_visibility, check_brick, same_display, whole_frame,
    whole_geometry, whole_header, BrickFrame,
};
use wavesplat_codec::view::bricked::{brick_view, cue_factor, on_screen, reach};
use wavesplat_codec::view::{
    resolve_cue, Camera, CueDirection, Orientation, ResolvedCue, View, ViewError, ViewSpec,
};

/// What drawing a bricked file made.
#[derive(Debug)]
pub struct BrickedImage {
    /// The image in display space (multiview: three panels side by side).
    pub image: Image,
    /// Bricks in the file.
    pub bricks: usize,
    /// Bricks drawn (the others project off the image in every panel).
    pub drawn: usize,
    /// Coefficients splatted over all bricks drawn.
    pub coefficients: usize,
    /// Bytes of the bricks drawn.
    pub bytes: u64,
    /// Planning and splatting counters.
    pub stats: RenderStats,
}

/// Why a bricked file cannot be drawn.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum BrickedError {
    /// The container or one of its bricks is not valid.
    #[error("reading the bricked file")]
    Format(#[from] FormatError),
    /// A brick's packets do not decode.
    #[error("decoding a brick's packets")]
    Packet(#[from] PacketError),
    /// The view is invalid.
    #[error(transparent)]
    View(#[from] ViewError),
    /// Drawing failed.
    #[error(transparent)]
    Render(#[from] RenderError),
}

/// Parses a bricked file and the header of its first brick.
pub fn parse_with_first(bytes: &[u8]) -> Result<(BrickedFile<'_>, Header), BrickedError> {
    let file = parse_bricked(bytes)?;
    let first = parse_file(file.brick_bytes(0)?)?.header;
    Ok((file, first))
}

/// The view of one panel of `spec` as a single view: multiview's panels become explicit bases
/// at the first panel's zoom, and a cue along "the view" becomes the first panel's direction,
/// as the multiview renderer resolves it.
fn panel_views(spec: &ViewSpec, whole: &Geometry) -> Result<Vec<View>, BrickedError> {
    let cameras = spec.cameras(whole).map_err(RenderError::from)?;
    let n0 = cameras[0].n;
    Ok(cameras
        .iter()
        .map(|c| {
            let mut v = spec.view;
            v.orientation = Orientation::Basis { u: c.u, v: c.v };
            v.zoom = Some(c.zoom);
            if let Some(cue) = v.cue.as_mut() {
                if spec.multiview && cue.direction == CueDirection::View {
                    cue.direction = CueDirection::Vector(n0);
                }
            }
            v
        })
        .collect())
}

/// Draws every coefficient of a bricked file's bytes for `spec` with `backend`.
pub fn draw_bricked_file(
    bytes: &[u8],
    spec: &ViewSpec,
    backend: &mut dyn AccumulationBackend,
) -> Result<BrickedImage, BrickedError> {
    let (file, first) = parse_with_first(bytes)?;
    let m = &file.manifest;
    let whole = whole_geometry(m, &first);
    // Per panel: its view, the whole's camera and cue, and how far beyond a brick's box its
    // splats reach (clipped splats draw nothing outside it; otherwise a basis function
    // reaches (order/2)·2^M voxels beyond it at most).
    let panels: Vec<(View, Camera, Option<ResolvedCue>, f64)> = panel_views(spec, &whole)?
        .into_iter()
        .map(|view| {
            let camera = Camera::new(&view, &whole)?;
            let cue = view
                .cue
                .map(|c| resolve_cue(&c, &camera, &whole))
                .transpose()?;
            let reach = reach(&camera);
            Ok((view, camera, cue, reach))
        })
        .collect::<Result<_, ViewError>>()
        .map_err(RenderError::from)?;
    let (w, h) = (spec.view.width, spec.view.height);
    let mut planner = Planner::new(PlanOptions::default());
    let mut buffers = SplatBuffers::default();
    let mut stats = RenderStats::default();
    let mut images: Vec<Option<Image>> = vec![None; panels.len()];
    let (mut drawn, mut coefficients, mut drawn_bytes) = (0, 0, 0u64);
    for (i, entry) in m.bricks.iter().enumerate() {
        let mut decoded: Option<(Header, Vec<Vec<_>>)> = None;
        for (p, (view, camera, whole_cue, reach)) in panels.iter().enumerate() {
            if !on_screen(camera, entry.origin, entry.dims, *reach) {
                continue;
            }
            if decoded.is_none() {
                // Only a brick that is drawn is checked, parsed and decoded.
                let data = file.brick_bytes(i)?;
                let f = parse_file(data)?;
                // Against the manifest's channels, as every other reader checks them.
                check_brick(i, entry, &f.header, &first, m.channels)?;
                let d = decode_packets(&f.header, &f.packets, 0)?;
                let n: usize = d.iter().map(Vec::len).sum();
                check_kept(&f.header, n as u64)?;
                coefficients += n;
                drawn += 1;
                drawn_bytes += data.len() as u64;
                decoded = Some((f.header, d));
            }
            let (header, coeffs) = decoded.as_ref().expect("decoded above");
            let g = &header.geometry;
            let bv = brick_view(view, camera, &whole, g, entry.origin);
            let bspec = ViewSpec::single(bv);
            let mut plan = planner.plan(g, &bspec, header.channels)?;
            backend.begin(plan.layout()).map_err(RenderError::Backend)?;
            plan.splat_in_batches(
                coeffs.iter().map(Vec::as_slice),
                backend,
                SPLAT_BATCH,
                &mut buffers,
                &mut stats,
            )?;
            let raw = backend.read().map_err(RenderError::Backend)?;
            let mut img = crate::color::to_rgb(&raw, header, &plan.cameras, plan.cue.as_ref())?;
            if let (Some(wc), Some(bc)) = (whole_cue, plan.cue.as_ref()) {
                let scale = cue_factor(wc, bc, entry.origin) as f32;
                img.data.iter_mut().for_each(|v| *v *= scale);
            }
            match &mut images[p] {
                Some(total) => total
                    .data
                    .iter_mut()
                    .zip(&img.data)
                    .for_each(|(t, v)| *t += v),
                slot => *slot = Some(img),
            }
        }
    }
    let channels = images
        .iter()
        .flatten()
        .next()
        .map_or(if first.channels == 3 { 3 } else { 1 }, |i| i.channels);
    let panels: Vec<Image> = images
        .into_iter()
        .map(|i| i.unwrap_or_else(|| Image::new(w, h, channels)))
        .collect();
    let image = if panels.len() == 1 {
        panels.into_iter().next().expect("one panel")
    } else {
        side_by_side(&panels)
    };
    Ok(BrickedImage {
        image,
        bricks: m.bricks.len(),
        drawn,
        coefficients,
        bytes: drawn_bytes,
        stats,
    })
}

/// Panels of equal size side by side, as multiview lays them out.
fn side_by_side(panels: &[Image]) -> Image {
    let (w, h, c) = (panels[0].width, panels[0].height, panels[0].channels);
    let mut out = Image::new(w * panels.len(), h, c);
    for (p, img) in panels.iter().enumerate() {
        for y in 0..h {
            let src = &img.data[y * w * c..(y + 1) * w * c];
            let at = (y * w * panels.len() + p * w) * c;
            out.data[at..at + w * c].copy_from_slice(src);
        }
    }
    out
}

/// The header a time point of a series is drawn with as a bricked session's whole: the series'
/// header (`series`, [`wavesplat_codec::view::bricked::series_header`]) with the whole's
/// geometry (no transform of its own) and the time point's offset (`offset`: its components'
/// offsets weighted), which a session draws once for the whole.
pub fn time_point_header(series: &Header, spacing: [f32; 3], offset: f64) -> Header {
    let mut whole = series.clone();
    whole.geometry = wavesplat_codec::view::bricked::space_geometry(
        whole.geometry.dims,
        whole.geometry.family,
        spacing,
    );
    whole.color.mean[0] = offset;
    whole
}
