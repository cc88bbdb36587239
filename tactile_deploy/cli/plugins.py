"""``tactile-deploy plugins list | show NAME | validate PATH | copy NAME DEST | schema``."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from tactile_deploy.cli.common import console, fail

plugins_app = typer.Typer(help="Sensor plugins: list, show, validate, copy.", no_args_is_help=True)


@plugins_app.command("list")
def plugins_list() -> None:
    """List the installed sensor plugins (and plugins shadowed by one of the same name)."""
    from rich.table import Table

    from tactile_deploy.runtime.plugins import (
        PluginError,
        discover_plugins,
        load_manifest,
    )

    by_name, shadowed = discover_plugins()
    if not by_name:
        console.print("no sensor plugins found (shipped plugins live in plugins/ of a source "
                      "checkout; add folders with $TACTILE_DEPLOY_PLUGIN_PATH)")
        return
    table = Table("name", "family", "description", "origin", "folder")
    for name, loc in sorted(by_name.items()):
        try:
            m = load_manifest(loc.folder)
            family, desc = m.family.name, m.description
        except PluginError:
            family, desc = "?", "[red]invalid manifest: run `tactile-deploy plugins validate`[/]"
        table.add_row(name, family, desc, loc.origin, str(loc.folder))
    console.print(table)
    for loc in shadowed:
        console.print(f"[yellow]shadowed:[/] {loc.name} at {loc.folder} ({loc.origin})")


@plugins_app.command("show")
def plugins_show(name: str = typer.Argument(..., help="Plugin name or folder.")) -> None:
    """Print a plugin's manifest in words (files are not checked: use `validate`)."""
    from tactile_deploy.runtime.plugins import PluginError, SensorPlugin

    try:
        plugin = SensorPlugin.load(name)
    except PluginError as e:
        fail(str(e))
    m = plugin.manifest
    cam = m.camera
    g = cam.grid
    console.print(f"[bold]{m.name}[/]  {m.description}")
    console.print(f"  folder          {plugin.folder} ({plugin.origin})")
    console.print(f"  family          {m.family.name}: pad {m.family.pad} v{m.family.pad_version}, "
                  f"mesh hash {m.family.mesh_hash[:16]}...")
    for key, ref in m.files().items():
        path = plugin.path_of(key)
        state = "" if path.is_file() else "  [red](missing)[/]"
        extra = f", noise handling '{m.noise_reference.handling}'" if key == "noise_reference" else ""
        console.print(f"  {key:15s} {path}  sha256 {ref.sha256[:12]}...{extra}{state}")
    console.print(f"  camera          {cam.image_width_px}x{cam.image_height_px} px, "
                  f"fx {cam.intrinsics.fx_px:.1f} px, k1 {cam.distortion.k1:+.4f}, "
                  f"{cam.mm_per_px_x:.4f} x {cam.mm_per_px_y:.4f} mm/px, "
                  f"{'mirrored' if cam.image_mirrored else 'not mirrored'}")
    console.print(f"  imaging grid    {g.nx}x{g.ny} over x [{g.x_min_mm:g}, {g.x_max_mm:g}] mm, "
                  f"y [{g.y_min_mm:g}, {g.y_max_mm:g}] mm ({g.pitch_x_mm:.4f} mm/px)")
    d = m.depth_grid
    console.print(f"  depth grid      {d.nx}x{d.ny} over x [{d.x_min_mm:g}, {d.x_max_mm:g}] mm, "
                  f"y [{d.y_min_mm:g}, {d.y_max_mm:g}] mm")
    if m.model is None:
        console.print("  model           none: meshes from the pad's physics lift (run --mesh "
                      "physics)")
    console.print(f"  material        E {m.material.E_mpa:g} MPa, nu {m.material.nu:g} "
                  f"({m.material.source or 'source not given'})")
    console.print(f"  default source  {m.default_source.model_dump()}")
    console.print(f"  OOD threshold   {m.ood_threshold if m.ood_threshold is not None else 'from the model'}")
    for k, v in m.provenance.items():
        console.print(f"  provenance      {k}: {v}")


@plugins_app.command("validate")
def plugins_validate(
    path: str = typer.Argument(..., help="Plugin folder (or name)."),
    no_model: bool = typer.Option(False, "--no-model", help="Skip loading the ONNX model."),
) -> None:
    """Check a plugin completely: manifest, checksums, shapes, pad hash, model contract."""
    from tactile_deploy.runtime.plugins import validate_plugin

    report = validate_plugin(path, check_model=not no_model)
    for item in report.checked:
        console.print(f"  [green]ok[/]   {item}")
    for problem in report.problems:
        console.print(f"  [red]fail[/] {problem}")
    if not report.ok:
        fail(f"plugin {path} has {len(report.problems)} problem(s)", code=1)
    console.print(f"[green]plugin {report.manifest.name} is valid[/]")


@plugins_app.command("copy")
def plugins_copy(
    name: str = typer.Argument(..., help="Plugin name or folder."),
    dest: Path = typer.Argument(..., help="New folder for the copy (must not exist)."),
    with_adapted: bool = typer.Option(False, "--with-adapted",
                                      help="Also copy the adapted model versions."),
    model: Optional[Path] = typer.Option(
        None, "--model", help="An ONNX family model for the copy to run instead of the original's, "
        "checked against the plugin's pad: e.g. exported/gelslim_mesh_grip.onnx for a gel that grips "
        "the object (Coulomb friction or sticking; docs/predictor.md)."),
) -> None:
    """Copy a plugin to a folder of your own (e.g. a writable one to adapt it), keeping the files
    it shares with other plugins (the family model) where they are. The copy's plugin name is
    DEST's folder name: the original's name makes it shadow the original, another name makes it a
    plugin of its own."""
    from tactile_deploy.runtime.plugins import PluginError, SensorPlugin, copy_plugin, discover_plugins

    try:
        original = SensorPlugin.load(name).name
        out = copy_plugin(name, dest, with_adapted, model)
    except (PluginError, OSError) as e:
        fail(str(e))
    current = discover_plugins()[0].get(out.name)
    if current is not None and current.folder.resolve() == out.resolve():
        use = f"its folder is on $TACTILE_DEPLOY_PLUGIN_PATH: `--sensor {out.name}` runs it"
    else:
        use = f"put {out.parent} on $TACTILE_DEPLOY_PLUGIN_PATH to run it with `--sensor {out.name}`"
        if current is not None:
            use += f"; it then shadows the plugin {out.name!r} in {current.folder}"
        else:
            use += "; it shadows no other plugin"
    renamed = "" if out.name == original else f" (renamed from {original!r}; meshes on mesh/{out.name})"
    runs = f"; it runs the model {model}" if model is not None else ""
    console.print(f"copied plugin {original} to {out} as plugin {out.name!r}{renamed}{runs}; {use}")


@plugins_app.command("schema")
def plugins_schema(out: Path | None = typer.Option(None, help="Write to this file instead of "
                                                      "printing.")) -> None:
    """Print (or write) the JSON Schema of plugin.json."""
    from tactile_deploy.fileformat import schema_text
    from tactile_deploy.runtime.plugins import PluginManifest

    if out is None:
        typer.echo(schema_text(PluginManifest), nl=False)
        return
    if out.exists():
        fail(f"{out} exists; choose another file name")
    from tactile_deploy.atomic import write_text

    write_text(out, schema_text(PluginManifest))
    console.print(f"wrote {out}")
