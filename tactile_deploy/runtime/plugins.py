"""Sensor plugins: one folder per sensor with a strict JSON manifest, and the registry that finds them.

A plugin folder holds ``plugin.json`` (:class:`PluginManifest`) and the files it names, each with
its sha256: the shading model (``.npz``), the no-contact reference frame (PNG, raw camera
pixels), the noise reference (``.npy`` depth map on the model's grid), the demo clip (``.npz`` or
a video) and, usually outside the folder, the ONNX model of the sensor family. Relative paths in
a manifest are relative to the plugin folder.

Where plugins are found (first found wins; a later plugin of the same name is reported as
shadowed by ``tactile-deploy plugins list``):

1. the folders listed in ``$TACTILE_DEPLOY_PLUGIN_PATH`` (``os.pathsep``-separated), each either a
   plugin folder or a folder of plugin folders;
2. packages that register entry points in the group ``tactile_deploy.plugins``: the entry point
   (``name = "package.module:attribute"``) loads to a :class:`PluginEntry` (folder plus optional
   :class:`PluginHooks`), a folder path, or a function returning either;
3. the ``plugins/`` folder of a source checkout of tactile-deploy (the shipped plugins).

Only entry-point plugins can bring code (:class:`PluginHooks`): a plugin folder on its own is
data, and loading it never runs code from it.
"""

from __future__ import annotations

import json
import logging
import math
import os
import re
import shutil
from dataclasses import dataclass, field
from functools import cached_property
from importlib.metadata import entry_points
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    model_validator,
)

from tactile_deploy.checksums import file_sha256
from tactile_deploy.imaging.camera_mapping import CameraMapping, OutputGrid
from tactile_deploy.jsonfile import read_json, validation_error_text
from tactile_deploy.runtime.drift import ReferenceRange
from tactile_deploy.runtime.sources.config import SourceConfig

log = logging.getLogger(__name__)

#: Version of the manifest format this code reads and writes.
FORMAT_VERSION = 1
#: File name of the manifest inside a plugin folder.
MANIFEST_NAME = "plugin.json"
#: Entry-point group through which installed packages register plugins.
ENTRY_POINT_GROUP = "tactile_deploy.plugins"
#: Environment variable with extra plugin folders.
PLUGIN_PATH_ENV = "TACTILE_DEPLOY_PLUGIN_PATH"
#: The shipped plugins of a source checkout.
CHECKOUT_PLUGINS = Path(__file__).resolve().parents[2] / "plugins"
#: The depth grid every model of this project takes: +-17.5 mm, 128 x 128 (sensor frame).
MODEL_GRID = OutputGrid()

_STRICT = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
_SHA256 = r"^[0-9a-f]{64}$"
#: What a plugin name (and so a plugin folder's name) may be.
_NAME = r"^[a-z0-9][a-z0-9_\-]*$"


class PluginError(ValueError):
    """A plugin is missing, invalid, or its files do not match it (the message says which file,
    which field, what was expected and found, and what to do)."""


# ------------------------------------------------------------------------------------ manifest
class FileRef(BaseModel):
    """A file of the plugin and its checksum."""

    model_config = _STRICT

    path: str = Field(min_length=1, description="File path, relative to the plugin folder "
                      "(POSIX separators) or absolute.")
    sha256: str = Field(pattern=_SHA256, description="sha256 of the file's bytes, lower-case hex.")


class FamilySpec(BaseModel):
    """The sensor family: which pad mesh its model outputs."""

    model_config = _STRICT

    name: str = Field(min_length=1, description="Family name, e.g. 'gelslim'.")
    pad: str = Field("gelslim", description="Shipped pad asset the model's vertices follow "
                     "(`tactile-deploy pad info --pad NAME`).")
    pad_version: int = Field(1, ge=1, description="Version of that pad asset.")
    mesh_hash: str = Field(pattern=_SHA256, description="Content hash of the pad mesh; the "
                           "model's metadata must carry the same hash.")


class MaterialSpec(BaseModel):
    """The calibrated gel material used for contact forces."""

    model_config = _STRICT

    E_mpa: float = Field(gt=0, le=1e4, description="Young's modulus, MPa (scales forces).")
    nu: float = Field(ge=0.0, lt=0.5, description="Poisson's ratio (sets the stiffness shape).")
    source: str = Field("", description="Where the values come from (calibration run, paper).")


class NoiseReferenceSpec(FileRef):
    """Depth map of the sensor with nothing touching it: its fixed-pattern depth noise."""

    handling: Literal["subtract", "keep"] = Field(
        description="'subtract': removed from every depth map before the model (the model was "
        "trained on clean depth); 'keep': left in (the model was trained with this noise added "
        "to its inputs, as in the paper's augmentation).")


class PluginManifest(BaseModel):
    """``plugin.json``: everything the runtime needs to turn this sensor's frames into meshes."""

    model_config = _STRICT

    format_version: Literal[1] = Field(FORMAT_VERSION, description="Version of this file format.")
    name: str = Field(pattern=_NAME,
                      description="Plugin name (lower case, digits, '-' and '_').")
    description: str = Field("", description="One line about the sensor.")
    family: FamilySpec = Field(description="Sensor family and its pad mesh.")
    model: FileRef | None = Field(
        None, description="ONNX model of the family: depth (N, 1, 128, 128) mm -> vertices "
        "(N, n, 3) mm (docs/onnx_contract.md); null when the family has no learned model yet: "
        "meshes then come from the physics lift of the pad (`run --mesh physics`).")
    adapted_model: FileRef | None = Field(
        None, description="Optional model adapted to this very sensor; used instead of `model` "
        "unless the user asks for the family model.")
    camera: CameraMapping = Field(description="Camera mapping: lens, homography to the sensing "
                                  "plane, and the imaging grid the shading model works on.")
    depth_grid: OutputGrid = Field(default_factory=OutputGrid,
                                   description="Grid of the depth maps: the pad family's depth "
                                   "grid (the GelSlim model's: +-17.5 mm, 128 x 128), row 0 at "
                                   "the largest y.")
    shading: FileRef = Field(description="Shading model (.npz with JSON header) fitted on frames "
                             "rectified onto the camera's imaging grid.")
    readout: FileRef | None = Field(
        None, description="Optional learned read-out of the sensor's design (.onnx: rectified "
        "frame features -> depth, tactile_deploy/imaging/learned_readout.py); when given, it "
        "turns frames into depth instead of the shading model and the integration.")
    readout_depth_gain: float = Field(
        1.0, gt=0, description="This unit's depth gain of the learned read-out (its depth is "
        "multiplied by it), calibrated from ball presses of known intrusion.")
    reference_frame: FileRef = Field(description="No-contact frame, raw camera pixels, RGB "
                                     "image file (PNG).")
    noise_reference: NoiseReferenceSpec = Field(description="No-contact depth map (.npy, "
                                                "float32 mm, depth grid) and how to use it.")
    material: MaterialSpec = Field(description="Calibrated E and nu of the gel.")
    default_source: SourceConfig = Field(description="Frame source used when none is given.")
    demo_clip: FileRef = Field(description="Short recording (.npz clip or video) that "
                               "`tactile-deploy run` plays without a sensor.")
    topology: FileRef = Field(description="Topology file of the model's mesh (.npz: rest "
                              "vertices, tets, surface faces, sensing nodes, mesh hash; "
                              "docs/onnx_contract.md), for programs that use the ONNX model "
                              "without tactile-deploy.")
    ood_threshold: float | None = Field(
        None, gt=0, description="Out-of-distribution score above which frames are flagged "
        "(None: the model's own threshold from its metadata).")
    provenance: dict[str, str] = Field(default_factory=dict,
                                       description="How the plugin was made (tool, date, inputs).")
    reference_range: ReferenceRange | None = Field(
        None, description="What the calibration saw of the no-contact image (illumination "
        "drift, noise): `tactile-deploy run` warns when frames drift beyond it.")

    @model_validator(mode="after")
    def _check(self) -> PluginManifest:
        if self.model is not None and self.depth_grid != MODEL_GRID:
            raise ValueError(f"depth_grid must be the model grid {MODEL_GRID.model_dump()} (the "
                             f"learned model's input), got {self.depth_grid.model_dump()}")
        return self

    def files(self) -> dict[str, FileRef]:
        """Every file reference of the manifest, by field name."""
        out = {"shading": self.shading,
               "reference_frame": self.reference_frame,
               "noise_reference": self.noise_reference, "demo_clip": self.demo_clip,
               "topology": self.topology}
        if self.model is not None:
            out["model"] = self.model
        if self.adapted_model is not None:
            out["adapted_model"] = self.adapted_model
        if self.readout is not None:
            out["readout"] = self.readout
        return out


def manifest_json_schema() -> dict:
    """JSON Schema of ``plugin.json`` (field descriptions included)."""
    return PluginManifest.model_json_schema()


def load_manifest(path: str | os.PathLike) -> PluginManifest:
    """Read and validate a ``plugin.json`` (the file, or the folder holding it)."""
    path = Path(path)
    if path.is_dir():
        path = path / MANIFEST_NAME
    if not path.is_file():
        raise PluginError(f"plugin manifest {path} not found; a plugin folder holds a "
                          f"{MANIFEST_NAME} (see `tactile-deploy plugins list`)")
    doc = read_json(path, PluginError, "a JSON plugin manifest")
    if not isinstance(doc, dict):
        raise PluginError(f"{path}: expected a JSON object, got {type(doc).__name__}")
    if doc.get("format_version") != FORMAT_VERSION:
        raise PluginError(f"{path}: field 'format_version': this version of tactile-deploy reads "
                          f"version {FORMAT_VERSION}, the file has {doc.get('format_version')!r}")
    try:
        # strict JSON types: "0.3" is no number, "yes" no boolean, 1.0 no integer (an integer is
        # a number); JSON arrays fill the tuple fields
        return PluginManifest.model_validate_json(json.dumps(doc), strict=True)
    except ValidationError as e:
        raise PluginError(validation_error_text(
            path, e, "plugin manifest",
            "the format is described by tactile_deploy/runtime/manifest.schema.json")) from None


# ------------------------------------------------------------------------------------ hooks
class PluginHooks:
    """Code a third-party sensor package may add (override what you need; defaults do nothing).

    Hooks are called by :class:`tactile_deploy.runtime.pipeline.ImagingPipeline` and the source
    factory; they must keep the documented shapes, dtypes and units.
    """

    def preprocess_frame(self, frame: np.ndarray) -> np.ndarray:
        """Raw camera frame (H, W, 3) uint8 RGB -> the same shape and dtype (e.g. colour
        correction, own demosaicing), before rectification."""
        return frame

    def postprocess_depth(self, depth_mm: np.ndarray) -> np.ndarray:
        """Depth map (128, 128) float32 mm on the model grid -> the same, before the model."""
        return depth_mm

    def open_source(self, config) -> object | None:
        """A :class:`~tactile_deploy.runtime.sources.base.FrameSource` for ``config`` (e.g. the
        sensor's own camera driver), or None to use the built-in sources."""
        return None


@dataclass(frozen=True)
class PluginEntry:
    """What an entry point of the group ``tactile_deploy.plugins`` provides."""

    folder: Path
    hooks: PluginHooks | None = None


@dataclass(frozen=True)
class PluginLocation:
    """A plugin found by the registry: its name, folder, where it came from, its hooks."""

    name: str
    folder: Path
    origin: str
    hooks: PluginHooks | None = None


# ------------------------------------------------------------------------------------ registry
def _folder_plugins(root: Path, origin: str) -> list[PluginLocation]:
    if (root / MANIFEST_NAME).is_file():
        return [PluginLocation(root.name, root, origin)]
    if not root.is_dir():
        return []
    return [PluginLocation(p.name, p, origin) for p in sorted(root.iterdir())
            if (p / MANIFEST_NAME).is_file()]


def _entry_point_plugins() -> list[PluginLocation]:
    out = []
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        try:
            obj = ep.load()
            if callable(obj) and not isinstance(obj, (PluginEntry, str, os.PathLike)):
                obj = obj()
            if isinstance(obj, (str, os.PathLike)):
                obj = PluginEntry(Path(obj))
            if not isinstance(obj, PluginEntry):
                raise TypeError(f"expected a PluginEntry or a folder path, got {type(obj).__name__}")
        except Exception as exc:  # a broken third-party package must not break the others
            log.warning("plugin entry point '%s' (%s) failed to load: %s", ep.name, ep.value, exc)
            continue
        dist = getattr(ep, "dist", None)
        origin = f"entry point {ep.value}" + (f" ({dist.name})" if dist is not None else "")
        out.append(PluginLocation(ep.name, Path(obj.folder), origin, obj.hooks))
    return out


def search_path() -> list[Path]:
    """Folders named by ``$TACTILE_DEPLOY_PLUGIN_PATH``, in order."""
    text = os.environ.get(PLUGIN_PATH_ENV, "")
    return [Path(p).expanduser() for p in text.split(os.pathsep) if p.strip()]


def discover_plugins() -> tuple[dict[str, PluginLocation], list[PluginLocation]]:
    """All plugins: ``(by name, shadowed)`` in the search order of the module docstring."""
    found: list[PluginLocation] = []
    for root in search_path():
        found += _folder_plugins(root, f"${PLUGIN_PATH_ENV}")
    found += _entry_point_plugins()
    found += _folder_plugins(CHECKOUT_PLUGINS, "shipped")
    by_name: dict[str, PluginLocation] = {}
    shadowed = []
    for loc in found:
        if loc.name in by_name:
            shadowed.append(loc)
        else:
            by_name[loc.name] = loc
    return by_name, shadowed


def find_plugin(name_or_path: str | os.PathLike) -> PluginLocation:
    """A plugin by registered name, or by the path of its folder or manifest."""
    text = str(name_or_path)
    path = Path(text).expanduser()
    if os.sep in text or text.startswith(".") or path.is_dir() or path.suffix == ".json":
        folder = path.parent if path.suffix == ".json" else path
        if not (folder / MANIFEST_NAME).is_file():
            raise PluginError(f"{folder} is not a plugin folder (no {MANIFEST_NAME} in it)")
        return PluginLocation(folder.name, folder, "path")
    by_name, _ = discover_plugins()
    if text not in by_name:
        known = ", ".join(sorted(by_name)) or "none"
        raise PluginError(f"unknown sensor plugin {text!r}; installed plugins: {known} (run "
                          "`tactile-deploy plugins list`, or pass the path of a plugin folder)")
    return by_name[text]


# ------------------------------------------------------------------------------------ plugin
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
        import shlex

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
        from tactile_deploy.adapt.versions import active_version

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
        from tactile_deploy.imaging.shading import ShadingModelError, load_shading

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
        from tactile_deploy.imaging.learned_readout import LearnedReadout, ReadoutError

        try:
            return LearnedReadout(self.verified_path("readout"))
        except ReadoutError as e:
            raise PluginError(f"plugin {self.name!r}: {e}") from None

    @cached_property
    def reference_frame(self) -> np.ndarray:
        """No-contact frame, (H, W, 3) uint8 RGB, raw camera pixels."""
        import cv2

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
        from tactile_deploy.runtime.predictor import MeshTopology

        path = self.verified_path("topology")
        try:
            topo = MeshTopology.load(path)
        except (KeyError, ValueError, OSError, EOFError) as e:
            raise PluginError(f"plugin {self.name!r}: topology file {path} is not readable "
                              f"({e}); rebuild the plugin") from None
        from tactile_deploy.pad.mesh import content_hash

        actual = content_hash(topo.rest_vertices_mm.astype(np.float64), topo.tets)
        expected = self.manifest.family.mesh_hash
        if topo.mesh_hash != expected or actual != expected:
            raise PluginError(
                f"plugin {self.name!r}: topology file {path.name} describes mesh "
                f"{actual[:16]}... (recorded {topo.mesh_hash[:16]}...), the family's mesh is "
                f"{expected[:16]}...; rebuild the plugin")
        return topo


# ------------------------------------------------------------------------------------ checks
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

    from tactile_deploy.runtime.sources.base import SourceError

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
        from tactile_deploy.runtime.predictor import check_model_contract

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
    from tactile_deploy.pad.asset import load_pad

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
    from tactile_deploy.pad.family import FAMILIES

    family = FAMILIES.get(fam.pad)
    grid = plugin.manifest.depth_grid
    if family is not None and grid != family.depth_grid:
        raise PluginError(
            f"plugin {plugin.name!r}: field 'depth_grid' is {grid.model_dump()}, the pad "
            f"{fam.pad}'s depth grid is {family.depth_grid.model_dump()}; rebuild the plugin")


def _check_demo(plugin: SensorPlugin) -> None:
    from tactile_deploy.runtime.sources.factory import open_clip

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


# ------------------------------------------------------------------------------------ writing
def write_plugin(folder: str | os.PathLike, manifest_fields: dict, files: dict[str, Path],
                 overwrite: bool = False) -> PluginManifest:
    """Write ``plugin.json`` into ``folder``, recording the sha256 of each file.

    manifest_fields : every manifest field except the file references.
    files : manifest field -> file path (absolute or relative to ``folder``) for ``model``,
        ``shading``, ``reference_frame``, ``noise_reference``, ``demo_clip`` (and
        ``adapted_model``). The noise reference's ``handling`` goes in
        ``manifest_fields["noise_handling"]``.
    overwrite : replace an existing manifest (otherwise an existing one is an error).
    """
    from tactile_deploy.atomic import write_json

    folder = Path(folder)
    target = folder / MANIFEST_NAME
    if target.exists() and not overwrite:
        raise PluginError(f"{target} exists; pass overwrite=True (--overwrite) to replace it")
    fields = dict(manifest_fields)
    handling = fields.pop("noise_handling")
    for key, p in files.items():
        p = Path(p)
        full = p if p.is_absolute() else folder / p
        if not full.is_file():
            raise PluginError(f"cannot write {target}: {key} file {full} does not exist")
        rel = os.path.relpath(full.resolve(), folder.resolve())
        ref = {"path": Path(rel).as_posix(), "sha256": file_sha256(full)}
        if key == "noise_reference":
            ref["handling"] = handling
        fields[key] = ref
    manifest = PluginManifest.model_validate(fields)
    write_json(target, manifest.model_dump(mode="json"))
    return manifest


def copy_plugin(name_or_path: str | os.PathLike, dest: str | os.PathLike,
                with_adapted: bool = False) -> Path:
    """Copy a plugin folder to ``dest`` (which must not exist) so that the copy works there.

    The registry names a plugin by its folder, so the copy's manifest ``name`` is set to
    ``dest``'s folder name: a copy in a folder of the original's name shadows the original once
    its parent folder is on ``$TACTILE_DEPLOY_PLUGIN_PATH`` (ahead of the original's); under
    another name it is a plugin of its own (its meshes are published on ``mesh/<new name>``),
    and a virtual default source that named no sensor keeps the original's virtual sensor.

    Files the manifest names outside the plugin folder (the shipped plugins share the family
    model and the learned read-out in ``exported/``) are recorded by absolute path in the copy's
    ``plugin.json``; files inside are copied with the folder. The adapted versions
    (``adapted/``) are left behind unless ``with_adapted``. The copy is assembled beside ``dest``
    and renamed into place only after it validates (checksums, shapes; not the model's
    contract). Returns ``dest`` as an absolute path.
    """
    from tactile_deploy.atomic import write_json

    plugin = SensorPlugin.load(name_or_path)
    dest = Path(dest).expanduser().absolute()
    if dest.exists():
        raise PluginError(f"cannot copy plugin {plugin.name!r} to {dest}: it exists; choose a new "
                          "folder (nothing there is overwritten)")
    if not dest.parent.is_dir():
        raise PluginError(f"cannot copy plugin {plugin.name!r} to {dest}: folder {dest.parent} "
                          "does not exist")
    if not re.fullmatch(_NAME, dest.name):
        raise PluginError(f"cannot copy plugin {plugin.name!r} to {dest}: the folder name is the "
                          f"copy's plugin name (field 'name'): lower case letters, digits, '-' and "
                          f"'_', starting with a letter or digit, got {dest.name!r}; choose "
                          "another folder name")
    source = plugin.folder.resolve()
    doc = json.loads((plugin.folder / MANIFEST_NAME).read_text(encoding="utf-8"))
    if dest.name != plugin.name:
        doc["name"] = dest.name
        default = doc.get("default_source", {})
        if default.get("kind") == "virtual" and not default.get("sensor"):
            default["sensor"] = plugin.name
    for key in plugin.manifest.files():
        path = plugin.path_of(key).resolve()
        if not path.is_relative_to(source):
            doc[key]["path"] = path.as_posix()
    staging = dest.parent / f".{dest.name}.copy-{os.getpid()}"
    if staging.exists():
        shutil.rmtree(staging)
    ignore = None if with_adapted else shutil.ignore_patterns("adapted")
    shutil.copytree(plugin.folder, staging, ignore=ignore)
    try:
        write_json(staging / MANIFEST_NAME, PluginManifest.model_validate(doc).model_dump(mode="json"))
        report = validate_plugin(staging, check_model=False)
        if not report.ok:
            raise PluginError(f"the copy of plugin {plugin.name!r} does not validate: "
                              + "; ".join(report.problems))
        os.replace(staging, dest)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return dest


def crop_camera_mapping(image_width_px: int, image_height_px: int, mm_per_px: float,
                        crop: tuple[int, int, int, int] | None = None,
                        mirrored: bool = False) -> CameraMapping:
    """Camera mapping of a sensor whose frames need no lens or perspective correction: a crop.

    The image (or the crop ``(x0, y0, width, height)`` px of it) is centred on the sensor
    origin, columns along +x and rows along -y (``mirrored``: rows along +y), at ``mm_per_px``;
    the imaging grid is exactly the crop's pixels, so rectification copies them.
    """
    from tactile_deploy.imaging.camera_mapping import camera_mapping_from_parameters

    x0, y0, w, h = crop if crop is not None else (0, 0, image_width_px, image_height_px)
    if not (0 <= x0 and 0 <= y0 and x0 + w <= image_width_px and y0 + h <= image_height_px
            and w >= 2 and h >= 2):
        raise ValueError(f"crop {crop} does not fit a {image_width_px}x{image_height_px} image")
    s = float(mm_per_px)
    cu = x0 + (w - 1) / 2.0
    cv = y0 + (h - 1) / 2.0
    sy = s if mirrored else -s
    hmat = [[s, 0.0, -s * cu], [0.0, sy, -sy * cv], [0.0, 0.0, 1.0]]
    k = [[float(image_width_px), 0.0, (image_width_px - 1) / 2.0],
         [0.0, float(image_width_px), (image_height_px - 1) / 2.0], [0.0, 0.0, 1.0]]
    grid = OutputGrid(x_min_mm=-w * s / 2, x_max_mm=w * s / 2, y_min_mm=-h * s / 2,
                      y_max_mm=h * s / 2, nx=w, ny=h)
    return camera_mapping_from_parameters((image_width_px, image_height_px), k, np.zeros(5),
                                          hmat, grid=grid)
