//! `echosurf live` end to end over loopback: against pyigtl (an independent OpenIGTLink peer) streaming
//! the demo's simulated duck, and against fake servers written here that send broken messages.

mod common;

use std::io::{BufRead, BufReader, Write};
use std::net::TcpListener;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::Duration;

use echosurf::io::sequence::mat4_to_row_major;
use echosurf::io::{ReferenceChoice, read_calibration, read_sequence, resolve_poses};
use echosurf_live::codec::{Image, encode_message};
use glam::{DMat4, DVec3};

/// A Python that imports pyigtl and numpy: `ECHOSURF_PYTHON`, else `python3`; `None` (the test then
/// skips) without one.
fn python_with_pyigtl() -> Option<String> {
    let python = std::env::var("ECHOSURF_PYTHON").unwrap_or_else(|_| "python3".into());
    let ok = Command::new(&python)
        .args(["-c", "import pyigtl, numpy"])
        .output()
        .is_ok_and(|o| o.status.success());
    if !ok {
        eprintln!(
            "skipping: `import pyigtl, numpy` fails in {python} (set ECHOSURF_PYTHON to a Python with \
             pyigtl: pip install pyigtl)"
        );
    }
    ok.then_some(python)
}

fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

fn compare_mean_mm(mesh: &Path, truth: &Path) -> f64 {
    let out = common::echosurf_ok(&[
        "compare".as_ref(),
        mesh.as_os_str(),
        truth.as_os_str(),
        "--json".as_ref(),
    ]);
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    v["accuracy"]["mean_mm"].as_f64().unwrap()
}

#[test]
fn live_records_the_duck_streamed_by_pyigtl_and_sends_surfaces_back() {
    let Some(python) = python_with_pyigtl() else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let sim = dir.path().join("sim");
    // The demo's sweep: the duck with the simulator's defaults, seed 1.
    common::echosurf_ok(&[
        "simulate".as_ref(),
        "--phantom".as_ref(),
        "duck".as_ref(),
        "--seed".as_ref(),
        "1".as_ref(),
        "--out".as_ref(),
        sim.as_os_str(),
    ]);
    let (mha, config) = (sim.join("sim.mha"), sim.join("sim_config.xml"));
    let sequence = read_sequence(&mha).unwrap();
    let calibration = read_calibration(&config).unwrap();
    let poses = resolve_poses(&sequence, Some(&calibration), ReferenceChoice::Auto, &mha).unwrap();
    assert_eq!(poses.poses.len(), sequence.frames.len());
    let echosurf::io::PixelData::U8(pixels) = &sequence.pixels else {
        panic!("the simulator writes 8-bit frames")
    };
    let frames: Vec<serde_json::Value> = poses
        .poses
        .iter()
        .map(|p| {
            let t = sequence.frames[p.frame_index].timestamp_s.unwrap();
            serde_json::json!({
                "timestamp_s": 1_000_000.0 + t,
                "ijk_to_world": mat4_to_row_major(&p.image_to_world).to_vec(),
            })
        })
        .collect();
    let spec = serde_json::json!({
        "width": sequence.width, "height": sequence.height, "fps": 30.0, "frames": frames,
    });
    let (bin, json, result, done) = (
        dir.path().join("frames.bin"),
        dir.path().join("frames.json"),
        dir.path().join("result.json"),
        dir.path().join("done"),
    );
    std::fs::write(&bin, pixels).unwrap();
    std::fs::write(&json, spec.to_string()).unwrap();
    let port = free_port();
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/live/pyigtl_server.py");
    let mut server = Command::new(&python)
        .arg(&script)
        .arg(port.to_string())
        .args([&bin, &json, &result, &done])
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    let mut ready = String::new();
    BufReader::new(server.stdout.take().unwrap())
        .read_line(&mut ready)
        .unwrap();
    assert_eq!(ready.trim(), "READY");

    let out = dir.path().join("live");
    let n = sequence.frames.len().to_string();
    let run = common::echosurf(&[
        "live".as_ref(),
        "--connect".as_ref(),
        format!("127.0.0.1:{port}").as_ref(),
        "--calibration".as_ref(),
        config.as_os_str(),
        "--out".as_ref(),
        out.as_os_str(),
        "--frames".as_ref(),
        n.as_ref(),
    ]);
    // The peer waits for the final surface (its triangle count) before it reports.
    let final_triangles = echosurf::io::read_mesh(&out.join("live_surface.ply"))
        .map(|m| m.triangles.len())
        .unwrap_or(0);
    std::fs::write(&done, final_triangles.to_string()).unwrap();
    let status = server.wait().unwrap();
    let stdout = String::from_utf8_lossy(&run.stdout);
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(run.status.success(), "{stdout}\n{stderr}");
    assert!(status.success(), "the pyigtl server failed");
    eprintln!("{stdout}");

    // Every frame recorded, pixels byte-identical, poses as pyigtl decodes the bytes it sent.
    let recorded = read_sequence(&out.join("live.igs.mha")).unwrap();
    assert_eq!(recorded.frames.len(), sequence.frames.len());
    assert_eq!(recorded.pixels, sequence.pixels);
    let peer: serde_json::Value = serde_json::from_slice(&std::fs::read(&result).unwrap()).unwrap();
    let sent = peer["sent"].as_array().unwrap();
    assert_eq!(sent.len(), recorded.frames.len());
    for (k, (frame, sent)) in recorded.frames.iter().zip(sent).enumerate() {
        let pose = frame.transforms["ImageToReference"];
        assert!(pose.valid);
        let got = mat4_to_row_major(&pose.matrix);
        for (a, b) in got.iter().zip(sent["ijk_to_world"].as_array().unwrap()) {
            assert!(
                (a - b.as_f64().unwrap()).abs() < 1e-9,
                "frame {k}: {got:?} vs {sent}"
            );
        }
        let t = sent["timestamp_s"].as_f64().unwrap();
        assert!((frame.timestamp_s.unwrap() - t).abs() < 1e-6, "frame {k}");
        // The float32 wire keeps the placement within 1e-3 mm of the simulator's f64 pose.
        let centre = |m: &DMat4| m.transform_point3(DVec3::new(128.0, 100.0, 0.0));
        assert!(centre(&pose.matrix).distance(centre(&poses.poses[k].image_to_world)) < 1e-3);
    }
    assert!(
        peer["stream_s"].as_f64().unwrap() >= (sent.len() - 1) as f64 / 30.0,
        "the server did not pace the frames"
    );

    // POLYDATA updates came back and parse (pyigtl's side checks every index); the last one is the
    // final mesh.
    let polydata = peer["polydata"].as_array().unwrap();
    assert!(polydata.len() >= 2, "{peer}");
    assert!(
        polydata
            .iter()
            .all(|p| p["device"] == "EchosurfSurface" && p["triangles"] == true)
    );
    let final_mesh = echosurf::io::read_mesh(&out.join("live_surface.ply")).unwrap();
    assert_eq!(
        polydata.last().unwrap()["polygons"].as_u64().unwrap() as usize,
        final_mesh.triangles.len()
    );

    // The final mesh scores like `extract` on the same sweep.
    let extracted = dir.path().join("extract.ply");
    common::echosurf_ok(&[
        "extract".as_ref(),
        mha.as_os_str(),
        "--calibration".as_ref(),
        config.as_os_str(),
        "--out".as_ref(),
        extracted.as_os_str(),
    ]);
    let truth = sim.join("truth.ply");
    let (live_mean, extract_mean) = (
        compare_mean_mm(&out.join("live_surface.ply"), &truth),
        compare_mean_mm(&extracted, &truth),
    );
    eprintln!("mean distance to the truth: live {live_mean:.4} mm, extract {extract_mean:.4} mm");
    assert!(
        (live_mean - extract_mean).abs() <= 0.05,
        "{live_mean} vs {extract_mean}"
    );
}

/// An 8-bit frame of 32 x 24 px at 0.5 mm, `k` mm along z.
fn frame_bytes(k: usize, version: u16, metadata: &[(String, String)]) -> Vec<u8> {
    let pose = DMat4::from_scale_rotation_translation(
        DVec3::new(0.5, 0.5, 1.0),
        glam::DQuat::IDENTITY,
        DVec3::new(0.0, 0.0, k as f64),
    );
    let pixels = (0..32 * 24)
        .map(|i| ((i * 3 + k * 17) % 251) as u8)
        .collect();
    let image = Image::from_u8_frame(32, 24, pixels, &pose);
    encode_message(
        version,
        "IMAGE",
        "Image_Reference",
        10.0 + k as f64 / 30.0,
        &image.encode(),
        metadata,
        0,
    )
}

/// A fake server on loopback: each accepted connection gets its list of byte chunks, then is closed.
fn fake_server(connections: Vec<Vec<Vec<u8>>>) -> (u16, std::thread::JoinHandle<()>) {
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let port = listener.local_addr().unwrap().port();
    let handle = std::thread::spawn(move || {
        for chunks in connections {
            let (mut stream, _) = listener.accept().unwrap();
            for chunk in chunks {
                if stream.write_all(&chunk).is_err() {
                    break;
                }
                std::thread::sleep(Duration::from_millis(5));
            }
            let _ = stream.flush();
            std::thread::sleep(Duration::from_millis(50));
        }
    });
    (port, handle)
}

#[test]
fn live_survives_malformed_messages_and_disconnects_without_losing_frames() {
    let dir = tempfile::tempdir().unwrap();
    let (_, config) = common::simulate_small_sphere(dir.path(), "1", &[]);
    let invalid = vec![(
        "ImageToReferenceTransformStatus".to_string(),
        "INVALID".to_string(),
    )];
    let mut bad_crc = frame_bytes(90, 1, &[]);
    *bad_crc.last_mut().unwrap() ^= 0xFF;
    let mut lying_size = frame_bytes(91, 1, &[]);
    lying_size[42..50].copy_from_slice(&(1u64 << 40).to_be_bytes());
    let mut bad_header = frame_bytes(92, 1, &[]);
    bad_header[2..14].copy_from_slice(b"\x01\x02garb\xff\xfe\0\0\0\0");
    let cut = frame_bytes(93, 2, &[]);
    let (port, server) = fake_server(vec![
        // A frame, then a header that is not a header: the client reconnects.
        vec![frame_bytes(0, 1, &[]), bad_header[..58].to_vec()],
        // A bad CRC (dropped, the stream goes on), a frame, then a body size that lies: reconnect.
        vec![bad_crc, frame_bytes(1, 2, &[]), lying_size[..58].to_vec()],
        // A frame whose transform is INVALID, a frame, then the server drops mid-message: reconnect.
        vec![
            frame_bytes(2, 2, &invalid),
            frame_bytes(3, 3, &[]),
            cut[..cut.len() / 2].to_vec(),
        ],
        // The last frames, then a clean close.
        vec![frame_bytes(4, 1, &[]), frame_bytes(5, 1, &[])],
    ]);
    let out = dir.path().join("live");
    let run = common::echosurf(&[
        "live".as_ref(),
        "--connect".as_ref(),
        format!("127.0.0.1:{port}").as_ref(),
        "--calibration".as_ref(),
        config.as_os_str(),
        "--out".as_ref(),
        out.as_os_str(),
        "--update-every".as_ref(),
        "0".as_ref(),
        "--max-message-mb".as_ref(),
        "1".as_ref(),
    ]);
    server.join().unwrap();
    let stdout = String::from_utf8_lossy(&run.stdout);
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(run.status.success(), "{stdout}\n{stderr}");
    for expected in [
        "malformed header",
        "CRC-64",
        "over the limit",
        "bytes into a",
        "INVALID: recorded, not used",
        "reconnecting",
    ] {
        assert!(
            stderr.contains(expected),
            "no warning with {expected:?}:\n{stderr}"
        );
    }
    assert!(stdout.contains("4 connection(s)"), "{stdout}");
    let recorded = read_sequence(&out.join("live.igs.mha")).unwrap();
    assert_eq!(recorded.frames.len(), 6, "{stderr}");
    let valid: Vec<bool> = recorded
        .frames
        .iter()
        .map(|f| f.transforms["ImageToReference"].valid)
        .collect();
    assert_eq!(valid, [true, true, false, true, true, true]);
    for (k, frame) in recorded.frames.iter().enumerate() {
        let z = frame.transforms["ImageToReference"].matrix.w_axis.z;
        assert_eq!(z, k as f64, "frame {k} is not the k-th good frame sent");
    }
}

#[test]
fn live_writes_nothing_and_says_so_when_no_server_answers() {
    let dir = tempfile::tempdir().unwrap();
    let (_, config) = common::simulate_small_sphere(dir.path(), "1", &[]);
    let port = free_port();
    let out = dir.path().join("live");
    let run = common::echosurf(&[
        "live".as_ref(),
        "--connect".as_ref(),
        format!("127.0.0.1:{port}").as_ref(),
        "--calibration".as_ref(),
        config.as_os_str(),
        "--out".as_ref(),
        out.as_os_str(),
        "--reconnect-attempts".as_ref(),
        "2".as_ref(),
    ]);
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(!run.status.success());
    assert!(stderr.contains("no frames were received"), "{stderr}");
    assert!(!out.join("live.igs.mha").exists());
}

/// Reads messages from `stream` until it closes; returns the type names received.
fn collect_types(mut stream: std::net::TcpStream) -> Vec<String> {
    let limits = echosurf_live::codec::Limits {
        max_body_bytes: 1 << 30,
    };
    let mut types = Vec::new();
    while let Ok(raw) = echosurf_live::codec::read_message(&mut stream, &limits) {
        if raw.header.type_name == "POLYDATA" {
            let split = echosurf_live::codec::split_body(&raw.header, &raw.body).unwrap();
            let poly = echosurf_live::codec::decode_polydata(split.content).unwrap();
            assert!(
                !poly.0.is_empty() && !poly.1.is_empty(),
                "an empty POLYDATA was sent"
            );
        }
        types.push(raw.header.type_name);
    }
    types
}

#[test]
fn live_serves_a_sender_that_connects_twice_and_updates_by_time() {
    let dir = tempfile::tempdir().unwrap();
    let (mha, config) = common::simulate_small_sphere(dir.path(), "1", &[]);
    let sequence = read_sequence(&mha).unwrap();
    let calibration = read_calibration(&config).unwrap();
    let poses = resolve_poses(&sequence, Some(&calibration), ReferenceChoice::Auto, &mha).unwrap();
    let echosurf::io::PixelData::U8(pixels) = &sequence.pixels else {
        panic!("the simulator writes 8-bit frames")
    };
    let frame_len = sequence.width * sequence.height;
    let messages: Vec<Vec<u8>> = poses
        .poses
        .iter()
        .map(|p| {
            let k = p.frame_index;
            let image = Image::from_u8_frame(
                sequence.width as u16,
                sequence.height as u16,
                pixels[k * frame_len..(k + 1) * frame_len].to_vec(),
                &p.image_to_world,
            );
            let t = sequence.frames[k].timestamp_s.unwrap();
            encode_message(
                2,
                "IMAGE",
                "Image_Reference",
                100.0 + t,
                &image.encode(),
                &[],
                0,
            )
        })
        .collect();
    let n = messages.len();
    let out = dir.path().join("live");
    let mut child = Command::new(env!("CARGO_BIN_EXE_echosurf"))
        .args(["live", "--serve", "127.0.0.1:0", "--calibration"])
        .arg(&config)
        .arg("--out")
        .arg(&out)
        .args(["--frames", &n.to_string(), "--update-every", "0"])
        .args(["--update-seconds", "0.2", "--update-samples", "3000"])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut stderr = BufReader::new(child.stderr.take().unwrap());
    let mut line = String::new();
    let address = loop {
        line.clear();
        assert!(
            stderr.read_line(&mut line).unwrap() > 0,
            "live exited before listening"
        );
        if let Some(a) = line.trim().strip_prefix("listening on ") {
            break a.to_string();
        }
    };
    // First connection: a third of the frames, then half a message and a drop.
    let mut first = std::net::TcpStream::connect(&address).unwrap();
    let third = n / 3;
    for m in &messages[..third] {
        first.write_all(m).unwrap();
        std::thread::sleep(Duration::from_millis(30));
    }
    first.write_all(&messages[third][..100]).unwrap();
    drop(first);
    std::thread::sleep(Duration::from_millis(100));
    // Second connection: the rest, slowly enough for updates by time; it reads what comes back.
    let mut second = std::net::TcpStream::connect(&address).unwrap();
    let reader = {
        let stream = second.try_clone().unwrap();
        std::thread::spawn(move || collect_types(stream))
    };
    for m in &messages[third..] {
        second.write_all(m).unwrap();
        std::thread::sleep(Duration::from_millis(30));
    }
    let received = reader.join().unwrap();
    let output = child.wait_with_output().unwrap();
    let mut rest = String::new();
    std::io::Read::read_to_string(&mut stderr, &mut rest).unwrap();
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(output.status.success(), "{stdout}\n{rest}");
    assert!(stdout.contains("2 connection(s)"), "{stdout}");
    assert!(stdout.contains("update at"), "no update by time:\n{stdout}");
    let polydata = received.iter().filter(|t| *t == "POLYDATA").count();
    assert!(polydata >= 2, "updates and the final surface: {received:?}");
    let recorded = read_sequence(&out.join("live.igs.mha")).unwrap();
    assert_eq!(recorded.frames.len(), n, "{rest}");
    assert_eq!(
        recorded.pixels, sequence.pixels,
        "recorded pixels differ from those sent"
    );
    for (got, p) in recorded.frames.iter().zip(&poses.poses) {
        let m = got.transforms["ImageToReference"].matrix;
        assert!(
            (m.w_axis - p.image_to_world.w_axis).abs().max_element() < 1e-3,
            "frame {} is not the frame sent",
            p.frame_index
        );
    }
    assert!(out.join("live_surface.ply").exists());
}
