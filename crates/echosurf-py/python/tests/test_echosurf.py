"""The Python package against the `echosurf` CLI and against independent readers: the same input and
options give the same mesh bytes, the same model file and the same values; bad input raises
EchosurfError naming the file."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
import textwrap
import threading
import time
import zlib
from pathlib import Path

import numpy as np
import pytest

import echosurf


# --- independent readers of what the CLI writes ------------------------------------------------


def read_obj(path: Path) -> "tuple[np.ndarray, np.ndarray, np.ndarray]":
    """Vertices, normals (float64, as written: the CLI prints each f64's shortest round-trip
    decimal) and 0-based int32 faces of an OBJ file."""
    vertices, normals, faces = [], [], []
    for line in path.read_text().splitlines():
        words = line.split()
        if not words:
            continue
        if words[0] == "v":
            vertices.append([float(w) for w in words[1:4]])
        elif words[0] == "vn":
            normals.append([float(w) for w in words[1:4]])
        elif words[0] == "f":
            faces.append([int(w.split("/")[0]) - 1 for w in words[1:4]])
    return (
        np.array(vertices, dtype=np.float64).reshape(-1, 3),
        np.array(normals, dtype=np.float64).reshape(-1, 3),
        np.array(faces, dtype=np.int32).reshape(-1, 3),
    )


PLY_TYPES = {"float": "<f4", "double": "<f8", "uchar": "u1", "int": "<i4", "uint": "<u4"}


def read_binary_ply_vertices(path: Path) -> np.ndarray:
    """The vertex element of a binary little-endian PLY as a structured array."""
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii").splitlines()
    assert "format binary_little_endian 1.0" in header, header
    fields, count, in_vertex = [], 0, False
    for line in header:
        words = line.split()
        if words[:2] == ["element", "vertex"]:
            count, in_vertex = int(words[2]), True
        elif words[:1] == ["element"]:
            in_vertex = False
        elif words[:1] == ["property"] and in_vertex:
            fields.append((words[2], PLY_TYPES[words[1]]))
    return np.frombuffer(data, dtype=np.dtype(fields), count=count, offset=end)


def write_ascii_ply(path: Path, points: np.ndarray, intensity: np.ndarray) -> None:
    """A point cloud with double x y z and a float `intensity`, as `echosurf fit` reads it."""
    lines = [
        "ply", "format ascii 1.0", f"element vertex {len(points)}",
        "property double x", "property double y", "property double z",
        "property float intensity", "end_header",
    ]
    lines += [" ".join(repr(float(x)) for x in (*p, v)) for p, v in zip(points, intensity)]
    path.write_text("\n".join(lines) + "\n")


def read_metaimage(path: Path) -> "tuple[dict, np.ndarray]":
    """Header fields and the (zlib-compressed or raw) uint8 pixels of a LOCAL MetaImage."""
    data = path.read_bytes()
    marker = b"ElementDataFile = LOCAL\n"
    start = data.index(marker) + len(marker)
    header = {}
    for line in data[: start - 1].decode("ascii").splitlines():
        key, _, value = line.partition(" = ")
        header[key] = value
    assert header["ElementType"] == "MET_UCHAR"
    payload = data[start:]
    if header.get("CompressedData") == "True":
        payload = zlib.decompress(payload)
    return header, np.frombuffer(payload, dtype=np.uint8)


# --- read_sequence -----------------------------------------------------------------------------


def test_read_sequence_gives_the_files_frames_poses_and_statuses(sphere):
    sequence_path, _ = sphere
    sequence = echosurf.read_sequence(sequence_path)
    header, pixels = read_metaimage(sequence_path)
    width, height, frames = (int(w) for w in header["DimSize"].split())
    assert header["UltrasoundImageOrientation"] == "MF"  # held as read, no flip to undo
    assert sequence.frames.dtype == np.uint8
    assert sequence.frames.shape == (frames, height, width)
    assert np.array_equal(sequence.frames, pixels.reshape(frames, height, width))
    assert (sequence.width, sequence.height, sequence.channels) == (width, height, 1)
    assert sequence.element_type == "MET_UCHAR"
    assert list(sequence.transforms) == ["ProbeToTracker"]
    matrices = sequence.transforms["ProbeToTracker"]
    assert matrices.shape == (frames, 4, 4) and matrices.dtype == np.float64
    for k in (0, frames - 1):
        numbers = [float(w) for w in header[f"Seq_Frame{k:04d}_ProbeToTrackerTransform"].split()]
        assert np.array_equal(matrices[k], np.array(numbers).reshape(4, 4))
        ok = header[f"Seq_Frame{k:04d}_ProbeToTrackerTransformStatus"] == "OK"
        assert sequence.transform_valid["ProbeToTracker"][k] == ok
        assert sequence.image_valid[k] == (header[f"Seq_Frame{k:04d}_ImageStatus"] == "OK")
        assert sequence.timestamps_s[k] == float(header[f"Seq_Frame{k:04d}_Timestamp"])
    assert sequence.transform_valid["ProbeToTracker"].dtype == np.bool_
    assert sequence.image_valid.shape == (frames,)


# --- extract -----------------------------------------------------------------------------------


def test_extract_of_the_demo_sweep_equals_the_cli_mesh_byte_for_byte(duck, cli, tmp_path):
    sequence_path, calibration_path = duck
    cli_obj = tmp_path / "cli.obj"
    report_path = tmp_path / "cli.json"
    cli("extract", sequence_path, "--calibration", calibration_path, "--out", cli_obj,
        "--report", report_path)
    surfaces, report = echosurf.extract_surfaces(sequence_path, calibration_path)
    assert len(surfaces) == 1
    surface = surfaces[0]
    vertices, normals, faces = read_obj(cli_obj)
    assert surface.vertices.dtype == np.float64 and surface.vertices.shape[1] == 3
    assert surface.faces.dtype == np.int32 and surface.faces.shape[1] == 3
    assert len(surface.faces) > 1000, "the duck's surface has thousands of triangles"
    assert surface.vertices.tobytes() == vertices.tobytes()
    assert surface.normals.tobytes() == normals.tobytes()
    assert surface.faces.tobytes() == faces.tobytes()
    # What the run did is what the CLI's report says, all but the clocks and the memory.
    cli_report = json.loads(report_path.read_text())
    assert set(report) == set(cli_report)
    for key in ("method", "parameters", "levels", "counts", "sheets", "voxel", "warnings",
                "coordinates"):
        assert report[key] == cli_report[key], key
    assert report["coordinates"] == {"frame": report["parameters"]["world_frame"], "space": "RAS"}
    assert report["counts"]["triangles"] == [len(surface.faces)]


def test_extract_options_match_the_cli_flags(sphere, cli, tmp_path):
    sequence_path, calibration_path = sphere
    out = tmp_path / "cli.obj"
    cli("extract", sequence_path, "--calibration", calibration_path, "--out", out,
        "--smoothing", 3, "--resolution", 0.8, "--sheet", "iso", "--seed", 5, "--space", "lps")
    vertices, faces, report = echosurf.extract(
        sequence_path, calibration_path, smoothing_mm=3, resolution_mm=0.8, sheet="iso",
        seed=np.int64(5), space="lps",
    )
    cli_vertices, _, cli_faces = read_obj(out)
    assert vertices.tobytes() == cli_vertices.tobytes()
    assert faces.tobytes() == cli_faces.tobytes()
    assert report["parameters"]["smoothing_mm"] == 3
    assert report["coordinates"]["space"] == "LPS"
    # LPS is RAS with x and y negated, and nothing else.
    ras, ras_faces, _ = echosurf.extract(
        sequence_path, calibration_path, smoothing_mm=3, resolution_mm=0.8, sheet="iso", seed=5
    )
    assert np.array_equal(vertices, ras * np.array([-1.0, -1.0, 1.0]))
    assert np.array_equal(faces, ras_faces)


def test_several_levels_need_extract_surfaces(sphere):
    sequence_path, calibration_path = sphere
    surfaces, report = echosurf.extract_surfaces(
        sequence_path, calibration_path, iso=[60, 90], sheet="iso", resolution_mm=1.0
    )
    assert [s.level for s in surfaces] == [60.0, 90.0]
    assert report["counts"]["triangles"] == [len(s.faces) for s in surfaces]
    with pytest.raises(ValueError, match="2 levels: use extract_surfaces"):
        echosurf.extract(sequence_path, calibration_path, iso=(60, 90), resolution_mm=1.0)


def test_options_and_config_file_are_read_as_the_cli_reads_them(cli, tmp_path):
    printed = cli("extract", "--print-config", "--smoothing", 3, "--sheet", "ridge").stdout
    toml_text = echosurf.options_toml(smoothing_mm=3.0, sheet="ridge")
    assert printed.split("\n[outputs]\n")[0].rstrip() == toml_text.rstrip()
    config = tmp_path / "options.toml"
    config.write_text(printed)
    assert echosurf.options_toml(config=config) == toml_text
    # Keywords override the file, as flags override --config.
    assert "smoothing_mm = 4.0" in echosurf.options_toml(config=config, smoothing_mm=4.0)


def test_bad_options_name_the_keyword():
    with pytest.raises(TypeError, match="unexpected keyword argument 'smoothing'"):
        echosurf.options_toml(smoothing=2.0)
    with pytest.raises(ValueError, match=r"^smoothing_mm "):
        echosurf.options_toml(smoothing_mm=-1.0)
    with pytest.raises(ValueError, match=r"^sheet: "):
        echosurf.options_toml(sheet="flat")
    with pytest.raises(ValueError, match=r"^max_samples: "):
        echosurf.options_toml(max_samples="many")
    with pytest.raises(ValueError, match=r"^iso: .* not a finite number"):
        echosurf.options_toml(iso=float("nan"))
    with pytest.raises(ValueError, match="space `ijk`"):
        echosurf.extract("a.mha", "b.xml", space="ijk")


def test_a_bad_config_file_is_an_error_naming_it(tmp_path):
    config = tmp_path / "bad.toml"
    config.write_text("[user]\nsmothing_mm = 2\n")
    with pytest.raises(echosurf.EchosurfError, match=re.escape(str(config))) as raised:
        echosurf.options_toml(config=config)
    assert "smothing_mm" in str(raised.value)
    config.write_text('[outputs]\nmodel = "m.esrbf"\n')
    with pytest.raises(echosurf.EchosurfError, match="outputs.model: the Python extract writes"):
        echosurf.options_toml(config=config)


def test_bad_files_raise_echosurf_error_naming_the_file(sphere, tmp_path):
    _, calibration_path = sphere
    broken = tmp_path / "broken.mha"
    broken.write_bytes(b"ObjectType = Image\nNDims = 3\nDimSize = 64 64 10\n"
                       b"ElementType = MET_UCHAR\nElementDataFile = LOCAL\n" + bytes(100))
    for call in (
        lambda: echosurf.read_sequence(broken),
        lambda: echosurf.extract(broken, calibration_path),
    ):
        with pytest.raises(echosurf.EchosurfError, match=re.escape(str(broken))):
            call()
    missing = tmp_path / "missing.mha"
    with pytest.raises(echosurf.EchosurfError, match=re.escape(str(missing))):
        echosurf.read_sequence(missing)
    with pytest.raises(echosurf.EchosurfError, match=re.escape(str(tmp_path / "nothing.xml"))):
        echosurf.extract(sphere[0], tmp_path / "nothing.xml")
    assert issubclass(echosurf.EchosurfError, Exception)


# --- fit / evaluate ----------------------------------------------------------------------------


def field_samples(n: int, seed: int = 7) -> "tuple[np.ndarray, np.ndarray]":
    """Jittered points in a 20 mm box with a linear field plus a bump; float32 values (what a PLY
    `float intensity` holds)."""
    rng = np.random.default_rng(seed)
    points = rng.uniform(0.0, 20.0, size=(n, 3))
    values = 20 + 3 * points[:, 0] - points[:, 2] + 40 * np.exp(
        -((points - 10.0) ** 2).sum(axis=1) / 20.0
    )
    return points, values.astype(np.float32)


def test_fit_and_evaluate_equal_the_cli(cli, tmp_path):
    points, values = field_samples(600)
    cloud = tmp_path / "points.ply"
    write_ascii_ply(cloud, points, values)
    cli_model = tmp_path / "cli.esrbf"
    fitted = cli("fit", cloud, "--out", cli_model, "--smoothing", 0.5, "--accuracy", 0.05,
                 "--json")
    model = echosurf.fit(points, values, smoothing=0.5, accuracy=0.05)
    own_model = tmp_path / "python.esrbf"
    model.save(own_model)
    assert own_model.read_bytes() == cli_model.read_bytes()
    report, cli_report = json.loads(model.report_json), json.loads(fitted.stdout)
    for key in ("input_points", "merged_points", "centres", "solver", "iterations",
                "max_residual", "rms_residual", "max_data_misfit", "rms_data_misfit"):
        assert report[key] == cli_report[key], key
    # Values and gradients at other points equal what `echosurf eval` writes (in float32).
    query, _ = field_samples(50, seed=11)
    write_ascii_ply(tmp_path / "query.ply", query, np.zeros(len(query), np.float32))
    cli("eval", cli_model, tmp_path / "query.ply", "--out", tmp_path / "values.ply")
    evaluated = read_binary_ply_vertices(tmp_path / "values.ply")
    value, gradient = model.evaluate(query)
    assert value.shape == (50,) and gradient.shape == (50, 3)
    assert np.array_equal(value.astype(np.float32), evaluated["value"])
    for axis, name in enumerate(("gx", "gy", "gz")):
        assert np.array_equal(gradient[:, axis].astype(np.float32), evaluated[name])
    # The CLI's model file loads and evaluates to the same numbers.
    loaded_value, loaded_gradient = echosurf.Model.load(str(cli_model)).evaluate(query.tolist())
    assert np.array_equal(loaded_value, value) and np.array_equal(loaded_gradient, gradient)


def test_fit_reproduces_an_analytic_field():
    # w = 0 interpolates; a linear field is in the spline's null space, so it is reproduced
    # everywhere, with its constant gradient.
    rng = np.random.default_rng(3)
    points = rng.uniform(-5, 5, size=(300, 3))
    slope = np.array([2.0, -1.0, 0.5])
    model = echosurf.fit(points, 7.0 + points @ slope, smoothing=0.0, accuracy=1e-6)
    query = rng.uniform(-4, 4, size=(40, 3))
    value, gradient = model.evaluate(query)
    np.testing.assert_allclose(value, 7.0 + query @ slope, atol=1e-6)
    np.testing.assert_allclose(gradient, np.broadcast_to(slope, gradient.shape), atol=1e-6)


def test_fit_refuses_bad_arrays_and_options():
    points, values = field_samples(20)
    with pytest.raises(ValueError, match=r"shape \(N, 3\)"):
        echosurf.fit(points[:, :2], values)
    with pytest.raises(ValueError, match="19 values for 20 points"):
        echosurf.fit(points, values[:19])
    with pytest.raises(ValueError, match="solver `lu`"):
        echosurf.fit(points, values, solver="lu")
    with pytest.raises(echosurf.EchosurfError):
        echosurf.fit(points, values, accuracy=-1.0)
    with pytest.raises(echosurf.EchosurfError, match=re.escape("nothing.esrbf")):
        echosurf.Model.load("nothing.esrbf")


# --- progress, interruption, the GIL -----------------------------------------------------------


def test_progress_is_reported_per_stage_and_an_exception_in_it_stops_the_work(sphere):
    calls = []
    echosurf.extract(*sphere, resolution_mm=1.0, progress=lambda s, f: calls.append((s, f)))
    stages = {stage for stage, _ in calls}
    assert "segment" in stages, stages
    assert all(0.0 <= f <= 1.0 for _, f in calls)
    assert any(f == 1.0 for _, f in calls)
    for stage in stages:
        fractions = [f for s, f in calls if s == stage]
        assert fractions == sorted(fractions) or fractions.count(0.0) > 1, (stage, fractions)

    class Stop(Exception):
        pass

    def stop(stage, fraction):
        if stage == "segment" and fraction > 0.0:
            raise Stop(stage)

    with pytest.raises(Stop, match="segment"):
        echosurf.extract(*sphere, resolution_mm=1.0, progress=stop)
    # The package works on after an interrupted run.
    points, values = field_samples(100)
    assert echosurf.fit(points, values).centres == 100


def fit_span_and_ticks(n: int) -> "tuple[float, int]":
    """Fits n samples on a worker thread while this one ticks every millisecond; returns the fit's
    duration and how many ticks fell inside it (past its first tenth)."""
    points, values = field_samples(n)
    span = {}

    def work():
        span["start"] = time.monotonic()
        echosurf.fit(points, values, smoothing=0.5, solver="pu")
        span["end"] = time.monotonic()

    worker = threading.Thread(target=work)
    ticks = []
    worker.start()
    while worker.is_alive():
        ticks.append(time.monotonic())
        time.sleep(0.001)
    worker.join()
    duration = span["end"] - span["start"]
    inside = [t for t in ticks if span["start"] + 0.1 * duration < t < span["end"]]
    return duration, len(inside)


def test_the_gil_is_released_while_fitting():
    # The check needs a fit long enough for ticks to land inside it: on a fast, quiet machine 6,000
    # samples took 0.044 s, so the sample count grows until the fit lasts 0.1 s.
    for n in (6000, 24000, 96000):
        duration, inside = fit_span_and_ticks(n)
        if duration > 0.1:
            break
    # Holding the GIL for the whole fit would leave this thread no tick inside it.
    assert duration > 0.05 and inside >= 10, (n, duration, inside)


def test_ctrl_c_stops_a_run_with_keyboard_interrupt(duck):
    # A child process extracts the duck (tens of seconds) and gets SIGINT once segmentation has
    # started: it must end in KeyboardInterrupt long before the run could have finished. The child
    # installs Python's own handler: a process started in the background by a non-interactive shell
    # inherits SIGINT ignored, and Python then leaves it ignored (the run would finish unstopped).
    script = textwrap.dedent(
        """
        import signal, sys, echosurf
        signal.signal(signal.SIGINT, signal.default_int_handler)
        def progress(stage, fraction):
            print(stage, flush=True)
        try:
            echosurf.extract(sys.argv[1], sys.argv[2], progress=progress)
        except KeyboardInterrupt:
            print("interrupted", flush=True)
            sys.exit(3)
        print("finished", flush=True)
        """
    )
    child = subprocess.Popen(
        [sys.executable, "-c", script, str(duck[0]), str(duck[1])],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    assert child.stdout is not None
    for line in child.stdout:
        if line.strip() == "segment":
            break
    child.send_signal(signal.SIGINT)
    rest, errors = child.communicate(timeout=120)
    assert child.returncode == 3, (child.returncode, rest[-500:], errors[-2000:])
    assert "interrupted" in rest and "finished" not in rest
