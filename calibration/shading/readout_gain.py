"""A unit's depth gain for a learned read-out, from ball presses of known intrusion.

The read-out (:mod:`tactile_deploy.imaging.learned_readout`) is trained on other units of the
design; on a given unit its depth comes out scaled by a few per cent (measured on the virtual
GelSlim 2: about 5 % short, docs/shading.md). The scale is calibrated on the wizard's ball
presses: under a rigid ball the gel's surface at the apex is pushed in by exactly the ball's
intrusion, which the rig knows up to its zero offset (the FEM step fits it). The gain is the
median over presses of that intrusion over the read-out's deepest cell.
"""

from __future__ import annotations

import numpy as np


def readout_depth_gain(pipeline, frames, intrusion_mm, offset_mm: float = 0.0):
    """(gain, per-press ratios (N,)) of a learned read-out on one unit.

    pipeline : an :class:`~tactile_deploy.runtime.pipeline.ImagingPipeline` with the read-out
        and gain 1. frames : raw camera frames (N, H, W, 3) uint8 of ball presses.
    intrusion_mm : (N,) the rig's intrusion of each press (commanded tip depth below the
        surface), mm. offset_mm : the rig's zero offset (true intrusion = intrusion + offset).
    """
    intrusion = np.asarray(intrusion_mm, np.float64) + float(offset_mm)
    if len(intrusion) != len(frames) or len(frames) == 0:
        raise ValueError(f"need one intrusion per frame and at least one press, got "
                         f"{len(intrusion)} intrusions for {len(frames)} frames")
    if getattr(pipeline, "readout", None) is None:
        raise ValueError("the pipeline has no learned read-out")
    peaks = np.array([float(pipeline.frame_to_depth(f).max()) for f in frames])
    ok = peaks > 0.02
    if not ok.any():
        raise ValueError("no press shows a contact deeper than 0.02 mm in the read-out's depth "
                         f"(deepest {peaks.max():.3f} mm)")
    ratios = intrusion[ok] / peaks[ok]
    return float(np.median(ratios)), ratios
