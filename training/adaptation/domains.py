"""Target domains of the adaptation experiments: depth maps as the runtime sees them, with the
truth where a simulator made them.

A domain is a set of depth maps (N, 128, 128) float32 mm on the model grid (row 0 = largest y),
the pixel weights (128, 128) of what the sensor sees (1 inside its view and the pad, 0 elsewhere:
the adaptation loss and the label-free metric are taken there), and, for simulated domains, the
true deformed pad meshes (N, 5380, 3) mm (sensor frame) and the clean depth maps rendered from
them.

* ``sim`` (Sim-Prim): the contact simulator's own depth maps of the primitive indenters, clean,
  the whole pad seen (:func:`sim_domain`).
* ``gelslim1``, ``gelslim2`` (Real-Prim, Real-Prim-2): frames of the virtual sensors of those
  names (FEM, RGB optics, effects, camera noise) pressing the primitive indenters inside the
  camera's view, turned into depth by the plugin of the same name (rectification, shading,
  Poisson integration) (:func:`virtual_domain`).
* ``gelslim1-novel`` (Real-Novel): the same with the 16 indenter STL files of
  ``../shared/data/indenters``, shapes the model never saw.
* ``real-balls``: the 42 real GelSight ball presses of ``../shared/data/real``, through a plugin
  calibrated on them (shading model of the same presses, its crop camera mapping; built by
  ``python -m tactile_deploy.calibration.shading.real_gelsight``); no truth (:func:`real_ball_domain`).

Domains are cached as ``.npz`` (:func:`load_or_make`); everything is seeded.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
SHARED_DATA = ROOT.parent / "shared" / "data"
#: Commanded indentation depths of the virtual presses, mm (the training data spans 0.2-1.2).
DEPTH_RANGE_MM = (0.3, 1.1)
#: Contacts are placed inside the sensor's view, this far from its edge, mm.
VIEW_MARGIN_MM = 2.5


@dataclass
class Domain:
    """depth_mm (N, 128, 128) float32 mm, model grid; weight (128, 128) float32 in [0, 1];
    vertices_mm (N, n, 3) float32 mm, sensor frame, or None; true_depth_mm (N, 128, 128) or None
    (the clean depth map rendered from the true mesh); indenter (N,) str."""

    name: str
    depth_mm: np.ndarray
    weight: np.ndarray
    indenter: np.ndarray
    vertices_mm: np.ndarray | None = None
    true_depth_mm: np.ndarray | None = None
    description: str = ""

    def __len__(self) -> int:
        return len(self.depth_mm)

    def subset(self, idx) -> "Domain":
        def pick(a):
            return None if a is None else a[idx]

        return Domain(self.name, self.depth_mm[idx], self.weight, self.indenter[idx], pick(self.vertices_mm),
                      pick(self.true_depth_mm), self.description)

    def split(self, n_first: int) -> tuple["Domain", "Domain"]:
        """(first n_first samples, the rest): adaptation and evaluation parts (different presses)."""
        return self.subset(slice(0, n_first)), self.subset(slice(n_first, None))

    def save(self, path: str | Path) -> None:
        from tactile_deploy.atomic import write_npz

        arrays = {"depth_mm": self.depth_mm, "weight": self.weight, "indenter": self.indenter.astype(str),
                  "name": np.array(self.name), "description": np.array(self.description)}
        if self.vertices_mm is not None:
            arrays["vertices_mm"] = self.vertices_mm
            arrays["true_depth_mm"] = self.true_depth_mm
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        write_npz(path, **arrays)

    @staticmethod
    def load(path: str | Path) -> "Domain":
        with np.load(path) as d:
            return Domain(str(d["name"]), d["depth_mm"], d["weight"], d["indenter"],
                          d["vertices_mm"] if "vertices_mm" in d else None,
                          d["true_depth_mm"] if "true_depth_mm" in d else None, str(d["description"]))


def pad_weight() -> np.ndarray:
    """(128, 128) float32: 1 on the pad's disc (the depth camera's mask), 0 outside."""
    from tactile_deploy.camera.depth import DepthCamera
    from tactile_deploy.pad.asset import load_pad

    pad = load_pad()
    return DepthCamera().render(pad, pad.vertices).mask.astype(np.float32)


def view_weight(plugin) -> np.ndarray:
    """(128, 128) float32: the share of each model-grid cell that the plugin's imaging grid
    covers (its camera's view), times the pad's disc."""
    from tactile_deploy.imaging.camera_mapping import OutputGrid
    from tactile_deploy.runtime.pipeline import GridResampler

    grid = plugin.manifest.camera.grid
    ones = np.ones((grid.ny, grid.nx), np.float32)
    model = OutputGrid()
    if grid == model:
        cover = ones
    else:
        cover = GridResampler(grid, model)(ones)
    return (np.clip(cover, 0.0, 1.0) * pad_weight()).astype(np.float32)


def sim_domain(n: int, seed: int, indenters="primitive") -> Domain:
    """``n`` simulated contacts (the training data's distribution, other seed): clean depth."""
    from tactile_deploy.training.config import SyntheticData
    from tactile_deploy.training.data import generate

    spec = SyntheticData(n_samples=n, seed=seed, indenters=indenters, radius_max_mm=12.0,
                         depth_min_mm=0.2, depth_max_mm=1.2)
    data = generate(spec)
    from tactile_deploy.pad.asset import load_pad

    rest = load_pad().vertices.astype(np.float32)
    return Domain("sim", data.depth_mm, pad_weight(), data.indenter, data.displacement_mm + rest[None],
                  data.depth_mm.copy(), "Sim-Prim: simulated depth maps of the primitive indenters")


def virtual_domain(sensor_name: str, n: int, seed: int, indenters: list[str] | None = None,
                   plugin_name: str | None = None, log=print) -> Domain:
    """``n`` presses of the virtual sensor ``sensor_name`` (random indenter of ``indenters``,
    place inside the camera's view, angle, depth in DEPTH_RANGE_MM), each frame turned into depth
    by the plugin ``plugin_name`` (default: the sensor's name)."""
    import time

    from tactile_deploy.indenters import ContactPose, list_indenters
    from tactile_deploy.runtime.pipeline import ImagingPipeline
    from tactile_deploy.runtime.plugins import SensorPlugin
    from tactile_deploy.sensors import load_sensor
    from tactile_deploy.simulation.contact import ContactError

    indenters = list(indenters or list_indenters("primitive"))
    plugin = SensorPlugin.load(plugin_name or sensor_name)
    pipeline = ImagingPipeline.from_plugin(plugin)
    sensor = load_sensor(sensor_name)
    sensor.prepare()
    g = plugin.manifest.camera.grid
    x0, x1 = g.x_min_mm + VIEW_MARGIN_MM, g.x_max_mm - VIEW_MARGIN_MM
    y0, y1 = g.y_min_mm + VIEW_MARGIN_MM, g.y_max_mm - VIEW_MARGIN_MM
    rng = np.random.default_rng([seed, 0x646F6D])
    depth, true, verts, names = [], [], [], []
    t0 = time.perf_counter()
    while len(depth) < n:
        k = int(rng.integers(len(indenters)))
        pose = ContactPose(x_mm=float(rng.uniform(x0, x1)), y_mm=float(rng.uniform(y0, y1)),
                           theta_deg=float(rng.uniform(0.0, 360.0)), depth_mm=float(rng.uniform(*DEPTH_RANGE_MM)))
        try:
            out = sensor.press(indenters[k], pose, np.random.default_rng([seed, len(depth), 7]))
        except ContactError:
            continue
        if not out.in_contact:
            continue
        depth.append(pipeline.frame_to_depth(out.frame))
        true.append(out.depth_mm)
        verts.append(out.vertices_mm)
        names.append(Path(indenters[k]).stem)
        if len(depth) % 50 == 0:
            log(f"  {sensor_name}: {len(depth)}/{n} presses ({time.perf_counter() - t0:.0f} s)")
    return Domain(sensor_name, np.stack(depth).astype(np.float32), view_weight(plugin), np.array(names),
                  np.stack(verts).astype(np.float32), np.stack(true).astype(np.float32),
                  f"virtual sensor {sensor_name} through plugin {plugin.name}, indenters: "
                  f"{', '.join(sorted(set(names)))}")


def novel_indenters(shared_data: Path = SHARED_DATA) -> list[str]:
    """Paths of the shared indenter STL files (shapes not in the training set)."""
    folder = Path(shared_data) / "indenters"
    files = sorted(str(p) for p in folder.glob("*.stl"))
    if not files:
        raise FileNotFoundError(f"no indenter STL files in {folder}: the novel domain needs "
                                "../shared/data/indenters beside the repository")
    return files


#: Folder (inside a domain cache) of the plugin calibrated on the real ball presses.
REAL_PLUGIN_FOLDER = "fots-gelsight"


def real_ball_domain(work: Path) -> Domain:
    """The 42 real ball presses as depth maps (no truth), through the plugin calibrated on them
    in ``work/fots-gelsight`` (:func:`tactile_deploy.calibration.shading.real_gelsight.real_gelsight_plugin`
    builds it; its demo clip holds the presses)."""
    from tactile_deploy.runtime.pipeline import ImagingPipeline
    from tactile_deploy.runtime.plugins import PluginError, SensorPlugin
    from tactile_deploy.runtime.sources.factory import open_clip

    folder = Path(work) / REAL_PLUGIN_FOLDER
    try:
        plugin = SensorPlugin.load(folder)
    except PluginError as e:
        raise FileNotFoundError(f"{e}; build the plugin of the real ball presses first: python -m "
                                f"tactile_deploy.calibration.shading.real_gelsight --out {folder}") from None
    pipe = ImagingPipeline.from_plugin(plugin)
    depth = []
    with open_clip(plugin.demo_clip_path(), name="the real ball presses") as clip:
        while (frame := clip.read()) is not None:
            depth.append(pipe.frame_to_depth(frame.image))
    depth = np.stack(depth).astype(np.float32)
    return Domain("real-balls", depth, view_weight(plugin), np.array(["ball_r2.35"] * len(depth)),
                  description="42 real GelSight presses of a 2.35 mm ball (../shared/data/real)")


#: name -> how to make it (n, seed) for :func:`load_or_make`.
DOMAINS = {
    "sim": lambda n, seed, work, log: sim_domain(n, seed),
    "gelslim1": lambda n, seed, work, log: virtual_domain("gelslim1", n, seed, log=log),
    "gelslim2": lambda n, seed, work, log: virtual_domain("gelslim2", n, seed, log=log),
    "gelslim1-novel": lambda n, seed, work, log: _named(
        virtual_domain("gelslim1", n, seed, novel_indenters(), log=log), "gelslim1-novel"),
    "real-balls": lambda n, seed, work, log: real_ball_domain(work),
}


def _named(domain: Domain, name: str) -> Domain:
    domain.name = name
    return domain


def load_or_make(name: str, n: int, seed: int, work: str | Path, log=print) -> Domain:
    """Domain ``name`` with ``n`` samples (seeded), cached in ``work/<name>_n<n>_s<seed>.npz``."""
    if name not in DOMAINS:
        raise ValueError(f"unknown domain {name!r}; known: {', '.join(DOMAINS)}")
    path = Path(work) / f"{name}_n{n}_s{seed}.npz"
    if path.is_file():
        return Domain.load(path)
    log(f"making domain {name} ({n} samples, seed {seed}) -> {path}")
    domain = DOMAINS[name](n, seed, Path(work), log)
    domain.save(path)
    return domain


def rmse_mm(a: np.ndarray, b: np.ndarray, weight: np.ndarray | None = None) -> float:
    """Root mean square of a - b over samples and pixels, weighted by ``weight`` (H, W)."""
    d2 = (np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2
    if weight is None:
        return float(math.sqrt(d2.mean()))
    w = np.broadcast_to(weight, d2.shape)
    return float(math.sqrt((d2 * w).sum() / w.sum()))
