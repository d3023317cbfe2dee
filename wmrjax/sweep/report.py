"""What a finished sweep reports: ``summary.json`` (counts, fractions, quantiles, certified
radii) and the figures -- outcome maps over every pair of swept quantities and histograms of
final errors and margins -- read back from ``runs.parquet``."""

from __future__ import annotations

import dataclasses
import itertools
import re
import time
from pathlib import Path

import numpy as np

from wmrjax import _files, _math, certify
from wmrjax.problem import Task
from wmrjax.report import JobReport
from wmrjax.sweep import run
from wmrjax.sweep import spec as S
from wmrjax.sweep.run import OUTCOMES

COLORS = {"converged": "#2ca02c", "not_converged": "#ff7f0e", "singular": "#d62728", "failed": "#7f7f7f"}
# "failed": non-finite or inaccurate (the step's error estimate above error_tol), not singular
LABELS = {
    "converged": "converged",
    "not_converged": "not converged",
    "singular": "singular",
    "failed": "failed (inaccurate or non-finite)",
}
MAX_MAPS = 12  # maps of a one-group sweep
MAX_MAPS_PER_GROUP = 3  # and per group of a sweep over several types or levels
UNITS = {
    "initial_error_x": "m",
    "initial_error_y": "m",
    "initial_error_vx": "m/s",
    "initial_error_vy": "m/s",
    "initial_error_theta": "rad",
    "initial_error_beta": "rad",
    "initial_error_beta1": "rad",
    "initial_error_beta2": "rad",
    "geometry_L": "m",
    "geometry_e": "m",
    "geometry_delta": "rad",
    "gains_poles": "1/s",
    "gains_omega": "rad/s",
    "reference_heading_offset": "rad",
    "reference_radius": "m",
    "reference_omega": "rad/s",
    "reference_size": "m",
}


def label(col: str) -> str:
    """The column name with its unit, for a figure's axis."""
    unit = UNITS.get(col)
    return f"{col} [{unit}]" if unit else col


def read_table(path: Path, columns=None) -> dict:
    """The columns ``columns`` (all: None) of a Parquet table as NumPy arrays."""
    import pyarrow.parquet as pq  # optional dependency (the cli extra): only the Parquet table needs it

    t = pq.read_table(path, columns=columns)
    return {name: t.column(name).to_numpy(zero_copy_only=False) for name in t.column_names}


def columns_needed(plan: S.Plan) -> list:
    """The columns the summary and the figures read back (not the whole table)."""
    cases = ["case"] if any(g.case is not None for g in plan.groups) else []
    return [
        "run",
        *cases,
        "robot",
        "level",
        *[c for c in plan.swept if c not in ("case", "robot", "level")],
        "outcome",
        "failed",
        "inaccurate",
        "final_position_error",
        "final_heading_error",
        "min_margin",
        "min_distance",
    ]


def quantiles(a) -> dict:
    """Quantiles of the finite values of ``a``, and their minimum."""
    a = np.asarray(a, float)
    a = a[np.isfinite(a)]
    return _math.quantiles(a) | ({"min": float(a.min())} if a.size else {})


def summarize(plan: S.Plan, table: dict, certified: dict) -> dict:
    """The sweep's ``summary.json`` from its table and the certified radii."""
    n = len(table["run"])
    counts = {o: int(np.sum(table["outcome"] == o)) for o in OUTCOMES}
    ok = ~table["failed"]
    out = {
        "runs": n,
        "counts": counts,
        "fractions": {o: (c / n if n else None) for o, c in counts.items()},
        "converged_definition": (
            f"regular run with final position error <= {plan.position_tol} m"
            + (f" and heading error <= {plan.heading_tol} rad" if plan.task == Task.POSTURE else "")
        ),
        "quantiles_regular_runs": {
            "final_position_error_m": quantiles(table["final_position_error"][ok]),
            "final_heading_error_rad": quantiles(table["final_heading_error"][ok]),
            "min_margin": quantiles(table["min_margin"][ok]),
        },
        "fraction_flagged_inaccurate": float(np.mean(table["inaccurate"])) if n else None,
    }
    if plan.law == "dynamic":
        out["quantiles_regular_runs"]["min_distance"] = quantiles(table["min_distance"][ok])
    groups = {}
    for g in plan.groups:
        sel = select(table, g)
        groups[group_name(g)] = {
            "runs": int(sel.sum()),
            **{o: int(np.sum(sel & (table["outcome"] == o))) for o in OUTCOMES},
        }
    out["by_group"] = groups
    if certified:  # one group: its radii; several: by group
        out["certified_radii"] = next(iter(certified.values())) if len(plan.groups) == 1 else certified
    return out


def file_part(label: str) -> str:
    """A case's name as part of a file name: a problem file's names are checked labels
    (:data:`wmrjax.problem.CASE_NAME`); anything else a path could read is replaced, never used."""
    return re.sub(r"[^A-Za-z0-9_.+-]", "_", label).lstrip(".") or "_"


def group_name(g) -> str:
    """``"(2,0) velocity"``, prefixed by the case's name (``"tuned: (2,0) velocity"``)."""
    name = f"{g.ctrl.robot.name} {g.ctrl.level}"
    return name if g.case is None else f"{g.case}: {name}"


def select(table: dict, g):
    """The rows of group ``g``."""
    sel = (table["robot"] == g.ctrl.robot.name) & (table["level"] == str(g.ctrl.level))
    return sel & (table["case"] == g.case) if g.case is not None else sel


def certified_radii(plan: S.Plan) -> dict:
    """Certified radii of the position slice (group name -> radii) for every group that is one
    dynamic closed loop (one geometry, reference and gains; no plant) swept over initial output
    errors."""
    if not (plan.law == "dynamic" and plan.space == "output"):
        return {}
    out = {}
    for g in plan.groups:
        geo, _, ref, gains, _ = g.axes
        if g.plant or geo.size != 1 or ref.size != 1 or gains.size != 1:
            continue
        ctrl, params = g.ctrl, g.params()
        eps = 0.01
        radii = {"eps": eps}
        rep = certify.lemma2(ctrl, params, t_final=plan.t_final, eps=eps)
        for name, c in rep.certificates().items():
            if c is not None:
                radii[f"lemma2_{name}"] = float(c.radius)
        try:
            radii["exact_map_position_slice"] = float(
                certify.exact_map_radius(
                    ctrl, params, t_final=plan.t_final, eps=eps, basis=certify.Slice.POSITION
                ).radius
            )
        except ValueError as err:  # (1,2): curved singular set
            radii["exact_map_note"] = str(err)
        out[group_name(g)] = radii
    return out


def _determines(table, a, c) -> bool:
    """Whether column ``c`` is a function of column ``a`` (e.g. two entries of one limit vector)."""
    pairs = np.unique(np.stack([table[a], table[c]], axis=1), axis=0)
    return len(pairs) == len(np.unique(table[a]))


def _edges(v):
    """Cell edges around sorted grid values."""
    if len(v) == 1:
        return np.array([v[0] - 0.5, v[0] + 0.5])
    mid = 0.5 * (v[1:] + v[:-1])
    return np.concatenate([[2 * v[0] - mid[0]], mid, [2 * v[-1] - mid[-1]]])


def figures(plan: S.Plan, table: dict, certified: dict, out: Path) -> list:
    """The sweep's figures (PNG) written under ``out``; returns their file names."""
    plt = _files.headless_pyplot()
    written = []
    for old in out.glob("map_*.png"):  # an earlier run's maps (other quantities) must not linger
        old.unlink()
    numeric, random_cols, pairs = _map_pairs(plan, table)
    for g in plan.groups:
        robot, level = g.ctrl.robot.name, str(g.ctrl.level)
        gsel = select(table, g)
        tag = (
            (f"_{file_part(g.case)}" if g.case is not None else "") + f"_{robot.strip('()').replace(',', '')}_{level}"
            if len(plan.groups) > 1
            else ""
        )
        radii = certified.get(group_name(g), {})
        for a, b in pairs:
            sel = gsel.copy()
            fixed = []
            for c in numeric:
                if (
                    c in (a, b)
                    or c in random_cols
                    and (a in random_cols or b in random_cols)
                    or _determines(table, a, c)
                    or _determines(table, b, c)
                ):
                    continue  # c varies with a or b (one vector, one random draw): not fixed
                vals = table[c][gsel]
                if vals.size:
                    v0 = vals[0]
                    sel &= table[c] == v0
                    fixed.append(f"{c} = {v0:.4g}")
            path = out / f"map_{a}_{b}{tag}.png"
            _map_figure(plt, plan, table, g, a, b, sel, fixed, random_cols, radii, path)
            written.append(path.name)
    _histograms(plt, plan, table, out)
    written.append("histograms.png")
    written += _plant_figures(plt, plan, table, out)
    return written


def _plant_figures(plt, plan: S.Plan, table: dict, out: Path) -> list:
    """``plant_<column>.png`` for each plant column a sweep varies (a geometry or input-scale
    range, a limit): the final position error of every regular run at each value, per group, so
    "does it track under +-5 % geometry" is read off a figure, not the table."""
    ok = ~table["failed"]
    written = []
    for col in sorted(c for c in table if c.startswith("plant_")):
        values = np.unique(np.asarray(table[col], float)[ok])
        if values.size < 2:
            continue
        fig, ax = plt.subplots(figsize=(7, 4))
        width = 0.8 * float(np.min(np.diff(values)))
        for k, (g, c) in enumerate(zip(plan.groups, itertools.cycle([f"C{i}" for i in range(10)]))):
            sel = ok & select(table, g)
            err = np.maximum(np.asarray(table["final_position_error"], float)[sel], 1e-16)
            x = np.asarray(table[col], float)[sel] + (k - 0.5 * (len(plan.groups) - 1)) * 0.1 * width
            ax.scatter(x, err, s=8, alpha=0.5, color=c, label=group_name(g))
            med = [np.median(err[x == v]) if np.any(x == v) else np.nan for v in np.unique(x)]
            ax.plot(np.unique(x), med, color=c, marker="_", markersize=14, linestyle="none")
        ax.set_yscale("log")
        ax.set_xlabel(label(col))
        ax.set_ylabel("final position error [m] (bars: median)")
        ax.set_title(f"{plan.problem.title}: tracking error per {label(col)}", fontsize=9)
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7)
        fig.tight_layout()
        name = f"plant_{col.removeprefix('plant_')}.png"
        _files.write_png(fig, out / name)
        plt.close(fig)
        written.append(name)
    return written


def _map_pairs(plan: S.Plan, table: dict):
    """``(numeric columns, random columns, pairs to map)``: one map axis per quantity (a column in
    one-to-one correspondence with an earlier one dropped; random draws of several columns are
    one-to-one by construction: kept, and mapped as scatter plots), initial errors first."""
    numeric = [c for c in plan.swept if c not in ("case", "robot", "level")]
    random_cols = {c for g in plan.groups for a in g.axes[-1:] if a.random for c in a.columns}  # the initial axis
    numeric = [
        c
        for i, c in enumerate(numeric)
        if c in random_cols or not any(_determines(table, q, c) and _determines(table, c, q) for q in numeric[:i])
    ]
    pairs = [
        (a, b)
        for a, b in itertools.combinations(numeric, 2)
        if {a, b} <= random_cols or not (_determines(table, a, b) or _determines(table, b, a))
    ]
    # initial errors first (x against y above all), then the rest in the file's order
    pairs.sort(
        key=lambda ab: (
            -sum(c.startswith("initial_error_") for c in ab) - 2 * (ab == ("initial_error_x", "initial_error_y"))
        )
    )
    return numeric, random_cols, pairs[: MAX_MAPS if len(plan.groups) == 1 else MAX_MAPS_PER_GROUP]


def _map_figure(
    plt, plan: S.Plan, table: dict, g, a: str, b: str, sel, fixed: list, random_cols, radii: dict, path: Path
) -> None:
    """One outcome map of columns ``a`` against ``b`` over the runs ``sel`` (cells on a full grid,
    points otherwise), the certified circles on the initial-position plane."""
    robot, level = g.ctrl.robot.name, str(g.ctrl.level)
    fig, ax = plt.subplots(figsize=(6.4, 5.6))
    xa, yb, oc = table[a][sel], table[b][sel], table["outcome"][sel]
    ux, uy = np.unique(xa), np.unique(yb)
    grid = a not in random_cols and b not in random_cols and len(xa) == len(ux) * len(uy) > 1
    if grid and len(ux) > 1 and len(uy) > 1:  # a full grid: cells that touch
        from matplotlib.colors import ListedColormap  # optional dependency (the cli extra): only a figure needs it

        code = np.full((len(uy), len(ux)), np.nan)
        code[np.searchsorted(uy, yb), np.searchsorted(ux, xa)] = [OUTCOMES.index(o) for o in oc]
        ax.pcolormesh(
            _edges(ux),
            _edges(uy),
            code,
            cmap=ListedColormap([COLORS[o] for o in OUTCOMES]),
            vmin=-0.5,
            vmax=len(OUTCOMES) - 0.5,
            shading="flat",
        )
        for o in OUTCOMES:
            m = int(np.sum(oc == o))
            if m:
                ax.scatter([], [], marker="s", c=COLORS[o], label=f"{LABELS[o]} ({m})")
    else:
        for o in OUTCOMES:
            m = oc == o
            if m.any():
                ax.scatter(xa[m], yb[m], s=12, c=COLORS[o], linewidths=0, label=f"{LABELS[o]} ({int(m.sum())})")
    if radii and {a, b} == {"initial_error_x", "initial_error_y"}:
        th = np.linspace(0, 2 * np.pi, 400)
        styles = {
            "lemma2_paper": ("k", ":"),
            "lemma2_lyapunov": ("k", "-."),
            "lemma2_exact_norm": ("k", "--"),
            "exact_map_position_slice": ("b", "-"),
        }
        for name, (col, ls) in styles.items():
            rad = radii.get(name)
            if rad:
                ax.plot(
                    rad * np.cos(th),
                    rad * np.sin(th),
                    color=col,
                    ls=ls,
                    lw=1.2,
                    label=f"{name.replace('_', ' ')}: {rad:.3g} m",
                )
    ax.set_xlabel(label(a))
    ax.set_ylabel(label(b))
    title = (f"{g.case}: " if g.case is not None else "") + f"{robot}, {plan.law} law, {level} level"
    ax.set_title(title + ("\n" + ", ".join(fixed) if fixed else ""), fontsize=9)
    ax.legend(fontsize=7, loc="upper right", framealpha=0.85)
    ax.grid(alpha=0.3)
    if len(ux) > 1 and len(uy) > 1 and {a, b} <= {"initial_error_x", "initial_error_y"}:
        ax.set_aspect("equal")
    fig.tight_layout()
    _files.write_png(fig, path)
    plt.close(fig)


def _histograms(plt, plan: S.Plan, table: dict, out: Path) -> None:
    """``histograms.png``: final position error, min margin (and min distance) of the regular runs, per group."""
    fig, axs = plt.subplots(1, 3 if plan.law == "dynamic" else 2, figsize=(14 if plan.law == "dynamic" else 10, 4))
    ok = ~table["failed"]
    for g, c in zip(plan.groups, itertools.cycle([f"C{i}" for i in range(10)])):
        sel = ok & select(table, g)
        lab = group_name(g)
        axs[0].hist(
            *_hist_args(np.log10(np.maximum(table["final_position_error"][sel], 1e-16))), alpha=0.6, color=c, label=lab
        )
        axs[1].hist(*_hist_args(np.log10(np.maximum(table["min_margin"][sel], 1e-16))), alpha=0.6, color=c, label=lab)
        if plan.law == "dynamic":
            d = table["min_distance"][sel]
            axs[2].hist(*_hist_args(d[np.isfinite(d)]), alpha=0.6, color=c, label=lab)
    axs[0].set_xlabel("log10 final position error [m]")
    axs[1].set_xlabel("log10 min margin |det K| over the run")
    if plan.law == "dynamic":
        axs[2].set_xlabel("min distance to the singular set (output jet) [m/s]")
    for ax in axs:
        ax.set_ylabel("regular runs")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    _files.write_png(fig, out / "histograms.png")
    plt.close(fig)


HIST_BINS = 50


def _hist_args(x):
    """``(values, bins)`` for ``hist``: 50 bins, or one bin around a constant (a static point
    law's |det K| = |e sin(delta)| is the same for every run, up to the last bits, and 50 bins
    over a range of 1e-16 do not exist)."""
    x = np.asarray(x, float)
    if x.size and np.ptp(x) <= 1e-9 * max(1.0, float(np.max(np.abs(x)))):
        mid = float(np.mean(x))
        return x, np.array([mid - 0.5, mid + 0.5])
    return x, HIST_BINS


def header(plan, source: str) -> dict:
    """The sweep's identifying fields, which lead summary.json (``source``: the problem file)."""
    return {
        "sweep": source,
        "title": plan.spec.get("title", Path(source).stem),
        "law": str(plan.law),
        "task": str(plan.task),
        "initial_space": str(plan.space),
        "swept": plan.swept,
        "fingerprint": plan.fingerprint,
        "t_final": plan.t_final,
        "dt": plan.dt,
        "n_steps": plan.n_steps,
        "cases": [c for c, _ in plan.problem.cases() if c is not None],
        "problem": plan.problem.resolved(),
    }


def execution(plan, n_proc: int, n_devices: int, procs: list) -> dict:
    """The execution block of summary.json, from the per-process block stats."""
    computed = sum(s["runs_computed"] for s in procs)
    compute_wall = max(s["wall_s"] for s in procs)
    return {
        "processes": n_proc,
        "devices_per_process": n_devices,
        "block": plan.block,
        "blocks": len(plan.blocks()),
        "runs_computed": computed,
        "runs_resumed": plan.n_runs - computed,
        "compute_wall_s": compute_wall,
        "first_calls_s": max(s["first_calls_s"] for s in procs),
        "throughput_runs_per_s": computed / compute_wall if compute_wall > 0 and computed else None,
        "throughput_trajectory_steps_per_s": computed * plan.n_steps / compute_wall
        if compute_wall > 0 and computed
        else None,
    }


@dataclasses.dataclass(frozen=True)
class SweepReport(JobReport):
    """What a finished sweep found (:func:`wmrjax.sweep.sweep`): its outcomes counted and
    summarized from the table ``runs.parquet``, the certified radii, the figures.

    Attributes:
        plan: the sweep's plan (:func:`wmrjax.sweep.spec.plan`: its groups, runs and blocks).
        source: the problem file, as the user named it.
        table: the path of ``runs.parquet`` (one row per run; :func:`read_table` reads it).
        statistics: the outcomes counted (``counts``, ``fractions``, per group ``by_group``), the
            quantiles of the regular runs' final errors and margins, and the certified radii
            (:func:`summarize`).
        execution: processes, devices, blocks computed and resumed, throughput (:func:`execution`).
        figures: the PNG files written (names in the output directory).
        wall_time_s: the job's wall time [s].
    """

    plan: S.Plan
    source: str
    table: Path
    statistics: dict
    execution: dict
    figures: tuple
    wall_time_s: float

    @property
    def counts(self) -> dict:
        """Runs per outcome (``converged``, ``not_converged``, ``singular``, ``failed``)."""
        return self.statistics["counts"]

    def summary(self) -> dict:
        """``summary.json`` (plain JSON)."""
        s = header(self.plan, self.source) | self.statistics
        s |= {"execution": self.execution, "figures": list(self.figures), "wall_time_s": self.wall_time_s}
        return _files.jsonable(s)


def finish(plan, out: Path, source: str, procs: list, n_devices: int, t_start: float) -> SweepReport:
    """After every block is computed: the table ``runs.parquet``, the certified radii, the figures
    and ``summary.json`` (written atomically).

    Args:
      plan: the sweep's plan (:func:`wmrjax.sweep.spec.plan`).
      out: the output directory.
      source: the problem file, as the user named it.
      procs: each process's block statistics (``blocks/process_<i>.json``).
      n_devices: JAX devices per process.
      t_start: ``time.perf_counter()`` when the job started (for ``wall_time_s``).

    Returns:
      the :class:`SweepReport`.
    """
    path = run.assemble(plan, out)
    table = read_table(path, columns=columns_needed(plan))
    certified = certified_radii(plan)
    statistics = summarize(plan, table, certified)
    drawn = figures(plan, table, certified, out)
    ran = execution(plan, len(procs), n_devices, procs)
    report = SweepReport(plan, source, path, statistics, ran, tuple(drawn), time.perf_counter() - t_start)
    report.write_summary(out)
    return report
