"""Checking a plugin completely: manifest, files and checksums, shapes that must agree, the
family's pad hash and the ONNX model's contract (``tactile-deploy plugins validate``)."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

from tactile_deploy.onnx_runtime.contract import check_model_contract
from tactile_deploy.pad.asset import load_pad
from tactile_deploy.pad.family import FAMILIES
from tactile_deploy.runtime.plugins.discovery import find_plugin
from tactile_deploy.runtime.plugins.loading import SensorPlugin
from tactile_deploy.runtime.plugins.manifest import PluginError, PluginManifest, load_manifest
from tactile_deploy.runtime.sources.base import SourceError
from tactile_deploy.runtime.sources.factory import open_clip


@dataclass
class ValidationReport:
    """Outcome of :func:`validate_plugin`: what was checked, and the problems found."""

    folder: Path
    checked: list[str] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)
    manifest: PluginManifest | None = None

    @property
    def ok(self) -> bool:
        return not self.problems


def validate_plugin(name_or_path: str | os.PathLike, check_model: bool = True) -> ValidationReport:
    """Check a plugin completely: manifest, every file's presence and checksum, shapes that must
    agree (shading vs imaging grid, reference vs camera, noise reference vs depth grid, demo clip
    vs camera), the family's pad hash, and the ONNX model's contract and mesh hash."""
    try:
        loc = find_plugin(name_or_path)
    except PluginError as e:
        return ValidationReport(Path(str(name_or_path)), problems=[str(e)])
    report = ValidationReport(loc.folder)
    try:
        manifest = load_manifest(loc.folder)
    except PluginError as e:
        report.problems.append(str(e))
        return report
    report.manifest = manifest
    report.checked.append("manifest")
    plugin = SensorPlugin(manifest, loc.folder, loc.hooks, loc.origin)

    def attempt(what: str, fn) -> None:
        try:
            fn()
            report.checked.append(what)
        except (PluginError, ValueError, OSError, SourceError) as e:
            report.problems.append(str(e))

    for name in manifest.files():
        attempt(f"{name} checksum", lambda n=name: plugin.verified_path(n))
    attempt("pad mesh hash", lambda: _check_family(plugin))
    attempt("shading model", lambda: plugin.shading_model)
    if manifest.readout is not None:
        attempt("learned read-out", lambda: plugin.readout)
    attempt("reference frame", lambda: plugin.reference_frame)
    attempt("noise reference", lambda: plugin.noise_reference)
    attempt("demo clip", lambda: _check_demo(plugin))
    attempt("topology", lambda: plugin.topology)
    if check_model:
        if manifest.model is not None:
            attempt("model contract", lambda: check_model_contract(
                plugin.verified_path("model"), manifest.family.mesh_hash, what=f"plugin "
                f"{manifest.name!r} model"))
        def adapted_contract():
            path = plugin.adapted_model_path()
            if path is not None:
                check_model_contract(path, manifest.family.mesh_hash, what=f"plugin {manifest.name!r} adapted model")

        attempt("adapted model contract", adapted_contract)
    return report


def _check_family(plugin: SensorPlugin) -> None:
    fam = plugin.manifest.family
    try:
        mesh = load_pad(fam.pad, fam.pad_version)
    except (KeyError, FileNotFoundError) as e:
        raise PluginError(f"plugin {plugin.name!r}: field 'family.pad': {e}") from None
    if mesh.content_hash != fam.mesh_hash:
        raise PluginError(
            f"plugin {plugin.name!r}: field 'family.mesh_hash' is {fam.mesh_hash[:16]}..., but "
            f"the pad {fam.pad} v{fam.pad_version} installed here has {mesh.content_hash[:16]}"
            "...; this plugin was made for another pad mesh: rebuild it for this one")
    family = FAMILIES.get(fam.pad)
    grid = plugin.manifest.depth_grid
    if family is not None and grid != family.depth_grid:
        raise PluginError(
            f"plugin {plugin.name!r}: field 'depth_grid' is {grid.model_dump()}, the pad "
            f"{fam.pad}'s depth grid is {family.depth_grid.model_dump()}; rebuild the plugin")


def _check_demo(plugin: SensorPlugin) -> None:
    cam = plugin.manifest.camera
    with open_clip(plugin.demo_clip_path(), name=f"demo clip of {plugin.name!r}") as src:
        frame = src.read()
    if frame is None:
        raise PluginError(f"plugin {plugin.name!r}: demo clip has no frames")
    if frame.image.shape[:2] != (cam.image_height_px, cam.image_width_px):
        raise PluginError(
            f"plugin {plugin.name!r}: demo clip frames are {frame.image.shape[1]}x"
            f"{frame.image.shape[0]} px, the camera mapping expects {cam.image_width_px}x"
            f"{cam.image_height_px}; record the clip with this camera setting")
