#!/usr/bin/env python3
"""``lint-imports`` on the installed layout: the contracts of pyproject.toml checked on a copy of
the Python sources laid out as the wheel installs them (``calibration/`` as
``tactile_deploy/calibration``, ``training/`` as ``tactile_deploy/training``; setup.py says where
each folder goes), because import-linter reads packages from one folder each. Usage, from any
folder::

    python tools/lint_imports.py        # prints lint-imports' report; exit status 0 when all contracts are kept
"""

from __future__ import annotations

import importlib.util
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def layout() -> dict[str, str]:
    """Installed package path (``tactile_deploy/calibration``) -> source folder, from setup.py."""
    spec = importlib.util.spec_from_file_location("_tactile_deploy_setup", ROOT / "setup.py")
    setup = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(setup)
    out = {"tactile_deploy": "tactile_deploy", "bench": "bench"}
    out.update({name.replace(".", "/"): folder for name, folder in setup.MAPPED_PACKAGES.items()})
    return out


def mirror(dest: Path) -> None:
    """Copy every ``.py`` file of the source folders to where the wheel installs it."""
    for target, folder in layout().items():
        for src in (ROOT / folder).rglob("*.py"):
            if "__pycache__" in src.parts:
                continue
            out = dest / target / src.relative_to(ROOT / folder)
            out.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(src, out)


def lint(folder: Path, contract: str | None = None, **run_options) -> subprocess.CompletedProcess:
    """lint-imports with pyproject.toml's contracts (or only the one of id ``contract``) on the
    mirror in ``folder``."""
    env = {**os.environ, "PYTHONPATH": str(folder)}
    code = "import sys; from importlinter.cli import lint_imports_command; sys.exit(lint_imports_command())"
    only = ["--contract", contract] if contract else []
    return subprocess.run([sys.executable, "-c", code, str(ROOT / "pyproject.toml"), "--no-cache", *only],
                          cwd=folder, env=env, **run_options)


def main() -> int:
    with tempfile.TemporaryDirectory(prefix="tactile-deploy-lint-") as tmp:
        mirror(Path(tmp))
        return lint(Path(tmp)).returncode


if __name__ == "__main__":
    sys.exit(main())
