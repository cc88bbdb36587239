"""Lean mesh decoder for deployment: latent -> in-plane feature grid (transposed convolutions)
-> one Gather of the pixel under each pad node.

Why: onnxruntime on a CPU runs dense convolutions and GEMMs well but per-node sparse products
badly (a Gather costs ~10 ns per row whatever its width, and per-row weighting is slower still),
so the fine levels of a Chebyshev decoder dominate its time. This decoder does all spatial work
on a regular in-plane grid and touches the mesh once: node ``layer * 1076 + i`` reads channel
``3 * layer + axis`` of the grid pixel holding in-plane point ``i``.

Grid: ``grid`` x ``grid`` pixels over the camera's field (+-half_extent_mm), pixel (r, c) centred
at ``x = -h + (c + 0.5) p``, ``y = -h + (r + 0.5) p`` (rows along +y; internal, not an image).
At 64 x 64 (0.55 mm) no two in-plane points of the pad share a pixel (checked at build time),
so the read-out is an exact assignment, not an interpolation. Channels: 3 per free node layer
(the backplate layer is bonded and outputs exactly 0).

Layers: FC (latent -> c0 x 4 x 4), ReLU, then stride-2 transposed convolutions (kernel 2) with
ReLU up to grid / 2, a 3 x 3 convolution at the middle resolution, and a last linear stride-2
transposed convolution to 3 * (n_layers - 1) channels at ``grid``.
Input: latent (B, d); output: normalised displacement (B, n, 3), node order of the pad mesh.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn

from tactile_deploy.training.config import GridDecoderConfig


def pixel_of_points(xy_mm: np.ndarray, grid: int, half_extent_mm: float) -> np.ndarray:
    """Flat pixel index (m,) int64 (row-major, rows along +y) of in-plane points (m, 2) mm."""
    pitch = 2.0 * half_extent_mm / grid
    col = np.clip(np.floor((xy_mm[:, 0] + half_extent_mm) / pitch), 0, grid - 1).astype(np.int64)
    row = np.clip(np.floor((xy_mm[:, 1] + half_extent_mm) / pitch), 0, grid - 1).astype(np.int64)
    return row * grid + col


class GridDecoder(nn.Module):
    def __init__(self, cfg: GridDecoderConfig, latent: int, plane_xy_mm: np.ndarray, n_layers: int):
        super().__init__()
        steps = int(round(math.log2(cfg.grid / 4)))
        if 4 * 2**steps != cfg.grid or steps != len(cfg.channels):
            raise ValueError(
                f"grid={cfg.grid} needs log2(grid / 4) = {math.log2(cfg.grid / 4):g} up-sampling steps, "
                f"channels {cfg.channels} give {len(cfg.channels)}"
            )
        pix = pixel_of_points(np.asarray(plane_xy_mm), cfg.grid, cfg.half_extent_mm)
        if len(np.unique(pix)) != len(pix):
            raise ValueError(
                f"grid={cfg.grid} puts several pad nodes in one pixel; use a finer grid (64 for the GelSlim pad)"
            )
        self.n_plane = len(pix)
        self.n_free_layers = n_layers - 1
        self.out_channels = 3 * self.n_free_layers
        self.c0 = cfg.channels[0]
        self.grid = cfg.grid
        self.fc = nn.Linear(latent, self.c0 * 16)
        layers: list[nn.Module] = []
        c = self.c0
        for i, w in enumerate(cfg.channels[1:]):
            layers += [nn.ConvTranspose2d(c, w, 2, stride=2), nn.ReLU()]
            c = w
            if i == len(cfg.channels) // 2 - 1:
                layers += [nn.Conv2d(c, c, 3, padding=1), nn.ReLU()]
        layers.append(nn.ConvTranspose2d(c, self.out_channels, 2, stride=2))
        self.net = nn.Sequential(*layers)
        self.register_buffer("pixel", torch.as_tensor(pix), persistent=False)

    def grid_features(self, z: torch.Tensor) -> torch.Tensor:
        """(B, d) -> (B, 3 * free layers, grid, grid)."""
        h = torch.relu(self.fc(z)).reshape(z.shape[0], self.c0, 4, 4)
        return self.net(h)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        b = z.shape[0]
        f = self.grid_features(z).reshape(b, self.out_channels, self.grid * self.grid)
        g = f[:, :, self.pixel]  # (B, 3 * free layers, n_plane)
        d = g.reshape(b, self.n_free_layers, 3, self.n_plane).transpose(2, 3)
        d = d.reshape(b, self.n_free_layers * self.n_plane, 3)
        return torch.cat([d, d.new_zeros(b, self.n_plane, 3)], dim=1)
