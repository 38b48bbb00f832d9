"""JAX's persistent compilation cache, on by default, in the user's cache directory.

Compiling the reference integrator, an error-map step or a fit takes seconds to tens of
seconds, and a command-line call would pay it again every time. Importing dampax therefore
points JAX's persistent compilation cache (``jax_compilation_cache_dir``) at
``$XDG_CACHE_HOME/dampax/jax`` (``~/.cache/dampax/jax``; ``~/Library/Caches/dampax/jax`` on
macOS, ``%LOCALAPPDATA%\\dampax\\jax`` on Windows), unless

- ``DAMPAX_CACHE=0`` (or ``off``/``false``/``no``) is set: no cache is configured, or
- ``DAMPAX_CACHE_DIR`` names another directory, or
- a cache directory is already configured (``JAX_COMPILATION_CACHE_DIR`` or
  ``jax.config.update("jax_compilation_cache_dir", ...)`` before the import): it is kept.

Programs that compile in under ``_MIN_COMPILE_S`` seconds are not written.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import jax

_OFF = ("0", "off", "false", "no")
_MIN_COMPILE_S = 0.5


def default_cache_dir() -> Path:
    """The platform's user cache directory for dampax's compiled programs."""
    if os.environ.get("DAMPAX_CACHE_DIR"):
        return Path(os.environ["DAMPAX_CACHE_DIR"]).expanduser()
    if sys.platform == "win32":
        base = Path(os.environ.get("LOCALAPPDATA") or Path.home() / "AppData" / "Local")
    elif sys.platform == "darwin":
        base = Path.home() / "Library" / "Caches"
    else:
        base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "dampax" / "jax"


def enable_compilation_cache() -> Path | None:
    """Turn JAX's persistent compilation cache on (see the module docstring).

    Returns:
        The cache directory in use (the user's own if one was configured), or None when
        ``DAMPAX_CACHE`` turns it off or the directory cannot be created.
    """
    if os.environ.get("DAMPAX_CACHE", "1").strip().lower() in _OFF:
        return None
    configured = jax.config.jax_compilation_cache_dir
    if configured:
        return Path(configured)
    path = default_cache_dir()
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None  # a read-only home: run without the cache rather than fail to import
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", _MIN_COMPILE_S)
    return path
