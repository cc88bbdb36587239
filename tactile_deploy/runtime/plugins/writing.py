"""Writing a plugin folder's manifest (checksums recorded) and copying a plugin so that the copy
works where it lands."""

from __future__ import annotations

import json
import os
import re
import shutil
from pathlib import Path

from tactile_deploy.atomic import write_json
from tactile_deploy.checksums import file_sha256
from tactile_deploy.runtime.plugins.loading import SensorPlugin
from tactile_deploy.runtime.plugins.manifest import (
    MANIFEST_NAME,
    NAME_PATTERN,
    PluginError,
    PluginManifest,
)
from tactile_deploy.runtime.plugins.validation import validate_plugin


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
                with_adapted: bool = False, model: str | os.PathLike | None = None) -> Path:
    """Copy a plugin folder to ``dest`` (which must not exist) so that the copy works there.

    The registry names a plugin by its folder, so the copy's manifest ``name`` is set to
    ``dest``'s folder name: a copy in a folder of the original's name shadows the original once
    its parent folder is on ``$TACTILE_DEPLOY_PLUGIN_PATH`` (ahead of the original's); under
    another name it is a plugin of its own (its meshes are published on ``mesh/<new name>``),
    and a virtual default source that named no sensor keeps the original's virtual sensor.

    Files the manifest names outside the plugin folder (the shipped plugins share the family
    model and the learned read-out in ``exported/``) are recorded by absolute path in the copy's
    ``plugin.json``; files inside are copied with the folder. The adapted versions
    (``adapted/``) are left behind unless ``with_adapted``.

    ``model``: an ONNX family model for the copy to run instead of the original's (recorded by
    absolute path and sha256; e.g. ``exported/gelslim_mesh_grip.onnx``, the graph for gels that
    grip); the original's adapted versions belong to the original's model and are not carried
    over (``with_adapted`` is refused with it), and the copy then validates with the model's
    contract (its pad and node count must be the plugin's). The copy is assembled beside ``dest``
    and renamed into place only after it validates (checksums, shapes; the model's contract too
    when ``model`` is given). Returns ``dest`` as an absolute path.
    """
    plugin = SensorPlugin.load(name_or_path)
    new_model = None
    if model is not None:
        new_model = Path(model).expanduser().absolute()
        if not new_model.is_file():
            raise PluginError(f"cannot copy plugin {plugin.name!r} with model {new_model}: no such file; "
                              "give an ONNX family model, e.g. exported/gelslim_mesh_grip.onnx")
        if with_adapted:
            raise PluginError(f"cannot copy plugin {plugin.name!r} with another model and its adapted "
                              "versions: they were adapted from its own model; leave out --with-adapted "
                              "(adapt the copy with `tactile-deploy adapt`)")
    dest = Path(dest).expanduser().absolute()
    if dest.exists():
        raise PluginError(f"cannot copy plugin {plugin.name!r} to {dest}: it exists; choose a new "
                          "folder (nothing there is overwritten)")
    if not dest.parent.is_dir():
        raise PluginError(f"cannot copy plugin {plugin.name!r} to {dest}: folder {dest.parent} "
                          "does not exist")
    if not re.fullmatch(NAME_PATTERN, dest.name):
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
    if new_model is not None:
        doc["model"] = {"path": new_model.as_posix(), "sha256": file_sha256(new_model)}
        doc["adapted_model"] = None
    staging = dest.parent / f".{dest.name}.copy-{os.getpid()}"
    if staging.exists():
        shutil.rmtree(staging)
    ignore = None if with_adapted else shutil.ignore_patterns("adapted")
    shutil.copytree(plugin.folder, staging, ignore=ignore)
    try:
        write_json(staging / MANIFEST_NAME, PluginManifest.model_validate(doc).model_dump(mode="json"))
        report = validate_plugin(staging, check_model=new_model is not None)
        if not report.ok:
            raise PluginError(f"the copy of plugin {plugin.name!r} does not validate: "
                              + "; ".join(report.problems))
        os.replace(staging, dest)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return dest
