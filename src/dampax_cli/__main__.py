"""``python -m dampax_cli``: the ``dampax`` console script."""

import sys

from . import main

sys.exit(main())
