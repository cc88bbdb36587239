"""The file formats of :mod:`tactile_deploy.training` and their committed JSON Schemas (``python -m tactile_deploy.training.formats``
rewrites them; see :mod:`tactile_deploy.fileformat`)."""

from __future__ import annotations

from pathlib import Path

from tactile_deploy.fileformat import Format, schemas_main
from tactile_deploy.training.card import ModelCard
from tactile_deploy.training.config import TrainConfig

_HERE = Path(__file__).resolve().parent

#: Every file format of training, by name.
FORMATS = {f.name: f for f in (
    Format("training config (training/configs/*.json)", TrainConfig,
           _HERE / "train_config.schema.json"),
    Format("model card (exported/NAME.json)", ModelCard, _HERE / "model_card.schema.json"),
)}

if __name__ == "__main__":
    raise SystemExit(schemas_main(FORMATS))
