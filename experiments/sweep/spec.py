"""The sweep file: TOML read with the standard library, validated key by key before anything
compiles, and turned into a :class:`Plan` -- groups of runs (one per robot type and level),
each the Cartesian product of five axes: geometry, plant, reference, gains, initial condition.

Every value of a swept quantity is one of:

* a number (or, for a vector such as ``input_limit``, a list of numbers): fixed;
* a list of numbers (of vectors): a grid axis;
* a table ``{ min = a, max = b, num = n }``: ``n`` evenly spaced values (``numpy.linspace``);
* in a random ``[initial]`` block, a table ``{ low = a, high = b }``: uniform draws.

The README documents the format; ``experiments/sweeps/*.toml`` are complete examples.
"""

from __future__ import annotations

import dataclasses
import hashlib
import inspect
import json
import math
import tomllib
from pathlib import Path
from typing import Any

import numpy as np

SECTIONS = ("title", "controller", "geometry", "plant", "reference", "initial", "gains", "simulation", "classify")
LAWS = ("dynamic", "static")
LEVELS = ("velocity", "torque")
FAMILIES = ("paper_62", "paper_66", "line", "circle", "figure_eight", "random_smooth", "samples")
RANDOM_OPTIONS = {"n_modes": 3, "speed": 1.0, "min_speed": 0.3, "max_omega": 1.0, "start_scale": 0.0}
GEOMETRY_KEYS = ("L", "e", "delta")


class SpecError(ValueError):
    """A sweep file that cannot run: the message names the key and the expected form."""


@dataclasses.dataclass
class Axis:
    """One axis of a group: ``n`` values, their table columns and what the rollout consumes.

    Attributes:
      name: "geometry" | "plant" | "reference" | "gains" | "initial".
      columns: column name -> (n,) values (float, or str for labels).
      payload: key -> (n, ...) arrays (or a pytree with that leading axis) for the rollout.
      random: the values are random draws (not a grid): maps do not slice along them.
    """

    name: str
    columns: dict
    payload: dict
    random: bool = False

    @property
    def size(self) -> int:
        for v in self.columns.values():
            return len(v)
        return 1


@dataclasses.dataclass
class Group:
    """The runs of one (robot type, level): the product of its axes (last axis fastest)."""

    robot: str
    level: str
    axes: list
    reference_path: Any            # the reference family's static path function
    reference_name: str
    branch: np.ndarray             # (n_reference,) branch of each reference (dynamic laws)

    @property
    def shape(self) -> tuple:
        return tuple(a.size for a in self.axes)

    @property
    def size(self) -> int:
        return int(np.prod(self.shape))


@dataclasses.dataclass
class Plan:
    """A validated sweep."""

    spec: dict
    source: Path
    law: str
    task: str
    space: str                     # initial conditions: "output" | "physical"
    groups: list
    t_final: float
    dt: float
    n_steps: int
    block: int                     # runs per compiled block (per device)
    save_every: int                # steps between the samples min_distance is taken on
    error_tol: float | None
    position_tol: float
    heading_tol: float
    plant: bool                    # actuator limits / mismatch: the loop is wmrjax.with_plant(ctrl)
    swept: list                    # the columns with more than one value (map axes)
    fingerprint: str

    @property
    def n_runs(self) -> int:
        return sum(g.size for g in self.groups)

    def blocks(self):
        """``(group index, first run in group, runs)`` for every block, in table order."""
        out = []
        for gi, g in enumerate(self.groups):
            for start in range(0, g.size, self.block):
                out.append((gi, start, min(self.block, g.size - start)))
        return out


# --- reading values ---------------------------------------------------------------------------

def _where(section: str, key: str) -> str:
    return f"[{section}] {key}" if section else key


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def axis_values(section: str, key: str, v, *, vector: int | None = None, positive: bool = False,
                allow_inf: bool = False) -> np.ndarray:
    """A fixed value, a list (grid) or a ``{min, max, num}`` table -> (n,) or (n, vector) values."""
    where = _where(section, key)
    form = ("a number, a list of numbers or { min = a, max = b, num = n }" if vector is None else
            f"a list of {vector} numbers, or a list of such lists (a grid)")

    def number(x):
        ok = isinstance(x, (int, float)) and not isinstance(x, bool) and (math.isfinite(x) or (allow_inf and x == math.inf))
        if not ok:
            raise SpecError(f"{where}: expected {form}, got {x!r}")
        if positive and not x > 0:
            raise SpecError(f"{where}: values must be > 0, got {x!r}")
        return float(x)

    if vector is not None:
        if isinstance(v, list) and v and all(isinstance(x, list) for x in v):
            rows = v
        elif isinstance(v, list):
            rows = [v]
        else:
            raise SpecError(f"{where}: expected {form}, got {v!r}")
        for r in rows:
            if len(r) != vector:
                raise SpecError(f"{where}: expected {form}, got a vector of {len(r)}: {r!r}")
        return np.array([[number(x) for x in r] for r in rows], float)
    if isinstance(v, dict):
        unknown = set(v) - {"min", "max", "num"}
        if unknown or set(v) != {"min", "max", "num"}:
            raise SpecError(f"{where}: a grid table needs exactly min, max, num; got keys {sorted(v)}")
        lo, hi = number(v["min"]), number(v["max"])
        num = v["num"]
        if not (isinstance(num, int) and not isinstance(num, bool) and num >= 1):
            raise SpecError(f"{where}: num must be an integer >= 1, got {num!r}")
        if num > 1 and not hi > lo:
            raise SpecError(f"{where}: max must be > min, got min = {lo}, max = {hi}")
        return np.linspace(lo, hi, num)
    if isinstance(v, list):
        if not v:
            raise SpecError(f"{where}: an empty list; expected {form}")
        return np.array([number(x) for x in v], float)
    return np.array([number(v)], float)


def _check_keys(section: str, table: dict, allowed, required=()) -> None:
    if not isinstance(table, dict):
        raise SpecError(f"[{section}] must be a table, got {table!r}")
    unknown = sorted(set(table) - set(allowed))
    if unknown:
        raise SpecError(f"[{section}]: unknown key(s) {unknown}; expected some of {sorted(allowed)}")
    missing = [k for k in required if k not in table]
    if missing:
        raise SpecError(f"[{section}]: missing key(s) {missing}")


def _choice(section: str, key: str, v, choices) -> str:
    if v not in choices:
        raise SpecError(f"{_where(section, key)}: expected one of {list(choices)}, got {v!r}")
    return v


def _integer(section: str, key: str, v, minimum: int) -> int:
    if not (isinstance(v, int) and not isinstance(v, bool) and v >= minimum):
        raise SpecError(f"{_where(section, key)}: expected an integer >= {minimum}, got {v!r}")
    return v


def _positive(section: str, key: str, v) -> float:
    if not (_is_number(v) and v > 0):
        raise SpecError(f"{_where(section, key)}: expected a number > 0, got {v!r}")
    return float(v)


def _product(named: dict) -> dict:
    """Cartesian product of named 1-D (or (n, k)) value arrays -> columns of equal length."""
    names = list(named)
    sizes = [len(named[k]) for k in names]
    idx = np.indices(sizes).reshape(len(names), -1) if names else np.zeros((0, 1), int)
    return {k: named[k][idx[i]] for i, k in enumerate(names)}


# --- loading ------------------------------------------------------------------------------------

def load(path) -> Plan:
    """Read, validate and plan a sweep file; every error is a :class:`SpecError` (a ValueError)
    naming the key, raised before JAX compiles anything."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as err:
        raise SpecError(f"cannot read sweep file {str(path)!r}: {err.strerror}") from None
    try:
        spec = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise SpecError(f"{path}: not valid TOML: {err}") from None
    return plan(spec, path)


def plan(spec: dict, source: Path) -> Plan:
    """Validate a parsed sweep file (see :func:`load`)."""
    import wmrjax as w

    unknown = sorted(set(spec) - set(SECTIONS))
    if unknown:
        raise SpecError(f"unknown section(s) {unknown}; expected some of {list(SECTIONS)}")
    for s in ("controller", "reference", "initial", "simulation"):
        if s not in spec:
            raise SpecError(f"missing section [{s}]")
    c = spec["controller"]
    _check_keys("controller", c, ("law", "robot", "level", "task"), ("law", "robot"))
    law = _choice("controller", "law", c["law"], LAWS)
    robots_ = c["robot"] if isinstance(c["robot"], list) else [c["robot"]]
    levels = c.get("level", "velocity")
    levels = levels if isinstance(levels, list) else [levels]
    if not robots_ or not levels:
        raise SpecError("[controller] robot and level must not be empty lists")
    for lv in levels:
        _choice("controller", "level", lv, LEVELS)
    kinds = []
    for r in robots_:
        try:
            kinds.append(w.robot_type(r).name)
        except (ValueError, TypeError) as err:
            raise SpecError(f"[controller] robot: {err}") from None
    task = c.get("task", "posture" if law == "dynamic" else None)
    if law == "dynamic":
        if task != "posture":
            raise SpecError(f"[controller] task: dynamic laws track a posture (task = \"posture\"), got {task!r}")
        bad = [k for k in kinds if k not in w.controllers.TABLE4]
        if bad:
            raise SpecError(f"[controller] robot: no dynamic linearizing law (Table 4) for type(s) {bad}; "
                            f"expected some of {sorted(w.controllers.TABLE4)}")
    else:
        task = _choice("controller", "task", task if task is not None else "point", ("point", "posture"))

    sim = spec["simulation"]
    _check_keys("simulation", sim, ("t_final", "dt", "block", "error_tol", "distance_every"), ("t_final", "dt"))
    t_final = _positive("simulation", "t_final", sim["t_final"])
    dt = _positive("simulation", "dt", sim["dt"])
    n_steps = int(round(t_final / dt))
    if n_steps < 1 or abs(n_steps * dt - t_final) > 1e-9 * max(1.0, t_final):
        raise SpecError(f"[simulation] t_final = {t_final} s is not a whole number of steps dt = {dt} s")
    block = _integer("simulation", "block", sim.get("block", 256), 1)
    every = sim.get("distance_every", max(1, int(round(0.1 / dt))))
    every = min(_integer("simulation", "distance_every", every, 1), n_steps)
    tol = sim.get("error_tol", 1e-3)
    if tol == "none":
        tol = None
    elif not (_is_number(tol) and tol > 0):
        raise SpecError(f"[simulation] error_tol: expected a number > 0 or \"none\", got {tol!r}")

    cls = spec.get("classify", {})
    _check_keys("classify", cls, ("position_tol", "heading_tol"))
    position_tol = _positive("classify", "position_tol", cls.get("position_tol", 0.01))
    heading_tol = _positive("classify", "heading_tol", cls.get("heading_tol", 0.01))

    space = spec["initial"].get("space", "output" if law == "dynamic" else "physical")
    _choice("initial", "space", space, ("output", "physical"))
    if space == "output" and law != "dynamic":
        raise SpecError("[initial] space = \"output\" (errors in the output jet) needs a dynamic law; "
                        "static laws take space = \"physical\"")
    plant = "plant" in spec

    groups = []
    for kind in kinds:
        for level in levels:
            ctrl = controller(law, kind, level, task)
            groups.append(_group(ctrl, spec, source, law, space, t_final, dt, n_steps))
    swept = []            # columns with more than one value within a group (defaults differ across groups)
    for g in groups:
        for a in g.axes:
            for k, v in a.columns.items():
                if k not in swept and len(set(np.asarray(v).tolist())) > 1:
                    swept.append(k)
    if len(groups) > 1:
        swept = (["robot"] if len(kinds) > 1 else []) + (["level"] if len(levels) > 1 else []) + swept
    fp = hashlib.sha256(json.dumps([spec, _files_digest(spec, source)], sort_keys=True, default=str).encode())
    return Plan(spec, source, law, task, space, groups, t_final, dt, n_steps, block, every, tol,
                position_tol, heading_tol, plant, swept, fp.hexdigest()[:16])


def _files_digest(spec, source):
    """Digests of the files a sweep reads (reference samples, tuned gains): part of its fingerprint,
    so that a changed file is not resumed from blocks computed with the old one."""
    out = []
    for section in ("reference", "gains"):
        f = spec.get(section, {}).get("file") if isinstance(spec.get(section), dict) else None
        p = Path(source).parent / f if isinstance(f, str) else None
        out.append(hashlib.sha256(p.read_bytes()).hexdigest() if p is not None and p.is_file() else None)
    return out


def controller(law: str, kind: str, level: str, task: str):
    import wmrjax as w

    if law == "dynamic":
        return w.dynamic_linearization(kind, level)
    try:
        return w.controller(kind, level=level, task=task)
    except ValueError as err:
        raise SpecError(f"[controller]: {err}") from None


def _group(ctrl, spec, source, law, space, t_final, dt, n_steps) -> Group:
    import wmrjax as w

    kind, level = ctrl.robot.name, ctrl.level
    row = ctrl.row
    # -- geometry
    gs = spec.get("geometry", {})
    _check_keys("geometry", gs, GEOMETRY_KEYS)
    base = row.default_geometry
    geo = {k: axis_values("geometry", k, gs[k]) if k in gs else np.array([float(getattr(base, k))])
           for k in GEOMETRY_KEYS}
    geo_cols = _product(geo)
    for i in range(len(geo_cols["L"])):
        g = w.Geometry(**{k: float(geo_cols[k][i]) for k in GEOMETRY_KEYS})
        try:
            w.robots.check_geometry(g)
            w.controllers.law.check_requirements(row.requires, g, f"type {kind}")
        except ValueError as err:
            raise SpecError(f"[geometry] for type {kind}: {err}") from None
    geometry = Axis("geometry", {f"geometry_{k}": v for k, v in geo_cols.items()}, dict(geo_cols))

    # -- plant
    nu = ctrl.robot.n_input
    ps = spec.get("plant", {})
    _check_keys("plant", ps, ("input_limit", "input_scale", "geometry_scale"))
    lim = axis_values("plant", "input_limit", ps["input_limit"], vector=nu, positive=True, allow_inf=True) \
        if "input_limit" in ps else np.full((1, nu), np.inf)
    pv = {"limit": lim,
          "input_scale": axis_values("plant", "input_scale", ps.get("input_scale", 1.0), positive=True),
          "geometry_scale": axis_values("plant", "geometry_scale", ps.get("geometry_scale", 1.0), positive=True)}
    pcols = _product(pv)
    plant_cols = {f"plant_input_limit_{i + 1}": pcols["limit"][:, i] for i in range(nu)}
    plant_cols |= {"plant_input_scale": pcols["input_scale"], "plant_geometry_scale": pcols["geometry_scale"]}
    plant = Axis("plant", plant_cols, pcols)

    # -- reference
    reference, path, ref_name, refs = _reference_axis(spec["reference"], source, law, kind)

    # -- gains
    gains = _gains_axis(spec.get("gains", {}), ctrl, source)

    # -- initial conditions
    initial = _initial_axis(spec["initial"], ctrl, law, space)

    # validate every (geometry, reference) pair over the horizon, and every gain against dt
    n_pairs = len(geo_cols["L"]) * len(refs)
    if n_pairs > 4096:
        raise SpecError(f"type {kind}: {n_pairs} (geometry, reference) pairs to check; at most 4096 "
                        "(sweep fewer geometries or references per file)")
    branch = np.ones(len(refs), int)
    for i in range(len(geo_cols["L"])):
        g = w.Geometry(**{k: float(geo_cols[k][i]) for k in GEOMETRY_KEYS})
        for j, ref in enumerate(refs):
            try:
                params = ctrl.params(ref, poles=1.0, geometry=g)
                ctrl.check_reference(params, t_final)
            except ValueError as err:
                raise SpecError(f"[reference] {ref_name} (#{j}) with geometry {g._asdict()} for type {kind}, "
                                f"{level} level: {err}") from None
            branch[j] = ctrl.reference_branch(params)
    for i, coeffs in enumerate(gains.payload["coeffs"]):
        try:
            ctrl.check_step(ctrl.params(refs[0], geometry=w.Geometry(**{k: float(geo_cols[k][0]) for k in GEOMETRY_KEYS}),
                                        gains=w.Gains(np.asarray(coeffs))), dt)
        except ValueError as err:
            raise SpecError(f"[simulation] dt with gains #{i} for type {kind}, {level} level: {err}") from None
    return Group(kind, level, [geometry, plant, reference, gains, initial], path, ref_name, branch)


def _reference_axis(rs, source, law, kind):
    import jax
    import jax.numpy as jnp

    from wmrjax import references as R

    if not isinstance(rs, dict) or "family" not in rs:
        raise SpecError(f"[reference]: needs family = one of {list(FAMILIES)}")
    fam = _choice("reference", "family", rs["family"], FAMILIES)
    common = ("family", "heading_offset")
    if fam == "random_smooth":
        _check_keys("reference", rs, common + ("count", "seed", "options"), ("count",))
        count = _integer("reference", "count", rs["count"], 1)
        seed = _integer("reference", "seed", rs.get("seed", 0), 0)
        opts = dict(RANDOM_OPTIONS)
        given = rs.get("options", {})
        _check_keys("reference.options", given, tuple(RANDOM_OPTIONS))
        for k, v in given.items():
            if k == "n_modes":
                opts[k] = _integer("reference.options", k, v, 1)
            elif not _is_number(v) or (k != "start_scale" and v <= 0) or v < 0:
                raise SpecError(f"[reference.options] {k}: expected a number {'>= 0' if k == 'start_scale' else '> 0'}, got {v!r}")
            else:
                opts[k] = float(v)
        if not 0 < opts["min_speed"] < opts["speed"]:
            raise SpecError(f"[reference.options]: need 0 < min_speed < speed, got {opts['min_speed']}, {opts['speed']}")
        keys = jax.random.split(jax.random.PRNGKey(seed), count)
        batch = jax.vmap(lambda k: R.random_smooth(k, **opts))(keys)
        params = jax.tree_util.tree_map(np.asarray, batch.params)
        refs = [R.Reference(jax.tree_util.tree_map(lambda x: jnp.asarray(x[i]), params), 0.0, batch.path, fam)
                for i in range(count)]
        cols = {"reference_index": np.arange(count, dtype=float)}
    elif fam == "samples":
        _check_keys("reference", rs, common + ("file", "min_speed"), ("file",))
        f = rs["file"]
        if not isinstance(f, str):
            raise SpecError(f"[reference] file: expected a path (relative to the sweep file) of a CSV with columns t, x, y, got {f!r}")
        min_speed = rs.get("min_speed", 1e-3 if law == "dynamic" else None)
        try:
            ref = R.load_samples(Path(source).parent / f, min_speed=min_speed)
        except ValueError as err:
            raise SpecError(f"[reference] file: {err}") from None
        refs, params = [ref], jax.tree_util.tree_map(lambda x: np.asarray(x)[None], ref.params)
        cols = {"reference_index": np.zeros(1)}
    else:
        factory = R.REFERENCES[fam]
        sig = inspect.signature(factory)
        names = [k for k in sig.parameters if k != "heading_offset"]
        _check_keys("reference", rs, common + ("options",))
        given = rs.get("options", {})
        _check_keys("reference.options", given, names)
        vals = {}
        for k, v in given.items():
            default = sig.parameters[k].default
            vec = len(default) if isinstance(default, tuple) else None
            vals[k] = axis_values("reference.options", k, v, vector=vec)
        grid = _product(vals) if vals else {}
        count = len(next(iter(grid.values()))) if grid else 1
        refs = []
        for i in range(count):
            kw = {k: (tuple(v[i]) if np.ndim(v) == 2 else float(v[i])) for k, v in grid.items()}
            try:
                refs.append(factory(**kw))
            except (ValueError, TypeError) as err:
                raise SpecError(f"[reference.options] {kw}: {err}") from None
        params = jax.tree_util.tree_map(lambda *xs: np.stack([np.asarray(x) for x in xs]), *[r.params for r in refs])
        cols = {}
        for k, v in grid.items():
            if np.ndim(v) == 2:
                cols |= {f"reference_{k}_{j}": v[:, j] for j in range(v.shape[1])}
            else:
                cols[f"reference_{k}"] = v
        if not cols:
            cols = {"reference_index": np.zeros(1)}
    heading = axis_values("reference", "heading_offset", rs.get("heading_offset", _default_offset(law, kind)))
    n_ref = len(refs)
    # product of the references and the heading offsets (offset fastest)
    ii, jj = np.indices((n_ref, len(heading))).reshape(2, -1)
    refs = [R.Reference(r.params, jnp.asarray(h), r.path, r.name) for r in refs for h in heading]
    cols = {k: v[ii] for k, v in cols.items()} | {"reference_heading_offset": heading[jj]}
    payload = {"reference": jax.tree_util.tree_map(lambda x: x[ii], params), "heading_offset": heading[jj]}
    return Axis("reference", cols, payload), refs[0].path, fam, refs


def _default_offset(law, kind):
    import wmrjax as w

    if law == "dynamic":
        return float(w.controllers.TABLE4[kind].default_heading_offset)
    return 0.0


def _gains_axis(gs, ctrl, source) -> Axis:
    import wmrjax as w

    _check_keys("gains", gs, ("poles", "omega", "zeta", "lam", "file"))
    m, r = ctrl.m, ctrl.relative_degree
    if "file" in gs:
        if len(gs) > 1:
            raise SpecError("[gains]: file excludes poles/omega/zeta/lam")
        f = Path(source).parent / gs["file"]
        try:
            data = json.loads(f.read_text())
            coeffs = np.asarray(data["tuned_gains"]["coefficients_k0_to_kr-1"], float)
        except (OSError, ValueError, KeyError, TypeError) as err:
            raise SpecError(f"[gains] file: cannot read tuned gains (tuned_gains.coefficients_k0_to_kr-1) "
                            f"from {str(f)!r}: {err}") from None
        if coeffs.shape != (m, r):
            raise SpecError(f"[gains] file: gains of shape {coeffs.shape}, this controller needs ({m}, {r}) "
                            f"(type {ctrl.robot.name}, {ctrl.level} level)")
        try:
            w.Gains(coeffs).check(m, r)
        except ValueError as err:
            raise SpecError(f"[gains] file: {err}") from None
        return Axis("gains", {"gains_file": np.array([str(gs['file'])])}, {"coeffs": coeffs[None]})
    if "omega" in gs or "zeta" in gs:
        if "poles" in gs or not ("omega" in gs and "zeta" in gs):
            raise SpecError("[gains]: give either poles, or omega and zeta (and lam for an odd relative degree)")
        vals = {k: axis_values("gains", k, gs[k], positive=True) for k in ("omega", "zeta")}
        if r % 2:
            vals["lam"] = axis_values("gains", "lam", gs.get("lam", 1.0), positive=True)
        elif "lam" in gs:
            raise SpecError(f"[gains] lam: only for an odd relative degree; this controller's is {r}")
        grid = _product(vals)
        coeffs = []
        for i in range(len(grid["omega"])):
            om = np.full((m, r // 2), grid["omega"][i])
            ze = np.full((m, r // 2), grid["zeta"][i])
            lam = np.full((m,), grid["lam"][i]) if r % 2 else None
            coeffs.append(np.asarray(w.Gains.from_damping(om, ze, lam, m=m).coeffs))
        return Axis("gains", {f"gains_{k}": v for k, v in grid.items()}, {"coeffs": np.stack(coeffs)})
    if "lam" in gs:
        raise SpecError("[gains] lam: only with omega and zeta")
    poles = axis_values("gains", "poles", gs.get("poles", 1.0), positive=True)
    coeffs = np.stack([np.asarray(w.Gains.from_poles(np.full((m, r), p)).coeffs) for p in poles])
    return Axis("gains", {"gains_poles": poles}, {"coeffs": coeffs})


def initial_keys(ctrl, space: str) -> tuple:
    """The initial-error keys this controller accepts in ``space``."""
    if space == "output":
        return ("x", "y", "vx", "vy")
    beta = ("beta",) if ctrl.robot.delta_s == 1 else ("beta1", "beta2")[: ctrl.robot.delta_s]
    return ("x", "y", "theta") + beta


def _initial_axis(ins, ctrl, law, space) -> Axis:
    keys = initial_keys(ctrl, space)
    _check_keys("initial", ins, ("space", "random") + keys)
    errs = {}
    rnd = ins.get("random")
    if rnd is not None:
        _check_keys("initial.random", rnd, ("count", "seed"), ("count",))
        count = _integer("initial.random", "count", rnd["count"], 1)
        rng = np.random.default_rng(_integer("initial.random", "seed", rnd.get("seed", 0), 0))
        for k in keys:          # draw every key (fixed order) so a key's values do not depend on the others
            v = ins.get(k, 0.0)
            if isinstance(v, dict):
                if set(v) != {"low", "high"} or not (_is_number(v["low"]) and _is_number(v["high"])) \
                        or not v["high"] >= v["low"]:
                    raise SpecError(f"[initial] {k}: a random range is {{ low = a, high = b }} with b >= a, got {v!r}")
                errs[k] = rng.uniform(v["low"], v["high"], count)
            elif _is_number(v):
                rng.uniform(0.0, 1.0, count)
                errs[k] = np.full(count, float(v))
            else:
                raise SpecError(f"[initial] {k}: with [initial.random], expected a number or {{ low = a, high = b }}, got {v!r}")
    else:
        for k in keys:
            if isinstance(ins.get(k), dict) and set(ins[k]) == {"low", "high"}:
                raise SpecError(f"[initial] {k}: a {{ low, high }} range needs [initial.random] (count, seed)")
        errs = _product({k: axis_values("initial", k, ins.get(k, 0.0)) for k in keys})
    if space == "output" and ctrl.relative_degree < 2 and any(np.any(errs[k] != 0) for k in ("vx", "vy")):
        raise SpecError("[initial] vx, vy: the output jet has no velocity row at relative degree 1")
    cols = {f"initial_error_{k}": v for k, v in errs.items()}
    return Axis("initial", cols, {"initial": np.stack([errs[k] for k in keys], axis=1)}, random=rnd is not None)


def unravel(group: Group, start: int, n: int) -> list:
    """Per-axis value indices of runs ``start .. start + n - 1`` of ``group`` (last axis fastest)."""
    return list(np.unravel_index(np.arange(start, start + n), group.shape))


def columns_of(group: Group, idx: list) -> dict:
    out = {}
    for a, i in zip(group.axes, idx):
        for k, v in a.columns.items():
            out[k] = np.asarray(v)[i]
    return out
