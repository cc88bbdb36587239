"""Preview pictures of the runtime: the depth map and the coloured deformed mesh, side by side.

Pure numpy + OpenCV (no display needed): the mesh panel is an orthographic view of the pad's
outer surface from above and in front (``elev_deg`` above the pad plane, ``azim_deg`` around z),
rasterised with the project's triangle rasteriser, coloured by displacement magnitude on a fixed
scale (``max_mm``) and shaded by the face normal. Images are RGB uint8.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from tactile_deploy.atomic import atomic_path
from tactile_deploy.raster import RasterGrid, rasterize_triangles


def colourise(values: np.ndarray, vmax: float, colormap: int = cv2.COLORMAP_VIRIDIS) -> np.ndarray:
    """(...) floats in [0, vmax] -> (..., 3) uint8 RGB through an OpenCV colour map."""
    v = np.clip(np.nan_to_num(np.asarray(values, np.float32)) / max(vmax, 1e-9), 0.0, 1.0)
    u8 = (255.0 * v).astype(np.uint8)
    lut = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None], colormap)[:, 0, ::-1]
    return lut[u8]


def depth_panel(depth_mm: np.ndarray, size: int = 320, max_mm: float = 1.0) -> np.ndarray:
    """Depth map (128, 128) mm, row 0 = largest y -> (size, size, 3) RGB, fixed scale 0..max_mm."""
    img = colourise(np.maximum(depth_mm, 0.0), max_mm, cv2.COLORMAP_INFERNO)
    return cv2.resize(img, (size, size), interpolation=cv2.INTER_NEAREST)


class MeshRenderer:
    """Orthographic rendering of a deformed mesh's outer surface (module docstring)."""

    def __init__(self, topology, size: int = 320, elev_deg: float = 35.0,
                 azim_deg: float = -60.0, max_mm: float = 1.0, z_exaggeration: float = 3.0):
        self.faces = np.asarray(topology.surface_faces, np.int64)
        self.rest = np.asarray(topology.rest_vertices_mm, np.float64)
        self.size = int(size)
        self.max_mm = float(max_mm)
        self.z_exaggeration = float(z_exaggeration)
        a, e = math.radians(azim_deg), math.radians(elev_deg)
        # view rotation: world -> camera (x right, y up on screen, z towards the viewer)
        rz = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
        rx = np.array([[1, 0, 0], [0, math.sin(e), math.cos(e)], [0, -math.cos(e), math.sin(e)]])
        self.rot = rx @ rz
        pts = self._view(self.rest)
        lo, hi = pts[:, :2].min(0), pts[:, :2].max(0)
        span = float((hi - lo).max()) * 1.15
        self.pitch = span / self.size
        centre = 0.5 * (lo + hi)
        x0 = centre[0] - 0.5 * span + 0.5 * self.pitch
        y0 = centre[1] - 0.5 * span + 0.5 * self.pitch
        self.grid = RasterGrid(x0, y0, self.pitch, self.size, self.size)
        self.light = np.array([0.3, 0.5, 0.8]) / np.linalg.norm([0.3, 0.5, 0.8])

    def _view(self, vertices: np.ndarray) -> np.ndarray:
        v = vertices.copy()
        v[:, 2] = self.rest[:, 2] + self.z_exaggeration * (v[:, 2] - self.rest[:, 2])
        return v @ self.rot.T

    def render(self, vertices_mm: np.ndarray) -> np.ndarray:
        """(size, size, 3) uint8 RGB of the mesh deformed to ``vertices_mm`` (n, 3)."""
        v = np.asarray(vertices_mm, np.float64)
        mag = np.linalg.norm(v - self.rest, axis=1)
        pts = self._view(v)
        tri = pts[self.faces]
        r = rasterize_triangles(tri, self.grid, reduce="max", return_face_index=True,
                                return_barycentric=True)
        img = np.full((self.size, self.size, 3), 245, np.uint8)
        cov = r.covered
        if cov.any():
            fi = r.face_index[cov]
            bary = r.barycentric[cov]
            val = (mag[self.faces[fi]] * bary).sum(1)
            n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
            shade = 0.35 + 0.65 * np.abs(n[fi] @ self.light)
            col = colourise(val, self.max_mm).astype(np.float32) * shade[:, None]
            img[cov] = np.clip(col, 0, 255).astype(np.uint8)
        return img[::-1].copy()   # grid rows run up the screen; image rows run down


def compose_preview(depth_mm: np.ndarray, mesh_rgb: np.ndarray, lines: list[str],
                    max_depth_mm: float = 1.0) -> np.ndarray:
    """Depth panel | mesh panel, with text lines underneath (RGB uint8)."""
    size = mesh_rgb.shape[0]
    left = depth_panel(depth_mm, size, max_depth_mm)
    top = np.concatenate([left, np.full((size, 6, 3), 255, np.uint8), mesh_rgb], axis=1)
    text_h = 22 * max(len(lines), 1) + 8
    bottom = np.full((text_h, top.shape[1], 3), 255, np.uint8)
    for i, line in enumerate(lines):
        cv2.putText(bottom, line, (8, 20 + 22 * i), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (20, 20, 20),
                    1, cv2.LINE_AA)
    return np.concatenate([top, bottom], axis=0)


def write_png(path, rgb: np.ndarray) -> None:
    """Write an RGB image as PNG (atomic)."""

    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)):
            raise OSError(f"OpenCV could not write {path}")
