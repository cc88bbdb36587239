"""Rig presses recorded as measured data: the input of the discrepancy workflow from a real unit.

Data flow of :func:`collect_presses` (``tactile-deploy rig collect``)::

    plan: commanded contacts (x_mm, y_mm, depth_mm; sensor frame), an indenter, its angle
      -> reference frames with the rig retracted (nothing touching the sensor)
      -> per contact: the rig presses (tare, approach in steps, force limit), and with the
         indenter held at full depth the camera's frames are grabbed and the gauge read
      -> frames (and, with the unit's plugin, its depth maps), the commanded contacts, the
         forces, one contact id per press
      -> the measured-data .npz of :mod:`tactile_deploy.calibration.discrepancy.measured` (plus the rig's own
         record of every press, ``rig_log``: a :class:`CollectionLog` as JSON)

A press the force limit stopped is not recorded (no frame at a known depth); the log says which.
The noise of the plugin's depth maps is measured on the reference frames (their spread about
their mean, one sigma, mm) and stored as ``noise_mm``.

Plans come from :func:`plan_contacts` (uniform over a disc, depths uniform in a range) or a CSV
file with columns ``x_mm, y_mm, depth_mm`` (:func:`load_plan`).
"""

from __future__ import annotations

import csv
import math
from collections.abc import Callable
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import ConfigDict, Field

from tactile_deploy.calibration.rig.indent import PressRecord, check_press_depth
from tactile_deploy.fileformat import STRICT, StrictModel

#: Version of :class:`CollectionLog`.
LOG_FORMAT_VERSION = 1


#: The strict base, with no type coercion either (a string where a number goes is refused).
_NO_COERCION = ConfigDict(**STRICT, strict=True)


class PlannedContact(StrictModel):
    """One commanded contact, sensor frame."""

    model_config = _NO_COERCION

    x_mm: float = Field(description="Contact x, sensor frame, mm.")
    y_mm: float = Field(description="Contact y, sensor frame, mm.")
    depth_mm: float = Field(gt=0.0, description="Depth below the gel surface, mm.")


class CollectionLog(StrictModel):
    """The rig's record of a collection (stored in the .npz as ``rig_log``, JSON)."""

    model_config = _NO_COERCION

    format_version: Literal[1] = LOG_FORMAT_VERSION
    indenter: str = Field(description="Indenter pressed: library name or mesh path.")
    theta_deg: float = Field(description="The indenter's angle about z, sensor frame, degrees.")
    source: str = Field(description="Frame source the frames came from.")
    plugin: str | None = Field(description="Plugin whose imaging pipeline made the depth maps.")
    frames_per_press: int = Field(ge=1, description="Frames grabbed per press.")
    reference_frames: int = Field(ge=0, description="No-contact frames grabbed first.")
    noise_mm: float | None = Field(description="Depth noise of one pixel measured on the "
                                   "reference frames, mm (one sigma).")
    presses: list[PressRecord] = Field(description="Every press, in order (recorded or not).")
    recorded: list[int] = Field(description="Indices into presses of the recorded ones.")


def plan_contacts(n: int, radius_mm: float, depth_range_mm: tuple[float, float],
                  seed: int = 0) -> list[PlannedContact]:
    """``n`` contacts uniform over a disc of ``radius_mm`` about the sensor's centre, depths
    uniform in ``depth_range_mm`` (mm)."""
    lo, hi = depth_range_mm
    if not 0 < lo <= hi:
        raise ValueError(f"depth range {depth_range_mm} mm: expected 0 < min <= max")
    check_press_depth(hi)
    if n < 1 or radius_mm < 0:
        raise ValueError(f"need n >= 1 and radius_mm >= 0, got n={n}, radius_mm={radius_mm}")
    rng = np.random.default_rng([seed, 0x636F6C6C])
    out = []
    for _ in range(n):
        r = radius_mm * math.sqrt(rng.uniform())
        a = rng.uniform(0.0, 2.0 * math.pi)
        out.append(PlannedContact(x_mm=float(r * math.cos(a)), y_mm=float(r * math.sin(a)),
                                  depth_mm=float(rng.uniform(lo, hi))))
    return out


def load_plan(path: str | Path) -> list[PlannedContact]:
    """Contacts from a CSV file with columns ``x_mm, y_mm, depth_mm`` (sensor frame, mm)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"plan {path} not found: a CSV file with columns x_mm, y_mm, "
                                "depth_mm")
    with open(path, newline="", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    if not rows:
        raise ValueError(f"{path}: no contacts (the header alone, or empty)")
    missing = {"x_mm", "y_mm", "depth_mm"} - set(rows[0])
    if missing:
        raise ValueError(f"{path}: column(s) {', '.join(sorted(missing))} missing; expected "
                         "x_mm, y_mm, depth_mm (sensor frame, mm)")
    out = []
    for k, row in enumerate(rows):
        try:
            values = {c: float(row[c]) for c in ("x_mm", "y_mm", "depth_mm")}
        except (TypeError, ValueError):
            raise ValueError(f"{path}, row {k + 2}: x_mm, y_mm and depth_mm must be numbers, "
                             f"got {[row.get(c) for c in ('x_mm', 'y_mm', 'depth_mm')]}") from None
        if not values["depth_mm"] > 0:
            raise ValueError(f"{path}, row {k + 2}: depth_mm must be > 0 (into the gel), got "
                             f"{values['depth_mm']}")
        try:
            check_press_depth(values["depth_mm"])
        except ValueError as e:
            raise ValueError(f"{path}, row {k + 2}: {e}") from None
        out.append(PlannedContact(**values))
    return out


def collect_presses(rig, grab: Callable[[int], np.ndarray], plan: list[PlannedContact],
                    indenter: str, *, theta_deg: float = 0.0, frames_per_press: int = 1,
                    reference_frames: int = 8, pipeline=None, source: str = "",
                    plugin: str | None = None, keep_frames: bool = True,
                    retract: Callable[[], None] | None = None, progress=None):
    """Press every planned contact with ``rig`` (an :class:`~tactile_deploy.calibration.rig.IndentationRig`,
    connected and homed) and grab ``frames_per_press`` frames with ``grab(n) -> (n, H, W, 3)
    uint8`` at each; ``pipeline`` (``frame_to_depth``) adds depth maps. Returns
    ``(MeasuredData, CollectionLog)`` (module docstring). ``progress(k)`` after each press."""
    from tactile_deploy.calibration.discrepancy.measured import MeasuredData

    if frames_per_press < 1:
        raise ValueError(f"frames_per_press must be >= 1, got {frames_per_press}")
    if not keep_frames and pipeline is None:
        raise ValueError("without frames the depth maps must come from a plugin: give one, or "
                         "keep the frames")
    (retract or rig.retract)()
    noise = None
    if reference_frames > 0 and pipeline is not None:
        ref = grab(reference_frames)
        maps = np.stack([np.asarray(pipeline.frame_to_depth(f), np.float64) for f in ref])
        if reference_frames >= 2:
            noise = float(np.sqrt(np.mean(np.var(maps, axis=0, ddof=1))))
    records, recorded, frames, depths, ids = [], [], [], [], []
    for k, c in enumerate(plan):
        held = []
        rec = rig.press(c.x_mm, c.y_mm, c.depth_mm,
                        on_pressed=lambda r: held.append(grab(frames_per_press)))
        records.append(rec)
        if not rec.force_limited and held:
            recorded.append(k)
            for f in held[0]:
                frames.append(f)
                ids.append(k)
                if pipeline is not None:
                    depths.append(np.asarray(pipeline.frame_to_depth(f), np.float32))
        if progress is not None:
            progress(1)
    if not recorded:
        raise ValueError(f"no press was recorded: all {len(plan)} stopped at the rig's force "
                         "limit; press less deep or raise force_limit_n")
    n = len(ids)
    by_press = {k: records[k] for k in recorded}
    rows = [by_press[i] for i in ids]
    log = CollectionLog(indenter=indenter, theta_deg=float(theta_deg), source=source,
                        plugin=plugin, frames_per_press=frames_per_press,
                        reference_frames=reference_frames, noise_mm=noise, presses=records,
                        recorded=recorded)
    data = MeasuredData(
        depth_mm=np.stack(depths) if depths else None,
        frames=np.stack(frames) if keep_frames else None,
        indenter=[indenter] * n,
        x_mm=np.array([r.x_mm for r in rows]), y_mm=np.array([r.y_mm for r in rows]),
        theta_deg=np.full(n, float(theta_deg)),
        depth_cmd_mm=np.array([r.depth_mm for r in rows]),
        force_n=np.array([max(r.force_n, 0.0) for r in rows]),
        contact_id=np.array(ids, np.int64),
        noise_mm=noise if depths and noise and noise > 0 else None,
        source=f"rig presses from {source or 'the camera'}")
    return data, log


def save_collection(path: str | Path, data, log: CollectionLog) -> None:
    """The measured-data .npz with the rig's log (atomic)."""
    from tactile_deploy.calibration.discrepancy.measured import measured_arrays
    from tactile_deploy.atomic import write_npz

    arrays = measured_arrays(data)
    arrays["rig_log"] = np.array(log.model_dump_json())
    write_npz(path, **arrays)


def load_collection_log(path: str | Path) -> CollectionLog:
    """The rig's log of a collection .npz (ValueError naming the file when absent or invalid)."""
    from pydantic import ValidationError

    with np.load(path, allow_pickle=False) as z:
        if "rig_log" not in z.files:
            raise ValueError(f"{path}: field 'rig_log' missing: not written by `tactile-deploy "
                             "rig collect`")
        text = str(z["rig_log"])
    try:
        return CollectionLog.model_validate_json(text)
    except ValidationError as e:
        err = e.errors()[0]
        raise ValueError(f"{path}: field 'rig_log': {err['msg']} at "
                         f"{'.'.join(map(str, err['loc']))}") from None
