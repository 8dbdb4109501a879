use echosurf::simulate::*;
#[test]
#[ignore]
fn scratch_preview() {
    let opts = SimulationOptions::default();
    let t = std::time::Instant::now();
    let sim = simulate_sweeps(&opts, &echosurf::progress::NoProgress).unwrap();
    eprintln!("{} frames in {:?}; bg {} bd {} iso {}", sim.sequence.frames.len(), t.elapsed(), sim.background_level, sim.boundary_level, sim.suggested_iso);
    write_preview(std::path::Path::new("/tmp/sim_preview.png"), &sim, 12).unwrap();
}
