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

Programs that compile in under ``_MIN_COMPILE_S`` seconds are not written, except within a
command of the command line (:func:`keep_every_program`). The largest programs (an error-map
step) are also kept traced, as ``jax.export`` files in ``exported/`` of the same folder
(:func:`compile_cached`), so a repeated call skips tracing too: a few seconds of Python. Eager
calls of the commands' numeric work (a solve, a fit's core and batch of starts, a sensitivity)
run through :func:`call_cached` / :func:`call_cached_tree`: the program is kept as a
``.jaxcall`` file, a ``jax.export`` program with its output's treedef beside it, so any pytree
(equinox modules included) comes back whole and a repeated command neither traces nor
compiles. The executables of both kinds, when compiled in this process (not read from JAX's
cache), are also kept whole (``.jaxexe``, :func:`_keep_executable`): a repeated command then
neither lowers the kept program nor hashes it for JAX's cache (a few tenths of a second per
program).
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import io
import os
import pickle
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


@contextlib.contextmanager
def keep_every_program():
    """Within the block, write every compiled program to dampax's persistent cache, however
    quick to compile.

    For the command line: a command compiles dozens of small programs (one per eager array
    operation, each 20-60 ms) below the ``_MIN_COMPILE_S`` threshold, seconds in all that a
    repeated command would pay again. They are small (a few kB each) and, for a given command
    and input size, the same every time. Library use keeps the threshold (it would fill the
    cache with every eager operation of every shape); so does a cache folder configured by
    the user. The threshold is restored when the block ends.

    Yields:
        True when dampax's own cache folder is in use (the threshold is 0 in the block).
    """
    configured = jax.config.jax_compilation_cache_dir
    if not configured or Path(configured) != default_cache_dir():
        yield False
        return
    before = jax.config.jax_persistent_cache_min_compile_time_secs
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    try:
        yield True
    finally:
        jax.config.update("jax_persistent_cache_min_compile_time_secs", before)


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
    mesh = getattr(getattr(specs[0], "sharding", None), "mesh", None) if specs else None
    exe_path = _executable_path(folder, name, text)
    devices = list(mesh.devices.flat) if mesh is not None else None
    loaded = _load_executable(exe_path, devices)
    if loaded is not None:
        return loaded[0]
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
    lowered = jax.jit(exported.call).lower(*specs)
    with _fresh_compilation() as fresh:
        compiled = lowered.compile()
    _keep_executable(exe_path if fresh() and _keepable(lowered) else None, compiled)
    return compiled


# ----------------------------------------------------------------------------------------------
# compiled executables kept whole: a repeated call neither lowers nor looks up JAX's cache


@functools.lru_cache(maxsize=1)
def _machine_text() -> str:
    """What a compiled executable depends on beyond its program: the backend's version, XLA's
    flags and the processor (XLA compiles CPU programs for the host's instruction set)."""
    import platform

    cpu = platform.processor()
    with contextlib.suppress(OSError):  # Linux: the model and the instruction-set extensions
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as info:
            cpu = "".join(line for line in info.read().split("\n\n")[0].splitlines(True)
                          if line.startswith(("model name", "flags", "Features", "CPU part")))
    client = jax.devices()[0].client
    return repr((client.platform, client.platform_version, os.environ.get("XLA_FLAGS", ""),
                 platform.machine(), hashlib.sha256(cpu.encode()).hexdigest()))


def _executable_path(folder: Path, name: str, text: str) -> Path | None:
    """The ``.jaxexe`` file of the executable of the program described by ``text`` on this
    machine, or None in a ``jax.distributed`` run (each process's devices differ; see
    ``dampax._studies._distributed.compile_cached_here``)."""
    if jax.process_count() > 1:
        return None
    digest = hashlib.sha256((text + _machine_text()).encode()).hexdigest()[:32]
    return folder / f"{name}-{digest}.jaxexe"


def _load_executable(path: Path | None, devices=None):
    """(executable, extra) of a file written by :func:`_keep_executable`, or None.

    Loading skips what a kept ``jax.export`` program still costs a repeated command: lowering
    it (a few tenths of a second per program) and hashing it for JAX's persistent cache. Like
    JAX's own cache the file holds machine code: the cache folder must be the user's own.
    """
    if path is None or not path.exists():
        return None
    try:
        from jax.experimental import serialize_executable

        _prepare_loading()
        data = path.read_bytes()
        size = int.from_bytes(data[:8], "little")
        in_tree, out_tree, extra = _load_tree(data[8:8 + size])
        executable = serialize_executable.deserialize_and_load(
            data[8 + size:], in_tree, out_tree, execution_devices=devices)
    except Exception:  # noqa: BLE001 - a damaged file: the kept program instead
        with contextlib.suppress(OSError):
            path.unlink()  # written again when the program is next compiled here
        return None
    return executable, extra


#: custom calls an executable may make and still be kept: XLA's sharding markers, and LAPACK
#: (its function pointers are set by :func:`_prepare_loading` before a kept executable loads)
_SAFE_CUSTOM_CALLS = ("Sharding", "SPMDFullToShardShape", "SPMDShardToFullShape")


def _keepable(lowered) -> bool:
    """Whether the executable of ``lowered`` may be kept: only when every custom call it makes
    is one of :data:`_SAFE_CUSTOM_CALLS` or LAPACK's. Not a Python callback (equinox's run-time
    checks, ``jax.pure_callback``): its address is baked into the machine code and another
    process would jump into nothing (JAX's own cache does not keep these either); nor any other
    kernel that jaxlib sets up only when it lowers a program, which a kept executable skips."""
    import re

    try:
        if getattr(lowered._lowering, "compile_args", {}).get("host_callbacks"):
            return False
        targets = set(re.findall(r"custom_call\s*@([\w.]+)", lowered.as_text()))
    except Exception:  # noqa: BLE001 - in doubt, not kept
        return False
    return all(t in _SAFE_CUSTOM_CALLS or t.startswith("lapack_") for t in targets)


@functools.lru_cache(maxsize=1)
def _prepare_loading() -> None:
    """Set up what a kept executable may call that jaxlib otherwise sets up while lowering:
    LAPACK's function pointers (taken from scipy; a kept fit or linear solve would call null
    pointers without them)."""
    from jax._src.lax import linalg

    linalg.initialize_lapack()


@contextlib.contextmanager
def _fresh_compilation():
    """Yields a function that tells whether no program compiled in the block came from JAX's
    persistent cache. Only an executable compiled here may be kept by :func:`_keep_executable`:
    one read from that cache serializes without its kernels (jaxlib 0.10: "Function ... not
    found" when the copy runs)."""
    hits = []

    def listener(event, **kwargs):
        if event == "/jax/compilation_cache/cache_hits":
            hits.append(event)

    jax.monitoring.register_event_listener(listener)
    try:
        yield lambda: not hits
    finally:
        jax.monitoring.unregister_event_listener(listener)


def _keep_executable(path: Path | None, executable, extra=None) -> None:
    """Write ``executable`` (``jax.experimental.serialize_executable``) and ``extra`` (a
    treedef and static leaves, or None) to ``path``, atomically; nothing when it cannot be
    serialized or written (the kept program and JAX's cache still serve the next call)."""
    if path is None:
        return
    try:
        from jax.experimental import serialize_executable

        payload, in_tree, out_tree = serialize_executable.serialize(executable)
        blob = _dump_tree((in_tree, out_tree, extra))
        if _load_tree(blob) != (in_tree, out_tree, extra):
            return
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_bytes(len(blob).to_bytes(8, "little") + blob + payload)
        os.replace(tmp, path)  # atomic: a concurrent process never reads half a file
    except Exception:  # noqa: BLE001 - not serializable, or a read-only cache
        return


_EXECUTABLES: dict = {}  # (name, repr(key), specs) -> (compiled, treedef, static leaves)


def _missing():
    """equinox's MISSING sentinel (a treedef's auxiliary data holds it; pickled by name)."""
    from equinox._module._flatten import MISSING

    return MISSING


class _TreePickler(pickle.Pickler):
    """Pickles a treedef with equinox's MISSING by name (its unpickled copy would be a new,
    different object, and equinox's unflatten tests for the one sentinel with ``is``)."""

    def reducer_override(self, obj):
        if type(obj).__name__ == "_Missing" and type(obj).__module__.startswith("equinox."):
            return _missing, ()
        return NotImplemented


#: globals a kept treedef may name: jax's treedef and registries (a compiled call's argument
#: tree names the registry of traced calls), MISSING, and classes of these
_TREE_GLOBALS = {("jaxlib._jax.pytree", "PyTreeDef"), ("jax._src.tree_util", "default_registry"),
                 ("jax._src.tree_util", "tracing_registry"), ("dampax._cache", "_missing")}
_TREE_PACKAGES = ("dampax", "equinox", "collections", "builtins")


class _TreeUnpickler(pickle.Unpickler):
    """Unpickles a treedef: only the names of :data:`_TREE_GLOBALS` and classes of dampax,
    equinox and the standard containers (nothing else is imported or called)."""

    def find_class(self, module, name):
        if (module, name) in _TREE_GLOBALS:
            return super().find_class(module, name)
        if module.split(".")[0] in _TREE_PACKAGES:
            obj = super().find_class(module, name)
            if isinstance(obj, type):
                return obj
        raise pickle.UnpicklingError(f"not a treedef: {module}.{name}")


def _dump_tree(value) -> bytes:
    """``value`` (a treedef and its static leaves) pickled with :class:`_TreePickler`."""
    buffer = io.BytesIO()
    _TreePickler(buffer, protocol=pickle.HIGHEST_PROTOCOL).dump(value)
    return buffer.getvalue()


def _load_tree(data: bytes):
    """Inverse of :func:`_dump_tree` (:class:`_TreeUnpickler`)."""
    return _TreeUnpickler(io.BytesIO(data)).load()


def _spec_text(specs) -> list:
    """What of the argument specs determines a program: shapes, dtypes, weak types."""
    return [(s.shape, str(s.dtype), bool(getattr(s, "weak_type", False))) for s in specs]


def _compile_tree(name: str, key, fn, specs):
    """(executable, treedef, static): ``fn`` compiled for ``specs``, kept as a file.

    The kept program returns the array leaves of ``fn``'s output; its treedef and its other
    leaves (Python values fixed at tracing) are pickled beside it, so any pytree (equinox
    modules, named tuples) comes back whole. Without a cache folder, or when the program or
    its treedef cannot be kept, the executable is compiled in-process (treedef None: it
    returns the pytree itself).
    """
    folder = exported_dir()
    plain = jax.jit(fn)
    if folder is None:
        return plain.lower(*specs).compile(), None, None
    devices = jax.devices()
    text = repr((key, _spec_text(specs), len(devices), devices[0].platform,
                 devices[0].device_kind, jax.config.jax_enable_x64, _source_digest()))
    path = folder / f"{name}-{hashlib.sha256(text.encode()).hexdigest()[:32]}.jaxcall"
    exe_path = _executable_path(folder, name, text)
    loaded = _load_executable(exe_path)
    if loaded is not None:
        executable, (treedef, static) = loaded
        return executable, treedef, static
    exported = None
    if path.exists():
        try:
            data = path.read_bytes()
            size = int.from_bytes(data[:8], "little")
            treedef, static, weak = _load_tree(data[8:8 + size])
            exported = jax.export.deserialize(bytearray(data[8 + size:]))
        except Exception:  # noqa: BLE001 - a damaged or foreign file: trace again
            exported = None
    if exported is None:
        traced = {}

        def flat_fn(*args):
            leaves, treedef = jax.tree_util.tree_flatten(fn(*args))
            arrays = [leaf for leaf in leaves if isinstance(leaf, jax.Array)]
            traced["treedef"] = treedef
            traced["static"] = {i: leaf for i, leaf in enumerate(leaves)
                                if not isinstance(leaf, jax.Array)}
            traced["weak"] = tuple(bool(jax.typeof(a).weak_type) for a in arrays)
            return arrays

        try:
            exported = jax.export.export(jax.jit(flat_fn))(*specs)
            kept = (traced["treedef"], traced["static"], traced["weak"])
            blob = _dump_tree(kept)
            if _load_tree(blob) != kept:
                raise ValueError("the treedef does not survive pickling")
            treedef, static, weak = kept
            payload = exported.serialize()
            exported = jax.export.deserialize(payload)  # the program a later process reads
        except Exception:  # noqa: BLE001 - not exportable: the plain route
            return plain.lower(*specs).compile(), None, None
        try:
            folder.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(f".{os.getpid()}.tmp")
            tmp.write_bytes(len(blob).to_bytes(8, "little") + blob + payload)
            os.replace(tmp, path)  # atomic: a concurrent process never reads half a file
        except OSError:  # a read-only cache: not kept
            pass

    def call(*args):  # the outputs' weak types, lost in serialization, restored (no-op)
        return [_weak(a) if w else a for a, w in zip(exported.call(*args), weak, strict=True)]

    lowered = jax.jit(call).lower(*specs)
    with _fresh_compilation() as fresh:
        executable = lowered.compile()
    _keep_executable(exe_path if fresh() and _keepable(lowered) else None, executable,
                     (treedef, static))
    return executable, treedef, static


def _weak(x):
    """``x`` as a weakly typed array of the same dtype and values (inside a trace)."""
    from jax._src.lax.lax import _convert_element_type

    return _convert_element_type(x, None, weak_type=True)


def call_cached(name: str, key, fn, *args):
    """``fn(*args)`` for concrete arrays, through a kept compiled program (eager calls only).

    The executable is kept for the life of the process (so a second call neither traces nor
    compiles) and, as a ``jax.export`` file with the output's treedef beside it (in
    ``exported/``, keyed by ``key``, the argument specs, the devices, dampax's source and the
    jax version) plus JAX's persistent compilation cache, across processes: a repeated
    command-line call deserializes the program instead of tracing it. Without a cache
    directory (``DAMPAX_CACHE=0``) only the in-process memo is kept.

    Arguments:
        name: a readable prefix of the cached file's name.
        key: a hashable description of everything static that ``fn`` closes over (its repr
            must determine the program).
        fn: a function of the flat arrays ``args`` returning a pytree: arrays in standard
            containers, named tuples or equinox modules (static fields and non-array leaves
            must be picklable: strings, numbers, classes).
        args: concrete arrays (or scalars), positional; weak types are kept.

    Returns:
        ``fn(*args)``, computed by the compiled program.
    """
    arrays = [jnp.asarray(a) for a in args]
    specs = tuple(jax.ShapeDtypeStruct(a.shape, a.dtype, weak_type=a.weak_type)
                  for a in arrays)
    memo = (name, repr(key), tuple(map(tuple, _spec_text(specs))))
    entry = _EXECUTABLES.get(memo)
    if entry is None:
        entry = _compile_tree(name, key, fn, specs)
        _EXECUTABLES[memo] = entry
    executable, treedef, static = entry
    out = executable(*arrays)
    if treedef is None:
        return out
    flat = iter(out)
    leaves = [static[i] if i in static else next(flat) for i in range(treedef.num_leaves)]
    return jax.tree_util.tree_unflatten(treedef, leaves)


def call_cached_tree(name: str, key, fn, *args):
    """:func:`call_cached` for pytree arguments: ``fn(*args)`` with ``args`` pytrees of
    concrete arrays (an Oscillator, a solution, named tuples), flattened for the program.

    Arguments:
        name: a readable prefix of the cached file's name.
        key: a hashable description of everything static that ``fn`` closes over (the
            arguments' tree structure is added to it).
        fn: a function of the pytrees ``args`` returning a pytree (as for :func:`call_cached`).
        args: pytrees whose leaves are concrete arrays or numbers.

    Returns:
        ``fn(*args)``, computed by the compiled program.
    """
    leaves, treedef = jax.tree_util.tree_flatten(args)

    def flat(*values):
        return fn(*jax.tree_util.tree_unflatten(treedef, values))

    return call_cached(name, (key, str(treedef)), flat, *leaves)
