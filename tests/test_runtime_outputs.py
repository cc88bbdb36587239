"""What ``tactile-deploy run`` leaves behind: per-frame ``.npz`` arrays, mesh files that keep the
pad's vertex order (GLB y-up), frames.csv with source times and mesh files, lossless raw-frame
recordings, dropped meshes counted with their reason, ``--overwrite`` clearing the previous run,
progress lines for logs."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from test_runtime_support import build_test_plugin
from typer.testing import CliRunner

from tactile_deploy.cli.main import app
from tactile_deploy.runtime.frame_file import FrameFileError, load_frame_npz
from tactile_deploy.runtime.predictor import MeshPredictor
from tactile_deploy.runtime.sources.npz import load_clip

runner = CliRunner()


@pytest.fixture(scope="module")
def plugin(tmp_path_factory):
    return build_test_plugin(tmp_path_factory.mktemp("plugins") / "testsensor", n_frames=6)


@pytest.fixture(scope="module")
def predictor(plugin):
    return MeshPredictor.from_plugin(plugin)


def _image_folder(plugin, folder: Path, n: int | None = None) -> np.ndarray:
    frames, _, _ = load_clip(plugin.demo_clip_path())
    frames = frames[:n]
    folder.mkdir()
    for i, f in enumerate(frames):
        cv2.imwrite(str(folder / f"press_{i:03d}.png"), cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
    return frames


def test_format_npz_writes_one_file_per_frame_with_vertices_rest_and_depth(plugin, predictor,
                                                                            tmp_path):
    """The exact form ``run --sensor NAME --source DIR --format npz --out OUT``: one .npz per
    frame, holding the prediction of that frame (checked against a direct prediction)."""
    frames = _image_folder(plugin, tmp_path / "frames", n=4)
    out = tmp_path / "out"
    res = runner.invoke(app, ["run", "--sensor", str(plugin.folder), "--source",
                              str(tmp_path / "frames"), "--format", "npz", "--out", str(out),
                              "--no-forces"])
    assert res.exit_code == 0, res.output
    files = sorted(p.name for p in out.glob("*.npz"))
    assert files == [f"mesh_{i:06d}.npz" for i in range(4)]
    topo = predictor.topology
    for i in (0, 3):
        expected = predictor.predict_frame(frames[i])
        frame_file = load_frame_npz(out / f"mesh_{i:06d}.npz")   # the format's reader
        z, meta = frame_file.arrays, frame_file.metadata.model_dump()
        assert z["vertices"].dtype == np.float32 and z["vertices"].shape == (5380, 3)
        assert np.allclose(z["vertices"], expected.vertices_mm, atol=1e-5)
        assert np.array_equal(z["rest_vertices"], topo.rest_vertices_mm.astype(np.float32))
        assert z["depth"].shape == (128, 128)
        assert np.allclose(z["depth"], expected.depth_mm, atol=1e-6)
        assert meta["units"] == {"vertices": "mm", "rest_vertices": "mm", "depth": "mm"}
        assert meta["frame_index"] == i and meta["mesh_hash"] == topo.mesh_hash
        assert meta["source_label"] == f"press_{i:03d}.png"
        assert meta["total_normal_force_n"] is None            # --no-forces
    # the press is really in the depth map: the deepest frame is deeper than the no-contact noise
    with np.load(out / "mesh_000001.npz") as z:
        assert z["depth"].max() > 0.05
    # a file whose metadata or arrays break the format is refused, naming the file and field
    with np.load(out / "mesh_000000.npz") as z:
        arrays = {k: z[k] for k in z.files}
    doc = json.loads(str(arrays["metadata"]))
    bad = tmp_path / "bad.npz"
    for change, words in (({**doc, "frame_index": -1}, ("frame_index", "-1")),
                          ({**doc, "version": 2}, ("version", "2"))):
        np.savez(bad, **{**arrays, "metadata": np.array(json.dumps(change))})
        with pytest.raises(FrameFileError) as err:
            load_frame_npz(bad)
        assert str(bad) in str(err.value) and all(w in str(err.value) for w in words), err.value
    np.savez(bad, **{**arrays, "depth": arrays["depth"][:64]})
    with pytest.raises(FrameFileError, match=r"field 'depth': expected shape \(128, 128\)"):
        load_frame_npz(bad)


def test_frames_csv_traces_source_time_and_mesh_files_and_a_looped_recording_loses_no_mesh(
        plugin, tmp_path):
    """--loop over a 6-frame recording for 20 frames: every requested mesh is written (a
    recording waits for the disk), and frames.csv gives each frame's time in its recording and
    its mesh files."""
    import csv

    out = tmp_path / "out"
    res = runner.invoke(app, ["run", "--sensor", str(plugin.folder), "--loop", "--max-frames",
                              "20", "--every", "2", "--format", "ply,npz", "--out", str(out),
                              "--no-forces"])
    assert res.exit_code == 0, res.output
    assert "meshes written 10, skipped 0" in res.output
    with open(out / "frames.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 20
    t = [int(r["t_source_ns"]) for r in rows]
    assert t[:7] == [0, 33_333_333, 66_666_666, 99_999_999, 133_333_332, 166_666_665, 0]
    for r in rows:
        i = int(r["frame_index"])
        if i % 2 == 0:
            assert r["mesh_status"] == "written"
            assert r["mesh_files"] == f"mesh_{i:06d}.ply;mesh_{i:06d}.npz"
            assert all((out / name).is_file() for name in r["mesh_files"].split(";"))
        else:
            assert (r["mesh_status"], r["mesh_files"]) == ("not requested", "")


def test_meshes_dropped_for_a_live_camera_are_counted_warned_and_traced(plugin, predictor,
                                                                         tmp_path, monkeypatch,
                                                                         caplog):
    import csv
    import logging
    import time

    from test_runtime_support import FakeCapture

    from tactile_deploy.runtime import writers
    from tactile_deploy.runtime.run import Runner, RunOptions, prepare_out_dir
    from tactile_deploy.runtime.sources.camera import OpenCVCamera
    from tactile_deploy.runtime.sources.config import CameraSourceConfig

    real = writers.write_surface

    def slow_disk(*a, **k):
        time.sleep(0.05)
        real(*a, **k)

    monkeypatch.setattr(writers, "write_surface", slow_disk)
    frames, _, _ = load_clip(plugin.demo_clip_path())
    script = {"frames": [cv2.cvtColor(f, cv2.COLOR_RGB2BGR) for f in frames], "period_s": 0.002}
    cam = OpenCVCamera(CameraSourceConfig(device=0), capture_factory=lambda d: FakeCapture(script))
    out = prepare_out_dir(tmp_path / "out")
    with caplog.at_level(logging.WARNING):
        summary = Runner(predictor, cam, RunOptions(out_dir=out, formats=("ply",),
                                                    max_frames=40)).run()
    assert summary.meshes_skipped > 0
    assert summary.meshes_written + summary.meshes_skipped == 40
    assert set(summary.meshes_skipped_reasons) == {writers.REASON_QUEUE_FULL}
    assert "not written (1 so far): writer queue full" in caplog.text
    with open(out / "frames.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    dropped = [r for r in rows if r["mesh_status"].startswith("dropped: writer queue full")]
    written = [r for r in rows if r["mesh_status"] == "written"]
    assert len(dropped) == summary.meshes_skipped and len(written) == summary.meshes_written
    assert all((out / r["mesh_files"]).is_file() for r in written)
    assert all(r["t_source_ns"] == "" for r in rows)         # a live camera has no source time
    assert not any((out / f"mesh_{int(r['frame_index']):06d}.ply").exists() for r in dropped)


def test_mesh_files_keep_the_vertex_order_and_glb_is_y_up(plugin, predictor, tmp_path):
    """Every format read back by read_mesh gives the prediction, vertex for vertex; trimesh's
    default reader (which drops unused vertices) would not; the GLB, read by trimesh as glTF,
    has the pad's sensing surface facing +y and its backplate at y = -3 mm."""
    import trimesh

    from tactile_deploy.runtime.meshfiles import read_mesh

    frames = _image_folder(plugin, tmp_path / "frames", n=2)
    out = tmp_path / "out"
    res = runner.invoke(app, ["run", "--sensor", str(plugin.folder), "--source",
                              str(tmp_path / "frames"), "--format", "ply,obj,glb,vtu,npz",
                              "--out", str(out), "--no-forces"])
    assert res.exit_code == 0, res.output
    topo = predictor.topology
    expected = predictor.predict_frame(frames[1]).vertices_mm
    for ext in ("ply", "obj", "glb", "vtu", "npz"):
        m = read_mesh(out / f"mesh_000001.{ext}")
        assert m.vertices_mm.shape == (5380, 3), ext
        assert np.allclose(m.vertices_mm, expected, atol=1e-4), ext
        if m.faces is not None:
            assert np.array_equal(m.faces, topo.surface_faces), ext
    default = trimesh.load(out / "mesh_000001.ply")            # process=True: renumbered
    assert len(default.vertices) < 5380
    glb = trimesh.load(out / "mesh_000001.glb", force="mesh", process=False)
    assert np.allclose(glb.vertices[:, 0], 1e-3 * expected[:, 0], atol=1e-7)
    assert np.allclose(glb.vertices[:, 1], 1e-3 * expected[:, 2], atol=1e-7)   # sensor z is up
    assert np.allclose(glb.vertices[:, 2], -1e-3 * expected[:, 1], atol=1e-7)
    up = glb.face_normals[np.isin(topo.surface_faces, topo.sensing_nodes).all(1)]
    assert np.median(up[:, 1]) > 0.99, "the sensing surface must face +y (glTF's up)"


def test_progress_lines_give_frames_fps_and_eta_for_finite_sources(plugin, predictor):
    from tactile_deploy.runtime.run import Runner, RunOptions
    from tactile_deploy.runtime.sources.base import ArrayPlayback

    frames, t, _ = load_clip(plugin.demo_clip_path())
    lines = []
    Runner(predictor, ArrayPlayback(list(frames), t, "clip"), RunOptions(status_every_s=0.0),
           status=lines.append).run()
    assert len(lines) == 6
    assert "frame 1/6 (17 %" in lines[0] and "frame 6/6 (100 %" in lines[-1]
    assert "ETA 0 s" in lines[-1] and " fps" in lines[-1]
    looped = []
    Runner(predictor, ArrayPlayback(list(frames), t, "clip", loop=True),
           RunOptions(status_every_s=0.0, max_frames=8), status=looped.append).run()
    assert "frame 8/8 (100 %" in looped[-1]                      # --max-frames bounds a loop


def test_record_keeps_raw_frames_losslessly_and_replays_with_their_times(plugin, predictor,
                                                                          tmp_path):
    """--record on a live (fake) camera: the PNGs are the delivered frames bit for bit, with
    their capture times; replaying the folder gives the same meshes and the recorded pacing."""
    import csv

    from test_runtime_support import FakeCapture

    from tactile_deploy.runtime.record import RawFrameRecorder
    from tactile_deploy.runtime.run import Runner, RunOptions, prepare_out_dir
    from tactile_deploy.runtime.sources.camera import OpenCVCamera
    from tactile_deploy.runtime.sources.config import CameraSourceConfig

    frames, _, _ = load_clip(plugin.demo_clip_path())
    script = {"frames": [cv2.cvtColor(f, cv2.COLOR_RGB2BGR) for f in frames], "period_s": 0.01}
    cam = OpenCVCamera(CameraSourceConfig(device=0), capture_factory=lambda d: FakeCapture(script))
    out = prepare_out_dir(tmp_path / "out")
    summary = Runner(predictor, cam, RunOptions(out_dir=out, formats=("npz",), max_frames=8),
                     sinks=[RawFrameRecorder(out / "frames")]).run()
    rep = summary.sinks["raw frame recorder"]
    assert rep["handled"] + sum(rep["dropped"].values()) == 8 and rep["error"] is None
    with open(out / "frames" / "timestamps.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    with open(out / "frames.csv", newline="") as f:
        log_rows = {r["frame_index"]: r for r in csv.DictReader(f)}
    assert len(rows) == rep["handled"] >= 4
    for r in rows:
        img = cv2.cvtColor(cv2.imread(str(out / "frames" / r["file"])), cv2.COLOR_BGR2RGB)
        assert any(np.array_equal(img, f) for f in frames)             # lossless
        assert r["t_capture_ns"] == log_rows[r["frame_index"]]["t_capture_ns"]
        with np.load(out / f"mesh_{int(r['frame_index']):06d}.npz") as z:
            assert np.allclose(z["vertices"], predictor.predict_frame(img).vertices_mm, atol=1e-5)
    # replay: same frames, in order, with the recorded times (from the first frame)
    replay = tmp_path / "replay"
    res = runner.invoke(app, ["run", "--sensor", str(plugin.folder), "--source",
                              str(out / "frames"), "--out", str(replay), "--format", "npz",
                              "--no-forces"])
    assert res.exit_code == 0, res.output
    with open(replay / "frames.csv", newline="") as f:
        again = list(csv.DictReader(f))
    t0 = int(rows[0]["t_capture_ns"])
    assert [int(r["t_source_ns"]) for r in again] == [int(r["t_capture_ns"]) - t0 for r in rows]
    assert [r["source_label"] for r in again] == [r["file"] for r in rows]
    # --record needs --out; --overwrite removes the recording with the rest of the run
    res = runner.invoke(app, ["run", "--sensor", str(plugin.folder), "--record"])
    assert res.exit_code == 2 and "give --out DIR" in res.output
    res = runner.invoke(app, ["run", "--sensor", str(plugin.folder), "--out", str(out),
                              "--overwrite", "--record", "--no-forces", "--format", "ply"])
    assert res.exit_code == 0, res.output
    assert sorted(p.name for p in (out / "frames").glob("*.png")) == [
        f"frame_{i:06d}.png" for i in range(6)]
    assert not list(out.glob("*.npz"))
