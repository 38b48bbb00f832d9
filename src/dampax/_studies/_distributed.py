"""Error maps over several processes: local workers, joining a ``jax.distributed`` run, timeouts.

Three ways to run one error map in several processes, each computing its share of the steps
(``dampax._studies._maps.error_map`` splits them by ``jax.process_index()``) and process 0
keeping the gathered map:

- **local workers** (``error_map(..., processes=N)``, ``dampax errormap --processes N``):
  :func:`run_local` starts N Python processes (``dampax._studies._worker.worker``) that join
  a ``jax.distributed`` run on 127.0.0.1 at a free port; process 0 writes the gathered map to a
  temporary file (atomically), which the caller loads once every worker has exited with
  status 0 (``dampax errormap`` then writes errormap.nc, atomically too). The caller watches
  the workers: when one dies the others are stopped at once and
  :class:`DistributedError` says which died and how; nothing is returned or written.
- **joining a run** (``dampax errormap --coordinator HOST:PORT --process-id I --num-processes N``
  in each process, or ``--cluster`` under Slurm / Open MPI, where
  ``jax.distributed.initialize()`` reads the job's environment): :func:`initialize`, then the
  plain ``error_map``; process 0 writes the files.
- **from Python** on a cluster: ``jax.distributed.initialize()`` (or :func:`initialize`) in each
  process before any JAX computation, then ``dp.error_map(...)``: every process gets the map.

Nothing waits forever: connecting is bounded by the timeout (``initialization_timeout``); at
the gather each process waits at most the timeout for the others (:func:`gather`, a barrier
of the distributed runtime before the collective, which has no timeout of its own) and then
raises :class:`DistributedError`; and a process that sends no heartbeat for
``min(2 timeout, 100)`` seconds is taken as dead, upon which JAX ends every other process of
the run (status 134, "the JAX distributed service detected fatal errors ... another task
died"), whichever comes first. Process 0 writes only after the gather: a failed run writes
nothing.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import math
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

from .._cache import (
    _digest,
    _load_tree,
    _program_text,
    _read_entry,
    _write_entry,
    compile_cached,
    executable_header,
    exported_dir,
    load_executable_bytes,
)
from .._io import private_folder

#: Seconds to wait for the processes to connect, and at the gather for the others.
DEFAULT_TIMEOUT = 300.0
#: jax's own heartbeat timeout; a shorter ``timeout`` shortens it too
_HEARTBEAT_S = 100
#: tests: the process of this index kills itself (SIGKILL) on reaching the gather
KILL_ENV = "DAMPAX_TEST_KILL_PROCESS"

_GATHERS = itertools.count()  # barrier names: every process gathers in the same order


class DistributedError(RuntimeError):
    """A multi-process error map failed: a process died, exited with an error or timed out."""


# ----------------------------------------------------------------------------------------------
# checks


def check_processes(value, name: str = "processes") -> int | None:
    """None, or an integer >= 1 (ValueError naming ``name`` otherwise)."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
    return int(value)


def check_timeout(value, name: str = "timeout") -> float:
    """A finite number of seconds > 0 (ValueError naming ``name`` otherwise)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (
            math.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be a number of seconds > 0, got {value!r}")
    return float(value)


def _check_address(address: str, name: str) -> str:
    host, sep, port = str(address).rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"{name} must be HOST:PORT (e.g. 10.0.0.1:12345), got {address!r}")
    return str(address)


# ----------------------------------------------------------------------------------------------
# joining a run


def initialize(coordinator: str | None = None, process_id: int | None = None,
               num_processes: int | None = None, *, timeout: float = DEFAULT_TIMEOUT,
               bind: str | None = None, names: tuple[str, str, str] = (
                   "coordinator", "process_id", "num_processes"),
               on_timeout: Callable[[str], object] | None = None) -> tuple[int, int]:
    """Join a ``jax.distributed`` run; must come before any JAX computation in this process.

    With no arguments ``jax.distributed.initialize()`` takes them from the cluster's
    environment (Slurm's ``srun``, Open MPI's ``mpirun``, or ``JAX_COORDINATOR_ADDRESS``).
    Collectives between CPU processes use gloo (JAX's default since 0.5.1).

    Arguments:
        coordinator: HOST:PORT of process 0's coordinator service (all processes give the same).
        process_id: this process's index, 0 <= process_id < num_processes.
        num_processes: the number of processes of the run.
        timeout: seconds for every process to connect, and (:func:`gather`) for the others
            at the gather; a process that sends no heartbeat for twice as long (at most jax's
            default, 100 s) is taken as dead and JAX ends every process of the run.
        bind: the address the coordinator (process 0) listens on (default: every interface
            at the coordinator's port).
        names: how errors name the three arguments (the command line passes its options).
        on_timeout: called with a one-line message (from another thread) when connecting
            takes longer than ``timeout``; the command line prints it and ends the process.
            Without it, JAX itself ends the process when ``timeout`` has passed (status 134,
            "the JAX distributed service detected fatal errors": it aborts, raising nothing).

    Returns:
        (process index, process count).

    Raises:
        ValueError: naming the argument: some but not all of the three are given, or one is
            malformed; or this process already ran JAX computations or joined a run.
        DistributedError: connecting failed where JAX raises an error instead of aborting.
    """
    import jax
    from jax._src import xla_bridge

    given = [v is not None for v in (coordinator, process_id, num_processes)]
    if any(given) and not all(given):
        missing = [n for n, g in zip(names, given, strict=True) if not g]
        raise ValueError(f"{missing[0]} is missing: give all of {', '.join(names)}, or none "
                         "of them under Slurm / Open MPI")
    timeout = check_timeout(timeout)
    if all(given):
        coordinator = _check_address(coordinator, names[0])
        num_processes = check_processes(num_processes, names[2])
        if isinstance(process_id, bool) or not isinstance(process_id, int) or not (
                0 <= process_id < num_processes):
            raise ValueError(f"{names[1]} must be an integer in 0 .. {num_processes - 1} "
                             f"({names[2]} - 1), got {process_id!r}")
    if jax.distributed.is_initialized():
        raise ValueError("this process already joined a jax.distributed run")
    if xla_bridge.backends_are_initialized():
        raise ValueError("jax.distributed must be initialised before any JAX computation in "
                         "the process (here JAX already ran)")
    seconds = max(1, math.ceil(timeout))
    where = coordinator or os.environ.get("JAX_COORDINATOR_ADDRESS") or "the coordinator"
    watchdog = None
    if on_timeout is not None:
        count = f"all {num_processes} processes" if num_processes else "every process"
        watchdog = threading.Timer(timeout, on_timeout, args=(
            f"could not join the jax.distributed run at {where} within {timeout:g} s: not every "
            f"process connected (are {count} started, with the same coordinator, and can "
            "they reach it?)",))
        watchdog.daemon = True
        watchdog.start()
    try:
        jax.distributed.initialize(  # jax's own limit a little later: the watchdog speaks first
            coordinator, num_processes, process_id,
            initialization_timeout=seconds + (5 if watchdog else 0),
            heartbeat_timeout_seconds=min(2 * seconds, _HEARTBEAT_S),
            shutdown_timeout_seconds=max(seconds, int(DEFAULT_TIMEOUT)),  # process 0 may
            coordinator_bind_address=bind)  # still be writing files while the others exit
    except ValueError as err:  # no cluster environment found, and no arguments
        raise ValueError(f"cannot join a jax.distributed run: {err} (outside Slurm / Open MPI "
                         f"give {', '.join(names)})") from None
    except Exception as err:  # noqa: BLE001 - jaxlib's errors: connecting failed or timed out
        raise DistributedError(
            f"could not join the run at {where} within {timeout:g} s (are all processes "
            f"started, and is the address reachable?): {_first_line(err)}") from None
    finally:
        if watchdog is not None:
            watchdog.cancel()
    return jax.process_index(), jax.process_count()


def _first_line(err: BaseException) -> str:
    text = str(err).strip()
    return text.splitlines()[0] if text else type(err).__name__


def gather(arrays, *, timeout: float):
    """``multihost_utils.process_allgather(arrays, tiled=False)``, waiting at most ``timeout``
    seconds for the other processes to reach it (a barrier of the distributed runtime first:
    the collective itself has no timeout of its own).

    Raises:
        DistributedError: not every process arrived within ``timeout`` (one died or is stuck).
    """
    import jax
    from jax._src import distributed
    from jax.experimental import multihost_utils

    kill = os.environ.get(KILL_ENV)
    if kill is not None and kill.strip() == str(jax.process_index()):
        os.kill(os.getpid(), signal.SIGKILL)  # tests: a worker that dies mid-run
    client = distributed.global_state.client
    if client is not None:
        name = f"dampax_error_map_gather_{next(_GATHERS)}"
        try:
            client.wait_at_barrier(name, max(1, int(timeout * 1000)))
        except Exception as err:  # noqa: BLE001 - jaxlib's error: a timeout or a dead peer
            raise DistributedError(
                f"process {jax.process_index()} of {jax.process_count()} waited up to "
                f"{timeout:g} s for the other processes to finish their share of the error "
                f"map; not all arrived (one died or is stuck): {_first_line(err)}") from None
    return multihost_utils.process_allgather(arrays, tiled=False)


def compile_cached_here(name: str, key, fn, *specs):
    """``dampax._cache.compile_cached`` for a process other than 0 of a ``jax.distributed`` run.

    JAX's persistent compilation cache keeps only process 0's programs (it writes nothing
    elsewhere), and on a CPU a program's cache key names its devices, which differ from
    process to process: without this, every other process would compile the step again on
    every run (about 10 s for the default map, longer than its share of the work). So the
    compiled executable of this process is kept too, in dampax's ``exported/`` folder, one file
    per program and process index, written and verified as every cache file is
    (``dampax._cache._write_entry`` / ``_read_entry``: the user's own folder, a digest of
    what shaped the program, an HMAC); a refused or damaged file is compiled again.

    Arguments:
        name, key, fn, specs: as for ``compile_cached``.

    Returns:
        The compiled executable.
    """
    import jax

    folder = exported_dir()
    if folder is None:
        return compile_cached(name, key, fn, *specs)
    digest = _digest(_program_text(key, specs) + repr((
        jax.process_index(), jax.process_count(),
        [(d.id, d.platform, d.device_kind) for d in jax.local_devices()])))
    path = folder / f"{name}-{digest[:32]}.jaxexe"
    devices = list(specs[0].sharding.mesh.devices.flat) if specs and hasattr(
        specs[0], "sharding") else jax.local_devices()
    entry = _read_entry(path, digest)
    if entry is not None:
        header, payload = entry
        try:
            in_tree, out_tree, _ = _load_tree(header["trees"].encode())
            return load_executable_bytes(payload, in_tree, out_tree, devices)
        except Exception:  # noqa: BLE001 - verified, yet not loadable here: compile again
            pass
    compiled = compile_cached(name, key, fn, *specs)
    kept = executable_header(compiled)
    if kept is not None:
        _write_entry(path, digest, *kept)
    return compiled


# ----------------------------------------------------------------------------------------------
# local workers


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port that is free on ``host`` now (the OS picks it)."""
    with contextlib.closing(socket.socket(socket.AF_INET, socket.SOCK_STREAM)) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def _signal_name(code: int) -> str:
    try:
        return signal.Signals(code).name
    except ValueError:
        return f"signal {code}"


def _tail(path: Path, lines: int = 3) -> str:
    """The last Python-looking lines of a worker's log (XLA's own chatter skipped)."""
    try:
        text = path.read_text(errors="replace").splitlines()
    except OSError:
        return ""
    keep = [t.strip() for t in text if t.strip() and not t.startswith(("[Gloo]", "    @ "))]
    return " | ".join(keep[-lines:])


def run_local(kwargs: dict, processes: int, *, timeout: float = DEFAULT_TIMEOUT,
              progress: bool = False):
    """``error_map(**kwargs)`` computed by ``processes`` local worker processes.

    The workers join a ``jax.distributed`` run on 127.0.0.1 at a free port (each with its own
    CPU device: the step's compiled program is the one-process program), compute their shares,
    and process 0 gathers them and writes the map (the pickled Dataset) to a temporary file,
    atomically; it is loaded here once every worker has exited with status 0. A worker that
    dies or fails stops the
    others at once. Workers end when this process ends (they watch their stdin).

    Arguments:
        kwargs: checked keyword arguments of ``error_map`` (axes as 1-D float arrays).
        processes: the number of workers, >= 1.
        timeout: seconds to connect, and for the workers to wait for each other at the gather.
        progress: worker 0 draws its progress bar on this process's stderr.

    Returns:
        The ``xarray.Dataset`` of the map (what ``error_map`` returns in one process).

    Raises:
        DistributedError: a worker died, failed or timed out; the message names it, how it
            ended and its last words. Nothing is left behind.
    """
    import pickle

    import numpy as np

    spec = {key: (np.asarray(value, dtype=float).tolist() if isinstance(value, np.ndarray)
                  else list(value) if isinstance(value, tuple) else value)
            for key, value in kwargs.items()}
    address = f"127.0.0.1:{free_port()}"
    with private_folder("dampax-map-") as folder:
        result = folder / "map.pickle"
        procs, logs = [], []
        try:
            for i in range(processes):
                job = folder / f"worker{i}.json"
                job.write_text(json.dumps(dict(
                    kwargs=spec | {"progress": bool(progress and i == 0)}, coordinator=address,
                    process_id=i, num_processes=processes, timeout=timeout,
                    output=str(result) if i == 0 else None)))
                log = folder / f"worker{i}.log"
                logs.append(log)
                with open(log, "wb") as out:
                    procs.append(subprocess.Popen(
                        [sys.executable, "-c", _WORKER, str(job)],
                        stdin=subprocess.PIPE, stdout=out,
                        stderr=None if (progress and i == 0) else subprocess.STDOUT))
            _wait(procs, logs, processes, (0,) if progress else ())
        finally:
            for p in procs:  # after a failure, or an interrupt here (KeyboardInterrupt)
                if p.poll() is None:
                    p.kill()
                with contextlib.suppress(OSError, ValueError):
                    p.stdin.close()
                p.wait()
        with open(result, "rb") as f:  # written by worker 0 in this private folder
            return pickle.load(f)


def _wait(procs, logs, processes: int, shown: tuple[int, ...]) -> None:
    """Until every worker has exited with status 0; DistributedError at the first that did
    not (the others are killed by the caller's ``finally``). ``shown``: the workers whose
    stderr is this process's."""
    while True:
        codes = [p.poll() for p in procs]
        for i, code in enumerate(codes):
            if code not in (None, 0):
                how = (f"was killed by {_signal_name(-code)}" if code < 0
                       else f"exited with status {code}")
                last = _tail(logs[i]) or ("its messages are above" if i in shown else "")
                raise DistributedError(
                    f"error map over {processes} processes failed: worker {i} {how}"
                    + (f" ({last})" if last else "") + "; the other workers were stopped and "
                    "no map was written")
        if all(code == 0 for code in codes):
            return
        time.sleep(0.05)


def _watch_parent() -> None:
    """End this worker when the process that started it ends (its stdin pipe closes)."""
    def watch():
        with contextlib.suppress(OSError):
            while os.read(0, 4096):  # the raw descriptor: no lock held at interpreter exit
                pass
        os._exit(3)

    threading.Thread(target=watch, name="dampax-parent", daemon=True).start()


def _give_up(message: str) -> None:
    """A worker's end when its run cannot be joined: the message, status 3."""
    with contextlib.suppress(OSError):
        os.write(2, f"dampax worker: {message}\n".encode())
    os._exit(3)


#: the command of a local worker (`dampax._studies._worker.worker`: above the map, which
#: imports this module, so no import cycle; not ``-m``: dampax imports the package first)
_WORKER = "import sys; from dampax._studies._worker import worker; sys.exit(worker(sys.argv[1]))"
