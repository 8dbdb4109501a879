//! From a fitted model to the output surfaces: the seeds and region of trust, the echo-ridge sheet,
//! and removing and joining pieces.

use crate::io::ClipRect;
use crate::segment::crests::{CrestCache, echo_crests_reusing};
use crate::surface::{
    CrestLink, OrientedPoints, PlacedCrest, add_linked_crests, keep_pieces_reaching, orient_crests,
};

use super::{
    AUTO_RIDGE_MIN_REACHED_SHARE, Calibration, DVec3, ECHO_SUPPORT_RADIUS_MM, EchoReach, Error,
    ExtractOptions, FramePlane, ImageCrests, IntensityLevels, Mesh, PoseResolution,
    PreparedSamples, RbfModel, Result, RidgeOptions, SampleSet, Sheet, SheetUsed, SurfaceDomain,
    SurfaceOptions, TrackedSequence, WeakRidge, clip_corners_px, extend_ridge_sheet, frame_corners,
    proximal_sheet_on_ridge, sheet_through_points,
};

/// The beam direction of the frame nearest a point (among frames whose image the point projects into).
pub(super) struct FrameBeams {
    /// Each frame's plane and unit beam direction (the image's +v axis).
    frames: Vec<(FramePlane, DVec3)>,
    width: f64,
    height: f64,
    max_distance_mm: f64,
}

impl FrameBeams {
    pub(super) fn new(
        sequence: &TrackedSequence,
        poses: &PoseResolution,
        max_distance_mm: f64,
    ) -> Self {
        FrameBeams {
            frames: poses
                .poses
                .iter()
                .filter_map(|p| {
                    let plane = FramePlane::new(p.image_to_world)?;
                    Some((plane, plane.v.try_normalize()?))
                })
                .collect(),
            width: sequence.width.saturating_sub(1) as f64,
            height: sequence.height.saturating_sub(1) as f64,
            max_distance_mm,
        }
    }

    fn beam_at(&self, x: DVec3) -> Option<DVec3> {
        let mut best: Option<(f64, DVec3)> = None;
        for (plane, beam) in &self.frames {
            let [u, v] = plane.pixel_of(x);
            if !(u >= 0.0 && u <= self.width && v >= 0.0 && v <= self.height) {
                continue;
            }
            let distance = x.distance(plane.world_of([u, v]));
            if distance <= self.max_distance_mm && best.is_none_or(|(d, _)| distance < d) {
                best = Some((distance, *beam));
            }
        }
        best.map(|(_, b)| b)
    }
}

/// Region-of-trust radius from the data: three frame spacings (so the surface bridges the gaps between
/// frames and the missing steep walls between neighbouring echoes), at least 2 mm and at most 10 mm.
pub fn trust_distance_for(median_frame_spacing_mm: Option<f64>) -> f64 {
    match median_frame_spacing_mm {
        Some(s) if s.is_finite() && s > 0.0 => (3.0 * s).clamp(2.0, 10.0),
        _ => 3.0,
    }
}

/// Median distance between the image centres of consecutive used frames.
pub fn median_frame_spacing_mm(sequence: &TrackedSequence, poses: &PoseResolution) -> Option<f64> {
    let centres: Vec<DVec3> = poses
        .poses
        .iter()
        .map(|p| crate::io::pose::image_centre(sequence, p))
        .collect();
    let mut steps: Vec<f64> = centres
        .windows(2)
        .map(|w| w[0].distance(w[1]))
        .filter(|d| d.is_finite() && *d > 1e-6)
        .collect();
    if steps.is_empty() {
        return None;
    }
    steps.sort_by(f64::total_cmp);
    Some(steps[steps.len() / 2])
}

/// Checks requested iso-levels against the range of the fitted data: a level outside it has no surface.
pub(super) fn check_levels(levels: &[f64], samples: &SampleSet) -> Result<()> {
    let (lo, hi) = samples
        .intensities
        .iter()
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), &x| {
            (a.min(x), b.max(x))
        });
    for &level in levels {
        if !level.is_finite() {
            return Err(Error::InvalidInput(format!(
                "iso-level {level} is not a number"
            )));
        }
        if level <= lo as f64 || level >= hi as f64 {
            return Err(Error::Options {
                kind: crate::OptionsErrorKind::InvalidInput,
                message: crate::Phrase::new(format!(
                    "iso-level {level} is outside the grey levels of the kept pixels ({lo} to {hi}): \
                     it would give no surface; set "
                ))
                .option(crate::OptionName::IsoLevels)
                .text(" to auto or a level in that range"),
            });
        }
    }
    Ok(())
}

/// Seeds for surface-following: samples whose grey level is near some iso-level (they sit close to the
/// surface), spread over the data by a deterministic stride, at most `max` of them.
pub(super) fn surface_seeds(
    points: &[DVec3],
    values: &[f64],
    levels: &[f64],
    band: f64,
    max: usize,
) -> Vec<DVec3> {
    let near: Vec<DVec3> = points
        .iter()
        .zip(values)
        .filter(|(_, v)| levels.iter().any(|&k| (**v - k).abs() <= band))
        .map(|(p, _)| *p)
        .collect();
    let stride = near.len().div_ceil(max.max(1)).max(1);
    near.into_iter().step_by(stride).collect()
}

/// At most this many seeds start the surface-following: more cost field evaluations without adding
/// surface, and every separate piece still gets seeds because they are spread evenly
/// (docs/decisions/0035-figures-from-code-comments.md).
pub const MAX_SURFACE_SEEDS: usize = 5_000;

/// Width of the seed band as a fraction of (boundary - background) echo levels.
pub const SEED_BAND_FRACTION: f64 = 0.1;

/// The surfacer's domain around data points: their box grown by the trust distance, seeds from the
/// points whose value lies within `seed_band` of a level, the points themselves as the region of trust.
pub fn surface_domain(
    points: &[DVec3],
    values: &[f64],
    levels: &[f64],
    seed_band: f64,
    trust_distance_mm: f64,
) -> SurfaceDomain {
    let (lo, hi) = bounds(points);
    let margin = DVec3::splat(trust_distance_mm);
    SurfaceDomain {
        bounds_min_mm: lo - margin,
        bounds_max_mm: hi + margin,
        seeds: surface_seeds(
            points,
            values,
            levels,
            seed_band.max(1.0),
            MAX_SURFACE_SEEDS,
        ),
        trust_points: points.to_vec(),
    }
}

/// Frame outlines (clip rectangle if any, else the image border) as world line segments.
pub fn frame_outlines(
    sequence: &TrackedSequence,
    poses: &PoseResolution,
    calibration: Option<&Calibration>,
) -> Vec<[DVec3; 2]> {
    let clip = calibration
        .and_then(|c| c.clip)
        .and_then(|c| clip_corners_px(sequence.width, sequence.height, &c));
    poses
        .poses
        .iter()
        .flat_map(|p| {
            let corners = match clip {
                Some([u0, v0, u1, v1]) => [(u0, v0), (u1, v0), (u1, v1), (u0, v1)]
                    .map(|(u, v)| p.image_to_world.transform_point3(DVec3::new(u, v, 0.0))),
                None => {
                    // frame_corners lists (0,0), (u,0), (0,v), (u,v): reorder into a cycle.
                    let [a, b, c, d] = frame_corners(sequence, p);
                    [a, b, d, c]
                }
            };
            (0..4).map(move |i| [corners[i], corners[(i + 1) % 4]])
        })
        .collect()
}

/// What the ridge stage reads: the fitted field, the beam at each point, where the surface may go.
pub(super) struct RidgeInputs<'a> {
    pub(super) model: &'a RbfModel,
    pub(super) beams: &'a FrameBeams,
    pub(super) domain: &'a SurfaceDomain,
    pub(super) surface_options: &'a SurfaceOptions,
    pub(super) levels: Option<IntensityLevels>,
    /// A bone sweep's echoes are one-sided ridges (a shadow below): `Sheet::Auto` draws the ridge sheet.
    pub(super) bone_sweep: bool,
}

/// The frames' echo crests with their normals, and where the sheet they extend may go
/// ([`ImageCrests`]).
pub(super) struct CrestExtension<'a> {
    pub(super) crests: &'a OrientedPoints,
    pub(super) domain: &'a SurfaceDomain,
    pub(super) surface_options: &'a SurfaceOptions,
}

/// The echo crests of every placed frame ([`crate::segment::crests::echo_crests`]; those of frames not
/// in `cache` are added to it) in world mm, with normals across their chains tilted by the neighbouring
/// frames ([`orient_crests`]), inside the clip rectangle and, as the segmentation has it, the frames'
/// data region.
pub(super) fn oriented_echo_crests(
    sequence: &TrackedSequence,
    poses: &PoseResolution,
    clip: Option<ClipRect>,
    detect_data_region: bool,
    options: &ImageCrests,
    cache: &mut CrestCache,
) -> Result<OrientedPoints> {
    let frames = echo_crests_reusing(
        sequence,
        poses,
        clip,
        detect_data_region,
        &options.crest,
        cache,
    )?;
    let mut placed = Vec::new();
    for (k, frame) in frames.iter().enumerate() {
        let m = frame.image_to_world;
        // One column and one row of the image, in world mm.
        let (lateral, down) = (m.transform_vector3(DVec3::X), m.transform_vector3(DVec3::Y));
        let frame_normal = lateral.cross(down).normalize_or_zero();
        let beam = down.normalize_or_zero();
        for c in &frame.crests {
            placed.push(PlacedCrest {
                point: m.transform_point3(DVec3::new(c.column, c.row, 0.0)),
                tangent: (lateral + down * c.row_slope).normalize_or_zero(),
                frame_normal,
                beam,
                frame: k as u32,
            });
        }
    }
    Ok(orient_crests(&placed, options.normal_radius_mm))
}

/// Each level's echo ridges on the probe side of its iso-surface ([`proximal_sheet_on_ridge`]), where
/// its ridge sheet is to be drawn (`--sheet ridge`; with `--sheet auto`, only where enough of the
/// iso-surface's probe side reached a ridge); `None` keeps the iso-surface.
pub(super) fn echo_ridges_to_draw(
    meshes: &[Mesh],
    sheets: &mut [SheetUsed],
    inputs: &RidgeInputs,
    options: &ExtractOptions,
) -> Vec<Option<Mesh>> {
    let beam = |x: DVec3| inputs.beams.beam_at(x);
    meshes
        .iter()
        .zip(sheets)
        .map(|(mesh, used)| {
            let (ridge, stats) =
                proximal_sheet_on_ridge(mesh, inputs.model, &beam, &RidgeOptions::default());
            used.ridge_reached_share = Some(stats.reached_share());
            let keep_iso = options.sheet == Sheet::Auto
                && !inputs.bone_sweep
                && stats.reached_share() < AUTO_RIDGE_MIN_REACHED_SHARE;
            (!keep_iso).then_some(ridge)
        })
        .collect()
}

/// Replaces the iso-surface of each level with a ridge (from [`echo_ridges_to_draw`]) by one sheet
/// through its echoes' ridges, extended by the ridges of the weaker echoes that continue them.
pub(super) fn draw_echo_ridge_sheets(
    meshes: &mut [Mesh],
    sheets: &mut [SheetUsed],
    ridges: &[Option<Mesh>],
    inputs: &RidgeInputs,
    options: &ExtractOptions,
) -> Result<()> {
    let beam = |x: DVec3| inputs.beams.beam_at(x);
    for ((mesh, used), ridge) in meshes.iter_mut().zip(sheets).zip(ridges) {
        let Some(ridge) = ridge else {
            continue;
        };
        let (mut sheet, _) = sheet_through_points(
            &ridge.vertices,
            &ridge.normals,
            inputs.domain,
            inputs.surface_options,
            &options.echo_sheet,
        )?;
        if let Some(weak_level) = options.weak_echoes.level_below(used.level, inputs.levels) {
            let weak = WeakRidge {
                strong_level: used.level,
                weak_level,
                reach_mm: options.weak_echoes.reach_mm,
                min_seed_area_mm2: options.min_component_area_for(Sheet::EchoRidge),
            };
            sheet = extend_ridge_sheet(
                sheet,
                inputs.model,
                &beam,
                inputs.domain,
                inputs.surface_options,
                &options.echo_sheet,
                &weak,
            )?;
            used.weak_ridge_level = Some(weak_level);
        }
        *mesh = sheet;
        used.sheet = Sheet::EchoRidge;
    }
    Ok(())
}

/// Removes the triangles far from every echo, then small pieces, then pieces too few frames echo, then
/// draws each ridge sheet again through its vertices and the frames' echo crests linked to them
/// (`extension`; small pieces removed once more), then joins the pieces that continue one another across
/// small gaps, then removes the pieces far smaller than the largest (unless a smallest piece is given),
/// then (if asked) trims the rims.
pub(super) fn remove_and_join_pieces(
    meshes: &mut [Mesh],
    sheets: &mut [SheetUsed],
    prepared: &PreparedSamples,
    frame_size_px: [usize; 2],
    trust_distance_mm: f64,
    extension: Option<&CrestExtension>,
    options: &ExtractOptions,
) -> Result<()> {
    for (mesh, used) in meshes.iter_mut().zip(sheets) {
        // The ridge sheet only: it claims to lie on echoes. The iso sheet wraps a thick bright
        // structure where the fitted field stays above the level beyond the kept band (the real spine
        // sweep: a third of its triangles lie farther than 2.5 mm from a kept block that bright).
        if used.sheet == Sheet::EchoRidge
            && options.max_echo_distance_mm.is_finite()
            && options.max_echo_distance_mm > 0.0
        {
            // The weak echoes' ridges extend the sheet: they back it too.
            let (echoes, frames) =
                kept_echoes(prepared, used.weak_ridge_level.unwrap_or(used.level));
            let reach = EchoReach::new(
                &echoes,
                &frames,
                &prepared.poses,
                frame_size_px,
                options.max_echo_distance_mm,
                0.5 * trust_distance_mm,
            );
            used.max_echo_distance_mm = options.max_echo_distance_mm;
            used.triangles_far_from_echoes = mesh.remove_triangles_not_backed(|v| reach.backs(v));
        }
        used.min_component_area_mm2 = options.min_component_area_for(used.sheet);
        if used.min_component_area_mm2 > 0.0 {
            mesh.remove_small_components(used.min_component_area_mm2);
        }
        // A recording of fewer frames cannot show a wall more often than it has frames.
        used.min_echo_frames = options.min_echo_frames.min(prepared.counts.frames_used);
        if used.min_echo_frames > 0 {
            let (echoes, frames) = kept_echoes(prepared, used.level);
            used.pieces_without_echoes = mesh.remove_components_seen_in_few_frames(
                &echoes,
                &frames,
                ECHO_SUPPORT_RADIUS_MM,
                used.min_echo_frames,
            );
        }
        if let Some(extension) = extension.filter(|_| used.sheet == Sheet::EchoRidge) {
            let (extended, linked) = extend_by_crests(mesh, extension, options)?;
            used.crests_linked = linked;
            if linked > 0 {
                *mesh = extended;
                mesh.remove_small_components(used.min_component_area_mm2);
            }
        }
        // Only pieces that passed both checks are bridged: a crumb next to a wall stays a crumb.
        if options.bridge_gap_mm.is_finite() && options.bridge_gap_mm > 0.0 {
            used.bridge_gap_mm = options.bridge_gap_mm;
            used.bridged_pieces = mesh.bridge_near_pieces(options.bridge_gap_mm);
        }
        // Specks far smaller than the structure, once it has all its pieces: the crests grow some, and
        // a crumb bridged to a wall is part of it.
        used.min_piece_share_of_largest = options.min_piece_share_of_largest();
        if used.min_piece_share_of_largest > 0.0 {
            used.minor_pieces_removed = mesh.remove_minor_components(
                used.min_component_area_mm2,
                used.min_piece_share_of_largest,
            );
        }
        if options.trim_rim_rings > 0 {
            used.trim_rim_rings = options.trim_rim_rings;
            used.rim_triangles_trimmed = mesh.trim_rim(options.trim_rim_rings);
        }
    }
    Ok(())
}

/// A piece of the ridge sheet drawn again with the frames' crests is kept when at least this share of
/// its triangles lies near the sheet as it was: it continues that sheet rather than being drawn through
/// crests alone (measured in docs/decisions/0044-image-crests.md).
pub const CRESTS_MIN_ANCHORED_SHARE: f64 = 0.5;

/// `mesh` drawn again through its vertices (those of its triangles) and the crests linked to them,
/// less the pieces that do not continue it ([`CRESTS_MIN_ANCHORED_SHARE`]); the number of crests linked
/// (0: `mesh` has no normals, or no crest is linked).
fn extend_by_crests(
    mesh: &Mesh,
    extension: &CrestExtension,
    options: &ExtractOptions,
) -> Result<(Mesh, usize)> {
    if mesh.normals.len() != mesh.vertices.len() {
        return Ok((Mesh::default(), 0));
    }
    let mut used = vec![false; mesh.vertices.len()];
    for t in &mesh.triangles {
        for &i in t {
            used[i as usize] = true;
        }
    }
    let (points, normals) = mesh
        .vertices
        .iter()
        .zip(&mesh.normals)
        .zip(&used)
        .filter(|(_, u)| **u)
        .map(|((p, n), _)| (*p, *n))
        .unzip();
    let mut points = OrientedPoints { points, normals };
    let anchors = points.points.clone();
    let link = CrestLink {
        seed_mm: options.image_crests.seed_mm,
        link_mm: options.image_crests.link_mm,
    };
    let linked = add_linked_crests(&mut points, extension.crests, link);
    if linked == 0 {
        return Ok((Mesh::default(), 0));
    }
    let (mut sheet, _) = sheet_through_points(
        &points.points,
        &points.normals,
        extension.domain,
        extension.surface_options,
        &options.echo_sheet,
    )?;
    keep_pieces_reaching(
        &mut sheet,
        &anchors,
        link.seed_mm,
        CRESTS_MIN_ANCHORED_SHARE,
    );
    Ok((sheet, linked))
}

/// The kept blocks at or above `level` (positions, and the frame each came from): all of them, not just
/// the fitted samples, so that the checks on a surface do not depend on the sample budget.
pub(super) fn kept_echoes(prepared: &PreparedSamples, level: f64) -> (Vec<DVec3>, Vec<u32>) {
    let all = &prepared.all;
    all.positions
        .iter()
        .zip(&all.intensities)
        .zip(&all.frame_of_sample)
        .filter(|((_, value), _)| **value as f64 >= level)
        .map(|((&p, _), &f)| (p, f))
        .unzip()
}

pub(super) fn bounds(points: &[DVec3]) -> (DVec3, DVec3) {
    points.iter().fold(
        (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
        |(lo, hi), p| (lo.min(*p), hi.max(*p)),
    )
}
