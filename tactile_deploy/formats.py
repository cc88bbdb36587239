"""The file formats of :mod:`tactile_deploy`, each with the path of its committed JSON Schema.

    python -m tactile_deploy.formats [--check]     rewrite (or check) the schemas

Models are on :class:`tactile_deploy.fileformat.StrictModel`; a test fails when a committed
schema differs from its model's (``tests/test_formats.py``).
"""

from __future__ import annotations

from pathlib import Path

from tactile_deploy.adapt.card import AdaptationCard
from tactile_deploy.adapt.report import AdaptationReport
from tactile_deploy.fileformat import Format, schemas_main
from tactile_deploy.imaging.camera_mapping import CameraMapping
from tactile_deploy.imaging.shading import ShadingHeader
from tactile_deploy.pad.asset import PadCard
from tactile_deploy.runtime.plugins.manifest import PluginManifest
from tactile_deploy.runtime.plugins.versions import AdaptationHistory
from tactile_deploy.runtime.frame_file import FrameMeshMetadata
from tactile_deploy.runtime.run_record import RunRecord
from tactile_deploy.sensors.config import SCHEMA_PATH as VIRTUAL_SENSOR_SCHEMA
from tactile_deploy.sensors.config import VirtualSensorConfig
from tactile_deploy.simulation.contact_file import ContactMetadata
from tactile_deploy.simulation.dataset import DatasetCard, ShardMetadata

_HERE = Path(__file__).resolve().parent

#: Every file format of the runtime and the shared physics, by name.
FORMATS = {f.name: f for f in (
    Format("plugin manifest (plugin.json)", PluginManifest,
           _HERE / "runtime" / "manifest.schema.json"),
    Format("adaptation history (adapted/history.json)", AdaptationHistory,
           _HERE / "runtime" / "plugins" / "adaptation_history.schema.json"),
    Format("adaptation step card (card.json)", AdaptationCard,
           _HERE / "adapt" / "adaptation_card.schema.json"),
    Format("adaptation report (adapted/vN/report.json)", AdaptationReport,
           _HERE / "adapt" / "adaptation_report.schema.json"),
    Format("camera mapping (camera_mapping.json)", CameraMapping,
           _HERE / "imaging" / "camera_mapping.schema.json"),
    Format("shading model header (shading.npz)", ShadingHeader,
           _HERE / "imaging" / "shading_header.schema.json"),
    Format("virtual sensor config", VirtualSensorConfig, VIRTUAL_SENSOR_SCHEMA),
    Format("pad asset card (pads/NAME_vN.json)", PadCard,
           _HERE / "pad" / "pad_card.schema.json"),
    Format("run summary (run.json)", RunRecord, _HERE / "runtime" / "run_record.schema.json"),
    Format("per-frame mesh metadata (metadata in run's mesh_NNNNNN.npz)", FrameMeshMetadata,
           _HERE / "runtime" / "frame_metadata.schema.json"),
    Format("dataset card (dataset.json)", DatasetCard,
           _HERE / "simulation" / "dataset_card.schema.json"),
    Format("dataset shard metadata (metadata in shard_NNNNN.npz)", ShardMetadata,
           _HERE / "simulation" / "shard_metadata.schema.json"),
    Format("simulated contact metadata (metadata in simulate --out FILE.npz)", ContactMetadata,
           _HERE / "simulation" / "contact_metadata.schema.json"),
)}

if __name__ == "__main__":
    raise SystemExit(schemas_main(FORMATS))
