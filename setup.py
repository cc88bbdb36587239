"""Where every installed file of tactile-deploy comes from (metadata and dependencies: pyproject.toml).

Every import name lives under ``tactile_deploy``; the source folders stay where they are:

    source folder      installed as                   what
    tactile_deploy/    tactile_deploy                 the runtime and the shared physics
    calibration/       tactile_deploy.calibration     the calibration wizard, fits, rig, discrepancy
    training/          tactile_deploy.training        data, networks, training, export
    plugins/           tactile_deploy/plugins/        the shipped sensor plugins (data only)
    exported/          tactile_deploy/exported/       the shipped models and their cards (data only)

``plugins/`` and ``exported/`` become folders of the installed package with the same relative
layout as in a source checkout (a plugin's ``../../exported/gelslim_mesh.onnx`` resolves in
both); :mod:`tactile_deploy.shipped` finds them. Shipped is what the runtime and ``adapt`` read:
each plugin folder whole, and from ``exported/`` the ONNX graphs, their cards and the adaptation
steps (``*_adapt/``); not the training bundles (``*.pt``), the figures or the wizard configs that
rebuild the plugins (docs/packaging.md says why). ``tests/test_packaging.py`` checks the list.
"""

from __future__ import annotations

from pathlib import Path

from setuptools import find_packages, setup
from setuptools.command.build_py import build_py

ROOT = Path(__file__).resolve().parent

#: Source folders mapped into the namespace (import name -> folder).
MAPPED_PACKAGES = {
    "tactile_deploy.calibration": "calibration",
    "tactile_deploy.training": "training",
}
#: Data-only folders installed inside the package (name -> folder); their Python files (the
#: script that rebuilds the shipped plugins) are not installed.
DATA_FOLDERS = {
    "tactile_deploy.plugins": "plugins",
    "tactile_deploy.exported": "exported",
}
#: Data files of the runtime's models, by pattern (the training bundles ``*.pt`` and the figures
#: are left out: nothing that runs from an install reads them).
MODEL_FILES = ["*.onnx", "*.json", "*.md", "*_adapt/*"]
#: Never installed: byte code, editor and merge leftovers.
SKIPPED_SUFFIXES = (".py", ".pyc", ".pyo", "~", ".orig", ".rej", ".swp")
#: Not installed with a plugin: the versions `tactile-deploy adapt` made in a checkout.
PLUGIN_ADAPTED = "adapted/"


def _data_files_below(folder: Path, into_packages: bool = False) -> list[str]:
    """Every data file below ``folder`` (relative posix paths), without those of sub-folders that
    are packages themselves (they list their own) unless ``into_packages``, nor the skipped ones."""
    out = []
    for path in sorted(folder.rglob("*")):
        rel = path.relative_to(folder)
        parents = [folder.joinpath(*rel.parts[:i]) for i in range(1, len(rel.parts))]
        if (not path.is_file() or path.name.startswith(".") or path.name.endswith(SKIPPED_SUFFIXES)
                or "__pycache__" in rel.parts
                or (not into_packages and any((p / "__init__.py").is_file() for p in parents))):
            continue
        out.append(rel.as_posix())
    return out


def packages() -> list[str]:
    found = find_packages(str(ROOT), include=["tactile_deploy", "tactile_deploy.*"])
    for name, folder in MAPPED_PACKAGES.items():
        found += [name] + [f"{name}.{sub}" for sub in find_packages(str(ROOT / folder))]
    return found + list(DATA_FOLDERS)


def package_folder(name: str) -> Path:
    """Source folder of the package ``name`` (as installed)."""
    for prefix, folder in {**MAPPED_PACKAGES, **DATA_FOLDERS}.items():
        if name == prefix or name.startswith(prefix + "."):
            return ROOT / folder / name[len(prefix):].lstrip(".").replace(".", "/")
    return ROOT / name.replace(".", "/")


def package_data() -> dict[str, list[str]]:
    """Package -> its data files: every non-Python file of each package's folder (schemas, pad
    assets, configs); of ``plugins/`` each plugin folder (one with a plugin.json, not
    ``plugins/wizard/``) whole but its adapted versions; of ``exported/`` :data:`MODEL_FILES`."""
    data = {name: _data_files_below(package_folder(name)) for name in packages() if name not in DATA_FOLDERS}
    data["tactile_deploy.plugins"] = [f"{manifest.parent.name}/{rel}"
                                      for manifest in sorted((ROOT / "plugins").glob("*/plugin.json"))
                                      for rel in _data_files_below(manifest.parent, into_packages=True)
                                      if not rel.startswith(PLUGIN_ADAPTED)]
    data["tactile_deploy.exported"] = list(MODEL_FILES)
    return {name: files for name, files in data.items() if files}


class BuildPy(build_py):
    """Installs no Python module from the data-only folders."""

    def find_package_modules(self, package, package_dir):
        if package in DATA_FOLDERS:
            return []
        return super().find_package_modules(package, package_dir)


if __name__ == "__main__":  # as the build runs it; tests and tools/ import the layout above
    setup(
        packages=packages(),
        package_dir={**MAPPED_PACKAGES, **DATA_FOLDERS},
        package_data=package_data(),
        include_package_data=False,
        cmdclass={"build_py": BuildPy},
    )
