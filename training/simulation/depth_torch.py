"""Batched depth rendering of the deformed sensing surface in torch (CPU or CUDA).

:class:`TorchDepthCamera` renders a batch of deformed pads and equals
:meth:`tactile_deploy.camera.depth.DepthCamera.render` (same pixel grid, row 0 at the largest y,
``depth = rest z - deformed z``, lowest surface where folds overlap, mask from the rest outline).
:class:`TriangleRasterizer` is the reusable part: a fixed triangle mesh whose vertices move per
sample, rasterised onto a :class:`~tactile_deploy.raster.RasterGrid` with the rules of
:func:`tactile_deploy.raster.rasterize_triangles`, and z interpolated barycentrically (so it is
differentiable in the vertex positions).

Method. For every (sample, triangle) the pixel centres in the triangle's *deformed* xy bounding
box (computed in float64, widened by the edge tolerance) are enumerated, padded to the largest
box of the batch (about 20 pixels on the shipped pad); for every such (sample, triangle, pixel)
the three edge functions give coverage and barycentric weights, and ``scatter_reduce(amin)``
keeps the lowest z per pixel. Enumerating the deformed box rather than a fixed pixel list around
the rest triangle needs no bound on the lateral displacement (contacts of large flat indenters
push the rim of the contact more than 1 mm sideways) and visits 5-7x fewer pixels than a rest
box widened by 1 mm.

Watertight edges. The edge function of the edge between mesh vertices a < b is always evaluated
as ``cross(b - a, p - a)`` from the lower-index vertex, with ``p - a`` formed as
``(column - column_a) * pitch + (offset_a - u_a)``: an integer pixel step from a fixed pixel near
a's rest position, plus that pixel's offset from the rest position (computed once in float64),
minus a's displacement. Two triangles sharing an edge therefore get exactly opposite values, so
a pixel centre on the edge is covered by at least one of them in any precision (float32
included), whatever the tolerance; and all terms are small, so float32 keeps ~1e-7 mm.

Edge rule and steep facets as in :mod:`tactile_deploy.raster`: a centre within
``edge_tolerance_mm`` of a triangle counts as covered; triangles whose normal is (numerically)
horizontal are skipped; on triangles steeper than ``|grad z| > 10`` the centre is moved onto the
triangle before its plane is evaluated and z is clamped to the triangle's z range. (The CPU
rasteriser also clips spans to the triangle's bounding box widened by the tolerance; that only
differs within ~1e-7 mm of a vertex, where the neighbouring triangles give the same z.)

Units: mm throughout; vertices and displacements in the frame of the grid (the sensor frame for
the depth camera).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch

import tactile_deploy.raster as _raster
from tactile_deploy.raster import EDGE_TOLERANCE_MM, RasterGrid

# Elements of the largest (sample, triangle, pixel, edge) tensor built at once: large on a GPU
# (fewer kernel launches), cache-sized on a CPU (measured: 2x faster than 2^25 on 2 cores).
_CHUNK_ELEMENTS = {"cuda": 1 << 25, "cpu": 1 << 20}
# Bounding boxes are widened by this much (mm) beyond the edge tolerance before enumerating
# pixels; the edge functions then decide coverage exactly.
_BOX_SLACK_MM = 1e-4


class DeformedTriangles(NamedTuple):
    """Geometry of deformed surface triangles, per (sample, triangle); mm, sensor frame.

    uf : (B, t, 3, 3) vertex displacements. ua : (B, t, 3, 3) displacement of each edge's start.
    ex, ey : (B, t, 3) deformed edge vectors b - a (xy). exs, eys : the same with the edge's
    orientation and the triangle's winding folded in (exact sign flips), so that the edge
    function E = cross(b - a, p - a) * sign is >= 0 inside. nx, ny, area2 : (B, t) the
    triangle's normal (area2: signed double xy area). keep : (B, t) bool, not vertical or
    degenerate. inv_area : (B, t) 1 / |area2| (1 where not kept).
    """

    uf: torch.Tensor
    ua: torch.Tensor
    ex: torch.Tensor
    ey: torch.Tensor
    exs: torch.Tensor
    eys: torch.Tensor
    nx: torch.Tensor
    ny: torch.Tensor
    area2: torch.Tensor
    keep: torch.Tensor
    inv_area: torch.Tensor


def deformed_triangles(u: torch.Tensor, faces, edge_a, edge_b, edge_rest, rest_rel,
                       edge_sign) -> DeformedTriangles:
    """Deformed triangles of displacements ``u`` (B, n, 3) mm, from the rest tables of a
    rasteriser: ``faces`` (t, 3), ``edge_a``/``edge_b`` (t, 3) edge end vertices, ``edge_rest``
    (t, 3, 2) rest edge vectors, ``rest_rel`` (t, 2, 3) rest positions of vertices 1, 2 relative
    to 0, ``edge_sign`` (t, 3). Shapes are fixed (exportable)."""
    uf = u[:, faces]
    ua = u[:, edge_a]
    ub = u[:, edge_b]
    ex = edge_rest[..., 0] + (ub[..., 0] - ua[..., 0])
    ey = edge_rest[..., 1] + (ub[..., 1] - ua[..., 1])
    rel = rest_rel + (uf[:, :, 1:, :] - uf[:, :, :1, :])  # (B, t, 2, 3)
    nx = rel[:, :, 0, 1] * rel[:, :, 1, 2] - rel[:, :, 0, 2] * rel[:, :, 1, 1]
    ny = rel[:, :, 0, 2] * rel[:, :, 1, 0] - rel[:, :, 0, 0] * rel[:, :, 1, 2]
    area2 = rel[:, :, 0, 0] * rel[:, :, 1, 1] - rel[:, :, 0, 1] * rel[:, :, 1, 0]
    keep = area2.abs() > _raster._VERTICAL * torch.sqrt(nx * nx + ny * ny + area2 * area2)
    inv_area = 1.0 / torch.where(keep, area2.abs(), torch.ones_like(area2))
    sign = edge_sign * torch.where(area2 < 0, -1.0, 1.0).to(u.dtype)[:, :, None]
    return DeformedTriangles(uf, ua, ex, ey, ex * sign, ey * sign, nx, ny, area2, keep, inv_area)


@dataclass(frozen=True)
class RestTables:
    """Tables of a triangle mesh at rest on a raster grid that a rasteriser keeps (numpy).

    faces : (t, 3) int64. edge_a, edge_b : (t, 3) int64, edge i of a face (opposite vertex i)
    runs from its lower-index vertex a to b. edge_sign : (t, 3) float64, +1 where the face's
    own direction (vertex j -> k) is a -> b, else -1. ref_pixel : (n, 2) float64, the whole
    pixel (column, row) nearest each vertex's rest xy. offset : (n, 2) mm, that pixel centre
    minus the vertex's rest xy. edge_rest : (t, 3, 2) mm, rest xy of b - a. rest_z : (t, 3) mm,
    rest z of the face's vertices. rest_rel : (t, 2, 3) mm, rest vertices 1 and 2 minus vertex
    0. rest_pix : (n, 2) float64, rest xy in pixel units (for bounding boxes).
    """

    faces: np.ndarray
    edge_a: np.ndarray
    edge_b: np.ndarray
    edge_sign: np.ndarray
    ref_pixel: np.ndarray
    offset: np.ndarray
    edge_rest: np.ndarray
    rest_z: np.ndarray
    rest_rel: np.ndarray
    rest_pix: np.ndarray

    @classmethod
    def of(cls, faces, rest_vertices_mm, grid: RasterGrid) -> RestTables:
        """The tables of ``faces`` (t, 3) int over ``rest_vertices_mm`` (n, 3) mm (the frame of
        ``grid``); ValueError naming the array when a shape or an index is wrong."""
        faces = np.asarray(faces, dtype=np.int64)
        rest = np.asarray(rest_vertices_mm, dtype=np.float64)
        if faces.ndim != 2 or faces.shape[1] != 3:
            raise ValueError(f"faces must have shape (t, 3), got {faces.shape}")
        if rest.ndim != 2 or rest.shape[1] != 3:
            raise ValueError(f"rest_vertices_mm must have shape (n, 3), got {rest.shape}")
        if faces.size and (faces.min() < 0 or faces.max() >= len(rest)):
            raise ValueError(f"faces index vertices 0..{len(rest) - 1}, got "
                             f"{faces.min()}..{faces.max()}")
        p = grid.pitch_mm
        j, k = np.array([1, 2, 0]), np.array([2, 0, 1])
        fj, fk = faces[:, j], faces[:, k]
        forward = fj < fk
        edge_a = np.where(forward, fj, fk)
        edge_b = np.where(forward, fk, fj)
        pix = np.stack([(rest[:, 0] - grid.x0_mm) / p, (rest[:, 1] - grid.y0_mm) / p], axis=1)
        ref = np.rint(pix)
        offset = np.stack([grid.x0_mm + ref[:, 0] * p - rest[:, 0],
                           grid.y0_mm + ref[:, 1] * p - rest[:, 1]], axis=1)
        tri = rest[faces]
        return cls(faces, edge_a, edge_b, np.where(forward, 1.0, -1.0), ref, offset,
                   rest[edge_b, :2] - rest[edge_a, :2], tri[:, :, 2],
                   tri[:, 1:, :] - tri[:, :1, :], pix)


@dataclass(frozen=True)
class TorchRaster:
    """Result of :meth:`TriangleRasterizer.rasterize` for B samples on a grid (ny, nx).

    z_mm : (B, ny, nx) tensor, mm; +inf (reduce "min") or -inf ("max") where nothing covers.
    face_index : (B, ny, nx) int64 tensor or None; winning triangle, -1 where nothing covers.
    barycentric : (B, ny, nx, 3) tensor or None; weights of the winning triangle's vertices
        (in its face order) at the pixel centre, 0 where nothing covers.
    pixels_per_triangle : int, the padded box size used (largest deformed bounding box).
    """

    z_mm: torch.Tensor
    face_index: torch.Tensor | None = None
    barycentric: torch.Tensor | None = None
    pixels_per_triangle: int = 0


class TriangleRasterizer:
    """Rasterise a fixed triangle mesh with per-sample vertex displacements, in batches.

    Parameters
    ----------
    faces : (t, 3) int
        Triangles, indices into the vertices.
    rest_vertices_mm : (n, 3) float, mm
        Rest positions, in the frame of ``grid``.
    grid : RasterGrid
        Pixel centres (mm).
    device, dtype : where and in which precision to compute (boxes are found in float64).
    edge_tolerance_mm : float
        Pixel centres this close to a triangle (in xy) count as covered.
    """

    def __init__(
        self,
        faces,
        rest_vertices_mm,
        grid: RasterGrid,
        device="cpu",
        dtype: torch.dtype = torch.float64,
        edge_tolerance_mm: float = EDGE_TOLERANCE_MM,
    ):
        if not edge_tolerance_mm >= 0:
            raise ValueError(f"edge_tolerance_mm must be >= 0, got {edge_tolerance_mm!r}")
        tables = RestTables.of(faces, rest_vertices_mm, grid)
        self.grid = grid
        self.tol = float(edge_tolerance_mm)
        self.device = torch.device(device)
        self.dtype = dtype
        self.n_vertices = len(tables.rest_pix)
        self.n_pixels = grid.nx * grid.ny

        def dev(x, dt=dtype):
            return torch.as_tensor(x, dtype=dt, device=self.device)

        self.faces = dev(tables.faces, torch.int64)
        self.edge_a = dev(tables.edge_a, torch.int64)
        self.edge_b = dev(tables.edge_b, torch.int64)
        self.edge_sign = dev(tables.edge_sign)
        self.ref_pixel_f = dev(tables.ref_pixel)  # (n, 2), whole pixels
        self.offset = dev(tables.offset)  # (n, 2) mm
        self.edge_rest = dev(tables.edge_rest)  # (t, 3, 2)
        self.rest_z = dev(tables.rest_z)  # (t, 3)
        self.rest_rel = dev(tables.rest_rel)  # (t, 2, 3): v1 - v0, v2 - v0
        # Rest xy in pixel units (float64) for the bounding boxes.
        self.rest_pix = dev(tables.rest_pix, torch.float64)

    # ------------------------------------------------------------------------------------------
    def rasterize(
        self,
        displacements_mm: torch.Tensor,
        reduce: str = "min",
        return_face_index: bool = False,
        return_barycentric: bool = False,
    ) -> TorchRaster:
        """Rasterise the mesh displaced by ``displacements_mm`` (B, n, 3) (mm, grid frame).

        Returns :class:`TorchRaster` with z_mm (B, ny, nx): per pixel centre the ``reduce``
        ("min" or "max") of the z of the covering triangles. z is differentiable in the
        displacements (barycentric interpolation of the vertices' z).
        """
        u = torch.as_tensor(displacements_mm)
        if u.ndim != 3 or u.shape[1:] != (self.n_vertices, 3):
            raise ValueError(
                f"displacements_mm must have shape (B, {self.n_vertices}, 3), got {tuple(u.shape)}"
            )
        if reduce not in ("min", "max"):
            raise ValueError(f"reduce must be 'min' or 'max', got {reduce!r}")
        u = u.to(device=self.device, dtype=self.dtype)
        B = u.shape[0]
        box = self._boxes(u.detach())
        P = max(int(box[4].max()) if B else 1, 1)
        per_sample = self.faces.shape[0] * P * 3
        chunk = max(1, _CHUNK_ELEMENTS.get(self.device.type, 1 << 25) // per_sample)
        want_winner = return_face_index or return_barycentric
        zs, faces_out, bary_out = [], [], []
        for s in range(0, B, chunk):
            part = tuple(x[s : s + chunk] for x in box)
            z, face, bary = self._rasterize_chunk(u[s : s + chunk], part, P, reduce, want_winner,
                                                  return_barycentric)
            zs.append(z)
            faces_out.append(face)
            bary_out.append(bary)
        ny, nx = self.grid.ny, self.grid.nx
        z = torch.cat(zs).reshape(B, ny, nx)
        face_index = torch.cat(faces_out).reshape(B, ny, nx) if return_face_index else None
        barycentric = torch.cat(bary_out).reshape(B, ny, nx, 3) if return_barycentric else None
        return TorchRaster(z, face_index, barycentric, P)

    def _boxes(self, u):
        """Pixel boxes of the deformed triangles (B, t): first column, first row, width, height,
        number of pixels (int64)."""
        p = self.grid.pitch_mm
        xy = self.rest_pix[None] + u[..., :2].to(torch.float64) / p  # (B, n, 2) pixel units
        corners = xy[:, self.faces]  # (B, t, 3, 2)
        slack = (self.tol + _BOX_SLACK_MM) / p
        lo = torch.ceil(corners.amin(dim=2) - slack)
        hi = torch.floor(corners.amax(dim=2) + slack)
        size = torch.tensor([self.grid.nx - 1, self.grid.ny - 1], dtype=torch.float64,
                            device=u.device)
        lo = torch.clamp(lo, min=0.0)
        hi = torch.minimum(hi, size)
        extent = torch.clamp(hi - lo + 1.0, min=0.0).to(torch.int64)
        lo = lo.to(torch.int64)
        return lo[..., 0], lo[..., 1], extent[..., 0], extent[..., 1], extent[..., 0] * extent[..., 1]

    def _rasterize_chunk(self, u, box, P, reduce, want_winner, want_bary):
        B = u.shape[0]
        t = self.faces.shape[0]
        col0, row0, width, _, count = box
        tri = deformed_triangles(u, self.faces, self.edge_a, self.edge_b, self.edge_rest,
                                 self.rest_rel, self.edge_sign)
        uf, ua, ex, ey, exs, eys = tri.uf, tri.ua, tri.ex, tri.ey, tri.exs, tri.eys
        keep, inv_area = tri.keep, tri.inv_area
        steep = torch.hypot(tri.nx, tri.ny) > _raster._STEEP_GRADIENT * tri.area2.abs()

        # Pixels of each box: (B, t, P) columns and rows, padding -> the spare pixel slot.
        k = torch.arange(P, device=u.device)
        w = width.clamp(min=1)[..., None]
        col = col0[..., None] + k % w
        row = row0[..., None] + k // w
        valid = k < count[..., None]
        pixel = torch.where(valid, row * self.grid.nx + col, self.n_pixels)
        # p - a for every edge start a: integer steps from a's reference pixel (exact in
        # floating point) times the pitch, plus that pixel's offset from a, minus a's motion.
        pitch = self.grid.pitch_mm
        ref = self.ref_pixel_f[self.edge_a]  # (t, 3, 2)
        base_x = (self.offset[self.edge_a, 0] - ua[..., 0])[:, :, None, :]  # (B, t, 1, 3)
        base_y = (self.offset[self.edge_a, 1] - ua[..., 1])[:, :, None, :]
        dxa = (col.to(u.dtype)[..., None] - ref[None, :, None, :, 0]) * pitch + base_x
        dya = (row.to(u.dtype)[..., None] - ref[None, :, None, :, 1]) * pitch + base_y
        E = exs[:, :, None, :] * dya - eys[:, :, None, :] * dxa  # (B, t, P, 3)
        length = torch.hypot(ex, ey)  # (B, t, 3)
        covered = (E >= (-self.tol * length)[:, :, None, :]).all(dim=-1)
        covered = covered & keep[:, :, None] & valid
        zv = self.rest_z + uf[..., 2]  # (B, t, 3)
        zw = zv * inv_area[:, :, None]
        z = (E * zw[:, :, None, :]).sum(dim=-1)  # barycentric: w_i = E_i / |area2|
        if bool(steep.any()):
            z = torch.where(steep[:, :, None], self._steep_z(E, exs, eys, length, zv, zw), z)
        fill = torch.inf if reduce == "min" else -torch.inf
        z = torch.where(covered, z, torch.full_like(z, fill))
        flat = z.reshape(B, t * P)
        index = pixel.reshape(B, t * P)
        out = torch.full((B, self.n_pixels + 1), fill, dtype=u.dtype, device=u.device)
        out = out.scatter_reduce(1, index, flat, reduce="amin" if reduce == "min" else "amax",
                                 include_self=True)
        face = bary = None
        if want_winner:
            best = out.gather(1, index)
            win = (flat == best) & covered.reshape(B, t * P)
            big = t * P
            pair = torch.arange(big, device=u.device).expand(B, -1)
            pair_best = torch.full((B, self.n_pixels + 1), big, dtype=torch.int64, device=u.device)
            pair_best = pair_best.scatter_reduce(1, index, torch.where(win, pair, big), "amin")
            pair_best = pair_best[:, : self.n_pixels]
            hit = pair_best < big
            safe = torch.where(hit, pair_best, 0)
            face = torch.where(hit, safe // P, -1)
            if want_bary:
                wts = (E * inv_area[:, :, None, None]).reshape(B, big, 3)
                bary = torch.gather(wts, 1, safe[..., None].expand(-1, -1, 3))
                bary = torch.where(hit[..., None], bary, torch.zeros_like(bary))
        return out[:, : self.n_pixels], face, bary

    @staticmethod
    def _steep_z(E, exs, eys, length, zv, zw):
        """z of steep triangles: the centre moved onto the triangle, z clamped to its range."""
        # grad_p E_i = (-eys_i, exs_i); unit inward normal n_i = grad E_i / |e_i|.
        inv_len = (1.0 / torch.where(length > 0, length, torch.ones_like(length)))[:, :, None, :]
        outside = torch.clamp(E * inv_len, max=0.0)  # signed distance where negative
        step = -outside * inv_len  # q - p = sum_m step_m grad E_m
        gx, gy = -eys[:, :, None, :], exs[:, :, None, :]
        qx = (step * gx).sum(dim=-1, keepdim=True)
        qy = (step * gy).sum(dim=-1, keepdim=True)
        z = ((E + gx * qx + gy * qy) * zw[:, :, None, :]).sum(dim=-1)
        lo = zv.amin(dim=-1)[:, :, None]
        hi = zv.amax(dim=-1)[:, :, None]
        return torch.minimum(torch.maximum(z, lo), hi)


class TorchDepthCamera:
    """:class:`~tactile_deploy.camera.depth.DepthCamera` for batches of deformed pads in torch.

    Parameters
    ----------
    mesh : PadMesh
    camera : DepthCamera or None (default 128 x 128 over +-17.5 mm)
    device, dtype : where and in which precision to render.
    """

    def __init__(self, mesh, camera=None, device="cpu", dtype: torch.dtype = torch.float32):
        from tactile_deploy.camera.depth import DepthCamera

        self.mesh = mesh
        self.camera = camera or DepthCamera()
        self.device = torch.device(device)
        self.dtype = dtype
        n_plane = mesh.n_plane
        rest = mesh.vertices[:n_plane]
        self.rasterizer = TriangleRasterizer(mesh.sensing_faces, rest, self.camera.grid, device,
                                             dtype)
        # Rest surface and outline, once, in float64.
        rest_raster = TriangleRasterizer(mesh.sensing_faces, rest, self.camera.grid, device,
                                         torch.float64)
        z = rest_raster.rasterize(torch.zeros((1, n_plane, 3), dtype=torch.float64,
                                              device=self.device)).z_mm[0]
        self.mask = torch.isfinite(z)  # (ny, nx), grid rows (along +y)
        self.z_rest = torch.where(self.mask, z, torch.zeros_like(z))
        #: Padded pixel-box size of the last render (largest deformed triangle box).
        self.last_pixels_per_triangle = 0

    def image_mask(self) -> torch.Tensor:
        """(H, W) bool, pixel on the pad, image rows (row 0 = largest y)."""
        return self.mask.flip(0)

    def render_displacements(self, displacements_mm: torch.Tensor) -> torch.Tensor:
        """Depth images (B, H, W), mm pushed in, image rows (row 0 = largest y), in ``dtype``.

        displacements_mm : (B, n_plane, 3) or (B, n, 3) tensor, mm, sensor frame (only the
            sensing nodes are used).
        """
        u = torch.as_tensor(displacements_mm)
        n_plane = self.mesh.n_plane
        if u.ndim != 3 or u.shape[1] not in (n_plane, self.mesh.n_nodes) or u.shape[2] != 3:
            raise ValueError(
                f"displacements_mm must have shape (B, {n_plane} or {self.mesh.n_nodes}, 3), "
                f"got {tuple(u.shape)}"
            )
        r = self.rasterizer.rasterize(u[:, :n_plane])
        self.last_pixels_per_triangle = r.pixels_per_triangle
        z = r.z_mm
        ok = self.mask[None] & torch.isfinite(z)
        depth = torch.where(ok, self.z_rest.to(z.dtype)[None] - torch.where(ok, z, 0.0),
                            torch.zeros_like(z))
        return depth.flip(1)

    def render(self, vertices_mm: torch.Tensor) -> torch.Tensor:
        """Depth images (B, H, W), mm, from deformed vertices (B, n or n_plane, 3), mm."""
        v = torch.as_tensor(vertices_mm)
        n_plane = self.mesh.n_plane
        rest = torch.as_tensor(self.mesh.vertices[:n_plane], dtype=torch.float64, device=v.device)
        return self.render_displacements(v[:, :n_plane].to(torch.float64) - rest)
