"""The experiment that tells look-alike candidates apart.

Each look-alike, at its fitted parameters, is simulated on a small set of probe contacts (three
indenters of different shape, at the pad's centre and toward its edge along x and y, shallow and
deep); the probe whose depth maps differ most between the candidates (the smallest pairwise RMS
difference, so that every pair is told apart) is the experiment to run, with the difference in
units of the pixel noise and the forces the candidates predict (optical effects do not change
the force: a force gauge separates them from mechanical ones).
"""

from __future__ import annotations

import itertools

import numpy as np

from tactile_deploy.calibration.discrepancy.reproduce import ContactReproducer
from tactile_deploy.indenters import ContactPose
from tactile_deploy.sensors.config import EffectSpec

PROBE_INDENTERS = ("sphere_r4", "flat_punch", "cylinder_side")
PROBE_DEPTHS_MM = (0.4, 1.0)


def probe_contacts(reach_mm: float) -> list[tuple[str, ContactPose]]:
    """Probes: every indenter at (0, 0), (reach, 0), (0, reach), each shallow and deep."""
    out = []
    for name, (x, y), d in itertools.product(PROBE_INDENTERS,
                                             ((0.0, 0.0), (reach_mm, 0.0), (0.0, reach_mm)),
                                             PROBE_DEPTHS_MM):
        out.append((name, ContactPose(x_mm=x, y_mm=y, depth_mm=d)))
    return out


def distinguishing_experiment(repro: ContactReproducer, specs: dict[str, EffectSpec],
                              view_warps: dict, sigma_mm: float) -> dict:
    """The probe that best separates the candidates ``specs`` (name -> fitted effect).

    view_warps : name -> ViewWarp for candidates simulated through the view (None otherwise).
    Returns {"indenter", "x_mm", "y_mm", "depth_mm", "rms_difference_mm", "noise_units",
    "forces_n": {name: N}, "text"}.
    """
    mesh = repro.sensor.simulator.mesh
    reach = 0.55 * mesh.geometry.half_extent_mm
    mask = repro.pad_mask
    best = None
    for name, pose in probe_contacts(reach):
        maps, forces = {}, {}
        try:
            base, base_force = repro.depth_map(name, pose)
            for cand, spec in specs.items():
                warp = view_warps.get(cand)
                if warp is not None:
                    maps[cand], forces[cand] = warp(base), base_force
                else:
                    maps[cand], forces[cand] = repro.depth_map(name, pose, repro.variant(spec))
        except (ValueError, RuntimeError):
            continue
        diffs = [float(np.sqrt(np.mean((maps[a] - maps[b])[mask] ** 2)))
                 for a, b in itertools.combinations(maps, 2)]
        score = min(diffs) if diffs else 0.0
        if best is None or score > best[0]:
            best = (score, name, pose, forces)
    if best is None:
        return {"text": "no probe contact could be simulated for these candidates"}
    score, name, pose, forces = best
    pix = int(mask.sum())
    # noise units: the RMS difference over the pad against the noise of the pad's mean square
    units = score / sigma_mm * np.sqrt(pix)
    force_text = ", ".join(f"{k} {v:.3f} N" for k, v in forces.items())
    text = (f"press {name} at x = {pose.x_mm:.1f} mm, y = {pose.y_mm:.1f} mm to "
            f"{pose.depth_mm:.1f} mm: the candidates' depth maps differ by "
            f"{score * 1e3:.2f} um RMS over the pad ({units:.0f} x the noise of one map); "
            f"predicted forces {force_text}")
    return {"indenter": name, "x_mm": pose.x_mm, "y_mm": pose.y_mm, "depth_mm": pose.depth_mm,
            "rms_difference_mm": score, "noise_units": float(units),
            "forces_n": {k: float(v) for k, v in forces.items()}, "text": text}
