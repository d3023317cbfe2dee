"""The sections of a problem's controller: ``[controller]``, ``[geometry]``, ``[plant]``,
``[initial]`` and ``[simulation]``, read into one :class:`wmrjax.problem.Setting` per case, robot
type and level (with ``[reference]`` and ``[gains]``: :mod:`wmrjax.problem.reference`,
:mod:`wmrjax.problem.gains_file`).
"""

from __future__ import annotations

from pathlib import Path

import jax
import numpy as np

from wmrjax import controllers, robots
from wmrjax.controllers import dynamic_linearization
from wmrjax.controllers.law import Level, Task
from wmrjax.controllers.placement import Space, initial_keys
from wmrjax.problem.gains_file import gains_axis
from wmrjax.problem.reference import reference_axis
from wmrjax.problem.schema import (
    GEOMETRY_KEYS,
    Law,
    ProblemError,
    axis_values,
    check_keys,
    check_table_fits,
    choice,
    integer,
    is_number,
    positive,
    product,
)
from wmrjax.problem.setting import Axis, Setting
from wmrjax.robots import Geometry, robot_type


def controller(law, kind: str, level, task):
    """The controller of a law, robot type, level and task (ProblemError if there is none)."""
    try:
        if Law(law) == Law.DYNAMIC:
            return dynamic_linearization(kind, str(level))
        return controllers.controller(kind, level=str(level), task=str(task))
    except ValueError as err:
        raise ProblemError(f"[controller]: {err}") from None


def settings_of(data: dict, base: Path, case) -> list:
    """One :class:`Setting` per robot type and level of one case's sections ``data``, every key
    validated; ``base`` resolves its file names, ``case`` is its name (None: no ``[[case]]``)."""
    for s in ("controller", "reference", "initial", "simulation"):
        if s not in data:
            raise ProblemError(f"missing section [{s}]")
    c = data["controller"]
    check_keys("controller", c, ("law", "robot", "level", "task"), ("law", "robot"))
    law = choice("controller", "law", c["law"], Law)
    robots_ = c["robot"] if isinstance(c["robot"], list) else [c["robot"]]
    levels = c.get("level", Level.VELOCITY)
    levels = levels if isinstance(levels, list) else [levels]
    if not robots_ or not levels:
        raise ProblemError("[controller] robot and level must not be empty lists")
    levels = [choice("controller", "level", lv, Level) for lv in levels]
    kinds = []
    for r in robots_:
        try:
            kinds.append(robot_type(r).name)
        except (ValueError, TypeError) as err:
            raise ProblemError(f"[controller] robot: {err}") from None
    for what, values in (("robot", kinds), ("level", levels)):
        if len(set(values)) != len(values):
            raise ProblemError(f"[controller] {what}: listed twice in {[str(v) for v in values]}")
    task = c.get("task", Task.POSTURE if law == Law.DYNAMIC else Task.POINT)
    task = choice("controller", "task", task, Task)
    if law == Law.DYNAMIC:
        if task != Task.POSTURE:
            raise ProblemError(f'[controller] task: dynamic laws track a posture (task = "posture"), got {task!r}')
        bad = [k for k in kinds if k not in controllers.TABLE4]
        if bad:
            raise ProblemError(
                f"[controller] robot: no dynamic linearizing law (Table 4) for type(s) {bad}; "
                f"expected some of {sorted(controllers.TABLE4)}"
            )
    t_final, dt, n_steps = simulation(data["simulation"])
    space = choice(
        "initial",
        "space",
        data["initial"].get("space", "output" if law == Law.DYNAMIC else "physical")
        if isinstance(data["initial"], dict)
        else None,
        Space,
    )
    if space == Space.OUTPUT and law != Law.DYNAMIC:
        raise ProblemError(
            '[initial] space = "output" (errors in the output jet) needs a dynamic law; '
            'static laws take space = "physical"'
        )
    return [
        _setting(controller(law, kind, level, task), data, base, case, law, task, space, t_final, dt, n_steps)
        for kind in kinds
        for level in levels
    ]


# more RK4 steps than this in one run is an overflow of t_final / dt, not a horizon
MAX_STEPS = 1e12


def simulation(sim) -> tuple:
    """``(t_final, dt, n_steps)`` of a ``[simulation]`` section (its other keys are the jobs')."""
    check_keys("simulation", sim, ("t_final", "dt", "block", "error_tol", "distance_every"), ("t_final", "dt"))
    t_final = positive("simulation", "t_final", sim["t_final"])
    dt = positive("simulation", "dt", sim["dt"])
    if not t_final / dt <= MAX_STEPS:  # 1e308 / 0.01 is inf: no whole number of steps, no run
        raise ProblemError(
            f"[simulation] t_final / dt = {t_final} s / {dt} s is {t_final / dt:.3g} steps, more than "
            f"{MAX_STEPS:.0e}: shorten t_final or raise dt"
        )
    n_steps = int(round(t_final / dt))
    if n_steps < 1 or abs(n_steps * dt - t_final) > 1e-9 * max(1.0, t_final):
        raise ProblemError(f"[simulation] t_final = {t_final} s is not a whole number of steps dt = {dt} s")
    return t_final, dt, n_steps


def _reference_error(ref, j: int, g, kind: str, level: str, err) -> ProblemError:
    """The error of the ``j``-th reference of a problem, unusable with geometry ``g``."""
    return ProblemError(
        f"[reference] {ref.name} (#{j}) with geometry {g._asdict()} for type {kind}, {level} level: {err}"
    )


def _setting(ctrl, data, base, case, law, task, space, t_final, dt, n_steps) -> Setting:
    """The :class:`Setting` of one controller, every axis read and every reference and gain checked."""
    kind, level = ctrl.robot.name, ctrl.level
    geometry = _geometry_axis(data.get("geometry", {}), ctrl)
    plant, period, noise_std, noise_seed = _plant_axis(data.get("plant"), ctrl, dt, t_final)
    reference, refs = reference_axis(data["reference"], base, law, kind, ctrl.path_order, horizon=t_final)
    gains = gains_axis(data.get("gains", {}), ctrl, base)
    initial = initial_axis(data["initial"], ctrl, space)
    geo = geometry.payload
    # every (geometry, reference) pair over the horizon, and every gain against dt
    n_pairs = geometry.size * len(refs)
    if n_pairs > 4096:
        raise ProblemError(
            f"type {kind}: {n_pairs} (geometry, reference) pairs to check; at most 4096 "
            "(sweep fewer geometries or references per file)"
        )
    branch = np.ones(len(refs), int)
    for i in range(geometry.size):
        g = Geometry(**{k: float(geo[k][i]) for k in GEOMETRY_KEYS})
        params, errors = [None] * len(refs), [None] * len(refs)
        for j, ref in enumerate(refs):
            try:
                params[j] = ctrl.params(ref, poles=1.0, geometry=g)
            except ValueError as err:
                errors[j] = str(err)
        # every usable reference of the group in one batched evaluation (one program, not one
        # call each); the first unusable reference is named, whichever check refused it
        ok = [j for j, p in enumerate(params) if p is not None]
        for j, err in zip(ok, ctrl.reference_errors([params[j] for j in ok], t_final)):
            errors[j] = err
        for j, err in enumerate(errors):
            if err is not None:
                raise _reference_error(refs[j], j, g, kind, level, err)
            branch[j] = ctrl.reference_branch(params[j])
    g0 = Geometry(**{k: float(geo[k][0]) for k in GEOMETRY_KEYS})
    step = dt if period is None else period
    for i in range(gains.size):
        gi = jax.tree_util.tree_map(lambda x: x[i], gains.payload["gains"])
        try:
            ctrl.check_step(ctrl.params(refs[0], geometry=g0, gains=gi), step)
        except ValueError as err:
            what = "[plant] control_period" if period is not None else "[simulation] dt"
            raise ProblemError(f"{what} with gains #{i} for type {kind}, {level} level: {err}") from None
    return Setting(
        case,
        law,
        task,
        space,
        ctrl,
        [geometry, plant, reference, gains, initial],
        refs,
        branch,
        "plant" in data,
        period,
        noise_std,
        noise_seed,
        t_final,
        dt,
        n_steps,
        data,
    )


def _geometry_axis(gs, ctrl) -> Axis:
    """The geometries of a ``[geometry]`` section (lists are axes), each checked for the robot type."""
    kind = ctrl.robot.name
    check_keys("geometry", gs, GEOMETRY_KEYS)
    base = ctrl.row.default_geometry
    geo = {
        k: axis_values("geometry", k, gs[k]) if k in gs else np.array([float(getattr(base, k))]) for k in GEOMETRY_KEYS
    }
    cols = product(geo)
    for i in range(len(cols["L"])):
        g = Geometry(**{k: float(cols[k][i]) for k in GEOMETRY_KEYS})
        try:
            robots.check_geometry(g)
            controllers.law.check_requirements(ctrl.row.requires, g, f"type {kind}")
        except ValueError as err:
            raise ProblemError(f"[geometry] for type {kind}: {err}") from None
    return Axis("geometry", {f"geometry_{k}": v for k, v in cols.items()}, dict(cols))


PLANT_KEYS = ("input_limit", "input_scale", "geometry_scale", "control_period", "noise_std", "noise_seed")


def _input_scales(v, nu: int) -> np.ndarray:
    """(n, nu) input scales of ``[plant] input_scale``: one factor for every input (a number, a
    list of numbers or a ``{min, max, num}`` table: an axis), or one factor per input (a list
    of nu numbers in a list: ``[[0.97, 1.02]]``; several such lists: an axis)."""
    if isinstance(v, list) and v and all(isinstance(x, list) for x in v):
        return axis_values("plant", "input_scale", v, vector=nu, positive=True)
    return np.repeat(axis_values("plant", "input_scale", v, positive=True)[:, None], nu, axis=1)


def _plant_axis(ps, ctrl, dt, t_final):
    """``(axis, control_period, noise_std, noise_seed)`` of a ``[plant]`` section (None: none)."""
    nu, nX = ctrl.robot.n_input, ctrl.robot.n_state
    ps = {} if ps is None else ps
    check_keys("plant", ps, PLANT_KEYS)
    lim = (
        axis_values("plant", "input_limit", ps["input_limit"], vector=nu, positive=True, allow_inf=True)
        if "input_limit" in ps
        else np.full((1, nu), np.inf)
    )
    pv = {
        "limit": lim,
        "input_scale": _input_scales(ps.get("input_scale", 1.0), nu),
        "geometry_scale": axis_values("plant", "geometry_scale", ps.get("geometry_scale", 1.0), positive=True),
    }
    cols = product(pv)
    columns = {f"plant_input_limit_{i + 1}": cols["limit"][:, i] for i in range(nu)}
    columns |= {f"plant_input_scale_{i + 1}": cols["input_scale"][:, i] for i in range(nu)}
    columns["plant_geometry_scale"] = cols["geometry_scale"]
    period = None
    if "control_period" in ps:
        period = positive("plant", "control_period", ps["control_period"])
        k = period / dt
        if abs(k - round(k)) > 1e-9 * k or round(k) < 1:
            raise ProblemError(f"[plant] control_period = {period} s is not a whole number of steps dt = {dt} s")
        if abs(t_final / period - round(t_final / period)) > 1e-9 * (t_final / period):
            raise ProblemError(f"[plant] control_period = {period} s does not divide t_final = {t_final} s")
        if ctrl.level == Level.TORQUE and ctrl.law.extension.n_comp == 0:
            raise ProblemError(
                '[plant] control_period: a sampled-data loop at torque level needs a dynamic law (law = "dynamic")'
            )
    noise = ps.get("noise_std", [])
    if not (isinstance(noise, list) and len(noise) <= nX and all(is_number(v) and v >= 0 for v in noise)):
        raise ProblemError(
            f"[plant] noise_std: expected a list of at most {nX} numbers >= 0 (std of x, y [m], "
            f"theta [rad] and steering angles [rad] as measured), got {noise!r}"
        )
    if any(noise) and period is None:
        raise ProblemError("[plant] noise_std: measurement noise needs a digital controller (control_period [s])")
    seed = integer("plant", "noise_seed", ps.get("noise_seed", 0), 0, 2**32 - 1)
    return Axis("plant", columns, cols), period, tuple(float(v) for v in noise), seed


def initial_axis(ins, ctrl, space) -> Axis:
    """The initial errors of an ``[initial]`` section: a grid (values, lists or ``{min, max,
    num}`` per key), random draws (``random = { count, seed }`` with ``{ low, high }`` ranges)
    or ``points`` (a list of error vectors in :func:`initial_keys` order)."""
    keys = initial_keys(ctrl, space)
    check_keys("initial", ins, ("space", "random", "points") + keys)
    if "points" in ins:
        return _points(ins, keys)
    rnd = ins.get("random")
    if rnd is not None:
        errs = _random_errors(ins, rnd, keys)
    else:
        for k in keys:
            if isinstance(ins.get(k), dict) and set(ins[k]) == {"low", "high"}:
                raise ProblemError(f"[initial] {k}: a {{ low, high }} range needs random = {{ count, seed }}")
        errs = product({k: axis_values("initial", k, ins.get(k, 0.0)) for k in keys})
    if space == Space.OUTPUT and ctrl.relative_degree < 2 and any(np.any(errs[k] != 0) for k in ("vx", "vy")):
        raise ProblemError("[initial] vx, vy: the output jet has no velocity row at relative degree 1")
    cols = {f"initial_error_{k}": v for k, v in errs.items()}
    return Axis("initial", cols, {"initial": np.stack([errs[k] for k in keys], axis=1)}, random=rnd is not None)


def _points(ins, keys) -> Axis:
    pts = ins["points"]
    other = [k for k in ins if k not in ("space", "points")]
    if other:
        raise ProblemError(f"[initial] points: a list of error vectors excludes {other}")
    if not (isinstance(pts, list) and pts and all(isinstance(p, list) and len(p) == len(keys) for p in pts)):
        raise ProblemError(f"[initial] points: expected a list of error vectors ({', '.join(keys)}), got {pts!r}")
    arr = np.stack([axis_values("initial", "points", p, vector=len(keys))[0] for p in pts])
    cols = {f"initial_error_{k}": arr[:, i] for i, k in enumerate(keys)}
    return Axis("initial", cols, {"initial": arr})


def _random_errors(ins, rnd, keys) -> dict:
    check_keys("initial.random", rnd, ("count", "seed"), ("count",))
    count = integer("initial.random", "count", rnd["count"], 1)
    check_table_fits("[initial] random", count, len(keys), "count")
    rng = np.random.default_rng(integer("initial.random", "seed", rnd.get("seed", 0), 0))
    errs = {}
    for k in keys:  # every key drawn (fixed order), so a key's values do not depend on the others
        v = ins.get(k, 0.0)
        lo, hi = initial_box(ins, (k,))[k]
        if isinstance(v, dict):
            errs[k] = rng.uniform(lo, hi, count)
        else:
            rng.uniform(0.0, 1.0, count)
            errs[k] = np.full(count, lo)
    return errs


def initial_box(ins, keys) -> dict:
    """The range of each key: key -> (low, high) of the initial errors' distribution: a ``{ low, high }`` range or a
    fixed number (low = high)."""
    out = {}
    for k in keys:
        v = ins.get(k, 0.0)
        if isinstance(v, dict):
            if (
                set(v) != {"low", "high"}
                or not (is_number(v["low"]) and is_number(v["high"]))
                or not v["high"] >= v["low"]
            ):
                raise ProblemError(f"[initial] {k}: a random range is {{ low = a, high = b }} with b >= a, got {v!r}")
            out[k] = (float(v["low"]), float(v["high"]))
        elif is_number(v):
            out[k] = (float(v), float(v))
        else:
            raise ProblemError(
                f"[initial] {k}: with random draws, expected a number or {{ low = a, high = b }}, got {v!r}"
            )
    return out
