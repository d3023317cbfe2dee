"""Batch sweeps from a declarative TOML file: ``wmrjax sweep SPEC.toml --out DIR``, or
:func:`sweep` from Python.

* :mod:`wmrjax.sweep.spec` -- the file format, validated before anything compiles;
* :mod:`wmrjax.sweep.run` -- blocks of runs on every local device, resumable, several
  processes through ``jax.distributed``, the table streamed into ``runs.parquet``;
* :mod:`wmrjax.sweep.report` -- ``summary.json``, outcome maps and histograms
  (:class:`SweepReport`);
* :mod:`wmrjax.sweep.job` -- the job: :func:`sweep` (one process), :func:`~wmrjax.sweep.job.start`
  and :func:`~wmrjax.sweep.job.compute_share` (each process of several).
"""

from wmrjax.sweep.job import sweep
from wmrjax.sweep.report import SweepReport

__all__ = ["SweepReport", "sweep"]
