"""The self-supervised adaptation step (paper, "Self-Supervised Adaptation") as torch modules.

Data flow of :meth:`AdaptationStep.forward` (train mode; the module :mod:`tactile_deploy.training.adaptation.export`
captures with ``torch.export``)::

    depth (B, 1, 128, 128) mm   (a sensor's depth map I, model grid)
      -> / depth_scale_mm -> image encoder (mean)  z_I (B, 128)       trainable
      -> latent projection                          z_M (B, 128)       trainable
      -> mesh decoder (lean grid decoder) x scale, backplate 0         frozen
                                                    displacement (B, n, 3) mm, sensor frame
      -> DepthRenderer (sensing nodes)              rendered (B, 128, 128) mm, image rows
    loss = mean over the batch of sum_px w (rendered - target)^2 / sum_px w      (mm^2)

The target is the image VAE's reconstruction of the same depth map, ``VAE(I)``
(:class:`VAEFilter`, frozen: the paper's noise filter), or ``I`` itself (the ablation without
the filter); ``w`` (128, 128) weights the pixels the sensor sees. The label-free metric of the
paper is the square root of the same mean over a set of maps (an RMSE in mm).
"""

from __future__ import annotations

import copy

import torch
from torch import nn

from tactile_deploy.training.adaptation.render import DEFAULT_PIXELS_PER_TRIANGLE, DepthRenderer
from tactile_deploy.training.networks.predictor import Predictor

#: Parameter prefixes the step updates: image encoder (convolutions, FC, mean head) and projection.
TRAINABLE_PREFIXES = ("convs.", "fc.", "mu.", "projection.")
#: With the surface-anchored decoder: the image encoder and the decoder but its 1 x 1 head (whose
#: weights carry the folded displacement scale in the ONNX graph).
SURFACE_TRAINABLE_PREFIXES = ("convs.", "fc.", "mu.", "decoder.fc.", "decoder.skips.", "decoder.ups.", "decoder.convs.")


class AdaptationStep(nn.Module):
    """Image encoder + projection (trainable), mesh decoder (frozen), renderer, loss; or, for a
    model with the surface-anchored decoder, image encoder + surface decoder (trainable but its
    head), the anchor (fixed), renderer, loss.

    decoder : "lean" (the latent path's deployed decoder), "surface", or None (the model's
    deployed one: "surface" when it has the surface decoder).
    """

    def __init__(self, model: Predictor, decoder: str | None = None,
                 pixels_per_triangle: int = DEFAULT_PIXELS_PER_TRIANGLE, lateral: nn.Module | None = None):
        super().__init__()
        #: the hybrid graphs' lateral physics lift (fixed), or None; added to the decoder's lateral
        #: residual where the model was trained with it (``lateral_adds``), else replacing it
        self.lateral = lateral
        self.lateral_adds = model.lateral_adds
        decoder = decoder or ("surface" if hasattr(model, "surface_decoder") else "lean")
        if decoder not in ("lean", "surface"):
            raise ValueError(f"decoder must be 'lean' or 'surface' (a deployed mesh decoder), got {decoder!r}")
        self.kind = decoder
        enc = copy.deepcopy(model.image_vae.encoder)
        self.convs, self.fc, self.mu = enc.convs, enc.fc, enc.mu
        if decoder == "surface":
            self.decoder = copy.deepcopy(model.surface_decoder)
            self.anchor = copy.deepcopy(model.anchor)
            self.moved = model.cfg.surface.anchor == "moved"
            self.prefixes = SURFACE_TRAINABLE_PREFIXES
        else:
            self.projection = copy.deepcopy(model.projection)
            self.decoder = copy.deepcopy(model.lean_decoder)
            self.prefixes = TRAINABLE_PREFIXES
        for name, p in self.named_parameters():
            p.requires_grad_(name.startswith(self.prefixes))
        norm = model.norm
        self.register_buffer("depth_scale_mm", norm.depth_scale_mm.detach().clone())
        self.register_buffer("displacement_scale_mm",
                             (norm.displacement_scale_mm * norm.free_mask).detach().clone())  # (n, 3)
        self.n_plane = self.decoder.n_plane
        from tactile_deploy.pad.asset import load_pad

        pad = load_pad()
        if pad.n_plane != self.n_plane or list(pad.sensing_nodes) != list(range(pad.n_plane)):
            raise ValueError("the pad's sensing nodes must be its first n_plane nodes (layer 0)")
        self.renderer = DepthRenderer.for_pad(pad, pixels_per_triangle=pixels_per_triangle)

    def trainable_names(self) -> list[str]:
        return [n for n, _ in self.named_parameters() if n.startswith(self.prefixes)]

    def displacement(self, depth_mm: torch.Tensor) -> torch.Tensor:
        """depth (B, 1, R, R) mm -> displacement (B, n, 3) mm."""
        x = depth_mm / self.depth_scale_mm
        if self.kind == "lean":
            z = self.mu(self.fc(self.convs(x)))
            return self.decoder(self.projection(z)) * self.displacement_scale_mm
        from tactile_deploy.training.networks.surface_decoder import compose_surface

        maps = []
        for layer in self.convs:
            x = layer(x)
            if not isinstance(layer, nn.Conv2d):
                maps.append(x)
        z = self.mu(self.fc(x))
        d = self.decoder(maps, z) * self.displacement_scale_mm
        return compose_surface(d, depth_mm, self.anchor, self.moved, None, self.lateral, self.lateral_adds)

    def forward(self, depth_mm: torch.Tensor, target_mm: torch.Tensor, weight: torch.Tensor):
        """(loss () mm^2, per-map mse (B,) mm^2, rendered (B, R, R) mm, displacement (B, n, 3)
        mm, overflow (B,) int64) for depth (B, 1, R, R) mm, target (B, R, R) mm, weight (R, R)."""
        disp = self.displacement(depth_mm)
        rendered, overflow = self.renderer(disp[:, : self.n_plane])
        mse = ((rendered - target_mm) ** 2 * weight).sum(dim=(1, 2)) / weight.sum().clamp(min=1e-12)
        return mse.mean(), mse, rendered, disp, overflow


class VAEFilter(nn.Module):
    """depth (B, 1, R, R) mm -> the image VAE's reconstruction from its mean latent (B, R, R) mm.

    ``kind``: "vae" (the image VAE's own decoder, as in the paper) or "lean" (the small decoder
    of the same latent that the deployed ood_score uses)."""

    def __init__(self, model: Predictor, kind: str = "vae"):
        super().__init__()
        if kind not in ("vae", "lean"):
            raise ValueError(f"filter kind must be 'vae' or 'lean', got {kind!r}")
        self.encoder = copy.deepcopy(model.image_vae.encoder)
        self.decoder = copy.deepcopy(model.image_vae.decoder if kind == "vae" else model.ood_decoder)
        self.register_buffer("depth_scale_mm", model.norm.depth_scale_mm.detach().clone())

    def forward(self, depth_mm: torch.Tensor) -> torch.Tensor:
        z = self.encoder(depth_mm / self.depth_scale_mm)[0]
        return self.decoder(z)[:, 0] * self.depth_scale_mm
