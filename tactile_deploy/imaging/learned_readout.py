"""Learned read-out: rectified camera frame -> depth map by a small convolutional network.

The shading table (:mod:`tactile_deploy.imaging.shading`) reads each pixel's colour alone; where
the slope of a contact edge is steep, one LED channel clips and another goes dark, and the
colour no longer tells the slope. A network that sees the pixel's neighbourhood can hold such a
pixel by the shape around it. It is trained once per sensor *design* on a family of virtual units
(LED placement and brightness varied within assembly tolerances, ``training/shading_net``), so a
new unit needs only its own no-contact reference frame and camera mapping.

Input features (:class:`FeatureMaker`, one (11, H, W) float32 stack per frame on the imaging
grid; H, W any size, the network is fully convolutional):

==========  ==============================================================================
channels    meaning
==========  ==============================================================================
0-2         ``(frame - reference - offset) * reference_gain / COLOUR_SCALE_GREY`` (RGB), the
            offset being the frame's illumination drift (:func:`~.shading.frame_offset`)
3-5         1 where the frame's channel is saturated (>= ``saturation_level``), else 0
6-8         ``reference / 255`` (the unit's illumination)
9-10        sensor-frame x and y of the cell centre / ``POSITION_SCALE_MM`` (the LEDs' geometry)
==========  ==============================================================================

Output: depth (H, W) mm, positive into the gel, on the same imaging grid (the ONNX output
``depth_mm``, shape (B, H, W)); the network also returns the depth gradients it was trained
on (``gradients``, (B, 2, H, W), along image columns (+x) and rows (-y), mm per mm), which the
runtime does not use.

The ONNX file carries its contract in its metadata (``readout_format``, ``feature_version``,
``colour_scale_grey``, ``position_scale_mm``, ``saturation_level``, ``design``), checked on load,
and optionally ``window_cells``: the side of the crops it was trained on. The network pads its
input on the right and at the bottom to a multiple of 8 cells; a grid wider or taller than the
training crops would be padded where training never padded (the GelSight Mini's 66-cell-wide grid
read by a network trained on 64-cell crops over-read every falling flank at its right edge by up to
0.2 mm). Such a grid is read in overlapping windows of ``window_cells`` along that axis
(:func:`window_starts`), blended with weights that fall to 0 towards the windows' inner edges
(:func:`window_weights`), so that every cell is read as in training. Without the key, the whole
grid is read at once.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from tactile_deploy.imaging.camera_mapping import OutputGrid, grid_centres_mm
from tactile_deploy.imaging.shading import frame_offset, reference_gain
from tactile_deploy.onnx_runtime.errors import ModelContractError
from tactile_deploy.onnx_runtime.session import make_session

#: Version of the feature definition above; a network trained on another version is refused.
FEATURE_VERSION = 1
#: Grey levels that map to 1.0 in the colour-difference channels.
COLOUR_SCALE_GREY = 64.0
#: Millimetres that map to 1.0 in the position channels.
POSITION_SCALE_MM = 17.5
#: Feature channels (see the module docstring).
N_FEATURES = 11
#: ``readout_format`` value of a network file in this format.
READOUT_FORMAT = "tactile-deploy learned read-out 1"


class ReadoutError(ValueError):
    """A learned read-out file, or a frame given to it, is not what it must be."""


#: Cells over which overlapping windows hand over to each other (:func:`window_weights`).
WINDOW_OVERLAP_CELLS = 16


def _whole_number(text: str) -> int | None:
    """``int(text)``, or None when the text is not a whole number."""
    try:
        return int(text)
    except ValueError:
        return None


def window_starts(n: int, size: int, overlap: int = WINDOW_OVERLAP_CELLS) -> list[int]:
    """First cells of the windows of ``size`` cells that cover ``n`` cells along one axis: one
    window (start 0) when ``n <= size``, else the fewest windows that overlap by at least
    ``overlap`` cells, spread evenly, the first at 0 and the last ending at ``n``."""
    if n <= size:
        return [0]
    if size <= overlap:
        raise ValueError(f"window of {size} cells must be wider than the overlap ({overlap})")
    k = -(-(n - overlap) // (size - overlap))      # ceil
    k = max(k, 2)
    return [round(i * (n - size) / (k - 1)) for i in range(k)]


def window_weights(n: int, size: int, starts: list[int], overlap: int = WINDOW_OVERLAP_CELLS) -> np.ndarray:
    """(len(starts), min(n, size)) float32 blending weights of each window's cells: 1, falling
    linearly to near 0 over ``overlap`` cells towards each window edge that lies inside the grid
    (an edge at the grid's own border keeps weight 1: training crops had it there too)."""
    size = min(n, size)
    ramp = (np.arange(size, dtype=np.float32) + 0.5) / overlap
    w = np.ones((len(starts), size), np.float32)
    for i, s in enumerate(starts):
        if s > 0:
            w[i] = np.minimum(w[i], ramp)
        if s + size < n:
            w[i] = np.minimum(w[i], ramp[::-1])
    return w


class FeatureMaker:
    """Per-frame features of one unit: the parts that depend only on the reference and the
    imaging grid are computed once.

    reference_u8 : (H, W, 3) uint8 rectified no-contact frame on ``grid``.
    grid : the imaging grid (sensor frame, mm).
    saturation_level, inlier_grey : raw value counted as saturated, and the offset estimate's
        window (:func:`~.shading.frame_offset`); the defaults are the ones read-outs are trained
        with.
    """

    def __init__(self, reference_u8: np.ndarray, grid: OutputGrid, saturation_level: int = 254,
                 inlier_grey: float = 12.0):
        ref = np.asarray(reference_u8)
        if ref.shape != (grid.ny, grid.nx, 3) or ref.dtype != np.uint8:
            raise ReadoutError(f"reference must be ({grid.ny}, {grid.nx}, 3) uint8 (the imaging "
                               f"grid), got {ref.shape} {ref.dtype}")
        self.reference_u8 = np.ascontiguousarray(ref)
        self.reference = ref.astype(np.float32)
        self.scale = (reference_gain(ref) / COLOUR_SCALE_GREY).astype(np.float32)
        self.saturation_level = int(saturation_level)
        self.inlier_grey = float(inlier_grey)
        x, y = grid_centres_mm(grid)
        self.fixed = np.concatenate(
            [np.moveaxis(self.reference / 255.0, -1, 0),
             (np.stack([x, y]) / POSITION_SCALE_MM)], axis=0).astype(np.float32)   # (5, H, W)

    def __call__(self, image_u8: np.ndarray) -> np.ndarray:
        """(11, H, W) float32 features of a rectified frame (H, W, 3) uint8."""
        image = np.asarray(image_u8)
        if image.shape != self.reference_u8.shape or image.dtype != np.uint8:
            raise ReadoutError(f"frame must be {self.reference_u8.shape} uint8 (the imaging grid), "
                               f"got {image.shape} {image.dtype}")
        diff = image.astype(np.float32)
        diff -= self.reference
        diff -= frame_offset(image, self.reference_u8, self.inlier_grey)
        diff *= self.scale
        sat = image >= self.saturation_level
        return np.concatenate([np.moveaxis(diff, -1, 0), np.moveaxis(sat, -1, 0).astype(np.float32),
                               self.fixed], axis=0)


class LearnedReadout:
    """An onnxruntime session of a learned read-out network and its contract.

    path : the ``.onnx`` file. threads : intra-op threads (1: the runtime's default, one core).
    """

    def __init__(self, path: str | Path, threads: int = 1):
        self.path = Path(path)
        if not self.path.is_file():
            raise ReadoutError(f"learned read-out {self.path} not found")
        try:
            self.session = make_session(self.path, threads, providers="cpu")
        except ModelContractError as e:
            raise ReadoutError(f"learned read-out {e}") from None
        meta = self.session.get_modelmeta().custom_metadata_map
        self.metadata = dict(meta)
        fmt = meta.get("readout_format")
        if fmt != READOUT_FORMAT:
            raise ReadoutError(f"learned read-out {self.path}: metadata field 'readout_format' must "
                               f"be {READOUT_FORMAT!r}, got {fmt!r}")
        expected = {"feature_version": str(FEATURE_VERSION),
                    "colour_scale_grey": repr(COLOUR_SCALE_GREY),
                    "position_scale_mm": repr(POSITION_SCALE_MM)}
        for key, value in expected.items():
            if meta.get(key) != value:
                raise ReadoutError(f"learned read-out {self.path}: metadata field {key!r} must be "
                                   f"{value!r} (this version's features), got {meta.get(key)!r}")
        self.saturation_level = int(meta.get("saturation_level", "254"))
        inputs = self.session.get_inputs()
        if len(inputs) != 1 or inputs[0].shape[1] != N_FEATURES:
            raise ReadoutError(f"learned read-out {self.path}: expected one input of "
                               f"{N_FEATURES} channels, got {[(i.name, i.shape) for i in inputs]}")
        self.input_name = inputs[0].name
        self.output_names = [o.name for o in self.session.get_outputs()]
        if "depth_mm" not in self.output_names:
            raise ReadoutError(f"learned read-out {self.path}: no output 'depth_mm' "
                               f"(outputs {self.output_names})")
        window = meta.get("window_cells")
        self.window_cells = None if window is None else _whole_number(window)
        if window is not None and not (self.window_cells or 0) > 2 * WINDOW_OVERLAP_CELLS:
            raise ReadoutError(f"learned read-out {self.path}: metadata field 'window_cells' must be a whole "
                               f"number of cells > {2 * WINDOW_OVERLAP_CELLS}, got {window!r}")
        self._windows: dict[tuple[int, int], tuple] = {}   # (H, W) -> window plan (:meth:`_window_plan`)

    def _run(self, features: np.ndarray) -> np.ndarray:
        out = self.session.run(["depth_mm"], {self.input_name: features[None]})[0]
        return np.asarray(out[0], np.float32)

    def _window_plan(self, h: int, w: int) -> tuple[list[tuple[slice, slice, np.ndarray]], np.ndarray]:
        """The windows of an (h, w) grid: (rows, columns, blending weights) each, and 1 / the
        summed weights (h, w); made once per grid size."""
        plan = self._windows.get((h, w))
        if plan is None:
            size = self.window_cells
            rows, cols = window_starts(h, size), window_starts(w, size)
            wr, wc = window_weights(h, size, rows), window_weights(w, size, cols)
            sh, sw = min(h, size), min(w, size)
            windows, weight = [], np.zeros((h, w), np.float32)
            for r, w_r in zip(rows, wr):
                for c, w_c in zip(cols, wc):
                    windows.append((slice(r, r + sh), slice(c, c + sw), w_r[:, None] * w_c[None, :]))
                    weight[r:r + sh, c:c + sw] += windows[-1][2]
            plan = self._windows[(h, w)] = (windows, 1.0 / weight)
        return plan

    def depth_mm(self, features: np.ndarray) -> np.ndarray:
        """Depth (H, W) float32 mm from features (11, H, W) float32; in overlapping windows of
        ``window_cells`` along an axis longer than that (module docstring)."""
        h, w = features.shape[-2:]
        size = self.window_cells
        if size is None or (h <= size and w <= size):
            return self._run(features)
        windows, inverse_weight = self._window_plan(h, w)
        total = np.zeros((h, w), np.float32)
        for rows, cols, weight in windows:
            total[rows, cols] += weight * self._run(features[:, rows, cols])
        return total * inverse_weight
