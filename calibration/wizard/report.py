"""The calibration report inside the plugin folder: ``calibration/report.html`` (figures of merit
and pictures of every step), ``calibration/metrics.json`` (:class:`CalibrationMetrics`, read back
by :func:`load_calibration_metrics`) and the PNG figures it shows."""

from __future__ import annotations

import html
import math
import os
import shutil
from pathlib import Path

from typing import Literal

from pydantic import Field

from tactile_deploy.atomic import write_json, write_text
from tactile_deploy.calibration.wizard.config import WizardConfig
from tactile_deploy.calibration.wizard.state import STEP_TITLES, STEPS
from tactile_deploy.fileformat import StrictModel
from tactile_deploy.jsonfile import read_model_json

METRICS_NAME = "metrics.json"

#: A figure of merit: a number (its name carries the unit), a text, or None (not measured).
Metric = float | int | str | None


class CalibrationMetricsError(ValueError):
    """A calibration metrics file is missing or invalid (the message names file and field)."""


class CalibrationMetrics(StrictModel):
    """``PLUGIN/calibration/metrics.json``: the figures of merit of each step of the calibration
    that made the plugin (what ``report.html`` shows as tables)."""

    sensor: str = Field(description="Name of the plugin the calibration made.")
    source: str = Field(description="Frame source the frames came from (--source).")
    rig: str | None = Field(description="Rig that pressed (--rig), or None for hand presses.")
    config: WizardConfig = Field(description="The wizard config the steps were run with.")
    steps: dict[Literal[STEPS], dict[str, Metric]] = Field(  # type: ignore[valid-type]
        description="Figures of merit by step (names carry units; None: not measured).")


def load_calibration_metrics(path: str | os.PathLike) -> CalibrationMetrics:
    """Read and check a calibration's ``metrics.json`` (:class:`CalibrationMetricsError` naming
    the file, each bad field and the value it had)."""
    return read_model_json(path, CalibrationMetrics, CalibrationMetricsError,
                           "calibration metrics", "written by `tactile-deploy calibrate`; the "
                           "format is metrics.schema.json in calibration/wizard/",
                           expected="the calibration's metrics.json")


def _cell(v) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return html.escape(str(v))


def _plain(v):
    """JSON-safe value (NaN and inf become None)."""
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def write_report(ctx, folder: Path, extra_metrics: dict, extra_figures: list[Path]) -> Path:
    """Write the report of the steps recorded in ``ctx.state`` plus ``extra_metrics`` (by step)
    and ``extra_figures`` into ``folder``; returns the HTML path."""
    folder.mkdir(parents=True, exist_ok=True)
    state = ctx.state
    sections, metrics = [], {}
    for step in STEPS:
        rec = state.steps.get(step)
        m = dict(rec.metrics) if rec else {}
        m.update(extra_metrics.get(step, {}))
        figs = [ctx.work.folder / f for f in rec.figures] if rec else []
        if step == "plugin":
            figs += [Path(f) for f in extra_figures]
        if not m and not figs:
            continue
        metrics[step] = m
        rows = "".join(f"<tr><td>{html.escape(k)}</td><td>{_cell(v)}</td></tr>"
                       for k, v in m.items())
        notes = "".join(f"<li>{html.escape(n)}</li>" for n in (rec.notes if rec else []))
        imgs = []
        for f in figs:
            if f.is_file():
                shutil.copyfile(f, folder / f.name)
                imgs.append(f'<p><img src="{html.escape(f.name)}" alt="{html.escape(step)}" '
                            'style="max-width:100%"></p>')
        sections.append(f"<h2>{html.escape(step)}: {html.escape(STEP_TITLES[step])}</h2>"
                        f"<table>{rows}</table>" + (f"<ul>{notes}</ul>" if notes else "")
                        + "".join(imgs))
    page = f"""<!doctype html>
<html><head><meta charset="utf-8"><title>calibration of {html.escape(ctx.sensor)}</title>
<style>body{{font-family:sans-serif;max-width:1000px;margin:auto}}
table{{border-collapse:collapse}}td{{border:1px solid #ccc;padding:2px 8px}}</style></head>
<body><h1>Calibration of {html.escape(ctx.sensor)}</h1>
<p>Frames from {html.escape(state.source)}; rig: {html.escape(state.rig or 'none (hand presses)')};
started {html.escape(state.started)}. Made by <code>tactile-deploy calibrate</code>.</p>
{''.join(sections)}
</body></html>
"""
    path = folder / "report.html"
    write_text(path, page)
    doc = CalibrationMetrics(sensor=ctx.sensor, source=state.source, rig=state.rig,
                             config=WizardConfig.model_validate(state.config),
                             steps={s: {k: _plain(v) for k, v in m.items()}
                                    for s, m in metrics.items()})
    write_json(folder / METRICS_NAME, doc.model_dump(mode="json"))
    return path
