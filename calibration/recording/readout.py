"""A learned read-out in a calibration from recorded ball presses: its design checked against the
pad family, its grid, and which presses its checks can measure.

A learned read-out (:mod:`tactile_deploy.imaging.learned_readout`) is trained on virtual units of
one sensor design, on the imaging grid of model-grid cells (0.273 mm): it reads frames rectified
onto that grid, and its depth is used as trained (gain 1). The calibration wizard calibrates a
per-unit gain from the rig's known intrusions
(:mod:`tactile_deploy.calibration.shading.readout_gain`); recorded presses have none. A gain from
the ball's curvature inside each contact was tried and is not used: on the virtual DIGIT the
read-out's cap inside 1 mm contacts (4 cells) is flatter than the ball (smoothed), so that gain
came out 1.34 and put new ball presses 90 um RMS off where gain 1 left them 15 um off
(docs/families.md).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from tactile_deploy.calibration.recording.errors import PlausibilityError
from tactile_deploy.calibration.shading.evaluate import MIN_FIT_PIXELS, fit_region

#: Fewest cells of the read-out's grid inside 0.8 contact radii for a press to be measured: the
#: sphere fits' minimum.
MIN_REGION_CELLS = MIN_FIT_PIXELS


def measurable(presses, region_fraction: float = 0.8) -> np.ndarray:
    """(N,) bool: the presses of a :class:`~tactile_deploy.calibration.shading.presses.PressSet`
    (circles in grid cells) whose sphere-fit region (``region_fraction`` of the contact circle,
    :func:`~tactile_deploy.calibration.shading.evaluate.fit_region`) holds at least
    ``MIN_REGION_CELLS`` cells of the grid (small or edge-cut contacts on the read-out's coarser
    grid do not)."""
    return np.array([fit_region(presses.shape, c, region_fraction)[2].sum() >= MIN_REGION_CELLS
                     for c in presses.circles])


class ReadoutDepth:
    """Depth (H, W) mm on the imaging grid from rectified frames, through a learned read-out.

    readout : a :class:`~tactile_deploy.imaging.learned_readout.LearnedReadout`.
    reference : (H, W, 3) uint8 rectified no-contact frame. grid : the imaging grid
    (:class:`~tactile_deploy.imaging.camera_mapping.OutputGrid`, sensor frame, mm).
    """

    def __init__(self, readout, reference, grid):
        from tactile_deploy.imaging.learned_readout import FeatureMaker

        self.readout = readout
        self.features = FeatureMaker(np.asarray(reference, np.uint8), grid, readout.saturation_level)

    def depth(self, frame) -> np.ndarray:
        """Depth (H, W) float32 mm of one rectified frame (H, W, 3) uint8."""
        return self.readout.depth_mm(self.features(np.asarray(frame, np.uint8)))


def load_family_readout(path: str | Path, family_name: str):
    """The :class:`~tactile_deploy.imaging.learned_readout.LearnedReadout` at ``path`` and its
    design, refused (:class:`PlausibilityError`) when the design's pad is not ``family_name``."""
    from tactile_deploy.imaging.learned_readout import LearnedReadout, ReadoutError
    from tactile_deploy.sensors.catalog import UnknownSensorError, sensor_config

    try:
        readout = LearnedReadout(path)
    except ReadoutError as e:
        raise PlausibilityError(f"--readout: {e}") from None
    design = readout.metadata.get("design")
    try:
        pad = sensor_config(design).pad if design else None
    except (UnknownSensorError, FileNotFoundError):
        pad = None
    if pad is not None and pad != family_name:
        raise PlausibilityError(
            f"--readout {path}: it was trained for the design {design!r}, whose pad is {pad!r}, "
            f"not --pad {family_name!r}; give the read-out of a {family_name} design "
            f"(exported/{family_name}_readout.onnx, or one trained with python -m "
            "tactile_deploy.training.shading_net --design NAME), or leave --readout out to use "
            "the fitted shading model")
    return readout, design
