"""The sensor loop behind ``tactile-deploy run``: frames in, meshes (and forces) out.

Per frame (:meth:`Runner.step`): read the frame -> :func:`~tactile_deploy.runtime.pipeline.
frame_to_mesh` (imaging stages, then the ONNX model) -> contact forces -> publish -> queue mesh
files -> preview. What can go wrong and what happens:

* a frame the pipeline refuses (wrong size or type): logged (first few, then every 100th),
  counted, skipped; ``max_bad_frames`` refused frames in a row stop the run with the last error;
* frames outside the model's training range (OOD score above the threshold): a warning when the
  stream leaves the range and when it returns; counted;
* a camera that vanishes: the source reconnects with back-off (logged); if it does not come back
  the run stops with :class:`~tactile_deploy.runtime.sources.base.SourceDisconnectedError`;
* mesh files that cannot be written: logged once, writing stops, the loop goes on;
* Ctrl-C (KeyboardInterrupt) or SIGTERM (the CLI maps it to KeyboardInterrupt): the loop ends,
  queued meshes are written, the source and the publisher are closed, the summary is returned;
  further Ctrl-C / SIGTERM while the outputs are finished are held back (in the main thread),
  so frames.csv and run.json are always complete.

Latency is from the frame's capture to its mesh (and forces). With ``realtime``, a recording's
frame counts as captured when it is due, so the pacing wait is not latency.

Statistics use fixed-size ring buffers, so memory stays flat however long the run.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import json
import logging
import os
import signal
import threading
import time
from collections import deque
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from pydantic import ValidationError

from tactile_deploy.runtime.pipeline import FrameError, Laps, frame_to_mesh
from tactile_deploy.runtime.run_record import RunRecord
from tactile_deploy.runtime.sinks import FrameResult

log = logging.getLogger(__name__)

#: Samples kept for the percentiles of latency and stage times.
RING = 2048


class RunError(RuntimeError):
    """The run cannot start or cannot go on (the message says why and what to do)."""


@dataclass
class RunOptions:
    """Options of a run (see ``tactile-deploy run --help``)."""

    out_dir: Path | None = None
    every: int = 1
    formats: tuple[str, ...] = ("ply", "vtu")
    publish: str | None = None
    view: bool = False
    preview_dir: Path | None = None
    forces: bool = True
    clip_tension: bool = False
    max_frames: int | None = None
    realtime: bool = False
    preview_every_s: float = 1.0
    status_every_s: float = 0.5
    colour_max_mm: float = 1.0
    max_bad_frames: int = 50


@dataclass
class RunSummary:
    """What a run did. Times in ms, rates in frames per second."""

    sensor: str
    source: str
    frames: int = 0
    bad_frames: int = 0
    ood_frames: int = 0
    dropped_frames: int = 0
    unreadable_frames: int = 0
    unreadable_files: list = field(default_factory=list)
    reconnects: int = 0
    meshes_written: int = 0
    meshes_skipped: int = 0
    meshes_skipped_reasons: dict = field(default_factory=dict)
    write_error: str | None = None
    previews_written: int = 0
    published: int = 0
    wall_s: float = 0.0
    fps: float = 0.0
    latency_p50_ms: float | None = None
    latency_p95_ms: float | None = None
    stage_p50_ms: dict = field(default_factory=dict)
    last_total_force_n: float | None = None
    stopped_by: str = "end of source"
    sinks: dict = field(default_factory=dict)
    source_settings: dict = field(default_factory=dict)


class _Ring:
    """Fixed-size sample buffer for percentiles."""

    def __init__(self, n: int = RING):
        self.a = np.full(n, np.nan)
        self.i = 0

    def add(self, x: float) -> None:
        self.a[self.i % len(self.a)] = x
        self.i += 1

    def pct(self, q: float) -> float | None:
        """The q-th percentile of the samples kept, None before the first sample."""
        v = self.a[: min(self.i, len(self.a))]
        return float(np.percentile(v, q)) if len(v) else None


#: Files a run writes into --out (glob patterns); ``--overwrite`` removes these first.
RUN_OUTPUTS = ("mesh_[0-9]*.ply", "mesh_[0-9]*.obj", "mesh_[0-9]*.glb", "mesh_[0-9]*.vtu",
               "mesh_[0-9]*.npz", ".mesh_*.partial.*", "frames.csv", ".frames.csv.partial",
               "run.json", ".run.*.partial.json", "preview.png", "preview_peak.png",
               ".preview*.partial.png")
#: The folder ``--record`` writes raw frames into.
RECORD_FOLDER = "frames"


def clear_previous_run(path: Path) -> int:
    """Remove what an earlier run wrote into ``path`` (:data:`RUN_OUTPUTS`, and the raw frames
    folder of ``--record`` when it holds only a recording); other files stay. Returns the
    number of files removed."""
    import shutil

    removed = 0
    for pattern in RUN_OUTPUTS:
        for p in path.glob(pattern):
            if p.is_file():
                p.unlink()
                removed += 1
    rec = path / RECORD_FOLDER
    if rec.is_dir():
        files = list(rec.iterdir())
        ours = [p for p in files if p.name == "timestamps.csv"
                or (p.name.startswith(("frame_", ".frame_")) and p.suffix == ".png")]
        if len(ours) == len(files):
            shutil.rmtree(rec)
            removed += len(files)
        else:
            log.warning("%s holds files --record did not write; left as it is", rec)
    return removed


def prepare_out_dir(path: Path, overwrite: bool = False, ask=None) -> Path:
    """Create or check an output folder: never write into a folder holding files unless the
    user agrees (``ask(question) -> bool``, or ``overwrite``), and then remove the previous
    run's files (:func:`clear_previous_run`) so the folder holds this run only; check it is
    writable."""
    path = Path(path).expanduser()
    if path.exists() and not path.is_dir():
        raise RunError(f"--out {path} is a file, not a folder; choose a folder name")
    if path.is_dir():
        existing = [p for p in path.iterdir()]
        if existing and not overwrite:
            question = (f"{path} already holds {len(existing)} file(s); remove the previous "
                        "run's meshes, frames.csv, run.json, previews and recorded frames and "
                        "write there (other files stay)?")
            if ask is None or not ask(question):
                raise RunError(f"{path} already holds {len(existing)} file(s) (e.g. "
                               f"{existing[0].name}); choose another --out, or pass --overwrite "
                               "to replace the previous run's files there")
        if existing:
            n = clear_previous_run(path)
            if n:
                log.warning("removed %d file(s) of the previous run from %s", n, path)
    else:
        try:
            path.mkdir(parents=True)
        except OSError as e:
            raise RunError(f"cannot create output folder {path}: {e.strerror}; choose another "
                           "--out") from None
    probe = path / f".write-test-{os.getpid()}"
    try:
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as e:
        raise RunError(f"cannot write into output folder {path}: {e.strerror}; fix its "
                       "permissions or choose another --out") from None
    return path


class Runner:
    """The loop (module docstring). ``predictor`` has a pipeline (``MeshPredictor.from_plugin``);
    ``forces`` is a :class:`~tactile_deploy.runtime.forces.ForceEstimator` or None;
    ``status(text)`` receives a live status line every ``status_every_s``."""

    def __init__(self, predictor, source, options: RunOptions | None = None, forces=None,
                 publisher=None, status=None, sensor: str | None = None, sinks=()):
        self.predictor = predictor
        self.source = source
        self.opt = options or RunOptions()
        if self.opt.every < 1:
            raise RunError(f"--every must be >= 1, got {self.opt.every}")
        self.forces = forces
        self.publisher = publisher
        self.sinks = list(sinks)          # FrameSink: recordings, live view (runtime/sinks.py)
        self.status = status
        self.sensor = sensor or getattr(getattr(predictor, "plugin", None), "name", "sensor")
        self.summary = RunSummary(self.sensor, getattr(source, "name", str(source)))
        self.writer = None
        self.renderer = None
        self._lat = _Ring()
        self._stages: dict[str, _Ring] = {}
        self._consecutive_bad = 0
        self._stop = threading.Event()
        self._in_ood = False
        self._last_status = 0.0
        self._last_preview = -1e18
        self._t0 = time.monotonic()
        # frame times of the last 2 s, at most 256 frames (fps); bounded so memory does not follow the frame rate
        self._recent: deque[float] = deque(maxlen=256)
        self._frame_log = None
        self._last = None
        self._peak = None

    @property
    def _wants_pressure(self) -> bool:
        """Per-node pressures cost a dense product per frame: only when someone sends them."""
        return self.publisher is not None or any(s.wants_pressure for s in self.sinks)

    # ------------------------------------------------------------------ setup / teardown
    def _open_outputs(self) -> None:
        o = self.opt
        topo = self.predictor.topology
        if o.out_dir is not None:
            from tactile_deploy.runtime.writers import MeshWriter

            pipeline = getattr(self.predictor, "pipeline", None)
            self.writer = MeshWriter(o.out_dir, topo, o.formats, o.colour_max_mm,
                                     depth_grid=getattr(pipeline, "depth_grid", None))
            from tactile_deploy.runtime.frame_log import FrameLog

            self._frame_log = FrameLog(o.out_dir, self.writer)
        if o.view:
            from tactile_deploy.runtime.preview import MeshRenderer

            if o.preview_dir is None:
                o.preview_dir = o.out_dir
            self.renderer = MeshRenderer(topo, max_mm=o.colour_max_mm)
        for sink in self.sinks:
            sink.start(live=source_is_live(self.source))

    def _close_outputs(self) -> None:
        if self.writer is not None:
            self.writer.close()
            self.summary.meshes_written = self.writer.written
            self.summary.meshes_skipped = self.writer.skipped
            self.summary.meshes_skipped_reasons = dict(self.writer.skipped_reasons)
            self.summary.write_error = self.writer.error
        if self._frame_log is not None:
            try:
                self._frame_log.close()
            except OSError as e:
                log.error("could not finish %s: %s", self.opt.out_dir / "frames.csv", e)
        if self.renderer is not None and self._last is not None:
            self._write_preview(*self._last)
        if self.renderer is not None and self._peak is not None:
            self._write_preview(*self._peak[1:], name="preview_peak.png")
        if self.publisher is not None:
            self.summary.published = self.publisher.seq
            self.publisher.close()
        for sink in self.sinks:
            sink.close()
            self.summary.sinks[sink.name] = sink.report()

    # ------------------------------------------------------------------ the loop
    def run(self) -> RunSummary:
        """Run until the source ends, ``max_frames``, Ctrl-C, or an error (re-raised after the
        outputs are closed)."""
        self._open_outputs()
        self._t0 = time.monotonic()
        pace = None  # (monotonic ns, recording ns) of the frame the pacing counts from
        last_t_source = None
        try:
            with self.source:
                while True:
                    if self.opt.max_frames is not None and self.summary.frames >= self.opt.max_frames:
                        self.summary.stopped_by = "max frames"
                        break
                    if self._stop.is_set():
                        self.summary.stopped_by = "stopped"
                        break
                    frame = self.source.read()
                    if frame is None:
                        break
                    due_ns = None
                    if self.opt.realtime and frame.t_source_ns is not None:
                        if pace is None or frame.t_source_ns < last_t_source:  # first, or a loop restarts
                            pace = (time.monotonic_ns(), frame.t_source_ns)
                        last_t_source = frame.t_source_ns
                        due_ns = pace[0] + frame.t_source_ns - pace[1]
                        wait = (due_ns - time.monotonic_ns()) / 1e9
                        if wait > 0:
                            time.sleep(wait)
                    self.step(frame, due_ns)
                stats = self.source.stats
        except KeyboardInterrupt:
            self.summary.stopped_by = "interrupted"
            stats = self.source.stats
        except Exception:
            self.summary.stopped_by = "error"
            stats = self.source.stats
            self._finish(stats)
            raise
        self._finish(stats)
        return self.summary

    def _mesh_dropped(self, index: int) -> str:
        """The reason the mesh of frame ``index`` was not queued; warned about (first, then
        every 100th), counted in the summary."""
        w = self.writer
        reason = max(w.skipped_reasons, key=w.skipped_reasons.get) if w.skipped_reasons else "?"
        if w.skipped == 1 or w.skipped % 100 == 0:
            log.warning("mesh of frame %d not written (%d so far): %s%s", index, w.skipped,
                        reason, "; write fewer --format or a larger --every"
                        if reason.startswith("writer queue") else "")
        return reason

    def stop(self) -> None:
        """Ask a run going on in another thread to end after the current frame (as Ctrl-C)."""
        self._stop.set()

    def _finish(self, stats) -> None:
        held: list[int] = []
        with _interrupts_held(held):
            if held:
                self.summary.stopped_by = "interrupted"
            self._finish_outputs(stats)

    def _finish_outputs(self, stats) -> None:
        s = self.summary
        s.dropped_frames = stats.dropped
        s.unreadable_frames = stats.unreadable
        s.unreadable_files = list(getattr(self.source, "unreadable_files", []))
        s.reconnects = stats.reconnects
        s.source_settings = dict(getattr(self.source, "settings", None) or {})
        s.wall_s = time.monotonic() - self._t0
        s.fps = s.frames / s.wall_s if s.wall_s > 0 else 0.0
        s.latency_p50_ms = self._lat.pct(50)
        s.latency_p95_ms = self._lat.pct(95)
        s.stage_p50_ms = {k: round(r.pct(50), 4) for k, r in self._stages.items()}
        self._close_outputs()
        if self.opt.out_dir is not None:
            from tactile_deploy.atomic import finite_or_null, write_json

            doc = finite_or_null({**asdict(s), **self._provenance(),
                                  "finished": _dt.datetime.now().isoformat(timespec="seconds")})
            try:
                doc = RunRecord.model_validate(doc).model_dump(mode="json")
            except ValidationError as e:  # a defect: keep the summary all the same
                log.error("the run summary breaks the run.json format (%s); written as it is", e)
            try:
                write_json(self.opt.out_dir / "run.json", doc)
            except OSError as e:
                log.error("could not write the run summary into %s: %s", self.opt.out_dir, e)

    def _provenance(self) -> dict:
        """run.json's tool, model and plugin (versions and sha256); a failure is logged and
        leaves them out (the run's summary is written all the same)."""
        from tactile_deploy.runtime.provenance import run_provenance

        try:
            return run_provenance(self.predictor)
        except (OSError, ValueError, AttributeError) as e:
            log.error("could not record the tool, model and plugin of the run: %s", e)
            return {}

    def step(self, frame, due_ns: int | None = None) -> None:
        """Process one :class:`~tactile_deploy.runtime.sources.base.Frame`; ``due_ns``: when a
        paced recording's frame was due (monotonic ns), its capture time for the latency."""
        o, s = self.opt, self.summary
        laps = Laps().start()
        try:
            pred = frame_to_mesh(frame.image, self.predictor.pipeline, self.predictor,
                                 laps).single()
        except FrameError as e:
            s.bad_frames += 1
            self._consecutive_bad += 1
            if s.bad_frames <= 3 or s.bad_frames % 100 == 0:
                log.warning("frame %d skipped (%d so far): %s", frame.index, s.bad_frames, e)
            if self._consecutive_bad >= o.max_bad_frames:
                raise RunError(f"{self._consecutive_bad} frames in a row were refused; the last: "
                               f"{e}") from None
            return
        self._consecutive_bad = 0
        force = None
        if self.forces is not None:
            force = self.forces.estimate(pred.vertices_mm, clip_tension=o.clip_tension,
                                         pressure=self._wants_pressure)
            laps.lap("forces")
        captured_ns = frame.t_mono_ns if due_ns is None else max(frame.t_mono_ns, due_ns)
        latency_ms = (time.monotonic_ns() - captured_ns) / 1e6
        self._track_ood(frame.index, pred)
        if self.publisher is not None:
            self.publisher.publish(
                pred.vertices_mm, frame_index=frame.index, t_capture_ns=frame.t_wall_ns,
                latency_ms=latency_ms, ood_score=pred.ood_score,
                in_distribution=pred.in_distribution,
                total_normal_force_n=None if force is None else force.total_normal_force_n,
                pressure_kpa=None if force is None or not force.pressure_kpa.size
                else force.pressure_kpa)
            laps.lap("publish")
        if self.sinks:
            result = FrameResult(frame, pred, force, latency_ms)
            for sink in self.sinks:
                sink.consume(result)
            laps.lap("sinks")
        mesh_status = "no mesh files" if self.writer is None else "not requested"
        if self.writer is not None and frame.index % o.every == 0:
            queued = self.writer.submit(frame.index, pred.vertices_mm,
                               block=not source_is_live(self.source),
                               depth_mm=pred.depth_mm,
                               metadata={"sensor": self.sensor, "frame_index": frame.index,
                                         "t_capture_ns": frame.t_wall_ns,
                                         "t_source_ns": frame.t_source_ns,
                                         "source_label": frame.label,
                                         "ood_score": float(pred.ood_score),
                                         "total_normal_force_n": None if force is None
                                         else float(force.total_normal_force_n)})
            mesh_status = None if queued else f"dropped: {self._mesh_dropped(frame.index)}"
        if self._frame_log is not None:
            self._frame_log.add(frame, pred, force, latency_ms, mesh_status)
        s.frames += 1
        if force is not None:
            s.last_total_force_n = float(force.total_normal_force_n)
        self._lat.add(latency_ms)
        for k, v in laps.times_ns.items():
            self._stages.setdefault(k, _Ring()).add(v / 1e6)
        now = time.monotonic()
        if self.renderer is not None:
            self._last = (frame.index, pred, force)
            deepest = float(pred.depth_mm.max())
            if self._peak is None or deepest > self._peak[0]:
                self._peak = (deepest, frame.index, pred, force)
            if now - self._last_preview >= o.preview_every_s:
                self._write_preview(frame.index, pred, force)
                self._last_preview = now
        self._recent.append(now)
        while now - self._recent[0] > 2.0:
            self._recent.popleft()
        if self.status is not None and now - self._last_status >= o.status_every_s:
            self._last_status = now
            self.status(self.status_line())

    def status_line(self) -> str:
        fps = (len(self._recent) - 1) / (self._recent[-1] - self._recent[0]) if len(
            self._recent) > 1 and self._recent[-1] > self._recent[0] else 0.0
        s = self.summary
        force = "" if s.last_total_force_n is None else f"  force {s.last_total_force_n:6.2f} N"
        p50 = self._lat.pct(50)
        latency = "   -  " if p50 is None else f"{p50:6.2f}"
        return (f"{self.sensor}: frame {s.frames}{self._progress(fps)}  {fps:7.1f} fps  "
                f"latency p50 {latency} ms{force}  dropped {self.source.stats.dropped}  "
                f"ood {s.ood_frames}  bad {s.bad_frames}")

    def expected_frames(self) -> int | None:
        """Frames the run will process when it ends by itself (the source's count, at most
        ``max_frames``), None when unknown (a camera without --max-frames, a looped clip)."""
        n = getattr(self.source, "frame_count", None)
        m = self.opt.max_frames
        if n is None:
            return m
        return n if m is None else min(n, m)

    def _progress(self, fps: float) -> str:
        total = self.expected_frames()
        if not total:
            return ""
        done = self.summary.frames + self.summary.bad_frames
        eta = f", ETA {max(total - done, 0) / fps:.0f} s" if fps > 0 else ""
        return f"/{total} ({100.0 * done / total:.0f} %{eta})"

    def _track_ood(self, index: int, pred) -> None:
        if not pred.in_distribution:
            self.summary.ood_frames += 1
            if not self._in_ood:
                self._in_ood = True
                log.warning("frame %d is outside the model's training range (OOD score %.3g > "
                            "%.3g): its mesh may be wrong", index, pred.ood_score,
                            self.predictor.ood_threshold)
        elif self._in_ood:
            self._in_ood = False
            log.warning("frame %d: back inside the training range (OOD score %.3g)", index,
                        pred.ood_score)

    def _write_preview(self, index, pred, force, name: str = "preview.png") -> None:
        from tactile_deploy.runtime.preview import compose_preview, write_png

        if self.opt.preview_dir is None:
            return
        mesh_rgb = self.renderer.render(pred.vertices_mm)
        force_txt = ("" if force is None
                     else f"   total normal force {force.total_normal_force_n:.3f} N")
        inside = "in" if pred.in_distribution else "OUT OF"
        lines = [
            (f"{self.sensor} frame {index}   max depth {float(pred.depth_mm.max()):.3f} mm   "
             f"max displacement {float(np.linalg.norm(pred.displacement_mm, axis=-1).max()):.3f} mm"),
            f"OOD score {pred.ood_score:.3g} ({inside} training range){force_txt}",
            (f"colour scale 0-{self.opt.colour_max_mm:g} mm (left: depth, right: "
             "displacement magnitude, z x3)"),
        ]
        img = compose_preview(pred.depth_mm, mesh_rgb, lines, self.opt.colour_max_mm)
        try:
            write_png(self.opt.preview_dir / name, img)
            self.summary.previews_written += 1
        except OSError as e:
            log.error("could not write the preview into %s: %s", self.opt.preview_dir, e)
            self.renderer = None


def source_is_live(source) -> bool:
    """A live source (a camera) keeps capturing while the loop waits, so the loop must not wait
    for a disk; a recording (even looped) loses nothing by waiting."""
    live = getattr(source, "live", None)
    return bool(live) if live is not None else not getattr(source, "finite", True)


@contextlib.contextmanager
def _interrupts_held(held: list | None = None):
    """Hold Ctrl-C and SIGTERM back while the outputs are finished (a second Ctrl-C would leave
    frames.csv half-written); the signals that came are appended to ``held``. Signals can only
    be handled in the main thread, elsewhere this does nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held = [] if held is None else held

    def hold(signum, _frame):
        if not held:
            log.warning("finishing the outputs; they will be complete in a moment")
        held.append(signum)

    previous = {sig: signal.signal(sig, hold) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def default_preview_dir() -> Path:
    """A new folder for previews when ``--view`` is given without ``--out``."""
    stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    return Path.cwd() / f"tactile-preview-{stamp}"


def summary_text(s: RunSummary) -> str:
    stages = ", ".join(f"{k} {v:.3f}" for k, v in s.stage_p50_ms.items())
    lines = [
        (f"{s.sensor} from {s.source}: {s.frames} frames in {s.wall_s:.2f} s "
         f"({s.fps:.1f} fps), stopped by {s.stopped_by}"),
    ]
    if s.latency_p50_ms is not None:
        lines += [f"  latency capture->mesh p50 {s.latency_p50_ms:.2f} ms, p95 {s.latency_p95_ms:.2f} ms",
                  f"  stages p50 (ms): {stages}"]
    got = s.source_settings.get("delivered")
    if got:
        lines.append(f"  camera delivered {got['width_px']}x{got['height_px']} px "
                     f"{got.get('fourcc') or ''} at {got['fps']:g} fps, exposure "
                     f"{got['exposure']:g} (auto {got['auto_exposure']:g}), white balance "
                     f"{got['white_balance_k']:g} K (auto {got['auto_white_balance']:g})")
    unreadable = ""
    if s.unreadable_frames:
        names = ", ".join(s.unreadable_files[:5]) + (" ..." if len(s.unreadable_files) > 5 else "")
        unreadable = f", unreadable {s.unreadable_frames}" + (f" ({names})" if names else "")
    lines.append(f"  dropped {s.dropped_frames}, reconnects {s.reconnects}, refused {s.bad_frames}"
                 f"{unreadable}, outside training range {s.ood_frames}")
    if s.meshes_written or s.write_error or s.meshes_skipped:
        why = "; ".join(f"{n} {r}" for r, n in s.meshes_skipped_reasons.items())
        lines.append(f"  meshes written {s.meshes_written}, skipped {s.meshes_skipped}"
                     + (f" ({why})" if why else ""))
    if s.write_error:
        lines.append(f"  write error: {s.write_error}")
    if s.previews_written:
        lines.append(f"  previews written {s.previews_written}")
    if s.published:
        lines.append(f"  meshes published {s.published}")
    for name, rep in s.sinks.items():
        dropped = sum(rep.get("dropped", {}).values())
        why = "; ".join(f"{n} {reason}" for reason, n in rep.get("dropped", {}).items())
        lines.append(f"  {name}: {rep.get('handled', 0)} frames" +
                     (f" ({rep['file']})" if rep.get("file") else "") +
                     (f", dropped {dropped}: {why}" if dropped else ""))
        if rep.get("error"):
            lines.append(f"  {name} error: {rep['error']}")
    return "\n".join(lines)


def json_summary(s: RunSummary) -> str:
    return json.dumps(asdict(s), indent=2)
