"""Builders shared by the runtime tests (a complete small plugin, a linear ONNX mesh model that
honours the model contract, fake cameras), and tests of the builders themselves.

Other runtime test modules import from here (pytest puts tests/ on sys.path).
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from tactile_deploy.imaging.camera_mapping import camera_mapping_from_parameters
from tactile_deploy.imaging.shading import ShadingHeader, ShadingModel, save_shading
from tactile_deploy.onnx_runtime.contract import mesh_model_metadata
from tactile_deploy.pad.topology import MeshTopology
from tactile_deploy.runtime.plugins import MODEL_GRID, SensorPlugin, write_plugin
from tactile_deploy.runtime.sources.npz import save_clip

FRAME_W, FRAME_H = 640, 480
POOL = 16                              # the linear model averages 16 x 16 depth pixels
N_FEATURES = (128 // POOL) ** 2        # 64 features


# ------------------------------------------------------------------------------------ camera
def make_camera(k1: float = -0.05):
    """640 x 480 camera, 0.075 mm/px, barrel distortion, columns along +x, rows along -y."""
    k = [[600.0, 0, 319.5], [0, 600.0, 239.5], [0, 0, 1]]
    s = 0.075
    h = [[s, 0, -s * 319.5], [0, -s, s * 239.5], [0, 0, 1]]
    return camera_mapping_from_parameters((FRAME_W, FRAME_H), k, [k1, 0, 0, 0, 0], h, grid=MODEL_GRID)


def make_reference(seed: int = 0) -> np.ndarray:
    """Smooth no-contact frame (480, 640, 3) uint8 RGB with a little noise."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:FRAME_H, 0:FRAME_W] / 640.0
    img = np.stack([110 + 20 * x, 120 + 15 * y, 100 + 10 * (x + y)], -1)
    img += rng.normal(0, 0.5, img.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


# ------------------------------------------------------------------------------------ shading
LUT_SLOPE = 0.05          # gradient per colour bin


def make_shading(bins: int = 8) -> ShadingModel:
    """Analytic shading LUT on the 128 x 128 model grid: the red difference sets the gradient
    along columns, the green difference along rows (0.05 per 16-grey-level bin, 0 at no change)."""
    header = ShadingHeader(image_height_px=128, image_width_px=128, mm_per_px=MODEL_GRID.pitch_x_mm,
                           ball_radius_mm=2.0, bins=bins, colour_min=-64.0, colour_max=64.0,
                           saturation_level=255, node_spacing_px=127.0, n_slots=(bins + 1) ** 3,
                           offset_inlier_grey=12.0, poisson_weight_x=1.0, poisson_weight_y=1.0,
                           n_presses=1)
    nb = bins + 1
    q = np.stack(np.unravel_index(np.arange(nb ** 3), (nb, nb, nb)), -1).astype(np.float32)
    g = np.where(q[:, :2] < bins, LUT_SLOPE * (q[:, :2] - bins / 2), 0.0)
    table = np.broadcast_to(g, (2, 2, nb ** 3, 2)).astype(np.float32).copy()
    return ShadingModel(header, np.arange(nb ** 3, dtype=np.int64), table)


def blob_frame(reference: np.ndarray, centre_px=(320, 240), radius_px: float = 40.0,
               amplitude: float = 40.0) -> np.ndarray:
    """The reference with a red/green dipole around ``centre_px``: a press-like depth bump."""
    y, x = np.mgrid[0:FRAME_H, 0:FRAME_W].astype(np.float32)
    dx, dy = x - centre_px[0], y - centre_px[1]
    g = np.exp(-(dx ** 2 + dy ** 2) / (2 * radius_px ** 2))
    out = reference.astype(np.float32)
    out[..., 0] += amplitude * g * dx / radius_px
    out[..., 1] += amplitude * g * dy / radius_px
    return np.clip(np.round(out), 0, 254).astype(np.uint8)


# ------------------------------------------------------------------------------------ ONNX
def build_linear_onnx(path: Path, topology: MeshTopology, mesh_hash: str | None = None,
                      ood_threshold: float | None = 0.5, seed: int = 0, scale: float = 0.02,
                      input_name: str = "depth") -> np.ndarray:
    """A linear mesh model honouring the contract: displacement = avgpool16(depth) @ W,
    vertices = rest + displacement, ood_score = max |depth|. Returns W (64, n*3)."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    n = len(topology.rest_vertices_mm)
    rng = np.random.default_rng(seed)
    w = (scale * rng.standard_normal((N_FEATURES, n * 3))).astype(np.float32)
    inits = [numpy_helper.from_array(w, "W"),
             numpy_helper.from_array(topology.rest_vertices_mm.astype(np.float32), "rest"),
             numpy_helper.from_array(np.array([-1, N_FEATURES], np.int64), "flat_shape"),
             numpy_helper.from_array(np.array([-1, n, 3], np.int64), "mesh_shape")]
    nodes = [
        helper.make_node("AveragePool", [input_name], ["pooled"], kernel_shape=[POOL, POOL],
                         strides=[POOL, POOL]),
        helper.make_node("Reshape", ["pooled", "flat_shape"], ["flat"]),
        helper.make_node("MatMul", ["flat", "W"], ["disp_flat"]),
        helper.make_node("Reshape", ["disp_flat", "mesh_shape"], ["displacement"]),
        helper.make_node("Add", ["displacement", "rest"], ["vertices"]),
        helper.make_node("Abs", [input_name], ["absdepth"]),
        helper.make_node("ReduceMax", ["absdepth"], ["ood_score"], axes=[1, 2, 3], keepdims=0),
    ]
    graph = helper.make_graph(
        nodes, "linear_mesh",
        [helper.make_tensor_value_info(input_name, TensorProto.FLOAT, ["N", 1, 128, 128])],
        [helper.make_tensor_value_info("vertices", TensorProto.FLOAT, ["N", n, 3]),
         helper.make_tensor_value_info("displacement", TensorProto.FLOAT, ["N", n, 3]),
         helper.make_tensor_value_info("ood_score", TensorProto.FLOAT, ["N"])],
        inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    helper.set_model_props(model, mesh_model_metadata("gelslim_v1", mesh_hash or topology.mesh_hash,
                                                      n, ood_threshold))
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return w


def linear_reference(depth: np.ndarray, w: np.ndarray, rest: np.ndarray) -> np.ndarray:
    """numpy version of :func:`build_linear_onnx`'s vertices for depth (N, 128, 128)."""
    d = np.asarray(depth, np.float64)
    n = len(d)
    pooled = d.reshape(n, 128 // POOL, POOL, 128 // POOL, POOL).mean(axis=(2, 4)).reshape(n, -1)
    return rest[None] + (pooled @ w.astype(np.float64)).reshape(n, -1, 3)


# ------------------------------------------------------------------------------------ plugin
def build_test_plugin(folder: Path, name: str = "testsensor", n_frames: int = 6,
                      noise_handling: str = "subtract", model_path: Path | None = None,
                      ood_threshold: float | None = 0.5) -> SensorPlugin:
    """A complete plugin in ``folder``: camera, analytic LUT, reference, noise reference,
    demo clip (presses moving across the pad), linear ONNX model, topology."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    topo = MeshTopology.from_pad()
    camera = make_camera()
    ref = make_reference()
    cv2.imwrite(str(folder / "reference.png"), cv2.cvtColor(ref, cv2.COLOR_RGB2BGR))
    save_shading(make_shading(), folder / "shading.npz")
    rng = np.random.default_rng(3)
    noise = (0.01 * rng.standard_normal((128, 128))).astype(np.float32)
    np.save(folder / "noise_reference.npy", noise)
    frames = np.stack([blob_frame(ref, (200 + 40 * i, 240)) for i in range(n_frames)])
    save_clip(folder / "demo.npz", frames, np.arange(n_frames) * 33_333_333,
              {"sensor": name, "made_by": "test builder"})
    topo.save(folder / "topology.npz")
    if model_path is None:
        model_path = folder / "model.onnx"
        build_linear_onnx(model_path, topo, ood_threshold=ood_threshold)
    fields = {
        "name": name, "description": "test sensor",
        "family": {"name": "gelslim", "pad": "gelslim", "pad_version": 1,
                   "mesh_hash": topo.mesh_hash},
        "camera": json.loads(camera.model_dump_json()),
        "material": {"E_mpa": 0.3, "nu": 0.48, "source": "test"},
        "default_source": {"kind": "demo"},
        "noise_handling": noise_handling,
    }
    files = {"model": model_path, "shading": folder / "shading.npz",
             "reference_frame": folder / "reference.png",
             "noise_reference": folder / "noise_reference.npy", "demo_clip": folder / "demo.npz",
             "topology": folder / "topology.npz"}
    write_plugin(folder, fields, files)
    return SensorPlugin.load(folder)


# ------------------------------------------------------------------------------------ fakes
class FakeCapture:
    """``cv2.VideoCapture`` stand-in replaying frames (BGR), able to vanish and come back.

    script : shared dict of the fake camera's life: ``frames`` (list of BGR arrays, replayed in a
        loop), ``fail_after`` (reads before the device vanishes, None: never), ``down_opens``
        (opening attempts that fail while it is gone; None: gone for good), ``period_s``
        (sleep per read, simulating the frame rate), counters ``reads`` and ``opens``.
    """

    def __init__(self, script: dict):
        import time

        self._time = time
        self.s = script
        self.s["opens"] = self.s.get("opens", 0) + 1
        self.opened = True
        if self.s.get("gone"):
            left = self.s.get("down_opens")
            if left is None or left > 0:
                self.opened = False
                if left is not None:
                    self.s["down_opens"] = left - 1
            else:
                self.s["gone"] = False
        self.props = {}

    def isOpened(self):
        return self.opened

    def set(self, prop, value):
        self.props[prop] = value
        return True

    def get(self, prop):
        return self.props.get(prop, 0.0)

    def read(self):
        if not self.opened or self.s.get("gone"):
            return False, None
        fa = self.s.get("fail_after")
        if fa is not None and self.s.get("reads", 0) >= fa:
            self.s["gone"] = True
            self.s["fail_after"] = None
            return False, None
        if self.s.get("period_s"):
            self._time.sleep(self.s["period_s"])
        i = self.s.get("reads", 0)
        self.s["reads"] = i + 1
        frames = self.s["frames"]
        return True, frames[i % len(frames)].copy()

    def release(self):
        self.opened = False


def wait_for_subscription(pub, sub, timeout_s: float = 10.0) -> None:
    """ZeroMQ's slow joiner: send topology messages until the subscriber gets one."""
    import time

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        pub.send_topology()
        if sub.recv(100) is not None:
            while sub.recv(50) is not None:        # drain the probes
                pass
            return
    raise AssertionError("the subscriber never connected")


# ------------------------------------------------------------------------------------ tests
def test_linear_onnx_matches_its_numpy_reference(tmp_path):
    import onnxruntime as ort

    topo = MeshTopology.from_pad()
    w = build_linear_onnx(tmp_path / "m.onnx", topo)
    rng = np.random.default_rng(1)
    depth = rng.uniform(0, 1, (3, 128, 128)).astype(np.float32)
    sess = ort.InferenceSession(str(tmp_path / "m.onnx"), providers=["CPUExecutionProvider"])
    v, d, ood = sess.run(None, {"depth": depth[:, None]})
    ref = linear_reference(depth, w, topo.rest_vertices_mm.astype(np.float64))
    assert np.allclose(v, ref, atol=2e-5)
    assert np.allclose(d, ref - topo.rest_vertices_mm, atol=2e-5)
    assert np.allclose(ood, np.abs(depth).reshape(3, -1).max(1))


def test_analytic_lut_gives_zero_gradient_without_contact():
    from tactile_deploy.imaging.shading import DepthFromShading

    ref = np.full((128, 128, 3), 120, np.uint8)
    run = DepthFromShading(make_shading(), ref)
    g_col, g_row = run.image_gradients(ref)
    assert np.abs(g_col).max() == 0 and np.abs(g_row).max() == 0
    f = ref.copy()
    f[:, 96:, 0] += 20                   # +20 grey in red (bin 5) on the right quarter
    g_col, _ = run.image_gradients(f)
    assert np.allclose(g_col[:, 96:], LUT_SLOPE) and np.allclose(g_col[:, :90], 0)
