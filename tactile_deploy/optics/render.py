"""Render the RGB frame of a tactile sensor from a height map of its sensing surface.

Data flow of :meth:`OpticsRenderer.render`::

    height_mm (ny, nx) on the surface grid (sensor frame)
      --np.gradient (mm)--> slopes f_x, f_y
      --one cv2.remap through the camera mapping--> z, f_x, f_y at every raw camera pixel
      --shade: ambient + sum over LEDs of colour * fall-off * (n . l)+ [+ specular]-->
      --x albedo x vignetting x exposure gain--> radiance (H, W, 3) float32, grey levels
      --Gaussian blur, shot + read noise, round, clip to [0, saturation]--> frame (H, W, 3) uint8

Everything that does not depend on the surface (the sensor-frame point of every camera pixel,
light vectors at rest, fall-off, vignetting, albedo, half vectors) is computed once per model in
the constructor; a frame costs one remap and a few vectorised passes over the pixels.

The height map lives on a :class:`~tactile_deploy.imaging.camera_mapping.OutputGrid` (row 0 at
the largest y, x to the right, pixel centres at ``x_min + (j + 0.5) pitch``,
``y_max - (i + 0.5) pitch``), by default the bounding box of the camera's view at the camera's
own pixel scale. Heights are the sensor-frame z of the sensing surface, mm: 0 for a flat pad at
rest, negative where the gel is pushed in (``height = rest_height - depth``).

:func:`radiance_reference` is a direct per-light implementation of the same equations (float64,
scipy sampling, nothing precomputed): the second method of the tests and the benchmark baseline.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from tactile_deploy.imaging.camera_mapping import (
    OutputGrid,
    pixels_to_sensor_mm,
    sensor_mm_to_pixels,
)
from tactile_deploy.optics.model import OpticsModel


def camera_pixel_grid(width: int, height: int) -> np.ndarray:
    """Raw pixel centres (u, v) of a W x H frame, (H * W, 2) float64, row-major."""
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    return np.stack([u.ravel(), v.ravel()], axis=1)


def grid_for_camera(model: OpticsModel, margin_px: float = 3.0) -> OutputGrid:
    """The height-map grid covering the camera's view of the sensing plane (sensor frame, mm).

    Pitch: ``model.surface_pitch_mm`` or the camera's finest pixel scale on the pad (median over
    the image, lens distortion included); the box is the view's bounding box plus ``margin_px``.
    """
    w, h = model.image_size
    xy = pixels_to_sensor_mm(camera_pixel_grid(w, h), model.camera).reshape(h, w, 2)
    if model.surface_pitch_mm is not None:
        pitch = float(model.surface_pitch_mm)
    else:
        du = np.median(np.linalg.norm(np.diff(xy, axis=1), axis=2))
        dv = np.median(np.linalg.norm(np.diff(xy, axis=0), axis=2))
        pitch = float(min(du, dv))
    lo = xy.reshape(-1, 2).min(axis=0) - margin_px * pitch
    hi = xy.reshape(-1, 2).max(axis=0) + margin_px * pitch
    nx = math.ceil((hi[0] - lo[0]) / pitch)
    ny = math.ceil((hi[1] - lo[1]) / pitch)
    cx, cy = (lo + hi) / 2.0
    return OutputGrid(x_min_mm=cx - nx * pitch / 2, x_max_mm=cx + nx * pitch / 2,
                      y_min_mm=cy - ny * pitch / 2, y_max_mm=cy + ny * pitch / 2, nx=nx, ny=ny)


def grid_centres(grid: OutputGrid) -> tuple[np.ndarray, np.ndarray]:
    """Sensor-frame centres ``(x, y)`` of the grid's cells, each (ny, nx) float64, mm."""
    xs = grid.x_min_mm + (np.arange(grid.nx) + 0.5) * grid.pitch_x_mm
    ys = grid.y_max_mm - (np.arange(grid.ny) + 0.5) * grid.pitch_y_mm
    return np.meshgrid(xs, ys, indexing="xy")


def surface_slopes(height_mm: np.ndarray, grid: OutputGrid) -> tuple[np.ndarray, np.ndarray]:
    """Slopes ``(dz/dx, dz/dy)`` of a height map on ``grid``, each (ny, nx), dimensionless.

    Central differences inside, one-sided at the border (``np.gradient``); rows run along -y.
    """
    d_row, d_col = np.gradient(np.asarray(height_mm, np.float64), grid.pitch_y_mm, grid.pitch_x_mm)
    return d_col, -d_row


#: Half extent of the texture lattice, mm (covers every shipped pad).
TEXTURE_EXTENT_MM = 20.0


def _texture_lattice(seed: int, length_mm: float) -> tuple[np.ndarray, float]:
    """Unit-variance Gaussian random field on the lattice (rows along +y), and its pitch (mm)."""
    step = length_mm / 4.0
    n = math.ceil(2.0 * TEXTURE_EXTENT_MM / step) + 1
    white = np.random.default_rng(seed).standard_normal((n, n)).astype(np.float32)
    sigma = 4.0 / math.sqrt(2.0)  # lattice steps: correlation exp(-d^2 / (2 length^2))
    field = cv2.GaussianBlur(white, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
    return field / float(field.std()), step


def albedo_field(model: OpticsModel, xy_mm: np.ndarray) -> np.ndarray:
    """Membrane albedo ``1 + rms g`` at sensor points (..., 2) mm -> (...) float64 (see GelTexture).

    The field is drawn on a fixed sensor-frame lattice of pitch ``length_mm / 4`` over
    +-``TEXTURE_EXTENT_MM`` (white noise from ``seed``, Gaussian-filtered, rescaled to unit
    variance) and sampled bilinearly, so a seed gives the same texture at the same sensor point
    whatever camera looks at it (points outside the lattice see its border).
    """
    tex = model.texture
    shape = xy_mm.shape[:-1]
    if tex.rms == 0.0:
        return np.ones(shape)
    field, step = _texture_lattice(tex.seed, tex.length_mm)
    pts = xy_mm.reshape(-1, 2)
    n = field.shape[0]
    # Bilinear sampling; points beyond the lattice are clamped to its border.
    u = np.clip((pts[:, 0] + TEXTURE_EXTENT_MM) / step, 0.0, n - 1.000001)
    v = np.clip((pts[:, 1] + TEXTURE_EXTENT_MM) / step, 0.0, n - 1.000001)
    i, j = np.floor(u).astype(np.intp), np.floor(v).astype(np.intp)
    a, b = u - i, v - j
    f = field.astype(np.float64)
    g = ((f[j, i] * (1 - a) + f[j, i + 1] * a) * (1 - b)
         + (f[j + 1, i] * (1 - a) + f[j + 1, i + 1] * a) * b)
    return (1.0 + tex.rms * g).reshape(shape)


def vignetting_gain(model: OpticsModel, uv_px: np.ndarray) -> np.ndarray:
    """``1 + k2 rho^2 + k4 rho^4`` at raw pixels (..., 2) -> (...) float64 (see Vignetting)."""
    w, h = model.image_size
    k = model.camera.intrinsics
    half_diag = 0.5 * math.hypot(w, h)
    rho2 = ((uv_px[..., 0] - k.cx_px) ** 2 + (uv_px[..., 1] - k.cy_px) ** 2) / half_diag**2
    return 1.0 + model.vignetting.k2 * rho2 + model.vignetting.k4 * rho2**2


class OpticsRenderer:
    """Shade height maps of the sensing surface into raw camera frames (see module docstring).

    Parameters
    ----------
    model : OpticsModel
    grid : OutputGrid or None
        Grid of the height maps given to :meth:`radiance` / :meth:`render` (sensor frame, mm);
        default :func:`grid_for_camera`.
    rest_height_mm : (ny, nx) float or None
        The sensing surface at rest on ``grid`` (default flat, z = 0). Its frame is computed once;
        a frame of a pressed surface is shaded only inside the camera region whose surface differs
        from rest by more than ``change_tol_mm`` (the rest of the frame is the same radiance), so
        a local contact costs a fraction of a full frame.
    change_tol_mm, change_tol_slope : float
        A surface point counts as at rest while its height differs from rest by at most
        ``change_tol_mm`` and its slopes by at most ``change_tol_slope``. Slopes drive the
        shading (a slope change of 1e-4 moves a 300-grey light by 0.03 grey levels); height
        matters only through the distance to point lights (0.01 mm at 30 mm: < 0.3 grey levels).
        A nearly incompressible pad bulges by a few micrometres over its whole surface around a
        contact, far below both.

    Noise: shot and read noise per pixel and channel are unit normal deviates scaled by the
    noise model. The deviates come from two banks of pre-drawn normals (drawn once per renderer
    from the renderer's seed), read at two independent random offsets per frame and averaged
    (x 1/sqrt(2)): within a frame they are independent and standard normal; two frames never
    share a (shifted) copy of the same noise. Drawing fresh normals costs 10-25 ms per 640 x 480
    frame on the target CPU, the banks about 1 ms.
    """

    def __init__(self, model: OpticsModel, grid: OutputGrid | None = None,
                 rest_height_mm: np.ndarray | None = None, change_tol_mm: float = 0.01,
                 change_tol_slope: float = 1e-4,
                 noise_seed: int = 0):
        self.model = model
        self.grid = grid or grid_for_camera(model)
        self.change_tol_mm = float(change_tol_mm)
        self.change_tol_slope = float(change_tol_slope)
        w, h = model.image_size
        self.shape = (h, w)
        uv = camera_pixel_grid(w, h)
        xy = pixels_to_sensor_mm(uv, model.camera)
        #: Sensor-frame (x, y) of every raw camera pixel, (H, W, 2) float64, mm.
        self.pixel_xy_mm = xy.reshape(h, w, 2)
        g = self.grid
        map_x = ((xy[:, 0] - g.x_min_mm) / g.pitch_x_mm - 0.5).astype(np.float32).reshape(h, w)
        map_y = ((g.y_max_mm - xy[:, 1]) / g.pitch_y_mm - 0.5).astype(np.float32).reshape(h, w)
        self._map_xy, self._map_frac = cv2.convertMaps(map_x, map_y, cv2.CV_16SC2)
        self._prepare(xy.reshape(h, w, 2), uv.reshape(h, w, 2))
        if rest_height_mm is None:
            rest = np.zeros((g.ny, g.nx), np.float32)
        else:
            rest = np.asarray(rest_height_mm, np.float32)
            self._check_height(rest, "rest_height_mm")
        self.rest_height_mm = rest
        #: Radiance of the surface at rest, (H, W, 3) float32 grey levels (before blur).
        self.rest_radiance = self.radiance(rest)
        self._rest_blurred = self._blur(self.rest_radiance)
        self._pad = 2 + math.ceil(3.0 * model.blur_sigma_px)
        self._rest_sigma = self._noise_sigma(self._rest_blurred)
        bank_len = h * w * 3 + (1 << 16)
        nrng = np.random.default_rng([noise_seed, 0x6E6F697365])
        self._banks = [nrng.standard_normal(bank_len, dtype=np.float32) for _ in range(2)]

    # ------------------------------------------------------------------ precomputation
    def _prepare(self, xy: np.ndarray, uv: np.ndarray) -> None:
        """Per-pixel maps that do not depend on the surface, each (H, W) float32."""
        m = self.model
        x, y = xy[..., 0], xy[..., 1]
        gain = vignetting_gain(m, uv) * albedo_field(m, xy) * m.exposure_gain
        f32 = np.float32
        self._ambient = [(a * gain).astype(f32) for a in m.ambient_grey]
        cam = np.asarray(m.camera_position_mm)
        view = np.stack([cam[0] - x, cam[1] - y, np.full_like(x, cam[2])], axis=-1)
        view /= np.linalg.norm(view, axis=-1, keepdims=True)
        self._lights = []
        for lt in m.lights:
            fall = self._falloff(lt, x, y) * gain
            entry = {"kind": lt.kind}
            if lt.kind == "directional":
                d = lt.direction()
                entry.update(lx=float(d[0]), ly=float(d[1]), c=float(-d[2]))
                ldir = np.broadcast_to(np.asarray(d), view.shape)
                spec_w = fall
            else:
                p = np.asarray(lt.position_mm, float)
                r0sq = float(p @ p)
                lx, ly = p[0] - x, p[1] - y
                entry.update(lx=lx.astype(f32), ly=ly.astype(f32), pz=float(p[2]),
                             rxy2=(lx * lx + ly * ly).astype(f32))
                fall = fall * r0sq  # r0^2 / r^3 (n.l) is applied per frame
                lv = np.stack([lx, ly, np.full_like(x, p[2])], axis=-1)
                r = np.linalg.norm(lv, axis=-1)
                ldir = lv / r[..., None]
                spec_w = self._falloff(lt, x, y) * gain * r0sq / r**2
            entry["w"] = [(fall * c).astype(f32) for c in lt.colour_grey]
            if max(lt.specular_grey) > 0:
                half = ldir + view
                half /= np.linalg.norm(half, axis=-1, keepdims=True)
                entry["spec"] = {"hx": half[..., 0].astype(f32), "hy": half[..., 1].astype(f32),
                                     "hc": (-half[..., 2]).astype(f32), "k": float(lt.shininess),
                                     "w": [(spec_w * c).astype(f32) for c in lt.specular_grey]}
            self._lights.append(entry)

    @staticmethod
    def _falloff(light, x, y) -> np.ndarray:
        if light.falloff_per_mm == 0.0:
            return np.ones_like(x)
        ex, ey = light.inplane_direction()
        return np.exp(light.falloff_per_mm * (ex * x + ey * y))

    def _check_height(self, hgt: np.ndarray, name: str = "height_mm") -> None:
        if hgt.shape != (self.grid.ny, self.grid.nx):
            raise ValueError(f"{name} must have shape ({self.grid.ny}, {self.grid.nx}) (the "
                             f"renderer's surface grid), got {hgt.shape}")

    # ------------------------------------------------------------------------ shading
    def sample_surface(self, height_mm: np.ndarray, roi=None) -> np.ndarray:
        """z, dz/dx, dz/dy at the raw camera pixels of ``roi``: (h, w, 3) float32 (mm, -, -).

        roi : (v0, v1, u0, u1) pixel rows v0:v1 and columns u0:u1, or None for the whole frame.
        Slopes are central differences on the grid (:func:`surface_slopes`), computed only on
        the part of the grid the region reads, and sampled bilinearly.
        """
        hgt = np.asarray(height_mm, dtype=np.float32)
        self._check_height(hgt)
        v0, v1, u0, u1 = roi or (0, self.shape[0], 0, self.shape[1])
        mxy = self._map_xy[v0:v1, u0:u1]
        g = self.grid
        j0 = max(int(mxy[..., 0].min()) - 2, 0)
        j1 = min(int(mxy[..., 0].max()) + 4, g.nx)
        i0 = max(int(mxy[..., 1].min()) - 2, 0)
        i1 = min(int(mxy[..., 1].max()) + 4, g.ny)
        sub = np.ascontiguousarray(hgt[i0:i1, j0:j1])
        # Kernel [-1, 0, 1]: central differences; the first and last cells of the crop (never
        # read unless they are the grid's own border, outside the camera's view) see half the
        # one-sided difference.
        fx = cv2.Sobel(sub, cv2.CV_32F, 1, 0, ksize=1, scale=0.5 / g.pitch_x_mm,
                       borderType=cv2.BORDER_REPLICATE)
        fy = cv2.Sobel(sub, cv2.CV_32F, 0, 1, ksize=1, scale=-0.5 / g.pitch_y_mm,
                       borderType=cv2.BORDER_REPLICATE)
        stack = cv2.merge([sub, fx, fy])
        shift = np.array([j0, i0], np.int16)
        return cv2.remap(stack, mxy - shift, self._map_frac[v0:v1, u0:u1], cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REPLICATE)

    def radiance(self, height_mm: np.ndarray, roi=None) -> np.ndarray:
        """Noise-free radiance (h, w, 3) float32, grey levels, before blur, noise, quantisation.

        roi : (v0, v1, u0, u1) or None (whole frame).
        """
        v0, v1, u0, u1 = roi or (0, self.shape[0], 0, self.shape[1])
        sl = (slice(v0, v1), slice(u0, u1))
        s = self.sample_surface(height_mm, (v0, v1, u0, u1))
        z, fx, fy = cv2.split(s)
        inv_norm = cv2.multiply(fx, fx)
        cv2.accumulateSquare(fy, inv_norm)
        inv_norm += 1.0
        cv2.pow(inv_norm, -0.5, dst=inv_norm)
        out = [a[sl].copy() for a in self._ambient]
        dot = np.empty_like(z)
        tmp = np.empty_like(z)
        for lt in self._lights:
            if lt["kind"] == "directional":
                cv2.addWeighted(fx, lt["lx"], fy, lt["ly"], lt["c"], dst=dot)
                cv2.multiply(dot, inv_norm, dst=dot)
            else:
                # light vector (lx, ly, pz - z); n.l |n| = f_x lx + f_y ly - (pz - z)
                lz = lt["pz"] - z
                cv2.multiply(fx, lt["lx"][sl], dst=dot)
                cv2.accumulateProduct(fy, lt["ly"][sl], dot)
                dot -= lz
                cv2.multiply(lz, lz, dst=tmp)
                tmp += lt["rxy2"][sl]                       # r^2
                cv2.pow(tmp, -1.5, dst=tmp)                 # 1 / r^3
                cv2.multiply(dot, tmp, dst=dot)
                cv2.multiply(dot, inv_norm, dst=dot)
            np.maximum(dot, 0.0, out=dot)
            for c in range(3):
                cv2.accumulateProduct(dot, lt["w"][c][sl], out[c])
            spec = lt.get("spec")
            if spec is not None:
                cv2.multiply(fx, spec["hx"][sl], dst=dot)
                cv2.accumulateProduct(fy, spec["hy"][sl], dot)
                dot += spec["hc"][sl]
                cv2.multiply(dot, inv_norm, dst=dot)
                np.maximum(dot, 0.0, out=dot)
                cv2.pow(dot, spec["k"], dst=dot)
                for c in range(3):
                    cv2.accumulateProduct(dot, spec["w"][c][sl], out[c])
        return cv2.merge(out)

    def changed_roi(self, height_mm: np.ndarray):
        """Camera pixels whose surface may differ from rest: (v0, v1, u0, u1), or None if none.

        The bounding box of the grid cells whose height or slopes differ from rest by more than
        the tolerances, grown by two cells, mapped to raw pixels through the camera mapping
        (box outline sampled every few cells) and grown by two pixels.
        """
        diff = np.asarray(height_mm, np.float32) - self.rest_height_mm
        g = self.grid
        sx = cv2.Sobel(diff, cv2.CV_32F, 1, 0, ksize=1, scale=0.5 / g.pitch_x_mm)
        sy = cv2.Sobel(diff, cv2.CV_32F, 0, 1, ksize=1, scale=0.5 / g.pitch_y_mm)
        changed = ((np.abs(diff) > self.change_tol_mm) | (np.abs(sx) > self.change_tol_slope)
                   | (np.abs(sy) > self.change_tol_slope))
        rows = np.flatnonzero(changed.any(axis=1))
        if len(rows) == 0:
            return None
        cols = np.flatnonzero(changed[rows[0]:rows[-1] + 1].any(axis=0))
        i0, i1 = rows[0] - 2, rows[-1] + 3
        j0, j1 = cols[0] - 2, cols[-1] + 3
        x0, x1 = g.x_min_mm + j0 * g.pitch_x_mm, g.x_min_mm + j1 * g.pitch_x_mm
        y1, y0 = g.y_max_mm - i0 * g.pitch_y_mm, g.y_max_mm - i1 * g.pitch_y_mm
        t = np.linspace(0.0, 1.0, 33)
        outline = np.concatenate([
            np.stack([x0 + (x1 - x0) * t, np.full_like(t, y0)], 1),
            np.stack([x0 + (x1 - x0) * t, np.full_like(t, y1)], 1),
            np.stack([np.full_like(t, x0), y0 + (y1 - y0) * t], 1),
            np.stack([np.full_like(t, x1), y0 + (y1 - y0) * t], 1)])

        uv = sensor_mm_to_pixels(outline, self.model.camera)
        h, w = self.shape
        u0 = int(np.clip(np.floor(uv[:, 0].min()) - 2, 0, w))
        u1 = int(np.clip(np.ceil(uv[:, 0].max()) + 3, 0, w))
        v0 = int(np.clip(np.floor(uv[:, 1].min()) - 2, 0, h))
        v1 = int(np.clip(np.ceil(uv[:, 1].max()) + 3, 0, h))
        if u1 <= u0 or v1 <= v0:
            return None
        return (v0, v1, u0, u1)

    def _blur(self, img: np.ndarray) -> np.ndarray:
        s = self.model.blur_sigma_px
        return cv2.GaussianBlur(img, (0, 0), s) if s > 0 else img

    def _noise_sigma(self, radiance: np.ndarray) -> np.ndarray:
        """Noise standard deviation per pixel and channel for a radiance, grey levels (float32).

        The deviates are the sum of two unit normals (variance 2), hence the factor 1/2.
        """
        nz = self.model.noise
        var = np.maximum(radiance, 0.0)
        var *= np.float32(nz.conversion_gain_grey_per_e / 2.0)
        var += np.float32(nz.read_noise_grey**2 / 2.0)
        return cv2.sqrt(var)

    def _blurred_region(self, height_mm: np.ndarray):
        """``(radiance, region)``: blurred radiance (H, W, 3) float32 and the pixel box
        (v0, v1, u0, u1) where it differs from rest (None: nowhere)."""
        roi = self.changed_roi(height_mm)
        out = self._rest_blurred.copy()
        if roi is None:
            return out, None
        h, w = self.shape
        p = self._pad
        v0, v1, u0, u1 = roi
        if (v1 - v0) * (u1 - u0) > 0.8 * h * w:  # most of the frame: shade it all, no pasting
            return self._blur(self.radiance(height_mm)), (0, h, 0, w)
        e = (max(v0 - p, 0), min(v1 + p, h), max(u0 - p, 0), min(u1 + p, w))
        full = self.rest_radiance
        f0 = (max(e[0] - p, 0), min(e[1] + p, h), max(e[2] - p, 0), min(e[3] + p, w))
        big = full[f0[0]:f0[1], f0[2]:f0[3]].copy()
        big[v0 - f0[0]:v1 - f0[0], u0 - f0[2]:u1 - f0[2]] = self.radiance(height_mm, roi)
        # The blur reads the true neighbours: outside the shaded box the radiance is at rest.
        big = self._blur(big)
        out[e[0]:e[1], e[2]:e[3]] = big[e[0] - f0[0]:e[1] - f0[0], e[2] - f0[2]:e[3] - f0[2]]
        return out, e

    def blurred_radiance(self, height_mm: np.ndarray, with_region: bool = False):
        """Radiance after the optical blur, (H, W, 3) float32 grey levels (a new array).

        Only the region that differs from rest is shaded (see ``changed_roi``); the result equals
        ``blur(radiance(height_mm))`` up to the ``change_tol_mm`` tolerance. with_region : also
        return that region ``(row0, row1, col0, col1)`` (None: all at rest), for :meth:`finish`.
        """
        out, region = self._blurred_region(height_mm)
        return (out, region) if with_region else out

    def _finish(self, img: np.ndarray, region, rng, gain=None) -> np.ndarray:
        m = self.model
        if gain is not None:
            img = img * np.asarray(gain, np.float32)
            region = (0, self.shape[0], 0, self.shape[1])
        nz = m.noise
        if rng is not None and (nz.read_noise_grey > 0 or nz.conversion_gain_grey_per_e > 0):
            sigma = self._rest_sigma.copy()
            if region is not None:
                v0, v1, u0, u1 = region
                sigma[v0:v1, u0:u1] = self._noise_sigma(img[v0:v1, u0:u1])
            n = img.size
            o1, o2 = (int(v) for v in rng.integers(0, len(self._banks[0]) - n + 1, size=2))
            dev = cv2.add(self._banks[0][o1:o1 + n], self._banks[1][o2:o2 + n]).reshape(img.shape)
            cv2.multiply(sigma, dev, dst=sigma)
            img = cv2.add(img, sigma)
        if m.saturation_grey < 255.0:
            img = np.minimum(img, np.float32(m.saturation_grey))
        # cv2.add into an 8-bit output rounds to nearest and saturates (saturate_cast).
        return cv2.add(img, 0.0, dtype=cv2.CV_8U)

    def finish(self, radiance: np.ndarray, rng: np.random.Generator | None,
               gain=None, region="all") -> np.ndarray:
        """Noise (when ``rng`` is given), round, saturate: blurred radiance (H, W, 3) -> uint8.

        gain : as in :meth:`render` (per-frame camera effects), or None. region : where the
        radiance differs from rest (from ``blurred_radiance(..., with_region=True)``; the noise
        level elsewhere is the one at rest), or "all".
        """
        if isinstance(region, str):
            region = (0, self.shape[0], 0, self.shape[1])
        return self._finish(radiance, region, rng, gain)

    def render(self, height_mm: np.ndarray, rng: np.random.Generator | None = None,
               gain=None) -> np.ndarray:
        """RGB frame (H, W, 3) uint8 of the surface ``height_mm`` (noise-free when rng is None).

        gain : None, a (3,) per-channel gain or an (H, W, 3) / (H, W, 1) map multiplying the
        blurred radiance before noise (per-frame camera effects).
        """
        img, region = self._blurred_region(height_mm)
        return self._finish(img, region, rng, gain)

    def flat_height(self) -> np.ndarray:
        """A flat surface at z = 0 on the renderer's grid: zeros (ny, nx) float32, mm."""
        return np.zeros((self.grid.ny, self.grid.nx), np.float32)

    def reference_frame(self, rng: np.random.Generator | None = None, gain=None) -> np.ndarray:
        """The frame of the surface at rest (nothing touching), (H, W, 3) uint8."""
        return self._finish(self._rest_blurred, None, rng, gain)


# ------------------------------------------------------------------------------ reference
def shading_basis(model: OpticsModel, uv_px: np.ndarray, xy_mm: np.ndarray, z_mm: np.ndarray,
                  fx: np.ndarray, fy: np.ndarray, albedo: np.ndarray | None = None):
    """The radiance's terms at given pixels, before their colours are applied (float64).

    Returns ``(gain (k,), diffuse (k, L), specular (k, L))``: the radiance of channel c is
    ``gain * ambient_c + sum_l colour_lc * diffuse_l + sum_l specular_lc * specular_l``, with
    ``gain`` = vignetting x albedo x exposure gain, and the per-light terms including the gain
    and the fall-off (see :func:`shade_points`).
    """
    x, y = xy_mm[:, 0], xy_mm[:, 1]
    normal = np.stack([fx, fy, -np.ones_like(fx)], axis=1)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    surf = np.stack([x, y, z_mm], axis=1)
    rest = np.stack([x, y, np.zeros_like(x)], axis=1)
    cam = np.asarray(model.camera_position_mm, float)
    view = cam - rest
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    if albedo is None:
        albedo = albedo_field(model, xy_mm)
    gain = vignetting_gain(model, uv_px) * albedo * model.exposure_gain
    n_l = len(model.lights)
    diffuse = np.zeros((len(x), n_l))
    specular = np.zeros((len(x), n_l))
    for i, lt in enumerate(model.lights):
        ex, ey = lt.inplane_direction()
        fall = np.exp(lt.falloff_per_mm * (ex * x + ey * y))
        if lt.kind == "directional":
            ldir = np.broadcast_to(np.asarray(lt.direction()), surf.shape)
            scale = fall
            l_rest, scale_rest = ldir, fall
        else:
            p = np.asarray(lt.position_mm, float)
            lvec = p - surf
            r = np.linalg.norm(lvec, axis=1)
            ldir = lvec / r[:, None]
            scale = fall * float(p @ p) / r**2
            lv0 = p - rest
            r_rest = np.linalg.norm(lv0, axis=1)
            l_rest, scale_rest = lv0 / r_rest[:, None], fall * float(p @ p) / r_rest**2
        diffuse[:, i] = np.maximum(np.sum(normal * ldir, axis=1), 0.0) * scale * gain
        if max(lt.specular_grey) > 0:
            half = l_rest + view
            half /= np.linalg.norm(half, axis=1, keepdims=True)
            lobe = np.maximum(np.sum(normal * half, axis=1), 0.0) ** lt.shininess
            specular[:, i] = lobe * scale_rest * gain
    return gain, diffuse, specular


def shade_points(model: OpticsModel, uv_px: np.ndarray, xy_mm: np.ndarray, z_mm: np.ndarray,
                 fx: np.ndarray, fy: np.ndarray, albedo: np.ndarray | None = None) -> np.ndarray:
    """Radiance at given camera pixels from their surface samples, computed directly (float64).

    uv_px : (k, 2) raw px; xy_mm : (k, 2) their sensor-frame points at rest, mm; z_mm, fx, fy :
    (k,) surface height (mm) and slopes dz/dx, dz/dy there. albedo : (k,) or None (computed
    from the model's texture). Returns (k, 3) float64 grey levels (no blur, noise or rounding).
    One light at a time, nothing precomputed: the equations of the module docstring as written.
    Used by the tests as the second method, by the benchmark as the baseline, and by the
    optics fit (:mod:`tactile_deploy.calibration.optics_fit`).
    """
    gain, diffuse, specular = shading_basis(model, uv_px, xy_mm, z_mm, fx, fy, albedo)
    colours = np.array([lt.colour_grey for lt in model.lights], float)
    spec = np.array([lt.specular_grey for lt in model.lights], float)
    return gain[:, None] * np.asarray(model.ambient_grey) + diffuse @ colours + specular @ spec


def sample_grid_bilinear(values: np.ndarray, grid: OutputGrid, xy_mm: np.ndarray) -> np.ndarray:
    """Bilinear samples (k,) of a grid map (ny, nx) at sensor points (k, 2) mm (scipy; edges
    repeat the border)."""
    from scipy.ndimage import map_coordinates

    col = (xy_mm[:, 0] - grid.x_min_mm) / grid.pitch_x_mm - 0.5
    row = (grid.y_max_mm - xy_mm[:, 1]) / grid.pitch_y_mm - 0.5
    return map_coordinates(np.asarray(values, np.float64), np.stack([row, col]), order=1,
                           mode="nearest")


def radiance_reference(model: OpticsModel, grid: OutputGrid, height_mm: np.ndarray) -> np.ndarray:
    """The same radiance as :meth:`OpticsRenderer.radiance`, computed directly.

    Float64, one light at a time, every per-pixel quantity recomputed from the model (camera
    mapping included), slopes by ``np.gradient``, surface sampled with
    ``scipy.ndimage.map_coordinates``. Slow: test oracle and benchmark baseline.
    Returns (H, W, 3) float64 grey levels.
    """
    w, h = model.image_size
    uv = camera_pixel_grid(w, h)
    xy = pixels_to_sensor_mm(uv, model.camera)
    hgt = np.asarray(height_mm, np.float64)
    fx_g, fy_g = surface_slopes(hgt, grid)
    z = sample_grid_bilinear(hgt, grid, xy)
    fx = sample_grid_bilinear(fx_g, grid, xy)
    fy = sample_grid_bilinear(fy_g, grid, xy)
    return shade_points(model, uv, xy, z, fx, fy).reshape(h, w, 3)
