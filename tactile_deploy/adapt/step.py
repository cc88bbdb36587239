"""Run an exported adaptation step: the torch program (autograd and Adam here, in the runtime)
and the VAE filter (onnxruntime). No training code is imported; torch is needed (optional extra).

    step = StepProgram.load("exported/gelslim_mesh_adapt", device="cpu")
    target, _ = adaptation_target(step, depth)       # (N, 128, 128) mm: VAE(I) or I, by design
    history = adapt(step, depth, target, weight, AdaptSettings(steps=200))
    rmse = evaluate(step, held_depth, held_target, weight).rmse_mm

Shapes: depth (N, 128, 128) float32 mm on the model grid; weight (128, 128) float32 (pixels the
sensor sees); displacements (N, n, 3) mm, sensor frame.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from tactile_deploy.adapt.card import AdaptationCard, CardError, load_card
from tactile_deploy.adapt.weights import INSTALL_HINT, AdaptationUnavailable
from tactile_deploy.checksums import file_sha256
from tactile_deploy.onnx_runtime.session import make_session
from tactile_deploy.safe_torch import weights_only_loads


def require_torch():
    """torch, or :class:`AdaptationUnavailable` saying how to install it."""
    try:
        import torch
    except ImportError:
        raise AdaptationUnavailable(f"the adaptation step runs in torch, which is not installed; {INSTALL_HINT}") from None
    return torch


def _verified(card: AdaptationCard, folder: Path, key: str) -> Path:
    path = card.path(folder, key)
    if not path.is_file():
        raise CardError(f"{folder}: the card names {key} file {path}, which does not exist; restore it or "
                        "export the step again")
    actual = file_sha256(path)
    if actual != card.files[key].sha256:
        raise CardError(f"{path} does not match the card's {key}.sha256 ({card.files[key].sha256[:16]}..., file "
                        f"{actual[:16]}...); the file was replaced: export the step again")
    return path


class StepProgram:
    """The loaded step program, its trainable parameters, and its card."""

    def __init__(self, folder: Path, card: AdaptationCard, module, device):
        self.folder = Path(folder)
        self.card = card
        self.module = module
        self.device = device
        self._filter = None

    @classmethod
    def load(cls, folder: str | Path, device: str = "cpu") -> "StepProgram":
        torch = require_torch()
        folder = Path(folder)
        card = load_card(folder)
        path = _verified(card, folder, "step")
        dev = torch.device(device)
        if dev.type == "cuda" and not torch.cuda.is_available():
            raise AdaptationUnavailable("--device cuda was asked for, but this torch has no CUDA device; use "
                                        "--device cpu or install a CUDA build of torch")
        try:
            with weights_only_loads():       # no code from the file runs (docs/adaptation.md)
                program = torch.export.load(str(path))
        except Exception as e:  # torch raises several types for damaged or foreign files
            raise CardError(f"{path}: torch cannot load the step program ({type(e).__name__}: {e}); it was "
                            f"exported with torch {card.versions.get('torch')}, this is torch {torch.__version__}: "
                            "export the step again with this torch") from None
        if dev.type != "cpu":  # weights and the devices of tensors the graph creates (exported on the CPU)
            from torch.export.passes import move_to_device_pass

            program = move_to_device_pass(program, dev)
        module = program.module()
        params = dict(module.named_parameters())
        missing = [n for n in card.trainable if n not in params]
        if missing:
            raise CardError(f"{path}: parameters {missing[:3]} named trainable by the card are not in the program")
        for name, p in params.items():
            p.requires_grad_(name in card.trainable)
        return cls(folder, card, module, dev)

    def check_family_model(self, model_path: str | Path) -> None:
        """Refuse a family model other than the one the step was exported with."""

        actual = file_sha256(model_path)
        expected = self.card.files["family_model"].sha256
        if actual != expected:
            raise CardError(
                f"the adaptation step {self.folder} was exported for the family model with sha256 "
                f"{expected[:16]}..., but {model_path} has {actual[:16]}...; export the step for this model "
                "(python -m tactile_deploy.training export-adapt --bundle MODEL.pt --onnx MODEL.onnx)")

    def trainable(self) -> list:
        params = dict(self.module.named_parameters())
        return [params[n] for n in self.card.trainable]

    def weights(self) -> dict[str, np.ndarray]:
        """The trainable tensors now, name -> float32 array (CPU)."""
        params = dict(self.module.named_parameters())
        return {n: params[n].detach().cpu().numpy().astype(np.float32) for n in self.card.trainable}

    def load_weights(self, weights: dict[str, np.ndarray]) -> None:
        torch = require_torch()
        params = dict(self.module.named_parameters())
        with torch.no_grad():
            for n, arr in weights.items():
                params[n].copy_(torch.as_tensor(arr))

    def __call__(self, depth, target, weight):
        """Outputs of the program (loss, mse (B,), rendered, displacement, overflow) on numpy or
        torch inputs: depth (B, 128, 128) or (B, 1, 128, 128), target (B, 128, 128) mm."""
        torch = require_torch()
        d = torch.as_tensor(np.asarray(depth, np.float32) if isinstance(depth, np.ndarray) else depth)
        d = d.reshape(d.shape[0], 1, d.shape[-2], d.shape[-1]).to(self.device)
        t = torch.as_tensor(np.asarray(target, np.float32) if isinstance(target, np.ndarray) else target).to(self.device)
        w = torch.as_tensor(np.asarray(weight, np.float32) if isinstance(weight, np.ndarray) else weight).to(self.device)
        return self.module(d, t, w)

    # -- the filter ----------------------------------------------------------------------------
    def filter_session(self):
        if self._filter is None:
            path = _verified(self.card, self.folder, "filter")
            self._filter = make_session(path, threads=1, providers="cpu")
        return self._filter


def filters_by_default(step: StepProgram) -> bool:
    """Whether the design of the step's family model adapts towards VAE(I) by default (the paper's
    latent design) or towards the measured map I itself (the surface-anchored designs, variants
    ``hybrid*`` and ``surface*``: their sensing nodes sit on I, and towards VAE(I) they leave it;
    on 12 real GelSight ball presses the surface error against the ball went 138 -> 317 um towards
    VAE(I) and 138 -> 121 um towards I, docs/adaptation.md)."""
    return not step.card.family_variant.startswith(("hybrid", "surface"))


def adaptation_target(step: StepProgram, depth_mm: np.ndarray, use_filter: bool | None = None) -> tuple[np.ndarray, bool]:
    """The adaptation target (N, 128, 128) mm of depth maps (N, 128, 128) mm and whether it is the
    filter's VAE(I) (else I itself); ``use_filter`` None: the design's default (:func:`filters_by_default`)."""
    use_filter = filters_by_default(step) if use_filter is None else bool(use_filter)
    return (vae_filter(step, depth_mm) if use_filter else np.array(depth_mm, np.float32)), use_filter


def vae_filter(step: StepProgram, depth_mm: np.ndarray, batch: int = 32) -> np.ndarray:
    """The image VAE's reconstruction VAE(I) (N, 128, 128) mm of depth maps (N, 128, 128) mm."""
    session = step.filter_session()
    d = np.asarray(depth_mm, np.float32).reshape(-1, 1, depth_mm.shape[-2], depth_mm.shape[-1])
    out = [session.run(None, {"depth": d[i : i + batch]})[0] for i in range(0, len(d), batch)]
    return np.concatenate(out).astype(np.float32)


@dataclass(frozen=True)
class AdaptSettings:
    """steps: Adam steps; batch_size: maps per step; lr: Adam learning rate; seed: batch order."""

    steps: int = 200
    batch_size: int = 16
    lr: float = 1e-4
    seed: int = 0


@dataclass
class Evaluation:
    """Label-free figures of a set of maps: rmse_mm = sqrt(mean over maps of the weighted pixel
    MSE between the rendered mesh and the target); per-map mse (N,) mm^2; displacement (N, n, 3)
    mm (when asked); overflow: triangles beyond the renderer's pixel budget, summed."""

    rmse_mm: float
    mse_mm2: np.ndarray
    displacement_mm: np.ndarray | None = None
    rendered_mm: np.ndarray | None = None
    overflow: int = 0


def evaluate(step: StepProgram, depth_mm, target_mm, weight, batch: int = 32,
             keep: tuple[str, ...] = ()) -> Evaluation:
    """Run the program without gradients over all maps (``keep``: "displacement", "rendered")."""
    torch = require_torch()
    mses, disps, rends, overflow = [], [], [], 0
    with torch.no_grad():
        for i in range(0, len(depth_mm), batch):
            _, mse, rendered, disp, ov = step(depth_mm[i : i + batch], target_mm[i : i + batch], weight)
            mses.append(mse.cpu().numpy())
            overflow += int(ov.sum())
            if "displacement" in keep:
                disps.append(disp.cpu().numpy())
            if "rendered" in keep:
                rends.append(rendered.cpu().numpy())
    mse = np.concatenate(mses).astype(np.float64)
    return Evaluation(float(math.sqrt(mse.mean())), mse, np.concatenate(disps) if disps else None,
                      np.concatenate(rends) if rends else None, overflow)


@dataclass
class History:
    """loss_mm2 per step, seconds per step, total seconds."""

    loss_mm2: list[float] = field(default_factory=list)
    step_seconds: list[float] = field(default_factory=list)

    @property
    def seconds(self) -> float:
        return float(sum(self.step_seconds))


def adapt(step: StepProgram, depth_mm: np.ndarray, target_mm: np.ndarray, weight: np.ndarray,
          settings: AdaptSettings, progress: Callable[[int, float], None] | None = None) -> History:
    """``settings.steps`` Adam steps on the trainable parameters, batches drawn without
    replacement (a new permutation every pass); ``progress(step, loss_mm2)`` after each."""
    torch = require_torch()
    if len(depth_mm) == 0:
        raise ValueError("no depth maps to adapt on")
    params = step.trainable()
    opt = torch.optim.Adam(params, lr=settings.lr)
    rng = np.random.default_rng(settings.seed)
    d_all = torch.as_tensor(np.asarray(depth_mm, np.float32))
    t_all = torch.as_tensor(np.asarray(target_mm, np.float32))
    w = torch.as_tensor(np.asarray(weight, np.float32)).to(step.device)
    order: list[int] = []
    history = History()
    for k in range(settings.steps):
        t0 = time.perf_counter()
        if len(order) < min(settings.batch_size, len(d_all)):
            order += list(rng.permutation(len(d_all)))
        idx = order[: settings.batch_size]
        del order[: settings.batch_size]
        loss = step(d_all[idx], t_all[idx], w)[0]
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        value = float(loss.detach())
        history.loss_mm2.append(value)
        history.step_seconds.append(time.perf_counter() - t0)
        if progress is not None:
            progress(k + 1, value)
    return history
