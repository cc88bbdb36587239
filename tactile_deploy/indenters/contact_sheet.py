"""Contact sheet of indenter pressing surfaces: one envelope heightmap per indenter.

Regenerate the documentation figure with::

    python -m tactile_deploy.indenters.contact_sheet docs/img/indenter_library.png
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from tactile_deploy.atomic import atomic_path
from tactile_deploy.indenters.library import get_indenter, list_indenters

#: Half-width (mm) of the square shown for every indenter (library features lie within 12 mm).
VIEW_HALF_WIDTH_MM = 12.5


def envelope_image(indenter, relief_mm: float = 2.0, pixels: int = 200) -> np.ma.MaskedArray:
    """Envelope of ``indenter`` (mm) on a ``pixels`` x ``pixels`` grid over
    +-VIEW_HALF_WIDTH_MM (indenter frame; row 0 at -y), masked where higher than ``relief_mm``
    or absent."""
    axis = np.linspace(-VIEW_HALF_WIDTH_MM, VIEW_HALF_WIDTH_MM, pixels)
    gx, gy = np.meshgrid(axis, axis, indexing="xy")
    h = indenter.envelope_mm(np.stack([gx.ravel(), gy.ravel()], axis=1)).reshape(gx.shape)
    return np.ma.masked_where(~(h <= relief_mm), h)


def render_contact_sheet(
    path: str | Path,
    names: list[str] | None = None,
    relief_mm: float = 2.0,
    columns: int = 6,
    pixels_per_panel: int = 200,
) -> Path:
    """Draw the envelope of each named indenter (default: the whole library) and save a PNG.

    Each panel shows the indenter frame over +-VIEW_HALF_WIDTH_MM (x right, y up, mm); colour is
    the height of the pressing surface above its lowest point, 0 to ``relief_mm`` (dark = first
    contact), white where it is higher or absent. The dashed circle (radius 12 mm) bounds where
    every library pressing surface lies.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(names) if names is not None else list_indenters()
    half = VIEW_HALF_WIDTH_MM
    rows = -(-len(names) // columns)
    fig, axes = plt.subplots(rows, columns, figsize=(1.45 * columns + 0.6, 1.6 * rows + 0.7),
                             squeeze=False)
    fig.subplots_adjust(left=0.01, right=0.88, bottom=0.01, top=1 - 0.75 / (1.6 * rows + 0.7),
                        wspace=0.06, hspace=0.32)
    cmap = plt.get_cmap("viridis").with_extremes(bad="white")
    image = None
    for ax, name in zip(axes.ravel(), names):
        ind = get_indenter(name)
        h = envelope_image(ind, relief_mm, pixels_per_panel)
        image = ax.imshow(h, origin="lower", extent=(-half, half, -half, half), cmap=cmap,
                          vmin=0.0, vmax=relief_mm, interpolation="nearest")
        ax.add_patch(plt.Circle((0, 0), 12.0, fill=False, ls="--", lw=0.5, color="0.7"))
        ax.set_title(f"{name}\n({ind.kind})", fontsize=7)
        ax.set_xticks([])
        ax.set_yticks([])
    for ax in axes.ravel()[len(names):]:
        ax.axis("off")
    fig.suptitle(f"Pressing surfaces: height above the lowest point, {2 * half:g} mm windows",
                 fontsize=9)
    if image is not None:
        bar = fig.colorbar(image, cax=fig.add_axes((0.9, 0.25, 0.02, 0.5)))
        bar.set_label("height above lowest point, mm", fontsize=7)
        bar.ax.tick_params(labelsize=6)
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    return path


if __name__ == "__main__":
    print(render_contact_sheet(sys.argv[1] if len(sys.argv) > 1 else "indenter_library.png"))
