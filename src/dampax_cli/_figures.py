"""``dampax fit``'s figure drawn in a process of its own, forked before dampax (and JAX) loads.

On a 2-core machine a repeated ``dampax fit --example`` keeps both cores busy with the fit, its
ranking and the loading of their programs from the moment ``import dampax`` ends; before that,
for the 0.4 s in which Python starts and JAX imports, one core is idle. The figure needs
matplotlib (0.3 s of Python to import) and 0.13 s to draw, both on the busy cores until now.
So the console script forks, right after it has parsed a ``fit`` command and before anything
else is imported (:func:`start`), a worker that imports matplotlib in that idle time and then
waits for the one figure it draws: the fit's values as plain numbers, strings and arrays
(``dampax._plot_fit.figure_data``), drawn by the same ``dampax._plot_fit.fit_figure``, which
the worker imports without dampax's ``__init__`` (:func:`_figure_module`; that module and
``dampax._io`` import neither JAX nor the rest of dampax), into the temporary file that the
command made for it (``dampax._io.atomic_path``: it replaces fit.png with the command's other
outputs, or is removed with them). Measured in benchmarks/README.md (issue 36, forty-first
session).

The worker never writes a file the command did not make (it opens the temporary file without
creating it: one the command has removed stays removed), ignores Ctrl-C (held back from the
fork until it does: the command handles it and removes its temporary files), holds none of the
command's standard streams (its pipes stay clear of a closed fd 0, 1 or 2), sends the warnings
and the log messages of its drawing back to the command (which warns and logs them as its
own drawing did), and ends when the command's end of the pipe closes, whether or not a figure
was asked for. Starting it never fails a command: where it cannot start, there is none.
Where there is no worker (no ``fork`` on this platform, macOS, ``DAMPAX_FIGURE_PROCESS=0``, a
caller other than the console script) or it fails, :func:`draw` raises :class:`Unavailable`
and the command draws the figure in its own process, as before.
"""

from __future__ import annotations

import os
import struct
import sys
import threading

#: the worker of this process: (pid, request pipe, reply pipe), or None
_WORKER: tuple[int, int, int] | None = None
_LOCK = threading.Lock()
_HEADER = struct.Struct("<Q")


class Unavailable(RuntimeError):
    """There is no figure process, or it could not draw the figure (the reason)."""


def wanted(args) -> bool:
    """Whether a worker would draw a figure of this command: a ``fit`` of one trace or of its
    maxima (a joint fit of several files draws its own figure), on a platform with ``fork``
    other than macOS (whose system libraries are not safe in a forked child), unless
    ``DAMPAX_FIGURE_PROCESS=0``."""
    if os.environ.get("DAMPAX_FIGURE_PROCESS", "1").strip().lower() in ("0", "no", "off",
                                                                       "false"):
        return False
    if not hasattr(os, "fork") or sys.platform == "darwin":
        return False
    if getattr(args, "command", None) != "fit":
        return False
    paths = args.path if isinstance(args.path, (list, tuple)) else [args.path]
    return len([p for p in paths if p is not None]) <= 1


def start() -> bool:
    """Fork the worker (once per process), only while nothing but the launcher is loaded: no
    JAX, no other thread (a forked copy of a process with threads may hold their locks).
    Returns whether a worker runs; never raises (a worker that cannot start is no worker)."""
    global _WORKER
    if _WORKER is not None:
        return True
    if "jax" in sys.modules or "numpy" in sys.modules or threading.active_count() != 1:
        return False
    import signal

    for stream in (sys.stdout, sys.stderr):  # (None where the command's fd 1 or 2 is closed)
        try:
            stream.flush()
        except (AttributeError, OSError, ValueError):
            pass
    fds: list[int] = []
    blocked = False
    try:
        for _ in range(2):
            fds.extend(_high(fd) for fd in os.pipe())
        # Ctrl-C held back until the worker ignores it (a KeyboardInterrupt in its first
        # instants ran the launcher's own code in the copy, onto the command's stderr)
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        blocked = True
        pid = os.fork()
    except Exception:  # noqa: BLE001 - no worker: the command draws its figure
        for fd in fds:
            os.close(fd)
        if blocked:
            signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
        return False
    requests_r, requests_w, replies_r, replies_w = fds
    if pid == 0:  # the worker: never returns
        try:
            signal.signal(signal.SIGINT, signal.SIG_IGN)
            signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
            os.close(requests_w)
            os.close(replies_r)
            _serve(requests_r, replies_w)
        finally:
            os._exit(1)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    os.close(requests_r)
    os.close(replies_w)
    _WORKER = (pid, requests_w, replies_r)
    return True


def _high(fd: int) -> int:
    """``fd`` moved to 3 or above (where the command's fd 0, 1 or 2 is closed, a pipe took
    its number, and the worker's own standard streams, pointed at /dev/null, closed it)."""
    import fcntl

    if fd > 2:
        return fd
    try:
        return fcntl.fcntl(fd, fcntl.F_DUPFD_CLOEXEC, 3)
    finally:
        os.close(fd)


def running() -> bool:
    """Whether this process has a worker that has not drawn yet."""
    return _WORKER is not None


def draw(data, path) -> list[str]:
    """Draw ``data`` (``dampax._plot_fit.figure_data``) into ``path``, an existing file that
    the worker overwrites (a temporary one of ``dampax._io.atomic_path``), waiting for it.

    Returns:
        The messages of the warnings the drawing raised.

    Raises:
        Unavailable: no worker, or it failed (the reason); the caller draws the figure itself.
    """
    global _WORKER
    with _LOCK:
        worker, _WORKER = _WORKER, None
    if worker is None:
        raise Unavailable("there is no figure process")
    pid, requests, replies = worker
    try:
        try:
            _send(requests, (data, os.fspath(path)))
        finally:
            os.close(requests)
        reply = _receive(replies)
    except OSError as err:  # (a worker that has gone: a broken pipe)
        raise Unavailable(f"the figure process has gone ({err})") from None
    finally:
        os.close(replies)
        _reap(pid)
    if reply is None:
        raise Unavailable("the figure process ended without an answer")
    status, detail, logged = reply
    if status != "ok":  # (the command draws, and logs what it logs)
        raise Unavailable(f"the figure process could not draw: {detail}")
    _log_again(logged)
    return list(detail)


def _log_again(records) -> None:
    """The worker's log records of WARNING and above, logged here as they were there."""
    import logging

    for name, level, message in records:
        logging.getLogger(name).log(level, "%s", message)


def close() -> None:
    """Let the worker end without a figure (the command draws none, or has ended)."""
    global _WORKER
    with _LOCK:
        worker, _WORKER = _WORKER, None
    if worker is not None:
        pid, requests, replies = worker
        os.close(requests)  # (the worker reads the end of its pipe and leaves: not waited
        os.close(replies)  # for, it may still be importing; it is reaped when it has ended)
        _reap(pid, os.WNOHANG)


def _reap(pid: int, options: int = 0) -> None:
    try:
        os.waitpid(pid, options)
    except ChildProcessError:
        pass


def _send(fd: int, message) -> None:
    import pickle  # (here: ``dampax --help`` imports this module)

    blob = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
    view = memoryview(_HEADER.pack(len(blob)) + blob)
    while view:
        view = view[os.write(fd, view):]


def _read_exactly(fd: int, n: int) -> bytes | None:
    chunks, left = [], n
    while left:
        chunk = os.read(fd, min(left, 1 << 20))
        if not chunk:
            return None
        chunks.append(chunk)
        left -= len(chunk)
    return b"".join(chunks)


def _receive(fd: int):
    """The next message on ``fd``, or None at the end of the pipe. (Only the two ends of
    this process's own pipe write to it.)"""
    head = _read_exactly(fd, _HEADER.size)
    if head is None:
        return None
    import pickle

    blob = _read_exactly(fd, _HEADER.unpack(head)[0])
    return None if blob is None else pickle.loads(blob)  # noqa: S301 - our own pipe


def _figure_module():
    """``dampax._plot_fit`` without running dampax's ``__init__`` (which imports JAX): the
    package object made from its spec, unexecuted, holds the path its submodules load from."""
    import importlib.util

    if "dampax" not in sys.modules:
        spec = importlib.util.find_spec("dampax")
        sys.modules["dampax"] = importlib.util.module_from_spec(spec)
    import dampax._plot_fit as module

    return module


def _serve(requests: int, replies: int):
    """The worker's life: import, wait for one figure, draw it, answer, end (``os._exit``:
    none of the command's exit handlers or buffers are the worker's)."""
    import logging

    status = 0
    try:
        # the command's standard streams are not the worker's (a caller reading them to
        # their end would wait for the worker too); what it has to say goes through the pipe
        devnull = os.open(os.devnull, os.O_RDWR)
        for fd in (0, 1, 2):
            os.dup2(devnull, fd)
        if devnull > 2:
            os.close(devnull)
        said = _collector()
        logging.getLogger().addHandler(said)
        try:
            module = _figure_module()
            from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: F401
            from matplotlib.figure import Figure  # noqa: F401
            ready = None
        except Exception as err:  # noqa: BLE001 - said in the answer; the command draws
            ready = f"{type(err).__name__}: {err}"
        request = _receive(requests)
        if request is not None:
            reply = _drawn(module, *request) if ready is None else ("failed", ready)
            _send(replies, (*reply, said.records))
    except BaseException:  # noqa: BLE001 - a closed pipe: the command has gone
        status = 1
    os._exit(status)


def _collector():
    """A logging handler of the worker that keeps (logger, level, message) of the records of
    WARNING and above (matplotlib's "findfont: ..."), for the command to log again."""
    import logging

    class Said(logging.Handler):
        def __init__(self):
            super().__init__(logging.WARNING)
            self.records = []

        def emit(self, record):
            self.records.append((record.name, record.levelno, record.getMessage()))

    return Said()


def _drawn(module, data, path: str):
    """("ok", warning messages) once ``data`` is drawn into the existing file ``path``;
    ("failed", the reason) if it could not be."""
    import warnings

    from dampax._io import write_figure

    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            fig = module.fit_figure(data)
            fd = os.open(path, os.O_WRONLY | os.O_TRUNC)  # not created if it was removed
            with open(fd, "wb") as fh:
                write_figure(fig, fh, os.path.splitext(path)[1], dpi=module.FIT_DPI)
                fh.flush()
                os.fsync(fh.fileno())
        return "ok", [str(w.message) for w in caught]
    except Exception as err:  # noqa: BLE001 - said in the answer; the command draws
        return "failed", f"{type(err).__name__}: {err}"
