"""What produced a run's meshes: the tool, the model and the plugin, with versions and sha256
(``run.json``'s ``tool``, ``model`` and ``plugin``; :mod:`tactile_deploy.runtime.run_record`)."""

from __future__ import annotations

from pathlib import Path

from tactile_deploy.checksums import file_sha256
from tactile_deploy.runtime.plugins.manifest import MANIFEST_NAME
from tactile_deploy.runtime.plugins.versions import active_version
from tactile_deploy.runtime.run_record import ModelRecord, PluginRecord, ToolRecord
from tactile_deploy.version import DISTRIBUTION, code_sha256, library_versions, tool_version


def tool_record() -> ToolRecord:
    """This install of tactile-deploy (:mod:`tactile_deploy.version`)."""
    return ToolRecord(name=DISTRIBUTION, version=tool_version(), code_sha256=code_sha256(),
                      libraries=library_versions())


def model_record(model_path: str | Path, plugin=None, metadata: dict | None = None) -> ModelRecord:
    """The ONNX model a predictor loaded, with its contract format and training commit from its
    ``metadata`` (the ONNX metadata properties); ``adapted_version`` when it is the plugin's
    active adapted version (``tactile-deploy adapt``)."""
    path = Path(model_path).resolve()
    version = None
    if plugin is not None:
        try:
            rec = active_version(plugin.folder)
        except ValueError:
            rec = None
        if rec is not None and (plugin.folder / rec.model).resolve() == path:
            version = rec.version
    metadata = metadata or {}
    commit = metadata.get("training_commit")
    if commit and metadata.get("training_dirty") == "true":
        commit += " (dirty)"
    return ModelRecord(path=str(path), sha256=file_sha256(path), format=metadata.get("format"),
                       training_commit=commit or None, adapted_version=version)


def plugin_record(plugin) -> PluginRecord:
    """A loaded :class:`~tactile_deploy.runtime.plugins.SensorPlugin`: its manifest's sha256
    pins every file the plugin names (each by its own sha256)."""
    manifest = plugin.folder / MANIFEST_NAME
    return PluginRecord(name=plugin.name, folder=str(plugin.folder.resolve()), origin=plugin.origin,
                        format_version=plugin.manifest.format_version, manifest_sha256=file_sha256(manifest))


def run_provenance(predictor) -> dict:
    """``tool``, ``model`` and ``plugin`` of a run of ``predictor`` (a
    :class:`~tactile_deploy.runtime.predictor.MeshPredictor`, or any predictor with a
    ``model_path`` and a ``plugin``), as JSON-ready dicts; ``model`` is None when the predictor
    reads no model file."""
    plugin = getattr(predictor, "plugin", None)
    model_path = getattr(predictor, "model_path", None)
    model = None
    if model_path is not None and Path(model_path).is_file():
        metadata = getattr(predictor, "metadata", None)
        model = model_record(model_path, plugin, metadata if isinstance(metadata, dict) else None)
    return {"tool": tool_record().model_dump(mode="json"),
            "model": None if model is None else model.model_dump(mode="json"),
            "plugin": None if plugin is None else plugin_record(plugin).model_dump(mode="json")}
