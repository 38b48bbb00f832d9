"""Outputs written safely (issue 37, item 2): temporary files are made exclusively beside their
target and never through a planted link; a command's outputs replace the earlier ones together
or not at all (a file size limit or a full disk half-way leaves the whole earlier set, byte
for byte, and a named error); SIGTERM, like Ctrl-C, leaves no temporary file or folder behind.

The maps are those of tests/studies/test_distributed.py (a 2 x 2 x 2 grid, 3 periods, one
model): the same compiled step.
"""

import errno
import os
import resource
import signal
import subprocess
import sys
import time

import pytest
import xarray as xr

from dampax import _io
from dampax._cli import main

CLI = ["errormap", "--d0", "0,0.04", "--d2", "0,0.3", "--phi0", "0,2", "--periods", "3",
       "--samples-per-period", "16", "--chunk-size", "4", "--models", "matched", "--no-progress"]


def _snapshot(folder):
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def test_a_link_at_the_target_is_replaced_not_followed(tmp_path):
    """Another user who can write the output folder plants links under the output names (the
    final name, and the old predictable temporary name): the victim's files elsewhere are
    left as they were, and the outputs are plain files."""
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    out = tmp_path / "out"
    out.mkdir()
    (out / "errormap.nc").symlink_to(victim)
    (out / f".errormap.{os.getpid()}.part.nc").symlink_to(victim)
    ds = xr.Dataset({"a": ("x", [1.0, 2.0])})
    _io.write_netcdf(ds, out / "errormap.nc")
    _io.write_text(out / "fit.json", "{}")
    assert victim.read_text() == "precious"
    assert not (out / "errormap.nc").is_symlink()
    assert xr.open_dataset(out / "errormap.nc", engine="scipy")["a"].values.tolist() == [1, 2]


def test_temporary_names_are_unpredictable_and_exclusive(tmp_path):
    """Two writes of the same target in one process use different, freshly created names."""
    names = []
    for _ in range(2):
        with _io.atomic_file(tmp_path / "a.png") as fh:
            (tmp,) = _io.PARTIAL
            names.append(tmp.name)
            fh.write(b"x")
    assert len(set(names)) == 2 and all(n.startswith(".a.") and ".part" in n for n in names)
    assert os.getpid() not in {int(p) for n in names for p in n.split(".") if p.isdigit()}


def test_all_or_nothing_keeps_the_earlier_set_when_a_write_fails(tmp_path):
    """In a block, the first file is complete when the second fails (a full disk): neither
    replaces its target, no temporary file is left, and the error names the file and says
    the disk is full."""
    _io.write_text(tmp_path / "a.txt", "old a")
    _io.write_text(tmp_path / "b.txt", "old b")
    with pytest.raises(OSError, match="b.txt.*the disk is full"):
        with _io.all_or_nothing():
            _io.write_text(tmp_path / "a.txt", "new a")
            with _io.atomic_file(tmp_path / "b.txt") as fh:
                fh.write(b"new b")
                raise OSError(errno.ENOSPC, "No space left on device")
    assert _snapshot(tmp_path) == {"a.txt": b"old a", "b.txt": b"old b"}
    with _io.all_or_nothing():
        _io.write_text(tmp_path / "a.txt", "new a")
        _io.write_text(tmp_path / "b.txt", "new b")
    assert _snapshot(tmp_path) == {"a.txt": b"new a", "b.txt": b"new b"}


def test_a_rename_that_fails_leaves_no_temporary_file(tmp_path):
    """A folder where an output goes: its rename fails at the end of the block, with an error
    naming it, and none of the block's temporary files is left (they were before)."""
    (tmp_path / "b.txt").mkdir()
    with pytest.raises(OSError, match="b.txt"):
        with _io.all_or_nothing():
            _io.write_text(tmp_path / "a.txt", "new a")
            _io.write_text(tmp_path / "b.txt", "new b")
            _io.write_text(tmp_path / "c.txt", "new c")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt", "b.txt"]
    assert not _io.PARTIAL


def test_errormap_over_the_file_size_limit_leaves_the_earlier_outputs(tmp_path, capsys):
    """`dampax errormap` under a file size limit (as `ulimit -f`) that the netCDF file fits
    but the figure does not: exit 2 with one line naming the figure and the limit; the
    earlier errormap.nc and max_error.png are there byte for byte, and nothing else."""
    assert main(CLI + ["--out", str(tmp_path)]) == 0
    before = _snapshot(tmp_path)
    assert set(before) == {"errormap.nc", "max_error.png"}
    capsys.readouterr()
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    limit = len(before["errormap.nc"]) + 4096
    assert limit < len(before["max_error.png"])
    resource.setrlimit(resource.RLIMIT_FSIZE, (limit, hard))
    try:
        status = main(CLI + ["--out", str(tmp_path)])
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
    _, err = capsys.readouterr()
    assert status == 2
    assert "max_error.png" in err and "file size limit" in err and err.count("\n") == 1
    assert _snapshot(tmp_path) == before


@pytest.mark.parametrize("processes", [None, 2])
def test_sigterm_leaves_no_temporary_file_or_folder(tmp_path, processes):
    """SIGTERM (as a batch system sends at its time limit) during `dampax errormap`: exit 143
    with one line; no output, no temporary file in the output folder, and (with --processes 2)
    no temporary folder of the workers, which end with the command."""
    out = tmp_path / "maps"
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    env = dict(os.environ, TMPDIR=str(scratch))
    argv = ["errormap", "--out", str(out), "--no-progress", "--quick"]
    if processes:
        argv += ["--processes", str(processes)]
    proc = subprocess.Popen([sys.executable, "-u", "-m", "dampax._cli", *argv],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    header = proc.stdout.readline()
    assert header.startswith("dampax errormap: "), header
    deadline = time.monotonic() + 20
    while processes and not list(scratch.glob("dampax-map-*/worker1.log")):
        assert time.monotonic() < deadline, "the workers did not start"
        time.sleep(0.1)
    time.sleep(0.5)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 143, err
    assert err.strip().endswith("dampax: terminated")
    assert list(out.iterdir()) == []
    time.sleep(0.5)  # the workers see their stdin close
    assert list(scratch.iterdir()) == []


def test_work_beside_the_command_is_awaited_and_its_error_raised():
    """A fit's figure is drawn in a thread beside the model ranking (``_common.beside``):
    leaving the block waits for it, also when the block fails (no thread writes after the
    command has ended), and its own error is raised where its result is asked for."""
    import threading

    from dampax._cli._common import beside

    release = threading.Event()

    def slow():
        release.wait(5.0)
        time.sleep(0.05)
        return "drawn"

    with pytest.raises(KeyError):
        with beside(slow) as figure:
            release.set()
            raise KeyError("the ranking failed")
    assert figure.done() and figure.result() == "drawn"

    def broken():
        raise OSError(errno.ENOSPC, "No space left on device")

    with beside(broken) as figure:
        pass
    with pytest.raises(OSError, match="No space left"):
        figure.result()
