"""From a folder of recorded ball presses to a sensor plugin in one command.

``tactile-deploy calibrate --sensor NAME --pad FAMILY --presses DIR [--reference REF.png]
[--annotations CSV] --ball-radius-mm R [--mm-per-px S] [--plugins-dir DIR] --yes``:
:mod:`.load` reads the folder (and picks or checks the no-contact frame), :mod:`.checks` catches
plausible but wrong inputs, :mod:`.build` fits the shading model on the frames rectified onto
the family's sensing area and writes the plugin atomically; :mod:`.cli` is the command.
"""
