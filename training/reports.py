"""Reconstruction quality of the coarsening hierarchy (the figures of docs/predictor.md).

``python -m tactile_deploy.training report-coarsening --data DATA.npz [--png FIGURE.png]`` projects fields down
to level l and back up (``Hierarchy.down_up``) and reports the relative L2 error

    e_l = ||U_0 ... U_{l-1} D_{l-1} ... D_0 f - f|| / ||f||

for a smooth field and for simulated contact displacements (all nodes, all axes), with both
down-samplings, and the floor of any level-l field interpolated with these weights (the L2
projection onto the span of the up-sampling chain).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from tactile_deploy.training.networks.coarsening import build_hierarchy


def smooth_field(vertices_mm: np.ndarray) -> np.ndarray:
    """A smooth test field (n,): wavelengths of ~30-40 mm in-plane, linear through the thickness."""
    p = vertices_mm
    return np.cos(p[:, 0] / 6.0) * np.sin(p[:, 1] / 5.0) * (p[:, 2] + 3.0) / 3.0


def coarsening_table(displacements_mm: np.ndarray) -> list[dict]:
    """Rows {level, nodes, pooling, smooth, contact, contact_floor} of relative errors.

    displacements_mm : (S, n, 3) float, mm -- simulated contacts (held-out ones).
    """
    from tactile_deploy.pad.asset import load_pad

    pad = load_pad()
    f_s = smooth_field(pad.vertices)
    u = np.moveaxis(np.asarray(displacements_mm, np.float64), 0, 1).reshape(pad.n_nodes, -1)
    rows = []
    hier = {p: build_hierarchy(pad, pooling=p) for p in ("select", "average")}
    for level in range(1, len(hier["select"].levels)):
        row = {"level": level, "nodes": hier["select"].levels[level].n_nodes}
        for p, h in hier.items():
            row[f"smooth_{p}"] = float(np.linalg.norm(h.down_up(f_s, level) - f_s) / np.linalg.norm(f_s))
            row[f"contact_{p}"] = float(np.linalg.norm(h.down_up(u, level) - u) / np.linalg.norm(u))
        if level <= 2:
            floor = hier["select"].least_squares_up(u, level)
            row["contact_floor"] = float(np.linalg.norm(floor - u) / np.linalg.norm(u))
        rows.append(row)
    return rows


def markdown_table(rows: list[dict]) -> str:
    lines = [
        "| level | nodes | smooth field, select | smooth field, average | contacts, select | contacts, average "
        "| contacts, L2 floor |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        floor = f"{r['contact_floor']:.3f}" if "contact_floor" in r else "-"
        lines.append(
            f"| {r['level']} | {r['nodes']} | {r['smooth_select']:.4f} | {r['smooth_average']:.4f} "
            f"| {r['contact_select']:.3f} | {r['contact_average']:.3f} | {floor} |"
        )
    return "\n".join(lines)


def pick_contacts(displacements_mm: np.ndarray, n_plane: int = 1076) -> list[int]:
    """Indices of a broad, a median and a narrow contact (peak |u_z| > 0.5 mm; ranked by the number
    of surface nodes above 20 % of the peak)."""
    uz = np.abs(np.asarray(displacements_mm)[:, :n_plane, 2])
    peak = uz.max(axis=1)
    ok = np.flatnonzero(peak > 0.5)
    if len(ok) == 0:
        ok = np.arange(len(uz))
    spread = (uz[ok] > 0.2 * peak[ok, None]).sum(axis=1)
    order = ok[np.argsort(spread, kind="stable")]
    return [int(order[-1]), int(order[len(order) // 2]), int(order[0])]


def coarsening_figure(displacements_mm: list[np.ndarray], path: str | Path) -> None:
    """Per contact (row): sensing-surface u_z, down-up at levels 1-3, and the error at level 1."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.tri import Triangulation

    from tactile_deploy.pad.asset import load_pad

    pad = load_pad()
    h = build_hierarchy(pad)
    m = pad.n_plane
    tri = Triangulation(pad.vertices[:m, 0], pad.vertices[:m, 1], pad.plane_triangles)
    fig, axes = plt.subplots(len(displacements_mm), 5, figsize=(16, 3.3 * len(displacements_mm)), squeeze=False)
    for row, disp in zip(axes, displacements_mm):
        uz = np.asarray(disp, np.float64)[:, 2]
        panels = [("simulated u_z", uz)]
        for level in (1, 2, 3):
            f = h.down_up(uz, level)
            e = np.linalg.norm(f - uz) / np.linalg.norm(uz)
            panels.append((f"level {level} ({h.levels[level].n_nodes} nodes): {e:.0%}", f))
        panels.append(("error at level 1", panels[1][1] - uz))
        lim = np.abs(uz[:m]).max()
        for ax, (title, f) in zip(row, panels):
            im = ax.tripcolor(tri, f[:m], shading="gouraud", cmap="RdBu_r", vmin=-lim, vmax=lim)
            ax.set_title(title, fontsize=9)
            ax.set_aspect("equal")
            ax.set_xticks([])
            ax.set_yticks([])
        for level, ax in zip((1, 2, 3), row[1:4]):
            xy = h.levels[level].plane_xy_mm
            ax.plot(xy[:, 0], xy[:, 1], "k.", ms=1.2)
        fig.colorbar(im, ax=list(row), shrink=0.8, label="u_z, mm (sensing surface)")
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100, bbox_inches="tight")
    plt.close(fig)
