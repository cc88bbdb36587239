"""Depth profile of a ball press from the FEM of the pad: training targets outside the contact.

Inside the contact the gel takes the ball's shape (:mod:`.targets`); just outside it the gel is
still sunk, and further out a nearly incompressible layer bonded to its backplate bulges up a
little. Neither follows from the ball's geometry alone: it is the pad's response. This module
solves the contact of the ball on the sensor family's pad mesh (frictionless, the FEM of
:mod:`tactile_deploy.fem`, E irrelevant: the displacements of a given indentation do not depend
on it) and reduces it to an axisymmetric depth profile around the press centre, so that the
shading fit can give the pixels outside the contact the slopes the gel has there.

Profile: ``depth(r)`` mm (positive into the gel) against the distance r (mm) from the press
centre in the sensing plane: the azimuthal mean of the FEM surface (linear between the mesh's
sensing nodes) outside the contact, the sphere of the ball's radius inside it (where the mesh's
chords cut the ball), i.e. the larger of the two depths.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class PressProfile:
    """Axisymmetric depth profile of one ball press.

    r_mm : (n,) float64, distances from the press centre, mm, uniform from 0.
    depth_mm : (n,) float64, depth at r_mm, mm, positive into the gel.
    contact_radius_mm : where the FEM surface leaves the ball, mm. press_depth_mm : indentation
        of the ball, mm. centre_mm : (x, y) of the press centre, sensor frame, mm, when known.
    """

    r_mm: np.ndarray
    depth_mm: np.ndarray
    contact_radius_mm: float
    press_depth_mm: float
    centre_mm: tuple[float, float] | None = None

    def slope(self, r_mm) -> np.ndarray:
        """d depth / d r at ``r_mm`` (dimensionless, mm per mm); 0 beyond the profile."""
        d = np.gradient(self.depth_mm, self.r_mm)
        return np.interp(np.asarray(r_mm, np.float64), self.r_mm, d, right=0.0)

    def depth(self, r_mm) -> np.ndarray:
        """Depth at ``r_mm`` (mm); 0 beyond the profile."""
        return np.interp(np.asarray(r_mm, np.float64), self.r_mm, self.depth_mm, right=0.0)

    def depth_map(self, grid) -> np.ndarray:
        """Depth (ny, nx) float32 mm at the cell centres of ``grid`` (an
        :class:`~tactile_deploy.imaging.camera_mapping.OutputGrid`, sensor frame) around
        ``centre_mm``; 0 beyond the profile."""
        from tactile_deploy.imaging.camera_mapping import grid_centres_mm

        if self.centre_mm is None:
            raise ValueError("this profile has no centre_mm: it cannot be placed on a grid")
        x, y = grid_centres_mm(grid)
        return self.depth(np.hypot(x - self.centre_mm[0], y - self.centre_mm[1])).astype(np.float32)

    def image_gradients(self, cols, rows, centre_px, mm_per_px: float) -> np.ndarray:
        """Gradients of depth along image columns and rows (N, 2), mm per mm, at pixels
        (cols, rows) (N,) of an image whose press centre is ``centre_px`` (column, row)."""
        dc = np.asarray(cols, np.float64) - float(centre_px[0])
        dr = np.asarray(rows, np.float64) - float(centre_px[1])
        rho = np.hypot(dc, dr)
        s = self.slope(rho * mm_per_px) / np.maximum(rho, 1e-9)
        return np.stack([s * dc, s * dr], -1)


class BallPressModel:
    """Ball presses on a sensor family's pad, solved by the contact FEM.

    pad : the family's pad mesh name (``tactile_deploy.pad.asset.load_pad``), e.g. "gelslim".
    ball_radius_mm : radius of the calibration ball, mm.
    nu : Poisson ratio of the gel (the profile's one material parameter; E drops out).

    The pad's surface operators are computed once per (pad, nu) and cached on disk (about 20 s
    the first time). node_xy_mm : (n_plane, 2) sensing nodes at rest, sensor frame, mm.
    """

    def __init__(self, pad: str, ball_radius_mm: float, nu: float = 0.48):
        from tactile_deploy.fem.material import Material
        from tactile_deploy.fem.simulator import ContactSimulator
        from tactile_deploy.indenters import AnalyticSphere
        from tactile_deploy.pad.asset import load_pad

        if not ball_radius_mm > 0:
            raise ValueError(f"ball_radius_mm must be > 0, got {ball_radius_mm}")
        self.ball = AnalyticSphere(float(ball_radius_mm))
        self.radius_mm = float(ball_radius_mm)
        self.sim = ContactSimulator(load_pad(pad), Material(nu=float(nu)))
        self.sim.prepare()
        mesh = self.sim.mesh
        self.node_xy_mm = mesh.vertices[mesh.sensing_nodes, :2]

    def solve(self, x_mm: float, y_mm: float, depth_mm: float):
        """FEM contact of the ball at (x_mm, y_mm) (sensor frame), pressed ``depth_mm``:
        ``(surface depth at the sensing nodes (n_plane,) mm, contact mask (n_plane,) bool)``."""
        from tactile_deploy.indenters import ContactPose

        res = self.sim.solve(self.ball, ContactPose(x_mm=float(x_mm), y_mm=float(y_mm),
                                                    depth_mm=float(depth_mm)))
        return -res.displacements_mm[self.sim.mesh.sensing_nodes, 2], res.contact_mask

    def profile(self, x_mm: float, y_mm: float, depth_mm: float, r_max_mm: float,
                step_mm: float = 0.02, n_angles: int = 72) -> PressProfile:
        """The :class:`PressProfile` of a press at (x_mm, y_mm), ``depth_mm`` deep, out to
        ``r_max_mm`` (clipped to the pad)."""
        from scipy.interpolate import LinearNDInterpolator

        depth_nodes, contact = self.solve(x_mm, y_mm, depth_mm)
        if not contact.any():
            raise ValueError(f"the ball at ({x_mm:.2f}, {y_mm:.2f}) mm, {depth_mm:.3f} mm deep, "
                             "touches no node of the pad")
        r = np.arange(0.0, r_max_mm + step_mm, step_mm)
        ang = np.linspace(0, 2 * math.pi, n_angles, endpoint=False)
        px = x_mm + r[:, None] * np.cos(ang)[None]
        py = y_mm + r[:, None] * np.sin(ang)[None]
        fem = LinearNDInterpolator(self.node_xy_mm, depth_nodes)(px, py)
        with np.errstate(invalid="ignore"):
            fem_mean = np.nanmean(np.where(np.isfinite(fem), fem, np.nan), axis=1)
        valid = np.isfinite(fem_mean)
        fem_mean = np.interp(r, r[valid], fem_mean[valid])      # off the pad: the last value
        rr = np.minimum(r, 0.999 * self.radius_mm)
        sphere = depth_mm - (self.radius_mm - np.sqrt(self.radius_mm ** 2 - rr ** 2))
        # the gel cannot enter the ball (depth >= the ball's); inside the contact the mesh's
        # chords lie above the ball, so the sphere takes over there
        depth = np.maximum(sphere, fem_mean)
        # contact edge: where the mean FEM surface leaves the ball (continuous in the depth,
        # unlike the set of contact nodes ~1 mm apart)
        off = np.flatnonzero((fem_mean > sphere + 1e-6) & (r > 2 * step_mm))
        a = float(r[off[0]]) if len(off) else float(r[-1])
        return PressProfile(r, depth, a, float(depth_mm), (float(x_mm), float(y_mm)))

    def depth_for_contact_radius(self, x_mm: float, y_mm: float, contact_radius_mm: float,
                                 max_depth_mm: float = 1.5) -> float:
        """The indentation (mm) whose profile's contact radius (:meth:`profile`) is
        ``contact_radius_mm``: for presses whose depth was not measured (by hand)."""

        def radius(d):
            return self.profile(x_mm, y_mm, d, 1.5 * contact_radius_mm + 0.5,
                                n_angles=24).contact_radius_mm

        lo, hi = 1e-3, max_depth_mm
        if radius(hi) < contact_radius_mm:
            return hi
        for _ in range(12):
            mid = 0.5 * (lo + hi)
            if radius(mid) < contact_radius_mm:
                lo = mid
            else:
                hi = mid
        return 0.5 * (lo + hi)
