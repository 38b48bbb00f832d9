"""dampax.error_map: one point against scipy, devices, units, chunking, bad input, the CLI.

The map with the diffrax reference compiles for ~40 s, so one map (the settings of
``dampax errormap --quick``) is computed once and reused: by the CLI test (same settings, so the
compiled step is reused) and by the scaling tests against scipy in two unit systems. The
4-device run starts in a subprocess at the first test of this module and runs beside the rest.
"""

import math
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import equinox as eqx
import jax
import numpy as np
import pytest
import xarray as xr
from helpers import check_cf_file, evaluate, ratios_to_constants, scipy_stick_slip

import dampax as dp
import dampax._studies._maps as maps
from dampax._cli import main
from dampax._studies._maps import error_map

# count the traces (compilations) of the per-point function (equinox.debug), for the whole module
maps._per_point = eqx.debug.assert_max_traces(maps._per_point, max_traces=None)


def trace_count() -> int:
    return eqx.debug.get_num_traces(maps._per_point)


@pytest.fixture(scope="module", autouse=True)
def no_exported_programs():
    """Trace counts need the serialized-program cache off (``DAMPAX_CACHE=0`` is read per call):
    a program loaded from ``exported/`` is not traced, and an earlier test may have written it."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("DAMPAX_CACHE", "0")
        yield


# the settings of `dampax errormap --quick` (keep in step with dampax_cli._arguments.ERRORMAP_QUICK)
QUICK = dict(d0_ratio=np.linspace(0.0, 0.1, 4), d1_ratio=np.array([0.0]),
             d2_ratio=np.linspace(0.0, 0.75, 4), phi0=np.array([0.0, math.pi / 2]),
             periods=10.0, samples_per_period=32, chunk_size=32, progress=False)
MODELS = maps.DEFAULT_MODELS
METRICS = ("max_error", "rms_error", "energy_error", "halt_time_error", "halt_position_error")
FLAGS = ("valid", "reference_valid")  # bool, written as bytes 0 / 1 with CF flag attributes

FOUR_DEVICES = textwrap.dedent("""
    import os, sys
    os.environ["XLA_FLAGS"] = "--xla_force_host_platform_device_count=4"
    import math
    import jax
    import numpy as np
    import dampax as dp
    from dampax._studies._maps import error_map
    # the forced host devices are the devices on a CPU; on a GPU host, the GPUs it has
    assert jax.default_backend() != "cpu" or len(jax.devices()) == 4, jax.devices()
    ds = error_map(d0_ratio=np.linspace(0.0, 0.1, 4), d1_ratio=np.array([0.0]),
                   d2_ratio=np.linspace(0.0, 0.75, 4), phi0=np.array([0.0, math.pi / 2]),
                   periods=10.0, samples_per_period=32, chunk_size=3, progress=False,
                   models=("matched_tail",))
    ds.to_netcdf(sys.argv[1], engine="scipy")
""")


@pytest.fixture(scope="module", autouse=True)
def four_devices(tmp_path_factory):
    """The quick map on 4 (forced host) devices, 3 points per device per step, in a subprocess.

    XLA_FLAGS must be set before jax is imported, hence the separate interpreter. Only the
    matched + Coulomb tail model (it contains the plain ansatz) is mapped there, to halve the
    compilation; every model is computed independently of the others.
    """
    path = tmp_path_factory.mktemp("devices") / "four.nc"
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    proc = subprocess.Popen([sys.executable, "-c", FOUR_DEVICES, str(path)], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    yield proc, path
    if proc.poll() is None:
        proc.kill()
        proc.communicate()


@pytest.fixture(scope="module")
def quick_map():
    before = trace_count()
    ds = error_map(**QUICK)
    assert trace_count() == before + 1  # one compilation for all the steps
    return ds


def test_layout_and_attrs(quick_map, tmp_path):
    ds = quick_map
    assert ds["max_error"].dims == ("model", "d0_ratio", "d1_ratio", "d2_ratio", "phi0")
    assert ds["max_error"].shape == (4, 4, 1, 4, 2)
    assert list(ds["model"].values) == list(MODELS)
    for name in METRICS + ("valid",):
        assert name in ds and "long_name" in ds[name].attrs
    # CF conventions: dimensionless variables in units "1", the normalisation in long_name
    for name in METRICS + ("window", "reference_halt_time"):
        assert ds[name].attrs["units"] == "1", name
    assert "/ A0" in ds["max_error"].attrs["long_name"]
    assert ds.attrs["Conventions"] == "CF-1.10"
    assert ds.attrs["source"].startswith(f"dampax {dp.__version__}")
    assert "dampax.error_map(" in ds.attrs["history"]
    assert bool(ds["reference_valid"].all())
    for key in ("periods", "samples_per_period", "dampax_version", "reference_rtol",
                "reference_atol"):
        assert key in ds.attrs
    assert ds.attrs["dampax_version"] == dp.__version__
    # Rizcallah's model exists only without quadratic drag; the others everywhere here
    valid = ds["valid"]
    assert bool(valid.sel(model="rizcallah", d2_ratio=0.0).all())
    assert not bool(valid.sel(model="rizcallah").isel(d2_ratio=slice(1, None)).any())
    assert bool(np.isnan(ds["max_error"].sel(model="rizcallah").isel(d2_ratio=1)).all())
    assert bool(valid.sel(model=["matched", "undamped", "matched_tail"]).all())
    # no friction: no halt position error; no damping at all: every model exact
    assert bool(np.isnan(ds["halt_position_error"].sel(d0_ratio=0.0)).all())
    assert float(ds["max_error"].sel(d0_ratio=0.0, d2_ratio=0.0).max()) < 1e-8
    # the quick grid's damped points all stop or fade within the window
    assert float(ds["window"].max()) <= 10.0 + 1e-9
    # netCDF round trip with the scipy engine; a plain to_netcdf is CF-clean too (no _FillValue
    # on the coordinates, the two flags with flag_values / flag_meanings)
    path = tmp_path / "map.nc"
    ds.to_netcdf(path, engine="scipy")
    back = xr.load_dataset(path, engine="scipy")
    xr.testing.assert_allclose(back, ds)
    assert back["valid"].dtype == bool and back["reference_valid"].dtype == bool
    check_cf_file(path, flags=FLAGS)


@pytest.mark.parametrize("m, k, A0", [(1.0, 30.0, 0.2), (2.0, 50.0, 0.3)])
def test_point_matches_scipy_in_other_units(quick_map, m, k, A0):
    """One map point (computed at w0 = A0 = 1) recomputed with scipy for the paper's block and
    for m = 2 kg, k = 50 N/m, A0 = 0.3 m with the same ratios: the map holds in every unit."""
    d0r, d2r, phi0 = float(QUICK["d0_ratio"][1]), float(QUICK["d2_ratio"][1]), math.pi / 2
    w0 = math.sqrt(k / m)
    mu, b, D = ratios_to_constants(d0r, 0.0, d2r, m=m, k=k, A0=A0)
    x0, v0 = A0 * math.cos(phi0), -w0 * A0 * math.sin(phi0)
    period = 2 * math.pi / w0
    t = np.arange(int(QUICK["periods"] * QUICK["samples_per_period"]) + 1) * (
        period / QUICK["samples_per_period"])
    segments, _, rest = scipy_stick_slip(m, k, mu, b, D, x0, v0, t[-1])
    x_ref, v_ref = evaluate(segments, rest, t)
    if rest is not None:
        window = t <= rest[0]
    else:
        energy = 0.5 * k * x_ref**2 + 0.5 * m * v_ref**2
        window = np.cumsum(energy < 1e-4 * 0.5 * k * A0**2) == 0
    sol = dp.solve(dp.Oscillator(m=m, k=k, mu=mu, b=b, D=D), x0, v0, method="ansatz")
    expected = np.max(np.abs(np.asarray(sol.x(t[window])) - x_ref[window])) / A0
    got = float(quick_map["max_error"].sel(model="matched", d0_ratio=d0r, d2_ratio=d2r,
                                           phi0=phi0).squeeze())
    assert got == pytest.approx(expected, rel=0.02)
    assert 1e-3 < got < 0.2  # a damped point, not a trivial one


def test_same_map_on_four_devices(quick_map, four_devices):
    proc, path = four_devices
    _, err = proc.communicate(timeout=400)
    assert proc.returncode == 0, err
    four = xr.load_dataset(path, engine="scipy")
    # sharded over 4 host devices on a CPU; on another platform (a GPU host) over the devices
    # it has (its default backend's; the flag only adds host devices): the same code path, one
    # step of 3 points per device against the quick map's chunks of 32
    devices = jax.local_devices()
    expected = "4 x cpu" if jax.default_backend() == "cpu" else \
        f"{len(devices)} x {devices[0].platform}"
    assert four.attrs["devices"].startswith(expected)
    one = quick_map.sel(model=["matched_tail"])
    for name in METRICS + ("window", "reference_halt_time"):
        a, b = np.asarray(one[name]), np.asarray(four[name])
        np.testing.assert_array_equal(np.isnan(a), np.isnan(b), err_msg=name)
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12, err_msg=name)
    for name in ("valid", "reference_valid"):
        np.testing.assert_array_equal(np.asarray(one[name]), np.asarray(four[name]))


CHUNKED = dict(d0_ratio=[0.0, 0.02, 0.05], d1_ratio=[0.0, 0.1], d2_ratio=0.0,
               phi0=[0.0, 1.0, 2.5], models=("matched", "coulomb_exact"),
               reference="coulomb_exact", periods=3.0, samples_per_period=16, progress=False)


def test_chunk_size_does_not_change_the_map():
    before = trace_count()
    small = error_map(**CHUNKED, chunk_size=3)  # 6 steps
    assert trace_count() == before + 1  # one trace for every step, the padded one included
    again = error_map(**{**CHUNKED, "phi0": [0.5, 1.5, 3.0]}, chunk_size=3)
    assert trace_count() == before + 1  # new values, same shapes: reused
    big = error_map(**CHUNKED, chunk_size=64)  # one padded step
    assert trace_count() == before + 2
    for name in METRICS:
        np.testing.assert_allclose(np.asarray(small[name]), np.asarray(big[name]), rtol=0,
                                   atol=1e-12, err_msg=name)
    np.testing.assert_array_equal(np.asarray(small["valid"]), np.asarray(big["valid"]))
    assert not np.allclose(np.asarray(small["max_error"]), np.asarray(again["max_error"]),
                           equal_nan=True)
    # the exact half-swings against themselves; the matched ansatz is exact without damping
    assert float(np.nanmax(small["max_error"].sel(model="coulomb_exact"))) < 1e-12
    assert float(small["max_error"].sel(model="matched", d0_ratio=0.0, d1_ratio=0.0).max()) \
        < 1e-12


def test_chunk_size_from_the_platform_and_clipped_to_the_grid_and_the_memory(quick_map):
    """Not given: 128 per CPU device (as before), on a GPU the grid in one launch up to 32768
    points per device; given or not, no more than the grid needs (not below 128: small maps
    share a step) nor a quarter of the device's memory (issue 37: chunk_size=1_000_000 on 4
    points asked for 47 GB)."""
    import dataclasses

    cfg = maps._config(MODELS, "reference", 20.0, 64, 1e-10, 1e-12)
    per_point = maps.step_bytes_per_point(cfg)
    assert 151_000 < per_point < 300_000  # XLA's measured temporaries: 151 KB a point
    cpu = jax.local_devices()[:1]

    @dataclasses.dataclass
    class Device:  # an accelerator as jax describes one (platform, memory_stats)
        platform: str = "gpu"
        limit: float = 80e9

        def memory_stats(self):
            return {"bytes_limit": self.limit}

    choose = maps.choose_chunk
    assert choose(None, cfg, 2048, cpu) == 128 and choose(None, cfg, 8, cpu) == 128
    assert choose(1_000_000, cfg, 4, cpu) == 128 and choose(3, cfg, 18, cpu) == 3
    assert choose(None, cfg, 2048, [Device()]) == 2048  # the default map: one launch
    assert choose(None, cfg, 128 * 128 * 8, [Device()]) == 32768
    assert choose(None, cfg, 2048, [Device(), Device()]) == 1024  # per device
    assert choose(None, cfg, 2048, [Device()], n_processes=4) == 512  # per process
    small = Device(limit=1e9)  # a quarter of it holds 1282 points: 1024
    assert choose(None, cfg, 10**6, [small]) == 1024 == choose(10**6, cfg, 10**6, [small])
    assert choose(None, cfg, 10**6, [Device(limit=1e3)]) == 1
    assert quick_map.attrs["chunk_size"] == 32  # a map reports the value it used


@pytest.mark.parametrize("change, name", [
    (dict(d0_ratio=[]), "d0_ratio"),
    (dict(d2_ratio=[0.1, -0.2]), "d2_ratio"),
    (dict(d1_ratio=-1e-3), "d1_ratio"),
    (dict(phi0=[0.0, math.nan]), "phi0"),
    (dict(d0_ratio=[0.0, math.inf]), "d0_ratio"),
    (dict(phi0=[[0.0, 1.0]]), "phi0"),
    (dict(models=("matched", "exact")), "models"),
    (dict(models=()), "models"),
    (dict(chunk_size=0), "chunk_size"),
    (dict(chunk_size=2.5), "chunk_size"),
    (dict(periods=0.0), "periods"),
    (dict(periods=1e7), "periods"),
    (dict(samples_per_period=1), "samples_per_period"),
    (dict(reference="euler"), "reference"),
    (dict(reference="coulomb_exact", rtol=1e-3), "rtol"),  # (ignored unsaid before)
    (dict(reference="coulomb_exact", engine="diffrax"), "engine"),
])
def test_bad_grid_input_names_the_argument(change, name):
    kwargs = dict(d0_ratio=0.01, d2_ratio=0.1, phi0=0.0, progress=False) | change
    with pytest.raises(ValueError, match=rf"^{name}\b"):
        error_map(**kwargs)


def test_cli_quick(quick_map, tmp_path, capsys):
    out_dir = tmp_path / "maps"
    before = trace_count()
    assert main(["errormap", "--quick", "--out", str(out_dir), "--no-progress",
                 "--plots", "all"]) == 0
    assert trace_count() == before  # the same settings as quick_map: compiled once
    captured = capsys.readouterr()
    ds = xr.load_dataset(out_dir / "errormap.nc", engine="scipy")
    xr.testing.assert_allclose(ds, quick_map)
    attrs = check_cf_file(out_dir / "errormap.nc", flags=FLAGS)  # CF: see test_layout_and_attrs
    assert "_FillValue" in attrs["max_error"]  # NaN marks missing data in data variables
    assert attrs["valid"]["flag_meanings"].split() == [b"model_not_defined", b"model_defined"]
    assert list(attrs["valid"]["flag_values"]) == [0, 1]
    pngs = sorted(p.name for p in out_dir.glob("*.png"))
    assert pngs == sorted(f"{m}.png" for m in METRICS)
    for png in pngs:
        assert (out_dir / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    out = captured.out
    for model in MODELS:
        assert any(line.split()[:1] == [model] for line in out.splitlines()), out
    assert "0.5 (III)" in out and "0.05 (IV)" in out and "d0<=0.03,d2<=0.25" in out
    # the undamped (no-damping) corner is exact, so every row starts at d2 = 0 or above
    row = next(line.split() for line in out.splitlines() if line.split()[:1] == ["matched"])
    assert float(row[1]) >= 0.0


def test_errormap_file_passes_the_cf_checker(quick_map, tmp_path):
    """The IOOS compliance-checker's CF 1.10 suite, strict (errors, warnings and notes), on the
    file as `dampax errormap` writes it (the quick map is the CLI's, test_cli_quick); skipped
    unless compliance-checker is installed (it needs netCDF4: not a test dependency)."""
    import json
    import shutil

    from dampax._io import write_netcdf

    here = str(Path(sys.executable).parent)
    checker = shutil.which("compliance-checker", path=os.pathsep.join(
        [here, os.environ.get("PATH", "")]))
    if checker is None:
        pytest.skip("compliance-checker is not installed (pip install compliance-checker)")
    path = write_netcdf(quick_map, tmp_path / "errormap.nc")
    report = tmp_path / "report.json"
    proc = subprocess.run([checker, "--test", "cf:1.10", "--criteria", "strict", "--format",
                           "json", "--output", str(report), str(path)],
                          capture_output=True, text=True, timeout=120)
    result = json.loads(report.read_text())["cf:1.10"]
    failed = [(c["name"], c["msgs"]) for level in ("high", "medium", "low")
              for c in result[f"{level}_priorities"] if c["value"][0] < c["value"][1]]
    assert failed == [] and proc.returncode == 0, (failed, proc.stdout[-2000:], proc.stderr)
    assert result["scored_points"] == result["possible_points"] > 100


def test_cli_bad_axis_exits_2(tmp_path, capsys):
    assert main(["errormap", "--d0", "0:0.1", "--out", str(tmp_path)]) == 2
    assert capsys.readouterr().err.startswith("dampax: error: --d0")
    assert main(["errormap", "--d2=-0.1,0.2", "--out", str(tmp_path)]) == 2
    assert capsys.readouterr().err.startswith("dampax: error: --d2")
    assert main(["errormap", "--models", "matched,foo", "--out", str(tmp_path)]) == 2
    assert capsys.readouterr().err.startswith("dampax: error: --models")
    assert not any(Path(tmp_path).iterdir())


#: 100 periods in four segments, one step of 24 points (a halt in a later segment, a harmonic
#: point, a point fading in the second segment): shared by the two tests below
LONG = dict(d0_ratio=[0.0, 0.002], d1_ratio=[0.0, 0.003], d2_ratio=[0.0, 0.01, 0.3],
            phi0=[1.0, 2.0], periods=100.0, samples_per_period=32, models=("matched",),
            progress=False)


@pytest.fixture(scope="module")
def long_map():
    ds = error_map(**LONG)
    assert ds.attrs["reference_segments"] == 4 and ds.attrs["chunk_size"] >= 24  # one step
    return ds


def test_long_window_in_segments_matches_scipy(long_map):
    """Beyond 32 periods the reference runs in restarted segments: a 100-period point against
    scipy's stick-slip integration (an independent reference over the same window)."""
    d0r, d1r, d2r, phi0 = 0.002, 0.003, 0.01, 2.0
    periods, spp = LONG["periods"], LONG["samples_per_period"]
    mu, b, D = ratios_to_constants(d0r, d1r, d2r, m=1.0, k=1.0, A0=1.0)
    x0, v0 = math.cos(phi0), -math.sin(phi0)
    t = np.arange(int(periods * spp) + 1) * (2 * math.pi / spp)
    segments, _, rest = scipy_stick_slip(1.0, 1.0, mu, b, D, x0, v0, t[-1])
    x_ref, v_ref = evaluate(segments, rest, t)
    assert rest is not None and rest[0] > 32 * 2 * math.pi  # halts in a later segment
    window = t <= rest[0]
    sol = dp.solve(dp.Oscillator(m=1.0, k=1.0, mu=mu, b=b, D=D), x0, v0, method="ansatz")
    expected = np.max(np.abs(np.asarray(sol.x(t[window])) - x_ref[window]))
    got = long_map.sel(d0_ratio=d0r, d1_ratio=d1r, d2_ratio=d2r, phi0=phi0).squeeze()
    assert float(got["max_error"]) == pytest.approx(expected, rel=1e-6)
    assert float(got["reference_halt_time"]) == pytest.approx(rest[0] / (2 * math.pi),
                                                              rel=1e-9)
    assert float(got["window"]) == pytest.approx(t[window][-1] / (2 * math.pi), rel=1e-12)


def test_harmonic_points_are_the_exact_motion(quick_map):
    """Without damping and with a linear spring (d0 = d1 = d2 = 0) the map's reference is the
    harmonic motion x0 cos t + v0 sin t in closed form, not integrated (issue 35: a motion that
    never stops held its batch for the whole span): the undamped model, which is that motion,
    errs by rounding only (with the integrator: its error, 3e-10 over 10 periods), over the
    whole window, with no halt."""
    point = quick_map.sel(d0_ratio=0.0, d2_ratio=0.0).squeeze()
    assert float(point["max_error"].sel(model="undamped").max()) < 1e-14
    assert float(point["energy_error"].sel(model="undamped").max()) < 1e-14
    # the matched ansatz without damping is the same cosine, up to rounding of its phase
    assert float(point["max_error"].sel(model="matched").max()) < 1e-13
    assert np.allclose(point["window"], 10.0, rtol=0, atol=1e-12)
    assert bool(np.isnan(point["reference_halt_time"]).all())
    assert bool(point["reference_valid"].all())


def test_faded_point_beside_a_harmonic_one_matches_scipy(long_map):
    """A point whose energy falls below the floor in the second of four segments, in one step
    with harmonic points (which keep every segment of the step live): once faded it no longer
    integrates, and its metrics over its window still match scipy's integration."""
    d2r, phi0 = 0.3, 1.0
    periods, spp = LONG["periods"], LONG["samples_per_period"]
    mu, b, D = ratios_to_constants(0.0, 0.0, d2r, m=1.0, k=1.0, A0=1.0)
    x0, v0 = math.cos(phi0), -math.sin(phi0)
    t = np.arange(int(periods * spp) + 1) * (2 * math.pi / spp)
    segments, _, rest = scipy_stick_slip(1.0, 1.0, mu, b, D, x0, v0, t[-1])
    x_ref, v_ref = evaluate(segments, rest, t)
    below = 0.5 * (x_ref**2 + v_ref**2) < maps.ENERGY_FLOOR * 0.5
    window = np.cumsum(below) == 0  # up to the first sample below the floor
    assert 32 < t[window][-1] / (2 * math.pi) < 64  # fades in the second segment
    sol = dp.solve(dp.Oscillator(m=1.0, k=1.0, mu=mu, b=b, D=D), x0, v0, method="ansatz")
    err = np.abs(np.asarray(sol.x(t[window])) - x_ref[window])
    point = long_map.sel(d0_ratio=0.0, d1_ratio=0.0)
    got = point.sel(d2_ratio=d2r, phi0=phi0).squeeze()
    assert float(got["max_error"]) == pytest.approx(err.max(), rel=1e-6)
    assert float(got["rms_error"]) == pytest.approx(np.sqrt(np.mean(err**2)), rel=1e-6)
    assert float(got["window"]) == pytest.approx(t[window][-1] / (2 * math.pi), rel=1e-12)
    assert float(point["max_error"].sel(d2_ratio=0.0).max()) < 1e-13  # the harmonic points


def test_blocks_after_every_window_closed_are_skipped_without_changing_the_map():
    """A step whose points have all halted skips its later blocks of samples: a point of such a
    step has the metrics it has in a step that must evaluate them (a point beside it still
    moves), and they match scipy's stick-slip integration over the window."""
    a, b, c, d = 0.3, 1.2, 2.0, 2.9
    common = dict(d1_ratio=0.0, d2_ratio=0.05, periods=20.0, samples_per_period=64,
                  models=("matched",), chunk_size=4, progress=False)
    # 1281 samples: two blocks of 641 (10 periods each); d0 = 0.2 halts within a period
    assert maps._config(("matched",), "reference", 20.0, 64, 1e-10, 1e-12).n_blocks == 2
    # steps: the four d0 = 0.2 points (halted before the second block: skipped), then d0 = 0
    skipped = error_map(d0_ratio=[0.2, 0.0], phi0=[a, b, c, d], **common)
    # steps: three d0 = 0.2 points beside a d0 = 0 point, which keeps the second block live
    evaluated = error_map(d0_ratio=[0.2, 0.0], phi0=[a, b, c], **common)
    assert float(skipped["window"].sel(d0_ratio=0.2).max()) < 1.0
    assert float(skipped["window"].sel(d0_ratio=0.0).min()) == pytest.approx(20.0)
    for phi0 in (a, b, c):
        for name in METRICS + ("window", "reference_halt_time"):
            one = float(skipped[name].sel(d0_ratio=0.2, phi0=phi0).squeeze())
            other = float(evaluated[name].sel(d0_ratio=0.2, phi0=phi0).squeeze())
            assert one == pytest.approx(other, rel=0, abs=1e-15), name
    mu, b_, D = ratios_to_constants(0.2, 0.0, 0.05, m=1.0, k=1.0, A0=1.0)
    x0, v0 = math.cos(a), -math.sin(a)
    t = np.arange(1281) * (2 * math.pi / 64)
    segments, _, rest = scipy_stick_slip(1.0, 1.0, mu, b_, D, x0, v0, t[-1])
    x_ref, _ = evaluate(segments, rest, t)
    window = t <= rest[0]
    sol = dp.solve(dp.Oscillator(m=1.0, k=1.0, mu=mu, b=b_, D=D), x0, v0, method="ansatz")
    err = np.abs(np.asarray(sol.x(t[window])) - x_ref[window])
    got = skipped.sel(d0_ratio=0.2, phi0=a).squeeze()
    assert float(got["max_error"]) == pytest.approx(err.max(), rel=1e-6)
    assert float(got["rms_error"]) == pytest.approx(np.sqrt(np.mean(err**2)), rel=1e-6)
    assert float(got["reference_halt_time"]) == pytest.approx(rest[0] / (2 * math.pi),
                                                              rel=1e-9)


def test_error_map_memory_does_not_grow_with_periods():
    """The compiled step's scratch memory (XLA's own analysis) for 2,000 periods is that of 100
    periods: the reference is kept one segment at a time."""
    import jax

    ids = tuple(d.id for d in jax.local_devices())

    def scratch(periods):
        cfg = maps._config(("matched",), "reference", periods, 32, 1e-10, 1e-12)
        return maps._executable(cfg, ids, len(ids)).memory_analysis().temp_size_in_bytes

    small, large = scratch(100.0), scratch(2000.0)
    assert large < 1.5 * small


def test_longest_windows_apart_and_closed_windows_skipped_change_nothing():
    """The few points whose windows are far longer than the rest run in steps of their own
    (TAIL_CHUNK points), and steps skip what is past every window: the map is the one that
    computes every point in one step."""
    from dampax._studies._maps import TAIL_CHUNK, _tail_count, _window_estimate

    kw = dict(d0_ratio=[0.0, 0.05, 0.1], d1_ratio=[0.0, 0.2], d2_ratio=0.0,
              phi0=[0.0, 1.0, 2.5], models=("matched", "coulomb_exact"),
              reference="coulomb_exact", periods=30.0, samples_per_period=16, progress=False)
    grid = np.stack([g.ravel() for g in np.meshgrid(kw["d0_ratio"], kw["d1_ratio"], [0.0],
                                                    kw["phi0"], indexing="ij")], axis=-1)
    estimate = np.sort(_window_estimate(grid, kw["periods"]))[::-1]
    assert _tail_count(estimate, 16, TAIL_CHUNK) > 0  # the undamped points form a tail
    apart = error_map(**kw, chunk_size=16)
    together = error_map(**kw, chunk_size=32)  # one step holds every point: no tail
    for name in METRICS + ("window", "reference_halt_time"):
        np.testing.assert_array_equal(np.asarray(apart[name]), np.asarray(together[name]),
                                      err_msg=name)
    assert float(apart["window"].max()) == pytest.approx(30.0)  # the undamped motion


def test_the_summary_says_dash_where_the_reference_does_not_exist():
    """The errormap summary's scan along d2 stops where the closed-form reference (D = 0 only)
    is invalid: "-" (not defined), not "0" as if the model failed at the next d2."""
    import xarray as xr

    from dampax._cli.errormap import _defined_along

    coords = dict(model=["matched"], d0_ratio=[0.0, 0.05], d1_ratio=[0.0], d2_ratio=[0.0, 0.3],
                  phi0=[0.0])
    shape = (1, 2, 1, 2, 1)
    valid = xr.DataArray(np.ones(shape, bool), coords=coords, dims=list(coords))
    ref = valid.isel(model=0, drop=True).copy(data=np.ones(shape[1:], bool))
    ref.loc[dict(d2_ratio=0.3)] = False  # coulomb_exact at D > 0
    ds = xr.Dataset({"valid": valid, "reference_valid": ref})
    assert not _defined_along(ds, "matched", "d2_ratio")
    assert _defined_along(ds, "matched", "d0_ratio")
    assert _defined_along(ds.drop_vars("reference_valid"), "matched", "d2_ratio")
