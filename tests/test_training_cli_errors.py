"""``python -m tactile_deploy.training`` and ``python -m tactile_deploy.training.shading_net`` on user mistakes: one clean
``error: ...`` message and exit status 2, checked before any work; a run folder resumed only with
the settings it was trained with; caches reused only for the data they hold; exports that replace
files only with --overwrite and never half; Ctrl-C during training ends with a note and status 130.

Config and option mistakes need no training; the resume and export checks use one tiny run
(a few seconds on a CPU)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from tactile_deploy.training.__main__ import main
from tactile_deploy.training.errors import UsageError, run_command

ROOT = Path(__file__).resolve().parents[1]
STAGE = {"epochs": 1, "batch_size": 8, "lr": 2e-3, "kl_weight": 1e-5}
SYNTHETIC = {
    "n_samples": 16, "seed": 9, "indenters": ["sphere_r4", "cube_corner"], "radius_max_mm": 3.0,
    "depth_min_mm": 0.3, "depth_max_mm": 1.0, "contact_radius_mm": 7.5, "formulation": "standard",
}


def tiny_config(run_dir: Path, cache: Path, **changes) -> dict:
    cfg = {
        "run_dir": str(run_dir), "threads": 1,
        "model": {
            "image": {"widths": [8, 8, 16, 16, 32], "hidden": 16, "latent": 16},
            "mesh": {"channels": [4, 4, 4, 8], "cheb_k": [2, 2, 2, 2], "latent": 16},
            "projection": {"hidden": [32, 32, 32]},
            "lean_decoder": {"channels": [8, 8, 8, 8]},
            "ood_decoder": {"channels": [4, 4, 4, 4, 4]},
        },
        "data": {"synthetic": dict(SYNTHETIC), "cache_file": str(cache)},
        "image_vae": STAGE, "mesh_vae": STAGE, "lean_decoder": STAGE, "ood_decoder": STAGE, "projection": STAGE,
    }
    cfg.update(changes)
    return cfg


def _write(path: Path, doc) -> Path:
    path.write_text(doc if isinstance(doc, str) else json.dumps(doc))
    return path


def _error(capsys, argv, run=None) -> str:
    """The message of a refused command: status 2, no traceback, one ``error:`` line."""
    rc = run_command(lambda: run(argv)) if run is not None else main([str(a) for a in argv])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert "Traceback" not in err
    assert len([ln for ln in err.splitlines() if ln.startswith("error: ")]) == 1, err
    assert err.startswith("error: "), err
    return err


# ------------------------------------------------------------------------------ train: configs
@pytest.mark.parametrize("case,expected", [
    ("unknown_key", ["field 'bogus'", "Extra inputs"]),
    ("wrong_type", ["field 'data.synthetic.n_samples'", '"many"']),
    ("negative_epochs", ["field 'image_vae.epochs'", "greater than 0", "-1"]),
    ("broken_json", ["not valid JSON (line"]),
    ("missing_file", ["not found", "training/configs"]),
    ("missing_dataset_dir", ["data.dataset_dir", "no such folder"]),
    ("not_a_dataset", ["data.dataset_dir", "dataset.json not found"]),
])
def test_config_mistakes_are_one_error_line(tmp_path, capsys, case, expected):
    run = tmp_path / "run"
    base = {"run_dir": str(run), "data": {"synthetic": {"n_samples": 4}}}
    docs = {
        "unknown_key": {**base, "bogus": 1},
        "wrong_type": {**base, "data": {"synthetic": {"n_samples": "many"}}},
        "negative_epochs": {**base, "image_vae": {"epochs": -1}},
        "broken_json": '{"run_dir": "x", "data": {',
        "missing_dataset_dir": {**base, "data": {"dataset_dir": str(tmp_path / "nowhere")}},
        "not_a_dataset": {**base, "data": {"dataset_dir": str(tmp_path)}},
    }
    path = tmp_path / "cfg.json"
    if case in docs:
        _write(path, docs[case])
    err = _error(capsys, ["train", "--config", path])
    assert str(path) in err
    for text in expected:
        assert text in err, err
    assert not run.exists()  # nothing is made for a refused config


def test_bad_options_are_one_error_line(tmp_path, capsys):
    cfg = _write(tmp_path / "cfg.json", {"run_dir": str(tmp_path / "run"), "data": {"synthetic": {"n_samples": 4}}})
    err = _error(capsys, ["train", "--config", cfg, "--device", "gpu"])
    assert "--device" in err and "'gpu'" in err and "'cpu'" in err
    assert not (tmp_path / "run").exists()

    err = _error(capsys, ["export", "--run", tmp_path / "nowhere", "--out", tmp_path / "m.onnx", "--variant", "bogus"])
    assert "--variant 'bogus'" in err and "lean-int8-fastood" in err
    err = _error(capsys, ["export", "--run", tmp_path / "nowhere", "--out", tmp_path / "m.onnx"])
    assert f"--run {tmp_path / 'nowhere'}: no such folder" in err
    err = _error(capsys, ["heldout", "--run", tmp_path / "nowhere"])
    assert "--run" in err and "no such folder" in err
    (tmp_path / "empty_run").mkdir()
    err = _error(capsys, ["heldout", "--run", tmp_path / "empty_run"])
    assert "holds no config.json" in err
    err = _error(capsys, ["export", "--run", tmp_path / "empty_run", "--out", tmp_path / "m.onnx"])
    assert "holds no model.pt" in err


def test_export_refuses_existing_out_before_any_work(tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    (run / "model.pt").write_bytes(b"not read: the output is checked first")
    (run / "heldout.npz").write_bytes(b"")
    out = tmp_path / "m.onnx"
    out.write_bytes(b"old graph")
    err = _error(capsys, ["export", "--run", run, "--out", out])
    assert f"{out} exists" in err and "--overwrite" in err
    assert out.read_bytes() == b"old graph"
    err = _error(capsys, ["export", "--run", run, "--out", tmp_path / "m.json"])
    assert "must end in .onnx" in err


def test_export_help_says_the_default_out_is_relative_to_the_current_folder(capsys):
    with pytest.raises(SystemExit):
        main(["export", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "exported/gelslim_mesh.onnx" in text and "relative to the current folder" in text
    assert "--overwrite" in text


def test_evaluate_checks_model_and_out_before_simulating(tmp_path, capsys, monkeypatch):
    import tactile_deploy.training.evaluation

    def never(*args, **kwargs):
        raise AssertionError("simulated before checking the options")

    monkeypatch.setattr(tactile_deploy.training.evaluation, "run_evaluation", never)
    good_out = tmp_path / "report.json"
    err = _error(capsys, ["evaluate", "--model", tmp_path / "none.onnx", "--out", good_out, "--domains", "primitives"])
    assert "--model" in err and "no such file" in err
    not_onnx = _write(tmp_path / "m.onnx", "not a graph")
    err = _error(capsys, ["evaluate", "--model", not_onnx, "--out", good_out, "--domains", "primitives"])
    assert f"--model {not_onnx}" in err
    err = _error(capsys, ["evaluate", "--model", not_onnx, "--out", tmp_path / "no" / "r.json", "--domains", "primitives"])
    assert "--out" in err and "does not exist" in err
    err = _error(capsys, ["evaluate", "--model", not_onnx, "--out", good_out, "--domains", "primitives,moon"])
    assert "--domains" in err and "'moon'" in err
    assert not good_out.exists()


# ------------------------------------------------------------------------------- data caches
def test_data_cache_of_other_settings_is_refused(tmp_path):
    from tactile_deploy.atomic import write_npz
    from tactile_deploy.training.config import DataConfig
    from tactile_deploy.training.data import cache_spec, check_data, load

    cache = tmp_path / "data.npz"
    cfg = DataConfig.model_validate({"synthetic": SYNTHETIC, "cache_file": str(cache)})
    write_npz(cache, depth_mm=np.zeros((2, 8, 8), np.float32), source=np.array("synthetic seed=4 rank=0"))
    with pytest.raises(UsageError, match=r"holds other data .*seed=4.*this config: seed 9"):
        check_data(cfg)
    # an older cache without its settings: reused when its seed, rank and size are the config's
    n = cfg.synthetic.n_samples
    write_npz(cache, depth_mm=np.zeros((n, 8, 8), np.float32), displacement_mm=np.zeros((n, 5, 3), np.float32),
              contact_id=np.arange(n), indenter=np.array(["sphere_r4"] * n),
              source=np.array(f"synthetic seed={cfg.synthetic.seed} rank=0"))
    assert len(load(cfg).depth_mm) == n
    other = cfg.synthetic.model_copy(update={"n_samples": 32, "seed": 3})
    write_npz(cache, depth_mm=np.zeros((2, 8, 8), np.float32), spec=np.array(json.dumps(cache_spec(other))))
    with pytest.raises(UsageError) as e:
        load(cfg)
    msg = str(e.value)
    assert f"data.cache_file {cache}" in msg
    assert "data.synthetic.n_samples: cache 32, config 16" in msg and "data.synthetic.seed: cache 3, config 9" in msg
    assert "delete it" in msg and "another data.cache_file" in msg


# ---------------------------------------------------------------------------- int8 calibration
def test_int8_calibration_never_falls_back_to_heldout_maps(tmp_path):
    from tactile_deploy.training.config import TrainConfig
    from tactile_deploy.training.export import calibration_maps

    cfg = TrainConfig.model_validate({"run_dir": "x", "data": {"dataset_dir": str(tmp_path / "moved")}})
    with pytest.raises(UsageError, match=r"data.dataset_dir .*moved.*cannot be read.*--variant hybrid-fastood\)"):
        calibration_maps(cfg)
    # a held-out file simulated with the seed the calibration would take: another seed is used
    cfg = TrainConfig.model_validate({"run_dir": "x", "data": {"synthetic": SYNTHETIC}})
    maps, info = calibration_maps(cfg, n=2, heldout_seed=SYNTHETIC["seed"] + 1000)
    assert maps.shape == (2, 1, 128, 128) and info["n_maps"] == 2
    assert f"seed {SYNTHETIC['seed'] + 2000}" in info["source"] and f"held-out maps: seed {SYNTHETIC['seed'] + 1000}" in info["source"]


# ------------------------------------------------------------------------------- shading_net
def _shading(argv):
    from tactile_deploy.training.shading_net.train import main as shading_main

    return shading_main([str(a) for a in argv])


def test_shading_net_options_checked_up_front(tmp_path, capsys):
    err = _error(capsys, ["--units", "0", "--out", tmp_path / "r.onnx"], run=_shading)
    assert "--units must be >= 1, got 0" in err
    err = _error(capsys, ["--presses", "-5", "--out", tmp_path / "r.onnx"], run=_shading)
    assert "--presses must be >= 1, got -5" in err
    err = _error(capsys, ["--design", "nosuchsensor", "--out", tmp_path / "r.onnx"], run=_shading)
    assert "--design" in err and "nosuchsensor" in err
    out = _write(tmp_path / "r.onnx", "old read-out")
    err = _error(capsys, ["--units", "1", "--out", out], run=_shading)
    assert f"{out} exists" in err and "--overwrite" in err
    assert out.read_text() == "old read-out"


def test_shading_net_data_cache_must_match_the_options(tmp_path, capsys):
    from tactile_deploy.atomic import write_npz

    cache = tmp_path / "crops.npz"
    write_npz(cache, features=np.zeros((1, 11, 4, 4), np.float32), depth_mm=np.zeros((1, 4, 4), np.float32),
              pitch_mm=0.2)
    err = _error(capsys, ["--units", "1", "--data-cache", cache, "--out", tmp_path / "r.onnx"], run=_shading)
    assert "--data-cache" in err and "no record" in err
    spec = {"design": "gelslim1", "units": 2, "presses": 6, "seed": 5, "crop_cells": 48, "jitter_cells": 8}
    write_npz(cache, features=np.zeros((1, 11, 4, 4), np.float32), depth_mm=np.zeros((1, 4, 4), np.float32),
              pitch_mm=0.2, spec=np.array(json.dumps(spec)))
    err = _error(capsys, ["--units", "1", "--presses", "6", "--data-cache", cache, "--out", tmp_path / "r.onnx"],
                 run=_shading)
    assert "units: cache 2, now 1" in err and "presses:" not in err
    assert not (tmp_path / "r.onnx").exists()


def test_shading_net_command_line(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    res = subprocess.run([sys.executable, "-m", "tactile_deploy.training.shading_net", "--units", "0", "--out", str(tmp_path / "r.onnx")],
                         capture_output=True, text=True, env=env, cwd=tmp_path, timeout=120, check=False)
    assert res.returncode == 2 and res.stderr.strip() == "error: --units must be >= 1, got 0", res.stderr
    for option, value, message in (("--workers", "0", "error: --workers must be >= 1, got 0"),
                                   ("--device", "gpu0", "error: --device must be a torch device such as cpu or cuda, "
                                                        "got 'gpu0'")):
        res = subprocess.run([sys.executable, "-m", "tactile_deploy.training.shading_net", option, value, "--out",
                              str(tmp_path / "r.onnx")], capture_output=True, text=True, env=env, cwd=tmp_path,
                             timeout=120, check=False)
        assert res.returncode == 2 and res.stderr.strip() == message, res.stderr
    res = subprocess.run([sys.executable, "-m", "tactile_deploy.training.shading_net", "--help"], capture_output=True, text=True,
                         env=env, cwd=tmp_path, timeout=120, check=False)
    text = " ".join(res.stdout.split())
    assert "virtual units of the design (default: 8)" in text and "(default: 1000)" in text
    assert "exported/<the design's pad>_readout.onnx" in text and "relative to the current folder" in text


# ------------------------------------------------------------------------ a tiny trained run
@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """A trained tiny run (one epoch per stage) and its config file."""
    from tactile_deploy.training.config import TrainConfig
    from tactile_deploy.training.train import train

    root = tmp_path_factory.mktemp("tiny")
    cfg = tiny_config(root / "run", root / "data.npz")
    train(TrainConfig.model_validate(cfg), log=lambda m: None)
    return root, _write(root / "cfg.json", cfg), cfg


def _files(folder: Path) -> dict:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("change,expected", [
    ({"model": {"image": {"latent": 8}}}, ["model.image.latent: run 16, config 8"]),
    ({"data": {"dataset_dir": "elsewhere"}}, ["data.dataset_dir: run null", "data.synthetic: run {"]),
    ({"seed": 3}, ["seed: run 0, config 3"]),
    ({"image_vae": {"epochs": 4}}, ["image_vae.epochs: run 1, config 4 (stage image_vae is complete)"]),
])
def test_resume_with_other_settings_is_refused(tiny_run, tmp_path, capsys, change, expected):
    root, _, cfg = tiny_run
    cfg = json.loads(json.dumps(cfg))
    for section, value in change.items():
        if isinstance(value, dict) and section != "data":
            for k, v in value.items():
                if isinstance(v, dict):
                    cfg[section][k].update(v)
                else:
                    cfg[section] = {**cfg[section], k: v}
        else:
            cfg[section] = value
    before = _files(root / "run")
    path = _write(tmp_path / "changed.json", cfg)
    err = _error(capsys, ["train", "--config", path])
    for text in expected:
        assert text in err, err
    assert f"run_dir {root / 'run'}" in err and "choose another run_dir, or delete" in err
    assert _files(root / "run") == before  # config.json, model.pt and the checkpoints untouched


def test_resume_may_change_threads_and_evaluation(tiny_run, tmp_path, capsys):
    from tactile_deploy.training.config import TrainConfig

    root, _, cfg = tiny_run
    cfg = {**cfg, "threads": 2, "eval_max_samples": 3, "data": {**cfg["data"], "cache_file": str(root / "data.npz")}}
    assert main(["train", "--config", str(_write(tmp_path / "c.json", cfg))]) == 0
    out = capsys.readouterr().out
    assert out.count("skipped") == 5
    assert TrainConfig.load(root / "run" / "config.json").eval_max_samples == 3  # the accepted config is kept
    assert not list((root / "run").rglob("*partial*"))


def test_ctrl_c_during_training_then_resume(tiny_run, tmp_path, capsys):
    """Ctrl-C: a note, status 130, no temporary file left; the interrupted stage resumes with more
    epochs, never with fewer than it has run."""
    _, _, cfg = tiny_run
    run = tmp_path / "run"
    long = {**cfg, "run_dir": str(run), "image_vae": {**STAGE, "epochs": 100000}}
    path = _write(tmp_path / "long.json", long)
    env = {**os.environ, "PYTHONPATH": str(ROOT), "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1"}
    # as from a terminal: SIGINT handled by default even when this test runner was started with it
    # ignored (a background job), which the child would otherwise inherit
    proc = subprocess.Popen([sys.executable, "-m", "tactile_deploy.training", "train", "--config", str(path)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env, cwd=tmp_path,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    t0 = time.time()
    for line in proc.stdout:
        if line.startswith("[image_vae] epoch 3/"):  # the checkpoint of epoch 2 is on disk
            break
        assert time.time() - t0 < 120, "no third epoch"
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert "interrupted; rerun the same command to resume" in err and "Traceback" not in err
    assert not [p for p in run.rglob("*") if "partial" in p.name]
    from tactile_deploy.safe_torch import load_torch_file

    done = load_torch_file(run / "checkpoints" / "image_vae.pt")["epoch"]
    assert done >= 2  # the checkpoint being saved at Ctrl-C may be the one before

    fewer = _write(tmp_path / "fewer.json", {**long, "image_vae": {**STAGE, "epochs": 1}})
    err = _error(capsys, ["train", "--config", fewer])
    assert f"image_vae.epochs: run 100000, config 1, but {done} epochs have run" in err
    more = _write(tmp_path / "more.json", {**long, "image_vae": {**STAGE, "epochs": done + 1}})
    assert main(["train", "--config", str(more)]) == 0
    out = capsys.readouterr().out
    assert f"[image_vae] resuming after epoch {done}" in out and "held-out:" in out
    history = json.loads((run / "history.json").read_text())
    assert len(history["image_vae"]) == done + 1


@pytest.mark.slow
def test_export_prints_both_graphs_and_replaces_the_set_only_whole(tiny_run, tmp_path, capsys, monkeypatch):
    import tactile_deploy.training.card
    import tactile_deploy.training.export

    root, _, _ = tiny_run
    run = root / "run"
    with np.load(run / "heldout.npz") as held:  # fast stand-ins for the simulated calibration maps
        calib = held["depth_mm"][:, None].astype(np.float32) * 0.9
    monkeypatch.setattr(tactile_deploy.training.export, "calibration_maps",
                        lambda cfg, n=256, heldout_seed=None: (calib, {"source": "test maps", "n_maps": len(calib)}))
    out = tmp_path / "m.onnx"
    # the tiny run has the latent decoders only: their int8 variant (the default needs the surface decoder)
    assert main(["export", "--run", str(run), "--out", str(out), "--variant", "lean-int8-fastood"]) == 0
    text = capsys.readouterr().out
    assert "parity of the fp32 graph m_fp32.onnx vs torch" in text
    assert "shipped int8 graph m.onnx vs m_fp32.onnx: max |difference|" in text
    card = json.loads(out.with_suffix(".json").read_text())
    assert card["int8_calibration"] == {"source": "test maps", "n_maps": len(calib)}
    assert "int8 calibration: " in out.with_suffix(".md").read_text()
    assert not [p for p in tmp_path.iterdir() if "partial" in p.name]

    before = _files(tmp_path)
    err = _error(capsys, ["export", "--run", run, "--out", out, "--variant", "lean-fastood"])
    assert "--overwrite" in err and _files(tmp_path) == before

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(tactile_deploy.training.card, "write_card", interrupted)
    assert main(["export", "--run", str(run), "--out", str(out), "--variant", "lean-fastood", "--overwrite"]) == 130
    assert _files(tmp_path) == before  # the old set, whole; no temporary file left


def test_export_adapt_refuses_a_mismatched_bundle_cleanly(tiny_run, tmp_path, capsys):
    root, _, _ = tiny_run
    shipped = ROOT / "exported" / "gelslim_mesh.onnx"
    if not shipped.is_file():
        pytest.fail(f"{shipped} is missing: it is committed with the repository (check out main again)")
    out = tmp_path / "step"
    out.mkdir()
    (out / "card.json").write_text("{}")
    err = _error(capsys, ["export-adapt", "--bundle", root / "run", "--onnx", shipped, "--out", out])
    assert "not exported from this bundle" in err and "--onnx" in err
    assert _files(tmp_path) == {"step/card.json": b"{}"}  # the step folder as it was, nothing built aside left
    other = tmp_path / "notes"
    other.mkdir()
    (other / "keep.txt").write_text("mine")
    err = _error(capsys, ["export-adapt", "--bundle", root / "run", "--onnx", shipped, "--out", other])
    assert "is not an adaptation step folder" in err and (other / "keep.txt").read_text() == "mine"


def test_augmented_twin_writes_the_run_formats(tiny_run, tmp_path):
    """The augmented twin of a run writes metrics.json in the training run's format: the reader
    gives back what make_twin returned, and the twin's source is the run's model.pt."""
    from tactile_deploy.atomic import finite_or_null
    from tactile_deploy.training.adaptation.augmented_twin import make_twin
    from tactile_deploy.training.config import StageConfig, TrainConfig
    from tactile_deploy.training.run_files import load_training_metrics

    root, _, cfg = tiny_run
    twin_cfg = TrainConfig.model_validate({**cfg, "run_dir": str(tmp_path / "twin"), "augmentation": {}})
    metrics = make_twin(root / "run" / "model.pt", twin_cfg, tmp_path / "twin", StageConfig(**STAGE), n_eval=2,
                        log=lambda m: None)
    back = load_training_metrics(tmp_path / "twin" / "metrics.json")
    assert back.model_dump(mode="json", exclude_unset=True) == finite_or_null(json.loads(json.dumps(metrics)))
    assert back.twin_of.bundle == str(root / "run" / "model.pt") and back.scales is None
    assert back.decoders["lean"].heldout_augmented.n_samples == back.n_samples == 2


def test_missing_init_weights_is_refused_before_any_data(tmp_path, capsys):
    cfg = tiny_config(tmp_path / "run", tmp_path / "data.npz")
    cfg["init_weights"] = str(tmp_path / "nowhere" / "model.pt")
    err = _error(capsys, ["train", "--config", _write(tmp_path / "cfg.json", cfg)])
    assert f"init_weights: {tmp_path / 'nowhere' / 'model.pt'} is not a file" in err, err
    assert not (tmp_path / "data.npz").exists()  # refused before generating the data
