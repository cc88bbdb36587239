"""A simulated indentation rig: a G-code stage and a force gauge served on pseudo-terminals.

Each device is a pseudo-terminal pair (``os.openpty``) and one background thread that reads
the master side; the host opens the slave side by name with pyserial exactly like a USB serial
adapter (``serial.Serial(sim.stage.port)``). POSIX only.

* :class:`SimulatedStage` keeps a stage-frame position (mm) and obeys ``G0``/``G1`` (``X Y Z F``
  words, absolute ``G90`` or relative ``G91``), ``G28`` (home), ``G21``, ``M114``
  (``X:1.00 Y:2.00 Z:3.00 E:0.00 Count X:.. Y:.. Z:..``, two decimals as Marlin prints) and
  ``M400``, each answered ``ok``; moves are instantaneous. Unknown commands get
  ``echo:Unknown command: "..."`` and ``ok``, as Marlin does.
* :class:`SimulatedGauge` answers its request string with one line, by default
  ``"{value:.2f} N"``. The force comes from ``force_fn(indentation_mm, x_mm, y_mm) -> N`` at the
  tip position implied by the stage position and the *true* :class:`StageFrame` of the virtual
  rig (``indentation_mm = -z_tip``, sensor frame, negative above the surface), plus a constant
  ``offset_n`` and Gaussian noise; ``sign`` and ``newtons_per_unit`` mimic a gauge that reports
  compression as negative or in other units.
* :meth:`SimulatedRig.contact` is the sensor-frame contact ``(x_mm, y_mm, depth_mm)`` the stage
  position implies, for a virtual sensor to render the matching camera frame.

Faults are injected per device with ``inject(kind, match=..., times=...)``; the next ``times``
received lines that start with ``match`` (any line if None) get the fault:

``"drop"``    carry the command out, send no reply;
``"garble"``  carry it out, send every reply line with its bytes corrupted (non-ASCII);
``"error"``   do not carry it out, reply with an error line;
``"delay"``   carry it out at once, send the reply ``delay_s`` later (the device answers
              nothing else meanwhile);
``"noise"``   send ``lines`` junk lines, then carry it out and reply normally;
``"busy"``    send ``busy: processing`` every ``busy_interval_s`` for ``delay_s``, then carry
              it out and reply.
"""

from __future__ import annotations

import math
import os
import random
import select
import threading
import tty
from dataclasses import dataclass
from typing import Any, Callable, NamedTuple

from tactile_deploy.calibration.rig.config import RigConfig, StageFrame, rig_config_from_dict

ForceFn = Callable[[float, float, float], float]

FAULT_KINDS = ("drop", "garble", "error", "delay", "noise", "busy")

_JUNK_LINE = b"~#\xfe\xa3?\x1b\xc7]"


@dataclass(frozen=True)
class HertzForce:
    """Hertz-like contact force ``F = k * max(0, indentation)^1.5``, N, indentation in mm.

    For a sphere of radius R on a thick elastic layer, ``k = 4/3 * E* * sqrt(R)``; the default
    0.7 N/mm^1.5 is a 3 mm radius tip on a gel of E* about 0.3 MPa.
    """

    stiffness_n_per_mm1p5: float = 0.7

    def __call__(self, indentation_mm: float, x_mm: float, y_mm: float) -> float:
        return self.stiffness_n_per_mm1p5 * max(0.0, indentation_mm) ** 1.5


class SensorContact(NamedTuple):
    """Contact implied by the simulated stage: tip at (x_mm, y_mm), ``depth_mm`` into the gel.

    Sensor frame, mm; ``depth_mm`` is 0 when the tip is above the surface plane z = 0.
    """

    x_mm: float
    y_mm: float
    depth_mm: float


@dataclass
class _Fault:
    kind: str
    match: str | None
    remaining: int
    delay_s: float
    lines: int
    busy_interval_s: float


class _PtyDevice:
    """A pseudo-terminal with a thread that answers each received line."""

    #: Reply of the ``"error"`` fault.
    error_reply = "error: simulated fault"

    def __init__(self, name: str):
        self.name = name
        self._lock = threading.Lock()
        self._faults: list[_Fault] = []
        self._received: list[str] = []
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._fds: list[int] = []
        self._master = self._slave = self._wake_r = self._wake_w = -1
        self.port = ""

    # -- lifecycle --------------------------------------------------------------------------

    @property
    def running(self) -> bool:
        return self._thread is not None

    def start(self) -> None:
        if self._thread is not None:
            return
        try:
            self._master, self._slave = os.openpty()
            self._fds = [self._master, self._slave]
            tty.setraw(self._slave)  # no echo, no line editing, no CR/LF translation
            self.port = os.ttyname(self._slave)
            self._wake_r, self._wake_w = os.pipe()
            self._fds += [self._wake_r, self._wake_w]
        except BaseException:
            self._close_fds()
            raise
        self._stop.clear()
        self._thread = threading.Thread(
            target=self._serve, name=f"simulated-{self.name}", daemon=True
        )
        self._thread.start()

    def stop(self) -> None:
        if self._thread is None:
            return
        self._stop.set()
        os.write(self._wake_w, b"x")
        self._thread.join()
        self._thread = None
        self._close_fds()

    def _close_fds(self) -> None:
        for fd in self._fds:
            try:
                os.close(fd)
            except OSError:
                pass
        self._fds = []

    def __enter__(self):
        self.start()
        return self

    def __exit__(self, *exc_info) -> None:
        self.stop()

    # -- faults and log ---------------------------------------------------------------------

    def inject(
        self,
        kind: str,
        *,
        match: str | None = None,
        times: int = 1,
        delay_s: float = 0.0,
        lines: int = 1,
        busy_interval_s: float = 0.05,
    ) -> None:
        """Apply fault ``kind`` to the next ``times`` received lines starting with ``match``."""
        if kind not in FAULT_KINDS:
            raise ValueError(f"unknown fault kind {kind!r}; known: {', '.join(FAULT_KINDS)}")
        if times < 1:
            raise ValueError(f"times must be >= 1, got {times}")
        with self._lock:
            self._faults.append(_Fault(kind, match, times, delay_s, lines, busy_interval_s))

    def clear_faults(self) -> None:
        with self._lock:
            self._faults.clear()

    @property
    def received(self) -> list[str]:
        """Every line received so far, in order (a copy)."""
        with self._lock:
            return list(self._received)

    def _take_fault(self, line: str) -> _Fault | None:
        with self._lock:
            for fault in self._faults:
                if fault.match is None or line.startswith(fault.match):
                    fault.remaining -= 1
                    if fault.remaining <= 0:
                        self._faults.remove(fault)
                    return fault
        return None

    # -- serving ----------------------------------------------------------------------------

    def handle(self, line: str) -> list[str]:
        """Carry out one received line and return the reply lines (subclasses)."""
        raise NotImplementedError

    def _send(self, lines: list[bytes]) -> None:
        data = b"".join(line + b"\n" for line in lines)
        while data:
            written = os.write(self._master, data)
            data = data[written:]

    def _process(self, line: str) -> None:
        with self._lock:
            self._received.append(line)
        fault = self._take_fault(line)
        kind = fault.kind if fault else None
        if kind == "error":
            self._send([self.error_reply.encode()])
            return
        if kind == "busy":
            waited = 0.0
            while waited < fault.delay_s:
                step = min(fault.busy_interval_s, fault.delay_s - waited)
                if self._stop.wait(step):
                    return
                waited += step
                self._send([b"busy: processing"])
        if kind == "noise":
            self._send([_JUNK_LINE] * fault.lines)
        replies = [r.encode("ascii") for r in self.handle(line)]
        if kind == "drop":
            return
        if kind == "garble":
            replies = [bytes(b ^ 0x80 for b in r) for r in replies]
        if kind == "delay" and self._stop.wait(fault.delay_s):
            return
        self._send(replies)

    def _serve(self) -> None:
        buffer = bytearray()
        while not self._stop.is_set():
            ready, _, _ = select.select([self._master, self._wake_r], [], [])
            if self._wake_r in ready:
                return
            try:
                data = os.read(self._master, 4096)
            except OSError:
                return
            if not data:
                return
            buffer.extend(data)
            while True:
                cuts = [i for i in (buffer.find(b"\n"), buffer.find(b"\r")) if i >= 0]
                if not cuts:
                    break
                cut = min(cuts)
                line = bytes(buffer[:cut]).decode("ascii", errors="replace").strip()
                del buffer[: cut + 1]
                if line:
                    self._process(line)
                if self._stop.is_set():
                    return


class SimulatedStage(_PtyDevice):
    """A Marlin-like three-axis G-code stage; position in the stage frame, mm."""

    error_reply = "Error: simulated fault"

    def __init__(self, home_mm: tuple[float, float, float] = (0.0, 0.0, 50.0)):
        super().__init__("stage")
        self.home_mm = tuple(float(v) for v in home_mm)
        self._position = list(self.home_mm)
        self._relative = False
        self._history: list[tuple[float, float, float]] = [tuple(self._position)]
        self.feed_mm_min = 0.0

    @property
    def position_mm(self) -> tuple[float, float, float]:
        """Current (X, Y, Z), stage frame, mm."""
        with self._lock:
            return tuple(self._position)

    @property
    def history_mm(self) -> list[tuple[float, float, float]]:
        """Every position the stage stopped at, stage frame, mm (a copy)."""
        with self._lock:
            return list(self._history)

    def handle(self, line: str) -> list[str]:
        text = line.split(";", 1)[0].strip().upper()
        words = text.split()
        if not words:
            return ["ok"]
        code, args = words[0], words[1:]
        if code in ("G0", "G1"):
            values = {}
            for word in args:
                try:
                    values[word[0]] = float(word[1:])
                except ValueError:
                    return [f"Error: bad number in {word!r} of {line!r}"]
                if not math.isfinite(values[word[0]]):
                    return [f"Error: bad number in {word!r} of {line!r}"]
            with self._lock:
                for i, axis in enumerate("XYZ"):
                    if axis in values:
                        base = self._position[i] if self._relative else 0.0
                        self._position[i] = base + values[axis]
                if "F" in values:
                    self.feed_mm_min = values["F"]
                self._history.append(tuple(self._position))
            return ["ok"]
        if code == "G28":
            axes = [w[0] for w in args if w[0] in "XYZ"] or list("XYZ")
            with self._lock:
                for i, axis in enumerate("XYZ"):
                    if axis in axes:
                        self._position[i] = self.home_mm[i]
                self._history.append(tuple(self._position))
            return ["ok"]
        if code in ("G90", "G91"):
            self._relative = code == "G91"
            return ["ok"]
        if code == "G21":
            return ["ok"]
        if code == "M114":
            x, y, z = self.position_mm
            return [
                f"X:{x:.2f} Y:{y:.2f} Z:{z:.2f} E:0.00 Count X:{round(x * 80)} "
                f"Y:{round(y * 80)} Z:{round(z * 400)}",
                "ok",
            ]
        if code == "M400":
            return ["ok"]
        return [f'echo:Unknown command: "{line}"', "ok"]


class SimulatedGauge(_PtyDevice):
    """A request/reply force gauge whose force follows the simulated stage."""

    error_reply = "ERROR"

    def __init__(
        self,
        stage: SimulatedStage,
        frame: StageFrame,
        force_fn: ForceFn | None = None,
        *,
        request: str = "?",
        reply_format: str = "{value:.2f} N",
        offset_n: float = 0.0,
        noise_std_n: float = 0.0,
        sign: int = 1,
        newtons_per_unit: float = 1.0,
        seed: int = 0,
    ):
        super().__init__("gauge")
        if sign not in (1, -1):
            raise ValueError(f"sign must be 1 or -1, got {sign}")
        if not newtons_per_unit > 0:
            raise ValueError(f"newtons_per_unit must be > 0, got {newtons_per_unit}")
        self.stage = stage
        self.frame = frame
        self.force_fn: ForceFn = force_fn or HertzForce()
        self.request = request
        self.reply_format = reply_format
        self.offset_n = offset_n
        self.noise_std_n = noise_std_n
        self.sign = sign
        self.newtons_per_unit = newtons_per_unit
        self._rng = random.Random(seed)

    def tip_mm(self) -> tuple[float, float, float]:
        """Tip position in the sensor frame (true frame of the virtual rig), mm."""
        return self.frame.stage_to_sensor(*self.stage.position_mm)

    def contact(self) -> SensorContact:
        x, y, z = self.tip_mm()
        return SensorContact(x, y, max(0.0, -z))

    def force_n(self) -> float:
        """Noise-free contact force at the current stage position, N (no offset)."""
        x, y, z = self.tip_mm()
        return float(self.force_fn(-z, x, y))

    def handle(self, line: str) -> list[str]:
        if line != self.request.strip():
            return []
        force = self.force_n() + self.offset_n
        if self.noise_std_n > 0:
            force += self._rng.gauss(0.0, self.noise_std_n)
        value = self.sign * force / self.newtons_per_unit
        return [self.reply_format.format(value=value)]


class SimulatedRig:
    """A simulated stage and force gauge, each on its own pseudo-terminal.

    ``frame`` is the *true* placement of the virtual sensor on the stage (what a real rig's
    calibration would estimate); the default equals the default :class:`StageFrame`. Use it
    with ``with SimulatedRig() as sim:``; :meth:`rig_config` builds a matching
    :class:`RigConfig`.
    """

    def __init__(
        self,
        force_fn: ForceFn | None = None,
        *,
        frame: StageFrame | None = None,
        home_mm: tuple[float, float, float] = (0.0, 0.0, 50.0),
        **gauge_options: Any,
    ):
        self.frame = frame if frame is not None else StageFrame()
        self.stage = SimulatedStage(home_mm=home_mm)
        self.gauge = SimulatedGauge(self.stage, self.frame, force_fn, **gauge_options)

    @property
    def stage_port(self) -> str:
        return self.stage.port

    @property
    def gauge_port(self) -> str:
        return self.gauge.port

    def start(self) -> None:
        self.stage.start()
        try:
            self.gauge.start()
        except BaseException:
            self.stage.stop()
            raise

    def stop(self) -> None:
        try:
            self.gauge.stop()
        finally:
            self.stage.stop()

    def __enter__(self) -> "SimulatedRig":
        self.start()
        return self

    def __exit__(self, *exc_info) -> None:
        self.stop()

    def contact(self) -> SensorContact:
        """Sensor-frame contact (x_mm, y_mm, depth_mm) implied by the current stage position."""
        return self.gauge.contact()

    def force_n(self) -> float:
        """Noise-free force at the current stage position, N."""
        return self.gauge.force_n()

    def rig_config(
        self,
        *,
        stage: dict | None = None,
        gauge: dict | None = None,
        **rig: Any,
    ) -> RigConfig:
        """A :class:`RigConfig` for this rig: its ports and true frame, plus overrides.

        ``stage`` and ``gauge`` are dicts of :class:`StageConfig` / :class:`GaugeConfig` fields;
        other keywords are :class:`RigConfig` fields.
        """
        if not self.stage.running:
            raise RuntimeError("start the simulated rig first (use `with SimulatedRig() as sim`)")
        data = {
            "stage": {"port": self.stage_port, "frame": self.frame.model_dump(), **(stage or {})},
            "gauge": {"port": self.gauge_port, "request": self.gauge.request, **(gauge or {})},
            **rig,
        }
        return rig_config_from_dict(data, source="SimulatedRig.rig_config")
