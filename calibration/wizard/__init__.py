"""The calibration wizard: a new sensor -> a plugin (docs/calibration.md); the steps are in
:mod:`tactile_deploy.calibration.wizard.steps`, the data they leave in :mod:`tactile_deploy.calibration.wizard.work_data`."""
