"""Frame sources (LeRobot-style): configs in :mod:`.config` (no hardware imports), one module
per kind, and :func:`.factory.make_source`."""
