"""Torch code shared by calibration and training: the learned read-out's network, its training
targets, ONNX export and import, and its fine-tuning on one unit.

Needs torch and onnx (the ``train`` extra). Nothing else in :mod:`tactile_deploy` imports this
package, so the runtime imports and runs without torch (an import-linter contract in
``pyproject.toml`` keeps it so).
"""
