"""The import structure of the package (docs/DESIGN.md section 6): one folder per layer, every
import points down (or within its layer), no import cycle, also through imports inside
functions, and package imports inside functions only in the CLI and the public face's lazy
names."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src" / "dampax"


def _module_name(path: Path) -> str:
    rel = path.relative_to(SRC.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _imports(path: Path) -> set[str]:
    """dampax modules imported anywhere in the file (module level and inside functions)."""
    name = _module_name(path)
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.startswith("dampax"):
                out.add(target)
                for alias in node.names:  # "from . import _x" names a module
                    module = SRC.parent / target.replace(".", "/") / (alias.name + ".py")
                    if module.exists():
                        out.add(f"{target}.{alias.name}")
        elif isinstance(node, ast.Import):
            out.update(a.name for a in node.names if a.name.startswith("dampax"))
    return out


def _graph() -> dict[str, set[str]]:
    files = {_module_name(p): p for p in SRC.rglob("*.py")}
    graph = {}
    for name, path in files.items():
        # an import of a package runs its __init__; edges to the package itself (its own
        # __init__ from a submodule) are how Python loads it, not a dependency
        graph[name] = {t for t in _imports(path) if t in files and not name.startswith(t + ".")
                       and t != name}
    return graph


def test_no_import_cycle():
    graph = _graph()
    state: dict[str, int] = {}

    def visit(node, path):
        state[node] = 1
        for nxt in sorted(graph[node]):
            if nxt == "dampax":  # the public face re-exports; nothing imports it back
                continue
            if state.get(nxt) == 1:
                pytest.fail("import cycle: " + " -> ".join(path + [nxt]))
            if nxt not in state:
                visit(nxt, path + [nxt])
        state[node] = 2

    for node in sorted(graph):
        if node not in state:
            visit(node, [node])


#: the layers, bottom up (docs/DESIGN.md section 6): a module may import its own layer and the
#: ones below it
LAYERS = (
    ("dampax._version", "dampax._trig", "dampax._io", "dampax._cachefiles",
     "dampax._cachethreads", "dampax._cache",
     "dampax._oscillator", "dampax._trace"),
    ("dampax._models",),
    ("dampax._reference",),
    ("dampax._solve",),
    ("dampax._studies",),
    ("dampax._plot", "dampax._plot_fit"),
    ("dampax._fit",),
    ("dampax._paper",),
    ("dampax._cli",),
    ("dampax",),
)


def _layer(module: str) -> int:
    for i, prefixes in enumerate(LAYERS[:-1]):
        if any(module == p or module.startswith(p + ".") for p in prefixes):
            return i
    assert module == "dampax", f"{module} is in no layer of LAYERS"
    return len(LAYERS) - 1


def test_every_import_points_down():
    up = [f"{name} (layer {_layer(name)}) imports {t} (layer {_layer(t)})"
          for name, targets in _graph().items() for t in sorted(targets)
          if _layer(t) > _layer(name)]
    assert not up, "\n".join(up)


def test_top_level_modules_and_layer_folders():
    """At most 12 modules directly in the package; the layers' folders exist."""
    top = sorted(p.name for p in SRC.glob("*.py"))
    assert len(top) <= 12, top
    for folder in ("_models", "_reference", "_studies", "_fit", "_paper", "_cli"):
        assert (SRC / folder / "__init__.py").exists(), folder


def _imports_inside_functions(path: Path) -> list[int]:
    tree = ast.parse(path.read_text())
    lines = []
    for fn in ast.walk(tree):
        if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            for node in ast.walk(fn):
                if isinstance(node, ast.ImportFrom) and (
                        node.level or (node.module or "").startswith("dampax")):
                    lines.append(node.lineno)
                elif isinstance(node, ast.Import) and any(
                        a.name.startswith("dampax") for a in node.names):
                    lines.append(node.lineno)
                elif (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                      and node.func.attr == "import_module"):
                    lines.append(node.lineno)
    return sorted(set(lines))


def test_package_imports_inside_functions_only_in_the_cli_and_the_public_face():
    """Outside the CLI (where they keep ``--version`` fast) at most two places import the
    package inside a function; here two: the lazy names of ``dampax/__init__.py``, and the
    fused GPU kernel's module in ``_reference._solve`` (Pallas's Triton backend: 50-100 ms of
    every import, used only on a CUDA GPU or with ``engine="pallas"``)."""
    places = {}
    for path in SRC.rglob("*.py"):
        name = _module_name(path)
        if name.startswith("dampax._cli"):
            continue
        lines = _imports_inside_functions(path)
        if lines:
            places[name] = lines
    assert len(places) <= 2 and set(places) <= {"dampax", "dampax._reference._solve"}, places
    assert len(places.get("dampax._reference._solve", [])) <= 1, places  # the kernel alone


def test_reference_engine_imports_only_the_ground_layers():
    allowed = {"dampax._oscillator", "dampax._models._solution", "dampax._models._atlas",
               "dampax._trig"}
    for name, targets in _graph().items():
        if name.startswith("dampax._reference"):
            outside = {t for t in targets if not t.startswith("dampax._reference")}
            assert outside <= allowed, f"{name} imports {sorted(outside - allowed)}"


def _validations(call) -> dict:
    """{(check, name): calls} of dampax's input checks (``_oscillator.check_finite``,
    ``check_real``, ``check_count``) while ``call()`` runs: each module's reference to them
    (they are imported by name) is replaced by a counting wrapper for the call."""
    import collections
    import functools
    import sys

    from dampax import _oscillator as o

    seen = collections.Counter()
    originals = {f.__name__: f for f in (o.check_finite, o.check_real, o.check_count)}

    def counting(f):
        @functools.wraps(f)
        def wrapper(name, *args, **kwargs):
            seen[f.__name__, name] += 1
            return f(name, *args, **kwargs)
        return wrapper

    patched = []
    for module in [m for n, m in sys.modules.items() if n.startswith("dampax") and m]:
        for attr, f in originals.items():
            if getattr(module, attr, None) is f:
                setattr(module, attr, counting(f))
                patched.append((module, attr, f))
    try:
        call()
    finally:
        for module, attr, f in patched:
            setattr(module, attr, f)
    return dict(seen)


def test_each_public_call_validates_once():
    """Validation once, at the edge (issue 27): a public call checks each input once (the
    oscillator's constants when it is made, x0 and v0 in solve or sensitivity) and the inner
    functions trust them, also inside the compiled programs (method="auto" runs two models,
    sensitivity differentiates solve)."""
    import math

    import jax.numpy as jnp

    import dampax as dp

    # the oscillator and settings of tests/studies/test_sensitivity.py and tests/models/ (their
    # kept programs serve: nothing new is compiled for this test in the suite)
    made = _validations(lambda: dp.Oscillator(m=1.0, k=30.0, mu=0.05, D=1.0))
    assert made == {("check_finite", n): 1 for n in ("m", "k", "mu", "b", "D", "g", "k3")}
    osc = dp.Oscillator(m=1.0, k=30.0, mu=0.05, D=1.0)
    coulomb = dp.Oscillator(m=1.0, k=30.0, mu=0.05)
    ts = jnp.linspace(0.05, 2.0 * math.pi / math.sqrt(30.0), 24)
    calls = {
        "ansatz": lambda: dp.solve(osc, 0.2, 0.0),
        "rizcallah": lambda: dp.solve(coulomb, 0.2, 0.0, method="rizcallah"),
        "reference": lambda: dp.solve(osc, 0.2, 0.0, method="reference"),
        "auto": lambda: dp.solve(osc, 0.2, 0.0, method="auto"),
        "sensitivity": lambda: dp.sensitivity(osc, 0.2, 0.0, ts,
                                              wrt=("mu", "b", "D", "x0", "v0"),
                                              method="ansatz", turning_points=3),
    }
    for name, call in calls.items():
        seen = _validations(call)
        assert seen.get(("check_finite", "x0")) == 1 and seen.get(("check_finite", "v0")) == 1, \
            (name, seen)
        assert all(n == 1 for n in seen.values()), (name, seen)


#: the layers inside the fit package, bottom up (issue 33): a module may import its own layer
#: and the ones below it. The result (built from the checks' findings) sits below the
#: pipeline that builds it; the searches of k3 and mu_s above the pipeline they run.
FIT_LAYERS = (
    ("_params", "_dist", "_intervals", "_profile", "_mcmc", "_sampler", "_text",
     "_linalg"),  # ground
    ("_curves", "_lm"),  # the fit models: their curves and settings
    ("_core",),  # the solver core
    ("_analysis", "_noise", "_guess", "_inputs", "_checks", "_measures", "_assess",
     "_options"),  # checks
    ("_problem", "_context", "_report", "_result", "_example"),  # problem, result, example
    ("_starts", "_halts", "_answer"),  # stages: the batch of starts, the neighbouring halts
    ("_pipeline",),  # the plan of stages and the assessment
    ("_static", "_stiffness"),  # the searches of mu_s and k3
    ("_api",),  # single-trace entry points
    ("_joint_problem", "_joint_result", "_joint_build", "_joint_stages", "_joint_search",
     "_joint"),  # joint fits
    ("_entry",),  # dp.fit
    ("_posterior_result", "_posterior_joint", "_posterior"),  # the posterior
    ("__init__",),
)


def test_fit_layers_point_down():
    """Every module of _fit/ is in one layer of FIT_LAYERS and imports only its own layer and
    those below (the fit function reaches no lower layer as a value: the AST test below)."""
    fit = SRC / "_fit"
    layer = {name: i for i, names in enumerate(FIT_LAYERS) for name in names}
    assert sorted(layer) == sorted(p.stem for p in fit.glob("*.py"))
    up = []
    for path in fit.glob("*.py"):
        for target in _imports(path):
            if target.startswith("dampax._fit."):
                other = target.split(".")[2]
                if layer[other] > layer[path.stem]:
                    up.append(f"{path.stem} (layer {layer[path.stem]}) imports {other} "
                              f"(layer {layer[other]})")
    assert not up, "\n".join(up)


def test_fit_functions_take_no_private_or_fit_function_parameters():
    """No parameter in _fit/ starts with "_" (a hidden switch such as _inner) or is named fit
    (the orchestrator handed down to be called back): variants are plans and problems."""
    bad = []
    for path in (SRC / "_fit").glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                a = node.args
                names = [x.arg for x in (*a.posonlyargs, *a.args, *a.kwonlyargs,
                                         *filter(None, (a.vararg, a.kwarg)))]
                bad += [f"{path.name}:{getattr(node, 'name', 'lambda')}({n})" for n in names
                        if n.startswith("_") or n == "fit"]
    assert not bad, bad


#: issue 33's limits on the fit layer: lines per function (its docstring excluded), lines per
#: module, parameters per private function (the public entry points keep their signatures)
FIT_FUNCTION_LINES, FIT_MODULE_LINES, FIT_PRIVATE_PARAMETERS = 60, 500, 8


def _public_fit_functions() -> set[tuple[str, str]]:
    """(module file name, function name) of the functions that ``dampax`` exports from _fit/
    (their signatures are the public interface, docs/DESIGN.md)."""
    import inspect

    import dampax

    out = set()
    for name in dir(dampax):
        obj = getattr(dampax, name)
        module = getattr(obj, "__module__", "") or ""
        if module.startswith("dampax._fit.") and inspect.isfunction(obj):
            out.add((module.rsplit(".", 1)[1] + ".py", obj.__name__))
    return out


def _body_lines(node) -> int:
    """Lines of a function from its first statement after the docstring to its end."""
    body = node.body
    doc = (isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant)
           and isinstance(body[0].value.value, str))
    if doc and len(body) == 1:
        return 0
    return node.end_lineno - body[1 if doc else 0].lineno + 1


def test_fit_functions_and_modules_are_small():
    """No function of _fit/ is longer than 60 lines (docstring excluded), no module longer
    than 500 lines, and no private function (every one but the public entry points) takes more
    than 8 parameters: a long list of switches is a problem or an option value."""
    public = _public_fit_functions()
    bad = []
    for path in sorted((SRC / "_fit").glob("*.py")):
        text = path.read_text()
        if len(text.splitlines()) > FIT_MODULE_LINES:
            bad.append(f"{path.name}: {len(text.splitlines())} lines")
        for node in ast.walk(ast.parse(text)):
            if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            if _body_lines(node) > FIT_FUNCTION_LINES:
                bad.append(f"{path.name}:{node.name}: {_body_lines(node)} lines")
            a = node.args
            n = len([x for x in (*a.posonlyargs, *a.args, *a.kwonlyargs)
                     if x.arg not in ("self", "cls")])
            if n > FIT_PRIVATE_PARAMETERS and (path.name, node.name) not in public:
                bad.append(f"{path.name}:{node.name}: {n} parameters")
    assert not bad, "\n".join(bad)
