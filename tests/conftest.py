"""Test configuration: importing dampax enables float64 in JAX once, for every test module.

The tests get a cache folder of their own (``DAMPAX_CACHE_DIR``, a fresh temporary directory
per session), set before dampax is imported: nothing from the user's ``~/.cache/dampax`` (or an
earlier run of ``dampax errormap``) is re-used, so compilation counts mean what they say, and
the suite writes nothing there.
"""

import os
import tempfile

os.environ["DAMPAX_CACHE_DIR"] = tempfile.mkdtemp(prefix="dampax-test-cache-")

import dampax  # noqa: E402, F401  (jax_enable_x64 is set on import)
