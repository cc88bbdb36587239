"""Fit the read-out network to training crops (torch; CPU or a CUDA device).

    python -m tactile_deploy.training.shading_net.fitting --crops CROPS.npz --weights-out W.pt [--epochs 60]
        [--width 8] [--seed 5] [--batch 32] [--lr 2e-3] [--device cuda] [--init W0.pt]

needs only numpy and torch (no OpenCV or pydantic), so a crop file made by
``python -m tactile_deploy.training.shading_net --data-only`` can be trained on a GPU machine; the weights
(a torch state dict with the settings and per-epoch losses beside it) come back to
``python -m tactile_deploy.training.shading_net --weights W.pt``, which exports them with their card.

Loss: mean squared error of the depth gradients (mm per mm, clipped to +-``gradient_clip``) and
of the depth (in ``DEPTH_UNIT_MM``), the gradient channels weighted by ``gradient_weight``;
AdamW with a one-cycle learning rate.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np


def fit_network(crops, width: int, epochs: int, seed: int, batch: int = 32, lr: float = 2e-3,
                gradient_clip: float = 1.0, gradient_weight: float = 1.0, device: str = "cpu",
                init_state=None, log=print):
    """Train a :class:`~tactile_deploy.learning.readout_network.ReadoutNet` of base width
    ``width`` on :class:`~.crops.Crops`; returns (network on the CPU in eval mode, per-epoch
    mean losses). ``init_state``: a state dict to start from (default: random)."""
    import torch

    from tactile_deploy.learning.readout_network import ReadoutNet, targets

    torch.manual_seed(seed)
    net = ReadoutNet(width)
    if init_state is not None:
        net.load_state_dict(init_state)
    dev = torch.device(device)
    net.to(dev)
    x = torch.from_numpy(crops.features()).to(dev)
    y = torch.from_numpy(targets(crops.depth_mm, crops.pitch_mm, gradient_clip)).to(dev)
    opt = torch.optim.AdamW(net.parameters(), lr, weight_decay=1e-4)
    steps_per_epoch = max(len(x) // batch, 1)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, lr, total_steps=epochs * steps_per_epoch)
    weight = torch.tensor([gradient_weight, gradient_weight, 1.0], device=dev).view(1, 3, 1, 1)
    gen = torch.Generator().manual_seed(seed)
    losses = []
    t0 = time.perf_counter()
    net.train()
    for epoch in range(epochs):
        perm = torch.randperm(len(x), generator=gen).to(dev)
        total = torch.zeros((), device=dev)
        for i in range(steps_per_epoch):
            idx = perm[i * batch:(i + 1) * batch]
            loss = (((net(x[idx]) - y[idx]) ** 2) * weight).mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            total += loss.detach()
        losses.append(float(total) / steps_per_epoch)
        log(f"epoch {epoch + 1}/{epochs}: loss {losses[-1]:.3g} ({time.perf_counter() - t0:.0f} s)")
    return net.cpu().eval(), losses


def main(argv=None) -> int:
    import torch

    from .crops import load_crops

    ap = argparse.ArgumentParser(prog="python -m tactile_deploy.training.shading_net.fitting",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("--crops", type=Path, required=True, help="crop file (.npz)")
    ap.add_argument("--weights-out", type=Path, required=True, help="state dict to write (.pt)")
    ap.add_argument("--epochs", type=int, default=60)
    ap.add_argument("--width", type=int, default=8)
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--lr", type=float, default=2e-3)
    ap.add_argument("--gradient-clip", type=float, default=1.0)
    ap.add_argument("--gradient-weight", type=float, default=1.0)
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--init", type=Path, default=None,
                    help="start from these weights (a .pt written by this command, same --width)")
    args = ap.parse_args(argv)
    init_state, init_settings = None, None
    if args.init is not None:
        from tactile_deploy.safe_torch import load_torch_file

        saved = load_torch_file(args.init)
        init_state, init_settings = saved["state_dict"], saved["settings"]
        if int(init_settings["width"]) != args.width:
            raise SystemExit(f"--init {args.init} has width {init_settings['width']}, "
                             f"not --width {args.width}")
    t0 = time.perf_counter()
    crops = load_crops(args.crops)
    print(f"{len(crops)} crops of {crops.frames.shape[1]} x {crops.frames.shape[2]} cells "
          f"({time.perf_counter() - t0:.0f} s)", flush=True)
    net, losses = fit_network(crops, args.width, args.epochs, args.seed, args.batch, args.lr,
                              args.gradient_clip, args.gradient_weight, args.device,
                              init_state=init_state, log=lambda m: print(m, flush=True))
    settings = {k: getattr(args, k) for k in ("epochs", "width", "seed", "batch", "lr",
                                               "gradient_clip", "gradient_weight", "device")}
    settings["device_name"] = (torch.cuda.get_device_name() if args.device.startswith("cuda")
                               else "cpu")
    if init_settings is not None:   # the epochs the weights saw before, and how
        settings["init"] = {"weights": args.init.name, **init_settings}
    torch.save({"state_dict": net.state_dict(), "settings": settings, "losses": losses,
                "crops": str(args.crops.name), "seconds": time.perf_counter() - t0},
               args.weights_out)
    print(json.dumps({"weights": str(args.weights_out), "loss_last": losses[-1],
                      "seconds": round(time.perf_counter() - t0, 1)}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
