"""The threads that build dampax's kept programs (``_cache``): the tracing turn, the pool that
compiles ahead of a program's first call, the loader of kept executables and its loads,
claimed by whoever needs one first, and a repeated command's programs loaded while dampax
imports.

**Loaded while dampax imports.** Loading a kept executable is XLA rebuilding its program
(0.1-0.4 s each, Python's lock released), and a repeated ``dampax fit --example`` loads six,
most while its fit waits; ``import dampax`` before it is Python on one core, with the other
idle. So the console script (``dampax_cli.main``) names the command line it runs
(``dampax_cli.COMMAND``) before it imports dampax, and dampax's import starts one thread
(:func:`start_prefetch`) that loads the executables the last run of the same command line
used, in the order it used them. The list is a verified cache file like every other
(``command-<digest>.loads`` in the folder of kept programs: ``_cachefiles._read_entry``, HMAC
under the user's key) and names files of that folder only, each verified before it is read, as
always. A program loaded ahead is used only where its file's digest is the one its caller asks
for (:func:`prefetched`), so a list that names other programs (other data, another version of
dampax) costs that thread's work and nothing else; the list is rewritten when a command used
other programs (:func:`recording`). Library use (``import dampax`` in Python) starts nothing.
"""

from __future__ import annotations

import contextlib
import functools
import gc
import hashlib
import json
import re
import sys
import threading
from pathlib import Path

from ._cachefiles import _read_entry, _write_entry, executable_parts

#: the tracing turn (:func:`_turn`): one thread traces and lowers a program at a time
_TRACING = threading.Lock()
_HOLDS = threading.local()


@contextlib.contextmanager
def _turn():
    """Hold the tracing turn for the block (re-entrant; ``_cache._compile`` ends it early).

    Tracing is Python, so threads that trace at once share one core and all finish late
    (a cold fit traced three programs side by side, each 3-4 s instead of 1); in turns, in
    the order asked, the program wanted first is ready first, and each compiles (with
    Python's lock released) while the next one traces (issue 36)."""
    if getattr(_HOLDS, "turn", False):
        yield
        return
    _begin_turn()
    try:
        yield
    finally:
        _end_turn()


def _begin_turn() -> None:
    """Take the turn; Python's cyclic garbage collector pauses while the holder traces (a
    trace allocates millions of objects: the collector took 1.4 of a cold fit's 14 s of CPU,
    collecting next to nothing; what is garbage is collected after the turn)."""
    _TRACING.acquire()
    _HOLDS.turn = True
    _HOLDS.gc = gc.isenabled()
    gc.disable()


def _end_turn() -> None:
    if getattr(_HOLDS, "turn", False):
        _HOLDS.turn = False
        if _HOLDS.gc:
            gc.enable()
        _TRACING.release()


@functools.lru_cache(maxsize=1)
def _pool():
    """The threads that compile programs ahead of their first call (``_cache.prepare_cached``)."""
    from concurrent.futures import ThreadPoolExecutor

    # three: one traces (in turns, :func:`_turn`) while two compile
    return ThreadPoolExecutor(max_workers=3,
                              thread_name_prefix="dampax-compile")


@functools.lru_cache(maxsize=1)
def _loader():
    """The one thread that loads kept executables ahead of their first call
    (``_cache.prepare_cached``), in the order asked (:class:`_Claimable`)."""
    from concurrent.futures import ThreadPoolExecutor

    return ThreadPoolExecutor(max_workers=1, thread_name_prefix="dampax-load")


class _Claimable:
    """A kept executable's loading, run by whoever needs it first: the loader thread in its
    turn, or a caller that needs the program before then (``_cache._entry``).

    Loading takes 0.1-0.4 s per program (XLA rebuilding the optimised HLO module), with
    Python's lock released; the six programs of ``dampax fit --example`` loaded three at a
    time on 2 cores made the first one the fit calls wait 0.6 s for all of them (issue 36).
    One loader thread, and the caller loading what it needs first itself, keep at most two
    loads at once, the one wanted now among them."""

    def __init__(self, fn, *args):
        from concurrent.futures import Future

        self._call = functools.partial(fn, *args)
        self._claim = threading.Lock()
        self._future = Future()

    def run(self) -> None:
        """Load, unless another thread has started to."""
        if not self._claim.acquire(blocking=False):
            return
        try:
            self._future.set_result(self._call())
        except BaseException as err:  # noqa: BLE001 - raised by result(), in the caller
            self._future.set_exception(err)

    def result(self):
        """What the load returns (a kept program, or a file's parts loaded ahead): loaded
        here if no thread has begun."""
        self.run()
        return self._future.result()


# ----------------------------------------------------------------------------------------------
# a repeated command's programs, loaded while dampax imports (see the module docstring)

#: a name the list may hold: a kept executable of the same folder
_NAME = re.compile(r"[A-Za-z0-9_.-]{1,200}\.jaxexe")
#: the most programs a list names (a command uses fewer than ten)
MAX_NAMES = 32

#: file path -> its load (:class:`_Claimable` of (header, parts) or None), until taken
_PENDING: dict[str, _Claimable] = {}
#: the kept executables this process loaded or wrote, in order (file names)
_USED: list[str] = []
#: the names the list of this command held when it was read
_LISTED: list[list[str]] = []
#: set when the command has ended: what is not loaded yet is not loaded
_DONE = threading.Event()


def _command() -> tuple[str, ...] | None:
    """The command line the console script runs (``dampax_cli.COMMAND``), or None."""
    command = getattr(sys.modules.get("dampax_cli"), "COMMAND", None)
    return tuple(command) if isinstance(command, (list, tuple)) else None


def _list_file(folder: Path, command) -> tuple[Path, str]:
    """(path, digest) of the list of the programs ``command`` used."""
    digest = hashlib.sha256(json.dumps(["loads", list(command)]).encode()).hexdigest()
    return folder / f"command-{digest[:32]}.loads", digest


def _load(path: Path):
    """(header, executable parts) of a verified kept executable, or None."""
    entry = _read_entry(path, None)
    if entry is None or entry[0].get("kind") != "jaxexe":
        return None
    try:
        return entry[0], executable_parts(entry[1])
    except Exception:  # noqa: BLE001 - not loadable here: its caller loads (and sets aside)
        return None


def start_prefetch(folder_of) -> None:
    """Start loading, in one thread, the kept executables the last run of the console
    script's command line used (nothing outside it, or without a cache folder), in the order
    that run used them. ``dampax fit --example`` calls the approximate model's program first
    (its ranking, in a thread, and its fit's start at once) and the exact model's last: loaded
    largest first (the exact model's, 0.37 s alone), both waited 0.3-0.5 s for a program they
    then loaded themselves beside it (issue 36; 12 alternations: median 2.215 -> 2.115 s, the
    CPU time the same). A caller that needs a program before its turn loads it itself
    (:class:`_Claimable`). LAPACK's pointers are set later, before the first program runs
    (``dampax._cache._load_executable``): scipy's import here would take Python's lock from
    dampax's import.

    Arguments:
        folder_of: returns the folder of kept programs, or None
            (``dampax._cache.exported_dir``); called only for a command of the console script.
    """
    command = _command()
    folder = None if command is None else folder_of()
    if folder is None:
        return
    path, digest = _list_file(folder, command)
    entry = _read_entry(path, digest)
    names = entry[0].get("names") if entry is not None else None
    if not isinstance(names, list):
        return
    names = [n for n in names[:MAX_NAMES] if isinstance(n, str) and _NAME.fullmatch(n)]
    _LISTED.append(names)
    _DONE.clear()
    loads = [(str(folder / n), _Claimable(_load, folder / n)) for n in names]
    _PENDING.update(loads)

    def run():
        for _, load in loads:
            if _DONE.is_set():
                return
            load.run()

    threading.Thread(target=run, name="dampax-prefetch", daemon=True).start()


def prefetched(path: Path, digest: str):
    """(header, executable parts) of ``path`` loaded ahead (waiting for its load if it has
    begun, loading it here if not) when the file holds the program of ``digest``; else
    None."""
    load = _PENDING.pop(str(path), None)
    if load is None:
        return None
    got = load.result()
    if got is None or got[0].get("digest") != digest:
        return None
    return got


def note_used(path: Path) -> None:
    """Note that this process loaded or wrote the kept executable ``path``."""
    if path.name not in _USED:
        _USED.append(path.name)


@contextlib.contextmanager
def recording(folder_of):
    """Around a command of the console script: at its end, the list of the kept executables
    it used (when other than the list read at its start) is written for its next run, and
    the programs loaded ahead that it did not use are dropped.

    Arguments:
        folder_of: as for :func:`start_prefetch`.
    """
    del _USED[:]
    try:
        yield
    finally:
        _DONE.set()
        _PENDING.clear()
        _write_list(_command(), _USED[:MAX_NAMES], folder_of)


def _write_list(command, names: list[str], folder_of) -> None:
    """Keep ``names`` as the list of ``command``'s programs, unless it is the list read."""
    if command is None or not names or (_LISTED and _LISTED[-1] == names):
        return
    folder = folder_of()
    if folder is not None:
        path, digest = _list_file(folder, command)
        _write_entry(path, digest, {"kind": "loads", "names": names}, b"")


# ----------------------------------------------------------------------------------------------
# what a kept executable calls that jaxlib sets up only while lowering

_LOADING = threading.Lock()


def prepare_loading() -> None:
    """Set up what a kept executable may call that jaxlib otherwise sets up while lowering:
    LAPACK's function pointers (taken from scipy; a kept fit or linear solve would call null
    pointers without them). Once per process, also where threads load at once."""
    with _LOADING:
        _prepare_loading_once()


@functools.lru_cache(maxsize=1)
def prepare_loading_beside() -> None:
    """Start :func:`prepare_loading` in a thread, once: the first program's load (XLA,
    without Python's lock) and LAPACK's set-up (scipy.linalg's import, 0.07 s of Python) then
    overlap instead of following each other on a fresh process's critical path."""
    threading.Thread(target=prepare_loading, name="dampax-lapack", daemon=True).start()


@functools.lru_cache(maxsize=1)
def _prepare_loading_once() -> None:
    from jax._src.lax import linalg

    linalg.initialize_lapack()
