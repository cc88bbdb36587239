"""A design's learned read-out fine-tuned on one unit's ball presses: the plugin's own read-out.

The design's read-out (:mod:`tactile_deploy.imaging.learned_readout`) was trained on virtual
units within assembly tolerances; on a built unit its depth is a few per cent off in scale and
its ball caps come out too flat (docs/shading.md). The calibration knows the depth of the
unit's own presses: each rig press is the ball at the rig's position (sensor frame) pushed in by
the rig's intrusion plus its zero offset (the FEM step fits it), and the pad's FEM gives the
surface around the cap (:class:`~tactile_deploy.calibration.shading.press_profile.PressProfile`). Those depth
maps, and the no-contact frames with zero depth, continue the design's network
(:mod:`tactile_deploy.learning.readout_finetuning`; needs torch and onnx, the ``train``
extra).

Data flow: profiles -> :meth:`PressProfile.depth_map` on the imaging grid (targets) ->
read-out features of the raw frames (:meth:`ImagingPipeline.readout_features`) ->
:func:`tactile_deploy.learning.readout_finetuning.finetune_network` -> an ONNX file in the
read-out format, the base's contract and this fine-tuning in its metadata.
"""

from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: Adam steps and learning rate of the fine-tuning (24 presses: docs/shading.md).
DEFAULT_STEPS = 800
DEFAULT_LR = 1e-4


class FinetuneUnavailable(RuntimeError):
    """torch or onnx, which the fine-tuning needs, is not installed."""


@dataclass
class FinetuneResult:
    """What the fine-tuning did. path : the written ONNX file; presses, no_contact : frames of
    each kind it trained on; steps; loss_first, loss_last : mean loss of the first and last 100
    steps; seconds : wall time."""

    path: Path
    presses: int
    no_contact: int
    steps: int
    loss_first: float
    loss_last: float
    seconds: float

    def summary(self) -> str:
        return (f"fine-tuned on this unit's {self.presses} ball presses and {self.no_contact} "
                f"no-contact frames: {self.steps} Adam steps, loss {self.loss_first:.3g} -> "
                f"{self.loss_last:.3g}, {self.seconds:.0f} s")


def finetune_unit_readout(pipeline, press_frames, press_depths_mm, no_contact_frames, out: Path,
                          unit: str, steps: int = DEFAULT_STEPS, lr: float = DEFAULT_LR,
                          seed: int = 0, log=None) -> FinetuneResult:
    """Fine-tune the read-out of ``pipeline`` on one unit and write it to ``out`` (atomically).

    pipeline : an :class:`~tactile_deploy.runtime.pipeline.ImagingPipeline` of the unit with
        the design's read-out (its features are the network's input).
    press_frames : (N, H, W, 3) uint8 raw camera frames of presses of known depth.
    press_depths_mm : (N, ny, nx) float32, their depth on the imaging grid, mm, positive into
        the gel (e.g. :meth:`PressProfile.depth_map`).
    no_contact_frames : (M, H, W, 3) uint8 raw frames without contact (depth 0).
    unit : the unit's name, recorded in the metadata. log : ``(step, steps, loss, seconds)``
        callback every 100 steps.
    """
    try:
        import onnx  # noqa: F401  (the network is read from and written to ONNX)
        import torch  # noqa: F401

        from tactile_deploy.learning.readout_finetuning import finetune_network, network_from_onnx
        from tactile_deploy.learning.readout_network import export_onnx, targets
    except ImportError as e:
        raise FinetuneUnavailable(
            f"fine-tuning the learned read-out needs torch and onnx ({e}): install them with "
            "pip install 'tactile-deploy[train]', or set the wizard config's readout_steps to 0 "
            "to use the design's read-out with a depth gain") from None

    readout = pipeline.readout
    if readout is None:
        raise ValueError("the pipeline has no learned read-out to fine-tune")
    grid = pipeline.camera.grid
    depths = np.asarray(press_depths_mm, np.float32)
    if len(press_frames) != len(depths) or len(depths) == 0:
        raise ValueError(f"need one depth map per press frame and at least one press, got "
                         f"{len(depths)} depth maps for {len(press_frames)} frames")
    if depths.shape[1:] != (grid.ny, grid.nx):
        raise ValueError(f"press depth maps must be ({grid.ny}, {grid.nx}) (the imaging grid), "
                         f"got {depths.shape[1:]}")
    t0 = time.perf_counter()
    frames = list(press_frames) + list(no_contact_frames)
    features = np.stack([pipeline.readout_features(f) for f in frames])
    depth_all = np.concatenate([depths, np.zeros((len(no_contact_frames), grid.ny, grid.nx),
                                                 np.float32)])
    net = network_from_onnx(readout.path)
    net, losses = finetune_network(net, features, targets(depth_all, grid.pitch_x_mm), steps,
                                   lr=lr, seed=seed, log=log)
    metadata = dict(readout.metadata)
    metadata.update({
        "finetuned_on": unit,
        "finetune": f"{len(depths)} ball presses and {len(no_contact_frames)} no-contact frames, "
                    f"{steps} Adam steps at lr {lr:g}",
        "base_sha256": hashlib.sha256(Path(readout.path).read_bytes()).hexdigest(),
    })
    export_onnx(net, Path(out), metadata)
    first = float(np.mean(losses[:100])) if losses else float("nan")
    last = float(np.mean(losses[-100:])) if losses else float("nan")
    return FinetuneResult(Path(out), len(depths), len(no_contact_frames), int(steps), first, last,
                          time.perf_counter() - t0)
