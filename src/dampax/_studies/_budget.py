"""What an error map will cost before it is computed (issue 37) and the step size that suits
the device (issue 34): the grid's host memory and time, refused or announced beyond the
machine's share; the chunk of points per step, chosen from the platform and the memory and
clipped to the grid."""

from __future__ import annotations

import math

import jax

#: At most this many samples per grid point (periods x samples_per_period).
MAX_SAMPLES = 10**8
#: host memory a grid point takes [bytes], measured (issue 37): the window estimate's
#: (points, 129) arrays (5.2 KB), the grid, the outputs and the dataset
MAP_BYTES_PER_POINT = 6_000
#: seconds a grid point takes at the default window (20 periods x 64 samples, 4 models),
#: measured on an idle 2-core machine (the default 2048-point map in 12.9 s, compilation
#: loaded from the cache): a rough guide for the size checks, not a promise
MAP_SECONDS_PER_POINT = 6e-3
#: the share of the machine's memory a map may need before it is refused
MAP_MEMORY_SHARE = 0.5


def physical_memory() -> float:
    """The machine's memory [bytes] (inf where the platform does not say)."""
    import os

    try:
        return float(os.sysconf("SC_PAGE_SIZE")) * float(os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return math.inf


def map_cost(n_points: int, n_models: int, periods: float,
             samples_per_period: int) -> tuple[float, float]:
    """Rough host memory [bytes] and time [s] of an error map of ``n_points`` points (the
    measured :data:`MAP_BYTES_PER_POINT` and :data:`MAP_SECONDS_PER_POINT`, the time scaled
    with the samples per point and the models).

    Arguments:
        n_points: grid points.
        n_models: analytic models compared.
        periods, samples_per_period: the window.

    Returns:
        (bytes, seconds).
    """
    samples = min(float(periods) * float(samples_per_period), float(MAX_SAMPLES))
    seconds = (float(n_points) * MAP_SECONDS_PER_POINT * (samples / 1280.0)
               * (n_models + 1) / 5.0)
    return float(n_points) * MAP_BYTES_PER_POINT, seconds


def check_map_size(sizes: dict, n_models: int, periods: float,
                   samples_per_period: int) -> int:
    """The grid's number of points; ValueError naming the axes when its memory estimate
    (:func:`map_cost`) exceeds :data:`MAP_MEMORY_SHARE` of the machine's memory.

    Arguments:
        sizes: the axes' names (or flags) and lengths.
        n_models, periods, samples_per_period: as in :func:`map_cost`.

    Returns:
        The number of points.
    """
    n_points = math.prod(int(v) for v in sizes.values())
    need, seconds = map_cost(n_points, n_models, periods, samples_per_period)
    have = physical_memory()
    if need > MAP_MEMORY_SHARE * have:
        shape = " x ".join(f"{v} {k}" for k, v in sizes.items())
        raise ValueError(
            f"{', '.join(sizes)}: a grid of {n_points:.4g} points ({shape}) needs about "
            f"{need / 2**30:.0f} GiB of memory (this machine has {have / 2**30:.0f} GiB) and "
            f"about {duration_text(seconds)} on a 2-core machine; use coarser axes, or split "
            f"the grid into maps of a part of an axis each")
    return n_points


def duration_text(seconds: float) -> str:
    """A duration in the unit that suits it: "40 s", "12 min", "3.5 h", "69 days"."""
    for unit, size, below in (("s", 1.0, 120.0), ("min", 60.0, 7200.0), ("h", 3600.0, 172800.0),
                              ("days", 86400.0, math.inf)):
        if seconds < below:
            value = seconds / size
            return f"{value:.2g} {unit}" if value < 10 else f"{value:.0f} {unit}"
    return "forever"


#: grid points per device and step when ``chunk_size`` is not given, on a CPU: the vmapped step
#: runs its points one after the other there (a few SIMD lanes aside), so larger steps gain
#: nothing (issue 34: the default map in the same 0.27 s as before this choice existed)
CPU_CHUNK = 128
#: on an accelerator (GPU, TPU) when ``chunk_size`` is not given: at most this many points per
#: device and step, the whole grid in one launch where it fits (one H100, issue 34: the
#: default map took 0.17 s in steps of 128 points, 0.05 s in one of 4096), within
#: :data:`STEP_MEMORY_SHARE` of the device's memory
ACCELERATOR_CHUNK = 32768
#: the share of a device's memory that one step's buffers may take (whatever chunk_size says)
STEP_MEMORY_SHARE = 0.25


def step_bytes_per_point(cfg) -> int:
    """Memory one grid point of a step takes on its device [bytes], an upper estimate.

    XLA's temporaries of the compiled step (``compiled.memory_analysis()``, measured on a CPU
    for issue 34, per point): 151 KB at the default window (4 models, blocks of 641 samples),
    3.8 KB for one model against the exact half-swings (blocks of 49), 265 KB for 100 periods
    in segments (blocks of 915); 8 bytes x block x (6 (models + 1) + 8) is above each.
    """
    return 8 * cfg.block * (6 * (len(cfg.models) + 1) + 8)


def device_memory(device) -> float:
    """Memory of one device [bytes]: what its allocator may use (``memory_stats()``, GPUs and
    TPUs), else the machine's memory shared by the host's devices of its platform."""
    try:
        stats = device.memory_stats() or {}
    except Exception:  # noqa: BLE001 - a backend without memory statistics
        stats = {}
    limit = stats.get("bytes_limit")
    if limit:
        return float(limit)
    host = [d for d in jax.local_devices() if d.platform == device.platform]
    return physical_memory() / max(1, len(host))


def choose_chunk(chunk_size: int | None, cfg, n_points: int, devices,
                 n_processes: int = 1) -> int:
    """Grid points per device and step.

    Not given (None): :data:`CPU_CHUNK` on a CPU, :data:`ACCELERATOR_CHUNK` elsewhere. Given or
    not, it is then clipped to the grid (no more than the points each device gets, rounded up
    to a power of two, but not below :data:`CPU_CHUNK`, so that small maps share one compiled
    step) and to the memory (:data:`STEP_MEMORY_SHARE` of a device's memory over
    :func:`step_bytes_per_point`, a power of two, at least 1).
    """
    chunk = (CPU_CHUNK if devices[0].platform == "cpu" else ACCELERATOR_CHUNK) \
        if chunk_size is None else int(chunk_size)
    per_device = -(-int(n_points) // (len(devices) * max(1, int(n_processes))))
    chunk = min(chunk, max(1 << max(per_device - 1, 0).bit_length(), CPU_CHUNK))
    fits = STEP_MEMORY_SHARE * device_memory(devices[0]) / step_bytes_per_point(cfg)
    if math.isfinite(fits):
        chunk = min(chunk, 1 << max(int(fits), 1).bit_length() - 1)
    return max(1, chunk)
