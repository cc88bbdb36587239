"""The physics lift as one graph of the ONNX contract (a design compared with the learned ones).

    depth (N, 1, 128, 128) mm
      -> u_z of the sensing nodes = -bilinear(depth) at their rest (x, y)      (SurfaceAnchor)
      -> displacement = H u_z, H = G' C^-1 (n * 3 x n_plane), dense fp32        (SurfaceToVolume)
    vertices = rest + displacement (N, n, 3) mm; ood_score = 0 (no notion of a training range)

One pass (the depth read at rest positions), where the reference
:meth:`tactile_deploy.fem.surface_to_volume.SurfaceToVolume.vertices_from_depth` reads it again
where the nodes have moved (3 passes). ``H`` is 16,140 x 1,076 (69 MB in fp32): the graph is
built for comparison (``tactile-deploy bench predictor``), not shipped.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from tactile_deploy.training.networks.surface_decoder import SurfaceAnchor


class LiftGraph(nn.Module):
    """depth (N, 1, R, R) mm -> (vertices, displacement (N, n, 3) mm, ood_score (N,) zeros)."""

    def __init__(self, H: np.ndarray, rest_vertices_mm: np.ndarray, n_plane: int, resolution: int = 128,
                 half_extent_mm: float = 17.5):
        super().__init__()
        if H.shape != (len(rest_vertices_mm) * 3, n_plane):
            raise ValueError(f"H must be ({len(rest_vertices_mm) * 3}, {n_plane}), got {H.shape}")
        self.anchor = SurfaceAnchor(rest_vertices_mm[:n_plane, :2], resolution, half_extent_mm)
        self.register_buffer("Ht", torch.as_tensor(np.ascontiguousarray(H.T), dtype=torch.float32))
        self.register_buffer("rest", torch.as_tensor(rest_vertices_mm, dtype=torch.float32))

    @classmethod
    def for_pad(cls, nu: float = 0.48) -> "LiftGraph":
        from tactile_deploy.fem.material import Material
        from tactile_deploy.fem.surface_to_volume import SurfaceToVolume
        from tactile_deploy.simulation.contact import get_simulator

        s2v = SurfaceToVolume(get_simulator(Material(nu=nu)))
        return cls(s2v.H, s2v.mesh.vertices, s2v.mesh.n_plane)

    def forward(self, depth: torch.Tensor):
        uz = self.anchor(depth)
        d = (uz @ self.Ht).reshape(depth.shape[0], -1, 3)
        return self.rest + d, d, torch.zeros_like(depth[:, 0, 0, 0])


class LateralLift(nn.Module):
    """u_z (B, m) mm of the sensing nodes -> their lateral displacement (B, m, 2) mm by the pad's
    linear FEM: the physics lift's rows for the sensing nodes' x and y (surface free to slide,
    backplate bonded). One dense (m x 2m) product: 2.3 M weights for the GelSlim pad.

    H_xy : (m, 2, m) -- displacement (node, axis) per unit u_z of each sensing node.
    """

    def __init__(self, H_xy: np.ndarray):
        super().__init__()
        m = H_xy.shape[0]
        if H_xy.shape != (m, 2, m):
            raise ValueError(f"H_xy must be (m, 2, m), got {H_xy.shape}")
        self.m = m
        # column 2 * node + axis; not saved with the model (rebuilt from the pad's FEM)
        self.register_buffer("weight", torch.as_tensor(np.ascontiguousarray(H_xy.reshape(2 * m, m).T),
                                                       dtype=torch.float32), persistent=False)

    @classmethod
    def for_pad(cls, nu: float = 0.48) -> "LateralLift":
        from tactile_deploy.fem.material import Material
        from tactile_deploy.fem.surface_to_volume import SurfaceToVolume
        from tactile_deploy.simulation.contact import get_simulator

        s2v = SurfaceToVolume(get_simulator(Material(nu=nu)))
        m = s2v.mesh.n_plane
        H = s2v.H.reshape(s2v.mesh.n_nodes, 3, m)[:m, :2]
        return cls(np.asarray(H, np.float32))

    def forward(self, uz_mm: torch.Tensor) -> torch.Tensor:
        return (uz_mm @ self.weight).reshape(uz_mm.shape[0], self.m, 2)
