"""The calibration wizard: a new sensor -> a plugin (docs/calibration.md); the steps are in
:mod:`calibration.wizard.steps`, the data they leave in :mod:`calibration.wizard.work_data`."""
