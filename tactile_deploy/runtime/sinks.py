"""Where a run's results go besides the mesh files: recordings and viewers, each a *frame sink*.

The run loop hands every processed frame to each sink as a :class:`FrameResult` (the camera
frame, its mesh prediction, its contact forces, its latency). A sink that does slow work (encode,
compress, write) subclasses :class:`BackgroundSink`: ``consume`` only queues the result and a
worker thread does the work, so the sensor loop never waits for a disk or a network, except when
the source is a recording (nothing is lost by waiting: every frame is handled).

With a live source a full queue drops the result: it is counted with its reason (``dropped``),
and the run warns when it happens (first time, then every 100th). A failure inside the worker
stops that sink only (logged once, ``error`` holds the message); the run goes on.
"""

from __future__ import annotations

import logging
import queue
import threading
from collections import Counter
from dataclasses import dataclass

import numpy as np

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FrameResult:
    """One processed frame.

    frame : :class:`~tactile_deploy.runtime.sources.base.Frame` (raw RGB image, index, times).
    prediction : :class:`~tactile_deploy.runtime.predictor.MeshPrediction` (vertices_mm (n, 3),
        displacement_mm, depth_mm (128, 128), ood_score, in_distribution).
    force : :class:`~tactile_deploy.runtime.forces.ForceEstimate` or None (``--no-forces``);
        its ``pressure_kpa`` is empty unless a sink or the publisher asked for it.
    latency_ms : capture -> mesh (and forces), ms.
    """

    frame: object
    prediction: object
    force: object | None
    latency_ms: float

    @property
    def total_normal_force_n(self) -> float | None:
        return None if self.force is None else float(self.force.total_normal_force_n)

    @property
    def pressure_kpa(self) -> np.ndarray | None:
        if self.force is None or not np.size(self.force.pressure_kpa):
            return None
        return np.asarray(self.force.pressure_kpa)


class FrameSink:
    """Base of the sinks: ``start(live)`` before the first frame, ``consume(result)`` per frame,
    ``close()`` at the end (always called). ``wants_pressure``: the run computes the per-node
    pressure (a dense product per frame) only when a sink or the publisher needs it."""

    name = "sink"
    wants_pressure = False

    def __init__(self) -> None:
        self.handled = 0
        self.dropped: Counter = Counter()
        self.error: str | None = None

    def start(self, live: bool) -> None:
        pass

    def consume(self, result: FrameResult) -> None:
        raise NotImplementedError

    def close(self) -> None:
        pass

    def report(self) -> dict:
        """What the sink did, for run.json: frames handled, dropped by reason, error."""
        return {"handled": self.handled, "dropped": dict(self.dropped), "error": self.error}


class BackgroundSink(FrameSink):
    """A sink whose work (:meth:`handle`, in a worker thread) may be slow (module docstring).

    queue_size : results waiting at most (each holds a camera frame: ~1 MB at 640 x 480).
    """

    def __init__(self, queue_size: int = 8) -> None:
        super().__init__()
        self._q: queue.Queue = queue.Queue(maxsize=queue_size)
        self._thread: threading.Thread | None = None
        self._block = True
        self._lock = threading.Lock()

    # -- for subclasses
    def setup(self) -> None:
        """Called in the worker thread before the first result (open files, servers)."""

    def handle(self, result: FrameResult) -> None:
        raise NotImplementedError

    def teardown(self) -> None:
        """Called in the worker thread after the last result (finish files)."""

    # -- the machinery
    def start(self, live: bool) -> None:
        self._block = not live
        self._ready = threading.Event()
        self._thread = threading.Thread(target=self._work, name=self.name, daemon=True)
        self._thread.start()

    def consume(self, result: FrameResult) -> None:
        if self.error is not None:
            return self._drop("stopped after an error")
        if self._block:
            while self._thread is not None and self._thread.is_alive() and self.error is None:
                try:
                    self._q.put(result, timeout=0.5)
                    return None
                except queue.Full:
                    continue
            return self._drop("stopped after an error")
        try:
            self._q.put_nowait(result)
        except queue.Full:
            self._drop("queue full (the sink is slower than the sensor)")

    def _drop(self, reason: str) -> None:
        with self._lock:
            self.dropped[reason] += 1
            n = sum(self.dropped.values())
        if n == 1 or n % 100 == 0:
            log.warning("%s: %d frame(s) dropped so far (%s)", self.name, n, reason)

    def _work(self) -> None:
        try:
            self.setup()
        except Exception as e:  # noqa: BLE001 - reported, the run goes on without this sink
            self._fail(f"{self.name} could not start: {type(e).__name__}: {e}")
        while True:
            item = self._q.get()
            if item is None:
                break
            if self.error is not None:
                self._drop("stopped after an error")
                continue
            try:
                self.handle(item)
                self.handled += 1
            except Exception as e:  # noqa: BLE001 - any failure stops this sink only
                self._drop("stopped after an error")
                self._fail(f"{self.name} failed at frame {item.frame.index}: "
                           f"{type(e).__name__}: {e}; it handles no further frames")
        try:
            self.teardown()
        except Exception as e:  # noqa: BLE001
            self._fail(f"{self.name} could not finish: {type(e).__name__}: {e}")

    def _fail(self, message: str) -> None:
        if self.error is None:
            self.error = message
            log.error(message)

    def close(self, timeout_s: float = 120.0) -> None:
        """Handle what is queued, finish, stop the thread."""
        if self._thread is None:
            return
        self._q.put(None)
        self._thread.join(timeout=timeout_s)
        if self._thread.is_alive():
            self._fail(f"{self.name} did not finish within {timeout_s:g} s")
        self._thread = None
