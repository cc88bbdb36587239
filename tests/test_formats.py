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


def test_committed_result_files_validate_through_their_readers(tmp_path):
    """The result files committed in the repository are documents of their formats: the
    training histories and experiments of docs/results and the learned read-out's card; a
    changed field is refused with the file, the field and the value named."""
    from pathlib import Path

    from tactile_deploy.training.experiments import ExperimentsError, load_experiments
    from tactile_deploy.training.run_files import TrainingRunFileError, load_training_history
    from tactile_deploy.training.shading_net.card import load_readout_card

    root = Path(__file__).resolve().parents[1]
    histories = sorted((root / "docs" / "results").glob("*.history.json"))
    experiments = sorted((root / "docs" / "results").glob("experiments_*.json"))
    assert len(histories) >= 2 and len(experiments) >= 2
    for path in histories:
        history = load_training_history(path)
        assert history.surface and all(r.val_rmse_mm > 0 for r in history.surface), path
    for path in experiments:
        report = load_experiments(path)
        assert report.runs and len(report.runs) == len(json.loads(path.read_text())["runs"]), path
    for pad in ("gelslim", "gelsight_mini", "digit"):      # every shipped read-out's card names its graph
        card = load_readout_card(root / "exported" / f"{pad}_readout.json")
        counts = card.data.presses_by_kind            # older cards do not count them
        assert card.model == f"{pad}_readout.onnx", pad
        assert counts is None or card.data.presses_per_unit * card.family.units == sum(counts.values()), pad

    doc = json.loads(histories[0].read_text())
    doc["surface"][0]["epoch"] = 0
    (tmp_path / "h.json").write_text(json.dumps(doc))
    with pytest.raises(TrainingRunFileError, match=r"(?s)h\.json.*field 'surface\.0\.epoch'.*greater than or equal to 1.*got 0"):
        load_training_history(tmp_path / "h.json")
    doc = json.loads(experiments[0].read_text())
    doc["runs"][0]["group"] = "sizes"
    (tmp_path / "e.json").write_text(json.dumps(doc))
    with pytest.raises(ExperimentsError, match=r"(?s)e\.json.*field 'runs\.0\.group'.*got \"sizes\""):
        load_experiments(tmp_path / "e.json")
