"""The identification job (``wmrjax identify``): the logs read and checked, the plant fitted
(:func:`wmrjax.identify.identify`), held-out logs predicted, and ``summary.json``,
``plant.toml``/``problem.toml`` (the problem with the identified ``[plant]``) and a figure
written."""

from __future__ import annotations

import dataclasses
import time
import tomllib
from pathlib import Path

import jax
import numpy as np

from wmrjax import _files as files
from wmrjax import identify as I
from wmrjax import io
from wmrjax.problem import Problem
from wmrjax.report import JobReport


@dataclasses.dataclass(frozen=True)
class IdentifyReport(JobReport):
    """What :func:`run` identified and wrote.

    Attributes:
        problem: the problem whose plant was identified.
        identification: the fit (:class:`wmrjax.identify.Identification`: estimates with their
            intervals, residuals, the segments).
        holdout: per held-out log's name, the RMS prediction error per channel of the identified
            and of the nominal plant (``{"identified_rms": {...}, "nominal_rms": {...}}``).
        plant_section: the identified ``[plant]`` section (TOML text, as in ``plant.toml``).
        files: the files written into the output directory.
        problem_toml_not_written: why ``problem.toml`` was not written (``None``: it was).
        wall_time_s: the job's wall time [s].
    """

    problem: Problem
    identification: I.Identification
    holdout: dict
    plant_section: str
    files: tuple
    problem_toml_not_written: str | None
    wall_time_s: float

    def summary(self) -> dict:
        """``summary.json`` (plain JSON)."""
        s = {
            "experiment": "identify",
            "problem_name": self.problem.title,
            "problem": self.problem.resolved(),
            **self.identification.summary(),
        }
        if self.holdout:
            s["holdout"] = self.holdout
        if self.problem_toml_not_written is not None:
            s["problem_toml_not_written"] = self.problem_toml_not_written
        return files.jsonable(s | {"files": list(self.files), "wall_time_s": self.wall_time_s})


def run(
    out: Path, problem: Problem, logs, *, holdout=(), period=None, segment=2.0, max_delay=0, progress=None
) -> IdentifyReport:
    """Identify the plant of ``problem`` (loaded from its file) from ``logs``; write into ``out``.

    Args:
        out: the output directory (``Path``; it exists).
        problem: the problem (:class:`wmrjax.problem.Problem`, loaded from a file: its text is
            copied with the identified ``[plant]`` into ``problem.toml``).
        logs: the logs to fit (paths to CSV or Parquet files).
        holdout: logs to predict, not fitted (paths).
        period: the controller period [s] the logs' inputs were held over (default: the problem's).
        segment: the length of the segments the logs are cut into [s].
        max_delay: the largest input delay searched [samples].
        progress: called with each progress message (default: printed).

    Returns:
        the :class:`IdentifyReport`.
    """
    say = progress or (lambda msg: print(msg, flush=True))
    jax.config.update("jax_enable_x64", True)  # the job runs in float64
    t0 = time.time()
    model = I.sections.plant_model(problem.setting("identify"), period)
    fit_logs, held = ([read_log(p, model.robot) for p in paths] for paths in (logs, holdout))
    options = I.FitOptions(segment=segment, max_delay=max_delay)
    say(
        f"identify a {model.robot.name} robot ({model.level}) from {len(fit_logs)} log(s), {sum(len(x.t) for x in fit_logs)} samples"
    )
    ident = I.identify(model, fit_logs, options)
    predicted = {}
    if held:
        say(f"predict {len(held)} held-out log(s)")
        predicted = _holdout(ident, held)
    plant = problem.resolved().get("plant", {})
    section = I.sections.plant_section(ident, plant, ", ".join(Path(p).name for p in logs))
    files.write_bytes(out / "plant.toml", section.encode())
    written, not_written = ["summary.json", "plant.toml", "paths.png"], None
    text = I.sections.with_plant_section(io.read_small_text(problem.source, "problem file"), section)
    try:  # the problem with the identified plant, if it loads from --out (relative paths may not)
        Problem.from_dict(tomllib.loads(text), base=out.resolve())
        files.write_bytes(out / "problem.toml", text.encode())
        written.append("problem.toml")
    except ValueError as err:
        not_written = f"{err}; put plant.toml's section into the problem file instead"
    _figure(ident, out / "paths.png")
    report = IdentifyReport(problem, ident, predicted, section, tuple(written), not_written, time.time() - t0)
    report.write_summary(out)
    return report


def read_log(path: Path, robot):
    """A CSV log, or a Parquet one (by its ``.parquet`` suffix)."""
    path = Path(path)
    if path.suffix != ".parquet":
        return I.read_log(path, robot)
    data, header = files.read_parquet_columns(path, I.columns(robot), f"log of a {robot.name} robot")
    return I.log_from_columns(path.name, data, header, robot)


def _holdout(ident, logs) -> dict:
    fitted = I.prediction_error(ident, logs)
    nominal = I.prediction_error(ident, logs, theta=np.ones(len(ident.model.names)))
    ch = ident.model.channels
    return {
        log.name: {"identified_rms": dict(zip(ch, map(float, a))), "nominal_rms": dict(zip(ch, map(float, b)))}
        for log, a, b in zip(logs, fitted, nominal)
    }


def _figure(ident, path: Path) -> None:
    plt = files.headless_pyplot()
    n = len(ident.log_names)
    fig, axes = plt.subplots(1, n, figsize=(5 * n, 4.5), squeeze=False)
    seg = ident.segments
    for j, ax in enumerate(axes[0]):
        rows = np.flatnonzero(seg.log == j)
        for k, g in enumerate(rows):
            m = seg.mask[g] > 0
            ax.plot(*seg.measured[g, m, :2].T, ".", ms=2, color="0.6", label="logged" if k == 0 else None)
            ax.plot(
                *ident.predicted[g, m, :2].T, "-", lw=1, color="C0", label="fitted (per segment)" if k == 0 else None
            )
        ax.set(xlabel="x [m]", ylabel="y [m]", title=f"{ident.log_names[j]}: logged and fitted paths", aspect="equal")
        ax.legend(loc="best", fontsize=8)
    files.write_png(fig, path)
    plt.close(fig)
