"""The image-to-mesh predictor: depth map (mm) -> volumetric mesh (mm), and its parts.

Data flow of :meth:`Predictor.forward` (each step a method you can call on its own)::

    depth (N, 1, 128, 128) mm
      -> normalise_depth          / depth_scale_mm
      -> encode_image             image VAE encoder mean z_I (N, 128)
      -> project                  latent projection z_M (N, 128)   (3 FC: 256, 512, 256 + linear)
      -> decode_displacement      mesh decoder (COMA, or the lean grid decoder), x scale,
                                  backplate held at 0                                  (N, n, 3) mm
      -> vertices = rest + displacement                                                (N, n, 3) mm

Frames: depth image rows/columns as :class:`tactile_deploy.camera.depth.DepthCamera` (row 0 =
largest y); vertices and displacements in the sensor frame, node order of the frozen pad mesh.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from tactile_deploy.training.config import ModelConfig, ProjectionConfig
from tactile_deploy.training.networks.coarsening import Hierarchy
from tactile_deploy.training.networks.grid_decoder import GridDecoder
from tactile_deploy.training.networks.image_vae import _ACT, ImageVAE, LeanImageDecoder
from tactile_deploy.training.networks.mesh_vae import MeshVAE


class LatentProjection(nn.Module):
    """z_I (N, d_I) -> z_M (N, d_M): FC layers of ``hidden`` widths with activations, then linear."""

    def __init__(self, cfg: ProjectionConfig, d_in: int, d_out: int):
        super().__init__()
        layers: list[nn.Module] = []
        c = d_in
        for w in cfg.hidden:
            layers += [nn.Linear(c, w), _ACT[cfg.activation]()]
            c = w
        layers.append(nn.Linear(c, d_out))
        self.net = nn.Sequential(*layers)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        return self.net(z)


class Normalisation(nn.Module):
    """Fixed data scales (buffers, saved with the model).

    depth_scale_mm : () -- depth maps are divided by it
    displacement_scale_mm : (3,) -- per-axis scale of normalised displacements
    rest_vertices_mm : (n, 3) -- the frozen pad mesh, sensor frame
    free_mask : (n, 1) -- 0 on backplate nodes (bonded, never move), 1 elsewhere
    """

    def __init__(self, rest_vertices_mm, backplate_nodes, depth_scale_mm=1.0, displacement_scale_mm=(1.0, 1.0, 1.0)):
        super().__init__()
        rest = torch.as_tensor(np.asarray(rest_vertices_mm), dtype=torch.float32)
        mask = torch.ones(len(rest), 1)
        mask[torch.as_tensor(np.asarray(backplate_nodes), dtype=torch.int64)] = 0.0
        self.register_buffer("rest_vertices_mm", rest)
        self.register_buffer("free_mask", mask)
        self.register_buffer("depth_scale_mm", torch.tensor(float(depth_scale_mm)))
        self.register_buffer("displacement_scale_mm", torch.as_tensor(displacement_scale_mm, dtype=torch.float32))

    def set_scales(self, depth_scale_mm: float, displacement_scale_mm) -> None:
        self.depth_scale_mm.fill_(float(depth_scale_mm))
        self.displacement_scale_mm.copy_(torch.as_tensor(displacement_scale_mm, dtype=torch.float32))

    def normalise_displacement(self, d_mm: torch.Tensor) -> torch.Tensor:
        return d_mm / self.displacement_scale_mm

    def denormalise_displacement(self, d: torch.Tensor) -> torch.Tensor:
        return d * self.displacement_scale_mm * self.free_mask


class Predictor(nn.Module):
    """Image VAE + mesh VAE + latent projection; ``forward`` is the deployed image-to-mesh path."""

    def __init__(self, cfg: ModelConfig, hierarchy: Hierarchy, rest_vertices_mm, backplate_nodes):
        super().__init__()
        if hierarchy.levels[0].n_nodes != len(rest_vertices_mm):
            raise ValueError(
                f"hierarchy has {hierarchy.levels[0].n_nodes} nodes at level 0 but rest_vertices_mm "
                f"has {len(rest_vertices_mm)}: they describe different meshes"
            )
        self.cfg = cfg
        self.image_vae = ImageVAE(cfg.image)
        self.mesh_vae = MeshVAE(cfg.mesh, hierarchy)
        self.projection = LatentProjection(cfg.projection, cfg.image.latent, cfg.mesh.latent)
        self.norm = Normalisation(rest_vertices_mm, backplate_nodes)
        lv = hierarchy.levels[0]
        #: Sensing nodes (the first layer of the node order).
        self.n_plane = len(lv.plane_xy_mm)
        self.lean_decoder = GridDecoder(cfg.lean_decoder, cfg.mesh.latent, lv.plane_xy_mm, lv.n_layers)
        #: Decoder of the deployed path: "coma" (the mesh VAE's) or "lean" (the grid decoder).
        self.deploy_decoder = "coma"
        self.ood_decoder = LeanImageDecoder(cfg.ood_decoder, cfg.image.latent, cfg.image.resolution)
        if cfg.surface is not None:
            from tactile_deploy.training.networks.surface_decoder import SurfaceAnchor, SurfaceDecoder

            self.surface_decoder = SurfaceDecoder(cfg.surface, cfg.image.widths, cfg.image.latent,
                                                  cfg.image.resolution, lv.plane_xy_mm, lv.n_layers)
            self.anchor = SurfaceAnchor(lv.plane_xy_mm, cfg.image.resolution, cfg.surface.half_extent_mm)
            self.deploy_decoder = "surface"
        #: With the surface decoder: the physics lift of the sensing nodes' u_z, giving their lateral
        #: displacement instead of the decoder's (:meth:`use_lateral_lift`; the "hybrid" export
        #: variants), or under it (``lateral_adds``: the decoder's residual is added; set by
        #: ``build_model`` for ``surface.lateral = "lift_residual"``, where it is part of the model).
        self.lateral_lift = None
        self.lateral_adds = cfg.surface is not None and cfg.surface.lateral == "lift_residual"

    # -- the deployed path, step by step -------------------------------------------------------
    def normalise_depth(self, depth_mm: torch.Tensor) -> torch.Tensor:
        return depth_mm / self.norm.depth_scale_mm

    def encode_image(self, depth_norm: torch.Tensor) -> torch.Tensor:
        return self.image_vae.encoder(depth_norm)[0]

    def project(self, z_image: torch.Tensor) -> torch.Tensor:
        return self.projection(z_image)

    def decode_displacement(self, z_mesh: torch.Tensor) -> torch.Tensor:
        decoder = self.lean_decoder if self.deploy_decoder == "lean" else self.mesh_vae.decoder
        return self.norm.denormalise_displacement(decoder(z_mesh))

    def surface_displacement_normalised(self, depth_mm: torch.Tensor, maps=None, z=None) -> torch.Tensor:
        """The surface-anchored path in units of the displacement scale (N, n, 3): the residual of
        the surface decoder plus the anchor (u_z of the sensing nodes read off the depth map) on the
        sensing layer's z. ``maps``, ``z``: the encoder's feature maps and latent when computed."""
        if maps is None:
            maps, z = self.image_vae.encoder.feature_maps(self.normalise_depth(depth_mm))
        from tactile_deploy.training.networks.surface_decoder import compose_surface

        return compose_surface(self.surface_decoder(maps, z), depth_mm, self.anchor, self.cfg.surface.anchor == "moved",
                               self.norm.displacement_scale_mm, self.lateral_lift, self.lateral_adds)

    def use_lateral_lift(self, lift) -> None:
        """Take the sensing nodes' lateral displacement from ``lift``
        (:class:`tactile_deploy.training.networks.lift.LateralLift`: u_z -> x, y by the pad's FEM); None: the decoder's."""
        if lift is not None and not hasattr(self, "surface_decoder"):
            raise ValueError("the lateral lift completes the surface decoder; this model has none")
        if lift is None and self.lateral_adds:
            raise ValueError("this model's decoder was trained on top of the lateral lift "
                             "(surface.lateral = 'lift_residual'): it cannot run without it")
        self.lateral_lift = lift

    def forward(self, depth_mm: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """depth (N, 1, R, R) mm -> (vertices (N, n, 3) mm, displacement (N, n, 3) mm)."""
        if self.deploy_decoder == "surface":
            disp = self.norm.denormalise_displacement(self.surface_displacement_normalised(depth_mm))
        else:
            disp = self.decode_displacement(self.project(self.encode_image(self.normalise_depth(depth_mm))))
        return self.norm.rest_vertices_mm + disp, disp

    # -- out-of-distribution score -------------------------------------------------------------
    def image_reconstruction_rmse(self, depth_mm: torch.Tensor, decoder: str = "vae") -> torch.Tensor:
        """RMS error (N,) mm of the reconstruction from the image VAE's mean latent, by its own
        decoder (``"vae"``) or the lean one (``"lean"``)."""
        x = self.normalise_depth(depth_mm)
        dec = self.ood_decoder if decoder == "lean" else self.image_vae.decoder
        recon = dec(self.image_vae.encoder(x)[0])
        err = (recon - x) * self.norm.depth_scale_mm
        return torch.sqrt(torch.mean(err.pow(2), dim=(1, 2, 3)))
