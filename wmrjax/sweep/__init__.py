"""Batch sweeps from a declarative TOML file: ``wmrjax sweep SPEC.toml --out DIR``.

* :mod:`wmrjax.sweep.spec` -- the file format, validated before anything compiles;
* :mod:`wmrjax.sweep.run` -- blocks of runs on every local device, resumable, several
  processes through ``jax.distributed``, the table streamed into ``runs.parquet``;
* :mod:`wmrjax.sweep.report` -- ``summary.json``, outcome maps and histograms.
"""
