"""Image beta-VAE of depth maps (the paper's green branch).

Encoder: five stride-2 convolutions (32, 64, 128, 256, 512 channels; 128 -> 4 pixels), a fully
connected layer of 128 and the latent heads (mean and log-variance, 128 each). The decoder mirrors
it (FC 128, FC to 512 x 4 x 4, five stride-2 transposed convolutions back to 1 x 128 x 128).
Loss: ``MSE(I, I^) + lambda_I KL(q(z|I) || N(0, 1))`` (see :func:`vae_loss` for the reductions).

Inputs are depth maps normalised by ``depth_scale_mm`` (done by the caller, see
:mod:`tactile_deploy.training.networks.predictor`), image layout (B, 1, H, W), row 0 = largest y.
"""

from __future__ import annotations

import torch
from torch import nn

from tactile_deploy.training.config import ImageVAEConfig, LeanImageDecoderConfig

_ACT = {"elu": nn.ELU, "relu": nn.ReLU}


def conv_padding(kernel: int) -> tuple[int, int]:
    """(padding, output_padding) making a stride-2 conv halve and its transpose double the size."""
    p = (kernel - 1) // 2
    return p, 2 - kernel + 2 * p


class ImageEncoder(nn.Module):
    """(B, 1, R, R) normalised depth -> (mu, logvar), each (B, latent)."""

    def __init__(self, cfg: ImageVAEConfig):
        super().__init__()
        act = _ACT[cfg.activation]
        pad, _ = conv_padding(cfg.kernel)
        layers: list[nn.Module] = []
        c = 1
        for w in cfg.widths:
            layers += [nn.Conv2d(c, w, cfg.kernel, stride=2, padding=pad), act()]
            c = w
        self.convs = nn.Sequential(*layers)
        side = cfg.resolution // 2 ** len(cfg.widths)
        self.flat_features = c * side * side
        self.fc = nn.Sequential(nn.Flatten(), nn.Linear(self.flat_features, cfg.hidden), act())
        self.mu = nn.Linear(cfg.hidden, cfg.latent)
        self.logvar = nn.Linear(cfg.hidden, cfg.latent)

    def features(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc(self.convs(x))

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        h = self.features(x)
        return self.mu(h), self.logvar(h)


class ImageDecoder(nn.Module):
    """(B, latent) -> (B, 1, R, R) normalised depth (linear output)."""

    def __init__(self, cfg: ImageVAEConfig):
        super().__init__()
        act = _ACT[cfg.activation]
        pad, out_pad = conv_padding(cfg.kernel)
        self.side = cfg.resolution // 2 ** len(cfg.widths)
        self.top = cfg.widths[-1]
        self.fc = nn.Sequential(
            nn.Linear(cfg.latent, cfg.hidden), act(),
            nn.Linear(cfg.hidden, self.top * self.side * self.side), act(),
        )
        widths = list(cfg.widths[::-1]) + [1]
        layers: list[nn.Module] = []
        for i, (a, b) in enumerate(zip(widths[:-1], widths[1:])):
            layers.append(nn.ConvTranspose2d(a, b, cfg.kernel, stride=2, padding=pad, output_padding=out_pad))
            if i < len(widths) - 2:
                layers.append(act())
        self.deconvs = nn.Sequential(*layers)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        h = self.fc(z).reshape(-1, self.top, self.side, self.side)
        return self.deconvs(h)


class LeanImageDecoder(nn.Module):
    """A small decoder of the image VAE's latent, for the deployed ``ood_score``.

    (B, latent) -> (B, 1, R, R) normalised depth: FC to channels[0] x 4 x 4, ReLU, stride-2
    kernel-2 transposed convolutions with ReLU, a linear last one to 1 channel. Trained on the
    frozen image encoder (same latent space), it reconstructs at a fraction of the symmetric
    decoder's cost; its reconstruction error is the deployed out-of-distribution score.
    """

    def __init__(self, cfg: LeanImageDecoderConfig, latent: int, resolution: int):
        super().__init__()
        steps = len(cfg.channels)
        if 4 * 2**steps != resolution:
            raise ValueError(
                f"{steps} up-sampling steps from 4 x 4 give {4 * 2**steps}, not resolution {resolution}"
            )
        self.c0 = cfg.channels[0]
        self.fc = nn.Sequential(nn.Linear(latent, self.c0 * 16), nn.ReLU())
        layers: list[nn.Module] = []
        widths = list(cfg.channels) + [1]
        for i, (a, b) in enumerate(zip(widths[:-1], widths[1:])):
            layers.append(nn.ConvTranspose2d(a, b, 2, stride=2))
            if i < len(widths) - 2:
                layers.append(nn.ReLU())
        self.deconvs = nn.Sequential(*layers)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        return self.deconvs(self.fc(z).reshape(-1, self.c0, 4, 4))


class ImageVAE(nn.Module):
    def __init__(self, cfg: ImageVAEConfig):
        super().__init__()
        self.cfg = cfg
        self.encoder = ImageEncoder(cfg)
        self.decoder = ImageDecoder(cfg)

    def forward(self, x: torch.Tensor, sample: bool = True):
        mu, logvar = self.encoder(x)
        z = reparameterise(mu, logvar) if sample else mu
        return self.decoder(z), mu, logvar


def reparameterise(mu: torch.Tensor, logvar: torch.Tensor) -> torch.Tensor:
    return mu + torch.randn_like(mu) * torch.exp(0.5 * logvar)


def kl_divergence(mu: torch.Tensor, logvar: torch.Tensor) -> torch.Tensor:
    """KL(N(mu, exp(logvar)) || N(0, 1)), summed over latent dims, mean over the batch."""
    return (-0.5 * (1.0 + logvar - mu.pow(2) - logvar.exp()).sum(dim=-1)).mean()


def vae_loss(target, recon, mu, logvar, kl_weight: float) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """``MSE (mean over all elements) + kl_weight * KL (sum over latent dims, batch mean)``.

    Returns the loss and its terms as detached 0-d tensors (read once per epoch: no device sync per step).
    """
    mse = torch.mean((recon - target) ** 2)
    kl = kl_divergence(mu, logvar)
    loss = mse + kl_weight * kl
    return loss, {"loss": loss.detach(), "mse": mse.detach(), "kl": kl.detach()}
