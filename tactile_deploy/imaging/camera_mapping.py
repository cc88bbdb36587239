"""Camera mapping: raw camera pixels <-> sensor-frame mm, and rectification onto the depth grid.

Frames and conventions
----------------------
* **Camera pixels** ``(u, v)``: u to the right, v down, in px, OpenCV's convention that the
  integer coordinate is the *centre* of a pixel (pixel (row v, column u) is centred at (u, v); the
  image spans u in [-0.5, W - 0.5]). *Raw* pixels are those of the frame as the camera delivers
  it (with lens distortion); *undistorted* pixels are those of the ideal pinhole camera with the
  same camera matrix.
* **Sensor frame** ``(x, y)``: mm, origin at the centre of the sensing (top) surface of the gel
  pad, z up and out of the gel. The camera mapping concerns the plane z = 0.
* **Lens model** (OpenCV, coefficients ``k1 k2 p1 p2 k3``): for undistorted normalised
  coordinates ``x = (u - cx) / fx``, ``y = (v - cy) / fy`` and ``r^2 = x^2 + y^2``, the raw
  normalised coordinates are, with ``R = 1 + k1 r^2 + k2 r^4 + k3 r^6``,
  ``x_d = x R + 2 p1 x y + p2 (r^2 + 2 x^2)`` and ``y_d = y R + p1 (r^2 + 2 y^2) + 2 p2 x y``.
* **Homography** ``H`` (``homography_px_to_mm``): ``[X, Y, W]^T = H [u, v, 1]^T`` maps undistorted
  pixels to the sensor plane, ``x = X / W``, ``y = Y / W`` mm. It carries the whole placement of
  the plane: scale (anisotropic if the view is oblique), rotation, translation, perspective and
  the mirror, if any. It is stored scaled so that ``W = +1`` at the undistorted image centre.
* **Mirror**: the camera looks at the underside of the gel. A camera looking straight up at the
  gel sees the pad mirrored with respect to the pad seen from outside (from +z): with u along +x,
  v runs along +y, whereas an image of the pad seen from outside has rows running along -y. A
  single folding mirror in the optical path (as in GelSlim designs) undoes this. No flag is
  needed: the sign of the homography's determinant carries it, and :attr:`CameraMapping.
  image_mirrored` reports it (True when ``det d(x, y)/d(u, v) > 0`` at the image centre).
* **Output grid** (:class:`OutputGrid`, fixed convention, other modules rely on it): pixel
  (row i, column j) of the ``ny x nx`` grid is centred at ``x = x_min + (j + 0.5) * pitch_x``,
  ``y = y_max - (i + 0.5) * pitch_y``: row 0 at the largest y, x to the right, y up, i.e. an image
  of the sensor seen from outside the gel. Default +-17.5 mm at 128 x 128 (pitch 0.2734375 mm).
* **mm per pixel** (``mm_per_px_x``, ``mm_per_px_y``): at the raw image centre, moving 1 mm along
  sensor +x moves the image point by ``1 / mm_per_px_x`` px (lens distortion included); likewise
  for y. For a camera whose u axis is along x these are the usual pixel sizes on the pad.

Speed: :func:`build_remap` is computed once per mapping; :func:`rectify` is then a single
``cv2.remap`` (bilinear, border replicated). It point-samples the raw frame; it does not average
the raw pixels that fall into one output cell (about 4 x 4 raw px at 640 x 480).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
from pydantic import Field, ValidationError, model_validator

from tactile_deploy.atomic import write_text
from tactile_deploy.fileformat import StrictModel
from tactile_deploy.jsonfile import read_json, validation_error_text

#: Version of the camera mapping file format written by :func:`save_mapping`.
FORMAT_VERSION = 1

# Relative tolerance when checking stored derived values (mm per px) against recomputation.
_DERIVED_RTOL = 1e-6



class CameraMappingError(ValueError):
    """A camera mapping file or argument is invalid (the message says which and why)."""


class OutputGrid(StrictModel):
    """The regular sensor-frame grid that frames are resampled onto (mm, sensor frame).

    Pixel (row i, column j) is centred at ``x = x_min_mm + (j + 0.5) * pitch_x_mm``,
    ``y = y_max_mm - (i + 0.5) * pitch_y_mm``: row 0 at the largest y.
    """

    x_min_mm: float = Field(-17.5, description="Left edge of the grid (not a pixel centre), mm.")
    x_max_mm: float = Field(17.5, description="Right edge of the grid, mm.")
    y_min_mm: float = Field(-17.5, description="Bottom edge of the grid (last row's edge), mm.")
    y_max_mm: float = Field(17.5, description="Top edge of the grid (row 0's outer edge), mm.")
    nx: int = Field(128, ge=2, description="Number of columns (along +x).")
    ny: int = Field(128, ge=2, description="Number of rows (along -y).")

    @model_validator(mode="after")
    def _check(self) -> OutputGrid:
        if not self.x_max_mm > self.x_min_mm:
            raise ValueError(f"x_max_mm={self.x_max_mm} must exceed x_min_mm={self.x_min_mm}")
        if not self.y_max_mm > self.y_min_mm:
            raise ValueError(f"y_max_mm={self.y_max_mm} must exceed y_min_mm={self.y_min_mm}")
        return self

    @property
    def pitch_x_mm(self) -> float:
        """Column pitch, mm."""
        return (self.x_max_mm - self.x_min_mm) / self.nx

    @property
    def pitch_y_mm(self) -> float:
        """Row pitch, mm."""
        return (self.y_max_mm - self.y_min_mm) / self.ny


class Intrinsics(StrictModel):
    """Pinhole camera matrix ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``, px."""

    fx_px: float = Field(gt=0, description="Focal length along u, px.")
    fy_px: float = Field(gt=0, description="Focal length along v, px.")
    cx_px: float = Field(description="Principal point u, px (pixel-centre convention).")
    cy_px: float = Field(description="Principal point v, px (pixel-centre convention).")


class Distortion(StrictModel):
    """OpenCV lens distortion coefficients (dimensionless, on normalised coordinates)."""

    k1: float = Field(0.0, description="Radial, r^2 term.")
    k2: float = Field(0.0, description="Radial, r^4 term.")
    p1: float = Field(0.0, description="Tangential (decentring), first coefficient.")
    p2: float = Field(0.0, description="Tangential (decentring), second coefficient.")
    k3: float = Field(0.0, description="Radial, r^6 term.")


class FitSummary(StrictModel):
    """How a mapping was estimated, and how well it fits its calibration points."""

    method: Literal["charuco-multi-view", "charuco-single-view", "dots-single-view"] = Field(
        description="Estimator: ChArUco with several views, ChArUco or pressed dots with one view."
    )
    n_frames: int = Field(ge=1, description="Number of target frames used.")
    n_points: int = Field(ge=1, description="Number of target points in the final fit.")
    n_rejected: int = Field(0, ge=0, description="Points dropped as outliers before the final fit.")
    rms_px: float = Field(ge=0, description="RMS reprojection error in the raw image, px.")
    max_px: float = Field(ge=0, description="Largest reprojection error, px.")
    rms_mm: float = Field(ge=0, description="RMS error of the mapped points on the sensor plane, "
                          "mm.")
    fitted_lens: tuple[str, ...] = Field(
        description="Lens parameters estimated from the frames (of fx fy cx cy k1 k2 p1 p2 k3); "
        "the others were held at their stored values."
    )
    focal_assumed: bool = Field(
        description="True when fx = fy was assumed, not measured (single view): the distortion "
        "field in pixels is then meaningful, the coefficients on their own are not."
    )
    grid_coverage: float = Field(
        ge=0, le=1, description="Fraction of output-grid cell centres that fall inside the image."
    )


Row3 = tuple[float, float, float]


class CameraMapping(StrictModel):
    """Everything needed to map a raw camera frame onto the sensor-frame output grid.

    Build one with :func:`camera_mapping_from_parameters` (which computes the derived fields),
    read one with :func:`load_mapping`.
    """

    format_version: Literal[1] = Field(FORMAT_VERSION, description="Version of this file format.")
    image_width_px: int = Field(gt=0, description="Width W of the raw frames, px.")
    image_height_px: int = Field(gt=0, description="Height H of the raw frames, px.")
    intrinsics: Intrinsics = Field(description="Camera matrix, px.")
    distortion: Distortion = Field(description="Lens distortion, OpenCV model.")
    homography_px_to_mm: tuple[Row3, Row3, Row3] = Field(
        description="3x3, row-major: undistorted pixels (u, v, 1) -> sensor plane (x, y) mm, "
        "scaled so that W = +1 at the undistorted image centre."
    )
    mm_per_px_x: float = Field(
        gt=0, description="Derived: mm along sensor x per px of image motion, at the image centre."
    )
    mm_per_px_y: float = Field(
        gt=0, description="Derived: mm along sensor y per px of image motion, at the image centre."
    )
    image_mirrored: bool = Field(
        description="Derived: True when the raw image is a mirror image of the pad seen from "
        "outside the gel (det d(x, y)/d(u, v) > 0)."
    )
    grid: OutputGrid = Field(default_factory=OutputGrid, description="Output grid, sensor frame.")
    fit: FitSummary | None = Field(None, description="Calibration summary, if estimated.")

    # ----------------------------------------------------------------------------- arrays
    @property
    def image_size(self) -> tuple[int, int]:
        """``(width, height)`` of the raw frames, px (OpenCV order)."""
        return (self.image_width_px, self.image_height_px)

    @property
    def camera_matrix(self) -> np.ndarray:
        """(3, 3) float64, px."""
        k = self.intrinsics
        return np.array([[k.fx_px, 0.0, k.cx_px], [0.0, k.fy_px, k.cy_px], [0.0, 0.0, 1.0]])

    @property
    def dist_coeffs(self) -> np.ndarray:
        """(5,) float64, OpenCV order k1 k2 p1 p2 k3."""
        d = self.distortion
        return np.array([d.k1, d.k2, d.p1, d.p2, d.k3])

    @property
    def homography(self) -> np.ndarray:
        """(3, 3) float64: undistorted px -> sensor mm."""
        return np.array(self.homography_px_to_mm, dtype=np.float64)

    @model_validator(mode="after")
    def _check_geometry(self) -> CameraMapping:
        _check_radial_invertible(self)
        h = self.homography
        if not np.isfinite(np.linalg.cond(h)) or np.linalg.cond(h) > 1e12:
            raise ValueError(f"homography_px_to_mm is singular: {h.tolist()}")
        corners_raw = _image_corners(self.image_width_px, self.image_height_px)
        w_img = _apply_h_w(h, undistort_pixels(corners_raw, self))
        if not (np.all(w_img > 0) or np.all(w_img < 0)):
            raise ValueError(
                "homography_px_to_mm sends part of the image to infinity (its horizon crosses "
                f"the image: W at the image corners = {np.round(w_img, 6).tolist()})"
            )
        g = self.grid
        grid_corners = np.array(
            [[g.x_min_mm, g.y_min_mm], [g.x_max_mm, g.y_min_mm],
             [g.x_max_mm, g.y_max_mm], [g.x_min_mm, g.y_max_mm]]
        )
        w_grid = _apply_h_w(np.linalg.inv(h), grid_corners)
        if not (np.all(w_grid > 0) or np.all(w_grid < 0)):
            raise ValueError(
                "the output grid crosses the camera's horizon (the inverse homography sends "
                f"part of it to infinity: W at the grid corners = {np.round(w_grid, 6).tolist()})"
            )
        sx, sy, mirrored = _derived_scale(self)
        for name, stored, actual in (("mm_per_px_x", self.mm_per_px_x, sx),
                                     ("mm_per_px_y", self.mm_per_px_y, sy)):
            if abs(stored - actual) > _DERIVED_RTOL * actual:
                raise ValueError(
                    f"{name}={stored!r} does not match the value {actual!r} derived from the "
                    "intrinsics, distortion and homography; after editing those, rebuild the "
                    "file with camera_mapping_from_parameters() (or recalibrate)"
                )
        if self.image_mirrored != mirrored:
            raise ValueError(
                f"image_mirrored={self.image_mirrored} contradicts the homography, whose "
                f"determinant says {mirrored}"
            )
        return self


# ------------------------------------------------------------------------------ lens model
def distort_normalized(x: np.ndarray, y: np.ndarray, d: np.ndarray):
    """Forward OpenCV distortion and its Jacobian on normalised coordinates.

    x, y : (N,) float64, undistorted normalised coordinates ((u - cx) / fx, (v - cy) / fy).
    d : (5,) float64, k1 k2 p1 p2 k3.
    Returns ``xd, yd, (j11, j12, j21, j22)``: distorted normalised coordinates, each (N,), and
    the Jacobian ``j = d(xd, yd) / d(x, y)`` entry by entry.
    """
    k1, k2, p1, p2, k3 = d
    r2 = x * x + y * y
    rad = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    drad = 2.0 * k1 + r2 * (4.0 * k2 + 6.0 * k3 * r2)  # d(rad)/d(r^2) * 2
    xy = x * y
    xd = x * rad + 2.0 * p1 * xy + p2 * (r2 + 2.0 * x * x)
    yd = y * rad + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * xy
    j11 = rad + drad * x * x + 2.0 * p1 * y + 6.0 * p2 * x
    j12 = drad * xy + 2.0 * p1 * x + 2.0 * p2 * y
    j21 = drad * xy + 2.0 * p1 * x + 2.0 * p2 * y
    j22 = rad + drad * y * y + 6.0 * p1 * y + 2.0 * p2 * x
    return xd, yd, (j11, j12, j21, j22)


def _as_points(points, name: str) -> np.ndarray:
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise ValueError(f"{name} must have shape (N, 2), got {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise ValueError(f"{name} contains NaN or inf")
    return pts


def distort_pixels(uv_undistorted_px, mapping: CameraMapping) -> np.ndarray:
    """Undistorted pixels -> raw pixels (closed form).

    uv_undistorted_px : (N, 2) float, px (u, v) of the ideal pinhole image.
    Returns (N, 2) float64, raw px.
    """
    uv = _as_points(uv_undistorted_px, "uv_undistorted_px")
    k = mapping.intrinsics
    x = (uv[:, 0] - k.cx_px) / k.fx_px
    y = (uv[:, 1] - k.cy_px) / k.fy_px
    xd, yd, _ = distort_normalized(x, y, mapping.dist_coeffs)
    return np.stack([xd * k.fx_px + k.cx_px, yd * k.fy_px + k.cy_px], axis=1)


def undistort_pixels(uv_raw_px, mapping: CameraMapping, tol_px: float = 1e-9) -> np.ndarray:
    """Raw pixels -> undistorted pixels (Newton iterations on the lens model).

    uv_raw_px : (N, 2) float, raw px (u, v).
    Returns (N, 2) float64, undistorted px; converged to ``tol_px`` or an error is raised.
    """
    uv = _as_points(uv_raw_px, "uv_raw_px")
    k = mapping.intrinsics
    d = mapping.dist_coeffs
    xt = (uv[:, 0] - k.cx_px) / k.fx_px
    yt = (uv[:, 1] - k.cy_px) / k.fy_px
    x, y = xt.copy(), yt.copy()
    tol = tol_px / max(k.fx_px, k.fy_px)
    for _ in range(50):
        xd, yd, (a, b, c, e) = distort_normalized(x, y, d)
        rx, ry = xd - xt, yd - yt
        if np.all(np.abs(rx) + np.abs(ry) < tol):
            break
        det = a * e - b * c
        det = np.where(np.abs(det) < 1e-12, 1e-12, det)
        x = x - (e * rx - b * ry) / det
        y = y - (a * ry - c * rx) / det
    xd, yd, _ = distort_normalized(x, y, d)
    bad = np.abs(xd - xt) + np.abs(yd - yt) >= 10 * tol
    if np.any(bad):
        raise CameraMappingError(
            f"{int(bad.sum())} of {len(uv)} points could not be undistorted (first: "
            f"{uv[bad][0].tolist()} px); they lie outside the region where the lens model is "
            "invertible"
        )
    return np.stack([x * k.fx_px + k.cx_px, y * k.fy_px + k.cy_px], axis=1)


def _apply_h(h: np.ndarray, pts: np.ndarray) -> np.ndarray:
    q = pts @ h[:, :2].T + h[:, 2]
    return q[:, :2] / q[:, 2:3]


def _apply_h_w(h: np.ndarray, pts: np.ndarray) -> np.ndarray:
    return pts @ h[2, :2] + h[2, 2]


def _image_corners(width: int, height: int) -> np.ndarray:
    return np.array(
        [[-0.5, -0.5], [width - 0.5, -0.5], [width - 0.5, height - 0.5], [-0.5, height - 0.5]]
    )


def _check_radial_invertible(mapping: CameraMapping) -> None:
    """Raise if the radial lens polynomial turns back before reaching the image corners."""
    k = mapping.intrinsics
    d = mapping.distortion
    corners = _image_corners(mapping.image_width_px, mapping.image_height_px)
    r_corner = float(np.max(np.hypot((corners[:, 0] - k.cx_px) / k.fx_px,
                                     (corners[:, 1] - k.cy_px) / k.fy_px)))
    r = np.linspace(0.0, 4.0 * r_corner + 1.0, 4001)
    r2 = r * r
    rd = r * (1.0 + r2 * (d.k1 + r2 * (d.k2 + r2 * d.k3)))
    slope = 1.0 + r2 * (3.0 * d.k1 + r2 * (5.0 * d.k2 + 7.0 * d.k3 * r2))
    turn = np.nonzero(slope <= 0.05)[0]
    if len(turn) and rd[turn[0]] <= 1.02 * r_corner:
        raise ValueError(
            f"distortion k1={d.k1}, k2={d.k2}, k3={d.k3} is not invertible over the image: the "
            f"radial polynomial turns back at distorted radius {rd[turn[0]] * k.fx_px:.1f} px, "
            f"inside the image (corner at {r_corner * k.fx_px:.1f} px)"
        )


# ------------------------------------------------------------------------ derived values
def _raw_to_mm_jacobian(mapping: CameraMapping, uv_raw: np.ndarray) -> np.ndarray:
    """d(x, y mm) / d(u, v raw px) at one raw pixel: (2, 2) float64."""
    k = mapping.intrinsics
    uvu = undistort_pixels(uv_raw[None, :], mapping)[0]
    x = np.array([(uvu[0] - k.cx_px) / k.fx_px])
    y = np.array([(uvu[1] - k.cy_px) / k.fy_px])
    _, _, (a, b, c, e) = distort_normalized(x, y, mapping.dist_coeffs)
    # d(raw px)/d(undistorted px) = diag(f) J diag(1/f)
    jd = np.array([[a[0], b[0] * k.fx_px / k.fy_px], [c[0] * k.fy_px / k.fx_px, e[0]]])
    h = mapping.homography
    q = h @ np.array([uvu[0], uvu[1], 1.0])
    xy = q[:2] / q[2]
    jh = (h[:2, :2] - np.outer(xy, h[2, :2])) / q[2]
    return jh @ np.linalg.inv(jd)


def _derived_scale(mapping: CameraMapping) -> tuple[float, float, bool]:
    centre = np.array([(mapping.image_width_px - 1) / 2.0, (mapping.image_height_px - 1) / 2.0])
    j = _raw_to_mm_jacobian(mapping, centre)
    m = np.linalg.inv(j)  # d(raw px) / d(mm)
    return (1.0 / float(np.hypot(*m[:, 0])), 1.0 / float(np.hypot(*m[:, 1])),
            bool(np.linalg.det(j) > 0))


def camera_mapping_from_parameters(
    image_size: tuple[int, int],
    camera_matrix,
    dist_coeffs,
    homography_px_to_mm,
    grid: OutputGrid | None = None,
    fit: FitSummary | None = None,
) -> CameraMapping:
    """Assemble and validate a :class:`CameraMapping`, computing its derived fields.

    image_size : (width, height) px of the raw frames.
    camera_matrix : (3, 3) px. dist_coeffs : (4,), (5,) k1 k2 p1 p2 [k3]; longer vectors must
    have zeros beyond k3. homography_px_to_mm : (3, 3), undistorted px -> sensor mm (any scale;
    it is rescaled so that W = +1 at the undistorted image centre).
    """
    k = np.asarray(camera_matrix, dtype=np.float64)
    if k.shape != (3, 3):
        raise ValueError(f"camera_matrix must be (3, 3), got {k.shape}")
    d = np.asarray(dist_coeffs, dtype=np.float64).ravel()
    if d.size < 4 or (d.size > 5 and np.any(d[5:] != 0)):
        raise ValueError(
            f"dist_coeffs must be k1 k2 p1 p2 [k3] (rational and prism terms unsupported), got {d}"
        )
    d = np.concatenate([d[:5], np.zeros(max(0, 5 - d.size))])
    h = np.asarray(homography_px_to_mm, dtype=np.float64)
    if h.shape != (3, 3):
        raise ValueError(f"homography_px_to_mm must be (3, 3), got {h.shape}")
    width, height = (int(image_size[0]), int(image_size[1]))
    intr = Intrinsics(fx_px=k[0, 0], fy_px=k[1, 1], cx_px=k[0, 2], cy_px=k[1, 2])
    dist = Distortion(k1=d[0], k2=d[1], p1=d[2], p2=d[3], k3=d[4])
    # Build an unvalidated draft to evaluate the derived quantities, then validate for real.
    draft = CameraMapping.model_construct(
        image_width_px=width, image_height_px=height, intrinsics=intr, distortion=dist,
        homography_px_to_mm=tuple(tuple(float(v) for v in row) for row in h),
        grid=grid or OutputGrid(), fit=fit,
    )
    _check_radial_invertible(draft)
    centre = np.array([[(width - 1) / 2.0, (height - 1) / 2.0]])
    w0 = _apply_h_w(h, undistort_pixels(centre, draft))[0]
    if abs(w0) < 1e-300:
        raise ValueError("homography_px_to_mm sends the image centre to infinity")
    h = h / w0
    draft = draft.model_copy(
        update={"homography_px_to_mm": tuple(tuple(float(v) for v in row) for row in h)}
    )
    sx, sy, mirrored = _derived_scale(draft)
    return CameraMapping(
        image_width_px=width, image_height_px=height, intrinsics=intr, distortion=dist,
        homography_px_to_mm=draft.homography_px_to_mm, mm_per_px_x=sx, mm_per_px_y=sy,
        image_mirrored=mirrored, grid=grid or OutputGrid(), fit=fit,
    )


# ----------------------------------------------------------------------- point mappings
def pixels_to_sensor_mm(uv_raw_px, mapping: CameraMapping) -> np.ndarray:
    """Raw camera pixels -> sensor-plane points.

    uv_raw_px : (N, 2) float, raw px (u right, v down, pixel-centre convention).
    Returns (N, 2) float64, (x, y) mm in the sensor frame (plane z = 0).
    """
    return _apply_h(mapping.homography, undistort_pixels(uv_raw_px, mapping))


def sensor_mm_to_pixels(xy_mm, mapping: CameraMapping) -> np.ndarray:
    """Sensor-plane points -> raw camera pixels.

    xy_mm : (N, 2) float, (x, y) mm in the sensor frame (plane z = 0).
    Returns (N, 2) float64, raw px (u, v).
    """
    xy = _as_points(xy_mm, "xy_mm")
    return distort_pixels(_apply_h(np.linalg.inv(mapping.homography), xy), mapping)


def grid_centres_mm(grid: OutputGrid) -> tuple[np.ndarray, np.ndarray]:
    """Centres of the output grid cells: ``(x, y)``, each (ny, nx) float64, mm, sensor frame.

    ``x[i, j] = x_min + (j + 0.5) * pitch_x``, ``y[i, j] = y_max - (i + 0.5) * pitch_y``.
    """
    xs = grid.x_min_mm + (np.arange(grid.nx) + 0.5) * grid.pitch_x_mm
    ys = grid.y_max_mm - (np.arange(grid.ny) + 0.5) * grid.pitch_y_mm
    x, y = np.meshgrid(xs, ys, indexing="xy")
    return x, y


def build_remap(mapping: CameraMapping) -> tuple[np.ndarray, np.ndarray]:
    """Resampling tables of the output grid: for each cell, the raw pixel it reads.

    Returns ``(map_x, map_y)``, each (ny, nx) float32, raw px (u and v): output cell (i, j) takes
    the raw frame's value at ``(map_x[i, j], map_y[i, j])``. Compute once per mapping and pass to
    :func:`rectify`.
    """
    x, y = grid_centres_mm(mapping.grid)
    uv = sensor_mm_to_pixels(np.stack([x.ravel(), y.ravel()], axis=1), mapping)
    shape = x.shape
    return (uv[:, 0].reshape(shape).astype(np.float32),
            uv[:, 1].reshape(shape).astype(np.float32))


def compact_remap(remap: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The tables of :func:`build_remap` in OpenCV's fixed-point form, for a faster :func:`rectify`.

    Returns ``(map_xy, map_frac)``: (ny, nx, 2) int16 whole pixels and (ny, nx) uint16
    interpolation-table indices (positions quantised to 1/32 px).
    """
    map_x, map_y = remap
    return cv2.convertMaps(map_x, map_y, cv2.CV_16SC2)


def grid_coverage(mapping: CameraMapping) -> float:
    """Fraction of output-grid cell centres whose raw pixel lies inside the image."""
    map_x, map_y = build_remap(mapping)
    inside = ((map_x >= -0.5) & (map_x <= mapping.image_width_px - 0.5)
              & (map_y >= -0.5) & (map_y <= mapping.image_height_px - 0.5))
    return float(inside.mean())


_REMAP_DTYPES = frozenset(np.dtype(t) for t in (np.uint8, np.uint16, np.int16, np.float32,
                                                 np.float64))


def rectify(frame: np.ndarray, mapping: CameraMapping, remap=None) -> np.ndarray:
    """Resample a raw camera frame onto the sensor-frame output grid (one ``cv2.remap``).

    frame : (H, W) or (H, W, C), uint8 / uint16 / int16 / float32 / float64, raw camera pixels;
        H, W must equal the mapping's image size.
    remap : ``(map_x, map_y)`` from :func:`build_remap`, or their :func:`compact_remap` form
        (about twice as fast, positions to 1/32 px); built on the fly when None (slow path).
    Returns (ny, nx) or (ny, nx, C), the frame's dtype: row i, column j is the sensor point
    ``x = x_min + (j + 0.5) * pitch_x``, ``y = y_max - (i + 0.5) * pitch_y`` (bilinear; cells
    outside the image repeat the nearest edge pixel).
    """
    shape = getattr(frame, "shape", None)
    if shape is None or len(shape) not in (2, 3):
        raise ValueError(f"frame must be an (H, W) or (H, W, C) array, got {type(frame).__name__} "
                         f"of shape {shape}")
    if shape[0] != mapping.image_height_px or shape[1] != mapping.image_width_px:
        raise CameraMappingError(
            f"frame is {shape[1]}x{shape[0]} px (W x H) but the camera mapping was calibrated "
            f"for {mapping.image_width_px}x{mapping.image_height_px} px; check the camera's "
            "resolution setting or recalibrate for this resolution"
        )
    if remap is None:
        remap = build_remap(mapping)
    map_x, map_y = remap
    if map_x.shape[:2] != (mapping.grid.ny, mapping.grid.nx) or map_y.shape[:2] != map_x.shape[:2]:
        raise ValueError(
            f"remap tables have shape {map_x.shape}/{map_y.shape}, expected "
            f"{(mapping.grid.ny, mapping.grid.nx)}: rebuild them with build_remap(mapping)"
        )
    if frame.dtype not in _REMAP_DTYPES:
        raise ValueError(f"frame dtype {frame.dtype} is not supported; use one of "
                         f"{', '.join(sorted(str(d) for d in _REMAP_DTYPES))}")
    out = cv2.remap(frame, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out[..., None] if out.ndim < len(shape) else out


# --------------------------------------------------------------------------------- files
def save_mapping(mapping: CameraMapping, path: str | os.PathLike) -> None:
    """Write ``mapping`` as JSON (atomic: temporary file + rename)."""
    write_text(path, mapping.model_dump_json(indent=2) + "\n")


def load_mapping(path: str | os.PathLike) -> CameraMapping:
    """Read and validate a camera mapping JSON written by :func:`save_mapping`.

    Raises FileNotFoundError if missing, :class:`CameraMappingError` naming the file and the
    offending fields (expected and actual values) if the content is invalid.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(
            f"camera mapping {path} not found; create one with `tactile-deploy calibrate camera`"
        )
    doc = read_json(path, CameraMappingError, "a JSON camera mapping")
    if not isinstance(doc, dict):
        raise CameraMappingError(f"{path}: expected a JSON object, got {type(doc).__name__}")
    if "format_version" not in doc:
        raise CameraMappingError(
            f"{path}: field 'format_version' is missing (expected {FORMAT_VERSION}); is this a "
            "camera mapping file?"
        )
    if doc["format_version"] != FORMAT_VERSION:
        raise CameraMappingError(
            f"{path}: field 'format_version': this version of tactile-deploy reads version "
            f"{FORMAT_VERSION}, the file has {doc.get('format_version')!r}"
        )
    try:
        return CameraMapping.model_validate(doc)
    except ValidationError as e:
        raise CameraMappingError(validation_error_text(path, e, "camera mapping")) from None



def crop_camera_mapping(image_width_px: int, image_height_px: int, mm_per_px: float,
                        crop: tuple[int, int, int, int] | None = None,
                        mirrored: bool = False) -> CameraMapping:
    """Camera mapping of a sensor whose frames need no lens or perspective correction: a crop.

    The image (or the crop ``(x0, y0, width, height)`` px of it) is centred on the sensor
    origin, columns along +x and rows along -y (``mirrored``: rows along +y), at ``mm_per_px``;
    the imaging grid is exactly the crop's pixels, so rectification copies them.
    """
    x0, y0, w, h = crop if crop is not None else (0, 0, image_width_px, image_height_px)
    if not (0 <= x0 and 0 <= y0 and x0 + w <= image_width_px and y0 + h <= image_height_px
            and w >= 2 and h >= 2):
        raise ValueError(f"crop {crop} does not fit a {image_width_px}x{image_height_px} image")
    s = float(mm_per_px)
    cu = x0 + (w - 1) / 2.0
    cv = y0 + (h - 1) / 2.0
    sy = s if mirrored else -s
    hmat = [[s, 0.0, -s * cu], [0.0, sy, -sy * cv], [0.0, 0.0, 1.0]]
    k = [[float(image_width_px), 0.0, (image_width_px - 1) / 2.0],
         [0.0, float(image_width_px), (image_height_px - 1) / 2.0], [0.0, 0.0, 1.0]]
    grid = OutputGrid(x_min_mm=-w * s / 2, x_max_mm=w * s / 2, y_min_mm=-h * s / 2,
                      y_max_mm=h * s / 2, nx=w, ny=h)
    return camera_mapping_from_parameters((image_width_px, image_height_px), k, np.zeros(5),
                                          hmat, grid=grid)
