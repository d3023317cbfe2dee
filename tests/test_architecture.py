"""The library's structure: layering, one gain representation, typed certification results,
static laws reporting their internal dynamics, float32 runs, checkpoints that refuse bad input."""

import ast
import inspect
import json
import math
import os
import pathlib
import re
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.linalg import expm, solve_continuous_lyapunov

import wmrjax as w
from wmrjax import _files as files
from wmrjax import certify as C
from wmrjax import references as R

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _sources(pkg):
    return sorted((ROOT / pkg).rglob("*.py"))


def _imports(path):
    """(modules imported, names imported from modules) of one source file, by its syntax tree."""
    mods, names = [], []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            mods += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module:
            mods.append(node.module)
            names += [(node.module, a.name) for a in node.names]
    return mods, names


LAYERS = ("wmrjax", "paper", "benchmarks")  # the package, and the repository's scripts above it
JOBS = ("wmrjax.tune", "wmrjax.sweep")  # the jobs that are whole subpackages
JOB_MODULES = (
    "wmrjax.certify.job",
    "wmrjax.certify.plant_table",
    "wmrjax.export.job",
    "wmrjax.identify.job",
)  # a job beside its library
CLI = "wmrjax.cli"  # with wmrjax.__main__, its entry point
PRIVATE_MODULES = ("_cgen", "_files", "_hoist", "_math", "_rk4", "_scalarize", "_simplify", "_validate")


def _module(f) -> str:
    rel = f.relative_to(ROOT).with_suffix("")
    parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
    return ".".join(parts)


def _within(m: str, prefixes) -> bool:
    return any(m == p or m.startswith(p + ".") for p in prefixes)


def _import_graph() -> dict:
    """Module -> the package's modules it imports (function-local imports included): an import of
    ``a.b`` or ``from a import b`` is an edge to ``a.b`` when that is a module, else to ``a``."""
    modules = {_module(f): f for f in _sources("wmrjax")}
    graph = {}
    for m, f in modules.items():
        targets = set()
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, ast.Import):
                targets |= {a.name for a in node.names if a.name in modules}
            elif isinstance(node, ast.ImportFrom) and node.module in modules:
                targets |= {
                    f"{node.module}.{a.name}" if f"{node.module}.{a.name}" in modules else node.module
                    for a in node.names
                }
        graph[m] = sorted(targets - {m})
    return graph


def _cycles(graph: dict) -> list:
    """The strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for u in graph.get(v, ()):
            if u not in index:
                visit(u)
                low[v] = min(low[v], low[u])
            elif u in on:
                low[v] = min(low[v], index[u])
        if low[v] == index[v]:
            comp = []
            while True:
                u = stack.pop()
                on.discard(u)
                comp.append(u)
                if u == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_the_package_has_no_import_cycle():
    """The package's modules import each other as a DAG (function-local imports count: a cycle
    held together by them is still a cycle); the scan finds a cycle it is shown."""
    graph = _import_graph()
    assert len(graph) > 60 and "wmrjax._rk4" in graph["wmrjax.linearize"]
    assert not _cycles(graph), f"import cycles: {_cycles(graph)}"
    assert _cycles({"a": ["b"], "b": ["c"], "c": ["a"], "d": ["a"]}) == [["a", "b", "c"]]


def test_layers_never_point_up():
    """The core (models, controllers, the run, the problem file, the certificates' mathematics)
    imports no job and no command line; a job (wmrjax.tune, wmrjax.sweep, the ``job`` module
    beside a library) never imports the command line; only wmrjax.cli and the scripts above the
    package (paper/, benchmarks/) import wmrjax.cli; the package imports nothing of the scripts."""
    for f in _sources("wmrjax"):
        m = _module(f)
        mods, names = _imports(f)
        targets = mods + [f"{mod}.{n}" for mod, n in names]
        if not _within(m, (CLI, "wmrjax.__main__")):
            bad = [t for t in targets if _within(t, (CLI,))]
            assert not bad, f"{f.relative_to(ROOT)} imports the command line: {bad}"
        if not _within(m, (CLI, *JOBS, *JOB_MODULES)):
            bad = [t for t in targets if _within(t, (*JOBS, *JOB_MODULES))]
            assert not bad, f"{f.relative_to(ROOT)} (the core) imports a job: {bad}"
        bad = [t for t in mods if t.split(".")[0] in ("paper", "benchmarks", "tests")]
        assert not bad, f"{f.relative_to(ROOT)} imports a script of the repository: {bad}"
    for pkg in LAYERS:
        for f in _sources(pkg):
            _, names = _imports(f)
            # private names stay in their module (the package's private helper modules excepted)
            private = [
                (m, n) for m, n in names if n.startswith("_") and not n.startswith("__") and n not in PRIVATE_MODULES
            ]
            assert not private, f"{f.relative_to(ROOT)} imports private names {private}"


# what the wmrjax command's jobs need (the cli extra) and the tests' reference (scipy): never at a
# module's top in the package (``import wmrjax.tune`` works without them), and argparse only in cli
OPTIONAL = ("matplotlib", "pyarrow", "cmaes", "optuna", "scipy")


def test_the_package_imports_optional_dependencies_only_where_used():
    """No module of wmrjax/ imports matplotlib, pyarrow, cmaes, optuna or scipy at its top (only
    inside the function that writes a figure, a table or runs a baseline: ``pip install wmrjax``
    does not install them); argparse only in wmrjax.cli."""
    for f in _sources("wmrjax"):
        tree = ast.parse(f.read_text())
        top = [n for n in tree.body if isinstance(n, (ast.Import, ast.ImportFrom))]
        mods = [a.name for n in top if isinstance(n, ast.Import) for a in n.names]
        mods += [n.module for n in top if isinstance(n, ast.ImportFrom) and n.module]
        bad = [m for m in mods if m.split(".")[0] in OPTIONAL]
        assert not bad, f"{f.relative_to(ROOT)} imports {bad} at its top: not a dependency of the library"
        if not _within(_module(f), (CLI, "wmrjax.__main__")):
            every, _ = _imports(f)
            assert "argparse" not in every, f"{f.relative_to(ROOT)} parses arguments outside wmrjax.cli"


def test_function_local_imports_give_their_reason():
    """An import inside a function of wmrjax/ is an exception (an optional dependency, a POSIX-only
    or private JAX module, an import a job makes only when asked): its line says why in a comment.
    Everything else is imported at the module's top."""
    bare = []
    for f in _sources("wmrjax"):
        lines = f.read_text().splitlines()
        for fn in ast.walk(ast.parse("\n".join(lines))):
            if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            for st in ast.walk(fn):
                if isinstance(st, (ast.Import, ast.ImportFrom)):
                    text = " ".join(lines[st.lineno - 1 : st.end_lineno])
                    if "#" not in text:
                        bare.append(f"{f.relative_to(ROOT)}:{st.lineno}")
    assert not bare, f"function-local imports without a reason: {sorted(set(bare))}"


def test_every_module_says_what_it_is():
    """Every module of the package and of the repository's scripts opens with a docstring, and
    none is a placeholder."""
    for pkg in LAYERS:
        for f in _sources(pkg):
            doc = ast.get_docstring(ast.parse(f.read_text()))
            if f.name == "__init__.py" and not f.read_text().strip():
                continue  # an empty namespace marker (paper/)
            assert doc and len(doc) > 20 and "TODO" not in doc, f"{f.relative_to(ROOT)}: {doc!r}"


def test_every_package_declares_its_public_api():
    """Every package of ``wmrjax`` lists its public names in ``__all__``: each is defined there,
    none twice, and a package of re-exports lists every name it imports (none re-exported by
    accident, as a ``noqa: F401`` once allowed)."""
    for f in sorted((ROOT / "wmrjax").rglob("__init__.py")):
        name = _module(f)
        module = __import__(name, fromlist=["__all__"])
        public = getattr(module, "__all__", None)
        assert public is not None, f"{name} has no __all__"
        assert len(set(public)) == len(public), f"{name}.__all__ repeats a name"
        missing = [n for n in public if not hasattr(module, n)]
        assert not missing, f"{name}.__all__ names what it does not define: {missing}"
        tree = ast.parse(f.read_text())
        imported = {
            a.asname or a.name
            for node in tree.body
            if isinstance(node, ast.ImportFrom) and node.module not in ("__future__", None) and node.level == 0
            and node.module.startswith("wmrjax")
            for a in node.names
        }  # fmt: skip
        defines = any(isinstance(node, (ast.FunctionDef, ast.ClassDef)) for node in tree.body)
        if not defines:  # a package of re-exports: all of them public
            assert imported <= set(public), f"{name} imports {sorted(imported - set(public))}, not in __all__"


def test_the_library_runs_without_the_cli_extra(tmp_path):
    """With matplotlib, pyarrow, cmaes and optuna made unimportable, ``import wmrjax`` and a short
    simulation work, and nothing of the upper layers is loaded."""
    code = """
import sys
for m in ("matplotlib", "pyarrow", "cmaes", "optuna"):
    sys.modules[m] = None
import wmrjax as w
ctrl = w.dynamic_linearization("(2,0)")
params = ctrl.params(w.references.paper_62(), poles=1.0, geometry=w.Geometry(e=0.0))
tr = w.simulate(ctrl, ctrl.reference_state(0.0, params), params, dt=0.01, n_steps=10)
upper = sorted(m for m in sys.modules if m.startswith(("wmrjax.cli", "wmrjax.tune", "wmrjax.sweep")))
print(tr.state.shape, upper)
"""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, env=env, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    assert r.stdout.strip() == "(11, 4) []", r.stdout


def test_core_requirements_are_jax_numpy_optax(tmp_path):
    """The installed distribution (``pip install wmrjax``) requires jax, numpy and optax, nothing
    else outside its extras, and carries the package's one version. Read in a fresh process
    outside the repository (its checkout's ``wmrjax.egg-info`` is not the installed metadata); a
    failure after editing pyproject.toml means: reinstall (``pip install -e ".[test,cli,docs]"``)."""
    code = """
import importlib.metadata as m, json, re
reqs = m.requires("wmrjax") or []
core = sorted(re.match(r"[A-Za-z0-9_.-]+", r).group(0).lower() for r in reqs if "extra ==" not in r)
extras = sorted(re.search(r'extra == "([^"]+)"', r).group(1) for r in reqs if "extra ==" in r)
print(json.dumps({"core": core, "extras": sorted(set(extras)), "version": m.version("wmrjax")}))
"""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, env=env, timeout=120)
    assert r.returncode == 0, r.stderr[-3000:]
    got = json.loads(r.stdout)
    assert got["core"] == ["jax", "numpy", "optax"], got
    assert {"cli", "test", "docs"} <= set(got["extras"]), got
    assert got["version"] == w.__version__, got


def test_per_type_facts_live_in_the_tables():
    """No dispatch on a robot's name outside robots.py and the two table definitions: no comparison
    with a type-name string, no membership test in a list of them, no dict keyed by them."""
    type_name = r"""["']\(\d,\d\)["']"""
    patterns = [
        re.compile(r"\.name\s*(==|!=|in)\s*[(\[{\"']"),  # robot.name == "(2,0)"
        re.compile(r"(==|!=)\s*" + type_name),
        re.compile(type_name + r"\s*(==|!=)"),
        re.compile(r"\bin\s*[(\[{]\s*" + type_name),  # kind in ("(2,1)", ...)
        re.compile(r"[{,]\s*" + type_name + r"\s*:"),  # {"(2,0)": ...}
        re.compile(r"\[\s*[\w.]*\.name\s*\]"),
    ]  # TABLE[ctrl.robot.name]
    allowed = {ROOT / "wmrjax" / "robots.py"}
    table_lookups = {ROOT / "wmrjax" / "controllers" / f for f in ("dynamic.py", "static.py")}
    for pkg in LAYERS:
        for f in _sources(pkg):
            if f in allowed:
                continue
            text = f.read_text()
            for pat in patterns[:5] + ([] if f in table_lookups else patterns[5:]):
                hit = pat.search(text)
                assert not hit, f"{f.relative_to(ROOT)} dispatches on a type name: {hit.group(0)!r}"


def test_signatures_are_uniform():
    """Certification: the closed loop first, then t_final and eps keyword-only; controllers: the
    same argument kinds in the same order for both siblings."""
    P = inspect.Parameter
    for fn, keys in [
        (C.lemma2, ("t_final", "eps")),
        (C.exact_map_radius, ("t_final", "eps")),
        (C.empirical_radius, ("t_final", "eps")),
        (C.falsified_radius, ("t_final", "eps")),
        (C.analyse, ("t_final", "eps")),
        (C.verify, ("t_final",)),
        (C.min_distance, ("t_final",)),
        (C.falsify, ("t_final",)),
    ]:
        ps = inspect.signature(fn).parameters
        assert list(ps)[:2] == ["ctrl", "params"], fn.__name__
        assert all(p.kind == P.KEYWORD_ONLY for p in list(ps.values())[2:]), fn.__name__
        assert all(k in ps for k in keys), fn.__name__
    methods = {
        "vector_field": ["t", "z", "params"],
        "control": ["t", "z", "params"],
        "error": ["t", "z", "params"],
        "reference_jet": ["t", "params"],
        "margin": ["z", "params"],
        "psi": ["z", "params"],
        "outputs": ["z", "params"],
        "jet": ["z", "params"],
        "physical_state": ["X", "u", "params"],
        "initial_state_from_physical": ["X", "u", "params"],
        "check_regular": ["z", "params", "name"],
        "check_reference": ["params", "t_final", "t0", "floor"],
        "error_matrix": ["gains"],
    }
    for cls in (w.DynamicLinearization, w.StaticLinearization):
        for name, args in methods.items():
            got = list(inspect.signature(getattr(cls, name)).parameters)[1:]
            assert got == args, f"{cls.__name__}.{name}{tuple(got)}"


# --- one gain representation --------------------------------------------------------------------


def test_gains_constructors_agree_and_read_back_their_poles():
    np.testing.assert_array_equal(w.Gains.from_poles(1.0, 2, 2).coeffs, [[1.0, 2.0], [1.0, 2.0]])
    np.testing.assert_array_equal(w.Gains.from_damping(1.0, 1.0, m=2).coeffs, [[1.0, 2.0], [1.0, 2.0]])
    np.testing.assert_allclose(w.Gains.from_poles([[0.8, 2.0]]).coeffs, [[1.6, 2.8]], rtol=1e-15)
    g = w.Gains.from_damping(3.76, 0.47, m=2)
    re_, im = -0.47 * 3.76, 3.76 * math.sqrt(1 - 0.47**2)
    np.testing.assert_allclose(g.poles(), [[re_ - 1j * im, re_ + 1j * im]] * 2, rtol=1e-12)
    g3 = w.Gains.from_damping([2.0], [0.5], lam=3.0, m=1)  # r = 3: (s^2 + 2 s + 4)(s + 3)
    np.testing.assert_allclose(g3.coeffs, [[12.0, 10.0, 5.0]], rtol=1e-15)
    np.testing.assert_allclose(w.Gains(jnp.array([[1.6, 2.8]])).cascade_pole(), [0.8], rtol=1e-12)
    assert np.isnan(float(g.cascade_pole()[0]))  # complex poles: no real cascade
    with pytest.raises(ValueError, match="poles"):
        w.Gains.from_poles(-1.0, 2, 2)
    with pytest.raises(ValueError, match="not Hurwitz"):
        w.Gains(jnp.array([[1.0, -0.5], [1.0, 2.0]])).check(2, 2)


def test_params_take_gains_and_refuse_bad_ones(paper61):
    ctrl, params, _ = paper61
    tuned = w.Gains.from_damping(3.76, 0.47, m=2)
    p = ctrl.params(params.reference, geometry=params.geometry, gains=tuned)
    np.testing.assert_array_equal(p.gains.coeffs, tuned.coeffs)
    with pytest.raises(ValueError, match=r"shape \(2, 2\)"):
        ctrl.params(params.reference, geometry=params.geometry, gains=w.Gains(jnp.ones((2, 3))))
    with pytest.raises(ValueError, match="complex pole pairs"):
        ctrl.params(params.reference, poles=jnp.array([1.0 + 1.0j, 1.0 - 1.0j]), geometry=params.geometry)
    with pytest.raises(ValueError, match="wmrjax.Gains"):
        ctrl.params(params.reference, geometry=params.geometry, gains=jnp.ones((2, 2)))


def test_lemma2_gives_eq64_only_for_the_double_pole_whatever_the_representation(paper61):
    """The latent bug of the old two representations: tuned gains (complex poles) must not get the
    eq (64) certificate, which is only a bound of ||e^{At}|| for the double pole at -1."""
    ctrl, params, _ = paper61
    kw = dict(t_final=10.0, eps=1e-2, n_t=1001)
    by_poles = C.lemma2(ctrl, params, **kw)
    by_damping = C.lemma2(ctrl, params._replace(gains=w.Gains.from_damping(1.0, 1.0, m=2)), **kw)
    assert by_poles.paper is not None and by_damping.paper is not None
    assert float(by_damping.paper.radius) == float(by_poles.paper.radius)
    np.testing.assert_allclose(float(by_poles.paper.radius), 0.7681795, atol=1e-7)  # §6.1 (summary.json)

    tuned = params._replace(gains=w.Gains.from_damping(3.76, 0.47, m=2))
    rep = C.lemma2(ctrl, tuned, **kw)
    assert rep.paper is None and set(rep.certificates()) == {"lyapunov", "exact_norm"}
    # why it matters: eq (64) is no bound for other gains (a lightly damped pair: ||e^{At}|| exceeds it)
    light = w.Gains.from_damping(1.0, 0.1, m=2)
    assert C.lemma2(ctrl, params._replace(gains=light), **kw).paper is None
    ts = np.linspace(0.0, 10.0, 201)
    exact = np.array([np.linalg.norm(expm(np.asarray(ctrl.error_matrix(light)) * t), 2) for t in ts])
    np.testing.assert_allclose(np.max(exact / np.asarray(C.k2_paper(ts))), 1.49896, rtol=1e-4)  # > 1: not a bound
    A = np.asarray(ctrl.error_matrix(tuned.gains))
    # the Lyapunov certificate for the tuned gains, against SciPy's Lyapunov solver
    P = solve_continuous_lyapunov(A.T, -np.eye(4))
    ev = np.linalg.eigvalsh(0.5 * (P + P.T))
    k2 = np.sqrt(ev[-1] / ev[0]) * np.exp(-0.5 / ev[-1] * np.asarray(rep.lyapunov.ts))
    F = (np.asarray(rep.lyapunov.m1) - 1e-2) / k2
    np.testing.assert_allclose(np.asarray(rep.lyapunov.F), F, rtol=1e-9)
    # the radius is min F refined between grid points: at most the grid minimum, and close to it
    assert np.min(F) * (1 - 1e-4) <= float(rep.lyapunov.radius) <= np.min(F)
    with pytest.raises(ValueError, match="m1 must be one of"):
        C.lemma2(ctrl, params, t_final=10.0, eps=1e-2, m1="closedform")


def test_sigma_tilde_reads_the_coefficients():
    ctrl = w.controller("(3,0)", "torque")
    p_poles = ctrl.params(R.circle(), poles=jnp.array([0.8, 2.0]))
    p_coeffs = p_poles._replace(gains=w.Gains(jnp.broadcast_to(jnp.array([1.6, 2.8]), (3, 2))))
    z = jnp.array([0.3, -0.2, 0.1, 0.4, 0.5, -0.1])
    np.testing.assert_allclose(ctrl.sigma_tilde(0.3, z, p_coeffs), ctrl.sigma_tilde(0.3, z, p_poles), rtol=1e-12)
    # the coefficients forget the order of the poles: (2.0, 0.8) is the same law, with Lambda_1 = 0.8
    p_desc = ctrl.params(R.circle(), poles=jnp.array([2.0, 0.8]))
    np.testing.assert_array_equal(p_desc.gains.coeffs, p_poles.gains.coeffs)
    np.testing.assert_allclose(ctrl.sigma_tilde(0.3, z, p_desc), ctrl.sigma_tilde(0.3, z, p_poles), rtol=1e-12)
    complex_gains = p_poles._replace(gains=w.Gains.from_damping(2.0, 0.5, m=3))
    assert np.all(np.isnan(np.asarray(ctrl.sigma_tilde(0.3, z, complex_gains))))
    # at a double pole the root is 0: finite derivative of Lambda_1 = k1 / 2 there
    dlam = jax.grad(lambda c: w.Gains(c).cascade_pole()[0])(jnp.array([[1.0, 2.0]]))
    np.testing.assert_allclose(dlam, [[0.0, 0.5]])


# --- controllers are siblings; certification refuses a static law ------------------------------


def test_static_and_dynamic_laws_are_siblings_and_certify_refuses_static():
    stat = w.controller("(2,0)", "velocity", "point")
    dyn = w.controller("(2,0)", "velocity", "posture")
    assert not isinstance(stat, w.DynamicLinearization) and not isinstance(dyn, w.StaticLinearization)
    assert (
        isinstance(stat, w.ClosedLoop)
        and isinstance(dyn, w.ClosedLoop)
        and isinstance(w.hybrid_parking(), w.ClosedLoop)
    )
    # siblings: neither is a kind of the other (a static law used to pass for a dynamic one)
    assert not issubclass(w.StaticLinearization, w.DynamicLinearization)
    assert not issubclass(w.DynamicLinearization, w.StaticLinearization)
    sp = stat.params(R.circle(), geometry=stat.row.default_geometry)
    for fn in (
        lambda: C.lemma2(stat, sp, t_final=5.0, eps=1e-2),
        lambda: C.exact_map_radius(stat, sp, t_final=5.0, eps=1e-2),
        lambda: C.min_distance(stat, sp, t_final=5.0, initial_errors=jnp.zeros((1, 2)), dt=0.1),
    ):
        with pytest.raises(ValueError, match="static law"):
            fn()


# --- static laws report their internal dynamics ---------------------------------------------------


@pytest.mark.parametrize(
    "delta, heading_offset, turned", [(0.5 * math.pi, math.pi - 0.3, False), (-0.5 * math.pi, 0.3, True)]
)
def test_static_law_flags_a_robot_that_turned_round(delta, heading_offset, turned):
    """(2,0) on a line, e = 0.3. With the point ahead of the axle (delta = pi/2) the heading
    (z3 = theta, uncontrolled) settles facing forward, even from a start nearly reversed; with
    the point behind it (delta = -pi/2) the robot tracks the point while it turns round, from a
    start facing forward. The point is tracked either way; the report tells the two apart."""
    ctrl = w.controller("(2,0)", "velocity", "point")
    p = ctrl.params(R.line(velocity=(1.0, 0.0)), geometry=w.Geometry(e=0.3, delta=delta))
    th0 = float(p.reference.posture(0.0)[2]) + heading_offset
    X = jnp.array([0.0, 0.0, th0])
    X = X.at[:2].add(-ctrl.outputs(X, p)[:2])
    z0 = ctrl.initial_state_from_physical(X, jnp.zeros(2), p)
    tr = w.simulate(ctrl, z0, p, dt=0.02, n_steps=500, save_every=500)
    rep = tr.diagnostics.internal
    assert isinstance(rep, w.InternalDynamics) and not bool(tr.diagnostics.failed)
    assert float(jnp.linalg.norm(ctrl.error(tr.t[-1], tr.final_state, p))) < 1e-6  # the point is tracked either way
    expected = np.angle(np.exp(1j * (float(tr.final_state[2]) - float(p.reference.posture(tr.t[-1])[2]))))
    np.testing.assert_allclose(float(rep.heading_error), expected, atol=1e-12)
    np.testing.assert_allclose(float(rep.z3_norm), abs(float(tr.final_state[2])), rtol=1e-12)
    assert bool(rep.turned_round) is turned
    np.testing.assert_allclose(abs(expected), math.pi if turned else 0.0, atol=1e-6)


# --- float32 ---------------------------------------------------------------------------------------


def test_float32_closed_loop_smoke():
    """The §6.1 loop runs in float32 (x64 off, in a fresh process) and agrees with float64 to 1e-3."""
    code = (
        "import jax, numpy as np\n"
        "import wmrjax as w\n"
        "from wmrjax import references as R\n"
        "def run():\n"
        "    ctrl = w.dynamic_linearization('(2,0)')\n"
        "    p = ctrl.params(R.paper_62(), poles=1.0, geometry=w.Geometry(e=0.0))\n"
        "    z0 = ctrl.initial_state(np.array([[4.81, 6.97], [-3.5355, -3.5355]]), p)\n"
        "    tr = w.simulate(ctrl, z0, p, dt=0.01, n_steps=300, save_every=300)\n"
        "    return tr.final_state\n"
        "z32 = run()\n"
        "jax.config.update('jax_enable_x64', True)\n"
        "z64 = run()\n"
        "print(z32.dtype, z64.dtype, float(np.max(np.abs(np.asarray(z32, float) - np.asarray(z64)))))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True)
    d32, d64, diff = out.stdout.split()
    assert (d32, d64) == ("float32", "float64") and float(diff) < 1e-3


# --- checkpoints -------------------------------------------------------------------------------------


def test_checkpoint_round_trip_and_refusals(tmp_path):
    path = tmp_path / "ck.json"
    trees = {"raw": jnp.arange(3.0), "opt": (jnp.zeros((2, 2)), jnp.asarray(4, dtype=jnp.int32))}
    files.write_checkpoint(path, fingerprint="abc", config={"lr": 0.1}, step=5, trees=trees, state={"best": 1.5})
    ck = files.read_checkpoint(path, fingerprint="abc", config={"lr": 0.1}, templates=trees)
    assert ck.step == 5 and ck.state == {"best": 1.5}
    np.testing.assert_array_equal(ck.trees["raw"], [0.0, 1.0, 2.0])
    assert ck.trees["opt"][1].dtype == jnp.int32 and int(ck.trees["opt"][1]) == 4
    with pytest.raises(ValueError, match=r"differs in \['lr'\]"):
        files.read_checkpoint(path, fingerprint="xyz", config={"lr": 0.2}, templates=trees)
    text = path.read_text().replace("2.0\n", "", 1)  # truncate the raw parameters by hand
    path.write_text(text.replace("1.0,", "1.0", 1))
    with pytest.raises(ValueError, match="raw"):
        files.read_checkpoint(path, fingerprint="abc", config={"lr": 0.1}, templates=trees)


def _calls(path, name):
    """Line numbers where ``path`` calls a function or method named ``name``."""
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Call):
            f = node.func
            if (isinstance(f, ast.Attribute) and f.attr == name) or (isinstance(f, ast.Name) and f.id == name):
                out.append(node.lineno)
    return out


def test_one_registry_of_reference_families():
    """Only wmrjax.references names the families: no other module holds a collection (tuple,
    list, set or dict keys) of two or more family names, and every family a problem file may
    name is in the registry."""
    names = set(R.FAMILIES) | {"random"}  # (the tuner once called random_smooth "random")
    for pkg in LAYERS:
        for f in _sources(pkg):
            if f == ROOT / "wmrjax" / "references.py":
                continue
            for node in ast.walk(ast.parse(f.read_text())):
                elts = node.keys if isinstance(node, ast.Dict) else getattr(node, "elts", None)
                if not isinstance(node, (ast.Tuple, ast.List, ast.Set, ast.Dict)) or elts is None:
                    continue
                found = [e.value for e in elts if isinstance(e, ast.Constant) and e.value in names]
                assert len(found) < 2, f"{f.relative_to(ROOT)}:{node.lineno} lists reference families {found}"
    assert set(R.REFERENCES) < set(R.FAMILIES) and {"samples", "waypoints", "random_smooth"} <= set(R.FAMILIES)


def test_one_initial_state_placement():
    """Initial states near a reference are placed by wmrjax.controllers.placement.place only: no
    other module of the library, the tuner or the experiments maps an output jet back (inverse_psi)."""
    allowed = set((ROOT / "wmrjax" / "controllers").rglob("*.py"))
    for pkg in LAYERS:
        for f in _sources(pkg):
            if f not in allowed:
                assert not _calls(f, "inverse_psi"), f"{f.relative_to(ROOT)} places states itself (inverse_psi)"
    users = [f.relative_to(ROOT).as_posix() for pkg in LAYERS for f in _sources(pkg) if _calls(f, "place")]
    assert {
        "wmrjax/problem/setting.py",
        "wmrjax/certify/empirical.py",
        "wmrjax/tune/scenarios.py",
        "paper/posture_tracking.py",
        "paper/static_tracking.py",
    } <= set(users)


def test_no_rk4_step_outside_simulate():
    """One RK4 step: wmrjax._rk4's (simulate's time loop runs it). No other module of the library, the tuner or the
    experiments weighs four stages 1, 2, 2, 1 (the benchmark's NumPy and C reference loops are
    oracles, not the library's integrator)."""
    pattern = re.compile(r"\+\s*2(\.0)?\s*\*\s*\w+\s*\+\s*2(\.0)?\s*\*\s*\w+\s*\+")
    for pkg in LAYERS:
        for f in _sources(pkg):
            if f.name in ("_rk4.py", "benchmark.py"):
                continue
            hits = [i + 1 for i, line in enumerate(f.read_text().splitlines()) if pattern.search(line)]
            assert not hits, f"{f.relative_to(ROOT)}:{hits} has an RK4 step of its own"
    assert _calls(ROOT / "wmrjax" / "linearize.py", "rk4_step")  # the transition matrix uses simulate's


def _level_literals(tree, names):
    """Line numbers where ``tree`` compares with one of ``names`` (``x == "torque"``, ``x in
    ("velocity", ...)``) or spells the whole set again as a tuple, list or set (``LEVELS =
    ("velocity", "torque")``, ``for lv in ("velocity", "torque")``), a ``choices=`` keyword excepted."""
    literal = lambda node: isinstance(node, ast.Constant) and node.value in names
    elements = lambda node: node.elts if isinstance(node, (ast.Tuple, ast.List, ast.Set)) else [node]
    choices = {
        id(kw.value)
        for node in ast.walk(tree)
        if isinstance(node, ast.Call)
        for kw in node.keywords
        if kw.arg == "choices"
    }
    hits = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Compare) and any(
            literal(e) for o in (node.left, *node.comparators) for e in elements(o)
        ):
            hits.append(node.lineno)
        elif (
            isinstance(node, (ast.Tuple, ast.List, ast.Set))
            and id(node) not in choices
            and names <= {e.value for e in node.elts if literal(e)}
        ):
            hits.append(node.lineno)
    return sorted(set(hits))


def test_levels_are_one_enumeration():
    """wmrjax.Level is the one enumeration of the levels: no module of the library, the command
    lines, the tuner or the experiments compares a level with the literal "velocity" or "torque"
    or lists the two again (the command lines' ``choices=`` are user-facing names). A StrEnum
    member equals and hashes as its name, so JSON outputs keep the names."""
    names = {str(lv) for lv in w.Level}
    assert names == {"velocity", "torque"} and w.Level is w.controllers.law.Level
    for pkg in LAYERS:
        for f in _sources(pkg):
            hits = _level_literals(ast.parse(f.read_text()), names)
            assert not hits, f"{f.relative_to(ROOT)}:{hits} compares or lists level names instead of wmrjax.Level"
    assert _level_literals(
        ast.parse('ok = level == "torque" or lv in ("velocity",)\nL = ["torque", "velocity"]'), names
    ) == [1, 2]  # the scan sees what it forbids
    summary = {f"(2,0) {lv}": {"level": lv, "levels": list(w.Level)} for lv in w.Level}
    assert json.dumps(summary) == (
        '{"(2,0) velocity": {"level": "velocity", "levels": ["velocity", "torque"]}, '
        '"(2,0) torque": {"level": "torque", "levels": ["velocity", "torque"]}}'
    )
    assert json.dumps({w.Level.TORQUE: 1}) == '{"torque": 1}'
    assert w.dynamic_linearization("(2,0)", "torque") == w.dynamic_linearization("(2,0)", w.Level.TORQUE)
    assert w.controller("(2,1)", "torque", "point").level is w.Level.TORQUE


MAX_FUNCTION_LINES = 80


def test_no_long_functions_in_the_library():
    """No function or method of wmrjax/ is longer than MAX_FUNCTION_LINES lines, from its
    ``def`` to its last line (docstring and nested functions included): a longer one is cut in
    named pieces."""
    long = []
    for f in _sources("wmrjax"):
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = node.end_lineno - node.lineno + 1
                if n > MAX_FUNCTION_LINES:
                    long.append(f"{f.relative_to(ROOT)}:{node.lineno} {node.name} ({n} lines)")
    assert not long, "functions longer than the limit: " + ", ".join(long)
