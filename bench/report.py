"""Write benchmark sections into BENCHMARKS.md (atomically), one marked section per benchmark."""

from __future__ import annotations

import datetime as _dt
import platform
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
BENCHMARKS_MD = ROOT / "BENCHMARKS.md"

HEADER = """# Benchmarks

Every figure below is written by `tactile-deploy bench <name>` (sources in `bench/`), measured
as a ratio against a baseline in the same run. Sections are replaced in place when rerun; each
says where and when it was measured.
"""


def machine_line() -> str:
    import os

    return (
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} logical CPUs, "
        f"Python {platform.python_version()}, measured {_dt.date.today().isoformat()}"
    )


def write_section(name: str, markdown: str, path: Path = BENCHMARKS_MD) -> None:
    """Replace (or append) the section ``name`` of BENCHMARKS.md with ``markdown``."""
    import sys

    sys.path.insert(0, str(ROOT))
    from tactile_deploy.atomic import write_text

    begin, end = f"<!-- bench:{name} -->", f"<!-- /bench:{name} -->"
    text = path.read_text() if path.exists() else HEADER
    block = f"{begin}\n{markdown.strip()}\n{end}"
    if begin in text and end in text:
        head, rest = text.split(begin, 1)
        _, tail = rest.split(end, 1)
        text = head + block + tail
    else:
        text = text.rstrip() + "\n\n" + block + "\n"
    write_text(path, text)
