"""Files written whole or not at all, safely: an interrupted or failed run leaves no half-written
output, never writes through a link someone planted, and a set of outputs is replaced together.

Every output goes first to a temporary file made with exclusive creation (``tempfile.mkstemp``:
a name nobody can predict, created ``O_EXCL``, so it cannot be a planted file or link) in the
target folder, is written through the descriptor that created it where the writer takes a file
object, and replaces the target with ``os.replace`` once complete (a link at the target's name is
replaced, not followed). Inside :func:`all_or_nothing` the replacements wait until every file of
the block is complete: a full disk or an error half-way leaves the whole earlier set of outputs.
The temporary files and folders being written are listed in :data:`PARTIAL`, which the command
line's SIGINT/SIGTERM handler removes (:func:`remove_partial_files`).
"""

from __future__ import annotations

import contextlib
import errno
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

#: Temporary files and folders being written now (removed by the command line's signal handler).
PARTIAL: set[Path] = set()

#: The pending replacements (temporary, final) of the open :func:`all_or_nothing` blocks.
_STAGED: list[list[tuple[Path, Path]]] = []


def remove_partial_files() -> None:
    """Remove the temporary files and folders of writes still in progress (:data:`PARTIAL`)."""
    for tmp in list(PARTIAL):
        with contextlib.suppress(OSError):
            if tmp.is_dir() and not tmp.is_symlink():
                shutil.rmtree(tmp, ignore_errors=True)
            else:
                tmp.unlink()
        PARTIAL.discard(tmp)


def _named(err: OSError, path: Path) -> OSError:
    """``err`` with the file it concerns and a readable reason (a full disk says so)."""
    reason = {errno.ENOSPC: "the disk is full", errno.EDQUOT: "the disk quota is exceeded",
              errno.EFBIG: "the file size limit (ulimit -f) is exceeded"}.get(
                  err.errno, err.strerror or str(err))
    return OSError(err.errno, f"cannot write {str(path)!r}: {reason}; the earlier output, if "
                              "any, is left as it was")


def _make_temp(path: Path) -> tuple[int, Path]:
    """A new temporary file beside ``path`` (exclusive creation, unpredictable name): its
    descriptor and path, listed in :data:`PARTIAL`."""
    try:
        fd, name = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".part{path.suffix}",
                                    dir=path.parent)
    except OSError as err:
        raise _named(err, path) from None
    tmp = Path(name)
    PARTIAL.add(tmp)
    return fd, tmp


def _finish(tmp: Path, path: Path, alone: bool = False) -> None:
    """Replace ``path`` by ``tmp`` now, or at the end of the open :func:`all_or_nothing`
    (``alone``: now in any case)."""
    if _STAGED and not alone:
        _STAGED[-1].append((tmp, path))
        return
    os.replace(tmp, path)
    PARTIAL.discard(tmp)


def _discard(tmp: Path) -> None:
    PARTIAL.discard(tmp)
    with contextlib.suppress(FileNotFoundError):
        tmp.unlink()


@contextlib.contextmanager
def _removed_on_failure(tmp: Path, path: Path):
    """If the block raises, remove ``tmp`` (an OSError is re-raised naming ``path``)."""
    try:
        yield
    except OSError as err:
        _discard(tmp)
        raise _named(err, path) from None
    except BaseException:
        _discard(tmp)
        raise


@contextlib.contextmanager
def atomic_path(path) -> Iterator[Path]:
    """A temporary path beside ``path`` that replaces it once the block completes.

    For writers that take only a file name (h5netcdf): the temporary file already exists,
    created exclusively by this process. The temporary name keeps the suffix (matplotlib and
    xarray pick the format from it). If the block raises (including KeyboardInterrupt), the
    temporary file is removed and ``path`` is left as it was.

    Arguments:
        path: the final file.

    Yields:
        The temporary path to write.
    """
    path = Path(path)
    fd, tmp = _make_temp(path)
    os.close(fd)
    with _removed_on_failure(tmp, path):
        yield tmp
    _finish(tmp, path)


@contextlib.contextmanager
def atomic_file(path, mode: str = "wb", *, alone: bool = False, **kwargs):
    """A file object writing a temporary file beside ``path`` through the descriptor that
    created it; it replaces ``path`` once the block completes (and the data are on disk).

    Arguments:
        path: the final file.
        mode: ``"wb"`` or ``"w"`` (text; ``kwargs`` such as ``encoding``, ``newline``).
        alone: replace ``path`` when the block completes even inside :func:`all_or_nothing`
            (a cache file: not part of a command's set of outputs).

    Yields:
        The open file object.
    """
    path = Path(path)
    fd, tmp = _make_temp(path)
    with _removed_on_failure(tmp, path), open(fd, mode, **kwargs) as fh:
        yield fh
        fh.flush()
        os.fsync(fh.fileno())
    _finish(tmp, path, alone)


@contextlib.contextmanager
def all_or_nothing() -> Iterator[None]:
    """Within the block, outputs replace their targets only when the whole block succeeds.

    Every file written by :func:`atomic_path`, :func:`atomic_file` and the writers below is
    kept as a complete temporary file until the block ends; then all replace their targets
    (renames, which need no space). If the block raises, every temporary file is removed and
    every earlier output is left as it was.
    """
    _STAGED.append([])
    try:
        yield
    except BaseException:
        for tmp, _ in _STAGED.pop():
            _discard(tmp)
        raise
    staged = _STAGED.pop()
    for i, (tmp, path) in enumerate(staged):
        if _STAGED:  # a block inside a block: the outer one decides
            _STAGED[-1].append((tmp, path))
            continue
        try:
            os.replace(tmp, path)
        except OSError as err:  # (a folder at the target's name): no temporary file is left
            for left, _ in staged[i:]:
                _discard(left)
            raise _named(err, path) from None
        PARTIAL.discard(tmp)


@contextlib.contextmanager
def private_folder(prefix: str) -> Iterator[Path]:
    """A new folder only this user can read (``tempfile.mkdtemp``), removed when the block ends
    and by the command line's signal handler (listed in :data:`PARTIAL`)."""
    folder = Path(tempfile.mkdtemp(prefix=prefix))
    PARTIAL.add(folder)
    try:
        yield folder
    finally:
        shutil.rmtree(folder, ignore_errors=True)
        PARTIAL.discard(folder)


#: zlib level of a PNG (Pillow's default 6): the fit figure of ``dampax fit --example`` in
#: 0.126 s instead of 0.145-0.173 s (its encoding was a quarter), the file 8 % larger
PNG_COMPRESS_LEVEL = 3


def save_figure(fig, path, **kwargs):
    """``fig.savefig`` to ``path`` through :func:`atomic_file`; returns ``path``."""
    with atomic_file(path) as fh:
        write_figure(fig, fh, Path(path).suffix, **kwargs)
    return path


def write_figure(fig, fh, suffix: str, **kwargs) -> None:
    """``fig.savefig`` into the open file ``fh`` in the format of ``suffix`` (PNG at
    :data:`PNG_COMPRESS_LEVEL`); ``kwargs`` are savefig's."""
    fmt = suffix.lstrip(".").lower() or "png"
    if fmt == "png":
        kwargs.setdefault("pil_kwargs", {"compress_level": PNG_COMPRESS_LEVEL})
    fig.savefig(fh, format=fmt, **kwargs)


def check_writable_dir(folder, flag: str) -> None:
    """ValueError naming ``flag`` unless a file can be created in ``folder`` (tried, then removed).

    Arguments:
        folder: an existing directory.
        flag: the option or argument named in the error.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise ValueError(f"{flag}: folder {str(folder)!r} does not exist")
    try:
        fd, probe = tempfile.mkstemp(prefix=".dampax-write-test.", dir=folder)
    except OSError as err:
        raise ValueError(f"{flag}: cannot write in {str(folder)!r} ({err.strerror})") from None
    os.close(fd)
    os.unlink(probe)


def write_text(path, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` through :func:`atomic_file`; returns the path."""
    with atomic_file(path, "w", encoding="utf-8") as fh:
        fh.write(text)
    return Path(path)


def write_netcdf(ds, path) -> Path:
    """Write an xarray Dataset as netCDF-3 (scipy backend) through :func:`atomic_file`.

    CF conventions (2.5.1): coordinate variables carry no ``_FillValue`` (xarray would give
    every floating-point variable ``_FillValue = NaN``); data variables keep theirs.

    Arguments:
        ds: the dataset.
        path: the file.

    Returns:
        The path.
    """
    encoding = {name: {"_FillValue": None} for name in ds.coords}
    data = ds.to_netcdf(None, engine="scipy", encoding=encoding)  # bytes: no file by name
    with atomic_file(path) as fh:
        fh.write(bytes(data))
    return Path(path)
