"""The file formats of :mod:`tactile_deploy.training` and their committed JSON Schemas (``python -m tactile_deploy.training.formats``
rewrites them; see :mod:`tactile_deploy.fileformat`)."""

from __future__ import annotations

from pathlib import Path

from tactile_deploy.fileformat import Format, schemas_main
from tactile_deploy.training.card import ModelCard
from tactile_deploy.training.config import TrainConfig
from tactile_deploy.training.evaluation import EvaluationReport
from tactile_deploy.training.experiments import ExperimentsReport
from tactile_deploy.training.run_files import TrainingHistory, TrainingMetrics
from tactile_deploy.training.shading_net.card import ReadoutCard

_HERE = Path(__file__).resolve().parent

#: Every file format of training, by name.
FORMATS = {f.name: f for f in (
    Format("training config (training/configs/*.json)", TrainConfig,
           _HERE / "train_config.schema.json"),
    Format("model card (exported/NAME.json)", ModelCard, _HERE / "model_card.schema.json"),
    Format("evaluation report (python -m tactile_deploy.training evaluate --out, docs/results/evaluation.json)", EvaluationReport,
           _HERE / "evaluation_report.schema.json"),
    Format("training run metrics (RUN/metrics.json)", TrainingMetrics,
           _HERE / "training_metrics.schema.json"),
    Format("training run history (RUN/history.json, docs/results/*.history.json)", TrainingHistory,
           _HERE / "training_history.schema.json"),
    Format("experiments results (DIR/experiments.json, docs/results/experiments_*.json)", ExperimentsReport,
           _HERE / "experiments.schema.json"),
    Format("learned read-out card (exported/gelslim_readout.json)", ReadoutCard,
           _HERE / "shading_net" / "readout_card.schema.json"),
)}

if __name__ == "__main__":
    raise SystemExit(schemas_main(FORMATS))
