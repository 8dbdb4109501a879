//! Latency of the live surface on the demo's sweep (the simulated duck, seed 1, 180 frames): the frames
//! go through the codec (encode, read, decode) into a session as they would arrive; after every
//! `--update-every` (30) frames the update surface is timed, then the new frames' echo crests as the
//! client's worker finds them; after the last frame the final mesh (`extract`'s defaults, reading those
//! crests), beside `extract` from scratch before and after it (the same mesh, asserted).
//! Run: `cargo bench -p echosurf-live --bench live_latency` (env `LIVE_UPDATE_SAMPLES` sets the update's sample budget, default 10000, and
//! `LIVE_UPDATE_RESOLUTION_MM` its surfacer lattice, default 1).
//! The targets it reports against (issue #30): an update within 1 s after each 30 new frames, the final
//! mesh within 2 s of the last frame. It also prints the final `extract`'s stage times, and the final
//! beside the last update still running (left to finish, or abandoned as the client does), with how
//! long that update went on into the final.

use std::sync::atomic::AtomicBool;
use std::time::Instant;

use echosurf::io::{ReferenceChoice, resolve_poses};
use echosurf::pipeline::{ExtractOptions, Reused, extract_reusing};
use echosurf::progress::NoProgress;
use echosurf::segment::crests::CrestCache;
use echosurf_live::codec::{self, Image, Limits, encode_message};
use echosurf_live::session::{
    IncrementalBands, LiveSession, SessionOptions, add_echo_crests, update_extract_options,
    update_surface, update_surface_unless_stopped,
};
use echosurf_sim::{SimulationOptions, simulate};

const UPDATE_EVERY: usize = 30;

fn main() {
    // `cargo bench` passes `--bench`; nothing else is taken.
    faer::set_global_parallelism(faer::Par::Seq);
    let samples: usize = std::env::var("LIVE_UPDATE_SAMPLES")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(10_000);
    let resolution_mm: f64 = std::env::var("LIVE_UPDATE_RESOLUTION_MM")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(1.0);
    let sim = simulate(&SimulationOptions::default(), &NoProgress).expect("simulate the duck");
    let sequence = &sim.sequence;
    let calibration = &sim.calibration_written;
    let poses = resolve_poses(
        sequence,
        Some(calibration),
        ReferenceChoice::Auto,
        std::path::Path::new("<duck>"),
    )
    .expect("poses");
    let echosurf::io::PixelData::U8(pixels) = &sequence.pixels else {
        panic!("8-bit frames")
    };
    let frame_len = sequence.frame_len();
    let mut session = LiveSession::new(SessionOptions {
        update_every_frames: UPDATE_EVERY,
        ..SessionOptions::default()
    });
    let update_options = update_extract_options(samples, resolution_mm);
    let mut bands = IncrementalBands::default();
    let mut bands_before_last = IncrementalBands::default();
    let mut crests = CrestCache::default();
    let mut worst_crests_s = 0.0f64;
    let mut receive_s = 0.0f64;
    let mut worst_update_s = 0.0f64;
    println!(
        "live latency, demo duck ({} frames of {} x {} px), update every {UPDATE_EVERY} frames, {samples} samples, {resolution_mm} mm lattice, iso sheet",
        poses.poses.len(),
        sequence.width,
        sequence.height
    );
    for pose in &poses.poses {
        let k = pose.frame_index;
        let image = Image::from_u8_frame(
            sequence.width as u16,
            sequence.height as u16,
            pixels[k * frame_len..(k + 1) * frame_len].to_vec(),
            &pose.image_to_world,
        );
        let t = sequence.frames[k].timestamp_s.unwrap_or(k as f64 / 30.0);
        let bytes = encode_message(2, "IMAGE", "Image_Reference", t, &image.encode(), &[], 0);
        let start = Instant::now();
        let raw = codec::read_message(&mut &bytes[..], &Limits::default()).expect("read");
        let decoded = codec::decode(&raw).expect("decode");
        let warnings = session.handle(&decoded);
        receive_s = receive_s.max(start.elapsed().as_secs_f64());
        assert!(warnings.is_empty(), "{warnings:?}");
        if session.update_due() {
            bands_before_last = bands.clone();
            let snapshot = session.snapshot_for_update();
            let start = Instant::now();
            let mesh = update_surface(&mut bands, &snapshot, calibration, &update_options)
                .expect("update");
            let s = start.elapsed().as_secs_f64();
            worst_update_s = worst_update_s.max(s);
            // Then, as the client's worker does, the new frames' echo crests for the final mesh.
            let start = Instant::now();
            add_echo_crests(
                &snapshot,
                calibration,
                &ExtractOptions::default(),
                &mut crests,
                &AtomicBool::new(false),
            )
            .expect("crests");
            let crests_s = start.elapsed().as_secs_f64();
            worst_crests_s = worst_crests_s.max(crests_s);
            println!(
                "  update at {:>3} frames: {:>6} triangles in {s:.3} s, then the new frames' crests in {crests_s:.3} s",
                snapshot.frames.len(),
                mesh.triangles.len()
            );
        }
    }
    let recorded = session.sequence();
    let update_options = &update_options;
    // The client's final mesh: `extract`, with the crests the worker found during the sweep (a fresh
    // copy each time, as the sweep left them).
    let final_extract = || {
        let mut found = crests.clone();
        let reused = Reused {
            masks: None,
            crests: Some(&mut found),
        };
        extract_reusing(
            recorded,
            Some(calibration),
            &ExtractOptions::default(),
            reused,
            &NoProgress,
        )
        .expect("final")
    };
    // Before/after in one run: `extract` finding every frame's crests itself, before the final mesh
    // and after it (the machine's drift falls on both sides).
    let extract_from_scratch = || {
        let start = Instant::now();
        let output = echosurf::pipeline::extract(
            recorded,
            Some(calibration),
            &ExtractOptions::default(),
            &NoProgress,
        )
        .expect("final from scratch");
        (output, start.elapsed().as_secs_f64())
    };
    let (from_scratch, from_scratch_s) = extract_from_scratch();
    let start = Instant::now();
    let final_output = final_extract();
    let final_s = start.elapsed().as_secs_f64();
    let from_scratch_after_s = extract_from_scratch().1;
    assert_eq!(
        from_scratch.surfaces.first().map(|s| &s.mesh),
        final_output.surfaces.first().map(|s| &s.mesh),
        "the final mesh with the sweep's crests is extract's"
    );
    // The client's case: the last update (its bands as before it) is still running when the sweep
    // ends. Left to finish, it shares the cores with the final mesh; stopped, it is abandoned.
    // Returns the final's time and how long the update went on beside it.
    let final_beside_update = |abandon: bool| {
        let stop = std::sync::atomic::AtomicBool::new(false);
        let mut last_bands = bands_before_last.clone();
        std::thread::scope(|scope| {
            let (stop, last_bands) = (&stop, &mut last_bands);
            let update = scope.spawn(move || {
                update_surface_unless_stopped(
                    last_bands,
                    recorded,
                    calibration,
                    update_options,
                    stop,
                );
                Instant::now()
            });
            // Let the update get going, as it would be when the last frame arrives.
            std::thread::sleep(std::time::Duration::from_millis(100));
            let start = Instant::now();
            if abandon {
                stop.store(true, std::sync::atomic::Ordering::Relaxed);
            }
            let _ = final_extract();
            let final_s = start.elapsed().as_secs_f64();
            let update_ended = update.join().expect("update thread");
            (final_s, update_ended.duration_since(start).as_secs_f64())
        })
    };
    let beside_finished_s = final_beside_update(false);
    let beside_abandoned_s = final_beside_update(true);
    let stages: Vec<String> = final_output
        .report
        .stages
        .iter()
        .map(|s| format!("{} {:.3} s", s.stage, s.seconds))
        .collect();
    let final_mesh = final_output
        .surfaces
        .into_iter()
        .next()
        .map(|s| s.mesh)
        .unwrap_or_default();
    println!("  slowest frame received and recorded: {:.4} s", receive_s);
    println!(
        "  slowest update: {worst_update_s:.3} s (target 1 s: {})",
        if worst_update_s <= 1.0 {
            "met"
        } else {
            "NOT met"
        }
    );
    println!(
        "  last frame to final mesh ({} triangles, extract's defaults): {final_s:.3} s (target 2 s: {})",
        final_mesh.triangles.len(),
        if final_s <= 2.0 { "met" } else { "NOT met" }
    );
    println!("  final mesh stages: {}", stages.join(", "));
    println!(
        "  the same mesh by `extract` finding every frame's crests itself: {from_scratch_s:.3} s before, \
         {from_scratch_after_s:.3} s after; \
         the crests of {} frames were found during the sweep (slowest batch {worst_crests_s:.3} s)",
        crests.frames()
    );
    println!(
        "  final mesh with the last update still running: {:.3} s if it finishes (it ran on {:.3} s \
         into the final), {:.3} s if it is abandoned (the client's way; it ended {:.3} s into the final)",
        beside_finished_s.0, beside_finished_s.1, beside_abandoned_s.0, beside_abandoned_s.1
    );
}
