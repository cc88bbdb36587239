"""Reading a JSON document from a file, with errors that name the file and the place; the text of
a pydantic validation error that names each bad field and the value it had; a JSON file read
through its format's model."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path


def read_json(path: str | os.PathLike, error: type[Exception], what: str = "a JSON document"):
    """The parsed JSON document at ``path`` (any JSON value; callers check its type).

    A file that is not UTF-8 text or not valid JSON raises ``error`` with the path and, for a
    syntax error, the line, column and reason: ``"{path}: not valid JSON (line 3, column 5:
    Expecting ',' delimiter)"``. ``what`` names the expected content in the first message.
    """
    path = Path(path)
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError:
        raise error(f"{path}: not a text file (expected {what})") from None
    except json.JSONDecodeError as e:
        raise error(f"{path}: not valid JSON (line {e.lineno}, column {e.colno}: {e.msg})") from None


def validation_error_text(source, err, what: str, hint: str = "") -> str:
    """``"{source}: invalid {what}:"`` and one line per problem of the pydantic ``err``: the
    field's place, the rule it breaks and the value it had (JSON scalars and lists as written,
    other values by their type), then ``hint`` on a line of its own when given."""
    lines = []
    for e in err.errors():
        loc = ".".join(str(p) for p in e["loc"]) or "(document)"
        got = e.get("input")
        if isinstance(got, float) and not math.isfinite(got):
            got_txt = str(got)
        elif isinstance(got, (int, float, str, bool, type(None), list)):
            got_txt = json.dumps(got)
        else:
            got_txt = type(got).__name__
        lines.append(f"  field '{loc}': {e['msg']} (got {got_txt})")
    return f"{source}: invalid {what}:\n" + "\n".join(lines) + (f"\n  ({hint})" if hint else "")


def read_model_json(path: str | os.PathLike, model, error: type[Exception], what: str,
                    hint: str = "", expected: str | None = None, missing: str | None = None):
    """The JSON file at ``path`` validated by the pydantic ``model`` (an instance of it).

    Each failure raises ``error``: a missing file (``missing``, or ``"{what} {path} not found"``),
    a file that is not JSON text (naming ``expected``, default ``what``), and a document the model
    refuses (:func:`validation_error_text`: each bad field and its value, then ``hint``).
    """
    from pydantic import ValidationError

    path = Path(path)
    if not path.is_file():
        raise error(missing or f"{what} {path} not found")
    doc = read_json(path, error, expected or what)
    try:
        return model.model_validate(doc)
    except ValidationError as e:
        raise error(validation_error_text(path, e, what, hint)) from None
