"""Files written whole or not at all: an interrupted run leaves no half-written output."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

#: Temporary files being written now (removed by the command line's Ctrl-C handler).
PARTIAL: set[Path] = set()


def remove_partial_files() -> None:
    """Remove the temporary files of :func:`atomic_path` blocks still being written."""
    for tmp in list(PARTIAL):
        with contextlib.suppress(OSError):
            tmp.unlink()


@contextlib.contextmanager
def atomic_path(path) -> Iterator[Path]:
    """A temporary path beside ``path`` that replaces it once the block completes.

    The temporary name keeps the suffix (matplotlib and xarray pick the format from it). If
    the block raises (including KeyboardInterrupt), the temporary file is removed and
    ``path`` is left as it was.

    Arguments:
        path: the final file.

    Yields:
        The temporary path to write.
    """
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.part{path.suffix}")
    PARTIAL.add(tmp)
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        PARTIAL.discard(tmp)
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()


def save_figure(fig, path, **kwargs):
    """``fig.savefig(path, **kwargs)`` through :func:`atomic_path`; returns ``path``."""
    with atomic_path(path) as tmp:
        fig.savefig(tmp, **kwargs)
    return path


def check_writable_dir(folder, flag: str) -> None:
    """ValueError naming ``flag`` unless a file can be created in ``folder`` (tried, then removed).

    Arguments:
        folder: an existing directory.
        flag: the option or argument named in the error.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise ValueError(f"{flag}: folder {str(folder)!r} does not exist")
    probe = folder / f".dampax-write-test.{os.getpid()}"
    try:
        probe.touch()
    except OSError as err:
        raise ValueError(f"{flag}: cannot write in {str(folder)!r} ({err.strerror})") from None
    probe.unlink()


def write_text(path, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` through :func:`atomic_path`; returns the path."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


def write_netcdf(ds, path) -> Path:
    """Write an xarray Dataset as netCDF-3 (scipy backend) through :func:`atomic_path`.

    CF conventions (2.5.1): coordinate variables carry no ``_FillValue`` (xarray would give
    every floating-point variable ``_FillValue = NaN``); data variables keep theirs.

    Arguments:
        ds: the dataset.
        path: the file.

    Returns:
        The path.
    """
    encoding = {name: {"_FillValue": None} for name in ds.coords}
    with atomic_path(path) as tmp:
        ds.to_netcdf(tmp, engine="scipy", encoding=encoding)
    return Path(path)
