"""Bad input is refused before any work, with a message naming the argument.

Two layers, both asserting that no time loop was even traced (``jax.lax.scan``/``map``
spied on: every rollout, optimisation and batch in this project runs under one), which
proves nothing expensive was compiled:

* concrete cases (the reliability probe's, and one per argument and failure class) for
  the public functions and every command line;
* property-based cases (hypothesis, derandomized): random bad values for every numeric
  option of every command line and for the simulator's and certificates' arguments.

The number of distinct concrete cases is asserted at the end (the issue's target: >= 160).
"""

import importlib
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import refpaths
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import wmrjax as w
from wmrjax import certify as C
from wmrjax import references as R

SETTINGS = settings(
    max_examples=25,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)


@pytest.fixture
def no_loops(monkeypatch):
    """Fail if anything traces a time loop (lax.scan / lax.map) during the call."""
    calls = []

    def spy(name, fn):
        def wrapped(*a, **k):
            calls.append(name)
            return fn(*a, **k)

        return wrapped

    monkeypatch.setattr(jax.lax, "scan", spy("scan", jax.lax.scan))
    monkeypatch.setattr(jax.lax, "map", spy("map", jax.lax.map))
    return calls


@pytest.fixture(scope="module")
def loop61():
    ctrl = w.dynamic_linearization("(2,0)")
    params = ctrl.params(R.paper_62(), poles=1.0, geometry=w.Geometry(e=0.0))
    z0 = ctrl.reference_state(0.0, params)
    return ctrl, params, z0


# --- the public API: concrete cases --------------------------------------------------------------


def _api_cases():
    """(id, function of the §6.1 loop, the regex the ValueError must match)."""
    cases = []

    def add(name, fn, match):
        cases.append(pytest.param(fn, match, id=name))

    sim = lambda c, p, z, **k: w.simulate(c, k.pop("z0", z), k.pop("params", p), **({"dt": 0.01, "n_steps": 10} | k))
    for v in (0.0, -0.01, math.nan, math.inf, -math.inf, 1j, np.ones(2)):
        add(f"simulate-dt-{v!r}", lambda c, p, z, v=v: sim(c, p, z, dt=v), "dt must be")
    for v in (0, -1, 1.5, True, "10", None):
        add(f"simulate-n_steps-{v!r}", lambda c, p, z, v=v: sim(c, p, z, n_steps=v), "n_steps must be an integer")
    for v in (0, -2, 2.0, 11):
        add(f"simulate-save_every-{v!r}", lambda c, p, z, v=v: sim(c, p, z, save_every=v), "save_every must be")
    for v in (math.nan, math.inf, 1j, np.ones(2)):
        add(f"simulate-t0-{v!r}", lambda c, p, z, v=v: sim(c, p, z, t0=v), "t0 must be a finite real scalar")
    for v in (math.nan, -1.0, math.inf, 1j):
        add(f"simulate-margin_floor-{v!r}", lambda c, p, z, v=v: sim(c, p, z, margin_floor=v), "margin_floor must be")
    for v in (0.0, -1.0, math.nan, 1j):
        add(f"simulate-error_tol-{v!r}", lambda c, p, z, v=v: sim(c, p, z, error_tol=v), "error_tol must be")
    for name, z in (
        ("nan", lambda z: z.at[0].set(jnp.nan)),
        ("inf", lambda z: z.at[1].set(jnp.inf)),
        ("complex", lambda z: z.astype(jnp.complex128)),
        ("2d", lambda z: z[None]),
        ("short", lambda z: z[:3]),
        ("long", lambda z: jnp.concatenate([z, z])),
        ("empty", lambda z: ()),
        ("scalar", lambda z: z[0]),
    ):
        add(f"simulate-z0-{name}", lambda c, p, zz, f=z: sim(c, p, zz, z0=f(zz)), "z0 must be")
    add("simulate-unstable-dt", lambda c, p, z: sim(c, p, z, dt=3.0), "outside RK4's stability region")
    add("simulate-memory", lambda c, p, z: sim(c, p, z, dt=1e-10, n_steps=10**11), "of memory available now")
    add(
        "simulate-other-controller-params",
        lambda c, p, z: sim(
            c,
            p,
            z,
            params=w.dynamic_linearization("(1,1)").params(R.circle(), poles=1.0, geometry=w.Geometry(L=1.0, e=0.3)),
        ),
        r"coeffs must have shape \(2, 2\)",
    )
    add(
        "simulate-static-params",
        lambda c, p, z: sim(
            c, p, z, params=w.static_linearization("(2,0)").params(R.circle(), geometry=w.Geometry(e=0.3, delta=1.0))
        ),
        "params must be the DynamicParams",
    )
    add(
        "simulate-reference-stops",
        lambda c, p, z: sim(c, p, z, params=p._replace(reference=R.paper_66()), n_steps=1500),
        "singular set",
    )
    add(
        "simulate-reference-kink",
        lambda c, p, z: sim(c, p, z, params=p._replace(reference=R.from_function(refpaths.kink)), n_steps=500),
        "not smooth",
    )

    # parameters and references
    g0 = w.Geometry(e=0.0)
    for v in (0.0, -1.0, math.nan, math.inf, 1j, np.ones((3, 2)), np.ones(3)):
        add(f"params-poles-{v!r}", lambda c, p, z, v=v: c.params(R.paper_62(), poles=v, geometry=g0), "poles")
    add(
        "params-gains-shape",
        lambda c, p, z: c.params(R.paper_62(), gains=w.Gains(jnp.ones((2, 3))), geometry=g0),
        "coeffs",
    )
    add(
        "params-gains-type",
        lambda c, p, z: c.params(R.paper_62(), gains=np.ones((2, 2)), geometry=g0),
        "gains must be a wmrjax.Gains",
    )
    add(
        "params-gains-not-hurwitz",
        lambda c, p, z: c.params(R.paper_62(), gains=w.Gains(-jnp.ones((2, 2))), geometry=g0),
        "Hurwitz",
    )
    for name, ref in (
        ("function", lambda t: t),
        ("string", "paper_62"),
        ("stopped", R.line(velocity=(0.0, 0.0))),
        ("shape3", R.from_function(refpaths.three)),
        ("numpy", R.from_function(refpaths.numpy_path)),
    ):
        add(f"params-reference-{name}", lambda c, p, z, ref=ref: c.params(ref, poles=1.0, geometry=g0), "reference")
    for name, g in (("nan-e", w.Geometry(e=math.nan)), ("inf-L", w.Geometry(L=math.inf))):
        add(f"params-geometry-{name}", lambda c, p, z, g=g: c.params(R.paper_62(), geometry=g), "geometry")
    add(
        "static-params-e0",
        lambda c, p, z: w.static_linearization("(2,0)").params(R.circle(), geometry=w.Geometry(e=0.0)),
        "e",
    )
    add(
        "dynamic-12-L0",
        lambda c, p, z: w.dynamic_linearization("(1,2)").params(R.circle(), geometry=w.Geometry(L=0.0)),
        "L",
    )
    # a negative L was accepted as a mirrored robot; an integer key raised a raw TypeError
    add(
        "dynamic-11-L-negative",
        lambda c, p, z: w.dynamic_linearization("(1,1)").params(
            R.circle(), poles=1.0, geometry=w.Geometry(L=-1.0, e=0.3)
        ),
        r"geometry.L is a length .* must be >= 0",
    )
    add("random-smooth-int-key", lambda c, p, z: R.random_smooth(3), "key must be a jax.random key")
    # a complex path lost its imaginary part with a ComplexWarning; lemma2 under jit raised a raw
    # TracerArrayConversionError
    ts, circ = (
        np.linspace(0.0, 6.0, 13),
        np.stack([np.cos(np.linspace(0.0, 6.0, 13)), np.sin(np.linspace(0.0, 6.0, 13))], 1),
    )
    add("from-samples-complex", lambda c, p, z: R.from_samples(ts, circ.astype(complex)), "xy must be real")
    add("from-waypoints-complex", lambda c, p, z: R.from_waypoints(circ * (1 + 0j)), "points must be real")
    add(
        "lemma2-under-jit",
        lambda c, p, z: jax.jit(lambda q: C.lemma2(c, q, t_final=10.0, eps=0.01).exact_norm.radius)(p),
        "lemma2 runs eagerly",
    )
    # the probe's POOR cases of session 21: raw TracerArrayConversionErrors and a raw TypeError
    add(
        "exact-map-under-jit",
        lambda c, p, z: jax.jit(lambda q: C.exact_map_radius(c, q, t_final=10.0, eps=0.01).radius)(p),
        "exact_map_radius runs eagerly",
    )
    add(
        "gain-schedule-traced-knots",
        lambda c, p, z: jax.jit(
            lambda ts: w.GainSchedule.from_damping(ts, jnp.ones((2, 2, 1)), jnp.ones((2, 2, 1))).omega
        )(jnp.array([0.0, 5.0])),
        "knot times, which must be concrete",
    )
    add(
        "complex-path-from-function",
        lambda c, p, z: c.params(
            R.from_function(
                lambda t, q: jnp.stack(
                    [jax.lax.complex(2 * jnp.cos(0.5 * t), 0.1 * t), jax.lax.complex(2 * jnp.sin(0.5 * t), 0.0 * t)]
                )
            ),
            poles=1.0,
        ),
        "returns complex numbers",
    )
    for v in ("(4,0)", "(2,2)", "abc", None):
        add(f"robot-type-{v!r}", lambda c, p, z, v=v: w.dynamic_linearization(v), "type")
    add("level", lambda c, p, z: w.dynamic_linearization("(2,0)", "acceleration"), "level must be one of")
    add("controller-task", lambda c, p, z: w.controller("(2,0)", "velocity", "parking"), "task")
    add(
        "initial-state-singular",
        lambda c, p, z: c.initial_state(jnp.array([[5.0, 6.0], [0.0, 0.0]]), p),
        "singular set",
    )
    add(
        "initial-state-branch",
        lambda c, p, z: c.initial_state(jnp.array([[5.0, 6.0], [-3.5, -3.5]]), p, branch=-1),
        "Remark 17",
    )
    add("initial-state-shape", lambda c, p, z: c.initial_state(jnp.zeros(4), p), "zeta0 must have shape")
    add("check-reference-nan-horizon", lambda c, p, z: c.check_reference(p, math.nan), "t_final must be a finite time")
    add("check-reference-reversed-horizon", lambda c, p, z: c.check_reference(p, 1.0, t0=2.0), "must end after")

    # gains
    for v in (-1.0, 0.0, math.nan):
        add(f"gains-from_poles-{v!r}", lambda c, p, z, v=v: w.Gains.from_poles(v, 2, 2), "pole")
    for om, ze in ((-1.0, 1.0), (1.0, 0.0), (1.0, -0.5), (math.nan, 1.0)):
        add(
            f"gains-from_damping-{om}-{ze}",
            lambda c, p, z, om=om, ze=ze: w.Gains.from_damping(om, ze, m=2),
            "omega|zeta",
        )

    # certificates
    cert = lambda c, p, **k: C.lemma2(c, p, **({"t_final": 10.0, "eps": 0.01} | k))
    for v in (0, 1, 2, 2.5, 5, True):
        add(f"lemma2-n_t-{v!r}", lambda c, p, z, v=v: cert(c, p, n_t=v), "n_t")
    for v in ("closedform", "exact", 1, None):
        add(f"lemma2-m1-{v!r}", lambda c, p, z, v=v: cert(c, p, m1=v), "m1 must be one of")
    for v in (0.0, -0.01, math.nan, math.inf):
        add(f"lemma2-eps-{v!r}", lambda c, p, z, v=v: cert(c, p, eps=v), "eps must be > 0")
    for v in (0.0, -1.0, math.nan):
        add(f"lemma2-t_final-{v!r}", lambda c, p, z, v=v: cert(c, p, t_final=v), "horizon must be > 0")
    add("lemma2-static", lambda c, p, z: C.lemma2(w.static_linearization("(2,0)"), p, t_final=1.0, eps=0.01), "dynamic")
    add("lemma2-reference-stops", lambda c, p, z: cert(c, p._replace(reference=R.paper_66()), t_final=12.0), "eps")
    e4 = np.ones((3, 4))
    md = lambda c, p, **k: C.min_distance(c, p, **({"t_final": 1.0, "initial_errors": e4, "dt": 0.01} | k))
    for name, v in (
        ("shape", np.ones((3, 3))),
        ("1d", np.ones(4)),
        ("empty", np.ones((0, 4))),
        ("nan", np.full((2, 4), np.nan)),
        ("complex", np.ones((2, 4)) * 1j),
    ):
        add(f"min_distance-errors-{name}", lambda c, p, z, v=v: md(c, p, initial_errors=v), "initial_errors")
    for v in (0.0, -0.01, math.nan, 2.0, 1j):
        add(f"min_distance-dt-{v!r}", lambda c, p, z, v=v: md(c, p, dt=v), "dt")
    add("min_distance-save_every", lambda c, p, z: md(c, p, save_every=0), "save_every")
    ver = lambda c, p, **k: C.verify(c, p, **({"t_final": 1.0, "initial_errors": e4, "k2": C.k2_paper, "dt": 0.01} | k))
    add("verify-k2", lambda c, p, z: ver(c, p, k2=2.0), "k2 must be a function")
    add("verify-tol", lambda c, p, z: ver(c, p, tol=-1.0), "tol must be")
    add("verify-errors", lambda c, p, z: ver(c, p, initial_errors=np.ones((2, 5))), "initial_errors")
    fal = lambda c, p, **k: C.falsify(c, p, **({"t_final": 1.0, "radius": 1.0, "starts": e4, "dt": 0.02} | k))
    for name, k in (
        ("radius-0", dict(radius=0.0)),
        ("radius-nan", dict(radius=math.nan)),
        ("starts-shape", dict(starts=np.ones((2, 3)))),
        ("starts-zero", dict(starts=np.zeros((2, 4)))),
        ("steps-0", dict(steps=0)),
        ("lr-0", dict(learning_rate=0.0)),
        ("windows-0", dict(n_windows=0)),
        ("basis", dict(basis="diagonal")),
    ):
        add(f"falsify-{name}", lambda c, p, z, k=k: fal(c, p, **k), "slice" if "basis" in k else next(iter(k)))
    key = jax.random.PRNGKey(0)
    fr = lambda c, p, **k: C.falsified_radius(
        c, p, **({"t_final": 1.0, "eps": 0.01, "r_hi": 1.0, "key": key, "dt": 0.02} | k)
    )
    for name, k in (
        ("r_hi-0", dict(r_hi=0.0)),
        ("r_lo", dict(r_lo=2.0)),
        ("n_starts-0", dict(n_starts=0)),
        ("n_bisect", dict(n_bisect=-1)),
        ("dt", dict(dt=5.0)),
    ):
        add(f"falsified_radius-{name}", lambda c, p, z, k=k: fr(c, p, **k), "slice" if "basis" in k else next(iter(k)))
    er = lambda c, p, **k: C.empirical_radius(
        c, p, **({"t_final": 1.0, "eps": 0.01, "directions": e4, "r_max": 1.0, "dt": 0.01} | k)
    )
    for name, k in (
        ("r_max", dict(r_max=-1.0)),
        ("n_grid", dict(n_grid=1)),
        ("directions", dict(directions=np.ones(4))),
        ("n_bisect", dict(n_bisect=0)),
    ):
        add(f"empirical_radius-{name}", lambda c, p, z, k=k: er(c, p, **k), "slice" if "basis" in k else next(iter(k)))
    an = lambda c, p, **k: C.analyse(c, p, **({"t_final": 1.0} | k))
    for name, k in (
        ("n_directions", dict(n_directions=0)),
        ("n_empirical", dict(n_empirical=-5)),
        ("n_starts", dict(n_starts=-1)),
        ("falsifier_dt", dict(falsifier_dt=0.0)),
        ("log", dict(log=3)),
        ("seed", dict(seed=-1)),
    ):
        add(f"analyse-{name}", lambda c, p, z, k=k: an(c, p, **k), "slice" if "basis" in k else next(iter(k)))
    add(
        "curved_exact_map-linear",
        lambda c, p, z: C.curved_exact_map_radius(c, p, t_final=1.0, eps=0.01),
        "linear singular set",
    )
    add("batch_map-sizes", lambda c, p, z: w.batch_map(lambda a, b: a + b, jnp.ones(3), jnp.ones(4)), "leading batch")
    for bad in ("8", 2.5, True, 0):  # before: int(chunk) read "8" and 2.5, True as 1, 0 as 1
        add(
            f"batch_map-chunk-{bad!r}",
            lambda c, p, z, k=bad: w.batch_map(jnp.sin, jnp.ones(3), chunk=k),
            "chunk must be an integer >= 1",
        )
    # text and booleans where numbers are meant (issue 57): a raw TypeError, or True taken as 1
    add(
        "simulate-dt-text",
        lambda c, p, z: w.simulate(c, z, p, dt="0.01", n_steps=10),
        "dt must be a finite real scalar > 0 .s., got str",
    )
    add(
        "simulate-dt-bool",
        lambda c, p, z: w.simulate(c, z, p, dt=True, n_steps=10),
        "dt must be a finite real scalar > 0 .s., got bool",
    )
    add(
        "simulate-floor-text",
        lambda c, p, z: w.simulate(c, z, p, dt=0.01, n_steps=10, margin_floor="x"),
        "margin_floor must be a finite real scalar >= 0, got str",
    )
    add(
        "simulate-z0-text",
        lambda c, p, z: w.simulate(c, "abc", p, dt=0.01, n_steps=10),
        "z0 must be a state array of numbers",
    )
    add(
        "params-poles-text",
        lambda c, p, z: c.params(p.reference, poles="1.0"),
        "poles must be real pole magnitudes > 0, got str",
    )
    add(
        "params-poles-bool",
        lambda c, p, z: c.params(p.reference, poles=True),
        "poles must be real pole magnitudes > 0, got bool",
    )
    add(
        "geometry-text",
        lambda c, p, z: c.params(p.reference, poles=1.0, geometry=w.Geometry(e="0")),
        "geometry.e must be a real scalar",
    )
    return cases


API_CASES = _api_cases()


@pytest.mark.parametrize("call, match", API_CASES)
def test_api_refuses_bad_input_before_any_work(loop61, no_loops, call, match):
    ctrl, params, z0 = loop61
    with pytest.raises(ValueError, match=match):
        call(ctrl, params, z0)
    assert not no_loops, f"a time loop was traced before the refusal: {no_loops}"


# --- the command lines: concrete cases -----------------------------------------------------------

CLIS = {
    "section_6_1": "paper.section_6_1",
    "section_6_2": "paper.section_6_2",
    "posture_tracking": "paper.posture_tracking",
    "static_tracking": "paper.static_tracking",
    "certify": "wmrjax.cli.certify",
    "benchmark": "benchmarks.benchmark",
    "tuning": "wmrjax.cli.tune",
}

# every numeric option of every command line and the kind of value it takes
OPTIONS = {
    "section_6_1": {"--dt": "positive", "--t-final": "positive"},
    "section_6_2": {
        "--dt": "positive",
        "--t-final": "positive",
        "--n-batch": "count",
        "--tol-distance": "positive",
        "--tol-heading": "positive",
        "--r-switch": "positive",
        "--lam": "positive",
    },
    "posture_tracking": {"--n-random": "count", "--t-final": "positive", "--dt": "positive", "--seed": "seed"},
    "static_tracking": {"--n-random": "count", "--t-final": "positive", "--dt": "positive", "--seed": "seed"},
    "certify": {  # the problem options every job shares (wmrjax.cli.problem_args) and its own
        "--poles": "positive",
        "--t-final": "positive",
        "--dt": "positive",
        "--control-dt": "positive",
        "--heading-offset": "finite",
        "--devices": "count",
    },
    "benchmark": {
        "--batches": "count",
        "--reps": "count",
        "--grad-batch": "count",
        "--scipy-trajectories": "count",
        "--devices": "count",
    },
    "tuning": {"--poles": "positive", "--control-dt": "positive", "--t-final": "positive", "--dt": "positive"},
}
NARGS = {("certify", "--geometry"): 3, ("tuning", "--geometry"): 3}

BAD = {  # concrete bad values of each kind
    "positive": ["0", "-1", "nan", "inf", "-inf", "abc", "", "1e999"],
    "count": ["0", "-3", "1.5", "abc", "nan", ""],
    "nonnegative_int": ["-1", "2.5", "x"],
    "seed": ["-1", "4294967296", "1.5", "s"],
    "finite": ["nan", "inf", "-inf", "abc"],
    "grid": ["0", "1", "-4", "2.5"],
    "fraction": ["-0.1", "1", "1.5", "nan", "x"],
    "nonnegative": ["-0.01", "nan", "inf", "x"],
}


def _run_cli(name, argv, tmp_path, capsys, code=2):
    """The error message of a refused command line: exit status 2 with the usage for a bad option,
    ``code=1`` for an error of the work (no usage: the options were fine)."""
    mod = importlib.import_module(CLIS[name])
    argv = list(argv) + ["--no-compile-cache"]  # never touch the user's cache from the tests
    if "--out" not in argv:
        argv += ["--out", str(tmp_path / "out")]
    with pytest.raises(SystemExit) as exc:
        mod.main(argv)
    assert exc.value.code == code
    text = capsys.readouterr().err
    assert ("usage: " in text) == (code == 2), text
    err = text.strip().splitlines()
    assert ": error: " in err[-1], err  # argparse's "prog: error: message" line
    return err[-1].split(": error: ", 1)[1]  # the message, not the usage (which names every option)


def _option_cases():
    cases = []
    for cli, opts in OPTIONS.items():
        for opt, kind in opts.items():
            for v in BAD[kind]:
                cases.append(pytest.param(cli, [opt, v], opt, id=f"{cli}{opt}={v}"))
    for cli, opt in NARGS:
        for v in ("nan", "inf", "x"):
            cases.append(pytest.param(cli, [opt, "1", v, "0"], opt, id=f"{cli}{opt}=1,{v},0"))
    return cases


CROSS_CASES = [  # (cli, argv, what the message must say)
    ("section_6_1", ["--dt", "20"], "longer than the horizon"),
    ("section_6_1", ["--dt", "0.03"], "not a whole number of steps"),
    ("section_6_1", ["--dt", "1e-9"], "GB of memory available now"),
    ("section_6_2", ["--t-final", "5"], "must exceed 10 s"),
    ("section_6_2", ["--dt", "1e-9"], "GB of memory available now"),
    ("section_6_2", ["--n-batch", "100000000"], "memory available now: lower --n-batch"),
    ("posture_tracking", ["--types", "(9,9)"], "argument --types: unknown robot type"),
    ("posture_tracking", ["--types", "(3,0)"], "not among"),
    ("posture_tracking", ["--t-final", "1e308"], "--t-final"),  # finite, and t_final / dt overflows the step count
    ("static_tracking", ["--dt", "1e-9"], "GB of memory available now"),
    ("certify", ["--dt", "20"], "not a whole number of steps dt = 20.0 s"),
    ("certify", ["--robot", "(3,0)"], "certification needs a dynamic linearizing law"),
    ("certify", ["--robot", "(7,7)"], "unknown robot type"),
    (
        "certify",
        ["--set", "certify.n_directions=1000000"],
        "48000048 runs needs about",
    ),  # was std::bad_alloc after 90 s
    ("certify", ["--set", "certify.eps=0"], "[certify] eps"),
    ("certify", ["--set", "certify.map_grid=1"], "[certify] map_grid"),
    ("certify", ["--set", "certify.budget=-5"], "[certify] budget: expected a number >= 0"),
    ("certify", ["--reference", "spiral"], "or a CSV file of samples, got 'spiral'"),
    ("certify", ["--level", "jerk"], "argument --level: invalid choice"),
    ("certify", ["--robot", "(1,2)", "--geometry", "0", "0.3", "0"], "geometry.L must be != 0"),
    ("certify", ["--reference", "paper_66", "--t-final", "12"], "singular set"),
    ("tuning", ["--control-dt", "100"], "[plant] control_period = 100.0 s does not divide t_final"),
    ("tuning", ["--t-final", "0.01"], "[plant] control_period = 0.05 s does not divide t_final = 0.01 s"),
    ("tuning", ["--robot", "(2,0)", "--task", "point", "--geometry", "1", "0", "1.57"], "geometry.e must be != 0"),
    (
        "tuning",
        ["--robot", "(1,2)", "--geometry", "0", "0.3", "0", "--set", "plant.input_limit=[1,1,1]"],
        "geometry.L must be != 0",
    ),
    ("tuning", ["--set", "plant.input_limit=[-1,-1]"], "[plant] input_limit: values must be > 0, got -1"),
    ("tuning", ["--set", "plant.input_limit=[0,1]"], "[plant] input_limit: values must be > 0, got 0"),
    ("tuning", ["--set", "plant.input_limit=[1,2,3]"], "[plant] input_limit: expected a list of 2 numbers"),
    ("tuning", ["--set", "plant.noise_std=[-0.01,-0.01,-0.01]"], "[plant] noise_std: expected a list of at most 3"),
    ("tuning", ["--set", "plant.noise_std=[nan,0,0]"], "[plant] noise_std: expected a list of at most 3"),
    ("tuning", ["--set", "plant.noise_std=[0.1,0.1,0.1,0.1]"], "[plant] noise_std: expected a list of at most 3"),
    ("tuning", ["--set", "tune.scenarios.train=0"], "[tune.scenarios] train: expected an integer >= 1, got 0"),
    ("tuning", ["--set", "tune.seed=-1"], "[tune] seed: expected an integer >= 0 and <= 4294967295, got -1"),
    ("tuning", ["--set", "tune.scenarios.mismatch=1.5"], "[tune.scenarios] mismatch: expected a number in [0, 1)"),
    ("tuning", ["--set", "tune.stepz=3"], "[tune]: unknown key(s) ['stepz']"),
    ("tuning", ["--set", "nokey"], "argument --set: expected KEY=VALUE"),
    ("tuning", ["--set", "a..b=1"], "argument --set: expected KEY=VALUE"),
    ("tuning", ["--geometry", "1", "0", "nan"], "argument --geometry: must be finite"),
    ("tuning", ["--robot", "(5,5)"], "unknown robot type"),
    ("tuning", ["--reference", "spiral"], "or a CSV file of samples, got 'spiral'"),
    ("tuning", ["--task", "parking"], "argument --task: invalid choice"),
    ("tuning", ["--set", "tune.family.parameterization=gains"], 'parameterization: expected "damping" or "poles"'),
    (
        "tuning",
        ["--set", "tune.loss.tracking=0", "--set", "tune.loss.effort=0", "--set", "tune.loss.saturation=0"]
        + ["--set", "tune.loss.barrier=0"],
        "at least one",
    ),
    ("tuning", ["--set", "tune.loss.certificate=1", "--reference", "random_smooth"], "the certificate term needs"),
]


@pytest.mark.parametrize("cli, argv, opt", _option_cases())
def test_cli_option_refused_at_parse_time(cli, argv, opt, tmp_path, capsys, no_loops):
    err = _run_cli(cli, argv, tmp_path, capsys)
    assert f"argument {opt}" in err, err
    assert not no_loops


@pytest.mark.parametrize("cli, argv, what", CROSS_CASES, ids=[f"{c}:{' '.join(a)}" for c, a, _ in CROSS_CASES])
def test_cli_inconsistent_arguments_refused_before_work(cli, argv, what, tmp_path, capsys, no_loops):
    err = _run_cli(cli, argv, tmp_path, capsys)
    assert what in err, err
    assert not no_loops


@pytest.mark.parametrize("cli", list(CLIS))
def test_cli_output_path_checked_first(cli, tmp_path, capsys, no_loops):
    f = tmp_path / "a_file"
    f.write_text("x")
    err = _run_cli(cli, ["--out", str(f)], tmp_path, capsys)
    assert "exists and is not a directory" in err
    err = _run_cli(cli, ["--out", str(f / "sub")], tmp_path, capsys)  # under a file: cannot be created
    assert "not a writable directory" in err
    assert not no_loops


def test_corrupt_tuning_checkpoint_names_file_and_fresh(tmp_path, capsys):
    """Found by the work (the options are fine): exit 1 without the usage, naming the file, --fresh
    and --verbose (which shows the traceback)."""
    out = tmp_path / "out"
    out.mkdir()
    (out / "checkpoint.json").write_text('{"fingerprint": ')
    err = _run_cli(
        "tuning",
        [
            "--out",
            str(out),
            "--set",
            "tune.steps=1",
            "--set",
            "tune.scenarios.train=2",
            "--set",
            "tune.scenarios.heldout=2",
            "--set",
            "tune.baselines.cma_population=2",
            "--set",
            "tune.baselines.budget=2",
        ],
        tmp_path,
        capsys,
        code=1,
    )
    assert str(out / "checkpoint.json") in err and "--fresh" in err and "--verbose" in err


def test_every_cli_option_has_help_with_units():
    """Every option documents itself; physical quantities carry their unit in brackets."""
    physical = (
        "dt",
        "t-final",
        "eps",
        "tol-distance",
        "tol-heading",
        "r-switch",
        "lam",
        "geometry",
        "poles",
        "heading-offset",
        "input-limit",
        "noise-std",
        "control-dt",
    )
    for cli in CLIS:
        mod = importlib.import_module(CLIS[cli])
        p = mod.parser() if cli == "tuning" else _capture_parser(mod)
        for action in p._actions:
            if not action.option_strings or action.dest == "help":
                continue
            assert action.help and len(action.help) > 8, (cli, action.option_strings)
            name = action.option_strings[0].lstrip("-")
            if name in physical:
                assert "[" in action.help and "]" in action.help, (cli, name, action.help)
        assert "%(default)s" not in p.format_help()
        assert "(default:" in p.format_help()


def _capture_parser(mod):
    """The parser a command line builds (it raises SystemExit on --help; we take it just before)."""
    from wmrjax.cli import options

    captured = {}
    original = options.parser

    def spy(*a, **k):
        captured["p"] = original(*a, **k)
        return captured["p"]

    options.parser, saved = spy, options.parser
    try:
        try:
            mod.main(["--help"])
        except SystemExit:
            pass
    finally:
        options.parser = saved
    return captured["p"]


# --- property-based: random bad values --------------------------------------------------------------


def _bad_text(kind):
    finite_bad = {
        "positive": st.floats(max_value=0.0, allow_nan=False, allow_infinity=False),
        "count": st.integers(max_value=0),
        "nonnegative_int": st.integers(max_value=-1),
        "seed": st.one_of(st.integers(max_value=-1), st.integers(min_value=2**32, max_value=2**70)),
        "finite": st.nothing(),
        "grid": st.integers(max_value=1),
        "fraction": st.one_of(
            st.floats(max_value=-1e-12, allow_nan=False, allow_infinity=False),
            st.floats(min_value=1.0, allow_nan=False, allow_infinity=False),
        ),
        "nonnegative": st.floats(max_value=-1e-300, allow_nan=False, allow_infinity=False),
    }[kind]
    junk = st.sampled_from(
        ["nan", "inf", "-inf", "", "1,5", "one", "0x10"]
        + (["2.5"] if "int" in kind or kind in ("count", "seed", "grid") else [])
    )
    return st.one_of(finite_bad.map(repr), junk)


@st.composite
def _cli_bad(draw):
    cli = draw(st.sampled_from(sorted(OPTIONS)))
    opt = draw(st.sampled_from(sorted(OPTIONS[cli])))
    return cli, opt, draw(_bad_text(OPTIONS[cli][opt]))


@SETTINGS
@given(case=_cli_bad())
def test_property_cli_bad_numbers(case, tmp_path, capsys, monkeypatch):
    cli, opt, value = case
    traced = []
    monkeypatch.setattr(jax.lax, "scan", lambda *a, **k: traced.append(1))
    err = _run_cli(cli, [opt, value], tmp_path, capsys)
    assert f"argument {opt}" in err, (case, err)
    assert not traced


_bad_scalar = st.one_of(
    st.floats(max_value=0.0),
    st.just(math.inf),
    st.just(math.nan),
    st.complex_numbers(min_magnitude=1e-3, allow_nan=False, allow_infinity=False).filter(lambda c: c.imag != 0),
)


@SETTINGS
@given(
    kw=st.one_of(
        st.builds(lambda v: {"dt": v}, _bad_scalar),
        st.builds(lambda v: {"t0": v}, st.one_of(st.just(math.nan), st.just(math.inf), st.just(-math.inf))),
        st.builds(
            lambda v: {"margin_floor": v}, st.one_of(st.floats(max_value=-1e-300), st.just(math.nan), st.just(math.inf))
        ),
        st.builds(lambda v: {"error_tol": v}, st.one_of(st.floats(max_value=0.0), st.just(math.nan))),
        st.builds(lambda v: {"n_steps": v}, st.one_of(st.integers(max_value=0), st.floats(), st.text(max_size=3))),
        st.builds(
            lambda v: {"save_every": v}, st.one_of(st.integers(max_value=0), st.integers(min_value=11, max_value=10**6))
        ),
        st.builds(
            lambda i, v: {"z0_entry": (i, v)}, st.integers(0, 3), st.sampled_from([math.nan, math.inf, -math.inf])
        ),
    )
)
def test_property_simulate_bad_arguments(loop61, kw, monkeypatch):
    ctrl, params, z0 = loop61
    traced = []
    monkeypatch.setattr(jax.lax, "scan", lambda *a, **k: traced.append(1))
    args = {"dt": 0.01, "n_steps": 10}
    if "z0_entry" in kw:
        i, v = kw.pop("z0_entry")
        z0 = z0.at[i].set(v)
    args.update(kw)
    with pytest.raises(ValueError, match="must be|z0"):
        w.simulate(ctrl, z0, params, **args)
    assert not traced


@SETTINGS
@given(
    kw=st.one_of(
        st.builds(lambda v: {"n_t": v}, st.one_of(st.integers(max_value=2), st.floats(), st.booleans())),
        st.builds(lambda v: {"eps": v}, st.one_of(st.floats(max_value=0.0), st.just(math.nan), st.just(math.inf))),
        st.builds(lambda v: {"t_final": v}, st.one_of(st.floats(max_value=0.0), st.just(math.nan), st.just(math.inf))),
        st.builds(lambda v: {"m1": v}, st.text(max_size=12).filter(lambda s: s not in ("closed", "numerical"))),
    )
)
def test_property_lemma2_bad_arguments(loop61, kw):
    ctrl, params, _ = loop61
    with pytest.raises(ValueError, match="must be|n_t"):
        C.lemma2(ctrl, params, **({"t_final": 10.0, "eps": 0.01} | kw))


def test_bad_input_cases_are_distinct():
    """Every concrete case is its own input: a case listed twice (the same name, or the same
    command line) would run one check twice and count it as two. (This replaced a count of these
    lists' own lengths, which could not fail.)"""
    api = [c.id for c in API_CASES]
    assert len(api) == len(set(api)), sorted({i for i in api if api.count(i) > 1})
    options = [(c.values[0], tuple(c.values[1])) for c in _option_cases()]
    assert len(options) == len(set(options))
    cross = [(cli, tuple(argv)) for cli, argv, _ in CROSS_CASES]
    assert len(cross) == len(set(cross)) and not set(cross) & set(options)
