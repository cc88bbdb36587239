"""Sensor plugins: one folder per sensor with a strict JSON manifest, and the registry that finds
them.

One job per module:

- :mod:`.manifest`: ``plugin.json`` (:class:`PluginManifest`), reading and validating it;
- :mod:`.discovery`: where plugins are found (search path, entry points, shipped) and the code
  hooks an installed package may add;
- :mod:`.loading`: :class:`SensorPlugin`, a loaded plugin whose files are checked against their
  sha256 when read;
- :mod:`.validation`: :func:`validate_plugin`, every check including the ONNX model contract;
- :mod:`.writing`: :func:`write_plugin` and :func:`copy_plugin`;
- :mod:`.versions`: the adapted models of a plugin (``adapted/history.json``).

The names below are the public API; import them from here.
"""

from __future__ import annotations

from tactile_deploy.runtime.plugins.discovery import (
    ENTRY_POINT_GROUP,
    PLUGIN_PATH_ENV,
    PluginEntry,
    PluginHooks,
    PluginLocation,
    discover_plugins,
    find_plugin,
    search_path,
)
from tactile_deploy.runtime.plugins.loading import SensorPlugin
from tactile_deploy.runtime.plugins.manifest import (
    FORMAT_VERSION,
    MANIFEST_NAME,
    MODEL_GRID,
    FamilySpec,
    FileRef,
    MaterialSpec,
    NoiseReferenceSpec,
    PluginError,
    PluginManifest,
    load_manifest,
)
from tactile_deploy.runtime.plugins.validation import ValidationReport, validate_plugin
from tactile_deploy.runtime.plugins.writing import copy_plugin, write_plugin

__all__ = [
    "ENTRY_POINT_GROUP", "FORMAT_VERSION", "MANIFEST_NAME", "MODEL_GRID", "PLUGIN_PATH_ENV",
    "FamilySpec", "FileRef", "MaterialSpec", "NoiseReferenceSpec", "PluginEntry", "PluginError",
    "PluginHooks", "PluginLocation", "PluginManifest", "SensorPlugin", "ValidationReport",
    "copy_plugin", "discover_plugins", "find_plugin", "load_manifest",
    "search_path", "validate_plugin", "write_plugin",
]
