"""Volumetric mesh VAE after COMA (Ranjan et al. 2018), on the layered tet graph of the pad.

Encoder (levels 0 -> 4 of :class:`~tactile_deploy.training.networks.coarsening.Hierarchy`): at level l a
Chebyshev convolution (order ``cheb_k[l]``) to ``channels[l]`` features, ReLU, down-sampling to
level l + 1; then fully connected heads to the latent mean and log-variance (128 each).
Decoder (mirror): FC from the latent to level 4 x channels[-1] (no activation, like COMA), then
for l = 3 .. 0: up-sampling to level l, Chebyshev convolution to ``channels[l - 1]`` (3 at
level 0), activation except after the last.

Features 16, 16, 16, 32 with K = 6 and 4x down-sampling per level are the paper's sizes.
The VAE works on **normalised displacements** (displacement / per-axis scale, see
:mod:`tactile_deploy.training.networks.predictor`), node-major ``(n, B, 3)`` inside, ``(B, n, 3)`` outside.
"""

from __future__ import annotations

import torch
from torch import nn

from tactile_deploy.training.config import MeshVAEConfig
from tactile_deploy.training.networks.coarsening import Hierarchy
from tactile_deploy.training.networks.graph import ChebConv, SparseMap


class MeshGraphs(nn.Module):
    """The hierarchy's fixed operators as modules (shared by encoder and decoder)."""

    def __init__(self, hierarchy: Hierarchy):
        super().__init__()
        self.hierarchy = hierarchy
        self.laplacians = nn.ModuleList([SparseMap(lv.chebyshev_operator) for lv in hierarchy.levels])
        self.up = nn.ModuleList([SparseMap(t) for t in hierarchy.up])
        self.down = nn.ModuleList([SparseMap(t) for t in hierarchy.down])

    def set_use_tables(self, flag: bool) -> None:
        for m in self.modules():
            if isinstance(m, SparseMap):
                m.use_tables = flag


class MeshEncoder(nn.Module):
    """(B, n0, 3) normalised displacement -> (mu, logvar), each (B, latent)."""

    def __init__(self, cfg: MeshVAEConfig, graphs: MeshGraphs):
        super().__init__()
        self.graphs = graphs
        c = [3] + list(cfg.channels)
        self.convs = nn.ModuleList(
            [ChebConv(c[l], c[l + 1], cfg.cheb_k[l], graphs.laplacians[l]) for l in range(len(cfg.channels))]
        )
        n_last = graphs.hierarchy.levels[len(cfg.channels)].n_nodes
        self.flat = n_last * cfg.channels[-1]
        self.mu = nn.Linear(self.flat, cfg.latent)
        self.logvar = nn.Linear(self.flat, cfg.latent)
        self.act = nn.ReLU() if cfg.activation == "relu" else nn.ELU()

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        h = x.transpose(0, 1)  # (n, B, 3)
        for l, conv in enumerate(self.convs):
            h = self.graphs.down[l](self.act(conv(h)))
        h = h.transpose(0, 1).reshape(x.shape[0], self.flat)
        return self.mu(h), self.logvar(h)


class MeshDecoder(nn.Module):
    """(B, latent) -> (B, n0, 3) normalised displacement."""

    def __init__(self, cfg: MeshVAEConfig, graphs: MeshGraphs):
        super().__init__()
        self.graphs = graphs
        self.n_levels = len(cfg.channels)
        self.n_last = graphs.hierarchy.levels[self.n_levels].n_nodes
        self.c_last = cfg.channels[-1]
        self.fc = nn.Linear(cfg.latent, self.n_last * self.c_last)
        outs = [3] + list(cfg.channels[:-1])  # conv at level l outputs outs[l]
        ins = list(cfg.channels)  # conv at level l takes the features up-sampled from l + 1
        self.convs = nn.ModuleList(
            [ChebConv(ins[l], outs[l], cfg.cheb_k[l], graphs.laplacians[l]) for l in range(self.n_levels)]
        )  # indexed by level
        self.act = nn.ReLU() if cfg.activation == "relu" else nn.ELU()

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        h = self.fc(z).reshape(z.shape[0], self.n_last, self.c_last).transpose(0, 1)
        for l in reversed(range(self.n_levels)):
            h = self.convs[l](self.graphs.up[l](h))
            if l > 0:
                h = self.act(h)
        return h.transpose(0, 1)


class MeshVAE(nn.Module):
    def __init__(self, cfg: MeshVAEConfig, hierarchy: Hierarchy):
        super().__init__()
        if len(cfg.channels) != len(hierarchy.up):
            raise ValueError(
                f"{len(cfg.channels)} channel sizes need {len(cfg.channels)} coarsening levels, "
                f"the hierarchy has {len(hierarchy.up)}"
            )
        self.cfg = cfg
        self.graphs = MeshGraphs(hierarchy)
        self.encoder = MeshEncoder(cfg, self.graphs)
        self.decoder = MeshDecoder(cfg, self.graphs)

    def forward(self, x: torch.Tensor, sample: bool = True):
        from tactile_deploy.training.networks.image_vae import reparameterise

        mu, logvar = self.encoder(x)
        z = reparameterise(mu, logvar) if sample else mu
        return self.decoder(z), mu, logvar
