//! Bricked volumes in a session: the bricks of one volume
//! ([`wavesplat_codec::format::bricked`]) drawn into one accumulation. A brick's packets carry
//! global ids (they follow the previous bricks' packets), are decoded with their brick's header
//! and ranked by their brick's view; a batch is splatted brick by brick, each with its brick's
//! plan (the whole's camera moved into the brick's frame, [`crate::bricked::brick_frame`]),
//! values scaled by the brick's depth-cue factor, onto the one image. The session's own plan and
//! header are the whole's: cameras, cue and image layout, what the display pass uses. A brick
//! whose box projects off the image has no plan: its packets are held but not queued.

use super::{RenderSession, SessionError};
use crate::backend::AccumulationBackend;
use crate::bricked::{brick_frames, brick_visibility, same_display, whole_frame, BrickFrame};
use crate::plan::{RenderStats, SharedFactorTables, ViewPlan};
use crate::RenderError;
use wavesplat_codec::format::packet::Coefficient;
use wavesplat_codec::format::{FormatError, Header};
use wavesplat_codec::layout::Geometry;
use wavesplat_codec::view::visibility::Visibility;
use wavesplat_codec::view::ViewSpec;

/// One brick of a volume a session draws.
#[derive(Debug, Clone)]
pub struct SessionBrick {
    /// The brick's own header (its geometry is the brick's).
    pub header: Header,
    /// Its first voxel in the whole.
    pub origin: [u64; 3],
    /// Packets it has (its packets' global ids follow the previous bricks').
    pub packets: u32,
}

/// A bricked volume as a session draws it: the whole's header (its geometry is the whole's:
/// dimensions and spacing; the colour coding every brick shares) and the bricks.
#[derive(Debug, Clone)]
pub struct BrickedVolume {
    /// The whole's header.
    pub whole: Header,
    /// The bricks, in the order of their packets' global ids.
    pub bricks: Vec<SessionBrick>,
}

impl BrickedVolume {
    /// The global id of packet `local` of brick `brick` (`None` past the last packet).
    pub fn global_id(&self, brick: usize, local: u32) -> Option<u32> {
        let first: u64 = self.bricks[..brick]
            .iter()
            .map(|b| u64::from(b.packets))
            .sum();
        (local < self.bricks.get(brick)?.packets)
            .then(|| u32::try_from(first + u64::from(local)).ok())
            .flatten()
    }

    /// Checks that the bricks can share one accumulation: as many channels and the same colour
    /// coding as the whole, global ids within `u32`.
    pub fn check(&self) -> Result<(), FormatError> {
        let invalid = |detail: String| FormatError::Invalid {
            what: "bricked volume",
            detail,
        };
        let mut ids = 0u64;
        for (i, b) in self.bricks.iter().enumerate() {
            if b.header.channels != self.whole.channels || !same_display(&b.header, &self.whole) {
                return Err(invalid(format!(
                    "brick {i} codes its channels otherwise than the first brick"
                )));
            }
            ids += u64::from(b.packets);
        }
        if ids > u64::from(u32::MAX) {
            return Err(invalid(format!(
                "{ids} packets, more than a session numbers"
            )));
        }
        Ok(())
    }
}

/// What the current view draws of one brick.
pub(super) struct PartView {
    pub(super) plan: ViewPlan,
    pub(super) visibility: Visibility,
    /// The brick's depth-cue factor (1 without a cue): its coefficients are scaled by it.
    pub(super) cue_scale: f32,
}

/// A brick in a session.
pub(super) struct Part {
    pub(super) header: Header,
    origin: [u64; 3],
    first_id: u32,
    packets: u32,
    /// Basis norm² × importance per (channel, band index) of the brick's geometry.
    pub(super) energy_scale: Vec<f64>,
    /// `None`: off the image in the current view.
    pub(super) view: Option<PartView>,
}

/// The bricks of a session.
pub(super) struct Bricks {
    pub(super) whole: Geometry,
    pub(super) parts: Vec<Part>,
}

/// Basis norm² × importance per (channel, band index) of `header`'s volume.
pub(super) fn energy_scale(header: &Header) -> Vec<f64> {
    let g = header.geometry;
    let bands = g.bands();
    (0..header.channels)
        .flat_map(|c| {
            let importance = header.importance(c);
            bands
                .iter()
                .map(move |b| g.basis_norm2(*b) * importance)
                .collect::<Vec<_>>()
        })
        .collect()
}

/// Where a brick's plan comes from: the frame thread (exact or preview) or the background
/// builder's exact plan.
pub(super) type PartPlanner<'a> =
    dyn FnMut(&Geometry, &ViewSpec) -> Result<(ViewPlan, bool), SessionError> + 'a;

impl Bricks {
    pub(super) fn new(volume: BrickedVolume) -> Result<Bricks, SessionError> {
        volume.check().map_err(SessionError::Volume)?;
        let mut first_id = 0u32;
        let parts = volume
            .bricks
            .into_iter()
            .map(|b| {
                let p = Part {
                    energy_scale: energy_scale(&b.header),
                    header: b.header,
                    origin: b.origin,
                    first_id,
                    packets: b.packets,
                    view: None,
                };
                first_id = first_id.wrapping_add(b.packets);
                p
            })
            .collect();
        Ok(Bricks {
            whole: volume.whole.geometry,
            parts,
        })
    }

    /// The brick holding global packet `id`.
    pub(super) fn part_of(&self, id: u32) -> Option<usize> {
        let k = self
            .parts
            .partition_point(|p| p.first_id <= id)
            .checked_sub(1)?;
        let p = &self.parts[k];
        (id - p.first_id < p.packets).then_some(k)
    }

    /// The plan brick-of-`id` draws with in the current view.
    pub(super) fn plan_of(&self, id: u32) -> Option<&ViewPlan> {
        let k = self.part_of(id)?;
        self.parts[k].view.as_ref().map(|v| &v.plan)
    }

    /// The frames of `spec` for every brick (`None`: off the image).
    pub(super) fn frames(&self, spec: &ViewSpec) -> Result<Vec<Option<BrickFrame>>, RenderError> {
        brick_frames(
            spec,
            &self.whole,
            self.parts.iter().map(|p| (&p.header.geometry, p.origin)),
        )
        .map_err(RenderError::from)
    }

    /// Plans every brick the view `spec` sees with `plan` (the bricks of one volume share
    /// their footprint tables through one planner); returns whether every plan is exact.
    pub(super) fn set_view(
        &mut self,
        spec: &ViewSpec,
        plan: &mut PartPlanner<'_>,
    ) -> Result<bool, SessionError> {
        let frames = self.frames(spec)?;
        let mut exact = true;
        let mut like = Vec::new();
        for (part, frame) in self.parts.iter_mut().zip(frames) {
            part.view = None;
            let Some(frame) = frame else { continue };
            let (p, e) = plan(&part.header.geometry, &frame.spec)?;
            exact &= e;
            let visibility = brick_visibility(&part.header, &frame, &mut like)?;
            part.view = Some(PartView {
                plan: in_frame(p, &frame),
                visibility,
                cue_scale: frame.cue_scale as f32,
            });
        }
        self.share_tables();
        Ok(exact)
    }

    /// Makes the bricks' plans of the view build each factor table once for all of them.
    pub(super) fn share_tables(&mut self) {
        let shared = std::sync::Arc::new(SharedFactorTables::default());
        for plan in self.plans_mut() {
            plan.share_factor_tables(shared.clone());
        }
    }

    /// The bricks' geometries and frames for a background build: `None` for a brick off the
    /// image.
    pub(super) fn jobs(
        &self,
        spec: &ViewSpec,
    ) -> Result<Vec<Option<(Geometry, BrickFrame)>>, RenderError> {
        Ok(self
            .frames(spec)?
            .into_iter()
            .zip(&self.parts)
            .map(|(f, p)| f.map(|f| (p.header.geometry, f)))
            .collect())
    }

    /// The plans of the bricks the view sees.
    pub(super) fn plans_mut(&mut self) -> impl Iterator<Item = &mut ViewPlan> {
        self.parts
            .iter_mut()
            .filter_map(|p| p.view.as_mut().map(|v| &mut v.plan))
    }
}

impl<B: AccumulationBackend> RenderSession<B> {
    /// A session for a bricked volume (see the module documentation of `session::bricks`):
    /// the bricks' packets are added under their global ids
    /// ([`BrickedVolume::global_id`]).
    pub fn new_bricked(
        volume: BrickedVolume,
        spec: ViewSpec,
        backend: B,
        options: super::SessionOptions,
    ) -> Result<RenderSession<B>, SessionError> {
        let whole = volume.whole.clone();
        let bricks = Bricks::new(volume)?;
        // The view is checked against the whole before anything is planned.
        whole_frame(&spec, &bricks.whole)?;
        RenderSession::build(whole, spec, backend, options, Some(bricks))
    }

    /// Replaces the volume a bricked session draws by `volume` (the next time point of a
    /// series, whose components have the geometries of the last one's): everything held is
    /// dropped and the view is drawn again from nothing, while the backend, the planners and
    /// the footprint tables they cached stay (a time point's parts are planned at once with
    /// the tables the last one built). A background build in flight is dropped: it was for
    /// the old parts. The source that fed the old volume goes with it (its ids mean other
    /// packets now).
    pub fn replace_bricked_volume(&mut self, volume: BrickedVolume) -> Result<(), SessionError> {
        let whole = volume.whole.clone();
        let bricks = Bricks::new(volume)?;
        whole_frame(&self.plan.spec, &bricks.whole)?;
        self.energy_scale = energy_scale(&whole);
        self.header = whole;
        self.bricks = Some(bricks);
        self.packets.clear();
        self.queue.clear();
        self.waiting.clear();
        self.dropped.clear();
        self.dropped_before_redraw.clear();
        self.path_lengths = None;
        self.device_colour = None;
        self.shown_preview = None;
        self.building = None;
        self.fresh_bytes = 0;
        self.stats.coefficients_held = 0;
        let spec = self.plan.spec;
        self.set_view(spec)
    }

    /// Draws a batch of a bricked session brick by brick; returns the indices (into `batch`)
    /// left waiting for their cue tables, ascending, and the records drawn.
    pub(super) fn draw_bricked(
        &mut self,
        batch: &[(u32, u32)],
        coefficients: &[Coefficient],
        stats: &mut RenderStats,
    ) -> Result<(Vec<usize>, usize), SessionError> {
        let Some(bricks) = self.bricks.as_mut() else {
            return Ok((Vec::new(), 0));
        };
        let mut order: Vec<(usize, usize)> = batch
            .iter()
            .enumerate()
            .map(|(k, (id, _))| (bricks.part_of(*id).unwrap_or(usize::MAX), k))
            .collect();
        order.sort_unstable();
        let (mut deferred, mut records) = (Vec::new(), 0);
        let mut scaled = Vec::new();
        // The records of consecutive bricks whose plans share an atlas (all of them, when the
        // bricks have one shape) are accumulated in one call: one pass over the image's tiles
        // per batch, not one per brick.
        let mut pending: Option<usize> = None;
        self.records.clear();
        for run in order.chunk_by(|a, b| a.0 == b.0) {
            // Only coefficients of bricks the view sees are queued.
            let part = run[0].0;
            if bricks.parts.get(part).is_none_or(|p| p.view.is_none()) {
                continue;
            }
            if let Some(held) = pending.filter(|&h| !same_atlas(bricks, h, part)) {
                records += flush_records(&mut self.backend, &mut self.records, bricks, held)?;
            }
            let Some(view) = bricks.parts[part].view.as_mut() else {
                continue;
            };
            scaled.clear();
            scaled.extend(run.iter().map(|&(_, k)| {
                let mut c = coefficients[k];
                c.value *= view.cue_scale;
                c
            }));
            view.plan.splats(&scaled, &mut self.records, stats)?;
            deferred.extend(view.plan.take_deferred().into_iter().map(|j| run[j].1));
            pending = Some(part);
        }
        if let Some(held) = pending {
            records += flush_records(&mut self.backend, &mut self.records, bricks, held)?;
        }
        deferred.sort_unstable();
        Ok((deferred, records))
    }
}

/// A brick's plan of its frame's spec with every camera moved by the frame's own pan for it
/// (multiview's panels move into a brick by pans of their own, [`BrickFrame::move_cameras`]).
pub(super) fn in_frame(mut plan: ViewPlan, frame: &BrickFrame) -> ViewPlan {
    frame.move_cameras(&mut plan.cameras);
    plan
}

/// Whether bricks `a` and `b` are drawn with plans that share an atlas.
fn same_atlas(bricks: &Bricks, a: usize, b: usize) -> bool {
    match (&bricks.parts[a].view, &bricks.parts[b].view) {
        (Some(x), Some(y)) => x.plan.shares_atlas_with(&y.plan),
        _ => false,
    }
}

/// Accumulates `records` (gathered from bricks drawn with brick `part`'s atlas) and clears
/// them; returns how many there were.
fn flush_records<B: AccumulationBackend>(
    backend: &mut B,
    records: &mut Vec<crate::backend::SplatRecord>,
    bricks: &Bricks,
    part: usize,
) -> Result<usize, SessionError> {
    let n = records.len();
    if let Some(view) = bricks.parts[part].view.as_ref() {
        let atlas = view.plan.atlas();
        backend.prepare(&atlas)?;
        backend.accumulate(&atlas, records)?;
    }
    records.clear();
    Ok(n)
}
