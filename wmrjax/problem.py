r"""A user's problem: controller, geometry, reference, plant, gains, initial conditions, horizon.

One description serves every job: a sweep runs it over many starts, the tuner improves its
gains, the certification says from where it is safe. Build it in Python
(:meth:`Problem.from_dict`) or read it from its file form (:meth:`Problem.load`, TOML)::

    title = "my robot on my path"
    [controller]
    law = "dynamic"                      # or "static"
    robot = "(2,0)"                      # a list: one setting per type
    level = "velocity"                   # or "torque"; a list: one setting per level
    [geometry]
    e = 0.15                             # [m]; L [m], delta [rad]
    [plant]                              # optional: the robot the law does not know exactly
    input_limit = [1.5, 2.0]             # |u_i| <= limit_i [m/s, rad/s; per s at torque level]
    input_scale = 1.0                    # true input = scale * command ([[s1, s2]]: one per input)
    geometry_scale = 1.0                 # the plant's L and e = scale * the law's
    control_period = 0.05                # [s]: a digital controller (zero-order hold) ...
    noise_std = [0.01, 0.01, 0.005]      # ... measuring X with this noise [m, m, rad]
    noise_seed = 0
    [reference]
    family = "samples"                   # every family of wmrjax.references.FAMILIES
    file = "path.csv"                    # relative to this file (or t = [...], x = [...], y = [...])
    [initial]
    space = "output"                     # errors of the output jet; or "physical" (posture)
    x = { min = -1.0, max = 1.0, num = 11 }        # a grid; or random = { count, seed } with
    y = { min = -1.0, max = 1.0, num = 11 }        # { low, high } ranges; or points = [[...]]
    [gains]
    poles = 1.0                          # or omega, zeta (lam), or coefficients, or file
    [simulation]
    t_final = 10.0                       # [s]
    dt = 0.01                            # [s]
    [[case]]                             # optional: named variants, e.g. default and tuned gains
    name = "tuned"
    gains = { file = "tuned/gains.json" }

Every value of a swept quantity is a number (or a vector), a list of them (an axis), or a
table ``{ min, max, num }``; the initial conditions may also be random (``{ low, high }``
ranges with ``random = { count, seed }``) or an explicit list of error vectors (``points``).
A sweep runs the Cartesian product of the axes (and every case); the tuner and the
certification take one value of each, and read their own sections (``[tune]``,
``[certify]``). Everything is validated key by key, before anything compiles; errors are
:class:`ProblemError` (a ``ValueError``) naming the key and the expected form.

:func:`place` is the one placement of an initial state near a reference, and
:meth:`Setting.run` the one run of a problem: the tuner, the sweep and the certification's
rollouts go through :func:`wmrjax.simulate` with them.
"""

from __future__ import annotations

import copy
import dataclasses
import enum
import functools
import hashlib
import importlib
import json
import math
import re
import tomllib
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from wmrjax import controllers, io, resources, robots
from wmrjax import references as R
from wmrjax.controllers import PlantParams, SampledParams, dynamic_linearization, measurement_noise, sampled, with_plant
from wmrjax.controllers.dynamic import DynamicLinearization
from wmrjax.controllers.law import Level, Task
from wmrjax.gains import Gains, GainSchedule
from wmrjax.references import spline_degree_for
from wmrjax.robots import Geometry, robot_type
from wmrjax.simulate import simulate

# a case's name is a label in tables and a part of its figures' file names: no path separator,
# no control character, no leading dot, a bounded length
CASE_NAME_MAX = 64
CASE_NAME = re.compile(rf"[A-Za-z0-9][A-Za-z0-9 _.+\-]{{0,{CASE_NAME_MAX - 1}}}")

SECTIONS = (
    "title",
    "controller",
    "geometry",
    "plant",
    "reference",
    "initial",
    "gains",
    "simulation",
    "classify",
    "case",
    "tune",
    "certify",
)
JOB_SECTIONS = {"tune": "wmrjax.tune.config", "certify": "wmrjax.certify.job", "classify": "wmrjax.sweep.spec"}
"""A job's own section -> the module that owns its schema, whose ``read_section(data)`` checks it
key by key over its defaults (each written there once) and returns the job's settings. A file
is validated whole when it is loaded; the module is imported only when the file has its
section, so the core imports no job."""
CASE_SECTIONS = ("controller", "geometry", "plant", "reference", "initial", "gains")
GEOMETRY_KEYS = ("L", "e", "delta")
GAIN_FILE_KIND = "wmrjax.gains"


class Law(enum.StrEnum):
    """The linearizing law: Table 4's dynamic extension or Prop 3 / Table 3's static feedback."""

    DYNAMIC = "dynamic"
    STATIC = "static"


class Space(enum.StrEnum):
    """Where initial errors live: the output jet (x, y and their rates) or the physical posture."""

    OUTPUT = "output"
    PHYSICAL = "physical"


class ProblemError(ValueError):
    """A problem that cannot run: the message names the key and the expected form."""


# --- reading values ----------------------------------------------------------------------------


def _where(section: str, key: str) -> str:
    return f"[{section}] {key}" if section else key


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def axis_values(
    section: str,
    key: str,
    v,
    *,
    vector: int | None = None,
    positive: bool = False,
    allow_inf: bool = False,
    axis: bool = True,
) -> np.ndarray:
    """A fixed value, a list (axis) or a ``{min, max, num}`` table -> (n,) or (n, vector) values.
    An axis lists each value once; ``axis=False`` reads a list of data (samples) instead, where
    values may repeat."""
    where = _where(section, key)
    form = (
        "a number, a list of numbers or { min = a, max = b, num = n }"
        if vector is None
        else f"a list of {vector} numbers, or a list of such lists (an axis)"
    )

    def number(x):
        ok = (
            isinstance(x, (int, float))
            and not isinstance(x, bool)
            and (math.isfinite(x) or (allow_inf and x == math.inf))
        )
        if not ok:
            raise ProblemError(f"{where}: expected {form}, got {x!r}")
        if positive and not x > 0:
            raise ProblemError(f"{where}: values must be > 0, got {x!r}")
        return float(x)

    if vector is not None:
        if isinstance(v, list) and v and all(isinstance(x, list) for x in v):
            rows = v
        elif isinstance(v, list):
            rows = [v]
        else:
            raise ProblemError(f"{where}: expected {form}, got {v!r}")
        for r in rows:
            if len(r) != vector:
                raise ProblemError(f"{where}: expected {form}, got a vector of {len(r)}: {r!r}")
        rows = np.array([[number(x) for x in r] for r in rows], float)
        return _once(where, rows) if axis else rows
    if isinstance(v, dict):
        if set(v) != {"min", "max", "num"}:
            raise ProblemError(f"{where}: a grid table needs exactly min, max, num; got keys {sorted(v)}")
        lo, hi = number(v["min"]), number(v["max"])
        num = v["num"]
        if not (isinstance(num, int) and not isinstance(num, bool) and num >= 1):
            raise ProblemError(f"{where}: num must be an integer >= 1, got {num!r}")
        if num > 1 and not hi > lo:
            raise ProblemError(f"{where}: max must be > min, got min = {lo}, max = {hi}")
        check_table_fits(where, num, 1, "num")
        return np.linspace(lo, hi, num)
    if isinstance(v, list):
        if not v:
            raise ProblemError(f"{where}: an empty list; expected {form}")
        values = np.array([number(x) for x in v], float)
        return _once(where, values) if axis else values
    return np.array([number(v)], float)


# arrays alive at once while a problem's values are built (the draws or grid, their columns,
# the stacked payload)
TABLE_COPIES = 3


def check_table_fits(where: str, n: int, width: int, key: str) -> None:
    """ProblemError, before anything is allocated, when ``n`` values of ``width`` numbers (a grid's
    ``num``, a random draw's ``count``) do not fit in the memory available now; names the key."""
    try:
        resources.check_fits(
            resources.Estimate(0.0, TABLE_COPIES * 8.0 * n * max(1, width)), f"{where}: {n} values", f"lower {key}"
        )
    except ValueError as err:
        raise ProblemError(str(err)) from None


def _once(where: str, values: np.ndarray) -> np.ndarray:
    """``values`` (an axis: (n,) or (n, k)) if no value is listed twice; a value listed twice would
    run (and count) the same runs twice."""
    _, first, counts = np.unique(values, axis=0, return_index=True, return_counts=True)
    if np.any(counts > 1):
        twice = values[first[np.argmax(counts > 1)]]
        listed = repr(values.tolist())
        listed = listed if len(listed) <= 200 else f"{listed[:200]}... ({len(values)} values)"
        raise ProblemError(f"{where}: {twice.tolist()!r} listed twice in {listed}: an axis lists each value once")
    return values


def check_keys(section: str, table, allowed, required=()) -> None:
    """ProblemError for a non-table, an unknown key or a missing one."""
    if not isinstance(table, dict):
        raise ProblemError(f"[{section}] must be a table, got {table!r}")
    unknown = sorted(set(table) - set(allowed))
    if unknown:
        raise ProblemError(f"[{section}]: unknown key(s) {unknown}; expected some of {sorted(allowed)}")
    missing = [k for k in required if k not in table]
    if missing:
        raise ProblemError(f"[{section}]: missing key(s) {missing}")


def choice(section: str, key: str, v, choices):
    """``v`` if it is one of ``choices`` (strings or a StrEnum), else a ProblemError."""
    values = [str(c) for c in choices]
    if not isinstance(v, str) or v not in values:
        raise ProblemError(f"{_where(section, key)}: expected one of {values}, got {v!r}")
    return choices(v) if isinstance(choices, type) else v


def integer(section: str, key: str, v, minimum: int, maximum: int | None = None) -> int:
    ok = isinstance(v, int) and not isinstance(v, bool) and v >= minimum and (maximum is None or v <= maximum)
    if not ok:
        bound = f">= {minimum}" + (f" and <= {maximum}" if maximum is not None else "")
        raise ProblemError(f"{_where(section, key)}: expected an integer {bound}, got {v!r}")
    return v


def positive(section: str, key: str, v) -> float:
    if not (_is_number(v) and v > 0):
        raise ProblemError(f"{_where(section, key)}: expected a number > 0, got {v!r}")
    return float(v)


def nonnegative(section: str, key: str, v) -> float:
    if not (_is_number(v) and v >= 0):
        raise ProblemError(f"{_where(section, key)}: expected a number >= 0, got {v!r}")
    return float(v)


PRODUCT_COPIES = 3


def product(named: dict) -> dict:
    """Cartesian product of named 1-D (or (n, k)) value arrays -> columns of equal length (last fastest)."""
    names = list(named)
    sizes = [len(named[k]) for k in names]
    runs = math.prod(sizes)
    # the index grid and the columns: refused before allocating (a grid too large otherwise fails
    # only after a long allocation, with MemoryError); PRODUCT_COPIES arrays of runs x names
    # numbers are alive at once
    try:
        resources.check_fits(
            resources.Estimate(0.0, PRODUCT_COPIES * runs * max(1, len(names)) * 8.0),
            f"a grid of {runs} runs over {names}",
            "sweep fewer values",
        )
    except ValueError as err:
        raise ProblemError(str(err)) from None
    idx = np.indices(sizes).reshape(len(names), -1) if names else np.zeros((0, 1), int)
    return {k: named[k][idx[i]] for i, k in enumerate(names)}


def read_text(path: Path, what: str) -> str:
    """A small UTF-8 text file (:func:`wmrjax.io.read_small_text`); ProblemError naming it otherwise."""
    try:
        return io.read_small_text(path, what)
    except ValueError as err:
        raise ProblemError(str(err)) from None


# --- the problem -------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class Problem:
    """A user's problem (see the module docstring for its file form).

    Attributes:
      data: the problem as parsed TOML (plain JSON types); checked when built.
      base: the directory relative file names resolve against (the file's own directory).
      source: the file it was read from (None if built in Python).
    """

    data: dict
    base: Path = dataclasses.field(default_factory=Path.cwd)
    source: Path | None = None

    def __post_init__(self):
        # every key validated now, before anything compiles; the settings are kept (immutable data)
        object.__setattr__(self, "_settings", self._validated())

    @classmethod
    def load(cls, path) -> "Problem":
        """Read and validate a problem file (TOML)."""
        path = Path(path)
        text = read_text(path, "problem file")
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as err:
            raise ProblemError(f"{path}: not valid TOML: {err}") from None
        return cls(data, path.resolve().parent, path)

    @classmethod
    def from_dict(cls, data: dict, base=None) -> "Problem":
        """A problem from its sections as a dict (the TOML tree; e.g. a summary's ``problem``)."""
        if not isinstance(data, dict):
            raise ProblemError(f"a problem is a table of sections, got {type(data).__name__}")
        return cls(copy.deepcopy(data), Path.cwd() if base is None else Path(base))

    def with_values(self, values: dict) -> "Problem":
        """A copy with values set by dotted keys, validated (e.g. ``{"plant.input_limit": [2.0, 1.5],
        "tune.optimizer.learning_rate": 0.1}``; ``None`` deletes a key). Command lines apply
        their options to a problem file this way."""
        data = copy.deepcopy(self.data)
        for key, v in values.items():
            *path, last = key.split(".")
            node = data
            for k in path:
                node = node.setdefault(k, {})
                if not isinstance(node, dict):
                    raise ProblemError(f"{key}: {k} is not a table in this problem")
            if v is None:
                node.pop(last, None)
            else:
                node[last] = v
        return Problem(data, self.base, self.source)

    @property
    def title(self) -> str:
        return str(self.data.get("title", self.source.stem if self.source else "problem"))

    def section(self, name: str) -> dict:
        """A job's own section (``tune``, ``certify``, ``classify``), {} if absent."""
        s = self.data.get(name, {})
        check_keys(name, s, s.keys() if isinstance(s, dict) else ())
        return s

    def cases(self) -> list:
        """``(name, data)`` for every case: the problem itself (name None) when it has no ``[[case]]``."""
        cases = self.data.get("case")
        if cases is None:
            return [(None, self.data)]
        if not isinstance(cases, list) or not cases or not all(isinstance(c, dict) for c in cases):
            raise ProblemError("[[case]]: expected an array of tables, each with a name and the sections it changes")
        out, names = [], set()
        for i, c in enumerate(cases):
            check_keys(f"case #{i + 1}", c, ("name",) + CASE_SECTIONS, ("name",))
            name = c["name"]
            if not isinstance(name, str) or not CASE_NAME.fullmatch(name) or name in names:
                shown = repr(name)
                raise ProblemError(
                    f"[[case]] #{i + 1} name: expected a label of 1 to {CASE_NAME_MAX} characters -- letters, "
                    "digits, space, '_', '.', '+', '-', starting with a letter or digit (it names the case's "
                    f"figures and rows) -- not used by another case, got "
                    f"{shown[:60] + '...' if len(shown) > 60 else shown}"
                )
            names.add(name)
            merged = {k: v for k, v in self.data.items() if k != "case"}
            merged.update({k: v for k, v in c.items() if k != "name"})
            out.append((name, merged))
        return out

    def settings(self) -> list:
        """One :class:`Setting` per case, robot type and level, every key validated."""
        return list(self._settings)

    def _validated(self) -> list:
        unknown = sorted(set(self.data) - set(SECTIONS))
        if unknown:
            raise ProblemError(f"unknown section(s) {unknown}; expected some of {list(SECTIONS)}")
        for name, module in JOB_SECTIONS.items():
            if name in self.data:  # the job's own schema, from the module that owns it
                importlib.import_module(module).read_section(self.data)
        out = []
        for name, data in self.cases():
            out += _settings(data, self.base, name)
        return out

    def setting(self, job: str, case: str | None = None) -> "Setting":
        """The one setting a job runs (``job`` names it in messages): one robot, one level, and
        one case (or ``case``)."""
        settings = self.settings()
        if case is not None:
            settings = [s for s in settings if s.case == case]
            if not settings:
                raise ProblemError(f"no case named {case!r}; the problem has {[c for c, _ in self.cases()]}")
        if len(settings) != 1:
            which = sorted({(s.case, s.ctrl.robot.name, str(s.ctrl.level)) for s in settings}, key=str)
            raise ProblemError(
                f"{job} takes one controller: this problem has {len(settings)} settings {which} "
                "(a list of robots or levels, or several [[case]]s); keep one"
                + (" or choose a case" if len({s.case for s in settings}) > 1 else "")
            )
        return settings[0]

    def resolved(self) -> dict:
        """The problem as plain JSON with every file it reads inlined (reference samples, gains),
        so that it runs again from this dict alone (:meth:`from_dict`)."""
        data = copy.deepcopy(self.data)
        sections = [data] + list(data.get("case", []))
        for sec in sections:
            ref = sec.get("reference")
            family = _family_of(ref)
            if family is not None and family.kind == "data" and "file" in ref:
                path = self.base / ref["file"]
                cols = _read_csv(path, family.columns)
                ref.pop("file")
                ref.update({k: v.tolist() for k, v in cols.items()})
                ref["source_file"] = {"path": str(path), "sha256": _digest(path)}
            gains = sec.get("gains")
            if isinstance(gains, dict) and isinstance(gains.get("file"), str):
                path = self.base / gains["file"]
                sec["gains"] = {
                    **read_gains_file(path).to_problem(),
                    "source_file": {"path": str(path), "sha256": _digest(path)},
                }
        return data

    def fingerprint(self) -> str:
        """A digest of the resolved problem (files included): equal problems, equal fingerprints."""
        return hashlib.sha256(json.dumps(self.resolved(), sort_keys=True).encode()).hexdigest()[:16]


def _family_of(ref):
    """The registry's family a ``[reference]`` section names (None if it names none)."""
    return R.FAMILIES.get(ref.get("family")) if isinstance(ref, dict) else None


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@dataclasses.dataclass
class Axis:
    """One axis of a setting: ``n`` values, their table columns and what the run consumes.

    Attributes:
      name: "geometry" | "plant" | "reference" | "gains" | "initial".
      columns: column name -> (n,) values (float, or str for labels).
      payload: key -> (n, ...) arrays (or a pytree with that leading axis) for the run.
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


@dataclasses.dataclass(eq=False)
class Setting:
    """One controller of a problem (one case, robot type and level) with its axes.

    Attributes:
      case: the case's name (None without ``[[case]]``).
      law, task, space: the law, what it tracks, where initial errors live.
      ctrl: the controller (static, hashable).
      axes: geometry, plant, reference, gains, initial (:class:`Axis`; runs are their product,
        last fastest).
      references: the references of the reference axis (heading offsets applied).
      branch: (n_reference,) branch of each reference (dynamic laws).
      plant: the run closes the law around a plant (limits, scale, mismatch, sampling, noise).
      control_period: the digital controller's period [s] (None: continuous feedback).
      noise_std: measurement noise std of X's components (sampled loops), noise_seed its seed.
      t_final, dt, n_steps: horizon [s], step [s] and step count.
      data: this setting's sections as parsed.
    """

    case: str | None
    law: Law
    task: Task
    space: Space
    ctrl: Any
    axes: list
    references: list
    branch: np.ndarray
    plant: bool
    control_period: float | None
    noise_std: tuple
    noise_seed: int
    t_final: float
    dt: float
    n_steps: int
    data: dict

    @property
    def shape(self) -> tuple:
        return tuple(a.size for a in self.axes)

    def content_digest(self) -> str:
        """A digest of every value this setting runs with, read from files included (a path's
        samples, a gains file's gains): a resumable job's fingerprint, which changes when a file's
        content changes under the same name."""
        h = hashlib.sha256()
        for a in self.axes:
            h.update(a.name.encode())
            for leaf in jax.tree_util.tree_leaves((a.columns, a.payload)):
                arr = np.ascontiguousarray(np.asarray(leaf))
                h.update(f"{arr.dtype}{arr.shape}".encode())
                h.update(arr.tobytes())
        return h.hexdigest()[:16]

    @property
    def size(self) -> int:
        return int(np.prod(self.shape))

    @property
    def reference(self):
        """The first reference of the axis (the only one for a single-valued problem)."""
        return self.references[0]

    @property
    def steps_per_sample(self) -> int | None:
        return None if self.control_period is None else int(round(self.control_period / self.dt))

    def axis(self, name: str) -> Axis:
        return next(a for a in self.axes if a.name == name)

    def system(self):
        """The closed loop a run simulates: the controller, with a plant, or sampled."""
        if self.control_period is not None:
            return sampled(self.ctrl, self.steps_per_sample)
        return with_plant(self.ctrl) if self.plant else self.ctrl

    def check_single(self, job: str, keep=("initial",)) -> None:
        """ProblemError naming the first axis (other than ``keep``) with more than one value."""
        for a in self.axes:
            if a.name in keep or a.size == 1:
                continue
            swept = [k for k, v in a.columns.items() if len(set(np.asarray(v).tolist())) > 1]
            raise ProblemError(
                f"{job} takes one value of [{a.name}], got {a.size} ({', '.join(swept)} swept); "
                "keep one value (sweeps take lists)"
            )

    def geometry(self, i: int = 0):
        geo = self.axis("geometry").payload
        return Geometry(**{k: float(geo[k][i]) for k in GEOMETRY_KEYS})

    def gains(self, i: int = 0):
        """The i-th gains of the axis: :class:`wmrjax.Gains` or :class:`wmrjax.GainSchedule`."""
        return jax.tree_util.tree_map(lambda x: x[i], self.axis("gains").payload["gains"])

    def params(self, *, gains=None, reference: int = 0, geometry: int = 0):
        """The law's checked parameters (one geometry, one reference; ``gains`` overrides the axis's first)."""
        g = self.geometry(geometry)
        return self.ctrl.params(self.references[reference], geometry=g, gains=self.gains() if gains is None else gains)

    def initial_errors(self) -> np.ndarray:
        """(n, k) initial errors of the initial axis (keys :func:`initial_keys`)."""
        return np.asarray(self.axis("initial").payload["initial"])

    def inputs(self, idx: list | None = None) -> dict:
        """Every run input at its axis's level, or (with ``idx``, per-axis indices of some runs)
        per run: key -> array (or pytree) with a leading axis."""
        geo, plant, ref, gains, init = (a.payload for a in self.axes)
        src = {
            "L": geo["L"],
            "e": geo["e"],
            "delta": geo["delta"],
            "limit": plant["limit"],
            "input_scale": plant["input_scale"],
            "geometry_scale": plant["geometry_scale"],
            "reference": ref["reference"],
            "heading_offset": ref["heading_offset"],
            "branch": self.branch.astype(float),
            "gains": gains["gains"],
            "initial": init["initial"],
        }
        if idx is None:
            return src
        return {k: jax.tree_util.tree_map(lambda x, k=k: np.asarray(x)[idx[AXIS_OF[k]]], v) for k, v in src.items()}

    def run_inputs(self, i: int) -> dict:
        """The inputs of run ``i`` (its flat index, last axis fastest), unbatched: for :meth:`run`."""
        if not 0 <= i < self.size:
            raise ProblemError(f"run index {i} outside [0, {self.size}) of this setting")
        idx = list(np.unravel_index(np.array([i]), self.shape))
        return jax.tree_util.tree_map(lambda x: np.asarray(x)[0], self.inputs(idx))

    def run(
        self,
        p: dict,
        *,
        save_every: int | None = None,
        error_tol=1e-3,
        margin_floor=1e-9,
        noise_key=None,
        t0=0.0,
        save_fn=None,
    ):
        """One run (pure: vmap it) from one run's inputs ``p`` (:meth:`inputs`, unbatched).

        ``save_every`` (default: every sample of a digital controller, else every step),
        ``error_tol``, ``margin_floor`` and ``save_fn`` are :func:`wmrjax.simulate`'s;
        ``noise_key`` draws the measurement noise of a digital controller; ``t0`` [s] starts the run.

        Returns:
          ``(trajectory, params)``: the :class:`wmrjax.Trajectory` of :meth:`system`, and the
          law's parameters (reference, gains, nominal geometry) of this run.
        """
        ctrl = self.ctrl
        g = Geometry(L=p["L"], e=p["e"], delta=p["delta"])
        ref = R.Reference(p["reference"], p["heading_offset"], self.reference.path, self.reference.name)
        params = ctrl.params_unchecked(ref, 1.0, g)._replace(gains=p["gains"])
        t0 = jnp.asarray(t0, jnp.result_type(float))
        # the law's initial state: given (``z0``), or placed from the initial error
        z0 = p["z0"] if "z0" in p else place(ctrl, params, p["initial"], self.space, self.task, p["branch"], t0)
        loop = self.system()
        if self.plant:
            scale = jnp.broadcast_to(p["geometry_scale"], (2,))  # of L and e (one factor: both)
            pg = Geometry(L=scale[0] * g.L, e=scale[1] * g.e, delta=g.delta)
            plant = PlantParams(params, pg, jnp.broadcast_to(p["input_scale"], (ctrl.robot.n_input,)), p["limit"])
            if self.control_period is not None:
                noise = None
                if any(self.noise_std) and noise_key is not None:
                    n_samples = self.n_steps // self.steps_per_sample + 1
                    noise = measurement_noise(noise_key, jnp.asarray(self.noise_std), n_samples, ctrl.robot.n_state)
                sp = SampledParams(plant, jnp.zeros((1, ctrl.robot.n_state), t0.dtype) if noise is None else noise)
                z0, params_run = loop.initial_state(z0, sp), sp
            else:
                z0, params_run = loop.initial_state(z0, plant), plant
        else:
            params_run = params
        save_every = (self.steps_per_sample or 1) if save_every is None else save_every
        tr = simulate(
            loop,
            z0,
            params_run,
            dt=self.dt,
            n_steps=self.n_steps,
            t0=t0,
            save_every=save_every,
            error_tol=error_tol,
            margin_floor=margin_floor,
            save_fn=save_fn,
        )
        return tr, params


AXIS_OF = {
    "L": 0,
    "e": 0,
    "delta": 0,
    "limit": 1,
    "input_scale": 1,
    "geometry_scale": 1,
    "reference": 2,
    "heading_offset": 2,
    "branch": 2,
    "gains": 3,
    "initial": 4,
}
"""The axis (index into :attr:`Setting.axes`) each run input varies along."""


def law_state(system, z):
    """The law's own state ``(X, compensator...)`` of a closed loop's state (batched or not)."""
    return system.law_state(z)


# --- the one placement of an initial state near a reference ---------------------------------


def initial_keys(ctrl, space) -> tuple:
    """The initial-error keys this controller takes in ``space`` (output: position and velocity
    errors of the output point; physical: posture and steering-angle errors)."""
    if Space(space) == Space.OUTPUT:
        return ("x", "y", "vx", "vy")
    beta = ("beta",) if ctrl.robot.delta_s == 1 else ("beta1", "beta2")[: ctrl.robot.delta_s]
    return ("x", "y", "theta") + beta


def place(ctrl, params, error, space, task, branch, t0=0.0, rest: bool = False, jet=None):
    r"""The initial state of a run whose error from the reference at ``t0`` is ``error`` (pure).

    Output space (dynamic laws): the output jet is the reference's plus ``(x, y)`` in its
    position row and ``(vx, vy)`` in its velocity row (r >= 2) -- or, with r * m entries, plus
    the whole error jet (rows of derivative order, as ``ctrl.error`` flattens it) -- mapped back
    by :math:`\Psi^{-1}` on ``branch``. Physical space: the posture (and steering angles) are
    the reference's plus ``(x, y, theta, beta...)``; a dynamic law's compensator is the
    reference's; a static law tracking a point puts its tracked point at the reference's
    position plus ``(x, y)``, and at torque level starts with the wheel velocities that give the
    reference's output velocity (``rest``: at rest).

    Args:
      ctrl: the controller; params: its parameters (reference, geometry, gains).
      error: (k,) errors in the keys of :func:`initial_keys` [m, m, m/s, m/s or m, m, rad, rad...],
        or (r * m,) output-jet errors.
      space, task: :class:`Space`, :class:`Task` (or their strings).
      branch: +1 or -1 (dynamic laws; the reference's branch, ``ctrl.reference_branch``).
      t0: initial time [s].
      rest: static laws at torque level: zero wheel velocities.
      jet: dynamic laws: the reference's output jet ((>= r, m)) to place against instead of
        the reference's at ``t0`` (the saturation-free radius places against a jet seen from
        turned axes, or an enclosure of it).

    Returns:
      The controller's state, shape (ctrl.n_state,).
    """
    t0 = jnp.asarray(t0, jnp.result_type(float))
    d = jnp.asarray(error, t0.dtype)
    if isinstance(ctrl, DynamicLinearization):
        r = ctrl.relative_degree
        zeta = (ctrl.reference_jet(t0, params) if jet is None else jet)[:r]
        if Space(space) == Space.OUTPUT:
            if d.shape[0] == r * ctrl.m:  # the whole error jet
                return ctrl.inverse_psi(zeta + d.reshape(r, ctrl.m), params, branch)
            zeta = zeta.at[0, 0].add(d[0]).at[0, 1].add(d[1])
            if r >= 2:
                zeta = zeta.at[1, 0].add(d[2]).at[1, 1].add(d[3])
            return ctrl.inverse_psi(zeta, params, branch)
        return ctrl.inverse_psi(zeta, params, branch).at[: ctrl.robot.n_state].add(d)
    return _place_static(ctrl, params, d, Task(task), t0, rest)


def _place_static(ctrl, params, d, task, t0, rest):
    ref, g = params.reference, params.geometry
    post = ref.posture(t0)
    steer = _steering(ctrl, params, t0)
    X = jnp.concatenate([jnp.zeros(2, t0.dtype), post[2:3], steer])
    X = X.at[2:].add(d[2:])
    offset = ctrl.law.outputs(X, g)[:2]  # the tracked point relative to (x, y)
    target = ref.position(t0) if task == Task.POINT else post[:2]
    X = X.at[:2].set(target + d[:2] - (offset if task == Task.POINT else 0.0))
    if ctrl.level != Level.TORQUE:
        return X
    if rest:
        return jnp.concatenate([X, jnp.zeros(ctrl.robot.n_input, X.dtype)])
    vl = controller(Law.STATIC, ctrl.robot.name, Level.VELOCITY, task)
    u = vl.law.solve_top(X, vl.reference_jet(t0, params)[1], g)  # output velocity = the reference's
    return ctrl.physical_state(X, u, params)


def _steering(ctrl, params, t0):
    """The initial steering angles: the steering reference's where the law has one, else 0."""
    n = ctrl.robot.delta_s
    b = (
        jnp.reshape(params.steering(t0), (-1,))
        if getattr(params, "steering", None) is not None
        else jnp.zeros((0,), t0.dtype)
    )
    # (1,2): beta1 free (0), beta2 the steering reference; (2,1): beta the steering reference
    return jnp.concatenate([jnp.zeros(n - b.shape[0], t0.dtype), b]) if b.shape[0] < n else b[:n]


# --- the sections ------------------------------------------------------------------------------


def controller(law, kind: str, level, task):
    """The controller of a law, robot type, level and task (ProblemError if there is none)."""
    try:
        if Law(law) == Law.DYNAMIC:
            return dynamic_linearization(kind, str(level))
        return controllers.controller(kind, level=str(level), task=str(task))
    except ValueError as err:
        raise ProblemError(f"[controller]: {err}") from None


def _settings(data: dict, base: Path, case) -> list:

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
    if not (isinstance(noise, list) and len(noise) <= nX and all(_is_number(v) and v >= 0 for v in noise)):
        raise ProblemError(
            f"[plant] noise_std: expected a list of at most {nX} numbers >= 0 (std of x, y [m], "
            f"theta [rad] and steering angles [rad] as measured), got {noise!r}"
        )
    if any(noise) and period is None:
        raise ProblemError("[plant] noise_std: measurement noise needs a digital controller (control_period [s])")
    seed = integer("plant", "noise_seed", ps.get("noise_seed", 0), 0, 2**32 - 1)
    return Axis("plant", columns, cols), period, tuple(float(v) for v in noise), seed


def reference_axis(rs, base: Path, law, kind, path_order: int, horizon: float | None = None):
    """``(axis, references)`` of a ``[reference]`` section: the references (their heading offsets
    applied; offsets fastest) and their columns. A sampled path's spline keeps the law's
    ``path_order`` (its ``ctrl.path_order``) continuous; a horizon [s] past its samples (without
    ``extrapolate``) is refused before the spline is built."""
    if not isinstance(rs, dict) or "family" not in rs:
        raise ProblemError(f"[reference]: needs family = one of {list(R.FAMILIES)}")
    fam = R.FAMILIES[choice("reference", "family", rs["family"], tuple(R.FAMILIES))]
    build = (
        _named_references if fam.kind == "named" else _random_references if fam.kind == "random" else _data_reference
    )
    if build is _data_reference:
        refs, cols = _data_reference(fam, rs, base, law, path_order, horizon)
    else:
        refs, cols = build(fam, rs, base, law, path_order)
    params = jax.tree_util.tree_map(lambda *xs: np.stack([np.asarray(x) for x in xs]), *[r.params for r in refs])
    heading = axis_values("reference", "heading_offset", rs.get("heading_offset", _default_offset(law, kind)))
    ii, jj = np.indices((len(refs), len(heading))).reshape(2, -1)
    refs = [r.with_heading_offset(float(h)) for r in refs for h in heading]
    cols = {k: v[ii] for k, v in cols.items()} | {"reference_heading_offset": heading[jj]}
    payload = {"reference": jax.tree_util.tree_map(lambda x: x[ii], params), "heading_offset": heading[jj]}
    return Axis("reference", cols, payload), refs


COMMON_REFERENCE_KEYS = ("family", "heading_offset")


def _named_references(fam, rs, base, law, path_order):
    del path_order  # a named family's path is smooth
    check_keys("reference", rs, COMMON_REFERENCE_KEYS + ("options",))
    defaults = fam.options()
    given = rs.get("options", {})
    check_keys("reference.options", given, tuple(defaults))
    vals = {}
    for k, v in given.items():
        vec = len(defaults[k]) if isinstance(defaults[k], tuple) else None
        vals[k] = axis_values("reference.options", k, v, vector=vec)
    grid = product(vals) if vals else {}
    count = len(next(iter(grid.values()))) if grid else 1
    refs = []
    for i in range(count):
        kw = {k: (tuple(v[i]) if np.ndim(v) == 2 else float(v[i])) for k, v in grid.items()}
        try:
            refs.append(fam.make(**kw))
        except (ValueError, TypeError) as err:
            raise ProblemError(f"[reference.options] {kw}: {err}") from None
    cols = {}
    for k, v in grid.items():
        if np.ndim(v) == 2:
            cols |= {f"reference_{k}_{j}": v[:, j] for j in range(v.shape[1])}
        else:
            cols[f"reference_{k}"] = v
    return refs, cols or {"reference_index": np.zeros(1)}


def random_options(rs) -> dict:
    """The options of a random family (``[reference] options``) over its defaults, checked."""
    opts = R.FAMILIES["random_smooth"].options()
    given = rs.get("options", {})
    check_keys("reference.options", given, tuple(opts))
    for k, v in given.items():
        if k == "n_modes":
            opts[k] = integer("reference.options", k, v, 1)
        elif not _is_number(v) or (k != "start_scale" and v <= 0) or v < 0:
            raise ProblemError(
                f"[reference.options] {k}: expected a number {'>= 0' if k == 'start_scale' else '> 0'}, got {v!r}"
            )
        else:
            opts[k] = float(v)
    if not 0 < opts["min_speed"] < opts["speed"]:
        raise ProblemError(f"[reference.options]: need 0 < min_speed < speed, got {opts['min_speed']}, {opts['speed']}")
    return opts


def _random_references(fam, rs, base, law, path_order):
    del path_order  # a random family's path is smooth

    check_keys("reference", rs, COMMON_REFERENCE_KEYS + ("count", "seed", "options"))
    count = integer("reference", "count", rs.get("count", 1), 1)
    seed = integer("reference", "seed", rs.get("seed", 0), 0)
    opts = random_options(rs)
    batch = _draw_references(fam.make, tuple(sorted(opts.items())), seed, count)
    params = jax.tree_util.tree_map(np.asarray, batch.params)
    refs = [
        R.Reference(jax.tree_util.tree_map(lambda x: jnp.asarray(x[i]), params), 0.0, batch.path, fam.name)
        for i in range(count)
    ]
    return refs, {"reference_index": np.arange(count, dtype=float)}


# level 1 of XLA's backend optimization: a shorter compile than the default's, the same bits
# (level 0 changes the draws' last bits, hence the references)
@functools.partial(jax.jit, static_argnums=(0, 1, 2, 3), compiler_options={"xla_backend_optimization_level": 1})
def _draw_references(make, opts: tuple, seed: int, count: int):
    """``count`` references of a random family, one program (eagerly, each of the draw's small
    operations compiled on its first use took seconds)."""
    keys = jax.random.split(jax.random.PRNGKey(seed), count)
    return jax.vmap(lambda k: make(k, **dict(opts)))(keys)


def _data_reference(fam, rs, base, law, path_order, horizon=None):
    """A reference through the user's samples (t, x, y) or waypoints (x, y), from a file or arrays:
    the spline of the lowest degree that keeps the law's ``path_order`` continuous. Samples whose
    times end before ``horizon`` are refused first (:func:`wmrjax.references.check_span`)."""
    cols = fam.columns
    waypoints = "t" not in cols
    extra = ("speed", "t0") if waypoints else ()
    check_keys(
        "reference", rs, COMMON_REFERENCE_KEYS + ("file", "min_speed", "extrapolate", "source_file") + cols + extra
    )
    if ("file" in rs) == any(c in rs for c in cols):
        raise ProblemError(
            f'[reference] family = "{fam.name}": give file = "path.csv" (columns {", ".join(cols)}) '
            f"or the arrays {', '.join(cols)} = [...], not both"
        )
    if "file" in rs:
        f = rs["file"]
        if not isinstance(f, str):
            raise ProblemError(
                f"[reference] file: expected one path (relative to the problem file) of a CSV with "
                f"columns {', '.join(cols)}, got {f!r}"
            )
        data = _read_csv(base / f, cols)
        name = Path(f).stem
    else:
        data = {c: axis_values("reference", c, rs.get(c, []), axis=False) for c in cols}
        n = {len(v) for v in data.values()}
        if len(n) != 1:
            raise ProblemError(
                f"[reference] {', '.join(cols)}: arrays of different lengths {[len(data[c]) for c in cols]}"
            )
        name = fam.name
    default_speed = 1e-3 if Law(law) == Law.DYNAMIC else None
    min_speed = rs.get("min_speed", default_speed)
    if min_speed is not None:
        min_speed = positive("reference", "min_speed", min_speed)
    extrapolate = rs.get("extrapolate", False)
    if not isinstance(extrapolate, bool):
        raise ProblemError(
            f"[reference] extrapolate: expected true or false (extend the path past its first and "
            f"last point), got {extrapolate!r}"
        )
    where = f"[reference] {'file ' + repr(rs['file']) if 'file' in rs else cols}"
    if not waypoints and not extrapolate and horizon is not None:
        t = np.asarray(data["t"], float)
        # only well-formed times here (strictly increasing, finite): from_samples names the others
        if t.size >= 2 and np.all(np.isfinite(t)) and np.all(np.diff(t) > 0):
            try:
                R.check_span(name, float(t[0]), float(t[-1]), 0.0, horizon)
            except ValueError as err:
                raise ProblemError(f"{where}: {err}") from None
    xy = np.stack([data["x"], data["y"]], axis=1)
    degree = spline_degree_for(path_order)
    try:
        if waypoints:
            ref = fam.make(
                xy,
                speed=positive("reference", "speed", rs.get("speed", 1.0)),
                t0=float(rs.get("t0", 0.0)),
                min_speed=min_speed,
                name=name,
                extrapolate=extrapolate,
                degree=degree,
            )
        else:
            ref = fam.make(data["t"], xy, min_speed=min_speed, name=name, extrapolate=extrapolate, degree=degree)
    except ValueError as err:
        raise ProblemError(f"{where}: {err}") from None
    return [ref], {"reference_index": np.zeros(1)}


def _read_csv(path: Path, cols: tuple) -> dict:
    """The named columns of a CSV file with a header line (:func:`wmrjax.io.read_csv_columns`)."""
    try:
        return io.read_csv_columns(path, cols, "[reference] file")
    except ValueError as err:
        raise ProblemError(str(err)) from None


def _default_offset(law, kind):
    if Law(law) == Law.DYNAMIC:
        return float(controllers.TABLE4[kind].default_heading_offset)
    return 0.0


# --- gains ---------------------------------------------------------------------------------------

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


# --- initial conditions --------------------------------------------------------------------------


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
    """key -> (low, high) of the initial errors' distribution: a ``{ low, high }`` range or a
    fixed number (low = high)."""
    out = {}
    for k in keys:
        v = ins.get(k, 0.0)
        if isinstance(v, dict):
            if (
                set(v) != {"low", "high"}
                or not (_is_number(v["low"]) and _is_number(v["high"]))
                or not v["high"] >= v["low"]
            ):
                raise ProblemError(f"[initial] {k}: a random range is {{ low = a, high = b }} with b >= a, got {v!r}")
            out[k] = (float(v["low"]), float(v["high"]))
        elif _is_number(v):
            out[k] = (float(v), float(v))
        else:
            raise ProblemError(
                f"[initial] {k}: with random draws, expected a number or {{ low = a, high = b }}, got {v!r}"
            )
    return out


def unravel(setting: Setting, start: int, n: int) -> list:
    """Per-axis value indices of runs ``start .. start + n - 1`` of ``setting`` (last axis fastest)."""
    return list(np.unravel_index(np.arange(start, start + n), setting.shape))


def columns_of(setting: Setting, idx: list) -> dict:
    out = {}
    for a, i in zip(setting.axes, idx):
        for k, v in a.columns.items():
            out[k] = np.asarray(v)[i]
    return out
