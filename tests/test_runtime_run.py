"""The run loop and ``tactile-deploy run``: meshes, previews and logs written; bad frames,
frames outside the training range, a camera that vanishes, unwritable folders, Ctrl-C; and the
rule that ``tactile_deploy`` runs without torch or warp."""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import cv2
import meshio
import numpy as np
import pytest
import trimesh
from test_runtime_support import (
    FakeCapture,
    blob_frame,
    build_test_plugin,
    wait_for_subscription,
)
from typer.testing import CliRunner

from tactile_deploy.cli.main import app
from tactile_deploy.runtime.predictor import MeshPredictor
from tactile_deploy.runtime.run import RunError, Runner, RunOptions, prepare_out_dir
from tactile_deploy.runtime.sources.base import ArrayPlayback, SourceDisconnectedError
from tactile_deploy.runtime.sources.camera import OpenCVCamera
from tactile_deploy.runtime.sources.config import CameraSourceConfig
from tactile_deploy.runtime.sources.npz import load_clip

ROOT = Path(__file__).resolve().parent.parent
runner = CliRunner()


@pytest.fixture(scope="module")
def plugin(tmp_path_factory):
    return build_test_plugin(tmp_path_factory.mktemp("plugins") / "testsensor", n_frames=6)


@pytest.fixture(scope="module")
def predictor(plugin):
    return MeshPredictor.from_plugin(plugin)


def _clip_source(plugin, frames=None, name="clip"):
    if frames is None:
        frames, _, _ = load_clip(plugin.demo_clip_path())
    return ArrayPlayback(list(frames), np.arange(len(frames)) * 33_000_000, name)


# ------------------------------------------------------------------------------------ outputs
def test_run_writes_meshes_log_and_preview(plugin, predictor, tmp_path):
    out = prepare_out_dir(tmp_path / "out")
    opts = RunOptions(out_dir=out, every=2, formats=("ply", "obj", "glb", "vtu"), view=True)
    summary = Runner(predictor, _clip_source(plugin), opts).run()
    assert summary.frames == 6 and summary.bad_frames == 0 and summary.stopped_by == "end of source"
    assert summary.meshes_written == 3 and summary.write_error is None
    names = sorted(p.name for p in out.iterdir())
    for i in (0, 2, 4):
        for ext in ("ply", "obj", "glb", "vtu"):
            assert f"mesh_{i:06d}.{ext}" in names
    assert "mesh_000001.ply" not in names and "preview.png" in names
    assert "frames.csv" in names and "run.json" in names
    assert not [n for n in names if "partial" in n]
    # the files hold the predicted mesh (checked against a direct prediction)
    frames, _, _ = load_clip(plugin.demo_clip_path())
    expected = predictor.predict_frame(frames[2]).vertices_mm
    vol = meshio.read(out / "mesh_000002.vtu")
    assert np.allclose(vol.points, expected, atol=1e-5)
    assert np.allclose(vol.point_data["displacement_mm"],
                       expected - predictor.topology.rest_vertices_mm, atol=1e-5)
    assert vol.cells_dict["tetra"].shape == predictor.topology.tets.shape
    surf = trimesh.load(out / "mesh_000002.ply", process=False)
    assert np.allclose(surf.vertices, expected, atol=1e-5)
    assert np.allclose(surf.metadata["_ply_raw"]["vertex"]["data"]["disp_z_mm"],
                       (expected - predictor.topology.rest_vertices_mm)[:, 2], atol=1e-6)
    glb = trimesh.load(out / "mesh_000002.glb", force="mesh", process=False)   # glTF: metres, y up
    assert np.allclose(glb.vertices, 1e-3 * expected[:, [0, 2, 1]] * [1, 1, -1], atol=1e-8)
    rows = (out / "frames.csv").read_text().splitlines()
    assert rows[0].startswith("frame_index,t_capture_ns,latency_ms") and len(rows) == 7
    run = json.loads((out / "run.json").read_text())
    assert run["frames"] == 6 and set(run["stage_p50_ms"]) >= {"rectify", "poisson", "model"}
    preview = cv2.imread(str(out / "preview.png"))
    assert preview is not None and preview.shape[1] == 2 * 320 + 6


def test_out_dir_is_never_overwritten_without_asking(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "mesh_000000.ply").write_text("user's file")
    with pytest.raises(RunError, match="already holds 1 file.*--overwrite"):
        prepare_out_dir(out)
    with pytest.raises(RunError, match="already holds"):
        prepare_out_dir(out, ask=lambda q: False)
    (out / "notes.txt").write_text("user's notes")
    assert prepare_out_dir(out, ask=lambda q: True) == out
    assert not (out / "mesh_000000.ply").exists()            # the previous run's files go ...
    assert (out / "notes.txt").read_text() == "user's notes"  # ... the user's own stay
    for name in ("mesh_000003.vtu", "frames.csv", "run.json", "preview.png", "frames/frame_000000.png"):
        (out / name).parent.mkdir(exist_ok=True)
        (out / name).write_text("old run")
    assert prepare_out_dir(out, overwrite=True) == out
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]
    f = tmp_path / "a_file"
    f.write_text("x")
    with pytest.raises(RunError, match="is a file, not a folder"):
        prepare_out_dir(f)
    with pytest.raises(RunError, match="cannot create output folder"):
        prepare_out_dir(f / "sub")


def test_write_failure_mid_run_is_logged_and_the_loop_goes_on(plugin, predictor, tmp_path,
                                                               monkeypatch, caplog):
    from tactile_deploy.runtime import writers

    calls = {"n": 0}
    real = writers.write_volume

    def flaky(path, topology, v):
        calls["n"] += 1
        if calls["n"] >= 2:
            raise OSError(28, "No space left on device")
        real(path, topology, v)

    monkeypatch.setattr(writers, "write_volume", flaky)
    out = prepare_out_dir(tmp_path / "out")
    with caplog.at_level(logging.ERROR):
        summary = Runner(predictor, _clip_source(plugin), RunOptions(out_dir=out, formats=("vtu",))).run()
    assert summary.frames == 6 and summary.meshes_written == 1
    assert summary.meshes_skipped == 5                 # the failed one and the four after it
    assert "No space left on device" in summary.write_error and "frame 1" in summary.write_error
    assert caplog.text.count("No space left") == 1


def test_realtime_pacing_is_not_latency_and_restarts_with_a_loop(plugin, predictor):
    """Frames 0.2 s apart in the recording: the run takes the recording's time, but each frame
    counts as captured when it is due, so the latency is the processing alone; a looping
    recording is paced again after each restart."""
    frames, _, _ = load_clip(plugin.demo_clip_path())
    clip = ArrayPlayback(list(frames[:3]), np.arange(3) * 200_000_000, "slow clip", loop=True)
    summary = Runner(predictor, clip, RunOptions(realtime=True, max_frames=7)).run()
    assert summary.frames == 7 and summary.stopped_by == "max frames"
    assert summary.wall_s >= 0.78                       # 0.4 s per pass of the clip, twice
    assert summary.latency_p50_ms < 100.0               # not the 200 ms of pacing


def test_a_second_interrupt_while_finishing_is_held_back():
    from tactile_deploy.runtime.run import _interrupts_held

    before = signal.getsignal(signal.SIGINT)
    with _interrupts_held():
        os.kill(os.getpid(), signal.SIGINT)             # would raise KeyboardInterrupt here
        time.sleep(0.05)
    assert signal.getsignal(signal.SIGINT) is before


def test_a_run_without_any_mesh_fails_and_leaves_valid_json(plugin, tmp_path):
    """Every frame of the folder has the wrong size: exit 1, and run.json is strict JSON (no NaN
    latency: null)."""
    frames = tmp_path / "frames"
    frames.mkdir()
    for i in range(3):
        cv2.imwrite(str(frames / f"{i:04d}.png"), np.zeros((50, 60, 3), np.uint8))
    out = tmp_path / "out"
    res = runner.invoke(app, ["run", "--sensor", str(plugin.folder), "--source", str(frames),
                              "--out", str(out), "--no-forces"])
    assert res.exit_code == 1, res.output
    assert "no frame" in res.output and "3 refused" in " ".join(res.output.split())

    def no_nan(name):
        raise AssertionError(f"run.json holds {name}")

    run = json.loads((out / "run.json").read_text(), parse_constant=no_nan)
    assert run["frames"] == 0 and run["bad_frames"] == 3 and run["latency_p50_ms"] is None


def test_frames_of_an_image_folder_are_traced_to_their_files(plugin, tmp_path):
    """frames.csv names each mesh's image file; an unreadable file is counted and named."""
    import csv

    frames, _, _ = load_clip(plugin.demo_clip_path())
    folder = tmp_path / "frames"
    folder.mkdir()
    for i, name in ((0, "a_0001.png"), (1, "b,0002.jpg"), (2, "c_0003.png")):
        cv2.imwrite(str(folder / name), cv2.cvtColor(frames[i], cv2.COLOR_RGB2BGR),
                    [cv2.IMWRITE_JPEG_QUALITY, 100])
    (folder / "b_0002b.png").write_bytes(b"not an image")
    out = tmp_path / "out"
    res = runner.invoke(app, ["run", "--sensor", str(plugin.folder), "--source", str(folder),
                              "--out", str(out), "--no-forces", "--format", "ply"])
    assert res.exit_code == 0, res.output
    text = " ".join(res.output.split())
    assert "3 frames" in text and "unreadable 1 (b_0002b.png)" in text
    with open(out / "frames.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [(r["frame_index"], r["source_label"]) for r in rows] == [
        ("0", "a_0001.png"), ("1", "b,0002.jpg"), ("2", "c_0003.png")]
    run = json.loads((out / "run.json").read_text())
    assert run["unreadable_frames"] == 1 and run["unreadable_files"] == ["b_0002b.png"]


def test_cli_refuses_before_making_the_output_folder(plugin, tmp_path):
    out = tmp_path / "out"
    res = runner.invoke(app, ["run", "--sensor", str(plugin.folder), "--source",
                              str(tmp_path / "missing.mp4"), "--out", str(out), "--no-forces"])
    assert res.exit_code == 2 and "file not found" in " ".join(res.output.split())
    assert not out.exists()                             # a corrected rerun is not blocked
    res = runner.invoke(app, ["run", "--sensor", str(plugin.folder), "--providers", "gpu"])
    assert res.exit_code == 2 and "auto, cpu, cuda" in " ".join(res.output.split())
    res = runner.invoke(app, ["run", "--sensor", str(plugin.folder), "--out", "--help"])
    assert res.exit_code == 2 and "looks like an option" in " ".join(res.output.split())
    res = runner.invoke(app, ["run", "--sensor", str(plugin.folder), "--publish", "tcp://*:99999",
                              "--out", str(out), "--no-forces"])
    assert res.exit_code == 2 and "1-65535" in res.output and not out.exists()


# ------------------------------------------------------------------------------------ stream
def test_bad_frames_are_skipped_and_counted(plugin, predictor, caplog):
    frames, _, _ = load_clip(plugin.demo_clip_path())
    mixed = [frames[0], frames[1][:240], frames[2].astype(np.float32), frames[3]]
    with caplog.at_level(logging.WARNING):
        summary = Runner(predictor, _clip_source(plugin, mixed), RunOptions()).run()
    assert summary.frames == 2 and summary.bad_frames == 2
    assert "frame 1 skipped" in caplog.text and "640x240 px" in caplog.text
    bad = [frames[0][:100]] * 5
    with pytest.raises(RunError, match="5 frames in a row were refused"):
        Runner(predictor, _clip_source(plugin, bad), RunOptions(max_bad_frames=5)).run()


def test_frames_leaving_the_training_range_are_flagged(plugin, caplog):
    pred = MeshPredictor.from_plugin(plugin)
    pred.ood_threshold = 0.45          # the clip's later presses score 0.44-0.49
    with caplog.at_level(logging.WARNING):
        summary = Runner(pred, _clip_source(plugin), RunOptions()).run()
    assert 0 < summary.ood_frames < summary.frames
    assert "outside the model's training range" in caplog.text


def test_camera_vanishing_mid_run(plugin, predictor, caplog):
    bgr = cv2.cvtColor(blob_frame(plugin.reference_frame), cv2.COLOR_RGB2BGR)
    script = {"frames": [bgr], "period_s": 0.002, "fail_after": 4, "down_opens": 2}
    cam = OpenCVCamera(CameraSourceConfig(device=0, reconnect_timeout_s=5),
                       capture_factory=lambda d: FakeCapture(script), sleep=lambda s: None)
    with caplog.at_level(logging.WARNING):
        summary = Runner(predictor, cam, RunOptions(max_frames=10)).run()
    assert summary.frames == 10 and summary.reconnects == 1
    assert "is back after" in caplog.text
    script = {"frames": [bgr], "period_s": 0.002, "fail_after": 3, "down_opens": None}
    cam = OpenCVCamera(CameraSourceConfig(device=0, reconnect_timeout_s=0.2, max_backoff_s=0.05),
                       capture_factory=lambda d: FakeCapture(script),
                       sleep=lambda s: time.sleep(min(s, 0.01)))
    r = Runner(predictor, cam, RunOptions(max_frames=50))
    with pytest.raises(SourceDisconnectedError, match="did not come back"):
        r.run()
    assert r.summary.stopped_by == "error" and 1 <= r.summary.frames <= 3


def test_keyboard_interrupt_ends_cleanly(plugin, predictor, tmp_path):
    class Interrupting(ArrayPlayback):
        def _read(self):
            if self.stats.delivered == 3:
                raise KeyboardInterrupt
            return super()._read()

    frames, _, _ = load_clip(plugin.demo_clip_path())
    src = Interrupting(list(frames), np.arange(6) * 1000, "clip")
    out = prepare_out_dir(tmp_path / "out")
    summary = Runner(predictor, src, RunOptions(out_dir=out, formats=("ply",))).run()
    assert summary.stopped_by == "interrupted" and summary.frames == 3
    assert summary.meshes_written == 3 and (out / "run.json").is_file()
    assert not src.is_connected


def test_publishing_during_a_run(plugin, predictor):
    from tactile_deploy.runtime.forces import ForceEstimator, SurfaceStiffness
    from tactile_deploy.runtime.publish import MeshPublisher, MeshSubscriber

    n = len(predictor.topology.sensing_nodes)
    stiff = SurfaceStiffness(predictor.topology.sensing_nodes, np.eye(n), "identity")
    forces = ForceEstimator(stiff, 1.0, predictor.topology.rest_vertices_mm, np.ones(n))
    pub = MeshPublisher("tcp://127.0.0.1:*", "testsensor", predictor.topology, hwm=100)
    with MeshSubscriber(pub.endpoint, "testsensor") as sub:
        wait_for_subscription(pub, sub)
        summary = Runner(predictor, _clip_source(plugin), RunOptions(), forces=forces,
                         publisher=pub).run()
        got = []
        while (m := sub.recv(1000)) is not None:
            got.append(m)
    meshes = [m for m in got if m[0] == "mesh/testsensor"]
    assert summary.published == 6 and len(meshes) == 6
    h, a = meshes[-1][1], meshes[-1][2]
    assert h["frame_index"] == 5 and a["vertices_mm"].shape == (5380, 3)
    uz = a["vertices_mm"][:n, 2] - predictor.topology.rest_vertices_mm[:n, 2]
    assert np.isclose(h["total_normal_force_n"], (-uz).sum(), rtol=1e-4)


# ------------------------------------------------------------------------------------ CLI
def test_cli_run_on_the_demo_clip(plugin, tmp_path):
    out = tmp_path / "out"
    args = ["run", "--sensor", str(plugin.folder), "--out", str(out), "--every", "3", "--view",
            "--no-forces"]
    res = runner.invoke(app, args)
    assert res.exit_code == 0, res.output
    assert "6 frames" in res.output and "meshes written 2" in res.output
    assert (out / "mesh_000003.vtu").is_file() and (out / "preview.png").is_file()
    res = runner.invoke(app, args)                   # same folder again: refused
    assert res.exit_code == 2 and "--overwrite" in res.output
    res = runner.invoke(app, [*args, "--overwrite", "--format", "stl"])
    assert res.exit_code == 2 and "unknown mesh format" in res.output
    res = runner.invoke(app, ["run", "--sensor", "no_such_sensor"])
    assert res.exit_code == 2 and "plugins list" in res.output
    res = runner.invoke(app, ["run", "--sensor", str(plugin.folder), "--source", "nowhere.xyz"])
    assert res.exit_code == 2 and "Accepted forms" in res.output


def test_sigint_stops_a_looping_run(plugin, tmp_path):
    """A real process on an endless source, interrupted like Ctrl-C: exits 0 with its summary
    and its files complete."""
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "tactile_deploy.cli.main", "run", "--sensor", str(plugin.folder),
           "--loop", "--out", str(out), "--every", "50", "--format", "ply", "--no-forces"]
    # as from a terminal: SIGINT handled by default even if this test runner was started with it
    # ignored (a background job), which Python would otherwise pass on to the child
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            cwd=tmp_path,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not (out / "mesh_000050.ply").exists():
        time.sleep(0.2)
    proc.send_signal(signal.SIGINT)
    stdout, stderr = proc.communicate(timeout=30)
    assert proc.returncode == 0, stderr
    assert "stopped by interrupted" in stdout
    run = json.loads((out / "run.json").read_text())
    assert run["stopped_by"] == "interrupted" and run["frames"] > 50


# ------------------------------------------------------------------------------------ imports
def test_runtime_runs_without_torch_or_warp(plugin, tmp_path):
    """Import every runtime module, predict frames, compute a surface compliance and the CLI's
    help with torch and warp made unimportable."""
    script = textwrap.dedent(f"""
        import importlib.abc, sys
        class Block(importlib.abc.MetaPathFinder):
            def find_spec(self, name, path=None, target=None):
                if name.split(".")[0] in ("torch", "warp"):
                    raise ImportError("blocked: " + name)
        sys.meta_path.insert(0, Block())
        import pkgutil, importlib, numpy as np
        import tactile_deploy
        for m in pkgutil.walk_packages(tactile_deploy.__path__, "tactile_deploy."):
            if m.name.split(".")[1] in ("runtime", "imaging", "pad", "cli"):
                importlib.import_module(m.name)
        from tactile_deploy.runtime import MeshPredictor
        p = MeshPredictor.from_plugin({str(plugin.folder)!r})
        frame = p.plugin.reference_frame
        assert p.predict_frame(frame).vertices_mm.shape == (5380, 3)
        from tactile_deploy.fem.material import Material
        from tactile_deploy.fem.simulator import ContactSimulator
        from tactile_deploy.pad.asset import load_pad
        from tactile_deploy.runtime.forces import _z_compliance
        mesh = load_pad()
        # the standard formulation factors in a second (the default one takes longer; both
        # go through the same numpy assembly and sparse Cholesky)
        sim = ContactSimulator(mesh, Material(nu=0.48), assembly="numpy",
                               contact_nodes=np.arange(0, mesh.n_plane, 60), use_cache=False,
                               formulation="standard")
        c = _z_compliance(sim)
        assert np.all(np.linalg.eigvalsh(c) > 0)
        from typer.testing import CliRunner
        from tactile_deploy.cli.main import app
        assert CliRunner().invoke(app, ["run", "--help"]).exit_code == 0
        assert not any(k.split(".")[0] in ("torch", "warp") for k in sys.modules)
        print("ok")
        """)
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         cwd=ROOT, timeout=300,
                         env={**os.environ, "TACTILE_DEPLOY_CACHE_DIR": str(tmp_path)})
    assert res.returncode == 0 and res.stdout.strip().endswith("ok"), res.stderr[-3000:]


# ------------------------------------------------------------------------------------ example
def test_embedding_example_runs_with_onnxruntime_and_numpy_only(plugin):
    """examples/embed_onnx_numpy.py on a plugin: it runs, reports the press, and imports neither
    tactile_deploy nor torch (what a program in another language would have)."""
    example = ROOT / "examples" / "embed_onnx_numpy.py"
    script = textwrap.dedent(f"""
        import runpy, sys
        sys.argv = [{str(example)!r}, "--plugin", {str(plugin.folder)!r}]
        try:
            runpy.run_path(sys.argv[0], run_name="__main__")
        except SystemExit as e:
            assert e.code in (0, None), e.code
        bad = sorted(k for k in sys.modules if k.split(".")[0] in ("tactile_deploy", "torch", "cv2"))
        print("foreign modules:", bad)
        """)
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         cwd=ROOT, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "foreign modules: []" in res.stdout
    assert "5380 vertices, 24444 tets" in res.stdout and "out-of-distribution score" in res.stdout


def test_mesh_writer_skips_for_live_sources_and_waits_for_recordings(predictor, tmp_path,
                                                                      monkeypatch):
    from tactile_deploy.runtime import writers

    monkeypatch.setattr(writers, "write_surface", lambda *a, **k: time.sleep(0.02))
    v = predictor.topology.rest_vertices_mm
    live = writers.MeshWriter(tmp_path, predictor.topology, ("ply",), queue_size=2)
    for i in range(20):
        live.submit(i, v)
    live.close()
    assert live.skipped > 0 and live.written + live.skipped == 20
    rec = writers.MeshWriter(tmp_path, predictor.topology, ("ply",), queue_size=2)
    for i in range(20):
        assert rec.submit(i, v, block=True)
    rec.close()
    assert rec.written == 20 and rec.skipped == 0


def test_loop_memory_does_not_grow_with_frames(plugin, predictor):
    """Python allocations of the loop over frames 300-349 and, 1,000 frames later, 1300-1349 (no
    outputs): flat (fixed-size statistics; a per-frame leak of one float would add 32 kB). Arrays
    in flight at the moment of a reading add up to ~20 kB of noise, never less than the live
    set: the smallest reading of each window is compared."""
    import tracemalloc

    frames, _, _ = load_clip(plugin.demo_clip_path())
    src = ArrayPlayback(list(frames), np.arange(len(frames)) * 1000, "clip", loop=True)
    early, late = [], []

    class Probe(Runner):
        def step(self, frame, due_ns=None):
            super().step(frame, due_ns)
            n = self.summary.frames
            if 300 <= n < 350 or 1300 <= n < 1350:
                (early if n < 350 else late).append(tracemalloc.get_traced_memory()[0])

    tracemalloc.start()
    try:
        Probe(predictor, src, RunOptions(max_frames=1350)).run()
    finally:
        tracemalloc.stop()
    assert len(early) == len(late) == 50
    assert min(late) - min(early) < 16_000, (min(early), min(late))
