"""Silently wrong answers: certificates on long horizons, sampled paths used past their samples,
a traced step that is not > 0, duplicated inputs, gains of another robot, complex numbers."""

from __future__ import annotations

import json
import re

from tests.probe import specs
from tests.probe.harness import BAD, GOOD, POOR, Case
from tests.probe.oracles import answer, cli_refuses, hang, refuses, short

CAT = "wrong_answer"
SPAN = r"sample|extrapolat|span|\[0, 4\]|\[5, 25\]|domain"


# --- certificates that must not collapse ---------------------------------------------------------

EXACT_MAP = """
ctrl, p, _ = loop61(poles=POLES)
ref = {b: float(C.exact_map_radius(ctrl, p, t_final=20.0, eps=0.01, basis=b).radius) for b in ("full", "position")}
arm()
got = {b: float(C.exact_map_radius(ctrl, p, t_final=T, eps=0.01, basis=b).radius) for b in ("full", "position")}
emit(ref=ref, got=got)
"""


def _same_radius(r):
    ref, got = r["ref"], r["got"]
    ok = all(abs(got[b] - ref[b]) <= 1e-3 * ref[b] for b in ref)
    return (
        ok,
        f"radius at T (full, position): {got['full']:.6g}, {got['position']:.6g}; at 20 s: {ref['full']:.6g}, {ref['position']:.6g}",
    )


def _exact_map(poles: float, t: float, issue: bool) -> Case:
    return Case(
        f"exact-map-radius-poles{poles:g}-T{t:g}",
        CAT,
        f"certify.exact_map_radius of the 6.1 loop, poles at -{poles:g}, over {t:g} s (must equal the 20 s radius: "
        "the minimum is reached early)",
        answer(_same_radius),
        code=EXACT_MAP.replace("POLES", repr(poles)).replace("=T", f"={t!r}"),
        timeout=150,
        issue=issue,
    )


LEMMA2_VS_MAP = """
ctrl, p, _ = loop61(poles=1.0)
l2 = C.lemma2(ctrl, p, t_final=100.0, eps=0.01)
em = C.exact_map_radius(ctrl, p, t_final=100.0, eps=0.01)
emit(lemma2_exact_norm=float(l2.exact_norm.radius), exact_map=float(em.radius))
"""


def _map_above_lemma2(r):
    ok = r["exact_map"] >= r["lemma2_exact_norm"] * (1 - 1e-6)
    return ok, f"exact-map radius {r['exact_map']:.6g} against Lemma 2's exact-norm radius {r['lemma2_exact_norm']:.6g}"


def _certify_cli(run):
    """The certification's exact-map radius (position slice) against its own empirical radius
    (rollouts): within 2 %, or an exit 1 whose alarm names the disagreement."""
    if run.timed_out:
        return hang(run)
    try:
        s = json.loads(run.file("out/summary.json").read_text())
    except (OSError, ValueError):
        return POOR, f"exit {run.rc}, no summary.json: {short(run.last_line)}"
    em, emp = s.get("radius_exact_map_position_slice"), s.get("empirical_radius_position_slice")
    alarms = s.get("alarms") or []
    said = f"exact map (position) {em:.4g}, empirical {emp:.4g}, exact map (full) {s.get('radius_exact_map'):.4g}"
    agree = em is not None and emp is not None and abs(em - emp) <= 0.02 * emp
    if agree and run.rc == 0:
        return GOOD, f"exit 0: {said}"
    if not agree and run.rc == 1 and alarms:
        return GOOD, f"exit 1 with alarms: {said}; {short(alarms[0], 120)}"
    if not agree and run.rc == 0:
        return BAD, f"exit 0: {said}, no alarm"
    return POOR, f"exit {run.rc}: {said}; alarms {short(alarms, 150)}"


def _certificates() -> list[Case]:
    cases = [_exact_map(2.0, t, issue=True) for t in (35.0, 40.0, 50.0)]
    cases += [_exact_map(1.0, 100.0, True), _exact_map(5.0, 40.0, False), _exact_map(0.5, 200.0, False)]
    cases.append(_exact_map(2.0, 1000.0, False))
    cases.append(
        Case(
            "exact-map-below-lemma2-T100",
            CAT,
            "the exact-map radius of the 6.1 loop over 100 s against Lemma 2's exact-norm radius (it is the "
            "tighter one: never smaller)",
            answer(_map_above_lemma2),
            code=LEMMA2_VS_MAP,
            timeout=150,
            issue=True,
        )
    )
    cases.append(
        Case(
            "certify-cli-poles2-T40",
            CAT,
            "wmrjax certify --poles 2 --t-final 40 (small counts, no falsifier): the exact-map "
            "radius against the empirical one it reports beside it",
            _certify_cli,
            argv=("-m", "wmrjax", "certify", "--poles", "2", "--t-final", "40", *specs.CERTIFY_SMALL, "--out", "out"),
            timeout=180,
            issue=True,
            note="the issue's run compares against the falsifier (5.34); without it (time) the oracle is the "
            "empirical position-slice radius of the same run",
        )
    )
    return cases


# --- sampled paths used past their samples ---------------------------------------------------------

SAMPLED = """
ts, xy, circ = circle_samples(T0, T1, 81)
ctrl = w.dynamic_linearization("(2,0)", "velocity")
p = ctrl.params(R.from_samples(ts, xy), poles=1.0, geometry=w.Geometry())
z0 = ctrl.reference_state(START, p)
arm()
CALL
off = float(jnp.linalg.norm(p.reference.position(END) - circ.position(END)))
emit(failed=bool(jnp.asarray(tr.diagnostics.failed).reshape(-1)[-1]), reference_off_m=off)
"""


def _ran_past(run):
    """Accepted: a run flagged failed, or a warning naming the samples, is not silent."""
    r = run.results
    warned = [x["message"] for x in run.warnings if re.search(SPAN + r"|not checked", x["message"], re.I)]
    if warned:
        return GOOD, f"ran, with a warning: {short(warned[0])}"
    if r.get("failed"):
        return GOOD, "ran; the run is flagged failed"
    off = r.get("reference_off_m")
    return BAD, f"ran past the samples without a word: failed = False, the path {off:.3g} m off the sampled circle"


def _sampled(cid, desc, t0, t1, start, end, call, issue=False, note="") -> Case:
    code = (
        SAMPLED.replace("T0, T1", f"{t0!r}, {t1!r}")
        .replace("START", repr(start))
        .replace("END", repr(end))
        .replace("CALL", call)
    )
    return Case(f"samples-{cid}", CAT, desc, refuses(SPAN, accepted=_ran_past), code=code, issue=issue, note=note)


def _sampled_cases() -> list[Case]:
    sim = "tr = w.simulate(ctrl, z0, p, dt=0.01, n_steps=N, save_every=N, t0=START)"
    cases = [
        _sampled(
            "past-end",
            "circle samples on [0, 4] s, simulated to 8 s",
            0.0,
            4.0,
            0.0,
            8.0,
            sim.replace("N", "800").replace("START", "0.0"),
            True,
        ),
        _sampled(
            "before-start",
            "circle samples on [5, 25] s, simulated from t = 0",
            5.0,
            25.0,
            0.0,
            0.0,
            sim.replace("N", "500").replace("START", "0.0"),
            True,
        ),
        _sampled(
            "t0-negative",
            "circle samples on [0, 4] s, simulated from t0 = -1 s for 2 s",
            0.0,
            4.0,
            -1.0,
            -1.0,
            sim.replace("N", "200").replace("START", "-1.0"),
        ),
        _sampled(
            "jit-traced-dt",
            "circle samples on [0, 4] s, simulate under jax.jit with a traced dt = 0.02 and 400 steps (8 s)",
            0.0,
            4.0,
            0.0,
            8.0,
            "tr = jax.jit(lambda dt: w.simulate(ctrl, z0, p, dt=dt, n_steps=400, save_every=400))(0.02)",
        ),
        _sampled(
            "jit-traced-t0",
            "circle samples on [0, 4] s, simulate under jax.jit from a traced t0 = 4 s for 4 s",
            0.0,
            4.0,
            0.0,
            8.0,
            "tr = jax.jit(lambda t0: w.simulate(ctrl, z0, p, dt=0.01, n_steps=400, save_every=400, t0=t0))(4.0)",
        ),
        _sampled(
            "vmap-t0",
            "circle samples on [0, 4] s, simulate vmapped over t0 = [0, 4] s for 4 s each",
            0.0,
            4.0,
            0.0,
            8.0,
            "tr = jax.vmap(lambda t0: w.simulate(ctrl, z0, p, dt=0.01, n_steps=400, save_every=400, "
            "t0=t0))(jnp.array([0.0, 4.0]))",
        ),
    ]
    checks = [
        ("check-reference-past-end", "ctrl.check_reference(p, 8.0)", True),
        ("lemma2-past-end", "C.lemma2(ctrl, p, t_final=8.0, eps=0.01)", False),
        ("exact-map-past-end", "C.exact_map_radius(ctrl, p, t_final=8.0, eps=0.01)", False),
    ]
    for cid, call, issue in checks:
        code = SAMPLED.replace("T0, T1", "0.0, 4.0").replace("START", "0.0").replace("END", "8.0")
        code = code.replace("CALL", call).replace(
            "failed=bool(jnp.asarray(tr.diagnostics.failed).reshape(-1)[-1]), ", ""
        )
        cases.append(
            Case(f"samples-{cid}", CAT, f"circle samples on [0, 4] s: {call}", refuses(SPAN), code=code, issue=issue)
        )
    return cases


EXTRAPOLATE = """
ts, xy, circ = circle_samples(0.0, 4.0, 81)
ctrl = w.dynamic_linearization("(2,0)", "velocity")
p = ctrl.params(R.from_samples(ts, xy, extrapolate=True), poles=1.0, geometry=w.Geometry())
tr = w.simulate(ctrl, ctrl.reference_state(0.0, p), p, dt=0.01, n_steps=800, save_every=800)
emit(failed=bool(tr.diagnostics.failed))
"""

INSIDE = """
ts, xy, circ = circle_samples(0.0, 4.0, 81)
ctrl = w.dynamic_linearization("(2,0)", "velocity")
p = ctrl.params(R.from_samples(ts, xy), poles=1.0, geometry=w.Geometry())
z0 = ctrl.reference_state(0.0, p).at[0].add(0.1)
tr = w.simulate(ctrl, z0, p, dt=0.01, n_steps=400, save_every=400)
exact = w.simulate(ctrl, z0, ctrl.params(circ, poles=1.0, geometry=w.Geometry()), dt=0.01, n_steps=400, save_every=400)
emit(failed=bool(tr.diagnostics.failed), diff=float(jnp.max(jnp.abs(tr.final_state - exact.final_state))))
"""

WAYPOINTS = """
ang = np.linspace(0.0, np.pi, 40)
pts = np.stack([3 * np.cos(ang), 3 * np.sin(ang)], axis=1)
ref = R.from_waypoints(pts, speed=1.5)
ctrl = w.dynamic_linearization("(2,0)", "velocity")
p = ctrl.params(ref, poles=1.0, geometry=w.Geometry())
arm()
tr = w.simulate(ctrl, ctrl.reference_state(0.0, p), p, dt=0.01, n_steps=1200, save_every=1200)
end = float(jnp.linalg.norm(ref.position(12.0) - jnp.asarray(pts[-1])))
emit(failed=bool(tr.diagnostics.failed), reference_off_m=end)
"""

SWEEP_SAMPLES = """
from probe_driver import run, read_json
r = run("-m", "wmrjax", "sweep", "s.toml", "--out", "out")
s = read_json("out/summary.json") or {}
emit(run=r, counts=s.get("counts"))
"""


def _sweep_past(run):
    if run.timed_out:
        return hang(run)
    r = run.results["run"]
    if r["rc"] == 0:
        return BAD, f"exit 0 over 8 s on samples of [0, 4] s: counts {run.results.get('counts')}"
    if r["traceback"] or not re.search(SPAN, r["last"], re.I):
        return POOR, f"exit {r['rc']}: {short(r['last'])}"
    return GOOD, f"exit {r['rc']}: {short(r['last'])}"


def _more_sampled() -> list[Case]:
    csv = specs.circle_csv(0.0, 4.0, 81)
    return [
        Case(
            "samples-waypoints-past-end",
            CAT,
            "waypoints of a half circle (timed to 6.3 s at 1.5 m/s), simulated to 12 s",
            refuses(SPAN, accepted=_ran_past),
            code=WAYPOINTS,
        ),
        Case(
            "samples-sweep-past-end",
            CAT,
            "a sweep of circle samples on [0, 4] s (a CSV file) with t_final = 8 s",
            _sweep_past,
            code=SWEEP_SAMPLES,
            prelude="none",
            issue=True,
            timeout=150,
            files={"s.toml": specs.SAMPLES_SWEEP.replace("T_FINAL", "8.0"), "circle.csv": csv},
        ),
        Case(
            "samples-problem-past-end",
            CAT,
            "a problem file of circle samples on [0, 4] s with t_final = 8 s, loaded",
            refuses(SPAN),
            code='from wmrjax.problem import Problem\nProblem.load("s.toml")',
            files={"s.toml": specs.SAMPLES_SWEEP.replace("T_FINAL", "8.0"), "circle.csv": csv},
        ),
        Case(
            "samples-tuning-cli-past-end",
            CAT,
            "wmrjax tune --reference circle.csv (samples on [0, 4] s) --t-final 8",
            cli_refuses(SPAN),
            argv=(
                "-m",
                "wmrjax",
                "tune",
                "--reference",
                "circle.csv",
                "--t-final",
                "8",
                *specs.TUNE_SMALL,
                "--out",
                "out",
            ),
            files={"circle.csv": csv},
            timeout=180,
        ),
        Case(
            "samples-extrapolate-true",
            CAT,
            "from_samples(..., extrapolate=True) on [0, 4] s, simulated to 8 s (asked for: must run)",
            answer(lambda r: (not r["failed"], f"ran, failed = {r['failed']}")),
            code=EXTRAPOLATE,
            note="extrapolate= does not exist before #34: a TypeError there",
        ),
        Case(
            "samples-inside-span",
            CAT,
            "circle samples on [0, 4] s, simulated over [0, 4] s (control: the sampled run equals the exact circle's)",
            answer(
                lambda r: (
                    not r["failed"] and r["diff"] < 1e-6,
                    f"failed = {r['failed']}, max difference {r['diff']:.2g}",
                )
            ),
            code=INSIDE,
        ),
    ]


# --- a traced step that is not a finite number > 0 -----------------------------------------------

TRACED_DT = """
ctrl, p, z0 = loop61()
f = jax.jit(lambda dt: w.simulate(ctrl, z0, p, dt=dt, n_steps=100))
arm()
tr = f(DT)
emit(failed=bool(tr.diagnostics.failed), t_last=float(tr.t[-1]))
"""

VMAP_DT = """
ctrl, p, z0 = loop61()
arm()
tr = jax.vmap(lambda dt: w.simulate(ctrl, z0, p, dt=dt, n_steps=100))(jnp.array([0.01, -0.01]))
emit(failed=[bool(x) for x in tr.diagnostics.failed], t_last=[float(x) for x in tr.t[:, -1]])
"""


def _traced_dt(run):
    r = run.results
    if r["failed"]:
        return GOOD, f"the run failed (t[-1] = {r['t_last']})"
    return BAD, f"failed = False, t[-1] = {r['t_last']}"


def _vmap_dt(run):
    r = run.results
    if r["failed"] == [False, True]:
        return GOOD, f"the run of dt = -0.01 failed, the other did not (t[-1] = {r['t_last']})"
    return BAD, f"failed = {r['failed']}, t[-1] = {r['t_last']}"


def _dt_cases() -> list[Case]:
    cases = []
    for name, dt, issue in (
        ("negative", "-0.01", True),
        ("zero", "0.0", False),
        ("nan", "float('nan')", False),
        ("inf", "float('inf')", False),
    ):
        cases.append(
            Case(
                f"dt-{name}-under-jit",
                CAT,
                f"simulate under jax.jit with a traced dt = {dt}, 100 steps",
                refuses(r"dt", accepted=_traced_dt),
                code=TRACED_DT.replace("DT", dt),
                issue=issue,
            )
        )
    cases.append(
        Case(
            "dt-negative-under-vmap",
            CAT,
            "simulate vmapped over dt = [0.01, -0.01], 100 steps",
            refuses(r"dt", accepted=_vmap_dt),
            code=VMAP_DT,
            issue=True,
        )
    )
    cases.append(
        Case(
            "dt-negative-eager",
            CAT,
            "simulate with dt = -0.01 (control: refused eagerly)",
            refuses(r"dt must be"),
            code="ctrl, p, z0 = loop61()\narm()\nw.simulate(ctrl, z0, p, dt=-0.01, n_steps=10)",
        )
    )
    return cases


def cases() -> list[Case]:
    """Every wrong-answer case (the duplicated inputs, gains files and complex numbers follow)."""
    from tests.probe import cases_inputs

    return _certificates() + _sampled_cases() + _more_sampled() + _dt_cases() + cases_inputs.cases()
