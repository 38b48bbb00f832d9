"""JAX's persistent compilation cache, on by default, in the user's cache directory, and
dampax's own kept programs beside it, verified before use.

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
``.jaxcall`` file, a ``jax.export`` program with its output's tree structure beside it (as
JSON, rebuilt from classes of dampax and equinox only), so any pytree (equinox modules
included) comes back whole and a repeated command neither traces nor compiles. The executables
of both kinds, when compiled in this process (not read from JAX's cache), are also kept whole
(``.jaxexe``, :func:`_keep_executable`): a repeated command then neither lowers the kept program
nor hashes it for JAX's cache. A program compiled afresh goes straight from its trace to its
kept executable (:func:`_compile_kept`); the ``.jaxcall`` is written only where the executable
cannot be kept. :func:`prepare_cached` builds a program in a background thread ahead of its
first call (XLA compiles with Python's lock released).

**Safety** (docs/DESIGN.md, "The cache"). A kept program is code that runs as the user, so the
cache is used only where nobody else could have put a file, and every file is checked before
it is read, as pip does for its cache and as JAX's cache assumes:

- the folders are made ``0o700``; a folder not owned by the user, or one that others can write
  (a ``DAMPAX_CACHE_DIR`` on a group-shared file system), is not used: a :class:`CacheWarning`
  says why, and the run goes on without the cache;
- every file carries the digest of everything that shapes its program (dampax's source, the
  versions of jax, jaxlib, equinox, optimistix, lineax and numpy, the platform and device,
  ``XLA_FLAGS``, float64, the options) and an HMAC-SHA256 of its whole content under a key
  that only the user can read (``key`` in the cache folder, ``0o600``, 32 random bytes);
  nothing of a file is interpreted before its HMAC and its digest are verified, so a file that
  another user planted, a file copied under another program's name, one built by another
  version, and a damaged one (a flipped byte, a truncated file) are all refused;
- a file that is not a regular file (a FIFO, a link, a device), not the user's own, writable
  by others, or larger than :data:`MAX_FILE_BYTES` is refused without being read (opened with
  ``O_NOFOLLOW | O_NONBLOCK``); a refused file is moved aside to ``rejected/`` (with a
  warning) and its program built again, never fatal;
- dampax's own formats hold no pickle: tree structures are JSON of plain values and classes of
  dampax, equinox and the standard containers. JAX's executable format
  (``jax.experimental.serialize_executable``) is a pickle: it is given only bytes whose HMAC
  verified, and through an unpickler that admits classes of jax, jaxlib and numpy only;
- files are written to an exclusively created temporary name and renamed into place (a
  concurrent reader never sees half a file; an interrupted writer leaves no file behind).
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import io
import math
import os
import threading
from pathlib import Path

import jax
import jax.export  # noqa: F401 (jax 0.7 does not import this submodule itself)
import jax.numpy as jnp
import numpy as np

from ._cachefiles import _CLASS_PACKAGES as _CLASS_PACKAGES
from ._cachefiles import _EXECUTABLE_PACKAGES as _EXECUTABLE_PACKAGES
from ._cachefiles import _MAGIC as _MAGIC
from ._cachefiles import _NUMPY_HELPERS as _NUMPY_HELPERS
from ._cachefiles import _SAFE_BUILTINS as _SAFE_BUILTINS
from ._cachefiles import _TAG as _TAG
from ._cachefiles import _WARNED as _WARNED
from ._cachefiles import MAX_FILE_BYTES as MAX_FILE_BYTES
from ._cachefiles import CacheWarning as CacheWarning
from ._cachefiles import _decode as _decode
from ._cachefiles import _digest as _digest
from ._cachefiles import _dump_tree as _dump_tree
from ._cachefiles import _encode as _encode
from ._cachefiles import _key as _key
from ._cachefiles import _load_tree as _load_tree
from ._cachefiles import _missing as _missing
from ._cachefiles import _owner_problem as _owner_problem
from ._cachefiles import _read_entry as _read_entry
from ._cachefiles import _read_regular as _read_regular
from ._cachefiles import _restricted_unpickler as _restricted_unpickler
from ._cachefiles import _set_aside as _set_aside
from ._cachefiles import _source_digest as _source_digest
from ._cachefiles import _sweep as _sweep
from ._cachefiles import _tree_from_json as _tree_from_json
from ._cachefiles import _tree_json as _tree_json
from ._cachefiles import _warn as _warn
from ._cachefiles import _write_entry as _write_entry
from ._cachefiles import dampax_cache_dir as dampax_cache_dir
from ._cachefiles import default_cache_dir as default_cache_dir
from ._cachefiles import executable_header as executable_header
from ._cachefiles import load_executable_bytes as load_executable_bytes
from ._cachefiles import secure_folder as secure_folder
from ._cachethreads import _HOLDS as _HOLDS
from ._cachethreads import _TRACING as _TRACING
from ._cachethreads import _begin_turn as _begin_turn
from ._cachethreads import _Claimable as _Claimable
from ._cachethreads import _end_turn as _end_turn
from ._cachethreads import _loader as _loader
from ._cachethreads import _pool as _pool
from ._cachethreads import _turn as _turn
from ._cachethreads import note_used, prefetched, prepare_loading, prepare_loading_beside

_OFF = ("0", "off", "false", "no")
_MIN_COMPILE_S = 0.5

#: XLA options of every program compiled here on a CPU (:func:`compiler_options`): XLA's
#: loop-fusion emitter instead of the MLIR fusion emitters that jaxlib 0.10 uses by default,
#: which run an MLIR pass pipeline of their own for every fusion of a program. A cold default
#: fit compiled its programs in 20 s of CPU with those and 12 s with this (11.2 -> 7.2 s on 2
#: cores, issue 36). Most programs run as fast; the exact model's fit runs 1.6x longer (about
#: 0.1 s of a warm fit): ``DAMPAX_FAST_COMPILE=0`` keeps XLA's defaults for many warm fits
#: (benchmarks/README.md, issue 36, eighth session).
CPU_COMPILER_OPTIONS = (("xla_cpu_use_fusion_emitters", False),)
#: set when this jaxlib's XLA refused :data:`CPU_COMPILER_OPTIONS` (jaxlib 0.11 removed the
#: option: "No such compile option"); programs are then compiled with XLA's defaults
_REFUSED = threading.Event()


#: programs compiled on a CPU without XLA's backend optimisations
#: (``xla_backend_optimization_level`` 0): the approximate model's fit where it only starts
#: the exact one (``_core.run_core``'s ``quick``; once per default fit). It compiles in about
#: half the time (2 of 4 s) and runs 2-3x longer (about 30 ms more per call): a cold default
#: fit takes 3 s less CPU, 1.3 s less on 2 cores (benchmarks/README.md, issue 36, twenty-sixth
#: session). Not for the ansatz's own fits (``model="ansatz"``, the model ranking: 1.6x
#: longer warm), nor for the small programs, which compile in 0.1-0.7 s either way
QUICK_PROGRAMS = frozenset({"fit-core-quick"})


def compiler_options(name: str | None = None) -> dict | None:
    """The XLA options dampax compiles its program ``name`` with: :data:`CPU_COMPILER_OPTIONS`
    on a CPU (and optimisation level 0 for :data:`QUICK_PROGRAMS`) unless
    ``DAMPAX_FAST_COMPILE`` is 0 (or off/false/no) or this XLA does not know them, XLA's
    defaults otherwise (None)."""
    if _REFUSED.is_set() or os.environ.get("DAMPAX_FAST_COMPILE", "1").strip().lower() in _OFF:
        return None
    if jax.default_backend() != "cpu":
        return None
    quick = {"xla_backend_optimization_level": 0} if name in QUICK_PROGRAMS else {}
    return dict(CPU_COMPILER_OPTIONS, **quick)


def _compile(lowered, name: str | None = None):
    """``lowered.compile()`` with :func:`compiler_options` of the program ``name``; the tracing
    turn passes on."""
    _end_turn()
    options = compiler_options(name)
    try:
        return lowered.compile(options)
    except jax.errors.JaxRuntimeError as err:
        if not options or "No such compile option" not in str(err):
            raise
        _REFUSED.set()
        return lowered.compile()


def enable_compilation_cache() -> Path | None:
    """Turn JAX's persistent compilation cache on (see the module docstring).

    Returns:
        The cache directory in use (the user's own if one was configured), or None when
        ``DAMPAX_CACHE`` turns it off, the directory cannot be created, or it is not safe
        (not the user's own, or writable by others: a :class:`CacheWarning` says so).
    """
    if os.environ.get("DAMPAX_CACHE", "1").strip().lower() in _OFF:
        return None
    configured = jax.config.jax_compilation_cache_dir
    if configured:
        return Path(configured)
    path = default_cache_dir()
    if not (secure_folder(dampax_cache_dir()) and secure_folder(path)):
        return None
    _sweep(path)
    if secure_folder(dampax_cache_dir() / "exported"):
        _sweep(dampax_cache_dir() / "exported", kept=True)
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", _MIN_COMPILE_S)
    return path


def keep_every_program_active() -> bool:
    """Whether dampax's own JAX cache folder is the one in use."""
    configured = jax.config.jax_compilation_cache_dir
    return bool(configured) and Path(configured) == default_cache_dir()


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
    if not keep_every_program_active():
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


def exported_dir() -> Path | None:
    """Where serialized programs are kept (beside the compilation cache), or None when off
    or not safe (see :func:`secure_folder`)."""
    if os.environ.get("DAMPAX_CACHE", "1").strip().lower() in _OFF:
        return None
    folder = dampax_cache_dir() / "exported"
    if not (secure_folder(dampax_cache_dir()) and secure_folder(folder)):
        return None
    return folder


def _program_text(key, specs, name: str | None = None) -> str:
    """What determines a program ``name`` beyond the environment: the key, the specs, the
    devices, the compiler's options."""
    devices = jax.devices()
    return repr((key, [(s.shape, str(s.dtype), str(getattr(s, "sharding", None)),
                        bool(getattr(s, "weak_type", False))) for s in specs],
                 len(devices), devices[0].platform, devices[0].device_kind,
                 compiler_options(name)))


def compile_cached(name: str, key, fn, *specs):
    """``fn.lower(*specs).compile()``, tracing ``fn`` only when no serialized program exists
    (:func:`_compile_cached_turn`, in its tracing turn: :func:`_turn`)."""
    with _turn():
        return _compile_cached_turn(name, key, fn, *specs)


def _compile_cached_turn(name: str, key, fn, *specs):
    """``_compile(fn.lower(*specs))``, tracing ``fn`` only when no serialized program exists.

    The first call traces ``fn`` with ``jax.export`` and writes the program, keyed by
    ``key``, the argument specs, the devices, dampax's source and the versions it runs on; a
    later process deserializes it (milliseconds instead of seconds of tracing), and the
    compiled executable comes from JAX's persistent cache. Without a cache directory
    (``DAMPAX_CACHE=0``) or if the program cannot be exported, this is a plain
    ``lower().compile()``.

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
        return _compile(fn.lower(*specs), name)
    digest = _digest(_program_text(key, specs, name))
    path = folder / f"{name}-{digest[:32]}.jaxexport"
    mesh = getattr(getattr(specs[0], "sharding", None), "mesh", None) if specs else None
    exe_path = _executable_path(folder, name, digest)
    loaded = _load_executable(exe_path, list(mesh.devices.flat) if mesh is not None else None)
    if loaded is not None:
        return loaded[0]
    exported = None
    entry = _read_entry(path, digest)
    if entry is not None:
        with contextlib.suppress(Exception):  # verified, yet not readable here: trace again
            exported = jax.export.deserialize(bytearray(entry[1]))
    if exported is None:
        try:
            exported = jax.export.export(fn)(*specs)
            payload = exported.serialize()
        except Exception:  # noqa: BLE001 - not exportable: the plain route
            return _compile(fn.lower(*specs), name)
        _write_entry(path, digest, {"kind": "jaxexport"}, bytes(payload))
    lowered = jax.jit(exported.call).lower(*specs)
    _end_turn()  # traced: the next program traces while this one is printed (_keepable)
    keep = exe_path is not None and _keepable(lowered)
    with _fresh_compilation(keep) as fresh:
        compiled = _compile(lowered, name)
    _keep_executable(exe_path if fresh() and keep else None, compiled)
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


def _executable_path(folder: Path, name: str, digest: str) -> tuple[Path, str] | None:
    """The ``.jaxexe`` file and digest of the executable of the program of ``digest`` on
    this machine, or None in a ``jax.distributed`` run (each process's devices differ; see
    ``dampax._studies._distributed.compile_cached_here``)."""
    if jax.process_count() > 1:
        return None
    exe_digest = hashlib.sha256((digest + _machine_text()).encode()).hexdigest()
    return folder / f"{name}-{exe_digest[:32]}.jaxexe", exe_digest


def _load_executable(where, devices=None):
    """(executable, extra) of a file written by :func:`_keep_executable`, or None.

    Loading skips what a kept ``jax.export`` program still costs a repeated command: lowering
    it (a few tenths of a second per program) and hashing it for JAX's persistent cache.
    """
    if where is None:
        return None
    path, digest = where
    prepare_loading_beside()  # (scipy's import under Python's lock, the load without it)
    ahead = prefetched(path, digest) if devices is None else None
    entry = (ahead[0], b"") if ahead is not None else _read_entry(path, digest)
    if entry is None:
        return None
    header, payload = entry
    try:
        prepare_loading()
        in_tree, out_tree, extra = _load_tree(header["trees"].encode())
        executable = load_executable_bytes(payload, in_tree, out_tree, devices,
                                           ahead[1] if ahead is not None else None)
    except Exception:  # noqa: BLE001 - verified, yet not loadable here: the kept program
        _set_aside(path, "it could not be loaded on this machine")
        return None
    note_used(path)
    return executable, (extra if header.get("extra") else None)


#: custom calls an executable may make and still be kept: XLA's sharding markers, and LAPACK
#: (its function pointers are set by :func:`prepare_loading` before a kept executable loads)
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


@contextlib.contextmanager
def _fresh_compilation(kept: bool = False):
    """Yields a function that tells whether no program compiled in the block came from JAX's
    persistent cache. Only an executable compiled here may be kept by :func:`_keep_executable`:
    one read from that cache serializes without its kernels (jaxlib 0.10: "Function ... not
    found" when the copy runs).

    Arguments:
        kept: the program will be kept as its own file: JAX's cache does not write it too
            (in this thread only). A second copy cost a cold fit 0.8 s of its 2 cores
            (serialized and compressed again, issue 36), and it is worse than none: a later
            process that traces the program again (dampax's source changed, not the program)
            reads it from there, and such an executable cannot be kept.
    """
    from jax._src import config

    hits = []

    def listener(event, **kwargs):
        if event == "/jax/compilation_cache/cache_hits":
            hits.append(event)

    jax.monitoring.register_event_listener(listener)
    writes = config.persistent_cache_min_compile_time_secs(math.inf) if kept else \
        contextlib.nullcontext()
    try:
        with writes:
            yield lambda: not hits
    finally:
        jax.monitoring.unregister_event_listener(listener)


def _keep_executable(where, executable, extra=None) -> None:
    """Write ``executable`` and ``extra`` (a treedef and static leaves, or None) to the
    ``.jaxexe`` file of ``where`` (see :func:`_executable_path`), verified and atomically;
    nothing when it cannot be serialized or written."""
    if where is None:
        return
    kept = executable_header(executable, extra)
    if kept is not None:
        _write_entry(where[0], where[1], *kept)
        note_used(where[0])


_EXECUTABLES: dict = {}  # (name, repr(key), specs) -> (compiled, treedef, static)
#: held while a memo is looked up and claimed (:func:`_claim`)
_MEMO_LOCK = threading.Lock()


def _spec_text(specs) -> list:
    """What of the argument specs determines a program: shapes, dtypes, weak types."""
    return [(s.shape, str(s.dtype), bool(getattr(s, "weak_type", False))) for s in specs]


def _flat_tracer(fn, name: str):
    """(flat_fn, traced): ``fn`` flattened to its array leaves, named ``name`` (in JAX's
    compilation logs and profiles); tracing flat_fn records in ``traced`` the output's
    treedef, its other leaves and the arrays' weak types."""
    traced = {}

    def flat_fn(*args):
        leaves, treedef = jax.tree_util.tree_flatten(fn(*args))
        arrays = [leaf for leaf in leaves if isinstance(leaf, jax.Array)]
        traced["treedef"] = treedef
        traced["static"] = {i: leaf for i, leaf in enumerate(leaves)
                            if not isinstance(leaf, jax.Array)}
        traced["weak"] = tuple(bool(jax.typeof(a).weak_type) for a in arrays)
        return arrays

    flat_fn.__name__ = flat_fn.__qualname__ = name.replace("-", "_")
    return flat_fn, traced


def _kept_tree(traced) -> tuple:
    """(treedef, static, weak) of a traced flat_fn; raises when the tree cannot be kept."""
    kept = (traced["treedef"], traced["static"], traced["weak"])
    if _load_tree(_dump_tree(kept)) != kept:
        raise ValueError("the tree does not survive its JSON form")
    return kept


def _export_tree(name: str, fn, specs):
    """(exported program, treedef, static leaves, weak types) of ``fn`` flattened to arrays;
    raises when it cannot be exported or its tree kept."""
    flat_fn, traced = _flat_tracer(fn, name)
    exported = jax.export.export(jax.jit(flat_fn))(*specs)
    return exported, *_kept_tree(traced)


def _compile_kept(name: str, fn, specs, exe_path):
    """(executable, treedef, static) of ``fn`` compiled straight from its trace and kept as
    its ``.jaxexe`` file, or None where that cannot be (no executable file, a program that
    may not be kept, a tree that cannot, an executable read from JAX's cache): the caller
    then keeps the ``jax.export`` program. The direct route skips exporting, serializing and
    lowering the exported program again (0.5-1 s of a cold fit's program, issue 36)."""
    if exe_path is None:
        return None
    flat_fn, traced = _flat_tracer(fn, name)
    try:
        lowered = jax.jit(flat_fn).lower(*specs)
        treedef, static, _ = _kept_tree(traced)
    except Exception:  # noqa: BLE001 - the export route decides (and raises what it must)
        return None
    held = getattr(_HOLDS, "turn", False)
    _end_turn()  # the next program traces while this one is printed for its custom calls
    if not _keepable(lowered):
        if held:  # the export route traces again, in its turn
            _begin_turn()
        return None
    with _fresh_compilation(kept=True) as fresh:
        executable = _compile(lowered, name)
    if not fresh():
        return None
    _keep_executable(exe_path, executable, (treedef, static))
    return executable, treedef, static


def _compile_tree(name: str, key, fn, specs):
    """(executable, treedef, static) of ``fn`` for ``specs``: a kept executable loaded
    without the tracing turn (:func:`_kept_executable_tree`), else :func:`_compile_tree_turn`
    in its turn (:func:`_turn`)."""
    folder = exported_dir()
    digest = None if folder is None else _digest(_program_text(key, specs, name))
    kept = _kept_executable_tree(folder, name, digest)
    if kept is not None:
        return kept
    with _turn():
        return _compile_tree_turn(name, fn, specs, folder, digest)


def _kept_executable_tree(folder, name: str, digest):
    """(executable, treedef, static) of a kept executable of the program, or None.

    Loading traces nothing, so it does not wait for the tracing turn: a repeated command's
    programs load side by side in the compile threads, each ready as soon as its own file is
    read, where in turns the first one the fit calls waited for those asked before it (the
    exact model's fit, the longest to load: 0.35 s of ``dampax fit --example``)."""
    if folder is None:
        return None
    loaded = _load_executable(_executable_path(folder, name, digest))
    if loaded is None or loaded[1] is None:
        return None
    executable, (treedef, static) = loaded
    return executable, treedef, static


def _compile_tree_turn(name: str, fn, specs, folder, digest):
    """(executable, treedef, static): ``fn`` compiled for ``specs``, kept as a file.

    The kept program returns the array leaves of ``fn``'s output; its treedef and its other
    leaves (Python values fixed at tracing) are kept beside it as JSON, so any pytree (equinox
    modules, named tuples) comes back whole. Without a cache folder, or when the program or
    its treedef cannot be kept, the executable is compiled in-process (treedef None: it
    returns the pytree itself).

    Arguments:
        folder: the cache folder (``exported_dir()``), or None.
        digest: the digest of the program's text (``_program_text``), or None without one.
    """
    plain = jax.jit(fn)
    if folder is None:
        return _compile(plain.lower(*specs), name), None, None
    path = folder / f"{name}-{digest[:32]}.jaxcall"
    exe_path = _executable_path(folder, name, digest)
    exported = None
    entry = _read_entry(path, digest)
    if entry is not None:
        try:
            treedef, static, weak = _load_tree(entry[0]["trees"].encode())
            exported = jax.export.deserialize(bytearray(entry[1]))
        except Exception:  # noqa: BLE001 - verified, yet not readable here: trace again
            exported = None
    if exported is None:
        kept = _compile_kept(name, fn, specs, exe_path)
        if kept is not None:
            return kept
        try:
            exported, treedef, static, weak = _export_tree(name, fn, specs)
            payload = exported.serialize()
            exported = jax.export.deserialize(payload)  # the program a later process reads
        except Exception:  # noqa: BLE001 - not exportable: the plain route
            return _compile(plain.lower(*specs), name), None, None
        _write_entry(path, digest, {"kind": "jaxcall", "trees": _dump_tree(
            (treedef, static, weak)).decode()}, bytes(payload))

    def call(*args):  # the outputs' weak types, lost in serialization, restored (no-op)
        return [_weak(a) if w else a for a, w in zip(exported.call(*args), weak, strict=True)]

    lowered = jax.jit(call).lower(*specs)
    _end_turn()  # traced: the next program traces while this one is printed (_keepable)
    keep = exe_path is not None and _keepable(lowered)
    with _fresh_compilation(keep) as fresh:
        executable = _compile(lowered, name)
    _keep_executable(exe_path if fresh() and keep else None, executable, (treedef, static))
    return executable, treedef, static


def _weak(x):
    """``x`` as a weakly typed array of the same dtype and values (inside a trace)."""
    from jax._src.lax.lax import _convert_element_type

    return _convert_element_type(x, None, weak_type=True)


def _memo(name: str, key, args):
    """(arrays, specs, memo) of a call of :func:`call_cached`: the memo names its program."""
    # numpy arrays go to the program as they are (strongly typed; a jnp.asarray per leaf
    # cost a fit's call of 26 leaves 6-11 ms of Python), anything else as a JAX array
    arrays = [a if isinstance(a, np.ndarray) else jnp.asarray(a) for a in args]
    specs = tuple(jax.ShapeDtypeStruct(a.shape, a.dtype,
                                       weak_type=getattr(a, "weak_type", False))
                  for a in arrays)
    return arrays, specs, (name, repr(key), tuple(map(tuple, _spec_text(specs))))


def prepare_cached(name: str, key, fn, *args) -> None:
    """Start building the program of ``call_cached(name, key, fn, *args)`` in a background
    thread, so that it compiles while the caller does other work; its first call then waits
    for it (nothing else changes: the same memo, files and executable).

    XLA compiles with Python's lock released: on 2 cores a fit whose next programs compile
    beside the current one's work pays about half of their compiling (issue 36: a cold
    default fit compiled three programs of 3-6 s one after the other). Only the arguments'
    shapes and types matter; ``args`` may hold any values. A program already built or being
    built is not started again; an error in the thread is raised by neither: the first call
    then builds the program itself.
    """
    _, specs, memo = _memo(name, key, args)
    if memo in _EXECUTABLES:
        return
    if _kept_file(name, key, specs):  # loaded, not compiled: by the loader or its caller
        job = _claim(memo, name, key, fn, specs)
        if job is not None:
            _loader().submit(job.run)
    else:
        with _MEMO_LOCK:
            if memo not in _EXECUTABLES:
                _EXECUTABLES[memo] = _pool().submit(_compile_tree, name, key, fn, specs)


def _claim(memo, name: str, key, fn, specs):
    """The new :class:`_Claimable` build of the memo's program, entered in the memo; None
    where the memo already holds the program or its build. Whoever needs a program first
    claims it, so that two threads asking for it at once wait for one build (the model
    ranking beside ``dampax fit``'s fit loaded the approximate model's 1.9 MB program a
    second time beside the loader thread: 1.3 s of CPU on 2 cores)."""
    with _MEMO_LOCK:
        if memo in _EXECUTABLES:
            return None
        job = _EXECUTABLES[memo] = _Claimable(_compile_tree, name, key, fn, specs)
        return job


def _kept_file(name: str, key, specs) -> bool:
    """Whether the program has a kept executable file on this machine (:func:`_keep_executable`)."""
    folder = exported_dir()
    if folder is None:
        return False
    where = _executable_path(folder, name, _digest(_program_text(key, specs, name)))
    return where is not None and where[0].is_file()


def finish_background() -> None:
    """Wait for every program still being built in the background (:func:`prepare_cached`),
    so that each is compiled and kept for the next process; an error is left to the call
    that would have needed the program. A process that ends with ``os._exit`` (the console
    script, ``dampax_cli.console``) calls this first: a normal exit joins the compile
    threads, which finish their queue."""
    for entry in list(_EXECUTABLES.values()):
        if hasattr(entry, "result"):
            with contextlib.suppress(Exception):
                entry.result()


def _entry(name: str, key, fn, specs, memo):
    """The memo's (executable, treedef, static), built now or awaited from the thread that
    builds it (:func:`prepare_cached`'s, or another caller's)."""
    mine = _claim(memo, name, key, fn, specs) if memo not in _EXECUTABLES else None
    if mine is not None:  # built here; a thread that asks meanwhile waits for it
        try:
            entry = mine.result()
        except BaseException:
            with _MEMO_LOCK:  # the next call builds it again (and raises what it must)
                if _EXECUTABLES.get(memo) is mine:
                    del _EXECUTABLES[memo]
            raise
        _EXECUTABLES[memo] = entry
        return entry
    entry = _EXECUTABLES.get(memo)
    if hasattr(entry, "result"):  # being built in the background
        held = getattr(_HOLDS, "turn", False)
        if held:  # (a trace that calls a kept program) the builder may need the turn
            _end_turn()
        try:
            entry = entry.result()
        except Exception:  # noqa: BLE001 - built again here, where an error is raised
            entry = None
        if held:
            _begin_turn()
    if entry is None:
        entry = _compile_tree(name, key, fn, specs)
    _EXECUTABLES[memo] = entry
    return entry


def call_cached(name: str, key, fn, *args):
    """``fn(*args)`` for concrete arrays, through a kept compiled program (eager calls only).

    The executable is kept for the life of the process (so a second call neither traces nor
    compiles) and, as a ``jax.export`` file with the output's tree structure beside it (in
    ``exported/``, keyed by ``key``, the argument specs, the devices, dampax's source and the
    versions it runs on) plus JAX's persistent compilation cache, across processes: a
    repeated command-line call deserializes the program instead of tracing it. Without a
    cache directory (``DAMPAX_CACHE=0``) only the in-process memo is kept. A program started
    by :func:`prepare_cached` is awaited.

    Arguments:
        name: a readable prefix of the cached file's name.
        key: a hashable description of everything static that ``fn`` closes over (its repr
            must determine the program).
        fn: a function of the flat arrays ``args`` returning a pytree: arrays in standard
            containers, named tuples or equinox modules (static fields and non-array leaves
            must be plain values: strings, numbers, classes of dampax or equinox).
        args: concrete arrays (or scalars), positional; weak types are kept.

    Returns:
        ``fn(*args)``, computed by the compiled program.
    """
    arrays, specs, memo = _memo(name, key, args)
    executable, treedef, static = _entry(name, key, fn, specs, memo)
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
    return call_cached(*_flat_call(name, key, fn, args))


def prepare_cached_tree(name: str, key, fn, *args) -> None:
    """:func:`prepare_cached` for the pytree arguments of :func:`call_cached_tree`."""
    prepare_cached(*_flat_call(name, key, fn, args))


def kept_arrays(name: str, key, make) -> dict:
    """``make()``, a dict of numpy arrays, kept as a verified ``.npz`` in ``exported/``
    (the checks of every cache file: the folder, the digest of ``key``, dampax's source and
    the machine, the HMAC) and read back by later processes without pickle; computed
    afresh without a cache. For deterministic results that take a compiled program to make
    (``dampax fit --example``'s synthetic trace: 0.4 s a command).

    Arguments:
        name: a readable prefix of the file's name.
        key: a description of everything ``make``'s result depends on (its repr).
        make: a function of no arguments returning {name: numpy array}.
    """
    folder = exported_dir()
    if folder is None:
        return make()
    digest = _digest(repr(("arrays", name, key)) + _machine_text())
    path = folder / f"{name}-{digest[:32]}.npz"
    entry = _read_entry(path, digest)
    if entry is not None:
        with contextlib.suppress(ValueError, OSError, KeyError):
            with np.load(io.BytesIO(entry[1]), allow_pickle=False) as data:
                return {k: data[k] for k in data.files}
    out = make()
    buffer = io.BytesIO()
    np.savez(buffer, **out)
    _write_entry(path, digest, {"kind": "arrays"}, buffer.getvalue())
    return out


def _flat_call(name: str, key, fn, args) -> tuple:
    """(name, key, flat fn, *leaves): :func:`call_cached_tree`'s call of :func:`call_cached`."""
    leaves, treedef = jax.tree_util.tree_flatten(args)

    def flat(*values):
        return fn(*jax.tree_util.tree_unflatten(treedef, values))

    return (name, (key, str(treedef)), flat, *leaves)
