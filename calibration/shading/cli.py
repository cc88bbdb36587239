"""Command line: ``calibrate shading`` (fit a shading model) and ``depth`` (apply one).

    tactile-deploy calibrate shading --reference REF.png --presses DIR [--annotations CSV]
        --ball-radius-mm R --mm-per-px S --out shading.npz [--circles-out CSV] [--folds K]
    tactile-deploy depth --shading shading.npz --reference REF.png FRAME.png... --out DIR

``shading_app`` holds the ``shading`` command (add it to the ``calibrate`` group);
``depth_command`` is a plain function (register it as ``depth``). Heavy imports happen inside
the commands so that ``--help`` stays fast.
"""

from __future__ import annotations

from pathlib import Path

import typer

shading_app = typer.Typer(help="Marble shading model: colour -> surface gradient -> depth.")


def _fail(msg: str) -> None:
    typer.echo(f"error: {msg}", err=True)
    raise typer.Exit(code=2)


def write_circles_csv(path: Path, names, circles) -> None:
    """Write circles (px) as ``img_names,center_x,center_y,radius`` (atomic)."""
    from tactile_deploy.atomic import write_text

    lines = ["img_names,center_x,center_y,radius"]
    lines += [f"{n},{c[0]:.2f},{c[1]:.2f},{c[2]:.2f}" for n, c in zip(names, circles)]
    write_text(path, "\n".join(lines) + "\n")


@shading_app.command("shading")
def shading_command(
    reference: Path = typer.Option(..., help="Frame of the sensor with nothing touching it."),
    presses: Path = typer.Option(..., help="Folder of ball-press frames (one press each)."),
    ball_radius_mm: float = typer.Option(..., help="Radius of the calibration ball, mm."),
    mm_per_px: float = typer.Option(..., help="Sensor-plane scale, mm per pixel."),
    out: Path = typer.Option(..., help="Shading model to write (.npz)."),
    annotations: Path | None = typer.Option(
        None, help="CSV img_names,center_x,center_y,radius (px); without it circles are "
        "detected."),
    circles_out: Path | None = typer.Option(
        None, help="Write the circles used (refined centres, measured contact radii) as CSV: "
        "correct them by hand and pass them back with --annotations."),
    folds: int = typer.Option(0, help="Also cross-validate with this many folds (0: no) and "
                              "print held-out shape error and fitted radius."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace existing --out and "
                                   "--circles-out files."),
) -> None:
    """Fit a shading model (position-dependent colour LUT) to ball presses and save it."""
    import math

    import numpy as np

    from tactile_deploy.outputs import OutputPathError, check_distinct, check_output_file
    from tactile_deploy.imaging.shading import DepthFromShading, save_shading

    from .circles import ContactNotFoundError
    from .evaluate import cross_validate, markdown_table, summarise
    from .fit import fit_shading
    from .presses import IMAGE_SUFFIXES, PressDataError, load_presses

    for option, value, unit in (("--ball-radius-mm", ball_radius_mm, "mm"),
                                ("--mm-per-px", mm_per_px, "mm per px")):
        if not (value > 0 and math.isfinite(value)):
            _fail(f"{option} must be a finite number > 0 ({unit}), got {value}")
    if folds != 0 and folds < 2:
        _fail(f"--folds must be 0 (no cross-validation) or at least 2, got {folds}")
    inputs = [reference, annotations]
    if presses.is_dir():
        inputs += [p for p in presses.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES]
    try:
        check_output_file(out, "--out", overwrite=overwrite, inputs=inputs, suffixes=(".npz",))
        if circles_out is not None:
            check_output_file(circles_out, "--circles-out", overwrite=overwrite, inputs=inputs)
        check_distinct(("--out", out), ("--circles-out", circles_out))
    except OutputPathError as e:
        _fail(str(e))
    try:
        data = load_presses(reference, presses, annotations)
        if folds > len(data):
            _fail(f"--folds must lie in [2, {len(data)}] (the number of presses in {presses}), "
                  f"got {folds}")
        fit = fit_shading(data, ball_radius_mm, mm_per_px)
    except ContactNotFoundError as e:
        _fail(f"{presses}: {e}; give the circles with --annotations CSV "
              "(img_names,center_x,center_y,radius) or remove the frame")
    except (PressDataError, ValueError) as e:
        _fail(str(e))
    save_shading(fit.model, out)
    h = fit.model.header
    typer.echo(f"wrote {out}: {len(data)} presses, {h.n_slots} colour slots on a "
               f"{h.node_grid_shape[0]}x{h.node_grid_shape[1]} node grid, depth weights "
               f"x {h.poisson_weight_x:g} / y {h.poisson_weight_y:g}")
    typer.echo(f"in-sample fit residual {h.fit_metrics['in_sample_sphere_rms_um']:.1f} um: "
               "against the targets the model was fitted to, not an accuracy figure"
               + ("" if folds else "; use --folds N for held-out figures"))
    shift = np.hypot(*(fit.circles[:, :2] - fit.circles_input[:, :2]).T)
    typer.echo(f"circles: centres moved by {shift.mean():.1f} px on average (max "
               f"{shift.max():.1f} px); contact radii {fit.circles[:, 2].min():.1f}-"
               f"{fit.circles[:, 2].max():.1f} px")
    if circles_out is not None:
        write_circles_csv(circles_out, data.names, fit.circles)
        typer.echo(f"wrote {circles_out}")
    if folds:
        if data.circles is None:
            data.circles = fit.circles_input

        def fitter(train):
            m = fit_shading(train, ball_radius_mm, mm_per_px).model
            return DepthFromShading(m, train.reference)

        res = cross_validate(data, fitter, ball_radius_mm, mm_per_px, folds)
        typer.echo(markdown_table({"held-out presses": summarise(res)}))


def depth_command(
    frames: list[Path] = typer.Argument(..., help="RGB frames to reconstruct."),
    shading: Path = typer.Option(..., help="Shading model (.npz) from `calibrate shading`."),
    reference: Path = typer.Option(..., help="Frame of the sensor with nothing touching it."),
    out: Path = typer.Option(..., help="Folder for the depth maps (<frame name>.npy, mm)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace depth maps already in "
                                   "--out."),
) -> None:
    """Depth maps (mm, positive into the gel, the frame's resolution) of frames, as .npy."""
    import numpy as np

    from tactile_deploy.atomic import atomic_path
    from tactile_deploy.imaging.shading import (
        DepthFromShading,
        ShadingModelError,
        load_shading,
    )

    from .presses import PressDataError, read_rgb

    if out.exists() and not out.is_dir():
        _fail(f"--out {out} is a file: give a folder for the depth maps (it is created if "
              "missing)")
    targets = {}
    for path in frames:
        target = out / f"{path.stem}.npy"
        if target in targets:
            _fail(f"frames {targets[target]} and {path} would both be written to {target}: give "
                  "frames with different names (or run depth once per folder)")
        targets[target] = path
        if target.exists() and not overwrite:
            _fail(f"{target} exists: pass --overwrite to replace it, or choose another --out")
    try:
        model = load_shading(shading)
    except (FileNotFoundError, ShadingModelError) as e:
        _fail(str(e))
    fitted_for = f"the size {shading} was fitted for; use frames of that sensor at that size"
    try:
        runner = DepthFromShading(model, read_rgb(reference))
    except PressDataError as e:
        _fail(str(e))
    except ShadingModelError as e:
        _fail(f"--reference {reference}: {e}, {fitted_for}")
    for path in frames:   # every frame is checked before anything is written
        try:
            img = read_rgb(path)
        except PressDataError as e:
            _fail(str(e))
        if img.shape[:2] != runner.shape:
            _fail(f"{path}: frame is {img.shape[1]}x{img.shape[0]} (WxH) px, expected "
                  f"{runner.shape[1]}x{runner.shape[0]}, {fitted_for}")
    out.mkdir(parents=True, exist_ok=True)
    for target, path in targets.items():
        depth = runner.depth(read_rgb(path))
        with atomic_path(target) as tmp, open(tmp, "wb") as f:
            np.save(f, depth.astype(np.float32))
        typer.echo(f"{target}: max depth {float(depth.max()):.3f} mm")
