"""The sensor model of a calibrated unit, and what ``discrepancy --sensor`` accepts.

A unit calibrated by the wizard has a plugin folder (camera mapping, shading model, material);
the discrepancy workflow needs a *sensor model* of it: a virtual sensor description
(:class:`~tactile_deploy.sensors.config.VirtualSensorConfig`) that reproduces its contacts. The
wizard writes one into the plugin folder as ``sensor_model.json`` (:func:`unit_sensor_model`):

* pad and family: the plugin's;
* material: the plugin's E and Poisson ratio (the wizard's FEM step), frictionless contact
  (the library's ``friction`` candidate measures how much the gel grips);
* optics: the unit's calibrated camera mapping, with the lights, noise and exposure of the
  family's shipped virtual sensor (a template: depth maps through the unit's plugin do not
  depend on them; frames imaged through the model do, so give the plugin's depth maps unless
  the optics were fitted to the unit, ``python -m tactile_deploy.calibration.optics_fit``);
* no effects: the discrepancy workflow finds and adds them (``--apply``).

``--sensor`` takes a shipped virtual sensor's name, a model JSON path, or a plugin (name or
folder) holding ``sensor_model.json`` (:func:`resolve_sensor`); with a plugin, measured frames
are imaged by that plugin's pipeline unless ``--plugin`` says otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from tactile_deploy.sensors.config import VirtualSensorConfig

#: The sensor model's file name inside a plugin folder.
MODEL_FILE = "sensor_model.json"


@dataclass(frozen=True)
class ResolvedSensor:
    """config : the model; model_ref : what ``--apply`` versions (a shipped name or a JSON
    path); plugin : the plugin the model came with (its folder), or None."""

    config: VirtualSensorConfig
    model_ref: str
    plugin: str | None = None


class SensorModelError(ValueError):
    """``--sensor`` names nothing usable (the message says what to give)."""


def family_template(family: str) -> VirtualSensorConfig:
    """The first shipped virtual sensor of ``family`` (its optics are the template)."""
    from tactile_deploy.sensors.catalog import list_sensors, sensor_config

    for name in list_sensors():
        cfg = sensor_config(name)
        if cfg.family == family:
            return cfg
    raise SensorModelError(f"no shipped virtual sensor of family {family!r} to take the optics "
                           f"from (shipped: {', '.join(list_sensors())})")


def unit_sensor_model(name: str, family: str, camera, E_mpa: float, nu: float,
                      description: str = "") -> VirtualSensorConfig:
    """The sensor model of a calibrated unit (module docstring). camera : its
    :class:`~tactile_deploy.imaging.camera_mapping.CameraMapping`."""
    from tactile_deploy.fem.material import Material

    template = family_template(family)
    optics = template.optics.model_copy(update={"camera": camera})
    optics = type(optics).model_validate(optics.model_dump())  # re-validated with the camera
    return VirtualSensorConfig(
        name=name, family=template.family, pad=template.pad,
        description=description or (f"{name}: calibrated unit (camera mapping, E, nu); lights "
                                    f"and noise of the shipped {template.name}"),
        material=Material(E_mpa=float(E_mpa), nu=float(nu)), optics=optics, effects=(),
        fps=template.fps, seed=0, surface_smooth_mm=template.surface_smooth_mm)


def resolve_sensor(text: str) -> ResolvedSensor:
    """``--sensor``: a model JSON path, a shipped virtual sensor, or a plugin with a model."""
    from tactile_deploy.sensors.catalog import UnknownSensorError, sensor_config

    p = Path(text)
    if p.suffix == ".json":
        return ResolvedSensor(sensor_config(p), text)
    try:
        return ResolvedSensor(sensor_config(text), text)
    except UnknownSensorError as shipped_error:
        from tactile_deploy.runtime.plugins import PluginError, find_plugin

        try:
            folder = find_plugin(text).folder
        except PluginError:
            raise SensorModelError(f"{shipped_error}; or a plugin (name or folder) whose folder "
                                   f"holds {MODEL_FILE} (the calibration wizard writes it)") \
                from None
        model = folder / MODEL_FILE
        if not model.is_file():
            raise SensorModelError(
                f"plugin {text!r} ({folder}) has no {MODEL_FILE}: recalibrate it with the "
                "wizard (its discrepancy step writes the unit's model), or give a model JSON "
                "(docs/discrepancy.md)") from None
        return ResolvedSensor(sensor_config(model), str(model), str(folder))
