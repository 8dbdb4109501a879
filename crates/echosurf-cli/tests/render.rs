//! End-to-end tests of `echosurf render`.

use std::path::Path;
use std::process::Output;

mod common;

use echosurf::metrics::shapes::torus;

use echosurf_testkit::png_pixels;
use echosurf_testkit::real_data;
use png_pixels::read_rgb_png;

/// `echosurf render MESH --out OUT EXTRA...`.
fn render_args<'a>(mesh: &'a Path, out: &'a Path, extra: &[&'a str]) -> Vec<&'a str> {
    let mut args = vec![
        "render",
        mesh.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ];
    args.extend_from_slice(extra);
    args
}

/// Runs `render` unchecked (for the refusals).
fn render(mesh: &Path, out: &Path, extra: &[&str]) -> Output {
    common::echosurf(&render_args(mesh, out, extra))
}

/// Runs `render`, which must succeed.
fn render_ok(mesh: &Path, out: &Path, extra: &[&str]) -> Output {
    common::echosurf_ok(&render_args(mesh, out, extra))
}

/// A pixel clearly red: red over twice its green and blue (the error maps' far end).
fn clearly_red(p: &[u8]) -> bool {
    p[0] > 60 && p[0] as u32 > 2 * p[1].max(p[2]) as u32
}

#[test]
fn render_writes_a_deterministic_png_of_the_requested_size() {
    let dir = tempfile::tempdir().unwrap();
    let mesh = dir.path().join("torus.ply");
    echosurf::io::write_mesh(&mesh, &torus(20.0, 6.0, 64, 32)).unwrap();
    let (a, b) = (dir.path().join("a.png"), dir.path().join("b.png"));
    for path in [&a, &b] {
        render_ok(&mesh, path, &["--size", "240"]);
    }
    let bytes = std::fs::read(&a).unwrap();
    assert_eq!(bytes, std::fs::read(&b).unwrap());
    // PNG signature, then the IHDR chunk with big-endian width and height.
    assert_eq!(&bytes[..8], b"\x89PNG\r\n\x1a\n");
    assert_eq!(&bytes[12..16], b"IHDR");
    let dimension = |at: usize| u32::from_be_bytes(bytes[at..at + 4].try_into().unwrap());
    assert_eq!((dimension(16), dimension(20)), (240, 240));

    // A missing mesh: an error naming it, and no picture.
    let out = render(
        Path::new("no-such-mesh.stl"),
        &dir.path().join("c.png"),
        &[],
    );
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("no-such-mesh.stl"));
    assert!(!dir.path().join("c.png").exists());
}

#[test]
fn distance_to_a_truth_colours_the_picture() {
    let dir = tempfile::tempdir().unwrap();
    let (mesh, truth) = (dir.path().join("mesh.ply"), dir.path().join("truth.ply"));
    echosurf::io::write_mesh(&mesh, &torus(20.0, 6.0, 64, 32)).unwrap();
    echosurf::io::write_mesh(&truth, &torus(20.0, 5.0, 64, 32)).unwrap();
    let sized = |extra: &[&'static str]| [&["--size", "200"][..], extra].concat();
    let (plain, near, far) = (
        dir.path().join("plain.png"),
        dir.path().join("near.png"),
        dir.path().join("far.png"),
    );
    render_ok(&mesh, &plain, &sized(&[]));
    // 1 mm apart: red on a 1 mm scale, green on a 2 mm one.
    for (scale, out) in [("1", &near), ("2", &far)] {
        let run = render_ok(
            &mesh,
            out,
            &[
                "--size",
                "200",
                "--distance-to",
                truth.to_str().unwrap(),
                "--scale-mm",
                scale,
            ],
        );
        let said = String::from_utf8_lossy(&run.stdout);
        assert!(said.contains("coloured by distance to"), "{said}");
        // 200 px wide: the views' 200 x 200, and the colour bar's strip of 24 px under them.
        assert!(said.contains("(200 x 224 px"), "{said}");
    }
    // Pixels clearly red, and pixels clearly green.
    let counts = |path: &std::path::Path| {
        let (width, _, mut buf) = read_rgb_png(path);
        // The views only: a coloured picture has its colour bar in a strip below them.
        buf.truncate(3 * (width * width) as usize);
        let (mut red, mut green) = (0, 0);
        for p in buf.chunks_exact(3) {
            let [r, g, b] = [p[0] as u32, p[1] as u32, p[2] as u32];
            red += usize::from(clearly_red(p));
            green += usize::from(g > 60 && g > r + 20 && g > b + 20);
        }
        (red, green)
    };
    let ((plain_red, plain_green), (near_red, near_green), (far_red, far_green)) =
        (counts(&plain), counts(&near), counts(&far));
    // Only the small axes in the tiles' corners are red or green on the plain picture.
    assert!(
        plain_red < 100 && plain_green < 100,
        "{plain_red} {plain_green}"
    );
    assert!(
        near_red > 2000 && near_green < near_red / 20,
        "{near_red} {near_green}"
    );
    assert!(
        far_green > 2000 && far_red < far_green / 20,
        "{far_red} {far_green}"
    );

    // --scale-mm means nothing without --distance-to.
    let out = render(
        &mesh,
        &dir.path().join("x.png"),
        &sized(&["--scale-mm", "2"]),
    );
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--distance-to"));
}

/// `--sequence` draws the frames' outlines (yellow) where the recording's poses put them.
#[test]
fn frame_outlines_of_a_recording_are_drawn_over_the_mesh() {
    use echosurf::io;
    let spine = real_data::real("SpinePhantomFreehand.igs.mha");
    let config = real_data::real("PlusDeviceSet_VolumeReconstructionOnly_SpinePhantom_NN_MEAN.xml");
    // A ball in the middle of the swept volume, in the world frame `extract` writes meshes in.
    let sequence = io::read_sequence(&spine).unwrap();
    let calibration = io::read_calibration(&config).unwrap();
    let poses = io::resolve_poses(
        &sequence,
        Some(&calibration),
        io::ReferenceChoice::Auto,
        &spine,
    )
    .unwrap();
    let (lo, hi) = io::world_bounds(&sequence, &poses.poses).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let mesh = dir.path().join("ball.ply");
    io::write_mesh(
        &mesh,
        &echosurf::metrics::shapes::icosphere((lo + hi) / 2.0, 5.0, 2),
    )
    .unwrap();
    let yellow_pixels = |extra: &[&str]| {
        let out_png = dir.path().join("view.png");
        render_ok(&mesh, &out_png, &[&["--size", "200"][..], extra].concat());
        read_rgb_png(&out_png)
            .2
            .chunks_exact(3)
            .filter(|p| p[0] > 150 && p[1] > 110 && p[2] < 90)
            .count()
    };
    let (spine_arg, config_arg) = (spine.to_str().unwrap(), config.to_str().unwrap());
    let without = yellow_pixels(&[]);
    let every_8th = yellow_pixels(&["--sequence", spine_arg, "--calibration", config_arg]);
    let every_frame = yellow_pixels(&[
        "--sequence",
        spine_arg,
        "--calibration",
        config_arg,
        "--outline-every",
        "1",
    ]);
    assert!(
        every_8th > without + 300 && every_frame > every_8th,
        "{without} / {every_8th} / {every_frame}"
    );

    // The sequence's options mean nothing without it; no frame at all is refused.
    for (extra, says) in [
        (vec!["--calibration", config_arg], "--sequence"),
        (vec!["--outline-every", "2"], "--sequence"),
        (
            vec!["--sequence", spine_arg, "--outline-every", "0"],
            "--outline-every",
        ),
    ] {
        let run = render(&mesh, &dir.path().join("bad.png"), &extra);
        assert!(!run.status.success(), "{extra:?}");
        let err = String::from_utf8_lossy(&run.stderr);
        assert!(err.contains(says), "{extra:?}: {err}");
    }
    assert!(!dir.path().join("bad.png").exists());
}

/// A PLY whose vertices carry colours (an error map from `compare --error-map`) is drawn in them;
/// `--plain` draws the mesh colour instead.
#[test]
fn a_coloured_ply_is_drawn_in_its_colours() {
    let dir = tempfile::tempdir().unwrap();
    let (mesh, truth, map) = (
        dir.path().join("mesh.ply"),
        dir.path().join("truth.ply"),
        dir.path().join("map.ply"),
    );
    echosurf::io::write_mesh(&mesh, &torus(20.0, 6.0, 64, 32)).unwrap();
    echosurf::io::write_mesh(&truth, &torus(20.0, 5.0, 64, 32)).unwrap();
    let run = |args: &[&std::ffi::OsStr]| {
        String::from_utf8_lossy(&common::echosurf_ok(args).stdout).into_owned()
    };
    // 1 mm apart everywhere: red on the default 1 mm scale.
    run(&[
        "compare".as_ref(),
        mesh.as_os_str(),
        truth.as_os_str(),
        "--error-map".as_ref(),
        map.as_os_str(),
    ]);
    let red_pixels = |extra: &[&str]| {
        let png_path = dir.path().join("view.png");
        let mut args: Vec<&std::ffi::OsStr> = vec![
            "render".as_ref(),
            map.as_os_str(),
            "--size".as_ref(),
            "200".as_ref(),
            "--out".as_ref(),
            png_path.as_os_str(),
        ];
        args.extend(extra.iter().map(|s| std::ffi::OsStr::new(*s)));
        let said = run(&args);
        let red = read_rgb_png(&png_path)
            .2
            .chunks_exact(3)
            .filter(|p| clearly_red(p))
            .count();
        (red, said)
    };
    let (coloured, said) = red_pixels(&[]);
    assert!(coloured > 2000, "{coloured}");
    assert!(
        said.contains("colours the file gives its vertices"),
        "{said}"
    );
    let (plain, said) = red_pixels(&["--plain"]);
    assert!(plain < 100, "only the axes: {plain}");
    assert!(!said.contains("colours the file gives"), "{said}");
}
