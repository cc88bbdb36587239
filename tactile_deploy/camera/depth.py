"""Synthetic orthographic depth camera of the sensing surface.

The camera sits under the gel and looks along +z at the sensing surface through the
transparent backplate, orthographically, over a square field of ``+-half_extent_mm`` with
``resolution`` x ``resolution`` pixels (default +-17.5 mm at 128 x 128, 0.273 mm per pixel).

Image convention (shared with the camera mapping of the runtime): pixel (row i, column j) has
its centre at ``x = -h + (j + 0.5) p``, ``y = +h - (i + 0.5) p`` in the sensor frame
(row 0 at the largest y, x to the right: the sensor seen from outside the gel).

Depth (mm, >= 0 where pushed in) is how far the sensing surface has moved in along -z from its
rest shape at that pixel, read from the *deformed* surface triangles (lateral displacement
included) by exact rasterisation; where surface folds overlap the camera sees the lowest one.
The mask marks pixels inside the pad's outline.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tactile_deploy.pad.mesh import PadMesh
from tactile_deploy.raster import RasterGrid, rasterize_triangles


@dataclass(frozen=True)
class DepthImage:
    """``depth_mm`` (H, W) float32, mm pushed in; ``mask`` (H, W) bool, pixel on the pad."""

    depth_mm: np.ndarray
    mask: np.ndarray


class DepthCamera:
    """Orthographic depth camera of the sensing surface (see module docstring for conventions)."""

    def __init__(self, half_extent_mm: float = 17.5, resolution: int = 128):
        if not half_extent_mm > 0:
            raise ValueError(f"half_extent_mm must be > 0, got {half_extent_mm}")
        if int(resolution) != resolution or resolution < 2:
            raise ValueError(f"resolution must be an integer >= 2, got {resolution}")
        self.half_extent_mm = float(half_extent_mm)
        self.resolution = int(resolution)
        self.pitch_mm = 2.0 * self.half_extent_mm / self.resolution
        c = -self.half_extent_mm + 0.5 * self.pitch_mm
        # Rasteriser grid: rows along +y; images flip it so that row 0 is the largest y.
        self.grid = RasterGrid(c, c, self.pitch_mm, self.resolution, self.resolution)
        self._rest_cache: dict[str, tuple[np.ndarray, np.ndarray]] = {}

    @classmethod
    def for_grid(cls, grid) -> DepthCamera:
        """A camera over an :class:`~tactile_deploy.imaging.camera_mapping.OutputGrid` of square
        cells (a pad family's depth grid, e.g. 124 x 96 cells of 0.15 mm): same conventions,
        row 0 at the largest y."""
        if abs(grid.pitch_x_mm - grid.pitch_y_mm) > 1e-9 * grid.pitch_x_mm:
            raise ValueError(f"a depth camera needs square cells, the grid has "
                             f"{grid.pitch_x_mm} x {grid.pitch_y_mm} mm")
        cam = cls(max(grid.x_max_mm - grid.x_min_mm, grid.y_max_mm - grid.y_min_mm) / 2,
                  max(grid.nx, grid.ny))
        cam.pitch_mm = float(grid.pitch_x_mm)
        cam.grid = RasterGrid(grid.x_min_mm + 0.5 * cam.pitch_mm, grid.y_min_mm + 0.5 * cam.pitch_mm,
                              cam.pitch_mm, grid.nx, grid.ny)
        return cam

    def pixel_centres_mm(self) -> np.ndarray:
        """Sensor-frame (x, y) of every pixel centre, (H, W, 2) mm, image row order."""
        centres = self.grid.pixel_centres_mm()
        return centres[::-1]

    def _surface_z(self, mesh: PadMesh, sensing_xyz: np.ndarray) -> np.ndarray:
        tri = sensing_xyz[mesh.sensing_faces]
        z = rasterize_triangles(tri, self.grid, reduce="min").z_mm
        return z[::-1]

    def _rest(self, mesh: PadMesh) -> tuple[np.ndarray, np.ndarray]:
        key = mesh.content_hash
        if key not in self._rest_cache:
            z = self._surface_z(mesh, mesh.vertices[mesh.sensing_nodes])
            self._rest_cache[key] = (np.nan_to_num(z), np.isfinite(z))
        return self._rest_cache[key]

    def render(self, mesh: PadMesh, vertices_mm: np.ndarray) -> DepthImage:
        """Depth image of ``mesh`` deformed to ``vertices_mm`` (n, 3) (or its sensing nodes only)."""
        vertices_mm = np.asarray(vertices_mm, dtype=np.float64)
        if vertices_mm.shape not in ((mesh.n_nodes, 3), (mesh.n_plane, 3)):
            raise ValueError(
                f"vertices_mm must have shape ({mesh.n_nodes}, 3) or ({mesh.n_plane}, 3), "
                f"got {vertices_mm.shape}"
            )
        z_rest, mask = self._rest(mesh)
        z = self._surface_z(mesh, vertices_mm[: mesh.n_plane])
        depth = np.where(mask & np.isfinite(z), z_rest - z, 0.0)
        return DepthImage(depth.astype(np.float32), mask)
