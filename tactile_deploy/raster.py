"""Rasterise triangles onto a regular grid: per pixel centre, the z of the covering triangle.

Grid convention (:class:`RasterGrid`): pixel (row ``iy``, column ``ix``) has its centre at
``x = x0_mm + ix * pitch_mm``, ``y = y0_mm + iy * pitch_mm``; rows run along y, columns along x.
Coordinates are in mm, in whatever frame the triangles are given (sensor frame for the depth
camera, indenter frame for an indenter's pressing surface).

Method (vectorised, no per-pixel or per-triangle Python loop): every triangle is cut into the
pixel rows it spans; on each row the three edge half-planes give the exact span of covered pixel
centres; the spans are expanded into pixels and the z of the triangle's plane at each centre is
reduced by ``min`` or ``max`` with ``np.minimum.at`` / ``np.maximum.at``. Work is proportional to
the number of covered pixels, whatever the mix of triangle sizes; triangles are processed in
chunks of bounded size to cap memory.

Edge rule: a pixel centre within ``edge_tolerance_mm`` of a triangle (measured perpendicular to
its edges, in the xy plane) counts as covered, so a centre exactly on an edge shared by two
triangles is covered by both and a closed surface leaves no cracks. Triangles whose xy
projection has (numerically) zero area -- vertical walls -- are skipped: their xy outline is
covered by their neighbours. For steep triangles a centre in the tolerance band is first moved
onto the triangle (along the violated edges' normals) before its plane is evaluated, so that a
nearly vertical facet cannot extrapolate its z across the band.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

#: Default tolerance (mm) of the edge rule.
EDGE_TOLERANCE_MM = 1e-7

# Largest number of bounding-box pixels expanded at once (peak memory ~ 20 bytes each).
_CHUNK_PIXELS = 1 << 22
_NO_FACE = np.iinfo(np.int64).max
# Triangles steeper than this |dz/dxy| evaluate z at the centre moved onto the triangle.
_STEEP_GRADIENT = 10.0
# Triangles whose normal is closer than this (|n_z| / |n|) to horizontal count as vertical.
_VERTICAL = 1e-9


@dataclass(frozen=True)
class RasterGrid:
    """A regular grid of pixel centres.

    Pixel (iy, ix) is centred at ``(x0_mm + ix * pitch_mm, y0_mm + iy * pitch_mm)``, mm.
    """

    x0_mm: float
    y0_mm: float
    pitch_mm: float
    nx: int
    ny: int

    def __post_init__(self) -> None:
        for name in ("x0_mm", "y0_mm", "pitch_mm"):
            value = getattr(self, name)
            if not np.isfinite(value):
                raise ValueError(f"RasterGrid.{name} must be finite, got {value!r}")
        if not self.pitch_mm > 0:
            raise ValueError(f"RasterGrid.pitch_mm must be > 0, got {self.pitch_mm!r}")
        for name in ("nx", "ny"):
            value = getattr(self, name)
            if int(value) != value or value < 1:
                raise ValueError(f"RasterGrid.{name} must be an integer >= 1, got {value!r}")

    @classmethod
    def covering(
        cls, xy_min_mm, xy_max_mm, pitch_mm: float, pad_pixels: int = 0
    ) -> "RasterGrid":
        """Smallest grid whose pixel centres lie on integer multiples of ``pitch_mm`` and which
        covers the box ``xy_min_mm``..``xy_max_mm`` (each (2,), mm) plus ``pad_pixels`` pixels
        on every side."""
        lo = np.floor(np.asarray(xy_min_mm, dtype=np.float64) / pitch_mm) - pad_pixels
        hi = np.ceil(np.asarray(xy_max_mm, dtype=np.float64) / pitch_mm) + pad_pixels
        if lo.shape != (2,) or hi.shape != (2,) or not np.all(np.isfinite(lo + hi)):
            raise ValueError(
                f"xy_min_mm and xy_max_mm must be finite (2,) arrays, got {xy_min_mm!r}, {xy_max_mm!r}"
            )
        n = (hi - lo).astype(np.int64) + 1
        return cls(float(lo[0] * pitch_mm), float(lo[1] * pitch_mm), float(pitch_mm), int(n[0]), int(n[1]))

    @property
    def x_mm(self) -> np.ndarray:
        """Pixel-centre x of every column, (nx,) float64, mm."""
        return self.x0_mm + np.arange(self.nx) * self.pitch_mm

    @property
    def y_mm(self) -> np.ndarray:
        """Pixel-centre y of every row, (ny,) float64, mm."""
        return self.y0_mm + np.arange(self.ny) * self.pitch_mm

    def pixel_centres_mm(self) -> np.ndarray:
        """Pixel centres, (ny, nx, 2) float64, mm, last axis (x, y)."""
        gx, gy = np.meshgrid(self.x_mm, self.y_mm, indexing="xy")
        return np.stack([gx, gy], axis=-1)


@dataclass(frozen=True)
class Raster:
    """Result of :func:`rasterize_triangles` on a grid of shape (ny, nx).

    z_mm : (ny, nx) float64, mm; NaN where no triangle covers the pixel centre.
    face_index : (ny, nx) int64 or None; index of the triangle that gave ``z_mm`` (the lowest
        index among ties), -1 where nothing covers.
    barycentric : (ny, nx, 3) float64 or None; weights of that triangle's three vertices (in
        their given order) at the pixel centre, summing to 1 (NaN where nothing covers). Weights
        of a centre on an edge may be negative by about ``edge_tolerance_mm / edge height``.
    """

    grid: RasterGrid
    z_mm: np.ndarray
    face_index: np.ndarray | None = None
    barycentric: np.ndarray | None = None

    @property
    def covered(self) -> np.ndarray:
        """(ny, nx) bool, True where a triangle covers the pixel centre."""
        return ~np.isnan(self.z_mm)


def _edge_coefficients(tri: np.ndarray):
    """Normalised edge functions of triangles (m, 3, 3) with non-zero xy area.

    Returns ``abc`` (m, 3, 3): for the edge opposite vertex i, ``(a, b, c)`` with
    ``a x + b y + c`` = signed distance (mm) from the edge, positive inside; ``length`` (m, 3)
    of each edge (mm); ``area2`` (m,) twice the unsigned xy area (mm^2).
    """
    x, y = tri[:, :, 0], tri[:, :, 1]
    area2 = (x[:, 1] - x[:, 0]) * (y[:, 2] - y[:, 0]) - (x[:, 2] - x[:, 0]) * (y[:, 1] - y[:, 0])
    sign = np.sign(area2)
    j = np.array([1, 2, 0])
    k = np.array([2, 0, 1])
    dx = x[:, k] - x[:, j]
    dy = y[:, k] - y[:, j]
    length = np.hypot(dx, dy)
    a = -dy * sign[:, None] / length
    b = dx * sign[:, None] / length
    c = -(a * x[:, j] + b * y[:, j])
    return np.stack([a, b, c], axis=-1), length, np.abs(area2)


def rasterize_triangles(
    triangles,
    grid: RasterGrid,
    reduce: Literal["min", "max"] = "min",
    return_face_index: bool = False,
    return_barycentric: bool = False,
    edge_tolerance_mm: float = EDGE_TOLERANCE_MM,
) -> Raster:
    """Rasterise triangles onto ``grid``: per pixel centre, the z of the covering triangle.

    Parameters
    ----------
    triangles : (m, 3, 3) float, mm
        Vertex xyz of each triangle, in the frame of ``grid``.
    grid : RasterGrid
        Pixel centres (mm).
    reduce : "min" or "max"
        Which z to keep where several triangles cover a pixel centre (``min``: the lower
        envelope, e.g. an indenter's pressing surface; ``max``: the upper envelope, e.g. a
        camera looking down).
    return_face_index, return_barycentric : bool
        Also return the winning triangle index and its barycentric weights per pixel.
    edge_tolerance_mm : float
        Pixel centres this close to a triangle (in xy) count as covered.

    Returns
    -------
    Raster
        ``z_mm`` (ny, nx) float64 with NaN where nothing covers, plus the optional arrays.
    """
    tri = np.asarray(triangles, dtype=np.float64)
    if tri.ndim != 3 or tri.shape[1:] != (3, 3):
        raise ValueError(f"triangles must have shape (m, 3, 3), got {tri.shape}")
    if not np.all(np.isfinite(tri)):
        raise ValueError("triangles contain NaN or inf coordinates")
    if reduce not in ("min", "max"):
        raise ValueError(f"reduce must be 'min' or 'max', got {reduce!r}")
    if not edge_tolerance_mm >= 0:
        raise ValueError(f"edge_tolerance_mm must be >= 0, got {edge_tolerance_mm!r}")
    want_index = return_face_index or return_barycentric
    n_pix = grid.nx * grid.ny
    fill = np.inf if reduce == "min" else -np.inf
    z_best = np.full(n_pix, fill)
    face_best = np.full(n_pix, _NO_FACE, dtype=np.int64) if want_index else None

    # Keep triangles that are not vertical and reach the grid.
    tol = float(edge_tolerance_mm)
    p = grid.pitch_mm
    v0, v1, v2 = tri[:, 0], tri[:, 1], tri[:, 2]
    xy_lo = np.minimum(np.minimum(v0[:, :2], v1[:, :2]), v2[:, :2]) - tol
    xy_hi = np.maximum(np.maximum(v0[:, :2], v1[:, :2]), v2[:, :2]) + tol
    normal = np.cross(v1 - v0, v2 - v0)  # (m, 3); z component = twice the signed xy area
    row_lo = np.maximum(np.ceil((xy_lo[:, 1] - grid.y0_mm) / p), 0)
    row_hi = np.minimum(np.floor((xy_hi[:, 1] - grid.y0_mm) / p), grid.ny - 1)
    col_lo = np.maximum(np.ceil((xy_lo[:, 0] - grid.x0_mm) / p), 0)
    col_hi = np.minimum(np.floor((xy_hi[:, 0] - grid.x0_mm) / p), grid.nx - 1)
    keep = (
        (np.abs(normal[:, 2]) > _VERTICAL * np.linalg.norm(normal, axis=1))
        & (row_hi >= row_lo)
        & (col_hi >= col_lo)
    )
    steep = np.hypot(normal[:, 0], normal[:, 1]) > _STEEP_GRADIENT * np.abs(normal[:, 2])
    for clamp in (False, True):
        index = np.flatnonzero(keep & (steep == clamp))
        if index.size == 0:
            continue
        n_rows = (row_hi - row_lo + 1)[index].astype(np.int64)
        estimate = n_rows * (col_hi - col_lo + 1)[index].astype(np.int64)
        # Chunk boundaries so that each chunk expands at most ~_CHUNK_PIXELS candidates.
        cum = np.cumsum(estimate)
        bounds = np.searchsorted(cum, np.arange(_CHUNK_PIXELS, cum[-1], _CHUNK_PIXELS), side="right")
        starts = np.unique(np.concatenate([[0], bounds, [index.size]]))
        for s, e in zip(starts[:-1], starts[1:]):
            _raster_chunk(tri, index[s:e], row_lo[index[s:e]].astype(np.int64), n_rows[s:e],
                          grid, tol, reduce, clamp, z_best, face_best)

    covered = np.isfinite(z_best)
    z = np.where(covered, z_best, np.nan).reshape(grid.ny, grid.nx)
    face_index = None
    bary = None
    if want_index:
        face_best[face_best == _NO_FACE] = -1
        face_index = face_best.reshape(grid.ny, grid.nx)
        if return_barycentric:
            bary = np.full((n_pix, 3), np.nan)
            hit = np.flatnonzero(face_best >= 0)
            faces = face_best[hit]
            with np.errstate(divide="ignore", invalid="ignore"):
                abc, length, area2_abs = _edge_coefficients(tri)
                coef = abc * (length / area2_abs[:, None])[:, :, None]  # (m, 3, 3)
            px = grid.x0_mm + (hit % grid.nx) * p
            py = grid.y0_mm + (hit // grid.nx) * p
            w = [
                coef[:, i, 0].take(faces) * px + coef[:, i, 1].take(faces) * py
                + coef[:, i, 2].take(faces)
                for i in range(3)
            ]
            total = w[0] + w[1] + w[2]
            for i in range(3):
                bary[hit, i] = w[i] / total
            bary = bary.reshape(grid.ny, grid.nx, 3)
        if not return_face_index:
            face_index = None
    return Raster(grid=grid, z_mm=z, face_index=face_index, barycentric=bary)


def _raster_chunk(tri, index, row_lo, n_rows, grid, tol, reduce, clamp, z_best, face_best):
    """Rasterise triangles ``tri[index]`` and merge into ``z_best`` / ``face_best`` in place.

    ``row_lo`` (t,) is the first pixel row of each triangle and ``n_rows`` (t,) how many rows it
    spans. ``clamp``: move centres in the tolerance band onto the triangle before evaluating its
    plane, and clamp z to the triangle's z range (for steep triangles). All
    x below are relative to the grid origin ``x0_mm``; all y relative to a triangle's first row.
    """
    p = grid.pitch_mm
    sub = tri[index].transpose(2, 1, 0)  # (xyz, vertex, t)
    x = sub[0] - grid.x0_mm
    y = sub[1] - (grid.y0_mm + row_lo * p)
    z = sub[2]
    area2 = (x[1] - x[0]) * (y[2] - y[0]) - (x[2] - x[0]) * (y[1] - y[0])  # signed
    sign = np.sign(area2)

    # Edge i runs from vertex j = i + 1 to k = i + 2. On a row at height dy above the first row
    # its tolerance-widened half-plane is x >= alpha + beta dy (a "lower" bound, when the
    # interior lies to its right in x) or x <= alpha + beta dy (an "upper" bound).
    alpha, beta, lower, upper = [], [], [], []
    with np.errstate(divide="ignore", invalid="ignore"):
        for i in range(3):
            j, k = (i + 1) % 3, (i + 2) % 3
            ex, ey = x[k] - x[j], y[k] - y[j]
            # Edge normal x component, interior side: a = -ey * sign / |e|.
            b_over_a = ex / ey
            beta.append(b_over_a)
            alpha.append(x[j] - b_over_a * y[j] + tol * np.hypot(ex, ey) / (ey * sign))
            lower.append(ey * sign < 0)
            upper.append(ey * sign > 0)
    # Two lower and two upper lines per triangle: the first and last edge of each kind (the
    # same edge twice when there is only one; a horizontal edge is neither: it bounds the rows,
    # which the row range already does).
    def pick(values, first_of, mask):
        if first_of:
            return np.where(mask[0], values[0], np.where(mask[1], values[1], values[2]))
        return np.where(mask[2], values[2], np.where(mask[1], values[1], values[0]))

    # Plane through the vertices (barycentric interpolation): z = z_origin + gx x + gy dy.
    with np.errstate(divide="ignore", invalid="ignore"):
        grad_x = -((y[2] - y[1]) * z[0] + (y[0] - y[2]) * z[1] + (y[1] - y[0]) * z[2]) / area2
        grad_y = ((x[2] - x[1]) * z[0] + (x[0] - x[2]) * z[1] + (x[1] - x[0]) * z[2]) / area2
    table = np.empty((25 if clamp else 14, index.size))
    table[0] = pick(alpha, True, lower)
    table[1] = pick(alpha, False, lower)
    table[2] = pick(beta, True, lower)
    table[3] = pick(beta, False, lower)
    table[4] = pick(alpha, True, upper)
    table[5] = pick(alpha, False, upper)
    table[6] = pick(beta, True, upper)
    table[7] = pick(beta, False, upper)
    table[8] = np.minimum(np.minimum(x[0], x[1]), x[2]) - tol
    table[9] = np.maximum(np.maximum(x[0], x[1]), x[2]) + tol
    table[10] = row_lo
    table[11] = z[0] - grad_x * x[0] - grad_y * y[0]
    table[12] = grad_x
    table[13] = grad_y
    if clamp:
        table[14] = np.minimum(np.minimum(z[0], z[1]), z[2])
        table[15] = np.maximum(np.maximum(z[0], z[1]), z[2])
        for i in range(3):  # unit edge normals (interior side) and offsets: a x + b y + c
            j, k = (i + 1) % 3, (i + 2) % 3
            ex, ey = x[k] - x[j], y[k] - y[j]
            length = np.hypot(ex, ey)
            table[16 + i] = -ey * sign / length
            table[19 + i] = ex * sign / length
            table[22 + i] = -(table[16 + i] * x[j] + table[19 + i] * y[j])
    # One entry per (triangle, pixel row); each quantity is a contiguous row of ``rows``.
    rows = np.repeat(table, n_rows, axis=1)
    first = np.repeat(np.cumsum(n_rows) - n_rows, n_rows)
    local_row = np.arange(rows.shape[1]) - first
    dy = local_row * p
    lo = np.maximum(np.maximum(rows[0] + rows[2] * dy, rows[1] + rows[3] * dy), rows[8])
    hi = np.minimum(np.minimum(rows[4] + rows[6] * dy, rows[5] + rows[7] * dy), rows[9])
    c_lo = np.maximum(np.ceil(lo / p), 0)
    c_hi = np.minimum(np.floor(hi / p), grid.nx - 1)
    width = np.maximum(c_hi - c_lo + 1, 0).astype(np.int64)
    total = int(width.sum())
    if total == 0:
        return
    iy = rows[10].astype(np.int64) + local_row
    dz = rows[12] * p
    z_col0 = rows[11] + rows[13] * dy  # z of the row's plane at column 0

    # One entry per covered pixel: pixel k of a row's span is column c_lo + k. Values depend only
    # on (row, column), so chunking does not change the result.
    first_pix = np.cumsum(width) - width
    col = np.repeat(c_lo.astype(np.int64) - first_pix, width) + np.arange(total)
    pix = np.repeat(iy * grid.nx, width) + col
    zp = np.repeat(z_col0, width) + np.repeat(dz, width) * col
    if clamp:
        # Move centres in the tolerance band onto the triangle, then evaluate its plane there.
        px = col * p
        py = np.repeat(dy, width)
        qx, qy = px.copy(), py.copy()
        for i in range(3):
            ea, eb = np.repeat(rows[16 + i], width), np.repeat(rows[19 + i], width)
            outside = np.minimum(ea * px + eb * py + np.repeat(rows[22 + i], width), 0.0)
            qx -= outside * ea
            qy -= outside * eb
        zp = np.repeat(rows[11], width) + np.repeat(rows[12], width) * qx + np.repeat(rows[13], width) * qy
        np.clip(zp, np.repeat(rows[14], width), np.repeat(rows[15], width), out=zp)

    reducer = np.minimum if reduce == "min" else np.maximum
    if face_best is None:
        reducer.at(z_best, pix, zp)
        return
    # Merge z, then give each pixel the lowest face index attaining its (possibly new) best z.
    z_before = z_best[pix]
    reducer.at(z_best, pix, zp)
    z_after = z_best[pix]
    face_best[pix[z_after != z_before]] = _NO_FACE  # an earlier winner was beaten
    win = zp == z_after
    np.minimum.at(face_best, pix[win], np.repeat(np.repeat(index, n_rows), width)[win])
