#!/usr/bin/env python3
"""Rewrite references to the packages ``calibration`` and ``training`` as
``tactile_deploy.calibration`` and ``tactile_deploy.training`` in every text file of a checkout.

The folders ``calibration/`` and ``training/`` stay where they are; the build maps them into the
``tactile_deploy`` namespace, so every import, ``python -m`` command, entry point, docstring
reference and import-linter contract names them by their installed names. Usage, from the root
of a checkout (tracked and untracked, not ignored, files are rewritten in place)::

    python3 tools/rename_namespace.py            # rewrite, print the files changed
    python3 tools/rename_namespace.py --check    # exit 1 and list the files that still need it

What is rewritten (nothing else):

* import statements: ``from training.export import x``, ``import calibration.rig``,
  ``from calibration import formats`` (also after ``>>>`` in docstrings and in Markdown);
* dotted module paths ``calibration.X...`` / ``training.X...`` where ``X`` is a real module or
  sub-package of that folder in this checkout (so ``calibration.md``, ``report.calibration.x``
  or a variable named ``training`` with an attribute are left alone): docstrings, entry points,
  ``:mod:`` roles, monkeypatch targets, subprocess arguments;
* ``python -m training`` / ``python -m calibration`` and ``[..., "-m", "training", ...]``;
* ``:mod:`training``` / ``:mod:`calibration```.

The rewrite is idempotent: a second run changes nothing.
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
from pathlib import Path

PACKAGES = ("calibration", "training")
NAMESPACE = "tactile_deploy"
TEXT_SUFFIXES = {".py", ".md", ".toml", ".json", ".txt", ".cfg", ".ini", ".yaml", ".yml", ".sh",
                 ".rst", ".html", ".pyi"}
TEXT_NAMES = {"run"}  # .ci/run


def submodules(root: Path, package: str) -> set[str]:
    """Names of the modules and sub-packages directly inside ``root/package``."""
    folder = root / package
    names = {p.stem for p in folder.glob("*.py")}
    names |= {p.parent.name for p in folder.glob("*/__init__.py")}
    names.discard("__init__")
    return names


def rules(root: Path) -> list[tuple[re.Pattern, str]]:
    out = []
    for pkg in PACKAGES:
        subs = sorted(submodules(root, pkg), key=len, reverse=True)
        if not subs:
            raise SystemExit(f"{root / pkg}: no modules found; run this from the checkout's root")
        alt = "|".join(map(re.escape, subs))
        # import statements (line start, optional docstring prompt)
        out.append((re.compile(rf"^([ \t]*(?:>>>[ \t]*|\.\.\.[ \t]*)?(?:from|import)[ \t]+){pkg}(?=[ \t.,]|$)",
                               re.M), rf"\g<1>{NAMESPACE}.{pkg}"))
        # `import a, training.x` continuation is not used in this code base; dotted module paths:
        out.append((re.compile(rf"(?<![\w.\-/\\]){pkg}(?=\.(?:{alt})\b)"), f"{NAMESPACE}.{pkg}"))
        # python -m training (bare; the dotted form is handled above)
        out.append((re.compile(rf"(?<=-m ){pkg}(?=[\s`\"')\]]|$)", re.M), f"{NAMESPACE}.{pkg}"))
        # subprocess argument lists: "-m", "training"
        out.append((re.compile(rf"""((["'])-m\2,\s*(["'])){pkg}(?=\3)"""), rf"\g<1>{NAMESPACE}.{pkg}"))
        # :mod:`training`
        out.append((re.compile(rf"(:mod:`~?){pkg}(?=`)"), rf"\g<1>{NAMESPACE}.{pkg}"))
    return out


def candidate_files(root: Path) -> list[Path]:
    names = subprocess.run(["git", "ls-files", "-co", "--exclude-standard", "-z"], cwd=root,
                           capture_output=True, check=True).stdout.decode().split("\0")
    me = Path(__file__).resolve()
    files = []
    for name in filter(None, names):
        path = root / name
        if not path.is_file() or path.is_symlink() or path.resolve() == me:
            continue
        if path.suffix in TEXT_SUFFIXES or path.name in TEXT_NAMES:
            files.append(path)
    return files


def rewrite(text: str, compiled: list[tuple[re.Pattern, str]]) -> str:
    for pattern, repl in compiled:
        text = pattern.sub(repl, text)
    return text


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="change nothing; exit 1 when a file needs the rewrite")
    args = ap.parse_args(argv)
    root = Path(subprocess.run(["git", "rev-parse", "--show-toplevel"], capture_output=True, text=True,
                               check=True).stdout.strip())
    compiled = rules(root)
    changed = []
    for path in candidate_files(root):
        try:
            raw = path.read_bytes()
            text = raw.decode("utf-8")
        except (OSError, UnicodeDecodeError):
            continue
        new = rewrite(text, compiled)
        if new != text:
            changed.append(path.relative_to(root))
            if not args.check:
                path.write_bytes(new.encode("utf-8"))
    for name in changed:
        print(name)
    if args.check:
        return 1 if changed else 0
    print(f"{len(changed)} files rewritten", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
