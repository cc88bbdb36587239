"""Speed benchmarks: the triangle rasteriser and the indenter intrusion query.

Cases (targets on a 2-core CPU):

* ``raster_10k``: ~10k triangles (a closed sphere, r 8 mm) onto a 701 x 701 grid at 0.025 mm,
  ``min`` only and with face index and barycentric weights (target < 0.2 s for ``min``);
* ``raster_pad``: ~2,100 small triangles (a pad's sensing surface, r 17.5 mm, ~1 mm edges) onto
  the 128 x 128 depth grid (target < 5 ms);
* ``envelope``: building an indenter's envelope grid (sphere_r6, uncached);
* ``intrusion``: ``Indenter.intrusion_mm`` at 1,100 points with the grid cached (target < 0.5 ms).

Run ``python -m tactile_deploy.indenters.benchmark`` (``--small`` for a quick check).
"""

from __future__ import annotations

import sys
import time

import numpy as np

from tactile_deploy.indenters import ContactPose, Indenter, get_indenter, library_entry
from tactile_deploy.raster import RasterGrid, rasterize_triangles


def _timeit(fn, repeats: int) -> dict:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return {"min_ms": 1e3 * min(times), "median_ms": 1e3 * float(np.median(times)), "repeats": repeats}


def pad_surface_triangles(n_points: int = 1080, radius_mm: float = 17.5, seed: int = 0) -> np.ndarray:
    """Delaunay triangles (m, 3, 3) mm of ``n_points`` spread over a disc, with a gentle dent."""
    from scipy.spatial import Delaunay

    rng = np.random.default_rng(seed)
    n_rim = int(2 * np.pi * radius_mm)
    rim = np.linspace(0, 2 * np.pi, n_rim, endpoint=False)
    r = radius_mm * np.sqrt(rng.uniform(0, 0.97, n_points - n_rim))
    a = rng.uniform(0, 2 * np.pi, len(r))
    xy = np.concatenate([np.c_[r * np.cos(a), r * np.sin(a)], radius_mm * np.c_[np.cos(rim), np.sin(rim)]])
    z = -0.5 * np.exp(-(xy**2).sum(axis=1) / 20.0)
    return np.c_[xy, z][Delaunay(xy).simplices]


def run(small: bool = False) -> dict[str, dict]:
    """Run every case; ``small``: fewer repeats and smaller grids. Returns timings per case."""
    import trimesh

    repeats = 2 if small else 15
    results = {}
    sphere = trimesh.creation.uv_sphere(radius=8.0, count=[36, 72])
    pitch = 0.1 if small else 0.025
    grid = RasterGrid.covering([-8.75, -8.75], [8.75, 8.75], pitch)
    tri = sphere.triangles
    results["raster_10k_min"] = _timeit(lambda: rasterize_triangles(tri, grid), repeats)
    results["raster_10k_min_index_bary"] = _timeit(
        lambda: rasterize_triangles(tri, grid, return_face_index=True, return_barycentric=True), repeats)
    results["raster_10k_min"].update(faces=len(tri), grid=f"{grid.nx}x{grid.ny}")

    pad = pad_surface_triangles()
    depth_grid = RasterGrid(-17.5 + 35 / 256, -17.5 + 35 / 256, 35 / 128, 128, 128)
    results["raster_pad_max"] = _timeit(lambda: rasterize_triangles(pad, depth_grid, reduce="max"),
                                        repeats * 10)
    results["raster_pad_max"].update(faces=len(pad), grid="128x128")
    results["raster_pad_max_index_bary"] = _timeit(
        lambda: rasterize_triangles(pad, depth_grid, reduce="max", return_face_index=True,
                                    return_barycentric=True), repeats * 10)

    mesh = library_entry("sphere_r6").build()
    results["envelope_sphere_r6"] = _timeit(
        lambda: Indenter(mesh, "sphere_r6", cache_dir=None, pitch_mm=pitch).envelope_grid(),
        max(1, repeats // 5))

    ind = get_indenter("sphere_r4")
    points = np.random.default_rng(1).uniform(-17.5, 17.5, (1100, 2))
    pose = ContactPose(x_mm=1.0, y_mm=-2.0, theta_deg=30.0, depth_mm=1.0)
    ind.intrusion_mm(points, pose)  # build and cache the grid
    results["intrusion_1100"] = _timeit(lambda: ind.intrusion_mm(points, pose), repeats * 100)
    return results


if __name__ == "__main__":
    for name, r in run(small="--small" in sys.argv).items():
        extra = {k: v for k, v in r.items() if k not in ("min_ms", "median_ms")}
        print(f"{name:28s} min {r['min_ms']:9.3f} ms  median {r['median_ms']:9.3f} ms  {extra}")
