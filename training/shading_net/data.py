"""Ball presses of virtual units on their imaging grids: features and true depth.

For each unit: its imaging grid (the camera's view, cells of the model grid's pitch:
:func:`tactile_deploy.imaging.imaging_grid.imaging_grid`), the rectified no-contact frame, then
presses: half of them spheres (radii ``RADII_MM``, depth up to 1 mm and 0.6 R, centres anywhere
with at least half the contact radius inside the view), half the indenter library's shapes
(primitives and objects with edges, corners and fine relief: ``tactile-deploy indenters list``;
depth ``DEPTH_RANGE_MM``, any rotation, centres inside the view), each rectified exactly as the runtime does
(:class:`~tactile_deploy.runtime.pipeline.Rectifier`, 2 x 2 samples per cell), and the surface
the frame was shaded from, area-averaged onto the imaging grid.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Ball radii pressed, mm.
RADII_MM = (1.5, 2.0, 3.0, 4.0, 6.0)
#: Press depth range, mm (the upper end is also capped at 0.6 x the radius).
DEPTH_RANGE_MM = (0.15, 1.0)


@dataclass
class UnitPresses:
    """features : (N, 11, H, W) float32 (:mod:`tactile_deploy.imaging.learned_readout`);
    depth_mm : (N, H, W) float32, true depth on the unit's imaging grid; pitch_mm : grid pitch."""

    features: np.ndarray
    depth_mm: np.ndarray
    pitch_mm: float


def unit_presses(config, n: int, rng: np.random.Generator, simulator=None) -> tuple[UnitPresses, object]:
    """``n`` ball presses of the virtual unit ``config``; returns (presses, the unit's simulator,
    to share with the next unit of the same pad)."""
    from tactile_deploy.imaging.imaging_grid import imaging_grid, with_grid
    from tactile_deploy.imaging.learned_readout import FeatureMaker
    from tactile_deploy.indenters import AnalyticSphere, ContactPose
    from tactile_deploy.indenters.library import list_indenters
    from tactile_deploy.runtime.pipeline import (
        GridResampler,
        Rectifier,
        rectify_frame,
        resample_to_grid,
    )
    from tactile_deploy.sensors.virtual import VirtualSensor
    from tactile_deploy.simulation.contact import ContactError

    sensor = VirtualSensor(config, simulator=simulator)
    sensor.prepare()
    camera = with_grid(config.optics.camera, imaging_grid(config.optics.camera))
    grid = camera.grid
    rect = Rectifier(camera, 2)
    to_grid = GridResampler(sensor.renderer.grid, grid)

    def rectified(frame):
        return resample_to_grid(rectify_frame(frame, rect), rect)

    features = FeatureMaker(rectified(sensor.renderer.reference_frame(rng)), grid)
    balls = {r: AnalyticSphere(r) for r in RADII_MM}
    shapes = list_indenters()
    feats, depths = [], []
    while len(feats) < n:
        if rng.random() < 0.5:
            radius = float(rng.choice(RADII_MM))
            indenter = balls[radius]
            depth = rng.uniform(DEPTH_RANGE_MM[0], min(DEPTH_RANGE_MM[1], 0.6 * radius))
            margin = 0.5 * math.sqrt(2 * radius * depth)
            theta = 0.0
        else:
            indenter = shapes[int(rng.integers(len(shapes)))]
            depth = rng.uniform(*DEPTH_RANGE_MM)
            margin, theta = 0.0, float(rng.uniform(0.0, 360.0))
        x = rng.uniform(grid.x_min_mm + margin, grid.x_max_mm - margin)
        y = rng.uniform(grid.y_min_mm + margin, grid.y_max_mm - margin)
        try:
            out = sensor.press(indenter, ContactPose(x_mm=x, y_mm=y, theta_deg=theta,
                                                     depth_mm=depth), rng, truth=False)
        except ContactError:
            continue
        feats.append(features(rectified(out.frame)))
        depths.append(to_grid(np.asarray(out.surface_depth_mm, np.float32)))
    return (UnitPresses(np.stack(feats), np.stack(depths), grid.pitch_x_mm),
            getattr(sensor, "simulator", None))
