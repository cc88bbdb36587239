"""Checks of contact solutions shared by the tests: a resolved solution against its indenter's
surface (no penetration anywhere on the continuous surface, no tensile traction, gap and force
complementary at every loaded node and feature point), and how far a pad-mesh solution is from
neo-Hookean equilibrium."""

from __future__ import annotations

import numpy as np


def check_resolved_contact(sol, field, geometric: bool, label: str,
                           max_penetration_mm: float | None = 10e-3) -> tuple[float, float]:
    """Assert the contact conditions of the truth solution ``sol`` against the intrusion
    ``field`` (indenter surface depth, mm, sensor frame; ``geometric``: gaps at the current
    positions): penetration of the continuous surface at most ``max_penetration_mm`` (None:
    measured, not checked), no tensile traction, gap and force complementary. Returns
    (largest penetration mm, deepest surface point mm)."""
    from tactile_deploy.fem.truth import surface_penetration

    n = sol.mesh.n_plane
    pen, _ = surface_penetration(sol, field, pitch_mm=0.01, geometric=geometric)
    tip_depth = -sol.vertices_mm[:n, 2].min()
    print(f"{label}: largest penetration {pen * 1e3:.2f} um, deepest surface point "
          f"{tip_depth:.5f} mm, force {sol.force_n:.4f} N")
    # 10 um anywhere, vertically, on a 10 um grid and at every node
    if max_penetration_mm is not None:
        assert pen <= max_penetration_mm
    assert np.all(sol.normal_force_n >= 0)  # no tensile traction
    # gap and force are complementary at every node
    X = sol.mesh.vertices[:n]
    xy = X[:, :2] + (sol.displacements_mm[:n, :2] if geometric else 0.0)
    gap = -field(xy) - sol.vertices_mm[:n, 2]
    gap = np.where(np.isfinite(gap), gap, 1.0)
    # (a sensing node's own normal force, and a feature point's force; the points' forces reach
    # their triangle's corners, which may lie below the indenter between its features)
    own = sol.info["node_normal_force_n"] > 1e-6 * sol.force_n
    assert np.all(np.abs(gap[own]) < 1e-3)
    loaded = sol.info["point_force_n"] > 1e-6 * sol.force_n
    assert np.all(np.abs(sol.info["point_gap_mm"][loaded]) < 1e-3)
    return pen, tip_depth


def neo_hookean_imbalance(displacement_mm: np.ndarray, contact_mask: np.ndarray, nu: float = 0.48) -> float:
    """Largest neo-Hookean internal force on an unloaded free dof of the shipped pad (every free
    dof but the contact nodes' z) over the contact's total force: ~0 for a frictionless
    neo-Hookean equilibrium. ``displacement_mm`` (5380, 3), ``contact_mask`` (n_plane,) bool."""
    from tactile_deploy.fem.constraints import SENSOR_SUPPORTS, build_dof_map
    from tactile_deploy.fem.hyperelastic import NeoHookeanGel
    from tactile_deploy.pad.asset import load_pad

    pad = load_pad()
    gel = NeoHookeanGel(pad.vertices, pad.tets, 1.0, nu)
    dofs = build_dof_map(pad, SENSOR_SUPPORTS)
    unloaded = np.ones(dofs.T.shape[1], bool)
    unloaded[dofs.z_col[pad.sensing_nodes[contact_mask]]] = False
    f = dofs.T.T @ gel.forces(displacement_mm.astype(np.float64)).ravel()
    return float(np.abs(f[unloaded]).max() / abs(f[~unloaded].sum()))
