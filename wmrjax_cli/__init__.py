"""wmrjax_cli: the layer between the library and the command lines (installed with the ``cli``
extra: ``pip install "wmrjax[cli]"``).

* :mod:`wmrjax_cli.options` -- the shared parser (``--out``, the compilation cache,
  ``--verbose``), option types that refuse bad values at parse time, the output directory
  prepared before any work, a heartbeat, and the exit statuses (2: a bad option, 1: an
  error of the work).
* :mod:`wmrjax_cli.files` -- atomic JSON/NPZ/PNG/Parquet writers, JSON checkpoints and one
  writer per output directory.

It imports the library (:mod:`wmrjax`) and never the command lines (``tuning``,
``experiments``); the library never imports it.
"""
