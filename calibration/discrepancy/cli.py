"""``tactile-deploy discrepancy``: which effect is missing from a sensor model.

    tactile-deploy discrepancy --sensor NAME|MODEL.json --measured DATA.npz|DIR
        [--report DIR [--overwrite]] [--json] [--apply] [--model-dir DIR]

Registered through the ``tactile_deploy.cli`` entry-point group (pyproject.toml). Progress goes
to stderr; stdout holds the verdict (text, or JSON with ``--json``).
"""

from __future__ import annotations

from pathlib import Path

import typer


def discrepancy_command(
    sensor: str = typer.Option(..., help="Sensor model: a shipped virtual sensor's name "
                               "(gelslim1, gelslim2, gelsight_fots) or a model JSON path."),
    measured: Path = typer.Option(..., help="Measured data: an .npz file or a folder with "
                                  "contacts.csv (docs/discrepancy.md)."),
    report: Path | None = typer.Option(None, help="Write report.md, verdict.json and figures "
                                       "into this folder."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing --report "
                                   "folder."),
    json_output: bool = typer.Option(False, "--json", help="Print the verdict as JSON."),
    apply: bool = typer.Option(False, help="Write the found effect into the sensor model "
                               "(a new version; every previous one is kept)."),
    model_dir: Path | None = typer.Option(None, help="Where --apply puts the model of a shipped "
                                          "sensor (NAME.json; default: the current folder)."),
    plugin: str | None = typer.Option(None, help="Sensor plugin whose imaging pipeline turns "
                                      "measured frames into depth (default: the sensor's name)."),
    candidates: str | None = typer.Option(None, help="Comma-separated candidates to consider "
                                          "(default: the whole library)."),
    folds: int = typer.Option(5, min=2, help="Folds of the cross-validation by contact."),
    null_replicates: int = typer.Option(200, min=20, help="Effect-free replicates of the null."),
    seed: int = typer.Option(0, min=0, help="Seed of the folds, null and bootstrap."),
    workers: int = typer.Option(2, min=1, help="Processes that simulate the contacts' "
                                "responses (the machine's cores)."),
) -> None:
    """Name the effect missing from a sensor model, with its size (or: none, unexplained)."""
    from tactile_deploy.calibration.discrepancy.apply import apply_effect, check_target
    from tactile_deploy.calibration.discrepancy.candidates import candidate_library
    from tactile_deploy.calibration.discrepancy.measured import (
        MeasuredDataError,
        load_measured,
        measured_sha256,
    )
    from tactile_deploy.calibration.discrepancy.report import check_report_folder
    from tactile_deploy.calibration.discrepancy.verdict import verdict_text
    from tactile_deploy.calibration.discrepancy.workflow import DiscrepancyOptions, find_discrepancy
    from tactile_deploy.outputs import OutputPathError
    from tactile_deploy.cli.common import err_console, fail, prepare_simulator, progress_bar
    from tactile_deploy.sensors.catalog import UnknownSensorError, sensor_config
    from tactile_deploy.sensors.config import SensorConfigError
    from tactile_deploy.sensors.virtual import VirtualSensor

    try:
        config = sensor_config(sensor)
    except (UnknownSensorError, SensorConfigError, FileNotFoundError) as e:
        fail(str(e))
    names = None
    if candidates:
        names = tuple(n.strip() for n in candidates.split(",") if n.strip())
        try:
            candidate_library(names)
        except KeyError as e:
            fail(str(e.args[0]))
    # outputs before any work: the report folder and the model file --apply writes
    model_file = None
    try:
        if apply:
            model_file = check_target(sensor, config, model_dir)
        if report is not None:
            check_report_folder(report, overwrite=overwrite,
                                inputs=[measured, sensor if sensor.endswith(".json") else None,
                                        model_file])
    except (OutputPathError, OSError, SensorConfigError) as e:
        fail(str(e))
    try:
        data = load_measured(measured)
        measured_hash = measured_sha256(measured) if apply else None
    except (MeasuredDataError, FileNotFoundError) as e:
        fail(f"{e}")
    except Exception as e:  # what the loader's checks did not foresee: one line, no traceback
        fail(f"{measured}: cannot be read as measured data ({type(e).__name__}: "
             f"{' '.join(str(e).split())}); check it against the layout in docs/discrepancy.md "
             "(Measured data)")
    virtual = VirtualSensor(config)
    prepare_simulator(virtual.simulator)
    opts = DiscrepancyOptions(folds=folds, null_replicates=null_replicates, seed=seed,
                              candidates=names, plugin=plugin, workers=workers)
    try:
        result = find_discrepancy(virtual, data, opts,
                                  progress=lambda d, n: progress_bar(d, n, "contacts"))
    except (MeasuredDataError, ValueError) as e:
        fail(str(e))
    v = result.verdict
    if json_output:
        typer.echo(v.to_json(), nl=False)
    else:
        typer.echo(verdict_text(v))
    if report is not None:
        from tactile_deploy.calibration.discrepancy.report import write_report

        try:
            files = write_report(result, report, overwrite=overwrite)
        except OutputPathError as e:
            fail(str(e))
        except OSError as e:
            fail(f"the report could not be written into {report}: {e}")
        err_console.print(f"report: {files[0]} ({len(files)} files)")
    if apply:
        if v.verdict != "effect":
            what = {"none": "nothing is missing", "unexplained": "no candidate explains the gap",
                    "ambiguous": "look-alikes explain it equally well: run the experiment "
                                 "first, or restrict --candidates"}[v.verdict]
            fail(f"--apply: nothing written, {what}", code=1)
        reason = {"gap_before_mm": v.gap_before_mm, "gap_after_mm": v.gap_after_mm,
                  "explained_fraction": v.explained_fraction, "confidence": v.confidence,
                  "intervals": v.intervals, "measured": str(measured.resolve()),
                  "measured_sha256": measured_hash, "n_samples": v.n_samples}
        try:
            out = apply_effect(sensor, config, result.verification.spec, reason, model_dir)
        except (OSError, SensorConfigError) as e:
            fail(str(e))
        err_console.print(f"applied {v.effect} to {out.path} (version {out.version}; previous: "
                          f"{out.previous}); use --sensor {out.path} from now on")
