"""A contact sheet: one simulated depth map per indenter, for the docs and for eyeballing."""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from tactile_deploy.atomic import atomic_path
from tactile_deploy.fem.material import Material
from tactile_deploy.indenters import ContactPose, get_indenter
from tactile_deploy.simulation.contact import simulate_contact


def contact_sheet(
    indenters: list[str],
    out: str | os.PathLike,
    depth_mm: float = 1.0,
    theta_deg: float = 20.0,
    material: Material = Material(),
    columns: int = 8,
    labels: list[str] | None = None,
) -> Path:
    """Simulate each indenter pressed at the pad centre and tile the depth maps into a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = math.ceil(len(indenters) / columns)
    fig, axes = plt.subplots(rows, columns, figsize=(1.9 * columns, 2.1 * rows), squeeze=False)
    pose = ContactPose(x_mm=0.0, y_mm=0.0, theta_deg=theta_deg, depth_mm=depth_mm)
    for ax, name, label in zip(axes.flat, indenters, labels or indenters):
        sample = simulate_contact(get_indenter(name), pose, material)
        ax.imshow(sample.depth_mm, cmap="magma", vmin=0.0, vmax=depth_mm, extent=(-17.5, 17.5, -17.5, 17.5))
        ax.set_title(f"{label}\n{sample.force_n:.2f} N", fontsize=7)
        ax.set_xticks([])
        ax.set_yticks([])
    for ax in list(axes.flat)[len(indenters):]:
        ax.axis("off")
    fig.suptitle(
        f"Simulated depth maps (mm, 0 to {depth_mm:g}), indenters at the centre, depth {depth_mm:g} mm, "
        f"E {material.E_mpa:g} MPa, nu {material.nu:g}, {material.friction}",
        fontsize=9,
    )
    fig.tight_layout()
    out = Path(out)
    with atomic_path(out) as tmp:
        fig.savefig(tmp, dpi=70)
    plt.close(fig)
    return out
