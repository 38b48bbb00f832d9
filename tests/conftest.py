"""Test configuration: float64 everywhere (dampax enables it on import; set it here too)."""

import jax

jax.config.update("jax_enable_x64", True)
