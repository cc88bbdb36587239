"""The imaging grid of a plugin: the part of the model grid that a camera sees.

The shading model runs on a grid of the sensing plane (sensor frame, mm); making it a box of
whole model-grid cells (+-17.5 mm, 128 x 128, 0.273 mm) lets the runtime area-average its depth
onto the model grid without interpolation, with depth 0 in the cells the camera does not see.
"""

from __future__ import annotations

import json

import numpy as np

from tactile_deploy.imaging.camera_mapping import (
    CameraMapping,
    OutputGrid,
    sensor_mm_to_pixels,
)


def imaging_grid(camera: CameraMapping, divisor: int = 1, margin_px: float = 2.0,
                 fast_sizes: bool = True) -> OutputGrid:
    """The largest axis-aligned box of whole model-grid cells whose corners the camera sees
    (``margin_px`` inside the image), as an OutputGrid at ``model pitch / divisor``. With
    ``fast_sizes`` it is trimmed (centred) to sizes with prime factors 2, 3 and 5 only (the
    shading model's depth integration by sine transforms is ~1.5 x faster); a learned read-out,
    which integrates nothing, reads the whole box at its own margin (:func:`readout_grid`).

    Raises ValueError when the camera sees no whole model-grid cell.
    """
    g = OutputGrid()
    xs = g.x_min_mm + np.arange(g.nx + 1) * g.pitch_x_mm
    ys = g.y_max_mm - np.arange(g.ny + 1) * g.pitch_y_mm
    cx, cy = np.meshgrid(xs, ys)
    uv = sensor_mm_to_pixels(np.stack([cx.ravel(), cy.ravel()], 1), camera).reshape(*cx.shape, 2)
    w, h = camera.image_size
    seen = ((uv[..., 0] >= margin_px) & (uv[..., 0] <= w - 1 - margin_px)
            & (uv[..., 1] >= margin_px) & (uv[..., 1] <= h - 1 - margin_px))
    inside = seen[:-1, :-1] & seen[1:, :-1] & seen[:-1, 1:] & seen[1:, 1:]   # (ny, nx) cells
    rows, cols = np.flatnonzero(inside.any(1)), np.flatnonzero(inside.any(0))
    if len(rows) == 0:
        raise ValueError("the camera sees no whole cell of the model grid (+-17.5 mm): check "
                         "the camera mapping")
    r0, r1, c0, c1 = rows[0], rows[-1], cols[0], cols[-1]
    while not inside[r0:r1 + 1, c0:c1 + 1].all():      # shed the worst side (convex view)
        bad = {"r0": (~inside[r0, c0:c1 + 1]).sum(), "r1": (~inside[r1, c0:c1 + 1]).sum(),
               "c0": (~inside[r0:r1 + 1, c0]).sum(), "c1": (~inside[r0:r1 + 1, c1]).sum()}
        side = max(bad, key=bad.get)
        r0, r1, c0, c1 = (r0 + (side == "r0"), r1 - (side == "r1"), c0 + (side == "c0"),
                          c1 - (side == "c1"))
    # trim to cell counts whose prime factors are 2, 3, 5 (fast sine transforms), centred
    for axis in (0, 1) if fast_sizes else ():
        a, b = (r0, r1) if axis == 0 else (c0, c1)
        n = b - a + 1
        keep = max(k for k in range(1, n + 1) if _smooth(k * divisor))
        a += (n - keep) // 2
        b = a + keep - 1
        if axis == 0:
            r0, r1 = a, b
        else:
            c0, c1 = a, b
    return OutputGrid(x_min_mm=float(xs[c0]), x_max_mm=float(xs[c1 + 1]),
                      y_min_mm=float(ys[r1 + 1]), y_max_mm=float(ys[r0]),
                      nx=int(c1 - c0 + 1) * divisor, ny=int(r1 - r0 + 1) * divisor)


#: Margin (pixels) of a learned read-out's grid: every whole cell inside the image's footprint
#: (pixel centres 0 .. w - 1, the footprint half a pixel wider; the rectifier replicates the
#: outermost pixels across that half pixel). The shading model keeps 2 px: its table and
#: integration were fitted there. With 2 px the GelSight Mini's read-out saw 66 x 48 cells
#: of the 68 x 50 inside its image, and contacts at the view's edge reached 0.3-0.4 mm into
#: a strip where the depth could only be carried from the edge (docs/families.md).
READOUT_MARGIN_PX = -0.5


def readout_grid(camera: CameraMapping) -> OutputGrid:
    """The imaging grid a learned read-out reads (and is trained on): the whole box of
    model-grid cells inside the camera's image (:data:`READOUT_MARGIN_PX`), not trimmed."""
    return imaging_grid(camera, margin_px=READOUT_MARGIN_PX, fast_sizes=False)


def _smooth(n: int) -> bool:
    """True when n has no prime factor above 5."""
    for p in (2, 3, 5):
        while n % p == 0:
            n //= p
    return n == 1


def with_grid(camera: CameraMapping, grid: OutputGrid) -> CameraMapping:
    """The camera mapping with another output grid (validated)."""
    doc = json.loads(camera.model_dump_json())
    doc["grid"] = grid.model_dump()
    return CameraMapping.model_validate(doc)
