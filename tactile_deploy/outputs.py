"""Checks of a command's output paths, made before any work is done.

An output must not be one of the command's inputs (not even with ``--overwrite``), its folder
must exist, and an existing file is replaced only with ``--overwrite``.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path


class OutputPathError(ValueError):
    """An output path that cannot or must not be written (the message says what to do)."""


def same_file(a: str | os.PathLike, b: str | os.PathLike) -> bool:
    """True when the paths name the same file (after resolving links and relative parts)."""
    a, b = Path(a), Path(b)
    try:
        if a.exists() and b.exists():
            return os.path.samefile(a, b)
        return a.resolve() == b.resolve()
    except OSError:
        return False


def check_not_input(path: str | os.PathLike, option: str,
                    inputs: Iterable[str | os.PathLike | None]) -> None:
    """Raise :class:`OutputPathError` when ``path`` (given as ``option``) is one of ``inputs``."""
    for given in inputs:
        if given is not None and same_file(path, given):
            raise OutputPathError(f"{option} {path} is also an input of this command: choose "
                                  f"another {option} (an input is never replaced, even with "
                                  "--overwrite)")


def check_output_file(path: str | os.PathLike, option: str, *, overwrite: bool,
                      inputs: Iterable[str | os.PathLike | None] = (),
                      suffixes: tuple[str, ...] = ()) -> Path:
    """Check that the file ``path`` (given as ``option``) may be written; returns it as a Path.

    suffixes : allowed endings, lower case with the dot (empty: any). inputs : files the
    command reads. Raises :class:`OutputPathError` naming the option, the path and what to do.
    """
    path = Path(path)
    if path.name.startswith("-"):
        raise OutputPathError(f"{option} {path}: that looks like an option, not a file name; give "
                              f"the file name right after {option}")
    if suffixes and path.suffix.lower() not in suffixes:
        raise OutputPathError(f"{option} {path}: the file name must end in "
                              f"{' or '.join(suffixes)}, got "
                              f"{repr(path.suffix) if path.suffix else 'no suffix'}; choose "
                              f"another {option}")
    check_not_input(path, option, inputs)
    if path.is_dir():
        raise OutputPathError(f"{option} {path} is a folder: give a file name inside it")
    if not path.parent.is_dir():
        state = "is a file, not a folder" if path.parent.exists() else "does not exist"
        raise OutputPathError(f"{option} {path}: folder {path.parent} {state}: create it "
                              f"first, or choose another {option}")
    if path.exists() and not overwrite:
        raise OutputPathError(f"{path} exists: pass --overwrite to replace it, or choose another "
                              f"{option}")
    return path


def check_distinct(*outputs: tuple[str, str | os.PathLike | None]) -> None:
    """Raise :class:`OutputPathError` when two of the ``(option, path)`` outputs are one file."""
    given = [(option, path) for option, path in outputs if path is not None]
    for i, (option_a, a) in enumerate(given):
        for option_b, b in given[i + 1:]:
            if same_file(a, b):
                raise OutputPathError(f"{option_a} and {option_b} are both {a}: give them "
                                      "different files")
