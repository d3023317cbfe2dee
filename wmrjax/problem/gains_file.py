"""The ``[gains]`` section (poles, damping factors, Hurwitz coefficients, a schedule, or tuned-gains
files; lists are an axis) and the tuned-gains file format that ``wmrjax tune`` writes and a
problem's ``[gains] file`` reads.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import jax
import numpy as np

from wmrjax.controllers.law import Level
from wmrjax.gains import Gains, GainSchedule
from wmrjax.problem.schema import ProblemError, axis_values, check_keys, product, read_text
from wmrjax.problem.setting import Axis

GAIN_FILE_KIND = "wmrjax.gains"
GAIN_KEYS = ("poles", "omega", "zeta", "lam", "coefficients", "schedule", "file", "source_file")


def gains_axis(gs, ctrl, base: Path) -> Axis:
    """The gains of a ``[gains]`` section: poles, damping factors (omega, zeta, lam), Hurwitz
    coefficients, a schedule, or tuned-gains files; lists are an axis."""
    check_keys("gains", gs, GAIN_KEYS)
    m, r = ctrl.m, ctrl.relative_degree
    forms = [k for k in ("poles", "omega", "coefficients", "schedule", "file") if k in gs]
    if "zeta" in gs and "omega" not in gs:
        forms.append("zeta")
    if len(forms) > 1:
        raise ProblemError(
            f"[gains]: give one of poles, omega and zeta (lam), coefficients, schedule or file; got {forms}"
        )
    if "file" in gs:
        files = gs["file"] if isinstance(gs["file"], list) else [gs["file"]]
        if not files or not all(isinstance(f, str) for f in files):
            raise ProblemError(
                f"[gains] file: expected a path, or a list of paths (an axis), of tuned-gains files; got {gs['file']!r}"
            )
        if len(set(files)) != len(files):
            raise ProblemError(f"[gains] file: a file listed twice in {files}")
        values = [read_gains_file(base / f, ctrl).gains for f in files]
        cols = {"gains_file": np.array(files)}
    elif "coefficients" in gs:
        values = [_checked(ctrl, _gains_from_coefficients(gs["coefficients"], m, r), "coefficients")]
        cols = {"gains_index": np.zeros(1)}
    elif "schedule" in gs:
        values = [_schedule(gs["schedule"], ctrl)]
        cols = {"gains_index": np.zeros(1)}
    elif "omega" in gs or "zeta" in gs:
        values, cols = _damping(gs, ctrl)
    else:
        if "lam" in gs:
            raise ProblemError("[gains] lam: only with omega and zeta")
        poles = axis_values("gains", "poles", gs.get("poles", 1.0), positive=True)
        values = [Gains.from_poles(np.full((m, r), p)) for p in poles]
        cols = {"gains_poles": poles}
    kinds = {type(v).__name__ for v in values}
    if len(kinds) > 1:
        raise ProblemError(
            f"[gains] file: constant gains and gain schedules in one axis ({sorted(kinds)}); use one kind per case"
        )
    stacked = jax.tree_util.tree_map(lambda *xs: np.stack([np.asarray(x) for x in xs]), *values)
    return Axis("gains", cols, {"gains": stacked})


def _checked(ctrl, gains, where):
    try:
        return gains.check(ctrl.m, ctrl.relative_degree)
    except ValueError as err:
        raise ProblemError(f"[gains] {where}: {err}") from None


def _gains_from_coefficients(v, m, r):
    a = np.asarray(v, float) if isinstance(v, list) else None
    if a is None or a.shape not in ((m, r), (r,)) or not np.all(np.isfinite(a)):
        raise ProblemError(
            f"[gains] coefficients: expected {r} Hurwitz coefficients k_0 .. k_{r - 1} per output, "
            f"shape ({m}, {r}) or ({r},), got {v!r}"
        )
    return Gains(np.broadcast_to(a, (m, r)).copy())


def _damping(gs, ctrl):
    m, r = ctrl.m, ctrl.relative_degree
    if not ("omega" in gs and "zeta" in gs):
        raise ProblemError("[gains]: give either poles, or omega and zeta (and lam for an odd relative degree)")
    vals = {k: axis_values("gains", k, gs[k], positive=True) for k in ("omega", "zeta")}
    if r % 2:
        vals["lam"] = axis_values("gains", "lam", gs.get("lam", 1.0), positive=True)
    elif "lam" in gs:
        raise ProblemError(f"[gains] lam: only for an odd relative degree; this controller's is {r}")
    if r < 2:
        raise ProblemError(
            f"[gains] omega, zeta: second-order factors need a relative degree >= 2; this controller's "
            f"is {r} (give poles)"
        )
    grid = product(vals)
    values = []
    for i in range(len(grid["omega"])):
        om = np.full((m, r // 2), grid["omega"][i])
        ze = np.full((m, r // 2), grid["zeta"][i])
        lam = np.full((m,), grid["lam"][i]) if r % 2 else None
        values.append(Gains.from_damping(om, ze, lam, m=m))
    return values, {f"gains_{k}": v for k, v in grid.items()}


def _schedule(s, ctrl):
    """A :class:`wmrjax.GainSchedule` from ``{ knots = [...], omega = ..., zeta = ..., lam = ... }``
    (values per knot, output and factor: (K, m, r // 2); lam (K, m) for an odd r)."""
    check_keys("gains.schedule", s, ("knots", "omega", "zeta", "lam"), ("knots", "omega", "zeta"))
    try:
        lam = None if "lam" not in s else np.asarray(s["lam"], float)
        return GainSchedule.from_damping(
            np.asarray(s["knots"], float), np.asarray(s["omega"], float), np.asarray(s["zeta"], float), lam
        ).check(ctrl.m, ctrl.relative_degree)
    except (ValueError, TypeError) as err:
        raise ProblemError(f"[gains] schedule: {err}") from None


@dataclasses.dataclass(frozen=True)
class GainsFile:
    """A tuned-gains file: the gains and the controller they were tuned for."""

    gains: Any
    robot: str | None
    level: str | None
    law: str | None

    def to_problem(self) -> dict:
        """The ``[gains]`` section that gives these gains inline."""
        if getattr(self.gains, "time_varying", False):
            g = self.gains
            return {
                "schedule": {
                    "knots": np.asarray(g.times).tolist(),
                    "omega": np.asarray(g.omega).tolist(),
                    "zeta": np.asarray(g.zeta).tolist(),
                    **({"lam": np.asarray(g.lam).tolist()} if g.lam is not None else {}),
                }
            }
        return {"coefficients": jax.tree_util.tree_map(lambda x: np.asarray(x).tolist(), self.gains.coeffs)}


def gains_owner(ctrl) -> dict:
    """Whose gains a file holds, as gains files and tuning summaries say it: ``robot``, ``level``
    and ``law`` (``"dynamic"`` or ``"static"``) of ``ctrl``."""
    return {
        "robot": ctrl.robot.name,
        "level": str(ctrl.level),
        "law": "dynamic" if ctrl.law.extension.n_comp else "static",
    }


def gains_file_dict(gains, ctrl) -> dict:
    """The JSON of a tuned-gains file for ``gains`` (:class:`wmrjax.Gains` or a schedule) of ``ctrl``."""
    body = GainsFile(gains, None, None, None).to_problem()
    return {
        "kind": GAIN_FILE_KIND,
        **gains_owner(ctrl),
        **body,
        "poles_re_im": [[[float(p.real), float(p.imag)] for p in row] for row in np.atleast_2d(gains.poles())]
        if not getattr(gains, "time_varying", False)
        else None,
    }


def _summary_controller(data: dict) -> tuple:
    """``(robot, level, law)`` a tuning summary says it tuned (None where it does not): its own
    keys, else its resolved problem's controller, whose level defaults as a problem file's does
    (a summary of a problem that left the level out was refused as saying nothing), else the
    older summaries' config."""
    if isinstance(data.get("robot"), str) and isinstance(data.get("level"), str):
        return data["robot"], data["level"], data.get("law")
    prob = data.get("problem") if isinstance(data.get("problem"), dict) else {}
    if isinstance(prob.get("controller"), dict):
        cfg = prob["controller"]
        level = cfg.get("level", str(Level.VELOCITY) if isinstance(cfg.get("robot"), str) else None)
        return cfg.get("robot"), level, cfg.get("law")
    cfg = data.get("config") if isinstance(data.get("config"), dict) else {}
    return cfg.get("robot"), cfg.get("level"), cfg.get("law")


def read_gains_file(path: Path, ctrl=None) -> GainsFile:
    """A tuned-gains file: ``gains.json`` of ``wmrjax tune`` (kind ``wmrjax.gains``), or a
    tuning ``summary.json`` (its ``tuned_gains``). With ``ctrl``: refused unless tuned for this
    robot type and level, and of its shape."""
    text = read_text(path, "[gains] file")
    where = f"[gains] file {str(path)!r}"
    try:
        data = json.loads(text)
    except ValueError as err:
        raise ProblemError(f"{where}: not JSON ({err})") from None
    if not isinstance(data, dict):
        raise ProblemError(f"{where}: expected a JSON object, got {type(data).__name__}")
    if data.get("kind") == GAIN_FILE_KIND:
        body = {k: data[k] for k in ("coefficients", "schedule") if k in data}
        robot, level, law = data.get("robot"), data.get("level"), data.get("law")
    elif isinstance(data.get("tuned_gains"), dict) and "coefficients_k0_to_kr-1" in data["tuned_gains"]:
        body = {"coefficients": data["tuned_gains"]["coefficients_k0_to_kr-1"]}
        robot, level, law = _summary_controller(data)
    else:
        raise ProblemError(
            f'{where}: neither a gains file (kind = "{GAIN_FILE_KIND}") nor a tuning summary '
            "(tuned_gains.coefficients_k0_to_kr-1)"
        )
    if len(body) != 1:
        raise ProblemError(f"{where}: needs one of coefficients or schedule")
    if ctrl is not None:
        # gains of the same shape fit other types and levels (e.g. (2,0) and (1,1) at velocity
        # level); on another robot they are not the tuned gains, so the file must say whose they are
        if not (isinstance(robot, str) and isinstance(level, str)):
            raise ProblemError(
                f"{where}: does not say which robot type and level the gains were tuned for "
                f'(keys robot and level, e.g. robot = "{ctrl.robot.name}", level = "{ctrl.level}")'
            )
        law_here = "dynamic" if ctrl.law.extension.n_comp else "static"
        if robot != ctrl.robot.name or level != str(ctrl.level) or (isinstance(law, str) and law != law_here):
            raise ProblemError(
                f"{where}: gains tuned for type {robot} at {level} level"
                + (f" ({law} law)" if isinstance(law, str) else "")
                + f", this controller is type {ctrl.robot.name} at {ctrl.level} level ({law_here} law)"
            )
    try:
        if "schedule" in body:
            sch = body["schedule"]
            check_keys("gains.schedule", sch, ("knots", "omega", "zeta", "lam"), ("knots", "omega", "zeta"))
            gains = GainSchedule.from_damping(
                np.asarray(sch["knots"], float),
                np.asarray(sch["omega"], float),
                np.asarray(sch["zeta"], float),
                None if "lam" not in sch else np.asarray(sch["lam"], float),
            )
        else:
            gains = Gains(np.asarray(body["coefficients"], float))
        if ctrl is not None:
            gains = gains.check(ctrl.m, ctrl.relative_degree)
    except (ValueError, TypeError) as err:
        raise ProblemError(f"{where}: {err}") from None
    return GainsFile(gains, robot, level, law)
