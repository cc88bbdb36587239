"""Presses of virtual units on their imaging grids: rectified frames, their features and true depth.

For each unit: its imaging grid (the camera's view, the whole box of model-grid cells it sees,
not trimmed to fast sizes: :func:`tactile_deploy.imaging.imaging_grid.imaging_grid`), the rectified no-contact frame, then
presses drawn by :class:`PressMix`: spheres (radii ``RADII_MM``, depth up to 1 mm and 0.6 R,
centres anywhere with at least half the contact radius inside the view), the indenter library's
shapes (``tactile-deploy indenters list``) and procedural faces of many kinds and sizes
(:mod:`.shapes`: flats, holes, lines, dots, curved parts, edges reaching beyond the view, relief),
depth ``DEPTH_RANGE_MM``, any rotation, centres inside the view; each rectified exactly as the
runtime does (:class:`~tactile_deploy.runtime.pipeline.Rectifier`, 2 x 2 samples per cell), and
the surface the frame was shaded from, area-averaged onto the imaging grid.

The presses are kept compact (8-bit frames, the per-frame illumination offset, the unit's
reference and cell positions); :func:`readout_features` turns them into the read-out's input
exactly as :class:`~tactile_deploy.imaging.learned_readout.FeatureMaker` does at run time, in
numpy alone (so that training can run where the project's other dependencies are not installed).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Ball radii pressed, mm.
RADII_MM = (1.5, 2.0, 3.0, 4.0, 6.0)
#: Press depth range, mm (the upper end is also capped at 0.6 x the radius for balls).
DEPTH_RANGE_MM = (0.15, 1.0)
#: Grey levels that map to 1.0 in the colour channels, and mm that map to 1.0 in the position
#: channels (the values of :mod:`tactile_deploy.imaging.learned_readout`, checked by a test).
COLOUR_SCALE_GREY = 64.0
POSITION_SCALE_MM = 17.5
SATURATION_LEVEL = 254


@dataclass(frozen=True)
class PressMix:
    """Shares of the presses: balls, the indenter library's shapes, procedural faces (sum 1)."""

    balls: float = 0.5
    library: float = 0.5
    procedural: float = 0.0

    def __post_init__(self):
        s = (self.balls, self.library, self.procedural)
        if min(s) < 0 or abs(sum(s) - 1.0) > 1e-9:
            raise ValueError(f"press shares must be >= 0 and sum to 1, got {s}")


@dataclass
class UnitPresses:
    """Presses of one unit on its imaging grid (H, W cells).

    images : (N, H, W, 3) uint8 rectified frames. offsets : (N, 3) float32 per-frame illumination
    offset (grey levels, :func:`~tactile_deploy.imaging.shading.frame_offset`). reference :
    (H, W, 3) uint8 rectified no-contact frame. xy_mm : (2, H, W) float32 sensor-frame x and y of
    the cell centres, mm. depth_mm : (N, H, W) float32 true depth. pitch_mm : grid pitch, mm.
    kinds : (N,) str, "ball", "library" or "procedural".
    """

    images: np.ndarray
    offsets: np.ndarray
    reference: np.ndarray
    xy_mm: np.ndarray
    depth_mm: np.ndarray
    pitch_mm: float
    kinds: np.ndarray

    @property
    def features(self) -> np.ndarray:
        """(N, 11, H, W) float32 read-out features (:func:`readout_features`)."""
        return readout_features(self.images, self.offsets, self.reference, self.xy_mm)


def readout_features(images, offsets, reference, xy_mm) -> np.ndarray:
    """Read-out features (N, 11, h, w) float32 of rectified frames (N, h, w, 3) uint8 with their
    offsets (N, 3) grey, the reference (h, w, 3) uint8 and cell positions (2, h, w) mm: the
    definition of :class:`~tactile_deploy.imaging.learned_readout.FeatureMaker`."""
    img = np.asarray(images)
    ref = np.asarray(reference).astype(np.float32)
    gain = ref.reshape(-1, 3).mean(0) / np.maximum(ref, 1.0)
    diff = img.astype(np.float32) - ref - np.asarray(offsets, np.float32)[:, None, None, :]
    diff *= gain / COLOUR_SCALE_GREY
    sat = (img >= SATURATION_LEVEL).astype(np.float32)
    n = len(img)
    fixed = np.concatenate([np.moveaxis(ref / 255.0, -1, 0),
                            np.asarray(xy_mm, np.float32) / POSITION_SCALE_MM], 0)
    return np.concatenate([np.moveaxis(diff, -1, 1), np.moveaxis(sat, -1, 1),
                           np.broadcast_to(fixed, (n, *fixed.shape))], 1).astype(np.float32)


def unit_presses(config, n: int, rng: np.random.Generator, simulator=None,
                 mix: PressMix = PressMix()) -> tuple[UnitPresses, object]:
    """``n`` presses of the virtual unit ``config`` drawn by ``mix``; returns (presses, the
    unit's simulator, to share with the next unit of the same pad)."""
    from tactile_deploy.imaging.camera_mapping import grid_centres_mm
    from tactile_deploy.imaging.imaging_grid import readout_grid, with_grid
    from tactile_deploy.imaging.shading import frame_offset
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

    from .shapes import random_indenter

    sensor = VirtualSensor(config, simulator=simulator)
    sensor.prepare()
    camera = with_grid(config.optics.camera, readout_grid(config.optics.camera))
    grid = camera.grid
    rect = Rectifier(camera, 2)
    to_grid = GridResampler(sensor.renderer.grid, grid)

    def rectified(frame):
        return resample_to_grid(rectify_frame(frame, rect), rect)

    reference = rectified(sensor.renderer.reference_frame(rng))
    balls = {r: AnalyticSphere(r) for r in RADII_MM}
    shapes = list_indenters()
    shares = np.array([mix.balls, mix.library, mix.procedural])
    images, offsets, depths, kinds = [], [], [], []
    while len(images) < n:
        kind = ("ball", "library", "procedural")[int(rng.choice(3, p=shares))]
        if kind == "ball":
            radius = float(rng.choice(RADII_MM))
            indenter = balls[radius]
            depth = rng.uniform(DEPTH_RANGE_MM[0], min(DEPTH_RANGE_MM[1], 0.6 * radius))
            margin = 0.5 * math.sqrt(2 * radius * depth)
            theta = 0.0
        else:
            indenter = (shapes[int(rng.integers(len(shapes)))] if kind == "library"
                        else random_indenter(rng))
            depth = rng.uniform(*DEPTH_RANGE_MM)
            margin, theta = 0.0, float(rng.uniform(0.0, 360.0))
        x = rng.uniform(grid.x_min_mm + margin, grid.x_max_mm - margin)
        y = rng.uniform(grid.y_min_mm + margin, grid.y_max_mm - margin)
        try:
            out = sensor.press(indenter, ContactPose(x_mm=x, y_mm=y, theta_deg=theta,
                                                     depth_mm=depth), rng, truth=False)
        except ContactError:
            continue
        image = rectified(out.frame)
        images.append(image)
        offsets.append(frame_offset(image, reference))
        depths.append(to_grid(np.asarray(out.surface_depth_mm, np.float32)))
        kinds.append(kind)
    x, y = grid_centres_mm(grid)
    return (UnitPresses(np.stack(images), np.array(offsets, np.float32), reference,
                        np.stack([x, y]).astype(np.float32), np.stack(depths), grid.pitch_x_mm,
                        np.array(kinds)),
            getattr(sensor, "simulator", None))
