"""The ``[reference]`` section: a named family with its options (an axis), draws of a random
family, or the user's samples or waypoints (a file or arrays), each with heading offsets.
"""

from __future__ import annotations

import functools
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from wmrjax import controllers
from wmrjax import references as R
from wmrjax.problem.schema import (
    Law,
    ProblemError,
    axis_values,
    check_keys,
    choice,
    integer,
    is_number,
    positive,
    product,
    read_csv,
)
from wmrjax.problem.setting import Axis
from wmrjax.references import spline_degree_for


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
        elif not is_number(v) or (k != "start_scale" and v <= 0) or v < 0:
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
        data = read_csv(base / f, cols)
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


def _default_offset(law, kind):
    if Law(law) == Law.DYNAMIC:
        return float(controllers.TABLE4[kind].default_heading_offset)
    return 0.0


def family_of(ref):
    """The registry's family a ``[reference]`` section names (None if it names none)."""
    return R.FAMILIES.get(ref.get("family")) if isinstance(ref, dict) else None
