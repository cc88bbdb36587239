"""Rigid indenters: loading, our procedural library, and the pressing-surface envelope.

Importing this package is cheap: meshes are built and envelopes rasterised on first use.
"""

from tactile_deploy.indenters.base import (
    DEFAULT_MAX_RELIEF_MM,
    DEFAULT_PITCH_MM,
    ENVELOPE_OUTSIDE_MM,
    AnalyticIndenter,
    AnalyticParaboloid,
    AnalyticSphere,
    EnvelopeGrid,
    Indenter,
    default_cache_dir,
)
from tactile_deploy.indenters.library import get_indenter, library_entry, list_indenters
from tactile_deploy.indenters.loading import load_indenter
from tactile_deploy.indenters.pose import ContactPose, indenter_to_sensor, pose_matrix, sensor_to_indenter_xy

__all__ = [
    "DEFAULT_MAX_RELIEF_MM",
    "DEFAULT_PITCH_MM",
    "ENVELOPE_OUTSIDE_MM",
    "AnalyticIndenter",
    "AnalyticParaboloid",
    "AnalyticSphere",
    "ContactPose",
    "EnvelopeGrid",
    "Indenter",
    "default_cache_dir",
    "get_indenter",
    "indenter_to_sensor",
    "library_entry",
    "list_indenters",
    "load_indenter",
    "pose_matrix",
    "sensor_to_indenter_xy",
]
