//! `echosurf fit` keeps its accuracy contract through the binary: a dense solve that cannot fit in memory
//! and an accuracy out of reach are refused cleanly (exit 1, the figure and what to change, no model).

mod common;

use common::echosurf;
use echosurf::io::{PointCloud, write_point_cloud};
use glam::DVec3;

fn cloud(n: usize) -> PointCloud {
    let positions: Vec<DVec3> = (0..n)
        .map(|i| {
            let (a, b, c) = (i % 100, (i / 100) % 100, i / 10_000);
            DVec3::new(
                a as f64 * 0.3,
                b as f64 * 0.3 + 0.01 * a as f64,
                c as f64 * 0.4,
            )
        })
        .collect();
    let intensity = positions
        .iter()
        .map(|p| (40.0 + 30.0 * (p.x * 0.7).sin() * (p.y * 0.5).cos() + p.z) as f32)
        .collect();
    PointCloud {
        positions,
        scalars: vec![("intensity".into(), intensity)],
    }
}

#[test]
fn direct_solve_of_200k_points_is_refused_before_allocating() {
    let dir = tempfile::tempdir().unwrap();
    let points = dir.path().join("points.ply");
    let model = dir.path().join("model.esrbf");
    write_point_cloud(&points, &cloud(200_000)).unwrap();
    let out = echosurf(&[
        "fit".as_ref(),
        points.as_os_str(),
        "--out".as_ref(),
        model.as_os_str(),
        "--solver".as_ref(),
        "direct".as_ref(),
    ]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    // The CLI's memory budget refuses first (about 640,000 MB: the dense matrix, 640,026 MB, plus
    // what the process holds, which varies by a few MB), naming the solver and the budget.
    let needed_mb: f64 = stderr
        .split("would need about ")
        .nth(1)
        .and_then(|rest| rest.split(' ').next())
        .and_then(|n| n.parse().ok())
        .unwrap_or(0.0);
    assert!(
        (640_026.0..640_100.0).contains(&needed_mb)
            && stderr.contains("--solver")
            && stderr.contains("--memory-budget"),
        "{stderr}"
    );
    assert!(!model.exists());
}

#[test]
fn an_unreachable_accuracy_is_refused_with_the_achieved_figure() {
    let dir = tempfile::tempdir().unwrap();
    let points = dir.path().join("points.ply");
    let model = dir.path().join("model.esrbf");
    write_point_cloud(&points, &cloud(3_000)).unwrap();
    let out = echosurf(&[
        "fit".as_ref(),
        points.as_os_str(),
        "--out".as_ref(),
        model.as_os_str(),
        "--solver".as_ref(),
        "pu".as_ref(),
        "--smoothing".as_ref(),
        "0".as_ref(),
        "--accuracy".as_ref(),
        "1e-14".as_ref(),
    ]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains("above the requested accuracy") && stderr.contains("grey levels"),
        "{stderr}"
    );
    assert!(!model.exists());
}
