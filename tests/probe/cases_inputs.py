"""Inputs that must mean one thing (wrong answers when they do not): duplicated columns and
list entries, tuned gains of another robot, level or law, complex numbers."""

from __future__ import annotations

import json
import re

from tests.probe import specs
from tests.probe.harness import BAD, GOOD, POOR, Case
from tests.probe.oracles import cli_refuses, refuses, short

CAT = "wrong_answer"
TWICE = r"twice|more than once|duplicat|repeated"


def _runs(run) -> str:
    try:
        s = json.loads(run.file("out/summary.json").read_text())
        return f"{s.get('runs')} runs, counts {s.get('counts')}"
    except (OSError, ValueError):
        return "no summary.json"


def _dup_accepted(run):
    return BAD, f"exit 0: {_runs(run)} (the duplicate is run or counted twice)"


# --- duplicated columns and list entries ---------------------------------------------------------

LOAD = """
arm()
ref = R.load_samples("dup.csv")
emit(position_at_1s=[float(v) for v in ref.position(1.0)])
"""


def _csv_dup(header: str, extra) -> str:
    rows = specs.circle_csv(0.0, 12.0, 121).splitlines()[1:]
    body = [f"{r},{extra(float(r.split(',')[0]), float(r.split(',')[1]))!r}" for r in rows]
    return "\n".join([header] + body) + "\n"


def _column_cases() -> list[Case]:
    dup_x = _csv_dup("t,x,y,x", lambda t, x: x + 5.0)
    dup_t = _csv_dup("t,x,y,t", lambda t, x: t + 100.0)
    accepted = lambda run: (BAD, f"loaded: the path at 1 s is {run.results.get('position_at_1s')}")  # noqa: E731
    problem = specs.SAMPLES_SWEEP.replace("circle.csv", "dup.csv").replace("T_FINAL", "2.0")
    return [
        Case(
            "csv-duplicate-column-x",
            CAT,
            "load_samples of a CSV whose header is t,x,y,x (the second x 5 m off)",
            refuses(TWICE, accepted=accepted),
            code=LOAD,
            files={"dup.csv": dup_x},
            issue=True,
        ),
        Case(
            "csv-duplicate-column-t",
            CAT,
            "load_samples of a CSV whose header is t,x,y,t (the second t 100 s later)",
            refuses(TWICE, accepted=accepted),
            code=LOAD,
            files={"dup.csv": dup_t},
        ),
        Case(
            "csv-duplicate-column-problem",
            CAT,
            "a problem file whose samples file has the header t,x,y,x",
            refuses(TWICE),
            code='from wmrjax.problem import Problem\narm()\nProblem.load("s.toml")',
            files={"s.toml": problem, "dup.csv": dup_x},
        ),
        Case(
            "csv-duplicate-column-tuning-cli",
            CAT,
            "wmrjax tune --reference dup.csv (header t,x,y,x)",
            cli_refuses(TWICE),
            argv=(
                "-m",
                "wmrjax",
                "tune",
                "--reference",
                "dup.csv",
                "--t-final",
                "2",
                *specs.TUNE_SMALL,
                "--out",
                "out",
            ),
            files={"dup.csv": dup_x},
            timeout=180,
        ),
    ]


def _spec_dup(cid: str, desc: str, changes, issue=False, note="", extra_files=None, pattern=TWICE) -> Case:
    return Case(
        f"sweep-{cid}",
        CAT,
        desc,
        cli_refuses(pattern, accepted=_dup_accepted),
        argv=("-m", "wmrjax", "sweep", "s.toml", "--out", "out"),
        files={"s.toml": specs.sweep(1.0, changes), **(extra_files or {})},
        issue=issue,
        note=note,
        timeout=150,
    )


def _list_cases() -> list[Case]:
    g = specs.gains_json("(2,0)", "velocity", "dynamic", [[1.0, 2.0], [1.0, 2.0]])
    cases = '\n[[case]]\nname = "a"\n[[case]]\nname = "a"\n'
    uncertain = (
        "whether a duplicated axis value must be refused is the issue's rule ('duplicated list entries ... "
        "refused by name') applied beyond its example (robot); accepted, the same run is in the table twice"
    )
    return [
        _spec_dup(
            "robot-listed-twice",
            'a sweep with robot = ["(2,0)", "(2,0)"]',
            [('robot = "(2,0)"', 'robot = ["(2,0)", "(2,0)"]')],
            issue=True,
        ),
        _spec_dup(
            "level-listed-twice",
            'a sweep with level = ["velocity", "velocity"]',
            [('level = "velocity"', 'level = ["velocity", "velocity"]')],
        ),
        _spec_dup(
            "gains-file-listed-twice",
            'a sweep with [gains] file = ["g.json", "g.json"]',
            [("poles = 1.0", 'file = ["g.json", "g.json"]')],
            extra_files={"g.json": g},
        ),
        _spec_dup(
            "case-name-twice",
            "a sweep with two [[case]]s named 'a'",
            [("block = 4", "block = 4\n" + cases)],
            pattern=TWICE + "|used by another case",
        ),
        _spec_dup(
            "axis-value-twice",
            "a sweep with [initial] x = [0.0, 0.0, 0.7]",
            [("x = [-0.5, 0.0, 0.7]", "x = [0.0, 0.0, 0.7]")],
            note=uncertain,
        ),
        _spec_dup(
            "poles-value-twice",
            "a sweep with [gains] poles = [1.0, 1.0]",
            [("poles = 1.0", "poles = [1.0, 1.0]")],
            note=uncertain,
        ),
    ]


# --- tuned gains of another robot, level or law --------------------------------------------------

STATIC11 = """title = "static11"
[controller]
law = "static"
robot = "(1,1)"
[reference]
family = "circle"
[initial]
space = "physical"
x = [0.0, 0.1]
[gains]
file = "GAINS"
[simulation]
t_final = 1.0
dt = 0.02
"""

TUNE20 = specs.TUNE.replace(
    'robot = "(3,0)"\ntask = "posture"', 'robot = "(2,0)"\nlevel = "velocity"\ntask = "point"'
).replace('family = "line"', 'family = "circle"')
# the same for (1,1), its level left to the default (velocity), as most problem files do
TUNE11 = specs.TUNE.replace('robot = "(3,0)"\ntask = "posture"', 'robot = "(1,1)"\ntask = "point"').replace(
    'family = "line"', 'family = "circle"'
)

FROM_TUNER = """
from probe_driver import run
t = run("-m", "wmrjax", "tune", "tune20.toml", "--out", "t")
s = run("-m", "wmrjax", "sweep", "s.toml", "--out", "out")
emit(tuning=t, sweep=s)
"""

OTHER = r"another|robot|tuned for|\(2,0\)|level|law"


def _own_summary(run):
    r = run.results
    if r["tuning"]["rc"] != 0:
        return POOR, f"the tuning failed: {short(r['tuning']['last'])}"
    s = r["sweep"]
    if s["rc"] == 0:
        return GOOD, f"exit 0: the (1,1) tuning's summary.json read as (1,1) gains ({_runs(run)})"
    return POOR, f"a valid input refused (exit {s['rc']}): {short(s['last'])}"


def _from_tuner(run):
    r = run.results
    if r["tuning"]["rc"] != 0:
        return POOR, f"the tuning (2,0) failed: {short(r['tuning']['last'])}"
    s = r["sweep"]
    if s["rc"] == 0:
        return BAD, f"exit 0: the (2,0) tuning's summary.json used as (1,1) gains ({_runs(run)})"
    if s["traceback"] or not re.search(OTHER, s["last"], re.I):
        return POOR, f"exit {s['rc']}: {short(s['last'])}"
    return GOOD, f"exit {s['rc']}: {short(s['last'])}"


def _own_gains(run):
    if run.timed_out or run.rc != 0:
        return POOR, f"exit {run.rc}: {short(run.last_line)}"
    return GOOD, f"exit 0: {_runs(run)}"


_G20 = specs.gains_json("(2,0)", "velocity", "static", [[1.5], [1.5]])
_G11 = specs.gains_json("(1,1)", "velocity", "static", [[1.5], [1.5]])
_TORQUE = specs.gains_json("(2,0)", "torque", "static", [[1.0, 2.0], [1.0, 2.0]])
_DYN11 = specs.gains_json("(1,1)", "velocity", "dynamic", [[1.0, 2.0], [1.0, 2.0]])
_BARE = json.dumps({"kind": "wmrjax.gains", "coefficients": [[1.5], [1.5]]})
_SWEEP11 = ("-m", "wmrjax", "sweep", "s.toml", "--out", "out")


def _ran(run):
    """Accepted: gains of another robot, level or law were used."""
    return BAD, f"exit 0: gains of another robot, level or law used ({_runs(run)})"


GAINS_CASES = [
    Case(
        "gains-file-other-robot",
        CAT,
        "a static (1,1) sweep with [gains] file = a static (2,0) gains.json of the same shape",
        cli_refuses(OTHER, accepted=_ran),
        argv=_SWEEP11,
        files={"s.toml": STATIC11.replace("GAINS", "g.json"), "g.json": _G20},
        issue=True,
        timeout=150,
    ),
    Case(
        "gains-option-other-robot",
        CAT,
        "a static (1,1) sweep with --compare-gains g.json of a static (2,0) robot",
        cli_refuses(OTHER, accepted=_ran),
        argv=(*_SWEEP11, "--compare-gains", "g.json"),
        files={"s.toml": STATIC11.replace("GAINS", "own.json"), "own.json": _G11, "g.json": _G20},
        timeout=150,
    ),
    Case(
        "gains-file-other-level-and-law",
        CAT,
        "a dynamic (2,0) velocity sweep with [gains] file = static torque-level (2,0) gains of the same shape (2, 2)",
        cli_refuses(OTHER, accepted=_ran),
        argv=_SWEEP11,
        files={"s.toml": specs.sweep(1.0, [("poles = 1.0", 'file = "g.json"')]), "g.json": _TORQUE},
        issue=True,
        timeout=150,
    ),
    Case(
        "gains-file-own-robot",
        CAT,
        "a static (1,1) sweep with [gains] file = (1,1) gains (control: runs)",
        _own_gains,
        argv=_SWEEP11,
        files={"s.toml": STATIC11.replace("GAINS", "g.json"), "g.json": _G11},
        timeout=150,
    ),
    Case(
        "gains-file-without-robot",
        CAT,
        "a static (1,1) sweep with a gains file that does not say its robot",
        cli_refuses(r"robot|level|say", accepted=POOR),
        argv=_SWEEP11,
        files={"s.toml": STATIC11.replace("GAINS", "g.json"), "g.json": _BARE},
        timeout=150,
        note="accepted is POOR, not BAD: nothing says these gains are another robot's",
    ),
    Case(
        "gains-summary-other-robot",
        CAT,
        "a static (1,1) sweep with [gains] file = the summary.json of a static (2,0) tuning (wmrjax tune, real run)",
        _from_tuner,
        code=FROM_TUNER,
        prelude="none",
        files={"tune20.toml": TUNE20, "s.toml": STATIC11.replace("GAINS", "t/summary.json")},
        issue=True,
        timeout=200,
    ),
    Case(
        "gains-summary-own-robot",
        CAT,
        "a static (1,1) sweep with [gains] file = the summary.json of a "
        "static (1,1) tuning whose problem leaves the level to its default (control: accepted)",
        _own_summary,
        code=FROM_TUNER.replace("tune20", "tune11"),
        prelude="none",
        files={"tune11.toml": TUNE11, "s.toml": STATIC11.replace("GAINS", "t/summary.json")},
        timeout=200,
    ),
    Case(
        "certify-gains-other-robot",
        CAT,
        "wmrjax certify (the (2,0) problem) --gains g.json of a dynamic (1,1) robot, same shape",
        cli_refuses(OTHER, accepted=_ran),
        argv=("-m", "wmrjax", "certify", "--gains", "g.json", "--t-final", "10", *specs.CERTIFY_SMALL, "--out", "out"),
        files={"g.json": _DYN11},
        timeout=180,
    ),
]


# --- complex numbers -------------------------------------------------------------------------------

COMPLEX = {
    "from-samples": (
        "ts, xy, _ = circle_samples(0.0, 6.0, 13)\narm()\nref = R.from_samples(ts, xy + 0.5j)\n"
        "emit(value=[float(v) for v in ref.position(1.0)])",
        True,
    ),
    "from-waypoints": (
        "ts, xy, _ = circle_samples(0.0, 6.0, 13)\narm()\nref = R.from_waypoints(xy * (1 + 0.5j))\n"
        "emit(value=[float(v) for v in ref.position(1.0)])",
        False,
    ),
    "gains-coefficients": (
        "ctrl, p, z0 = loop61()\narm()\ng = w.Gains(jnp.asarray([[1.0 + 0.5j, 2.0], [1.0, 2.0]]))\n"
        "q = ctrl.params(R.paper_62(), gains=g, geometry=w.Geometry(e=0.0))\n"
        "tr = w.simulate(ctrl, z0, q, dt=0.01, n_steps=100)\n"
        "emit(gains=str(q.gains.coeffs.dtype), state=str(tr.final_state.dtype), "
        "failed=bool(tr.diagnostics.failed))",
        False,
    ),
    "initial-zeta": (
        "ctrl, p, z0 = loop61()\nzeta = ctrl.reference_jet(0.0, p)[:2]\narm()\n"
        "z = ctrl.initial_state(zeta + 0.1j, p)\nemit(value=str(z.dtype))",
        False,
    ),
}


def _complex_accepted(run):
    warned = [x for x in run.warnings if "omplex" in x["category"] + x["message"] or "imaginary" in x["message"]]
    if warned:
        return (
            POOR,
            f"accepted with only a {warned[0]['category']}: {short(warned[0]['message'], 100)}; got {run.results}",
        )
    return BAD, f"accepted silently: {run.results}"


def _complex_cases() -> list[Case]:
    return [
        Case(
            f"complex-{cid}",
            CAT,
            f"a complex array given to {cid.replace('-', ' ')}",
            refuses(r"real|complex", accepted=_complex_accepted),
            code=code,
            issue=issue,
        )
        for cid, (code, issue) in COMPLEX.items()
    ]


def cases() -> list[Case]:
    """The inputs cases."""
    return _column_cases() + _list_cases() + GAINS_CASES + _complex_cases()
