"""Command line: ``calibrate fem`` (fit the FEM material to matched contacts).

    tactile-deploy calibrate fem --contacts contacts.csv [--nu-grid 0.48]
        [--method brent|cem] [--stick] [--bootstrap N] [--pad gelslim] [--out fem.json]
    tactile-deploy calibrate fem --work NEW.calibration [...]     (a wizard run's ball presses)

``contacts.csv`` has the header ``depth_file,indenter,x_mm,y_mm,depth_mm,force_n``: one measured
contact per line; ``depth_file`` a (128, 128) float depth map in mm on the model grid (``.npy``,
or ``.npz`` holding ``depth`` as ``simulate`` writes it; relative paths from the CSV's folder);
``indenter`` a library name or mesh path; the contact (sensor frame, mm) and force (N) may be
left empty: the contact is then estimated from the map, and without forces E is reported as not
identifiable. nu is fixed at 0.48 unless ``--nu-grid`` gives several values: it is identifiable
only from depth maps accurate to about 1 um, not from shading-based ones (docs/calibration.md).
"""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Optional

import typer

fem_app = typer.Typer(help="FEM material fit: E from forces; nu fixed at 0.48 unless "
                      "--nu-grid gives several values.")

CONTACTS_HEADER = ["depth_file", "indenter", "x_mm", "y_mm", "depth_mm", "force_n"]


class ContactsError(ValueError):
    """A contacts CSV or one of its depth maps is invalid (file, line, field, values)."""


def _fail(message: str) -> None:
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(code=2)


def _float_or_none(path: Path, line: int, field: str, text: str) -> float | None:
    text = text.strip()
    if not text:
        return None
    try:
        v = float(text)
    except ValueError:
        raise ContactsError(f"{path}, line {line}: field '{field}' must be a number or empty, got "
                            f"{text!r}") from None
    if not math.isfinite(v):
        raise ContactsError(f"{path}, line {line}: field '{field}' must be finite, got {text!r}")
    return v


def _depth_map(path: Path, where: str):
    import numpy as np

    if not path.is_file():
        raise ContactsError(f"{where}: depth file {path} not found")
    try:
        if path.suffix == ".npz":
            with np.load(path, allow_pickle=False) as z:
                if "depth" not in z.files:
                    raise ContactsError(f"{where}: {path} has no 'depth' array (has "
                                        f"{sorted(z.files)})")
                arr = z["depth"]
        else:
            arr = np.load(path, allow_pickle=False)
    except (ValueError, OSError) as e:
        raise ContactsError(f"{where}: {path} is not a readable .npy/.npz ({e})") from None
    if arr.shape != (128, 128) or arr.dtype.kind != "f" or not np.all(np.isfinite(arr)):
        raise ContactsError(f"{where}: {path} must be a finite (128, 128) float depth map in mm "
                            f"on the model grid, got {arr.shape} {arr.dtype}")
    return arr.astype(np.float64)


def _positive(path: Path, line: int, field: str, value: float | None, unit: str,
              hint: str) -> None:
    if value is not None and not value > 0:
        raise ContactsError(f"{path}, line {line}: field '{field}' must be > 0 {unit}, got "
                            f"{value:g}; {hint}")


def _check_indenter(where: str, name: str) -> None:
    from tactile_deploy.indenters import get_indenter

    try:
        get_indenter(name)
    except (ValueError, FileNotFoundError) as e:
        raise ContactsError(f"{where}: field 'indenter': {e} (`tactile-deploy indenters list` "
                            "lists the library)") from None


def read_contacts(path: Path) -> list:
    """:class:`~tactile_deploy.calibration.fem_fit.fit.MatchedContact` of each line of a contacts CSV."""
    from tactile_deploy.calibration.fem_fit.fit import MatchedContact
    from tactile_deploy.indenters import ContactPose

    path = Path(path)
    if not path.is_file():
        raise ContactsError(f"contacts file {path} not found")
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            rows = list(csv.reader(f))
    except UnicodeDecodeError:
        raise ContactsError(f"{path}: not a text file (expected a CSV with the header "
                            f"{','.join(CONTACTS_HEADER)})") from None
    if not rows or [c.strip() for c in rows[0]] != CONTACTS_HEADER:
        raise ContactsError(f"{path}: the header must be {','.join(CONTACTS_HEADER)}, got "
                            f"{','.join(rows[0]) if rows else '(empty file)'}")
    out = []
    for k, row in enumerate(rows[1:], start=2):
        if not any(c.strip() for c in row):
            continue
        if len(row) != len(CONTACTS_HEADER):
            raise ContactsError(f"{path}, line {k}: expected {len(CONTACTS_HEADER)} fields, got "
                                f"{len(row)}")
        where = f"{path}, line {k}"
        depth_file = Path(row[0].strip())
        if not depth_file.is_absolute():
            depth_file = path.parent / depth_file
        depth = _depth_map(depth_file, where)
        x, y, d, force = (_float_or_none(path, k, CONTACTS_HEADER[j], row[j]) for j in
                          range(2, 6))
        if (x is None) != (y is None) or (x is None) != (d is None):
            raise ContactsError(f"{where}: give all of x_mm, y_mm, depth_mm or none of them")
        _positive(path, k, "depth_mm", d, "mm (into the gel)",
                  "leave x_mm, y_mm and depth_mm empty to estimate the contact from the map")
        _positive(path, k, "force_n", force, "N (compression)",
                  "leave it empty when the force was not measured")
        pose = None if x is None else ContactPose(x_mm=x, y_mm=y, depth_mm=d)
        if not row[1].strip():
            raise ContactsError(f"{where}: field 'indenter' is empty (a library name such as "
                                "sphere_r4, or a mesh path)")
        _check_indenter(where, row[1].strip())
        out.append(MatchedContact(depth, row[1].strip(), pose, force))
    if not out:
        raise ContactsError(f"{path}: no contacts")
    return out


def _nu_grid(text: str) -> tuple[float, ...]:
    try:
        vals = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise typer.BadParameter(f"expected comma-separated Poisson ratios, got {text!r}",
                                 param_hint="--nu-grid") from None
    if any(not 0 <= v < 0.5 for v in vals) or len(set(vals)) != len(vals):
        raise typer.BadParameter(f"Poisson ratios must be distinct and in [0, 0.5), got {text!r}",
                                 param_hint="--nu-grid")
    return vals


@fem_app.command("fem")
def fem_command(
    contacts: Optional[Path] = typer.Option(None, help="CSV depth_file,indenter,x_mm,y_mm,"
                                            "depth_mm,force_n (see docs/calibration.md)."),
    work: Optional[Path] = typer.Option(None, help="A wizard work folder: fit its ball presses "
                                        "(depth from its shading model, rig contacts and "
                                        "forces)."),
    nu_grid: str = typer.Option("0.48", help="Poisson ratios of the exact surface operators "
                                "(about 20 s each, cached); one value fixes nu. Give several "
                                "only with depth maps accurate to about 1 um (not shading-based "
                                "ones: docs/calibration.md)."),
    method: str = typer.Option("brent", help="Search over nu: brent or cem (cross-entropy, as "
                               "the paper)."),
    stick: bool = typer.Option(False, help="Also fit with sticking contact and say which law "
                               "the data prefers."),
    bootstrap: int = typer.Option(10, min=0, help="Bootstrap resamples for the spread of nu."),
    fit_depth_offset: bool = typer.Option(False, help="Fit a common offset of the given "
                                          "contacts' depths (a rig's touch-off error) with E."),
    pad: str = typer.Option("gelslim", help="Pad mesh of the sensor family."),
    out: Optional[Path] = typer.Option(None, help="Write the result as JSON here."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing --out "
                                   "file."),
) -> None:
    """Fit E (forces) of the gel to measured contacts, and nu (depth maps) when --nu-grid has
    several values."""
    from tactile_deploy.calibration.fem_fit.fit import fit_fem_parameters
    from tactile_deploy.calibration.fem_fit.operator_bank import OperatorBank
    from tactile_deploy.calibration.fem_fit.result import FemResult, write_fem_result
    from tactile_deploy.camera.depth import DepthCamera
    from tactile_deploy.outputs import OutputPathError, check_output_file
    from tactile_deploy.pad.asset import load_pad

    if (contacts is None) == (work is None):
        _fail("give exactly one of --contacts CSV and --work FOLDER")
    if method not in ("brent", "cem"):
        _fail(f"--method must be brent or cem, got {method!r}")
    grid = _nu_grid(nu_grid)
    if out is not None:
        read = ("presses.npz", "reference.npz", "camera_mapping.json", "shading.npz")  # what --work gives
        inputs = [contacts] + ([work / name for name in read] if work is not None else [])
        try:
            check_output_file(out, "--out", overwrite=overwrite, inputs=inputs,
                              suffixes=(".json",))
        except OutputPathError as e:
            _fail(str(e))
    try:
        if contacts is not None:
            matched = read_contacts(contacts)
        else:
            from tactile_deploy.calibration.wizard.config import wizard_config_from_dict
            from tactile_deploy.calibration.wizard.context import StepError
            from tactile_deploy.calibration.wizard.press_data import contacts_from_work
            from tactile_deploy.calibration.wizard.state import WorkFolder

            wf = WorkFolder(work)
            if not wf.exists():
                _fail(f"--work {work}: no wizard state (state.json) there")
            state = wf.load()
            try:
                matched = contacts_from_work(wf, wizard_config_from_dict(state.config))
            except (StepError, FileNotFoundError) as e:
                _fail(f"--work {work}: {e} (the wizard's presses and shading steps must be done)")
    except ContactsError as e:
        _fail(str(e))
    try:
        mesh = load_pad(pad)
    except KeyError as e:
        _fail(f"--pad: {e}")
    typer.echo(f"{len(matched)} contacts; surface operators at nu = {nu_grid} (about 20 s each "
               "the first time, then cached)", err=True)
    bank = OperatorBank(mesh, grid_nu=grid)
    stick_bank = OperatorBank(mesh, friction="stick", grid_nu=grid) if stick else None
    try:
        res = fit_fem_parameters(matched, bank, DepthCamera(), method=method,
                                 stick_bank=stick_bank, bootstrap=bootstrap,
                                 fit_depth_offset=fit_depth_offset)
    except ValueError as e:
        _fail(f"{contacts or work}: {e}")
    bad = [f"{name} = {value}" for name, value in (("nu", res.nu), ("E", res.E_mpa),
                                                    ("depth-map gap", res.rmse_mm))
           if value is not None and not math.isfinite(value)]
    if res.E_mpa is not None and res.E_mpa <= 0:
        bad.append(f"E = {res.E_mpa:g} MPa (not > 0)")
    if bad:
        _fail(f"the fit gave {', '.join(bad)}: nothing written; check the depth maps, contacts "
              f"and forces of {contacts or work}")
    n_forces = sum(c.force_n is not None for c in matched)
    nu_fixed = len(grid) == 1
    nu_std = None if nu_fixed or not math.isfinite(res.nu_std) else res.nu_std
    E_std = res.E_std_mpa if n_forces > 1 else None
    result = FemResult(nu=res.nu, nu_std=nu_std, nu_note=res.nu_note, E_mpa=res.E_mpa,
                       E_std_mpa=E_std, E_note=res.E_note, friction=res.friction,
                       friction_note=res.friction_note, depth_gap_um=1e3 * res.rmse_mm,
                       method=res.method, evaluations=res.evaluations, n_contacts=len(matched),
                       depth_offset_mm=res.depth_offset_mm, source="tactile-deploy calibrate fem")
    if nu_fixed:
        typer.echo(f"nu = {res.nu:.4f} (fixed by --nu-grid {nu_grid}, not fitted)")
    else:
        nu_spread = (f"+- {nu_std:.4f} over {bootstrap} bootstrap resamples"
                     if nu_std is not None else "spread not measured: --bootstrap 0")
        typer.echo(f"nu = {res.nu:.4f} ({nu_spread}; {res.nu_note})")
    if res.E_mpa is None:
        typer.echo(f"E: {res.E_note}")
    else:
        E_spread = (f"+- {E_std:.4f} MPa bootstrap" if E_std is not None
                    else "one force: no spread")
        typer.echo(f"E = {res.E_mpa:.4f} MPa ({E_spread}; {res.E_note})")
    typer.echo(f"friction: {res.friction_note}")
    typer.echo(f"depth-map gap at the optimum: {1e3 * res.rmse_mm:.2f} um RMS")
    if out is not None:
        write_fem_result(out, result)
        typer.echo(f"wrote {out}")
