"""Evaluation of exported predictors against the physics lift, domain by domain.

``python -m tactile_deploy.training evaluate --model exported/gelslim_mesh.onnx --out docs/results/evaluation.json``

Domains (fresh contacts simulated on the CPU with seeds no training run uses; poses as in
training: uniform in a disc of radius 12 mm, theta uniform):

* ``primitives``: the training indenters, frictionless, depth 0.2-1.2 mm;
* ``coulomb``: the training indenters with Coulomb friction, mu uniform in 0.3-1.5 per contact
  (:class:`tactile_deploy.fem.coulomb.CoulombSimulator`, one load step from rest as ``stick``);
* ``stick``: the training indenters, the gel sticking to them;
* ``large_strain``: the training indenters with the neo-Hookean large-deformation solve (effect
  ``hyperelastic``, strength 1), depth 0.6-1.2 mm;
* ``noisy``: the primitives' depth maps with sensor-like noise: white noise of 10 um RMS plus a
  smooth field of 20 um RMS (Gaussian-filtered noise, 2 mm correlation length);
* ``unseen_shapes``: the 16 STL indenters of ``../shared/data/indenters``, never trained on,
  frictionless, depth 0.2-1.2 mm.

The gel of the frictionless domains (``primitives``, ``noisy``, ``unseen_shapes``) is linear
elastic unless ``gel="neo-hookean"`` (``--gel neo-hookean``): then their truth is the
neo-Hookean large-deformation solve of ``large_strain``, at poses and depths drawn as for the
linear gel: the truth a graph trained on neo-Hookean contacts is measured against. The friction
domains have no neo-Hookean truth yet (they are reported as not measured under that gel).

Two more, for graphs of gels that grip, run only when named (``--domains``; :data:`ALL_DOMAINS`):
``unseen_shapes_coulomb`` (the shared STL indenters with Coulomb friction, mu as ``coulomb``) and
``noisy_coulomb`` (the ``coulomb`` contacts' maps with the ``noisy`` domain's noise).

Methods: each ONNX model (onnxruntime, as the runtime runs it) and the **physics lift** that
needs no learning (:class:`tactile_deploy.fem.surface_to_volume.SurfaceToVolume`: the depth map as
the sensing surface's normal displacement, read where each node has moved to in 3 passes, the
linear FEM for the rest of the pad).

Figures: :func:`tactile_deploy.training.metrics.mesh_metrics` (contact patch, deepest node, all nodes; per-node
Euclidean errors in um), for every domain and method, and the lift's contact-patch error over the
model's (``lift_ratio``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field

from tactile_deploy.fileformat import StrictModel
from tactile_deploy.training.metrics import MeshMetrics

DOMAINS = ("primitives", "coulomb", "stick", "large_strain", "noisy", "unseen_shapes")
#: Every domain: the default ones, then those run only when named.
ALL_DOMAINS = DOMAINS + ("unseen_shapes_coulomb", "noisy_coulomb")
DOMAIN_LABELS = {
    "primitives": "primitives, frictionless",
    "coulomb": "Coulomb friction, mu 0.3-1.5",
    "stick": "sticking contact",
    "large_strain": "large strain (neo-Hookean), depth 0.6-1.2 mm",
    "noisy": "noisy maps: 10 um white + 20 um smooth",
    "unseen_shapes": "unseen shapes (shared STL indenters)",
    "unseen_shapes_coulomb": "unseen shapes, Coulomb friction, mu 0.3-1.5",
    "noisy_coulomb": "noisy maps, Coulomb friction, mu 0.3-1.5",
}
#: Targets per domain: (largest contact-patch RMSE um, largest mean |deepest-node error| %, least
#: lift_ratio); None where the domain has no such target.
TARGETS = {
    "primitives": (30.0, 3.0, None),
    "unseen_shapes": (30.0, 3.0, None),
    "coulomb": (50.0, None, 1.5),
    "stick": (50.0, None, 1.5),
    "large_strain": (50.0, None, 1.5),
    "noisy": (50.0, None, 1.5),
    "unseen_shapes_coulomb": (30.0, 3.0, None),
    "noisy_coulomb": (50.0, None, 1.5),
}
PHYSICS_LIFT = "physics lift"
#: The gel laws of the frictionless domains' truth.
GELS = ("linear", "neo-hookean")
#: Domains whose truth follows ``gel``; ``large_strain`` is neo-Hookean under either.
FRICTIONLESS_DOMAINS = ("primitives", "noisy", "unseen_shapes")


class DomainResult(StrictModel):
    """One domain of an evaluation report: every method's figures on the same contacts."""

    n_samples: int = Field(ge=1, description="Contacts simulated for this domain.")
    methods: dict[str, MeshMetrics] = Field(description="Model label (and 'physics lift') -> its figures.")
    true_rms_displacement_um: float = Field(ge=0, description="RMS length of the true displacement over all nodes, um.")
    redrawn_contacts: int = Field(0, ge=0, description=(
        "Poses drawn and discarded: the indenter touched no sensing node, or the solve did not converge."))
    seconds: float = Field(ge=0, description="Wall time of the domain (simulation + every method), s.")


class DomainNotMeasured(StrictModel):
    """A domain the simulator could not make, and why."""

    unavailable: str


class EvaluationReport(StrictModel):
    """``python -m tactile_deploy.training evaluate --out REPORT.json`` (e.g. docs/results/evaluation.json)."""

    models: dict[str, str] = Field(description="Label -> the ONNX model evaluated.")
    seed: int = Field(ge=0, description="Seed of the fresh contacts (no training run uses it).")
    gel: Literal["linear", "neo-hookean"] = Field(
        "linear", description="Gel law of the frictionless domains' truth (primitives, noisy, unseen_shapes).")
    metrics: str = Field(description="Where the figures are defined.")
    domains: dict[str, DomainResult | DomainNotMeasured] = Field(description=f"Domain ({', '.join(ALL_DOMAINS)}) -> result.")


class DomainUnavailable(RuntimeError):
    """The simulator cannot make this domain's contacts (the message says why)."""


@dataclass
class DomainData:
    """depth_mm (N, 128, 128); displacement_mm (N, n, 3); contact_mask (N, n_plane) bool; indenter (N,);
    redrawn: poses discarded (no sensing node touched, or no convergence) and drawn again."""

    depth_mm: np.ndarray
    displacement_mm: np.ndarray
    contact_mask: np.ndarray
    indenter: np.ndarray
    redrawn: int = 0


def simulate_domain(domain: str, n: int, seed: int, shared_dir: Path | None = None,
                    gel: str = "linear") -> DomainData:
    """``n`` contacts of ``domain`` (see the module docstring), deterministic in ``seed``; the
    frictionless domains' truth from the ``gel`` law ("linear" or "neo-hookean"; the same draws
    under either until a contact one of them rejects is redrawn)."""
    from tactile_deploy.fem.material import Material
    from tactile_deploy.indenters import ContactPose, get_indenter, list_indenters
    from tactile_deploy.simulation.contact import ContactError, get_camera, get_simulator, simulate_contact
    from tactile_deploy.training.data import neo_hookean_press

    if domain not in ALL_DOMAINS:
        raise ValueError(f"unknown domain {domain!r}; known: {', '.join(ALL_DOMAINS)}")
    if gel not in GELS:
        raise ValueError(f"unknown gel {gel!r}; known: {', '.join(GELS)}")
    if gel == "neo-hookean" and domain not in FRICTIONLESS_DOMAINS + ("large_strain",):
        raise DomainUnavailable("no neo-Hookean truth with friction (the neo-Hookean solve is frictionless); "
                                "evaluate this domain with the linear gel")
    if domain.startswith("unseen_shapes"):
        if shared_dir is None or not shared_dir.is_dir():
            raise FileNotFoundError(f"shared indenter folder {shared_dir} not found: place ../shared beside the checkout")
        names = sorted(str(p) for p in shared_dir.glob("*.stl"))
    else:
        names = list(list_indenters("primitive"))
    indenters = [get_indenter(n_) for n_ in names]
    coulomb = domain in ("coulomb", "unseen_shapes_coulomb", "noisy_coulomb")
    friction = "coulomb" if coulomb else {"stick": "stick"}.get(domain, "frictionless")
    material = Material(nu=0.48, friction=friction)
    sim = None if coulomb else get_simulator(material)
    cam = get_camera()
    large_strain = domain == "large_strain"
    neo_hookean = large_strain or (gel == "neo-hookean" and domain in FRICTIONLESS_DOMAINS)
    depth_range = (0.6, 1.2) if large_strain else (0.2, 1.2)
    rng = np.random.default_rng([seed, ALL_DOMAINS.index(domain)])
    depth, disp, mask, ind = [], [], [], []
    redrawn = 0
    while len(depth) < n:
        k = int(rng.integers(len(indenters)))
        r = 12.0 * math.sqrt(rng.random())
        phi = 2 * math.pi * rng.random()
        pose = ContactPose(x_mm=r * math.cos(phi), y_mm=r * math.sin(phi), theta_deg=360 * rng.random(),
                           depth_mm=float(rng.uniform(*depth_range)))
        try:
            if coulomb:
                mat = Material(nu=0.48, friction="coulomb", mu=float(rng.uniform(0.3, 1.5)))
                try:
                    s = simulate_contact(indenters[k], pose, mat, cam)
                except (NotImplementedError, ValueError) as e:
                    if "coulomb" in str(e).lower() or isinstance(e, NotImplementedError):
                        raise DomainUnavailable(f"this simulator does not solve Coulomb friction ({e})") from None
                    raise
                depth.append(s.depth_mm)
                disp.append(s.vertices_mm - s.rest_vertices_mm)
                mask.append(s.contact_mask)
            elif not neo_hookean:
                s = simulate_contact(indenters[k], pose, material, cam, sim)
                depth.append(s.depth_mm)
                disp.append(s.vertices_mm - s.rest_vertices_mm)
                mask.append(s.contact_mask)
            else:
                s = neo_hookean_press(sim, indenters[k], pose, cam)   # the hyperelastic effect's solve
                depth.append(s.depth_mm)
                disp.append(s.displacements_mm.astype(np.float32))
                mask.append(s.contact_mask)
        except (ContactError, RuntimeError) as e:
            if isinstance(e, DomainUnavailable):
                raise
            redrawn += 1
            continue
        ind.append(Path(names[k]).stem)
    depth_arr = np.asarray(depth, np.float32)
    if domain.startswith("noisy"):
        depth_arr = add_sensor_noise(depth_arr, np.random.default_rng([seed, 99]))
    return DomainData(depth_arr, np.asarray(disp, np.float32), np.asarray(mask, bool), np.asarray(ind), redrawn)


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


def physics_lift(depth_mm: np.ndarray) -> np.ndarray:
    """Displacements (N, n, 3) mm of the physics lift (3 passes) for depth maps (N, R, R) mm."""
    from tactile_deploy.fem.material import Material
    from tactile_deploy.fem.surface_to_volume import SurfaceToVolume
    from tactile_deploy.simulation.contact import get_simulator

    s2v = SurfaceToVolume(get_simulator(Material(nu=0.48)))
    rest = s2v.mesh.vertices
    return np.stack([s2v.vertices_from_depth(d) - rest for d in depth_mm]).astype(np.float32)


def onnx_displacements(model_path: Path, depth_mm: np.ndarray, batch: int = 32, threads: int = 2) -> np.ndarray:
    """Displacements (N, n, 3) mm of an exported model, run as the runtime runs it."""
    from tactile_deploy.runtime.predictor import MeshPredictor

    predictor = MeshPredictor(model_path, threads=threads, warmup=0)
    return np.concatenate([predictor.predict_depth(depth_mm[i: i + batch]).displacement_mm
                           for i in range(0, len(depth_mm), batch)])


def evaluate_domain(data: DomainData, predictions: dict[str, np.ndarray], n_plane: int) -> dict:
    """Figures of each method's displacements (name -> (N, n, 3) mm) on ``data``, and each
    method's ``lift_ratio`` (the physics lift's contact-patch RMSE over the method's)."""
    from tactile_deploy.training.metrics import mesh_metrics

    methods = {name: mesh_metrics(p, data.displacement_mm, data.contact_mask, n_plane) for name, p in predictions.items()}
    lift = methods.get(PHYSICS_LIFT, {}).get("contact_patch_rmse_um")
    if lift is not None:
        for name, m in methods.items():
            m["lift_ratio"] = float(lift / m["contact_patch_rmse_um"]) if m.get("contact_patch_rmse_um") else None
    return {
        "n_samples": int(len(data.depth_mm)),
        "methods": methods,
        "true_rms_displacement_um": float(np.sqrt(np.mean((data.displacement_mm.astype(np.float64) ** 2).sum(-1))) * 1e3),
    }


def run_evaluation(models: dict[str, Path] | str | Path, n: int = 256, seed: int = 2024,
                   domains: tuple[str, ...] = DOMAINS, shared_dir: Path | None = None, log=print,
                   gel: str = "linear") -> dict:
    """Every domain: simulate ``n`` contacts (``large_strain``: n / 8, the costly solve), evaluate
    each model (label -> ONNX path; one path: labelled "model") and the physics lift; the
    frictionless domains' truth from the ``gel`` law (module docstring)."""
    import time

    from tactile_deploy.pad.asset import load_pad

    if not isinstance(models, dict):
        models = {"model": Path(models)}
    n_plane = load_pad().n_plane
    out = {"models": {k: str(v) for k, v in models.items()}, "seed": seed, "gel": gel,
           "metrics": "training/metrics.py: per-node Euclidean error, um; deepest node in % of its true depth",
           "domains": {}}
    for d in domains:
        t0 = time.perf_counter()
        try:
            data = simulate_domain(d, n if d != "large_strain" else max(8, n // 8), seed, shared_dir, gel)
        except DomainUnavailable as e:
            out["domains"][d] = {"unavailable": str(e)}
            log(f"{d}: not evaluated: {e}")
            continue
        preds = {label: onnx_displacements(path, data.depth_mm) for label, path in models.items()}
        preds[PHYSICS_LIFT] = physics_lift(data.depth_mm)
        res = evaluate_domain(data, preds, n_plane)
        res["seconds"] = time.perf_counter() - t0
        res["redrawn_contacts"] = data.redrawn
        out["domains"][d] = res
        log(f"{d} [{res['n_samples']} contacts, {data.redrawn} redrawn, {res['seconds']:.0f} s]: " + "; ".join(
            f"{name} patch {m['contact_patch_rmse_um']:.1f} um, deepest {m['deepest_node_error_pct']['mean']:+.2f} % "
            f"(|.| {m['deepest_node_error_pct']['mean_abs']:.2f}), all {m['all_node_rmse_um']:.1f} um"
            for name, m in res["methods"].items()))
    return out


def markdown_table(report: dict, model: str | None = None) -> str:
    """The report as one markdown table: a row per domain, the model's figures with the physics
    lift's beside them, and whether the domain's target is met."""
    labels = [k for k in report["models"]] if model is None else [model]
    lines = []
    for label in labels:
        lines += [
            f"| domain (contacts) | contact patch um: {label} / lift | deepest node %: {label} / lift (mean, signed) "
            f"| all nodes um: {label} / lift | lift / {label} (patch) | target |",
            "|---|---|---|---|---|---|",
        ]
        for d, res in report["domains"].items():
            if "unavailable" in res:
                lines.append(f"| {DOMAIN_LABELS[d]} | not measured: {res['unavailable']} | | | | |")
                continue
            m, p = res["methods"][label], res["methods"][PHYSICS_LIFT]
            gel = ", neo-Hookean gel" if report.get("gel") == "neo-hookean" and d in FRICTIONLESS_DOMAINS else ""
            lines.append(
                f"| {DOMAIN_LABELS[d]}{gel} ({res['n_samples']}) | **{m['contact_patch_rmse_um']:.1f}** / {p['contact_patch_rmse_um']:.1f} "
                f"| {m['deepest_node_error_pct']['mean']:+.1f} / {p['deepest_node_error_pct']['mean']:+.1f} "
                f"| {m['all_node_rmse_um']:.1f} / {p['all_node_rmse_um']:.1f} | {m['lift_ratio']:.2f}x "
                f"| {target_text(d, m)} |"
            )
        lines.append("")
    return "\n".join(lines).rstrip() + "\n"


def target_text(domain: str, m: dict) -> str:
    """'met' or 'not met (...)' against :data:`TARGETS`."""
    patch_max, deepest_max, ratio_min = TARGETS[domain]
    misses, goals = [], [f"patch <= {patch_max:g} um"]
    if m["contact_patch_rmse_um"] > patch_max:
        misses.append("patch")
    if deepest_max is not None:  # no "|" in the text: it goes into markdown table cells
        goals.append(f"deepest node within {deepest_max:g} % (mean absolute)")
        if m["deepest_node_error_pct"]["mean_abs"] > deepest_max:
            misses.append(f"deepest node {m['deepest_node_error_pct']['mean_abs']:.2f} %")
    if ratio_min is not None:
        goals.append(f">= {ratio_min:g}x the lift")
        if (m.get("lift_ratio") or 0) < ratio_min:
            misses.append("ratio")
    return f"{', '.join(goals)}: " + ("met" if not misses else f"**not met** ({', '.join(misses)})")
