"""Rigid indenters: a closed mesh in the indenter frame and its pressing surface (lower envelope).

Indenter frame (mm): origin at the indenter's reference point (for a mesh: the centre of its
bounding box in x, y), z up, pressing surface facing -z (towards the gel) with its lowest point
at z = 0. The pressing surface is described by its **envelope**: the height (mm) of the lowest
point of the indenter above each indenter-frame (x, y), measured from the lowest point overall.

Only the part of the envelope within ``max_relief_mm`` of the lowest point can ever touch the gel
(a pose is never pressed deeper than that); higher or uncovered points report ``+inf``.

For a mesh the envelope is rasterised once (``min`` z over the mesh's triangles at the centres of
a ``pitch_mm`` grid, :mod:`tactile_deploy.raster`) and sampled bilinearly (:class:`EnvelopeGrid`);
the grid is cached in memory and, keyed by the mesh content, on disk. Analytic indenters
(:class:`AnalyticSphere`, :class:`AnalyticParaboloid`) evaluate their envelope exactly.

Intrusion of an indenter at a pose (see :mod:`tactile_deploy.indenters.pose`) at sensor-frame
points p: ``delta = depth_mm - envelope(q)`` with ``q = R(-theta) (p - (x, y))``; ``delta > 0``
where the rigid indenter reaches below the rest sensing surface z = 0, ``-inf`` where it does
not cover p.
"""

from __future__ import annotations

import hashlib
import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from tactile_deploy.atomic import write_npz
from tactile_deploy.indenters.pose import (
    ContactPose,
    pose_matrix,
    sensor_to_indenter_xy,
)
from tactile_deploy.indenters.shapes import paraboloid, sphere
from tactile_deploy.raster import RasterGrid, rasterize_triangles

if TYPE_CHECKING:  # trimesh is imported lazily: it takes seconds to import
    import trimesh

log = logging.getLogger(__name__)

#: Default pitch (mm) of the rasterised envelope of a mesh indenter.
DEFAULT_PITCH_MM = 0.025
#: Default relief (mm) above the lowest point up to which the envelope is kept.
DEFAULT_MAX_RELIEF_MM = 4.0
#: Finite stand-in for +inf when an envelope grid is sampled by interpolation code that cannot
#: carry inf (torch ``grid_sample``: inf * 0 = NaN). Any bilinear sample with a non-zero weight on
#: such a pixel exceeds ``max_relief_mm`` and so reads as outside. Fits float32.
ENVELOPE_OUTSIDE_MM = 1e30
# Fractional pixel positions closer than this to a pixel line are snapped onto it.
_SNAP_PIXELS = 1e-6
# Largest envelope grid (pixels) built for a mesh: 64 MB of float32.
_MAX_GRID_PIXELS = 1 << 24
# Bump when the rasterised envelope changes for the same mesh (invalidates the disk cache).
_ENVELOPE_CACHE_VERSION = 1
_USE_DEFAULT_CACHE = "default"


@dataclass(frozen=True, eq=False)
class EnvelopeGrid:
    """An indenter's pressing surface sampled on a regular grid (indenter frame, mm).

    heights_mm : (ny, nx) float32, mm
        Envelope at pixel centres ``(x0_mm + ix * pitch_mm, y0_mm + iy * pitch_mm)``; ``+inf``
        where uncovered or higher than ``max_relief_mm``. The outermost rows and columns are
        always ``+inf``.

    How to sample it (this is what :meth:`sample_mm`, and so ``Indenter.envelope_mm`` for a mesh
    indenter, does): replace ``+inf`` by :data:`ENVELOPE_OUTSIDE_MM` (``finite_heights_mm()``),
    interpolate bilinearly between the four surrounding pixel centres, and read values greater
    than ``max_relief_mm`` (and points beyond the outer pixel centres) as ``+inf``. (Positions
    within 1e-6 pixel of a pixel row or column are snapped onto it, so that rounding cannot
    give weight to an outside neighbour.) With torch::

        h = torch.as_tensor(grid.finite_heights_mm())[None, None]          # (1, 1, ny, nx)
        uv = torch.as_tensor(grid.normalized_coordinates(q_xy))[None, None]  # (1, 1, k, 2)
        e = F.grid_sample(h, uv, mode="bilinear", padding_mode="border",
                          align_corners=True)[0, 0, 0]                     # (k,)
        e = torch.where(e > grid.max_relief_mm, torch.inf, e)

    (``padding_mode="border"`` repeats the all-outside border; for intrusion
    ``depth - e`` the last line may be skipped: outside then gives about -1e30 instead of -inf).
    """

    heights_mm: np.ndarray
    x0_mm: float
    y0_mm: float
    pitch_mm: float
    max_relief_mm: float

    @property
    def ny(self) -> int:
        return self.heights_mm.shape[0]

    @property
    def nx(self) -> int:
        return self.heights_mm.shape[1]

    def finite_heights_mm(self) -> np.ndarray:
        """(ny, nx) float32, mm: ``heights_mm`` with +inf replaced by ENVELOPE_OUTSIDE_MM."""
        cached = self.__dict__.get("_finite")
        if cached is None:
            cached = np.where(np.isfinite(self.heights_mm), self.heights_mm, ENVELOPE_OUTSIDE_MM)
            cached = cached.astype(np.float32)
            cached.flags.writeable = False
            object.__setattr__(self, "_finite", cached)
        return cached

    def normalized_coordinates(self, q_xy_mm) -> np.ndarray:
        """Indenter-frame points (k, 2) mm -> (k, 2) float64 coordinates in [-1, 1] for
        ``torch.nn.functional.grid_sample(..., align_corners=True)`` (x first)."""
        q = np.asarray(q_xy_mm, dtype=np.float64)
        u = 2.0 * (q[:, 0] - self.x0_mm) / (self.pitch_mm * (self.nx - 1)) - 1.0
        v = 2.0 * (q[:, 1] - self.y0_mm) / (self.pitch_mm * (self.ny - 1)) - 1.0
        return np.stack([u, v], axis=1)

    def sample_mm(self, q_xy_mm) -> np.ndarray:
        """Envelope at indenter-frame points q (k, 2) mm -> (k,) float64 mm, +inf outside."""
        q = np.asarray(q_xy_mm, dtype=np.float64)
        h = self.finite_heights_mm()
        u = (q[:, 0] - self.x0_mm) / self.pitch_mm
        v = (q[:, 1] - self.y0_mm) / self.pitch_mm
        # A point within rounding of a pixel row or column takes no weight from its neighbour.
        u = np.where(np.abs(u - np.round(u)) < _SNAP_PIXELS, np.round(u), u)
        v = np.where(np.abs(v - np.round(v)) < _SNAP_PIXELS, np.round(v), v)
        inside = (u >= 0) & (u <= self.nx - 1) & (v >= 0) & (v <= self.ny - 1)
        u = np.where(inside, u, 0.0)
        v = np.where(inside, v, 0.0)
        i = np.minimum(np.floor(u), self.nx - 2).astype(np.intp)
        j = np.minimum(np.floor(v), self.ny - 2).astype(np.intp)
        fx = u - i
        fy = v - j
        flat = h.ravel()
        k = j * self.nx + i
        top = flat[k] * (1.0 - fx) + flat[k + 1] * fx
        bottom = flat[k + self.nx] * (1.0 - fx) + flat[k + self.nx + 1] * fx
        e = top * (1.0 - fy) + bottom * fy
        return np.where(inside & (e <= self.max_relief_mm), e, np.inf)

    def coverage_distance_mm(self, q_xy_mm):
        """Signed distance (indenter frame, mm) from points q (k, 2) to the outline of the
        region the envelope covers, negative inside, and its unit gradient (k, 2) (pointing
        away from the region).

        The covered pixels' outline is a staircase of ``pitch_mm`` steps; the indenter's true
        outline (a punch's straight rim) runs through it. The distance is taken to the
        straight-edged outline the staircase samples: the signed distance between covered and
        uncovered pixel centres (Euclidean distance transform), smoothed over one pixel,
        interpolated bilinearly (value and gradient). Within half a pixel of the staircase;
        saturates 8 pixels away from it."""
        sdf, gx, gy = self._coverage_field()
        q = np.asarray(q_xy_mm, dtype=np.float64).reshape(-1, 2)
        u = np.clip((q[:, 0] - self.x0_mm) / self.pitch_mm, 0.0, self.nx - 1.0)
        v = np.clip((q[:, 1] - self.y0_mm) / self.pitch_mm, 0.0, self.ny - 1.0)
        i = np.minimum(np.floor(u), self.nx - 2).astype(np.intp)
        j = np.minimum(np.floor(v), self.ny - 2).astype(np.intp)
        fx, fy = u - i, v - j

        def interp(a):
            return ((a[j, i] * (1 - fx) + a[j, i + 1] * fx) * (1 - fy)
                    + (a[j + 1, i] * (1 - fx) + a[j + 1, i + 1] * fx) * fy)

        # beyond the grid the distance keeps growing with the distance to it
        dist = interp(sdf) + np.hypot(u - (q[:, 0] - self.x0_mm) / self.pitch_mm,
                                      v - (q[:, 1] - self.y0_mm) / self.pitch_mm) * self.pitch_mm
        g = np.stack([interp(gx), interp(gy)], axis=1)
        norm = np.linalg.norm(g, axis=1, keepdims=True)
        g = np.where(norm > 1e-12, g / np.maximum(norm, 1e-300), np.array([[1.0, 0.0]]))
        return dist, g

    def _coverage_field(self):
        cached = self.__dict__.get("_coverage")
        if cached is None:
            from scipy.ndimage import distance_transform_edt, gaussian_filter

            finite = np.isfinite(self.heights_mm)
            reach = 8.0
            outside = np.minimum(distance_transform_edt(~finite), reach + 0.5)
            inside = np.minimum(distance_transform_edt(finite), reach + 0.5)
            sdf = np.where(finite, 0.5 - inside, outside - 0.5)
            sdf = gaussian_filter(sdf, 1.0, mode="nearest") * self.pitch_mm
            gy, gx = np.gradient(sdf, self.pitch_mm)
            cached = (sdf, gx, gy)
            object.__setattr__(self, "_coverage", cached)
        return cached


def default_cache_dir() -> Path | None:
    """Folder of the on-disk envelope cache: ``$TACTILE_DEPLOY_CACHE_DIR/indenters`` when that
    variable is set (an empty value turns the disk cache off), else
    ``~/.cache/tactile-deploy/indenters``."""
    root = os.environ.get("TACTILE_DEPLOY_CACHE_DIR")
    if root is None:
        return Path("~/.cache/tactile-deploy").expanduser() / "indenters"
    if root.strip() == "":
        return None
    return Path(root).expanduser() / "indenters"


def _check_points(points, name: str) -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 2:
        raise ValueError(f"{name} must have shape (k, 2), got {p.shape}")
    return p


class Indenter:
    """A rigid indenter: a closed triangle mesh and its pressing surface.

    Parameters
    ----------
    mesh : trimesh.Trimesh, mm
        The indenter with its pressing face towards -z. It is moved into the indenter frame:
        bounding-box centre in x, y to the origin, lowest point to z = 0.
    name : str
        Short name (library name or file stem).
    kind : str
        "primitive", "novel" (procedural library), "file" (loaded mesh) or "analytic".
    pitch_mm : float
        Pitch of the rasterised envelope grid (mm). Interpolation error of the envelope is about
        ``curvature * pitch_mm**2 / 8``; near a vertical wall the footprint is eroded by up to
        one pitch.
    max_relief_mm : float
        Relief above the lowest point up to which the envelope is kept (mm); poses deeper than
        this are refused.
    cache_dir : Path, None or "default"
        Where the envelope grid is cached on disk ("default": :func:`default_cache_dir`;
        None: memory only).
    """

    def __init__(
        self,
        mesh: "trimesh.Trimesh",
        name: str,
        kind: str = "file",
        *,
        pitch_mm: float = DEFAULT_PITCH_MM,
        max_relief_mm: float = DEFAULT_MAX_RELIEF_MM,
        cache_dir: Path | str | None = _USE_DEFAULT_CACHE,
    ) -> None:
        if not (math.isfinite(pitch_mm) and pitch_mm > 0):
            raise ValueError(f"indenter {name!r}: pitch_mm must be > 0, got {pitch_mm!r}")
        if not (math.isfinite(max_relief_mm) and max_relief_mm > 0):
            raise ValueError(f"indenter {name!r}: max_relief_mm must be > 0, got {max_relief_mm!r}")
        self.name = name
        self.kind = kind
        self.pitch_mm = float(pitch_mm)
        self.max_relief_mm = float(max_relief_mm)
        self._cache_dir = cache_dir
        self._grid: EnvelopeGrid | None = None
        self._footprint_radius: float | None = None
        self._mesh = None if mesh is None else _to_indenter_frame(mesh, name)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r}, kind={self.kind!r})"

    # -- geometry ------------------------------------------------------------------------------

    @property
    def mesh(self) -> "trimesh.Trimesh":
        """The indenter in the indenter frame (mm), pressing face down, lowest point z = 0.

        Shared, not copied: do not modify it (use ``mesh.copy()``)."""
        return self._mesh

    @property
    def content_hash(self) -> str:
        """sha256 (hex) of the mesh vertices (float64) and faces (int64)."""
        h = hashlib.sha256()
        h.update(np.ascontiguousarray(self.mesh.vertices, dtype=np.float64).tobytes())
        h.update(np.ascontiguousarray(self.mesh.faces, dtype=np.int64).tobytes())
        return h.hexdigest()

    def mesh_in_sensor_frame(self, pose: ContactPose) -> "trimesh.Trimesh":
        """A copy of the mesh placed at ``pose`` in the sensor frame (mm): lowest point at
        z = -depth_mm, origin at (x_mm, y_mm), rotated by theta_deg about +z."""
        moved = self.mesh.copy()
        moved.apply_transform(pose_matrix(pose))
        return moved

    # -- pressing surface ----------------------------------------------------------------------

    def envelope_grid(self) -> EnvelopeGrid:
        """The rasterised envelope (cached in memory and, for meshes, on disk)."""
        if self._grid is None:
            self._grid = self._load_or_build_grid()
        return self._grid

    def envelope_mm(self, q_xy_mm) -> np.ndarray:
        """Height (mm) of the pressing surface above its lowest point at indenter-frame points.

        q_xy_mm : (k, 2) float, mm, indenter frame.
        Returns (k,) float64, mm; +inf outside the footprint or above ``max_relief_mm``.
        """
        return self.envelope_grid().sample_mm(_check_points(q_xy_mm, "q_xy_mm"))

    def intrusion_mm(self, points_xy_sensor_mm, pose: ContactPose) -> np.ndarray:
        """Intrusion of the indenter at ``pose`` below the rest surface z = 0 at sensor points.

        points_xy_sensor_mm : (k, 2) float, mm, sensor frame.
        Returns (k,) float64, mm: ``depth_mm - envelope(q)``; > 0 where the rigid indenter
        reaches below z = 0, -inf where it does not cover the point.
        """
        if not isinstance(pose, ContactPose):
            raise TypeError(f"pose must be a ContactPose, got {type(pose).__name__}")
        if pose.depth_mm > self.max_relief_mm:
            raise ValueError(
                f"pose.depth_mm={pose.depth_mm} exceeds max_relief_mm={self.max_relief_mm} of "
                f"indenter {self.name!r}: its pressing surface is only kept to that relief; "
                f"build it with a larger max_relief_mm"
            )
        q = sensor_to_indenter_xy(_check_points(points_xy_sensor_mm, "points_xy_sensor_mm"), pose)
        return pose.depth_mm - self._envelope_unchecked(q)

    def _envelope_unchecked(self, q: np.ndarray) -> np.ndarray:
        return self.envelope_grid().sample_mm(q)

    def coverage_distance_mm(self, points_xy_sensor_mm, pose: ContactPose):
        """Where the pressing surface ends: signed distance (k,) mm from sensor-frame points
        (k, 2) mm to the edge of the region the indenter covers (where ``intrusion_mm`` is
        finite; negative inside), and its gradient (k, 2), the unit direction away from that
        region, sensor frame. Above a punch's rim the indenter's side rises as a wall along
        this edge."""
        q = sensor_to_indenter_xy(_check_points(points_xy_sensor_mm, "points_xy_sensor_mm"), pose)
        d, g = self._coverage_unchecked(q)
        c, s = math.cos(math.radians(pose.theta_deg)), math.sin(math.radians(pose.theta_deg))
        return d, np.stack([c * g[:, 0] - s * g[:, 1], s * g[:, 0] + c * g[:, 1]], axis=1)

    def _coverage_unchecked(self, q: np.ndarray):
        return self.envelope_grid().coverage_distance_mm(q)

    @property
    def footprint_radius_mm(self) -> float:
        """Radius (mm) of the smallest origin-centred disc holding every indenter-frame point
        where the envelope is finite (within ``max_relief_mm`` of the lowest point)."""
        if self._footprint_radius is None:
            self._footprint_radius = self._compute_footprint_radius()
        return self._footprint_radius

    def _compute_footprint_radius(self) -> float:
        g = self.envelope_grid()
        # A bilinear sample is finite only inside the hull of finite pixel centres.
        iy, ix = np.nonzero(np.isfinite(g.heights_mm))
        return float(np.hypot(g.x0_mm + ix * g.pitch_mm, g.y0_mm + iy * g.pitch_mm).max())

    # -- grid construction and caching -----------------------------------------------------------

    def _cache_path(self) -> Path | None:
        folder = default_cache_dir() if self._cache_dir == _USE_DEFAULT_CACHE else self._cache_dir
        if folder is None:
            return None
        h = hashlib.sha256(self.content_hash.encode())
        h.update(f"v{_ENVELOPE_CACHE_VERSION} {self.pitch_mm!r} {self.max_relief_mm!r}".encode())
        return Path(folder) / f"{h.hexdigest()[:32]}.npz"

    def _load_or_build_grid(self) -> EnvelopeGrid:
        path = self._cache_path()
        if path is not None and path.exists():
            grid = _read_grid(path, self.pitch_mm, self.max_relief_mm)
            if grid is not None:
                return grid
        grid = self._build_grid()
        if path is not None:
            try:
                path.parent.mkdir(parents=True, exist_ok=True)
                write_npz(path, heights_mm=grid.heights_mm,
                          origin_mm=np.array([grid.x0_mm, grid.y0_mm]),
                          pitch_mm=np.float64(grid.pitch_mm),
                          max_relief_mm=np.float64(grid.max_relief_mm))
            except OSError as err:
                log.warning("could not cache the envelope of %s at %s: %s", self.name, path, err)
        return grid

    def _build_grid(self) -> EnvelopeGrid:
        tri = self.mesh.triangles
        low = tri[:, :, 2].min(axis=1) <= self.max_relief_mm
        tri = tri[low]
        xy = tri[:, :, :2].reshape(-1, 2)
        raster = RasterGrid.covering(xy.min(axis=0), xy.max(axis=0), self.pitch_mm, pad_pixels=2)
        if raster.nx * raster.ny > _MAX_GRID_PIXELS:
            raise ValueError(
                f"indenter {self.name!r}: its pressing surface spans "
                f"{np.ptp(xy[:, 0]):.1f} x {np.ptp(xy[:, 1]):.1f} mm, a {raster.nx} x {raster.ny} "
                f"envelope grid at pitch_mm={self.pitch_mm:g}; at most {_MAX_GRID_PIXELS} pixels "
                f"are allowed: pass a larger pitch_mm or a smaller max_relief_mm"
            )
        z = rasterize_triangles(tri, raster, reduce="min").z_mm
        heights = np.where(z <= self.max_relief_mm, z, np.inf).astype(np.float32)
        heights[[0, -1], :] = np.inf
        heights[:, [0, -1]] = np.inf
        heights.flags.writeable = False
        return EnvelopeGrid(heights, raster.x0_mm, raster.y0_mm, raster.pitch_mm, self.max_relief_mm)


def _read_grid(path: Path, pitch_mm: float, max_relief_mm: float) -> EnvelopeGrid | None:
    """Envelope grid from a cache file, or None (with a warning) if it is unreadable or stale."""
    try:
        with np.load(path) as f:
            heights = f["heights_mm"]
            origin = f["origin_mm"]
            pitch = float(f["pitch_mm"])
            relief = float(f["max_relief_mm"])
    except Exception as err:  # a damaged cache file is rebuilt, never trusted
        log.warning("ignoring unreadable envelope cache %s: %s", path, err)
        return None
    if (heights.dtype != np.float32 or heights.ndim != 2 or min(heights.shape) < 3
            or origin.shape != (2,) or pitch != pitch_mm or relief != max_relief_mm):
        log.warning("ignoring envelope cache %s: unexpected contents", path)
        return None
    heights.flags.writeable = False
    return EnvelopeGrid(heights, float(origin[0]), float(origin[1]), pitch, relief)


def _to_indenter_frame(mesh, name: str):
    """Copy of ``mesh`` translated so that its x, y bounding-box centre is the origin and its
    lowest point is at z = 0."""
    import trimesh

    if not isinstance(mesh, trimesh.Trimesh):
        raise TypeError(f"indenter {name!r}: mesh must be a trimesh.Trimesh, got {type(mesh).__name__}")
    if len(mesh.faces) == 0:
        raise ValueError(f"indenter {name!r}: mesh has no faces")
    if not np.all(np.isfinite(mesh.vertices)):
        raise ValueError(f"indenter {name!r}: mesh has NaN or inf vertices")
    moved = mesh.copy()
    lo, hi = moved.bounds
    moved.apply_translation([-(lo[0] + hi[0]) / 2, -(lo[1] + hi[1]) / 2, -lo[2]])
    # Make the frame exact despite rounding of the translation.
    moved.vertices[:, 2] -= moved.vertices[:, 2].min()
    return moved


class AnalyticIndenter(Indenter):
    """An axisymmetric indenter whose envelope ``h(r)`` is known in closed form.

    ``envelope_mm`` evaluates ``h`` exactly (used by validation where mesh faceting would bias
    results); ``envelope_grid()`` samples ``h`` at pixel centres for batched code, and ``mesh``
    is a finely faceted solid for rendering.
    """

    def __init__(self, name: str, *, pitch_mm: float, max_relief_mm: float) -> None:
        super().__init__(None, name, "analytic", pitch_mm=pitch_mm, max_relief_mm=max_relief_mm,
                         cache_dir=None)

    def height_of_radius_mm(self, r_mm: np.ndarray) -> np.ndarray:
        """Envelope h(r) (mm) at distance r (mm) from the axis, without the relief limit."""
        raise NotImplementedError

    @property
    def mesh(self) -> "trimesh.Trimesh":
        if self._mesh is None:
            self._mesh = _to_indenter_frame(self._build_mesh(), self.name)
        return self._mesh

    def _build_mesh(self) -> "trimesh.Trimesh":
        raise NotImplementedError

    def _footprint_radius_exact(self) -> float:
        raise NotImplementedError

    def envelope_mm(self, q_xy_mm) -> np.ndarray:
        return self._envelope_unchecked(_check_points(q_xy_mm, "q_xy_mm"))

    def _envelope_unchecked(self, q: np.ndarray) -> np.ndarray:
        h = self.height_of_radius_mm(np.hypot(q[:, 0], q[:, 1]))
        return np.where(h <= self.max_relief_mm, h, np.inf)

    def _compute_footprint_radius(self) -> float:
        return self._footprint_radius_exact()

    def _coverage_unchecked(self, q: np.ndarray):
        r = np.hypot(q[:, 0], q[:, 1])
        g = np.where(r[:, None] > 0, q / np.maximum(r, 1e-300)[:, None], np.array([[1.0, 0.0]]))
        return r - self._footprint_radius_exact(), g

    def _load_or_build_grid(self) -> EnvelopeGrid:
        r = self._footprint_radius_exact()
        raster = RasterGrid.covering([-r, -r], [r, r], self.pitch_mm, pad_pixels=2)
        c = raster.pixel_centres_mm().reshape(-1, 2)
        heights = self._envelope_unchecked(c).reshape(raster.ny, raster.nx).astype(np.float32)
        heights[[0, -1], :] = np.inf
        heights[:, [0, -1]] = np.inf
        heights.flags.writeable = False
        return EnvelopeGrid(heights, raster.x0_mm, raster.y0_mm, raster.pitch_mm, self.max_relief_mm)


class AnalyticSphere(AnalyticIndenter):
    """A sphere of radius R (mm): envelope ``R - sqrt(R^2 - r^2)`` for r < R, +inf beyond."""

    def __init__(self, radius_mm: float, *, pitch_mm: float = DEFAULT_PITCH_MM,
                 max_relief_mm: float = DEFAULT_MAX_RELIEF_MM) -> None:
        if not (math.isfinite(radius_mm) and radius_mm > 0):
            raise ValueError(f"AnalyticSphere: radius_mm must be > 0, got {radius_mm!r}")
        self.radius_mm = float(radius_mm)
        super().__init__(f"analytic_sphere_r{radius_mm:g}", pitch_mm=pitch_mm,
                         max_relief_mm=max_relief_mm)

    def height_of_radius_mm(self, r_mm):
        r = np.asarray(r_mm, dtype=np.float64)
        big = self.radius_mm
        with np.errstate(invalid="ignore"):
            return np.where(r < big, big - np.sqrt(np.maximum(big * big - r * r, 0.0)), np.inf)

    def _footprint_radius_exact(self) -> float:
        big, h = self.radius_mm, self.max_relief_mm
        return big if h >= big else math.sqrt(h * (2.0 * big - h))

    def _build_mesh(self):
        return sphere(self.radius_mm)


class AnalyticParaboloid(AnalyticIndenter):
    """A paraboloid of tip radius R (mm): envelope ``r^2 / (2 R)``. Its mesh is the paraboloid
    up to 1 mm above ``max_relief_mm``, closed by a flat top."""

    def __init__(self, radius_mm: float, *, pitch_mm: float = DEFAULT_PITCH_MM,
                 max_relief_mm: float = DEFAULT_MAX_RELIEF_MM) -> None:
        if not (math.isfinite(radius_mm) and radius_mm > 0):
            raise ValueError(f"AnalyticParaboloid: radius_mm must be > 0, got {radius_mm!r}")
        self.radius_mm = float(radius_mm)
        super().__init__(f"analytic_paraboloid_r{radius_mm:g}", pitch_mm=pitch_mm,
                         max_relief_mm=max_relief_mm)

    def height_of_radius_mm(self, r_mm):
        r = np.asarray(r_mm, dtype=np.float64)
        return r * r / (2.0 * self.radius_mm)

    def _footprint_radius_exact(self) -> float:
        return math.sqrt(2.0 * self.radius_mm * self.max_relief_mm)

    def _build_mesh(self):
        return paraboloid(self.radius_mm, self.max_relief_mm + 1.0)
