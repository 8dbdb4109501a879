//! Latency of the live surface on the demo's sweep (the simulated duck, seed 1, 180 frames): the frames
//! go through the codec (encode, read, decode) into a session as they would arrive; after every
//! `--update-every` (30) frames the update surface is timed, and after the last frame the final mesh
//! (`extract`'s defaults). Run: `cargo bench -p echosurf-live --bench live_latency`
//! (env `LIVE_UPDATE_SAMPLES` sets the update's sample budget, default 10000, and
//! `LIVE_UPDATE_RESOLUTION_MM` its surfacer lattice, default 1).
//! The targets it reports against (issue #30): an update within 1 s after each 30 new frames, the final
//! mesh within 2 s of the last frame.

use std::time::Instant;

use echosurf::io::{ReferenceChoice, resolve_poses};
use echosurf::pipeline::ExtractOptions;
use echosurf::progress::NoProgress;
use echosurf_live::codec::{self, Image, Limits, encode_message};
use echosurf_live::session::{
    IncrementalBands, LiveSession, SessionOptions, surface_of, update_extract_options,
    update_surface,
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
            let snapshot = session.snapshot_for_update();
            let start = Instant::now();
            let mesh = update_surface(&mut bands, &snapshot, calibration, &update_options)
                .expect("update");
            let s = start.elapsed().as_secs_f64();
            worst_update_s = worst_update_s.max(s);
            println!(
                "  update at {:>3} frames: {:>6} triangles in {s:.3} s",
                snapshot.frames.len(),
                mesh.triangles.len()
            );
        }
    }
    let start = Instant::now();
    let final_mesh =
        surface_of(session.sequence(), calibration, &ExtractOptions::default()).expect("final");
    let final_s = start.elapsed().as_secs_f64();
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
}
