"""The learned read-out made this unit's own in the plugin step: fine-tuned on its presses
(needs the ``train`` extra) and its depth gain from the rig's presses."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from tactile_deploy.calibration.fem_fit.result import FemResult
from tactile_deploy.calibration.shading.readout_finetune import finetune_unit_readout
from tactile_deploy.calibration.shading.readout_gain import readout_depth_gain
from tactile_deploy.calibration.wizard.config import WizardConfig
from tactile_deploy.calibration.wizard.context import StepError
from tactile_deploy.calibration.wizard.press_data import press_profiles
from tactile_deploy.imaging.learned_readout import LearnedReadout
from tactile_deploy.runtime.pipeline import ImagingPipeline


def finetune_readout_on_presses(config: WizardConfig, camera, shading, ref, ref_frames, readout,
                                presses_npz: dict, material: FemResult, out: Path, unit: str,
                                log=None):
    """The design's ``readout`` fine-tuned on the kept presses of ``presses_npz`` and the
    no-contact ``ref_frames`` (:mod:`tactile_deploy.calibration.shading.readout_finetune`; targets: the
    presses' FEM depth profiles at the rig's intrusion plus the FEM step's zero offset, with its
    nu), ``config.readout_steps`` steps, written to ``out``: ``(LearnedReadout of it, a line for
    the provenance)``."""
    d = presses_npz
    keep = d["keep"]
    if not keep.any():
        raise StepError("no kept presses to fine-tune the learned read-out on: redo the presses "
                        "step, or set readout_steps to 0 in the config")
    offset = material.depth_offset_mm
    nu = material.nu
    profiles = press_profiles(config, d, camera, 4.0, offset or 0.0, nu)
    depths = np.stack([p.depth_map(camera.grid) for p in profiles])
    pipeline = ImagingPipeline(camera, shading, ref, None, "keep", readout=readout)
    result = finetune_unit_readout(pipeline, d["raw"][keep], depths, ref_frames, out, unit,
                                   steps=config.readout_steps, log=log)
    source = (f"depth targets at the rig's intrusion plus its zero offset {1e3 * offset:+.1f} um"
              if offset is not None
              else "depth targets at the rig's intrusion (no zero offset known: FEM fit off)")
    return LearnedReadout(result.path), f"{result.summary()} ({source}, nu {nu:.3g})"


def readout_gain(camera, shading, ref, noise, readout, d,
                 material: FemResult) -> tuple[float, str]:
    """The unit's depth gain of the learned read-out from the rig's presses
    (:mod:`tactile_deploy.calibration.shading.readout_gain`), and a line for the provenance."""
    tips = d["tip_mm"]
    use = d["keep"] & np.all(np.isfinite(tips), axis=1)
    what = f"{readout.path.name} (design {readout.metadata.get('design', '?')})"
    if not use.any():
        return 1.0, (f"{what}; depth gain not calibrated (1): no rig presses of known depth")
    offset = material.depth_offset_mm
    pipeline = ImagingPipeline(camera, shading, ref, noise, "subtract", readout=readout)
    gain, ratios = readout_depth_gain(pipeline, d["raw"][use], tips[use, 2], offset or 0.0)
    source = (f"the rig's zero offset {1e3 * offset:+.1f} um from the FEM step"
              if offset is not None else "no zero offset known (FEM fit off): taken as 0")
    return gain, (f"{what}; depth gain {gain:.4f} = median over {len(ratios)} rig presses of the "
                  f"intrusion over the read-out's deepest cell (p10-p90 {np.percentile(ratios, 10):.3f}"
                  f"-{np.percentile(ratios, 90):.3f}), {source}")
