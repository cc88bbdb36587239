"""The read-out network: a small U-Net from colour features to depth and its gradients.

Input (B, 11, H, W) features (:mod:`tactile_deploy.imaging.learned_readout`), any H, W (padded
to multiples of 8 inside, cropped back). Three levels of 2 x 2 average pooling, two 3 x 3
convolutions with GELU per level, skip connections, bilinear upsampling: a receptive field of
about 70 cells (19 mm), wider than any contact. Output (B, 3, H, W): depth gradients along image
columns and rows (mm per mm) and depth in units of ``DEPTH_UNIT_MM``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from tactile_deploy.atomic import atomic_path
from tactile_deploy.imaging.learned_readout import N_FEATURES
from tactile_deploy.onnx_runtime.metadata import set_metadata

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


def targets(depth_mm: np.ndarray, pitch_mm: float, gradient_clip: float = 1.0) -> np.ndarray:
    """(N, 3, H, W) float32: depth gradients along image columns and rows (mm per mm, clipped
    to +-``gradient_clip``: the walls of flat punches and prisms are near vertical and would
    dominate the loss) and depth in DEPTH_UNIT_MM, of depth maps (N, H, W) mm (rows along -y)."""
    g_row, g_col = np.gradient(depth_mm, pitch_mm, axis=(1, 2))
    g = np.clip(np.stack([g_col, g_row], 1), -gradient_clip, gradient_clip)
    return np.concatenate([g, (depth_mm / DEPTH_UNIT_MM)[:, None]], 1).astype(np.float32)


def export_onnx(net, out: Path, metadata: dict) -> None:
    """Write ``net`` as the deployed graph (:class:`ExportedReadout`) to ``out``
    atomically, with ``metadata`` as ONNX metadata properties."""
    import onnx

    graph = ExportedReadout(net).eval()
    example = torch.zeros(1, 11, 64, 90)
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(out) as tmp:
        torch.onnx.export(graph, example, str(tmp), input_names=["features"],
                          output_names=["depth_mm", "gradients"], opset_version=17,
                          dynamic_axes={"features": {0: "batch", 2: "rows", 3: "columns"},
                                        "depth_mm": {0: "batch", 1: "rows", 2: "columns"},
                                        "gradients": {0: "batch", 2: "rows", 3: "columns"}},
                          dynamo=False)
        model = onnx.load(str(tmp))
        set_metadata(model, metadata)
        onnx.save(model, str(tmp))
