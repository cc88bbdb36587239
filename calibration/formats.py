"""The file formats of :mod:`tactile_deploy.calibration` and their committed JSON Schemas (``python -m tactile_deploy.calibration.formats``
rewrites them; see :mod:`tactile_deploy.fileformat`)."""

from __future__ import annotations

from pathlib import Path

from tactile_deploy.calibration.discrepancy.apply import SensorModelHistory
from tactile_deploy.calibration.discrepancy.collect import CollectionLog
from tactile_deploy.calibration.discrepancy.measured import MeasuredHeader
from tactile_deploy.calibration.discrepancy.verdict import DiscrepancyVerdict
from tactile_deploy.calibration.fem_fit.result import FemResult
from tactile_deploy.calibration.rig.config import RIG_CONFIG_SCHEMA_PATH, RigConfig
from tactile_deploy.calibration.wizard.report import CalibrationMetrics
from tactile_deploy.calibration.wizard.config import SCHEMA_PATH as WIZARD_CONFIG_SCHEMA
from tactile_deploy.calibration.wizard.config import WizardConfig
from tactile_deploy.calibration.wizard.state import WizardState
from tactile_deploy.fileformat import Format, schemas_main

_HERE = Path(__file__).resolve().parent

#: Every file format of the calibrations, by name.
FORMATS = {f.name: f for f in (
    Format("wizard config", WizardConfig, WIZARD_CONFIG_SCHEMA),
    Format("wizard state (WORK/state.json)", WizardState,
           _HERE / "wizard" / "wizard_state.schema.json"),
    Format("calibration metrics (PLUGIN/calibration/metrics.json)", CalibrationMetrics,
           _HERE / "wizard" / "metrics.schema.json"),
    Format("FEM result (fem.json)", FemResult, _HERE / "fem_fit" / "fem_result.schema.json"),
    Format("rig config", RigConfig, RIG_CONFIG_SCHEMA_PATH),
    Format("discrepancy verdict (REPORT/verdict.json)", DiscrepancyVerdict,
           _HERE / "discrepancy" / "verdict.schema.json"),
    Format("rig collection log (rig_log in a collected .npz)", CollectionLog,
           _HERE / "discrepancy" / "collection_log.schema.json"),
    Format("measured-data header (header_json in a measured .npz)", MeasuredHeader,
           _HERE / "discrepancy" / "measured_header.schema.json"),
    Format("sensor model history (MODEL.versions/history.json)", SensorModelHistory,
           _HERE / "discrepancy" / "sensor_model_history.schema.json"),
)}

if __name__ == "__main__":
    raise SystemExit(schemas_main(FORMATS))
