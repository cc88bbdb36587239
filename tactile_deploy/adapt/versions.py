"""Adapted models of a plugin, as numbered versions, and the switch between them.

Layout inside the plugin folder::

    adapted/
      history.json        every version and which one is active (:class:`AdaptationHistory`)
      v1/model.onnx       the adapted model of version 1 (+ model_fp32.onnx when the shipped graph
      v1/report.json      is int8), what the adaptation did and measured, and its before/after
      v1/adaptation.png   figure
      v2/...

``history.json`` names the active version (with its model's sha256 and the sha256 of the family
model it was adapted from); ``tactile-deploy run`` uses it (:meth:`SensorPlugin.model_path
<tactile_deploy.runtime.plugins.SensorPlugin.model_path>`), ``active: null`` = the plugin's own
model. ``plugin.json`` and every other file the plugin shipped with are never written: a shipped
plugin stays as shipped, and ``adapted/`` is the only thing added. A version is written into a
hidden temporary folder and renamed into place, then ``history.json`` is replaced atomically: an
interruption leaves the plugin on its previous model. Versions are never deleted;
:func:`rollback` makes the previous one (or the plugin's own model) active again.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

from pydantic import BaseModel, ConfigDict, Field

from tactile_deploy.atomic import write_json

ADAPTED_DIR = "adapted"
HISTORY_FILE = "history.json"
MODEL_FILE = "model.onnx"

_STRICT = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class VersionRecord(BaseModel):
    model_config = _STRICT

    version: int = Field(ge=1)
    model: str = Field(description="Model path relative to the plugin folder.")
    sha256: str = Field(pattern=r"^[0-9a-f]{64}$", description="sha256 of the model file.")
    family_model_sha256: str = Field(pattern=r"^[0-9a-f]{64}$",
                                     description="sha256 of the plugin's family model it was adapted from.")
    created: str = Field(description="ISO date and time (UTC).")
    heldout_rmse_before_mm: float = Field(description="Label-free RMSE on the held-out frames, family/previous model.")
    heldout_rmse_after_mm: float = Field(description="The same after adaptation.")
    summary: str = Field(description="One line: frames, steps, time.")


class AdaptationHistory(BaseModel):
    model_config = _STRICT

    format_version: int = 1
    versions: list[VersionRecord] = Field(default_factory=list)
    active: int | None = Field(None, description="Active version, or None: the plugin's own model.")
    previous: list[int | None] = Field(default_factory=list, description="Stack of earlier active versions (rollback).")


def history_path(plugin) -> Path:
    return Path(plugin.folder) / ADAPTED_DIR / HISTORY_FILE


def load_history(plugin) -> AdaptationHistory:
    path = history_path(plugin)
    if not path.is_file():
        return AdaptationHistory()
    return AdaptationHistory.model_validate(json.loads(path.read_text(encoding="utf-8")))


def check_writable(plugin) -> None:
    """Refuse early, with what to do, when versions cannot be written into the plugin folder."""
    folder = Path(plugin.folder)
    root = folder / ADAPTED_DIR
    probe = root if root.is_dir() else folder
    if not os.access(probe, os.W_OK):
        raise PermissionError(
            f"cannot write adapted versions into {probe} (read-only); copy the plugin to a writable "
            f"place (`tactile-deploy plugins copy {plugin.name} DIR/{plugin.name}`) and put DIR on "
            "$TACTILE_DEPLOY_PLUGIN_PATH (the copy, of the same name, then shadows this one), or pass "
            "--dry-run to measure only")


def active_version(folder: str | Path) -> VersionRecord | None:
    """The active version recorded in ``folder/adapted/history.json``, or None."""
    path = Path(folder) / ADAPTED_DIR / HISTORY_FILE
    if not path.is_file():
        return None
    try:
        history = AdaptationHistory.model_validate(json.loads(path.read_text(encoding="utf-8")))
    except (ValueError, OSError) as e:
        raise ValueError(f"{path}: not a valid adaptation history ({e}); restore it from a backup, or move it "
                         "away to run the plugin's own model") from None
    if history.active is None:
        return None
    return next(v for v in history.versions if v.version == history.active)


def add_version(plugin, staging: Path, record: dict) -> VersionRecord:
    """Move the finished ``staging`` folder (holding ``model.onnx``) into ``adapted/v<n>``, record
    it and make it active. ``record``: the VersionRecord fields but ``version`` and ``model``."""
    root = Path(plugin.folder) / ADAPTED_DIR
    root.mkdir(exist_ok=True)
    history = load_history(plugin)
    n = max([v.version for v in history.versions] + [0]) + 1
    while (root / f"v{n}").exists():  # a folder left by an interrupted run: never overwrite it
        n += 1
    if not (staging / MODEL_FILE).is_file():
        raise FileNotFoundError(f"{staging} holds no {MODEL_FILE}")
    target = root / f"v{n}"
    os.replace(staging, target)
    from tactile_deploy.runtime.plugins import file_sha256

    rec = VersionRecord(version=n, model=f"{ADAPTED_DIR}/v{n}/{MODEL_FILE}", sha256=file_sha256(target / MODEL_FILE),
                        family_model_sha256=plugin.manifest.model.sha256, **record)
    history = AdaptationHistory(versions=[*history.versions, rec], active=n,
                                previous=[*history.previous, history.active])
    write_json(history_path(plugin), history.model_dump(mode="json"))
    return rec


def staging_folder(plugin) -> Path:
    """A fresh hidden folder inside ``adapted/`` for a version being written."""
    root = Path(plugin.folder) / ADAPTED_DIR
    root.mkdir(exist_ok=True)
    path = root / f".staging-{os.getpid()}"
    if path.exists():
        shutil.rmtree(path)
    path.mkdir()
    return path


def rollback(plugin) -> tuple[int | None, int | None]:
    """Make the previously active version (or the plugin's own model) active again; returns
    ``(from_version, to_version)`` (None = the plugin's own model). The files stay."""
    history = load_history(plugin)
    if history.active is None and not history.previous:
        raise ValueError(f"plugin {plugin.name!r} runs its own model and has no earlier adapted version to "
                         "roll back to")
    to = history.previous[-1] if history.previous else None
    by_version = {v.version: v for v in history.versions}
    if to is not None and not (Path(plugin.folder) / by_version[to].model).is_file():
        raise FileNotFoundError(f"version {to} of plugin {plugin.name!r} lost its model file "
                                f"{by_version[to].model}; restore it or adapt again")
    new = AdaptationHistory(versions=history.versions, active=to, previous=history.previous[:-1])
    write_json(history_path(plugin), new.model_dump(mode="json"))
    return history.active, to
