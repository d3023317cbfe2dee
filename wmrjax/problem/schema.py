"""The problem file's schema: its sections, the errors it raises, and the readers every section's
values go through (numbers, axes, grids, choices, tables), each naming the key it refuses.

A section's own parser (:mod:`wmrjax.problem.sections`, :mod:`wmrjax.problem.reference`,
:mod:`wmrjax.problem.gains_file`, a job's ``read_section``) reads its values with these.
"""

from __future__ import annotations

import enum
import math
import re
from pathlib import Path

import numpy as np

from wmrjax import io, resources

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


class Law(enum.StrEnum):
    """The linearizing law: Table 4's dynamic extension or Prop 3 / Table 3's static feedback."""

    DYNAMIC = "dynamic"
    STATIC = "static"


class ProblemError(ValueError):
    """A problem that cannot run: the message names the key and the expected form."""


# --- reading values ----------------------------------------------------------------------------


def _where(section: str, key: str) -> str:
    return f"[{section}] {key}" if section else key


def is_number(v) -> bool:
    """True for a finite int or float (not a bool)."""
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
    """``v`` if it is an integer in [minimum, maximum], else a ProblemError naming ``[section] key``."""
    ok = isinstance(v, int) and not isinstance(v, bool) and v >= minimum and (maximum is None or v <= maximum)
    if not ok:
        bound = f">= {minimum}" + (f" and <= {maximum}" if maximum is not None else "")
        raise ProblemError(f"{_where(section, key)}: expected an integer {bound}, got {v!r}")
    return v


def positive(section: str, key: str, v) -> float:
    """``v`` as a float if it is a finite number > 0, else a ProblemError naming ``[section] key``."""
    if not (is_number(v) and v > 0):
        raise ProblemError(f"{_where(section, key)}: expected a number > 0, got {v!r}")
    return float(v)


def nonnegative(section: str, key: str, v) -> float:
    """``v`` as a float if it is a finite number >= 0, else a ProblemError naming ``[section] key``."""
    if not (is_number(v) and v >= 0):
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


def read_csv(path: Path, cols: tuple) -> dict:
    """The named columns of a CSV file with a header line (:func:`wmrjax.io.read_csv_columns`)."""
    try:
        return io.read_csv_columns(path, cols, "[reference] file")
    except ValueError as err:
        raise ProblemError(str(err)) from None
