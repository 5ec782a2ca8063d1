"""``python -m service.cli``: the ``omnisplat`` command line."""

import sys

from . import main

sys.exit(main())
