"""`tactile-deploy simulate` (and `indenters list`, `pad export`): reruns and resumes that keep and
report the truth, clean errors that name the option, self-describing files, Ctrl-C."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from typer.testing import CliRunner

from tactile_deploy.cli.main import app

runner = CliRunner()
BATCH = ("simulate", "--n", 4, "--shard-size", 2, "--indenters", "sphere_r4,flat_punch", "--workers", 1)


def run(*args):
    return runner.invoke(app, [str(a) for a in args])


def text(result) -> str:
    return " ".join(result.output.split())


def assert_clean_error(result, *needles):
    """Exit 2 with one `error:` message naming ``needles``, and no traceback or pydantic dump."""
    out = text(result)
    assert result.exit_code == 2, result.output
    assert out.count("error:") == 1 and "Traceback" not in out, result.output
    assert "pydantic" not in out and "validation error" not in out, result.output
    for needle in needles:
        assert needle in out, (needle, result.output)


def card_of(folder):
    return json.loads((folder / "dataset.json").read_text())


def test_rerunning_a_finished_dataset_keeps_it_and_says_so(tmp_path, pad_sim):
    out = tmp_path / "ds"
    assert run(*BATCH, "--seed", 0, "--out", out).exit_code == 0
    before = card_of(out)
    again = run(*BATCH, "--seed", 0, "--out", out)
    assert again.exit_code == 0, again.output
    assert "complete: 2 shards (4 samples)" in text(again) and "nothing to do" in text(again)
    assert "wrote 0" not in text(again)
    after = card_of(out)
    assert after["complete"] and after["shards"] == before["shards"] and len(after["shards"]) == 2
    assert after["counts_per_indenter"] == before["counts_per_indenter"]


def test_resume_prints_and_records_what_happened(tmp_path, pad_sim):
    out = tmp_path / "ds"
    assert run(*BATCH, "--seed", 0, "--out", out).exit_code == 0
    card = card_of(out)
    card["shards"][0]["rejected_poses"] = 3  # what shard 0 recorded when it was simulated
    (out / "dataset.json").write_text(json.dumps(card))
    (out / "shard_00001.npz").unlink()
    resumed = run(*BATCH, "--seed", 0, "--out", out)
    assert resumed.exit_code == 0, resumed.output
    out_text = text(resumed)
    assert "wrote 1 shard to" in out_text and "(2 samples)" in out_text, out_text
    assert "1 shard (2 samples) already there" in out_text and "2 shards (4 samples) in all" in out_text
    assert "4/4" in out_text  # the progress bar counts the shards already on disk
    after = card_of(out)
    assert after["complete"] and [s["rejected_poses"] for s in after["shards"]][0] == 3
    assert after["shards"][0]["sha256"] == card["shards"][0]["sha256"]


def test_a_shard_of_another_dataset_is_refused_not_mixed_in(tmp_path, pad_sim):
    a, b = tmp_path / "a", tmp_path / "b"
    assert run(*BATCH, "--seed", 0, "--out", a).exit_code == 0
    assert run(*BATCH, "--seed", 1, "--out", b).exit_code == 0
    foreign = (b / "shard_00001.npz").read_bytes()
    (a / "shard_00001.npz").write_bytes(foreign)
    # checked against the checksum the card recorded
    refused = run(*BATCH, "--seed", 0, "--out", a)
    assert_clean_error(refused, "shard_00001.npz", "checksum", "delete")
    assert (a / "shard_00001.npz").read_bytes() == foreign  # the user's file is left alone
    # no card (a run killed before it wrote one): checked against the shard's own metadata
    (a / "dataset.json").unlink()
    refused = run(*BATCH, "--seed", 0, "--out", a)
    assert_clean_error(refused, "shard_00001.npz", "seed (--seed): 1 in the shard, 0 now", "delete")
    assert (a / "shard_00001.npz").read_bytes() == foreign
    # a shard whose metadata breaks the format is refused, naming the field and its value
    with np.load(a / "shard_00001.npz") as z:
        arrays = {k: z[k] for k in z.files}
    meta = {**json.loads(str(arrays["metadata"])), "shard_index": -1}
    np.savez(a / "shard_00001.npz", **{**arrays, "metadata": np.array(json.dumps(meta))})
    refused = run(*BATCH, "--seed", 0, "--out", a)
    assert_clean_error(refused, "shard_00001.npz", "field 'shard_index'", "(got -1)", "delete")
    # deleting it, as the message says, regenerates it; the shard without a card entry is kept
    (a / "shard_00001.npz").unlink()
    fixed = run(*BATCH, "--seed", 0, "--out", a)
    assert fixed.exit_code == 0, fixed.output
    assert "wrote 1 shard" in text(fixed) and card_of(a)["complete"]


@pytest.mark.parametrize(
    "args, needles",
    [
        (("--n", 0, "--out", "ds"), ("--n", "got 0")),
        (("--n", 4, "--depth-range", "0.2,2", "--out", "ds"), ("--depth-range 0.2,2", "1.5 mm", "max 2 mm")),
        (("--n", 4, "--depth-range", "0.2,nan", "--out", "ds"), ("--depth-range 0.2,nan",)),
        (("--n", 4, "--shard-size", 0, "--out", "ds"), ("--shard-size", "got 0")),
        (("--n", 4, "--seed", -1, "--out", "ds"), ("--seed", "got -1")),
        (("--n", 4, "--E", "nan", "--out", "ds"), ("--E nan", "MPa")),
        (("--indenter", "cone", "--depth", "nan", "--out", "one.npz"), ("--depth", "got nan")),
        (("--indenter", "cone", "--theta", "inf", "--out", "one.npz"), ("--theta", "got inf")),
        (("--indenter", "cone", "--friction", "stick", "--slide-x", "nan", "--out", "one.npz"),
         ("--slide-x", "got nan")),
        (("--indenter", "cone", "--slide-x", 0.05, "--out", "one.npz"),
         ("--slide-x/--slide-y", "without friction", "--friction stick")),
        (("--indenter", "cone", "--friction", "stick", "--slide-y", 0.05, "--sensor", "gelslim2",
          "--out", "one.npz"), ("--slide-x/--slide-y", "leave out --sensor")),
    ],
)
def test_option_errors_name_the_option_and_value(tmp_path, args, needles):
    args = [tmp_path / a if a in ("ds", "one.npz") else a for a in args]
    assert_clean_error(run("simulate", *args), *needles)
    assert not (tmp_path / "ds").exists() and not (tmp_path / "one.npz").exists()


def test_another_spec_names_the_fields_that_differ(tmp_path, pad_sim):
    out = tmp_path / "ds"
    assert run(*BATCH, "--seed", 0, "--out", out).exit_code == 0
    clash = run(*BATCH, "--seed", 1, "--out", out)
    assert_clean_error(clash, "different dataset", "seed (--seed): 0 in the card, 1 now", "another --out")
    assert "n_samples" not in text(clash) and "shard_size" not in text(clash)  # only what differs


@pytest.mark.parametrize(
    "extra, needles",
    [
        (("--indenter", "cone", "--depth", 0.3), ("--indenter, --depth", "--indenters", "--depth-range")),
        (("--x", 1.0, "--theta", 30), ("--x, --theta", "draws random contacts", "leave out --n")),
        (("--overwrite",), ("--overwrite", "new --out folder")),
        (("--slide-x", 0.02), ("--slide-x", "leave out --n")),
    ],
)
def test_single_contact_options_are_refused_with_n(tmp_path, extra, needles):
    out = tmp_path / "ds"
    assert_clean_error(run(*BATCH, *extra, "--out", out), *needles)
    assert not out.exists()


def test_dataset_options_are_refused_without_n(tmp_path):
    out = tmp_path / "one.npz"
    assert_clean_error(run("simulate", "--indenter", "cone", "--depth-range", "0.2,1", "--out", out),
                       "--depth-range", "--n")
    assert not out.exists()


def test_outputs_of_the_wrong_kind_are_refused_before_any_work(tmp_path):
    existing = tmp_path / "pad.vtu"
    existing.write_text("the user's file")
    assert_clean_error(run(*BATCH, "--out", existing), "--out", "pad.vtu", "is a file", "dataset folder")
    assert existing.read_text() == "the user's file"
    folder = tmp_path / "dir.npz"
    folder.mkdir()
    (folder / "keep.txt").write_text("x")
    result = run("simulate", "--indenter", "cone", "--out", folder, "--overwrite")
    assert_clean_error(result, "--out", "dir.npz", "is a folder", "give a file name inside it")
    assert (folder / "keep.txt").read_text() == "x"


def test_single_contact_npz_describes_itself(tmp_path, pad_sim):
    out = tmp_path / "one.npz"
    result = run("simulate", "--indenter", "flat_punch", "--theta", 10, "--depth", 0.5, "--model",
                 "linear", "--out", out)
    assert result.exit_code == 0, result.output
    with np.load(out) as d:
        assert d["depth"].dtype == np.float32 and d["depth_detail"].dtype == np.float32
        meta = json.loads(str(d["metadata"]))
    units = meta["units"]
    for key in ("depth", "depth_detail", "vertices", "rest_vertices", "pose.x_mm", "pose.depth_mm"):
        assert units[key] == "mm", key
    assert units["pose.theta_deg"] == "deg" and units["material.E_mpa"] == "MPa"
    assert units["force_n"] == "N" and units["pressure_kpa"] == "kPa"
    assert "resolved surface" in meta["depth"] and "intrusion" in meta["depth_detail"]
    assert meta["model"] == "linear" and meta["truth_mesh"]["fine_spacing_mm"] <= 0.27
    image = meta["image"]
    assert image["shape_px"] == [128, 128] and image["half_extent_mm"] == 17.5
    assert image["pixel_pitch_mm"] == pytest.approx(35 / 128)
    assert "row 0 = largest y" in image["pixel_centre"]
    assert meta["frame"].startswith("sensor")


def test_shards_describe_themselves_and_keep_their_arrays(tmp_path, pad_sim):
    from tactile_deploy.simulation.dataset import load_dataset
    from tactile_deploy.training.data import load_dataset_dir

    out = tmp_path / "ds"
    assert run(*BATCH, "--seed", 2, "--out", out).exit_code == 0
    with np.load(out / "shard_00000.npz") as d:
        dtypes = {k: d[k].dtype for k in d.files if k != "metadata"}
        meta = json.loads(str(d["metadata"]))
    assert dtypes["depth"] == np.float16 and dtypes["displacement"] == np.float16
    assert dtypes["force_n"] == np.float32 and dtypes["rest_vertices"] == np.float32
    assert dtypes["indenter_index"] == np.int16 and dtypes["contact_mask"] == bool
    assert meta["storage"]["precision"] == "float16"
    assert {k: meta["storage"]["dtypes"][k] for k in dtypes} == {k: str(v) for k, v in dtypes.items()}
    assert meta["mesh_hash"] == pad_sim.mesh.content_hash and meta["shard_index"] == 0
    assert meta["spec"]["seed"] == 2 and meta["spec"]["material"]["E_mpa"] == 0.3
    units = meta["units"]
    assert units["displacement"] == "mm" and units["force_n"] == "N" and units["theta_deg"] == "deg"
    assert units["spec.material.E_mpa"] == "MPa"
    assert meta["frame"].startswith("sensor") and "row 0 = largest y" in meta["image"]["pixel_centre"]
    assert meta["depth"] != meta["depth_detail"]
    card, paths = load_dataset(out)
    data = load_dataset_dir(out)  # the training reader still reads the shards
    assert len(paths) == 2 and data.depth_mm.shape == (4, 128, 128) and data.depth_mm.dtype == np.float32


def _interrupt_after(monkeypatch, n_calls, name):
    """Raise KeyboardInterrupt (as Ctrl-C does) at the ``n_calls``-th call of dataset.``name``."""
    from tactile_deploy.simulation import dataset

    real, calls = getattr(dataset, name), [0]

    def wrapper(*args, **kwargs):
        calls[0] += 1
        if calls[0] == n_calls:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(dataset, name, wrapper)


def test_ctrl_c_says_how_far_it_got_and_how_to_resume(tmp_path, pad_sim, monkeypatch):
    out = tmp_path / "ds"
    args = ("simulate", "--n", 6, "--shard-size", 2, "--indenters", "sphere_r4", "--workers", 1, "--out", out)
    with monkeypatch.context() as m:
        _interrupt_after(m, 2, "generate_shard")  # Ctrl-C while the second shard is simulated
        stopped = run(*args)
    assert stopped.exit_code == 130, stopped.output
    assert "interrupted; 1 of 3 shards done; rerun the same command to resume" in text(stopped)
    assert sorted(p.name for p in out.iterdir()) == ["dataset.json", "shard_00000.npz"]
    resumed = run(*args)
    assert resumed.exit_code == 0 and "wrote 2 shards" in text(resumed), resumed.output


@pytest.mark.timeout(180)  # forked workers: a stop that hangs fails here instead of stalling the suite
def test_ctrl_c_with_workers_stops_them_and_leaves_whole_shards(tmp_path, pad_sim, monkeypatch):
    out = tmp_path / "ds"
    args = ("simulate", "--n", 6, "--shard-size", 2, "--indenters", "sphere_r4", "--workers", 2, "--out", out)
    with monkeypatch.context() as m:
        _interrupt_after(m, 1, "write_json")  # Ctrl-C in the parent when the first shard is back
        stopped = run(*args)
    assert stopped.exit_code == 130, stopped.output
    match = re.search(r"interrupted; (\d) of 3 shards done; rerun the same command to resume", text(stopped))
    assert match, stopped.output
    shards = sorted(out.glob("shard_*.npz"))
    assert int(match.group(1)) == len(shards) >= 1
    assert [p.name for p in out.iterdir() if p.name.startswith(".")] == []  # no partial files
    resumed = run(*args)
    assert resumed.exit_code == 0, resumed.output
    assert card_of(out)["complete"] and len(card_of(out)["shards"]) == 3


def test_indenters_list_names_the_kind_option(tmp_path):
    assert_clean_error(run("indenters", "list", "--kind", "foo"), "--kind", "primitive, novel", "'foo'")


def test_pad_export_into_a_missing_folder_says_what_to_do(tmp_path):
    out = tmp_path / "missing" / "pad.vtu"
    assert_clean_error(run("pad", "export", "--out", out), "missing does not exist",
                       "create it first, or choose another --out")
    assert not out.parent.exists()
