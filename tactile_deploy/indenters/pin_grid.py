"""A calibration target as an indenter: a rigid plate with a square lattice of hemispherical pins
(the dot target of the camera mapping). Sensor frame, mm."""

from __future__ import annotations

import numpy as np

from tactile_deploy.indenters.pose import ContactPose, indenter_to_sensor, sensor_to_indenter_xy


class PinGrid:
    """A rigid plate with a square lattice of hemispherical pins (calibration target).

    ``shape`` = (columns, rows) pins at ``pitch_mm``, centred on the indenter origin, rows along
    indenter x; each pin a sphere cap of ``pin_radius_mm``. Duck-types the parts of
    :class:`tactile_deploy.indenters.Indenter` the simulator uses (``intrusion_mm``,
    ``footprint_radius_mm``, ``name``).
    """

    kind = "target"

    def __init__(self, pitch_mm: float = 2.5, shape: tuple[int, int] = (9, 7),
                 pin_radius_mm: float = 0.75):
        if not 0 < 2 * pin_radius_mm < pitch_mm:
            raise ValueError(f"pins of radius {pin_radius_mm} mm do not fit a {pitch_mm} mm pitch")
        self.pitch_mm = float(pitch_mm)
        self.shape = (int(shape[0]), int(shape[1]))
        self.pin_radius_mm = float(pin_radius_mm)
        self.name = f"pin_grid_{self.shape[0]}x{self.shape[1]}_p{pitch_mm:g}"
        half = np.array([(self.shape[0] - 1) / 2.0, (self.shape[1] - 1) / 2.0]) * self.pitch_mm
        self.footprint_radius_mm = float(np.hypot(*half) + pin_radius_mm)

    def pin_centres_mm(self, pose: ContactPose) -> np.ndarray:
        """Pin centres in the sensor frame, (k, 2) mm, row-major (rows along +y)."""
        i = np.arange(self.shape[0]) - (self.shape[0] - 1) / 2.0
        j = np.arange(self.shape[1]) - (self.shape[1] - 1) / 2.0
        gx, gy = np.meshgrid(i * self.pitch_mm, j * self.pitch_mm)
        q = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1)
        return indenter_to_sensor(q, pose)[:, :2]

    def intrusion_mm(self, points_xy_sensor_mm, pose: ContactPose) -> np.ndarray:
        """Intrusion (k,) mm below z = 0 at sensor points (k, 2); -inf between pins."""
        q = sensor_to_indenter_xy(np.asarray(points_xy_sensor_mm, np.float64), pose)
        p = self.pitch_mm
        lim = (np.array(self.shape) - 1) / 2.0
        idx = np.clip(np.round(q / p), -lim, lim)
        r = np.hypot(*(q - idx * p).T)
        big = self.pin_radius_mm
        with np.errstate(invalid="ignore"):
            h = np.where(r < big, big - np.sqrt(np.maximum(big * big - r * r, 0.0)), np.inf)
        return pose.depth_mm - h
