"""JAX's persistent compilation cache, on by default, in the user's cache directory.

Compiling the reference integrator, an error-map step or a fit takes seconds to tens of
seconds, and a command-line call would pay it again every time. Importing dampax therefore
points JAX's persistent compilation cache (``jax_compilation_cache_dir``) at ``jax/`` in
dampax's cache folder ``$XDG_CACHE_HOME/dampax`` (``~/.cache/dampax``; ``~/Library/Caches/dampax``
on macOS, ``%LOCALAPPDATA%\\dampax`` on Windows), unless

- ``DAMPAX_CACHE=0`` (or ``off``/``false``/``no``) is set: no cache at all, or
- ``DAMPAX_CACHE_DIR`` names another folder (used instead of ``.../dampax``), or
- a cache directory is already configured (``JAX_COMPILATION_CACHE_DIR`` or
  ``jax.config.update("jax_compilation_cache_dir", ...)`` before the import): it is kept.

Programs that compile in under ``_MIN_COMPILE_S`` seconds are not written. The largest programs
(an error-map step) are also kept traced, as ``jax.export`` files in ``exported/`` of the same
folder (:func:`compile_cached`), so a repeated call skips tracing too: a few seconds of Python.
"""

from __future__ import annotations

import functools
import hashlib
import os
import sys
from pathlib import Path

import jax
import jax.numpy as jnp

_OFF = ("0", "off", "false", "no")
_MIN_COMPILE_S = 0.5


def dampax_cache_dir() -> Path:
    """dampax's folder in the platform's user cache directory, or ``$DAMPAX_CACHE_DIR``."""
    if os.environ.get("DAMPAX_CACHE_DIR"):
        return Path(os.environ["DAMPAX_CACHE_DIR"]).expanduser()
    if sys.platform == "win32":
        base = Path(os.environ.get("LOCALAPPDATA") or Path.home() / "AppData" / "Local")
    elif sys.platform == "darwin":
        base = Path.home() / "Library" / "Caches"
    else:
        base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "dampax"


def default_cache_dir() -> Path:
    """The directory of JAX's compiled programs: ``jax`` in dampax's cache folder."""
    return dampax_cache_dir() / "jax"


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


# ----------------------------------------------------------------------------------------------
# serialized programs: a repeated call skips tracing, not only compiling


@functools.lru_cache(maxsize=1)
def _source_digest() -> str:
    """Digest of dampax's own source files and the versions of what it runs on."""
    import jaxlib

    h = hashlib.sha256(f"{jax.__version__} {jaxlib.__version__}".encode())
    root = Path(__file__).parent
    for path in sorted(root.rglob("*.py")):
        h.update(str(path.relative_to(root)).encode())
        h.update(path.read_bytes())
    return h.hexdigest()


def exported_dir() -> Path | None:
    """Where serialized programs are kept (beside the compilation cache), or None when off."""
    if os.environ.get("DAMPAX_CACHE", "1").strip().lower() in _OFF:
        return None
    return dampax_cache_dir() / "exported"


def compile_cached(name: str, key, fn, *specs):
    """``fn.lower(*specs).compile()``, tracing ``fn`` only when no serialized program exists.

    The first call traces ``fn`` with ``jax.export`` and writes the program, keyed by
    ``key``, the argument specs, the devices, dampax's source and the jax version; a later
    process deserializes it (milliseconds instead of seconds of tracing), and the compiled
    executable comes from JAX's persistent cache. Without a cache directory (``DAMPAX_CACHE=0``)
    or if the program cannot be exported, this is a plain ``lower().compile()``.

    Arguments:
        name: a readable prefix of the file name.
        key: a hashable description of everything static that ``fn`` closes over (its repr
            must determine the program).
        fn: a ``jax.jit``-wrapped function.
        specs: ``jax.ShapeDtypeStruct`` of its arguments (with shardings where needed).

    Returns:
        The compiled executable.
    """
    folder = exported_dir()
    if folder is None:
        return fn.lower(*specs).compile()
    devices = jax.devices()
    text = repr((key, [(s.shape, str(s.dtype), str(getattr(s, "sharding", None)))
                       for s in specs], len(devices), devices[0].platform,
                 devices[0].device_kind, jax.config.jax_enable_x64, _source_digest()))
    path = folder / f"{name}-{hashlib.sha256(text.encode()).hexdigest()[:32]}.jaxexport"
    exported = None
    if path.exists():
        try:
            exported = jax.export.deserialize(bytearray(path.read_bytes()))
        except Exception:  # noqa: BLE001 - a damaged or foreign file: trace again
            exported = None
    if exported is None:
        try:
            exported = jax.export.export(fn)(*specs)
        except Exception:  # noqa: BLE001 - not exportable: the plain route
            return fn.lower(*specs).compile()
        try:
            folder.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(f".{os.getpid()}.tmp")
            tmp.write_bytes(exported.serialize())
            os.replace(tmp, path)  # atomic: a concurrent process never reads half a file
        except (OSError, ImportError):  # read-only cache, or no flatbuffers: not kept
            pass
    return jax.jit(exported.call).lower(*specs).compile()


_EXECUTABLES: dict = {}  # (name, repr(key), specs) -> compiled, for the life of the process


def call_cached(name: str, key, fn, *args):
    """``fn(*args)`` for concrete arrays, through :func:`compile_cached` (eager calls only).

    The executable is kept for the life of the process (so a second call neither traces nor
    compiles) and, through the exported-program and compilation caches, across processes: a
    repeated command-line call deserializes the program instead of tracing it.

    Arguments:
        name: a readable prefix of the cached file's name.
        key: a hashable description of everything static that ``fn`` closes over (its repr
            must determine the program).
        fn: a function of the flat arrays ``args`` returning a pytree of arrays (standard
            containers only: dicts, tuples, lists).
        args: concrete arrays (or scalars), positional.

    Returns:
        ``fn(*args)``, computed by the compiled program.
    """
    arrays = [jnp.asarray(a) for a in args]
    specs = tuple(jax.ShapeDtypeStruct(a.shape, a.dtype) for a in arrays)
    memo = (name, repr(key), tuple((s.shape, str(s.dtype)) for s in specs))
    executable = _EXECUTABLES.get(memo)
    if executable is None:
        executable = compile_cached(name, key, jax.jit(fn), *specs)
        _EXECUTABLES[memo] = executable
    return executable(*arrays)
