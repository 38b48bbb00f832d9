"""``python -m dampax_cli``: the ``dampax`` console script."""

from . import console

console()
