"""The files of dampax's cache: safe folders, verified entries, tree structures as JSON, and
jax's executables read through a restricted unpickler (docs/DESIGN.md, "The cache and the
outputs"; ``_cache`` uses them for the kept programs).

A folder is used only when it is the user's own and others cannot write it
(:func:`secure_folder`); every file is ``MAGIC | length | JSON header | payload | HMAC-SHA256``
under a private key (:func:`_write_entry`, :func:`_read_entry`), opened without following links
or blocking, and set aside (:func:`_set_aside`) when any check fails.
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

from ._io import atomic_file

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


def _sweep(folder: Path, kept: bool = False) -> None:
    """Move aside what in JAX's cache folder is not a regular file of the user's own (a FIFO
    would hang JAX's read, a link could point anywhere, another user's file could hold any
    machine code) and temporary files that writers killed mid-write left (older than an hour).
    JAX reads its own entries without a check of its own; a damaged regular entry fails its
    decompression and JAX compiles again. ``kept``: the folder of dampax's kept programs, whose
    size is held to :func:`cache_limit` (:func:`_trim`)."""
    now = time.time()
    files = []
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
                    if problem is None:  # last used: its access time, set when loaded
                        files.append((max(st.st_atime, st.st_mtime), st.st_size, entry.path))
                else:
                    problem = "it is not a regular file"
                if problem:
                    _set_aside(Path(entry.path), problem)
    if kept:
        _trim(files, cache_limit())


#: the default size of the kept programs' folder (``DAMPAX_CACHE_MAX_MB``)
CACHE_MAX_MB = 2048


def cache_limit() -> int:
    """The most bytes the kept programs may take: ``DAMPAX_CACHE_MAX_MB`` (a number of MiB,
    0 for no limit) or :data:`CACHE_MAX_MB`."""
    text = os.environ.get("DAMPAX_CACHE_MAX_MB", "").strip()
    try:
        mb = float(text) if text else CACHE_MAX_MB
    except ValueError:
        _warn(f"dampax: DAMPAX_CACHE_MAX_MB={text!r} is not a number of MiB; "
              f"using {CACHE_MAX_MB}")
        mb = CACHE_MAX_MB
    return int(mb * (1 << 20)) if mb > 0 else 0


def _trim(files: list, limit: int) -> None:
    """Where the (last used, size, path) ``files`` take more than ``limit`` bytes (0: no
    limit), remove the least recently used (a kept program's access time is set each time it is
    loaded, :func:`_read_entry`; its modification time stays) until they take at most 3/4 of
    it. Every change of dampax or of the versions it runs on keeps a new set of programs
    (about 30 MB for a fit's); the old ones are never read again, and grew this folder to 343 MB
    on a developer's machine. A program removed while another process needs it is built again
    there."""
    total = sum(size for _, size, _ in files)
    if not limit or total <= limit:
        return
    for _, size, path in sorted(files):
        if total <= limit * 3 // 4:
            break
        with contextlib.suppress(OSError):
            os.unlink(path)
            total -= size


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


def _read_entry(path: Path, digest: str | None) -> tuple[dict, bytes] | None:
    """The (header, payload) of a cache file written by :func:`_write_entry` for the program
    of ``digest``, after its checks; None when absent or refused (set aside). ``digest``
    None: a verified file of any program (its header's digest is compared by the caller
    before the program is used: ``dampax._cachethreads.prefetched``)."""
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
    if not isinstance(header, dict) or (digest is not None and header.get("digest") != digest):
        _set_aside(path, "it was built for other settings or versions")
        return None
    with contextlib.suppress(OSError):  # used now: the last to go (_trim); read, not written
        os.utime(path, ns=(time.time_ns(), os.stat(path).st_mtime_ns))
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


def load_executable_bytes(payload: bytes, in_tree, out_tree, devices=None, loaded=None):
    """``serialize_executable.deserialize_and_load`` through :func:`_restricted_unpickler`
    (call only with bytes whose HMAC verified); ``loaded``: what :func:`executable_parts`
    already made of ``payload`` (then it is not read again)."""
    executable, args_info_flat, no_kwargs = loaded or executable_parts(payload, devices)
    return jax.stages.Compiled(executable, [], in_tree.unflatten(args_info_flat),
                               out_tree, no_kwargs=no_kwargs)


def executable_parts(payload: bytes, devices=None):
    """(loaded executable, flat argument info, no_kwargs) of a kept executable's bytes: the
    part of :func:`load_executable_bytes` that needs no class of dampax (XLA rebuilding the
    program, with Python's lock released), so it may run while dampax imports."""
    backend = jax.devices()[0].client
    devices = devices or backend.devices()
    unloaded, args_info_flat, no_kwargs = _restricted_unpickler()(
        io.BytesIO(payload), backend, devices).load()
    return unloaded.load(), args_info_flat, no_kwargs


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


