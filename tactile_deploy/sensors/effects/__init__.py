"""Effects of virtual sensors: one module per effect, registered by name.

``REGISTRY`` maps a name to its ``module:Class`` (imported on first use), :func:`effect_class`
returns the class; :func:`get_effect` builds one from a name and parameters
(the JSON form ``{"name": ..., "params": {...}}``); :func:`list_effects` names them. Every effect
is documented in its module's docstring (physics, signature, residual, realistic range) and in
docs/effects.md. To add an effect: write a module with an :class:`Effect` subclass and add it to
``REGISTRY``.
"""

from __future__ import annotations

import importlib

from tactile_deploy.sensors.effects.base import Effect, EffectParams

#: effect name -> "module:ClassName" (imported on first use)
REGISTRY = {
    "dome": "dome:Dome",
    "tilt": "tilt:Tilt",
    "zero_offset": "zero_offset:ZeroOffset",
    "hyperelastic": "hyperelastic:Hyperelastic",
    "lens_distortion": "lens_distortion:LensDistortion",
    "pixel_scale": "pixel_scale:PixelScale",
    "illumination_gradient": "illumination_gradient:IlluminationGradient",
    "saturation": "saturation:Saturation",
    "led_drift": "led_drift:LedDrift",
    "depth_scale": "depth_scale:DepthScale",
    "position_offset": "position_offset:PositionOffset",
    "rotation_offset": "rotation_offset:RotationOffset",
    "poisson_drift": "poisson_drift:PoissonDrift",
    "compression_set": "compression_set:CompressionSet",
    "gain_gradient": "gain_gradient:GainGradient",
    "blur": "blur:Blur",
    "shading_saturation": "shading_saturation:ShadingSaturation",
    "friction": "friction:Friction",
}


class UnknownEffectError(KeyError):
    """An effect name that is not registered (the message lists the known ones)."""

    def __str__(self) -> str:
        return str(self.args[0])


def effect_class(name: str) -> type[Effect]:
    """The class registered under ``name``."""
    if name not in REGISTRY:
        raise UnknownEffectError(f"unknown effect {name!r}; known effects: "
                                 f"{', '.join(sorted(REGISTRY))}")
    module, cls = REGISTRY[name].split(":")
    return getattr(importlib.import_module(f"{__name__}.{module}"), cls)


def get_effect(name: str, params: dict | EffectParams | None = None) -> Effect:
    """Build the effect ``name`` with ``params`` (dict or its Params model; None = null)."""
    return effect_class(name)(params)


def list_effects(kind: str | None = None) -> list[str]:
    """Registered effect names (``kind``: "mechanical", "optical" or None for all)."""
    names = sorted(REGISTRY)
    if kind is None:
        return names
    return [n for n in names if effect_class(n).kind == kind]


__all__ = ["REGISTRY", "Effect", "EffectParams", "UnknownEffectError", "effect_class",
           "get_effect", "list_effects"]
