//! Views of a bricked volume ([`crate::format::bricked`]): the pure geometry by which every
//! reader of one (the renderer, the file and range sources, the cache) places the whole's view
//! in each brick and ranks the bricks' packets together. A brick is seen through the whole's
//! camera moved into the brick's frame (the same zoom, a pan that puts the whole's centre where
//! it belongs) and clipped at its faces; depth cueing measures from the whole's light-facing
//! faces, which differ from a brick's own by a constant distance per brick, so its image (and
//! its packets' visible energy, squared) is scaled by e^(−k·δ). A brick whose box projects off
//! the image is seen by no packet of it. The bricks of one view share the band weights of their
//! visibility ([`Visibility::new_like`]). In multiview each panel moves into a brick by a pan
//! of its own (the panels' screen axes differ): a brick's frame holds the whole's multiview
//! spec at the whole's zoom and one pan per panel ([`BrickFrame::cameras`]).

use super::visibility::Visibility;
use super::{dot, resolve_cue, Camera, ResolvedCue, View, ViewError, ViewSpec};
use crate::family::Family;
use crate::format::bricked::{BrickEntry, Manifest};
use crate::format::{FormatError, Header};
use crate::layout::{Band, Geometry};

/// The whole volume's geometry for cameras (dims and spacing; no transform of its own, and not
/// limited to what one transform holds).
pub fn whole_geometry(manifest: &Manifest, first: &Header) -> Geometry {
    space_geometry(
        manifest.dims.map(|d| d as usize),
        first.geometry.family,
        manifest.spacing,
    )
}

/// The geometry of a whole of `dims` voxels at `spacing` drawn from transforms of `family`:
/// no transform of its own (what cameras and a bricked session's whole need).
pub fn space_geometry(dims: [usize; 3], family: Family, spacing: [f32; 3]) -> Geometry {
    Geometry {
        dims,
        padded: dims,
        origin: [0; 3],
        levels: 0,
        family,
        spacing,
    }
}

/// The header a reader draws a bricked volume of `manifest` with: the first brick's, with the
/// whole's geometry and placement.
pub fn whole_header(manifest: &Manifest, first: &Header) -> Header {
    let mut header = first.clone();
    header.geometry = whole_geometry(manifest, first);
    header.placement = manifest.placement;
    header
}

/// The header a reader draws a time point of a series with: its first component's (the
/// whole's, for a bricked one) with the series' placement, checked against the series' space.
/// Every component spans the same whole, so one view fits every time point.
pub fn series_header(file: &crate::format::series::SeriesFile<'_>) -> Result<Header, FormatError> {
    use crate::format::bricked::{is_bricked, parse_bricked};
    let data = file.component_bytes(0)?;
    let first = if is_bricked(data) {
        let b = parse_bricked(data)?;
        let first = crate::format::parse_file(b.brick_bytes(0)?)?.header;
        whole_header(&b.manifest, &first)
    } else {
        crate::format::parse_file(data)?.header
    };
    series_space_header(&file.manifest.space, first)
}

/// [`series_header`] from the header of component 0's first brick (`first`; `bricked`: the
/// component is a bricked container, whose whole header [`whole_header`] makes from the
/// space) and the series' space: checked against the space, with its placement. What a reader
/// that holds only the components' brick headers (a cache, its clients) draws a series with.
pub fn series_brick_header(
    space: &crate::format::bricked::Space,
    mut first: Header,
    bricked: bool,
) -> Result<Header, FormatError> {
    if bricked {
        first.geometry = space_geometry(
            space.dims.map(|d| d as usize),
            first.geometry.family,
            space.spacing,
        );
    }
    series_space_header(space, first)
}

/// [`series_header`] from the whole header of a series' component 0 (`first`, a bricked one's
/// [`whole_header`]) and the series' space: `first` checked against the space, with its
/// placement.
pub fn series_space_header(
    space: &crate::format::bricked::Space,
    mut first: Header,
) -> Result<Header, FormatError> {
    let dims = space.dims.map(|d| d as usize);
    if first.geometry.dims != dims || first.channels != space.channels {
        return Err(FormatError::Invalid {
            what: "series manifest",
            detail: format!(
                "component 0 is {:?} with {} channel(s); the series is {dims:?} with {}",
                first.geometry.dims, first.channels, space.channels
            ),
        });
    }
    first.placement = space.placement;
    Ok(first)
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

/// The view of brick `brick_geometry` at `origin` that draws what `whole_view` shows of it.
pub fn brick_view(
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
    // The whole's zoom: a view without one would fit the brick's own box.
    v.zoom = Some(whole_camera.zoom);
    v.pan = [
        whole_view.pan[0] + dot(d, whole_camera.u),
        whole_view.pan[1] + dot(d, whole_camera.v),
    ];
    v
}

/// Whether the box of a brick at `origin` of `dims` (voxel indices of the whole, its support
/// reaching `reach` voxels beyond) projects onto the image of `camera`.
pub fn on_screen(camera: &Camera, origin: [u64; 3], dims: [usize; 3], reach: f64) -> bool {
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

/// How far beyond a brick's box the splats of `g` reach on `camera`'s screen, in voxels: a
/// pixel's margin. The splines are clipped to the box ([`Geometry::splats_clip_to_box`]);
/// Haar's blocks reach into a margin only with what the margin held (zeros, lossless).
pub fn reach(camera: &Camera) -> f64 {
    1.0 / camera.zoom
}

/// e^(−k·δ): what a brick at `origin` whose own cue is `own` scales its image by so that its
/// cue measures from the whole's light-facing faces (`whole`), δ the distance between the two.
pub fn cue_factor(whole: &ResolvedCue, own: &ResolvedCue, origin: [u64; 3]) -> f64 {
    let delta = whole.dist(origin.map(|v| v as f64)) - own.dist([0.0; 3]);
    (-whole.k * delta).exp()
}

/// How one brick draws its share of a view of the whole: its own view (the whole's camera moved
/// into the brick's frame: the whole's zoom, a pan that puts the whole's centre where it
/// belongs), one pan per camera (multiview's panels each move by their own), and the factor its
/// image is scaled by so that its depth cue measures from the whole's light-facing faces (1
/// without a cue; multiview has none).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BrickFrame {
    /// The brick's view (multiview: the whole's multiview spec, its first panel's pan).
    pub spec: ViewSpec,
    /// The pan of each camera of `spec` in the brick's frame (the first is `spec`'s own; a
    /// single view uses only it).
    pub pans: [[f64; 2]; 3],
    /// e^(−k·δ): δ the distance from the whole's light-facing faces to the brick's.
    pub cue_scale: f64,
}

impl BrickFrame {
    /// The brick's cameras in this frame (one, or the three multiview panels), for the brick of
    /// `geometry`: `spec`'s cameras, each moved by its own pan.
    pub fn cameras(&self, geometry: &Geometry) -> Result<Vec<Camera>, ViewError> {
        let mut cameras = self.spec.cameras(geometry)?;
        self.move_cameras(&mut cameras);
        Ok(cameras)
    }

    /// Moves `cameras` (those of `spec`, in its order) each by its own pan: what a brick's
    /// plan of `spec` needs to draw in this frame (the footprint tables do not depend on the
    /// pan).
    pub fn move_cameras(&self, cameras: &mut [Camera]) {
        for (camera, pan) in cameras.iter_mut().zip(self.pans) {
            camera.pan = pan;
        }
    }
}

/// The whole's cameras (one, or the three multiview panels) and resolved cue for `spec` of
/// `whole`: the frame every brick is drawn in.
pub fn whole_frame(
    spec: &ViewSpec,
    whole: &Geometry,
) -> Result<(Vec<Camera>, Option<ResolvedCue>), ViewError> {
    let cameras = spec.cameras(whole)?;
    let cue = spec
        .view
        .cue
        .map(|c| resolve_cue(&c, &cameras[0], whole))
        .transpose()?;
    Ok((cameras, cue))
}

/// How the brick of `geometry` at `origin` draws its share of the view `spec` of the whole
/// (cameras and cue from [`whole_frame`]); `None` when its box projects off the image of every
/// camera.
pub fn brick_frame(
    spec: &ViewSpec,
    (cameras, whole_cue): (&[Camera], Option<&ResolvedCue>),
    whole: &Geometry,
    geometry: &Geometry,
    origin: [u64; 3],
) -> Result<Option<BrickFrame>, ViewError> {
    let Some(first) = cameras.first() else {
        return Ok(None);
    };
    if !cameras
        .iter()
        .any(|c| on_screen(c, origin, geometry.dims, reach(c)))
    {
        return Ok(None);
    }
    let view = brick_view(&spec.view, first, whole, geometry, origin);
    let mut pans = [view.pan; 3];
    for (pan, camera) in pans.iter_mut().zip(cameras).skip(1) {
        *pan = brick_view(&spec.view, camera, whole, geometry, origin).pan;
    }
    let cue_scale = match (whole_cue, view.cue) {
        (Some(wc), Some(cue)) => {
            let own = resolve_cue(&cue, &Camera::new(&view, geometry)?, geometry)?;
            cue_factor(wc, &own, origin)
        }
        _ => 1.0,
    };
    Ok(Some(BrickFrame {
        spec: ViewSpec {
            view,
            multiview: spec.multiview,
        },
        pans,
        cue_scale,
    }))
}

/// The frames of `spec` for bricks given by geometry and origin, in the order given (`None`:
/// the brick projects off the image).
pub fn brick_frames<'a>(
    spec: &ViewSpec,
    whole: &Geometry,
    bricks: impl IntoIterator<Item = (&'a Geometry, [u64; 3])>,
) -> Result<Vec<Option<BrickFrame>>, ViewError> {
    let (cameras, cue) = whole_frame(spec, whole)?;
    bricks
        .into_iter()
        .map(|(g, origin)| brick_frame(spec, (&cameras, cue.as_ref()), whole, g, origin))
        .collect()
}

/// The visibility of a brick of `header` in its `frame` (every camera with its own pan),
/// sharing with the visibilities of earlier bricks of the view kept in `shapes` (one per brick
/// shape met, filled by these calls): their band weights ([`Visibility::new_like`]) and, with
/// a brick of the same shape, its tile boxes. A volume's bricks come in a few shapes (its
/// faces' bricks are padded otherwise than inner ones), and the boxes are most of a brick's
/// own cost: for 512 bricks of 256³ they took ~60 % of the view's 50 ms.
pub fn brick_visibility(
    header: &Header,
    frame: &BrickFrame,
    shapes: &mut Vec<Visibility>,
) -> Result<Visibility, ViewError> {
    let cameras = frame.cameras(&header.geometry)?;
    let same = shapes.iter().find(|v| v.is_shape_of(header));
    let like = same.or(shapes.first());
    let visibility = Visibility::with_cameras(header, &frame.spec, &cameras, like)?;
    if same.is_none() {
        shapes.push(visibility.clone());
    }
    Ok(visibility)
}

/// What one view of a bricked volume sees of each brick's packets: per brick, its visibility in
/// its frame and its cue factor squared (energy scales with the square of the values), or
/// nothing for a brick off the image.
#[derive(Debug, Clone)]
pub struct BrickedVisibility {
    bricks: Vec<Option<(Visibility, f64)>>,
}

impl BrickedVisibility {
    /// The view `spec` of the whole `whole` seen in bricks given by header and first voxel.
    pub fn new(
        spec: &ViewSpec,
        whole: &Geometry,
        bricks: &[(&Header, [u64; 3])],
    ) -> Result<BrickedVisibility, ViewError> {
        let frames = brick_frames(spec, whole, bricks.iter().map(|(h, o)| (&h.geometry, *o)))?;
        let mut like = Vec::new();
        let bricks = bricks
            .iter()
            .zip(frames)
            .map(|((header, _), frame)| {
                frame
                    .map(|f| {
                        let vis = brick_visibility(header, &f, &mut like)?;
                        Ok((vis, f.cue_scale * f.cue_scale))
                    })
                    .transpose()
            })
            .collect::<Result<_, ViewError>>()?;
        Ok(BrickedVisibility { bricks })
    }

    /// Whether the view sees brick `brick` at all (its box projects onto the image).
    pub fn sees(&self, brick: usize) -> bool {
        self.bricks.get(brick).is_some_and(Option::is_some)
    }

    /// The visible energy of a packet of brick `brick` (tile `tile`, energy per band
    /// `summary`); `None` for a brick off the image.
    pub fn visible_energy(
        &self,
        brick: usize,
        tile: usize,
        summary: &[(Band, f64)],
    ) -> Option<f64> {
        let (vis, factor) = self.bricks.get(brick)?.as_ref()?;
        Some(vis.visible_energy(tile, summary) * factor)
    }
}

/// What ranks one packet of a bricked volume.
#[derive(Debug, Clone, Copy)]
pub struct BrickPacket<'a> {
    /// Its brick.
    pub brick: usize,
    /// Its tile in the brick.
    pub tile: usize,
    /// Its energy per band.
    pub summary: &'a [(Band, f64)],
    /// Its size.
    pub bytes: usize,
}

/// A bricked volume's packets (ids in the order given) for `spec` by visible energy per byte,
/// with that figure, best first: each brick's seen by its own view of the whole `whole` (scaled
/// by its cue factor²), ties by id; the packets of a brick the view does not see are left out.
/// `bricks`: each brick's header and first voxel in the whole.
pub fn bricked_packet_order<'a>(
    spec: &ViewSpec,
    whole: &Geometry,
    bricks: &[(&Header, [u64; 3])],
    packets: impl Iterator<Item = BrickPacket<'a>>,
) -> Result<Vec<(f64, u32)>, ViewError> {
    let seen = BrickedVisibility::new(spec, whole, bricks)?;
    let mut keyed: Vec<(f64, u32)> = packets
        .enumerate()
        .filter_map(|(i, p)| {
            let e = seen.visible_energy(p.brick, p.tile, p.summary)?;
            Some((e / p.bytes.max(1) as f64, i as u32))
        })
        .collect();
    keyed.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
    Ok(keyed)
}
