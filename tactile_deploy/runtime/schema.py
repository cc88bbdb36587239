"""The committed JSON Schema of ``plugin.json`` (``manifest.schema.json`` beside this module).

``python -m tactile_deploy.runtime.schema`` rewrites it from
:class:`~tactile_deploy.runtime.plugins.manifest.PluginManifest`; a test fails when they drift apart.
"""

from __future__ import annotations

import json
from pathlib import Path

from tactile_deploy.runtime.plugins.manifest import manifest_json_schema

#: Where the schema is committed.
SCHEMA_PATH = Path(__file__).resolve().parent / "manifest.schema.json"


def schema_text() -> str:
    """The schema as committed: 2-space indented JSON with a trailing newline."""
    return json.dumps(manifest_json_schema(), indent=2) + "\n"


if __name__ == "__main__":
    from tactile_deploy.atomic import write_text

    write_text(SCHEMA_PATH, schema_text())
    print(f"wrote {SCHEMA_PATH}")
