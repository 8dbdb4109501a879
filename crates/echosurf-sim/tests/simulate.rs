//! The simulator's physics and files: speckle statistics, angle dependence of boundary echoes,
//! shadowing, read-back through the project's readers, closed truth surfaces, determinism.

use echosurf::io::{PixelData, read_calibration, read_mesh, read_sequence};
use echosurf::progress::NoProgress;
use echosurf_sim::phantom::{Sdf, SolidPhantom};
use echosurf_sim::{
    Acoustics, FrameFormer, ImageGrid, Phantom, PhantomKind, SimulationOptions, simulate,
    simulate_sweeps, write_simulation,
};
use glam::{DMat4, DVec3};

const W: usize = 256;
const H: usize = 200;
const PITCH: f64 = 0.2;

/// Image -> object for a probe whose face centre is at `face`, beam along `beam`, array along `lateral`.
fn probe_at(face: DVec3, lateral: DVec3, beam: DVec3) -> DMat4 {
    let ex = lateral.normalize() * PITCH;
    let ey = beam.normalize() * PITCH;
    let origin = face - ex * (0.5 * (W as f64 - 1.0));
    DMat4::from_cols(
        ex.extend(0.0),
        ey.extend(0.0),
        (ex.cross(ey).normalize() * PITCH).extend(0.0),
        origin.extend(1.0),
    )
}

fn former(phantom: &dyn Phantom) -> FrameFormer<'_> {
    FrameFormer {
        phantom,
        acoustics: Acoustics::default(),
        grid: ImageGrid {
            width: W,
            height: H,
        },
        scatter_salt: 12345,
    }
}

/// Half-space phantom: material where (p - point) . normal < 0.
#[derive(Debug)]
struct HalfSpace {
    point: DVec3,
    normal: DVec3,
}

impl Phantom for HalfSpace {
    fn distance_and_gradient(&self, p: DVec3) -> (f64, DVec3) {
        ((p - self.point).dot(self.normal), self.normal)
    }
    fn bounds(&self) -> (DVec3, DVec3) {
        (DVec3::splat(-1e3), DVec3::splat(1e3))
    }
    fn surfaces(&self) -> Vec<(String, &echosurf_sim::phantom::SurfaceFn)> {
        Vec::new()
    }
}

fn mean(values: impl Iterator<Item = f64>) -> f64 {
    let (s, n) = values.fold((0.0, 0usize), |(s, n), v| (s + v, n + 1));
    s / n as f64
}

#[test]
fn homogeneous_speckle_envelope_is_rayleigh() {
    // Water only: a sphere far away from the image.
    let phantom = SolidPhantom::new(
        "far",
        Sdf::Sphere {
            center: DVec3::new(0.0, 0.0, -500.0),
            radius: 1.0,
        },
    );
    let m = probe_at(DVec3::new(0.0, 0.0, 50.0), DVec3::X, -DVec3::Z);
    let frame = former(&phantom).form(&m, 7, true);
    let env = frame.envelope.unwrap();
    // Skip the margins (edge rows see fewer scatterers in the axial kernel).
    let values: Vec<f64> = (10..H - 10)
        .flat_map(|v| (10..W - 10).map(move |u| (v, u)))
        .map(|(v, u)| env[v * W + u] as f64)
        .collect();
    let mu = mean(values.iter().copied());
    let sd = (mean(values.iter().map(|x| (x - mu).powi(2)))).sqrt();
    let snr = mu / sd;
    // Rayleigh: sqrt(pi / (4 - pi)) = 1.913. ~40k correlated pixels, ~3k speckle cells: the estimate's
    // sampling error is ~1-2 %, so the required 10 % is a test of the model, not of luck.
    let rayleigh = (std::f64::consts::PI / (4.0 - std::f64::consts::PI)).sqrt();
    assert!(
        (snr / rayleigh - 1.0).abs() < 0.10,
        "SNR {snr} vs {rayleigh}"
    );
    // Background level near the paper's 15.
    let grey = mean(frame.grey.iter().map(|&g| g as f64));
    assert!((10.0..=22.0).contains(&grey), "water grey {grey}");
}

#[test]
fn horizontal_wall_echoes_and_vertical_wall_does_not() {
    // Horizontal: tissue below z = 0, probe face 20 mm above, beam down: the wall is at row 100.
    let horizontal = HalfSpace {
        point: DVec3::ZERO,
        normal: DVec3::Z,
    };
    let m = probe_at(DVec3::new(0.0, 0.0, 20.0), DVec3::X, -DVec3::Z);
    let frame = former(&horizontal).form(&m, 1, false);
    let row_mean = |v: usize| mean((0..W).map(|u| frame.grey[v * W + u] as f64));
    let wall = (98..=102).map(row_mean).fold(0.0, f64::max);
    let above = mean((20..80).map(row_mean));
    assert!(wall > 100.0, "horizontal wall {wall}");
    assert!(wall > above + 80.0, "wall {wall} vs water {above}");

    // Vertical: tissue at x < 0, the beam runs parallel to the wall, which crosses column 127/128.
    let vertical = HalfSpace {
        point: DVec3::ZERO,
        normal: DVec3::X,
    };
    let m = probe_at(DVec3::new(0.1, 0.0, 20.0), DVec3::X, -DVec3::Z);
    let frame = former(&vertical).form(&m, 1, false);
    let column_mean = |u: usize| mean((0..H).map(|v| frame.grey[v * W + u] as f64));
    let at_wall = (125..=130).map(column_mean).fold(0.0, f64::max);
    let tissue = mean((20..100).map(column_mean));
    let water = mean((156..236).map(column_mean));
    // No echo: the wall columns are no brighter than the brighter medium beside them (+3 grey levels
    // for the blur of the two speckle textures).
    assert!(
        at_wall < tissue.max(water) + 3.0,
        "vertical wall {at_wall}, tissue {tissue}, water {water}"
    );
}

#[test]
fn strong_reflector_shadows_what_lies_below() {
    // A 6 mm sphere 12 mm below the face with a strongly reflecting surface.
    let phantom = SolidPhantom::new(
        "ball",
        Sdf::Sphere {
            center: DVec3::new(0.0, 0.0, 0.0),
            radius: 6.0,
        },
    );
    let mut f = former(&phantom);
    f.acoustics.interface_loss = 0.8;
    let m = probe_at(DVec3::new(0.0, 0.0, 12.0), DVec3::X, -DVec3::Z);
    let frame = f.form(&m, 3, false);
    // Rows 25-38 mm deep (below the ball: it ends at 18 mm); columns within 3 mm of the axis vs beyond 12.
    let rows = 125..190;
    let below = mean(
        rows.clone()
            .flat_map(|v| (113..143).map(move |u| (v, u)))
            .map(|(v, u)| frame.grey[v * W + u] as f64),
    );
    let beside = mean(
        rows.flat_map(|v| (0..60).chain(196..W).map(move |u| (v, u)))
            .map(|(v, u)| frame.grey[v * W + u] as f64),
    );
    assert!(below + 5.0 < beside, "shadow {below} vs beside {beside}");

    // The default (rubber-like) material shadows too, less.
    let frame = former(&phantom).form(&m, 3, false);
    let below_default = mean(
        (125..190)
            .flat_map(|v| (113..143).map(move |u| (v, u)))
            .map(|(v, u)| frame.grey[v * W + u] as f64),
    );
    assert!(
        below_default < beside && below_default > below,
        "{below_default}"
    );
}

fn small_options(phantom: PhantomKind) -> SimulationOptions {
    SimulationOptions {
        phantom,
        frames_per_sweep: 6,
        sweeps: Some(2),
        width_px: 96,
        height_px: 80,
        pixel_size_mm: 0.4,
        truth_resolution_mm: 1.0,
        ..Default::default()
    }
}

#[test]
fn files_read_back_with_the_project_readers() {
    let options = small_options(PhantomKind::Duck);
    let sim = simulate(&options, &NoProgress).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let files = write_simulation(dir.path(), "duck", &sim, &options).unwrap();
    let seq = read_sequence(&files.sequence).unwrap();
    assert_eq!((seq.width, seq.height, seq.frames.len()), (96, 80, 12));
    assert_eq!(seq.pixels, sim.sequence.pixels);
    for (a, b) in seq.frames.iter().zip(&sim.sequence.frames) {
        let (ma, mb) = (
            a.transforms["ProbeToTracker"],
            b.transforms["ProbeToTracker"],
        );
        assert!(ma.valid);
        assert!(ma.matrix.abs_diff_eq(mb.matrix, 1e-9));
        assert_eq!(a.timestamp_s, b.timestamp_s);
    }
    let cal = read_calibration(&files.calibration).unwrap();
    assert!(
        cal.image_to_probe
            .abs_diff_eq(sim.calibration_written.image_to_probe, 1e-9)
    );
    // The written calibration differs from the true one by the calibration error.
    assert!(
        !cal.image_to_probe
            .abs_diff_eq(sim.calibration_true.image_to_probe, 1e-3)
    );
    assert_eq!(files.truth.len(), 3);
    let truth = read_mesh(&files.truth[0]).unwrap();
    assert_eq!(
        truth.triangles.len(),
        sim.truth
            .iter()
            .map(|(_, m)| m.triangles.len())
            .sum::<usize>()
    );
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(&files.description).unwrap()).unwrap();
    assert_eq!(json["seed"], 1);
    assert!(json["suggested_iso"].as_f64().unwrap() > 20.0);
}

#[test]
fn truth_surfaces_are_closed_manifolds_on_the_phantom() {
    for kind in [PhantomKind::Duck, PhantomKind::Torus, PhantomKind::Hand] {
        let phantom = echosurf_sim::build_phantom(&kind).unwrap();
        let resolution = if kind == PhantomKind::Hand { 1.5 } else { 0.8 };
        let truth =
            echosurf_sim::output::truth_meshes(phantom.as_ref(), resolution, &NoProgress).unwrap();
        assert_eq!(truth.len(), if kind == PhantomKind::Duck { 2 } else { 1 });
        for (name, mesh) in &truth {
            let topology = mesh.topology();
            assert!(
                topology.is_closed_manifold(),
                "{kind:?} {name}: {topology:?}"
            );
            assert_eq!(topology.components, 1, "{kind:?} {name}");
            // Vertices lie on the zero level (the surfacer projects them with Newton steps).
            for v in mesh.vertices.iter().step_by(97) {
                assert!(phantom.distance(*v).abs() < 0.05, "{kind:?} {name}: {v}");
            }
        }
        if kind == PhantomKind::Torus {
            assert_eq!(truth[0].1.topology().euler_characteristic, 0);
        }
    }
}

#[test]
fn same_seed_same_bytes_whatever_the_thread_count() {
    let options = small_options(PhantomKind::Sphere);
    let run = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| simulate_sweeps(&options, &NoProgress).unwrap())
    };
    let (a, b) = (run(1), run(3));
    assert_eq!(a.sequence, b.sequence);
    assert_eq!(a.background_level, b.background_level);
    let other = simulate_sweeps(
        &SimulationOptions {
            seed: 2,
            ..options.clone()
        },
        &NoProgress,
    )
    .unwrap();
    assert_ne!(a.sequence.pixels, other.sequence.pixels);
    let PixelData::U8(p) = &a.sequence.pixels else {
        panic!("8-bit frames expected")
    };
    assert!(p.iter().any(|&g| g > 100), "no echo anywhere");
}

#[test]
fn duck_sweep_has_the_papers_levels() {
    let options = SimulationOptions {
        frames_per_sweep: 12,
        ..Default::default()
    };
    let sim = simulate_sweeps(&options, &NoProgress).unwrap();
    assert_eq!(sim.sweeps.len(), 3);
    // Paper: background ~15, boundary ~130, iso 50.
    assert!(
        (10.0..=22.0).contains(&sim.background_level),
        "{}",
        sim.background_level
    );
    assert!(
        (110.0..=150.0).contains(&sim.boundary_level),
        "{}",
        sim.boundary_level
    );
    assert!(
        (40.0..=60.0).contains(&sim.suggested_iso),
        "{}",
        sim.suggested_iso
    );
}

#[test]
fn bad_options_are_rejected_with_a_message() {
    let mut options = SimulationOptions {
        width_px: 0,
        ..Default::default()
    };
    let err = simulate(&options, &NoProgress).unwrap_err().to_string();
    assert!(err.contains("image size"), "{err}");
    options.width_px = 256;
    options.pixel_size_mm = f64::NAN;
    assert!(simulate(&options, &NoProgress).is_err());
    options.pixel_size_mm = 0.2;
    options.phantom = PhantomKind::Mesh("/nonexistent/shape.stl".into());
    let err = simulate(&options, &NoProgress).unwrap_err().to_string();
    assert!(err.contains("/nonexistent/shape.stl"), "{err}");
}

#[test]
fn mesh_phantom_from_file_uses_its_own_mesh_as_truth() {
    // Write the surfacer's sphere of the analytic phantom, then simulate it as a mesh phantom.
    let sphere = echosurf_sim::build_phantom(&PhantomKind::Sphere).unwrap();
    let truth = echosurf_sim::output::truth_meshes(sphere.as_ref(), 1.0, &NoProgress).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("ball.ply");
    echosurf::io::write_mesh(&path, &truth[0].1).unwrap();
    let kind = PhantomKind::Mesh(path);
    let mesh_phantom = echosurf_sim::build_phantom(&kind).unwrap();
    for p in [DVec3::new(0.0, 0.0, 20.0), DVec3::new(3.0, -2.0, 1.0)] {
        // The 1 mm lattice mesh is within ~0.05 mm of the true sphere (chords of a 15 mm radius).
        assert!((mesh_phantom.distance(p) - sphere.distance(p)).abs() < 0.1);
    }
    let sim = simulate(&small_options(kind), &NoProgress).unwrap();
    assert_eq!(sim.truth.len(), 1);
    assert_eq!(sim.truth[0].1.triangles.len(), truth[0].1.triangles.len());
}

#[test]
fn object_motion_moves_the_echoes_but_not_the_recorded_poses() {
    let still = small_options(PhantomKind::Sphere);
    let moving = SimulationOptions {
        motion: echosurf_sim::HandMotion {
            object_motion_mm: 2.0,
            ..still.motion
        },
        ..still.clone()
    };
    let (a, b) = (
        simulate_sweeps(&still, &NoProgress).unwrap(),
        simulate_sweeps(&moving, &NoProgress).unwrap(),
    );
    // The tracker cannot see the object move: identical recorded poses, different images.
    for (fa, fb) in a.sequence.frames.iter().zip(&b.sequence.frames) {
        assert_eq!(fa.transforms, fb.transforms);
    }
    assert_ne!(a.sequence.pixels, b.sequence.pixels);
    // The truth-frame poses differ by the motion (at most 2 mm sway + 2 mm drift).
    let last = a.true_image_to_world.len() - 1;
    let shift = (a.true_image_to_world[last].w_axis - b.true_image_to_world[last].w_axis)
        .truncate()
        .length();
    assert!(shift > 0.01 && shift <= 4.0 + 1e-9, "{shift}");
}
