"""``dampax fit`` (temporary: being moved here from dampax._fit)."""

from .._fit import add_arguments as add_arguments  # noqa: F401
from .._fit import run as run  # noqa: F401
