"""The calibration station: a camera, an optional indentation rig, and the person at the bench.

* :class:`CameraStation`: any frame source of the runtime (a live camera, a video, a folder of
  images) and, optionally, an :class:`~tactile_deploy.calibration.rig.IndentationRig` on serial ports. Without
  a rig the person presses the ball by hand when asked.
* :class:`VirtualStation`: a virtual sensor (``--source virtual:NAME``). With ``--rig
  simulated`` a simulated rig runs on two pseudo-terminals in this process and the wizard drives
  it over pyserial exactly as it drives hardware; the virtual camera renders whatever the
  simulated stage is pressing (its true stage frame, the sensor's own effects), and the gauge
  reads the sensor's FEM force. Without a rig, presses are made for the person at the planned
  places with a hand's scatter.

Tools: :class:`Ball` (the shading calibration's marble) and :class:`PinPlate` (the dot target of
the camera mapping). Contacts are in the sensor frame (mm; depth below the gel surface).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np

from tactile_deploy.calibration.rig import IndentationRig, RigConfig
from tactile_deploy.indenters import ContactPose


@dataclass(frozen=True)
class Ball:
    """A ball (marble) of ``radius_mm``."""

    radius_mm: float

    def describe(self) -> str:
        return f"the {2 * self.radius_mm:g} mm ball (radius {self.radius_mm:g} mm)"

    @property
    def indenter_name(self) -> str:
        return f"analytic_sphere_r{self.radius_mm:g}"


@dataclass(frozen=True)
class PinPlate:
    """A plate of ``grid`` (columns, rows) pins at ``pitch_mm``, caps of ``pin_radius_mm``."""

    pitch_mm: float
    grid: tuple[int, int]
    pin_radius_mm: float

    def describe(self) -> str:
        return (f"the dot target ({self.grid[0]} x {self.grid[1]} pins at {self.pitch_mm:g} mm, "
                "rows along sensor x)")


class StationError(RuntimeError):
    """The station cannot do what a step needs (the message says what to change)."""


class Station(ABC):
    """Frames, the rig (or the person's hands), and tool changes.

    image_size : (W, H) px of the camera. rig : the connected rig, or None.
    """

    description = "station"
    rig: IndentationRig | None = None
    image_size: tuple[int, int] = (0, 0)
    #: True when presses need no person (a rig, or a virtual sensor's simulated hand).
    automatic_presses = False

    @abstractmethod
    def grab(self, n: int = 1) -> np.ndarray:
        """``n`` consecutive frames, (n, H, W, 3) uint8 RGB, raw camera pixels."""

    def mount(self, tool, ui) -> None:
        """Have ``tool`` mounted on the rig (or at hand)."""
        ui.wait(f"Mount {tool.describe()} on the rig's tool holder" if self.rig is not None
                else f"Have {tool.describe()} at hand")

    def hand_press(self, tool, contact: tuple[float, float, float], ui, label: str) -> None:
        """Without a rig: have ``tool`` pressed near ``contact`` (x_mm, y_mm, depth_mm)."""
        x, y, d = contact
        ui.wait(f"{label}: press {tool.describe()} into the gel near x = {x:+.1f} mm, y = "
                f"{y:+.1f} mm (sensor frame), about {d:.2f} mm deep, straight down, and hold it")

    def release(self, ui) -> None:
        """Without a rig: have nothing touch the sensor."""
        ui.wait("Lift everything off the sensor (nothing may touch it)")

    def close(self) -> None:
        if self.rig is not None:
            self.rig.disconnect()


class CameraStation(Station):
    """A frame source of the runtime (``--source``) and an optional rig."""

    def __init__(self, source_config, rig_config: RigConfig | None = None):
        from tactile_deploy.runtime.sources.factory import make_source

        self.source_config = source_config
        self.description = f"frame source {source_config.model_dump()}"
        self.source = make_source(source_config)
        self.source.connect()
        try:
            first = self.source.read()
            if first is None:
                raise StationError(f"the frame source {source_config.model_dump()} gave no "
                                   "frame")
            h, w = first.image.shape[:2]
            self.image_size = (w, h)
            if rig_config is not None:
                self.rig = IndentationRig(rig_config)
                self.rig.connect()
                self.rig.home()
                self.automatic_presses = True
        except BaseException:
            self.close()   # the source (and the rig's ports) are not left open
            raise

    def grab(self, n: int = 1) -> np.ndarray:
        frames = []
        for _ in range(n):
            f = self.source.read()
            if f is None:
                raise StationError(f"the frame source {self.source_config.model_dump()} ran out "
                                   "of frames")
            frames.append(f.image)
        return np.stack(frames)

    def close(self) -> None:
        try:
            super().close()
        finally:
            self.source.disconnect()


class VirtualStation(Station):
    """A virtual sensor, pressed by a simulated rig over pseudo-terminals or by a simulated hand.

    sensor_name : a shipped virtual sensor (``tactile-deploy sensors list``).
    simulated_rig : run a :class:`~tactile_deploy.calibration.rig.simulated.SimulatedRig` whose stage carries
        the mounted tool; ``rig_overrides`` are :class:`RigConfig` fields (dicts for ``stage`` and
        ``gauge``) applied to the config the wizard connects with.
    """

    automatic_presses = True

    def __init__(self, sensor_name: str, simulated_rig: bool = False, seed: int = 0,
                 rig_overrides: dict | None = None):
        from tactile_deploy.sensors import load_sensor

        self.sensor = load_sensor(sensor_name)
        self.sensor.prepare()
        self.description = f"virtual sensor {sensor_name}" + (
            " on a simulated rig (pseudo-terminals)" if simulated_rig else ", pressed by hand")
        self.image_size = tuple(self.sensor.optics.image_size)
        self.seed = int(seed)
        self._count = 0
        self.tool = None
        self._hand: ContactPose | None = None
        self._indenters: dict = {}
        self.sim = None
        if simulated_rig:
            from tactile_deploy.calibration.rig.simulated import SimulatedRig

            self.sim = SimulatedRig(self._force_n)
            self.sim.start()
            try:
                overrides = dict(rig_overrides or {})
                stage = {"timeout_s": 1.0, "motion_timeout_s": 2.0, **overrides.pop("stage", {})}
                gauge = {"timeout_s": 1.0, **overrides.pop("gauge", {})}
                self.rig = IndentationRig(self.sim.rig_config(stage=stage, gauge=gauge,
                                                              **overrides))
                self.rig.connect()
                self.rig.home()
            except BaseException:
                self.sim.stop()
                raise

    # -- the virtual world
    def _indenter(self, tool):
        if tool not in self._indenters:
            if isinstance(tool, Ball):
                from tactile_deploy.indenters import AnalyticSphere

                self._indenters[tool] = AnalyticSphere(tool.radius_mm)
            else:
                from tactile_deploy.indenters.pin_grid import PinGrid

                self._indenters[tool] = PinGrid(tool.pitch_mm, tool.grid, tool.pin_radius_mm)
        return self._indenters[tool]

    def _force_n(self, indentation_mm: float, x_mm: float, y_mm: float) -> float:
        """What the simulated gauge reads: the FEM force of the mounted tool, N."""
        from tactile_deploy.sensors.virtual import MAX_DEPTH_MM
        from tactile_deploy.simulation.contact import ContactError

        if self.tool is None or indentation_mm <= 0:
            return 0.0
        pose = ContactPose(x_mm=x_mm, y_mm=y_mm, depth_mm=min(indentation_mm, MAX_DEPTH_MM))
        try:
            return self.sensor.contact_force_n(self._indenter(self.tool), pose)
        except ContactError:
            return 0.0

    def current_contact(self) -> ContactPose | None:
        """The contact the camera sees now (sensor frame), or None."""
        if self.sim is not None:
            c = self.sim.contact()
            if c.depth_mm <= 0 or self.tool is None:
                return None
            return ContactPose(x_mm=c.x_mm, y_mm=c.y_mm, depth_mm=c.depth_mm)
        return self._hand

    def grab(self, n: int = 1) -> np.ndarray:
        pose = self.current_contact()
        frames = []
        for _ in range(n):
            rng = np.random.default_rng([self.sensor.config.seed, self.seed, 0x677262,
                                         self._count])
            self._count += 1
            if pose is None:
                frames.append(self.sensor.reference_frame(rng))
            else:
                frames.append(self.sensor.press(self._indenter(self.tool), pose, rng,
                                                truth=False).frame)
        return np.stack(frames)

    def mount(self, tool, ui) -> None:
        self.tool = tool
        ui.say(f"virtual sensor: {tool.describe()} mounted"
               + (" on the simulated rig" if self.sim is not None else ""))

    def hand_press(self, tool, contact, ui, label: str) -> None:
        x, y, d = contact
        rng = np.random.default_rng([self.seed, 0x68616E64, self._count])
        self.tool = tool
        self._hand = ContactPose(x_mm=x + rng.normal(0, 0.3), y_mm=y + rng.normal(0, 0.3),
                                 depth_mm=d * rng.uniform(0.9, 1.1))
        ui.say(f"virtual sensor: {label}: pressed at x = {self._hand.x_mm:+.2f} mm, y = "
               f"{self._hand.y_mm:+.2f} mm, {self._hand.depth_mm:.3f} mm deep")

    def release(self, ui) -> None:
        self._hand = None

    def close(self) -> None:
        try:
            super().close()
        finally:
            if self.sim is not None:
                self.sim.stop()


def rig_press_frames(station: Station, tool, contact, n_frames: int):
    """Press with the rig and grab frames with the tool held: (frames or None, record)."""
    held = []
    x, y, d = contact
    record = station.rig.press(x, y, d, on_pressed=lambda rec: held.append(
        station.grab(n_frames)))
    return (held[0] if held else None), record
