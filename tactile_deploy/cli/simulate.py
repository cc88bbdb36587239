"""``tactile-deploy simulate``: one contact to an .npz, or a sharded dataset to a folder."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Optional

import typer

from tactile_deploy.cli.common import (
    console,
    err_console,
    fail,
    prepare_simulator,
    progress_bar,
)

FRICTION_CHOICES = ("frictionless", "stick", "coulomb")
MODEL_CHOICES = ("neo-hookean", "linear")


def _indenter_list(text: str) -> tuple[str, ...]:
    from tactile_deploy.indenters import list_indenters

    if text in ("primitives", "primitive"):
        return tuple(list_indenters("primitive"))
    if text in ("novel",):
        return tuple(list_indenters("novel"))
    if text == "all":
        return tuple(list_indenters())
    return tuple(t.strip() for t in text.split(",") if t.strip())


#: Options of one contact (parameter name -> option; refused with --n).
SINGLE_OPTIONS = {"indenter": "--indenter", "x": "--x", "y": "--y", "theta": "--theta",
                  "depth": "--depth", "pressing_face": "--pressing-face", "overwrite": "--overwrite",
                  "slide_x": "--slide-x", "slide_y": "--slide-y"}
#: Options of a dataset (used with --n only).
BATCH_OPTIONS = {"indenters": "--indenters", "shard_size": "--shard-size", "depth_range": "--depth-range",
                 "workers": "--workers", "storage": "--storage"}
MATERIAL_OPTIONS = {"E_mpa": "--E", "nu": "--nu", "mu": "--mu", "friction": "--friction"}


def _given(ctx: typer.Context, options: dict[str, str]) -> list[str]:
    """The ``options`` the user typed (not left at their defaults)."""
    return [opt for name, opt in options.items()
            if getattr(ctx.get_parameter_source(name), "name", "DEFAULT") != "DEFAULT"]


def simulate_command(
    ctx: typer.Context,
    indenter: Optional[str] = typer.Option(None, "--indenter", help="Library name (see `tactile-deploy indenters list`) or mesh file (STL/OBJ/PLY, mm)."),
    x: float = typer.Option(0.0, "--x", help="Indenter origin x in the sensor frame, mm."),
    y: float = typer.Option(0.0, "--y", help="Indenter origin y in the sensor frame, mm."),
    theta: float = typer.Option(0.0, "--theta", help="Rotation about +z, degrees (counter-clockwise seen from above)."),
    depth: float = typer.Option(0.8, "--depth", help="Indentation depth of the lowest point below the rest surface, mm."),
    E: float = typer.Option(0.3, "--E", help="Young's modulus, MPa (scales forces only)."),
    nu: float = typer.Option(0.48, "--nu", help="Poisson's ratio."),
    mu: float = typer.Option(1.0, "--mu", help="Coulomb friction coefficient gel/indenter (used by --friction coulomb)."),
    friction: str = typer.Option("frictionless", "--friction", help="Contact law: frictionless, stick, or coulomb (friction coefficient --mu)."),
    model: str = typer.Option("neo-hookean", "--model", help="Gel law of a single contact: neo-hookean (large deformation) or linear (its small-strain limit); both resolved at the depth-pixel scale."),
    slide_x: float = typer.Option(0.0, "--slide-x", help="After pressing, slide the indenter this far along x (sensor frame), mm: a tangential load; needs --friction stick or coulomb."),
    slide_y: float = typer.Option(0.0, "--slide-y", help="The same along y, mm."),
    pressing_face: str = typer.Option("top", "--pressing-face", help="For mesh files: 'top' if the feature is the top of the file (indenters standing on a base), 'bottom' if it already faces -z."),
    out: Path = typer.Option(..., "--out", help="FILE.npz for one contact; a folder with --n."),
    n: Optional[int] = typer.Option(None, "--n", help="Batch mode: number of random contacts."),
    indenters: str = typer.Option("primitives", "--indenters", help="Batch mode: 'primitives', 'novel', 'all' or a comma list."),
    seed: int = typer.Option(0, "--seed", help="Batch mode: random seed (reproducible)."),
    shard_size: int = typer.Option(256, "--shard-size", help="Batch mode: samples per shard file."),
    depth_range: str = typer.Option("0.2,1.2", "--depth-range", help="Batch mode: min,max depth, mm."),
    workers: int = typer.Option(2, "--workers", help="Batch mode: worker processes."),
    storage: str = typer.Option("float16", "--storage", help="Batch mode: precision of stored depth maps and displacements, float16 (<= 0.49 um rounding) or float32."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing output file."),
    sensor: Optional[str] = typer.Option(None, "--sensor", help="Virtual sensor (name, see docs/optics.md, or .json): its material and effects replace --E --nu --mu --friction; one contact only."),
    rgb: bool = typer.Option(False, "--rgb", help="With --sensor: render the camera frame into the .npz ('frame', (H, W, 3) uint8 RGB) and a PNG beside it (noise from --seed)."),
) -> None:
    """Simulate one indenter contact (FEM + depth camera), or generate a dataset with --n."""
    from pydantic import ValidationError

    from tactile_deploy.fem.material import Material

    if friction not in FRICTION_CHOICES:
        fail(f"--friction must be one of {', '.join(FRICTION_CHOICES)}, got {friction!r}")
    if model not in MODEL_CHOICES:
        fail(f"--model must be one of {', '.join(MODEL_CHOICES)}, got {model!r}")
    try:
        material = Material(E_mpa=E, nu=nu, mu=mu, friction=friction)
    except ValidationError as exc:
        e = exc.errors()[0]
        option = MATERIAL_OPTIONS.get(str(e["loc"][0]), str(e["loc"][0]))
        rule = {"--E": "Young's modulus, MPa, > 0", "--nu": "Poisson's ratio, 0 <= nu < 0.5",
                "--mu": "friction coefficient, >= 0"}.get(option, "")
        fail(f"{option} {e.get('input')}: {e['msg'].lower()}; pass a value in range ({rule})")
    if rgb and sensor is None:
        fail("--rgb renders a virtual sensor's camera frame: give --sensor NAME as well")
    if sensor is not None:
        if n is not None:
            fail("--sensor simulates one contact; leave out --n")
        if slide_x or slide_y:
            fail("--slide-x/--slide-y apply to a resolved contact without --sensor (a virtual "
                 "sensor's frames are of a straight press); leave out --sensor to slide")
        if indenter is None:
            fail("give --indenter NAME|PATH for the contact")
        from tactile_deploy.cli.simulate_sensor import single_sensor_contact

        single_sensor_contact(sensor, rgb, seed, indenter, pressing_face, x, y, theta, depth,
                              out, overwrite)
        return
    if n is None:
        batch_only = _given(ctx, BATCH_OPTIONS)
        if batch_only:
            fail(f"{', '.join(batch_only)} set up a dataset and need --n N; leave "
                 f"{'them' if len(batch_only) > 1 else 'it'} out for one contact")
        if indenter is None:
            fail("give --indenter NAME|PATH for one contact, or --n N for a dataset")
        if (slide_x or slide_y) and friction == "frictionless":
            fail("--slide-x/--slide-y move the indenter along the surface after pressing; without "
                 "friction that loads nothing: add --friction stick, or --friction coulomb --mu MU")
        _single(indenter, pressing_face, x, y, theta, depth, material, out, overwrite, model,
                (slide_x, slide_y))
    else:
        if _given(ctx, {"model": "--model"}):
            fail("--model applies to one contact; datasets (--n) use the linear pad-mesh solver")
        single_only = _given(ctx, SINGLE_OPTIONS)
        if single_only:
            fail(_single_options_with_n(single_only))
        _batch(n, indenters, seed, shard_size, depth_range, workers, material, out, storage)


def _count(k: int, noun: str) -> str:
    return f"{k} {noun}{'' if k == 1 else 's'}"


def _single_options_with_n(given: list[str]) -> str:
    """The error for one-contact options given with --n: what a dataset uses instead."""
    from tactile_deploy.simulation.dataset import DatasetSpec

    radius = DatasetSpec.model_fields["radius_max_mm"].default
    instead = []
    if {"--indenter", "--pressing-face"} & set(given):
        instead.append("choose its shapes with --indenters NAMES|primitives|novel|all")
    if "--depth" in given:
        instead.append("its depths with --depth-range MIN,MAX (mm)")
    if "--overwrite" in given:
        instead.append("start over in a new --out folder (a dataset folder is resumed, never replaced)")
    return (f"{', '.join(given)} set one contact and do not apply with --n: a dataset draws random "
            f"contacts (positions within {radius:g} mm of the centre, rotations 0-360 deg)"
            f"{'; ' if instead else ''}{', '.join(instead)}; or leave out --n to simulate one contact")


def _single(indenter, pressing_face, x, y, theta, depth, material, out: Path, overwrite: bool,
            model: str = "neo-hookean", slide_mm: tuple[float, float] = (0.0, 0.0)) -> None:
    from pydantic import ValidationError

    from tactile_deploy.atomic import write_npz
    from tactile_deploy.indenters import ContactPose, get_indenter
    from tactile_deploy.outputs import OutputPathError, check_output_file
    from tactile_deploy.fem.truth import TruthSolveError
    from tactile_deploy.simulation.contact import ContactError, simulate_resolved

    try:  # one contact: FILE.npz in an existing folder, --overwrite to replace it
        check_output_file(out, "--out", overwrite=overwrite, suffixes=(".npz",))
    except OutputPathError as e:
        fail(str(e))
    for option, value in (("--x", x), ("--y", y), ("--theta", theta), ("--depth", depth),
                          ("--slide-x", slide_mm[0]), ("--slide-y", slide_mm[1])):
        if not math.isfinite(value):
            fail(f"{option} must be a finite number ({'degrees' if option == '--theta' else 'mm'}), got {value}")
    try:
        ind = get_indenter(indenter, pressing_face=pressing_face)
        pose = ContactPose(x_mm=x, y_mm=y, theta_deg=theta, depth_mm=depth)
    except (ValueError, FileNotFoundError, OSError, ValidationError) as exc:
        fail(str(exc))
    try:
        sample = simulate_resolved(ind, pose, material, model=model, slide_mm=slide_mm)
    except ContactError as exc:
        fail(str(exc))
    except TruthSolveError as exc:
        fail(f"{exc}; try a shallower --depth or --model linear")
    write_npz(out, **sample.npz_arrays())
    stick = "" if sample.stick_mask is None or material.friction == "frictionless" else (
        f" ({int(sample.stick_mask.sum())} sticking)")
    console.print(
        f"wrote {out}: indenter {ind.name}, {model}, {material.friction} contact, depth {depth:g} mm "
        f"-> force {sample.force_n:.4f} N, {int(sample.contact_mask.sum())} sensing nodes in "
        f"contact{stick}, max depth {float(sample.depth_mm.max()):.3f} mm, largest penetration "
        f"{1e3 * sample.metadata['max_penetration_mm']:.2f} um"
        + ("" if not any(slide_mm) else
           f"; slid ({slide_mm[0]:g}, {slide_mm[1]:g}) mm -> tangential force "
           f"({sample.metadata['tangential_force_n'][0]:.4f}, "
           f"{sample.metadata['tangential_force_n'][1]:.4f}) N")
    )


def _batch(n, indenters, seed, shard_size, depth_range, workers, material, out: Path, storage: str = "float16") -> None:
    from pydantic import ValidationError

    from tactile_deploy.simulation.contact import get_simulator
    from tactile_deploy.simulation.dataset import (
        DEPTH_LIMIT_MM,
        SPEC_OPTIONS,
        DatasetSpec,
        generate_dataset,
        scan_dataset,
        shard_path,
    )

    if n <= 0:
        fail(f"--n must be a positive number of contacts, got {n}")
    if shard_size <= 0:
        fail(f"--shard-size must be a positive number of samples per shard, got {shard_size}")
    if seed < 0:
        fail(f"--seed must be >= 0, got {seed}")
    if workers < 1:
        fail(f"--workers must be >= 1 (worker processes), got {workers}")
    if storage not in ("float16", "float32"):
        fail(f"--storage must be float16 or float32, got {storage!r}")
    if out.suffix == ".npz":
        fail(f"--out must be a folder in batch mode, got {out}")
    if out.exists() and not out.is_dir():
        fail(f"--out {out} is a file, not a dataset folder; choose a new or existing dataset folder")
    try:
        lo, hi = (float(v) for v in depth_range.split(","))
    except ValueError:
        fail(f"--depth-range must be 'min,max' in mm, got {depth_range!r}")
    if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo <= hi <= DEPTH_LIMIT_MM):
        fail(f"--depth-range {depth_range}: need 0 < min <= max <= {DEPTH_LIMIT_MM:g} mm (the pad "
             f"model's deepest indentation), got min {lo:g} mm, max {hi:g} mm; e.g. --depth-range 0.2,1.2")
    names = _indenter_list(indenters)
    try:
        from tactile_deploy.indenters import get_indenter

        for name in names:
            get_indenter(name)
    except (ValueError, FileNotFoundError) as exc:
        fail(f"--indenters: {exc}")
    try:
        spec = DatasetSpec(
            n_samples=n, indenters=names, seed=seed, shard_size=shard_size,
            depth_min_mm=lo, depth_max_mm=hi, material=material, storage=storage,
        )
    except ValidationError as exc:
        e = exc.errors()[0]
        option = SPEC_OPTIONS.get(str(e["loc"][0]), str(e["loc"][0])) if e["loc"] else "--depth-range"
        fail(f"{option}: {e['msg']} (got {e.get('input')!r}); see `tactile-deploy simulate --help`")
    try:
        existing = scan_dataset(spec, out)  # checks the folder before any work
    except ValueError as exc:
        fail(str(exc))
    n_done = sum(r.n_samples for r in existing.values())
    if len(existing) == spec.n_shards:
        card = generate_dataset(spec, out, workers=workers, existing=existing)  # completes the card
        console.print(f"complete: {_count(len(card.shards), 'shard')} ({n_done} samples) in {out}, nothing to do; "
                      f"card: {out / 'dataset.json'}")
        console.print(json.dumps(card.counts_per_indenter))
        return
    prepare_simulator(get_simulator(material))
    shards_now = [0]
    try:
        with progress_bar(f"simulating {n} contacts", n, "samples") as advance:
            if n_done:
                advance(n_done)  # already on disk (the rate counts this run's samples only)
            written = [0]

            def on_shard(count: int, elapsed: float) -> None:
                written[0] += count
                shards_now[0] += 1
                advance(count, rate=written[0] / max(elapsed, 1e-9))

            try:
                card = generate_dataset(spec, out, workers=workers, on_shard=on_shard, existing=existing)
            except ValueError as exc:
                fail(str(exc))
    except KeyboardInterrupt:  # shards are written whole or not at all: count those on disk
        on_disk = sum(shard_path(out, i).exists() for i in range(spec.n_shards))
        err_console.print(f"interrupted; {on_disk} of {spec.n_shards} shards done; rerun the same "
                          f"command to resume")
        raise typer.Exit(130)
    kept = (f"; {_count(len(existing), 'shard')} ({n_done} samples) already there, "
            f"{_count(len(card.shards), 'shard')} ({sum(s.n_samples for s in card.shards)} samples) "
            f"in all") if existing else ""
    console.print(
        f"wrote {_count(shards_now[0], 'shard')} to {out} ({written[0]} samples){kept}; "
        f"card: {out / 'dataset.json'}"
    )
    console.print(json.dumps(card.counts_per_indenter))
