"""The wizard's work folder: what each step produced, so that a run can stop and resume.

``WORK/state.json`` (:class:`WizardState`) lists the steps done, their figures of merit and
figures; each step's data sits beside it (``WORK/<step>.npz``, ``WORK/camera_mapping.json``,
``WORK/shading.npz``, ``WORK/figures/*.png``). Every file is written atomically and the state
last, so an interruption at any moment leaves the previous consistent state: the interrupted
step is simply not done.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
from pathlib import Path
from typing import Literal

from pydantic import ConfigDict, Field, ValidationError

from tactile_deploy.atomic import write_json
from tactile_deploy.fileformat import StrictModel

STATE_NAME = "state.json"
FORMAT_VERSION = 1

#: The wizard's steps, in order.
STEPS = ("reference", "camera", "presses", "shading", "fem", "plugin", "discrepancy")

#: One line per step, for prompts and the report.
STEP_TITLES = {
    "reference": "reference frame (nothing touching the sensor)",
    "camera": "camera mapping (calibration target)",
    "presses": "ball presses (contact circles)",
    "shading": "shading model (colour -> gradients -> depth)",
    "fem": "FEM material (nu from depth maps, E from forces)",
    "plugin": "plugin folder and calibration report",
    "discrepancy": "the unit's sensor model, and rig presses for the discrepancy workflow",
}

Metric = float | int | str | None   # None: not measured (NaN is stored as null)


class WizardStateError(ValueError):
    """The work folder's state file is unreadable or belongs to another calibration."""


class StepRecord(StrictModel):
    """What one finished step produced."""

    model_config = ConfigDict(frozen=False, allow_inf_nan=True)  # NaN: not measured

    finished: str = Field(description="ISO time the step was accepted.")
    metrics: dict[str, Metric] = Field(default_factory=dict,
                                       description="Figures of merit (names carry units).")
    figures: list[str] = Field(default_factory=list,
                               description="Figure files, relative to the work folder.")
    notes: list[str] = Field(default_factory=list, description="What the step reported.")


class WizardState(StrictModel):
    """``state.json``: the calibration in progress."""

    model_config = ConfigDict(frozen=False)  # the wizard records its progress in it

    format_version: Literal[1] = FORMAT_VERSION
    sensor: str = Field(description="Name of the plugin being made.")
    source: str = Field(description="Frame source the frames come from (--source).")
    rig: str | None = Field(None, description="Rig used (--rig), or None for hand presses.")
    config: dict = Field(description="The wizard config the steps were run with.")
    started: str = Field(description="ISO time the calibration started.")
    steps: dict[str, StepRecord] = Field(default_factory=dict, description="Finished steps.")
    plugin_written: str | None = Field(None, description="Plugin folder this calibration wrote "
                                       "(a redo may replace it without --overwrite).")

    def done(self, step: str) -> bool:
        return step in self.steps

    def first_pending(self) -> str | None:
        return next((s for s in STEPS if s not in self.steps), None)


def now_iso() -> str:
    return _dt.datetime.now().isoformat(timespec="seconds")


class WorkFolder:
    """The work folder of one calibration and its state."""

    def __init__(self, folder: str | os.PathLike):
        self.folder = Path(folder)
        self.figures = self.folder / "figures"

    @property
    def state_path(self) -> Path:
        return self.folder / STATE_NAME

    def exists(self) -> bool:
        return self.state_path.is_file()

    def path(self, name: str) -> Path:
        return self.folder / name

    def create(self, state: WizardState) -> WizardState:
        self.folder.mkdir(parents=True, exist_ok=True)
        self.figures.mkdir(exist_ok=True)
        self.save(state)
        return state

    def load(self) -> WizardState:
        try:
            doc = json.loads(self.state_path.read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError) as e:
            raise WizardStateError(f"{self.state_path}: unreadable ({e}); remove the folder or "
                                   "pass --restart to start over") from None
        if not isinstance(doc, dict) or doc.get("format_version") != FORMAT_VERSION:
            raise WizardStateError(f"{self.state_path}: field 'format_version': expected "
                                   f"{FORMAT_VERSION}, got {doc.get('format_version')!r}; pass "
                                   "--restart to start over")
        try:
            state = WizardState.model_validate(doc)
        except ValidationError as e:
            raise WizardStateError(f"{self.state_path}: invalid state ({e.errors()[0]['msg']} at "
                                   f"{'.'.join(map(str, e.errors()[0]['loc']))}); pass --restart "
                                   "to start over") from None
        self.figures.mkdir(exist_ok=True)
        return state

    def save(self, state: WizardState) -> None:
        write_json(self.state_path, json.loads(state.model_dump_json()))

    def finish(self, state: WizardState, step: str, metrics: dict, figures: list[Path],
               notes: list[str]) -> None:
        """Record ``step`` as done (figures relative to the folder) and save the state."""
        rel = [str(Path(f).resolve().relative_to(self.folder.resolve())) for f in figures]
        state.steps[step] = StepRecord(finished=now_iso(), metrics=metrics, figures=rel,
                                       notes=notes)
        self.save(state)

    def forget_from(self, state: WizardState, step: str) -> list[str]:
        """Mark ``step`` and every later step as not done; returns the steps forgotten."""
        k = STEPS.index(step)
        gone = [s for s in STEPS[k:] if s in state.steps]
        for s in gone:
            del state.steps[s]
        self.save(state)
        return gone
