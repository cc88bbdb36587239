"""Reading a JSON document from a file, with errors that name the file and the place."""

from __future__ import annotations

import json
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
