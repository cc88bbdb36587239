"""The file formats of :mod:`training`, each with the path of its committed JSON Schema.

    python -m training.formats [--check]     rewrite (or check) the schemas

Models are on :class:`tactile_deploy.fileformat.StrictModel`; a test fails when a committed
schema differs from its model's (``tests/test_formats.py``).
"""

from __future__ import annotations

from pathlib import Path

from tactile_deploy.fileformat import Format, schemas_main
from training.card import ModelCard
from training.config import TrainConfig

_HERE = Path(__file__).resolve().parent

#: Every file format of training, by name.
FORMATS = {f.name: f for f in (
    Format("training config (training/configs/*.json)", TrainConfig,
           _HERE / "train_config.schema.json"),
    Format("model card (exported/NAME.json)", ModelCard, _HERE / "model_card.schema.json"),
)}

if __name__ == "__main__":
    raise SystemExit(schemas_main(FORMATS))
