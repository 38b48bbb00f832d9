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
nor hashes it for JAX's cache.

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
import hmac
import io
import json
import os
import stat
import sys
import tempfile
import time
import warnings
from pathlib import Path

import jax
import jax.export  # noqa: F401 (jax 0.7 does not import this submodule itself)
import jax.numpy as jnp

from ._io import atomic_file

_OFF = ("0", "off", "false", "no")
_MIN_COMPILE_S = 0.5
#: the largest cache file read (an error-map step's executable is a few MB)
MAX_FILE_BYTES = 1 << 30
_MAGIC = b"dampax cache 2\n"
_TAG = 32  # bytes of HMAC-SHA256


class CacheWarning(UserWarning):
    """A folder or file of dampax's cache was refused (not the user's own, writable by others,
    damaged, or built for other settings): it is not used, and the program is built again."""


_WARNED: set[str] = set()


def _warn(text: str) -> None:
    """One :class:`CacheWarning` per distinct message and process."""
    if text not in _WARNED:
        _WARNED.add(text)
        warnings.warn(text, CacheWarning, stacklevel=3)


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


def _owner_problem(st: os.stat_result, *, private: bool = False) -> str | None:
    """Why a file or folder with this ``stat`` is not safe to trust, or None: not the user's
    own, or writable by others (``private``: readable by others)."""
    if os.name == "nt":
        return None  # no POSIX owners; the user's profile folder is private by default
    if st.st_uid != os.getuid():
        return f"it belongs to user id {st.st_uid}, not to you ({os.getuid()})"
    if st.st_mode & (0o077 if private else 0o022):
        return f"other users can {'read' if private else 'write'} it (mode {st.st_mode & 0o777:o})"
    return None


def secure_folder(path: Path) -> bool:
    """Make ``path`` (``0o700``) if needed; whether the cache may use it.

    A folder that is not the user's own, or that others can write, is refused with a
    :class:`CacheWarning` (a file planted there would run as the user's code).
    """
    try:
        path.mkdir(mode=0o700, parents=True, exist_ok=True)
        st = path.stat()
    except OSError:
        return False  # a read-only home: run without the cache rather than fail
    problem = None if stat.S_ISDIR(st.st_mode) else "it is not a folder"
    problem = problem or _owner_problem(st)
    if problem:
        _warn(f"dampax: not using the cache folder {str(path)!r}: {problem}; a program planted "
              "there would run as your code. Set DAMPAX_CACHE_DIR to a folder of your own, or "
              "DAMPAX_CACHE=0.")
        return False
    return True


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
        _sweep(dampax_cache_dir() / "exported")
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", _MIN_COMPILE_S)
    return path


def _sweep(folder: Path) -> None:
    """Move aside what in JAX's cache folder is not a regular file of the user's own (a FIFO
    would hang JAX's read, a link could point anywhere, another user's file could hold any
    machine code) and temporary files that writers killed mid-write left (older than an hour).
    JAX reads its own entries without a check of its own; a damaged regular entry fails its
    decompression and JAX compiles again."""
    now = time.time()
    with contextlib.suppress(OSError), os.scandir(folder) as entries:
        for entry in entries:
            with contextlib.suppress(OSError):
                st = entry.stat(follow_symlinks=False)
                if stat.S_ISDIR(st.st_mode):
                    continue  # rejected/, or JAX's own
                if stat.S_ISREG(st.st_mode):
                    problem = _owner_problem(st)
                    stale = (".tmp" in entry.name or ".part" in entry.name) and (
                        now - st.st_mtime > 3600)
                    if problem is None and stale:  # its writer was killed mid-write
                        os.unlink(entry.path)
                        continue
                else:
                    problem = "it is not a regular file"
                if problem:
                    _set_aside(Path(entry.path), problem)


def _set_aside(path: Path, reason: str) -> None:
    """Move a refused cache file to ``rejected/`` beside it (removed if that fails), with a
    :class:`CacheWarning`; its program is built again."""
    aside = path.parent / "rejected"
    try:
        aside.mkdir(mode=0o700, exist_ok=True)
        os.replace(path, aside / f"{path.name}.{os.getpid()}.{time.time_ns()}")
    except OSError:
        with contextlib.suppress(OSError):
            path.unlink()
    _warn(f"dampax: cache file {str(path)!r} refused and set aside: {reason}; its program is "
          "built again")


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
# verified files: a digest of what shaped the program and an HMAC under the user's own key


@functools.lru_cache(maxsize=1)
def _source_digest() -> str:
    """Digest of dampax's own source files and of the versions and machine it runs on."""
    import importlib.metadata as metadata

    h = hashlib.sha256()
    for package in ("jax", "jaxlib", "equinox", "optimistix", "lineax", "numpy"):
        try:
            h.update(f"{package} {metadata.version(package)};".encode())
        except metadata.PackageNotFoundError:
            h.update(f"{package} -;".encode())
    device = jax.devices()[0]
    h.update(repr((device.platform, device.device_kind, device.client.platform_version,
                   os.environ.get("XLA_FLAGS", ""), sys.version_info[:2])).encode())
    root = Path(__file__).parent
    for path in sorted(root.rglob("*.py")):
        h.update(str(path.relative_to(root)).encode())
        h.update(path.read_bytes())
    return h.hexdigest()


def _digest(text: str) -> str:
    """The digest of a program described by ``text`` in this environment (the file's name
    and its header both carry it)."""
    extra = repr((jax.config.jax_enable_x64, jax.config.jax_default_matmul_precision))
    return hashlib.sha256((text + extra + _source_digest()).encode()).hexdigest()


@functools.lru_cache(maxsize=8)
def _key(folder: str) -> bytes | None:
    """The user's secret key of the cache in ``folder`` (made on first use), or None."""
    path = Path(folder) / "key"
    for _ in range(3):
        data = _read_regular(path, private=True)
        if data is not None and len(data) == _TAG:
            return data
        if data is not None:
            _set_aside(path, "a key must be 32 bytes")
        try:
            fd, tmp = tempfile.mkstemp(prefix=".key.", suffix=".tmp", dir=folder)
            try:
                os.write(fd, os.urandom(_TAG))
            finally:
                os.close(fd)
            try:
                os.link(tmp, path)  # fails if another process made the key first: read it
            except FileExistsError:
                pass
            finally:
                os.unlink(tmp)
        except OSError:
            return None
    return None


def _read_regular(path: Path, *, private: bool = False) -> bytes | None:
    """The bytes of ``path`` if it is a regular file of the user's own that others cannot
    write (``private``: nor read), at most :data:`MAX_FILE_BYTES`; None if it does not exist.
    Anything else is set aside (:func:`_set_aside`) without being read: a FIFO does not block
    (``O_NONBLOCK``), a link is not followed (``O_NOFOLLOW``)."""
    flags = os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0)
    try:
        fd = os.open(path, flags | getattr(os, "O_BINARY", 0))
    except FileNotFoundError:
        return None
    except OSError as err:
        _set_aside(path, f"it cannot be opened safely ({err.strerror}: a link?)")
        return None
    try:
        st = os.fstat(fd)
        problem = None if stat.S_ISREG(st.st_mode) else "it is not a regular file"
        problem = problem or _owner_problem(st, private=private)
        if problem is None and st.st_size > MAX_FILE_BYTES:
            problem = f"it is larger than {MAX_FILE_BYTES} bytes"
        if problem:
            _set_aside(path, problem)
            return None
        chunks, left = [], st.st_size
        while left > 0:
            chunk = os.read(fd, min(left, 1 << 24))
            if not chunk:
                break
            chunks.append(chunk)
            left -= len(chunk)
        return b"".join(chunks)
    finally:
        os.close(fd)


def _read_entry(path: Path, digest: str) -> tuple[dict, bytes] | None:
    """The (header, payload) of a cache file written by :func:`_write_entry` for the program
    of ``digest``, after its checks; None when absent or refused (set aside)."""
    folder = path.parent
    if not path.exists() and not path.is_symlink():
        return None
    key = _key(str(dampax_cache_dir()))
    if key is None or not secure_folder(folder):
        return None
    data = _read_regular(path)
    if data is None:
        return None
    body, tag = data[:-_TAG], data[-_TAG:]
    if (len(data) < len(_MAGIC) + 8 + _TAG or not body.startswith(_MAGIC)
            or not hmac.compare_digest(hmac.new(key, body, hashlib.sha256).digest(), tag)):
        _set_aside(path, "its checksum does not verify (damaged, or not written by dampax for "
                         "you)")
        return None
    size = int.from_bytes(body[len(_MAGIC):len(_MAGIC) + 8], "little")
    start = len(_MAGIC) + 8
    try:
        header = json.loads(body[start:start + size].decode())
    except ValueError:
        header = None
    if not isinstance(header, dict) or header.get("digest") != digest:
        _set_aside(path, "it was built for other settings or versions")
        return None
    return header, body[start + size:]


def _write_entry(path: Path, digest: str, header: dict, payload: bytes) -> None:
    """Write a verified cache file (see :func:`_read_entry`) atomically; nothing when the
    folder is not safe or not writable."""
    folder = path.parent
    key = _key(str(dampax_cache_dir()))
    if key is None or not secure_folder(folder):
        return
    head = json.dumps(dict(header, digest=digest)).encode()
    body = _MAGIC + len(head).to_bytes(8, "little") + head + payload
    with contextlib.suppress(OSError), atomic_file(path, alone=True) as fh:
        fh.write(body + hmac.new(key, body, hashlib.sha256).digest())


# ----------------------------------------------------------------------------------------------
# tree structures as JSON: no pickle, classes only from dampax, equinox and the containers

_CLASS_PACKAGES = ("dampax", "equinox", "collections", "builtins", "jax", "jaxlib", "numpy")


def _missing():
    """equinox's MISSING sentinel (a treedef's auxiliary data holds it)."""
    from equinox._module._flatten import MISSING

    return MISSING


def _encode(obj):
    """A JSON value for ``obj``: plain values, containers, classes of :data:`_CLASS_PACKAGES`
    and equinox's MISSING; TypeError for anything else (then the program is not kept)."""
    import numpy as np

    if obj is None or isinstance(obj, bool | str) or type(obj) is int:
        return obj
    if type(obj) is float:
        return {"f": obj.hex()}
    if isinstance(obj, np.generic):
        return {"g": [obj.dtype.str, _encode(obj.item())]}
    if type(obj) in (tuple, list):
        return {type(obj).__name__[0]: [_encode(x) for x in obj]}
    if type(obj) is dict:
        return {"d": [[_encode(k), _encode(v)] for k, v in obj.items()]}
    if obj is _missing():
        return {"m": 0}
    if isinstance(obj, type) and obj.__module__.split(".")[0] in _CLASS_PACKAGES:
        return {"c": [obj.__module__, obj.__qualname__]}
    if isinstance(obj, jax.tree_util.PyTreeDef):
        return {"p": _tree_json(obj)}
    raise TypeError(f"cannot keep {type(obj).__name__} in a cache file")


def _decode(value):
    """Inverse of :func:`_encode`; a class only of :data:`_CLASS_PACKAGES`, and only one
    already imported."""
    import numpy as np

    if not isinstance(value, dict):
        return value
    (tag, item), = value.items()
    if tag == "f":
        return float.fromhex(item)
    if tag == "g":
        return np.dtype(item[0]).type(_decode(item[1]))
    if tag in ("t", "l"):
        items = [_decode(x) for x in item]
        return tuple(items) if tag == "t" else items
    if tag == "d":
        return {_decode(k): _decode(v) for k, v in item}
    if tag == "m":
        return _missing()
    if tag == "p":
        return _tree_from_json(item)
    if tag == "c":
        module, name = item
        if module.split(".")[0] not in _CLASS_PACKAGES:
            raise ValueError(f"a cache file names the class {module}.{name}")
        if (module, name) == ("builtins", "NoneType"):
            return type(None)
        obj = sys.modules.get(module)  # already imported: a cache file imports nothing
        if obj is None:
            raise ValueError(f"a cache file names {module}.{name}, not imported here")
        for part in name.split("."):
            obj = getattr(obj, part)
        if not isinstance(obj, type):
            raise ValueError(f"a cache file names {module}.{name}, not a class")
        return obj
    raise ValueError(f"unknown tag {tag!r} in a cache file")


def _tree_json(treedef):
    """A JSON value for a treedef (its node types, auxiliary data and children)."""
    node = treedef.node_data()
    if node is None:
        return "*"
    return {"n": _encode(node[0]), "a": _encode(node[1]),
            "c": [_tree_json(child) for child in treedef.children()]}


def _tree_from_json(value, registry=None):
    """Inverse of :func:`_tree_json`."""
    registry = registry or jax.tree_util.default_registry
    if value == "*":
        return jax.tree_util.tree_structure(0)
    children = [_tree_from_json(child, registry) for child in value["c"]]
    return jax.tree_util.PyTreeDef.from_node_data_and_children(
        registry, (_decode(value["n"]), _decode(value["a"])), children)


def _dump_tree(value) -> bytes:
    """JSON bytes of ``value``: treedefs, static leaves, weak types (:func:`_encode`)."""
    return json.dumps(_encode(value)).encode()


def _load_tree(data: bytes):
    """Inverse of :func:`_dump_tree`."""
    return _decode(json.loads(data.decode()))


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


def _program_text(key, specs) -> str:
    """What determines a program beyond the environment: the key, the specs, the devices."""
    devices = jax.devices()
    return repr((key, [(s.shape, str(s.dtype), str(getattr(s, "sharding", None)),
                        bool(getattr(s, "weak_type", False))) for s in specs],
                 len(devices), devices[0].platform, devices[0].device_kind))


def compile_cached(name: str, key, fn, *specs):
    """``fn.lower(*specs).compile()``, tracing ``fn`` only when no serialized program exists.

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
        return fn.lower(*specs).compile()
    digest = _digest(_program_text(key, specs))
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
            return fn.lower(*specs).compile()
        _write_entry(path, digest, {"kind": "jaxexport"}, bytes(payload))
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


def _executable_path(folder: Path, name: str, digest: str) -> tuple[Path, str] | None:
    """The ``.jaxexe`` file and digest of the executable of the program of ``digest`` on
    this machine, or None in a ``jax.distributed`` run (each process's devices differ; see
    ``dampax._studies._distributed.compile_cached_here``)."""
    if jax.process_count() > 1:
        return None
    exe_digest = hashlib.sha256((digest + _machine_text()).encode()).hexdigest()
    return folder / f"{name}-{exe_digest[:32]}.jaxexe", exe_digest


#: what an executable's pickle (``jax.experimental.serialize_executable``) may name: classes
#: of these packages, their ``_unpickle*`` helpers, numpy's array helpers, plain containers
_EXECUTABLE_PACKAGES = ("jax", "jaxlib", "numpy")
_NUMPY_HELPERS = ("_reconstruct", "scalar")
_SAFE_BUILTINS = {("builtins", name) for name in (
    "frozenset", "set", "slice", "complex", "tuple", "list", "dict", "bytearray", "range")}


def _restricted_unpickler():
    """jax's executable unpickler, admitting only classes (and ``_unpickle*`` helpers) defined
    in jax, jaxlib and numpy: a verified file still cannot name ``os.system``."""
    import pickle

    from jax.experimental import serialize_executable

    class Unpickler(serialize_executable._JaxPjrtUnpickler):
        def find_class(self, module, name):
            if (module, name) in _SAFE_BUILTINS:
                return super().find_class(module, name)
            if module.split(".")[0] in _EXECUTABLE_PACKAGES and "." not in name:
                obj = super().find_class(module, name)
                home = getattr(obj, "__module__", "") or ""
                if home.split(".")[0] in _EXECUTABLE_PACKAGES and (
                        isinstance(obj, type) or name in _NUMPY_HELPERS
                        or name.startswith("_unpickle")):
                    return obj
            raise pickle.UnpicklingError(f"not part of a jax executable: {module}.{name}")

    return Unpickler


def load_executable_bytes(payload: bytes, in_tree, out_tree, devices=None):
    """``serialize_executable.deserialize_and_load`` through :func:`_restricted_unpickler`
    (call only with bytes whose HMAC verified)."""
    backend = jax.devices()[0].client
    devices = devices or backend.devices()
    unloaded, args_info_flat, no_kwargs = _restricted_unpickler()(
        io.BytesIO(payload), backend, devices).load()
    return jax.stages.Compiled(unloaded.load(), [], in_tree.unflatten(args_info_flat),
                               out_tree, no_kwargs=no_kwargs)


def _load_executable(where, devices=None):
    """(executable, extra) of a file written by :func:`_keep_executable`, or None.

    Loading skips what a kept ``jax.export`` program still costs a repeated command: lowering
    it (a few tenths of a second per program) and hashing it for JAX's persistent cache.
    """
    if where is None:
        return None
    path, digest = where
    entry = _read_entry(path, digest)
    if entry is None:
        return None
    header, payload = entry
    try:
        _prepare_loading()
        in_tree, out_tree, extra = _load_tree(header["trees"].encode())
        executable = load_executable_bytes(payload, in_tree, out_tree, devices)
    except Exception:  # noqa: BLE001 - verified, yet not loadable here: the kept program
        _set_aside(path, "it could not be loaded on this machine")
        return None
    return executable, (extra if header.get("extra") else None)


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


def executable_header(executable, extra=None) -> tuple[dict, bytes] | None:
    """(header, payload) of a kept executable: its trees (and ``extra``: a treedef and static
    leaves) as JSON, and jax's serialization; None when it cannot be serialized."""
    try:
        from jax.experimental import serialize_executable

        payload, in_tree, out_tree = serialize_executable.serialize(executable)
        trees = (in_tree, out_tree, extra if extra is not None else ())
        blob = _dump_tree(trees)
        if _load_tree(blob) != trees:
            return None
    except Exception:  # noqa: BLE001 - not serializable: not kept
        return None
    return {"kind": "jaxexe", "trees": blob.decode(), "extra": extra is not None}, payload


def _keep_executable(where, executable, extra=None) -> None:
    """Write ``executable`` and ``extra`` (a treedef and static leaves, or None) to the
    ``.jaxexe`` file of ``where`` (see :func:`_executable_path`), verified and atomically;
    nothing when it cannot be serialized or written."""
    if where is None:
        return
    kept = executable_header(executable, extra)
    if kept is not None:
        _write_entry(where[0], where[1], *kept)


_EXECUTABLES: dict = {}  # (name, repr(key), specs) -> (compiled, treedef, static)


def _spec_text(specs) -> list:
    """What of the argument specs determines a program: shapes, dtypes, weak types."""
    return [(s.shape, str(s.dtype), bool(getattr(s, "weak_type", False))) for s in specs]


def _export_tree(fn, specs):
    """(exported program, treedef, static leaves, weak types) of ``fn`` flattened to arrays;
    raises when it cannot be exported or its tree kept."""
    traced = {}

    def flat_fn(*args):
        leaves, treedef = jax.tree_util.tree_flatten(fn(*args))
        arrays = [leaf for leaf in leaves if isinstance(leaf, jax.Array)]
        traced["treedef"] = treedef
        traced["static"] = {i: leaf for i, leaf in enumerate(leaves)
                            if not isinstance(leaf, jax.Array)}
        traced["weak"] = tuple(bool(jax.typeof(a).weak_type) for a in arrays)
        return arrays

    exported = jax.export.export(jax.jit(flat_fn))(*specs)
    kept = (traced["treedef"], traced["static"], traced["weak"])
    if _load_tree(_dump_tree(kept)) != kept:
        raise ValueError("the tree does not survive its JSON form")
    return exported, *kept


def _compile_tree(name: str, key, fn, specs):
    """(executable, treedef, static): ``fn`` compiled for ``specs``, kept as a file.

    The kept program returns the array leaves of ``fn``'s output; its treedef and its other
    leaves (Python values fixed at tracing) are kept beside it as JSON, so any pytree (equinox
    modules, named tuples) comes back whole. Without a cache folder, or when the program or
    its treedef cannot be kept, the executable is compiled in-process (treedef None: it
    returns the pytree itself).
    """
    folder = exported_dir()
    plain = jax.jit(fn)
    if folder is None:
        return plain.lower(*specs).compile(), None, None
    digest = _digest(_program_text(key, specs))
    path = folder / f"{name}-{digest[:32]}.jaxcall"
    exe_path = _executable_path(folder, name, digest)
    loaded = _load_executable(exe_path)
    if loaded is not None and loaded[1] is not None:
        executable, (treedef, static) = loaded
        return executable, treedef, static
    exported = None
    entry = _read_entry(path, digest)
    if entry is not None:
        try:
            treedef, static, weak = _load_tree(entry[0]["trees"].encode())
            exported = jax.export.deserialize(bytearray(entry[1]))
        except Exception:  # noqa: BLE001 - verified, yet not readable here: trace again
            exported = None
    if exported is None:
        try:
            exported, treedef, static, weak = _export_tree(fn, specs)
            payload = exported.serialize()
            exported = jax.export.deserialize(payload)  # the program a later process reads
        except Exception:  # noqa: BLE001 - not exportable: the plain route
            return plain.lower(*specs).compile(), None, None
        _write_entry(path, digest, {"kind": "jaxcall", "trees": _dump_tree(
            (treedef, static, weak)).decode()}, bytes(payload))

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
    compiles) and, as a ``jax.export`` file with the output's tree structure beside it (in
    ``exported/``, keyed by ``key``, the argument specs, the devices, dampax's source and the
    versions it runs on) plus JAX's persistent compilation cache, across processes: a
    repeated command-line call deserializes the program instead of tracing it. Without a
    cache directory (``DAMPAX_CACHE=0``) only the in-process memo is kept.

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
