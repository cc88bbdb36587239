"""A loaded sensor plugin: its manifest, folder and hooks, and its files (read on first use,
checked against their sha256)."""

from __future__ import annotations

import logging
import math
import os
import shlex
from functools import cached_property
from pathlib import Path

import cv2
import numpy as np

from tactile_deploy.checksums import file_sha256
from tactile_deploy.imaging.camera_mapping import CameraMapping
from tactile_deploy.imaging.learned_readout import LearnedReadout, ReadoutError
from tactile_deploy.imaging.shading import ShadingModelError, load_shading
from tactile_deploy.pad.mesh import content_hash
from tactile_deploy.pad.topology import MeshTopology
from tactile_deploy.runtime.plugins.discovery import PluginHooks, find_plugin
from tactile_deploy.runtime.plugins.manifest import (
    MANIFEST_NAME,
    PluginError,
    PluginManifest,
    load_manifest,
)
from tactile_deploy.runtime.plugins.versions import active_version

log = logging.getLogger(__name__)


class SensorPlugin:
    """A loaded plugin: manifest, folder, hooks, and its files (read on first use, checked
    against their sha256)."""

    def __init__(self, manifest: PluginManifest, folder: Path, hooks: PluginHooks | None = None,
                 origin: str = "path"):
        self.manifest = manifest
        self.folder = Path(folder)
        self.hooks = hooks or PluginHooks()
        self.origin = origin
        self._verified: set[str] = set()
        self._found_as: str | None = None  # the registered name it was loaded by

    @classmethod
    def load(cls, name_or_path: str | os.PathLike) -> SensorPlugin:
        """Load by name or path; the manifest is validated, files are checked when read."""
        if isinstance(name_or_path, SensorPlugin):
            return name_or_path
        loc = find_plugin(name_or_path)
        manifest = load_manifest(loc.folder)
        if loc.origin != "path" and manifest.name != loc.name:
            log.warning("plugin registered as %r has manifest name %r", loc.name, manifest.name)
        plugin = cls(manifest, loc.folder, loc.hooks, loc.origin)
        plugin._found_as = loc.name if loc.origin != "path" else None
        return plugin

    @property
    def name(self) -> str:
        return self.manifest.name

    @property
    def sensor_option(self) -> str:
        """The ``--sensor`` value that finds this plugin from any folder: the registered name it
        was loaded by, else its absolute folder (quoted for a shell when needed)."""
        return self._found_as or shlex.quote(str(self.folder.resolve()))

    def __repr__(self) -> str:
        return f"SensorPlugin({self.name!r}, folder={str(self.folder)!r})"

    # -- files
    def path_of(self, field_name: str) -> Path:
        """Absolute path of the file named by manifest field ``field_name``."""
        ref = self.manifest.files().get(field_name)
        if ref is None:
            raise PluginError(f"plugin {self.name!r} has no file field {field_name!r}")
        p = Path(ref.path).expanduser()
        return p if p.is_absolute() else (self.folder / p).resolve()

    def verified_path(self, field_name: str) -> Path:
        """:meth:`path_of`, after checking the file exists and matches its sha256."""
        path = self.path_of(field_name)
        if field_name in self._verified:
            return path
        ref = self.manifest.files()[field_name]
        if not path.is_file():
            raise PluginError(
                f"plugin {self.name!r} ({self.folder / MANIFEST_NAME}): field '{field_name}."
                f"path' names {path}, which does not exist; restore the file or rebuild the "
                "plugin")
        actual = file_sha256(path)
        if actual != ref.sha256:
            raise PluginError(
                f"plugin {self.name!r} ({self.folder / MANIFEST_NAME}): {path} does not match "
                f"field '{field_name}.sha256': expected {ref.sha256[:16]}..., file has "
                f"{actual[:16]}...; the file was changed or replaced - restore it, or if the "
                "change is intended rebuild the plugin (which records the new checksum)")
        self._verified.add(field_name)
        return path

    def model_path(self, adapted: bool | None = None) -> Path:
        """The ONNX model: the adapted one when present (unless ``adapted=False``)."""
        active = self.adapted_model_path()
        if adapted is None:
            adapted = active is not None
        if adapted and active is None:
            raise PluginError(f"plugin {self.name!r} has no adapted model; run without asking "
                              "for the adapted model, or adapt one first (tactile-deploy adapt)")
        if not adapted and self.manifest.model is None:
            raise PluginError(f"plugin {self.name!r} has no learned model (field 'model' is "
                              "null): its meshes come from the physics lift of the pad; run with "
                              "--mesh physics (the default for such a plugin)")
        return active if adapted else self.verified_path("model")

    def adapted_model_path(self) -> Path | None:
        """The adapted model in use: the active version written by ``tactile-deploy adapt``
        (``adapted/history.json``, checked against its sha256) when it was adapted from this
        plugin's family model, else the manifest's ``adapted_model``, else None."""
        try:
            rec = active_version(self.folder)
        except ValueError as e:
            raise PluginError(f"plugin {self.name!r}: {e}") from None
        if rec is not None and (self.manifest.model is None
                                or rec.family_model_sha256 != self.manifest.model.sha256):
            log.warning("plugin %r: adapted version %d was made from another family model (sha256 %s..., now "
                        "%s...); using the plugin's own model - adapt again for the new one", self.name,
                        rec.version, rec.family_model_sha256[:12],
                        "none" if self.manifest.model is None else self.manifest.model.sha256[:12])
        elif rec is not None:
            path = (self.folder / rec.model).resolve()
            if not path.is_file() or file_sha256(path) != rec.sha256:
                raise PluginError(
                    f"plugin {self.name!r}: active adapted version {rec.version} ({path}) is missing or does not "
                    f"match its sha256 in adapted/history.json; restore it, or go back with "
                    f"`tactile-deploy adapt --sensor {self.sensor_option} --rollback`")
            return path
        if self.manifest.adapted_model is not None:
            return self.verified_path("adapted_model")
        return None

    @property
    def camera_mapping(self) -> CameraMapping:
        return self.manifest.camera

    @cached_property
    def shading_model(self):
        path = self.verified_path("shading")
        try:
            model = load_shading(path)
        except ShadingModelError as e:
            raise PluginError(f"plugin {self.name!r}: {e}") from None
        g = self.manifest.camera.grid
        h = model.header
        if h.image_shape != (g.ny, g.nx):
            raise PluginError(
                f"plugin {self.name!r}: shading model {path.name} was fitted for "
                f"{h.image_width_px}x{h.image_height_px} px frames, but the camera's imaging "
                f"grid is {g.nx}x{g.ny}; refit it on rectified frames or fix camera.grid")
        if not math.isclose(h.mm_per_px, g.pitch_x_mm, rel_tol=1e-4) or not math.isclose(
                g.pitch_x_mm, g.pitch_y_mm, rel_tol=1e-4):
            raise PluginError(
                f"plugin {self.name!r}: shading model {path.name} has mm_per_px={h.mm_per_px}, "
                f"the imaging grid has pitch {g.pitch_x_mm} x {g.pitch_y_mm} mm (expected one "
                "equal square pitch); refit the shading model on this grid")
        return model

    @cached_property
    def readout(self):
        """The learned read-out (:class:`~tactile_deploy.imaging.learned_readout.LearnedReadout`)
        named by the manifest, or None."""
        if self.manifest.readout is None:
            return None
        try:
            return LearnedReadout(self.verified_path("readout"))
        except ReadoutError as e:
            raise PluginError(f"plugin {self.name!r}: {e}") from None

    @cached_property
    def reference_frame(self) -> np.ndarray:
        """No-contact frame, (H, W, 3) uint8 RGB, raw camera pixels."""
        path = self.verified_path("reference_frame")
        img = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if img is None:
            raise PluginError(f"plugin {self.name!r}: reference frame {path} is not a readable "
                              "image; restore it or rebuild the plugin")
        rgb = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
        cam = self.manifest.camera
        if rgb.shape[:2] != (cam.image_height_px, cam.image_width_px):
            raise PluginError(
                f"plugin {self.name!r}: reference frame {path.name} is {rgb.shape[1]}x"
                f"{rgb.shape[0]} px, the camera mapping expects {cam.image_width_px}x"
                f"{cam.image_height_px}; record it again at the camera's resolution")
        return rgb

    @cached_property
    def noise_reference(self) -> np.ndarray:
        """No-contact depth, (128, 128) float32 mm on the model grid."""
        path = self.verified_path("noise_reference")
        try:
            arr = np.load(path, allow_pickle=False)
        except (ValueError, OSError, EOFError) as e:
            raise PluginError(f"plugin {self.name!r}: noise reference {path} is not a readable "
                              f".npy array ({e})") from None
        g = self.manifest.depth_grid
        if arr.shape != (g.ny, g.nx) or arr.dtype.kind != "f":
            raise PluginError(f"plugin {self.name!r}: noise reference {path.name} must be a "
                              f"({g.ny}, {g.nx}) float depth map in mm, got {arr.shape} "
                              f"{arr.dtype}")
        if not np.all(np.isfinite(arr)):
            raise PluginError(f"plugin {self.name!r}: noise reference {path.name} holds NaN or "
                              "inf")
        return arr.astype(np.float32)

    def demo_clip_path(self) -> Path:
        return self.verified_path("demo_clip")

    @cached_property
    def topology(self):
        """The :class:`~tactile_deploy.runtime.predictor.MeshTopology` of the topology file,
        checked against the family's mesh hash."""
        path = self.verified_path("topology")
        try:
            topo = MeshTopology.load(path)
        except (KeyError, ValueError, OSError, EOFError) as e:
            raise PluginError(f"plugin {self.name!r}: topology file {path} is not readable "
                              f"({e}); rebuild the plugin") from None
        actual = content_hash(topo.rest_vertices_mm.astype(np.float64), topo.tets)
        expected = self.manifest.family.mesh_hash
        if topo.mesh_hash != expected or actual != expected:
            raise PluginError(
                f"plugin {self.name!r}: topology file {path.name} describes mesh "
                f"{actual[:16]}... (recorded {topo.mesh_hash[:16]}...), the family's mesh is "
                f"{expected[:16]}...; rebuild the plugin")
        return topo
