"""Marble shading model: camera frame + no-contact reference -> surface gradients -> depth map.

The model is a binned lookup table from colour to surface gradient, as in the paper (a mapping
from RGB colour to surface normals calibrated with a marble of known size, then integrated into
a depth map), made position-dependent because a sensor's illumination is not uniform:

1. **Illumination drift.** ``offset = frame_offset(frame, reference)``: the per-channel grey
   level by which the whole frame differs from the reference, estimated robustly from the pixels
   that look like the reference (the non-contact area). Real recordings drift by tens of grey
   levels; the offset is subtracted before the lookup.
2. **Colour bin.** ``diff = (frame - reference - offset) * gain`` per channel (``gain`` =
   :func:`reference_gain` when the header's ``reference_gain`` is set, else 1), binned into
   ``bins`` steps over ``[colour_min, colour_max]``; a channel that is saturated in the frame
   (raw value >= ``saturation_level``) goes to an extra bin of its own (its difference only says
   "at least").
3. **Position.** Each colour bin points to a slot of a table stored at a grid of nodes every
   ``node_spacing_px`` pixels; the gradient at a pixel is the bilinear blend of the four nodes
   around it.
4. **Depth.** The gradients are integrated by :mod:`tactile_deploy.imaging.poisson` (zero depth
   half a pixel outside the image: the far field is flat), with per-axis weights fitted at
   calibration (one illumination axis is usually better resolved than the other).

Frames and axes: frames are (H, W, 3) uint8 **RGB** camera images (not OpenCV's BGR). Image
columns run along the sensor's +x axis and image rows along -y (row 0 is the largest y), so the
image is the sensing surface seen from outside the gel, z towards the viewer. The pixel at
(row i, column j) is at ``x = (j - (W - 1) / 2) * mm_per_px``, ``y = ((H - 1) / 2 - i) *
mm_per_px`` in the sensor frame (mm), see :func:`pixel_centres_mm`.

Depth: how far the sensing surface is pushed into the gel, mm, positive into the gel, at each
pixel of the frame's own resolution. Gradients: ``(dd_dx, dd_dy)``, derivatives of depth along
sensor x and y, dimensionless (mm per mm).

Files: a model is one ``.npz`` holding the arrays and a JSON header (``header_json``) validated
by :class:`ShadingHeader`; :func:`save_shading` writes atomically, :func:`load_shading` names the
file and field of any problem.
"""

from __future__ import annotations

import json
import math
import os
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field, ValidationError, model_validator

from tactile_deploy.atomic import write_npz
from tactile_deploy.fileformat import StrictModel
from tactile_deploy.imaging.poisson import poisson_solver
from tactile_deploy.jsonfile import validation_error_text

FORMAT_VERSION = 1



class ShadingModelError(ValueError):
    """A shading model file, or a frame given to a model, is not what it must be."""


class ShadingHeader(StrictModel):
    """JSON header of a shading model file (``.npz`` key ``header_json``)."""

    format_version: Literal[1] = Field(FORMAT_VERSION, description="Version of this file format.")
    method: Literal["binned-lut-position"] = Field(
        "binned-lut-position",
        description="Colour-to-gradient model: binned colour-difference LUT blended bilinearly "
        "between nodes of a position grid.",
    )
    colour_order: Literal["RGB"] = Field("RGB", description="Channel order of frames.")
    image_height_px: int = Field(ge=2, description="Frame height the model was fitted for, px.")
    image_width_px: int = Field(ge=2, description="Frame width the model was fitted for, px.")
    mm_per_px: float = Field(gt=0, description="Sensor-plane scale, mm per pixel.")
    ball_radius_mm: float = Field(gt=0, description="Radius of the calibration ball, mm.")
    bins: int = Field(ge=2, le=255, description="Colour-difference bins per channel (one more "
                      "bin per channel holds saturated values).")
    colour_min: float = Field(description="Lower end of the binned colour difference, grey levels.")
    colour_max: float = Field(description="Upper end of the binned colour difference, grey levels.")
    saturation_level: int = Field(ge=1, le=255, description="Raw frame value at or above which "
                                  "a channel counts as saturated.")
    node_spacing_px: float = Field(gt=0, description="Spacing of the position grid, px; node "
                                   "(i, j) is at row i * spacing, column j * spacing.")
    n_slots: int = Field(ge=1, description="Number of distinct table entries per node.")
    reference_gain: bool = Field(False, description="Colour differences are multiplied by "
                                 "reference_gain(reference) (channel mean over pixel value) "
                                 "before binning, evening out the illumination brightness.")
    offset_inlier_grey: float = Field(gt=0, description="Half-width of the colour window around "
                                      "the median difference whose pixels estimate the frame's "
                                      "illumination offset, grey levels.")
    poisson_weight_x: float = Field(gt=0, description="Weight of the x (column) derivatives in "
                                    "the depth integration.")
    poisson_weight_y: float = Field(gt=0, description="Weight of the y (row) derivatives in the "
                                    "depth integration.")
    n_presses: int = Field(ge=1, description="Number of ball presses the model was fitted on.")
    fit_metrics: dict[str, float] = Field(
        default_factory=dict,
        description="Figures measured when the model was fitted (names carry their units).",
    )

    @model_validator(mode="after")
    def _check(self) -> ShadingHeader:
        if not self.colour_max > self.colour_min:
            raise ValueError(f"colour_max={self.colour_max} must exceed colour_min="
                             f"{self.colour_min}")
        return self

    @property
    def image_shape(self) -> tuple[int, int]:
        """(H, W) in pixels."""
        return (self.image_height_px, self.image_width_px)

    @property
    def node_grid_shape(self) -> tuple[int, int]:
        """(rows, columns) of the node grid covering the image."""
        return node_grid_shape(self.image_shape, self.node_spacing_px)


def node_grid_shape(image_shape: tuple[int, int], spacing_px: float) -> tuple[int, int]:
    """(rows, columns) of nodes at multiples of ``spacing_px`` that cover (H, W) pixels."""
    h, w = image_shape
    return (math.ceil((h - 1) / spacing_px) + 1, math.ceil((w - 1) / spacing_px) + 1)


@dataclass(frozen=True)
class ShadingModel:
    """A fitted shading model.

    header : :class:`ShadingHeader`.
    slot_of_bin : ((bins + 1) ** 3,) int32, table slot of each colour bin (R-major order).
    table : (node rows, node columns, n_slots, 2) float32, gradient of depth along image
        columns and image rows (dimensionless, mm per mm) at each node and slot.
    """

    header: ShadingHeader
    slot_of_bin: np.ndarray
    table: np.ndarray

    def __post_init__(self):
        h = self.header
        nb = h.bins + 1
        if self.slot_of_bin.shape != (nb ** 3,):
            raise ShadingModelError(f"slot_of_bin has shape {self.slot_of_bin.shape}, expected "
                                    f"({nb ** 3},) for bins={h.bins}")
        expected = (*h.node_grid_shape, h.n_slots, 2)
        if self.table.shape != expected:
            raise ShadingModelError(f"table has shape {self.table.shape}, expected {expected}")
        if self.slot_of_bin.size and (self.slot_of_bin.min() < 0
                                      or self.slot_of_bin.max() >= h.n_slots):
            raise ShadingModelError(f"slot_of_bin values must lie in [0, {h.n_slots}), got "
                                    f"[{self.slot_of_bin.min()}, {self.slot_of_bin.max()}]")
        if not np.all(np.isfinite(self.table)):
            raise ShadingModelError("table holds non-finite values")


# --------------------------------------------------------------------------------- geometry
def pixel_centres_mm(shape: tuple[int, int], mm_per_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Sensor-frame coordinates of pixel centres, mm: x (W,) along columns, y (H,) along rows.

    Columns run along +x and rows along -y, centred on the image centre.
    """
    h, w = shape
    x = (np.arange(w) - (w - 1) / 2.0) * mm_per_px
    y = ((h - 1) / 2.0 - np.arange(h)) * mm_per_px
    return x, y


def gradients_to_depth(dd_dx, dd_dy, mm_per_px: float,
                       weights_xy: tuple[float, float] = (1.0, 1.0)) -> np.ndarray:
    """Depth map (H, W) float32, mm, from sensor-frame gradients (dimensionless).

    Flat far field: the depth is zero half a pixel outside the image. ``weights_xy`` weighs the
    x and y derivative terms of the least-squares integration.
    """
    dd_dx = np.asarray(dd_dx, np.float32)
    dd_dy = np.asarray(dd_dy, np.float32)
    if dd_dx.ndim != 2 or dd_dx.shape != dd_dy.shape:
        raise ValueError(f"dd_dx and dd_dy must be (H, W) arrays of one shape, got "
                         f"{dd_dx.shape} and {dd_dy.shape}")
    if not mm_per_px > 0:
        raise ValueError(f"mm_per_px must be > 0, got {mm_per_px}")
    solver = poisson_solver(dd_dx.shape, "dirichlet", tuple(float(w) for w in weights_xy))
    s = np.float32(mm_per_px)
    # image columns = +x, image rows = -y; derivatives in mm per pixel
    return solver.integrate(dd_dx * s, -dd_dy * s)


# --------------------------------------------------------------------------------- frames
def _check_rgb(name: str, img, shape: tuple[int, int] | None = None) -> np.ndarray:
    img = np.asarray(img)
    if img.dtype != np.uint8:
        raise ShadingModelError(f"{name} must be uint8 (8-bit RGB), got dtype {img.dtype}")
    if img.ndim != 3 or img.shape[2] != 3:
        raise ShadingModelError(f"{name} must be an (H, W, 3) RGB image, got shape {img.shape}")
    if shape is not None and img.shape[:2] != tuple(shape):
        raise ShadingModelError(f"{name} is {img.shape[1]}x{img.shape[0]} (WxH) px, expected "
                                f"{shape[1]}x{shape[0]}")
    return img


def frame_offset(frame, reference, inlier_grey: float = 12.0, stride: int = 3) -> np.ndarray:
    """Per-channel illumination offset of ``frame`` against ``reference``, grey levels, (3,).

    The median of ``frame - reference`` over pixels on a ``stride`` grid, refined twice with
    only the pixels whose three channels all lie within ``inlier_grey`` of the current estimate,
    so that a contact covering less than about half of the frame does not bias it.
    """
    f = _check_rgb("frame", frame)
    r = _check_rgb("reference", reference, f.shape[:2])
    d = (f[::stride, ::stride].astype(np.int16) - r[::stride, ::stride]).reshape(-1, 3)
    d = np.ascontiguousarray(d.T)                      # (3, n)
    m = np.array([_median_int(c) for c in d], np.float32)
    for _ in range(2):
        keep = np.all(np.abs(d - m[:, None]) < inlier_grey, axis=0)
        if keep.sum() < 16:
            break
        m = np.array([_median_int(c[keep]) for c in d], np.float32)
    return m


def _median_int(v: np.ndarray) -> float:
    """Median of integers in [-255, 255] by counting (faster than sorting)."""
    cnt = np.bincount(v.astype(np.int64) + 255, minlength=511)
    cum = np.cumsum(cnt)
    n = cum[-1]
    lo = int(np.searchsorted(cum, (n + 1) // 2))
    hi = int(np.searchsorted(cum, n // 2 + 1))
    return 0.5 * (lo + hi) - 255.0


def reference_gain(reference) -> np.ndarray:
    """(H, W, 3) float32: each channel's mean over the reference divided by the pixel's value.

    Multiplying colour differences by it evens out the brightness of the illumination across
    the image (a press under a dimmer part of the field changes the colour less).
    """
    r = _check_rgb("reference", reference).astype(np.float32)
    return r.reshape(-1, 3).mean(0) / np.maximum(r, 1.0)


def colour_bin_index(diff, saturated, bins: int, colour_min: float,
                     colour_max: float) -> np.ndarray:
    """Flat colour-bin index (H, W) int64 of colour differences (H, W, 3), grey levels.

    ``saturated`` (H, W, 3) bool marks channels that go to the extra bin ``bins``.
    """
    scale = bins / (colour_max - colour_min)
    q = ((np.asarray(diff, np.float32) - np.float32(colour_min)) * np.float32(scale))
    q = np.clip(q, 0, bins - 1).astype(np.int64)
    q[saturated] = bins
    nb = bins + 1
    return (q[..., 0] * nb + q[..., 1]) * nb + q[..., 2]


class DepthFromShading:
    """Apply a :class:`ShadingModel` to frames of one sensor (tables set up once).

    model : the fitted model.
    reference : (H, W, 3) uint8 RGB frame of the sensor with nothing touching it, at the
        model's resolution.
    """

    def __init__(self, model: ShadingModel, reference):
        self.model = model
        h = model.header
        self.shape = h.image_shape
        self.reference = _check_rgb("reference", reference, self.shape)
        self._ref = self.reference.astype(np.float32)
        scale = np.float32(h.bins / (h.colour_max - h.colour_min))
        self._scale = (reference_gain(self.reference) * scale if h.reference_gain
                       else np.full(self._ref.shape, scale, np.float32))
        self._lo = np.float32(h.colour_min) * scale
        hh, ww = self.shape
        ny, nx = h.node_grid_shape
        sp = h.node_spacing_px
        fy = np.arange(hh) / sp
        fx = np.arange(ww) / sp
        iy = np.minimum(fy.astype(np.int64), ny - 2)
        ix = np.minimum(fx.astype(np.int64), nx - 2)
        ty = (fy - iy).astype(np.float32)[:, None]
        tx = (fx - ix).astype(np.float32)[None, :]
        base = (iy[:, None] * nx + ix[None, :]) * h.n_slots
        self._corner = [base, base + h.n_slots, base + nx * h.n_slots,
                        base + (nx + 1) * h.n_slots]
        self._weight = [(1 - ty) * (1 - tx), (1 - ty) * tx, ty * (1 - tx), ty * tx]
        flat = model.table.reshape(-1, 2)
        # one complex gather per corner is much faster than gathering (., 2) rows
        self._table = (flat[:, 0] + 1j * flat[:, 1]).astype(np.complex64)
        self._solver = poisson_solver(self.shape, "dirichlet",
                                      (h.poisson_weight_x, h.poisson_weight_y))

    def image_gradients(self, frame) -> tuple[np.ndarray, np.ndarray]:
        """Gradients of depth along image columns and rows, (H, W) float32 each, mm per mm."""
        h = self.model.header
        f = _check_rgb("frame", frame, self.shape)
        off = frame_offset(f, self.reference, h.offset_inlier_grey)
        # bin coordinate per channel: ((frame - reference - offset) * gain - colour_min) * scale
        q = f.astype(np.float32)
        q -= self._ref
        q -= off
        q *= self._scale
        q -= self._lo
        np.clip(q, 0, h.bins - 1, out=q)
        qi = q.astype(np.int32)
        qi[f >= h.saturation_level] = h.bins
        nb = h.bins + 1
        slot = self.model.slot_of_bin[(qi[..., 0] * nb + qi[..., 1]) * nb + qi[..., 2]]
        g = self._table[self._corner[0] + slot]
        g *= self._weight[0]
        for corner, w in zip(self._corner[1:], self._weight[1:]):
            t = self._table[corner + slot]
            t *= w
            g += t
        return g.real.copy(), g.imag.copy()

    def gradients(self, frame) -> tuple[np.ndarray, np.ndarray]:
        """Sensor-frame gradients ``(dd_dx, dd_dy)`` of depth, (H, W) float32, dimensionless."""
        g_col, g_row = self.image_gradients(frame)
        return g_col, -g_row

    def depth(self, frame) -> np.ndarray:
        """Depth map (H, W) float32, mm, positive into the gel, at the frame's resolution."""
        g_col, g_row = self.image_gradients(frame)
        s = np.float32(self.model.header.mm_per_px)
        return self._solver.integrate(g_col * s, g_row * s)

    __call__ = depth


def frame_to_depth(model: ShadingModel, frame, reference) -> np.ndarray:
    """Depth map (H, W) float32, mm, of one RGB frame (see :class:`DepthFromShading`)."""
    return DepthFromShading(model, reference).depth(frame)


# --------------------------------------------------------------------------------- files
def save_shading(model: ShadingModel, path: str | os.PathLike) -> None:
    """Write ``model`` as ``.npz`` with its JSON header (atomic: temporary file + rename)."""
    write_npz(path, header_json=np.array(model.header.model_dump_json()),
              slot_of_bin=model.slot_of_bin.astype(np.int32),
              table=model.table.astype(np.float32))


def load_shading(path: str | os.PathLike) -> ShadingModel:
    """Read and validate a shading model written by :func:`save_shading`.

    Raises FileNotFoundError if missing, :class:`ShadingModelError` naming the file and the
    offending field (expected and actual values) if the content is invalid.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"shading model {path} not found; fit one with "
                                "`tactile-deploy calibrate shading`")
    not_a_model = (f"{path}: not a readable .npz file, so not a shading model; fit one with "
                   "`tactile-deploy calibrate shading` and pass the .npz it writes")
    try:
        loaded = np.load(path, allow_pickle=False)
        if not isinstance(loaded, np.lib.npyio.NpzFile):   # a .npy array
            raise ShadingModelError(not_a_model)
        with loaded as z:
            arrays = {k: z[k] for k in z.files}
    except (zipfile.BadZipFile, ValueError):
        raise ShadingModelError(not_a_model) from None
    except OSError as e:
        raise ShadingModelError(f"{path}: cannot be read ({e.strerror or e}); check its "
                                "permissions") from None
    for key in ("header_json", "slot_of_bin", "table"):
        if key not in arrays:
            raise ShadingModelError(f"{path}: array '{key}' is missing (has "
                                    f"{sorted(arrays)}); is this a shading model file?")
    try:
        doc = json.loads(str(arrays["header_json"]))
    except json.JSONDecodeError as e:
        raise ShadingModelError(f"{path}: header_json is not valid JSON ({e.msg})") from None
    if not isinstance(doc, dict):
        raise ShadingModelError(f"{path}: header_json must be a JSON object, got "
                                f"{type(doc).__name__}")
    if doc.get("format_version") != FORMAT_VERSION:
        raise ShadingModelError(f"{path}: field 'format_version': this version of "
                                f"tactile-deploy reads version {FORMAT_VERSION}, the file has "
                                f"{doc.get('format_version')!r}")
    try:
        header = ShadingHeader.model_validate(doc)
    except ValidationError as e:
        raise ShadingModelError(validation_error_text(path, e, "shading model header")) from None
    slot = arrays["slot_of_bin"]
    table = arrays["table"]
    if slot.dtype.kind not in "iu":
        raise ShadingModelError(f"{path}: array 'slot_of_bin' must be integer, got {slot.dtype}")
    if table.dtype.kind != "f":
        raise ShadingModelError(f"{path}: array 'table' must be floating point, got "
                                f"{table.dtype}")
    try:
        return ShadingModel(header, slot.astype(np.int64), table.astype(np.float32))
    except ShadingModelError as e:
        raise ShadingModelError(f"{path}: {e}") from None

