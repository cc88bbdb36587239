"""`tactile-deploy simulate`: every indenter, output format, bad input, datasets (seed, resume)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from tactile_deploy.camera.depth import DepthCamera
from tactile_deploy.cli.main import app
from tactile_deploy.fem.material import Material
from tactile_deploy.indenters import ContactPose, get_indenter, list_indenters
from tactile_deploy.simulation.contact import ContactError, simulate_contact
from tactile_deploy.simulation.contact_file import ContactFileError, contact_metadata, load_contact

runner = CliRunner()
MATERIAL = Material(nu=0.48)


def run(*args):
    return runner.invoke(app, [str(a) for a in args])


def test_single_contact_writes_the_documented_npz(tmp_path, pad_sim):
    out = tmp_path / "one.npz"
    result = run("simulate", "--indenter", "flat_punch", "--x", 2, "--y", -1, "--depth", 0.5,
                 "--model", "linear", "--out", out)
    assert result.exit_code == 0, result.output
    contact = load_contact(out)   # the format's reader checks the arrays and the metadata
    d, meta = contact.arrays, contact.metadata.model_dump(mode="json", exclude_none=True)
    assert d["depth"].shape == (128, 128) and d["depth"].dtype == np.float32
    assert d["vertices"].shape == (pad_sim.mesh.n_nodes, 3) and d["vertices"].dtype == np.float32
    np.testing.assert_allclose(d["rest_vertices"], pad_sim.mesh.vertices, atol=1e-6)
    with np.load(out) as z:   # the file holds what the reader returned, nothing more
        assert json.loads(str(z["metadata"])) == meta
    assert meta["mesh_hash"] == pad_sim.mesh.content_hash
    assert meta["pose"] == {"x_mm": 2.0, "y_mm": -1.0, "theta_deg": 0.0, "depth_mm": 0.5}
    # a flat punch pushes its whole face 0.5 mm in: the depth map is flat at 0.5 inside it
    depth = d["depth"]
    assert depth.max() == pytest.approx(0.5, abs=1e-4)
    assert float(d["force_n"]) > 0
    # the contact sits where the pose says (row 0 = largest y, x to the right)
    rows, cols = np.nonzero(depth > 0.45)
    x = -17.5 + (cols.mean() + 0.5) * 35 / 128
    y = 17.5 - (rows.mean() + 0.5) * 35 / 128
    assert x == pytest.approx(2.0, abs=0.3) and y == pytest.approx(-1.0, abs=0.3)
    assert np.abs(depth[:20]).max() < 0.01 * 0.5  # 13 mm away the gel has moved < 1 % of d
    assert meta["model"] == "linear" and meta["max_penetration_mm"] < 1e-5
    assert d["stick_mask"].shape == d["contact_mask"].shape and not d["stick_mask"].any()
    again = run("simulate", "--indenter", "flat_punch", "--depth", 0.5, "--out", out)
    assert again.exit_code != 0 and "--overwrite" in " ".join(again.output.split())
    # a file whose metadata breaks the format is refused, naming file, field, expected, actual
    bad = tmp_path / "bad.npz"
    for field, value, words in ((("pose", "depth_mm"), "deep", ("pose.depth_mm", '"deep"')),
                                (("n_nodes",), 7, ("'vertices'", "(7, 3)"))):
        doc = json.loads(json.dumps(meta))
        inner = doc
        for k in field[:-1]:
            inner = inner[k]
        inner[field[-1]] = value
        np.savez(bad, **{**d, "metadata": np.array(json.dumps(doc))})
        with pytest.raises(ContactFileError) as err:
            load_contact(bad)
        assert str(bad) in str(err.value) and all(w in str(err.value) for w in words), err.value


def test_a_slide_after_pressing_loads_the_gel_tangentially(tmp_path):
    """`simulate --slide-x`: the indenter, pressed, then moved along x (Coulomb, mu 0.5). The
    gel is dragged along +x by at most mu times the normal force, part of the contact slips
    (partial slip is checked against Cattaneo-Mindlin in tests/test_truth.py), and the record
    says how far the indenter slid."""
    out = tmp_path / "slide.npz"
    result = run("simulate", "--indenter", "sphere_r4", "--depth", 0.2, "--model", "linear",
                 "--friction", "coulomb", "--mu", 0.5, "--slide-x", 0.03, "--out", out)
    assert result.exit_code == 0, result.output
    assert "tangential force" in " ".join(result.output.split())
    contact = load_contact(out)
    d, meta = contact.arrays, contact.metadata
    assert meta.slide_mm == [0.03, 0.0] and meta.units["slide_mm"] == "mm"
    fx, fy = meta.tangential_force_n
    force = float(d["force_n"])
    print(f"normal {force:.4f} N, tangential ({fx:.4f}, {fy:.4f}) N, contact nodes "
          f"{int(d['contact_mask'].sum())}, sticking {int(d['stick_mask'].sum())}")
    assert 0.05 * 0.5 * force < fx <= 0.5 * force * (1 + 1e-6)
    assert abs(fy) < 0.02 * fx
    assert 0 < d["stick_mask"].sum() < d["contact_mask"].sum()


@pytest.mark.parametrize("name", list_indenters())
def test_every_library_indenter_simulates(name, pad_sim):
    indenter = get_indenter(name)
    pose = ContactPose(x_mm=1.0, y_mm=-1.0, theta_deg=15, depth_mm=1.0)
    s = simulate_contact(indenter, pose, MATERIAL)
    assert s.force_n > 0 and s.contact_mask.any()
    pixels, nodes = _deepest_intrusion_mm(indenter, pose, pad_sim)
    # The reference is the indenter's own shape: the exact depth map (mesh plus the indenter's
    # non-penetration floor) reaches its deepest intrusion at the pixel centres; the rendered
    # mesh is never deeper than its deepest contact node is pushed (a sharp tip between nodes
    # is held by the nodes around it), and the pixel centres, 0.27 mm apart on a 1 mm mesh, see
    # at least 3/4 of that node's depth (a cone's tip on a node: 0.82 of it).
    assert np.all(s.depth_detail_mm >= s.depth_mm - 1e-7)
    assert s.depth_detail_mm.max() == pytest.approx(pixels, abs=1e-3)
    assert 0.75 * nodes <= s.depth_mm.max() <= nodes + 1e-4


def test_every_shared_stl_simulates(shared_data, pad_sim):
    paths = sorted((shared_data / "indenters").glob("*.stl"))
    assert len(paths) == 16
    for path in paths:
        indenter = get_indenter(path)
        pose = ContactPose(x_mm=0, y_mm=0, theta_deg=0, depth_mm=0.8)
        s = simulate_contact(indenter, pose, MATERIAL)
        assert s.force_n > 0, path.name
        pixels, nodes = _deepest_intrusion_mm(indenter, pose, pad_sim)
        assert s.depth_detail_mm.max() == pytest.approx(pixels, abs=1e-3), path.name
        assert 0.75 * nodes <= s.depth_mm.max() <= nodes + 1e-4, path.name


def _deepest_intrusion_mm(indenter, pose, sim) -> tuple[float, float]:
    """The indenter's deepest intrusion below the rest surface at the depth map's pixel centres
    and at the pad's sensing nodes, mm (from its geometry alone)."""
    pixels = DepthCamera().pixel_centres_mm().reshape(-1, 2)
    nodes = sim.mesh.vertices[sim.mesh.sensing_nodes, :2]
    out = []
    for points in (pixels, nodes):
        intrusion = indenter.intrusion_mm(points, pose)
        out.append(float(np.max(intrusion[np.isfinite(intrusion)])))
    return out[0], out[1]


def test_depth_map_of_a_sphere_matches_its_shape_inside_the_contact(pad_sim):
    # Inside the contact the gel takes the sphere's shape: depth = d - (R - sqrt(R^2 - r^2)).
    R, d = 6.0, 0.8
    s = simulate_contact(get_indenter("analytic_sphere_r6"), ContactPose(x_mm=0, y_mm=0, theta_deg=0, depth_mm=d), MATERIAL)
    xy = np.stack(np.meshgrid(-17.5 + (np.arange(128) + 0.5) * 35 / 128, 17.5 - (np.arange(128) + 0.5) * 35 / 128), -1)
    r2 = (xy**2).sum(-1)
    inside = r2 < 1.5**2
    cap = d - (R - np.sqrt(R * R - r2[inside]))
    # Contact is linearised at the rest positions: a node that slides sideways by u carries the
    # sphere's depth at its rest position, an error of slope * u (slope r/R <= 0.25 here).
    slope_times_slide = 0.25 * 0.06
    assert np.abs(s.depth_detail_mm[inside] - cap).max() < slope_times_slide
    assert np.abs(s.depth_mm[inside] - cap).max() < 0.05  # piecewise-linear 1 mm mesh


def test_bad_input_gives_clear_errors(tmp_path):
    out = tmp_path / "x.npz"
    cases = [
        (("--indenter", "sphere_r4", "--x", 30, "--out", out), "off the pad"),
        (("--indenter", "sphere_r4", "--depth", 2.0, "--out", out), "outside (0, 1.5]"),
        (("--indenter", "no_such_shape", "--out", out), "unknown indenter"),
        (("--indenter", tmp_path / "missing.stl", "--out", out), "does not exist"),
        (("--indenter", "sphere_r4", "--out", tmp_path / "nofolder" / "x.npz"), "does not exist"),
        (("--indenter", "sphere_r4", "--nu", 0.5, "--out", out), "nu"),
        (("--indenter", "sphere_r4", "--friction", "sticky", "--out", out), "--friction"),
    ]
    broken = tmp_path / "broken.stl"
    broken.write_text("solid nothing\nendsolid nothing\n")
    cases.append((("--indenter", broken, "--out", out), "broken.stl"))
    for args, message in cases:
        result = run("simulate", *args)
        assert result.exit_code != 0, args
        assert message in " ".join(result.output.split()), (args, result.output)
    assert not out.exists()
    with pytest.raises(ContactError, match="does not reach"):
        simulate_contact(get_indenter("cone"), ContactPose(x_mm=0.31, y_mm=0.27, theta_deg=0, depth_mm=0.05), MATERIAL)


def test_dataset_is_reproducible_by_seed_and_resumable(tmp_path, pad_sim):
    args = ("simulate", "--n", 12, "--shard-size", 4, "--indenters", "sphere_r4,flat_punch,cross",
            "--seed", 7, "--workers", 1)
    a, b = tmp_path / "a", tmp_path / "b"
    assert run(*args, "--out", a).exit_code == 0
    assert run(*args, "--out", b).exit_code == 0
    shards = sorted(p.name for p in a.glob("shard_*.npz"))
    assert shards == ["shard_00000.npz", "shard_00001.npz", "shard_00002.npz"]
    for name in shards:
        with np.load(a / name) as da, np.load(b / name) as db:
            for key in da.files:
                np.testing.assert_array_equal(da[key], db[key])
    card = json.loads((a / "dataset.json").read_text())
    assert card["complete"] and sum(card["counts_per_indenter"].values()) == 12
    assert card["mesh_hash"] == pad_sim.mesh.content_hash
    # a killed run: one shard missing, one half-written; rerunning restores identical files
    reference = (a / "shard_00001.npz").read_bytes()
    (a / "shard_00001.npz").unlink()
    (a / "shard_00002.npz").write_bytes(b"truncated")
    assert run(*args, "--out", a).exit_code == 0
    assert (a / "shard_00001.npz").read_bytes() == reference
    with np.load(a / "shard_00002.npz") as d, np.load(b / "shard_00002.npz") as e:
        np.testing.assert_array_equal(d["displacement"], e["displacement"])
    # other parameters into the same folder are refused rather than mixed
    clash = run("simulate", "--n", 12, "--shard-size", 4, "--indenters", "sphere_r4", "--seed", 7,
                "--workers", 1, "--out", a)
    assert clash.exit_code != 0 and "different dataset" in " ".join(clash.output.split())


def test_float16_storage_is_float32_rounded_to_half_precision(tmp_path, pad_sim):
    # Same seed, two precisions: the half-precision shard holds exactly the float32 values rounded to
    # 11 significant bits, so its error is within half a unit in the last place (<= 2^-11 relative).
    common = ("simulate", "--n", 3, "--shard-size", 3, "--indenters", "sphere_r4,cross", "--seed", 3, "--workers", 1)
    assert run(*common, "--storage", "float32", "--out", tmp_path / "f32").exit_code == 0
    assert run(*common, "--out", tmp_path / "f16").exit_code == 0  # float16 is the default
    with np.load(tmp_path / "f32" / "shard_00000.npz") as a, np.load(tmp_path / "f16" / "shard_00000.npz") as b:
        for key in ("depth", "depth_detail", "displacement"):
            exact, half = a[key], b[key]
            assert exact.dtype == np.float32 and half.dtype == np.float16
            np.testing.assert_array_equal(half, exact.astype(np.float16))
            err = np.abs(half.astype(np.float32) - exact)
            assert np.all(err <= 2.0**-11 * np.abs(exact) + 2.0**-25), key  # half an ulp; + subnormal spacing
            assert err.max() <= 0.49e-3 and exact.max() > 0.1  # mm: < 0.5 um on a real contact
        np.testing.assert_array_equal(a["force_n"], b["force_n"])
    bad = run(*common, "--storage", "float8", "--out", tmp_path / "bad")
    assert bad.exit_code != 0 and "storage" in bad.output


def test_mesh_file_indenters_are_recorded_so_they_can_be_simulated_again(shared_data):
    import hashlib

    from tactile_deploy.simulation.contact import indenter_record

    path = sorted((shared_data / "indenters").glob("*.stl"))[0]
    ind = get_indenter(path, pressing_face="top")
    rec = indenter_record(ind)
    assert rec["indenter"] == str(path.resolve()) and rec["indenter_name"] == path.stem
    assert rec["indenter_sha256"] == hashlib.sha256(path.read_bytes()).hexdigest()
    again = get_indenter(rec["indenter"], pressing_face=rec["pressing_face"])
    assert again.content_hash == ind.content_hash
    # the format holds the record, and refuses a mesh-file record without its path or hash
    base = {**rec, "pose": {"depth_mm": 0.5}, "material": {}, "mesh_hash": "m", "n_nodes": 1,
            "units": {}, "frame": "sensor"}
    assert contact_metadata(base).indenter_sha256 == rec["indenter_sha256"]
    with pytest.raises(ContactFileError, match="absolute path"):
        contact_metadata({**base, "indenter": path.name})
    with pytest.raises(ContactFileError, match="indenter_sha256 missing"):
        contact_metadata({k: v for k, v in base.items() if k != "indenter_sha256"})
    assert indenter_record(get_indenter("sphere_r4")) == {"indenter": "sphere_r4", "indenter_kind": "primitive"}
