"""Marble shading calibration: ball presses -> a position-dependent colour-to-gradient LUT.

Modules: :mod:`.presses` (reference, press frames, annotation CSV), :mod:`.circles` (OpenCV
contact detection, shared-colour-model centre refinement, contact radius from gradients),
:mod:`.targets` (sphere gradients of the ball's radius), :mod:`.press_profile` (the ball press
solved by the FEM of the pad: targets around the contact), :mod:`.fit` (the table and the depth
integration weights), :mod:`.baselines` (RGB-difference table and per-pixel MLP, as public tools
do), :mod:`.evaluate` (sphere fits, grouped cross-validation, depth errors), :mod:`.compare`
(all three side by side), :mod:`.virtual_check` (absolute depth on virtual-sensor presses),
:mod:`.cli` (``calibrate shading`` and ``depth`` commands),
:mod:`.schema` (committed JSON Schema of the model header). The result is a
:class:`tactile_deploy.imaging.shading.ShadingModel`; see docs/shading.md.
"""
