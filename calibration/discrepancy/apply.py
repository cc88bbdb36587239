"""Write a found effect into the sensor model, versioned.

The sensor model is the virtual sensor's JSON (``tactile_deploy.sensors``: pad, material,
optics, effects). Applying an effect replaces an effect of the same name or appends it, and
writes the new JSON atomically. Every version is kept beside it::

    gelslim2.json                 the current model (what --sensor ./gelslim2.json loads)
    gelslim2.versions/
      v1.json, v2.json, ...        every version, the current one included
      history.json                 version, file, sha256, time, what changed and why

A shipped sensor (given by name) is never changed in place: its model is copied to
``<name>.json`` in the chosen folder (version 1 = the shipped model) and the effect goes into
the copy. A version file is never overwritten: a new version takes the next number whose file
does not exist (files left by an earlier history, or by an interrupted run, are kept).
"""

from __future__ import annotations

import datetime as dt
import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from pydantic import Field, ValidationError

from tactile_deploy.atomic import write_json, write_text
from tactile_deploy.fileformat import StrictModel
from tactile_deploy.jsonfile import validation_error_text
from tactile_deploy.sensors.config import (
    EffectSpec,
    SensorConfigError,
    VirtualSensorConfig,
    load_sensor_config,
)

HISTORY_FORMAT = 1


class ModelVersion(StrictModel):
    """One version of a sensor model in its history."""

    version: int = Field(ge=1, description="Version number (the file's, vN.json).")
    file: str = Field(description="The version's file, relative to the versions folder.")
    sha256: str = Field(pattern=r"^[0-9a-f]{64}$", description="SHA-256 of the file's text.")
    created: str = Field(description="When it was written, ISO 8601 UTC.")
    change: str = Field(description="What changed (the effect added and its parameters).")
    reason: dict[str, Any] | None = Field(None, description="Why: the discrepancy verdict's "
                                          "numbers and the measured data (path, SHA-256).")


class SensorModelHistory(StrictModel):
    """``<model>.versions/history.json``: every version of a sensor model, oldest first."""

    format_version: Literal[1] = HISTORY_FORMAT
    sensor: str = Field(description="The sensor model's name.")
    current: str = Field(description="The current model's file name (beside the folder).")
    versions: list[ModelVersion]


@dataclass(frozen=True)
class AppliedModel:
    """path : the current model file; version : its version number; previous : the file of the
    version before it; history : the history file."""

    path: Path
    version: int
    previous: Path
    history: Path


def with_effect(config: VirtualSensorConfig, spec: EffectSpec) -> VirtualSensorConfig:
    """``config`` with ``spec`` replacing its effect of the same name, or appended."""
    effects = [e for e in config.effects if e.name != spec.name] + [spec]
    return VirtualSensorConfig.model_validate({**config.model_dump(), "effects": [
        e.model_dump() for e in effects]})


def _sha256(text: str) -> str:
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def _history(history_path: Path) -> list[dict]:
    """The version entries of ``history_path`` ([] when it does not exist)."""
    if not history_path.exists():
        return []
    advice = ("restore it, or move it away to start a new history (the version files beside it "
              "are kept; new versions take the next free numbers)")
    try:
        doc = json.loads(history_path.read_text(encoding="utf-8"))
        history = SensorModelHistory.model_validate(doc)
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise SensorConfigError(f"{history_path}: not a version history ({e}); {advice}") from None
    except ValidationError as e:
        raise SensorConfigError(validation_error_text(history_path, e, "version history", advice)
                                ) from None
    return [v.model_dump() for v in history.versions]


def _next_version(versions: Path, entries: list[dict]) -> int:
    """The next version number after ``entries`` whose file does not exist yet in ``versions``."""
    k = max([int(e["version"]) for e in entries] + [0]) + 1
    while (versions / f"v{k}.json").exists():  # never overwrite a version file
        k += 1
    return k


def check_target(sensor: str, config: VirtualSensorConfig, folder: Path | None = None) -> Path:
    """The model file that :func:`apply_effect` writes for ``sensor``, checked before any work:
    its folder exists, a shipped sensor's copy does not exist yet, the version history (if any)
    is readable. Raises FileNotFoundError, FileExistsError or SensorConfigError."""
    is_path = sensor.endswith(".json")
    target = Path(sensor) if is_path else Path(folder or ".") / f"{config.name}.json"
    if not target.parent.is_dir():
        raise FileNotFoundError(f"cannot write the sensor model {target}: folder "
                                f"{target.parent} does not exist; create it, or choose another "
                                "--model-dir")
    if target.exists() and not is_path:
        raise FileExistsError(f"{target} exists already: pass it as --sensor {target} to add the "
                              "effect to that model, or choose another folder")
    versions = target.with_name(f"{target.stem}.versions")
    if versions.exists() and not versions.is_dir():
        raise FileExistsError(f"{versions} is a file: the versions of {target.name} go into a "
                              "folder of that name; move the file away")
    _history(versions / "history.json")
    return target


def apply_effect(sensor: str, config: VirtualSensorConfig, spec: EffectSpec, reason: dict,
                 folder: Path | None = None) -> AppliedModel:
    """Write ``config`` + ``spec`` as the next version of the model ``sensor``.

    sensor : a model JSON path (changed in place, its versions kept beside it) or a shipped
    name (copied to ``folder / <name>.json``, default the current folder). reason : what the
    history records (verdict numbers, measured data).
    """
    is_path = sensor.endswith(".json")
    target = check_target(sensor, config, folder)
    versions = target.with_name(f"{target.stem}.versions")
    history_path = versions / "history.json"
    versions.mkdir(exist_ok=True)
    entries = _history(history_path)
    now = dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds")
    current_text = config.model_dump_json(indent=2) + "\n"
    if is_path:
        on_disk = load_sensor_config(target).model_dump_json(indent=2) + "\n"
        if on_disk != current_text:
            raise SensorConfigError(f"{target} changed since it was read; run the workflow again")
    if not entries or entries[-1]["sha256"] != _sha256(current_text):
        k = _next_version(versions, entries)
        name = f"v{k}.json"
        write_text(versions / name, current_text)
        entries.append({"version": k, "file": name, "sha256": _sha256(current_text),
                        "created": now, "change": ("the model before the discrepancy workflow"
                                                   if is_path else
                                                   f"shipped sensor {sensor!r}")})
    previous = versions / entries[-1]["file"]
    new = with_effect(config, spec)
    new_text = new.model_dump_json(indent=2) + "\n"
    k = _next_version(versions, entries)
    name = f"v{k}.json"
    write_text(versions / name, new_text)
    entries.append({"version": k, "file": name, "sha256": _sha256(new_text), "created": now,
                    "change": f"effect {spec.name} {json.dumps(spec.params)}", "reason": reason})
    history = SensorModelHistory(sensor=config.name, current=target.name,
                                 versions=[ModelVersion.model_validate(e) for e in entries])
    write_json(history_path, history.model_dump(mode="json"))
    write_text(target, new_text)
    return AppliedModel(target, k, previous, history_path)
