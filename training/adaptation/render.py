"""Differentiable depth camera of the pad's sensing surface, as a torch module with fixed shapes.

:class:`DepthRenderer` renders what :class:`tactile_deploy.camera.depth.DepthCamera` renders
(same 128 x 128 grid over +-17.5 mm, row 0 at the largest y, ``depth = rest z - deformed z`` at
each pixel centre, the lowest surface where folds overlap, 0 outside the rest outline and where
nothing covers a centre), and is differentiable in the vertex displacements, lateral ones
included: inside a triangle the depth is the plane through its deformed vertices (the
barycentric interpolation of their z, with weights from their deformed xy positions).

Method, in two passes:

1. *which triangle each pixel centre sees* (no gradient): the rules and the watertight edge
   functions of :class:`tactile_deploy.training.simulation.depth_torch.TriangleRasterizer` (edge functions
   always evaluated from the lower-index vertex of an edge, as integer pixel steps from a fixed
   reference pixel plus a precomputed offset, so that neighbouring triangles agree exactly on
   shared edges), the lowest covering triangle winning;
2. *its depth there* (differentiable): the plane through the winning triangle's deformed
   vertices at the pixel centre, clamped to the triangle's z range (the steep-facet rule). Only
   this pass is recorded by autograd: one gather of 5 plane coefficients per pixel.

One change to the rules makes the module capturable by ``torch.export``: every
triangle visits a **fixed** number ``pixels_per_triangle`` of pixel centres, enumerated row by
row in the bounding box of its deformed xy outline. The rest boxes of the shipped pad hold at
most 20 pixels (5 x 5 at most); the default of 36 leaves room for every box to grow by one pixel
column and row (lateral displacements up to ~0.27 mm across a triangle). Triangles whose
deformed box holds more pixels than that are counted in the ``overflow`` output (those pixels
may be missed). No data-dependent branch anywhere.

Shapes: displacements (B, n_plane, 3) mm of the sensing nodes (sensor frame), depth (B, 128, 128)
mm pushed in, image rows (row 0 = largest y).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from tactile_deploy.training.simulation.depth_torch import RestTables, deformed_triangles
from tactile_deploy.raster import EDGE_TOLERANCE_MM

#: Pixels each triangle visits (see module docstring).
DEFAULT_PIXELS_PER_TRIANGLE = 36
_BOX_SLACK_MM = 1e-4


class DepthRenderer(nn.Module):
    """Depth map (B, H, W) mm of the sensing surface displaced by (B, n_plane, 3) mm.

    Parameters
    ----------
    faces : (t, 3) int, triangles of the sensing surface (indices into its n_plane nodes).
    rest_vertices_mm : (n_plane, 3) float, rest positions of the sensing nodes, sensor frame.
    camera : DepthCamera or None (128 x 128 over +-17.5 mm).
    pixels_per_triangle : pixel centres visited per triangle (fixed shape; see module docstring).
    dtype : precision of the depth computation (bounding boxes are found in float64).
    """

    def __init__(self, faces, rest_vertices_mm, camera=None,
                 pixels_per_triangle: int = DEFAULT_PIXELS_PER_TRIANGLE,
                 dtype: torch.dtype = torch.float32, edge_tolerance_mm: float = EDGE_TOLERANCE_MM):
        super().__init__()
        from tactile_deploy.camera.depth import DepthCamera
        from tactile_deploy.raster import rasterize_triangles

        if int(pixels_per_triangle) < 1:
            raise ValueError(f"pixels_per_triangle must be >= 1, got {pixels_per_triangle}")
        camera = camera or DepthCamera()
        grid = camera.grid
        tables = RestTables.of(faces, rest_vertices_mm, grid)
        if tables.faces.size == 0:
            raise ValueError("faces must hold at least one triangle, got none")
        rest = np.asarray(rest_vertices_mm, dtype=np.float64)
        self.n_vertices = len(rest)
        self.nx, self.ny = grid.nx, grid.ny
        self.pitch_mm = float(grid.pitch_mm)
        self.tol = float(edge_tolerance_mm)
        self.pixels_per_triangle = int(pixels_per_triangle)
        p = self.pitch_mm
        tri = rest[tables.faces]
        z_rest = rasterize_triangles(tri, grid, reduce="min").z_mm  # (ny, nx), grid rows
        mask = np.isfinite(z_rest)

        def buf(name, x, dt=dtype):
            self.register_buffer(name, torch.as_tensor(np.ascontiguousarray(x), dtype=dt))

        buf("faces", tables.faces, torch.int64)
        buf("edge_a", tables.edge_a, torch.int64)
        buf("edge_b", tables.edge_b, torch.int64)
        buf("edge_sign", tables.edge_sign)
        # per edge start a: a pixel near a's rest position (whole pixels) and its offset from a (mm)
        buf("edge_ref", tables.ref_pixel[tables.edge_a])              # (t, 3, 2)
        buf("edge_offset", tables.offset[tables.edge_a])              # (t, 3, 2)
        buf("edge_rest", tables.edge_rest)                            # (t, 3, 2) mm
        buf("rest_z", tables.rest_z)                                  # (t, 3) mm
        buf("rest_rel", tables.rest_rel)                              # (t, 2, 3) mm
        buf("rest_pix", tables.rest_pix, torch.float64)               # (n, 2) pixel units
        buf("mask", mask, torch.bool)                                 # (ny, nx) grid rows
        buf("z_rest", np.where(mask, z_rest, 0.0))                    # (ny, nx) mm
        buf("pixel_step", np.arange(self.pixels_per_triangle), torch.int64)
        buf("rest_xyz", rest)                                         # (n, 3) mm
        buf("pixel_x", grid.x0_mm + (np.arange(self.nx * self.ny) % self.nx) * p)   # (ny * nx,) mm
        buf("pixel_y", grid.y0_mm + (np.arange(self.nx * self.ny) // self.nx) * p)

    @classmethod
    def for_pad(cls, pad=None, **kwargs) -> DepthRenderer:
        """Renderer of the sensing surface of ``pad`` (default: the shipped GelSlim pad)."""
        if pad is None:
            from tactile_deploy.pad.asset import load_pad

            pad = load_pad()
        return cls(pad.sensing_faces, pad.vertices[: pad.n_plane], **kwargs)

    def forward(self, displacements_mm: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(depth (B, H, W) mm, image rows; overflow (B,) int64: triangles whose deformed box
        held more pixels than ``pixels_per_triangle``)."""
        u = displacements_mm.to(self.rest_z.dtype)
        b = u.shape[0]
        col0, row0, width, count = self._boxes(u.detach())
        overflow = (count > self.pixels_per_triangle).sum(dim=1)
        face = self._winners(u.detach(), col0, row0, width, count)  # (B, ny * nx)
        z = self._surface_z(u, face).reshape(b, self.ny, self.nx)
        ok = self.mask & (face >= 0).reshape(b, self.ny, self.nx)
        depth = torch.where(ok, self.z_rest - z, torch.zeros_like(z))
        return depth.flip(1), overflow

    def _boxes(self, u: torch.Tensor):
        """Per (sample, triangle): first column, first row, width, pixel count of the deformed
        xy bounding box (int64), clipped to the grid."""
        xy = self.rest_pix + u[..., :2].to(torch.float64) / self.pitch_mm  # (B, n, 2)
        corners = xy[:, self.faces]  # (B, t, 3, 2)
        slack = (self.tol + _BOX_SLACK_MM) / self.pitch_mm
        lo = torch.clamp(torch.ceil(corners.amin(dim=2) - slack), min=0.0)
        hi = torch.floor(corners.amax(dim=2) + slack)
        hi = torch.minimum(hi, torch.tensor([self.nx - 1.0, self.ny - 1.0], dtype=torch.float64, device=u.device))
        extent = torch.clamp(hi - lo + 1.0, min=0.0).to(torch.int64)
        lo = lo.to(torch.int64)
        return lo[..., 0], lo[..., 1], extent[..., 0], extent[..., 0] * extent[..., 1]

    def _triangles(self, u: torch.Tensor):
        """Per (sample, triangle) quantities of the deformed triangles: signed edge vectors
        (exs, eys) (B, t, 3) with E >= 0 inside, edge lengths (B, t, 3), vertex z (B, t, 3),
        1 / twice the xy area (B, t), kept (not vertical) (B, t) bool, displacement of each
        edge's start vertex (B, t, 3, 3)."""
        tri = deformed_triangles(u, self.faces, self.edge_a, self.edge_b, self.edge_rest,
                                 self.rest_rel, self.edge_sign)
        return (tri.exs, tri.eys, torch.hypot(tri.ex, tri.ey), self.rest_z + tri.uf[..., 2],
                tri.inv_area, tri.keep, tri.ua)

    def _winners(self, u, col0, row0, width, count) -> torch.Tensor:
        """Triangle seen at each pixel centre (the lowest covering one), (B, ny * nx) int64,
        -1 where none covers. No gradient."""
        b = u.shape[0]
        t = self.faces.shape[0]
        n_pix = self.nx * self.ny
        big = t * self.pixels_per_triangle
        exs, eys, length, zv, inv_area, keep, ua = self._triangles(u)
        k = self.pixel_step  # (P,)
        w = width.clamp(min=1)[..., None]
        col = col0[..., None] + k % w  # (B, t, P)
        row = row0[..., None] + torch.div(k, w, rounding_mode="floor")
        valid = k < count[..., None]
        pixel = torch.where(valid, row * self.nx + col, torch.full_like(col, n_pix)).reshape(b, big)
        e = _edge_functions(col[..., None], row[..., None], exs[:, :, None, :], eys[:, :, None, :],
                            ua[:, :, None], self.edge_ref[:, None], self.edge_offset[:, None], self.pitch_mm)
        covered = (e >= (-self.tol * length)[:, :, None, :]).all(dim=-1) & keep[:, :, None] & valid
        z = _interpolate(e, zv[:, :, None, :], inv_area[:, :, None])
        z = torch.where(covered, z, torch.full_like(z, torch.inf)).reshape(b, big)
        best = torch.full((b, n_pix + 1), torch.inf, dtype=u.dtype, device=u.device)
        best = best.scatter_reduce(1, pixel, z, reduce="amin", include_self=True)
        win = covered.reshape(b, big) & (z == best.gather(1, pixel))
        pair = torch.arange(big, device=u.device).expand(b, big)
        first = torch.full((b, n_pix + 1), big, dtype=torch.int64, device=u.device)
        first = first.scatter_reduce(1, pixel, torch.where(win, pair, big), reduce="amin", include_self=True)
        first = first[:, :n_pix]
        return torch.where(first < big, torch.div(first, self.pixels_per_triangle, rounding_mode="floor"), -1)

    def _surface_z(self, u, face) -> torch.Tensor:
        """z (B, ny * nx) mm of the surface at each pixel centre, from the plane of triangle
        ``face`` through its deformed vertices, clamped to the triangle's z range
        (differentiable in ``u``; 0 where ``face`` is -1)."""
        b = u.shape[0]
        v = self.rest_xyz + u  # (B, n, 3) deformed sensing nodes, sensor frame
        tri = v[:, self.faces]  # (B, t, 3 vertices, 3)
        d1 = tri[:, :, 1] - tri[:, :, 0]
        d2 = tri[:, :, 2] - tri[:, :, 0]
        area2 = d1[..., 0] * d2[..., 1] - d1[..., 1] * d2[..., 0]
        inv = 1.0 / torch.where(area2 != 0, area2, torch.ones_like(area2))
        gx = (d1[..., 2] * d2[..., 1] - d2[..., 2] * d1[..., 1]) * inv  # dz/dx of the plane
        gy = (d2[..., 2] * d1[..., 0] - d1[..., 2] * d2[..., 0]) * inv  # dz/dy
        x0, y0, z0 = tri[:, :, 0, 0], tri[:, :, 0, 1], tri[:, :, 0, 2]
        zs = tri[..., 2]
        coef = torch.stack([z0 - gx * x0 - gy * y0, gx, gy, zs.amin(dim=-1), zs.amax(dim=-1)], dim=-1)  # (B, t, 5)
        f = face.clamp(min=0)
        c = torch.gather(coef, 1, f[..., None].expand(b, -1, 5))  # (B, npix, 5)
        z = c[..., 0] + c[..., 1] * self.pixel_x + c[..., 2] * self.pixel_y
        z = torch.minimum(torch.maximum(z, c[..., 3]), c[..., 4])
        return torch.where(face >= 0, z, torch.zeros_like(z))


def _edge_functions(col, row, exs, eys, ua, ref, off, pitch_mm: float):
    """E = cross(b - a, p - a) (signed so that E >= 0 inside) at pixel (col, row); ``p - a`` as
    whole pixel steps from a's reference pixel ``ref`` times the pitch, plus that pixel's offset
    ``off`` from a's rest position, minus a's displacement ``ua`` (watertight: module docstring)."""
    dxa = (col.to(exs.dtype) - ref[..., 0]) * pitch_mm + (off[..., 0] - ua[..., 0])
    dya = (row.to(exs.dtype) - ref[..., 1]) * pitch_mm + (off[..., 1] - ua[..., 1])
    return exs * dya - eys * dxa


def _interpolate(e, zv, inv_area):
    """Barycentric z = sum_i E_i z_i / |2 area|, clamped to the triangle's z range (the steep
    facet rule: a centre in the tolerance band cannot extrapolate beyond the triangle)."""
    z = (e * zv).sum(dim=-1) * inv_area
    return torch.minimum(torch.maximum(z, zv.amin(dim=-1)), zv.amax(dim=-1))
