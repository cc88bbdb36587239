"""``python -m training.shading_net``: see :mod:`training.shading_net.train`."""

import sys

from .train import main

sys.exit(main())
