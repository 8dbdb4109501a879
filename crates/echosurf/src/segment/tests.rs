use super::synthetic::{SyntheticSweep, synthetic_sweep};
use super::*;
use glam::DMat4;

use crate::io::{ClipRect, FramePose, PixelData, TrackedFrame};
use crate::progress::NoProgress;

/// Share of the pixels within `radius_mm` of the true boundary that are kept, over `frames`, and the kept
/// share of all pixels.
fn coverage(
    s: &SyntheticSweep,
    masks: &BandMasks,
    frames: impl Iterator<Item = usize>,
    radius_mm: f64,
) -> (f64, f64) {
    let (w, h) = (s.sequence.width, s.sequence.height);
    let r_px = radius_mm / s.pixel_size_mm;
    let (mut near, mut near_kept, mut kept, mut all) = (0usize, 0usize, 0usize, 0usize);
    for f in frames {
        let m = &masks.masks[f];
        kept += m.iter().filter(|&&x| x != 0).count();
        all += w * h;
        for u in 0..w {
            let b = s.boundary_row(f, u as f64);
            // The curve's slope is below 1, so every pixel within r of it is within 2r vertically.
            let v_lo = (b - 2.0 * r_px).floor().max(0.0) as usize;
            let v_hi = ((b + 2.0 * r_px).ceil() as usize).min(h - 1);
            for v in v_lo..=v_hi {
                if s.distance_to_boundary_px(f, u, v, r_px + 1.0) <= r_px {
                    near += 1;
                    near_kept += (m[v * w + u] != 0) as usize;
                }
            }
        }
    }
    eprintln!("near-boundary pixels kept {near_kept}/{near}, kept {kept}/{all}");
    (near_kept as f64 / near as f64, kept as f64 / all as f64)
}

fn polygon_around_first_boundary(s: &SyntheticSweep, half_width_px: f64) -> Vec<[f64; 2]> {
    let w = s.sequence.width as f64;
    let mut poly: Vec<[f64; 2]> = (0..=32)
        .map(|k| {
            let u = -1.0 + (w + 1.0) * k as f64 / 32.0;
            [u, s.boundary_row(0, u) - half_width_px]
        })
        .collect();
    poly.extend((0..=32).rev().map(|k| {
        let u = -1.0 + (w + 1.0) * k as f64 / 32.0;
        [u, s.boundary_row(0, u) + half_width_px]
    }));
    poly
}

/// The default segmentation from a polygon +/- 15 px around the first frame's boundary.
fn segment_from_first_polygon(s: &SyntheticSweep) -> BandMasks {
    segment_sequence(
        &s.sequence,
        &s.poses,
        None,
        &InitialBand::Polygon(polygon_around_first_boundary(s, 15.0)),
        &SegmentOptions::default(),
        &NoProgress,
    )
    .unwrap()
}

/// Share of the pixels 12-20 px from the boundary of `frame`, in columns `columns`, that its mask keeps:
/// beyond the narrow radius of an unconfirmed echo (11.4 px), inside the full band (29.2 px).
fn flank_kept(
    s: &SyntheticSweep,
    masks: &BandMasks,
    frame: usize,
    columns: std::ops::Range<usize>,
) -> f64 {
    let w = s.sequence.width;
    let (mut near, mut kept) = (0usize, 0usize);
    for u in columns {
        let b = s.boundary_row(frame, u as f64).round() as usize;
        for v in b.saturating_sub(40)..(b + 40).min(s.sequence.height) {
            if (12.0..=20.0).contains(&s.distance_to_boundary_px(frame, u, v, 41.0)) {
                near += 1;
                kept += (masks.masks[frame][v * w + u] != 0) as usize;
            }
        }
    }
    kept as f64 / near as f64
}

#[test]
fn auto_init_band_keeps_the_boundary_and_drops_most_pixels() {
    let s = synthetic_sweep(320, 240, 10, 0.15, 3.0, 7);
    let masks = segment_sequence(
        &s.sequence,
        &s.poses,
        None,
        &InitialBand::Auto,
        &SegmentOptions::default(),
        &NoProgress,
    )
    .unwrap();
    let (kept_near, kept_all) = coverage(&s, &masks, 0..10, 1.0);
    assert!(
        kept_near >= 0.99,
        "kept {kept_near} of the pixels within 1 mm"
    );
    assert!(kept_all <= 0.30, "kept {kept_all} of all pixels");
    assert!(masks.warnings.is_empty(), "{:?}", masks.warnings);
    assert_eq!(masks.initialised_frames, vec![0]);
}

#[test]
fn polygon_init_band_keeps_the_boundary_and_drops_most_pixels() {
    let s = synthetic_sweep(320, 240, 10, 0.15, -4.0, 11);
    let masks = segment_from_first_polygon(&s);
    let (kept_near, kept_all) = coverage(&s, &masks, 0..10, 1.0);
    assert!(
        kept_near >= 0.99,
        "kept {kept_near} of the pixels within 1 mm"
    );
    assert!(kept_all <= 0.30, "kept {kept_all} of all pixels");
    assert!(masks.warnings.is_empty(), "{:?}", masks.warnings);
}

#[test]
fn mm_lengths_convert_with_the_pixel_size() {
    let s = synthetic_sweep(96, 80, 2, 0.2, 0.0, 1);
    let options = SegmentOptions {
        likelihood_sigma: Length::Mm(3.0),
        likelihood_truncation: Length::Mm(6.4),
        ..Default::default()
    };
    let masks = segment_sequence(
        &s.sequence,
        &s.poses,
        None,
        &InitialBand::Auto,
        &options,
        &NoProgress,
    )
    .unwrap();
    let p = masks.parameters;
    assert!((p.likelihood_sigma_px - 15.0).abs() < 1e-9);
    assert!((p.likelihood_truncation_px - 32.0).abs() < 1e-9);
    // sigma sqrt(2 ln(C1 / (T - C0))) and sigma sqrt(2 ln(C0 / (T - C0))) with the paper's values.
    assert!((p.band_radius_inside_px - 15.0 * (2.0 * (1.0f64 / 0.15).ln()).sqrt()).abs() < 1e-9);
    assert!((p.band_radius_outside_px - 15.0 * (2.0 * (0.2f64 / 0.15).ln()).sqrt()).abs() < 1e-9);
}

/// An MF sequence of `w` x `h` grey frames (`pixels` holds them one after the other), every frame
/// placed at the same pose: what the band does depends on the pixels alone.
fn frames_in_place(w: usize, h: usize, pixels: Vec<u8>) -> (TrackedSequence, PoseResolution) {
    let n = pixels.len() / (w * h);
    let sequence = TrackedSequence {
        width: w,
        height: h,
        channels: 1,
        orientation: "MF".into(),
        frames: vec![TrackedFrame::default(); n],
        pixels: PixelData::U8(pixels),
        header: Default::default(),
    };
    let poses = PoseResolution {
        poses: (0..n)
            .map(|k| FramePose {
                frame_index: k,
                image_to_world: DMat4::IDENTITY,
            })
            .collect(),
        skipped: vec![],
        world_frame: "Tracker".into(),
    };
    (sequence, poses)
}

#[test]
fn band_follows_the_boundary_and_is_centred_on_it() {
    // A clean horizontal step moving 6 px per frame: the band must be the paper's +/-29 px around this
    // frame's edge, not around the first frame's.
    let (w, h, n) = (64usize, 160usize, 6usize);
    let mut pixels = Vec::new();
    for k in 0..n {
        let edge = 40 + 6 * k;
        for v in 0..h {
            pixels.extend(std::iter::repeat_n(if v >= edge { 200u8 } else { 20 }, w));
        }
    }
    let (sequence, poses) = frames_in_place(w, h, pixels);
    let init = InitialBand::Polygon(vec![[-1.0, 30.0], [70.0, 30.0], [70.0, 50.0], [-1.0, 50.0]]);
    let masks = segment_sequence(
        &sequence,
        &poses,
        None,
        &init,
        &SegmentOptions::default(),
        &NoProgress,
    )
    .unwrap();
    for k in 0..n {
        let rows: Vec<usize> = (0..h)
            .filter(|&v| masks.masks[k][v * w + w / 2] != 0)
            .collect();
        // Edgel at row edge-1 (central difference peaks at edge - 0.5, maximum kept at the upper row);
        // radius 29.2 px -> rows edge-1-29 ..= edge-1+29.
        let edge = 40 + 6 * k;
        // The step sits between rows edge-1 and edge: the two central differences tie, so the edgel is
        // on either row.
        let first = rows[0];
        assert!(
            first == edge - 1 - 29 || first == edge - 29,
            "frame {k}: first kept row {first}"
        );
        assert_eq!(rows.last().copied(), Some(first + 58), "frame {k}");
        assert_eq!(rows.len(), 59, "frame {k}");
    }
}

#[test]
fn clip_rectangle_and_invalid_frames_give_zero_pixels() {
    let mut s = synthetic_sweep(160, 120, 4, 0.15, 0.0, 3);
    // Frame 2 has no pose.
    s.poses.poses.retain(|p| p.frame_index != 2);
    let segment_within = |origin_px: [usize; 2], size_px: [usize; 2]| {
        let clip = ClipRect { origin_px, size_px };
        let masks = segment_sequence(
            &s.sequence,
            &s.poses,
            Some(clip),
            &InitialBand::Auto,
            &SegmentOptions::default(),
            &NoProgress,
        );
        (clip, masks.unwrap())
    };
    let (clip, masks) = segment_within([20, 10], [100, 90]);
    assert!(masks.masks[2].iter().all(|&m| m == 0));
    for f in [0, 1, 3] {
        let m = &masks.masks[f];
        assert!(m.contains(&255));
        for v in 0..120 {
            for u in 0..160 {
                if !clip.contains(u, v) {
                    assert_eq!(
                        m[v * 160 + u],
                        0,
                        "frame {f} pixel ({u}, {v}) outside the clip"
                    );
                }
            }
        }
    }
    let seq = masks.to_sequence();
    assert_eq!((seq.width, seq.height, seq.frames.len()), (160, 120, 4));
    assert_eq!(seq.pixels.len(), 160 * 120 * 4);
    assert!(masks.warnings.is_empty(), "{:?}", masks.warnings);

    // A rectangle reaching past the frame (a calibration for a larger image) is cut to the frame, and
    // said so once, before any per-frame warning.
    let (_, cut) = segment_within([20, 10], [400, 90]);
    let warned = cut
        .warnings
        .iter()
        .filter(|w| w.contains("clip rectangle"))
        .count();
    assert_eq!(warned, 1, "{:?}", cut.warnings);
    assert!(
        cut.warnings[0].contains("origin 20 10, size 400 x 90 px")
            && cut.warnings[0].contains("160 x 120")
    );
    let (_, fitting) = segment_within([20, 10], [140, 90]);
    assert!(fitting.warnings.is_empty(), "{:?}", fitting.warnings);
    assert_eq!(cut.masks, fitting.masks);
}

#[test]
fn lost_band_is_reported_with_its_frame_and_recovered() {
    // Frames 0-4 and 7-11: one sweep whose boundary jumps 60 px deeper at frame 5 (probe re-placed);
    // frame 6 is a black dropout.
    let mut s = synthetic_sweep(320, 240, 12, 0.15, 0.0, 5);
    let jumped = synthetic_sweep(320, 240, 12, 0.15, 0.0, 6);
    let (w, h) = (320usize, 240usize);
    let PixelData::U8(px) = &mut s.sequence.pixels else {
        unreachable!()
    };
    for f in 0..12 {
        if f >= 5 {
            let [base, amp, freq, phase] = jumped.curves[f];
            s.curves[f] = [base + 60.0, amp, freq, phase];
        }
    }
    // Build the jumped frames by shifting the other sweep's rows down by 60 px.
    let PixelData::U8(other) = &jumped.sequence.pixels else {
        unreachable!()
    };
    for f in 5..12 {
        for v in 0..h {
            let src_v = v.saturating_sub(60);
            let src = &other[f * w * h + src_v * w..f * w * h + (src_v + 1) * w];
            px[f * w * h + v * w..f * w * h + (v + 1) * w].copy_from_slice(src);
        }
    }
    px[6 * w * h..7 * w * h].fill(0);
    let masks = segment_from_first_polygon(&s);
    assert!(
        masks
            .warnings
            .iter()
            .any(|w| w.starts_with("frame 5: band lost")),
        "{:?}",
        masks.warnings
    );
    assert!(
        masks.warnings.iter().any(|w| w.starts_with("frame 6:")),
        "{:?}",
        masks.warnings
    );
    assert!(masks.initialised_frames.contains(&5) && masks.initialised_frames.contains(&7));
    // Recovered: every frame but the black one keeps the boundary.
    let (kept_near, kept_all) = coverage(&s, &masks, (0..12).filter(|&f| f != 6), 1.0);
    assert!(kept_near >= 0.99, "kept {kept_near}");
    assert!(kept_all <= 0.30, "kept {kept_all}");
    assert!(masks.masks[6].iter().all(|&m| m == 0));
}

#[test]
fn wrong_size_mask_and_empty_polygon_are_errors() {
    let s = synthetic_sweep(64, 48, 2, 0.15, 0.0, 2);
    let mask = InitialBand::Mask {
        width: 10,
        height: 10,
        data: vec![true; 100],
    };
    let err = segment_sequence(
        &s.sequence,
        &s.poses,
        None,
        &mask,
        &SegmentOptions::default(),
        &NoProgress,
    )
    .unwrap_err()
    .to_string();
    assert!(err.contains("10x10") && err.contains("64x48"), "{err}");
    let err = segment_sequence(
        &s.sequence,
        &s.poses,
        None,
        &InitialBand::Polygon(vec![]),
        &SegmentOptions::default(),
        &NoProgress,
    )
    .unwrap_err()
    .to_string();
    assert!(err.contains("0 vertices"), "{err}");

    let dir = tempfile::tempdir().unwrap();
    let empty = dir.path().join("empty.json");
    std::fs::write(&empty, r#"{"polygon": []}"#).unwrap();
    let err = InitialBand::from_polygon_json(&empty)
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("empty.json") && err.contains("0 vertices"),
        "{err}"
    );
    let bad = dir.path().join("bad.json");
    std::fs::write(&bad, r#"{"poly": [[1, 2]]"#).unwrap();
    let err = InitialBand::from_polygon_json(&bad)
        .unwrap_err()
        .to_string();
    assert!(err.contains("bad.json"), "{err}");

    // A PNG of the wrong size names the file and both sizes; a right-sized one round-trips.
    let png_path = dir.path().join("band.png");
    let mut bytes = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut bytes, 10, 8);
        enc.set_color(png::ColorType::Grayscale);
        enc.set_depth(png::BitDepth::Eight);
        let mut wr = enc.write_header().unwrap();
        let mut data = vec![0u8; 80];
        data[13] = 255;
        wr.write_image_data(&data).unwrap();
    }
    std::fs::write(&png_path, &bytes).unwrap();
    let err = InitialBand::load(&png_path, 64, 48)
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("band.png") && err.contains("10x8") && err.contains("64x48"),
        "{err}"
    );
    match InitialBand::load(&png_path, 10, 8).unwrap() {
        InitialBand::Mask {
            width,
            height,
            data,
        } => {
            assert_eq!((width, height), (10, 8));
            assert_eq!(data.iter().filter(|&&b| b).count(), 1);
            assert!(data[13]);
        }
        other => panic!("expected a mask, got {other:?}"),
    }
    let not_png = dir.path().join("junk.png");
    std::fs::write(&not_png, b"not a png").unwrap();
    let err = InitialBand::from_png(&not_png).unwrap_err().to_string();
    assert!(err.contains("junk.png"), "{err}");
}

#[test]
fn bad_options_are_rejected_by_name() {
    let s = synthetic_sweep(32, 32, 1, 0.15, 0.0, 2);
    let cases = [
        (
            SegmentOptions {
                threshold: 0.1,
                ..Default::default()
            },
            "prior_outside",
        ),
        (
            SegmentOptions {
                min_edgel_relative_strength: -0.1,
                ..Default::default()
            },
            "min_edgel_relative_strength",
        ),
        (
            SegmentOptions {
                smoothing_sigma: Length::Mm(f64::NAN),
                ..Default::default()
            },
            "smoothing_sigma",
        ),
        (
            SegmentOptions {
                edgel_count: Some(0),
                ..Default::default()
            },
            "edgel_count",
        ),
    ];
    for (options, name) in cases {
        let err = segment_sequence(
            &s.sequence,
            &s.poses,
            None,
            &InitialBand::Auto,
            &options,
            &NoProgress,
        )
        .unwrap_err()
        .to_string();
        assert!(err.contains(name), "{err}");
    }
}

#[test]
fn result_does_not_depend_on_thread_count() {
    let s = synthetic_sweep(200, 150, 3, 0.15, 2.0, 9);
    let run = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| {
                segment_sequence(
                    &s.sequence,
                    &s.poses,
                    None,
                    &InitialBand::Auto,
                    &SegmentOptions::default(),
                    &NoProgress,
                )
                .unwrap()
                .masks
            })
    };
    assert_eq!(run(1), run(3));
}

#[test]
fn preview_montage_is_written() {
    let s = synthetic_sweep(120, 90, 4, 0.15, 1.0, 4);
    let masks = segment_sequence(
        &s.sequence,
        &s.poses,
        None,
        &InitialBand::Auto,
        &SegmentOptions::default(),
        &NoProgress,
    )
    .unwrap();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("p.png");
    let frames = default_preview_frames(&masks, 9);
    assert_eq!(frames, vec![0, 1, 2, 3]);
    write_band_preview(&path, &s.sequence, &masks, &frames).unwrap();
    let decoder = png::Decoder::new(std::fs::File::open(&path).unwrap());
    let reader = decoder.read_info().unwrap();
    // 2 x 2 tiles of 120 x 90 with 4 px gaps.
    assert_eq!(
        (reader.info().width, reader.info().height),
        (2 * 120 + 12, 2 * 90 + 12)
    );
}

#[test]
fn black_margins_of_the_frame_grab_are_not_data() {
    // A scanner frame grab: image data in the middle, exact zeros around it (the PLUS spine data).
    let mut s = synthetic_sweep(200, 150, 3, 0.15, 0.0, 8);
    let (w, h) = (200usize, 150usize);
    let PixelData::U8(px) = &mut s.sequence.pixels else {
        unreachable!()
    };
    for f in 0..3 {
        for v in 0..h {
            for u in 0..w {
                if !(30..170).contains(&u) || v < 12 {
                    px[f * w * h + v * w + u] = 0;
                }
            }
        }
    }
    let masks = segment_sequence(
        &s.sequence,
        &s.poses,
        None,
        &InitialBand::Auto,
        &SegmentOptions::default(),
        &NoProgress,
    )
    .unwrap();
    for f in 0..3 {
        for v in 0..h {
            for u in 0..w {
                if !(30..170).contains(&u) || v < 12 {
                    assert_eq!(masks.masks[f][v * w + u], 0, "frame {f} ({u}, {v})");
                }
            }
        }
    }
    // The boundary inside the data region is still kept.
    let u = 100;
    let b = s.boundary_row(1, u as f64).round() as usize;
    assert_eq!(masks.masks[1][b * w + u], 255);
}

#[test]
fn backward_pass_gives_an_echo_the_full_band_on_the_frame_it_enters() {
    // A polygon around the left half of the boundary only: going forward, the right half's edgels lie
    // outside the initial band on frame 0 and get the narrow outside radius (11.4 px); from frame 1 on
    // (carried inside that narrow band) the band is whole. Going back, frame 0 inherits the whole band.
    let s = synthetic_sweep(320, 240, 8, 0.15, 2.0, 11);
    let half = s.sequence.width as f64 / 2.0;
    let full = polygon_around_first_boundary(&s, 15.0);
    let left: Vec<[f64; 2]> = full.into_iter().filter(|p| p[0] <= half).collect();
    let run = |backward_pass: bool| {
        segment_sequence(
            &s.sequence,
            &s.poses,
            None,
            &InitialBand::Polygon(left.clone()),
            &SegmentOptions {
                backward_pass,
                ..SegmentOptions::default()
            },
            &NoProgress,
        )
        .unwrap()
    };
    let (forward, both) = (run(false), run(true));
    let right = s.sequence.width / 2 + 20..s.sequence.width - 5;
    let right_flank = |masks: &BandMasks, f: usize| flank_kept(&s, masks, f, right.clone());
    assert!(
        right_flank(&forward, 0) < 0.5,
        "{}",
        right_flank(&forward, 0)
    );
    assert!(right_flank(&both, 0) > 0.99, "{}", right_flank(&both, 0));
    assert!(right_flank(&forward, 1) > 0.99);
    // The backward pass only adds to the forward bands.
    for f in 0..8 {
        assert!(
            forward.masks[f]
                .iter()
                .zip(&both.masks[f])
                .all(|(&a, &b)| a == 0 || b != 0),
            "frame {f}"
        );
    }
    let (near_kept, kept_all) = coverage(&s, &both, 0..8, 1.0);
    assert!(
        near_kept >= 0.99 && kept_all <= 0.30,
        "{near_kept} {kept_all}"
    );
}

#[test]
fn a_later_sweep_starts_from_the_given_band_and_the_carried_one() {
    // One pass whose boundary drifts 3 px per frame, with the probe jumping 10 mm after frame 5 (a
    // sweep break). The polygon drawn around frame 0's boundary (+/- 15 px) no longer holds frame 6's
    // boundary, which has moved 18 px; the band carried from frame 5 does, so frame 6 keeps its
    // boundary at full width (29 px), not at the narrow width of an unconfirmed echo (11.4 px).
    let mut s = synthetic_sweep(320, 240, 10, 0.15, 3.0, 13);
    for p in &mut s.poses.poses[6..] {
        p.image_to_world =
            DMat4::from_translation(glam::DVec3::new(10.0, 0.0, 0.0)) * p.image_to_world;
    }
    let masks = segment_from_first_polygon(&s);
    assert_eq!(masks.initialised_frames, vec![0, 6], "{:?}", masks.warnings);
    let flank = flank_kept(&s, &masks, 6, 10..s.sequence.width - 10);
    assert!(flank > 0.99, "{flank}");
    let (near_kept, kept_all) = coverage(&s, &masks, 0..10, 1.0);
    assert!(
        near_kept >= 0.99 && kept_all <= 0.30,
        "{near_kept} {kept_all}"
    );
}

#[test]
fn a_band_that_follows_what_it_holds_never_takes_in_a_second_echo() {
    // Two clean echoes 100 px apart in every frame (rows 40 and 140 of 200); the first band is drawn
    // around the upper one. By default the lower echo's edgels, outside the band, keep 11.4 px around
    // them on frame 0 and the full band from frame 1 on; following the band, no pixel near it is kept.
    let (w, h, n) = (64usize, 200usize, 5usize);
    let row_grey = |v: usize| match v {
        40..=49 | 140..=149 => 200u8,
        _ => 20,
    };
    let frame: Vec<u8> = (0..h)
        .flat_map(|v| std::iter::repeat_n(row_grey(v), w))
        .collect();
    let (sequence, poses) = frames_in_place(w, h, frame.repeat(n));
    let upper = InitialBand::Polygon(vec![[-1.0, 25.0], [70.0, 25.0], [70.0, 60.0], [-1.0, 60.0]]);
    let run = |follow_band: bool| {
        let options = SegmentOptions {
            follow_band,
            // One edgel per column on each echo (the M largest would otherwise all lie on one).
            edgel_count: Some(2 * w),
            ..SegmentOptions::default()
        };
        segment_sequence(&sequence, &poses, None, &upper, &options, &NoProgress).unwrap()
    };
    let rows_kept = |masks: &BandMasks, f: usize, rows: std::ops::Range<usize>| {
        rows.filter(|&v| masks.masks[f][v * w + w / 2] != 0).count()
    };
    let (default, following) = (run(false), run(true));
    for f in 0..n {
        // Both keep the upper echo at full width: 29 px either side of its edgel (row 39).
        assert_eq!(rows_kept(&default, f, 10..70), 59, "frame {f}");
        assert_eq!(rows_kept(&following, f, 10..70), 59, "frame {f}");
        assert_eq!(rows_kept(&following, f, 100..h), 0, "frame {f}");
        assert!(following.warnings.is_empty(), "{:?}", following.warnings);
    }
    assert_eq!(
        rows_kept(&default, 0, 100..h),
        23,
        "11.4 px either side of row 139"
    );
    for f in 1..n {
        assert_eq!(rows_kept(&default, f, 100..h), 59, "frame {f}");
    }
    assert_eq!(following.parameters.band_radius_outside_px, 0.0);
}

use echosurf_testkit::png_pixels;
use png_pixels::read_grey_png;

#[test]
fn a_frame_is_written_pixel_for_pixel_to_draw_on() {
    let s = synthetic_sweep(40, 30, 3, 0.15, 1.0, 5);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("frame2.png");
    write_frame_png(&path, &s.sequence, 2).unwrap();
    let PixelData::U8(px) = &s.sequence.pixels else {
        unreachable!()
    };
    let (w, h, grey) = read_grey_png(&path);
    assert_eq!((w, h), (40, 30));
    assert_eq!(grey, px[2 * 1200..3 * 1200]);

    // Other pixel types: the frame's own range mapped to 0..255.
    let mut wide = s.sequence.clone();
    wide.pixels = PixelData::U16(px.iter().map(|&g| 1000 + 4 * g as u16).collect());
    write_frame_png(&path, &wide, 2).unwrap();
    let (_, _, scaled) = read_grey_png(&path);
    let frame = &px[2 * 1200..3 * 1200];
    let (lo, hi) = (*frame.iter().min().unwrap(), *frame.iter().max().unwrap());
    assert!(hi > lo);
    for (&g, &out) in frame.iter().zip(&scaled) {
        let want = (g - lo) as f64 * 255.0 / (hi - lo) as f64;
        assert!(
            (out as f64 - want).abs() <= 0.5 + 1e-9,
            "{g} -> {out}, want {want}"
        );
    }

    let err = write_frame_png(&dir.path().join("x.png"), &s.sequence, 3)
        .unwrap_err()
        .to_string();
    assert!(err.contains("frame 3") && err.contains("3 frames"), "{err}");
    assert!(!dir.path().join("x.png").exists());
}

#[test]
fn a_band_painted_on_a_transparent_layer_is_what_was_painted() {
    // RGBA 4 x 1: painted opaque red; transparent but coloured (an editor may keep colour under
    // alpha 0); opaque black; half-transparent white.
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("layer.png");
    let mut bytes = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut bytes, 4, 1);
        enc.set_color(png::ColorType::Rgba);
        enc.set_depth(png::BitDepth::Eight);
        let mut wr = enc.write_header().unwrap();
        wr.write_image_data(&[
            255, 0, 0, 255, 200, 200, 200, 0, 0, 0, 0, 255, 255, 255, 255, 128,
        ])
        .unwrap();
    }
    std::fs::write(&path, &bytes).unwrap();
    match InitialBand::from_png(&path).unwrap() {
        InitialBand::Mask { data, .. } => assert_eq!(data, vec![true, false, false, true]),
        other => panic!("expected a mask, got {other:?}"),
    }
}
