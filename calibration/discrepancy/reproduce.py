"""Reproduce measured contacts in simulation, with the sensor model and variants of it.

The sensor model is a :class:`~tactile_deploy.sensors.virtual.VirtualSensor` (pad, material,
effects); a contact is reproduced by its depth-map truth (:meth:`VirtualSensor.depth_map`: the
FEM on the pad's surface Green's functions, effects applied stage by stage, the deformed mesh
rendered onto the standard 128 x 128 depth grid). A *variant* is the sensor with one effect added
or changed. Contacts that were not commanded (or not recorded) are estimated from the map as in
:mod:`tactile_deploy.calibration.fem_fit.fit`: the maximum-displacement region, then least squares on the depth
gap.

With measured RGB frames the reproducer carries a :class:`~tactile_deploy.calibration.discrepancy.imaging.
FrameImaging`: its maps are then the model's frames through the same imaging pipeline (the
*imaged* maps), and :meth:`ContactReproducer.surface_map` still gives the FEM's surface.
"""

from __future__ import annotations

import functools
import math

import numpy as np
from scipy import ndimage, optimize

from tactile_deploy.indenters import ContactPose, get_indenter
from tactile_deploy.sensors.config import EffectSpec
from tactile_deploy.sensors.virtual import VirtualSensor

#: Largest change of a round indenter's intrusion when it turns (the facets of meshed
#: spheres and punches), mm, and the share of footprint points whose contact may change.
ROUND_TOLERANCE_MM = 5e-3
ROUND_OUTLINE_SHARE = 0.05


@functools.lru_cache(maxsize=64)
def is_round(name: str) -> bool:
    """Whether indenter ``name`` is a body of revolution about z up to its facets: turned by 13
    degrees, its intrusion over a polar grid of its footprint changes by less than
    ``ROUND_TOLERANCE_MM`` and the footprint's outline by less than ``ROUND_OUTLINE_SHARE`` of
    the points."""
    ind = get_indenter(name)
    r = np.linspace(0.0, ind.footprint_radius_mm, 25)
    a = np.linspace(0.0, 2.0 * math.pi, 36, endpoint=False)
    pts = np.stack([np.outer(r, np.cos(a)).ravel(), np.outer(r, np.sin(a)).ravel()], axis=1)
    d0 = np.asarray(ind.intrusion_mm(pts, ContactPose(depth_mm=1.0)), np.float64)
    d1 = np.asarray(ind.intrusion_mm(pts, ContactPose(theta_deg=13.0, depth_mm=1.0)), np.float64)
    outline = np.mean(np.isfinite(d0) != np.isfinite(d1))
    top = np.isfinite(d0) & np.isfinite(d1) & ((d0 > 0) | (d1 > 0))
    return bool(outline < ROUND_OUTLINE_SHARE
                and np.all(np.abs(d0[top] - d1[top]) < ROUND_TOLERANCE_MM))


class CachedIndenter:
    """An indenter whose intrusion at a set of points is remembered per pose (variants of a
    sensor that leave the pose alone then reuse it); everything else is the indenter's."""

    def __init__(self, indenter, maxsize: int = 256):
        self._indenter = indenter
        self._cache: dict = {}
        self._maxsize = maxsize

    def __getattr__(self, name):
        return getattr(self._indenter, name)

    def intrusion_mm(self, points_xy_mm, pose: ContactPose) -> np.ndarray:
        xy = np.ascontiguousarray(points_xy_mm, np.float64)
        key = (pose.x_mm, pose.y_mm, pose.theta_deg, pose.depth_mm, xy.shape, hash(xy.tobytes()))
        hit = self._cache.get(key)
        if hit is None:
            if len(self._cache) >= self._maxsize:
                self._cache.pop(next(iter(self._cache)))
            hit = np.asarray(self._indenter.intrusion_mm(xy, pose), np.float64)
            self._cache[key] = hit
        return hit.copy()


class ContactReproducer:
    """Depth maps (128, 128) mm and forces (N) of contacts, for a sensor and its variants."""

    def __init__(self, sensor: VirtualSensor, imaging=None):
        self.sensor = sensor
        #: :class:`~tactile_deploy.calibration.discrepancy.imaging.FrameImaging` or None (maps are the FEM's).
        self.imaging = imaging
        self._indenters: dict[str, CachedIndenter] = {}
        self._variants: dict[str, VirtualSensor] = {}
        from tactile_deploy.camera.depth import DepthCamera

        self.camera = DepthCamera()
        mesh = sensor.simulator.mesh
        #: (128, 128) bool: pixels on the pad.
        self.pad_mask = self.camera.render(mesh, mesh.vertices).mask

    def indenter(self, name: str) -> CachedIndenter:
        if name not in self._indenters:
            self._indenters[name] = CachedIndenter(get_indenter(name))
        return self._indenters[name]

    def variant(self, spec: EffectSpec | None) -> VirtualSensor:
        """The sensor with ``spec`` added, or replacing its effect of the same name (None: the
        sensor itself). Variants share the sensor's simulator."""
        if spec is None:
            return self.sensor
        key = f"{spec.name}:{sorted(spec.params.items())}"
        if key not in self._variants:
            if len(self._variants) > 64:
                self._variants.clear()
            cfg = self.sensor.config
            effects = [e for e in cfg.effects if e.name != spec.name] + [spec]
            self._variants[key] = VirtualSensor(cfg.model_copy(update={"effects": tuple(effects)}),
                                                simulator=self.sensor.simulator)
        return self._variants[key]

    def depth_map(self, indenter: str, pose: ContactPose, sensor: VirtualSensor | None = None,
                  noise_pose: ContactPose | None = None) -> tuple[np.ndarray, float]:
        """``(depth (128, 128) float64 mm, force N)`` of ``indenter`` at ``pose``: the imaged
        map with an imaging path (its noise draws those of ``noise_pose``, default ``pose``:
        maps of nearby poses compared with each other share them), else the FEM's surface."""
        if self.imaging is not None:
            return self.imaging.depth_map(sensor or self.sensor, self.indenter(indenter),
                                          indenter, pose, noise_pose)
        return self.surface_map(indenter, pose, sensor)

    def surface_map(self, indenter: str, pose: ContactPose,
                    sensor: VirtualSensor | None = None) -> tuple[np.ndarray, float]:
        """``(depth (128, 128) float64 mm, force N)``: the FEM's surface (the depth-map truth)."""
        depth, force = (sensor or self.sensor).depth_map(self.indenter(indenter), pose)
        return depth.astype(np.float64), force

    def noise_maps(self, indenter: str, pose: ContactPose, mean_map: np.ndarray) -> np.ndarray:
        """(J, 128, 128) float32 mm noise realisations of the model's imaged map of the contact
        (imaging path only)."""
        return self.imaging.noise_maps(self.sensor, self.indenter(indenter), indenter, pose,
                                       mean_map)

    def estimate_pose(self, indenter: str, measured_mm: np.ndarray,
                      start: ContactPose | None = None) -> ContactPose:
        """The contact that best reproduces ``measured_mm`` (128, 128) mm with this sensor.

        Start: the depth-weighted centroid of the maximum-displacement region and the map's
        largest depth (the best of 24 angles for indenters that are not round); then a grid of
        positions (+-0.6 mm), least squares on x, y, depth and theta over the pad pixels' depth
        gap, and a simplex polish. Theta stays free for round indenters too: their facets
        switch nodes of the 1 mm mesh in and out of contact. With an imaging path the search
        compares the FEM's surface with the measured map (hundreds of maps, several times
        cheaper than imaged ones), then least squares on imaged maps (their noise draws fixed,
        so the gap is smooth in the pose) removes what the pipeline's own error moved it by
        (tens of micrometres in depth).
        """
        round_shape = is_round(indenter)
        mask = self.pad_mask
        measured = np.asarray(measured_mm, np.float64)

        def gap(pose, noise_pose=None):
            try:
                sim, _ = (self.surface_map(indenter, pose) if noise_pose is None else
                          self.depth_map(indenter, pose, noise_pose=noise_pose))
            except ValueError:  # off the pad or too deep: a large, smooth penalty
                return measured[mask] + 1.0
            return (sim - measured)[mask]

        if start is None:
            smooth = ndimage.gaussian_filter(measured, 1.0)
            top = smooth > 0.5 * smooth.max()
            centres = self.camera.pixel_centres_mm()
            w = smooth[top]
            x0, y0 = (float(v) for v in (centres[top] * w[:, None]).sum(0) / w.sum())
            d0 = max(float(measured.max()), 1e-3)
            thetas = [0.0] if round_shape else list(np.arange(0.0, 360.0, 15.0))
            best = None
            for t in thetas:
                pose = ContactPose(x_mm=x0, y_mm=y0, theta_deg=float(t), depth_mm=d0)
                cost = float(np.sum(gap(pose) ** 2))
                if best is None or cost < best[0]:
                    best = (cost, pose)
            start = best[1]

        def pose_of(p):
            return ContactPose(x_mm=float(p[0]), y_mm=float(p[1]), theta_deg=float(p[3]),
                               depth_mm=max(float(p[2]), 1e-4))

        # The gap is piecewise smooth (a 1 mm mesh; sharp indenter edges switch nodes in and
        # out of contact): a coarse grid of positions, least squares, then a simplex polish.
        best = None
        for dx in np.linspace(-0.6, 0.6, 7):
            for dy in np.linspace(-0.6, 0.6, 7):
                p = start.model_copy(update={"x_mm": start.x_mm + dx, "y_mm": start.y_mm + dy})
                cost = float(np.sum(gap(p) ** 2))
                if best is None or cost < best[0]:
                    best = (cost, p)
        start = best[1]
        p0 = [start.x_mm, start.y_mm, start.depth_mm, start.theta_deg]
        scale = [0.3, 0.3, 0.05, 5.0]
        sol = optimize.least_squares(lambda p: gap(pose_of(p)), p0, x_scale=scale,
                                     diff_step=1e-2, max_nfev=80)
        step = np.array([0.03, 0.03, 0.005, 1.0])
        simplex = np.vstack([sol.x, sol.x + np.diag(step)])
        polish = optimize.minimize(lambda p: float(np.sum(gap(pose_of(p)) ** 2)), sol.x,
                                   method="Nelder-Mead",
                                   options={"initial_simplex": simplex, "xatol": 1e-4,
                                            "fatol": 1e-12, "maxfev": 200})
        best_x = polish.x if polish.fun <= 2.0 * sol.cost else sol.x
        if self.imaging is None:
            return pose_of(best_x)
        fixed = pose_of(best_x)
        imaged = optimize.least_squares(lambda p: gap(pose_of(p), fixed), best_x, x_scale=scale,
                                        diff_step=1e-2, max_nfev=40)
        return pose_of(imaged.x)

    def pose_jacobian(self, indenter: str, pose: ContactPose, pixels: np.ndarray) -> np.ndarray:
        """Change of the map at flat ``pixels`` per unit change of the contact's x, y, depth
        (and theta for indenters that are not round): (n_pixels, 3 or 4), mm/mm and mm/deg,
        by central differences (0.02 mm, 0.005 mm, 1 degree)."""
        steps = {"x_mm": 0.02, "y_mm": 0.02, "depth_mm": 0.005}
        if not is_round(indenter):
            steps["theta_deg"] = 1.0
        cols = []
        for name, h in steps.items():
            v = getattr(pose, name)
            lo = pose.model_copy(update={name: v - h})
            hi = pose.model_copy(update={name: v + h})
            if name == "depth_mm" and v - h <= 0:
                lo, h2 = pose, h / 2
            else:
                h2 = h
            a = self.depth_map(indenter, lo, noise_pose=pose)[0].ravel()[pixels]
            b = self.depth_map(indenter, hi, noise_pose=pose)[0].ravel()[pixels]
            cols.append((b - a) / (2.0 * h2))
        return np.stack(cols, axis=1)


def contact_radius_mm(depth_mm: np.ndarray, pitch_mm: float = 35.0 / 128) -> float:
    """Equivalent radius of the region pushed in by more than half the largest depth, mm
    (sqrt(area / pi)); 0 for a map without contact."""
    d = np.asarray(depth_mm)
    top = float(d.max())
    if top <= 0:
        return 0.0
    return math.sqrt(float((d > 0.5 * top).sum()) * pitch_mm**2 / math.pi)
