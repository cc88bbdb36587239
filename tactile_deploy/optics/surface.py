"""Fine height map of the deformed sensing surface, for shading.

The pad mesh has ~1 mm between sensing nodes: its surface is made of flat 1 mm triangles whose
normals jump at every edge, and it cannot follow an indenter's shape inside the contact. Shading
needs normals at the camera's scale (~0.05 mm), so the height map given to the optics (sensor
frame, mm, on an :class:`OutputGrid`, row 0 at the largest y) is built from the FEM solution and
the indenter's exact shape:

* **free surface** ``z_free``: the deformed mesh surface (lateral displacement included) rendered
  by a :class:`~tactile_deploy.camera.depth.DepthCamera` at ``coarse_pitch_mm``, smoothed by a
  Gaussian of ``smooth_mm`` (removes the facet edges, keeps the mm-scale sinking) and
  interpolated bicubically onto the fine grid;
* **near the indenter** ``z_gap = z_ind - g``: ``z_ind = -intrusion`` is the indenter's own
  surface evaluated exactly on the fine grid, ``g >= 0`` the gap between indenter and gel: the
  nodal gaps of the FEM solution (0 at contact nodes), interpolated linearly on the deformed
  mesh and smoothed like the free surface. Inside the contact ``g = 0`` and the surface *is*
  the indenter, with its fine detail (dots, edges) that the 1 mm mesh cannot carry;
* the two are blended by the gap: ``z_gap`` where ``g < gap_blend_mm[0]``, ``z_free`` where
  ``g > gap_blend_mm[1]`` (and wherever the indenter does not reach), a smoothstep between, and
  the result is capped by the indenter: ``height = min(blend, z_ind)``.

Residual: the smoothing lifts the gel off the indenter within about ``smooth_mm`` of the contact
rim (by a few um: the rim is soft, not a sharp step) and biases the free surface by about
``curvature * smooth_mm^2 / 2``. The true depth map (pushed in from rest, mm) is
``rest_height - height``.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import cv2
import numpy as np

from tactile_deploy.camera.depth import DepthCamera
from tactile_deploy.imaging.camera_mapping import OutputGrid
from tactile_deploy.pad.mesh import PadMesh

#: Intrusion function: sensor points (k, 2) mm -> intrusion below z = 0 (k,) mm, -inf uncovered.
IntrusionFn = Callable[[np.ndarray], np.ndarray]


class SurfaceBuilder:
    """Builds fine height maps on ``grid`` from FEM solutions of ``mesh`` (see module docstring).

    Parameters
    ----------
    mesh : PadMesh (its rest sensing surface must be flat, z = 0; a dome is a rest height)
    grid : OutputGrid, the fine grid (usually the optics renderer's ``grid``)
    smooth_mm : Gaussian sigma applied to the rasterised FEM surface and gaps, mm
    coarse_pitch_mm : pixel pitch of the depth camera that rasterises them, mm
    gap_blend_mm : (g0, g1) gaps between which the surface goes from the indenter-based to the
        free-surface form, mm
    """

    #: Gap (mm) given to nodes the indenter does not cover.
    GAP_CAP_MM = 1.0

    def __init__(self, mesh: PadMesh, grid: OutputGrid, smooth_mm: float = 0.3,
                 coarse_pitch_mm: float = 0.125, gap_blend_mm: tuple[float, float] = (0.02, 0.1)):
        if not smooth_mm >= 0 or not coarse_pitch_mm > 0:
            raise ValueError(f"smooth_mm must be >= 0 and coarse_pitch_mm > 0, got {smooth_mm} "
                             f"and {coarse_pitch_mm}")
        if not 0 <= gap_blend_mm[0] < gap_blend_mm[1] < self.GAP_CAP_MM:
            raise ValueError(f"gap_blend_mm must satisfy 0 <= g0 < g1 < {self.GAP_CAP_MM}, got "
                             f"{gap_blend_mm}")
        rest_z = mesh.vertices[mesh.sensing_nodes, 2]
        if np.any(np.abs(rest_z) > 1e-9):
            raise ValueError("SurfaceBuilder needs a flat pad mesh (sensing nodes at z = 0); "
                             "describe a dome by a rest height instead")
        self.mesh = mesh
        self.grid = grid
        self.smooth_mm = float(smooth_mm)
        self.gap_blend_mm = (float(gap_blend_mm[0]), float(gap_blend_mm[1]))
        reach = max(abs(grid.x_min_mm), abs(grid.x_max_mm), abs(grid.y_min_mm),
                    abs(grid.y_max_mm)) + 3.0 * smooth_mm + 2.0 * coarse_pitch_mm
        half = min(reach, mesh.geometry.half_extent_mm + 2.0 * coarse_pitch_mm)
        self.camera = DepthCamera(half, math.ceil(2.0 * half / coarse_pitch_mm))
        xs = grid.x_min_mm + (np.arange(grid.nx) + 0.5) * grid.pitch_x_mm
        ys = grid.y_max_mm - (np.arange(grid.ny) + 0.5) * grid.pitch_y_mm
        x, y = np.meshgrid(xs, ys)
        #: Sensor-frame centres of the fine grid, (ny, nx, 2) float64, mm.
        self.xy_mm = np.stack([x, y], axis=-1)
        p = self.camera.pitch_mm
        self._map_x = ((x + half) / p - 0.5).astype(np.float32)
        self._map_y = ((half - y) / p - 0.5).astype(np.float32)

    def _to_fine(self, coarse: np.ndarray, box=None) -> np.ndarray:
        """Smooth a coarse raster and interpolate it onto the fine grid (or its ``box`` =
        (i0, i1, j0, j1) of fine rows and columns)."""
        if self.smooth_mm > 0:
            coarse = cv2.GaussianBlur(coarse, (0, 0), self.smooth_mm / self.camera.pitch_mm,
                                      borderType=cv2.BORDER_REPLICATE)
        i0, i1, j0, j1 = box or (0, self.grid.ny, 0, self.grid.nx)
        return cv2.remap(coarse, self._map_x[i0:i1, j0:j1], self._map_y[i0:i1, j0:j1],
                         cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)

    def _changed_box(self, coarse: np.ndarray, tol_mm: float):
        """Fine-grid box (i0, i1, j0, j1) covering the coarse cells above ``tol_mm`` (grown by
        the smoothing and the cubic stencil), or None."""
        big = np.abs(coarse) > tol_mm
        rows = np.flatnonzero(big.any(axis=1))
        if len(rows) == 0:
            return None
        cols = np.flatnonzero(big[rows[0]:rows[-1] + 1].any(axis=0))
        p = self.camera.pitch_mm
        grow = 3.0 * self.smooth_mm + 3 * p
        h = self.camera.half_extent_mm
        x0, x1 = -h + cols[0] * p - grow, -h + (cols[-1] + 1) * p + grow
        y1, y0 = h - rows[0] * p + grow, h - (rows[-1] + 1) * p - grow
        g = self.grid
        j0 = max(math.floor((x0 - g.x_min_mm) / g.pitch_x_mm), 0)
        j1 = min(math.ceil((x1 - g.x_min_mm) / g.pitch_x_mm) + 1, g.nx)
        i0 = max(math.floor((g.y_max_mm - y1) / g.pitch_y_mm), 0)
        i1 = min(math.ceil((g.y_max_mm - y0) / g.pitch_y_mm) + 1, g.ny)
        if i1 <= i0 or j1 <= j0:
            return None
        return (i0, i1, j0, j1)

    def _sensing(self, vertices_mm) -> np.ndarray:
        v = np.asarray(vertices_mm, np.float64)
        if v.ndim != 2 or v.shape[1] != 3 or len(v) not in (self.mesh.n_nodes, self.mesh.n_plane):
            raise ValueError(f"vertices_mm must have shape ({self.mesh.n_nodes}, 3) or "
                             f"({self.mesh.n_plane}, 3), got {v.shape}")
        return v[: self.mesh.n_plane]

    #: Depth (mm) below which the FEM surface counts as at rest (not interpolated).
    REST_TOL_MM = 1e-6

    def fem_depth(self, vertices_mm: np.ndarray) -> np.ndarray:
        """Smoothed depth of the FEM surface on the fine grid, (ny, nx) float32, mm pushed in.

        Only the part of the grid near coarse cells deeper than ``REST_TOL_MM`` is interpolated;
        the rest is 0.
        """
        top = self._sensing(vertices_mm)
        coarse = self.camera.render(self.mesh, top).depth_mm
        out = np.zeros((self.grid.ny, self.grid.nx), np.float32)
        box = self._changed_box(coarse, self.REST_TOL_MM)
        if box is not None:
            i0, i1, j0, j1 = box
            out[i0:i1, j0:j1] = self._to_fine(coarse, box)
        return out

    def indenter_surface(self, intrusion: IntrusionFn, footprint_xy_mm: tuple[float, float],
                         footprint_radius_mm: float):
        """The indenter's surface height over the fine grid near its footprint.

        Returns ``(z_ind, box)``: z_ind (i1 - i0, j1 - j0) float32 mm (``-intrusion``, +inf where
        the indenter does not reach) over the grid box ``box = (i0, i1, j0, j1)`` covering the
        disc of ``footprint_radius_mm`` around ``footprint_xy_mm`` (sensor frame), or None when
        that disc misses the grid.
        """
        g = self.grid
        cx, cy = footprint_xy_mm
        r = footprint_radius_mm + 2.0 * max(g.pitch_x_mm, g.pitch_y_mm)
        j0 = max(math.floor((cx - r - g.x_min_mm) / g.pitch_x_mm), 0)
        j1 = min(math.ceil((cx + r - g.x_min_mm) / g.pitch_x_mm) + 1, g.nx)
        i0 = max(math.floor((g.y_max_mm - cy - r) / g.pitch_y_mm), 0)
        i1 = min(math.ceil((g.y_max_mm - cy + r) / g.pitch_y_mm) + 1, g.ny)
        if j1 <= j0 or i1 <= i0:
            return None
        pts = self.xy_mm[i0:i1, j0:j1].reshape(-1, 2)
        delta = np.asarray(intrusion(pts), np.float64).reshape(i1 - i0, j1 - j0)
        z_ind = np.where(np.isfinite(delta), -delta, np.inf).astype(np.float32)
        return z_ind, (i0, i1, j0, j1)

    def height(self, vertices_mm: np.ndarray, rest_height_mm: np.ndarray | float = 0.0,
               intrusion: IntrusionFn | None = None, footprint_xy_mm=(0.0, 0.0),
               footprint_radius_mm: float = 0.0) -> np.ndarray:
        """Fine height map of the deformed surface, (ny, nx) float32, mm, sensor frame.

        vertices_mm : deformed mesh (n, 3) or sensing nodes (n_plane, 3), mm, sensor frame (flat
            mesh: the rest height is added separately).
        rest_height_mm : rest height of the surface on the grid (a dome), mm, or a scalar.
        intrusion : indenter intrusion below z = 0 at sensor points (k, 2) -> (k,) mm (-inf where
            uncovered), absolute (not reduced by the rest height); None: no indenter floor.
        """
        top = self._sensing(vertices_mm)
        rest = np.asarray(rest_height_mm, np.float32)
        z = rest - self.fem_depth(top)
        if intrusion is None:
            return np.ascontiguousarray(z, dtype=np.float32)
        found = self.indenter_surface(intrusion, footprint_xy_mm, footprint_radius_mm)
        if found is None:
            return z.astype(np.float32)
        z_ind, (i0, i1, j0, j1) = found
        # Nodal gaps between indenter and gel, at the nodes' rest positions like the contact
        # solve (linearised contact): exactly 0 at contact nodes, > 0 elsewhere; capped.
        rest_xy = self.mesh.vertices[: self.mesh.n_plane, :2]
        node_int = np.asarray(intrusion(rest_xy), np.float64)
        u_z = top[:, 2] - self.mesh.vertices[: self.mesh.n_plane, 2]
        rest_nodes = float(rest) if rest.ndim == 0 else self._rest_at_nodes(rest, rest_xy)
        gap = np.where(np.isfinite(node_int), -node_int - (rest_nodes + u_z), self.GAP_CAP_MM)
        gap = np.clip(gap, 0.0, self.GAP_CAP_MM)
        gap_mesh = np.concatenate([rest_xy, -gap[:, None]], axis=1)
        g = self._to_fine(self.camera.render(self.mesh, gap_mesh).depth_mm, (i0, i1, j0, j1))
        g = np.maximum(g, 0.0)
        g0, g1 = self.gap_blend_mm
        t = np.clip((g - g0) / (g1 - g0), 0.0, 1.0)
        w = t * t * (3.0 - 2.0 * t)  # smoothstep: 0 -> indenter-based, 1 -> free surface
        z_box = z[i0:i1, j0:j1]
        finite = np.isfinite(z_ind)
        z_gap = np.where(finite, z_ind - g, z_box)
        blend = np.where(finite, (1.0 - w) * z_gap + w * z_box, z_box)
        z[i0:i1, j0:j1] = np.minimum(blend, z_ind)
        return np.ascontiguousarray(z, dtype=np.float32)

    def _rest_at_nodes(self, rest: np.ndarray, xy: np.ndarray) -> np.ndarray:
        from scipy.ndimage import map_coordinates

        g = self.grid
        col = (xy[:, 0] - g.x_min_mm) / g.pitch_x_mm - 0.5
        row = (g.y_max_mm - xy[:, 1]) / g.pitch_y_mm - 0.5
        return map_coordinates(rest.astype(np.float64), np.stack([row, col]), order=1,
                               mode="nearest")
