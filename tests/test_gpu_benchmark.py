"""benchmarks/gpu.py on a machine without a GPU: one clear line, exit status 0, nothing
measured (on a GPU host the same path is taken with the backend reported as the CPU)."""

import runpy
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "gpu.py"


def test_gpu_benchmark_on_a_cpu_says_so_and_exits_cleanly(capsys, monkeypatch):
    bench = runpy.run_path(str(SCRIPT), run_name="gpu_benchmark")
    monkeypatch.setattr(bench["jax"], "default_backend", lambda: "cpu")
    monkeypatch.setitem(bench["main"].__globals__, "timed", None)  # nothing may be timed
    assert bench["main"]([]) == 0
    out = capsys.readouterr().out
    assert out.startswith("benchmarks/gpu.py: no GPU here") and "nothing measured" in out
    assert 'pip install -U "jax[cuda12]"' in out and "--cpu" in out
