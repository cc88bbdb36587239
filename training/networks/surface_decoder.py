"""Surface-anchored mesh decoder: the sensing nodes sit on the measured surface, a convolutional
network adds what the depth map alone does not say.

Why: a decoder that rebuilds the whole pad from a 128-number latent cannot carry a contact patch
(the deepest node comes out 10-15 % too shallow, the patch 100-200 um off), while the depth map
itself already holds the sensing surface's vertical displacement where the contact is. So the
measured surface is an **anchor** in the graph, and the learned part is a residual:

    depth (B, 1, R, R) mm
      -> anchor       u_z of every sensing node = -bilinear(depth) at its rest (x, y)    fixed
                      (the physics lift's first step; one Gather of 4 pixels per node)
      -> encoder      the image encoder's stride-2 feature maps at R/2, R/4, ..., 4 and its latent
      -> decoder      4 x 4: 1 x 1 projection of the encoder's 4 x 4 map (+ FC of the latent);
                      then per level up to the last feature grid F: stride-2 transposed
                      convolution + 1 x 1 projection of the encoder map of that size (skip), ReLU,
                      optional 3 x 3 convolution; a per-pixel head to 3 x (free layers) values for
                      each of the (S / F)^2 sub-pixels of the output grid S = R / 2
      -> residual     read at the output-grid pixel of each in-plane point (one Gather of rows: at
                      64 x 64 no two pad points share a pixel; a pixel of F holds (S / F)^2 of them)
    displacement = residual x scale, + anchor on the sensing layer's z, backplate 0    (B, n, 3) mm

The residual learns what the anchor cannot: lateral motion of the surface (frictionless Poisson
flow, stick and slip), the interior layers, large-strain corrections, the depth map's noise
(denoising the anchor), the rasterisation of the depth map (a node's depth between pixel centres).
Being convolutional with skips at every scale, it is local where contact mechanics is local and
sees the whole map through its coarse levels, so new shapes are made of patterns it has seen.

Grids: image layout (row 0 = largest y, as the depth map); pixel (r, c) of a grid of side G is
centred at ``x = -h + (c + 0.5) p``, ``y = h - (r + 0.5) p`` with ``p = 2h / G``. Units: anchor in
mm; the residual in units of the displacement scale, as every decoder of
:mod:`tactile_deploy.training.networks.predictor`.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn

from tactile_deploy.training.config import SurfaceDecoderConfig


def bilinear_taps(xy_mm: np.ndarray, resolution: int, half_extent_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Flat pixel indices (m, 4) int64 and weights (m, 4) float32 of the bilinear sample of an
    image (row 0 = largest y, pixel centres as the depth camera) at points (m, 2) mm; edges
    clamped (scipy's ``map_coordinates(order=1, mode="nearest")``, as
    :func:`tactile_deploy.fem.surface_to_volume.sample_depth_at`)."""
    p = 2.0 * half_extent_mm / resolution
    col = (xy_mm[:, 0] + half_extent_mm) / p - 0.5
    row = (half_extent_mm - xy_mm[:, 1]) / p - 0.5
    r0, c0 = np.floor(row), np.floor(col)
    fr, fc = row - r0, col - c0
    idx, wts = [], []
    for dr, wr in ((0, 1 - fr), (1, fr)):
        for dc, wc in ((0, 1 - fc), (1, fc)):
            r = np.clip(r0 + dr, 0, resolution - 1).astype(np.int64)
            c = np.clip(c0 + dc, 0, resolution - 1).astype(np.int64)
            idx.append(r * resolution + c)
            wts.append(wr * wc)
    return np.stack(idx, 1), np.stack(wts, 1).astype(np.float32)


def grid_pixels(xy_mm: np.ndarray, grid: int, half_extent_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Row (m,) and column (m,) int64 of the image-layout grid pixel holding each point (m, 2) mm."""
    p = 2.0 * half_extent_mm / grid
    c = np.clip(np.floor((xy_mm[:, 0] + half_extent_mm) / p), 0, grid - 1).astype(np.int64)
    r = np.clip(np.floor((half_extent_mm - xy_mm[:, 1]) / p), 0, grid - 1).astype(np.int64)
    return r, c


def compose_surface(residual: torch.Tensor, depth_mm: torch.Tensor, anchor: "SurfaceAnchor", moved: bool,
                    scale_mm: torch.Tensor | None = None, lateral: nn.Module | None = None,
                    lateral_adds: bool = False) -> torch.Tensor:
    """The surface-anchored displacement (B, n, 3) from the decoder's residual (B, n, 3): the anchor
    (u_z of the sensing nodes read off ``depth_mm`` (B, 1, R, R) mm, where the residual moved them
    if ``moved``) on the sensing layer's z; with ``lateral`` (the physics lift u_z (B, m) mm ->
    x, y (B, m, 2) mm) the sensing layer's x, y replaced by the lift's, or added to it
    (``lateral_adds``). ``scale_mm`` (3,): the residual and the result are in units of the
    displacement scale (training); None: both in mm (the exported graphs). The one composition of
    the model, its training step, its exported graph and its adaptation step."""
    m = anchor.m
    top, rest = residual[:, :m], residual[:, m:]  # the sensing layer (B, m, 3); the layers below
    if scale_mm is None:  # mm throughout (the exported graphs: no unit conversions in them)
        uz = anchor.read(depth_mm, top, moved)
        z = top[..., 2] + uz
        lift_xy = lateral(z) if lateral is not None else None
    else:
        uz = anchor.read(depth_mm, top * scale_mm, moved)
        z = top[..., 2] + uz / scale_mm[2]
        lift_xy = lateral(z * scale_mm[2]) / scale_mm[:2] if lateral is not None else None
    xy = top[..., :2]
    if lift_xy is not None:
        xy = xy + lift_xy if lateral_adds else lift_xy
    # the sensing layer is built once and joined to the rest by one concatenation
    return torch.cat([torch.cat([xy, z[..., None]], dim=2), rest], dim=1)


class SurfaceAnchor(nn.Module):
    """depth (B, 1, R, R) mm -> u_z (B, m) mm of the sensing nodes: minus the bilinear sample of
    the depth map at each node's rest (x, y). Fixed (buffers only).

    Computed as one Gather of the flattened map: the 4 taps of a node are pixels ``k``, ``k + 1``,
    ``k + R`` and ``k + R + 1`` of its base pixel ``k = r0 * R + c0``, with the base moved in by one
    (fraction 1) at the last row or column, so that edges clamp as in :func:`bilinear_taps` and no
    tap lies past the map."""

    def __init__(self, sensing_xy_mm: np.ndarray, resolution: int, half_extent_mm: float):
        super().__init__()
        xy = np.asarray(sensing_xy_mm, np.float64)
        p = 2.0 * half_extent_mm / resolution
        col = np.clip((xy[:, 0] + half_extent_mm) / p - 0.5, 0.0, resolution - 1.0)
        row = np.clip((half_extent_mm - xy[:, 1]) / p - 0.5, 0.0, resolution - 1.0)
        r0 = np.minimum(np.floor(row), resolution - 2)
        c0 = np.minimum(np.floor(col), resolution - 2)
        fr, fc = row - r0, col - c0
        w = np.stack([(1 - fr) * (1 - fc), (1 - fr) * fc, fr * (1 - fc), fr * fc], 1).astype(np.float32)
        self.m = len(xy)
        self.resolution = int(resolution)
        self.pitch_mm = p
        base = torch.as_tensor((r0 * resolution + c0).astype(np.int64))
        #: flat pixel offsets of the 4 taps from the base pixel: itself, right, below, below-right
        self.register_buffer("tap_offsets", torch.as_tensor([0, 1, resolution, resolution + 1]), persistent=False)
        #: (m * 4,) flat pixels of every node's 4 taps, node-major
        self.register_buffer("taps", (base[:, None] + self.tap_offsets).reshape(-1), persistent=False)
        self.register_buffer("weights", torch.as_tensor(w), persistent=False)
        # continuous pixel coordinates of the rest positions (unclamped), for reads where nodes moved
        self.register_buffer("col_rest", torch.as_tensor((xy[:, 0] + half_extent_mm) / p - 0.5, dtype=torch.float32),
                             persistent=False)
        self.register_buffer("row_rest", torch.as_tensor((half_extent_mm - xy[:, 1]) / p - 0.5, dtype=torch.float32),
                             persistent=False)

    def forward(self, depth_mm: torch.Tensor) -> torch.Tensor:
        r = self.resolution
        v = torch.index_select(depth_mm.reshape(depth_mm.shape[0], r * r), 1, self.taps)  # (B, m * 4)
        return -(v.reshape(-1, self.m, 4) * self.weights).sum(-1)

    def moved(self, depth_mm: torch.Tensor, dxy_mm: torch.Tensor) -> torch.Tensor:
        """u_z (B, m) mm: minus the bilinear read at rest (x, y) + ``dxy_mm`` (B, m, 2), edges
        clamped; differentiable in ``dxy_mm`` (through the interpolation weights).

        One ``grid_sample`` (ONNX GridSample): pixel centres at -1 and +1 (``align_corners``), so
        a continuous pixel coordinate c maps to 2 c / (R - 1) - 1, and ``border`` padding clamps
        the read to the image as :func:`bilinear_taps` does. The same read as four gathered taps
        and their weights, in one kernel instead of ~40 small operators: in the exported graph at
        batch 1 that was an eighth of onnxruntime's summed operator time (docs/predictor.md)."""
        r = self.resolution
        col = self.col_rest + dxy_mm[..., 0] / self.pitch_mm
        row = self.row_rest - dxy_mm[..., 1] / self.pitch_mm
        grid = torch.stack([col, row], -1) * (2.0 / (r - 1)) - 1.0  # (B, m, 2): x (columns), y (rows)
        v = nn.functional.grid_sample(depth_mm, grid[:, :, None, :], mode="bilinear", padding_mode="border",
                                      align_corners=True)  # (B, 1, m, 1)
        return -v[:, 0, :, 0]

    def read(self, depth_mm: torch.Tensor, residual_mm: torch.Tensor, moved: bool) -> torch.Tensor:
        """The anchor of a decoder whose residual displacement is ``residual_mm`` (B, n, 3) mm."""
        return self.moved(depth_mm, residual_mm[:, : self.m, :2]) if moved else self(depth_mm)


class SurfaceDecoder(nn.Module):
    """Encoder feature maps + latent -> residual displacement (B, n, 3), normalised (backplate 0).

    enc_widths : channels of the image encoder's stride-2 maps (R/2, R/4, ..., 4).
    plane_xy_mm : (m, 2) in-plane points of the pad (node = layer * m + i).
    """

    def __init__(self, cfg: SurfaceDecoderConfig, enc_widths: tuple[int, ...], latent: int, resolution: int,
                 plane_xy_mm: np.ndarray, n_layers: int):
        super().__init__()
        n_enc = len(enc_widths)  # encoder maps at R/2 ... R/2**n_enc
        if resolution // 2**n_enc != 4:
            raise ValueError(f"the surface decoder starts at 4 x 4; the encoder ends at "
                             f"{resolution // 2**n_enc} x {resolution // 2**n_enc}")
        if not 1 <= len(cfg.channels) <= n_enc:
            raise ValueError(f"surface decoder channels {cfg.channels}: give 1 to {n_enc} levels (4 x 4 up to "
                             f"{resolution // 2} x {resolution // 2})")
        self.feature_side = 4 * 2 ** (len(cfg.channels) - 1)
        self.out_side = resolution // 2
        self.sub = self.out_side // self.feature_side  # sub-pixels per feature pixel, per axis
        self.n_plane = len(plane_xy_mm)
        self.n_free_layers = n_layers - 1
        self.out_channels = 3 * self.n_free_layers
        r, c = grid_pixels(np.asarray(plane_xy_mm, np.float64), self.out_side, cfg.half_extent_mm)
        if len(np.unique(r * self.out_side + c)) != len(r):
            raise ValueError(f"a {self.out_side} x {self.out_side} grid puts several pad nodes in one pixel; the "
                             "surface decoder needs a finer depth map (128 x 128 for the GelSlim pad)")
        # head channel (sub-pixel s = (r % sub) * sub + c % sub) * out_channels + k, at feature pixel (r // sub, c // sub)
        s = (r % self.sub) * self.sub + (c % self.sub)
        fp = (r // self.sub) * self.feature_side + (c // self.sub)
        # head row (feature pixel * sub^2 + sub-pixel) of each in-plane point i; as rows of 3 values
        # (one axis triple per layer), node layer * m + i (the pad's order) reads row head_row * L + layer
        L = self.n_free_layers
        rows = torch.as_tensor(fp * self.sub**2 + s)[None, :] * L + torch.arange(L)[:, None]
        self.register_buffer("read_rows", rows.reshape(-1), persistent=False)
        self.latent_start = cfg.latent_start
        c0 = cfg.channels[0]
        self.fc = nn.Linear(latent, c0 * 16) if cfg.latent_start else None
        enc_small_first = list(enc_widths[::-1])
        self.skips = nn.ModuleList(nn.Conv2d(w, ch, 1) for w, ch in zip(enc_small_first, cfg.channels))
        self.ups = nn.ModuleList(nn.ConvTranspose2d(a, b, 2, stride=2) for a, b in zip(cfg.channels[:-1], cfg.channels[1:]))
        sides = [4 * 2**i for i in range(len(cfg.channels))]
        self.convs = nn.ModuleList(
            nn.Conv2d(ch, ch, 3, padding=1) if sd in cfg.conv3x3_at else nn.Identity() for sd, ch in zip(sides, cfg.channels)
        )
        self.head = nn.Linear(cfg.channels[-1], self.out_channels * self.sub**2)  # per pixel (a 1 x 1 convolution)
        with torch.no_grad():  # start near a zero residual: the anchor alone
            self.head.weight.mul_(0.1)
            self.head.bias.zero_()

    def features(self, maps: list[torch.Tensor], z: torch.Tensor) -> torch.Tensor:
        """Encoder maps (R/2 first) and latent (B, d) -> features (B, C, F, F) of the last level."""
        maps = maps[::-1]
        x = self.skips[0](maps[0])
        if self.fc is not None:
            x = x + self.fc(z).reshape(z.shape[0], -1, 4, 4)
        x = torch.relu(x)
        if not isinstance(self.convs[0], nn.Identity):
            x = torch.relu(self.convs[0](x))
        for i, up in enumerate(self.ups, start=1):
            x = torch.relu(up(x) + self.skips[i](maps[i]))
            if not isinstance(self.convs[i], nn.Identity):
                x = torch.relu(self.convs[i](x))
        return x

    def forward(self, maps: list[torch.Tensor], z: torch.Tensor) -> torch.Tensor:
        b = z.shape[0]
        f = self.features(maps, z)
        f = f.permute(0, 2, 3, 1).reshape(b, self.feature_side**2, -1)  # pixel-major (B, F * F, C)
        # head: channel s * K + k of pixel p -> row p * sub^2 + s, column k (K = 3 * free layers)
        # channel k = 3 * layer + axis of row p: row p * L + layer of the (B, rows * L, 3) view
        o = self.head(f).reshape(b, self.feature_side**2 * self.sub**2 * self.n_free_layers, 3)
        d = torch.index_select(o, 1, self.read_rows)  # (B, L * m, 3): the free nodes in the pad's order
        return torch.cat([d, d.new_zeros(b, self.n_plane, 3)], dim=1)
