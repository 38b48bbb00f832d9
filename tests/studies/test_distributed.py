"""Error maps over several processes (jax.distributed on 127.0.0.1, CPU devices, gloo).

The map of two local worker processes is the one-process map bit for bit; a worker that dies
makes the run (dampax errormap --processes 2) fail at once with a message that names it, and
nothing is written; a process of a joined run (--coordinator) whose peer died, or that nobody
joins, ends within its --timeout with one line and status 3. The map has the settings of
tests/reference/test_speed.py's cached-step test (a 2 x 2 x 2 grid, 3 periods, the DOP853
reference, one model), two steps of 4 points: one per process.
"""

import os
import pickle
import subprocess
import sys
import textwrap
import time

import jax
import numpy as np
import pytest

from dampax._cli import main
from dampax._studies._distributed import KILL_ENV, free_port
from dampax._studies._maps import error_map

SMALL = dict(d0_ratio=[0.0, 0.04], d2_ratio=[0.0, 0.3], phi0=[0.0, 2.0], periods=3.0,
             samples_per_period=16, chunk_size=4, models=("matched",), progress=False)
CLI = ["errormap", "--d0", "0,0.04", "--d2", "0,0.3", "--phi0", "0,2", "--periods", "3",
       "--samples-per-period", "16", "--chunk-size", "4", "--models", "matched", "--no-progress"]


#: local worker processes share this host's devices: on a CPU its cores, on a GPU host the
#: host's CPU too (two processes on one GPU would be two NCCL ranks on one device), so there the
#: processes, and the one-process map they must equal bit for bit, run on the CPU
ON_CPU = jax.default_backend() == "cpu"
ONE_ON_CPU = textwrap.dedent("""
    import pickle, sys
    import dampax
    from dampax._studies._maps import error_map
    with open(sys.argv[1], "wb") as f:
        pickle.dump(error_map(**eval(sys.argv[2])), f)
""")


@pytest.fixture(scope="module", autouse=True)
def host_platform():
    with pytest.MonkeyPatch.context() as mp:
        if not ON_CPU:  # the workers (and the CLI's) inherit it
            mp.setenv("JAX_PLATFORMS", "cpu")
        yield


@pytest.fixture(scope="module")
def one(tmp_path_factory, host_platform):
    if ON_CPU:
        return error_map(**SMALL)
    path = tmp_path_factory.mktemp("one") / "one.pickle"
    subprocess.run([sys.executable, "-c", ONE_ON_CPU, str(path), repr(SMALL)], check=True)
    with open(path, "rb") as f:
        return pickle.load(f)


def assert_same_bits(a, b):
    assert list(a.data_vars) == list(b.data_vars) and set(a.coords) == set(b.coords)
    for name in list(a.data_vars) + list(a.coords):
        x, y = np.asarray(a[name]), np.asarray(b[name])
        assert x.dtype == y.dtype and x.shape == y.shape, name
        if x.dtype.kind in "fb":
            assert x.tobytes() == y.tobytes(), name  # bit for bit, NaNs included
        else:
            assert x.tolist() == y.tolist(), name


def test_two_processes_give_the_one_process_map_bit_for_bit(one):
    two = error_map(**SMALL, processes=2)
    assert_same_bits(one, two)
    for name in one.data_vars:
        assert one[name].attrs.keys() == two[name].attrs.keys(), name
    assert two.attrs["devices"] == "1 x cpu, 2 process(es)"
    assert one.attrs["devices"] == "1 x cpu, 1 process(es)"
    assert {k: str(v) for k, v in one.attrs.items() if k not in ("devices", "history")} == \
        {k: str(v) for k, v in two.attrs.items() if k not in ("devices", "history")}
    assert np.isfinite(np.asarray(two["max_error"])).all()


def test_a_worker_that_dies_fails_the_run_at_once_and_writes_nothing(tmp_path, capsys,
                                                                     monkeypatch):
    monkeypatch.setenv(KILL_ENV, "1")  # worker 1 kills itself (SIGKILL) at the gather
    start = time.perf_counter()
    assert main(CLI + ["--processes", "2", "--out", str(tmp_path)]) == 3
    assert time.perf_counter() - start < 120
    err = capsys.readouterr().err
    assert err.startswith("dampax: error: error map over 2 processes failed: worker 1 was "
                          "killed by SIGKILL"), err
    assert "no map was written" in err and "Traceback" not in err
    assert list(tmp_path.iterdir()) == []  # no errormap.nc, no partial file, no figure


def _join(i: int, port: int, out, timeout: float, **env):
    return subprocess.Popen(
        [sys.executable, "-m", "dampax._cli", *CLI, "--coordinator", f"127.0.0.1:{port}",
         "--process-id", str(i), "--num-processes", "2", "--timeout", str(timeout),
         "--out", str(out)],
        env=os.environ | env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def test_a_joined_run_whose_peer_dies_ends_within_its_timeout(tmp_path):
    """Two processes of a --coordinator run (as under srun): process 1 dies at the gather;
    process 0 waits there at most --timeout, then prints one line and exits with status 3."""
    port = free_port()
    start = time.perf_counter()
    procs = [_join(i, port, tmp_path, 10, **{KILL_ENV: "1"}) for i in (0, 1)]
    results = [p.communicate(timeout=180) for p in procs]
    elapsed = time.perf_counter() - start
    assert procs[1].returncode == -9
    assert procs[0].returncode == 3, results[0][1][-3000:]
    err = results[0][1]
    assert "dampax: error: process 0 of 2 waited up to 10 s for the other processes" in err
    assert elapsed < 120
    assert list(tmp_path.iterdir()) == []


def test_a_joined_run_nobody_joins_ends_within_its_timeout(tmp_path):
    start = time.perf_counter()
    proc = _join(0, free_port(), tmp_path, 3)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 3, err[-3000:]
    assert err.startswith("dampax: error: could not join the jax.distributed run at "
                          "127.0.0.1:"), err
    assert "within 3 s" in err
    assert time.perf_counter() - start < 60


@pytest.mark.parametrize("args, flag", [
    (["--processes", "0"], "--processes"),
    (["--processes", "2", "--cluster"], "--processes"),
    (["--cluster", "--coordinator", "h:1"], "--cluster"),
    (["--coordinator", "127.0.0.1:1234", "--num-processes", "2"], "--process-id"),
    (["--coordinator", "nohost", "--process-id", "0", "--num-processes", "2"], "--coordinator"),
    (["--coordinator", "h:1", "--process-id", "2", "--num-processes", "2"], "--process-id"),
    (["--timeout", "0"], "--timeout"),
])
def test_cli_bad_options_exit_2(args, flag, tmp_path, capsys):
    assert main(CLI + args + ["--out", str(tmp_path / "out")]) == 2
    assert capsys.readouterr().err.startswith(f"dampax: error: {flag}")


@pytest.mark.parametrize("change, name", [
    (dict(processes=0), "processes"), (dict(processes=1.5), "processes"),
    (dict(timeout=0.0), "timeout"), (dict(timeout=float("inf")), "timeout"),
])
def test_bad_input_names_the_argument(change, name):
    with pytest.raises(ValueError, match=rf"^{name}\b"):
        error_map(**SMALL | change)
