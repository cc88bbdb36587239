"""The package edges hold: the import contracts of pyproject.toml (layers, no import loops, a
runtime without torch or warp, only the wizard importing its UI steps), checked on the installed
layout; the runtime imports and turns a frame into a mesh with torch and warp made unimportable;
calibration/ and training/ import under one name only."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: Made unimportable in the subprocesses below: what the runtime must not need.
BLOCK = textwrap.dedent("""
    import importlib.abc, sys

    class _Blocked(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name.split(".")[0] in ("torch", "warp"):
                raise ImportError(f"{name} is blocked: the runtime must run without it")
            return None

    sys.meta_path.insert(0, _Blocked())
""")


def _python(code: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", BLOCK + textwrap.dedent(code)], cwd=ROOT,
                          capture_output=True, text=True, timeout=timeout)


def _lint_tool():
    spec = importlib.util.spec_from_file_location("lint_imports", ROOT / "tools" / "lint_imports.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _n_contracts() -> int:
    import tomllib

    return len(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"])


@pytest.fixture(scope="module")
def lint_tool():
    pytest.importorskip("importlinter", reason="import-linter is in the dev extra")
    return _lint_tool()


def test_import_contracts_hold(lint_tool, tmp_path):
    """`python tools/lint_imports.py`: the contracts in pyproject.toml on the installed layout."""
    lint_tool.mirror(tmp_path)
    res = lint_tool.lint(tmp_path, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stdout[-4000:] + res.stderr[-2000:]
    assert f"{_n_contracts()} kept, 0 broken" in res.stdout, res.stdout[-2000:]


@pytest.mark.parametrize("module, line, contract", [
    ("tactile_deploy/shipped.py", "import tactile_deploy.training.config", "package-layers"),
    ("tactile_deploy/calibration/formats.py", "import tactile_deploy.training.formats", "package-layers"),
    ("tactile_deploy/runtime/run_record.py", "import torch", "runtime-without-torch"),
])
def test_import_contracts_catch_a_forbidden_import(lint_tool, tmp_path, module, line, contract):
    """The contract fails when the runtime imports training, calibration imports training, or
    the runtime imports torch (in a copy of the sources), and holds without that line."""
    lint_tool.mirror(tmp_path)
    kept = lint_tool.lint(tmp_path, contract, capture_output=True, text=True, timeout=300)
    assert kept.returncode == 0 and "1 kept, 0 broken" in kept.stdout, kept.stdout[-3000:]
    path = tmp_path / module
    path.write_text(path.read_text() + "\n" + line + "\n")
    res = lint_tool.lint(tmp_path, contract, capture_output=True, text=True, timeout=300)
    assert res.returncode != 0 and "0 kept, 1 broken" in res.stdout, res.stdout[-3000:]


@pytest.mark.parametrize("folder", ["calibration", "training"])
def test_a_mapped_folder_imports_under_its_installed_name_only(folder):
    """From the repository root (on sys.path, as for pytest and `python -m`), the folder is
    tactile_deploy.<folder>; importing it by the folder's own name fails with the name to use
    instead of loading a second copy of its modules."""
    res = subprocess.run([sys.executable, "-c", textwrap.dedent(f"""
        import sys
        sys.path.insert(0, {str(ROOT)!r})
        import tactile_deploy.{folder} as pkg
        assert pkg.__file__ == {str(ROOT / folder / "__init__.py")!r}, pkg.__file__
        try:
            import {folder}
        except ImportError as e:
            print(e)
        else:
            raise SystemExit("imported twice")
        assert [k for k in sys.modules if k.split(".")[0] == {folder!r}] == []
    """)], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    assert f"import it by that name" in res.stdout and f"tactile_deploy.{folder}" in res.stdout


def test_blocking_works():
    """The blocker itself: importing torch fails in the subprocess (else the tests below prove
    nothing)."""
    res = _python("import torch")
    assert res.returncode != 0 and "torch is blocked" in res.stderr


def test_every_runtime_module_imports_without_torch_or_warp():
    """Every module of tactile_deploy but the torch-only ``learning`` package and the optional
    warp.fem assembly imports with torch and warp unimportable."""
    res = _python("""
        import importlib, pkgutil, tactile_deploy
        optional = ("tactile_deploy.learning", "tactile_deploy.fem.elasticity_warp",
                    "tactile_deploy.calibration", "tactile_deploy.training")
        names = [m.name for m in pkgutil.walk_packages(tactile_deploy.__path__, "tactile_deploy.")
                 if not m.name.startswith(optional) and not m.name.endswith("__main__")]
        for name in names:
            importlib.import_module(name)
        assert "torch" not in sys.modules and "warp" not in sys.modules
        print(len(names), "modules")
    """)
    assert res.returncode == 0, res.stderr[-3000:]
    assert int(res.stdout.split()[0]) > 100


def test_shipped_plugin_turns_a_frame_into_a_mesh_without_torch_or_warp():
    """The main job's path: the shipped plugin's predictor on its demo clip's first frame."""
    res = _python("""
        import numpy as np
        from tactile_deploy.runtime import MeshPredictor
        from tactile_deploy.runtime.sources.factory import open_clip

        predictor = MeshPredictor.from_plugin("gelslim2", warmup=0)
        with open_clip(predictor.plugin.demo_clip_path()) as clip:
            frame = clip.read()
        pred = predictor.predict_frame(frame.image)
        assert pred.vertices_mm.shape == (predictor.n_nodes, 3), pred.vertices_mm.shape
        assert np.all(np.isfinite(pred.vertices_mm))
        assert "torch" not in sys.modules and "warp" not in sys.modules
        print("ok", predictor.n_nodes)
    """)
    assert res.returncode == 0, res.stderr[-3000:]
    assert res.stdout.startswith("ok 5380")
