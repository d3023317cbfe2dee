"""Late or unclear refusals: checks that cannot run under ``jax.jit`` and must say so, messages that
must name the real cause, raw exceptions that must become a ValueError naming the argument, and
problem files whose bad keys must be named."""

from __future__ import annotations

import re

from tests.probe import specs
from tests.probe.harness import BAD, GOOD, POOR, Case
from tests.probe.oracles import cli_refuses, cli_succeeds, hang, refuses, short

CAT = "late_or_unclear"


def _warned(pattern: str, silent: str = POOR, what: str = "returned"):
    """Accepted under jit: GOOD if a warning says the check is not run, ``silent`` otherwise."""

    def accepted(run):
        said = [x["message"] for x in run.warnings if re.search(pattern, x["message"], re.I)]
        if said:
            return GOOD, f"{what}, with a warning: {short(said[0])}"
        return silent, f"{what} without a word: {short(run.results, 150)}"

    return accepted


STOPS = "t = np.linspace(0.0, 6.0, 31)\nxy = np.stack([(t - 3.0) ** 3 / 9.0, np.zeros_like(t)], axis=1)\n"

JIT = {
    "initial-state-singular-under-jit": (
        "initial_state under jax.jit on the singular set (zero output velocity)",
        "ctrl, p, z0 = loop61()\narm()\nz = jax.jit(lambda zeta: ctrl.initial_state(zeta, p))("
        "jnp.array([[5.0, 6.0], [0.0, 0.0]]))\nemit(state=z)",
        r"singular|not checked|eager|jit|traced",
        True,
    ),
    "min-speed-under-jit": (
        "from_samples(min_speed=0.05) under jax.jit on samples of a path that stops at t = 3 s",
        STOPS + "arm()\nv = jax.jit(lambda xy: R.from_samples(t, xy, min_speed=0.05).position(1.0))(jnp.asarray(xy))\n"
        "emit(position=v)",
        r"min_speed|not checked|slows|stops",
        True,
    ),
    "lemma2-under-jit": (
        "certify.lemma2 under jax.jit (traced params)",
        "ctrl, p, z0 = loop61()\narm()\nr = jax.jit(lambda q: C.lemma2(ctrl, q, t_final=10.0, eps=0.01)"
        ".exact_norm.radius)(p)\nemit(radius=r)",
        r"eager|jit|traced|concrete",
        True,
    ),
    "exact-map-under-jit": (
        "certify.exact_map_radius under jax.jit (traced params)",
        "ctrl, p, z0 = loop61()\narm()\nr = jax.jit(lambda q: C.exact_map_radius(ctrl, q, t_final=10.0, eps=0.01)"
        ".radius)(p)\nemit(radius=r)",
        r"eager|jit|traced|concrete",
        False,
    ),
    "gain-schedule-traced-knots": (
        "GainSchedule.from_damping under jax.jit with traced knot times",
        "from wmrjax.gains import GainSchedule\nones = jnp.ones((2, 2, 1))\narm()\n"
        "g = jax.jit(lambda ts: GainSchedule.from_damping(ts, ones, ones).omega)(jnp.array([0.0, 5.0]))\n"
        "emit(shape=g.shape)",
        r"knot|times|eager|jit|traced|concrete",
        True,
    ),
    "check-reference-traced-horizon": (
        "ctrl.check_reference under jax.jit with a traced t_final",
        "ctrl, p, z0 = loop61()\narm()\njax.jit(lambda T: ctrl.check_reference(p, T))(5.0)\nemit(ok=True)",
        r"t_final|eager|jit|traced|concrete",
        False,
    ),
    "n-steps-traced": (
        "simulate under jax.jit with a traced n_steps",
        "ctrl, p, z0 = loop61()\narm()\njax.jit(lambda n: w.simulate(ctrl, z0, p, dt=0.01, n_steps=n).final_state)(10)\n"
        "emit(ok=True)",
        r"n_steps",
        False,
    ),
}

MESSAGES = {
    "path-that-stops-message": (
        "check_reference of sampled path that stops at t = 3 s (its speed (t - 3)^2 / 3)",
        STOPS + "ctrl = w.dynamic_linearization('(2,0)', 'velocity')\n"
        "p = ctrl.params(R.from_samples(t, xy), poles=1.0, geometry=w.Geometry())\narm()\nctrl.check_reference(p, 6.0)",
        r"stop|speed|singular|at rest",
        True,
        "x64",
    ),
    "epoch-seconds-message": (
        "a sampled circle timed in epoch seconds (t = 1.7e9 + [0, 10] s), simulated from t0 = 1.7e9 (if run: "
        "against the same samples timed from 0)",
        "ts, xy, _ = circle_samples(0.0, 10.0, 101)\nctrl = w.dynamic_linearization('(2,0)', 'velocity')\n"
        "late = ctrl.params(R.from_samples(ts + 1.7e9, xy), poles=1.0, geometry=w.Geometry())\n"
        "early = ctrl.params(R.from_samples(ts, xy), poles=1.0, geometry=w.Geometry())\n"
        "b = w.simulate(ctrl, ctrl.reference_state(0.0, early).at[0].add(0.1), early, dt=0.01, n_steps=500, "
        "save_every=500)\nz0 = ctrl.reference_state(1.7e9, late).at[0].add(0.1)\n"
        "arm()\na = w.simulate(ctrl, z0, late, dt=0.01, n_steps=500, t0=1.7e9, save_every=500)\n"
        "emit(failed=bool(a.diagnostics.failed), difference=float(jnp.max(jnp.abs(a.final_state - b.final_state))))",
        r"epoch|clock",
        True,
        "x64",
    ),
    "float32-roundoff-message": (
        "a sampled circle checked over 20 s with float32 (x64 off)",
        "ts, xy, _ = circle_samples(0.0, 20.0, 400)\nctrl = w.dynamic_linearization('(2,0)', 'velocity')\n"
        "p = ctrl.params(R.from_samples(ts, xy), poles=1.0, geometry=w.Geometry())\narm()\nctrl.check_reference(p, 20.0)",
        r"float32|round|x64|precision",
        True,
        "x32",
    ),
}

RAW = {
    "complex-path-from-function": (
        "a path function returning a complex position (from_function), given to params and simulated",
        "ctrl, p, z0 = loop61()\nref = R.from_function(lambda t, q: jnp.stack([2 * jnp.cos(0.5 * t) + 0.1j * t, "
        "2 * jnp.sin(0.5 * t)]))\narm()\nq = ctrl.params(ref, poles=1.0, geometry=w.Geometry(e=0.0))\n"
        "tr = w.simulate(ctrl, ctrl.reference_state(0.0, q), q, dt=0.01, n_steps=100)\n"
        "emit(state=str(tr.final_state.dtype), failed=bool(tr.diagnostics.failed))",
        r"real|complex",
        True,
    ),
    "random-smooth-integer-key": (
        "references.random_smooth(3): an integer where a jax.random key is expected",
        "arm()\nref = R.random_smooth(3)\nemit(name=ref.name)",
        r"key",
        True,
    ),
    "negative-L": (
        "a dynamic (1,1) law with geometry L = -1 m (was taken as a mirrored robot)",
        "arm()\np = w.dynamic_linearization('(1,1)').params(R.circle(), poles=1.0, geometry=w.Geometry(L=-1.0, e=0.3))\n"
        "emit(L=float(p.geometry.L))",
        r"\bL\b",
        True,
    ),
    "initial-state-singular-eager": (
        "initial_state on the singular set, eagerly (control: refused)",
        "ctrl, p, z0 = loop61()\narm()\nctrl.initial_state(jnp.array([[5.0, 6.0], [0.0, 0.0]]), p)",
        r"singular",
        False,
    ),
}


def _same_as_from_zero(run):
    """Accepted: right only if the run equals the same samples timed from 0 (to 1 mm)."""
    r = run.results
    if r["failed"] or r["difference"] > 1e-3:
        return BAD, f"accepted: failed = {r['failed']}, {r['difference']:.3g} m from the run timed from 0"
    return GOOD, f"accepted: the run equals the one timed from 0 to {r['difference']:.2g} m"


def _library() -> list[Case]:
    out = []
    for cid, (desc, code, pattern, issue) in JIT.items():
        out.append(Case(cid, CAT, desc, refuses(pattern, accepted=_warned(pattern)), code=code, issue=issue))
    for cid, (desc, code, pattern, issue, prelude) in MESSAGES.items():
        accepted = {"x32": lambda run: (GOOD, "accepted: no false alarm"), "x64": POOR}[prelude]
        if cid.startswith("epoch"):
            accepted = _same_as_from_zero
        out.append(Case(cid, CAT, desc, refuses(pattern, accepted=accepted), code=code, issue=issue, prelude=prelude))
    for cid, (desc, code, pattern, issue) in RAW.items():
        accepted = _warned(r"complex|imaginary", silent=BAD) if "complex" in cid else POOR
        out.append(Case(cid, CAT, desc, refuses(pattern, accepted=accepted), code=code, issue=issue))
    return out


# --- files and keys of the command lines --------------------------------------------------------

FRESH = """
from probe_driver import run, same_table, finished
import shutil
first = finished("a.toml", "out")
shutil.copy("out/runs.parquet", "original.parquet")
open("out/sweep_state.json", "w").write("{not json")
again = run("-m", "wmrjax", "sweep", "a.toml", "--out", "out", "--fresh")
emit(again=again, same=same_table("out/runs.parquet", "original.parquet"))
"""


def _fresh(run):
    if run.timed_out:
        return hang(run)
    a = run.results["again"]
    if a["rc"] == 0 and run.results["same"]:
        return GOOD, "exit 0 with --fresh: the same table"
    if a["rc"] == 0:
        return POOR, "exit 0 with --fresh, but another table"
    return POOR, f"refused although --fresh was given (exit {a['rc']}): {short(a['last'])}"


def _summary_written(run):
    ok = run.file("out/summary.json").exists()
    return ok, f"exit 0, summary.json {'written' if ok else 'missing'}: {short(run.last_line)}"


def _spec(changes) -> dict:
    return {"s.toml": specs.sweep(1.0, changes)}


def _gains(value: str) -> dict:
    return {"s.toml": specs.sweep(1.0, [("poles = 1.0", f"file = {value}")])}


SWEEP = ("-m", "wmrjax", "sweep", "s.toml", "--out", "out")
NAMED = r"s\.toml|\[\w+\]"


_SPEC = specs.sweep(1.0)
_BOM = b"\xef\xbb\xbf" + _SPEC.encode()
_LATIN = b"# r\xe9sum\xe9 of the probe\n" + _SPEC.encode()
_KEYS = [
    (
        "spec-duplicate-key",
        "a sweep file with t_final given twice",
        _spec([("dt = 0.02", "dt = 0.02\nt_final = 3.0")]),
        NAMED,
    ),
    ("spec-dt-string", 'a sweep file with dt = "0.02" (a string)', _spec([("dt = 0.02", 'dt = "0.02"')]), r"dt"),
    ("spec-t-final-inf", "a sweep file with t_final = inf", _spec([("t_final = 2.0", "t_final = inf")]), r"t_final"),
    ("spec-dt-nan", "a sweep file with dt = nan", _spec([("dt = 0.02", "dt = nan")]), r"\bdt\b"),
    ("spec-level-capitalised", 'a sweep file with level = "Velocity"', _spec([('"velocity"', '"Velocity"')]), r"level"),
    (
        "spec-points-wrong-length",
        "a sweep file with [initial] points of 3 numbers (4 expected)",
        _spec([("x = [-0.5, 0.0, 0.7]\ny = { min = -1.0, max = 1.0, num = 3 }", "points = [[0.1, 0.0, 0.0]]")]),
        r"points",
    ),
    (
        "spec-classify-negative-tol",
        "a sweep file with [classify] position_tol = -1",
        _spec([("block = 4", "block = 4\n[classify]\nposition_tol = -1.0")]),
        r"position_tol",
    ),
    (
        "spec-random-count-float",
        "a sweep file with [initial] random = { count = 4.5 }",
        _spec(
            [
                (
                    "x = [-0.5, 0.0, 0.7]\ny = { min = -1.0, max = 1.0, num = 3 }",
                    "random = { count = 4.5 }\nx = { low = -0.5, high = 0.5 }",
                )
            ]
        ),
        r"count",
    ),
    (
        "gains-file-list-of-lists",
        '[gains] file = [["g.json"]] (was a raw traceback)',
        _gains('[["g.json"]]'),
        r"\[gains\] file",
    ),
    ("gains-file-list-of-numbers", "[gains] file = [1, 2]", _gains("[1, 2]"), r"\[gains\] file"),
    ("gains-file-empty-list", "[gains] file = []", _gains("[]"), r"\[gains\] file|empty"),
]
CLI_CASES = [
    Case(cid, CAT, desc, cli_refuses(pattern), argv=SWEEP, files=files, issue=cid == "gains-file-list-of-lists")
    for cid, desc, files, pattern in _KEYS
]
CLI_CASES += [
    Case(
        "sweep-fresh-with-corrupt-state",
        CAT,
        "a sweep rerun with --fresh over a corrupt sweep_state.json (was refused with 'delete it or pass --fresh')",
        _fresh,
        code=FRESH,
        files={"a.toml": _SPEC},
        prelude="none",
        issue=True,
        timeout=150,
    ),
    Case(
        "spec-not-utf8",
        CAT,
        "a sweep file with a Latin-1 byte in a comment",
        cli_refuses(r"s\.toml"),
        argv=SWEEP,
        files={"s.toml": _LATIN},
        issue=True,
    ),
    Case(
        "spec-byte-order-mark",
        CAT,
        "a sweep file starting with a UTF-8 byte-order mark (as spreadsheet programs write)",
        cli_succeeds(_summary_written),
        argv=SWEEP,
        files={"s.toml": _BOM},
        issue=True,
        timeout=150,
    ),
    Case(
        "tuning-file-byte-order-mark",
        CAT,
        "a tuning problem file starting with a UTF-8 byte-order mark",
        cli_succeeds(lambda run: (run.file("out/gains.json").exists(), "exit 0, gains.json written")),
        argv=("-m", "wmrjax", "tune", "t.toml", "--out", "out"),
        files={"t.toml": b"\xef\xbb\xbf" + specs.TUNE.encode()},
        timeout=150,
    ),
    Case(
        "static-point-sweep-histogram",
        CAT,
        "a sweep of a static point law, whose |det K| is the same for every run (its histogram raised 'Too many bins')",
        cli_succeeds(_summary_written),
        argv=SWEEP,
        files={"s.toml": specs.STATIC_POINT_SWEEP},
        issue=True,
        timeout=150,
    ),
    Case(
        "tuning-reference-missing-file",
        CAT,
        "wmrjax tune --reference missing.csv",
        cli_refuses(r"missing\.csv"),
        argv=("-m", "wmrjax", "tune", "--reference", "missing.csv", "--out", "out"),
    ),
    Case(
        "tuning-knot-times-decreasing",
        CAT,
        "wmrjax tune --set tune.family.knot_times=[5,1] (not increasing)",
        cli_refuses(r"knot"),
        argv=("-m", "wmrjax", "tune", "--set", "tune.family.knot_times=[5,1]", *specs.TUNE_SMALL, "--out", "out"),
    ),
    Case(
        "certify-static-law-file",
        CAT,
        "wmrjax certify of a static-law problem file",
        cli_refuses(r"static|dynamic"),
        argv=("-m", "wmrjax", "certify", "s.toml", "--out", "out"),
        files={"s.toml": specs.STATIC_POINT_SWEEP},
    ),
    Case(
        "certify-unknown-case",
        CAT,
        "wmrjax certify --case nope of a file with cases a and b",
        cli_refuses(r"nope|case"),
        argv=("-m", "wmrjax", "certify", "s.toml", "--case", "nope", "--out", "out"),
        files=_spec([("block = 4", 'block = 4\n[[case]]\nname = "a"\n[[case]]\nname = "b"')]),
    ),
]


def cases() -> list[Case]:
    """Every late-or-unclear case."""
    return _library() + CLI_CASES
