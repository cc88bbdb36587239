"""Measured data with hidden effects, made by virtual sensors (tests, benchmark, documentation).

A virtual sensor with one or more effects switched on presses a list of contacts; its depth-map
truth (:meth:`VirtualSensor.depth_map`) plus white Gaussian pixel noise on the pad, and its force
plus relative force noise, are the "measured" data; the commanded contacts are stored as the rig
would record them. The effect's parameters are drawn at random from its realistic range
(``realistic_range`` of the effect), away from the null value: a magnitude between
``floor`` and 1 times the range's extreme on a random side, so that the effect is there to be
found (a draw at 1 % of the range is not).
"""

from __future__ import annotations

import math
import zlib

import numpy as np

from tactile_deploy.calibration.discrepancy.measured import MeasuredData
from tactile_deploy.indenters import ContactPose
from tactile_deploy.sensors.config import EffectSpec
from tactile_deploy.sensors.effects import effect_class
from tactile_deploy.sensors.virtual import VirtualSensor

#: Indenters of the synthetic contact sets: spheres of two radii, a flat punch, a lying cylinder.
DEFAULT_INDENTERS = ("sphere_r4", "sphere_r6", "flat_punch", "cylinder_side")
#: Narrower draw ranges where an effect's solver limits them: the neo-Hookean solve converges
#: up to a strength of about 1.2 at 0.9 mm deep contacts.
HIDDEN_RANGES = {"hyperelastic": {"strength": (0.5, 1.2)}}


def random_contacts(n: int, seed: int, radius_mm: float = 6.0,
                    depth_range_mm: tuple[float, float] = (0.3, 0.9),
                    indenters=DEFAULT_INDENTERS) -> list[tuple[str, ContactPose]]:
    """``n`` contacts: indenters in turn, positions uniform over a disc of ``radius_mm`` (sensor
    frame), angles uniform, depths uniform in ``depth_range_mm``."""
    rng = np.random.default_rng([seed, 0x636F6E74])
    out = []
    for i in range(n):
        r = radius_mm * math.sqrt(rng.uniform())
        a = rng.uniform(0.0, 2.0 * math.pi)
        out.append((indenters[i % len(indenters)],
                    ContactPose(x_mm=float(r * math.cos(a)), y_mm=float(r * math.sin(a)),
                                theta_deg=float(rng.uniform(0.0, 180.0)),
                                depth_mm=float(rng.uniform(*depth_range_mm)))))
    return out


def draw_hidden(effect: str, seed: int, floor: float = 0.3) -> dict[str, float]:
    """Parameters of ``effect`` drawn from its realistic range, away from the null value."""
    rng = np.random.default_rng([seed, 0x68696464, zlib.crc32(effect.encode())])
    cls = effect_class(effect)
    ranges = {**cls.realistic_range, **HIDDEN_RANGES.get(effect, {})}
    if effect == "tilt":
        lo, hi = ranges["angle_deg"]
        return {"angle_deg": float(rng.uniform(lo + floor * (hi - lo), hi)),
                "azimuth_deg": float(rng.uniform(-180.0, 180.0))}
    if effect == "position_offset":
        r = ranges["dx_mm"][1] * rng.uniform(floor, 1.0)
        a = rng.uniform(0.0, 2.0 * math.pi)
        return {"dx_mm": float(r * math.cos(a)), "dy_mm": float(r * math.sin(a))}
    out = {}
    for name, (lo, hi) in ranges.items():
        null = cls.Params.model_fields[name].default
        if lo < null < hi:  # two-sided: a random side, 30-100 % of the way to its end
            end = hi if rng.uniform() < 0.5 else lo
            out[name] = float(null + (end - null) * rng.uniform(floor, 1.0))
        elif null == lo:  # one-sided from the null value
            out[name] = float(lo + (hi - lo) * rng.uniform(floor, 1.0))
        else:  # a range away from the null value
            out[name] = float(rng.uniform(lo, hi))
    return out


def hidden_effect_data(sensor: VirtualSensor, effects: list[EffectSpec], contacts, noise_mm: float,
                       seed: int, force_noise_rel: float = 0.01,
                       commanded: bool = True, frames: bool = False) -> MeasuredData:
    """Depth maps (or RGB frames) and forces of ``contacts`` pressed into ``sensor`` with
    ``effects`` added.

    noise_mm : white Gaussian pixel noise on the pad (one sigma, mm); the maps are float32.
    commanded : store the commanded contacts (else NaN: the workflow estimates them).
    frames : store the sensor's camera frames instead (its own camera noise; ``noise_mm`` is
    not used), as a real sensor delivers them.
    """
    from tactile_deploy.calibration.discrepancy.reproduce import CachedIndenter
    from tactile_deploy.indenters import get_indenter

    cfg = sensor.config
    names = {e.name for e in effects}
    kept = tuple(e for e in cfg.effects if e.name not in names)
    hidden = VirtualSensor(cfg.model_copy(update={"effects": kept + tuple(effects)}),
                           simulator=sensor.simulator)
    rng = np.random.default_rng([seed, 0x6D656173])
    from tactile_deploy.camera.depth import DepthCamera

    mesh = sensor.simulator.mesh
    mask = DepthCamera().render(mesh, mesh.vertices).mask
    indenters = {}
    depth, images, force = [], [], []
    for name, pose in contacts:
        if name not in indenters:
            indenters[name] = CachedIndenter(get_indenter(name))
        if frames:
            shot = hidden.press(indenters[name], pose, rng, truth=False)
            images.append(shot.frame)
            f = shot.force_n
        else:
            d, f = hidden.depth_map(indenters[name], pose)
            depth.append(np.where(mask, d + rng.normal(0.0, noise_mm, d.shape), 0.0))
        force.append(f * (1.0 + force_noise_rel * rng.standard_normal()))
    n = len(contacts)
    nan = np.full(n, np.nan)
    poses = [p for _, p in contacts]
    return MeasuredData(
        depth_mm=None if frames else np.stack(depth).astype(np.float32),
        frames=np.stack(images) if frames else None,
        indenter=[c for c, _ in contacts],
        x_mm=np.array([p.x_mm for p in poses]) if commanded else nan,
        y_mm=np.array([p.y_mm for p in poses]) if commanded else nan,
        theta_deg=np.array([p.theta_deg for p in poses]) if commanded else nan,
        depth_cmd_mm=np.array([p.depth_mm for p in poses]) if commanded else nan.copy(),
        force_n=np.array(force), contact_id=np.arange(n),
        source=f"virtual sensor {sensor.name!r} with hidden "
               f"{', '.join(e.name for e in effects) or 'nothing'}",
        metadata={"hidden": [e.model_dump() for e in effects],
                  "noise_mm": None if frames else noise_mm})
