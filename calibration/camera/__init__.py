"""Camera mapping calibration: lens distortion, homography to the sensor plane, mm per pixel.

Modules: :mod:`.charuco` (printed ChArUco board), :mod:`.dots` (dot grid pressed into the gel),
:mod:`.fitting` (shared least-squares fit), :mod:`.synthetic` (virtual-sensor target frames),
:mod:`.figure` (diagnostic plots), :mod:`.cli` (``camera`` and ``make-board`` commands),
:mod:`.benchmark` (rectification speed), :mod:`.schema` (committed JSON Schema).
The result is a :class:`tactile_deploy.imaging.camera_mapping.CameraMapping`.
"""
