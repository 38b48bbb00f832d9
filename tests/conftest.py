"""Test configuration: importing dampax enables float64 in JAX once, for every test module."""

import dampax  # noqa: F401  (jax_enable_x64 is set on import)
