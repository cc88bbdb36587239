"""The read-out network: a small U-Net from colour features to depth and its gradients.

Input (B, 11, H, W) features (:mod:`tactile_deploy.imaging.learned_readout`), any H, W (padded
to multiples of 8 inside, cropped back). Three levels of 2 x 2 average pooling, two 3 x 3
convolutions with GELU per level, skip connections, bilinear upsampling: a receptive field of
about 70 cells (19 mm), wider than any contact. Output (B, 3, H, W): depth gradients along image
columns and rows (mm per mm) and depth in units of ``DEPTH_UNIT_MM``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from tactile_deploy.imaging.learned_readout import N_FEATURES

#: Depth is learned in these units (mm) so that its loss weighs like the gradients'.
DEPTH_UNIT_MM = 0.1


class _Block(nn.Sequential):
    def __init__(self, c_in: int, c_out: int):
        super().__init__(nn.Conv2d(c_in, c_out, 3, padding=1), nn.GELU(),
                         nn.Conv2d(c_out, c_out, 3, padding=1), nn.GELU())


class ReadoutNet(nn.Module):
    """U-Net of base width ``width`` channels (8: about 53,000 parameters)."""

    def __init__(self, width: int = 8):
        super().__init__()
        w = int(width)
        self.width = w
        self.e1, self.e2, self.e3 = _Block(N_FEATURES, w), _Block(w, 2 * w), _Block(2 * w, 4 * w)
        self.bottom = _Block(4 * w, 4 * w)
        self.d3, self.d2, self.d1 = _Block(8 * w, 2 * w), _Block(4 * w, w), _Block(2 * w, w)
        self.head = nn.Conv2d(w, 3, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h, w = x.shape[-2:]
        x = F.pad(x, (0, (-w) % 8, 0, (-h) % 8), mode="replicate")
        e1 = self.e1(x)
        e2 = self.e2(F.avg_pool2d(e1, 2))
        e3 = self.e3(F.avg_pool2d(e2, 2))
        b = self.bottom(F.avg_pool2d(e3, 2))

        def up(t):
            return F.interpolate(t, scale_factor=2.0, mode="bilinear", align_corners=False)

        d3 = self.d3(torch.cat([up(b), e3], 1))
        d2 = self.d2(torch.cat([up(d3), e2], 1))
        d1 = self.d1(torch.cat([up(d2), e1], 1))
        return self.head(d1)[..., :h, :w]


class ExportedReadout(nn.Module):
    """The deployed graph: features -> (depth_mm (B, H, W), gradients (B, 2, H, W))."""

    def __init__(self, net: ReadoutNet):
        super().__init__()
        self.net = net

    def forward(self, features: torch.Tensor):
        out = self.net(features)
        return out[:, 2] * DEPTH_UNIT_MM, out[:, :2]
