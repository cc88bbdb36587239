"""``tactile-deploy run --sensor NAME [--source ...] [--out DIR] [--every N] [--publish ADDR] [--view]``."""

from __future__ import annotations

import logging
import signal
import sys
import time
from pathlib import Path

import typer

from tactile_deploy.cli.common import console, err_console, fail


def _ask(question: str) -> bool:
    if not (sys.stdin.isatty() and sys.stdout.isatty()):
        return False
    return typer.confirm(question, default=False)


def run_command(
    sensor: str = typer.Option("gelslim2", "--sensor", help="Sensor plugin name or folder "
                               "(`tactile-deploy plugins list`)."),
    source: str | None = typer.Option(
        None, "--source", help="Frame source: demo | camera index (0), /dev/videoN, "
        "/dev/v4l/by-id/... or serial:SERIAL (`tactile-deploy cameras`) | video file "
        "| image folder | recording.npz | virtual[:NAME]. Default: the plugin's default source "
        "(the shipped plugins: their demo clip)."),
    out: Path | None = typer.Option(None, "--out", help="Folder for meshes, frames.csv, "
                                       "run.json (and previews with --view)."),
    every: int = typer.Option(1, "--every", min=1, help="Write the mesh of every N-th frame."),
    mesh: str | None = typer.Option(None, "--mesh", help="learned (the plugin's ONNX model) or "
                                    "physics (the depth map through the pad's FEM lift: any pad, "
                                    "no training). Default: learned when the plugin has a model, "
                                    "else physics."),
    plugins_dir: list[Path] | None = typer.Option(None, "--plugins-dir", help="Folder of plugin "
                                                  "folders to search first (also "
                                                  "$TACTILE_DEPLOY_PLUGIN_PATH); repeatable."),
    formats: str = typer.Option("ply,vtu", "--format", help="Mesh files to write: ply, obj, glb "
                                "(surface), vtu (volume), npz (vertices, rest_vertices, depth "
                                "arrays); comma-separated."),
    publish: str | None = typer.Option(None, "--publish", help="Stream meshes over ZeroMQ "
                                          "PUB: a port (5555: this computer only, 127.0.0.1), "
                                          "tcp://*:5555 (every interface, the network) or "
                                          "ipc:///tmp/tactile.sock (docs/runtime.md)."),
    view: bool = typer.Option(False, "--view", help="Show the run: `--view` writes preview.png "
                              "(depth map and coloured mesh) about once a second; `--view live` "
                              "serves a live 3-D view to a web browser (rerun; needs the [view] "
                              "extra)."),
    view_mode: str | None = typer.Argument(None, hidden=True, show_default=False,
                                           help="`live` after --view."),
    view_port: int = typer.Option(9090, "--view-port", min=0, max=65535, help="Port of the live "
                                  "view's page (0: any free port); its data stays on 127.0.0.1."),
    forces: bool = typer.Option(True, "--forces/--no-forces", help="Estimate contact forces "
                                "(inverse FEM; the first run computes the pad stiffness once, 15-30 s)."),
    max_frames: int | None = typer.Option(None, "--max-frames", min=1, help="Stop after N frames."),
    loop: bool = typer.Option(False, "--loop", help="Replay a recorded source endlessly (Ctrl-C ends)."),
    realtime: bool = typer.Option(False, "--realtime", help="Play recordings at their recorded pace."),
    threads: int = typer.Option(1, "--threads", min=1, help="onnxruntime threads (and numpy's BLAS threads)."),
    providers: str = typer.Option("auto", "--providers", help="onnxruntime execution providers: "
                                  "auto | cpu | cuda."),
    family_model: bool = typer.Option(False, "--family-model", help="Use the family model even "
                                      "when the plugin has an adapted one."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Write into a non-empty --out "
                                   "folder without asking."),
    colour_max_mm: float = typer.Option(1.0, "--colour-max-mm", min=1e-3, help="Displacement "
                                        "(mm) at the top of the colour scale."),
    record: bool = typer.Option(False, "--record", help="Keep the raw camera frames losslessly "
                                "(PNG) with their capture times in <--out>/frames/ (a frame "
                                "source itself: --source <out>/frames)."),
    mcap: Path | None = typer.Option(None, "--mcap", help="Record standard ROS 2 messages (raw "
                                     "frame, depth, mesh, force, pressure) into this MCAP file "
                                     "(`ros2 bag play`, Foxglove; needs the [ros] extra)."),
) -> None:
    """Turn a sensor's frames into pad meshes live: prints fps and latency; Ctrl-C ends cleanly."""
    from rich.logging import RichHandler

    logging.basicConfig(level=logging.WARNING, format="%(message)s",
                        handlers=[RichHandler(console=err_console, show_path=False)])
    from tactile_deploy.runtime.forces import ForceEstimator
    from tactile_deploy.runtime.pipeline import FrameError
    from tactile_deploy.runtime.plugins import PluginError, SensorPlugin
    from tactile_deploy.runtime.predictor import MeshPredictor, ModelContractError
    from tactile_deploy.runtime.run import (
        RunError,
        Runner,
        RunOptions,
        default_preview_dir,
        prepare_out_dir,
        summary_text,
    )
    from tactile_deploy.runtime.sources.base import SourceError
    from tactile_deploy.runtime.sources.config import SourceSpecError, parse_source
    from tactile_deploy.runtime.sources.factory import make_source
    from tactile_deploy.runtime.writers import parse_formats

    view_live = _view_mode(view, view_mode)
    view = view and not view_live
    try:
        fmts = parse_formats(formats)
    except ValueError as e:
        fail(f"--format: {e}")
    if providers not in PROVIDERS:
        fail(f"--providers {providers!r}: choose one of {', '.join(PROVIDERS)}")
    if publish:
        from tactile_deploy.runtime.publish import PublishError, bind_address

        try:
            bind_address(publish)
        except PublishError as e:
            fail(str(e))
    if record and out is None:
        fail("--record keeps the raw frames in the --out folder: give --out DIR")
    if out is not None and str(out).startswith("-"):
        fail(f"--out {out}: that looks like an option, not a folder name; give the folder first "
             "(e.g. --out run1)")
    try:
        from tactile_deploy.runtime.drift import DriftCheckingHooks, DriftMonitor
        from tactile_deploy.runtime.physics import PhysicsPredictor, choose_mesh_mode
        from tactile_deploy.runtime.plugin_dirs import add_plugin_dirs

        add_plugin_dirs(plugins_dir)
        plugin = SensorPlugin.load(sensor)
        mesh_mode, mesh_note = choose_mesh_mode(plugin, mesh)
        if mesh_note:
            err_console.print(mesh_note)
        if plugin.manifest.reference_range is not None:
            plugin.hooks = DriftCheckingHooks(plugin.hooks, DriftMonitor(
                plugin.manifest.reference_range, plugin.reference_frame, plugin.sensor_option))
        if source is None:
            config, from_manifest = plugin.manifest.default_source, True
            if loop and hasattr(config, "loop"):
                config = config.model_copy(update={"loop": True})
        else:
            config, from_manifest = parse_source(source, loop=loop), False
        if mesh_mode == "physics":
            predictor = PhysicsPredictor(plugin)
        else:
            predictor = MeshPredictor.from_plugin(plugin, adapted=False if family_model else None,
                                                  threads=threads, providers=providers)
        # the source is opened once (and closed) before --out is made: a wrong source leaves no
        # folder behind; the run opens it again (a camera does not run and drop frames meanwhile)
        src = make_source(config, plugin, from_manifest=from_manifest)
        src.connect()
        src.disconnect()
        settings = getattr(src, "settings", None) or {}
        if settings.get("delivered"):
            got, asked = settings["delivered"], settings["asked"]
            err_console.print(f"{src.name} delivers {got['width_px']}x{got['height_px']} px at "
                              f"{got['fps']:g} fps (asked {asked['width_px']}x"
                              f"{asked['height_px']} at {asked['fps'] or 'its default rate'})")
        out_dir = prepare_out_dir(out, overwrite, _ask) if out is not None else None
        preview_dir = None
        if view and out_dir is None:
            preview_dir = prepare_out_dir(default_preview_dir())
        estimator = None
        if forces and mesh_mode == "physics":
            estimator = predictor.forces       # the lift's own reaction forces
        elif forces:
            from tactile_deploy.cli.common import progress_bar
            from tactile_deploy.pad.asset import load_pad
            from tactile_deploy.runtime.forces import SurfaceStiffness

            fam, mat = plugin.manifest.family, plugin.manifest.material
            path = SurfaceStiffness.cache_path(load_pad(fam.pad, fam.pad_version), mat.nu)
            if path.is_file():
                estimator = ForceEstimator.for_plugin(plugin)
            else:
                n = len(predictor.topology.sensing_nodes)
                err_console.print(f"computing the pad's surface stiffness for nu={mat.nu} once "
                                  f"(cached in {path.parent}); --no-forces skips it")
                with progress_bar("surface stiffness", n, "columns") as advance:
                    estimator = ForceEstimator.for_plugin(plugin, progress=advance)
        sinks = _make_sinks(plugin, predictor, mcap=mcap, overwrite=overwrite,
                            colour_max_mm=colour_max_mm, view_port=view_port if view_live else None,
                            record_dir=out_dir if record else None)
        publisher = None
        if publish:
            from tactile_deploy.runtime.publish import MeshPublisher

            publisher = MeshPublisher(publish, plugin.name, predictor.topology)
            err_console.print(f"publishing meshes on {publisher.endpoint} (topics mesh/{plugin.name}, "
                              f"topology/{plugin.name})")
            if not publisher.endpoint.startswith(("tcp://127.", "ipc://", "inproc://")):
                err_console.print("  this address is reachable from the network: anyone who "
                                  "can reach it receives the meshes (a port alone, --publish "
                                  "5555, keeps them on this computer)")
    except (PluginError, ModelContractError, SourceSpecError, SourceError, RunError,
            FrameError, FileNotFoundError) as e:
        fail(str(e))
    except OSError as e:  # a file that cannot be read or written
        where = f" ({e.filename})" if e.filename else ""
        fail(f"{e.strerror or e}{where}: check that the file exists and its permissions")
    except Exception as e:  # e.g. the publisher's or the live view's bind error
        from tactile_deploy.runtime.publish import PublishError

        if isinstance(e, PublishError):
            fail(str(e))
        if view_live and "address" in str(e).lower():
            fail(f"the live view cannot listen on port {view_port}: {e}; pass another "
                 "--view-port (0: any free port)")
        raise

    options = RunOptions(out_dir=out_dir, every=every, formats=fmts, publish=publish, view=view,
                         preview_dir=preview_dir or out_dir, forces=forces,
                         max_frames=max_frames, realtime=realtime, colour_max_mm=colour_max_mm)
    live = err_console.is_terminal
    last_line = [0.0]

    def status(line: str) -> None:
        if live:          # one line, rewritten in place
            err_console.file.write("\r" + line[: err_console.width - 1].ljust(err_console.width - 1))
            err_console.file.flush()
        elif time.monotonic() - last_line[0] >= 5.0:   # logs: a line every 5 s
            last_line[0] = time.monotonic()
            print(line, file=sys.stderr, flush=True)

    runner = Runner(predictor, src, options, forces=estimator, publisher=publisher,
                    status=status, sensor=plugin.name, sinks=sinks)
    previous = signal.signal(signal.SIGTERM, _raise_interrupt)
    model = predictor.model_path
    if model.is_relative_to(plugin.folder.resolve()):
        model = model.relative_to(plugin.folder.resolve())
    adapted = "adapted " if predictor.metadata.get("adapted") == "true" else ""
    err_console.print(f"running {plugin.name} on {src.name} with {predictor.providers[0]}, {adapted}model "
                      f"{model.as_posix()} (Ctrl-C to stop)")
    from threadpoolctl import threadpool_limits

    try:
        # numpy's BLAS (read-out, forces) at --threads as well: its default pool beside onnxruntime's
        # threads made the force stage 25x and the read-out 3x slower on a 2-core machine
        with threadpool_limits(limits=threads, user_api="blas"):
            summary = runner.run()
    except (SourceError, RunError) as e:
        if live:
            err_console.file.write("\n")
        fail(str(e), code=1)
    finally:
        signal.signal(signal.SIGTERM, previous)
    if live:
        err_console.file.write("\n")
    console.print(summary_text(summary))
    if out_dir is not None:
        console.print(f"outputs in {out_dir}")
    elif preview_dir is not None:
        console.print(f"preview in {preview_dir / 'preview.png'}")
    viewer = next((s for s in sinks if s.name == "live view"), None)
    if viewer is not None and summary.stopped_by != "interrupted":
        _keep_serving(viewer)
    if summary.write_error or any(r.get("error") for r in summary.sinks.values()):
        raise typer.Exit(1)
    if summary.frames == 0 and summary.stopped_by != "interrupted":
        fail(f"no frame of {src.name} became a mesh ({summary.bad_frames} refused, "
             f"{summary.unreadable_frames} unreadable): check that the source holds this "
             f"sensor's camera frames ({plugin.name} expects "
             f"{plugin.manifest.camera.image_width_px} x {plugin.manifest.camera.image_height_px} px RGB)",
             code=1)


def _view_mode(view: bool, mode: str | None) -> bool:
    """True for ``--view live``; ``--view`` alone (or ``--view png``) is the PNG preview."""
    if mode is None:
        return False
    if not view or mode not in ("live", "png"):
        fail(f"unexpected argument {mode!r}: `run` takes options only (did you mean "
             "`--view live`?)")
    return mode == "live"


def _keep_serving(viewer) -> None:
    """After a finite source ended the live view stays up until Ctrl-C (or SIGTERM)."""
    previous = signal.getsignal(signal.SIGTERM)
    try:
        signal.signal(signal.SIGTERM, _raise_interrupt)
        err_console.print(f"the live view stays at {viewer.url} until Ctrl-C")
        while True:
            time.sleep(0.5)
    except KeyboardInterrupt:
        pass
    finally:
        signal.signal(signal.SIGTERM, previous)


def _make_sinks(plugin, predictor, *, mcap: Path | None, overwrite: bool,
                colour_max_mm: float, view_port: int | None = None,
                record_dir: Path | None = None) -> list:
    """The recordings and viewers a run feeds (runtime/sinks.py); refuses before the run starts
    what cannot work (a missing extra, a file that would be written over)."""
    from tactile_deploy.runtime.run import RunError

    sinks = []
    if record_dir is not None:
        from tactile_deploy.runtime.record import RawFrameRecorder
        from tactile_deploy.runtime.run import RECORD_FOLDER

        sinks.append(RawFrameRecorder(record_dir / RECORD_FOLDER))
    if mcap is not None:
        _need("mcap", "ros", "--mcap")
        _need("rosbags", "ros", "--mcap")
        from tactile_deploy.outputs import OutputPathError, check_output_file

        try:
            mcap = check_output_file(Path(mcap).expanduser(), "--mcap", overwrite=overwrite,
                                     suffixes=(".mcap",))
        except OutputPathError as e:
            raise RunError(str(e)) from None
        from tactile_deploy.runtime.ros.mcap_recorder import McapRecorder

        sinks.append(McapRecorder(mcap, plugin.name, predictor.topology,
                                  colour_max_mm=colour_max_mm))
    if view_port is not None:
        _need("rerun", "view", "--view live")
        from tactile_deploy.runtime.live_view import LiveView

        viewer = LiveView(plugin.name, predictor.topology, web_port=view_port,
                          colour_max_mm=colour_max_mm)
        url = viewer.serve()
        err_console.print(f"live view: open {url} in a web browser")
        sinks.append(viewer)
    return sinks


def _need(module: str, extra: str, option: str) -> None:
    import importlib.util

    if importlib.util.find_spec(module) is None:
        fail(f"{option} needs the Python package {module!r}: pip install 'tactile-deploy[{extra}]'")


#: onnxruntime execution providers `--providers` accepts.
PROVIDERS = ("auto", "cpu", "cuda")


def _raise_interrupt(signum, frame) -> None:
    raise KeyboardInterrupt
