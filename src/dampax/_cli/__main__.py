"""``python -m dampax._cli``: the same as the ``dampax`` command."""

import sys

from . import main

sys.exit(main())
