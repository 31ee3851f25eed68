"""``python -m cosim.cli``: the same as ``buck-cosim``."""

import sys

from cosim.cli import main

sys.exit(main())
