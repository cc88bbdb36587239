"""What a wizard step gets (:class:`Context`) and gives back (:class:`Outcome`), and
:class:`StepError`."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from tactile_deploy.calibration.wizard.config import WizardConfig
from tactile_deploy.calibration.wizard.state import WizardState, WorkFolder
from tactile_deploy.calibration.wizard.station import Station


class StepError(RuntimeError):
    """A step could not be completed (the message says why and what to change)."""

@dataclass
class Context:
    """Everything a step needs."""
    sensor: str
    config: WizardConfig
    station: Station
    work: WorkFolder
    ui: object
    state: WizardState
    out: Path
    overwrite: bool = False
    model_path: Path | None = None


@dataclass
class Outcome:
    """What a step found: figures of merit (names carry units), pictures, notes, and extra
    actions the person may take before accepting (key, label, action returning a new Outcome)."""
    metrics: dict
    figures: list[Path]
    notes: list[str] = field(default_factory=list)
    actions: list[tuple[str, str, Callable[[], Outcome]]] = field(default_factory=list)
