"""Regenerate the committed JSON Schema of the virtual sensor file:
``python -m tactile_deploy.sensors.schema`` (a test fails when it drifts)."""

from tactile_deploy.atomic import write_text
from tactile_deploy.sensors.config import SCHEMA_PATH, schema_text

if __name__ == "__main__":
    write_text(SCHEMA_PATH, schema_text())
    print(f"wrote {SCHEMA_PATH}")
