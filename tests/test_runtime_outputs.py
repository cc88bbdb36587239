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
        with np.load(out / f"mesh_{i:06d}.npz", allow_pickle=False) as z:
            assert z["vertices"].dtype == np.float32 and z["vertices"].shape == (5380, 3)
            assert np.allclose(z["vertices"], expected.vertices_mm, atol=1e-5)
            assert np.array_equal(z["rest_vertices"], topo.rest_vertices_mm.astype(np.float32))
            assert z["depth"].shape == (128, 128)
            assert np.allclose(z["depth"], expected.depth_mm, atol=1e-6)
            meta = json.loads(str(z["metadata"]))
        assert meta["units"] == {"vertices": "mm", "rest_vertices": "mm", "depth": "mm"}
        assert meta["frame_index"] == i and meta["mesh_hash"] == topo.mesh_hash
        assert meta["source_label"] == f"press_{i:03d}.png"
        assert meta["total_normal_force_n"] is None            # --no-forces
    # the press is really in the depth map: the deepest frame is deeper than the no-contact noise
    with np.load(out / "mesh_000001.npz") as z:
        assert z["depth"].max() > 0.05
