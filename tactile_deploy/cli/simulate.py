"""``tactile-deploy simulate``: one contact to an .npz, or a sharded dataset to a folder."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

from tactile_deploy.cli.common import console, fail, prepare_simulator, progress_bar

FRICTION_CHOICES = ("frictionless", "stick")


def _indenter_list(text: str) -> tuple[str, ...]:
    from tactile_deploy.indenters import list_indenters

    if text in ("primitives", "primitive"):
        return tuple(list_indenters("primitive"))
    if text in ("novel",):
        return tuple(list_indenters("novel"))
    if text == "all":
        return tuple(list_indenters())
    return tuple(t.strip() for t in text.split(",") if t.strip())


def simulate_command(
    indenter: Optional[str] = typer.Option(None, "--indenter", help="Library name (see `tactile-deploy indenters list`) or mesh file (STL/OBJ/PLY, mm)."),
    x: float = typer.Option(0.0, "--x", help="Indenter origin x in the sensor frame, mm."),
    y: float = typer.Option(0.0, "--y", help="Indenter origin y in the sensor frame, mm."),
    theta: float = typer.Option(0.0, "--theta", help="Rotation about +z, degrees (counter-clockwise seen from above)."),
    depth: float = typer.Option(0.8, "--depth", help="Indentation depth of the lowest point below the rest surface, mm."),
    E: float = typer.Option(0.3, "--E", help="Young's modulus, MPa (scales forces only)."),
    nu: float = typer.Option(0.48, "--nu", help="Poisson's ratio."),
    mu: float = typer.Option(1.0, "--mu", help="Friction coefficient (recorded; used by Coulomb contact)."),
    friction: str = typer.Option("frictionless", "--friction", help="Contact law: frictionless or stick."),
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
    try:
        material = Material(E_mpa=E, nu=nu, mu=mu, friction=friction)
    except ValidationError as exc:
        fail(f"invalid material: {exc.errors()[0]['loc'][0]}: {exc.errors()[0]['msg']}")
    if rgb and sensor is None:
        fail("--rgb renders a virtual sensor's camera frame: give --sensor NAME as well")
    if sensor is not None:
        if n is not None:
            fail("--sensor simulates one contact; leave out --n")
        if indenter is None:
            fail("give --indenter NAME|PATH for the contact")
        from tactile_deploy.sensors.cli import single_sensor_contact

        single_sensor_contact(sensor, rgb, seed, indenter, pressing_face, x, y, theta, depth,
                              out, overwrite)
        return
    if n is None:
        if indenter is None:
            fail("give --indenter NAME|PATH for one contact, or --n N for a dataset")
        _single(indenter, pressing_face, x, y, theta, depth, material, out, overwrite)
    else:
        _batch(n, indenters, seed, shard_size, depth_range, workers, material, out, storage)


def _single(indenter, pressing_face, x, y, theta, depth, material, out: Path, overwrite: bool) -> None:
    from pydantic import ValidationError

    from tactile_deploy.atomic import write_npz
    from tactile_deploy.indenters import ContactPose, get_indenter
    from tactile_deploy.simulation.contact import ContactError, get_simulator, simulate_contact

    if out.suffix != ".npz":
        fail(f"--out must end in .npz for one contact, got {out}")
    if out.exists() and not overwrite:
        fail(f"{out} exists; pass --overwrite to replace it or choose another --out")
    if not out.parent.exists():
        fail(f"output folder {out.parent} does not exist; create it first")
    try:
        ind = get_indenter(indenter, pressing_face=pressing_face)
        pose = ContactPose(x_mm=x, y_mm=y, theta_deg=theta, depth_mm=depth)
    except (ValueError, FileNotFoundError, OSError, ValidationError) as exc:
        fail(str(exc))
    sim = get_simulator(material)
    prepare_simulator(sim)
    try:
        sample = simulate_contact(ind, pose, material, simulator=sim)
    except ContactError as exc:
        fail(str(exc))
    write_npz(out, **sample.npz_arrays())
    console.print(
        f"wrote {out}: indenter {ind.name}, depth {depth:g} mm -> force {sample.force_n:.4f} N, "
        f"{int(sample.contact_mask.sum())} sensing nodes in contact, max depth "
        f"{float(sample.depth_mm.max()):.3f} mm"
    )


def _batch(n, indenters, seed, shard_size, depth_range, workers, material, out: Path, storage: str = "float16") -> None:
    from pydantic import ValidationError

    from tactile_deploy.simulation.contact import get_simulator
    from tactile_deploy.simulation.dataset import DatasetSpec, generate_dataset

    try:
        lo, hi = (float(v) for v in depth_range.split(","))
    except ValueError:
        fail(f"--depth-range must be 'min,max' in mm, got {depth_range!r}")
    names = _indenter_list(indenters)
    try:
        from tactile_deploy.indenters import get_indenter

        for name in names:
            get_indenter(name)
        spec = DatasetSpec(
            n_samples=n, indenters=names, seed=seed, shard_size=shard_size,
            depth_min_mm=lo, depth_max_mm=hi, material=material, storage=storage,
        )
    except (ValueError, FileNotFoundError, ValidationError) as exc:
        fail(str(exc))
    if out.suffix == ".npz":
        fail(f"--out must be a folder in batch mode, got {out}")
    prepare_simulator(get_simulator(material))
    with progress_bar(f"simulating {n} contacts", n, "samples") as advance:
        done = [0]

        def on_shard(count: int, elapsed: float) -> None:
            done[0] += count
            advance(count, rate=done[0] / max(elapsed, 1e-9))

        try:
            card = generate_dataset(spec, out, workers=workers, on_shard=on_shard)
        except ValueError as exc:
            fail(str(exc))
    console.print(
        f"wrote {len(card.shards)} shards to {out} ({sum(s.n_samples for s in card.shards)} samples); "
        f"card: {out / 'dataset.json'}"
    )
    console.print(json.dumps(card.counts_per_indenter))
