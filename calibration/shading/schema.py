"""The committed JSON Schema of the shading model header (``shading_header.schema.json``).

``python -m calibration.shading.schema`` rewrites it from
:class:`tactile_deploy.imaging.shading.ShadingHeader`; a test fails when the committed file and
the model drift apart.
"""

from __future__ import annotations

import json
from pathlib import Path

from tactile_deploy.atomic import write_text
from tactile_deploy.imaging.shading import shading_header_json_schema

#: Where the schema is committed.
SCHEMA_PATH = Path(__file__).resolve().parent / "shading_header.schema.json"


def schema_text() -> str:
    """The schema as committed: 2-space indented JSON with a trailing newline."""
    return json.dumps(shading_header_json_schema(), indent=2) + "\n"


if __name__ == "__main__":
    write_text(SCHEMA_PATH, schema_text())
    print(f"wrote {SCHEMA_PATH}")
