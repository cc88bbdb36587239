"""Depth maps as a sensor's depth pipeline reports them: the surface seen through the view, then
the read-out's own departures.

A virtual sensor's depth-map truth (:meth:`VirtualSensor.depth_map`) is the FEM's surface on the
standard 128 x 128 grid. A depth pipeline calibrated on the sensor's *nominal* camera (its optics
before any effect) reports something else when the sensor has

* **optics effects that move the view** (``lens_distortion``, ``pixel_scale``): the pipeline
  maps camera pixels to the sensing plane with the nominal mapping ``N`` while the real optics
  image the plane with ``R``; the surface point q is imaged at ``R(q)`` and reported at the plane
  point ``p = N^-1(R(q))``. The map at p shows the surface at ``q(p)`` (each effect's
  :meth:`~tactile_deploy.sensors.effects.base.Effect.view_points`), with its depth scaled by the
  view's local stretch ``det(dq/dp) ** (-gamma / 2)``: gamma = 1 for a pipeline that integrates
  measured slopes over the calibrated grid (slopes are physical, the grid is stretched), gamma
  = 0 for a map that is only resampled;
* **read-out effects** (stage ``readout``: a depth gain across the field, blur, saturated
  shading): the pipeline's own error, applied to the map last.

:func:`reported_depth_map` applies both, effect by effect in the sensor's order; outside the
camera's view (plane points whose pixel is off the frame) the view leaves the map as it is.
Frames need none of this: a virtual sensor's frames are rendered through its real optics.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.ndimage import map_coordinates

#: Smallest local stretch det(dq/dp) the depth gain follows (a folding view is clipped).
MIN_STRETCH = 0.25


class ViewWarp:
    """The change of a (H, W) depth map seen through a view ``q(p)``.

    q_of_p : maps plane points (k, 2) mm to the surface points (k, 2) mm the map shows there.
    camera : the :class:`~tactile_deploy.camera.depth.DepthCamera` of the maps (its grid).
    inside : (H, W) bool, pixels whose plane point the camera sees (elsewhere: unchanged), or
        None (everywhere). gain_exponent : gamma above.
    """

    def __init__(self, q_of_p: Callable[[np.ndarray], np.ndarray], camera,
                 inside: np.ndarray | None = None, gain_exponent: float = 1.0):
        centres = camera.pixel_centres_mm()  # (H, W, 2), image rows
        h, w = centres.shape[:2]
        p = centres.reshape(-1, 2)
        keep = np.ones(len(p), bool) if inside is None else np.asarray(inside, bool).ravel()
        q = p.copy()
        with np.errstate(all="ignore"):
            q[keep] = q_of_p(p[keep])
        ok = np.all(np.isfinite(q), axis=1)
        q[~ok] = p[~ok]
        q = q.reshape(h, w, 2)
        pitch = camera.pitch_mm
        dqx_dc = np.gradient(q[..., 0], axis=1) / pitch
        dqy_dc = np.gradient(q[..., 1], axis=1) / pitch
        dqx_dr = -np.gradient(q[..., 0], axis=0) / pitch  # rows run along -y
        dqy_dr = -np.gradient(q[..., 1], axis=0) / pitch
        det = dqx_dc * dqy_dr - dqy_dc * dqx_dr
        gain = np.maximum(det, MIN_STRETCH) ** (-0.5 * float(gain_exponent))
        gain[~(keep & ok).reshape(h, w)] = 1.0
        half = camera.half_extent_mm
        #: (2, H, W) fractional (row, column) of q(p) in the map; (H, W) depth gain.
        self.coords = np.stack([(half - q[..., 1]) / pitch - 0.5, (q[..., 0] + half) / pitch - 0.5])
        self.gain = gain
        #: largest displacement |q - p| over the view, mm
        self.max_shift_mm = float(np.abs(q.reshape(-1, 2) - p).max())

    def __call__(self, depth_mm: np.ndarray) -> np.ndarray:
        """The map ``depth_mm`` (H, W) mm as the pipeline reports it, (H, W) float64."""
        d = np.asarray(depth_mm, np.float64)
        return self.gain * map_coordinates(d, self.coords, order=1, mode="constant", cval=0.0)


def camera_view_mask(camera_mapping, depth_camera) -> np.ndarray:
    """(H, W) bool: pixels of the depth grid whose plane point ``camera_mapping`` images inside
    its frame."""
    from tactile_deploy.imaging.camera_mapping import sensor_mm_to_pixels

    p = depth_camera.pixel_centres_mm().reshape(-1, 2)
    uv = sensor_mm_to_pixels(p, camera_mapping)
    width, height = camera_mapping.image_size
    inside = ((uv[:, 0] >= -0.5) & (uv[:, 0] <= width - 0.5) & (uv[:, 1] >= -0.5)
              & (uv[:, 1] <= height - 0.5))
    return inside.reshape(depth_camera.pixel_centres_mm().shape[:2])


def effect_view_warp(effect, camera_mapping, depth_camera, inside=None) -> ViewWarp | None:
    """The :class:`ViewWarp` of one optics effect seen through a pipeline calibrated on the
    nominal ``camera_mapping`` (None when the effect does not move the view or is null);
    ``inside`` (H, W) bool limits it to those pixels (None: everywhere)."""
    if not getattr(effect, "moves_view", False) or effect.is_null:
        return None
    return ViewWarp(lambda p: effect.view_points(p, camera_mapping), depth_camera, inside,
                    effect.depth_gain_exponent)


class DepthReadout:
    """What a depth pipeline calibrated on a sensor's nominal camera reports for the FEM's maps:
    :meth:`__call__` (module docstring).

    effects : the sensor's effects (:class:`~tactile_deploy.sensors.effects.base.Effect`, in
    order); nominal_camera : the ``CameraMapping`` the pipeline was calibrated on (the sensor
    config's optics camera, before effects); view : apply the view effects (False for maps
    imaged from the sensor's own frames, which already went through its optics).
    """

    def __init__(self, effects, nominal_camera, view: bool = True):
        from tactile_deploy.camera.depth import DepthCamera

        self.camera = DepthCamera()
        self.xy_mm = self.camera.pixel_centres_mm()
        self.warps = []
        if view:
            for e in effects:
                if getattr(e, "moves_view", False) and not e.is_null:
                    self.warps.append(effect_view_warp(e, nominal_camera, self.camera))
        self.readout = [e for e in effects if e.stage == "readout" and not e.is_null]

    @classmethod
    def of_sensor(cls, sensor, view: bool = True) -> DepthReadout:
        """The read-out of a :class:`~tactile_deploy.sensors.virtual.VirtualSensor`."""
        return cls(sensor.effects, sensor.config.optics.camera, view)

    @property
    def is_identity(self) -> bool:
        return not self.warps and not self.readout

    def __call__(self, depth_mm: np.ndarray) -> np.ndarray:
        """(H, W) float64 mm: the reported map of the surface's map ``depth_mm``."""
        d = np.asarray(depth_mm, np.float64)
        for w in self.warps:
            d = w(d)
        for e in self.readout:
            d = np.asarray(e.readout_map(d, self.xy_mm), np.float64)
        return d


def reported_depth_map(sensor, depth_mm: np.ndarray, view: bool = True) -> np.ndarray:
    """The map a depth pipeline calibrated on ``sensor``'s nominal camera reports for the
    surface's map ``depth_mm`` (see :class:`DepthReadout`; build one to reuse its warps)."""
    return DepthReadout.of_sensor(sensor, view)(depth_mm)
