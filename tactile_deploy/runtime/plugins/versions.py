"""Adapted models of a plugin, as numbered versions, and the switch between them.

Layout inside the plugin folder::

    adapted/
      history.json        every version and which one is active (:class:`AdaptationHistory`)
      v1/model.onnx       the adapted model of version 1 (+ model_fp32.onnx when the shipped graph
      v1/report.json      is int8), what the adaptation did and measured
                          (tactile_deploy.adapt.report.AdaptationReport), and its before/after
      v1/adaptation.png   figure
      v2/...

``history.json`` names the active version (with its model's sha256 and the sha256 of the family
model it was adapted from); ``tactile-deploy run`` uses it (:meth:`SensorPlugin.model_path
<tactile_deploy.runtime.plugins.loading.SensorPlugin.model_path>`), ``active: null`` = the plugin's own
model. ``plugin.json`` and every other file the plugin shipped with are never written: a shipped
plugin stays as shipped, and ``adapted/`` is the only thing added. A version is written into a
hidden temporary folder and renamed into place, then ``history.json`` is replaced atomically: an
interruption leaves the plugin on its previous model (at worst a ``v<n>/`` folder that no record
names, which a later version skips). Versions are never deleted; :func:`rollback` makes the
previous one (or the plugin's own model) active again, :func:`activate` a kept one.
"""

from __future__ import annotations

import logging
import os
import shutil
import socket
from pathlib import Path
from typing import Callable

from pydantic import Field, ValidationError, model_validator

from tactile_deploy.atomic import write_json
from tactile_deploy.checksums import file_sha256
from tactile_deploy.fileformat import StrictModel
from tactile_deploy.jsonfile import read_json

log = logging.getLogger(__name__)

ADAPTED_DIR = "adapted"
HISTORY_FILE = "history.json"
MODEL_FILE = "model.onnx"



class VersionRecord(StrictModel):
    version: int = Field(ge=1)
    model: str = Field(description="Model path relative to the plugin folder.")
    sha256: str = Field(pattern=r"^[0-9a-f]{64}$", description="sha256 of the model file.")
    family_model_sha256: str = Field(pattern=r"^[0-9a-f]{64}$",
                                     description="sha256 of the plugin's family model it was adapted from.")
    created: str = Field(description="ISO date and time (UTC).")
    heldout_rmse_before_mm: float = Field(description="Label-free RMSE on the held-out frames, family/previous model.")
    heldout_rmse_after_mm: float = Field(description="The same after adaptation.")
    summary: str = Field(description="One line: frames, steps, time.")


class AdaptationHistory(StrictModel):
    format_version: int = 1
    versions: list[VersionRecord] = Field(default_factory=list)
    active: int | None = Field(None, description="Active version, or None: the plugin's own model.")
    previous: list[int | None] = Field(default_factory=list, description="Stack of earlier active versions (rollback).")

    @model_validator(mode="after")
    def _refers_to_listed_versions(self):
        listed = [v.version for v in self.versions]
        if len(set(listed)) != len(listed):
            raise ValueError(f"field 'versions' lists a version number twice ({listed})")
        known = f"the listed versions are {', '.join(map(str, listed)) or 'none'}"
        if self.active is not None and self.active not in listed:
            raise ValueError(f"field 'active' names version {self.active}, which field 'versions' does not list "
                             f"({known}; null = the plugin's own model)")
        lost = [p for p in self.previous if p is not None and p not in listed]
        if lost:
            raise ValueError(f"field 'previous' names version {lost[0]}, which field 'versions' does not list ({known})")
        return self


class HistoryError(ValueError):
    """``adapted/history.json`` cannot be read or breaks its rules (the message says what to do)."""


def history_path(plugin) -> Path:
    return Path(plugin.folder) / ADAPTED_DIR / HISTORY_FILE


def read_history(path: str | Path) -> AdaptationHistory:
    """The history at ``path`` (none: an empty one), or :class:`HistoryError` naming the file,
    the field and the way out."""
    path = Path(path)
    if not path.is_file():
        return AdaptationHistory()
    way_out = ("restore it from a backup or correct it; or move it away, and the plugin runs its own model "
               "again (the versions stay in adapted/)")
    try:
        doc = read_json(path, HistoryError, "the adaptation history")
    except OSError as e:
        raise HistoryError(f"{path}: cannot be read ({e.strerror or e}); {way_out}") from None
    except HistoryError as e:
        raise HistoryError(f"{e}; {way_out}") from None
    try:
        return AdaptationHistory.model_validate(doc)
    except ValidationError as e:
        err = e.errors()[0]
        loc = ".".join(str(p) for p in err["loc"])
        msg = err["msg"].removeprefix("Value error, ")
        what = f"field '{loc}': {msg} (got {err.get('input')!r})" if loc else msg
        more = f" (and {e.error_count() - 1} more problems)" if e.error_count() > 1 else ""
        raise HistoryError(f"{path}: not a valid adaptation history: {what}{more}; {way_out}") from None


def load_history(plugin) -> AdaptationHistory:
    return read_history(history_path(plugin))


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
    history = read_history(Path(folder) / ADAPTED_DIR / HISTORY_FILE)
    if history.active is None:
        return None
    return next(v for v in history.versions if v.version == history.active)


def add_version(plugin, staging: Path, record: dict) -> VersionRecord:
    """Move the finished ``staging`` folder (holding ``model.onnx``) into ``adapted/v<n>``, record
    it and make it active. ``record``: the VersionRecord fields but ``version`` and ``model``."""
    root = Path(plugin.folder) / ADAPTED_DIR
    root.mkdir(exist_ok=True)
    history = load_history(plugin)
    if not (staging / MODEL_FILE).is_file():
        raise FileNotFoundError(f"{staging} holds no {MODEL_FILE}")
    n = max([v.version for v in history.versions] + [0]) + 1
    while (root / f"v{n}").exists():  # a folder left by an interrupted run: never overwrite it
        n += 1
    rec = VersionRecord(version=n, model=f"{ADAPTED_DIR}/v{n}/{MODEL_FILE}", sha256=file_sha256(staging / MODEL_FILE),
                        family_model_sha256=plugin.manifest.model.sha256, **record)
    history = AdaptationHistory(versions=[*history.versions, rec], active=n,
                                previous=[*history.previous, history.active])
    target = root / f"v{n}"
    os.replace(staging, target)  # everything is checked and computed: only the rename and the history remain
    try:
        write_json(history_path(plugin), history.model_dump(mode="json"))
    except OSError:
        os.replace(target, staging)  # no version folder that the history does not name
        raise
    return rec


def staging_folder(plugin) -> Path:
    """A fresh hidden folder inside ``adapted/`` for a version being written (those left by runs
    that were killed are removed)."""
    root = Path(plugin.folder) / ADAPTED_DIR
    root.mkdir(exist_ok=True)
    host = socket.gethostname()
    for old in root.glob(f".staging-{host}-*"):  # only this machine's: the folder may be shared
        pid = old.name.removeprefix(f".staging-{host}-")
        if pid.isdigit() and int(pid) != os.getpid() and not _running(int(pid)):
            shutil.rmtree(old, ignore_errors=True)
    path = root / f".staging-{host}-{os.getpid()}"
    if path.exists():
        shutil.rmtree(path)
    path.mkdir()
    return path


def _usable(plugin, rec: VersionRecord) -> str | None:
    """Why version ``rec`` cannot be made active (its model file is missing or changed), or None."""
    path = Path(plugin.folder) / rec.model
    if not path.is_file():
        return f"lost its model file {rec.model}"
    if file_sha256(path) != rec.sha256:
        return f"model file {rec.model} no longer matches its sha256 in {HISTORY_FILE}"
    return None


def _running(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):
        return True
    return True


def rollback(plugin, dry_run: bool = False,
             warn: Callable[[str], None] | None = None) -> tuple[int | None, int | None]:
    """Make the previously active version (or the plugin's own model) active again; returns
    ``(from_version, to_version)`` (None = the plugin's own model). The files stay. Earlier
    versions whose model file is missing or changed are skipped (``warn`` says which).
    ``dry_run``: only say what it would do."""
    warn = warn or log.warning
    history = load_history(plugin)
    if history.active is None and not history.previous:
        raise ValueError(f"plugin {plugin.name!r} runs its own model and has no earlier adapted version to "
                         "roll back to")
    by_version = {v.version: v for v in history.versions}
    stack = list(history.previous)
    to = stack.pop() if stack else None
    while to is not None:
        problem = _usable(plugin, by_version[to])
        if problem is None and by_version[to].family_model_sha256 != plugin.manifest.model.sha256:
            problem = "was adapted from another family model than the plugin's (run would ignore it)"
        if problem is None:
            break
        warn(f"version {to} of plugin {plugin.name!r} {problem}: skipped, going back further")
        to = stack.pop() if stack else None
    if not dry_run:
        new = AdaptationHistory(versions=history.versions, active=to, previous=stack)
        write_json(history_path(plugin), new.model_dump(mode="json"))
    return history.active, to


def activate(plugin, version: int, dry_run: bool = False) -> tuple[int | None, int]:
    """Make kept ``version`` active again, after checking its model file (sha256) and that it was
    adapted from the plugin's current family model; recorded like a new version, so that
    :func:`rollback` returns to the one active before. Returns ``(from_version, version)``."""
    history = load_history(plugin)
    path = history_path(plugin)
    kept = ", ".join(str(v.version) for v in history.versions) or "none"
    rec = next((v for v in history.versions if v.version == version), None)
    if rec is None:
        raise ValueError(f"{path} lists no version {version} (kept versions: {kept}); give one of them")
    problem = _usable(plugin, rec)
    if problem is not None:
        raise ValueError(f"version {version} of plugin {plugin.name!r} {problem}; restore the file, or activate "
                         f"another version (kept: {kept})")
    if rec.family_model_sha256 != plugin.manifest.model.sha256:
        raise ValueError(f"version {version} of plugin {plugin.name!r} was adapted from another family model "
                         f"(sha256 {rec.family_model_sha256[:12]}..., the plugin's model now has "
                         f"{plugin.manifest.model.sha256[:12]}...); adapt again for this model")
    if history.active == version or dry_run:
        return history.active, version
    new = AdaptationHistory(versions=history.versions, active=version, previous=[*history.previous, history.active])
    write_json(path, new.model_dump(mode="json"))
    return history.active, version
