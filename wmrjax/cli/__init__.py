"""The ``wmrjax`` command: ``wmrjax JOB PROBLEM --out DIR [options]`` (installed with the ``cli``
extra, ``pip install "wmrjax[cli]"``; ``python -m wmrjax`` is the same command).

Each job is a module of this package with a ``main(argv) -> int``: it parses its options, calls
one library function (``wmrjax.sweep``, ``wmrjax.tune``, ``wmrjax.certify``, ``wmrjax.export``,
``wmrjax.identify``) and writes what it returns. What they share:

* :mod:`wmrjax.cli.options` -- the shared parser (``--out``, the compilation cache,
  ``--verbose``), option types that refuse bad values at parse time, the output directory
  prepared before any work, a heartbeat, and the exit statuses (2: a bad option, 1: an
  error of the work);
* :mod:`wmrjax._files` -- atomic JSON/NPZ/PNG/Parquet writers, JSON checkpoints and one
  writer per output directory.

The library never imports this package.
"""

from __future__ import annotations

import importlib
import importlib.util
import sys

__all__ = ["JOBS", "main"]

JOBS = {
    "sweep": ("wmrjax.cli.sweep", "run a problem from many starts: one row per run in runs.parquet"),
    "tune": ("wmrjax.cli.tune", "tune the gains by gradient descent, against CMA-ES and random search"),
    "certify": ("wmrjax.cli.certify", "certified regions: Lemma 2, the exact map, rollouts and the falsifier"),
    "export": ("wmrjax.cli.export", "the controller as C99 and a jax.export artifact, checked against the simulator"),
    "identify": ("wmrjax.cli.identify", "the plant's geometry and input scales from logs, with 95 % intervals"),
    "study": ("wmrjax.cli.study", "gradient tuning against CMA-ES, Optuna and random search at equal compute"),
    "pareto": ("wmrjax.cli.pareto", "the front of tracking loss against a required certified radius"),
    "plant-table": ("wmrjax.cli.plant_table", "the nominal certificate on the problem's own loop, feature by feature"),
}
"""Job name -> (module, one line of help)."""

# The jobs write figures and tables at the end of their work: without the extra they would
# compute for minutes and then fail on an import. Say so before anything runs.
_CLI_EXTRA = ("matplotlib", "pyarrow", "cmaes", "optuna")


def _usage() -> str:
    width = max(map(len, JOBS))
    jobs = "\n".join(f"  {name:<{width}}  {about}" for name, (_, about) in JOBS.items())
    return (
        "usage: wmrjax JOB [PROBLEM] [--out DIR] [--set KEY=VALUE ...] [options]\n\n"
        "Wheeled mobile robots under feedback-linearizing control: one problem file, these jobs.\n\n"
        f"jobs:\n{jobs}\n\n"
        "PROBLEM is a problem file (TOML) or a shipped example (wmrjax.examples: s_path, section_6_1, ...).\n"
        "wmrjax JOB --help lists a job's options."
    )


def _check_extra() -> None:
    missing = [
        name
        for name in _CLI_EXTRA
        if (sys.modules[name] is None if name in sys.modules else importlib.util.find_spec(name) is None)
    ]
    if missing:
        raise SystemExit(
            f"wmrjax: error: the jobs need {', '.join(missing)}: install them with "
            'pip install "wmrjax[cli]" (the library alone, wmrjax, needs only jax, numpy and optax)'
        )


def main(argv=None) -> int:
    """Run ``wmrjax JOB ...``.

    Args:
      argv: the arguments after the program name (default ``sys.argv[1:]``).

    Returns:
      The job's exit status: 0 done, 1 the work failed, 2 a bad option.
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(_usage())
        return 0 if argv else 2
    if argv[0] == "--version":
        from wmrjax import __version__  # the package above this one: read only when asked

        print(f"wmrjax {__version__}")
        return 0
    job, rest = argv[0], argv[1:]
    if job not in JOBS:
        print(_usage(), file=sys.stderr)
        print(f"\nwmrjax: error: unknown job {job!r}: choose one of {', '.join(JOBS)}", file=sys.stderr)
        return 2
    _check_extra()
    sys.argv[0] = f"wmrjax {job}"  # argparse's prog: usage and errors name the job
    return importlib.import_module(JOBS[job][0]).main(rest)
