"""A simulated rig pressing a virtual sensor with any indenter: the bench of ``rig collect
--simulated`` and of its tests.

A :class:`~tactile_deploy.calibration.rig.simulated.SimulatedRig` serves a G-code stage and a force gauge on
two pseudo-terminals; an :class:`~tactile_deploy.calibration.rig.IndentationRig` drives them over pyserial
exactly as it drives hardware. The stage carries the indenter (a library name or mesh path, at
``theta_deg`` about z): the gauge reads the virtual sensor's FEM force for the contact the stage
position implies (through the rig's true stage frame), and :meth:`VirtualPressBench.grab`
renders the sensor's camera frames of that contact (its own optics, effects and camera noise),
or its reference frame when the indenter is above the gel.
"""

from __future__ import annotations

import numpy as np

from tactile_deploy.calibration.rig.indent import IndentationRig
from tactile_deploy.indenters import ContactPose


class VirtualPressBench:
    """A virtual sensor on a simulated rig (module docstring).

    sensor : a :class:`~tactile_deploy.sensors.virtual.VirtualSensor`. indenter : library name
    or mesh path. rig_overrides : :class:`~tactile_deploy.calibration.rig.RigConfig` fields (dicts for
    ``stage`` and ``gauge``) of the config the rig connects with. Use it with ``with``.
    """

    def __init__(self, sensor, indenter: str, theta_deg: float = 0.0, seed: int = 0,
                 rig_overrides: dict | None = None):
        from tactile_deploy.calibration.rig.simulated import SimulatedRig

        self.sensor = sensor
        self.indenter_name = indenter
        self.indenter = sensor.indenter(indenter)
        self.theta_deg = float(theta_deg)
        self.seed = int(seed)
        self._count = 0
        self.sim = SimulatedRig(self._force_n)
        self._overrides = dict(rig_overrides or {})
        self.rig: IndentationRig | None = None

    def _pose(self, x_mm: float, y_mm: float, depth_mm: float) -> ContactPose:
        from tactile_deploy.sensors.virtual import MAX_DEPTH_MM

        return ContactPose(x_mm=x_mm, y_mm=y_mm, theta_deg=self.theta_deg,
                           depth_mm=min(depth_mm, MAX_DEPTH_MM))

    def _force_n(self, indentation_mm: float, x_mm: float, y_mm: float) -> float:
        from tactile_deploy.simulation.contact import ContactError

        if indentation_mm <= 0:
            return 0.0
        try:
            return self.sensor.contact_force_n(self.indenter,
                                               self._pose(x_mm, y_mm, indentation_mm))
        except ContactError:
            return 0.0

    def open(self) -> VirtualPressBench:
        self.sensor.prepare()
        self.sim.start()
        try:
            overrides = dict(self._overrides)
            stage = {"timeout_s": 1.0, "motion_timeout_s": 2.0, **overrides.pop("stage", {})}
            gauge = {"timeout_s": 1.0, **overrides.pop("gauge", {})}
            self.rig = IndentationRig(self.sim.rig_config(stage=stage, gauge=gauge, **overrides))
            self.rig.connect()
            self.rig.home()
        except BaseException:
            self.sim.stop()
            raise
        return self

    def close(self) -> None:
        try:
            if self.rig is not None:
                self.rig.disconnect()
        finally:
            self.sim.stop()

    def __enter__(self) -> VirtualPressBench:
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()

    def grab(self, n: int = 1) -> np.ndarray:
        """``n`` camera frames of what the stage presses now, (n, H, W, 3) uint8 RGB."""
        c = self.sim.contact()
        frames = []
        for _ in range(n):
            rng = np.random.default_rng([self.sensor.config.seed, self.seed, 0x76627263,
                                         self._count])
            self._count += 1
            if c.depth_mm <= 0:
                frames.append(self.sensor.reference_frame(rng))
            else:
                frames.append(self.sensor.press(self.indenter,
                                                self._pose(c.x_mm, c.y_mm, c.depth_mm), rng,
                                                truth=False).frame)
        return np.stack(frames)
