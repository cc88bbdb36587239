"""``tactile-deploy pad ...`` and ``tactile-deploy indenters ...``."""

from __future__ import annotations

from pathlib import Path

import typer

from tactile_deploy.cli.common import console, fail

pad_app = typer.Typer(help="The pad mesh: summary and export.", no_args_is_help=True)
indenters_app = typer.Typer(help="The indenter library.", no_args_is_help=True)


@pad_app.command("info")
def pad_info(name: str = typer.Option("gelslim", "--pad", help="Shipped pad name.")) -> None:
    """Print the frozen pad's geometry, node sets, quality figures and content hash."""
    from tactile_deploy.pad.asset import load_pad_card

    mesh = _load_pad(name)
    card = load_pad_card(name)
    g = card.geometry
    outline = (f"disc, radius {g.radius_mm} mm" if g.shape == "disc"
               else f"rectangle {g.width_mm} x {g.length_mm} mm (x by y)")
    crown = f", crown {g.dome_height_mm} mm" if g.dome_height_mm else ""
    console.print(f"pad {card.name} v{card.version}: {outline}, thickness {g.thickness_mm} mm{crown}")
    fam = card.family
    if fam is not None:
        a, dg = fam.sensing_area, fam.depth_grid
        console.print(f"  {fam.description}")
        console.print(f"  held: backplate {fam.backplate}, sides {fam.sides}")
        console.print(f"  sensing area x {a.x_min_mm:g}..{a.x_max_mm:g} mm, y {a.y_min_mm:g}.."
                      f"{a.y_max_mm:g} mm, node spacing there {card.sensing_spacing_mm} mm")
        console.print(f"  depth grid {dg.nx} x {dg.ny} cells of {dg.pitch_x_mm:.3g} mm")
        for src in fam.sources:
            console.print(f"  source: {src.what} -- {src.reference}")
        for text in fam.assumptions:
            console.print(f"  assumed: {text}")
    console.print(f"  {card.n_nodes} nodes, {card.n_tets} tets, {len(mesh.edges)} edges")
    for set_name, nodes in mesh.node_sets.items():
        console.print(f"  node set {set_name}: {len(nodes)} nodes")
    console.print(
        f"  min dihedral {card.min_dihedral_deg:.1f} deg, max dihedral {card.max_dihedral_deg:.1f} deg, "
        f"worst aspect ratio {card.worst_aspect_ratio:.2f}"
    )
    console.print(f"  content hash {card.content_hash}")


@pad_app.command("export")
def pad_export(
    out: Path = typer.Option(..., "--out", help="Output file: .vtu/.vtk/.msh/.inp/.mesh (volume) or "
                             ".stl/.ply/.obj/.glb/.off (surface)."),
    name: str = typer.Option("gelslim", "--pad", help="Shipped pad name."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing file."),
) -> None:
    """Export the rest pad mesh (volume via meshio, surface via trimesh)."""
    from tactile_deploy.outputs import OutputPathError, check_output_file
    from tactile_deploy.pad.export import (
        SURFACE_SUFFIXES,
        VOLUME_SUFFIXES,
        export_surface,
        export_volume,
    )

    try:  # a mesh suffix (volume or surface), a file in an existing folder, --overwrite to replace
        check_output_file(out, "--out", overwrite=overwrite, suffixes=VOLUME_SUFFIXES + SURFACE_SUFFIXES)
    except OutputPathError as e:
        fail(str(e))
    mesh = _load_pad(name)
    try:
        if out.suffix.lower() in SURFACE_SUFFIXES:
            export_surface(mesh, out)
        else:
            export_volume(mesh, out)
    except (ValueError, FileNotFoundError) as exc:
        fail(str(exc))
    console.print(f"wrote {out}")


def _load_pad(name: str):
    """The shipped pad ``name``, or a clean error listing the shipped pads."""
    from tactile_deploy.pad.asset import SHIPPED_PADS, load_pad

    if name not in SHIPPED_PADS:
        fail(f"--pad {name!r} is not a shipped pad; pass one of: {', '.join(sorted(SHIPPED_PADS))}")
    try:
        return load_pad(name)
    except (FileNotFoundError, ValueError) as exc:
        fail(str(exc))


@indenters_app.command("list")
def indenters_list(kind: str = typer.Option(None, "--kind", help="'primitive' or 'novel'.")) -> None:
    """List the procedural indenter library."""
    from tactile_deploy.indenters import library_entry, list_indenters
    from tactile_deploy.indenters.library import KINDS

    if kind is not None and kind not in KINDS:
        fail(f"--kind must be one of {', '.join(KINDS)}, got {kind!r}; or leave out --kind to list all")
    names = list_indenters(kind)
    for name in names:
        entry = library_entry(name)
        console.print(f"{name:18s} {entry.kind:9s} {entry.description}")
