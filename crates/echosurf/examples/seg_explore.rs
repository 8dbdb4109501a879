//! Scratch: segmentation on simulated sweeps, per-frame coverage. Not committed.
use echosurf::io::{FramePose, PoseResolution};
use echosurf::progress::NoProgress;
use echosurf::segment::{BandMasks, InitialBand, SegmentOptions, segment_sequence};
use echosurf::simulate::{PhantomKind, Simulation, SimulationOptions, build_phantom, simulate_sweeps};
use glam::DVec3;

fn simulated(kind: PhantomKind, frames: usize, sweeps: usize) -> Simulation {
    let options = SimulationOptions {
        phantom: kind,
        frames_per_sweep: frames,
        sweeps: Some(sweeps),
        width_px: 200,
        height_px: 160,
        pixel_size_mm: 0.2,
        ..Default::default()
    }
    .without_errors();
    simulate_sweeps(&options, &NoProgress).unwrap()
}

fn true_poses(sim: &Simulation, kind: &PhantomKind) -> PoseResolution {
    let phantom = build_phantom(kind).unwrap();
    let (w, h) = (sim.sequence.width, sim.sequence.height);
    PoseResolution {
        poses: sim.true_image_to_world.iter().enumerate()
            .filter(|(_, m)| {
                let hit = (0..w).filter(|&u| (0..h).any(|v| phantom.distance_and_gradient(m.transform_point3(DVec3::new(u as f64, v as f64, 0.0))).0 < 0.0)).count();
                4 * hit >= w
            })
            .map(|(frame_index, &image_to_world)| FramePose { frame_index, image_to_world })
            .collect(),
        skipped: Vec::new(),
        world_frame: "Reference".into(),
    }
}

fn coverage(sim: &Simulation, kind: &PhantomKind, masks: &BandMasks, poses: &PoseResolution, min_cos: f64, verbose: bool) -> (f64, f64) {
    let phantom = build_phantom(kind).unwrap();
    let (w, h) = (sim.sequence.width, sim.sequence.height);
    let (mut near, mut near_kept, mut kept) = (0usize, 0usize, 0usize);
    let mut hist_miss = [0usize; 10];
    let mut hist_all = [0usize; 10];
    let segmented: Vec<usize> = poses.poses.iter().map(|p| p.frame_index).collect();
    for &f in &segmented {
        let m = &sim.true_image_to_world[f];
        let mask = &masks.masks[f];
        let fk = mask.iter().filter(|&&x| x != 0).count();
        kept += fk;
        let (mut fn_, mut fnk) = (0, 0);
        let beam = m.y_axis.truncate().normalize();
        for u in 0..w {
            let world = |v: usize| m.transform_point3(DVec3::new(u as f64, v as f64, 0.0));
            let Some(first_inside) = (0..h).find(|&v| phantom.distance_and_gradient(world(v)).0 < 0.0) else { continue };
            for v in 0..h.min(first_inside + 10) {
                let (d, g) = phantom.distance_and_gradient(world(v));
                let c = g.normalize().dot(beam).abs();
                if d.abs() <= 1.0 && c >= min_cos {
                    let ang = c.acos().to_degrees();
                    let b = ((ang / 10.0) as usize).min(9);
                    hist_all[b] += 1;
                    fn_ += 1;
                    if mask[v * w + u] != 0 { fnk += 1 } else { hist_miss[b] += 1 }
                }
            }
        }
        near += fn_;
        near_kept += fnk;
        if verbose {
            eprintln!("frame {f:3}: near kept {fnk}/{fn_}  kept {:.1}%", 100.0 * fk as f64 / (w * h) as f64);
        }
    }
    let all = w * h * segmented.len();
    if verbose {
        eprintln!("angle hist (10deg bins) all  {:?}", hist_all);
        eprintln!("angle hist (10deg bins) miss {:?}", hist_miss);
    }
    (near_kept as f64 / near as f64, kept as f64 / all as f64)
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let kind = match args.get(1).map(|s| s.as_str()) { Some("duck") => PhantomKind::Duck, _ => PhantomKind::Sphere };
    let frames: usize = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(12);
    let sweeps: usize = args.get(3).and_then(|s| s.parse().ok()).unwrap_or(1);
    let init = args.get(4).map(|s| s.as_str()).unwrap_or("auto");
    let sim = simulated(kind.clone(), frames, sweeps);
    let poses = true_poses(&sim, &kind);
    let mut options = SegmentOptions::default();
    if let Ok(j) = std::env::var("SEGOPT") {
        // merge JSON over defaults
        let mut v = serde_json::to_value(&options).unwrap();
        let patch: serde_json::Value = serde_json::from_str(&j).unwrap();
        for (k, x) in patch.as_object().unwrap() { v[k] = x.clone(); }
        options = serde_json::from_value(v).unwrap();
    }
    let init_band = match init {
        "poly" => polygon_init(&sim, &kind, &poses),
        _ => InitialBand::Auto,
    };
    if std::env::var("STATS").is_ok() { stats(&sim, &kind, &poses); }
    let t = std::time::Instant::now();
    let masks = segment_sequence(&sim.sequence, &poses, None, &init_band, &options, &NoProgress).unwrap();
    let dt = t.elapsed();
    for wmsg in &masks.warnings { eprintln!("warn: {wmsg}"); }
    let verbose = std::env::var("V").is_ok();
    let (a, b) = coverage(&sim, &kind, &masks, &poses, 0.5, verbose);
    let (a70, _) = coverage(&sim, &kind, &masks, &poses, 0.7071, false);
    println!("{} segmented, {} warnings, near kept {:.2}% (45deg: {:.2}%), all kept {:.2}%  [{:?}]", masks.masks.iter().filter(|m| m.contains(&255)).count(), masks.warnings.len(), 100.0 * a, 100.0*a70, 100.0 * b, dt);
    if let Ok(path) = std::env::var("RAW") {
        let mut empty = masks.clone();
        for m in &mut empty.masks { m.fill(0); }
        let fr: Vec<usize> = std::env::var("RAWF").unwrap().split(',').map(|x| x.parse().unwrap()).collect();
        echosurf::segment::write_band_preview(std::path::Path::new(&path), &sim.sequence, &empty, &fr).unwrap();
    }
    if let Ok(fs) = std::env::var("BIG") {
        for f in fs.split(',').map(|x| x.parse::<usize>().unwrap()) {
            big(&sim, &kind, &masks, f, &format!("/tmp/big{f}.png"));
        }
    }
    if let Ok(path) = std::env::var("PREVIEW") {
        let frames: Vec<usize> = (0..masks.masks.len()).filter(|&i| masks.masks[i].contains(&255)).collect();
        echosurf::segment::write_band_preview(std::path::Path::new(&path), &sim.sequence, &masks, &frames).unwrap();
    }
}

/// Polygon: the true visible surface of the first posed frame, thickened by +/- 3 mm, as a user would draw it.
fn polygon_init(sim: &Simulation, kind: &PhantomKind, poses: &PoseResolution) -> InitialBand {
    let phantom = build_phantom(kind).unwrap();
    let (w, h) = (sim.sequence.width, sim.sequence.height);
    let m = poses.poses[0].image_to_world;
    let mut top = Vec::new();
    let mut bottom = Vec::new();
    for u in (0..w).step_by(10).chain(std::iter::once(w - 1)) {
        if let Some(v) = (0..h).find(|&v| phantom.distance_and_gradient(m.transform_point3(DVec3::new(u as f64, v as f64, 0.0))).0 < 0.0) {
            top.push([u as f64, v as f64 - 15.0]);
            bottom.push([u as f64, v as f64 + 15.0]);
        }
    }
    bottom.reverse();
    top.extend(bottom);
    InitialBand::Polygon(top)
}

fn big(sim: &Simulation, kind: &PhantomKind, masks: &BandMasks, f: usize, path: &str) {
    let phantom = build_phantom(kind).unwrap();
    let (w, h) = (sim.sequence.width, sim.sequence.height);
    let s = 3;
    let m = sim.true_image_to_world[f];
    let mut rgb = vec![0u8; w * s * h * s * 3];
    for v in 0..h { for u in 0..w {
        let g = sim.sequence.pixel_f32(f, u, v) as u8;
        let kept = masks.masks[f][v * w + u] != 0;
        let d = phantom.distance_and_gradient(m.transform_point3(DVec3::new(u as f64, v as f64, 0.0))).0;
        let mut px = [g, g, g];
        if kept { px = [g / 2, (g / 2).saturating_add(60), g / 2]; }
        if d.abs() < 0.1 { px = [255, 0, 255]; }
        for dy in 0..s { for dx in 0..s {
            let o = ((v * s + dy) * w * s + u * s + dx) * 3;
            if dx == 0 && dy == 0 || d.abs() >= 0.1 { rgb[o..o + 3].copy_from_slice(&px); } else { rgb[o..o+3].copy_from_slice(&[g,g,g]); }
        }}
    }}
    let file = std::fs::File::create(path).unwrap();
    let mut enc = png::Encoder::new(std::io::BufWriter::new(file), (w * s) as u32, (h * s) as u32);
    enc.set_color(png::ColorType::Rgb);
    enc.set_depth(png::BitDepth::Eight);
    enc.write_header().unwrap().write_image_data(&rgb).unwrap();
}

/// Mean grey by angle bin for: water 1-3 mm above the first boundary, the boundary (|d| < 0.3 mm), interior 1-3 mm below.
fn stats(sim: &Simulation, kind: &PhantomKind, poses: &PoseResolution) {
    let phantom = build_phantom(kind).unwrap();
    let (w, h) = (sim.sequence.width, sim.sequence.height);
    let mut acc = vec![[0f64; 6]; 10];
    for p in &poses.poses {
        let f = p.frame_index;
        let m = sim.true_image_to_world[f];
        let beam = m.y_axis.truncate().normalize();
        for u in 0..w {
            let world = |v: usize| m.transform_point3(DVec3::new(u as f64, v as f64, 0.0));
            let Some(first) = (0..h).find(|&v| phantom.distance_and_gradient(world(v)).0 < 0.0) else { continue };
            let (_, g) = phantom.distance_and_gradient(world(first));
            let c = g.normalize().dot(beam).abs();
            let b = ((c.acos().to_degrees() / 10.0) as usize).min(9);
            for v in first.saturating_sub(20)..h.min(first + 20) {
                let (d, _) = phantom.distance_and_gradient(world(v));
                let gr = sim.sequence.pixel_f32(f, u, v) as f64;
                let k = if d.abs() < 0.3 { 2 } else if (1.0..3.0).contains(&d) { 0 } else if (-3.0..-1.0).contains(&d) { 4 } else { continue };
                acc[b][k] += gr; acc[b][k + 1] += 1.0;
            }
        }
    }
    let mut rows = vec![[0f64; 4]; h / 10];
    for p in &poses.poses {
        let f = p.frame_index;
        let m = sim.true_image_to_world[f];
        for v in 0..h / 10 * 10 { for u in 0..w {
            let (d, _) = phantom.distance_and_gradient(m.transform_point3(DVec3::new(u as f64, v as f64, 0.0)));
            let g = sim.sequence.pixel_f32(f, u, v) as f64;
            if d > 2.0 { rows[v / 10][0] += g; rows[v / 10][1] += 1.0; }
            if d < -2.0 { rows[v / 10][2] += g; rows[v / 10][3] += 1.0; }
        }}
    }
    for (r, a) in rows.iter().enumerate() { eprintln!("rows {:3}..: water {:5.1} (n {}) inside {:5.1} (n {})", r * 10, a[0] / a[1], a[1], a[2] / a[3], a[3]); }
    for (b, a) in acc.iter().enumerate() {
        if a[3] > 0.0 { eprintln!("{:2}-{:2} deg: water {:5.1}  boundary {:5.1}  interior {:5.1}  (n={})", b*10, b*10+10, a[0]/a[1], a[2]/a[3], a[4]/a[5], a[3]); }
    }
}
