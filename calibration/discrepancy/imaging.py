"""Measured RGB frames: the sensor model's contacts seen through the same imaging pipeline.

A depth map made from frames by a shading pipeline is not the surface: the colour-to-slope table
and the integration have their own errors, which depend on the contact, and its noise is the
camera's noise integrated (smooth, correlated from pixel to pixel). Comparing such maps with the
FEM's surface would call the pipeline's error a missing effect. So with measured frames every
map of the sensor model (the base, each candidate's tabulated values, the exact re-simulations)
is made the way the measured maps were::

    contact -> the model's (or a variant's) frame: FEM, shading, blur
            -> camera noise, ``n_mean`` draws -> the plugin's imaging pipeline -> depth maps
            -> their mean: the expected imaged map (128, 128) mm

and the camera noise through the pipeline is sampled the same way: ``n_noise`` further draws,
each minus the mean, are realisations of the residual's noise (the null distribution of every
statistic of :mod:`tactile_deploy.calibration.discrepancy.selection`, instead of white noise).

Common random numbers: the draws of one contact use the same generators for the model and for
every variant, so a candidate's change is not buried under the difference of two noise draws.
The camera noise is the sensor model's (its optics' read and shot noise).
"""

from __future__ import annotations

import zlib

import numpy as np

from tactile_deploy.indenters import ContactPose

#: Noise draws averaged into one imaged map, and draws kept as noise realisations per contact.
N_MEAN = 6
N_NOISE = 8


class FrameImaging:
    """The imaging path of measured frames applied to the sensor model (module docstring).

    pipeline : an object with ``frame_to_depth(frame (H, W, 3) uint8) -> (128, 128) mm`` (the
    runtime's :class:`~tactile_deploy.runtime.pipeline.ImagingPipeline` of the sensor plugin);
    n_mean, n_noise : draws per imaged map and noise realisations per contact; seed : of the
    noise draws.
    """

    def __init__(self, pipeline, n_mean: int = N_MEAN, n_noise: int = N_NOISE, seed: int = 0):
        if n_mean < 1 or n_noise < 2:
            raise ValueError(f"n_mean must be >= 1 and n_noise >= 2, got {n_mean}, {n_noise}")
        self.pipeline = pipeline
        self.n_mean = int(n_mean)
        self.n_noise = int(n_noise)
        self.seed = int(seed)

    def _rngs(self, indenter_name: str, pose: ContactPose, first: int, count: int):
        key = zlib.crc32(repr((indenter_name, pose.x_mm, pose.y_mm, pose.theta_deg,
                               pose.depth_mm)).encode())
        return [np.random.default_rng([self.seed, key, first + k]) for k in range(count)]

    def _image(self, frames) -> np.ndarray:
        return np.stack([np.asarray(self.pipeline.frame_to_depth(f), np.float64)
                         for f in frames])

    def depth_map(self, sensor, indenter, indenter_name: str, pose: ContactPose,
                  noise_pose: ContactPose | None = None) -> tuple[np.ndarray, float]:
        """``(expected imaged map (128, 128) float64 mm, force N)`` of ``sensor`` (the model or
        a variant) pressed by ``indenter`` at ``pose``; the noise draws are those of
        ``noise_pose`` (default ``pose``): finite differences in the pose share them."""
        frames, force = sensor.press_frames(indenter, pose, self._rngs(
            indenter_name, noise_pose or pose, 0, self.n_mean))
        return self._image(frames).mean(axis=0), force

    def noise_maps(self, sensor, indenter, indenter_name: str, pose: ContactPose,
                   mean_map: np.ndarray) -> np.ndarray:
        """(n_noise, 128, 128) float32 mm: imaged maps of further noise draws minus
        ``mean_map`` (the residual's noise, including the mean's own: variance
        ``sigma^2 (1 + 1/n_mean)`` per pixel, as a measured map's residual has)."""
        frames, _ = sensor.press_frames(indenter, pose, self._rngs(
            indenter_name, pose, self.n_mean, self.n_noise))
        return (self._image(frames) - mean_map[None]).astype(np.float32)
