"""Every file format's committed JSON Schema is its model's (one test per format; rewrite them
with ``python -m tactile_deploy.formats``, ``python -m tactile_deploy.calibration.formats`` and
``python -m tactile_deploy.training.formats``), and every model is on the one strict base."""

from __future__ import annotations

import json

import pytest
from pydantic import ValidationError

from tactile_deploy.calibration.formats import FORMATS as CALIBRATION_FORMATS
from tactile_deploy.fileformat import StrictModel
from tactile_deploy.formats import FORMATS as RUNTIME_FORMATS

pytest.importorskip("torch", reason="the training formats import training (train extra)")
from tactile_deploy.training.formats import FORMATS as TRAINING_FORMATS  # noqa: E402

ALL = {**RUNTIME_FORMATS, **CALIBRATION_FORMATS, **TRAINING_FORMATS}


@pytest.mark.parametrize("name", sorted(ALL))
def test_committed_schema_is_the_models(name):
    fmt = ALL[name]
    assert fmt.schema_path.is_file(), f"{fmt.schema_path} is missing: run python -m <package>.formats"
    assert fmt.schema_path.read_text(encoding="utf-8") == fmt.schema_text(), (
        f"{fmt.schema_path} is stale: run python -m tactile_deploy.formats / tactile_deploy.calibration.formats / "
        "tactile_deploy.training.formats")


@pytest.mark.parametrize("name", sorted(ALL))
def test_every_format_refuses_unknown_fields_and_nan(name):
    """The strict base: an unknown field is an error naming it; so is NaN where a number goes."""
    model = ALL[name].model
    assert issubclass(model, StrictModel)
    assert model.model_config["extra"] == "forbid"
    with pytest.raises(ValidationError, match="no_such_field"):
        model.model_validate({"no_such_field": 1})
    numbers = [k for k, f in model.model_fields.items() if f.annotation in (float, float | None)]
    if model.model_config.get("allow_inf_nan") is False and numbers:
        with pytest.raises(ValidationError, match=numbers[0]):
            model.model_validate_json(json.dumps({numbers[0]: "NaN"}).replace('"NaN"', "NaN"))
