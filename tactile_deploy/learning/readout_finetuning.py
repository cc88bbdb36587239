"""Fine-tune a design's learned read-out on one unit's presses of known depth.

The read-out of a design (``python -m tactile_deploy.training.shading_net``) is trained on virtual units within
assembly tolerances; a built unit differs from all of them. The calibration wizard knows the depth of its own rig
presses (the ball's cap at the rig's intrusion plus its zero offset, the pad's FEM response
around it), so it can continue the design's network on them: the same network, loss and
targets as in training (depth and its gradients), full imaging-grid frames, Adam at a small
learning rate for a few hundred steps, then exported in the same format with the base's
contract and where it came from in the metadata.

Data flow: :func:`network_from_onnx` (the base's weights) -> :func:`finetune_network` ->
:func:`~tactile_deploy.learning.readout_network.export_onnx`. The calibration side (targets,
features, the plugin file) is ``tactile_deploy.calibration.shading.readout_finetune``.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import onnx
import torch
from onnx import numpy_helper

from tactile_deploy.learning.readout_network import ReadoutNet


def network_from_onnx(path: str | Path):
    """The :class:`tactile_deploy.learning.readout_network.ReadoutNet` of an exported read-out (``.onnx`` written by
    :func:`tactile_deploy.learning.readout_network.export_onnx`), weights loaded from its initializers."""
    model = onnx.load(str(path))
    state = {i.name.removeprefix("net."): torch.from_numpy(numpy_helper.to_array(i).copy())
             for i in model.graph.initializer if i.name.startswith("net.")}
    if "e1.0.weight" not in state:
        raise ValueError(f"{path}: not a read-out exported by tactile_deploy.training.shading_net (no "
                         f"initializer 'net.e1.0.weight')")
    net = ReadoutNet(int(state["e1.0.weight"].shape[0]))
    try:
        net.load_state_dict(state)
    except RuntimeError as e:
        raise ValueError(f"{path}: its weights do not fit the read-out network ({e})") from None
    return net


def finetune_network(net, features: np.ndarray, targets: np.ndarray, steps: int,
                     lr: float = 1e-4, batch: int = 8, seed: int = 0, log=None):
    """Continue ``net`` on frames ``features`` (N, 11, H, W) float32 with ``targets`` (N, 3, H,
    W) float32 (:func:`.train.targets`): Adam, ``steps`` steps of ``batch`` frames drawn at
    random, mean squared error over all cells; returns (net in eval mode, per-step losses)."""
    if len(features) != len(targets) or len(features) == 0:
        raise ValueError(f"need as many targets as frames and at least one frame, got "
                         f"{len(features)} frames and {len(targets)} targets")
    gen = torch.Generator().manual_seed(int(seed))
    x, y = torch.from_numpy(features), torch.from_numpy(targets)
    opt = torch.optim.Adam(net.parameters(), lr)
    net.train()
    losses = []
    t0 = time.perf_counter()
    for step in range(1, int(steps) + 1):
        idx = torch.randperm(len(x), generator=gen)[:batch]
        loss = ((net(x[idx]) - y[idx]) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.item()))
        if log is not None and (step % 100 == 0 or step == steps):
            log(step, steps, float(np.mean(losses[-100:])), time.perf_counter() - t0)
    return net.eval(), losses
