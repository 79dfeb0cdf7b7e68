//! Rendering a bricked volume ([`wavesplat_codec::format::bricked`]) as one: an X-ray image is
//! linear in the data and the bricks tile the whole, so the whole's image is the sum of the
//! bricks' images, each drawn by the ordinary splatting path with the whole's camera moved into
//! the brick's frame (the same zoom, a pan that puts the whole's centre where it belongs) and
//! clipped at the brick's faces, as a volume is clipped at its own. Depth cueing attenuates
//! from the whole's light-facing faces: a brick's own cue measures from its own faces, and the
//! two distances differ by a constant per brick, so its image is scaled by e^(−k·δ). Bricks
//! whose box projects off the image are neither decoded nor drawn. One planner serves every
//! brick (their footprint tables are the same for one view and depth).

use crate::backend::AccumulationBackend;
use crate::plan::{PlanOptions, Planner, SplatBuffers, SPLAT_BATCH};
use crate::{Image, RenderError, RenderStats};
use wavesplat_codec::family::Family;
use wavesplat_codec::format::bricked::{parse_bricked, BrickEntry, BrickedFile, Manifest};
use wavesplat_codec::format::packet::{decode_packets, PacketError};
use wavesplat_codec::format::{check_kept, parse_file, FormatError, Header};
use wavesplat_codec::layout::Geometry;
use wavesplat_codec::view::visibility::Visibility;
use wavesplat_codec::view::{
    dot, resolve_cue, Camera, CueDirection, Orientation, ResolvedCue, View, ViewError, ViewSpec,
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

/// The whole volume's geometry for cameras (dims and spacing; no transform of its own, and not
/// limited to what one transform holds).
pub fn whole_geometry(manifest: &Manifest, first: &Header) -> Geometry {
    let dims = manifest.dims.map(|d| d as usize);
    Geometry {
        dims,
        padded: dims,
        origin: [0; 3],
        levels: 0,
        family: first.geometry.family,
        spacing: manifest.spacing,
    }
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

/// The view of brick `brick_geometry` at `origin` that draws what `whole_view` shows of it.
fn brick_view(
    whole_view: &View,
    whole_camera: &Camera,
    whole: &Geometry,
    brick_geometry: &Geometry,
    origin: [u64; 3],
) -> View {
    let s = whole_camera.spacing;
    let centre = |d: usize| (d as f64 - 1.0) / 2.0;
    // The whole's centre in the brick's voxel indices, minus the brick's centre, in physical
    // units: the brick's camera looks at its own centre, so the pan moves it by this.
    let d: [f64; 3] = std::array::from_fn(|a| {
        (centre(whole.dims[a]) - origin[a] as f64 - centre(brick_geometry.dims[a])) * s[a]
    });
    let mut v = *whole_view;
    v.pan = [
        whole_view.pan[0] + dot(d, whole_camera.u),
        whole_view.pan[1] + dot(d, whole_camera.v),
    ];
    v
}

/// Whether the box of a brick at `origin` of `dims` (voxel indices of the whole, its support
/// reaching `reach` voxels beyond) projects onto the image of `camera`.
fn on_screen(camera: &Camera, origin: [u64; 3], dims: [usize; 3], reach: f64) -> bool {
    let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
    for corner in 0..8 {
        let x: [f64; 3] = std::array::from_fn(|a| {
            if corner >> a & 1 == 0 {
                origin[a] as f64 - 0.5 - reach
            } else {
                origin[a] as f64 + dims[a] as f64 - 0.5 + reach
            }
        });
        let p = camera.to_screen(x);
        for k in 0..2 {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
        }
    }
    hi[0] >= 0.0 && lo[0] <= camera.width as f64 && hi[1] >= 0.0 && lo[1] <= camera.height as f64
}

/// How one brick draws its share of a single view of the whole: its own view (the whole's
/// camera moved into the brick's frame) and the factor its image is scaled by so that its
/// depth cue measures from the whole's light-facing faces (1 without a cue).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BrickFrame {
    /// The brick's view.
    pub spec: ViewSpec,
    /// e^(−k·δ): δ the distance from the whole's light-facing faces to the brick's.
    pub cue_scale: f64,
}

/// The whole's camera and resolved cue for a single view `spec` of `whole` (the frame every
/// brick is drawn in); multiview is refused here: its panels each move into a brick's frame by
/// a pan of their own, which one brick view cannot hold.
pub fn whole_frame(
    spec: &ViewSpec,
    whole: &Geometry,
) -> Result<(Camera, Option<ResolvedCue>), RenderError> {
    if spec.multiview {
        return Err(RenderError::Unsupported(
            "multiview of a bricked volume is drawn in one pass only (render without --progressive)",
        ));
    }
    let camera = spec.cameras(whole)?.remove(0);
    let cue = spec
        .view
        .cue
        .map(|c| resolve_cue(&c, &camera, whole))
        .transpose()?;
    Ok((camera, cue))
}

/// How the brick of `geometry` at `origin` draws its share of the single view `spec` of the
/// whole (camera and cue from [`whole_frame`]); `None` when its box projects off the image.
pub fn brick_frame(
    spec: &ViewSpec,
    (camera, whole_cue): (&Camera, Option<&ResolvedCue>),
    whole: &Geometry,
    geometry: &Geometry,
    origin: [u64; 3],
) -> Result<Option<BrickFrame>, RenderError> {
    if !on_screen(camera, origin, geometry.dims, reach(geometry, camera)) {
        return Ok(None);
    }
    let view = brick_view(&spec.view, camera, whole, geometry, origin);
    let cue_scale = match (whole_cue, view.cue) {
        (Some(wc), Some(cue)) => {
            let own = resolve_cue(&cue, &Camera::new(&view, geometry)?, geometry)?;
            cue_factor(wc, &own, origin)
        }
        _ => 1.0,
    };
    Ok(Some(BrickFrame {
        spec: ViewSpec::single(view),
        cue_scale,
    }))
}

/// The frames of `spec` for bricks given by geometry and origin, in the order given (`None`:
/// the brick projects off the image).
pub fn brick_frames<'a>(
    spec: &ViewSpec,
    whole: &Geometry,
    bricks: impl IntoIterator<Item = (&'a Geometry, [u64; 3])>,
) -> Result<Vec<Option<BrickFrame>>, RenderError> {
    let (camera, cue) = whole_frame(spec, whole)?;
    bricks
        .into_iter()
        .map(|(g, origin)| brick_frame(spec, (&camera, cue.as_ref()), whole, g, origin))
        .collect()
}

/// The visibility of a brick of `header` in its frame's `spec`, sharing the band weights of
/// the first brick's visibility kept in `like` (set by the first call): the bricks of one
/// view share them ([`Visibility::new_like`]).
pub fn brick_visibility(
    header: &Header,
    spec: &ViewSpec,
    like: &mut Option<Visibility>,
) -> Result<Visibility, ViewError> {
    let visibility = match like.as_ref() {
        Some(l) => Visibility::new_like(header, spec, l)?,
        None => Visibility::new(header, spec)?,
    };
    like.get_or_insert_with(|| visibility.clone());
    Ok(visibility)
}

/// e^(−k·δ): what a brick at `origin` whose own cue is `own` scales its image by so that its
/// cue measures from the whole's light-facing faces (`whole`), δ the distance between the two.
fn cue_factor(whole: &ResolvedCue, own: &ResolvedCue, origin: [u64; 3]) -> f64 {
    let delta = whole.dist(origin.map(|v| v as f64)) - own.dist([0.0; 3]);
    (-whole.k * delta).exp()
}

/// Checks brick `i`'s header against its manifest entry: its dimensions, `channels` channels
/// and the first brick's family.
pub fn check_brick(
    i: usize,
    entry: &BrickEntry,
    header: &Header,
    first: &Header,
    channels: usize,
) -> Result<(), FormatError> {
    if header.geometry.dims != entry.dims
        || header.channels != channels
        || header.geometry.family != first.geometry.family
    {
        return Err(FormatError::Invalid {
            what: "bricked manifest",
            detail: format!(
                "brick {i} at {:?} does not match the manifest or the first brick",
                entry.origin
            ),
        });
    }
    Ok(())
}

/// Whether two bricks' values are shown alike: the same colour space, basis and offset (their
/// channels' importance may differ: it only ranks).
pub fn same_display(a: &Header, b: &Header) -> bool {
    let (a, b) = (&a.color, &b.color);
    (a.kind, a.basis, a.mean) == (b.kind, b.basis, b.mean)
}

/// How far beyond a brick's box the splats of `geometry` reach on `camera`'s screen, in voxels:
/// clipped splats draw nothing outside it (a pixel's margin); otherwise a basis function
/// reaches (order/2)·2^M voxels beyond it at most.
fn reach(g: &Geometry, camera: &Camera) -> f64 {
    if g.clips_to_box() || g.family == Family::Haar {
        1.0 / camera.zoom
    } else {
        0.5 * g.family.order() as f64 * (1u64 << g.levels) as f64
    }
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
            let reach = reach(&first.geometry, &camera);
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
                check_brick(i, entry, &f.header, &first, first.channels)?;
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
