"""What the wheel installs: only ``tactile_deploy`` as a top-level name, the runtime's shipped
plugins and models with the layout their relative paths expect, every package of calibration/
and training/ under ``tactile_deploy``; and what the install tells: ``--version``, the extra a
missing library belongs to, module references under their installed names.

The file list comes from setuptools' own ``build_py`` on setup.py's configuration (the files the
wheel is made of, without building it: fast). When ``TACTILE_DEPLOY_WHEEL`` names a built wheel
(``.ci/run`` builds one), the same checks run on the wheel's zip listing too.
"""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
import textwrap
import zipfile
from pathlib import Path, PurePosixPath

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _load(path: Path, name: str):
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def layout():
    return _load(ROOT / "setup.py", "tactile_deploy_setup")


def _tracked(folder: str) -> list[str]:
    out = subprocess.run(["git", "ls-files", "-z", "--", folder], cwd=ROOT, capture_output=True, check=True)
    return [name for name in out.stdout.decode().split("\0") if name]


@pytest.fixture(scope="module")
def wheel_files(layout) -> set[str]:
    """Paths (posix, relative to site-packages) of the files build_py puts into the wheel."""
    pytest.importorskip("setuptools")
    from setuptools.dist import Distribution

    cwd = os.getcwd()
    os.chdir(ROOT)  # package_dir is relative to the project root
    try:
        dist = Distribution({
            "name": "tactile-deploy", "script_name": "setup.py", "packages": layout.packages(),
            "package_dir": {**layout.MAPPED_PACKAGES, **layout.DATA_FOLDERS},
            "package_data": layout.package_data(), "include_package_data": False,
            "cmdclass": {"build_py": layout.BuildPy}})
        cmd = dist.get_command_obj("build_py")
        cmd.build_lib = "BUILD"
        cmd.ensure_finalized()
        return {PurePosixPath(path).relative_to("BUILD").as_posix() for path in cmd.get_output_mapping()}
    finally:
        os.chdir(cwd)


def _shipped_plugins() -> list[str]:
    return sorted(p.parent.name for p in (ROOT / "plugins").glob("*/plugin.json"))


def check_file_list(files: set[str]) -> None:
    """The checks every file list of the wheel must pass (a list of posix paths in site-packages,
    without the .dist-info folder)."""
    tops = {f.split("/")[0] for f in files}
    assert tops == {"tactile_deploy"}, f"top-level names besides tactile_deploy: {sorted(tops)}"
    # every plugin folder, whole (tracked files), at tactile_deploy/plugins/NAME
    plugins = _shipped_plugins()
    assert {"gelslim1", "gelslim2"} <= set(plugins)
    for name in plugins:
        want = {"tactile_deploy/" + f for f in _tracked(f"plugins/{name}")}
        assert want, name
        assert want <= files, f"plugin {name}: missing from the wheel: {sorted(want - files)[:5]}"
        # the files its manifest names (model, read-out, ...) are in the wheel where its relative paths point
        manifest = json.loads((ROOT / "plugins" / name / "plugin.json").read_text())
        for field, ref in manifest.items():
            if isinstance(ref, dict) and "sha256" in ref and "path" in ref:
                target = os.path.normpath(f"tactile_deploy/plugins/{name}/{ref['path']}")
                assert target in files, f"plugin {name}: {field} -> {target} is not in the wheel"
    # the runtime's models and cards, the adaptation step and the fp32 twin it starts from
    for name in ("gelslim_mesh.onnx", "gelslim_mesh.json", "gelslim_mesh.md", "gelslim_readout.onnx",
                 "gelslim_readout.json", "gelsight_mini_readout.onnx", "gelsight_mini_readout.json",
                 "gelsight_mini_readout.md", "digit_readout.onnx", "digit_readout.json", "digit_readout.md",
                 "gelslim_mesh_fp32.onnx", "gelslim_mesh_adapt/step.pt2", "gelslim_mesh_grip.onnx",
                 "gelslim_mesh_grip.json", "gelslim_mesh_grip.md",
                 "gelslim_mesh_adapt/filter.onnx", "gelslim_mesh_adapt/card.json"):
        assert f"tactile_deploy/exported/{name}" in files, name
    # not shipped: training bundles, figures, the scripts and configs that rebuild the plugins
    unwanted = [f for f in files if f.endswith(".pt") or "/figures/" in f or "build_shipped" in f
                or f.startswith("tactile_deploy/plugins/wizard/") or "__pycache__" in f
                or "/adapted/" in f]
    assert not unwanted, unwanted
    # every file of tactile_deploy/, calibration/ and training/ (code, schemas, pad assets,
    # configs), calibration/ and training/ under tactile_deploy
    for folder, into in (("tactile_deploy", ""), ("calibration", "tactile_deploy/"), ("training", "tactile_deploy/")):
        want = {into + f for f in _tracked(folder)}
        assert want <= files, f"{folder}/: missing from the wheel: {sorted(want - files)[:5]}"
    assert "tactile_deploy/assets/pads/gelslim_v1.npz" in files
    assert "tactile_deploy/runtime/run_record.schema.json" in files


def test_wheel_holds_only_tactile_deploy_and_the_shipped_plugins_and_models(wheel_files):
    check_file_list(wheel_files)


def test_the_file_list_check_fails_on_a_wrong_wheel(wheel_files):
    """The check above is not vacuous: a top-level ``calibration``, a missing model or a shipped
    training bundle each fail it."""
    bad_lists = [
        wheel_files | {"calibration/__init__.py"},
        wheel_files - {"tactile_deploy/exported/gelslim_mesh.onnx"},
        wheel_files - {"tactile_deploy/plugins/gelslim2/demo.avi"},
        wheel_files | {"tactile_deploy/exported/gelslim_mesh.pt"},
        wheel_files - {"tactile_deploy/training/networks/__init__.py"},
        wheel_files - {"tactile_deploy/training/configs/cpu_small.json"},
        wheel_files | {"tactile_deploy/plugins/gelslim2/adapted/v1/model.onnx"},
    ]
    for files in bad_lists:
        with pytest.raises(AssertionError):
            check_file_list(files)


@pytest.mark.skipif(not os.environ.get("TACTILE_DEPLOY_WHEEL"), reason="no built wheel given "
                    "(TACTILE_DEPLOY_WHEEL; .ci/run builds one)")
def test_built_wheel_zip():
    """The wheel .ci/run built: its zip listing passes the same checks, and its metadata names
    tactile_deploy as the only top-level package."""
    path = Path(os.environ["TACTILE_DEPLOY_WHEEL"])
    with zipfile.ZipFile(path) as zf:
        names = [n for n in zf.namelist() if not n.endswith("/")]
        info = [n for n in names if n.split("/")[0].endswith(".dist-info")]
        top_level = [n for n in info if n.endswith("top_level.txt")]
        if top_level:
            assert zf.read(top_level[0]).decode().split() == ["tactile_deploy"]
        entry_points = zf.read(next(n for n in info if n.endswith("entry_points.txt"))).decode()
    assert "tactile_deploy.calibration.cli:calibrate_app" in entry_points
    check_file_list({n for n in names if n not in info})


def test_module_references_use_the_installed_names():
    """No import, `python -m`, entry point or docstring reference names calibration or training
    by its folder (tools/rename_namespace.py --check)."""
    res = subprocess.run([sys.executable, str(ROOT / "tools" / "rename_namespace.py"), "--check"], cwd=ROOT,
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, "rewrite with python tools/rename_namespace.py:\n" + res.stdout[-3000:]


def test_rename_rewrites_module_references_only(tmp_path):
    """The rename on sample lines: imports, module paths, -m commands change; file names,
    attributes, plain words and already renamed names do not; a second run changes nothing."""
    tool = _load(ROOT / "tools" / "rename_namespace.py", "rename_namespace")
    rules = tool.rules(ROOT)
    before = textwrap.dedent("""\
        from @T.export import export_onnx
        import @C.rig
        from @C import formats
            >>> from @T import config
        python -m @T train --config training/configs/cpu_small.json
        [sys.executable, "-m", "@T", "train"]
        see :mod:`@C` and :class:`~@C.rig.stage.GCodeStage`
        rig = "@C.rig.cli:rig_app"
        docs/@C.md, plugin/@C/report.html, card["@T"], self.@T.data
        the @C. Then @T.
        from tactile_deploy.@T.export import export_onnx
        """).replace("@T", "training").replace("@C", "calibration")  # the rewrite would change literal samples
    after = textwrap.dedent("""\
        from tactile_deploy.training.export import export_onnx
        import tactile_deploy.calibration.rig
        from tactile_deploy.calibration import formats
            >>> from tactile_deploy.training import config
        python -m tactile_deploy.training train --config training/configs/cpu_small.json
        [sys.executable, "-m", "tactile_deploy.training", "train"]
        see :mod:`tactile_deploy.calibration` and :class:`~tactile_deploy.calibration.rig.stage.GCodeStage`
        rig = "tactile_deploy.calibration.rig.cli:rig_app"
        docs/calibration.md, plugin/calibration/report.html, card["training"], self.training.data
        the calibration. Then training.
        from tactile_deploy.training.export import export_onnx
        """)
    assert tool.rewrite(before, rules) == after
    assert tool.rewrite(after, rules) == after


def test_version_names_the_install_and_its_code():
    res = subprocess.run([sys.executable, "-m", "tactile_deploy.cli.main", "--version"], capture_output=True,
                         text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    from importlib.metadata import version

    from tactile_deploy.version import code_sha256

    first, second = res.stdout.splitlines()[:2]
    assert first == f"tactile-deploy {version('tactile-deploy')}"
    assert second.startswith(f"code sha256 {code_sha256()}")
    assert "onnxruntime" in res.stdout


def test_code_sha256_follows_the_runtime_sources(tmp_path):
    """The digest changes when a runtime source changes and not when calibration/training does
    (in a copy of the package)."""
    import shutil

    from tactile_deploy.version import code_sha256

    pkg = tmp_path / "tactile_deploy"
    shutil.copytree(ROOT / "tactile_deploy", pkg, ignore=shutil.ignore_patterns("__pycache__", "assets"))
    shutil.copytree(ROOT / "training", pkg / "training", ignore=shutil.ignore_patterns("__pycache__"))
    code = ("import sys; sys.path.insert(0, {!r}); import tactile_deploy.version as v; "
            "assert v.package_root().parent == __import__('pathlib').Path({!r}); print(v.code_sha256())")
    digest = lambda: subprocess.run([sys.executable, "-c", code.format(str(tmp_path), str(tmp_path))],  # noqa: E731
                                    capture_output=True, text=True, cwd=tmp_path, timeout=120, check=True).stdout.strip()
    first = digest()
    assert first == code_sha256()  # the copy is the same code as the install
    (pkg / "training" / "config.py").write_text("# changed\n")
    assert digest() == first
    (pkg / "runtime" / "run.py").write_text((pkg / "runtime" / "run.py").read_text() + "\n# changed\n")
    assert digest() != first


def test_missing_extra_names_the_pip_install():
    """A command needing a library of an extra that is not installed ends with the pip install
    that brings it (exit 2); an unknown missing module stays a traceback (a defect)."""
    from tactile_deploy.cli.main import missing_extra_message

    exc = ModuleNotFoundError("No module named 'matplotlib.pyplot'", name="matplotlib.pyplot")
    assert missing_extra_message(exc).endswith("pip install 'tactile-deploy[figures]'")
    assert missing_extra_message(ModuleNotFoundError("x", name="numpy_typo")) is None
    code = textwrap.dedent("""
        import importlib.abc, sys
        class Block(importlib.abc.MetaPathFinder):
            def find_spec(self, name, path=None, target=None):
                if name.split(".")[0] in ("matplotlib", "numpy_typo"):
                    raise ModuleNotFoundError(f"No module named {name!r}", name=name)
        sys.meta_path.insert(0, Block())
        from tactile_deploy.cli.main import app, main

        @app.command("needs")
        def needs(module: str):
            __import__(module)

        sys.argv = ["tactile-deploy", "needs", sys.argv[1]]
        main()
    """)
    res = subprocess.run([sys.executable, "-c", code, "matplotlib.pyplot"], capture_output=True, text=True, timeout=300)
    assert res.returncode == 2, res.stdout[-2000:] + res.stderr[-2000:]
    assert "needs matplotlib, which is not installed" in res.stderr
    assert "pip install 'tactile-deploy[figures]'" in res.stderr
    res = subprocess.run([sys.executable, "-c", code, "numpy_typo"], capture_output=True, text=True, timeout=300)
    assert res.returncode == 1 and "Traceback" in res.stderr, res.stderr[-2000:]


def test_run_json_records_the_tool_model_and_plugin(tmp_path):
    """run.json names what made the meshes: the installed version and code digest, the model
    file with its sha256 (the plugin's own model, then its adapted version 1), the plugin with
    its manifest's sha256; each digest recomputed here from the files."""
    import hashlib
    from importlib.metadata import version

    import numpy as np
    from test_runtime_support import build_test_plugin

    from tactile_deploy.runtime.plugins import SensorPlugin
    from tactile_deploy.runtime.plugins.versions import add_version, staging_folder
    from tactile_deploy.runtime.predictor import MeshPredictor
    from tactile_deploy.runtime.run import Runner, RunOptions, prepare_out_dir
    from tactile_deploy.runtime.run_record import RunRecord
    from tactile_deploy.runtime.sources.base import ArrayPlayback
    from tactile_deploy.runtime.sources.npz import load_clip
    from tactile_deploy.version import code_sha256

    def sha256(path) -> str:
        return hashlib.sha256(Path(path).read_bytes()).hexdigest()

    def plugin_metadata(plugin) -> dict:
        onnx = pytest.importorskip("onnx")
        graph = onnx.load(str(plugin.verified_path("model")), load_external_data=False)
        return {p.key: p.value for p in graph.metadata_props}

    folder = tmp_path / "testsensor"
    plugin = build_test_plugin(folder, n_frames=3)
    frames, _, _ = load_clip(plugin.demo_clip_path())

    def run(name: str) -> dict:
        loaded = SensorPlugin.load(str(folder))
        out = prepare_out_dir(tmp_path / name)
        source = ArrayPlayback(list(frames), np.arange(len(frames)) * 33_000_000, "clip")
        Runner(MeshPredictor.from_plugin(loaded), source, RunOptions(out_dir=out)).run()
        doc = json.loads((out / "run.json").read_text())
        RunRecord.model_validate(doc)
        return doc

    own = run("own")
    tool = own["tool"]
    assert (tool["name"], tool["version"], tool["code_sha256"]) == ("tactile-deploy", version("tactile-deploy"),
                                                                    code_sha256())
    assert tool["libraries"]["onnxruntime"] == version("onnxruntime")
    model = own["model"]
    assert model["adapted_version"] is None
    assert model["format"] == plugin_metadata(plugin)["format"] and model["format"].startswith("tactile-deploy.")
    assert Path(model["path"]) == plugin.verified_path("model").resolve()
    assert model["sha256"] == sha256(model["path"]) == plugin.manifest.model.sha256
    assert own["plugin"] == {"name": "testsensor", "folder": str(folder.resolve()), "origin": plugin.origin,
                             "format_version": plugin.manifest.format_version,
                             "manifest_sha256": sha256(folder / "plugin.json")}

    # an adapted version: a different file (same graph, another doc string) becomes the model
    onnx = pytest.importorskip("onnx")
    staging = staging_folder(plugin)
    graph = onnx.load(str(model["path"]))
    graph.doc_string = "adapted"
    onnx.save(graph, str(staging / "model.onnx"))
    add_version(plugin, staging, {"created": "2026-01-01T00:00:00", "heldout_rmse_before_mm": 0.02,
                                  "heldout_rmse_after_mm": 0.01, "summary": "test"})
    adapted = run("adapted")["model"]
    assert adapted["adapted_version"] == 1
    assert Path(adapted["path"]) == (folder / "adapted" / "v1" / "model.onnx").resolve()
    assert adapted["sha256"] == sha256(adapted["path"]) != model["sha256"]

    # meshes made without a model file (a lift of the depth map through the pad's FEM): model
    # null, the tool and the plugin recorded all the same
    from types import SimpleNamespace

    from tactile_deploy.runtime.provenance import run_provenance

    lift = run_provenance(SimpleNamespace(model_path=Path("physics lift of pad gelslim_v1"), plugin=plugin))
    assert lift["model"] is None and lift["plugin"] == own["plugin"] and lift["tool"] == own["tool"]
    RunRecord.model_validate({**own, **lift})


def test_model_record_reads_the_training_commit_from_the_metadata(tmp_path):
    from tactile_deploy.runtime.provenance import model_record

    path = tmp_path / "m.onnx"
    path.write_bytes(b"not a graph: only its sha256 is read")
    rec = model_record(path, metadata={"format": "tactile-deploy.predictor/1", "training_commit": "9aa5d54",
                                       "training_dirty": "true"})
    assert (rec.format, rec.training_commit, rec.adapted_version) == ("tactile-deploy.predictor/1",
                                                                      "9aa5d54 (dirty)", None)
    assert model_record(path).format is None and model_record(path).training_commit is None


def test_adapt_refuses_a_plugin_inside_the_installed_package(monkeypatch, tmp_path, capsys):
    """Adapted versions are written into the plugin's folder: `adapt` refuses a shipped plugin
    of a wheel install (lost at the next upgrade) with the command that copies it, and accepts
    the same plugin in a source checkout and a copied plugin."""
    from types import SimpleNamespace

    import typer

    import tactile_deploy.shipped as shipped
    from tactile_deploy.cli.adapt import _refuse_installed_plugin

    folder = tmp_path / "site-packages" / "tactile_deploy" / "plugins" / "gelslim2"
    folder.mkdir(parents=True)
    monkeypatch.setattr(shipped, "plugins_dir", lambda: folder.parent)
    monkeypatch.setattr(shipped, "installed", lambda: True)
    with pytest.raises(typer.Exit) as exc:
        _refuse_installed_plugin(SimpleNamespace(name="gelslim2", origin="shipped", folder=folder))
    assert exc.value.exit_code == 2
    assert "tactile-deploy plugins copy gelslim2 ./gelslim2" in " ".join(capsys.readouterr().err.split())
    _refuse_installed_plugin(SimpleNamespace(name="gelslim2", origin="path", folder=tmp_path / "gelslim2"))
    monkeypatch.setattr(shipped, "installed", lambda: False)
    _refuse_installed_plugin(SimpleNamespace(name="gelslim2", origin="shipped", folder=folder))


def test_the_extra_named_for_each_library_installs_it():
    """Each library the missing-extra message knows is brought by the extra it names (its
    distribution among the extra's requirements, with the extras it includes), and by no base
    dependency (else a missing one is a broken install, not an install choice)."""
    import re
    import tomllib
    from importlib.metadata import packages_distributions

    from tactile_deploy.cli.main import EXTRA_OF

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    extras = project["optional-dependencies"]

    def names(requirements) -> set[str]:
        return {re.split(r"[<>=!~\[; ]", r, maxsplit=1)[0].lower().replace("_", "-") for r in requirements}

    def closure(extra: str) -> set[str]:
        out = set()
        for req in extras[extra]:
            included = re.fullmatch(r"tactile-deploy\[(.+)\]", req)
            out |= set().union(*(closure(e) for e in included.group(1).split(","))) if included else names([req])
        return out

    base = names(project["dependencies"])
    providers = packages_distributions()
    for module, extra in EXTRA_OF.items():
        dists = {d.lower().replace("_", "-") for d in providers.get(module, [])}
        assert dists, f"{module}: not installed here (the dev extra installs every extra)"
        assert dists & closure(extra), f"{module} ({dists}) is not in the extra {extra!r}: {sorted(closure(extra))}"
        assert not dists & base, f"{module} ({dists}) is a base dependency, not an extra's"
