"""Batch sweeps from a declarative TOML file: ``python -m experiments.sweep SPEC.toml --out DIR``.

* :mod:`experiments.sweep.spec` -- the file format, validated before anything compiles;
* :mod:`experiments.sweep.run` -- blocks of runs on every local device, resumable, several
  processes through ``jax.distributed``, the table streamed into ``runs.parquet``;
* :mod:`experiments.sweep.report` -- ``summary.json``, outcome maps and histograms.
"""
