"""Imaging pipeline: raw camera frame -> depth map on the model grid, one named function per stage.

Data flow (:meth:`ImagingPipeline.frame_to_depth`, and :func:`frame_to_mesh` with the model)::

    frame (H, W, 3) uint8 RGB, raw camera pixels
      -> check_frame            refuse wrong size / type / NaN with a clear error
      -> hooks.preprocess_frame (a plugin's own code, identity by default)
      -> rectify_frame          undistort + homography: samples of the imaging grid (one cv2.remap)
      -> resample_to_grid       area average of each grid cell's samples
      -> subtract_reference     colour difference to the no-contact frame, minus the illumination drift
      -> shading_gradients      shading LUT (colour bin x position) -> depth gradients, mm/mm
      -> integrate_depth        least-squares (Poisson) integration, DST, depth 0 outside the grid
      -> to_model_grid          area resampling onto the model grid (+-17.5 mm, 128 x 128), if different
      -> apply_noise_reference  subtract the no-contact depth, or keep it, as the plugin says
      -> hooks.postprocess_depth
    depth (128, 128) float32 mm, positive into the gel, model grid
      -> MeshPredictor.infer    ONNX model -> vertices (5380, 3) mm, sensor frame

Grids and frames. The *imaging grid* is the camera mapping's output grid (:class:`~tactile_deploy.
imaging.camera_mapping.OutputGrid`): for the GelSlim plugins it is the model grid itself; for a
sensor with a smaller field of view or finer pixels (e.g. a GelSight at 0.05 mm/px) it is that
sensor's own grid, so the shading model keeps the camera's resolution, and ``to_model_grid``
averages the depth onto the model grid (cells outside the sensor's field get depth 0, the flat far
field, except within the plugin's ``view_edge_extension_mm`` of the field's edge, where the edge's
depth continues: a contact seen at the edge of the view goes on past it). Both grids are
sensor-frame grids with row 0 at the largest y and columns along +x.

The shading stages reproduce :class:`tactile_deploy.imaging.shading.DepthFromShading` exactly
(same operations in the same order; tested), split so each stage can be timed and called alone.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import cv2
import numpy as np
import scipy.sparse

from tactile_deploy.imaging.camera_mapping import (
    CameraMapping,
    OutputGrid,
    build_remap,
    compact_remap,
    rectify,
)
from tactile_deploy.imaging.learned_readout import FeatureMaker
from tactile_deploy.imaging.poisson import PoissonSolver
from tactile_deploy.imaging.shading import ShadingModel, depth_solver, frame_offset, reference_gain

NoiseHandling = str  # "subtract" | "keep"


class FrameError(ValueError):
    """A frame (or depth map) the pipeline cannot use: wrong size, type, channels or NaN."""


# ------------------------------------------------------------------------------------ timing
class Laps:
    """Stage timer: ``lap(name)`` records the ns since the previous lap (or ``start``)."""

    __slots__ = ("_t", "times_ns")

    def __init__(self) -> None:
        self.times_ns: dict[str, int] = {}
        self._t = time.perf_counter_ns()

    def start(self) -> Laps:
        self._t = time.perf_counter_ns()
        return self

    def lap(self, name: str) -> None:
        t = time.perf_counter_ns()
        self.times_ns[name] = self.times_ns.get(name, 0) + (t - self._t)
        self._t = t

    def ms(self) -> dict[str, float]:
        return {k: v / 1e6 for k, v in self.times_ns.items()}


class _NoLaps:
    __slots__ = ()

    def lap(self, name: str) -> None:
        pass


_NO_LAPS = _NoLaps()


# ------------------------------------------------------------------------------------ stages
def check_frame(frame, shape_hw: tuple[int, int]) -> np.ndarray:
    """Check a raw camera frame: (H, W, 3) uint8 RGB with (H, W) = ``shape_hw``.

    Raises :class:`FrameError` naming what is wrong and how to fix it.
    """
    h, w = shape_hw
    if not isinstance(frame, np.ndarray):
        raise FrameError(f"frame must be a numpy array (H, W, 3) uint8 RGB, got "
                         f"{type(frame).__name__}")
    if frame.dtype != np.uint8:
        nan = int(np.isnan(frame).sum()) if frame.dtype.kind == "f" else 0
        extra = f" with {nan} NaN values" if nan else ""
        raise FrameError(f"frame has dtype {frame.dtype}{extra}, expected uint8 RGB (0-255) "
                         "camera pixels; convert with np.clip(frame, 0, 255).astype(np.uint8) "
                         "after replacing NaNs")
    if frame.ndim != 3 or frame.shape[2] != 3:
        hint = (" (drop the alpha channel: frame[..., :3])" if frame.ndim == 3
                and frame.shape[2] == 4 else " (a grey frame: the shading model needs colour)"
                if frame.ndim == 2 else "")
        raise FrameError(f"frame has shape {frame.shape}, expected ({h}, {w}, 3) RGB{hint}")
    if frame.shape[:2] != (h, w):
        raise FrameError(f"frame is {frame.shape[1]}x{frame.shape[0]} px (W x H), the plugin's "
                         f"camera mapping is for {w}x{h} px; set the camera to {w}x{h} or "
                         "recalibrate the plugin for this resolution")
    return frame


def default_supersample(camera: CameraMapping, max_factor: int = 2) -> int:
    """Samples per imaging-grid cell side for :class:`Rectifier`: enough for the samples to be
    no coarser than the camera's pixels on the pad, at most ``max_factor`` (the cost of the
    remap grows with its square)."""
    g = camera.grid
    ratio = min(g.pitch_x_mm / camera.mm_per_px_x, g.pitch_y_mm / camera.mm_per_px_y)
    return int(np.clip(np.ceil(ratio - 1e-6), 1, max_factor))


class Rectifier:
    """Resampling of raw camera frames onto the imaging grid.

    The raw frame is sampled (bilinear, lens and homography undone, one ``cv2.remap``) at
    ``supersample x supersample`` points per grid cell, and the samples of each cell are then
    averaged (``cv2.resize`` with ``INTER_AREA``): an area average of the frame over the cell,
    which keeps camera noise and aliasing down when a cell covers several camera pixels (a
    GelSlim at 0.075 mm/px sees about 3.6 x 3.6 pixels per 0.273 mm cell). ``supersample=1`` is
    point sampling at the cell centres.
    """

    def __init__(self, camera: CameraMapping, supersample: int | None = None):
        self.camera = camera
        self.supersample = int(default_supersample(camera) if supersample is None else supersample)
        if not 1 <= self.supersample <= 8:
            raise ValueError(f"supersample must be 1..8, got {self.supersample}")
        g = camera.grid
        s = self.supersample
        fine = g.model_copy(update={"nx": g.nx * s, "ny": g.ny * s})
        self.fine_camera = camera.model_copy(update={"grid": fine})
        self.remap = compact_remap(build_remap(self.fine_camera))
        self.size = (g.nx, g.ny)


def rectify_frame(frame: np.ndarray, rectifier: Rectifier) -> np.ndarray:
    """Raw frame (H, W, 3) uint8 -> (ny * s, nx * s, 3) uint8 samples of the imaging grid (lens
    and homography undone, bilinear; row 0 = largest y)."""
    return rectify(frame, rectifier.fine_camera, rectifier.remap)


def resample_to_grid(samples: np.ndarray, rectifier: Rectifier) -> np.ndarray:
    """Samples from :func:`rectify_frame` -> (ny, nx, 3) uint8, the average of each cell's
    ``s x s`` samples (rounded to grey levels)."""
    if rectifier.supersample == 1:
        return samples
    return cv2.resize(samples, rectifier.size, interpolation=cv2.INTER_AREA)


@dataclass(frozen=True)
class ShadingTables:
    """Precomputed tables of a shading model on one reference frame (imaging grid).

    reference : (ny, nx, 3) float32, the rectified no-contact frame, grey levels.
    scale : (ny, nx, 3) float32, bins per grey level (times the reference gain if used).
    lo : float32, ``colour_min * scale``.
    corner : 4 x (ny, nx) int64 table rows of the four position nodes around each pixel.
    weight : 4 x (ny, nx) float32 bilinear weights.
    table : (nodes * slots,) complex64, gradient (columns + 1j rows) per node and slot.
    """

    reference_u8: np.ndarray
    reference: np.ndarray
    scale: np.ndarray
    lo: np.float32
    corner: tuple
    weight: tuple
    table: np.ndarray
    slot_of_bin: np.ndarray
    bins: int
    saturation_level: int
    inlier_grey: float
    mm_per_px: float

    @classmethod
    def build(cls, model: ShadingModel, reference_u8: np.ndarray) -> ShadingTables:
        h = model.header
        ref_u8 = np.ascontiguousarray(reference_u8)
        if ref_u8.shape != (*h.image_shape, 3) or ref_u8.dtype != np.uint8:
            raise FrameError(f"reference must be {h.image_shape + (3,)} uint8 to match the "
                             f"shading model, got {ref_u8.shape} {ref_u8.dtype}")
        scale = np.float32(h.bins / (h.colour_max - h.colour_min))
        scale_map = (reference_gain(ref_u8) * scale if h.reference_gain
                     else np.full(ref_u8.shape, scale, np.float32))
        hh, ww = h.image_shape
        ny, nx = h.node_grid_shape
        sp = h.node_spacing_px
        fy = np.arange(hh) / sp
        fx = np.arange(ww) / sp
        iy = np.minimum(fy.astype(np.int64), ny - 2)
        ix = np.minimum(fx.astype(np.int64), nx - 2)
        ty = (fy - iy).astype(np.float32)[:, None]
        tx = (fx - ix).astype(np.float32)[None, :]
        base = (iy[:, None] * nx + ix[None, :]) * h.n_slots
        corner = (base, base + h.n_slots, base + nx * h.n_slots, base + (nx + 1) * h.n_slots)
        weight = ((1 - ty) * (1 - tx), (1 - ty) * tx, ty * (1 - tx), ty * tx)
        flat = model.table.reshape(-1, 2)
        table = (flat[:, 0] + 1j * flat[:, 1]).astype(np.complex64)
        return cls(ref_u8, ref_u8.astype(np.float32), scale_map.astype(np.float32),
                   np.float32(h.colour_min) * scale, corner, weight, table,
                   np.ascontiguousarray(model.slot_of_bin, dtype=np.int64), h.bins,
                   h.saturation_level, h.offset_inlier_grey, h.mm_per_px)


def subtract_reference(image: np.ndarray, tables: ShadingTables) -> np.ndarray:
    """Colour difference (ny, nx, 3) float32, grey levels: ``image - reference - offset``, the
    offset being the frame's illumination drift estimated on its non-contact pixels."""
    off = frame_offset(image, tables.reference_u8, tables.inlier_grey)
    diff = image.astype(np.float32)
    diff -= tables.reference
    diff -= off
    return diff


def shading_gradients(diff: np.ndarray, image: np.ndarray,
                      tables: ShadingTables) -> tuple[np.ndarray, np.ndarray]:
    """Depth gradients along image columns (+x) and rows (-y), (ny, nx) float32 each, mm/mm.

    diff : colour difference from :func:`subtract_reference`; image : the rectified uint8 frame
    (saturated channels, value >= the model's saturation level, go to their own bin).
    """
    q = diff * tables.scale
    q -= tables.lo
    np.clip(q, 0, tables.bins - 1, out=q)
    qi = q.astype(np.int32)
    qi[image >= tables.saturation_level] = tables.bins
    nb = tables.bins + 1
    slot = tables.slot_of_bin[(qi[..., 0] * nb + qi[..., 1]) * nb + qi[..., 2]]
    c, w = tables.corner, tables.weight
    g = tables.table[c[0] + slot]
    g *= w[0]
    for k in (1, 2, 3):
        t = tables.table[c[k] + slot]
        t *= w[k]
        g += t
    return g.real.copy(), g.imag.copy()


def integrate_depth(g_col: np.ndarray, g_row: np.ndarray, solver: PoissonSolver,
                    mm_per_px: float) -> np.ndarray:
    """Depth (ny, nx) float32 mm (positive into the gel) from image-axis gradients (mm/mm):
    weighted least squares, depth 0 half a pixel outside the grid (flat far field)."""
    s = np.float32(mm_per_px)
    return solver.integrate(g_col * s, g_row * s)


class GridResampler:
    """Area-weighted resampling between two axis-aligned sensor-frame grids.

    ``dst = Ay @ src @ Ax.T`` where ``Ax[j, k]`` is the fraction of destination column j's
    width covered by source column k (likewise rows). The source is piecewise constant over its
    cells; with ``extend_mm`` > 0 its outermost cells reach ``extend_mm`` further out (each side,
    corners included: the view's edge value continues), and destination cells, or the parts of
    them, beyond that receive 0 (the flat far field).
    """

    def __init__(self, src: OutputGrid, dst: OutputGrid, extend_mm: float = 0.0):
        if not extend_mm >= 0.0:
            raise ValueError(f"extend_mm must be >= 0 mm, got {extend_mm!r}")
        self.src, self.dst, self.extend_mm = src, dst, float(extend_mm)
        self.identity = src == dst
        xs = src.x_min_mm + np.arange(src.nx + 1) * src.pitch_x_mm
        xd = dst.x_min_mm + np.arange(dst.nx + 1) * dst.pitch_x_mm
        ys = src.y_max_mm - np.arange(src.ny + 1) * src.pitch_y_mm
        yd = dst.y_max_mm - np.arange(dst.ny + 1) * dst.pitch_y_mm
        xs[0] -= extend_mm
        xs[-1] += extend_mm
        ys[0] += extend_mm
        ys[-1] -= extend_mm
        # sparse products: no BLAS thread pool (a multi-threaded GEMM on a busy machine is
        # slower than the work itself)
        self.ax = scipy.sparse.csr_matrix(self._overlap(xd, xs, dst.pitch_x_mm).astype(np.float32))
        self.ay = scipy.sparse.csr_matrix(self._overlap(-yd, -ys, dst.pitch_y_mm).astype(np.float32))

    @staticmethod
    def _overlap(d_edges, s_edges, d_pitch) -> np.ndarray:
        lo = np.maximum(d_edges[:-1, None], s_edges[None, :-1])
        hi = np.minimum(d_edges[1:, None], s_edges[None, 1:])
        return np.maximum(hi - lo, 0.0) / d_pitch

    def __call__(self, depth: np.ndarray) -> np.ndarray:
        if self.identity:
            return depth
        rows = self.ay @ depth                      # (dst.ny, src.nx)
        return np.ascontiguousarray((self.ax @ rows.T).T, dtype=np.float32)


def to_model_grid(depth: np.ndarray, resampler: GridResampler) -> np.ndarray:
    """Depth on the imaging grid -> (128, 128) float32 mm on the model grid."""
    return resampler(depth)


def apply_noise_reference(depth: np.ndarray, noise_mm: np.ndarray | None,
                          handling: str) -> np.ndarray:
    """``"subtract"``: ``depth - noise`` (fixed-pattern depth of the unloaded sensor removed);
    ``"keep"``: unchanged (the model was trained with this noise in its inputs)."""
    if handling == "subtract" and noise_mm is not None:
        return depth - noise_mm
    if handling not in ("subtract", "keep"):
        raise ValueError(f"noise handling must be 'subtract' or 'keep', got {handling!r}")
    return depth


# ------------------------------------------------------------------------------------ pipeline
class ImagingPipeline:
    """Frame -> depth of one sensor, with every table set up once.

    camera : camera mapping (its grid is the imaging grid).
    shading : shading model fitted on frames rectified onto that grid.
    reference_raw : (H, W, 3) uint8 RGB no-contact frame, raw camera pixels.
    noise_mm : (128, 128) float32 no-contact depth on the model grid, or None.
    noise_handling : "subtract" or "keep".
    hooks : :class:`~tactile_deploy.runtime.plugins.PluginHooks` or None.
    supersample : samples per imaging-grid cell side (:class:`Rectifier`; default from the
        camera's scale, at most 2). The shading model must be fitted on frames rectified the
        same way (:meth:`rectify`).
    readout : a :class:`~tactile_deploy.imaging.learned_readout.LearnedReadout`, or None. When
        given, the rectified frame's features go through it to depth (stages ``reference``:
        features, ``shading``: the network) instead of the shading table and the integration.
    readout_gain : the unit's depth gain of the read-out (the plugin's ``readout_depth_gain``),
        multiplying its depth.
    view_edge_extension_mm : how far (mm) beyond the imaging grid's edge its edge depth
        continues on the depth grid (the plugin's ``view_edge_extension_mm``); beyond it, 0.
    """

    def __init__(self, camera: CameraMapping, shading: ShadingModel, reference_raw: np.ndarray,
                 noise_mm: np.ndarray | None = None, noise_handling: str = "keep",
                 depth_grid: OutputGrid | None = None, hooks=None,
                 supersample: int | None = None, readout=None, readout_gain: float = 1.0,
                 view_edge_extension_mm: float = 0.0):
        self.camera = camera
        self.frame_shape = (camera.image_height_px, camera.image_width_px)
        self.rectifier = Rectifier(camera, supersample)
        reference_raw = check_frame(np.asarray(reference_raw), self.frame_shape)
        if hooks is not None:      # the reference goes through the same preprocessing as frames
            reference_raw = check_frame(hooks.preprocess_frame(reference_raw), self.frame_shape)
        self.tables = ShadingTables.build(shading, self.rectify(reference_raw))
        self.readout = readout
        self.readout_gain = np.float32(readout_gain)
        if readout is not None:

            self.features = FeatureMaker(self.tables.reference_u8, camera.grid,
                                         readout.saturation_level)
        h = shading.header
        self.solver = depth_solver(h)
        self.depth_grid = depth_grid or OutputGrid()
        self.resampler = GridResampler(camera.grid, self.depth_grid, view_edge_extension_mm)
        if noise_handling not in ("subtract", "keep"):
            raise ValueError(f"noise_handling must be 'subtract' or 'keep', got {noise_handling!r}")
        if noise_mm is not None:
            noise_mm = np.asarray(noise_mm, np.float32)
            if noise_mm.shape != (self.depth_grid.ny, self.depth_grid.nx):
                raise ValueError(f"noise_mm must have shape {(self.depth_grid.ny, self.depth_grid.nx)}, "
                                 f"got {noise_mm.shape}")
        self.noise_mm = noise_mm
        self.noise_handling = noise_handling
        self.hooks = hooks

    @classmethod
    def from_plugin(cls, plugin) -> ImagingPipeline:
        """The pipeline of a :class:`~tactile_deploy.runtime.plugins.SensorPlugin`."""
        m = plugin.manifest
        return cls(m.camera, plugin.shading_model, plugin.reference_frame,
                   plugin.noise_reference, m.noise_reference.handling, m.depth_grid,
                   plugin.hooks, readout=plugin.readout, readout_gain=m.readout_depth_gain,
                   view_edge_extension_mm=m.view_edge_extension_mm)

    def rectify(self, frame) -> np.ndarray:
        """Raw frame -> (ny, nx, 3) uint8 on the imaging grid (rectify and resample stages)."""
        return resample_to_grid(rectify_frame(frame, self.rectifier), self.rectifier)

    def readout_features(self, frame) -> np.ndarray:
        """(11, ny, nx) float32 input of the learned read-out for a raw frame (checked,
        preprocessed by the hooks, rectified), as :meth:`imaging_depth` makes it."""
        if self.readout is None:
            raise ValueError("this pipeline has no learned read-out")
        frame = check_frame(frame, self.frame_shape)
        if self.hooks is not None:
            frame = self.hooks.preprocess_frame(frame)
        return self.features(self.rectify(frame))

    def imaging_depth(self, frame, laps=None) -> np.ndarray:
        """Depth (ny, nx) float32 mm on the imaging grid (before resampling and noise handling)."""
        laps = laps or _NO_LAPS
        frame = check_frame(frame, self.frame_shape)
        if self.hooks is not None:
            frame = self.hooks.preprocess_frame(frame)
        laps.lap("check")
        samples = rectify_frame(frame, self.rectifier)
        laps.lap("rectify")
        image = resample_to_grid(samples, self.rectifier)
        laps.lap("resample")
        if self.readout is not None:
            features = self.features(image)
            laps.lap("reference")
            depth = self.readout.depth_mm(features)
            depth *= self.readout_gain
            laps.lap("shading")
            return depth
        diff = subtract_reference(image, self.tables)
        laps.lap("reference")
        g_col, g_row = shading_gradients(diff, image, self.tables)
        laps.lap("shading")
        depth = integrate_depth(g_col, g_row, self.solver, self.tables.mm_per_px)
        laps.lap("poisson")
        return depth

    def frame_to_depth(self, frame, laps=None) -> np.ndarray:
        """Depth map (128, 128) float32 mm, positive into the gel, model grid (module docstring)."""
        laps = laps or _NO_LAPS
        depth = self.imaging_depth(frame, laps)
        depth = to_model_grid(depth, self.resampler)
        depth = apply_noise_reference(depth, self.noise_mm, self.noise_handling)
        if self.hooks is not None:
            depth = self.hooks.postprocess_depth(depth)
        laps.lap("depth_grid")
        return depth

    __call__ = frame_to_depth


def frame_to_mesh(frame, pipeline: ImagingPipeline, predictor, laps=None):
    """One frame to its mesh: frame -> depth (every stage of :class:`ImagingPipeline`) -> model.

    Returns the predictor's :class:`~tactile_deploy.runtime.predictor.MeshPrediction` (batch of
    one) with the depth map attached.
    """
    laps = laps or _NO_LAPS
    depth = pipeline.frame_to_depth(frame, laps)
    prediction = predictor.infer(depth[None, None])
    laps.lap("model")
    return prediction.with_depth(depth[None])
