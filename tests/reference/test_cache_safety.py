"""The kept programs cannot be turned against the user (issue 37, item 1).

A planted file runs no code; a file kept for other options, under another name, or by another
version is refused; a folder or file that is not the user's own, or that others can write, is
refused with a warning; a damaged file (a flipped byte, a truncated file, a FIFO, a link) is
set aside and the program built again, never fatal and never a hang. Each check compares the
result with the one computed without any cache (the independent number) and looks for the
planted code's marker file.

One tiny program (``3 x + 1`` over three floats) serves every test: the mechanism, not the
program, is tested, and it compiles in milliseconds.
"""

import os
import pickle
import stat
import subprocess
import sys
import threading
import time
import warnings

import jax.numpy as jnp
import numpy as np
import pytest

import dampax_cli
from dampax import _cache, _cachefiles, _cachethreads


def _fn(x):
    return {"y": 3.0 * x + 1.0, "n": jnp.sum(x)}


X = jnp.asarray([0.5, 1.5, -2.0])
EXPECTED = 3.0 * np.asarray(X) + 1.0


@pytest.fixture
def cache(tmp_path, monkeypatch):
    """A fresh private cache folder for this test, and an empty in-process memo."""
    folder = tmp_path / "cache"
    monkeypatch.setenv("DAMPAX_CACHE_DIR", str(folder))
    monkeypatch.setattr(_cache, "_EXECUTABLES", {})
    _cache._key.cache_clear()
    _cache._WARNED.clear()
    yield folder
    _cache._key.cache_clear()


def _call(key="k"):
    _cache._EXECUTABLES.clear()  # as a new process would
    out = _cache.call_cached("safety", key, _fn, X)
    np.testing.assert_array_equal(np.asarray(out["y"]), EXPECTED)
    return out


def _kept(folder, suffix):
    files = sorted((folder / "exported").glob(f"safety-*{suffix}"))
    assert len(files) == 1, files
    return files[0]


class _Bomb:
    """Pickled, it runs a shell command when unpickled."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


def _aside(folder):
    return list((folder / "exported" / "rejected").glob("*"))


def _export_route(monkeypatch):
    """Programs kept as ``jax.export`` files (``.jaxcall``) beside their executables, as for a
    program whose executable alone cannot be kept (a fresh program otherwise goes straight
    from its trace to a kept executable: ``_cache._compile_kept``)."""
    monkeypatch.setattr(_cache, "_compile_kept", lambda *args: None)


def _only_program(folder, suffix):
    """Where ``suffix`` is the program (.jaxcall), its executable goes: the program is read
    only when no executable was kept."""
    if suffix == ".jaxcall":
        _kept(folder, ".jaxexe").unlink()


@pytest.mark.parametrize("suffix", [".jaxcall", ".jaxexe"])
@pytest.mark.parametrize("layout", ["old", "new"])
def test_planted_pickle_runs_nothing(cache, tmp_path, suffix, layout, monkeypatch):
    """A pickle that runs a shell command, planted under a kept program's name (in the old
    layout: length + pickle + payload; in the new one: a header and a wrong checksum), is
    refused before anything of it is read; the result is the computed one."""
    if suffix == ".jaxcall":
        _export_route(monkeypatch)
    _call()
    _only_program(cache, suffix)
    marker = tmp_path / "pwned"
    bomb = pickle.dumps(_Bomb(marker))
    if layout == "old":
        data = len(bomb).to_bytes(8, "little") + bomb + b"\0" * 64
    else:
        head = b'{"digest": "x", "trees": ""}'
        data = _cache._MAGIC + len(head).to_bytes(8, "little") + head + bomb + b"\0" * 32
    _kept(cache, suffix).write_bytes(data)
    with pytest.warns(_cache.CacheWarning, match="checksum does not verify"):
        _call()
    assert not marker.exists()
    assert _aside(cache)


def test_a_program_kept_for_other_options_is_not_taken_for_the_default(cache, monkeypatch):
    """A verified file of another key (another rtol, say), copied under the default's name, is
    refused (its header names another program); the default's numbers come back."""
    _export_route(monkeypatch)
    _call("default")
    default = _kept(cache, ".jaxcall")
    for f in (cache / "exported").glob("safety-*"):
        f.rename(f.with_name("other-" + f.name))  # keep the default's files out of the way
    _cache._EXECUTABLES.clear()
    other = _cache.call_cached("safety", "rtol=1e-3", lambda x: {"y": 0.0 * x, "n": x[0]}, X)
    assert float(other["y"][0]) == 0.0
    _kept(cache, ".jaxcall").rename(default)
    with pytest.warns(_cache.CacheWarning, match="other settings or versions"):
        _call("default")


def test_digest_covers_the_versions_of_what_shapes_the_program(monkeypatch):
    """Another equinox (or optimistix, lineax, jaxlib) gives another digest, so another file."""
    import importlib.metadata as metadata

    real = metadata.version
    before = _cache._digest("p")
    for package in ("equinox", "optimistix", "lineax", "jaxlib"):
        monkeypatch.setattr(metadata, "version",
                            lambda name, p=package: "9.9.9" if name == p else real(name))
        _cache._source_digest.cache_clear()
        assert _cache._digest("p") != before, package
    monkeypatch.setattr(metadata, "version", real)
    _cache._source_digest.cache_clear()
    assert _cache._digest("p") == before


@pytest.mark.parametrize("damage", ["flip", "truncate", "fifo", "link", "empty", "huge"])
@pytest.mark.parametrize("suffix", [".jaxcall", ".jaxexe"])
def test_damaged_files_are_set_aside_and_rebuilt(cache, tmp_path, damage, suffix, monkeypatch):
    """A flipped byte, a truncated file, a FIFO (would block a plain read), a link to another
    file, an empty file, a file over the size limit: set aside with a warning, rebuilt, same
    numbers; the next call reads the rebuilt file without a warning."""
    if suffix == ".jaxcall":
        _export_route(monkeypatch)
    _call()
    _only_program(cache, suffix)
    path = _kept(cache, suffix)
    data = path.read_bytes()
    path.unlink()
    if damage == "flip":
        path.write_bytes(data[:100] + bytes([data[100] ^ 1]) + data[101:])
    elif damage == "truncate":
        path.write_bytes(data[: len(data) // 2])
    elif damage == "fifo":
        os.mkfifo(path)
    elif damage == "link":
        target = tmp_path / "elsewhere"
        target.write_bytes(data)
        path.symlink_to(target)
    elif damage == "empty":
        path.write_bytes(b"")
    else:
        path.write_bytes(data)
        monkeypatch.setattr(_cachefiles, "MAX_FILE_BYTES", len(data) - 1)
    with pytest.warns(_cache.CacheWarning, match="set aside"):
        _call()
    assert _aside(cache)
    monkeypatch.setattr(_cachefiles, "MAX_FILE_BYTES", 1 << 30)
    rebuilt = _kept(cache, suffix)
    assert stat.S_ISREG(os.lstat(rebuilt).st_mode)
    with warnings.catch_warnings():
        warnings.simplefilter("error", _cache.CacheWarning)
        _call()


@pytest.mark.skipif(os.name == "nt", reason="POSIX owners and modes")
def test_folder_others_can_write_is_not_used(cache):
    """A cache folder that the group can write (a DAMPAX_CACHE_DIR on a shared file system):
    a warning, no file read or written there, the right numbers."""
    cache.mkdir(mode=0o700)
    os.chmod(cache, 0o770)
    with pytest.warns(_cache.CacheWarning, match="other users can write"):
        assert _cache.exported_dir() is None
        _call()
    assert not (cache / "exported").exists() and not (cache / "key").exists()


@pytest.mark.skipif(os.name == "nt", reason="POSIX owners and modes")
def test_files_of_another_user_are_refused(cache, monkeypatch):
    """Files that belong to another user id (here: this process pretends to be another user
    after the files were written) are refused; so is their folder."""
    _call()
    monkeypatch.setattr(os, "getuid", lambda: os.stat(cache).st_uid + 1)
    with pytest.warns(_cache.CacheWarning, match="belongs to user id"):
        _call()


@pytest.mark.skipif(os.name == "nt", reason="POSIX owners and modes")
def test_key_readable_by_others_is_replaced(cache):
    """The HMAC key must be private (0600): one that others can read is set aside and a new
    one made; files signed with the old key are then refused and rebuilt."""
    _call()
    key = cache / "key"
    old = key.read_bytes()
    os.chmod(key, 0o644)
    _cache._key.cache_clear()
    with pytest.warns(_cache.CacheWarning):
        _call()
    assert key.read_bytes() != old and stat.S_IMODE(os.stat(key).st_mode) == 0o600


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs")
def test_jax_cache_folder_is_swept_of_fifos_and_links(cache):
    """JAX reads its own cache entries without a check: a FIFO there would hang every later
    compile and a link could point anywhere. Turning the cache on sets both aside and removes
    temporary files that killed writers left; entries and folders stay."""
    jax_dir = cache / "jax"
    jax_dir.mkdir(parents=True, mode=0o700)
    os.chmod(cache, 0o700)
    os.mkfifo(jax_dir / "jit_f-0123-cache")
    (jax_dir / "jit_g-4567-cache").symlink_to("/etc/passwd")
    stale = jax_dir / ".jit_h-89ab-cache.k2j4.part"  # a writer killed two hours ago
    stale.write_bytes(b"half")
    os.utime(stale, (time.time() - 7200, time.time() - 7200))
    (jax_dir / "jit_i-cdef-cache").write_bytes(b"an entry")
    with pytest.warns(_cache.CacheWarning, match="not a regular file"):
        _cache._sweep(jax_dir)
    assert sorted(p.name for p in jax_dir.iterdir()) == ["jit_i-cdef-cache", "rejected"]
    assert len(list((jax_dir / "rejected").iterdir())) == 2
    _cache._sweep(jax_dir)  # rejected/ stays where it is
    assert len(list((jax_dir / "rejected").iterdir())) == 2


def test_tree_structures_round_trip_as_json_without_pickle():
    """The kept tree structure of a real output (a solution: equinox modules, an enumeration,
    None leaves) survives its JSON form; a class outside dampax/equinox is refused."""
    import jax

    import dampax as dp

    sol = dp.solve(dp.Oscillator(m=1.0, k=30.0, mu=0.02, D=1.5), 0.2, 0.0, phase="undamped")
    kept = (jax.tree_util.tree_structure((sol, 1)), {3: "name", 5: 2.5, 7: None}, (True,))
    blob = _cache._dump_tree(kept)
    assert b"pickle" not in blob and _cache._load_tree(blob) == kept
    with pytest.raises(ValueError, match="names the class"):
        _cache._load_tree(b'{"c": ["os", "system"]}')
    with pytest.raises(ValueError, match="not a class"):
        _cache._load_tree(b'{"c": ["dampax", "solve"]}')


def test_a_prepared_program_is_built_once_in_the_background(cache, monkeypatch):
    """``prepare_cached`` builds the program in a thread; the first call awaits it (one
    build, the same result as without any cache); a build that fails in the thread is built
    again by the call, which raises the error itself."""
    built = []
    compile_tree = _cache._compile_tree
    monkeypatch.setattr(_cache, "_compile_tree",
                        lambda *a: built.append(a[0]) or compile_tree(*a))
    _cache.prepare_cached("safety", "bg", _fn, jnp.zeros(3))  # any values of the shapes
    _cache.prepare_cached("safety", "bg", _fn, X)  # already under way: not started again
    out = _cache.call_cached("safety", "bg", _fn, X)
    np.testing.assert_array_equal(np.asarray(out["y"]), EXPECTED)
    assert built == ["safety"]

    def broken(x):
        raise RuntimeError("no program here")

    _cache.prepare_cached("broken", "bg", broken, X)
    with pytest.raises(RuntimeError, match="no program here"):
        _cache.call_cached("broken", "bg", broken, X)
    assert built == ["safety", "broken", "broken"]


def test_kept_arrays_are_verified_and_read_without_pickle(cache, tmp_path):
    """``kept_arrays`` (the example trace of ``dampax fit --example``): made once, then read
    back equal without calling ``make``; another key makes them again; a file whose payload
    is replaced by a pickle that would run code (the header kept, the HMAC now wrong) is set
    aside with a warning and the arrays made again, and the planted code never runs."""
    calls = []

    def make():
        calls.append(1)
        return {"x": np.linspace(0.0, 1.0, 7) ** 3, "n": np.arange(4)}

    first = _cache.kept_arrays("arrays", ("k", 1), make)
    again = _cache.kept_arrays("arrays", ("k", 1), make)
    assert len(calls) == 1
    for k in first:
        np.testing.assert_array_equal(again[k], first[k])
    _cache.kept_arrays("arrays", ("k", 2), make)
    assert len(calls) == 2
    for path in (cache / "exported").glob("arrays-*.npz"):
        data = path.read_bytes()
        start = len(_cachefiles._MAGIC) + 8
        size = int.from_bytes(data[len(_cachefiles._MAGIC):start], "little")
        bomb = pickle.dumps(np.asarray([_Bomb(tmp_path / "planted")], dtype=object))
        path.write_bytes(data[:start + size] + bomb + data[-_cachefiles._TAG:])
    with pytest.warns(_cache.CacheWarning, match="set aside"):
        out = _cache.kept_arrays("arrays", ("k", 1), make)
    assert len(calls) == 3 and not (tmp_path / "planted").exists()
    np.testing.assert_array_equal(out["x"], first["x"])


def test_kept_programs_are_held_to_their_size_least_recently_used_first(cache, monkeypatch):
    """The kept programs' folder grows by a set of programs at every change of dampax or its
    versions; turning the cache on removes the least recently used files while they take more
    than ``DAMPAX_CACHE_MAX_MB``, down to 3/4 of it. Loading a kept program sets its access time
    (not its modification time): an old file just used stays, files not read go first; 0 means
    no limit."""
    exported = cache / "exported"
    _call()  # a real kept program, then old files around it
    program = _kept(cache, ".jaxexe")
    now = time.time()
    old = []
    for i in range(6):  # 6 x 0.2 MiB, the oldest first
        path = exported / f"old-{i}.jaxexe"
        path.write_bytes(b"x" * (200 << 10))
        os.utime(path, (now - 86400 * (10 - i),) * 2)
        old.append(path)
    os.utime(program, (now - 86400 * 30,) * 2)  # older than all of them ...
    written = program.stat().st_mtime_ns
    _call()  # ... but loaded now: its access time (read, not written)
    assert program.stat().st_atime > now - 60 and program.stat().st_mtime_ns == written
    monkeypatch.setenv("DAMPAX_CACHE_MAX_MB", "0")
    _cache._sweep(exported, kept=True)
    assert all(p.exists() for p in old)
    monkeypatch.setenv("DAMPAX_CACHE_MAX_MB", "1")  # 1.2 MiB + the program > 1 MiB
    _cache._sweep(exported, kept=True)
    left = sorted(p.name for p in exported.glob("old-*"))
    size = sum(p.stat().st_size for p in exported.iterdir() if p.is_file())
    assert program.exists() and size <= 3 * (1 << 20) // 4, (left, size)
    assert left == [f"old-{i}.jaxexe" for i in range(6 - len(left), 6)] and left  # newest kept
    _call()  # the program still loads


@pytest.fixture
def command(cache, monkeypatch):
    """The console script's command line set (``dampax_cli.COMMAND``), and the loads ahead of
    an earlier command forgotten, as in a new process."""
    threads = _cachethreads
    monkeypatch.setattr(dampax_cli, "COMMAND", ("safety", "--example"))
    for name in ("_PENDING", "_USED", "_LISTED"):
        monkeypatch.setattr(threads, name, type(getattr(threads, name))())
    monkeypatch.setattr(threads, "_DONE", threads.threading.Event())
    return threads


def _prefetch(threads):
    """Start the loads ahead of the command (as ``import dampax`` does) and wait for them."""
    threads.start_prefetch(_cache.exported_dir)
    for t in threading.enumerate():
        if t.name == "dampax-prefetch":
            t.join(timeout=60)
    return dict(threads._PENDING)


def test_a_command_s_programs_load_ahead_of_its_next_run(command):
    """A command of the console script leaves the list of the programs it used; its next run
    loads them while dampax imports and its call takes that load: the kept file, removed
    after the load ahead, is not read again and not rebuilt (the same result as without any
    cache). A list that names another program's file loads it, yet the call does not take
    it (its digest is another), and builds its own program."""
    with command.recording(_cache.exported_dir):
        _call()
    lists = list((_cache.exported_dir()).glob("command-*.loads"))
    exe = _kept(_cache.exported_dir().parent, ".jaxexe")
    assert len(lists) == 1 and exe.exists()

    _cache._EXECUTABLES.clear()
    pending = _prefetch(command)
    assert list(pending) == [str(exe)]
    exe.unlink()  # the call must take the program loaded ahead
    with command.recording(_cache.exported_dir):
        _call()
    assert not command._PENDING and not exe.exists()  # taken, not built again

    # the same list, the file now another program's: loaded ahead, not taken
    command._LISTED.clear()
    _call(key="other")  # keeps the program of key "other"
    other = next(p for p in _cache.exported_dir().glob("safety-*.jaxexe"))
    other.rename(exe)
    _cache._EXECUTABLES.clear()
    assert list(_prefetch(command)) == [str(exe)]
    with pytest.warns(_cache.CacheWarning, match="other settings"):  # the file, read again
        _call()  # key "k": not the loaded program; built (and its result right)
    assert not command._PENDING


def test_a_planted_or_foreign_list_loads_nothing(command):
    """A list file another user planted (its checksum does not verify) is set aside and loads
    nothing; a verified list's names outside the folder (a path, not a file name) are
    skipped; without the console script's command (library use) nothing starts."""
    _call()
    exe = _kept(_cache.exported_dir().parent, ".jaxexe")
    path, digest = command._list_file(_cache.exported_dir(), command._command())
    _cachefiles._write_entry(path, digest, {"kind": "loads",
                                            "names": ["../x.jaxexe", "/etc/x.jaxexe",
                                                      exe.name]}, b"")
    assert list(_prefetch(command)) == [str(exe)]

    data = bytearray(path.read_bytes())
    data[-40] ^= 1
    path.write_bytes(bytes(data))
    command._PENDING.clear()
    with pytest.warns(_cache.CacheWarning, match="checksum"):
        assert _prefetch(command) == {}
    assert _aside(_cache.exported_dir().parent)

    dampax_cli.COMMAND = None  # (the fixture restores it)
    called = []
    command.start_prefetch(lambda: called.append(1))
    assert not called and not command._PENDING


def test_import_dampax_loads_the_console_command_s_programs_ahead(command):
    """The wiring: the console script names its command before it imports dampax
    (``dampax_cli.COMMAND``), and ``import dampax`` starts loading that command's programs
    (a fresh process, the list and the program of this test's cache)."""
    with command.recording(_cache.exported_dir):
        _call()
    exe = _kept(_cache.exported_dir().parent, ".jaxexe")
    code = ("import dampax_cli; dampax_cli.COMMAND = ('safety', '--example'); import dampax; "
            "from dampax import _cachethreads as t; print(sorted(t._PENDING))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env=dict(os.environ), check=True, timeout=120)
    assert out.stdout.strip() == repr([str(exe)])
