//! End-to-end tests of `echosurf render`.

use std::process::Command;

use echosurf::metrics::shapes::torus;

#[test]
fn render_writes_a_deterministic_png_of_the_requested_size() {
    let dir = tempfile::tempdir().unwrap();
    let mesh = dir.path().join("torus.ply");
    echosurf::io::write_mesh(&mesh, &torus(20.0, 6.0, 64, 32)).unwrap();
    let render = |out: &std::path::Path| {
        Command::new(env!("CARGO_BIN_EXE_echosurf"))
            .args(["render", mesh.to_str().unwrap(), "--size", "240", "--out"])
            .arg(out)
            .output()
            .unwrap()
    };
    let (a, b) = (dir.path().join("a.png"), dir.path().join("b.png"));
    for path in [&a, &b] {
        let out = render(path);
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
    let bytes = std::fs::read(&a).unwrap();
    assert_eq!(bytes, std::fs::read(&b).unwrap());
    // PNG signature, then the IHDR chunk with big-endian width and height.
    assert_eq!(&bytes[..8], b"\x89PNG\r\n\x1a\n");
    assert_eq!(&bytes[12..16], b"IHDR");
    let dimension = |at: usize| u32::from_be_bytes(bytes[at..at + 4].try_into().unwrap());
    assert_eq!((dimension(16), dimension(20)), (240, 240));

    // A missing mesh: an error naming it, and no picture.
    let out = Command::new(env!("CARGO_BIN_EXE_echosurf"))
        .args(["render", "no-such-mesh.stl", "--out"])
        .arg(dir.path().join("c.png"))
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("no-such-mesh.stl"));
    assert!(!dir.path().join("c.png").exists());
}
