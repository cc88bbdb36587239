"""Recordings of a virtual sensor in the layouts the calibrations read: FOTS-style ball presses
with their contact circles (:func:`record_ball_presses`, written by
:meth:`BallPressRecording.save` as ``background.png``, ``NNNN.png`` and ``annotate.csv``) and a
pressed pin grid with the true pin positions (:func:`record_target_frames`).

Frames are RGB (H, W, 3) uint8 in raw camera pixels; poses and points are in the sensor frame
(mm).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from tactile_deploy.atomic import atomic_path, write_text
from tactile_deploy.imaging.camera_mapping import sensor_mm_to_pixels
from tactile_deploy.indenters import AnalyticSphere, ContactPose
from tactile_deploy.indenters.pin_grid import PinGrid
from tactile_deploy.sensors.virtual import VirtualSensor


@dataclass
class BallPressRecording:
    """Ball presses of a virtual sensor, in the format of the real FOTS recordings.

    reference : (H, W, 3) uint8; frames : (N, H, W, 3) uint8; circles_px : (N, 3) float64
    (column, row, contact radius) raw px; poses : N commanded poses; contact_radius_mm : (N,);
    ball_radius_mm; depth_mm : (N, 128, 128) float32 true depth maps (evaluation only).
    """

    reference: np.ndarray
    frames: np.ndarray
    circles_px: np.ndarray
    poses: list
    contact_radius_mm: np.ndarray
    ball_radius_mm: float
    depth_mm: np.ndarray

    def save(self, folder: str | Path) -> None:
        """Write ``background.png``, ``0001.png`` ... and ``annotate.csv`` (FOTS layout)."""
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)

        def png(path, img):
            with atomic_path(path) as tmp:
                if not cv2.imwrite(str(tmp), np.ascontiguousarray(img[..., ::-1])):
                    raise OSError(f"could not write {path}")

        png(folder / "background.png", self.reference)
        lines = ["img_names,center_x,center_y,radius"]
        for i, (img, c) in enumerate(zip(self.frames, self.circles_px)):
            name = f"{i + 1:04d}.png"
            png(folder / name, img)
            lines.append(f"{name},{c[0]:.2f},{c[1]:.2f},{c[2]:.2f}")
        write_text(folder / "annotate.csv", "\n".join(lines) + "\n")


@dataclass
class TargetRecording:
    """Frames of a pressed pin grid: ``reference`` and ``frames`` (N, H, W, 3) uint8, the pin
    centres ``pins_mm`` (N, k, 2) in the sensor frame and their images ``pins_px`` (N, k, 2) raw
    px (through the sensor's true camera mapping), the ``poses`` and the ``target``."""

    reference: np.ndarray
    frames: np.ndarray
    pins_mm: np.ndarray
    pins_px: np.ndarray
    poses: list
    target: PinGrid


def record_ball_presses(sensor: VirtualSensor, n: int, radius_mm: float = 2.0,
                        depth_range_mm: tuple[float, float] = (0.3, 1.0), seed: int = 0,
                        margin_mm: float | None = None) -> BallPressRecording:
    """``n`` presses of a ball at random places in the view (FOTS-style recording).

    Contact circles: centre = image of the ball's axis through the sensor's true camera
    mapping, radius = equivalent radius of the region where the gel touches the ball
    (sqrt(area / pi)), converted with the mapping's mm per px at that point.
    """
    ball = AnalyticSphere(radius_mm)
    rng = np.random.default_rng([sensor.config.seed, seed, 0x62616C6C])
    margin = 1.5 * radius_mm if margin_mm is None else margin_mm
    x0, x1, y0, y1 = sensor.view_box_mm(margin)
    if x1 <= x0 or y1 <= y0:
        raise ValueError(f"a {radius_mm} mm ball with a {margin} mm margin does not fit the "
                         "view; use a smaller ball or margin")
    ref = sensor.record_reference(seed)
    frames, circles, poses, radii, depths = [], [], [], [], []
    g = sensor.renderer.grid
    cell = g.pitch_x_mm * g.pitch_y_mm
    geometry = sensor.simulator.mesh.geometry
    for i in range(n):
        for _ in range(1000):  # positions inside the view box and on the pad
            x, y = float(rng.uniform(x0, x1)), float(rng.uniform(y0, y1))
            if geometry.contains_xy(x, y, margin_mm=margin):
                break
        else:
            raise ValueError("no ball position lies both in the view and on the pad")
        pose = ContactPose(x_mm=x, y_mm=y, depth_mm=float(rng.uniform(*depth_range_mm)))
        out = sensor.press(ball, pose, np.random.default_rng([sensor.config.seed, seed, 1, i]))
        # Contact: surface within 1 um of the ball.
        reached = out.pose_reached
        zi = -ball.intrusion_mm(sensor.surface.xy_mm.reshape(-1, 2), reached).reshape(
            out.surface_depth_mm.shape)
        height = sensor.renderer.rest_height_mm - out.surface_depth_mm
        touching = np.isfinite(zi) & (height >= zi - 1e-3)
        a_mm = math.sqrt(touching.sum() * cell / math.pi)
        c = sensor_mm_to_pixels(np.array([[reached.x_mm, reached.y_mm],
                                          [reached.x_mm + a_mm, reached.y_mm]]),
                                sensor.optics.camera)
        frames.append(out.frame)
        circles.append([c[0, 0], c[0, 1], float(np.hypot(*(c[1] - c[0])))])
        poses.append(pose)
        radii.append(a_mm)
        depths.append(out.depth_mm)
    return BallPressRecording(ref, np.stack(frames), np.array(circles), poses,
                              np.array(radii), float(radius_mm), np.stack(depths))


def record_target_frames(sensor: VirtualSensor, target: PinGrid | None = None,
                         poses: Sequence[ContactPose] | None = None,
                         seed: int = 0) -> TargetRecording:
    """Frames of a pressed pin grid (default 9 x 7 pins, 2.5 mm pitch, 0.75 mm pins, centred,
    0.35 mm deep) through the full optics, with the true pin positions in mm and px."""
    target = target or PinGrid()
    poses = list(poses) if poses is not None else [ContactPose(depth_mm=0.35)]
    ref = sensor.record_reference(seed)
    frames, mm, px = [], [], []
    for i, pose in enumerate(poses):
        out = sensor.press(target, pose, np.random.default_rng([sensor.config.seed, seed, 2, i]),
                         truth=False)
        centres = target.pin_centres_mm(out.pose_reached)
        frames.append(out.frame)
        mm.append(centres)
        px.append(sensor_mm_to_pixels(centres, sensor.optics.camera))
    return TargetRecording(ref, np.stack(frames), np.stack(mm), np.stack(px), poses, target)
