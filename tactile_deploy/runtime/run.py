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

from tactile_deploy.runtime.pipeline import FrameError, Laps, frame_to_mesh

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


def prepare_out_dir(path: Path, overwrite: bool = False, ask=None) -> Path:
    """Create or check an output folder: never write into a folder holding files unless the
    user agrees (``ask(question) -> bool``, or ``overwrite``); check it is writable."""
    path = Path(path).expanduser()
    if path.exists() and not path.is_dir():
        raise RunError(f"--out {path} is a file, not a folder; choose a folder name")
    if path.is_dir():
        existing = [p for p in path.iterdir()]
        if existing and not overwrite:
            question = (f"{path} already holds {len(existing)} file(s); write into it and replace "
                        "files of the same names?")
            if ask is None or not ask(question):
                raise RunError(f"{path} already holds {len(existing)} file(s) (e.g. "
                               f"{existing[0].name}); choose another --out, or pass --overwrite "
                               "to write into it")
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
                 publisher=None, status=None, sensor: str | None = None):
        self.predictor = predictor
        self.source = source
        self.opt = options or RunOptions()
        if self.opt.every < 1:
            raise RunError(f"--every must be >= 1, got {self.opt.every}")
        self.forces = forces
        self.publisher = publisher
        self.status = status
        self.sensor = sensor or getattr(getattr(predictor, "plugin", None), "name", "sensor")
        self.summary = RunSummary(self.sensor, getattr(source, "name", str(source)))
        self.writer = None
        self.renderer = None
        self._lat = _Ring()
        self._stages: dict[str, _Ring] = {}
        self._consecutive_bad = 0
        self._in_ood = False
        self._last_status = 0.0
        self._last_preview = -1e18
        self._t0 = time.monotonic()
        # frame times of the last 2 s, at most 256 frames (fps); bounded so memory does not follow the frame rate
        self._recent: deque[float] = deque(maxlen=256)
        self._csv = None
        self._csv_tmp = None
        self._last = None
        self._peak = None

    # ------------------------------------------------------------------ setup / teardown
    def _open_outputs(self) -> None:
        o = self.opt
        topo = self.predictor.topology
        if o.out_dir is not None:
            from tactile_deploy.runtime.writers import MeshWriter

            pipeline = getattr(self.predictor, "pipeline", None)
            self.writer = MeshWriter(o.out_dir, topo, o.formats, o.colour_max_mm,
                                     depth_grid=getattr(pipeline, "depth_grid", None))
            self._csv_tmp = o.out_dir / ".frames.csv.partial"
            self._csv = open(self._csv_tmp, "w", encoding="utf-8")
            self._csv.write("frame_index,t_capture_ns,latency_ms,ood_score,in_distribution,"
                            "total_normal_force_n,source_label\n")
        if o.view:
            from tactile_deploy.runtime.preview import MeshRenderer

            if o.preview_dir is None:
                o.preview_dir = o.out_dir
            self.renderer = MeshRenderer(topo, max_mm=o.colour_max_mm)

    def _close_outputs(self) -> None:
        if self.writer is not None:
            self.writer.close()
            self.summary.meshes_written = self.writer.written
            self.summary.meshes_skipped = self.writer.skipped
            self.summary.write_error = self.writer.error
        if self._csv is not None:
            try:
                self._csv.close()
                os.replace(self._csv_tmp, self.opt.out_dir / "frames.csv")
            except OSError as e:
                log.error("could not finish %s: %s", self.opt.out_dir / "frames.csv", e)
        if self.renderer is not None and self._last is not None:
            self._write_preview(*self._last)
        if self.renderer is not None and self._peak is not None:
            self._write_preview(*self._peak[1:], name="preview_peak.png")
        if self.publisher is not None:
            self.summary.published = self.publisher.seq
            self.publisher.close()

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
        s.wall_s = time.monotonic() - self._t0
        s.fps = s.frames / s.wall_s if s.wall_s > 0 else 0.0
        s.latency_p50_ms = self._lat.pct(50)
        s.latency_p95_ms = self._lat.pct(95)
        s.stage_p50_ms = {k: round(r.pct(50), 4) for k, r in self._stages.items()}
        self._close_outputs()
        if self.opt.out_dir is not None:
            from tactile_deploy.atomic import write_json

            try:
                write_json(self.opt.out_dir / "run.json",
                           {**asdict(s), "finished": _dt.datetime.now().isoformat(timespec="seconds")})
            except OSError as e:
                log.error("could not write the run summary into %s: %s", self.opt.out_dir, e)

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
            # per-node pressures cost a dense product; only the publisher sends them
            force = self.forces.estimate(pred.vertices_mm, clip_tension=o.clip_tension,
                                         pressure=self.publisher is not None)
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
        if self.writer is not None and frame.index % o.every == 0:
            self.writer.submit(frame.index, pred.vertices_mm,
                               block=getattr(self.source, "finite", False),
                               depth_mm=pred.depth_mm)
        if self._csv is not None:
            f_txt = "" if force is None else f"{force.total_normal_force_n:.6g}"
            label = "" if frame.label is None else _csv_field(frame.label)
            self._csv.write(f"{frame.index},{frame.t_wall_ns},{latency_ms:.4f},"
                            f"{pred.ood_score:.6g},{int(pred.in_distribution)},{f_txt},{label}\n")
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
        return (f"{self.sensor}: frame {s.frames}  {fps:7.1f} fps  latency p50 "
                f"{latency} ms{force}  dropped {self.source.stats.dropped}  "
                f"ood {s.ood_frames}  bad {s.bad_frames}")

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


def _csv_field(text: str) -> str:
    """``text`` as one CSV field (quoted when it holds a comma, quote or line break)."""
    if any(c in text for c in ',"\n\r'):
        return '"' + text.replace('"', '""') + '"'
    return text


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
    unreadable = ""
    if s.unreadable_frames:
        names = ", ".join(s.unreadable_files[:5]) + (" ..." if len(s.unreadable_files) > 5 else "")
        unreadable = f", unreadable {s.unreadable_frames}" + (f" ({names})" if names else "")
    lines.append(f"  dropped {s.dropped_frames}, reconnects {s.reconnects}, refused {s.bad_frames}"
                 f"{unreadable}, outside training range {s.ood_frames}")
    if s.meshes_written or s.write_error or s.meshes_skipped:
        lines.append(f"  meshes written {s.meshes_written}, skipped {s.meshes_skipped}")
    if s.write_error:
        lines.append(f"  write error: {s.write_error}")
    if s.previews_written:
        lines.append(f"  previews written {s.previews_written}")
    if s.published:
        lines.append(f"  meshes published {s.published}")
    return "\n".join(lines)


def json_summary(s: RunSummary) -> str:
    return json.dumps(asdict(s), indent=2)
