"""The one base of every file format tactile-deploy reads or writes, and its JSON Schema.

Every JSON file (and JSON header inside an ``.npz``) is a pydantic model on :class:`StrictModel`:
unknown fields are refused, NaN and infinity are refused, and a loaded document is frozen. Each
format is listed, with the path of its committed JSON Schema, in the ``formats`` module of its
package (:mod:`tactile_deploy.formats`, ``tactile_deploy.calibration.formats``, ``tactile_deploy.training.formats``);
``python -m tactile_deploy.formats`` (and the others) rewrite the schemas, and one test fails
when a committed schema differs from its model's.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

from pydantic import BaseModel, ConfigDict

from tactile_deploy.atomic import write_text

#: The configuration every format shares.
STRICT = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class StrictModel(BaseModel):
    """Base of the file formats: unknown fields, NaN and infinity refused; frozen."""

    model_config = STRICT


@dataclass(frozen=True)
class Format:
    """A file format: its model and where its JSON Schema is committed."""

    name: str
    model: type[BaseModel]
    schema_path: Path

    def schema_text(self) -> str:
        """The schema as committed: 2-space indented JSON with a trailing newline."""
        return schema_text(self.model)


def schema_text(model: type[BaseModel]) -> str:
    """JSON Schema of ``model`` (field descriptions included), 2-space indented, newline-ended."""
    return json.dumps(model.model_json_schema(), indent=2) + "\n"


def write_schemas(formats: dict[str, Format], check: bool = False) -> list[Path]:
    """Write the schema of every format (``check``: write nothing); returns the paths whose
    committed schema differed from the model's."""
    stale = []
    for fmt in formats.values():
        text = fmt.schema_text()
        path = Path(fmt.schema_path)
        if not path.is_file() or path.read_text(encoding="utf-8") != text:
            stale.append(path)
            if not check:
                write_text(path, text)
    return stale


def schemas_main(formats: dict[str, Format], argv=None) -> int:
    """``python -m <package>.formats [--check]``: rewrite (or check) the committed schemas."""
    import argparse

    ap = argparse.ArgumentParser(description="Rewrite the committed JSON Schemas of the file "
                                 "formats from their models.")
    ap.add_argument("--check", action="store_true", help="only report stale schemas (exit 1)")
    args = ap.parse_args(argv)
    stale = write_schemas(formats, check=args.check)
    for path in stale:
        print(f"{'stale' if args.check else 'wrote'} {os.path.relpath(path)}")
    return 1 if (args.check and stale) else 0


def read_npz_arrays(path: str | os.PathLike, error: type[Exception]) -> dict:
    """Every array of the ``.npz`` file at ``path``, by name (no pickled objects); a file that
    is missing or not an ``.npz`` raises ``error`` naming it."""
    import numpy as np

    try:
        with np.load(Path(path), allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except (OSError, ValueError) as e:
        raise error(f"{path}: not a readable .npz file ({e})") from None
