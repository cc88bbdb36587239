"""Evaluation report of the exported predictor against the physics baseline, domain by domain.

``python -m tactile_deploy.training evaluate --model exported/gelslim_mesh.onnx --out docs/results/evaluation.json``

Domains (fresh contacts simulated on the CPU, never seen in training; poses drawn as in training:
uniform in a disc of radius 12 mm, theta uniform, depth 0.2-1.2 mm):

* ``primitives``: the training indenters, frictionless linear FEM (the training distribution);
* ``shared_stl``: the 16 indenters of ``../shared/data/indenters`` (never trained on);
* ``stick``: the training indenters with sticking contact (the gel does not slide on them);
* ``large_strain``: the training indenters with the neo-Hookean large-deformation solve
  (effect ``hyperelastic``, strength 1), depths 0.6-1.2 mm;
* ``noisy``: the primitives' depth maps with sensor-like noise: white noise of 10 um RMS plus a
  smooth field of 20 um RMS (Gaussian-filtered noise, 2 mm correlation length).

Methods: the ONNX model (onnxruntime, the shipped graph) and the physics baseline that needs no
learning (:class:`tactile_deploy.fem.surface_to_volume.SurfaceToVolume`: the depth map as the
sensing surface's normal displacement, the linear FEM for the rest).

Metrics (mm, sensor frame): vertex RMSE over all nodes (the paper's metric), relative error
``||pred - true|| / ||true||`` of the displacements, and the RMSE per region: sensing surface
(layer 0), interior (the free layers below it), contact patch (sensing nodes in contact).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

DOMAINS = ("primitives", "shared_stl", "stick", "large_strain", "noisy")


@dataclass
class DomainData:
    """depth_mm (N, 128, 128); displacement_mm (N, n, 3); contact_mask (N, n_plane) bool; indenter (N,)."""

    depth_mm: np.ndarray
    displacement_mm: np.ndarray
    contact_mask: np.ndarray
    indenter: np.ndarray


def simulate_domain(domain: str, n: int, seed: int, shared_dir: Path | None = None) -> DomainData:
    """``n`` contacts of ``domain`` (see the module docstring), deterministic in ``seed``."""
    from tactile_deploy.fem.material import Material
    from tactile_deploy.indenters import ContactPose, get_indenter, list_indenters
    from tactile_deploy.simulation.contact import ContactError, get_camera, get_simulator, simulate_contact

    if domain not in DOMAINS:
        raise ValueError(f"unknown domain {domain!r}; known: {', '.join(DOMAINS)}")
    if domain == "shared_stl":
        if shared_dir is None or not shared_dir.is_dir():
            raise FileNotFoundError(f"shared indenter folder {shared_dir} not found: place ../shared beside the checkout")
        names = sorted(str(p) for p in shared_dir.glob("*.stl"))
    else:
        names = list(list_indenters("primitive"))
    indenters = [get_indenter(n_) for n_ in names]
    friction = "stick" if domain == "stick" else "frictionless"
    material = Material(nu=0.48, friction=friction)
    sim = get_simulator(material)
    cam = get_camera()
    effect = None
    depth_range = (0.2, 1.2)
    if domain == "large_strain":
        from tactile_deploy.sensors.effects import get_effect

        effect = get_effect("hyperelastic", {"strength": 1.0})
        depth_range = (0.6, 1.2)
    rng = np.random.default_rng([seed, DOMAINS.index(domain)])
    depth, disp, mask, ind = [], [], [], []
    while len(depth) < n:
        k = int(rng.integers(len(indenters)))
        r = 12.0 * math.sqrt(rng.random())
        phi = 2 * math.pi * rng.random()
        pose = ContactPose(x_mm=r * math.cos(phi), y_mm=r * math.sin(phi), theta_deg=360 * rng.random(),
                           depth_mm=float(rng.uniform(*depth_range)))
        try:
            if effect is None:
                s = simulate_contact(indenters[k], pose, material, cam, sim)
                depth.append(s.depth_mm)
                disp.append(s.vertices_mm - s.rest_vertices_mm)
                mask.append(s.contact_mask)
            else:
                delta = sim.intrusion(indenters[k], pose)
                if not np.any(delta > 0):
                    continue
                res = effect.correct_contact(sim, delta, sim.solve_intrusion(delta))
                depth.append(cam.render(sim.mesh, res.vertices_mm).depth_mm)
                disp.append(res.displacements_mm.astype(np.float32))
                mask.append(res.contact_mask)
        except (ContactError, RuntimeError):
            continue
        ind.append(Path(names[k]).stem)
    depth_arr = np.asarray(depth, np.float32)
    if domain == "noisy":
        depth_arr = add_sensor_noise(depth_arr, np.random.default_rng([seed, 99]))
    return DomainData(depth_arr, np.asarray(disp, np.float32), np.asarray(mask, bool), np.asarray(ind))


def add_sensor_noise(depth_mm: np.ndarray, rng: np.random.Generator, white_um: float = 10.0,
                     smooth_um: float = 20.0, correlation_mm: float = 2.0) -> np.ndarray:
    """Depth maps (N, R, R) mm plus white noise and a smooth Gaussian-correlated field (RMS in um)."""
    from scipy.ndimage import gaussian_filter

    n, r, _ = depth_mm.shape
    sigma_px = correlation_mm / (35.0 / r)
    smooth = gaussian_filter(rng.standard_normal((n, r, r)), sigma=(0, sigma_px, sigma_px))
    smooth *= smooth_um * 1e-3 / smooth.std(axis=(1, 2), keepdims=True)
    white = rng.standard_normal((n, r, r)) * white_um * 1e-3
    return (depth_mm + smooth + white).astype(np.float32)


def region_metrics(pred: np.ndarray, true: np.ndarray, contact_mask: np.ndarray, n_plane: int,
                   free_layers: int) -> dict:
    """Errors (mm) of predicted displacements (N, n, 3) against the truth, overall and per region."""
    err = (pred - true).astype(np.float64)
    sq = (err**2).sum(-1)  # (N, n)
    surface = sq[:, :n_plane]
    interior = sq[:, n_plane: free_layers * n_plane]
    patch = surface[contact_mask]
    return {
        "vertex_rmse_mm": float(np.sqrt(sq.mean() / 3)),
        "relative_error": float(np.linalg.norm(err) / max(np.linalg.norm(true), 1e-12)),
        "max_error_mm": float(np.sqrt(sq.max())),
        "surface_rmse_mm": float(np.sqrt(surface.mean() / 3)),
        "interior_rmse_mm": float(np.sqrt(interior.mean() / 3)),
        "contact_patch_rmse_mm": float(np.sqrt(patch.mean() / 3)) if patch.size else float("nan"),
    }


def evaluate_domain(data: DomainData, model_path: Path, batch: int = 32) -> dict:
    """Region metrics of the ONNX model and of the physics baseline on ``data``."""
    from tactile_deploy.fem.material import Material
    from tactile_deploy.fem.surface_to_volume import SurfaceToVolume
    from tactile_deploy.runtime.predictor import MeshPredictor
    from tactile_deploy.simulation.contact import get_simulator

    predictor = MeshPredictor(model_path, threads=2)
    preds = []
    for i in range(0, len(data.depth_mm), batch):
        preds.append(predictor.predict_depth(data.depth_mm[i: i + batch]).displacement_mm)
    learned = np.concatenate(preds)
    s2v = SurfaceToVolume(get_simulator(Material(nu=0.48)))
    mesh = s2v.mesh
    physics = np.stack([s2v.vertices_from_depth(d) - mesh.vertices for d in data.depth_mm]).astype(np.float32)
    n_plane = mesh.n_plane
    free_layers = int(round(mesh.n_nodes / n_plane)) - 1  # the last layer is the bonded backplate
    return {
        "n_samples": int(len(data.depth_mm)),
        "learned": region_metrics(learned, data.displacement_mm, data.contact_mask, n_plane, free_layers),
        "physics": region_metrics(physics, data.displacement_mm, data.contact_mask, n_plane, free_layers),
        "true_rms_displacement_mm": float(np.sqrt(np.mean(data.displacement_mm.astype(np.float64) ** 2))),
    }


def run_evaluation(model_path: str | Path, n: int = 256, seed: int = 2024,
                   domains: tuple[str, ...] = DOMAINS, shared_dir: Path | None = None, log=print) -> dict:
    """Every domain: simulate ``n`` contacts (fewer for the costly large-strain solve), evaluate both methods."""
    import time

    out = {"model": str(model_path), "seed": seed, "domains": {}}
    for d in domains:
        t0 = time.perf_counter()
        data = simulate_domain(d, n if d != "large_strain" else max(8, n // 8), seed, shared_dir)
        res = evaluate_domain(data, Path(model_path))
        res["seconds"] = time.perf_counter() - t0
        out["domains"][d] = res
        log(f"{d}: learned {res['learned']['vertex_rmse_mm'] * 1e3:.2f} um (rel {res['learned']['relative_error']:.3f}), "
            f"physics {res['physics']['vertex_rmse_mm'] * 1e3:.2f} um (rel {res['physics']['relative_error']:.3f}) "
            f"[{res['n_samples']} contacts, {res['seconds']:.0f} s]")
    return out
