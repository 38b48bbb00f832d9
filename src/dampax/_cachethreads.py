"""The threads that build dampax's kept programs (``_cache``): the tracing turn, the pool that
compiles ahead of a program's first call, the loader of kept executables and its loads,
claimed by whoever needs one first."""

from __future__ import annotations

import contextlib
import functools
import gc
import threading

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
        """The loaded (executable, treedef, static): loaded here if no thread has begun."""
        self.run()
        return self._future.result()
